"""The `facerec3d` command line."""

from __future__ import annotations

import csv
import functools
import os
import sqlite3
import sys
from pathlib import Path

import click

from facerec3d.errors import FaceRec3DError


def friendly(fn):
    """Turn facerec3d's errors (and a few user errors) into one line and exit code 2, not a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (FaceRec3DError, OSError, ValueError, sqlite3.Error) as e:
            click.echo(f"error: {e}", err=True)
            sys.exit(2)

    return wrapper


@click.group()
@click.version_option(package_name="facerec3d")
def main():
    """3D face recognition (Mian & Pears, '3D Face Recognition', 2012): scans, preprocessing, matching, evaluation."""


@main.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@friendly
def info(files):
    """Size, valid points, bounding box and resolution (mm) of scan FILES."""
    from facerec3d.io import load_scan

    failed = 0
    for f in files:
        try:
            s = load_scan(f)
        except FaceRec3DError as e:
            click.echo(f"{f}: error: {e.reason if hasattr(e, 'reason') else e}", err=True)
            failed += 1
            continue
        lo, hi = s.bounding_box()
        grid = f"{s.grid_shape[0]}x{s.grid_shape[1]} grid, " if s.grid is not None else ""
        click.echo(f"{f}: {grid}{s.n_points} valid points, bbox [{lo[0]:.1f} {lo[1]:.1f} {lo[2]:.1f}] .. "
                   f"[{hi[0]:.1f} {hi[1]:.1f} {hi[2]:.1f}] mm, resolution {s.resolution():.2f} mm"
                   + (f", {len(s.landmarks)} landmarks" if s.landmarks else ""))
    if failed:
        sys.exit(2)


@main.command()
@click.argument("src", type=click.Path(dir_okay=False))
@click.argument("dst", type=click.Path(dir_okay=False))
@friendly
def convert(src, dst):
    """Convert scan SRC to DST (.abs, .abs.gz, .bnt, .ply, .npz; format from the name)."""
    from facerec3d.io import load_scan, save_scan

    save_scan(load_scan(src), dst)
    click.echo(f"wrote {dst}")


@main.command()
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--subjects", default=20, show_default=True, help="Number of subjects.")
@click.option("--scans", default=4, show_default=True, help="Scans per subject (the first is neutral and frontal).")
@click.option("--format", "fmt", type=click.Choice(["abs", "bnt"]), default="abs", show_default=True,
              help="FRGC (.abs.gz in nd1/<session>/) or Bosphorus (.bnt) layout.")
@click.option("--seed", default=0, show_default=True)
@click.option("--first-subject", default=0, show_default=True,
              help="Number of the first subject: a training set disjoint from the default test set starts at, "
                   "say, 1000 (identities depend on seed and subject number).")
@click.option("--expressions", help="Comma-separated expressions drawn for the expression scans "
              "(of smile, open-mouth, surprise, frown, puffed-cheeks; default all).")
@click.option("--expression-strength", nargs=2, type=float, default=(0.6, 1.0), show_default=True,
              help="Range (low high) of the expression strength; 1 1 is full strength.")
@click.option("--sensor", type=click.Choice(["frgc", "kinect-v2", "kinect-v2-8bit", "realsense"]), default="frgc",
              show_default=True, help="Simulated depth sensor: FRGC's Minolta laser scanner, Kinect v2 time of "
              "flight (1 mm, or 4/8 mm depth steps), RealSense D435 active stereo.")
@click.option("--identities", type=click.Choice(["model", "outside-model"]), default="model", show_default=True,
              help="Faces from the morphable model, or beyond it: wider identities, a non-linear deformation "
              "and occluders (hair fringe, glasses, hand).")
@click.option("--rows", type=int, help="Range image rows (default: the sensor's).")
@click.option("--cols", type=int, help="Range image columns (default: the sensor's; the focal length scales with it).")
@friendly
def synth(out, subjects, scans, fmt, seed, first_subject, expressions, expression_strength, sensor, identities, rows,
          cols):
    """Write a synthetic dataset of range scans with ground truth to OUT."""
    from dataclasses import replace

    from facerec3d.datasets.synthetic import (EXPRESSIONS, DatasetConfig, identity_profile, sensor_profile,
                                              write_dataset)

    chosen = tuple(e.strip() for e in expressions.split(",") if e.strip()) if expressions else EXPRESSIONS
    scanner = sensor_profile(sensor)
    if rows is not None or cols is not None:  # overrides; the focal length keeps the field of view
        cols = scanner.cols if cols is None else cols
        rows = scanner.rows if rows is None else rows
        scanner = replace(scanner, rows=rows, cols=cols, focal_px=scanner.focal_px * cols / scanner.cols)
    cfg = DatasetConfig(subjects=subjects, scans=scans, seed=seed, first_subject=first_subject, expressions=chosen,
                        expression_strength=tuple(expression_strength), scanner=scanner,
                        identity=identity_profile(identities))
    manifest = write_dataset(out, cfg, fmt, progress=True)
    click.echo(f"wrote {subjects * scans} scans; manifest and ground truth: {manifest}")


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="PNG to write.")
@click.option("--preprocess/--raw", "with_face", default=True, show_default=True,
              help="Also show the preprocessed face, with its detected landmarks.")
@friendly
def view(file, output, with_face):
    """Render scan FILE (shaded depth) before and after preprocessing, landmarks marked, to a PNG."""
    from facerec3d.io import load_scan
    from facerec3d.preprocess import Preprocessor, gridify, landmarks_in_input_frame
    from facerec3d.render import render

    scan = gridify(load_scan(file))
    panels = [(f"{Path(file).name} (raw)", scan)]
    if with_face:
        face = Preprocessor()(scan)
        panels[0] = (panels[0][0], scan.replace(landmarks=landmarks_in_input_frame(face)))
        panels.append(("preprocessed (frontal, 1 mm grid)", face))
    render(panels, output)
    click.echo(f"wrote {output}")


LANDMARK_COLUMNS = ("nose_tip", "nose_bridge", "left_eye_inner", "right_eye_inner", "left_eye_outer",
                    "right_eye_outer", "left_mouth_corner", "right_mouth_corner", "chin")


@main.command()
@click.argument("inputs", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--out", "outdir", required=True, type=click.Path(file_okay=False))
@click.option("--config", "config_file", type=click.Path(dir_okay=False), help="TOML or JSON preprocessing settings.")
@click.option("--format", "fmt", type=click.Choice(["npz", "ply"]), default="npz", show_default=True)
@click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores", help="Processes to use.")
@click.option("--intrinsics", type=click.Path(dir_okay=False), default=None,
              help="Depth frames: pinhole intrinsics JSON (fx, fy, cx, cy); default: an intrinsics.json beside them.")
@friendly
def preprocess(inputs, outdir, config_file, fmt, jobs, intrinsics):
    """Preprocess scans INPUTS into normalised faces in OUT, with OUT/landmarks.csv (chapter §8.5)."""
    from tqdm import tqdm

    from facerec3d.io import save_scan, scan_stem
    from facerec3d.preprocess import PreprocessConfig, landmarks_in_input_frame
    from facerec3d.preprocess.batch import preprocess_files
    from facerec3d.preprocess.pipeline import QUALITY_FIELDS, scan_quality

    config = PreprocessConfig.load(config_file) if config_file else PreprocessConfig()
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    header = (["scan", "status", "output"] + [f"{n}_{'xyz'[k]}" for n in LANDMARK_COLUMNS for k in range(3)]
              + list(QUALITY_FIELDS))
    failed = 0
    with open(out / "landmarks.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        bar = tqdm(preprocess_files(inputs, config, jobs, intrinsics=intrinsics), total=len(inputs), unit="scan",
                   desc="preprocessing")
        for outcome in bar:
            if outcome.face is None:
                failed += 1
                tqdm.write(f"{outcome.path}: failed: {outcome.error}")
                w.writerow([outcome.path, outcome.error, ""] + [""] * (len(header) - 3))
                continue
            target = out / f"{scan_stem(outcome.path)}.{fmt}"
            save_scan(outcome.face, target)
            lm = landmarks_in_input_frame(outcome.face)
            coords = [f"{lm[n][k]:.3f}" if n in lm else "" for n in LANDMARK_COLUMNS for k in range(3)]
            quality = scan_quality(outcome.face)
            w.writerow([outcome.path, "ok", str(target)] + coords + [quality.get(k, "") for k in QUALITY_FIELDS])
            tqdm.write(f"{outcome.path}: kept -> {target}")
    click.echo(f"{len(inputs) - failed} kept, {failed} failed; landmarks and quality in {out / 'landmarks.csv'}")
    if failed == len(inputs):
        sys.exit(1)


def _engine_options(fn):
    """--jobs and --scheduler, shared by the commands that match."""
    fn = click.option("--scheduler", help="Dask scheduler address (e.g. tcp://host:8786): shard the gallery over "
                      "its workers instead of local processes (pip install 'facerec3d[distributed]').")(fn)
    return click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores",
                        help="Processes to use (the gallery is split into one shard per process).")(fn)


def _cascade_options(fn, screens: bool = False):
    fn = click.option("--shortlist", default=20, show_default=True,
                      help="With --cascade: faces passed from the screen to full ICP.")(fn)
    if screens:
        fn = click.option("--screen", type=click.Choice(["depth", "keypoints"]), default="depth", show_default=True,
                          help="With --cascade: the first stage (depth descriptor, or keypoint matching §8.10.2).")(fn)
    return click.option("--cascade", is_flag=True, help="ICP only: screen the gallery cheaply (a depth descriptor) and "
                        "run full ICP on the shortlist only (faces off it score -inf).")(fn)


def _cascade_config(cascade: bool, shortlist: int, screen: str = "depth"):
    from facerec3d.gallery.cascade import CascadeConfig

    return CascadeConfig(shortlist=shortlist, screen=screen) if cascade else None


def _print_metrics(m: dict) -> None:
    from facerec3d.evaluation.report import format_value

    keys = ("rank1", "rank5", "eer", "vr_at_far_0.001", "vr_at_far_0.01")
    click.echo(f"{'probes':<14}{'n':>6}{'FTA':>6}" + "".join(f"{k:>17}" for k in keys))
    rows = [("all", m)] + list(m.get("subsets", {}).items())
    for name, r in rows:
        click.echo(f"{name:<14}{r['n_probes']:>6}{r['failures']:>6}" + "".join(f"{format_value(k, r.get(k)):>17}" for k in keys))
    t = m.get("timings", {})
    click.echo(f"gallery {m['n_gallery']}, failures to enrol {m.get('failures_to_enrol', 0)}; "
               f"preprocess {t.get('preprocess_s', 0):.1f} s, enrol {t.get('enrol_s', 0):.1f} s, "
               f"match {t.get('match_s', 0):.1f} s ({t.get('prepare_ms', 0):.1f} ms to prepare a probe, "
               f"{t.get('match_ms', 0):.4g} ms per comparison)")
    for f in m.get("failed_scans", []):
        click.echo(f"failed ({f['role']}): {f['path']}: {f['reason']}")


@main.command()
@click.argument("data", type=click.Path(exists=True))
@click.option("--method", default="icp", show_default=True,
              help="Matching method: icp, pca, lda, curvature, region-icp, keypoints, fusion.")
@click.option("--method-config", type=click.Path(exists=True, dir_okay=False),
              help="TOML or JSON file of the method's settings (its config dataclass's fields).")
@click.option("--train", type=click.Path(exists=True),
              help="Training dataset (subjects not in DATA) for learnt methods (pca, lda).")
@click.option("--model", type=click.Path(exists=True, dir_okay=False),
              help="Saved model (a run's model.npz) instead of --method/--train.")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False), help="Run folder to write.")
@click.option("--protocol", type=click.Choice(["frgc", "bosphorus", "roles", "all-vs-all"]),
              help="Default: from the dataset (Bosphorus folder, manifest roles, else FRGC).")
@click.option("--config", "config_file", type=click.Path(dir_okay=False), help="TOML or JSON preprocessing settings.")
@click.option("--cache", type=click.Path(file_okay=False), help="Preprocessing cache folder.")
@click.option("--intrinsics", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Depth frames: pinhole intrinsics JSON (fx, fy, cx, cy); default: an intrinsics.json beside them.")
@functools.partial(_cascade_options, screens=True)
@_engine_options
@friendly
def evaluate(data, method, method_config, train, model, out, protocol, config_file, cache, intrinsics, cascade,
             shortlist, screen, jobs, scheduler):
    """Evaluate a method on DATA (FRGC or Bosphorus folder, or manifest CSV): metrics, scores, plots, report."""
    from facerec3d.config import read_settings
    from facerec3d.evaluation.run import DEFAULT_CACHE, evaluate as run
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else PreprocessConfig()
    options = read_settings(method_config) if method_config else None
    m = run(data, method, out, protocol, jobs, cache or DEFAULT_CACHE, config, options=options, train=train,
            model=model, scheduler=scheduler, cascade=_cascade_config(cascade, shortlist, screen),
            intrinsics=intrinsics)
    _print_metrics(m)
    click.echo(f"report: {Path(out) / 'report.html'}")


@main.command()
@click.argument("data", nargs=-1, required=True, type=click.Path(exists=True))
@click.option("--gallery", "gallery", required=True, type=click.Path(dir_okay=False),
              help="Gallery store (SQLite file; made if missing).")
@click.option("--method", default="icp", show_default=True, help="Matching method (as for evaluate).")
@click.option("--method-config", type=click.Path(exists=True, dir_okay=False), help="TOML or JSON method settings.")
@click.option("--train", type=click.Path(exists=True), help="Training dataset for learnt methods (pca, lda).")
@click.option("--model", type=click.Path(exists=True, dir_okay=False), help="Saved model instead of --method/--train.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False), help="TOML or JSON preprocessing settings.")
@click.option("--subject", help="Subject of scan files whose names do not say it (default: the file stem).")
@click.option("--gallery-only", is_flag=True, help="Of a dataset, enrol only its protocol's gallery scans.")
@click.option("--cache", type=click.Path(file_okay=False), help="Preprocessing cache folder.")
@_engine_options
@friendly
def enroll(data, gallery, method, method_config, train, model, config_file, subject, gallery_only, cache, jobs,
           scheduler):
    """Enrol scans DATA (files, dataset folders or manifests) into the gallery store, one transaction each;
    scans that fail are recorded (failures to enrol) and the batch goes on."""
    from tqdm import tqdm

    from facerec3d.config import read_settings
    from facerec3d.evaluation.run import DEFAULT_CACHE, trained_matcher
    from facerec3d.gallery.engine import Engine
    from facerec3d.gallery.service import enroll_scans, scan_records
    from facerec3d.gallery.store import GalleryStore
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else PreprocessConfig()
    options = read_settings(method_config) if method_config else None
    matcher, _ = trained_matcher(method, options, train, model, jobs, cache or DEFAULT_CACHE, config)
    records = scan_records(data, subject, gallery_only)
    with GalleryStore(gallery, create=True) as store, Engine.create(jobs, scheduler) as engine, \
            tqdm(total=len(records), unit="scan", desc="enrolling") as bar:
        def show(source, status):
            bar.update()
            if status not in ("enrolled", "skipped"):
                tqdm.write(f"{source}: failed to enrol: {status}")

        report = enroll_scans(store, records, matcher, config, engine, cache or DEFAULT_CACHE, show)
        total = store.stats()["entries"]
    click.echo(f"{report.enrolled} enrolled, {len(report.skipped)} already enrolled, {len(report.failures)} failed "
               f"to enrol; {gallery}: {total} entries")


@main.command()
@click.argument("probe", type=click.Path(exists=True, dir_okay=False))
@click.option("--gallery", "gallery", required=True, type=click.Path(dir_okay=False), help="Gallery store.")
@click.option("-k", "k", default=5, show_default=True, help="Number of candidates to list.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False),
              help="Preprocessing settings; must be the gallery's (default: the gallery's).")
@click.option("--cache", type=click.Path(file_okay=False), help="Preprocessing cache folder.")
@_cascade_options
@_engine_options
@friendly
def identify(probe, gallery, k, config_file, cache, cascade, shortlist, jobs, scheduler):
    """The k gallery entries most like scan PROBE, best first (rank, subject, scan, score)."""
    from facerec3d.evaluation.run import DEFAULT_CACHE
    from facerec3d.gallery.engine import Engine
    from facerec3d.gallery.service import identify_scan
    from facerec3d.gallery.store import GalleryStore
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else None
    with GalleryStore(gallery) as store, Engine.create(jobs, scheduler) as engine:
        hits = identify_scan(store, probe, k, _cascade_config(cascade, shortlist), config, engine=engine,
                             cache=cache or DEFAULT_CACHE)
    click.echo(f"{'rank':>4}  {'subject':<12}{'scan':<20}{'score':>12}")
    for r, (entry, score) in enumerate(hits, start=1):
        click.echo(f"{r:>4}  {str(entry.subject):<12}{str(entry.scan_id):<20}{score:>12.4f}")


@main.command()
@click.argument("probe", type=click.Path(exists=True, dir_okay=False))
@click.option("--gallery", "gallery", required=True, type=click.Path(dir_okay=False), help="Gallery store.")
@click.option("--claim", required=True, help="The claimed subject ID.")
@click.option("--threshold", type=float, help="Accept scores >= this (default for icp: -1.0 mm², the EER point "
              "of the synthetic test60 protocol).")
@click.option("--config", "config_file", type=click.Path(dir_okay=False),
              help="Preprocessing settings; must be the gallery's (default: the gallery's).")
@click.option("--cache", type=click.Path(file_okay=False), help="Preprocessing cache folder.")
@friendly
def verify(probe, gallery, claim, threshold, config_file, cache):
    """Is scan PROBE the claimed subject? Prints accept/reject with the score; exit code 0 accept, 1 reject."""
    from facerec3d.evaluation.run import DEFAULT_CACHE
    from facerec3d.gallery.service import verify_scan
    from facerec3d.gallery.store import GalleryStore
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else None
    with GalleryStore(gallery) as store:
        accepted, score, threshold = verify_scan(store, probe, claim, threshold, config, cache or DEFAULT_CACHE)
    click.echo(f"{'accept' if accepted else 'reject'}: claim {claim}, score {score:.4f} (threshold {threshold:g})")
    sys.exit(0 if accepted else 1)


@main.group()
@click.argument("store", type=click.Path(dir_okay=False))
@click.pass_context
def gallery(ctx, store):
    """Look after the gallery store STORE: list, remove ID, stats."""
    ctx.obj = store


@gallery.command("list")
@click.pass_obj
@friendly
def gallery_list(store):
    """The enrolled entries (id, subject, scan, source) and the failures to enrol."""
    from facerec3d.gallery.store import GalleryStore

    with GalleryStore(store) as s:
        for e in s.entries():
            click.echo(f"{e.id}\t{e.subject}\t{e.scan_id}\t{e.source}")
        for source, reason in s.failures():
            click.echo(f"failed\t{source}\t{reason}")


@gallery.command("remove")
@click.argument("ident")
@click.pass_obj
@friendly
def gallery_remove(store, ident):
    """Remove subject IDENT's entries (or else the entry of scan IDENT)."""
    from facerec3d.gallery.store import GalleryError, GalleryStore

    with GalleryStore(store) as s:
        n = s.remove(ident)
    if not n:
        raise GalleryError(f"{store}: no subject or scan {ident!r}")
    click.echo(f"removed {n} entr{'y' if n == 1 else 'ies'}")


