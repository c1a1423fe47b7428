"""A gallery's verification threshold calibrated on its own sensor's scans, recorded and used by verify.

The −1.8 mm² ICP default sits at the EER of synthetic laser scans; on Kinect-class depth (4–8 mm steps) genuine
pairs score well below it, so it rejects genuine claims: a calibrated gallery must accept them at a known FMR."""

import numpy as np
import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from facerec3d.datasets.synthetic import DatasetConfig, sensor_profile, write_dataset
from facerec3d.errors import threshold_text
from facerec3d.evaluation.calibrate import (OWN_SCANS, calibrate, calibration_scores, expected_fmr, gallery_records,
                                            threshold_at_fmr, threshold_record, too_few_pairs)
from facerec3d.evaluation.metrics import eer, roc
from facerec3d.gallery.engine import Engine
from facerec3d.gallery.service import DEFAULT_THRESHOLDS, enroll_scans, gallery_threshold, scan_records, verify_scan
from facerec3d.gallery.store import GalleryError, GalleryStore
from facerec3d.matching.registry import make_matcher


@pytest.fixture(scope="module")
def kinect(tmp_path_factory):
    """5 subjects x 3 scans of the synthetic 8-bit Kinect v2 (4/8 mm depth steps), FRGC layout."""
    root = tmp_path_factory.mktemp("kinect")
    cfg = DatasetConfig(subjects=5, scans=3, scanner=sensor_profile("kinect-v2-8bit"), seed=4)
    write_dataset(root / "data", cfg)
    return root / "data"


@pytest.fixture(scope="module")
def gallery(kinect, tmp_path_factory):
    path = tmp_path_factory.mktemp("g") / "g.sqlite"
    with GalleryStore(path, create=True) as store, Engine.create(1) as engine:
        report = enroll_scans(store, scan_records([kinect]), make_matcher("icp"), engine=engine)
    assert report.enrolled == 15 and not report.failures
    return path


def test_eer_threshold_is_the_scores_own_and_verify_uses_it(gallery):
    with GalleryStore(gallery) as store, Engine.create(1) as engine:
        assert store.threshold() is None
        genuine, impostor, failed = calibration_scores(store, scan_records([store.entries()[0].source]),
                                                       engine=engine)
        assert failed == 0 and len(impostor) == 12 and len(genuine) == 2  # its own entry left out
        record = calibrate(store, None, fmr=None, engine=engine)
        g, i, _ = calibration_scores(store, gallery_records(store), engine=engine)
    assert record["rule"] == "eer" and record["genuine_pairs"] == len(g) == 30 and record["impostor_pairs"] == 180
    assert record["eer"] == pytest.approx(eer(g, i))
    fmr = np.mean(i >= record["value"])
    tar = np.mean(g >= record["value"])
    assert abs((1 - tar) - fmr) <= 1 / 30 + 1 / 180  # at the crossing, to one pair
    with GalleryStore(gallery) as store:
        assert store.threshold()["value"] == record["value"]
        source = store.entries(subject=store.entries()[0].subject)[1].source
        accepted, score, threshold = verify_scan(store, source, claim=str(store.entries()[0].subject))
    assert threshold == record["value"] and accepted == (score >= record["value"])


def test_calibrated_threshold_accepts_the_genuine_kinect_claims_the_laser_default_rejects(gallery):
    with GalleryStore(gallery) as store, Engine.create(1) as engine:
        record = calibrate(store, None, fmr=0.05, engine=engine)
        g, i, _ = calibration_scores(store, gallery_records(store), engine=engine)
    laser = DEFAULT_THRESHOLDS["icp"]
    assert record["value"] < laser  # Kinect depth steps: genuine MSE of several mm²
    assert np.mean(i >= record["value"]) <= 0.05
    assert np.mean(g >= record["value"]) > np.mean(g >= laser)
    fmr, tar, thr = roc(g, i)
    assert record["value"] in thr  # a threshold of the scores' own ROC


