"""FRGC v2 range images: `.abs` and gzip-compressed `.abs.gz`.

Three header lines `R rows`, `C columns`, `pixels (flag X Y Z):`, then R·C
flags (1 valid, 0 invalid), then R·C X, R·C Y and R·C Z values, each block
row-major and whitespace separated (line breaks anywhere). Invalid pixels hold
-999999. Units are mm in the scanner's camera frame (Z < 0); points are kept
in that frame. Compressed files are recognised by their content, whatever
their name.
"""

from __future__ import annotations

import gzip
import zlib
from pathlib import Path

import numpy as np
from numba import njit

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import check_grid_size, grid_scan, open_binary, range_image
from facerec3d.scan import FaceScan

INVALID = -999999.0
MAX_HEADER_LINE = 256  # bytes
GZIP_MAGIC = b"\x1f\x8b"
MAX_VALUE_CHARS = 64  # average bytes per value (with separator) beyond which the body is refused


def _parse_header(path: str | Path, lines: list[bytes]) -> tuple[int, int]:
    """(rows, columns) from the three header lines."""
    words = [line.split() for line in lines]
    try:
        if words[0][1:] != [b"rows"] or words[1][1:] != [b"columns"] or not lines[2].lstrip().startswith(b"pixels"):
            raise ValueError
        return int(words[0][0]), int(words[1][0])
    except (ValueError, IndexError):
        raise ScanFormatError(path, "bad header (need 'R rows', 'C columns', 'pixels (flag X Y Z):')") from None


_POW10 = 10.0 ** np.arange(16)


@njit(cache=True)
def _parse_decimals(buf, out):  # pragma: no cover - compiled
    """Whitespace-separated plain decimals (`-12.345678`, at most 15 digits) from ASCII bytes into `out`.

    Returns the number of values (stopping one past the size of `out`), or −1 at a token it cannot read
    exactly (an exponent, more digits, anything else): the caller then parses the text with NumPy. Each
    value is mantissa / 10^k of exactly representable doubles, so it is the correctly rounded one, as strtod's.
    """
    n, i, size = 0, 0, len(buf)
    while True:
        while i < size and (buf[i] == 32 or 9 <= buf[i] <= 13):
            i += 1
        if i >= size or n >= len(out):
            return n
        negative = buf[i] == 45
        if buf[i] == 45 or buf[i] == 43:
            i += 1
        mantissa, digits, decimals, dot = 0, 0, 0, False
        while i < size:
            c = buf[i]
            if 48 <= c <= 57:
                mantissa = mantissa * 10 + (c - 48)
                digits += 1
                decimals += dot
            elif c == 46 and not dot:
                dot = True
            else:
                break
            i += 1
        if digits == 0 or digits > 15 or (i < size and not (buf[i] == 32 or 9 <= buf[i] <= 13)):
            return -1
        value = mantissa / _POW10[decimals]
        out[n] = -value if negative else value
        n += 1


def read_abs(path: str | Path) -> FaceScan:
    """A FRGC `.abs` / `.abs.gz` range image: points in mm, grid (row, column) of each valid pixel."""
    with open_binary(path) as raw:
        gz = raw.read(2) == GZIP_MAGIC  # trust the content, not the name
        raw.seek(0)
        f = gzip.GzipFile(fileobj=raw) if gz else raw
        try:
            header = [f.readline(MAX_HEADER_LINE) for _ in range(3)]
            if not header[2].endswith(b"\n"):
                raise ScanFormatError(path, "truncated or bad header (need 'R rows', 'C columns', 'pixels ...' lines)")
            rows, cols = _parse_header(path, header)
            n = check_grid_size(path, rows, cols)
            limit = 4 * n * MAX_VALUE_CHARS
            body = f.read(limit + 1)
        except (EOFError, zlib.error, gzip.BadGzipFile) as e:
            raise ScanFormatError(path, f"corrupt or truncated gzip data ({e})") from None
    if len(body) > limit:
        raise ScanFormatError(path, f"far more data than {rows}×{cols} pixels need")
    values = np.empty(4 * n + 1)
    count = _parse_decimals(np.frombuffer(body, dtype=np.uint8), values)
    if count >= 0:
        values = values[:count]
    else:  # a token the fast parser does not read exactly (exponent, > 15 digits, or not a number)
        try:
            values = np.array(body.split(), dtype=np.float64)
        except ValueError:
            raise ScanFormatError(path, "non-numeric value in the pixel data") from None
    if len(values) != 4 * n:
        raise ScanFormatError(path, f"expected {4 * n} values for {rows}×{cols} pixels, found {len(values)}")
    flags = values[:n].reshape(rows, cols)
    if not np.isin(flags, (0.0, 1.0)).all():
        raise ScanFormatError(path, "flags must be 0 or 1")
    xyz = np.moveaxis(values[n:].reshape(3, rows, cols), 0, -1)
    return grid_scan(path, xyz, flags == 1.0)


def _format(values: np.ndarray, fmt: str) -> str:
    """Values joined by spaces, each written with a %-format."""
    return " ".join([fmt] * len(values)) % tuple(values.tolist())


def write_abs(scan: FaceScan, path: str | Path) -> None:
    """Write a grid scan as FRGC `.abs` (gzip-compressed when the name ends in `.gz`); values to 1e-6 mm."""
    xyz, valid = range_image(scan, path)
    rows, cols = valid.shape
    xyz = np.where(valid[..., None], xyz, INVALID)
    parts = [f"{rows} rows\n{cols} columns\npixels (flag X Y Z):", _format(valid.ravel().astype(int), "%d")]
    parts += [_format(xyz[..., k].ravel(), "%.6f") for k in range(3)]
    data = ("\n".join(parts) + "\n").encode("ascii")
    Path(path).write_bytes(gzip.compress(data, compresslevel=6) if str(path).lower().endswith(".gz") else data)
