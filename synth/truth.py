"""Exact ground truth of a scenario: per-frame positions and postures, and events.

Tracks (``truth/tracks.csv``, a tracks file of :mod:`common.runfiles`):
one row per person per frame while the person's pelvis is inside the
monitored volume (the room's floor rectangle); ``x, y`` the pelvis (hip-joint
midpoint) projected on the floor, ``z_top`` the highest body point, metres;
``posture`` 'standing' (walking included), 'sitting', 'lying' or 'bending'
(kneeling included).

Events (``truth/events.jsonl``, an events file of :mod:`common.runfiles`):
:class:`~common.messages.Event` with the person id as ``track``. The frame
of each kind:

* ``fall``: the frame the body reaches the floor (end of the ~0.9 s drop);
  posture is 'lying' from that frame. details: direction.
* ``sit_down`` / ``stand_up``: half-way through the transition (the frame
  posture switches). details: seat, from ('sitting' or 'lying').
* ``enter``: the first frame the pelvis is inside the volume after being
  outside (people present from frame 0 do not enter); ``exit``: the first
  frame outside after being inside.
* ``dwell_start``: a person who stopped walking inside a hot spot (standing,
  sitting down, sitting ...) and stays at least :data:`DWELL_WINDOW_S`
  seconds; the event is at the end of that window (as a detector that
  watches a still window decides), details: hotspot, since_frame (when they
  stopped). ``dwell_end``: the first frame they walk again. details:
  hotspot. (Fed through ``fusion_server.hotspots.DwellDetector`` with its
  defaults, the true positions give starts and ends within about 2 s of
  these frames.)
* ``long_lie``: :data:`LONG_LIE_S` seconds after a fall, if still lying.
* ``visit``: more people present than the site's residents and two of them
  dwelling at the same hot spot: at the later of their dwell starts, once per
  episode of extra people. details: hotspot, reason ('for dinner' ...), people.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.postures import BODY_POSTURES
from common.messages import Event, event_id
from common.runfiles import EVENTS_FILE, META_FILE, TRACKS_FILE, write_events_file, write_tracks_file
from synth.behaviour import LYING

DWELL_WINDOW_S = 10.0
LONG_LIE_S = 30.0


def _event(kind: str, person: int, frame: int, stamp_ns: int, x: float, y: float, details: dict) -> Event:
    """A true event; ``track`` is the person id, ``x, y`` metres, world frame (four decimals)."""
    return Event(id=event_id(stamp_ns, kind, person), kind=kind, track=int(person), frame=int(frame),
                 stamp_ns=int(stamp_ns), x=round(float(x), 4), y=round(float(y), 4), details=details)


@dataclass(frozen=True)
class Truth:
    """All ground truth of one scenario run.

    Track rows as parallel arrays sorted by (frame, id): frame (N,) int64, stamp_ns (N,) int64,
    person (N,) int64, x, y, z_top (N,) float64 (metres), posture (N,) str.
    events: sorted by frame.
    """

    frame: np.ndarray
    stamp_ns: np.ndarray
    person: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z_top: np.ndarray
    posture: np.ndarray
    events: list[Event]

    def rows_at(self, frame: int) -> np.ndarray:
        """Indices of the rows of ``frame``."""
        lo, hi = np.searchsorted(self.frame, [frame, frame + 1])
        return np.arange(lo, hi)

    def events_of(self, kind: str) -> list[Event]:
        return [e for e in self.events if e.kind == kind]

    def cut(self, n_frames: int) -> "Truth":
        """The truth of frames ``0 .. n_frames - 1`` only."""
        keep = self.frame < n_frames
        return Truth(frame=self.frame[keep], stamp_ns=self.stamp_ns[keep], person=self.person[keep], x=self.x[keep],
                     y=self.y[keep], z_top=self.z_top[keep], posture=self.posture[keep],
                     events=[e for e in self.events if e.frame < n_frames])


def derive_truth(scenario) -> Truth:
    """Ground truth of a :class:`synth.scenario.Scenario` (pure, deterministic)."""
    room = scenario.room
    n = scenario.n_frames
    fps = scenario.fps
    frames = np.arange(n)
    stamps = np.array([scenario.stamp_ns(int(f)) for f in frames], dtype=np.int64)
    states = scenario.states
    in_volume = [st["present"] & room.inside_volume(st["xy"]) for st in states]
    rows = []
    events: list[Event] = []
    for person, st, inside in zip(scenario.people, states, in_volume):
        pid = person.person_id
        f = frames[inside]
        rows.append((f, np.full(f.shape, pid), st["xy"][inside, 0], st["xy"][inside, 1], st["z_top"][inside],
                     st["label"][inside]))

        def event(kind: str, frame: int, details: dict, xy=None) -> Event:
            x, y = (st["xy"][frame] if xy is None else xy)
            return _event(kind, pid, int(frame), int(stamps[frame]), float(x), float(y), details)

        for t_s, kind, details in person.events:
            fr = scenario.frame_of(t_s)
            if 0 <= fr < n and inside[fr]:
                events.append(event(kind, fr, dict(details)))
        prev = np.concatenate([[inside[0]], inside[:-1]])
        for fr in np.nonzero(inside & ~prev)[0]:
            events.append(event("enter", fr, {}))
        for fr in np.nonzero(~inside & prev)[0]:
            events.append(event("exit", fr, {}, xy=st["xy"][fr - 1]))
        lying = inside & (st["label"] == LYING)
        long_lie = int(round(LONG_LIE_S * fps))
        for a, b in _runs(lying):
            if b - a > long_lie:
                events.append(event("long_lie", a + long_lie, {"lying_since_frame": int(a)}))
    dwells = _dwell_intervals(scenario, states, in_volume)
    window = int(round(DWELL_WINDOW_S * fps))
    for pid, hs, a, b, xy in dwells:
        start = a + window
        events.append(_event("dwell_start", pid, start, int(stamps[start]), float(xy[0]), float(xy[1]),
                                 {"hotspot": hs.name, "since_frame": int(a)}))
        if b < n:
            st = states[[p.person_id for p in scenario.people].index(pid)]
            events.append(_event("dwell_end", pid, b, int(stamps[b]), float(st["xy"][b, 0]), float(st["xy"][b, 1]),
                                     {"hotspot": hs.name}))
    events += _visits(scenario, in_volume, dwells, window, stamps)
    events.sort(key=lambda e: (e.frame, e.track, e.kind))
    if rows:
        cols = [np.concatenate(c) for c in zip(*rows)]
    else:
        cols = [np.zeros(0, dtype=np.int64)] * 2 + [np.zeros(0)] * 3 + [np.zeros(0, dtype=np.int8)]
    order = np.lexsort((cols[1], cols[0]))
    fr, pid, x, y, z, lab = (c[order] for c in cols)
    return Truth(frame=fr.astype(np.int64), stamp_ns=stamps[fr.astype(np.int64)], person=pid.astype(np.int64),
                 x=x.astype(np.float64), y=y.astype(np.float64), z_top=z.astype(np.float64),
                 posture=np.array([BODY_POSTURES[int(v)] for v in lab], dtype=str).reshape(-1), events=events)


def write_truth(scenario, out_dir, truth: Truth | None = None, *, n_frames: int | None = None) -> dict[str, Path]:
    """Write ``OUT/tracks.csv``, ``OUT/events.jsonl`` and ``OUT/meta.json``; returns their paths.
    ``n_frames`` limits everything to the first frames (a partial render)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth = truth or derive_truth(scenario)
    n_frames = scenario.n_frames if n_frames is None else int(n_frames)
    truth = truth.cut(n_frames)
    tracks = write_tracks_file(out / TRACKS_FILE, zip(truth.frame, truth.stamp_ns, truth.person.tolist(), truth.x,
                                                      truth.y, truth.z_top, truth.posture))
    events = write_events_file(out / EVENTS_FILE, (ev.to_dict() for ev in truth.events))
    meta = out / META_FILE
    meta.write_text(json.dumps({
        "scenario": scenario.name,
        "description": scenario.spec.description,
        "seed": scenario.seed,
        "fps": scenario.fps,
        "n_frames": n_frames,
        "start_ns": scenario.start_ns,
        "start_local": scenario.spec.start_local,
        "date": scenario.spec.date,
        "residents": scenario.spec.residents,
        "dwell_window_s": DWELL_WINDOW_S,
        "long_lie_s": LONG_LIE_S,
        "people": [{"id": p.person_id, "resident": p.resident, "height_m": round(p.shape.height_m, 4),
                    "width": round(p.shape.width, 4)} for p in scenario.people],
    }, indent=2) + "\n", encoding="utf-8")
    return {"tracks": tracks, "events": events, "meta": meta}


