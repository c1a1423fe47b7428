"""The learned embedding (--method embedding): the shipped ONNX model through onnxruntime (no torch), its input,
identification of synthetic people it never saw, templates in the gallery store, the cascade's embedding screen,
bad model files; and (with the [train] extra only) a tiny model trained here separating a few identities."""

import json
from pathlib import Path
import sqlite3

import numpy as np
import pytest

from facerec3d.datasets.synthetic import FaceScanner, ScanSpec, sensor_profile
from facerec3d.errors import FaceRec3DError
from facerec3d.gallery.cascade import CascadeConfig, face_descriptor, template_descriptor
from facerec3d.gallery.store import GalleryStore
from facerec3d.matching.embedding import (N_CHANNELS, SHIPPED_MODEL, EmbeddingConfig, EmbeddingMatcher,
                                          EmbeddingModel, InputRecipe, face_input, input_channels, read_card, wccn)
from facerec3d.matching.registry import load_matcher
from facerec3d.matching.base import Template
from facerec3d.matching.icp import ICPMatcher
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor
from facerec3d.scan import MIRRORED
from tests.conftest import cli_dataset, model_face, service_identify

SUBJECTS = tuple(range(8))


@pytest.fixture(scope="module")
def kinect_faces():
    """Eight synthetic people the model never saw (subjects 0–7: training uses 100,000 on), each a near-frontal
    neutral enrolment scan and a probe turned 15° with a smile, through a Kinect v2 and the whole preprocessing."""
    scanner = FaceScanner(sensor_profile("kinect-v2"))
    pre = Preprocessor()
    out = {}
    for s in SUBJECTS:
        out[(s, "gallery")] = pre(scanner.scan(ScanSpec(s, seed=0)).scan)
        out[(s, "probe")] = pre(scanner.scan(ScanSpec(s, "smile", 0.7, yaw=15.0, pitch=-5.0, seed=1)).scan)
    return out


def test_shipped_model_loads_with_its_card_and_embeds_the_same_twice(kinect_faces):
    card = read_card(SHIPPED_MODEL)
    assert card["license"] == "MIT" and card["format"] == "onnx"
    recipe = InputRecipe(**card["input"])
    matcher = EmbeddingMatcher()
    face = kinect_faces[(0, "gallery")]
    x = face_input(face, recipe)
    assert x.shape == (N_CHANNELS, recipe.size, recipe.size) and x.dtype == np.float32 and np.isfinite(x).all()
    a, b = matcher.prepare(face), EmbeddingMatcher().prepare(face)  # a second session too
    assert a.shape == (card["embedding_dim"],) and np.array_equal(a, b)
    assert np.linalg.norm(a) == pytest.approx(1.0, abs=1e-5)
    batch = matcher.embed([kinect_faces[(s, "gallery")] for s in SUBJECTS[:3]])
    assert np.allclose(batch[0], a, atol=1e-5)  # batched as one by one


def test_identifies_unseen_synthetic_people_across_pose_and_expression(kinect_faces):
    matcher = EmbeddingMatcher()
    gallery = [matcher.enroll(kinect_faces[(s, "gallery")]) for s in SUBJECTS]
    hits = []
    for s in SUBJECTS:
        ranked = matcher.identify(kinect_faces[(s, "probe")], gallery, k=len(SUBJECTS))
        hits.append(ranked[0][0] == s)
        scores = dict(ranked)
        impostors = [scores[j] for j in SUBJECTS if j != s]
        assert scores[s] > max(impostors)  # the genuine claim above every impostor of this probe
    assert all(hits)


def _cosine_rank1(gallery: np.ndarray, probes: np.ndarray) -> float:
    g = gallery / np.linalg.norm(gallery, axis=1, keepdims=True)
    p = probes / np.linalg.norm(probes, axis=1, keepdims=True)
    return float(np.mean(np.argmax(p @ g.T, axis=1) == np.arange(len(p))))


