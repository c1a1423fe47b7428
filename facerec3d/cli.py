"""The `facerec3d` command line."""

from __future__ import annotations

import csv
import functools
import os
import sys
from pathlib import Path

import click

from facerec3d.config import DEFAULT_METHOD, DEFAULT_THRESHOLDS
from facerec3d.errors import FaceRec3DError, threshold_text
from facerec3d.workers import one_blas_thread


def friendly(fn):
    """Turn facerec3d's own errors (bad input, settings, stores; and the file system's, which name the file) into
    one line, `error: FILE: reason`, and exit code 2. Anything else is a bug, and shows its traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except BrokenPipeError:  # the reader went away (`| head`): not an error of this command
            raise
        except (FaceRec3DError, OSError) as e:
            if isinstance(e, OSError) and e.filename is not None and e.strerror:  # not "[Errno 2] ...: 'x'"
                e = f"{e.filename}: {e.strerror[:1].lower()}{e.strerror[1:]}"
            click.echo(f"error: {e}", err=True)
            sys.exit(2)

    return wrapper


#: Exit codes of a Unix tool stopped by a signal: 128 + SIGINT (Ctrl-C), 128 + SIGPIPE (its reader went away).
EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 130, 141


_HELP_FOR_NO_ARGUMENTS = getattr(click.exceptions, "NoArgsIsHelpError", ())  # click >= 8.2


class _Main(click.Group):
    """The command group, ending as a Unix tool does: Ctrl-C exits 130 with one line, and output into a closed pipe
    (`facerec3d gallery g.sqlite list | head -1`) ends quietly with 141; a usage error (a missing argument, a bad
    option value) is one line, as every other error, with the command's --help to look at (exit code 2)."""

    def main(self, *args, standalone_mode: bool = True, **kwargs):
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except _HELP_FOR_NO_ARGUMENTS as e:  # `facerec3d` alone: the help, as click shows it
            e.show()
            sys.exit(e.exit_code)
        except click.UsageError as e:
            where = f" (see {e.ctx.command_path} --help)" if e.ctx is not None else ""
            click.echo(f"error: {e.format_message()}{where}", err=True)
            sys.exit(e.exit_code)
        except click.ClickException as e:
            e.show()
            sys.exit(e.exit_code)
        except click.Abort:
            click.echo("aborted", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (KeyboardInterrupt, ImportError) as e:
            # Ctrl-C while a compiled module loads (scipy's pybind11 ones) is "initialization failed" from it
            if isinstance(e, ImportError) and not isinstance(e.__cause__, KeyboardInterrupt):
                raise
            click.echo("interrupted", err=True)
            raise click.exceptions.Exit(EXIT_INTERRUPTED) from None
        except MemoryError as e:  # the machine's memory ran out (a plot's C++ bad_alloc under a memory limit): one
            #                       line, as any error, not a traceback
            click.echo(f"error: out of memory{f' ({e})' if str(e) else ''}: free memory, or give the command less "
                       "at once (fewer --jobs, a smaller gallery or dataset)", err=True)
            raise click.exceptions.Exit(1) from None
        except BrokenPipeError:
            try:  # nothing more reaches the reader; send what is still buffered nowhere, quietly
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            except (OSError, ValueError):  # no real stdout (e.g. under a test runner)
                pass
            raise click.exceptions.Exit(EXIT_BROKEN_PIPE) from None


@click.group(cls=_Main)
@click.version_option(package_name="facerec3d")
def main():
    """3D face recognition (Mian & Pears, '3D Face Recognition', 2012): scans, preprocessing, matching, evaluation."""


#: --intrinsics, of every command that reads scans given by the user (a missing file is refused before any work).
_INTRINSICS_OPTION = click.option(
    "--intrinsics", type=click.Path(exists=True, dir_okay=False), default=None,
    help="Depth frames: pinhole intrinsics JSON (fx, fy, cx, cy); default: an intrinsics.json beside them.")


@main.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@_INTRINSICS_OPTION
@friendly
def info(files, intrinsics):
    """Size, valid points, bounding box and resolution (mm) of scan FILES."""
    import numpy as np

    from facerec3d.io import load_scan

    failed = 0
    for f in files:
        try:
            s = load_scan(f, intrinsics)
        except FaceRec3DError as e:  # the next file is still looked at
            click.echo(f"error: {e}", err=True)
            failed += 1
            continue
        lo, hi = s.bounding_box()
        grid = f"{s.grid_shape[0]}x{s.grid_shape[1]} grid, " if s.grid is not None else ""
        res = s.resolution()
        spacing = f"resolution {res:.2f} mm" if np.isfinite(res) else "no resolution (a single point)"
        click.echo(f"{f}: {grid}{s.n_points} valid point{'s' * (s.n_points != 1)}, bbox [{lo[0]:.1f} {lo[1]:.1f} "
                   f"{lo[2]:.1f}] .. [{hi[0]:.1f} {hi[1]:.1f} {hi[2]:.1f}] mm, {spacing}"
                   + (f", {len(s.landmarks)} landmarks" if s.landmarks else ""))
    if failed:
        sys.exit(2)


@main.command()
@click.argument("src", type=click.Path(dir_okay=False))
@click.argument("dst", type=click.Path(dir_okay=False))
@friendly
def convert(src, dst):
    """Convert scan SRC to DST (.abs, .abs.gz, .bnt, .ply, .obj, .npz; format from the name). Every point is
    kept; an OBJ holds no range-image grid (its points and the grid's triangles), the others keep it."""
    from facerec3d.io import load_scan, save_scan

    save_scan(load_scan(src), dst)
    click.echo(f"wrote {dst}")


@main.command()
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--subjects", default=20, show_default=True, type=click.IntRange(min=1), help="Number of subjects.")
@click.option("--scans", default=4, show_default=True, type=click.IntRange(min=1),
              help="Scans per subject (the first is neutral and frontal).")
@click.option("--format", "fmt", type=click.Choice(["abs", "bnt", "png", "obj", "ply"]), default="abs",
              show_default=True,
              help="FRGC (.abs.gz in nd1/<session>/) or Bosphorus (.bnt) layout, a depth camera's 16-bit frames "
                   "(<subject>/front_1.png, ... with intrinsics.json), or a scanner's meshes (obj) or point clouds "
                   "(ply), --spacing mm between vertices, each in a random frame (the manifest's landmarks in it).")
@click.option("--spacing", type=click.FloatRange(0.5, 10.0),
              help="With --format obj / ply: millimetres between vertices (a stereo scanner's ~4)  [default: 2].")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0))
@click.option("--first-subject", default=0, show_default=True, type=click.IntRange(min=0),
              help="Number of the first subject: a training set disjoint from the default test set starts at, "
                   "say, 1000 (identities depend on seed and subject number). Subject N is named in FRGC's "
                   "style, 04200 + N: 300 makes 04500.")
@click.option("--expressions", help="Comma-separated expressions drawn for the expression scans "
              "(of smile, open-mouth, surprise, frown, puffed-cheeks; default all).")
@click.option("--expression-strength", nargs=2, type=click.FloatRange(0.0, 1.0), default=(0.6, 1.0), show_default=True,
              help="Range (low high) of the expression strength; 1 1 is full strength.")
@click.option("--sensor", type=click.Choice(["frgc", "kinect-v2", "kinect-v2-8bit", "realsense"]), default="frgc",
              show_default=True, help="Simulated depth sensor: FRGC's Minolta laser scanner, Kinect v2 time of "
              "flight (1 mm, or 4/8 mm depth steps), RealSense D435 active stereo.")
@click.option("--identities", type=click.Choice(["model", "outside-model", "outside-model-unoccluded"]),
              default="model", show_default=True,
              help="Faces from the morphable model, or beyond it: wider identities, a non-linear deformation and "
              "occluders (hair fringe, glasses, hand); outside-model-unoccluded: the same faces without the occluders.")
@click.option("--rows", type=click.IntRange(min=16), help="Range image rows (default: the sensor's).")
@click.option("--cols", type=click.IntRange(min=16),
              help="Range image columns (default: the sensor's; the focal length scales with it).")
@click.option("--overwrite", is_flag=True, help="Replace the dataset already in OUT (the files its manifest.csv "
              "lists are removed first); without it, an OUT holding a dataset is refused.")
@friendly
def synth(out, subjects, scans, fmt, spacing, seed, first_subject, expressions, expression_strength, sensor,
          identities, rows, cols, overwrite):
    """Write a synthetic dataset of range scans with ground truth to OUT (refused when OUT holds one, unless
    --overwrite: a gallery enrolled from its files would silently hold other faces)."""
    from dataclasses import replace

    from facerec3d.datasets.synthetic import (EXPRESSIONS, DatasetConfig, identity_profile, sensor_profile,
                                              write_dataset)
    from facerec3d.io.common import MAX_POINTS

    chosen = tuple(e.strip() for e in expressions.split(",") if e.strip()) if expressions else EXPRESSIONS
    scanner = sensor_profile(sensor)
    if rows is not None or cols is not None:  # overrides; the focal length keeps the field of view
        cols = scanner.cols if cols is None else cols
        rows = scanner.rows if rows is None else rows
        if rows * cols > MAX_POINTS:  # before any work: scans that every reader here would refuse
            raise click.UsageError(f"--rows {rows} --cols {cols}: {rows * cols} pixels a scan, more than the "
                                   f"{MAX_POINTS} facerec3d reads")
        scanner = replace(scanner, rows=rows, cols=cols, focal_px=scanner.focal_px * cols / scanner.cols)
    if spacing is not None and fmt not in ("obj", "ply"):
        raise click.UsageError(f"--spacing is for meshes and point clouds (--format obj / ply), not --format {fmt}")
    _clear_dataset(Path(out), overwrite)
    cfg = DatasetConfig(subjects=subjects, scans=scans, seed=seed, first_subject=first_subject, expressions=chosen,
                        expression_strength=tuple(expression_strength), scanner=scanner,
                        identity=identity_profile(identities))
    manifest = write_dataset(out, cfg, fmt, progress=True, spacing_mm=2.0 if spacing is None else spacing)
    click.echo(f"wrote {subjects * scans} scans; manifest and ground truth: {manifest}")


def _capped_jobs(ctx, param, value: int | None) -> int | None:
    """--jobs, at most `workers.JOBS_PER_CORE` processes per core, saying so once when it caps: more only queue for
    the cores (--jobs 100000 opened a process pool each and ran out of open files)."""
    from facerec3d.workers import JOBS_PER_CORE, useful_jobs

    if ctx.params.get("scheduler"):  # a Dask cluster's workers do the work (--scheduler is read first: eager)
        return value
    if value is not None and (limit := useful_jobs(value)) < value:
        click.echo(f"warning: --jobs {value}: using {limit} processes ({JOBS_PER_CORE} per core; more would only wait "
                   "for a core)", err=True)
        return limit
    return value


