"""Issue 23, the service's items, over real HTTP (`facerec3d serve` as a child process, tests.test_server.Server)
and in process (FastAPI's TestClient): admission before the body is read, separate lanes for writes, a killed
worker replaced, failed authentication aggregated, refused writes audited, ids, intrinsics, store failures,
and a property-based fuzz of the upload endpoints under a memory bound."""

import json
import os
import signal
import socket
import time
import tracemalloc
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

httpx = pytest.importorskip("httpx")
pytest.importorskip("fastapi")
psutil = pytest.importorskip("psutil")

from fastapi.testclient import TestClient  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from facerec3d.gallery.store import GalleryError  # noqa: E402
from facerec3d.server.app import Service, ServiceSettings, create_app  # noqa: E402
from facerec3d.server.keys import KeyFile, add_key  # noqa: E402
from facerec3d.server.live import AuditLog, LiveGallery  # noqa: E402
from tests.test_security import attack_files  # noqa: E402
from tests.test_server import Server, assert_error, call, make_gallery, probe_file  # noqa: E402

MiB = 1 << 20


def audit_lines(gallery: Path) -> list[dict]:
    return [json.loads(line) for line in Path(str(gallery) + ".audit.jsonl").read_text().splitlines()]


# ---------------------------------------------------------------- a real service
@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A service with 2 worker processes, one query at a time and none waiting (the query lane holds 1), writes
    in their own lane (2 at once + 16 waiting, 9 per key), 1 MiB uploads."""
    tmp = tmp_path_factory.mktemp("served")
    gallery, keys = tmp / "g.sqlite", tmp / "keys.json"
    make_gallery(gallery)
    key = {name: add_key(keys, name, scopes) for name, scopes in
           [("alice", "enrol,query,admin"), ("bob", "query"), ("carol", "enrol"), ("dave", "query")]}
    server = Server(gallery, keys, "--jobs", "2", "--concurrency", "1", "--queue", "0", "--max-upload-mb", "1",
                    "--max-points", "50000")
    yield {"tmp": tmp, "gallery": gallery, "key": key, "server": server, "url": server.url}
    server.stop()


def hold(served, path: str, key: str, length: int = 500_000) -> socket.socket:
    """A request whose headers are sent with a little of its body, the rest never: it holds its place."""
    s = socket.create_connection(("127.0.0.1", served["server"].port))
    s.sendall(f"POST {path} HTTP/1.1\r\nHost: x\r\nX-API-Key: {served['key'][key]}\r\n"
              f"Content-Type: multipart/form-data; boundary=b\r\nContent-Length: {length}\r\n\r\n--b\r\n".encode())
    return s


def answer_without_body(served, path: str, key: str, length: int = 500_000) -> int:
    """The status the service answers to headers announcing a body that is never sent (0: no answer in 20 s)."""
    with socket.create_connection(("127.0.0.1", served["server"].port), timeout=20) as s:
        s.sendall(f"POST {path} HTTP/1.1\r\nHost: x\r\nX-API-Key: {served['key'][key]}\r\n"
                  f"Content-Type: multipart/form-data; boundary=b\r\nContent-Length: {length}\r\n\r\n".encode())
        try:
            head = s.recv(200).decode("latin-1")
        except socket.timeout:
            return 0
    return int(head.split()[1]) if head.startswith("HTTP/1.1") else 0


def lane(served, name: str) -> dict:
    return call(served, "GET", "/v1/stats", key="alice").json()[name]


def wait_for(condition, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_busy_answers_come_before_the_body_and_writes_have_their_own_lane(served):
    """Item 3: a full queue answers 503 from the headers alone (the upload is never read); item 11: an enrolment
    still gets through while queries fill their lane."""
    held = hold(served, "/v1/identify", "bob")  # takes the query lane's only place
    try:
        wait_for(lambda: lane(served, "queue")["waiting"] + lane(served, "queue")["running"] == 1, "admitted")
        assert answer_without_body(served, "/v1/identify", "dave") == 503
        assert answer_without_body(served, "/v1/verify", "dave") == 503
        scan = probe_file(served["tmp"], 5, 1)
        r = call(served, "POST", "/v1/enrol", key="carol", files={"scan": (scan.name, scan.read_bytes())},
                 data={"subject": "s5"})
        assert r.status_code == 201, r.text
        assert_error(call(served, "POST", "/v1/identify", key="dave",
                          files={"probe": (scan.name, scan.read_bytes())}), 503, "query queue is full")
    finally:
        held.close()
    wait_for(lambda: lane(served, "queue")["waiting"] + lane(served, "queue")["running"] == 0, "place given back")
    probe = probe_file(served["tmp"], 5, 2)
    r = call(served, "POST", "/v1/identify", key="dave", files={"probe": (probe.name, probe.read_bytes())})
    assert r.status_code == 200 and r.json()["candidates"][0]["subject"] == "s5"


def test_refused_writes_are_audited(served):
    """Item 12: 409, 413, 415, 422, 429 and 503 answers to enrolments and removals leave an audit line."""
    scan = probe_file(served["tmp"], 6, 1)
    files = {"scan": (scan.name, scan.read_bytes())}
    assert call(served, "POST", "/v1/enrol", key="carol", files=files, data={"subject": "s6"}).status_code == 201
    assert_error(call(served, "POST", "/v1/enrol", key="carol", files=files, data={"subject": "s6"}), 409)
    assert_error(call(served, "POST", "/v1/enrol", key="carol", files={"scan": ("big.npz", os.urandom(2 * MiB))},
                      data={"subject": "s6"}), 413)
    assert_error(call(served, "POST", "/v1/enrol", key="carol", files={"scan": ("x.exe", b"MZ")},
                      data={"subject": "s6"}), 415)
    assert_error(call(served, "POST", "/v1/enrol", key="carol", files=files, data={"subject": "s6\n"}), 422)
    assert_error(call(served, "DELETE", "/v1/subjects/nobody", key="alice"), 404)
    held = [hold(served, "/v1/enrol", "carol") for _ in range(9)]  # carol's 9 places of the write lane
    try:
        wait_for(lambda: lane(served, "write_queue")["waiting"] + lane(served, "write_queue")["running"] == 9,
                 "admitted")
        assert answer_without_body(served, "/v1/enrol", "carol") == 429
        held += [hold(served, "/v1/enrol", "alice") for _ in range(9)]  # and the lane's last 9
        wait_for(lambda: lane(served, "write_queue")["waiting"] + lane(served, "write_queue")["running"] == 18,
                 "admitted")
        assert answer_without_body(served, "/v1/enrol", "alice") == 503
    finally:
        for s in held:
            s.close()
    wait_for(lambda: lane(served, "write_queue")["waiting"] + lane(served, "write_queue")["running"] == 0,
             "places given back")
    refused = [a for a in audit_lines(served["gallery"]) if a["action"] == "refused"]
    assert {409, 413, 415, 422, 404, 429, 503} <= {a["status"] for a in refused}, refused
    assert all(a["reason"] and a["client"] == "127.0.0.1" for a in refused)
    assert any(a["status"] == 422 and "subject" in a["reason"] and a["key"] == "carol" for a in refused)
    assert any(a["status"] == 429 and a["key"] == "carol" for a in refused)


def test_failed_authentication_does_not_fill_the_audit_log(served):
    """Item 10: 300 bad-key enrolments leave one audit line (its repeats are counted, not written)."""
    before = len(audit_lines(served["gallery"]))

    def bad(i):
        return call(served, "POST", "/v1/enrol", key=f"fr3d_guess{i}", files={"scan": ("a.npz", b"x")},
                    data={"subject": "x"}).status_code

    with ThreadPoolExecutor(4) as pool:
        assert set(pool.map(bad, range(300))) == {401}
    new = audit_lines(served["gallery"])[before:]
    denied = [a for a in new if a["action"] == "denied"]
    assert 1 <= len(denied) <= 2 and len(new) <= 2, new
    assert denied[0]["reason"] == "unknown API key" and denied[0]["client"] == "127.0.0.1"


def worker_pids(server: Server) -> set[int]:
    return {p.pid for p in psutil.Process(server.proc.pid).children()
            if "resource_tracker" not in " ".join(p.cmdline())}


def test_a_killed_worker_is_replaced_and_health_says_degraded_meanwhile(tmp_path):
    """Item 2: after kill -9 of a worker process, /v1/health says degraded, requests answer 200 or 503 (never
    500), and within seconds a new worker serves the whole gallery again."""
    gallery, keys = tmp_path / "g.sqlite", tmp_path / "keys.json"
    make_gallery(gallery)
    key = add_key(keys, "alice", "enrol,query,admin")
    server = Server(gallery, keys, "--jobs", "2")
    try:
        workers = worker_pids(server)
        assert len(workers) == 2, workers
        probe = probe_file(tmp_path, 2, 1)
        files = {"probe": (probe.name, probe.read_bytes())}

        def identify():
            return httpx.post(server.url + "/v1/identify", headers={"X-API-Key": key}, files=files, timeout=120)

        assert identify().status_code == 200
        statuses, answers = [], []
        with ThreadPoolExecutor(1) as pool:
            load = pool.submit(lambda: [answers.append(identify().status_code) for _ in range(6)])
            os.kill(min(workers), signal.SIGKILL)
            deadline = time.monotonic() + 90
            while not statuses or statuses[-1] != "ok" or "degraded" not in statuses:
                assert time.monotonic() < deadline, statuses[-5:]
                statuses.append(httpx.get(server.url + "/v1/health", timeout=10).json()["status"])
                time.sleep(0.01)
            load.result()
        assert set(answers) <= {200, 503}, answers
        now = worker_pids(server)
        assert len(now) == 2 and min(workers) not in now
        r = identify()
        assert r.status_code == 200 and r.json()["candidates"][0]["subject"] == "s2"
        assert "replaced" in server.output() and "Traceback" not in server.output()
    finally:
        server.stop()


# ---------------------------------------------------------------- in process
@pytest.fixture(scope="module")
def app(tmp_path_factory):
    """The service in this process (one worker: this process), called through FastAPI's TestClient."""
    tmp = tmp_path_factory.mktemp("inproc")
    gallery, keys = tmp / "g.sqlite", tmp / "keys.json"
    make_gallery(gallery)
    key = add_key(keys, "alice", "enrol,query,admin")
    live = LiveGallery(gallery, jobs=1, audit=AuditLog(Path(str(gallery) + ".audit.jsonl")), max_points=50000)
    service = Service(live, KeyFile(keys), ServiceSettings(concurrency=2, queue=4, max_upload_bytes=4 * MiB))
    with TestClient(create_app(service), raise_server_exceptions=False) as client:
        client.headers["X-API-Key"] = key
        yield {"client": client, "live": live, "tmp": tmp, "gallery": gallery}
    service.close()