def test_wccn_shrinks_what_a_cameras_scans_of_one_person_share_and_finds_people_it_hid():
    # people differ in every direction (σ 1); the camera adds a large spread (σ 3) along 4 directions to every scan
    rng = np.random.default_rng(0)
    d, camera = 24, np.linalg.qr(np.random.default_rng(1).normal(size=(24, 4)))[0]

    def scans(people: np.ndarray, seed: int) -> np.ndarray:
        r = np.random.default_rng(seed)
        return people + 3.0 * r.normal(size=(len(people), 4)) @ camera.T + 0.2 * r.normal(size=people.shape)

    others, test = rng.normal(size=(60, d)), rng.normal(size=(100, d))
    train = np.concatenate([scans(others, 10), scans(others, 11), scans(others, 12)])
    mean, W = wccn(train, [f"p{i}" for i in range(60)] * 3, ridge=0.1)
    # within-person differences, mostly along the camera's directions before, evenly spread after (whitened)
    rest = np.linalg.qr(np.concatenate([camera, rng.normal(size=(d, d - 4))], axis=1))[0][:, 4:]
    diff = scans(others, 13) - scans(others, 14)
    before = np.var(diff @ camera) / np.var(diff @ rest)
    after = np.var(diff @ W @ camera) / np.var(diff @ W @ rest)
    assert before > 100 and after < 0.05 * before
    gallery, probes = scans(test, 20), scans(test, 21)  # other people, never trained on
    raw, adapted = _cosine_rank1(gallery, probes), _cosine_rank1((gallery - mean) @ W, (probes - mean) @ W)
    assert raw < 0.6 and adapted > raw + 0.3
    with pytest.raises(FaceRec3DError, match="two or more subjects with two or more scans"):
        wccn(train[:3], ["a", "b", "c"])


def test_the_embedding_adapted_to_a_camera_trains_saves_loads_and_still_identifies(kinect_faces, tmp_path):
    adapted = EmbeddingMatcher(EmbeddingConfig(adapt="wccn"))
    assert adapted.needs_training and not EmbeddingMatcher().needs_training
    with pytest.raises(FaceRec3DError, match="not learnt"):
        adapted.prepare(kinect_faces[(0, "gallery")])
    trained = SUBJECTS[:4]  # scans of other people taken by the camera; subjects 4–7 are tested
    adapted.fit([kinect_faces[(s, k)] for s in trained for k in ("gallery", "probe")],
                [str(s) for s in trained for _ in range(2)])
    adapted.save(tmp_path / "adapted.npz")
    loaded = load_matcher(tmp_path / "adapted.npz")
    face = kinect_faces[(5, "probe")]
    assert np.array_equal(loaded.prepare(face), adapted.prepare(face))
    assert np.linalg.norm(adapted.prepare(face)) == pytest.approx(1.0, abs=1e-5)
    assert not np.allclose(adapted.prepare(face), EmbeddingMatcher().prepare(face), atol=1e-3)
    bad = Template(None, None, "embedding", {"wccn_mean": np.zeros(3), "wccn_matrix": np.eye(2)},
                   {"options": adapted.options(), "state": {}})
    bad.save(tmp_path / "bad.npz")
    with pytest.raises(FaceRec3DError,  # the network's 128 values, not 3: learnt with another model
                       match=r"bad.npz: not a usable embedding model \('wccn_mean' of shape \(3,\), not \(128,\)\)"):
        load_matcher(tmp_path / "bad.npz")
    tested = SUBJECTS[4:]
    gallery = [loaded.enroll(kinect_faces[(s, "gallery")]) for s in tested]
    assert [loaded.identify(kinect_faces[(s, "probe")], gallery, k=1)[0][0] for s in tested] == list(range(len(tested)))


