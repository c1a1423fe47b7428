"""The gallery side of ICP (chapter §8.6.1): a face's closest-point search structures, built once at enrolment.

`GalleryIndex`, kept in the face's template:
  * the voxel nearest-neighbour lookup: for every centre of a `voxel_size` mm
    voxel within `margin` of the face (margin = the initial distance
    threshold, at most `max_reach_mm` or the final threshold, plus half a
    voxel diagonal; pairs farther than it are dropped) the index of its nearest gallery
    point, so a closest-point query is one array read (found at enrolment by
    a separable distance transform, `voxel_nearest`). Only the z-run of
    such voxels is kept in each x–y column. The stored point is the nearest
    to the voxel centre, so it may miss the query's true closest point by up
    to a voxel diagonal;
  * x–y buckets: the points sorted by x–y column of the same grid, for an
    exact fixed-radius closest-point search in compiled code. This takes the
    place of a k-d tree: scipy's cKDTree can neither be called from Numba nor
    saved without pickle (so it would be rebuilt on every load) and costs
    ~1 µs per query from Python; the buckets are plain arrays in the .npz;
  * PCA normals (int8, unit normal × 127) and boundary points (rim and hole
    edges), geometry.normals.

`closest_point` is the compiled query the ICP loop (`matching.icp.align`) makes for each probe point:
exact whenever the closest point lies within the final threshold (`distance_end`); the search is bounded by
the point's pair of the previous iteration or by the voxel lookup's candidate, which also rejects queries that
cannot have a point within the threshold. Farther pairs, which only the early, wide thresholds accept, come
from the voxel lookup alone.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from facerec3d.geometry.normals import boundary_mask, estimate_normals
from facerec3d.matching.base import Template
from facerec3d.matching.icp.config import ICPConfig
from facerec3d.scan import FaceScan, column_bounds


class GalleryIndex(NamedTuple):
    """A gallery face's search structures (see the module docstring); built once by `from_scan`.

    The voxel lookup covers pairs up to the enrolment config's distance_start;
    matching with a larger one misses the farther pairs.
    """

    points: np.ndarray  # (N, 3) float32 mm, sorted by x–y bucket
    normals: np.ndarray  # (N, 3) int8: unit normal × 127
    boundary: np.ndarray  # (N,) bool
    colors: np.ndarray  # (N, 3) uint8, or (0, 3) without colours
    voxel_first: np.ndarray  # (C,) int16: z index of the first stored voxel of each x–y column
    voxel_offset: np.ndarray  # (C + 1,) int32: column c's voxels are voxel_index[offset[c]:offset[c + 1]]
    voxel_index: np.ndarray  # (V,) uint16 (int32 above 65,534 points): nearest point; dtype max = none
    bucket_start: np.ndarray  # (C + 1,) int32: column c's points are points[start[c]:start[c + 1]]
    origin: np.ndarray  # (3,) mm: corner of the voxel grid
    voxel_size: float  # mm
    nx: int
    ny: int
    nz: int
    resolution: float  # mm: median spacing of the gallery points
    margin: float  # mm: voxels farther than this from every point store none

    @classmethod
    def from_scan(cls, scan: FaceScan, config: ICPConfig = ICPConfig()) -> "GalleryIndex":
        """Build from a scan: PCA normals (the scan's own if it has them) and boundary from its grid when it has one."""
        normals = scan.normals
        if normals is None:
            normals = estimate_normals(scan.points, config.normal_neighbours, grid=scan.grid,
                                       grid_shape=scan.grid_shape)
        boundary = boundary_mask(scan.points, grid=scan.grid, grid_shape=scan.grid_shape)
        return cls.build(scan.points, normals, boundary, scan.colors, resolution=matching_resolution(scan, config),
                         config=config)

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray, boundary: np.ndarray, colors: np.ndarray | None = None,
              *, resolution: float, config: ICPConfig = ICPConfig()) -> "GalleryIndex":
        """Build from gallery points (mm), unit normals, boundary flags, optional RGB, and point spacing (mm)."""
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3).astype(np.float64)  # as stored
        if len(pts) < 3:
            raise ValueError("a gallery face needs at least 3 points")
        h = float(config.voxel_size)
        reach = min(config.distance_start * resolution, max(config.max_reach_mm, config.distance_end * resolution))
        margin = reach + 0.5 * math.sqrt(3.0) * h
        lo, hi = column_bounds(pts)
        origin = lo - margin
        nx, ny, nz = (np.ceil((hi + margin - origin) / h).astype(np.int64) + 1).tolist()
        column = (np.floor((pts[:, 0] - origin[0]) / h).astype(np.int64) * ny
                  + np.floor((pts[:, 1] - origin[1]) / h).astype(np.int64))
        order = np.argsort(column, kind="stable")
        pts = pts[order]
        bucket_start = np.concatenate([[0], np.cumsum(np.bincount(column, minlength=nx * ny))]).astype(np.int32)
        nearest = voxel_nearest(pts, origin, h, (nx, ny, nz), margin)
        first, offset, index = _compress_columns(nearest, len(pts))
        col = np.zeros((0, 3), np.uint8) if colors is None else np.asarray(colors, dtype=np.uint8)[order]
        nrm = np.asarray(normals, dtype=np.float64)[order]
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        return cls(pts.astype(np.float32), np.round(nrm * 127).astype(np.int8), np.asarray(boundary, dtype=bool)[order],
                   np.ascontiguousarray(col), first, offset, index, bucket_start, origin, h, nx, ny, nz,
                   float(resolution), float(margin))

    def to_template(self, subject: str | None = None, scan_id: str | None = None, method: str = "icp") -> Template:
        """The index as a template of `method` (ICP's, or another method keeping an ICP index)."""
        arrays = {name: getattr(self, name) for name in _INDEX_ARRAYS}
        attrs = {name: getattr(self, name) for name in _INDEX_SCALARS}
        attrs["origin"] = self.origin.tolist()
        return Template(subject, scan_id, method, arrays, attrs)

    @classmethod
    def from_template(cls, template: Template) -> "GalleryIndex":
        if missing := set(_INDEX_ARRAYS) - set(template.arrays):
            raise ValueError(f"not an ICP gallery template (method {template.method!r}): no {sorted(missing)}")
        a, s = template.arrays, template.attrs
        return cls(*(a[name] for name in _INDEX_ARRAYS), np.asarray(s["origin"], dtype=np.float64),
                   float(s["voxel_size"]), int(s["nx"]), int(s["ny"]), int(s["nz"]),
                   float(s["resolution"]), float(s["margin"]))


