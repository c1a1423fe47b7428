"""FRGC Experiment 3 on a synthetic FRGC-layout set with three semesters, and reruns from a report's record."""

import csv
import json
import shlex
from itertools import product

import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
from facerec3d.evaluation.metrics import FIGURES
from facerec3d.preprocess import PreprocessConfig

SMALL = ScannerConfig(rows=320, cols=400, focal_px=1000.0)
SEMESTERS = {"Spring2003range": "Spring2003", "Fall2003range": "Fall2003", "Spring2004range": "Spring2004"}


@pytest.fixture(scope="module")
def exp3(tmp_path_factory):
    """3 subjects x 6 scans (2 per semester) evaluated with --protocol frgc-exp3 through the command line."""
    root = tmp_path_factory.mktemp("exp3")
    write_dataset(root / "data", DatasetConfig(subjects=3, scans=6, seed=4, scanner=SMALL), "abs")
    args = ["evaluate", str(root / "data"), "--method", "icp", "--protocol", "frgc-exp3", "--out", str(root / "run"), "--jobs", "1",
            "--cache", str(root / "cache"), "--bootstrap", "200", "--seed", "3"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    return root, r.output, json.loads((root / "run" / "metrics.json").read_text())


def test_synthetic_frgc_layout_has_three_semesters_in_folders_and_manifest(exp3):
    root, _, _ = exp3
    rows = list(csv.DictReader(open(root / "data" / "manifest.csv")))
    assert {r["session"] for r in rows} == set(SEMESTERS)
    assert all(r["path"].split("/")[1] == r["session"] for r in rows)
    assert {r["pose"] for r in rows} == {"", "yaw", "yaw-pitch-roll"}


def test_exp3_reports_roc_i_ii_iii_with_pair_counts_computed_independently(exp3):
    root, output, m = exp3
    assert m["protocol"] == "frgc-exp3" and set(m["masks"]) == {"ROC I", "ROC II", "ROC III"}
    rows = list(csv.DictReader(open(root / "data" / "manifest.csv")))
    failed = {f["path"] for f in m["failed_scans"]}
    scans = [(r["subject"], SEMESTERS[r["session"]]) for r in rows
             if r["session"] != "Spring2003range" and str(root / "data" / r["path"]) not in failed]
    assert m["n_processed"] == len(scans) and "left out" in m["protocol_note"]
    rules = {"ROC I": lambda q, t: q == t, "ROC II": lambda q, t: True,  # Fall 2003 and Spring 2004: one year
             "ROC III": lambda q, t: (t, q) == ("Fall2003", "Spring2004")}
    for name, rule in rules.items():
        pairs = [(a[0] == b[0]) for (i, a), (j, b) in product(enumerate(scans), repeat=2) if i != j and rule(a[1], b[1])]
        got = m["masks"][name]
        assert (got["n_genuine"], got["n_impostor"]) == (sum(pairs), len(pairs) - sum(pairs)), name
        assert got["vr_at_far_0.001"] is not None and got["ci95"]["eer"] is not None
        assert f"mask {name} " in output
    assert (root / "run" / "roc_masks.png").is_file()
    assert "(value (95% interval), subject-level bootstrap)" in output
    assert "ROC by comparison mask" in (root / "run" / "report.md").read_text()


def test_every_figure_has_its_interval_around_it(exp3):
    _, _, m = exp3
    sets = {"all": m, **m["subsets"], **m["masks"]}
    assert len(sets) == 1 + len(m["subsets"]) + 3 and m["bootstrap"]["replicates"] == 200
    for name, s in sets.items():
        assert s["ci95"].keys() == set(FIGURES), name
        for k in FIGURES:
            if s[k] is None:
                continue
            lo, hi = s["ci95"][k]
            assert (lo is None or lo <= s[k]) and (hi is None or s[k] <= hi), (name, k)


def figures(m: dict) -> dict:
    """Everything of metrics.json that is a result (not timings, provenance, paths or dates)."""
    keep = {k: v for k, v in m.items() if k not in ("timings", "provenance", "dataset", "options", "scan_quality")}
    keep["failed_scans"] = sorted(f["path"] for f in m["failed_scans"])
    return keep


def test_report_records_enough_to_rerun_and_the_rerun_gives_the_same_figures(exp3, tmp_path):
    root, _, m = exp3
    p = m["provenance"]
    assert p["facerec3d_version"] and p["date"] and p["machine"]["cores"] >= 1 and "git_commit" in p
    assert m["preprocess"]["crop_radius_mm"] == PreprocessConfig().crop_radius_mm and m["options"]["variant"] == "point-to-point"
    report = (root / "run" / "report.md").read_text()
    assert shlex.join(p["rerun"]) in report and "Preprocessing configuration" in report
    rerun = list(p["rerun"])
    assert rerun[:2] == ["facerec3d", "evaluate"]
    rerun[rerun.index("--out") + 1] = str(tmp_path / "again")
    r = CliRunner().invoke(main, rerun[1:])
    assert r.exit_code == 0, r.output
    again = json.loads((tmp_path / "again" / "metrics.json").read_text())
    assert figures(again) == figures(m)
    assert again["options"] == m["options"]
    # timings: first use (JIT compilation, worker start) apart from the steady state; cached apart from computed
    first, second = m["timings"], again["timings"]
    assert second["preprocess_cached"] == m["n_gallery"] == first["preprocess_computed"] + first["preprocess_cached"]
    assert second["preprocess_computed"] == 0
    for t in (first, second):
        assert {"enrol_first_s", "enrol_ms", "match_first_s", "match_ms", "prepare_ms"} <= t.keys()
