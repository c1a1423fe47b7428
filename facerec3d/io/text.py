"""Text point clouds (`.xyz`, `.csv`, `.txt`): one point per line, x y z in mm.

Columns are separated by whitespace or commas; columns after the third are
ignored; `#` starts a comment; a first line of column names is skipped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import point_scan, read_bytes
from facerec3d.scan import FaceScan


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_text_points(path: str | Path) -> FaceScan:
    """A text point cloud (see the module docstring)."""
    text = read_bytes(path).decode("utf-8-sig", errors="replace")
    rows = [line.split("#", 1)[0].replace(",", " ").split() for line in text.splitlines()]
    rows = [row for row in rows if row]
    if rows and not _is_number(rows[0][0]):
        rows = rows[1:]  # a header of column names
    short = next((row for row in rows if len(row) < 3), None)
    if short is not None:
        raise ScanFormatError(path, f"a line has fewer than 3 columns: {' '.join(short)[:80]!r}")
    try:
        points = np.array([row[:3] for row in rows], dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise ScanFormatError(path, "non-numeric value in the point data") from None
    return point_scan(path, points)
