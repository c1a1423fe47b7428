"""Bosphorus range images (`.bnt`) and landmark files (`.lm3`).

`.bnt`, little-endian: uint16 rows, uint16 columns, float64 zmin, uint16
name length L, L bytes of texture file name, uint32 N = rows·columns·5, then
N float64 in five blocks X, Y, Z, u, v (one value per pixel each, row-major,
rows stored bottom-up). A pixel whose Z equals zmin is invalid. Units are mm.

`.lm3`: a title line, a count line `N landmarks:`, then N pairs of a name
line and an `x y z` line (mm, the frame of the `.bnt` points). Blank lines
and `#` comment lines are ignored.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import check_grid_size, grid_scan, open_binary, range_image, read_bytes
from facerec3d.scan import FaceScan, ScanMeta

HEADER = struct.Struct("<HHdH")  # rows, columns, zmin, texture name length
COUNT = struct.Struct("<I")
INVALID_Z = -1e9  # the zmin of the real Bosphorus files
MAX_LM3_BYTES = 1 << 20  # a landmark file holds a few dozen lines
LM3_COUNT_LINE = re.compile(r"([0-9]+)\s+landmarks?:?", re.IGNORECASE)


def _read_exact(f, size: int, path: str | Path) -> bytes:
    data = f.read(size)
    if len(data) != size:
        raise ScanFormatError(path, "truncated header")
    return data


def read_bnt(path: str | Path) -> FaceScan:
    """A Bosphorus `.bnt` range image (grid row 0 at the top), with the landmarks of a sibling `.lm3` file.

    The texture file name goes to `meta.extra['texture']`; the u, v texture coordinates are dropped.
    """
    with open_binary(path) as f:
        rows, cols, zmin, name_len = HEADER.unpack(_read_exact(f, HEADER.size, path))
        texture = _read_exact(f, name_len, path).decode("latin-1")
        (count,) = COUNT.unpack(_read_exact(f, COUNT.size, path))
        n = check_grid_size(path, rows, cols)
        if count != 5 * n:
            raise ScanFormatError(path, f"header says {count} values, {rows}×{cols} pixels need {5 * n}")
        body = f.read(8 * count + 1)
    if len(body) != 8 * count:
        raise ScanFormatError(path, f"expected {8 * count} bytes of point data, found {len(body)}")
    if not np.isfinite(zmin):
        raise ScanFormatError(path, f"bad zmin {zmin}")
    blocks = np.frombuffer(body, dtype="<f8").reshape(5, rows, cols)[:, ::-1]  # stored bottom-up
    xyz = np.moveaxis(blocks[:3], 0, -1)
    scan = grid_scan(path, xyz, xyz[..., 2] != zmin, meta=ScanMeta(extra={"texture": texture}))
    lm3 = Path(path).with_suffix(".lm3")
    return scan.replace(landmarks=load_landmarks_lm3(lm3)) if lm3.is_file() else scan


def write_bnt(scan: FaceScan, path: str | Path, texture_name: str = "") -> None:
    """Write a grid scan as Bosphorus `.bnt` (u, v written as 0) and its landmarks, if any, as a sibling `.lm3`.

    Invalid pixels get X = Y = Z = zmin = -1e9 mm (lower still if a valid Z is not above that). A scan without
    landmarks removes a `.lm3` already beside the path: read_bnt would give it another scan's landmarks.
    """
    xyz, valid = range_image(scan, path)
    rows, cols = valid.shape
    if max(rows, cols) > 0xFFFF:
        raise ScanFormatError(path, f"a .bnt grid is at most 65535×65535, not {rows}×{cols}")
    zmin = min(INVALID_Z, float(xyz[valid][:, 2].min(initial=np.inf)) - 1.0)
    blocks = np.zeros((5, rows, cols))
    blocks[:3] = np.moveaxis(np.where(valid[..., None], xyz, zmin), -1, 0)
    name = texture_name.encode("latin-1")
    header = HEADER.pack(rows, cols, zmin, len(name)) + name + COUNT.pack(blocks.size)
    with open(path, "wb") as f:
        f.write(header)
        np.ascontiguousarray(blocks[:, ::-1], dtype="<f8").tofile(f)
    lm3 = Path(path).with_suffix(".lm3")
    if scan.landmarks:
        write_lm3(scan.landmarks, lm3)
    else:
        lm3.unlink(missing_ok=True)


def load_landmarks_lm3(path: str | Path) -> dict[str, np.ndarray]:
    """Bosphorus `.lm3` landmarks: name -> (3,) float64 position in mm. ScanFormatError if malformed."""
    lines = [line.strip() for line in read_bytes(path, MAX_LM3_BYTES).decode("latin-1").splitlines()]
    lines = [line for line in lines if line and not line.startswith("#")]
    start = next((i for i, line in enumerate(lines[:2]) if LM3_COUNT_LINE.fullmatch(line)), None)
    if start is None:
        raise ScanFormatError(path, "bad .lm3 file: no 'N landmarks:' line at the top")
    count = int(LM3_COUNT_LINE.fullmatch(lines[start])[1])
    body = lines[start + 1 :]
    if len(body) != 2 * count:
        raise ScanFormatError(path, f"bad .lm3 file: {count} landmarks announced, {len(body)} lines follow")
    landmarks: dict[str, np.ndarray] = {}
    for name, coords in zip(body[0::2], body[1::2]):
        try:
            v = np.array(coords.split(), dtype=np.float64)
        except ValueError:
            v = np.empty(0)
        if v.shape != (3,) or not np.isfinite(v).all():
            raise ScanFormatError(path, f"bad .lm3 file: bad coordinates {coords[:80]!r} for {name[:80]!r}")
        if name in landmarks:
            raise ScanFormatError(path, f"bad .lm3 file: landmark {name[:80]!r} given twice")
        landmarks[name] = v
    return landmarks


def write_lm3(landmarks: dict[str, np.ndarray], path: str | Path) -> None:
    """Write landmarks (name -> position in mm) as a Bosphorus `.lm3` file, to 1e-6 mm."""
    lines = ["3D landmark file", f"{len(landmarks)} landmarks:"]
    for name, v in landmarks.items():
        lines += [name, "  " + " ".join(f"{x:.6f}" for x in np.asarray(v, dtype=np.float64).reshape(3))]
    Path(path).write_text("\n".join(lines) + "\n", encoding="latin-1")
