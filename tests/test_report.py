"""Run folders (write_run), reports and run comparison."""

import html
import json

import numpy as np
import pytest

from facerec3d.evaluation.compare import compare_runs
from facerec3d.evaluation.metrics import FIGURES, summarize
from facerec3d.evaluation.report import write_run

RUN_FILES = ("scores.txt", "metrics.json", "probes.csv", "curves.npz", "roc.png", "det.png", "cmc.png", "open_set.png",
             "scores_hist.png", "report.html", "report.md")


def random_run(seed: int, n_subjects: int = 6, n_probes: int = 18):
    """A score matrix with one template per subject; genuine scores shifted up, one NaN."""
    rng = np.random.default_rng(seed)
    gallery = [f"s{i:02d}" for i in range(n_subjects)]
    probes = [gallery[i % n_subjects] for i in range(n_probes)]
    S = rng.normal(0, 1, (n_probes, n_subjects))
    S[np.arange(n_probes), np.arange(n_probes) % n_subjects] += 2.0
    S[0, 1] = np.nan
    labels = [f"p{i:03d}" for i in range(n_probes)]
    neutral = np.arange(n_probes) % 2 == 0
    return S, probes, labels, gallery, neutral


def make_run(path, seed, method, strangers=False):
    """A run folder; `strangers`: its impostors also scored as strangers' claims, 0.5 higher (as a method
    normalised over the gallery scores them without the probe's own entry)."""
    S, probes, labels, gallery, neutral = random_run(seed)
    metrics = {"method": method, "protocol": "test", "n_gallery": len(gallery),
               "timings": {"enrol_s": 1.5 + seed, "match_ms": np.float64(0.25)}}
    return write_run(path, S, probes, labels, gallery, metrics, n_failed=1,
                     subsets={"neutral": neutral, "non-neutral": ~neutral}, subset_failures={"non-neutral": 1},
                     strangers=S + 0.5 if strangers else None)


