import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from facerec3d.cli import main
from tests.conftest import cli_dataset


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


def test_synth_never_overwrites_a_dataset_unasked(tmp_path):
    """A second synth into a dataset's folder overwrote same-named scans (a gallery enrolled from them then holds
    other faces) and left the others behind: refused without --overwrite; with it, only the new dataset remains."""
    out, run = tmp_path / "d", CliRunner()
    small = ["--rows", "64", "--cols", "80"]
    r = run.invoke(main, ["synth", str(out), "--subjects", "2", "--scans", "3", *small])
    assert r.exit_code == 0, r.output
    (out / "notes.txt").write_text("mine")
    before = {p: p.read_bytes() for p in out.rglob("*.abs.gz")}
    r = run.invoke(main, ["synth", str(out), "--subjects", "1", "--scans", "2", "--seed", "3", *small])
    assert r.exit_code == 2 and r.output == f"error: {out}: holds a dataset already (manifest.csv); give --overwrite " \
                                            "to replace it\n", r.output
    assert {p: p.read_bytes() for p in out.rglob("*.abs.gz")} == before
    r = run.invoke(main, ["synth", str(out), "--subjects", "1", "--scans", "2", "--seed", "3", "--overwrite", *small])
    assert r.exit_code == 0, r.output
    listed = [line.split(",")[0] for line in (out / "manifest.csv").read_text().splitlines()[1:]]
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*.abs.gz")) == sorted(listed) and len(listed) == 2
    assert (out / "notes.txt").read_text() == "mine"  # not the dataset's: left alone


@pytest.mark.parametrize("args, said", [
    (["--seed", "-1"], "error: Invalid value for '--seed': -1 is not in the range x>=0."),
    (["--first-subject", "-5"], "error: Invalid value for '--first-subject': -5 is not in the range x>=0."),
    (["--expression-strength", "50", "50"], "error: Invalid value for '--expression-strength': 50.0 is not in the "
                                            "range 0.0<=x<=1.0."),
    (["--expression-strength", "nan", "nan"], "error: expression strength nan nan: give a range 0 <= low <= high"),
    (["--expression-strength", "0.9", "0.5"], "error: expression strength 0.9 0.5: give a range 0 <= low <= high"),
])
def test_synth_refuses_seeds_and_strengths_it_cannot_make_faces_of(tmp_path, args, said):
    """Negative seeds crashed (NumPy's ValueError), a NaN strength overflowed, and a strength of 50 wrote faces
    444 mm wide without a word: each is one line, exit code 2, and nothing is written."""
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "s"), "--subjects", "2", "--scans", "2", *args])
    assert r.exit_code == 2 and r.output.startswith(said) and r.output.count("\n") == 1, r.output
    assert not (tmp_path / "s").exists()


def test_usage_errors_are_one_line_naming_the_help_to_read(tmp_path):
    for args, said in ((["synth", str(tmp_path / "s"), "--subjects", "0"], "Invalid value for '--subjects'"),
                       (["verify"], "Missing argument 'PROBE'"), (["nosuch"], "No such command 'nosuch'")):
        r = CliRunner().invoke(main, args, prog_name="facerec3d")
        assert r.exit_code == 2 and r.output.count("\n") == 1 and r.output.startswith(f"error: {said}"), r.output
        assert f"(see facerec3d {args[0] + ' ' if args[0] != 'nosuch' else ''}--help)" in r.output, r.output
    r = CliRunner().invoke(main, [], prog_name="facerec3d")  # the command alone: its help
    assert r.output.startswith("Usage: facerec3d [OPTIONS] COMMAND") and "synth" in r.output, r.output


def test_a_threshold_that_is_no_number_is_refused(tmp_path):
    probe = tmp_path / "p.xyz"
    probe.write_text("0 0 0\n")
    for value in ("nan", "inf", "-inf"):  # `verify` said "reject (threshold nan)" for any score
        r = CliRunner().invoke(main, ["verify", str(probe), "--gallery", str(tmp_path / "g.sqlite"), "--claim", "a",
                                      "--threshold", value])
        assert r.exit_code == 2 and f"--threshold: must be a finite number, not {float(value)}" in r.output, r.output


def test_verify_help_names_the_calibrated_threshold_and_every_methods_default():
    """`verify --help` named only ICP's default threshold (-1.8 mm²): the gallery's calibrated threshold is used,
    else its method's default, each of the table the code uses."""
    from facerec3d.gallery.service import DEFAULT_THRESHOLDS

    r = CliRunner().invoke(main, ["verify", "--help"])
    text = " ".join(r.output.split())
    assert r.exit_code == 0 and "default: the gallery's calibrated threshold" in text, text
    said = ", ".join(f"{m} {v!r}{' mm²' if m == 'icp' else ''}" for m, v in DEFAULT_THRESHOLDS.items())
    assert f"else the method's default: {said};" in text and "fusion 4.0, embedding 0.5, icp -1.8 mm²" in text, text


