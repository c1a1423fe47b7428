"""ICP matching (chapter §8.6.1) on morphable-model faces: motion recovery, filters, exactness, identification."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from facerec3d import FaceScan, ScanMeta
from facerec3d.datasets.frontal import face_mesh, frontal_face, on_preprocessing_grid
from facerec3d.geometry.normals import estimate_normals
from facerec3d.geometry.transforms import rigid_fit, rotation_between, rotation_from_euler
from facerec3d.geometry.transforms import rigid_from_covariance as _fit_rigid
from facerec3d.matching import GalleryIndex, ICPConfig, ICPMatcher, ProbeData, Template, icp


CROP_MM = 80.0  # the ICP scenarios below are built on Mian et al.'s 80 mm crop (preprocessing's default is wider)


def grid_scan(mesh, identity: int = 0) -> FaceScan:
    """The face as preprocessing leaves it: on the 1 mm x–y grid, cropped to 80 mm around the nose."""
    scan = on_preprocessing_grid(*mesh, CROP_MM)
    return scan.replace(meta=ScanMeta(subject=f"s{identity}", scan_id=f"s{identity}-g"))


def random_points(mesh, density: float, rng: np.random.Generator) -> np.ndarray:
    """Uniform random points on the face surface (about `density` per mm²), cropped to 80 mm."""
    v, tri = mesh
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    k = rng.choice(len(tri), int(area.sum() * density), p=area / area.sum())
    u, w = rng.random(len(k)), rng.random(len(k))
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    p = a[k] + u[:, None] * (b[k] - a[k]) + w[:, None] * (c[k] - a[k])
    return p[np.linalg.norm(p, axis=1) <= CROP_MM]


def moved_back(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points p with R p + t = the given points: a probe whose true alignment is (R, t)."""
    return (points - t) @ R


