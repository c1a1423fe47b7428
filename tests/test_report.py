"""Run folders (write_run), reports and run comparison."""

import json

import numpy as np
import pytest

from facerec3d.evaluation.compare import compare_runs
from facerec3d.evaluation.metrics import summarize
from facerec3d.evaluation.report import write_run

RUN_FILES = ("scores.txt", "metrics.json", "curves.npz", "roc.png", "det.png", "cmc.png", "scores_hist.png",
             "report.html", "report.md")


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


def make_run(path, seed, method):
    S, probes, labels, gallery, neutral = random_run(seed)
    metrics = {"method": method, "protocol": "test", "n_gallery": len(gallery),
               "timings": {"enrol_s": 1.5 + seed, "match_ms": np.float64(0.25)}}
    return write_run(path, S, probes, labels, gallery, metrics, n_failed=1,
                     subsets={"neutral": neutral, "non-neutral": ~neutral}, subset_failures={"non-neutral": 1})


def test_write_run_creates_every_file(tmp_path):
    result = make_run(tmp_path / "run", 0, "icp")
    for name in RUN_FILES:
        assert (tmp_path / "run" / name).stat().st_size > 0, name
    for name in ("roc.png", "det.png", "cmc.png", "scores_hist.png"):
        assert (tmp_path / "run" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics == result
    S, probes, labels, gallery, neutral = random_run(0)
    assert {k: metrics[k] for k in summarize(S, probes, gallery)} == pytest.approx(summarize(S, probes, gallery, 1))
    assert metrics["method"] == "icp" and metrics["timings"] == {"enrol_s": 1.5, "match_ms": 0.25}
    assert metrics["subsets"]["neutral"]["n_probes"] == 9 and metrics["subsets"]["non-neutral"]["n_probes"] == 10
    assert metrics["subsets"]["non-neutral"]["failures"] == 1

    with np.load(tmp_path / "run" / "curves.npz") as z:
        assert set(z.files) == {"roc_fmr", "roc_tar", "det_fmr", "det_fnmr", "cmc"}
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
    assert [r[0] for r in result["rows"]] == ["icp (a)", "pca (b)"]
    assert result["columns"] == ["run", "FTA", "rank-1", "rank-5", "EER", "VR@0.1%", "VR@1%",
                                 "rank-1 neutral", "rank-1 non-neutral", "enrol_s", "match_ms"]
    rank1 = json.loads((tmp_path / "a" / "metrics.json").read_text())["rank1"]
    assert result["rows"][0][2] == f"{100 * rank1:.2f}%"
    for page in ("compare.html", "compare.md"):
        text = (tmp_path / "cmp" / page).read_text()
        assert "icp (a)" in text and "pca (b)" in text and "compare_roc.png" in text


def test_compare_runs_names_folder_without_metrics(tmp_path):
    make_run(tmp_path / "a", 0, "icp")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="empty"):
        compare_runs([tmp_path / "a", tmp_path / "empty"], tmp_path / "cmp")
