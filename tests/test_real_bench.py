"""benchmarks/real_bench.py's argument handling (the benchmark itself needs the real data, which tests do not)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import real_bench  # noqa: E402


def test_score_files_split_on_commas_between_files_not_inside_a_name():
    assert real_bench.parse_score_files("a=/x/w_1,1,1.txt,b=y.txt") == [("a", "/x/w_1,1,1.txt"), ("b", "y.txt")]
    assert real_bench.parse_score_files(" a=x.txt , ") == [("a", "x.txt")]
    assert real_bench.parse_score_files("") == []
    assert real_bench.parse_score_files("nolabel") == [("nolabel", "")]


def test_a_missing_score_file_is_refused_in_one_line_before_any_method_runs(tmp_path, capsys):
    (tmp_path / "manifest.csv").write_text("path,subject,pose,role\n")
    (tmp_path / "intrinsics.json").write_text("{}")
    with pytest.raises(SystemExit) as e:
        real_bench.main(["--data", str(tmp_path), "--methods", "icp", "--anchors", "", "--out", str(tmp_path / "o"),
                         "--scores", f"w={tmp_path / 'missing.txt'}"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "missing.txt" in err and "existing score file" in err
    assert not (tmp_path / "o").exists()  # nothing ran


def test_training_on_the_tuning_half_never_lists_a_held_out_person(tmp_path):
    manifest = [{"path": f"{s}/{p}_1.png", "subject": s, "pose": p, "role": "gallery" if p == "front" else "probe"}
                for s in ("s000", "s001", "s002", "s003") for p in ("front", "left")]
    path = real_bench.tuning_manifest(tmp_path, manifest, tmp_path)
    rows = path.read_text().splitlines()
    assert rows[0] == "path,subject,pose"
    listed = [r.split(",") for r in rows[1:]]
    assert {s for _, s, _ in listed} == {"s000", "s002"} and len(listed) == 4  # the even-index (tuning) half
    assert all(Path(p).is_absolute() and Path(p).parent.name == s for p, s, _ in listed)


def test_the_strangers_eer_takes_impostors_from_the_strangers_scores_and_genuine_ones_from_the_scores():
    """Two probes of two people: as scored (impostors 0.1, 0.2 below both genuine 0.9, 0.8) no error; scored as
    strangers' claims one impostor (0.85) outscores a genuine score (0.8): one error of two on each side at best.
    The strangers matrix's genuine entries (NaN here, as scores.strangers.txt has none) are never read."""
    S = np.array([[0.9, 0.1], [0.2, 0.8]])
    T = np.array([[np.nan, 0.3], [0.85, np.nan]])
    args = (["a", "b"], ["a", "b"], ["front", "left"], [False, False])
    m = real_bench.identification_metrics(S, *args, S_strangers=T)
    assert m["eer"] == 0.0 and m["rank1_all"] == 1.0
    assert m["eer_strangers"] == pytest.approx(0.5)
    assert real_bench.identification_metrics(S, *args)["eer_strangers"] is None
    assert real_bench.identification_metrics(S, *args, S_strangers=S)["eer_strangers"] == m["eer"]
