"""The fusion server process over real zenoh on loopback.

Each test writes a tiny site (three pinhole cameras around a 3 x 3 x 2 m
room, coarse voxels), starts ``voxelwatch-fusion`` as a real process,
publishes masks of a box-shaped "person" projected through each camera, and
reads what the server publishes: tracks, status, events and history.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from common import keys, messages  # noqa: E402
from common.camera import Camera  # noqa: E402
from evaluation.io import read_events, read_tracks  # noqa: E402
from common.messages import Event, HoldRegions, LookRequest, Status, TrackFrame, decode, decode_event, encode  # noqa: E402
from procs import Proc, loopback_config  # noqa: E402
from tinysite import BOX_XY, CAMERA_CENTRES, FPS, H, PERIOD_NS, W, box_mask, mask_frame, write_site  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> tuple[Path, dict[str, Camera]]:
    return write_site(tmp_path_factory.mktemp("site"))


# --------------------------------------------------------------------------- processes and sessions


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _open_peer(listen: str) -> "zenoh.Session":
    return zenoh.open(loopback_config(mode="peer", listen=[listen]))


class Net:
    """The test's own zenoh session (listening on a free port) and what it has heard."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        self.session = _open_peer(self.endpoint)
        self.lock = threading.Lock()
        self.tracks: list[TrackFrame] = []
        self.status: list[Status] = []
        self.events: list[Event] = []
        self.holds: dict[str, list[HoldRegions]] = {cid: [] for cid in CAMERA_CENTRES}
        self.looks: dict[str, list[LookRequest]] = {cid: [] for cid in CAMERA_CENTRES}
        self.fusion_alive = threading.Event()
        self._entities = [
            *(self.session.declare_subscriber(keys.hold_key(prefix, cid), self._on(self.holds[cid], HoldRegions))
              for cid in CAMERA_CENTRES),
            *(self.session.declare_subscriber(keys.look_key(prefix, cid), self._on(self.looks[cid], LookRequest))
              for cid in CAMERA_CENTRES),
            self.session.declare_subscriber(keys.tracks_key(prefix), self._on(self.tracks, TrackFrame)),
            self.session.declare_subscriber(keys.status_key(prefix), self._on(self.status, Status)),
            self.session.declare_subscriber(keys.events_wildcard(prefix), self._on_event),
            self.session.liveliness().declare_subscriber(keys.alive_fusion_key(prefix), self._on_alive, history=True),
        ]
        self.pubs = {}

    def _on(self, into: list, cls) -> Callable:
        def callback(sample) -> None:
            msg = decode(sample.payload.to_bytes(), cls)
            with self.lock:
                into.append(msg)
        return callback

    def _on_event(self, sample) -> None:
        assert str(sample.encoding).startswith("application/json")
        event = Event.from_json(sample.payload.to_string())  # plain text, as a stock client prints it
        with self.lock:
            self.events.append(event)

    def _on_alive(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.fusion_alive.set()
        else:
            self.fusion_alive.clear()

    def put_mask(self, cam: str, payload: bytes) -> None:
        if cam not in self.pubs:
            self.pubs[cam] = self.session.declare_publisher(keys.mask_key(self.prefix, cam))
        self.pubs[cam].put(payload)

    def publish_box(self, cams: dict[str, Camera], frames: range, *, offsets_ns: dict[str, int] | None = None,
                    between: Callable[[int], None] | None = None, box_until: int | None = None) -> None:
        """Publish ``frames`` at the site rate, stamped with this host's clock (plus per-camera offsets);
        from frame ``box_until`` on, the masks are empty (the person has left)."""
        offsets_ns = offsets_ns or {}
        masks = {cid: box_mask(cam, *BOX_XY) for cid, cam in cams.items()}
        empty = np.zeros((H, W), np.uint8)
        for seq in frames:
            now = time.time_ns()
            for cid, cam in cams.items():
                mask = masks[cid] if box_until is None or seq < box_until else empty
                self.put_mask(cid, encode(mask_frame(cam, seq, now + offsets_ns.get(cid, 0), mask)))
            if between is not None:
                between(seq)
            time.sleep(1.0 / FPS)

    def latest_status(self) -> Status | None:
        with self.lock:
            return self.status[-1] if self.status else None

    def history(self, parameters: str = "", *, key: str | None = None) -> tuple[list[Event], list[str]]:
        """(events, error texts) from one history query on the history key (or ``key``).

        On the history key itself every reply shares one key, so the query asks for no
        consolidation; under ``<p>/history/events/**`` each event has its own key and
        zenoh's default consolidation (what stock clients use) keeps them all.
        """
        selector = (key or keys.history_key(self.prefix)) + (f"?{parameters}" if parameters else "")
        options = {} if key else {"consolidation": zenoh.ConsolidationMode.NONE}
        events, errors = [], []
        for reply in self.session.get(selector, timeout=5.0, **options):
            if reply.ok is not None:
                events.append(decode_event(reply.ok.payload.to_bytes()))
            else:
                errors.append(reply.err.payload.to_string())
        return events, errors

    def close(self) -> None:
        for entity in self._entities + list(self.pubs.values()):
            entity.undeclare()
        self.session.close()


class Server(Proc):
    """A ``voxelwatch-fusion`` process connected to the test's session."""

    def __init__(self, site_file: Path, tmp: Path, net: Net, *extra: str) -> None:
        argv = [sys.executable, "-m", "fusion_server.cli", "--site", str(site_file),
                "--listen", f"tcp/127.0.0.1:{_free_port()}", "--connect", net.endpoint,
                "--cache-dir", str(site_file.parent / "cache"), *extra]
        super().__init__("fusion", argv, tmp / f"server-{time.monotonic_ns()}.log")
        self.net = net

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not self.net.fusion_alive.wait(0.1):
            assert self.alive(), f"server exited with {self.popen.returncode}:\n{self.output()}"
            assert time.monotonic() < deadline, f"server not ready after {timeout_s} s:\n{self.output()}"


@pytest.fixture
def net(site):
    n = Net(keys.default_prefix("tiny"))
    try:
        yield n
    finally:
        n.close()


@pytest.fixture
def start_server(site, tmp_path, net):
    started: list[Server] = []

    def start(*extra: str) -> Server:
        server = Server(site[0], tmp_path, net, *extra)
        started.append(server)
        server.wait_ready()
        return server

    yield start
    for server in started:
        server.kill()


def wait_for(predicate: Callable[[], object], timeout_s: float, what: str) -> object:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _near_box(frame: TrackFrame, tol_m: float = 0.2) -> bool:
    return len(frame.tracks) == 1 and np.hypot(frame.tracks[0].x - BOX_XY[0], frame.tracks[0].y - BOX_XY[1]) < tol_m


# --------------------------------------------------------------------------- tests


def test_tracks_a_box_holds_it_and_writes_files_then_exits_when_idle(site, tmp_path, net, start_server):
    site_file, cams = site
    out = tmp_path / "out"
    server = start_server("--store", str(tmp_path / "events.sqlite"), "--out", str(out), "--exit-after-idle", "2.0")
    net.publish_box(cams, range(70), box_until=45)  # 1.5 s standing still, then gone
    assert server.popen.wait(timeout=20) == 0, server.output()
    with net.lock:
        frames = list(net.tracks)
        holds = {cid: list(msgs) for cid, msgs in net.holds.items()}
        looks = {cid: list(msgs) for cid, msgs in net.looks.items()}
    assert len(frames) >= 50, server.output()
    assert all(f.cameras == ["c1", "c2", "c3"] for f in frames)
    assert [f.frame for f in frames] == sorted({f.frame for f in frames})
    tracked = [f for f in frames if f.tracks]
    assert len(tracked) >= 30 and all(_near_box(f) for f in tracked), [f.tracks for f in tracked]
    assert all(f.frame < 55 for f in tracked) and any(f.frame >= 60 for f in frames), str([(f.frame, len(f.tracks)) for f in frames])
    assert tracked[0].tracks[0].z_top > 1.2 and tracked[-1].tracks[0].posture == "standing"
    # the still person is held in every camera, and released when gone
    for cid, cam in cams.items():
        uv, _ = cam.project(np.array([[BOX_XY[0], BOX_XY[1], 0.85]]))
        u, v = uv[0]
        held = [m for m in holds[cid] if m.boxes]
        assert held, f"no hold regions for {cid}"
        assert all(m.cam == cid and m.ttl_ms == 2000 and len(m.boxes) == 1 for m in held)
        assert all(x0 <= u < x1 and y0 <= v < y1 for m in held for (x0, y0, x1, y1) in m.boxes)
        assert holds[cid][-1].boxes == [] and holds[cid][0].boxes != []
        # and every camera is asked for the person's colours: head, torso and legs boxes around it
        assert looks[cid], f"no look requests for {cid}"
        assert all(m.cam == cid and len(m.people) == 1 for m in looks[cid])
        for m in looks[cid]:
            (person,) = m.people
            x0 = min(b[0] for b in person.boxes if b[2] > b[0])
            x1 = max(b[2] for b in person.boxes if b[2] > b[0])
            assert x0 <= u < x1 and person.depth_m > 0
        stamps = [m.stamp_ns for m in looks[cid]]
        assert stamps == sorted(stamps)
    table = read_tracks(out / "tracks.csv")
    assert len(table) == sum(len(f.tracks) for f in frames)
    assert np.allclose(table.x, BOX_XY[0], atol=0.2) and np.allclose(table.y, BOX_XY[1], atol=0.2)
    assert read_events(out / "events.jsonl") == [] or all(e.kind in messages.EVENT_KINDS for e in read_events(out / "events.jsonl"))
    text = server.output()
    assert "fusion stopped:" in text and "frames fused" in text and "Traceback" not in text


def test_a_flood_of_masks_is_dropped_and_counted_and_tracking_goes_on(site, tmp_path, net, start_server):
    site_file, cams = site
    server = start_server("--store", str(tmp_path / "events.sqlite"))
    n_flood = 300
    masks = {cid: box_mask(cam, *BOX_XY) for cid, cam in cams.items()}
    start_ns = time.time_ns() - n_flood * PERIOD_NS  # ten seconds of frames, all at once
    for seq in range(n_flood):
        for cid, cam in cams.items():
            net.put_mask(cid, encode(mask_frame(cam, seq, start_ns + seq * PERIOD_NS, masks[cid])))
    net.publish_box(cams, range(n_flood, n_flood + 45))

    def settled() -> Status | None:
        st = net.latest_status()
        return st if st and all(c.received >= 45 and c.state == "ok" for c in st.cameras) else None

    status = wait_for(settled, 10.0, "a status with every camera back to normal")
    assert server.popen.poll() is None
    lost = status.frame_sets_dropped + sum(c.dropped for c in status.cameras)
    assert lost > 0 and status.frame_sets < n_flood
    with net.lock:
        paced = [f for f in net.tracks if f.frame >= n_flood + 5]
    assert len(paced) >= 30 and all(_near_box(f) for f in paced)
    assert server.stop() == 0


def test_events_are_stored_published_and_answered_after_a_restart(site, tmp_path, net, start_server):
    site_file, cams = site
    store = tmp_path / "events.sqlite"
    args = ("--store", str(store), "--max-clock-skew-ms", "250")
    server = start_server(*args)
    # a camera that comes, goes and comes back
    token = net.session.liveliness().declare_token(keys.alive_camera_key(net.prefix, "c3"))
    wait_for(lambda: (st := net.latest_status()) and {c.cam: c.state for c in st.cameras}["c3"] == "degraded",
             10.0, "c3 alive (but sending nothing) in the status")
    token.undeclare()
    wait_for(lambda: any(e.kind == "camera_lost" for e in net.events), 10.0, "a camera_lost event")
    wait_for(lambda: {c.cam: c.state for c in net.latest_status().cameras}["c3"] == "lost", 5.0, "c3 lost in the status")
    token = net.session.liveliness().declare_token(keys.alive_camera_key(net.prefix, "c3"))
    wait_for(lambda: any(e.kind == "camera_back" for e in net.events), 10.0, "a camera_back event")
    # a camera whose clock runs a second ahead
    net.publish_box(cams, range(15), offsets_ns={"c1": 1_000_000_000})
    wait_for(lambda: any(e.kind == "clock_skew" for e in net.events), 10.0, "a clock_skew event")
    skewed = wait_for(lambda: (st := net.latest_status()) and {c.cam: c for c in st.cameras}["c1"].state == "skewed"
                      and st, 5.0, "c1 skewed in the status")
    assert {c.cam: c for c in skewed.cameras}["c1"].clock_offset_ms == pytest.approx(1000.0, abs=100.0)

    with net.lock:
        published = list(net.events)
    kinds = [e.kind for e in published]
    assert kinds.count("camera_lost") == 1 and kinds.count("camera_back") == 1 and kinds.count("clock_skew") == 1
    lost = next(e for e in published if e.kind == "camera_lost")
    assert lost.track == -1 and lost.details["camera"] == "c3"
    skew = next(e for e in published if e.kind == "clock_skew")
    assert skew.details["camera"] == "c1" and skew.details["offset_ms"] == pytest.approx(1000.0, abs=100.0)

    history, errors = net.history()
    assert errors == [] and history == sorted(published, key=lambda e: e.stamp_ns)
    as_stock_client, errors = net.history(key=keys.history_key(net.prefix) + "/**")
    assert errors == [] and sorted(as_stock_client, key=lambda e: e.stamp_ns) == history
    only_lost, _ = net.history("kind=camera_lost;format=msgpack")
    assert only_lost == [lost]
    later, _ = net.history(f"since={lost.stamp_ns + 1}")
    assert lost not in later and len(later) == len(published) - 1
    none, errors = net.history("since=yesterday")
    assert none == [] and len(errors) == 1 and "since" in errors[0]
    none, errors = net.history("kind=teleport")
    assert none == [] and "teleport" in errors[0]
    # every query gets an answer, however large its numbers or long its text
    for parameters, words in (("since=99999999999999999999999", "since"), ("until=99999999999999999999999", "until"),
                              ("limit=99999999999999999999999", "limit"), ("kind=" + "x" * 10_000, "kind")):
        none, errors = net.history(parameters)
        assert none == [] and len(errors) == 1 and words in errors[0] and len(errors[0]) < 400, (parameters, errors)
    assert server.stop() == 0
    token.undeclare()

    again = start_server(*args)
    history_after, errors = net.history()
    assert errors == [] and history_after == history
    assert again.stop() == 0


def test_a_bad_site_file_stops_with_exit_code_2_and_one_message(site, tmp_path):
    site_file, _ = site
    bad = tmp_path / "bad.toml"
    bad.write_text(site_file.read_text().replace("[0.4, 0.2, 0.1]", "[0.4, 0.3]"))
    result = subprocess.run([sys.executable, "-m", "fusion_server.cli", "--site", str(bad)], cwd=ROOT,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert str(bad) in lines[0] and "carving.voxel_sizes_m" in lines[0] and "halve" in lines[0]

    calibration_gone = tmp_path / "gone" / "site.toml"
    calibration_gone.parent.mkdir()
    calibration_gone.write_text(site_file.read_text())  # its calibration files are not beside it
    result = subprocess.run([sys.executable, "-m", "fusion_server.cli", "--site", str(calibration_gone),
                             "--store", str(tmp_path / "events.sqlite")], cwd=ROOT, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "c1.toml" in lines[0] and "not found" in lines[0], result.stderr

    result = subprocess.run([sys.executable, "-m", "fusion_server.cli", "--site", str(site_file),
                             "--min-cameras", "4"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--min-cameras" in result.stderr and len(result.stderr.strip().splitlines()) == 1

    missing = tmp_path / "nowhere.toml"
    result = subprocess.run([sys.executable, "-m", "fusion_server.cli", "--site", str(missing)], cwd=ROOT,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "not found" in result.stderr and len(result.stderr.strip().splitlines()) == 1


# --------------------------------------------------------------------------- the server's timeline


def test_future_masks_and_a_camera_a_minute_fast_never_stop_the_live_server(site, tmp_path, net, start_server):
    """Over zenoh, to the real process: c3 starts first with a clock 60 s fast, then every camera sends one
    valid mask stamped an hour ahead; the server tracks on with c1 and c2, says c3 is skewed, and takes c3 back
    once its clock is right."""
    site_file, cams = site
    server = start_server("--store", str(tmp_path / "events.sqlite"))
    minute, hour = 60 * 10**9, 3600 * 10**9
    net.publish_box({"c3": cams["c3"]}, range(5), offsets_ns={"c3": minute})  # started first
    net.publish_box(cams, range(5, 40), offsets_ns={"c3": minute})

    def forged(seq: int) -> None:
        if seq == 45:
            for cid, cam in cams.items():
                net.put_mask(cid, encode(mask_frame(cam, 10_000, time.time_ns() + hour, box_mask(cam, *BOX_XY))))

    net.publish_box(cams, range(40, 70), offsets_ns={"c3": minute}, between=forged)
    status = wait_for(lambda: (st := net.latest_status()) and st.frame_sets >= 55
                      and sum(c.refused for c in st.cameras if c.cam != "c3") == 2 and st, 10.0, "frame sets fused")
    by_cam = {c.cam: c for c in status.cameras}
    c3 = by_cam["c3"]
    assert c3.state == "skewed" and c3.refused == c3.received >= 50 and c3.late == c3.refused, c3
    assert by_cam["c3"].clock_offset_ms == pytest.approx(60_000, abs=500)
    assert by_cam["c1"].state == by_cam["c2"].state == "ok", by_cam
    assert by_cam["c1"].refused == by_cam["c2"].refused == 1 and by_cam["c1"].late == 1
    with net.lock:
        frames = list(net.tracks)
    assert len(frames) >= 55 and all(f.cameras == ["c1", "c2"] for f in frames)
    assert all(abs(f.stamp_ns - time.time_ns()) < 30 * 10**9 for f in frames)  # never an hour ahead
    assert sum(1 for f in frames[-20:] if f.tracks and _near_box(f, 0.3)) >= 15
    net.publish_box(cams, range(70, 110))  # c3's clock is set right
    wait_for(lambda: {c.cam: c.state for c in net.latest_status().cameras} == {"c1": "ok", "c2": "ok", "c3": "ok"},
             10.0, "every camera ok")
    with net.lock:
        assert net.tracks[-1].cameras == ["c1", "c2", "c3"] and _near_box(net.tracks[-1])
        skews = sorted(e.details["camera"] for e in net.events if e.kind == "clock_skew")
    assert skews == ["c1", "c2", "c3"]
    assert server.stop() == 0 and "Traceback" not in server.output()


def _write_box_videos(folder: Path, cam: Camera, n: int) -> tuple[Path, Path]:
    """(background clip, clip of the box standing still) as ``cam`` sees the room, MJPG at the site rate."""
    import cv2

    rng = np.random.default_rng(5)
    room = np.clip(120 + 50 * cv2.resize(rng.normal(0, 1, (H // 8, W // 8, 3)).astype(np.float32), (W, H)),
                   0, 255).astype(np.uint8)
    person = room.copy()
    person[box_mask(cam, *BOX_XY) > 0] = (40, 40, 200)
    paths = folder / f"{cam.id}-bg.avi", folder / f"{cam.id}-clip.avi"
    for path, image, frames in ((paths[0], room, 30), (paths[1], person, n)):
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
        for _ in range(frames):
            writer.write(image)
        writer.release()
    return paths


@pytest.mark.slow
def test_a_recorded_file_worker_restarted_mid_run_joins_the_shared_clock(site, tmp_path, net, start_server):
    """A real worker plays c3's recording with the shared start while the test plays c1 and c2 on the same
    lattice; SIGKILLed and started again with the same start, it publishes the frames for now (never frame 0
    again): no replayed masks, no clock_skew, c3 ok, and sets with all three cameras again."""
    site_file, cams = site
    server = start_server("--store", str(tmp_path / "events.sqlite"))
    bg, clip = _write_box_videos(tmp_path, cams["c3"], n=int(20 * FPS))
    start_ns = time.time_ns() + 2_500_000_000
    server_listen = server.argv[server.argv.index("--listen") + 1]

    def worker() -> Proc:
        return Proc("camera-c3", [sys.executable, "-m", "camera_worker.cli", "--site", str(site_file), "--camera", "c3",
                                  "--source", str(clip), "--background", str(bg), "--start-ns", str(start_ns),
                                  "--connect", net.endpoint, "--connect", server_listen,
                                  "--listen", f"tcp/127.0.0.1:{_free_port()}"], tmp_path / f"c3-{time.monotonic_ns()}.log")

    first = worker()
    masks = {cid: box_mask(cam, *BOX_XY) for cid, cam in cams.items()}
    restarted: list[Proc] = []
    seq = 0
    try:
        while time.time_ns() < start_ns + int(9e9):
            stamp = start_ns + int(round(seq * 1e9 / FPS))
            if stamp > time.time_ns():
                time.sleep((stamp - time.time_ns()) / 1e9)
            if stamp >= start_ns:
                for cid in ("c1", "c2"):
                    net.put_mask(cid, encode(mask_frame(cams[cid], seq, stamp, masks[cid])))
            if seq == int(3.5 * FPS):  # mid-run: the worker dies and is started again at once
                first.kill()
                restarted.append(worker())
            seq += 1
        status = net.latest_status()
        with net.lock:
            frames = list(net.tracks)
            kinds = [e.kind for e in net.events]
    finally:
        first.kill()
        for proc in restarted:
            proc.stop()
    again = restarted[0].output()
    assert "joining it at frame" in again, again
    c3 = {c.cam: c for c in status.cameras}["c3"]
    # late masks measure the worker's load, not its clock: on a machine shared with a parallel suite its
    # frames take about a period each (9 of 184 late seen there), so the bound is a share, not a count
    assert c3.state == "ok" and c3.refused == 0 and c3.late <= 0.1 * c3.received, (c3, again)
    assert "clock_skew" not in kinds
    with_c3 = [f for f in frames if "c3" in f.cameras]
    assert with_c3 and with_c3[-1].frame > int(6 * FPS), [(f.frame, f.cameras) for f in frames[-5:]]
    assert sum(1 for f in frames[-30:] if f.cameras == ["c1", "c2", "c3"]) >= 25
    assert _near_box(frames[-1], 0.3)


# --------------------------------------------------------------------------- clean failure


@pytest.mark.parametrize("endpoint, sig", [pytest.param("free port", "SIGTERM", marks=pytest.mark.slow),
                                           ("tcp/router.invalid:7447", "SIGINT")])
def test_a_server_whose_router_is_unreachable_says_so_once_and_stops_on_a_signal(site, tmp_path, endpoint, sig):
    """Client mode, nothing listening at the router's address (or a name that does not resolve): one
    warning line, retries with back-off, and a clean exit within 2 s of SIGTERM or SIGINT."""
    import signal

    site_file, _ = site
    if endpoint == "free port":
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
    argv = [sys.executable, "-m", "fusion_server.cli", "--site", str(site_file), "--mode", "client",
            "--connect", endpoint, "--store", str(tmp_path / "events.sqlite"),
            "--cache-dir", str(site_file.parent / "cache")]
    server = Proc("fusion", argv, tmp_path / "server.log")
    wait_for(lambda: "cannot reach zenoh" in server.output(), 30.0, "the unreachable router in the log")
    time.sleep(2.0)  # a few retries
    assert server.alive()
    asked = time.monotonic()
    code = server.stop(timeout_s=10.0, sig=getattr(signal, sig))
    took = time.monotonic() - asked
    out = server.output()
    assert code == 0 and took < 2.0, (code, took, out)
    assert out.count("cannot reach zenoh") == 1 and endpoint in out and "Traceback" not in out, out
    assert "stopped before zenoh could be reached" in out


HUGE_BYTES = 300 * 1024 * 1024
MEMORY_GROWTH_MAX_KB = 50 * 1024


@pytest.mark.slow
def test_huge_payloads_cost_the_router_and_the_server_no_lasting_memory(site, tmp_path, net, start_server):
    """300 MB puts, from a client of the site's router and from a peer connected to the server itself, on a
    mask key and on an events key: zenoh's message size limit (common.transport) refuses them while they
    arrive, so neither the router nor the server holds them, and the server goes on tracking."""
    router_endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = Proc("router", [sys.executable, "-m", "voxelwatch", "router", "--listen", router_endpoint],
                  tmp_path / "router.log")
    hostile = []
    try:
        wait_for(lambda: "voxelwatch router listening" in router.output(), 30.0, "the router")
        server = start_server("--connect", router_endpoint)
        server_endpoint = server.argv[server.argv.index("--listen") + 1]
        net.publish_box(site[1], range(20))
        time.sleep(1.0)
        before = {"router": router.rss_kb(), "fusion": server.rss_kb()}
        for endpoint, mode in ((router_endpoint, "client"), (server_endpoint, "peer")):
            conf = zenoh.Config()   # a host that does not keep to the site's settings: zenoh's defaults
            for key, value in (("mode", mode), ("connect/endpoints", [endpoint]), ("scouting/multicast/enabled", False)):
                conf.insert_json5(key, json.dumps(value))
            session = zenoh.open(conf)
            hostile.append(session)
            for key in (keys.mask_key(net.prefix, "c1"), keys.event_key(net.prefix, "fall", 1)):
                session.put(key, bytes(HUGE_BYTES))
        time.sleep(3.0)
        after = {"router": router.rss_kb(), "fusion": server.rss_kb()}
        growth = {name: after[name] - before[name] for name in before}
        print("rss growth kB", growth)
        assert all(kb < MEMORY_GROWTH_MAX_KB for kb in growth.values()), (before, after)
        tracked = len(net.tracks)
        net.publish_box(site[1], range(20, 40))
        wait_for(lambda: len(net.tracks) >= tracked + 10, 10.0, "tracks after the huge payloads")
        assert server.alive() and router.alive()
        assert all(e.kind != "fall" or e.track != 1 for e in net.events)   # nothing came through as an event
    finally:
        for session in hostile:
            session.close()
        router.stop()


@pytest.mark.parametrize("sig", ["SIGTERM", pytest.param("SIGINT", marks=pytest.mark.slow)])
def test_a_signal_while_the_tables_are_built_stops_the_server_with_one_line_and_status_0(tmp_path, sig):
    """The house's five cameras and an empty table cache: the server says first what it does and whom
    it will connect to, then builds the tables (seconds); a signal then stops it within 2 s, exit status
    0, one line saying so."""
    import signal

    import synth

    site_file = synth.default_site(tmp_path / "site").base_dir / "site.toml"
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    argv = [sys.executable, "-m", "fusion_server.cli", "--site", str(site_file), "--mode", "client",
            "--connect", endpoint, "--store", str(tmp_path / "events.sqlite"), "--cache-dir", str(tmp_path / "empty")]
    server = Proc("fusion", argv, tmp_path / "server.log")
    wait_for(lambda: "loading the carving tables" in server.output(), 30.0, "the server's first line")
    assert endpoint in server.output() and "5 cameras" in server.output()
    asked = time.monotonic()
    code = server.stop(timeout_s=10.0, sig=getattr(signal, sig))
    took = time.monotonic() - asked
    out = server.output()
    assert code == 0 and took < 2.0, (code, took, out)
    assert f"{sig} received while starting, stopping" in out and "Traceback" not in out, out
    assert "cannot reach zenoh" not in out   # stopped before it got that far


def test_a_malformed_endpoint_stops_start_up_with_one_line(site, tmp_path):
    site_file, _ = site
    for endpoint in ("tpc/127.0.0.1:7447", "tcp/127.0.0.1"):
        result = subprocess.run([sys.executable, "-m", "fusion_server.cli", "--site", str(site_file), "--mode", "client",
                                 "--connect", endpoint, "--store", str(tmp_path / "events.sqlite")], cwd=ROOT,
                                capture_output=True, text=True, timeout=60)
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert result.returncode == 2 and len(lines) == 1 and endpoint in lines[0], result.stderr
