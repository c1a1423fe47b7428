"""Issue 12: what a new user, a fuzzer and a damaged disk found — memory bombs, damaged stores and caches, settings,
exit codes, failure records, failures as misses, output names, demo data and concurrent enrolments."""

import csv
import dataclasses
import gzip
import json
import os
import pickle
import re
import shutil
import sqlite3
import subprocess
import sys
import zipfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from threadpoolctl import threadpool_limits

from facerec3d.cli import main
from facerec3d.config import read_settings
from facerec3d.datasets.catalog import DatasetError
from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
from facerec3d.errors import FailureToAcquire, InputError, ScanFormatError, SettingsError
from facerec3d.evaluation.metrics import summarize
from facerec3d.gallery.service import enroll_scans, scan_records
from facerec3d.gallery.store import AlreadyEnrolled, GalleryError, GalleryStore, encode_array
from facerec3d.io import load_scan, unique_stems
from facerec3d.matching.checks import check_template
from facerec3d.matching.icp import ICPMatcher
from facerec3d.matching.registry import make_matcher
from facerec3d.preprocess import PreprocessConfig
from facerec3d.preprocess import batch
from facerec3d.preprocess.batch import cache_key, code_stamp, preprocess_file, preprocess_files
from tests.conftest import cap_face

SMALL = ScannerConfig(rows=240, cols=320, focal_px=500.0)
GiB_KB = 1024 * 1024  # ru_maxrss is in KiB on Linux


