"""The sharded matching engine: local processes and a Dask cluster give exactly the single-process results."""

import json
import os
import signal
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest

from facerec3d.datasets.frontal import frontal_face
from facerec3d.gallery.cascade import CascadeConfig
from facerec3d.gallery.engine import Engine
from facerec3d.matching.base import rank
from facerec3d.matching.icp import ICPMatcher
from facerec3d.workers import Workers
from tests.conftest import model_face

N_GALLERY = 7


@pytest.fixture(scope="module")
def faces():
    gallery = [frontal_face(s) for s in range(N_GALLERY)]
    probes = [frontal_face(s, pose_deg=3.0, shift_mm=3.0, noise_mm=0.3, seed=10 + s) for s in (1, 4, 6)]
    return gallery, probes


@pytest.fixture(scope="module")
def reference(faces):
    """Templates and exhaustive (scores, tiebreak) computed directly by the matcher, one process."""
    gallery, probes = faces
    m = ICPMatcher()
    templates = [m.enroll(f) for f in gallery]
    return templates, [m.scores(m.prepare(p), templates) for p in probes]


def _check(engine, faces, reference):
    gallery, probes = faces
    templates, expected = reference
    m = ICPMatcher()
    enrolled = engine.enroll(m, gallery)
    for a, b in zip(enrolled, templates):
        assert a.arrays.keys() == b.arrays.keys()
        assert all(np.array_equal(a.arrays[k], b.arrays[k]) for k in a.arrays)
    sharded = engine.load(m, enrolled)
    prepared = engine.prepare(m, probes, CascadeConfig())
    for (s, t), (es, et) in zip(sharded.scores(prepared), expected):
        np.testing.assert_array_equal(s, es)
        np.testing.assert_array_equal(t, et)
    cascade = sharded.cascade(prepared, CascadeConfig(shortlist=3))
    for k, (face, (s, t, shortlist)) in enumerate(zip(probes, cascade)):
        assert len(shortlist) == 3
        np.testing.assert_array_equal(s[shortlist], expected[k][0][shortlist])  # full ICP on the shortlist
        assert np.all(np.isneginf(np.delete(s, shortlist)))
        assert int(face.meta.subject) in shortlist  # the true identity passes the screen ...
        assert rank(s, t)[0] == int(face.meta.subject)  # ... and wins
        assert sharded.identify(face, k=2, cascade=CascadeConfig(shortlist=3))[0] == (int(face.meta.subject),
                                                                                       float(s.max()))
    sharded.release()
    return cascade


def test_one_and_two_processes_give_the_same_results(faces, reference):
    with Engine.create(1) as one:
        a = _check(one, faces, reference)
    with Engine.create(2) as two:
        assert two.workers == 2
        b = _check(two, faces, reference)
    for (s1, t1, l1), (s2, t2, l2) in zip(a, b):
        assert np.array_equal(s1, s2) and np.array_equal(t1, t2) and np.array_equal(l1, l2)


def test_dask_local_cluster_gives_the_same_results(faces, reference):
    distributed = pytest.importorskip("distributed")

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None)
    with cluster, distributed.Client(cluster) as client:
        with Engine.create(scheduler=client) as engine:
            assert engine.workers == 2
            _check(engine, faces, reference)
        with Engine.create(scheduler=cluster.scheduler_address) as engine:  # by address, as --scheduler
            templates = engine.enroll(ICPMatcher(), faces[0][:3])
            assert [t.subject for t in templates] == ["0", "1", "2"]


def _small_dataset(path, subjects: int = 3, seed: int = 3):
    from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset

    write_dataset(path, DatasetConfig(subjects=subjects, scans=2, seed=seed,
                                      scanner=ScannerConfig(rows=240, cols=320, focal_px=725.0)), "abs")
    return path


def _tasks(stream, name: str) -> list[dict]:
    """The tasks of a Dask task stream that ran function `name` (keys "name-<id>")."""
    return [t for t in stream.data if str(t["key"]).startswith(f"{name}-")]


