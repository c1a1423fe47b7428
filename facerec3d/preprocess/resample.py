"""Spatial resampling (chapter §8.5.6): a uniform x–y grid in the frontal frame.

The pose-normalised face (nose tip at the origin, looking along +z) is
triangulated on its range-image grid and rasterised orthographically onto a
uniform grid, keeping the front-most surface: each cell gets the depth z of
the surface above its centre by linear interpolation inside the triangle that
covers it. The result is both a point cloud (one point per valid cell, with
the cell as its grid position) and a depth map with a validity mask, which
PCA and LDA use (§8.7–8.8).

Grid layout: cell (r, c) has centre x = −w + c·res, y = w − r·res, so row 0
is the top of the face and column 0 its right side (the viewer's left).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from facerec3d.config import check_cells
from facerec3d.errors import FailureToAcquire, InputError
from facerec3d.io.common import MAX_POINTS
from facerec3d.scan import FaceScan, column_bounds


@dataclass(frozen=True)
class ResampleConfig:
    """Resampling grid (§8.5.6)."""

    resolution_mm: float = 1.0  # cell size
    half_width_mm: float = 95.0  # the grid spans [−w, w] in x and y; also the default crop radius (PreprocessConfig)

    def __post_init__(self) -> None:
        check_cells("resolution_mm", self.resolution_mm, 2 * self.half_width_mm, "the grid, 2 × half_width_mm")

    @property
    def size(self) -> int:
        return int(round(2 * self.half_width_mm / self.resolution_mm)) + 1


@njit(cache=True)
def front_triangles(points, tris, x0, y0, res, rows, cols):  # pragma: no cover - compiled
    """The front-most surface of the triangles over the cell centres (x0 + c·res, y0 − r·res) of a rows × cols
    grid, seen from +z: (z (−inf: no triangle), the triangle's index (−1: none), its barycentric coordinates
    (rows, cols, 3)). Preprocessing's resampling keeps z; the geometry images (matching.morphable) the rest."""
    z = np.full((rows, cols), -np.inf)
    tri = np.full((rows, cols), -1, np.int64)
    bary = np.zeros((rows, cols, 3))
    for k in range(tris.shape[0]):
        a = points[tris[k, 0]]
        b = points[tris[k, 1]]
        c = points[tris[k, 2]]
        # continuous cell coordinates: col = (x - x0)/res, row = (y0 - y)/res
        ua, va = (a[0] - x0) / res, (y0 - a[1]) / res
        ub, vb = (b[0] - x0) / res, (y0 - b[1]) / res
        uc, vc = (c[0] - x0) / res, (y0 - c[1]) / res
        area = (ub - ua) * (vc - va) - (uc - ua) * (vb - va)
        if abs(area) < 1e-12:
            continue
        cmin = max(int(np.ceil(min(ua, ub, uc))), 0)
        cmax = min(int(np.floor(max(ua, ub, uc))), cols - 1)
        rmin = max(int(np.ceil(min(va, vb, vc))), 0)
        rmax = min(int(np.floor(max(va, vb, vc))), rows - 1)
        for r in range(rmin, rmax + 1):
            for col in range(cmin, cmax + 1):
                w1 = ((col - ua) * (vc - va) - (uc - ua) * (r - va)) / area
                w2 = ((ub - ua) * (r - va) - (col - ua) * (vb - va)) / area
                w0 = 1.0 - w1 - w2
                if w0 < -1e-9 or w1 < -1e-9 or w2 < -1e-9:
                    continue
                depth = w0 * a[2] + w1 * b[2] + w2 * c[2]
                if depth > z[r, col]:
                    z[r, col], tri[r, col] = depth, k
                    bary[r, col, 0], bary[r, col, 1], bary[r, col, 2] = w0, w1, w2
    return z, tri, bary


def rasterize_depth(points: np.ndarray, triangles: np.ndarray, config: ResampleConfig = ResampleConfig()) -> np.ndarray:
    """(size, size) depth map z (mm) of a triangle mesh seen from +z; NaN where no surface."""
    return _depth_image(points, triangles, *_frontal_grid(config))