@pytest.fixture(autouse=True)
def one_blas_thread():
    """One BLAS thread, as the batch paths' workers have (on a busy machine a thread per core is many times slower)."""
    with threadpool_limits(1):
        yield


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Three subjects × two small synthetic scans (manifest rows: gallery scan, probe scan, ...), a broken scan,
    and a preprocessing cache warmed with all of them."""
    root = tmp_path_factory.mktemp("data")
    write_dataset(root, DatasetConfig(subjects=3, scans=2, seed=5, scanner=SMALL, expressions=("smile",),
                                      expression_strength=(0.2, 0.2)), "abs")
    rows = [line.split(",") for line in (root / "manifest.csv").read_text().splitlines()[1:]]
    scans = [root / p for p, *_ in rows]
    (root / "broken.abs").write_text("not a range image\n")
    cache = root / "cache"
    list(preprocess_files(scans, jobs=2, cache=cache))
    return {"root": root, "scans": scans, "subjects": [s for _, s, *_ in rows], "cache": cache,
            "broken": root / "broken.abs"}


def enroll(args, data, store, *more):
    return CliRunner().invoke(main, ["enroll", *map(str, args), "--gallery", str(store), "--method", "icp", "--jobs", "1",
                                     "--cache", str(data["cache"]), *more])


# ---------------------------------------------------------------- 1. memory: stream, check, bound
#: Starts `python -m facerec3d.cli ARGS` from a small process and writes its peak resident memory (KiB, from
#: wait4) to the file named first. Measured from the test process itself, the peak would include the test
#: process's own memory: Linux counts the memory of the process that execs into the child's peak.
_MEASURE = ("import os, subprocess, sys; p = subprocess.Popen(sys.argv[2:]); _, s, u = os.wait4(p.pid, 0); "
            "open(sys.argv[1], 'w').write(str(u.ru_maxrss)); sys.exit(os.waitstatus_to_exitcode(s))")


def peak_rss_kb(tmp_path, *args) -> tuple[int, int, str, str]:
    """(peak resident memory in KiB, exit code, stdout, stderr) of `python -m facerec3d.cli ARGS` (the largest of
    the process and its children, from wait4, measured by a small launcher process)."""
    out, err, peak = tmp_path / "stdout.txt", tmp_path / "stderr.txt", tmp_path / "peak.txt"
    with open(out, "w") as fo, open(err, "w") as fe:
        code = subprocess.run([sys.executable, "-c", _MEASURE, str(peak), sys.executable, "-m", "facerec3d.cli",
                               *map(str, args)], stdout=fo, stderr=fe).returncode
    return int(peak.read_text()), code, out.read_text(), err.read_text()


def bombs(folder) -> dict[str, str]:
    """Small files (< 10 MB) whose headers claim huge sizes, with the reason each must be refused for."""
    folder.mkdir()
    # .abs.gz, 1 MB: a 2000 × 2000 header and a gigabyte of zero bytes (gzip members of 1 MiB each)
    member = gzip.compress(bytes(1 << 20), compresslevel=9, mtime=0)
    with open(folder / "zeros.abs.gz", "wb") as f:
        f.write(gzip.compress(b"2000 rows\n2000 columns\npixels (flag X Y Z):\n", mtime=0))
        f.write(member * 1000)
    # .abs.gz: a header beyond the largest scan accepted (2000 × 2000)
    (folder / "big.abs.gz").write_bytes(gzip.compress(b"2001 rows\n2000 columns\npixels (flag X Y Z):\n" + b"0 " * 99))
    # .npz: a 2100 × 2000 × 3 float64 member of zeros (101 MB unpacked), streamed into the zip
    with zipfile.ZipFile(folder / "zeros.npz", "w", zipfile.ZIP_DEFLATED) as z, \
            z.open("xyz.npy", "w", force_zip64=True) as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (2100, 2000, 3)})
        block = bytes(2000 * 3 * 8)
        for _ in range(2100):
            f.write(block)
    # a 2048 × 2049 16-bit depth frame of zeros
    from PIL import Image

    Image.fromarray(np.zeros((2048, 2049), np.uint16)).save(folder / "zeros.png")
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 500, "fy": 500, "cx": 1024, "cy": 1024}))
    # a point cloud 1 km wide: its grid of 0.7 mm cells would be 1.4 million cells square (enough points that a
    # face could be there, so it is the grid's size that is refused, not the point count)
    cluster = "".join(f"{i % 10} {i // 10} 5\n" for i in range(120))
    (folder / "far.ply").write_text("ply\nformat ascii 1.0\nelement vertex 121\nproperty float x\nproperty float y\n"
                                    "property float z\nend_header\n1000000 1000000 0\n" + cluster)
    for name in os.listdir(folder):
        assert (folder / name).stat().st_size < 10 << 20
    return {"zeros.abs.gz": "non-numeric", "big.abs.gz": "absurd size", "zeros.npz": "absurd size",
            "zeros.png": "absurd size", "far.ply": "spans"}


def test_no_small_file_makes_a_command_exceed_1_gib(tmp_path):
    expected = bombs(tmp_path / "bombs")
    files = [tmp_path / "bombs" / name for name in expected]
    # the largest scan accepted (2000 × 2000 pixels, all valid): read and preprocessed within the bound too
    biggest = tmp_path / "biggest.abs.gz"
    row = " ".join(f"{0.5 * c:g}" for c in range(2000)) + " "
    with gzip.open(biggest, "wb", compresslevel=1) as f:  # a plane, every pixel valid
        f.write(b"2000 rows\n2000 columns\npixels (flag X Y Z):\n" + b"1 " * 4_000_000 + b"\n")
        f.write((row * 2000).encode() + b"\n")
        f.write("".join(f"{0.5 * r:g} " * 2000 for r in range(2000)).encode() + b"\n")
        f.write(b"-1000 " * 4_000_000 + b"\n")
    assert biggest.stat().st_size < 10 << 20
    peak, code, out, err = peak_rss_kb(tmp_path, "info", *files, biggest)
    assert peak < GiB_KB, f"info: {peak / 1024:.0f} MiB"
    assert code == 2 and "Traceback" not in err and "2000x2000 grid, 4000000 valid points" in out, err
    for f, reason in zip(files[:-1], expected.values()):  # far.ply is a readable point cloud
        assert any(line.startswith(f"error: {f}: ") and reason in line for line in err.splitlines()), (f, err)
    peak, code, out, err = peak_rss_kb(tmp_path, "preprocess", *files, biggest, "-o", tmp_path / "out", "--jobs", "1")
    assert peak < GiB_KB, f"preprocess: {peak / 1024:.0f} MiB"
    assert code == 1 and "Traceback" not in err and f"0 kept, {len(files) + 1} failed" in out, err
    statuses = {r["scan"]: r["status"] for r in csv.DictReader(open(tmp_path / "out" / "landmarks.csv"))}
    assert all(reason in statuses[str(f)] for f, reason in zip(files, expected.values())), statuses
    peak, code, out, err = peak_rss_kb(tmp_path, "convert", biggest, tmp_path / "biggest.ply")  # the largest output
    assert peak < GiB_KB and code == 0, f"convert: {peak / 1024:.0f} MiB {err}"


def test_meshes_are_refused_before_a_library_reads_too_much(tmp_path, monkeypatch):
    """trimesh parses a whole OFF / STL at ~9× its size and plyfile allocates what a PLY header announces:
    a mesh file over MAX_MESH_BYTES, an OBJ of more than MAX_POINTS vertices, or a PLY header announcing more than
    MAX_POINTS vertices (more bytes' worth than the file holds or not), is one line naming the file; files within
    the limits read."""
    import facerec3d.io.mesh as mesh_io
    from facerec3d.errors import ScanFormatError
    from facerec3d.io import load_scan

    obj = tmp_path / "face.obj"
    obj.write_text("".join(f"v {i} {i % 7} {i % 5}\n" for i in range(60))
                   + "".join(f"f {i} {i + 1} {i + 2}\n" for i in range(1, 59)))
    assert load_scan(obj).n_points == 60
    monkeypatch.setattr(mesh_io, "MAX_MESH_BYTES", obj.stat().st_size - 1)
    with pytest.raises(ScanFormatError, match=r"face\.obj.*absurd size: more than \d+ bytes"):
        load_scan(obj)
    monkeypatch.setattr(mesh_io, "MAX_POINTS", 50)
    monkeypatch.setattr(mesh_io, "MAX_MESH_BYTES", obj.stat().st_size)
    with pytest.raises(ScanFormatError) as e:  # an OBJ's vertices counted as they are read
        load_scan(obj)
    assert str(e.value) == f"{obj}: absurd size: more than 50 points"
    head = "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\n" \
           "property float z\nend_header\n"
    ply = tmp_path / "cloud.ply"
    ply.write_bytes(head.format(51).encode() + bytes(51 * 12))
    with pytest.raises(ScanFormatError, match=r"cloud\.ply.*absurd size: 51 vertex elements \(more than 50\)"):
        load_scan(ply)
    ply.write_bytes(head.format(50).encode() + bytes(50 * 12))
    assert load_scan(ply).n_points == 50


def test_abs_body_is_streamed_and_checked_as_it_is_read(tmp_path):
    header = b"1000 rows\n1000 columns\npixels (flag X Y Z):\n"
    (tmp_path / "short.abs").write_bytes(header + b"1 0 1\n")
    (tmp_path / "long.abs").write_bytes(header + b"0 " * 4_000_001)
    (tmp_path / "garbage.abs.gz").write_bytes(gzip.compress(header + b"\xff" * (1 << 22)))
    for name, reason in (("short.abs", "expected 4000000 values for 1000×1000 pixels, found 3"),
                         ("long.abs", "expected 4000000 values for 1000×1000 pixels, found more"),
                         ("garbage.abs.gz", "non-numeric")):
        with pytest.raises(ScanFormatError, match=reason):
            load_scan(tmp_path / name)


# ---------------------------------------------------------------- 2. damaged templates
def small_store(path) -> GalleryStore:
    """A store of two ICP templates of sphere caps (no preprocessing needed)."""
    store = GalleryStore(path, create=True)
    matcher = ICPMatcher()
    store.bind(PreprocessConfig(), matcher)
    for i in range(2):
        t = matcher.enroll(cap_face(30, 40))
        t.subject, t.scan_id = f"s{i}", f"scan{i}"
        store.add(t, f"/data/{i}.abs")
    return store


def damage(path, entry: int, name: str, change, checksum: bool = False) -> None:
    """Change one stored array's bytes (with `checksum`, forge a matching checksum too)."""
    db = sqlite3.connect(path)
    dtype, shape, data = db.execute("SELECT dtype, shape, data FROM arrays WHERE entry = ? AND name = ?",
                                    (entry, name)).fetchone()
    a = np.frombuffer(bytearray(data), dtype=dtype).reshape(json.loads(shape))
    change(a)
    if checksum:
        db.execute("UPDATE arrays SET data = ?, checksum = ? WHERE entry = ? AND name = ?",
                   (a.tobytes(), encode_array(a)[3], entry, name))
    else:
        db.execute("UPDATE arrays SET data = ? WHERE entry = ? AND name = ?", (a.tobytes(), entry, name))
    db.commit()
    db.close()


def test_flipped_template_bytes_are_refused_naming_the_entry(tmp_path):
    path = tmp_path / "g.sqlite"
    small_store(path).close()

    def flip(a):
        a.view(np.uint8).reshape(-1)[5] ^= 0x10

    damage(path, 2, "points", flip)
    assert sqlite3.connect(path).execute("PRAGMA integrity_check").fetchone()[0] == "ok"  # SQLite cannot tell
    with GalleryStore(path) as store:
        assert len(store.templates(store.entries()[:1])) == 1  # the sound entry still reads
        with pytest.raises(GalleryError, match=r"entry 2 \(subject s1, scan scan1, /data/1.abs\) is damaged: "
                                               r"array 'points': checksum mismatch.*remove --entry 2\)"):
            store.templates()
    db = sqlite3.connect(path)  # a damaged subject (identity) is refused too
    db.execute("UPDATE entries SET subject = 's0' WHERE id = 2")
    db.commit()
    with GalleryStore(path) as store, pytest.raises(GalleryError, match="entry: checksum mismatch"):
        store.templates(store.entries()[1:])


@pytest.mark.parametrize("name, change, reason", [
    ("bucket_start", lambda a: a.__setitem__(-1, a[-1] + 1000), "'bucket_start' is not a run of offsets"),
    ("voxel_offset", lambda a: a.__setitem__(len(a) // 2, 10**9), "'voxel_offset' is not a run of offsets"),
    ("points", lambda a: a.__setitem__((0, 0), np.nan), "all finite"),
])
def test_forged_templates_are_checked_before_compiled_code(tmp_path, name, change, reason):
    path = tmp_path / "g.sqlite"
    small_store(path).close()
    damage(path, 1, name, change, checksum=True)  # a consistent checksum: only the structure check can tell
    with GalleryStore(path) as store, pytest.raises(GalleryError, match=f"entry 1 .* is damaged: template: .*{reason}"):
        store.templates()


def test_icp_template_check_by_hand():
    t = ICPMatcher().enroll(cap_face(30, 40))
    check_template(t)
    for name, value in (("normals", t.arrays["normals"][:-1]), ("colors", np.zeros((5, 3), np.uint8)),
                        ("voxel_index", t.arrays["voxel_index"].astype(np.int64)),
                        ("voxel_first", t.arrays["voxel_first"][:-1])):
        with pytest.raises(ValueError, match=name):
            check_template(type(t)(t.subject, t.scan_id, t.method, {**t.arrays, name: value}, t.attrs))
    with pytest.raises(ValueError, match="voxel grid size"):
        check_template(type(t)(t.subject, t.scan_id, t.method, t.arrays, {**t.attrs, "nx": "7"}))
    with pytest.raises(ValueError, match="no array 'points'"):
        check_template(type(t)(t.subject, t.scan_id, "region-icp", {}, t.attrs))


def test_cli_on_a_damaged_gallery_is_one_line_never_a_crash(data, tmp_path):
    store = tmp_path / "g.sqlite"
    r = enroll(data["scans"][::2], data, store)
    assert r.exit_code == 0, r.output
    damage(store, 1, "voxel_index", lambda a: a.view(np.uint8).__setitem__(7, a.view(np.uint8)[7] ^ 0xFF))
    probe, claim = data["scans"][1], data["subjects"][0]  # entry 1 is the claimed subject's
    for args in (["identify", probe, "--jobs", "1"], ["identify", probe, "--jobs", "2"],
                 ["verify", probe, "--claim", claim]):
        r = CliRunner().invoke(main, [*map(str, args), "--gallery", str(store), "--cache", str(data["cache"])])
        assert r.exit_code == 2, r.output
        assert "is damaged: array 'voxel_index': checksum mismatch" in r.output and "Traceback" not in r.output


def test_the_python_api_refuses_a_verification_without_a_claim_and_a_k_below_one(data, tmp_path):
    """verify_scan(store, probe, None) accepted anyone (the best score over the whole gallery was "the claim's"), and
    identify_scan(k=-1) dropped the last candidate: both are refused before any work."""
    from facerec3d.errors import InputError
    from facerec3d.gallery.service import identify_scan, verify_scan

    store = tmp_path / "g.sqlite"
    assert enroll(data["scans"][:2], data, store).exit_code == 0
    with GalleryStore(store) as st:
        for claim in (None, ""):
            with pytest.raises(GalleryError, match=r"a verification claims a subject \(a non-empty text\)"):
                verify_scan(st, data["scans"][2], claim, cache=data["cache"])
        for k in (0, -1):
            with pytest.raises(InputError, match="k must be a whole number of 1 or more"):
                identify_scan(st, data["scans"][2], k=k, cache=data["cache"])
        assert len(identify_scan(st, data["scans"][2], k=1, cache=data["cache"])) == 1


def test_damaged_method_settings_of_a_store_are_one_line_naming_it(data, tmp_path):
    """A store whose `options` or `state` is not a JSON table, or whose `method` is unknown, gave a JSONDecodeError
    traceback (stats, verify, identify) or an error not naming the store."""
    import shutil

    store = tmp_path / "g.sqlite"
    assert enroll(data["scans"][:2], data, store).exit_code == 0
    probe = str(data["scans"][2])
    for key, value, reason in (("options", "{bad", "damaged options setting (not JSON: "),
                               ("options", "[1]", "damaged options setting (a list, not a table)"),
                               ("state", "{bad", "damaged state setting (not JSON: "),
                               ("method", "{bad", "damaged method settings (unknown method '{bad'")):
        bad = tmp_path / f"{key}.sqlite"
        shutil.copy(store, bad)
        db = sqlite3.connect(bad)
        db.execute("UPDATE meta SET value = ? WHERE key = ?", (value, key))
        db.commit()
        db.close()
        for args in ([] if key != "options" else [["gallery", str(bad), "stats"]]) + [
                ["verify", probe, "--gallery", str(bad), "--claim", data["subjects"][0], "--threshold", "-3"],
                ["identify", probe, "--gallery", str(bad), "--jobs", "1"]]:
            r = CliRunner().invoke(main, [*args, "--cache", str(data["cache"])] if args[0] != "gallery" else args)
            assert r.exit_code == 2 and "Traceback" not in r.output, (key, args, r.output)
            assert r.output.startswith(f"error: {bad}: {reason}"), (key, args, r.output)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(["points", "normals", "voxel_index", "bucket_start", "voxel_offset"]),
       where=st.floats(0, 1), how=st.sampled_from(["flip", "truncate", "extend"]))
def test_fuzzed_store_rows_raise_gallery_error_only(tmp_path_factory, name, where, how):
    path = tmp_path_factory.mktemp("fuzz") / "g.sqlite"
    small_store(path).close()
    db = sqlite3.connect(path)
    (data,) = db.execute("SELECT data FROM arrays WHERE entry = 1 AND name = ?", (name,)).fetchone()
    data = bytearray(data)
    i = int(where * (len(data) - 1))
    data = {"flip": lambda: data[:i] + bytes([data[i] ^ 0x41]) + data[i + 1:], "truncate": lambda: data[:i],
            "extend": lambda: data + b"\x00" * (i + 1)}[how]()
    db.execute("UPDATE arrays SET data = ? WHERE entry = 1 AND name = ?", (bytes(data), name))
    db.commit()
    db.close()
    with GalleryStore(path) as store, pytest.raises(GalleryError, match="entry 1 .* is damaged"):
        store.templates()


# ---------------------------------------------------------------- 3. errors across processes; damaged cache
def _raise(error):
    raise error


@pytest.mark.parametrize("error", [
    ScanFormatError("a.abs", "truncated"), FailureToAcquire("no face", "b.abs"), SettingsError("c.toml", "x.y", "bad"),
    GalleryError("g: gone"), AlreadyEnrolled("d: twice"), DatasetError("e: empty"), InputError("f: wrong"),
])
def test_every_error_crosses_process_boundaries(error):
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is type(error) and str(back) == str(error) and back.__dict__ == error.__dict__
    with ProcessPoolExecutor(1) as pool:
        raised = pool.submit(_raise, error).exception()
    assert type(raised) is type(error) and str(raised) == str(error)


def test_a_damaged_cache_entry_is_recomputed(data, tmp_path):
    cache = shutil.copytree(data["cache"], tmp_path / "cache")
    scans = data["scans"][:2]
    first = list(preprocess_files(scans, jobs=1, cache=cache))
    entries = [cache / (cache_key(s, PreprocessConfig()) + ".npz") for s in scans]
    entries[0].write_bytes(entries[0].read_bytes()[:1000])  # truncated
    entries[1].write_bytes(b"PK\x03\x04" + os.urandom(300))  # garbled
    again = list(preprocess_files(scans, jobs=2, cache=cache))
    assert [o.face is not None and not o.cached for o in again] == [True, True]
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.face.points, b.face.points)
    assert all(o.cached for o in preprocess_files(scans, jobs=1, cache=cache))  # written again, whole
    # an emptied failure record is recomputed too
    fail = cache / (cache_key(data["broken"], PreprocessConfig()) + ".fail")
    assert preprocess_file(data["broken"], cache=cache).error and fail.read_text()
    fail.write_text("")
    assert preprocess_file(data["broken"], cache=cache).error == preprocess_file(data["broken"]).error
    # and the CLI commands that read the cache go on
    entries[0].write_bytes(entries[0].read_bytes()[:1000])
    r = enroll(scans, data | {"cache": cache}, tmp_path / "g.sqlite", "--jobs", "2")
    assert r.exit_code == 0 and "2 enrolled" in r.output, r.output


def test_a_cache_entry_that_is_a_folder_is_recomputed(data, tmp_path, monkeypatch):
    """A folder under an entry's name stopped the whole run ("...tmp.npz: is a directory", naming a temporary file,
    from the rename of the new entry onto it): it is damaged like any other entry, removed and computed again; one
    that cannot be removed leaves that scan uncached, and the run goes on."""
    cache = shutil.copytree(data["cache"], tmp_path / "cache")
    scans = data["scans"][:2]
    entries = [cache / (cache_key(s, PreprocessConfig()) + ".npz") for s in scans]
    for entry in entries:
        entry.unlink()
        entry.mkdir()
        (entry / "inside").write_text("x")
    again = list(preprocess_files(scans, jobs=1, cache=cache))
    assert [o.face is not None and not o.cached for o in again] == [True, True]
    assert all(e.is_file() for e in entries) and all(o.cached for o in preprocess_files(scans, jobs=1, cache=cache))
    fail = cache / (cache_key(data["broken"], PreprocessConfig()) + ".fail")
    fail.mkdir()  # a failure's entry
    assert preprocess_file(data["broken"], cache=cache).error and fail.is_file()
    entries[0].unlink()
    entries[0].mkdir()
    (entries[0] / "inside").write_text("x")
    monkeypatch.setattr(batch.shutil, "rmtree", lambda *a, **k: None)  # a folder that cannot be removed
    outcome = preprocess_file(scans[0], cache=cache)
    assert outcome.face is not None and not outcome.cached and entries[0].is_dir()
    assert [p.name for p in cache.iterdir() if ".tmp." in p.name] == []  # no temporary file left either


def test_only_a_scan_s_own_failures_are_cached(data, tmp_path, monkeypatch):
    """A MemoryError (a run short of memory) was cached as the scan's failure: every later run, with memory to spare,
    failed the scan from the cache. Only SCAN_FAILURES (an unreadable file, no face) are kept; any other error is
    that run's, reported and not kept."""
    from facerec3d.errors import FaceRec3DError
    from facerec3d.io.common import library_errors

    cache, scan = tmp_path / "cache", data["scans"][0]
    entry = cache / cache_key(scan, PreprocessConfig())

    def short_of_memory(self, scan):
        raise MemoryError("Unable to allocate 7.03 MiB")

    monkeypatch.setattr(batch.Preprocessor, "__call__", short_of_memory)
    outcome = preprocess_file(scan, cache=cache)
    assert outcome.error == "internal error (MemoryError: Unable to allocate 7.03 MiB); please report it"
    assert not outcome.cached and not entry.with_suffix(".fail").exists()
    monkeypatch.setattr(batch.Preprocessor, "__call__", lambda self, scan: (_ for _ in ()).throw(
        FaceRec3DError("m.onnx: the nose proposer cannot be read (Permission denied)")))
    assert preprocess_file(scan, cache=cache).error == "m.onnx: the nose proposer cannot be read (Permission denied)"
    assert not entry.with_suffix(".fail").exists()
    monkeypatch.undo()
    again = preprocess_file(scan, cache=cache)  # with memory to spare: the face, then cached
    assert again.face is not None and not again.cached and preprocess_file(scan, cache=cache).cached
    # a scan's own failure is cached, as a record naming its kind
    broken = cache / cache_key(data["broken"], PreprocessConfig())
    first = preprocess_file(data["broken"], cache=cache)
    assert json.loads(broken.with_suffix(".fail").read_text()) == {"failure": "ScanFormatError",
                                                                   "reason": first.error}
    again = preprocess_file(data["broken"], cache=cache)
    assert (again.error, again.cached) == (first.error, True)
    # memory running out inside a file's parser is no ScanFormatError (which would be cached) either
    with pytest.raises(MemoryError), library_errors("x.ply", "PLY file"):
        raise MemoryError


@pytest.mark.parametrize("text", ["garbage", "", '{"failure": "MemoryError", "reason": "internal error"}',
                                  '{"reason": "no face"}', '{"failure": "FailureToAcquire", "reason": 5}', "[" * 5000])
def test_a_damaged_failure_entry_is_recomputed(data, tmp_path, text):
    """A `.fail` entry holding `garbage` gave `garbage` as the scan's reason: one that is not a record
    `_write_cache` writes is damaged, removed and computed again, as a damaged face is."""
    cache = tmp_path / "cache"
    fail = cache / (cache_key(data["broken"], PreprocessConfig()) + ".fail")
    record = (preprocess_file(data["broken"], cache=cache), fail.read_text())
    fail.write_text(text)
    outcome = preprocess_file(data["broken"], cache=cache)
    assert not outcome.cached and outcome.error == record[0].error and fail.read_text() == record[1]


def test_faces_cached_by_another_version_of_the_code_are_made_again(data, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    scan = data["scans"][0]
    first = preprocess_file(scan, cache=cache)
    assert first.face is not None and preprocess_file(scan, cache=cache).cached
    monkeypatch.setattr(batch, "code_stamp", lambda: "another version")
    again = preprocess_file(scan, cache=cache)
    assert again.face is not None and not again.cached  # made again, not the old version's face
    np.testing.assert_array_equal(again.face.points, first.face.points)
    assert preprocess_file(scan, cache=cache).cached


def test_the_code_stamp_follows_the_preprocessing_code_only(tmp_path):
    package = Path(batch.__file__).resolve().parent.parent
    copy = tmp_path / "facerec3d"
    for pattern in (*batch.CODE, "matching/*.py"):
        for f in package.glob(pattern):
            (copy / f.relative_to(package)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(f, copy / f.relative_to(package))
    assert code_stamp(copy) == code_stamp(package)
    stamp = lambda: code_stamp.__wrapped__(copy)  # not the per-process cache
    (copy / "matching" / "icp.py").write_text("# a matcher changed: the same faces\n")
    assert stamp() == code_stamp(package)
    for changed in ("preprocess/holes.py", "io/abs.py", "scan.py", "facemodel/data/ict_facekit.npz"):
        before = (copy / changed).read_bytes()
        (copy / changed).write_bytes(before + b"\n")
        assert stamp() != code_stamp(package), changed
        (copy / changed).write_bytes(before)
    assert stamp() == code_stamp(package)


def test_cache_entries_are_written_atomically(data, tmp_path, monkeypatch):
    import facerec3d.io

    cache, scan = tmp_path / "cache", data["scans"][0]
    real = facerec3d.io.save_scan

    def killed_while_writing(face, path):
        with open(path, "wb") as f:
            f.write(b"PK\x03\x04 half a file")
        raise KeyboardInterrupt  # the process dies mid-write

    monkeypatch.setattr(facerec3d.io, "save_scan", killed_while_writing)
    with pytest.raises(KeyboardInterrupt):
        preprocess_file(scan, cache=cache)
    assert os.listdir(cache) == []  # no partial entry, no temporary file
    monkeypatch.setattr(facerec3d.io, "save_scan", real)
    assert preprocess_file(scan, cache=cache).face is not None
    assert [p.suffix for p in cache.iterdir()] == [".npz"] and preprocess_file(scan, cache=cache).cached


# ---------------------------------------------------------------- 4. settings
@pytest.mark.parametrize("text, where", [
    ('[resample]\nresolution_mm = 0\n', "resample.resolution_mm: must be > 0, not 0"),
    ('[detect]\ncrop_radius_mm = 70\n', "detect.crop_radius_mm: unknown setting"),
    ('[detect]\nmin_seen = 1.5\n', "detect.min_seen: must be in [0, 1], not 1.5"),
    ('[detect]\nmax_roll_deg = 0\n', "detect.max_roll_deg: must be > 0, not 0"),  # a divisor (head_penalty)
    ('[detect]\nscreen_iterations = 4\nscreened = 0\n', "detect.screened: must be > 0, not 0"),  # IndexError on every scan
    ('[spikes]\nwindow = 2.5\n', "spikes.window: must be an integer, not 2.5"),
    ('gridify_mm = "0.7"\n', "gridify_mm: must be a number, not '0.7'"),
    ('[denoise]\nmethod = "blur"\n', "denoise: unknown denoising method 'blur'"),
    ('[detect.model]\nexpression_modes = 1\n', "detect.model.expression_modes: must be true or false, not 1"),
    ('[detect.model]\nlookup_mm = 1.5\n', "detect.model: lookup_mm must be 0, or >= 1 mm for a rigid fit"),
    ('[detect.coarse]\nlookup_mm = 1.5\nidentity_modes = 10\n', "detect.coarse: lookup_mm must be 0, or >= 1 mm for a rigid fit"),
    ('[detect.coarse]\nlookup_mm = 0.01\n', "detect.coarse: lookup_mm must be 0, or >= 1 mm for a rigid fit"),  # 10¹⁰ cells
    ('crop_radius_mm = nan\n', "crop_radius_mm: must be a finite number"),
    ('crop_radius_mm = 120\n', "crop_radius_mm 120 is wider than the resampling grid (resample.half_width_mm 95)"),
    ('[detect]\nring_mm = [20]\n', "detect.ring_mm: must be a list of 2"),
    ('resample = 3\n', "resample: must be a table of ResampleConfig settings"),
    ('crop_radius_mm = \n', "not valid TOML"),
    ("crop_radius_mm = " + "1" * 5000 + "\n", "not usable TOML: a number of thousands of digits"),
    ("a = " + "[" * 100_000 + "]" * 100_000 + "\n", "not usable TOML: lists or tables nested thousands deep"),
])
def test_preprocessing_settings_are_checked_field_by_field(tmp_path, text, where):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SettingsError) as e:
        PreprocessConfig.load(path)
    assert str(e.value).startswith(f"{path}: {where}") and "\n" not in str(e.value)


GRID_OVER = "on {} cells a side, more than the 2000 × 2000 of the largest scan facerec3d reads: use larger cells"


@pytest.mark.parametrize("text, where", [
    ('[resample]\nresolution_mm = 1e-9\n', "resample.resolution_mm: 1e-09 mm cells lay the grid, 2 × half_width_mm = "
                                            "190 mm, " + GRID_OVER.format("1.9e+11")),
    ('[resample]\nhalf_width_mm = 5000\nresolution_mm = 0.1\n', "resample.resolution_mm: 0.1 mm cells lay the grid, "
                                                                "2 × half_width_mm = 10000 mm, " + GRID_OVER.format(100001)),
    ('crop_radius_mm = 100\n[resample]\nhalf_width_mm = 100\nresolution_mm = 0.1\n',
     "resample.resolution_mm: 0.1 mm cells lay the grid, 2 × half_width_mm = 200 mm, " + GRID_OVER.format(2001)),
    ('gridify_mm = 1e-9\n', "gridify_mm: 1e-09 mm cells lay a face, 2 × crop_radius_mm = 190 mm, " + GRID_OVER.format("1.9e+11")),
    ('gridify_mm = 0.05\n', "gridify_mm: 0.05 mm cells lay a face, 2 × crop_radius_mm = 190 mm, " + GRID_OVER.format(3801)),
    ('[detect]\nsample_mm = 1e-9\n', "detect.sample_mm: 1e-09 mm cells lay a head down to its nose, crown_mm[1] = 190 mm, "
                                      + GRID_OVER.format("1.9e+11")),
])
def test_a_grid_too_large_to_allocate_is_refused_with_the_settings(tmp_path, text, where):
    """Settings that passed the check made every scan fail: a 1e-9 mm resampling cell "internal error (ValueError:
    array is too big)", a 10 m grid at 0.1 mm a MemoryError, a 1e-9 mm detection sample a MemoryError (1.4 TiB), a
    1e-9 mm gridify cell a failure to acquire. A cell size that lays its span on a grid wider than the largest scan
    facerec3d reads (2000 × 2000) is refused, naming the file and `section.field`."""
    path = tmp_path / "grid.toml"
    path.write_text(text)
    with pytest.raises(SettingsError) as e:
        PreprocessConfig.load(path)
    assert str(e.value) == f"{path}: {where}"


def test_the_finest_usable_grids_are_accepted_and_the_cli_refuses_a_finer_one_before_any_work(data, tmp_path):
    from facerec3d.preprocess.resample import ResampleConfig

    assert ResampleConfig(resolution_mm=0.1).size == 1901  # 0.1 mm over the default 95 mm: finer than any scanner
    assert PreprocessConfig(gridify_mm=0.1).gridify_mm == 0.1
    with pytest.raises(SettingsError, match=r"^resolution_mm: 0\.09 mm cells lay the grid"):
        ResampleConfig(resolution_mm=0.09)  # built in Python: the same check
    (tmp_path / "tiny.toml").write_text("[resample]\nresolution_mm = 1e-9\n")
    for command in (["preprocess", str(data["scans"][0]), "-o", str(tmp_path / "p")],
                    ["evaluate", str(data["root"]), "--method", "icp", "--out", str(tmp_path / "p"), "--jobs", "1"]):
        r = CliRunner().invoke(main, [*command, "--config", str(tmp_path / "tiny.toml"), "--cache", str(tmp_path / "c")]
                               if command[0] == "evaluate" else [*command, "--config", str(tmp_path / "tiny.toml")])
        assert r.exit_code == 2 and r.output == (f"error: {tmp_path / 'tiny.toml'}: resample.resolution_mm: 1e-09 mm "
                                                 "cells lay the grid, 2 × half_width_mm = 190 mm, "
                                                 + GRID_OVER.format("1.9e+11") + "\n"), r.output
        assert not (tmp_path / "p").exists() and not (tmp_path / "c").exists()


def test_settings_built_in_python_are_range_checked_as_files_are():
    """PreprocessConfig(crop_radius_mm=-5) made faces of no points (a file's value was refused); a dict or a path
    given to Preprocessor failed deep inside with an AttributeError."""
    from facerec3d.errors import InputError
    from facerec3d.preprocess import Preprocessor
    from facerec3d.preprocess.detect import DetectConfig

    for build, said in ((lambda: PreprocessConfig(crop_radius_mm=-5.0), "crop_radius_mm: must be > 0, not -5.0"),
                        (lambda: PreprocessConfig(crop_radius_mm=float("nan")), "crop_radius_mm: must be a finite"),
                        (lambda: PreprocessConfig(detect=DetectConfig(sample_mm=0.0)), "detect.sample_mm: must be > 0")):
        with pytest.raises(SettingsError) as e:
            build()
        assert str(e.value).startswith(said)
    assert PreprocessConfig(crop_radius_mm=80.0).crop_radius_mm == 80.0
    with pytest.raises(InputError, match="Preprocessor takes a PreprocessConfig .* not dict"):
        Preprocessor({"crop_radius_mm": 50})
    with pytest.raises(InputError, match=r"Preprocessor takes a FaceScan \(facerec3d.io.load_scan reads a file\), "
                                         r"not str"):
        Preprocessor()("scan.png")


def test_a_json_settings_file_of_absurd_numbers_or_depth_is_one_line(tmp_path):
    from facerec3d.config import read_settings

    for text, where in (('{"max_iterations": ' + "1" * 5000 + "}", "a number of thousands of digits"),
                        ("[" * 100_000 + "]" * 100_000, "lists or tables nested thousands deep")):
        (tmp_path / "bad.json").write_text(text)
        with pytest.raises(SettingsError) as e:
            read_settings(tmp_path / "bad.json")
        assert str(e.value) == f"{tmp_path / 'bad.json'}: not usable JSON: {where}"


def test_a_partial_table_changes_only_what_it_names(tmp_path):
    # the coarse fit's defaults differ from ModelFitConfig's: a file setting only its points keeps it rigid
    path = tmp_path / "coarse.toml"
    path.write_text("[detect.coarse]\nmax_points = 400\nlookup_mm = 2.0\n[detect.model]\niterations = 7\n")
    cfg = PreprocessConfig.load(path)
    default = PreprocessConfig().detect
    assert cfg.detect.coarse == dataclasses.replace(default.coarse, max_points=400, lookup_mm=2.0)
    assert cfg.detect.coarse.identity_modes == 0 and not cfg.detect.coarse.expression_modes
    assert cfg.detect.model == dataclasses.replace(default.model, iterations=7)
    assert cfg.detect.candidates == default.candidates


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[1] / "examples").glob("*.toml")), ids=lambda p: p.name)
def test_every_example_settings_file_loads(path):
    """The settings files the docs name: preprocess-*.toml as preprocessing, the others as the settings of the method
    their name starts with (the longest such name)."""
    if path.name.startswith("preprocess-"):
        assert PreprocessConfig.load(path) != PreprocessConfig()
        return
    from facerec3d.matching.registry import METHODS

    method = max((m for m in METHODS if path.stem.startswith(m)), key=len, default="region-icp")  # region-committee
    assert make_matcher(method, read_settings(path)) is not None


