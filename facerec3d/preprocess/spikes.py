"""Spike removal (chapter §8.5.2): outliers found from neighbourhood statistics.

On a range-image grid a spike is a point with too few grid neighbours near it
in 3D: a real surface point has most of its window's pixels within a few
millimetres, a spike (a pixel whose depth is off by tens of millimetres,
nearer or farther) has almost none. Scans without a grid use the same test
on their k nearest neighbours in 3D.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from facerec3d.preprocess.sampling import Sampling
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class SpikeConfig:
    """Spike-removal settings (§8.5.2)."""

    window: int = 2  # half-width of the grid window in pixels (5×5)
    distance_mm: float = 4.0  # a neighbour within this 3D distance supports a point ...
    scale: float = 2.0  # ... or within this many times the scan's pitch or depth step, whichever is larger
    min_support: int = 3  # fewer supporting neighbours than this makes a spike
    k: int = 8  # neighbours for scans without a grid


@njit(cache=True)
def _grid_support(index_image, points, window, dist2):  # pragma: no cover - compiled
    n = points.shape[0]
    support = np.zeros(n, np.int32)
    rows, cols = index_image.shape
    for r in range(rows):
        for c in range(cols):
            i = index_image[r, c]
            if i < 0:
                continue
            count = 0
            for rr in range(max(r - window, 0), min(r + window + 1, rows)):
                for cc in range(max(c - window, 0), min(c + window + 1, cols)):
                    j = index_image[rr, cc]
                    if j < 0 or j == i:
                        continue
                    d0 = points[i, 0] - points[j, 0]
                    d1 = points[i, 1] - points[j, 1]
                    d2 = points[i, 2] - points[j, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= dist2:
                        count += 1
            support[i] = count
    return support


def support_distance(config: SpikeConfig, sampling: Sampling | None = None) -> float:
    """The 3D distance (mm) within which a neighbour supports a point: the configured floor, or `scale` times the
    measured pitch or depth step (a 3.5 mm Kinect pixel with 8 mm depth steps needs ~16 mm, a 0.7 mm laser
    pixel keeps the 4 mm floor)."""
    if sampling is None:
        return config.distance_mm
    return max(config.distance_mm, config.scale * max(sampling.pitch_mm, sampling.depth_step_mm))


def spike_mask(scan: FaceScan, config: SpikeConfig = SpikeConfig(), sampling: Sampling | None = None) -> np.ndarray:
    """(N,) bool: True for the points judged to be spikes."""
    if scan.n_points == 0:
        return np.zeros(0, bool)
    distance = support_distance(config, sampling)
    if scan.grid is not None:
        support = _grid_support(scan.index_image(), scan.points, config.window, distance**2)
        return support < config.min_support
    from scipy.spatial import cKDTree

    k = min(config.k + 1, scan.n_points)
    d, _ = cKDTree(scan.points).query(scan.points, k=k)
    support = (d[:, 1:] <= distance).sum(axis=1)
    return support < min(config.min_support, k - 1)


def remove_spikes(scan: FaceScan, config: SpikeConfig = SpikeConfig(), sampling: Sampling | None = None) -> FaceScan:
    """The scan without its spikes (thresholds scaled to the measured `sampling` when given)."""
    return scan.subset(~spike_mask(scan, config, sampling))
