"""Meshes and point clouds: PLY through plyfile (read and write), OBJ / OFF / STL through trimesh (read).

Vertices become the scan's points (mm). A mesh's triangles are kept (`FaceScan.mesh`, polygons fanned into
triangles) when it has no range-image grid, so preprocessing rasterises the surface, not only its vertices; a grid
scan is re-triangulated from its grid. A PLY written here keeps the range-image grid:
integer vertex properties `row` and `col` and a header comment
`facerec3d grid_shape R C`.
"""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import numpy as np

from facerec3d.errors import ScanFormatError
from facerec3d.io.common import MAX_MESH_BYTES, MAX_POINTS, library_errors, open_binary, point_scan, read_bytes
from facerec3d.scan import FaceScan

GRID_COMMENT = "facerec3d grid_shape"
PLY_ELEMENT_LINE = re.compile(rb"^element\s+(\S+)\s+(\S+)", re.MULTILINE)
MAX_PLY_HEADER = 65536  # bytes
TRIANGLES = {"face": {"vertex_indices": 3, "vertex_index": 3}}  # lets plyfile memory-map triangle lists


def _check_ply_header(path: str | Path) -> None:
    """Refuse a file without PLY header, or whose header announces more elements than the file has bytes, more
    than MAX_POINTS vertices or more than 4 × MAX_POINTS of any other element (a grid of MAX_POINTS pixels has
    fewer than 2 × MAX_POINTS triangles).

    This runs before plyfile, which allocates whatever the header announces.
    """
    with open_binary(path) as f:
        head = f.read(MAX_PLY_HEADER)
        size = f.seek(0, 2)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ScanFormatError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    for name, count in PLY_ELEMENT_LINE.findall(head[:end]):
        name, count = name[:20].decode(errors="replace"), count[:20].decode(errors="replace")
        if not (count.isascii() and count.isdigit()):  # "²" is a digit to str.isdigit, not to int()
            raise ScanFormatError(path, f"bad PLY header: the count of element {name!r} is {count!r}, not a number")
        if int(count) > size:
            raise _truncated(path, name, count, f"fewer ({size} bytes in all)")
        most = MAX_POINTS if name == "vertex" else 4 * MAX_POINTS
        if int(count) > most:
            raise ScanFormatError(path, f"absurd size: {int(count)} {name} elements (more than {most})")


def _truncated(path: str | Path, name: str, count: int | str, holds: str) -> ScanFormatError:
    """The error of a PLY file that ends before the `count` `name` elements its header promises (it `holds` ...)."""
    what = "vertices" if name == "vertex" else f"{name} elements"
    return ScanFormatError(path, f"truncated PLY: header promises {count} {what}, the file holds {holds}")


def _read_ply_elementwise(path: str | Path):
    """plyfile's reading element by element (any polygons); a file that ends early is a ScanFormatError saying so."""
    from plyfile import PlyData, PlyElementParseError

    try:
        return PlyData.read(str(path))
    except PlyElementParseError as e:
        if e.message != "early end-of-file" or e.element is None:
            raise
        raise _truncated(path, e.element.name, e.element.count, f"only {e.row}") from None


def _stack(vertex: np.ndarray, names: tuple[str, str, str], dtype) -> np.ndarray | None:
    """The (N, 3) array of three vertex properties, or None when the file lacks them."""
    if not set(names) <= set(vertex.dtype.names):
        return None
    return np.stack([vertex[name] for name in names], axis=1).astype(dtype)


def read_ply(path: str | Path) -> FaceScan:
    """A PLY mesh or point cloud (ASCII or binary), with normals, colours and a facerec3d grid when present."""
    from plyfile import PlyData

    _check_ply_header(path)
    with library_errors(path, "PLY file"), warnings.catch_warnings():
        # an ASCII face of no corners (a line `0`) is no triangle: NumPy's loadtxt warns of its empty list
        warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
        try:  # fast: triangle lists memory-mapped
            ply = PlyData.read(str(path), known_list_len=TRIANGLES)
        except Exception:  # other polygons, or a corrupt file: read again element by element
            ply = _read_ply_elementwise(path)
        vertex = ply["vertex"].data
        points = _stack(vertex, ("x", "y", "z"), np.float64)
        normals = _stack(vertex, ("nx", "ny", "nz"), np.float64)
        colors = _stack(vertex, ("red", "green", "blue"), np.uint8)
        shape = [c.split()[2:] for c in ply.comments if c.startswith(GRID_COMMENT)]
        grid = grid_shape = None
        if shape and {"row", "col"} <= set(vertex.dtype.names):
            grid_shape = (int(shape[0][0]), int(shape[0][1]))
            grid = np.stack([vertex["row"], vertex["col"]], axis=1).astype(np.int64)
        mesh = None if grid is not None or "face" not in ply else _ply_triangles(ply["face"].data)
    if points is None:
        raise ScanFormatError(path, "PLY vertices have no x, y, z")
    return point_scan(path, points, grid=grid, grid_shape=grid_shape, normals=normals, colors=colors, mesh=mesh)


