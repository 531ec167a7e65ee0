"""Calibration boards: geometry, printable images and detection.

Two kinds of board are supported:

- ``chessboard``: a plain black-and-white chessboard of ``squares_x`` by
  ``squares_y`` squares; its ``(squares_x-1) * (squares_y-1)`` inner corners are
  found by ``cv2.findChessboardCorners`` and refined by ``cv2.cornerSubPix``.
  It must be seen whole. Its orientation is fixed by handedness (the printed
  face is seen from the front) and by the colour of square (0, 0) (black); a
  board with ``squares_x + squares_y`` even looks the same turned by 180 deg,
  so its pose is ambiguous (:attr:`BoardSpec.symmetric`): fine for intrinsics,
  refused for extrinsics and hand-eye.
- ``charuco``: OpenCV's ChArUco board (ArUco markers in the white squares,
  ``cv2.aruco.CharucoBoard``, non-legacy layout: square (0, 0) black). Corners
  carry ids, so partial views count and the pose is never ambiguous.

Board frame (both kinds): origin at the outer corner of square (0, 0), x along
``squares_x``, y along ``squares_y`` (down the printed image), z into the board.
Corner ``k`` of either kind is the inner corner at
``((k % (squares_x-1) + 1) * s, (k // (squares_x-1) + 1) * s, 0)``, the same
numbering as OpenCV's ChArUco corner ids.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from .errors import CalibrationError

__all__ = ["BOARD_KINDS", "BoardSpec", "BoardDetection", "detect_board", "board_image"]

BOARD_KINDS = ("chessboard", "charuco")


@dataclass(frozen=True)
class BoardSpec:
    """Geometry of a calibration board.

    Attributes
    ----------
    kind : str
        ``"chessboard"`` or ``"charuco"``.
    squares_x, squares_y : int
        Number of squares along the board's x and y axes (>= 3 each).
    square_size : float
        Side of one square, m.
    marker_size : float or None
        ChArUco only: side of one ArUco marker, m (< ``square_size``).
    dictionary : str
        ChArUco only: an OpenCV predefined dictionary name, e.g. ``"DICT_5X5_100"``.
    """

    kind: str = "charuco"
    squares_x: int = 9
    squares_y: int = 6
    square_size: float = 0.035
    marker_size: float | None = 0.026
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self):
        if self.kind not in BOARD_KINDS:
            raise ValueError(f"board kind must be one of {BOARD_KINDS}, got {self.kind!r}")
        if int(self.squares_x) < 3 or int(self.squares_y) < 3:
            raise ValueError(f"a board needs at least 3x3 squares, got {self.squares_x}x{self.squares_y}")
        object.__setattr__(self, "squares_x", int(self.squares_x))
        object.__setattr__(self, "squares_y", int(self.squares_y))
        if not np.isfinite(self.square_size) or self.square_size <= 0:
            raise ValueError(f"square size must be a positive length in metres, got {self.square_size}")
        if self.kind == "charuco":
            if self.marker_size is None or not (0 < self.marker_size < self.square_size):
                raise ValueError(
                    f"a ChArUco board needs 0 < marker size < square size ({self.square_size} m), got {self.marker_size}")
            if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_5X5_100, DICT_6X6_250)")
            n_markers = (self.squares_x * self.squares_y) // 2
            n_dict = _dictionary(self.dictionary).bytesList.shape[0]
            if n_markers > n_dict:
                raise ValueError(f"{self.squares_x}x{self.squares_y} ChArUco needs {n_markers} markers, "
                                 f"{self.dictionary} has only {n_dict}")

    # -- geometry --------------------------------------------------------
    @property
    def inner_x(self) -> int:
        """Inner corners per row."""
        return self.squares_x - 1

    @property
    def inner_y(self) -> int:
        return self.squares_y - 1

    @property
    def n_corners(self) -> int:
        return self.inner_x * self.inner_y

    @property
    def size(self) -> tuple[float, float]:
        """Width and height of the square pattern, m (without margin)."""
        return self.squares_x * self.square_size, self.squares_y * self.square_size

    @property
    def symmetric(self) -> bool:
        """True when the pattern looks the same turned by 180 deg (chessboard
        with ``squares_x + squares_y`` even): its pose is then ambiguous."""
        return self.kind == "chessboard" and (self.squares_x + self.squares_y) % 2 == 0

    @property
    def P_board(self) -> np.ndarray:
        """Inner corners in the board frame, shape (n_corners, 3), m; row k is corner id k."""
        i, j = np.meshgrid(np.arange(self.inner_x), np.arange(self.inner_y))
        P = np.zeros((self.n_corners, 3))
        P[:, 0] = (i.ravel() + 1) * self.square_size
        P[:, 1] = (j.ravel() + 1) * self.square_size
        return P

    def describe(self) -> str:
        s = f"{self.kind} {self.squares_x}x{self.squares_y} squares of {self.square_size * 1e3:g} mm"
        if self.kind == "charuco":
            s += f", markers {self.marker_size * 1e3:g} mm {self.dictionary}"
        return s


@functools.lru_cache(maxsize=None)
def _dictionary(name: str):
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@functools.lru_cache(maxsize=16)
def _charuco(spec: BoardSpec):
    board = cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_size, spec.marker_size,
                                   _dictionary(spec.dictionary))
    board.setLegacyPattern(False)
    # The corner numbering of this module must be OpenCV's: checked once here.
    if not np.allclose(np.asarray(board.getChessboardCorners()), spec.P_board, atol=1e-9):
        raise RuntimeError("OpenCV's ChArUco corner layout differs from vespro's board frame")
    return board


def board_image(spec: BoardSpec, px_per_square: int = 64, margin_px: int = 0) -> np.ndarray:
    """The printable board, 8-bit grey.

    Parameters
    ----------
    spec : BoardSpec
    px_per_square : int
        Pixels per square side.
    margin_px : int
        White margin around the pattern, pixels.

    Returns
    -------
    ndarray, shape (squares_y * px + 2 margin, squares_x * px + 2 margin), uint8
        Pixel column u spans board x in ``[(u - margin) / px, (u + 1 - margin) / px] * square_size``
        (pixel edges, not centres, are at the square boundaries).
    """
    w, h = spec.squares_x * px_per_square, spec.squares_y * px_per_square
    if spec.kind == "charuco":
        img = _charuco(spec).generateImage((w, h), marginSize=0, borderBits=1)
    else:
        j, i = np.mgrid[0:h, 0:w] // px_per_square
        img = np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)
    if margin_px:
        img = cv2.copyMakeBorder(img, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)
    return img


@dataclass(frozen=True)
class BoardDetection:
    """Board corners found in one image.

    Attributes
    ----------
    ids : ndarray, shape (N,), int
        Corner ids (rows of :attr:`BoardSpec.P_board`), increasing.
    uv : ndarray, shape (N, 2)
        Pixel coordinates (OpenCV convention, distorted image).
    image_size : tuple
        ``(width, height)`` of the image, pixels.
    """

    ids: np.ndarray
    uv: np.ndarray
    image_size: tuple

    def __len__(self) -> int:
        return len(self.ids)


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {image.shape}")
    return image


def _min_neighbour_distance(spec: BoardSpec, ids: np.ndarray, uv: np.ndarray) -> float:
    """Smallest image distance between grid-adjacent detected corners, px."""
    pos = {int(k): p for k, p in zip(ids, uv)}
    d = []
    for k, p in pos.items():
        for nb in (k + 1 if (k + 1) % spec.inner_x else None, k + spec.inner_x):
            if nb is not None and nb in pos:
                d.append(np.linalg.norm(pos[nb] - p))
    return float(min(d)) if d else 0.0


def _refine(grey: np.ndarray, uv: np.ndarray, half_window: int) -> np.ndarray:
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    pts = uv.reshape(-1, 1, 2).astype(np.float32)
    cv2.cornerSubPix(grey, pts, (half_window, half_window), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(np.float64)


def _orient_chessboard(grey: np.ndarray, spec: BoardSpec, grid: np.ndarray) -> np.ndarray:
    """Reorder a detected corner grid (rows along board y) into board ids.

    ``findChessboardCorners`` may start at any corner of the pattern. A mirrored
    order (printed face seen from behind) is undone by handedness; of the two
    remaining orders (0 and 180 deg) the one that puts black where square
    (0, 0) and its colour class are is kept.
    """
    g = grid.reshape(spec.inner_y, spec.inner_x, 2)
    du = g[:, -1] - g[:, 0]
    dv = g[-1, :] - g[0, :]
    # Image axes (u right, v down) and board axes (x, y) have the same handedness
    # when the printed face is seen from the front.
    a, b = du.mean(0), dv.mean(0)
    if a[0] * b[1] - a[1] * b[0] < 0:
        g = g[:, ::-1]
    candidates = [g, g[::-1, ::-1]]
    # Centres of all squares, predicted through a homography from each candidate.
    s = spec.square_size
    obj = spec.P_board[:, :2] / s
    cx, cy = np.meshgrid(np.arange(spec.squares_x) + 0.5, np.arange(spec.squares_y) + 0.5)
    centres = np.stack([cx.ravel(), cy.ravel()], 1)
    black = ((np.floor(cx) + np.floor(cy)) % 2 == 0).ravel()
    h, w = grey.shape
    scores = []
    for c in candidates:
        H, _ = cv2.findHomography(obj, c.reshape(-1, 2), 0)
        p = cv2.perspectiveTransform(centres.reshape(-1, 1, 2), H).reshape(-1, 2)
        u = np.clip(np.round(p[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.round(p[:, 1]).astype(int), 0, h - 1)
        val = grey[v, u].astype(float)
        scores.append(val[~black].mean() - val[black].mean())
    return candidates[int(np.argmax(scores))].reshape(-1, 2)


def detect_board(image: np.ndarray, spec: BoardSpec, min_corners: int = 8) -> BoardDetection | None:
    """Find the board's inner corners in an image, refined to sub-pixel.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3), uint8
        Grey or BGR image.
    spec : BoardSpec
    min_corners : int
        ChArUco: fewer corners than this (or collinear ones) count as not found.

    Returns
    -------
    BoardDetection or None
        None when the board is not found.
    """
    grey = _grey(image)
    size = (grey.shape[1], grey.shape[0])
    if spec.kind == "chessboard":
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(grey, (spec.inner_x, spec.inner_y), flags=flags)
        if not found or corners is None or len(corners) != spec.n_corners:
            return None
        uv = _orient_chessboard(grey, spec, corners.reshape(-1, 2).astype(np.float64))
        ids = np.arange(spec.n_corners)
        # Half the search window below half the square side: no neighbour corner inside.
        hw = int(np.clip(0.4 * _min_neighbour_distance(spec, ids, uv), 2, 15))
        uv = _refine(grey, uv, hw)
        return BoardDetection(ids, uv, size)
    board = _charuco(spec)
    dparams = cv2.aruco.DetectorParameters()
    dparams.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(), dparams)
    corners, ids, _, _ = det.detectBoard(grey)
    if ids is None or len(ids) < min_corners:
        return None
    ids = ids.ravel().astype(int)
    order = np.argsort(ids)
    ids, uv = ids[order], corners.reshape(-1, 2)[order].astype(np.float64)
    if board.checkCharucoCornersCollinear(ids.reshape(-1, 1)):
        return None
    # The window must stay inside the white margin between a corner and the nearest
    # marker, (square - marker)/2: marker edges would pull the corner.
    margin_frac = 0.5 * (spec.square_size - spec.marker_size) / spec.square_size
    hw = int(np.floor(0.9 * margin_frac * _min_neighbour_distance(spec, ids, uv)))
    if hw >= 2:
        uv = _refine(grey, uv, min(hw, 15))
    return BoardDetection(ids, uv, size)


def require_unambiguous(spec: BoardSpec, what: str) -> None:
    """Raise when a board's pose cannot be told from its 180-deg turn."""
    if spec.symmetric:
        raise CalibrationError(
            f"{what} needs the board's pose, but a {spec.squares_x}x{spec.squares_y} chessboard looks the same "
            "turned by 180 deg: use a chessboard with one odd and one even square count, or a ChArUco board")
