import dataclasses
import signal
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vespro.library import ModelLibrary
from vespro.model import ModelError, box_model, load_model, model_from_arrays

OBJECTS = Path(__file__).resolve().parents[2] / "models" / "objects"


@contextmanager
def deadline(seconds=20):
    """Fail instead of hanging (SIGALRM; loaders are Python code, so it fires)."""

    def boom(*_):
        raise TimeoutError(f"took more than {seconds} s")

    old = signal.signal(signal.SIGALRM, boom)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@pytest.fixture(scope="module")
def models():
    return {n: load_model(OBJECTS / f"{n}.stl") for n in ("box", "lblock", "bracket")}


def box_arrays():
    m = trimesh.creation.box(extents=[0.12, 0.08, 0.06])
    return np.array(m.vertices), np.array(m.faces)


# --- the committed models, against facts worked by hand -------------------------------


def test_box_features_by_hand(models):
    m = models["box"]
    assert len(m.triangles) == 12 and len(m.faces) == 6
    # 8 corners: (+-0.06, +-0.04, {0, 0.06}), each with 3 mutually orthogonal faces.
    want = np.array([(sx * 0.06, sy * 0.04, z) for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, 0.06)])
    # The STL stores float32: 1e-7 m covers its rounding.
    dist = np.linalg.norm(m.corners[:, None] - want[None], axis=2)
    assert m.n_corners == 8 and np.all(dist.min(1) < 1e-7) and np.all(dist.min(0) < 1e-7)
    for i in range(m.n_corners):
        n = m.face_normals[m.corner_faces(i)]
        assert n.shape == (3, 3)
        np.testing.assert_allclose(np.abs(n @ n.T), np.eye(3), atol=1e-7)
    assert len(m.edge_vertices) == 12 and m.edge_convex.all()
    assert m.corner_convex.all() and not m.corner_concave.any()
    assert abs(m.volume - 0.12 * 0.08 * 0.06) < 1e-9
    assert abs(m.diameter - np.sqrt(0.12**2 + 0.08**2 + 0.06**2)) < 1e-7
    # Normals point out: the +z face has offset 0.06 (plane z = 0.06).
    top = int(np.argmax(m.face_normals[:, 2]))
    np.testing.assert_allclose(m.face_normals[top], [0, 0, 1], atol=1e-7)
    assert abs(m.face_offsets[top] - 0.06) < 1e-8


def test_lblock_has_one_concave_edge_along_the_inner_corner(models):
    m = models["lblock"]
    # An L prism: 8 planar faces, 6 profile vertices x 2 = 12 corners, 18 edges.
    assert len(m.faces) == 8 and m.n_corners == 12 and len(m.edge_vertices) == 18
    concave = np.flatnonzero(~m.edge_convex)
    assert len(concave) == 1
    a, b = m.edge_points[concave[0]]
    # Inner edge: x = -0.015 (riser face), z = 0.035 (foot top), along y.
    np.testing.assert_allclose([a[0], a[2], b[0], b[2]], [-0.015, 0.035, -0.015, 0.035], atol=1e-7)
    assert abs(abs(a[1] - b[1]) - 0.08) < 1e-7
    # Its two end corners are neither all-convex nor all-concave (saddle).
    ends = [int(np.flatnonzero(np.all(np.abs(m.corners - p) < 1e-9, axis=1))[0]) for p in (a, b)]
    assert not m.corner_convex[ends].any() and not m.corner_concave[ends].any()
    assert m.corner_convex.sum() == 10


def test_bracket_faces_with_holes(models):
    m = models["bracket"]
    with_holes = [f for f in m.faces if len(f.loops) > 1]
    assert len(with_holes) >= 2  # base plate top and bottom, pierced by the two holes
    for f in with_holes:
        assert all(len(lp) >= 3 for lp in f.loops)


