"""Who is who: long-term appearance of each person, identity through crossings and absences.

The tracker follows bodies (its *targets*, numbered as it creates them); this
module gives each body the identity of a person (its *label*, the track id
users see) and keeps a long-term appearance model per person, after the
second seed paper's height and normalised colour histograms:

* **Asking**: each frame, for the targets due (every ``1 / rate_hz`` seconds,
  and at once for a new one) it computes per camera a
  :class:`~common.messages.PersonRegion`: the image boxes of the body's head,
  torso and legs bands and the body's distance from the camera. The camera
  worker answers with colour histograms of its foreground in those boxes
  (:mod:`common.appearance`), leaving out what nearer people hide. A band is
  also left out here when a *farther* person's box covers much of it (their
  colours would show through around the body).
* **Learning**: a person's model (per band, a histogram averaged over the
  clean views; the standing height) takes a frame's views only while the
  body reads standing, and, for a few seconds after the body came close to
  another, only when the views agree with the model: the labels of two
  people who crossed may have swapped, and a model must not learn the other
  person's clothes.
* **A label for a new body**: a target gets a label when the tracker first
  confirms it: a person lost within ``reid_window_s`` whose model its views
  match (clearly better than any other's), or whose body was lost just
  there a moment ago (a track that broke up, or merged into a neighbour's
  and split off again), gets their label back; otherwise a new label.
  Residents enrolled in the site file are such lost people that never
  expire.
* **Swaps**: two labelled bodies that were close and are now apart are
  compared with the other's model too; when swapping their labels explains
  their views better, frame after frame, the labels (and models) swap.

Time comes from the frame stamps only.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from common import appearance
from common.appearance import AppearanceModel, Resident, View
from common.camera import Camera
from common.messages import Appearance, PersonRegion
from common.settings import NON_NEGATIVE, Settings, declared
from common.site import IdentitySettings

__all__ = ["IdentityKeeper", "IdentityParams"]

log = logging.getLogger("voxelwatch.identity")

_N_BANDS = len(appearance.BANDS)


_SHARE = dict(ge=0.0, le=1.0)   # [0, 1]


class IdentityParams(Settings):
    """Settings of :class:`IdentityKeeper` (defaults in brackets).

    rate_hz: descriptor requests per body per second, to every camera [3 Hz:
        about 450 bytes per person per second per camera on the wire].
    body_radius_m: half-width of the floor square a band box covers [0.22 m].
    min_pixels: fewest foreground pixels of a band view that count [40].
    min_visible: least share of a band's box that no nearer person hides [0.7].
    max_farther_overlap: most of a band's box a farther person's box may cover
        [0.15].
    learn_rate: weight of one frame's views in a model once it has more than
        ``1 / learn_rate`` frames [0.05].
    settle_s: after two bodies came within ``close_m`` of each other, their
        models learn only views that agree with them (distance below
        ``agree``) for this long [3 s; 1.0 m; 0.3].
    reid_window_s: how long a lost person can come back under their own
        label [600 s].
    reid_distance: largest appearance distance (mean Hellinger over bands) at
        which a new body takes a lost person's label [0.3].
    reid_margin: the best lost person must beat the next by this much [0.08].
    near_s, near_m: a lost person whose body was lost less than ``near_s``
        ago within ``near_m`` of the new body (or whose body merged into a
        neighbour now within ``near_m``) is taken at a looser distance,
        ``near_distance`` [4 s, 1.2 m, 0.45], and with no views at all when
        they are the only such person.
    height_tolerance_m, height_weight, height_frames: the standing height of a
        body (the median of its standing tops, once it has ``height_frames``
        of them) and a person's model that lie further apart than the
        tolerance add ``height_weight`` per metre beyond it to their
        appearance distance [0.08 m, 2.0 per m: 10 cm beyond adds 0.2, which
        takes a colour match to a stranger's distance; 5 frames]: a child in
        the clothes of an adult who left is not that adult. Two lost people
        whose heights differ so are never one person lost twice.
    swap_margin, swap_evidence: a frame adds the amount by which the swapped
        labels explain the two bodies' views better, less the margin; the
        labels swap once the sum passes the evidence [0.05, 0.6].
    min_model_frames: frames a model needs before it is compared [5].
    decide_s, decide_views: a confirmed body that a lost person could be waits
        for its label (and is not reported) until its torso has been seen in
        views weighing ``decide_views`` in all (about that many clear camera
        views) or for ``decide_s``, whichever comes first [0.5 s, 3]; it is
        asked for views every frame meanwhile. With nobody lost it is
        labelled at once.
    same_person: two lost people whose models lie closer than this are taken
        for one person lost twice (a track that broke up more than once): the
        runner-up does not make the best match ambiguous [0.2].

    A mature model learns only views within ``agree`` of it. A body whose views
    lie far from its person's model keeps its label all the same: away from
    everyone, a person's own views drift from their model as they cross the room
    (other cameras, other light, the door's views) as far as another person's
    lie, and opening the identity again then gave the same person a new label
    more often than it caught a track that slid onto someone else (those the
    swap test catches while the two are close).
    """

    rate_hz: float = declared(IdentitySettings, "rate_hz")   # the site file's [identity] declares it
    body_radius_m: float = Field(0.22, gt=0.0, allow_inf_nan=False)
    min_pixels: int = Field(40, ge=0)
    min_visible: float = Field(0.7, **_SHARE)
    max_farther_overlap: float = Field(0.15, **_SHARE)
    learn_rate: float = Field(0.05, gt=0.0, le=1.0)
    settle_s: float = Field(3.0, **NON_NEGATIVE)
    close_m: float = Field(1.0, **NON_NEGATIVE)
    agree: float = Field(0.3, **_SHARE)
    reid_window_s: float = declared(IdentitySettings, "reid_window_s")
    reid_distance: float = Field(0.3, **_SHARE)
    reid_margin: float = Field(0.08, **_SHARE)
    near_s: float = Field(4.0, **NON_NEGATIVE)
    near_m: float = Field(1.2, **NON_NEGATIVE)
    near_distance: float = Field(0.45, **_SHARE)
    height_tolerance_m: float = Field(0.08, **NON_NEGATIVE)
    height_weight: float = Field(2.0, **NON_NEGATIVE)
    height_frames: int = Field(5, ge=1)
    swap_margin: float = Field(0.05, **_SHARE)
    swap_evidence: float = Field(0.6, **NON_NEGATIVE)
    min_model_frames: int = Field(5, ge=0)
    decide_s: float = Field(0.5, **NON_NEGATIVE)
    decide_views: float = Field(3.0, **NON_NEGATIVE)
    same_person: float = Field(0.2, **NON_NEGATIVE)


@dataclass
class _Person:
    label: int
    model: AppearanceModel
    name: str | None = None


@dataclass
class _Body:
    label: int  # negative until the tracker first confirms the target
    next_ask_ns: int = -(2**62)
    views: deque = field(default_factory=lambda: deque(maxlen=16))  # recent (stamp, View)
    view: View | None = None  # this frame's
    xy: tuple[float, float] = (0.0, 0.0)
    stamp_ns: int = 0
    close_until_ns: int = -(2**62)
    close_to: set[int] = field(default_factory=set)  # targets this one came close to recently
    born_ns: int = 0
    confirmed_ns: int | None = None  # when the tracker first confirmed it
    fresh_until_ns: int = 0  # a new label that may yet give way to a neighbour's or a lost person's
    tops: deque = field(default_factory=lambda: deque(maxlen=15))  # standing tops of the last second or so (metres)


@dataclass
class _Lost:
    person: _Person
    xy: tuple[float, float]
    lost_ns: int
    partner: int | None  # target id of the body it merged into, if any


class IdentityKeeper:
    """Labels for the tracker's targets, appearance models for the people behind them.

    cameras: camera id -> full-resolution camera (for the regions).
    params: :class:`IdentityParams`.
    residents: enrolled people; their labels come first (1, 2, ...).
    """

    def __init__(self, cameras: Mapping[str, Camera], params: IdentityParams | None = None,
                 residents: Sequence[Resident] = ()) -> None:
        self.cameras = dict(cameras)
        self.p = params if params is not None else IdentityParams()
        self._bodies: dict[int, _Body] = {}
        self._people: dict[int, _Person] = {}
        self._lost: dict[int, _Lost] = {}
        self._labels = itertools.count(1)
        self._asked: dict[str, dict[int, np.ndarray]] = {}  # camera -> target -> usable bands
        self._swap_evidence: dict[tuple[int, int], float] = {}
        self.swaps = 0
        self.reclaimed = 0
        for r in residents:
            label = next(self._labels)
            person = _Person(label=label, model=r.model, name=r.name)
            self._lost[label] = _Lost(person=person, xy=(math.nan, math.nan), lost_ns=2**62, partner=None)

    def restore(self, people: Sequence[tuple[int, str | None, tuple[float, float], AppearanceModel | None]],
                stamp_ns: int) -> None:
        """People a server watched before its restart, ``(label, name, (x, y), model)``: lost
        right there at ``stamp_ns``, so the first body confirmed where each was takes their label
        back (an enrolled resident keeps the enrolled name); new labels come after theirs."""
        for label, name, xy, model in people:
            lost = self._lost.get(label)
            if lost is not None:
                if model is not None:
                    lost.person.model = model
                lost.xy, lost.lost_ns, lost.partner = (float(xy[0]), float(xy[1])), int(stamp_ns), None
                continue
            if label in self._people:
                continue
            person = _Person(label=int(label), model=model if model is not None else AppearanceModel(), name=name)
            self._lost[label] = _Lost(person=person, xy=(float(xy[0]), float(xy[1])), lost_ns=int(stamp_ns), partner=None)
        top = max((int(label) for label, *_ in people), default=0)
        self._labels = itertools.count(max(next(self._labels), top + 1))

    # ------------------------------------------------------------------ per frame

    def assign(self, estimates: Sequence, looks: Mapping[str, Iterable[Appearance]], stamp_ns: int) -> dict[int, int]:
        """Take this frame's descriptors and give every target its label.

        estimates: the tracker's estimates (``id`` is the target id; ``x``, ``y``,
            ``confirmed``). looks: camera id -> the descriptors that came with its mask.
        Returns {target id: label} for every live target; labels change only for
        targets the tracker just confirmed (and for swapped pairs). A label
        stays negative while the body waits for its identity (see
        ``IdentityParams.decide_s``): such a body is not reported yet.
        """
        live = {int(e.id): e for e in estimates}
        for tid in [t for t in self._bodies if t not in live]:
            self._forget(tid, live, stamp_ns)
        for tid, est in live.items():
            body = self._bodies.get(tid)
            if body is None:
                body = self._bodies[tid] = _Body(label=-tid, born_ns=stamp_ns)
                self._ask_partners(est)
            body.xy, body.stamp_ns, body.view = (float(est.x), float(est.y)), stamp_ns, None
        self._take_looks(looks, stamp_ns)
        self._mark_close(live, stamp_ns)
        for tid, est in sorted(live.items()):
            body = self._bodies[tid]
            if body.label < 0 and est.confirmed:
                if body.confirmed_ns is None:
                    body.confirmed_ns = stamp_ns
                self._label_new(tid, body, stamp_ns)
            elif stamp_ns < body.fresh_until_ns and body.view is not None:
                fresh = body.label
                view = self._recent_view(body)
                if self._exchange(body, view, stamp_ns):
                    del self._people[fresh]  # a label nobody needs any more
                    body.fresh_until_ns = 0
                elif (chosen := self._choose(tid, body, view, stamp_ns, loose=False)) is not None:
                    log.info("body %d is person %d after all (was given %d)", tid, chosen, fresh)
                    del self._people[fresh]  # a label nobody needs any more
                    self._reclaim(body, chosen)
                    body.fresh_until_ns = 0
        self._check_swaps(live, stamp_ns)
        self._expire(stamp_ns)
        return {tid: self._bodies[tid].label for tid in live}

    def learn(self, estimates: Sequence, standing: Mapping[int, float], stamp_ns: int) -> None:
        """Let each labelled, confirmed body's person learn this frame's views.

        standing: target id -> standing height (metres) for the bodies that read
        standing this frame; only those learn.
        """
        p = self.p
        for est in estimates:
            tid = int(est.id)
            body = self._bodies.get(tid)
            if body is not None and tid in standing:
                body.tops.append(float(standing[tid]))
            if body is None or body.label < 0 or not est.confirmed or tid not in standing:
                continue
            person = self._people[body.label]
            view = body.view
            if view is None or view.empty:
                continue
            if person.model.mature(p.min_model_frames):
                d = person.model.distance(view)
                if d is None:
                    continue
                if d > p.agree:
                    continue  # a mature model learns only views that agree with it
            person.model.learn(view, p.learn_rate, standing[tid])

    def regions(self, estimates: Sequence, stamp_ns: int) -> dict[str, list[PersonRegion]]:
        """Per camera, the regions of the targets due for a descriptor (sent as a
        :class:`~common.messages.LookRequest`); cameras with none are left out."""
        p = self.p
        due = []
        for est in estimates:
            body = self._bodies.get(int(est.id))
            if body is not None and (stamp_ns >= body.next_ask_ns or body.label < 0):
                due.append(est)
                body.next_ask_ns = stamp_ns + int(round(1e9 / p.rate_hz))
        if not due:
            return {}
        everyone = list(estimates)
        out: dict[str, list[PersonRegion]] = {}
        for cam_id, cam in self.cameras.items():
            boxes, depths = _band_boxes(cam, everyone, p.body_radius_m)
            asked = self._asked.setdefault(cam_id, {})
            regions = []
            for est in due:
                i = everyone.index(est)
                if depths[i] is None or not any(_area(b) for b in boxes[i]):
                    continue
                usable = np.array([_farther_overlap(boxes[i][k], i, boxes, depths) <= p.max_farther_overlap
                                   for k in range(_N_BANDS)])
                asked[int(est.id)] = usable
                regions.append(PersonRegion(track=int(est.id), depth_m=float(depths[i]),
                                            boxes=[tuple(int(v) for v in b) for b in boxes[i]]))
            if regions:
                out[cam_id] = regions
        return out

    # ------------------------------------------------------------------ queries

    def name_of(self, label: int) -> str | None:
        """The enrolled name of the person under ``label`` (in view or lost), else None."""
        person = self._person(label)
        return person.name if person is not None else None

    def model_of(self, label: int) -> AppearanceModel | None:
        """The model of the person under ``label`` (in view or lost), else None."""
        person = self._person(label)
        return person.model if person is not None else None

    def models(self) -> dict[int, AppearanceModel]:
        """Every person's model by label, in view or lost (enrolled residents not yet
        seen included), in label order."""
        people = {**{label: lost.person for label, lost in self._lost.items()}, **self._people}
        return {label: people[label].model for label in sorted(people)}

    # ------------------------------------------------------------------ internals

    def _person(self, label: int) -> _Person | None:
        person = self._people.get(label)
        if person is None and label in self._lost:
            person = self._lost[label].person
        return person

    def _take_looks(self, looks: Mapping[str, Iterable[Appearance]], stamp_ns: int) -> None:
        p = self.p
        sums: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for cam_id, items in looks.items():
            asked = self._asked.get(cam_id, {})
            for look in items:
                tid = int(look.track)
                usable = asked.pop(tid, None)
                if tid not in self._bodies or usable is None:
                    continue
                hist = np.frombuffer(look.hist, dtype=np.uint8).reshape(_N_BANDS, appearance.N_BINS).astype(np.float64)
                acc = sums.setdefault(tid, (np.zeros((_N_BANDS, appearance.N_BINS)), np.zeros(_N_BANDS)))
                for k in range(_N_BANDS):
                    if not usable[k] or look.pixels[k] < p.min_pixels or look.visible[k] < p.min_visible:
                        continue
                    total = hist[k].sum()
                    if total <= 0:
                        continue
                    w = min(1.0, look.pixels[k] / 400.0) * float(look.visible[k])
                    acc[0][k] += w * hist[k] / total
                    acc[1][k] += w
        for tid, (h, w) in sums.items():
            body = self._bodies[tid]
            norm = np.where(w > 0, w, 1.0)[:, None]
            view = View(hist=h / norm, weight=np.minimum(w, 1.0))
            if not view.empty:
                body.view = view
                body.views.append((stamp_ns, view))

    def _mark_close(self, live: Mapping[int, object], stamp_ns: int) -> None:
        p = self.p
        until = stamp_ns + int(round(p.settle_s * 1e9))
        for a, b in itertools.combinations(sorted(live), 2):
            ba, bb = self._bodies[a], self._bodies[b]
            if math.dist(ba.xy, bb.xy) < p.close_m:
                ba.close_until_ns = bb.close_until_ns = until
                ba.close_to.add(b)
                bb.close_to.add(a)
        for lost in self._lost.values():
            partner = self._bodies.get(lost.partner) if lost.partner is not None else None
            if partner is not None and stamp_ns - lost.lost_ns < 60e9:
                partner.close_until_ns = max(partner.close_until_ns, until)  # two people in one body
        for body in self._bodies.values():
            if stamp_ns >= body.close_until_ns:
                body.close_to.clear()

    def _recent_view(self, body: _Body) -> View | None:
        """The body's views so far (the last few), averaged."""
        return _view_since(body, -(2**62))

    def _label_new(self, tid: int, body: _Body, stamp_ns: int) -> None:
        """Give a body the tracker confirmed its label: a lost person's, or a new one; or
        wait for more views while a lost person could be it."""
        p = self.p
        view = self._recent_view(body)
        seen = sum(v.weight[1] for _, v in body.views)
        waited = stamp_ns - body.confirmed_ns >= p.decide_s * 1e9
        candidates = any(lost.person.model.mature(1) or self._near(lost, body, stamp_ns) for lost in self._lost.values())
        if candidates and seen < p.decide_views and not waited:
            return
        if view is not None and self._exchange(body, view, stamp_ns):
            return
        chosen = self._choose(tid, body, view, stamp_ns, loose=True)
        if chosen is not None:
            self._reclaim(body, chosen)
            log.info("person %d is back (body %d at %.2f, %.2f)", chosen, tid, *body.xy)
        else:
            label = next(self._labels)
            self._people[label] = _Person(label=label, model=AppearanceModel())
            body.label = label
            body.fresh_until_ns = stamp_ns + int(round(p.near_s * 1e9))
        if view is not None:
            self._people[body.label].model.learn(view, p.learn_rate, None)

    def _choose(self, tid: int, body: _Body, view: View | None, stamp_ns: int, *, loose: bool) -> int | None:
        """The lost person ``body`` is, or None. ``loose``: a person lost right there
        is taken at the looser distance (and alone, without views)."""
        p = self.p
        scored = []
        height = self._height_of(body)
        for label, lost in self._lost.items():
            d = lost.person.model.distance(view) if view is not None else None
            if d is not None:
                d += self._height_gap(height, lost.person.model)
            scored.append((label, loose and self._near(lost, body, stamp_ns), d))
        chosen = None
        with_d = sorted((d, label, near) for label, near, d in scored if d is not None)
        if with_d:
            d0, label0, near0 = with_d[0]
            best_model = self._lost[label0].person.model
            best = best_model.as_view()
            rivals = [(d, near) for d, label, near in with_d[1:]
                      if _or_far(self._lost[label].person.model.distance(best)) >= p.same_person
                      or self._height_gap(self._model_height(best_model), self._lost[label].person.model) > 0]
            d1 = rivals[0][0] if rivals else math.inf
            others_near = any(near for _, near in rivals)
            if d0 <= (p.near_distance if near0 else p.reid_distance) and (
                    d1 - d0 >= p.reid_margin or (near0 and not others_near)):
                chosen = label0
        elif view is None:
            near_only = [label for label, near, _ in scored if near]
            if len(near_only) == 1:
                chosen = near_only[0]
        if log.isEnabledFor(logging.DEBUG):
            log.debug("body %d at (%.2f, %.2f) with %s views; lost people (label, near, distance): %s -> %s",
                      tid, *body.xy, "no" if view is None else "some",
                      [(label, near, None if d is None else round(d, 3)) for label, near, d in scored], chosen)
        return chosen

    def _height_of(self, body: _Body) -> float | None:
        """The body's standing height (median of its last 15 standing tops), None before ``height_frames``."""
        if len(body.tops) < self.p.height_frames:
            return None
        return float(np.median(body.tops))

    def _model_height(self, model: AppearanceModel) -> float | None:
        """A person's learnt standing height, None before ``height_frames`` frames taught it."""
        if model.height_frames < self.p.height_frames or not math.isfinite(model.height_m):
            return None
        return float(model.height_m)

    def _height_gap(self, height: float | None, model: AppearanceModel) -> float:
        """What a standing height ``height`` adds to its appearance distance from ``model``
        (0 when either height is unknown or they agree within the tolerance)."""
        known = self._model_height(model)
        if height is None or known is None:
            return 0.0
        return self.p.height_weight * max(0.0, abs(height - known) - self.p.height_tolerance_m)

    def _ask_partners(self, est) -> None:
        """A new body beside a body a lost person merged into: ask for the neighbour's views
        at once too, to tell which of the two is which."""
        for lost in self._lost.values():
            partner = self._bodies.get(lost.partner) if lost.partner is not None else None
            if partner is not None and math.dist(partner.xy, (float(est.x), float(est.y))) < self.p.near_m:
                partner.next_ask_ns = -(2**62)

    def _exchange(self, body: _Body, view: View, stamp_ns: int) -> bool:
        """A body split off a neighbour that a lost person's body had merged into: when
        the neighbour's own person explains the new body's views better, and the lost
        person the neighbour's (the tracker kept the wrong one on the neighbour), the
        new body takes the neighbour's label and the neighbour the lost person's."""
        p = self.p
        for label, lost in self._lost.items():
            partner = self._bodies.get(lost.partner) if lost.partner is not None else None
            if partner is None or partner.label < 0 or not self._near(lost, body, stamp_ns):
                continue
            pview = _view_since(partner, body.born_ns)
            mine, theirs = lost.person.model, self._people[partner.label].model
            if pview is None or not (mine.mature(p.min_model_frames) and theirs.mature(p.min_model_frames)):
                continue
            d = [mine.distance(view), theirs.distance(pview), theirs.distance(view), mine.distance(pview)]
            if any(x is None for x in d):
                continue
            if d[2] + d[3] + p.swap_margin < d[0] + d[1] and d[2] <= p.near_distance:
                log.info("person %d split off person %d's body: labels exchanged", label, partner.label)
                body.label = partner.label
                self._reclaim(partner, label)
                self.swaps += 1
                return True
        return False

    def _reclaim(self, body: _Body, label: int) -> None:
        lost = self._lost.pop(label)
        self._people[label] = lost.person
        body.label = label
        self.reclaimed += 1

    def _near(self, lost: _Lost, body: _Body, stamp_ns: int) -> bool:
        p = self.p
        if stamp_ns - lost.lost_ns > p.near_s * 1e9 or stamp_ns < lost.lost_ns:
            return False
        if lost.partner is not None and lost.partner in self._bodies:
            if math.dist(self._bodies[lost.partner].xy, body.xy) < p.near_m:
                return True
        return math.dist(lost.xy, body.xy) < p.near_m

    def _forget(self, tid: int, live: Mapping[int, object], stamp_ns: int) -> None:
        body = self._bodies.pop(tid)
        for asked in self._asked.values():
            asked.pop(tid, None)
        if body.label < 0:
            return
        person = self._people.pop(body.label)
        partner = None
        nearest = math.inf
        for other, ob in self._bodies.items():
            if other in live:
                d = math.dist(ob.xy, body.xy)
                if d < 0.5 and d < nearest:
                    partner, nearest = other, d
        self._lost[body.label] = _Lost(person=person, xy=body.xy, lost_ns=stamp_ns, partner=partner)

    def _expire(self, stamp_ns: int) -> None:
        window = self.p.reid_window_s * 1e9
        for label in [key for key, lost in self._lost.items() if lost.person.name is None and stamp_ns - lost.lost_ns > window]:
            del self._lost[label]

    def _check_swaps(self, live: Mapping[int, object], stamp_ns: int) -> None:
        p = self.p
        seen: set[tuple[int, int]] = set()
        for a in sorted(live):
            ba = self._bodies[a]
            for b in sorted(ba.close_to):
                if b <= a or b not in live:
                    continue
                key = (a, b)
                seen.add(key)
                bb = self._bodies[b]
                if ba.label < 0 or bb.label < 0 or ba.view is None or bb.view is None:
                    continue
                if math.dist(ba.xy, bb.xy) < p.close_m:
                    continue  # still together: their views mix
                ma, mb = self._people[ba.label].model, self._people[bb.label].model
                if not (ma.mature(p.min_model_frames) and mb.mature(p.min_model_frames)):
                    continue
                d = [ma.distance(ba.view), mb.distance(bb.view), ma.distance(bb.view), mb.distance(ba.view)]
                if any(x is None for x in d):
                    continue
                gain = (d[0] + d[1]) - (d[2] + d[3]) - p.swap_margin
                e = max(0.0, self._swap_evidence.get(key, 0.0) + gain)
                if e >= p.swap_evidence:
                    log.info("persons %d and %d had swapped bodies: swapped back", ba.label, bb.label)
                    ba.label, bb.label = bb.label, ba.label
                    self.swaps += 1
                    e = 0.0
                self._swap_evidence[key] = e
        self._swap_evidence = {k: v for k, v in self._swap_evidence.items() if k in seen}


