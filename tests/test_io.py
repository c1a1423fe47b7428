import gzip
import struct

import numpy as np
import pytest
import trimesh

from facerec3d import ScanFormatError
from facerec3d.io import load_scan, read_lm3, save_scan, write_lm3
from facerec3d.io.meshes import write_ply
from tests.conftest import cap_image


def same_valid_points(a, b):
    assert a.n_points == b.n_points
    np.testing.assert_allclose(a.points, b.points, atol=1e-6)
    np.testing.assert_array_equal(a.grid, b.grid)
    assert a.grid_shape == b.grid_shape


@pytest.mark.parametrize("name", ["s.abs", "s.abs.gz", "s.bnt", "s.ply", "s.npz"])
def test_round_trip_is_exact(tmp_path, cap, name):
    save_scan(cap, tmp_path / name)
    back = load_scan(tmp_path / name)
    same_valid_points(cap, back)
    assert back.meta.scan_id == "s" and back.meta.path == str(tmp_path / name)


def test_ascii_ply_round_trip(tmp_path, cap):
    write_ply(cap, tmp_path / "a.ply", binary=False)
    assert (tmp_path / "a.ply").read_bytes().startswith(b"ply\nformat ascii")
    same_valid_points(cap, load_scan(tmp_path / "a.ply"))


def test_abs_with_any_rows_and_columns(tmp_path):
    scan = cap_image(7, 11, invalid=((3, 4),))
    save_scan(scan, tmp_path / "odd.abs")
    back = load_scan(tmp_path / "odd.abs")
    assert back.grid_shape == (7, 11)
    same_valid_points(scan, back)


def test_hand_written_abs(tmp_path):
    text = ("2 rows\n3 columns\npixels (flag X Y Z):\n1 0 1 1 1 0\n"
            "1 -999999 3 4 5 -999999\n10 -999999 30 40 50 -999999\n-100 -999999 -300 -400 -500 -999999\n")
    (tmp_path / "h.abs").write_text(text)
    s = load_scan(tmp_path / "h.abs")
    assert s.grid_shape == (2, 3)
    np.testing.assert_array_equal(s.grid, [[0, 0], [0, 2], [1, 0], [1, 1]])
    np.testing.assert_array_equal(s.points[1], [3, 30, -300])
    np.testing.assert_array_equal(s.points[3], [5, 50, -500])


def test_hand_built_bnt_is_read_bottom_up(tmp_path):
    rows, cols, zmin = 2, 2, -1e9
    # stored rows bottom-up: the first stored row is the image's bottom row
    X = [[10, 11], [0, 1]]
    Y = [[-1, -1], [1, 1]]
    Z = [[5, zmin], [7, 8]]
    blocks = np.array([X, Y, Z, np.zeros((2, 2)), np.zeros((2, 2))], dtype="<f8")
    name = b"tex.png"
    data = struct.pack("<HHdH", rows, cols, zmin, len(name)) + name + struct.pack("<I", 20) + blocks.tobytes()
    (tmp_path / "bs000_N_N_0.bnt").write_bytes(data)
    s = load_scan(tmp_path / "bs000_N_N_0.bnt")
    np.testing.assert_array_equal(s.grid, [[0, 0], [0, 1], [1, 0]])  # top row first; (1, 1) invalid
    np.testing.assert_array_equal(s.points[0], [0, 1, 7])
    np.testing.assert_array_equal(s.points[2], [10, -1, 5])
    assert s.meta.extra["texture"] == "tex.png"


def test_lm3_landmarks_attached_to_bnt(tmp_path, cap):
    save_scan(cap, tmp_path / "bs001_E_HAPPY_0.bnt")
    (tmp_path / "bs001_E_HAPPY_0.lm3").write_text(
        "3D landmark file\n2 landmarks:\nNose tip\n  1.5 2.5 -3.5\nChin middle\n  0 -60 -20\n")
    s = load_scan(tmp_path / "bs001_E_HAPPY_0.bnt")
    np.testing.assert_array_equal(s.landmarks["Nose tip"], [1.5, 2.5, -3.5])
    write_lm3(s.landmarks, tmp_path / "copy.lm3")
    assert set(read_lm3(tmp_path / "copy.lm3")) == {"Nose tip", "Chin middle"}


@pytest.mark.parametrize("suffix", ["obj", "off", "stl"])
def test_meshes_through_trimesh(tmp_path, suffix):
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    mesh.export(tmp_path / f"m.{suffix}")
    s = load_scan(tmp_path / f"m.{suffix}")
    assert s.n_points >= len(mesh.vertices) * (0.99 if suffix != "stl" else 0.0)
    np.testing.assert_allclose(np.linalg.norm(s.points, axis=1), 50.0, atol=1e-3)


def test_text_point_clouds(tmp_path):
    (tmp_path / "p.xyz").write_text("# comment\n1 2 3\n4 5 6 7\n")
    (tmp_path / "p.csv").write_text("x,y,z\n1,2,3\n4,5,6\n")
    for name in ("p.xyz", "p.csv"):
        np.testing.assert_array_equal(load_scan(tmp_path / name).points, [[1, 2, 3], [4, 5, 6]])


def test_numpy_depth_map_and_points(tmp_path):
    depth = np.full((4, 5), 10.0)
    depth[1, 1] = np.nan
    np.save(tmp_path / "d.npy", depth)
    s = load_scan(tmp_path / "d.npy")
    assert s.n_points == 19 and s.grid_shape == (4, 5)
    np.savez(tmp_path / "p.npz", points=np.ones((3, 3)))
    assert load_scan(tmp_path / "p.npz").n_points == 3


@pytest.mark.parametrize("content, reason", [
    (b"", "truncated header"),
    (b"480 rows\n640 columns\npixels (flag X Y Z):\n1 2 3\n", "expected"),
    (b"1000000000 rows\n1000 columns\npixels (flag X Y Z):\n", "absurd size"),
    (b"1 rows\n2 columns\npixels (flag X Y Z):\n1 1 a b c d e f\n", "non-numeric"),
    (b"1 rows\n1 columns\npixels (flag X Y Z):\n0 -999999 -999999 -999999\n", "no valid points"),
])
def test_bad_abs_files_name_the_file_and_the_reason(tmp_path, content, reason):
    p = tmp_path / "bad.abs"
    p.write_bytes(content)
    with pytest.raises(ScanFormatError) as e:
        load_scan(p)
    assert str(p) in str(e.value) and reason in str(e.value)


def test_unknown_missing_and_corrupt_gzip(tmp_path):
    with pytest.raises(ScanFormatError, match="unknown scan format"):
        load_scan(tmp_path / "x.foo")
    with pytest.raises(ScanFormatError, match="no such file"):
        load_scan(tmp_path / "missing.abs")
    (tmp_path / "c.abs.gz").write_bytes(gzip.compress(b"2 rows\n2 columns\npixels")[:-5])
    with pytest.raises(ScanFormatError, match="c.abs.gz"):
        load_scan(tmp_path / "c.abs.gz")
