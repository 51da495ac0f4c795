"""Named floor areas (hot spots) and dwelling in them.

A hot spot is a polygon on the floor plan with a name ("dinner table"), a
label used in messages (defaults to the name) and a kind ("table", "sofa",
"tv", "bed", "door" ...). Draw it around where people stand or sit when they
use the place: the table *and its chairs*, the sofa and the floor in front.

Dwelling follows the seed paper: over the last ``window_s`` seconds, the
variance of the person's floor position about its mean (the mean squared
distance from the mean 2D location) is compared to a threshold. A dwell
starts when the person has been that still for a whole window and the mean
of the window lies inside a hot spot; it ends when they move (the variance
over the window exceeds a larger threshold, or their recent position is more
than ``move_radius_m`` from where they settled), leave (their recent
position is outside the hot spot) or the track is lost.

Pure math: no clock, no I/O; time is ``stamp_ns``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np


@dataclass(frozen=True)
class Hotspot:
    """A named floor polygon.

    name: unique name, used as identifier in events.
    polygon_m: (K, 2) float64, K >= 3, world floor (x, y), metres; any
        orientation, may be concave, must not self-intersect.
    label: human wording for messages ("the dinner table"); defaults to name.
    kind: free category ("table", "sofa", "tv", "bed", "door" ...).
    """

    name: str
    polygon_m: np.ndarray
    label: str = ""
    kind: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise ValueError("hot spot name must be a non-empty string")
        poly = np.asarray(self.polygon_m, dtype=np.float64)
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3:
            raise ValueError(f"hot spot {self.name!r}: polygon_m must be (K, 2) with K >= 3, got shape {poly.shape}")
        if not np.all(np.isfinite(poly)):
            raise ValueError(f"hot spot {self.name!r}: polygon_m has non-finite coordinates")
        if abs(polygon_area(poly)) <= 0:
            raise ValueError(f"hot spot {self.name!r}: polygon_m encloses no area")
        poly.setflags(write=False)
        object.__setattr__(self, "polygon_m", poly)
        object.__setattr__(self, "_edges", _edges(poly))
        if not self.label:
            object.__setattr__(self, "label", self.name)

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) or (2,) floor points -> (N,) bool (even-odd rule)."""
        return _inside(np.atleast_2d(np.asarray(xy, dtype=np.float64)), self._edges)

    def distance_m(self, x: float, y: float) -> float:
        """Floor distance from (x, y) to the polygon, metres: 0 inside it."""
        px, py = self.nearest_m(x, y)
        return float(math.hypot(px - x, py - y))

    def nearest_m(self, x: float, y: float) -> tuple[float, float]:
        """The polygon's floor point nearest (x, y): (x, y) itself inside it, else on its edge."""
        if bool(self.contains(np.array([x, y]))[0]):
            return float(x), float(y)
        a = self.polygon_m
        b = np.roll(a, -1, axis=0)
        ab = b - a
        t = np.clip(((x - a[:, 0]) * ab[:, 0] + (y - a[:, 1]) * ab[:, 1]) / (ab * ab).sum(axis=1), 0.0, 1.0)
        px, py = a[:, 0] + t * ab[:, 0], a[:, 1] + t * ab[:, 1]
        k = int(np.argmin(np.hypot(px - x, py - y)))
        return float(px[k]), float(py[k])

    @property
    def centroid_m(self) -> np.ndarray:
        """(2,) float64 area centroid of the polygon, world floor frame."""
        p = self.polygon_m
        q = np.roll(p, -1, axis=0)
        cross = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
        a = cross.sum() / 2.0
        return np.array([((p[:, 0] + q[:, 0]) * cross).sum(), ((p[:, 1] + q[:, 1]) * cross).sum()]) / (6.0 * a)


SEAT_KINDS: frozenset[str] = frozenset({"sofa", "table", "chair", "armchair", "bench", "bed"})
"""Hot spot kinds where people sit: a site that marks them tells where sitting is possible."""
BED_KINDS: frozenset[str] = frozenset({"sofa", "bed", "bench"})
"""Hot spot kinds people lie on: a site that marks them tells where lying above the floor is possible."""


