"""The gallery store: exact array round trip, settings checks, transactions that survive a kill, and the CLI."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from facerec3d.gallery.store import GalleryError, GalleryStore
from facerec3d.matching.base import Template
from facerec3d.matching.icp import ICPConfig, ICPMatcher
from facerec3d.preprocess.pipeline import PreprocessConfig
from tests.conftest import cli_dataset


def big_template(i: int) -> Template:
    """Entry i's deterministic content: ~4 MB of arrays of several dtypes."""
    rng = np.random.default_rng(i)
    arrays = {"points": rng.normal(size=(300_000, 3)).astype(np.float32), "flags": rng.random(1000) < 0.5,
              "index": rng.integers(0, 60000, 5000).astype(np.uint16), "empty": np.zeros((0, 3), np.uint8),
              "scalar": np.array(float(i))}
    # method "arrays": arbitrary arrays, not an ICP index (the store checks an "icp" template's structure)
    return Template(f"s{i}", f"scan{i}", "arrays", arrays, {"i": i, "origin": [1.5, -2.0, 0.25]})


class ArraysMatcher(ICPMatcher):
    """What a store of `big_template`s is bound to: ICP's settings under the method name "arrays"."""

    name = "arrays"


def assert_same(a: Template, b: Template) -> None:
    assert (a.subject, a.scan_id, a.method, a.attrs) == (b.subject, b.scan_id, b.method, b.attrs)
    assert a.arrays.keys() == b.arrays.keys()
    for k in a.arrays:
        assert a.arrays[k].dtype == b.arrays[k].dtype and a.arrays[k].shape == b.arrays[k].shape
        assert np.array_equal(a.arrays[k], b.arrays[k])


def test_round_trip_settings_and_removal(tmp_path):
    path = tmp_path / "g.sqlite"
    with pytest.raises(GalleryError, match="no such gallery"):
        GalleryStore(path)
    matcher = ArraysMatcher(ICPConfig(variant="point-to-plane", fine_points=800))
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), matcher)
        for i in range(3):
            store.add(big_template(i), f"/data/{i}.abs")
        store.add_failure("/data/bad.abs", "no face found")
        with pytest.raises(GalleryError, match="already enrolled"):
            store.add(big_template(0), "/data/0.abs")
    with GalleryStore(path) as store:  # reopened: everything as written
        loaded = store.templates()
        for i, t in enumerate(loaded):
            assert_same(t, big_template(i))
            assert t.arrays["points"].flags.writeable
        assert store.stats()["method"] == "arrays" and store.stats()["options"] == json.loads(json.dumps(matcher.options()))
        assert store.failures() == [("/data/bad.abs", "no face found")]
        st = store.stats()
        assert (st["entries"], st["subjects"], st["failures_to_enrol"]) == (3, 3, 1)
        assert st["template_bytes"] == 3 * big_template(0).nbytes
        store.bind(PreprocessConfig(), matcher)  # same settings: accepted
        with pytest.raises(GalleryError, match=r"preprocessed differently.*crop_radius_mm"):
            store.check_preprocess(PreprocessConfig(crop_radius_mm=70.0))
        with pytest.raises(GalleryError, match="enrolled with method 'arrays'"):
            store.bind(PreprocessConfig(), ICPMatcher())
        assert store.remove("s1") == 1 and store.remove("scan2") == 1 and store.remove("nobody") == 0
        assert [e.subject for e in store.entries()] == ["s0"]
        assert sqlite3.connect(path).execute("SELECT COUNT(*) FROM arrays").fetchone()[0] == 5  # cascade delete
    (tmp_path / "junk.sqlite").write_bytes(b"not a database at all" * 100)
    with pytest.raises(GalleryError, match="not a gallery store"):
        GalleryStore(tmp_path / "junk.sqlite")



