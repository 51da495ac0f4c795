"""The whole pipeline as real processes on loopback, and its behaviour under faults.

Every test runs ``voxelwatch-fusion`` (and, where said, ``voxelwatch-camera``
workers) as separate processes connected as zenoh clients to the test
process, which is the router (multicast scouting off, one
``tcp/127.0.0.1`` endpoint on a free port). The synthetic house supplies the
scene and its ground truth.

* slow, with the machine to itself: five workers play 'fall_forward' on the
  host clock; the fall is raised near the truth fall frame and no other fall
  is; a stock-style ``z_sub`` prints every event as readable JSON and a
  stock-style ``z_get`` on the history key returns them; one worker is
  SIGKILLed mid-run (reported lost, tracking goes on with four cameras) and
  restarted (back in the frame sets). (The default run holds a fall over live
  processes in ``test_view.py``: the demo's fall on the view's banner.)
* slow: a fusion restart on the same store keeps the whole history and
  tracking resumes; thousands of malformed messages during a run leave the
  tracks and events byte-identical and are counted; a flood drops frame sets
  with bounded memory; a camera clock one second ahead is reported and left
  out while the others track.
* slow, with the machine to itself: the server SIGKILLed 3 s after a fall and
  started again 5 s later finds the person on the floor under their label and
  raises the long lie at its time, once; two CPU burners on the host make it
  read ``overloaded`` and no camera ``skewed``; oversized valid masks on three
  cameras' keys for 20 s neither stall fusion nor hide the fall.

The malformed-message and flood tests feed the true silhouettes from the
test in lockstep (each frame's masks, then wait for its TrackFrame), so that
two runs see the same frame sets in the same order and their outputs can be
compared byte for byte.

No timing is asserted: waits have generous timeouts and only the scenario's
own frame numbers are compared with the truth.
"""

from __future__ import annotations

import csv
import json
import math
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from procs import (  # noqa: E402
    Listener,
    confine,
    acknowledge,
    Proc,
    Router,
    start_camera,
    start_fusion,
    start_fusion_and_cameras,
    start_in_step,
    start_stock_sub,
    stock_get,
    stock_sub_payloads,
    stop_all,
    wait_for,
)

import synth  # noqa: E402
from common import keys, maskcodec, messages  # noqa: E402
from evaluation import evaluate  # noqa: E402
from common.messages import MaskFrame  # noqa: E402

NEAR_M = 0.5
"""A track is 'near the truth' within this floor distance (the evaluation's CLEAR-MOT radius)."""
FALL_LATE_FRAMES = 45
"""The fall must be raised at most this many frames (3 s at 15 fps) after the truth fall frame ..."""
FALL_EARLY_FRAMES = 30
"""... and no earlier than this many frames before it (the evaluation's event window)."""


# --------------------------------------------------------------------------- the house, its truth, comparisons


def write_truth(name: str, n_frames: int, folder: Path) -> dict[int, list[tuple[float, float]]]:
    """Write the scenario's truth into ``folder``; return frame -> true floor positions."""
    synth.write_truth(synth.get_scenario(name, 0), folder, n_frames=n_frames)
    truth: dict[int, list[tuple[float, float]]] = {}
    with open(folder / "tracks.csv", newline="") as f:
        for row in csv.DictReader(f):
            truth.setdefault(int(row["frame"]), []).append((float(row["x"]), float(row["y"])))
    return truth


def truth_events(folder: Path, kind: str) -> list[dict]:
    lines = (folder / "events.jsonl").read_text().splitlines()
    return [e for e in map(json.loads, lines) if e["kind"] == kind]


def near_truth(frame: messages.TrackFrame, truth: dict[int, list[tuple[float, float]]]) -> bool:
    """Exactly one track, within NEAR_M of the one true person at that frame."""
    people = truth.get(frame.frame, [])
    if len(frame.tracks) != 1 or len(people) != 1:
        return False
    t = frame.tracks[0]
    return math.hypot(t.x - people[0][0], t.y - people[0][1]) < NEAR_M


def fused_after(listener: Listener, frame: int) -> list[messages.TrackFrame]:
    return [h.msg for h in listener.track_frames() if h.msg.frame > frame]


# --------------------------------------------------------------------------- 1 + 2: five workers, a fall, a kill


SCENARIO = "fall_forward"
N_FRAMES = 330          # 22 s of the 40 s scenario; the truth fall is at frame 101, its long lie at 551; alone on a
                        # quiet machine the killed camera was back at frame 192 and 30 frames later at 222
KILL_AFTER_FRAME = 135  # the fall has had time to be confirmed
VICTIM = "cam3"


