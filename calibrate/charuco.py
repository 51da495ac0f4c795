"""The ChArUco board: a chessboard with an ArUco marker in each white square, so that every inner
corner can be named from the markers around it, and a view of part of the board still says which
corners it shows.

That is what a lens calibration wants of a fisheye or a strongly bent lens: views of the board
half out of the image, at its edges, where the lens bends most, and where a plain chessboard
(:mod:`.board`), which must be seen whole, is not found.

The board is counted in squares, ``cols x rows``, as OpenCV and the board generators count it
(``cv2.aruco.CharucoBoard``); its ``(cols - 1) x (rows - 1)`` inner corners are the points a
calibration uses. Its frame is OpenCV's: origin at the outer corner of the first square, X along
the first row of the printed sheet, Y down the sheet, Z = X x Y into it; inner corner ``id`` lies
at ``board.object_points()[id]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

DICTIONARIES = {
    **{f"{bits}x{bits}_{count}": getattr(cv2.aruco, f"DICT_{bits}X{bits}_{count}")
       for bits in (4, 5, 6, 7) for count in (50, 100, 250, 1000)},
    "aruco_original": cv2.aruco.DICT_ARUCO_ORIGINAL,
    "apriltag_16h5": cv2.aruco.DICT_APRILTAG_16h5,
    "apriltag_25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "apriltag_36h10": cv2.aruco.DICT_APRILTAG_36h10,
    "apriltag_36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "aruco_mip_36h12": cv2.aruco.DICT_ARUCO_MIP_36h12,
}
"""The marker dictionaries by name: ``'5x5_100'`` is ``cv2.aruco.DICT_5X5_100``."""
MARKER_SHARE = 0.75
"""The marker side as a share of the square side, when not given."""
FACE_UP = np.diag([1.0, -1.0, -1.0])
"""The board's frame turned over about X: a board lying face up on the floor, its frame's Z (into the
sheet) pointing down, has this rotation between its frame and a floor frame with Z up."""
MIN_CORNERS = 6
"""A view counts when it shows at least this many inner corners, not all on one line."""


@dataclass(frozen=True)
class CharucoBoard:
    """A ChArUco board: ``cols`` squares along a row, ``rows`` along a column, squares of
    ``square_m`` metres, markers of ``marker_m`` metres from the dictionary named ``dictionary``
    (a key of :data:`DICTIONARIES`)."""

    cols: int
    rows: int
    square_m: float
    marker_m: float
    dictionary: str

    def __post_init__(self) -> None:
        for name in ("cols", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 3 <= value <= 40:
                raise ValueError(f"--board: ChArUco {name} must be a whole number of squares in 3..40, got {value!r}")
        if self.n < MIN_CORNERS:
            raise ValueError(f"--board {self.cols}x{self.rows}: a ChArUco board of so few squares has {self.n} inner "
                             f"corners; a view needs {MIN_CORNERS}")
        if not (math.isfinite(self.square_m) and 0.005 <= self.square_m <= 1.0):
            raise ValueError(f"--square-mm: the square size must lie in 5..1000 mm, got {self.square_m * 1000:g} mm")
        if not (math.isfinite(self.marker_m) and 0.0 < self.marker_m < self.square_m):
            raise ValueError(f"--marker-mm: the marker ({self.marker_m * 1000:g} mm) must be smaller than the square "
                             f"({self.square_m * 1000:g} mm)")
        if self.dictionary not in DICTIONARIES:
            raise ValueError(f"--charuco {self.dictionary!r}: unknown marker dictionary; one of "
                             f"{', '.join(DICTIONARIES)}")
        size = cv2.aruco.getPredefinedDictionary(DICTIONARIES[self.dictionary]).bytesList.shape[0]
        if self.markers > size:
            raise ValueError(f"--board {self.cols}x{self.rows}: a ChArUco board of so many squares has {self.markers} "
                             f"markers; --charuco {self.dictionary} has only {size}")

    @classmethod
    def parse(cls, text: str, square_mm: float, marker_mm: float | None, dictionary: str) -> "CharucoBoard":
        """``'7x5'`` (squares), the square and marker sizes in millimetres (marker None:
        :data:`MARKER_SHARE` of the square) and the dictionary's name (``'5x5_100'``, case and a
        ``DICT_`` prefix ignored); ValueError naming the option and the problem."""
        parts = str(text).lower().split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise ValueError(f"--board: expected a ChArUco board's squares as COLSxROWS, e.g. 7x5, got {text!r}")
        name = str(dictionary).strip().lower().removeprefix("dict_")
        marker_mm = MARKER_SHARE * float(square_mm) if marker_mm is None else float(marker_mm)
        return cls(int(parts[0]), int(parts[1]), float(square_mm) / 1000.0, marker_mm / 1000.0, name)

    @property
    def n(self) -> int:
        """The number of inner corners."""
        return (self.cols - 1) * (self.rows - 1)

    @property
    def markers(self) -> int:
        """The number of markers (one in every other square)."""
        return self.cols * self.rows // 2

    def opencv(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board of the same layout, in metres."""
        marks = cv2.aruco.getPredefinedDictionary(DICTIONARIES[self.dictionary])
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, marks)

    def object_points(self) -> np.ndarray:
        """(N, 3) float64 inner corners in the board frame, metres, by id (row-major)."""
        col, row = np.meshgrid(np.arange(1, self.cols), np.arange(1, self.rows))
        return np.stack([col.ravel(), row.ravel(), np.zeros(self.n)], axis=1) * self.square_m

    def describe(self) -> str:
        return (f"ChArUco {self.cols}x{self.rows} squares of {self.square_m * 1000:g} mm, "
                f"{self.dictionary} markers of {self.marker_m * 1000:g} mm")


class CharucoFinder:
    """Finds one board's inner corners in grey images (OpenCV's ``CharucoDetector``, kept between images)."""

    def __init__(self, board: CharucoBoard) -> None:
        self.board = board
        self._opencv_board = board.opencv()
        self._detector = cv2.aruco.CharucoDetector(self._opencv_board)

    def find(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The inner corners seen in ``gray`` ((H, W) uint8): ids (N,) int and (N, 2) float64 pixels;
        None when fewer than :data:`MIN_CORNERS` are seen or they lie on one line."""
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        ids = ids.ravel().astype(int)
        if self._opencv_board.checkCharucoCornersCollinear(ids):
            return None
        return ids, corners.reshape(-1, 2).astype(np.float64)
