"""Preprocessing benchmark (chapter §8.5): accuracy against ground truth and time per scan.

    python benchmarks/preprocess_bench.py [--scans 60] [--subjects N] [--sensor frgc|kinect-v2|kinect-v2-8bit|realsense]
                                          [--identities model|outside-model] [--against 6c9c085] [--real DIR]
                                          [--preprocess-config settings.toml]

`--sensor` picks the synthetic scanner's sensor profile (default frgc: 480×640
laser scans); `--identities outside-model` gives faces outside the morphable
model's span (wider identity spread, smooth deformations, occluders), which is
what real users bring.

Synthetic scans with yaw ±30°, pitch ±20°, roll ±10°, expressions, spikes,
holes, neck and torso in view. Prints nose-tip error (median, 99th
percentile), residual rotation to the true frontal pose, spike removal rates,
and the median time per scan with each stage's share (one process, one core).

`--against REF` (default 6c9c085, the release before the speed work; `--against ''` skips it) then times the same
scans, written as `.abs.gz` range scans, with this tree and with that release in the same run
(`benchmarks/release.py`: each in a child process, one core, after a warm-up scan): reading, preprocessing and
enrolling (ICP's template), median ms and the speed-up. `--real DIR` adds `--real-frames` depth frames of a
rap3df-2019-style folder (manifest.csv + intrinsics.json; `../shared/data/rap3df-2019` where it is present; the
bench says so and goes on without them when it is not).

`--preprocess-config FILE` judges a preprocessing setting: the accuracy figures above are those of the settings in
FILE, and the same scans (and --real frames) are then preprocessed with those settings and with the defaults,
alternately, in this process, one core, after a warm-up of both: median ms of each and the speed-up (the release
comparison then times the defaults, which is what the release knows).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from facerec3d.datasets.synthetic import (  # noqa: E402
    EXPRESSIONS, SENSOR_PROFILES, FaceScanner, ScanSpec, identity_profile, sensor_profile)
from facerec3d.geometry.transforms import rotation_angle  # noqa: E402
from facerec3d.preprocess import (  # noqa: E402
    PreprocessConfig, Preprocessor, landmarks_in_input_frame, spike_mask)
from facerec3d.preprocess.sampling import measure_sampling  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import release  # noqa: E402
from release import RELEASE  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=60)
    ap.add_argument("--subjects", type=int, default=None,
                    help="scan i shows subject i mod SUBJECTS (default: every scan its own subject)")
    ap.add_argument("--sensor", default="frgc", choices=sorted(SENSOR_PROFILES))
    ap.add_argument("--identities", default="model", choices=["model", "outside-model"])
    ap.add_argument("--against", default=RELEASE, help="a release (git commit) timed on the same scans; '' for none")
    ap.add_argument("--real", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/rap3df-2019",
                    help="a folder of real depth frames (manifest.csv, intrinsics.json) also timed against the release")
    ap.add_argument("--real-frames", type=int, default=40, help="frames of --real timed (evenly spread)")
    ap.add_argument("--preprocess-config", type=Path, default=None,
                    help="settings judged: accuracy with them, and their time against the defaults on the same scans")
    args = ap.parse_args()
    config = PreprocessConfig.load(args.preprocess_config) if args.preprocess_config else PreprocessConfig()
    rng = np.random.default_rng(11)
    identity = identity_profile(args.identities)
    scanner = FaceScanner(sensor_profile(args.sensor), seed=3, identity=identity)
    Preprocessor(config)(scanner.scan(ScanSpec(0)).scan)  # compile the Numba kernels first
    nose, rot, times, fails, kept = [], [], [], 0, []
    shares: dict[str, float] = {}
    caught = injected = lost = good = 0
    for i in range(args.scans):
        expression = "neutral" if i % 3 == 0 else EXPRESSIONS[i % len(EXPRESSIONS)]
        occluder = identity.occluders[i % len(identity.occluders)]
        truth = scanner.scan(ScanSpec(i % (args.subjects or args.scans), expression, rng.uniform(0.5, 1.0), rng.uniform(-30, 30),
                                      rng.uniform(-20, 20), rng.uniform(-10, 10), seed=i, occluder=occluder))
        kept.append(truth.scan)
        m = spike_mask(truth.scan, sampling=measure_sampling(truth.scan))  # as the pipeline scales it
        caught, injected = caught + (m & truth.spike).sum(), injected + truth.spike.sum()
        lost, good = lost + (m & ~truth.spike).sum(), good + (~truth.spike).sum()
        pre = Preprocessor(config)
        if i == 0:  # the kernels compiled (or their cache loaded) before any timing
            with contextlib.suppress(Exception):
                pre(truth.scan)
        t0 = time.perf_counter()
        try:
            face = pre(truth.scan)
        except Exception as e:  # a failure to acquire counts as a miss
            fails += 1
            print(f"scan {i}: failed: {e}")
            continue
        times.append(time.perf_counter() - t0)
        for k, v in pre.timings.items():
            shares[k] = shares.get(k, 0.0) + v
        nose.append(np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - truth.landmarks["nose_tip"]))
        rot.append(rotation_angle(np.asarray(face.meta.extra["to_frontal"])[:, :3] @ truth.rotation))
    nose, rot = np.array(nose), np.array(rot)
    total = sum(shares.values())
    print(f"sensor {args.sensor}, identities {args.identities}; scans: {args.scans}, failures to acquire: {fails}")
    print(f"nose tip error: median {np.median(nose):.2f} mm, 99th percentile {np.percentile(nose, 99):.2f} mm, "
          f"within 10 mm {np.mean(nose < 10):.1%}")
    print(f"residual rotation to frontal: median {np.median(rot):.2f} deg, max {rot.max():.2f} deg")
    print(f"spikes removed: {caught / injected:.1%}; good points removed: {lost / good:.3%}")
    print(f"time per scan: median {np.median(times) * 1000:.0f} ms (one core, steady state: the first scan "
          "preprocessed once untimed before, for the kernels' JIT compilation or cache load)")
    print("stage shares: " + ", ".join(f"{k} {v / total:.0%}" for k, v in sorted(shares.items(), key=lambda kv: -kv[1])))
    if args.preprocess_config:
        against_defaults(args, kept, config)
    if args.against:
        against_release(args, kept)


def against_defaults(args: argparse.Namespace, scans: list, config: PreprocessConfig) -> None:
    """The bench's scans (and --real frames) preprocessed with `config` and with the defaults, alternately, in this
    process after a warm-up of both: median ms and the speed-up."""
    from facerec3d.io import load_scan

    print(f"{args.preprocess_config} against the default settings (same scans, alternately, this process, one core):")
    sets = [(f"synthetic {args.sensor} ({args.identities}), {len(scans)} scans", scans)]
    if args.real_frames > 0 and (args.real / "manifest.csv").exists():
        with open(args.real / "manifest.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        step = max(1, len(rows) // args.real_frames)
        frames = [load_scan(args.real / r["path"], args.real / "intrinsics.json") for r in rows[::step][: args.real_frames]]
        sets.append((f"real frames of {args.real.name}, {len(frames)}", frames))
    pres = (Preprocessor(config), Preprocessor())  # the settings tried, the defaults
    for label, items in sets:
        ms = np.zeros((len(items), 2))
        for i, scan in enumerate(items):
            for k, pre in enumerate(pres):
                t0 = time.perf_counter()
                try:
                    pre(scan)
                except Exception:  # a failure to acquire is timed too: it is what the scan costs
                    pass
                ms[i, k] = 1000 * (time.perf_counter() - t0)
        a, b = np.median(ms, axis=0)
        print(f"  {label}: {a:.0f} ms per scan, defaults {b:.0f} ms: {b / a:.2f}× as fast (median)")


def against_release(args: argparse.Namespace, scans: list) -> None:
    """The bench's scans (and --real frames) timed with this tree and with release --against, in the same run."""
    from facerec3d.io import save_scan

    print(f"against release {args.against} (same files, each version in its own process, one core, steady state):")
    with tempfile.TemporaryDirectory() as tmp:
        files = [Path(tmp) / f"{i:03d}.abs.gz" for i in range(len(scans))]
        for scan, f in zip(scans, files):
            save_scan(scan, f)
        try:
            release.report(f"synthetic {args.sensor} ({args.identities}), {len(files)} .abs.gz scans",
                           release.compare(files, ref=args.against), args.against)
            if args.real_frames > 0 and (args.real / "manifest.csv").exists():
                with open(args.real / "manifest.csv", newline="") as f:
                    rows = list(csv.DictReader(f))
                step = max(1, len(rows) // args.real_frames)
                frames = [args.real / r["path"] for r in rows[::step][: args.real_frames]]
                release.report(f"real frames of {args.real.name}, {len(frames)}",
                               release.compare(frames, args.real / "intrinsics.json", args.against), args.against)
            elif args.real_frames > 0:
                print(f"  no real frames: {args.real} has no manifest.csv (rap3df-2019 is not shipped; pass --real)")
        except RuntimeError as e:
            print(f"  not timed: {e}")


if __name__ == "__main__":
    main()
