"""The ICP loop (chapter §8.6.1) and the ICP matcher: align a probe to a gallery face; the score is −MSE: by
default the truncated point-to-plane one at the final transform (`ICPConfig.plane_cap_mm`), or the kept pairs'.

Each iteration, all inside one Numba call per probe–gallery pair (the steps below, compiled inline):
  closest points → pair filters → error → stop? → transform.
  * coarse phase: the first `coarse_points` of the randomly ordered probe,
    with the distance threshold falling geometrically from `distance_start`
    to `distance_end` (× gallery resolution) over `shrink_iterations`
    iterations and then held, until the MSE changes by less than
    `tolerance` (or only `fine_iterations` of `max_iterations` are left);
  * fine phase: the first `fine_points`, at the final threshold, for at most
    `fine_iterations` more updates, stopping early when the MSE changes by
    less than `tolerance`. The MSE and pair count returned are those of the
    exact closest points at the returned transform.
Pairs are kept when (1) the distance is within the threshold, (2) the angle
between the probe normal (computed once, in `prepare`) and the gallery normal
is at most `max_normal_angle`, (3) the gallery point is not a boundary point,
(4) with colours on both sides, the RGB difference is at most
`max_color_difference`. Each update is the SVD solution (Arun et al.,
reflection fixed, t = ḡ − R p̄; point-to-point) or the linearised
point-to-plane least squares (Chen & Medioni; chapter 6). Closest points come
from the gallery's `GalleryIndex` (matching.icp.index).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numba import njit

from facerec3d.geometry.normals import estimate_normals
from facerec3d.geometry.transforms import rigid_from_covariance
from facerec3d.matching.base import Matcher, Template, check_face, check_templates
from facerec3d.matching.icp.config import ICPConfig
from facerec3d.matching.icp.index import GalleryIndex, closest_point, nearest_within
from facerec3d.scan import MIRRORED, FaceScan

PROBE_METHOD = "icp-probe"  # the method name of a prepared probe saved as a template (`ProbeData.save`)


class ICPResult(NamedTuple):
    """The gallery-frame transform x -> R x + t of the probe, and the fit at it."""

    R: np.ndarray  # (3, 3) rotation
    t: np.ndarray  # (3,) mm
    mse: float  # mm²: what the score is −1 × (inf: no match): the mean squared distance of the kept exact
    #             correspondences, or the capped one of `score_cap` / `plane_cap_mm`
    n_correspondences: int  # kept correspondences m (of the fine probe points)
    iterations: int  # transform updates made
    converged: bool  # the MSE change fell below the tolerance


class ProbeData(NamedTuple):
    """A probe prepared for ICP (what `ICPMatcher.prepare` returns): points in random order (the first ones are
    the coarse subset)."""

    points: np.ndarray  # (n, 3) float64 mm
    normals: np.ndarray  # (n, 3) float64 unit, or (0, 3) when the normal filter is off
    colors: np.ndarray  # (n, 3) uint8, or (0, 3)

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray | None = None, colors: np.ndarray | None = None,
              config: ICPConfig = ICPConfig(), *, grid: np.ndarray | None = None,
              grid_shape: tuple[int, int] | None = None) -> "ProbeData":
        """Shuffle (seeded) and keep the fine_points needed; normals, when needed and absent, estimated at the kept
        points from their neighbours among all points."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        keep = np.random.default_rng(config.seed).permutation(len(pts))
        if config.fine_points:
            keep = keep[: config.fine_points]
        if normals is not None:
            nrm = np.asarray(normals, dtype=np.float64)[keep]
        elif config.max_normal_angle is not None:
            nrm = estimate_normals(pts, config.normal_neighbours, grid=grid, grid_shape=grid_shape, at=keep)
        else:
            nrm = np.zeros((0, 3))
        col = np.zeros((0, 3), np.uint8) if colors is None else np.asarray(colors, dtype=np.uint8)[keep]
        return cls(np.ascontiguousarray(pts[keep]), np.ascontiguousarray(nrm), np.ascontiguousarray(col))

    def save(self, path, subject: str | None = None, scan_id: str | None = None) -> None:
        """Write to an .npz file as a template of method "icp-probe" (read back by `from_template`)."""
        Template(subject, scan_id, PROBE_METHOD, dict(self._asdict()), {}).save(path)

    @classmethod
    def from_template(cls, template: Template) -> "ProbeData":
        """The probe saved by `save` (and read with Template.load)."""
        if template.method != PROBE_METHOD:
            raise TypeError(f"not a prepared ICP probe: a template of method {template.method!r}")
        return cls(**template.arrays)


