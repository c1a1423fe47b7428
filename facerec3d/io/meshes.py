"""Meshes and point clouds: PLY through plyfile, OBJ / OFF / STL through trimesh, and text point clouds.

A PLY written by facerec3d keeps the range-image grid: integer vertex
properties `row` and `col` and a comment `facerec3d grid_shape R C`.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.scan import FaceScan

GRID_COMMENT = "facerec3d grid_shape"


def _checked(path, points: np.ndarray, **fields) -> FaceScan:
    if points.ndim != 2 or points.shape[1] != 3 or not len(points):
        raise ScanFormatError(path, "no valid points")
    if not np.isfinite(points).all():
        raise ScanFormatError(path, "non-finite coordinates")
    return FaceScan(points=points, **fields)


def read_ply(path: str | Path) -> FaceScan:
    """A PLY mesh or point cloud (ASCII or binary), with normals, colours and a facerec3d grid when present."""
    from plyfile import PlyData

    path = Path(path)
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
        names = v.dtype.names
        points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float64) if "nx" in names else None
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8) if "red" in names else None
        grid = grid_shape = None
        shape = [c.split()[2:] for c in ply.comments if c.startswith(GRID_COMMENT)]
        if shape and "row" in names:
            grid_shape = (int(shape[0][0]), int(shape[0][1]))
            grid = np.stack([v["row"], v["col"]], axis=1).astype(np.int64)
            if len(grid) and (grid.min() < 0 or (grid >= np.array(grid_shape)).any()):
                raise ValueError("grid position outside the grid")
    except ScanFormatError:
        raise
    except Exception as e:  # plyfile raises many kinds on corrupt input
        raise ScanFormatError(path, f"not a readable PLY file ({type(e).__name__}: {e})") from None
    if normals is not None and not np.isfinite(normals).all():
        normals = None
    return _checked(path, points, normals=normals, colors=colors, grid=grid, grid_shape=grid_shape)


def write_ply(scan: FaceScan, path: str | Path, binary: bool = True) -> None:
    """Write a scan as PLY: vertices (+ normals, colours, grid) and, for grid scans, the grid triangles."""
    from plyfile import PlyData, PlyElement

    fields = [("x", "f8"), ("y", "f8"), ("z", "f8")]
    columns = [scan.points[:, 0], scan.points[:, 1], scan.points[:, 2]]
    if scan.normals is not None:
        fields += [("nx", "f8"), ("ny", "f8"), ("nz", "f8")]
        columns += list(scan.normals.T)
    if scan.colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        columns += list(np.asarray(scan.colors, np.uint8).T)
    comments = []
    if scan.grid is not None:
        fields += [("row", "i4"), ("col", "i4")]
        columns += [scan.grid[:, 0], scan.grid[:, 1]]
        comments.append(f"{GRID_COMMENT} {scan.grid_shape[0]} {scan.grid_shape[1]}")
    vertex = np.empty(scan.n_points, dtype=fields)
    for (name, _), col in zip(fields, columns):
        vertex[name] = col
    elements = [PlyElement.describe(vertex, "vertex")]
    if scan.grid is not None and scan.n_points:
        tris = scan.triangles()
        face = np.empty(len(tris), dtype=[("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = tris
        elements.append(PlyElement.describe(face, "face"))
    PlyData(elements, text=not binary, comments=comments).write(str(path))


def read_mesh(path: str | Path) -> FaceScan:
    """An OBJ, OFF or STL mesh (its vertices; vertex normals when the file has them)."""
    import trimesh

    path = Path(path)
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
        points = np.asarray(mesh.vertices, dtype=np.float64)
    except Exception as e:  # trimesh raises many kinds on corrupt input
        raise ScanFormatError(path, f"not a readable mesh ({type(e).__name__}: {e})") from None
    return _checked(path, points)


def read_text_points(path: str | Path) -> FaceScan:
    """A text point cloud: x y z (more columns ignored), whitespace or comma separated, `#` comments, optional header."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ScanFormatError(path, f"cannot read ({e})") from None
    lines = [ln.split("#", 1)[0].replace(",", " ").strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if lines and not _numeric(lines[0].split()[0]):
        lines = lines[1:]  # a header of column names
    try:
        rows = [ln.split()[:3] for ln in lines]
        if any(len(r) < 3 for r in rows):
            raise ValueError("a line has fewer than 3 columns")
        points = np.array(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError as e:
        raise ScanFormatError(path, f"bad point data ({e})") from None
    return _checked(path, points)


def _numeric(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False