def _finite(value: float | None, name: str) -> float | None:
    """A click option's float, refused (a usage error) when it is NaN or infinite: no score compares to NaN (and NaN
    passes click's FloatRange)."""
    import math

    if value is not None and not math.isfinite(value):
        raise click.BadParameter(f"must be a finite number, not {value}", param_hint=name)
    return value


def _clear_dataset(out: Path, overwrite: bool) -> None:
    """Refuse an OUT that holds a dataset (its manifest.csv), or with `overwrite` remove the files its manifest lists
    (those inside OUT only), its intrinsics.json and the manifest, so no scan of the old dataset stays behind."""
    import csv

    from facerec3d.errors import InputError

    manifest = out / "manifest.csv"
    if not manifest.is_file():
        return
    if not overwrite:
        raise InputError(f"{out}: holds a dataset already ({manifest.name}); give --overwrite to replace it")
    root = out.resolve()
    try:
        with open(manifest, newline="", encoding="utf-8-sig") as f:
            listed = [row.get("path") or "" for row in csv.DictReader(f)]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"{manifest}: cannot read the old dataset's manifest ({e})") from None
    for rel in listed + ["intrinsics.json", manifest.name]:
        path = (out / rel).resolve()
        if rel and path.is_relative_to(root) and path.is_file():
            path.unlink()


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="PNG to write.")
@click.option("--preprocess/--raw", "with_face", default=True, show_default=True,
              help="Also show the preprocessed face, with its detected landmarks.")
@friendly
def view(file, output, with_face):
    """Render scan FILE (shaded depth) before and after preprocessing, landmarks marked, to a PNG."""
    import numpy as np

    from facerec3d.io import load_scan
    from facerec3d.jit import compilation_notice
    from facerec3d.preprocess import Preprocessor, gridify, landmarks_in_input_frame
    from facerec3d.render import check_image_path, render, shaded

    check_image_path(output)  # before the work: a format or folder that cannot be written says so at once
    with compilation_notice(lambda line: click.echo(line, err=True)):  # a cold Numba cache: ~30 s, said first
        scan = gridify(load_scan(file))
        if min(scan.grid_shape) < 2 or not np.isfinite(shaded(scan)).any():  # shading: depth differences along
            from facerec3d.errors import InputError                           # rows and columns

            raise InputError(f"{file}: too thin to draw (a grid of {scan.grid_shape[0]}×{scan.grid_shape[1]} points; "
                             "the shaded drawing needs points with neighbours along both rows and columns)")
        panels = [(f"{Path(file).name} (raw)", scan)]
        if with_face:
            from facerec3d.errors import FailureToAcquire

            try:
                with one_blas_thread():
                    face = Preprocessor()(scan)
            except FailureToAcquire as e:  # the scan itself can still be looked at
                raise FailureToAcquire(f"{e.reason} (`facerec3d view --raw` renders the scan as it is)",
                                       e.path) from None
            panels[0] = (panels[0][0], scan.replace(landmarks=landmarks_in_input_frame(face)))
            panels.append(("preprocessed (frontal, 1 mm grid)", face))
        render(panels, output)
    click.echo(f"wrote {output}")


LANDMARK_COLUMNS = ("nose_tip", "nose_bridge", "left_eye_inner", "right_eye_inner", "left_eye_outer",
                    "right_eye_outer", "left_mouth_corner", "right_mouth_corner", "chin")


@main.command()
@click.argument("inputs", nargs=-1, required=True, type=click.Path())
@click.option("-o", "--out", "outdir", required=True, type=click.Path(file_okay=False))
@click.option("--overwrite", is_flag=True, help="Replace the faces and landmarks.csv an earlier preprocess wrote "
              "into OUT (they are removed first); without it such a folder is refused.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False), help="TOML or JSON preprocessing settings.")
@click.option("--format", "fmt", type=click.Choice(["npz", "ply"]), default="npz", show_default=True)
@click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores", type=click.IntRange(min=1),
              callback=_capped_jobs,
              help="Processes to use.")
@_INTRINSICS_OPTION
@friendly
def preprocess(inputs, outdir, overwrite, config_file, fmt, jobs, intrinsics):
    """Preprocess scans INPUTS (files, dataset folders or manifests, as for enroll) into normalised faces in OUT,
    with OUT/landmarks.csv (chapter §8.5). Outputs are named after the inputs; when files of several folders share
    a name, after folder and file (s000/front_1.png gives s000_front_1.npz). An OUT holding an earlier
    preprocess's output is refused unless --overwrite. Exit code 1 when no scan could be used."""
    from contextlib import closing

    from tqdm import tqdm

    from facerec3d.evaluation.report import claim_run_folder
    from facerec3d.gallery.service import scan_paths
    from facerec3d.io import save_scan, unique_stems
    from facerec3d.preprocess import PreprocessConfig, landmarks_in_input_frame
    from facerec3d.preprocess.batch import preprocess_files
    from facerec3d.preprocess.pipeline import QUALITY_FIELDS, scan_quality

    config = PreprocessConfig.load(config_file) if config_file else PreprocessConfig()
    inputs = scan_paths(inputs)
    out = Path(outdir)
    claim_run_folder(out, overwrite, files=_preprocess_outputs(out), what="a preprocess output")
    out.mkdir(parents=True, exist_ok=True)
    header = (["scan", "status", "output"] + [f"{n}_{'xyz'[k]}" for n in LANDMARK_COLUMNS for k in range(3)]
              + list(QUALITY_FIELDS))
    failed = 0
    # the batch's worker processes shut down here, not when its generator is collected (a Ctrl-C then was an
    # "Exception ignored" traceback, exit code 0)
    with open(out / "landmarks.csv", "w", newline="") as f, \
            closing(preprocess_files(inputs, config, jobs=jobs, intrinsics=intrinsics)) as outcomes:
        w = csv.writer(f)
        w.writerow(header)
        bar = tqdm(outcomes, total=len(inputs), unit="scan", desc="preprocessing")
        for stem, outcome in zip(unique_stems(inputs), bar):
            if outcome.face is None:
                failed += 1
                tqdm.write(f"{outcome.path}: failed: {outcome.error}")
                w.writerow([outcome.path, outcome.error, ""] + [""] * (len(header) - 3))
                continue
            target = out / f"{stem}.{fmt}"
            lm = landmarks_in_input_frame(outcome.face)
            coords = [f"{lm[n][k]:.3f}" if n in lm else "" for n in LANDMARK_COLUMNS for k in range(3)]
            quality = scan_quality(outcome.face)
            try:  # a face only with its row: interrupted in between (Ctrl-C), a face landmarks.csv did not list stayed
                save_scan(outcome.face, target)
                w.writerow([outcome.path, "ok", str(target)] + coords + [quality.get(k, "") for k in QUALITY_FIELDS])
                f.flush()
            except BaseException:
                target.unlink(missing_ok=True)
                raise
            tqdm.write(f"{outcome.path}: kept -> {target}")
    click.echo(f"{len(inputs) - failed} kept, {failed} failed; landmarks and quality in {out / 'landmarks.csv'}")
    if failed == len(inputs):
        sys.exit(1)


def _preprocess_outputs(out: Path) -> list[str]:
    """The names of the files an earlier `preprocess` wrote into OUT: landmarks.csv and the faces it lists."""
    from facerec3d.errors import InputError

    listing = out / "landmarks.csv"
    if not listing.is_file():
        return []
    try:
        with open(listing, newline="", errors="replace") as f:
            faces = [Path(row["output"]).name for row in csv.DictReader(f) if row.get("output")]
    except csv.Error as e:  # a field over the csv module's limit, a NUL byte: not the listing preprocess writes
        raise InputError(f"{listing}: not a readable CSV file ({e}): not a listing preprocess wrote; remove it or "
                         "choose another OUT") from None
    return ["landmarks.csv", *(name for name in faces if Path(name).suffix in (".npz", ".ply"))]


def _to_stderr(line: str) -> None:
    """One line of information or warning for the user, on stderr (what a learnt method learnt from, ...)."""
    click.echo(line, err=True)


def _cache_folder(cache: str | None) -> "str | Path":
    """--cache, or else the default preprocessing cache, whose place is said (one line on stderr) when a command
    first makes it."""
    from facerec3d.preprocess import batch

    if cache:
        return cache
    if not batch.DEFAULT_CACHE.is_dir():
        click.echo(f"preprocessing cache: {batch.DEFAULT_CACHE} (first use: faces preprocessed from now on are kept "
                   "there and reused; `facerec3d cache info` shows it, `facerec3d cache clear` empties it, --cache DIR "
                   "chooses another)", err=True)
    return batch.DEFAULT_CACHE


_CACHE_OPTION = click.option("--cache", type=click.Path(file_okay=False),
                             help="Preprocessing cache folder [default: the user's cache folder, see facerec3d cache "
                                  "info].")


def _engine_options(fn):
    """--jobs and --scheduler, shared by the commands that match."""
    fn = click.option("--scheduler", is_eager=True,  # before --jobs, whose local cap it lifts (`_capped_jobs`)
                      help="Dask scheduler address (e.g. tcp://host:8786): shard the gallery over "
                      "its workers instead of local processes (pip install 'facerec3d[distributed]').")(fn)
    return click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores", type=click.IntRange(min=1),
                        callback=_capped_jobs,
                        help="Processes to use (the gallery is split into one shard per process).")(fn)


def _cascade_options(fn, screens: tuple[str, ...] = ("depth", "embedding")):
    fn = click.option("--shortlist", default=20, show_default=True, type=click.IntRange(min=1),
                      help="With --cascade: faces passed from the screen to full ICP.")(fn)
    fn = click.option("--screen", type=click.Choice(screens), default="depth", show_default=True,
                      help="With --cascade: the first stage (depth descriptor, the learned embedding"
                           + (", or keypoint matching §8.10.2" if "keypoints" in screens else "") + ").")(fn)
    return click.option("--cascade", is_flag=True, help="ICP only: screen the gallery cheaply (a depth descriptor or "
                        "the learned embedding) and run full ICP on the shortlist only (faces off it score -inf).")(fn)


def _given(*names) -> list[str]:
    """The options NAMES of the command that were given (not left at their defaults), as spelt (`--fmr`)."""
    from click.core import ParameterSource

    ctx = click.get_current_context()
    opts = {p.name: p.opts[0] for p in ctx.command.params}
    return [opts[n] for n in names if ctx.get_parameter_source(n) not in (None, ParameterSource.DEFAULT)]


def _check_cascade(cascade: bool) -> None:
    """Refuse --shortlist and --screen without --cascade (they would be ignored: the whole gallery is matched)."""
    if not cascade and (given := _given("shortlist", "screen")):
        raise click.UsageError(f"{', '.join(given)} works with --cascade only (without it the whole gallery is "
                               "matched, and it would be ignored).")


