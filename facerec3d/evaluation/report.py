"""Write one evaluation run to a folder: scores, metrics, curves, plots, report.

A run folder written by `write_run` holds::

    scores.txt       4-column bob score file (see scorefile)
    metrics.json     see write_run
    probes.csv       one row per probe: label, subject, status, rank, mated and best non-mated score
    curves.npz       roc_fmr, roc_tar, det_fmr, det_fnmr, cmc, openset_fpir, openset_fnir (float arrays; no pickle)
    roc.png det.png cmc.png open_set.png scores_hist.png, and roc_masks.png with comparison masks (FRGC ROC I-III)
    report.html      self-contained page, <img> links relative to the folder
    report.md        the same tables in Markdown
"""

from __future__ import annotations

import csv
import html
import json
import os
import shlex
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from urllib.parse import quote

import numpy as np

from facerec3d.evaluation.metrics import (BOOTSTRAP, CI_LEVEL, FAR_LEVELS, FPIR_LEVELS, cmc, det, open_set, roc,
                                          search, split_scores, summarize)
from facerec3d.evaluation.plots import plot_cmc, plot_det, plot_roc, plot_score_histograms
from facerec3d.evaluation.scorefile import strangers_file, write_scores

#: The files of a run folder (write_run's, and evaluate's settings and model): a folder holding any of them holds a
#: run, and a new run into it removes them first, so that none is left over from another method.
RUN_FILES = ("metrics.json", "scores.txt", "probes.csv", "curves.npz", "roc.png", "roc_masks.png", "det.png",
             "cmc.png", "open_set.png", "scores_hist.png", "report.html", "report.md", "method.json", "model.npz",
             "preprocess.json")


def claim_run_folder(out_dir: str | Path, overwrite: bool = False, keep: Sequence[str | Path | None] = (),
                     files: Sequence[str] = RUN_FILES, what: str = "a run") -> Path:
    """Make `out_dir` ready for a new run: refuse (InputError) a folder that already holds `what` (any of the
    file names `files`: a run's, `RUN_FILES`, by default) unless `overwrite`, and then remove those files (other
    files stay), except those in `keep` (e.g. the model the new run loads)."""
    from facerec3d.errors import InputError

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: not a folder (a run folder is written there)")
    held = [out / name for name in dict.fromkeys(files) if (out / name).is_file()]
    if held and not overwrite:
        raise InputError(f"{out}: holds {what} already ({', '.join(p.name for p in held[:3])}"
                         f"{', ...' if len(held) > 3 else ''}): give --overwrite to replace it, or another --out")
    kept = {Path(k).resolve() for k in keep if k is not None}
    for path in held:
        if path.resolve() not in kept:
            path.unlink()
    return out


@contextmanager
def run_folder(out_dir: str | Path, overwrite: bool = False, keep: Sequence[str | Path | None] = (),
               files: Sequence[str] = RUN_FILES, what: str = "a run") -> Iterator[Path]:
    """`claim_run_folder`, then a new folder to write the files into, hidden beside `out_dir`: when the block ends
    they are moved into `out_dir` (the first of `files`, metrics.json for a run, last); when it raises (Ctrl-C too)
    that folder is removed. An interrupted run leaves no part of itself in `out_dir` (it left metrics.json and
    scores.txt without the report, looking like a run that a new one then refused to replace)."""
    out = claim_run_folder(out_dir, overwrite, keep, files, what)
    beside = out.resolve()
    beside.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{beside.name}.", suffix=".partial", dir=beside.parent))
    try:
        yield work
        out.mkdir(parents=True, exist_ok=True)
        for name in sorted(os.listdir(work), key=lambda name: name == files[0]):
            os.replace(work / name, out / name)
    finally:
        shutil.rmtree(work, ignore_errors=True)


