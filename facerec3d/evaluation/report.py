"""Write one evaluation run to a folder: scores, metrics, curves, plots, report.

A run folder written by `write_run` holds::

    scores.txt       4-column bob score file (see scorefile)
    metrics.json     see write_run
    curves.npz       roc_fmr, roc_tar, det_fmr, det_fnmr, cmc (float arrays; np.savez, no pickle)
    roc.png det.png cmc.png scores_hist.png
    report.html      self-contained page, <img> links relative to the folder
    report.md        the same tables in Markdown
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from urllib.parse import quote

import numpy as np

from facerec3d.evaluation.metrics import cmc, det, roc, split_scores, summarize
from facerec3d.evaluation.plots import plot_cmc, plot_det, plot_roc, plot_score_histograms
from facerec3d.evaluation.scorefile import write_scores

# summarize() keys shown in reports, with their labels; RATES are shown in %.
SUMMARY_ROWS = (
    ("n_probes", "Probes"),
    ("n_processed", "Processed"),
    ("failures", "Failures to acquire"),
    ("fta_rate", "FTA rate"),
    ("n_ranked", "Probes ranked (subject enrolled)"),
    ("n_genuine", "Genuine comparisons"),
    ("n_impostor", "Impostor comparisons"),
    ("rank1", "Rank-1 identification rate"),
    ("rank5", "Rank-5 identification rate"),
    ("eer", "Equal error rate"),
    ("vr_at_far_0.001", "VR at FMR 0.1%"),
    ("vr_at_far_0.01", "VR at FMR 1%"),
    ("rank1_all", "Rank-1, failures as misses"),
    ("rank5_all", "Rank-5, failures as misses"),
    ("vr_at_far_0.001_all", "VR at FMR 0.1%, failures as rejections"),
    ("vr_at_far_0.01_all", "VR at FMR 1%, failures as rejections"),
)
SUMMARY_KEYS = frozenset(k for k, _ in SUMMARY_ROWS)
RATES = SUMMARY_KEYS - {"n_probes", "n_processed", "failures", "n_ranked", "n_genuine", "n_impostor"}

Table = tuple[str, Sequence[str], Sequence[Sequence[str]]]  # (heading, column names, rows of cells)


def format_value(key: str, value) -> str:
    """A metric as text: rates in % (2 decimals), other floats to 4 significant digits, None as '–'.

    Lists and dicts are shown as JSON, cut to 300 characters (metrics.json keeps them whole).
    """
    if value is None:
        return "–"
    if isinstance(value, bool) or isinstance(value, (int, np.integer)):
        return str(value)
    if isinstance(value, (float, np.floating)):
        return f"{100 * value:.2f}%" if key in RATES else f"{value:.4g}"
    if isinstance(value, str):
        return value
    text = json.dumps(value, default=str)
    return text if len(text) <= 300 else text[:299] + "…"


def _img_src(out_dir: Path, path: str | Path) -> str:
    """A plot's path as a URL relative to out_dir."""
    path = Path(path)
    if path.is_absolute():
        path = Path(os.path.relpath(path, out_dir.resolve()))
    return quote(path.as_posix())


def _md_row(cells: Sequence[str]) -> str:
    """One Markdown table row, '|' in cells escaped."""
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


def write_pages(
    out_dir: str | Path, stem: str, title: str, tables: Sequence[Table], plots: Mapping[str, str | Path]
) -> None:
    """Write <stem>.html (self-contained, inline CSS) and <stem>.md: the tables, then the plots."""
    out_dir = Path(out_dir)
    e = html.escape
    parts = [
        "<!DOCTYPE html>",
        f'<html lang="en"><head><meta charset="utf-8"><title>{e(title)}</title><style>',
        "body{font-family:sans-serif;margin:2em;max-width:75em}"
        "table{border-collapse:collapse;margin-bottom:1.5em}"
        "th,td{border:1px solid #bbb;padding:.25em .6em}td{text-align:right}"
        "td:first-child{text-align:left}th{background:#eee}img{max-width:48%;margin:.5%}",
        f"</style></head><body><h1>{e(title)}</h1>",
    ]
    md = [f"# {title}", ""]
    for heading, columns, rows in tables:
        parts += [f"<h2>{e(heading)}</h2><table>", "<tr>" + "".join(f"<th>{e(c)}</th>" for c in columns) + "</tr>"]
        parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>" for row in rows]
        parts.append("</table>")
        md += [f"## {heading}", "", _md_row(columns), "|" + "---|" * len(columns), *map(_md_row, rows)]
        md.append("")
    if plots:
        parts.append("<h2>Plots</h2>")
        md += ["## Plots", ""]
    for name, path in plots.items():
        src = _img_src(out_dir, path)
        parts.append(f'<figure style="display:inline-block;width:48%;margin:0"><img src="{e(src)}" alt="{e(name)}" '
                     f'style="max-width:100%"><figcaption>{e(name)}</figcaption></figure>')
        md.append(f"![{name}]({src})")
    parts.append("</body></html>")
    (out_dir / f"{stem}.html").write_text("\n".join(parts) + "\n", encoding="utf-8")
    (out_dir / f"{stem}.md").write_text("\n".join(md) + "\n", encoding="utf-8")


