"""Noise removal (chapter §8.5.4): smoothing of depth that keeps the shape.

Works on any grid scan (a camera-frame range image or the resampled frontal
grid): the Z image is filtered, X and Y are kept. `median` removes impulsive
noise and keeps edges; `gaussian` is a normalised convolution (missing pixels
neither contribute nor get filled). Strength is given in mm on the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage

from facerec3d.preprocess.sampling import Sampling
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class DenoiseConfig:
    """Depth smoothing (§8.5.4)."""

    method: str = "median"  # "median", "gaussian" or "none"
    size_mm: float = 2.0  # median window width, or 2σ of the Gaussian

    def __post_init__(self) -> None:
        if self.method not in ("median", "gaussian", "none"):
            raise ValueError(f"unknown denoising method {self.method!r}: use median, gaussian or none")


@dataclass(frozen=True)
class SmoothConfig:
    """Smoothing of the camera-frame range image before the face is searched (§8.5.4), scaled to the scan:
    σ on the surface = `scale` × the finest depth detail the scan shows (its depth step, or 2σ of its noise;
    `sampling.Sampling.surface_mm`), in pixels of the measured pitch, capped at `max_px`; skipped below
    `min_px` (a laser scan of 0.25 mm noise at 0.7 mm pitch is left alone). Bilateral, so that depth edges stay."""

    scale: float = 1.0
    min_px: float = 1.0
    max_px: float = 3.0
    edge_factor: float = 3.0  # σ in depth of the bilateral weight: this many times the smoothing scale (mm)

    def sigmas(self, sampling: Sampling) -> tuple[float, float]:
        """(σ in pixels, σ in mm of depth) for a scan's sampling; σ_px = 0 means no smoothing."""
        sigma_mm = self.scale * sampling.surface_mm
        sigma_px = min(sigma_mm / sampling.pitch_mm, self.max_px) if sampling.pitch_mm > 0 else 0.0
        if not sigma_px >= self.min_px:
            return 0.0, 0.0
        return sigma_px, self.edge_factor * max(sigma_mm, sampling.pitch_mm)


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


@njit(cache=True)
def _bilateral(xyz, valid, sigma_px, sigma_mm):  # pragma: no cover - compiled
    """Masked bilateral filter of a range image of points: each valid pixel becomes the weighted mean of the
    valid pixels around it, weights exp(−Δpx² / 2σ_px²) · exp(−Δz² / 2σ_mm²) (Tomasi & Manduchi 1998)."""
    rows, cols = valid.shape
    half = int(np.ceil(2.5 * sigma_px))
    out = xyz.copy()
    for r in range(rows):
        for c in range(cols):
            if not valid[r, c]:
                continue
            z0 = xyz[r, c, 2]
            acc0 = 0.0
            acc1 = 0.0
            acc2 = 0.0
            wsum = 0.0
            for rr in range(max(r - half, 0), min(r + half + 1, rows)):
                for cc in range(max(c - half, 0), min(c + half + 1, cols)):
                    if not valid[rr, cc]:
                        continue
                    dz = xyz[rr, cc, 2] - z0
                    w = np.exp(-((rr - r) ** 2 + (cc - c) ** 2) / (2.0 * sigma_px * sigma_px)
                               - dz * dz / (2.0 * sigma_mm * sigma_mm))
                    acc0 += w * xyz[rr, cc, 0]
                    acc1 += w * xyz[rr, cc, 1]
                    acc2 += w * xyz[rr, cc, 2]
                    wsum += w
            out[r, c, 0] = acc0 / wsum
            out[r, c, 1] = acc1 / wsum
            out[r, c, 2] = acc2 / wsum
    return out


def smooth_range_image(scan: FaceScan, sigma_px: float, sigma_mm: float) -> FaceScan:
    """The grid scan's points smoothed by a masked bilateral filter (σ in pixels over the grid, σ in mm of depth):
    it removes the terraces of quantised depth and keeps depth edges (a face against its background)."""
    if scan.n_points == 0 or sigma_px <= 0:
        return scan
    xyz, valid = scan.to_range_image()
    out = _bilateral(np.nan_to_num(xyz), valid, float(sigma_px), float(sigma_mm))
    return scan.replace(points=out[scan.grid[:, 0], scan.grid[:, 1]], normals=None)
