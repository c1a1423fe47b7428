"""The model-based methods (chapter §8.10.1, §8.10.3): geometry images from the morphable-model fit, their Haar
coefficients, expression removal (blendshapes, residue PCA), identity coefficients, and the methods through
enrolment, identification and the gallery store."""

import json
import sqlite3

import numpy as np
import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from facerec3d.datasets.synthetic import OCCLUDERS, identity_profile, quick_scan
from facerec3d.errors import FaceRec3DError
from facerec3d.gallery.store import GalleryStore
from facerec3d.matching.afm import AFMConfig, AFMMatcher, haar_pyramid
from facerec3d.matching.base import Template
from facerec3d.matching.morphable import GeometryImageConfig, MorphIDMatcher, RefitConfig, face_fit, geometry_image
from facerec3d.matching.registry import load_matcher, make_matcher
from facerec3d.preprocess.pipeline import MODEL_FIT_KEY, PreprocessConfig, Preprocessor
from tests.conftest import cli_dataset, model_face, service_identify

SUBJECTS = (0, 1, 2, 3)


def with_fit(face):
    """The face with its model fit kept in meta.extra, as preprocessing keeps it (fitted once here)."""
    fit = face_fit(face)
    assert np.allclose(fit.R, np.eye(3), atol=0.1)  # refitted from the frontal pose it is in
    # the refit's pose is not the identity: keep the face moved into the fit's frame, as preprocessing does
    moved = face.transformed(fit.R, fit.t)
    extra = dict(face.meta.extra, **{MODEL_FIT_KEY: {"identity": fit.identity.tolist(),
                                                     "expression": fit.expression.tolist()}})
    return moved.replace(meta=moved.meta.replace(extra=extra))


@pytest.fixture(scope="module")
def faces():
    """Model faces of four test subjects (neutral, smile) and three training subjects (neutral, smile,
    open mouth), each fitted once."""
    out = {(s, e): with_fit(model_face(s, e)) for s in SUBJECTS for e in ("neutral", "smile")}
    out.update({(s, e): with_fit(model_face(s, e)) for s in (20, 21, 22) for e in ("neutral", "smile", "open-mouth")})
    return out


def test_haar_pyramid_is_orthonormal_and_masks_whole_supports():
    rng = np.random.default_rng(0)
    images = rng.normal(size=(2, 16, 16))
    valid = np.ones((16, 16), bool)
    bands = haar_pyramid(images, valid, 3)
    assert [b.shape for b, _ in bands] == [(2, 3, 8, 8), (2, 3, 4, 4), (2, 3, 2, 2), (2, 1, 2, 2)]
    energy = sum(np.sum(b**2) for b, _ in bands)
    assert energy == pytest.approx(np.sum(images**2))  # orthonormal: Parseval
    valid[5, 9] = False
    images[:, 5, 9] = np.nan  # a missing cell may hold anything: it reaches no valid coefficient
    bands = haar_pyramid(images, valid, 3)
    for level, (b, ok) in enumerate(bands[:3]):
        assert np.count_nonzero(~ok) == 1 and not ok[5 >> (level + 1), 9 >> (level + 1)]
        assert np.isfinite(b).all()
    assert np.count_nonzero(~bands[3][1]) == 1


