"""Compare run folders written by report.write_run: overlaid curves, tables, and McNemar tests of rank-1."""

from __future__ import annotations

import csv
import json
import zipfile
import zlib
from collections.abc import Sequence
from itertools import combinations
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from facerec3d.evaluation.plots import plot_cmc, plot_det, plot_roc
from facerec3d.errors import InputError
from facerec3d.evaluation.report import RATES, SET_COLUMNS, format_value, run_folder, with_interval, write_pages
from facerec3d.evaluation.scorefile import text_file

ALPHA = 0.05  # significance level of the McNemar tests
#: The files compare_runs writes: a folder holding any of them holds a comparison.
COMPARE_FILES = ("compare_roc.png", "compare_det.png", "compare_cmc.png", "compare.html", "compare.md")


def _load(run_dir: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """A run's metrics.json and curves.npz arrays ({} when curves.npz is absent)."""
    path = run_dir / "metrics.json"
    if not path.is_file():
        raise InputError(f"{run_dir}: not a run folder (no metrics.json)")
    try:
        metrics = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise InputError(f"{path}: not a metrics file ({e})") from None
    if not isinstance(metrics, dict):
        raise InputError(f"{path}: not a metrics file (a JSON {type(metrics).__name__}, not an object)")
    _check_layout(metrics, path)
    curves = run_dir / "curves.npz"
    if not curves.is_file():
        return metrics, {}
    try:
        with np.load(curves, allow_pickle=False) as z:
            return metrics, {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise InputError(f"{curves}: not a run's curves file, or a damaged one ({type(e).__name__}: "
                         f"{str(e)[:200]})") from None


def _check_layout(metrics: dict, path: Path) -> None:
    """The parts of metrics.json that compare reads laid out as write_run writes them (objects; intervals as
    [low, high]): InputError naming the file and the key, not an error deep in the tables."""
    for key in ("ci95", "timings", "subsets", "masks"):
        if (value := metrics.get(key)) is not None and not isinstance(value, dict):
            raise InputError(f"{path}: not a metrics file ({key!r} is a JSON {type(value).__name__}, not an object)")
    for key in ("subsets", "masks"):
        for name, value in (metrics.get(key) or {}).items():
            if not isinstance(value, dict):
                raise InputError(f"{path}: not a metrics file ({key}.{name} is a JSON {type(value).__name__}, "
                                 "not an object)")
    for key, ci in (metrics.get("ci95") or {}).items():
        if ci and not (isinstance(ci, list) and len(ci) == 2 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) or x is None and key not in RATES for x in ci)):
            raise InputError(f"{path}: not a metrics file (ci95.{key} is not an interval [low, high])")


def rank1_hits(run_dir: str | Path) -> dict[str, bool | None] | None:
    """{probe label: found at rank 1} from a run's probes.csv (None when the run has none). A failed probe is a
    miss; a processed probe whose subject is not enrolled is None (no identification attempt)."""
    path = Path(run_dir) / "probes.csv"
    if not path.is_file():
        return None
    with text_file(path, newline="") as f:  # not UTF-8, or not CSV: one line naming the file
        reader = csv.DictReader(f)
        if missing := [c for c in ("probe", "rank", "status") if c not in (reader.fieldnames or [])]:
            raise InputError(f"{path}: not a run's probes file: no column {', '.join(missing)}")
        return {r["probe"]: (r["rank"] == "1") if r["rank"] or r["status"] == "failed" else None for r in reader}


def mcnemar(a: dict[str, bool | None], b: dict[str, bool | None]) -> dict:
    """McNemar's exact test of two runs' rank-1 hits on the probes both ran (a probe that is an identification
    attempt in neither is left out; in one only, a miss in the other).

    Returns {"n": probes compared, "a_only": hits of a missed by b, "b_only": the reverse, "p": two-sided p
    (binomial test of a_only against Binomial(a_only + b_only, 1/2); 1.0 without discordant probes)}.
    """
    common = [k for k in a.keys() & b.keys() if a[k] is not None or b[k] is not None]
    hit_a = np.array([bool(a[k]) for k in common], bool)
    hit_b = np.array([bool(b[k]) for k in common], bool)
    a_only, b_only = int((hit_a & ~hit_b).sum()), int((hit_b & ~hit_a).sum())
    p = binomtest(a_only, a_only + b_only, 0.5).pvalue if a_only + b_only else 1.0
    return {"n": len(common), "a_only": a_only, "b_only": b_only, "p": float(p)}


