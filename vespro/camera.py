"""Pinhole camera with OpenCV plumb_bob distortion.

The camera frame is OpenCV's optical frame: x right, y down, z forward along
the optical axis. Pixel coordinates have (0, 0) at the centre of the top-left
pixel, as in OpenCV.
"""

from __future__ import annotations

import functools

from dataclasses import dataclass, field

import numpy as np

from .jit import njit
from .numerics import transform_point

__all__ = ["CameraIntrinsics", "project_points", "distort_normalized", "undistort_pixels"]


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class CameraIntrinsics:
    """Intrinsics of one camera.

    Attributes
    ----------
    width, height : int
        Image size, pixels.
    K : ndarray, shape (3, 3)
        Camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, pixels (no skew,
        as in OpenCV).
    dist : ndarray, shape (5,)
        plumb_bob coefficients ``k1 k2 p1 p2 k3`` (OpenCV order).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"camera matrix must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera matrix must have finite, positive focal lengths: {K.tolist()}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise ValueError(f"camera matrix must be upper triangular with K[2] = [0, 0, 1]: {K.tolist()}")
        if abs(K[0, 1]) > 1e-9 * K[0, 0]:
            # OpenCV's projection, PnP and undistortion ignore skew: accepting it
            # would make our projections silently disagree with theirs.
            raise ValueError(f"camera matrix has skew K[0,1]={K[0, 1]}; OpenCV's model has none")
        dist = np.asarray(self.dist, dtype=float).ravel()
        if dist.shape != (5,) or not np.all(np.isfinite(dist)):
            raise ValueError(f"plumb_bob distortion needs 5 finite coefficients, got {dist.tolist()}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "K", _readonly(K))
        object.__setattr__(self, "dist", _readonly(dist))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @functools.cached_property
    def has_distortion(self) -> bool:
        # cached: dist is read-only, and this is asked several times per camera and frame
        return bool(np.any(self.dist != 0.0))

    @classmethod
    def from_fovy(cls, width: int, height: int, fovy_deg: float) -> "CameraIntrinsics":
        """Square-pixel pinhole with the principal point at the image centre.

        This is MuJoCo's camera model: ``fovy`` is the full vertical field of
        view; the image centre in OpenCV pixel convention is ``((w-1)/2, (h-1)/2)``.
        """
        fy = 0.5 * height / np.tan(0.5 * np.deg2rad(fovy_deg))
        K = np.array([[fy, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(width, height, K)

    def scaled(self, factor: float) -> "CameraIntrinsics":
        """Same camera at another resolution (``factor`` times the size)."""
        w, h = int(round(self.width * factor)), int(round(self.height * factor))
        K = self.K.copy()
        K[0, :] *= w / self.width
        K[1, :] *= h / self.height
        # Pixel centres: keep (w-1)/2 mapping consistent.
        K[0, 2] = (self.cx + 0.5) * w / self.width - 0.5
        K[1, 2] = (self.cy + 0.5) * h / self.height - 0.5
        return CameraIntrinsics(w, h, K, self.dist)


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply plumb_bob distortion to normalised image coordinates.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Ideal normalised coordinates ``(X/Z, Y/Z)``.
    dist : ndarray, shape (5,)
        ``k1 k2 p1 p2 k3``.

    Returns
    -------
    ndarray, shape (N, 2)
        Distorted normalised coordinates.
    """
    k1, k2, p1, p2, k3 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def project_points(intr: CameraIntrinsics, T_camera_object: np.ndarray, P_object: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project 3D points into the image.

    Parameters
    ----------
    intr : CameraIntrinsics
    T_camera_object : ndarray, shape (4, 4)
        Pose of the points' frame in the camera frame.
    P_object : ndarray, shape (N, 3)
        Points in the object frame, m.

    Returns
    -------
    uv : ndarray, shape (N, 2)
        Pixel coordinates (distortion applied). Points behind the camera get NaN.
    z : ndarray, shape (N,)
        Depth along the optical axis, m.

    Without distortion compiled (:func:`_project_pinhole`, the visibility query projects
    every frame), else as :func:`project_points_numpy`.
    """
    P_object = np.asarray(P_object, dtype=float).reshape(-1, 3)
    if not intr.has_distortion and len(P_object) != 1:  # (NumPy multiplies one point otherwise: gemv)
        K = intr.K
        return _project_pinhole(np.ascontiguousarray(T_camera_object, dtype=float), np.ascontiguousarray(P_object),
                                float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    return project_points_numpy(intr, T_camera_object, P_object)


@njit
def _project_pinhole(T, P, fx, fy, cx, cy):
    """:func:`project_points_numpy` without distortion, compiled: its operations in its order
    (the rotation as OpenBLAS's gemm, :func:`vespro.numerics.transform_point`), so the same bits."""
    N = P.shape[0]
    uv = np.empty((N, 2))
    z = np.empty(N)
    for i in range(N):
        X0, X1, zi = transform_point(T, P[i, 0], P[i, 1], P[i, 2])
        z[i] = zi
        x, y = X0 / zi, X1 / zi
        if zi <= 1e-9:
            x = y = np.nan
        uv[i, 0] = fx * x + cx
        uv[i, 1] = fy * y + cy
    return uv, z


def project_points_numpy(intr: CameraIntrinsics, T_camera_object: np.ndarray,
                         P_object: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project_points` in NumPy (distortion included)."""
    P_object = np.asarray(P_object, dtype=float).reshape(-1, 3)
    P_c = P_object @ T_camera_object[:3, :3].T + T_camera_object[:3, 3]
    z = P_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = P_c[:, :2] / z[:, None]
    xy[z <= 1e-9] = np.nan
    if intr.has_distortion:
        xy = distort_normalized(xy, intr.dist)
    K = intr.K
    uv = np.empty((len(xy), 2))
    uv[:, 0] = K[0, 0] * xy[:, 0] + K[0, 2]
    uv[:, 1] = K[1, 1] * xy[:, 1] + K[1, 2]
    return uv, z


def undistort_pixels(intr: CameraIntrinsics, uv: np.ndarray) -> np.ndarray:
    """Ideal (undistorted) pixel coordinates of distorted pixels, shape (N, 2).

    Uses OpenCV's iterative inverse; the result is in pixels of the same camera
    matrix (``P = K``).
    """
    import cv2

    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    if not intr.has_distortion:
        return uv.reshape(-1, 2).copy()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        out = cv2.undistortPointsIter(uv, intr.K, intr.dist, None, intr.K, crit)
    else:  # OpenCV 5 folded the criteria into undistortPoints
        out = cv2.undistortPoints(uv, intr.K, intr.dist, R=None, P=intr.K, criteria=crit)
    return out.reshape(-1, 2)