def test_evaluation_on_a_dask_cluster_preprocesses_on_its_workers(tmp_path):
    """--scheduler: reading and preprocessing run on the cluster's workers (filling the cache there), as do
    enrolment and matching; the metrics and scores are those of the local run."""
    distributed = pytest.importorskip("distributed")
    from facerec3d.evaluation.run import evaluate

    data = _small_dataset(tmp_path / "data")
    local = evaluate(data, "icp", tmp_path / "local", jobs=1, cache=tmp_path / "cache-local", progress=False)
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None)
    with cluster, distributed.Client(cluster) as client, distributed.get_task_stream(client) as stream:
        remote = evaluate(data, "icp", tmp_path / "dask", scheduler=client, cache=tmp_path / "cache-dask",
                          progress=False)
        workers = set(client.scheduler_info()["workers"])
    scans = remote["timings"]["preprocess_computed"]
    assert scans == 6 and remote["timings"]["preprocess_cached"] == 0 and remote["workers"] == 2
    ran = _tasks(stream, "preprocess_file")
    assert len(ran) == scans and {t["worker"] for t in ran} == workers  # on both workers, each scan once
    assert {t["worker"] for t in _tasks(stream, "_enroll")} == workers
    assert len(list((tmp_path / "cache-dask").glob("*.npz"))) == scans  # the workers filled the cache
    for key in ("rank1", "rank5", "eer", "vr_at_far_0.001", "vr_at_far_0.01", "subsets", "failures", "n_gallery"):
        assert json.dumps(remote[key], sort_keys=True) == json.dumps(local[key], sort_keys=True), key
    assert (tmp_path / "dask" / "scores.txt").read_text() == (tmp_path / "local" / "scores.txt").read_text()


def test_enroll_and_identify_preprocess_on_the_dask_workers(tmp_path):
    """facerec3d enroll / identify --scheduler: each scan is read, preprocessed and enrolled on a worker; the probe
    is preprocessed on one too."""
    distributed = pytest.importorskip("distributed")
    from click.testing import CliRunner

    from facerec3d.cli import main

    from facerec3d.datasets.catalog import open_dataset

    data = _small_dataset(tmp_path / "data", subjects=2, seed=5)
    probe = open_dataset(data).records[-1]
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None)
    with cluster, distributed.Client(cluster) as client:
        address, run = cluster.scheduler_address, CliRunner()
        with distributed.get_task_stream(client) as stream:
            r = run.invoke(main, ["enroll", str(data), "--gallery", str(tmp_path / "g.sqlite"), "--no-calibrate", "--scheduler",
                                  address, "--cache", str(tmp_path / "cache")])
            assert r.exit_code == 0 and "4 enrolled, 0 already enrolled, 0 failed" in r.output, r.output
            r = run.invoke(main, ["identify", str(probe.path), "--gallery", str(tmp_path / "g.sqlite"), "-k", "1",
                                  "--scheduler", address, "--cache", str(tmp_path / "cache-probe")])
            assert r.exit_code == 0, r.output
        workers = set(client.scheduler_info()["workers"])
    assert len(_tasks(stream, "_enrol_one")) == 4 and {t["worker"] for t in _tasks(stream, "_enrol_one")} == workers
    assert len(_tasks(stream, "preprocess_file")) == 1  # the probe, on a worker
    assert r.output.splitlines()[1].split()[1:3] == [probe.subject, probe.scan_id]  # itself, enrolled


def test_evaluation_is_identical_on_one_and_two_processes(tmp_path):
    from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
    from facerec3d.evaluation.run import evaluate

    data = tmp_path / "data"
    write_dataset(data, DatasetConfig(subjects=3, scans=2, seed=3, scanner=ScannerConfig(rows=240, cols=320,
                                                                                      focal_px=725.0)), "abs")
    runs = {jobs: evaluate(data, "icp", tmp_path / f"run{jobs}", jobs=jobs, cache=tmp_path / "cache", progress=False)
            for jobs in (1, 2)}
    assert runs[1]["workers"] == 1 and runs[2]["workers"] == 2
    assert (tmp_path / "run1" / "scores.txt").read_text() == (tmp_path / "run2" / "scores.txt").read_text()
    assert runs[1]["rank1"] == runs[2]["rank1"] == 1.0
    m = evaluate(data, "icp", tmp_path / "cascade", jobs=2, cache=tmp_path / "cache", progress=False,
                 cascade=CascadeConfig(shortlist=2))
    assert m["cascade"]["shortlist"] == 2 and m["cascade"]["recall"] == 1.0 and m["rank1"] == 1.0
    scores = [line.split() for line in (tmp_path / "cascade" / "scores.txt").read_text().splitlines()]
    assert sum(s[3] == "-inf" for s in scores) == len(scores) // 3  # one of 3 faces per probe is off the shortlist


