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

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit

from facerec3d.facemodel import FIDUCIAL_LANDMARK68, load_model
from facerec3d.geometry.ball import bucket


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
    max_points: int = 3000  # scan points used: every k-th of those given, k = ⌊n / max_points⌋ (so between
    #                        max_points and twice that many where more are given; a rap3df-2019 face gives the
    #                        detector's full fits 1,357 in the median, up to ~2,900, all of them used)
    core_radius_mm: float = 60.0  # the fit is scored on the scan points this near the nose tip ...
    inlier_mm: float = 2.5  # ... as the share of them this near the model surface
    robust_mm: float = 0.0  # 0: least squares; else the Cauchy M-estimator's scale (mm, `fit_face_model`)
    lookup_mm: float = 0.0  # 0: each scan point's exact nearest model vertex; h > 0 (a rigid fit only, no modes:
    #                        the mean face never changes): the vertex nearest to the centre of the point's h-mm cell
    #                        in a map over the mean face built once (`_face_map`), at most h·√3 mm farther than
    #                        the nearest, at about 40 % of the cost of the exact map that the rigid fits use by
    #                        default (Fitzgibbon, "Robust registration of 2D and 3D point sets", IVC 2003: ICP
    #                        against a fixed model through a precomputed distance transform). The fit's inlier share
    #                        is still measured exactly

    def __post_init__(self) -> None:
        if self.lookup_mm != 0 and not (self.lookup_mm >= 1.0 and not (self.identity_modes or self.expression_modes)):
            raise ValueError("lookup_mm must be 0, or >= 1 mm for a rigid fit (identity_modes = 0, "
                             "expression_modes = false): a finer map would take gigabytes")