# summarize() keys shown in reports, with their labels; RATES are shown in %.
SUMMARY_ROWS = (
    ("n_probes", "Probes"),
    ("n_processed", "Processed"),
    ("failures", "Failures to acquire"),
    ("fta_rate", "FTA rate"),
    ("n_subjects", "Probe subjects (bootstrap unit)"),
    ("n_ranked", "Probes ranked (subject enrolled)"),
    ("n_genuine", "Genuine comparisons"),
    ("n_impostor", "Impostor comparisons"),
    ("rank1", "Rank-1 identification rate"),
    ("rank5", "Rank-5 identification rate"),
    ("eer", "Equal error rate"),
    ("threshold_at_eer", "Threshold at the EER"),
    *((f"vr_at_far_{f}", f"VR at FMR {100 * f:g}%") for f in FAR_LEVELS),
    *((f"threshold_at_far_{f}", f"Threshold at FMR {100 * f:g}%") for f in FAR_LEVELS),
    ("rank1_all", "Rank-1, failures as misses"),
    ("rank5_all", "Rank-5, failures as misses"),
    *((f"vr_at_far_{f}_all", f"VR at FMR {100 * f:g}%, failures as rejections") for f in FAR_LEVELS),
    ("n_nonmated", "Open set: non-mated searches"),
    *((f"fnir_at_fpir_{f}", f"Open set: FNIR at FPIR {100 * f:g}%") for f in FPIR_LEVELS),
)
SUMMARY_KEYS = frozenset(k for k, _ in SUMMARY_ROWS) | {"ci95"}
RATES = frozenset(k for k, _ in SUMMARY_ROWS if not k.startswith(("n_", "threshold")) and k != "failures")
# (key, column) of the per-probe-set table: report, console and compare
SET_COLUMNS = (("rank1", "rank-1"), ("eer", "EER"), ("vr_at_far_0.001", "VR@0.1%"), ("vr_at_far_0.01", "VR@1%"),
               ("fnir_at_fpir_0.01", "FNIR@FPIR 1%"))
TIMING_LABELS = {
    "preprocess_s": "preprocessing, wall (s)",
    "preprocess_computed": "scans preprocessed (computed)",
    "preprocess_computed_ms": "  per computed scan, in its worker (ms)",
    "preprocess_cached": "scans read from the cache",
    "preprocess_cached_ms": "  per cached scan, in its worker (ms)",
    "fit_s": "training (s)",
    "enrol_first_s": "enrolment, first use: one template per worker, incl. JIT compilation / worker start (s)",
    "enrol_s": "enrolment, all templates (s)",
    "enrol_ms": "enrolment, steady state, per template (ms)",
    "match_first_s": "matching, first use: gallery loaded into the workers, one probe each, incl. JIT compilation (s)",
    "match_s": "matching, all probes (s)",
    "prepare_ms": "matching, steady state: probe preparation, per probe (ms)",
    "match_ms": "matching, steady state: per comparison, preparation excluded (ms)",
    "matches_per_s": "matching, steady state: comparisons per second",
}
SECTION_TITLES = {"options": "Method options", "preprocess": "Preprocessing configuration",
                  "provenance": "Provenance (the rerun command repeats this evaluation)",
                  "quality_median": "Scan quality (median)", "cascade": "Cascade"}
# metrics.json entries that have their own table (or none) rather than a row of the Run table
STRUCTURED = frozenset({"subsets", "masks", "strangers", "timings", "failed_scans", "scan_quality", "bootstrap"})

Table = tuple  # (heading, column names, rows of cells[, "wrap": long cells may wrap])


def format_value(key: str, value) -> str:
    """A metric as text: rates in % (2 decimals), other floats to 4 significant digits, None as '–'; lists and
    dicts as JSON, whole."""
    if value is None:
        return "–"
    if isinstance(value, bool) or isinstance(value, (int, np.integer)):
        return str(value)
    if isinstance(value, (float, np.floating)):
        return f"{100 * value:.2f}%" if key in RATES else f"{value:.4g}"
    if isinstance(value, str):
        return value
    return json.dumps(value, default=str)


