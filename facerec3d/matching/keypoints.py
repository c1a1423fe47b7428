"""Keypoints and local surface features (chapter §8.10.2): a fast matcher and pre-filter.

Detection (after Mian, Bennamoun & Owens 2008, "Keypoint identification and
feature-based 3D face recognition"): at every grid point of a preprocessed
face, PCA of the points in a (2r + 1)² mm window (box filters over the 1 mm
grid) gives eigenvalues λ₁ ≥ λ₂ ≥ λ₃; the surface variation λ₃ / (λ₁ + λ₂ + λ₃)
(Pauly, Gross & Kobbelt 2002: zero on a plane, growing with curvature) is
the keypoint strength. Keypoints are its local maxima (non-maximum
suppression over `nms_radius`) above `min_variation`, at most
`max_keypoints` of the strongest, where the window is at least 60 % covered.

Descriptor: a local depth patch in the keypoint's own frame — normal n (the
PCA's smallest axis, towards +z), e₁ the face's x axis projected on the
tangent plane, e₂ = n × e₁; the points within `patch_radius` mm are binned on a
`patch_bins`² grid in (e₁, e₂) and each bin holds their mean height along n
(mm; empty bins 0).

Matching: mutual nearest neighbours of the descriptors (Euclidean, brute
force: a few dozen per face), restricted to keypoints within
`max_offset` mm of each other (both faces are in the same frontal frame);
then a RANSAC rigid check: of `ransac_iterations` random triples, the rigid
motion (Arun et al.) with the most matches mapped within `inlier_mm`. The
score is that number of consistent matches; the tiebreak is −their RMS
residual (mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter, uniform_filter
from scipy.spatial.distance import cdist

from facerec3d.geometry.transforms import rigid_from_covariances
from facerec3d.matching.base import Matcher, Template, check_face
from facerec3d.scan import FaceScan


@dataclass(frozen=True)
class KeypointConfig:
    """Keypoint detection, description and matching (§8.10.2; Mian et al. 2008). Lengths in mm."""

    radius: int = 8  # half-width (grid cells ≈ mm) of the PCA window (Mian et al. 2008: r = 20 mm spheres)
    min_variation: float = 0.01  # keypoint strength λ₃/Σλ below this: no keypoint (flat)
    nms_radius: int = 5  # grid cells: a keypoint is the strongest within this half-width
    max_keypoints: int = 80  # strongest kept per face
    patch_radius: float = 12.0  # descriptor support
    patch_bins: int = 8  # descriptor = patch_bins² mean heights
    max_offset: float = 15.0  # matched keypoints at most this far apart in the frontal frame
    inlier_mm: float = 2.5  # RANSAC: a match fits a motion when mapped within this distance
    ransac_iterations: int = 100
    seed: int = 0

    def __post_init__(self) -> None:
        if self.radius < 2 or self.nms_radius < 1 or self.patch_bins < 2 or self.max_keypoints < 3:
            raise ValueError("need radius >= 2, nms_radius >= 1, patch_bins >= 2, max_keypoints >= 3")


def _grid_images(face: FaceScan) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) points image (0 where invalid) and (H, W) validity of a gridded face."""
    if face.grid is None:
        raise ValueError("keypoints need a face on a grid (a preprocessed face)")
    xyz, valid = face.to_range_image()
    xyz[~valid] = 0.0
    return xyz, valid


