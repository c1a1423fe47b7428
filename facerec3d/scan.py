"""`FaceScan`: the one data type that flows through facerec3d.

A scan is a set of 3D points in millimetres. When it comes from a range
scanner it also keeps the range-image row and column of each point (`grid`),
so that pixel neighbours are known; grid triangulation, hole filling and
spike removal use them. Every processing stage takes a scan and returns a
new one; a scan is never modified in place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit


#: `FaceScan.provenance` values: where a point of a face comes from.
SEEN, FILLED, MIRRORED = 0, 1, 2


@dataclass(frozen=True)
class ScanMeta:
    """Who and what a scan is. Every field is optional."""

    subject: str | None = None
    scan_id: str | None = None
    session: str | None = None
    expression: str | None = None  # "neutral", "non-neutral" or a finer label
    path: str | None = None  # the source file
    extra: dict[str, Any] = field(default_factory=dict)

    def replace(self, **changes: Any) -> "ScanMeta":
        return dataclasses.replace(self, **changes)


def column_bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of each column of a 2-D array: the values of `a.min(axis=0), a.max(axis=0)`, a column at a time,
    which is ~20× faster on an (n, 3) or (n, 2) array (NumPy's axis-0 reduction of so few columns runs its inner
    loop across them: 3.4 ms for the bounding box of a 62,000-point laser scan, 0.2 ms so)."""
    a = np.asarray(a)
    if a.ndim != 2 or not len(a):
        raise ValueError(f"column_bounds needs a non-empty 2-D array, got shape {a.shape}")
    return (np.array([a[:, k].min() for k in range(a.shape[1])], dtype=a.dtype),
            np.array([a[:, k].max() for k in range(a.shape[1])], dtype=a.dtype))


