"""The preprocessing pipeline (chapter §8.5): raw scan in, clean frontal face on a uniform grid out.

    Preprocessor()(scan) -> face

1. point clouds without a range-image grid are put on one (`gridify`);
2. spikes are removed (§8.5.2);
3. the face is detected: nose tip, fiducials and frontal pose (§8.5.1, §8.5.5);
4. the face is cropped as a sphere around the nose tip (§8.5.1);
5. holes inside it are filled (§8.5.3);
6. it is turned into the frontal frame (nose tip at the origin, looking along +z);
7. resampled on a uniform x–y grid (§8.5.6) and cropped again to the sphere;
8. and its depth is smoothed (§8.5.4).

The result keeps the scan's metadata; its landmarks are the fiducials in the
frontal frame, and `meta.extra["to_frontal"]` holds the 3×4 matrix [R | t]
that maps input-scan coordinates x to R x + t in the frontal frame.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.config import from_dict, read_settings
from facerec3d.preprocess.denoise import DenoiseConfig, denoise
from facerec3d.preprocess.detect import DetectConfig, crop_sphere, detect_face
from facerec3d.preprocess.holes import HoleConfig, fill_holes
from facerec3d.preprocess.resample import ResampleConfig, gridify, resample
from facerec3d.preprocess.spikes import SpikeConfig, remove_spikes
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class PreprocessConfig:
    """Every preprocessing setting, by stage; defaults as documented on each stage's config."""

    crop_radius_mm: float = 80.0  # §8.5.1: the face is the sphere of this radius around the nose tip
    gridify_mm: float = 0.7  # cell size when a point cloud has to be put on a grid
    spikes: SpikeConfig = field(default_factory=SpikeConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    holes: HoleConfig = field(default_factory=HoleConfig)
    resample: ResampleConfig = field(default_factory=ResampleConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def fingerprint(self) -> str:
        """A stable text of the whole configuration (cache keys, gallery stores)."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PreprocessConfig":
        return from_dict(cls, data)

    @classmethod
    def load(cls, path: str | Path) -> "PreprocessConfig":
        """A configuration from a TOML or JSON file holding some of the fields (nested by stage)."""
        data = read_settings(path)
        return cls.from_dict(data.get("preprocess", data))


class Preprocessor:
    """Raw scan -> cropped, cleaned, frontal face on a uniform grid (chapter §8.5)."""

    def __init__(self, config: PreprocessConfig = PreprocessConfig()):
        self.config = config
        self.timings: dict[str, float] = {}

    def __call__(self, scan: FaceScan) -> FaceScan:
        cfg = self.config
        scan = self._timed("gridify", gridify, scan, cfg.gridify_mm)
        scan = self._timed("spikes", remove_spikes, scan, cfg.spikes)
        found = self._timed("detect", detect_face, scan, cfg.detect)
        face = self._timed("crop", crop_sphere, scan, found.nose_tip, cfg.crop_radius_mm)
        face = self._timed("holes", fill_holes, face, cfg.holes)
        frontal = face.transformed(found.R, found.t).replace(
            landmarks={k: found.R @ v + found.t for k, v in found.landmarks.items()}
        )
        out = self._timed("resample", resample, frontal, cfg.resample)
        out = out.subset(np.linalg.norm(out.points, axis=1) <= cfg.crop_radius_mm)
        out = self._timed("denoise", denoise, out, cfg.denoise)
        extra = dict(out.meta.extra, to_frontal=np.hstack([found.R, found.t[:, None]]).tolist(),
                     fit_rms_mm=found.fit_rms_mm)
        return out.replace(meta=out.meta.replace(extra=extra))

    def _timed(self, stage: str, fn, *args):
        t0 = time.perf_counter()
        result = fn(*args)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t0
        return result


def landmarks_in_input_frame(face: FaceScan) -> dict[str, np.ndarray]:
    """The fiducials of a preprocessed face mapped back into the input scan's coordinates (mm)."""
    M = np.asarray(face.meta.extra["to_frontal"], dtype=float)
    R, t = M[:, :3], M[:, 3]
    return {k: R.T @ (v - t) for k, v in face.landmarks.items()}
