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

from facerec3d.geometry.ball import within_ball
from facerec3d.preprocess.sampling import Sampling
from facerec3d.scan import FaceScan, column_bounds


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
        smooth = _masked_gaussian(z, valid, max(px / 2.0, 0.5))
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


@dataclass(frozen=True)
class DequantiseConfig:
    """Restoring the shape that coarse depth steps hide (§8.5.4), after the face is found.

    A depth camera that keeps depth in coarse steps (8 mm for rap3df-2019's one byte at 1.2 m) reports, for each
    pixel, only the step its true depth rounds to. Smoothing the terraces away (`SmoothConfig`) also flattens the
    nose: on synthetic Kinect v2 frames stored with 8-bit depth the bilateral filter puts the nose tip 5.6 mm behind
    the true surface. Here the smoothed depth is made consistent with what was measured again, by alternating
    projections (POCS; cf. the constrained smoothing of quantised images, Youla & Webb, IEEE TMI 1982): each pixel's
    depth is clipped to the interval that rounds to its measured step, then smoothed by a narrow Gaussian, `rounds`
    times. It is applied only where the steps dominate the noise (the raw depth's deviation from its smoothed self is at
    most `max_noise_ratio` × step/√12, the spread of pure rounding): on rap3df-2019 and synthetic 8-bit frames it is
    1.1–1.25, on a RealSense's disparity-quantised depth, whose noise exceeds its steps, 2–2.4."""

    rounds: int = 20  # alternating clip / smooth rounds (0: off); 20 and 100 gave the same surface
    sigma_px: float = 0.5  # σ of the smoothing between clips (pixels); 0.7 left 0.1 mm more error
    max_noise_ratio: float = 1.5  # dequantise only when the raw depth's residual is at most this × step/√12

    def __post_init__(self) -> None:
        if self.rounds < 0 or not self.sigma_px > 0 or not self.max_noise_ratio > 0:
            raise ValueError("dequantise: rounds must be ≥ 0, sigma_px and max_noise_ratio > 0")


def _masked_gaussian(z: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised convolution: the Gaussian mean of the valid pixels around each pixel."""
    w = ndimage.gaussian_filter(valid.astype(float), sigma)
    return ndimage.gaussian_filter(np.where(valid, z, 0.0), sigma) / np.maximum(w, 1e-12)


def quantisation_intervals(z: np.ndarray, valid: np.ndarray, step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel, the depth interval (lo, hi) that rounds to its measured level: halfway to the next lower and
    higher levels present in the image (levels need not be evenly spaced: a Kinect's 8-bit depth changes step at
    1024 mm), never more than `step_mm` / 2 on either side (a level whose neighbour is absent)."""
    levels = np.unique(z[valid])
    below = np.minimum(np.diff(levels, prepend=-np.inf), step_mm) / 2
    above = np.minimum(np.diff(levels, append=np.inf), step_mm) / 2
    i = np.searchsorted(levels, np.where(valid, z, levels[0]))
    return levels[i] - below[i], levels[i] + above[i]


def dequantise(scan: FaceScan, raw: FaceScan, step_mm: float, center: np.ndarray, radius_mm: float,
               config: DequantiseConfig = DequantiseConfig()) -> FaceScan:
    """`scan` (the smoothed grid scan) with the depth of its points within `radius_mm` of `center` brought back
    within the quantisation intervals of `raw` (the same grid before smoothing) by alternating projections
    (`DequantiseConfig`). Points move along their line of sight from the camera at the origin (a depth camera's
    frame), so they stay on their pixel's ray. Unchanged when the depth is not quantised (`step_mm` 0), the
    noise exceeds the steps, or `rounds` is 0."""
    if config.rounds == 0 or step_mm <= 0 or scan.n_points == 0 or scan.grid is None:
        return scan
    near = within_ball(scan.points, center, radius_mm)
    if near.sum() < 10:
        return scan
    lo_rc, hi_rc = column_bounds(scan.grid[near])
    hi_rc = hi_rc + 1
    window = (slice(lo_rc[0], hi_rc[0]), slice(lo_rc[1], hi_rc[1]))
    xyz_s, valid = scan.to_range_image()
    xyz_r, valid_r = raw.to_range_image()
    zs, zr, ok = xyz_s[window][..., 2], xyz_r[window][..., 2], (valid & valid_r)[window]
    inner = ok & ndimage.minimum_filter(ok, 5)
    residual = (zr - _masked_gaussian(zr, ok, 1.0))[inner]
    if len(residual) < 10:
        return scan
    spread = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    if spread > config.max_noise_ratio * step_mm / np.sqrt(12.0):
        return scan  # noise, not rounding, dominates: the measured level says little more than the smoothing
    lo, hi = quantisation_intervals(zr, ok, step_mm)
    z = np.where(ok, zs, 0.0)
    for _ in range(config.rounds):
        z = np.clip(z, lo, hi)
        z = np.where(ok, _masked_gaussian(z, ok, config.sigma_px), z)
    z = np.clip(z, lo, hi)
    r, c = scan.grid[near, 0] - lo_rc[0], scan.grid[near, 1] - lo_rc[1]  # inside the window by its making
    moved = near.copy()
    moved[near] = ok[r, c] & (np.abs(scan.points[near, 2]) > 1e-9)  # (a camera's points all lie off its plane)
    r, c = scan.grid[moved, 0] - lo_rc[0], scan.grid[moved, 1] - lo_rc[1]
    points = scan.points.copy()
    points[moved] *= (z[r, c] / points[moved, 2])[:, None]  # along the ray through the camera at the origin
    return scan.replace(points=points, normals=None)