def test_write_run_creates_every_file(tmp_path):
    result = make_run(tmp_path / "run", 0, "icp")
    for name in RUN_FILES:
        assert (tmp_path / "run" / name).stat().st_size > 0, name
    for name in ("roc.png", "det.png", "cmc.png", "open_set.png", "scores_hist.png"):
        assert (tmp_path / "run" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics == result
    S, probes, labels, gallery, neutral = random_run(0)
    plain = summarize(S, probes, gallery, 1)  # the failure's subject is not known: no interval for it
    assert {k: metrics[k] for k in plain if k not in ("ci95", "n_subjects")} == pytest.approx(
        {k: v for k, v in plain.items() if k not in ("ci95", "n_subjects")})
    assert metrics["bootstrap"]["replicates"] == 1000 and metrics["ci95"].keys() == set(FIGURES)
    assert metrics["method"] == "icp" and metrics["timings"] == {"enrol_s": 1.5, "match_ms": 0.25}
    assert metrics["subsets"]["neutral"]["n_probes"] == 9 and metrics["subsets"]["non-neutral"]["n_probes"] == 10
    assert metrics["subsets"]["non-neutral"]["failures"] == 1

    with np.load(tmp_path / "run" / "curves.npz") as z:
        assert set(z.files) == {"roc_fmr", "roc_tar", "det_fmr", "det_fnmr", "cmc", "openset_fpir", "openset_fnir"}
        assert z["cmc"].shape == (6,) and z["cmc"][-1] == 1.0
        assert z["roc_fmr"][0] == 0 and z["roc_fmr"][-1] == 1

    assert len((tmp_path / "run" / "scores.txt").read_text().splitlines()) == 18 * 6 - 1
    page = (tmp_path / "run" / "report.html").read_text()
    assert 'src="roc.png"' in page and "non-neutral" in page and "match_ms" in page
    assert "![CMC](cmc.png)" in (tmp_path / "run" / "report.md").read_text()


def test_write_run_rejects_bad_subset_mask(tmp_path):
    S, probes, labels, gallery, _ = random_run(0)
    with pytest.raises(ValueError, match="subset 'x'"):
        write_run(tmp_path, S, probes, labels, gallery, {}, subsets={"x": np.arange(18)})


def test_compare_runs(tmp_path):
    make_run(tmp_path / "a", 0, "icp")
    make_run(tmp_path / "b", 1, "pca")
    result = compare_runs([tmp_path / "a", tmp_path / "b"], tmp_path / "cmp")
    for name in ("compare_roc.png", "compare_cmc.png", "compare_det.png", "compare.html", "compare.md"):
        assert (tmp_path / "cmp" / name).stat().st_size > 0, name
    assert [r[0] for r in result["rows"]] == ["#1", "#2"]
    assert result["columns"] == ["run", "FTA", "rank-1", "EER", "VR@0.1%", "VR@1%", "FNIR@FPIR 1%"]
    a = json.loads((tmp_path / "a" / "metrics.json").read_text())
    lo, hi = a["ci95"]["rank1"]
    assert result["rows"][0][2] == f"{100 * a['rank1']:.2f}% ({100 * lo:.2f}–{100 * hi:.2f}%)"
    tables = {heading: (columns, rows) for heading, columns, rows in result["tables"]}
    assert tables["Runs"][1][0][:2] == ["#1", "icp (a)"]
    assert tables["Rank-1 by subset"] == (["subset", "#1", "#2"], [
        ["neutral", *(f"{100 * json.loads((tmp_path / r / 'metrics.json').read_text())['subsets']['neutral']['rank1']:.2f}%"
                      for r in "ab")],
        ["non-neutral", *(f"{100 * json.loads((tmp_path / r / 'metrics.json').read_text())['subsets']['non-neutral']['rank1']:.2f}%"
                          for r in "ab")]])
    assert [row[0] for row in tables["Timings"][1]] == ["enrol_s", "match_ms"]
    for page in ("compare.html", "compare.md"):
        text = (tmp_path / "cmp" / page).read_text()
        assert "icp (a)" in text and "pca (b)" in text and "compare_roc.png" in text


def test_compare_runs_names_folder_without_metrics(tmp_path):
    make_run(tmp_path / "a", 0, "icp")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="empty"):
        compare_runs([tmp_path / "a", tmp_path / "empty"], tmp_path / "cmp")
    (tmp_path / "list").mkdir()  # JSON, but not a run's metrics: one line, not an AttributeError
    (tmp_path / "list" / "metrics.json").write_text("[]")
    with pytest.raises(ValueError, match=r"list/metrics\.json: not a metrics file \(a JSON list, not an object\)"):
        compare_runs([tmp_path / "a", tmp_path / "list"], tmp_path / "cmp")


def test_histogram_counts_every_score_as_the_table_does(tmp_path):
    """Scores of -inf (e.g. faces off the cascade's shortlist) are in the table's counts and in the plot's."""
    S, probes, labels, gallery, _ = random_run(2)
    S[1:4, :] = -np.inf  # 3 genuine and 15 impostor comparisons that could not be made well
    m = write_run(tmp_path, S, probes, labels, gallery, {}, bootstrap=0)
    n_genuine = int((np.array(probes)[:, None] == np.array(gallery)[None, :]).sum())
    n_impostor = S.size - n_genuine - 1  # one NaN (not compared)
    assert (m["n_genuine"], m["n_impostor"]) == (n_genuine, n_impostor)
    report = (tmp_path / "report.md").read_text()
    assert f"genuine ({n_genuine}, 3 at −inf)" in report and f"impostor ({n_impostor}, 15 at −inf)" in report
    assert f"| Impostor comparisons | {n_impostor} |" in report