@dataclass(frozen=True)
class _FitBasis:
    mean: np.ndarray  # (n, 3) vertices of the fitted part, mean nose tip at the origin
    basis: np.ndarray  # (n, 3, K) modes
    triangles: np.ndarray  # (T, 3) triangles of the fitted part
    boundary: np.ndarray  # (n,) bool: vertex on the rim of the fitted part or of its holes
    landmarks: dict[str, int]  # fiducial -> row in mean
    normals: np.ndarray  # (n, 3) vertex normals of mean
    grid: _Grid  # nearest-vertex search structure of mean
    modes32: np.ndarray  # (K, 3n) basis, mode by mode, in float32: what shaping the face reads at every iteration
    #                      (half the memory traffic of float64; the vertices move by < 1e-4 mm)


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
    mean = (m.mean[sel] - nose).astype(np.float64)
    basis, tris = np.ascontiguousarray(basis), np.ascontiguousarray(tris, dtype=np.int64)
    grid = _Grid.build(mean, _DistanceField.build(mean))
    modes32 = np.ascontiguousarray(basis.reshape(len(sel) * 3, -1).T, dtype=np.float32)
    return _FitBasis(mean, basis, tris, boundary, fid, _normals(mean, tris), grid, modes32)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals of a triangle mesh (area-weighted face normals)."""
    fn = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]], vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
    corners, weights = triangles.ravel(), np.repeat(fn, 3, axis=0)  # each face normal to its three vertices
    vn = np.stack([np.bincount(corners, weights[:, d], minlength=len(vertices)) for d in range(3)], axis=1)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


# Nearest model vertices, found exactly (the pairs are those of a k-d tree, scipy's cKDTree, whose rebuild on
# every iteration and whose queries dominated the fit) but at a fraction of the cost. The vertices are bucketed in a
# uniform grid; a point's search starts from a vertex near it (its partner in the previous iteration, else the
# vertex nearest to the centre of its cell in a finer distance field over the mean face) and visits only the
# cells that the ball through that vertex reaches. The field's distances also bound the point's distance to the
# surface from below (less `shift`, how far the fitted vertices may have moved from the mean), which drops the
# far points of the coarse fits at once. The mean face's grid and field are built once (`_basis`).
_GRID_MM = 8.0  # search cell size
_GRID_MOST = 4096  # cells along an axis at most (larger cells beyond: a face far off stays a small grid)
_FIELD_MM = 3.0  # distance-field cell size ...
_FIELD_REACH_MM = 25.0  # ... over the mean face and this far around it (past the coarse fit's first cut-off)
_SLACK_MM = 1e-6  # the search's bounds are loosened by this much, far above rounding of coordinates in mm


@dataclass(frozen=True)
class _DistanceField:
    """For each cell centre of a grid over the mean face: the distance to the nearest vertex (capped at the reach)
    and that vertex (-1 beyond the reach)."""

    lo: np.ndarray  # (3,) corner of cell (0, 0, 0)
    dims: np.ndarray  # (3,) cells along x, y, z
    dist: np.ndarray  # (cells,) mm
    near: np.ndarray  # (cells,)

    @staticmethod
    def build(V: np.ndarray) -> _DistanceField:
        return _DistanceField(*_distance_field(V, _FIELD_MM, _FIELD_REACH_MM))


_NO_FIELD = _DistanceField(np.zeros(3), np.zeros(3, np.int64), np.zeros(0), np.zeros(0, np.int64))


@dataclass(frozen=True)
class _Grid:
    """Vertices bucketed by cell: those of cell (a, b, c) are order[start[i]:start[i + 1]], i = (a·ny + b)·nz + c;
    with the distance field of the mean face, whose vertices lie at most `shift` mm from these."""

    lo: np.ndarray  # (3,) corner of cell (0, 0, 0)
    h: float  # cell size (mm): `_GRID_MM`, larger for a grid that would span more than `_GRID_MOST` cells
    dims: np.ndarray  # (3,) cells along x, y, z
    start: np.ndarray  # (cells + 1,)
    order: np.ndarray  # (n,) vertex indices, cell by cell
    pts: np.ndarray  # (n, 3) the vertices in that order
    field: _DistanceField
    shift: float

    @staticmethod
    def build(V: np.ndarray, field: _DistanceField = _NO_FIELD, mean: np.ndarray | None = None) -> _Grid:
        """The grid of vertices V, its `shift` measured from `mean` (their mean positions; None: V is the mean)."""
        lo, h, dims, start, order = bucket(V, 3, _GRID_MM, _GRID_MOST)
        pts, shift = _ordered(V, order, V if mean is None else mean)
        return _Grid(lo, float(h), dims, start, order, pts, field, shift)

    def args(self) -> tuple:
        f = self.field
        return (self.lo, self.h, self.dims, self.start, self.order, self.pts,
                f.lo, _FIELD_MM, f.dims, f.dist, f.near, self.shift)


@njit(cache=True)
def _ordered(V, order, mean):  # pragma: no cover - compiled
    """(V's rows in `order`, the largest distance of a row of V from the same row of `mean`)."""
    pts = np.empty((V.shape[0], 3))
    shift2 = 0.0
    for s in range(V.shape[0]):
        for d in range(3):
            pts[s, d] = V[order[s], d]
        e0, e1, e2 = V[s, 0] - mean[s, 0], V[s, 1] - mean[s, 1], V[s, 2] - mean[s, 2]
        shift2 = max(shift2, e0 * e0 + e1 * e1 + e2 * e2)
    return pts, np.sqrt(shift2)


@njit(cache=True)
def _distance_field(V, h, reach):  # pragma: no cover - compiled
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    for d in range(3):
        lo[d] = V[:, d].min() - reach
        dims[d] = int(np.floor((V[:, d].max() + reach - lo[d]) / h)) + 1
    dist2 = np.full(dims[0] * dims[1] * dims[2], reach * reach)
    near = np.full(dims[0] * dims[1] * dims[2], -1, np.int64)
    for i in range(V.shape[0]):  # each vertex to the centres within reach
        cells, dd = _centres_around(V[i], reach, lo, h, dims)
        for m in range(len(cells)):
            if dd[m] < dist2[cells[m]]:
                dist2[cells[m]] = dd[m]
                near[cells[m]] = i
    return lo, dims, np.sqrt(dist2), near


@njit(cache=True)
def _centres_around(v, r, lo, h, dims):  # pragma: no cover - compiled
    """The cells (flat index) of the grid (corner lo, cell size h, dims cells) whose centres lie in the cube of half
    side r around v, and the squared distance of each centre from v."""
    lo_i = np.empty(3, np.int64)
    hi_i = np.empty(3, np.int64)
    for d in range(3):
        lo_i[d] = max(int(np.ceil((v[d] - r - lo[d]) / h - 0.5)), 0)
        hi_i[d] = min(int(np.floor((v[d] + r - lo[d]) / h - 0.5)), dims[d] - 1)
    n = max(hi_i[0] - lo_i[0] + 1, 0) * max(hi_i[1] - lo_i[1] + 1, 0) * max(hi_i[2] - lo_i[2] + 1, 0)
    cells = np.empty(n, np.int64)
    dist2 = np.empty(n)
    m = 0
    for a in range(lo_i[0], hi_i[0] + 1):
        e0 = lo[0] + (a + 0.5) * h - v[0]
        for b in range(lo_i[1], hi_i[1] + 1):
            e1 = lo[1] + (b + 0.5) * h - v[1]
            for c in range(lo_i[2], hi_i[2] + 1):
                e2 = lo[2] + (c + 0.5) * h - v[2]
                cells[m] = (a * dims[1] + b) * dims[2] + c
                dist2[m] = e0 * e0 + e1 * e1 + e2 * e2
                m += 1
    return cells, dist2


@njit(cache=True, inline="always")
def _nearest(x0, x1, x2, best2, bj, V, lo, h, dims, start, order, pts,
             flo, fh, fdims, fdist, fnear, shift):  # pragma: no cover - compiled
    """Index of the vertex nearest to x among those at squared distance < best2 (else bj)."""
    if bj < 0:  # no vertex to start from: the distance field's, which may also show that none is near enough
        g0 = int(np.floor((x0 - flo[0]) / fh))
        g1 = int(np.floor((x1 - flo[1]) / fh))
        g2 = int(np.floor((x2 - flo[2]) / fh))
        if 0 <= g0 < fdims[0] and 0 <= g1 < fdims[1] and 0 <= g2 < fdims[2]:
            g = (g0 * fdims[1] + g1) * fdims[2] + g2
            e0, e1, e2 = x0 - flo[0] - (g0 + 0.5) * fh, x1 - flo[1] - (g1 + 0.5) * fh, x2 - flo[2] - (g2 + 0.5) * fh
            b = fdist[g] - np.sqrt(e0 * e0 + e1 * e1 + e2 * e2) - shift - _SLACK_MM  # no vertex is nearer
            if b > 0.0 and b * b >= best2:
                return bj
            j = fnear[g]
            if j >= 0:
                e0, e1, e2 = x0 - V[j, 0], x1 - V[j, 1], x2 - V[j, 2]
                dd = e0 * e0 + e1 * e1 + e2 * e2
                if dd < best2:
                    best2, bj = dd, j
    f0, f1, f2 = (x0 - lo[0]) / h, (x1 - lo[1]) / h, (x2 - lo[2]) / h
    if not (best2 < np.inf and abs(f0) < 1e12 and abs(f1) < 1e12 and abs(f2) < 1e12):
        for s in range(pts.shape[0]):  # no bound, far off or not a number: every vertex
            e0, e1, e2 = x0 - pts[s, 0], x1 - pts[s, 1], x2 - pts[s, 2]
            dd = e0 * e0 + e1 * e1 + e2 * e2
            if dd < best2:
                best2, bj = dd, order[s]
        return bj
    # the cells that the ball of squared radius best2 around x reaches, with pruning by their distance from x
    rr = np.sqrt(best2) + _SLACK_MM
    a_lo, a_hi = max(int(np.floor(f0 - rr / h)), 0), min(int(np.floor(f0 + rr / h)), dims[0] - 1)
    b_lo, b_hi = max(int(np.floor(f1 - rr / h)), 0), min(int(np.floor(f1 + rr / h)), dims[1] - 1)
    c_lo, c_hi = max(int(np.floor(f2 - rr / h)), 0), min(int(np.floor(f2 + rr / h)), dims[2] - 1)
    for a in range(a_lo, a_hi + 1):
        da = max(max(lo[0] + a * h - x0, x0 - lo[0] - (a + 1) * h) - _SLACK_MM, 0.0)
        da2 = da * da
        if da2 >= best2:
            continue
        for bb in range(b_lo, b_hi + 1):
            db = max(max(lo[1] + bb * h - x1, x1 - lo[1] - (bb + 1) * h) - _SLACK_MM, 0.0)
            dab2 = da2 + db * db
            if dab2 >= best2:
                continue
            base = (a * dims[1] + bb) * dims[2]
            for c in range(c_lo, c_hi + 1):
                s0, s1 = start[base + c], start[base + c + 1]
                if s0 == s1:
                    continue
                dc = max(max(lo[2] + c * h - x2, x2 - lo[2] - (c + 1) * h) - _SLACK_MM, 0.0)
                if dab2 + dc * dc >= best2:
                    continue
                for s in range(s0, s1):
                    e0, e1, e2 = x0 - pts[s, 0], x1 - pts[s, 1], x2 - pts[s, 2]
                    dd = e0 * e0 + e1 * e1 + e2 * e2
                    if dd < best2:
                        best2, bj = dd, order[s]
    return bj


@njit(cache=True, inline="always")
def _start(x0, x1, x2, cutoff2, j, V):  # pragma: no cover - compiled
    """(squared distance, index) to start a search from: vertex j (the last partner) if nearer than the cut-off."""
    if j >= 0:
        e0, e1, e2 = x0 - V[j, 0], x1 - V[j, 1], x2 - V[j, 2]
        dd = e0 * e0 + e1 * e1 + e2 * e2
        if dd < cutoff2:
            return dd, j
    return cutoff2, -1


@njit(cache=True)
def _query(P, cutoff, prev, V, face_map, lo, h, dims, start, order, pts,
           flo, fh, fdims, fdist, fnear, shift):  # pragma: no cover - compiled
    """Index of the vertex nearest to each point, -1 where none is nearer than `cutoff`; prev: first candidates;
    `face_map`: a `_face_map` of V (the mean face: rigid fits only) asked first, or `_NO_MAP`."""
    mlo, mh, mdims, mstart, mitems, mreach2, mexact = face_map
    out = np.empty(P.shape[0], np.int64)
    cutoff2 = cutoff * cutoff
    for i in range(P.shape[0]):
        x0, x1, x2 = P[i, 0], P[i, 1], P[i, 2]
        j = _mapped(x0, x1, x2, cutoff2, V, mlo, mh, mdims, mstart, mitems, mreach2, mexact) if mh > 0 else -2
        if j == -2:  # no map, or it cannot tell: the grid search
            best2, bj = _start(x0, x1, x2, cutoff2, prev[i], V)
            j = _nearest(x0, x1, x2, best2, bj, V, lo, h, dims, start, order, pts, flo, fh, fdims, fdist, fnear, shift)
        out[i] = j
    return out


@njit(cache=True)
def _linearise(points, R, t, cutoff, prev, V, normals, boundary, basis, face_map, lo, h, dims, start, order, pts,
               flo, fh, fdims, fdist, fnear, shift):  # pragma: no cover - compiled
    """One linearised point-to-plane step: each scan point, moved by x -> R x + t, paired with its nearest
    model vertex nearer than `cutoff` and not on the rim; (J, r) of the pairs. prev: the last partners (updated).
    `face_map`: a `_face_map` of V (rigid fits of the mean face only; `_NO_MAP` for none): an exact one gives the
    same pairs faster, an approximate one (`lookup_mm`) the vertex its cell names instead of the exact nearest."""
    m, K = points.shape[0], basis.shape[2]
    X = np.empty((m, 3))
    for i in range(m):
        for d in range(3):
            X[i, d] = points[i, 0] * R[d, 0] + points[i, 1] * R[d, 1] + points[i, 2] * R[d, 2] + t[d]
    prev[:] = _query(X, cutoff, prev, V, face_map, lo, h, dims, start, order, pts, flo, fh, fdims, fdist, fnear, shift)
    J = np.empty((m, 6 + K))
    r = np.empty(m)
    count = 0
    for i in range(m):
        j = prev[i]
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        if j < 0 or boundary[j]:
            continue
        n0, n1, n2 = normals[j, 0], normals[j, 1], normals[j, 2]
        r[count] = n0 * (x0 - V[j, 0]) + n1 * (x1 - V[j, 1]) + n2 * (x2 - V[j, 2])
        J[count, 0] = x1 * n2 - x2 * n1  # x × n: rotation
        J[count, 1] = x2 * n0 - x0 * n2
        J[count, 2] = x0 * n1 - x1 * n0
        J[count, 3] = n0  # translation
        J[count, 4] = n1
        J[count, 5] = n2
        for k in range(K):  # the modes, moving the vertex
            J[count, 6 + k] = -(n0 * basis[j, 0, k] + n1 * basis[j, 1, k] + n2 * basis[j, 2, k])
        count += 1
    return J[:count], r[:count]


@njit(cache=True)
def _normals(V, tris):  # pragma: no cover - compiled
    """vertex_normals, compiled: the same sums in the same order."""
    vn = np.zeros((V.shape[0], 3))
    for f in range(tris.shape[0]):
        a, b, c = tris[f, 0], tris[f, 1], tris[f, 2]
        e0, e1, e2 = V[b, 0] - V[a, 0], V[b, 1] - V[a, 1], V[b, 2] - V[a, 2]
        g0, g1, g2 = V[c, 0] - V[a, 0], V[c, 1] - V[a, 1], V[c, 2] - V[a, 2]
        m0, m1, m2 = e1 * g2 - e2 * g1, e2 * g0 - e0 * g2, e0 * g1 - e1 * g0
        for v in (a, b, c):
            vn[v, 0] += m0
            vn[v, 1] += m1
            vn[v, 2] += m2
    for v in range(V.shape[0]):
        s = max(np.sqrt(vn[v, 0] * vn[v, 0] + vn[v, 1] * vn[v, 1] + vn[v, 2] * vn[v, 2]), 1e-12)
        vn[v, 0] /= s
        vn[v, 1] /= s
        vn[v, 2] /= s
    return vn


@njit(cache=True)
def _rotvec_matrix(w):  # pragma: no cover - compiled
    """The rotation matrix of rotation vector w (via the unit quaternion, as scipy's Rotation.from_rotvec)."""
    angle = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    scale = 0.5 - angle**2 / 48 + angle**4 / 3840 if angle <= 1e-3 else np.sin(angle / 2) / angle
    x, y, z, q = scale * w[0], scale * w[1], scale * w[2], np.cos(angle / 2)
    return np.array([[x * x - y * y - z * z + q * q, 2 * (x * y - z * q), 2 * (x * z + y * q)],
                     [2 * (x * y + z * q), -x * x + y * y - z * z + q * q, 2 * (y * z - x * q)],
                     [2 * (x * z - y * q), 2 * (y * z + x * q), -x * x - y * y + z * z + q * q]])


@njit(cache=True)
def _rigid_step(J, r, R, t):  # pragma: no cover - compiled
    """The pose after one linearised step without modes: x = (JᵀJ)⁻¹(−Jᵀr) (the normal equations, 6 × 6, summed
    here: for a rigid fit NumPy's call overheads cost more than the sums), then the pose moved by it (`_moved`)."""
    A = np.zeros((6, 6))
    b = np.zeros(6)
    for i in range(r.shape[0]):
        for a in range(6):
            b[a] -= J[i, a] * r[i]
            for c in range(a, 6):
                A[a, c] += J[i, a] * J[i, c]
    for a in range(6):
        for c in range(a):
            A[a, c] = A[c, a]
    return _moved(np.linalg.solve(A, b), R, t)


# The rigid fits pair scan points with the *mean* face, which never moves: a map over it, built once per process,
# answers most of their queries from one cell (the distance transform of a fixed model; Fitzgibbon, "Robust
# registration of 2D and 3D point sets", IVC 2003). Exact (the default): each cell of `_MAP_MM` lists every vertex
# that can be the nearest to some point of the cell (those within d* + the cell's diagonal of its centre, d* the
# centre's nearest-vertex distance), sorted by distance from the centre, so a query reads them in order until no
# later one can be nearer (its distance from the centre less the point's own distance from the centre, at most half
# the diagonal, bounds its distance from the point below): the nearest vertex the grid search finds, at ~45 % of
# its cost (the same pairs and fits, checked by tests/test_preprocess.py; the same faces on 568 frames and scans).
# Cells farther than the fits' largest cut-off from every vertex list none (no pair); the exact search takes over
# for a cut-off beyond it (the inlier share's). Approximate (`lookup_mm` = h > 0):
# each h-mm cell names only the vertex nearest to its centre.
_MAP_MM = 4.0  # exact map's cell: 2.2 million listed vertices (18 MB) for the coarse fit's 20 mm reach, built in
#                ~0.2 s; 2 or 3 mm: 47 or 27 MB and no faster (memory reads, not distances, dominate a query)
_MAP_REACH_MM = 25.0  # a map reaches at most this far from the mean face (a fit set to start farther gets the grid
#                       search beyond it): memory stays bounded whatever the settings (the exact map's lists grow with
#                       the square of the reach, the approximate one's cells with its cube)


@lru_cache(maxsize=4)
def _face_map(identity_modes: int, expression_modes: bool, radius_mm: float, h: float, reach: float,
              exact: bool) -> tuple:
    """The map over the mean face of `_basis(...)` (see above): (corner, cell size h, cells along x, y, z, list
    starts per cell, the listed (distance from the cell centre, vertex) pairs, reach², exact); approximate: one
    pair per cell, no starts."""
    V = _basis(identity_modes, expression_modes, radius_mm).mean
    if exact:
        lo, dims, start, items = _candidate_lists(V, h, reach)
    else:  # the nearest vertex of each centre within the reach, cell by cell (-1: none)
        lo, dims, dist, near = _distance_field(V, h, reach)
        start, items = np.zeros(1, np.int32), np.stack([dist, near], axis=1).astype(np.float32)
    return lo, h, dims, start, items, reach * reach, exact


_NO_MAP = (np.zeros(3), 0.0, np.zeros(3, np.int64), np.zeros(1, np.int32), np.zeros((0, 2), np.float32), 0.0, False)


@njit(cache=True)
def _candidate_lists(V, h, reach):  # pragma: no cover - compiled
    """The exact map's lists: for each cell whose centre lies within reach + half a diagonal of a vertex, the
    vertices within d* + a diagonal of its centre, by distance from it."""
    hd = h * np.sqrt(3.0) / 2
    lo, dims, dist, near = _distance_field(V, h, reach + hd)
    cells = dims[0] * dims[1] * dims[2]
    radius = np.where(near >= 0, dist + 2 * hd + _SLACK_MM, -1.0)  # a vertex beyond it is never the nearest
    start = np.zeros(cells + 1, np.int64)
    far = radius.max()  # each vertex to the cells within the largest list's radius
    items = np.empty((0, 2), np.float32)
    fill = np.zeros(0, np.int64)
    for count_only in (True, False):
        if not count_only:
            for k in range(cells):
                start[k + 1] += start[k]
            items = np.empty((start[-1], 2), np.float32)
            fill = start[:-1].copy()
        for i in range(V.shape[0]):
            cells_i, dd = _centres_around(V[i], far, lo, h, dims)
            for m in range(len(cells_i)):
                k = cells_i[m]
                if radius[k] >= 0.0 and dd[m] <= radius[k] * radius[k]:
                    if count_only:
                        start[k + 1] += 1
                    else:
                        items[fill[k], 0] = np.sqrt(dd[m])
                        items[fill[k], 1] = i
                        fill[k] += 1
    for k in range(cells):
        s0, s1 = start[k], start[k + 1]
        if s1 - s0 > 1:
            items[s0:s1] = items[s0:s1][np.argsort(items[s0:s1, 0])]
    return lo, dims, start.astype(np.int32), items


@njit(cache=True, inline="always")
def _mapped(x0, x1, x2, cutoff2, V, mlo, mh, mdims, mstart, mitems, mreach2, mexact):  # pragma: no cover - compiled
    """The vertex nearest to x nearer than the cut-off (-1: none) from a `_face_map`; -2 where it cannot tell (its
    cell lists none and the cut-off reaches past the map's reach: the grid search answers)."""
    f0, f1, f2 = (x0 - mlo[0]) / mh, (x1 - mlo[1]) / mh, (x2 - mlo[2]) / mh
    unknown = -2 if cutoff2 > mreach2 else -1
    if not (0.0 <= f0 < mdims[0] and 0.0 <= f1 < mdims[1] and 0.0 <= f2 < mdims[2]):
        return unknown  # farther than the reach from every vertex
    i0, i1, i2 = int(f0), int(f1), int(f2)
    k = (i0 * mdims[1] + i1) * mdims[2] + i2
    s0, s1 = (mstart[k], mstart[k + 1]) if mexact else (k, k + int(mitems[k, 1] >= 0))  # approximate: one per cell
    if s0 == s1:
        return unknown
    best2, bj = cutoff2, -1
    e0, e1, e2 = (f0 - i0 - 0.5) * mh, (f1 - i1 - 0.5) * mh, (f2 - i2 - 0.5) * mh
    off = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2) + 1e-4  # x from its cell's centre (at most half the diagonal),
    #                                                     loosened past rounding (of the list's float32 too)
    for s in range(s0, s1):
        low = mitems[s, 0] - off  # no vertex listed from here on is nearer to x than this
        if low > 0.0 and low * low >= best2:
            break
        j = int(mitems[s, 1])
        e0, e1, e2 = x0 - V[j, 0], x1 - V[j, 1], x2 - V[j, 2]
        dd = e0 * e0 + e1 * e1 + e2 * e2
        if dd < best2:
            best2, bj = dd, j
    return bj


