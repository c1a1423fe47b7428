"""The view of a mesh or point cloud in a frame of its own (§8.5.1, before detection): which way it was seen from.

A range image is seen along its camera's axis, but a mesh exported by a stereo scanner or in a world frame may
look along any axis, with any roll. Before it is rasterised (`resample.gridify`), such a scan is turned so that
it is seen along +z, head up, in two steps, each measured on the surface itself:

1. `view_axis`: the axis the surface was seen along, the area-weighted mean of its unit normals (a single-view
   scan shows only surface that faces its viewer). Which end of it the viewer was at, the normals do not tell
   (a mesh's winding may be either way, a point cloud has none): both are tried in step 2, and the one where
   the face fits better wins. A view within `OrientConfig.both_from_deg` of +z is taken as the camera's own
   and the frame is kept; one beyond `max_tilt_deg` is turned so it is seen along +z; one between is tried both
   ways, and again the better fit wins.
2. `upright_fit`: the rigid mean face of the morphable model is fitted around the strongest nose candidates from
   `rolls` starting turns about the view axis (the detector's coarse fit); the best fit's vertical axis turns
   the scan head up, as face detection's upright-head prior expects (Mian et al. 2007). As in the detector, fits
   that put the nose where the scan shows one (`detect.shows_nose`) go first, then the share of points fitting: the
   mean face turned upside down on a chin and neck can fit more points than the right placement does (one of 40
   synthetic meshes at 3 mm was turned 159° that way). The best distinct rigid placements are then fitted fully
   and ranked by the detector's `placement_score` (the share of points fitting, less a penalty for an unlikely
   face): on a fine mesh a wrong placement can fit every point too, only with a less likely face.

The rotation applied is recorded: `Preprocessor` composes it into the face's `to_frontal`, so landmarks map back
into the file's own frame, and keeps the estimated view direction (`meta.extra["view"]`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facerec3d.geometry.ball import within_ball
from facerec3d.geometry.transforms import rotation_from_euler
from facerec3d.preprocess.detect import DetectConfig, Neighbours, nose_candidates, placement_score, shows_nose
from facerec3d.preprocess.pose import (ModelFitting, fit_face_model, hotelling_rotation, rotation_to_z,
                                       screen_fits)
from facerec3d.preprocess.resample import front_points, gridify, point_spacing
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class OrientConfig:
    """How a scan without a range-image grid is turned to be seen along +z, head up (module docstring)."""

    enabled: bool = True
    max_tilt_deg: float = 30.0  # a view within this of +z may be the camera's own (a head turned 30° in a camera
    #                             frame shows a mean normal ~15–25° off the axis, so camera frames are kept as they are)
    both_from_deg: float = 10.0  # a view between this and max_tilt_deg off +z is fitted both ways, the frame kept
    #                             and turned, and the better fit wins: the mean normal misjudges the view by up to ~6°,
    #                             and a face seen 32–34° off +z in a kept frame was fitted upside down or not found
    #                             (`mesh_bench.py --subjects 50`, 2026-12-06: subject 19's probe at 2 and 4 mm)
    rolls: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)  # degrees: starting turns of
    #                             the upright fit about the view axis (the coarse fit converges from ±25°)
    nose_candidates: int = 3  # the strongest nose candidates tried by the upright fit
    normal_neighbours: int = 12  # neighbours of a point cloud's points whose plane gives its normal
    sample_mm: float = 2.0  # the upright fit works on a range image of this pitch (or the scan's, if coarser)
    screen_iterations: int = 4  # the finalists' full fits run this many iterations, are ranked, and only the
    screened: int = 2  #          `screened` best so ranked run to the end (screen_iterations 0: every one); the same
    #                             nose errors (median, worst, misses) on the 10 mesh_bench formats run both ways
    #                             (docs/methods.md), meshes 1.1–1.3× faster


@dataclass(frozen=True)
class Orientation:
    """How a scan was turned: x -> R x (input frame to the frame seen along +z, head up)."""

    R: np.ndarray
    view: np.ndarray  # unit view direction in the input frame (towards the viewer)
    turned: bool  # False: the frame was kept as it is (a camera frame, or a grid scan)
    roll_deg: float  # the head's roll corrected by `upright`

    def record(self) -> dict:
        return {"direction": [round(float(v), 4) for v in self.view], "turned": self.turned,
                "roll_deg": round(self.roll_deg, 1)}


def _normals(scan: FaceScan, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals, weights) of the surface: a mesh's triangle normals and areas, or a point cloud's local-plane
    normals (least-variance axis of each point's k neighbours) with equal weights. Signs as they come."""
    p = scan.points
    if scan.mesh is not None and len(scan.mesh):
        a, b, c = p[scan.mesh[:, 0]], p[scan.mesh[:, 1]], p[scan.mesh[:, 2]]
        cross = np.cross(b - a, c - a)
        area = np.linalg.norm(cross, axis=1)
        ok = area > 0
        return cross[ok] / area[ok, None], area[ok]
    from scipy.spatial import cKDTree

    sample = p if len(p) <= 20000 else p[np.random.default_rng(0).choice(len(p), 20000, replace=False)]
    _, idx = cKDTree(p).query(sample, k=min(k, len(p)))
    nb = p[idx] - p[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return vecs[:, :, 0], np.ones(len(sample))


def view_axis(scan: FaceScan, config: OrientConfig = OrientConfig()) -> np.ndarray:
    """The unit axis along which the surface was seen (input frame), its sign not known from the normals alone
    (a mesh's winding may be either or mixed; a point cloud's normals have none): the area-weighted mean of its unit
    normals, each turned to the side of the least-variance axis, and that mean turned towards +z."""
    n, w = _normals(scan, config.normal_neighbours)
    axis = hotelling_rotation(scan.points)[2]  # the least-variance axis: the rough direction of the normals
    n = n * np.where(n @ axis < 0, -1.0, 1.0)[:, None]
    v = (w[:, None] * n).sum(axis=0)
    v = v / np.linalg.norm(v) if np.linalg.norm(v) > 0 else axis
    return v if v[2] >= 0 else -v


# The rigid mean face alone cannot always tell a noisy cheek or chin from the nose: on a Kinect-quality point cloud
# (`benchmarks/mesh_bench.py --sensor kinect-v2`) a placement 63 mm off, turned upside down, fitted 60 % of the points
# and showed a "nose", the true one 45 %. Fitted fully (identity and expression modes, the detector's own fit) the
# true placement fits 99 % of the points near its nose, the wrong one 93 %. So the best few rigid placements are
# fitted fully and ranked again.
_FULL_FITS = 8
_SAME_ROLL_DEG = 20.0
_SAME_TIP_MM = 5.0


def _roll(R: np.ndarray) -> float:
    """The roll about +z (degrees) of a placement x -> R x + t: the face's vertical axis in the scan frame."""
    up = R.T @ np.array([0.0, 1.0, 0.0])
    return float(np.degrees(np.arctan2(up[0], up[1])))


def _finalists(rigid: list) -> list:
    """The rigid fits that get a full fit, from (key, fit, points) sorted best first: the first `_FULL_FITS`
    distinct placements, where one whose nose tip lies within `_SAME_TIP_MM` of an earlier one's, its roll within
    `_SAME_ROLL_DEG`, is that placement again (fits from neighbouring starting rolls converge to the same one). The
    rigid ranking is a weak filter: on 3 mm Kinect-quality points the true placement was the fifth distinct one, on
    a 1 mm mesh the fifth fit, behind fits of wrong candidates and wrong rolls; its full fit won by 0.27–0.29."""
    kept: list = []
    for _, fit, near in rigid:
        tip, roll = fit.landmarks["nose_tip"], _roll(fit.R)
        if any(np.linalg.norm(tip - t2) <= _SAME_TIP_MM and abs((roll - r2 + 180.0) % 360.0 - 180.0) <= _SAME_ROLL_DEG
               for t2, r2, _, _ in kept):
            continue
        kept.append((tip, roll, fit, near))
        if len(kept) == _FULL_FITS:
            break
    return [(fit, near) for _, _, fit, near in kept]


def upright_fit(grid_scan: FaceScan, config: OrientConfig = OrientConfig(),
                detect: DetectConfig = DetectConfig()) -> tuple[float, tuple[bool, float]]:
    """(roll in degrees about +z that turns a scan seen along +z head up, how well the face fits there): the rigid
    mean face fitted around the strongest nose candidates from each of `rolls`, ranked (those showing a nose,
    `detect.shows_nose`, first, then the largest share of points fitting); the first `_FULL_FITS` distinct ones
    (`_finalists`) fitted fully (`detect.model`; screened after `config.screen_iterations`, `pose.screen_fits`) and
    ranked again, the share replaced by `detect.placement_score`;
    the best one's vertical axis. The fit is (whether it shows a nose, that score); (0, (False, 0)) when nothing
    can be fitted."""
    if grid_scan.n_points < 100:
        return 0.0, (False, 0.0)
    sub, cands, _ = nose_candidates(grid_scan, detect)
    around = Neighbours(grid_scan, detect)
    rigid = []
    for i in cands[: config.nose_candidates]:
        c = sub.points[i]
        near = sub.points[within_ball(sub.points, c, detect.context_mm)]
        if len(near) < 50:
            continue
        R0 = hotelling_rotation(near[within_ball(near, c, 0.6 * detect.context_mm)])
        for roll in config.rolls:
            T = rotation_from_euler(0.0, 0.0, roll) @ R0
            fit = fit_face_model(near, T, -T @ c, detect.coarse)
            rigid.append(((shows_nose(around, fit, detect), fit.inlier_fraction), fit, near))
    rigid.sort(key=lambda f: f[0], reverse=True)  # stable: ties keep the candidates' order
    fitting = [ModelFitting(near, fit.R, fit.t, detect.model) for fit, near in _finalists(rigid)]
    key = lambda full: (shows_nose(around, full, detect), placement_score(full, detect))
    best, best_key = None, (False, 0.0)
    for i in screen_fits(fitting, config.screen_iterations, config.screened,  # stable sort: ties keep their order
                         lambda fits: sorted(range(len(fits)), key=lambda j: key(fits[j]), reverse=True)):
        full = fitting[i].run().result()
        k = key(full)
        if best is None or k > best_key:
            best, best_key = full, k
    if best is None:
        return 0.0, (False, 0.0)
    return _roll(best.R), (bool(best_key[0]), float(best_key[1]))


def orient(scan: FaceScan, config: OrientConfig = OrientConfig(),
           detect: DetectConfig = DetectConfig()) -> tuple[FaceScan, Orientation]:
    """The scan turned to be seen along +z, head up, and how (module docstring). Grid scans (range images, depth
    frames) are in their camera's frame already and come back as they are."""
    if scan.grid is not None or not config.enabled or scan.n_points < 100:
        return scan, Orientation(np.eye(3), np.array([0.0, 0.0, 1.0]), False, 0.0)
    axis = view_axis(scan, config)
    cell = max(config.sample_mm, point_spacing(scan.points))  # the sign and the roll need only the face's shape
    best = None
    for v in (axis, -axis):  # seen from one side of the axis or the other: the side the face fits better
        tilt = np.degrees(np.arccos(np.clip(v[2], -1.0, 1.0)))
        frames = [True] if tilt > config.max_tilt_deg else [False, True] if tilt > config.both_from_deg else [False]
        for turned in frames:  # the frame kept (a camera's), turned to be seen along v, or both: the better fit
            R = rotation_to_z(v) if turned else np.eye(3)
            seen = scan.transformed(R, np.zeros(3))
            roll, fits = upright_fit(gridify(front_points(seen, cell), cell), config, detect)  # nose, then inliers
            if best is None or fits > best[0]:
                best = (fits, Orientation(rotation_from_euler(0.0, 0.0, roll) @ R, v, turned, roll))
    view = best[1]
    return scan.transformed(view.R, np.zeros(3)), view