class _Params(NamedTuple):
    """ICPConfig as the compiled loop sees it."""

    point_to_plane: bool
    max_iterations: int
    tolerance: float
    coarse_points: int
    fine_points: int
    fine_iterations: int
    distance_start: float
    distance_end: float
    shrink_iterations: int
    cos_max_angle: float  # −2: normal filter off
    max_color2: float  # −1: colour filter off
    drop_boundary: bool
    min_overlap: float
    score_cap: float  # × res; 0: off
    plane_cap: float  # mm; 0: off


def _params(config: ICPConfig) -> _Params:
    return _Params(
        config.variant == "point-to-plane", int(config.max_iterations), float(config.tolerance),
        int(config.coarse_points), int(config.fine_points), int(config.fine_iterations),
        float(config.distance_start), float(config.distance_end), int(config.shrink_iterations),
        -2.0 if config.max_normal_angle is None else math.cos(math.radians(config.max_normal_angle)),
        -1.0 if config.max_color_difference is None else float(config.max_color_difference) ** 2,
        bool(config.drop_boundary), float(config.min_overlap), float(config.score_cap or 0.0),
        float(config.plane_cap_mm),
    )


def icp(probe_points: np.ndarray, gallery: GalleryIndex, config: ICPConfig = ICPConfig(),
        init: tuple[np.ndarray, np.ndarray] | None = None, *, probe_normals: np.ndarray | None = None,
        probe_colors: np.ndarray | None = None) -> ICPResult:
    """Align probe points (N, 3) mm to an enrolled gallery face; init = (R, t) to start from (default identity).

    Probe normals are estimated (k-NN PCA) when the normal filter is on and none are given.
    """
    probe = ProbeData.build(probe_points, probe_normals, probe_colors, config)
    return _align(probe, gallery, _params(config), init)


def _align(probe: ProbeData, gallery: GalleryIndex, params: _Params,
           init: tuple[np.ndarray, np.ndarray] | None = None) -> ICPResult:
    R0 = np.eye(3) if init is None else np.asarray(init[0], dtype=np.float64).reshape(3, 3)
    t0 = np.zeros(3) if init is None else np.asarray(init[1], dtype=np.float64).reshape(3)
    R, t, mse, m, k, converged, pairs = _icp_loop(probe, gallery, params, np.ascontiguousarray(R0), t0)
    return ICPResult(R, t, _score_mse(probe, gallery, params, R, t, mse, pairs), m, k, converged)


def _score_mse(probe: ProbeData, gallery: GalleryIndex, params: _Params, R: np.ndarray, t: np.ndarray,
               mse: float, pairs: np.ndarray) -> float:
    """The MSE the score is made of: the loop's (kept pairs), or with `score_cap` the capped one (`_capped_mse`), or
    with `plane_cap_mm` the capped point-to-plane one (`_plane_capped_mse`, on the loop's last closest points
    `pairs`)."""
    if not (params.score_cap or params.plane_cap) or not np.isfinite(mse):
        return mse
    n = min(params.fine_points, len(probe.points)) if params.fine_points else len(probe.points)
    if params.plane_cap:
        reach = params.distance_end * gallery.resolution  # the final pair threshold
        return _plane_capped_mse(probe.points, n, R, t, gallery, pairs, min(params.plane_cap, reach))
    return _capped_mse(probe.points, n, R, t, gallery, params.score_cap * gallery.resolution)


