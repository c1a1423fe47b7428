"""Compare run folders written by report.write_run: overlaid curves and one table."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from facerec3d.evaluation.plots import plot_cmc, plot_det, plot_roc
from facerec3d.evaluation.report import format_value, write_pages

# (metrics.json key, column name) of the fixed columns
COLUMNS = (
    ("fta_rate", "FTA"),
    ("rank1", "rank-1"),
    ("rank5", "rank-5"),
    ("eer", "EER"),
    ("vr_at_far_0.001", "VR@0.1%"),
    ("vr_at_far_0.01", "VR@1%"),
)


def _load(run_dir: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """A run's metrics.json and curves.npz arrays ({} when curves.npz is absent)."""
    path = run_dir / "metrics.json"
    if not path.is_file():
        raise ValueError(f"{run_dir}: not a run folder (no metrics.json)")
    metrics = json.loads(path.read_text(encoding="utf-8"))
    curves = run_dir / "curves.npz"
    if not curves.is_file():
        return metrics, {}
    with np.load(curves, allow_pickle=False) as z:
        return metrics, {k: z[k] for k in z.files}


def compare_runs(run_dirs: Sequence[str | Path], out_dir: str | Path) -> dict:
    """Overlay the runs' curves and tabulate their headline metrics in out_dir.

    Writes compare_roc.png and compare_cmc.png, compare_det.png when some run
    has a DET curve, and compare.html / compare.md with one table: a row per
    run, labelled "<method> (<folder name>)"; columns FTA, rank-1, rank-5, EER,
    VR@0.1%, VR@1%, rank-1 of each subset found in any run, and each timings
    entry found in any run (named as in metrics.json, unit in the name). A run
    without curves.npz is tabulated but not plotted. Raises ValueError naming
    the folder when a run folder has no metrics.json.

    Returns {"columns": [...], "rows": [[cell, ...], ...], "runs": [{"label",
    "dir", "metrics"}, ...], "files": [written paths]}.
    """
    if not run_dirs:
        raise ValueError("no run folders to compare")
    runs = []
    for d in map(Path, run_dirs):
        metrics, curves = _load(d)
        method = metrics.get("method")
        runs.append({"label": f"{method} ({d.name})" if method else d.name, "dir": str(d), "metrics": metrics,
                     "curves": curves})
    labels = [r["label"] for r in runs]
    for i, r in enumerate(runs):  # keep labels unique so no curve hides another
        if labels.count(r["label"]) > 1:
            r["label"] = f"{r['label']} #{i + 1}"

    subsets = list(dict.fromkeys(s for r in runs for s in r["metrics"].get("subsets") or {}))
    timings = list(dict.fromkeys(t for r in runs for t in r["metrics"].get("timings") or {}))
    columns = ["run", *(c for _, c in COLUMNS), *(f"rank-1 {s}" for s in subsets), *timings]
    rows = []
    for r in runs:
        m = r["metrics"]
        rows.append([
            r["label"],
            *(format_value(k, m.get(k)) for k, _ in COLUMNS),
            *(format_value("rank1", (m.get("subsets") or {}).get(s, {}).get("rank1")) for s in subsets),
            *(format_value(t, (m.get("timings") or {}).get(t)) for t in timings),
        ])

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plots = {}

    def curves_of(*keys: str) -> dict:
        """{label: arrays} of the runs that have these non-empty curve arrays."""
        return {r["label"]: tuple(r["curves"][k] for k in keys) for r in runs
                if all(k in r["curves"] and r["curves"][k].size for k in keys)}

    plot_roc(curves_of("roc_fmr", "roc_tar"), out / "compare_roc.png")
    plots["ROC"] = "compare_roc.png"
    det = curves_of("det_fmr", "det_fnmr")
    if det:
        plot_det(det, out / "compare_det.png")
        plots["DET"] = "compare_det.png"
    plot_cmc({k: v[0] for k, v in curves_of("cmc").items()}, out / "compare_cmc.png")
    plots["CMC"] = "compare_cmc.png"
    write_pages(out, "compare", "facerec3d: comparison of runs", [("Runs", columns, rows)], plots)
    files = [str(out / f) for f in (*plots.values(), "compare.html", "compare.md")]
    return {"columns": columns, "rows": rows,
            "runs": [{k: r[k] for k in ("label", "dir", "metrics")} for r in runs], "files": files}
