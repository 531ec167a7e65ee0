"""Scenario suites: declarative benchmark runs of the tracker against ground truth.

A suite is a YAML file (see ``bench/suites/default.yaml``)::

    name: default
    defaults:              # fields every scenario starts from
      frames: 65
      noise_px: 0.3
    scenarios:             # explicit scenarios
      - {name: box-fixed2-conveyor, object: box, rig: fixed2, motion: conveyor}
    cross:                 # cross products: list-valued fields expand
      - name: "{object}-{rig}-{motion}"
        object: [box, lblock, bracket]
        rig: [fixed2, hybrid]

Scenario fields (defaults in :data:`DEFAULTS`):

* recording (they key the cache): ``object`` (box, lblock, bracket or a mesh
  path), ``rig`` (fixed1, fixed2, fixed3, hand, hybrid or a cameras.yaml path),
  ``motion`` (conveyor, sinusoid, sinusoid_fast, random, static), ``speed``,
  ``amplitude`` (m), ``rot_amplitude_deg``, ``stop_time`` (s), ``frames``,
  ``rate_hz``, ``resolution`` ("WxH"), ``noise_px`` (geometric feature noise),
  ``intensity_noise``, ``blur_px``, ``distortion`` (bool or k1,k2,p1,p2,k3),
  ``occluder`` (bool: a paddle sweeps in front of the first fixed camera),
  ``dropouts`` (list of ``CAMERA:T0:T1``; CAMERA a name or a rig index),
  ``arm`` (home, watch; eye-in-hand rigs always watch), ``encoder_noise``,
  ``seed``, ``clutter`` (a count of textured background items),
  ``distractors`` (a list of kinds: near, block, cylinder, box, lblock,
  bracket; see :mod:`vespro.sim.distractors`), ``distractor_motion`` (static,
  belt), ``textured_part`` (bool);
* tracking: ``init`` (``gt``: the filter starts from the ground-truth pose of
  frame 0, an evaluator-only choice that scores tracking alone; ``auto``: the
  automatic initialiser of :mod:`vespro.init`), ``features``, ``selection``,
  ``sigma_px``.

:func:`run_suite` makes the recordings it lacks (cached under ``cache_dir`` by a
hash of the recording fields, the object mesh and the rig file), tracks them,
scores them (:func:`score_scenario`) and writes ``results.json``,
``results.md``, ``summary.png`` and per scenario ``poses.csv`` and
``errors.png``.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import shutil
import time
import traceback
from pathlib import Path

import numpy as np
import yaml

from . import metrics
from .crlb import crlb_from_information, crlb_std, frame_information, posterior_crlb

__all__ = ["DEFAULTS", "RECORDING_FIELDS", "load_suite", "expand_suite", "scenario_key", "ensure_recording",
           "score_scenario", "score_published", "track_scenario", "run_scenario", "run_suite", "markdown_table"]

#: Bumped when the simulator's output for the same fields changes (invalidates the cache).
SIM_CACHE_VERSION = 1

RECORDING_FIELDS = ("object", "rig", "motion", "speed", "amplitude", "rot_amplitude_deg", "stop_time", "frames",
                    "rate_hz", "resolution", "noise_px", "intensity_noise", "blur_px", "distortion", "occluder",
                    "dropouts", "arm", "encoder_noise", "seed", "clutter", "distractors", "distractor_motion",
                    "textured_part")
TRACK_FIELDS = ("init", "features", "selection", "sigma_px")

DEFAULTS = {
    "object": "box", "rig": "fixed2", "motion": "conveyor", "speed": None, "amplitude": None,
    "rot_amplitude_deg": None, "stop_time": None, "frames": 65, "rate_hz": 26.0, "resolution": None,
    "noise_px": 0.0, "intensity_noise": 0.0, "blur_px": 0.0, "distortion": False, "occluder": False,
    "dropouts": [], "arm": "home", "encoder_noise": 0.0, "seed": 0,
    "clutter": 0, "distractors": [], "distractor_motion": "static", "textured_part": False,
    "init": "gt", "features": 8, "selection": "quality", "sigma_px": 0.5,
}
#: Scene fields added after the cache's first recordings: left out of the cache key at their default,
#: so the recordings of scenarios that do not use them keep their keys.
_KEYED_WHEN_SET = ("clutter", "distractors", "distractor_motion", "textured_part")
_NOT_CROSSED = ("dropouts", "distortion", "distractors")
MOTIONS = {"conveyor": ("conveyor", None), "sinusoid": ("sinusoid", None), "sinusoid_slow": ("sinusoid", 1.0),
           "sinusoid_fast": ("sinusoid", 2.5), "random": ("random", None), "static": ("static", None)}
SYMMETRIC_OBJECTS_NOTE = "ADD-S for objects with discrete symmetries (found from the model), ADD otherwise"


# -- suite files --------------------------------------------------------------
def _check_fields(d: dict, where: str) -> None:
    unknown = set(d) - set(DEFAULTS) - {"name"}
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {sorted(unknown)}; known: {sorted(DEFAULTS)}")


def _check_scene(s: dict, where: str) -> None:
    """Validate (and normalise in place) the clutter and distractor fields of a scenario."""
    from .sim.distractors import DISTRACTOR_KINDS, DISTRACTOR_MOTIONS

    c = s["clutter"]
    if isinstance(c, bool) or not isinstance(c, int) or c < 0:
        raise ValueError(f"{where}: clutter must be a count >= 0, got {c!r}")
    d = s["distractors"]
    if isinstance(d, str):
        d = [d]
    if not isinstance(d, list) or any(k not in DISTRACTOR_KINDS for k in d):
        raise ValueError(f"{where}: distractors must be a list of {', '.join(DISTRACTOR_KINDS)}, got {d!r}")
    s["distractors"] = list(d)
    if s["distractor_motion"] not in DISTRACTOR_MOTIONS:
        raise ValueError(f"{where}: distractor_motion must be one of {', '.join(DISTRACTOR_MOTIONS)}, "
                         f"got {s['distractor_motion']!r}")
    if s["distractor_motion"] == "belt" and s["motion"] != "conveyor":
        raise ValueError(f"{where}: distractor_motion belt needs motion conveyor")
    if not isinstance(s["textured_part"], bool):
        raise ValueError(f"{where}: textured_part must be true or false, got {s['textured_part']!r}")


def expand_suite(data: dict, source: str = "suite") -> tuple[str, list[dict]]:
    """Scenarios of a parsed suite: defaults applied, cross products expanded.

    Returns
    -------
    name : str
    scenarios : list of dict
        Every field of :data:`DEFAULTS` plus ``name``; names are unique.
    """
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a mapping with 'scenarios' and/or 'cross'")
    unknown = set(data) - {"name", "defaults", "scenarios", "cross", "description"}
    if unknown:
        raise ValueError(f"{source}: unknown top-level key(s) {sorted(unknown)}")
    base = dict(DEFAULTS)
    d = data.get("defaults") or {}
    _check_fields(d, f"{source}: defaults")
    base.update(d)
    out = []
    for k, s in enumerate(data.get("scenarios") or []):
        _check_fields(s, f"{source}: scenarios[{k}]")
        sc = {**base, **s}
        sc.setdefault("name", f"scenario{k}")
        out.append(sc)
    for k, c in enumerate(data.get("cross") or []):
        _check_fields(c, f"{source}: cross[{k}]")
        template = c.get("name", "{object}-{rig}-{motion}")
        axes = [(f, v) for f, v in c.items() if f != "name" and isinstance(v, list) and f not in _NOT_CROSSED]
        fixed = {f: v for f, v in c.items() if f != "name" and (f, v) not in axes}
        for combo in itertools.product(*[v for _, v in axes]):
            sc = {**base, **fixed, **dict(zip([f for f, _ in axes], combo))}
            sc["name"] = template.format(**sc)
            out.append(sc)
    names = [s["name"] for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{source}: duplicate scenario names {dup}")
    for s in out:
        if s["motion"] not in MOTIONS:
            raise ValueError(f"{source}: scenario {s['name']}: motion must be one of {sorted(MOTIONS)}")
        if s["init"] not in ("gt", "auto"):
            raise ValueError(f"{source}: scenario {s['name']}: init must be 'gt' or 'auto', got {s['init']!r}")
        _check_scene(s, f"{source}: scenario {s['name']}")
    return str(data.get("name", Path(source).stem)), out


def load_suite(path: str | Path) -> tuple[str, list[dict]]:
    """Read and expand a suite YAML file (see the module docstring)."""
    path = Path(path)
    return expand_suite(yaml.safe_load(path.read_text()), str(path))


# -- recordings -----------------------------------------------------------------
def _file_hash(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def scenario_key(sc: dict) -> str:
    """Cache key of a scenario's recording: hash of its recording fields, mesh and rig file."""
    from .library import object_mesh_path
    from .sim.rigs import rig_path

    fields = {f: sc[f] for f in RECORDING_FIELDS if f not in _KEYED_WHEN_SET or sc[f] != DEFAULTS[f]}
    payload = {"fields": fields, "mesh": _file_hash(object_mesh_path(str(sc["object"]))),
               "rig": _file_hash(rig_path(str(sc["rig"]))), "version": SIM_CACHE_VERSION}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _record_args(sc: dict, rig) -> argparse.Namespace:
    from .sim.cell import CameraDropout
    from .sim.scenario import parse_resolution

    kind, speed = MOTIONS[sc["motion"]]
    drops = []
    for d in sc["dropouts"] or []:
        if isinstance(d, dict):
            cam, t0, t1 = d["camera"], d["t0"], d["t1"]
        else:
            cam, t0, t1 = str(d).split(":")
        if isinstance(cam, int) or str(cam).isdigit():
            cam = rig.names[int(cam)]
        drops.append(CameraDropout(str(cam), float(t0), float(t1)))
    dist = sc["distortion"]
    coeffs = None
    if isinstance(dist, (list, tuple)):
        coeffs, dist = tuple(float(x) for x in dist), True
    return argparse.Namespace(
        object=str(sc["object"]), rig=str(sc["rig"]), motion=kind, rate=float(sc["rate_hz"]),
        resolution=parse_resolution(sc["resolution"]) if sc["resolution"] else None,
        speed=sc["speed"] if sc["speed"] is not None else speed, amplitude=sc["amplitude"],
        rot_amplitude_deg=sc["rot_amplitude_deg"], stop_time=sc["stop_time"], noise=float(sc["noise_px"]),
        intensity_noise=float(sc["intensity_noise"]), blur=float(sc["blur_px"]), distortion=bool(dist),
        distortion_coeffs=coeffs, occluder=bool(sc["occluder"]), drop=drops, arm=sc["arm"],
        encoder_noise=float(sc["encoder_noise"]), seed=int(sc["seed"]), frames=int(sc["frames"]),
        clutter=int(sc["clutter"]), distractor=list(sc["distractors"]), distractor_motion=sc["distractor_motion"],
        textured_part=bool(sc["textured_part"]))


