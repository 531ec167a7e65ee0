"""ViSP .cao models: sections, includes, line endings, triangulation, clear errors."""

from pathlib import Path

import numpy as np
import pytest

from vespro.cao import CaoError, read_cao, triangulate_polygon
from vespro.model import ModelError, box_model, load_model

VISP_MBT = Path("/usr/share/visp-images-data/ViSP-images/mbt")

# The 84 mm cube of ViSP's tutorial, faces from points, wound counter-clockwise seen from outside.
CUBE_POINTS = """8
 0.000  0.000  0.000 # point 0
-0.084  0.000  0.000
-0.084  0.084  0.000
 0.000  0.084  0.000
 0.000  0.000  0.084
-0.084  0.000  0.084
-0.084  0.084  0.084
 0.000  0.084  0.084
"""
CUBE_FACES = """6
4 0 4 5 1 name=front
4 1 5 6 2
4 6 7 3 2
4 3 7 4 0
4 0 1 2 3
4 7 6 5 4
"""
CUBE = f"V1\n# 3D points\n{CUBE_POINTS}# 3D lines\n0\n# faces from lines\n0\n# faces from points\n{CUBE_FACES}0\n0\n"


def _write(path: Path, text: str, newline="\n") -> Path:
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def _same_solid(m, ref, atol=1e-12):
    assert len(m.faces) == len(ref.faces) and m.n_corners == ref.n_corners
    assert abs(m.volume - ref.volume) < 1e-12
    np.testing.assert_allclose(np.sort(m.corners, axis=0), np.sort(ref.corners, axis=0), atol=atol)


def test_faces_from_points_make_the_closed_cube(tmp_path):
    m = load_model(_write(tmp_path / "cube.cao", CUBE))
    # Independent reference: the same box built by trimesh, shifted to the .cao's corner at the origin.
    _same_solid(m, box_model([0.084, 0.084, 0.084], center=(-0.042, 0.042, 0.042)))
    assert m.unit == "m" and m.name == "cube"


def test_crlf_and_comments_read_as_lf(tmp_path):
    a = load_model(_write(tmp_path / "lf.cao", CUBE))
    b = load_model(_write(tmp_path / "crlf.cao", CUBE, "\r\n"))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)


def test_faces_from_lines_chain_into_the_same_cube(tmp_path):
    faces = [[int(v) for v in ln.split()[1:5]] for ln in CUBE_FACES.splitlines()[1:]]
    # Each face's first line runs along the face; its other lines are stored the other
    # way round (as a shared line is for one of its two faces), and listed out of order.
    lines, face_lines = [], []
    for f in faces:
        sides = list(zip(f, f[1:] + f[:1]))
        ids = []
        for k, (a, b) in enumerate(sides):
            ids.append(len(lines))
            lines.append((a, b) if k == 0 else (b, a))
        face_lines.append([ids[0], ids[2], ids[3], ids[1]])
    text = "V1\n" + CUBE_POINTS + f"{len(lines)}\n" + "".join(f"{a} {b}\n" for a, b in lines)
    text += f"{len(face_lines)}\n" + "".join(f"4 {' '.join(map(str, ids))}\n" for ids in face_lines) + "0\n"
    m = load_model(_write(tmp_path / "lines.cao", text))
    _same_solid(m, load_model(_write(tmp_path / "points.cao", CUBE)))


def test_a_face_from_lines_takes_the_direction_of_its_first_line(tmp_path):
    square = "V1\n4\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4\n0 1\n2 1\n2 3\n0 3\n"
    V, F = read_cao(_write(tmp_path / "a.cao", square + "1\n4 0 1 2 3\n0\n"))
    n = np.cross(V[F[0, 1]] - V[F[0, 0]], V[F[0, 2]] - V[F[0, 0]])
    assert n[2] > 0  # 0 -> 1 -> 2: counter-clockwise about +z
    V, F = read_cao(_write(tmp_path / "b.cao", square + "1\n4 3 2 1 0\n0\n"))
    n = np.cross(V[F[0, 1]] - V[F[0, 0]], V[F[0, 2]] - V[F[0, 0]])
    assert n[2] < 0  # first line (0, 3): 0 -> 3 -> 2 -> 1, clockwise about +z


