"""Articulated human bodies made of ellipsoids, posed by joint angles.

A body is 14 solid ellipsoids: pelvis, torso, neck, head, upper arms,
forearms (with the hand), thighs, shanks and feet. Each ellipsoid ``k`` is
the set ``{c_k + A_k u : |u| <= 1}`` with ``c_k`` its centre and ``A_k`` a
(3, 3) matrix whose columns are its semi-axes in the world frame (metres).
Segment proportions follow standard anthropometric tables (fractions of the
standing height ``H``).

A pose is a vector ``q`` of :data:`N_Q` floats (radians and metres, named
by the ``Q_*`` indices): pelvis position (the midpoint of the hip joints,
world), root yaw / pitch / roll and twist (``R = Rz(yaw) Ry(pitch) Rx(roll)
Rz(twist)``; body frame x forward, y left, z up; positive pitch tips the
body forward, positive roll tips it onto its right side, twist turns it
about its own long axis), spine forward bend, neck bend, and per side
(left, right) hip flexion, hip abduction, knee flexion, shoulder flexion
(arm forward), shoulder abduction and elbow flexion.

:func:`forward_kinematics` is vectorised over a batch of poses so that the
ground truth of a ten-minute scenario is computed in one call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

N_Q = 21
Q_PELVIS = slice(0, 3)
Q_YAW, Q_PITCH, Q_ROLL = 3, 4, 5
Q_SPINE, Q_NECK = 6, 7
Q_HIP_FLEX = (8, 9)
Q_HIP_ABD = (10, 11)
Q_KNEE = (12, 13)
Q_SHOULDER_FLEX = (14, 15)
Q_SHOULDER_ABD = (16, 17)
Q_ELBOW = (18, 19)
Q_TWIST = 20

PART_NAMES = (
    "pelvis", "torso", "neck", "head",
    "upper arm left", "upper arm right", "forearm left", "forearm right",
    "thigh left", "thigh right", "shank left", "shank right", "foot left", "foot right",
)
N_PARTS = len(PART_NAMES)

SKIN, HAIR, SHIRT, TROUSERS, SHOES = range(5)
PART_MATERIAL = np.array([TROUSERS, SHIRT, SKIN, SKIN, SHIRT, SHIRT, SHIRT, SHIRT,
                          TROUSERS, TROUSERS, TROUSERS, TROUSERS, SHOES, SHOES], dtype=np.int8)
HEAD_PART = 3
FOREARM_PARTS = (6, 7)

SKIN_TONES = ((180, 200, 235), (150, 180, 220), (110, 145, 195), (80, 110, 160), (55, 75, 110))
HAIR_COLOURS = ((25, 25, 30), (40, 60, 90), (60, 110, 160), (170, 180, 190), (30, 45, 70), (120, 150, 180))
SHIRT_COLOURS = ((190, 80, 40), (40, 40, 180), (60, 150, 60), (200, 200, 200), (30, 30, 30), (40, 160, 220),
                 (150, 60, 140), (150, 130, 60), (90, 90, 200), (200, 120, 120))
TROUSER_COLOURS = ((90, 50, 30), (40, 40, 40), (120, 110, 100), (60, 80, 100), (150, 140, 110), (30, 30, 80))
SHOE_COLOURS = ((25, 25, 25), (40, 60, 90), (200, 200, 200), (60, 60, 70))

# Ellipsoids overlap their neighbours by stretching along the segment.
_SEGMENT_OVERLAP = 1.12


@dataclass(frozen=True)
class BodyShape:
    """One person's build and clothing.

    height_m: standing height (top of the head), metres.
    width: lateral/depth scale of trunk and limbs (1 = average build).
    *_bgr: colours, 0..255, BGR. long_sleeves: forearms clothed or bare.
    """

    height_m: float = 1.75
    width: float = 1.0
    skin_bgr: tuple[int, int, int] = SKIN_TONES[1]
    hair_bgr: tuple[int, int, int] = HAIR_COLOURS[0]
    shirt_bgr: tuple[int, int, int] = SHIRT_COLOURS[0]
    trousers_bgr: tuple[int, int, int] = TROUSER_COLOURS[0]
    shoes_bgr: tuple[int, int, int] = SHOE_COLOURS[0]
    long_sleeves: bool = True

    def __post_init__(self) -> None:
        if not (0.9 <= self.height_m <= 2.2):
            raise ValueError(f"height_m must lie in 0.9..2.2 (children included), got {self.height_m}")
        if not (0.6 <= self.width <= 1.6):
            raise ValueError(f"width must lie in 0.6..1.6, got {self.width}")

    @classmethod
    def random(cls, rng: np.random.Generator, *, height_m: float | None = None) -> "BodyShape":
        """A random adult: height 1.5..1.95 m, width 0.85..1.25, random clothes."""
        pick = lambda table: tuple(int(c) for c in table[int(rng.integers(len(table)))])  # noqa: E731
        h = float(rng.uniform(1.5, 1.95)) if height_m is None else float(height_m)
        return cls(
            height_m=h,
            width=float(rng.uniform(0.85, 1.25)),
            skin_bgr=pick(SKIN_TONES),
            hair_bgr=pick(HAIR_COLOURS),
            shirt_bgr=pick(SHIRT_COLOURS),
            trousers_bgr=pick(TROUSER_COLOURS),
            shoes_bgr=pick(SHOE_COLOURS),
            long_sleeves=bool(rng.random() < 0.6),
        )

    @property
    def colours_bgr(self) -> np.ndarray:
        """(5, 3) float32 material colours indexed by SKIN, HAIR, SHIRT, TROUSERS, SHOES."""
        return np.array([self.skin_bgr, self.hair_bgr, self.shirt_bgr, self.trousers_bgr, self.shoes_bgr],
                        dtype=np.float32)

    # Segment lengths, metres.
    @property
    def thigh_m(self) -> float:
        return 0.245 * self.height_m

    @property
    def shank_m(self) -> float:
        return 0.246 * self.height_m

    @property
    def ankle_m(self) -> float:
        return 0.039 * self.height_m

    @property
    def hip_height_m(self) -> float:
        """Height of the hip joints standing straight."""
        return self.thigh_m + self.shank_m + self.ankle_m

    @property
    def seat_offset_m(self) -> float:
        """Height of the hip joints above a seat surface when seated."""
        return 0.05 * self.height_m


@dataclass(frozen=True)
class Body:
    """One posed person: 14 ellipsoids in the world frame.

    person_id: the person. centers_m: (P, 3) float64. axes: (P, 3, 3) float64,
    columns are semi-axis vectors (world, metres): the part is ``c + A u, |u| <= 1``.
    shape: the person's build and clothing.
    """

    person_id: int
    centers_m: np.ndarray
    axes: np.ndarray
    shape: BodyShape

    @property
    def inverse_axes(self) -> np.ndarray:
        """(P, 3, 3) float64 ``A^-1``: world offsets to the unit-ball frame of each part."""
        return np.linalg.inv(self.axes)

    @property
    def extents_m(self) -> np.ndarray:
        """(P, 3) float64 half-extents of each part's axis-aligned bounding box (exact)."""
        return np.linalg.norm(self.axes, axis=2)

    @property
    def z_top_m(self) -> float:
        """Height of the highest body point, metres."""
        return float(np.max(self.centers_m[:, 2] + self.extents_m[:, 2]))

    @property
    def pelvis_m(self) -> np.ndarray:
        """(3,) float64 hip-joint midpoint, world."""
        return self.centers_m[0] - self.axes[0] @ np.array([0.0, 0.0, 0.03 / 0.07])

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box of the whole body: ((3,), (3,)) world, metres."""
        ext = self.extents_m
        return (self.centers_m - ext).min(axis=0), (self.centers_m + ext).max(axis=0)

    def volumes_m3(self) -> np.ndarray:
        """(P,) float64 volume of each part."""
        return 4.0 / 3.0 * np.pi * np.abs(np.linalg.det(self.axes))

    def contains(self, points_m) -> np.ndarray:
        """(N, 3) world points -> (N,) bool: inside any part."""
        pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        inv = self.inverse_axes
        u = np.einsum("pij,pnj->pni", inv, pts[None, :, :] - self.centers_m[:, None, :])
        return np.any(np.einsum("pni,pni->pn", u, u) <= 1.0, axis=0)

    def sample_points(self, n: int, rng: np.random.Generator, *, surface_fraction: float = 0.0) -> np.ndarray:
        """(n, 3) float64 world points inside the body, parts chosen by volume;
        ``surface_fraction`` of them lie on the part surfaces (just inside)."""
        vol = self.volumes_m3()
        part = rng.choice(N_PARTS, size=n, p=vol / vol.sum())
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = np.cbrt(rng.random(n))
        on_surface = rng.random(n) < surface_fraction
        r[on_surface] = 0.999
        u = d * r[:, None]
        return self.centers_m[part] + np.einsum("nij,nj->ni", self.axes[part], u)

    def intersect(self, origin_m, dirs) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays ``origin + t d`` with the body.

        origin_m: (3,) world. dirs: (N, 3) world directions (any length).
        Returns t (N,) float64 (inf where missed; in units of |d|) and part (N,) int (-1 where missed).
        """
        d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        o = np.asarray(origin_m, dtype=np.float64)
        best = np.full(d.shape[0], np.inf)
        part = np.full(d.shape[0], -1)
        for k, inv in enumerate(self.inverse_axes):
            oo = inv @ (o - self.centers_m[k])
            dd = d @ inv.T
            t = _ray_unit_sphere(oo, dd)
            closer = t < best
            best[closer] = t[closer]
            part[closer] = k
        return best, part


