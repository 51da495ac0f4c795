"""``voxelwatch bench --sections soak``: the demo system run for a long time, with processes dying.

The synthetic house as in ``voxelwatch demo`` (one worker per camera, one
fusion server, this process as their zenoh router), played ``speed`` times
faster than real time (every camera's rate and the site's times ``speed``,
the recording looping), for ``minutes``. Every ``kill_every_s`` one camera
worker, in turn, is SIGKILLed and started again two seconds later with the
same shared start; once, half-way, the fusion server is SIGKILLed and started
again on the same event store (it goes on from the snapshot the first kept).
Two hostile hosts come by: a quarter of the way, for 20 s, one sends 15 valid
4096x3072 masks a second on three cameras' keys (each refused on its size
before it is decoded); three quarters of the way, another sends a 300 MB
payload on a mask key and on an events key (zenoh's message-size limit drops
them). At the end it reports:

* frame sets lost: frame numbers between the first and the last fused frame
  that never came as tracks (a restart, a dead camera below ``min_cameras``,
  a slow machine), and the server's own dropped-set count;
* events: published (heard on ``<p>/events/**``) against stored (in the
  SQLite store): every published event must be in the store, whatever died;
* memory (resident set) of the fusion server and of each worker, shortly
  after it starts and when it ends (killed, or at the end of the soak), per
  process lifetime (``cam2#1``: camera cam2's first process);
* the faults: frame sets fused of those in the span while the oversized masks
  came, the fusion server's and this router's memory growth 3 s after the
  huge payloads, and whether the restarted server went on from the snapshot.

It measures; it asserts nothing. Run it on an otherwise idle machine: five
workers rendering the house at four times real time need several cores, and
a machine that cannot keep up shows as lost frame sets.
"""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from common.runfiles import START_FILE
from common.transport import free_port, zenoh_config
from voxelwatch.demo import BACKGROUND_FRAMES, _spawn, _stop_all, _wait_alive, site_at_speed, start_in_step

__all__ = ["run_soak", "send_oversized_masks"]

RESTART_DELAY_S = 2.0
FLOOD_S = 20.0
FLOOD_HZ = 15.0
HUGE_BYTES = 300 * 1024 * 1024
WARM_S = 20.0
"""Memory is first read this long after a process starts (tables loaded, buffers at their size)."""


@dataclass
class _Heard:
    lock: threading.Lock = field(default_factory=threading.Lock)
    frames: set = field(default_factory=set)
    events: dict = field(default_factory=dict)
    status: Any = None