@pytest.mark.parametrize("method, options, where", [
    ("icp", {"fine_points": "800"}, "fine_points: must be an integer, not '800'"),
    ("icp", {"tolerance": "1e-4"}, "tolerance: must be a number, not '1e-4'"),
    ("icp", {"seed": 1.5}, "seed: must be an integer, not 1.5"),
    ("icp", {"drop_boundary": 1}, "drop_boundary: must be true or false"),
    ("icp", {"voxel_size": -2}, "voxel_size: must be > 0"),
    ("region-icp", {"icp": {"max_normal_angle": "45"}}, "icp.max_normal_angle: must be a number"),
    ("fusion", {"member_options": {"icp": {"seed": -1}}}, "member_options.icp.seed: must be >= 0, not -1"),
    ("fusion", {"members": ["icp", "nope"]}, "members: unknown method 'nope'"),
    ("curvature", {"min_overlap": 2}, "min_overlap: must be in [0, 1]"),
])
def test_method_settings_are_checked_and_name_the_file(tmp_path, method, options, where):
    path = tmp_path / "method.json"
    path.write_text(json.dumps(options))
    with pytest.raises(SettingsError) as e:
        make_matcher(method, read_settings(path))
    assert str(e.value).startswith(f"{path}: {where}"), str(e.value)
    assert make_matcher("icp", {"max_normal_angle": None, "fine_points": 800}).config.fine_points == 800


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(st.sampled_from(["crop_radius_mm", "spikes", "detect", "resample", "denoise", "x"]),
                       st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=4),
                                    lambda inner: st.lists(inner, max_size=3)
                                    | st.dictionaries(st.sampled_from(["window", "resolution_mm", "method",
                                                                       "ring_mm", "model", "size_mm"]), inner),
                                    max_leaves=6)))