def _frontal_grid(config: ResampleConfig) -> tuple[float, float, float, int, int]:
    """(x0, y0, cell, rows, cols) of the frontal grid: its first cell's corner at (−half width, +half width)."""
    w = config.half_width_mm
    return -w, w, config.resolution_mm, config.size, config.size


def _depth_image(points, triangles, x0: float, y0: float, res: float, rows: int, cols: int) -> np.ndarray:
    """`front_triangles`' depth with NaN where no triangle covers a cell."""
    return _rasterised(points, triangles, x0, y0, res, rows, cols)[0]


def _rasterised(points, triangles, x0: float, y0: float, res: float, rows: int,
                cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`front_triangles` with NaN depth where no triangle covers a cell."""
    z, tri, bary = front_triangles(np.ascontiguousarray(points, np.float64),
                                   np.ascontiguousarray(triangles, np.int64), x0, y0, res, rows, cols)
    z[~np.isfinite(z)] = np.nan
    return z, tri, bary


def grid_xy(config: ResampleConfig = ResampleConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) coordinates (mm) of the cell centres of the resampling grid."""
    w, res, n = config.half_width_mm, config.resolution_mm, config.size
    coords = np.arange(n) * res
    return np.meshgrid(-w + coords, w - coords)


def depth_to_scan(z: np.ndarray, config: ResampleConfig, like: FaceScan | None = None) -> FaceScan:
    """A grid scan with one point per valid cell of a depth map (metadata and landmarks from `like`)."""
    X, Y = grid_xy(config)
    fields = {} if like is None else {"meta": like.meta, "landmarks": like.landmarks}
    return FaceScan.from_range_image(np.stack([X, Y, z], axis=-1), np.isfinite(z), **fields)


def resample(scan: FaceScan, config: ResampleConfig = ResampleConfig()) -> FaceScan:
    """The frontal-frame scan on a uniform x–y grid (front-most surface, linear interpolation); each cell takes the
    provenance (`FaceScan.provenance`) of the corner of its triangle that weighs most in its depth (the corner
    nearest it, in barycentric terms)."""
    if scan.grid is None:
        raise ValueError("resampling needs a range-image grid (see preprocess.gridify for point clouds)")
    tris = scan.triangles()
    z, tri, bary = _rasterised(scan.points, tris, *_frontal_grid(config))
    out = depth_to_scan(z, config, like=scan)
    if scan.provenance is not None and scan.provenance.any() and out.n_points:
        r, c = out.grid[:, 0], out.grid[:, 1]
        corner = tris[tri[r, c], np.argmax(bary[r, c], axis=1)]
        out = out.replace(provenance=scan.provenance[corner])
    return out


def depth_map(scan: FaceScan, config: ResampleConfig = ResampleConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(depth (size, size) with NaN where invalid, valid mask) of a resampled scan: the z of its range image."""
    if scan.grid is None or scan.grid_shape != (config.size, config.size):
        raise InputError(f"not a preprocessed face: grid {scan.grid_shape}, expected the {config.size}×{config.size} "
                         "resampling grid (§8.5.6)")
    xyz, valid = scan.to_range_image()
    return xyz[..., 2], valid


def point_spacing(points: np.ndarray, sample: int = 20000) -> float:
    """The typical distance between neighbouring points (mm): median distance to the nearest other point."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    idx = np.arange(len(pts)) if len(pts) <= sample else np.random.default_rng(0).choice(len(pts), sample, replace=False)
    d, _ = cKDTree(pts).query(pts[idx], k=2)
    d = d[:, 1]
    d = d[d > 0]  # repeated vertices
    return float(np.median(d)) if len(d) else float("nan")


MAX_TRIANGULATED = 400_000  # points a point cloud is thinned to before its Delaunay triangulation (memory; a
#                              480 × 640 range image holds at most 307,200)


def front_points(scan: FaceScan, cell: float) -> FaceScan:
    """A mesh as it is (it is rasterised at the cell size); a point cloud thinned to its front-most point in each
    `cell` × `cell` square of x–y, so that its triangulation is quick and regular. The squares start at the cloud's
    own corner (its least x and y), as `gridify`'s cells do, so a cloud moved in x–y keeps the same points (counted
    from the frame's origin, a 1 mm move changed the points kept and with them the roll `orient` found)."""
    if scan.mesh is not None:
        return scan
    xy = scan.points[:, :2]
    key = np.floor((xy - column_bounds(xy)[0]) / cell).astype(np.int64)
    key = key[:, 0] * (key[:, 1].max() + 1) + key[:, 1]
    order = np.lexsort((-scan.points[:, 2], key))
    return scan.subset(order[np.r_[True, key[order][1:] != key[order][:-1]]])


def surface_triangles(points: np.ndarray, max_edge_mm: float) -> np.ndarray:
    """(M, 3) triangles of a point cloud seen along z: the Delaunay triangulation of its (x, y), less triangles
    with an edge longer than `max_edge_mm` in 3D (they would bridge holes and depth discontinuities). It is taken
    of x–y measured from the cloud's own corner: Qhull's lifting (x² + y²) of coordinates far from the origin loses
    the digits that tell a point's neighbours apart (a Kinect face 10⁶ mm away got other triangles for 0.4 % of
    its surface, and depths on the grid up to 3 mm off; 10⁷ mm away, for a third of it)."""
    from scipy.spatial import Delaunay, QhullError

    try:
        xy = points[:, :2]
        tris = Delaunay(xy - column_bounds(xy)[0]).simplices.astype(np.int64)
    except (QhullError, ValueError):  # fewer than 3 points, or all on a line
        return np.zeros((0, 3), np.int64)
    p = points[tris]
    longest = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
    return tris[longest <= max_edge_mm]


def gridify(scan: FaceScan, resolution_mm: float = 0.0, edge_factor: float = 4.0) -> FaceScan:
    """A range image of a mesh or point cloud without a grid, seen along −z → +z: its surface rasterised from
    its triangles (a mesh's own, or a point cloud's Delaunay triangles in x–y with edges of at most
    `edge_factor` × the point spacing, which do not bridge holes), keeping the front-most surface, on cells of
    `resolution_mm` (0: the point spacing measured on the scan, so a 3.8 mm stereo mesh and a 0.5 mm laser
    mesh both fill their grid without gaps or wasted cells). Each valid cell becomes one point at its centre,
    its depth interpolated linearly inside the triangle that covers it.

    The face must look roughly along +z (`preprocess.orient` turns other frames so). The points carry no
    colour or normals any more.
    """
    if scan.grid is not None:
        return scan
    if scan.n_points < 3:
        return scan.replace(grid=np.zeros((0, 2), np.int32), grid_shape=(0, 0), points=np.zeros((0, 3)), normals=None,
                            colors=None, mesh=None)
    spacing = point_spacing(scan.points)
    if not np.isfinite(spacing) or spacing <= 0:
        raise FailureToAcquire(f"the {scan.n_points} points have no measurable spacing", scan.meta.path)
    if scan.mesh is None and scan.n_points > MAX_TRIANGULATED:  # no face needs more: thinned, memory bounded
        spacing = spacing * np.sqrt(scan.n_points / MAX_TRIANGULATED)  # one point per cell of this size
        scan = front_points(scan, spacing)
    res = float(resolution_mm) if resolution_mm > 0 else spacing
    lo, hi = column_bounds(scan.points[:, :2])
    shape = (int(np.floor((hi[1] - lo[1]) / res)) + 1, int(np.floor((hi[0] - lo[0]) / res)) + 1)
    if shape[0] * shape[1] > MAX_POINTS:  # the grid's images would not fit in memory; no face is that large
        raise FailureToAcquire(f"the surface spans {shape[0]}×{shape[1]} cells of {res:.3g} mm, more than a face "
                               f"scan's {MAX_POINTS}", scan.meta.path)
    tris = scan.mesh if scan.mesh is not None else surface_triangles(scan.points, edge_factor * spacing)
    z = _depth_image(scan.points, tris, lo[0], hi[1], res, *shape)
    rows, cols = np.nonzero(np.isfinite(z))
    xyz = np.stack([lo[0] + cols * res, hi[1] - rows * res, z[rows, cols]], axis=1)
    return scan.replace(points=xyz, grid=np.stack([rows, cols], axis=1), grid_shape=shape, normals=None,
                        colors=None, mesh=None)
