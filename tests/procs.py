"""Real voxelwatch processes on loopback for the distributed tests.

The test process is the zenoh router (mode ``router``, multicast scouting
off, one ``tcp/127.0.0.1`` endpoint on a free port); camera workers, the
fusion server and two stand-ins for the stock zenoh-python examples connect
to it as clients. :class:`Listener` records what a user of the system hears
(tracks, events, status) from the router's own session; its callbacks only
decode and append.

Run as a script, this module is a client written like the stock examples:

    python tests/procs.py sub -e tcp/127.0.0.1:7447 -k 'voxelwatch/site/events/**'
    python tests/procs.py get -e tcp/127.0.0.1:7447 -s 'voxelwatch/site/history/events/**'

``sub`` prints ``>> [Subscriber] Received <kind> ('<key>': '<payload>')`` per
sample as ``z_sub.py`` does, ``get`` prints ``>> Received ('<key>': '<payload>')``
per reply as ``z_get.py`` does; both take the payload with
``payload.to_string()`` and know nothing of voxelwatch.
"""

from __future__ import annotations

import io
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()

SUB_LINE = re.compile(r"^>> \[Subscriber\] Received (?P<kind>\S+) \('(?P<key>[^']*)': '(?P<payload>.*)'\)$")
GET_LINE = re.compile(r"^>> Received \('(?P<key>[^']*)': '(?P<payload>.*)'\)$")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def loopback_config(*, mode: str, listen: Iterable[str] = (), connect: Iterable[str] = ()):
    """A zenoh config for loopback tests: multicast scouting and shared memory off."""
    from common.transport import zenoh_config

    return zenoh_config(mode=mode, listen=list(listen), connect=list(connect))


def wait_for(predicate: Callable[[], object], timeout_s: float, what: str, *,
             procs: Iterable["Proc"] = (), period_s: float = 0.1) -> object:
    """Poll ``predicate`` until it returns something true; AssertionError after ``timeout_s``
    or as soon as one of ``procs`` has exited (with the end of its log)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        for proc in procs:
            if proc.popen.poll() is not None:
                raise AssertionError(f"waiting for {what}: {proc.name} exited with {proc.popen.returncode}\n"
                                     f"{proc.tail()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(period_s)


# --------------------------------------------------------------------------- processes


class Proc:
    """One child process with its output in a log file."""

    def __init__(self, name: str, argv: list[str], log_path: Path, *, env: dict | None = None) -> None:
        self.name = name
        self.argv = argv
        self.log_path = Path(log_path)
        self._log = self.log_path.open("w")
        self.popen = subprocess.Popen(argv, stdout=self._log, stderr=subprocess.STDOUT, cwd=ROOT,
                                      env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
                                      start_new_session=True)
        self.started = time.monotonic()

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def send(self, sig: int) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)

    def stop(self, timeout_s: float = 20.0, sig: int = signal.SIGTERM) -> int:
        """Signal (SIGTERM by default) and wait; SIGKILL when it does not end in time. The exit code."""
        self.send(sig)
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            return self.popen.wait(timeout=10)
        finally:
            self._log.close()

    def kill(self) -> None:
        """SIGKILL now (no clean-up in the child)."""
        if self.popen.poll() is None:
            self.popen.kill()
        self.popen.wait(timeout=10)
        self._log.close()

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def tail(self, n: int = 30) -> str:
        return "\n".join(self.output().splitlines()[-n:])

    def rss_kb(self, field: str = "VmRSS") -> int:
        """Resident set size in KiB from /proc/<pid>/status: ``VmRSS`` (all), ``RssAnon`` (heap and
        other anonymous memory) or ``RssFile`` (mapped files)."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
        raise RuntimeError(f"no {field} for {self.name} (pid {self.pid})")