def test_ids_may_not_end_in_a_line_break(app):
    """Item 5: `$` let 'id\\n' through; ids are matched whole."""
    scan = probe_file(app["tmp"], 3, 1)
    for fields in ({"subject": "s9\n"}, {"subject": "s9", "scan_id": "x\n"}, {"subject": "s9\r"}):
        r = app["client"].post("/v1/enrol", files={"scan": (scan.name, scan.read_bytes())}, data=fields)
        assert_error(r, 422, "line breaks")
    assert all("\n" not in e.subject for e in app["live"].entries)


def test_ids_may_not_be_dot_or_dot_dot(app):
    """A subject '..' was enrolled (201) and then could not be fetched or removed by name: URL paths lose it. A file
    named '..' + suffix no longer gives the scan id '..'."""
    scan = probe_file(app["tmp"], 3, 1)
    for fields in ({"subject": ".."}, {"subject": "."}, {"subject": "s9", "scan_id": ".."}):
        r = app["client"].post("/v1/enrol", files={"scan": (scan.name, scan.read_bytes())}, data=fields)
        assert_error(r, 422, "not . or ..")
    r = app["client"].post("/v1/enrol", files={"scan": (".." + scan.suffix, scan.read_bytes())}, data={"subject": "s9"})
    assert r.status_code == 201 and r.json()["scan_id"] == "upload", r.text
    assert {e.subject for e in app["live"].entries}.isdisjoint({".", ".."})
    assert app["client"].delete("/v1/subjects/s9").status_code == 200