@njit(cache=True)
def _rigid_fit(points, R, t, cutoffs, robust, prev, V, normals, boundary, basis, face_map, *grid):  # pragma: no cover
    """`fit_face_model`'s iterations without modes: (R, t, whether it stopped) after one `_rigid_step` per cut-off
    (stopping when fewer than 50 pairs are left; rows weighted as its IRLS does when `robust` > 0), as its Python
    loop does them, without a call per iteration; pairs through `face_map` (`_linearise`)."""
    for cutoff in cutoffs:
        J, r = _linearise(points, R, t, cutoff, prev, V, normals, boundary, basis, face_map, *grid)
        if r.shape[0] < 50:
            return R, t, True
        if robust > 0:
            for i in range(r.shape[0]):
                w = np.sqrt(1.0 / (1.0 + (r[i] / robust) ** 2))
                J[i, :] *= w
                r[i] *= w
        R, t = _rigid_step(J, r, R, t)
    return R, t, False


@njit(cache=True)
def _moved(x, R, t):  # pragma: no cover - compiled
    """The pose (R, t) after a linearised step x (rotation vector x[:3], translation x[3:6]): R ← dR R,
    t ← dR t + x[3:6]."""
    dR = _rotvec_matrix(x[:3])
    return dR @ R, dR @ t + x[3:6]


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


