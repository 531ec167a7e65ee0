"""Benchmark: BSP build and corner-visibility query time against brute force.

    python3 bench/visibility.py [--views 300] [--sizes 12,100,1000,10000]

Models: unions of randomly placed and rotated boxes (real corners, large and
small coplanar faces, self-occlusion), sized to about the requested number of
triangles; the 12-triangle model is a plain box. Needs manifold3d for the
booleans: the benches' extra ``vespro[bench]``, which set-up (.ci/setup.sh) installs
(as for models/objects/make_objects.py).

For each model: BSP build time, the set-up of the corner/plane distance table
(``SceneBody``), and the time of one full visibility query (all corners, one
viewpoint: facing test plus BSP occlusion, ``SceneBody.visible_mask``) over
random viewpoints 0.2-2 m from the model, median and p99 and per corner,
beside brute-force ray casting (Moller-Trumbore against every triangle, numpy,
in the same process) of the same query, and the agreement between the two
(the rare disagreements are grazing views; see tests/vespro/test_visibility.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "vespro"))

from vespro.bsp import build_bsp  # noqa: E402
from vespro.model import box_model, model_from_arrays  # noqa: E402
from vespro.visibility import DEFAULT_END_EPS, DEFAULT_FACING_EPS, SceneBody  # noqa: E402
from vis_bruteforce import brute_visible, segment_edge_clearance  # noqa: E402


def boxes_union(n_boxes: int, seed: int):
    """Union of n random boxes in a 0.2 m cube (vertices, triangles)."""
    import trimesh
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    meshes = []
    scale = 3.0 / max(1, n_boxes) ** (1 / 3)
    for _ in range(n_boxes):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.5).as_matrix()
        T[:3, 3] = rng.uniform(-0.1, 0.1, 3)
        meshes.append(trimesh.creation.box(extents=rng.uniform(0.02, 0.08, 3) * scale, transform=T))
    u = trimesh.boolean.union(meshes, engine="manifold")
    return np.asarray(u.vertices), np.asarray(u.faces)


def model_of_size(n_tri: int):
    if n_tri <= 12:
        return box_model([0.12, 0.08, 0.06])
    # About 12-14 triangles per box survive the union: search the box count.
    n = max(2, n_tri // 13)
    for _ in range(8):
        V, F = boxes_union(n, seed=n)
        if abs(len(F) - n_tri) < 0.15 * n_tri:
            break
        n = max(2, int(round(n * n_tri / len(F))))
    return model_from_arrays(V, F, name=f"boxes{n}")


def viewpoints(model, n, rng):
    ctr = 0.5 * (model.bounds[0] + model.bounds[1])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return ctr + d * rng.uniform(0.2, 2.0, size=(n, 1))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=300)
    ap.add_argument("--brute-views", type=int, default=30, help="views for brute force (slow on big models)")
    ap.add_argument("--sizes", default="12,100,1000,10000")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    rows = []
    for size in [int(s) for s in args.sizes.split(",")]:
        model = model_of_size(size)
        t = time.perf_counter()
        tree = build_bsp(model)
        build_s = time.perf_counter() - t
        t = time.perf_counter()
        body = SceneBody(model.name, model, tree)  # + corner/plane distance table
        setup_s = time.perf_counter() - t
        views = viewpoints(model, args.views, rng)
        body.visible_mask(views[0])  # warm up
        q = []
        for c in views:
            t = time.perf_counter()
            body.visible_mask(c)
            q.append(time.perf_counter() - t)
        bq, agree, total, n_dis, n_graze = [], 0, 0, 0, 0
        for c in views[: args.brute_views]:
            t = time.perf_counter()
            ref = brute_visible(model, c, DEFAULT_FACING_EPS, DEFAULT_END_EPS)
            bq.append(time.perf_counter() - t)
            got = body.visible_mask(c)
            agree += int((ref == got).sum())
            total += ref.size
            for i in np.flatnonzero(ref != got):
                # Grazing as in the tests: within 0.06 deg of a face plane at
                # the corner, or within 1 um of another sharp edge.
                p = model.corners[i]
                los = (c - p) / np.linalg.norm(c - p)
                cos = np.abs(model.face_normals[model.corner_faces(i)] @ los).min()
                clear = segment_edge_clearance(c, p, model.edge_points, exclude_point=p)
                n_dis += 1
                n_graze += int(cos < 1e-3 or clear < 1e-6)
        q, bq = np.array(q) * 1e3, np.array(bq) * 1e3
        rows.append(
            (
                len(model.triangles),
                len(model.faces),
                model.n_corners,
                tree.n_nodes,
                tree.depth,
                build_s * 1e3,
                np.median(q),
                np.percentile(q, 99),
                np.median(bq),
                np.median(bq) / np.median(q),
                agree / max(total, 1),
                setup_s * 1e3,
                np.median(q) * 1e3 / model.n_corners,
                f"{n_dis} ({n_graze} grazing)",
            )
        )
        print(f"  done {rows[-1][0]} triangles", file=sys.stderr, flush=True)
    hdr = (
        "| triangles | planar faces | corners | BSP nodes | depth | build ms | table ms "
        "| query median ms | query p99 ms | us per corner | brute median ms | brute/BSP | agreement | disagreements |"
    )
    print(hdr)
    print("|" + "---|" * 14)
    for r in rows:
        print(
            f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]} | {r[5]:.1f} | {r[11]:.1f} | {r[6]:.3f} | {r[7]:.3f} "
            f"| {r[12]:.2f} | {r[8]:.2f} | {r[9]:.1f}x | {100 * r[10]:.3f}% | {r[13]} |"
        )


if __name__ == "__main__":
    main()