def test_fuzzed_settings_raise_settings_error_only(table):
    try:
        PreprocessConfig.from_dict(table, "fuzz.json")
    except SettingsError as e:
        assert str(e).startswith("fuzz.json: ") and "\n" not in str(e)


def test_a_proposer_that_is_no_onnx_file_is_refused_before_anything_is_enrolled(data, tmp_path):
    """`[detect] proposer = "base.obj"` (a file, but no ONNX model) recorded every scan as a failure to enrol; as a
    missing file, it is one settings line, exit 2, and no gallery is made."""
    (tmp_path / "base.obj").write_text("v 0 0 0\n")
    settings = tmp_path / "prop.toml"
    settings.write_text('[detect]\nproposer = "base.obj"\n')
    r = enroll(data["scans"][:2], data, tmp_path / "gp.sqlite", "--config", settings)
    prefix = (f"error: {settings}: detect: proposer '{tmp_path / 'base.obj'}': not a usable ONNX nose proposer "
              "([ONNXRuntimeError] : 7 : INVALID_PROTOBUF : Load model from ")
    assert r.exit_code == 2 and r.output.startswith(prefix) and r.output.count("\n") == 1, r.output
    assert not (tmp_path / "gp.sqlite").exists()


def test_cli_settings_errors_are_one_line_and_bugs_are_not_disguised(data, tmp_path, monkeypatch):
    bad = tmp_path / "bad.toml"
    bad.write_text('fine_points = "800"\n')
    r = enroll(data["scans"][:1], data, tmp_path / "g.sqlite", "--method-config", bad)
    assert r.exit_code == 2 and r.output.strip().splitlines()[-1] == f"error: {bad}: fine_points: must be an " \
                                                                    "integer, not '800'", r.output
    cfg = tmp_path / "cfg.toml"
    cfg.write_text("[resample]\nresolution_mm = 0\n")
    r = CliRunner().invoke(main, ["preprocess", str(data["scans"][0]), "-o", str(tmp_path / "o"), "--config", str(cfg)])
    assert r.exit_code == 2 and f"{cfg}: resample.resolution_mm: must be > 0" in r.output and "Traceback" not in r.output
    # user errors that were ValueErrors are still one line
    xyz = tmp_path / "p.xyz"
    xyz.write_text("1 2 3\n4 5 6\n7 8 10\n")
    for args, reason in ((["convert", xyz, tmp_path / "p.abs"], "needs a scan with a grid"),
                         (["compare", tmp_path], "not a run folder"),
                         (["synth", tmp_path / "s", "--expressions", "grin"], "unknown expressions")):
        r = CliRunner().invoke(main, list(map(str, args)))
        assert r.exit_code == 2 and reason in r.output and isinstance(r.exception, SystemExit), r.output
    # a bug (an error that is not facerec3d's) shows itself, not as a user error
    import facerec3d.preprocess.batch

    monkeypatch.setattr(facerec3d.preprocess.batch, "preprocess_files", lambda *a, **k: 1 / 0)
    r = CliRunner().invoke(main, ["preprocess", str(data["scans"][0]), "-o", str(tmp_path / "o")])
    assert isinstance(r.exception, ZeroDivisionError) and r.exit_code == 1


