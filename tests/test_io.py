"""Scan readers and writers: exact round trips, hand-made files of known content, bad input."""

import gzip
import struct
import time

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from plyfile import PlyData

from facerec3d import FaceScan, ScanFormatError
from facerec3d.io import SUPPORTED_SUFFIXES, load_landmarks_lm3, load_scan, save_scan, write_ply
from tests.conftest import cap_image


def assert_same_grid_scan(a, b):
    assert a.grid_shape == b.grid_shape
    np.testing.assert_array_equal(a.grid, b.grid)
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-6)


@pytest.fixture
def cap():
    return cap_image()


# ------------------------------------------------------------------ round trips
@pytest.mark.parametrize("name", ["s.abs", "s.abs.gz", "s.bnt", "s.ply", "s.npz", "S.ABS.GZ", "s.NPZ"])
def test_round_trip_is_exact(tmp_path, cap, name):
    save_scan(cap, tmp_path / name)
    assert [p.name for p in tmp_path.iterdir()] == [name]
    back = load_scan(tmp_path / name)
    assert_same_grid_scan(cap, back)
    assert back.meta.path == str(tmp_path / name) and back.meta.scan_id == name.split(".")[0]


@given(
    rows=st.integers(1, 9), cols=st.integers(1, 9), seed=st.integers(0, 2**32 - 1),
    suffix=st.sampled_from([".abs", ".abs.gz", ".bnt", ".ply", ".npz"]),
)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_round_trip_of_random_grids(tmp_path, rows, cols, seed, suffix):
    rng = np.random.default_rng(seed)
    valid = rng.random((rows, cols)) < 0.7
    valid.flat[rng.integers(rows * cols)] = True
    xyz = rng.uniform(-500, 500, (rows, cols, 3)).round(6)
    scan = FaceScan.from_range_image(xyz, valid)
    save_scan(scan, tmp_path / f"r{suffix}")
    assert_same_grid_scan(scan, load_scan(tmp_path / f"r{suffix}"))


@pytest.mark.parametrize("binary", [True, False])
def test_ply_keeps_normals_colours_grid_and_writes_grid_triangles(tmp_path, cap, binary):
    normals = np.tile([0.0, 0.0, 1.0], (cap.n_points, 1))
    colors = np.random.default_rng(2).integers(0, 256, (cap.n_points, 3), dtype=np.uint8)
    scan = cap.replace(normals=normals, colors=colors)
    write_ply(scan, tmp_path / "a.ply", binary=binary)
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\nformat " + (b"binary" if binary else b"ascii"))
    back = load_scan(tmp_path / "a.ply")
    assert_same_grid_scan(scan, back)
    np.testing.assert_array_equal(back.normals, normals)
    np.testing.assert_array_equal(back.colors, colors)
    assert PlyData.read(str(tmp_path / "a.ply"))["face"].count == len(scan.triangles()) > 0


def test_point_cloud_ply_without_faces(tmp_path):
    points = np.random.default_rng(3).normal(0, 50, (40, 3))
    save_scan(FaceScan(points), tmp_path / "cloud.ply")
    back = load_scan(tmp_path / "cloud.ply")
    assert back.grid is None and back.normals is None and back.colors is None
    np.testing.assert_array_equal(back.points, points)


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_ply_from_other_writers_float32_and_quads(tmp_path, byte_order):
    from plyfile import PlyElement

    vertex = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    face = np.array([([0, 1, 2, 3],)], dtype=[("vertex_indices", "i4", (4,))])
    ply = PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")], byte_order=byte_order)
    ply.write(str(tmp_path / "quad.ply"))
    s = load_scan(tmp_path / "quad.ply")
    assert s.grid is None
    np.testing.assert_array_equal(s.points, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])