_INDEX_ARRAYS = ("points", "normals", "boundary", "colors", "voxel_first", "voxel_offset", "voxel_index",
                 "bucket_start")
_INDEX_SCALARS = ("voxel_size", "nx", "ny", "nz", "resolution", "margin")


def matching_resolution(scan: FaceScan, config: ICPConfig = ICPConfig()) -> float:
    """The resolution (mm) ICP's distance thresholds are multiples of: the face's point spacing, or, when the
    scan it was resampled from was coarser (its measured pitch or depth step, `meta.extra["quality"]`),
    `sensor_scale` times that."""
    quality = scan.meta.extra.get("quality", {})
    source = max(float(quality.get("pitch_mm", 0.0)), float(quality.get("depth_step_mm", 0.0)))
    return max(scan.resolution(), config.sensor_scale * source)


# --------------------------------------------------------------------------- enrolment kernels
@njit(cache=True, inline="always")
def _centres_within(p, r, o, h, n):  # pragma: no cover - compiled
    """range(first, last + 1) bounds of the n voxel centres o + (i + ½) h of one axis within r of the coordinate p."""
    return max(int(math.ceil((p - r - o) / h - 0.5)), 0), min(int(math.floor((p + r - o) / h - 0.5)), n - 1) + 1


@njit(cache=True, inline="always")
def _offset_and_rest(r2, o, h, i, p):  # pragma: no cover - compiled
    """(d, r² − d²): the offset d of voxel centre i of one axis from the coordinate p, and what is left of r²."""
    d = o + (i + 0.5) * h - p
    return d, r2 - d * d