def format_interval(key: str, interval) -> str:
    """A 95 % interval as text: '96.67–100.00%' for rates, '-1.234 – -0.5678' otherwise (an infinite threshold
    as ∞), '–' when None."""
    if not interval:
        return "–"
    lo, hi = interval
    if key in RATES:
        return f"{100 * lo:.2f}–{100 * hi:.2f}%"
    return f"{'−∞' if lo is None else f'{lo:.4g}'} – {'∞' if hi is None else f'{hi:.4g}'}"


def with_interval(key: str, figures: Mapping) -> str:
    """A figure and its interval in one cell: '98.89% (96.67–100.00%)'."""
    value = format_value(key, figures.get(key))
    ci = (figures.get("ci95") or {}).get(key)
    return f"{value} ({format_interval(key, ci)})" if ci else value


STRANGERS = "all probes, impostors as strangers"  # the probe set of metrics.json's `strangers` (see write_run)


def probe_sets(metrics: Mapping) -> dict[str, Mapping]:
    """{name: figures} of all probes, the strangers' claims (`STRANGERS`, methods normalised over the gallery),
    each subset and each comparison mask (named 'mask ROC I' etc.)."""
    return {"all probes": metrics, **({STRANGERS: metrics["strangers"]} if metrics.get("strangers") else {}),
            **(metrics.get("subsets") or {}),
            **{f"mask {name}": m for name, m in (metrics.get("masks") or {}).items()}}


def set_table(metrics: Mapping) -> tuple[list[str], list[list[str]]]:
    """The per-probe-set table: columns and rows (name, probes, FTA, then SET_COLUMNS with 95 % intervals)."""
    columns = ["probes", "n", "FTA", *(c for _, c in SET_COLUMNS)]
    rows = [[name, str(m.get("n_probes", "–")), format_value("fta_rate", m.get("fta_rate")),
             *(with_interval(k, m) for k, _ in SET_COLUMNS)] for name, m in probe_sets(metrics).items()]
    return columns, rows


def _img_src(out_dir: Path, path: str | Path) -> str:
    """A plot's path as a URL relative to out_dir."""
    path = Path(path)
    if path.is_absolute():
        path = Path(os.path.relpath(path, out_dir.resolve()))
    return quote(path.as_posix())


def _md_row(cells: Sequence[str]) -> str:
    """One Markdown table row, '|' in cells escaped."""
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


PAGE_CSS = ("body{font-family:sans-serif;font-size:14px;margin:2em;max-width:1200px}"
            "table{border-collapse:collapse;margin-bottom:1.5em}"
            "th,td{border:1px solid #bbb;padding:.25em .6em;white-space:nowrap}td{text-align:right}"
            "td:first-child{text-align:left}th{background:#eee}"
            "table.wrap td{white-space:normal;overflow-wrap:anywhere;text-align:left}"
            "figure{display:inline-block;width:48%;margin:0}img{max-width:100%}")


