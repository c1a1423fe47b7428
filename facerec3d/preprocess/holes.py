"""Hole filling (chapter §8.5.3): interpolate missing data inside the face.

Holes are the groups of missing range-image pixels enclosed by valid ones
(eyes, specular dropouts, an open mouth), once gaps of a pixel or two in
their rim are sealed; missing pixels connected to the outside of the face
are the boundary and stay missing. Each hole's X, Y and Z images are
filled by the thin plate through the valid pixels around it (the surface of least bending) on a fine (laser) scan,
by cubic (Clough–Tocher) interpolation over a ring of them on a coarser one (`HoleConfig.interpolation`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage
from scipy.interpolate import griddata

from facerec3d.scan import FILLED, FaceScan


@dataclass(frozen=True)
class HoleConfig:
    """Hole-filling settings (§8.5.3)."""

    max_area_mm2: float = 2000.0  # larger enclosed holes are left open
    seal_px: int = 2  # gaps in the rim this wide (scattered dropouts) do not open a hole to the outside
    interpolation: str = "auto"  # "cubic": Clough–Tocher interpolation over a ring of valid pixels (scipy's
    #   griddata; the chapter's cubic interpolation). "thin-plate": the surface of least bending through the pixels
    #   around each hole (`_thin_plate`, one sparse solve): nearer the generator's true surface (0.42 mm RMS on its
    #   dropouts against 0.68) and an FRGC-size scan's holes in ~7 ms instead of ~45. "auto" (since 2026-12-06): the
    #   thin plate on scans finer than `fine_mm` (laser scans, whose hundreds of dropouts make the cubic's
    #   triangulation slow; no accuracy figure moved there), the cubic on coarser ones (depth cameras, with few
    #   holes; the thin plate cost one probe of 45 on kinect-v2-outside there: docs/benchmarks.md)
    fine_mm: float = 1.5  # "auto": the pitch (the face's `resolution`) below which the thin plate fills
    ring_px: int = 3  # "cubic": width of the ring of valid pixels interpolated from
    stretch: float = 0.01  # "thin-plate": weight of the membrane (stretching) energy beside the bending one
    RETIRED: ClassVar[dict] = {"small_mm2": 0.0}  # settings files and galleries of 2026-12-06 (session 30) hold it

    def __post_init__(self) -> None:
        if self.interpolation not in ("auto", "thin-plate", "cubic"):
            raise ValueError(f"interpolation must be \"auto\", \"thin-plate\" or \"cubic\", not "
                             f"{self.interpolation!r}")
        if not self.stretch > 0:
            raise ValueError(f"stretch must be > 0, not {self.stretch}")


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


_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)


def _thin_plate_fill(xyz: np.ndarray, valid: np.ndarray, holes: np.ndarray, stretch: float) -> np.ndarray:
    """(n, 3) X, Y and Z at the `holes` pixels (row-major order): `_thin_plate` through the valid pixels around each
    hole; a hole that no valid pixel borders (4-neighbours: a notch of the outline that sealing closed, touching the
    face only diagonally) takes its nearest valid pixel's values."""
    labels, n = ndimage.label(holes, _CROSS)
    anchored = np.bincount(labels[ndimage.binary_dilation(valid, _CROSS) & holes], minlength=n + 1) > 0
    anchored[0] = False
    solved = anchored[labels]
    values = np.empty((int(holes.sum()), 3))
    order = solved[holes]
    values[order] = _thin_plate(xyz, valid, solved, stretch)
    if not order.all():
        _, (r, c) = ndimage.distance_transform_edt(~valid, return_indices=True)
        rr, cc = np.nonzero(holes & ~solved)
        values[~order] = xyz[r[rr, cc], c[rr, cc]]
    return values


