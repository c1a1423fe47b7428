import pytest
from click.testing import CliRunner

from facerec3d.cli import main


def test_synth_info_convert_view(tmp_path):
    run = CliRunner()
    r = run.invoke(main, ["synth", str(tmp_path / "d"), "--subjects", "1", "--scans", "2", "--rows", "240", "--cols", "320"])
    assert r.exit_code == 0, r.output
    scan = next((tmp_path / "d").rglob("*.abs.gz"))
    r = run.invoke(main, ["info", str(scan)])
    assert r.exit_code == 0 and "240x320 grid" in r.output
    r = run.invoke(main, ["convert", str(scan), str(tmp_path / "s.ply")])
    assert r.exit_code == 0 and (tmp_path / "s.ply").stat().st_size > 0
    r = run.invoke(main, ["view", str(scan), "-o", str(tmp_path / "v.png")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "v.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_input_is_one_line_and_exit_code_2(tmp_path):
    bad = tmp_path / "bad.bnt"
    bad.write_bytes(b"\x01\x02")
    r = CliRunner().invoke(main, ["info", str(bad)])
    assert r.exit_code == 2
    assert "bad.bnt" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(main, ["convert", str(bad), str(tmp_path / "x.ply")])
    assert r.exit_code == 2 and "truncated header" in r.output


@pytest.mark.slow  # a minute or more on 2 cores
def test_demo_evaluates_each_method_and_compares_them(tmp_path):
    import json

    out = tmp_path / "demo"
    r = CliRunner().invoke(main, ["demo", "--subjects", "4", "--scans", "2", "--methods", "icp,lda", "--out", str(out),
                                  "--jobs", "1"])
    assert r.exit_code == 0, r.output
    icp, lda = (json.loads((out / m / "metrics.json").read_text()) for m in ("icp", "lda"))
    assert icp["method"] == "icp" and "train" not in icp
    assert lda["method"] == "lda" and lda["n_train_subjects"] == 4 and (out / "lda" / "model.npz").is_file()
    train = {line.split(",")[1] for line in (out / "train" / "manifest.csv").read_text().splitlines()[1:]}
    test = {line.split(",")[1] for line in (out / "data" / "manifest.csv").read_text().splitlines()[1:]}
    assert train and test and not train & test  # disjoint subjects
    assert icp["subsets"]["neutral"]["rank1"] == 1.0
    table = (out / "compare" / "compare.md").read_text()
    assert "| icp |" in table and "| lda |" in table and "icp (icp)" not in table  # each run named once

    # the same figures from the demo's score file alone, as from any system's; EER and VR as pyeer has them
    from tests.conftest import check_against_pyeer

    r = CliRunner().invoke(main, ["metrics", str(out / "icp" / "scores.txt"), "--out", str(tmp_path / "m")])
    assert r.exit_code == 0, r.output
    again = json.loads((tmp_path / "m" / "metrics.json").read_text())
    assert icp["failures"] == 0 and "subsets" in icp
    figures = [k for k in again if k not in ("scores", "scores_sha256", "format", "score_direction", "provenance")]
    assert figures and {k: again[k] for k in figures} == {k: icp[k] for k in figures}
    check_against_pyeer(out / "icp" / "scores.txt")