def test_input_channels_hold_depth_normals_and_validity():
    recipe = InputRecipe(half_width_mm=8.0, step_mm=2.0)
    yy, xx = np.mgrid[0:8, 0:8].astype(float) * 2.0
    z = 0.5 * xx  # a plane rising along +x: normal ∝ (−0.5, 0, 1)
    z[0, 0] = np.nan
    x = input_channels(z, recipe)
    n = np.array([-0.5, 0.0, 1.0]) / np.linalg.norm([-0.5, 0.0, 1.0])
    assert np.allclose(x[1:4, 4, 4], n, atol=1e-6)
    assert x[4, 0, 0] == 0 and x[4].sum() == 63 and np.all(x[1:4, 0, 0] == 0)
    assert x[0, 0, 0] in (x[0, 0, 1], x[0, 1, 0])  # the missing cell takes a nearest seen cell's depth
    assert x[0, 3, 5] == pytest.approx(0.5 * 10.0 / recipe.depth_scale_mm)


def test_mirrored_cells_are_not_shown_to_the_network():
    face = model_face(1)
    prov = np.zeros(face.n_points, np.uint8)
    prov[face.points[:, 0] > 20] = MIRRORED
    marked = face.replace(provenance=prov)
    seen = face.subset(face.points[:, 0] <= 20)
    assert np.array_equal(face_input(marked), face_input(seen))
    assert not np.array_equal(face_input(marked), face_input(face))


def test_templates_round_trip_through_the_gallery_store_with_checksums(kinect_faces, tmp_path):
    matcher = EmbeddingMatcher()
    path = tmp_path / "g.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), matcher)
        for s in SUBJECTS[:3]:
            store.add(matcher.enroll(kinect_faces[(s, "gallery")]), f"/data/{s}.png")
    with GalleryStore(path) as store:
        assert store.matcher().name == "embedding"
        loaded = store.templates()
        for s, t in zip(SUBJECTS[:3], loaded):
            assert np.array_equal(t.arrays["embedding"], matcher.enroll(kinect_faces[(s, "gallery")]).arrays["embedding"])
        assert store.matcher().identify(kinect_faces[(1, "probe")], loaded, k=1)[0][0] == 1
    db = sqlite3.connect(path)  # one damaged byte of a stored embedding: refused, named
    blob = bytearray(db.execute("SELECT data FROM arrays WHERE name='embedding' LIMIT 1").fetchone()[0])
    blob[5] ^= 0xFF
    db.execute("UPDATE arrays SET data=? WHERE rowid=(SELECT MIN(rowid) FROM arrays WHERE name='embedding')",
               (bytes(blob),))
    db.commit()
    db.close()
    with GalleryStore(path) as store, pytest.raises(FaceRec3DError, match="checksum"):
        store.templates()


def test_the_embedding_screen_keeps_every_probes_subject_on_a_short_shortlist(kinect_faces):
    """The cascade's embedding screen embeds each enrolled face from its ICP template's points: the same
    embedding as the face's own, and each probe's subject among its 3 best of 8."""
    config = CascadeConfig(screen="embedding", shortlist=3)
    icp = ICPMatcher()
    gallery = np.stack([template_descriptor(icp.enroll(kinect_faces[(s, "gallery")]), config) for s in SUBJECTS])
    own = np.stack([face_descriptor(kinect_faces[(s, "gallery")], config) for s in SUBJECTS])
    assert np.allclose(gallery, own, atol=1e-4)
    for s in SUBJECTS:
        p = face_descriptor(kinect_faces[(s, "probe")], config)
        assert s in np.argsort(-(gallery @ p))[:3]


