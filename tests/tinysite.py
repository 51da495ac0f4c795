"""A tiny site for fusion tests: three pinhole cameras around a 3 x 3 x 2 m room, coarse voxels,
and the masks of a box-shaped "person" projected through each camera."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from common import maskcodec
from common.calibration import save_voxelwatch
from common.camera import Camera, look_at
from common.messages import MaskFrame

FPS = 30.0
PERIOD_NS = int(1e9 / FPS)
BOX_XY = (1.5, 1.4)
CAMERA_CENTRES = {"c1": (-0.5, -0.5, 2.5), "c2": (3.5, -0.5, 2.5), "c3": (1.5, 3.6, 2.5)}
W, H = 160, 120


def write_site(folder: Path) -> tuple[Path, dict[str, Camera]]:
    """(site file, cameras): three cameras looking at the middle of a 3 x 3 x 2 m room."""
    cams = {}
    for cid, centre in CAMERA_CENTRES.items():
        R, t = look_at(centre, (1.5, 1.5, 0.8))
        cams[cid] = Camera.pinhole(cid, W, H, hfov_deg=80.0, R=R, t=t)
        save_voxelwatch(cams[cid], folder / f"{cid}.toml")
    text = (
        'name = "tiny"\n\n[volume]\nmin_m = [0.0, 0.0, 0.0]\nmax_m = [3.0, 3.0, 2.0]\n\n'
        "[carving]\nvoxel_sizes_m = [0.4, 0.2, 0.1]\nmin_cameras = 2\n"
    )
    for cid in cams:
        text += f'\n[[cameras]]\nid = "{cid}"\ncalibration = "{cid}.toml"\nfps = {FPS}\n'
    (folder / "site.toml").write_text(text)
    return folder / "site.toml", cams


def box_mask(cam: Camera, x: float, y: float, *, width_m: float = 0.5, depth_m: float = 0.4,
             height_m: float = 1.7) -> np.ndarray:
    """(H, W) uint8 0/255: the silhouette of an upright box standing at floor point (x, y)."""
    corners = np.array([[x + sx * width_m / 2, y + sy * depth_m / 2, z]
                        for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, height_m)])
    uv, ok = cam.project(corners)
    assert ok.all()
    mask = np.zeros((cam.height, cam.width), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(uv).astype(np.int32)), 255)
    return mask


def mask_frame(cam: Camera, seq: int, stamp_ns: int, mask: np.ndarray | None = None, **changes) -> MaskFrame:
    """The wire message of ``mask`` (default: the box at BOX_XY) from ``cam``; ``changes`` override fields."""
    mask = box_mask(cam, *BOX_XY) if mask is None else mask
    fields = dict(cam=cam.id, seq=seq, stamp_ns=stamp_ns, width=mask.shape[1], height=mask.shape[0],
                  src_width=cam.width, src_height=cam.height, codec="rle-zlib",
                  data=maskcodec.encode_mask(mask), fg_fraction=float(np.count_nonzero(mask)) / mask.size)
    fields.update(changes)
    return MaskFrame(**fields)
