"""Which method should be the default? Every candidate on every kind of data at once, not on one tuning half.

    python benchmarks/default_bench.py [--methods icp,region-icp,fusion]
        [--subjects 20] [--scans 4] [--real runs/real/real_bench.json] [--data bench-out/default] [--jobs 2]
        [--preprocess-config settings.toml]

Synthetic sets (FRGC layout, written once under --data, then reused), each `--subjects` x `--scans` (the first
scan neutral and frontal, then expressions and ±25° / free poses): one per sensor profile (`frgc`, `kinect-v2`,
`kinect-v2-8bit`, `realsense`) with the model's identities, and `frgc` and `kinect-v2` with faces outside the
model's span (wider identities, deformations, hair fringe, glasses, a hand). Each candidate is evaluated on each
set (`evaluate`, protocol frgc: first scan gallery, the rest probes) with one preprocessing cache.

Learnt methods (`needs_training`: the embedding adapted to the camera, `adapt = "wccn"`; pca, lda) are trained, per
set, on other people taken by the same sensor: a set of the same size and kind with subjects numbered from 1000
(seed 8), written beside it (`NAME-train-SxK`), as an integrator would adapt to a camera with a few volunteers.

Real data: `--real` names the `real_bench.json` of a `python benchmarks/real_bench.py --methods ...` run with the
same candidates (their labels must match); its held-out-half rank-1 over all probes joins the table. Without it
the real column is left out, and the table says so: a default chosen without real data is a guess.

Two tables: rank-1 over all probes (failures count as misses) and the EER, per set, with the mean and the worst
over the sets. `--preprocess-config` judges a preprocessing setting the same way, as `real_bench.py
--preprocess-config` does on the real frames (the cache keys each face by its settings, so both share --data).
No rule picks the default for you: the docs (docs/methods.md) say which was chosen and why.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from facerec3d.config import read_settings
from facerec3d.datasets.synthetic import DatasetConfig, identity_profile, sensor_profile, write_dataset
from facerec3d.evaluation.run import evaluate
from facerec3d.matching.registry import make_matcher
from facerec3d.preprocess.pipeline import PreprocessConfig

SETS = {  # name: (sensor profile, identities)
    "frgc": ("frgc", "model"), "frgc-outside": ("frgc", "outside-model"), "kinect-v2": ("kinect-v2", "model"),
    "kinect-v2-outside": ("kinect-v2", "outside-model"), "kinect-v2-8bit": ("kinect-v2-8bit", "model"),
    "realsense": ("realsense", "model"),
}


def set_config(name: str, subjects: int, scans: int, **fields) -> DatasetConfig:
    """The generator's settings of set `name` (its sensor and identities), `subjects` x `scans`."""
    sensor, identities = SETS[name]
    return DatasetConfig(subjects=subjects, scans=scans, scanner=sensor_profile(sensor),
                         identity=identity_profile(identities), **fields)


def training_set(data: Path, name: str, subjects: int, scans: int) -> Path:
    """The training set of learnt methods for set `name`: other people (subjects from 1000, seed 8) taken by the same
    sensor, with the same identities, `subjects` x `scans`; written once."""
    root = data / f"{name}-train-{subjects}x{scans}"
    if not (root / "manifest.csv").is_file():
        write_dataset(root, set_config(name, subjects, scans, first_subject=1000, seed=8), "abs", progress=False)
    return root


def method_specs(text: str) -> list[tuple[str, str, dict | None]]:
    """(label, method, options) of NAME or NAME=settings.toml items (label NAME:stem for a settings file)."""
    out = []
    for item in filter(None, text.split(",")):
        name, _, path = item.partition("=")
        out.append((f"{name}:{Path(path).stem}" if path else name, name, read_settings(path) if path else None))
    return out


def render(values: dict[str, dict[str, float]], columns: list[str], worst) -> list[str]:
    """A markdown table: one row per method, one column per set, then the mean and the worst (min or max)."""
    lines = ["| method | " + " | ".join(columns) + " | mean | worst |", "|---" * (len(columns) + 3) + "|"]
    for label, row in values.items():
        got = [row[c] for c in columns if c in row]
        cells = [f"{100 * row[c]:.1f}" if c in row else "–" for c in columns]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {100 * sum(got) / len(got):.1f} | {100 * worst(got):.1f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", default="icp,region-icp,fusion")
    ap.add_argument("--sets", default=",".join(SETS), help=f"of {', '.join(SETS)}")
    ap.add_argument("--subjects", type=int, default=20)
    ap.add_argument("--scans", type=int, default=4)
    ap.add_argument("--real", type=Path, help="real_bench.json of a real_bench run with the same methods")
    ap.add_argument("--data", type=Path, default=Path("bench-out/default"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--preprocess-config", type=Path, default=None,
                    help="preprocessing settings (TOML/JSON, any subset, as `facerec3d preprocess --config`), e.g. "
                         "[symmetry] mode = \"mirror\"; the run folders get the file's name")
    args = ap.parse_args(argv)
    if args.real is not None:  # read before the runs, not after them
        try:
            real_results = json.loads(args.real.read_text())["results"]["held-out"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            ap.error(f"--real {args.real}: not a real_bench.json ({type(e).__name__}: {str(e)[:120]})")
    config = PreprocessConfig.load(args.preprocess_config) if args.preprocess_config else PreprocessConfig()
    runs = "runs" if args.preprocess_config is None else f"runs-{args.preprocess_config.stem}"
    specs = method_specs(args.methods)
    table: dict[str, dict[str, float]] = {label: {} for label, _, _ in specs}
    eers: dict[str, dict[str, float]] = {label: {} for label, _, _ in specs}
    for name in filter(None, args.sets.split(",")):
        root = args.data / f"{name}-{args.subjects}x{args.scans}"
        if not (root / "manifest.csv").is_file():
            write_dataset(root, set_config(name, args.subjects, args.scans, seed=7), "abs", progress=False)
        for label, method, options in specs:
            train = training_set(args.data, name, args.subjects, args.scans) \
                if make_matcher(method, options).needs_training else None
            m = evaluate(root, method=method, options=options, out=args.data / runs / name / label.replace(":", "-"),
                         jobs=args.jobs, cache=args.data / "cache", config=config, progress=False, bootstrap=0,
                         train=train)
            table[label][name], eers[label][name] = m["rank1_all"], m["eer"]
            print(f"{name:18s} {label:28s} rank-1 all {100 * m['rank1_all']:5.1f} %  EER {100 * m['eer']:5.1f} %",
                  flush=True)
    if args.real:
        real = real_results
        for label in table:
            if label in real:
                table[label]["rap3df held-out"] = real[label]["rank1_all"]
                eers[label]["rap3df held-out"] = real[label]["eer"]
    columns = sorted({c for row in table.values() for c in row}, key=lambda c: (c != "rap3df held-out", c))
    print("\nNO REAL DATA: give --real (a default chosen without real data is a guess)" if not args.real else "")
    for title, values, worst in (("Rank-1 over all probes (%)", table, min), ("EER (%)", eers, max)):
        print(f"\n{title}\n" + "\n".join(render(values, columns, worst)))
    print(f"\nruns (each with its report.html) in {args.data / runs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
