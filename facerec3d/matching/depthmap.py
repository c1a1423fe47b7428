"""The depth-map representation of a preprocessed face (chapter §8.7.1), shared by PCA, LDA and curvature.

A preprocessed face lies on the resampling grid (§8.5.6: 1 mm cells over
±95 mm by default, nose tip at the origin, looking along +z). Its depth map z(x, y) is
cut to a square window around the nose tip and sampled every `step_mm`, so
every face becomes a vector of the same length with corresponding cells
(§8.7.1). Cells with no surface (outside the cropped sphere, self-occluded
by yaw, dropouts) are recorded in a validity mask and filled with the depth
of the nearest valid cell (Euclidean distance transform, scipy.ndimage) or,
for learnt matchers, with the training mean.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from facerec3d.config import check_ranges
from facerec3d.preprocess.resample import ResampleConfig, depth_map
from facerec3d.scan import FaceScan

FILLS = ("nearest", "mean")


@dataclass(frozen=True)
class DepthMapConfig:
    """Window and sampling of the depth map (§8.7.1)."""

    half_width_mm: float = 60.0  # the window is [−w, w]² mm around the nose tip: the face without the crop's
    #                              rim; on the 60 × 5 data as good as ±80 mm for LDA, better for PCA, better than ±40
    step_mm: float = 2.0  # cell spacing; a multiple of the resampling grid's cell (1 mm)
    fill: str = "nearest"  # missing cells: depth of the nearest valid cell, or "mean": the training mean
    #                        (learnt matchers only)
    grid: ResampleConfig = field(default_factory=ResampleConfig)  # the preprocessing's resampling grid (§8.5.6)

    def __post_init__(self) -> None:
        check_ranges(self)  # NaN or a negative named before the checks below compute with it
        if self.fill not in FILLS:
            raise ValueError(f"unknown fill {self.fill!r}: use one of {', '.join(FILLS)}")
        stride = self.step_mm / self.grid.resolution_mm
        if self.step_mm <= 0 or abs(stride - round(stride)) > 1e-9:
            raise ValueError("step_mm must be a positive multiple of the resampling grid's resolution_mm")
        if not 0 < self.half_width_mm <= self.grid.half_width_mm:
            raise ValueError(f"half_width_mm must be in (0, {self.grid.half_width_mm}]")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the window."""
        n = len(range(*self._slice().indices(self.grid.size)))
        return n, n

    def _slice(self) -> slice:
        res = self.grid.resolution_mm
        centre = (self.grid.size - 1) // 2
        half = round(self.half_width_mm / res)
        return slice(centre - half, centre + half + 1, round(self.step_mm / res))

    def window(self, image: np.ndarray) -> np.ndarray:
        """The window's cells of an image on the resampling grid (first two axes)."""
        s = self._slice()
        return image[s, s]


def depth_image(scan: FaceScan, grid: ResampleConfig | None = None) -> np.ndarray:
    """(size, size) depth z (mm) of a preprocessed face on the resampling grid (default: the preprocessing's
    default, §8.5.6), NaN where there is no surface."""
    return depth_map(scan, grid or ResampleConfig())[0]


def fill_nearest(z: np.ndarray) -> np.ndarray:
    """A copy of z with each NaN replaced by the value of its nearest non-NaN cell (all NaN: zeros)."""
    missing = np.isnan(z)
    if not missing.any():
        return z.copy()
    if missing.all():
        return np.zeros_like(z)
    index = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
    return z[tuple(index)]


def depth_window(scan: FaceScan, config: DepthMapConfig = DepthMapConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(z (rows, cols) mm with NaN where invalid, valid mask) of a preprocessed face in the window."""
    z = config.window(depth_image(scan, config.grid))
    return z, ~np.isnan(z)
