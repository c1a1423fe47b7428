"""Fuzzing: every reader, fed truncated, bit-flipped or garbled files, returns a sound scan or raises ScanFormatError."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facerec3d import FaceScan, ScanFormatError
from facerec3d.io import load_landmarks_lm3, load_scan, save_scan, write_lm3, write_ply
from tests.conftest import cap_image

FORMATS = ["abs", "abs.gz", "bnt", "ply", "ascii.ply", "npy", "npz", "xyz", "csv", "obj", "off", "stl", "lm3"]


def write_seed(fmt: str, path) -> None:
    """A valid small file of the format: a 12×16 range image with invalid pixels (or its points, mesh, landmarks)."""
    scan = cap_image(12, 16)
    if fmt == "ascii.ply":
        write_ply(scan.replace(normals=np.tile([0.0, 0.0, 1.0], (scan.n_points, 1))), path, binary=False)
    elif fmt == "npy":
        np.save(path, scan.to_range_image()[0])
    elif fmt in ("xyz", "csv"):
        sep = "," if fmt == "csv" else " "
        path.write_text("x,y,z\n" * (fmt == "csv") + "\n".join(sep.join(f"{v:.3f}" for v in p) for p in scan.points))
    elif fmt in ("obj", "off", "stl"):
        trimesh.Trimesh(scan.points, scan.triangles(), process=False).export(path)
    elif fmt == "lm3":
        write_lm3({f"landmark {i}": p for i, p in enumerate(scan.points[:5])}, path)
    else:
        save_scan(scan, path)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seeds")
    out = {}
    for fmt in FORMATS:
        write_seed(fmt, folder / f"seed.{fmt}")
        out[fmt] = (folder / f"seed.{fmt}").read_bytes()
    return out


def test_seeds_are_valid(seeds, tmp_path):
    for fmt, data in seeds.items():
        (tmp_path / f"s.{fmt}").write_bytes(data)
        if fmt == "lm3":
            assert len(load_landmarks_lm3(tmp_path / f"s.{fmt}")) == 5
        else:
            assert load_scan(tmp_path / f"s.{fmt}").n_points > 100


mutations = st.lists(
    st.one_of(
        st.tuples(st.just("truncate"), st.floats(0, 1)),
        st.tuples(st.just("flip"), st.floats(0, 1), st.integers(1, 255)),
        st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=8)),
    ),
    min_size=1,
    max_size=4,
)


def mutate(data: bytes, ops) -> bytes:
    data = bytearray(data)
    for op, where, *arg in ops:
        i = int(where * max(len(data) - 1, 0))
        if op == "truncate":
            del data[i:]
        elif op == "flip" and data:
            data[i] ^= arg[0]
        elif op == "insert":
            data[i:i] = arg[0]
    return bytes(data)


@pytest.mark.parametrize("fmt", FORMATS)
@given(ops=mutations)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_reader_survives_mutations(seeds, tmp_path, fmt, ops):
    path = tmp_path / f"fuzz.{fmt}"
    path.write_bytes(mutate(seeds[fmt], ops))
    try:
        result = load_landmarks_lm3(path) if fmt == "lm3" else load_scan(path)
    except ScanFormatError as e:
        assert str(e).startswith(str(path))
        return
    if fmt == "lm3":
        assert all(v.shape == (3,) and np.isfinite(v).all() for v in result.values())
        return
    assert isinstance(result, FaceScan) and result.n_points > 0
    assert np.isfinite(result.points).all()
    if result.grid is not None:
        assert ((result.grid >= 0) & (result.grid < result.grid_shape)).all()
