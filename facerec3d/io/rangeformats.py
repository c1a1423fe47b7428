"""Range-image formats of the public 3D face databases, read and written by hand (no library knows them).

FRGC v2 `.abs` (and `.abs.gz`): three header lines `R rows`, `C columns`,
`pixels (flag X Y Z):`, then R·C flags, then R·C X, Y and Z values, row-major;
invalid pixels have flag 0 and value -999999; mm, camera frame (Z < 0).

Bosphorus `.bnt`: little-endian uint16 rows, uint16 cols, float64 zmin,
uint16 name length, the texture file name, uint32 N = rows·cols·5, then N
float64 in five column blocks X, Y, Z, u, v; rows stored bottom-up; a point
whose Z equals zmin is invalid. Landmarks in a sibling `.lm3` text file.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.scan import FaceScan, ScanMeta

MAX_PIXELS = 20_000_000  # refuse headers promising more than this (absurd sizes)
ABS_INVALID = -999999.0
BNT_INVALID = -1e9


def _grid_scan(path, xyz: np.ndarray, valid: np.ndarray, **fields) -> FaceScan:
    """A grid scan from an (R, C, 3) image, refusing empty and non-finite data."""
    if not valid.any():
        raise ScanFormatError(path, "no valid points")
    if not np.isfinite(xyz[valid]).all():
        raise ScanFormatError(path, "non-finite coordinates in valid pixels")
    return FaceScan.from_range_image(xyz, valid, **fields)


def _pixels(path, rows: int, cols: int) -> int:
    if rows <= 0 or cols <= 0:
        raise ScanFormatError(path, f"bad size {rows}×{cols}")
    if rows * cols > MAX_PIXELS:
        raise ScanFormatError(path, f"absurd size {rows}×{cols} (more than {MAX_PIXELS} pixels)")
    return rows * cols


# ------------------------------------------------------------------- FRGC .abs
def read_abs(path: str | Path) -> FaceScan:
    """A FRGC v2 `.abs` or `.abs.gz` range image."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        if path.name.lower().endswith(".gz"):
            raw = gzip.decompress(raw)
        text = raw.decode("ascii")
    except (OSError, EOFError, zlib.error, gzip.BadGzipFile) as e:
        raise ScanFormatError(path, f"cannot read ({e})") from None
    except UnicodeDecodeError:
        raise ScanFormatError(path, "not an ASCII .abs file") from None
    lines = text.split("\n", 3)
    if len(lines) < 4:
        raise ScanFormatError(path, "truncated header (need 'R rows', 'C columns', 'pixels ...' lines)")
    try:
        rows_word = lines[0].split()
        cols_word = lines[1].split()
        if rows_word[1:2] != ["rows"] or cols_word[1:2] != ["columns"] or not lines[2].strip().startswith("pixels"):
            raise ValueError
        rows, cols = int(rows_word[0]), int(cols_word[0])
    except (ValueError, IndexError):
        raise ScanFormatError(path, "bad header (need 'R rows', 'C columns', 'pixels (flag X Y Z):')") from None
    n = _pixels(path, rows, cols)
    try:
        values = np.array(lines[3].split(), dtype=np.float64)
    except ValueError:
        raise ScanFormatError(path, "non-numeric value in the pixel data") from None
    if len(values) != 4 * n:
        raise ScanFormatError(path, f"expected {4 * n} values for {rows}×{cols} pixels, found {len(values)}")
    flags = values[:n].reshape(rows, cols)
    if not np.isin(flags, (0.0, 1.0)).all():
        raise ScanFormatError(path, "flags must be 0 or 1")
    xyz = np.stack([values[n * (k + 1) : n * (k + 2)].reshape(rows, cols) for k in range(3)], axis=-1)
    return _grid_scan(path, xyz, flags == 1.0)


