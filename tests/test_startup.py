"""A process stopped at any moment of its start-up says so in one line and exits 0.

The mechanism in-process (a signal whose exception a library swallows still stops the
start-up), then the camera worker and the fusion server as processes whose router cannot be
reached, signalled while their modules load, while they get ready and while they wait for
zenoh.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.shell import Stopped, stop_if_asked, stop_on_signals, stopped_raises

ROOT = Path(__file__).resolve().parents[1]


def test_a_signal_whose_exception_a_library_eats_still_stops_the_start_up():
    with pytest.raises(Stopped) as caught:
        with stopped_raises(who="test", log=None):
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1.0)            # the handler runs here and raises ...
            except BaseException:          # noqa: BLE001 - ... into a bare except, as some imports have
                pass
            with stop_on_signals() as stop:
                assert stop.is_set()       # serving would stop before opening zenoh
            stop_if_asked()
            pytest.fail("the start-up went on after the signal")
    assert caught.value.signame == "SIGTERM"
    with stopped_raises(who="test", log=None):   # the next start-up begins afresh
        stop_if_asked()
        with stop_on_signals() as stop:
            assert not stop.is_set()


def test_a_signal_during_a_compiled_modules_initialisation_stops_the_start_up():
    """A compiled module (scipy's HiGHS, loading) turns the exception raised in its initialisation
    into ``ImportError: initialization failed`` caused by it: the start-up stops as asked, and an
    ImportError nothing asked for stays one."""
    with pytest.raises(Stopped) as caught:
        with stopped_raises(who="test", log=None):
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1.0)
            except Stopped as stop:        # what the module's initialisation does with it
                raise ImportError("initialization failed") from stop
            pytest.fail("the start-up went on after the signal")
    assert caught.value.signame == "SIGTERM"
    assert isinstance(caught.value.__cause__, ImportError)
    with pytest.raises(ImportError):
        with stopped_raises(who="test", log=None):
            raise ImportError("no module named nothing")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def house_site(tmp_path_factory, lut_cache):
    import synth
    from fusion_server.pipeline import build_carver

    site = synth.default_site(tmp_path_factory.mktemp("startup") / "site")
    build_carver(site, site.load_cameras(), cache_dir=lut_cache)
    return site.base_dir / "site.toml", lut_cache


def _first_line_and_stop(argv: list[str], after_s: float, log: Path) -> tuple[float | None, int | str, float, str]:
    """Start ``argv``, SIGTERM it ``after_s`` later: (seconds to its first line, exit status, seconds
    from the signal to the exit, its output)."""
    with open(log, "w") as out:
        t0 = time.monotonic()
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        first = None
        while time.monotonic() - t0 < after_s:
            if first is None and log.stat().st_size:
                first = time.monotonic() - t0
            time.sleep(0.02)
        asked = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            code: int | str = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            code = "hung"
        took = time.monotonic() - asked
    return first, code, took, log.read_text()


@pytest.mark.slow
@pytest.mark.parametrize("after_s", [0.5, 6.0, 12.0])
@pytest.mark.parametrize("who", ["camera", "fusion"])
def test_a_process_whose_router_is_unreachable_says_so_at_once_and_stops_at_any_moment(
        house_site, tmp_path, who, after_s, machine_to_itself):
    """Client mode, nothing at the router's address: the first line within 1 s (what it does and
    whom it waits for), and SIGTERM at 0.5 s (modules loading), 6 s and 12 s (waiting for zenoh,
    a camera having learnt its background): exit 0 within 2 s, one line saying so, no traceback.
    With the machine to itself: the bounds are the issue's, for a process that is not starved."""
    site_file, cache = house_site
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    common = ["--site", str(site_file), "--mode", "client", "--connect", endpoint]
    if who == "camera":
        argv = [sys.executable, "-m", "camera_worker.cli", *common, "--camera", "cam1", "--source", "synthetic",
                "--background", "synthetic", "--background-frames", "15"]
    else:
        argv = [sys.executable, "-m", "fusion_server.cli", *common, "--store", str(tmp_path / "events.sqlite"),
                "--cache-dir", str(cache)]
    first, code, took, out = _first_line_and_stop(argv, after_s, tmp_path / f"{who}.log")
    print(who, after_s, {"first_line_s": first, "exit": code, "exit_after_signal_s": round(took, 2)})
    assert code == 0 and took < 2.0, (code, took, out)
    assert "Traceback" not in out, out
    assert ("received" in out and "stopping" in out) or "stopped before zenoh could be reached" in out, out
    if after_s >= 1.0:
        assert first is not None and first <= 1.0, (first, out)
        assert endpoint in out.splitlines()[0], out