def test_geometry_images_put_the_same_fiducial_at_the_same_place(faces):
    """The fit's dense correspondence: each fiducial lies at the same UV cell on every face, although the faces
    put it at different x–y positions (more than a cell apart)."""
    cfg = GeometryImageConfig()
    names = ("nose_tip", "nose_bridge", "left_eye_inner", "right_eye_inner", "left_eye_outer", "right_eye_outer")
    cells = {name: [] for name in names}
    positions = {name: [] for name in names}
    for s in SUBJECTS:
        face = faces[(s, "neutral")]
        g = geometry_image(face, config=cfg)
        for name in names:
            truth = face.landmarks[name]
            d = np.linalg.norm(np.nan_to_num(g.fitted, nan=1e9) - truth, axis=2)
            cells[name].append(np.unravel_index(np.argmin(d), d.shape))
            positions[name].append(truth[:2])
            assert d.min() < 3.0  # a UV point lies within 3 mm of the true fiducial (cells 2 mm apart)
    for name in names:  # the same cell within ± 1 (4 mm on the model face; the fit has 40 of the faces' 100 modes)
        assert np.ptp(np.array(cells[name]), axis=0).max() <= 2, (name, cells[name])
    for name in ("nose_bridge", "left_eye_inner", "right_eye_outer"):  # while a fixed x–y grid would spread them
        assert np.ptp(np.array(positions[name]), axis=0).max() > 3 * cfg.cell_mm, name


def test_preprocessing_keeps_the_fit_and_its_geometry_image_finds_the_true_fiducials():
    """Through the whole pipeline: a synthetic scan's stored fit puts the generator's true fiducials (mapped
    into the frontal frame) on the geometry image's cells of those fiducials for the model's mean face."""
    ref = geometry_image(model_face(0), config=GeometryImageConfig())  # any face: the cell is the model's
    for subject in (3, 4):
        synth = quick_scan(subject, "smile", yaw=10.0, rows=320, cols=400, focal_px=1000.0)
        face = Preprocessor()(synth.scan)
        assert len(face.meta.extra[MODEL_FIT_KEY]["identity"]) == 40
        assert len(face.meta.extra[MODEL_FIT_KEY]["expression"]) == 53
        M = np.asarray(face.meta.extra["to_frontal"])
        g = geometry_image(face)
        for name in ("nose_tip", "left_eye_inner", "right_eye_outer"):
            truth = M[:, :3] @ synth.landmarks[name] + M[:, 3]
            d = np.linalg.norm(np.nan_to_num(g.points, nan=1e9) - truth, axis=2)
            cell = np.unravel_index(np.argmin(d), d.shape)
            d_ref = np.linalg.norm(ref.fitted - model_face(0).landmarks[name], axis=2)
            assert np.abs(np.subtract(cell, np.unravel_index(np.argmin(d_ref), d_ref.shape))).max() <= 1, name
            assert d.min() < 3.0


def test_the_robust_refit_finds_occluded_faces_outside_the_model():
    """Faces outside the model's span, each seen clean (gallery) and behind a hand, a fringe or glasses (probes,
    another session): with the robust refit (the default) every occluded face is nearer its own clean face than
    anyone else's, and nearer it than with the preprocessing fit alone, whose modes the occluder pulls."""
    pre, outside, small = Preprocessor(), identity_profile("outside-model"), dict(rows=320, cols=400, focal_px=1000.0)
    people = range(6)
    clean = [pre(quick_scan(s, seed=10 + s, identity=outside, **small).scan) for s in people]
    hidden = [[pre(quick_scan(s, seed=20 + s, identity=outside, occluder=o, **small).scan) for s in people]
              for o in OCCLUDERS]
    own = {}
    for name, matcher in (("refit", AFMMatcher()), ("plain", AFMMatcher(AFMConfig(refit=RefitConfig(enabled=False))))):
        gallery = [matcher.enroll(f) for f in clean]
        D = np.array([[matcher.distances(matcher.prepare(f), gallery) for f in row] for row in hidden])  # (o, p, g)
        own[name] = np.einsum("opp->op", D)
        if name == "refit":
            assert (D.argmin(axis=2) == np.arange(len(people))).all(), D.argmin(axis=2)
    assert own["refit"].mean() < 0.7 * own["plain"].mean(), (own["refit"].round(1), own["plain"].round(1))
    morph = MorphIDMatcher()  # its identity coefficients come from the same refit
    gallery = [morph.enroll(f) for f in clean]
    found = [[int(np.argmax(morph.scores(f, gallery)[0])) for f in row] for row in hidden]
    assert (np.array(found) == np.arange(len(people))).all(), found