def test_keypoint_screen_shortlists_the_true_subject_identically_on_one_and_two_processes(tmp_path):
    from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
    from facerec3d.evaluation.run import evaluate

    data = tmp_path / "data"
    write_dataset(data, DatasetConfig(subjects=4, scans=2, seed=4, scanner=ScannerConfig(rows=240, cols=320,
                                                                                      focal_px=725.0)), "abs")
    cascade = CascadeConfig(shortlist=2, screen="keypoints")
    runs = {jobs: evaluate(data, "icp", tmp_path / f"kp{jobs}", jobs=jobs, cache=tmp_path / "cache", progress=False,
                           cascade=cascade) for jobs in (1, 2)}
    assert runs[1]["cascade"]["screen"] == "keypoints" and runs[1]["cascade"]["recall"] == 1.0
    assert runs[1]["rank1"] == 1.0
    assert (tmp_path / "kp1" / "scores.txt").read_text() == (tmp_path / "kp2" / "scores.txt").read_text()
    scores = [line.split() for line in (tmp_path / "kp1" / "scores.txt").read_text().splitlines()]
    assert sum(s[3] == "-inf" for s in scores) == len(scores) // 2  # two of four faces per probe are screened out


@pytest.mark.parametrize("method, options", [
    ("region-icp", {"regions": ["nose", "eyes-forehead"], "normalisation": "z-score", "icp": {"fine_points": 300}}),
    ("fusion", {"members": ["icp", "region-icp"], "normalisation": "min-max",
                "member_options": {"region-icp": {"regions": ["nose"], "normalisation": "tanh"}}}),
])
def test_gallery_normalised_scores_do_not_depend_on_the_sharding(method, options):
    """Region ICP and fusion normalise over the whole gallery: 2 shards must give the 1-shard scores."""
    from facerec3d.matching.registry import make_matcher

    matcher = make_matcher(method, options)
    gallery = [model_face(s) for s in range(5)]
    probes = [model_face(s, "smile") for s in (1, 3)]
    templates = [matcher.enroll(f) for f in gallery]
    expected = [matcher.scores(matcher.prepare(p), templates)[0] for p in probes]
    with Engine.create(2) as two:
        rows = two.load(matcher, templates).scores(two.prepare(matcher, probes))
    for (s, _), e in zip(rows, expected):
        np.testing.assert_array_equal(s, e)
    assert [int(np.argmax(s)) for s, _ in rows] == [1, 3]


def test_a_malformed_scheduler_address_is_one_clear_error():
    """`--scheduler tcp://localhost` (no port) or `127.0.0.1:8799x` gave distributed's ValueError traceback."""
    pytest.importorskip("distributed")
    from facerec3d.errors import InputError

    for address, why in (("tcp://localhost", "missing port number"), ("127.0.0.1:8799x", "invalid literal")):
        with pytest.raises(InputError, match=rf"scheduler '{address}': not a Dask scheduler's address \(.*{why}"):
            Engine.create(scheduler=address)


def test_jobs_are_capped_at_what_is_useful(tmp_path, monkeypatch):
    """--jobs 100000 opened a process pool each before any work and stopped with "[Errno 24] Too many open files";
    identify and evaluate started --jobs processes for a 3-entry gallery. At most JOBS_PER_CORE per core now (the
    command line saying so once) and no more than the pieces of work."""
    from click.testing import CliRunner

    from facerec3d.cli import main
    from facerec3d.workers import JOBS_PER_CORE, InlineExecutor, Workers

    monkeypatch.setattr("os.cpu_count", lambda: 2)
    with Workers.create(100_000) as workers:
        assert workers.workers == 2 * JOBS_PER_CORE
    with Engine.create(100_000, items=3) as engine:
        assert engine.workers == 3
    with Engine.create(8, items=1) as engine:
        assert isinstance(engine.executors[0], InlineExecutor)
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "d"), "--subjects", "1", "--scans", "1", "--rows", "120",
                                  "--cols", "160"])
    assert r.exit_code == 0, r.output
    scan = next(p for p in (tmp_path / "d").rglob("*") if p.is_file() and p.name != "manifest.csv")
    r = CliRunner().invoke(main, ["preprocess", str(scan), "-o", str(tmp_path / "p"), "--jobs", "100000"])
    assert r.output.count(f"warning: --jobs 100000: using {2 * JOBS_PER_CORE} processes") == 1, r.output
    assert "Too many open files" not in r.output
    for order in (["--jobs", "100000", "--scheduler", "bad://x"], ["--scheduler", "bad://x", "--jobs", "100000"]):
        r = CliRunner().invoke(main, ["evaluate", str(tmp_path / "d"), "--out", str(tmp_path / "e"), *order,
                                      "--cache", str(tmp_path / "c")])  # (no first-use line of the default cache)
        assert r.exit_code == 2 and "warning: --jobs" not in r.output, r.output  # a cluster's workers: no local cap
        assert r.output.startswith("error: scheduler 'bad://x'") or "dask.distributed" in r.output, r.output