def test_bad_model_files_give_one_clear_error(tmp_path):
    with pytest.raises(FaceRec3DError, match="no such embedding model"):
        EmbeddingMatcher(EmbeddingConfig(model=str(tmp_path / "missing.onnx")))
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x00not onnx" * 50)
    with pytest.raises(FaceRec3DError, match="junk.json: not a usable model card"):
        EmbeddingMatcher(EmbeddingConfig(model=str(junk)))
    (tmp_path / "junk.json").write_text(json.dumps({"input": {"half_width_mm": 64, "step_mm": 2}}))
    with pytest.raises(FaceRec3DError, match="junk.onnx: not a usable ONNX embedding model"):
        EmbeddingMatcher(EmbeddingConfig(model=str(junk))).prepare(model_face(0))
    (tmp_path / "junk.json").write_text(json.dumps({"input": {"half_width_mm": -3}}))
    with pytest.raises(FaceRec3DError, match="not a usable model card"):
        EmbeddingModel(junk)
    wrong = tmp_path / "wrong.onnx"  # the shipped network with a card that promises another input size
    wrong.write_bytes(SHIPPED_MODEL.read_bytes())
    (tmp_path / "wrong.json").write_text(json.dumps({"input": {"half_width_mm": 32, "step_mm": 2}}))
    with pytest.raises(FaceRec3DError, match="wrong.onnx: not a usable ONNX embedding model|input of shape"):
        EmbeddingMatcher(EmbeddingConfig(model=str(wrong))).prepare(model_face(0))


def test_a_saved_training_set_is_reused_only_with_todays_preprocessing(tmp_path):
    """Training faces made by other preprocessing settings (another version's) are made again, never reused."""
    from facerec3d.training.data import DataRecipe, TrainingSet, cached_training_set

    recipe = DataRecipe(identities=2, scans=2, sensors=("frgc",), identity_profiles=("model",), max_yaw=5.0,
                        max_pitch=3.0, max_roll=2.0, expression_share=0.0)
    inputs = InputRecipe()
    made = cached_training_set(tmp_path / "set.npz", recipe, inputs, progress=False)
    assert made.info["preprocess"] == PreprocessConfig().digest() and len(made.labels) == 4
    marked = TrainingSet(np.full_like(made.windows, 7.0), made.labels, made.sensors, dict(made.info))
    marked.save(tmp_path / "set.npz")
    assert np.all(cached_training_set(tmp_path / "set.npz", recipe, inputs, progress=False).windows == 7.0)
    TrainingSet(marked.windows, marked.labels, marked.sensors, {**marked.info, "preprocess": "0123456789abcdef"}
                ).save(tmp_path / "set.npz")
    again = cached_training_set(tmp_path / "set.npz", recipe, inputs, progress=False)
    assert again.info["preprocess"] == PreprocessConfig().digest()
    assert np.allclose(again.windows, made.windows, equal_nan=True)


def test_the_terrace_augmentation_ripples_depth_by_at_most_a_millimetre_and_keeps_unseen_cells():
    pytest.importorskip("torch")
    from facerec3d.training.embedding import _terraced, augment

    yy, xx = np.mgrid[-40:41, -40:41].astype(float)
    z = 40.0 - (xx ** 2 + yy ** 2) / 80.0  # a dome, 40 mm high
    z[:5] = np.nan
    out = _terraced(z, np.random.default_rng(1))
    d = out - z
    assert np.array_equal(np.isnan(out), np.isnan(z))
    assert 0.2 <= np.nanmax(np.abs(d)) <= 1.0 + 1e-9
    # a ripple along the depth: equal depths move alike, and the shift changes sign across the dome's 40 mm
    ring = np.isclose(z, 30.0)
    assert ring.sum() > 4 and np.ptp(d[ring]) < 1e-9
    assert np.nanmin(d) < 0 < np.nanmax(d)
    recipe = InputRecipe()
    windows = np.repeat(np.nan_to_num(z, nan=0.0)[None, :recipe.size + 8, :recipe.size + 8], 4, axis=0)
    plain = augment(windows, np.random.default_rng(0), recipe, 4, terraces=0.0)
    rippled = augment(windows, np.random.default_rng(0), recipe, 4, terraces=1.0)
    assert plain.shape == rippled.shape and not np.allclose(plain, rippled)


