"""Sensor profiles (Kinect v2, RealSense) and faces beyond the model in the synthetic scanner."""

import csv
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

from facerec3d.cli import main, synth
from facerec3d.datasets.synthetic import (
    IDENTITY_PROFILES,
    MANIFEST_COLUMNS,
    OCCLUDERS,
    SENSOR_PROFILES,
    DatasetConfig,
    FaceScanner,
    IdentityConfig,
    ScannerConfig,
    ScanSpec,
    identity_profile,
    plan_dataset,
    quick_scan,
    sensor_profile,
)
from facerec3d.io import load_scan

SMALL = ScannerConfig(rows=240, cols=320, focal_px=725.0)


def pixel_of(point, cfg):
    """(row, col) of a camera-frame point in a scanner's range image."""
    return (int(round((cfg.rows - 1) / 2 - cfg.focal_px * point[1] / -point[2])),
            int(round((cfg.cols - 1) / 2 + cfg.focal_px * point[0] / -point[2])))


def test_profiles_are_named_and_unknown_names_are_refused():
    assert {"frgc", "kinect-v2", "kinect-v2-8bit", "realsense"} <= set(SENSOR_PROFILES)
    with pytest.raises(ValueError, match="nope.*frgc.*kinect-v2.*realsense"):
        sensor_profile("nope")
    with pytest.raises(ValueError, match="model.*outside-model"):
        identity_profile("nope")
    choices = {p.name: list(p.type.choices) for p in synth.params if p.name in ("sensor", "identities")}
    assert choices == {"sensor": list(SENSOR_PROFILES), "identities": list(IDENTITY_PROFILES)}
    with pytest.raises(ValueError, match="unknown occluder"):
        plan_dataset(DatasetConfig(identity=IdentityConfig(occluders=("hat",))))


def test_frgc_profile_is_todays_scanner_bit_for_bit():
    assert sensor_profile("frgc") == ScannerConfig() and IDENTITY_PROFILES["model"] == IdentityConfig()
    spec = ScanSpec(subject=2, expression="smile", strength=0.8, yaw=12.0, pitch=-4.0, seed=3)
    a, b = FaceScanner(sensor_profile("frgc")).scan(spec), FaceScanner().scan(spec)
    np.testing.assert_array_equal(a.scan.points, b.scan.points)
    np.testing.assert_array_equal(a.spike, b.spike)
    assert not (a.flying.any() or a.shadow.any() or a.occluded.any())
    assert all(s.occluder is None for s in plan_dataset(DatasetConfig(subjects=3, scans=4)))


def test_kinect_v2_grid_pixel_pitch_distance_and_noise_growing_with_distance():
    cfg = sensor_profile("kinect-v2")
    s = FaceScanner(cfg).scan(ScanSpec(subject=1, seed=0))
    assert s.scan.grid_shape == (424, 512)
    nose = s.landmarks["nose_tip"]
    assert 800.0 <= -nose[2] <= 1500.0
    xyz, _ = s.scan.to_range_image()
    r, c = pixel_of(nose, cfg)
    pitch = np.nanmedian(np.diff(xyz[r - 3 : r + 4, c - 4 : c + 4, 0], axis=1))
    assert pitch == pytest.approx(-nose[2] / 365.0, rel=0.1)
    for distance, sigma in [(800.0, 0.5 + 1.0 * 0.8**2), (1500.0, 0.5 + 1.0 * 1.5**2)]:
        t = FaceScanner(replace(cfg, distance_mm=distance, distance_jitter_mm=0.0)).scan(ScanSpec(subject=1, seed=0))
        assert -t.landmarks["nose_tip"][2] == pytest.approx(distance)
        xyz, valid = t.scan.to_range_image()
        plain = valid & ~t.flying & np.isfinite(t.clean_xyz[..., 2])
        plain[t.scan.grid[t.spike, 0], t.scan.grid[t.spike, 1]] = False
        residual = xyz[plain, 2] - t.clean_xyz[plain, 2]
        assert np.std(residual) == pytest.approx(np.hypot(sigma, 1 / np.sqrt(12)), rel=0.15)  # noise and 1 mm steps


def test_kinect_8bit_depth_is_in_4mm_steps_below_1024_and_8mm_beyond():
    cfg = replace(sensor_profile("kinect-v2-8bit"), distance_mm=980.0, distance_jitter_mm=0.0)
    s = FaceScanner(cfg).scan(ScanSpec(subject=5, seed=1))
    depth = -s.scan.points[:, 2]
    near, far = depth[depth < 1024], depth[depth >= 1024]
    assert len(near) > 500 and len(far) > 500
    np.testing.assert_array_equal(near % 4, 0)
    np.testing.assert_array_equal(far % 8, 0)
    assert np.any(near % 8 == 4)  # the near steps really are 4 mm


