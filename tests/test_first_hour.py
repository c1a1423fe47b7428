"""What a new user met in the first hour (issue 24): a depth camera's frames in per-person folders whose file names
repeat (as in rap3df-2019), evaluated and scored again; run folders; the protocol check; the cache; the pipe;
Ctrl-C; the error layout; messages; the service's intrinsics as a file part; the threshold hint."""

import csv
import gzip
import json
import os
import re
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from facerec3d.datasets.synthetic import DatasetConfig, frame_intrinsics, sensor_profile, write_dataset

# a Kinect v2 at half its resolution (the field of view kept): quick, and still a depth camera's sampling
KINECT_SMALL = replace(sensor_profile("kinect-v2"), rows=212, cols=256, focal_px=sensor_profile("kinect-v2").focal_px / 2)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Depth frames of 3 people x 3 scans: <subject>/front_1.png, front_2.png, expression_3.png, intrinsics.json
    at the top, manifest.csv (path, subject, expression, ...): every file name is there three times."""
    root = tmp_path_factory.mktemp("frames")
    write_dataset(root, DatasetConfig(subjects=3, scans=3, seed=2, scanner=KINECT_SMALL), "png")
    return root


@pytest.fixture(scope="module")
def run(frames, tmp_path_factory):
    """`facerec3d evaluate` of the frames (icp, one process)."""
    out = tmp_path_factory.mktemp("run") / "icp"
    r = CliRunner().invoke(main, ["evaluate", str(frames), "--out", str(out), "--jobs", "1", "--bootstrap", "0",
                                  "--cache", str(out.parent / "cache")])
    assert r.exit_code == 0, r.output
    return out, r


def test_frames_are_written_as_a_depth_camera_gives_them(frames):
    rows = list(csv.DictReader(open(frames / "manifest.csv")))
    assert [r["path"] for r in rows[:3]] == ["04200/front_1.png", "04200/front_2.png", "04200/expression_3.png"]
    assert json.loads((frames / "intrinsics.json").read_text())["fx"] == pytest.approx(182.5)
    from facerec3d.io import load_scan

    scan = load_scan(frames / rows[0]["path"])  # read back through intrinsics.json: the truth is on the surface
    nose = np.array([float(rows[0][f"nose_tip_{a}"]) for a in "xyz"])
    assert np.min(np.linalg.norm(scan.points - nose, axis=1)) < 5.0


def test_metrics_reads_evaluates_own_scores_of_frames_whose_names_repeat(run, tmp_path):
    """Item 1: probe labels are the paths within the dataset (unique), so `metrics` takes the score file and gives
    the run's figures again."""
    out, r = run
    lines = (out / "scores.txt").read_text().split("\n")
    labels = {line.split()[2] for line in lines if line}
    assert labels == {f"{s}/{name}" for s in ("04200", "04201", "04202") for name in ("front_2.png", "expression_3.png")}
    r = CliRunner().invoke(main, ["metrics", str(out / "scores.txt"), "--out", str(tmp_path / "m"), "--bootstrap", "0"])
    assert r.exit_code == 0, r.output
    again = json.loads((tmp_path / "m" / "metrics.json").read_text())
    evaluated = json.loads((out / "metrics.json").read_text())
    for key in ("rank1", "eer", "n_probes", "vr_at_far_0.001"):
        assert again[key] == evaluated[key]
    with open(out / "probes.csv") as f:
        assert {row["probe"] for row in csv.DictReader(f)} == labels


def test_a_score_file_whose_label_has_two_subjects_is_one_plain_line(tmp_path):
    scores = tmp_path / "s.txt"
    scores.write_text("a a front_1 -1.0\nb a front_1 -3.0\na b front_1 -2.0\nb b front_1 -0.5\n")
    r = CliRunner().invoke(main, ["metrics", str(scores), "--out", str(tmp_path / "m")])
    assert r.exit_code == 2
    assert r.output.startswith(f"error: {scores}: probe label 'front_1' has two subjects ('a', 'b')")
    assert "np.str_" not in r.output and "Traceback" not in r.output


def test_evaluate_shows_enrolment_progress(run):
    """Item 3: a bar while the gallery is enrolled, between preprocessing and matching."""
    _, r = run
    out = r.output
    assert "enrolling" in out and out.index("preprocessing") < out.index("enrolling") < out.index("matching")