def test_a_repeated_form_field_is_refused_naming_it(app):
    """`-F subject=a -F subject=b` enrolled b (201), of two `scan` parts the second, and of two `claim`s the last was
    verified: the form parser keeps the last value unsaid. Now 422 naming the field, and nothing enrolled."""
    scan, other = probe_file(app["tmp"], 3, 1), probe_file(app["tmp"], 3, 2)
    part = lambda path, field="scan": (field, (path.name, path.read_bytes()))
    before = {e.id for e in app["live"].entries}
    for path, files, data, field in [
            ("/v1/enrol", [part(scan)], {"subject": ["s9", "s10"]}, "subject"),
            ("/v1/enrol", [part(scan), part(other)], {"subject": "s9"}, "scan"),
            ("/v1/enrol", [part(scan)], {"subject": "s9", "scan_id": ["a", "b"]}, "scan_id"),
            ("/v1/verify", [part(scan, "probe")], {"claim": ["s0", "s3"]}, "claim"),
            ("/v1/identify", [part(scan, "probe"), part(other, "probe")], {}, "probe"),
            ("/v1/identify", [part(scan, "probe")], {"k": ["1", "2"]}, "k"),
            ("/v1/calibrate", [part(scan), part(other)], {"subject": ["s3", "s3"], "fmr": ["0.1", "0.2"]}, "fmr")]:
        r = app["client"].post(path, files=files, data=data)
        assert_error(r, 422, f"form field {field!r} is given 2 times")
    assert {e.id for e in app["live"].entries} == before