def errors(result, R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    return rotation_between(R, result.R), float(np.linalg.norm(result.t - t))


@pytest.fixture(scope="module")
def mesh():
    return face_mesh(1)


@pytest.fixture(scope="module")
def cloud(mesh):
    """A gridless gallery of random surface samples (no lattice for point-to-point ICP to lock onto)."""
    return FaceScan(random_points(mesh, 0.7, np.random.default_rng(3)))


# Large motions need a wide start and a slow shrink; point-to-point ICP creeps.
WIDE = ICPConfig(distance_start=60.0, shrink_iterations=60, max_iterations=150, fine_iterations=20, tolerance=1e-10)
MOTIONS = [((15, 0, 0), (0, 0, 0)), ((0, 0, 15), (0, 0, 0)), ((0, 0, 0), (20, 0, 0)), ((0, 0, 0), (0, 0, 20)),
           ((-9, 9, 9), (-12, 12, -12)), ((10, -5, 8), (12, -10, 12))]


@pytest.fixture(scope="module")
def wide_index(cloud):
    return GalleryIndex.from_scan(cloud, WIDE)


@pytest.mark.parametrize("kind", ["grid", "cloud"])
def test_voxel_lookup_stores_the_nearest_point_of_every_voxel_centre(mesh, cloud, kind):
    """Each stored voxel holds a point exactly as near its centre as the nearest gallery point (k-d tree), and
    every centre with a point within the margin has one: the separable search on a gridded face and the ball
    scatter on a cloud of points alike."""
    scan = grid_scan(mesh) if kind == "grid" else cloud
    g = GalleryIndex.from_scan(scan, ICPConfig(distance_start=30.0))
    pts = g.points.astype(np.float64)
    ix, iy = np.divmod(np.arange(g.nx * g.ny), g.ny)
    runs = np.diff(g.voxel_offset)
    col = np.repeat(np.arange(g.nx * g.ny), runs)
    iz = g.voxel_first[col] + (np.arange(len(g.voxel_index)) - g.voxel_offset[col])
    centres = g.origin + (np.stack([ix[col], iy[col], iz], axis=1) + 0.5) * g.voxel_size
    truth, _ = cKDTree(pts).query(centres)
    stored = g.voxel_index.astype(np.int64)
    has = stored < len(pts)
    assert has.sum() > 10_000
    d = np.linalg.norm(pts[stored[has]] - centres[has], axis=1)
    assert np.allclose(d, truth[has], rtol=0, atol=1e-9)
    assert (truth[~has] > g.margin - 1e-9).all()  # an empty voxel has no point within the margin


@pytest.mark.parametrize("variant", ["point-to-point", "point-to-plane"])
@pytest.mark.parametrize("angles,shift", MOTIONS)
def test_exact_motion_recovered(cloud, wide_index, variant, angles, shift):
    R, t = rotation_from_euler(*angles), np.asarray(shift, float)
    config = dataclasses.replace(WIDE, variant=variant)
    result = icp(moved_back(cloud.points, R, t), wide_index, config)
    rot, tra = errors(result, R, t)
    assert rot < 0.05 and tra < 0.02, (rot, tra)
    assert result.mse < 1e-6
    # converged, within a few updates of the threshold's last shrink, far below the cap of 150
    assert result.converged and WIDE.shrink_iterations <= result.iterations <= WIDE.shrink_iterations + 5


@pytest.mark.parametrize("variant", ["point-to-point", "point-to-plane"])
def test_noisy_motion_recovered(cloud, wide_index, variant):
    config = dataclasses.replace(WIDE, variant=variant)
    rng = np.random.default_rng(5)
    for angles, shift in MOTIONS[::2]:
        R, t = rotation_from_euler(*angles), np.asarray(shift, float)
        probe = moved_back(cloud.points, R, t) + rng.normal(0.0, 0.5, cloud.points.shape)
        rot, tra = errors(icp(probe, wide_index, config), R, t)
        assert rot < 0.5 and tra < 0.5, (angles, shift, rot, tra)


def test_default_config_on_preprocessed_faces(mesh):
    """Grid gallery, probe resampled after a small pose error (≤ 3°, ≤ 3 mm) with 0.3 mm depth noise."""
    gallery = GalleryIndex.from_scan(grid_scan(mesh))
    Rp, tp = rotation_from_euler(2.5, -2.0, 1.5), np.array([2.0, -3.0, 1.5])
    moved = (mesh[0] @ Rp.T + tp, mesh[1])
    probe = grid_scan(moved).points
    probe[:, 2] += np.random.default_rng(0).normal(0.0, 0.3, len(probe))
    R, t = Rp.T, -Rp.T @ tp
    start_rot, start_tra = errors(icp(probe, gallery, ICPConfig(max_iterations=0, fine_iterations=0)), R, t)
    for variant, (max_rot, max_tra) in {"point-to-point": (1.0, 1.5), "point-to-plane": (0.2, 0.2)}.items():
        result = icp(probe, gallery, ICPConfig(variant=variant))
        rot, tra = errors(result, R, t)
        assert rot < max_rot and tra < max_tra, (variant, rot, tra)
        assert result.n_correspondences > 800 and result.mse < 0.6
        assert result.iterations < ICPConfig().max_iterations  # the coarse phase converged before its cap
    assert start_rot > 3.0 and start_tra > 3.0  # the test starts away from the answer


@pytest.mark.parametrize("variant", ["point-to-point", "point-to-plane"])
def test_iterations_and_convergence(mesh, variant):
    """The loop stops when the MSE settles (§8.6.1), and says so; caps stop it only when reached."""
    gallery = GalleryIndex.from_scan(grid_scan(mesh))
    Rp, tp = rotation_from_euler(2.5, -2.0, 1.5), np.array([2.0, -3.0, 1.5])
    probe = grid_scan((mesh[0] @ Rp.T + tp, mesh[1])).points
    probe[:, 2] += np.random.default_rng(0).normal(0.0, 0.3, len(probe))
    default = ICPConfig(variant=variant)
    result = icp(probe, gallery, default)
    # the coarse phase converges after the threshold stops shrinking, before its cap (max − fine updates); the
    # fine phase then ends at its cap of fine_iterations updates, not converged
    coarse = result.iterations - default.fine_iterations
    assert default.shrink_iterations <= coarse < default.max_iterations - default.fine_iterations
    assert not result.converged
    if variant == "point-to-plane":  # converges as soon as the threshold stops shrinking
        assert coarse == default.shrink_iterations
    # with room in the fine phase it converges there, before every cap
    roomy = ICPConfig(variant=variant, fine_iterations=10, max_iterations=60, tolerance=1e-6)
    result = icp(probe, gallery, roomy)
    assert result.converged and result.iterations < roomy.max_iterations
    # caps: exactly max_iterations updates, not converged; none at all with a cap of 0
    for cap, fine in ((5, 2), (0, 0)):
        result = icp(probe, gallery, ICPConfig(variant=variant, max_iterations=cap, fine_iterations=fine))
        assert result.iterations == cap and not result.converged


def test_the_fine_phase_starts_when_only_its_updates_are_left(mesh):
    """Coarse to fine (§8.6.1): a coarse phase whose threshold is still shrinking when only `fine_iterations` of
    `max_iterations` updates are left hands over then; the fine phase, at the final threshold, converges before the
    cap (point-to-plane: it settles in a few updates)."""
    gallery = GalleryIndex.from_scan(grid_scan(mesh))
    Rp, tp = rotation_from_euler(2.5, -2.0, 1.5), np.array([2.0, -3.0, 1.5])
    probe = grid_scan((mesh[0] @ Rp.T + tp, mesh[1])).points
    probe[:, 2] += np.random.default_rng(0).normal(0.0, 0.3, len(probe))
    config = ICPConfig(variant="point-to-plane", max_iterations=20, fine_iterations=10, shrink_iterations=30,
                       tolerance=1e-6)  # the threshold would shrink for 30 updates
    result = icp(probe, gallery, config)
    assert result.converged
    assert config.max_iterations - config.fine_iterations < result.iterations < config.max_iterations
    rot, tra = errors(result, Rp.T, -Rp.T @ tp)  # the probe is the face moved by (Rp, tp): ICP undoes it
    assert rot < 0.3 and tra < 0.3


@pytest.mark.parametrize("variant", ["point-to-point", "point-to-plane"])
def test_the_first_pairs_are_those_within_distance_start_times_the_resolution(variant):
    """§8.6.1: the first iteration's pair threshold is distance_start × res (10 × 1 mm here): a probe plane 9.5 mm
    in front of a gallery plane of 1 mm pixels finds its pairs and is brought onto it; one 10.5 mm in front finds
    none, and is no match."""
    r, c = np.mgrid[0:60, 0:60].astype(float)
    plane = FaceScan.from_range_image(np.stack([c - 30.0, 30.0 - r, np.zeros_like(r)], axis=-1),
                                      np.ones((60, 60), bool))
    config = ICPConfig(variant=variant)
    gallery = GalleryIndex.from_scan(plane, config)
    assert gallery.resolution == 1.0 and config.distance_start == 10.0
    probe = plane.points[np.max(np.abs(plane.points[:, :2]), axis=1) <= 20.0]  # away from the gallery's rim
    near = icp(probe + [0.0, 0.0, 9.5], gallery, config)
    assert near.n_correspondences == min(config.fine_points, len(probe)) and near.mse < 1e-6
    np.testing.assert_allclose(near.t[2], -9.5, atol=1e-6)
    assert icp(probe + [0.0, 0.0, 10.5], gallery, config).mse == np.inf


def test_rigid_fit_fixes_reflections():
    """Noisy near-planar points mirrored through their plane: the raw SVD solution is a reflection."""
    rng = np.random.default_rng(2)
    P = np.c_[rng.uniform(-50, 50, (40, 2)), rng.normal(0, 0.5, 40)]
    G = P * [1.0, 1.0, -1.0] + rng.normal(0, 0.05, P.shape)
    H = (P - P.mean(0)).T @ (G - G.mean(0))
    U, _, Vt = np.linalg.svd(H)
    assert np.linalg.det(Vt.T @ U.T) < 0  # the configuration does trigger the fix
    R1, t1 = rigid_fit(P, G)
    R2, t2 = _fit_rigid(np.ascontiguousarray(H), P.mean(0), G.mean(0))
    for R in (R1, R2):
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R2, R1, atol=1e-12)
    np.testing.assert_allclose(t2, t1, atol=1e-9)
    assert rotation_between(np.eye(3), R1) < 2.0  # the best rotation here is nearly the identity


