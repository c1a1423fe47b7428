"""Pose correction against a reference face (chapter §8.5.5).

The frontal frame is that of the shipped morphable model: looking along +z,
y up, with the nose tip at the origin. A scan is brought into it by an
initial Hotelling (PCA) alignment of the face's normal axis, a rigid
point-to-plane ICP to the model's mean face, and then a fit of the model's
identity and expression modes together with the pose, so that neither the
subject's own face shape nor an expression tilts the result. After it, a
probe and a gallery face start within the matcher's zone of convergence.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from facerec3d.datasets.model import FIDUCIAL_LANDMARK68, load_model


def rotation_to_z(normal: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit vector `normal` onto +z."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    axis = np.cross(n, [0.0, 0.0, 1.0])
    s, c = np.linalg.norm(axis), n[2]
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def hotelling_rotation(points: np.ndarray) -> np.ndarray:
    """Initial rotation from the face's least-variance (normal) axis, turned to face +z (Hotelling / PCA)."""
    centred = points - points.mean(axis=0)
    _, vecs = np.linalg.eigh(centred.T @ centred)
    normal = vecs[:, 0]
    if normal[2] < 0:  # the face looks towards the camera, along +Z of the scan frame
        normal = -normal
    return rotation_to_z(normal)


@dataclass(frozen=True)
class ModelFitConfig:
    """Fitting the morphable model's identity and expression modes with the pose (§8.5.5, §8.10.3)."""

    identity_modes: int = 40  # leading identity modes fitted
    expression_modes: bool = True  # fit the 53 blendshapes too, so expressions do not tilt the pose
    iterations: int = 10
    start_distance_mm: float = 10.0
    end_distance_mm: float = 3.0
    regularisation: float = 1.0  # λ of the Gaussian prior on the coefficients (mm²)
    radius_mm: float = 95.0  # model vertices this close to the mean nose tip take part
    max_points: int = 3000  # scan points used (an even subset of those given)
    core_radius_mm: float = 60.0  # the fit is scored on the scan points this near the nose tip ...
    inlier_mm: float = 2.5  # ... as the share of them this near the model surface


@dataclass(frozen=True)
class _FitBasis:
    mean: np.ndarray  # (n, 3) vertices of the fitted part, mean nose tip at the origin
    basis: np.ndarray  # (n, 3, K) modes
    triangles: np.ndarray  # (T, 3) triangles of the fitted part
    boundary: np.ndarray  # (n,) bool: vertex on the rim of the fitted part or of its holes
    landmarks: dict[str, int]  # fiducial -> row in mean


def _fit_basis(config: ModelFitConfig) -> _FitBasis:
    return _basis(config.identity_modes, config.expression_modes, config.radius_mm)


