"""Keypoints and local features (chapter §8.10.2): repeatability against ground truth, matching, config, save/load."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from facerec3d.config import read_settings
from facerec3d.datasets.synthetic import ScannerConfig, quick_scan
from facerec3d.geometry.transforms import rigid_fit
from facerec3d.matching.base import Template
from facerec3d.matching.keypoints import KeypointConfig, KeypointMatcher, detect_keypoints, match_keypoints
from facerec3d.matching.registry import load_matcher, make_matcher
from facerec3d.preprocess import Preprocessor
from tests.conftest import model_face

SMALL = ScannerConfig(rows=320, cols=400, focal_px=1000.0)


@pytest.fixture(scope="module")
def two_scans():
    """Two scans of subject 5 (frontal, and 12° yaw with other noise), preprocessed, and the true map from
    the first's frontal frame to the second's, from the generator's fiducials in scan coordinates."""
    faces, truth = [], []
    for yaw, seed in ((0.0, 0), (12.0, 1)):
        s = quick_scan(5, "neutral", yaw=yaw, seed=seed, scanner=SMALL)
        faces.append(Preprocessor()(s.scan))
        truth.append(np.stack([s.landmarks[k] for k in sorted(s.landmarks)]))
    R, t = rigid_fit(truth[0], truth[1])  # scan A -> scan B (the same face, moved rigidly)
    MA, MB = (np.asarray(f.meta.extra["to_frontal"]) for f in faces)

    def a_to_b(p):
        in_a = (p - MA[:, 3]) @ MA[:, :3]  # frontal A -> scan A
        return (in_a @ R.T + t) @ MB[:, :3].T + MB[:, 3]

    return faces, a_to_b


def test_keypoints_are_repeatable(two_scans):
    (a, b), a_to_b = two_scans
    ka, _ = detect_keypoints(a)
    kb, _ = detect_keypoints(b)
    assert len(ka) >= 10 and len(kb) >= 10
    d = cKDTree(kb).query(a_to_b(ka))[0]
    repeat = np.mean(d <= 4.0)  # Mian et al. 2008's criterion: within 4 mm
    # control: as many random points of the same face are "repeated" far less often
    rng = np.random.default_rng(0)
    random = a.points[rng.choice(a.n_points, len(ka), replace=False)]
    chance = np.mean(cKDTree(kb).query(a_to_b(random))[0] <= 4.0)
    assert repeat >= 0.6 and repeat > 2 * chance


def test_matching_same_face_beats_other_faces(two_scans):
    (a, b), _ = two_scans
    m = KeypointMatcher()
    others = [model_face(s) for s in (1, 2, 3)]
    s, tiebreak = m.scores(a, [m.enroll(f) for f in [b, *others]])
    assert s[0] > s[1:].max() and np.all(tiebreak <= 0)


def test_ransac_counts_consistent_matches():
    """Ten keypoints moved rigidly, three of them then displaced by 10 mm: seven consistent matches."""
    rng = np.random.default_rng(3)
    p = rng.uniform(-40, 40, (10, 3))
    desc = rng.normal(size=(10, 64)).astype(np.float32)
    c, s = np.cos(np.radians(5)), np.sin(np.radians(5))
    g = p @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [1.0, -2.0, 0.5]
    g[:3] += [10.0, 0.0, 0.0]
    n, rms = match_keypoints(p, desc, g, desc, KeypointConfig(max_offset=20.0, ransac_iterations=200))
    assert n == 7 and rms < 1e-6


def test_config_toml_round_trip_and_save_load(tmp_path, two_scans):
    (a, b), _ = two_scans
    path = tmp_path / "keypoints.toml"
    path.write_text("radius = 6\npatch_bins = 6\nmax_keypoints = 40\n")
    m = make_matcher("keypoints", read_settings(path))
    assert m.config == KeypointConfig(radius=6, patch_bins=6, max_keypoints=40)
    t = m.enroll(b)
    assert t.arrays["descriptors"].shape[1] == 36 and len(t.arrays["points"]) <= 40
    m.save(tmp_path / "model.npz")
    back = load_matcher(tmp_path / "model.npz")
    t.save(tmp_path / "t.npz")
    assert back.config == m.config
    assert back.score(a, Template.load(tmp_path / "t.npz")) == m.score(a, t)
    with pytest.raises(ValueError):
        KeypointConfig(patch_bins=1)
