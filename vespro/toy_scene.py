"""Tiny analytic scenes for testing and benchmarking the tracker core.

Not the simulator (that is ``vespro``'s MuJoCo cell): a convex polyhedron,
pinhole cameras on a ring, a constant-velocity trajectory drawn from the very
noise model the EKF assumes, exact projections plus Gaussian pixel noise,
visibility by back-face culling (exact for a convex body), silhouette distance
from the convex hull of the projection, and an anti-aliased rendering for the
corner extractor. All randomness comes from the caller's ``Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import ConvexHull

from . import ekf
from .camera import CameraIntrinsics
from .projection import project_with_jacobian
from .se3 import invert_transform, transform_from_rt

__all__ = [
    "Polyhedron",
    "convex_polyhedron",
    "cube",
    "chamfered_box",
    "look_at",
    "ring_cameras",
    "cv_trajectory",
    "visible_features",
    "render_polyhedron",
    "run_ekf",
]


@dataclass(frozen=True)
class Polyhedron:
    """Convex polyhedron in the object frame (m).

    Attributes
    ----------
    V : ndarray, shape (N, 3)
        Vertices (the model corners).
    faces : tuple of ndarray
        Vertex indices per face, counter-clockwise seen from outside.
    normals : ndarray, shape (F, 3)
        Outward unit face normals.
    vertex_faces : tuple of ndarray
        Face indices incident to each vertex.
    """

    V: np.ndarray
    faces: tuple
    normals: np.ndarray
    vertex_faces: tuple


def convex_polyhedron(V: np.ndarray) -> Polyhedron:
    """Faces of the convex hull of ``V`` (coplanar hull triangles merged)."""
    V = np.asarray(V, dtype=float)
    hull = ConvexHull(V)
    groups: dict = {}
    for simplex, eq in zip(hull.simplices, hull.equations):
        key = tuple(np.round(eq, 6))
        groups.setdefault(key, set()).update(simplex.tolist())
    faces, normals = [], []
    for key, idx in groups.items():
        n = np.array(key[:3])
        n /= np.linalg.norm(n)
        idx = np.array(sorted(idx))
        c = V[idx].mean(axis=0)
        a = V[idx[0]] - c
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        ang = np.arctan2((V[idx] - c) @ b, (V[idx] - c) @ a)
        faces.append(idx[np.argsort(ang)])
        normals.append(n)
    vf = tuple(np.array([f for f, face in enumerate(faces) if i in face]) for i in range(len(V)))
    return Polyhedron(V, tuple(faces), np.array(normals), vf)


def cube(half: float = 0.05) -> Polyhedron:
    """Cube of edge ``2 * half`` m centred on the object origin (8 corners)."""
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return convex_polyhedron(half * s)


def chamfered_box(half_extents=(0.08, 0.05, 0.035), chamfer: float = 0.012) -> Polyhedron:
    """Box with every corner cut off (24 corners, 6 octagons + 8 triangles)."""
    a = np.asarray(half_extents, dtype=float)
    V = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                s = np.array([sx, sy, sz], dtype=float)
                for k in range(3):
                    v = s * a
                    v[k] -= s[k] * chamfer
                    V.append(v)
    return convex_polyhedron(np.array(V))


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_camera`` (4, 4) of an OpenCV optical camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return transform_from_rt(np.stack([x, y, z], axis=1), eye)


def ring_cameras(n: int, radius: float = 0.8, height: float = 0.4, target=(0.0, 0.0, 0.0), start_deg: float = -30.0, step_deg: float = 75.0):
    """``n`` poses ``T_world_camera`` on a horizontal ring, looking at ``target``."""
    out = []
    for i in range(n):
        a = np.deg2rad(start_deg + i * step_deg)
        out.append(look_at([radius * np.cos(a), radius * np.sin(a), height], target))
    return out


def cv_trajectory(rng, n: int, dt: float, T0: np.ndarray, v0, w0, q_acc: float, q_alpha: float) -> np.ndarray:
    """True states (n, 13) of the EKF's own motion model with sampled process noise."""
    x = ekf.state_from_pose(T0, v0, w0)
    Q = ekf.process_noise(dt, q_acc, q_alpha)
    L = np.linalg.cholesky(Q + 1e-30 * np.eye(12))
    out = np.empty((n, 13))
    for k in range(n):
        out[k] = x
        x = ekf.inject(ekf.motion_model(x, dt), L @ rng.standard_normal(12))
    return out