def ensure_recording(sc: dict, cache_dir: str | Path, log=print) -> Path:
    """The scenario's recording in the cache, simulated first when missing.

    Written to a temporary folder and renamed, so an interrupted run leaves
    no half recording behind under the final name.
    """
    from .rig import load_rig
    from .sim.record import record
    from .sim.rigs import rig_path
    from .sim.scenario import build_config

    cache_dir = Path(cache_dir)
    key = scenario_key(sc)
    final = cache_dir / key
    if (final / "groundtruth.csv").is_file():
        return final
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = cache_dir / f".tmp-{key}"
    if tmp.exists():
        shutil.rmtree(tmp)
    args = _record_args(sc, load_rig(rig_path(str(sc["rig"]))))
    config, motion, name = build_config(args)
    log(f"  recording {sc['name']} ({args.frames} frames) -> {final}")
    record(tmp, config, motion, args.frames, name, extra_meta={"scenario": {f: sc[f] for f in RECORDING_FIELDS}})
    if final.exists():
        shutil.rmtree(final)
    tmp.rename(final)
    return final


# -- scoring ---------------------------------------------------------------------
def _nan_none(x):
    if x is None:
        return None
    x = float(x)
    return None if not np.isfinite(x) else x


def _rms(x) -> float:
    x = np.asarray([v for v in x if v is not None and np.isfinite(v)], dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def score_scenario(rec, outs, T_true: np.ndarray, model, tracker_config, scene=None, salient=None,
                   sigma_nominal_px: float = 0.0) -> tuple[dict, dict]:
    """All figures of one tracked recording.

    Parameters
    ----------
    rec : Recording
    outs : list of TrackerOutput
    T_true : ndarray (N, 4, 4)
        True ``T_world_object`` per frame.
    model : Model
    tracker_config : TrackerConfig
        For the posterior bound's motion model and prior.
    scene, salient : VisibilityScene, ndarray (C,) bool, optional
        The tracker's visibility scene and salient-corner mask: with them the
        bound for "every visible salient corner measured" is added.
    sigma_nominal_px : float
        The scenario's nominal feature noise (reported only).

    Returns
    -------
    figures : dict
        JSON-ready numbers (units in the key names).
    series : dict
        Per-frame arrays for plots: ``t``, ``pos_err_m``, ``rot_err_rad``,
        ``crlb_pos_m``, ``crlb_rot_rad``, ``pcrlb_pos_m``, ``pcrlb_rot_rad``.
    """
    from .camera import project_points
    from .evaluate import pnp_baseline, score
    from .se3 import invert_transform

    n = len(outs)
    t = rec.t
    T_est = [o.T_world_object if o.status == "tracking" else None for o in outs]
    status = [o.status for o in outs]
    syms = metrics.discrete_symmetries(model.vertices)
    symmetric = len(syms) > 1
    base = score(T_est, status, T_true, t, model, [o.time_ms for o in outs], [o.cov6 for o in outs],
                 symmetric=symmetric)
    tracked = np.array([T is not None for T in T_est])
    P = model.vertices

    # BOP-style errors: a frame without an estimate counts as a miss (infinite error).
    mssd = np.array([metrics.mssd(T, T_true[i], P, syms) if T is not None else np.inf for i, T in enumerate(T_est)])
    mspd = []
    for i in range(n):
        for cam in rec.rig:
            if rec.image_path(cam.name, i).is_file() is False:
                continue
            T_wc = rec.T_world_camera(cam.name, i)
            T_co_true = invert_transform(T_wc) @ T_true[i]
            uv, z = project_points(cam.intrinsics, T_co_true, model.corners)
            w, h = cam.intrinsics.width, cam.intrinsics.height
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            if not inside.any():
                continue  # the object is not in this image: BOP has no ground truth there either
            e = (metrics.mspd(invert_transform(T_wc) @ T_est[i], T_co_true, P, cam.intrinsics, syms)
                 if T_est[i] is not None else np.inf)
            mspd.append(e * 640.0 / w)  # in units of a 640-px-wide image: one threshold set for all cameras
    mspd = np.array(mspd)
    add_fn = metrics.add_s if symmetric else metrics.add
    adds = np.array([add_fn(T, T_true[i], P) if T is not None else np.inf for i, T in enumerate(T_est)])

    # Measured feature noise: accepted corners against their projection at the true pose.
    res = []
    views_used, views_vis = [], []
    for i, o in enumerate(outs):
        vu, vv = [], []
        for ob in o.observations:
            cam = rec.rig[ob.name]
            T_wc = rec.T_world_camera(ob.name, i)
            if ob.feature_ids.size:
                ids = ob.feature_ids[ob.accepted]
                if ids.size:
                    Pc = model.corners[ids]
                    uv_true, _ = project_points(cam.intrinsics, invert_transform(T_wc) @ T_true[i], Pc)
                    res.append(ob.uv_meas[ob.accepted] - uv_true)
                    vu.append((cam.intrinsics, T_wc, Pc))
            if scene is not None and ob.has_image:
                vis = scene.query(0, T_wc, [T_true[i]], cam.intrinsics)
                keep = salient[vis.indices] if salient is not None else np.ones(vis.indices.size, bool)
                if keep.any():
                    vv.append((cam.intrinsics, T_wc, vis.points[keep]))
        views_used.append(vu)
        views_vis.append(vv)
    res = np.concatenate(res) if res else np.zeros((0, 2))
    res = res[np.all(np.isfinite(res), axis=1)]
    sigma_meas = float(np.sqrt(np.mean(res**2))) if res.size else float("nan")
    sigma = sigma_meas if np.isfinite(sigma_meas) and sigma_meas > 0 else max(sigma_nominal_px, 0.1)

    infos = [frame_information(v, T_true[i], sigma) for i, v in enumerate(views_used)]
    crlb = [crlb_std(crlb_from_information(I)) for I in infos]
    crlb_pos = np.array([c[0] for c in crlb])
    crlb_rot = np.array([c[1] for c in crlb])
    crlb_vis = [crlb_std(crlb_from_information(frame_information(v, T_true[i], sigma)))
                for i, v in enumerate(views_vis)] if scene is not None else []
    c = tracker_config
    P0 = np.diag(np.r_[np.full(3, c.init_sigma_pos**2), np.full(3, c.init_sigma_rot**2),
                       np.full(3, c.init_sigma_vel**2), np.full(3, c.init_sigma_angvel**2)])
    pc = posterior_crlb(T_true, t, infos, P0, c.q_acc, c.q_alpha)
    pcrlb_pos = np.sqrt(np.trace(pc[:, :3, :3], axis1=1, axis2=2))
    pcrlb_rot = np.sqrt(np.trace(pc[:, 3:, 3:], axis1=1, axis2=2))

    pos_err = np.array([np.linalg.norm(T[:3, 3] - T_true[i][:3, 3]) if T is not None else np.nan
                        for i, T in enumerate(T_est)])
    rot_err = np.array([np.linalg.norm(metrics.pose_error_vector(T, T_true[i])[3:]) if T is not None else np.nan
                        for i, T in enumerate(T_est)])
    # Bounds over the tracked frames with a finite per-frame bound, the same frames as the errors.
    both = tracked & np.isfinite(crlb_pos)
    crlb_pos_rms = _rms(crlb_pos[both])
    crlb_rot_rms = _rms(crlb_rot[both])
    pos_rmse_b = _rms(pos_err[both])
    rot_rmse_b = _rms(rot_err[both])
    pc_pos_rms = _rms(pcrlb_pos[tracked])
    pc_rot_rms = _rms(pcrlb_rot[tracked])

    losses = metrics.reacquisition_times(tracked, t)
    lo, hi = metrics.nees_band(6)
    T_b = pnp_baseline(rec, outs, model)
    pnp_pos = [np.linalg.norm(T[:3, 3] - T_true[i][:3, 3]) for i, T in enumerate(T_b) if T is not None]
    d = model.diameter
    fig = {
        "frames": n,
        "cameras": rec.rig.names,
        "tracked_fraction": base["tracked_fraction"],
        "time_to_first_track_s": base["time_to_first_track_s"],
        "losses": len(losses),
        "reacquisition_s": losses,
        "position_rmse_mm": base["position_rmse_mm"],
        "position_max_mm": base["position_max_mm"],
        "orientation_rmse_deg": base["orientation_rmse_deg"],
        "orientation_max_deg": base["orientation_max_deg"],
        "add_mm": base["add_mm"],
        "adds_mm": base.get("adds_mm"),
        "symmetries": len(syms),
        "addS_recall_0.1d": float(np.mean(adds < 0.1 * d)),
        "mssd_mm_median": _nan_none(np.median(mssd[np.isfinite(mssd)]) * 1e3) if np.isfinite(mssd).any() else None,
        "mssd_recall": metrics.recall(mssd, metrics.mssd_thresholds(d)),
        "mspd_px_median": _nan_none(np.median(mspd[np.isfinite(mspd)])) if np.isfinite(mspd).any() else None,
        "mspd_recall": metrics.recall(mspd, metrics.mspd_thresholds(640)),
        "nees_mean": base.get("nees_mean"),
        "nees_in_band": base.get("nees_in_band"),
        "nees_band": [lo, hi],
        "time_ms_median": base.get("time_ms_median"),
        "time_ms_p99": base.get("time_ms_p99"),
        "wrong_lock_frames": base["wrong_lock_frames"],
        "pnp_position_rmse_mm": rmse_mm(pnp_pos),
        "sigma_nominal_px": sigma_nominal_px,
        "sigma_measured_px": _nan_none(sigma_meas),
        "crlb_sigma_px": sigma,
        "crlb_frames": int(both.sum()),
        "crlb_pos_mm": _nan_none(crlb_pos_rms * 1e3),
        "crlb_rot_deg": _nan_none(np.rad2deg(crlb_rot_rms)),
        "rmse_over_crlb_pos": _nan_none(pos_rmse_b / crlb_pos_rms) if both.any() else None,
        "rmse_over_crlb_rot": _nan_none(rot_rmse_b / crlb_rot_rms) if both.any() else None,
        # The bound scales linearly with sigma: the same bound at the scenario's nominal noise.
        "crlb_pos_mm_at_nominal": (_nan_none(crlb_pos_rms * 1e3 * sigma_nominal_px / sigma)
                                   if sigma_nominal_px > 0 else None),
        "crlb_visible_pos_mm": _nan_none(_rms([x[0] for x in crlb_vis]) * 1e3) if crlb_vis else None,
        "crlb_visible_rot_deg": _nan_none(np.rad2deg(_rms([x[1] for x in crlb_vis]))) if crlb_vis else None,
        "pcrlb_pos_mm": _nan_none(pc_pos_rms * 1e3),
        "pcrlb_rot_deg": _nan_none(np.rad2deg(pc_rot_rms)),
        "rmse_over_pcrlb_pos": _nan_none(_rms(pos_err[tracked]) / pc_pos_rms) if tracked.any() else None,
        "rmse_over_pcrlb_rot": _nan_none(_rms(rot_err[tracked]) / pc_rot_rms) if tracked.any() else None,
    }
    series = {"t": t, "pos_err_m": pos_err, "rot_err_rad": rot_err, "crlb_pos_m": crlb_pos,
              "crlb_rot_rad": crlb_rot, "pcrlb_pos_m": pcrlb_pos, "pcrlb_rot_rad": pcrlb_rot}
    return fig, series


def rmse_mm(errors_m) -> float | None:
    e = np.asarray(errors_m, dtype=float)
    return float(np.sqrt(np.mean(e * e)) * 1e3) if e.size else None


def _plot_series(path: Path, title: str, s: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].semilogy(s["t"], s["pos_err_m"] * 1e3, lw=1, label="EKF |error|")
    ax[0].semilogy(s["t"], s["crlb_pos_m"] * 1e3, lw=1, ls="--", label="per-frame CRLB")
    ax[0].semilogy(s["t"], s["pcrlb_pos_m"] * 1e3, lw=1, ls=":", label="posterior CRLB")
    ax[0].set_ylabel("position (mm)")
    ax[1].semilogy(s["t"], np.rad2deg(s["rot_err_rad"]), lw=1)
    ax[1].semilogy(s["t"], np.rad2deg(s["crlb_rot_rad"]), lw=1, ls="--")
    ax[1].semilogy(s["t"], np.rad2deg(s["pcrlb_rot_rad"]), lw=1, ls=":")
    ax[1].set_ylabel("orientation (deg)")
    ax[1].set_xlabel("time (s)")
    ax[0].legend(loc="upper right", fontsize=8)
    ax[0].set_title(title, fontsize=10)
    for a in ax:
        a.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_summary(path: Path, results: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in results if r.get("figures")]
    if not ok:
        return
    names = [r["name"] for r in ok]
    x = np.arange(len(ok))
    fig, ax = plt.subplots(2, 1, figsize=(max(8, 0.45 * len(ok) + 2), 7), sharex=True)
    for a, key, bound, pbound, unit in [(ax[0], "position_rmse_mm", "crlb_pos_mm", "pcrlb_pos_mm", "mm"),
                                        (ax[1], "orientation_rmse_deg", "crlb_rot_deg", "pcrlb_rot_deg", "deg")]:
        f = [r["figures"] for r in ok]
        a.bar(x - 0.27, [v.get(key) or np.nan for v in f], 0.27, label="EKF RMSE")
        a.bar(x, [v.get(bound) or np.nan for v in f], 0.27, label="per-frame CRLB (RMS)")
        a.bar(x + 0.27, [v.get(pbound) or np.nan for v in f], 0.27, label="posterior CRLB (RMS)")
        a.set_yscale("log")
        a.set_ylabel(unit)
        a.grid(alpha=0.3, axis="y", which="both")
    ax[0].legend(fontsize=8)
    ax[1].set_xticks(x)
    ax[1].set_xticklabels(names, rotation=60, ha="right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def score_published(outs, T_true: np.ndarray, model, distractors: dict | None = None) -> dict:
    """Figures of what was published (status ``tracking``) over one tracked recording.

    Parameters
    ----------
    outs : list of TrackerOutput
    T_true : ndarray (N, 4, 4)
        True ``T_world_object`` per frame.
    model : Model
    distractors : dict, optional
        :func:`vespro.groundtruth.read_distractors` of the recording.

    Returns
    -------
    dict
        ``frames``; ``published`` (frames published ``tracking``); ``max_err`` (largest
        published error, ADD to the nearest symmetric equivalent, fraction of the
        diameter; nan if none); ``ge5``, ``ge10`` (published frames at least 5% / 10% of
        the diameter off); ``first`` (first published frame or None); ``on_distractor``
        (published frames whose model centre lies nearer a distractor's centre than the
        part's true centre); ``times_s`` (the tracker's time per frame).
    """
    syms = metrics.discrete_symmetries(model.vertices)
    P = model.vertices
    c = 0.5 * (P.min(axis=0) + P.max(axis=0))
    n = len(outs)
    err = np.full(n, np.nan)
    on_distractor = 0
    for i, o in enumerate(outs):
        if o.status != "tracking":
            continue
        T = o.T_world_object
        err[i] = metrics.add_sym(T, T_true[i], P, syms) / model.diameter
        p = T[:3, :3] @ c + T[:3, 3]
        d_part = np.linalg.norm(p - (T_true[i][:3, :3] @ c + T_true[i][:3, 3]))
        for d in (distractors or {}).values():
            k = np.flatnonzero(d["index"] == o.index)
            if k.size and np.linalg.norm(p - d["center"][k[0]]) < d_part:
                on_distractor += 1
                break
    pub = np.isfinite(err)
    return {"frames": n, "published": int(pub.sum()), "max_err": float(np.nanmax(err)) if pub.any() else float("nan"),
            "ge5": int(np.sum(err[pub] >= 0.05)), "ge10": int(np.sum(err[pub] >= 0.10)),
            "first": int(np.argmax(pub)) if pub.any() else None, "on_distractor": on_distractor,
            "times_s": [o.time_ms * 1e-3 for o in outs]}


# -- running -----------------------------------------------------------------------
def track_scenario(sc: dict, cache_dir: str | Path, log=print, overrides: dict | None = None) -> dict:
    """Record (if needed) and track one scenario.

    ``overrides``: ``TrackerConfig`` fields to set besides the scenario's.

    Returns
    -------
    dict
        ``rec_path``, ``rec`` (Recording), ``T_true`` (N, 4, 4), ``tracker``, ``config`` and ``outs``
        (list of TrackerOutput).
    """
    from dataclasses import replace

    from .groundtruth import read_groundtruth
    from .recording import Recording
    from .track import make_tracker, track_recording
    from .tracker import TrackerConfig

    make_initializer = None
    if sc["init"] == "auto":  # checked before simulating anything
        try:
            from .init import decision_options, make_initializer
        except ImportError:
            raise RuntimeError("init: auto needs vespro.init (automatic initialisation), which is not available") from None
    rec_path = ensure_recording(sc, cache_dir, log=log)
    rec = Recording(rec_path)
    _, _, T_true = read_groundtruth(rec_path)
    config = replace(TrackerConfig(features_per_camera=int(sc["features"]), selection=sc["selection"],
                                   sigma_px=float(sc["sigma_px"])), **(overrides or {}))
    tracker = make_tracker(rec, config)
    init_pose = None
    if sc["init"] == "gt":
        init_pose = T_true[0]  # evaluator-only: scores tracking, not initialisation
    else:
        # The decision's initialiser settings, as ``--decision`` sets them (vespro.init.decision_options).
        tracker.initializer = make_initializer(rec.rig, tracker.model, **decision_options(config.decision))
    outs = track_recording(rec, tracker, init_pose)
    return {"rec_path": rec_path, "rec": rec, "T_true": T_true, "tracker": tracker, "config": config, "outs": outs}


def run_scenario(sc: dict, cache_dir: str | Path, out_dir: str | Path, log=print) -> dict:
    """Record (if needed), track and score one scenario; writes poses.csv and errors.png under ``out_dir``."""
    from .track import write_track

    t_start = time.perf_counter()
    r = track_scenario(sc, cache_dir, log=log)
    rec, tracker, outs = r["rec"], r["tracker"], r["outs"]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_track(out_dir / "poses.csv", rec, outs)
    fig, series = score_scenario(rec, outs, r["T_true"], tracker.model, r["config"], tracker.scene, tracker.salient,
                                 float(sc["noise_px"]))
    _plot_series(out_dir / "errors.png", sc["name"], series)
    return {"name": sc["name"], "scenario": {k: sc[k] for k in ("name",) + RECORDING_FIELDS + TRACK_FIELDS},
            "recording": str(r["rec_path"]), "figures": fig, "wall_s": time.perf_counter() - t_start}


def _f(v, nd=2, scale=1.0):
    if v is None:
        return "-"
    v = float(v) * scale
    return "-" if not np.isfinite(v) else f"{v:.{nd}f}"


def _describe(sc: dict) -> str:
    bits = []
    if sc["noise_px"]:
        bits.append(f"noise {sc['noise_px']:g}px")
    if sc["blur_px"]:
        bits.append(f"blur {sc['blur_px']:g}")
    if sc["intensity_noise"]:
        bits.append(f"sensor {sc['intensity_noise']:g}")
    if sc["distortion"]:
        bits.append("distortion")
    if sc["occluder"]:
        bits.append("occluder")
    for d in sc["dropouts"] or []:
        bits.append(f"drop {d}")
    if sc.get("clutter"):
        bits.append(f"clutter {sc['clutter']}")
    for d in sc.get("distractors") or []:
        bits.append(f"distractor {d}")
    if sc.get("textured_part"):
        bits.append("textured part")
    return ", ".join(bits) or "clean"


def markdown_table(results: list[dict]) -> str:
    """Two Markdown tables (accuracy vs bound; robustness and timing) of suite results."""
    h1 = ("| scenario | object | rig | motion | conditions | tracked | pos RMSE mm | pos max mm | rot RMSE deg "
          "| ADD(-S) mm | MSSD AR | MSPD AR | NEES in 95% | CRLB pos mm | RMSE/CRLB pos | CRLB rot deg "
          "| RMSE/CRLB rot | RMSE/post. CRLB pos |")
    lines = [h1, "|" + "---|" * (h1.count("|") - 1)]
    for r in results:
        sc = r["scenario"]
        f = r.get("figures")
        if not f:
            lines.append(f"| {r['name']} | {sc['object']} | {sc['rig']} | {sc['motion']} | {_describe(sc)} "
                         f"| error: {r.get('error', '?')} |" + " |" * 12)
            continue
        addv = f["adds_mm"] if f["symmetries"] > 1 else f["add_mm"]
        lines.append(
            f"| {r['name']} | {sc['object']} | {sc['rig']} | {sc['motion']} | {_describe(sc)} "
            f"| {_f(f['tracked_fraction'], 0, 100)}% | {_f(f['position_rmse_mm'])} | {_f(f['position_max_mm'])} "
            f"| {_f(f['orientation_rmse_deg'], 3)} | {_f(addv)} | {_f(f['mssd_recall'])} | {_f(f['mspd_recall'])} "
            f"| {_f(f['nees_in_band'])} | {_f(f['crlb_pos_mm'], 3)} | {_f(f['rmse_over_crlb_pos'])} "
            f"| {_f(f['crlb_rot_deg'], 4)} | {_f(f['rmse_over_crlb_rot'])} | {_f(f['rmse_over_pcrlb_pos'])} |")
    h2 = ("| scenario | frames | first track s | losses | re-acquired after s | sigma meas. px | CRLB all-visible pos mm "
          "| posterior CRLB pos mm | PnP pos RMSE mm | ms/frame median | ms/frame p99 |")
    lines += ["", h2, "|" + "---|" * (h2.count("|") - 1)]
    for r in results:
        f = r.get("figures")
        if not f:
            continue
        re = ", ".join("never" if x is None else f"{x:.2f}" for x in f["reacquisition_s"]) or "-"
        lines.append(
            f"| {r['name']} | {f['frames']} | {_f(f['time_to_first_track_s'])} | {f['losses']} | {re} "
            f"| {_f(f['sigma_measured_px'])} | {_f(f['crlb_visible_pos_mm'], 3)} | {_f(f['pcrlb_pos_mm'], 3)} "
            f"| {_f(f['pnp_position_rmse_mm'])} | {_f(f['time_ms_median'], 1)} | {_f(f['time_ms_p99'], 1)} |")
    return "\n".join(lines) + "\n"


NOTES = """Notes
- init: `gt` scenarios start the filter from the ground-truth pose of frame 0 (evaluator-only):
  they score tracking, not initialisation; a lost track is then never re-acquired.
- ADD(-S): {sym}. MSSD / MSPD recall: BOP average recall over thresholds 0.05..0.5 x diameter
  and 5..50 px x (width/640); frames without an estimate count as misses. MSPD is pooled over
  every camera image that shows the object.
- CRLB: the per-frame (static, no-prior) Cramer-Rao bound from the corners the tracker measured
  and accepted in that frame (all cameras), Jacobians at the true pose, pixel noise = the measured
  RMS error of those corners (column "sigma meas."). A filter with a motion model can go below
  it (RMSE/CRLB < 1). "posterior CRLB" is the recursive bound with the EKF's constant-velocity
  model and initial covariance; "CRLB all-visible" assumes every visible salient corner measured.
""".format(sym=SYMMETRIC_OBJECTS_NOTE)


def run_suite(path: str | Path, out: str | Path | None = None, cache_dir: str | Path = "out/suite_cache",
              only: str | None = None, log=print) -> dict:
    """Run every scenario of a suite file; write results.json, results.md, summary.png.

    Returns
    -------
    dict
        ``{"suite", "results": [...], "failed": n}``.
    """
    name, scenarios = load_suite(path)
    if only:
        scenarios = [s for s in scenarios if only in s["name"]]
    out = Path(out or Path("out") / "suite" / name)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    t0 = time.perf_counter()
    for k, sc in enumerate(scenarios):
        log(f"[{k + 1}/{len(scenarios)}] {sc['name']}")
        try:
            r = run_scenario(sc, cache_dir, out / sc["name"], log=log)
            f = r["figures"]
            log(f"  tracked {f['tracked_fraction']:.0%}, pos RMSE {_f(f['position_rmse_mm'])} mm "
                f"(CRLB {_f(f['crlb_pos_mm'], 3)}), rot RMSE {_f(f['orientation_rmse_deg'], 3)} deg, "
                f"{r['wall_s']:.1f} s")
        except Exception as e:  # one broken scenario must not stop the suite
            r = {"name": sc["name"], "scenario": {k2: sc[k2] for k2 in ("name",) + RECORDING_FIELDS + TRACK_FIELDS},
                 "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
            log(f"  FAILED: {r['error']}")
        results.append(r)
    summary = {"suite": name, "source": str(path), "wall_s": time.perf_counter() - t0, "results": results,
               "failed": sum("error" in r for r in results)}
    (out / "results.json").write_text(json.dumps(summary, indent=2, default=str))
    (out / "results.md").write_text(f"# Suite `{name}`\n\n" + markdown_table(results) + "\n" + NOTES)
    _plot_summary(out / "summary.png", results)
    return summary
