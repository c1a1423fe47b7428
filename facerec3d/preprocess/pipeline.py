"""The preprocessing pipeline (chapter §8.5): raw scan in, clean frontal face on a uniform grid out.

    Preprocessor()(scan) -> face

1. meshes and point clouds without a range-image grid are turned to be seen along +z, head up, when their
   frame is not a camera's (`orient`: the view direction estimated from the surface), and their surface is
   rasterised into a range image at their own point spacing (`gridify`);
2. the scan's sampling is measured: pixel pitch, depth step, noise (`sampling`); the
   sensor-dependent thresholds below are multiples of it;
3. spikes are removed (§8.5.2);
4. quantised or noisy depth is smoothed in the camera frame (bilateral, scaled to the
   measured depth step and noise; skipped on fine laser scans) (§8.5.4);
5. the face is detected: nose tip, fiducials and frontal pose (§8.5.1, §8.5.5); then, where coarse depth steps
   dominate the noise, the smoothed depth around it is brought back within what each pixel measured
   (`dequantise`: smoothing flattens the nose by ~5 mm on 8 mm steps);
6. the face is cropped as a sphere around the nose tip (§8.5.1);
7. holes inside it are filled (§8.5.3);
8. it is turned into the frontal frame (nose tip at the origin, looking along +z);
9. resampled on a uniform x–y grid (§8.5.6) and cropped again to the sphere;
10. its depth is smoothed (§8.5.4);
11. and, when `symmetry.mode = "mirror"`, the side of a turned face the camera did not see is completed from its
    mirror image (`symmetry`; Passalis et al. 2011), each point's provenance (seen, filled, mirrored) kept.

The result keeps the scan's metadata; its landmarks are the fiducials in the
frontal frame, `meta.extra["to_frontal"]` holds the 3×4 matrix [R | t]
that maps input-scan coordinates x to R x + t in the frontal frame (for a mesh or point cloud, the file's own
frame: `meta.extra["view"]` records the view direction estimated there and whether the scan was turned), and
`meta.extra["quality"]` the scan's quality (`QUALITY_FIELDS`): how well the
face model fits (RMS mm, share of inliers), how far the nose protrudes, how
much of the face was seen, and the measured pitch, depth step and noise at
the face, so a user can see why a scan is weak; `meta.extra["model_fit"]` the face model's fitted identity and
expression coefficients in that frame (for the model-based matchers); `meta.extra["preprocess_fingerprint"]`
is the settings' `PreprocessConfig.digest()`, so a saved face (`.npz`) says how it was made
(`preprocessed_with`: a gallery service takes such a face as it is when the settings are its own).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.config import check_cells, check_ranges, from_dict, read_settings
from facerec3d.errors import InputError
from facerec3d.preprocess.denoise import (DenoiseConfig, DequantiseConfig, SmoothConfig, denoise, dequantise,
                                         smooth_range_image)
from facerec3d.preprocess.detect import DetectConfig, check_points, crop_sphere, detect_face, proposer
from facerec3d.preprocess.holes import HoleConfig, fill_holes
from facerec3d.preprocess.orient import OrientConfig, Orientation, orient
from facerec3d.preprocess.resample import ResampleConfig, gridify, resample
from facerec3d.preprocess.sampling import Sampling, check_surface, measure_sampling
from facerec3d.preprocess.spikes import SpikeConfig, remove_spikes
from facerec3d.preprocess.symmetry import SymmetryConfig, complete_by_symmetry
from facerec3d.scan import FaceScan
from facerec3d.workers import one_blas_thread


@dataclass(frozen=True)
class PreprocessConfig:
    """Every preprocessing setting, by stage; defaults as documented on each stage's config."""

    crop_radius_mm: float = ResampleConfig.half_width_mm  # §8.5.1: the face is the sphere of this radius around the
    #   nose tip, 95 mm (the grid's half-width, where the value is kept). Mian et al. use 80 mm on FRGC's laser scans;
    #   on the real Kinect v2 frames (rap3df-2019, tuning half) 95 mm gave ICP's best rank-1 over all probes: 62.7 %
    #   at 80 mm, 69.6 at 95, 68.1 at 100, 67.2 at 110, 60.8 at 125 (README)
    coverage_radius_mm: float = 60.0  # quality: the share of this frontal disc around the nose tip that holds data
    gridify_mm: float = 0.0  # cell size of the range image a mesh or point cloud is rasterised into; 0: its own
    #                          point spacing, measured (a 0.7 mm cell left a 3.8 mm stereo mesh as isolated points)
    max_noise_pitches: float = 5.0  # a scan whose depth noise σ exceeds this many pixel pitches is no surface
    #   (`sampling.check_surface`; 0: off). The 521 rap3df-2019 Kinect v2 frames measure at most 0.90, synthetic
    #   frgc, kinect-v2 and realsense scans at most 0.81; frames of random depths spread uniformly over 50, 100, 200
    #   or 700 mm at a 2 mm pitch (7.9, 16, 32, 110 pitches) passed the detector as faces in 3 of 10, 25 of 30, 30 of
    #   30 and 10 of 30 draws; over 10–30 mm (1.6–4.7) in none of 30 (2026-12-05)
    orient: OrientConfig = field(default_factory=OrientConfig)
    spikes: SpikeConfig = field(default_factory=SpikeConfig)
    smooth: SmoothConfig = field(default_factory=SmoothConfig)
    dequantise: DequantiseConfig = field(default_factory=DequantiseConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    holes: HoleConfig = field(default_factory=HoleConfig)
    resample: ResampleConfig = field(default_factory=ResampleConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    symmetry: SymmetryConfig = field(default_factory=SymmetryConfig)

    def __post_init__(self) -> None:
        check_ranges(self)  # as a settings file's values are (a config built in Python skips from_dict)
        if not self.max_noise_pitches >= 0:
            raise ValueError(f"max_noise_pitches must be >= 0 (0: off), not {self.max_noise_pitches}")
        if self.gridify_mm > 0:  # gridify's grid spans the whole scan, at least the face
            check_cells("gridify_mm", self.gridify_mm, 2 * self.crop_radius_mm, "a face, 2 × crop_radius_mm")
        if self.crop_radius_mm > self.resample.half_width_mm:
            raise ValueError(f"crop_radius_mm {self.crop_radius_mm:g} is wider than the resampling grid "
                             f"(resample.half_width_mm {self.resample.half_width_mm:g}), which would cut the face: "
                             f"set both")

    def to_dict(self) -> dict[str, Any]:
        """Every setting as plain values, nested tables as dicts (what `load` reads back, and a run's
        preprocess.json holds)."""
        return dataclasses.asdict(self)

    def fingerprint(self) -> str:
        """A stable text of the whole configuration (cache keys, gallery stores), with the SHA-256 of the nose
        proposer's model file when there is one (a new model makes new faces)."""
        data = self.to_dict()
        if self.detect.proposer:
            data["detect"]["proposer_sha256"] = proposer(self.detect.proposer).sha256
        return json.dumps(data, sort_keys=True)

    def digest(self) -> str:
        """A short hash of `fingerprint()` (16 hex digits): recorded in every face `Preprocessor` makes
        (`meta.extra["preprocess_fingerprint"]`, kept in its `.npz`) and shown by a gallery service's stats."""
        return hashlib.sha256(self.fingerprint().encode()).hexdigest()[:16]

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str | Path | None = None) -> "PreprocessConfig":
        """Settings checked field by field (config.from_dict); errors name `source`, the file they came from. A
        `fingerprint()` reads back too: its nose proposer's SHA-256 must be that of the model the settings name
        now."""
        detect = data.get("detect")
        made_with = detect.get("proposer_sha256") if isinstance(detect, dict) else None
        if made_with is not None:
            data = {**data, "detect": {k: v for k, v in detect.items() if k != "proposer_sha256"}}
        config = from_dict(cls, data, source)
        model = proposer(config.detect.proposer) if made_with is not None and config.detect.proposer else None
        if model is not None and made_with != model.sha256:
            raise ValueError(f"{source}: made with another nose proposer model (SHA-256 {str(made_with)[:12]}..., "
                             f"{model.path}'s is {model.sha256[:12]}...)")
        return config

    @classmethod
    def load(cls, path: str | Path) -> "PreprocessConfig":
        """A configuration from a TOML or JSON file holding some of the fields (nested by stage)."""
        data = read_settings(path)
        return cls.from_dict(data.get("preprocess", data), path)


class Preprocessor:
    """Raw scan -> cropped, cleaned, frontal face on a uniform grid (chapter §8.5)."""

    def __init__(self, config: PreprocessConfig = PreprocessConfig()):
        if not isinstance(config, PreprocessConfig):
            raise InputError(f"Preprocessor takes a PreprocessConfig (PreprocessConfig.from_dict for a table of "
                             f"settings, PreprocessConfig.load for a file), not {type(config).__name__}")
        self.config = config
        self.timings: dict[str, float] = {}

    def detector_view(self, scan: FaceScan) -> tuple[FaceScan, FaceScan, Sampling, Orientation]:
        """Steps 1–4: the scan as the face detector sees it (oriented, gridded, checked, de-spiked, smoothed), the
        scan before smoothing (what each pixel measured), its sampling and the orientation applied."""
        cfg = self.config
        check_points(scan)  # the count as read: a sparse cloud has fewer once rasterised (`gridify`)
        scan, view = self._timed("orient", orient, scan, cfg.orient, cfg.detect)
        scan = self._timed("gridify", gridify, scan, cfg.gridify_mm)
        sampling = self._timed("measure", measure_sampling, scan)
        self._timed("measure", check_surface, scan, sampling, cfg.max_noise_pitches)
        measured = self._timed("spikes", remove_spikes, scan, cfg.spikes, sampling)
        scan = self._timed("smooth", smooth_range_image, measured, *cfg.smooth.sigmas(sampling))
        return scan, measured, sampling, view

    def __call__(self, scan: FaceScan) -> FaceScan:
        """The preprocessed face of `scan`, computed with one BLAS thread (`workers.one_blas_thread`: its small
        linear algebra runs slower on more, many times slower on a busy machine); the caller's setting returns
        after."""
        if not isinstance(scan, FaceScan):
            raise InputError(f"Preprocessor takes a FaceScan (facerec3d.io.load_scan reads a file), not "
                             f"{type(scan).__name__}")
        with one_blas_thread():
            return self._preprocess(scan)

    def _preprocess(self, scan: FaceScan) -> FaceScan:
        cfg = self.config
        scan, measured, sampling, view = self.detector_view(scan)
        found = self._timed("detect", detect_face, scan, cfg.detect)
        scan = self._timed("dequantise", dequantise, scan, measured, sampling.depth_step_mm, found.nose_tip,
                           cfg.crop_radius_mm, cfg.dequantise)
        face = self._timed("crop", crop_sphere, scan, found.nose_tip, cfg.crop_radius_mm)
        at_face = Sampling(face.resolution(), sampling.depth_step_mm, sampling.noise_mm)
        face = self._timed("holes", fill_holes, face, cfg.holes)
        frontal = face.transformed(found.R, found.t).replace(
            landmarks={k: found.R @ v + found.t for k, v in found.landmarks.items()}
        )
        out = self._timed("resample", resample, frontal, cfg.resample)
        out = out.subset(np.linalg.norm(out.points, axis=1) <= cfg.crop_radius_mm)
        out = self._timed("denoise", denoise, out, cfg.denoise)
        out = self._timed("symmetry", complete_by_symmetry, out, cfg.symmetry, cfg.resample)
        quality = {"fit_rms_mm": found.fit_rms_mm, "inlier_fraction": found.inlier_fraction,
                   "protrusion_mm": found.protrusion_mm, "coverage": face_coverage(out, cfg.coverage_radius_mm),
                   **at_face.to_dict()}
        if view.turned or view.roll_deg:
            out = out.replace(meta=out.meta.replace(extra=dict(out.meta.extra, view=view.record())))
        extra = dict(out.meta.extra, to_frontal=np.hstack([found.R @ view.R, found.t[:, None]]).tolist(),
                     quality={k: round(float(v), 4) for k, v in quality.items()}, **{FINGERPRINT_KEY: cfg.digest()})
        if found.model_coefficients is not None:  # the model fit in this frame (matching.morphable.face_fit)
            k = cfg.detect.model.identity_modes
            extra[MODEL_FIT_KEY] = {"identity": found.model_coefficients[:k].tolist(),
                                    "expression": found.model_coefficients[k:].tolist()}
        return out.replace(meta=out.meta.replace(extra=extra))

    def _timed(self, stage: str, fn, *args):
        t0 = time.perf_counter()
        result = fn(*args)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t0
        return result


FINGERPRINT_KEY = "preprocess_fingerprint"  # meta.extra of a preprocessed face: its settings' digest()
MODEL_FIT_KEY = "model_fit"  # meta.extra of a preprocessed face: the morphable-model fit's coefficients


def preprocessed_with(face: FaceScan) -> str | None:
    """The `PreprocessConfig.digest()` a face made by `Preprocessor` records (a preprocessed `.npz` keeps it);
    "" for a face preprocessed by facerec3d that records none (an older version: its frontal transform only);
    None for a scan that is not a preprocessed face."""
    extra = face.meta.extra
    if FINGERPRINT_KEY in extra:
        return str(extra[FINGERPRINT_KEY])
    return "" if "to_frontal" in extra else None


QUALITY_FIELDS = ("fit_rms_mm", "inlier_fraction", "protrusion_mm", "coverage", "pitch_mm", "depth_step_mm",
                  "noise_mm")


def face_coverage(face: FaceScan, radius_mm: float) -> float:
    """Share of the frontal disc of `radius_mm` around the nose tip that holds data (1 = the whole face was seen)."""
    r = np.linalg.norm(face.points[:, :2], axis=1)
    cell = face.resolution() if face.n_points > 1 else 1.0
    return float(min(1.0, (r <= radius_mm).sum() * cell**2 / (np.pi * radius_mm**2)))


def scan_quality(face: FaceScan) -> dict[str, float]:
    """The quality record of a preprocessed face (`QUALITY_FIELDS`; empty when it has none)."""
    return dict(face.meta.extra.get("quality", {}))


def landmarks_in_input_frame(face: FaceScan) -> dict[str, np.ndarray]:
    """The fiducials of a preprocessed face mapped back into the input scan's coordinates (mm)."""
    M = np.asarray(face.meta.extra["to_frontal"], dtype=float)
    R, t = M[:, :3], M[:, 3]
    return {k: R.T @ (v - t) for k, v in face.landmarks.items()}