@pytest.mark.slow
def test_fall_is_raised_over_processes_and_a_killed_camera_is_left_out_then_rejoins(house, tmp_path, machine_to_itself):
    site, site_file, cache = house
    prefix = site.prefix
    truth_dir, run_dir, logs = tmp_path / "truth", tmp_path / "run", tmp_path / "logs"
    logs.mkdir()
    truth = write_truth(SCENARIO, N_FRAMES, truth_dir)
    (fall_truth,) = truth_events(truth_dir, "fall")
    procs: list[Proc] = []
    measured: dict[str, object] = {}
    with Router() as router:
        listener = Listener(router.session, prefix)
        try:
            z_sub = start_stock_sub(router.endpoint, keys.events_wildcard(prefix), logs)
            procs.append(z_sub)
            fusion = start_fusion(site_file, endpoint=router.endpoint, store=run_dir / "events.sqlite", out=run_dir,
                                  cache_dir=cache, log_dir=logs)
            procs.append(fusion)
            listener.wait_fusion(fusion)
            start_file = tmp_path / "start_ns"   # written once all five are ready, as the demo does
            workers = {cam: start_camera(site_file, cam, endpoint=router.endpoint, scenario=SCENARIO,
                                         start_file=start_file, max_frames=N_FRAMES, log_dir=logs)
                       for cam in site.camera_ids}
            procs.extend(workers.values())
            start_ns = start_in_step(router.session, prefix, workers, start_file)
            everyone = [fusion, *(w for c, w in workers.items() if c != VICTIM)]

            # -- the fall, with all five cameras
            wait_for(lambda: listener.last_frame() >= KILL_AFTER_FRAME, 120,
                     f"fused frame {KILL_AFTER_FRAME}", procs=everyone + [workers[VICTIM]])
            before = [h.msg for h in listener.track_frames()][-30:]
            # (a mask that comes too late for its set leaves a camera out of that one set)
            assert sum(VICTIM in f.cameras for f in before) >= 0.5 * len(before), [f.cameras for f in before]
            measured["sets_with_all_five"] = f"{sum(f.cameras == list(site.camera_ids) for f in before)}/{len(before)}"

            # -- SIGKILL one worker: reported lost, the others go on
            kill_ns = time.time_ns()
            workers[VICTIM].kill()
            wait_for(lambda: any(e.details.get("camera") == VICTIM for e in listener.events_of("camera_lost")),
                     30, f"a camera_lost event for {VICTIM}", procs=everyone)
            lost_heard = next(h for h in listener.event_list()
                              if h.msg.kind == "camera_lost" and h.msg.details.get("camera") == VICTIM)
            measured["camera_lost_after_kill_s"] = (lost_heard.recv_ns - kill_ns) / 1e9
            wait_for(lambda: listener.camera_state(VICTIM) == "lost", 30, f"{VICTIM} 'lost' in the status",
                     procs=everyone)
            lost_mark = listener.last_frame()
            # frame sets of before the kill may still be on their way through a busy server and carry the
            # victim's last masks; a set stamped a frame after the kill cannot
            after_kill = lambda: [f for f in fused_after(listener, lost_mark)  # noqa: E731
                                  if f.stamp_ns > kill_ns + PERIOD_NS]
            wait_for(lambda: len(after_kill()) >= 30, 60, "30 fused frames after the loss", procs=everyone)
            without = after_kill()
            assert all(VICTIM not in f.cameras for f in without), [f.cameras for f in without]
            others = sorted(set(site.camera_ids) - {VICTIM})
            measured["sets_with_all_four"] = f"{sum(f.cameras == others for f in without)}/{len(without)}"
            measured["near_truth_without_victim"] = f"{sum(near_truth(f, truth) for f in without)}/{len(without)}"
            assert sum(near_truth(f, truth) for f in without) >= 0.9 * len(without), \
                [(f.frame, f.tracks) for f in without]

            # -- restart it with the same start file: back in the frame sets
            restart_ns = time.time_ns()
            again = start_camera(site_file, VICTIM, endpoint=router.endpoint, scenario=SCENARIO, start_file=start_file,
                                 max_frames=N_FRAMES, log_dir=logs, name=f"{VICTIM}-again")
            procs.append(again)
            wait_for(lambda: any(e.details.get("camera") == VICTIM for e in listener.events_of("camera_back")),
                     90, f"a camera_back event for {VICTIM}", procs=everyone + [again])
            back_mark = listener.last_frame()
            rejoined = wait_for(lambda: [f for f in fused_after(listener, back_mark) if VICTIM in f.cameras],
                                60, f"a fused frame with {VICTIM} again", procs=everyone + [again])
            measured["rejoined_after_restart_s"] = (time.time_ns() - restart_ns) / 1e9
            measured["rejoined_at_frame"] = rejoined[0].frame
            wait_for(lambda: len(fused_after(listener, rejoined[0].frame)) >= 30, 60,
                     "30 fused frames after the rejoin", procs=everyone + [again])
            back = fused_after(listener, rejoined[0].frame)
            assert sum(VICTIM in f.cameras for f in back) >= 0.5 * len(back), [f.cameras for f in back]
            measured["near_truth_after_rejoin"] = f"{sum(near_truth(f, truth) for f in back)}/{len(back)}"

            # -- the recording ends; then ask the history like z_get.py does
            for cam, worker in workers.items():
                if cam != VICTIM:
                    assert worker.popen.wait(timeout=N_FRAMES / 15 + 120) == 0, worker.tail()
            assert again.stop() == 0, again.tail()
            assert fusion.alive(), fusion.tail()
            # workers that end on purpose say so: camera_stopped, never camera_lost
            wait_for(lambda: len(listener.events_of("camera_stopped")) >= len(site.camera_ids), 30,
                     "camera_stopped events as the workers end", procs=[fusion])
            wait_for(lambda: all(listener.camera_state(c) == "stopped" for c in site.camera_ids), 30,
                     "every camera 'stopped' in the status", procs=[fusion])
            assert [e.details["camera"] for e in listener.events_of("camera_lost")] == [VICTIM]  # the kill only

            # -- acknowledge the fall as the live view does: a query that the fusion server answers
            (fall_id,) = [e.id for e in listener.events_of("fall")]
            ack = acknowledge(router.session, prefix, fall_id, "night nurse")
            assert (ack.kind, ack.details, ack.id) == ("alarm_ack", {"event": fall_id, "alarm": "fall", "by": "night nurse"},
                                                       f"{fall_id}-ack")
            assert acknowledge(router.session, prefix, fall_id, "someone else") == ack  # the first one stands
            with pytest.raises(AssertionError, match="no stored event"):
                acknowledge(router.session, prefix, "0-fall-99", "night nurse")
            wait_for(lambda: listener.events_of("alarm_ack"), 10, "the acknowledgement published", procs=[fusion])
            time.sleep(1.0)
            heard = listener.event_list()
            got, errors = stock_get(router.endpoint, keys.history_key(prefix) + "/**")
            assert errors == []
            assert z_sub.stop(sig=signal.SIGINT) == 0, z_sub.tail()
            printed = stock_sub_payloads(z_sub)
            assert fusion.stop() == 0, fusion.tail()
        finally:
            stop_all(procs)
            listener.close()

    # events: the stock-style subscriber printed readable JSON, the same events the listener decoded
    published = {h.msg.id: h.msg for h in heard}
    assert listener.unreadable == []
    assert all(isinstance(json.loads(text), dict) for _, text in printed)  # plain JSON objects
    printed_events = [messages.Event.from_json(text) for _, text in printed]
    assert sorted(e.id for e in printed_events) == sorted(published)
    assert all(key == keys.event_key(prefix, e.kind, e.track) for (key, _), e in zip(printed, printed_events))
    assert all(isinstance(json.loads(text), dict) for _, text in got)
    history = [messages.Event.from_json(text) for _, text in got]
    assert sorted(e.id for e in history) == sorted(published)
    assert all(e == published[e.id] for e in history)

    assert [e.kind for e in history].count("alarm_ack") == 1  # stored once, with the events

    # the fall: once, near the truth frame; nothing else called a fall
    falls = [e for e in published.values() if e.kind == "fall"]
    assert len(falls) == 1, [(e.kind, e.frame) for e in published.values()]
    delay_frames = falls[0].frame - fall_truth["frame"]
    assert -FALL_EARLY_FRAMES <= delay_frames <= FALL_LATE_FRAMES, (falls[0], fall_truth)
    fall_heard = next(h for h in heard if h.msg.kind == "fall")
    measured["fall_delay_frames"] = delay_frames
    measured["fall_event_latency_ms"] = (fall_heard.recv_ns - start_ns - falls[0].frame * 1e9 / 15) / 1e6
    assert not any(e.kind == "long_lie" for e in published.values())  # the truth's long lie is at 36.7 s

    scores = evaluate(truth_dir, run_dir)
    fall_scores = scores["events"]["per_kind"]["fall"]
    assert (fall_scores["tp"], fall_scores["fp"], fall_scores["fn"]) == (1, 0, 0)
    tracking = scores["tracking"]
    measured.update(mota=round(tracking["mota"], 3), idf1=round(tracking["idf1"], 3),
                    motp_m=round(tracking["motp_m"], 3),
                    events={k: v.get("run", 0) for k, v in scores["events"]["per_kind"].items()})
    print("measured:", measured)