def test_the_refit_runs_longer_on_laser_fine_faces_only(faces, monkeypatch):
    """afm's and morph-id's refit runs 48 iterations on a face its preprocessing measured finer than 1.5 mm (a laser
    scan) and 6 on a depth camera's coarser faces or a face with no measured pitch; galleries stored before the
    setting keep 6 everywhere."""
    import facerec3d.matching.morphable as morphable

    seen, real = [], morphable.fit_face_model
    monkeypatch.setattr(morphable, "fit_face_model", lambda *a, **k: seen.append(a[3].iterations) or real(*a, **k))
    face = faces[(0, "neutral")]
    assert "quality" not in face.meta.extra
    pitched = lambda p: face.replace(meta=face.meta.replace(extra=dict(face.meta.extra, quality={"pitch_mm": p})))
    before = {"refit": {k: v for k, v in RefitConfig().__dict__.items() if k != "fine_iterations"}}
    for config, cases in ((AFMConfig().refit, ((pitched(0.72), 48), (pitched(3.5), 6), (face, 6))),
                          (MorphIDMatcher().config.refit, ((pitched(0.72), 48), (pitched(3.5), 6))),
                          (AFMMatcher.from_stored(before).config.refit, ((pitched(0.72), 6),)),
                          (MorphIDMatcher.from_stored(before).config.refit, ((pitched(0.72), 6),))):
        for scan, iterations in cases:
            seen.clear()
            morphable.refit(scan, config)
            assert seen == [iterations]


def distances(matcher, faces, probe_expression):
    gallery = [matcher.enroll(faces[(s, "neutral")]) for s in SUBJECTS]
    return np.array([matcher.distances(matcher.prepare(faces[(s, probe_expression)]), gallery) for s in SUBJECTS])


def test_expression_removal_brings_a_smile_closer_to_its_own_neutral_face(faces):
    """Each subject's smiling face is nearer its own neutral face than anyone else's after removal (blendshapes
    or the residue model learnt from other subjects), and the removal shrinks the distance to its own face. Scored
    on the whole face (one region): the default's nearest regions would leave the smile's regions out by themselves."""
    whole = dict(regions=1, keep_regions=1.0)
    raw = distances(AFMMatcher(AFMConfig(expression="none", **whole)), faces, "smile")
    removed = distances(AFMMatcher(AFMConfig(expression="blendshapes", **whole)), faces, "smile")
    train = [(s, e) for s in (20, 21, 22) for e in ("neutral", "smile", "open-mouth")]
    residue = AFMMatcher(AFMConfig(expression="residue", **whole))
    residue.fit([faces[k] for k in train], [str(s) for s, _ in train])
    learnt = distances(residue, faces, "smile")
    for D in (removed, learnt):
        assert np.all(np.diag(D) < np.min(D + np.diag(np.full(len(D), np.inf)), axis=1)), D
    for D in (removed, learnt):  # nearer its own neutral face than without removal: on average by half or more
        assert np.all(np.diag(D) < np.diag(raw)) and np.mean(np.diag(D)) < 0.5 * np.mean(np.diag(raw)), (D, raw)