def test_calibration_needs_impostors_and_genuine_pairs_for_the_eer(tmp_path, kinect):
    path = tmp_path / "one.sqlite"
    one = [r for r in scan_records([kinect]) if r.subject == scan_records([kinect])[0].subject][:1]
    with GalleryStore(path, create=True) as store, Engine.create(1) as engine:
        enroll_scans(store, one, make_matcher("icp"), engine=engine)
        with pytest.raises(GalleryError, match="no impostor pair"):
            calibrate(store, None, engine=engine)
        with pytest.raises(GalleryError, match="no calibrated verification threshold"):
            gallery_threshold(store, "region-icp")  # a method without a default


def test_cli_enroll_calibrates_and_stats_show_it(kinect, tmp_path):
    g = tmp_path / "g.sqlite"
    run = CliRunner().invoke(main, ["enroll", str(kinect), "--gallery", str(g), "--jobs", "1"])
    assert run.exit_code == 0, run.output
    assert "verification threshold" in run.output and "recorded" in run.output
    stats = CliRunner().invoke(main, ["gallery", str(g), "stats"])
    assert "verification threshold" in stats.output
    run = CliRunner().invoke(main, ["gallery", str(g), "calibrate", "--eer", "--jobs", "1"])
    assert run.exit_code == 0 and "(eer:" in run.output, run.output
    with GalleryStore(g) as store:
        assert store.threshold()["rule"] == "eer"
    few = CliRunner().invoke(main, ["gallery", str(g), "calibrate", "--fmr", "0.0001", "--jobs", "1"])
    assert few.exit_code == 0 and "too few impostor pairs" in few.output, few.output
    with GalleryStore(g) as store, Engine.create(1) as engine:
        _, impostor, _ = calibration_scores(store, gallery_records(store), engine=engine)
        assert impostor.max() < store.threshold()["value"] == pytest.approx(impostor.max())  # no impostor accepted


def test_threshold_at_fmr_counts_impostors_and_ties():
    imp = np.array([5.0, 4.0, 4.0, 3.0, 2.0, 1.0, 0.0, -1.0, -2.0, -3.0])
    assert threshold_at_fmr(imp, 0.1) == 5.0  # one impostor of ten accepted
    t = threshold_at_fmr(imp, 0.2)  # 4.0 would accept three: just above it, one
    assert 4.0 < t < 5.0 and np.mean(imp >= t) <= 0.2
    assert threshold_at_fmr(imp, 0.3) == 4.0
    assert 5.0 < threshold_at_fmr(imp, 0.01) < 5.0 + 1e-9  # fewer than one allowed: above them all


def test_a_gallery_of_one_scan_per_person_calibrates_on_impostors_alone(kinect, tmp_path):
    firsts = {}
    for r in scan_records([kinect]):
        firsts.setdefault(r.subject, r)
    path = tmp_path / "firsts.sqlite"
    with GalleryStore(path, create=True) as store, Engine.create(1) as engine:
        enroll_scans(store, list(firsts.values()), make_matcher("icp"), engine=engine)
        record = calibrate(store, None, fmr=0.05, engine=engine)
        _, impostor, _ = calibration_scores(store, gallery_records(store), engine=engine)
    assert record["genuine_pairs"] == 0 and record["impostor_pairs"] == impostor.size == 20
    assert record["value"] == threshold_at_fmr(impostor, 0.05) and record["fmr"] <= 0.05