def test_load_includes_part_files_relative_to_the_including_file(tmp_path):
    (tmp_path / "parts").mkdir()
    _write(tmp_path / "parts" / "cube.cao", CUBE)
    # A second cube moved 0.2 m along x and turned 90 deg about z (theta-u in degrees).
    top = 'V1\nload("parts/cube.cao")\nload("parts/cube.cao", t=[0.2; 0; 0], tu=[0; 0; 90deg])\n0\n0\n0\n0\n'
    m = load_model(_write(tmp_path / "two.cao", top))
    assert abs(m.volume - 2 * 0.084**3) < 1e-12 and m.n_corners == 16
    # The turned copy: the point (-0.084, 0, 0) goes to (0.2, -0.084, 0).
    assert np.min(np.linalg.norm(m.vertices - [0.2, -0.084, 0.0], axis=1)) < 1e-12


def test_include_cycle_and_missing_part_are_named(tmp_path):
    _write(tmp_path / "a.cao", 'V1\nload("b.cao")\n0\n0\n0\n0\n')
    _write(tmp_path / "b.cao", 'V1\nload("a.cao")\n0\n0\n0\n0\n')
    with pytest.raises(CaoError, match="cycle"):
        read_cao(tmp_path / "a.cao")
    _write(tmp_path / "c.cao", 'V1\nload("nowhere.cao")\n0\n0\n0\n0\n')
    with pytest.raises(CaoError, match=r"nowhere.cao: no such file \(loaded from .*c.cao\)"):
        read_cao(tmp_path / "c.cao")


@pytest.mark.parametrize("text, match", [
    ("V1\n8\n0 0 0\n", r"bad.cao:3: file ends where 3D point 1 was expected"),
    ("cube\n8\n", r"bad.cao:1: expected the header V1"),
    (CUBE.replace("-0.084  0.084  0.000", "-0.084  oops  0.000"), r"bad.cao:6: 3D point 2: expected 3 number"),
    (CUBE.replace("4 1 5 6 2", "4 1 5 9 2"), r"bad.cao:19: point index 9 out of range"),
    (CUBE.replace("4 1 5 6 2", "4 1 5 6"), r"bad.cao:19: face from points 1: expected 5 number"),
    (CUBE.replace("4 1 5 6 2", "4 1 5 5 2"), r"bad.cao:19: a face repeats a point"),
    (CUBE.replace("0\n0\n", "1\n0 7 0.02\n0\n"), r"bad.cao:\d+: 3D cylinders are not supported"),
    (CUBE.replace("0\n0\n", "0\n1\n0.02 0 1 2\n"), r"bad.cao:\d+: 3D circles are not supported"),
    ("V1\n3\n0 0 0\n1 0 0\n0 1 0\n0\n0\n0\n", r"bad.cao: no faces"),
])
def test_malformed_lines_name_file_and_line(tmp_path, text, match):
    with pytest.raises(CaoError, match=match):
        load_model(_write(tmp_path / "bad.cao", text, "\r\n"))


def test_open_surface_is_refused_with_what_to_do(tmp_path):
    no_top = CUBE.replace("6\n4 0 4 5 1", "5\n4 0 4 5 1").replace("4 7 6 5 4\n", "")
    with pytest.raises(ModelError, match=r"open\.cao: not watertight: 4 boundary edge.*add the missing faces"):
        load_model(_write(tmp_path / "open.cao", no_top))