def _cascade_config(cascade: bool, shortlist: int, screen: str = "depth"):
    from facerec3d.gallery.cascade import CascadeConfig

    return CascadeConfig(shortlist=shortlist, screen=screen) if cascade else None


def _server_options(fn):
    """--server and --api-key: the same command against a gallery service (facerec3d serve)."""
    fn = click.option("--api-key", envvar="FACEREC3D_API_KEY", show_envvar=True,
                      help="With --server: the API key (better from the environment than the command line).")(fn)
    return click.option("--server", metavar="URL", help="Use the gallery service at URL (facerec3d serve) instead "
                        "of a local gallery store.")(fn)


def _edge_option(fn):
    """--preprocess-locally: with --server, preprocess here and upload the face (the service skips that step)."""
    return click.option("--preprocess-locally", is_flag=True,
                        help="With --server: preprocess each scan here, with the service's settings, and upload the "
                             "face, which the service matches without preprocessing it again.")(fn)


def _edge(server, preprocess_locally):
    """The cap on BLAS threads while scans are preprocessed here (--preprocess-locally), else nothing."""
    from contextlib import nullcontext

    return one_blas_thread() if server and preprocess_locally else nullcontext()


def _local_only(server, gallery, *names):
    """With --server: refuse --gallery and the local-only options NAMES that were given; else --gallery is needed."""
    from click.core import ParameterSource

    ctx = click.get_current_context()
    if not server:
        if ctx.params.get("preprocess_locally"):
            raise click.UsageError("--preprocess-locally works with --server only (locally, scans are always "
                                   "preprocessed here).")
        if not gallery:
            raise click.UsageError("Missing option '--gallery' (or --server URL).")
        return
    opts = {p.name: p.opts[0] for p in ctx.command.params}
    given = [opts[n] for n in ("gallery", *names) if ctx.get_parameter_source(n) not in (None, ParameterSource.DEFAULT)]
    if given:
        raise click.UsageError(f"{', '.join(given)} cannot be used with --server (the service's gallery has its own "
                               "store and settings).")


def _client(server, api_key):
    from facerec3d.client import Client

    return Client(server, api_key)


def _enroll_remote(server, api_key, records, jobs, preprocess_locally=False, intrinsics=None, calibrate=True):
    """Upload scans to a service's enrol endpoint (`jobs` at once) and report as the local enrolment does; with
    `preprocess_locally`, preprocessed here first (a scan without a face fails here, unrecorded by the service);
    depth frames with the `intrinsics` file when given. With `calibrate`, once some scan was enrolled, the
    service's threshold is calibrated on this enrolment's scans that its gallery holds (`_calibrate_remote`), as
    a local enrolment calibrates on the gallery's own scans."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from facerec3d.client import ServiceError
    from facerec3d.errors import FaceRec3DError
    from facerec3d.evaluation.calibrate import calibration_selection

    chosen = {id(r) for r in calibration_selection(records)}  # the scans a calibration would score
    sent = {}  # with preprocess_locally, the faces sent for them: calibrated on as the very bytes enrolled
    lost = []  # the reason the service could not be reached, once it could not: the scans after it are not sent

    def one(record):
        if lost:
            return None
        try:
            scan = record.path
            if preprocess_locally:
                scan = client.upload(record.path, preprocess_locally=True, intrinsics=intrinsics)
                if id(record) in chosen:
                    sent[id(record)] = scan
            client.enrol(scan, record.subject, record.scan_id, intrinsics=intrinsics)
            return "enrolled"
        except ServiceError as e:
            if e.status == 409:
                return "skipped"
            if e.status == 0:  # the service gone (stopped, the network down, no answer in time): this scan's
                lost.append(e.reason)  # outcome is unknown, and every later scan would fail alike: not sent
                return f"{e.reason} (whether the service enrolled it is unknown: enrol it again to know)"
            if e.status in (413, 415, 422):
                return e.reason.removeprefix("failure to enrol: ").removeprefix(f"{Path(record.path).name}: ")
            if e.status >= 500:  # this scan's: the service answers the next (a refused key or a lost service stops)
                return f"service error {e.status}: {e.reason}"
            raise
        except FaceRec3DError as e:  # read here (a depth frame's intrinsics) or preprocessed here: unreadable, no face
            reason = str(e).removeprefix(f"{record.path}: ")
            return f"{reason} (preprocessed locally)" if preprocess_locally else reason

    counts = {"enrolled": 0, "skipped": 0, "failed": 0}
    held = []  # the chosen scans the gallery holds (enrolled now or before)
    with _client(server, api_key) as client, ThreadPoolExecutor(max(1, min(jobs, 8))) as pool, \
            tqdm(total=len(records), unit="scan", desc="enrolling") as bar:
        if preprocess_locally:
            client.preprocessor()  # the service's settings, or stop here when this facerec3d cannot reproduce them
        for record, status in zip(records, pool.map(one, records)):
            bar.update()
            if status is None:
                counts["not sent"] = counts.get("not sent", 0) + 1
            elif status in counts:
                counts[status] += 1
                if id(record) in chosen:
                    held.append(record)
            else:
                counts["failed"] += 1
                tqdm.write(f"{record.path}: failed to enrol: {status}")
    if lost:  # what was committed stays; say how far it got, and fail: the enrolment is not complete
        click.echo(f"{counts['enrolled']} enrolled, {counts['skipped']} already enrolled, {counts['failed']} failed to "
                   f"enrol, {counts.get('not sent', 0)} not sent: the service stopped answering ({lost[0]})", err=True)
        sys.exit(1)
    with _client(server, api_key) as client:
        st = client.stats()
        if calibrate and counts["enrolled"]:
            _calibrate_own_remote(client, st, [sent.get(id(r), r.path) for r in held], [r.subject for r in held],
                                  intrinsics)
    click.echo(f"{counts['enrolled']} enrolled, {counts['skipped']} already enrolled, {counts['failed']} failed "
               f"to enrol; {server}: {st['entries']} entries")
    if counts["failed"] and not counts["enrolled"] and not counts["skipped"]:
        sys.exit(1)  # nothing succeeded, as a local enrolment


def _keeps_given_threshold(kept: dict | None, where: str, entries: int | None = None) -> bool:
    """Whether the gallery's threshold was calibrated on scans given for it (the user's choice, not replaced behind
    them by the calibration that follows an enrolment): then says so in one line, with how to recalibrate
    (`facerec3d gallery WHERE calibrate ...`) and, when the gallery now holds another number of `entries` than it
    was calibrated with, that too (a fusion's scores are normalised over the gallery)."""
    from facerec3d.evaluation.calibrate import OWN_SCANS

    if kept is None or kept.get("data") == OWN_SCANS:
        return False
    then = kept.get("entries")
    grown = (f"; calibrated when the gallery held {then} entries, it holds {entries} now"
             if entries is not None and then is not None and then != entries else "")
    click.echo(f"kept the verification threshold {threshold_text(kept['value'])} calibrated on {kept['data']}"
               f"{grown} (recalibrate: facerec3d gallery {where} calibrate SCANS ...)")
    return True


def _stale_threshold(kept: dict | None, entries: int) -> bool:
    """Whether a threshold the gallery calibrated on its own scans no longer covers it (an interrupted enrolment, or
    one run with --no-calibrate, added entries after it): the next enrolment calibrates again, even adding none."""
    from facerec3d.evaluation.calibrate import OWN_SCANS

    return kept is None or (kept.get("data") == OWN_SCANS and kept.get("entries") != entries)


def _calibrate_own_remote(client, stats, scans, subjects, intrinsics) -> None:
    """After an enrolment through the service: calibrate its threshold on the enrolled scans, as the local
    enrolment does on the gallery's own (FMR 1 %), unless the threshold was calibrated on scans given for it
    (kept, as locally); a calibration that fails or is refused (e.g. a key without the admin scope) is said in
    one line, the enrolment stands."""
    if _keeps_given_threshold(stats.get("threshold"), f"--server {client.url}", stats.get("entries")):
        return
    if not scans:  # (more than 100 scans, and those a calibration would score all failed)
        click.echo("verification threshold not calibrated: none of the scans it would score is in the gallery")
        return
    try:
        _calibrate_remote(client, stats, scans, subjects, 0.01, own=True, intrinsics=intrinsics)
    except (FaceRec3DError, OSError) as e:
        click.echo(f"verification threshold not calibrated: {e}")


def _calibrate_remote(client, stats, scans, subjects, fmr, own=False, intrinsics=None) -> None:
    """Calibrate a service's threshold on labelled scans (paths, or `ScanUpload`s as they were sent), in one
    request: an even selection of them that fits the service's upload limit (from its `stats`); print the
    record as a local calibration does."""
    from facerec3d.client import ScanUpload
    from facerec3d.evaluation.calibrate import calibration_selection

    sizes = [len(s.data) if isinstance(s, ScanUpload) else Path(s).stat().st_size for s in scans]
    budget = 0.9 * stats.get("limits", {}).get("max_upload_bytes", float("inf")) - 4096  # (multipart's own bytes)
    chosen = list(range(len(scans)))
    while len(chosen) > 2 and sum(sizes[i] + 1024 for i in chosen) > budget:
        chosen = calibration_selection(range(len(scans)), len(chosen) - 1)
    r = client.calibrate([scans[i] for i in chosen], [subjects[i] for i in chosen], fmr, own=own,
                         intrinsics=intrinsics)
    click.echo(_threshold_line(r, client.url))


_THRESHOLDS = (("EER", "threshold_at_eer"), ("FMR 0.1%", "threshold_at_far_0.001"), ("FMR 1%", "threshold_at_far_0.01"))


def _print_metrics(m: dict, negated: bool = False) -> None:
    """The console table: per probe set and comparison mask, figures with their 95 % intervals; then counts,
    thresholds (on the score file's own scale: `negated`, distances read as similarities, are turned back),
    timings and failures."""
    from facerec3d.evaluation.report import format_value, set_table

    columns, rows = set_table(m)
    widths = [max(len(str(x)) for x in col) for col in zip(columns, *rows)]
    for row in (columns, *rows):
        click.echo("  ".join(f"{c:<{w}}" if k == 0 else f"{c:>{w}}" for k, (c, w) in enumerate(zip(row, widths))))
    click.echo("(value (95% interval), subject-level bootstrap)" if m.get("ci95") else "")
    if m.get("rank1_all") is not None and m.get("rank1_all") != m.get("rank1"):  # failures to acquire or enrol
        click.echo(f"rank-1 over every probe, failures to acquire and probes of unenrolled subjects counted as "
                   f"misses: {format_value('rank1_all', m['rank1_all'])} (the figure to compare systems on)")

    def thresholds(figures: dict) -> str:
        def own_scale(t):
            return -t if negated and t is not None else t
        return ", ".join(f"{name} {format_value('', own_scale(figures.get(key)))}" for name, key in _THRESHOLDS)

    click.echo(f"thresholds ({'distance <=' if negated else 'score >='} t accepts): {thresholds(m)}")
    if strangers := m.get("strangers"):  # a method normalised over the gallery: a stranger's claim scores higher
        click.echo("thresholds with impostors scored as strangers' claims (people not enrolled; for verify): "
                   + thresholds(strangers))
    t = m.get("timings", {})
    if t:
        click.echo(f"gallery {m['n_gallery']}, failures to enrol {m.get('failures_to_enrol', 0)}; "
                   f"preprocess {t.get('preprocess_s', 0):.1f} s ({t.get('preprocess_computed', 0)} computed, "
                   f"{t.get('preprocess_cached', 0)} cached), enrol {t.get('enrol_s', 0):.1f} s, "
                   f"match {t.get('match_s', 0):.1f} s (first use {t.get('match_first_s', 0):.1f} s; steady state "
                   f"{t.get('prepare_ms', 0):.1f} ms to prepare a probe, {t.get('match_ms', 0):.4g} ms per comparison)")
    for f in m.get("failed_scans", []):
        click.echo(f"failed ({f['role']}): {f['path']}: {f['reason']}")


_OVERWRITE_OPTION = click.option("--overwrite", is_flag=True, help="Replace the run already in --out (its files "
                                 "are removed first); without it such a folder is refused.")


def _bootstrap_options(fn):
    """--bootstrap and --seed: the 95 % intervals of every figure."""
    fn = click.option("--seed", default=0, show_default=True, help="Seed of the bootstrap draws.")(fn)
    return click.option("--bootstrap", default=1000, show_default=True, type=click.IntRange(min=0),
                        help="Bootstrap replicates (resampling probe subjects) for the 95% intervals; 0: none.")(fn)


@main.command()
@click.argument("data", type=click.Path(exists=True))
@click.option("--method", default=DEFAULT_METHOD, show_default=True,
              help="Matching method: icp, pca, lda, curvature, region-icp, keypoints, afm, morph-id, embedding, fusion.")
@click.option("--method-config", type=click.Path(exists=True, dir_okay=False),
              help="TOML or JSON file of the method's settings (its config dataclass's fields).")
@click.option("--train", type=click.Path(exists=True),
              help="Training dataset (subjects not in DATA) for learnt methods (pca, lda, an embedding adapted to "
                   "the camera).")
@click.option("--model", type=click.Path(exists=True, dir_okay=False),
              help="Saved model (a run's model.npz) instead of --method/--train.")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False), help="Run folder to write.")
