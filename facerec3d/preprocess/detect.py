"""Face detection and segmentation (chapter §8.5.1): find the nose tip, crop a sphere around it.

The nose tip is not taken as the point of largest Z (spikes, hair, chin and
shoulders can be nearer than the nose). Candidates (`nose_candidates`,
`silhouette_candidates`) are the points that protrude most from their
surroundings on a ~2 mm sub-sampled range image, along Z and along the local
surface normal, those standing out at the rim of the data, and the peaks of
each head's outline at nose height (a head in profile; `silhouette_candidates`). Each is
verified by a rigid fit of the morphable model's mean face from a Hotelling
frame turned by a few yaws (each yaw's placement competes, not only the best
fitting one per candidate); the best distinct placements get a full fit of
the model (pose, identity, expression; `pose.fit_face_model`), which gives
the nose tip, the other fiducials and the frontal pose. The model's identity
prior regularises that fit and ranks placements; it does not decide whether
there is a face, since real faces lie well outside any model's span.

Since 2026-12-05 the candidates are, by default, the best peaks of a learned nose proposer (`propose`:
a small network reading a height map of the scan) instead, verified the same way with fewer finalists; a scan
where none of its placements is face-shaped is searched again from the hand-made candidates.

A placement counts only if the scan shows a face there: a nose standing out
of the plane and the dome of the surface around it (`nose_heights`) and a face surface
the camera could have seen (`seen_share`: a face fitted to an ear or a
shoulder puts its nose where the camera saw nothing, or saw past it). The
upright-head prior of Mian et al. (2007) breaks ties: a nose lies 30–190 mm
below the top of the head (`head_penalty`). A failure to acquire is a scan
with no such placement: nothing scanned, a wall, the back of a head, a hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from facerec3d.config import check_cells
from facerec3d.errors import FaceRec3DError, FailureToAcquire, short_of
from facerec3d.geometry.ball import BallIndex, nearest_index, within_ball
from facerec3d.geometry.normals import least_eigenvector
from facerec3d.geometry.transforms import rotation_from_euler
from facerec3d.preprocess.propose import NoseProposer
from facerec3d.preprocess.pose import (ModelFit, ModelFitConfig, ModelFitting, fit_face_model, hotelling_rotation,
                                       screen_fits)
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class DetectConfig:
    """Nose-tip detection and face cropping (§8.5.1)."""

    sample_mm: float = 2.0  # spacing of the sub-sampled range image used for the search
    detail_mm: float = 1.5  # the tests of each placement (`Neighbours`: `nose_heights`, `seen_share`,
    #   `disc_coverage`) use every k-th row and column of a scan finer than this (k = round(detail_mm / pitch): 2 on a
    #   0.75 mm laser scan, 1 on a Kinect frame); the full fits every point; 0: every point. Since 2026-12-06
    window_mm: float = 40.0  # the local mean that protrusion is measured against
    min_coverage: float = 0.7  # share of that window that must hold data ...
    rim_coverage: float = 0.35  # ... or this share, for candidates along the normal at the rim (a nose in profile)
    separation_mm: float = 25.0  # candidates are local maxima over this distance
    candidates: int = 4  # how many candidates are verified
    context_mm: float = 100.0  # points within this distance of a candidate are aligned
    min_coarse_inliers: float = 0.3  # least share of points near a candidate fitting the mean face (rigid)
    min_inliers: float = 0.5  # least share of the scan points near the nose that fit the full face model
    min_protrusion_mm: float = 6.0  # the nose tip must stand this far above the plane of the surface around it (a
    #                                 nose ~10–25 mm, less after smoothing 8 mm depth steps; a wall 0, the back of a
    #                                 head ~4); measured on the scan, not the model
    min_seen: float = 0.8  # least share of the fitted face's camera-facing surface the scan agrees with (seen_share)
    min_disc_coverage: float = 0.25  # placements whose 60 mm frontal disc the scan covers less go after the others
    #                                  (a dense mesh once had its best placement on a patch covering 2.5 % of it)
    seen_radius_mm: float = 50.0
    seen_margin_mm: float = 15.0
    seen_radius_px: float = 1.5
    seen_outline_px: float = 3.0  # lines of sight this near the data with none on them are not judged (seen_share)
    tip_radius_mm: float = 8.0  # protrusion: scan points this near the nose axis give the tip's height ...
    ring_mm: tuple[float, float] = (20.0, 35.0)  # ... above the plane through the points this far from it
    min_dome_mm: float = 3.0  # ... and, where that ring is whole, above the dome through it (plane + κ r²): a
    #                           rounded surface (the synthetic back of a head, ~4-6 mm above its plane) stands ≤ 1.6
    #                           above its dome; on rap3df-2019 this test rejected 2 of the 521 real frames
    start_yaws: tuple[float, ...] = (-70.0, -35.0, 0.0, 35.0, 70.0)  # degrees: coarse fits start from the Hotelling
    #                                                                   frame turned so (a head in profile) ...
    frontal_yaw: float = 40.0  # ... those of at most this yaw for candidates inside the surface, all for those at its rim
    #                            (hand-made candidates: `nose_candidates`; the proposer's: `at_rim`, since 2026-12-06)
    crown_mm: tuple[float, float] = (30.0, 190.0)  # a nose tip lies this far below the top of its head (upright) ...
    crown_reach_mm: float = 250.0  # ... the highest point this far sideways or less ...
    crown_depth_mm: float = 400.0  # ... and this far in depth (not the wall behind)
    max_roll_deg: float = 45.0  # ... and a face is rolled (tilted sideways) at most this much: on rap3df-2019 the
    #                             detections before this prior had a median roll of 3°, 99 % under 46°; a face fitted
    #                             rolled 74° to a hand and a cheek on the synthetic outside-model set
    heads: int = 2  # profile candidates are looked for on the largest surfaces ...
    min_head_area_mm2: float = 8000.0  # ... of at least this area (a head seen from any side: ~30,000) ...
    join_mm: float = 15.0  # ... whose neighbouring pixels lie this near in 3D
    profile_step_mm: float = 20.0  # a nose in profile stands out of the head's outline this far above and below ...
    min_profile_peak_mm: float = 4.0  # ... by at least this much (its bridge and upper lip lie ~10 mm behind it)
    profile_peaks: int = 2  # peaks per side of each head, beside its outermost point (1: 2 frames right, 5 wrong)
    max_head_width_mm: float = 350.0  # a head is at most this wide at nose height (median; shoulders ~400–500)
    head_weight: float = 0.5  # placement penalty per 50 mm outside crown_mm
    finalists: int = 8  # the best distinct coarse placements get a full fit (6, not 4: with the profile candidates
    #                     the frontal nose of a bowed head was left out of 4 on rap3df-2019; 8 since 2026-12-04, when
    #                     every start yaw's placement began to compete: with 6, four bowed heads of rap3df-2019 lost
    #                     their nose, with 7 one; detection ~1.28× slower, docs/methods.md) ...
    screen_iterations: int = 0  # ... 0: every finalist fitted to the end; n > 0: each fitted n iterations first,
    #                             ranked (`rank_placements`) ...
    screened: int = 2  # ... and only this many best so ranked fitted to the end. An option for speed
    #                    (examples/preprocess-fast.toml: 4 and 2), not the default: the full fits of 4 rap3df-2019
    #                    frames of 521 and 2 synthetic outside-model scans of 600 end elsewhere (turned heads,
    #                    glasses), the default fusion lost 1 probe on the real held-out half, test60-outside and
    #                    strong60-outside each, for a Kinect frame 1.05-1.12x faster (docs/benchmarks.md)
    identity_penalty: float = 0.1  # ... and the best `placement_score` wins: the identity prior regularises, never gates
    prominence_weight: float = 0.35  # ... with a bonus for a nose standing out as noses do (`prominence`) ...
    prominence_mm: float = 20.0  # ... up to this height above its plane and its dome ...
    rms_weight: float = 2.0  # ... less this × how much the full fit's RMS exceeds the best face-shaped placement's,
    rms_tolerance: float = 0.1  # ... relative, beyond this share (`rms_excess`: hair and the back of a head leave a
    #                             rougher residue than a face). 2 since 2026-12-03, measured over three ICP seeds:
    #                             rap3df-2019 held-out +2.1 points (default fusion), synthetic sensor, outside-model
    #                             and FRGC-style sets equal within one probe (docs/methods.md, "A face fits smoother
    #                             than hair"); 0 turns it off
    coarse: ModelFitConfig = field(default_factory=lambda: ModelFitConfig(
        identity_modes=0, expression_modes=False, iterations=15, start_distance_mm=20.0, end_distance_mm=5.0,
        max_points=800))  # rigid fit of the mean face, to verify each candidate (400 points: 1.25× faster, but the
    #                      rap3df-2019 held-out rank-1 fell 1–4 points, docs/benchmarks.md; `lookup_mm = 1.5`, pairs
    #                      from an approximate map of the mean face: 2.4× faster fits than the default exact one, 1.2×
    #                      faster preprocessing of a Kinect frame, no loss on the benchmarks, but knife-edge detections
    #                      move: examples/preprocess-fast.toml)
    proposer: str = "shipped"  # the learned nose proposer (`propose.NoseProposer`: "shipped", facerec3d/models/
    #   nose.onnx, or an ONNX file of `facerec3d train-nose`) names the candidates instead of the hand-made ones above,
    #   each verified like them (`at_rim`); a scan where none of its placements is face-shaped is searched again
    #   from the hand-made ones. "": those alone (the default until 2026-12-05). Since 2026-12-05: rap3df-2019
    #   held-out half 60.8 → 64.6 % rank-1 (default fusion), left / right 58.3 / 50.0 → 60.4 / 60.9 %, the
    #   synthetic sensor and outside-model sets equal or better (docs/methods.md, "A learned nose proposer") ...
    proposals: int = 3  # ... this many of its peaks ...
    proposed_finalists: int = 3  # ... and this many distinct placements fitted in full (8 from the hand-made ones)
    model: ModelFitConfig = field(default_factory=lambda: ModelFitConfig(max_points=1500))  # full fit of the finalists
    #   (1500 points, 3000 until 2026-12-03: a Kinect face gives ~1,100 near its nose, a 480 × 640 laser scan ~20,000,
    #   where 1500 make preprocessing 1.2× faster)

    def __post_init__(self) -> None:
        check_cells("sample_mm", self.sample_mm, self.crown_mm[1], "a head down to its nose, crown_mm[1]")
        if self.proposals < 1 or self.proposed_finalists < 1:
            raise ValueError("proposals and proposed_finalists must be ≥ 1")
        if self.proposer not in ("", "shipped"):
            if not Path(self.proposer).is_file():
                raise ValueError(f"proposer {self.proposer!r}: no such file (give \"shipped\", an ONNX file, or \"\")")
            model = proposer(self.proposer)
            try:  # opened here, once per process: a file that is no nose proposer is refused with the settings,
                model.session  # before any work (it failed every scan to acquire)
            except FaceRec3DError as e:
                raise ValueError(f"proposer {self.proposer!r}: {str(e).removeprefix(f'{model.path}: ')}") from None


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
    protrusion_mm: float
    model_coefficients: np.ndarray | None = None  # the full fit's identity then expression coefficients (kept for
    #                                               the model-based matchers, matching.morphable)


MIN_SEARCH_POINTS = 50  # points of the search image (`_subsample` at `sample_mm`) below which no face is searched


def check_search_image(sub: FaceScan, scan: FaceScan, config: DetectConfig) -> None:
    """FailureToAcquire when the search image, the scan on every k-th row and column ~`sample_mm` apart, holds fewer
    than MIN_SEARCH_POINTS points (a `sample_mm` coarser than the scan is wide left none: an internal error)."""
    if sub.n_points < MIN_SEARCH_POINTS:
        raise FailureToAcquire(f"the face search sees only {sub.n_points} of the {scan.n_points} points at its "
                               f"spacing ([detect] sample_mm = {config.sample_mm:g}), it needs {MIN_SEARCH_POINTS}",
                               scan.meta.path)


def _subsample(scan: FaceScan, spacing_mm: float) -> tuple[FaceScan, float]:
    """The grid scan on every k-th row and column so that points are ~spacing_mm apart; (scan, spacing)."""
    res = scan.resolution()
    step = max(1, int(round(spacing_mm / res)))
    if step == 1:
        return scan, res
    g = scan.grid
    keep = (g[:, 0] % step == 0) & (g[:, 1] % step == 0)
    sub = scan.subset(keep)
    h, w = scan.grid_shape
    sub = sub.replace(grid=sub.grid // step, grid_shape=((h + step - 1) // step, (w + step - 1) // step))
    return sub, res * step


@njit(cache=True)
def _protrusion(xyz, valid, half, reach2, min_coverage, edge_coverage):  # pragma: no cover - compiled
    """(height along Z, height along the local surface normal) of each pixel above the window pixels within
    `reach` in 3D: above their mean depth, and above the plane through their mean with their least-variance
    direction as normal, turned towards the camera (a nose turned 45° away still stands out of its face); and
    that height along the normal where the window is only `edge_coverage` full (a nose in profile, at the rim of
    the scan)."""
    rows, cols = valid.shape
    out_z = np.full((rows, cols), -np.inf)
    out_n = np.full((rows, cols), -np.inf)
    out_e = np.full((rows, cols), -np.inf)
    full = (2 * half + 1) ** 2
    cov = np.empty((3, 3))
    for r in range(half, rows - half):
        for c in range(half, cols - half):
            if not valid[r, c]:
                continue
            sx = sy = sz = sxx = syy = szz = sxy = sxz = syz = 0.0
            count = 0
            x0, y0, z0 = xyz[r, c, 0], xyz[r, c, 1], xyz[r, c, 2]
            for rr in range(r - half, r + half + 1):
                for cc in range(c - half, c + half + 1):
                    if not valid[rr, cc]:
                        continue
                    dx = xyz[rr, cc, 0] - x0
                    dy = xyz[rr, cc, 1] - y0
                    dz = xyz[rr, cc, 2] - z0
                    if dx * dx + dy * dy + dz * dz <= reach2:
                        sx += dx
                        sy += dy
                        sz += dz
                        sxx += dx * dx
                        syy += dy * dy
                        szz += dz * dz
                        sxy += dx * dy
                        sxz += dx * dz
                        syz += dy * dz
                        count += 1
            if count < edge_coverage * full:
                continue
            mx, my, mz = sx / count, sy / count, sz / count
            cov[0, 0], cov[0, 1], cov[0, 2] = sxx / count - mx * mx, sxy / count - mx * my, sxz / count - mx * mz
            cov[1, 1], cov[1, 2], cov[2, 2] = syy / count - my * my, syz / count - my * mz, szz / count - mz * mz
            cov[1, 0], cov[2, 0], cov[2, 1] = cov[0, 1], cov[0, 2], cov[1, 2]
            n = least_eigenvector(cov)  # (Jacobi: ~3x faster here than LAPACK's eigh through Numba)
            if n[0] * x0 + n[1] * y0 + n[2] * z0 > 0:  # towards the camera
                n = -n
            height = -(mx * n[0] + my * n[1] + mz * n[2])
            out_e[r, c] = height
            if count >= min_coverage * full:
                out_z[r, c] = -mz
                out_n[r, c] = height
    return out_z, out_n, out_e


def _peaks(height: np.ndarray, sep: int, count: int) -> np.ndarray:
    """(row, col) of up to `count` local maxima of a height image over a sep × sep window, highest first."""
    peaks = np.isfinite(height) & (height == ndimage.maximum_filter(height, sep, mode="constant", cval=-np.inf))
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-height[rows, cols])[:count]
    return np.stack([rows[order], cols[order]], axis=1)


def at_rim(sub: FaceScan, spacing: float, points: np.ndarray, config: DetectConfig = DetectConfig()) -> np.ndarray:
    """Whether each of the sub-sampled scan's `points` (indices; `spacing`: its pitch, `_subsample`'s) lies at the
    rim of the data: less than `min_coverage` of the `window_mm` window around it holds points within `context_mm`
    of it in 3D (a nose in profile or turned far from the camera: the window runs off the head, onto nothing or the
    background; the cheeks of a nose facing the camera lie 20-40 mm behind its tip, in reach). Those are verified
    from every start yaw, the others from the yaws within `frontal_yaw`."""
    idx = sub.index_image()
    half = max(1, int(round(config.window_mm / spacing / 2)))
    reach2 = config.context_mm ** 2
    rows, cols = idx.shape
    out = np.ones(len(points), dtype=bool)
    for k, (r, c) in enumerate(sub.grid[points]):
        if not (half <= r < rows - half and half <= c < cols - half):
            continue  # the window leaves the grid: at its rim
        near = idx[r - half:r + half + 1, c - half:c + half + 1]
        near = near[near >= 0]
        d2 = ((sub.points[near] - sub.points[idx[r, c]]) ** 2).sum(axis=1)
        out[k] = (d2 <= reach2).sum() < config.min_coverage * (2 * half + 1) ** 2
    return out


def nose_candidates(scan: FaceScan, config: DetectConfig = DetectConfig()) -> tuple[FaceScan, np.ndarray, np.ndarray]:
    """(sub-sampled scan, indices of its candidate nose tips, whether each was found at the rim).

    Protrusion is measured against the surface connected to a point (window
    pixels within the window's reach in 3D), so a chin over a far-away neck
    or a shoulder rim does not stand out: along Z (a face towards the camera),
    along the local surface normal (a head turned away), and along the normal
    where the window is half empty (a nose in profile); the peaks of each,
    `candidates` of them, in that order, less repeats.
    """
    sub, spacing = _subsample(scan, config.sample_mm)
    check_search_image(sub, scan, config)
    xyz, valid = sub.to_range_image()
    half = max(1, int(round(config.window_mm / spacing / 2)))
    along_z, along_normal, at_rim = _protrusion(np.nan_to_num(xyz), valid, half, (0.75 * config.window_mm) ** 2,
                                                config.min_coverage, config.rim_coverage)
    sep = max(3, int(round(config.separation_mm / spacing)) | 1)
    found: list[tuple[int, int]] = []
    rim: list[bool] = []
    for height in (along_z, along_normal, at_rim):
        for r, c in _peaks(height, sep, config.candidates):
            if all(max(abs(r - r2), abs(c - c2)) > sep // 2 for r2, c2 in found):
                found.append((r, c))
                rim.append(height is at_rim)
    index = sub.index_image()
    return sub, np.array([index[r, c] for r, c in found], dtype=np.int64), np.array(rim, dtype=bool)


MIN_POINTS = 100  # valid points that a face needs at the least


MIN_EXTENT_MM = 50.0  # the least a face spans (mm, the longest side of its bounding box): a face is 120-200 mm
MAX_EXTENT_MM = 50_000.0  # the most a scene with a face spans (mm): depth cameras see 5-10 m. The detector's head
#   search bins the scene in 25 mm cells (`crown_heights`): a face read in the wrong unit (×1000: 200 m) made that
#   grid take 7.6 GB; at 50 m it takes 32 MB
MAX_FACE_DISTANCE_MM = 5_000.0  # the farthest a depth camera sees a face (mm): the Kinect v2 reads to 4.5 m, and
#   at 5 m its pixel spans 14 mm (fx 365 px), a face ~11 pixels across with the nose in one or two; a face read
#   at 10 times its depth (a frame of 0.1 mm units read as mm, a cloud scaled ×10) lies 5-15 m away


def check_points(scan: FaceScan) -> None:
    """FailureToAcquire when the scan has fewer valid points than any face needs, saying how many it has, or spans
    less than any face does (`MIN_EXTENT_MM`: a mesh or cloud in metres, or a depth image read at the wrong scale),
    or more than any scene with a face (`MAX_EXTENT_MM`: one in micrometres, or a depth image's intrinsics wrong)."""
    if scan.n_points < MIN_POINTS:
        raise FailureToAcquire(f"only {scan.n_points} valid point{'s' * (scan.n_points != 1)}", scan.meta.path)
    lo, hi = scan.bounding_box()
    if not (extent := float(np.max(hi - lo))) >= MIN_EXTENT_MM:
        raise FailureToAcquire(f"the scan spans only {extent:.3g} mm, far too small for a face: facerec3d reads "
                               "millimetres (a mesh or point cloud in metres needs scaling by 1000; a depth image, "
                               "its depth scale in the intrinsics)", scan.meta.path)
    if extent > MAX_EXTENT_MM:
        raise FailureToAcquire(f"the scan spans {extent / 1000:.3g} m, far more than a scene with a face: facerec3d "
                               "reads millimetres (a mesh or point cloud in micrometres needs scaling by 0.001; a "
                               "depth image, its depth scale and intrinsics (fx, fy, cx, cy in pixels) checked)",
                               scan.meta.path)


def detect_face(scan: FaceScan, config: DetectConfig = DetectConfig()) -> Detection:
    """Find the nose tip, fiducials and frontal pose of a scan; raises FailureToAcquire when no face fits.

    With a nose proposer (`DetectConfig.proposer`), a scan where none of its placements is face-shaped is searched
    again from the hand-made candidates, so the proposer never adds a failure to acquire."""
    check_points(scan)
    if scan.grid is None:
        raise ValueError("face detection needs a range-image grid (see preprocess.gridify)")
    try:
        if config.proposer:
            try:
                return _detect_face(scan, config)
            except FailureToAcquire:
                config = replace(config, proposer="")
        return _detect_face(scan, config)
    except FailureToAcquire as e:
        if hint := too_far(scan):
            raise FailureToAcquire(f"{e.reason}; {hint}", e.path) from None
        raise


def too_far(scan: FaceScan) -> str | None:
    """For a scan with no face found: when its nearest point lies beyond MAX_FACE_DISTANCE_MM of the camera (the
    origin of a depth frame's points and of a cloud in camera coordinates), that its depth likely reads too large
    (a depth image of 0.1 mm units read as millimetres, a cloud scaled ×10); else None. A cloud or mesh whose
    origin is not its camera has points near the origin, and gets no hint."""
    nearest = float(np.sqrt(np.min(np.einsum("ij,ij->i", scan.points, scan.points))))
    if not nearest > MAX_FACE_DISTANCE_MM:
        return None
    return (f"its nearest point is {nearest / 1000:.3g} m from the camera, beyond where a depth camera sees a face "
            f"(~{MAX_FACE_DISTANCE_MM / 1000:g} m): is its depth 10 times too large? facerec3d reads millimetres (a "
            "depth image needs its depth scale in the intrinsics, e.g. depth_unit_mm 0.1 for 0.1 mm units; a mesh "
            "or point cloud, scaling)")


def _detect_face(scan: FaceScan, config: DetectConfig) -> Detection:
    tested = _subsample(scan, config.detail_mm)[0] if config.detail_mm > 0 else scan  # placements' tests
    if config.proposer:
        sub, spacing = _subsample(scan, config.sample_mm)
        check_search_image(sub, scan, config)
        cands = proposer(config.proposer).propose(sub.points, config.proposals, config.separation_mm)
        rim, profile, n_final = at_rim(sub, spacing, cands, config), [], config.proposed_finalists
    else:
        sub, cands, rim = nose_candidates(scan, config)
        profile, n_final = silhouette_candidates(sub, config), config.finalists
    crown = crown_heights(sub, config)
    turns = [rotation_from_euler(yaw, 0.0, 0.0) for yaw in config.start_yaws]
    frontal = [T for T, yaw in zip(turns, config.start_yaws) if abs(yaw) <= config.frontal_yaw]
    cands = list(cands) + profile
    starts = [turns if at_rim else frontal for at_rim in rim] + [turns] * len(profile)
    coarse: list[ModelFit] = []
    for i, trials in zip(cands, starts):
        c = sub.points[i]
        near = sub.points[within_ball(sub.points, c, config.context_mm)]
        if len(near) >= 50:
            R0 = hotelling_rotation(near[within_ball(near, c, 0.6 * config.context_mm)])
            coarse += [fit_face_model(near, T @ R0, -(T @ R0) @ c, config.coarse) for T in trials]
    # every start's placement stays (those ending within `separation_mm` of a better one are dropped below): on a
    # face with a hand over one cheek, the start that fitted best slid onto the hand, and one that fitted a little
    # worse was the face
    # on quantised depth nearly every placement fits the rigid mean face, so those with a nose standing out of
    # the scan where the mean face puts it go first (the same test that decides below)
    around = Neighbours(tested, config)
    coarse.sort(key=lambda f: -f.inlier_fraction + head_penalty(f, sub, crown, config))
    first, finalists = best_distinct(coarse, lambda f: shows_nose(around, f, config), config.separation_mm,
                                     n_final)
    if first is None or first.inlier_fraction < config.min_coarse_inliers:
        why = "no face-like surface found" if first is None else (
            f"no face fits: at best {first.inlier_fraction:.0%} of the points near a nose candidate fit a face")
        raise FailureToAcquire(why, scan.meta.path)
    # the best distinct placements get a full fit (pose, identity, expression); with `screen_iterations`, each
    # is fitted that far first and only the `screened` best so ranked are fitted to the end
    every = around if tested is scan else Neighbours(scan, config, sight=False)  # the full fits see every point
    fitting = [ModelFitting(every.points(f, config.context_mm, exact=True), f.R, f.t, config.model)
               for f in finalists]
    keep = screen_fits(fitting, config.screen_iterations, config.screened, lambda fits: [
        x.index for x in rank_placements(fits, finalists, tested, around, sub, crown, config)])
    fitting, finalists = [fitting[i] for i in keep], [finalists[i] for i in keep]  # in the finalists' order
    ranked = rank_placements([g.run().result() for g in fitting], finalists, tested, around, sub, crown, config)
    fit, (protrusion, dome), (_, seen) = ranked[0].fit, ranked[0].heights, ranked[0].seen
    if not ranked[0].face_shaped:
        if fit.inlier_fraction < config.min_inliers:
            why = f"the face model does not fit ({fit.inlier_fraction:.0%} of points)"
        elif protrusion < config.min_protrusion_mm:
            why = ("no face-shaped surface: nothing protrudes at the fitted nose "
                   f"({tip_above(protrusion, config.min_protrusion_mm, 'its surroundings')})")
        elif dome < config.min_dome_mm:
            why = ("no face-shaped surface: a rounded surface, no nose "
                   f"({tip_above(dome, config.min_dome_mm, 'the dome around it')})")
        else:
            why = f"no face-shaped surface: the camera saw only {seen:.0%} of where the fitted face would be"
        raise FailureToAcquire(why, scan.meta.path)
    return Detection(fit.landmarks["nose_tip"], fit.R, fit.t, fit.landmarks, fit.rms_mm, fit.inlier_fraction,
                     protrusion, fit.coefficients)


_PROPOSERS: dict[str, NoseProposer] = {}


def proposer(name: str) -> NoseProposer:
    """The nose proposer of `DetectConfig.proposer` ("shipped" or a path), opened once per process."""
    if name not in _PROPOSERS:
        _PROPOSERS[name] = NoseProposer() if name == "shipped" else NoseProposer(name)
    return _PROPOSERS[name]


class Placement(NamedTuple):
    """A finalist's full fit as `rank_placements` judges it."""

    index: int  # among the finalists ranked
    fit: ModelFit  # the full fit
    coarse: ModelFit  # the coarse placement it started from
    heights: tuple[float, float]  # `nose_heights`
    seen: tuple[float, float]  # `seen_share`
    face_shaped: bool  # a nose (`is_nose`), seen (`min_seen`) and the full model fitting (`min_inliers`)


def rank_placements(fits: list[ModelFit], coarse: list[ModelFit], scan: FaceScan, around: Neighbours,
                    sub: FaceScan, crown: np.ndarray, config: DetectConfig = DetectConfig()) -> list[Placement]:
    """The finalists' full fits (`fits`, of the coarse placements `coarse`), best first. The face-shaped ones come
    first: a nose standing out of the scanned surface (`nose_heights`), a face surface the camera could have seen
    (`seen_share`) and the full model fitting; among them those whose face disc the scan covers (`disc_coverage`)
    before those it hardly covers (a fit to a small patch). Within each group they are ranked by the rigid mean
    face fitting there (the coarse fit), the full model fitting with a likely identity and the seen share, less the
    head penalty and how much rougher the fit's residue is than the smoothest face-shaped placement's
    (`rms_excess`)."""
    shaped = []
    for i, (f, c) in enumerate(zip(fits, coarse)):
        heights = nose_heights(around.points(f, _heights_reach(config)), f, config)
        seen = seen_share(scan, f, config, around)
        face = is_nose(heights, config) and seen[1] >= config.min_seen and f.inlier_fraction >= config.min_inliers
        shaped.append(Placement(i, f, c, heights, seen, face))
    best_rms = min((x.fit.rms_mm for x in shaped if x.face_shaped and np.isfinite(x.fit.rms_mm)),
                   default=0.0)  # the smoothest face-shaped placement's: a smoother one that is no face (hair, the
    #                             back of a head) sets no bar
    shaped.sort(key=lambda x: -(x.coarse.inlier_fraction + placement_score(x.fit, config) + x.seen[0]
                                + prominence(x.heights, config) - head_penalty(x.fit, sub, crown, config)
                                - (config.rms_weight * rms_excess(x.fit.rms_mm, best_rms, config.rms_tolerance)
                                   if config.rms_weight else 0.0)))
    pitch = scan.resolution()
    small = lambda x: (disc_coverage(around.points(x.fit, _disc_reach(config)), x.fit, pitch, config)
                       < config.min_disc_coverage)
    return sorted((x for x in shaped if x.face_shaped), key=small) + [x for x in shaped if not x.face_shaped]


def best_distinct(ranked: list[ModelFit], passes, separation_mm: float,
                  count: int) -> tuple[ModelFit | None, list[ModelFit]]:
    """(the first placement, the first `count` distinct ones) of `ranked` reordered with those that `passes` first
    (a stable partition), distinct meaning a nose tip more than `separation_mm` from every earlier one's. The test is
    made only as far down the ranking as needed (once `count` distinct placements pass, no later one can come
    before them) and only on placements that can still be distinct: one near a placement that passed already can
    be neither a finalist (passing or not) nor the first (which passed before it)."""
    passing, failing = [], []
    distinct: list[ModelFit] = []
    new = lambda f: all(np.linalg.norm(f.landmarks["nose_tip"] - g.landmarks["nose_tip"]) > separation_mm
                        for g in distinct)
    for f in ranked:
        if not new(f):  # near a finalist that passed: skipped untested (a third of the placements of a Kinect frame)
            continue
        if not passes(f):
            failing.append(f)
            continue
        passing.append(f)
        distinct.append(f)
        if len(distinct) == count:
            return passing[0], distinct
    for f in failing:
        if len(distinct) == count:
            break
        if new(f):
            distinct.append(f)
    return (passing or failing or [None])[0], distinct


def crown_heights(sub: FaceScan, config: DetectConfig = DetectConfig()) -> np.ndarray:
    """For each point of the sub-sampled scan, the height (Y, mm) of the highest point at most `crown_reach_mm`
    sideways and `crown_depth_mm` nearer or farther: the top of the head above a nose, the top of the head far
    above a chin or a shoulder; a wall well behind the person does not count. Computed on 25 mm (x, z) bins."""
    cell = 25.0
    x, y, z = sub.points[:, 0], sub.points[:, 1], sub.points[:, 2]
    ix = np.floor((x - x.min()) / cell).astype(np.int64)
    iz = np.floor((z - z.min()) / cell).astype(np.int64)
    top = np.full((ix.max() + 1, iz.max() + 1), -np.inf)
    np.maximum.at(top, (ix, iz), y)
    size = (2 * int(round(config.crown_reach_mm / cell)) + 1, 2 * int(round(config.crown_depth_mm / cell)) + 1)
    top = ndimage.maximum_filter(top, size=size, mode="constant", cval=-np.inf)
    return top[ix, iz]


def head_regions(sub: FaceScan, config: DetectConfig = DetectConfig()) -> list[np.ndarray]:
    """The heads of the scan: of each of its `heads` largest surfaces (pixels joined when their points lie within
    `join_mm` in 3D; at least `min_head_area_mm2`), the part at most `crown_mm[1]` below its highest point that is
    joined to that point (the head and, on a person, the top of the neck; a shoulder or an arm that only the body
    joins to the head, and flying pixels, are left out). Each as indices into `sub`, its highest point first."""
    labels = _surfaces(sub, config.join_mm)
    sizes = np.bincount(labels)
    y = sub.points[:, 1]
    cell = sub.resolution() ** 2
    heads = []
    for label in np.argsort(-sizes)[: config.heads]:
        if sizes[label] * cell < config.min_head_area_mm2:
            break
        members = labels == label
        top = int(np.flatnonzero(members)[np.argmax(y[members])])
        slab = members & (y >= y[top] - config.crown_mm[1])
        joined = _surfaces(sub, config.join_mm, slab)
        head = np.flatnonzero(slab & (joined == joined[top]))
        heads.append(np.r_[top, head[head != top]])
    return heads


def _surfaces(sub: FaceScan, join_mm: float, keep: np.ndarray | None = None) -> np.ndarray:
    """Connected surfaces of a grid scan: label of each point (pixels 8-connected when their points lie within
    `join_mm`; points not in `keep` each alone)."""
    index = sub.index_image()
    if keep is not None:
        index = np.where((index >= 0) & keep[np.maximum(index, 0)], index, -1)
    h, w = index.shape
    pairs = []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        i = index[: h - dr, max(0, -dc): w - max(0, dc)].ravel()
        j = index[dr:, max(0, dc): w + min(0, dc)].ravel()
        both = (i >= 0) & (j >= 0)
        i, j = i[both], j[both]
        near = np.linalg.norm(sub.points[i] - sub.points[j], axis=1) <= join_mm
        pairs.append((i[near], j[near]))
    i, j = (np.concatenate(k) for k in zip(*pairs))
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(sub.n_points, sub.n_points))
    return connected_components(graph, directed=False)[1]


def silhouette_candidates(sub: FaceScan, config: DetectConfig = DetectConfig()) -> list[int]:
    """Nose tips of heads in profile, which no window-based protrusion sees: on each head (`head_regions`), the
    outline seen from the left and from the right (the outermost point of each `sample_mm` slice of height) between
    `crown_mm[0] + 30` and `crown_mm[1] - 30` mm below the top of the head; its outermost point, and its peaks, the
    `profile_peaks` points standing out most, by at least `min_profile_peak_mm`, beyond the outline
    `profile_step_mm` above and below them (a nose stands ~10 mm beyond its bridge and its upper lip; the back of a
    head and a shoulder rising from the slice below form none, but ears and curls do, which the placement tests
    reject). A surface wider than `max_head_width_mm` at nose height (median over the slices) is no head and gives
    none. Indices into `sub`. On rap3df-2019 these found the nose of ~30 heads turned 60–90° that the earlier
    candidates (the leftmost and rightmost points of the whole scan at nose height: a shoulder, flying pixels)
    missed."""
    spacing = config.sample_mm
    step = int(round(config.profile_step_mm / spacing))
    lo, hi = int((config.crown_mm[0] + 30.0) / spacing), int((config.crown_mm[1] - 30.0) / spacing)
    found: list[int] = []
    for head in head_regions(sub, config):
        slices = np.floor((sub.points[head[0], 1] - sub.points[head, 1]) / spacing).astype(np.int64)
        outlines = {}
        for side in (-1.0, 1.0):
            out = side * sub.points[head, 0]  # how far out on this side
            outline = np.full(slices.max() + 1, -np.inf)
            np.maximum.at(outline, slices, out)
            outlines[side] = out, outline
        band = np.arange(lo, min(hi, slices.max() + 1))
        band = band[np.isfinite(outlines[1.0][1][band])]
        if len(band) == 0 or np.median(outlines[1.0][1][band] + outlines[-1.0][1][band]) > config.max_head_width_mm:
            continue  # no head: shoulders, a torso the head is not joined to, a wall
        for side, (out, outline) in outlines.items():
            at = np.full(len(outline), -1)
            at[slices[out == outline[slices]]] = head[out == outline[slices]]
            found.append(int(at[band[np.argmax(outline[band])]]))
            inner = np.arange(max(lo, step), min(hi, len(outline) - step))
            above, below, here = outline[inner - step], outline[inner + step], outline[inner]
            known = np.isfinite(above) & np.isfinite(below) & np.isfinite(here)
            peak = np.full(len(inner), -np.inf)
            peak[known] = here[known] - np.maximum(above[known], below[known])
            peaks: list[int] = []
            for k in np.argsort(-peak):
                if peak[k] < config.min_profile_peak_mm or len(peaks) == config.profile_peaks:
                    break
                if all(abs(inner[k] - q) > step for q in peaks):
                    peaks.append(int(inner[k]))
            found += [int(at[r]) for r in peaks]
    return list(dict.fromkeys(found))


def head_penalty(fit: ModelFit, sub: FaceScan, crown: np.ndarray, config: DetectConfig = DetectConfig()) -> float:
    """Penalty of a placement that is not an upright head (Mian et al. 2007 also take faces as upright):
    `head_weight` per 50 mm that the crown above its nose is nearer than `crown_mm[0]` or farther than `crown_mm[1]`
    (the crown is that of the sub-sampled point nearest the fitted nose tip), and per `max_roll_deg` that the
    face is rolled beyond `max_roll_deg` (`roll_deg`)."""
    nose = fit.landmarks["nose_tip"]
    i = nearest_index(sub.points, nose)
    height = crown[i] - nose[1]
    lo, hi = config.crown_mm
    rolled = max(0.0, abs(roll_deg(fit.R)) - config.max_roll_deg) / config.max_roll_deg
    return config.head_weight * (max(0.0, lo - height, height - hi) / 50.0 + rolled)


def roll_deg(R: np.ndarray) -> float:
    """How far (degrees) a placement x -> R x + t turns the face's up direction about the line of sight, from the
    scan's +y (`orient` has made the scan upright); 0 where the face looks up or down so steeply that its up
    direction hardly shows in the image (less than half of it)."""
    up = R[1]  # the frontal frame's y axis in scan coordinates
    return float(np.degrees(np.arctan2(-up[0], up[1]))) if np.hypot(up[0], up[1]) >= 0.5 else 0.0


class Neighbours:
    """The scan's points by their (x, y), built once for all placements of a scan: the lines of sight of
    `seen_share`, and the points near a placement's nose for the tests that look at those only."""

    def __init__(self, scan: FaceScan, config: DetectConfig, sight: bool = True):
        from scipy.spatial import cKDTree

        self.scan = scan
        self.tree = cKDTree(scan.points[:, :2]) if sight else None  # for `seen_share` (not needed: `sight` False)
        self.balls = BallIndex(scan.points)
        self.reach = config.seen_radius_px * scan.resolution()
        self.outline = config.seen_outline_px * scan.resolution()

    def points(self, fit: ModelFit, radius_mm: float, exact: bool = False) -> np.ndarray:
        """The scan's points within `radius_mm` of the fitted nose tip (3D), in scan order: exactly those when
        `exact`, else those and the few within 1 mm more (for tests that cut at `radius_mm` in their own frame,
        whose rounding may differ)."""
        nose = fit.landmarks["nose_tip"]
        return self.scan.points[self.balls.within(nose, radius_mm if exact else radius_mm + 1.0)]


def shows_nose(around: Neighbours, fit: ModelFit, config: DetectConfig = DetectConfig()) -> bool:
    """Whether the scan shows a nose where a placement puts one (`nose_heights` of the scan's points near it,
    `is_nose`): the test that orders the coarse placements and, with the others, decides the winner."""
    return is_nose(nose_heights(around.points(fit, _heights_reach(config)), fit, config), config)


def _heights_reach(config: DetectConfig) -> float:
    """How far from the nose tip the points that `nose_heights` looks at lie (mm)."""
    return config.ring_mm[1] + 20.0


def _disc_reach(config: DetectConfig) -> float:
    """How far from the nose tip the points that `disc_coverage` counts lie (mm)."""
    return float(np.hypot(60.0, config.context_mm))


def seen_share(scan: FaceScan, fit: ModelFit, config: DetectConfig = DetectConfig(),
               sight: Neighbours | None = None) -> tuple[float, float]:
    """Free-space check of a placement: of the fitted model's surface within `seen_radius_mm` of its nose that faces
    the camera (scan frame, looking along −Z), the share the scan agrees with, i.e. has a point within
    `seen_margin_mm` in depth along the line of sight, or nearer (occluding it). A face fitted to an ear or a
    shoulder puts its nose where the camera saw nothing or saw past it. Lines of sight are taken parallel to Z
    within `seen_radius_px` pixels (the scan's pitch), which holds near the optical axis.

    Returns (that share, the share among the lines of sight judged): a line of sight with no scan point on it but
    one within `seen_outline_px` pixels runs along the outline of the data, whose mixed-depth pixels spike removal
    took away, and is not judged there. The test of a placement uses the second (a nose in profile lies on that
    outline), its ranking the first (judging fewer lines of sight would favour placements hanging over the outline,
    on hair at the top of a bowed head: on rap3df-2019 ranking by the second broke 6 frames and fixed 4)."""
    R, t = fit.R, fit.t
    near = np.linalg.norm(fit.vertices, axis=1) <= config.seen_radius_mm
    v = (fit.vertices[near] - t) @ R  # frontal -> scan frame: x = Rᵀ (y − t)
    n = fit.vertex_normals[near] @ R
    v = v[n[:, 2] > 0.3]
    if len(v) == 0:
        return 0.0, 0.0
    sight = sight or Neighbours(scan, config)
    d, idx = sight.tree.query(v[:, :2], k=8, distance_upper_bound=sight.reach)
    found = np.isfinite(d)
    z = np.where(found, scan.points[np.minimum(idx, scan.n_points - 1), 2], -np.inf)
    agree = (z >= v[:, 2:3] - config.seen_margin_mm).any(axis=1)
    judged = found.any(axis=1)
    if not judged.all():
        nearest, _ = sight.tree.query(v[~judged, :2], k=1, distance_upper_bound=sight.outline)
        judged[np.flatnonzero(~judged)[~np.isfinite(nearest)]] = True  # nothing near: the camera saw past it
    return float(agree.mean()), float(agree[judged].mean()) if judged.any() else 0.0


def prominence(heights: tuple[float, float], config: DetectConfig = DetectConfig()) -> float:
    """Ranking bonus of a placement whose nose stands out as a nose does: `prominence_weight` × the lesser of its
    `nose_heights` (the dome's counts only where the ring is whole) over `prominence_mm`, clipped to [0, 1]. A hand on
    the cheek, the rim of glasses or a tuft of hair stands 5–15 mm out of the surface around it and can fit the face
    model as well as the face does; a nose stands 15–35 mm out of both its plane and its dome."""
    return config.prominence_weight * float(np.clip(min(heights) / config.prominence_mm, 0.0, 1.0))


def rms_excess(rms_mm: float, best_mm: float, tolerance: float = 0.0) -> float:
    """How much a placement's full-fit RMS (mm) exceeds the best placement's of the same scan, as a fraction of it,
    beyond `tolerance` (0 for the best). Hair, the back of a head or a face model fitted across a face's outline
    leave a rougher residue than a face does, whatever the sensor's noise. 0 where either is not a positive finite
    number (a fit without inliers fails on its inliers)."""
    if not (np.isfinite(rms_mm) and np.isfinite(best_mm) and best_mm > 0):
        return 0.0
    return max(0.0, rms_mm / best_mm - 1.0 - tolerance)


def placement_score(fit: ModelFit, config: DetectConfig = DetectConfig()) -> float:
    """How well a full fit explains its placement: the share of points fitting, less `identity_penalty` per prior
    standard deviation of identity RMS beyond 1 (a chin or a shoulder fits only with an unlikely face)."""
    identity = fit.coefficients[: config.model.identity_modes]
    rms = float(np.sqrt(np.mean(identity**2))) if len(identity) else 0.0
    return fit.inlier_fraction - config.identity_penalty * max(0.0, rms - 1.0)


def disc_coverage(points: np.ndarray, fit: ModelFit, pitch: float, config: DetectConfig = DetectConfig()) -> float:
    """Share of the 60 mm disc around the fitted nose, in the fitted frontal frame, that the scan's points cover
    (each point standing for a pitch × pitch cell, within `context_mm` in depth)."""
    p = points @ fit.R.T + fit.t
    near = (np.linalg.norm(p[:, :2], axis=1) <= 60.0) & (np.abs(p[:, 2]) <= config.context_mm)
    return float(min(1.0, near.sum() * pitch**2 / (np.pi * 60.0**2)))


def nose_heights(points: np.ndarray, fit: ModelFit, config: DetectConfig = DetectConfig()) -> tuple[float, float]:
    """How far (mm) the scanned surface at the fitted nose tip stands out of the scanned surface around it: the
    90th percentile height of the points within `tip_radius_mm` of the nose axis (the 5 nearest within twice that when
    fewer are left: a nose in profile, whose outline pixels spike removal took) above (1) the plane through the
    points of the `ring_mm` annulus around it (least squares, normal towards the fitted face's front) and (2), where
    that ring is whole (points left, right, above and below), the dome through it: that plane plus κ r², r the
    distance from the axis. A nose stands out of the plane of its cheeks and brow; a wall, however the frame is
    tilted, does not; nor does the rim of a convex body (a hand, a shoulder), whose surface falls away from the plane
    through what lies inside; a rounded surface (the back of a head) stands a few mm out of its plane but not out of
    its dome. (−inf, −inf) without tip points or with ring points on fewer than two sides (left, right, above); the
    dome height is +inf when the ring is not whole (a face in profile). Measured on the scan only, so a face model
    bent to fit a wall does not make a nose."""
    p = points @ fit.R.T + fit.t
    p = p[within_ball(p, np.zeros(3), _heights_reach(config))]
    r = np.linalg.norm(p[:, :2], axis=1)
    tip = p[r <= config.tip_radius_mm]
    if len(tip) < 3:  # a nose in profile whose rim pixels are gone: the points nearest its axis, within twice that
        near = np.flatnonzero(r <= 2 * config.tip_radius_mm)
        tip = p[near[np.argsort(r[near])[:5]]]
    ring = p[(r >= config.ring_mm[0]) & (r <= config.ring_mm[1])]
    sides = [(ring[:, 0] < -10.0).sum(), (ring[:, 0] > 10.0).sum(), (ring[:, 1] > 10.0).sum(), (ring[:, 1] < -10.0).sum()]
    if len(tip) == 0 or sum(n >= 5 for n in sides[:3]) < 2:
        return float("-inf"), float("-inf")
    centre = ring.mean(axis=0)
    normal = np.linalg.svd(ring - centre, full_matrices=False)[2][2]
    if normal[2] < 0:
        normal = -normal
    plane = float(np.percentile((tip - centre) @ normal, 90))
    if min(sides) < 5:
        return plane, float("inf")
    design = lambda q: np.c_[np.ones(len(q)), q[:, :2], (q[:, :2] ** 2).sum(axis=1)]  # z = a + b x + c y + κ r²
    coef = np.linalg.lstsq(design(ring), ring[:, 2], rcond=None)[0]
    return plane, float(np.percentile(tip[:, 2] - design(tip) @ coef, 90))


def tip_above(height: float, need: float, around: str) -> str:
    """How far a `nose_heights` height falls short of `need` (mm) above `around`, for a failure's reason: without a
    height (−inf: no scanned surface at the tip, or too little around it), that there was nothing to measure."""
    if not np.isfinite(height):
        return f"no height to measure: too little scanned surface at the tip or around it; a nose needs {need:g} mm " \
               f"above {around}"
    return f"tip {short_of(height, need)} mm above {around}, a nose needs {need:g}"


def is_nose(heights: tuple[float, float], config: DetectConfig = DetectConfig()) -> bool:
    """Whether `nose_heights` are those of a nose: above `min_protrusion_mm` over the plane, `min_dome_mm` over the
    dome."""
    return heights[0] >= config.min_protrusion_mm and heights[1] >= config.min_dome_mm


def crop_sphere(scan: FaceScan, center: np.ndarray, radius_mm: float = 80.0) -> FaceScan:
    """The points within `radius_mm` of `center` (§8.5.1)."""
    return scan.subset(within_ball(scan.points, center, radius_mm))
