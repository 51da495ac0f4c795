"""``voxelwatch demo``: the synthetic house as real processes on loopback.

slow: ``--secure`` end to end: certificates made in the output folder, the
router (the demo process) enforcing the site's access control over mutual
TLS, five camera workers and the fusion server as processes with their own
certificates, and the demo listening as a reader.
"""

from __future__ import annotations

import io
import re
import stat

import pytest

from common.certs import read_common_name
from common.demo import run_demo
from common.site import load_site
from tests.procs import ROOT


@pytest.mark.slow
def test_secure_demo_tracks_the_person_over_tls_and_access_control(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(ROOT))  # the workers and the server run this tree's code
    out = io.StringIO()
    code = run_demo(out_dir=tmp_path / "demo", frames=150, secure=True, stream=out)
    text = out.getvalue()
    assert code == 0, text
    assert re.search(r"zenoh router tls/localhost:\d+ \(TLS, access control", text), text
    site = load_site(tmp_path / "demo" / "site" / "site.toml")
    assert site.zenoh.tls is not None and site.zenoh.tls.access_control
    certs = tmp_path / "demo" / "certs"
    assert read_common_name(certs / "cam3.pem") == "camera-cam3"
    assert all(stat.S_IMODE(k.stat().st_mode) == 0o600 for k in certs.glob("*-key.pem"))
    fused = int(re.search(r"summary: (\d+) fused frames", text).group(1))
    assert fused >= 100, text  # masks crossed the router from every camera to the fusion server
    assert "ENTER" in text  # the reader heard the event through the router
    mota = float(re.search(r"MOTA ([\d.]+) %", text).group(1))
    assert mota >= 90.0, text


@pytest.mark.slow
def test_demo_of_a_mixed_rig_carries_masks_and_range_from_separate_workers(tmp_path, monkeypatch):
    """World 5 (tuning seed) with a depth and a thermal camera: each worker process renders and
    segments its own modality, and the depth camera's range crosses zenoh with its masks."""
    monkeypatch.setenv("PYTHONPATH", str(ROOT))
    out = io.StringIO()
    code = run_demo(world="random", seed=5, sensors="mixed", out_dir=tmp_path / "demo", frames=150, stream=out)
    text = out.getvalue()
    assert code == 0, text
    assert "cam1 depth, cam2 thermal" in text, text
    site = load_site(tmp_path / "demo" / "site" / "site.toml")
    assert (site.camera("cam1").modality, site.camera("cam2").modality) == ("depth", "thermal")
    log = (tmp_path / "demo" / "logs" / "fusion.log").read_text()
    fused, ranged = map(int, re.search(r"(\d+) frames fused \((\d+) with range\)", log).groups())
    assert fused >= 100 and ranged >= 0.8 * fused, log[-2000:]
    mota = float(re.search(r"MOTA ([\d.]+) %", text).group(1))
    assert mota >= 70.0, text