class ICPMatcher(Matcher[ProbeData]):
    """ICP identification and verification (§8.6.1): score = −MSE (mm²; `ICPConfig.plane_cap_mm`), tiebreak =
    correspondence count."""

    name = "icp"
    config_class = ICPConfig
    added_options = {"plane_cap_mm": 0.0}  # galleries stored before the plane-capped score (December 2026)

    def __init__(self, config: ICPConfig = ICPConfig()):
        self.config = config
        self._params = _params(config)

    def enroll(self, scan: FaceScan) -> Template:
        check_face(scan)
        return GalleryIndex.from_scan(scan, self.config).to_template(scan.meta.subject, scan.meta.scan_id)

    def prepare(self, scan: FaceScan) -> ProbeData:
        """The probe's random subset with normals (of what was seen, unless `probe_mirrored`)."""
        check_face(scan)
        if not self.config.probe_mirrored and scan.provenance is not None:
            scan = scan.subset(scan.provenance != MIRRORED)
        return ProbeData.build(scan.points, scan.normals, scan.colors, self.config, grid=scan.grid,
                               grid_shape=scan.grid_shape)

    def _probe(self, probe: FaceScan | ProbeData | Template, templates: Sequence[Template] = ()) -> ProbeData:
        """A probe as `prepare` makes it, from a scan, a prepared probe, or one saved and read back (Template)."""
        if isinstance(probe, Template):
            check_templates(self, templates)
            return ProbeData.from_template(probe)
        return super()._probe(probe, templates)

    @staticmethod
    def gallery_points(template: Template) -> np.ndarray:
        """(N, 3) float32 mm: the points of an enrolled face."""
        return GalleryIndex.from_template(template).points

    def align(self, probe: FaceScan | ProbeData | Template, template: Template,
              init: tuple[np.ndarray, np.ndarray] | None = None) -> ICPResult:
        """The full ICP result of a probe against a gallery template."""
        return _align(self._probe(probe, [template]), GalleryIndex.from_template(template), self._params, init)

    def score(self, probe: FaceScan | ProbeData | Template, template: Template) -> float:
        return -self.align(probe, template).mse

    def scores(self, probe: FaceScan | ProbeData | Template,
               templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray]:
        """(−MSE, correspondence count) against each template; one compiled call per template."""
        return self.data_scores(self._probe(probe, templates), [GalleryIndex.from_template(t) for t in templates])

    def data_scores(self, probe: ProbeData, galleries: Sequence[GalleryIndex]) -> tuple[np.ndarray, np.ndarray]:
        """(−MSE mm², correspondence count) of probe data (e.g. one region of a face) against gallery indices."""
        s = np.empty(len(galleries))
        m = np.empty(len(galleries), dtype=np.int64)
        eye, zero = np.eye(3), np.zeros(3)
        for i, gallery in enumerate(galleries):
            R, t, mse, m[i], _, _, pairs = _icp_loop(probe, gallery, self._params, eye, zero)
            s[i] = -_score_mse(probe, gallery, self._params, R, t, mse, pairs)
        return s, m


@njit(cache=True)
def _capped_mse(points, n, R, t, g, cap):  # pragma: no cover - compiled
    """Mean over the first n probe points, moved by (R, t), of min(d, cap)², d the distance to the closest gallery
    point (exact within cap)."""
    total = 0.0
    for i in range(n):
        x, y, z = _moved(R, t, points, i)
        total += nearest_within(x, y, z, cap, g)[1]  # cap² when none is nearer
    return total / n


@njit(cache=True)
def _plane_capped_mse(points, n, R, t, g, pairs, cap):  # pragma: no cover - compiled
    """Mean over the first n probe points, moved by (R, t), of min(e, cap)², e = |n_j · (x − g_j)| the distance to
    the tangent plane of the closest gallery point j = pairs[i] (the loop's last exact closest points within the
    final threshold, at this transform; cap when there is none)."""
    total = 0.0
    for i in range(n):
        x, y, z = _moved(R, t, points, i)
        j = pairs[i]
        e = cap
        if j >= 0:
            n0, n1, n2 = g.normals[j, 0] / 127.0, g.normals[j, 1] / 127.0, g.normals[j, 2] / 127.0
            norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if norm > 0.0:
                e = min(abs((x - g.points[j, 0]) * n0 + (y - g.points[j, 1]) * n1 + (z - g.points[j, 2]) * n2) / norm,
                        cap)
        total += e * e
    return total / n


# --------------------------------------------------------------------------- the steps of one iteration
# Small compiled functions, inlined into the loop (numba inline="always"), each one formula of §8.6.1.
_UPDATE, _FINE, _STOP = 0, 1, 2  # what `_next_step` decides


@njit(cache=True, inline="always")
def _threshold(prm, resolution, k, fine):  # pragma: no cover - compiled
    """Pair distance threshold (mm) at update k (§8.6.1: a multiple of the resolution, shrinking):
    d_k = res · d_start · (d_end / d_start)^min(k / K, 1) over K = shrink_iterations, then res · d_end."""
    if fine or prm.shrink_iterations <= 0:
        return prm.distance_end * resolution
    f = min(k, prm.shrink_iterations) / prm.shrink_iterations
    return resolution * prm.distance_start * (prm.distance_end / prm.distance_start) ** f


