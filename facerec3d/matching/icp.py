"""ICP matching (chapter §8.6.1): rigidly align a probe face to a gallery face; the score is −MSE.

Gallery side, built once per face at enrolment and kept in its template (`GalleryIndex`):
  * the voxel nearest-neighbour lookup: for every centre of a `voxel_size` mm
    voxel within `margin` of the face (margin = the initial distance
    threshold, at most `max_reach_mm` or the final threshold, plus half a
    voxel diagonal; pairs farther than it are dropped) the index of its nearest gallery
    point, so a closest-point query is one array read. Only the z-run of
    such voxels is kept in each x–y column. The stored point is the nearest
    to the voxel centre, so it may miss the query's true closest point by up
    to a voxel diagonal;
  * x–y buckets: the points sorted by x–y column of the same grid, for an
    exact fixed-radius closest-point search in compiled code. This takes the
    place of a k-d tree: scipy's cKDTree can neither be called from Numba nor
    saved without pickle (so it would be rebuilt on every load) and costs
    ~1 µs per query from Python; the buckets are plain arrays in the .npz;
  * PCA normals (int8, unit normal × 127) and boundary points (rim and hole
    edges), geometry.normals.

Matching (`icp`, `ICPMatcher`), all inside one Numba call per probe–gallery pair:
  * closest points: exact whenever the closest point lies within the final
    threshold (`distance_end`); the search is bounded by the point's pair of
    the previous iteration or by the voxel lookup's candidate, which also
    rejects queries that cannot have a point within the threshold. Farther
    pairs, which only the early, wide thresholds accept, come from the voxel
    lookup alone;
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
point-to-plane least squares (Chen & Medioni; chapter 6).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from facerec3d.geometry.normals import boundary_mask, estimate_normals
from facerec3d.matching.base import Matcher, Template
from facerec3d.scan import FaceScan

VARIANTS = ("point-to-point", "point-to-plane")


@dataclass(frozen=True)
class ICPConfig:
    """ICP settings (chapter §8.6.1). Distances marked × res are multiples of the gallery's resolution
    (its median point spacing, ~1 mm for preprocessed faces)."""

    variant: str = "point-to-point"  # §8.6.1 (Besl & McKay); or "point-to-plane" (Chen & Medioni 1992; chapter 6)
    max_iterations: int = 40  # transform updates in all; §8.6.1 stops at convergence or an iteration cap
    tolerance: float = 1e-4  # mm²: converged when the MSE changes by less between iterations (§8.6.1)
    coarse_points: int = 300  # probe points of the coarse iterations (§8.6.1: coarse to fine)
    fine_points: int = 1000  # probe points of the fine iterations and of the score; 0 = all
    fine_iterations: int = 2  # at most this many updates in the fine phase
    distance_start: float = 10.0  # × res: initial pair distance threshold (§8.6.1: a multiple of the resolution)
    distance_end: float = 2.0  # × res: final threshold (§8.6.1: about the resolution; 2× keeps the pairs
    #                            of two differently sampled 1 mm scans with 0.3 mm noise)
    shrink_iterations: int = 10  # iterations over which the threshold falls geometrically to distance_end
    max_normal_angle: float | None = 45.0  # degrees between probe and gallery normals; None = off (§8.6.1)
    drop_boundary: bool = True  # reject pairs on gallery boundary points (§8.6.1)
    max_color_difference: float | None = None  # RGB distance (0–255); None = off; needs colours on both (§8.6.1)
    min_overlap: float = 0.1  # final pairs fewer than this share of the fine probe points: no match (MSE = inf)
    max_reach_mm: float = 30.0  # mm, enrolment: the voxel lookup reaches at most this far (or the final threshold),
    #                            so a coarse source (large res) does not blow up the template; faces arrive pre-aligned
    voxel_size: float = 2.0  # mm, enrolment: voxel lookup cell and x–y bucket (§8.6.1); ~0.4 MB per template
    normal_neighbours: int = 16  # k of the PCA normals (§8.6.1; geometry.normals)
    sensor_scale: float = 1.0  # res = max(point spacing, this × the source scan's pitch or depth step, whichever is
    #                            larger, as preprocessing measured them): a 1 mm grid resampled from 3.5 mm Kinect
    #                            pixels in 8 mm depth steps is not 1 mm data (§8.6.1: thresholds follow the resolution)
    seed: int = 0  # random probe subsets

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown ICP variant {self.variant!r}: use one of {VARIANTS}")
        if not 0 < self.distance_end <= self.distance_start:
            raise ValueError("need 0 < distance_end <= distance_start")
        if self.voxel_size <= 0 or self.coarse_points < 1 or self.fine_points < 0:
            raise ValueError("voxel_size and coarse_points must be positive, fine_points >= 0")


class ICPResult(NamedTuple):
    """The gallery-frame transform x -> R x + t of the probe, and the fit at it."""

    R: np.ndarray  # (3, 3) rotation
    t: np.ndarray  # (3,) mm
    mse: float  # mm²: mean squared distance of the kept exact correspondences (inf: no match)
    n_correspondences: int  # kept correspondences m (of the fine probe points)
    iterations: int  # transform updates made
    converged: bool  # the MSE change fell below the tolerance


class GalleryIndex(NamedTuple):
    """A gallery face's search structures (see the module docstring); built once by `from_scan`.

    The voxel lookup covers pairs up to the enrolment config's distance_start;
    matching with a larger one misses the farther pairs.
    """

    points: np.ndarray  # (N, 3) float32 mm, sorted by x–y bucket
    normals: np.ndarray  # (N, 3) int8: unit normal × 127
    boundary: np.ndarray  # (N,) bool
    colors: np.ndarray  # (N, 3) uint8, or (0, 3) without colours
    voxel_first: np.ndarray  # (C,) int16: z index of the first stored voxel of each x–y column
    voxel_offset: np.ndarray  # (C + 1,) int32: column c's voxels are voxel_index[offset[c]:offset[c + 1]]
    voxel_index: np.ndarray  # (V,) uint16 (int32 above 65,534 points): nearest point; dtype max = none
    bucket_start: np.ndarray  # (C + 1,) int32: column c's points are points[start[c]:start[c + 1]]
    origin: np.ndarray  # (3,) mm: corner of the voxel grid
    voxel_size: float  # mm
    nx: int
    ny: int
    nz: int
    resolution: float  # mm: median spacing of the gallery points
    margin: float  # mm: voxels farther than this from every point store none

    @classmethod
    def from_scan(cls, scan: FaceScan, config: ICPConfig = ICPConfig()) -> "GalleryIndex":
        """Build from a scan: PCA normals (the scan's own if it has them) and boundary from its grid when it has one."""
        normals = scan.normals
        if normals is None:
            normals = estimate_normals(scan.points, config.normal_neighbours, grid=scan.grid,
                                       grid_shape=scan.grid_shape)
        boundary = boundary_mask(scan.points, grid=scan.grid, grid_shape=scan.grid_shape)
        return cls.build(scan.points, normals, boundary, scan.colors, resolution=matching_resolution(scan, config),
                         config=config)

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray, boundary: np.ndarray, colors: np.ndarray | None = None,
              *, resolution: float, config: ICPConfig = ICPConfig()) -> "GalleryIndex":
        """Build from gallery points (mm), unit normals, boundary flags, optional RGB, and point spacing (mm)."""
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3).astype(np.float64)  # as stored
        if len(pts) < 3:
            raise ValueError("a gallery face needs at least 3 points")
        h = float(config.voxel_size)
        reach = min(config.distance_start * resolution, max(config.max_reach_mm, config.distance_end * resolution))
        margin = reach + 0.5 * math.sqrt(3.0) * h
        origin = pts.min(axis=0) - margin
        nx, ny, nz = (np.ceil((pts.max(axis=0) + margin - origin) / h).astype(np.int64) + 1).tolist()
        column = (np.floor((pts[:, 0] - origin[0]) / h).astype(np.int64) * ny
                  + np.floor((pts[:, 1] - origin[1]) / h).astype(np.int64))
        order = np.argsort(column, kind="stable")
        pts = pts[order]
        bucket_start = np.concatenate([[0], np.cumsum(np.bincount(column, minlength=nx * ny))]).astype(np.int32)
        nearest = _voxel_nearest(pts, origin, h, nx, ny, nz, margin)
        first, offset, index = _compress_columns(nearest, len(pts))
        col = np.zeros((0, 3), np.uint8) if colors is None else np.asarray(colors, dtype=np.uint8)[order]
        nrm = np.asarray(normals, dtype=np.float64)[order]
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        return cls(pts.astype(np.float32), np.round(nrm * 127).astype(np.int8), np.asarray(boundary, dtype=bool)[order],
                   np.ascontiguousarray(col), first, offset, index, bucket_start, origin, h, nx, ny, nz,
                   float(resolution), float(margin))

    def to_template(self, subject: str | None = None, scan_id: str | None = None) -> Template:
        arrays = {name: getattr(self, name) for name in _INDEX_ARRAYS}
        attrs = {name: getattr(self, name) for name in _INDEX_SCALARS}
        attrs["origin"] = self.origin.tolist()
        return Template(subject, scan_id, ICPMatcher.name, arrays, attrs)

    @classmethod
    def from_template(cls, template: Template) -> "GalleryIndex":
        if missing := set(_INDEX_ARRAYS) - set(template.arrays):
            raise ValueError(f"not an ICP gallery template (method {template.method!r}): no {sorted(missing)}")
        a, s = template.arrays, template.attrs
        return cls(*(a[name] for name in _INDEX_ARRAYS), np.asarray(s["origin"], dtype=np.float64),
                   float(s["voxel_size"]), int(s["nx"]), int(s["ny"]), int(s["nz"]),
                   float(s["resolution"]), float(s["margin"]))