def test_a_method_config_without_method_is_the_existing_gallerys_methods_settings(data, tmp_path, monkeypatch):
    """`enroll --method-config p2p.toml` without --method on an icp gallery read the file as the default method's
    (fusion's: "unknown FusionConfig settings: variant"), and `serve` ignored it: it is the gallery's own method's
    settings, refused as they differ from the stored options, as with --method icp."""
    store = tmp_path / "gi.sqlite"
    assert enroll(data["scans"][:1], data, store, "--no-calibrate").exit_code == 0
    p2p = tmp_path / "p2p.toml"
    p2p.write_text('variant = "point-to-plane"\n')
    common = ["--gallery", str(store), "--jobs", "1", "--cache", str(data["cache"]), "--method-config", str(p2p)]
    for more in ([], ["--method", "icp"]):
        r = CliRunner().invoke(main, ["enroll", str(data["scans"][2]), *common, *more])
        assert r.exit_code == 2 and "the gallery was enrolled with method 'icp' and other options" in r.output \
            and "FusionConfig" not in r.output \
            and "variant: 'point-to-point' in the gallery, 'point-to-plane' given" in r.output, r.output
    same = tmp_path / "p2p-same.toml"  # the stored settings themselves are taken
    same.write_text('variant = "point-to-point"\n')
    r = CliRunner().invoke(main, ["enroll", str(data["scans"][2]), *common[:-1], str(same), "--no-calibrate"])
    assert r.exit_code == 0 and "1 enrolled" in r.output, r.output
    import facerec3d.server.app

    def run(gallery, keys, host, port, jobs, scheduler, method, options, *rest, **kw):  # the service's own check
        with GalleryStore(gallery) as st:
            st.check_matcher(make_matcher(method, options))

    monkeypatch.setattr(facerec3d.server.app, "serve", run)
    r = CliRunner().invoke(main, ["serve", "--gallery", str(store), "--keys", str(tmp_path / "k.json"),
                                  "--method-config", str(p2p)])
    assert r.exit_code == 2 and "the gallery was enrolled with method 'icp' and other options" in r.output, r.output