def visit_reason(kind: str, local_hour: float) -> str:
    """Why people gather at a hot spot of ``kind`` at ``local_hour`` (0..24)."""
    h = local_hour % 24
    if kind == "table":
        if 6.0 <= h < 10.5:
            return "for breakfast"
        if 11.5 <= h < 14.5:
            return "for lunch"
        if 17.0 <= h < 21.5:
            return "for dinner"
        return "for a meal"
    if kind in ("sofa", "tv"):
        return "for tea" if 14.5 <= h < 17.5 else "for company"
    if kind == "kitchen":
        return "for coffee" if h < 12.0 else "for tea" if h < 17.5 else "for a drink"
    return "for a visit"


# ---------------------------------------------------------------------- helpers


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of True as [start, stop) frame pairs."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))


def _in_polygon(xy: np.ndarray, poly) -> np.ndarray:
    """(N, 2) points -> (N,) bool inside polygon (even-odd rule)."""
    p = np.asarray(poly, dtype=np.float64)
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(xy.shape[0], dtype=bool)
    for (x0, y0), (x1, y1) in zip(p, np.roll(p, -1, axis=0)):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < xc)
    return inside


def _dwell_intervals(scenario, states, in_volume):
    """(person id, hotspot, start frame, stop frame, mean xy) of stays of at least the dwell window."""
    window = int(round(DWELL_WINDOW_S * scenario.fps))
    out = []
    for person, st, inside in zip(scenario.people, states, in_volume):
        still = inside & ~st["moving"]
        for hs in scenario.room.hotspots:
            for a, b in _runs(still & _in_polygon(st["xy"], hs.polygon_m)):
                if b - a > window:
                    out.append((person.person_id, hs, a, b, st["xy"][a:b].mean(axis=0)))
    return out