def write_pages(
    out_dir: str | Path, stem: str, title: str, tables: Sequence[Table], plots: Mapping[str, str | Path]
) -> None:
    """Write <stem>.html (self-contained, inline CSS) and <stem>.md: the tables, then the plots.

    Cells do not wrap, except in tables marked "wrap" (long text: paths, commands, settings). plots maps a
    caption to a PNG path.
    """
    out_dir = Path(out_dir)
    e = html.escape
    parts = ["<!DOCTYPE html>", f'<html lang="en"><head><meta charset="utf-8"><title>{e(title)}</title>',
             f"<style>{PAGE_CSS}</style></head><body><h1>{e(title)}</h1>"]
    md = [f"# {title}", ""]
    for heading, columns, rows, *wrap in tables:
        css = ' class="wrap"' if wrap and wrap[0] == "wrap" else ""
        parts += [f"<h2>{e(heading)}</h2><table{css}>", "<tr>" + "".join(f"<th>{e(c)}</th>" for c in columns) + "</tr>"]
        parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>" for row in rows]
        parts.append("</table>")
        md += [f"## {heading}", "", _md_row(columns), "|" + "---|" * len(columns), *map(_md_row, rows)]
        md.append("")
    if plots:
        parts.append("<h2>Plots</h2>")
        md += ["## Plots", ""]
    for name, path in plots.items():
        src = _img_src(out_dir, path)
        parts.append(f'<figure><img src="{e(src)}" alt="{e(name)}"><figcaption>{e(name)}</figcaption></figure>')
        md.append(f"![{name}]({src})")
    parts.append("</body></html>")
    (out_dir / f"{stem}.html").write_text("\n".join(parts) + "\n", encoding="utf-8")
    (out_dir / f"{stem}.md").write_text("\n".join(md) + "\n", encoding="utf-8")


def _flat(value, prefix: str = "") -> list[tuple[str, object]]:
    """Nested dicts as (dotted key, leaf) pairs, in order."""
    if isinstance(value, Mapping) and value:
        return [pair for k, v in value.items() for pair in _flat(v, f"{prefix}.{k}" if prefix else str(k))]
    return [(prefix, value)]


def _text(key: str, value) -> str:
    """A setting or provenance entry as text: argv lists as a shell command line, others by format_value."""
    if isinstance(value, list) and value and all(isinstance(v, str) for v in value) and key.endswith(
            ("command", "rerun")):
        return shlex.join(value)
    return format_value(key, value)


def report_tables(metrics: Mapping) -> list[Table]:
    """The tables of a run's report (see write_report)."""
    tables: list[Table] = []
    run = [[k, _text(k, v)] for k, v in metrics.items()
           if k not in SUMMARY_KEYS | STRUCTURED and not isinstance(v, Mapping)]
    if run:
        tables.append(("Run", ["", "value"], run, "wrap"))
    ci = metrics.get("ci95") or {}
    boot = metrics.get("bootstrap") or {}
    level = f"{100 * boot.get('level', CI_LEVEL):g}% interval"
    tables.append(("Figures, all probes", ["figure", "value", level],
                   [[label, format_value(k, metrics.get(k)), format_interval(k, ci.get(k)) if k in ci else ""]
                    for k, label in SUMMARY_ROWS]))
    columns, rows = set_table(metrics)
    tables.append((f"By probe set and comparison mask (value ({level}))", columns, rows))
    masks = metrics.get("masks") or {}
    if masks:
        keys = ("n_genuine", "n_impostor", "eer", "vr_at_far_0.001", "vr_at_far_0.01", "threshold_at_far_0.001")
        tables.append(("Comparison masks (FRGC Experiment 3)", ["mask", "genuine", "impostor", "EER", "VR@0.1%",
                                                               "VR@1%", "threshold@0.1%"],
                       [[name, *(with_interval(k, m) for k in keys)] for name, m in masks.items()]))
    if boot:
        tables.append(("Uncertainty", ["", "value"], [[k, format_value(k, v)] for k, v in boot.items()], "wrap"))
    timings = metrics.get("timings") or {}
    if timings:
        tables.append(("Timings", ["", "what", "value"], [[k, TIMING_LABELS.get(k, ""), format_value(k, v)]
                                                          for k, v in timings.items()]))
    failed = metrics.get("failed_scans") or []
    if failed:
        tables.append((f"Failed scans ({len(failed)})", ["scan", "role", "reason"],
                       [[f.get("path", ""), f.get("role", ""), f.get("reason", "")] for f in failed], "wrap"))
    for key, value in metrics.items():
        if isinstance(value, Mapping) and key not in SUMMARY_KEYS | STRUCTURED:
            tables.append((SECTION_TITLES.get(key, key.replace("_", " ").capitalize()), ["", "value"],
                           [[k, _text(k, v)] for k, v in _flat(value)], "wrap"))
    return tables