@lru_cache(maxsize=8)
def _basis(identity_modes: int, expression_modes: bool, radius_mm: float) -> _FitBasis:
    """The part of the model within `radius_mm` of the mean nose tip, with its modes (cached per choice)."""
    m = load_model()
    nose = m.mean[m.nose_tip]
    inside = (m.region == 0) & (np.linalg.norm(m.mean - nose, axis=1) < radius_mm)
    sel = np.flatnonzero(inside)
    modes = [m.identity_basis[:identity_modes, sel]]
    if expression_modes:
        modes.append(m.expression_basis[:, sel])
    basis = np.concatenate(modes).astype(np.float64).transpose(1, 2, 0)  # (n, 3, K)
    row = np.full(len(m.mean), -1)
    row[sel] = np.arange(len(sel))
    tris = row[m.triangles[inside[m.triangles].all(axis=1)]]
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(edges, axis=0, return_counts=True)
    boundary = np.zeros(len(sel), bool)
    boundary[uniq[count == 1].ravel()] = True
    fid = {name: int(row[m.landmarks68[i]]) for name, i in FIDUCIAL_LANDMARK68.items() if row[m.landmarks68[i]] >= 0}
    return _FitBasis((m.mean[sel] - nose).astype(np.float64), basis, tris, boundary, fid)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals of a triangle mesh (area-weighted face normals)."""
    fn = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]], vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    corners, weights = triangles.ravel(), np.repeat(fn, 3, axis=0)  # each face normal to its three vertices
    vn = np.stack([np.bincount(corners, weights[:, d], minlength=len(vertices)) for d in range(3)], axis=1)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class ModelFit:
    """A morphable-model fit: the map x -> R x + t from scan to frontal frame (nose tip at the origin),
    the fitted fiducials in scan coordinates (mm) and the RMS point-to-plane distance of the fit (mm)."""

    R: np.ndarray
    t: np.ndarray
    landmarks: dict[str, np.ndarray]
    rms_mm: float  # of the inliers
    inlier_fraction: float  # share of the scan points near the nose (core radius) that fit the model
    coefficients: np.ndarray
    vertices: np.ndarray  # (n, 3) the fitted model surface in the frontal frame (nose tip at the origin)
    vertex_normals: np.ndarray  # (n, 3) its unit normals


def fit_face_model(points: np.ndarray, R: np.ndarray, t: np.ndarray, config: ModelFitConfig = ModelFitConfig()) -> ModelFit:
    """Fit pose, identity and expression of the morphable model to scan points (mm), from x -> R x + t.

    Each iteration pairs every scan point with its closest model vertex
    (pairs farther than a shrinking cut-off, or on the model's rim, are
    dropped: the neck, ears and hair have no partner), then solves one
    linearised point-to-plane least-squares problem (Chen & Medioni) for a
    small rigid motion and the mode coefficients together, with a Gaussian
    prior of weight λ on the coefficients. Pairing from the scan side means
    self-occluded parts of the face do not pull the fit.
    """
    fb = _fit_basis(config)
    points = points[:: max(1, len(points) // config.max_points)]
    K = fb.basis.shape[2]
    c = np.zeros(K)
    R, t = np.asarray(R, float), np.asarray(t, float)
    n = config.iterations
    V = fb.mean
    tree, normals = cKDTree(V), vertex_normals(V, fb.triangles)
    reg = np.zeros(6 + K)
    reg[6:] = config.regularisation
    for i in range(n):
        cutoff = config.start_distance_mm + (config.end_distance_mm - config.start_distance_mm) * i / max(n - 1, 1)
        p = points @ R.T + t
        d, j = tree.query(p, distance_upper_bound=cutoff)
        keep = np.isfinite(d)
        keep[keep] = ~fb.boundary[j[keep]]
        if keep.sum() < 50:
            break
        p, j = p[keep], j[keep]
        nrm = normals[j]
        r = np.einsum("ij,ij->i", nrm, p - V[j])
        J = np.concatenate([np.cross(p, nrm), nrm, -np.einsum("ij,ijk->ik", nrm, fb.basis[j])], axis=1)
        x = np.linalg.solve(J.T @ J + np.diag(reg), -(J.T @ r) - reg * np.concatenate([np.zeros(6), c]))
        dR = Rotation.from_rotvec(x[:3]).as_matrix()
        R, t = dR @ R, dR @ t + x[3:6]
        if K:
            c = c + x[6:]
            V = fb.mean + fb.basis @ c
            tree, normals = cKDTree(V), vertex_normals(V, fb.triangles)
    nose = V[fb.landmarks["nose_tip"]]
    landmarks = {name: R.T @ (V[k] - t) for name, k in fb.landmarks.items()}
    p = points @ R.T + (t - nose)
    core = np.linalg.norm(p, axis=1) <= config.core_radius_mm
    d, j = tree.query(p[core] + nose)
    dist = np.abs(np.einsum("ij,ij->i", normals[j], p[core] + nose - V[j]))
    good = dist <= config.inlier_mm
    rms = float(np.sqrt(np.mean(dist[good] ** 2))) if good.any() else float("inf")
    return ModelFit(R, t - nose, landmarks, rms, float(good.mean()) if len(good) else 0.0, c, V - nose, normals)