_ROW_CELLS = 8_000_000  # the separable search keeps a (y, z) distance map per row: at most this many cells ...
_ROW_SHARE = 8  # ... and only for points in rows (at least this many points per distinct x on average)


def voxel_nearest(points: np.ndarray, origin: np.ndarray, h: float, dims: tuple[int, int, int],
                  radius: float) -> np.ndarray:
    """(nx, ny, nz) int32: the index of the point nearest each voxel centre within `radius`, −1 if none (exact;
    of equally near points, either).

    A preprocessed face lies on an x–y grid: its points fall in rows of one x, with one point per y in a row.
    Then the squared distance separates, (x − xᵣ)² + (y − yₖ)² + (z − zₖ)², and the search is the
    separable distance transform of Felzenszwalb & Huttenlocher (Theory of Computing 2012) with these points
    as sites: the lower envelope of parabolas along y within each row, then along x across the rows
    (`_voxel_nearest_rows`), 20× faster on a Kinect face (whose lookup reaches 26 mm) and 6× on a laser
    scan than visiting every voxel of each point's ball (`_voxel_nearest_balls`), which any other cloud of
    points gets."""
    nx, ny, nz = dims
    order = np.lexsort((np.arange(len(points)), points[:, 1], points[:, 0]))
    x = points[order, 0]
    row_start = np.flatnonzero(np.r_[True, x[1:] != x[:-1], True])
    rows = len(row_start) - 1
    if rows * _ROW_SHARE <= len(points) and rows * ny * nz <= _ROW_CELLS:
        return _voxel_nearest_rows(points, order, row_start, origin, h, nx, ny, nz, radius)
    return _voxel_nearest_balls(points, origin, h, nx, ny, nz, radius)


@njit(cache=True)
def _lower_envelope(vertex, offset, n, env, cut):  # pragma: no cover - compiled
    """The lower envelope of the parabolas (u − vertex[i])² + offset[i], i < n, vertices ascending (Felzenszwalb &
    Huttenlocher's algorithm): env[:k] the parabolas on it, left to right, parabola env[i] lowest from cut[i] to
    cut[i + 1]; returns k. Of parabolas with one vertex, the first with the least offset stays."""
    top = -1
    for q in range(n):
        meet = -np.inf  # where parabola q takes over from env[top]
        lower = True
        while top >= 0:
            p = env[top]
            if vertex[q] == vertex[p]:  # one vertex: the parabola of the lesser offset lies wholly below
                lower = offset[q] < offset[p]
                if not lower:
                    break
            else:
                meet = ((offset[q] + vertex[q] ** 2) - (offset[p] + vertex[p] ** 2)) / (2.0 * (vertex[q] - vertex[p]))
                if meet > cut[top]:
                    break
            top -= 1
            meet = -np.inf
        if not lower:
            continue
        top += 1
        env[top] = q
        cut[top] = meet
        cut[top + 1] = np.inf
    return top + 1


