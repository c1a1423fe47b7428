"""Synthetic faces made directly in the preprocessed form (no range scanner, no preprocessing), for tests and
benchmarks: a random ICT-FaceKit identity (coefficients ~ N(0, 1), seeded by the subject number), nose tip at
the origin, looking along +z, rasterised on the 1 mm grid of §8.5.6 and cropped to CROP_MM around the nose tip,
like the output of `Preprocessor` (~18k points with the 95 mm crop). ~60 ms per face.
"""

from __future__ import annotations

import numpy as np

from facerec3d.facemodel import EXPRESSION_PRESETS, load_model
from facerec3d.geometry.transforms import rotation_from_euler
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.preprocess.resample import ResampleConfig, depth_to_scan, rasterize_depth
from facerec3d.scan import FaceScan, ScanMeta

CROP_MM = PreprocessConfig().crop_radius_mm  # mm: crop radius around the nose tip, as preprocessing crops


def face_mesh(subject: int, expression: str = "neutral") -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) mm with the nose tip at the origin, face triangles (T, 3)) of identity `subject` with an
    expression (`EXPRESSION_PRESETS`)."""
    model = load_model()
    v = model.shape(np.random.default_rng(subject).standard_normal(100), EXPRESSION_PRESETS[expression])
    return v - v[model.nose_tip], model.triangles[(model.region[model.triangles] == 0).all(axis=1)]


def on_preprocessing_grid(vertices: np.ndarray, triangles: np.ndarray, crop_mm: float = CROP_MM) -> FaceScan:
    """A face mesh (frontal frame, nose tip near the origin) as preprocessing leaves a face: rasterised on the
    1 mm x–y grid of §8.5.6 and cropped to `crop_mm` around the origin."""
    scan = depth_to_scan(rasterize_depth(vertices, triangles), ResampleConfig())
    return scan.subset(np.linalg.norm(scan.points, axis=1) <= crop_mm)


def frontal_face(subject: int, pose_deg: float = 0.0, shift_mm: float = 0.0, noise_mm: float = 0.0,
                 seed: int | None = None, expression: str = "neutral", crop_mm: float = CROP_MM) -> FaceScan:
    """Identity `subject` as a preprocessed face, with the model's true fiducials as landmarks; a probe of
    it: with an expression (`EXPRESSION_PRESETS`), moved by a random rotation (≤ pose_deg degrees about each
    axis) and shift (≤ shift_mm mm per axis), with Gaussian depth noise (σ noise_mm mm), drawn from `seed`; cropped
    to `crop_mm` around the nose tip."""
    v, tris = face_mesh(subject, expression)
    rng = np.random.default_rng(seed)
    if pose_deg or shift_mm:
        v = v @ rotation_from_euler(*rng.uniform(-pose_deg, pose_deg, 3)).T + rng.uniform(-shift_mm, shift_mm, 3)
    scan = on_preprocessing_grid(v, tris, crop_mm)
    points = scan.points.copy()
    if noise_mm:
        points[:, 2] += rng.normal(0.0, noise_mm, len(points))
    meta = ScanMeta(subject=str(subject), scan_id=f"{subject}-{expression}-{seed}", expression=expression)
    return scan.replace(points=points, landmarks=load_model().fiducials(v), meta=meta)