# ---------------------------------------------------------------- 5. exit codes
def test_enroll_and_preprocess_fail_when_nothing_succeeded(data, tmp_path):
    bad2 = tmp_path / "broken2.abs"
    bad2.write_text("1 rows\n")
    r = enroll([data["broken"], bad2], data, tmp_path / "g.sqlite")
    assert r.exit_code == 1 and "0 enrolled, 0 already enrolled, 2 failed to enrol" in r.output, r.output
    r = enroll([data["broken"], data["scans"][0]], data, tmp_path / "g.sqlite")
    assert r.exit_code == 0 and "1 enrolled, 0 already enrolled, 1 failed to enrol" in r.output, r.output
    r = CliRunner().invoke(main, ["preprocess", str(data["broken"]), str(bad2), "-o", str(tmp_path / "o")])
    assert r.exit_code == 1 and "0 kept, 2 failed" in r.output


# ---------------------------------------------------------------- 6. failures per source, and current
def test_failures_to_enrol_are_per_source_and_current(data, tmp_path):
    store, bad = tmp_path / "g.sqlite", tmp_path / "later.abs.gz"
    bad.write_text("not yet\n")
    for _ in range(3):  # reruns
        enroll([data["broken"], bad, data["scans"][0]], data, store)
    with GalleryStore(store) as s:
        assert sorted(src for src, _ in s.failures()) == sorted([str(data["broken"].resolve()), str(bad.resolve())])
        assert s.stats()["failures_to_enrol"] == 2
    shutil.copy(data["scans"][2], bad)  # the file is fixed: it enrols, and its failure is no longer current
    r = enroll([data["broken"], bad], data, store)
    assert "1 enrolled, 0 already enrolled, 1 failed to enrol" in r.output, r.output
    with GalleryStore(store) as s:
        assert [src for src, _ in s.failures()] == [str(data["broken"].resolve())]
    listed = CliRunner().invoke(main, ["gallery", str(store), "list"]).output.splitlines()
    assert len(listed) == 3 and [line.split("\t")[0] for line in listed].count("failed") == 1


