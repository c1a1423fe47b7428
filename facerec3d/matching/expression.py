"""Expression handling (chapter §8.10.3): masking where expressions move the face, and the expression deformation
model of Al-Osaimi, Bennamoun & Mian (IJCV 2009, `ResidueModel`; used by the afm matcher, `afm.py`, which also
removes the fitted blendshapes instead).

Masking: where does an expression move the face?

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

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

from facerec3d.facemodel import load_model
from facerec3d.matching.base import learnt_arrays
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


# ------------------------------------------------------------------------- expression deformation model
@dataclass(frozen=True)
class ResidueConfig:
    """The expression deformation model of Al-Osaimi, Bennamoun & Mian (IJCV 2009; chapter §8.10.3)."""

    variance: float = 0.95  # share of the training residues' energy its modes keep (PCA, §8.7.2)
    max_components: int = 60  # and at most this many modes


@dataclass(frozen=True, eq=False)
class ResidueModel:
    """A PCA model of expression residues: shape vectors of one person's non-neutral scan less their neutral one.

    Vectors are a face's features with a validity mask per feature group (`valid` (k,) covering `coefficients`
    (C·k,) channel by channel, as the afm templates have them). The model is learnt from ± each residue, so it
    has zero mean and a probe–gallery residue scores the same whichever face is the expressive one. A residue r
    is reconstructed from the modes P (eq. 8.46: r̂ = P Pᵀ r) and scored by its reconstruction error (eq. 8.47:
    e = ‖r − r̂‖, here as RMS over the features both faces have): an expression of the same person is what the
    model reconstructs, a difference of identity is not. Missing features of a residue take the value 0 (no
    deformation) for the projection, and are left out of the error.
    """

    components: np.ndarray  # (C·k, p) orthonormal columns
    eigenvalues: np.ndarray  # (p,)

    @staticmethod
    def learn(features: Sequence[tuple[np.ndarray, np.ndarray]], subjects: Sequence[str],
              labels: Sequence[str | None], expression_energy: Sequence[float],
              config: ResidueConfig = ResidueConfig()) -> "ResidueModel | None":
        """From training faces' (coefficients, valid) with their subjects: each subject's neutral face (its first
        labelled neutral, else the one whose fitted expression is weakest, `expression_energy`) against each of its
        other faces. None when no subject has two faces."""
        by_subject: dict[str, list[int]] = {}
        for i, s in enumerate(subjects):
            by_subject.setdefault(s, []).append(i)
        residues = []
        for idx in by_subject.values():
            if len(idx) < 2:
                continue
            neutral = [i for i in idx if labels[i] == "neutral"]
            ref = neutral[0] if neutral else min(idx, key=lambda i: expression_energy[i])
            c0, m0 = features[ref]
            for i in idx:
                if i != ref:
                    c, m = features[i]
                    ok = np.tile(m & m0, len(c) // len(m))
                    residues.append(np.where(ok, c.astype(np.float64) - c0, 0.0))
        if not residues:
            return None
        R = np.array(residues)
        _, s, Vt = np.linalg.svd(np.concatenate([R, -R]), full_matrices=False)
        energy = s**2 / (2 * len(R))
        share = np.cumsum(energy) / max(energy.sum(), np.finfo(float).tiny)
        p = min(int(np.searchsorted(share, config.variance - 1e-12)) + 1, config.max_components, len(s))
        return ResidueModel(np.ascontiguousarray(Vt[:p].T), energy[:p])

    def state(self) -> tuple[dict[str, np.ndarray], dict]:
        return {"residue_components": self.components, "residue_eigenvalues": self.eigenvalues}, {}

    @staticmethod
    def from_state(arrays, features: int) -> "ResidueModel":
        """The model `state()` gave, for vectors of `features` values (ValueError naming the array when its arrays
        are not of such a model: `base.learnt_arrays`)."""
        return ResidueModel(*learnt_arrays(arrays, {"residue_components": ("d", "p"), "residue_eigenvalues": ("p",)},
                                           d=features))

    def errors(self, probe: np.ndarray, probe_valid: np.ndarray, gallery: np.ndarray,
               gallery_valid: np.ndarray) -> np.ndarray:
        """(n,) reconstruction errors (RMS over the shared features) of the residues probe − gallery[i]
        (eqs. 8.46–8.47); +inf where the two share no feature."""
        channels = probe.shape[-1] // probe_valid.shape[-1]
        M = np.tile(gallery_valid & probe_valid, channels).astype(np.float64)
        R = (probe.astype(np.float64) - gallery) * M
        E = R - (R @ self.components) @ self.components.T
        num, den = np.einsum("ij,ij->i", E * M, E), M.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, np.sqrt(num / np.maximum(den, 1.0)), np.inf)
