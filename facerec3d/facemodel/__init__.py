"""The ICT-FaceKit Light morphable face model, shipped with facerec3d: preprocessing fits its fiducials (pose),
matching uses its expression mobility, and the synthetic data are made from it.

Copyright (c) 2020 USC Institute for Creative Technologies, MIT licence (see
data/LICENSE-ICT-FaceKit). The face and head-and-neck part (11,248 vertices)
is stored with float16 bases (max error 0.004 mm identity, 0.016 mm
expression). Units mm; the face looks along +z, y is up.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

#: Expression presets: blendshape name -> weight at full strength.
EXPRESSION_PRESETS: dict[str, dict[str, float]] = {
    "neutral": {},
    "smile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0, "cheekSquint_L": 0.6, "cheekSquint_R": 0.6,
              "eyeSquint_L": 0.3, "eyeSquint_R": 0.3},
    "open-mouth": {"jawOpen": 1.0},
    "surprise": {"jawOpen": 0.6, "browInnerUp_L": 1.0, "browInnerUp_R": 1.0, "browOuterUp_L": 1.0,
                 "browOuterUp_R": 1.0, "eyeWide_L": 0.8, "eyeWide_R": 0.8},
    "frown": {"browDown_L": 1.0, "browDown_R": 1.0, "mouthFrown_L": 1.0, "mouthFrown_R": 1.0,
              "noseSneer_L": 0.4, "noseSneer_R": 0.4},
    "puffed-cheeks": {"cheekPuff_L": 1.0, "cheekPuff_R": 1.0, "mouthClose": 0.3},
}

#: Names of the 68 Multi-PIE landmarks used as named fiducials.
FIDUCIAL_LANDMARK68 = {
    "nose_tip": 30,
    "nose_bridge": 27,
    "left_eye_inner": 42,  # subject's left (+x)
    "right_eye_inner": 39,
    "left_eye_outer": 45,
    "right_eye_outer": 36,
    "left_mouth_corner": 54,
    "right_mouth_corner": 48,
    "chin": 8,
}


@dataclass(frozen=True)
class MorphableModel:
    """A linear face model: shape = mean + Σ α_k identity_k + Σ w_j expression_j (mm)."""

    mean: np.ndarray  # (V, 3) float32
    identity_basis: np.ndarray  # (K, V, 3) float16
    expression_basis: np.ndarray  # (E, V, 3) float16
    expression_names: tuple[str, ...]
    triangles: np.ndarray  # (T, 3) int32
    region: np.ndarray  # (V,) uint8, 0 face, 1 head and neck
    nose_tip: int
    landmarks68: np.ndarray  # (68,) int64

    def shape(self, identity: np.ndarray | None = None, expression: dict[str, float] | np.ndarray | None = None) -> np.ndarray:
        """Vertex positions (V, 3) float64 in mm for identity coefficients α and expression weights w."""
        v = self.mean.astype(np.float64)
        if identity is not None:
            a = np.asarray(identity, dtype=np.float64)
            v = v + np.tensordot(a, self.identity_basis[: len(a)].astype(np.float64), 1)
        if expression is not None:
            w = self.expression_weights(expression) if isinstance(expression, dict) else np.asarray(expression, float)
            nz = np.flatnonzero(w)
            if len(nz):
                v = v + np.tensordot(w[nz], self.expression_basis[nz].astype(np.float64), 1)
        return v

    def expression_weights(self, blend: dict[str, float]) -> np.ndarray:
        """Blendshape weight vector from a {name: weight} dict; unknown names raise KeyError."""
        w = np.zeros(len(self.expression_names))
        index = {n: i for i, n in enumerate(self.expression_names)}
        for name, value in blend.items():
            w[index[name]] = value
        return w

    def fiducials(self, vertices: np.ndarray) -> dict[str, np.ndarray]:
        """Named fiducial points (mm) of a face given its vertices."""
        return {name: vertices[self.landmarks68[i]].copy() for name, i in FIDUCIAL_LANDMARK68.items()}


@lru_cache(maxsize=1)
def load_model() -> MorphableModel:
    """The packaged ICT-FaceKit model (cached)."""
    with resources.files("facerec3d.facemodel").joinpath("data/ict_facekit.npz").open("rb") as f:
        d = np.load(f)
        return MorphableModel(
            mean=d["mean"],
            identity_basis=d["identity_basis"],
            expression_basis=d["expression_basis"],
            expression_names=tuple(str(s) for s in d["expression_names"]),
            triangles=d["triangles"],
            region=d["region"],
            nose_tip=int(d["nose_tip"]),
            landmarks68=d["landmarks68"],
        )