def points_in_polygon(xy: np.ndarray, polygon_m: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test, vectorised over points and edges.

    xy: (N, 2) or (2,) points; polygon_m: (K, 2) vertices (closed
    implicitly). Returns (N,) bool. Points exactly on an edge may fall
    either side.
    """
    pts = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    poly = np.asarray(polygon_m, dtype=np.float64)
    if pts.shape[-1] != 2 or poly.ndim != 2 or poly.shape[1] != 2:
        raise ValueError(f"points must be (N, 2) and polygon (K, 2), got {pts.shape} and {poly.shape}")
    return _inside(pts, _edges(poly))


def _edges(poly: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per edge (i, i-1): x_i, y_i, y_(i-1), and dx/dy (0 for horizontal edges, which never straddle)."""
    xi, yi = poly[:, 0].copy(), poly[:, 1].copy()
    xj, yj = np.roll(xi, 1), np.roll(yi, 1)
    dy = yj - yi
    slope = np.divide(xj - xi, dy, out=np.zeros_like(dy), where=dy != 0)
    return xi, yi, yj, slope


def _inside(pts: np.ndarray, edges: tuple[np.ndarray, ...]) -> np.ndarray:
    xi, yi, yj, slope = edges
    x, y = pts[:, 0:1], pts[:, 1:2]
    straddles = (yi > y) != (yj > y)  # (N, K): edge crosses the horizontal line through the point
    x_cross = xi + slope * (y - yi)
    return (np.count_nonzero(straddles & (x < x_cross), axis=1) % 2) == 1


def polygon_area(polygon_m: np.ndarray) -> float:
    """Signed shoelace area of a (K, 2) polygon, m² (positive when counter-clockwise)."""
    p = np.asarray(polygon_m, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    return float((p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]).sum() / 2.0)


def hotspot_index(hotspots: Sequence[Hotspot], xy: np.ndarray) -> np.ndarray:
    """(N,) int: index of the first hot spot (in list order) containing each
    (N, 2) point, -1 where none does."""
    pts = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    out = np.full(len(pts), -1, dtype=np.int64)
    for i in range(len(hotspots) - 1, -1, -1):
        out[hotspots[i].contains(pts)] = i
    return out


def hotspot_at(hotspots: Sequence[Hotspot], x: float, y: float) -> Hotspot | None:
    """The first hot spot (in list order) containing the floor point, or None."""
    idx = int(hotspot_index(hotspots, np.array([[x, y]]))[0])
    return hotspots[idx] if idx >= 0 else None


def position_variance(xy: np.ndarray) -> float:
    """Mean squared distance of (N, 2) floor positions from their mean, m²."""
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0:
        raise ValueError(f"positions must be a non-empty (N, 2) array, got shape {pts.shape}")
    return float(((pts - pts.mean(axis=0)) ** 2).sum(axis=1).mean())


class PositionWindow:
    """Floor positions of one track over the last ``window_s`` seconds.

    Keeps one sample at or before the window start, so :attr:`span_s`
    reaches ``window_s`` exactly when the history is long enough. Samples
    live in numpy arrays (amortised O(1) append, slices without copies).
    """

    def __init__(self, *, window_s: float) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be positive, got {window_s}")
        self.window_ns = int(round(window_s * 1e9))
        self._t = np.zeros(64, dtype=np.int64)
        self._xy = np.zeros((64, 2), dtype=np.float64)
        self._lo = 0
        self._hi = 0

    def add(self, stamp_ns: int, x: float, y: float) -> None:
        stamp_ns = int(stamp_ns)
        if self._hi > self._lo and stamp_ns < self._t[self._hi - 1]:
            raise ValueError(f"stamp_ns {stamp_ns} is older than the previous sample {self._t[self._hi - 1]}")
        if self._hi == len(self._t):
            self._compact()
        self._t[self._hi] = stamp_ns
        self._xy[self._hi] = (x, y)
        self._hi += 1
        # Drop samples while the next one still reaches back to the window start.
        start = stamp_ns - self.window_ns
        drop = int(np.searchsorted(self._t[self._lo + 1: self._hi], start, side="right"))
        self._lo += drop

    def clear(self) -> None:
        self._lo = self._hi = 0

    def __len__(self) -> int:
        return self._hi - self._lo

    @property
    def span_s(self) -> float:
        """Time from the oldest kept sample to the newest, seconds."""
        return (self._t[self._hi - 1] - self._t[self._lo]) * 1e-9 if len(self) else 0.0

    @property
    def full(self) -> bool:
        """True when the samples cover the whole window."""
        return len(self) > 0 and self._t[self._hi - 1] - self._t[self._lo] >= self.window_ns

    @property
    def start_ns(self) -> int:
        """Stamp of the oldest kept sample."""
        if not len(self):
            raise ValueError("empty position window")
        return int(self._t[self._lo])

    def stamps(self) -> np.ndarray:
        """(N,) int64 stamps of the kept samples, oldest first (a view)."""
        return self._t[self._lo: self._hi]

    def positions(self, since_ns: int | None = None) -> np.ndarray:
        """(N, 2) float64 positions, oldest first, optionally only those at or after ``since_ns`` (a view)."""
        lo = self._lo
        if since_ns is not None:
            lo += int(np.searchsorted(self._t[self._lo: self._hi], since_ns, side="left"))
        return self._xy[lo: self._hi]

    def settled_since_ns(self, radius_m: float) -> int:
        """Stamp of the first sample after the last one farther than ``radius_m``
        from the window's mean: when the person arrived where they now are."""
        xy = self.positions()
        far = np.flatnonzero(np.hypot(*(xy - xy.mean(axis=0)).T) > radius_m)
        t = self.stamps()
        return int(t[far[-1] + 1]) if len(far) and far[-1] + 1 < len(t) else int(t[0])

    def variance_m2(self) -> float:
        """:func:`position_variance` of the window."""
        return position_variance(self.positions())

    def mean_xy(self, since_ns: int | None = None) -> np.ndarray:
        """(2,) mean position of the window (or of the samples since ``since_ns``)."""
        xy = self.positions(since_ns)
        if len(xy) == 0:
            xy = self.positions()[-1:]
        return xy.mean(axis=0)

    def _compact(self) -> None:
        n = len(self)
        if n * 2 > len(self._t):  # more than half in use: grow
            t = np.zeros(2 * len(self._t), dtype=np.int64)
            xy = np.zeros((2 * len(self._t), 2), dtype=np.float64)
        else:
            t, xy = self._t, self._xy
        t[:n] = self._t[self._lo: self._hi]
        xy[:n] = self._xy[self._lo: self._hi]
        self._t, self._xy, self._lo, self._hi = t, xy, 0, n


@dataclass(frozen=True)
class DwellChange:
    """A dwell starting or ending.

    kind: ``"dwell_start"`` or ``"dwell_end"``.
    hotspot: where. stamp_ns: the frame that decided it.
    start_ns: when the person settled there: the first sample of the still
        window after the last one farther than ``still_std_m`` from its mean.
    x, y: mean floor position over the window, metres.
    reason: for ends, ``"moved"``, ``"left"`` or ``"lost"``; empty for starts.
    """

    kind: str
    hotspot: Hotspot
    stamp_ns: int
    start_ns: int
    x: float
    y: float
    reason: str = ""

    @property
    def duration_s(self) -> float:
        return (self.stamp_ns - self.start_ns) * 1e-9


class DwellDetector:
    """Dwelling of one track in a list of hot spots.

    hotspots: the hot spots, first match wins where they overlap.
    window_s: length of the still window (the seed paper's period).
    still_std_m: a dwell starts when ``sqrt(variance)`` over a full window is
        at or below this.
    move_std_m: a dwell ends when it rises above this (larger than
        ``still_std_m``, so tracker jitter does not toggle the dwell).
    move_radius_m: a dwell ends when the recent position is farther than
        this from the mean position at the dwell's start (walking away ends
        a dwell within a second, long before the window's variance grows).
    recent_s: the "recent position" is the mean over this many seconds.
    """

    def __init__(
        self,
        *,
        hotspots: Iterable[Hotspot],
        window_s: float = 10.0,
        still_std_m: float = 0.15,
        move_std_m: float = 0.30,
        move_radius_m: float = 0.5,
        recent_s: float = 0.5,
    ) -> None:
        self.hotspots = tuple(hotspots)
        for h in self.hotspots:
            if not isinstance(h, Hotspot):
                raise ValueError(f"hotspots must be Hotspot instances, got {type(h).__name__}")
        if not still_std_m > 0:
            raise ValueError(f"still_std_m must be positive, got {still_std_m}")
        if not move_std_m >= still_std_m:
            raise ValueError(f"move_std_m ({move_std_m}) must be at least still_std_m ({still_std_m})")
        if not move_radius_m > 0:
            raise ValueError(f"move_radius_m must be positive, got {move_radius_m}")
        if not recent_s > 0:
            raise ValueError(f"recent_s must be positive, got {recent_s}")
        self.window = PositionWindow(window_s=window_s)
        self.still_radius_m = float(still_std_m)
        self.still_var_m2 = float(still_std_m) ** 2
        self.move_var_m2 = float(move_std_m) ** 2
        self.move_radius_m = float(move_radius_m)
        self.recent_ns = int(round(recent_s * 1e9))
        self.current: Hotspot | None = None
        self.start_ns = 0
        self.anchor_xy = np.zeros(2)

    def update(self, stamp_ns: int, x: float, y: float) -> list[DwellChange]:
        """Add one position; returns the dwell changes it causes (0, 1 or 2)."""
        stamp_ns = int(stamp_ns)
        self.window.add(stamp_ns, x, y)
        changes: list[DwellChange] = []
        var = self.window.variance_m2() if self.window.full else None
        if self.current is not None:
            recent = self.window.mean_xy(stamp_ns - self.recent_ns)
            reason = ""
            if (var is not None and var > self.move_var_m2) or np.hypot(*(recent - self.anchor_xy)) > self.move_radius_m:
                reason = "moved"
            elif not bool(self.current.contains(recent)[0]):
                reason = "left"
            if reason:
                changes.append(self._end(stamp_ns, recent, reason))
        if self.current is None and var is not None and var <= self.still_var_m2:
            mean = self.window.mean_xy()
            spot = hotspot_at(self.hotspots, mean[0], mean[1])
            # The recent position must agree, or a dwell that just ended (moved, drifted out) would restart.
            recent = self.window.mean_xy(stamp_ns - self.recent_ns)
            settled_here = np.hypot(*(recent - mean)) <= 0.5 * self.move_radius_m
            if spot is not None and settled_here and bool(spot.contains(recent)[0]):
                self.current, self.start_ns = spot, self.window.settled_since_ns(self.still_radius_m)
                self.anchor_xy = mean
                changes.append(DwellChange("dwell_start", spot, stamp_ns, self.start_ns, float(mean[0]), float(mean[1])))
        return changes

    def lost(self, stamp_ns: int) -> list[DwellChange]:
        """The track is gone: end any dwell and forget the history."""
        changes = []
        if self.current is not None and len(self.window):
            changes.append(self._end(int(stamp_ns), self.window.positions()[-1], "lost"))
        self.current = None
        self.window.clear()
        return changes

    def _end(self, stamp_ns: int, xy: np.ndarray, reason: str) -> DwellChange:
        change = DwellChange("dwell_end", self.current, stamp_ns, self.start_ns, float(xy[0]), float(xy[1]), reason)
        self.current = None
        return change
