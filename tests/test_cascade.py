"""The cascade's depth screen against ground truth, and its settings."""

import numpy as np
import pytest

from facerec3d.gallery.cascade import CascadeConfig, check_cascadable, depth_descriptor, screen_distances
from facerec3d.matching.base import Matcher


def grid_points(depth) -> np.ndarray:
    """Points on a 1 mm x–y grid over ±80 mm with z = depth(x, y)."""
    x, y = np.meshgrid(np.arange(-80.0, 80.0) + 0.5, np.arange(-80.0, 80.0) + 0.5, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), depth(x, y).ravel()])


def test_descriptor_is_the_mean_depth_of_the_upper_face_cells():
    c = CascadeConfig(cell_mm=8.0, radius_mm=40.0, min_y_mm=-8.0)
    d = depth_descriptor(grid_points(lambda x, y: 2.0 * x - y + 5.0), c)
    centres = (np.arange(-5, 5) + 0.5) * 8.0  # 10 × 10 cells over ±40 mm
    cx, cy = np.meshgrid(centres, centres, indexing="ij")
    keep = (cx**2 + cy**2 <= 40.0**2) & (cy >= -8.0)
    np.testing.assert_allclose(d, (2.0 * cx - cy + 5.0)[keep], atol=1e-9)  # a plane's cell mean = its centre value
    half = grid_points(lambda x, y: np.where(x < 0, np.nan, 1.0))
    d = depth_descriptor(half[np.isfinite(half[:, 2])], c)  # no points left of the nose: empty cells are NaN
    assert np.array_equal(np.isnan(d), (cx < 0)[keep])


def test_screen_distance_ignores_a_shift_and_the_worst_cells():
    rng = np.random.default_rng(0)
    probe = rng.normal(0.0, 5.0, 200)
    shifted = probe + 3.0  # same face, z offset
    moved = probe.copy()
    moved[:30] += rng.uniform(5.0, 10.0, 30)  # 15 % of the cells changed (an expression)
    other = rng.normal(0.0, 5.0, 200)
    sparse = np.full(200, np.nan)
    sparse[:7] = probe[:7]  # 7 cells in common: too few
    gallery = np.array([shifted, moved, other, sparse])
    d = screen_distances(probe, gallery, keep=0.8)
    assert d[0] == pytest.approx(0.0, abs=1e-12) and d[1] == pytest.approx(0.0, abs=1e-12)
    assert d[2] > 10.0 and d[3] == np.inf
    full = screen_distances(probe, gallery, keep=1.0)
    expected = np.mean((moved - probe - np.median(moved - probe)) ** 2)
    assert full[1] == pytest.approx(expected)  # keep 1: every common cell counts


def _numpy_screen(probe, gallery, keep):
    """The screen distance as NumPy says it (nanmedian, sort, cumsum): the compiled one must give it to the bit."""
    d = gallery - probe
    common = ~np.isnan(d)
    w = common.sum(axis=1)
    with np.errstate(invalid="ignore"):
        shift = np.nanmedian(np.where(w[:, None] > 0, d, 0.0), axis=1, keepdims=True)
    r = np.sort(np.where(common, (d - shift) ** 2, np.inf), axis=1)
    k = np.maximum((w * keep).astype(np.int64), 1)
    total = np.cumsum(np.where(np.isfinite(r), r, 0.0), axis=1)[np.arange(len(r)), k - 1]
    return np.where(w >= 8, total / k, np.inf)


@pytest.mark.parametrize("keep", [0.8, 1.0, 0.05])
def test_screen_distance_is_numpys_to_the_bit(keep):
    rng = np.random.default_rng(1)
    probe = rng.normal(0.0, 5.0, 244)
    probe[rng.random(244) < 0.05] = np.nan
    gallery = probe + rng.normal(0.0, 2.0, (300, 244))
    for i, share in enumerate(np.linspace(0.0, 1.0, 300)):  # from no common cell to all of them
        gallery[i, rng.random(244) < share] = np.nan
    gallery[5, :] = probe  # odd and even counts, exact zeros and ties
    gallery[6, ::2] = np.round(gallery[6, ::2])
    ours, numpys = screen_distances(probe, gallery, keep), _numpy_screen(probe, gallery, keep)
    assert np.isinf(ours).sum() > 10 and np.isfinite(ours).sum() > 200
    assert np.array_equal(ours, numpys)


def test_settings_are_checked():
    with pytest.raises(ValueError, match="shortlist"):
        CascadeConfig(shortlist=0)
    with pytest.raises(ValueError, match="keep"):
        CascadeConfig(keep=0.0)

    class Other(Matcher):
        name = "other"

        def enroll(self, scan):
            raise NotImplementedError

        def score(self, probe, template):
            raise NotImplementedError

    with pytest.raises(ValueError, match="icp method"):
        check_cascadable(Other())