def _thin_plate(xyz: np.ndarray, valid: np.ndarray, wanted: np.ndarray, stretch: float) -> np.ndarray:
    """(n, 3) X, Y and Z at the `wanted` pixels (row-major order; each group of them borders a valid pixel)
    minimising the discrete thin-plate (bending) energy Σ (Δu)² over every pixel whose 5-point Laplacian Δ lies on
    valid or wanted pixels and touches a wanted one, plus `stretch` × the membrane energy Σ (u_p − u_q)² over the
    edges from wanted pixels to their wanted or valid 4-neighbours, the valid pixels fixed (least squares, one sparse
    solve; cf. biharmonic inpainting). The membrane term holds pixels that no whole Laplacian reaches (a gap in a
    hole's rim) and keeps the solve well posed."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    rows, cols = np.nonzero(wanted)
    n = len(rows)
    index = np.full(wanted.shape, -1, np.int64)
    index[rows, cols] = np.arange(n)
    terms: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []  # (row, pixel r, pixel c, weight)
    n_rows = 0

    def add_rows(weighted: list[tuple[np.ndarray, np.ndarray, float]]) -> None:
        nonlocal n_rows
        m = len(weighted[0][0])
        for r, c, w in weighted:
            terms.append((n_rows + np.arange(m), r, c, np.full(m, w)))
        n_rows += m

    # bending: the Laplacian at each pixel whose stencil holds data and touches a wanted pixel
    whole = ndimage.binary_erosion(valid | wanted, _CROSS, border_value=0)
    at = np.nonzero(whole & ndimage.binary_dilation(wanted, _CROSS))
    add_rows([(at[0], at[1], -4.0)] + [(at[0] + dr, at[1] + dc, 1.0) for dr, dc in _STEPS])
    weight = float(np.sqrt(stretch))
    for dr, dc in _STEPS:  # stretching: each edge from a wanted pixel to a known or (once) to a wanted one
        r, c = rows + dr, cols + dc
        inside = (r >= 0) & (r < wanted.shape[0]) & (c >= 0) & (c < wanted.shape[1])
        r, c = np.where(inside, r, 0), np.where(inside, c, 0)
        edge = inside & (valid[r, c] | (index[r, c] > np.arange(n)))
        add_rows([(rows[edge], cols[edge], weight), (r[edge], c[edge], -weight)])
    i, r, c, w = (np.concatenate(x) for x in zip(*terms))
    unknown = index[r, c] >= 0
    A = coo_matrix((w[unknown], (i[unknown], index[r[unknown], c[unknown]])), shape=(n_rows, n)).tocsr()
    b = np.zeros((n_rows, 3))
    for k in range(3):
        b[:, k] = -np.bincount(i[~unknown], w[~unknown] * xyz[r[~unknown], c[~unknown], k], minlength=n_rows)
    return np.asarray(spsolve((A.T @ A).tocsc(), A.T @ b)).reshape(n, 3)


def fill_holes(scan: FaceScan, config: HoleConfig = HoleConfig()) -> FaceScan:
    """The scan with its holes filled; filled points get no normal or colour (normals and colours are dropped) and
    the provenance FILLED."""
    if not scan.n_points:
        return scan
    xyz, valid, lo = _window(scan, _margin(config))
    pitch = scan.resolution()
    holes = _holes(valid, pitch**2, config)
    if not holes.any():
        return scan
    at = np.argwhere(holes)
    if config.interpolation == "thin-plate" or (config.interpolation == "auto" and pitch < config.fine_mm):
        values = _thin_plate_fill(xyz, valid, holes, config.stretch)
    else:  # cubic over the ring, interpolated in the scan's grid (+ lo): the pixels it always saw, to the bit
        ring = ndimage.binary_dilation(holes, iterations=config.ring_px) & valid
        known = np.argwhere(ring)
        values = griddata(known + lo, xyz[ring], at + lo, method="cubic")
        bad = ~np.isfinite(values).all(axis=1)
        if bad.any():
            values[bad] = griddata(known + lo, xyz[ring], at[bad] + lo, method="nearest")
    return scan.replace(
        points=np.concatenate([scan.points, values]),
        grid=np.concatenate([scan.grid, at + lo]),
        normals=None,
        colors=None,
        provenance=np.concatenate([np.zeros(scan.n_points, np.uint8) if scan.provenance is None else scan.provenance,
                                   np.full(len(values), FILLED, np.uint8)]),
    )
