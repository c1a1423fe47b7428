import csv

import numpy as np
import pytest
from scipy.spatial import cKDTree

from facerec3d.datasets.catalog import DatasetError, open_dataset, scan_record
from facerec3d.datasets.synthetic import DatasetConfig, FaceScanner, ScannerConfig, ScanSpec, write_dataset
from facerec3d.io import load_scan

SMALL = ScannerConfig(rows=240, cols=320, focal_px=725.0)


@pytest.fixture(scope="module")
def scanner():
    return FaceScanner()


@pytest.mark.parametrize("yaw", [-30.0, -15.0, 0.0, 15.0, 30.0])
def test_true_nose_tip_lies_on_the_scanned_surface(scanner, yaw):
    s = scanner.scan(ScanSpec(subject=int(yaw) + 40, yaw=yaw, pitch=5.0, seed=1))
    distance, _ = cKDTree(s.scan.points).query(s.landmarks["nose_tip"])
    assert distance < 2.0
    assert s.scan.points[:, 2].max() < 0  # camera frame: Z negative


def test_scans_look_like_range_scans(scanner):
    s = scanner.scan(ScanSpec(subject=1, expression="smile", yaw=10.0, seed=2))
    assert s.scan.grid_shape == (480, 640)
    assert 0.6 < s.scan.resolution() < 0.9  # mm per pixel at about 1 m
    assert s.spike.sum() > 50 and s.hole.sum() > 50
    depth = -s.scan.points[:, 2]
    assert depth.min() < 960 and depth.max() > 1100  # spikes nearer than the nose, torso and neck farther
    clean = np.isfinite(s.clean_xyz[..., 2])
    assert clean.sum() > s.scan.n_points * 0.9  # dropouts removed only a small part


def test_generator_is_deterministic_and_subjects_differ(scanner):
    a = scanner.scan(ScanSpec(subject=3, seed=0))
    b = FaceScanner().scan(ScanSpec(subject=3, seed=0))
    np.testing.assert_array_equal(a.scan.points, b.scan.points)
    c = scanner.scan(ScanSpec(subject=4, seed=0))
    assert np.linalg.norm(a.landmarks["left_eye_inner"] - a.landmarks["right_eye_inner"]) != pytest.approx(
        np.linalg.norm(c.landmarks["left_eye_inner"] - c.landmarks["right_eye_inner"]), abs=1e-6)


@pytest.mark.parametrize("fmt, layout", [("abs", "frgc"), ("bnt", "bosphorus")])
def test_dataset_layouts_round_trip(tmp_path, fmt, layout):
    manifest = write_dataset(tmp_path, DatasetConfig(subjects=2, scans=3, scanner=SMALL), fmt)
    rows = list(csv.DictReader(open(manifest)))
    assert len(rows) == 6
    # each file's name says the subject its manifest row does (bnt files were named bs000_... for subject 04200:
    # a file enrolled on its own was another person)
    assert [scan_record(tmp_path / r["path"]).subject for r in rows] == [r["subject"] for r in rows]
    manifest.unlink()  # the folder alone must be recognised by its layout
    ds = open_dataset(tmp_path)
    assert ds.layout == layout and len(ds) == 6 and len(ds.subjects) == 2
    rec = next(r for r in ds if r.path.name.endswith(rows[0]["path"].split("/")[-1]))
    scan = load_scan(rec.path)
    nose = np.array([float(rows[0][f"nose_tip_{a}"]) for a in "xyz"])
    assert cKDTree(scan.points).query(nose)[0] < 2.0
    if layout == "bosphorus":
        assert {r.expression for r in ds} >= {"neutral"}


def test_frgc_names_sessions_and_manifest_roles(tmp_path):
    for sess, name in [("Spring2003range", "02463d452.abs"), ("Fall2003range", "02463d550.abs.gz")]:
        (tmp_path / "nd1" / sess).mkdir(parents=True, exist_ok=True)
        (tmp_path / "nd1" / sess / name).write_text("")
    ds = open_dataset(tmp_path)
    assert [(r.subject, r.scan_id, r.session) for r in ds] == [
        ("02463", "02463d550", "Fall2003range"), ("02463", "02463d452", "Spring2003range")]
    m = tmp_path / "list.csv"
    m.write_text("path,subject,expression,role\nnd1/Spring2003range/02463d452.abs,s1,neutral,gallery\n"
                 "nd1/Fall2003range/02463d550.abs.gz,s1,smile,probe\n")
    ds = open_dataset(m)
    assert [r.role for r in ds] == ["gallery", "probe"]
    assert [r.expression for r in ds] == ["neutral", "non-neutral"]
    assert ds.records[0].path == tmp_path / "nd1/Spring2003range/02463d452.abs"
    m.write_text("path,who\nx.abs,1\n")
    with pytest.raises(DatasetError, match="path,subject"):
        open_dataset(m)


def test_a_training_set_from_first_subject_is_disjoint_and_expressions_are_chosen():
    from facerec3d.datasets.synthetic import plan_dataset, subject_id

    test = plan_dataset(DatasetConfig(subjects=10, scans=5))
    train = plan_dataset(DatasetConfig(subjects=10, scans=5, first_subject=1000, seed=1,
                                       expressions=("open-mouth",), expression_strength=(1.0, 1.0)))
    assert not {subject_id(s.subject) for s in test} & {subject_id(s.subject) for s in train}
    moved = [s for s in train if s.expression != "neutral"]
    assert moved and all(s.expression == "open-mouth" and s.strength == 1.0 for s in moved)
    with pytest.raises(ValueError, match="unknown expressions"):
        plan_dataset(DatasetConfig(expressions=("wink",)))