def visible_features(poly: Polyhedron, intr: CameraIntrinsics, T_world_camera, T_world_object):
    """Visible corners in one camera, what the BSP module will provide.

    Returns
    -------
    idx : ndarray (K,) int
        Visible vertex indices (some front face contains them, projection in the image).
    uv : ndarray (K, 2)
        Predicted pixels.
    view_angle : ndarray (K,)
        Smallest angle (rad) between the line of sight and an incident front-face normal.
    silhouette_px : ndarray (K,)
        Pixel distance to the silhouette (0 for silhouette corners).
    """
    c_obj = invert_transform(T_world_object) @ np.append(T_world_camera[:3, 3], 1.0)
    to_cam = c_obj[:3] - poly.V                                   # object frame
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    uv, depth, _ = project_with_jacobian(intr, T_world_camera, T_world_object, poly.V)
    vis = np.zeros(len(poly.V), bool)
    ang = np.full(len(poly.V), np.pi)
    for i, fs in enumerate(poly.vertex_faces):
        cosang = poly.normals[fs] @ to_cam[i]
        if np.any(cosang > 1e-9):
            vis[i] = True
            ang[i] = np.arccos(np.clip(cosang.max(), -1, 1))
    inside = (depth > 0) & np.all(np.isfinite(uv), axis=1)
    inside &= (uv[:, 0] >= 0) & (uv[:, 0] <= intr.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= intr.height - 1)
    vis &= inside
    # silhouette of a convex body = hull of all its projected vertices
    hull = cv2.convexHull(uv[depth > 0].astype(np.float32))
    sil = np.array([abs(cv2.pointPolygonTest(hull, (float(u), float(v)), True)) for u, v in uv[vis]])
    return np.flatnonzero(vis), uv[vis], ang[vis], sil


