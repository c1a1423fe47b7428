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

try:  # python-isal's igzip inflates the same files ~2.5x faster (an FRGC-size .abs.gz: 26 -> 10 ms)
    from isal.igzip import GzipFile as _GzipReader
    from isal.igzip_lib import IsalError as _InflateError
except ImportError:  # pragma: no cover - isal is a dependency; the standard library does the same, slower
    _GzipReader, _InflateError = gzip.GzipFile, zlib.error

import numpy as np
from numba import njit

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import check_grid_size, open_binary, range_image
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
    A token of the same bytes as the one before it (most of a range image: `0` flags, `-999999.000000` for
    the pixels the scanner missed) takes that one's value without being parsed again (17 → 15 ms a scan).
    """
    n, i, size = 0, 0, len(buf)
    last, length, value = 0, 0, 0.0  # the previous token: where it starts, its bytes, its value
    while True:
        while i < size and (buf[i] == 32 or 9 <= buf[i] <= 13):
            i += 1
        if i >= size or n >= len(out):
            return n
        if length and i + length <= size and (i + length == size or buf[i + length] == 32
                                              or 9 <= buf[i + length] <= 13):
            k = 0
            while k < length and buf[i + k] == buf[last + k]:
                k += 1
            if k == length:
                out[n] = value
                n += 1
                last = i
                i += length
                continue
        last = i
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
        value = -value if negative else value
        out[n] = value
        length = i - last
        n += 1


CHUNK = 1 << 20  # bytes of text parsed at a time: memory stays bounded whatever the header or the body holds
WHITESPACE = b" \t\n\r\x0b\x0c"


def read_abs(path: str | Path) -> FaceScan:
    """A FRGC `.abs` / `.abs.gz` range image: points in mm, grid (row, column) of each valid pixel."""
    with open_binary(path) as raw:
        gz = raw.read(2) == GZIP_MAGIC  # trust the content, not the name
        raw.seek(0)
        f = _GzipReader(fileobj=raw) if gz else raw
        try:
            header = [f.readline(MAX_HEADER_LINE) for _ in range(3)]
            if not header[2].endswith(b"\n"):
                raise ScanFormatError(path, "truncated or bad header (need 'R rows', 'C columns', 'pixels ...' lines)")
            rows, cols = _parse_header(path, header)
            n = check_grid_size(path, rows, cols)
            flags, xyz = _read_body(path, f, n, f"{rows}×{cols}")
        except (EOFError, zlib.error, _InflateError, gzip.BadGzipFile) as e:
            raise ScanFormatError(path, f"corrupt or truncated gzip data ({e})") from None
    return _valid_pixels(path, xyz.reshape(3, n), flags, rows, cols)


def _valid_pixels(path: str | Path, blocks: np.ndarray, flags: np.ndarray, rows: int, cols: int) -> FaceScan:
    """The scan of the flagged pixels of the X, Y, Z blocks (3, rows·cols), in row-major order: what `grid_scan`
    makes of the (rows, cols, 3) image, without that image (a third of an FRGC-size scan's reading time)."""
    at = np.flatnonzero(flags)
    if not len(at):
        raise ScanFormatError(path, "no valid points")
    points = blocks[:, at].T
    if not np.isfinite(points).all():
        raise ScanFormatError(path, "non-finite coordinates in valid pixels")
    return FaceScan(points, grid=np.stack(np.divmod(at, cols), axis=1), grid_shape=(rows, cols))


def _read_body(path: str | Path, f, n: int, size: str) -> tuple[np.ndarray, np.ndarray]:
    """(valid flags (n,), X, Y, Z blocks (3, n)) streamed from the body, CHUNK bytes at a time, so that a header
    announcing more pixels than the body holds, or a body of garbage, is refused without reading it all."""
    flags = np.empty(n, dtype=bool)
    xyz = np.empty(3 * n)
    limit = 4 * n * MAX_VALUE_CHARS
    filled, consumed, carry, bad_flags = 0, 0, b"", False
    while True:
        data = f.read(CHUNK)
        consumed += len(data)
        if consumed > limit:
            raise ScanFormatError(path, f"far more data than {size} pixels need")
        text = carry + data
        cut = max(text.rfind(c) for c in WHITESPACE) + 1 if data else len(text)  # the last token may go on
        text, carry = text[:cut], text[cut:]
        if len(carry) > MAX_VALUE_CHARS:
            raise ScanFormatError(path, "non-numeric value in the pixel data")
        values = _parse_text(path, text)
        if filled + len(values) > 4 * n:
            raise ScanFormatError(path, f"expected {4 * n} values for {size} pixels, found more")
        head = values[: max(n - filled, 0)]  # the flags' share of this chunk
        bad_flags |= not np.isin(head, (0.0, 1.0)).all()
        flags[filled : filled + len(head)] = head == 1.0
        rest = values[len(head) :]  # and the X, Y, Z blocks'
        start = max(filled - n, 0)
        xyz[start : start + len(rest)] = rest
        filled += len(values)
        if not data:
            break
    if filled != 4 * n:
        raise ScanFormatError(path, f"expected {4 * n} values for {size} pixels, found {filled}")
    if bad_flags:
        raise ScanFormatError(path, "flags must be 0 or 1")
    return flags, xyz


def _parse_text(path: str | Path, text: bytes) -> np.ndarray:
    """The whitespace-separated numbers of a piece of the body (the fast parser, else NumPy's)."""
    values = np.empty(len(text) // 2 + 1)
    count = _parse_decimals(np.frombuffer(text, dtype=np.uint8), values)
    if count >= 0:
        return values[:count]
    try:  # a token the fast parser does not read exactly (exponent, > 15 digits, or not a number)
        return np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise ScanFormatError(path, "non-numeric value in the pixel data") from None


def _format(values: np.ndarray, fmt: str) -> str:
    """Values joined by spaces, each written with a %-format."""
    return " ".join([fmt] * len(values)) % tuple(values.tolist())


def write_abs(scan: FaceScan, path: str | Path) -> None:
    """Write a grid scan as FRGC `.abs` (gzip-compressed when the name ends in `.gz`); values to 1e-6 mm."""
    xyz, valid = range_image(scan, path)
    rows, cols = valid.shape
    xyz = np.where(valid[..., None], xyz, INVALID)
    blocks = [(valid.ravel().astype(int), "%d")] + [(xyz[..., k].ravel(), "%.6f") for k in range(3)]
    gz = str(path).lower().endswith(".gz")
    with gzip.open(path, "wb", compresslevel=6) if gz else open(path, "wb") as f:
        f.write(f"{rows} rows\n{cols} columns\npixels (flag X Y Z):".encode("ascii"))
        for values, fmt in blocks:  # written a piece at a time: memory stays small whatever the size
            for start in range(0, len(values), CHUNK // 16):
                f.write((" " if start else "\n").encode("ascii")
                        + _format(values[start : start + CHUNK // 16], fmt).encode("ascii"))
        f.write(b"\n")