def write_abs(scan: FaceScan, path: str | Path) -> None:
    """Write a grid scan as FRGC `.abs` (gzip-compressed if the name ends in `.gz`)."""
    if scan.grid is None:
        raise ValueError("writing .abs needs a range-image grid")
    xyz, valid = scan.to_range_image()
    rows, cols = scan.grid_shape
    parts = [f"{rows} rows\n{cols} columns\npixels (flag X Y Z):\n", " ".join("1" if v else "0" for v in valid.ravel()), "\n"]
    for k in range(3):
        channel = np.where(valid, xyz[..., k], ABS_INVALID).ravel()
        text = np.char.mod("%.6f", channel)
        text[~valid.ravel()] = "-999999"
        parts += [" ".join(text.tolist()), "\n"]
    data = "".join(parts).encode("ascii")
    path = Path(path)
    path.write_bytes(gzip.compress(data, compresslevel=6) if path.name.lower().endswith(".gz") else data)


# ------------------------------------------------------------- Bosphorus .bnt
def read_bnt(path: str | Path) -> FaceScan:
    """A Bosphorus `.bnt` range image (with landmarks from a sibling `.lm3` file, when there is one)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ScanFormatError(path, f"cannot read ({e})") from None
    try:
        rows, cols, zmin, name_len = struct.unpack_from("<HHdH", raw, 0)
        offset = 14 + name_len
        texture = raw[14:offset].decode("latin-1")
        (n,) = struct.unpack_from("<I", raw, offset)
    except struct.error:
        raise ScanFormatError(path, "truncated header") from None
    pixels = _pixels(path, rows, cols)
    if n != 5 * pixels:
        raise ScanFormatError(path, f"header says {n} values, {rows}×{cols} pixels need {5 * pixels}")
    body = raw[offset + 4 :]
    if len(body) != 8 * n:
        raise ScanFormatError(path, f"expected {8 * n} bytes of point data, found {len(body)}")
    data = np.frombuffer(body, dtype="<f8").reshape(5, rows, cols)[:, ::-1]  # stored bottom-up
    xyz = np.ascontiguousarray(np.moveaxis(data[:3], 0, -1))
    valid = xyz[..., 2] != zmin
    lm = path.with_suffix(".lm3")
    landmarks = read_lm3(lm) if lm.is_file() else {}
    return _grid_scan(path, xyz, valid, landmarks=landmarks, meta=ScanMeta(extra={"texture": texture}))


def write_bnt(scan: FaceScan, path: str | Path, texture_name: str = "") -> None:
    """Write a grid scan as Bosphorus `.bnt` (invalid pixels at zmin = -1e9; u, v written as 0)."""
    if scan.grid is None:
        raise ValueError("writing .bnt needs a range-image grid")
    xyz, valid = scan.to_range_image()
    rows, cols = scan.grid_shape
    blocks = np.zeros((5, rows, cols))
    blocks[:3] = np.moveaxis(np.where(valid[..., None], xyz, BNT_INVALID), -1, 0)
    name = texture_name.encode("latin-1")
    header = struct.pack("<HHdH", rows, cols, BNT_INVALID, len(name)) + name + struct.pack("<I", 5 * rows * cols)
    Path(path).write_bytes(header + blocks[:, ::-1].astype("<f8").tobytes())


def read_lm3(path: str | Path) -> dict[str, np.ndarray]:
    """Bosphorus `.lm3` landmarks: name -> (3,) position in mm."""
    path = Path(path)
    try:
        lines = [ln.strip() for ln in path.read_text(encoding="latin-1").splitlines() if ln.strip()]
        count = int(lines[1].split()[0])
        body = lines[2 : 2 + 2 * count]
        if len(body) != 2 * count:
            raise ValueError(f"{count} landmarks announced, {len(body) // 2} found")
        out = {}
        for name, coords in zip(body[0::2], body[1::2]):
            v = np.array(coords.split(), dtype=np.float64)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"bad coordinates for {name!r}")
            out[name] = v
        return out
    except (OSError, ValueError, IndexError) as e:
        raise ScanFormatError(path, f"bad .lm3 landmark file ({e})") from None


def write_lm3(landmarks: dict[str, np.ndarray], path: str | Path) -> None:
    """Write landmarks as a Bosphorus `.lm3` file."""
    lines = ["3D landmark file", f"{len(landmarks)} landmarks:"]
    for name, v in landmarks.items():
        lines += [name, "  " + " ".join(f"{x:.6f}" for x in np.asarray(v, float))]
    Path(path).write_text("\n".join(lines) + "\n", encoding="latin-1")