def compare_runs(run_dirs: Sequence[str | Path], out_dir: str | Path, overwrite: bool = False) -> dict:
    """Overlay the runs' curves and tabulate them in out_dir.

    Writes compare_roc.png and compare_cmc.png, compare_det.png when some run
    has a DET curve, and compare.html / compare.md. Runs are numbered #1, #2,
    ... in the order given; tables (each fits a 1280 px page: wide ones have
    a column per run): "Runs" (number, label "<method> (<folder name>)", or
    the folder's name alone when it is the method's, protocol, probes,
    gallery); "Figures" (a row per run: FTA and rank-1, EER,
    VR@0.1%, VR@1%, FNIR@FPIR 1% with their 95 % intervals); "Rank-1 by
    subset" (a row per subset found in any run); "VR@0.1% by comparison mask"
    (FRGC ROC I-III, when present); "Timings" (a row per timings entry, named
    as in metrics.json, unit in the name); and "Rank-1: McNemar tests" for
    every pair of runs with probes.csv: probes compared, hits of one missed
    by the other each way, p, and whether they differ at the 5 % level. A run
    without curves.npz is tabulated but not plotted. Raises ValueError naming
    the folder when a run folder has no metrics.json, and an InputError when
    out_dir holds a comparison already (COMPARE_FILES) unless `overwrite`,
    with which those files are removed first.

    Returns {"columns", "rows" (the Figures table), "tables" [(heading,
    columns, rows)], "mcnemar" [{"a", "b", "n", "a_only", "b_only", "p",
    "differ"}], "runs": [{"label", "dir", "metrics"}, ...], "files": [written
    paths]}.
    """
    if not run_dirs:
        raise InputError("no run folders to compare")
    runs = []
    for d in map(Path, run_dirs):
        metrics, curves = _load(d)
        method = metrics.get("method")
        label = f"{method} ({d.name})" if method and method != d.name else d.name  # "icp", not "icp (icp)"
        runs.append({"label": label, "dir": str(d), "metrics": metrics,
                     "curves": curves, "hits": rank1_hits(d)})
    labels = [r["label"] for r in runs]
    for i, r in enumerate(runs):  # keep labels unique so no curve hides another
        if labels.count(r["label"]) > 1:
            r["label"] = f"{r['label']} #{i + 1}"
    ids = [f"#{i + 1}" for i in range(len(runs))]

    def by_run(keys, cell) -> list[list[str]]:
        """Rows keyed by `keys`, one column per run."""
        return [[k, *(cell(r["metrics"], k) for r in runs)] for k in keys]

    def union(field: str) -> list[str]:
        return list(dict.fromkeys(k for r in runs for k in r["metrics"].get(field) or {}))

    columns = ["run", "FTA", *(c for _, c in SET_COLUMNS)]
    rows = [[i, format_value("fta_rate", r["metrics"].get("fta_rate")),
             *(with_interval(k, r["metrics"]) for k, _ in SET_COLUMNS)] for i, r in zip(ids, runs)]
    if any(isinstance(r["metrics"].get("strangers"), dict) for r in runs):  # a method normalised over the gallery:
        # its EER with impostors scored as strangers' claims, beside the protocol's (write_run's `strangers`)
        columns.insert(columns.index("EER") + 1, "EER, strangers")
        for row, r in zip(rows, runs):
            strangers = r["metrics"].get("strangers")
            row.insert(columns.index("EER") + 1,  # (the value only: the table fits a page; its report has the interval)
                       format_value("eer", strangers.get("eer")) if isinstance(strangers, dict) else "–")
    tables = [("Runs", ["run", "label", "protocol", "probes", "gallery"],
               [[i, r["label"], str(r["metrics"].get("protocol", "–")), format_value("", r["metrics"].get("n_probes")),
                 format_value("", r["metrics"].get("n_gallery"))] for i, r in zip(ids, runs)], "wrap"),
              ("Figures: value (95% interval)", columns, rows)]
    subsets = union("subsets")
    if subsets:
        tables.append(("Rank-1 by subset", ["subset", *ids],
                       by_run(subsets, lambda m, s: format_value("rank1", (m.get("subsets") or {}).get(s, {}).get("rank1")))))
    masks = union("masks")
    if masks:
        tables.append(("VR@0.1% by comparison mask", ["mask", *ids],
                       by_run(masks, lambda m, s: format_value("vr_at_far_0.001",
                                                               (m.get("masks") or {}).get(s, {}).get("vr_at_far_0.001")))))
    timings = union("timings")
    if timings:
        tables.append(("Timings", ["", *ids], by_run(timings, lambda m, t: format_value(t, (m.get("timings") or {}).get(t)))))
    tests = []
    for (i, a), (j, b) in combinations(list(zip(ids, runs)), 2):
        if a["hits"] is not None and b["hits"] is not None:
            test = mcnemar(a["hits"], b["hits"])
            tests.append({"a": a["label"], "b": b["label"], **test, "differ": test["p"] < ALPHA})
            verdict = (f"differ (p < {ALPHA:g})" if tests[-1]["differ"] else "no significant difference") \
                if test["n"] else "no common probes"
            tests[-1]["row"] = [f"{i} vs {j}", str(test["n"]), str(test["a_only"]), str(test["b_only"]),
                                f"{test['p']:.3g}", verdict]
    if tests:
        tables.append(("Rank-1: McNemar tests on the same probes",
                       ["runs", "probes", "hit by first only", "hit by second only", "p", "verdict"],
                       [t.pop("row") for t in tests]))

    plots = {}

    def curves_of(*keys: str) -> dict:
        """{label: arrays} of the runs that have these non-empty curve arrays."""
        return {r["label"]: tuple(r["curves"][k] for k in keys) for r in runs
                if all(k in r["curves"] and r["curves"][k].size for k in keys)}

    with run_folder(out_dir, overwrite, files=COMPARE_FILES, what="a comparison") as work:
        plot_roc(curves_of("roc_fmr", "roc_tar"), work / "compare_roc.png")
        plots["ROC"] = "compare_roc.png"
        det = curves_of("det_fmr", "det_fnmr")
        if det:
            plot_det(det, work / "compare_det.png")
            plots["DET"] = "compare_det.png"
        plot_cmc({k: v[0] for k, v in curves_of("cmc").items()}, work / "compare_cmc.png")
        plots["CMC"] = "compare_cmc.png"
        write_pages(work, "compare", "facerec3d: comparison of runs", tables, plots)
    files = [str(Path(out_dir) / f) for f in (*plots.values(), "compare.html", "compare.md")]
    return {"columns": columns, "rows": rows, "tables": [t[:3] for t in tables], "mcnemar": tests,
            "runs": [{k: r[k] for k in ("label", "dir", "metrics")} for r in runs], "files": files}