def run_soak(*, minutes: float = 30.0, speed: float = 4.0, kill_every_s: float = 180.0, out_dir: str | Path = "voxelwatch-soak",
             scenario: str | None = None, stream: TextIO = sys.stdout) -> dict[str, Any]:
    """Run the soak; returns (and prints) its figures."""
    import zenoh

    import synth
    from common import keys, messages
    from common.site import write_site

    if not (minutes > 0 and speed > 0 and kill_every_s > RESTART_DELAY_S):
        raise ValueError(f"minutes and speed must be > 0 and kill_every_s > {RESTART_DELAY_S}, "
                         f"got {minutes}, {speed}, {kill_every_s}")
    out = Path(out_dir).resolve()
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    store = out / "events.sqlite"
    for stale in (store, Path(f"{store}-wal"), Path(f"{store}-shm"), Path(f"{store}.pending.jsonl")):
        stale.unlink(missing_ok=True)
    name = scenario or synth.DEFAULT_SCENARIO
    base = synth.default_site(out / "site")
    fast = site_at_speed(base, speed)
    site_path = write_site(fast, out / "site" / "site-soak.toml")
    cams = list(fast.camera_ids)
    fps = fast.cameras[0].fps
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zenoh_args = ["--mode", "client", "--connect", endpoint]
    heard = _Heard()
    procs: dict[str, subprocess.Popen] = {}
    started: dict[str, float] = {}
    rss: dict[str, list[int]] = {}
    restarts: dict[str, int] = {}
    faults: dict[str, Any] = {}

    def fusion() -> subprocess.Popen:
        return _spawn(["voxelwatch-fusion", "--site", str(site_path), "--store", str(store),
                       "--cache-dir", str(out / "cache"), *zenoh_args], logs / f"fusion-{restarts.get('fusion', 0)}.log")

    start_file = out / START_FILE
    start_file.unlink(missing_ok=True)

    def worker(cam: str) -> subprocess.Popen:
        return _spawn(["voxelwatch-camera", "--site", str(site_path), "--camera", cam, "--source", f"synthetic:{name}",
                       "--background", f"synthetic:{name}", "--background-frames", str(BACKGROUND_FRAMES),
                       "--fps", str(fps), "--loop", "--start-file", str(start_file), "-q", *zenoh_args],
                      logs / f"{cam}-{restarts.get(cam, 0)}.log")

    print(f"voxelwatch soak: {name} at {speed:g}x ({fps:g} frames/s), {minutes:g} min, a camera killed every "
          f"{kill_every_s:g} s, the fusion server once; router {endpoint}, logs in {logs}", file=stream, flush=True)
    t0 = time.monotonic()
    with zenoh.open(zenoh_config(mode="router", listen=[endpoint])) as session:
        subs = [
            session.declare_subscriber(keys.events_wildcard(fast.prefix), lambda s: _on_event(s, heard, messages)),
            session.declare_subscriber(keys.tracks_key(fast.prefix), lambda s: _on_tracks(s, heard, messages)),
            session.declare_subscriber(keys.status_key(fast.prefix), lambda s: _on_status(s, heard, messages)),
        ]
        try:
            procs["fusion"], started["fusion"] = fusion(), time.monotonic()
            _wait_alive(session, keys.alive_fusion_key(fast.prefix), procs["fusion"], stream)
            for cam in cams:
                procs[cam], started[cam] = worker(cam), time.monotonic()
            start_in_step(session, fast.prefix, {cam: procs[cam] for cam in cams}, start_file, stream)
            end = time.monotonic() + minutes * 60
            next_kill = time.monotonic() + kill_every_s
            fusion_kill = time.monotonic() + minutes * 30
            flood_at, huge_at = time.monotonic() + minutes * 15, time.monotonic() + minutes * 45
            victim = 0
            while time.monotonic() < end:
                time.sleep(1.0)
                now = time.monotonic()
                for name_, proc in procs.items():  # first memory reading of each process, once warm
                    if name_ not in rss and now - started[name_] >= WARM_S and proc.poll() is None:
                        rss[name_] = [_rss_kb(proc.pid)]
                if now >= flood_at:
                    flood_at = float("inf")
                    print(f"[{now - t0:6.0f} s] oversized masks on three cameras' keys for {FLOOD_S:g} s",
                          file=stream, flush=True)
                    faults.update(_flood(session, fast.prefix, cams[:3], heard))
                if now >= huge_at:
                    huge_at = float("inf")
                    print(f"[{now - t0:6.0f} s] 300 MB payloads on a mask key and an events key", file=stream, flush=True)
                    faults.update(_huge(session, fast.prefix, cams[0], procs["fusion"].pid))
                if now >= fusion_kill:
                    fusion_kill = float("inf")
                    _retire(rss, restarts, "fusion", procs["fusion"])
                    procs["fusion"].kill()
                    procs["fusion"].wait()
                    restarts["fusion"] = restarts.get("fusion", 0) + 1
                    print(f"[{now - t0:6.0f} s] fusion server killed; starting it again", file=stream, flush=True)
                    time.sleep(RESTART_DELAY_S)
                    procs["fusion"], started["fusion"] = fusion(), time.monotonic()
                if now >= next_kill:
                    next_kill = now + kill_every_s
                    cam = cams[victim % len(cams)]
                    victim += 1
                    _retire(rss, restarts, cam, procs[cam])
                    procs[cam].kill()
                    procs[cam].wait()
                    restarts[cam] = restarts.get(cam, 0) + 1
                    print(f"[{now - t0:6.0f} s] camera {cam} killed; starting it again", file=stream, flush=True)
                    time.sleep(RESTART_DELAY_S)
                    procs[cam], started[cam] = worker(cam), time.monotonic()
                with heard.lock:
                    n, events = len(heard.frames), len(heard.events)
                print(f"\r\033[K[{now - t0:6.0f} s] {n} frames fused, {events} events", end="", file=stream, flush=True)
            for name_, proc in procs.items():
                if proc.poll() is None:
                    rss.setdefault(name_, []).append(_rss_kb(proc.pid))
            time.sleep(2.0)  # the last events on their way
        finally:
            _stop_all(procs)
            for sub in subs:
                sub.undeclare()
    stored = _stored_ids(store)
    with heard.lock:
        frames, published, status = sorted(heard.frames), dict(heard.events), heard.status
    span = frames[-1] - frames[0] + 1 if frames else 0
    figures = {
        "minutes": minutes, "speed": speed, "fps": fps, "restarts": restarts,
        "frames_fused": len(frames), "frame_span": span, "frame_sets_lost": span - len(frames),
        "frame_sets_dropped_by_server": status.frame_sets_dropped if status is not None else None,
        "events_published": len(published), "events_stored": len(stored),
        "laps": round(minutes * 60 * speed / synth.scenario_spec(name).duration_s, 2),
        "falls_raised": sum(kind == "fall" for kind in published.values()),
        "published_not_stored": sorted(set(published) - stored),
        "stored_not_heard": len(stored - set(published)),
        "rss_mb": {k: [round(v / 1024, 1) for v in vals] for k, vals in rss.items()},
        "faults": {**faults, "restart_went_on_from_the_snapshot": any(
            "going on from the snapshot" in log.read_text(errors="replace") for log in logs.glob("fusion-[1-9]*.log"))},
    }
    print("\n" + _table(figures), file=stream, flush=True)
    return figures


