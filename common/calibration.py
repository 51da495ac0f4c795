"""Calibration loaders: every supported file format to a :class:`~common.camera.Camera`
in the design's world frame (metres, right-handed, Z up, floor at Z = 0).

Formats (``load_calibration(path, fmt, ...)``):

* ``opencv`` / ``opencv-fisheye``: OpenCV FileStorage (XML, YAML or JSON) with
  the intrinsics under ``CameraMatrix`` | ``camera_matrix`` | ``cameraMatrix`` |
  ``mtx`` | ``K``, the distortion under ``DistortionCoeffs`` |
  ``distortion_coefficients`` | ``distCoeffs`` | ``dist_coeffs`` | ``dist`` |
  ``D``, the rotation (Rodrigues 3-vector or 3x3 matrix, world -> camera)
  under ``Rotation`` | ``rvec`` | ``rotation`` | ``R`` and the translation
  under ``Translation`` | ``tvec`` | ``translation`` | ``T``. The image size comes
  from ``image_width``/``image_height``, ``ImageSize``/``image_size``
  (``[width, height]``) or ``width``/``height`` when present, else from the
  ``image_size`` argument.
* ``pets-tsai``: the PETS 2009 Tsai XML: ``<Geometry width height dpx dpy/>``,
  ``<Intrinsic focal kappa1 cx cy sx/>``, ``<Extrinsic tx ty tz rx ry rz/>``;
  millimetres, ``R = Rz(rz) Ry(ry) Rx(rx)`` (radians), world -> camera.
* ``voxelwatch``: the project's own TOML::

      # voxelwatch camera calibration
      id = "cam1"                 # informational
      model = "pinhole"           # pinhole | fisheye | tsai
      width = 640                 # image size, pixels
      height = 480
      camera_matrix = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
      distortion = [k1, k2, p1, p2, k3]    # pinhole: 0/4/5/8/12/14 values; fisheye: k1..k4; tsai: []
      rotation = [[...], [...], [...]]     # world -> camera 3x3, or instead:
      # rvec = [rx, ry, rz]                # Rodrigues vector, world -> camera
      tvec_m = [tx, ty, tz]                # metres, X_cam = R X_world + t
      centre_sd_px = [sx, sy]              # optional: the principal point's standard deviations from
                                           # the lens fit (``calibrate intrinsics``; OpenCV files:
                                           # PrincipalPointStd)

      [tsai]                      # model = "tsai" only (camera_matrix is then optional)
      focal_mm = 5.55
      kappa1 = 0.0051             # 1/mm^2
      dpx = 0.00513               # mm per pixel
      dpy = 0.00465
      sx = 1.09
      cx = 324.2                  # pixels
      cy = 282.6

  :func:`save_voxelwatch` writes it (rotation as a matrix, floats with full
  precision, so a save/load round trip is exact).

World transform: a calibration is made in its own frame (the board's, in its
own length unit, maybe with Z down). :class:`WorldTransform` places that frame
in the world: with ``s`` the unit's length in metres, ``M = Rz(yaw) F`` where
``F = I`` for up ``+z`` and ``F = diag(1, -1, -1)`` (180 degrees about X,
right-handed) for up ``-z``, and ``o`` the calibration origin in the world,

    X_w = M (s X_cal) + o,    i.e.    s X_cal = M^T (X_w - o).

A camera ``X_cam = R X_cal + t`` (calibration units) becomes, in metres,
``X_cam_m = s X_cam = R M^T (X_w - o) + s t``, so ``R' = R M^T`` and
``t' = s t - R M^T o``; the intrinsics do not change.

Every problem raises :class:`CalibrationError` naming the file, the key and the
problem.
"""

from __future__ import annotations

import math
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.camera import Camera, TsaiIntrinsics, rodrigues_to_matrix

FORMATS = ("opencv", "opencv-fisheye", "pets-tsai", "voxelwatch")
UNITS_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}

K_KEYS = ("CameraMatrix", "camera_matrix", "cameraMatrix", "mtx", "K")
DIST_KEYS = ("DistortionCoeffs", "distortion_coefficients", "distCoeffs", "dist_coeffs", "dist", "D")
ROT_KEYS = ("Rotation", "rvec", "rotation", "R")
TRANS_KEYS = ("Translation", "tvec", "translation", "T")

