"""Meshes and point clouds of any density, in any frame (issue: a 3.8 mm stereo mesh gave 'only 0 valid points').

The generator's faces are exported as OBJ meshes and PLY point clouds with 1–4 mm between vertices, each turned
into a random frame; preprocessing must find every face, put the nose tip where the generator put it, and
identify them as well as the same faces given as range images."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facerec3d.datasets.synthetic import (DatasetConfig, FaceScanner, ScanSpec, export_surface, plan_dataset,
                                          quick_scan, random_frame, sensor_profile)
from facerec3d.geometry.transforms import rotation_from_euler
from facerec3d.io import load_scan, save_scan
from facerec3d.matching.registry import make_matcher
from facerec3d.preprocess import Preprocessor, gridify, landmarks_in_input_frame
from facerec3d.preprocess.orient import orient
from facerec3d.preprocess.resample import point_spacing
from facerec3d.scan import FaceScan

SUBJECTS = 4


def _scans():
    """Per subject a gallery scan (neutral) and a probe scan (another session: other noise, turned 12°)."""
    return ([quick_scan(s, seed=100 + s) for s in range(SUBJECTS)],
            [quick_scan(s, seed=200 + s, yaw=12.0 if s % 2 else -12.0) for s in range(SUBJECTS)])


@pytest.fixture(scope="module")
def synthetic():
    gallery, probes = _scans()
    return gallery, probes, _rank1([g.scan for g in gallery], [p.scan for p in probes])


def _rank1(gallery: list[FaceScan], probes: list[FaceScan]) -> float:
    pre, icp = Preprocessor(), make_matcher("icp")
    templates = [icp.enroll(pre(g)) for g in gallery]
    hits = [int(np.argmax(icp.scores(icp.prepare(pre(p)), templates)[0])) == s for s, p in enumerate(probes)]
    return float(np.mean(hits))


def _export(syn, spacing: float, mesh: bool, seed: int, folder) -> tuple[FaceScan, np.ndarray]:
    """The scan written as an OBJ mesh or a PLY point cloud in a random frame and read back; its true nose tip."""
    R, t = random_frame(seed)
    path = folder / f"{seed}.{'obj' if mesh else 'ply'}"
    save_scan(export_surface(syn.scan, spacing, mesh=mesh, rotation=R, translation=t), path)
    return load_scan(path), R @ syn.landmarks["nose_tip"] + t


# Every spacing, and meshes and point clouds, each at two spacings (the full 4 × 2, on 20 people, is
# `benchmarks/mesh_bench.py`; here one case costs 20–120 s of CI time, the 1 mm ones the most)
@pytest.mark.slow
@pytest.mark.parametrize(("spacing", "mesh"), [(1.0, False), (2.0, True), (3.0, False), (4.0, True)],
                         ids=["points-1.0", "mesh-2.0", "points-3.0", "mesh-4.0"])
def test_any_density_any_frame_acquires_locates_and_identifies(synthetic, spacing, mesh, tmp_path):
    gallery, probes, range_rank1 = synthetic
    scans, errors = [], []
    for k, syn in enumerate(gallery + probes):
        scan, nose = _export(syn, spacing, mesh, seed=int(spacing * 1000) + 2 * k + mesh, folder=tmp_path)
        assert scan.grid is None and (scan.mesh is not None) == mesh
        assert point_spacing(scan.points) == pytest.approx(spacing, rel=0.35)
        face = Preprocessor()(scan)  # raises FailureToAcquire: no failure is allowed
        errors.append(np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - nose))
        scans.append(scan)
    assert max(errors) <= 10.0, f"nose tip errors (mm): {np.round(errors, 1)}"
    assert _rank1(scans[:SUBJECTS], scans[SUBJECTS:]) >= range_rank1 - 0.02


def test_view_direction_and_head_up_are_found_in_any_frame():
    syn = quick_scan(3, seed=5)
    seen_from, up = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])  # the synthetic camera looks along -z
    for seed in range(4):
        R = Rotation.random(random_state=seed).as_matrix()
        for mesh in (True, False):
            turned, how = orient(export_surface(syn.scan, 2.0, mesh=mesh, rotation=R))
            angle = np.degrees(np.arccos(np.clip(how.view @ (R @ seen_from), -1, 1)))
            assert angle < 20.0, (seed, mesh, angle)
            head = how.R @ R @ up  # the head's vertical axis after the turn: up, within the head's own pose
            assert head[1] > np.cos(np.radians(25.0)), (seed, mesh, head)


def test_mesh_is_rasterised_from_triangles_without_gaps():
    """A 3.8 mm mesh becomes a range image at its own pitch whose face has no lattice of empty cells."""
    syn = quick_scan(1, seed=1)
    coarse = export_surface(syn.scan, 3.8, mesh=True)
    grid = gridify(coarse)
    assert grid.resolution() == pytest.approx(point_spacing(coarse.points), rel=0.05)
    xyz, valid = grid.to_range_image()
    nose = syn.landmarks["nose_tip"]
    near = np.linalg.norm(xyz[..., :2] - nose[:2], axis=-1) <= 40.0  # the middle of the face, seen whole
    assert valid[near].mean() > 0.99
    vertices_only = gridify(coarse.replace(mesh=None), resolution_mm=0.7)  # the old way: vertices gridded finely
    xyz, valid = vertices_only.to_range_image()
    near = np.linalg.norm(np.nan_to_num(xyz[..., :2]) - nose[:2], axis=-1) <= 40.0
    assert valid[near].mean() > 0.99  # point clouds are triangulated too, so they fill the finer grid as well


def test_the_turn_is_recorded_and_landmarks_map_back(tmp_path):
    syn = quick_scan(2, seed=3)
    scan, nose = _export(syn, 2.0, True, seed=11, folder=tmp_path)
    face = Preprocessor()(scan)
    view = face.meta.extra["view"]
    assert view["turned"] is True and len(view["direction"]) == 3
    assert np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - nose) < 10.0
    frame = Preprocessor()(syn.scan)  # a range image in its camera's frame is never turned
    assert "view" not in frame.meta.extra


def test_a_mesh_is_not_turned_upside_down_onto_its_chin(tmp_path):
    """`benchmarks/mesh_bench.py` on 20 people found this mesh (3 mm, one of 40) turned 159°: the mean face fitted
    upside down on the chin and neck held more points (56 %) than the right placement on the nose (46 %), and the
    detector then put the nose 87 mm off. The upright fit now puts the placements that show a nose first."""
    syn = quick_scan(17, seed=117)
    scan, nose = _export(syn, 3.0, True, seed=3035, folder=tmp_path)
    face = Preprocessor()(scan)
    assert np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - nose) <= 10.0


# `benchmarks/mesh_bench.py` cases (20 people; frgc unless said): (sensor, subject, scan seed, yaw, spacing, mesh,
# export seed). With the full fits ranked by inlier share alone, the 4 mm mesh was turned 109° off: a wrong
# placement and the right one both fitted 100 % of the points, the right one with a likelier face (the identity
# prior: `detect.placement_score`); the true nose of the first 1 mm mesh is the third nose candidate (two were
# tried); with three candidates the second 1 mm mesh's true placement was the fifth rigid fit (four got a full fit),
# and the Kinect-quality cloud's the fifth distinct one, behind a wrong roll of its own candidate. With 50 people,
# one probe seen 34° (2 mm mesh) and 32° (4 mm points) off +z, its view misjudged as 28–29°, kept its frame: there
# the mesh showed no nose (the face seen from behind won, then failed to acquire) and the points fitted upside down.
@pytest.mark.parametrize(("sensor", "subject", "seed", "yaw", "spacing", "mesh", "export"),
                         [("frgc", 8, 108, 0.0, 4.0, True, 4017), ("frgc", 0, 200, -12.0, 1.0, True, 1041),
                          ("frgc", 17, 117, 0.0, 1.0, True, 1035), ("kinect-v2", 17, 217, 12.0, 3.0, False, 3074),
                          ("frgc", 19, 219, 12.0, 2.0, True, 2139), ("frgc", 19, 219, 12.0, 4.0, False, 4138)],
                         ids=["4mm-tie", "1mm-third-candidate", "1mm-fifth-rigid-fit", "kinect-3mm-fifth-distinct",
                              "2mm-seen-34deg-off", "4mm-points-seen-32deg-off"])
def test_a_surface_is_turned_head_up_where_wrong_placements_fit_as_well(sensor, subject, seed, yaw, spacing, mesh,
                                                                        export, tmp_path):
    syn = FaceScanner(sensor_profile(sensor)).scan(ScanSpec(subject, yaw=yaw, seed=seed))
    scan, nose = _export(syn, spacing, mesh, seed=export, folder=tmp_path)
    face = Preprocessor()(scan)
    assert np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - nose) <= 10.0


def test_a_kinect_quality_point_cloud_is_not_placed_on_its_cheek(tmp_path):
    """`benchmarks/mesh_bench.py --sensor kinect-v2 --spacings 4` found this point cloud (one of 40) with its nose
    78 mm off: the rigid mean face, turned upside down 63 mm from the nose, fitted 60 % of the noisy points and
    showed a "nose", the true placement 45 %. The best rigid placements are now fitted fully before one is chosen
    (the true one then fits 99 %, the wrong one 93 %)."""
    syn = FaceScanner(sensor_profile("kinect-v2")).scan(ScanSpec(17, seed=117))
    scan, nose = _export(syn, 4.0, False, seed=4034, folder=tmp_path)
    face = Preprocessor()(scan)
    assert np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - nose) <= 10.0


def test_a_point_cloud_moved_anywhere_is_turned_head_up_the_same_way():
    """A tester's Kinect v2 frame (04203/front_2.png of `facerec3d synth frames --sensor kinect-v2 --format png
    --subjects 5 --scans 3`) as a point cloud was found upright; moved 1 mm along x, or 10⁶ mm along every axis, it
    was turned upside down (roll −178° and 169°), passed detection on its chin and matched another person. The
    upright fit works on the cloud thinned and rasterised on cells of its spacing: `front_points` counted those cells
    from the frame's origin, so a move changed the points kept and the fit, and Qhull triangulated coordinates
    10⁶ mm out imprecisely. Now both count from the cloud's own corner: in its camera frame and in random frames,
    moved by a fraction of a millimetre to 10⁶ mm, the cloud is turned head up alike and its nose found. Range
    images are never turned."""
    spec = plan_dataset(DatasetConfig(subjects=1, first_subject=3, scans=2, scanner=sensor_profile("kinect-v2")))[1]
    syn = FaceScanner(sensor_profile("kinect-v2")).scan(spec)
    assert orient(syn.scan)[0] is syn.scan  # a depth frame is in its camera's frame: never turned, not even copied
    head_up = rotation_from_euler(spec.yaw, spec.pitch, spec.roll) @ np.array([0.0, 1.0, 0.0])
    moves = [np.zeros(3), np.array([0.3, -0.7, 0.2]), np.array([1.0, 0.0, 0.0]), np.array([2.6, 1.9, -3.1]),
             np.full(3, 1e6)]
    for seed in (None, 0, 1, 2):  # the camera's frame, then random ones
        R = np.eye(3) if seed is None else Rotation.random(random_state=seed).as_matrix()
        rolls = []
        for t in moves:
            cloud = export_surface(syn.scan, syn.scan.resolution(), mesh=False, rotation=R, translation=t)
            _, how = orient(cloud)
            up = how.R @ R @ head_up  # the head's vertical axis after the turn
            rolls.append(np.degrees(np.arctan2(up[0], up[1])))
        assert np.abs(rolls).max() < 5.0 and np.ptp(rolls) < 1.0, (seed, np.round(rolls, 1))
        face = Preprocessor()(cloud)  # the farthest move
        error = np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - (R @ syn.landmarks["nose_tip"] + t))
        assert error <= 10.0, (seed, error)


@pytest.mark.parametrize("fmt", ["obj", "ply"])
def test_synth_writes_a_scanners_meshes_in_random_frames_that_evaluate_identifies(fmt, tmp_path):
    """`facerec3d synth --format obj|ply --spacing 4`: a stereo scanner's meshes (point clouds) for a user to try,
    each in its own random frame with its ground truth moved along; `evaluate` acquires and identifies them."""
    import csv
    import json

    from click.testing import CliRunner

    from facerec3d.cli import main

    out = tmp_path / "meshes"
    r = CliRunner().invoke(main, ["synth", str(out), "--format", fmt, "--spacing", "4", "--subjects", "4",
                                  "--scans", "2"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((out / "manifest.csv").open()))
    assert len(rows) == 8 and all(row["path"].endswith(f".{fmt}") for row in rows)
    frames = set()
    for row in rows[:3]:
        scan = load_scan(out / row["path"])
        assert (scan.mesh is not None) == (fmt == "obj") and scan.grid is None
        assert 3.0 < scan.resolution() < 5.0
        truth = np.array([float(row[f"nose_tip_{a}"]) for a in "xyz"])
        assert np.linalg.norm(landmarks_in_input_frame(Preprocessor()(scan))["nose_tip"] - truth) < 10.0
        frames.add(tuple(np.round(scan.points.mean(axis=0), -1)))
    assert len(frames) == 3  # each scan in a frame of its own
    r = CliRunner().invoke(main, ["evaluate", str(out), "--method", "icp", "--out", str(tmp_path / "run"),
                                  "--jobs", "1", "--cache", str(tmp_path / "cache")])
    assert r.exit_code == 0, r.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["fta_rate"] == 0 and metrics["failures_to_enrol"] == 0 and metrics["rank1_all"] == 1.0, metrics
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "frames"), "--format", "png", "--spacing", "4"])
    assert r.exit_code == 2 and "--spacing is for meshes and point clouds" in r.output, r.output