@_OVERWRITE_OPTION
@click.option("--protocol", type=click.Choice(["frgc", "frgc-exp3", "bosphorus", "roles", "all-vs-all"]),
              help="Default: from the dataset (Bosphorus folder, manifest roles, else FRGC). frgc-exp3: FRGC v2 "
                   "Experiment 3, all against all over Fall 2003 + Spring 2004, under the ROC I / II / III masks.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False), help="TOML or JSON preprocessing settings.")
@_CACHE_OPTION
@_INTRINSICS_OPTION
@functools.partial(_cascade_options, screens=("depth", "embedding", "keypoints"))
@_bootstrap_options
@_engine_options
@friendly
def evaluate(data, method, method_config, train, model, out, overwrite, protocol, config_file, cache, intrinsics,
             cascade, shortlist, screen, bootstrap, seed, jobs, scheduler):
    """Evaluate a method on DATA (FRGC or Bosphorus folder, or manifest CSV): metrics, scores, plots, report."""
    from click.core import ParameterSource

    from facerec3d.config import read_settings
    from facerec3d.datasets.catalog import open_dataset
    from facerec3d.errors import InputError
    from facerec3d.evaluation.run import evaluate as run
    from facerec3d.preprocess import PreprocessConfig

    _check_cascade(cascade)
    if model and click.get_current_context().get_parameter_source("method") is ParameterSource.COMMANDLINE:
        raise InputError(f"{model}: a saved model brings its own method: give --model or --method, not both")
    _model_or_train(model, train)
    if train:
        shared = {r.subject for r in open_dataset(train).records} & {r.subject for r in open_dataset(data).records}
        if shared:
            click.echo(f"warning: {train}: {len(shared)} of its subjects (e.g. {sorted(shared)[0]}) are also in "
                       f"{data}: a model trained on the people it is tested on flatters the figures", err=True)
    config = PreprocessConfig.load(config_file) if config_file else PreprocessConfig()
    options = read_settings(method_config) if method_config else None
    m = run(data, method, out, protocol=protocol, jobs=jobs, scheduler=scheduler, cache=_cache_folder(cache),
            config=config, options=options, train=train, model=model,
            cascade=_cascade_config(cascade, shortlist, screen), intrinsics=intrinsics, bootstrap=bootstrap, seed=seed,
            overwrite=overwrite,  # an earlier run in --out is refused before any work
            echo=_to_stderr)  # what a learnt method learnt from, --train unused
    if not (m.get("n_processed") and m.get("n_gallery")):  # nothing was compared: the batch failed as a whole
        failed = m.get("failed_scans") or []
        for f in failed:
            click.echo(f"failed ({f['role']}): {f['path']}: {f['reason']}")
        click.echo(f"error: no comparison made: {m.get('n_gallery', 0)} gallery faces enrolled, "
                   f"{m.get('n_processed', 0)} probes processed, {len(failed)} scans failed (listed above and in "
                   f"{Path(out) / 'metrics.json'}: failed_scans)", err=True)
        sys.exit(1)
    _print_metrics(m)
    click.echo(f"report: {Path(out) / 'report.html'}")


def _model_or_train(model, train) -> None:
    """A saved model is trained already: with --train too, one would be silently ignored; refused before the
    training set or the data is read (trained_matcher refuses it too)."""
    if model and train:
        from facerec3d.errors import InputError

        raise InputError(f"{model}: a saved model is trained already: give --model or --train, not both")


@main.command()
@click.argument("data", nargs=-1, required=True, type=click.Path(exists=True))
@click.option("--gallery", "gallery", type=click.Path(dir_okay=False),
              help="Gallery store (SQLite file; made if missing); or --server.")
@click.option("--method", help=f"Matching method of a new gallery (as for evaluate; default {DEFAULT_METHOD}); "
              "an existing gallery's own when not given.")
@click.option("--method-config", type=click.Path(exists=True, dir_okay=False), help="TOML or JSON method settings.")
@click.option("--train", type=click.Path(exists=True),
              help="Training dataset for learnt methods (pca, lda, an embedding adapted to the camera).")
@click.option("--model", type=click.Path(exists=True, dir_okay=False), help="Saved model instead of --method/--train.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False), help="TOML or JSON preprocessing settings.")
@click.option("--subject", help="Subject of scan files whose names do not say it (default: the file stem).")
@click.option("--gallery-only", is_flag=True, help="Of a dataset, enrol only its protocol's gallery scans.")
@_CACHE_OPTION
@_INTRINSICS_OPTION
@click.option("--calibrate/--no-calibrate", default=True, show_default=True,
              help="After enrolling, calibrate the gallery's verification threshold on its own scans (FMR 1 %; "
                   "see 'gallery STORE calibrate'); a threshold calibrated on scans given for it is kept.")
@_engine_options
@_server_options
@_edge_option
@friendly
def enroll(data, gallery, method, method_config, train, model, config_file, subject, gallery_only, cache, intrinsics,
           calibrate, jobs, scheduler, server, api_key, preprocess_locally):
    """Enrol scans DATA (files, dataset folders or manifests) into the gallery store, one transaction each;
    scans that fail are recorded (failures to enrol) and the batch goes on; exit code 1 when every scan failed.
    With --server, upload them to a gallery service (--jobs at once)."""
    _local_only(server, gallery, "method", "method_config", "train", "model", "config_file", "cache", "scheduler")
    _model_or_train(model, train)
    if server:
        from facerec3d.gallery.service import scan_records

        with _edge(server, preprocess_locally):
            return _enroll_remote(server, api_key, scan_records(data, subject, gallery_only), jobs, preprocess_locally,
                                  intrinsics, calibrate)
    from tqdm import tqdm

    from facerec3d.config import read_settings
    from facerec3d.gallery.engine import Engine
    from facerec3d.gallery.service import enroll_scans, scan_records
    from facerec3d.gallery.store import GalleryStore
    from facerec3d.matching.registry import trained_matcher
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else PreprocessConfig()
    options = read_settings(method_config) if method_config else None
    records = scan_records(data, subject, gallery_only)  # bad input is one line, before the cache's first-use note
    cache = _cache_folder(cache)
    with Engine.create(jobs, scheduler, items=len(records)) as engine:
        matcher = _gallery_matcher(gallery) if method is None and not (options or train or model) else None
        if matcher is None:  # --method-config or --train without --method: the settings of the gallery's own method
            matcher, _ = trained_matcher(method or _gallery_method(gallery) or DEFAULT_METHOD, options, train=train,
                                         model=model, workers=engine, cache=cache, config=config, echo=_to_stderr)
        with GalleryStore(gallery, create=True) as store:
            store.check_writable()  # before the progress bar: a read-only store, or one a service holds, in one line
            _note_new_method(store, matcher)
            with tqdm(total=len(records), unit="scan", desc="enrolling") as bar:
                def show(source, status):
                    bar.update()
                    if status not in ("enrolled", "skipped"):
                        tqdm.write(f"{source}: failed to enrol: {status}")

                report = enroll_scans(store, records, matcher, config=config, engine=engine, cache=cache,
                                      intrinsics=intrinsics, on_result=show)
            total = store.stats()["entries"]
        if calibrate and total:
            with GalleryStore(gallery) as store:
                kept = store.threshold()
                if (report.enrolled or _stale_threshold(kept, total)) and not _keeps_given_threshold(kept, gallery,
                                                                                                      total):
                    _calibrate_threshold(store, None, 0.01, engine, cache, quiet_if_impossible=True,
                                         intrinsics=intrinsics)
    for source, subject, asked in report.elsewhere:
        click.echo(f"{source}: already enrolled as subject {subject!r}, not {asked!r} (to enrol it as {asked!r}: "
                   f"gallery {gallery} remove --entry ID, then enroll again)")
    click.echo(f"{report.enrolled} enrolled, {len(report.skipped)} already enrolled, {len(report.failures)} failed "
               f"to enrol; {gallery}: {total} entries")
    if report.failures and not report.enrolled and not report.skipped:
        sys.exit(1)  # nothing succeeded


def _note_new_method(store, matcher) -> None:
    """One line on stderr when a gallery with no entries takes another method than the one an earlier enrolment
    recorded (all its scans failed, or every entry was removed): the store takes this enrolment's settings."""
    st = store.stats()
    if not st["entries"] and st["method"] not in (None, matcher.name):
        click.echo(f"{store.path}: no entries yet: method {matcher.name} replaces {st['method']}", err=True)


def _gallery_matcher(gallery):
    """The matcher an existing, non-empty gallery store was enrolled with; None for a new or empty one."""
    from facerec3d.gallery.store import GalleryStore

    if not Path(gallery).is_file() or not Path(gallery).stat().st_size:
        return None
    with GalleryStore(gallery) as store:
        return store.matcher() if store.stats()["entries"] else None


def _gallery_method(gallery, empty: bool = False) -> str | None:
    """The method an existing gallery store was enrolled with (one with no entries too when `empty`; enroll gives
    an empty one another method, serve checks it); None for a new one. A --method-config given without --method
    is that method's settings, not the default method's."""
    from facerec3d.gallery.store import GalleryStore

    if not Path(gallery).is_file() or not Path(gallery).stat().st_size:
        return None
    with GalleryStore(gallery) as store:
        st = store.stats()
        return st["method"] if st["entries"] or empty else None


@main.command()
@click.argument("probe", type=click.Path(exists=True, dir_okay=False))
@click.option("--gallery", "gallery", type=click.Path(dir_okay=False), help="Gallery store (or --server).")
@click.option("-k", "k", default=5, show_default=True, type=click.IntRange(min=1), help="Number of candidates to list.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False),
              help="Preprocessing settings; must be the gallery's (default: the gallery's).")
@_CACHE_OPTION
@_INTRINSICS_OPTION
@_cascade_options
@_engine_options
@_server_options
@_edge_option
@friendly
def identify(probe, gallery, k, config_file, cache, intrinsics, cascade, shortlist, screen, jobs, scheduler, server,
             api_key, preprocess_locally):
    """The k gallery entries most like scan PROBE, best first (rank, subject, scan, score)."""
    _local_only(server, gallery, "config_file", "cache", "jobs", "scheduler")
    _check_cascade(cascade)
    if server:
        with _edge(server, preprocess_locally), _client(server, api_key) as client:
            answer = client.identify(probe, k, cascade, shortlist, preprocess_locally=preprocess_locally,
                                     screen=screen, intrinsics=intrinsics)
        click.echo(f"{'rank':>4}  {'subject':<12}{'scan':<20}{'score':>12}")
        for c in answer["candidates"]:
            click.echo(f"{c['rank']:>4}  {str(c['subject']):<12}{str(c['scan_id']):<20}{c['score']:>12.4f}")
        return
    from facerec3d.gallery.engine import Engine
    from facerec3d.gallery.service import identify_scan
    from facerec3d.gallery.store import GalleryStore
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else None
    with one_blas_thread(), GalleryStore(gallery) as store, \
            Engine.create(jobs, scheduler, items=len(store.entries())) as engine:  # a shard per entry at most
        hits = identify_scan(store, probe, k=k, cascade=_cascade_config(cascade, shortlist, screen), config=config,
                             engine=engine, cache=_cache_folder(cache), intrinsics=intrinsics)
    click.echo(f"{'rank':>4}  {'subject':<12}{'scan':<20}{'score':>12}")
    for r, (entry, score) in enumerate(hits, start=1):
        click.echo(f"{r:>4}  {str(entry.subject):<12}{str(entry.scan_id):<20}{score:>12.4f}")


def _default_thresholds() -> str:
    """The methods' default verification thresholds as `verify --help` names them, from config.DEFAULT_THRESHOLDS
    (ICP's score is a −MSE, in mm²)."""
    return ", ".join(f"{m} {float(v)!r}{' mm²' if m == 'icp' else ''}" for m, v in DEFAULT_THRESHOLDS.items())


@main.command()
@click.argument("probe", type=click.Path(exists=True, dir_okay=False))
@click.option("--gallery", "gallery", type=click.Path(dir_okay=False), help="Gallery store (or --server).")
@click.option("--claim", required=True, help="The claimed subject ID.")
@click.option("--threshold", type=float, callback=lambda ctx, param, v: _finite(v, "--threshold"),
              help="Accept scores >= this (default: the gallery's calibrated threshold, see 'gallery STORE "
              f"calibrate'; else the method's default: {_default_thresholds()}; other methods need one calibrated).")
@click.option("--config", "config_file", type=click.Path(dir_okay=False),
              help="Preprocessing settings; must be the gallery's (default: the gallery's).")
@_CACHE_OPTION
@_INTRINSICS_OPTION
@_server_options
@_edge_option
@friendly
def verify(probe, gallery, claim, threshold, config_file, cache, intrinsics, server, api_key, preprocess_locally):
    """Is scan PROBE the claimed subject? Prints accept/reject with the score; exit code 0 accept, 1 reject."""
    _local_only(server, gallery, "config_file", "cache")
    if server:
        with _edge(server, preprocess_locally), _client(server, api_key) as client:
            answer = client.verify(probe, claim, threshold, preprocess_locally=preprocess_locally,
                                   intrinsics=intrinsics)
        expected = answer.get("expected_fmr")
        hint = _few_pairs_hint(expected, f"--server {server}") if isinstance(expected, (int, float)) else None
        accepted, score, threshold = answer["accepted"], answer["score"], answer["threshold"]
        score = float("nan") if score is None else score
        click.echo(f"{'accept' if accepted else 'reject'}: claim {claim}, score {score:.4f} "
                   f"(threshold {threshold_text(threshold)})")
        if hint:
            click.echo(hint, err=True)
        sys.exit(0 if accepted else 1)
    from facerec3d.evaluation.calibrate import too_few_pairs
    from facerec3d.gallery.service import verify_scan
    from facerec3d.gallery.store import GalleryStore
    from facerec3d.preprocess import PreprocessConfig

    config = PreprocessConfig.load(config_file) if config_file else None
    given = threshold is not None
    with one_blas_thread(), GalleryStore(gallery) as store:
        accepted, score, threshold = verify_scan(store, probe, claim, threshold=threshold, config=config,
                                                 cache=_cache_folder(cache), intrinsics=intrinsics)
        record = None if given else store.threshold()
        hint = None if given else (_few_pairs_hint(too_few_pairs(record), gallery, record.get("impostor_pairs"))
                                   if record is not None else _threshold_hint(store, claim, threshold))
        if store.stats()["subjects"] < 2 and (matcher := store.matcher()).cohort_scores:
            hint = (f"hint: method {matcher.name!r} normalises each probe's scores over the gallery's people, and "
                    "this gallery holds one: every claim scores 0. Enrol more people, or enrol this one with "
                    "--method icp")
    click.echo(f"{'accept' if accepted else 'reject'}: claim {claim}, score {score:.4f} "
               f"(threshold {threshold_text(threshold)})")
    if hint:
        click.echo(hint, err=True)
    sys.exit(0 if accepted else 1)


#: The sampling (mm) of the scans the default verification thresholds were chosen on: FRGC-like laser scans,
#: whose faces ICP matches at their 1 mm grid. A gallery matched at a coarser resolution (a depth camera's)
#: scores its genuine comparisons lower, and the default threshold then rejects most of them.
DEFAULT_THRESHOLD_RESOLUTION_MM = 1.5


def _threshold_hint(store, claim: str, threshold: float) -> str | None:
    """A hint when the default threshold does not suit the claimed subject's templates: ICP templates record the
    resolution they are matched at (`resolution`, mm), coarser than the laser scans the default was chosen on."""
    resolutions = [t.attrs.get("resolution") for t in store.templates(store.entries(subject=claim))]
    resolutions = [float(r) for r in resolutions if isinstance(r, (int, float))]
    if not resolutions or max(resolutions) <= DEFAULT_THRESHOLD_RESOLUTION_MM:
        return None
    return (f"hint: the default threshold {threshold_text(threshold)} was chosen on laser scans matched at 1 mm; this "
            f"gallery's faces are matched at {max(resolutions):.1f} mm (a depth camera's), where genuine scores are "
            "lower: calibrate the gallery's own ('facerec3d gallery STORE calibrate SCANS') or choose --threshold "
            "from an evaluation on this sensor's scans (metrics.json: threshold_at_eer, threshold_at_far_0.001; see "
            "the depth-camera quick start in the docs)")


class _GalleryGroup(click.Group):
    """`gallery STORE CMD`, or `gallery --server URL CMD` without STORE. Its help ends naming every command, those
    defined after the group too (a hand-written list missed calibrate and rekey)."""

    @property
    def help(self) -> str | None:
        return self._help and f"{self._help.rstrip('.')}: {', '.join(self.commands)}."

    @help.setter
    def help(self, text: str | None) -> None:
        self._help = text

    def parse_args(self, ctx, args):
        args, i = list(args), 0
        while i < len(args) and args[i].startswith("-"):  # the group's options: --server URL, --api-key KEY
            i += 1 if "=" in args[i] or args[i] == "--help" else 2
        if i < len(args) and args[i] in self.commands:
            args.insert(i, "")  # no STORE
        ctx.meta["facerec3d.help"] = "--help" in args[i:]  # a command's --help needs no store
        return super().parse_args(ctx, args)


@main.group(cls=_GalleryGroup)
@click.argument("store", required=False, type=click.Path(dir_okay=False))
@_server_options
@click.pass_context
def gallery(ctx, store, server, api_key):
    """Look after the gallery store STORE (or the gallery service --server URL)."""
    if bool(store) == bool(server) and not ctx.meta.get("facerec3d.help"):
        raise click.UsageError("give the gallery store STORE or --server URL" + (", not both" if store else "."))
    ctx.obj = store
    ctx.meta["facerec3d.server"] = (server, api_key)


def _service_side_only(*names) -> None:
    """With `gallery --server`: refuse the options NAMES of the command that were given (they are the service's)."""
    from click.core import ParameterSource

    ctx = click.get_current_context()
    opts = {p.name: p.opts[0] for p in ctx.command.params}
    given = [opts[n] for n in names if ctx.get_parameter_source(n) not in (None, ParameterSource.DEFAULT)]
    if given:
        raise click.UsageError(f"{', '.join(given)} cannot be used with --server (the service has its own).")


def _remote_gallery():
    """A client of the service `gallery --server URL` names, or None for a local store."""
    server, api_key = click.get_current_context().meta["facerec3d.server"]
    return _client(server, api_key) if server else None


@gallery.command("list")
@click.pass_obj
@friendly
def gallery_list(store):
    """The enrolled entries (id, subject, scan, source) and the failures to enrol."""
    if (client := _remote_gallery()) is not None:
        with client:
            listed = client.entries()
        for e in listed["entries"]:
            click.echo(f"{e['id']}\t{e['subject']}\t{e['scan_id']}\t{e['source']}")
        for f in listed["failures"]:
            click.echo(f"failed\t{f['source']}\t{f['reason']}")
        return
    from facerec3d.gallery.store import GalleryStore

    with GalleryStore(store) as s:
        for e in s.entries():
            click.echo(f"{e.id}\t{e.subject}\t{e.scan_id}\t{e.source}")
        for source, reason in s.failures():
            click.echo(f"failed\t{source}\t{reason}")


@gallery.command("remove")
@click.argument("ident", required=False)
@click.option("--entry", type=int, help="Remove only the entry of this id (the first column of `gallery G list`).")
@click.pass_obj
@friendly
def gallery_remove(store, ident, entry):
    """Remove subject IDENT's entries (or else the entry of scan IDENT, when one subject has it), or one entry by its
    id (--entry)."""
    from facerec3d.errors import InputError
    from facerec3d.gallery.store import GalleryError, GalleryStore

    if (ident is None) == (entry is None):
        raise InputError("gallery remove: give a subject or scan id, or --entry ID (not both)")
    if (client := _remote_gallery()) is not None:
        with client:
            n = len((client.remove(ident) if entry is None else client.remove_entry(entry))["removed"])
        click.echo(f"removed {n} entr{'y' if n == 1 else 'ies'}")
        return
    with GalleryStore(store) as s:
        n = s.remove(ident, entry)
    if not n:
        raise GalleryError(f"{store}: no entry {entry}" if entry is not None else
                           f"{store}: no subject or scan {ident!r}")
    click.echo(f"removed {n} entr{'y' if n == 1 else 'ies'}")


def _calibrate_threshold(store, records, fmr, engine, cache, quiet_if_impossible=False, intrinsics=None) -> None:
    """Calibrate and record the store's verification threshold (depth frames read with `intrinsics` when given);
    print what was recorded."""
    from facerec3d.evaluation.calibrate import calibrate
    from facerec3d.gallery.store import GalleryError

    try:
        r = calibrate(store, records, fmr=fmr, engine=engine, cache=cache, intrinsics=intrinsics)
    except GalleryError as e:
        if not quiet_if_impossible:
            raise
        click.echo(f"verification threshold not calibrated: {e}")
        return
    click.echo(_threshold_line(r, store.path))


def _threshold_line(r: dict, where) -> str:
    """What a calibration recorded, in one line: the threshold, its rule and pairs, its data and where."""
    extra = f", TAR {r['tar']:.1%} on {r['genuine_pairs']} genuine pairs" if "tar" in r else ""
    failed = f", {r['failed_scans']} of {r['scans']} scans unusable" if r.get("failed_scans") else ""
    expected = (f", {r['expected_fmr']:.1%} to expect of strangers' claims" if "expected_fmr" in r else "")
    return (f"verification threshold {threshold_text(r['value'])} ({r['rule']}: FMR {r['fmr']:.2%} on "
            f"{r['impostor_pairs']} impostor pairs{expected}{extra}; {r['data']}{failed}) recorded in {where}")


def _few_pairs_hint(expected: float | None, where, pairs: int | None = None) -> str | None:
    """A hint when the gallery's calibrated threshold rests on too few impostor pairs for its false-match rate
    (`evaluation.calibrate.too_few_pairs`: the rate `expected` of strangers' claims), and what to do; None without."""
    if expected is None:
        return None
    on = f"on {pairs} impostor pairs, " if pairs is not None else "on "
    return (f"hint: the gallery's threshold was calibrated {on}too few for its false-match rate: about "
            f"{expected:.0%} of strangers' claims are accepted. Calibrate it on scans of more people, enrolled or "
            f"not: facerec3d gallery {where} calibrate SCANS")


@gallery.command("calibrate")
@click.argument("data", nargs=-1, type=click.Path(exists=True))
@click.option("--fmr", type=click.FloatRange(0.0, 1.0, min_open=True), default=0.01, show_default=True,
              callback=lambda ctx, param, v: _finite(v, "--fmr"),
              help="False-match rate the threshold keeps.")
@click.option("--eer", is_flag=True, help="Threshold at the equal error rate instead (needs two scans of some "
              "subjects).")
@click.option("--subject", help="Subject of scan files whose names do not say it.")
@_CACHE_OPTION
@_INTRINSICS_OPTION
@_engine_options
@click.pass_obj
@friendly
def gallery_calibrate(store, data, fmr, eer, subject, cache, intrinsics, jobs, scheduler):
    """Calibrate the verification threshold of STORE on labelled scans DATA of its own sensor (files, dataset
    folders or manifests; default: the scans it was enrolled from) and record it: verify and the service use it
    whenever no threshold is given. Depth frames enrolled with --intrinsics need it here too. With --server, the
    service's gallery on DATA, sent to it (it keeps no scans); needs an admin key."""
    from facerec3d.evaluation.calibrate import calibration_selection
    from facerec3d.gallery.engine import Engine
    from facerec3d.gallery.service import scan_records
    from facerec3d.gallery.store import GalleryStore

    if eer and _given("fmr"):
        raise click.UsageError("--fmr cannot be used with --eer (the threshold is at the equal error rate, not at a "
                               "false-match rate).")
    if (client := _remote_gallery()) is not None:
        _service_side_only("cache", "jobs", "scheduler")
        if not data:
            raise click.UsageError("with --server, give the scans DATA to calibrate on (the service keeps no scans)")
        records = calibration_selection(scan_records(data, subject))
        with client:
            _calibrate_remote(client, client.stats(), [r.path for r in records], [r.subject for r in records],
                              None if eer else fmr, intrinsics=intrinsics)
        return
    records = scan_records(data, subject) if data else None
    with Engine.create(jobs, scheduler) as engine, GalleryStore(store) as s:
        _calibrate_threshold(s, records, None if eer else fmr, engine, _cache_folder(cache), intrinsics=intrinsics)


@gallery.command("stats")
@click.pass_obj
@friendly
def gallery_stats(store):
    """Entries, subjects, sizes, failures to enrol and the matcher."""
    if (client := _remote_gallery()) is not None:
        with client:
            st = client.stats()
    else:
        from facerec3d.gallery.store import GalleryStore

        with GalleryStore(store) as s:
            st = s.stats()
    click.echo(f"{st['entries']} entries of {st['subjects']} subjects; "
               f"templates {st['template_bytes'] / 2**20:.1f} MiB, "
               f"file {st['file_bytes'] / 2**20:.1f} MiB; {st['failures_to_enrol']} failures to enrol; "
               f"method {st['method']} {st['options']}")
    if (t := st.get("threshold")) is not None:
        from facerec3d.evaluation.calibrate import too_few_pairs

        few = too_few_pairs(t)
        few = f"; too few impostor pairs: about {few:.0%} of strangers' claims to expect" if few else ""
        click.echo(f"verification threshold {threshold_text(t['value'])} ({t.get('rule')}, {t.get('data')}, "
                   f"{t.get('entries')} entries, {t.get('calibrated_at')}{few})")


@gallery.command("rekey")
@click.option("--new-key-file", required=True, type=click.Path(dir_okay=False),
              help="The new key (64 hex digits); a new random key is written there (mode 0600) if the file is missing.")
@click.pass_obj
@friendly
def gallery_rekey(store, new_key_file):
    """Encrypt the stored templates under a new key (AES-256-GCM), or encrypt a clear gallery; the old key comes
    from FACEREC3D_GALLERY_KEY_FILE or FACEREC3D_GALLERY_KEY. Stop a service on the gallery first."""
    from facerec3d.gallery.store import KEY_FILE_ENV, GalleryError, GalleryStore, TemplateKey

    if _remote_gallery() is not None:
        raise click.UsageError("rekey works on a gallery store file, not --server")
    made = not os.path.exists(new_key_file)
    new = TemplateKey.make(new_key_file) if made else TemplateKey.load(new_key_file)
    s = None
    try:
        with GalleryStore(store) as s:
            if s.key is not None and s.key.check == new.check:
                raise GalleryError(f"{new_key_file}: this is the gallery's key already")
            n = s.rekey(new)
    except BaseException:
        # A key made for a rekey that failed (no store, the old key missing or wrong) is removed: it encrypts
        # nothing. Not once the store took it (rekey commits, then rewrites the file): then it is the only key.
        if made and (s is None or s.key is not new):
            Path(new_key_file).unlink(missing_ok=True)
        raise
    click.echo(f"{store}: {n} arrays encrypted under the key in {new_key_file}; from now on give "
               f"{KEY_FILE_ENV}={new_key_file}")


@main.command("train-nose")
@click.argument("out", type=click.Path(dir_okay=False))
@click.option("--samples", default=7000, show_default=True, type=click.IntRange(min=100),
              help="Synthetic scans (any sensor profile, pose, occluder) to learn from.")
@click.option("--epochs", default=10, show_default=True, type=click.IntRange(min=1))
@click.option("--seed", default=0, show_default=True, help="Seed of the network's initialisation and batches.")
@click.option("--data-seed", default=1, show_default=True, help="Seed of the synthetic scans.")
@click.option("--trainset", type=click.Path(dir_okay=False),
              help="File keeping the training samples, reused when it holds as many [default: OUT with "
                   ".trainset.npz].")
@click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores", type=click.IntRange(min=1),
              callback=_capped_jobs,
              help="Processes making the samples; torch trains on as many threads.")
@friendly
def train_nose(out, samples, epochs, seed, data_seed, trainset, jobs):
    """Train the nose proposer ([detect] proposer, docs/methods.md) on synthetic scans and write OUT (ONNX) and its
    card (OUT with .json). Needs the [train] extra (PyTorch); using it never does."""
    import numpy as np

    from facerec3d.training.nose import export, train_nose as train
    from facerec3d.training.nose_data import training_samples
    from facerec3d.workers import Workers

    out = Path(out)
    keep = Path(trainset or out.with_suffix(".trainset.npz"))
    data = None
    if keep.is_file():
        try:
            with np.load(keep, allow_pickle=False) as d:
                if int(d["data_seed"]) == data_seed and int(d["requested"]) == samples:
                    data = d["maps"], d["noses"]
        except (OSError, ValueError, KeyError) as e:
            click.echo(f"{keep}: not a training-sample file ({e}); making the samples again", err=True)
    if data is None:
        with Workers.create(jobs) as workers:
            data = training_samples(samples, data_seed, workers)
        with open(keep, "wb") as f:
            np.savez(f, maps=data[0], noses=data[1], data_seed=data_seed, requested=samples)
    click.echo(f"training samples: {len(data[0])} of {samples} scans ({keep})")
    net, figures = train(data[0].astype(np.float32), data[1], epochs=epochs, seed=seed, threads=jobs,
                         log=lambda line: click.echo(line))
    path = export(net, out, {"command": " ".join(["facerec3d", *sys.argv[1:]]), "samples": int(len(data[0])),
                             "data_seed": data_seed, "seed": seed, "epochs": epochs, **figures})
    click.echo(f"model: {path} (card {path.with_suffix('.json')})")


@main.command("train-embedding")
@click.argument("out", type=click.Path(dir_okay=False))
@click.option("--identities", default=1200, show_default=True, type=click.IntRange(min=2),
              help="Synthetic identities (faces no test or benchmark uses).")
@click.option("--scans", default=6, show_default=True, type=click.IntRange(min=2), help="Scans per identity.")
@click.option("--sensors", default="frgc,kinect-v2,kinect-v2-8bit,realsense", show_default=True,
              help="Sensor profiles, drawn per scan (comma-separated).")
@click.option("--identity-profiles", default="model,outside-model", show_default=True,
              help="Identity profiles, taken in turn by identity: the model's faces and faces outside its span.")
@click.option("--epochs", default=40, show_default=True, type=click.IntRange(min=1))
@click.option("--width", default=24, show_default=True, type=click.IntRange(min=4),
              help="Channels of the network's first block (doubling per block).")
@click.option("--seed", default=0, show_default=True, help="Seed of the network's initialisation and batches.")
@click.option("--data-seed", default=2026, show_default=True, help="Seed of the synthetic faces, poses and sensors.")
@click.option("--max-yaw", default=45.0, show_default=True, type=click.FloatRange(0, 90),
              help="Head turns drawn up to this many degrees left or right.")
@click.option("--max-pitch", default=20.0, show_default=True, type=click.FloatRange(0, 60),
              help="Heads tilted up to this many degrees up or down.")
@click.option("--terraces", default=0.0, show_default=True, type=click.FloatRange(0, 1),
              help="Share of the training windows given the ripple of coarse depth steps (augmentation).")
@click.option("--trainset", type=click.Path(dir_okay=False),
              help="File keeping the preprocessed training faces, reused when its recipe is the same "
                   "[default: OUT with .trainset.npz].")
@click.option("--real", type=click.Path(exists=True),
              help="A dataset of real scans whose people are added as identities (fine-tuning on real faces).")
@click.option("--real-subjects", help="Of --real, only these subjects: a file with one per line, or 'even' / 'odd' "
              "(every other subject in sorted order, as benchmarks/real_bench.py's tuning / held-out halves).")
@click.option("--init", "init", type=click.Path(exists=True, dir_okay=False),
              help="Start from a model's weights (MODEL.weights.npz, written beside every model).")
@_CACHE_OPTION
@click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores", type=click.IntRange(min=1),
              callback=_capped_jobs,
              help="Processes making the training faces; torch trains on as many threads.")
