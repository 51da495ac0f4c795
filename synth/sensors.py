"""Sensor models beside the colour camera: a time-of-flight range camera and a thermal camera.

Both turn what :class:`~synth.render.CameraRenderer` knows per pixel (the
nearest surface's range, its normal, how bright it is, what it is made of) into
what such a camera delivers:

* **Range** (:func:`range_frame_mm`), a continuous-wave time-of-flight camera
  (a PMD sensor): ``uint16`` millimetres of range along the pixel's ray, 0 where
  nothing was measured. The returned light's amplitude falls with the surface's
  reflectance, the cosine of the incidence and the square of the range; the
  noise grows as the amplitude falls (about 1 cm at 1 m on a mid-grey surface,
  about 5 cm at 5 m). No value where the amplitude is too weak (very dark
  surfaces far off), at grazing incidence, beyond the unambiguous range, on
  dark surfaces at random (black hair, a black sofa), and at depth edges some
  pixels mix the near and the far surface ("flying pixels") or drop out.
* **Thermal** (:func:`thermal_frame_ck`), an uncooled microbolometer:
  radiometric ``uint16`` centi-kelvin. Room surfaces sit at the room's
  temperature plus a per-surface offset (floor cooler, air warmer under the
  ceiling, cold window glass, a radiator under a window, the warm lamp), the
  room temperature drifting slowly (:func:`ambient_c`); people are warmer
  (skin about 34 C, hair 31 C, clothing 28-31 C, shoes 26 C), their edges a
  little nearer the room's temperature (emissivity falls at grazing angles);
  the optics blur a little; temporal noise (NETD) and fixed-pattern noise
  (per pixel, per column, a smooth radial offset) on top. No shadows: heat
  does not cast them.

Every output is a pure function of its arguments; randomness comes from
generators seeded by the caller's keys.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from synth.body import HAIR, SHIRT, SHOES, SKIN, TROUSERS

KELVIN_OFFSET_C = 273.15
CK_PER_K = 100.0
"""Thermal frames are centi-kelvin: ``uint16(round((t_c + 273.15) * 100))``."""

__all__ = [
    "CK_PER_K",
    "KELVIN_OFFSET_C",
    "RangeModel",
    "ThermalModel",
    "agc8",
    "ambient_c",
    "body_temperature_c",
    "celsius_to_ck",
    "ck_to_celsius",
    "range_frame_mm",
    "surface_offsets_k",
    "thermal_frame_ck",
]


@dataclass(frozen=True)
class RangeModel:
    """A time-of-flight camera. ``max_range_m``: unambiguous range, nothing measured beyond it.
    ``noise_mm``: noise of a surface of amplitude 1 (reflectance 1, head-on, 1 m); it grows as
    ``noise_mm / sqrt(amplitude)``. ``min_amplitude``: weaker returns give no value.
    ``min_cos``: incidence cosines below this give no value. ``dark_reflectance``: surfaces
    darker than this drop out at random, up to ``dark_dropout`` of the time for black.
    ``edge_m``: a range step this large within 3x3 pixels is a depth edge, whose pixels mix
    the two surfaces with probability ``flying_p`` and drop out with ``edge_dropout_p``."""

    max_range_m: float = 7.0
    noise_mm: float = 7.0
    min_amplitude: float = 0.003
    min_cos: float = 0.12
    dark_reflectance: float = 0.2
    dark_dropout: float = 0.6
    edge_m: float = 0.2
    flying_p: float = 0.35
    edge_dropout_p: float = 0.2

    def __post_init__(self) -> None:
        if not 0.5 <= self.max_range_m <= 60.0:
            raise ValueError(f"max_range_m must lie in 0.5..60, got {self.max_range_m!r}")
        if not 0.0 <= self.noise_mm <= 100.0:
            raise ValueError(f"noise_mm must lie in 0..100, got {self.noise_mm!r}")
        for name in ("dark_dropout", "flying_p", "edge_dropout_p", "min_cos", "dark_reflectance"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in 0..1, got {getattr(self, name)!r}")
        if self.flying_p + self.edge_dropout_p > 1.0:
            raise ValueError("flying_p + edge_dropout_p must not exceed 1")

    def sigma_mm(self, range_m, reflectance=0.5, cos=1.0):
        """Noise standard deviation, millimetres, of a surface at ``range_m``."""
        amp = np.maximum(np.asarray(reflectance) * np.asarray(cos) / np.maximum(np.asarray(range_m), 0.05) ** 2, 1e-6)
        return self.noise_mm / np.sqrt(amp)


@dataclass(frozen=True)
class ThermalModel:
    """An uncooled thermal camera. ``netd_k``: temporal noise (standard deviation, kelvin).
    ``fpn_k``: per-pixel fixed-pattern offsets; ``column_k``: per-column offsets; ``radial_k``:
    a smooth offset growing to the image corners. ``blur_px``: optics blur (Gaussian sigma)."""

    netd_k: float = 0.05
    fpn_k: float = 0.08
    column_k: float = 0.05
    radial_k: float = 0.4
    blur_px: float = 0.7

    def __post_init__(self) -> None:
        for name in ("netd_k", "fpn_k", "column_k", "radial_k"):
            if not 0.0 <= getattr(self, name) <= 5.0:
                raise ValueError(f"{name} must lie in 0..5 K, got {getattr(self, name)!r}")
        if not 0.0 <= self.blur_px <= 5.0:
            raise ValueError(f"blur_px must lie in 0..5, got {self.blur_px!r}")


def celsius_to_ck(t_c) -> np.ndarray:
    """Celsius -> centi-kelvin ``uint16`` (saturating)."""
    return np.clip(np.rint((np.asarray(t_c, dtype=np.float64) + KELVIN_OFFSET_C) * CK_PER_K), 0, 65535).astype(np.uint16)


def ck_to_celsius(ck) -> np.ndarray:
    """Centi-kelvin -> Celsius, float32."""
    return (np.asarray(ck, dtype=np.float32) / np.float32(CK_PER_K) - np.float32(KELVIN_OFFSET_C)).astype(np.float32)


def ambient_c(seed: int, t_s: float) -> float:
    """The room's air temperature, Celsius, at ``t_s`` seconds into a world of ``seed``: 19-24 C,
    drifting by up to 2 K an hour (heating coming on, a room cooling down)."""
    rng = np.random.default_rng([int(seed), 37])
    base = float(rng.uniform(19.0, 24.0))
    rate_k_per_s = float(rng.uniform(-1.0, 2.0)) / 3600.0
    return base + rate_k_per_s * float(t_s)


def body_temperature_c(material: np.ndarray, person_id: int, seed: int) -> np.ndarray:
    """(N,) float32 apparent surface temperature, Celsius, of body pixels of ``material`` codes:
    exposed skin 33.5-34.5 C, hair about 31 C, shirts 29-31 C, trousers 28-30 C, shoes 26 C
    (drawn per person: clothes differ in thickness)."""
    rng = np.random.default_rng([int(seed), 41, int(person_id)])
    table = np.zeros(5, dtype=np.float32)
    table[SKIN] = rng.uniform(33.5, 34.5)
    table[HAIR] = rng.uniform(30.0, 32.0)
    table[SHIRT] = rng.uniform(29.0, 31.0)
    table[TROUSERS] = rng.uniform(28.0, 30.0)
    table[SHOES] = rng.uniform(25.0, 27.0)
    return table[np.asarray(material, dtype=np.int64)]


def surface_offsets_k(room, surface: np.ndarray, point: np.ndarray, seed: int) -> np.ndarray:
    """(N,) float32 temperature of background hits above the room's air, kelvin.

    ``surface``: (N,) surface codes of :func:`synth.render.raycast_room`; ``point``: (N, 3)
    world points. The same for every camera of a world (``seed``), so cameras agree on the room.
    """
    from synth.render import (
        SURF_CEILING, SURF_CORRIDOR, SURF_FLOOR, SURF_FURNITURE, SURF_NONE, SURF_WALL_X0, SURF_WALL_Y1,
    )

    rng = np.random.default_rng([int(seed), 39])
    wall_off = rng.uniform(-0.4, 0.4, 4)
    box_off = rng.uniform(-0.6, 0.3, max(len(room.boxes), 1))
    s = np.asarray(surface)
    p = np.asarray(point, dtype=np.float64)
    off = np.zeros(s.shape[0], dtype=np.float64)
    off[s == SURF_FLOOR] = -0.6
    off[s == SURF_CEILING] = 0.4
    off[s == SURF_CORRIDOR] = -1.0
    for k in range(4):
        off[s == SURF_WALL_X0 + k] = wall_off[k]
    for k in range(len(room.boxes)):
        off[s == SURF_FURNITURE + k] = box_off[k]
    # warm air rises: about 0.6 K per metre
    off += 0.6 * (p[:, 2] - 1.2)
    # the lamp warms the ceiling around it
    light = np.asarray(room.light_m, dtype=np.float64)
    near = s == SURF_CEILING
    if near.any():
        d2 = np.sum((p[near] - light) ** 2, axis=1)
        off[near] += 5.0 * np.exp(-d2 / 0.35 ** 2)
    walls = {"x0": SURF_WALL_X0, "x1": SURF_WALL_X0 + 1, "y0": SURF_WALL_X0 + 2, "y1": SURF_WALL_Y1}
    radiator = True
    for dec in room.decals:
        if dec.pattern != "window" or dec.surface not in walls:
            continue
        u = p[:, 1] if dec.surface in ("x0", "x1") else p[:, 0]
        v = p[:, 2]
        u0, v0, u1, v1 = dec.rect_m
        on = s == walls[dec.surface]
        off[on & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)] -= 3.5   # cold glass
        if radiator and v0 > 0.75:   # one radiator, under the first window with room for it
            radiator = False
            off[on & (u >= u0) & (u <= u1) & (v >= 0.15) & (v <= min(0.7, v0 - 0.05))] += 22.0
    off[s == SURF_NONE] = 0.0
    return off.astype(np.float32)


def range_frame_mm(range_m: np.ndarray, reflectance: np.ndarray, cos: np.ndarray, valid: np.ndarray,
                   normal01: np.ndarray, model: RangeModel) -> np.ndarray:
    """(H, W) uint16 measured range, millimetres, 0 = no value.

    range_m: (H, W) float32 true range of the nearest surface. reflectance: (H, W) 0..1. cos: (H, W)
    |cos| of the incidence. valid: (H, W) bool pixels with a ray. normal01: (2, H, W) float32 draws,
    standard normal [0] and uniform 0..1 [1], for this frame.
    """
    r = range_m.astype(np.float32)
    refl = np.clip(reflectance, 0.02, 1.0).astype(np.float32)
    c = np.clip(cos, 0.0, 1.0).astype(np.float32)
    amp = refl * c / np.maximum(r, np.float32(0.05)) ** 2
    z, u = normal01[0], normal01[1]
    sigma_m = np.float32(model.noise_mm * 1e-3) / np.sqrt(np.maximum(amp, np.float32(1e-6)))
    out = r + sigma_m * z
    missing = ~valid | (r > model.max_range_m) | (c < model.min_cos) | (amp < model.min_amplitude)
    dark = np.clip((model.dark_reflectance - refl) / max(model.dark_reflectance, 1e-6), 0.0, 1.0)
    missing |= u < dark * model.dark_dropout
    # depth edges: the pixel's footprint straddles two surfaces
    near = cv2.erode(np.where(valid, r, np.float32(1e6)), None)
    far = cv2.dilate(np.where(valid, r, np.float32(0.0)), None)
    edge = (far - near) > model.edge_m
    # a surface beyond the range returns too little light to pull a mixture farther than that
    far = np.minimum(far, np.float32(model.max_range_m))
    if edge.any():
        # reuse the uniform draw: pixels not dropped for darkness have u spread over 0..1
        w = u[edge]
        flying = w < model.flying_p
        mixed = near[edge] + (far[edge] - near[edge]) * (w / max(model.flying_p, 1e-6))
        vals = out[edge]
        vals[flying] = mixed[flying]
        out[edge] = vals
        missing[edge] |= (w >= model.flying_p) & (w < model.flying_p + model.edge_dropout_p)
    mm = np.clip(np.rint(out * 1000.0), 1, 65535).astype(np.uint16)
    mm[missing] = 0
    return mm


def thermal_frame_ck(temp_c: np.ndarray, fixed_k: np.ndarray, noise: np.ndarray, model: ThermalModel) -> np.ndarray:
    """(H, W) uint16 centi-kelvin frame from the scene's surface temperatures ``temp_c`` (H, W)
    float32 Celsius: optics blur, then the camera's fixed pattern ``fixed_k`` (H, W) and temporal
    noise ``noise`` (H, W, standard normal draws) times ``model.netd_k``."""
    t = temp_c.astype(np.float32)
    if model.blur_px > 0:
        t = cv2.GaussianBlur(t, (0, 0), model.blur_px)
    t = t + fixed_k + np.float32(model.netd_k) * noise
    return celsius_to_ck(t)


def agc8(frame_ck: np.ndarray, *, lo_c: float | None = None, hi_c: float | None = None) -> np.ndarray:
    """(H, W) uint8 view of a centi-kelvin frame: ``lo_c``..``hi_c`` Celsius mapped to 0..255 (a
    fixed span, what a camera with its gain locked delivers); without them, automatic gain
    between the frame's 1st and 99th percentiles (what most cameras do by default; the mapping
    then changes whenever something warm enters the view)."""
    t = ck_to_celsius(frame_ck)
    if (lo_c is None) != (hi_c is None):
        raise ValueError("give both lo_c and hi_c, or neither")
    if lo_c is None:
        lo_c, hi_c = (float(v) for v in np.percentile(t, (1.0, 99.0)))
        hi_c = max(hi_c, lo_c + 1.0)
    if not hi_c > lo_c:
        raise ValueError(f"hi_c must exceed lo_c, got {lo_c!r}..{hi_c!r}")
    scale = 255.0 / (hi_c - lo_c)
    return cv2.convertScaleAbs(t, alpha=scale, beta=-lo_c * scale)