def render_polyhedron(
    poly: Polyhedron,
    intr: CameraIntrinsics,
    T_world_camera,
    T_world_object,
    rng=None,
    background: int = 20,
    noise_sigma: float = 2.0,
    blur_sigma: float = 0.6,
    supersample: int = 8,
    light=(-0.3, -0.5, -0.8),
) -> np.ndarray:
    """Grey image (H, W) uint8 of the polyhedron: flat-shaded faces, anti-aliased.

    Lambertian grey ``50 + 180 max(0, n . light)`` per face (``light``: unit
    direction towards the light, camera frame) on a dark background.
    Supersampled ``supersample`` x with 1/16 sub-pixel vertex positions
    (``fillPoly`` ``shift=4``), box-averaged back (``INTER_AREA``), then a small
    Gaussian blur (optics) and Gaussian noise. Front faces of a convex body do
    not overlap, so no depth sorting is needed. Distortion is applied to the
    vertices only (edges drawn straight), which is exact for ``dist == 0``.
    """
    s = supersample
    T_co = invert_transform(T_world_camera) @ T_world_object
    uv, depth, _ = project_with_jacobian(intr, T_world_camera, T_world_object, poly.V)
    cam_obj = invert_transform(T_co)[:3, 3]
    light_c = np.asarray(light, float) / np.linalg.norm(light)
    img = np.full((intr.height * s, intr.width * s), background, np.uint8)
    for f, n in zip(poly.faces, poly.normals):
        if (cam_obj - poly.V[f[0]]) @ n <= 0 or np.any(depth[f] <= 0):
            continue
        n_c = T_co[:3, :3] @ n
        grey = int(np.clip(50 + 180 * max(0.0, n_c @ light_c), 0, 255))
        hi = (uv[f] + 0.5) * s - 0.5                    # pixel-centre convention
        pts = np.round(hi * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(img, [pts], grey, lineType=cv2.LINE_8, shift=4)
    img = cv2.resize(img.astype(np.float32), (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if rng is not None and noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def run_ekf(
    poly: Polyhedron,
    cameras,
    truth: np.ndarray,
    dt: float,
    rng,
    select=None,
    sigma_px: float = 0.5,
    q_acc: float = 0.01,
    q_alpha: float = 0.1,
    init_error=(0.02, np.deg2rad(5.0)),
    outliers=None,
    select_joint=None,
    robust_nis: float = 0.0,
):
    """Track ``truth`` (n, 13) with :class:`vespro.ekf.PoseEKF` from synthetic pixels.

    Parameters
    ----------
    poly : Polyhedron
    cameras : list of (CameraIntrinsics, T_world_camera)
    truth : ndarray (n, 13)
    dt : float
    rng : numpy Generator
    select : callable or None
        ``select(cam_index, idx, uv, J, view_angle, silhouette_px, intr, P6) -> positions``
        into the visible list; None uses all visible corners.
    init_error : (m, rad)
        Magnitudes of the start error (random directions).
    outliers : callable or None
        ``outliers(k, z) -> z`` may corrupt the stacked measurements of frame k.
    select_joint : callable or None
        ``select_joint(cands, P6) -> list of positions`` with ``cands`` a list of
        per-camera ``(idx, uv, J, view_angle, silhouette_px, intr)``; used
        instead of ``select`` when given (selection across cameras).
    robust_nis : float
        The filter's residual-consistent covariance threshold (0: off).

    Returns
    -------
    dict with ``T_est`` (n,4,4), ``T_true`` (n,4,4), ``P6`` (n,6,6), ``results``
    (list of UpdateResult), ``n_meas`` (n,), ``meas`` (per frame, per camera
    ``(vertex indices, noisy pixels)`` before ``outliers``), ``z``/``h`` of the last frame.
    """
    n = len(truth)
    d = rng.standard_normal(3)
    dp = init_error[0] * d / np.linalg.norm(d)
    d = rng.standard_normal(3)
    dth = init_error[1] * d / np.linalg.norm(d)
    T0 = ekf.pose_from_state(ekf.inject(truth[0], np.r_[dp, dth, np.zeros(6)]))
    P0 = np.diag(np.r_[np.full(3, init_error[0] ** 2), np.full(3, init_error[1] ** 2), np.full(3, 0.1**2), np.full(3, 0.5**2)])
    f = ekf.PoseEKF(T0, P0, q_acc=q_acc, q_alpha=q_alpha, sigma_px=sigma_px, robust_nis=robust_nis)
    out = {"T_est": np.empty((n, 4, 4)), "T_true": np.empty((n, 4, 4)), "P6": np.empty((n, 6, 6)), "results": [], "n_meas": np.zeros(n, int), "meas": []}
    for k in range(n):
        if k > 0:
            f.predict(dt)
        T_true = ekf.pose_from_state(truth[k])
        T_pred = f.pose
        zs, hs, Js = [], [], []
        frame_meas = []
        out["meas"].append(frame_meas)
        cands = []
        for c, (intr, T_wc) in enumerate(cameras):
            idx, uv_pred, ang, sil = visible_features(poly, intr, T_wc, T_pred)
            h, _, J = project_with_jacobian(intr, T_wc, T_pred, poly.V[idx])
            cands.append((idx, h, J, ang, sil, intr))
        if select_joint is not None:
            picks = select_joint(cands, f.pose_covariance)
        elif select is not None:
            picks = [select(c, *cands[c][:5], cands[c][5], f.pose_covariance) for c in range(len(cameras))]
        else:
            picks = [np.arange(len(cd[0])) for cd in cands]
        for c, (intr, T_wc) in enumerate(cameras):
            pos = np.asarray(picks[c], dtype=int)
            idx, h, J = cands[c][0][pos], cands[c][1][pos], cands[c][2][pos]
            z_true, _, _ = project_with_jacobian(intr, T_wc, T_true, poly.V[idx])
            zs.append(z_true + rng.normal(0.0, sigma_px, z_true.shape))
            frame_meas.append((idx, zs[-1]))
            hs.append(h)
            Js.append(J)
        z, h, J = np.concatenate(zs), np.concatenate(hs), np.concatenate(Js)
        if outliers is not None:
            z = outliers(k, z)
        out["results"].append(f.update(z, h, J))
        out["n_meas"][k] = len(z)
        out["T_est"][k] = f.pose
        out["T_true"][k] = T_true
        out["P6"][k] = f.pose_covariance
    out["z"], out["h"] = z, h
    return out