@pytest.mark.parametrize("group", ["gallery", "keys"])
def test_a_groups_help_names_every_command_it_has(group):
    """`gallery --help` named "list, remove ID, stats" but not calibrate and rekey."""
    r = CliRunner().invoke(main, [group, "--help"])
    intro = " ".join(r.output.split("Options:")[0].split())
    assert r.exit_code == 0 and main.commands[group].commands, r.output
    for name in main.commands[group].commands:
        assert re.search(rf"[:,] {name}[,.]", intro), (name, intro)


@pytest.mark.parametrize("option, value, said", [
    ("--port", "70000", "not in the range 0<=x<=65535"), ("--port", "-1", "not in the range 0<=x<=65535"),
    ("--timeout", "nan", "must be a finite number, not nan"), ("--timeout", "inf", "must be a finite number"),
    ("--timeout", "-1", "not in the range x>0"), ("--timeout", "0", "not in the range x>0"),
    ("--max-upload-mb", "nan", "must be a finite number, not nan"), ("--max-upload-mb", "0", "not in the range x>=0.01"),
    ("--max-upload-mb", "1e-9", "not in the range x>=0.01"),  # int(1e-9 MiB) was a 0-byte limit: every upload 413
    ("--queue", "-5", "not in the range x>=0"), ("--per-key", "-1", "not in the range x>=1"),
    ("--per-key", "0", "not in the range x>=1"), ("--max-points", "-1", "not in the range 1<=x<=4000000"), ("--max-points", "5000000", "not in the range 1<=x<=4000000"),
    ("--concurrency", "-1", "not in the range x>=1")])
def test_serve_refuses_limits_it_cannot_keep_in_one_line(tmp_path, option, value, said):
    """`--port 70000` died on an OverflowError, `--timeout nan` on "cannot convert float NaN to integer"; `--timeout
    -1` served and answered every request 504; negative queue, per-key, max-points and concurrency were taken."""
    r = CliRunner().invoke(main, ["serve", "--gallery", str(tmp_path / "g.sqlite"), "--keys", str(tmp_path / "k.json"),
                                  option, value], prog_name="facerec3d")
    assert r.exit_code == 2 and r.output.count("\n") == 1 and r.output.startswith("error: Invalid value for"), r.output
    assert option in r.output and said in r.output and "(see facerec3d serve --help)" in r.output, r.output
    assert not (tmp_path / "g.sqlite").exists()


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


# ----------------------------------------------------------------------------- --train: what learns, from what
EXAMPLES = Path(__file__).parents[1] / "examples"
TRAIN_FIX = ("give --train DATA, scans of people other than those it will match (at least 2 people with 2 scans "
             "each), or a saved model (--model FILE)")


@pytest.fixture(scope="module")
def learning(tmp_path_factory):
    """3 people × 2 scans to enrol or evaluate on; a training manifest of 3 other people × 2 scans and one unreadable
    scan of a fourth; a preprocessing cache."""
    root = tmp_path_factory.mktemp("learning")
    data = cli_dataset(root / "d", 0.6)
    r = CliRunner().invoke(main, ["synth", str(root / "t"), "--subjects", "3", "--scans", "2", "--rows", "240",
                                  "--cols", "320", "--seed", "6", "--first-subject", "1000"])
    assert r.exit_code == 0, r.output
    (root / "bad.bnt").write_bytes(b"\x01\x02")
    rows = (root / "t" / "manifest.csv").read_text().splitlines()[1:]
    train = root / "train.csv"
    train.write_text("path,subject\n" + "".join(f"t/{row.split(',')[0]},{row.split(',')[1]}\n" for row in rows)
                     + "bad.bnt,09999\n")
    return data, train, str(root / "cache")