# --------------------------------------------------------------------------- masks fed by the test


FED_SCENARIO = "fall_forward"
FED_FRAMES = 150        # 10 s: the truth fall is at frame 101
FED_TIMELINE = ("--free-timeline",)  # fed masks carry the scenario's own (2024) stamps, faster than real time


@pytest.fixture(scope="module")
def fed(house):
    """The true silhouettes of FED_FRAMES frames of FED_SCENARIO in every camera, encoded once:
    ``(cam ids, stamps_ns, {cam: [(data, fg_fraction), ...]})``."""
    site = house[0]
    sc = synth.get_scenario(FED_SCENARIO, 0)
    masks = {}
    for cam in site.camera_ids:
        view = synth.SyntheticCamera(sc, cam, 0, site=site, noise_std=0.0, shadows=False)
        frames = []
        for i in range(FED_FRAMES):
            _, mask = view.frame(i)
            frames.append((maskcodec.encode_mask(mask), float(np.count_nonzero(mask)) / mask.size))
        masks[cam] = frames
    return tuple(site.camera_ids), [sc.stamp_ns(i) for i in range(FED_FRAMES)], masks


def mask_message(cam: str, seq: int, stamp_ns: int, data: bytes, fg_fraction: float, *, width: int = 640,
                 height: int = 480) -> bytes:
    return messages.encode(MaskFrame(cam=cam, seq=seq, stamp_ns=stamp_ns, width=width, height=height, src_width=640,
                                     src_height=480, codec="rle-zlib", data=data, fg_fraction=fg_fraction))


class Feeder:
    """Puts on the test's session, one publisher per key (declared on first use)."""

    def __init__(self, session, prefix: str) -> None:
        self.session = session
        self.prefix = prefix
        self.pubs: dict[str, object] = {}

    def put(self, key: str, payload: bytes) -> None:
        pub = self.pubs.get(key)
        if pub is None:
            # BLOCK: the test's own messages (a 4 MiB one too) must all reach the server
            pub = self.pubs[key] = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(payload)

    def put_mask(self, cam: str, payload: bytes) -> None:
        self.put(keys.mask_key(self.prefix, cam), payload)

    def close(self) -> None:
        for pub in self.pubs.values():
            pub.undeclare()
        self.pubs.clear()


def feed_lockstep(listener: Listener, feeder: Feeder, fed, frames: range, fusion: Proc, *,
                  before=None, after=None, seq_offset: int = 0) -> None:
    """Publish each frame's masks in camera order and wait for its TrackFrame before the next:
    the server sees the same frame sets in the same order on every run."""
    cams, stamps, masks = fed
    for i in frames:
        j = i % FED_FRAMES
        stamp = stamps[j] + (i - j) * PERIOD_NS
        if before is not None:
            before(i)
        for cam in cams:
            feeder.put_mask(cam, mask_message(cam, i + seq_offset, stamp, *masks[cam][j]))
        if after is not None:
            after(i)
        listener.wait_frame(i + seq_offset, fusion)


PERIOD_NS = round(1e9 / 15)
SUMMARY = re.compile(r"fusion stopped: (?P<fused>\d+) frames fused \(\d+ with range\); (?P<events>\d+) events; \d+ not stored; "
                     r"(?P<slow>\d+) frame sets "
                     r"dropped \(slow\); (?P<few>\d+) with too few cameras; (?P<inbox>\d+) masks dropped on arrival; "
                     r"(?P<unknown>\d+) from unknown cameras")


def summary_counts(log_text: str) -> dict[str, int]:
    """The counters of the fusion server's last 'fusion stopped:' line."""
    found = SUMMARY.findall(log_text)
    assert found, "no 'fusion stopped:' line in the log"
    names = ("fused", "events", "slow", "few", "inbox", "unknown")
    return dict(zip(names, map(int, found[-1])))


def fed_run(house, folder: Path, router: Router, fed, *, extra: tuple[str, ...] = (), before=None, after=None,
            settled=lambda status: True):
    """One fusion server fed FED_FRAMES frames in lockstep; returns (final Status, counters, log text).
    The final status is the first that counts every frame and satisfies ``settled``."""
    site, site_file, cache = house
    folder.mkdir()
    listener = Listener(router.session, site.prefix)
    feeder = Feeder(router.session, site.prefix)
    fusion = start_fusion(site_file, endpoint=router.endpoint, store=folder / "events.sqlite", out=folder / "run",
                          cache_dir=cache, log_dir=folder, extra=(*FED_TIMELINE, *extra))
    try:
        listener.wait_fusion(fusion)
        feed_lockstep(listener, feeder, fed, range(FED_FRAMES), fusion, before=before, after=after)
        n = FED_FRAMES
        status = wait_for(lambda: (st := listener.latest_status()) and st.frame_sets >= n
                          and all(c.received >= n for c in st.cameras) and settled(st) and st, 30,
                          "a status counting every frame", procs=[fusion])
        assert fusion.alive()
        assert fusion.stop() == 0, fusion.tail()
        return status, summary_counts(fusion.output()), fusion.output()
    finally:
        fusion.stop()
        feeder.close()
        listener.close()


# --------------------------------------------------------------------------- 4: garbage during a run


def rejected(payload: bytes, cam: str) -> bool:
    """Whether the fusion server must drop ``payload`` on ``cam``'s mask key as undecodable: not a
    MaskFrame, another camera's, not the camera's 4:3 shape, or data that does not decode."""
    try:
        msg = messages.decode(payload, MaskFrame)
        if msg.cam != cam or abs(msg.width - msg.height * 4 / 3) > 1.0 + 0.01 * msg.height * 4 / 3:
            return True
        maskcodec.decode_mask(msg.data, msg.codec, msg.width, msg.height)
    except (messages.WireError, maskcodec.MaskCodecError):
        return True
    return False


