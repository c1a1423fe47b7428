"""Fuzzing: every reader, fed truncated, flipped or garbled files, returns a valid scan or raises ScanFormatError."""

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facerec3d import FaceScan, ScanFormatError
from facerec3d.io import load_scan, save_scan
from facerec3d.io.meshes import write_ply
from tests.conftest import cap_image

FORMATS = ["abs", "abs.gz", "bnt", "ply", "ascii.ply", "npz", "xyz", "obj"]


def seed_bytes(fmt: str, tmp) -> bytes:
    scan = cap_image(6, 8, invalid=((0, 0), (3, 4)))
    path = tmp / f"seed.{fmt}"
    if fmt == "ascii.ply":
        write_ply(scan, path, binary=False)
    elif fmt == "xyz":
        path.write_text("\n".join(" ".join(f"{v:.3f}" for v in p) for p in scan.points))
    elif fmt == "obj":
        trimesh.Trimesh(scan.points, scan.triangles()).export(path)
    else:
        save_scan(scan, path)
    return path.read_bytes()


mutations = st.lists(
    st.tuples(st.sampled_from(["truncate", "flip", "insert"]), st.floats(0, 1), st.integers(0, 255)),
    min_size=1, max_size=4,
)


@pytest.mark.parametrize("fmt", FORMATS)
def test_reader_survives_mutations(fmt, tmp_path_factory):
    tmp = tmp_path_factory.mktemp(fmt.replace(".", "_"))
    original = seed_bytes(fmt, tmp)

    @settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(mutations)
    def check(ops):
        data = bytearray(original)
        for op, where, byte in ops:
            i = int(where * max(len(data) - 1, 0))
            if op == "truncate":
                del data[i:]
            elif op == "flip" and data:
                data[i] ^= byte or 1
            else:
                data[i:i] = bytes([byte]) * 3
        path = tmp / f"fuzz.{fmt}"
        path.write_bytes(bytes(data))
        try:
            scan = load_scan(path)
        except ScanFormatError as e:
            assert str(path) in str(e)
            return
        assert isinstance(scan, FaceScan) and scan.n_points > 0
        assert np.isfinite(scan.points).all()

    check()
