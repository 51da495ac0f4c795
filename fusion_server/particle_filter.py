"""The 2.5D particle filter that refines one person's floor position.

Seed paper 000, section 2.3. All foreground voxels are projected onto the
floor; the count of voxels in each column is the measurement. The state of a
particle is ``(x, y, alpha)``: the centre of a square box on the floor and
its half-size (the box spans ``2 * alpha + 1`` cells). With ``N(a)`` the
number of voxels in the columns of the box of half-size ``a`` cells around
the particle, ``h`` the highest column count (in voxels) in the inner box and

    F(a)  = N(a) / (h * (2a + 1)^2)                              fill ratio
    Fd(a) = (F(a + k) - F(a - k)) / (2k)
          ~ (N(a+k)/(2(a+k)+1)^2 - N(a-k)/(2(a-k)+1)^2) / (2kh)  its derivative

the likelihood is the paper's equation (5)

    L(a) = -F(a - k)^2 * sqrt(N(a + k)) * Fd(a).

A good box sits on one person: the inner box ``a - k`` is full (large
``F``), the ring out to ``a + k`` is empty floor (``F`` falls fast, ``-Fd``
large) and the person has real volume (``sqrt(N)`` outweighs specks). The
paper prints equation (3) with ``(2a + 1)`` where the box area
``(2a + 1)^2`` is meant (its own equation (4) and Figure 3 use the area);
this module uses the area.

Box sums come from a summed-area table and box maxima from a sparse table of
2^p x 2^p window maxima (four look-ups per box), both built once per frame
in :func:`floor_evidence`, so each particle costs O(1) and all particles are
evaluated in one vectorised pass.

State units: metres, world frame (``x``, ``y``) and metres for ``alpha``
(converted to whole cells for the box sums). Time comes in as ``stamp_ns``,
randomness as an injected ``np.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from common.settings import NON_NEGATIVE, Settings
from fusion_server.grid import FloorMaps, VoxelGrid

__all__ = [
    "FilterParams",
    "FloorEvidence",
    "ParticleFilter",
    "box_count",
    "effective_sample_size",
    "floor_evidence",
    "likelihood",
    "propagate",
    "systematic_resample",
]


@dataclass(frozen=True, eq=False)
class FloorEvidence:
    """Per-frame look-up tables over the floor count map, shared by every filter.

    integral: (ny + 2 pad + 1, nx + 2 pad + 1) int64 summed-area table of the
        zero-padded count map; ``integral[r, c]`` sums rows < r, columns < c.
    window_max: (levels, ny + 2 pad, nx + 2 pad) int32; ``window_max[p, r, c]``
        is the largest count in the 2^p x 2^p window whose first cell is ``(r, c)``.
    origin_xy_m: (2,) float64 world ``(x, y)`` of the floor map's corner.
    voxel_m: cell edge, metres.
    pad: cells of zero padding on every side.
    shape: (ny, nx) of the unpadded floor map.
    """

    integral: np.ndarray
    window_max: np.ndarray
    origin_xy_m: np.ndarray
    voxel_m: float
    pad: int
    shape: tuple[int, int]

    @property
    def max_half_cells(self) -> int:
        """Largest box half-size (cells) the tables can answer."""
        return self.pad - 1


def floor_evidence(floor: FloorMaps, grid: VoxelGrid, *, max_half_m: float) -> FloorEvidence:
    """Build the look-up tables for boxes of half-size up to ``max_half_m``.

    floor.count: (ny, nx) int32 voxels per column, indexed ``[j, i]``.
    max_half_m: the largest outer box half-size any particle will ask for
        (``alpha_max_m + k_m``).
    """
    if not max_half_m > 0:
        raise ValueError(f"max_half_m must be positive, got {max_half_m}")
    count = np.asarray(floor.count)
    ny, nx = grid.shape[1], grid.shape[0]
    if count.shape != (ny, nx):
        raise ValueError(f"FloorMaps.count has shape {count.shape}, the grid needs {(ny, nx)}")
    pad = int(np.ceil(max_half_m / grid.voxel_m - 1e-9)) + 1
    padded = np.zeros((ny + 2 * pad, nx + 2 * pad), dtype=np.int32)
    padded[pad : pad + ny, pad : pad + nx] = count
    integral = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1), dtype=np.int64)
    np.cumsum(np.cumsum(padded, axis=0, dtype=np.int64), axis=1, out=integral[1:, 1:])
    levels = int(np.floor(np.log2(2 * pad + 1))) + 1
    window_max = np.zeros((levels,) + padded.shape, dtype=np.int32)
    window_max[0] = padded
    for p in range(1, levels):
        s = 1 << (p - 1)
        prev = window_max[p - 1]
        rows = prev.copy()
        np.maximum(prev[:-s, :], prev[s:, :], out=rows[:-s, :])
        window_max[p] = rows
        np.maximum(rows[:, :-s], rows[:, s:], out=window_max[p][:, :-s])
    return FloorEvidence(
        integral=integral,
        window_max=window_max,
        origin_xy_m=np.asarray(grid.origin_m[:2], dtype=np.float64).copy(),
        voxel_m=float(grid.voxel_m),
        pad=pad,
        shape=(ny, nx),
    )


def likelihood(particles: np.ndarray, evidence: FloorEvidence, *, k_m: float) -> np.ndarray:
    """The paper's L(alpha) for every particle, clipped at zero.

    particles: (P, 3) float64 ``(x_m, y_m, alpha_m)``, world frame.
    k_m: the half-width of the ring between the inner and outer box, metres
        (at least one cell).
    Returns (P,) float64, >= 0; zero where the inner box is empty or the
    fill ratio grows outward (negative L).
    """
    n_in, n_out, h, r_in, r_out, k = _box_terms(particles, evidence, k_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        area_in = (2.0 * r_in + 1.0) ** 2
        area_out = (2.0 * r_out + 1.0) ** 2
        fill_in = n_in / (h * area_in)
        fill_d = (n_out / area_out - n_in / area_in) / (2.0 * k * h)
        lik = -(fill_in**2) * np.sqrt(n_out) * fill_d
    lik = np.where(h > 0, lik, 0.0)
    return np.maximum(lik, 0.0)


def box_count(particles: np.ndarray, evidence: FloorEvidence) -> np.ndarray:
    """(P,) int64 voxel count N(alpha) in each particle's own box."""
    j, i, a = _cells(particles, evidence)
    a = np.minimum(a, evidence.max_half_cells)
    return _box_sum(evidence.integral, j, i, a)