def _or_far(d: float | None) -> float:
    """A distance, or 1.0 (as far as two histograms lie) when there is none to tell."""
    return 1.0 if d is None else d


def _view_since(body: _Body, since_ns: int) -> View | None:
    """The body's views from ``since_ns`` on, averaged (None when there are none)."""
    views = [v for t, v in body.views if t >= since_ns]
    if not views:
        return None
    h = sum(v.weight[:, None] * v.hist for v in views)
    w = sum(v.weight for v in views)
    return View(hist=h / np.where(w > 0, w, 1.0)[:, None], weight=np.minimum(w, 1.0))


def _band_boxes(cam: Camera, estimates: Sequence, radius_m: float):
    """Per estimate, its band boxes in ``cam`` (full-resolution pixels, clipped; empty
    ``(0, 0, 0, 0)`` when out of view) and its distance from the camera (None when its
    body's centre projects nowhere)."""
    n = len(estimates)
    corners = []
    for est in estimates:
        top = max(float(est.z_top_m), 0.3)
        for lo, hi in appearance.BAND_FRACTIONS:
            for x, y, z in itertools.product((est.x - radius_m, est.x + radius_m), (est.y - radius_m, est.y + radius_m),
                                             (lo * top, hi * top)):
                corners.append((x, y, z))
    pts = np.asarray(corners, dtype=np.float64).reshape(n, _N_BANDS, 8, 3)
    uv, valid = cam.project(pts.reshape(-1, 3))
    uv = uv.reshape(n, _N_BANDS, 8, 2)
    valid = valid.reshape(n, _N_BANDS, 8)
    centre = cam.center
    boxes, depths = [], []
    for i, est in enumerate(estimates):
        person = []
        for k in range(_N_BANDS):
            if not valid[i, k].all():
                person.append((0, 0, 0, 0))  # partly off the image or behind: no clean view
                continue
            x0, y0 = np.floor(uv[i, k].min(axis=0)).astype(int)
            x1, y1 = np.ceil(uv[i, k].max(axis=0)).astype(int) + 1
            box = (max(0, x0), max(0, y0), min(cam.width, x1), min(cam.height, y1))
            person.append(box if box[2] > box[0] and box[3] > box[1] else (0, 0, 0, 0))
        boxes.append(person)
        mid = np.array([est.x, est.y, 0.5 * max(float(est.z_top_m), 0.3)])
        depths.append(float(np.linalg.norm(mid - centre)) if valid[i].any() else None)
    return boxes, depths


def _area(box) -> int:
    return max(0, box[2] - box[0]) * max(0, box[3] - box[1])


def _farther_overlap(box, i: int, boxes, depths) -> float:
    """Largest share of ``box`` covered by one band box of a person farther than person ``i``."""
    area = _area(box)
    if area == 0:
        return 1.0
    worst = 0.0
    for j, other in enumerate(boxes):
        if j == i or depths[j] is None or depths[i] is None or depths[j] <= depths[i]:
            continue
        for b in other:
            w = min(box[2], b[2]) - max(box[0], b[0])
            h = min(box[3], b[3]) - max(box[1], b[1])
            if w > 0 and h > 0:
                worst = max(worst, w * h / area)
    return worst
