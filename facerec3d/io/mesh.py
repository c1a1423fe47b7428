"""Meshes and point clouds: PLY through plyfile (read and write), OBJ read here (written by trimesh), OFF / STL
through trimesh (read).

Vertices become the scan's points (mm). A mesh's triangles are kept (`FaceScan.mesh`, polygons fanned into
triangles) when it has no range-image grid, so preprocessing rasterises the surface, not only its vertices; a grid
scan is re-triangulated from its grid. A PLY written here keeps the range-image grid:
integer vertex properties `row` and `col` and a header comment
`facerec3d grid_shape R C`.
"""

from __future__ import annotations

import io
import itertools
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


OBJ_CHUNK = 65536  # records converted to arrays at a time
MAX_OBJ_LINE = 65536  # characters in one record: a polygon of thousands of corners (longer ones are refused as read)


def read_obj(path: str | Path) -> FaceScan:
    """A Wavefront OBJ mesh or point cloud, read here record by record (trimesh's loader builds meshes to draw:
    it splits a file at each `usemtl`, makes one vertex per distinct vertex/texture/normal corner, drops the
    vertices no face uses, and passes vertex index 0 or a short `v` line without a word).

    Each `v x y z` record is one point, in the file's order, also those no face uses (a range scan written as OBJ
    has about 2 % of isolated points: a point whose neighbours are missing or too far away is in no grid
    triangle); `v x y z r g b` gives vertex colours when every `v` record has them (0–1, as trimesh reads them).
    Each `f` record is a polygon of vertex numbers, fanned into triangles from its first corner: `1` is the first
    vertex, `-1` the last one read before the face; of a corner `v/vt/vn` only `v` is read, and a face of fewer
    than 3 corners is no triangle. Other records (`vt`, `vn`, `usemtl`, `mtllib`, `o`, `g`, `s`, ...) and
    comments are skipped. A `v` record of fewer than 3 numbers, a corner that is not a vertex number, vertex 0
    or a vertex the file does not have is refused, naming its line. Files over MAX_MESH_BYTES are refused
    before they are read; lines over MAX_OBJ_LINE characters, more than MAX_POINTS points or 4 × MAX_POINTS
    triangles as they are read.
    """
    with open_binary(path) as raw:
        if raw.seek(0, 2) > MAX_MESH_BYTES:
            raise ScanFormatError(path, f"absurd size: more than {MAX_MESH_BYTES} bytes")
        raw.seek(0)
        points, colors, triangles, triangle_lines = _ObjReader(path).read(raw)
    if len(triangles) and (triangles.max() >= len(points)):
        row = int(np.argmax(triangles.max(axis=1) >= len(points)))
        raise ScanFormatError(path, f"line {triangle_lines[row]}: a face names vertex {triangles[row].max() + 1}, "
                                    f"the file has {len(points)}")
    if colors is not None:
        import trimesh

        colors = trimesh.visual.color.to_rgba(colors)[:, :3]
    return point_scan(path, points, colors=colors, mesh=triangles)