@dataclass(frozen=True, eq=False)
class FaceScan:
    """A 3D face scan.

    points:     (N, 3) float64, mm.
    grid:       (N, 2) int32 range-image (row, column) of each point, or None.
    grid_shape: (rows, columns) of that range image, or None.
    normals:    (N, 3) float64 unit normals, or None.
    colors:     (N, 3) uint8 RGB, or None.
    landmarks:  name -> (3,) float64 position in mm (same frame as points).
    meta:       identity and provenance.
    mesh:       (M, 3) int64 point indices of the triangles of a mesh file (a scan without a grid), or None;
                preprocessing rasterises them into a range image (`preprocess.resample.gridify`).
    provenance: (N,) uint8 where each point comes from (SEEN, FILLED by hole filling, MIRRORED from the other
                side of the face), or None (all seen); matchers may weigh points by it.
    """

    points: np.ndarray
    grid: np.ndarray | None = None
    grid_shape: tuple[int, int] | None = None
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    meta: ScanMeta = field(default_factory=ScanMeta)
    mesh: np.ndarray | None = None
    provenance: np.ndarray | None = None

    def __post_init__(self) -> None:
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        if pts.size and (pts.ndim != 2 or pts.shape[1] != 3):  # (an (N, 2) array would reshape into other points)
            raise ValueError(f"points must be an (N, 3) array of x, y, z, not one of shape {pts.shape}")
        pts = pts.reshape(-1, 3)
        object.__setattr__(self, "points", pts)
        n = len(pts)
        if self.grid is not None:
            g = np.ascontiguousarray(self.grid, dtype=np.int32).reshape(-1, 2)
            if len(g) != n:
                raise ValueError(f"grid has {len(g)} rows for {n} points")
            if self.grid_shape is None:
                raise ValueError("grid given without grid_shape")
            object.__setattr__(self, "grid", g)
            object.__setattr__(self, "grid_shape", (int(self.grid_shape[0]), int(self.grid_shape[1])))
        if self.normals is not None:
            nrm = np.ascontiguousarray(self.normals, dtype=np.float64).reshape(-1, 3)
            if len(nrm) != n:
                raise ValueError(f"normals has {len(nrm)} rows for {n} points")
            object.__setattr__(self, "normals", nrm)
        if self.colors is not None:
            col = np.ascontiguousarray(self.colors).reshape(-1, 3)
            if len(col) != n:
                raise ValueError(f"colors has {len(col)} rows for {n} points")
            object.__setattr__(self, "colors", col)
        if self.provenance is not None:
            prov = np.ascontiguousarray(self.provenance, dtype=np.uint8).reshape(-1)
            if len(prov) != n:
                raise ValueError(f"provenance has {len(prov)} rows for {n} points")
            object.__setattr__(self, "provenance", prov)
        if self.mesh is not None:
            tri = np.ascontiguousarray(self.mesh, dtype=np.int64).reshape(-1, 3)
            if len(tri) and (tri.min() < 0 or tri.max() >= n):
                raise ValueError(f"mesh triangles index points outside 0..{n - 1}")
            object.__setattr__(self, "mesh", tri)
        object.__setattr__(
            self, "landmarks", {k: np.asarray(v, dtype=np.float64).reshape(3) for k, v in self.landmarks.items()}
        )

    # ----------------------------------------------------------------- basics
    def __len__(self) -> int:
        return len(self.points)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def replace(self, **changes: Any) -> "FaceScan":
        """A copy with some fields changed (dataclasses.replace)."""
        return dataclasses.replace(self, **changes)

    def subset(self, index: np.ndarray) -> "FaceScan":
        """The scan restricted to the points selected by a boolean mask or index array."""
        index = np.asarray(index)
        mesh = None
        if self.mesh is not None:  # the triangles whose three corners are kept, renumbered
            new = np.full(self.n_points, -1, dtype=np.int64)
            kept = np.arange(self.n_points)[index]
            new[kept] = np.arange(len(kept))
            tri = new[self.mesh]
            mesh = tri[(tri >= 0).all(axis=1)]
        return self.replace(
            points=self.points[index],
            grid=None if self.grid is None else self.grid[index],
            normals=None if self.normals is None else self.normals[index],
            colors=None if self.colors is None else self.colors[index],
            mesh=mesh,
            provenance=None if self.provenance is None else self.provenance[index],
        )

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> "FaceScan":
        """The scan moved rigidly: x -> R x + t (points, normals and landmarks)."""
        R = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(translation, dtype=np.float64).reshape(3)
        return self.replace(
            points=self.points @ R.T + t,
            normals=None if self.normals is None else self.normals @ R.T,
            landmarks={k: R @ v + t for k, v in self.landmarks.items()},
        )

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners in mm."""
        if not len(self.points):
            raise ValueError("empty scan has no bounding box")
        return column_bounds(self.points)

    def resolution(self) -> float:
        """Typical point spacing in mm: median distance to the nearest other point (of up to 20,000 points;
        on a grid, the nearest of the 8 neighbouring pixels, which needs no search)."""
        known = self.__dict__.get("_resolution")  # measured once per scan (a scan is never changed in place)
        if known is None:
            known = self._measure_resolution()
            object.__setattr__(self, "_resolution", known)
        return known

    def _measure_resolution(self) -> float:
        n = len(self.points)
        if n < 2:
            return float("nan")
        sample = np.arange(n) if n <= 20000 else np.random.default_rng(0).choice(n, 20000, replace=False)
        if self.grid is not None and self.grid_shape is not None:
            d2 = _nearest_neighbour_pixel_d2(self.points, self.grid, _in_order(sample, n))  # the same set
            if np.isfinite(d2).any():
                return float(np.sqrt(np.median(d2[np.isfinite(d2)])))
        from scipy.spatial import cKDTree

        d, _ = cKDTree(self.points).query(self.points[sample], k=2)
        return float(np.median(d[:, 1]))

    # ------------------------------------------------------ range images
    @classmethod
    def from_range_image(
        cls,
        xyz: np.ndarray,
        valid: np.ndarray | None = None,
        colors: np.ndarray | None = None,
        **fields: Any,
    ) -> "FaceScan":
        """A scan from an (H, W, 3) image of points in mm; `valid` (H, W) marks real pixels.

        Pixels with a non-finite coordinate are invalid whatever `valid` says.
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 3 or xyz.shape[2] != 3:
            raise ValueError(f"range image must be (H, W, 3), got {xyz.shape}")
        ok = np.isfinite(xyz).all(axis=2)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        rows, cols = np.nonzero(ok)
        return cls(
            points=xyz[rows, cols],
            grid=np.stack([rows, cols], axis=1),
            grid_shape=xyz.shape[:2],
            colors=None if colors is None else np.asarray(colors)[rows, cols],
            **fields,
        )

    def to_range_image(self) -> tuple[np.ndarray, np.ndarray]:
        """(xyz (H, W, 3) with NaN where invalid, valid (H, W) bool). Needs a grid."""
        if self.grid is None or self.grid_shape is None:
            raise ValueError("scan has no range-image grid")
        h, w = self.grid_shape
        xyz = np.full((h, w, 3), np.nan)
        valid = np.zeros((h, w), dtype=bool)
        xyz[self.grid[:, 0], self.grid[:, 1]] = self.points
        valid[self.grid[:, 0], self.grid[:, 1]] = True
        return xyz, valid

    def windowed(self, margin: int = 0) -> tuple["FaceScan", np.ndarray]:
        """(the scan on the rows and columns of its grid that hold points, `margin` more on each side where the grid
        has them; the window's origin in the grid): pixel (r, c) of the window is pixel (r, c) + origin of the scan.
        A cropped face fills a small part of a camera frame's grid; its range images need only the window."""
        if self.grid is None or self.grid_shape is None:
            raise ValueError("scan has no range-image grid")
        if not self.n_points:
            return self, np.zeros(2, dtype=np.int64)
        lo, hi = column_bounds(self.grid)
        lo, hi = np.maximum(lo - margin, 0), np.minimum(hi + margin + 1, self.grid_shape)
        return self.replace(grid=self.grid - lo, grid_shape=(int(hi[0] - lo[0]), int(hi[1] - lo[1]))), lo

    def index_image(self) -> np.ndarray:
        """(H, W) int image holding each pixel's point index, -1 where there is none."""
        if self.grid is None or self.grid_shape is None:
            raise ValueError("scan has no range-image grid")
        idx = np.full(self.grid_shape, -1, dtype=np.int64)
        idx[self.grid[:, 0], self.grid[:, 1]] = np.arange(len(self.points))
        return idx

    # ------------------------------------------------------------- meshes
    def triangles(self, max_edge: float | None = None) -> np.ndarray:
        """Triangulate the range-image grid: (M, 3) point indices.

        Each 2×2 block of valid pixels gives two triangles; a triangle with a
        missing corner is skipped, and so is one with an edge longer than
        `max_edge` mm (default: 4 × the scan resolution), which would bridge
        a depth discontinuity.
        """
        if not self.n_points:
            return np.zeros((0, 3), np.int64)
        idx = self.windowed()[0].index_image()  # the rows and columns holding points (a cropped face is small)
        if max_edge is None:
            max_edge = 4.0 * self.resolution()
        return _grid_triangles(idx, self.points, float(max_edge))

    def __repr__(self) -> str:
        who = self.meta.scan_id or self.meta.path or "scan"
        grid = f", grid {self.grid_shape[0]}x{self.grid_shape[1]}" if self.grid is not None else ""
        return f"FaceScan({who}: {self.n_points} points{grid}, {len(self.landmarks)} landmarks)"