def test_a_tiny_model_trained_here_separates_a_few_identities(tmp_path):
    """Needs the [train] extra (pip install -e '.[train]'); CI without torch skips only this test."""
    pytest.importorskip("torch")
    from facerec3d.training.data import DataRecipe, synthetic_training_set
    from facerec3d.training.embedding import TrainConfig, export, train_embedding

    recipe = DataRecipe(identities=5, scans=4, sensors=("frgc",), identity_profiles=("model",), max_yaw=10.0,
                        max_pitch=5.0, max_roll=3.0, expression_share=0.0)
    inputs = InputRecipe()
    data = synthetic_training_set(recipe, inputs, progress=False)
    assert data.info["failures"] == 0 and len(data.labels) == 20
    net, figures = train_embedding(data.windows, data.labels, inputs, recipe.margin,
                                   TrainConfig(width=8, dim=32, epochs=30, batch=10, validation_share=0.0,
                                               threads=1, lr=3e-3), progress=False)
    assert figures["history"][-1]["loss"] < figures["history"][0]["loss"]
    path = export(net, tmp_path / "tiny.onnx", inputs, {"data": data.info})
    model = EmbeddingModel(path)
    from facerec3d.training.embedding import augment

    e = model.embed(augment(data.windows, np.random.default_rng(0), inputs, recipe.margin, train=False))
    s = e @ e.T
    same = data.labels[:, None] == data.labels[None, :]
    off = ~np.eye(len(e), dtype=bool)
    assert s[same & off].mean() > s[~same].mean() + 0.3
    nearest = np.argmax(np.where(off, s, -np.inf), axis=1)
    assert np.mean(data.labels[nearest] == data.labels) >= 0.9


