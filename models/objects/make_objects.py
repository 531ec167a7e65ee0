"""Generate the CAD models of the tracked objects (STL, metres, object frame).

Run once; the STL files are committed. Needs manifold3d for the booleans
(a generator-only dependency: ``pip install manifold3d``).

Object frame: origin at the centre of the bounding box's bottom face, z up, so a
part resting on a surface at height h has its origin at z = h.

- box: 0.12 x 0.08 x 0.06 m, 12 triangles.
- lblock: a non-convex L-shaped block (two boxes), 0.12 x 0.08 x 0.08 m.
- bracket: an angle bracket with a gusset, two octagonal holes, a slot and
  chamfered edges, a few hundred triangles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent


def _box(extents, center):
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(center))


def _union(*meshes):
    return trimesh.boolean.union(list(meshes), engine="manifold")


def _diff(a, *bs):
    return trimesh.boolean.difference([a, *bs], engine="manifold")


def make_box() -> trimesh.Trimesh:
    return _box([0.12, 0.08, 0.06], [0, 0, 0.03])


def make_lblock() -> trimesh.Trimesh:
    foot = _box([0.12, 0.08, 0.035], [0, 0, 0.0175])
    riser = _box([0.045, 0.08, 0.08], [-0.0375, 0, 0.04])
    return _union(foot, riser)


def _prism_hole(radius, height, sections, center, axis="z"):
    c = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    if axis == "x":
        c.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    elif axis == "y":
        c.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    c.apply_translation(center)
    return c


def make_bracket() -> trimesh.Trimesh:
    t = 0.016  # plate thickness
    base = _box([0.14, 0.10, t], [0, 0, t / 2])
    upright = _box([t, 0.10, 0.10], [-0.07 + t / 2, 0, 0.05])
    # Triangular gusset between the plates, centred in y.
    g = 0.012
    prof = np.array([[-0.07 + t, t], [0.02, t], [-0.07 + t, 0.09]])
    verts = []
    for y in (-g / 2, g / 2):
        verts += [[x, y, z] for x, z in prof]
    faces = [[0, 1, 2], [3, 5, 4], [0, 3, 4], [0, 4, 1], [1, 4, 5], [1, 5, 2], [2, 5, 3], [2, 3, 0]]
    gusset = trimesh.Trimesh(verts, faces, process=True)
    gusset.fix_normals()
    body = _union(base, upright, gusset)
    holes = [
        _prism_hole(0.011, 0.05, 12, [0.035, 0.03, t / 2]),
        _prism_hole(0.011, 0.05, 12, [0.035, -0.03, t / 2]),
    ]
    slot = _box([0.05, 0.03, 0.024], [-0.07 + t / 2, 0.0, 0.07])
    body = _diff(body, *holes, slot)
    # Chamfer the two outer corners of the base plate's free end.
    for sy in (-1, 1):
        cut = _box([0.03, 0.03, 0.05], [0.07, sy * 0.05, t / 2])
        cut.apply_transform(
            trimesh.transformations.rotation_matrix(np.pi / 4, [0, 0, 1], point=[0.07, sy * 0.05, 0])
        )
        body = _diff(body, cut)
    # Step on the upright's top edge.
    step = _box([0.03, 0.03, 0.02], [-0.07, 0.035, 0.10])
    body = _diff(body, step)
    return body


def main() -> None:
    for name, fn in [("box", make_box), ("lblock", make_lblock), ("bracket", make_bracket)]:
        m = fn()
        m.merge_vertices()
        assert m.is_watertight and m.is_winding_consistent and m.volume > 0, name
        m.export(HERE / f"{name}.stl")
        print(f"{name}: {len(m.faces)} triangles, extents {np.round(m.extents, 4)}, volume {m.volume:.3e} m^3")


if __name__ == "__main__":
    main()