def test_afm_scores_are_the_masked_rms_of_the_shared_coefficients(faces):
    m = AFMMatcher(AFMConfig(expression="none", regions=1, keep_regions=1.0))  # one score: the masked RMS
    gallery = [m.enroll(faces[(s, "neutral")]) for s in SUBJECTS]
    probe = m.prepare(faces[(0, "smile")])
    assert probe.arrays["coefficients"].shape == (3 * 1024,) and probe.arrays["valid"].shape == (1024,)
    direct = []
    for t in gallery:
        both = probe.arrays["valid"] & t.arrays["valid"]
        diff = (probe.arrays["coefficients"].astype(float) - t.arrays["coefficients"]).reshape(3, -1)[:, both]
        direct.append(-np.sqrt(np.sum(diff**2) / both.sum()))
    np.testing.assert_allclose(m.scores(probe, gallery)[0], direct, atol=1e-3)
    # masked, not zero-filled: a face missing half its coefficients is still at distance 0 from itself
    half = Template(None, None, "afm", {"coefficients": gallery[1].arrays["coefficients"] * 1,
                                        "valid": gallery[1].arrays["valid"] & (np.arange(1024) % 2 == 0)})
    half.arrays["coefficients"][np.tile(~half.arrays["valid"], 3)] = 1e6  # what a missing coefficient holds is unused
    assert m.score(half, gallery[1]) == pytest.approx(0.0, abs=0.01)  # float32 sums: µm
    assert m.scores(half, [gallery[1], gallery[2]])[0][0] == pytest.approx(0.0, abs=0.01)
    assert m.score(half, gallery[2]) == pytest.approx(m.score(gallery[1], gallery[2]), rel=0.2)


def test_identity_coefficients_identify_through_expressions(faces):
    m = MorphIDMatcher()
    gallery = [m.enroll(faces[(s, "neutral")]) for s in SUBJECTS]
    for s in SUBJECTS:
        assert m.identify(faces[(s, "smile")], gallery, k=1)[0][0] == SUBJECTS.index(s)


def test_model_methods_through_the_store_and_a_saved_model(tmp_path, faces):
    train = [(s, e) for s in (20, 21, 22) for e in ("neutral", "smile", "open-mouth")]
    for method, options in (("afm", None), ("afm", {"expression": "residue"}), ("morph-id", None)):
        matcher = make_matcher(method, options)
        if matcher.needs_training:
            matcher.fit([faces[k] for k in train], [str(s) for s, _ in train])
            matcher.save(tmp_path / "model.npz")
            reloaded = load_matcher(tmp_path / "model.npz")
            np.testing.assert_array_equal(reloaded.residue_.components, matcher.residue_.components)
            arrays, attrs = matcher.state()  # a damaged residue model is refused when loaded, not used
            d, p = arrays["residue_components"].shape
            for change, reason in (({"residue_components": arrays["residue_components"][:100]},
                                    rf"'residue_components' of shape \(100, {p}\), not \({d}, {p}\)"),
                                   ({"residue_eigenvalues": arrays["residue_eigenvalues"][:-1]},
                                    rf"'residue_eigenvalues' of shape \({p - 1},\), not \({p},\)"),
                                   ({"residue_components": np.full((d, p), np.nan)},
                                    "'residue_components' holds NaN or infinite values")):
                Template(None, None, "afm", {**arrays, **change}, {"options": matcher.options(), "state": attrs}
                         ).save(tmp_path / "bad.npz")
                with pytest.raises(FaceRec3DError, match=rf"bad.npz: not a usable afm model \({reason}\)$"):
                    load_matcher(tmp_path / "bad.npz")
        path = tmp_path / f"{method}-{bool(options)}.sqlite"
        with GalleryStore(path, create=True) as store:
            store.bind(PreprocessConfig(), matcher)
            for s in SUBJECTS:
                store.add(matcher.enroll(faces[(s, "neutral")]), f"/data/{s}.abs")
        with GalleryStore(path) as store:
            again, templates = store.matcher(), store.templates()
            assert again.options() == matcher.options()
            for s in SUBJECTS:
                best = again.identify(faces[(s, "smile")], templates, k=2)
                assert templates[best[0][0]].subject == f"s{s}" and best[0][1] > best[1][1]


