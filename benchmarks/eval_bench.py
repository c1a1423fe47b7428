"""Evaluation benchmark (chapter §8.4): the whole run of ICP on the synthetic 60 × 5 protocol, on 1 and 2 local
processes and on a 2-worker local Dask cluster, side by side.

    python benchmarks/eval_bench.py [--subjects 60] [--scans 5] [--out bench-out]

Scans per subject: a neutral gallery scan, then a neutral, an expression, a
±25° yaw and a second expression probe. Each run starts with an empty
preprocessing cache, so every set-up does the same whole job (reading and
preprocessing every scan, enrolment, matching) on its one engine; the Dask
run (`evaluate(..., scheduler=client)`, as `--scheduler`) preprocesses on the
cluster's workers too. The cluster is started before its run (its start is
printed apart), as a `--scheduler` run finds it running. All set-ups must
give the same metrics.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from facerec3d.datasets.synthetic import DatasetConfig, write_dataset
from facerec3d.evaluation.run import evaluate

KEYS = ("rank1", "rank5", "eer", "vr_at_far_0.001", "vr_at_far_0.01", "subsets")


def run(data: Path, out: Path, label: str, **engine) -> tuple[float, dict]:
    """(wall seconds, metrics) of one evaluation with an empty cache."""
    shutil.rmtree(out / "cache", ignore_errors=True)
    t0 = time.perf_counter()
    m = evaluate(data, "icp", out / f"icp-{label}", cache=out / "cache", progress=False, **engine)
    return time.perf_counter() - t0, m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=60)
    ap.add_argument("--scans", type=int, default=5)
    ap.add_argument("--out", default="bench-out")
    args = ap.parse_args()
    out = Path(args.out)
    data = out / f"data-{args.subjects}x{args.scans}"
    if not (data / "manifest.csv").is_file():
        t0 = time.perf_counter()
        write_dataset(data, DatasetConfig(subjects=args.subjects, scans=args.scans, seed=1), "abs", progress=True)
        print(f"synthesised {args.subjects * args.scans} scans in {time.perf_counter() - t0:.0f} s")
    t0 = time.perf_counter()  # Numba's kernels compiled (or their on-disk cache loaded) once, before any timing
    warm = out / "data-warm-up"
    if not (warm / "manifest.csv").is_file():
        write_dataset(warm, DatasetConfig(subjects=2, scans=2, seed=2), "abs", progress=False)
    run(warm, out, "warm-up", jobs=1)
    print(f"warm-up run (JIT compilation or its cache, not in the figures below): {time.perf_counter() - t0:.1f} s")
    results = {}
    for jobs in (1, 2):
        results[f"{jobs} process{'es' * (jobs > 1)}"] = run(data, out, f"jobs{jobs}", jobs=jobs)
    try:
        import distributed
    except ImportError:
        print("dask.distributed not installed (pip install 'facerec3d[distributed]'): no Dask run")
    else:
        t0 = time.perf_counter()
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as cluster, distributed.Client(cluster) as client:
            start = time.perf_counter() - t0
            results["Dask, 2 workers"] = run(data, out, "dask2", scheduler=client)
        print(f"(the local Dask cluster took {start:.1f} s to start, not counted below)")

    base = next(iter(results.values()))
    print(f"\n{'set-up':18s} {'wall s':>7s} {'speed-up':>8s} {'preprocess s':>12s} {'ms/scan':>8s} {'enrol s':>8s} "
          f"{'match s':>8s} {'ms/comparison':>13s} {'same metrics':>12s}")
    for label, (wall, m) in results.items():
        t = m["timings"]
        same = all(json.dumps(m[k], sort_keys=True) == json.dumps(base[1][k], sort_keys=True) for k in KEYS)
        print(f"{label:18s} {wall:7.1f} {base[0] / wall:7.2f}x {t['preprocess_s']:12.1f} "
              f"{t['preprocess_computed_ms']:8.0f} {t['enrol_s']:8.1f} {t['match_s']:8.1f} {t['match_ms']:13.2f} "
              f"{str(same):>12s}")
    m = base[1]
    subsets = "".join(f", {name} {m['subsets'][name]['rank1']:.2%}" for name in ("neutral", "non-neutral")
                      if name in m.get("subsets", {}))  # (2 scans a person: no expression probe)
    print(f"\nrank-1: all {m['rank1']:.2%}{subsets}; EER {m['eer']:.2%}; "
          f"VR@0.1% FAR {m['vr_at_far_0.001']:.2%}; failures {m['failures']}")
    print(f"(steady state: every set-up ran after the warm-up; each starts with an empty preprocessing cache; "
          f"runs in {out})")


if __name__ == "__main__":
    main()