def test_another_programs_sqlite_database_is_refused_and_left_untouched(tmp_path):
    """Reading (stats, list, identify) or enrolling into an SQLite file of another program added the store's tables
    to it and switched its journal to WAL: now it is refused by name, byte for byte as it was."""
    other = tmp_path / "notes.db"
    db = sqlite3.connect(other)
    db.execute("CREATE TABLE notes (x)")
    db.execute("INSERT INTO notes VALUES (1)")
    db.commit()
    db.close()
    before = other.read_bytes()
    for create in (False, True):
        with pytest.raises(GalleryError, match=r"notes\.db: not a gallery store \(an SQLite database of other "
                                               r"tables: notes\)"):
            GalleryStore(other, create=create)
    assert other.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["notes.db"]
    blank = tmp_path / "blank.db"  # a database with no table yet: a reader refuses it, an enrolment makes a store
    db = sqlite3.connect(blank)
    db.execute("CREATE TABLE t (x)")
    db.execute("DROP TABLE t")
    db.commit()
    db.close()
    assert blank.stat().st_size > 0
    with pytest.raises(GalleryError, match="an empty database, not a gallery"):
        GalleryStore(blank)
    with GalleryStore(blank, create=True) as store:
        assert store.stats()["entries"] == 0

def test_a_scan_name_of_several_people_is_never_removed_as_all_of_them(tmp_path):
    """Every person a depth camera enrols has a `front_1`: removing by that name is refused (nothing removed) and
    names the way to remove one entry, by its id (`--entry`), which is also what a damaged entry's message says."""
    path = tmp_path / "g.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), ArraysMatcher())
        for i in range(3):
            t = big_template(i)
            store.add(Template(t.subject, "front_1", t.method, t.arrays, t.attrs), f"/data/s{i}/front_1.png")
        ids = [e.id for e in store.entries()]
        with pytest.raises(GalleryError, match=r"scan 'front_1' names 3 entries of 3 subjects.*remove --entry ID"):
            store.remove("front_1")
        assert [e.id for e in store.entries()] == ids
        assert store.remove(entry=ids[1]) == 1 and store.remove(entry=ids[1]) == 0
        assert [e.subject for e in store.entries()] == ["s0", "s2"]
        assert store.remove("s2") == 1 and store.remove("front_1") == 1 and store.entries() == []
    with GalleryStore(path) as store:
        store.add(big_template(5), "/data/5.abs")
        store.add(big_template(6), "/data/6.abs")
    run = lambda *a: CliRunner().invoke(main, ["gallery", str(path), "remove", *a])
    for bad in ((), ("s5", "--entry", "1")):
        r = run(*bad)
        assert r.exit_code == 2 and "give a subject or scan id, or --entry ID" in r.output, r.output
    with GalleryStore(path) as store:
        first = store.entries()[0].id
    r = run("--entry", str(first))
    assert r.exit_code == 0 and "removed 1 entry" in r.output, r.output
    r = run("--entry", str(first))
    assert r.exit_code == 2 and f"no entry {first}" in r.output, r.output
    with GalleryStore(path) as store:
        assert [e.subject for e in store.entries()] == ["s6"]


def test_a_gallery_with_no_entries_takes_new_settings(tmp_path):
    """cal19 item 3: a store whose first enrolment failed (no entry, a failure recorded) takes another enrolment's
    settings, dropping the old ones' learnt arrays and threshold; a store object still on the old settings can add
    nothing (no store holds templates of two methods); once it has an entry, other settings are refused as before."""
    path = tmp_path / "g.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), ICPMatcher())
        store.add_failure("/data/bad.abs", "no face found")
        store.set_threshold({"value": -2.5, "rule": "fmr=0.01"})  # (as entries since removed left it)
    other = ArraysMatcher(ICPConfig(variant="point-to-plane"))
    with GalleryStore(path) as stale, GalleryStore(path) as store:
        store.bind(PreprocessConfig(crop_radius_mm=70.0), other)
        assert store.stats()["method"] == "arrays" and store.threshold() is None
        assert store.stats()["options"] == json.loads(json.dumps(other.options()))
        assert store.preprocess_config() == PreprocessConfig(crop_radius_mm=70.0)
        assert store.failures() == [("/data/bad.abs", "no face found")]
        with pytest.raises(GalleryError, match="settings were replaced .* by another enrolment"):
            stale.add(big_template(0), "/data/0.abs")
        store.add(big_template(0), "/data/0.abs")
        store.bind(PreprocessConfig(crop_radius_mm=70.0), other)  # the same settings: accepted
        with pytest.raises(GalleryError, match="enrolled with method 'arrays'"):
            store.bind(PreprocessConfig(crop_radius_mm=70.0), ICPMatcher())
        assert store.remove("s0") == 1
        store.bind(PreprocessConfig(), ICPMatcher())  # empty again: new settings once more
        assert store.matcher().options() == ICPMatcher().options()


