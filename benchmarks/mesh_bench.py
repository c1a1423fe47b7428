"""Meshes and point clouds of any density, in any frame, against the same faces as range images.

    python benchmarks/mesh_bench.py [--subjects 20] [--spacings 1,2,3,4] [--sensor frgc] [--out runs/mesh]

Each synthetic subject has a gallery scan (neutral) and a probe scan (another session, turned ±12°). Every scan
is exported as an OBJ mesh and as a PLY point cloud with about 1, 2, 3 and 4 mm between vertices (every k-th
row and column of its range image; a stereo scanner's meshes have ~3.8 mm), each in its own random frame
(uniform random rotation, ~500 mm translation), and read back with `load_scan`. For each format the benchmark
reports failures to acquire, the nose-tip error against the generator's ground truth (in the file's frame, via
`landmarks_in_input_frame`), rank-1 of whole-face ICP with the gallery and probes in that format, and the time
per scan, beside the same faces as range images (the reference row), and names the scans it missed. Needs no data.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one BLAS thread, as the CLI's workers have: with a thread per core and another
    #                                   process on the 2 cores, a 2 mm mesh took ~5 s instead of ~1.5 s (2026-12-06)

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from facerec3d.datasets.synthetic import (FaceScanner, ScanSpec, export_surface, random_frame,  # noqa: E402
                                          sensor_profile)
from facerec3d.errors import FailureToAcquire  # noqa: E402
from facerec3d.io import load_scan, save_scan  # noqa: E402
from facerec3d.matching.registry import make_matcher  # noqa: E402
from facerec3d.preprocess import Preprocessor, landmarks_in_input_frame  # noqa: E402


def run_format(syns, spacing: float | None, mesh: bool, folder: Path) -> dict:
    """FTA, nose errors, ICP rank-1 and seconds per scan of the scans in one format (spacing None: range images)."""
    pre, icp = Preprocessor(), make_matcher("icp")
    faces, errors, fails, seconds, missed = [], [], 0, [], []
    for k, syn in enumerate(syns):
        scan, R, t = syn.scan, np.eye(3), np.zeros(3)
        if spacing is not None:
            seed = int(spacing * 1000) + 2 * k + mesh
            R, t = random_frame(seed)
            path = folder / f"{k}.{'obj' if mesh else 'ply'}"
            save_scan(export_surface(scan, spacing, mesh=mesh, rotation=R, translation=t), path)
            scan = load_scan(path)
        t0 = time.perf_counter()
        try:
            face = pre(scan)
        except FailureToAcquire:
            fails, face = fails + 1, None
            missed.append(k)
        seconds.append(time.perf_counter() - t0)
        faces.append(face)
        if face is not None:
            errors.append(float(np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"]
                                               - (R @ syn.landmarks["nose_tip"] + t))))
            if errors[-1] > 10.0:
                missed.append(k)
    n = len(syns) // 2
    templates = [None if f is None else icp.enroll(f) for f in faces[:n]]
    enrolled = [j for j, tpl in enumerate(templates) if tpl is not None]
    hits = 0
    for s, face in enumerate(faces[n:]):
        if face is not None and enrolled:
            scores = icp.scores(icp.prepare(face), [templates[j] for j in enrolled])[0]
            hits += enrolled[int(np.argmax(scores))] == s
    e = np.array(errors) if errors else np.array([np.nan])
    return {"fta": fails / len(syns), "nose_median_mm": float(np.median(e)), "nose_within_10mm": float(np.mean(e <= 10.0)),
            "nose_max_mm": float(np.max(e)), "rank1": hits / n, "s_per_scan": float(np.median(seconds)),
            "missed": missed}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subjects", type=int, default=20)
    ap.add_argument("--spacings", default="1,2,3,4", help="mm between vertices, comma separated")
    ap.add_argument("--sensor", default="frgc", help="synthetic sensor profile of the range images exported")
    ap.add_argument("--out", type=Path, default=Path("runs/mesh"))
    args = ap.parse_args(argv)
    scanner = FaceScanner(sensor_profile(args.sensor))
    syns = ([scanner.scan(ScanSpec(s, seed=100 + s)) for s in range(args.subjects)]
            + [scanner.scan(ScanSpec(s, yaw=12.0 if s % 2 else -12.0, seed=200 + s)) for s in range(args.subjects)])
    Preprocessor()(syns[0].scan)  # Numba compilation, outside the times
    rows = {"range image": run_format(syns, None, False, Path("."))}
    with tempfile.TemporaryDirectory() as tmp:
        for mesh in (True, False):  # the mesh and point-cloud kernels too, outside the times
            warm = Path(tmp) / f"warm.{'obj' if mesh else 'ply'}"
            save_scan(export_surface(syns[0].scan, float(args.spacings.split(",")[0]), mesh=mesh), warm)
            Preprocessor()(load_scan(warm))
        for spacing in map(float, args.spacings.split(",")):
            for mesh in (True, False):
                name = f"{'OBJ mesh' if mesh else 'PLY points'} {spacing:g} mm"
                rows[name] = run_format(syns, spacing, mesh, Path(tmp))
                print(f"{name}: {rows[name]}", flush=True)
    ref = rows["range image"]["rank1"]
    lines = [f"# Meshes and point clouds in random frames ({args.subjects} subjects x 2 scans, sensor {args.sensor})", "",
             "| format | FTA | nose median | nose ≤ 10 mm | nose max | ICP rank-1 | Δ rank-1 vs range image | s per scan |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['fta']:.1%} | {r['nose_median_mm']:.2f} mm | {r['nose_within_10mm']:.1%} | "
                     f"{r['nose_max_mm']:.1f} mm | {r['rank1']:.1%} | {100 * (r['rank1'] - ref):+.1f} points | "
                     f"{r['s_per_scan']:.2f} |")
    lines += ["", "s per scan: the median preprocessing time of the format's scans, steady state (the kernels "
              "compiled on one range image, one mesh and one point cloud before any timing)"]
    missed = [f"{name}: scans {r['missed']}" for name, r in rows.items() if r["missed"]]
    lines += ["", "Scans not found or with the nose more than 10 mm off (k: subject k, or k - subjects' probe; "
              "its frame is seeded 1000 × spacing + 2k + 1 for a mesh, + 0 for points): "
              + ("; ".join(missed) if missed else "none")]
    print("\n".join(lines))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mesh_bench.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    (args.out / "mesh_bench.json").write_text(json.dumps(rows, indent=1), encoding="utf-8")
    print(f"wrote {args.out / 'mesh_bench.md'} and {args.out / 'mesh_bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