class _ObjReader:
    """The `v` and `f` records of one OBJ file, gathered as text a chunk at a time and converted to arrays."""

    def __init__(self, path: str | Path):
        self.path = path
        self.vertices, self.colors, self.triangles, self.triangle_lines = [], [], [], []
        self.n_vertices = self.n_triangles = 0
        self.all_coloured = True
        self.v_rows, self.c_rows, self.v_lines = [], [], []
        self.f_rows, self.f_lines, self.f_before = [], [], []

    def read(self, raw) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """(points (N, 3), colours (N, 3) or None, triangles (M, 3) from 0, the line of each triangle's face)."""
        with io.TextIOWrapper(raw, encoding="utf-8-sig", errors="replace") as text:
            record, first = "", 0
            for number in itertools.count(1):
                line = text.readline(MAX_OBJ_LINE + 1)
                if not line:
                    break
                if len(line) + len(record) > MAX_OBJ_LINE:
                    raise ScanFormatError(self.path, f"line {first or number}: a record longer than {MAX_OBJ_LINE} "
                                                     "characters")
                if "#" in line:
                    line = line.split("#", 1)[0]
                if "\\" in line and line.rstrip().endswith("\\"):  # continued on the next line
                    record, first = record + line.rstrip()[:-1] + " ", first or number
                    continue
                self._record(record + line, first or number)
                record, first = "", 0
            self._record(record, first)
        self._flush_vertices()
        self._flush_faces()
        points = np.concatenate(self.vertices) if self.vertices else np.empty((0, 3))
        colors = np.concatenate(self.colors) if self.all_coloured and self.colors else None
        triangles = np.concatenate(self.triangles) if self.triangles else np.empty((0, 3), dtype=np.int64)
        lines = np.concatenate(self.triangle_lines) if self.triangle_lines else np.empty(0, dtype=np.int64)
        return points, colors, triangles, lines

    def _record(self, line: str, number: int) -> None:
        fields = line.split()
        if not fields:
            return
        if fields[0] == "v":
            if len(fields) < 4:
                raise ScanFormatError(self.path, f"line {number}: a vertex needs 3 coordinates, x y z: "
                                                 f"{line.strip()[:80]!r}")
            self.v_rows.append(fields[1:4])
            self.v_lines.append(number)
            self.all_coloured = self.all_coloured and len(fields) >= 7
            if self.all_coloured:
                self.c_rows.append(fields[4:7])
            self.n_vertices += 1
            if len(self.v_rows) == OBJ_CHUNK:
                self._flush_vertices()
        elif fields[0] == "f":
            corners = [c.split("/", 1)[0] for c in fields[1:]] if "/" in line else fields[1:]
            for k in range(1, len(corners) - 1):  # a polygon fanned from its first corner
                self.f_rows.append([corners[0], corners[k], corners[k + 1]])
                self.f_lines.append(number)
                self.f_before.append(self.n_vertices)
            if len(self.f_rows) >= OBJ_CHUNK:
                self._flush_faces()

    def _flush_vertices(self) -> None:
        if self.n_vertices > MAX_POINTS:
            raise ScanFormatError(self.path, f"absurd size: more than {MAX_POINTS} points")
        if self.v_rows:
            self.vertices.append(self._numbers(self.v_rows, self.v_lines, np.float64, "a vertex coordinate"))
        if self.all_coloured and self.c_rows:
            self.colors.append(self._numbers(self.c_rows, self.v_lines, np.float64, "a vertex colour"))
        self.v_rows, self.c_rows, self.v_lines = [], [], []

    def _flush_faces(self) -> None:
        if not self.f_rows:
            return
        self.n_triangles += len(self.f_rows)
        if self.n_triangles > 4 * MAX_POINTS:
            raise ScanFormatError(self.path, f"absurd size: more than {4 * MAX_POINTS} triangles")
        index = self._numbers(self.f_rows, self.f_lines, np.int64, "a face's vertex number")
        lines, before = np.array(self.f_lines), np.array(self.f_before)[:, None]
        triangles = np.where(index > 0, index - 1, before + index)  # -1: the last vertex read before the face
        bad = (index == 0) | (triangles < 0)
        if bad.any():
            row = int(np.argmax(bad.any(axis=1)))
            number = index[row][bad[row]][0]
            reason = ("vertex 0 (OBJ numbers vertices from 1)" if number == 0 else
                      f"vertex {number}, but only {before[row, 0]} come before it")
            raise ScanFormatError(self.path, f"line {lines[row]}: a face names {reason}")
        self.triangles.append(triangles)
        self.triangle_lines.append(lines)
        self.f_rows, self.f_lines, self.f_before = [], [], []

    def _numbers(self, rows: list[list[str]], lines: list[int], dtype, what: str) -> np.ndarray:
        """rows of number texts as an array; the first text that is not a number is refused, naming its line."""
        try:
            return np.array(rows, dtype=dtype)
        except (ValueError, OverflowError):
            for row, number in zip(rows, lines):
                for value in row:
                    try:
                        np.array(value, dtype=dtype)
                    except (ValueError, OverflowError):
                        raise ScanFormatError(self.path, f"line {number}: {what} is not a number: {value[:40]!r}"
                                              ) from None
            raise


def read_mesh(path: str | Path) -> FaceScan:
    """An OFF or STL mesh or point cloud (trimesh): its vertices, with vertex colours when the file has them.

    Normals are not taken from these files (trimesh does not tell stored from computed ones);
    matchers estimate them from the points. trimesh parses the whole file, so files over MAX_MESH_BYTES are refused
    before it does.

    STL repeats each vertex for every triangle; those repeats are merged (the order of the points is then lost).
    """
    import trimesh

    suffix = Path(path).suffix.lower().lstrip(".")
    data = read_bytes(path, MAX_MESH_BYTES)
    normals = colors = mesh = None
    with library_errors(path, f"{suffix.upper()} file"):
        if suffix == "off":
            _check_off(path, data)
        geometry = trimesh.load(io.BytesIO(data), file_type=suffix, process=False)
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