def test_a_run_folder_is_not_overwritten_without_overwrite(run, frames, tmp_path):
    """Item 4: refused with the reason (before any work); with --overwrite the old run's files go, others stay."""
    out, _ = run
    folder = tmp_path / "again"
    folder.mkdir()
    for name in ("metrics.json", "scores.txt", "report.html"):
        (folder / name).write_bytes((out / name).read_bytes())
    (folder / "model.npz").write_bytes(b"an lda run's model")  # left by another method
    (folder / "notes.txt").write_text("mine")
    args = ["evaluate", str(frames), "--out", str(folder), "--jobs", "1", "--bootstrap", "0",
            "--cache", str(out.parent / "cache")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and f"error: {folder}: holds a run already" in r.output and "--overwrite" in r.output
    assert (folder / "model.npz").read_bytes() == b"an lda run's model"  # nothing touched
    r = CliRunner().invoke(main, args + ["--overwrite"])
    assert r.exit_code == 0, r.output
    assert not (folder / "model.npz").exists() and (folder / "method.json").is_file()
    assert (folder / "notes.txt").read_text() == "mine"


def test_a_comparison_is_not_overwritten_without_overwrite(run, tmp_path):
    """As evaluate's run folder: refused with one line naming --overwrite (nothing touched); with it, the old
    comparison's files go, others stay."""
    out, _ = run
    folder = tmp_path / "cmp"
    args = ["compare", str(out), "--out", str(folder)]
    assert CliRunner().invoke(main, args).exit_code == 0
    (folder / "compare.md").write_text("an older comparison")
    (folder / "notes.txt").write_text("mine")
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: {folder}: holds a comparison already (") and "--overwrite" in r.output
    assert (folder / "compare.md").read_text() == "an older comparison"
    r = CliRunner().invoke(main, args + ["--overwrite"])
    assert r.exit_code == 0, r.output
    assert "icp" in (folder / "compare.md").read_text() and (folder / "notes.txt").read_text() == "mine"


def test_bosphorus_protocol_on_a_dataset_without_bosphorus_types_is_refused(frames, tmp_path):
    """Item 6."""
    r = CliRunner().invoke(main, ["evaluate", str(frames), "--protocol", "bosphorus", "--out", str(tmp_path / "b"),
                                  "--cache", str(tmp_path / "cache"), "--jobs", "1"])
    assert r.exit_code == 2, r.output
    assert f"error: {frames / 'manifest.csv'}: the bosphorus protocol needs Bosphorus scan types" in r.output
    assert not (tmp_path / "b").exists()  # refused before any work


def test_preprocess_names_outputs_after_the_person(frames, tmp_path):
    """Item 9: front_1.png of three people gives 04200_front_1.npz, ... not front_1, front_1-2, ..."""
    inputs = [str(frames / s / "front_1.png") for s in ("04200", "04201")]
    r = CliRunner().invoke(main, ["preprocess", *inputs, "-o", str(tmp_path / "faces"), "--jobs", "1"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "faces").glob("*.npz")) == ["04200_front_1.npz", "04201_front_1.npz"]


@pytest.mark.parametrize("given", ["folder", "manifest"])
def test_preprocess_takes_a_folder_or_a_manifest_as_enroll_does(frames, tmp_path, given):
    """A dataset folder or its manifest.csv gives all the scans it lists, named as files given one by one are."""
    data = tmp_path / "data"
    data.mkdir()
    rows = [f"{frames / s / 'front_1.png'},{s}" for s in ("04200", "04201")]
    (data / "manifest.csv").write_text("path,subject\n" + "\n".join(rows) + "\n")
    source = data if given == "folder" else data / "manifest.csv"
    r = CliRunner().invoke(main, ["preprocess", str(source), "-o", str(tmp_path / "faces"), "--jobs", "1"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "faces").glob("*.npz")) == ["04200_front_1.npz", "04201_front_1.npz"]
    with open(tmp_path / "faces" / "landmarks.csv") as f:
        assert [row["scan"] for row in csv.DictReader(f)] == [str(frames / s / "front_1.png") for s in ("04200", "04201")]


def test_preprocess_into_an_earlier_output_is_refused_without_overwrite(frames, tmp_path):
    """landmarks.csv lists exactly the faces in OUT: a second preprocess into it is refused (nothing touched);
    with --overwrite the earlier faces and landmarks.csv go, other files stay."""
    faces = tmp_path / "faces"
    first = ["preprocess", str(frames / "04200" / "front_1.png"), "-o", str(faces), "--jobs", "1"]
    assert CliRunner().invoke(main, first).exit_code == 0
    (faces / "notes.txt").write_text("mine")
    before = (faces / "landmarks.csv").read_text()
    again = ["preprocess", str(frames / "04201" / "front_1.png"), "-o", str(faces), "--jobs", "1", "--format", "ply"]
    r = CliRunner().invoke(main, again)
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: {faces}: holds a preprocess output already (landmarks.csv, front_1.npz)")
    assert "--overwrite" in r.output
    assert (faces / "landmarks.csv").read_text() == before and (faces / "front_1.npz").is_file()
    r = CliRunner().invoke(main, again + ["--overwrite"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in faces.iterdir()) == ["front_1.ply", "landmarks.csv", "notes.txt"]
    with open(faces / "landmarks.csv") as f:
        assert [row["output"] for row in csv.DictReader(f)] == [str(faces / "front_1.ply")]


def test_an_interrupted_preprocess_leaves_only_faces_that_landmarks_csv_lists(frames, tmp_path, monkeypatch):
    """Ctrl-C after a face was written and before its row left a face that landmarks.csv did not list (8 faces, 7
    rows): a face is kept only with its row."""
    import facerec3d.io

    real, written = facerec3d.io.save_scan, []

    def written_then_interrupted(face, path):
        real(face, path)
        written.append(path)
        if len(written) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(facerec3d.io, "save_scan", written_then_interrupted)
    faces = tmp_path / "faces"
    r = CliRunner().invoke(main, ["preprocess", str(frames / "04200" / "front_1.png"),
                                  str(frames / "04201" / "front_1.png"), "-o", str(faces), "--jobs", "1"])
    assert r.exit_code == 130 and r.stderr.splitlines()[-1] == "interrupted", r.output
    assert written == [faces / "04200_front_1.npz", faces / "04201_front_1.npz"]
    with open(faces / "landmarks.csv") as f:
        assert [row["output"] for row in csv.DictReader(f)] == [str(faces / "04200_front_1.npz")]
    assert sorted(p.name for p in faces.iterdir()) == ["04200_front_1.npz", "landmarks.csv"]


def test_preprocess_interrupted_while_its_workers_shut_down_is_interrupted(frames, tmp_path, monkeypatch):
    """The batch's workers were shut down when its generator was collected, after the command: Ctrl-C then was an
    "Exception ignored" traceback and exit code 0. They shut down within the command: `interrupted`, 130."""
    from facerec3d.workers import Workers

    real = Workers.close

    def interrupted(self):
        real(self)
        raise KeyboardInterrupt

    monkeypatch.setattr(Workers, "close", interrupted)
    faces = tmp_path / "faces"
    r = CliRunner().invoke(main, ["preprocess", str(frames / "04200" / "front_1.png"), "-o", str(faces)])
    assert r.exit_code == 130 and r.stderr.splitlines()[-1] == "interrupted", r.output


def test_preprocess_overwrite_of_an_unreadable_listing_is_one_line(tmp_path):
    """OUT's landmarks.csv with a field over the csv module's limit: one line naming it, not `_csv.Error: field
    larger than field limit`; nothing in OUT is touched."""
    faces = tmp_path / "faces"
    faces.mkdir()
    (faces / "landmarks.csv").write_text("scan,status,output\na.png,ok," + "x" * 200_000 + ".npz\n")
    r = CliRunner().invoke(main, ["preprocess", str(tmp_path / "a.png"), "-o", str(faces), "--overwrite"])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: {faces / 'landmarks.csv'}: not a readable CSV file (field larger than field "
                               "limit")
    assert (faces / "landmarks.csv").stat().st_size > 200_000


def test_the_cache_says_where_it_is_and_can_be_listed_and_cleared(frames, tmp_path, monkeypatch):
    from facerec3d.preprocess import batch

    monkeypatch.setattr(batch, "DEFAULT_CACHE", tmp_path / "user-cache")
    (tmp_path / "g").mkdir()
    args = ["enroll", str(frames / "04200" / "front_1.png"), "--gallery", str(tmp_path / "g" / "g.sqlite"),
            "--subject", "04200", "--jobs", "1"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert f"preprocessing cache: {tmp_path / 'user-cache'} (first use" in r.output  # stderr, mixed in
    r = CliRunner().invoke(main, ["cache", "info"])
    assert r.exit_code == 0 and re.match(rf"{re.escape(str(tmp_path / 'user-cache'))}: 1 faces, 0 failures, "
                                         r"[\d.]+ MiB", r.output), r.output
    (tmp_path / "user-cache" / "keep.txt").write_text("not an entry")
    r = CliRunner().invoke(main, ["cache", "clear"])
    assert r.exit_code == 0 and "removed 1 entries" in r.output
    assert [p.name for p in (tmp_path / "user-cache").iterdir()] == ["keep.txt"]
    r = CliRunner().invoke(main, ["enroll", *args[1:]])  # said once: the folder is there now
    assert "preprocessing cache:" not in r.output


def test_output_into_a_closed_pipe_ends_quietly_as_a_unix_tool_does(tmp_path):
    """Item 2: `facerec3d gallery g.sqlite list | head -1`."""
    from facerec3d.gallery.store import GalleryStore

    with GalleryStore(tmp_path / "g.sqlite", create=True) as store:
        for i in range(5000):
            store.add_failure(f"/scans/person-{i:05d}/front_1.png", "no face-shaped surface")
    proc = subprocess.Popen([sys.executable, "-m", "facerec3d.cli", "gallery", str(tmp_path / "g.sqlite"), "list"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = proc.stdout.readline()
    proc.stdout.close()  # as head -1 does
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 141 and first.startswith(b"failed\t/scans/person-00000")
    assert err == "", err


def test_ctrl_c_exits_130_with_one_line(monkeypatch, tmp_path):
    import facerec3d.datasets.synthetic

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(facerec3d.datasets.synthetic, "write_dataset", interrupted)
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "d")])
    assert r.exit_code == 130 and r.output.strip() == "interrupted"


def test_ctrl_c_while_a_compiled_module_loads_exits_130_with_one_line(monkeypatch, tmp_path):
    """A compiled module (scipy's pybind11 ones) that Ctrl-C stops while it loads raises ImportError "initialization
    failed" from the KeyboardInterrupt: that was a traceback and exit code 1 (commands import as they start)."""
    import facerec3d.datasets.synthetic

    def interrupted(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise ImportError("initialization failed") from e

    monkeypatch.setattr(facerec3d.datasets.synthetic, "write_dataset", interrupted)
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "d")])
    assert r.exit_code == 130 and r.output == "interrupted\n", r.output


def test_an_interrupted_run_leaves_no_part_of_itself(run, frames, tmp_path, monkeypatch):
    """Ctrl-C while the plots were written left metrics.json and scores.txt but no report: a run that looked
    complete, which a new run refused to replace ("holds a run already"). The run is written beside its folder
    and moved in when complete: interrupted, it leaves nothing (nor its hidden folder) and the next run needs no
    --overwrite. `metrics`, writing the same run folder, alike."""
    import facerec3d.evaluation.report

    out, _ = run
    folder = tmp_path / "runs" / "icp"
    real = facerec3d.evaluation.report.plot_det

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(facerec3d.evaluation.report, "plot_det", interrupted)
    args = ["evaluate", str(frames), "--out", str(folder), "--jobs", "1", "--bootstrap", "0",
            "--cache", str(out.parent / "cache")]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 130 and r.stderr.splitlines()[-1] == "interrupted", r.output
    assert list((tmp_path / "runs").iterdir()) == []
    r = CliRunner().invoke(main, ["metrics", str(out / "scores.txt"), "--out", str(folder), "--bootstrap", "0"])
    assert r.exit_code == 130 and r.output == "interrupted\n", r.output
    assert list((tmp_path / "runs").iterdir()) == []
    monkeypatch.setattr(facerec3d.evaluation.report, "plot_det", real)
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["icp"]
    assert {"metrics.json", "scores.txt", "report.html", "det.png", "method.json"} <= set(os.listdir(folder))


def test_memory_running_out_is_one_line_and_leaves_no_part_of_a_run(run, tmp_path, monkeypatch):
    """Under a memory limit, matplotlib's C++ bad_alloc while a run's plots were drawn was a MemoryError traceback:
    one line now (exit 1), and the run, written beside its folder, leaves nothing."""
    import facerec3d.evaluation.report

    out, _ = run

    def no_memory(*args, **kwargs):
        raise MemoryError("std::bad_alloc")

    monkeypatch.setattr(facerec3d.evaluation.report, "plot_det", no_memory)
    folder = tmp_path / "runs" / "m"
    r = CliRunner().invoke(main, ["metrics", str(out / "scores.txt"), "--out", str(folder), "--bootstrap", "0"])
    assert r.exit_code == 1 and r.output == ("error: out of memory (std::bad_alloc): free memory, or give the command "
                                             "less at once (fewer --jobs, a smaller gallery or dataset)\n"), r.output
    assert list((tmp_path / "runs").iterdir()) == []


def test_info_lays_out_errors_as_every_command_does(tmp_path, frames):
    """Item 8: `error: FILE: reason`; and an RGBA or empty PNG is "not a depth image" before any intrinsics."""
    from PIL import Image

    rgba, empty = tmp_path / "photo.png", tmp_path / "empty.png"  # no intrinsics.json anywhere near
    Image.new("RGBA", (8, 8)).save(rgba)
    empty.write_bytes(b"")
    r = CliRunner().invoke(main, ["info", str(rgba), str(empty), str(frames / "04200" / "front_1.png")])
    assert r.exit_code == 2
    lines = r.output.splitlines()
    assert lines[0] == f"error: {rgba}: not a depth image: Pillow mode RGBA (need a grey depth image: 16-bit, 8-bit or float)"
    assert lines[1].startswith(f"error: {empty}: ") and "intrinsics" not in lines[1]
    assert lines[2].startswith(f"{frames / '04200' / 'front_1.png'}: 212x256 grid")



def test_info_of_a_single_point_says_so_instead_of_nan(tmp_path):
    """A one-point array has no spacing to measure: "no resolution (a single point)", not "resolution nan mm"."""
    import numpy as np

    xyz = np.full((10, 10, 3), np.nan)
    xyz[3, 3] = [1.0, 2.0, 3.0]
    np.save(tmp_path / "one.npy", xyz)
    xyz[3, 4] = [2.0, 2.0, 3.0]
    np.save(tmp_path / "two.npy", xyz)
    r = CliRunner().invoke(main, ["info", str(tmp_path / "one.npy"), str(tmp_path / "two.npy")])
    assert r.exit_code == 0, r.output
    one, two = r.output.splitlines()
    assert "1 valid point," in one and one.endswith("no resolution (a single point)") and "nan" not in one
    assert "2 valid points," in two and two.endswith("resolution 1.00 mm")

def test_a_reason_that_falls_short_never_reads_as_a_pass():
    """Item 5: "tip 6 mm above its surroundings, a nose needs 6" was 5.6 mm rounded."""
    from facerec3d.errors import short_of

    assert short_of(5.6, 6) == "5.6" and short_of(5.96, 6) == "5.96" and short_of(5.9996, 6) == "5.9996"
    assert short_of(2.5, 6) == "2.5" and float(short_of(5.99999999, 6)) < 6


def test_compare_legends_name_a_run_once(tmp_path):
    """Item 8: a run folder named after its method is "icp", not "icp (icp)"; another folder keeps its name."""
    from facerec3d.evaluation.compare import compare_runs
    from facerec3d.evaluation.report import write_run

    rng = np.random.default_rng(0)
    gallery = ["a", "b", "c"]
    S = rng.normal(size=(6, 3)) + 3 * np.equal.outer(["a", "b", "c"] * 2, gallery)
    for name in ("icp", "tuned"):
        write_run(tmp_path / name, S, ["a", "b", "c"] * 2, [f"p{i}" for i in range(6)], gallery, {"method": "icp"},
                  bootstrap=0)
    result = compare_runs([tmp_path / "icp", tmp_path / "tuned"], tmp_path / "cmp")
    assert [r["label"] for r in result["runs"]] == ["icp", "icp (tuned)"]
    assert "icp (icp)" not in (tmp_path / "cmp" / "compare.md").read_text()


def test_verify_hints_when_the_default_threshold_does_not_suit_the_sensor(run, frames, tmp_path):
    """Item 8: a gallery of depth-camera faces (matched at ~3 mm) and the default threshold, chosen on 1 mm laser
    faces: a hint says how to choose one. With --threshold, or on laser faces, no hint."""
    out, _ = run
    gallery, cache = str(tmp_path / "g.sqlite"), str(out.parent / "cache")
    r = CliRunner().invoke(main, ["enroll", str(frames / "04201" / "front_1.png"), "--gallery", gallery,
                                  "--subject", "04201", "--method", "icp", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0, r.output
    probe = str(frames / "04201" / "front_2.png")
    r = CliRunner().invoke(main, ["verify", probe, "--gallery", gallery, "--claim", "04201", "--cache", cache])
    from facerec3d.gallery.service import DEFAULT_THRESHOLDS

    default = DEFAULT_THRESHOLDS["icp"]
    assert f"hint: the default threshold {default:g} was chosen on laser scans" in r.output
    assert "threshold_at_eer" in r.output
    r = CliRunner().invoke(main, ["verify", probe, "--gallery", gallery, "--claim", "04201", "--cache", cache,
                                  "--threshold", "-20"])
    assert r.exit_code == 0 and "hint" not in r.output

    from facerec3d.datasets.frontal import frontal_face
    from facerec3d.io import save_scan

    laser = tmp_path / "laser"
    laser.mkdir()
    save_scan(frontal_face(1), laser / "s1.npz")
    save_scan(frontal_face(1, pose_deg=2.0, noise_mm=0.2, seed=3), laser / "s1-probe.npz")
    g2 = str(tmp_path / "laser.sqlite")
    r = CliRunner().invoke(main, ["enroll", str(laser / "s1.npz"), "--gallery", g2, "--subject", "s1", "--method",
                                  "icp", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["verify", str(laser / "s1-probe.npz"), "--gallery", g2, "--claim", "s1",
                                  "--cache", cache])
    assert r.output.startswith("accept") and "hint" not in r.output


def test_the_service_takes_intrinsics_as_a_file_part_or_text(frames, tmp_path):
    """Item 7: `curl -F scan=@front_1.png -F intrinsics=@intrinsics.json` as well as `-F intrinsics="$(cat ...)"`."""
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from facerec3d.server.app import Service, ServiceSettings, create_app
    from facerec3d.server.keys import KeyFile, add_key
    from facerec3d.server.live import LiveGallery

    key = add_key(tmp_path / "keys.json", "gate", "enrol,query,admin")
    live = LiveGallery(tmp_path / "g.sqlite", jobs=1)
    service = Service(live, KeyFile(tmp_path / "keys.json"), ServiceSettings())
    camera = (frames / "intrinsics.json").read_bytes()
    try:
        client = TestClient(create_app(service))
        headers = {"X-API-Key": key}
        scan = (frames / "04202" / "front_1.png").read_bytes()
        r = client.post("/v1/enrol", headers=headers, data={"subject": "04202"},
                        files={"scan": ("front_1.png", scan), "intrinsics": ("intrinsics.json", camera)})
        assert r.status_code == 201, r.text
        probe = (frames / "04202" / "front_2.png").read_bytes()
        r = client.post("/v1/identify", headers=headers, data={"intrinsics": camera.decode()},
                        files={"probe": ("front_2.png", probe)})
        assert r.status_code == 200 and r.json()["candidates"][0]["subject"] == "04202", r.text
        r = client.post("/v1/identify", headers=headers,
                        files={"probe": ("front_2.png", probe), "intrinsics": ("intrinsics.json", b"{fx: 1")})
        assert r.status_code == 422 and "not JSON" in r.json()["error"]
        for person in ("04200", "04201"):
            r = client.post("/v1/enrol", headers=headers, data={"subject": person},
                            files={"scan": ("front_1.png", (frames / person / "front_1.png").read_bytes()),
                                   "intrinsics": ("intrinsics.json", camera)})
            assert r.status_code == 201, r.text
        people = ["04200", "04201", "04202"]
        scans = [("scan", (f"{s}.png", (frames / s / "front_2.png").read_bytes())) for s in people]
        r = client.post("/v1/calibrate", headers=headers, data={"subject": people},  # a file part here too
                        files=scans + [("intrinsics", ("intrinsics.json", camera))])
        assert r.status_code == 200, r.text
        record = r.json()["threshold"]  # every scan read with the intrinsics of the file part
        assert (record["scans"], record["failed_scans"], record["impostor_pairs"]) == (3, 0, 6)
    finally:
        service.close()


def test_frames_without_intrinsics_beside_them_are_read_with_intrinsics(frames, tmp_path):
    """ux19 item 1: info, enroll, identify and verify take --intrinsics FILE as preprocess and evaluate do. Frames
    whose intrinsics.json is elsewhere fail with the reason in one line without it, and are read with it (enroll's
    calibration on the gallery's own frames included)."""
    import shutil

    shot = tmp_path / "shots"  # no intrinsics.json in it or above it
    shot.mkdir()
    for subject, frame, name in (("04200", "front_1", "04200"), ("04201", "front_1", "04201"),
                                 ("04200", "front_2", "probe")):  # subjects from the file names
        shutil.copy(frames / subject / f"{frame}.png", shot / f"{name}.png")
    camera = tmp_path / "kinect.json"
    shutil.copy(frames / "intrinsics.json", camera)
    enrolled = [str(shot / "04200.png"), str(shot / "04201.png")]
    probe, gallery, cache = str(shot / "probe.png"), str(tmp_path / "g.sqlite"), str(tmp_path / "cache")
    missing = "a depth image needs pinhole intrinsics"

    r = CliRunner().invoke(main, ["info", probe])
    assert r.exit_code == 2 and r.output.startswith(f"error: {probe}: {missing}") and r.output.count("\n") == 1
    assert "--intrinsics" in r.output, r.output
    r = CliRunner().invoke(main, ["info", probe, "--intrinsics", str(camera)])
    assert r.exit_code == 0 and r.output.startswith(f"{probe}: 212x256 grid"), r.output

    common = ["--gallery", gallery, "--cache", cache]
    r = CliRunner().invoke(main, ["enroll", *enrolled, *common, "--method", "icp", "--jobs", "1"])
    assert r.exit_code == 1 and "2 failed to enrol" in r.output and missing in r.output, r.output
    r = CliRunner().invoke(main, ["enroll", *enrolled, *common, "--method", "icp", "--jobs", "1", "--intrinsics",
                                  str(camera)])
    assert r.exit_code == 0 and "2 enrolled" in r.output, r.output
    assert "verification threshold" in r.output and "recorded in" in r.output, r.output  # calibrated on its frames

    for command in (["identify", probe, *common, "--jobs", "1"], ["verify", probe, *common, "--claim", "04200"]):
        r = CliRunner().invoke(main, command)
        assert r.exit_code == 2 and r.output.startswith(f"error: {probe}: {missing}"), r.output
        assert r.output.count("\n") == 1, r.output
    r = CliRunner().invoke(main, ["identify", probe, *common, "--jobs", "1", "--intrinsics", str(camera)])
    assert r.exit_code == 0 and r.output.splitlines()[1].split()[:2] == ["1", "04200"], r.output
    r = CliRunner().invoke(main, ["verify", probe, *common, "--claim", "04200", "--intrinsics", str(camera)])
    assert r.exit_code in (0, 1) and "claim 04200, score" in r.output, r.output


def test_a_gallery_of_frames_enrolled_with_intrinsics_recalibrates_with_them(frames, tmp_path):
    """cal19 item 2: `gallery G calibrate` takes --intrinsics as enroll does, so a gallery of frames whose
    intrinsics.json is elsewhere calibrates again on its own frames; without it, one line says why it cannot."""
    import shutil

    from facerec3d.gallery.store import GalleryStore

    shot = tmp_path / "shots"  # no intrinsics.json in it or above it
    shot.mkdir()
    for subject in ("04200", "04201"):
        shutil.copy(frames / subject / "front_1.png", shot / f"{subject}.png")
    camera = tmp_path / "kinect.json"
    shutil.copy(frames / "intrinsics.json", camera)
    gallery, cache = str(tmp_path / "g.sqlite"), str(tmp_path / "cache")
    r = CliRunner().invoke(main, ["enroll", str(shot / "04200.png"), str(shot / "04201.png"), "--gallery", gallery,
                                  "--cache", cache, "--method", "icp",
                                  "--jobs", "1", "--intrinsics", str(camera)])
    assert r.exit_code == 0 and "2 enrolled" in r.output, r.output

    r = CliRunner().invoke(main, ["gallery", gallery, "calibrate", "--fmr", "0.5", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: {gallery}: none of the 2 calibration scans could be used; "
                               f"{shot / '04200.png'}: a depth image needs pinhole intrinsics"), r.output
    with GalleryStore(gallery) as store:
        assert store.threshold()["rule"].startswith("fmr=0.01")  # enroll's, untouched
    r = CliRunner().invoke(main, ["gallery", gallery, "calibrate", "--fmr", "0.5", "--jobs", "1", "--cache", cache,
                                  "--intrinsics", str(camera)])
    assert r.exit_code == 0 and "(fmr=0.5:" in r.output and f"recorded in {gallery}" in r.output, r.output
    with GalleryStore(gallery) as store:
        record = store.threshold()
    assert record["rule"] == "fmr=0.5" and record["impostor_pairs"] == 2 and record["failed_scans"] == 0
    option = {name: next(p for p in command.params if p.name == "intrinsics")
              for name, command in (("enroll", main.commands["enroll"]),
                                    ("calibrate", main.commands["gallery"].commands["calibrate"]))}
    assert option["calibrate"].help == option["enroll"].help  # the same help as the other commands'


def test_a_failed_first_enrolment_does_not_tie_the_new_gallery_to_its_method(frames, tmp_path):
    """cal19 item 3: every frame of a first enrolment fails (no intrinsics); enrolling them again with another
    method, here the default, works without deleting the store, which takes that method."""
    import shutil

    from facerec3d.config import DEFAULT_METHOD
    from facerec3d.gallery.store import GalleryStore

    shot = tmp_path / "shots"  # no intrinsics.json in it or above it
    shot.mkdir()
    for subject in ("04200", "04201"):
        shutil.copy(frames / subject / "front_1.png", shot / f"{subject}.png")
    scans = [str(shot / "04200.png"), str(shot / "04201.png")]
    common = ["--gallery", str(tmp_path / "g.sqlite"), "--cache", str(tmp_path / "cache"), "--jobs", "1"]
    r = CliRunner().invoke(main, ["enroll", *scans, *common, "--method", "icp"])
    assert r.exit_code == 1 and "0 enrolled, 0 already enrolled, 2 failed to enrol" in r.output, r.output
    r = CliRunner().invoke(main, ["enroll", *scans, *common, "--intrinsics", str(frames / "intrinsics.json")])
    assert r.exit_code == 0 and "2 enrolled" in r.output, r.output
    assert f"no entries yet: method {DEFAULT_METHOD} replaces icp" in r.output, r.output
    with GalleryStore(tmp_path / "g.sqlite") as store:
        st = store.stats()
    assert st["method"] == DEFAULT_METHOD and st["entries"] == 2 and st["failures_to_enrol"] == 0


def test_the_client_sends_the_intrinsics_it_is_given(frames, tmp_path):
    """ux19 item 1, with --server: the frame goes with the --intrinsics file's camera, not only one found beside it."""
    import shutil

    from facerec3d.client import Client

    frame = tmp_path / "front_1.png"
    shutil.copy(frames / "04200" / "front_1.png", frame)
    _, data = Client._scan(frame, "probe")
    assert "intrinsics" not in data
    _, data = Client._scan(frame, "probe", frames / "intrinsics.json")
    assert json.loads(data["intrinsics"]) == json.loads((frames / "intrinsics.json").read_text())


def test_a_manifest_of_bosphorus_files_is_read_as_the_bosphorus_folder_would_be(tmp_path):
    """The protocol and subsets of synthetic Bosphorus data do not depend on its manifest.csv being there."""
    from facerec3d.datasets.catalog import open_dataset
    from facerec3d.datasets.protocols import split
    from facerec3d.datasets.synthetic import ScannerConfig

    write_dataset(tmp_path, DatasetConfig(subjects=2, scans=4, seed=1, scanner=ScannerConfig(rows=120, cols=160,
                                                                                             focal_px=360.0)), "bnt")
    through_manifest = split(open_dataset(tmp_path))
    (tmp_path / "manifest.csv").unlink()
    folder = split(open_dataset(tmp_path))
    assert through_manifest.protocol == folder.protocol == "bosphorus"
    assert {k: len(v) for k, v in through_manifest.subsets.items() if not k.startswith("pose:")} == \
        {k: len(v) for k, v in folder.subsets.items()}
    assert len(through_manifest.subsets) > 3  # neutral, non-neutral and the Bosphorus types


# ----------------------------------------------------------------------------------------------------------------
# A second new user's hour (2026-12-03): frames named after their pose, not their person; options and outputs.

def test_frames_given_one_by_one_take_their_subject_from_the_manifest_above_them(frames, tmp_path):
    """`enroll frames/04200/front_1.png frames/04201/front_1.png` made two people one subject, "front_1" (and a
    calibration on such frames counted no genuine pair): the manifest.csv above the frames says whose each is;
    without one, same-named files from different folders are refused instead of merged."""
    from facerec3d.datasets.catalog import DatasetError
    from facerec3d.gallery.service import scan_records

    files = [frames / s / "front_1.png" for s in ("04200", "04201")]
    records = scan_records(files)
    assert [r.subject for r in records] == ["04200", "04201"]
    assert [r.path for r in records] == files
    bare = tmp_path / "bare"  # the same frames without a manifest
    for s in ("04200", "04201"):
        (bare / s).mkdir(parents=True)
        (bare / s / "front_1.png").write_bytes((frames / s / "front_1.png").read_bytes())
    with pytest.raises(DatasetError, match="--subject"):
        scan_records([bare / s / "front_1.png" for s in ("04200", "04201")])
    assert [r.subject for r in scan_records([bare / "04200" / "front_1.png"])] == ["front_1"]  # one file: its stem
    assert [r.subject for r in scan_records([bare / s / "front_1.png" for s in ("04200", "04201")], "x")] == ["x", "x"]
    r = CliRunner().invoke(main, ["enroll", *map(str, [bare / s / "front_1.png" for s in ("04200", "04201")]),
                                  "--gallery", str(tmp_path / "g.sqlite"), "--jobs", "1"])
    assert r.exit_code == 2 and r.output.startswith("error: 2 scans named 'front_1'"), r.output
    assert not (tmp_path / "g.sqlite").exists()


def test_view_refuses_an_image_it_cannot_write_before_any_work(frames, tmp_path):
    scan = str(frames / "04200" / "front_1.png")
    for out, reason in ((tmp_path / "x.txt", "cannot write a txt image"), (tmp_path / "no" / "x.png", "no such folder")):
        r = CliRunner().invoke(main, ["view", scan, "-o", str(out)])
        assert r.exit_code == 2 and r.output.strip().splitlines() == [r.output.strip()], r.output
        assert r.output.startswith(f"error: {out}: {reason}"), r.output


def test_view_says_it_is_compiling_when_numbas_cache_is_cold(frames, tmp_path, monkeypatch):
    """ux19 item 3: the first `view` compiled for ~30 s with nothing printed. A cold cache is simulated by a kernel
    that no cache holds, called as the scan is gridded: one line on stderr says what the wait is (as Numba starts
    compiling); once compiled, nothing."""
    import numba

    import facerec3d.preprocess as preprocess
    from facerec3d.jit import COMPILING

    kernel = numba.njit(cache=False)(lambda x: x + 1)  # new to Numba: compiled on its first call
    gridify = preprocess.gridify

    def cold_gridify(scan):
        kernel(1)
        return gridify(scan)

    monkeypatch.setattr(preprocess, "gridify", cold_gridify)
    out = tmp_path / "v.png"
    r = CliRunner().invoke(main, ["view", str(frames / "04200" / "front_1.png"), "--raw", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert r.stderr.splitlines().count(COMPILING) == 1 and r.stdout == f"wrote {out}\n", r.output
    assert COMPILING == "compiling facerec3d's numerical kernels (first run only, ~30 s) ..."
    r = CliRunner().invoke(main, ["view", str(frames / "04200" / "front_1.png"), "--raw", "-o", str(out)])
    assert r.exit_code == 0 and COMPILING not in r.output, r.output  # compiled: nothing to say


def test_a_missing_output_folder_is_named_not_an_errno(frames, tmp_path):
    out = tmp_path / "no" / "x.ply"
    r = CliRunner().invoke(main, ["convert", str(frames / "04200" / "front_1.png"), str(out)])
    assert r.exit_code == 2 and r.output.strip() == f"error: {out}: no such file or directory", r.output


def test_counts_and_sizes_below_one_are_usage_errors(tmp_path, frames):
    for args in (["synth", str(tmp_path / "s"), "--subjects", "0"], ["synth", str(tmp_path / "s"), "--scans", "-2"],
                 ["identify", str(frames / "04200" / "front_1.png"), "--gallery", "g.sqlite", "-k", "0"],
                 ["evaluate", str(frames), "--bootstrap", "-5", "--out", str(tmp_path / "e")],
                 ["preprocess", str(frames / "04200" / "front_1.png"), "-o", str(tmp_path / "p"), "--jobs", "0"]):
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 2 and "Invalid value" in r.output, (args, r.output)
    assert not (tmp_path / "s").exists() and not (tmp_path / "e").exists()


def test_fusing_score_files_that_share_nothing_is_an_error(tmp_path):
    (tmp_path / "a.txt").write_text("s1 s1 p1 1.0\ns2 s1 p1 0.5\n")
    (tmp_path / "b.txt").write_text("s3 s3 q1 1.0\ns4 s3 q1 0.5\n")
    r = CliRunner().invoke(main, ["fuse", str(tmp_path / "a.txt"), str(tmp_path / "b.txt"), "--out",
                                  str(tmp_path / "f.txt")])
    assert r.exit_code == 2 and "shares no comparison" in r.output, r.output
    assert not (tmp_path / "f.txt").exists()
    # of three, the one that shares nothing is named, not the second (which fuses with the first)
    (tmp_path / "c.txt").write_text("s1 s1 p1 0.7\ns2 s1 p1 0.2\n")
    r = CliRunner().invoke(main, ["fuse", str(tmp_path / "a.txt"), str(tmp_path / "c.txt"), str(tmp_path / "b.txt"),
                                  "--out", str(tmp_path / "f.txt")])
    assert r.exit_code == 2 and r.output.strip() == (f"error: {tmp_path / 'b.txt'}: shares no comparison with "
                                                     f"{tmp_path / 'a.txt'} (other probes or gallery faces): nothing "
                                                     "to fuse"), r.output
    # each shares some with the first, none is in all three: all named
    (tmp_path / "d.txt").write_text("s2 s1 p1 0.9\n")
    (tmp_path / "e.txt").write_text("s1 s1 p1 0.9\n")
    r = CliRunner().invoke(main, ["fuse", str(tmp_path / "a.txt"), str(tmp_path / "d.txt"), str(tmp_path / "e.txt"),
                                  "--out", str(tmp_path / "f.txt")])
    assert r.exit_code == 2 and "no comparison is in every file" in r.output and "e.txt" in r.output, r.output
    r = CliRunner().invoke(main, ["fuse", str(tmp_path / "a.txt"), str(tmp_path / "c.txt"), "--rule", "avg",
                                  "--out", str(tmp_path / "f.txt")])
    assert r.exit_code == 2 and r.output.strip() == ("error: unknown fusion rule 'avg': use one of sum, product, "
                                                     "weighted-sum, borda, consensus"), r.output


def test_a_gallery_commands_help_needs_no_store():
    for command in ("list", "rekey", "calibrate"):
        r = CliRunner().invoke(main, ["gallery", command, "--help"], prog_name="facerec3d")
        assert r.exit_code == 0 and r.output.startswith(f"Usage: facerec3d gallery [STORE] {command}"), r.output
    r = CliRunner().invoke(main, ["gallery", "list"])
    assert r.exit_code == 2 and "give the gallery store STORE" in r.output


def test_evaluate_refuses_a_model_with_another_method_and_warns_of_training_on_the_test_people(run, frames,
                                                                                               tmp_path):
    out, _ = run
    model = tmp_path / "model.npz"
    model.write_bytes(b"not read: refused before")
    r = CliRunner().invoke(main, ["evaluate", str(frames), "--method", "icp", "--model", str(model), "--out",
                                  str(tmp_path / "x")])
    assert r.exit_code == 2 and "give --model or --method, not both" in r.output, r.output
    r = CliRunner().invoke(main, ["evaluate", str(frames), "--method", "icp", "--train", str(frames), "--out",
                                  str(tmp_path / "y"), "--jobs", "1", "--bootstrap", "0", "--cache",
                                  str(out.parent / "cache")])
    assert r.exit_code == 0, r.output
    assert "warning: " in r.output and "3 of its subjects" in r.output and "flatters" in r.output


def test_a_saved_model_with_a_training_set_is_refused_in_one_line(tmp_path):
    """`evaluate DATA --model FILE --train DIR` ignored --train without a word (the docs give them as alternatives,
    and --model with --method is refused); enroll did too. Both refuse it, before anything is read or made."""
    model, data, train = tmp_path / "model.npz", tmp_path / "data", tmp_path / "train"
    model.write_bytes(b"not read: refused before")
    data.mkdir(), train.mkdir()
    for args in (["evaluate", str(data), "--out", str(tmp_path / "x")],
                 ["enroll", str(data), "--gallery", str(tmp_path / "g.sqlite")]):
        r = CliRunner().invoke(main, [*args, "--model", str(model), "--train", str(train)])
        assert r.exit_code == 2 and r.output == f"error: {model}: a saved model is trained already: give --model " \
            "or --train, not both\n", r.output
    assert not (tmp_path / "x").exists() and not (tmp_path / "g.sqlite").exists()


def test_reading_an_empty_file_as_a_gallery_leaves_it_empty(tmp_path):
    """`gallery e.sqlite list` on a 0-byte file made it a 57 KB store and listed nothing, exit 0."""
    empty = tmp_path / "e.sqlite"
    empty.write_bytes(b"")
    for command in ("list", "stats"):
        r = CliRunner().invoke(main, ["gallery", str(empty), command])
        assert r.exit_code == 2 and r.output.strip() == f"error: {empty}: an empty file, not a gallery (enrol into it "\
                                                        "first)", r.output
    assert empty.stat().st_size == 0


def test_serve_on_a_port_in_use_is_one_line_before_anything_starts(tmp_path):
    """Not the banner and then uvicorn's error (exit 3): the address is checked before the gallery loads."""
    import socket

    pytest.importorskip("fastapi")
    from facerec3d.server.keys import add_key

    add_key(tmp_path / "keys.json", "alice", "query")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = CliRunner().invoke(main, ["serve", "--gallery", str(tmp_path / "g.sqlite"), "--keys",
                                      str(tmp_path / "keys.json"), "--port", str(port), "--jobs", "1"])
    assert r.exit_code == 2, r.output
    assert r.output == f"error: 127.0.0.1:{port}: address already in use\n"
    assert not (tmp_path / "g.sqlite").exists()  # refused before the gallery was made


def test_serve_holds_its_address_from_the_check_until_uvicorn_serves_on_it(tmp_path, monkeypatch):
    """ux19 item 2: the address was bound to check it, let go, and bound again by uvicorn after the gallery had
    loaded: another process could take the port in between. Now the socket bound first is the one uvicorn serves
    on, listening all along (no other socket can bind the port meanwhile), and a start refused after the check
    (no key file) lets the port go."""
    import errno
    import socket

    pytest.importorskip("fastapi")
    uvicorn = pytest.importorskip("uvicorn")
    import facerec3d.server.app as app
    from facerec3d.server.keys import add_key

    original, bound, served = app.bind_address, [], []

    def bind(host, port):
        sock = original(host, port)
        bound.append((sock, sock.getsockname()[1]))
        return sock

    def taken(port: int) -> bool:
        """Whether another socket, bound as uvicorn binds (SO_REUSEADDR), is refused the port."""
        with socket.socket() as other:
            other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                other.bind(("127.0.0.1", port))
            except OSError as e:
                return e.errno == errno.EADDRINUSE
            return False

    def run(server, sockets=None):  # instead of serving: what uvicorn is handed, and whether the port is held
        served.append((sockets, taken(bound[-1][1])))

    monkeypatch.setattr(app, "bind_address", bind)
    monkeypatch.setattr(uvicorn.Server, "run", run)
    add_key(tmp_path / "keys.json", "alice", "query")
    serve = ["serve", "--gallery", str(tmp_path / "g.sqlite"), "--port", "0", "--jobs", "1", "--keys"]
    r = CliRunner().invoke(main, [*serve, str(tmp_path / "keys.json")])
    assert r.exit_code == 0, r.output
    (sock, port), = bound
    assert served == [([sock], True)]  # the very socket, still bound and listening when uvicorn is given it
    assert f"on http://127.0.0.1:{port} " in r.output  # port 0: the banner names the port taken
    assert sock.fileno() == -1 and not taken(port)  # closed after serving

    bound.clear()
    r = CliRunner().invoke(main, [*serve, str(tmp_path / "missing.json")])
    assert r.exit_code == 2 and "missing.json" in r.output, r.output
    (sock, port), = bound
    assert sock.fileno() == -1 and not taken(port)  # refused after the check: the port let go


def _ply(vertices: int, rows: int) -> bytes:
    """A binary PLY whose header promises `vertices` (x, y, z floats) and that holds `rows` of them."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n").encode()
    return head + np.arange(3 * rows, dtype="<f4").tobytes()


@pytest.mark.parametrize("name, content, reason", [
    ("text.npz", b"an archive? no\n", "not a NumPy file: neither an .npy array nor an .npz archive"),
    ("cut.ply", _ply(1000, 2), "truncated PLY: header promises 1000 vertices, the file holds fewer (bytes"),
    ("cut.ply", _ply(100, 10), "truncated PLY: header promises 100 vertices, the file holds only 10"),
    ("packed.xyz", gzip.compress(b"1.0 2.0 3.0\n" * 500, mtime=0), "not a text point file (gzip-compressed data"),
    ("noise.xyz", bytes(range(256)) * 4, "not a text point file (binary data)"),
], ids=["text-as-npz", "ply-short-of-its-size", "ply-short-of-rows", "gzip-as-xyz", "binary-as-xyz"])
def test_messages_of_files_that_are_not_what_their_names_say(tmp_path, name, content, reason):
    """Item 5: the reason in the user's words: no option they cannot set (NumPy's allow_pickle), no byte-string
    reprs, no binary garbage quoted."""
    path = tmp_path / name
    path.write_bytes(content)
    r = CliRunner().invoke(main, ["info", str(path)])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    expected = f"error: {path}: {reason}"
    if reason.endswith("(bytes"):  # the size in bytes is said
        expected = expected.removesuffix("(bytes") + f"({path.stat().st_size} bytes in all)"
    assert r.output.startswith(expected), r.output
    assert r.output[:-1].isprintable() and "\ufffd" not in r.output  # no binary data quoted


def test_an_array_of_python_objects_is_refused_for_safety_not_loaded_unsafely(tmp_path):
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    r = CliRunner().invoke(main, ["info", str(tmp_path / "objects.npy")])
    assert r.exit_code == 2
    assert r.output == f"error: {tmp_path / 'objects.npy'}: holds pickled Python objects, which are refused for safety\n"


def test_a_single_point_is_counted_as_one(tmp_path):
    """Item 5d: 'only 0 valid points' came from the scan after rasterising, not from the file."""
    (tmp_path / "one.xyz").write_text("1 2 3\n")
    r = CliRunner().invoke(main, ["preprocess", str(tmp_path / "one.xyz"), "-o", str(tmp_path / "out"), "--jobs", "1"])
    assert r.exit_code == 1
    assert f"{tmp_path / 'one.xyz'}: failed: only 1 valid point\n" in r.output


def test_a_file_name_that_is_not_utf8_is_one_failure_and_the_batch_goes_on(frames, tmp_path):
    """A name whose bytes are not UTF-8 (Linux allows any) crashed enroll, identify and preprocess with a
    UnicodeEncodeError (the cache key, the store, the landmarks CSV), losing the batch: now it is that file's
    failure, shown with its bytes as \\xNN, and the other scans are enrolled or preprocessed."""
    import os
    import shutil

    odd = tmp_path / os.fsdecode(b"x\xff.png")
    shutil.copy(frames / "04200" / "front_1.png", odd)
    shutil.copy(frames / "intrinsics.json", tmp_path / "intrinsics.json")
    good = str(frames / "04201" / "front_1.png")
    store = tmp_path / "g.sqlite"
    r = CliRunner().invoke(main, ["enroll", str(odd), good, "--subject", "s", "--gallery", str(store), "--jobs", "1",
                                  "--method", "icp", "--cache", str(tmp_path / "cache")])
    assert r.exit_code == 0, r.output
    assert "x\\xff.png: failed to enrol: the file name is not UTF-8 text" in r.output
    assert "1 enrolled, 0 already enrolled, 1 failed to enrol" in r.output
    listed = CliRunner().invoke(main, ["gallery", str(store), "list"]).output
    assert "front_1.png" in listed and "failed\t" + str(tmp_path) + "/x\\xff.png\tthe file name" in listed
    r = CliRunner().invoke(main, ["preprocess", str(odd), good, "-o", str(tmp_path / "out")])
    assert r.exit_code == 0 and "1 kept, 1 failed" in r.output, r.output
    rows = (tmp_path / "out" / "landmarks.csv").read_text(encoding="utf-8").splitlines()
    assert rows[1].startswith(str(tmp_path) + "/x\\xff.png,the file name is not UTF-8") and ",ok," in rows[2]
    r = CliRunner().invoke(main, ["identify", str(odd), "--gallery", str(store)])
    assert r.exit_code == 2 and r.output.strip().endswith("x\\xff.png: the file name is not UTF-8 text (the bytes "
                                                          "shown as \\x..): rename the file"), r.output



def test_subjects_with_white_space_are_evaluated_and_written_percent_encoded(frames, tmp_path):
    """A manifest naming people 'person 04200' crashed `evaluate` on writing its score file, after all the work:
    the score file now holds 'person%2004200' (one field), the other outputs the name as it is."""
    import csv

    rows = list(csv.DictReader((frames / "manifest.csv").open()))
    manifest = frames / "spaced.csv"
    with manifest.open("w", newline="") as f:
        w = csv.DictWriter(f, rows[0].keys())
        w.writeheader()
        w.writerows({**r, "subject": "person " + r["subject"]} for r in rows)
    out = tmp_path / "run"
    r = CliRunner().invoke(main, ["evaluate", str(manifest), "--method", "icp", "--out", str(out), "--jobs", "1",
                                  "--bootstrap", "0", "--cache", str(tmp_path / "cache")])
    manifest.unlink()
    assert r.exit_code == 0, r.output
    first = (out / "scores.txt").read_text().split("\n")[0].split(" ")
    assert first[0].startswith("person%20042") and first[1] == "person%2004200" and len(first) == 4
    probes = list(csv.DictReader((out / "probes.csv").open()))
    assert {p["subject"] for p in probes} == {"person 04200", "person 04201", "person 04202"}
    assert all(p["rank"] == "1" for p in probes)  # the same frames as the `run` fixture's: each found first


def test_verify_against_a_one_person_fusion_gallery_says_why_every_claim_is_rejected(frames, tmp_path):
    """The default fusion z-normalises each probe's scores over the gallery's people: with one person every claim
    scores 0 and is rejected. The rejection now comes with the reason and what to do."""
    store = tmp_path / "one.sqlite"
    r = CliRunner().invoke(main, ["enroll", str(frames / "04200" / "front_1.png"), "--subject", "a", "--gallery",
                                  str(store), "--cache", str(tmp_path / "cache")])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["verify", str(frames / "04200" / "front_2.png"), "--gallery", str(store),
                                  "--claim", "a", "--cache", str(tmp_path / "cache")])
    assert r.exit_code == 1 and r.output.startswith("reject: claim a, score 0.0000"), r.output
    assert "hint: method 'fusion' normalises each probe's scores over the gallery's people, and this gallery holds " \
           "one: every claim scores 0." in r.output


def test_metrics_of_distances_prints_thresholds_on_the_distances_own_scale(tmp_path):
    """Scores read with --lower-is-better are negated inside; the thresholds printed were on that negated scale
    ("score >= -1.78 accepts": everyone, on the user's distances). They are now the distances themselves."""
    import re

    lines = [f"s{g} s{p} p{p}_{k} {0.1 + 0.05 * k if g == p else 0.8 + 0.05 * k}"
             for p in range(3) for k in range(2) for g in range(3)]
    (tmp_path / "dist.txt").write_text("\n".join(lines) + "\n")
    r = CliRunner().invoke(main, ["metrics", str(tmp_path / "dist.txt"), "--lower-is-better", "--out",
                                  str(tmp_path / "m"), "--bootstrap", "0"])
    assert r.exit_code == 0, r.output
    line = next(x for x in r.output.splitlines() if x.startswith("thresholds"))
    assert "distance <= t accepts" in line, line
    t = float(re.search(r"EER (-?[\d.]+)", line).group(1))
    assert 0.15 <= t < 0.8, line  # every genuine distance (0.10, 0.15) accepted, every impostor's (0.80, 0.85) not