def _interrupted():
    os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C reaching a worker while it computes


class _SentWhileInterrupted:
    """A result whose sending back (pickling) meets Ctrl-C."""

    def __reduce__(self):
        os.kill(os.getpid(), signal.SIGINT)
        return _SentWhileInterrupted, ()


def _result_sent_while_interrupted() -> _SentWhileInterrupted:
    return _SentWhileInterrupted()


def test_ctrl_c_ends_a_computing_worker_quietly_and_the_engine_closes_with_the_interrupt(capfd):
    """Ctrl-C reaches the whole process group: each worker printed a KeyboardInterrupt traceback, and closing the
    engine then dropped its galleries from the dead workers, raising BrokenProcessPool over the KeyboardInterrupt
    (4 tracebacks, exit code 1 instead of `interrupted`, 130). A computing worker now ends at once by the signal,
    without a word, and a gallery whose workers died is released without them."""
    with pytest.raises(KeyboardInterrupt):
        with Engine.create(2) as engine:
            engine.load(ICPMatcher(), [])
            processes = [p for ex in engine.executors for p in ex._processes.values()]
            for ex in engine.executors:
                with pytest.raises(BrokenProcessPool):
                    ex.submit(_interrupted).result()
            raise KeyboardInterrupt
    assert [p.exitcode for p in processes] == [-signal.SIGINT] * 2  # (joined by the pools as they closed)
    assert capfd.readouterr().err == ""


def test_ctrl_c_never_ends_a_worker_while_it_sends_a_result_back(capfd):
    """A worker that Ctrl-C killed half-way through sending a result back left the run reading the rest forever (a
    hang after Ctrl-C). Met while a worker sends a result or waits for work, Ctrl-C is noted: the result arrives
    whole, and the worker ends (quietly) before its next call."""
    with Workers.create(2) as workers:
        sending, waiting = workers.executors
        assert isinstance(sending.submit(_result_sent_while_interrupted).result(), _SentWhileInterrupted)
        os.kill(waiting.submit(os.getpid).result(), signal.SIGINT)
        processes = [p for ex in workers.executors for p in ex._processes.values()]
        for ex in workers.executors:
            with pytest.raises(BrokenProcessPool):
                ex.submit(os.getpid).result()
    assert [p.exitcode for p in processes] == [128 + signal.SIGINT] * 2
    assert capfd.readouterr().err == ""


def test_ctrl_c_while_a_worker_starts_is_noted_quietly(tmp_path, monkeypatch, capfd):
    """Ctrl-C while a worker started (threadpoolctl's look at the BLAS libraries in its initializer takes a while)
    was a KeyboardInterrupt traceback of the worker's ("Exception in initializer"). A worker starts with SIGINT held
    until its handler is in place; met there, Ctrl-C is noted and the worker ends, quietly, before its first call."""
    import facerec3d.workers

    real, held = facerec3d.workers._init_worker, tmp_path / "held"

    def starting():
        held.write_text(str(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])))
        real()

    monkeypatch.setattr(facerec3d.workers, "_init_worker", starting)
    monkeypatch.setattr(facerec3d.workers, "one_thread_per_process", lambda: os.kill(os.getpid(), signal.SIGINT))
    with Workers.create(2) as workers:
        with pytest.raises(BrokenProcessPool):
            workers.executors[0].submit(os.getpid).result()
    assert held.read_text() == "True"
    assert capfd.readouterr().err == ""


def _blas_threads() -> list[int]:
    from threadpoolctl import threadpool_info

    return sorted(p["num_threads"] for p in threadpool_info())


def test_work_done_in_this_process_runs_every_blas_library_on_one_thread():
    """`jobs` = 1 runs work here (InlineExecutor): one thread for every BLAS library loaded by then, SciPy's own
    included (a controller made when the module was imported had seen only NumPy's), and the caller's back after."""
    import scipy.linalg  # noqa: F401 (SciPy's BLAS loaded)

    from facerec3d.workers import InlineExecutor
    from threadpoolctl import threadpool_limits

    with threadpool_limits(2):
        before = _blas_threads()
        inside = InlineExecutor().submit(_blas_threads).result()
        assert set(inside) == {1} and _blas_threads() == before and max(before) == 2