@njit(cache=True, inline="always")
def _moved(R, t, points, i):  # pragma: no cover - compiled
    """x = R p_i + t: probe point i under the current transform."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    return (R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0],
            R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1],
            R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2])


@njit(cache=True, inline="always")
def _normals_agree(R, probe_normals, i, gallery_normals, j, cos_max_angle):  # pragma: no cover - compiled
    """Normal filter (§8.6.1): (R n_p) · n_g ≥ cos(max_normal_angle); gallery normals are int8 (× 127). The
    distance filter is the threshold of the closest-point query; the boundary filter is one flag."""
    gn0 = gallery_normals[j, 0] / 127.0  # int8 normals have norm 1 ± 0.007
    gn1 = gallery_normals[j, 1] / 127.0
    gn2 = gallery_normals[j, 2] / 127.0
    q0, q1, q2 = probe_normals[i, 0], probe_normals[i, 1], probe_normals[i, 2]
    c = ((R[0, 0] * q0 + R[0, 1] * q1 + R[0, 2] * q2) * gn0
         + (R[1, 0] * q0 + R[1, 1] * q1 + R[1, 2] * q2) * gn1
         + (R[2, 0] * q0 + R[2, 1] * q1 + R[2, 2] * q2) * gn2)
    return not c < cos_max_angle  # (a NaN normal passes, as it always did)


@njit(cache=True, inline="always")
def _colours_agree(probe_colors, i, gallery_colors, j, max_color2):  # pragma: no cover - compiled
    """Colour filter (§8.6.1): ‖c_p − c_g‖² ≤ max_color_difference² (RGB)."""
    e = 0.0
    for a in range(3):
        dc = float(probe_colors[i, a]) - float(gallery_colors[j, a])
        e += dc * dc
    return e <= max_color2


@njit(cache=True, inline="always")
def _accumulate_point_to_point(sp, sg, H, points, i, g, j):  # pragma: no cover - compiled
    """Point-to-point sums (Arun et al. 1987): Σ p, Σ g and Σ p gᵀ of the original probe points p and their
    pairs g, for H = Σ p gᵀ − m p̄ ḡᵀ."""
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    gx, gy, gz = float(g.points[j, 0]), float(g.points[j, 1]), float(g.points[j, 2])
    sp[0] += px
    sp[1] += py
    sp[2] += pz
    sg[0] += gx
    sg[1] += gy
    sg[2] += gz
    H[0, 0] += px * gx
    H[0, 1] += px * gy
    H[0, 2] += px * gz
    H[1, 0] += py * gx
    H[1, 1] += py * gy
    H[1, 2] += py * gz
    H[2, 0] += pz * gx
    H[2, 1] += pz * gy
    H[2, 2] += pz * gz


@njit(cache=True, inline="always")
def _accumulate_point_to_plane(A, b, row, x, y, z, g, j):  # pragma: no cover - compiled
    """Point-to-plane normal equations (Chen & Medioni 1992, linearised for small angles): with the moved point
    x, its pair g and g's normal n, a = [x × n, n] and r = (x − g) · n; A += a aᵀ, b −= a r, so that
    u = (ω, τ) = A⁻¹ b minimises Σ ((x + ω × x + τ − g) · n)²."""
    gx, gy, gz = float(g.points[j, 0]), float(g.points[j, 1]), float(g.points[j, 2])
    gn0 = g.normals[j, 0] / 127.0
    gn1 = g.normals[j, 1] / 127.0
    gn2 = g.normals[j, 2] / 127.0
    row[0] = y * gn2 - z * gn1
    row[1] = z * gn0 - x * gn2
    row[2] = x * gn1 - y * gn0
    row[3], row[4], row[5] = gn0, gn1, gn2
    r = (x - gx) * gn0 + (y - gy) * gn1 + (z - gz) * gn2
    for a in range(6):
        b[a] -= row[a] * r
        for c in range(6):
            A[a, c] += row[a] * row[c]


@njit(cache=True, inline="always")
def _solve_point_to_point(sp, sg, H, m):  # pragma: no cover - compiled
    """The absolute transform from the original probe points (Arun et al. 1987): p̄ = Σp / m, ḡ = Σg / m,
    (R, t) = rigid_from_covariance(Σ p gᵀ − m p̄ ḡᵀ, p̄, ḡ)."""
    p_bar = sp / m
    g_bar = sg / m
    return rigid_from_covariance(H - m * np.outer(p_bar, g_bar), p_bar, g_bar)


@njit(cache=True, inline="always")
def _solve_point_to_plane(A, b, R, t):  # pragma: no cover - compiled
    """The increment u = (ω, τ) = A⁻¹ b (A regularised by 1e-12 · (tr A + 1)), composed onto the current
    transform: R ← R(ω) R, t ← R(ω) t + τ, R(ω) by Rodrigues' formula."""
    scale = 1e-12 * (np.trace(A) + 1.0)
    for a in range(6):
        A[a, a] += scale
    u = np.linalg.solve(A, b)
    dR = _rotation_vector(u[:3])
    return dR @ R, dR @ t + u[3:]


