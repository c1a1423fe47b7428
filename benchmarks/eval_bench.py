"""Evaluation benchmark (chapter §8.4): accuracy of ICP on the synthetic 60 × 5 protocol and the gain of --jobs 2.

    python benchmarks/eval_bench.py [--subjects 60] [--scans 5] [--out bench-out]

Scans per subject: a neutral gallery scan, then a neutral, an expression, a
±25° yaw and a second expression probe. Each run starts with an empty
preprocessing cache, so the 1- and 2-process runs do the same whole job and
their ratio is the end-to-end speed-up; both must give the same metrics.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

from facerec3d.datasets.synthetic import DatasetConfig, write_dataset
from facerec3d.evaluation.run import evaluate


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
    wall, results = {}, {}
    for jobs in (1, 2):
        shutil.rmtree(out / "cache", ignore_errors=True)
        t0 = time.perf_counter()
        m = evaluate(data, "icp", out / f"icp-jobs{jobs}", jobs=jobs, cache=out / "cache", progress=False)
        wall[jobs] = time.perf_counter() - t0
        results[jobs] = m
        t = m["timings"]
        print(f"jobs {jobs}: wall {wall[jobs]:.1f} s (preprocess {t['preprocess_s']:.1f} s, enrol {t['enrol_s']:.1f} s, "
              f"match {t['match_s']:.1f} s, {t['match_ms']:.2f} ms per comparison)")
    print(f"rank-1: all {m['rank1']:.2%}, neutral {m['subsets']['neutral']['rank1']:.2%}, "
          f"non-neutral {m['subsets']['non-neutral']['rank1']:.2%}; EER {m['eer']:.2%}; "
          f"VR@0.1% FAR {m['vr_at_far_0.001']:.2%}; failures {m['failures']}")
    keys = ("rank1", "rank5", "eer", "vr_at_far_0.001", "vr_at_far_0.01", "subsets")
    same = all(results[1][k] == results[2][k] for k in keys)
    print(f"--jobs 2 speed-up over --jobs 1: {wall[1] / wall[2]:.2f}x; identical metrics: {same}")


if __name__ == "__main__":
    main()
