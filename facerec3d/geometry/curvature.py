"""Normals and curvature of a depth map z(x, y) (chapter §8.9).

The surface is the graph (x, y, z(x, y)) sampled on a square grid (a Monge
patch). z is smoothed with a Gaussian of σ = `sigma_mm` (scipy.ndimage)
and differentiated by central differences (numpy.gradient, twice for the
second derivatives), which is exact for quadrics. With W = √(1 + z_x² + z_y²):

* normal n = (−z_x, −z_y, 1) / W, towards the viewer (+z; the face looks along +z);
* Gaussian curvature K = (z_xx z_yy − z_xy²) / W⁴;
* mean curvature H = −((1 + z_y²) z_xx − 2 z_x z_y z_xy + (1 + z_x²) z_yy) / (2 W³);
* principal curvatures k1 ≥ k2 = H ± √(H² − K);
* shape index S = (2/π) arctan((k1 + k2) / (k1 − k2)) ∈ [−1, 1] (Koenderink & van Doorn);
* curvedness C = √((k1² + k2²) / 2) (1/mm).

Sign convention: curvatures are positive where the surface is convex
towards the viewer, as the nose tip is: a sphere of radius r seen from
outside has H = 1/r, K = 1/r². Shape index: cap (nose tip) +1, ridge
(nose bridge) +0.5, saddle 0, rut −0.5, cup (eye socket) −1; at planar
points (k1 = k2 = 0) it is undefined and set to 0 (their curvedness is 0).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage


class Curvature(NamedTuple):
    """Per-cell differential geometry of a depth map; curvatures in 1/mm, K in 1/mm²."""

    normals: np.ndarray  # (H, W, 3) unit, towards +z
    k1: np.ndarray  # (H, W) larger principal curvature
    k2: np.ndarray  # (H, W) smaller principal curvature
    mean: np.ndarray  # (H, W) H = (k1 + k2) / 2
    gaussian: np.ndarray  # (H, W) K = k1 k2
    shape_index: np.ndarray  # (H, W) in [−1, 1]
    curvedness: np.ndarray  # (H, W)


def depth_curvature(z: np.ndarray, spacing_mm: float = 1.0, sigma_mm: float = 2.0) -> Curvature:
    """Normals and curvatures of a depth map z (rows = −y, columns = +x, as the resampling grid, §8.5.6) in mm
    with no gaps (fill them first) on a grid of `spacing_mm`, smoothed at scale `sigma_mm` (Gaussian σ)."""
    z = np.asarray(z, dtype=np.float64)
    if np.isnan(z).any():
        raise ValueError("the depth map has gaps: fill them first")
    smooth = ndimage.gaussian_filter(z, sigma_mm / spacing_mm, mode="nearest")
    z_row, zx = np.gradient(smooth, spacing_mm)  # rows run along −y: ∂/∂y = −∂/∂row
    zy = -z_row
    zx_row, zxx = np.gradient(zx, spacing_mm)
    zxy, zyy = -zx_row, -np.gradient(zy, spacing_mm, axis=0)
    w2 = 1.0 + zx**2 + zy**2
    w = np.sqrt(w2)
    K = (zxx * zyy - zxy**2) / w2**2
    H = -((1 + zy**2) * zxx - 2 * zx * zy * zxy + (1 + zx**2) * zyy) / (2 * w2 * w)
    root = np.sqrt(np.maximum(H**2 - K, 0.0))
    k1, k2 = H + root, H - root
    normals = np.stack([-zx, -zy, np.ones_like(z)], axis=-1) / w[..., None]
    shape_index = (2 / np.pi) * np.arctan2(k1 + k2, k1 - k2)
    curvedness = np.sqrt((k1**2 + k2**2) / 2)
    return Curvature(normals, k1, k2, H, K, shape_index, curvedness)