def test_report_holds_settings_whole_failed_scans_as_a_table_and_thresholds(tmp_path):
    S, probes, labels, gallery, _ = random_run(0)
    options = {"regions": [{"name": f"region-{i}", "radius_mm": 25.0 + i} for i in range(20)]}
    failed = [{"path": "/data/nd1/Fall2003range/04200d900.abs.gz", "reason": "no face found", "role": "probe"}]
    metrics = {"method": "fusion", "options": options, "preprocess": {"crop_radius_mm": 80.0, "denoise": {"method": "median"}},
               "provenance": {"rerun": ["facerec3d", "evaluate", "/data/my scans", "--out", "run"]},
               "failed_scans": failed}
    m = write_run(tmp_path, S, probes, labels, gallery, metrics, failed=[("04200d900", "s00")], bootstrap=100)
    for page in ("report.md", "report.html"):
        text = html.unescape((tmp_path / page).read_text())
        assert "…" not in text and "region-19" in text
        assert "denoise.method" in text and "crop_radius_mm" in text
        assert "facerec3d evaluate '/data/my scans' --out run" in text
        assert "no face found" in text and "04200d900.abs.gz" in text and '"reason"' not in text
    md = (tmp_path / "report.md").read_text()
    assert "| scan | role | reason |" in md
    assert f"| Threshold at FMR 0.1% | {m['threshold_at_far_0.001']:.4g} |" in md
    assert m["failures"] == 1 and m["n_subjects"] == 6 and m["ci95"]["fta_rate"][1] > 0
    rows = (tmp_path / "probes.csv").read_text().splitlines()
    assert rows[0] == "probe,subject,status,rank,mated_score,nonmated_score" and rows[-1] == "04200d900,s00,failed,,,"


def test_comparison_masks_are_summarised_and_plotted(tmp_path):
    S, probes, labels, gallery, _ = random_run(1)
    upper = np.zeros(S.shape, bool)
    upper[:9] = True
    m = write_run(tmp_path, S, probes, labels, gallery, {}, masks={"first half": upper}, bootstrap=50)
    expected = summarize(np.where(upper, S, np.nan), probes, gallery, identification=False, bootstrap=50)
    assert m["masks"]["first half"] == expected
    assert m["masks"]["first half"]["n_genuine"] + m["masks"]["first half"]["n_impostor"] == 9 * 6 - 1
    assert m["masks"]["first half"]["rank1"] is None
    assert (tmp_path / "roc_masks.png").read_bytes()[:4] == b"\x89PNG"


def table_width_px(columns, rows, char_px=8.0, padding_px=18.0):
    """Width of an HTML table whose cells do not wrap, at 14 px sans-serif: about 8 px a character (digits
    7.8 px) plus 0.6 em padding each side and a border."""
    return sum(char_px * max(len(str(c)) for c in column) + padding_px for column in zip(columns, *rows))


def test_compare_tables_fit_a_1280_px_page_and_mcnemar_by_hand(tmp_path):
    for i, method in enumerate(("icp", "pca", "lda", "region-icp", "fusion")):
        make_run(tmp_path / f"run-{method}", i, method, strangers=method in ("region-icp", "fusion"))
    result = compare_runs([tmp_path / d for d in sorted(p.name for p in tmp_path.iterdir())], tmp_path / "cmp")
    assert "max-width:1200px" in (tmp_path / "cmp" / "compare.html").read_text()
    for heading, columns, rows in result["tables"]:
        assert table_width_px(columns, rows) <= 1280 - 2 * 28, heading  # 2 em body margins
    # McNemar by hand: run a hits probes 0-9, run b hits 5-14 of 20 common probes: discordant 5 and 5 -> p = 1;
    # run c hits 0-19: against a, 0 and 10 discordant -> p = 2 * 0.5**10
    for name, hits in (("a", range(10)), ("b", range(5, 15)), ("c", range(20))):
        d = tmp_path / "mc" / name
        d.mkdir(parents=True)
        (d / "metrics.json").write_text(json.dumps({"method": name}))
        (d / "probes.csv").write_text("probe,subject,status,rank,mated_score,nonmated_score\n" + "".join(
            f"p{i},s{i},processed,{1 if i in hits else 3},0.5,0.4\n" for i in range(20)))
    tests = compare_runs([tmp_path / "mc" / n for n in "abc"], tmp_path / "cmp2")["mcnemar"]
    got = {(t["a"], t["b"]): (t["n"], t["a_only"], t["b_only"], t["p"], t["differ"]) for t in tests}
    assert got[("a", "b")] == (20, 5, 5, pytest.approx(1.0), False)  # a run named after its method: its name once
    assert got[("a", "c")] == (20, 0, 10, pytest.approx(2 * 0.5**10), True)
    assert got[("b", "c")] == (20, 0, 10, pytest.approx(2 * 0.5**10), True)
    assert "differ (p < 0.05)" in (tmp_path / "cmp2" / "compare.md").read_text()


