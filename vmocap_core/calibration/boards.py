"""Calibration targets: checkerboards and ChArUco boards, with their detectors.

A board knows the 3D coordinates of its corners in its own frame (metres, z = 0 plane) and
finds them in a grayscale image, returning corner ids (rows of `object_points`) and pixels.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import CalibrationError

INCH = 0.0254


@dataclass
class Detection:
    """Board corners found in one image: ids index `Board.object_points`."""

    ids: np.ndarray  # (n,) int
    uv: np.ndarray  # (n, 2) float64 pixels
    markers: int = 0  # ArUco markers seen (ChArUco only), for diagnostics
    mirrored: bool = False  # found in the horizontally flipped image (board seen from behind)


class Board:
    """Base class: `object_points` (N, 3) and `detect(gray) -> Detection | None`."""

    kind = "board"
    object_points: np.ndarray
    min_corners = 6  # fewer corners make PnP / Zhang ill-conditioned
    # A board whose detector may number its corners from either end (a chessboard has no
    # marked origin): `flip` is the board-frame transform of that renumbering, else None.
    flip: tuple[np.ndarray, np.ndarray] | None = None

    def flip_ids(self, ids: np.ndarray) -> np.ndarray:
        return len(self.object_points) - 1 - np.asarray(ids)

    def detect(self, gray: np.ndarray) -> Detection | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:  # pragma: no cover - abstract
        raise NotImplementedError


class CheckerBoard(Board):
    """A chessboard with `cols` x `rows` inner corners, `square` metres apart."""

    kind = "checkerboard"

    def __init__(self, cols: int, rows: int, square: float) -> None:
        if cols < 2 or rows < 2 or square <= 0:
            raise CalibrationError(f"checkerboard: need >= 2x2 inner corners and a positive square, got {cols}x{rows}, {square}")
        self.cols, self.rows, self.square = int(cols), int(rows), float(square)
        grid = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)  # row-major, x fastest
        self.object_points = np.hstack([grid * self.square, np.zeros((len(grid), 1))])
        self.min_corners = len(grid)  # a chessboard is found whole or not at all
        # corner k <-> corner N-1-k: a half turn about the board normal through its centre
        size = np.array([(self.cols - 1) * self.square, (self.rows - 1) * self.square, 0.0])
        self.flip = (np.diag([-1.0, -1.0, 1.0]), size)

    def describe(self) -> str:
        return f"checkerboard {self.cols}x{self.rows} inner corners, square {self.square * 100:.2f} cm"

    def _find(self, gray: np.ndarray) -> tuple[np.ndarray, tuple[int, int]] | None:
        """Corners and the pattern size they were found with, on an image reduced to ~1000 px
        (refined at full resolution afterwards): the classic detector, then the sector-based
        one (more robust to blur and uneven light), then the classic one at full size."""
        scale = min(1.0, 1000.0 / max(gray.shape))
        small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else gray
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        patterns = ((self.cols, self.rows), (self.rows, self.cols))
        tries = [(lambda p: cv2.findChessboardCorners(small, p, flags=flags), scale),
                 (lambda p: cv2.findChessboardCornersSB(small, p, flags=cv2.CALIB_CB_NORMALIZE_IMAGE), scale)]
        if scale < 1:  # last resort: full resolution (slow on large images)
            tries.append((lambda p: cv2.findChessboardCorners(gray, p, flags=flags | cv2.CALIB_CB_FAST_CHECK), 1.0))
        for find, sc in tries:
            for pattern in patterns:
                ok, corners = find(pattern)
                if ok:
                    return corners.reshape(-1, 2) / sc, pattern
        return None

    def detect(self, gray: np.ndarray) -> Detection | None:
        found = self._find(gray)
        if found is None:
            return None
        corners, pattern = found
        if pattern != (self.cols, self.rows):
            # Found transposed (board seen rotated by 90 degrees): reorder to our row-major ids.
            corners = corners.reshape(self.cols, self.rows, 2).transpose(1, 0, 2).reshape(-1, 2)
        win = max(3, int(round(max(gray.shape) / 250)))
        corners = cv2.cornerSubPix(
            gray, corners.astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1),
            (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.01),
        )
        return Detection(np.arange(len(self.object_points)), corners.reshape(-1, 2).astype(np.float64))


class CharucoBoard(Board):
    """A ChArUco board: `cols` x `rows` squares, ArUco markers in the white squares."""

    kind = "charuco"

    def __init__(self, cols: int, rows: int, square: float, marker: float, dictionary: str = "DICT_4X4_50",
                 inverted: bool = False, legacy: bool = False) -> None:
        if not hasattr(cv2.aruco, dictionary):
            raise CalibrationError(f"charuco board: unknown ArUco dictionary '{dictionary}'")
        if not 0 < marker < square:
            raise CalibrationError(f"charuco board: marker size {marker} must be in (0, square={square})")
        self.cols, self.rows = int(cols), int(rows)
        self.square, self.marker = float(square), float(marker)
        self.dictionary, self.inverted = dictionary, bool(inverted)
        dic = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        self._board = cv2.aruco.CharucoBoard((self.cols, self.rows), self.square, self.marker, dic)
        self._board.setLegacyPattern(bool(legacy))
        self.object_points = np.asarray(self._board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
        self._detector = cv2.aruco.CharucoDetector(self._board)
        self.n_markers = len(self._board.getIds())

    def describe(self) -> str:
        inv = ", inverted" if self.inverted else ""
        return (f"charuco {self.cols}x{self.rows} squares of {self.square * 100:.2f} cm, markers "
                f"{self.marker * 100:.2f} cm, {self.dictionary}{inv}")

    def _detect(self, img: np.ndarray) -> Detection:
        corners, ids, _mc, mids = self._detector.detectBoard(np.ascontiguousarray(img))
        n_markers = 0 if mids is None else int(np.count_nonzero(mids.ravel() < self.n_markers))
        if ids is None or len(ids) == 0:
            return Detection(np.zeros(0, int), np.zeros((0, 2)), n_markers)
        return Detection(ids.ravel().astype(int), corners.reshape(-1, 2).astype(np.float64), n_markers)

    def detect(self, gray: np.ndarray) -> Detection | None:
        img = 255 - gray if self.inverted else gray  # a board printed white-on-black
        det = self._detect(img)
        if len(det.ids) >= self.min_corners:
            return det
        # A camera facing the printed side's back sees the pattern through the paper, mirrored:
        # ArUco codes then do not decode. Decode in the flipped image and map the pixels back;
        # the corner ids are physical, so the board geometry is unchanged.
        flipped = self._detect(img[:, ::-1])
        if len(flipped.ids) > len(det.ids):
            flipped.uv[:, 0] = img.shape[1] - 1 - flipped.uv[:, 0]
            flipped.mirrored = True
            return flipped
        return det


def _parse_dims(text: str) -> tuple[int, int]:
    try:
        a, b = text.lower().split("x")
        return int(a), int(b)
    except ValueError:
        raise CalibrationError(f"board size '{text}': expected COLSxROWS, e.g. 7x4") from None


def load_board(spec: str) -> Board:
    """A board from a spec string or a TOML file.

    - ``checkerboard:COLSxROWS:SQUARE_M`` (inner corners), e.g. ``checkerboard:7x4:0.06``
    - ``charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT[:inverted]`` (squares), e.g.
      ``charuco:4x5:0.054:0.0405:DICT_4X4_1000:inverted``
    - a ``.toml`` file in caliscope's ``charuco.toml`` layout (columns, rows, dictionary,
      square_size_override_cm or board size + units, aruco_scale, inverted, legacy_pattern).
    """
    path = Path(spec)
    if spec.endswith(".toml"):
        if not path.is_file():
            raise CalibrationError(f"board file {spec} does not exist")
        d = tomllib.loads(path.read_text())
        d = d.get("charuco", d)
        try:
            cols, rows = int(d["columns"]), int(d["rows"])
            if d.get("square_size_override_cm"):
                square = float(d["square_size_override_cm"]) / 100.0
            else:
                unit = INCH if d.get("units", "inch") == "inch" else 0.01
                square = min(float(d["board_width"]) / cols, float(d["board_height"]) / rows) * unit
            marker = square * float(d.get("aruco_scale", 0.75))
            return CharucoBoard(cols, rows, square, marker, str(d.get("dictionary", "DICT_4X4_50")),
                                inverted=bool(d.get("inverted", False)), legacy=bool(d.get("legacy_pattern", False)))
        except KeyError as exc:
            raise CalibrationError(f"board file {spec}: missing field {exc}") from None
    parts = spec.split(":")
    try:
        if parts[0] == "checkerboard" and len(parts) == 3:
            cols, rows = _parse_dims(parts[1])
            return CheckerBoard(cols, rows, float(parts[2]))
        if parts[0] == "charuco" and len(parts) in (5, 6):
            cols, rows = _parse_dims(parts[1])
            inverted = len(parts) == 6 and parts[5] == "inverted"
            return CharucoBoard(cols, rows, float(parts[2]), float(parts[3]), parts[4], inverted=inverted)
    except ValueError as exc:
        raise CalibrationError(f"board '{spec}': {exc}") from None
    raise CalibrationError(
        f"board '{spec}': expected checkerboard:COLSxROWS:SQUARE, charuco:COLSxROWS:SQUARE:MARKER:DICT[:inverted] or a .toml file"
    )