def test_ply_face_of_no_corners_is_no_triangle_and_no_warning(tmp_path):
    """A face line `0` (an empty vertex list) in an ASCII PLY printed plyfile's (NumPy loadtxt's) UserWarning
    'input contained no data' after the result; it is read as no triangle, in silence."""
    import warnings

    (tmp_path / "e.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
                                    "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n0\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = load_scan(tmp_path / "e.ply")
    assert [str(w.message) for w in caught] == []
    np.testing.assert_array_equal(s.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(s.mesh, [[0, 1, 2]])


# ------------------------------------------------------------------ FRGC .abs
def test_abs_with_unusual_rows_and_columns(tmp_path):
    scan = cap_image(7, 11, invalid=((3, 4), (6, 10)))
    save_scan(scan, tmp_path / "odd.abs")
    assert (tmp_path / "odd.abs").read_text().startswith("7 rows\n11 columns\npixels (flag X Y Z):\n")
    assert_same_grid_scan(scan, load_scan(tmp_path / "odd.abs"))


def test_hand_written_abs(tmp_path):
    text = (
        "2 rows\r\n3 columns\r\npixels (flag X Y Z):\r\n1 0 1\n1 1 0\n"  # values may break across lines
        "1 -999999 3 4 5 -999999\n10 -999999 30 40 50 -999999\n"
        "-100 -999999 -300\n-400 -500 -999999\n"
    )
    (tmp_path / "02463d452.abs").write_text(text)
    s = load_scan(tmp_path / "02463d452.abs")
    assert s.grid_shape == (2, 3) and s.meta.scan_id == "02463d452"
    np.testing.assert_array_equal(s.grid, [[0, 0], [0, 2], [1, 0], [1, 1]])
    np.testing.assert_array_equal(s.points, [[1, 10, -100], [3, 30, -300], [4, 40, -400], [5, 50, -500]])


def test_abs_values_of_16_and_17_digits_read_as_numpy_reads_them(tmp_path):
    """The fast parser reads at most 15 digits exactly (mantissa / 10^k of exact doubles); a longer token goes to
    NumPy. Tokens whose mantissa is above 2^53 (rounded once to a double, then again by the division) came out one
    unit in the last place off NumPy's correctly rounded value when the parser took them itself."""
    tokens = ["9420968.007385407", "9281.685028995789", "9786907.3662585178", "991734.06264219054"]
    values = " ".join(tokens)
    negated = " ".join("-" + t for t in tokens)
    (tmp_path / "long.abs").write_text(f"1 rows\n4 columns\npixels (flag X Y Z):\n1 1 1 1\n{values}\n{values}\n"
                                       f"{negated}\n")
    s = load_scan(tmp_path / "long.abs")
    expected = np.array(tokens, dtype=np.float64)
    np.testing.assert_array_equal(s.points, np.stack([expected, expected, -expected], axis=1))


def test_gzip_recognised_by_content_and_scan_id_drops_both_suffixes(tmp_path, cap):
    save_scan(cap, tmp_path / "02463d452.abs.gz")
    (tmp_path / "plain.abs").write_bytes((tmp_path / "02463d452.abs.gz").read_bytes())
    assert load_scan(tmp_path / "02463d452.abs.gz").meta.scan_id == "02463d452"
    assert_same_grid_scan(cap, load_scan(tmp_path / "plain.abs"))


@pytest.mark.parametrize("damage", ["truncated", "flipped", "crc"])
def test_a_damaged_abs_gz_is_one_clear_error(tmp_path, cap, damage):
    """A `.abs.gz` cut short, with a corrupt deflate stream or a wrong checksum is refused with one line naming the
    file (whichever inflater reads it: python-isal's or the standard library's)."""
    save_scan(cap, tmp_path / "good.abs.gz")
    data = bytearray((tmp_path / "good.abs.gz").read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    elif damage == "flipped":
        data[20:36] = b"\xff" * 16  # just past the header and the name "good.abs": no valid deflate block
    else:
        data[-8] ^= 0xFF  # the CRC-32 of the trailer
    (tmp_path / "bad.abs.gz").write_bytes(bytes(data))
    with pytest.raises(ScanFormatError, match=r"bad\.abs\.gz: corrupt or truncated gzip data \("):
        load_scan(tmp_path / "bad.abs.gz")


def test_full_size_abs_loads_fast(tmp_path):
    scan = cap_image(480, 640, invalid=())
    save_scan(scan, tmp_path / "big.abs")
    times = []
    for _ in range(2):
        t = time.perf_counter()
        back = load_scan(tmp_path / "big.abs")
        times.append(time.perf_counter() - t)
    assert back.n_points == 480 * 640
    assert min(times) < 1.0, times


# ------------------------------------------------------------- Bosphorus .bnt
def bnt_bytes(rows, cols, zmin, blocks, texture=b"tex.png", count=None) -> bytes:
    """A .bnt file: header, then the five (rows, cols) blocks X, Y, Z, u, v as given (stored order)."""
    count = rows * cols * 5 if count is None else count
    body = np.asarray(blocks, dtype="<f8").tobytes()
    return struct.pack("<HHdH", rows, cols, zmin, len(texture)) + texture + struct.pack("<I", count) + body


def test_hand_built_bnt_is_read_bottom_up_and_written_back_identically(tmp_path):
    zmin = -1e9
    # stored bottom-up: the first stored row is the image's bottom row; pixel (top row, right) is invalid
    X = [[10, 11], [0, zmin]]
    Y = [[-1, -1], [1, zmin]]
    Z = [[5, 6], [7, zmin]]
    data = bnt_bytes(2, 2, zmin, [X, Y, Z, np.zeros((2, 2)), np.zeros((2, 2))])
    (tmp_path / "bs000_N_N_0.bnt").write_bytes(data)
    s = load_scan(tmp_path / "bs000_N_N_0.bnt")
    np.testing.assert_array_equal(s.grid, [[0, 0], [1, 0], [1, 1]])  # grid row 0 is the top
    np.testing.assert_array_equal(s.points, [[0, 1, 7], [10, -1, 5], [11, -1, 6]])
    assert s.meta.extra["texture"] == "tex.png" and s.landmarks == {}
    save_scan(s, tmp_path / "copy.bnt")
    assert (tmp_path / "copy.bnt").read_bytes() == bnt_bytes(2, 2, zmin, [X, Y, Z, np.zeros((2, 2)), np.zeros((2, 2))], b"")


LM3 = "3D landmark file\n# a comment\n2 landmarks:\nNose tip\n  1.5 2.5 -3.5\n\nChin middle\n  0 -60 -20\n"


def test_lm3_landmarks(tmp_path, cap):
    save_scan(cap, tmp_path / "bs001_E_HAPPY_0.bnt")
    (tmp_path / "bs001_E_HAPPY_0.lm3").write_text(LM3)  # Bosphorus's landmarks beside it
    lm = load_landmarks_lm3(tmp_path / "bs001_E_HAPPY_0.lm3")
    assert list(lm) == ["Nose tip", "Chin middle"]
    np.testing.assert_array_equal(lm["Nose tip"], [1.5, 2.5, -3.5])
    s = load_scan(tmp_path / "bs001_E_HAPPY_0.bnt")
    np.testing.assert_array_equal(s.landmarks["Chin middle"], [0, -60, -20])
    save_scan(s, tmp_path / "copy.bnt")  # writes copy.lm3 beside it
    back = load_scan(tmp_path / "copy.bnt")
    assert back.landmarks.keys() == lm.keys()
    np.testing.assert_array_equal(back.landmarks["Nose tip"], lm["Nose tip"])


def test_lm3_landmarks_are_written_to_a_micrometre(tmp_path, cap):
    """`write_lm3` keeps 1e-6 mm, as `.abs` values are: landmarks of fine fractions come back within it."""
    landmarks = {"Nose tip": np.array([1.234567, -2.000001, -940.123456]),
                 "Chin middle": np.array([0.000004, -61.987654, -951.5])}
    save_scan(cap.replace(landmarks=landmarks), tmp_path / "fine.bnt")
    back = load_scan(tmp_path / "fine.bnt").landmarks
    assert back.keys() == landmarks.keys()
    for name, v in landmarks.items():
        np.testing.assert_allclose(back[name], v, rtol=0, atol=1e-6)


def test_writing_a_bnt_without_landmarks_removes_a_stale_lm3(tmp_path, cap):
    """`convert A.npz out.bnt` wrote out.lm3; converting a scan without landmarks to out.bnt then left it, and
    out.bnt read back with A's landmarks. The .lm3 is replaced by a scan with landmarks, removed by one without."""
    save_scan(cap.replace(landmarks={"nose_tip": np.array([1.0, 2.0, -940.0])}), tmp_path / "out.bnt")
    save_scan(cap.replace(landmarks={"chin": np.array([0.0, -9.0, -950.0])}), tmp_path / "out.bnt")
    assert list(load_scan(tmp_path / "out.bnt").landmarks) == ["chin"]
    save_scan(cap, tmp_path / "out.bnt")
    assert not (tmp_path / "out.lm3").exists() and not load_scan(tmp_path / "out.bnt").landmarks


@pytest.mark.parametrize("text, reason", [
    ("", "no 'N landmarks:' line"),
    ("3D landmark file\n2 landmarks:\nNose tip\n1 2 3\n", "2 landmarks announced"),
    ("3D landmark file\n1 landmarks:\nNose tip\n1 2\n", "bad coordinates"),
    ("3D landmark file\n1 landmarks:\nNose tip\n1 2 nan\n", "bad coordinates"),
    ("3D landmark file\n1 landmarks:\nNose tip\n1 2 x\n", "bad coordinates"),
    ("3D landmark file\n2 landmarks:\nA\n1 2 3\nA\n1 2 3\n", "given twice"),
])
def test_malformed_lm3(tmp_path, cap, text, reason):
    save_scan(cap, tmp_path / "f.bnt")
    (tmp_path / "f.lm3").write_text(text)
    with pytest.raises(ScanFormatError, match=reason):
        load_landmarks_lm3(tmp_path / "f.lm3")
    with pytest.raises(ScanFormatError, match="f.lm3"):
        load_scan(tmp_path / "f.bnt")


# ------------------------------------------------------------ trimesh meshes
@pytest.mark.parametrize("suffix", ["obj", "off", "stl"])
def test_meshes_written_by_trimesh(tmp_path, suffix):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    mesh.export(tmp_path / f"m.{suffix}")
    s = load_scan(tmp_path / f"m.{suffix}")
    if suffix == "stl":  # STL repeats vertices per triangle; the reader merges them
        np.testing.assert_allclose(s.points, np.unique(mesh.vertices.astype(np.float32), axis=0), atol=1e-4)
    else:
        np.testing.assert_allclose(s.points, mesh.vertices, atol=1e-5)


def test_obj_colours_and_point_clouds(tmp_path):
    (tmp_path / "n.obj").write_text("v 1 2 3\nv 4 5 6\nv 7 8 10\nvn 0 0 1\nvn 0 0 1\nvn 0 1 0\nf 1//1 2//2 3//3\n")
    s = load_scan(tmp_path / "n.obj")
    np.testing.assert_array_equal(s.points, [[1, 2, 3], [4, 5, 6], [7, 8, 10]])
    assert s.colors is None
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=50.0)
    mesh.visual.vertex_colors = np.tile([10, 20, 30, 255], (len(mesh.vertices), 1))
    mesh.export(tmp_path / "c.obj")
    np.testing.assert_array_equal(load_scan(tmp_path / "c.obj").colors, np.tile([10, 20, 30], (len(mesh.vertices), 1)))
    (tmp_path / "p.obj").write_text("v 1 2 3 255 0 0\nv 4 5 6 0 255 0\n")
    (tmp_path / "p.off").write_text("OFF\n2 0 0\n1 2 3\n4 5 6\n")
    for name in ("p.obj", "p.off"):
        np.testing.assert_array_equal(load_scan(tmp_path / name).points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(load_scan(tmp_path / "p.obj").colors, [[255, 0, 0], [0, 255, 0]])


def test_a_scan_converted_to_obj_keeps_every_point(tmp_path):
    """ux19 item 4: `facerec3d convert SCAN out.obj` wrote every point, but reading it back dropped the ~2 % that
    no grid triangle uses (trimesh keeps only the vertices faces reference). Now they all come back, in order,
    with the triangles."""
    from click.testing import CliRunner

    from facerec3d.cli import main
    from facerec3d.datasets.synthetic import quick_scan

    scan = quick_scan(0, rows=240, cols=320, focal_px=1000.0).scan  # a laser scan's noise and edges
    save_scan(scan, tmp_path / "s.npz")
    used = len(np.unique(scan.triangles()))
    assert used < scan.n_points  # some valid points are in no triangle: the case that lost them
    r = CliRunner().invoke(main, ["convert", str(tmp_path / "s.npz"), str(tmp_path / "s.obj")])
    assert r.exit_code == 0, r.output
    back = load_scan(tmp_path / "s.obj")
    assert back.n_points == scan.n_points
    np.testing.assert_allclose(back.points, scan.points, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(back.mesh, scan.triangles())


def test_obj_vertices_are_kept_whatever_their_faces_texture_or_normals(tmp_path):
    """Every `v` record is one point, in order: one that no face uses, and one with two texture coordinates
    (trimesh would make it two vertices)."""
    (tmp_path / "t.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 9 9 9\n"
                                    "vt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\nvt 0.5 0.5\nvn 0 0 1\n"
                                    "f 1/1/1 2/2/1 3/3/1\nf 2/5/1 4/4/1 3/3/1\n")
    s = load_scan(tmp_path / "t.obj")
    np.testing.assert_array_equal(s.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [9, 9, 9]])
    np.testing.assert_array_equal(s.mesh, [[0, 1, 2], [1, 3, 2]])


SQUARE = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"


def test_obj_materials_keep_each_vertex_once_and_the_triangles(tmp_path, cap):
    """A second `usemtl` split trimesh's mesh in two, each with every vertex: 8 points for a file's 4 and no
    triangles (a textured face export read as twice its points, no mesh, which preprocessing failed). Each vertex
    is one point, in order, and the faces of every material are the triangles."""
    (tmp_path / "u.obj").write_text(SQUARE + "f 1 2 3\nusemtl m\nf 2 4 3\n")
    s = load_scan(tmp_path / "u.obj")
    np.testing.assert_array_equal(s.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    np.testing.assert_array_equal(s.mesh, [[0, 1, 2], [1, 3, 2]])
    save_scan(cap, tmp_path / "base.obj")
    lines = (tmp_path / "base.obj").read_text().splitlines()
    faces = [i for i, line in enumerate(lines) if line.startswith("f ")]
    lines.insert(faces[len(faces) // 2], "usemtl b")
    lines.insert(faces[0], "usemtl a")
    (tmp_path / "mtl.obj").write_text("mtllib face.mtl\n" + "\n".join(lines) + "\n")
    s = load_scan(tmp_path / "mtl.obj")
    np.testing.assert_allclose(s.points, cap.points, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(s.mesh, cap.triangles())


def test_obj_corners_naming_texture_and_normals_the_file_lacks_keep_every_vertex(tmp_path):
    """`f 1/1/1 2/2/2 3/3/3` in a file without `vt` or `vn` records dropped the vertex no face uses (3 points of 4)."""
    (tmp_path / "t.obj").write_text(SQUARE + "f 1/1/1 2/2/2 3/3/3\n")
    s = load_scan(tmp_path / "t.obj")
    np.testing.assert_array_equal(s.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    np.testing.assert_array_equal(s.mesh, [[0, 1, 2]])


def test_obj_relative_indices_polygons_comments_and_continued_lines(tmp_path):
    """`-1` is the last vertex read before the face; a polygon is fanned from its first corner; `#` comments and
    records continued with `\\` are read as the OBJ format says; faces of fewer than 3 corners are no triangle."""
    (tmp_path / "r.obj").write_text("# a comment\nv 0 0 0\nv 1 0 0 # a vertex\nv 0 1 0\nf -3 -2 -1\no part\ng g1\n"
                                    "s off\nv 1 \\\n 1 0\nf 1 2 4 3\nf 1 2\n")
    s = load_scan(tmp_path / "r.obj")
    np.testing.assert_array_equal(s.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    np.testing.assert_array_equal(s.mesh, [[0, 1, 2], [0, 1, 3], [0, 3, 2]])


@pytest.mark.parametrize("text, reason", [
    (SQUARE + "f 1 2 0\n", "line 5: a face names vertex 0 (OBJ numbers vertices from 1)"),
    (SQUARE + "f 1 2 9\n", "line 5: a face names vertex 9, the file has 4"),
    ("v 0 0 0\nv 1 0 0\nf -1 -2 -3\n" + SQUARE, "line 3: a face names vertex -3, but only 2 come before it"),
    (SQUARE + "f 1 2/1 x\n", "line 5: a face's vertex number is not a number: 'x'"),
    ("v 0 0\n" + SQUARE, "line 1: a vertex needs 3 coordinates, x y z: 'v 0 0'"),
    (SQUARE + "v 1 2 z\n", "line 5: a vertex coordinate is not a number: 'z'"),
    (SQUARE + "f" + " 1" * 40000 + "\n", "line 5: a record longer than 65536 characters"),
], ids=["vertex-0", "past-the-last", "relative-before-the-first", "not-a-number", "short-vertex", "bad-coordinate",
        "long-line"])
def test_obj_malformed_records_are_refused_naming_their_line(tmp_path, text, reason):
    """`f 1 2 0` was read as the triangle [0, 1, 0], a short `v` line made the whole file 'no valid points'."""
    (tmp_path / "bad.obj").write_text(text)
    with pytest.raises(ScanFormatError) as e:
        load_scan(tmp_path / "bad.obj")
    assert str(e.value) == f"{tmp_path / 'bad.obj'}: {reason}"


# ------------------------------------------------------------ text point clouds
@pytest.mark.parametrize("name, text", [
    ("p.xyz", "# comment\n1 2 3\n\n4 5 6 7 8  # trailing comment\n"),
    ("p.csv", "x,y,z,intensity\n1,2,3,0.5\n4, 5, 6, 0.7\n"),
    ("p.txt", "X\tY\tZ\n1\t2\t3\n4\t5\t6\n"),
])
def test_text_point_clouds(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    s = load_scan(tmp_path / name)
    assert s.grid is None
    np.testing.assert_array_equal(s.points, [[1, 2, 3], [4, 5, 6]])


# ------------------------------------------------------------------- NumPy
def test_numpy_images_depth_maps_and_point_sets(tmp_path, cap):
    xyz, _ = cap.to_range_image()
    np.save(tmp_path / "i.npy", xyz)
    assert_same_grid_scan(cap, load_scan(tmp_path / "i.npy"))
    depth = np.arange(20.0).reshape(4, 5)
    depth[1, 1] = np.nan
    np.save(tmp_path / "d.npy", depth)
    s = load_scan(tmp_path / "d.npy")
    assert s.n_points == 19 and s.grid_shape == (4, 5)
    np.testing.assert_array_equal(s.points[s.grid.tolist().index([2, 3])], [3, -2, 13])  # x = col, y = -row
    np.save(tmp_path / "p.npy", np.ones((5, 3)))
    assert load_scan(tmp_path / "p.npy").n_points == 5
    np.savez(tmp_path / "p.npz", points=np.ones((3, 3)))
    assert load_scan(tmp_path / "p.npz").n_points == 3


def test_npz_keeps_landmarks_and_the_valid_mask(tmp_path, cap):
    save_scan(cap.replace(landmarks={"nose": [1, 2, 3]}), tmp_path / "s.npz")
    back = load_scan(tmp_path / "s.npz")
    np.testing.assert_array_equal(back.landmarks["nose"], [1, 2, 3])
    with np.load(tmp_path / "s.npz", allow_pickle=False) as z:
        assert set(z.files) == {"xyz", "valid", "landmark_nose"}
        xyz, valid = z["xyz"], z["valid"]
    xyz[0, 1] = np.nan  # NaN in a pixel marked valid is an error, not a hole
    np.savez(tmp_path / "nan.npz", xyz=xyz, valid=valid | True)
    with pytest.raises(ScanFormatError, match="non-finite"):
        load_scan(tmp_path / "nan.npz")


def test_npz_keeps_the_scans_quality_record_as_json_and_refuses_a_bad_one(tmp_path, cap):
    quality = {"fit_rms_mm": 0.9, "pitch_mm": 3.4, "depth_step_mm": 8.0}
    extra = {"quality": quality, "to_frontal": np.eye(3, 4)}
    save_scan(cap.replace(meta=cap.meta.replace(extra=extra)), tmp_path / "s.npz")
    back = load_scan(tmp_path / "s.npz")
    assert back.meta.extra["quality"] == quality
    np.testing.assert_array_equal(back.meta.extra["to_frontal"], np.eye(3, 4))
    with np.load(tmp_path / "s.npz", allow_pickle=False) as z:
        arrays = dict(z)
    for bad, reason in ((np.array("{not json"), "not valid JSON"), (np.array("[1]"), "JSON object"),
                        (np.arange(3), "one JSON text")):
        np.savez(tmp_path / "bad.npz", **{**arrays, "meta_json": bad})
        with pytest.raises(ScanFormatError, match=reason):
            load_scan(tmp_path / "bad.npz")


# --------------------------------------------------------------- bad input
CAP_ABS = "1 rows\n2 columns\npixels (flag X Y Z):\n"
BAD_FILES = [
    ("bad.abs", b"", "truncated or bad header"),
    ("bad.abs", b"480 rows\n640 columns\npixels (flag X Y Z):\n1 2 3\n", "expected 1228800 values"),
    ("bad.abs", b"1000000000 rows\n1000 columns\npixels (flag X Y Z):\n", "absurd size"),
    ("bad.abs", b"0 rows\n5 columns\npixels (flag X Y Z):\n", "bad size"),
    ("bad.abs", b"480 lines\n640 columns\npixels (flag X Y Z):\n", "bad header"),
    ("bad.abs", (CAP_ABS + "1 1 a b c d e f\n").encode(), "non-numeric"),
    ("bad.abs", (CAP_ABS + "1 1 1 2 3 4 5 \xff\n").encode("latin-1"), "non-numeric"),
    ("bad.abs", (CAP_ABS + "0 0 -999999 -999999 -999999 -999999 -999999 -999999\n").encode(), "no valid points"),
    ("bad.abs", (CAP_ABS + "1 0 nan -999999 1 -999999 1 -999999\n").encode(), "non-finite"),
    ("bad.abs", (CAP_ABS + "1 2 1 1 1 1 1 1\n").encode(), "flags must be 0 or 1"),
    ("bad.abs.gz", gzip.compress((CAP_ABS + "1 1 1 1 1 1 1 1\n").encode(), mtime=0)[:-12], "corrupt or truncated gzip"),
    ("bad.abs.gz", b"\x1f\x8b garbage", "corrupt or truncated gzip"),
    ("bad.bnt", b"", "truncated header"),
    ("bad.bnt", b"\x02\x00\x02\x00", "truncated header"),
    ("bad.bnt", bnt_bytes(65535, 65535, -1e9, [], count=0), "absurd size"),
    ("bad.bnt", bnt_bytes(1, 2, -1e9, np.ones((5, 1, 2)), count=11), "header says 11 values"),
    ("bad.bnt", bnt_bytes(1, 2, -1e9, np.ones((5, 1, 2)))[:-8], "expected 80 bytes"),
    ("bad.bnt", bnt_bytes(1, 2, -1e9, np.full((5, 1, 2), -1e9)), "no valid points"),
    ("bad.bnt", bnt_bytes(1, 2, -1e9, np.full((5, 1, 2), np.inf)), "non-finite"),
    ("bad.bnt", bnt_bytes(1, 2, np.nan, np.ones((5, 1, 2))), "bad zmin"),
    ("bad.ply", b"PLY\nformat ascii 1.0\n", "not a PLY file"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 99999999\nproperty float x\nend_header\n1\n",
     "truncated PLY: header promises 99999999 vertices, the file holds fewer (75 bytes in all)"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n",
     "truncated PLY: header promises 2 vertices, the file holds only 1"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 2x\nproperty float x\nend_header\n1\n",
     "bad PLY header: the count of element 'vertex' is '2x', not a number"),
    ("bad.ply", "ply\nformat ascii 1.0\nelement vertex \u00b2\nproperty float x\nproperty float y\n"
     "property float z\nend_header\n1 2 3\n4 5 6\n".encode(),  # a digit to str.isdigit, not to int()
     "bad PLY header: the count of element 'vertex' is '\u00b2', not a number"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement face 3\n"
     b"property list uchar int vertex_indices\nend_header\n1\n3 0 0 0\n",
     "truncated PLY: header promises 3 face elements, the file holds only 1"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n", "no x, y, z"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
     b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n",
     "a triangle names a vertex outside 0..2"),  # vertex 3 of 3: one past the last
    ("bad.ply", b"ply\nformat ascii 1.0\ncomment facerec3d grid_shape 2 2\nelement vertex 2\nproperty float x\n"
     b"property float y\nproperty float z\nproperty int row\nproperty int col\nend_header\n0 0 0 1 1\n1 0 0 1 1\n",
     "two points share a grid position"),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n", "no valid points"),
    ("bad.npy", b"\x93NUMPY garbage", "unsupported .npy version"),
    ("bad.npy", b"\x93NUMPY\x01\x00garbage", "not a readable NumPy file"),
    ("bad.npy", b"", "not a NumPy file: neither an .npy array nor an .npz archive"),
    ("bad.npz", b"PK\x03\x04 garbage", "not a readable NumPy file"),
    ("bad.xyz", b"x y z\n1 2\n", "fewer than 3 columns"),
    ("bad.xyz", b"1 2 3\n1 2 x\n", "non-numeric"),
    ("bad.xyz", b"1 2 3\n1 2 inf\n", "non-finite"),
    ("bad.xyz", b"x y z\n1 2 3\nx 5 6\n", "non-numeric"),  # only a first line is a header of column names
    ("bad.csv", b"", "no valid points"),
    ("bad.obj", b"\x00\xff\xfe garbage", "no valid points"),
    # an OFF cut before the faces its counts line promises was read as a scan of its vertices (a PLY is refused)
    ("bad.off", b"OFF\n3 99999999999 0\n0 0 0\n1 0 0\n0 1 0\n",
     "truncated OFF: header promises 3 vertices and 99999999999 faces (a line each), the file holds only 3 lines"),
    ("bad.off", b"OFF\n# a comment\n3 2 0\n0 0 0\n1 0 0 # a vertex\n\n0 1 0\n3 0 1 2\n",
     "truncated OFF: header promises 3 vertices and 2 faces (a line each), the file holds only 4 lines"),
    ("bad.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n", "truncated OFF: header promises 3 vertices and 1 faces"),
    ("bad.off", b"OFF\n-3 1 0\n0 0 0\n", "bad OFF header: the vertex and face counts are '-3 1', not numbers"),
    ("bad.stl", b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 1 2\n", "no valid points"),
]


@pytest.mark.parametrize("name, content, reason", BAD_FILES)
def test_bad_files_raise_scan_format_error_naming_file_and_reason(tmp_path, name, content, reason):
    p = tmp_path / name
    p.write_bytes(content)
    with pytest.raises(ScanFormatError) as e:
        load_scan(p)
    assert str(e.value).startswith(str(p)) and reason in str(e.value)


def test_an_off_counts_line_of_billions_of_faces_allocates_nothing_by_it(tmp_path):
    """The counts are checked against the lines the file holds, never used to size anything: refused in one line, the
    memory used bounded by the file's size whatever the counts line says."""
    import tracemalloc

    def peak(counts: bytes) -> int:
        p = tmp_path / "huge.off"
        p.write_bytes(b"OFF\n" + counts + b"\n0 0 0\n1 0 0\n0 1 0\n" + b"3 0 1 2\n" * 1000)
        tracemalloc.start()
        try:
            with pytest.raises(ScanFormatError, match=f"{p}: truncated OFF: header promises 3 vertices and "):
                load_scan(p)
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    assert peak(b"3 99999999999999999999 0") < peak(b"3 1001 0") + (1 << 20)  # as for a file one face short
    p = tmp_path / "ok.off"
    p.write_bytes(b"OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n4 0 1 2 0\n")  # counts met: read, a quad fanned
    assert load_scan(p).n_points == 3


def test_numpy_arrays_that_are_not_scans(tmp_path):
    np.save(tmp_path / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(tmp_path / "s.npy", np.array(["a", "b", "c"]))
    np.save(tmp_path / "v.npy", np.ones(7))
    np.savez(tmp_path / "k.npz", other=np.ones((3, 3)))
    np.savez(tmp_path / "m.npz", xyz=np.ones((2, 2, 3)), valid=np.ones((3, 2), bool))
    for name, reason in [("o.npy", "Python objects"), ("s.npy", "not numeric"), ("v.npy", r"shape \(7,\)"),
                         ("k.npz", "needs an 'xyz' or a 'points'"), ("m.npz", "'valid' must be")]:
        with pytest.raises(ScanFormatError, match=reason):
            load_scan(tmp_path / name)


def test_unknown_missing_and_unwritable(tmp_path, cap):
    with pytest.raises(ScanFormatError, match="unknown scan format"):
        load_scan(tmp_path / "x.foo")
    with pytest.raises(ScanFormatError, match="missing.abs: no such file"):
        load_scan(tmp_path / "missing.abs")
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(ScanFormatError, match="not a regular file"):
        load_scan(tmp_path / "dir.ply")
    with pytest.raises(ScanFormatError, match="cannot write"):
        save_scan(cap, tmp_path / "x.off")
    with pytest.raises(ValueError, match="needs a scan with a grid"):
        save_scan(FaceScan(cap.points), tmp_path / "x.abs")
    assert set(SUPPORTED_SUFFIXES) >= {".abs", ".abs.gz", ".bnt", ".ply", ".obj", ".off", ".stl", ".npz"}


@settings(deadline=None)  # the first call loads the compiled parser
@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False), max_size=50), st.sampled_from(["%.6f", "%.3f", "%d", "%.9f"]),
       st.sampled_from([" ", "\n", "  \t"]))
def test_fast_abs_number_parser_matches_numpy(values, fmt, sep):
    from facerec3d.io.abs import _parse_decimals

    text = sep.join(fmt % v for v in values).encode()
    out = np.empty(len(values) + 1)
    count = _parse_decimals(np.frombuffer(text, dtype=np.uint8), out)
    expected = np.array(text.split(), dtype=np.float64)
    if count >= 0:  # exact where it reads at all (else the reader falls back to NumPy)
        np.testing.assert_array_equal(out[:count], expected)
    else:
        assert any(len(t.strip(b"+-").replace(b".", b"")) > 15 for t in text.split())


@settings(deadline=None)
@given(st.lists(st.sampled_from(["0", "1", "10", "-0", "1.5", "1.50", "-1.5", "-999999.000000", "-999999.0000001",
                                 "-999999.00000", "15", "1e3"]), max_size=60),
       st.lists(st.sampled_from([" ", "\n", "\t", "  "]), min_size=1, max_size=4))
def test_fast_abs_number_parser_reads_repeated_tokens_as_numpy_does(tokens, seps):
    """A token equal to the one before it takes its value unparsed: only the very same bytes may (`1` then `10`,
    `-999999.00000` then `-999999.000000`, `1.5` then `1.50` are other tokens), and to the bit (-0 stays -0)."""
    from facerec3d.io.abs import _parse_decimals

    text = "".join(t + seps[i % len(seps)] for i, t in enumerate(tokens)).rstrip().encode()
    out = np.empty(len(tokens) + 1)
    count = _parse_decimals(np.frombuffer(text, dtype=np.uint8), out)
    if "1e3" in tokens:
        assert count == -1  # an exponent: NumPy reads it
        return
    expected = np.array(text.split(), dtype=np.float64)
    assert count == len(expected)
    np.testing.assert_array_equal(out[:count], expected)
    assert np.array_equal(np.signbit(out[:count]), np.signbit(expected))