def test_fit_rigid_matches_arun():
    rng = np.random.default_rng(4)
    P = rng.normal(0, 30, (50, 3))
    R, t = rotation_from_euler(20, -10, 5), np.array([3.0, -4.0, 5.0])
    G = P @ R.T + t + rng.normal(0, 0.1, P.shape)
    H = (P - P.mean(0)).T @ (G - G.mean(0))
    R2, t2 = _fit_rigid(np.ascontiguousarray(H), P.mean(0), G.mean(0))
    R1, t1 = rigid_fit(P, G)
    np.testing.assert_allclose(R2, R1, atol=1e-12)
    np.testing.assert_allclose(t2, t1, atol=1e-9)


def exact_mse(probe: ProbeData, gallery: GalleryIndex, result, config: ICPConfig) -> tuple[float, int]:
    """The MSE and pair count at the result's transform, recomputed with a k-d tree and the same filters."""
    p = probe.points @ result.R.T + result.t
    d, j = cKDTree(gallery.points.astype(np.float64)).query(p)
    keep = d <= config.distance_end * gallery.resolution
    keep &= ~gallery.boundary[j]
    cos = ((probe.normals @ result.R.T) * (gallery.normals[j] / 127.0)).sum(axis=1)
    keep &= cos >= np.cos(np.radians(config.max_normal_angle))
    return float(np.mean(d[keep] ** 2)), int(keep.sum())


