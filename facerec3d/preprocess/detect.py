"""Face detection and segmentation (chapter §8.5.1): find the nose tip, crop a sphere around it.

The nose tip is not taken as the point of largest Z (spikes, hair, chin and
shoulders can be nearer than the nose). Candidates are the points that
protrude most from their surroundings on a ~2 mm sub-sampled range image
(local maxima of height above a 40 mm local mean, with the window well
covered by data, so that the rims of the scan do not count). Each candidate
is verified by a rigid fit of the morphable model's mean face around it; the
candidate where most points fit wins, and a full fit of the model (pose,
identity, expression; `pose.fit_face_model`) gives the nose tip, the other
fiducials and the frontal pose. A scan where nothing fits a face is a
failure to acquire.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy import ndimage

from facerec3d.errors import FailureToAcquire
from facerec3d.preprocess.pose import ModelFit, ModelFitConfig, fit_face_model, hotelling_rotation
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class DetectConfig:
    """Nose-tip detection and face cropping (§8.5.1)."""

    sample_mm: float = 2.0  # spacing of the sub-sampled range image used for the search
    window_mm: float = 40.0  # the local mean that protrusion is measured against
    min_coverage: float = 0.7  # share of that window that must hold data
    separation_mm: float = 25.0  # candidates are local maxima over this distance
    candidates: int = 4  # how many candidates are verified
    context_mm: float = 100.0  # points within this distance of a candidate are aligned
    min_coarse_inliers: float = 0.3  # least share of points near a candidate fitting the mean face (rigid)
    min_inliers: float = 0.5  # least share of the scan points near the nose that fit the full face model
    max_identity_rms: float = 2.0  # RMS of the fitted identity coefficients (prior N(0, 1)) beyond which no face is plausible
    tie_margin: float = 0.1  # a distinct placement this close to the best one also gets a full fit
    crop_radius_mm: float = 80.0  # the face is the sphere of this radius around the nose tip
    coarse: ModelFitConfig = field(default_factory=lambda: ModelFitConfig(
        identity_modes=0, expression_modes=False, iterations=15, start_distance_mm=20.0, end_distance_mm=5.0,
        max_points=800))  # rigid fit of the mean face, to verify each candidate
    model: ModelFitConfig = field(default_factory=ModelFitConfig)  # full fit of the winner


@dataclass(frozen=True)
class Detection:
    """A detected face, in scan coordinates (mm): nose tip, fiducials, and the map x -> R x + t
    into the frontal frame (looking along +z, y up, nose tip at the origin)."""

    nose_tip: np.ndarray
    R: np.ndarray
    t: np.ndarray
    landmarks: dict[str, np.ndarray]
    fit_rms_mm: float
    inlier_fraction: float


def _subsample(scan: FaceScan, spacing_mm: float) -> tuple[FaceScan, float]:
    """The grid scan on every k-th row and column so that points are ~spacing_mm apart; (scan, spacing)."""
    res = scan.resolution()
    step = max(1, int(round(spacing_mm / res)))
    g = scan.grid
    keep = (g[:, 0] % step == 0) & (g[:, 1] % step == 0)
    sub = scan.subset(keep)
    h, w = scan.grid_shape
    sub = sub.replace(grid=sub.grid // step, grid_shape=((h + step - 1) // step, (w + step - 1) // step))
    return sub, res * step


@njit(cache=True)
def _protrusion(xyz, valid, half, reach2, min_coverage):  # pragma: no cover - compiled
    """Height (Z) of each pixel above the mean of the window pixels within `reach` in 3D."""
    rows, cols = valid.shape
    out = np.full((rows, cols), -np.inf)
    full = (2 * half + 1) ** 2
    for r in range(half, rows - half):
        for c in range(half, cols - half):
            if not valid[r, c]:
                continue
            total = 0.0
            count = 0
            for rr in range(r - half, r + half + 1):
                for cc in range(c - half, c + half + 1):
                    if not valid[rr, cc]:
                        continue
                    d0 = xyz[rr, cc, 0] - xyz[r, c, 0]
                    d1 = xyz[rr, cc, 1] - xyz[r, c, 1]
                    d2 = xyz[rr, cc, 2] - xyz[r, c, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= reach2:
                        total += xyz[rr, cc, 2]
                        count += 1
            if count >= min_coverage * full:
                out[r, c] = xyz[r, c, 2] - total / count
    return out


def nose_candidates(scan: FaceScan, config: DetectConfig = DetectConfig()) -> tuple[FaceScan, np.ndarray]:
    """(sub-sampled scan, indices of its candidate nose tips, best first).

    Protrusion is measured against the surface connected to a point (window
    pixels within the window's reach in 3D), so a chin over a far-away neck
    or a shoulder rim does not stand out.
    """
    sub, spacing = _subsample(scan, config.sample_mm)
    xyz, valid = sub.to_range_image()
    half = max(1, int(round(config.window_mm / spacing / 2)))
    protrusion = _protrusion(np.nan_to_num(xyz), valid, half, (0.75 * config.window_mm) ** 2, config.min_coverage)
    sep = max(3, int(round(config.separation_mm / spacing)) | 1)
    peaks = np.isfinite(protrusion) & (protrusion == ndimage.maximum_filter(protrusion, sep, mode="constant", cval=-np.inf))
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-protrusion[rows, cols])[: config.candidates]
    return sub, sub.index_image()[rows[order], cols[order]]


def detect_face(scan: FaceScan, config: DetectConfig = DetectConfig()) -> Detection:
    """Find the nose tip, fiducials and frontal pose of a scan; raises FailureToAcquire when no face fits."""
    if scan.n_points < 100:
        raise FailureToAcquire(f"only {scan.n_points} valid points", scan.meta.path)
    if scan.grid is None:
        raise ValueError("face detection needs a range-image grid (see preprocess.gridify)")
    sub, cands = nose_candidates(scan, config)
    coarse: list[ModelFit] = []
    for i in cands:
        c = sub.points[i]
        near = sub.points[np.linalg.norm(sub.points - c, axis=1) <= config.context_mm]
        if len(near) >= 50:
            R0 = hotelling_rotation(near[np.linalg.norm(near - c, axis=1) <= 0.6 * config.context_mm])
            coarse.append(fit_face_model(near, R0, -R0 @ c, config.coarse))
    coarse.sort(key=lambda f: -f.inlier_fraction)
    if not coarse or coarse[0].inlier_fraction < config.min_coarse_inliers:
        why = "no face-like surface found" if not coarse else (
            f"no face fits: at best {coarse[0].inlier_fraction:.0%} of the points near a nose candidate fit a face")
        raise FailureToAcquire(why, scan.meta.path)
    # the full fit decides between the best placement and a distinct one that fits almost as well
    finalists = [coarse[0]] + [f for f in coarse[1:] if f.inlier_fraction >= coarse[0].inlier_fraction - config.tie_margin
                               and np.linalg.norm(f.landmarks["nose_tip"] - coarse[0].landmarks["nose_tip"]) > config.separation_mm][:1]
    fits = []
    for f in finalists:
        near = scan.points[np.linalg.norm(scan.points - f.landmarks["nose_tip"], axis=1) <= config.context_mm]
        fits.append(fit_face_model(near, f.R, f.t, config.model))
    plausible = [f for f in fits if identity_rms(f, config.model) <= config.max_identity_rms]
    if not plausible:
        raise FailureToAcquire(f"no plausible face: the face model fits only with identity coefficients of RMS "
                               f"{min(identity_rms(f, config.model) for f in fits):.1f} (prior N(0, 1))", scan.meta.path)
    fit = max(plausible, key=lambda f: (f.inlier_fraction, -f.rms_mm))
    if fit.inlier_fraction < config.min_inliers:
        raise FailureToAcquire(f"the face model does not fit ({fit.inlier_fraction:.0%} of points)", scan.meta.path)
    return Detection(fit.landmarks["nose_tip"], fit.R, fit.t, fit.landmarks, fit.rms_mm, fit.inlier_fraction)


def identity_rms(fit: ModelFit, config: ModelFitConfig) -> float:
    """RMS of a fit's identity coefficients, in prior standard deviations (a wall or a wrong place needs > 2)."""
    return float(np.sqrt(np.mean(fit.coefficients[: config.identity_modes] ** 2)))


def crop_sphere(scan: FaceScan, center: np.ndarray, radius_mm: float = 80.0) -> FaceScan:
    """The points within `radius_mm` of `center` (§8.5.1)."""
    return scan.subset(np.linalg.norm(scan.points - np.asarray(center), axis=1) <= radius_mm)