def test_a_learnt_method_without_train_names_what_learns_the_settings_file_and_the_fix(learning):
    """One line, exit 2: the fusion member that learns and the settings file that made it learn; wording that fits
    enrol as well as evaluate (not 'the test set')."""
    data, _, cache = learning
    fusion = EXAMPLES / "fusion-adapted.toml"
    r = CliRunner().invoke(main, ["enroll", *map(str, data.gallery), "--gallery", str(data.folder / "g.sqlite"),
                                  "--method", "fusion", "--method-config", str(fusion), "--jobs", "1", "--cache", cache])
    assert r.exit_code == 2 and r.output == (f"error: {fusion}: member 'embedding' of method 'fusion' must learn from "
                                             f"data: {TRAIN_FIX}\n"), r.output
    embedding = EXAMPLES / "embedding-adapted.toml"
    r = CliRunner().invoke(main, ["evaluate", str(data.folder), "--method", "embedding", "--method-config",
                                  str(embedding), "--out", str(data.folder / "run"), "--jobs", "1", "--cache", cache])
    assert r.exit_code == 2 and r.output == (f"error: {embedding}: method 'embedding' must learn from data: "
                                             f"{TRAIN_FIX}\n"), r.output
    r = CliRunner().invoke(main, ["evaluate", str(data.folder), "--method", "lda", "--out", str(data.folder / "run"),
                                  "--jobs", "1", "--cache", cache])
    assert r.exit_code == 2 and r.output == f"error: method 'lda' must learn from data: {TRAIN_FIX}\n", r.output