WRITER = """
import sys
sys.path.insert(0, {tests!r})
from test_gallery import big_template
from facerec3d.gallery.store import GalleryStore
store = GalleryStore({path!r}, create=True)
i = 0
while True:  # enrol until killed
    store.add(big_template(i), f"/data/{{i}}.abs")
    i += 1
"""


def test_a_store_refuses_a_template_of_another_method_or_without_a_subject(tmp_path):
    """The Python API let a curvature template into an ICP gallery (every identify then crashed on it) and templates
    without a subject in (`remove()` with no argument then deleted them): both are refused, naming the source, and a
    removal must name what it removes."""
    path = tmp_path / "g.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), ArraysMatcher())
        store.add(big_template(0), "/data/0.abs")
        t = big_template(1)
        with pytest.raises(GalleryError, match=r"/data/1\.abs: a 'curvature' template, and .*g\.sqlite holds "
                                               r"'arrays' ones"):
            store.add(Template(t.subject, t.scan_id, "curvature", t.arrays, t.attrs), "/data/1.abs")
        for subject in (None, ""):
            with pytest.raises(GalleryError, match=r"/data/1\.abs: a template needs its subject to be enrolled"):
                store.add(Template(subject, t.scan_id, t.method, t.arrays, t.attrs), "/data/1.abs")
        with pytest.raises(GalleryError, match="a removal names a subject, a scan id or an entry id"):
            store.remove()
        assert [e.subject for e in store.entries()] == ["s0"]
    unbound = tmp_path / "raw.sqlite"  # a store never bound: its first template's method is the one it holds
    with GalleryStore(unbound, create=True) as store:
        store.add(big_template(0), "/data/0.abs")
        with pytest.raises(GalleryError, match="holds 'arrays' ones"):
            store.add(Template("s1", "x", "icp", t.arrays, t.attrs), "/data/1.abs")


def test_a_gallery_stored_before_a_setting_existed_accepts_todays_defaults(tmp_path):
    """Preprocessing settings stored without a field added since (here the detector's prominence_weight) read as
    that field's default: enrolling into or probing the gallery with today's default settings is accepted, while a
    real difference is still refused and named."""
    path = tmp_path / "old.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), ICPMatcher())
    db = sqlite3.connect(path)
    with db:
        stored = json.loads(db.execute("SELECT value FROM meta WHERE key = 'preprocess'").fetchone()[0])
        del stored["detect"]["prominence_weight"]
        db.execute("UPDATE meta SET value = ? WHERE key = 'preprocess'", (json.dumps(stored, sort_keys=True),))
    db.close()
    with GalleryStore(path) as store:
        assert store.preprocess_config() == PreprocessConfig()
        store.check_preprocess(PreprocessConfig())
        store.bind(PreprocessConfig(), ICPMatcher())
        with pytest.raises(GalleryError, match=r"preprocessed differently.*detect\.prominence_weight"):
            store.check_preprocess(PreprocessConfig.from_dict({"detect": {"prominence_weight": 0.0}}))


