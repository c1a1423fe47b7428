"""Helpers shared by the scan readers: size limits, error wrapping, and checked `FaceScan` construction."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from facerec3d.config import MAX_GRID_SIDE
from facerec3d.errors import ScanFormatError
from facerec3d.scan import FaceScan


def scan_suffix(path: str | Path) -> str:
    """The format suffix of a file name, lower case (`.abs.gz` counts as one suffix)."""
    name = Path(path).name.lower()
    return ".abs.gz" if name.endswith(".abs.gz") else Path(name).suffix


def scan_stem(path: str | Path) -> str:
    """The file name without its format suffix: `02463d452` for `02463d452.abs.gz`."""
    name = Path(path).name
    return name[: len(name) - len(scan_suffix(path))]


MAX_POINTS = MAX_GRID_SIDE**2  # 4,000,000: refuse files announcing more points or pixels than this: a 2000×2000 range image, more
#                          than face scanners and depth cameras deliver, keeps every command under 1 GB of memory
MAX_MESH_BYTES = 64 << 20  # OFF and STL files are parsed whole by trimesh, at ~9× their size (a 55 MB OBJ of
#                            700,000 vertices and 1.4 million triangles peaked at 575 MB when trimesh read OBJ too;
#                            OBJ is now read a record at a time, ~2× its size): larger ones are refused


def describe(error: BaseException) -> str:
    """A short description of a library exception for an error message."""
    text = str(error)
    return f"{type(error).__name__}: {text[:200]}{'...' if len(text) > 200 else ''}"


@contextmanager
def library_errors(path: str | Path, what: str) -> Iterator[None]:
    """Turn any exception a parsing library raises into ScanFormatError('not a readable <what>')."""
    try:
        yield
    except (ScanFormatError, ImportError, MemoryError):  # a missing dependency or memory running out: not a bad file
        raise
    except Exception as e:  # third-party parsers raise many kinds on corrupt input
        raise ScanFormatError(path, f"not a readable {what} ({describe(e)})") from None


@contextmanager
def open_binary(path: str | Path) -> Iterator[BinaryIO]:
    """The file opened for reading bytes; an OSError while it is open becomes ScanFormatError('cannot read')."""
    try:
        with open(path, "rb") as f:
            yield f
    except OSError as e:
        raise ScanFormatError(path, f"cannot read ({describe(e)})") from None


def read_bytes(path: str | Path, max_bytes: int | None = None) -> bytes:
    """The whole file, or ScanFormatError when it cannot be read or is longer than `max_bytes` (when given)."""
    with open_binary(path) as f:
        data = f.read() if max_bytes is None else f.read(max_bytes + 1)
    if max_bytes is not None and len(data) > max_bytes:
        raise ScanFormatError(path, f"absurd size: more than {max_bytes} bytes")
    return data


def check_grid_size(path: str | Path, rows: int, cols: int) -> int:
    """The pixel count rows × cols, refusing empty or absurd sizes."""
    if rows <= 0 or cols <= 0:
        raise ScanFormatError(path, f"bad size {rows}×{cols}")
    if rows * cols > MAX_POINTS:
        raise ScanFormatError(path, f"absurd size {rows}×{cols} (more than {MAX_POINTS} pixels)")
    return rows * cols


def grid_scan(path: str | Path, xyz: np.ndarray, valid: np.ndarray, **fields: Any) -> FaceScan:
    """A grid scan from an (R, C, 3) image of points in mm and an (R, C) validity mask.

    Refuses images without valid pixels and valid pixels with non-finite coordinates.
    """
    check_grid_size(path, *valid.shape)
    if not valid.any():
        raise ScanFormatError(path, "no valid points")
    if not np.isfinite(xyz[valid]).all():
        raise ScanFormatError(path, "non-finite coordinates in valid pixels")
    return FaceScan.from_range_image(xyz, valid, **fields)


def point_scan(
    path: str | Path,
    points: np.ndarray,
    grid: np.ndarray | None = None,
    grid_shape: tuple[int, int] | None = None,
    normals: np.ndarray | None = None,
    mesh: np.ndarray | None = None,
    **fields: Any,
) -> FaceScan:
    """A scan from (N, 3) points in mm (and optional per-point grid positions and normals), checked.

    Refuses empty or non-finite points, grids with positions outside `grid_shape` or
    repeated, and mesh triangles naming a missing vertex; drops normals that are not all finite.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not len(points):
        raise ScanFormatError(path, "no valid points")
    if len(points) > MAX_POINTS:
        raise ScanFormatError(path, f"absurd size: {len(points)} points (more than {MAX_POINTS})")
    if not np.isfinite(points).all():
        raise ScanFormatError(path, "non-finite coordinates")
    if grid is not None:
        rows, cols = grid_shape
        check_grid_size(path, rows, cols)
        grid = np.asarray(grid, dtype=np.int64)
        if (grid < 0).any() or (grid[:, 0] >= rows).any() or (grid[:, 1] >= cols).any():
            raise ScanFormatError(path, f"grid position outside the {rows}×{cols} grid")
        if len(np.unique(grid[:, 0] * cols + grid[:, 1])) != len(grid):
            raise ScanFormatError(path, "two points share a grid position")
    if normals is not None and not np.isfinite(normals).all():
        normals = None
    if mesh is not None:
        mesh = np.asarray(mesh, dtype=np.int64).reshape(-1, 3)
        if len(mesh) > 4 * MAX_POINTS:
            raise ScanFormatError(path, f"absurd size: {len(mesh)} triangles (more than {4 * MAX_POINTS})")
        if len(mesh) and (mesh.min() < 0 or mesh.max() >= len(points)):
            raise ScanFormatError(path, f"a triangle names a vertex outside 0..{len(points) - 1}")
        mesh = mesh if len(mesh) else None
    return FaceScan(points=points, grid=grid, grid_shape=grid_shape, normals=normals, mesh=mesh, **fields)


def range_image(scan: FaceScan, path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (R, C, 3), valid (R, C)) of a scan about to be written as a range image; ValueError without a grid."""
    if scan.grid is None:
        raise ScanFormatError(path, "writing a range-image format needs a scan with a grid")
    return scan.to_range_image()