class Garbage:
    """Malformed messages for a camera's mask key, built from the real ones around frame ``i``.

    Every message :meth:`make` returns is one the server must reject; bit flips
    and field mutations that happen to leave a valid mask (another sequence
    number, say) are not garbage and are redrawn (counted in ``redrawn``).
    """

    KINDS = ("random", "truncated", "bitflip", "version", "type", "other_message", "shape", "field", "header",
             "other_camera")

    def __init__(self, fed, prefix: str, seed: int = 0) -> None:
        self.cams, self.stamps, self.masks = fed
        self.prefix = prefix
        self.rng = np.random.default_rng(seed)
        self.redrawn = 0
        self.made: dict[str, int] = dict.fromkeys(self.KINDS, 0)

    def real(self, cam: str, i: int) -> bytes:
        j = i % FED_FRAMES
        return mask_message(cam, i, self.stamps[j], *self.masks[cam][j])

    def make(self, cam: str, i: int) -> bytes:
        kind = self.KINDS[int(self.rng.integers(len(self.KINDS)))]
        for _ in range(100):
            payload = getattr(self, f"_{kind}")(cam, i)
            if rejected(payload, cam):
                self.made[kind] += 1
                return payload
            self.redrawn += 1
        raise AssertionError(f"no rejected {kind} message in 100 draws")

    def _random(self, cam: str, i: int) -> bytes:
        return self.rng.bytes(int(self.rng.integers(0, 3000)))

    def _truncated(self, cam: str, i: int) -> bytes:
        good = self.real(cam, i)
        return good[: int(self.rng.integers(0, len(good)))]

    def _bitflip(self, cam: str, i: int) -> bytes:
        data = bytearray(self.real(cam, i))
        for pos in self.rng.integers(0, 8 * len(data), int(self.rng.integers(1, 4))):
            data[pos // 8] ^= 1 << (pos % 8)
        return bytes(data)

    def _fields(self, cam: str, i: int) -> dict:
        import msgpack

        return msgpack.unpackb(self.real(cam, i))

    def _pack(self, obj) -> bytes:
        import msgpack

        return msgpack.packb(obj, use_bin_type=True)

    def _version(self, cam: str, i: int) -> bytes:
        obj = self._fields(cam, i)
        choice = int(self.rng.integers(6))
        if choice == 5:
            del obj["v"]
        else:
            obj["v"] = [0, 2, -1, "1", 1.0][choice]
        return self._pack(obj)

    def _type(self, cam: str, i: int) -> bytes:
        obj = self._fields(cam, i)
        obj["type"] = [None, "hold", "tracks", "MASK", 7][int(self.rng.integers(5))]
        return self._pack(obj)

    def _other_message(self, cam: str, i: int) -> bytes:
        stamp = self.stamps[i % FED_FRAMES]
        choice = int(self.rng.integers(6))
        if choice == 0:
            return messages.encode(messages.HoldRegions(cam=cam, stamp_ns=stamp, boxes=[(10, 10, 100, 200)], ttl_ms=2000))
        if choice == 1:
            return messages.encode(messages.TrackFrame(frame=i, stamp_ns=stamp, tracks=[], cameras=[cam]))
        if choice == 2:
            return messages.encode(messages.Status(stamp_ns=stamp, cameras=[], frame_sets=i, frame_sets_dropped=0))
        event = messages.Event(id=f"e{i}", kind="fall", track=1, stamp_ns=stamp, frame=i, x=1.0, y=2.0)
        if choice == 3:
            return messages.encode(event)
        if choice == 4:
            return event.to_json().encode()
        return messages.encode(messages.WorkerStats(cam=cam, stamp_ns=stamp, read=i, dropped=0, published=i))

    def _shape(self, cam: str, i: int) -> bytes:
        j = i % FED_FRAMES
        choice = int(self.rng.integers(4))
        if choice == 0:  # a square mask: not the camera's aspect
            mask = np.zeros((100, 100), np.uint8)
            mask[20:80, 40:60] = 255
            return mask_message(cam, i, self.stamps[j], maskcodec.encode_mask(mask), 0.12, width=100, height=100)
        if choice == 1:  # a quarter-size mask's data said to be full size
            mask = np.zeros((120, 160), np.uint8)
            mask[30:90, 70:90] = 255
            return mask_message(cam, i, self.stamps[j], maskcodec.encode_mask(mask), 0.06)
        if choice == 2:  # full-size data said to be 320 x 240
            return mask_message(cam, i, self.stamps[j], self.masks[cam][j][0], self.masks[cam][j][1],
                                width=320, height=240)
        obj = self._fields(cam, i)  # larger than its capture
        obj["width"], obj["height"] = 1280, 960
        return self._pack(obj)

    def _field(self, cam: str, i: int) -> bytes:
        obj = self._fields(cam, i)
        name, value = [("seq", -1), ("seq", "7"), ("stamp_ns", 1.5e18), ("stamp_ns", -5), ("width", 0),
                       ("codec", "png"), ("data", "text"), ("fg_fraction", 2.0), ("cam", "bad/cam"), ("extra", 1),
                       ("data", b""), ("src_width", None)][int(self.rng.integers(12))]
        obj[name] = value
        if self.rng.random() < 0.2:
            del obj[str(self.rng.choice(sorted(k for k in obj if k not in ("v", "type"))))]
        return self._pack(obj)

    def _header(self, cam: str, i: int) -> bytes:
        return [b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff", b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff",
                self._pack([1, 2, 3]), self._pack(42), self._pack("mask"), b"\x91" * 5000, b"\xc1",
                self._pack({"v": 1, "type": "mask", "cam": {"nested": [1] * 100}})][int(self.rng.integers(10))]

    def _other_camera(self, cam: str, i: int) -> bytes:
        others = [c for c in self.cams if c != cam]
        return self.real(others[int(self.rng.integers(len(others)))], i)


@pytest.mark.slow
def test_thousands_of_malformed_messages_leave_the_tracks_unchanged_and_are_counted(house, fed, tmp_path):
    site = house[0]
    prefix = site.prefix
    garbage = Garbage(fed, prefix, seed=1)
    sent = dict.fromkeys(site.camera_ids, 0)
    per_frame = 10  # before and again after each frame's masks: 20 per frame set, 3000 in all
    oversize_frames = {20, 75, 130}
    extra = {"unknown_camera": 0, "tokens": 0, "queries": 0, "query_errors": 0}
    ghosts = [f"ghost{k}" for k in range(8)]

    with Router() as router:
        clean_status, clean_counts, _ = fed_run(house, tmp_path / "clean", router, fed)
        session = router.session
        feeder = Feeder(session, prefix)
        tokens = []

        def throw(i: int) -> None:
            for _ in range(per_frame):
                cam = site.camera_ids[int(garbage.rng.integers(len(site.camera_ids)))]
                feeder.put_mask(cam, garbage.make(cam, i))
                sent[cam] += 1
            if i in oversize_frames:
                cam = site.camera_ids[int(garbage.rng.integers(len(site.camera_ids)))]
                feeder.put_mask(cam, bytes(messages.MAX_MESSAGE_BYTES + 1))
                sent[cam] += 1
            if i % 10 == 0:  # cameras the site does not have, real masks and garbage
                feeder.put(keys.mask_key(prefix, ghosts[i % len(ghosts)]), garbage.real("cam1", i))
                feeder.put(keys.mask_key(prefix, "cam1x"), garbage.make("cam1", i))
                extra["unknown_camera"] += 2
                # plain puts on liveliness keys, and liveliness tokens of unknown cameras
                feeder.put(keys.alive_camera_key(prefix, "cam1"), garbage.make("cam1", i))
                feeder.put(keys.alive_fusion_key(prefix), b"\x00\x01")
                tokens.append(session.liveliness().declare_token(keys.alive_camera_key(prefix, ghosts[i % 8])))
                extra["tokens"] += 1
                if len(tokens) > 4:
                    tokens.pop(0).undeclare()
            if i % 15 == 7:  # selectors the history cannot parse
                params = ["since=yesterday", "until=-5", "kind=teleport", "format=xml", "since=1e999",
                          "kind=fall;kind=", "limit=" + "9" * 400, "since=" + "x" * 5000, "%%%", "until=12:99"]
                for text in params[(i // 15) % 3::3]:
                    replies = list(session.get(f"{keys.history_key(prefix)}?{text}", timeout=10.0))
                    extra["queries"] += 1
                    extra["query_errors"] += sum(r.ok is None for r in replies)
                    assert all(r.ok is None for r in replies), text

        try:
            fuzz_status, fuzz_counts, fuzz_log = fed_run(
                house, tmp_path / "fuzzed", router, fed, before=throw, after=throw,
                settled=lambda st: sum(c.undecodable for c in st.cameras) >= sum(sent.values()))
        finally:
            for token in tokens:
                token.undeclare()
            feeder.close()

    print("garbage sent per camera:", sent, "by kind:", garbage.made, "redrawn:", garbage.redrawn, extra)
    print("fuzzed run counters:", fuzz_counts)
    assert sum(sent.values()) >= 2000
    # the tracking result is exactly the clean run's
    clean_tracks = (tmp_path / "clean/run/tracks.csv").read_text()
    assert len(clean_tracks.splitlines()) > 100
    assert (tmp_path / "fuzzed/run/tracks.csv").read_text() == clean_tracks
    assert (tmp_path / "fuzzed/run/events.jsonl").read_text() == (tmp_path / "clean/run/events.jsonl").read_text()
    # every piece of garbage counted as undecodable on its camera, no real mask lost
    by_cam = {c.cam: c for c in fuzz_status.cameras}
    assert {cam: by_cam[cam].undecodable for cam in sent} == sent
    assert all((c.received, c.dropped, c.late) == (FED_FRAMES, 0, 0) for c in fuzz_status.cameras)
    assert all(c.undecodable == 0 for c in clean_status.cameras)
    assert fuzz_counts["unknown"] == extra["unknown_camera"] and fuzz_counts["inbox"] == 0
    assert fuzz_counts["fused"] == clean_counts["fused"] == FED_FRAMES
    assert extra["query_errors"] == extra["queries"] > 0
    assert "Traceback" not in fuzz_log and "undecodable mask dropped" in fuzz_log


# --------------------------------------------------------------------------- 5: a flood


FLOOD_SETS = 3000           # per flood: 15 000 masks of 38 KB (576 MB), published as fast as the test can
FLOODS = 2
WARM_FLOOD_SETS = 500       # a first, smaller flood brings the buffers to their working size
RSS_GROWTH_BOUND_MB = 64    # an unbounded inbox would hold up to 576 MB a flood, decoded masks 4.6 GB


def uncompressed(fed, first: int, n: int) -> dict[str, list[bytes]]:
    """Per camera, the data of ``n`` true masks from frame ``first`` on as 'bits-zlib' stored without
    compression (zlib level 0): 38 KB each, the same silhouettes as the fed frames."""
    cams, _, masks = fed
    return {cam: [maskcodec.encode_mask(maskcodec.decode_mask(masks[cam][first + k][0], "rle-zlib", 640, 480),
                                        "bits-zlib", zlib_level=0) for k in range(n)] for cam in cams}


@pytest.mark.slow
def test_a_flood_drops_old_frame_sets_and_memory_stays_bounded(house, fed, tmp_path):
    site, site_file, cache = house
    cams, stamps, masks = fed
    first = 75  # a standing person
    big = uncompressed(fed, first, 8)
    warm, tail = 60, 30
    measured: dict[str, object] = {"flood_s": [], "rss_peak_mb": []}
    with Router() as router:
        listener = Listener(router.session, site.prefix)
        feeder = Feeder(router.session, site.prefix)
        fusion = start_fusion(site_file, endpoint=router.endpoint, store=tmp_path / "events.sqlite", out=None,
                              cache_dir=cache, log_dir=tmp_path, extra=FED_TIMELINE)
        try:
            listener.wait_fusion(fusion)
            feed_lockstep(listener, feeder, fed, range(warm), fusion)
            rss: list[int] = []
            anon: list[int] = []
            i = warm
            for flood in range(FLOODS + 1):
                if flood == 1:  # the baseline: after the warm-up flood
                    rss, anon = [fusion.rss_kb()], [fusion.rss_kb("RssAnon")]
                t0 = time.monotonic()
                for n in range(WARM_FLOOD_SETS if flood == 0 else FLOOD_SETS):
                    stamp = stamps[0] + i * PERIOD_NS
                    for cam in cams:
                        feeder.put_mask(cam, messages.encode(MaskFrame(
                            cam=cam, seq=i, stamp_ns=stamp, width=640, height=480, src_width=640, src_height=480,
                            codec="bits-zlib", data=big[cam][n % 8], fg_fraction=masks[cam][first + n % 8][1])))
                    i += 1
                    if n % 50 == 0:
                        rss.append(fusion.rss_kb())
                        anon.append(fusion.rss_kb("RssAnon"))
                measured["flood_s"].append(round(time.monotonic() - t0, 2))

                def quiet():  # the server has taken in all it will: the fused count stops moving
                    before = listener.latest_status()
                    for _ in range(10):
                        rss.append(fusion.rss_kb())
                        anon.append(fusion.rss_kb("RssAnon"))
                        time.sleep(0.25)
                    after = listener.latest_status()
                    return after is not None and before is not None and after.frame_sets == before.frame_sets and after

                status = wait_for(quiet, 120, "the server to work off the flood", procs=[fusion], period_s=0)
                measured["rss_peak_mb"].append(round(max(rss) / 1024, 1))
            # it goes on fusing every frame set once the floods are over
            feed_lockstep(listener, feeder, fed, range(i, i + tail), fusion)
            after_flood = fused_after(listener, i - 1)
            assert fusion.alive()
            assert fusion.stop() == 0, fusion.tail()
        finally:
            fusion.stop()
            feeder.close()
            listener.close()
    counts = summary_counts(fusion.output())
    growth_mb = (max(rss) - rss[0]) / 1024
    anon_growth_mb = (max(anon) - anon[0]) / 1024
    measured.update(rss_before_mb=round(rss[0] / 1024, 1), rss_end_mb=round(rss[-1] / 1024, 1),
                    growth_mb=round(growth_mb, 1), anon_growth_mb=round(anon_growth_mb, 1),
                    fused_during_floods=status.frame_sets - warm,
                    frame_sets_dropped=status.frame_sets_dropped, masks_dropped_on_arrival=counts["inbox"],
                    camera_dropped=[c.dropped for c in status.cameras])
    print("measured:", measured)
    assert status.frame_sets - warm < FLOODS * FLOOD_SETS + WARM_FLOOD_SETS  # it could not keep up ...
    assert status.frame_sets_dropped > 0 and counts["slow"] >= status.frame_sets_dropped  # ... dropped old sets
    assert counts["inbox"] > 0 and all(c.dropped > 0 for c in status.cameras)  # and masks on arrival, counted
    assert growth_mb < RSS_GROWTH_BOUND_MB and anon_growth_mb < RSS_GROWTH_BOUND_MB, measured
    assert len(after_flood) == tail and all(f.cameras == list(cams) for f in after_flood)
    assert all(len(f.tracks) == 1 for f in after_flood[10:]), [f.tracks for f in after_flood]
    assert "Traceback" not in fusion.output()


# --------------------------------------------------------------------------- 6: a camera clock ahead


SKEWED = "cam5"
SKEW_NS = 1_000_000_000


# --------------------------------------------------------------------------- 3: the fusion server restarted


RESTART_SCENARIO = "enter_exit"
RESTART_FRAMES = 345        # 23 s: enters at frame 62, stands still 150..220, leaves through the door at 303
RESTART_AFTER_FRAME = 95


def history(session, prefix: str, parameters: str = "") -> list[messages.Event]:
    """Every event the history queryable returns (one reply per event, each on its own key)."""
    selector = keys.history_key(prefix) + "/**" + (f"?{parameters}" if parameters else "")
    replies = list(session.get(selector, timeout=10.0))
    assert all(r.ok is not None for r in replies), [r.err.payload.to_string() for r in replies if r.ok is None]
    return sorted((messages.decode_event(r.ok.payload.to_bytes()) for r in replies), key=lambda e: e.stamp_ns)


@pytest.mark.slow
def test_a_restarted_fusion_server_answers_the_whole_history_and_tracks_again(house, tmp_path, machine_to_itself):
    site, site_file, cache = house
    prefix = site.prefix
    truth = write_truth(RESTART_SCENARIO, RESTART_FRAMES, tmp_path / "truth")
    store = tmp_path / "events.sqlite"
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: list[Proc] = []
    measured: dict[str, object] = {}
    with Router() as router:
        listener = Listener(router.session, prefix)
        try:
            first = start_fusion(site_file, endpoint=router.endpoint, store=store, out=tmp_path / "run1",
                                 cache_dir=cache, log_dir=logs)
            procs.append(first)
            listener.wait_fusion(first)
            start_file = tmp_path / "start_ns"   # the person enters 62 frames after it: every worker must be ready
            workers = [start_camera(site_file, cam, endpoint=router.endpoint, scenario=RESTART_SCENARIO,
                                    start_file=start_file, max_frames=RESTART_FRAMES, log_dir=logs)
                       for cam in site.camera_ids]
            procs.extend(workers)
            start_in_step(router.session, prefix, dict(zip(site.camera_ids, workers)), start_file)
            wait_for(lambda: listener.events_of("enter") and listener.last_frame() >= RESTART_AFTER_FRAME,
                     120, "an enter event and fused frames past the restart point",
                     procs=[first, *workers])

            # -- SIGKILL the server mid-run, start another on the same store
            published = {h.msg.id: h.msg for h in listener.event_list()}
            mark = listener.last_frame()
            first.kill()
            wait_for(lambda: not listener.fusion_alive.is_set(), 30, "the first server's token to go")
            restart_ns = time.time_ns()
            second = start_fusion(site_file, endpoint=router.endpoint, store=store, out=tmp_path / "run2",
                                  cache_dir=cache, log_dir=logs, name="fusion-again")
            procs.append(second)
            listener.wait_fusion(second)
            after_restart = history(router.session, prefix)
            measured["events_before_restart"] = sorted(e.kind for e in published.values())

            # -- it tracks again
            resumed = wait_for(lambda: [f for f in fused_after(listener, mark) if near_truth(f, truth)], 60,
                               "a track near the truth from the new server", procs=[second, *workers])
            measured["tracking_again_after_s"] = (time.time_ns() - restart_ns) / 1e9
            measured["frames_missed"] = resumed[0].frame - mark
            for worker in workers:
                assert worker.popen.wait(timeout=RESTART_FRAMES / 15 + 120) == 0, worker.tail()
            time.sleep(1.0)
            frames = fused_after(listener, mark)
            heard = {h.msg.id: h.msg for h in listener.event_list()}
            at_end = history(router.session, prefix)
            only_enter = history(router.session, prefix, "kind=enter")
            assert second.stop() == 0, second.tail()
        finally:
            stop_all(procs)
            listener.close()

    # everything published before the restart is answered by the new server, unchanged
    assert published and all(e.kind in messages.EVENT_KINDS for e in published.values())
    assert {e.id: e for e in after_restart if e.id in published} == published
    assert set(published) <= {e.id for e in after_restart}
    # and the history keeps growing with what the new server publishes
    assert {e.id for e in at_end} == set(heard) and all(e == heard[e.id] for e in at_end)
    assert only_enter == [e for e in at_end if e.kind == "enter"] and only_enter
    # judged on what the new server was given: the frame sets it fused with every camera's mask (on a
    # loaded machine a worker's mask comes too late for some sets, and the server drops sets it cannot
    # keep up with; neither is what a restart must get right)
    with_person = [f for f in frames if f.frame >= resumed[0].frame and truth.get(f.frame)]
    whole = [f for f in with_person if sorted(f.cameras) == sorted(site.camera_ids)]
    near = sum(near_truth(f, truth) for f in whole)
    measured.update(events_at_end=sorted(e.kind for e in at_end), fused_after_restart=len(frames),
                    with_person_after_restart=len(with_person), near_truth_of_whole_sets=f"{near}/{len(whole)}")
    print("measured:", measured)
    assert len(whole) >= 30, measured   # of the ~200 sets with the person after the restart
    assert near >= 0.8 * len(whole), measured


# --------------------------------------------------------------------------- 4: the server killed after a fall


LIE_FRAMES = 780          # 52 s of 'fall_forward' looped (40 s a lap): the truth falls at frames 101 and 701
LIE_S = 15.0              # the site's long_lie_s here: the long lie is due at frame ~326, after the restart
KILL_AFTER_FALL_S = 3.0
DOWN_S = 5.0


@pytest.mark.slow
def test_a_fusion_server_killed_after_a_fall_finds_the_person_on_the_floor_again(house, tmp_path, machine_to_itself):
    """SIGKILL 3 s after the fall, a new server on the same store 5 s later: it goes on from the
    snapshot the first kept, the workers having held the person meanwhile, so the person lying
    there is tracked again under their label, the long lie comes at the fall + ``long_lie_s``,
    no event is raised twice, and the next lap's fall (the recording looped) is raised."""
    from common.site import load_site, write_site

    site, base_file, cache = house
    site = site.model_copy(update={"events": site.events.model_copy(update={"long_lie_s": LIE_S})})
    site_file = base_file.with_name("site-long-lie.toml")
    write_site(site, site_file)
    site = load_site(site_file)
    prefix = site.prefix
    truth_dir, logs = tmp_path / "truth", tmp_path / "logs"
    logs.mkdir()
    truth = write_truth(SCENARIO, min(LIE_FRAMES, 600), truth_dir)   # the first lap's (frames 0-599)
    (truth_fall,) = truth_events(truth_dir, "fall")
    truth_fall_frame = truth_fall["frame"]
    store = tmp_path / "events.sqlite"
    procs: list[Proc] = []
    measured: dict[str, object] = {}
    with Router() as router:
        listener = Listener(router.session, prefix)
        try:
            first, workers = start_fusion_and_cameras(site, site_file, router=router, listener=listener, store=store,
                                                      out=tmp_path / "run1", cache_dir=cache, log_dir=logs,
                                                      scenario=SCENARIO, max_frames=LIE_FRAMES, procs=procs,
                                                      loop=True)
            (fall,) = wait_for(lambda: listener.events_of("fall"), 120, "the fall", procs=[first, *workers.values()])
            after = fall.frame + int(KILL_AFTER_FALL_S * 15)
            wait_for(lambda: listener.last_frame() >= after, 60, f"fused frame {after}", procs=[first])
            kill_ns = time.time_ns()
            first.kill()
            wait_for(lambda: not listener.fusion_alive.is_set(), 30, "the first server's token to go")
            killed_at = listener.last_frame()
            time.sleep(max(0.0, DOWN_S - (time.time_ns() - kill_ns) / 1e9))
            second = start_fusion(site_file, endpoint=router.endpoint, store=store, out=tmp_path / "run2",
                                  cache_dir=cache, log_dir=logs, name="fusion-again")
            procs.append(second)
            listener.wait_fusion(second)
            live_ns = time.time_ns()
            again = wait_for(lambda: [f for f in fused_after(listener, killed_at)
                                      if near_truth(f, truth) and f.tracks[0].id == fall.track
                                      and f.tracks[0].posture == "lying"], 30,
                             "the person on the floor, under their label, from the new server",
                             procs=[second, *workers.values()])
            heard_again = next(h for h in listener.track_frames() if h.msg.frame == again[0].frame)
            measured["found_again_after_live_s"] = round((heard_again.recv_ns - live_ns) / 1e9, 2)
            measured["found_again_at_frame"] = again[0].frame
            (lie,) = wait_for(lambda: listener.events_of("long_lie"), 60, "the long lie", procs=[second])
            for worker in workers.values():
                assert worker.popen.wait(timeout=LIE_FRAMES / 15 + 120) == 0, worker.tail()
            time.sleep(1.0)
            heard = listener.event_list()
            at_end = history(router.session, prefix)
            assert second.stop() == 0, second.tail()
        finally:
            stop_all(procs)
            listener.close()
    log = (logs / "fusion-again.log").read_text()
    measured.update(long_lie_after_fall_s=round((lie.stamp_ns - fall.details["fall_stamp_ns"]) / 1e9, 2),
                    events=sorted(h.msg.kind for h in heard))
    print("measured:", measured)
    assert "going on from the snapshot" in log and f"person {fall.track} found again" in log, log[-3000:]
    assert measured["found_again_after_live_s"] <= 2.0, measured
    # the long lie: the fall's person, counted from the fall, at its time, raised once
    assert lie.track == fall.track and lie.details["lying_since_ns"] == fall.details["fall_stamp_ns"], lie
    assert abs(measured["long_lie_after_fall_s"] - LIE_S) <= 0.5, measured
    kinds = [h.msg.kind for h in heard]
    assert kinds.count("long_lie") == 1, kinds
    # the first lap's fall once (the first server's), the next lap's from the second server near its truth
    falls = [h.msg for h in heard if h.msg.kind == "fall"]
    lap_frames = int(synth.scenario_spec(SCENARIO).duration_s * 15)
    assert len(falls) == 2 and falls[0].id == fall.id, [(f.frame, f.track) for f in falls]
    next_truth = truth_fall_frame + lap_frames
    assert -FALL_EARLY_FRAMES <= falls[1].frame - next_truth <= FALL_LATE_FRAMES, (falls[1].frame, next_truth)
    # every event heard is in the history once, and nothing else
    ids = [e.id for e in at_end]
    assert len(ids) == len(set(ids)) and set(ids) == {h.msg.id for h in heard}


# --------------------------------------------------------------------------- 5: a loaded fusion host


BURN_FRAMES = 330   # 22 s of 'fall_forward'
FUSION_CPU = 0
FUSION_NICE = 15


def stop_burners(burners) -> None:
    """Kill the processes that burn a core (those still running) and reap them."""
    for burner in burners:
        if burner.poll() is None:
            burner.kill()
        burner.wait()


@pytest.mark.slow
def test_a_fusion_host_loaded_with_cpu_burners_reads_overloaded_and_no_camera_skewed(house, tmp_path, machine_to_itself):
    """Two processes that burn a core each start once the cameras run: the fusion server, left a
    fraction of a core, reads ``overloaded`` with its load, and no camera reads ``skewed``
    (its masks wait in the server's queue; before, a loaded host put every camera at -660 ms)."""
    import subprocess

    site, site_file, cache = house
    prefix = site.prefix
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: list[Proc] = []
    burners: list[subprocess.Popen] = []
    with Router() as router:
        listener = Listener(router.session, prefix)
        try:
            fusion, workers = start_fusion_and_cameras(site, site_file, router=router, listener=listener,
                                                       store=tmp_path / "events.sqlite", out=None, cache_dir=cache,
                                                       log_dir=logs, scenario=SCENARIO, max_frames=BURN_FRAMES,
                                                       procs=procs)
            wait_for(lambda: listener.last_frame() >= 30, 60, "fused frame 30", procs=[fusion])
            calm = len(listener.status)
            # the fusion server's processor taken by two burners, its own share of it under 2 % (nice 15
            # against their 0): less than it needs on any machine here, however fast (on an AMD EPYC two
            # burners free to use both cores left it 20-40 % busy, 20-35 ms behind: not overloaded)
            burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
            for burner in burners:
                confine(burner.pid, FUSION_CPU)
            confine(fusion.popen.pid, FUSION_CPU, nice=FUSION_NICE)
            try:
                wait_for(lambda: any(h.msg.state == "overloaded" for h in listener.status[calm:]), 30,
                         "an 'overloaded' status", procs=[fusion])
            except AssertionError as exc:
                seen = [(h.msg.state, round(h.msg.load, 2), h.msg.frame_sets_dropped,
                         [round(c.latency_ms) for c in h.msg.cameras]) for h in listener.status[calm:]]
                raise AssertionError(f"{exc}; the statuses since the burners started (state, load, sets "
                                     f"dropped, cameras' latency ms): {seen}") from None
            time.sleep(5.0)
            for worker in workers.values():
                worker.popen.wait(timeout=BURN_FRAMES / 15 + 120)
            loaded = [h.msg for h in listener.status[calm:]]
            # the burners go before the server is asked to stop: a clean exit is asked of a server given
            # its core back (starved to under 2 % of one, it logged its summary at once, then its
            # interpreter's exit outlasted 20 s on one run)
            stop_burners(burners)
            assert fusion.stop() == 0, fusion.tail()
        finally:
            stop_burners(burners)
            stop_all(procs)
            listener.close()
    over = [st for st in loaded if st.state == "overloaded"]
    skewed = sorted({c.cam for st in loaded for c in st.cameras if c.state == "skewed"})
    offsets = [c.clock_offset_ms for st in loaded for c in st.cameras if c.state != "stopped"]
    print("measured:", {"statuses": len(loaded), "overloaded": len(over), "max_load": max(st.load for st in loaded),
                        "skewed": skewed, "clock_offset_ms_min": min(offsets),
                        "latency_ms_max": max(c.latency_ms for st in loaded for c in st.cameras)})
    # overloaded from a share of 90 % worked, or from frame sets dropped for being slow
    assert over and max(st.load for st in over) >= 0.9, [(st.state, st.load, st.frame_sets_dropped) for st in loaded]
    assert skewed == [], [(st.state, [(c.cam, c.state, c.clock_offset_ms) for c in st.cameras]) for st in loaded]
    assert "clock off by" not in (logs / "fusion.log").read_text()


# --------------------------------------------------------------------------- 6: oversized masks on three keys


FLOOD_FRAMES = 330   # 22 s of 'fall_forward': the truth fall at frame 101
FLOOD_S = 20.0
FLOOD_RATE_HZ = 15.0


@pytest.mark.slow
def test_oversized_valid_masks_on_three_camera_keys_neither_stall_fusion_nor_hide_the_fall(house, tmp_path,
                                                                                          machine_to_itself):
    """A host that sends 15 valid 4096x3072 masks a second (55 KB each, 0.3 s each to inflate) on
    three cameras' keys for 20 s (the soak's hostile host), beside the real workers: refused on their size before they are
    decoded, so the server fuses as many frame sets as the cameras make, the fall is raised, and
    the three cameras read degraded with the reason (the other two ok)."""
    import threading

    from voxelwatch.soak import send_oversized_masks

    site, site_file, cache = house
    prefix = site.prefix
    truth_dir, logs = tmp_path / "truth", tmp_path / "logs"
    logs.mkdir()
    write_truth(SCENARIO, FLOOD_FRAMES, truth_dir)
    (fall_truth,) = truth_events(truth_dir, "fall")
    victims = list(site.camera_ids[:3])
    procs: list[Proc] = []
    sent = {"masks": 0}
    done = threading.Event()

    def flood(session) -> None:
        sent["masks"] = send_oversized_masks(session, prefix, victims, seconds=FLOOD_S, rate_hz=FLOOD_RATE_HZ,
                                             stop=done)

    with Router() as router:
        listener = Listener(router.session, prefix)
        try:
            fusion, workers = start_fusion_and_cameras(site, site_file, router=router, listener=listener,
                                                       store=tmp_path / "events.sqlite", out=None, cache_dir=cache,
                                                       log_dir=logs, scenario=SCENARIO, max_frames=FLOOD_FRAMES,
                                                       procs=procs)
            wait_for(lambda: listener.last_frame() >= 5, 60, "fused frame 5", procs=[fusion])
            mark = listener.last_frame()
            sender = threading.Thread(target=flood, args=(router.session,), daemon=True)
            sender.start()
            wait_for(lambda: listener.events_of("fall"), 60, "the fall", procs=[fusion])
            time.sleep(3.0)
            during = listener.latest_status()
            sender.join(timeout=FLOOD_S + 5)
            for worker in workers.values():
                assert worker.popen.wait(timeout=FLOOD_FRAMES / 15 + 120) == 0, worker.tail()
            frames = fused_after(listener, mark)
            falls = listener.events_of("fall")
            assert fusion.stop() == 0, fusion.tail()
        finally:
            done.set()
            stop_all(procs)
            listener.close()
    states = {c.cam: (c.state, c.reason) for c in during.cameras}
    span = frames[-1].frame - frames[0].frame + 1
    measured = {"hostile_masks_sent": sent["masks"], "fused": len(frames), "frames_spanned": span,
                "fall_frame": falls[0].frame, "truth_fall_frame": fall_truth["frame"], "states": states}
    print("measured:", measured)
    assert sent["masks"] >= 0.8 * FLOOD_S * FLOOD_RATE_HZ * len(victims), measured
    assert len(frames) >= 0.9 * span, measured       # every frame set the cameras made, or nearly
    assert len(falls) == 1 and -FALL_EARLY_FRAMES <= falls[0].frame - fall_truth["frame"] <= FALL_LATE_FRAMES
    for cam in victims:
        state, reason = states[cam]
        assert state == "degraded" and "is not a size camera" in (reason or ""), measured
    assert all(states[cam] == ("ok", None) for cam in site.camera_ids[3:]), measured
