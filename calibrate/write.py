"""Writing calibration files: all of them or none.

A camera's new calibration is written in the format, units and up axis its site entry already
declares, so the site file itself never changes: the file holds the camera in its calibration
frame, which the site's ``units``, ``up``, ``origin_m`` and ``yaw_deg`` place in the room
(:class:`common.calibration.WorldTransform`, inverted here). Every file is first written beside
its target under a temporary name and read back through the site's own loader, which must give
the intended camera; only then are the old files kept as ``<name>.bak`` and the new ones moved
into place.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from common.calibration import WorldTransform, load_calibration, save_voxelwatch
from common.camera import Camera, matrix_to_rodrigues

WRITABLE = ("opencv", "opencv-fisheye", "voxelwatch")


def write_intrinsics(camera: Camera, path: str | Path, centre_sd_px: tuple[float, float] | None = None) -> Path:
    """An intrinsics file: the project's TOML for ``.toml``, else OpenCV FileStorage (``.xml``,
    ``.yaml``, ``.yml``, ``.json``); the pose is the identity (a placeholder until the floor calibration).
    centre_sd_px: the principal point's standard deviations from the fit, kept for the floor calibration's
    bounds (:func:`common.calibration.lens_centre_sd`)."""
    path = Path(path)
    if path.suffix.lower() == ".toml":
        save_voxelwatch(camera, path, centre_sd_px)
    elif path.suffix.lower() in (".xml", ".yaml", ".yml", ".json"):
        _write_opencv(camera, path, centre_sd_px)
    else:
        raise ValueError(f"--out {path}: expected a .toml (voxelwatch) or .xml/.yaml/.json (OpenCV) file name")
    return path


def file_camera(world_camera: Camera, transform: WorldTransform) -> Camera:
    """The camera in its calibration frame (translation in calibration units) such that
    ``transform.apply`` gives ``world_camera`` back."""
    M = transform.rotation
    s = transform.scale_m
    o = np.asarray(transform.origin_m)
    # X_cal = M^T (X_w - o) / s
    return world_camera.with_world(M.T, -M.T @ o / s, scale=1.0 / s)


def write_site_calibrations(site, cameras: dict[str, Camera]) -> list[tuple[Path, Path | None]]:
    """Write each camera's calibration file of ``site`` (see the module text); returns (file, backup or None)."""
    plans = []
    for cam_id, world_cam in cameras.items():
        spec = site.camera(cam_id)
        if spec.format not in WRITABLE:
            raise ValueError(f"site file {site.source}: cameras[{site.camera_ids.index(cam_id)}].format: "
                             f"{spec.format} calibrations cannot be written; use one of {', '.join(WRITABLE)}")
        transform = WorldTransform(units=spec.units, up=spec.up, origin_m=spec.origin_m, yaw_deg=spec.yaw_deg)
        path = site.calibration_path(cam_id)
        if path.exists() and not os.access(path, os.W_OK) or not os.access(path.parent, os.W_OK):
            raise ValueError(f"calibration file {path}: cannot be replaced (no write permission)")
        plans.append((cam_id, world_cam, spec, transform, path))
    temps = []
    try:
        for cam_id, world_cam, spec, transform, path in plans:
            tmp = path.with_name(f".{path.stem}.new{path.suffix}")
            cal = file_camera(world_cam, transform)
            if spec.format == "voxelwatch":
                save_voxelwatch(cal, tmp)
            else:
                _write_opencv(cal, tmp)
            temps.append(tmp)
            back = load_calibration(tmp, spec.format, cam_id, transform, image_size=spec.resolution)
            if np.abs(back.center - world_cam.center).max() > 1e-6 or np.abs(back.R - world_cam.R).max() > 1e-9:
                raise ValueError(f"calibration file {path}: the written file does not read back as the camera")
        done = []
        for (cam_id, _, _, _, path), tmp in zip(plans, temps):
            backup = None
            if path.exists():
                backup = path.with_name(path.name + ".bak")
                shutil.copy2(path, backup)
            os.replace(tmp, path)
            done.append((path, backup))
        return done
    finally:
        for tmp in temps:
            if tmp.exists():
                tmp.unlink()


def _write_opencv(camera: Camera, path: Path, centre_sd_px: tuple[float, float] | None = None) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("CameraMatrix", np.asarray(camera.K, dtype=np.float64))
        fs.write("DistortionCoeffs", np.asarray(camera.dist, dtype=np.float64).reshape(1, -1))
        fs.write("Rotation", matrix_to_rodrigues(camera.R).reshape(3, 1))
        fs.write("Translation", np.asarray(camera.t, dtype=np.float64).reshape(3, 1))
        if centre_sd_px is not None:
            fs.write("PrincipalPointStd", np.asarray(centre_sd_px, dtype=np.float64).reshape(2, 1))
    finally:
        fs.release()