@pytest.mark.parametrize("variant", ["point-to-point", "point-to-plane"])
def test_final_mse_is_exact_closest_point_mse(mesh, variant):
    """The voxel lookup is approximate, but the reported MSE must be that of the exact closest points (the book's
    score, plane_cap_mm = 0)."""
    config = ICPConfig(variant=variant, plane_cap_mm=0.0)
    gallery = GalleryIndex.from_scan(grid_scan(mesh), config)
    rng = np.random.default_rng(8)
    for identity in (1, 2):  # genuine and impostor
        points = random_points(face_mesh(identity), 1.0, rng)
        points = points @ rotation_from_euler(2, 1, -1).T + [1.0, -1.0, 0.5] + rng.normal(0, 0.3, points.shape)
        probe = ProbeData.build(points, None, None, config)
        result = icp(points, gallery, config)
        mse, m = exact_mse(probe, gallery, result, config)
        assert m == result.n_correspondences
        assert result.mse == pytest.approx(mse, rel=1e-9)


def test_boundary_filter_helps_partial_overlap(mesh):
    """Gallery = upper part of the face, probe = the whole face: without the boundary filter the probe's
    lower face pulls on the gallery's lower edge (point-to-point; point-to-plane barely feels the pull)."""
    upper = grid_scan(mesh)
    upper = upper.subset(upper.points[:, 1] > -15.0)
    R, t = rotation_from_euler(3, -2, 2), np.array([1.5, -2.0, 1.0])
    probe = moved_back(random_points(mesh, 1.0, np.random.default_rng(6)), R, t)
    err = {}
    for drop in (True, False):
        config = ICPConfig(drop_boundary=drop, distance_end=3.0, tolerance=1e-5, fine_iterations=10, max_iterations=80)
        err[drop] = errors(icp(probe, GalleryIndex.from_scan(upper, config), config), R, t)
    assert err[True][1] < 0.5 * err[False][1], err
    assert err[True][0] < err[False][0], err