def _in_order(sample: np.ndarray, n: int) -> np.ndarray:
    """The distinct indices `sample` (of 0..n-1) in increasing order, as np.sort gives them, in O(n): the points in
    memory order (sorting 20,000 indices took longer than measuring their distances)."""
    if len(sample) == n:  # np.arange(n)
        return sample
    chosen = np.zeros(n, dtype=bool)
    chosen[sample] = True
    return np.flatnonzero(chosen)


@njit(cache=True)
def _nearest_neighbour_pixel_d2(points, grid, sample):  # pragma: no cover - compiled
    """For each sampled point, the squared distance (mm²) to the nearest point among its 8 neighbouring pixels
    (inf without one). The pixels' point indices are laid out over the rows and columns that hold points only
    (a cropped face fills a small window of a camera frame's grid)."""
    r0, c0, r1, c1 = grid[0, 0], grid[0, 1], grid[0, 0], grid[0, 1]
    for i in range(grid.shape[0]):
        r0, r1 = min(r0, grid[i, 0]), max(r1, grid[i, 0])
        c0, c1 = min(c0, grid[i, 1]), max(c1, grid[i, 1])
    rows, cols = r1 - r0 + 1, c1 - c0 + 1
    index = np.full((rows, cols), -1, np.int32)
    for i in range(grid.shape[0]):
        index[grid[i, 0] - r0, grid[i, 1] - c0] = i
    out = np.full(sample.shape[0], np.inf)
    for k in range(sample.shape[0]):
        i = sample[k]
        r, c = grid[i, 0] - r0, grid[i, 1] - c0
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                rr, cc = r + dr, c + dc
                if (dr or dc) and 0 <= rr < rows and 0 <= cc < cols and index[rr, cc] >= 0:
                    j = index[rr, cc]
                    dx = points[j, 0] - points[i, 0]
                    dy = points[j, 1] - points[i, 1]
                    dz = points[j, 2] - points[i, 2]
                    out[k] = min(out[k], dx * dx + dy * dy + dz * dz)
    return out


@njit(cache=True)
def _grid_triangles(idx, points, max_edge):  # pragma: no cover - compiled
    """`FaceScan.triangles` of the index image idx: each 2×2 block (a, b / c, d) gives (a, c, b) where its edges
    a–c, c–b and b–a are whole (both pixels valid, at most max_edge apart), and (b, c, d) where c–b, b–d and d–c are;
    every upper triangle in row-major order of the blocks, then every lower one."""
    rows, cols = idx.shape
    out = np.empty((2 * max(rows - 1, 0) * max(cols - 1, 0), 3), np.int64)
    n = 0
    for lower in range(2):
        for r in range(rows - 1):
            for c in range(cols - 1):
                a, b, cc, d = idx[r, c], idx[r, c + 1], idx[r + 1, c], idx[r + 1, c + 1]
                if b < 0 or cc < 0 or not _edge(points, b, cc, max_edge):  # the shared diagonal
                    continue
                if lower == 0:
                    if a >= 0 and _edge(points, a, cc, max_edge) and _edge(points, a, b, max_edge):
                        out[n, 0], out[n, 1], out[n, 2] = a, cc, b
                        n += 1
                elif d >= 0 and _edge(points, b, d, max_edge) and _edge(points, cc, d, max_edge):
                    out[n, 0], out[n, 1], out[n, 2] = b, cc, d
                    n += 1
    return out[:n].copy()


@njit(cache=True, inline="always")
def _edge(points, i, j, max_edge):  # pragma: no cover - compiled
    """Points i and j at most max_edge apart (the distance as `np.linalg.norm` sums it)."""
    dx, dy, dz = points[i, 0] - points[j, 0], points[i, 1] - points[j, 1], points[i, 2] - points[j, 2]
    return np.sqrt(dx * dx + dy * dy + dz * dz) <= max_edge