def test_enrolling_more_keeps_a_threshold_calibrated_on_scans_given_for_it(kinect, gallery, tmp_path):
    """A user's deliberate calibration (`gallery G calibrate SCANS`) is not replaced behind their back by the
    self-calibration that `enroll` runs after adding a face; a self-calibrated threshold still follows the gallery."""
    import shutil

    g = tmp_path / "g.sqlite"
    shutil.copy(gallery, g)
    run = CliRunner().invoke(main, ["gallery", str(g), "calibrate", str(kinect), "--eer", "--jobs", "1"])
    assert run.exit_code == 0, run.output
    with GalleryStore(g) as store:
        chosen = store.threshold()
    assert chosen["data"] == "calibration scans"
    more = tmp_path / "more"
    write_dataset(more, DatasetConfig(subjects=1, scans=1, first_subject=50, scanner=sensor_profile("kinect-v2-8bit"),
                                      seed=9))
    run = CliRunner().invoke(main, ["enroll", str(more), "--gallery", str(g), "--method", "icp", "--jobs", "1"])
    assert run.exit_code == 0 and "1 enrolled" in run.output, run.output
    assert "kept the verification threshold" in run.output
    assert f"calibrated when the gallery held {chosen['entries']} entries, it holds {chosen['entries'] + 1} now" \
        in run.output, run.output
    with GalleryStore(g) as store:
        assert store.threshold() == chosen
    # a gallery whose threshold came from its own scans is calibrated again when it grows
    own = tmp_path / "own.sqlite"
    shutil.copy(gallery, own)
    with GalleryStore(own) as store, Engine.create(1) as engine:
        calibrate(store, None, fmr=0.01, engine=engine)
        before = store.threshold()
    assert before["data"] == OWN_SCANS
    # (and enrolling into an existing gallery without --method takes the gallery's own, icp, not the default fusion)
    run = CliRunner().invoke(main, ["enroll", str(more), "--gallery", str(own), "--jobs", "1"])
    assert run.exit_code == 0 and "recorded in" in run.output, run.output
    with GalleryStore(own) as store:
        assert store.threshold()["entries"] == before["entries"] + 1
    # entries added with no calibration after them (--no-calibrate, or an enrolment interrupted before it): the
    # next enrolment calibrates again, though it adds nothing
    late = tmp_path / "late"
    write_dataset(late, DatasetConfig(subjects=1, scans=1, first_subject=60, scanner=sensor_profile("kinect-v2-8bit"),
                                      seed=9))
    run = CliRunner().invoke(main, ["enroll", str(late), "--gallery", str(own), "--jobs", "1", "--no-calibrate"])
    assert run.exit_code == 0 and "recorded in" not in run.output, run.output
    run = CliRunner().invoke(main, ["enroll", str(late), "--gallery", str(own), "--jobs", "1"])
    assert run.exit_code == 0 and "0 enrolled, 1 already enrolled" in run.output and "recorded in" in run.output, \
        run.output
    with GalleryStore(own) as store:
        assert store.threshold()["entries"] == before["entries"] + 2 == len(store.entries())
    run = CliRunner().invoke(main, ["enroll", str(late), "--gallery", str(own), "--jobs", "1"])
    assert run.exit_code == 0 and "recorded in" not in run.output, run.output  # up to date: not again


def test_a_printed_threshold_reads_back_as_itself_not_as_the_score_below_it(gallery, tmp_path):
    """A threshold stored just above an integer score (6.000000000000001) printed as "threshold 6", so "reject:
    claim X, score 6.0000 (threshold 6)" could be read; verify, stats and calibrate print every digit it takes
    (and the short form where that is the number)."""
    import re
    import shutil

    g = tmp_path / "g.sqlite"
    shutil.copy(gallery, g)
    above = float(np.nextafter(6.0, np.inf))
    with GalleryStore(g) as store:
        store.set_threshold({"value": above, "rule": "fmr=0.01", "data": "x", "entries": 15, "calibrated_at": "now"})
        entry = store.entries()[0]
        probe = store.entries(subject=entry.subject)[1].source
    run = CliRunner().invoke(main, ["gallery", str(g), "stats"])
    assert "verification threshold 6.000000000000001 (fmr=0.01, x, 15 entries, now)" in run.output, run.output
    run = CliRunner().invoke(main, ["verify", str(probe), "--gallery", str(g), "--claim", str(entry.subject)])
    assert run.exit_code == 1 and "(threshold 6.000000000000001)" in run.output, run.output
    run = CliRunner().invoke(main, ["verify", str(probe), "--gallery", str(g), "--claim", str(entry.subject),
                                    "--threshold", "-100"])
    assert run.exit_code == 0 and "(threshold -100)" in run.output, run.output
    run = CliRunner().invoke(main, ["gallery", str(g), "calibrate", "--jobs", "1"])  # just above the highest
    printed = re.search(r"verification threshold (\S+) \(", run.output)
    with GalleryStore(g) as store:
        assert printed and float(printed[1]) == store.threshold()["value"], run.output
    assert [threshold_text(t) for t in (6.000000000000001, 6.0, -1.8, 0.5, -2.522, -2.5224)] == \
        ["6.000000000000001", "6", "-1.8", "0.5", "-2.522", "-2.5224"]