def confine(pid: int, cpu: int, nice: int = 0) -> None:
    """Every thread of process ``pid`` runs on processor ``cpu`` only, at ``nice`` (Linux: both are
    properties of each thread, so each of its threads is set; where the kernel groups the processes
    of a session (autogroup), as it does each :class:`Proc`, nice weighs only within the group, so the
    group's own nice is set too)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        tid = int(task.name)
        os.sched_setaffinity(tid, {cpu})
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    autogroup = Path(f"/proc/{pid}/autogroup")
    if nice and autogroup.exists():
        autogroup.write_text(str(nice))


def stop_all(procs: Iterable[Proc], timeout_s: float = 20.0) -> dict[str, int]:
    """SIGTERM every process still running, then wait for each (SIGKILL after ``timeout_s``)."""
    procs = list(procs)
    for proc in procs:
        proc.send(signal.SIGTERM)
    codes = {}
    for proc in procs:
        codes[proc.name] = proc.stop(timeout_s)
    return codes


def start_fusion(site_file: Path, *, endpoint: str, store: Path, out: Path | None, cache_dir: Path, log_dir: Path,
                 name: str = "fusion", extra: Iterable[str] = ()) -> Proc:
    argv = [sys.executable, "-m", "fusion_server.cli", "--site", str(site_file), "--store", str(store),
            "--cache-dir", str(cache_dir), "--mode", "client", "--connect", endpoint, *extra]
    if out is not None:
        argv += ["--out", str(out)]
    return Proc(name, argv, Path(log_dir) / f"{name}.log")


def start_camera(site_file: Path, cam: str, *, endpoint: str, scenario: str, max_frames: int, log_dir: Path,
                 start_ns: int | None = None, start_file: Path | None = None, seed: int = 0,
                 background_frames: int = 45, name: str | None = None, loop: bool = False) -> Proc:
    """A ``voxelwatch-camera`` rendering and segmenting its view of a synthetic scenario, paced on the
    host clock from ``start_ns`` or the stamp in ``start_file`` once it is ready (frames it is late
    for are skipped), after learning the empty room."""
    if (start_ns is None) == (start_file is None):
        raise ValueError("give start_ns or start_file")
    name = name or cam
    start = ["--start-ns", str(start_ns)] if start_ns is not None else ["--start-file", str(start_file)]
    argv = [sys.executable, "-m", "camera_worker.cli", "--site", str(site_file), "--camera", cam,
            "--source", f"synthetic:{scenario}", "--background", f"synthetic:{scenario}",
            "--background-frames", str(background_frames), "--seed", str(seed), *start,
            "--max-frames", str(max_frames), "--mode", "client", "--connect", endpoint, "-q", *(["--loop"] if loop else [])]
    return Proc(name, argv, Path(log_dir) / f"{name}.log")


def start_in_step(session, prefix: str, workers: dict[str, Proc], start_file: Path) -> int:
    """Wait until every worker started with ``start_file`` is ready, then write their shared start
    (as the demo does); returns it."""
    from voxelwatch.demo import start_in_step as start

    return start(session, prefix, {cam: w.popen for cam, w in workers.items()}, start_file, io.StringIO())


def start_fusion_and_cameras(site, site_file: Path, *, router: "Router", listener: "Listener", store: Path,
                             out: Path | None, cache_dir: Path, log_dir: Path, scenario: str, max_frames: int,
                             procs: list[Proc], loop: bool = False) -> tuple[Proc, dict[str, Proc]]:
    """A fusion server on ``router`` (waited for until its token is out), then one worker per camera of
    ``site`` playing ``scenario`` in step from a shared start file beside ``log_dir``; every process is
    added to ``procs`` as it starts (for :func:`stop_all`). Returns ``(fusion, {camera: worker})``."""
    fusion = start_fusion(site_file, endpoint=router.endpoint, store=store, out=out, cache_dir=cache_dir,
                          log_dir=log_dir)
    procs.append(fusion)
    listener.wait_fusion(fusion)
    start_file = Path(log_dir).parent / "start_ns"
    workers = {cam: start_camera(site_file, cam, endpoint=router.endpoint, scenario=scenario, start_file=start_file,
                                 max_frames=max_frames, log_dir=log_dir, loop=loop)
               for cam in site.camera_ids}
    procs.extend(workers.values())
    start_in_step(router.session, site.prefix, workers, start_file)
    return fusion, workers


def start_stock_sub(endpoint: str, key: str, log_dir: Path, name: str = "z_sub") -> Proc:
    """This module's ``sub`` program (written like the stock ``z_sub.py``)."""
    return Proc(name, [sys.executable, str(THIS), "sub", "-e", endpoint, "-k", key], Path(log_dir) / f"{name}.log")


