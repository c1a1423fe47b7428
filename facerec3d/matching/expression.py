"""Expression handling by masking (chapter §8.10.3): where does an expression move the face?

The morphable model's 53 ARKit expression blendshapes (ICT-FaceKit,
`facerec3d.facemodel`) give each vertex's displacement at full weight.
A vertex's *mobility* is the largest displacement any one blendshape gives it
(mm). Mapped into the frontal frame of preprocessed faces (nose tip at the
origin, looking along +z, 1 mm grid) it marks the expression-driven parts
(mouth, jaw, cheeks, brows, eyelids) and leaves the semi-rigid ones (nose,
upper forehead, temples) low. Matchers drop probe points whose mobility
exceeds a threshold before matching, so that an expression cannot pull the
alignment or the score (cf. Chang, Bowyer & Flynn 2006; Mian et al. 2007,
who keep the nose and forehead for the same reason).

The map is learnt from the model alone (no training scans): it is the same
for every face, which is right to within a few mm because preprocessing
aligns every face to that model's frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

from facerec3d.facemodel import load_model
from facerec3d.preprocess.resample import ResampleConfig


@dataclass(frozen=True, eq=False)
class MobilityMap:
    """Expression mobility (mm) on a square x–y grid of the frontal frame; outside the model face: +inf."""

    values: np.ndarray  # (n, n) float64 mm; values[i, j] at x = lo + j·step, y = lo + i·step
    lo: float  # mm
    step: float  # mm

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Mobility (mm) at the x–y position of each point (N, 3) of a frontal face (nearest grid cell)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = self.values.shape[0]
        j = np.rint((p[:, 0] - self.lo) / self.step).astype(np.int64)
        i = np.rint((p[:, 1] - self.lo) / self.step).astype(np.int64)
        inside = (i >= 0) & (i < n) & (j >= 0) & (j < n)
        out = np.full(len(p), np.inf)
        out[inside] = self.values[i[inside], j[inside]]
        return out


@lru_cache(maxsize=1)
def expression_mobility(half_width: float | None = None, step: float = 1.0) -> MobilityMap:
    """The model's mobility map over ±half_width mm (default: the resampling grid's, §8.5.6) at `step` mm: at
    each grid cell, the mobility of the frontmost (largest z) of the 8 face vertices nearest in x–y; cells over
    3 mm from any vertex: +inf."""
    half_width = ResampleConfig().half_width_mm if half_width is None else half_width
    model = load_model()
    face = model.region == 0
    verts = (model.mean - model.mean[model.nose_tip]).astype(np.float64)[face]
    mobility = np.linalg.norm(model.expression_basis[:, face].astype(np.float64), axis=2).max(axis=0)
    axis = np.arange(-half_width, half_width + step / 2, step)
    gx, gy = np.meshgrid(axis, axis)
    dist, idx = cKDTree(verts[:, :2]).query(np.column_stack([gx.ravel(), gy.ravel()]), k=8)
    front = np.take_along_axis(idx, np.argmax(verts[idx, 2], axis=1)[:, None], axis=1)[:, 0]
    values = np.where(dist[:, 0] <= 3.0, mobility[front], np.inf).reshape(gx.shape)
    return MobilityMap(values, float(axis[0]), float(step))