@njit(cache=True)
def _rotation_vector(w):  # pragma: no cover - compiled
    """Rotation matrix of a rotation vector (axis × angle in radians), Rodrigues' formula."""
    theta = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    K /= theta
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


@njit(cache=True, inline="always")
def _next_step(prm, fine, converged, k, k_fine):  # pragma: no cover - compiled
    """Stopping (§8.6.1: convergence of the MSE, |e_k − e_{k−1}| < tolerance, or an iteration cap). Coarse phase:
    go fine once converged after the threshold stopped shrinking, or when only fine_iterations are left. Fine
    phase: stop when converged or after fine_iterations (or max_iterations) updates."""
    if fine:
        if converged or k_fine >= prm.fine_iterations or k >= prm.max_iterations:
            return _STOP
        return _UPDATE
    if (k >= prm.shrink_iterations and converged) or k >= prm.max_iterations - prm.fine_iterations:
        return _FINE
    return _UPDATE


@njit(cache=True, inline="always")
def _subsets(probe, g, prm):  # pragma: no cover - compiled
    """(coarse points, fine points, normal filter on, colour filter on) of a probe–gallery pair (§8.6.1: coarse to
    fine; the normal and colour filters need normals and colours on both sides)."""
    n_all = probe.points.shape[0]
    n_coarse = min(prm.coarse_points, n_all)
    n_fine = n_all if prm.fine_points == 0 else min(prm.fine_points, n_all)
    use_normals = prm.cos_max_angle > -1.5 and probe.normals.shape[0] > 0
    use_color = prm.max_color2 >= 0.0 and probe.colors.shape[0] > 0 and g.colors.shape[0] > 0
    return n_coarse, n_fine, use_normals, use_color


@njit(cache=True)
def _icp_loop(probe, g, prm, R0, t0):  # pragma: no cover - compiled
    """The coarse-to-fine ICP loop; returns (R, t, mse, m, iterations, converged, pairs), pairs[i] the closest
    gallery point of probe point i within the last threshold at the returned transform (−1: none; exact, before the
    pair filters: the loop stops in its fine phase, so the first fine_points hold the final ones). Point-to-point solves each
    update for the absolute transform of the original probe points; point-to-plane solves for a small motion
    of the moved points and composes that increment onto the current transform."""
    n_coarse, n_fine, use_normals, use_color = _subsets(probe, g, prm)
    exact = prm.distance_end * g.resolution  # closest points within this are exact
    hint = np.full(max(n_coarse, n_fine), -1, dtype=np.int64)  # each probe point's pair at the previous iteration
    R, t = R0.copy(), t0.copy()
    k, k_fine, m, fine, converged, prev, mse = 0, 0, 0, False, False, np.inf, np.inf
    while True:
        thr = _threshold(prm, g.resolution, k, fine)
        m, sse = 0, 0.0
        sp, sg, H, A, b, row = np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.zeros((6, 6)), np.zeros(6), np.empty(6)
        for i in range(n_fine if fine else n_coarse):
            x, y, z = _moved(R, t, probe.points, i)
            j, d2 = closest_point(x, y, z, thr, exact, g, hint[i])  # closest points
            hint[i] = j
            if j < 0 or (prm.drop_boundary and g.boundary[j]):  # filters
                continue
            if use_normals and not _normals_agree(R, probe.normals, i, g.normals, j, prm.cos_max_angle):
                continue
            if use_color and not _colours_agree(probe.colors, i, g.colors, j, prm.max_color2):
                continue
            m, sse = m + 1, sse + d2
            if prm.point_to_plane:
                _accumulate_point_to_plane(A, b, row, x, y, z, g, j)
            else:
                _accumulate_point_to_point(sp, sg, H, probe.points, i, g, j)
        if m < (6 if prm.point_to_plane else 3):  # too few pairs to solve for a motion
            return R, t, np.inf, m, k, False, hint
        mse = sse / m  # error
        converged = abs(mse - prev) < prm.tolerance
        step = _next_step(prm, fine, converged, k, k_fine)  # stop
        if step == _STOP:
            break
        if step == _FINE:
            fine, prev = True, np.inf
            continue
        if prm.point_to_plane:  # transform
            R, t = _solve_point_to_plane(A, b, R, t)
        else:
            R, t = _solve_point_to_point(sp, sg, H, m)
        prev, k, k_fine = mse, k + 1, k_fine + fine
    return R, t, (mse if m >= prm.min_overlap * n_fine else np.inf), m, k, converged, hint
