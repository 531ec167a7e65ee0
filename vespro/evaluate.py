"""Score tracker output against ground truth (an evaluator: reads groundtruth.csv).

:func:`score` turns per-frame poses into the figures users judge a tracker by;
:func:`pnp_baseline` re-estimates every frame from the tracker's own detections
with OpenCV's solvePnP per camera and no filter, so the filter's gain is shown
on the same measurements; :func:`plot_errors` and :func:`overlay_video` write
the pictures.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .camera import project_points
from .metrics import add, add_s, nees, nees_band, pose_error_vector, rmse
from .model import Model
from .recording import Recording
from .se3 import invert_transform, matrix_from_quat, quat_canonical, quat_from_matrix, transform_from_rt
from .tracker import TrackerOutput

__all__ = ["score", "pnp_baseline", "plot_errors", "overlay_video"]


def score(T_est: list, status: list[str], T_true: np.ndarray, t: np.ndarray, model: Model,
          time_ms: list | None = None, cov: list | None = None, symmetric: bool = False) -> dict:
    """Accuracy figures of one run.

    Parameters
    ----------
    T_est : list of (4, 4) or None
        Estimated poses per frame (None where not tracking).
    status : list of str
    T_true : ndarray (N, 4, 4)
        True poses; a frame whose true pose is not finite (a gap in the ground
        truth) is left out of every figure.
    t : ndarray (N,)
        Capture times, s.
    model : Model
        For ADD (its vertices) and the diameter.
    time_ms : list of float, optional
    cov : list of (6, 6) or None, optional
        For NEES.

    Returns
    -------
    dict
        ``position_rmse_mm``, ``position_max_mm``, ``orientation_rmse_deg``,
        ``orientation_max_deg``, ``add_mm`` (mean over tracked frames),
        ``adds_mm``, ``tracked_fraction`` (of the frames with ground truth),
        ``frames_without_truth``, ``time_to_first_track_s``,
        ``wrong_lock_frames`` (tracking with ADD > 10% of the diameter),
        ``time_ms_median``, ``time_ms_p99``, ``nees_mean``, ``nees_in_band``
        (fraction of frames in the two-sided 95% chi-square band, 6 dof).
    """
    n = len(T_true)
    P = model.vertices
    known = np.all(np.isfinite(np.asarray(T_true).reshape(n, -1)), axis=1)
    tracked = [i for i in range(n) if status[i] == "tracking" and T_est[i] is not None]
    idx = [i for i in tracked if known[i]]
    pos = np.array([np.linalg.norm(T_est[i][:3, 3] - T_true[i][:3, 3]) for i in idx])
    rot = np.array([np.linalg.norm(pose_error_vector(T_est[i], T_true[i])[3:]) for i in idx])
    adds = np.array([add(T_est[i], T_true[i], P) for i in idx])
    out = {
        "frames": n,
        "frames_without_truth": int(n - known.sum()),
        "tracked_fraction": float(len(idx) / known.sum()) if known.any() else 0.0,
        "time_to_first_track_s": float(t[tracked[0]] - t[0]) if tracked else None,
        "position_rmse_mm": rmse(pos) * 1e3 if idx else None,
        "position_max_mm": float(pos.max() * 1e3) if idx else None,
        "orientation_rmse_deg": float(np.rad2deg(rmse(rot))) if idx else None,
        "orientation_max_deg": float(np.rad2deg(rot.max())) if idx else None,
        "add_mm": float(adds.mean() * 1e3) if idx else None,
        "wrong_lock_frames": int(np.sum(adds > 0.1 * model.diameter)) if idx else 0,
    }
    if symmetric and idx:
        out["adds_mm"] = float(np.mean([add_s(T_est[i], T_true[i], P) for i in idx]) * 1e3)
    if time_ms is not None:
        tm = np.array([x for x in time_ms if x is not None], dtype=float)
        out["time_ms_median"] = float(np.median(tm)) if tm.size else None
        out["time_ms_p99"] = float(np.percentile(tm, 99)) if tm.size else None
    if cov is not None and idx:
        ne = np.array([nees(T_est[i], T_true[i], cov[i]) for i in idx if cov[i] is not None])
        lo, hi = nees_band(6, 0.95)
        out["nees_mean"] = float(np.mean(ne)) if ne.size else None
        out["nees_in_band"] = float(np.mean((ne >= lo) & (ne <= hi))) if ne.size else None
        out["nees_below_upper"] = float(np.mean(ne <= hi)) if ne.size else None
    return out


def _mean_pose(Ts: list[np.ndarray]) -> np.ndarray:
    """Average of poses: mean position, chordal (quaternion) mean rotation."""
    p = np.mean([T[:3, 3] for T in Ts], axis=0)
    qs = np.array([quat_canonical(quat_from_matrix(T[:3, :3])) for T in Ts])
    q0 = qs[0]
    qs = np.array([q if q @ q0 >= 0 else -q for q in qs])
    q = qs.mean(axis=0)
    return transform_from_rt(matrix_from_quat(q / np.linalg.norm(q)), p)


def pnp_baseline(rec: Recording, outs: list[TrackerOutput], model: Model, min_points: int = 5) -> list:
    """Per-frame pose from the tracker's detections with solvePnP per camera, no filter.

    Each camera with at least ``min_points`` measured corners gives a pose
    (iterative PnP started from the previous baseline pose when there is one,
    else SQPnP); the frame's pose is the average over cameras. Returns a list
    of ``T_world_object`` or None per frame.
    """
    res = []
    prev = None
    for o in outs:
        Ts = []
        for ob in o.observations:
            if ob.feature_ids.size == 0:
                continue
            ok = np.all(np.isfinite(ob.uv_meas), axis=1)
            if ok.sum() < min_points:
                continue
            cam = rec.rig[ob.name]
            T_wc = cam.T_world_camera if cam.is_fixed else rec.T_world_camera(ob.name, o.index)
            obj = model.corners[ob.feature_ids[ok]].astype(np.float64)
            img = ob.uv_meas[ok].astype(np.float64)
            K, d = cam.intrinsics.K, cam.intrinsics.dist
            if prev is not None:
                T_co = invert_transform(T_wc) @ prev
                rvec, _ = cv2.Rodrigues(T_co[:3, :3])
                success, rvec, tvec = cv2.solvePnP(obj, img, K, d, rvec.copy(), T_co[:3, 3].copy(),
                                                   useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
            else:
                success, rvec, tvec = cv2.solvePnP(obj, img, K, d, flags=cv2.SOLVEPNP_SQPNP)
            if not success:
                continue
            R, _ = cv2.Rodrigues(rvec)
            Ts.append(T_wc @ transform_from_rt(R, tvec.ravel()))
        T = _mean_pose(Ts) if Ts else None
        res.append(T)
        if T is not None:
            prev = T
    return res


def plot_errors(path: str | Path, t: np.ndarray, runs: dict, T_true: np.ndarray, cov: list | None = None) -> None:
    """PNG of position and orientation errors over time for several runs.

    ``runs``: label -> list of T_world_object or None per frame.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = 3 if cov is not None else 2
    fig, ax = plt.subplots(rows, 1, figsize=(9, 2.6 * rows), sharex=True)
    for label, Ts in runs.items():
        pe = np.array([np.nan if T is None else np.linalg.norm(T[:3, 3] - T_true[i][:3, 3]) * 1e3
                       for i, T in enumerate(Ts)])
        re = np.array([np.nan if T is None else np.rad2deg(np.linalg.norm(pose_error_vector(T, T_true[i])[3:]))
                       for i, T in enumerate(Ts)])
        ax[0].plot(t, pe, label=label, lw=1)
        ax[1].plot(t, re, label=label, lw=1)
    ax[0].set_ylabel("position error (mm)")
    ax[1].set_ylabel("orientation error (deg)")
    ax[0].legend(loc="upper right")
    for a in ax:
        a.grid(alpha=0.3)
    if cov is not None:
        first = next(iter(runs.values()))
        ne = np.array([np.nan if (T is None or C is None) else nees(T, T_true[i], C)
                       for i, (T, C) in enumerate(zip(first, cov))])
        lo, hi = nees_band(6)
        ax[2].semilogy(t, ne, lw=1, label="NEES (filter)")
        ax[2].axhspan(lo, hi, color="g", alpha=0.15, label="95% band")
        ax[2].set_ylabel("NEES (6 dof)")
        ax[2].legend(loc="upper right")
    ax[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw_overlay(img: np.ndarray, model: Model, intr, T_camera_object: np.ndarray | None, ob=None) -> np.ndarray:
    """One camera image with the model's edges at a pose and the selected features."""
    out = img.copy() if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if T_camera_object is not None:
        uv, z = project_points(intr, T_camera_object, model.vertices)
        for a, b in model.edge_vertices:
            if z[a] > 0 and z[b] > 0:
                pa, pb = uv[a], uv[b]
                if np.all(np.isfinite(pa)) and np.all(np.isfinite(pb)):
                    cv2.line(out, (int(round(pa[0] * 4)), int(round(pa[1] * 4))),
                             (int(round(pb[0] * 4)), int(round(pb[1] * 4))), (0, 220, 0), 1, cv2.LINE_AA, shift=2)
    if ob is not None and ob.feature_ids.size:
        for q, r, m, acc in zip(ob.uv_pred, ob.half_size, ob.uv_meas, ob.accepted):
            if not np.all(np.isfinite(q)):
                continue
            c = (int(round(q[0])), int(round(q[1])))
            r = int(r)
            cv2.rectangle(out, (c[0] - r, c[1] - r), (c[0] + r, c[1] + r), (255, 160, 0), 1)
            if np.all(np.isfinite(m)):
                cv2.circle(out, (int(round(m[0])), int(round(m[1]))), 2, (0, 255, 255) if acc else (0, 0, 255), -1)
    return out


def overlay_video(path: str | Path, rec: Recording, outs: list[TrackerOutput], model: Model, fps: float | None = None,
                  max_width: int = 1280, inset=None) -> None:
    """MP4 of every camera with the projected model (green), search windows
    (blue), accepted measurements (yellow) and rejected ones (red).

    ``inset(index) -> BGR image`` adds a tile per frame (e.g. a view of the arm).
    """
    import imageio.v2 as imageio

    writer = None
    try:
        for o in outs:
            tiles = []
            obs = {ob.name: ob for ob in o.observations}
            for cam in rec.rig:
                img = rec.image(cam.name, o.index)
                if img is None:
                    img = np.zeros((cam.intrinsics.height, cam.intrinsics.width, 3), np.uint8)
                    cv2.putText(img, "no image", (20, 40), cv2.FONT_HERSHEY_SIMPLEX, 1, (0, 0, 255), 2)
                T_wc = rec.T_world_camera(cam.name, o.index)
                T_co = None if o.T_world_object is None else invert_transform(T_wc) @ o.T_world_object
                tile = draw_overlay(img, model, cam.intrinsics, T_co, obs.get(cam.name))
                cv2.putText(tile, f"{cam.name}  #{o.index}  {o.status}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                            (255, 255, 255), 1, cv2.LINE_AA)
                tiles.append(tile)
            if inset is not None:
                extra = inset(o.index)
                s = tiles[0].shape[0] / extra.shape[0]
                tiles.append(cv2.resize(extra, (int(extra.shape[1] * s), tiles[0].shape[0])))
            h = max(t.shape[0] for t in tiles)
            tiles = [cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles]
            frame = np.hstack(tiles)
            if frame.shape[1] > max_width:
                s = max_width / frame.shape[1]
                frame = cv2.resize(frame, (max_width, int(frame.shape[0] * s) // 2 * 2), interpolation=cv2.INTER_AREA)
            frame = frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2]
            if writer is None:
                writer = imageio.get_writer(str(path), fps=fps or rec.rate_hz, codec="libx264", quality=7,
                                            macro_block_size=2)
            writer.append_data(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    finally:
        if writer is not None:
            writer.close()