@gallery.command("stats")
@click.pass_obj
@friendly
def gallery_stats(store):
    """Entries, subjects, sizes, failures to enrol and the matcher."""
    from facerec3d.gallery.store import GalleryStore

    with GalleryStore(store) as s:
        st = s.stats()
    click.echo(f"{st['entries']} entries of {st['subjects']} subjects; "
               f"templates {st['template_bytes'] / 2**20:.1f} MiB, "
               f"file {st['file_bytes'] / 2**20:.1f} MiB; {st['failures_to_enrol']} failures to enrol; "
               f"method {st['method']} {st['options']}")


@main.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--out", "out", default="compare", show_default=True, type=click.Path(file_okay=False))
@friendly
def compare(runs, out):
    """Overlay several evaluation runs' ROC, DET and CMC curves, with one table."""
    from facerec3d.evaluation.compare import compare_runs

    compare_runs(list(runs), out)
    click.echo(f"wrote {Path(out) / 'compare.html'}")


@main.command()
@click.option("--subjects", default=30, show_default=True)
@click.option("--scans", default=4, show_default=True, help="Scans per subject: neutral gallery, neutral, expression, ±25° yaw.")
@click.option("--methods", default="icp,region-icp,lda", show_default=True,
              help="Comma-separated methods to evaluate and compare (learnt ones get a disjoint training set).")