_ORTHO_FIX_TOL = 1e-3


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message names file, key and problem."""


@dataclass(frozen=True)
class WorldTransform:
    """Where a calibration's frame sits in the world frame (see the module docstring).

    units: ``'m'`` | ``'cm'`` | ``'mm'`` or a positive float, the calibration's length unit in metres.
    up: ``'+z'`` | ``'-z'``, the calibration's up axis.
    origin_m: (3,) the calibration origin's position in the world frame, metres.
    yaw_deg: rotation of the calibration frame about the world Z axis, degrees (after the up flip).
    """

    units: str | float = "m"
    up: str = "+z"
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.units, str):
            if self.units not in UNITS_M:
                raise ValueError(f"units must be one of {sorted(UNITS_M)} or a positive number, got {self.units!r}")
        elif isinstance(self.units, bool) or not isinstance(self.units, (int, float)) or not (
            math.isfinite(self.units) and self.units > 0
        ):
            raise ValueError(f"units must be one of {sorted(UNITS_M)} or a positive number, got {self.units!r}")
        if self.up not in ("+z", "-z"):
            raise ValueError(f"up must be '+z' or '-z', got {self.up!r}")
        origin = tuple(float(v) for v in np.asarray(self.origin_m, dtype=np.float64).ravel())
        if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
            raise ValueError(f"origin_m must be 3 finite numbers, got {self.origin_m!r}")
        object.__setattr__(self, "origin_m", origin)
        if isinstance(self.yaw_deg, bool) or not isinstance(self.yaw_deg, (int, float)) or not math.isfinite(self.yaw_deg):
            raise ValueError(f"yaw_deg must be a finite number, got {self.yaw_deg!r}")

    @property
    def scale_m(self) -> float:
        """Length of one calibration unit in metres."""
        return UNITS_M[self.units] if isinstance(self.units, str) else float(self.units)

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) float64 ``M``: calibration axes to world axes."""
        flip = np.diag([1.0, -1.0, -1.0]) if self.up == "-z" else np.eye(3)
        a = math.radians(self.yaw_deg)
        yaw = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        return yaw @ flip

    def points_to_world(self, points_cal) -> np.ndarray:
        """(N, 3) points in calibration units and frame -> (N, 3) float64 world points, metres."""
        p = np.asarray(points_cal, dtype=np.float64).reshape(-1, 3)
        return self.scale_m * p @ self.rotation.T + np.asarray(self.origin_m)

    def apply(self, camera: Camera) -> Camera:
        """A camera calibrated in the calibration frame (t in calibration units) -> world frame, metres."""
        return camera.with_world(self.rotation, np.asarray(self.origin_m), scale=self.scale_m)


def load_calibration(
    path: str | Path,
    fmt: str,
    cam_id: str,
    transform: WorldTransform | None = None,
    *,
    image_size: tuple[int, int] | None = None,
) -> Camera:
    """Load one camera from ``path`` in format ``fmt`` (one of :data:`FORMATS`), in the world frame.

    ``image_size`` ``(width, height)`` is used when the file does not give the size; when it does,
    a different ``image_size`` is an error (the calibration would not fit the images).
    """
    if fmt == "opencv":
        return load_opencv(path, cam_id, transform, model="pinhole", image_size=image_size)
    if fmt == "opencv-fisheye":
        return load_opencv(path, cam_id, transform, model="fisheye", image_size=image_size)
    if fmt == "pets-tsai":
        return load_pets_tsai(path, cam_id, transform, image_size=image_size)
    if fmt == "voxelwatch":
        return load_voxelwatch(path, cam_id, transform, image_size=image_size)
    raise CalibrationError(f"calibration file {path}: unknown format {fmt!r}; expected one of {FORMATS}")