def _ply_triangles(face: np.ndarray) -> np.ndarray | None:
    """(M, 3) triangles of a PLY face element (polygons fanned from their first corner); None without indices."""
    name = next((n for n in ("vertex_indices", "vertex_index") if n in (face.dtype.names or ())), None)
    if name is None or not len(face):
        return None
    lists = face[name]
    if lists.dtype != object:  # triangle lists read as an (M, 3) array
        return np.asarray(lists, dtype=np.int64).reshape(-1, 3)
    tris = [np.stack([np.full(len(p) - 2, p[0]), p[1:-1], p[2:]], axis=1) for p in lists if len(p) >= 3]
    return np.concatenate(tris).astype(np.int64) if tris else None


def write_ply(scan: FaceScan, path: str | Path, binary: bool = True) -> None:
    """Write a scan as PLY (little-endian binary or ASCII).

    Vertices: x, y, z (float64 mm), + nx, ny, nz, + red, green, blue, + grid row, col (int32) and the
    comment `facerec3d grid_shape R C`; faces: the grid triangles of a grid scan, or a mesh's own triangles. plyfile writes the
    header; the body is written here in one piece (plyfile writes list elements record by record).
    """
    from plyfile import PlyData, PlyElement

    columns = {"x": scan.points[:, 0], "y": scan.points[:, 1], "z": scan.points[:, 2]}
    if scan.normals is not None:
        columns.update(zip(("nx", "ny", "nz"), scan.normals.T))
    if scan.colors is not None:
        columns.update(zip(("red", "green", "blue"), np.asarray(scan.colors, dtype=np.uint8).T))
    comments = []
    if scan.grid is not None:
        columns.update(row=scan.grid[:, 0], col=scan.grid[:, 1])
        comments.append(f"{GRID_COMMENT} {scan.grid_shape[0]} {scan.grid_shape[1]}")
    kinds = {"f": "<f8", "u": "u1", "i": "<i4"}
    vertex = np.empty(scan.n_points, dtype=[(name, kinds[col.dtype.kind]) for name, col in columns.items()])
    for name, col in columns.items():
        vertex[name] = col
    elements = [PlyElement.describe(vertex, "vertex")]
    if scan.grid is not None and scan.n_points:
        tris = scan.triangles()
    else:
        tris = scan.mesh if scan.mesh is not None else np.empty((0, 3), dtype=np.int64)
    face = np.empty(len(tris), dtype=[("n", "u1"), ("vertex_indices", "<i4", (3,))])  # list uchar int
    face["n"], face["vertex_indices"] = 3, tris
    if len(tris):  # (an unfilled array of the face element's type, for its header lines)
        elements.append(PlyElement.describe(np.empty(len(tris), [("vertex_indices", "<i4", (3,))]), "face"))
    header = PlyData(elements, text=not binary, byte_order="<", comments=comments).header + "\n"
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            vertex.tofile(f)
            face.tofile(f)
        else:
            np.savetxt(f, vertex, fmt=["%.17g" if kinds[c.dtype.kind] == "<f8" else "%d" for c in columns.values()])
            np.savetxt(f, np.column_stack([face["n"], face["vertex_indices"]]), fmt="%d")


def write_obj(scan: FaceScan, path: str | Path) -> None:
    """Write a scan as a Wavefront OBJ mesh (trimesh): its vertices (mm) and triangles (a mesh's own, or the grid
    triangles of a grid scan; none for a point cloud). The grid itself is not kept: OBJ has no place for it."""
    import trimesh

    if scan.grid is not None and scan.n_points:
        tris = scan.triangles()
    else:
        tris = scan.mesh if scan.mesh is not None else np.empty((0, 3), dtype=np.int64)
    text = trimesh.exchange.obj.export_obj(trimesh.Trimesh(scan.points, tris, process=False), include_normals=False,
                                          include_color=False, include_texture=False)
    Path(path).write_text(text, encoding="utf-8")


_OBJ_CORNER_DATA = re.compile(rb"(?m)^[ \t]*v[tn][ \t]")  # a texture coordinate or normal record
_OBJ_FACE = re.compile(rb"(?m)^([ \t]*f[ \t][^\n]*)")
_OBJ_INDEX_TAIL = re.compile(rb"/\S*")  # the /vt/vn of a face corner v/vt/vn, v//vn or v/vt


