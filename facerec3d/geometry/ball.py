"""Points within a ball, and the nearest point: the neighbourhood tests preprocessing makes thousands of times per scan.

`np.linalg.norm(points - centre, axis=1) <= radius` allocates three temporaries the size of the scan and reduces
along the short axis; on a 480 × 640 scan (64,000 points) the face detector's ~70 such tests cost ~150 ms. The
compiled loop below makes one pass with the same arithmetic (the same differences, squares summed in the same
order, the same square root), so it selects exactly the same points. For many balls in one scan, `BallIndex`
buckets the points once (`bucket`, the counting sort into cells that the model fit's vertex grid uses too) and
tests only the points of the cells a ball reaches, with the same arithmetic.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _within(points, c0, c1, c2, radius):  # pragma: no cover - compiled
    out = np.empty(points.shape[0], np.bool_)
    for i in range(points.shape[0]):
        d0, d1, d2 = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
        out[i] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= radius
    return out


def within_ball(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """(n,) bool: which of the (n, 3) points lie within `radius` of `centre` (the same points as
    `np.linalg.norm(points - centre, axis=1) <= radius`)."""
    c = np.asarray(centre, dtype=np.float64)
    return _within(np.ascontiguousarray(points, dtype=np.float64), float(c[0]), float(c[1]), float(c[2]),
                   float(radius))


@njit(cache=True)
def _nearest(points, c0, c1, c2):  # pragma: no cover - compiled
    best, at = np.inf, 0
    for i in range(points.shape[0]):
        d0, d1, d2 = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
        d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if d < best:
            best, at = d, i
    return at


def nearest_index(points: np.ndarray, centre: np.ndarray) -> int:
    """The index of the point nearest to `centre`, the first of equals (`np.argmin` of the distances); the
    points must be finite and at least one."""
    c = np.asarray(centre, dtype=np.float64)
    return int(_nearest(np.ascontiguousarray(points, dtype=np.float64), float(c[0]), float(c[1]), float(c[2])))


class BallIndex:
    """The points bucketed by (x, y) once, for many `within` queries: the points of a dense scan within a ball
    around each of the detector's placements (a 480 × 640 scan's 64,000 points, ~65 queries) without testing
    every point each time. Same points, in the same order, as `np.flatnonzero(within_ball(points, centre, r))`."""

    CELL_MM = 8.0  # (larger for a scan spread over more than 1,024 cells, so memory stays bounded)

    def __init__(self, points: np.ndarray):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.lo, self.h, self.dims, self.start, self.order = bucket(self.points, 2, self.CELL_MM, 1024)

    def within(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """Indices (ascending) of the points within `radius` of `centre`."""
        c = np.asarray(centre, dtype=np.float64)
        return _ball_indices(self.points, self.lo, self.h, self.dims, self.start, self.order,
                             float(c[0]), float(c[1]), float(c[2]), float(radius))


@njit(cache=True)
def bucket(points, axes, h, most):  # pragma: no cover - compiled
    """Counting sort of points by their cell over their first `axes` coordinates: cells of size h, or larger so
    that at most `most` lie along an axis (memory stays bounded whatever the coordinates); (corner, cell size,
    cells along each axis, start of each cell's run in `order` (cells numbered axis by axis, the last fastest),
    the point indices cell by cell). A point with a coordinate that is not finite goes to cell 0: no finite
    ball holds it. The detector's ball index (x, y) and the model fit's nearest-vertex grid (x, y, z) use it."""
    n = points.shape[0]
    lo = np.full(axes, np.inf)
    hi = np.full(axes, -np.inf)
    finite = np.ones(n, np.bool_)
    for i in range(n):
        for d in range(axes):
            if not abs(points[i, d]) < np.inf:
                finite[i] = False
        if finite[i]:
            for d in range(axes):
                lo[d] = min(lo[d], points[i, d])
                hi[d] = max(hi[d], points[i, d])
    for d in range(axes):
        if lo[d] > hi[d]:
            lo[d] = hi[d] = 0.0
        h = max(h, (hi[d] - lo[d]) / (most - 1))
    dims = np.empty(axes, np.int64)
    cells = 1
    for d in range(axes):
        dims[d] = min(int(np.floor((hi[d] - lo[d]) / h)) + 1, most)
        cells *= dims[d]
    cell = np.zeros(n, np.int64)
    start = np.zeros(cells + 1, np.int64)
    for i in range(n):
        if finite[i]:
            idx = 0
            for d in range(axes):
                idx = idx * dims[d] + min(max(int(np.floor((points[i, d] - lo[d]) / h)), 0), dims[d] - 1)
            cell[i] = idx
        start[cell[i] + 1] += 1
    for k in range(cells):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return lo, h, dims, start, order


@njit(cache=True)
def _ball_indices(points, lo, h, dims, start, order, c0, c1, c2, radius):  # pragma: no cover - compiled
    """`BallIndex.within`: each point of the cells whose (x, y) span meets the ball's (widened past rounding)
    tested as `_within` tests it, the hits listed in index order; every point tested when the centre or the
    radius is not finite."""
    n = points.shape[0]
    mark = np.zeros(n, np.bool_)
    count = 0
    if abs(c0) < np.inf and abs(c1) < np.inf and abs(c2) < np.inf and abs(radius) < np.inf:
        reach = radius + 1e-6 * (1.0 + abs(radius) + abs(c0) + abs(c1))
        a_lo = int(max(np.floor((c0 - reach - lo[0]) / h), 0.0))  # clamped before the int: no overflow
        a_hi = int(min(np.floor((c0 + reach - lo[0]) / h), dims[0] - 1.0))
        b_lo = int(max(np.floor((c1 - reach - lo[1]) / h), 0.0))
        b_hi = int(min(np.floor((c1 + reach - lo[1]) / h), dims[1] - 1.0))
        for a in range(a_lo, a_hi + 1):
            for b in range(b_lo, b_hi + 1):
                k = a * dims[1] + b
                for s in range(start[k], start[k + 1]):
                    i = order[s]
                    d0, d1, d2 = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
                    if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= radius:
                        mark[i] = True
                        count += 1
    else:
        for i in range(n):
            d0, d1, d2 = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
            if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) <= radius:
                mark[i] = True
                count += 1
    out = np.empty(count, np.int64)
    m = 0
    for i in range(n):
        if mark[i]:
            out[m] = i
            m += 1
    return out