@pytest.mark.parametrize("name", ["box", "lblock", "bracket"])
def test_features_are_consistent(models, name):
    m = models[name]
    V = m.vertices
    # Each corner lies on the planes of its faces, which are >= 3 distinct planes.
    for i in range(m.n_corners):
        fs = m.corner_faces(i)
        np.testing.assert_allclose(m.face_normals[fs] @ m.corners[i], m.face_offsets[fs], atol=1e-7)
        assert len(np.unique(m.face_plane[fs])) >= 3
    # Edge ends lie on both face planes; the faces have different normals.
    for (a, b), (fa, fb) in zip(m.edge_vertices, m.edge_faces):
        for f in (fa, fb):
            np.testing.assert_allclose(m.face_normals[f] @ V[[a, b]].T, m.face_offsets[f], atol=1e-7)
        assert m.face_normals[fa] @ m.face_normals[fb] < 1 - 1e-6
    # Planar faces partition the triangles; areas add up to the mesh area.
    T = V[m.triangles]
    tri_area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1)
    assert sorted(np.concatenate([f.triangles for f in m.faces]).tolist()) == list(range(len(m.triangles)))
    np.testing.assert_allclose(m.face_areas.sum(), tri_area.sum(), rtol=1e-12)
    # Loops (shoelace, independent of the triangles): outer minus holes = face area.
    for f in m.faces:
        areas = []
        for lp in f.loops:
            P = V[lp]
            areas.append(0.5 * f.normal @ np.cross(P, np.roll(P, -1, axis=0)).sum(0))
        assert areas[0] > 0 and all(a < 0 for a in areas[1:])
        np.testing.assert_allclose(sum(areas), f.area, rtol=1e-6, atol=1e-12)
    # Plane identity: face planes are exactly sign * plane.
    np.testing.assert_array_equal(m.face_normals, m.face_plane_sign[:, None] * m.plane_normals[m.face_plane])