@pytest.mark.parametrize("method", ["afm", "morph-id"])
def test_a_gallery_stored_before_the_refit_keeps_working_without_it(tmp_path, method):
    """Options stored before `refit` existed load with the refit off (the templates were made without it), while a
    new gallery's and a saved model's options keep it as stored."""
    path = tmp_path / "old.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), make_matcher(method))
    assert GalleryStore(path).matcher().config.refit.enabled
    db = sqlite3.connect(path)
    with db:
        options = json.loads(db.execute("SELECT value FROM meta WHERE key = 'options'").fetchone()[0])
        del options["refit"]
        db.execute("UPDATE meta SET value = ? WHERE key = 'options'", (json.dumps(options),))
    db.close()
    with GalleryStore(path) as store:
        old = store.matcher()
    assert not old.config.refit.enabled and old.config.refit == RefitConfig(enabled=False, fine_iterations=0)
    assert {k: v for k, v in old.options().items() if k != "refit"} == options
    assert make_matcher(method, options).config.refit.enabled  # options a user gives take today's default


def test_cli_enroll_identify_verify_with_afm_and_morph_id(tmp_path):
    run = CliRunner()
    _, gallery_scans, probe, probe_subject, other = cli_dataset(tmp_path / "d", 0.8)
    cache = str(tmp_path / "cache")
    for method in ("afm", "morph-id"):
        store = str(tmp_path / f"{method}.sqlite")
        r = run.invoke(main, ["enroll", *map(str, gallery_scans), "--gallery", store, "--method", method,
                              "--jobs", "1", "--cache", cache])
        assert r.exit_code == 0 and "3 enrolled" in r.output, r.output
        r = run.invoke(main, ["identify", str(probe), "--gallery", store, "-k", "3", "--cache", cache])
        assert r.exit_code == 0, r.output
        assert r.output.splitlines()[1].split()[:2] == ["1", probe_subject], r.output
        r = run.invoke(main, ["gallery", store, "stats"])
        assert "3 entries of 3 subjects" in r.output
    threshold = "-0.8"  # afm: mean RMS coefficient distance (mm) of the nearest regions below 0.8 (FMR 1 % on the
    #                     synthetic outside-model set: -0.85)
    r = run.invoke(main, ["verify", str(probe), "--gallery", str(tmp_path / "afm.sqlite"), "--claim", probe_subject,
                          "--threshold", threshold, "--cache", cache])
    assert r.exit_code == 0 and r.output.startswith("accept"), r.output
    r = run.invoke(main, ["verify", str(probe), "--gallery", str(tmp_path / "afm.sqlite"), "--claim", other,
                          "--threshold", threshold, "--cache", cache])
    assert r.exit_code == 1 and r.output.startswith("reject"), r.output


def test_the_service_enrols_and_identifies_with_afm(tmp_path):
    """The service (in process, one worker) enrols a raw scan with afm and identifies a probe of the same person
    (with another expression) first."""
    candidates = service_identify(tmp_path, AFMMatcher(), {"k": "3"})
    assert candidates[0]["subject"] == "s1" and candidates[0]["score"] > candidates[1]["score"]


def test_region_scores_ignore_an_occluded_region(faces):
    """Scored by regions, averaging the nearest half, a probe with one region covered (coefficients moved 20 mm,
    as an occluder would) stays as near its own face; the whole-face RMS grows several-fold."""
    whole = AFMMatcher(AFMConfig(expression="none", regions=1, keep_regions=1.0))
    by_region = AFMMatcher(AFMConfig(expression="none", regions=4, keep_regions=0.5))
    for m in (whole, by_region):
        gallery = [m.enroll(faces[(s, "neutral")]) for s in SUBJECTS]
        probe = m.prepare(faces[(1, "neutral")])
        probe.arrays["coefficients"] = probe.arrays["coefficients"] + 0.05  # a little noise-like offset
        before = m.distances(probe, gallery)
        c = probe.arrays["coefficients"].reshape(3, 16, -1).copy()
        c[:, 5] += 20.0  # region 5 (second row, second column) covered
        covered = Template(None, None, "afm", {"coefficients": c.reshape(-1), "valid": probe.arrays["valid"]})
        after = m.distances(covered, gallery)
        assert np.argmin(before) == 1
        if m is whole:
            assert after[1] > 5 * before[1]
        else:
            assert np.argmin(after) == 1 and after[1] == pytest.approx(before[1], rel=0.05)