_INDEX_ARRAYS = ("points", "normals", "boundary", "colors", "voxel_first", "voxel_offset", "voxel_index",
                 "bucket_start")
_INDEX_SCALARS = ("voxel_size", "nx", "ny", "nz", "resolution", "margin")


def matching_resolution(scan: FaceScan, config: ICPConfig = ICPConfig()) -> float:
    """The resolution (mm) ICP's distance thresholds are multiples of: the face's point spacing, or, when the
    scan it was resampled from was coarser (its measured pitch or depth step, `meta.extra["quality"]`),
    `sensor_scale` times that."""
    quality = scan.meta.extra.get("quality", {})
    source = max(float(quality.get("pitch_mm", 0.0)), float(quality.get("depth_step_mm", 0.0)))
    return max(scan.resolution(), config.sensor_scale * source)


class ProbeData(NamedTuple):
    """A probe prepared for ICP: points in random order (the first ones are the coarse subset)."""

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


def _params(config: ICPConfig) -> _Params:
    return _Params(
        config.variant == "point-to-plane", int(config.max_iterations), float(config.tolerance),
        int(config.coarse_points), int(config.fine_points), int(config.fine_iterations),
        float(config.distance_start), float(config.distance_end), int(config.shrink_iterations),
        -2.0 if config.max_normal_angle is None else math.cos(math.radians(config.max_normal_angle)),
        -1.0 if config.max_color_difference is None else float(config.max_color_difference) ** 2,
        bool(config.drop_boundary), float(config.min_overlap),
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
    R, t, mse, m, k, converged = _icp_loop(probe, gallery, params, np.ascontiguousarray(R0), t0)
    return ICPResult(R, t, mse, m, k, converged)


class ICPMatcher(Matcher):
    """ICP identification and verification (§8.6.1): score = −MSE (mm²), tiebreak = correspondence count."""

    name = "icp"
    config_class = ICPConfig

    def __init__(self, config: ICPConfig = ICPConfig()):
        self.config = config
        self._params = _params(config)

    def enroll(self, scan: FaceScan) -> Template:
        return GalleryIndex.from_scan(scan, self.config).to_template(scan.meta.subject, scan.meta.scan_id)

    def prepare(self, scan: FaceScan) -> Template:
        """The probe's random subset with normals (method "icp-probe")."""
        p = ProbeData.build(scan.points, scan.normals, scan.colors, self.config, grid=scan.grid,
                            grid_shape=scan.grid_shape)
        return Template(scan.meta.subject, scan.meta.scan_id, "icp-probe", dict(p._asdict()), {})

    def _probe_data(self, probe: FaceScan | Template) -> ProbeData:
        p = self._probe(probe)
        if not isinstance(p, Template) or p.method != "icp-probe":
            raise TypeError("an ICP probe must be a FaceScan or a template from ICPMatcher.prepare")
        return ProbeData(**p.arrays)

    def align(self, probe: FaceScan | Template, template: Template,
              init: tuple[np.ndarray, np.ndarray] | None = None) -> ICPResult:
        """The full ICP result of a probe against a gallery template."""
        return _align(self._probe_data(probe), GalleryIndex.from_template(template), self._params, init)

    def score(self, probe: FaceScan | Template, template: Template) -> float:
        return -self.align(probe, template).mse

    def scores(self, probe: FaceScan | Template, templates: Sequence[Template]) -> tuple[np.ndarray, np.ndarray]:
        """(−MSE, correspondence count) against each template; one compiled call per template."""
        return self.data_scores(self._probe_data(probe), [GalleryIndex.from_template(t) for t in templates])

    def data_scores(self, probe: ProbeData, galleries: Sequence[GalleryIndex]) -> tuple[np.ndarray, np.ndarray]:
        """(−MSE mm², correspondence count) of probe data (e.g. one region of a face) against gallery indices."""
        s = np.empty(len(galleries))
        m = np.empty(len(galleries), dtype=np.int64)
        eye, zero = np.eye(3), np.zeros(3)
        for i, gallery in enumerate(galleries):
            out = _icp_loop(probe, gallery, self._params, eye, zero)
            s[i], m[i] = -out[2], out[3]
        return s, m


# --------------------------------------------------------------------------- enrolment kernels
@njit(cache=True)
def _voxel_nearest(points, origin, h, nx, ny, nz, radius):  # pragma: no cover - compiled
    """(nx, ny, nz) int32: index of the point nearest each voxel centre within radius, −1 if none (exact)."""
    nearest = np.full((nx, ny, nz), -1, dtype=np.int32)
    best = np.full((nx, ny, nz), np.inf)
    r2 = radius * radius
    for j in range(points.shape[0]):
        px, py, pz = points[j, 0], points[j, 1], points[j, 2]
        i0 = max(int(math.ceil((px - radius - origin[0]) / h - 0.5)), 0)
        i1 = min(int(math.floor((px + radius - origin[0]) / h - 0.5)), nx - 1)
        for ix in range(i0, i1 + 1):
            dx = origin[0] + (ix + 0.5) * h - px
            rx = r2 - dx * dx
            if rx < 0.0:
                continue
            ry = math.sqrt(rx)
            j0 = max(int(math.ceil((py - ry - origin[1]) / h - 0.5)), 0)
            j1 = min(int(math.floor((py + ry - origin[1]) / h - 0.5)), ny - 1)
            for iy in range(j0, j1 + 1):
                dy = origin[1] + (iy + 0.5) * h - py
                ryz = rx - dy * dy
                if ryz < 0.0:
                    continue
                rz = math.sqrt(ryz)
                k0 = max(int(math.ceil((pz - rz - origin[2]) / h - 0.5)), 0)
                k1 = min(int(math.floor((pz + rz - origin[2]) / h - 0.5)), nz - 1)
                for iz in range(k0, k1 + 1):
                    dz = origin[2] + (iz + 0.5) * h - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 < best[ix, iy, iz]:
                        best[ix, iy, iz] = d2
                        nearest[ix, iy, iz] = j
    return nearest


def _compress_columns(nearest: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep, per x–y column, the z-run from the first to the last voxel that has a nearest point."""
    nz = nearest.shape[2]
    found = nearest >= 0
    has = found.any(axis=2)
    first = np.where(has, found.argmax(axis=2), 0)
    last = np.where(has, nz - 1 - found[:, :, ::-1].argmax(axis=2), -1)
    z = np.arange(nz)
    run = (z >= first[..., None]) & (z <= last[..., None])
    dtype = np.uint16 if n_points < np.iinfo(np.uint16).max else np.int32
    values = nearest[run]
    index = np.where(values >= 0, values, np.iinfo(dtype).max).astype(dtype)
    offset = np.concatenate([[0], np.cumsum((last - first + 1).ravel())]).astype(np.int32)
    return first.ravel().astype(np.int16), offset, index


# --------------------------------------------------------------------------- matching kernels
@njit(cache=True, inline="always")
def _nearest_within(x, y, z, r, g):  # pragma: no cover - compiled
    """(index, squared distance) of the exact closest gallery point within r mm of (x, y, z); index −1 if none.

    Scans the x–y buckets overlapping the square of half-side r; the buckets
    of one x column are consecutive, so each column is one contiguous run.
    """
    h = g.voxel_size
    i0 = max(int(math.floor((x - r - g.origin[0]) / h)), 0)
    i1 = min(int(math.floor((x + r - g.origin[0]) / h)), g.nx - 1)
    j0 = max(int(math.floor((y - r - g.origin[1]) / h)), 0)
    j1 = min(int(math.floor((y + r - g.origin[1]) / h)), g.ny - 1)
    best = r * r
    found = -1
    if j0 > j1:
        return found, best
    for ix in range(i0, i1 + 1):
        c = ix * g.ny
        for j in range(g.bucket_start[c + j0], g.bucket_start[c + j1 + 1]):
            dx = g.points[j, 0] - x
            dy = g.points[j, 1] - y
            dz = g.points[j, 2] - z
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= best:
                best = d2
                found = j
    return found, best


@njit(cache=True, inline="always")
def _closest_point(x, y, z, thr, exact, g, hint):  # pragma: no cover - compiled
    """(index, squared distance) of the gallery point closest to (x, y, z) if within thr mm, else (−1, ·).

    Exact when it is within `exact` mm (the final threshold); farther ones
    come from the voxel lookup alone. A first guess bounds the exact search:
    `hint` (the point's closest point at the previous iteration, −1 if none)
    or the voxel's candidate. That candidate lies at distance d from the
    query and e from the voxel centre, so the true closest point is at least
    d − 2e away (triangle inequality): the query is rejected without search
    when d − 2e > thr. A radius of d(1 + 1e-9) absorbs rounding.
    """
    if hint >= 0:
        dx = g.points[hint, 0] - x
        dy = g.points[hint, 1] - y
        dz = g.points[hint, 2] - z
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d <= exact:
            return _nearest_within(x, y, z, d * (1.0 + 1e-9), g)
    h = g.voxel_size
    fx = (x - g.origin[0]) / h
    fy = (y - g.origin[1]) / h
    fz = (z - g.origin[2]) / h
    if not (0.0 <= fx < g.nx and 0.0 <= fy < g.ny and 0.0 <= fz < g.nz):
        return -1, np.inf
    ix, iy, iz = int(fx), int(fy), int(fz)
    c = ix * g.ny + iy
    k = iz - g.voxel_first[c]
    if k < 0 or k >= g.voxel_offset[c + 1] - g.voxel_offset[c]:
        return -1, np.inf
    j = int(g.voxel_index[g.voxel_offset[c] + k])
    if j >= g.points.shape[0]:  # no gallery point within margin of the voxel centre: none within thr
        return -1, np.inf
    ex, ey, ez = fx - ix - 0.5, fy - iy - 0.5, fz - iz - 0.5
    dx = g.points[j, 0] - x
    dy = g.points[j, 1] - y
    dz = g.points[j, 2] - z
    d2 = dx * dx + dy * dy + dz * dz
    d = math.sqrt(d2)
    if d - 2.0 * h * math.sqrt(ex * ex + ey * ey + ez * ez) > thr:
        return -1, np.inf
    r = min(d * (1.0 + 1e-9), thr)
    if r <= exact:
        return _nearest_within(x, y, z, r, g)
    return (j, d2) if d <= thr else (-1, np.inf)


@njit(cache=True)
def _fit_rigid(H, p_bar, g_bar):  # pragma: no cover - compiled
    """Arun et al.'s SVD solution from H = Σ (p − p̄)(g − ḡ)ᵀ, as geometry.transforms.rigid_fit: reflection
    fixed by flipping the last singular vector, t = ḡ − R p̄."""
    U, _, Vt = np.linalg.svd(H)
    V = Vt.T
    if np.linalg.det(V @ U.T) < 0.0:
        V[:, 2] = -V[:, 2]
    R = V @ U.T
    return R, g_bar - R @ p_bar


@njit(cache=True)
def _rotation_vector(w):  # pragma: no cover - compiled
    """Rotation matrix of a rotation vector (axis × angle in radians), Rodrigues' formula."""
    theta = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    K /= theta
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


@njit(cache=True)
def _icp_loop(probe, g, prm, R0, t0):  # pragma: no cover - compiled
    """The coarse-to-fine ICP loop; returns (R, t, mse, m, iterations, converged)."""
    n_all = probe.points.shape[0]
    n_coarse = min(prm.coarse_points, n_all)
    n_fine = n_all if prm.fine_points == 0 else min(prm.fine_points, n_all)
    use_normals = prm.cos_max_angle > -1.5 and probe.normals.shape[0] > 0
    use_color = prm.max_color2 >= 0.0 and probe.colors.shape[0] > 0 and g.colors.shape[0] > 0
    min_pairs = 6 if prm.point_to_plane else 3
    exact = prm.distance_end * g.resolution
    hint = np.full(max(n_coarse, n_fine), -1, dtype=np.int64)  # each probe point's pair at the previous iteration
    R = R0.copy()
    t = t0.copy()
    k = 0  # transform updates
    k_fine = 0  # of which in the fine phase
    fine = False
    prev = np.inf
    mse = np.inf
    m = 0
    while True:
        if fine or prm.shrink_iterations <= 0:
            thr = exact
        else:
            f = min(k, prm.shrink_iterations) / prm.shrink_iterations
            thr = g.resolution * prm.distance_start * (prm.distance_end / prm.distance_start) ** f
        n = n_fine if fine else n_coarse
        m = 0
        sse = 0.0
        sp = np.zeros(3)
        sg = np.zeros(3)
        H = np.zeros((3, 3))
        A = np.zeros((6, 6))
        b = np.zeros(6)
        row = np.empty(6)
        for i in range(n):
            px, py, pz = probe.points[i, 0], probe.points[i, 1], probe.points[i, 2]
            x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
            y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
            z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
            j, d2 = _closest_point(x, y, z, thr, exact, g, hint[i])
            hint[i] = j
            if j < 0:
                continue
            if prm.drop_boundary and g.boundary[j]:
                continue
            gn0 = g.normals[j, 0] / 127.0  # int8 normals have norm 1 ± 0.007
            gn1 = g.normals[j, 1] / 127.0
            gn2 = g.normals[j, 2] / 127.0
            if use_normals:
                q0, q1, q2 = probe.normals[i, 0], probe.normals[i, 1], probe.normals[i, 2]
                c = ((R[0, 0] * q0 + R[0, 1] * q1 + R[0, 2] * q2) * gn0
                     + (R[1, 0] * q0 + R[1, 1] * q1 + R[1, 2] * q2) * gn1
                     + (R[2, 0] * q0 + R[2, 1] * q1 + R[2, 2] * q2) * gn2)
                if c < prm.cos_max_angle:
                    continue
            if use_color:
                e = 0.0
                for a in range(3):
                    dc = float(probe.colors[i, a]) - float(g.colors[j, a])
                    e += dc * dc
                if e > prm.max_color2:
                    continue
            m += 1
            sse += d2
            gx, gy, gz = float(g.points[j, 0]), float(g.points[j, 1]), float(g.points[j, 2])
            if prm.point_to_plane:
                row[0] = y * gn2 - z * gn1
                row[1] = z * gn0 - x * gn2
                row[2] = x * gn1 - y * gn0
                row[3], row[4], row[5] = gn0, gn1, gn2
                r = (x - gx) * gn0 + (y - gy) * gn1 + (z - gz) * gn2
                for a in range(6):
                    b[a] -= row[a] * r
                    for c6 in range(6):
                        A[a, c6] += row[a] * row[c6]
            else:
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
        if m < min_pairs:  # too few pairs to solve for a motion
            return R, t, np.inf, m, k, False
        mse = sse / m
        converged = abs(mse - prev) < prm.tolerance
        if fine:
            if converged:
                break
            if k_fine >= prm.fine_iterations or k >= prm.max_iterations:
                break
        elif (k >= prm.shrink_iterations and converged) or k >= prm.max_iterations - prm.fine_iterations:
            fine = True
            prev = np.inf
            continue
        if prm.point_to_plane:
            scale = 1e-12 * (np.trace(A) + 1.0)
            for a in range(6):
                A[a, a] += scale
            u = np.linalg.solve(A, b)
            dR = _rotation_vector(u[:3])
            R = dR @ R
            t = dR @ t + u[3:]
        else:
            p_bar = sp / m
            g_bar = sg / m
            R, t = _fit_rigid(H - m * np.outer(p_bar, g_bar), p_bar, g_bar)
        prev = mse
        k += 1
        k_fine += fine
    if m < prm.min_overlap * n_fine:
        mse = np.inf
    return R, t, mse, m, k, converged