def test_a_threshold_needs_impostor_scores_that_vary():
    """One impostor pair, or pairs that all score alike (a fusion's per-probe normalisation over a one-person
    gallery gives 0 to every score), place no threshold: refused, where a threshold just above that one score was
    recorded and accepted impostors once the gallery grew."""
    for impostor in (np.array([0.37]), np.zeros(12)):
        with pytest.raises(ValueError, match="give no spread of scores"):
            threshold_record(np.zeros(0), impostor, 0.01, scans=3, failed=0, data="x", entries=1)
    record = threshold_record(np.zeros(0), np.array([0.1, 0.3]), 0.5, scans=2, failed=0, data="x", entries=2)
    assert record["value"] == 0.3 and record["impostor_pairs"] == 2


def test_enrolling_through_the_service_calibrates_its_gallery_as_a_local_calibration_does(kinect, tmp_path,
                                                                                          monkeypatch):
    """cal19 item 1: `enroll --server` ends by calibrating the service's gallery (a new one: the default method,
    normalised over the gallery) on the scans of the enrolment it holds, sent to POST /v1/calibrate since the
    service keeps only templates; admin keys only (an enrol-only key's enrolment stands, uncalibrated, in one
    line). The store then holds the threshold a local calibration of the same gallery on those scans gives, and
    the service verifies with it; `gallery --server URL calibrate SCANS` does the same on scans given for it."""
    import sqlite3

    pytest.importorskip("fastapi")
    pytest.importorskip("httpx")
    from fastapi.testclient import TestClient

    import facerec3d.cli as cli
    from facerec3d.client import Client
    from facerec3d.config import DEFAULT_METHOD
    from facerec3d.server.app import Service, ServiceSettings, create_app
    from facerec3d.server.keys import KeyFile, add_key
    from facerec3d.server.live import AuditLog, LiveGallery

    people = sorted({r.subject for r in scan_records([kinect])})[:3]
    records = [r for r in scan_records([kinect]) if r.subject in people]  # 3 people x 3 scans
    paths = [str(r.path) for r in records]
    gallery, keys, url = tmp_path / "g.sqlite", tmp_path / "keys.json", "http://testserver"
    admin, desk = add_key(keys, "admin", "enrol,query,admin"), add_key(keys, "desk", "enrol")
    service = Service(LiveGallery(gallery, 1, audit=AuditLog(None)), KeyFile(keys), ServiceSettings(timeout_s=600))
    app = create_app(service)

    def in_process(server, api_key):  # the CLI's client, talking to the service in this process
        client = Client(server, api_key)
        client._http.close()
        client._http = TestClient(app, base_url=server, headers=client._http.headers)
        return client

    monkeypatch.setattr(cli, "_client", in_process)
    try:
        run = CliRunner(env={"FACEREC3D_API_KEY": desk}).invoke(main, ["enroll", *paths[:-1], "--server", url,
                                                                       "--jobs", "1"])
        assert run.exit_code == 0 and "8 enrolled, 0 already enrolled, 0 failed" in run.output, run.output
        assert "verification threshold not calibrated: service error 403: key 'desk' has no 'admin' scope" \
            in run.output, run.output
        with GalleryStore(gallery) as store:
            assert store.threshold() is None and store.stats()["method"] == DEFAULT_METHOD
        run = CliRunner(env={"FACEREC3D_API_KEY": admin}).invoke(main, ["enroll", *paths, "--server", url,
                                                                        "--jobs", "1"])
        assert run.exit_code == 0 and "1 enrolled, 8 already enrolled" in run.output, run.output
        assert f"; {OWN_SCANS}) recorded in {url}" in run.output, run.output  # on all 9: those it held too
        with GalleryStore(gallery) as store:
            remote = store.threshold()
        assert remote["data"] == OWN_SCANS and remote["scans"] == 9 and remote["entries"] == 9
        assert f"verification threshold {threshold_text(remote['value'])} (fmr=0.01" in run.output
        probe = records[1].path  # the service verifies with the threshold it recorded
        answer = in_process(url, admin).verify(probe, claim=records[1].subject)
        assert answer["threshold"] == remote["value"]
        run = CliRunner(env={"FACEREC3D_API_KEY": admin}).invoke(
            main, ["gallery", "--server", url, "calibrate", *paths, "--fmr", "0.05"])
        assert run.exit_code == 0 and f"; calibration scans) recorded in {url}" in run.output, run.output
        with GalleryStore(gallery) as store:
            given = store.threshold()
    finally:
        service.close()
    copy = tmp_path / "copy.sqlite"  # a local calibration of the same gallery on the same scans
    with sqlite3.connect(gallery) as source, sqlite3.connect(copy) as target:
        source.backup(target)
    for fmr, theirs in ((0.01, remote), (0.05, given)):
        with GalleryStore(copy) as store, Engine.create(1) as engine:
            local = calibrate(store, records, fmr=fmr, engine=engine)
        same = ("rule", "fmr", "impostor_pairs", "genuine_pairs", "tar", "eer", "scans", "entries")
        assert {k: local[k] for k in same} == {k: theirs[k] for k in same}
        # the same threshold; to the bit until 2026-12-05, since then (the nose proposer's detections) 2e-8 apart at
        # fmr 0.05: the service and the local run sum the same scores in another order (faces and embeddings are
        # the same to the bit across processes and batch sizes); any other face would move it by far more
        assert local["value"] == pytest.approx(theirs["value"], rel=1e-7, abs=0)
        assert local["genuine_pairs"] == 9 * 2  # each scan's own entry left out (by its bytes: no file behind it)