@friendly
def train_embedding(out, identities, scans, sensors, identity_profiles, epochs, width, seed, data_seed, max_yaw,
                    max_pitch, terraces, trainset, real, real_subjects, init, cache, jobs):
    """Train the learned embedding on synthetic faces (and --real people) and write OUT (ONNX), its card
    (OUT with .json) and weights (.weights.npz). Needs the [train] extra (PyTorch); using a model never does:
    --method embedding with the method setting model = "OUT"."""
    import dataclasses
    import json

    from facerec3d.matching.embedding import InputRecipe
    from facerec3d.training.data import DataRecipe, cached_training_set, real_training_set
    from facerec3d.training.embedding import TrainConfig, export, train_embedding as train
    from facerec3d.workers import Workers

    try:
        recipe = DataRecipe(identities, scans, tuple(s for s in sensors.split(",") if s),
                            tuple(s for s in identity_profiles.split(",") if s), data_seed, max_yaw, max_pitch)
    except ValueError as e:
        raise click.BadParameter(str(e)) from None
    inputs = InputRecipe()
    out = Path(out)
    with Workers.create(jobs) as workers:
        data = cached_training_set(trainset or out.with_suffix(".trainset.npz"), recipe, inputs, workers)
        click.echo(f"training faces: {data.info['scans']} of {identities} identities "
                   f"({data.info['failures']} failed to preprocess)")
        if real:
            extra = real_training_set(real, real_subjects, inputs, recipe.margin, workers, _cache_folder(cache),
                                      first_label=int(data.labels.max()) + 1)
            click.echo(f"real faces: {extra.info['scans']} of {extra.info['subjects']} people "
                       f"({extra.info['failures']} failed to preprocess)")
            data = data.joined(extra)
    config = TrainConfig(width=width, epochs=epochs, seed=seed, threads=max(1, jobs), terraces=terraces)
    net, figures = train(data.windows, data.labels, inputs, recipe.margin, config, init=init)
    path = export(net, out, inputs, {"command": " ".join(["facerec3d", *sys.argv[1:]]), "data": data.info,
                                     "train": dataclasses.asdict(config),
                                     "loss": f"CosFace (s = {config.scale:g}, m = {config.margin:g})",
                                     "final_loss": figures["final_loss"], "figures": figures,
                                     "validation": figures.get("validation", {})})
    click.echo(f"model: {path} (card {path.with_suffix('.json')}); validation "
               f"{json.dumps(figures.get('validation', {}))}")