def test_train_says_what_the_method_learnt_from_and_warns_when_few_people(learning, tmp_path, monkeypatch):
    """evaluate and enroll say on stderr how many scans of how many people were learnt from (the unreadable scan
    and its person left out), and warn below FEW_TRAINING_PEOPLE."""
    from facerec3d.matching import registry

    data, train, cache = learning
    learnt = f"method 'pca' learnt from 6 scans of 3 people in {train} (1 scan failed to preprocess, left out)\n"
    few = (f"warning: {train}: 3 people only, too few to learn from reliably: give scans of 10 or more people (a few "
           "dozen are better)\n")
    r = CliRunner().invoke(main, ["evaluate", str(data.folder), "--method", "pca", "--train", str(train), "--out",
                                  str(tmp_path / "run"), "--bootstrap", "0", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0 and learnt + few in r.stderr and learnt not in r.stdout, r.output
    r = CliRunner().invoke(main, ["enroll", *map(str, data.gallery), "--gallery", str(tmp_path / "g.sqlite"),
                                  "--method", "lda", "--train", str(train), "--no-calibrate", "--jobs", "1",
                                  "--cache", cache])
    assert r.exit_code == 0 and learnt.replace("pca", "lda") + few in r.stderr, r.output
    monkeypatch.setattr(registry, "FEW_TRAINING_PEOPLE", 3)
    r = CliRunner().invoke(main, ["enroll", *map(str, data.gallery), "--gallery", str(tmp_path / "g2.sqlite"),
                                  "--method", "lda", "--train", str(train), "--no-calibrate", "--jobs", "1",
                                  "--cache", cache])
    assert r.exit_code == 0 and "learnt from 6 scans of 3 people" in r.stderr and "warning" not in r.stderr, r.output


def test_train_given_to_a_method_that_learns_nothing_is_a_warning_not_silence(learning, tmp_path):
    """Not read, not an error: one warning line on stderr, exit code 0, and nothing learnt recorded in the run."""
    import json

    data, train, cache = learning
    r = CliRunner().invoke(main, ["evaluate", str(data.folder), "--method", "curvature", "--train", str(train),
                                  "--out", str(tmp_path / "run"), "--bootstrap", "0", "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0, r.output
    assert f"warning: method 'curvature' learns nothing: --train {train} not used\n" in r.stderr, r.output
    assert "train" not in json.loads((tmp_path / "run" / "metrics.json").read_text())
    settings = tmp_path / "fusion.toml"
    settings.write_text('members = ["curvature"]\n')
    r = CliRunner().invoke(main, ["enroll", str(data.gallery[0]), "--gallery", str(tmp_path / "g.sqlite"), "--method",
                                  "fusion", "--method-config", str(settings), "--train", str(train), "--no-calibrate",
                                  "--jobs", "1", "--cache", cache])
    assert r.exit_code == 0 and r.stderr.startswith(f"warning: method 'fusion' learns nothing with the settings of "
                                                    f"{settings}: --train {train} not used\n"), r.output


@pytest.mark.parametrize("methods", ["", " , "])
def test_demo_refuses_no_methods_before_any_work(tmp_path, methods):
    """`demo --methods ""` synthesised the data first, then failed with "no run folders to compare"."""
    out = tmp_path / "demo"
    r = CliRunner().invoke(main, ["demo", "--subjects", "2", "--scans", "2", "--methods", methods, "--out", str(out)])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith("error: Invalid value for --methods: ") and "names no method" in r.output
    assert not out.exists()


@pytest.mark.parametrize("scans", ["1", "0", "-1"])
def test_demo_refuses_too_few_scans_for_a_protocol_before_any_work(tmp_path, scans):
    """`demo --scans 0` (or -1) synthesised nothing and then failed on the missing manifest.csv; `--scans 1` gave no
    probe ("all probes 0") with exit code 0. A protocol needs a gallery scan and a probe: a usage error, as
    synth's --scans."""
    out = tmp_path / "demo"
    r = CliRunner().invoke(main, ["demo", "--subjects", "2", "--scans", scans, "--methods", "icp", "--out", str(out)],
                           prog_name="facerec3d")
    assert r.exit_code == 2 and r.output == (f"error: Invalid value for '--scans': {scans} is not in the range x>=2. "
                                             "(see facerec3d demo --help)\n"), r.output
    assert not out.exists()


def test_calibrate_refuses_an_fmr_that_is_no_number_as_a_usage_error(tmp_path):
    """`gallery G calibrate --fmr nan` passed click's range check and died on "G: cannot convert float NaN to
    integer", blaming the store: a usage error naming --fmr now, before the store is opened."""
    r = CliRunner().invoke(main, ["gallery", str(tmp_path / "g.sqlite"), "calibrate", "--fmr", "nan"],
                           prog_name="facerec3d")
    assert r.exit_code == 2 and r.output == ("error: Invalid value for --fmr: must be a finite number, not nan "
                                             "(see facerec3d gallery [STORE] calibrate --help)\n"), r.output
    assert not (tmp_path / "g.sqlite").exists()


@pytest.mark.parametrize("args, refused", [
    (["gallery", "{g}", "calibrate", "--eer", "--fmr", "0.1"], "--fmr cannot be used with --eer"),
    (["identify", "{p}", "--gallery", "{g}", "--shortlist", "5"], "--shortlist works with --cascade only"),
    (["identify", "{p}", "--gallery", "{g}", "--screen", "embedding"], "--screen works with --cascade only"),
    (["evaluate", "{p}", "--out", "{o}", "--shortlist", "5"], "--shortlist works with --cascade only"),
])
def test_options_that_would_be_ignored_are_refused(tmp_path, args, refused):
    """`gallery G calibrate --eer --fmr 0.1` ignored --fmr, `identify --shortlist 5` without --cascade the
    shortlist: one line, before any work (the gallery is not even opened)."""
    (tmp_path / "p.abs").write_text("")
    names = {"g": tmp_path / "g.sqlite", "p": tmp_path / "p.abs", "o": tmp_path / "out"}
    r = CliRunner().invoke(main, [a.format(**names) for a in args])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: {refused}")
    assert not names["g"].exists() and not names["o"].exists()


@pytest.mark.parametrize("size, fmt", [(("100000", "100000"), "abs"), (("3000", "3000"), "png"),
                                       (("2001", "2000"), "bnt")])
def test_synth_refuses_scans_its_readers_would_refuse(tmp_path, size, fmt):
    """`synth --rows 100000 --cols 100000` was a MemoryError traceback, `--format png --rows 3000 --cols 3000` wrote
    frames that `info` refuses (over MAX_POINTS pixels): one line, before any work (OUT not made)."""
    from facerec3d.io.common import MAX_POINTS

    rows, cols = size
    r = CliRunner().invoke(main, ["synth", str(tmp_path / "x"), "--subjects", "1", "--scans", "1", "--rows", rows,
                                  "--cols", cols, "--format", fmt])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: --rows {rows} --cols {cols}: {int(rows) * int(cols)} pixels a scan, more than "
                               f"the {MAX_POINTS} facerec3d reads")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("shape", [(1, 500), (500, 1), "two points", "a line"])
def test_view_refuses_a_scan_too_thin_to_draw(tmp_path, shape):
    """`view --raw` of a 1×500 or 500×1 depth map, or of two points, was a ValueError from np.gradient ("Shape of
    array too small"), and points along a diagonal line an empty picture: one line naming the file."""
    import numpy as np

    scan = tmp_path / "thin.npy"
    line = np.c_[np.arange(50.0), np.arange(50.0), np.full(50, -1000.0)]  # each pixel's neighbours diagonal only
    np.save(scan, np.array([[0.0, 0.0, -1000.0], [1.0, 1.0, -1000.0]]) if shape == "two points"
            else line if shape == "a line" else np.full(shape, -1000.0))
    r = CliRunner().invoke(main, ["view", "--raw", str(scan), "-o", str(tmp_path / "v.png")])
    assert r.exit_code == 2 and r.output.count("\n") == 1, r.output
    assert r.output.startswith(f"error: {scan}: too thin to draw (a grid of ")
    assert not (tmp_path / "v.png").exists()