def test_distance_filter_rejects_outliers(mesh):
    """A cluster of 300 points 6 mm in front of the cheek: kept by a fixed 10 mm threshold, dropped by the schedule."""
    rng = np.random.default_rng(9)
    gallery = grid_scan(mesh)  # resolution 1 mm
    R, t = rotation_from_euler(2, 2, -2), np.array([1.0, 1.0, -1.0])
    face = random_points(mesh, 1.0, rng)
    cheek = face[np.argmin(np.linalg.norm(face - [40.0, -20.0, -20.0], axis=1))]
    cluster = cheek + [0.0, 0.0, 6.0] + rng.normal(0, 1.0, (300, 3))
    probe = moved_back(np.vstack([face, cluster]), R, t)
    config = dict(variant="point-to-plane", fine_points=0, max_normal_angle=None)
    shrinking = ICPConfig(**config)  # 10 mm down to 2 mm
    fixed = ICPConfig(**config, distance_end=10.0)
    good = icp(probe, GalleryIndex.from_scan(gallery, shrinking), shrinking)
    bad = icp(probe, GalleryIndex.from_scan(gallery, fixed), fixed)
    assert errors(good, R, t)[1] < 0.1 < errors(bad, R, t)[1]
    d = cKDTree(gallery.points).query(probe[len(face):] @ good.R.T + good.t)[0]
    assert np.all(d > 2.0 * gallery.resolution())  # no cluster point can be a pair
    assert good.n_correspondences <= len(face)


def test_normal_and_colour_filters(mesh):
    gallery = grid_scan(mesh)
    config = ICPConfig(max_color_difference=30.0, min_overlap=0.0)
    index = GalleryIndex.from_scan(gallery.replace(colors=np.full((gallery.n_points, 3), 120, np.uint8)), config)
    points = random_points(mesh, 1.0, np.random.default_rng(1))
    colours = np.full((len(points), 3), 125, np.uint8)
    base = icp(points, index, config, probe_colors=colours)
    assert base.n_correspondences > 0.8 * config.fine_points
    colours[points[:, 0] > 0] = 200  # 80 per channel off on the face's left half
    assert icp(points, index, config, probe_colors=colours).n_correspondences < 0.7 * base.n_correspondences
    flipped = icp(points, index, config, probe_normals=-estimate_normals(points))
    assert flipped.n_correspondences < 0.01 * base.n_correspondences and flipped.mse == np.inf


def test_template_round_trip(tmp_path, mesh):
    matcher = ICPMatcher()
    template = matcher.enroll(grid_scan(mesh, 1))
    path = tmp_path / "gallery.npz"
    template.save(path)
    loaded = Template.load(path)
    assert loaded.method == "icp" and loaded.subject == "s1" and loaded.attrs == template.attrs
    probe_scan = FaceScan(random_points(mesh, 1.0, np.random.default_rng(2)) + [0.5, -0.5, 0.3])
    probe = matcher.prepare(probe_scan)
    probe.save(tmp_path / "probe.npz")
    assert matcher.score(probe, loaded) == matcher.score(Template.load(tmp_path / "probe.npz"), template)
    assert matcher.score(probe_scan, template) == matcher.score(probe, loaded)
    assert template.nbytes < 600_000


def test_identification_and_verification():
    """15 identities: gallery on the preprocessing grid, probes differently sampled, 0.3 mm noise, ≤ 5°/5 mm off."""
    rng = np.random.default_rng(11)
    meshes = [face_mesh(100 + i) for i in range(15)]
    matcher = ICPMatcher()
    gallery = [matcher.enroll(grid_scan(m, i)) for i, m in enumerate(meshes)]
    probes = []
    for m in meshes:
        R, t = rotation_from_euler(*rng.uniform(-5, 5, 3)), rng.uniform(-5, 5, 3)
        points = random_points(m, 1.0, rng) @ R.T + t
        probes.append(matcher.prepare(FaceScan(points + rng.normal(0, 0.3, points.shape))))
    S = np.array([matcher.scores(p, gallery)[0] for p in probes])
    assert [matcher.identify(p, gallery, k=3)[0][0] for p in probes] == list(range(15))
    genuine, impostor = np.diag(S), S[~np.eye(15, dtype=bool)]
    assert genuine.min() > impostor.max()
    threshold = 0.5 * (genuine.min() + impostor.max())
    assert all(matcher.verify(probes[i], gallery[i], threshold) for i in (0, 7, 14))
    assert not any(matcher.verify(probes[i], gallery[(i + 1) % 15], threshold) for i in (0, 7, 14))
    assert matcher.score(probes[3], gallery[5]) == S[3, 5]  # the fast path agrees with score()