@njit(cache=True)
def _voxel_nearest_rows(points, order, row_start, origin, h, nx, ny, nz, radius):  # pragma: no cover - compiled
    """`voxel_nearest` for points in rows of one x each (order[row_start[r]:row_start[r + 1]] is row r, by y):
    (1) per row and voxel z, along y, the lower envelope of the parabolas (y − yₖ)² + (z − zₖ)² of the row's
    points: the squared (y, z) distance of each voxel centre to the row; (2) per (y, z) line of voxels, along x,
    the lower envelope of (x − xᵣ)² + that distance of each row r, read at the voxel centres."""
    R = row_start.shape[0] - 1
    r2 = radius * radius
    plane = np.full((ny, nz, R), np.inf)
    near = np.full((ny, nz, R), -1, np.int32)
    most = 0
    for r in range(R):
        most = max(most, row_start[r + 1] - row_start[r])
    vertex = np.empty(max(most, R))
    offset = np.empty(max(most, R))
    which = np.empty(max(most, R), np.int64)
    env = np.empty(max(most, R), np.int64)
    cut = np.empty(max(most, R) + 1)
    for r in range(R):
        for iz in range(nz):
            cz = origin[2] + (iz + 0.5) * h
            n = 0
            for s in range(row_start[r], row_start[r + 1]):
                j = order[s]
                dz = cz - points[j, 2]
                if dz * dz <= r2:
                    vertex[n], offset[n], which[n] = points[j, 1], dz * dz, j
                    n += 1
            k = _lower_envelope(vertex, offset, n, env, cut)
            _read_envelope(vertex, offset, which, env, cut, k, origin[1], h, r2, plane[:, iz, r], near[:, iz, r])
    x = np.empty(R)
    for r in range(R):
        x[r] = points[order[row_start[r]], 0]
    nearest = np.full((nx, ny, nz), -1, dtype=np.int32)
    dist = np.empty(nx)
    for iy in range(ny):
        for iz in range(nz):
            n = 0
            for r in range(R):
                if plane[iy, iz, r] < np.inf:
                    vertex[n], offset[n], which[n] = x[r], plane[iy, iz, r], near[iy, iz, r]
                    n += 1
            k = _lower_envelope(vertex, offset, n, env, cut)
            _read_envelope(vertex, offset, which, env, cut, k, origin[0], h, r2, dist, nearest[:, iy, iz])
    return nearest


@njit(cache=True, inline="always")
def _read_envelope(vertex, offset, which, env, cut, k, lo, h, r2, dist, index):  # pragma: no cover - compiled
    """The envelope of `_lower_envelope` (k parabolas) read at the centres u = lo + (i + ½) h, i < len(index): where
    its value is within r2, dist[i] = the value and index[i] = `which` of the parabola lowest there."""
    e = 0
    for i in range(index.shape[0] if k else 0):
        u = lo + (i + 0.5) * h
        while cut[e + 1] < u:
            e += 1
        q = env[e]
        du = u - vertex[q]
        d2 = du * du + offset[q]
        if d2 <= r2:
            dist[i] = d2
            index[i] = which[q]


@njit(cache=True)
def _voxel_nearest_balls(points, origin, h, nx, ny, nz, radius):  # pragma: no cover - compiled
    """`voxel_nearest` for any points: each point visits the voxel centres of its ball, axis by axis (x, then y
    within the disc left, then z)."""
    nearest = np.full((nx, ny, nz), -1, dtype=np.int32)
    best = np.full((nx, ny, nz), np.inf)
    r2 = radius * radius
    for j in range(points.shape[0]):
        px, py, pz = points[j, 0], points[j, 1], points[j, 2]
        for ix in range(*_centres_within(px, radius, origin[0], h, nx)):
            dx, rx = _offset_and_rest(r2, origin[0], h, ix, px)
            if rx < 0.0:
                continue
            for iy in range(*_centres_within(py, math.sqrt(rx), origin[1], h, ny)):
                dy, ryz = _offset_and_rest(rx, origin[1], h, iy, py)
                if ryz < 0.0:
                    continue
                for iz in range(*_centres_within(pz, math.sqrt(ryz), origin[2], h, nz)):
                    dz = origin[2] + (iz + 0.5) * h - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < best[ix, iy, iz]:
                        best[ix, iy, iz] = d2
                        nearest[ix, iy, iz] = j
    return nearest