def test_kill_during_enrolment_leaves_earlier_entries_intact(tmp_path):
    path = tmp_path / "g.sqlite"
    code = WRITER.format(tests=os.path.dirname(__file__), path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", code])
    try:
        deadline = time.monotonic() + 120
        n = 0
        while n < 2:  # wait until two enrolments are committed (no timing guess), then kill mid-way
            assert proc.poll() is None, "the writer died by itself"
            assert time.monotonic() < deadline, "the writer made no progress"
            time.sleep(0.05)
            if path.is_file():
                db = sqlite3.connect(path, timeout=30)
                try:
                    n = db.execute("SELECT COUNT(*) FROM entries").fetchone()[0]
                except sqlite3.OperationalError:  # the schema is not there yet
                    n = 0
                finally:
                    db.close()
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    with GalleryStore(path) as store:
        assert sqlite3.connect(path).execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        entries = store.entries()
        assert len(entries) >= n >= 2
        for i, (entry, template) in enumerate(zip(entries, store.templates(entries))):
            assert entry.source == f"/data/{i}.abs"
            assert_same(template, big_template(i))
        store.add(big_template(len(entries)), "/data/next.abs")  # still writable
        assert len(store.entries()) == len(entries) + 1


def test_cli_enroll_identify_verify_and_gallery(tmp_path):
    run = CliRunner()
    _, gallery_scans, probe, probe_subject, other = cli_dataset(tmp_path / "d", 0.2)
    bad = tmp_path / "broken.abs"
    bad.write_text("not a range image\n")
    store, cache = str(tmp_path / "g.sqlite"), str(tmp_path / "cache")
    r = run.invoke(main, ["enroll", *map(str, gallery_scans), str(bad), "--gallery", store, "--method", "icp",
                          "--jobs", "2", "--cache", cache])
    assert r.exit_code == 0, r.output
    assert "3 enrolled, 0 already enrolled, 1 failed to enrol" in r.output and "broken.abs" in r.output
    r = run.invoke(main, ["enroll", str(gallery_scans[0]), "--gallery", store, "--method", "icp", "--jobs", "1",
                          "--cache", cache])
    assert "0 enrolled, 1 already enrolled" in r.output and "already enrolled as subject" not in r.output
    r = run.invoke(main, ["enroll", str(gallery_scans[0]), "--gallery", store, "--subject", "bob", "--jobs", "1",
                          "--cache", cache])  # the same file under another name: said, not enrolled twice
    assert r.exit_code == 0 and "0 enrolled, 1 already enrolled" in r.output, r.output
    with GalleryStore(store) as s:
        first = next(e for e in s.entries() if e.source == str(gallery_scans[0].resolve()))
        rows = len(s.entries())
    assert f"already enrolled as subject {first.subject!r}, not 'bob'" in r.output and rows == 3, r.output
    for cascade in ([], ["--cascade"]):
        r = run.invoke(main, ["identify", str(probe), "--gallery", store, "-k", "3", "--jobs", "2", "--cache", cache,
                              *cascade])
        assert r.exit_code == 0, r.output
        first = r.output.splitlines()[1].split()
        assert first[:2] == ["1", probe_subject] and len(r.output.splitlines()) == 4
    r = run.invoke(main, ["verify", str(probe), "--gallery", store, "--claim", probe_subject, "--cache", cache])
    assert r.exit_code == 0 and r.output.startswith("accept"), r.output
    r = run.invoke(main, ["verify", str(probe), "--gallery", store, "--claim", other, "--cache", cache])
    assert r.exit_code == 1 and r.output.startswith("reject"), r.output
    # region ICP normalises over the gallery: verification scores the probe against all of it
    rstore = str(tmp_path / "r.sqlite")
    r = run.invoke(main, ["enroll", *map(str, gallery_scans), "--gallery", rstore, "--method", "region-icp",
                          "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0, r.output
    for claim, code in ((probe_subject, 0), (other, 1)):
        r = run.invoke(main, ["verify", str(probe), "--gallery", rstore, "--claim", claim, "--threshold", "0",
                              "--cache", cache])
        assert r.exit_code == code, r.output
    cfg = tmp_path / "other.json"
    cfg.write_text(json.dumps({"crop_radius_mm": 70}))
    r = run.invoke(main, ["identify", str(probe), "--gallery", store, "--config", str(cfg), "--cache", cache])
    assert r.exit_code == 2 and "preprocessed differently" in r.output and "Traceback" not in r.output
    r = run.invoke(main, ["identify", str(probe), "--gallery", str(tmp_path / "none.sqlite")])
    assert r.exit_code == 2 and "no such gallery" in r.output
    r = run.invoke(main, ["gallery", store, "stats"])
    assert r.exit_code == 0 and "3 entries of 3 subjects" in r.output and "1 failures to enrol" in r.output
    r = run.invoke(main, ["gallery", store, "remove", other])
    assert r.exit_code == 0 and "removed 1 entry" in r.output
    r = run.invoke(main, ["gallery", store, "list"])
    listed = r.output.splitlines()
    assert len(listed) == 3 and listed[-1].startswith("failed") and other not in {l.split()[1] for l in listed[:2]}
    r = run.invoke(main, ["gallery", store, "remove", other])
    assert r.exit_code == 2 and "no subject or scan" in r.output


def test_the_python_api_refuses_a_removal_the_command_line_refuses_and_deletes_nothing(tmp_path):
    """`GalleryStore.remove('s0', entry=ID)` ignored the subject and deleted entry ID, another person's; `entry='3'`
    matched nothing and returned 0. Both refused in one line (InputError), nothing deleted."""
    from facerec3d.errors import InputError

    path = tmp_path / "g.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), ArraysMatcher())
        for i in range(2):
            store.add(big_template(i), f"/data/{i}.abs")
        before = store.entries()
        other = before[1].id  # s1's entry
        for ident, entry, reason in (("s0", other, rf"remove a subject or scan id \('s0'\) or an entry id \({other}\), "
                                                   "not both"),
                                     (None, str(other), rf"an entry id is a whole number .*, not '{other}'"),
                                     (None, True, "an entry id is a whole number .*, not True"),
                                     (None, 1.0, "an entry id is a whole number .*, not 1.0"),
                                     (0, None, "a subject or scan id is a text, not 0")):
            with pytest.raises(InputError, match=f"^{path}: {reason}"):
                store.remove(ident, entry)
        assert store.entries() == before
        assert store.remove(entry=np.int64(other)) == 1 and [e.subject for e in store.entries()] == ["s0"]


def test_enroll_scans_takes_paths_and_verify_scan_refuses_a_threshold_that_is_not_a_finite_number(tmp_path):
    """`enroll_scans(store, ['file.abs.gz'], matcher)` gave AttributeError: 'str' object has no attribute 'path';
    `verify_scan(..., threshold=nan)` returned (False, score, nan) and threshold='1' a TypeError from >=."""
    from facerec3d.errors import InputError
    from facerec3d.gallery.service import enroll_scans, scan_records, verify_scan

    _, gallery_scans, probe, probe_subject, _ = cli_dataset(tmp_path / "d", 0.2, subjects=2)
    with GalleryStore(tmp_path / "g.sqlite", create=True) as store:
        report = enroll_scans(store, [str(gallery_scans[0]), *scan_records(gallery_scans[1:])], ICPMatcher())
        assert report.enrolled == 2 and not report.failures
        assert enroll_scans(store, gallery_scans[0], ICPMatcher()).skipped == [str(gallery_scans[0].resolve())]
        assert sorted(e.subject for e in store.entries()) == sorted(r.subject for r in scan_records(gallery_scans))
        with pytest.raises(InputError, match=r"^enroll_scans takes scan records \(scan_records\) or paths .*, not 3$"):
            enroll_scans(store, [3], ICPMatcher())
        with pytest.raises(InputError, match=r"^enroll_scans takes scan records .*, not 123$"):  # was a TypeError
            enroll_scans(store, 123, ICPMatcher())
        with pytest.raises(InputError, match=r"^enroll_scans takes a matcher .*, not 'icp'$"):  # was AttributeError
            enroll_scans(store, gallery_scans[0], "icp")
        for bad in (float("nan"), float("inf"), "1", True, None.__class__):
            with pytest.raises(InputError, match=r"^a verification threshold is a finite number, not "):
                verify_scan(store, probe, probe_subject, threshold=bad)
        accepted, score, threshold = verify_scan(store, probe, probe_subject, threshold=np.float32(-1e6))
        assert accepted and np.isfinite(score) and threshold == -1e6 and type(threshold) is float


@pytest.mark.skipif(not hasattr(os, "fork"), reason="a service's worker processes are forked on Unix only")
def test_processes_forked_from_a_service_do_not_keep_its_store_held(tmp_path):
    """A service holds its store with a `flock`, which lives while any process has the lock file open: its worker
    processes, forked from it, close their copy, so that one outliving a killed service keeps nothing held."""
    import multiprocessing

    from facerec3d.gallery.store import ServeLock, served_by

    gallery = tmp_path / "g.sqlite"
    hold = ServeLock(gallery, "http://127.0.0.1:8000")
    worker = multiprocessing.get_context("fork").Process(target=time.sleep, args=(60,))
    worker.start()
    try:
        with GalleryStore(gallery, create=True) as store:  # the service's own process writes
            store.bind(PreprocessConfig(), ICPMatcher())
        hold.release()  # (as the service's end does)
        assert worker.is_alive() and served_by(gallery) is None
    finally:
        worker.kill()
        worker.join()


# ---------------------------------------------------------------- store rules that mutation testing found untested
def small_template(i: int, subject: str | None = None, scan_id: str | None = None) -> Template:
    return Template(subject or f"s{i}", scan_id or f"scan{i}", "arrays", {"points": np.full((4, 3), float(i))},
                    {"i": i})


@pytest.fixture
def small_store(tmp_path, monkeypatch):
    monkeypatch.delenv("FACEREC3D_GALLERY_KEY", raising=False)
    monkeypatch.delenv("FACEREC3D_GALLERY_KEY_FILE", raising=False)
    path = tmp_path / "g.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), ArraysMatcher(ICPConfig(fine_points=800)))
        yield store


def test_a_store_refuses_the_same_method_with_other_options(small_store):
    small_store.add(small_template(0), "/data/0.abs")
    refused = r"enrolled with method 'arrays' and other options \(.*fine_points: 800 in the gallery, 900 given"
    with pytest.raises(GalleryError, match=refused):
        small_store.bind(PreprocessConfig(), ArraysMatcher(ICPConfig(fine_points=900)))
    with pytest.raises(GalleryError, match=refused):
        small_store.check_matcher(ArraysMatcher(ICPConfig(fine_points=900)))
    small_store.check_matcher(ArraysMatcher(ICPConfig(fine_points=800)))  # its own options: accepted


def test_a_failure_to_enrol_keeps_the_latest_reason_once(small_store):
    small_store.add_failure("/data/bad.abs", "cannot read")
    small_store.add_failure("/data/bad.abs", "no face found")
    assert small_store.failures() == [("/data/bad.abs", "no face found")]
    assert small_store.stats()["failures_to_enrol"] == 1


def test_a_threshold_is_a_finite_float_when_set_and_when_read(small_store):
    for value in (float("nan"), float("inf"), -float("inf"), 1, "1.0", None):
        with pytest.raises(ValueError, match="finite float"):
            small_store.set_threshold({"value": value, "rule": "eer"})
    assert small_store.threshold() is None
    small_store.set_threshold({"value": -1.5, "rule": "eer"})
    assert small_store.threshold() == {"value": -1.5, "rule": "eer"}
    db = sqlite3.connect(small_store.path, isolation_level=None)
    for damaged in ('{"value": Infinity, "rule": "eer"}', '{"value": NaN}', '{"rule": "eer"}', "not json"):
        db.execute("UPDATE meta SET value = ? WHERE key = 'threshold'", (damaged,))
        with pytest.raises(GalleryError, match="damaged threshold record"):
            small_store.threshold()
    db.close()


def test_a_scan_id_of_two_people_is_refused_and_a_subject_name_comes_before_a_scan_id(small_store):
    small_store.add(small_template(0, "ann", "front_1"), "/data/ann/front_1.png")
    small_store.add(small_template(1, "bob", "front_1"), "/data/bob/front_1.png")
    with pytest.raises(GalleryError, match="scan 'front_1' names 2 entries of 2 subjects"):
        small_store.remove("front_1")
    assert [e.subject for e in small_store.entries()] == ["ann", "bob"]
    # "bob" is a subject and also the scan id of one of ann's entries: the subject is meant
    small_store.add(small_template(2, "ann", "bob"), "/data/ann/bob.png")
    assert small_store.remove("bob") == 1
    assert [(e.subject, e.scan_id) for e in small_store.entries()] == [("ann", "front_1"), ("ann", "bob")]


def test_an_entry_whose_subject_was_changed_in_the_file_is_refused_not_matched(small_store):
    small_store.add(small_template(0, "ann"), "/data/0.abs")
    small_store.add(small_template(1, "bob"), "/data/1.abs")
    db = sqlite3.connect(small_store.path, isolation_level=None)
    db.execute("UPDATE entries SET subject = 'bob' WHERE subject = 'ann'")  # someone makes ann's face bob's
    db.close()
    with pytest.raises(GalleryError, match=r"entry \d+ \(subject bob, scan scan0.*damaged: entry: checksum"):
        small_store.templates()


def test_a_rekey_that_fails_midway_changes_nothing(small_store):
    """rekey is one transaction: a damaged row found after others were re-encrypted rolls them all back, so the
    store stays clear and readable without a key (the learnt-array table is re-encrypted last)."""
    pytest.importorskip("cryptography")
    from facerec3d.gallery.store import TemplateKey

    for i in range(3):
        small_store.add(small_template(i), f"/data/{i}.abs")
    db = sqlite3.connect(small_store.path, isolation_level=None)
    db.execute("INSERT INTO model_arrays VALUES ('w', '<f8', '[1]', ?, 'bad checksum')", (b"\0" * 8,))
    db.close()
    with pytest.raises(GalleryError, match="model_arrays row None 'w' is damaged"):
        small_store.rekey(TemplateKey(b"k" * 32))
    assert small_store.key is None
    with GalleryStore(small_store.path) as again:
        assert not again.encrypted
        for i, t in enumerate(again.templates()):
            np.testing.assert_array_equal(t.arrays["points"], small_template(i).arrays["points"])
