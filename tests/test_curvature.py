"""Normals, curvature and shape index of depth maps (chapter §8.9) and the curvature-map matcher."""

import numpy as np
import pytest

from facerec3d.datasets.catalog import open_dataset
from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
from facerec3d.evaluation.run import evaluate
from facerec3d.geometry.curvature import depth_curvature
from facerec3d.matching.depthmap import depth_image, fill_nearest
from facerec3d.matching.registry import make_matcher
from facerec3d.preprocess.batch import preprocess_files
from facerec3d.preprocess.resample import ResampleConfig

SMALL = ScannerConfig(rows=320, cols=400, focal_px=1000.0)
C = np.arange(161) - 80.0
X, Y = np.meshgrid(C, -C)  # the resampling grid's layout: row 0 at y = +80 mm


@pytest.mark.parametrize("r", [40.0, 50.0, 80.0])
def test_sphere_curvature_and_normals(r):
    z = np.sqrt(np.maximum(r**2 - X**2 - Y**2, 0.0))
    c = depth_curvature(z, spacing_mm=1.0, sigma_mm=2.0)
    inner = X**2 + Y**2 < (r / 2) ** 2
    np.testing.assert_allclose(c.mean[inner], 1 / r, rtol=0.02)
    np.testing.assert_allclose(c.gaussian[inner], 1 / r**2, rtol=0.02)
    np.testing.assert_allclose(c.k1[inner], 1 / r, rtol=0.02)
    np.testing.assert_allclose(c.k2[inner], 1 / r, rtol=0.02)
    outward = np.stack([X, Y, z], axis=-1) / r
    np.testing.assert_allclose(c.normals[inner], outward[inner], atol=0.01)
    np.testing.assert_allclose(c.shape_index[inner], 1.0, atol=0.02)


@pytest.mark.parametrize("z, index, k1, k2", [
    pytest.param(-(X**2 + Y**2) / 60, 1.0, 1 / 30, 1 / 30, id="cap"),
    pytest.param((X**2 + Y**2) / 60, -1.0, -1 / 30, -1 / 30, id="cup"),
    pytest.param((X**2 - Y**2) / 60, 0.0, 1 / 30, -1 / 30, id="saddle"),
    pytest.param(-X**2 / 60, 0.5, 1 / 30, 0.0, id="ridge"),
    pytest.param(Y**2 / 60, -0.5, 0.0, -1 / 30, id="rut"),
])
def test_shape_index_of_quadrics(z, index, k1, k2):
    """Koenderink's shape index with curvature positive where convex towards the viewer (+z), at the apex."""
    c = depth_curvature(z, sigma_mm=2.0)
    assert c.shape_index[80, 80] == pytest.approx(index, abs=1e-9)
    assert c.k1[80, 80] == pytest.approx(k1, abs=1e-9) and c.k2[80, 80] == pytest.approx(k2, abs=1e-9)
    assert c.curvedness[80, 80] == pytest.approx(np.sqrt((k1**2 + k2**2) / 2), abs=1e-9)
    np.testing.assert_allclose(c.normals[80, 80], [0, 0, 1], atol=1e-12)


def test_gaps_must_be_filled():
    z = np.zeros((20, 20))
    z[3, 4] = np.nan
    with pytest.raises(ValueError, match="fill"):
        depth_curvature(z)
    filled = fill_nearest(z)
    assert filled[3, 4] == 0.0 and not np.isnan(filled).any()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """4 subjects × 2 scans (a gallery and a neutral probe each), and the cache of their preprocessing."""
    root = tmp_path_factory.mktemp("curvature")
    data = write_dataset(root / "data", DatasetConfig(subjects=4, scans=2, seed=21, scanner=SMALL), "abs").parent
    return root, data, root / "cache"


@pytest.fixture(scope="module")
def faces(dataset):
    """Preprocessed faces: subject 0 twice (its two scans), subject 1 once."""
    _, data, cache = dataset
    records = open_dataset(data).records[:3]
    assert [r.subject for r in records] == ["04200", "04200", "04201"]
    return [o.face for o in preprocess_files([r.path for r in records], cache=cache)]


def test_face_landmarks_have_the_expected_shape(faces):
    """Nose tip: a cap (S near +1, H > 0); inner eye corners: concave (S < 0), in the face's frontal frame."""
    for face in faces:
        c = depth_curvature(fill_nearest(depth_image(face)), 1.0, 2.0)
        w = ResampleConfig().half_width_mm  # the 1 mm grid spans [−w, w]
        cell = {name: (round(w - y), round(x + w)) for name, (x, y, _) in face.landmarks.items()}
        assert c.shape_index[cell["nose_tip"]] > 0.8 and c.mean[cell["nose_tip"]] > 0
        for eye in ("left_eye_inner", "right_eye_inner"):
            assert c.shape_index[cell[eye]] < -0.2


def test_curvature_matcher_scores(faces):
    matcher = make_matcher("curvature")
    assert not matcher.needs_training
    gallery = [matcher.enroll(faces[0]), matcher.enroll(faces[2])]
    same, _ = matcher.scores(faces[0], gallery)
    assert same[0] == 0.0 and same[1] < 0  # −(mean |ΔS|): 0 for identical maps
    probe, _ = matcher.scores(faces[1], gallery)
    assert probe[0] > probe[1]  # the other scan of subject 0 is nearer than subject 1
    assert matcher.score(faces[1], gallery[1]) == pytest.approx(probe[1])
    region = make_matcher("curvature", {"below_nose_mm": 0.0}).prepare(faces[0]).mask
    rows = np.flatnonzero(region.reshape(61, 61).any(axis=1))
    assert rows.max() == 30  # the rigid region stops at the nose tip's row (y = 0, 2 mm steps from y = 60)


def test_curvature_end_to_end(dataset):
    root, data, cache = dataset
    m = evaluate(data, "curvature", root / "run", jobs=1, cache=cache, progress=False)
    assert m["n_gallery"] == 4 and m["subsets"]["neutral"]["rank1"] == 1.0
    assert "train" not in m and not (root / "run" / "model.npz").exists()
