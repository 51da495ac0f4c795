"""``voxelwatch demo``: the synthetic house as a real distributed system on this machine.

One ``voxelwatch-camera`` process per camera renders and segments its own
view of a scenario, one ``voxelwatch-fusion`` process fuses them, all over
zenoh on loopback with multicast scouting off: this process is the zenoh
router the others connect to as clients, and it subscribes to the events and
tracks like any user would. It prints events as they happen with a progress
line, and ends with a summary, the tracks and events files, a score against
the scenario's ground truth and an annotated plan view (``run/plan.svg``,
drawn by :func:`view.plan.plan_svg`; also ``run/plan.png`` when matplotlib
is installed).

With ``view``, the demo also runs ``voxelwatch view`` as one more process of
the system, with a random token written to ``OUT/view.token``, and prints the
page's address with the token in it.

With ``secure``, the demo makes the site's certificates in its output folder
(``certs/``), writes a ``[zenoh.tls]`` section into the demo's site file, and
every link is TLS with mutual authentication: the router enforces the site's
access control, and the demo listens as a reader (its own client session with
the reader certificate), never from inside the router.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from common.certs import ROUTER
from common.runfiles import EVENTS_FILE, START_FILE, TRACKS_FILE
from common.transport import free_port, site_config

START_MARGIN_S = 1.0
"""The workers' shared first frame is stamped this long after the last of them is ready."""
READY_TIMEOUT_S = 300.0
"""How long the camera workers may take to get ready (open the source, learn the background)."""
BACKGROUND_FRAMES = 45
"""Frames of the empty room each worker learns before the scenario (as replay does)."""


class UnknownCameras(ValueError):
    """A camera asked for that the house does not have."""


def _house_cameras(wanted: list[str] | None):
    """The house's cameras, or only the ``wanted`` ones (in the house's order); None for all."""
    import synth

    if not wanted:
        return None
    cameras = synth.default_cameras()
    unknown = [c for c in wanted if c not in cameras]
    if unknown:
        raise UnknownCameras(f"the house has no camera {', '.join(unknown)} (it has {', '.join(cameras)})")
    return {k: v for k, v in cameras.items() if k in wanted}


SPEEDS = (0.05, 4.0)
"""The demo's ``speed`` range: times real time."""


def site_at_speed(site, speed: float):
    """``site`` with every camera's frame rate times ``speed`` (a recording played that many times
    faster than real time; not validated: write it and load it)."""
    return site.model_copy(update={"cameras": [c.model_copy(update={"fps": c.fps * speed}) for c in site.cameras]})