def _shaped(fb: _FitBasis, c: np.ndarray) -> np.ndarray:
    """(n, 3) the fitted part's vertices with mode coefficients c."""
    return fb.mean + (c.astype(np.float32) @ fb.modes32).reshape(-1, 3)


def _shaped_grid(fb: _FitBasis, V: np.ndarray) -> _Grid:
    """The nearest-vertex search structure of shaped vertices V (the mean face's distance field, loosened by how
    far V moved from the mean)."""
    return _Grid.build(V, fb.grid.field, mean=fb.mean)


def model_nose_tip(coefficients: np.ndarray, config: ModelFitConfig = ModelFitConfig()) -> np.ndarray:
    """(3,) the nose tip of the model with these mode coefficients, in `fit_face_model`'s frame (the mean face's
    nose tip at the origin)."""
    fb = _fit_basis(config)
    K = fb.basis.shape[2]
    c = np.asarray(coefficients, dtype=np.float64)[:K]
    return _shaped(fb, np.concatenate([c, np.zeros(K - len(c))]))[fb.landmarks["nose_tip"]]


def fit_face_model(points: np.ndarray, R: np.ndarray, t: np.ndarray, config: ModelFitConfig = ModelFitConfig(),
                   start: np.ndarray | None = None, robust_mm: float | None = None) -> ModelFit:
    """Fit pose, identity and expression of the morphable model to scan points (mm), from x -> R x + t.

    Each iteration pairs every scan point with its closest model vertex
    (pairs farther than a shrinking cut-off, or on the model's rim, are
    dropped: the neck, ears and hair have no partner), then solves one
    linearised point-to-plane least-squares problem (Chen & Medioni) for a
    small rigid motion and the mode coefficients together, with a Gaussian
    prior of weight λ on the coefficients. Pairing from the scan side means
    self-occluded parts of the face do not pull the fit. `start`: the mode
    coefficients to start from (None: the mean face). `robust_mm`: None
    for the config's (`ModelFitConfig.robust_mm`), 0 for least squares, else
    each pair is weighted 1 / (1 + (r / robust_mm)²)
    (the Cauchy M-estimator by iteratively reweighted least squares; Zhang,
    "Parameter estimation techniques", IVC 1997), so points the model
    cannot explain, such as an occluder lying near the face, pull it less.
    """
    return ModelFitting(points, R, t, config, start, robust_mm).run().result()