def test_cli_evaluate_enroll_identify_verify_and_the_embedding_screen(tmp_path):
    from click.testing import CliRunner

    from facerec3d.cli import main

    run = CliRunner()
    data = cli_dataset(tmp_path / "d", 0.6, subjects=4, sensor="kinect-v2")
    cache = str(tmp_path / "cache")
    r = run.invoke(main, ["evaluate", str(data.folder), "--method", "embedding", "--out", str(tmp_path / "run"),
                          "--jobs", "1", "--bootstrap", "0", "--cache", cache])
    assert r.exit_code == 0, r.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["rank1_all"] == 1.0 and metrics["timings"]["matches_per_s"] > 0
    store = str(tmp_path / "e.sqlite")
    r = run.invoke(main, ["enroll", *map(str, data.gallery), "--gallery", store, "--method", "embedding",
                          "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0 and "4 enrolled" in r.output, r.output
    r = run.invoke(main, ["identify", str(data.probe), "--gallery", store, "-k", "2", "--cache", cache])
    assert r.exit_code == 0 and r.output.splitlines()[1].split()[:2] == ["1", data.probe_subject], r.output
    for claim, code in ((data.probe_subject, 0), (data.other, 1)):
        r = run.invoke(main, ["verify", str(data.probe), "--gallery", store, "--claim", claim, "--cache", cache])
        assert r.exit_code == code, r.output
    icp_store = str(tmp_path / "icp.sqlite")
    r = run.invoke(main, ["enroll", *map(str, data.gallery), "--gallery", icp_store, "--method", "icp",
                          "--no-calibrate", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0, r.output
    r = run.invoke(main, ["identify", str(data.probe), "--gallery", icp_store, "-k", "4", "--cascade", "--screen",
                          "embedding", "--shortlist", "2", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0, r.output
    listed = r.output.splitlines()[1:]
    assert listed[0].split()[:2] == ["1", data.probe_subject]
    assert [float(line.split()[-1]) for line in listed[2:]] == [float("-inf")] * 2  # off the shortlist


def test_cli_adapts_the_embedding_to_the_camera_with_scans_of_other_people(tmp_path):
    """`adapt = "wccn"` through evaluate and enroll: it asks for --train in one line, learns from other people's
    scans of the same camera, stores what it learnt with the gallery, and still identifies."""
    from click.testing import CliRunner

    from facerec3d.cli import main

    run = CliRunner()
    data = cli_dataset(tmp_path / "d", 0.6, subjects=3, sensor="kinect-v2")
    r = run.invoke(main, ["synth", str(tmp_path / "t"), "--subjects", "3", "--scans", "2", "--sensor", "kinect-v2",
                          "--first-subject", "1000", "--seed", "6"])
    assert r.exit_code == 0, r.output
    config = str(Path(__file__).parents[1] / "examples" / "embedding-adapted.toml")
    cache, common = str(tmp_path / "cache"), ["--jobs", "1"]
    r = run.invoke(main, ["evaluate", str(data.folder), "--method", "embedding", "--method-config", config,
                          "--out", str(tmp_path / "run0"), "--bootstrap", "0", "--cache", cache, *common])
    assert r.exit_code != 0 and "--train" in r.output and "Traceback" not in r.output, r.output
    r = run.invoke(main, ["evaluate", str(data.folder), "--method", "embedding", "--method-config", config,
                          "--train", str(tmp_path / "t"), "--out", str(tmp_path / "run"), "--bootstrap", "0",
                          "--cache", cache, *common])
    assert r.exit_code == 0, r.output
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["rank1_all"] == 1.0 and metrics["n_train_subjects"] == 3
    store = str(tmp_path / "a.sqlite")
    r = run.invoke(main, ["enroll", *map(str, data.gallery), "--gallery", store, "--method", "embedding",
                          "--method-config", config, "--train", str(tmp_path / "t"), "--cache", cache, *common])
    assert r.exit_code == 0 and "3 enrolled" in r.output, r.output
    with GalleryStore(store) as g:
        assert g.matcher().wccn_ is not None
    r = run.invoke(main, ["identify", str(data.probe), "--gallery", store, "-k", "2", "--cache", cache])
    assert r.exit_code == 0 and r.output.splitlines()[1].split()[:2] == ["1", data.probe_subject], r.output


def test_the_service_enrols_and_identifies_with_the_embedding_and_its_screen(tmp_path, kinect_faces):
    """The service (in process, one worker): an embedding gallery, as it is and adapted to a camera, identifies a
    smiling probe first, and an ICP gallery's cascade with screen=embedding lists only its shortlist, the right
    face first."""
    others = SUBJECTS[3:]  # the service enrols people 0–2
    adapted = EmbeddingMatcher(EmbeddingConfig(adapt="wccn")).fit(
        [kinect_faces[(s, k)] for s in others for k in ("gallery", "probe")], [str(s) for s in others for _ in "ab"])
    for matcher, form in ((EmbeddingMatcher(), {"k": "3"}), (adapted, {"k": "3"}),
                          (ICPMatcher(), {"k": "3", "cascade": "true", "screen": "embedding", "shortlist": "2"})):
        folder = tmp_path / f"{len(list(tmp_path.iterdir()))}"
        folder.mkdir()
        candidates = service_identify(folder, matcher, form)
        assert candidates[0]["subject"] == "s1", candidates
        assert len(candidates) == (2 if "screen" in form else 3)
        assert candidates[0]["score"] > candidates[1]["score"]


def test_training_poses_follow_the_recipes_ranges_and_the_cli_checks_them():
    """`train-embedding --max-yaw / --max-pitch` reach the drawn poses; an identity's first scan is near-frontal."""
    from click.testing import CliRunner

    from facerec3d.cli import main
    from facerec3d.training.data import DataRecipe, training_pose

    rng = np.random.default_rng(0)
    for recipe in (DataRecipe(), DataRecipe(max_yaw=80.0, max_pitch=30.0)):
        poses = np.array([training_pose(rng, recipe) for _ in range(400)])
        limits = np.array([recipe.max_yaw, recipe.max_pitch, recipe.max_roll])
        assert np.all(np.abs(poses) <= limits) and np.all(np.abs(poses).max(axis=0) > 0.9 * limits)
        first = np.array([training_pose(rng, recipe, first=True) for _ in range(100)])
        assert np.all(np.abs(first) <= 0.2 * limits)
    with pytest.raises(ValueError, match="max_yaw"):
        DataRecipe(max_yaw=120.0)
    result = CliRunner().invoke(main, ["train-embedding", "out.onnx", "--max-yaw", "120"])
    assert result.exit_code == 2 and "--max-yaw" in result.output