def local_pca(face: FaceScan, radius: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per grid cell of a gridded face: (eigenvalues (H, W, 3) ascending, eigenvectors (H, W, 3, 3) as columns,
    window coverage (H, W) in [0, 1], validity (H, W)) of the points in the (2·radius + 1)² window."""
    xyz, valid = _grid_images(face)
    size = 2 * radius + 1
    v = valid.astype(np.float64)
    cover = uniform_filter(v, size, mode="constant")
    n = np.maximum(cover, 1e-12)
    mean = np.stack([uniform_filter(xyz[..., a] * v, size, mode="constant") for a in range(3)], -1) / n[..., None]
    cov = np.empty((*valid.shape, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            m = uniform_filter(xyz[..., a] * xyz[..., b] * v, size, mode="constant") / n
            cov[..., a, b] = cov[..., b, a] = m - mean[..., a] * mean[..., b]
    w, vec = np.linalg.eigh(cov)
    return w, vec, cover, valid


def detect_keypoints(face: FaceScan, config: KeypointConfig = KeypointConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints (K, 3) mm, their normals (K, 3)) of a preprocessed face, strongest first."""
    xyz, _ = _grid_images(face)
    w, vec, cover, valid = local_pca(face, config.radius)
    strength = np.where(valid & (cover >= 0.6), w[..., 0] / np.maximum(w.sum(-1), 1e-12), -np.inf)
    peak = (strength == maximum_filter(strength, 2 * config.nms_radius + 1, mode="constant", cval=-np.inf))
    rows, cols = np.nonzero(peak & (strength >= config.min_variation))
    order = np.argsort(-strength[rows, cols], kind="stable")[: config.max_keypoints]
    rows, cols = rows[order], cols[order]
    normals = vec[rows, cols, :, 0]
    normals *= np.where(normals[:, 2] < 0, -1.0, 1.0)[:, None]
    return xyz[rows, cols], normals


def describe(face: FaceScan, keypoints: np.ndarray, normals: np.ndarray,
             config: KeypointConfig = KeypointConfig()) -> np.ndarray:
    """(K, patch_bins²) float32 local depth patches (mm) of keypoints with unit normals (module docstring)."""
    p = face.points
    e1 = np.array([1.0, 0.0, 0.0]) - normals[:, :1] * normals
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
    e2 = np.cross(normals, e1)
    B, R = config.patch_bins, config.patch_radius
    out = np.zeros((len(keypoints), B * B), np.float32)
    for k, (q, a, b, n) in enumerate(zip(keypoints, e1, e2, normals)):
        d = p[np.abs(p[:, 0] - q[0]) <= R * 1.5] - q
        d = d[np.abs(d[:, 1]) <= R * 1.5]
        u, v, h = d @ a, d @ b, d @ n
        inside = (np.abs(u) < R) & (np.abs(v) < R)
        cell = (np.floor((v[inside] + R) / (2 * R) * B).astype(np.int64) * B
                + np.floor((u[inside] + R) / (2 * R) * B).astype(np.int64))
        total = np.bincount(cell, h[inside], B * B)
        count = np.bincount(cell, None, B * B)
        out[k] = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    return out


def match_keypoints(p_points: np.ndarray, p_desc: np.ndarray, g_points: np.ndarray, g_desc: np.ndarray,
                    config: KeypointConfig = KeypointConfig()) -> tuple[int, float]:
    """(consistent matches, RMS residual mm of them) between two faces' keypoints (module docstring)."""
    if len(p_points) < 3 or len(g_points) < 3:
        return 0, np.inf
    D = cdist(p_desc, g_desc)
    D[cdist(p_points, g_points) > config.max_offset] = np.inf
    j = np.argmin(D, axis=1)
    i = np.arange(len(p_points))
    mutual = (np.argmin(D, axis=0)[j] == i) & np.isfinite(D[i, j])
    P, G = p_points[i[mutual]], g_points[j[mutual]]
    if len(P) < 3:
        return int(len(P)), np.inf
    rng = np.random.default_rng(config.seed)
    triples = np.argsort(rng.random((config.ransac_iterations, len(P))), axis=1)[:, :3]  # distinct per row
    a, b = P[triples], G[triples]  # (T, 3, 3)
    a_bar, b_bar = a.mean(1, keepdims=True), b.mean(1, keepdims=True)
    H = np.ascontiguousarray(np.swapaxes(a - a_bar, 1, 2) @ (b - b_bar))
    R, t = rigid_from_covariances(H, np.ascontiguousarray(a_bar[:, 0]), np.ascontiguousarray(b_bar[:, 0]))
    res = np.linalg.norm(np.einsum("tij,nj->tni", R, P) + t[:, None] - G, axis=2)  # (T, M)
    inl = res <= config.inlier_mm
    best = int(np.argmax(inl.sum(1)))
    n = int(inl[best].sum())
    return n, float(np.sqrt(np.mean(res[best, inl[best]] ** 2))) if n else np.inf


class KeypointMatcher(Matcher[Template]):
    """Keypoint matching (§8.10.2): score = number of geometrically consistent descriptor matches,
    tiebreak = −their RMS residual (mm). Fast enough to shortlist a gallery before ICP."""

    name = "keypoints"
    config_class = KeypointConfig

    def __init__(self, config: KeypointConfig = KeypointConfig()):
        self.config = config

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        points, normals = detect_keypoints(scan, self.config)
        arrays = {"points": points.astype(np.float32), "descriptors": describe(scan, points, normals, self.config)}
        return Template(scan.meta.subject, scan.meta.scan_id, self.name, arrays, {})

    def _match(self, p: Template, t: Template) -> tuple[int, float]:
        return match_keypoints(p.arrays["points"].astype(np.float64), p.arrays["descriptors"],
                               t.arrays["points"].astype(np.float64), t.arrays["descriptors"], self.config)

    def score(self, probe: FaceScan | Template, template: Template) -> float:
        return float(self._match(self._probe(probe, [template]), template)[0])

    def scores(self, probe: FaceScan | Template, templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray]:
        p = self._probe(probe, templates)
        out = np.array([self._match(p, t) for t in templates], dtype=np.float64).reshape(-1, 2)
        return out[:, 0], -out[:, 1]