def propagate(
    particles: np.ndarray,
    dt_s: float,
    *,
    velocity_mps: np.ndarray | tuple[float, float] = (0.0, 0.0),
    position_noise_m: float,
    alpha_noise_m: float,
    alpha_range_m: tuple[float, float],
    rng: np.random.Generator,
) -> np.ndarray:
    """Move particles ``dt_s`` seconds forward: drift plus a random walk.

    particles: (P, 3) float64 ``(x_m, y_m, alpha_m)``; not modified.
    velocity_mps: (2,) drift in world ``(x, y)``, metres per second.
    position_noise_m / alpha_noise_m: standard deviation the random walk
        builds up over one second; a step of ``dt_s`` adds ``sqrt(dt_s)`` of it.
    alpha_range_m: (min, max) limits ``alpha`` is clipped to.
    Returns new (P, 3) float64.
    """
    out = np.array(particles, dtype=np.float64, copy=True)
    if dt_s <= 0:
        return out
    root = np.sqrt(dt_s)
    v = np.asarray(velocity_mps, dtype=np.float64)
    noise = rng.standard_normal((len(out), 3))
    out[:, 0] += v[0] * dt_s + noise[:, 0] * (position_noise_m * root)
    out[:, 1] += v[1] * dt_s + noise[:, 1] * (position_noise_m * root)
    out[:, 2] = np.clip(out[:, 2] + noise[:, 2] * (alpha_noise_m * root), alpha_range_m[0], alpha_range_m[1])
    return out