@main.command()
@click.option("--gallery", "gallery", required=True, type=click.Path(dir_okay=False),
              help="Gallery store (SQLite file; made if missing, with --method and --config).")
@click.option("--keys", "keys_file", required=True, type=click.Path(dir_okay=False),
              help="API key file (facerec3d keys add); re-read when it changes.")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; loopback by default (other addresses expose the service: use TLS).")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(0, 65535),
              help="Port to listen on (0: a free one, which the first line names).")
@_engine_options
@click.option("--method", help=f"Matching method of a new gallery (default {DEFAULT_METHOD}); an existing gallery's is "
              "checked.")
@click.option("--method-config", type=click.Path(exists=True, dir_okay=False), help="TOML or JSON method settings.")
@click.option("--config", "config_file", type=click.Path(dir_okay=False),
              help="Preprocessing settings of a new gallery; an existing gallery's are checked.")
@click.option("--concurrency", type=click.IntRange(min=1), help="Requests worked on at once [default: 2 per worker].")
@click.option("--queue", default=32, show_default=True, type=click.IntRange(min=0),
              help="Requests that may wait beyond those; more get 503.")
@click.option("--per-key", type=click.IntRange(min=1), help="Requests one key may have queued or running; more get "
              "429 [default: half of concurrency + queue].")
