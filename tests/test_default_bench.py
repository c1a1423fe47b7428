"""benchmarks/default_bench.py's training sets: learnt methods are trained on other people of the same sensor."""

import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import default_bench  # noqa: E402


def test_a_sets_training_people_are_other_people_of_the_same_sensor(tmp_path):
    root = default_bench.training_set(tmp_path, "kinect-v2-outside", 2, 2)
    assert root == tmp_path / "kinect-v2-outside-train-2x2"
    rows = list(csv.DictReader(open(root / "manifest.csv")))
    # subjects from 1000 (FRGC-style ids 05200, ...): a set's own people are 04200, 04201, ...
    assert len(rows) == 4 and {r["subject"] for r in rows} == {"05200", "05201"}, rows
    assert any(r["occluder"] for r in rows)  # the set's identities: outside-model faces, occluders in 3 of 4 scans
    stamp = (root / "manifest.csv").stat().st_mtime_ns
    assert default_bench.training_set(tmp_path, "kinect-v2-outside", 2, 2) == root  # written once, then reused
    assert (root / "manifest.csv").stat().st_mtime_ns == stamp
