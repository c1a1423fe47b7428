"""PCA normals and boundary points used by ICP (geometry/normals.py)."""

import numpy as np
import pytest

from facerec3d import FaceScan
from facerec3d.geometry.normals import boundary_mask, estimate_normals


def plane_scan(rows=30, cols=40, spacing=1.0) -> FaceScan:
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    x, y = c * spacing, -r * spacing
    z = 0.3 * x + 0.1 * y
    return FaceScan.from_range_image(np.stack([x, y, z], axis=-1))


def test_plane_normals_grid_and_gridless():
    scan = plane_scan()
    truth = np.array([-0.3, -0.1, 1.0]) / np.linalg.norm([-0.3, -0.1, 1.0])
    for n in (estimate_normals(scan.points, grid=scan.grid, grid_shape=scan.grid_shape), estimate_normals(scan.points)):
        np.testing.assert_allclose(n, np.broadcast_to(truth, n.shape), atol=1e-9)
    below = estimate_normals(scan.points, viewpoint=[0.0, 0.0, -100.0])
    np.testing.assert_allclose(below, np.broadcast_to(-truth, below.shape), atol=1e-9)


def test_sphere_normals_towards_viewpoint():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    points = 50.0 * d + [1.0, 2.0, 3.0]
    n = estimate_normals(points, k=12, viewpoint=[1.0, 2.0, 3.0])  # from the centre: inward
    assert np.median((n * -d).sum(axis=1)) > 0.999 and np.all((n * -d).sum(axis=1) > 0.9)


def test_few_neighbours_face_the_view_direction():
    xyz = np.full((5, 5, 3), np.nan)
    xyz[2, 2] = [0.0, 0.0, 5.0]
    scan = FaceScan.from_range_image(xyz)
    normals = estimate_normals(scan.points, grid=scan.grid, grid_shape=scan.grid_shape)
    np.testing.assert_array_equal(normals, [[0, 0, 1]])


def test_boundary_on_grid_is_the_incomplete_8_neighbourhood():
    scan = plane_scan(10, 12)
    keep = ~((scan.grid[:, 0] == 5) & (scan.grid[:, 1] == 6))  # a one-pixel hole
    scan = scan.subset(keep)
    b = boundary_mask(scan.points, grid=scan.grid, grid_shape=scan.grid_shape)
    r, c = scan.grid[:, 0], scan.grid[:, 1]
    rim = (r == 0) | (r == 9) | (c == 0) | (c == 11)
    hole_edge = (np.abs(r - 5) <= 1) & (np.abs(c - 6) <= 1)
    np.testing.assert_array_equal(b, rim | hole_edge)


@pytest.mark.parametrize("seed", [0, 1])
def test_boundary_without_grid_finds_the_rim_of_a_disc(seed):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-30, 30, (8000, 2))
    xy = xy[np.linalg.norm(xy, axis=1) < 30]
    points = np.c_[xy, 0.01 * (xy**2).sum(axis=1)]  # a shallow cap, ~2.8 points / mm²
    b = boundary_mask(points)
    r = np.linalg.norm(xy, axis=1)
    assert b[r > 29.6].mean() > 0.85  # the outermost ~0.6 spacing
    assert b[r < 26].mean() < 0.03


def test_least_eigenvector_agrees_with_lapack():
    """The compiled 3 × 3 eigensolver behind the PCA normals gives LAPACK's least eigenvector (up to sign) on
    random covariances over twelve orders of magnitude, and a unit vector for degenerate ones."""
    from facerec3d.geometry.normals import least_eigenvector

    rng = np.random.default_rng(4)
    for _ in range(500):
        A = rng.normal(size=(3, 3))
        A = A @ A.T * 10.0 ** rng.uniform(-6, 6)
        w, V = np.linalg.eigh(A)
        e = least_eigenvector(A)
        assert abs(abs(e @ V[:, 0]) - 1.0) < 1e-9
    for A in (np.zeros((3, 3)), np.eye(3), np.diag([3.0, 1.0, 2.0]), np.diag([2.0, 2.0, 0.5])):
        e = least_eigenvector(A)
        assert np.linalg.norm(e) == pytest.approx(1.0)
        assert e @ A @ e == pytest.approx(np.linalg.eigvalsh(A)[0])


@pytest.mark.parametrize("seed", [0, 1])
def test_within_ball_selects_exactly_the_points_numpy_selects(seed):
    """The compiled ball test replaces `np.linalg.norm(points - centre, axis=1) <= radius` in the face detector; the
    detections stay the same only if it selects the very same points, those lying on the sphere included."""
    from facerec3d.geometry.ball import within_ball

    rng = np.random.default_rng(seed)
    centre = rng.normal(0, 10, 3)
    points = rng.normal(0, 60, (5000, 3))
    on_sphere = centre + 55.0 * points[:1000] / np.linalg.norm(points[:1000], axis=1, keepdims=True)
    points = np.concatenate([points, on_sphere, np.round(points[:1000])])
    for radius in (0.0, 10.0, 55.0, 1e6):
        expected = np.linalg.norm(points - centre, axis=1) <= radius
        got = within_ball(points, centre, radius)
        assert got.dtype == bool and got.shape == expected.shape
        assert np.array_equal(got, expected), radius
    assert 0 < within_ball(points, centre, 55.0).sum() < len(points)


def test_a_ball_index_lists_exactly_the_points_within_ball_selects():
    """`BallIndex.within` (the detector's points near each placement, bucketed once per scan) gives the indices of
    exactly the points `within_ball` selects, in order: on a 1 mm lattice, where many points lie on the sphere;
    with points that are not finite or lie 10^15 mm out (whose cells are then coarse, so memory stays bounded);
    for centres inside, beside and far from the cloud, and radii of 0, negative, huge, infinite and NaN."""
    from facerec3d.geometry.ball import BallIndex, within_ball

    rng = np.random.default_rng(5)
    lattice = np.round(rng.normal(0, 40, (20000, 3)))
    odd = lattice.copy()
    odd[[3, 9, 27]] = [[np.nan, 0, 0], [np.inf, 1, 2], [1e15, -1e15, 0]]
    for points in (lattice, odd):
        index = BallIndex(points)
        assert index.start[-1] == len(points) and index.dims.prod() <= 1024**2
        centres = [p for p in rng.normal(0, 40, (30, 3))] + [np.zeros(3), np.array([500.0, 0, 0]),
                                                             np.array([np.nan, 0, 0]), np.array([1e15, -1e15, 0])]
        for centre in centres:
            for radius in (0.0, -1.0, 7.0, 30.0, 56.0, 1e300, np.inf, np.nan):
                expected = np.flatnonzero(within_ball(points, centre, radius))
                assert np.array_equal(index.within(centre, radius), expected), (centre, radius)
    assert 100 < len(BallIndex(lattice).within(np.zeros(3), 30.0)) < len(lattice)


def test_nearest_index_is_numpys_argmin_of_the_distances_first_of_equals():
    from facerec3d.geometry.ball import nearest_index

    rng = np.random.default_rng(3)
    points = np.round(rng.normal(0, 30, (3000, 3)))  # on a 1 mm lattice: many equal distances
    for centre in rng.normal(0, 30, (50, 3)).tolist() + [[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]:
        assert nearest_index(points, centre) == int(np.argmin(np.linalg.norm(points - centre, axis=1)))