def test_init_and_config_checks(cloud, wide_index):
    R, t = rotation_from_euler(40, 0, 0), np.array([0.0, 0.0, 60.0])  # far outside the zone of convergence
    probe = moved_back(cloud.points, R, t)
    assert icp(probe, wide_index, WIDE).mse == np.inf
    start = (rotation_from_euler(39, 0, 1), t + [1.0, 0.0, -1.0])
    rot, tra = errors(icp(probe, wide_index, WIDE, init=start), R, t)
    assert rot < 0.05 and tra < 0.02
    with pytest.raises(ValueError):
        ICPConfig(variant="plane-to-plane")
    with pytest.raises(ValueError):
        ICPConfig(distance_end=20.0)
    with pytest.raises(TypeError):
        ICPMatcher().score(Template(None, None, "icp", {}), Template(None, None, "icp", {}))


def test_capped_score_charges_probe_points_without_a_partner(mesh):
    """score_cap (× res): the score is the mean over every fine probe point of min(d, cap)², so a probe of which
    half has no partner in the gallery pays cap² for that half, where the book's MSE of the kept pairs (§8.6.1)
    sees only the half that fits and scores it like a whole face."""
    gallery_scan = grid_scan(mesh)
    whole = gallery_scan.points
    gallery_half = gallery_scan.subset(whole[:, 0] < 0)  # the gallery keeps only the face's right half
    half = gallery_half.points
    probe = grid_scan(mesh)
    kept = ICPMatcher(ICPConfig(fine_points=0, plane_cap_mm=0.0))
    capped = ICPMatcher(ICPConfig(fine_points=0, score_cap=3.0, plane_cap_mm=0.0))
    res = GalleryIndex.from_scan(gallery_half, capped.config).resolution
    # same face, all of it in the gallery: both near 0
    assert -capped.score(probe, capped.enroll(gallery_scan)) < 0.01
    # half of the probe without a partner: the kept-pairs MSE stays near 0, the capped one ≈ share × cap²
    share = np.mean(cKDTree(half).query(probe.points)[0] > 3.0 * res)
    assert share > 0.3
    assert -kept.score(probe, kept.enroll(gallery_half)) < 0.05
    assert -capped.score(probe, capped.enroll(gallery_half)) == pytest.approx(share * (3.0 * res) ** 2, rel=0.15)


def plane_capped_reference(probe_points: np.ndarray, index: GalleryIndex, R: np.ndarray, t: np.ndarray,
                           reach: float, cap: float) -> float:
    """NumPy's plane_cap_mm score: mean of min(|n_j · (x − g_j)|, cap)² over the probe points x moved by (R, t),
    j the closest gallery point (cap when it is farther than reach), n_j its stored normal made unit."""
    x = probe_points @ R.T + t
    d, j = cKDTree(index.points.astype(np.float64)).query(x)
    n = index.normals[j].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    e = np.where(d <= reach, np.abs(np.einsum("ij,ij->i", x - index.points[j], n)), cap)
    return float(np.mean(np.minimum(e, cap) ** 2))


@pytest.mark.parametrize("identity, cap_mm", [(1, 1.5), (2, 1.5), (1, 5.0)])
def test_plane_capped_score_is_the_truncated_point_to_plane_error(mesh, identity, cap_mm):
    """plane_cap_mm: the score is −mean over every fine probe point of min(e, cap)², e the distance to the tangent
    plane of its closest gallery point at ICP's final transform (cap without one within the final threshold T),
    cap = min(plane_cap_mm, T), as NumPy computes it; the alignment itself is the one of the default score."""
    gallery = grid_scan(mesh)
    probe = frontal_face(identity, pose_deg=3.0, shift_mm=2.0, noise_mm=0.3, seed=5)
    plain, capped = ICPMatcher(ICPConfig(seed=1, plane_cap_mm=0.0)), ICPMatcher(ICPConfig(seed=1, plane_cap_mm=cap_mm))
    t_plain, t_capped = plain.enroll(gallery), capped.enroll(gallery)
    a, b = plain.align(probe, t_plain), capped.align(probe, t_capped)
    np.testing.assert_allclose(a.R, b.R)
    np.testing.assert_allclose(a.t, b.t)
    index = GalleryIndex.from_template(t_capped)
    points = capped.prepare(probe).points
    reach = capped.config.distance_end * index.resolution
    assert reach < 5.0  # 1 mm faces: the final threshold bounds a 5 mm cap
    want = plane_capped_reference(points, index, b.R, b.t, reach, min(cap_mm, reach))
    assert -capped.score(probe, t_capped) == pytest.approx(want, rel=1e-6)
    assert b.mse == pytest.approx(want, rel=1e-6)


