"""Compile the per-frame kernels once, at set-up: ``python3 -m vespro.warmup``.

The kernels (:mod:`vespro.jit`) are compiled by numba on their first call after an
install and kept in its on-disk cache; later processes load them in well under a
second. Compiling them all takes 20-60 s, which a first ``vespro demo``, ``track``
or ``serve`` would otherwise spend before its first frame. Set-up (``.ci/setup.sh``)
runs this module, so that every run starts as fast as later ones.

It runs what those commands run, on a few simulated frame sets of the cell (its
renderer, colour and grey images): the automatic initialiser, the tracker with either
feature selection and with one camera and two, and the visibility structure (BSP) of
each of the cell's parts, built and written to its cache. Then it checks that every
kernel called from Python was compiled (or loaded), and names any that was not.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

__all__ = ["kernel_modules", "uncompiled_kernels", "warm_up", "main"]

CELL_PARTS = ("bracket", "box", "lblock")  # the parts `vespro demo` and the suites use
FRAMES = 3  # frame sets per run: the initialiser's start, then tracked frames


def kernel_modules() -> list[str]:
    """Names of the package's modules that define compiled kernels."""
    root = Path(__file__).resolve().parent
    names = []
    for p in sorted(root.rglob("*.py")):
        if re.search(r"^from (\.+|vespro\.)jit import njit", p.read_text(encoding="utf-8"), re.M):
            names.append(".".join(("vespro", *p.relative_to(root).with_suffix("").parts)))
    return names


def uncompiled_kernels() -> list[str]:
    """The kernels (``module.function``) called from Python that have not been compiled
    (or loaded from the cache) in this process. A kernel called only by other kernels
    is compiled into them (and, loaded from the cache, not listed as compiled itself)."""
    from .jit import KERNELS

    for name in kernel_modules():
        importlib.import_module(name)
    src = {id(k): inspect.getsource(k.py_func) for k in KERNELS}
    inner = {k.py_func.__name__ for k in KERNELS
             if any(re.search(rf"\b{k.py_func.__name__}\(", s) for i, s in src.items() if i != id(k))}
    return sorted(f"{k.py_func.__module__}.{k.py_func.__name__}" for k in KERNELS
                  if not k.signatures and k.py_func.__name__ not in inner)


def _frame_sets(part: str, rig_name: str, n: int, mono: bool):
    from .library import object_mesh_path
    from .rig import load_rig
    from .sim.cell import CellConfig, SimCell
    from .sim.imaging import ImageEffects
    from .sim.motion import Conveyor
    from .sim.rigs import CAMERAS_DIR

    rig = load_rig(CAMERAS_DIR / f"{rig_name}.yaml")
    cfg = CellConfig(object_mesh_path(part), rig, effects=ImageEffects(noise_px=0.5), mono=mono)
    with SimCell(cfg, Conveyor(speed=0.05, y0=-0.1)) as cell:
        cell.settle_arm()
        return rig, object_mesh_path(part), [cell.next_frameset() for _ in range(n)]


def _track(rig, model, frame_sets, selection: str, decision: str = "rules") -> int:
    from .init import decision_options, make_initializer
    from .tracker import Tracker, TrackerConfig

    tracker = Tracker(rig, model, TrackerConfig(selection=selection, decision=decision),
                      initializer=make_initializer(rig, model, **decision_options(decision)))
    n = sum(tracker.process(fs).status == "tracking" for fs in frame_sets)
    if tracker.bank is not None:  # the likelihood's optional region term (LikelihoodOptions.region)
        import numpy as np

        from .likelihood import ImageLikelihood, LikelihoodOptions

        cam = rig.cameras[0]
        lk = tracker.bank.likelihood
        region = ImageLikelihood(lk.mf, lk.tree, LikelihoodOptions(region=True))
        T = np.array(cam.T_world_camera, float)
        T[:3, 3] += 0.6 * T[:3, 2]  # the part 0.6 m along the camera's axis: its outline in view
        region(T, [(cam.T_world_camera, region.edge_image(frame_sets[-1].grey(cam.name), cam.intrinsics.K))])
    return n


def warm_up(log=print) -> list[str]:
    """Compile every kernel (and cache the cell's BSP trees); returns the kernels left
    uncompiled (none, unless a kernel is reached only by a path not run here)."""
    from .bsp import load_or_build_bsp
    from .library import object_mesh_path
    from .model import load_model
    from .visibility import SceneBody

    t0 = time.monotonic()
    for part in CELL_PARTS:
        model = load_model(object_mesh_path(part), name=part)
        body = SceneBody(part, model, load_or_build_bsp(model))
        body.visible_mask(model.bounds[1] + model.diameter)  # one body's corners alone (a viewpoint off a corner)
    log(f"  visibility structures of {', '.join(CELL_PARTS)} ready ({time.monotonic() - t0:.0f} s)")
    runs = []
    # The demo's cell (the bracket, not convex; two fixed cameras and one on the arm, grey
    # images), and a convex part on colour images with the other feature selection; each
    # also with one camera alone (the one-camera rules of the initialiser and tracker).
    for part, rig_name, mono, sel in (("bracket", "hybrid", True, "quality"), ("box", "fixed2", False, "information")):
        try:
            rig, mesh, sets = _frame_sets(part, rig_name, FRAMES, mono)
        except Exception as e:  # no offscreen rendering here: the rest compiles on first use
            log(f"  the simulated cell does not render here ({type(e).__name__}: {e}); skipped")
            break
        model = load_model(mesh, name=part)
        images = "grey" if mono else "colour"
        one = replace(rig, cameras=rig.cameras[:1])
        runs += [(f"{part}, cameras {', '.join(rig.names)}, {images}, {sel} selection", rig, model, sets, sel, "rules"),
                 (f"{part}, camera {rig.names[0]} alone", one, model, sets, sel, "rules")]
        if not mono:  # the hypothesis bank and its image likelihood (--decision bank)
            runs.append((f"{part}, camera {rig.names[0]} alone, decided by the bank", one, model, sets, sel, "bank"))
    for what, rig, model, frame_sets, sel, decision in runs:
        t = time.monotonic()
        n = _track(rig, model, frame_sets, sel, decision)
        log(f"  {what}: {n}/{len(frame_sets)} frames tracking ({time.monotonic() - t:.0f} s)")
    return uncompiled_kernels()


def main(argv=None) -> int:
    from .jit import compiled_count

    argparse.ArgumentParser(prog="python3 -m vespro.warmup", description=__doc__.split("\n\n")[0]).parse_args(argv)
    t0 = time.monotonic()
    print("vespro: compiling the tracker's kernels once (20-60 s; cached for every later run)", flush=True)
    left = warm_up(log=lambda m: print(m, flush=True))
    if left:
        print(f"vespro: not compiled here (they will compile on first use): {', '.join(left)}", file=sys.stderr,
              flush=True)
    compiled, loaded = compiled_count()
    print(f"vespro: kernels ready: {compiled} compiled, {loaded} loaded from the cache ({time.monotonic() - t0:.0f} s)",
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