@dataclass
class _Live:
    """What the demo has heard, updated from zenoh callbacks."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    frame: int = -1
    tracks: list = field(default_factory=list)
    track_frames: int = 0
    first_track_s: float | None = None
    events: list = field(default_factory=list)
    cameras: dict = field(default_factory=dict)


def run_demo(
    *,
    scenario: str | None = None,
    world: str | None = None,
    out_dir: str | Path = "voxelwatch-demo",
    seed: int = 0,
    frames: int | None = None,
    port: int | None = None,
    secure: bool = False,
    sensors: str = "colour",
    view: str | None = None,
    cache_dir: str | Path | None = None,
    cameras: list[str] | None = None,
    speed: float = 1.0,
    stream: TextIO = sys.stdout,
) -> int:
    """Run the scenario (or ``world="random"``: the randomised world of ``seed``, each worker
    rendering its own camera of it; ``sensors="mixed"``: its rig with a depth and a thermal
    camera) end to end; returns the process exit code. ``view``: ``HOST:PORT`` where the live
    view is served as well (None: no view). ``cache_dir``: the fusion server's carving tables
    (None: ``out_dir/cache``). ``cameras``: the house with only these of its cameras (None: all;
    :class:`UnknownCameras` names one it does not have). ``speed``: the recording played at this
    many times real time (every camera's frame rate times ``speed``): below 1 for a machine that
    cannot render and segment every camera in real time beside the server (the people move that
    much slower, so a fall may be too slow to be one)."""
    import zenoh

    import synth
    from common import keys

    out = Path(out_dir).resolve()
    run_dir = out / "run"
    for stale in (TRACKS_FILE, EVENTS_FILE, "events.sqlite"):
        (run_dir / stale).unlink(missing_ok=True)
    run_dir.mkdir(parents=True, exist_ok=True)
    if world is None:
        if sensors != "colour":
            raise ValueError("sensors other than colour are for a random world")
        name = scenario or synth.DEFAULT_SCENARIO
        spec = synth.scenario_spec(name)  # unknown names stop here with the list
        site = synth.default_site(out / "site", cameras=_house_cameras(cameras))
        sc = synth.get_scenario(name, seed, utc_offset_hours=site.utc_offset_hours)
        n_frames = sc.n_frames if frames is None else min(frames, sc.n_frames)
        synth.write_truth(sc, out / "truth", n_frames=n_frames)
        source = f"synthetic:{name}"
        title = f"scenario {name!r} ({spec.description})"
    else:
        if world != "random":
            raise ValueError(f"world must be 'random', got {world!r}")
        if scenario is not None:
            raise ValueError("give a scenario or a world, not both")
        if cameras:
            raise ValueError("cameras are for the house, not a world")
        from common.site import load_site
        from synth.world import random_world, write_world_site

        made = random_world(seed, sensors=sensors)
        sc = made.scenario
        n_frames = sc.n_frames if frames is None else min(frames, sc.n_frames)
        written = write_world_site(made, out / "site", frames=n_frames)
        (out / "truth").mkdir(exist_ok=True)
        for item in written.truth_dir.iterdir():
            item.replace(out / "truth" / item.name)
        written.truth_dir.rmdir()
        site = load_site(written.site)
        source = f"world:{seed}"
        summary = made.summary()
        kinds = summary.get("sensors", {}).get("modalities", {})
        mixed = ", ".join(f"{cam} {kind}" for cam, kind in kinds.items() if kind != "colour")
        title = (f"random world {seed} ({summary['people']} people, {summary['rig_label']} rig"
                 + (f"; {mixed}" if mixed else "") + ")")
    site_path = site.base_dir / "site.toml"
    if not (SPEEDS[0] <= speed <= SPEEDS[1]):
        raise ValueError(f"speed must lie in {SPEEDS[0]:g}..{SPEEDS[1]:g}, got {speed!r}")
    if speed != 1.0:
        from common.site import load_site, write_site

        write_site(site_at_speed(site, speed), site_path)
        site = load_site(site_path)
    if secure:
        site = _secure_site(site, out / "certs", site_path)
        endpoint = f"tls/localhost:{port or free_port()}"
    else:
        endpoint = f"tcp/127.0.0.1:{port or free_port()}"
    conf = site_config(site, host=ROUTER, mode="router", listen=[endpoint], connect=[])

    print(f"voxelwatch demo: {title}, {n_frames / (sc.fps * speed):.0f} s"
          f"{f' (at {speed:g}x real time)' if speed != 1.0 else ''}, "
          f"{len(site.camera_ids)} cameras, zenoh router {endpoint}"
          f"{' (TLS, access control; certificates in ' + str(out / 'certs') + ')' if secure else ''}",
          file=stream, flush=True)
    live = _Live()
    t_launch = time.monotonic()
    procs: dict[str, subprocess.Popen] = {}
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    zenoh_args = ["--mode", "client", "--connect", endpoint]
    with zenoh.open(conf) as router, _ReaderSession(site, endpoint, secure) as reader:
        session = reader or router
        subs = [
            session.declare_subscriber(keys.events_wildcard(site.prefix), lambda s: _on_event(s, live, stream, t_launch, sc)),
            session.declare_subscriber(keys.tracks_key(site.prefix), lambda s: _on_tracks(s, live, t_launch)),
            session.declare_subscriber(keys.status_key(site.prefix), lambda s: _on_status(s, live)),
        ]
        try:
            if view is not None:
                procs["view"] = _start_view(view, site_path, out, zenoh_args, logs, stream)
            procs["fusion"] = _spawn(
                ["voxelwatch-fusion", "--site", str(site_path), "--out", str(run_dir), "--store", str(run_dir / "events.sqlite"),
                 "--cache-dir", str(Path(cache_dir) if cache_dir is not None else out / "cache"),
                 "--exit-after-idle", "4", *zenoh_args],
                logs / "fusion.log",
            )
            _wait_alive(session, keys.alive_fusion_key(site.prefix), procs["fusion"], stream)
            start_file = run_dir / START_FILE
            start_file.unlink(missing_ok=True)
            for cam in site.camera_ids:
                procs[cam] = _spawn(
                    ["voxelwatch-camera", "--site", str(site_path), "--camera", cam, "--source", source,
                     "--background", source, "--background-frames", str(BACKGROUND_FRAMES),
                     "--seed", str(seed), "--start-file", str(start_file), "--max-frames", str(n_frames), "-q",
                     *(["--fps", f"{site.camera(cam).fps:g}"] if speed != 1.0 else []), *zenoh_args],
                    logs / f"{cam}.log",
                )
            start_in_step(router, site.prefix, {cam: procs[cam] for cam in site.camera_ids}, start_file, stream)
            print(f"started {len(site.camera_ids)} camera workers and the fusion server; logs in {logs}", file=stream, flush=True)
            _watch(procs, live, site.camera_ids, n_frames, sc.fps * speed, stream)
        except KeyboardInterrupt:
            print("\ninterrupted: stopping the processes", file=stream)
        finally:
            _stop_all(procs)
            for sub in subs:
                sub.undeclare()
    return _summary(out, run_dir, live, procs, stream)


# ---------------------------------------------------------------- a secured demo


def _secure_site(site, certs_dir: Path, site_path: Path):
    """The demo's site with TLS and access control, written back to ``site_path``; the
    certificates (fresh ones each run) in ``certs_dir``."""
    from common.certs import make_site_certs
    from common.site import TlsSettings, load_site, write_site

    make_site_certs(certs_dir, site=site.name, cameras=site.camera_ids, force=True)
    tls = TlsSettings(ca=str(certs_dir / "ca.pem"), certs=str(certs_dir))
    write_site(site.model_copy(update={"zenoh": site.zenoh.model_copy(update={"tls": tls})}), site_path)
    return load_site(site_path)


class _ReaderSession:
    """With ``secure``, a client session with the reader certificate (``None`` otherwise), closed on exit."""

    def __init__(self, site, endpoint: str, secure: bool) -> None:
        self.conf = site_config(site, host="reader", mode="client", connect=[endpoint]) if secure else None
        self.session = None

    def __enter__(self):
        import zenoh

        if self.conf is not None:
            self.session = zenoh.open(self.conf)
        return self.session

    def __exit__(self, *exc) -> None:
        if self.session is not None:
            self.session.close()


# ---------------------------------------------------------------- callbacks (only record and print)


def _on_event(sample, live: _Live, stream: TextIO, t_launch: float, sc) -> None:
    from common import messages

    try:
        event = messages.decode_event(sample.payload.to_bytes())
    except messages.WireError as exc:
        print(f"  (unreadable event on {sample.key_expr}: {exc})", file=stream)
        return
    with live.lock:
        live.events.append(event)
    t = event.frame / sc.fps if event.frame >= 0 else 0.0
    where = f" at ({event.x:.1f}, {event.y:.1f}) m" if event.track >= 0 else ""
    details = ", ".join(f"{k}={v}" for k, v in event.details.items() if k in ("hotspot", "reason", "camera", "door", "to_posture"))
    track = f"person {event.track}" if event.track >= 0 else ""
    print(f"\r\033[K[{t:6.1f} s] {event.kind.upper():<12} {track}{where}{'  ' + details if details else ''}", file=stream, flush=True)


def _on_tracks(sample, live: _Live, t_launch: float) -> None:
    from common import messages

    try:
        msg = messages.decode(sample.payload.to_bytes(), messages.TrackFrame)
    except messages.WireError:
        return
    with live.lock:
        live.frame = msg.frame
        live.tracks = list(msg.tracks)
        live.track_frames += 1
        if live.first_track_s is None:
            live.first_track_s = time.monotonic()


def _on_status(sample, live: _Live) -> None:
    from common import messages

    try:
        msg = messages.decode(sample.payload.to_bytes(), messages.Status)
    except messages.WireError:
        return
    with live.lock:
        live.cameras = {c.cam: c for c in msg.cameras}


# ---------------------------------------------------------------- processes


def _start_view(listen: str, site_path: Path, out: Path, zenoh_args: list[str], logs: Path,
                stream: TextIO) -> subprocess.Popen:
    """``voxelwatch view`` on ``listen`` with a fresh random token in ``out/view.token`` (owner only)."""
    import secrets
    from urllib.parse import quote

    host, sep, port = listen.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"--view: expected HOST:PORT, e.g. 127.0.0.1:8080, got {listen!r}")
    token = secrets.token_urlsafe(18)
    token_file = out / "view.token"
    token_file.unlink(missing_ok=True)
    fd = os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
    proc = _spawn(["voxelwatch", "view", "--site", str(site_path), "--listen", listen, "--token-file", str(token_file),
                   *zenoh_args], logs / "view.log")
    shown = "localhost" if host in ("0.0.0.0", "::") else host
    print(f"live view: http://{shown}:{port}/?token={quote(token)}  (token in {token_file})", file=stream, flush=True)
    return proc


def _spawn(cmd: list[str], log_path: Path) -> subprocess.Popen:
    exe = Path(sys.executable).parent / cmd[0]
    argv = [str(exe) if exe.exists() else cmd[0], *cmd[1:]]
    log = open(log_path, "w")
    return subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _wait_alive(session, key: str, proc: subprocess.Popen, stream: TextIO, timeout_s: float = 300.0) -> None:
    print("starting the fusion server (the first start computes the carving tables) ...", file=stream, flush=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the fusion server exited with code {proc.returncode} during start-up (see its log)")
        if any(r.ok is not None for r in session.liveliness().get(key, timeout=1.0)):
            return
        time.sleep(0.2)
    raise RuntimeError(f"the fusion server did not come up within {timeout_s:.0f} s")


def start_in_step(session, prefix: str, workers: dict[str, subprocess.Popen], start_file: Path, stream: TextIO,
                  timeout_s: float = READY_TIMEOUT_S) -> int:
    """Wait until every camera worker launched with ``--start-file start_file`` is ready (its
    liveliness token is out), then write their shared start, :data:`START_MARGIN_S` from now, and
    return it. Raises RuntimeError when a worker exits first or they are not all ready in time."""
    from common import keys, sharedstart

    deadline = time.monotonic() + timeout_s
    ready: set[str] = set()
    while True:
        for cam, proc in workers.items():
            if proc.poll() is not None:
                raise RuntimeError(f"camera worker {cam} exited with code {proc.returncode} while getting ready "
                                   "(see its log)")
        for reply in session.liveliness().get(keys.alive_cameras_wildcard(prefix), timeout=1.0):
            if reply.ok is not None:
                try:
                    ready.add(keys.camera_of(str(reply.ok.key_expr), prefix))
                except ValueError:
                    continue
        waiting = sorted(set(workers) - ready)
        print(f"\r\033[Kcameras ready {len(workers) - len(waiting)}/{len(workers)}", end="", file=stream, flush=True)
        if not waiting:
            print(file=stream, flush=True)
            start_ns = time.time_ns() + int(START_MARGIN_S * 1e9)
            sharedstart.write_start(start_file, start_ns)
            return start_ns
        if time.monotonic() > deadline:
            raise RuntimeError(f"camera workers {', '.join(waiting)} were not ready within {timeout_s:.0f} s")
        time.sleep(0.2)


def _watch(procs, live: _Live, cam_ids, n_frames: int, fps: float, stream: TextIO) -> None:
    last_frames, last_t = 0, time.monotonic()
    rate = 0.0
    while True:
        time.sleep(1.0)
        workers_done = all(procs[c].poll() is not None for c in cam_ids)
        if procs["fusion"].poll() is not None:
            return
        with live.lock:
            frame, tracks, count, cams = live.frame, list(live.tracks), live.track_frames, dict(live.cameras)
        now = time.monotonic()
        recent = (count - last_frames) / max(now - last_t, 1e-6)
        rate = 0.7 * rate + 0.3 * recent if last_frames else recent
        last_frames, last_t = count, now
        people = ", ".join(f"{t.id}:{t.posture}" for t in tracks) or "nobody"
        ok = sum(1 for c in cams.values() if c.state == "ok")
        progress = f"frame {max(frame, 0):>5}/{n_frames}  {rate:4.1f} fused/s  cameras {ok}/{len(cam_ids)} ok  people: {people}"
        print(f"\r\033[K{progress}", end="", file=stream, flush=True)
        if workers_done:
            # the recording has ended; the fusion server exits once idle
            try:
                procs["fusion"].wait(timeout=30)
            except subprocess.TimeoutExpired:
                pass
            return


def _stop_all(procs: dict[str, subprocess.Popen]) -> None:
    for proc in procs.values():
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 15
    for proc in procs.values():
        try:
            proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _summary(out: Path, run_dir: Path, live: _Live, procs, stream: TextIO) -> int:
    from evaluation import evaluate

    print("\n", file=stream)
    kinds = Counter(e.kind for e in live.events)
    print(f"summary: {live.track_frames} fused frames, {len(live.events)} events "
          f"({', '.join(f'{k} {n}' for k, n in sorted(kinds.items())) or 'none'})", file=stream)
    failed = {name: p.returncode for name, p in procs.items() if p.returncode not in (0, None, -signal.SIGTERM)}
    if failed:
        print(f"processes that failed: {failed} (logs in {out / 'logs'})", file=stream)
    if not (run_dir / TRACKS_FILE).is_file():
        print("no tracks were written", file=stream)
        return 1
    try:
        result = evaluate(out / "truth", run_dir)
        tr = result["tracking"]
        line = f"against ground truth: MOTA {_pct(tr.get('mota'))}, IDF1 {_pct(tr.get('idf1'))}, MOTP {tr.get('motp_m') or 0:.3f} m"
        ev = result.get("events") or {}
        fall = (ev.get("per_kind") or {}).get("fall")
        if fall and (fall.get("tp", 0) + fall.get("fn", 0)):
            line += f", falls found {fall['tp']}/{fall['tp'] + fall['fn']}"
        print(line, file=stream)
    except Exception as exc:  # noqa: BLE001 - the summary must not hide the files already written
        print(f"(could not score against ground truth: {exc})", file=stream)
    try:
        from evaluation import io
        from view.plan import plan_svg
        from common.site import load_site

        site = load_site(out / "site" / "site.toml")
        truth = io.read_truth_tracks(out / "truth") if (out / "truth").is_dir() else None
        svg = plan_svg(site, io.read_run_tracks(run_dir), io.read_run_events(run_dir, required=False), truth=truth)
        (run_dir / "plan.svg").write_text(svg, encoding="utf-8")
        print(f"plan view: {run_dir / 'plan.svg'}", file=stream)
        try:
            from evaluation import plots

            plots.plan_view(run_dir, site, run_dir / "plan.png", truth_dir=out / "truth")
        except ImportError:
            pass  # the PNG needs matplotlib; the SVG does not
    except Exception as exc:  # noqa: BLE001 - the summary must not hide the files already written
        print(f"(no plan view: {exc})", file=stream)
    print(f"tracks: {run_dir / TRACKS_FILE}\nevents: {run_dir / EVENTS_FILE}", file=stream)
    return 1 if failed else 0


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.1f} %"
