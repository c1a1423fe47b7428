"""Noise removal (chapter §8.5.4): smoothing of depth that keeps the shape.

Works on any grid scan (a camera-frame range image or the resampled frontal
grid): the Z image is filtered, X and Y are kept. `median` removes impulsive
noise and keeps edges; `gaussian` is a normalised convolution (missing pixels
neither contribute nor get filled). Strength is given in mm on the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class DenoiseConfig:
    """Depth smoothing (§8.5.4)."""

    method: str = "median"  # "median", "gaussian" or "none"
    size_mm: float = 2.0  # median window width, or 2σ of the Gaussian


def denoise(scan: FaceScan, config: DenoiseConfig = DenoiseConfig()) -> FaceScan:
    """The scan with its depth (Z) smoothed over the grid."""
    if config.method == "none" or scan.n_points == 0:
        return scan
    xyz, valid = scan.to_range_image()
    z = xyz[..., 2]
    px = config.size_mm / scan.resolution()
    if config.method == "median":
        size = max(3, int(round(px)) | 1)
        nearest = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        smooth = ndimage.median_filter(z[tuple(nearest)], size=size)
    elif config.method == "gaussian":
        sigma = max(px / 2.0, 0.5)
        w = ndimage.gaussian_filter(valid.astype(float), sigma)
        smooth = ndimage.gaussian_filter(np.where(valid, z, 0.0), sigma) / np.maximum(w, 1e-12)
    else:
        raise ValueError(f"unknown denoising method {config.method!r}: use median, gaussian or none")
    points = scan.points.copy()
    points[:, 2] = smooth[scan.grid[:, 0], scan.grid[:, 1]]
    return scan.replace(points=points, normals=None)