def test_flying_pixels_lie_between_the_surfaces_of_a_depth_edge():
    cfg = sensor_profile("kinect-v2")
    s = FaceScanner(cfg).scan(ScanSpec(subject=3, pitch=10.0, seed=2))
    clean = np.pad(-s.clean_xyz[..., 2], 1, constant_values=np.nan)
    xyz, valid = s.scan.to_range_image()
    spike = np.zeros(valid.shape, bool)
    spike[s.scan.grid[s.spike, 0], s.scan.grid[s.spike, 1]] = True
    rows, cols = np.nonzero(s.flying & valid & ~spike)
    assert len(rows) > 30
    hood = np.stack([clean[rows + i, cols + j] for i in range(3) for j in range(3)])
    near, far = np.nanmin(hood, axis=0), np.nanmax(hood, axis=0)
    assert np.all(far - near > cfg.flying_jump_mm)  # on a true depth edge
    depth = -xyz[rows, cols, 2]
    tol = 3 * (cfg.noise_mm + cfg.noise_z2_mm * (far / 1000.0) ** 2) + 0.5  # 3σ of the noise, and the 1 mm step
    assert np.all((depth > near - tol) & (depth < far + tol))
    assert 0.3 < np.median((depth - near) / (far - near)) < 0.7
    # most flying pixels are off both surfaces: neither the near nor the far depth
    off = (depth - near > 3.0) & (far - depth > 3.0)
    assert off.mean() > 0.5
    # they sit on the head's outline against the torso, below the chin, too
    chin_row = pixel_of(s.landmarks["chin"], cfg)[0]
    assert np.sum(rows > chin_row) > 5


def test_realsense_occlusion_shadow_is_on_one_side_and_depth_steps_grow_with_distance():
    def missing_beside_edges(s, jump=30.0):
        d = -s.clean_xyz[..., 2]
        _, valid = s.scan.to_range_image()
        left = np.zeros(d.shape, bool)  # far pixel with a nearer surface just right of it
        left[:, :-1] = d[:, :-1] - d[:, 1:] > jump
        right = np.zeros(d.shape, bool)  # far pixel with a nearer surface just left of it
        right[:, 1:] = d[:, 1:] - d[:, :-1] > jump
        return 1 - valid[left].mean(), 1 - valid[right].mean()

    quiet = dict(n_holes=0, spike_fraction=0.0, distance_jitter_mm=0.0)
    rs_cfg = replace(sensor_profile("realsense"), distance_mm=420.0, **quiet)
    rs = FaceScanner(rs_cfg).scan(ScanSpec(subject=0, seed=0))
    frgc = FaceScanner(replace(sensor_profile("frgc"), **quiet)).scan(ScanSpec(subject=0, seed=0))
    rs_left, rs_right = missing_beside_edges(rs)
    frgc_left, _ = missing_beside_edges(frgc)
    assert rs_left > 0.75 and rs_left > rs_right + 0.4 and rs_left > frgc_left + 0.3
    # every shadow pixel has a nearer surface to its right, within the disparity range
    d = -rs.clean_xyz[..., 2]
    rows, cols = np.nonzero(rs.shadow)
    assert len(rows) > 30
    for r, c in zip(rows, cols):
        span = d[r, c + 1 : c + 1 + int(rs_cfg.focal_px * rs_cfg.stereo_baseline_mm / d[r, c]) + 2]
        assert np.nanmin(span) < d[r, c] - 3.0

    gaps = []
    for distance in (450.0, 850.0):
        cfg = replace(sensor_profile("realsense"), distance_mm=distance, **quiet)
        s = FaceScanner(cfg).scan(ScanSpec(subject=2, seed=0))
        p = s.scan.points
        depth = np.unique(-p[np.linalg.norm(p - s.landmarks["nose_tip"], axis=1) < 40.0, 2])
        gap = (depth.max() - depth.min()) / (len(depth) - 1)
        step = distance**2 * cfg.disparity_step_px / (cfg.focal_px * cfg.stereo_baseline_mm)
        assert gap == pytest.approx(step, rel=0.25)
        gaps.append(gap)
    assert gaps[1] / gaps[0] > 2.5  # (850 / 450)² ≈ 3.6


