"""Every matching method on the same synthetic protocol, side by side (chapter §8.6–8.10).

    python benchmarks/methods_bench.py [--subjects 60] [--scans 5] [--data bench-out/data] [--out bench-out/methods]
        [--methods icp,pca,...,fusion=examples/fusion-icp-region.toml] [--jobs 2]
        [--identities model|outside-model|outside-model-unoccluded]

Three synthetic datasets (FRGC layout, made once under --data, then reused):
`testN` (mixed expressions at 0.6–1.0 strength), `strongN` (the same
subjects with open mouth, smile or surprise at full strength) and `trainN`
(disjoint subjects, numbered from 1000, for the learnt methods: PCA, LDA
and anything else whose `needs_training` is set). `--identities outside-model`
makes all three from faces outside the morphable model's span (wider identity
spread, smooth deformations, occluders: `datasets.synthetic.IDENTITY_PROFILES`),
named with an `-outside` suffix; `outside-model-unoccluded` the same faces without
the occluders (`-unoccluded`). Each method is evaluated
on the test and the strong set; one `compare` report per set holds every
method's metrics and timings. The table printed at the end gives rank-1
(neutral / non-neutral probes), EER and the time of one probe–gallery
comparison by the matcher alone (prepared probe against enrolled templates,
one core), also as a ratio against ICP (the peer) measured in the same run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from facerec3d.config import read_settings
from facerec3d.datasets.catalog import open_dataset
from facerec3d.datasets.synthetic import IDENTITY_PROFILES, DatasetConfig, identity_profile, write_dataset
from facerec3d.datasets.protocols import split
from facerec3d.evaluation.compare import compare_runs
from facerec3d.evaluation.run import evaluate
from facerec3d.matching.registry import make_matcher, trained_matcher
from facerec3d.preprocess import PreprocessConfig
from facerec3d.preprocess.batch import DEFAULT_CACHE, preprocess_files

DEFAULT_METHODS = ("icp,pca,lda,curvature,region-icp,region-icp=examples/region-committee.toml,keypoints,"
                   "fusion=examples/fusion-icp-region.toml")


def datasets(root: Path, subjects: int, scans: int, identities: str = "model") -> dict[str, Path]:
    """The test, strong-expression and training sets (written when missing) of model or outside-model faces."""
    who = identity_profile(identities)
    suffix = {"model": "", "outside-model": "-outside", "outside-model-unoccluded": "-unoccluded"}[identities]
    configs = {
        f"test{subjects}{suffix}": DatasetConfig(subjects=subjects, scans=scans, identity=who),
        f"strong{subjects}{suffix}": DatasetConfig(subjects=subjects, scans=scans, identity=who,
                                                   expressions=("open-mouth", "smile", "surprise"),
                                                   expression_strength=(1.0, 1.0)),
        f"train{subjects}{suffix}": DatasetConfig(subjects=subjects, scans=scans, first_subject=1000, seed=1,
                                                  identity=who),
    }
    for name, cfg in configs.items():
        if (root / name / "manifest.csv").is_file():  # reused: made with these sizes?
            rows = len((root / name / "manifest.csv").read_text(encoding="utf-8").splitlines()) - 1
            if rows != subjects * scans:
                raise SystemExit(f"methods_bench: {root / name} holds {rows} scans, not {subjects} x {scans}: "
                                 "remove it or give another --data")
        else:
            t0 = time.perf_counter()
            write_dataset(root / name, cfg, "abs", progress=True)
            print(f"synthesised {name} in {time.perf_counter() - t0:.0f} s")
    return {name: root / name for name in configs}


def comparison_cost(method: str, options: dict | None, model: Path | None, data: Path, cache: str,
                    n_probes: int = 8) -> float:
    """Microseconds per probe–gallery comparison of the matcher alone: `scores` of n prepared probes against
    the whole enrolled gallery of `data`, in this process with one BLAS thread (no engine, no preparation)."""
    matcher, _ = trained_matcher(method, options, model=model if model and model.is_file() else None, progress=False)
    dataset = open_dataset(data)
    sp = split(dataset)
    paths = [dataset.records[i].path for i in list(sp.gallery) + list(sp.probes[:n_probes])]
    faces = [o.face for o in preprocess_files(paths, PreprocessConfig(), cache=cache) if o.face is not None]
    gallery = [matcher.enroll(f) for f in faces[:len(sp.gallery)]]
    probes = [matcher.prepare(f) for f in faces[len(sp.gallery):]]
    with threadpool_limits(1):
        matcher.scores(probes[0], gallery)  # warm up (compiled code, caches)
        t0 = time.perf_counter()
        for p in probes:
            matcher.scores(p, gallery)
        return 1e6 * (time.perf_counter() - t0) / (len(probes) * len(gallery))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=int, default=60)
    ap.add_argument("--scans", type=int, default=5)
    ap.add_argument("--data", default="bench-out/data", help="Folder of the synthetic datasets.")
    ap.add_argument("--out", default="bench-out/methods")
    ap.add_argument("--methods", default=DEFAULT_METHODS, help="Comma-separated; NAME=CONFIG.toml gives settings.")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cache", default=str(DEFAULT_CACHE))
    ap.add_argument("--identities", default="model", choices=list(IDENTITY_PROFILES),
                    help="Faces in the morphable model's span, or outside it, with or without occluders "
                         "(IDENTITY_PROFILES).")
    args = ap.parse_args()
    sets = datasets(Path(args.data), args.subjects, args.scans, args.identities)
    test, strong, train = sets.values()
    out = Path(args.out)
    rows, runs = [], {test: [], strong: []}
    for spec in args.methods.split(","):
        method, _, config = spec.partition("=")
        options = read_settings(config) if config else None
        learnt = make_matcher(method, options).needs_training
        label = Path(config).stem if config else method
        for data in (test, strong):
            t0 = time.perf_counter()
            m = evaluate(data, method, out / f"{label}-{data.name}", jobs=args.jobs, cache=args.cache, progress=False,
                         options=options, train=train if learnt else None)
            s, t = m["subsets"], m["timings"]
            run = out / f"{label}-{data.name}"
            runs[data].append(run)
            us = comparison_cost(method, options, run / "model.npz", data, args.cache)
            rows.append((label, data.name, s["neutral"]["rank1"], s.get("non-neutral", {}).get("rank1", float("nan")),
                         m["eer"], us, t["prepare_ms"], t["enrol_ms"], time.perf_counter() - t0))  # (nan: 2 scans
            #   a person leave no expression probe)
            print(f"{label} on {data.name}: rank-1 neutral {rows[-1][2]:.2%}, non-neutral {rows[-1][3]:.2%}, "
                  f"{us:.1f} us per comparison; done in {rows[-1][-1]:.0f} s", flush=True)
    for data, dirs in runs.items():
        compare_runs(dirs, out / f"compare-{data.name}")
    icp_us = {r[1]: r[5] for r in rows if r[0] == "icp"}
    print("\nrank-1 of neutral / non-neutral probes; EER over all; us/cmp: one probe-gallery comparison of the "
          "matcher alone (one core); vs ICP: how many times faster than ICP's; prepare: per probe (features, "
          "normals), in the evaluation; wall: the whole evaluation")
    print(f"\n{'method':<22}{'data':<10}{'neutral':>9}{'non-neut':>9}{'EER':>8}{'us/cmp':>10}{'vs ICP':>9}"
          f"{'prepare ms':>11}{'enrol ms':>10}{'wall s':>8}")
    for label, name, neutral, other, eer, us, prepare, enrol, wall in rows:
        ratio = f"{icp_us[name] / us:.1f}x" if name in icp_us and us > 0 else "-"
        print(f"{label:<22}{name:<10}{neutral:>9.2%}{other:>9.2%}{eer:>8.2%}{us:>10.1f}{ratio:>9}{prepare:>11.1f}"
              f"{enrol:>10.1f}{wall:>8.0f}")
    print(f"\nreports: {', '.join(str(out / f'compare-{d.name}' / 'compare.html') for d in (test, strong))}")


if __name__ == "__main__":
    main()