def stock_sub_payloads(proc: Proc) -> list[tuple[str, str]]:
    """``(key, payload text)`` of every sample the ``sub`` program printed."""
    return [(m["key"], m["payload"]) for line in proc.output().splitlines() if (m := SUB_LINE.match(line))]


def stock_get(endpoint: str, selector: str, *, timeout_s: float = 10.0) -> tuple[list[tuple[str, str]], list[str]]:
    """Run this module's ``get`` program (written like the stock ``z_get.py``) once:
    ``([(key, payload text) of each reply], [error texts])``."""
    result = subprocess.run([sys.executable, str(THIS), "get", "-e", endpoint, "-s", selector,
                             "-o", str(timeout_s)], cwd=ROOT, capture_output=True, text=True,
                            timeout=timeout_s + 60)
    assert result.returncode == 0, result.stderr
    ok, errors = [], []
    for line in result.stdout.splitlines():
        if m := GET_LINE.match(line):
            ok.append((m["key"], m["payload"]))
        elif line.startswith(">> Received (ERROR"):
            errors.append(line)
    return ok, errors


def acknowledge(session, prefix: str, event_id: str, by: str, *, timeout_s: float = 10.0):
    """Acknowledge alarm ``event_id`` as the live view does (a query on ``<p>/ack/<id>?by=...``):
    the ``alarm_ack`` Event the fusion server answers with; AssertionError with its error text otherwise."""
    from common import keys, messages

    replies = list(session.get(keys.ack_selector(prefix, event_id, by), timeout=timeout_s))
    assert len(replies) == 1, f"{len(replies)} replies to the acknowledgement of {event_id}"
    reply = replies[0]
    if reply.ok is None:
        raise AssertionError(reply.err.payload.to_string())
    return messages.Event.from_json(reply.ok.payload.to_bytes())


# --------------------------------------------------------------------------- the router and a listener


class Router:
    """The test's own zenoh session, a router on a free loopback port."""

    def __init__(self) -> None:
        import zenoh

        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = zenoh.open(loopback_config(mode="router", listen=[self.endpoint]))

    def close(self) -> None:
        self.session.close()

    def __enter__(self) -> "Router":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class Heard:
    """One message as heard: the decoded message and the host clock at arrival."""

    msg: object
    recv_ns: int