def _compress_columns(nearest: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep, per x–y column, the z-run from the first to the last voxel that has a nearest point."""
    nz = nearest.shape[2]
    found = nearest >= 0
    has = found.any(axis=2)
    first = np.where(has, found.argmax(axis=2), 0)
    last = np.where(has, nz - 1 - found[:, :, ::-1].argmax(axis=2), -1)
    z = np.arange(nz)
    run = (z >= first[..., None]) & (z <= last[..., None])
    dtype = np.uint16 if n_points < np.iinfo(np.uint16).max else np.int32
    values = nearest[run]
    index = np.where(values >= 0, values, np.iinfo(dtype).max).astype(dtype)
    offset = np.concatenate([[0], np.cumsum((last - first + 1).ravel())]).astype(np.int32)
    return first.ravel().astype(np.int16), offset, index


# --------------------------------------------------------------------------- closest-point search (the ICP loop's query)
@njit(cache=True, inline="always")
def nearest_within(x, y, z, r, g):  # pragma: no cover - compiled
    """(index, squared distance) of the exact closest gallery point within r mm of (x, y, z); index −1 if none.

    Scans the x–y buckets overlapping the square of half-side r; the buckets
    of one x column are consecutive, so each column is one contiguous run.
    """
    h = g.voxel_size
    i0 = max(int(math.floor((x - r - g.origin[0]) / h)), 0)
    i1 = min(int(math.floor((x + r - g.origin[0]) / h)), g.nx - 1)
    j0 = max(int(math.floor((y - r - g.origin[1]) / h)), 0)
    j1 = min(int(math.floor((y + r - g.origin[1]) / h)), g.ny - 1)
    best = r * r
    found = -1
    if j0 > j1:
        return found, best
    for ix in range(i0, i1 + 1):
        c = ix * g.ny
        for j in range(g.bucket_start[c + j0], g.bucket_start[c + j1 + 1]):
            dx = g.points[j, 0] - x
            dy = g.points[j, 1] - y
            dz = g.points[j, 2] - z
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= best:
                best = d2
                found = j
    return found, best


@njit(cache=True, inline="always")
def closest_point(x, y, z, thr, exact, g, hint):  # pragma: no cover - compiled
    """(index, squared distance) of the gallery point closest to (x, y, z) if within thr mm, else (−1, ·).

    Exact when it is within `exact` mm (the final threshold); farther ones
    come from the voxel lookup alone. A first guess bounds the exact search:
    `hint` (the point's closest point at the previous iteration, −1 if none)
    or the voxel's candidate. That candidate lies at distance d from the
    query and e from the voxel centre, so the true closest point is at least
    d − 2e away (triangle inequality): the query is rejected without search
    when d − 2e > thr. A radius of d(1 + 1e-9) absorbs rounding.
    """
    if hint >= 0:
        dx = g.points[hint, 0] - x
        dy = g.points[hint, 1] - y
        dz = g.points[hint, 2] - z
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d <= exact:
            return nearest_within(x, y, z, d * (1.0 + 1e-9), g)
    h = g.voxel_size
    fx = (x - g.origin[0]) / h
    fy = (y - g.origin[1]) / h
    fz = (z - g.origin[2]) / h
    if not (0.0 <= fx < g.nx and 0.0 <= fy < g.ny and 0.0 <= fz < g.nz):
        return -1, np.inf
    ix, iy, iz = int(fx), int(fy), int(fz)
    c = ix * g.ny + iy
    k = iz - g.voxel_first[c]
    if k < 0 or k >= g.voxel_offset[c + 1] - g.voxel_offset[c]:
        return -1, np.inf
    j = int(g.voxel_index[g.voxel_offset[c] + k])
    if j >= g.points.shape[0]:  # no gallery point within margin of the voxel centre: none within thr
        return -1, np.inf
    ex, ey, ez = fx - ix - 0.5, fy - iy - 0.5, fz - iz - 0.5
    dx = g.points[j, 0] - x
    dy = g.points[j, 1] - y
    dz = g.points[j, 2] - z
    d2 = dx * dx + dy * dy + dz * dz
    d = math.sqrt(d2)
    if d - 2.0 * h * math.sqrt(ex * ex + ey * ey + ez * ez) > thr:
        return -1, np.inf
    r = min(d * (1.0 + 1e-9), thr)
    if r <= exact:
        return nearest_within(x, y, z, r, g)
    return (j, d2) if d <= thr else (-1, np.inf)