@click.option("--timeout", default=60.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
              callback=lambda ctx, param, v: _finite(v, "--timeout"), help="Time limit per request (s); past it, 504.")
@click.option("--max-upload-mb", default=64.0, show_default=True, type=click.FloatRange(min=0.01),
              callback=lambda ctx, param, v: _finite(v, "--max-upload-mb"),
              help="Largest upload (MiB, at least 0.01: a form's own parts take ~4 KiB); larger get 413.")
@click.option("--max-points", default=4_000_000, show_default=True, type=click.IntRange(min=1, max=4_000_000),
              help="Largest scan (points; at most 4,000,000, the most any reader takes: io.common.MAX_POINTS); "
                   "larger get 413.")
@click.option("--audit", type=click.Path(dir_okay=False),
              help="Audit log, JSON lines (who enrolled or removed what, when) [default: GALLERY.audit.jsonl].")
@click.option("--ssl-certfile", type=click.Path(exists=True, dir_okay=False), help="TLS certificate (PEM).")
@click.option("--ssl-keyfile", type=click.Path(exists=True, dir_okay=False), help="TLS private key (PEM).")
@friendly
def serve(gallery, keys_file, host, port, jobs, scheduler, method, method_config, config_file, concurrency, queue,
          per_key, timeout, max_upload_mb, max_points, audit, ssl_certfile, ssl_keyfile):
    """Serve the gallery over HTTP: enrol, identify, verify, list and remove subjects, stats, health, metrics
    (OpenAPI at /docs). The gallery is loaded once into the worker processes and updated in place; every
    enrolment is committed before it is acknowledged. Needs: pip install 'facerec3d[service]'."""
    import ipaddress

    try:
        from facerec3d.server.app import ServiceSettings, serve as run
    except ImportError as e:
        raise FaceRec3DError(f"serve: the service needs FastAPI and uvicorn ({e}): pip install -e \".[service]\" "
                             "(or pip install 'facerec3d[service]')") from None
    from facerec3d.config import read_settings
    from facerec3d.preprocess import PreprocessConfig

    if bool(ssl_certfile) != bool(ssl_keyfile):
        raise click.UsageError("TLS needs both --ssl-certfile and --ssl-keyfile (" +
                               ("--ssl-keyfile is missing)" if ssl_certfile else "--ssl-certfile is missing)"))
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if not loopback and not ssl_certfile:
        click.echo(f"warning: listening on {host} without TLS: API keys and scans cross the network in clear text",
                   err=True)
    workers = 1 if scheduler is None and (jobs or 1) <= 1 else (jobs or os.cpu_count() or 1)
    settings = ServiceSettings(concurrency=concurrency or 2 * workers, queue=queue, per_key=per_key,
                               timeout_s=timeout, max_upload_bytes=int(max_upload_mb * 2**20))
    if method is None and method_config:  # the settings of the gallery's own method, checked against its options
        method = _gallery_method(gallery, empty=True)
    run(gallery, keys_file, host, port, jobs, scheduler, method,
        read_settings(method_config) if method_config else None,
        PreprocessConfig.load(config_file) if config_file else None, settings, max_points, audit,
        ssl_certfile, ssl_keyfile, echo=_to_stderr)


@main.group()
def keys():
    """API keys of the gallery service (facerec3d serve --keys FILE): add, list, remove."""


@keys.command("add")
@click.argument("name")
@click.option("--scopes", required=True, help="Comma-separated: enrol (add scans), query (identify, verify), "
              "admin (list and remove subjects, metrics).")
@click.option("--keys", "keys_file", required=True, type=click.Path(dir_okay=False), help="Key file (made if missing).")
@friendly
def keys_add(name, scopes, keys_file):
    """Make a key NAME and print it, once: only its hash is stored."""
    from facerec3d.server.keys import add_key, parse_scopes

    key = add_key(keys_file, name, scopes)
    click.echo(key)
    click.echo(f"key {name!r} ({', '.join(parse_scopes(scopes))}) added to {keys_file}; it is shown only this once",
               err=True)


@keys.command("list")
@click.option("--keys", "keys_file", required=True, type=click.Path(dir_okay=False), help="Key file.")
@friendly
def keys_list(keys_file):
    """The keys' names, scopes and creation times (the keys themselves are not stored)."""
    from facerec3d.server.keys import read_keys

    for k in read_keys(keys_file):
        click.echo(f"{k['name']}\t{','.join(k['scopes'])}\t{k.get('created', '')}")


@keys.command("remove")
@click.argument("name")
@click.option("--keys", "keys_file", required=True, type=click.Path(dir_okay=False), help="Key file.")
@friendly
def keys_remove(name, keys_file):
    """Revoke key NAME (a running service stops taking it at its next request)."""
    from facerec3d.server.keys import remove_key

    remove_key(keys_file, name)
    click.echo(f"removed key {name!r}")


@main.group()
def cache():
    """The preprocessing cache: faces already preprocessed, reused by evaluate, enroll, identify and verify (keyed
    by file path, size, modification time, the settings and the preprocessing code, so a changed file, setting or
    facerec3d version is computed again)."""


