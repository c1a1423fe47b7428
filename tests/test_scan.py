import numpy as np

from facerec3d import FaceScan
from facerec3d.geometry.transforms import rigid_fit, rotation_angle, rotation_from_euler
from tests.conftest import cap_image


def test_range_image_round_trip(cap):
    xyz, valid = cap.to_range_image()
    assert valid.sum() == cap.n_points == 12 * 16 - 3
    back = FaceScan.from_range_image(xyz, valid)
    np.testing.assert_array_equal(back.points, cap.points)
    np.testing.assert_array_equal(back.grid, cap.grid)
    assert np.isnan(xyz[5, 7]).all()


def test_a_window_holds_the_same_pixels_and_stops_at_the_grid_edge():
    xyz = np.zeros((40, 50, 3))
    valid = np.zeros((40, 50), bool)
    valid[1:6, 30:48] = True  # 1 pixel from the top edge, 2 from the right
    xyz[..., 2] = np.arange(40 * 50).reshape(40, 50)  # each pixel's depth names it
    scan = FaceScan.from_range_image(xyz, valid)
    for margin, origin, shape in ((0, (1, 30), (5, 18)), (3, (0, 27), (9, 23))):
        window, lo = scan.windowed(margin)
        assert lo.tolist() == list(origin) and window.grid_shape == shape
        z, ok = window.to_range_image()
        assert ok.sum() == valid.sum()
        assert np.array_equal(z[ok][:, 2], xyz[valid][:, 2])  # the same pixels, in the same places
        assert np.array_equal(np.argwhere(ok) + lo, np.argwhere(valid))
    assert np.array_equal(scan.windowed(2)[0].triangles(), scan.triangles())


def test_triangles_skip_invalid_pixels_and_long_edges():
    scan = cap_image(invalid=())
    full = scan.triangles()
    assert len(full) == 2 * 11 * 15
    holed = cap_image(invalid=((5, 7),))
    assert len(holed.triangles()) == len(full) - 6  # an inner pixel touches six triangles
    xyz, valid = scan.to_range_image()
    xyz[:, 8:, 2] += 50.0  # a depth discontinuity between columns 7 and 8
    stepped = FaceScan.from_range_image(xyz, valid)
    assert len(stepped.triangles()) == len(full) - 2 * 11



def test_triangles_are_each_whole_block_half_in_order():
    """Every triangle's three pixels are valid, 2x2-block neighbours and no edge is longer than the limit; every
    block whose two halves qualify gives both, the upper (a, c, b) halves first, each group in row-major order."""
    rng = np.random.default_rng(4)
    xyz = np.dstack([*np.meshgrid(np.arange(30.0), np.arange(20.0)), rng.normal(0, 0.8, (20, 30))])
    valid = rng.random((20, 30)) > 0.2
    scan = FaceScan.from_range_image(xyz, valid)
    idx = scan.index_image()
    P = scan.points
    ok = lambda i, j: i >= 0 and j >= 0 and np.linalg.norm(P[i] - P[j]) <= 1.6
    upper, lower = [], []
    for r in range(19):
        for c in range(29):
            a, b, cc, d = idx[r, c], idx[r, c + 1], idx[r + 1, c], idx[r + 1, c + 1]
            if ok(a, cc) and ok(cc, b) and ok(b, a):
                upper.append((a, cc, b))
            if ok(b, cc) and ok(b, d) and ok(d, cc):
                lower.append((b, cc, d))
    expected = np.array(upper + lower, dtype=np.int64)
    got = scan.triangles(max_edge=1.6)
    assert 0 < len(upper) and 0 < len(lower) and len(expected) < 2 * 19 * 29  # some blocks are cut by the limit
    assert got.dtype == np.int64 and np.array_equal(got, expected)
    assert len(scan.triangles(max_edge=float("nan"))) == 0