def _visits(scenario, in_volume, dwells, window, stamps) -> list[Event]:
    residents = scenario.spec.residents
    resident_of = {p.person_id: p.resident for p in scenario.people}
    count = np.sum(in_volume, axis=0) if in_volume else np.zeros(scenario.n_frames, dtype=int)
    episodes = _runs(count > residents)
    out = []
    for ea, eb in episodes:
        best = None
        for i, (p1, h1, a1, b1, xy1) in enumerate(dwells):
            for p2, h2, a2, b2, _ in dwells[i + 1:]:
                if p1 == p2 or h1.name != h2.name:
                    continue
                start = max(a1, a2) + window
                if start < min(b1, b2) and ea <= start < eb and (best is None or start < best[0]):
                    best = (start, h1, p1, p2, xy1)
        if best is None:
            continue
        start, hs, p1, p2, xy = best
        visitor = p2 if resident_of.get(p1, True) and not resident_of.get(p2, True) else p1
        if resident_of.get(visitor, True):
            visitor = p2 if not resident_of.get(p2, True) else visitor
        out.append(_event("visit", visitor, start, int(stamps[start]), float(xy[0]), float(xy[1]), {
            "hotspot": hs.name,
            "reason": visit_reason(hs.kind, scenario.local_hour(start)),
            "people": ",".join(str(p) for p in sorted((p1, p2))),
        }))
    return out