def test_a_run_scored_also_as_strangers_claims_shows_both_eers_in_its_report_and_comparison(tmp_path):
    """Impostors scored higher as strangers' claims: a higher EER beside the protocol's; genuine scores, counts and
    identification as before; compare shows it beside the EER ("–" for a run without it)."""
    plain = make_run(tmp_path / "a", 0, "icp")
    both = make_run(tmp_path / "b", 0, "fusion", strangers=True)
    st = both["strangers"]
    assert {k: both[k] for k in ("rank1", "eer", "n_genuine")} == {k: plain[k] for k in ("rank1", "eer", "n_genuine")}
    assert st["n_genuine"] == both["n_genuine"] and st["n_impostor"] == both["n_impostor"] and st["rank1"] is None
    assert st["eer"] > both["eer"] and st["threshold_at_eer"] > both["threshold_at_eer"]
    assert (tmp_path / "b" / "scores.strangers.txt").is_file() and not (tmp_path / "a" / "scores.strangers.txt").exists()
    assert "all probes, impostors as strangers" in (tmp_path / "b" / "report.md").read_text()
    result = compare_runs([tmp_path / "a", tmp_path / "b"], tmp_path / "cmp")
    k = result["columns"].index("EER, strangers")
    assert result["columns"][k - 1] == "EER" and result["rows"][0][k] == "–"
    assert result["rows"][1][k] == f"{100 * st['eer']:.2f}%"


def test_compare_runs_names_a_damaged_run_file(tmp_path):
    """A run folder whose probes.csv or metrics.json is damaged (a column missing, not UTF-8, a JSON list or number
    where compare reads an object or an interval): an InputError naming the file, not a KeyError, UnicodeDecodeError
    or AttributeError."""
    import shutil

    from facerec3d.errors import InputError

    make_run(tmp_path / "a", 0, "icp")
    good = (tmp_path / "a" / "metrics.json").read_text()
    damage = [("probes.csv", b"label,rank,status\np1,1,ok\n", "no column probe"),
              ("probes.csv", b"probe,rank,status\n\xff\xfe,1,ok\n", "not UTF-8"),
              ("metrics.json", json.dumps({**json.loads(good), "subsets": [1]}), "'subsets' is a JSON list"),
              ("metrics.json", json.dumps({**json.loads(good), "subsets": {"x": 1}}), "subsets.x is a JSON int"),
              ("metrics.json", json.dumps({**json.loads(good), "ci95": 3}), "'ci95' is a JSON int"),
              ("metrics.json", json.dumps({**json.loads(good), "ci95": {"rank1": 0.5}}), "ci95.rank1 is not an interval"),
              ("metrics.json", json.dumps({**json.loads(good), "timings": [2]}), "'timings' is a JSON list")]
    for i, (name, text, reason) in enumerate(damage):
        run = tmp_path / f"b{i}"
        shutil.copytree(tmp_path / "a", run)
        (run / name).write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(InputError, match=f"{run / name}: .*{reason}"):
            compare_runs([tmp_path / "a", run], tmp_path / "cmp")
