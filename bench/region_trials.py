"""The region term of the image likelihood, trial by trial: the hypothesis bank with one camera.

Each trial is one of ``bench/init.py --track 52 --stride 5 --rigs 1 --set decision=bank``:
an object and a trial seed (that bench's ``--seed`` plus the trial's index: seed 610 is
``--seed 600``'s trial 10), run twice in one process on the same frames, the bank's
likelihood with its edge lines alone and with the region term
(``LikelihoodOptions.region``, :mod:`vespro.likelihood`). Per trial and likelihood: the
first frame published ``tracking``, its ADD and the worst ADD published in the run (% of
the diameter). A trial succeeds when published within 26 frames under 10%; a wrong lock is
a frame published 10% or more off.

The default trials: the bank's three wrong locks and the twelve trials the confirmation
rules publish and the bank does not (of 240 one-camera trials, seeds 0, 600, 1200 and
1800), and fifteen both publish.

With ``--detail OBJ:SEED:FRAME`` it also prints, on that frame of that trial, the
log-likelihood of the true pose and of each hypothesis the bank holds, its edge and
region parts apart (the region likelihood on the bank's views of the frame).

Usage: ``python3 bench/region_trials.py [--trials box:7,lblock:18] [--track 52]
[--detail lblock:18:22]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench._table import print_table  # noqa: E402
from bench.init import Trial, parse_overrides, run_tracked, sym_add  # noqa: E402
from vespro.library import object_mesh_path  # noqa: E402
from vespro.likelihood import ImageLikelihood, LikelihoodOptions  # noqa: E402
from vespro.model import load_model  # noqa: E402
from vespro.sim.trials import model_symmetries  # noqa: E402

WRONG = "lblock:18,lblock:610,box:1806"
RULES_ONLY = ("box:7,lblock:12,lblock:14,bracket:14,box:603,box:613,lblock:603,box:1204,box:1215,bracket:1204,"
              "box:1801,lblock:1801")
AGREE = ("box:0,box:1,box:2,box:3,box:5,lblock:0,lblock:1,lblock:2,lblock:3,lblock:4,"
         "bracket:0,bracket:1,bracket:2,bracket:3,bracket:4")
FRAMES = 26  # the budget to publish in (1 s at 26 Hz)


def _detail(model, syms, frame, rows, label):
    """``on_frame``: on ``frame``, the true pose's and the held hypotheses' likelihood parts into ``rows``."""

    def hook(k, fs, tracker, T_true):
        if k != frame or tracker.bank is None:
            return
        base = tracker.bank.likelihood
        lk = ImageLikelihood(base.mf, base.tree, LikelihoodOptions(region=True))
        hyps = list(tracker.bank.hypotheses)
        p = tracker.bank.probabilities()
        poses = [("true pose", T_true, float("nan"))] + [(f"hypothesis {i}", h.ekf.pose, float(p[i]))
                                                        for i, h in enumerate(hyps)]
        views = tracker.bank_views(fs, [T_true])
        for name, T, prob in poses:
            pl = lk(T, views)
            region = sum(c.region_log_lik for c in pl.cameras)
            rows.append([label, name, 100 * sym_add(T, T_true, model, syms) / model.diameter, prob,
                         pl.log_lik - region, region, pl.log_lik,
                         sum(c.n_observed for c in pl.cameras), sum(c.n_outline for c in pl.cameras)])

    return hook


def _summary(o):
    """(first frame published, its ADD %D, worst published ADD %D, success, wrong lock)."""
    f = o["track_frame"]
    ok = f is not None and f < FRAMES and o["track_add"] < 0.1
    return (f, None if f is None else 100 * o["track_add"],
            None if o["max_track_add"] is None else 100 * o["max_track_add"], ok, o["wrong_frame"] is not None)


def _fmt(s):
    f, a, m, _, _ = s
    return "-" if f is None else f"{f:3d} {a:6.1f} {m:6.1f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", default=",".join((WRONG, RULES_ONLY, AGREE)), metavar="OBJ:SEED,...")
    ap.add_argument("--track", type=int, default=52, help="frames the tracker runs")
    ap.add_argument("--stride", type=int, default=5, help="the initialiser is called every N frames")
    ap.add_argument("--init-set", default="", metavar="K=V,...",
                    help="InitOptions fields to change in both runs (as bench/init.py's --init-set)")
    ap.add_argument("--detail", default="lblock:18:22", metavar="OBJ:SEED:FRAME",
                    help="print the likelihood parts of the true pose and the held hypotheses on this frame")
    a = ap.parse_args(argv)
    pairs = [(o, int(s)) for o, s in (item.split(":") for item in a.trials.split(",") if item)]
    groups = {p: g for g, text in (("wrong lock", WRONG), ("rules only", RULES_ONLY), ("both", AGREE))
              for p in ((o, int(s)) for o, s in (i.split(":") for i in text.split(",")))}
    d_obj, d_seed, d_frame = a.detail.split(":") if a.detail else (None, -1, -1)
    init_set = parse_overrides(a.init_set)
    models = {}
    rows, detail, totals = [], [], {"edges": [0, 0], "edges + region": [0, 0]}
    t0 = time.perf_counter()
    for obj, seed in pairs:
        if obj not in models:
            m = load_model(object_mesh_path(obj))
            models[obj] = (m, model_symmetries(m.vertices))
        model, syms = models[obj]
        trial = Trial(obj, model, syms, "1", seed, FRAMES, a.stride)
        res = []
        for label, lset in (("edges", None), ("edges + region", {"region": True})):
            hook = _detail(model, syms, int(d_frame), detail, label) if (obj, seed) == (d_obj, int(d_seed)) else None
            s = _summary(run_tracked(trial, a.track, {"decision": "bank"}, init_set=init_set, likelihood_set=lset,
                                     on_frame=hook))
            totals[label][0] += s[3]
            totals[label][1] += s[4]
            res.append(s)
        change = "=" if res[0][3:] == res[1][3:] else ("better" if (res[1][3] - res[1][4]) > (res[0][3] - res[0][4])
                                                         else "worse")
        rows.append([obj, seed, groups.get((obj, seed), ""), _fmt(res[0]), "wrong" if res[0][4] else "",
                     _fmt(res[1]), "wrong" if res[1][4] else "", change])
        print(f"done {obj} {seed} ({time.perf_counter() - t0:.0f} s)", flush=True)
    print_table(["object", "seed", "group", "edges: frame ADD max", "", "+ region: frame ADD max", "", "change"], rows,
                title=f"One camera, decision bank{(', ' + a.init_set) if a.init_set else ''}, tracker run {a.track} "
                      f"frames: first frame published, its ADD and "
                      f"the worst published (% of the diameter)")
    n = len(pairs)
    for label, (ok, wrong) in totals.items():
        print(f"{label}: published within {FRAMES} frames under 10% {ok}/{n}, wrong locks {wrong}")
    if detail:
        print_table(["likelihood run", "pose", "ADD %D", "bank prob", "edge log lik", "region log lik", "log lik",
                     "lines", "outline lines"], detail,
                    title=f"{d_obj} seed {d_seed} frame {d_frame}: log-likelihoods with the region term (raw, before "
                          f"evidence_weight), on the bank's hypotheses of each run")


if __name__ == "__main__":
    main()