def _obj_positions_only(data: bytes) -> bytes:
    """An OBJ's text without its texture coordinates and normals (facerec3d uses neither): faces of plain vertex
    indices. With them, trimesh makes one vertex per distinct (vertex, texture, normal) corner of a face, so a
    vertex no face uses is dropped and one with two texture coordinates is doubled; without them (and with
    `maintain_order`) it keeps the file's vertices, each once and in order. A file with neither is returned as
    it is."""
    if not _OBJ_CORNER_DATA.search(data):
        return data
    data = _OBJ_CORNER_DATA.sub(b"#", data)  # the records become comments: line numbers stay
    return _OBJ_FACE.sub(lambda face: _OBJ_INDEX_TAIL.sub(b"", face.group(1)), data)


def _check_off(path: str | Path, data: bytes) -> None:
    """Refuse an OFF file whose counts line is not numbers, or that ends before the vertices and faces its counts
    line promises, one a line (trimesh reads the lines there are: a file cut in its faces, or a counts line of
    99999999999 faces over none, was a scan of its vertices). Lines are counted as trimesh reads them (its comment
    stripping); nothing is allocated by the counts."""
    from trimesh.util import comment_strip, decode_text

    parts = re.split("(COFF|OFF)", comment_strip(decode_text(data)).strip(), maxsplit=1)
    if len(parts) < 3:
        return  # not an OFF file: trimesh says so
    lines = (line for line in parts[2].splitlines() if line.strip())
    counts = next(lines, "").split()[:2]
    if len(counts) < 2:
        return  # no counts line: trimesh says so
    if not all(c.isascii() and c.isdigit() for c in counts):
        raise ScanFormatError(path, f"bad OFF header: the vertex and face counts are {' '.join(counts)[:40]!r}, not "
                                    "numbers")
    vertices, faces = map(int, counts)
    held = sum(1 for _ in lines)
    if held < vertices + faces:
        raise ScanFormatError(path, f"truncated OFF: header promises {vertices} vertices and {faces} faces (a line "
                                    f"each), the file holds only {held} lines after it")


def read_mesh(path: str | Path) -> FaceScan:
    """An OBJ, OFF or STL mesh or point cloud: its vertices, with vertex colours when the file has them.

    Every vertex of an OBJ is a point, in the file's order, also those no face uses (isolated points: trimesh
    drops them by default, about 2 % of a range scan written as OBJ, where a point whose neighbours are missing
    or too far away is in no grid triangle); see `_obj_positions_only`.

    Normals are not taken from these files (trimesh does not tell stored from computed ones);
    matchers estimate them from the points. trimesh parses the whole file, so files over MAX_MESH_BYTES are refused
    before it does.

    STL repeats each vertex for every triangle; those repeats are merged (the order of the points is then lost).
    """
    import trimesh

    suffix = Path(path).suffix.lower().lstrip(".")
    data = read_bytes(path, MAX_MESH_BYTES)
    normals = colors = mesh = None
    options = {"maintain_order": True} if suffix == "obj" else {}  # every vertex, in order (not only faces')
    if suffix == "obj":
        data = _obj_positions_only(data)
    with library_errors(path, f"{suffix.upper()} file"):
        if suffix == "off":
            _check_off(path, data)
        geometry = trimesh.load(io.BytesIO(data), file_type=suffix, process=False, **options)
        if isinstance(geometry, trimesh.Scene):
            parts = geometry.dump()
            points = np.concatenate([np.asarray(g.vertices) for g in parts]) if parts else np.empty((0, 3))
        else:
            points = np.asarray(geometry.vertices, dtype=np.float64)
        if isinstance(geometry, trimesh.Trimesh):
            if geometry.visual.kind == "vertex":  # otherwise trimesh reports a default colour
                colors = np.asarray(geometry.visual.vertex_colors)
            if len(geometry.faces):
                mesh = np.asarray(geometry.faces, dtype=np.int64)
        elif isinstance(geometry, trimesh.PointCloud):
            colors = np.asarray(geometry.colors)
    if colors is not None:
        colors = colors[:, :3] if colors.ndim == 2 and len(colors) == len(points) and len(points) else None
    if suffix == "stl":  # one vertex per corner: merged, the triangles renumbered
        points, inverse = np.unique(points, axis=0, return_inverse=True)
        mesh = None if mesh is None else inverse.reshape(-1)[mesh]
        normals = colors = None
    return point_scan(path, points, normals=normals, colors=colors, mesh=mesh)