@dataclass
class Listener:
    """What a user subscribed to ``<p>/tracks``, ``<p>/events/**`` and ``<p>/status`` hears."""

    session: object
    prefix: str
    lock: threading.Lock = field(default_factory=threading.Lock)
    tracks: list[Heard] = field(default_factory=list)
    events: list[Heard] = field(default_factory=list)
    status: list[Heard] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    fusion_alive: threading.Event = field(default_factory=threading.Event)
    _entities: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.changed = threading.Condition(self.lock)
        import zenoh

        from common import keys, messages

        def recorder(into: list, decode: Callable[[bytes], object]) -> Callable:
            def callback(sample) -> None:
                now = time.time_ns()
                try:
                    msg = decode(sample.payload.to_bytes())
                except messages.WireError as exc:
                    with self.lock:
                        self.unreadable.append(f"{sample.key_expr}: {exc}")
                    return
                with self.changed:
                    into.append(Heard(msg, now))
                    self.changed.notify_all()
            return callback

        def on_alive(sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                self.fusion_alive.set()
            else:
                self.fusion_alive.clear()

        p = self.prefix
        self._entities = [
            self.session.declare_subscriber(keys.tracks_key(p),
                                            recorder(self.tracks, lambda b: messages.decode(b, messages.TrackFrame))),
            self.session.declare_subscriber(keys.status_key(p),
                                            recorder(self.status, lambda b: messages.decode(b, messages.Status))),
            self.session.declare_subscriber(keys.events_wildcard(p), recorder(self.events, messages.decode_event)),
            self.session.liveliness().declare_subscriber(keys.alive_fusion_key(p), on_alive, history=True),
        ]

    def close(self) -> None:
        for entity in self._entities:
            entity.undeclare()
        self._entities.clear()

    # snapshots (copies taken under the lock)

    def track_frames(self) -> list[Heard]:
        with self.lock:
            return list(self.tracks)

    def event_list(self) -> list[Heard]:
        with self.lock:
            return list(self.events)

    def events_of(self, kind: str) -> list:
        return [h.msg for h in self.event_list() if h.msg.kind == kind]

    def latest_status(self):
        with self.lock:
            return self.status[-1].msg if self.status else None

    def camera_state(self, cam: str) -> str | None:
        st = self.latest_status()
        if st is None:
            return None
        return next((c.state for c in st.cameras if c.cam == cam), None)

    def last_frame(self) -> int:
        with self.lock:
            return self.tracks[-1].msg.frame if self.tracks else -1

    def wait_frame(self, frame: int, proc: Proc, timeout_s: float = 60.0) -> object:
        """Until the newest TrackFrame is numbered ``frame`` or later (frames only grow); returns it."""
        deadline = time.monotonic() + timeout_s
        with self.changed:
            while not (self.tracks and self.tracks[-1].msg.frame >= frame):
                if proc.popen.poll() is not None:
                    raise AssertionError(f"waiting for fused frame {frame}: {proc.name} exited with "
                                         f"{proc.popen.returncode}\n{proc.tail()}")
                if time.monotonic() > deadline:
                    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for fused frame {frame}")
                self.changed.wait(0.2)
            return self.tracks[-1].msg

    def wait_fusion(self, proc: Proc, timeout_s: float = 120.0) -> None:
        """Until the fusion server's liveliness token is seen (it declares it once serving)."""
        wait_for(self.fusion_alive.is_set, timeout_s, f"{proc.name}'s liveliness token", procs=[proc])


# --------------------------------------------------------------------------- the stock-like client programs


def _client_main(argv: list[str]) -> int:
    import argparse

    import zenoh

    parser = argparse.ArgumentParser(prog="procs.py", description="clients written like the stock zenoh examples")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("sub")
    p.add_argument("-e", "--connect", required=True)
    p.add_argument("-k", "--key", required=True)
    g = sub.add_parser("get")
    g.add_argument("-e", "--connect", required=True)
    g.add_argument("-s", "--selector", required=True)
    g.add_argument("-o", "--timeout", type=float, default=10.0)
    args = parser.parse_args(argv)

    conf = loopback_config(mode="client", connect=[args.connect])
    if args.cmd == "sub":
        # as the stock program run from a terminal: Ctrl-C ends it, even when started with SIGINT ignored
        # (a background job of a non-interactive shell)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with zenoh.open(conf) as session:
            print(f"Declaring Subscriber on '{args.key}'...")

            def listener(sample: zenoh.Sample) -> None:
                print(f">> [Subscriber] Received {sample.kind} ('{sample.key_expr}': '{sample.payload.to_string()}')")

            session.declare_subscriber(args.key, listener)
            print("Press CTRL-C to quit...")
            try:
                while True:
                    time.sleep(1)
            except KeyboardInterrupt:
                pass
        return 0
    with zenoh.open(conf) as session:
        print(f"Sending Query '{args.selector}'...")
        for reply in session.get(args.selector, timeout=args.timeout):
            try:
                print(f">> Received ('{reply.ok.key_expr}': '{reply.ok.payload.to_string()}')")
            except Exception:  # noqa: BLE001 - a reply that is not ok carries an error
                print(f">> Received (ERROR: '{reply.err.payload.to_string()}')")
    return 0


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    sys.exit(_client_main(sys.argv[1:]))