def test_a_gallery_normalised_method_calibrates_its_impostor_pairs_as_strangers_claims(kinect, tmp_path):
    """Hunt 4, bug 1: a fusion gallery of 3 scans per person calibrated on its own scans at FMR 1 % let 44 % of
    strangers' claims through. Each calibration scan's impostor scores were normalised over a cohort holding its
    own subject's other entries, whose high scores lower every other z-score; a stranger's cohort holds none.
    Now an impostor pair is scored as a stranger's claim is (the gallery without the claimant's entries) and a
    genuine one as a new scan of an enrolled person is (the gallery without its own entry), checked against
    `scores` of exactly those galleries, and strangers' claims pass at about the stated rate."""
    from facerec3d.preprocess.batch import preprocess_file

    matcher = make_matcher("fusion", {"members": ["icp"]})  # z-scored over the gallery: a cohort method, and quick
    path, cache = tmp_path / "g.sqlite", tmp_path / "cache"  # (each scan preprocessed once)
    with GalleryStore(path, create=True) as store, Engine.create(1) as engine:
        report = enroll_scans(store, scan_records([kinect]), matcher, engine=engine, cache=cache)
        assert report.enrolled == 15 and not report.failures
        records = gallery_records(store)
        genuine, impostor, failed = calibration_scores(store, records, engine=engine, cache=cache)
        entries, matcher, config = store.entries(), store.matcher(), store.preprocess_config()
        templates = store.templates(entries)
    assert failed == 0 and len(genuine) == 15 * 2 and len(impostor) == 15 * 12
    want_genuine, want_impostor = [], []
    for r in records:  # the reference: the scan scored against exactly the gallery its claim meets
        probe = matcher.prepare(preprocess_file(r.path, config, cache).face)
        mine = [e.subject == r.subject for e in entries]
        own = [e.source == str(r.path) for e in entries]
        without_own = [t for t, o in zip(templates, own) if not o]
        s = matcher.scores(probe, without_own)[0]
        want_genuine += [x for x, m, o in zip(s, [m for m, o in zip(mine, own) if not o], own) if m]
        want_impostor += list(matcher.scores(probe, [t for t, m in zip(templates, mine) if not m])[0])
    np.testing.assert_allclose(np.sort(genuine), np.sort(want_genuine), rtol=1e-12)
    np.testing.assert_allclose(np.sort(impostor), np.sort(want_impostor), rtol=1e-12)

    strangers = tmp_path / "strangers"  # people the gallery does not hold, each claiming every enrolled person
    write_dataset(strangers, DatasetConfig(subjects=3, scans=2, scanner=sensor_profile("kinect-v2-8bit"), seed=9,
                                           first_subject=500))
    claims, accepted, threshold = 0, 0, threshold_at_fmr(impostor, 0.01)  # what `calibrate` records
    with GalleryStore(path) as store:
        for r in scan_records([strangers]):
            for claim in sorted({e.subject for e in entries}):
                claims += 1
                accepted += verify_scan(store, r.path, claim=claim, threshold=threshold, cache=cache)[0]
    assert claims == 30 and accepted <= 3, f"{accepted} of {claims} strangers' claims accepted at {threshold:.3f}"