# ---------------------------------------------------------------- 7. failures to enrol as misses
def test_rank1_all_counts_probes_of_subjects_that_failed_to_enrol(data, tmp_path):
    S = np.array([[-1.0, -5.0], [-5.0, -1.0], [-3.0, -4.0], [-2.0, -3.0]])
    probes, gallery = ["a", "b", "c", "c"], ["a", "b"]
    assert summarize(S, probes, gallery)["rank1_all"] == 1.0  # c: not a mated search (open set)
    m = summarize(S, probes, gallery, unenrolled=["c"], bootstrap=20)  # c's gallery scan failed to enrol
    assert m["rank1"] == 1.0 and m["rank1_all"] == 0.5 and m["failures"] == 0 and m["fta_rate"] == 0.0
    assert summarize(S, probes, gallery, 1, unenrolled=["c"])["rank1_all"] == pytest.approx(2 / 5)
    # end to end: a manifest whose subject s3's gallery scan is broken
    manifest = tmp_path / "m.csv"
    rows = [(p, s, "gallery" if k % 2 == 0 else "probe") for k, (p, s) in enumerate(zip(data["scans"],
                                                                                        data["subjects"]))]
    rows[4] = (data["broken"], rows[4][1], "gallery")
    manifest.write_text("path,subject,role\n" + "".join(f"{p},{s},{r}\n" for p, s, r in rows))
    from facerec3d.evaluation.run import evaluate

    m = evaluate(manifest, "icp", tmp_path / "run", protocol="roles", jobs=1, cache=data["cache"], progress=False, bootstrap=0)
    assert m["failures_to_enrol"] == 1 and m["n_probes"] == 3 and m["failures"] == 0
    assert m["rank1"] == 1.0 and m["rank1_all"] == pytest.approx(2 / 3)



def test_all_vs_all_takes_a_person_with_one_scan_as_not_enrolled(data, tmp_path):
    """all-vs-all leaves a scan out of its own search, so the probe of a person with one scan has no mate: it was
    a rank-1 miss (rank 3, mated score -inf; rank-1 80 % though every probe with a mate ranked 1). It is a search
    of a person not enrolled, as in the other protocols: out of rank-1, still a non-mated search."""
    S = np.array([[np.nan, -1.0, -5.0], [-1.0, np.nan, -4.0], [-3.0, -4.0, np.nan]])
    m = summarize(S, ["a", "a", "b"], ["a", "a", "b"], mateless=[False, False, True])
    assert m["rank1"] == 1.0 and m["rank1_all"] == 1.0 and m["n_ranked"] == 2 and m["n_nonmated"] == 3
    from facerec3d.evaluation.run import evaluate

    manifest = tmp_path / "m.csv"
    kept = [k for k in range(6) if k != 3]  # the second subject keeps one scan
    manifest.write_text("path,subject\n" + "".join(f"{data['scans'][k]},{data['subjects'][k]}\n" for k in kept))
    m = evaluate(manifest, "icp", tmp_path / "run", protocol="all-vs-all", jobs=1, cache=data["cache"],
                 progress=False, bootstrap=0)
    assert m["n_probes"] == 5 and m["n_ranked"] == 4 and m["rank1"] == 1.0 and m["rank1_all"] == 1.0
    assert m["n_nonmated"] == 5
    alone = [row for row in csv.DictReader(open(tmp_path / "run" / "probes.csv"))
             if row["subject"] == data["subjects"][2]]
    assert len(alone) == 1 and alone[0]["rank"] == alone[0]["mated_score"] == "" and alone[0]["nonmated_score"]
    # the run's scores.txt (no line for a scan against itself) gives the same figures again
    r = CliRunner().invoke(main, ["metrics", str(tmp_path / "run" / "scores.txt"), "--out", str(tmp_path / "again"),
                                  "--bootstrap", "0"])
    assert r.exit_code == 0, r.output
    again = json.loads((tmp_path / "again" / "metrics.json").read_text())
    assert {k: again[k] for k in ("n_ranked", "rank1", "n_nonmated")} == {"n_ranked": 4, "rank1": 1.0, "n_nonmated": 5}


# ---------------------------------------------------------------- 8. unique output names
def test_preprocess_gives_every_input_its_own_output(data, tmp_path):
    assert unique_stems(["d1/face.ply", "d2/face.ply", "d1/face-2.ply", "d3/FACE.abs.gz"]) == \
        ["d1_face", "d2_face", "d1_face-2", "d3_FACE"]  # files of several folders: the folder (the person) named
    assert unique_stems(["d1/face.ply", "d1/face.abs", "d1/face-2.ply"]) == ["face", "face-3", "face-2"]
    (tmp_path / "d1").mkdir(), (tmp_path / "d2").mkdir()
    a, b = tmp_path / "d1" / "face.abs.gz", tmp_path / "d2" / "face.abs.gz"
    shutil.copy(data["scans"][0], a), shutil.copy(data["scans"][1], b)
    r = CliRunner().invoke(main, ["preprocess", str(a), str(b), "-o", str(tmp_path / "out"), "--jobs", "1"])
    assert r.exit_code == 0 and "2 kept, 0 failed" in r.output, r.output
    rows = {row["scan"]: row["output"] for row in csv.DictReader(open(tmp_path / "out" / "landmarks.csv"))}
    assert rows == {str(a): str(tmp_path / "out" / "d1_face.npz"), str(b): str(tmp_path / "out" / "d2_face.npz")}
    assert load_scan(rows[str(a)]).n_points != load_scan(rows[str(b)]).n_points  # two different faces


