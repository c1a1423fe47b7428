"""Service benchmark (issue 13): identification over HTTP against 1,000 enrolled faces, 1 / 4 / 16 concurrent
clients, exhaustive and cascade (depth screen, or the learned embedding's screen: `cascade-embedding`), raw scans and faces preprocessed at the edge, against the CLI's `identify` per
call, measured in the same run.

    python benchmarks/service_bench.py [--faces 1000] [--clients 1,4,16] [--requests 64] [--requests-preprocessed 48]
                                       [--jobs 2] [--cli-calls 2] [--uploads raw,preprocessed] [--json FILE]

What it does, exactly:
* Gallery: `--faces` distinct synthetic identities made directly in preprocessed form
  (`facerec3d.datasets.frontal`, ~18k points with the 95 mm crop each), enrolled with the ICP matcher (templates made on 2
  processes) and stored in a gallery store; cached under `--cache` (default: the temp folder) by size and preprocessing settings, so a
  rerun skips it (~0.2 core-s per face to make).
* Probes: 32 probe scans of enrolled identities (moved ≤ 3° / 3 mm, 0.3 mm depth noise) as .npz files
  (~150 KB). Two kinds of upload:
  - raw: the scan; the service reads and *preprocesses* it (the full §8.5 pipeline), prepares it and matches
    it: the latency is what an integrator sees, not matching alone;
  - preprocessed: the same scan preprocessed at the edge — in this process, one scan after another on one
    BLAS thread, before the service starts (so the two do not compete), with the gallery's settings (checked
    against the service's /v1/stats fingerprint once it runs) — and saved as the .npz `facerec3d preprocess`
    writes (~125 KB, recording the settings' fingerprint); the service checks the fingerprint, skips
    preprocessing, prepares and matches (every answer must say "preprocessed_upload": true). The edge's
    preprocessing time per scan is reported on its own (wall and CPU seconds): that work is moved to the
    client's cores, not removed.
* Service: `facerec3d serve --jobs J` as a child process on a loopback port (time to load the gallery
  reported). Warm-up (not timed, left out of every figure): 2 requests per worker for each mode and kind of
  upload, so every worker has loaded its compiled (Numba) code and the cascade's gallery descriptors exist
  before any figure is taken.
* Load: for each mode, kind of upload and client count C, C threads each with its own keep-alive HTTP
  connection send requests back to back, max(`--requests`, 2 C) in all (`--requests-preprocessed` for
  preprocessed uploads, which are cheaper, so their p95 / p99 rest on more requests); latency = client-side
  wall time per request (upload, queue, preprocessing, matching, answer); throughput = requests / wall time of
  the level; the CLI's figures (below) are the baseline of both kinds of upload. The
  service runs with a 900 s time limit, so no request is cut short under load. Also printed: the service's
  median stage times (preprocess, match) and its CPU seconds per request (service and workers, from its
  metrics) — on a shared machine wall times also measure the other load; CPU seconds much less so.
* CLI: `facerec3d identify PROBE --gallery G --jobs J [--cascade]` on a raw probe scan as a fresh process per
  call (a new cache folder each, so nothing is reused), `--cli-calls` calls per mode, after the service has
  stopped (its start-up — reading the gallery, loading compiled code — is part of every call: that is the
  cost the service removes); its
  throughput is one call at a time (each call already uses all J cores); its CPU seconds per call include
  its worker processes.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from facerec3d.gallery.engine import Engine
from facerec3d.gallery.store import GalleryStore
from facerec3d.datasets.frontal import frontal_face
from facerec3d.io import load_scan, save_scan
from facerec3d.matching.icp import ICPMatcher
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor

N_PROBES = 32


def _template(subject: int):
    t = ICPMatcher().enroll(frontal_face(subject))
    t.subject, t.scan_id = f"{subject:05d}", f"{subject:05d}-gallery"
    return t


def build_gallery(path: Path, faces: int, jobs: int) -> None:
    """A gallery store of `faces` synthetic identities (written to a temporary name, then renamed)."""
    tmp = path.with_suffix(".partial")
    for p in (tmp, Path(f"{tmp}-wal"), Path(f"{tmp}-shm")):
        p.unlink(missing_ok=True)
    t0 = time.perf_counter()
    with Engine.create(jobs) as engine, GalleryStore(tmp, create=True) as store:
        store.bind(PreprocessConfig(), ICPMatcher())
        for a in range(0, faces, 100):
            for t in engine.map(_template, range(a, min(faces, a + 100))):
                store.add(t, f"/synthetic/{t.subject}")
            print(f"  gallery: {min(faces, a + 100)}/{faces} faces ({time.perf_counter() - t0:.0f} s)", flush=True)
    os.replace(tmp, path)


def make_probes(folder: Path, faces: int) -> list[tuple[Path, str]]:
    """(probe file, true subject) for N_PROBES identities spread over the gallery."""
    out = []
    for i, s in enumerate(np.linspace(0, faces - 1, N_PROBES).astype(int)):
        path = folder / f"probe-{s:05d}.npz"
        if not path.exists():
            save_scan(frontal_face(int(s), pose_deg=3.0, shift_mm=3.0, noise_mm=0.3, seed=1000 + int(s)), path)
        out.append((path, f"{s:05d}"))
    return out


def preprocess_at_edge(probes: list, folder: Path, config: PreprocessConfig) -> tuple[list[tuple[Path, str]], dict]:
    """(preprocessed face file, true subject) for each probe, made here as an integrator's edge would (one scan
    after another, one BLAS thread), and the time it took per scan (wall and CPU seconds)."""
    from threadpoolctl import threadpool_limits

    out, wall, cpu = [], [], []
    pre = Preprocessor(config)
    with threadpool_limits(1):
        for path, truth in probes:
            target = folder / f"face-{path.stem}-{config.digest()}.npz"
            t0, c0 = time.perf_counter(), time.process_time()
            face = pre(load_scan(path))
            save_scan(face, target)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            out.append((target, truth))
    return out, {"scans": len(out), "wall_s_mean": float(np.mean(wall)), "wall_s_p50": float(np.median(wall)),
                 "core_s_mean": float(np.mean(cpu)), "bytes_mean": float(np.mean([p.stat().st_size for p, _ in out]))}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_service(gallery: Path, keys: Path, jobs: int, log: Path) -> tuple[subprocess.Popen, str, float]:
    import httpx

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "facerec3d.cli", "serve", "--gallery", str(gallery), "--keys",
                             str(keys), "--port", str(port), "--jobs", str(jobs), "--queue", "64", "--timeout", "900",
                             "--audit", str(log.with_suffix(".audit.jsonl"))],
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)
    while True:
        if proc.poll() is not None:
            raise SystemExit(f"the service exited: {log.read_text()}")
        try:
            if httpx.get(f"{url}/v1/health", timeout=2).status_code == 200:
                return proc, url, time.perf_counter() - t0
        except httpx.HTTPError:
            time.sleep(0.2)


def service_cpu(url: str, key: str) -> float:
    """CPU seconds used so far by the service and its workers (its metrics)."""
    import httpx

    text = httpx.get(f"{url}/metrics", headers={"X-API-Key": key}, timeout=60).text
    return float(next(line.split()[1] for line in text.splitlines() if line.startswith("facerec3d_cpu_seconds ")))


#: Modes: exhaustive ICP, or the cascade with the depth screen or the learned embedding's screen.
SCREENS = {"exhaustive": None, "cascade": "depth", "cascade-embedding": "embedding"}


def _form(mode: str) -> dict:
    screen = SCREENS[mode]
    return {"k": "5", "cascade": str(screen is not None).lower(), **({"screen": screen} if screen else {})}


def run_level(url: str, key: str, probes: list, clients: int, total: int, mode: str, preprocessed: bool) -> dict:
    """`total` identifications from `clients` threads (one connection each), back to back; every answer must say
    whether the service took the upload as a preprocessed face (`preprocessed`) or preprocessed it."""
    import httpx

    cpu0 = service_cpu(url, key)
    lock, nxt = threading.Lock(), [0]
    latencies, stages, correct, errors = [], [], [], []

    def client():
        with httpx.Client(base_url=url, headers={"X-API-Key": key}, timeout=600) as http:
            while True:
                with lock:
                    i = nxt[0]
                    nxt[0] += 1
                if i >= total:
                    return
                path, truth = probes[i % len(probes)]
                files = {"probe": (path.name, path.read_bytes())}
                t0 = time.perf_counter()
                r = http.post("/v1/identify", files=files, data=_form(mode))
                dt = time.perf_counter() - t0
                with lock:
                    if r.status_code != 200:
                        errors.append(f"{r.status_code} {r.text[:200]}")
                        continue
                    body = r.json()
                    if body.get("preprocessed_upload") is not preprocessed:
                        errors.append(f"preprocessed_upload is {body.get('preprocessed_upload')}")
                        continue
                    latencies.append(dt)
                    stages.append(body["timings"])
                    correct.append(body["candidates"][0]["subject"] == truth)

    threads = [threading.Thread(target=client) for _ in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    cpu = service_cpu(url, key) - cpu0
    lat = np.array(latencies)
    return {"clients": clients, "requests": len(lat), "errors": errors, "wall_s": wall,
            "core_s": cpu / max(1, len(lat)),
            "throughput": len(lat) / wall, "p50": float(np.percentile(lat, 50)), "p95": float(np.percentile(lat, 95)),
            "p99": float(np.percentile(lat, 99)), "rank1": float(np.mean(correct)),
            "preprocess_ms": float(np.median([s["preprocess_ms"] for s in stages])),
            "match_ms": float(np.median([s["match_ms"] for s in stages])),
            "match_p95_ms": float(np.percentile([s["match_ms"] for s in stages], 95))}


def cli_calls(gallery: Path, probes: list, calls: int, jobs: int, mode: str) -> tuple[list[float], float]:
    """Wall seconds of `calls` fresh `facerec3d identify` processes (a new, empty preprocessing cache each), and
    their CPU seconds per call (the process and its workers)."""
    import resource

    out = []
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu0 = ru.ru_utime + ru.ru_stime
    for i in range(calls):
        path, truth = probes[(7 * i + 3) % len(probes)]
        with tempfile.TemporaryDirectory() as cache:
            cmd = [sys.executable, "-m", "facerec3d.cli", "identify", str(path), "--gallery", str(gallery), "--jobs",
                   str(jobs), "-k", "5", "--cache", cache] + (["--cascade", "--screen", SCREENS[mode]]
                                                              if SCREENS[mode] else [])
            t0 = time.perf_counter()
            r = subprocess.run(cmd, capture_output=True, text=True)
            out.append(time.perf_counter() - t0)
        if r.returncode != 0 or r.stdout.splitlines()[1].split()[1] != truth:
            raise SystemExit(f"the CLI call went wrong: {r.stdout}{r.stderr}")
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return out, (ru.ru_utime + ru.ru_stime - cpu0) / calls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", type=int, default=1000)
    ap.add_argument("--clients", default="1,4,16")
    ap.add_argument("--requests", type=int, default=64, help="requests per level, raw uploads (at least 2 per "
                    "client; with 24, the default before 2026-12-06, the p95 was the second slowest request)")
    ap.add_argument("--requests-preprocessed", type=int, default=48,
                    help="requests per level, preprocessed uploads (at least 2 per client)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes of the service and of the CLI")
    ap.add_argument("--cli-calls", type=int, default=2, help="CLI identify calls per mode")
    ap.add_argument("--modes", default="cascade,cascade-embedding,exhaustive",
                    help=f"some of {', '.join(SCREENS)}")
    ap.add_argument("--uploads", default="raw,preprocessed")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "facerec3d-service-bench"))
    ap.add_argument("--json", help="write the figures to this file")
    args = ap.parse_args()
    clients = [int(c) for c in args.clients.split(",")]
    modes = [m.strip() for m in args.modes.split(",")]
    if unknown := set(modes) - set(SCREENS):
        raise SystemExit(f"unknown modes {sorted(unknown)}: use some of {', '.join(SCREENS)}")
    kinds = [u.strip() for u in args.uploads.split(",")]
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start", flush=True)

    config = PreprocessConfig()  # the gallery's settings (build_gallery binds the store to them)
    # keyed by size and preprocessing settings: a gallery bound to other settings would refuse today's faces
    gallery = cache / f"gallery-{args.faces}-{config.digest()}.sqlite"
    if not gallery.is_file():
        print(f"making the gallery of {args.faces} faces (cached in {gallery})", flush=True)
        build_gallery(gallery, args.faces, args.jobs)
    probes = {"raw": make_probes(cache, args.faces)}
    results: dict = {"faces": args.faces, "jobs": args.jobs, "cores": os.cpu_count(), "service": {}, "cli": {},
                     "load_average_start": os.getloadavg()[0]}
    if "preprocessed" in kinds:
        probes["preprocessed"], edge = preprocess_at_edge(probes["raw"], cache, config)
        results["edge"] = edge
        print(f"edge: {edge['scans']} probe scans preprocessed here, {edge['wall_s_mean']:.2f} s per scan "
              f"(median {edge['wall_s_p50']:.2f} s, {edge['core_s_mean']:.2f} core-s), faces of "
              f"{edge['bytes_mean'] / 1e3:.0f} KB", flush=True)

    from facerec3d.server.keys import add_key

    with tempfile.TemporaryDirectory() as tmp:
        key = add_key(Path(tmp) / "keys.json", "bench", "query,admin")
        proc, url, load_s = start_service(gallery, Path(tmp) / "keys.json", args.jobs, Path(tmp) / "service.log")
        results["service_start_s"] = load_s
        print(f"service: {args.faces} faces loaded into {args.jobs} workers, answering after {load_s:.1f} s", flush=True)
        try:
            import httpx

            st = httpx.get(f"{url}/v1/stats", headers={"X-API-Key": key}, timeout=60).json()
            if "preprocessed" in kinds and st["preprocess_fingerprint"] != config.digest():
                raise SystemExit(f"the service's preprocess_fingerprint {st['preprocess_fingerprint']} is not the "
                                 f"edge's {config.digest()}")
            for mode in modes:  # warm-up, not timed: every worker compiles / loads its code, descriptors made
                for kind in kinds:
                    run_level(url, key, probes[kind], args.jobs, 2 * args.jobs, mode, kind == "preprocessed")
            print(f"\n{'mode':>17} {'upload':>12} {'clients':>7} {'requests':>8} {'p50 s':>7} {'p95 s':>7} "
                  f"{'p99 s':>7} "
                  f"{'req/s':>7} {'core-s/req':>10} {'rank-1':>6}  service: preprocess / match (median ms); steady "
                  "state: after an untimed warm-up round per mode", flush=True)
            for mode in modes:
                for kind in kinds:
                    for c in clients:
                        n = args.requests_preprocessed if kind == "preprocessed" else args.requests
                        r = run_level(url, key, probes[kind], c, max(n, 2 * c), mode, kind == "preprocessed")
                        results["service"][f"{mode}/{kind}/{c}"] = r
                        print(f"{mode:>17} {kind:>12} {c:>7} {r['requests']:>8} {r['p50']:>7.3f} {r['p95']:>7.3f} "
                              f"{r['p99']:>7.3f} {r['throughput']:>7.2f} {r['core_s']:>10.2f} {r['rank1']:>6.2f}  "
                              f"{r['preprocess_ms']:.1f} / {r['match_ms']:.1f}"
                              + (f"  ERRORS {len(r['errors'])}: {r['errors'][:2]}" if r["errors"] else ""), flush=True)
            after = httpx.get(f"{url}/v1/stats", headers={"X-API-Key": key}, timeout=60).json()
            results["service_uploads"] = after["uploads"]
        finally:
            proc.terminate()
            proc.wait(60)

    print(f"\nCLI identify per call ({args.cli_calls} calls per mode, --jobs {args.jobs}, raw probe scans; each call "
          "a fresh process: its start, imports and workers are in the time, as a user's call pays them; Numba's "
          "on-disk cache warm):", flush=True)
    for mode in modes:
        times, core_s = cli_calls(gallery, probes["raw"], args.cli_calls, args.jobs, mode)
        results["cli"][mode] = {"calls_s": times, "mean_s": float(np.mean(times)),
                                "throughput": 1 / float(np.mean(times)), "core_s": core_s}
        print(f"{mode:>10}: {np.mean(times):.1f} s per call ({', '.join(f'{t:.1f}' for t in times)}), "
              f"{1 / np.mean(times):.3f} identifications/s, {core_s:.1f} core-s per call", flush=True)

    results["load_average_end"] = os.getloadavg()[0]
    print(f"\nservice ÷ CLI (same run, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the end):")
    for mode in modes:
        cli = results["cli"][mode]
        for kind in kinds:
            for c in clients:
                r = results["service"][f"{mode}/{kind}/{c}"]
                print(f"{mode:>10}, {kind:>12}, {c:>2} client{'s' if c > 1 else ' '}: throughput "
                      f"{r['throughput'] / cli['throughput']:6.1f}× the CLI's ({r['throughput']:.2f} vs "
                      f"{cli['throughput']:.3f} /s); p50 latency {cli['mean_s'] / r['p50']:6.1f}× shorter "
                      f"({r['p50']:.3f} s vs {cli['mean_s']:.1f} s); CPU per identification "
                      f"{cli['core_s'] / r['core_s']:.1f}× less ({r['core_s']:.2f} vs {cli['core_s']:.1f} core-s)")
    for mode in [m for m in modes if SCREENS[m] and 1 in clients]:
        for kind in kinds:
            r = results["service"][f"{mode}/{kind}/1"]
            cli = results["cli"][mode]
            ok = r["p95"] <= 0.100 and r["throughput"] >= 20 * cli["throughput"]
            print(f"\n{mode}, {kind} uploads, 1 client (rank-1 {r['rank1']:.3f}): p95 {r['p95'] * 1e3:.0f} ms end to end (target ≤ 100 ms), "
                  f"throughput {r['throughput'] / cli['throughput']:.1f}× the CLI's (target ≥ 20×): "
                  f"{'met' if ok else 'NOT met'}; the service spent a median {r['preprocess_ms']:.1f} ms "
                  f"preprocessing (or checking) the upload and {r['match_ms']:.1f} ms matching it "
                  f"(p95 {r['match_p95_ms']:.1f} ms)")
        if "edge" in results:
            print(f"(preprocessed uploads: plus {results['edge']['wall_s_mean']:.2f} s / "
                  f"{results['edge']['core_s_mean']:.2f} core-s per scan at the edge, before the request)")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
