"""Hole filling (chapter §8.5.3): interpolate missing data inside the face.

Holes are the groups of missing range-image pixels enclosed by valid ones
(eyes, specular dropouts, an open mouth), once gaps of a pixel or two in
their rim are sealed; missing pixels connected to the outside of the face
are the boundary and stay missing. Each hole is filled by
cubic (Clough–Tocher) interpolation of the X, Y and Z images over a ring of
valid pixels around it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.interpolate import griddata

from facerec3d.scan import FILLED, FaceScan


@dataclass(frozen=True)
class HoleConfig:
    """Hole-filling settings (§8.5.3)."""

    max_area_mm2: float = 2000.0  # larger enclosed holes are left open
    ring_px: int = 3  # width of the ring of valid pixels interpolated from
    seal_px: int = 2  # gaps in the rim this wide (scattered dropouts) do not open a hole to the outside


def _window(scan: FaceScan, margin: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xyz, valid, origin): the range image of `FaceScan.windowed(margin)`. Nothing beyond the margin holds a point,
    so closing, hole filling and dilating by less than `margin` pixels give inside it what they give on the whole
    grid."""
    window, lo = scan.windowed(margin)
    return *window.to_range_image(), lo


def _margin(config: HoleConfig) -> int:
    """Pixels of empty border that `hole_mask` and `fill_holes` need around the points (their reach, plus one)."""
    return max(config.seal_px, config.ring_px) + 2


def _holes(valid: np.ndarray, pixel_area: float, config: HoleConfig) -> np.ndarray:
    """`hole_mask` of a range image's valid mask."""
    sealed = ndimage.binary_closing(valid, np.ones((3, 3), bool), iterations=config.seal_px, border_value=0)
    holes = ndimage.binary_fill_holes(sealed | valid) & ~valid
    labels, n = ndimage.label(holes)
    if n == 0:
        return holes
    area = ndimage.sum_labels(holes, labels, index=np.arange(1, n + 1)) * pixel_area
    return np.isin(labels, 1 + np.flatnonzero(area <= config.max_area_mm2))


def hole_mask(scan: FaceScan, config: HoleConfig = HoleConfig()) -> np.ndarray:
    """(H, W) bool: the missing pixels of the scan's grid that holes consist of (small enough to fill)."""
    mask = np.zeros(scan.grid_shape, dtype=bool)
    if scan.n_points:
        _, valid, lo = _window(scan, _margin(config))
        h, w = valid.shape
        mask[lo[0]:lo[0] + h, lo[1]:lo[1] + w] = _holes(valid, scan.resolution() ** 2, config)
    return mask


def fill_holes(scan: FaceScan, config: HoleConfig = HoleConfig()) -> FaceScan:
    """The scan with its holes filled; filled points get no normal or colour (normals and colours are dropped) and
    the provenance FILLED."""
    if not scan.n_points:
        return scan
    xyz, valid, lo = _window(scan, _margin(config))
    holes = _holes(valid, scan.resolution() ** 2, config)
    if not holes.any():
        return scan
    ring = ndimage.binary_dilation(holes, iterations=config.ring_px) & valid
    known = np.argwhere(ring) + lo  # in the scan's grid: the interpolation sees the pixels it always saw
    wanted = np.argwhere(holes) + lo
    values = griddata(known, xyz[ring], wanted, method="cubic")
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        values[bad] = griddata(known, xyz[ring], wanted[bad], method="nearest")
    return scan.replace(
        points=np.concatenate([scan.points, values]),
        grid=np.concatenate([scan.grid, wanted]),
        normals=None,
        colors=None,
        provenance=np.concatenate([np.zeros(scan.n_points, np.uint8) if scan.provenance is None else scan.provenance,
                                   np.full(len(values), FILLED, np.uint8)]),
    )