@click.option("--out", "out", default="demo-out", show_default=True, type=click.Path(file_okay=False))
@click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores")
@click.option("--seed", default=0, show_default=True)
@friendly
def demo(subjects, scans, methods, out, jobs, seed):
    """The main job: synthesise a FRGC-style dataset (and a disjoint training set for learnt methods), evaluate
    each method on it, print the metrics and write one comparison report."""
    from facerec3d.datasets.synthetic import DatasetConfig, write_dataset
    from facerec3d.evaluation.compare import compare_runs
    from facerec3d.evaluation.run import evaluate as run
    from facerec3d.matching.registry import make_matcher

    out = Path(out)
    names = [m.strip() for m in methods.split(",") if m.strip()]
    learnt = {name for name in names if make_matcher(name).needs_training}
    sets = {"data": DatasetConfig(subjects=subjects, scans=scans, seed=seed)}
    if learnt:
        sets["train"] = DatasetConfig(subjects=subjects, scans=scans, seed=seed + 1, first_subject=1000)
    for name, cfg in sets.items():
        if not (out / name / "manifest.csv").is_file():
            click.echo(f"synthesising {name}: {cfg.subjects} subjects x {cfg.scans} scans")
            write_dataset(out / name, cfg, "abs", progress=True)
    for name in names:
        click.echo(f"\n== {name}" + (f" (trained on {out / 'train'})" if name in learnt else ""))
        m = run(out / "data", name, out / name, None, jobs, out / "cache",
                train=out / "train" if name in learnt else None)
        _print_metrics(m)
    compare_runs([out / name for name in names], out / "compare")
    click.echo(f"\nreports: {out / 'compare' / 'compare.html'} (all methods), {out}/<method>/report.html")


if __name__ == "__main__":
    main()