def test_deformation_is_smooth_nonlinear_of_its_amplitude_and_fixed_per_subject():
    ident = IdentityConfig(deformation_mm=3.0)
    deformed, plain = FaceScanner(identity=ident), FaceScanner()
    m = plain.model
    face = m.region == 0
    offset = deformed.face_shape(7) - plain.face_shape(7)
    size = np.linalg.norm(offset, axis=1)
    assert size[face].max() == pytest.approx(3.0) and np.median(size[face]) > 0.2
    np.testing.assert_array_equal(offset, FaceScanner(identity=ident).face_shape(7) - plain.face_shape(7))
    assert not np.allclose(deformed.face_shape(8) - plain.face_shape(8), offset, atol=0.5)
    # the expression does not change it, and the linear identity model cannot express it
    np.testing.assert_allclose(deformed.face_shape(7, "smile") - plain.face_shape(7, "smile"), offset, atol=1e-9)
    basis = m.identity_basis.astype(np.float64).reshape(len(m.identity_basis), -1).T
    coef = np.linalg.solve(basis.T @ basis, basis.T @ offset.ravel())  # least squares (normal equations)
    assert np.linalg.norm(offset.ravel() - basis @ coef) > 0.5 * np.linalg.norm(offset)
    # a wider identity spread scales the offset from the mean face
    wide = FaceScanner(identity=IdentityConfig(identity_sigma=2.0)).face_shape(7)
    np.testing.assert_allclose(wide - m.mean, 2.0 * (plain.face_shape(7) - m.mean), atol=1e-6)
    # the truth follows the deformed surface
    s = quick_scan(7, identity=ident, scanner=SMALL)
    assert cKDTree(s.scan.points).query(s.landmarks["nose_tip"])[0] < 2.0


ANCHORS = {"fringe": ("nose_bridge",), "glasses": ("left_eye_inner", "right_eye_outer"),
           "hand": ("left_mouth_corner", "right_mouth_corner", "chin")}


@pytest.mark.parametrize("occluder", OCCLUDERS)
@pytest.mark.parametrize("yaw", [0.0, -25.0])
def test_occluders_cover_their_place_but_never_the_nose_tip(occluder, yaw):
    ident = IDENTITY_PROFILES["outside-model"]
    s = quick_scan(4, yaw=yaw, pitch=8.0, seed=3, scanner=SMALL, identity=ident, occluder=occluder)
    bare = quick_scan(4, yaw=yaw, pitch=8.0, seed=3, scanner=SMALL, identity=ident)
    for name, point in bare.landmarks.items():
        np.testing.assert_array_equal(s.landmarks[name], point)  # the truth stays the head's
    assert s.occluded.sum() > 30
    seen = s.clean_xyz[s.occluded]
    assert min(np.linalg.norm(seen - s.landmarks[a], axis=1).min() for a in ANCHORS[occluder]) < 30.0
    tip = s.landmarks["nose_tip"]
    assert np.linalg.norm(seen - tip, axis=1).min() > 15.0
    r, c = pixel_of(tip, SMALL)
    assert not s.occluded[r - 2 : r + 3, c - 2 : c + 3].any()
    assert cKDTree(s.scan.points).query(tip)[0] < 2.0
    behind = s.occluded & np.isfinite(bare.clean_xyz[..., 2])
    assert np.all(s.clean_xyz[behind, 2] > bare.clean_xyz[behind, 2])  # in front of the head (Z < 0)


def test_outside_model_plan_keeps_poses_and_draws_occluders():
    plain = plan_dataset(DatasetConfig(subjects=6, scans=4, seed=1))
    wild = plan_dataset(DatasetConfig(subjects=6, scans=4, seed=1, identity=IDENTITY_PROFILES["outside-model"]))
    assert [replace(s, occluder=None) for s in wild] == plain
    assert {s.occluder for s in wild} == {None, *OCCLUDERS}


def test_the_unoccluded_profile_gives_the_outside_model_faces_with_nothing_in_front():
    cfg = DatasetConfig(subjects=6, scans=4, seed=1, identity=IDENTITY_PROFILES["outside-model"])
    bare = replace(cfg, identity=IDENTITY_PROFILES["outside-model-unoccluded"])
    assert plan_dataset(bare) == [replace(s, occluder=None) for s in plan_dataset(cfg)]
    face = dict(yaw=10.0, seed=3, scanner=SMALL)
    wild = quick_scan(4, identity=cfg.identity, **face)
    plain = quick_scan(4, identity=bare.identity, **face)
    np.testing.assert_array_equal(plain.scan.points, wild.scan.points)  # the same head
    assert not np.array_equal(plain.scan.points, quick_scan(4, **face).scan.points)  # outside the model's span


def test_cli_synth_writes_kinect_scans_with_occluders_in_the_manifest(tmp_path):
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "d"), "--subjects", "1", "--scans", "3",
                                  "--sensor", "kinect-v2", "--identities", "outside-model"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(open(tmp_path / "d" / "manifest.csv")))
    assert tuple(rows[0]) == MANIFEST_COLUMNS and MANIFEST_COLUMNS[-1] == "occluder"
    assert len(rows) == 3 and all(row["occluder"] in ("", *OCCLUDERS) for row in rows)
    for row in rows:
        scan = load_scan(tmp_path / "d" / row["path"])
        assert scan.grid_shape == (424, 512)
        nose = np.array([float(row[f"nose_tip_{a}"]) for a in "xyz"])
        assert cKDTree(scan.points).query(nose)[0] < 5.0
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "e"), "--subjects", "1", "--scans", "1",
                                  "--sensor", "realsense", "--cols", "320"])
    assert r.exit_code == 0, r.output
    assert load_scan(next((tmp_path / "e").rglob("*.abs.gz"))).grid_shape == (480, 320)