def test_a_key_file_that_cannot_be_read_lets_no_key_in_and_says_why(app, caplog):
    """A keys.json hand-edited to remove key `lost`, with a JSON typo, kept the keys last read: `lost` still got 200
    and the log said nothing. Now no key works (503) until the file reads again, and the log says why, once."""
    keys = app["tmp"] / "keys.json"
    good = keys.read_text()
    lost = add_key(keys, "lost", "query")
    client, alice = app["client"], app["client"].headers["X-API-Key"]
    assert client.get("/v1/stats", headers={"X-API-Key": lost}).status_code == 200
    try:
        keys.write_text(good.rstrip().removesuffix("}"))  # `lost` removed, and the closing brace with it
        with caplog.at_level("WARNING", logger="facerec3d.server"):
            for key in (lost, alice, lost):
                assert_error(client.get("/v1/stats", headers={"X-API-Key": key}), 503, "API keys", "retry later")
        said = [r.getMessage() for r in caplog.records if "no key works" in r.getMessage()]
        assert len(said) == 1 and str(keys) in said[0] and "not a key file" in said[0], said
        keys.write_bytes(b"\xff" + good.encode())  # changed again, and not UTF-8: said again
        assert_error(client.get("/v1/stats", headers={"X-API-Key": alice}), 503, "API keys")
    finally:
        keys.write_text(good)
    assert client.get("/v1/stats", headers={"X-API-Key": alice}).status_code == 200
    assert_error(client.get("/v1/stats", headers={"X-API-Key": lost}), 401, "unknown API key")