def write_report(out_dir: str | Path, metrics: Mapping, plots: Mapping[str, str | Path]) -> None:
    """Write report.html and report.md for one run into out_dir.

    metrics is the metrics.json layout (see write_run). Tables: the run's
    scalar entries (method, protocol, ...); every figure of all probes with
    its interval; rank-1 / EER / VR / FNIR with intervals by probe subset and
    comparison mask; the masks' counts and VR; the bootstrap settings;
    timings; failed scans; then each settings entry (method options,
    preprocessing, provenance with the command to rerun, ...) whole, one
    setting per row. plots maps a caption to a PNG path (relative to
    out_dir, or absolute).
    """
    title = f"facerec3d evaluation: {metrics['method']}" if "method" in metrics else "facerec3d evaluation"
    write_pages(out_dir, "report", title, report_tables(metrics), plots)


def _jsonable(value):
    """json.dump fallback for NumPy scalars/arrays and paths."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _curves(S, probe_ids, gallery_ids, tiebreak, mateless) -> dict[str, np.ndarray]:
    """ROC (collinear points dropped), DET, CMC and open-set arrays; empty where undefined."""
    genuine, impostor = split_scores(S, probe_ids, gallery_ids)
    empty = np.empty(0)
    out = dict(roc_fmr=empty, roc_tar=empty, det_fmr=empty, det_fnmr=empty, cmc=empty, openset_fpir=empty,
               openset_fnir=empty)
    if genuine.size and impostor.size:
        out["roc_fmr"], out["roc_tar"], _ = roc(genuine, impostor, drop_intermediate=True)
        out["det_fmr"], out["det_fnmr"], _ = det(genuine, impostor)
    if (np.isin(probe_ids, gallery_ids) & ~mateless).any():
        out["cmc"] = cmc(S, probe_ids, gallery_ids, tiebreak=tiebreak, mateless=mateless)
        try:
            out["openset_fpir"], out["openset_fnir"], _ = open_set(S, probe_ids, gallery_ids, tiebreak, mateless)
        except ValueError:  # no non-mated search (a single gallery subject)
            pass
    return out


def _write_probes(path: Path, S, probe_ids, probe_labels, gallery_ids, tiebreak, failed, mateless) -> None:
    """probes.csv: each processed probe's search (rank empty when its subject is not enrolled, or its only
    template is itself), then the failed."""
    s = search(S, probe_ids, gallery_ids, tiebreak, mateless)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["probe", "subject", "status", "rank", "mated_score", "nonmated_score"])
        for label, subject, ranked, rank, mated, nonmated in zip(probe_labels, probe_ids, *s):
            w.writerow([label, subject, "processed", rank if ranked else "", repr(float(mated)) if ranked else "",
                        "" if np.isnan(nonmated) else repr(float(nonmated))])
        w.writerows([label, subject, "failed", "", "", ""] for label, subject in failed)


def write_run(
    out_dir: str | Path,
    S,
    probe_ids: Sequence,
    probe_labels: Sequence,
    gallery_ids: Sequence,
    metrics: Mapping,
    *,
    tiebreak=None,
    subsets: Mapping[str, np.ndarray] | None = None,
    n_failed: int = 0,
    subset_failures: Mapping[str, int | Sequence[str]] | None = None,
    failed: Sequence[tuple[str, str]] | None = None,
    masks: Mapping[str, np.ndarray] | None = None,
    bootstrap: int = BOOTSTRAP,
    seed: int = 0,
    unenrolled: Sequence[str] = (),
    mateless=None,
    strangers=None,
) -> dict:
    """Evaluate score matrix S (higher = more similar) and write the run folder.

    S is (n_probes, n_gallery) over the processed probes; n_failed probes
    failed before matching (FTA), or ``failed`` lists them as (label, subject)
    so that the bootstrap draws them with their subject. tiebreak: optional
    secondary matrix for CMC ties (see metrics.cmc). subsets maps a name to a
    boolean mask over the processed probes (e.g. "neutral", "non-neutral");
    subset_failures gives each subset's failed probes, as a count or as
    labels of ``failed`` (default none). masks maps a name to a boolean (n_probes, n_gallery) matrix of the
    comparisons a figure counts (FRGC's ROC I / II / III): each is summarised
    without identification figures. bootstrap: replicates for the 95 %
    intervals (0: none), drawn with numpy.random.default_rng(seed). unenrolled: the subjects whose gallery
    scans all failed to enrol; their probes are misses in the failures-as-misses (*_all) figures. mateless:
    booleans over the processed probes, those whose subject's only gallery scan is the probe itself, not compared
    (all-vs-all, a person with one scan): searches of a subject not enrolled (see metrics.search). strangers: the
    impostor scores of a method normalised over the gallery as strangers' claims meet them (each probe scored over
    the entries not of its subject, `matching.base.scores_over`; S's shape, the rest ignored): then `strangers` in
    metrics.json holds the verification figures with those impostors (and S's genuine scores), and
    scores.strangers.txt those impostor scores.

    metrics.json is one JSON object (strict JSON: undefined metrics are null):
      - every entry of ``metrics`` as given (e.g. ``method``, ``protocol``,
        ``n_gallery``, ``timings`` {name: value, unit in the name, e.g.
        ``enrol_s`` seconds to enrol the gallery, ``match_ms`` milliseconds per
        probe-gallery comparison}, ``provenance``),
      - the keys of ``summarize(S, ...)``, ``ci95`` among them (computed values
        replace any caller entry of the same name),
      - ``bootstrap``: {replicates, seed, level, unit},
      - ``subsets``: {name: summarize(...) over that subset's probes} and
        ``masks``: {name: summarize(...) over the masked comparisons}, when given;
      - ``strangers``: summarize(...) without identification figures, each impostor pair scored as a stranger's
        claim (see strangers), when given.

    The plots show all probes and each subset (roc_masks.png: the masks). Returns the metrics.json object.
    """
    out = Path(out_dir)
    S = np.asarray(S, dtype=float)
    probe_ids, gallery_ids = np.asarray(probe_ids).astype(str), np.asarray(gallery_ids).astype(str)
    tiebreak = None if tiebreak is None else np.asarray(tiebreak, dtype=float)
    failed = [(str(label), str(subject)) for label, subject in (failed or [])]
    mateless = np.zeros(S.shape[0], bool) if mateless is None else np.asarray(mateless, dtype=bool)
    subject_of = dict(failed)
    groups = {name: np.asarray(mask) for name, mask in (subsets or {}).items()}
    for name, mask in groups.items():
        if mask.dtype != bool or mask.shape != (S.shape[0],):
            raise ValueError(f"subset {name!r}: need {S.shape[0]} booleans, got {mask.dtype} {mask.shape}")
    pairs = {name: np.asarray(mask) for name, mask in (masks or {}).items()}
    mated = probe_ids[:, None] == gallery_ids[None, :]
    if strangers is not None:
        strangers = np.asarray(strangers, dtype=float)
        if strangers.shape != S.shape:
            raise ValueError(f"strangers: need a {S.shape} matrix, got {strangers.shape}")
        strangers = np.where(mated, np.nan, strangers)
    for name, mask in pairs.items():
        if mask.dtype != bool or mask.shape != S.shape:
            raise ValueError(f"mask {name!r}: need {S.shape} booleans, got {mask.dtype} {mask.shape}")

    def tb(m: np.ndarray):
        """The tiebreak rows of a subset."""
        return None if tiebreak is None else tiebreak[m]

    def figures(rows: np.ndarray, failures, **kw) -> dict:
        """summarize over some rows, with their failures as a count or as failed labels."""
        Sm = kw.pop("S", S)[rows]
        kw.setdefault("unenrolled", unenrolled)
        kw.setdefault("mateless", mateless[rows])
        if isinstance(failures, (int, np.integer)):
            return summarize(Sm, probe_ids[rows], gallery_ids, int(failures), tb(rows), bootstrap=bootstrap, seed=seed,
                             **kw)
        return summarize(Sm, probe_ids[rows], gallery_ids, tiebreak=tb(rows), bootstrap=bootstrap, seed=seed,
                         failed_ids=[subject_of[label] for label in failures], **kw)

    every = np.ones(S.shape[0], bool)
    result = {**metrics, **figures(every, [label for label, _ in failed] if failed else n_failed)}
    if bootstrap:
        result["bootstrap"] = {"replicates": int(bootstrap), "seed": int(seed), "level": CI_LEVEL,
                               "unit": "probe subject (its probes, comparisons and failures); gallery fixed",
                               "interval": "percentile"}
    if groups:
        failures = subset_failures or {}
        result["subsets"] = {name: figures(m, failures.get(name, 0)) for name, m in groups.items()}
    if pairs:
        result["masks"] = {name: figures(every, 0, S=np.where(m, S, np.nan), identification=False)
                           for name, m in pairs.items()}
    if strangers is not None:
        result["strangers"] = figures(every, [label for label, _ in failed] if failed else n_failed,
                                      S=np.where(mated, S, strangers), identification=False)
    text = json.dumps(result, indent=2, allow_nan=False, default=_jsonable)  # fails before any file is written

    out.mkdir(parents=True, exist_ok=True)
    write_scores(out / "scores.txt", S, probe_ids, probe_labels, gallery_ids)
    if strangers is not None:
        write_scores(strangers_file(out / "scores.txt"), strangers, probe_ids, probe_labels, gallery_ids)
    (out / "metrics.json").write_text(text + "\n", encoding="utf-8")
    _write_probes(out / "probes.csv", S, probe_ids, probe_labels, gallery_ids, tiebreak, failed, mateless)
    curves = {name: _curves(S[m], probe_ids[m], gallery_ids, tb(m), mateless[m]) for name, m in {"all probes": every, **groups}.items()}
    np.savez(out / "curves.npz", **curves["all probes"])
    plot_roc({n: (c["roc_fmr"], c["roc_tar"]) for n, c in curves.items() if c["roc_fmr"].size}, out / "roc.png")
    plot_det({n: (c["det_fmr"], c["det_fnmr"]) for n, c in curves.items() if c["det_fmr"].size}, out / "det.png")
    plot_cmc({n: c["cmc"] for n, c in curves.items() if c["cmc"].size}, out / "cmc.png")
    plot_det({n: (c["openset_fpir"], c["openset_fnir"]) for n, c in curves.items() if c["openset_fpir"].size},
             out / "open_set.png", title="Open-set identification (DET)",
             xlabel="False positive identification rate (FPIR)", ylabel="False negative identification rate (FNIR)")
    labels = plot_score_histograms(*split_scores(S, probe_ids, gallery_ids), out / "scores_hist.png")
    plots = {"ROC": "roc.png", "DET": "det.png", "CMC": "cmc.png", "Open-set identification: FNIR against FPIR":
             "open_set.png", f"Score distributions: {'; '.join(labels)}": "scores_hist.png"}
    if pairs:
        mask_curves = {}
        for name, m in pairs.items():
            genuine, impostor = split_scores(np.where(m, S, np.nan), probe_ids, gallery_ids)
            if genuine.size and impostor.size:
                mask_curves[name] = roc(genuine, impostor, drop_intermediate=True)[:2]
        plot_roc(mask_curves, out / "roc_masks.png", title="ROC by comparison mask")
        plots["ROC by comparison mask (FRGC Experiment 3: ROC I, II, III)"] = "roc_masks.png"
    write_report(out, result, plots)
    return result
