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
    small_mm2: float = 0.0  # holes of at most this area (dropouts of a laser scanner: a few 0.7 mm pixels) are filled
    #                         by harmonic interpolation from the pixels around them (`_harmonic`), not the cubic one
    #                         (0: every hole cubic)


def _window(scan: FaceScan, margin: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(xyz, valid, origin): the range image of `FaceScan.windowed(margin)`. Nothing beyond the margin holds a point,
    so closing, hole filling and dilating by less than `margin` pixels give inside it what they give on the whole
    grid."""
    window, lo = scan.windowed(margin)
    return *window.to_range_image(), lo


def _margin(config: HoleConfig) -> int:
    """Pixels of empty border that `hole_mask` and `fill_holes` need around the points (their reach and two more)."""
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


_STEPS = ((-1, 0), (1, 0), (0, -1), (0, 1))


def _small(holes: np.ndarray, valid: np.ndarray, most: int) -> np.ndarray:
    """The pixels of the holes of at most `most` pixels that border a valid pixel (4-neighbours)."""
    labels, n = ndimage.label(holes)
    size = np.bincount(labels.ravel(), minlength=n + 1)
    grown = ndimage.binary_dilation(valid, np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool))
    touches = np.bincount(labels[grown & holes], minlength=n + 1) > 0
    keep = (size <= most) & touches
    keep[0] = False
    return keep[labels]


def _harmonic(xyz: np.ndarray, valid: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """(n, 3) X, Y and Z at the `wanted` pixels (row-major order) solving Laplace's equation, the valid pixels
    around them fixed (the discrete membrane; a dropout of a few pixels on a face is as flat as that)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    rows, cols = np.nonzero(wanted)
    n = len(rows)
    index = np.full(wanted.shape, -1, np.int64)
    index[rows, cols] = np.arange(n)
    degree, b = np.zeros(n), np.zeros((n, 3))
    i_all, j_all = [], []
    for dr, dc in _STEPS:
        r, c = rows + dr, cols + dc
        inside = (r >= 0) & (r < wanted.shape[0]) & (c >= 0) & (c < wanted.shape[1])
        r, c = np.where(inside, r, 0), np.where(inside, c, 0)
        unknown = inside & (index[r, c] >= 0)
        known = inside & ~unknown & valid[r, c]
        degree += unknown | known
        np.add.at(b, np.flatnonzero(known), xyz[r[known], c[known]])
        i_all.append(np.flatnonzero(unknown))
        j_all.append(index[r[unknown], c[unknown]])
    i, j = np.concatenate(i_all), np.concatenate(j_all)
    A = coo_matrix((np.r_[degree, -np.ones(len(i))], (np.r_[np.arange(n), i], np.r_[np.arange(n), j])),
                   shape=(n, n)).tocsc()
    return np.asarray(spsolve(A, b)).reshape(n, 3)


def fill_holes(scan: FaceScan, config: HoleConfig = HoleConfig()) -> FaceScan:
    """The scan with its holes filled; filled points get no normal or colour (normals and colours are dropped) and
    the provenance FILLED."""
    if not scan.n_points:
        return scan
    xyz, valid, lo = _window(scan, _margin(config))
    pixel_area = scan.resolution() ** 2
    holes = _holes(valid, pixel_area, config)
    if not holes.any():
        return scan
    small = _small(holes, valid, int(config.small_mm2 / pixel_area)) if config.small_mm2 > 0 else np.zeros_like(holes)
    large = holes & ~small
    filled = []  # (pixels of the window, their X, Y, Z)
    if small.any():
        filled.append((np.argwhere(small), _harmonic(xyz, valid, small)))
    if large.any():
        ring = ndimage.binary_dilation(large, iterations=config.ring_px) & valid
        known, at = np.argwhere(ring), np.argwhere(large)  # interpolated in the scan's grid (+ lo): the pixels it
        cubic = griddata(known + lo, xyz[ring], at + lo, method="cubic")  # always saw, to the bit
        bad = ~np.isfinite(cubic).all(axis=1)
        if bad.any():
            cubic[bad] = griddata(known + lo, xyz[ring], at[bad] + lo, method="nearest")
        filled.append((at, cubic))
    wanted = np.concatenate([at for at, _ in filled]) + lo
    values = np.concatenate([v for _, v in filled])
    return scan.replace(
        points=np.concatenate([scan.points, values]),
        grid=np.concatenate([scan.grid, wanted]),
        normals=None,
        colors=None,
        provenance=np.concatenate([np.zeros(scan.n_points, np.uint8) if scan.provenance is None else scan.provenance,
                                   np.full(len(values), FILLED, np.uint8)]),
    )