# ---------------------------------------------------------------- 9. demo --out with other sizes
def test_demo_makes_its_data_again_when_the_sizes_change(tmp_path, monkeypatch):
    import facerec3d.cli
    import facerec3d.evaluation.compare
    import facerec3d.evaluation.run

    evaluated = []
    monkeypatch.setattr(facerec3d.evaluation.run, "evaluate", lambda data, *a, **k: evaluated.append(data) or {})
    monkeypatch.setattr(facerec3d.evaluation.compare, "compare_runs", lambda *a, **k: None)
    monkeypatch.setattr(facerec3d.cli, "_print_metrics", lambda m: None)
    out = tmp_path / "demo"

    def demo(subjects, scans):
        r = CliRunner().invoke(main, ["demo", "--subjects", str(subjects), "--scans", str(scans), "--methods", "icp",
                                      "--out", str(out), "--jobs", "1"])
        assert r.exit_code == 0, r.output
        return r.output, (out / "data" / "manifest.csv").read_text().count("\n") - 1

    output, n = demo(2, 2)
    assert "synthesising data: 2 subjects x 2 scans" in output and n == 4
    output, n = demo(2, 2)
    assert "synthesising" not in output and n == 4  # same settings: reused
    output, n = demo(3, 2)
    assert "made with other settings: synthesising it again" in output and n == 6
    (out / "data" / "demo-dataset.json").unlink()  # data demo cannot vouch for: refused, not reused
    r = CliRunner().invoke(main, ["demo", "--subjects", "3", "--scans", "2", "--methods", "icp", "--out", str(out)])
    assert r.exit_code == 2 and "did not record making" in r.output and "remove it or choose another --out" in r.output


# ---------------------------------------------------------------- 10. concurrent and duplicate enrolments
def test_a_copied_scan_is_a_duplicate(data, tmp_path):
    store, copy = tmp_path / "g.sqlite", tmp_path / "elsewhere" / "copy.abs.gz"
    copy.parent.mkdir()
    shutil.copy(data["scans"][0], copy)
    assert "1 enrolled" in enroll([data["scans"][0]], data, store).output
    r = enroll([copy], data, store)
    assert r.exit_code == 0 and "0 enrolled, 1 already enrolled, 0 failed" in r.output and ": 1 entries" in r.output


def test_an_enrolment_racing_another_skips_what_the_other_enrolled(data, tmp_path):
    records = scan_records(data["scans"][:4:2])
    matcher = ICPMatcher()
    with GalleryStore(tmp_path / "g.sqlite", create=True) as store:
        assert enroll_scans(store, records[:1], matcher, cache=data["cache"]).enrolled == 1  # the other run
        store.sources = lambda: set()  # this run listed the store before the other enrolled its first scan
        report = enroll_scans(store, records, matcher, cache=data["cache"])
        assert (report.enrolled, len(report.skipped), report.failures) == (1, 1, [])
        assert len(store.entries()) == 2
        twin = matcher.enroll(cap_face())
        twin.subject = records[0].subject
        with pytest.raises(AlreadyEnrolled, match="already enrolled"):
            store.add(twin, str(records[0].path.resolve()))


def test_two_enrolments_at_once_enrol_everything_once(data, tmp_path):
    store = tmp_path / "g.sqlite"
    args = [sys.executable, "-m", "facerec3d.cli", "enroll", *map(str, data["scans"]), "--gallery", str(store),
            "--jobs", "1", "--cache", str(data["cache"])]
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outputs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outputs
    counts = [tuple(map(int, re.search(r"(\d+) enrolled, (\d+) already enrolled, 0 failed", out).groups()))
              for out, _ in outputs]
    assert sum(c[0] for c in counts) == 6 and all(sum(c) == 6 for c in counts), outputs
    with GalleryStore(store) as s:
        assert len(s.entries()) == 6 and s.failures() == []


def test_a_cached_kernel_is_compiled_again_when_a_kernel_it_calls_changes_in_another_module(tmp_path):
    """Numba keys a cached kernel on its own module only; `jit.guard_kernel_caches` makes it stale when any module
    of the package that defines kernels changes (a `git pull` that touched `geometry/ball.py` alone)."""
    package = tmp_path / "kpkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from numba import njit\nfrom kpkg.b import g\n\n\n@njit(cache=True)\n"
                                  "def f(x):\n    return g(x) + 1.0\n")
    callee = "from numba import njit\n\n\n@njit(cache=True)\ndef g(x):\n    return x * {}\n"
    script = ("import sys\nfrom pathlib import Path\nsys.path.insert(0, sys.argv[1])\n"
              "from facerec3d.jit import guard_kernel_caches\n"
              "assert guard_kernel_caches(Path(sys.argv[1]) / 'kpkg')\n"
              "from kpkg.a import f\nprint(f(2.0))\n")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}  # the kernels' own __pycache__
    run = lambda: subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True,
                                 env=env, check=True).stdout.split()[-1]
    (package / "b.py").write_text(callee.format("10.0"))
    assert run() == "21.0"
    assert run() == "21.0"  # from the cache
    assert list((package / "__pycache__").glob("a.f-*.nbi"))
    (package / "b.py").write_text(callee.format("100.0"))  # a.py untouched
    assert run() == "201.0"


def test_a_damaged_compiled_kernel_cache_is_said_in_one_line_and_compiled_again(tmp_path):
    """Numba stops with a traceback from `pickle` on a truncated cache file of a kernel; facerec3d's kernels are
    compiled again instead, with one line naming the cache, and a cache that cannot be written is said, not
    raised."""
    script = ("import numpy as np\nfrom facerec3d.geometry.ball import within_ball\n"
              "print(int(within_ball(np.arange(12.0).reshape(4, 3), np.zeros(3), 8.0).sum()))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = lambda: subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)
    first = run()
    assert first.returncode == 0 and first.stdout.split() == ["2"], first.stderr
    files = list((tmp_path / "numba").rglob("ball._within-*.nb[ic]"))
    assert {f.suffix for f in files} == {".nbi", ".nbc"}
    for f in files:  # truncated, as a full disk or a killed copy leaves them
        f.write_bytes(f.read_bytes()[:20])
    damaged = run()
    assert damaged.returncode == 0 and damaged.stdout.split() == ["2"], damaged.stderr
    lines = damaged.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in damaged.stderr, damaged.stderr
    assert "compiled-kernel cache" in lines[0] and "ball._within-" in lines[0] and "unreadable" in lines[0]
    again = run()  # the cache was written anew
    assert again.returncode == 0 and again.stdout.split() == ["2"] and again.stderr == ""
    index = next((tmp_path / "numba").rglob("ball._within-*.nbi"))
    index.unlink()
    index.mkdir()  # neither readable nor writable as a file
    blocked = run()
    assert blocked.returncode == 0 and blocked.stdout.split() == ["2"], blocked.stderr
    assert "Traceback" not in blocked.stderr and "unreadable" in blocked.stderr and "not saved" in blocked.stderr
