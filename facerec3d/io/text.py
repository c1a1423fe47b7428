"""Text point clouds (`.xyz`, `.csv`, `.txt`): one point per line, x y z in mm.

Columns are separated by whitespace or commas; columns after the third are
ignored; `#` starts a comment; a first line of column names is skipped.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import MAX_POINTS, open_binary, point_scan
from facerec3d.scan import FaceScan


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


MAX_LINE = 4096  # characters in one line: a point needs a few dozen
CHUNK_LINES = 65536  # lines parsed at a time
GZIP_MAGIC = b"\x1f\x8b"
CONTROL = bytes(set(range(32)) - set(b"\t\n\v\f\r")) + b"\x7f"  # bytes no text point file holds


def _check_text(path: str | Path, head: bytes) -> None:
    """Refuse a file whose first bytes `head` are not text (compressed or binary data), before its lines are
    parsed (and quoted in messages)."""
    if head.startswith(GZIP_MAGIC):
        raise ScanFormatError(path, "not a text point file (gzip-compressed data: decompress it first)")
    if any(b in CONTROL for b in head):
        raise ScanFormatError(path, "not a text point file (binary data)")


def read_text_points(path: str | Path) -> FaceScan:
    """A text point cloud (see the module docstring), read a block of lines at a time: a line longer than
    MAX_LINE characters, or more than MAX_POINTS points, is refused as soon as it is met."""
    blocks, count, first = [], 0, True
    with open_binary(path) as raw, io.TextIOWrapper(raw, encoding="utf-8-sig", errors="replace") as f:
        _check_text(path, raw.peek(MAX_LINE)[:MAX_LINE])
        while True:
            rows = []
            while len(rows) < CHUNK_LINES:
                line = f.readline(MAX_LINE + 1)
                if not line:
                    break
                if len(line) > MAX_LINE:
                    raise ScanFormatError(path, f"a line is longer than {MAX_LINE} characters")
                row = line.split("#", 1)[0].replace(",", " ").split()[:4]
                if not row:
                    continue
                if first and not _is_number(row[0]):
                    first = False
                    continue  # a header of column names
                first = False
                if len(row) < 3:
                    raise ScanFormatError(path, f"a line has fewer than 3 columns: {' '.join(row)[:80]!r}")
                rows.append(row[:3])
            if not rows:
                break
            count += len(rows)
            if count > MAX_POINTS:
                raise ScanFormatError(path, f"absurd size: more than {MAX_POINTS} points")
            try:
                blocks.append(np.array(rows, dtype=np.float64))
            except ValueError:
                raise ScanFormatError(path, "non-numeric value in the point data") from None
    points = np.concatenate(blocks) if blocks else np.zeros((0, 3))
    return point_scan(path, points)
