"""Dequantisation of coarse depth steps (preprocess.denoise.dequantise), judged against the generator's true surface."""

from dataclasses import replace

import numpy as np
import pytest

from facerec3d.datasets.synthetic import FaceScanner, ScanSpec, sensor_profile
from facerec3d.errors import SettingsError
from facerec3d.preprocess.denoise import (DequantiseConfig, SmoothConfig, dequantise, quantisation_intervals,
                                          smooth_range_image)
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.preprocess.sampling import measure_sampling
from facerec3d.preprocess.spikes import SpikeConfig, remove_spikes


def _stages(profile: str, subject: int, yaw: float, distance: float = 1200.0):
    """(true scan, measured scan after spike removal, smoothed scan, depth step) of one synthetic frame."""
    scanner = FaceScanner(replace(sensor_profile(profile), distance_mm=distance, distance_jitter_mm=100.0), seed=3)
    truth = scanner.scan(ScanSpec(subject, yaw=yaw, seed=subject))
    sampling = measure_sampling(truth.scan)
    measured = remove_spikes(truth.scan, SpikeConfig(), sampling)
    smoothed = smooth_range_image(measured, *SmoothConfig().sigmas(sampling))
    return truth, measured, smoothed, sampling.depth_step_mm


def _errors(truth, scan):
    """(RMS depth error near the nose, mean depth error at the nose tip) against the true surface (mm); the
    face's overall offset is left out (a rounding offset moves the whole face, which no matcher sees)."""
    xyz, valid = scan.to_range_image()
    clean = truth.clean_xyz
    d = np.linalg.norm(np.nan_to_num(clean) - truth.landmarks["nose_tip"], axis=-1)
    near = valid & np.isfinite(clean[..., 2]) & (d < 70) & ~truth.flying
    err = xyz[..., 2] - clean[..., 2]
    offset = np.median(err[near])
    return float(np.sqrt(np.mean((err[near] - offset) ** 2))), float(np.mean(err[near & (d < 15)] - offset))


def test_8bit_depth_regains_the_nose_that_smoothing_flattens():
    rms_s, rms_d, tip_s, tip_d = [], [], [], []
    for subject, yaw in [(0, 0.0), (1, 25.0), (2, -20.0), (3, 0.0)]:
        truth, measured, smoothed, step = _stages("kinect-v2-8bit", subject, yaw)
        assert step == 8.0  # faces at ~1.2 m: the 8-bit depth's 8 mm steps
        restored = dequantise(smoothed, measured, step, truth.landmarks["nose_tip"], 95.0)
        (a, b), (c, d) = _errors(truth, smoothed), _errors(truth, restored)
        rms_s.append(a), tip_s.append(b), rms_d.append(c), tip_d.append(d)
    # smoothing alone leaves the nose tip ~5 mm behind the true surface (it lies nearer the camera: z is larger)
    assert np.mean(tip_s) < -3.5
    assert abs(np.mean(tip_d)) < 0.5 * abs(np.mean(tip_s))
    assert np.mean(rms_d) < 0.85 * np.mean(rms_s)


@pytest.mark.parametrize("yaw", [-30.0, 30.0])
def test_a_turned_face_in_8mm_steps_regains_its_nose_too(yaw):
    """A face turned 30° at ~1.4 m: the silhouette, the far cheek's steep slope and the dropouts beside them put
    many pixels next to missing ones, where the smoothing used to tell rounding from noise sees one side only. The
    rounding test looks at pixels with a whole 5 × 5 neighbourhood (the raw depth's spread is 1.34-1.39 × that of
    pure rounding on these two, 1.51-1.55 over every pixel, past the 1.5 allowed), so the steps are still found to
    dominate and the nose comes back towards the true surface."""
    truth, measured, smoothed, step = _stages("kinect-v2-8bit", 5, yaw, distance=1400.0)
    assert step == 8.0
    restored = dequantise(smoothed, measured, step, truth.landmarks["nose_tip"], 95.0)
    (rms_s, tip_s), (rms_d, tip_d) = _errors(truth, smoothed), _errors(truth, restored)
    assert tip_s < -4.0  # smoothing left the nose tip behind the true surface
    assert abs(tip_d) < 0.6 * abs(tip_s) and rms_d < 0.9 * rms_s


def test_the_restored_depth_rounds_to_what_was_measured_and_stays_on_its_ray():
    truth, measured, smoothed, step = _stages("kinect-v2-8bit", 4, 10.0)
    restored = dequantise(smoothed, measured, step, truth.landmarks["nose_tip"], 95.0)
    moved = np.linalg.norm(restored.points - smoothed.points, axis=1) > 1e-9
    assert moved.sum() > 500
    xyz_m, valid = measured.to_range_image()
    lo, hi = quantisation_intervals(xyz_m[..., 2], valid, step)
    r, c = restored.grid[moved, 0], restored.grid[moved, 1]
    z = restored.points[moved, 2]
    assert np.all((z >= lo[r, c] - 1e-6) & (z <= hi[r, c] + 1e-6))
    # each point moved along its line of sight from the camera (the origin)
    a, b = restored.points[moved], smoothed.points[moved]
    cross = np.linalg.norm(np.cross(a / np.linalg.norm(a, axis=1)[:, None], b / np.linalg.norm(b, axis=1)[:, None]),
                           axis=1)
    assert cross.max() < 1e-9


@pytest.mark.parametrize("profile", ["kinect-v2", "realsense", "frgc"])
def test_depth_without_dominant_steps_is_left_as_smoothed(profile):
    # continuous depth (laser, Kinect in whole mm under its noise) or steps under noise (RealSense's disparity)
    truth, measured, smoothed, step = _stages(profile, 5, 0.0, distance=sensor_profile(profile).distance_mm)
    restored = dequantise(smoothed, measured, step, truth.landmarks["nose_tip"], 95.0)
    assert np.array_equal(restored.points, smoothed.points)


def test_quantisation_intervals_follow_uneven_levels():
    z = np.array([[1016.0, 1020.0, 1024.0, 1032.0, 1040.0]])
    lo, hi = quantisation_intervals(z, np.ones_like(z, bool), 8.0)
    assert np.allclose(lo, [1012.0, 1018.0, 1022.0, 1028.0, 1036.0])
    assert np.allclose(hi, [1018.0, 1022.0, 1028.0, 1036.0, 1044.0])


def test_settings_are_checked_and_a_settings_file_can_turn_it_off(tmp_path):
    with pytest.raises(ValueError, match="dequantise"):
        DequantiseConfig(rounds=-1)
    (tmp_path / "off.toml").write_text("[dequantise]\nrounds = 0\n")
    assert PreprocessConfig.load(tmp_path / "off.toml").dequantise.rounds == 0
    (tmp_path / "bad.toml").write_text("[dequantise]\nrounds = -2\n")
    with pytest.raises(SettingsError, match="bad.toml: dequantise.rounds"):
        PreprocessConfig.load(tmp_path / "bad.toml")