def load_opencv(
    path: str | Path,
    cam_id: str,
    transform: WorldTransform | None = None,
    *,
    model: str = "pinhole",
    image_size: tuple[int, int] | None = None,
) -> Camera:
    """An OpenCV FileStorage calibration (see the module docstring for the keys)."""
    path = Path(path)
    if model not in ("pinhole", "fisheye"):
        raise ValueError(f"model must be 'pinhole' or 'fisheye', got {model!r}")
    _check_file(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        opened = fs.isOpened()
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"calibration file {path}: not readable as OpenCV FileStorage: {_cv_reason(exc)}") from None
    if not opened:
        raise CalibrationError(f"calibration file {path}: not readable as OpenCV FileStorage")
    try:
        K = _fs_array(fs, path, K_KEYS, "camera matrix")
        dist = _fs_array(fs, path, DIST_KEYS, "distortion coefficients")
        rot = _fs_array(fs, path, ROT_KEYS, "rotation")
        trans = _fs_array(fs, path, TRANS_KEYS, "translation")
        size = _fs_size(fs, path)
    finally:
        fs.release()
    K = _shaped(path, K, (3, 3))
    dist_v = dist[1].ravel()
    if model == "fisheye" and dist_v.size != 4:
        raise CalibrationError(f"calibration file {path}: {dist[0]}: fisheye needs 4 coefficients (k1..k4), got {dist_v.size}")
    if model == "pinhole" and dist_v.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(
            f"calibration file {path}: {dist[0]}: expected 4, 5, 8, 12 or 14 coefficients, got {dist_v.size}"
        )
    R = _rotation(path, rot)
    t = _shaped(path, trans, (3,))
    width, height = _pick_size(path, size, image_size)
    return _build(path, transform, id=cam_id, model=model, width=width, height=height, K=K, dist=dist_v, R=R, t=t)


def lens_centre_sd(path: str | Path, fmt: str) -> tuple[float, float] | None:
    """The principal point's standard deviations (px) a lens file carries from its fit (``centre_sd_px`` in the
    project's TOML, ``PrincipalPointStd`` in OpenCV FileStorage), or None where it carries none."""
    path = Path(path)
    if fmt == "voxelwatch":
        try:
            value = tomllib.loads(path.read_text(encoding="utf-8")).get("centre_sd_px")
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            return None   # the loader says what is wrong with the file
        label = "centre_sd_px"
    elif fmt in ("opencv", "opencv-fisheye"):
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError):
            return None
        try:
            node = fs.getNode("PrincipalPointStd") if fs.isOpened() else None
            value = None if node is None or node.empty() else node.mat()
            value = None if value is None else value.ravel().tolist()
        finally:
            fs.release()
        label = "PrincipalPointStd"
    else:
        return None
    if value is None:
        return None
    try:
        sd = [float(v) for v in value] if not isinstance(value, (str, bool)) else []
    except (TypeError, ValueError):
        sd = []
    if len(sd) != 2 or not all(math.isfinite(v) and v >= 0.0 for v in sd) or any(isinstance(v, bool) for v in value):
        raise CalibrationError(f"calibration file {path}: {label}: expected two standard deviations "
                               f"(pixels, not negative), got {value!r}")
    return sd[0], sd[1]


