"""Two heads or one: whether the cameras see the gap between two people standing close together.

Where two people stand close, the carving vote fills the space between their
heads: only the cameras that look across the gap see it, too few to carve it
away. Each of those cameras still shows it: in its mask, the line from one
head to the other, at head height, runs from foreground (a head, with
background over it) through background (the gap) to foreground (the other
head). A target that slid onto someone else's body has no head of its own at
its place: its end of the line lies beside a head, on background, or the line
crosses no gap. Two people are seen apart when :data:`MIN_CAMERAS` cameras
show it.

:class:`HeadGaps` tests pairs of floor positions and tops against one frame
set's masks. Pure: no clock, no I/O.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from common.camera import Camera, MaskCameras

HEAD_DROP_M = 0.12
"""The line runs this far under each top: through the middle of the head."""
OVER_HEAD_M = 0.1
"""A head is the top of a silhouette: this far over it, the mask is background. (Where its line
of sight meets someone behind, the camera cannot tell and is not asked.)"""
SAMPLES = 15
"""Points along the line, ends included."""
MIN_CAMERAS = 2
"""Cameras that must see the two heads apart. In a crowd one camera's line can run by chance from a
head to someone else's behind the other person; two cameras agreeing by chance is rare."""


class HeadGaps:
    """Tests pairs of people against one frame set's masks, over a site's cameras (each resized to
    the masks it gets, once per mask size)."""

    def __init__(self, cameras: Mapping[str, Camera]) -> None:
        self.cameras = MaskCameras(cameras)

    def seen_apart(self, pairs: Iterable[tuple[tuple[float, float, float], tuple[float, float, float]]],
                   masks: Mapping[str, np.ndarray]) -> list[bool]:
        """For each pair of heads ``((x, y, top), (x, y, top))`` (world metres: floor position and
        top of each person), whether at least :data:`MIN_CAMERAS` cameras' masks show a head at
        both (foreground, with background over it) and background somewhere between them (module
        text)."""
        pairs = list(pairs)
        if not pairs:
            return []
        t = np.linspace(0.0, 1.0, SAMPLES)
        lines = []
        for (xa, ya, ta), (xb, yb, tb) in pairs:
            a = np.array([xa, ya, ta - HEAD_DROP_M])
            b = np.array([xb, yb, tb - HEAD_DROP_M])
            over = [[xa, ya, ta + OVER_HEAD_M], [xb, yb, tb + OVER_HEAD_M]]
            lines.append(np.concatenate([a[None, :] + t[:, None] * (b - a)[None, :], over]))
        n_pts = SAMPLES + 2
        pts = np.concatenate(lines)
        votes = np.zeros(len(pairs), dtype=int)
        for cam_id, cam in self.cameras.sized(masks).items():
            fg = np.asarray(masks[cam_id]) > 127
            uv, valid = cam.project(pts)
            uv = uv.reshape(len(pairs), n_pts, 2)
            valid = valid.reshape(len(pairs), n_pts)
            for n in np.flatnonzero(votes < MIN_CAMERAS):
                if not valid[n].all():
                    continue
                px = np.rint(uv[n]).astype(int)
                on = fg[px[:, 1], px[:, 0]]
                line, ends, over = on[:SAMPLES], px[[0, SAMPLES - 1]], on[SAMPLES:]
                if abs(ends[1, 0] - ends[0, 0]) + abs(ends[1, 1] - ends[0, 1]) < 3:
                    continue  # the two heads on one line of sight: this camera cannot tell
                heads = _near_fg(fg, ends[0]) and _near_fg(fg, ends[1]) and not over.any()
                if heads and not line[2:-2].all():
                    votes[n] += 1
        return (votes >= MIN_CAMERAS).tolist()


def _near_fg(fg: np.ndarray, px: np.ndarray) -> bool:
    """Foreground at pixel ``px`` (u, v) or one pixel beside it."""
    u, v = int(px[0]), int(px[1])
    return bool(fg[max(0, v - 1):v + 2, max(0, u - 1):u + 2].any())
