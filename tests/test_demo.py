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