def load_pets_tsai(
    path: str | Path,
    cam_id: str,
    transform: WorldTransform | None = None,
    *,
    image_size: tuple[int, int] | None = None,
) -> Camera:
    """A PETS 2009 Tsai XML calibration (world units millimetres: use ``units='mm'``)."""
    path = Path(path)
    _check_file(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise CalibrationError(f"calibration file {path}: not readable as XML: {exc}") from None
    values: dict[str, float] = {}
    wanted = {
        "Geometry": ("width", "height", "dpx", "dpy"),
        "Intrinsic": ("focal", "kappa1", "cx", "cy", "sx"),
        "Extrinsic": ("tx", "ty", "tz", "rx", "ry", "rz"),
    }
    for tag, names in wanted.items():
        el = root.find(tag)
        if el is None:
            raise CalibrationError(f"calibration file {path}: missing element <{tag}> (needs {', '.join(names)})")
        for name in names:
            raw = el.get(name)
            if raw is None:
                raise CalibrationError(f"calibration file {path}: {tag}.{name}: missing attribute")
            try:
                value = float(raw)
            except ValueError:
                raise CalibrationError(f"calibration file {path}: {tag}.{name}: not a number: {raw!r}") from None
            if not math.isfinite(value):
                raise CalibrationError(f"calibration file {path}: {tag}.{name}: not finite: {raw!r}")
            values[name] = value
    for name in ("width", "height"):
        if values[name] != int(values[name]) or values[name] <= 0:
            raise CalibrationError(f"calibration file {path}: Geometry.{name}: expected a positive integer, got {values[name]!r}")
    for name, tag in (("dpx", "Geometry"), ("dpy", "Geometry"), ("focal", "Intrinsic"), ("sx", "Intrinsic")):
        if values[name] <= 0:
            raise CalibrationError(f"calibration file {path}: {tag}.{name}: must be positive, got {values[name]!r}")
    tsai = TsaiIntrinsics(focal_mm=values["focal"], kappa1=values["kappa1"], dpx=values["dpx"], dpy=values["dpy"],
                          sx=values["sx"], cx=values["cx"], cy=values["cy"])
    width, height = _pick_size(path, ("Geometry", (int(values["width"]), int(values["height"]))), image_size)
    R = tsai_rotation(values["rx"], values["ry"], values["rz"])
    t = np.array([values["tx"], values["ty"], values["tz"]])
    return _build(path, transform, id=cam_id, model="tsai", width=width, height=height, K=tsai.camera_matrix(),
                  dist=np.zeros(0), R=R, t=t, tsai=tsai)


def load_voxelwatch(
    path: str | Path,
    cam_id: str,
    transform: WorldTransform | None = None,
    *,
    image_size: tuple[int, int] | None = None,
) -> Camera:
    """The project's TOML calibration (module docstring). Its ``tvec_m`` is in metres, so
    ``transform.units`` must be metres; ``up``, ``origin_m`` and ``yaw_deg`` apply."""
    path = Path(path)
    _check_file(path)
    if transform is not None and transform.scale_m != 1.0:
        raise CalibrationError(
            f"calibration file {path}: units: voxelwatch calibrations are in metres (tvec_m), got units {transform.units!r}"
        )
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise CalibrationError(f"calibration file {path}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"calibration file {path}: not valid TOML: {exc}") from None
    model = doc.get("model")
    if model not in ("pinhole", "fisheye", "tsai"):
        raise CalibrationError(f"calibration file {path}: model: expected 'pinhole', 'fisheye' or 'tsai', got {model!r}")
    size = []
    for key in ("width", "height"):
        value = doc.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise CalibrationError(f"calibration file {path}: {key}: expected a positive integer, got {value!r}")
        size.append(value)
    width, height = _pick_size(path, ("width/height", tuple(size)), image_size)
    tsai = None
    if model == "tsai":
        table = doc.get("tsai")
        if not isinstance(table, dict):
            raise CalibrationError(f"calibration file {path}: tsai: model 'tsai' needs a [tsai] table")
        params = {}
        for key in ("focal_mm", "kappa1", "dpx", "dpy", "sx", "cx", "cy"):
            params[key] = _toml_number(path, table, key, f"tsai.{key}")
        try:
            tsai = TsaiIntrinsics(**params)
        except ValueError as exc:
            raise CalibrationError(f"calibration file {path}: tsai: {exc}") from None
        K = _toml_array(path, doc, "camera_matrix", (3, 3)) if "camera_matrix" in doc else tsai.camera_matrix()
        if not np.allclose(K, tsai.camera_matrix(), rtol=1e-9, atol=1e-9):
            raise CalibrationError(f"calibration file {path}: camera_matrix: disagrees with the [tsai] table")
        K = tsai.camera_matrix()
    else:
        K = _toml_array(path, doc, "camera_matrix", (3, 3))
    dist = _toml_array(path, doc, "distortion", None).ravel() if "distortion" in doc else np.zeros(0)
    if "rotation" in doc and "rvec" in doc:
        raise CalibrationError(f"calibration file {path}: rotation/rvec: give one of them, not both")
    if "rotation" in doc:
        R = _rotation(path, ("rotation", _toml_array(path, doc, "rotation", (3, 3))))
    elif "rvec" in doc:
        R = _rotation(path, ("rvec", _toml_array(path, doc, "rvec", (3,))))
    else:
        raise CalibrationError(f"calibration file {path}: rotation: missing (tried 'rotation', 'rvec')")
    t = _toml_array(path, doc, "tvec_m", (3,))
    return _build(path, transform, id=cam_id, model=model, width=width, height=height, K=K, dist=dist, R=R, t=t, tsai=tsai)


def save_voxelwatch(camera: Camera, path: str | Path, centre_sd_px: tuple[float, float] | None = None) -> None:
    """Write ``camera`` (world frame, metres) as a voxelwatch TOML calibration, with the principal point's
    standard deviations from its lens fit when given."""
    lines = [
        "# voxelwatch camera calibration (world frame: metres, Z up; X_cam = R X_world + t)",
        f"id = {_toml_str(camera.id)}",
        f"model = {_toml_str(camera.model)}",
        f"width = {camera.width}",
        f"height = {camera.height}",
        f"camera_matrix = {_toml_matrix(camera.K)}",
        f"distortion = {_toml_vector(camera.dist)}",
        f"rotation = {_toml_matrix(camera.R)}",
        f"tvec_m = {_toml_vector(camera.t)}",
    ]
    if centre_sd_px is not None:
        lines.append(f"centre_sd_px = {_toml_vector(centre_sd_px)}")
    if camera.tsai is not None:
        ts = camera.tsai
        lines += ["", "[tsai]"] + [
            f"{name} = {_toml_float(getattr(ts, name))}" for name in ("focal_mm", "kappa1", "dpx", "dpy", "sx", "cx", "cy")
        ]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def tsai_rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """(3, 3) float64 ``Rz(rz) @ Ry(ry) @ Rx(rx)`` (radians), Tsai's world -> camera rotation."""
    cx, sx = math.cos(rx), math.sin(rx)
    cy, sy = math.cos(ry), math.sin(ry)
    cz, sz = math.cos(rz), math.sin(rz)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


# ---------------------------------------------------------------------- helpers


def _check_file(path: Path) -> None:
    if not path.exists():
        raise CalibrationError(f"calibration file {path}: not found")
    if not path.is_file():
        raise CalibrationError(f"calibration file {path}: not a regular file")


def _cv_reason(exc: BaseException) -> str:
    cause = exc.__cause__ if exc.__cause__ is not None else exc
    text = str(cause).strip().splitlines()
    reason = text[-1] if text else type(cause).__name__
    return reason.split(") ", 1)[-1] if "error: (" in reason else reason


def _fs_value(node) -> np.ndarray | None:
    """A FileNode as a float64 array: an opencv-matrix, a (nested) sequence or a number."""
    if node.isMap():
        mat = node.mat()
        return None if mat is None else np.asarray(mat, dtype=np.float64)
    if node.isSeq():
        rows = []
        for i in range(node.size()):
            item = _fs_value(node.at(i))
            if item is None:
                return None
            rows.append(item)
        try:
            return np.array(rows, dtype=np.float64)
        except ValueError:
            return None
    if node.isReal() or node.isInt():
        return np.array(node.real(), dtype=np.float64)
    return None


def _fs_array(fs, path: Path, names: tuple[str, ...], what: str) -> tuple[str, np.ndarray]:
    for name in names:
        node = fs.getNode(name)
        if node.empty() or node.isNone():
            continue
        value = _fs_value(node)
        if value is None:
            raise CalibrationError(f"calibration file {path}: {name}: not a numeric matrix or list ({what})")
        if not np.all(np.isfinite(value)):
            raise CalibrationError(f"calibration file {path}: {name}: non-finite values {value.ravel().tolist()}")
        return name, value
    raise CalibrationError(f"calibration file {path}: missing {what}; tried keys {', '.join(names)}")


def _fs_size(fs, path: Path) -> tuple[str, tuple[int, int]] | None:
    for wkey, hkey in (("image_width", "image_height"), ("width", "height"), ("imageWidth", "imageHeight")):
        w, h = fs.getNode(wkey), fs.getNode(hkey)
        if not w.empty() and not h.empty():
            pair = (_fs_value(w), _fs_value(h))
            if any(v is None or v.size != 1 for v in pair):
                raise CalibrationError(f"calibration file {path}: {wkey}/{hkey}: expected two numbers")
            return _size_of(path, f"{wkey}/{hkey}", pair[0].item(), pair[1].item())
    for key in ("ImageSize", "image_size", "imageSize"):
        node = fs.getNode(key)
        if not node.empty():
            value = _fs_value(node)
            if value is None or value.size != 2:
                raise CalibrationError(f"calibration file {path}: {key}: expected [width, height]")
            return _size_of(path, key, *value.ravel().tolist())
    return None


def _size_of(path: Path, key: str, w: float, h: float) -> tuple[str, tuple[int, int]]:
    if not all(math.isfinite(v) and v == int(v) and v > 0 for v in (w, h)):
        raise CalibrationError(f"calibration file {path}: {key}: expected positive integers, got {w!r}, {h!r}")
    return key, (int(w), int(h))


def _pick_size(path: Path, from_file, image_size) -> tuple[int, int]:
    if image_size is not None:
        try:
            given = (int(image_size[0]), int(image_size[1]))
        except (TypeError, ValueError, IndexError):
            raise ValueError(f"image_size must be (width, height), got {image_size!r}") from None
        if len(image_size) != 2 or min(given) <= 0:
            raise ValueError(f"image_size must be (width, height) with positive values, got {image_size!r}")
    if from_file is not None:
        key, size = from_file
        if image_size is not None and given != size:
            raise CalibrationError(
                f"calibration file {path}: {key}: calibrated for {size[0]}x{size[1]} but the images are "
                f"{given[0]}x{given[1]}"
            )
        return size
    if image_size is None:
        raise CalibrationError(
            f"calibration file {path}: image size: not in the file (image_width/image_height, ImageSize, width/height) "
            "and not given"
        )
    return given


def _shaped(path: Path, named: tuple[str, np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
    name, value = named
    if value.size != int(np.prod(shape)) or (len(shape) == 2 and value.shape != shape):
        raise CalibrationError(f"calibration file {path}: {name}: expected shape {shape}, got {value.shape}")
    return value.reshape(shape)


def _rotation(path: Path, named: tuple[str, np.ndarray]) -> np.ndarray:
    name, value = named
    if value.size == 3:
        return rodrigues_to_matrix(value.ravel())
    if value.shape != (3, 3):
        raise CalibrationError(
            f"calibration file {path}: {name}: expected a Rodrigues 3-vector or a 3x3 matrix, got shape {value.shape}"
        )
    err = np.abs(value @ value.T - np.eye(3)).max()
    if err > _ORTHO_FIX_TOL or np.linalg.det(value) <= 0:
        raise CalibrationError(
            f"calibration file {path}: {name}: not a rotation matrix (|R R^T - I| = {err:.3g}, det = {np.linalg.det(value):.6g})"
        )
    if err < 1e-12:
        return value
    u, _, vt = np.linalg.svd(value)
    return u @ vt  # nearest rotation: removes rounding in stored matrices (float32 files)


def _build(path: Path, transform: WorldTransform | None, **fields) -> Camera:
    try:
        cam = Camera(**fields)
        return cam if transform is None else transform.apply(cam)
    except ValueError as exc:
        raise CalibrationError(f"calibration file {path}: {exc}") from None


def _toml_number(path: Path, table: dict, key: str, label: str) -> float:
    value = table.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CalibrationError(f"calibration file {path}: {label}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise CalibrationError(f"calibration file {path}: {label}: not finite: {value!r}")
    return float(value)


def _toml_array(path: Path, doc: dict, key: str, shape: tuple[int, ...] | None) -> np.ndarray:
    value = doc.get(key)
    try:
        arr = np.array(value, dtype=np.float64)
        if any(isinstance(v, bool) for v in np.array(value, dtype=object).ravel()):
            raise ValueError
    except (TypeError, ValueError):
        raise CalibrationError(f"calibration file {path}: {key}: expected numbers, got {value!r}") from None
    if shape is not None and arr.shape != shape:
        raise CalibrationError(f"calibration file {path}: {key}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"calibration file {path}: {key}: non-finite values {arr.ravel().tolist()}")
    return arr


def _toml_float(value: float) -> str:
    text = repr(float(value))
    if text in ("inf", "-inf", "nan"):
        raise ValueError(f"cannot write non-finite value {value!r}")
    return text


def _toml_vector(values) -> str:
    return "[" + ", ".join(_toml_float(v) for v in np.asarray(values).ravel()) + "]"


def _toml_matrix(matrix) -> str:
    return "[" + ", ".join(_toml_vector(row) for row in np.asarray(matrix)) + "]"


def _toml_str(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