# ---------------------------------------------------------------- helpers


def send_oversized_masks(session, prefix: str, cams: list[str], *, seconds: float = FLOOD_S, rate_hz: float = FLOOD_HZ,
                         stop: threading.Event | None = None) -> int:
    """What a hostile host with a camera's key can send: ``rate_hz`` valid 4096x3072 masks a second
    (alternating columns: 55 KB on the wire, about 0.3 s each to inflate) on each of ``cams``' keys
    for ``seconds`` (or until ``stop``); returns how many were sent."""
    import numpy as np

    from common import keys, maskcodec, messages
    from common.messages import MaskFrame

    big = np.zeros((3072, 4096), np.uint8)
    big[:, ::2] = 255
    data = maskcodec.encode_mask(big)
    stop = stop if stop is not None else threading.Event()
    t0, seq, sent = time.monotonic(), 10**9, 0
    while not stop.is_set() and time.monotonic() - t0 < seconds:
        for cam in cams:
            msg = MaskFrame(cam=cam, seq=seq, stamp_ns=time.time_ns(), width=4096, height=3072, src_width=4096,
                            src_height=3072, codec="rle-zlib", data=data, fg_fraction=0.5)
            session.put(keys.mask_key(prefix, cam), messages.encode(msg))
            sent += 1
        seq += 1
        stop.wait(1.0 / rate_hz)
    return sent


def _flood(session, prefix: str, victims: list[str], heard: _Heard) -> dict[str, Any]:
    """:func:`send_oversized_masks` on the victims' keys; the frame sets fused meanwhile against those
    in their span."""
    with heard.lock:
        before = set(heard.frames)
    sent = send_oversized_masks(session, prefix, victims)
    with heard.lock:
        during = sorted(set(heard.frames) - before)
    span = during[-1] - during[0] + 1 if during else 0
    return {"oversized_masks_sent": sent, "fused_during_flood": len(during), "span_during_flood": span}