def standing_pose(shape: BodyShape, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """(N_Q,) float64 relaxed standing pose at floor point (x, y) facing ``yaw`` (radians)."""
    q = np.zeros(N_Q)
    q[Q_PELVIS] = (x, y, shape.hip_height_m)
    q[Q_YAW] = yaw
    for side in (0, 1):
        q[Q_KNEE[side]] = 0.04
        q[Q_HIP_FLEX[side]] = 0.02
        q[Q_SHOULDER_ABD[side]] = 0.12
        q[Q_ELBOW[side]] = 0.15
        q[Q_SHOULDER_FLEX[side]] = 0.03
    return q


def pose_body(shape: BodyShape, q: np.ndarray, person_id: int = 0) -> Body:
    """The :class:`Body` of one pose ``q`` (N_Q,)."""
    centers, axes = forward_kinematics(shape, np.asarray(q, dtype=np.float64)[None, :])
    return Body(person_id=person_id, centers_m=centers[0], axes=axes[0], shape=shape)


def forward_kinematics(shape: BodyShape, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched forward kinematics.

    q: (F, N_Q) poses. Returns centres (F, P, 3) and axes (F, P, 3, 3), world frame, metres.
    """
    q = np.asarray(q, dtype=np.float64)
    F = q.shape[0]
    H = shape.height_m
    w = shape.width
    pelvis = q[:, Q_PELVIS]
    R_root = _rz(q[:, Q_YAW]) @ _ry(q[:, Q_PITCH]) @ _rx(q[:, Q_ROLL]) @ _rz(q[:, Q_TWIST])
    R_spine = R_root @ _ry(q[:, Q_SPINE])
    R_head = R_spine @ _ry(q[:, Q_NECK])
    centers = np.empty((F, N_PARTS, 3))
    axes = np.empty((F, N_PARTS, 3, 3))

    def put(k, R, centre_local_origin, offset, radii):
        centers[:, k] = centre_local_origin + np.einsum("fij,j->fi", R, np.asarray(offset, dtype=np.float64))
        axes[:, k] = R * np.asarray(radii, dtype=np.float64)[None, None, :]

    put(0, R_root, pelvis, (0.0, 0.0, 0.03 * H), (0.065 * H * w, 0.095 * H * w, 0.07 * H))
    lumbar = pelvis + np.einsum("fij,j->fi", R_root, np.array([0.0, 0.0, 0.04 * H]))
    put(1, R_spine, lumbar, (0.0, 0.0, 0.13 * H), (0.07 * H * w, 0.105 * H * w, 0.16 * H))
    put(2, R_spine, lumbar, (0.0, 0.0, 0.27 * H), (0.03 * H, 0.03 * H, 0.05 * H))
    neck_joint = lumbar + np.einsum("fij,j->fi", R_spine, np.array([0.0, 0.0, 0.29 * H]))
    put(3, R_head, neck_joint, (0.01 * H, 0.0, 0.075 * H), (0.056 * H, 0.045 * H, 0.065 * H))

    for side, sgn in ((0, 1.0), (1, -1.0)):
        # Arms: shoulder joint on the torso, segment along -z of the limb frame.
        shoulder = lumbar + np.einsum("fij,j->fi", R_spine, np.array([0.0, sgn * 0.115 * H * w, 0.245 * H]))
        R_upper = R_spine @ _ry(-q[:, Q_SHOULDER_FLEX[side]]) @ _rx(sgn * q[:, Q_SHOULDER_ABD[side]])
        L_upper = 0.186 * H
        elbow = shoulder + R_upper[:, :, 2] * -L_upper
        _segment(centers, axes, 4 + side, shoulder, R_upper, L_upper, 0.03 * H * w, 0.028 * H * w)
        R_fore = R_upper @ _ry(-q[:, Q_ELBOW[side]])
        L_fore = 0.236 * H
        _segment(centers, axes, 6 + side, elbow, R_fore, L_fore, 0.024 * H * w, 0.022 * H * w)
        # Legs.
        hip = pelvis + np.einsum("fij,j->fi", R_root, np.array([0.0, sgn * 0.05 * H * w, 0.0]))
        R_thigh = R_root @ _ry(-q[:, Q_HIP_FLEX[side]]) @ _rx(sgn * q[:, Q_HIP_ABD[side]])
        knee = hip + R_thigh[:, :, 2] * -shape.thigh_m
        _segment(centers, axes, 8 + side, hip, R_thigh, shape.thigh_m, 0.045 * H * w, 0.042 * H * w)
        R_shank = R_thigh @ _ry(q[:, Q_KNEE[side]])
        ankle = knee + R_shank[:, :, 2] * -shape.shank_m
        _segment(centers, axes, 10 + side, knee, R_shank, shape.shank_m, 0.032 * H * w, 0.03 * H * w)
        put(12 + side, R_shank, ankle, (0.04 * H, 0.0, -0.018 * H), (0.072 * H, 0.026 * H, 0.022 * H))
    return centers, axes


TRUNK_PARTS = (0, 1, 3, 8, 9)


def lowest_point_m(shape: BodyShape, q: np.ndarray, parts=None) -> np.ndarray:
    """(F,) float64 height of the lowest point of the body (or of ``parts``) for poses (F, N_Q)."""
    centers, axes = forward_kinematics(shape, np.atleast_2d(q))
    low = centers[:, :, 2] - np.linalg.norm(axes[:, :, 2, :], axis=2)
    return np.min(low if parts is None else low[:, list(parts)], axis=1)


def highest_point_m(shape: BodyShape, q: np.ndarray) -> np.ndarray:
    """(F,) float64 height of the highest body point (``z_top``) for poses (F, N_Q)."""
    centers, axes = forward_kinematics(shape, np.atleast_2d(q))
    return np.max(centers[:, :, 2] + np.linalg.norm(axes[:, :, 2, :], axis=2), axis=1)


# ---------------------------------------------------------------------- helpers


def _segment(centers, axes, k, start, R, length, r_x, r_y) -> None:
    """A limb ellipsoid from joint ``start`` along ``-z`` of ``R`` for ``length`` metres."""
    centers[:, k] = start - R[:, :, 2] * (length / 2)
    axes[:, k] = R * np.array([r_x, r_y, _SEGMENT_OVERLAP * length / 2])[None, None, :]


def _ray_unit_sphere(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Ray ``o + t d`` (o (3,), d (N, 3)) against the unit sphere: (N,) smallest t > 0 or inf."""
    a = np.einsum("ni,ni->n", d, d)
    b = d @ o
    c = o @ o - 1.0
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0 = (-b - sq) / a
        t1 = (-b + sq) / a
    t = np.where(t0 > 0, t0, t1)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _rx(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0] = 1.0
    R[..., 1, 1] = c
    R[..., 1, 2] = -s
    R[..., 2, 1] = s
    R[..., 2, 2] = c
    return R


def _ry(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0] = c
    R[..., 0, 2] = s
    R[..., 1, 1] = 1.0
    R[..., 2, 0] = -s
    R[..., 2, 2] = c
    return R


def _rz(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 1, 1] = c
    R[..., 2, 2] = 1.0
    return R
