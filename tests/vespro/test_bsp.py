from pathlib import Path

import numpy as np
import pytest
from vis_bruteforce import segments_hit_triangles, winding_number

from vespro import bsp
from vespro.bsp import IN, OUT, build_bsp, load_bsp, load_or_build_bsp
from vespro.model import box_model, load_model, model_from_arrays

OBJECTS = Path(__file__).resolve().parents[2] / "models" / "objects"
NAMES = ("box", "lblock", "bracket")


@pytest.fixture(scope="module")
def bodies():
    out = {n: load_model(OBJECTS / f"{n}.stl") for n in NAMES}
    # Two disjoint boxes, one rotated: a multi-component solid.
    a, b = box_model([0.05, 0.05, 0.05]), box_model([0.04, 0.02, 0.06], center=[0.1, 0.0, 0.0])
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    Vb = b.vertices @ R.T
    out["two_boxes"] = model_from_arrays(
        np.vstack([a.vertices, Vb]), np.vstack([a.triangles, b.triangles + len(a.vertices)])
    )
    # A hollow box: an inward-facing inner shell bounds a closed cavity.
    outer, inner = box_model([0.1, 0.08, 0.06]), box_model([0.06, 0.04, 0.03], center=[0.005, 0.0, 0.004])
    out["hollow"] = model_from_arrays(
        np.vstack([outer.vertices, inner.vertices]),
        np.vstack([outer.triangles, inner.triangles[:, ::-1] + len(outer.vertices)]),
    )
    return {n: (m, build_bsp(m)) for n, m in out.items()}


@pytest.mark.parametrize("name", list(NAMES) + ["two_boxes", "hollow"])
def test_inside_test_matches_winding_number(bodies, name):
    m, tree = bodies[name]
    rng = np.random.default_rng(0)
    lo, hi = m.bounds
    P = rng.uniform(lo - 0.01, hi + 0.01, size=(3000, 3))
    inside_ref = winding_number(m.vertices, m.triangles, P) > 0.5
    assert 0.05 < inside_ref.mean() < 0.95  # both outcomes are exercised
    np.testing.assert_array_equal(tree.contains(P), inside_ref)


@pytest.mark.parametrize("name", list(NAMES) + ["two_boxes", "hollow"])
def test_segments_match_brute_force(bodies, name):
    """Random segments with both ends outside: blocked iff they cross a triangle."""
    m, tree = bodies[name]
    rng = np.random.default_rng(1)
    lo, hi = m.bounds
    A = rng.uniform(lo - 0.02, hi + 0.02, size=(4000, 3))
    B = rng.uniform(lo - 0.02, hi + 0.02, size=(4000, 3))
    out = (winding_number(m.vertices, m.triangles, A) < 0.5) & (winding_number(m.vertices, m.triangles, B) < 0.5)
    A, B = A[out][:1500], B[out][:1500]
    ref = segments_hit_triangles(A, B, m.vertices[m.triangles], np.zeros(len(A)), np.ones(len(A)))
    got = tree.segments_blocked(A, B)
    assert 0.1 < ref.mean() < 0.9
    np.testing.assert_array_equal(got, ref)
    # The common-start and pre-measured paths give the same answers.
    c = A[0]
    np.testing.assert_array_equal(tree.segments_blocked(c, B), tree.segments_blocked(np.broadcast_to(c, B.shape), B))
    rows = np.arange(len(B))[::-1]
    np.testing.assert_array_equal(
        tree.segments_blocked_from(c, B[rows], tree.plane_distances(B), rows), tree.segments_blocked(c, B[rows])
    )


@pytest.mark.parametrize("name", NAMES)
def test_tree_structure(bodies, name):
    m, tree = bodies[name]
    n = tree.n_nodes
    idx = np.arange(n)
    # Pre-order: children after parents (no cycles); leaves are IN / OUT codes.
    for ch in (tree.front, tree.back):
        assert np.all((ch == IN) | (ch == OUT) | (ch > idx))
    # Every node plane is one of the model's face planes, oriented as that face.
    np.testing.assert_allclose(tree.normal, m.face_normals[tree.face], atol=1e-12)
    np.testing.assert_allclose(tree.offset, m.face_offsets[tree.face], atol=1e-12)
    # Fragments lie in their node's plane, and splitting conserves area.
    node_of_poly = np.repeat(idx, np.diff(tree.poly_ptr))
    h = np.einsum("pvj,pj->pv", tree.poly_vertices, tree.normal[node_of_poly]) - tree.offset[node_of_poly][:, None]
    assert np.abs(h).max() < 1e-9
    e1 = tree.poly_vertices[:, 1] - tree.poly_vertices[:, 0]
    e2 = tree.poly_vertices[:, 2] - tree.poly_vertices[:, 0]
    # rtol: the build snaps float32 CAD vertices onto exact planes (moves ~1e-8 m).
    np.testing.assert_allclose(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum(), m.face_areas.sum(), rtol=1e-7)