def _huge(session, prefix: str, cam: str, fusion_pid: int) -> dict[str, Any]:
    """Three :data:`HUGE_BYTES` payloads on ``cam``'s mask key and on an events key; the growth of the
    fusion server's and this process's resident memory, MB, 3 s later."""
    import os

    from common import keys

    before = {"fusion": _rss_kb(fusion_pid), "router": _rss_kb(os.getpid())}
    payload = bytes(HUGE_BYTES)
    for key in (keys.mask_key(prefix, cam), keys.event_key(prefix, "fall", 1), keys.mask_key(prefix, cam)):
        session.put(key, payload)
    del payload
    time.sleep(3.0)
    after = {"fusion": _rss_kb(fusion_pid), "router": _rss_kb(os.getpid())}
    return {"huge_payload_rss_growth_mb": {k: round((after[k] - before[k]) / 1024, 1) for k in before}}


def _on_event(sample, heard: _Heard, messages) -> None:
    try:
        event = messages.decode_event(sample.payload.to_bytes())
    except messages.WireError:
        return
    with heard.lock:
        heard.events[event.id] = event.kind


def _on_tracks(sample, heard: _Heard, messages) -> None:
    try:
        msg = messages.decode(sample.payload.to_bytes(), messages.TrackFrame)
    except messages.WireError:
        return
    with heard.lock:
        heard.frames.add(int(msg.frame))


def _on_status(sample, heard: _Heard, messages) -> None:
    try:
        msg = messages.decode(sample.payload.to_bytes(), messages.Status)
    except messages.WireError:
        return
    with heard.lock:
        heard.status = msg


def _retire(rss: dict[str, list[int]], restarts: dict[str, int], name: str, proc: subprocess.Popen) -> None:
    """Close the memory readings of a process about to be killed, under its lifetime's name."""
    if name in rss:
        rss[name].append(_rss_kb(proc.pid))
        rss[f"{name}#{restarts.get(name, 0) + 1}"] = rss.pop(name)


def _rss_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _stored_ids(path: Path) -> set[str]:
    if not path.is_file():
        return set()
    with sqlite3.connect(str(path)) as db:
        return {row[0] for row in db.execute("SELECT id FROM events")}


def _table(f: dict[str, Any]) -> str:
    lines = [
        f"soak: {f['minutes']:g} min at {f['speed']:g}x; restarts {f['restarts'] or 'none'}",
        f"  frame sets: {f['frames_fused']} fused of {f['frame_span']} in the span, {f['frame_sets_lost']} lost; "
        f"dropped by the last server (slow) {f['frame_sets_dropped_by_server']}",
        f"  events: {f['events_published']} published, {f['events_stored']} stored, "
        f"{len(f['published_not_stored'])} published but not stored, {f['stored_not_heard']} stored but not heard; "
        f"{f['falls_raised']} falls in {f['laps']:g} laps of the recording",
        "  memory (MB, after warm-up -> end):",
    ]
    for name, vals in sorted(f["rss_mb"].items()):
        lines.append(f"    {name:<10} {' -> '.join(str(v) for v in vals)}")
    faults = f.get("faults", {})
    if "oversized_masks_sent" in faults:
        lines.append(f"  oversized masks: {faults['oversized_masks_sent']} sent; {faults['fused_during_flood']} frame "
                     f"sets fused of {faults['span_during_flood']} in their span meanwhile")
    if "huge_payload_rss_growth_mb" in faults:
        lines.append(f"  300 MB payloads: memory growth 3 s later (MB) {faults['huge_payload_rss_growth_mb']}")
    lines.append(f"  the restarted fusion server went on from the snapshot: "
                 f"{faults.get('restart_went_on_from_the_snapshot')}")
    return "\n".join(lines)