def systematic_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling: (P,) normalised weights -> (P,) intp indexes.

    One uniform offset, P evenly spaced pointers into the cumulative weights.
    """
    w = np.asarray(weights, dtype=np.float64)
    n = len(w)
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0  # guard against round-off
    return np.minimum(np.searchsorted(cumulative, positions, side="right"), n - 1).astype(np.intp)


def effective_sample_size(weights: np.ndarray) -> float:
    """1 / sum(w^2) of normalised weights."""
    w = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(w * w))


class FilterParams(Settings):
    """The bounds of :class:`ParticleFilter`'s keyword settings (described there), declared once."""

    n_particles: int = Field(200, ge=1)
    k_m: float = Field(0.1, gt=0.0, allow_inf_nan=False)
    alpha_range_m: tuple[float, float] = (0.15, 0.6)
    position_noise_m: float = Field(0.3, **NON_NEGATIVE)
    alpha_noise_m: float = Field(0.1, **NON_NEGATIVE)
    init_spread_m: float = Field(0.05, **NON_NEGATIVE)
    resample_below: float = Field(0.5, ge=0.0, le=1.0)
    max_dt_s: float = Field(0.5, gt=0.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _alpha_range(self) -> "FilterParams":
        lo, hi = self.alpha_range_m
        if not 0 < lo <= hi:
            raise ValueError(f"alpha_range_m must be 0 < min <= max, got {self.alpha_range_m}")
        return self


class ParticleFilter:
    """Particles, weights and generator of one target's 2.5D filter.

    Parameters (keyword; the settings are :class:`FilterParams`'s fields, declared there with their
    defaults and bounds):
    rng: the generator all randomness is drawn from.
    n_particles: particles per target (default 200).
    k_m: ring half-width of the likelihood (default 0.1 m: two 5 cm cells).
    alpha_range_m: (min, max) box half-size; default (0.15, 0.6) m spans a
        child's footprint to an adult lying down seen as a square.
    position_noise_m: random-walk standard deviation per second (default
        0.3 m: 8 cm per frame at 15 fps, enough for a change of pace).
    alpha_noise_m: the same for ``alpha`` (default 0.1 m).
    init_spread_m: spread of the initial particles around the start (0.05 m).
    resample_below: resample when the effective sample size falls below
        this fraction of ``n_particles`` (default 0.5).
    max_dt_s: longest time step the motion model is applied over (default
        0.5 s); after a longer gap (cameras lost, process paused) the drift
        and spread of a blind half second is all the filter assumes.
    """

    def __init__(self, x_m: float, y_m: float, alpha_m: float, *, rng: np.random.Generator, **settings) -> None:
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy Generator, got {type(rng).__name__}")
        p = FilterParams(**settings)
        lo, hi = p.alpha_range_m
        self.rng = rng
        self.k_m = p.k_m
        self.alpha_range_m = (lo, hi)
        self.position_noise_m = p.position_noise_m
        self.alpha_noise_m = p.alpha_noise_m
        self.resample_below = p.resample_below
        self.max_dt_s = p.max_dt_s
        n = p.n_particles
        self.particles = np.empty((n, 3), dtype=np.float64)
        self.particles[:, :2] = np.array([x_m, y_m], dtype=np.float64) + rng.standard_normal((n, 2)) * p.init_spread_m
        self.particles[:, 2] = np.clip(alpha_m + rng.standard_normal(n) * p.init_spread_m, lo, hi)
        self.weights = np.full(n, 1.0 / n)
        self.last_stamp_ns: int | None = None
        self.supported = False

    @property
    def max_half_m(self) -> float:
        """Outer box half-size the evidence tables must cover."""
        return self.alpha_range_m[1] + self.k_m

    def estimate(self) -> np.ndarray:
        """(3,) float64 weighted mean ``(x_m, y_m, alpha_m)``."""
        return self.weights @ self.particles

    def step(self, evidence: FloorEvidence, stamp_ns: int, velocity_mps=(0.0, 0.0), *,
             exclude_xy: np.ndarray | None = None, exclude_radius_m: float = 0.0) -> np.ndarray:
        """Propagate to ``stamp_ns``, weigh against the floor map, resample if needed.

        velocity_mps: (2,) drift of the target, metres per second.
        exclude_xy, exclude_radius_m: (E, 2) floor positions, world metres, of other people, and
            how close to them this target cannot stand: particles that near one weigh nothing
            (two bodies do not stand in one place), unless every particle that saw evidence is
            (then the evidence alone decides).
        Returns the new (3,) estimate. ``supported`` tells whether any particle
        saw evidence; without it the weights stay as they were.
        """
        stamp_ns = int(stamp_ns)
        if self.last_stamp_ns is not None and stamp_ns < self.last_stamp_ns:
            raise ValueError(f"stamp_ns {stamp_ns} is before the previous step's {self.last_stamp_ns}")
        if evidence.max_half_cells * evidence.voxel_m < self.max_half_m - 1e-9:
            raise ValueError(f"evidence covers boxes up to {evidence.max_half_cells} cells, the filter needs {self.max_half_m} m")
        dt_s = 0.0 if self.last_stamp_ns is None else (stamp_ns - self.last_stamp_ns) * 1e-9
        self.last_stamp_ns = stamp_ns
        self.particles = propagate(
            self.particles,
            min(dt_s, self.max_dt_s),
            velocity_mps=velocity_mps,
            position_noise_m=self.position_noise_m,
            alpha_noise_m=self.alpha_noise_m,
            alpha_range_m=self.alpha_range_m,
            rng=self.rng,
        )
        weights = self.weights * likelihood(self.particles, evidence, k_m=self.k_m)
        if exclude_xy is not None and len(exclude_xy) and exclude_radius_m > 0:
            gap2 = ((self.particles[:, None, :2] - np.asarray(exclude_xy, dtype=np.float64)[None, :, :]) ** 2).sum(-1)
            free = np.all(gap2 >= exclude_radius_m**2, axis=1)
            if weights[free].sum() > 0:
                weights = np.where(free, weights, 0.0)
        total = weights.sum()
        self.supported = bool(total > 0 and np.isfinite(total))
        if self.supported:
            self.weights = weights / total
        est = self.estimate()
        if effective_sample_size(self.weights) < self.resample_below * len(self.weights):
            self.particles = self.particles[systematic_resample(self.weights, self.rng)]
            self.weights = np.full(len(self.weights), 1.0 / len(self.weights))
        return est


def _cells(particles: np.ndarray, ev: FloorEvidence) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Padded centre cell (row, col) and half-size in cells of each particle."""
    p = np.asarray(particles, dtype=np.float64)
    col = np.floor((p[:, 0] - ev.origin_xy_m[0]) / ev.voxel_m)
    row = np.floor((p[:, 1] - ev.origin_xy_m[1]) / ev.voxel_m)
    i = np.clip(col, 0, ev.shape[1] - 1).astype(np.intp) + ev.pad
    j = np.clip(row, 0, ev.shape[0] - 1).astype(np.intp) + ev.pad
    a = np.rint(p[:, 2] / ev.voxel_m).astype(np.intp)
    return j, i, a


def _box_sum(integral: np.ndarray, j: np.ndarray, i: np.ndarray, r: np.ndarray) -> np.ndarray:
    return integral[j + r + 1, i + r + 1] - integral[j - r, i + r + 1] - integral[j + r + 1, i - r] + integral[j - r, i - r]


def _box_max(window_max: np.ndarray, j: np.ndarray, i: np.ndarray, r: np.ndarray) -> np.ndarray:
    side = 2 * r + 1
    level = np.floor(np.log2(side)).astype(np.intp)
    far = r - (1 << level) + 1
    top, left, bottom, right = j - r, i - r, j + far, i + far
    return np.maximum(
        np.maximum(window_max[level, top, left], window_max[level, top, right]),
        np.maximum(window_max[level, bottom, left], window_max[level, bottom, right]),
    )


def _box_terms(particles: np.ndarray, ev: FloorEvidence, k_m: float):
    j, i, a = _cells(particles, ev)
    k = max(1, int(round(k_m / ev.voxel_m)))
    a = np.clip(a, k, ev.max_half_cells - k)
    r_in, r_out = a - k, a + k
    n_in = _box_sum(ev.integral, j, i, r_in).astype(np.float64)
    n_out = _box_sum(ev.integral, j, i, r_out).astype(np.float64)
    h = _box_max(ev.window_max, j, i, r_in).astype(np.float64)
    return n_in, n_out, h, r_in.astype(np.float64), r_out.astype(np.float64), float(k)