def test_heuristic_keeps_tree_small(bodies):
    # Numbers from the committed models with margin. Taking always the largest
    # face (no split/balance scoring) makes the bracket's tree much deeper.
    m, tree = bodies["bracket"]
    assert tree.depth <= 20
    assert tree.n_polygons <= 1.2 * len(m.triangles)
    naive = build_bsp(m, max_candidates=1)
    assert tree.depth < naive.depth
    assert bodies["box"][1].n_nodes == 6  # one node per face of a convex solid, no splits


def test_tree_is_read_only(bodies):
    tree = bodies["box"][1]
    with pytest.raises(ValueError):
        tree.normal[0, 0] = 1.0


def test_cache_round_trip_and_corrupt_file(bodies, tmp_path, monkeypatch):
    m, _ = bodies["bracket"]
    t1 = load_or_build_bsp(m, cache_dir=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and m.content_hash in files[0].name

    # Second call must load, not build.
    def no_build(*a, **k):
        raise AssertionError("rebuilt although a valid cache file exists")

    monkeypatch.setattr(bsp, "build_bsp", no_build)
    t2 = load_or_build_bsp(m, cache_dir=tmp_path)
    monkeypatch.undo()
    for k, v in t1.arrays().items():
        np.testing.assert_array_equal(getattr(t2, k), v)
    assert (t2.depth, t2.plane_eps, t2.content_hash) == (t1.depth, t1.plane_eps, t1.content_hash)
    rng = np.random.default_rng(3)
    A, B = rng.uniform(-0.2, 0.2, (500, 3)), rng.uniform(-0.2, 0.2, (500, 3))
    np.testing.assert_array_equal(t1.segments_blocked(A, B), t2.segments_blocked(A, B))

    # Corrupt files of several kinds are rebuilt and rewritten.
    good = files[0].read_bytes()
    for bad in (b"", b"garbage" * 100, good[: len(good) // 2]):
        files[0].write_bytes(bad)
        with pytest.raises(ValueError):
            load_bsp(files[0], m.content_hash)
        t3 = load_or_build_bsp(m, cache_dir=tmp_path)
        np.testing.assert_array_equal(t3.segments_blocked(A, B), t1.segments_blocked(A, B))
        load_bsp(files[0], m.content_hash)  # valid again

    # A file of another model under this model's name (hash mismatch).
    other = bodies["box"][0]
    bsp.save_bsp(build_bsp(other), files[0])
    with pytest.raises(ValueError, match="another model"):
        load_bsp(files[0], m.content_hash)
    t4 = load_or_build_bsp(m, cache_dir=tmp_path)
    assert t4.n_nodes == t1.n_nodes


def test_inconsistent_cached_arrays_are_rejected(bodies, tmp_path):
    m, tree = bodies["lblock"]
    path = tmp_path / "t.npz"
    arrs = tree.arrays()
    arrs["front"] = np.zeros_like(arrs["front"])  # every node points to the root: a cycle
    meta = np.array([tree.content_hash, str(bsp.FORMAT_VERSION), str(tree.depth), repr(tree.plane_eps), "0.0"])
    np.savez(path, meta=meta, **arrs)
    with pytest.raises(ValueError, match="inconsistent"):
        load_bsp(path, m.content_hash)


def test_default_cache_dir_env(monkeypatch, tmp_path):
    monkeypatch.setenv("VESPRO_BSP_CACHE", str(tmp_path / "c"))
    assert bsp.default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("VESPRO_BSP_CACHE")
    assert bsp.default_cache_dir() == Path.home() / ".cache" / "vespro" / "bsp"


def test_unwritable_cache_still_returns_a_tree(bodies, tmp_path):
    m, tree = bodies["box"]
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("a file where the cache folder should be")
    t = load_or_build_bsp(m, cache_dir=blocker / "bsp")
    assert t.n_nodes == tree.n_nodes
    assert load_or_build_bsp(m, use_cache=False).n_nodes == tree.n_nodes
