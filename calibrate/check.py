"""Do the cameras still see people where their calibrations say? An offline check from short clips.

``voxelwatch site check SITE --clip cam1=walk1.avi --clip cam2=walk2.avi ...``
replays clips of people walking (one per camera, recorded at the same time:
videos, image folders or mask folders, as ``voxelwatch replay`` reads them)
through the fusion pipeline and reports, per camera, the measurements of the
moved-camera check (:mod:`fusion_server.consistency`): how many clear views
it had, the share of them that fit where the other cameras carve the person
(offset within 4 % of the silhouette's height plus a mask pixel of zero: a
calibration check has no baseline but the calibration itself), the median
offset in pixels and the median fit. A camera whose share is low and whose
offset points one way has moved since it was calibrated. For a camera whose
site entry names a ``view_reference`` picture (its worker's reference view
of the room), a video clip is also registered against it
(:mod:`camera_worker.viewcheck`): how far the view has turned, in degrees.
"""

from __future__ import annotations

import statistics
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from common.site import Site

__all__ = ["CameraCheck", "check_clips"]


@dataclass(frozen=True)
class CameraCheck:
    """One camera's figures: ``views`` measured, ``fit_share`` of them within tolerance of zero offset
    (None without views), ``offset_px`` median (dx, dy) full-image pixels, ``fit`` median agreement;
    ``view_deg``: how far the clip's view has turned from the camera's ``view_reference`` picture
    (None when the site names none, or the clip is not a video)."""

    cam: str
    views: int
    fit_share: float | None
    offset_px: tuple[float, float] | None
    fit: float | None
    view_deg: float | None = None

    def line(self) -> str:
        view = "" if self.view_deg is None else f"; view {self.view_deg:.2f} deg from its reference picture"
        if not self.views:
            return f"camera {self.cam}: no clear view of anyone the other cameras carve{view}"
        dx, dy = self.offset_px
        return (f"camera {self.cam}: {self.views} views, {100 * self.fit_share:.0f}% where the others put people, "
                f"median offset ({dx:+.1f}, {dy:+.1f}) px, median fit {self.fit:.2f}{view}")


def check_clips(site: Site, clips: Mapping[str, str | Path], *, cache_dir: str | Path | None = None,
                max_frames: int | None = None) -> list[CameraCheck]:
    """Replay ``clips`` (camera id -> video file, image folder or folder holding ``masks/``) through the
    site's pipeline and return each camera's :class:`CameraCheck` (the site's cameras without a clip
    are left out of the replay)."""
    from fusion_server.consistency import AlarmRule
    from fusion_server.pipeline import FusionPipeline
    from fusion_server.replay import replay

    unknown = sorted(set(clips) - set(site.camera_ids))
    if unknown:
        raise ValueError(f"--clip: no camera {', '.join(unknown)} in site {site.name} (cameras: {', '.join(site.camera_ids)})")
    if len(clips) < 3:
        raise ValueError(f"--clip: give clips of at least 3 cameras (each is judged against two others or more), got {len(clips)}")
    cams = list(clips)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for cam, clip in clips.items():
            path = Path(clip).resolve()
            if not path.exists():
                raise ValueError(f"--clip {cam}={clip}: no such file or folder")
            folder = root / "input" / cam
            if path.is_dir():
                folder.parent.mkdir(parents=True, exist_ok=True)
                folder.symlink_to(path, target_is_directory=True)
            else:
                folder.mkdir(parents=True)
                (folder / f"video{path.suffix.lower()}").symlink_to(path)
        loaded = site.load_cameras()
        pipeline = FusionPipeline.from_site(site, cameras={c: loaded[c] for c in cams}, cache_dir=cache_dir,
                                            min_cameras=min(site.carving.min_cameras, len(cams)))
        pipeline.consistency.history = []
        replay(site, root / "run", input_dir=root / "input", cameras=cams, max_frames=max_frames, pipeline=pipeline)
        measured = pipeline.consistency.history
    rule = AlarmRule(cams, pipeline.consistency.params)
    referenced = {c for c in cams if site.camera(c).view_reference}
    out = []
    for cam in cams:
        view_deg = pipeline.consistency.view_deg(cam) if cam in referenced else None
        views = [m for m in measured if m.cam == cam and m.offset_px is not None]
        if not views:
            out.append(CameraCheck(cam, 0, None, None, None, view_deg))
            continue
        fits = [rule.fits(m, (0.0, 0.0)) for m in views]
        out.append(CameraCheck(cam, len(views), sum(fits) / len(fits),
                               (statistics.median(m.offset_px[0] for m in views),
                                statistics.median(m.offset_px[1] for m in views)),
                               statistics.median(m.agreement for m in views), view_deg))
    return out
