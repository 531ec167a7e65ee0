"""Render time per camera frame at 320x240, 640x480 and 1280x960.

For each resolution, one fixed camera of the cell (the bracket on the belt):

- ``mujoco``: the raw offscreen render (``Renderer.update_scene`` + ``render``), shadows off;
- ``pipeline``: what capture costs per camera: the raw render plus the imaging
  pipeline with 0.5 px pixel noise and sensor noise;
- ``pipeline+dist``: the same with plumb_bob lens distortion (a larger render, remapped);
- ``shadows on``: the raw render with MuJoCo's default 4096 shadow map, for reference.

Ratios are against the raw render at the same resolution (the baseline, run in
this process). Usage: ``python bench/render.py [--frames N]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import mujoco  # noqa: E402
from _table import print_table, stats_ms  # noqa: E402

from vespro.camera import CameraIntrinsics  # noqa: E402
from vespro.rig import Rig, RigCamera, load_rig  # noqa: E402
from vespro.sim.cell import CellConfig, SimCell  # noqa: E402
from vespro.sim.imaging import ImageEffects  # noqa: E402
from vespro.sim.motion import Conveyor  # noqa: E402
from vespro.sim.rigs import CAMERAS_DIR  # noqa: E402
from vespro.sim.scene import MODELS_DIR  # noqa: E402


def time_calls(fn, n):
    fn()  # warm-up
    out = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    base = load_rig(CAMERAS_DIR / "fixed1.yaml")["cam_left"]
    rows = []
    for w, h in [(320, 240), (640, 480), (1280, 960)]:
        intr = base.intrinsics.scaled(w / base.intrinsics.width)
        dist = CameraIntrinsics(w, h, intr.K, (-0.22, 0.09, 0.0006, -0.0004, -0.015))
        results = {}
        for label, cam_intr, effects in [
            ("mujoco", intr, None),
            ("pipeline", intr, ImageEffects(noise_px=0.5, intensity_noise=2.0)),
            ("pipeline+dist", dist, ImageEffects(noise_px=0.5, intensity_noise=2.0)),
        ]:
            rig = Rig((RigCamera("cam", cam_intr, "fixed", T_world_camera=base.T_world_camera),))
            cell = SimCell(CellConfig(MODELS_DIR / "objects" / "bracket.stl", rig, effects=effects or ImageEffects()),
                           Conveyor(y0=-0.05))
            rintr, mj_name = cell._render_info["cam"]
            r = cell._renderers[(rintr.height, rintr.width)]
            if effects is None:
                def raw():
                    r.update_scene(cell.data, camera=mj_name)
                    return r.render()
                results[label] = time_calls(raw, args.frames)
                r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = True
                cell.model.vis.quality.shadowsize = 4096
                cell.model.light_castshadow[:] = 1
                r2 = mujoco.Renderer(cell.model, rintr.height, rintr.width)

                def shadowed():
                    r2.update_scene(cell.data, camera=mj_name)
                    return r2.render()
                results["shadows on"] = time_calls(shadowed, max(10, args.frames // 4))
                r2.close()
            else:
                results[label] = time_calls(cell.capture, args.frames)
            cell.close()
        base_med = stats_ms(results["mujoco"])[0]
        for label, samples in results.items():
            med, p99 = stats_ms(samples)
            rows.append([f"{w}x{h}", label, med, p99, med / base_med])
    print_table(["resolution", "path", "median ms", "p99 ms", "x raw"], rows,
                title=f"Render time per camera frame ({args.frames} frames each; capture includes scene update)")


if __name__ == "__main__":
    main()