_CACHE_DIR_OPTION = click.option("--cache", "folder", type=click.Path(file_okay=False),
                                 help="The cache folder [default: the user's, shown by info].")


def _cache_contents(folder: str | None) -> tuple[Path, list[Path], int]:
    """(the cache folder: --cache or the default, its entries, their bytes)."""
    from facerec3d.preprocess.batch import DEFAULT_CACHE, cache_entries

    folder = Path(folder) if folder else DEFAULT_CACHE
    entries = cache_entries(folder)
    return folder, entries, sum(p.stat().st_size for p in entries)


@cache.command("info")
@_CACHE_DIR_OPTION
@friendly
def cache_info(folder):
    """Where the cache is, how many faces and failures it holds and its size."""
    folder, entries, size = _cache_contents(folder)
    faces = sum(p.suffix == ".npz" for p in entries)
    click.echo(f"{folder}{'' if folder.is_dir() else ' (not made yet)'}: {faces} faces, {len(entries) - faces} "
               f"failures, {size / 2**20:.1f} MiB")


@cache.command("clear")
@_CACHE_DIR_OPTION
@friendly
def cache_clear(folder):
    """Remove the cache's entries (other files in the folder stay)."""
    folder, entries, size = _cache_contents(folder)
    for path in entries:
        path.unlink(missing_ok=True)
    click.echo(f"removed {len(entries)} entries ({size / 2**20:.1f} MiB) from {folder}")


@main.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--out", "out", default="compare", show_default=True, type=click.Path(file_okay=False))
@click.option("--overwrite", is_flag=True, help="Replace the comparison already in --out (its files are removed "
              "first); without it such a folder is refused.")
@friendly
def compare(runs, out, overwrite):
    """Overlay several evaluation runs' ROC, DET and CMC curves, tabulate their figures with 95% intervals, and
    test each pair's rank-1 on the same probes (McNemar)."""
    from facerec3d.evaluation.compare import compare_runs

    result = compare_runs(list(runs), out, overwrite)
    for t in result["mcnemar"]:
        if not t["n"]:
            click.echo(f"rank-1: {t['a']} and {t['b']} share no probe (runs on other data): no McNemar test")
            continue
        verdict = "differ" if t["differ"] else "do not differ significantly"
        click.echo(f"rank-1, McNemar on {t['n']} probes: {t['a']} and {t['b']} {verdict} (p = {t['p']:.3g}; "
                   f"{t['a_only']} vs {t['b_only']} discordant hits)")
    click.echo(f"wrote {Path(out) / 'compare.html'}")


@main.command()
@click.argument("scores", type=click.Path(exists=True, dir_okay=False))
@click.option("--format", "fmt", type=click.Choice(["bob4", "bob5", "csv"]), default="bob4", show_default=True,
              help="bob4: claimed_id real_id probe_label score; bob5: claimed_id model_label real_id probe_label "
                   "score; csv: bob 5's CSV (probe_subject_id, probe_template_id, bio_ref_subject_id, score, ...).")
@click.option("--higher-is-better/--lower-is-better", default=True, show_default=True,
              help="Scores are similarities, or distances (negated).")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False), help="Run folder to write.")
@_OVERWRITE_OPTION
@_bootstrap_options
@friendly
def metrics(scores, fmt, higher_is_better, out, overwrite, bootstrap, seed):
    """Every figure, plot and report of an evaluation from SCORES, a score file written by any system."""
    import hashlib

    from facerec3d.evaluation.metrics import mates_not_compared
    from facerec3d.evaluation.provenance import provenance
    from facerec3d.evaluation.report import run_folder, write_run
    from facerec3d.evaluation.scorefile import read_score_matrix

    m = read_score_matrix(scores, fmt, higher_is_better)
    source = Path(scores).resolve()
    rerun = ["facerec3d", "metrics", source, "--format", fmt,
             "--higher-is-better" if higher_is_better else "--lower-is-better", "--out", Path(out).resolve(),
             "--bootstrap", bootstrap, "--seed", seed]
    info = {"scores": str(source), "scores_sha256": hashlib.sha256(source.read_bytes()).hexdigest(), "format": fmt,
            "score_direction": "higher is better" if higher_is_better else
            "lower is better: negated, so every threshold below is minus the distance (a distance <= -t accepts)",
            "n_gallery": int(m.S.shape[1]), "provenance": provenance(rerun)}
    with run_folder(out, overwrite, keep=[scores]) as work:
        result = write_run(work, m.S, m.probe_ids, m.probe_labels, m.gallery_ids, info, bootstrap=bootstrap,
                           seed=seed, mateless=mates_not_compared(m.S, m.probe_ids, m.gallery_ids))
    _print_metrics(result, negated=not higher_is_better)
    click.echo(f"report: {Path(out) / 'report.html'}")


@main.command()
@click.argument("scores", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="Score file to write (bob4: claimed_id real_id probe_label score).")
@click.option("--format", "fmt", type=click.Choice(["bob4", "bob5", "csv"]), default="bob4", show_default=True,
              help="Format of the SCORES files (as `metrics` reads them); all similarities.")
@click.option("--normalisation", default="z-score", show_default=True,
              help="Per-probe normalisation over the gallery: none, min-max, z-score, tanh, tanh-hampel.")
@click.option("--rule", default="sum", show_default=True, help="sum, product, weighted-sum, borda or consensus.")
@click.option("--weights", default="", help="Comma-separated, one per file, for --rule weighted-sum (e.g. 2,1,1).")
@click.option("--top", default=0, show_default=True, help="borda / consensus: points only for each file's TOP best.")
@click.option("--cohort", default=0.0, show_default=True, type=click.FloatRange(0, 1),
              help="Share of the best other person's fused score taken off each (the fusion method's `cohort`; 0: "
                   "the plain combination). Moves no rank.")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists; without it an existing file is refused.")
@friendly
def fuse(scores, out, fmt, normalisation, rule, weights, top, cohort, overwrite):
    """Fuse several systems' score files (SCORES, two or more) into one, as the `fusion` method fuses its members
    (chapter §8.10): each probe's scores normalised over the gallery, then combined; evaluate it with `metrics`."""
    from facerec3d.errors import InputError, SettingsError
    from facerec3d.evaluation.scorefile import fuse_score_files, strangers_file, write_scores

    try:
        w = tuple(float(x) for x in weights.split(",")) if weights.strip() else ()
    except ValueError:
        raise InputError(f"--weights {weights!r}: not comma-separated numbers") from None
    side = strangers_file(out)
    if (Path(out).exists() or side.exists()) and not overwrite:
        raise InputError(f"{out if Path(out).exists() else side}: exists; give --overwrite to replace it")
    try:
        m, left_out, st = fuse_score_files(list(scores), fmt, rule, normalisation, w, top, cohort)
    except SettingsError as e:  # a weight or --top out of range: named as the option
        raise InputError(f"--{e.field}: {e.reason}") from None
    for path, matrix in ((side, st), (Path(out), m)):
        partial = path.with_name(path.name + ".partial")
        n = write_scores(partial, matrix.S, matrix.probe_ids, matrix.probe_labels, matrix.gallery_ids)
        partial.replace(path)
    click.echo(f"wrote {out}: {n} comparisons of {len(m.probe_labels)} probes, {rule} of {normalisation} scores of "
               f"{len(scores)} files" + (f"; {left_out} comparisons missing from some file left out" if left_out else "")
               + f"; and {side}: the impostor pairs scored as strangers' claims")


@main.command()
@click.option("--subjects", default=30, show_default=True, type=click.IntRange(min=2))
@click.option("--scans", default=4, show_default=True, type=click.IntRange(min=2),
              help="Scans per subject: neutral gallery, neutral, expression, ±25° yaw (2 at least: a gallery scan and "
                   "a probe).")
@click.option("--methods", default="icp,region-icp,lda", show_default=True,
              help="Comma-separated methods to evaluate and compare (learnt ones get a disjoint training set).")
@click.option("--out", "out", default="demo-out", show_default=True, type=click.Path(file_okay=False))
@click.option("--jobs", default=os.cpu_count() or 1, show_default="all cores", type=click.IntRange(min=1),
              callback=_capped_jobs)
@click.option("--seed", default=0, show_default=True)
@friendly
def demo(subjects, scans, methods, out, jobs, seed):
    """The main job: synthesise a FRGC-style dataset (and a disjoint training set for learnt methods), evaluate
    each method on it, print the metrics and write one comparison report. Data already in OUT is reused when it
    was made with the same sizes and seed, else made again."""
    import dataclasses
    import json
    import shutil

    from facerec3d.datasets.synthetic import DatasetConfig, write_dataset
    from facerec3d.evaluation.compare import compare_runs
    from facerec3d.evaluation.run import evaluate as run
    from facerec3d.matching.registry import make_matcher

    out = Path(out)
    names = [m.strip() for m in methods.split(",") if m.strip()]
    if not names:  # before any data is made: nothing would use it
        raise click.BadParameter(f"{methods!r} names no method (e.g. icp,region-icp,lda)", param_hint="--methods")
    learnt = {name for name in names if make_matcher(name).needs_training}
    sets = {"data": DatasetConfig(subjects=subjects, scans=scans, seed=seed)}
    if learnt:
        sets["train"] = DatasetConfig(subjects=subjects, scans=scans, seed=seed + 1, first_subject=1000)
    for name, cfg in sets.items():
        folder, record = out / name, out / name / "demo-dataset.json"  # record: the settings it was made with
        wanted = json.dumps(dataclasses.asdict(cfg), sort_keys=True)
        if (folder / "manifest.csv").is_file():
            if record.is_file() and record.read_text(encoding="utf-8") == wanted:
                continue
            if not record.is_file():
                raise FaceRec3DError(f"{folder}: holds a dataset that demo did not record making (an older version's, "
                                     "or another); remove it or choose another --out")
            click.echo(f"{folder} was made with other settings: synthesising it again")
            shutil.rmtree(folder)
        click.echo(f"synthesising {name}: {cfg.subjects} subjects x {cfg.scans} scans")
        write_dataset(folder, cfg, "abs", progress=True)
        record.write_text(wanted, encoding="utf-8")
    for name in names:
        click.echo(f"\n== {name}" + (f" (trained on {out / 'train'})" if name in learnt else ""))
        m = run(out / "data", name, out / name, jobs=jobs, cache=out / "cache",
                train=out / "train" if name in learnt else None, overwrite=True,  # its own runs: made again
                echo=_to_stderr)
        _print_metrics(m)
    compare_runs([out / name for name in names], out / "compare", overwrite=True)  # its own comparison
    click.echo(f"\nreports: {out / 'compare' / 'compare.html'} (all methods), {out}/<method>/report.html")


if __name__ == "__main__":
    main()