def test_column_bounds_are_numpys_column_min_and_max():
    from facerec3d.scan import column_bounds

    rng = np.random.default_rng(1)
    for a in (rng.normal(size=(1000, 3)), rng.integers(-50, 50, (77, 2)).astype(np.int32), rng.normal(size=(1, 3))):
        lo, hi = column_bounds(a)
        assert lo.dtype == a.dtype and np.array_equal(lo, a.min(axis=0)) and np.array_equal(hi, a.max(axis=0))
    with_nan = rng.normal(size=(10, 3))
    with_nan[4, 1] = np.nan
    assert np.isnan(column_bounds(with_nan)[0][1]) and np.isnan(column_bounds(with_nan)[1][1])
    for bad in (np.zeros((0, 3)), np.zeros(5)):
        try:
            column_bounds(bad)
        except ValueError as e:
            assert "non-empty 2-D" in str(e)
        else:
            raise AssertionError(f"column_bounds of shape {bad.shape} did not refuse")

def test_transformed_moves_points_normals_and_landmarks(cap):
    R = rotation_from_euler(20, -10, 5)
    t = np.array([1.0, 2.0, 3.0])
    scan = cap.replace(normals=np.tile([0, 0, 1.0], (cap.n_points, 1)), landmarks={"nose_tip": cap.points[0]})
    moved = scan.transformed(R, t)
    np.testing.assert_allclose(moved.points, cap.points @ R.T + t)
    np.testing.assert_allclose(moved.normals[0], R @ [0, 0, 1.0])
    np.testing.assert_allclose(moved.landmarks["nose_tip"], moved.points[0])


def test_rigid_fit_recovers_motion_and_handles_reflection():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(50, 3))
    R = rotation_from_euler(15, 5, -7)
    R2, t2 = rigid_fit(P, P @ R.T + [3, 2, 1])
    assert rotation_angle(R2 @ R.T) < 1e-8
    np.testing.assert_allclose(t2, [3, 2, 1], atol=1e-9)
    # a mirrored target: the raw SVD solution has det -1; the fit must stay a rotation
    R3, _ = rigid_fit(P, P * [1, 1, -1])
    assert np.isclose(np.linalg.det(R3), 1.0)


def test_resolution_of_a_grid_is_the_median_spacing_to_the_nearest_of_8_neighbouring_pixels():
    """`FaceScan.resolution` on a grid: the median over (a seeded sample of 20,000 of) the points of the distance to
    the nearest point among its 8 neighbouring pixels, here against NumPy's shifted images. The face is a window
    of a large frame with holes, so the compiled search's own window and its edges are exercised."""
    rng = np.random.default_rng(3)
    h, w = 200, 180
    rows, cols = np.mgrid[0:h, 0:w]
    xyz = np.dstack([cols * 0.9, rows * 1.1, 5 * np.sin(cols / 17.0) + rng.normal(0, 0.3, (h, w))])
    valid = rng.random((h, w)) > 0.25
    valid[:, :3] = False  # empty columns at the window's left
    frame = np.full((480, 640, 3), np.nan)
    frame[100:100 + h, 300:300 + w] = xyz
    big = np.zeros((480, 640), bool)
    big[100:100 + h, 300:300 + w] = valid
    scan = FaceScan.from_range_image(frame, big)
    assert scan.n_points > 20000  # the sampled path

    index = scan.index_image()
    pad = np.pad(index, 1, constant_values=-1)
    best = np.full(scan.n_points, np.inf)
    r, c = scan.grid[:, 0] + 1, scan.grid[:, 1] + 1
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            j = pad[r + dr, c + dc]
            if dr or dc:
                d2 = np.where(j >= 0, ((scan.points[np.maximum(j, 0)] - scan.points) ** 2).sum(axis=1), np.inf)
                best = np.minimum(best, d2)
    sample = np.random.default_rng(0).choice(scan.n_points, 20000, replace=False)
    expected = np.sqrt(np.median(best[sample][np.isfinite(best[sample])]))
    assert scan.resolution() == expected


def test_points_of_another_shape_are_refused_not_reshaped():
    """An (N, 2) array of N divisible by 3 was silently reshaped into other points: (3, 2) became 2 points."""
    import pytest

    from facerec3d.scan import FaceScan

    for shape in ((3, 2), (2, 6), (4, 3, 1)):
        with pytest.raises(ValueError, match=r"points must be an \(N, 3\) array"):
            FaceScan(np.zeros(shape))
    assert FaceScan(np.zeros((5, 3))).n_points == 5 and FaceScan(np.zeros(0)).n_points == 0
