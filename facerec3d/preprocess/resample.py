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

from facerec3d.errors import FailureToAcquire
from facerec3d.io.common import MAX_POINTS
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class ResampleConfig:
    """Resampling grid (§8.5.6)."""

    resolution_mm: float = 1.0  # cell size
    half_width_mm: float = 95.0  # the grid spans [−w, w] in x and y; also the default crop radius (PreprocessConfig)

    @property
    def size(self) -> int:
        return int(round(2 * self.half_width_mm / self.resolution_mm)) + 1


@njit(cache=True)
def _rasterize(points, tris, x0, y0, res, size):  # pragma: no cover - compiled
    z = np.full((size, size), -np.inf)
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
        cmax = min(int(np.floor(max(ua, ub, uc))), size - 1)
        rmin = max(int(np.ceil(min(va, vb, vc))), 0)
        rmax = min(int(np.floor(max(va, vb, vc))), size - 1)
        for r in range(rmin, rmax + 1):
            for col in range(cmin, cmax + 1):
                w1 = ((col - ua) * (vc - va) - (uc - ua) * (r - va)) / area
                w2 = ((ub - ua) * (r - va) - (col - ua) * (vb - va)) / area
                w0 = 1.0 - w1 - w2
                if w0 < -1e-9 or w1 < -1e-9 or w2 < -1e-9:
                    continue
                depth = w0 * a[2] + w1 * b[2] + w2 * c[2]
                if depth > z[r, col]:
                    z[r, col] = depth
    return z


def rasterize_depth(points: np.ndarray, triangles: np.ndarray, config: ResampleConfig = ResampleConfig()) -> np.ndarray:
    """(size, size) depth map z (mm) of a triangle mesh seen from +z; NaN where no surface."""
    w = config.half_width_mm
    z = _rasterize(np.ascontiguousarray(points, np.float64), np.ascontiguousarray(triangles, np.int64),
                   -w, w, config.resolution_mm, config.size)
    z[~np.isfinite(z)] = np.nan
    return z


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
    """The frontal-frame scan on a uniform x–y grid (front-most surface, linear interpolation)."""
    if scan.grid is None:
        raise ValueError("resampling needs a range-image grid (see preprocess.gridify for point clouds)")
    z = rasterize_depth(scan.points, scan.triangles(), config)
    return depth_to_scan(z, config, like=scan)


def depth_map(scan: FaceScan, config: ResampleConfig = ResampleConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(depth (size, size) with NaN where invalid, valid mask) of a resampled scan: the z of its range image."""
    if scan.grid is None or scan.grid_shape != (config.size, config.size):
        raise ValueError(f"not a preprocessed face: grid {scan.grid_shape}, expected the {config.size}×{config.size} "
                         "resampling grid (§8.5.6)")
    xyz, valid = scan.to_range_image()
    return xyz[..., 2], valid


def gridify(scan: FaceScan, resolution_mm: float = 0.7) -> FaceScan:
    """A grid scan from a point cloud seen along −z → +z (the front-most point of each x–y cell).

    For meshes and point clouds without a range-image grid; the face must
    look roughly along +z, as scanners' camera frames have it.
    """
    if scan.grid is not None:
        return scan
    if scan.n_points == 0:
        return scan.replace(grid=np.zeros((0, 2), np.int32), grid_shape=(0, 0))
    lo = scan.points[:, :2].min(axis=0)
    col = np.floor((scan.points[:, 0] - lo[0]) / resolution_mm).astype(np.int64)
    row = np.floor((scan.points[:, 1].max() - scan.points[:, 1]) / resolution_mm).astype(np.int64)
    shape = (int(row.max()) + 1, int(col.max()) + 1)
    if shape[0] * shape[1] > MAX_POINTS:  # the grid's images would not fit in memory; no face is that large
        raise FailureToAcquire(f"the point cloud spans {shape[0]}×{shape[1]} cells of {resolution_mm} mm, "
                               f"more than a face scan's {MAX_POINTS}")
    cell = row * shape[1] + col
    order = np.lexsort((-scan.points[:, 2], cell))  # per cell, front-most (largest z) first
    first = order[np.r_[True, cell[order][1:] != cell[order][:-1]]]
    front = scan.subset(first)
    return front.replace(grid=np.stack([row[first], col[first]], axis=1), grid_shape=shape)