def test_a_threshold_record_by_hand_at_an_fmr_and_at_the_eer():
    """The record's figures are those of its threshold, accepting score >= value: genuine .9 .8 .4, impostor .7 .3
    .2 .1 (test_metrics' ROC by hand). At FMR 25 %: one impostor of four accepted, the threshold is .7 and accepts
    it (FMR .25, TAR 2/3). At the EER (.25, crossed between t = .7 and t = .4, nearer .7) the threshold is .7."""
    genuine, impostor = np.array([0.9, 0.8, 0.4]), np.array([0.7, 0.3, 0.2, 0.1])
    at_fmr = threshold_record(genuine, impostor, 0.25, scans=7, failed=0, data="x", entries=7)
    assert at_fmr["value"] == 0.7 and at_fmr["rule"] == "fmr=0.25"
    assert at_fmr["fmr"] == 0.25 and at_fmr["tar"] == pytest.approx(2 / 3) and at_fmr["eer"] == pytest.approx(0.25)
    at_eer = threshold_record(genuine, impostor, None, scans=7, failed=0, data="x", entries=7)
    assert at_eer["value"] == 0.7 and at_eer["rule"] == "eer"
    assert at_eer["fmr"] == 0.25 and at_eer["tar"] == pytest.approx(2 / 3)