def test_concave_face_is_triangulated_inside_the_polygon():
    # An L-shaped hexagon: a fan from vertex 0 would cover the notch.
    P = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]], float)
    T = triangulate_polygon(P)
    assert T.shape == (4, 3)
    A = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    assert np.all(A[:, 2] > 0)  # all wound as the polygon (counter-clockwise about +z)
    assert abs(0.5 * A[:, 2].sum() - 3.0) < 1e-12  # the L's area, nothing over the notch
    # Same polygon listed clockwise: triangles follow it.
    T2 = triangulate_polygon(P[::-1])
    A2 = np.cross(P[::-1][T2[:, 1]] - P[::-1][T2[:, 0]], P[::-1][T2[:, 2]] - P[::-1][T2[:, 0]])
    assert np.all(A2[:, 2] < 0)


def test_collinear_points_and_crossed_polygons():
    # A midpoint on a side: no zero-area triangle.
    P = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]], float)
    T = triangulate_polygon(P)
    A = 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1)
    assert len(T) == 3 and A.min() > 0.1 and abs(A.sum() - 2.0) < 1e-12
    bowtie = np.array([[0, 0, 0], [1, 1, 0], [1, 0, 0], [0, 1, 0]], float)
    assert triangulate_polygon(bowtie) is None
    assert triangulate_polygon(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)) is None


def test_model_with_a_concave_face_is_a_valid_solid(tmp_path):
    # An L-prism from two concave caps and six walls.
    L = [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]
    pts = [(x * 0.01, y * 0.01, 0.0) for x, y in L] + [(x * 0.01, y * 0.01, 0.01) for x, y in L]
    faces = ["6 5 4 3 2 1 0", "6 6 7 8 9 10 11"] + [f"4 {i} {(i + 1) % 6} {(i + 1) % 6 + 6} {i + 6}" for i in range(6)]
    text = f"V1\n{len(pts)}\n" + "".join(f"{x} {y} {z}\n" for x, y, z in pts) + "0\n0\n"
    text += f"{len(faces)}\n" + "\n".join(faces) + "\n"
    m = load_model(_write(tmp_path / "lprism.cao", text))
    assert abs(m.volume - 3e-4 * 0.01) < 1e-15 and len(m.faces) == 8
    assert np.sum(~m.edge_convex) == 1  # the re-entrant edge of the notch


def test_inside_out_cao_is_turned_with_a_note(tmp_path, capsys):
    flipped = "\n".join(
        " ".join([ln.split()[0]] + ln.split()[1:5][::-1]) if ln.startswith("4 ") else ln for ln in CUBE.splitlines()
    ) + "\n"
    m = load_model(_write(tmp_path / "inv.cao", flipped))
    assert m.volume > 0
    err = capsys.readouterr().err
    assert "inv.cao: every face pointed inward" in err and err.count("\n") == 1


def test_unit_argument_scales_a_cao(tmp_path):
    mm = CUBE_POINTS.replace("0.084", "84.0")
    text = CUBE.replace(CUBE_POINTS, mm)
    with pytest.raises(ModelError, match="--model-unit mm"):
        load_model(_write(tmp_path / "cube_mm.cao", text))
    m = load_model(tmp_path / "cube_mm.cao", unit="mm")
    assert abs(m.volume - 0.084**3) < 1e-12


@pytest.mark.skipif(not VISP_MBT.is_dir(), reason="visp-images-data is not installed")
def test_visp_tutorial_models():
    m = load_model(VISP_MBT / "cube.cao")
    _same_solid(m, box_model([0.084, 0.084, 0.084], center=(-0.042, 0.042, 0.042)))
    with pytest.raises(CaoError, match=r"cube_and_cylinder.cao:27: 3D cylinders are not supported"):
        load_model(VISP_MBT / "cube_and_cylinder.cao")
    for f in ("cylinder_cao_model_linux_line_ending.cao", "cylinder_cao_model_windows_line_ending.cao"):
        with pytest.raises(CaoError, match=f"{f}:16: 3D cylinders"):
            load_model(VISP_MBT.parent / "mbt-cao" / f)
