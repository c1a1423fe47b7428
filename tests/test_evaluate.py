"""End-to-end evaluation on a small synthetic FRGC-style dataset (chapter §8.4)."""

import csv
import json

import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from facerec3d.datasets.catalog import open_dataset
from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
from facerec3d.datasets.protocols import split
from facerec3d.evaluation.run import evaluate
from facerec3d.evaluation.scorefile import read_score_rows
from facerec3d.io import save_scan
from tests.conftest import faceless_scans

SMALL = ScannerConfig(rows=320, cols=400, focal_px=1000.0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("frgc")
    manifest = write_dataset(root, DatasetConfig(subjects=8, scans=4, seed=5, scanner=SMALL), "abs")
    bad = root / "nd1" / "Fall2003range"
    bad.mkdir(parents=True, exist_ok=True)
    (bad / "04200d900.abs.gz").write_bytes(b"\x1f\x8b garbage")
    save_scan(faceless_scans()["wall"], bad / "04201d901.abs")
    with open(manifest, "a", newline="") as f:
        w = csv.writer(f)
        w.writerow(["nd1/Fall2003range/04200d900.abs.gz", "04200", "neutral"])
        w.writerow(["nd1/Fall2003range/04201d901.abs", "04201", "non-neutral"])
    return root


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs")
    cache = out / "cache"
    one = evaluate(dataset, "icp", out / "one", jobs=1, cache=cache, progress=False)
    two = evaluate(dataset, "icp", out / "two", jobs=2, cache=cache, progress=False)
    return out, one, two


def test_frgc_protocol_split(dataset):
    ds = open_dataset(dataset)
    sp = split(ds)
    assert sp.protocol == "frgc" and len(sp.gallery) == 8
    assert all(ds.records[i].expression == "neutral" for i in sp.gallery)
    assert len(sp.probes) == len(ds) - 8
    assert set(sp.subsets) == {"neutral", "non-neutral", "pose:yaw"}  # the ±25° yaw probes are not neutral
    assert all(ds.records[sp.probes[k]].pose == "yaw" for k in sp.subsets["pose:yaw"])


@pytest.mark.slow  # a minute or more on 2 cores
def test_identification_and_verification_on_neutral_probes(runs):
    _, m, _ = runs
    assert m["subsets"]["neutral"]["rank1"] == 1.0
    assert m["rank1"] >= 0.9
    assert m["eer"] < 0.1
    assert m["n_gallery"] == 8


def test_failures_are_listed_and_counted(runs):
    _, m, _ = runs
    failed = {f["path"].rsplit("/", 1)[-1]: f["reason"] for f in m["failed_scans"]}
    assert set(failed) == {"04200d900.abs.gz", "04201d901.abs"}
    assert m["failures"] == 2 and m["n_probes"] == m["n_processed"] + 2
    assert m["rank1_all"] < m["rank1"] or m["rank1"] == 0


def test_jobs_do_not_change_results(runs):
    _, one, two = runs
    for key in ("rank1", "rank5", "eer", "vr_at_far_0.001", "vr_at_far_0.01", "n_probes", "failures"):
        assert one[key] == two[key]
    assert one["subsets"] == two["subsets"]


def test_run_folder_contents(runs):
    out, m, _ = runs
    run = out / "one"
    for name in ("metrics.json", "scores.txt", "roc.png", "det.png", "cmc.png", "scores_hist.png", "report.html"):
        assert (run / name).is_file(), name
    rows = read_score_rows(run / "scores.txt")
    assert len(rows.score) == m["n_processed"] * m["n_gallery"]
    assert json.loads((run / "metrics.json").read_text())["method"] == "icp"


def test_cli_evaluate_and_compare(dataset, runs, tmp_path):
    out, _, _ = runs
    r = CliRunner().invoke(main, ["evaluate", str(dataset), "--out", str(tmp_path / "cli"), "--jobs", "1",
                                  "--cache", str(out / "cache")])
    assert r.exit_code == 0, r.output
    assert "non-neutral" in r.output and "failed (probe)" in r.output
    r = CliRunner().invoke(main, ["compare", str(out / "one"), str(tmp_path / "cli"), "--out", str(tmp_path / "cmp")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "cmp" / "compare.html").is_file()
    r = CliRunner().invoke(main, ["evaluate", str(tmp_path / "nothing-here.csv"), "--out", str(tmp_path / "x")])
    assert r.exit_code == 2
    gone = tmp_path / "gone"  # a manifest whose every scan is missing: each a failure, and the run exits 1
    gone.mkdir()
    (gone / "manifest.csv").write_text((dataset / "manifest.csv").read_text())
    r = CliRunner().invoke(main, ["evaluate", str(gone / "manifest.csv"), "--out", str(tmp_path / "g"), "--jobs", "1",
                                  "--cache", str(out / "cache")])
    assert r.exit_code == 1 and "error: no comparison made: 0 gallery faces enrolled, 0 probes processed" in r.output, \
        r.output
    n_scans = len((dataset / "manifest.csv").read_text().splitlines()) - 1
    assert r.output.count("failed (gallery): ") + r.output.count("failed (probe): ") == n_scans and f"{n_scans} scans failed" in r.output, r.output
    assert "rank-1" not in r.output and "per comparison" not in r.output  # no table of dashes, no time of 0 matches
    timings = json.loads((tmp_path / "g" / "metrics.json").read_text())["timings"]
    assert "match_ms" not in timings and "matches_per_s" not in timings
    curves = tmp_path / "cli" / "curves.npz"  # a run's damaged curves: one line naming the file
    curves.write_bytes(curves.read_bytes()[:200])
    r = CliRunner().invoke(main, ["compare", str(out / "one"), str(tmp_path / "cli"), "--out", str(tmp_path / "cmp2")])
    assert r.exit_code == 2 and f"{curves}: not a run's curves file, or a damaged one" in r.output, r.output


@pytest.mark.slow  # a minute or more on 2 cores
def test_icp_identifies_40_subjects_from_neutral_scans(tmp_path):
    """Issue 4's criterion: 40 subjects, neutral gallery, neutral probes: rank-1 100%, genuine and impostor apart."""
    data = tmp_path / "d"
    write_dataset(data, DatasetConfig(subjects=40, scans=2, seed=9, scanner=SMALL), "abs")
    m = evaluate(data, "icp", tmp_path / "run", jobs=2, cache=tmp_path / "cache", progress=False)
    assert m["n_probes"] == 40 and m["failures"] == 0
    assert m["rank1"] == 1.0
    rows = read_score_rows(tmp_path / "run" / "scores.txt")
    genuine = [s for c, r, s in zip(rows.claimed_id, rows.real_id, rows.score) if c == r]
    impostor = [s for c, r, s in zip(rows.claimed_id, rows.real_id, rows.score) if c != r]
    assert len(genuine) == 40 and min(genuine) > max(impostor)


def test_cli_method_config_sets_the_matcher_and_bad_settings_are_one_line(dataset, runs, tmp_path):
    out, _, _ = runs
    good, bad = tmp_path / "p2plane.toml", tmp_path / "bad.toml"
    good.write_text('variant = "point-to-plane"\nfine_points = 800\n')
    bad.write_text('variant = "point-to-plane"\nfine_pionts = 800\n')
    base = ["evaluate", str(dataset), "--method", "icp", "--jobs", "1", "--cache", str(out / "cache")]
    r = CliRunner().invoke(main, base + ["--out", str(tmp_path / "p2p"), "--method-config", str(good)])
    assert r.exit_code == 0, r.output
    m = json.loads((tmp_path / "p2p" / "metrics.json").read_text())
    assert m["options"]["variant"] == "point-to-plane" and m["options"]["fine_points"] == 800
    assert m["subsets"]["neutral"]["rank1"] == 1.0
    r = CliRunner().invoke(main, base + ["--out", str(tmp_path / "bad"), "--method-config", str(bad)])
    assert r.exit_code == 2 and "fine_pionts: unknown setting (did you mean 'fine_points'?)" in r.output
    assert "Traceback" not in r.output


def test_a_cascade_for_a_method_it_does_not_suit_is_refused_before_training(dataset, tmp_path, monkeypatch):
    import facerec3d.evaluation.run as run_module
    from facerec3d.errors import InputError
    from facerec3d.gallery.cascade import CascadeConfig

    def trained(*args, **kwargs):
        raise AssertionError("trained before the cascade was checked")

    monkeypatch.setattr(run_module, "trained_matcher", trained)
    with pytest.raises(InputError, match="the cascade works with the icp method, not 'lda'"):
        evaluate(dataset, "lda", tmp_path / "run", cascade=CascadeConfig(), train=dataset, progress=False)