def test_a_threshold_above_every_impostor_pair_admits_one_stranger_in_n_plus_one():
    """With fewer impostor pairs than 1 / FMR (three people give six), the threshold lies just above the highest
    of them: none of them passes, but a new stranger's claim is as likely as any of the n to be the highest, so it
    passes 1 time in n + 1, far above the FMR asked. The record says so, and `too_few_pairs` flags it (measured on
    synthetic Kinect v2 galleries with the default fusion: 3 people 15 of 108 strangers' claims accepted, 14.3 %
    expected; 5 people 11 of 180, 4.8 % expected; calibrated on 12 other people's 36 scans, 1 of 108 at 1 %)."""
    rng = np.random.default_rng(0)
    for n in (6, 20):
        draws = rng.normal(size=(20000, n + 1))  # n calibration pairs and one new stranger's claim, per trial
        t = np.array([threshold_at_fmr(d[:n], 0.01) for d in draws])
        assert np.mean(draws[:, n] >= t) == pytest.approx(expected_fmr(n), abs=0.01)
        record = threshold_record(np.zeros(0), draws[0, :n], 0.01, scans=3, failed=0, data="x", entries=3)
        assert record["fmr"] == 0 and record["asked_fmr"] == 0.01
        assert record["expected_fmr"] == expected_fmr(n) == too_few_pairs(record)
    enough = threshold_record(np.zeros(0), rng.normal(size=200), 0.01, scans=20, failed=0, data="x", entries=20)
    assert "expected_fmr" not in enough and too_few_pairs(enough) is None
    near = threshold_record(np.zeros(0), rng.normal(size=90), 0.01, scans=10, failed=0, data="x", entries=10)
    assert near["expected_fmr"] == pytest.approx(1 / 91) and too_few_pairs(near) is None  # within twice the FMR
    for damaged in (None, {}, {"expected_fmr": "0.2", "asked_fmr": 0.01}, {"expected_fmr": 0.2}, {
            "expected_fmr": True, "asked_fmr": 0.01}, {"expected_fmr": float("nan"), "asked_fmr": 0.01}):
        assert too_few_pairs(damaged) is None


def test_verify_says_when_a_small_gallerys_threshold_lets_strangers_through(kinect, tmp_path):
    """A gallery of five people calibrated on its own scans (20 impostor pairs) at FMR 1 %: verify and stats say
    that about 1 stranger's claim in 21 passes and how to calibrate on more; a threshold given by hand, or one
    calibrated on enough pairs, gives no such hint."""
    firsts = {}
    for r in scan_records([kinect]):
        firsts.setdefault(r.subject, r)
    g = tmp_path / "five.sqlite"
    run = CliRunner().invoke(main, ["enroll", *[str(r.path) for r in firsts.values()], "--gallery", str(g),
                                    "--method", "icp", "--jobs", "1"])
    assert run.exit_code == 0 and "4.8% to expect of strangers' claims" in run.output, run.output
    claim = next(iter(firsts))
    probe = next(r for r in scan_records([kinect]) if r.subject == claim and r.path != firsts[claim].path)
    run = CliRunner().invoke(main, ["verify", str(probe.path), "--gallery", str(g), "--claim", claim])
    assert "calibrated on 20 impostor pairs" in run.output and "about 5% of strangers' claims" in run.output
    assert f"facerec3d gallery {g} calibrate SCANS" in run.output, run.output
    stats = CliRunner().invoke(main, ["gallery", str(g), "stats"])
    assert "about 5% of strangers' claims to expect" in stats.output, stats.output
    run = CliRunner().invoke(main, ["verify", str(probe.path), "--gallery", str(g), "--claim", claim,
                                    "--threshold", "-3"])
    assert run.exit_code in (0, 1) and "hint" not in run.output, run.output
    run = CliRunner().invoke(main, ["gallery", str(g), "calibrate", "--fmr", "0.05", "--jobs", "1"])  # 20 pairs do
    assert run.exit_code == 0 and "to expect" not in run.output, run.output
    run = CliRunner().invoke(main, ["verify", str(probe.path), "--gallery", str(g), "--claim", claim])
    assert run.exit_code in (0, 1) and "hint" not in run.output, run.output


def test_a_calibration_selection_is_even_and_keeps_the_first_and_last_scans():
    from facerec3d.evaluation.calibrate import calibration_selection

    records = list(range(250))
    chosen = calibration_selection(records, 100)
    assert len(chosen) == 100 and chosen[0] == 0 and chosen[-1] == 249 and len(set(chosen)) == 100
    assert max(np.diff(chosen)) - min(np.diff(chosen)) <= 1  # evenly spread
    assert calibration_selection(records[:100], 100) == records[:100]