class ModelFitting:
    """`fit_face_model` run a few iterations at a time: `run(n)` does the next n iterations of the cut-off schedule
    (all that are left without n), `result()` is the fit so far. A fit looked at part of the way and then run to
    the end is the fit run to the end at once, to the bit (the detector ranks its finalists part of the way and
    finishes the best: `DetectConfig.screen_iterations`). A rigid fit (no modes) runs the iterations of each call in
    one compiled call."""

    def __init__(self, points: np.ndarray, R: np.ndarray, t: np.ndarray, config: ModelFitConfig = ModelFitConfig(),
                 start: np.ndarray | None = None, robust_mm: float | None = None):
        fb = self.fb = _fit_basis(config)
        self.config = config
        self.robust_mm = (config.robust_mm if robust_mm is None else robust_mm) or None
        self.points = np.ascontiguousarray(points[:: max(1, len(points) // config.max_points)], dtype=np.float64)
        K = fb.basis.shape[2]
        self.c = np.zeros(K)
        if start is not None:  # those given, zeros after them
            given = np.asarray(start, dtype=np.float64)[:K]
            self.c[: len(given)] = given
        self.R, self.t = np.asarray(R, float), np.asarray(t, float)
        n = config.iterations
        self.V, self.normals, self.grid = fb.mean, fb.normals, fb.grid
        if self.c.any():
            self.V = _shaped(fb, self.c)
            self.normals, self.grid = _normals(self.V, fb.triangles), _shaped_grid(fb, self.V)
        self.prev = np.full(len(self.points), -1, dtype=np.int64)  # each point's last partner, where searches start
        self.cutoffs = [config.start_distance_mm + (config.end_distance_mm - config.start_distance_mm) * i
                        / max(n - 1, 1) for i in range(n)]  # the shrinking cut-off of each iteration
        self.done = 0  # iterations run (all of them once the fit stopped for want of pairs)
        self.exact = _NO_MAP
        if K:  # the prior's weights: none on the pose, λ on each coefficient
            self.reg = np.zeros(6 + K)
            self.reg[6:] = config.regularisation
            self.prior = np.diag(self.reg)
        else:  # a rigid fit of the mean face pairs through its map
            key = (config.identity_modes, config.expression_modes, config.radius_mm)
            reach = min(max(config.start_distance_mm, config.end_distance_mm), _MAP_REACH_MM)
            self.exact = _face_map(*key, _MAP_MM, reach, True)
            self.pairs = _face_map(*key, config.lookup_mm, reach, False) if config.lookup_mm > 0 else self.exact

    def run(self, iterations: int | None = None) -> ModelFitting:
        """The next `iterations` of the schedule (those left when None; none once the fit stopped); returns self."""
        fb, points, prev = self.fb, self.points, self.prev
        todo = self.cutoffs[self.done:] if iterations is None else self.cutoffs[self.done:self.done + iterations]
        if not self.c.size:  # a rigid fit: these iterations in one compiled call
            if todo:
                self.R, self.t, stopped = _rigid_fit(points, self.R, self.t, np.array(todo, dtype=np.float64),
                                                     self.robust_mm or 0.0, prev, self.V, self.normals, fb.boundary,
                                                     fb.basis, self.pairs, *self.grid.args())
                self.done = len(self.cutoffs) if stopped else self.done + len(todo)
            return self
        for cutoff in todo:
            J, r = _linearise(points, self.R, self.t, cutoff, prev, self.V, self.normals, fb.boundary, fb.basis,
                              _NO_MAP, *self.grid.args())
            if len(r) < 50:
                self.done = len(self.cutoffs)
                break
            self.done += 1
            if self.robust_mm is not None:  # IRLS: rows scaled by the square root of the Cauchy weight
                w = np.sqrt(1.0 / (1.0 + (r / self.robust_mm) ** 2))
                J, r = J * w[:, None], r * w
            x = np.linalg.solve(J.T @ J + self.prior, -(J.T @ r) - self.reg * np.concatenate([np.zeros(6), self.c]))
            self.R, self.t = _moved(x, self.R, self.t)
            self.c = self.c + x[6:]
            self.V = _shaped(fb, self.c)
            self.normals, self.grid = _normals(self.V, fb.triangles), _shaped_grid(fb, self.V)
        return self

    def result(self) -> ModelFit:
        """The fit as it stands: pose with the nose tip at the origin, fiducials, and its RMS and inlier share over
        the scan points within `core_radius_mm` of the nose tip."""
        fb, R, t, V, normals = self.fb, self.R, self.t, self.V, self.normals
        nose = V[fb.landmarks["nose_tip"]]
        landmarks = {name: R.T @ (V[k] - t) for name, k in fb.landmarks.items()}
        p = self.points @ R.T + (t - nose)
        core = np.linalg.norm(p, axis=1) <= self.config.core_radius_mm
        q = p[core] + nose
        j = _query(q, np.inf, self.prev[core], V, self.exact, *self.grid.args())
        dist = np.abs(np.einsum("ij,ij->i", normals[j], q - V[j]))
        good = dist <= self.config.inlier_mm
        rms = float(np.sqrt(np.mean(dist[good] ** 2))) if good.any() else float("inf")
        return ModelFit(R, t - nose, landmarks, rms, float(good.mean()) if len(good) else 0.0, self.c, V - nose,
                        normals.copy() if normals is fb.normals else normals)


def screen_fits(fitting: list[ModelFitting], iterations: int, keep: int,
                best_first: Callable[[list[ModelFit]], Sequence[int]]) -> list[int]:
    """Which of several fits to run to the end (indices, in their given order): each run `iterations` iterations
    first and ranked by `best_first` (their fits so far -> indices, best first), the `keep` best; every one when
    screening is off (`iterations` 0 or the whole schedule, or `keep` no fewer than the fits). A kept fit run on
    to the end is that fit run to the end at once (`ModelFitting`), so screening only decides which are finished."""
    if not (fitting and 0 < iterations < fitting[0].config.iterations and keep < len(fitting)):
        return list(range(len(fitting)))
    return sorted(best_first([g.run(iterations).result() for g in fitting])[:keep])
