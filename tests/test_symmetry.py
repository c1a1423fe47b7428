"""The hidden side of a turned face completed from its mirror image, with each point's provenance kept."""

import numpy as np
import pytest

from facerec3d.datasets.synthetic import quick_scan
from facerec3d.errors import SettingsError
from facerec3d.matching.icp import ICPConfig, ICPMatcher
from facerec3d.preprocess import PreprocessConfig, Preprocessor
from facerec3d.preprocess.symmetry import SymmetryConfig
from facerec3d.scan import FILLED, MIRRORED, SEEN

MIRROR = PreprocessConfig(symmetry=SymmetryConfig("mirror"))


@pytest.fixture(scope="module")
def faces():
    """Subject 4 turned 40° (one cheek hidden), preprocessed with and without completion, and seen frontally."""
    turned = quick_scan(4, yaw=40.0, seed=2).scan
    return Preprocessor()(turned), Preprocessor(MIRROR)(turned), Preprocessor()(quick_scan(4, seed=3).scan)


def _depth(face) -> dict[tuple[int, int], float]:
    return {(int(r), int(c)): float(z) for (r, c), z in zip(face.grid, face.points[:, 2])}


def test_the_unseen_side_is_filled_from_the_seen_one_and_marked(faces):
    plain, completed, _ = faces
    assert plain.provenance is None or not (plain.provenance == MIRRORED).any()
    prov = completed.provenance
    assert (prov == MIRRORED).sum() > 0.15 * completed.n_points  # a 40° turn hides a good part of one side
    seen = {tuple(g) for g in plain.grid}
    mirrored = completed.grid[prov == MIRRORED]
    assert not any(tuple(g) in seen for g in mirrored)  # only cells the camera did not see are filled
    n = completed.grid_shape[1]
    source = {tuple(g) for g, p in zip(completed.grid, prov) if p != MIRRORED}
    assert all((r, n - 1 - c) in source for r, c in mirrored)  # each from its mirror cell
    assert set(np.unique(prov)) <= {SEEN, FILLED, MIRRORED}


def test_mirrored_depth_matches_the_true_surface(faces):
    _, completed, frontal = faces
    truth = _depth(frontal)  # the same person seen from the front: both sides
    mirrored = [(tuple(g), z) for g, z, p in zip(completed.grid, completed.points[:, 2], completed.provenance)
                if p == MIRRORED and (int(g[0]), int(g[1])) in truth]
    errors = np.abs([z - truth[(int(g[0]), int(g[1]))] for g, z in mirrored])
    assert len(errors) > 1000
    assert np.median(errors) < 2.0  # a face is nearly symmetric and the model's fit finds its plane


def test_icp_probes_align_what_was_seen_unless_told_otherwise(faces):
    _, completed, _ = faces
    seen_only = completed.subset(completed.provenance != MIRRORED)
    default, everything = ICPMatcher(), ICPMatcher(ICPConfig(probe_mirrored=True))
    np.testing.assert_array_equal(default.prepare(completed).points, default.prepare(seen_only).points)
    assert len(everything.prepare(completed).points) >= len(default.prepare(completed).points)
    assert not np.array_equal(everything.prepare(completed).points, default.prepare(completed).points)


def test_region_icp_probes_cut_what_was_seen_unless_told_otherwise(faces):
    """Region ICP's regions of a completed probe are those of what its camera saw (`ICPConfig.probe_mirrored`),
    as whole-face ICP's probe is; with probe_mirrored they take the mirrored points too."""
    from facerec3d.matching.regions import RegionICPConfig, RegionICPMatcher

    _, completed, _ = faces
    seen_only = completed.subset(completed.provenance != MIRRORED)
    default = RegionICPMatcher()
    everything = RegionICPMatcher(RegionICPConfig(icp=ICPConfig(probe_mirrored=True)))
    cut, seen, all_points = (m.prepare(f).regions for m, f in ((default, completed), (default, seen_only),
                                                                (everything, completed)))
    assert all(r is not None for r in cut)
    for a, b in zip(cut, seen):
        np.testing.assert_array_equal(a.points, b.points)
    assert any(len(b.points) > len(a.points) for a, b in zip(cut, all_points))


def test_provenance_survives_the_npz_round_trip(faces, tmp_path):
    from facerec3d.io import load_scan, save_scan

    _, completed, _ = faces
    save_scan(completed, tmp_path / "f.npz")
    back = load_scan(tmp_path / "f.npz")
    order = np.lexsort(completed.grid.T), np.lexsort(back.grid.T)
    np.testing.assert_array_equal(completed.provenance[order[0]], back.provenance[order[1]])


def test_unknown_mode_is_a_settings_error():
    with pytest.raises(SettingsError, match="symmetry.*unknown symmetry mode 'both'"):
        PreprocessConfig.from_dict({"symmetry": {"mode": "both"}}, "p.toml")
