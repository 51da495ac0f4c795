"""The segmenter a camera's modality calls for, built from one set of keyword arguments.

``colour`` and ``infrared`` cameras (intensity images) use the Gaussian-mixture
:class:`~camera_worker.segmentation.ForegroundSegmenter`; ``thermal`` cameras the
warmer-than-the-room :class:`~camera_worker.thermal.ThermalSegmenter`; ``depth``
cameras the nearer-than-the-room :class:`~camera_worker.depth.DepthSegmenter`,
whose foreground range travels beside the mask (:func:`foreground_depth`).
All three take ``apply(frame, holds=..., learn=...) -> (mask, stats)`` and
``learn(frame)``; settings that only the colour model has (mixtures, shadows,
light changes) are left out for the others.
"""

from __future__ import annotations

from typing import Any, Union

import numpy as np

from camera_worker.depth import DepthSegmenter
from camera_worker.segmentation import ForegroundSegmenter
from camera_worker.thermal import ThermalSegmenter

__all__ = ["COMMON_SETTINGS", "MODALITIES", "Segmenter", "foreground_depth", "segmenter_for"]

MODALITIES = ("colour", "thermal", "infrared", "depth")
COMMON_SETTINGS = frozenset({"window_frames", "alpha", "mask_scale", "open_px", "close_px", "min_area_px",
                             "fill_holes"})
"""Settings every segmenter takes; the rest belong to the colour model."""

Segmenter = Union[ForegroundSegmenter, ThermalSegmenter, DepthSegmenter]


def segmenter_for(modality: str, **settings: Any) -> Segmenter:
    """The segmenter for a camera of ``modality`` (``colour``, ``infrared``, ``thermal``, ``depth``).
    ``settings``: keyword arguments (None values dropped); for thermal and depth cameras only
    :data:`COMMON_SETTINGS` are passed on. Raises ValueError naming a bad modality or setting."""
    kwargs = {k: v for k, v in settings.items() if v is not None}
    if modality in ("colour", "infrared"):
        return ForegroundSegmenter(**kwargs)
    common = {k: v for k, v in kwargs.items() if k in COMMON_SETTINGS}
    if modality == "thermal":
        return ThermalSegmenter(**common)
    if modality == "depth":
        return DepthSegmenter(**common)
    raise ValueError(f"modality must be one of {', '.join(MODALITIES)}, got {modality!r}")


def foreground_depth(segmenter: Segmenter) -> np.ndarray | None:
    """The last frame's foreground range at mask size, ``(h, w) uint16`` millimetres (0 = none),
    for a depth camera's segmenter; None for the others."""
    return segmenter.depth_mm if isinstance(segmenter, DepthSegmenter) else None
