"""Curvature-map matching (chapter §8.9): shape-index maps compared inside the rigid part of the face.

A preprocessed face's depth map (filled where missing, `depthmap`) gives its
shape index at every cell (geometry.curvature: Gaussian smoothing at
`sigma_mm`, Koenderink's index, cap +1 … cup −1). The template is the
shape-index map sampled on the window, with a mask of the cells that are
valid, lie at least `sigma_mm` inside the measured surface (so filled depth
does not leak in) and belong to the rigid region: the part of the face no
lower than `below_nose_mm` under the nose tip (forehead, eyes, nose and upper
cheeks, which expressions move least, §8.9 and §8.10). The score is minus
the mean absolute shape-index difference over the cells valid in both maps
(higher = more alike, 0 for identical maps); pose is already normalised by
preprocessing, so nothing is learnt and one probe is compared with the whole
gallery in one array operation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from facerec3d.geometry.curvature import depth_curvature
from facerec3d.matching.base import Matcher, Template, check_face
from facerec3d.matching.depthmap import DepthMapConfig, depth_window, fill_nearest
from facerec3d.preprocess.resample import grid_xy
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class CurvatureConfig:
    """Curvature matcher settings (chapter §8.9)."""

    window: DepthMapConfig = field(default_factory=DepthMapConfig)  # the compared cells (§8.7.1 grid; its `fill`
    #                                                                  is unused: gaps take the nearest depth)
    sigma_mm: float = 2.0  # Gaussian σ of the depth smoothing before differentiation (§8.9: curvature is
    #                        noise-sensitive); cells nearer than this to missing data are not compared
    below_nose_mm: float = 25.0  # rigid region: cells lower than this under the nose tip (mouth, chin) are left out
    min_overlap: float = 0.3  # fewer common cells than this share of the window: no match (score −inf)

    def __post_init__(self) -> None:
        if self.sigma_mm <= 0 or not 0 <= self.min_overlap <= 1:
            raise ValueError("need sigma_mm > 0 and 0 <= min_overlap <= 1")


class CurvatureMap(NamedTuple):
    """A face's shape-index map on the window, flattened, and where it is compared."""

    shape_index: np.ndarray  # (d,) float32 in [−1, 1]
    mask: np.ndarray  # (d,) bool


class CurvatureMatcher(Matcher[CurvatureMap]):
    """Shape-index maps compared inside the rigid face region (chapter §8.9); see the module docstring."""

    name = "curvature"
    config_class = CurvatureConfig

    def __init__(self, config: CurvatureConfig = CurvatureConfig()) -> None:
        self.config = config
        _, y = grid_xy(config.window.grid)
        self._region = config.window.window(y >= -config.below_nose_mm).ravel()

    def curvature_map(self, scan: FaceScan) -> CurvatureMap:
        """The shape-index map and comparison mask of a preprocessed face."""
        cfg, w = self.config, self.config.window
        z, valid = depth_window(scan, w)
        s = depth_curvature(fill_nearest(z), w.step_mm, cfg.sigma_mm).shape_index
        inside = ndimage.binary_erosion(valid, iterations=int(np.ceil(cfg.sigma_mm / w.step_mm)), border_value=0)
        return CurvatureMap(s.ravel().astype(np.float32), inside.ravel() & self._region)

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        m = self.curvature_map(scan)
        return Template(scan.meta.subject, scan.meta.scan_id, self.name,
                        {"shape_index": m.shape_index, "mask": m.mask})

    def prepare(self, scan: FaceScan) -> CurvatureMap:
        check_face(scan)
        return self.curvature_map(scan)

    def scores(self, probe: FaceScan | CurvatureMap, templates: Sequence[Template]) -> tuple[np.ndarray, None]:
        p = self._probe(probe, templates)
        if not templates:
            return np.zeros(0), None
        S = np.stack([t.arrays["shape_index"] for t in templates])
        M = (np.stack([t.arrays["mask"] for t in templates]) & p.mask).astype(np.float32)
        n = M.sum(axis=1).astype(np.float64)
        diff = np.einsum("ij,ij->i", np.abs(S - p.shape_index), M).astype(np.float64) / np.maximum(n, 1)
        return np.where(n >= self.config.min_overlap * self._region.sum(), -diff, -np.inf), None

    def score(self, probe: FaceScan | CurvatureMap, template: Template) -> float:
        return float(self.scores(probe, [template])[0][0])