def test_plane_capped_score_bounds_what_a_coarse_sensor_keeps(mesh):
    """On a coarse sensor (8 mm depth steps: the final pair threshold is 16 mm) the kept-pairs MSE keeps flying
    pixels 12 mm off the face in its mean; the plane-capped score charges each at most cap², so the genuine face
    stays far ahead of every other person's."""
    gallery = grid_scan(mesh)
    gallery = gallery.replace(meta=dataclasses.replace(gallery.meta, extra={"quality": {"depth_step_mm": 8.0}}))
    probe = frontal_face(1, noise_mm=0.3, seed=2)
    rng = np.random.default_rng(0)
    spikes = rng.random(len(probe.points)) < 0.1
    points = probe.points.copy()
    points[spikes, 2] += rng.choice([-12.0, 12.0], spikes.sum())
    genuine = probe.replace(points=points, normals=None)
    others = [frontal_face(k, noise_mm=0.3, seed=2) for k in range(2, 7)]
    plain, capped = ICPMatcher(ICPConfig(fine_points=0, plane_cap_mm=0.0)), ICPMatcher(ICPConfig(fine_points=0))
    t_plain, t_capped = plain.enroll(gallery), capped.enroll(gallery)
    assert GalleryIndex.from_template(t_plain).resolution == pytest.approx(8.0)
    bound = spikes.mean() * 3.0**2 + 1.0  # the spikes at cap², the rest at a fraction of a mm²
    assert -plain.score(genuine, t_plain) > bound
    assert -capped.score(genuine, t_capped) < bound
    assert -capped.score(genuine, t_capped) < 0.5 * min(-capped.score(o, t_capped) for o in others)


def test_plane_cap_config_checks():
    assert ICPConfig().plane_cap_mm == 3.0
    with pytest.raises(ValueError):
        ICPConfig(plane_cap_mm=-1.0)
    with pytest.raises(ValueError):
        ICPConfig(score_cap=2.0)  # each replaces the score
    ICPConfig(score_cap=2.0, plane_cap_mm=0.0)


def test_min_overlap_makes_a_probe_that_pairs_too_few_points_no_match(mesh):
    """min_overlap: fewer final pairs than that share of the fine probe points is no match (MSE inf, score −inf),
    whatever the fit of the few pairs. A gallery that is only the face's right edge pairs a known share of a whole-face
    probe; the rule is checked either side of that share."""
    gallery = grid_scan(mesh)
    gallery = gallery.subset(gallery.points[:, 0] > 25.0)
    probe = random_points(mesh, 1.0, np.random.default_rng(2))
    base = ICPConfig(min_overlap=0.0, max_normal_angle=None)
    index = GalleryIndex.from_scan(gallery, base)
    free = icp(probe, index, base)
    n_fine = min(base.fine_points, len(probe))
    share = free.n_correspondences / n_fine
    assert np.isfinite(free.mse) and 0.05 < share < 0.5, share  # an edge strip: some pairs, not most
    below = icp(probe, index, dataclasses.replace(base, min_overlap=share - 0.02))
    above = icp(probe, index, dataclasses.replace(base, min_overlap=share + 0.02))
    assert below.n_correspondences == above.n_correspondences == free.n_correspondences
    assert below.mse == free.mse and above.mse == np.inf
    strict = ICPMatcher(dataclasses.replace(base, min_overlap=share + 0.02))
    assert strict.score(FaceScan(probe), strict.enroll(gallery)) == -np.inf
