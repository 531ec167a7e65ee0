"""Per-call timings of the tracker's building blocks, and a selection comparison.

Run from the repository root::

    python3 bench/tracker_core.py            # full (~1 min CPU, ~4 min wall on a busy 2-core box)
    python3 bench/tracker_core.py --quick    # fewer repetitions / seeds, no rendered loop

Three parts: per-call timings; the selection methods' pose RMSE with synthetic
pixels (exact projection + white 0.5 px noise: pure geometry); and the same
methods in a closed loop on rendered images through the corner extractor
(extraction errors are neither white nor equal across corners).

Every timing is the median and 99th percentile of single calls
(``time.perf_counter_ns``), beside an OpenCV / filterpy baseline run in the same
process on the same data with interleaved calls (so both see the same machine
load); "ratio" is ours / baseline (median).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from filterpy.kalman import predict as kf_predict  # noqa: E402

from vespro import ekf, se3  # noqa: E402
from vespro import selection as sel  # noqa: E402
from vespro import toy_scene as ts  # noqa: E402
from vespro.camera import CameraIntrinsics  # noqa: E402
from vespro.extraction import extract_corners  # noqa: E402
from vespro.projection import project_with_jacobian  # noqa: E402


def _stats(t):
    return np.median(t) / 1e3, np.quantile(t, 0.99) / 1e3


def timeit(fn, reps):
    for _ in range(min(20, reps)):
        fn()
    t = np.empty(reps)
    for i in range(reps):
        t0 = time.perf_counter_ns()
        fn()
        t[i] = time.perf_counter_ns() - t0
    return _stats(t)


def timepair(fa, fb, reps):
    """Time two functions with interleaved calls, so both see the same machine load."""
    for _ in range(min(20, reps)):
        fa()
        fb()
    ta, tb = np.empty(reps), np.empty(reps)
    for i in range(reps):
        t0 = time.perf_counter_ns()
        fa()
        t1 = time.perf_counter_ns()
        fb()
        t2 = time.perf_counter_ns()
        ta[i], tb[i] = t1 - t0, t2 - t1
    return _stats(ta), _stats(tb)


ROWS = []


def row(name, ours, base_name, base):
    ROWS.append((name, ours, base_name, base))


def print_table():
    print(f"| {'operation':<38} | {'median us':>9} | {'p99 us':>8} | {'baseline':<40} | {'median us':>9} | {'p99 us':>8} | {'ratio':>6} |")
    print(f"|{'-' * 40}|{'-' * 11}:|{'-' * 9}:|{'-' * 42}|{'-' * 10}:|{'-' * 9}:|{'-' * 7}:|")
    for name, (m, p), bname, (bm, bp) in ROWS:
        print(f"| {name:<38} | {m:9.1f} | {p:8.1f} | {bname:<40} | {bm:9.1f} | {bp:8.1f} | {m / bm:6.2f} |")


def bench_timings(reps):
    rng = np.random.default_rng(0)
    K = np.array([[600.0, 0, 321], [0, 590, 238], [0, 0, 1]])
    dist = np.array([-0.21, 0.09, 0.001, -0.0015, -0.02])
    intr = CameraIntrinsics(640, 480, K, dist)
    T_wc = ts.look_at([0.6, -0.5, 0.4], [0, 0, 0])
    T_wo = se3.transform_from_rt(se3.exp_so3([0.1, 0.2, 0.3]), [0.01, 0.0, 0.02])
    T_co = se3.invert_transform(T_wc) @ T_wo
    rvec, _ = cv2.Rodrigues(T_co[:3, :3])
    tvec = T_co[:3, 3].copy()

    # 1. projection + Jacobian
    for n in (8, 30, 100):
        P = rng.uniform(-0.08, 0.08, (n, 3))
        ours, base = timepair(lambda: project_with_jacobian(intr, T_wc, T_wo, P), lambda: cv2.projectPoints(P, rvec, tvec, K, dist), reps)
        row(f"project_with_jacobian N={n}", ours, f"cv2.projectPoints (+jacobian) N={n}", base)

    # 2. EKF predict
    x = ekf.state_from_pose(T_wo, [0.02, 0.0, 0.01], [0.0, 0.0, 0.2])
    P12 = np.diag(np.full(12, 1e-4))
    F = ekf.transition_jacobian(x, 1 / 26)
    Q = ekf.process_noise(1 / 26, 1e-4, 1e-3)
    ours, base = timepair(lambda: ekf.predict(x, P12, 1 / 26, 1e-4, 1e-3), lambda: kf_predict(np.zeros(12), P12, F, Q), reps)
    row("ekf.predict (12-D error state)", ours, "filterpy predict (F, Q given)", base)

    # 3. EKF update, 16 and 24 points from 2 cameras
    poly = ts.chamfered_box()
    cams = [(CameraIntrinsics.from_fovy(640, 480, 45.0), T) for T in ts.ring_cameras(2)]
    T_true = se3.transform_from_rt(se3.exp_so3([0.2, -0.1, 0.3]), [0.0, 0.0, 0.0])
    T_est = se3.transform_from_rt(se3.exp_so3([0.0, 0.005, 0.0]) @ T_true[:3, :3], [0.001, -0.001, 0.0])
    for m in (16, 24):
        zs, hs, Js, objs, imgs = [], [], [], [], []
        for ci, T in cams:
            idx, *_ = ts.visible_features(poly, ci, T, T_est)
            idx = idx[: m // 2]
            z, _, _ = project_with_jacobian(ci, T, T_true, poly.V[idx])
            z = z + rng.normal(0, 0.5, z.shape)
            h, _, J = project_with_jacobian(ci, T, T_est, poly.V[idx])
            zs.append(z)
            hs.append(h)
            Js.append(J)
            objs.append(poly.V[idx])
            imgs.append(z)
        z, h, J = np.concatenate(zs), np.concatenate(hs), np.concatenate(Js)
        xe = ekf.state_from_pose(T_est)
        Pe = np.diag(np.r_[np.full(3, 0.003**2), np.full(3, 0.01**2), np.full(6, 0.01)])
        # baseline: one solvePnP per camera on the same points (what a per-frame
        # least-squares tracker would run); extrinsic guess from the prediction
        ci = cams[0][0]
        T_ce = [se3.invert_transform(T) @ T_est for _, T in cams]
        guesses = [(cv2.Rodrigues(Tc[:3, :3])[0], Tc[:3, 3].reshape(3, 1).copy()) for Tc in T_ce]

        def pnp():
            for (o, im), (rv, tv) in zip(zip(objs, imgs), guesses):
                cv2.solvePnP(o, im, ci.K, ci.dist, rv.copy(), tv.copy(), True, cv2.SOLVEPNP_ITERATIVE)

        ours, base = timepair(lambda: ekf.update(xe, Pe, z, h, J), pnp, reps)
        row(f"ekf.update M={m} (2 cams, gated)", ours, f"cv2.solvePnP x2 cams ({m // 2} pts each)", base)

    # 4. selection N=30, k=8
    T_c = np.eye(4)
    T_o = se3.transform_from_rt(se3.exp_so3([0.4, -0.3, 0.8]), [0.02, -0.01, 0.8])
    P30 = rng.uniform(-0.1, 0.1, (30, 3))
    uv, _, J30 = project_with_jacobian(intr, T_c, T_o, P30)
    va = rng.uniform(0, np.deg2rad(70), 30)
    sil = rng.uniform(0, 30, 30)
    P6 = np.diag(np.r_[np.full(3, 0.003**2), np.full(3, 0.01**2)])
    proj30 = lambda: project_with_jacobian(intr, T_c, T_o, P30)  # noqa: E731
    ours, base = timepair(lambda: sel.select_quality(uv, va, sil, (640, 480), k=8), proj30, max(reps // 4, 50))
    row("select_quality N=30 k=8", ours, "project_with_jacobian N=30", base)
    ours, base = timepair(lambda: sel.select_information(uv, J30, va, sil, (640, 480), P6=P6, k=8), proj30, reps)
    row("select_information N=30 k=8", ours, "project_with_jacobian N=30", base)

    # 5. extraction of 8 windows in a 640x480 image
    intr0 = CameraIntrinsics.from_fovy(640, 480, 45.0)
    T_wc0 = ts.look_at([0.45, -0.45, 0.45], [0, 0, 0])
    # 8 windows: the 7 visible cube corners + 1 on a plain edge (a miss costs too)
    cube = ts.cube(0.05)
    img = ts.render_polyhedron(cube, intr0, T_wc0, T_true, np.random.default_rng(1))
    idx, uvv, *_ = ts.visible_features(cube, intr0, T_wc0, T_true)
    pred = np.vstack([uvv[:7], 0.5 * (uvv[0] + uvv[1])[None]])[:8] + rng.normal(0, 1.0, (8, 2))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.001)

    def gftt():
        c = cv2.goodFeaturesToTrack(img, 100, 0.05, 5)
        cv2.cornerSubPix(img, c[:8].copy(), (4, 4), (-1, -1), crit)

    ours, base = timepair(lambda: extract_corners(img, pred, 10), gftt, max(reps // 4, 50))
    row("extract_corners 8 windows r=10", ours, "cv2.goodFeaturesToTrack full + subpix x8", base)
    ours, base = timepair(lambda: extract_corners(img, pred, 10, refine_lines=False), gftt, max(reps // 4, 50))
    row("  (same, refine_lines=False)", ours, "cv2.goodFeaturesToTrack full + subpix x8", base)


def selection_comparison(seeds, n_frames=200):
    """EKF pose RMSE on the chamfered box (24 corners), 2 cameras, k per camera."""
    dt = 1 / 26
    intr = CameraIntrinsics.from_fovy(640, 480, 45.0)
    cams = [(intr, T) for T in ts.ring_cameras(2)]
    poly = ts.chamfered_box()
    size = (intr.width, intr.height)
    k = 8

    def quality(c, idx, uv, J, va, sil, intr_, P6):
        return sel.select_quality(uv, va, sil, size, k=k)

    def info(c, idx, uv, J, va, sil, intr_, P6):
        return sel.select_information(uv, J, va, sil, size, P6=P6, k=k)

    def info_w(c, idx, uv, J, va, sil, intr_, P6):
        return sel.select_information(uv, J, va, sil, size, P6=P6, k=k, weight_by_quality=True)

    def joint(cands, P6):
        return sel.select_information_joint([(uv, J, va, size) for (_, uv, J, va, _, _) in cands], P6=P6, k_per_camera=k)

    rsel = np.random.default_rng(12345)

    def rand(c, idx, uv, J, va, sil, intr_, P6):
        el = np.flatnonzero(sel.eligible_mask(uv, size, view_angle=va))
        return rsel.choice(el, min(k, len(el)), replace=False)

    methods = {"quality index": dict(select=quality), "information (per camera)": dict(select=info),
               "information (joint)": dict(select_joint=joint),
               "information, quality-weighted": dict(select=info_w), "random": dict(select=rand), "all visible": {}}
    res = {m: [] for m in methods}
    for seed in seeds:
        for name, kw in methods.items():
            rng = np.random.default_rng(seed)
            truth = ts.cv_trajectory(rng, n_frames, dt, np.eye(4), [0.02, 0.01, 0.0], [0.0, 0.0, 0.2], 1e-6, 1e-5)
            run = ts.run_ekf(poly, cams, truth, dt, rng, q_acc=1e-6, q_alpha=1e-5, **kw)
            pe = np.array([se3.pose_error(a, b) for a, b in zip(run["T_est"], run["T_true"])])[26:]
            ne = np.array([ekf.nees(a, b, P) for a, b, P in zip(run["T_est"], run["T_true"], run["P6"])])[26:]
            res[name].append((np.sqrt(np.mean(pe[:, 0] ** 2)), np.sqrt(np.mean(pe[:, 1] ** 2)), ne.mean(), run["n_meas"].mean()))
    print(f"\nSelection comparison: chamfered box (24 corners), 2 cameras, k={k} per camera, "
          f"{n_frames} frames at 26 Hz, 0.5 px noise, seeds {list(seeds)} (after 1 s convergence)\n")
    print(f"| {'method':<30} | {'pos RMSE mm':>11} | {'rot RMSE deg':>12} | {'mean NEES':>9} | {'points/frame':>12} |")
    print(f"|{'-' * 32}|{'-' * 12}:|{'-' * 13}:|{'-' * 10}:|{'-' * 13}:|")
    for name, v in res.items():
        v = np.array(v)
        print(f"| {name:<30} | {1e3 * np.sqrt(np.mean(v[:, 0] ** 2)):11.3f} | {np.rad2deg(np.sqrt(np.mean(v[:, 1] ** 2))):12.4f} | {v[:, 2].mean():9.2f} | {v[:, 3].mean():12.1f} |")
    return res


def rendered_comparison(seeds, n_frames=60, chamfer=0.02):
    """Closed loop on rendered images: selection -> windows -> extraction -> EKF.

    Unlike :func:`selection_comparison`, corners are measured by
    :func:`extract_corners` in flat-shaded renderings, so a selector that picks
    corners the extractor handles badly (obtuse chamfer corners, silhouette
    corners, grazing faces) pays for it.
    """
    from vespro.extraction import window_half_sizes

    dt = 1 / 26
    intr = CameraIntrinsics.from_fovy(640, 480, 45.0)
    cams = [(intr, T) for T in ts.ring_cameras(2, radius=0.6)]
    poly = ts.chamfered_box(chamfer=chamfer)
    size = (640, 480)
    sep = 12.0
    methods = ["quality index", "information", "information, quality-weighted", "random"]
    out = {m: [] for m in methods}
    for seed in seeds:
        for m in methods:
            rng = np.random.default_rng(seed)
            rsel = np.random.default_rng(1000 + seed)
            truth = ts.cv_trajectory(rng, n_frames, dt, se3.transform_from_rt(se3.exp_so3([0.1, 0.2, 0.3]), np.zeros(3)),
                                     [0.02, 0, 0], [0, 0, 0.3], 1e-6, 1e-5)
            T0 = ekf.pose_from_state(ekf.inject(truth[0], np.r_[0.006, -0.004, 0.004, np.deg2rad([1.5, -1, 1]), np.zeros(6)]))
            P0 = np.diag(np.r_[np.full(3, 0.01**2), np.full(3, np.deg2rad(2.0) ** 2), np.full(3, 0.05**2), np.full(3, 0.5**2)])
            f = ekf.PoseEKF(T0, P0, q_acc=1e-6, q_alpha=1e-5, sigma_px=0.5)
            err, found = [], []
            for k in range(n_frames):
                if k:
                    f.predict(dt)
                Tp, Tt = f.pose, ekf.pose_from_state(truth[k])
                zs, hs, Js = [], [], []
                for ic, Twc in cams:
                    idx, _, ang, sil = ts.visible_features(poly, ic, Twc, Tp)
                    h, _, J = project_with_jacobian(ic, Twc, Tp, poly.V[idx])
                    if m == "quality index":
                        pick = sel.select_quality(h, ang, sil, size, k=8, min_separation_px=sep)
                    elif m == "information":
                        pick = sel.select_information(h, J, ang, sil, size, P6=f.pose_covariance, k=8, min_separation_px=sep)
                    elif m == "information, quality-weighted":
                        pick = sel.select_information(h, J, ang, sil, size, P6=f.pose_covariance, k=8, min_separation_px=sep, weight_by_quality=True)
                    else:
                        el = np.flatnonzero(sel.eligible_mask(h, size, view_angle=ang, min_separation_px=sep))
                        pick = rsel.choice(el, min(8, len(el)), replace=False)
                    h, J = h[pick], J[pick]
                    S = J @ f.pose_covariance @ J.transpose(0, 2, 1) + 0.25 * np.eye(2)
                    img = ts.render_polyhedron(poly, ic, Twc, Tt, rng)
                    res = extract_corners(img, h, window_half_sizes(S))
                    found.append(res.found.mean())
                    zs.append(res.uv[res.found])
                    hs.append(h[res.found])
                    Js.append(J[res.found])
                f.update(np.concatenate(zs), np.concatenate(hs), np.concatenate(Js))
                err.append(se3.pose_error(f.pose, Tt))
            e = np.array(err)[15:]
            out[m].append((np.sqrt(np.mean(e[:, 0] ** 2)), np.sqrt(np.mean(e[:, 1] ** 2)), np.mean(found)))
    print(f"\nClosed loop on rendered images: chamfered box (chamfer {1e3 * chamfer:.0f} mm), 2 cameras, k=8, "
          f"min_separation 12 px, {n_frames} frames, seeds {list(seeds)} (after 15 frames)\n")
    print(f"| {'method':<30} | {'pos RMSE mm':>11} | {'rot RMSE deg':>12} | {'corners found':>13} |")
    print(f"|{'-' * 32}|{'-' * 12}:|{'-' * 13}:|{'-' * 14}:|")
    for m, v in out.items():
        v = np.array(v)
        print(f"| {m:<30} | {1e3 * np.sqrt(np.mean(v[:, 0] ** 2)):11.3f} | {np.rad2deg(np.sqrt(np.mean(v[:, 1] ** 2))):12.3f} | {100 * v[:, 2].mean():12.0f}% |")
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    reps = 300 if a.quick else 2000
    print(f"numpy {np.__version__}, opencv {cv2.__version__}, 1 thread (OMP_NUM_THREADS=1)\n")
    bench_timings(reps)
    print_table()
    selection_comparison(range(2) if a.quick else range(5))
    if not a.quick:
        rendered_comparison(range(5))


if __name__ == "__main__":
    main()