def test_malformed_intrinsics_are_4xx_with_one_line(app, capfd):
    """Item 6: 100,000-deep JSON, a 5,000-digit integer, a 4,000-digit one (too large for a float)."""
    scan = probe_file(app["tmp"], 3, 1)
    for intrinsics, words in [("[" * 100_000 + "]" * 100_000, "longer than"),
                              ("[" * 2000 + "]" * 2000, "not usable JSON"),
                              ('{"fx": ' + "9" * 5000 + "}", "longer than"),
                              ('{"fx": ' + "9" * 4000 + ', "fy": 1, "cx": 1, "cy": 1}', "finite number"),
                              ('{"fx": 1e999, "fy": 1, "cx": 1, "cy": 1}', "finite number"),
                              ("[1, 2]", "JSON object")]:
        for path, field in (("/v1/identify", "probe"), ("/v1/enrol", "scan")):
            r = app["client"].post(path, files={field: ("f.png", scan.read_bytes())},
                                   data={"intrinsics": intrinsics, "subject": "s9"})
            assert_error(r, 422, words)
    assert "Traceback" not in capfd.readouterr().err


def test_a_store_failure_is_503_without_the_servers_path(app, monkeypatch, capfd):
    """Item 7 (its second half) and 12: a write the store refuses answers 503 naming no file, is logged whole
    and audited."""
    live = app["live"]

    def broken(*args, **kwargs):
        raise GalleryError(f"{live.path}: attempt to write a readonly database")

    monkeypatch.setattr(live._store, "add", broken)
    scan = probe_file(app["tmp"], 8, 1)
    r = app["client"].post("/v1/enrol", files={"scan": (scan.name, scan.read_bytes())}, data={"subject": "s8"})
    body = assert_error(r, 503, "gallery store")
    assert str(app["tmp"]) not in body["error"] and "g.sqlite" not in body["error"]
    assert f"{live.path}: attempt to write a readonly database" in capfd.readouterr().err
    refused = [a for a in audit_lines(app["gallery"]) if a["action"] == "refused"]
    assert refused[-1]["status"] == 503 and refused[-1]["key"] == "alice"
    assert "s8" not in {e.subject for e in live.entries}


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    """Valid uploads and the memory bombs of test_security, as (name, bytes)."""
    folder = tmp_path_factory.mktemp("fuzzseeds")
    out = [(p.name, p.read_bytes()) for p in [probe_file(folder, 1, 1)]]
    bombs = attack_files(folder / "bombs")
    out += [(name, (folder / "bombs" / name).read_bytes()) for name in bombs
            if (folder / "bombs" / name).stat().st_size < 2 * MiB]
    return out


def mutated(data: bytes, cuts) -> bytes:
    for where, what in cuts:
        i = int(where * len(data))
        data = data[:i] + what + data[i + len(what):]
    return data


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_fuzzed_uploads_are_answered_without_500_within_a_memory_bound(app, seeds, data):
    """Property: whatever the upload (valid, a memory bomb, mutated, any name) and form fields, every upload
    endpoint answers one-line JSON with a status that is not 5xx, and tracing memory meanwhile peaks under
    512 MiB."""
    name, content = data.draw(st.sampled_from(seeds))
    content = mutated(content, data.draw(st.lists(st.tuples(st.floats(0, 1), st.binary(min_size=1, max_size=16)),
                                                  max_size=3)))
    suffix = data.draw(st.sampled_from([Path(name).suffix, ".npy", ".npz", ".xyz", ".abs.gz", ".png", ".ply", ""]))
    path, field = data.draw(st.sampled_from([("/v1/identify", "probe"), ("/v1/verify", "probe"),
                                             ("/v1/enrol", "scan")]))
    form = {"subject": data.draw(st.text(max_size=20)), "claim": "s1", "k": data.draw(st.sampled_from(["1", "0", "x",
                                                                                                      "9" * 30]))}
    if data.draw(st.booleans()):
        form["intrinsics"] = data.draw(st.one_of(st.text(max_size=50), st.just('{"fx": 500, "fy": 500, "cx": 8, '
                                                                                 '"cy": 8}')))
    tracemalloc.start()
    try:
        r = app["client"].post(path, files={field: ("upload" + suffix, content)}, data=form)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert r.status_code < 500 and "\n" not in r.text.strip(), r.text
    assert isinstance(r.json()["error" if r.status_code >= 400 else "gallery_version"], (str, int))
    assert peak < 512 * MiB, f"{peak / MiB:.0f} MiB"
