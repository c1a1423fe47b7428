"""The gallery service (`facerec3d serve`), started as a real process on a free loopback port and called over
real HTTP: enrol / identify / verify / remove, keys and scopes, limits (upload size, scan size, queue, time),
corrupt input, faces preprocessed at the edge (taken as they are, or refused with other settings), the audit
log and metrics, the CLI's --server, and kill -9 mid-enrolment with a restart that
keeps every acknowledged entry. Plus the in-place gallery update's snapshots and the BLAS-thread cap."""

import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")

from click.testing import CliRunner  # noqa: E402

from facerec3d.cli import main  # noqa: E402
from facerec3d.client import Client, ServiceError  # noqa: E402
from facerec3d.gallery.service import DEFAULT_THRESHOLDS  # noqa: E402
from facerec3d.gallery.store import GalleryStore  # noqa: E402
from facerec3d.datasets.frontal import frontal_face  # noqa: E402
from facerec3d.io import load_scan, save_scan  # noqa: E402
from facerec3d.matching.icp import ICPMatcher  # noqa: E402
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor  # noqa: E402
from facerec3d.server.keys import add_key, key_hash  # noqa: E402

SUBJECTS = 4  # enrolled directly (templates of synthetic faces) before the service starts


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_gallery(path: Path) -> None:
    """Subjects s0..s3, one template each, made directly from synthetic faces (no preprocessing)."""
    m = ICPMatcher()
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), m)
        for s in range(SUBJECTS):
            t = m.enroll(frontal_face(s))
            t.subject, t.scan_id = f"s{s}", f"s{s}-gallery"
            store.add(t, f"/synthetic/{s}")


def probe_file(folder: Path, subject: int, seed: int) -> Path:
    """A probe scan of a subject (moved ≤ 3° / 3 mm, 0.3 mm noise) as an .npz file (~150 KB)."""
    path = folder / f"probe-{subject}-{seed}.npz"
    if not path.exists():
        save_scan(frontal_face(subject, pose_deg=3.0, shift_mm=3.0, noise_mm=0.3, seed=seed), path)
    return path


