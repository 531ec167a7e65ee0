"""What the tracker publishes on the decision suites: fast motion, clutter and distractors.

For every scenario of the given suites (default ``bench/suites/fast.yaml`` and
``bench/suites/clutter.yaml``) the recording is made if the cache lacks it
(``vespro.suite``), tracked with the current tracker (the automatic start
where the scenario says ``init: auto``, the true pose of frame 0 where it
says ``gt``) and scored on what was *published* (frames with status
``tracking``):

- tracked: the fraction of frames published ``tracking``;
- max err: the largest error of a published pose, ADD to the nearest
  symmetric equivalent of the true pose, % of the part's diameter;
- >=5% / >=10%: published frames that far off (10%: a wrong lock);
- first: the first frame published ``tracking``;
- distractor: frames published at a pose whose model centre is nearer the
  centre of a distractor (``distractors.csv``, evaluator-only) than the
  part's true centre;
- NEES in 95%: the fraction of published frames whose error (to the
  nearest symmetric equivalent of the true pose) over the published
  covariance falls in the two-sided 95% chi-square band of 6 dof (a
  consistent covariance: 0.95);
- ms/frame median and p99: the tracker's own per-frame time (with
  ``init: auto`` the initialiser runs inside the frames it is called on, as
  replayed here, and its time counts there).

Totals sum the frames over scenarios. Timings depend on the machine's load.

Usage: ``python3 bench/decision.py [SUITE.yaml ...] [--only TEXT] [--cache DIR]
[--set FIELD=VALUE ...] [--out DIR]`` (``--set``: a ``TrackerConfig`` field
for every scenario, e.g. a decision switch; ``--out``: per scenario
``poses.csv`` and ``overlay.png``, every camera at the middle frame with the
published pose in green, each distractor's true centre as a red cross and the
near-shape distractor's outline in red).
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from bench._table import print_table, stats_ms  # noqa: E402
from vespro.camera import project_points  # noqa: E402
from vespro.groundtruth import read_distractors  # noqa: E402
from vespro.metrics import add, discrete_symmetries, nees, nees_band  # noqa: E402
from vespro.se3 import invert_transform  # noqa: E402
from vespro.sim.distractors import NEAR_HEIGHT_SCALE  # noqa: E402
from vespro.suite import load_suite, score_published, track_scenario  # noqa: E402

SUITES = [ROOT / "bench" / "suites" / "fast.yaml", ROOT / "bench" / "suites" / "clutter.yaml"]


def write_outputs(out: Path, r: dict, distractors: dict) -> None:
    """``poses.csv`` and ``overlay.png`` (every camera side by side, the middle frame) of a tracked scenario."""
    import cv2

    from vespro.evaluate import draw_overlay
    from vespro.track import write_track

    out.mkdir(parents=True, exist_ok=True)
    rec, outs, model = r["rec"], r["outs"], r["tracker"].model
    write_track(out / "poses.csv", rec, outs)
    i = len(outs) // 2
    o = outs[i]
    views = []
    for cam in rec.rig:
        img = rec.image(cam.name, i)
        if img is None:
            continue
        T_cw = invert_transform(rec.T_world_camera(cam.name, i))
        img = img.copy() if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        for d in distractors.values():
            k = np.flatnonzero(d["index"] == o.index)
            if not k.size:
                continue
            if d["kind"] == "near":  # its shape: the part's model, lower
                T = T_cw @ d["T"][k[0]] @ np.diag([1.0, 1.0, NEAR_HEIGHT_SCALE, 1.0])
                mask = np.any(draw_overlay(img, model, cam.intrinsics, T) != img, axis=2)
                img[mask] = (0, 0, 255)
            uv, z = project_points(cam.intrinsics, T_cw, d["center"][k[0]][None])
            if z[0] > 0:
                cv2.drawMarker(img, (int(uv[0, 0]), int(uv[0, 1])), (0, 0, 255), cv2.MARKER_CROSS, 12, 2)
        T = T_cw @ o.T_world_object if o.status == "tracking" else None
        views.append(draw_overlay(img, model, cam.intrinsics, T))
    cv2.putText(views[0], f"frame {i}: {o.status}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1)
    cv2.imwrite(str(out / "overlay.png"), np.hstack(views))


def published_nees(outs, T_true, model) -> list:
    """NEES of each published frame with a covariance, against the true pose's nearest symmetric equivalent."""
    syms = discrete_symmetries(model.vertices)
    out = []
    for i, o in enumerate(outs):
        if o.status != "tracking" or o.cov6 is None:
            continue
        Ts = min((T_true[i] @ S for S in syms), key=lambda T: add(o.T_world_object, T, model.vertices))
        out.append(nees(o.T_world_object, Ts, o.cov6))
    return out


def _in_band(values) -> float:
    lo, hi = nees_band(6)
    v = np.asarray(values, float)
    return float(np.mean((v >= lo) & (v <= hi))) if v.size else float("nan")


def _overrides(items) -> dict:
    out = {}
    for s in items or []:
        k, _, v = s.partition("=")
        try:
            out[k.strip()] = ast.literal_eval(v.strip())
        except (ValueError, SyntaxError):
            out[k.strip()] = v.strip()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("suites", nargs="*", type=Path, default=SUITES, help="suite files (default: fast and clutter)")
    ap.add_argument("--only", help="run only scenarios whose name contains this text")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "suite_cache", help="recording cache folder")
    ap.add_argument("--set", action="append", metavar="FIELD=VALUE", help="a TrackerConfig field for every scenario")
    ap.add_argument("--out", type=Path, help="write poses.csv and overlay.png per scenario under this folder")
    args = ap.parse_args(argv)
    overrides = _overrides(args.set)
    headers = ["scenario", "init", "frames", "tracked %", "max err %D", ">=5%", ">=10%", "first", "distractor",
               "NEES in 95%", "ms med", "ms p99"]
    for path in args.suites:
        name, scenarios = load_suite(path)
        if args.only:
            scenarios = [s for s in scenarios if args.only in s["name"]]
        rows, total, times, all_nees = [], [], [], []
        for sc in scenarios:
            r = track_scenario(sc, args.cache, log=lambda m: print(m, file=sys.stderr), overrides=overrides)
            dist = read_distractors(r["rec_path"])
            f = score_published(r["outs"], r["T_true"], r["tracker"].model, dist)
            if args.out:
                write_outputs(args.out / name / sc["name"], r, dist)
            med, p99 = stats_ms(f["times_s"])
            ne = published_nees(r["outs"], r["T_true"], r["tracker"].model)
            all_nees += ne
            rows.append([sc["name"], sc["init"], f["frames"], 100.0 * f["published"] / f["frames"],
                         100.0 * f["max_err"], f["ge5"], f["ge10"], "-" if f["first"] is None else f["first"],
                         f["on_distractor"] if sc["distractors"] else "-", _in_band(ne), med, p99])
            total.append(f)
            times += f["times_s"]
        if not total:
            continue
        frames = sum(f["frames"] for f in total)
        med, p99 = stats_ms(times)
        errs = [f["max_err"] for f in total if np.isfinite(f["max_err"])]
        rows.append(["total", "", frames, 100.0 * sum(f["published"] for f in total) / frames,
                     100.0 * max(errs) if errs else float("nan"), sum(f["ge5"] for f in total), sum(f["ge10"] for f in total), "",
                     sum(f["on_distractor"] for f in total), _in_band(all_nees), med, p99])
        title = f"suite {name} ({path}){'; ' + ', '.join(args.set) if args.set else ''}"
        print_table(headers, rows, title=title)
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