def write_report(out_dir: str | Path, metrics: Mapping, plots: Mapping[str, str | Path]) -> None:
    """Write report.html and report.md for one run into out_dir.

    metrics is the metrics.json layout (see write_run): a "Run" table of the
    caller's scalar entries (method, protocol, ...), a metrics table with one
    column for all probes and one per metrics['subsets'] entry, and a timings
    table from metrics['timings'] when present. plots maps a caption to a PNG
    path (relative to out_dir, or absolute).
    """
    subsets = metrics.get("subsets") or {}
    columns = {"all probes": metrics, **subsets}
    tables: list[Table] = []
    run = [[k, format_value(k, v)] for k, v in metrics.items() if k not in SUMMARY_KEYS | {"subsets", "timings"}]
    if run:
        tables.append(("Run", ["", "value"], run))
    rows = [[label] + [format_value(k, c.get(k)) for c in columns.values()] for k, label in SUMMARY_ROWS]
    tables.append(("Metrics", ["metric", *columns], rows))
    timings = metrics.get("timings") or {}
    if timings:
        tables.append(("Timings", ["", "value"], [[k, format_value(k, v)] for k, v in timings.items()]))
    title = f"facerec3d evaluation: {metrics['method']}" if "method" in metrics else "facerec3d evaluation"
    write_pages(out_dir, "report", title, tables, plots)


def _jsonable(value):
    """json.dump fallback for NumPy scalars/arrays and paths."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _curves(S, probe_ids, gallery_ids, tiebreak) -> dict[str, np.ndarray]:
    """ROC (collinear points dropped), DET and CMC arrays; empty where undefined."""
    genuine, impostor = split_scores(S, probe_ids, gallery_ids)
    empty = np.empty(0)
    out = dict(roc_fmr=empty, roc_tar=empty, det_fmr=empty, det_fnmr=empty, cmc=empty)
    if genuine.size and impostor.size:
        out["roc_fmr"], out["roc_tar"], _ = roc(genuine, impostor, drop_intermediate=True)
        out["det_fmr"], out["det_fnmr"], _ = det(genuine, impostor)
    if np.isin(probe_ids, gallery_ids).any():
        out["cmc"] = cmc(S, probe_ids, gallery_ids, tiebreak=tiebreak)
    return out


def write_run(
    out_dir: str | Path,
    S,
    probe_ids: Sequence,
    probe_labels: Sequence,
    gallery_ids: Sequence,
    metrics: Mapping,
    tiebreak=None,
    subsets: Mapping[str, np.ndarray] | None = None,
    n_failed: int = 0,
    subset_failures: Mapping[str, int] | None = None,
) -> dict:
    """Evaluate score matrix S (higher = more similar) and write the run folder.

    S is (n_probes, n_gallery) over the processed probes; n_failed probes
    failed before matching (FTA). tiebreak: optional secondary matrix for CMC
    ties (see metrics.cmc). subsets maps a name to a boolean mask over the
    processed probes (e.g. "neutral", "non-neutral"); subset_failures gives
    each subset's failed probes (default 0).

    metrics.json is one JSON object (strict JSON: undefined metrics are null):
      - every entry of ``metrics`` as given (e.g. ``method``, ``protocol``,
        ``n_gallery``, ``timings`` {name: value, unit in the name, e.g.
        ``enrol_s`` seconds to enrol the gallery, ``match_ms`` milliseconds per
        probe-gallery comparison}),
      - the keys of ``summarize(S, ...)`` (computed values replace any caller
        entry of the same name),
      - ``subsets``: {name: summarize(...) over that subset's probes} when
        subsets are given.

    The plots show all probes and each subset. Returns the metrics.json object.
    """
    out = Path(out_dir)
    S = np.asarray(S, dtype=float)
    probe_ids, gallery_ids = np.asarray(probe_ids).astype(str), np.asarray(gallery_ids).astype(str)
    tiebreak = None if tiebreak is None else np.asarray(tiebreak, dtype=float)
    result = {**metrics, **summarize(S, probe_ids, gallery_ids, n_failed, tiebreak)}
    masks = {name: np.asarray(mask) for name, mask in (subsets or {}).items()}
    for name, mask in masks.items():
        if mask.dtype != bool or mask.shape != (S.shape[0],):
            raise ValueError(f"subset {name!r}: need {S.shape[0]} booleans, got {mask.dtype} {mask.shape}")

    def tb(m: np.ndarray):
        """The tiebreak rows of a subset."""
        return None if tiebreak is None else tiebreak[m]

    if masks:
        failures = subset_failures or {}
        result["subsets"] = {
            name: summarize(S[m], probe_ids[m], gallery_ids, failures.get(name, 0), tb(m)) for name, m in masks.items()
        }
    text = json.dumps(result, indent=2, allow_nan=False, default=_jsonable)  # fails before any file is written

    out.mkdir(parents=True, exist_ok=True)
    write_scores(out / "scores.txt", S, probe_ids, probe_labels, gallery_ids)
    (out / "metrics.json").write_text(text + "\n", encoding="utf-8")
    groups = {"all probes": np.ones(S.shape[0], bool), **masks}
    curves = {name: _curves(S[m], probe_ids[m], gallery_ids, tb(m)) for name, m in groups.items()}
    np.savez(out / "curves.npz", **curves["all probes"])
    plot_roc({n: (c["roc_fmr"], c["roc_tar"]) for n, c in curves.items() if c["roc_fmr"].size}, out / "roc.png")
    plot_det({n: (c["det_fmr"], c["det_fnmr"]) for n, c in curves.items() if c["det_fmr"].size}, out / "det.png")
    plot_cmc({n: c["cmc"] for n, c in curves.items() if c["cmc"].size}, out / "cmc.png")
    plot_score_histograms(*split_scores(S, probe_ids, gallery_ids), out / "scores_hist.png")
    plots = {"ROC": "roc.png", "DET": "det.png", "CMC": "cmc.png", "Score distributions": "scores_hist.png"}
    write_report(out, result, plots)
    return result