class Server:
    """`facerec3d serve` as a child process on a free loopback port."""

    def __init__(self, gallery: Path, keys: Path, *options: str):
        self.gallery, self.keys, self.options = gallery, keys, options
        self.start()

    def start(self) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = open(self.gallery.with_suffix(f".{self.port}.log"), "w+")
        self.proc = subprocess.Popen([sys.executable, "-m", "facerec3d.cli", "serve", "--gallery", str(self.gallery),
                                      "--keys", str(self.keys), "--port", str(self.port), *self.options],
                                     stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 180
        while True:
            if self.proc.poll() is not None:
                self.log.seek(0)
                raise RuntimeError(f"the service exited with {self.proc.returncode}:\n{self.log.read()}")
            try:
                if httpx.get(f"{self.url}/v1/health", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "the service did not start"
            time.sleep(0.2)

    def output(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()
        self.log.close()


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A gallery of 4 subjects, keys with different scopes, and a running service (2 worker processes, small
    limits: 1 MiB uploads, 50,000-point scans, 2 requests at once + 2 waiting, 2 per key)."""
    tmp = tmp_path_factory.mktemp("service")
    gallery, keys = tmp / "g.sqlite", tmp / "keys.json"
    make_gallery(gallery)
    key = {name: add_key(keys, name, scopes) for name, scopes in
           [("alice", "enrol,query,admin"), ("bob", "query"), ("carol", "enrol"), ("dave", "query"),
            ("erin", "query")]}
    server = Server(gallery, keys, "--jobs", "2", "--concurrency", "2", "--queue", "2", "--per-key", "2",
                    "--max-upload-mb", "1", "--max-points", "50000", "--timeout", "120")
    yield {"tmp": tmp, "gallery": gallery, "keys": keys, "key": key, "server": server, "url": server.url}
    server.stop()


def call(setup, method, path, key="alice", **kw):
    headers = kw.pop("headers", {})
    if key is not None:
        headers["X-API-Key"] = setup["key"].get(key, key)
    return httpx.request(method, setup["url"] + path, headers=headers, timeout=120, **kw)


def assert_error(r, status: int, *words: str) -> dict:
    """A one-line JSON error with this status whose reason has these words."""
    assert r.status_code == status, r.text
    assert "\n" not in r.text.strip()
    body = r.json()
    assert body["status"] == status and isinstance(body["error"], str) and body["error"]
    for w in words:
        assert w in body["error"], body["error"]
    return body


def healthy(setup) -> None:
    r = httpx.get(setup["url"] + "/v1/health", timeout=10)
    assert r.status_code == 200 and r.json()["status"] == "ok"


def test_enrol_identify_verify_remove(setup):
    tmp = setup["tmp"]
    with Client(setup["url"], setup["key"]["alice"]) as c:
        assert c.health()["entries"] == SUBJECTS
        for cascade in (False, True):
            answer = c.identify(probe_file(tmp, 2, 100), k=3, cascade=cascade)
            assert answer["cascade"] is cascade and answer["gallery_entries"] == SUBJECTS
            best = answer["candidates"][0]
            assert (best["rank"], best["subject"], best["scan_id"]) == (1, "s2", "s2-gallery")
            assert len(answer["candidates"]) == 3 and answer["candidates"][0]["score"] > answer["candidates"][1]["score"]
            assert answer["timings"]["preprocess_ms"] > 0 and answer["timings"]["match_ms"] > 0
        # a new subject: enrolled, then found, verified, removed
        new = probe_file(tmp, 7, 1)
        entry = c.enrol(new, subject="s7")
        assert entry["subject"] == "s7" and entry["scan_id"] == new.name[:-4] and entry["source"].startswith("upload:sha256:")
        with pytest.raises(ServiceError) as e:  # the same bytes again
            c.enrol(new, subject="s7")
        assert e.value.status == 409 and f"entry {entry['id']}" in e.value.reason
        probe = probe_file(tmp, 7, 2)
        assert c.identify(probe, k=1)["candidates"][0]["entry"] == entry["id"]
        v = c.verify(probe, claim="s7")
        assert v["accepted"] is True and v["threshold"] == DEFAULT_THRESHOLDS["icp"] and v["score"] >= v["threshold"]
        v = c.verify(probe, claim="s1", threshold=-0.5)
        assert v["accepted"] is False and v["threshold"] == -0.5 and v["score"] < -0.5
        with pytest.raises(ServiceError) as e:
            c.verify(probe, claim="nobody")
        assert e.value.status == 404 and "not enrolled" in e.value.reason
        assert {"subject": "s7", "entries": 1} in c.subjects()
        removed = c.remove("s7")
        assert removed["removed"] == [entry["id"]] and removed["subjects"] == ["s7"]
        assert "s7" not in {s["subject"] for s in c.subjects()}
        assert c.identify(probe, k=1)["candidates"][0]["subject"] != "s7"
        with pytest.raises(ServiceError) as e:
            c.remove("s7")
        assert e.value.status == 404
        # two people's scans of one name (a depth camera's front_1): the name alone removes neither, an id removes one
        twins = []
        for subject in (10, 11):
            (tmp / f"t{subject}").mkdir(exist_ok=True)
            twins.append(tmp / f"t{subject}" / "front_1.npz")
            twins[-1].write_bytes(probe_file(tmp, subject, 1).read_bytes())
        ids = [c.enrol(f, subject=f"s{k}")["id"] for f, k in zip(twins, (10, 11))]
        with pytest.raises(ServiceError) as e:
            c.remove("front_1")
        assert e.value.status == 409 and "2 subjects" in e.value.reason and "/v1/entries/" in e.value.reason
        assert {"s10", "s11"} <= {s["subject"] for s in c.subjects()}
        assert c.remove_entry(ids[0])["removed"] == [ids[0]]
        assert {s["subject"] for s in c.subjects()} >= {"s11"} and "s10" not in {s["subject"] for s in c.subjects()}
        with pytest.raises(ServiceError) as e:
            c.remove_entry(ids[0])
        assert e.value.status == 404
        assert c.remove("front_1")["removed"] == [ids[1]]  # now one subject's: removed
        st = c.stats()
        assert st["entries"] == SUBJECTS and st["method"] == "icp" and len(st["preprocess_fingerprint"]) == 16
        assert "failures_to_enrol" in st and st["queue"]["capacity"] == 4
    # the store holds what the service said (read while it runs: WAL)
    with GalleryStore(setup["gallery"]) as store:
        assert [e.subject for e in store.entries()] == [f"s{s}" for s in range(SUBJECTS)]
    audit = [json.loads(line) for line in Path(str(setup["gallery"]) + ".audit.jsonl").read_text().splitlines()]
    mine = [a for a in audit if a.get("subject") == "s7" or a.get("ident") == "s7"]
    assert [a["action"] for a in mine] == ["enrol", "remove"]
    assert all(a["key"] == "alice" and a["client"] == "127.0.0.1" and a["time"].endswith("Z") for a in mine)
    assert mine[0]["entry"] == entry["id"] and mine[1]["entries"] == [entry["id"]]


def test_keys_and_scopes(setup):
    tmp = setup["tmp"]
    probe = probe_file(tmp, 1, 100)
    files = {"probe": (probe.name, probe.read_bytes())}
    assert_error(call(setup, "POST", "/v1/identify", key=None, files=files), 401, "API key")
    assert_error(call(setup, "POST", "/v1/identify", key="fr3d_not-a-key", files=files), 401, "unknown")
    assert_error(call(setup, "GET", "/v1/stats", key=None), 401)
    assert_error(call(setup, "GET", "/metrics", key=None), 401)
    # scopes: carol may enrol only, bob may query only
    assert_error(call(setup, "POST", "/v1/identify", key="carol", files=files), 403, "carol", "query")
    scan = {"scan": (probe.name, probe.read_bytes())}
    assert_error(call(setup, "POST", "/v1/enrol", key="bob", files=scan, data={"subject": "x"}), 403, "bob", "enrol")
    assert_error(call(setup, "DELETE", "/v1/subjects/s1", key="bob"), 403, "admin")
    assert_error(call(setup, "GET", "/v1/subjects", key="bob"), 403, "admin")
    r = call(setup, "POST", "/v1/identify", key="bob", files=files, data={"k": "1"})
    assert r.status_code == 200 and r.json()["candidates"][0]["subject"] == "s1"
    r = call(setup, "GET", "/v1/stats", key=None, headers={"Authorization": f"Bearer {setup['key']['bob']}"})
    assert r.status_code == 200
    # keys are stored as hashes only; denied writes are audited
    text = setup["keys"].read_text()
    assert all(k not in text and key_hash(k) in text for k in setup["key"].values())
    assert oct(setup["keys"].stat().st_mode & 0o777) == "0o600"
    audit = Path(str(setup["gallery"]) + ".audit.jsonl").read_text()
    assert '"action":"denied","key":"bob"' in audit
    # the service re-reads the key file: a new key works at once, a revoked one no longer
    r = CliRunner().invoke(main, ["keys", "add", "frank", "--scopes", "query", "--keys", str(setup["keys"])])
    assert r.exit_code == 0, r.output
    frank = r.stdout.strip().splitlines()[0]
    assert frank.startswith("fr3d_") and frank not in setup["keys"].read_text()
    assert call(setup, "GET", "/v1/stats", key=frank).status_code == 200
    r = CliRunner().invoke(main, ["keys", "list", "--keys", str(setup["keys"])])
    assert "frank\tquery" in r.output and frank not in r.output
    r = CliRunner().invoke(main, ["keys", "remove", "frank", "--keys", str(setup["keys"])])
    assert r.exit_code == 0
    assert_error(call(setup, "GET", "/v1/stats", key=frank), 401)
    r = CliRunner().invoke(main, ["keys", "add", "x", "--scopes", "everything", "--keys", str(setup["keys"])])
    assert r.exit_code == 2 and "unknown scope" in r.output


def test_bad_uploads_are_4xx_json_and_the_service_keeps_serving(setup):
    tmp = setup["tmp"]
    corrupt = [("junk.abs", b"not a range image\n" * 20), ("junk.npz", os.urandom(5000)),
               ("junk.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\n"),
               ("truncated.abs.gz", b"\x1f\x8b\x08\x00" + os.urandom(100))]
    for name, data in corrupt:
        body = assert_error(call(setup, "POST", "/v1/identify", files={"probe": (name, data)}), 422, name)
        assert "/tmp" not in body["error"]  # the reason, never the service's temporary path
        body = assert_error(call(setup, "POST", "/v1/enrol", files={"scan": (name, data)}, data={"subject": "bad"}),
                            422, "failure to enrol", name)
        healthy(setup)
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": ("scan.exe", b"MZ" * 100)}), 415, ".exe")
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": ("empty.npz", b"")}), 422, "empty")
    assert_error(call(setup, "POST", "/v1/identify", data={"k": "3"}), 422, "probe")
    probe = probe_file(tmp, 3, 100)
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": (probe.name, probe.read_bytes())},
                      data={"k": "0"}), 422, "k")
    assert_error(call(setup, "POST", "/v1/enrol", files={"scan": (probe.name, probe.read_bytes())},
                      data={"subject": "../../etc"}), 422, "subject")
    # over the upload limit (1 MiB): refused from Content-Length, and while a chunked upload streams in
    big = os.urandom(2 * 2**20)
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": ("big.npz", big)}), 413, "limit")

    def chunks():  # a well-formed multipart body, streamed without a Content-Length
        yield (b'--xyz\r\nContent-Disposition: form-data; name="probe"; filename="big.npz"\r\n'
               b"Content-Type: application/octet-stream\r\n\r\n")
        for i in range(0, len(big), 65536):
            yield big[i:i + 65536]
        yield b"\r\n--xyz--\r\n"

    r = call(setup, "POST", "/v1/identify", content=chunks(),
             headers={"Content-Type": "multipart/form-data; boundary=xyz"})
    assert_error(r, 413, "limit")
    # over the scan size limit (50,000 points)
    cloud = tmp / "cloud.npy"
    np.save(cloud, np.random.default_rng(0).normal(0, 50, (60000, 3)).astype(np.float32))
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": ("cloud.npy", cloud.read_bytes())}), 413,
                 "60000 points")
    # a file name is a label, never a path on the service
    r = call(setup, "POST", "/v1/identify", files={"probe": ("../../../../tmp/evil.npz", probe.read_bytes())},
             data={"k": "1"})
    assert r.status_code == 200 and r.json()["candidates"][0]["subject"] == "s3"
    assert not Path("/tmp/evil.npz").exists()
    openapi = call(setup, "GET", "/openapi.json", key=None).json()
    assert {"/v1/enrol", "/v1/identify", "/v1/verify", "/v1/subjects", "/v1/subjects/{ident}", "/v1/health",
            "/v1/stats", "/v1/entries", "/v1/calibrate", "/metrics"} <= set(openapi["paths"])
    fields = {f for name, schema in openapi["components"]["schemas"].items() if name.startswith("Body_")
              for f in schema["properties"]}
    assert fields == {"scan", "probe", "subject", "scan_id", "format", "intrinsics", "k", "cascade", "shortlist",
                      "screen", "claim", "threshold", "fmr", "eer", "own"}  # nothing names a file on the service
    # the failures to enrol were recorded, the service still answers
    listed = call(setup, "GET", "/v1/entries").json()
    assert len(listed["failures"]) >= len(corrupt) and all(f["source"].startswith("upload:") for f in listed["failures"])
    healthy(setup)


def test_queue_limits_and_time_limit(setup):
    """2 at once + 2 waiting, 2 per key: a key's third request is 429, a fifth request is 503; a request past
    its time limit is 504; all one-line JSON, and the service goes on."""
    tmp = setup["tmp"]
    probe = probe_file(tmp, 0, 100)
    files = {"probe": (probe.name, probe.read_bytes())}

    def busy() -> int:
        q = call(setup, "GET", "/v1/stats", key="erin").json()["queue"]
        return q["running"] + q["waiting"]

    def when_busy(holders: list[str], key: str):
        """`key`'s request while the holders' requests are in flight (running or waiting). A request takes ~0.1 s
        once the workers are warm, so one of them may end between the count and the request (then that request
        finds room, 200): tried again, up to 5 times, so a service that never refuses still fails."""
        for _ in range(5):
            held = [pool.submit(call, setup, "POST", "/v1/identify", key=k, files=files) for k in holders]
            slow.extend(held)
            deadline = time.monotonic() + 20
            while busy() < len(holders) and not all(f.done() for f in held):
                assert time.monotonic() < deadline
                time.sleep(0.005)
            r = call(setup, "POST", "/v1/identify", key=key, files=files)
            [f.result() for f in held]  # nothing left in flight for the next try
            if r.status_code != 200:
                return r
        return r

    slow = []
    with ThreadPoolExecutor(4) as pool:
        r = when_busy(["alice", "alice"], "alice")
        assert_error(r, 429, "alice")
        assert r.headers["retry-after"]
        r = when_busy(["alice", "alice", "bob", "bob"], "dave")
        assert_error(r, 503, "queue is full")
        assert {f.result().status_code for f in slow} == {200}
    r = call(setup, "POST", "/v1/identify", files=files, headers={"X-Request-Timeout": "0.05"})
    assert_error(r, 504, "time limit")
    metrics = call(setup, "GET", "/metrics").text
    assert 'facerec3d_requests_total{method="POST",endpoint="/v1/identify",status="429"}' in metrics
    assert 'facerec3d_requests_total{method="POST",endpoint="/v1/identify",status="503"}' in metrics
    assert "facerec3d_queue_length " in metrics and "facerec3d_request_duration_seconds_bucket" in metrics
    deadline = time.monotonic() + 30
    while busy():  # the abandoned request's work drains away
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert call(setup, "POST", "/v1/identify", files=files).status_code == 200


def test_identification_during_enrolment_sees_whole_versions(setup):
    """Enrolments and identifications at once: each identification answers from one gallery version, whose
    size is the one that version had (before or after an enrolment, never between)."""
    tmp = setup["tmp"]
    health = call(setup, "GET", "/v1/health").json()
    base = health["entries"]
    size = {health["gallery_version"]: base}
    scans = [probe_file(tmp, 20 + i, 1) for i in range(2)]
    probe = probe_file(tmp, 1, 101)
    with Client(setup["url"], setup["key"]["alice"]) as enroller, Client(setup["url"], setup["key"]["bob"]) as asker:
        def enrol_all():
            out = []
            for i, s in enumerate(scans):
                out.append(enroller.enrol(s, subject=f"new{i}"))
            return out

        with ThreadPoolExecutor(2) as pool:
            enrolled = pool.submit(enrol_all)
            answers = [asker.identify(probe, k=10) for _ in range(3)]
            enrolled = enrolled.result()
        for i, e in enumerate(enrolled):
            size[e["gallery_version"]] = base + i + 1
        for a in answers:
            assert a["gallery_entries"] == size[a["gallery_version"]]
            assert len(a["candidates"]) == a["gallery_entries"]
            assert a["candidates"][0]["subject"] == "s1"
        for i in range(len(scans)):
            enroller.remove(f"new{i}")


def test_cli_against_the_service(setup):
    tmp, url = setup["tmp"], setup["url"]
    run = CliRunner(env={"FACEREC3D_API_KEY": setup["key"]["alice"]})
    scans = [probe_file(tmp, 30, 1), probe_file(tmp, 30, 2)]
    bad = tmp / "broken.abs"
    bad.write_text("not a range image\n")
    r = run.invoke(main, ["enroll", *map(str, scans), str(bad), "--server", url, "--subject", "s30", "--jobs", "2"])
    assert r.exit_code == 0, r.output
    assert "2 enrolled, 0 already enrolled, 1 failed to enrol" in r.output and "broken.abs" in r.output
    r = run.invoke(main, ["enroll", str(scans[0]), "--server", url, "--subject", "s30"])
    assert "0 enrolled, 1 already enrolled" in r.output
    r = run.invoke(main, ["enroll", str(bad), "--server", url, "--subject", "s30"])  # nothing succeeded: exit 1
    assert r.exit_code == 1 and "0 enrolled, 0 already enrolled, 1 failed to enrol" in r.output, r.output
    r = run.invoke(main, ["identify", str(probe_file(tmp, 30, 3)), "--server", url, "-k", "2", "--cascade"])
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[1].split()[:2] == ["1", "s30"] and len(r.output.splitlines()) == 3
    r = run.invoke(main, ["verify", str(probe_file(tmp, 30, 3)), "--server", url, "--claim", "s30"])
    assert r.exit_code == 0 and r.output.startswith("accept"), r.output
    # the enrolment calibrated the service's threshold on its 2 scans against the 4 other people: 8 impostor pairs,
    # about 1 stranger's claim in 9 accepted: the answer says so (expected_fmr) and the CLI's hint with it
    assert "too few for its false-match rate: about 11% of strangers' claims" in r.output, r.output
    assert f"facerec3d gallery --server {url} calibrate SCANS" in r.output, r.output
    with Client(url, setup["key"]["alice"]) as c:
        assert c.verify(probe_file(tmp, 30, 3), "s30")["expected_fmr"] == pytest.approx(1 / 9)
        assert "expected_fmr" not in c.verify(probe_file(tmp, 30, 3), "s30", -50.0)  # a threshold given: its own
    r = run.invoke(main, ["verify", str(probe_file(tmp, 30, 3)), "--server", url, "--claim", "s30", "--threshold", "-50"])
    assert r.exit_code == 0 and "hint" not in r.output, r.output
    r = run.invoke(main, ["verify", str(probe_file(tmp, 30, 3)), "--server", url, "--claim", "s2"])
    assert r.exit_code == 1 and r.output.startswith("reject"), r.output
    r = run.invoke(main, ["gallery", "--server", url, "stats"])
    assert r.exit_code == 0 and f"{SUBJECTS + 2} entries of {SUBJECTS + 1} subjects" in r.output
    r = run.invoke(main, ["gallery", "--server", url, "list"])
    assert r.exit_code == 0 and sum("\ts30\t" in line for line in r.output.splitlines()) == 2
    r = run.invoke(main, ["gallery", "--server", url, "remove", "s30"])
    assert r.exit_code == 0 and "removed 2 entries" in r.output
    r = run.invoke(main, ["gallery", "--server", url, "remove", "s30"])
    assert r.exit_code == 2 and "no subject or scan" in r.output
    # the key from --api-key; wrong keys and scopes are one line, exit code 2
    r = CliRunner().invoke(main, ["identify", str(scans[0]), "--server", url, "--api-key", setup["key"]["carol"]])
    assert r.exit_code == 2 and "403" in r.output and "Traceback" not in r.output
    r = CliRunner(env={"FACEREC3D_API_KEY": "fr3d_wrong"}).invoke(main, ["gallery", "--server", url, "list"])
    assert r.exit_code == 2 and "401" in r.output
    r = run.invoke(main, ["identify", str(scans[0]), "--server", url, "--gallery", str(setup["gallery"])])
    assert r.exit_code == 2 and "cannot be used with --server" in r.output
    r = run.invoke(main, ["identify", str(scans[0])])
    assert r.exit_code == 2 and "--gallery" in r.output


def preprocessed_file(folder: Path, raw: Path, config: PreprocessConfig = PreprocessConfig(), name: str = "") -> Path:
    """The face `facerec3d preprocess` would write for scan `raw` under `config` (an .npz recording its
    preprocess_fingerprint)."""
    path = folder / f"face-{name or raw.stem}.npz"
    if not path.exists():
        save_scan(Preprocessor(config)(load_scan(raw)), path)
    return path


def uploads(setup) -> dict:
    return call(setup, "GET", "/v1/stats", key="erin").json()["uploads"]


def test_preprocessed_upload_is_matched_without_preprocessing_again(setup):
    """A face preprocessed at the edge with the service's settings identifies, verifies and enrols like its raw
    scan, with the service's preprocessing skipped (the answer's preprocessed_upload, the stats' counts); the
    Python client and the CLI do it with preprocess_locally / --preprocess-locally."""
    tmp, url = setup["tmp"], setup["url"]
    raw = probe_file(tmp, 2, 100)
    face = preprocessed_file(tmp, raw)
    st = call(setup, "GET", "/v1/stats", key="erin").json()
    assert load_scan(face).meta.extra["preprocess_fingerprint"] == st["preprocess_fingerprint"] \
        == PreprocessConfig().digest()
    before = uploads(setup)
    by_raw = call(setup, "POST", "/v1/identify", files={"probe": (raw.name, raw.read_bytes())}, data={"k": "4"})
    by_face = call(setup, "POST", "/v1/identify", files={"probe": (face.name, face.read_bytes())}, data={"k": "4"})
    assert by_raw.status_code == 200 and by_face.status_code == 200, (by_raw.text, by_face.text)
    by_raw, by_face = by_raw.json(), by_face.json()
    assert by_raw["preprocessed_upload"] is False and by_face["preprocessed_upload"] is True
    # the same face: the same ranking and (up to rounding) the same scores as when the service preprocessed it
    assert [c["subject"] for c in by_face["candidates"]] == [c["subject"] for c in by_raw["candidates"]]
    assert by_face["candidates"][0]["subject"] == "s2"
    assert [c["score"] for c in by_face["candidates"]] == pytest.approx([c["score"] for c in by_raw["candidates"]],
                                                                       rel=1e-3, abs=1e-3)
    # the service's preprocessing (hundreds of ms) skipped: what remains is the check of the face
    assert by_raw["timings"]["preprocess_ms"] > 100 and by_face["timings"]["preprocess_ms"] < 50
    after = uploads(setup)
    assert (after["raw"] - before["raw"], after["preprocessed"] - before["preprocessed"]) == (1, 1)
    with Client(url, setup["key"]["alice"]) as c:
        a = c.identify(raw, k=1, cascade=True, preprocess_locally=True)
        assert a["preprocessed_upload"] is True and a["cascade"] is True and a["candidates"][0]["subject"] == "s2"
        v = c.verify(raw, claim="s2", preprocess_locally=True)
        assert v["preprocessed_upload"] is True and v["accepted"] is True
        assert c.verify(face, claim="s1")["accepted"] is False  # a preprocessed file is uploaded as it is
        new = probe_file(tmp, 8, 1)
        entry = c.enrol(new, subject="s8", preprocess_locally=True)
        assert entry["preprocessed_upload"] is True and entry["scan_id"] == new.stem
        found = c.identify(probe_file(tmp, 8, 2), k=1)  # a raw probe finds the face enrolled from the edge
        assert found["preprocessed_upload"] is False and found["candidates"][0]["entry"] == entry["id"]
        assert c.remove("s8")["removed"] == [entry["id"]]
    assert uploads(setup)["preprocessed"] - after["preprocessed"] == 4
    run = CliRunner(env={"FACEREC3D_API_KEY": setup["key"]["alice"]})
    r = run.invoke(main, ["identify", str(raw), "--server", url, "-k", "2", "--cascade", "--preprocess-locally"])
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[1].split()[:2] == ["1", "s2"] and len(r.output.splitlines()) == 3
    r = run.invoke(main, ["verify", str(raw), "--server", url, "--claim", "s2", "--preprocess-locally"])
    assert r.exit_code == 0 and r.output.startswith("accept"), r.output
    assert uploads(setup)["preprocessed"] - after["preprocessed"] == 6
    r = run.invoke(main, ["identify", str(raw), "--gallery", str(setup["gallery"]), "--preprocess-locally"])
    assert r.exit_code == 2 and "--server only" in r.output


def test_preprocessed_upload_with_other_settings_is_refused(setup):
    """A face preprocessed with settings other than the gallery's (another fingerprint, or none recorded) is
    422 with both fingerprints in the reason — never preprocessed twice, never a failure to enrol — and a
    face off the gallery's grid is 422 too; the service keeps serving."""
    tmp = setup["tmp"]
    raw = probe_file(tmp, 3, 100)
    other = PreprocessConfig(crop_radius_mm=70.0)
    face = preprocessed_file(tmp, raw, other, "other-settings")
    own = PreprocessConfig().digest()
    assert load_scan(face).meta.extra["preprocess_fingerprint"] == other.digest() != own
    failures = len(call(setup, "GET", "/v1/entries").json()["failures"])
    before = uploads(setup)
    body = assert_error(call(setup, "POST", "/v1/identify", files={"probe": (face.name, face.read_bytes())}), 422,
                        face.name, "other settings", other.digest(), own, "raw scan")
    assert "/tmp" not in body["error"]
    assert_error(call(setup, "POST", "/v1/verify", files={"probe": (face.name, face.read_bytes())},
                      data={"claim": "s3"}), 422, other.digest(), own)
    body = assert_error(call(setup, "POST", "/v1/enrol", files={"scan": (face.name, face.read_bytes())},
                             data={"subject": "s3x"}), 422, other.digest(), own)
    assert "failure to enrol" not in body["error"]
    # a face from a facerec3d that recorded no fingerprint: its settings are unknown
    old = load_scan(preprocessed_file(tmp, raw))
    extra = {k: v for k, v in old.meta.extra.items() if k != "preprocess_fingerprint"}
    unknown = tmp / "face-no-fingerprint.npz"
    save_scan(old.replace(meta=old.meta.replace(extra=extra)), unknown)
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": (unknown.name, unknown.read_bytes())}), 422,
                 "unknown settings", own)
    # the right fingerprint on a face off the resampling grid (a point cloud): refused, not matched
    cloud = tmp / "face-cloud.npz"
    save_scan(old.replace(grid=None, grid_shape=None), cloud)
    assert_error(call(setup, "POST", "/v1/identify", files={"probe": (cloud.name, cloud.read_bytes())}), 422,
                 "resampling grid")
    assert uploads(setup) == before  # none of them was used
    assert len(call(setup, "GET", "/v1/entries").json()["failures"]) == failures  # no failure to enrol recorded
    healthy(setup)
    r = call(setup, "POST", "/v1/identify", files={"probe": (raw.name, raw.read_bytes())}, data={"k": "1"})
    assert r.status_code == 200 and r.json()["candidates"][0]["subject"] == "s3"


def test_serves_on_loopback_by_default(setup):
    out = setup["server"].output()
    assert f"on http://127.0.0.1:{setup['server'].port}" in out
    assert next(p for p in main.commands["serve"].params if p.name == "host").default == "127.0.0.1"
    try:
        outside = socket.gethostbyname(socket.gethostname())
    except OSError:
        outside = None
    if outside and not outside.startswith("127."):
        with pytest.raises(OSError):
            socket.create_connection((outside, setup["server"].port), timeout=2).close()


def test_kill_9_mid_enrolment_loses_no_acknowledged_entry(tmp_path):
    """Enrolments stream in from 3 clients; the service is killed (SIGKILL) right after the second
    acknowledgement, with more in flight; after a restart every acknowledged entry is there, whole, and the
    store is intact."""
    gallery, keys = tmp_path / "g.sqlite", tmp_path / "keys.json"
    make_gallery(gallery)
    key = add_key(keys, "writer", "enrol,query,admin")
    scans = [probe_file(tmp_path, 40 + i, 1) for i in range(9)]
    server = Server(gallery, keys, "--jobs", "1", "--concurrency", "3")
    acked: list[dict] = []
    lock = threading.Lock()
    try:
        def writer(mine):
            with Client(server.url, key, retries=0) as c:
                for s in mine:
                    try:
                        entry = c.enrol(s, subject=s.stem.split("-")[1])
                    except ServiceError:  # the service went away
                        return
                    with lock:
                        acked.append(entry)

        threads = [threading.Thread(target=writer, args=(scans[i::3],)) for i in range(3)]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 120
        while len(acked) < 2:
            assert time.monotonic() < deadline and server.proc.poll() is None
            time.sleep(0.005)
        server.kill9()
        for t in threads:
            t.join()
    finally:
        if server.proc.poll() is None:
            server.kill9()
    assert server.proc.returncode == -signal.SIGKILL and 2 <= len(acked) < len(scans)
    db = sqlite3.connect(gallery)
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert db.execute("SELECT COUNT(*) FROM entries WHERE id NOT IN (SELECT entry FROM arrays)").fetchone()[0] == 0
    db.close()
    server.start()  # the same store, restarted
    try:
        with Client(server.url, key) as c:
            listed = {e["id"]: e for e in c.entries()["entries"]}
            for entry in acked:
                assert listed[entry["id"]]["source"] == entry["source"]
                assert listed[entry["id"]]["subject"] == entry["subject"]
            assert len(listed) >= SUBJECTS + len(acked)
            last = acked[-1]
            probe = next(s for s in scans if s.stem.split("-")[1] == last["subject"])
            hit = c.identify(probe, k=1)["candidates"][0]
            assert hit["entry"] == last["id"] and hit["score"] > -1e-6  # the same scan, whole
    finally:
        server.stop()


def held_message(server: "Server") -> str:
    """The one line a local write to a served store is refused with."""
    return (f"error: {server.gallery}: a gallery service (pid {server.proc.pid}, {server.url}) holds this gallery: "
            f"change it through the service (--server {server.url}), or stop the service first\n")


def test_a_served_gallery_refuses_local_writes_and_a_second_service(tmp_path):
    """While a service serves a store, local commands that write to it (enroll, gallery remove, calibrate) are
    refused with one line naming the service's URL, the store unchanged (the service would go on answering from
    its memory: a subject removed locally still identified); reads go on; a second service on it is refused. Once
    the service has stopped, local writes work again."""
    gallery, keys = tmp_path / "g.sqlite", tmp_path / "keys.json"
    make_gallery(gallery)
    add_key(keys, "alice", "enrol,query,admin")
    server = Server(gallery, keys, "--jobs", "1")
    try:
        run = CliRunner()
        for args in (["gallery", str(gallery), "remove", "s1"],
                     ["enroll", str(probe_file(tmp_path, 9, 1)), "--gallery", str(gallery), "--subject", "s9",
                      "--jobs", "1", "--no-calibrate"],
                     ["gallery", str(gallery), "calibrate", "--jobs", "1"]):
            r = run.invoke(main, args)
            assert r.exit_code == 2 and r.output == held_message(server), (args, r.output)
        r = run.invoke(main, ["gallery", str(gallery), "list"])  # reading goes on
        assert r.exit_code == 0 and [line.split("\t")[1] for line in r.output.splitlines()] == \
            [f"s{s}" for s in range(SUBJECTS)], r.output
        with GalleryStore(gallery) as store:
            assert [e.subject for e in store.entries()] == [f"s{s}" for s in range(SUBJECTS)]
            assert store.threshold() is None
        # a second service on the same store
        r = subprocess.run([sys.executable, "-m", "facerec3d.cli", "serve", "--gallery", str(gallery), "--keys",
                            str(keys), "--jobs", "1", "--port", "0"], capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and r.stderr == (
            f"error: {gallery}: a gallery service (pid {server.proc.pid}, {server.url}) serves this gallery already: "
            f"use it (--server {server.url}) or stop it first\n"), r.stderr
        with Client(server.url, add_key(keys, "bob", "query")) as c:
            assert c.identify(probe_file(tmp_path, 1, 2), k=1)["candidates"][0]["subject"] == "s1"
    finally:
        server.stop()  # SIGTERM
    r = CliRunner().invoke(main, ["gallery", str(gallery), "remove", "s1"])
    assert r.exit_code == 0 and r.output == "removed 1 entry\n", r.output


def test_local_writes_go_on_once_the_service_is_killed(tmp_path):
    """The service's hold on its store is a lock the kernel lets go when it dies: after SIGKILL (its worker
    processes, forked from it, hold nothing) local writes work again, and so does a new service."""
    gallery, keys = tmp_path / "g.sqlite", tmp_path / "keys.json"
    make_gallery(gallery)
    key = add_key(keys, "alice", "enrol,query,admin")
    server = Server(gallery, keys, "--jobs", "2")
    try:
        r = CliRunner().invoke(main, ["gallery", str(gallery), "remove", "s1"])
        assert r.exit_code == 2 and r.output == held_message(server), r.output
        server.kill9()
    finally:
        if server.proc.poll() is None:
            server.kill9()
    assert Path(str(gallery) + ".serve.lock").exists()  # left behind, and blocking nothing
    r = CliRunner().invoke(main, ["gallery", str(gallery), "remove", "s1"])
    assert r.exit_code == 0 and r.output == "removed 1 entry\n", r.output
    server.start()
    try:
        with Client(server.url, key) as c:
            assert c.stats()["entries"] == SUBJECTS - 1
        r = CliRunner().invoke(main, ["gallery", str(gallery), "remove", "s2"])
        assert r.exit_code == 2 and r.output == held_message(server), r.output
    finally:
        server.stop()


# ------------------------------------------------------------------------------- in-process pieces
def test_gallery_update_keeps_snapshots_consistent():
    """ShardedGallery.update: the old version stays whole for probes using it; the new one scores as a
    gallery loaded from scratch would, in its order."""
    from facerec3d.gallery.cascade import CascadeConfig
    from facerec3d.gallery.engine import Engine

    m = ICPMatcher()
    templates = [m.enroll(frontal_face(s)) for s in range(5)]
    probe_face = frontal_face(3, pose_deg=3.0, shift_mm=3.0, noise_mm=0.3, seed=9)
    with Engine.create(2) as engine:
        old = engine.load(m, templates[:3])
        old.describe(CascadeConfig())
        probe = engine.prepare(m, [probe_face], CascadeConfig())
        before = old.scores(probe)[0][0]
        new, order = old.update(add=templates[3:], remove=[1])
        assert len(new) == 4 and sorted(order.tolist()) == [0, 2, 3, 4]
        np.testing.assert_array_equal(old.scores(probe)[0][0], before)  # the snapshot is unchanged
        combined = templates[:3] + templates[3:]
        fresh = engine.load(m, [combined[i] for i in order])
        np.testing.assert_array_equal(new.scores(probe)[0][0], fresh.scores(probe)[0][0])
        (a,), (b,) = new.cascade(probe, CascadeConfig(shortlist=2)), fresh.cascade(probe, CascadeConfig(shortlist=2))
        for x, y in zip(a, b):  # scores, tiebreak, shortlist
            np.testing.assert_array_equal(x, y)
        at = new.scores_at(probe[0], [1, 3])
        np.testing.assert_array_equal(at[0], new.scores(probe)[0][0][[1, 3]])
        old.release()
        assert new.scores(probe)[0][0].shape == (4,)  # still loaded after the old version went
        emptied, _ = new.update(remove=range(4))
        assert len(emptied) == 0


def test_single_probe_commands_use_one_blas_thread(tmp_path, monkeypatch):
    from threadpoolctl import threadpool_info

    import facerec3d.gallery.service as service
    import facerec3d.preprocess as preprocess

    seen = []

    def spy(fn):
        def wrapped(*args, **kwargs):
            seen.append(max((p["num_threads"] for p in threadpool_info()), default=1))
            return fn(*args, **kwargs)
        return wrapped

    monkeypatch.setattr(service, "load_probe", spy(service.load_probe))
    monkeypatch.setattr(preprocess.Preprocessor, "__call__", spy(preprocess.Preprocessor.__call__))
    gallery = tmp_path / "g.sqlite"
    make_gallery(gallery)
    probe = probe_file(tmp_path, 2, 5)
    run = CliRunner()
    r = run.invoke(main, ["identify", str(probe), "--gallery", str(gallery), "--jobs", "1", "-k", "1",
                          "--cache", str(tmp_path / "c")])
    assert r.exit_code == 0 and r.output.splitlines()[1].split()[1] == "s2", r.output
    r = run.invoke(main, ["verify", str(probe), "--gallery", str(gallery), "--claim", "s2", "--cache", str(tmp_path / "c2")])
    assert r.exit_code == 0, r.output
    r = run.invoke(main, ["view", str(probe), "-o", str(tmp_path / "v.png")])
    assert r.exit_code == 0, r.output
    assert len(seen) >= 3 and set(seen) == {1}


def test_connections_to_the_bound_address_send_without_nagles_delay():
    """`app.bind_address` makes the socket uvicorn serves on. asyncio turns Nagle's algorithm off (TCP_NODELAY) only
    on connections whose socket names IPPROTO_TCP; one made without it left Nagle on, and every answer waited ~40 ms
    for the client's delayed ACK (the service's p95 against 1,000 faces went from 50 to 96 ms, its matching unchanged).
    The connection the event loop accepts on that socket must have TCP_NODELAY set."""
    import asyncio

    from facerec3d.server.app import bind_address

    sock = bind_address("127.0.0.1", 0)
    nodelay = []

    async def serve_one():
        accepted = asyncio.Event()

        class Once(asyncio.Protocol):
            def connection_made(self, transport):
                nodelay.append(transport.get_extra_info("socket").getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
                transport.close()
                accepted.set()

        server = await asyncio.get_running_loop().create_server(Once, sock=sock)
        reader, writer = await asyncio.open_connection(*sock.getsockname()[:2])
        await asyncio.wait_for(accepted.wait(), 10)
        writer.close()
        server.close()
        await server.wait_closed()

    asyncio.run(serve_one())
    assert nodelay and nodelay[0] != 0


def test_a_service_error_on_one_scan_is_its_failure_and_the_enrolment_goes_on(setup, monkeypatch):
    """A 5xx answer to one upload stopped `enroll --server` with no summary (the other scans' results untallied):
    now it is that scan's failure; a refused key still stops the command."""
    from facerec3d.client import Client, ServiceError

    tmp, url = setup["tmp"], setup["url"]
    scans = [probe_file(tmp, 31, 1), probe_file(tmp, 31, 2)]
    real = Client.enrol

    def flaky(self, scan, *args, **kwargs):
        if str(scan).endswith(scans[0].name):
            raise ServiceError(500, "internal error (RuntimeError): boom")
        return real(self, scan, *args, **kwargs)

    monkeypatch.setattr(Client, "enrol", flaky)
    run = CliRunner(env={"FACEREC3D_API_KEY": setup["key"]["alice"]})
    r = run.invoke(main, ["enroll", *map(str, scans), "--server", url, "--subject", "s31", "--no-calibrate"])
    assert r.exit_code == 0, r.output
    assert f"{scans[0]}: failed to enrol: service error 500: internal error (RuntimeError): boom" in r.output
    assert "1 enrolled, 0 already enrolled, 1 failed to enrol" in r.output
    r = run.invoke(main, ["enroll", str(scans[0]), "--server", url, "--subject", "s31", "--no-calibrate"])
    assert r.exit_code == 1 and "0 enrolled, 0 already enrolled, 1 failed to enrol" in r.output, r.output
    monkeypatch.setattr(Client, "enrol", real)
    assert run.invoke(main, ["gallery", "--server", url, "remove", "s31"]).exit_code == 0


def test_a_service_lost_mid_enrolment_says_how_far_it_got_and_fails(setup, monkeypatch):
    """The service gone mid-batch (`cannot reach the service`) stopped `enroll --server` with that one line and no
    word of the scans enrolled before it: now the scan it happened on is a failure whose outcome is unknown, the
    later ones are not sent, the summary says so and the command exits 1."""
    from facerec3d.client import Client, ServiceError

    tmp, url = setup["tmp"], setup["url"]
    scans = [probe_file(tmp, 32, k) for k in (1, 2, 3)]
    real, tried = Client.enrol, []

    def gone(self, scan, *args, **kwargs):
        tried.append(Path(scan).name)
        if not str(scan).endswith(scans[0].name):
            raise ServiceError(0, f"cannot reach the service at {url}: [Errno 111] Connection refused")
        return real(self, scan, *args, **kwargs)

    monkeypatch.setattr(Client, "enrol", gone)
    run = CliRunner(env={"FACEREC3D_API_KEY": setup["key"]["alice"]})
    r = run.invoke(main, ["enroll", *map(str, scans), "--server", url, "--subject", "s32", "--no-calibrate",
                          "--jobs", "1"])
    assert r.exit_code == 1, r.output
    assert tried == [scans[0].name, scans[1].name]  # nothing sent after the service was lost
    assert f"{scans[1]}: failed to enrol: cannot reach the service" in r.output
    assert "whether the service enrolled it is unknown" in r.output
    assert ("1 enrolled, 0 already enrolled, 1 failed to enrol, 1 not sent: the service stopped answering "
            "(cannot reach the service") in r.output
    monkeypatch.setattr(Client, "enrol", real)
    assert run.invoke(main, ["gallery", "--server", url, "remove", "s32"]).exit_code == 0


def mocked(handler) -> Client:
    """A client whose requests `handler` answers (httpx.MockTransport): no service needed."""
    client = Client("http://service.test", api_key="fr3d_test")
    client._http = httpx.Client(base_url=client.url, transport=httpx.MockTransport(handler))
    return client


def test_an_answer_that_is_no_json_or_a_redirect_is_one_line_and_an_empty_id_is_not_sent():
    """`gallery --server URL remove ""` died on a JSONDecodeError: the service redirects DELETE /v1/subjects/ (307,
    no body) and the client parsed any answer below 400 as JSON. An id no entry can have is refused before sending;
    a redirect, or an answer that is no JSON, is a ServiceError in one line."""
    from facerec3d.errors import InputError

    c = mocked(lambda r: httpx.Response(307, headers={"location": "http://service.test/v1/subjects"}))
    with pytest.raises(ServiceError, match="redirected DELETE /v1/subjects/x to http://service.test/v1/subjects"):
        c.remove("x")
    c = mocked(lambda r: httpx.Response(200, text="<html>a proxy's page</html>"))
    with pytest.raises(ServiceError, match="the answer to GET /v1/stats is not JSON"):
        c.stats()
    sent = []
    c = mocked(lambda r: sent.append(r) or httpx.Response(200, json={"removed": []}))
    for ident in ("", ".", ".."):
        with pytest.raises(InputError, match="bad subject or scan id"):
            c.remove(ident)
    assert not sent
    r = CliRunner().invoke(main, ["gallery", "--server", "http://127.0.0.1:9", "--api-key", "k", "remove", ""])
    assert r.exit_code == 2 and r.output == "error: remove: bad subject or scan id '': give a non-empty id (not . or ..)\n"


def test_a_malformed_service_url_is_one_line(tmp_path):
    """`identify F --server 'http://[::1'` and `Client('http://[::1')` died on httpx.InvalidURL."""
    from facerec3d.errors import InputError

    with pytest.raises(InputError, match=r"bad service URL 'http://\[::1'"):
        Client("http://[::1")
    r = CliRunner().invoke(main, ["identify", str(probe_file(tmp_path, 0, 1)), "--server", "http://[::1",
                                  "--api-key", "k"])
    assert r.exit_code == 2 and r.output.startswith("error: bad service URL 'http://[::1'"), r.output
    assert r.output.count("\n") == 1


def test_a_frame_with_bad_intrinsics_is_that_scans_failure_with_server(setup):
    """`identify dir/front_1.png --server URL` with a broken intrinsics.json beside the frame (not JSON, not UTF-8)
    died on a JSONDecodeError / UnicodeDecodeError, and `enroll --server` stopped at that frame with no summary. Now
    one line naming the file, as locally; the enrolment records it as that scan's failure and goes on."""
    tmp, url = setup["tmp"], setup["url"]
    run = CliRunner(env={"FACEREC3D_API_KEY": setup["key"]["alice"]})
    frames = tmp / "bad-intrinsics"
    frames.mkdir()
    frame = frames / "front_1.png"
    frame.write_bytes(b"\x89PNG\r\n\x1a\n")  # never read: its intrinsics fail first
    for content, said in [(b'{"fx": 365,', "intrinsics are not valid JSON"),
                          (b'{"fx": "\xff"}', "cannot read intrinsics (UnicodeDecodeError)")]:
        (frames / "intrinsics.json").write_bytes(content)
        r = run.invoke(main, ["identify", str(frame), "--server", url])
        assert r.exit_code == 2 and r.output.startswith(f"error: {frames / 'intrinsics.json'}: {said}"), r.output
        assert r.output.count("\n") == 1, r.output
    good = probe_file(tmp, 32, 1)
    r = run.invoke(main, ["enroll", str(frame), str(good), "--server", url, "--subject", "s32", "--no-calibrate"])
    assert r.exit_code == 0, r.output
    assert f"{frame}: failed to enrol: {frames / 'intrinsics.json'}: cannot read intrinsics" in r.output
    assert "1 enrolled, 0 already enrolled, 1 failed to enrol" in r.output and "Traceback" not in r.output
    r = run.invoke(main, ["enroll", str(frame), "--server", url, "--subject", "s32", "--no-calibrate"])
    assert r.exit_code == 1 and "0 enrolled, 0 already enrolled, 1 failed to enrol" in r.output, r.output
    assert run.invoke(main, ["gallery", "--server", url, "remove", "s32"]).exit_code == 0


def test_calibrate_takes_a_single_scan_as_a_list_of_one(tmp_path):
    """`Client.calibrate('file', 'subj')` read the path's characters as files (IsADirectoryError: '.')."""
    scan = probe_file(tmp_path, 0, 1)
    sent = []

    def answer(request):
        sent.append(request.read())
        return httpx.Response(200, json={"threshold": {"value": 0.5}})

    c = mocked(answer)
    for one in (str(scan), scan, c.upload(scan)):
        assert c.calibrate(one, "s0") == {"value": 0.5}
    for body in sent:
        assert body.count(b'name="scan"') == 1 and body.count(b'name="subject"') == 1 and b"\r\n\r\ns0\r\n" in body


def test_the_workers_warm_up_before_the_service_answers_and_a_failed_warm_up_only_warns(tmp_path, monkeypatch):
    """A fresh install's first enrolment took ~20 s and its first identification ~7 s (Numba compiling the kernels
    in the worker): `serve` now runs a synthetic frame through each worker first (`app.warm`). The gallery is not
    touched; a warm-up that fails is one warning line and the service still starts."""
    import facerec3d.server.live as live_module
    from facerec3d.server.app import warm
    from facerec3d.server.live import LiveGallery

    gallery = tmp_path / "g.sqlite"
    make_gallery(gallery)
    live = LiveGallery(gallery, jobs=1)
    try:
        before = (live.version, len(live.entries))
        import facerec3d.server.jobs as jobs

        ran = []
        real = jobs.Preprocessor

        class Spy(real):  # the warm-up preprocesses a frame with the gallery's settings (in this process: jobs=1)
            def __call__(self, scan):
                face = super().__call__(scan)
                ran.append((self.config == live.config, face.n_points))
                return face

        monkeypatch.setattr(jobs, "Preprocessor", Spy)
        said = []
        warm(live, said.append)
        assert len(ran) == 1 and ran[0][0] and ran[0][1] > 1000, ran
        monkeypatch.setattr(jobs, "Preprocessor", real)
        assert said[0] == "warming up 1 worker (on a first run this compiles facerec3d's kernels, ~30 s) ..."
        assert said[1].startswith("warmed up in ") and len(said) == 2, said
        assert (live.version, len(live.entries)) == before

        def broken(*args):
            raise RuntimeError("no face in the synthetic frame")

        monkeypatch.setattr(live_module, "warm_up", broken)
        said.clear()
        warm(live, said.append)
        assert said[1] == ("warning: the warm-up failed (RuntimeError: no face in the synthetic frame); the first "
                           "requests will be slower"), said
    finally:
        live.close()
