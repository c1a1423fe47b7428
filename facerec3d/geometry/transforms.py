"""Rigid transforms: rotations from head-pose angles, the SVD solution of Arun et al., angles between rotations.

Conventions: the face looks along +z, y is up, x is the subject's left.
Yaw turns about y, pitch about x, roll about z; angles in degrees.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def rotation_from_euler(yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """3×3 rotation R = Rz(roll) · Rx(pitch) · Ry(yaw), angles in degrees."""
    y, p, r = np.deg2rad([yaw, pitch, roll])
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return Rz @ Rx @ Ry


def rotation_angle(R: np.ndarray) -> float:
    """The angle of a rotation matrix, in degrees (0 for the identity)."""
    c = (np.trace(np.asarray(R, dtype=np.float64)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_between(R1: np.ndarray, R2: np.ndarray) -> float:
    """The angle in degrees of the rotation taking R1 to R2."""
    return rotation_angle(np.asarray(R2) @ np.asarray(R1).T)


def rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid motion (R, t) with target ≈ R · source + t (Arun et al. 1987; chapter §8.6.1), optionally
    with per-pair weights: the cross-covariance of the centred point sets, then `rigid_from_covariance`."""
    P = np.asarray(source, dtype=np.float64)
    G = np.asarray(target, dtype=np.float64)
    if P.shape != G.shape or P.ndim != 2 or P.shape[1] != 3 or len(P) < 3:
        raise ValueError(f"need two (N>=3, 3) arrays of equal shape, got {P.shape} and {G.shape}")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    p_bar = w @ P
    g_bar = w @ G
    H = (P - p_bar).T @ ((G - g_bar) * w[:, None])
    return rigid_from_covariance(np.ascontiguousarray(H), p_bar, g_bar)


@njit(cache=True)
def rigid_from_covariance(H, p_bar, g_bar):  # pragma: no cover - compiled
    """Arun et al.'s SVD solution (R, t) from the cross-covariance H = Σ (p − p̄)(g − ḡ)ᵀ and the centroids p̄, ḡ
    (chapter §8.6.1): with H = U Σ Vᵀ, R = V Uᵀ, a reflection (det = −1) fixed by flipping the sign of the last
    singular vector; t = ḡ − R p̄. Compiled, so the ICP loop calls it too."""
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T
    if np.linalg.det(V @ U.T) < 0.0:
        V[:, 2] = -V[:, 2]
    R = V @ U.T
    return R, g_bar - R @ p_bar


@njit(cache=True)
def rigid_from_covariances(H, p_bar, g_bar):  # pragma: no cover - compiled
    """`rigid_from_covariance` of each of T problems: H (T, 3, 3), p̄ and ḡ (T, 3) → R (T, 3, 3), t (T, 3)."""
    R = np.empty_like(H)
    t = np.empty_like(p_bar)
    for k in range(H.shape[0]):
        R[k], t[k] = rigid_from_covariance(np.ascontiguousarray(H[k]), p_bar[k], g_bar[k])
    return R, t