def test_model_is_frozen_and_read_only(models):
    m = models["box"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.name = "x"
    for arr in (m.vertices, m.triangles, m.corners, m.corner_face_table, m.edge_normals, m.faces[0].normal):
        with pytest.raises(ValueError):
            arr[0] = 0


def test_content_hash_tracks_geometry():
    V, F = box_arrays()
    h1 = model_from_arrays(V, F).content_hash
    assert model_from_arrays(V.copy(), F.copy()).content_hash == h1
    V2 = V.copy()
    V2[0, 0] += 1e-9
    assert model_from_arrays(V2, F).content_hash != h1


# --- units and file formats ------------------------------------------------------------


def test_millimetre_file_is_caught_and_scaled(tmp_path):
    V, F = box_arrays()
    path = tmp_path / "box_mm.stl"
    trimesh.Trimesh(V * 1000.0, F).export(path)
    with pytest.raises(ModelError, match=r'unit="mm"') as e:
        load_model(path)
    assert "box_mm.stl" in str(e.value)
    m = load_model(path, unit="mm")
    ref = box_model([0.12, 0.08, 0.06])
    # float32 STL of 120 mm etc. is exact up to float32 rounding then * 1e-3.
    np.testing.assert_allclose(np.sort(m.corners, axis=0), np.sort(ref.corners, axis=0), atol=1e-9)
    assert m.unit == "mm"


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl"])
def test_formats_load_the_same_model(tmp_path, suffix):
    V, F = box_arrays()
    path = tmp_path / f"b{suffix}"
    trimesh.Trimesh(V, F).export(path)
    m = load_model(path)
    assert len(m.faces) == 6 and m.n_corners == 8 and abs(m.volume - 0.12 * 0.08 * 0.06) < 1e-9


def test_unknown_unit_is_rejected():
    with pytest.raises(ValueError, match="unknown unit"):
        load_model(OBJECTS / "box.stl", unit="furlong")


# --- malformed meshes: clear errors, no hang --------------------------------------------


def _write(tmp_path, name, V, F):
    path = tmp_path / name
    trimesh.Trimesh(V, F, process=False).export(path)
    return path


def test_hole_is_rejected(tmp_path):
    V, F = box_arrays()
    with deadline():
        with pytest.raises(ModelError, match="not watertight") as e:
            load_model(_write(tmp_path, "holey.ply", V, F[1:]))
    assert "holey.ply" in str(e.value)


def test_one_flipped_face_is_rejected():
    V, F = box_arrays()
    F = F.copy()
    F[3] = F[3, ::-1]
    with pytest.raises(ModelError, match="inconsistent winding"):
        model_from_arrays(V, F, name="flip1")


def test_inside_out_mesh_is_rejected():
    V, F = box_arrays()
    with pytest.raises(ModelError, match="inward"):
        model_from_arrays(V, F[:, ::-1], name="inside_out")


def test_degenerate_triangle_is_rejected():
    # Closed and consistently wound, but one triangle has zero area: split edge
    # (a, b) at its midpoint m on one side and close the crack with (m, a, b).
    V, F = box_arrays()
    a, b, c = F[0]
    V = np.vstack([V, 0.5 * (V[a] + V[b])])
    m = len(V) - 1
    F2 = [f for j, f in enumerate(F.tolist()) if j != 0]
    F2 += [[a, m, c], [m, b, c], [m, a, b]]
    with pytest.raises(ModelError, match="degenerate"):
        model_from_arrays(V, np.array(F2), name="sliver")
    # The same mesh without the zero-area triangle has a hole: caught too.
    with pytest.raises(ModelError):
        model_from_arrays(V, np.array(F2[:-1]), name="sliver")


def test_non_manifold_edge_is_rejected():
    # The same box twice over the same vertices: every edge is used four times.
    V, F = box_arrays()
    with pytest.raises(ModelError, match="manifold"):
        model_from_arrays(V, np.vstack([F, F]), name="twice")


@pytest.mark.parametrize(
    "name, data",
    [
        ("empty.stl", b""),
        ("garbage.stl", bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8))),
        ("garbage.ply", b"ply\nformat ascii 1.0\nelement vertex 999999999\n" + b"\x00\xff" * 100),
        ("garbage.obj", b"v 1 2\nf 1 2 3 4 5\nhello\n"),
        ("text.stl", b"solid nothing\nendsolid nothing\n"),
        ("huge_count.stl", b"\x00" * 80 + (2**31 - 1).to_bytes(4, "little") + b"\x00" * 50),
    ],
)
def test_bad_files_raise_model_error_naming_the_file(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    with deadline():
        with pytest.raises(ModelError) as e:
            load_model(path)
    assert name in str(e.value)


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(ModelError, match="no such file"):
        load_model(tmp_path / "nope.stl")
    (tmp_path / "x.step").write_text("ISO-10303-21;")
    with pytest.raises(ModelError, match="unsupported"):
        load_model(tmp_path / "x.step")


def test_non_finite_and_bad_shapes():
    V, F = box_arrays()
    V = V.copy()
    V[0, 0] = np.nan
    with pytest.raises(ModelError, match="non-finite"):
        model_from_arrays(V, F)
    with pytest.raises(ModelError, match="shape"):
        model_from_arrays(np.zeros((4, 2)), F)
    with pytest.raises(ModelError, match="indices"):
        model_from_arrays(box_arrays()[0], F + 100)


# --- library ---------------------------------------------------------------------------


def test_library_indexes_and_caches(tmp_path):
    lib = ModelLibrary(OBJECTS, cache_dir=tmp_path)
    assert lib.names == ("box", "bracket", "lblock")
    m = lib.load("lblock")
    assert lib.load("lblock") is m and m.name == "lblock"
    assert lib.tree("box").content_hash == lib.load("box").content_hash
    with pytest.raises(KeyError, match="have"):
        lib.load("nonexistent")
    assert "box" in lib and "nope" not in lib


def test_library_rejects_duplicate_stems(tmp_path):
    V, F = box_arrays()
    trimesh.Trimesh(V, F).export(tmp_path / "a.stl")
    trimesh.Trimesh(V, F).export(tmp_path / "a.obj")
    with pytest.raises(ValueError, match="two model files"):
        ModelLibrary(tmp_path)
    with pytest.raises(FileNotFoundError):
        ModelLibrary(tmp_path / "missing")
