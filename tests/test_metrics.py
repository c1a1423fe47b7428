"""Evaluation metrics against hand-computed cases, and the bob score file format."""

import numpy as np
import pytest

from facerec3d.evaluation.metrics import cmc, det, eer, rank_k, roc, split_scores, summarize, verification_rate
from facerec3d.evaluation.scorefile import read_score_rows, read_scores, write_scores

nan = np.nan

# Gallery: subjects A, B, C; A has two templates (columns 0 and 3).
GALLERY = ["A", "B", "C", "A"]
PROBES = ["A", "B", "C", "D"]  # D is not enrolled
S = np.array([
    [0.5, 0.9, 0.1, 0.95],  # A: best per subject A .95, B .9, C .1 -> rank 1
    [0.8, 0.8, 0.2, 0.3],  # B: A .8 ties B .8 -> pessimistic rank 2
    [0.7, nan, nan, 0.6],  # C: B and C not compared (-inf), tie -> rank 3 (last)
    [0.4, 0.35, 0.2, 0.1],  # D: excluded from CMC, impostor scores only
])
# Tiebreak: for probe B, B's template (20) beats A's best-scoring template (10);
# A's template 3 (99) does not count since its score .3 is not A's best .8.
# For probe C the values at NaN scores are ignored: C stays tied last.
T = np.array([
    [0, 0, 0, 0],
    [10, 20, 0, 99],
    [0, 5, 7, 0],
    [0, 0, 0, 0],
], float)


def test_split_scores_skips_nan():
    genuine, impostor = split_scores(S, PROBES, GALLERY)
    # genuine: A-A .5, A-A .95, B-B .8 (C-C is NaN); impostors row by row, NaN left out
    np.testing.assert_array_equal(genuine, [0.5, 0.95, 0.8])
    np.testing.assert_array_equal(impostor, [0.9, 0.1, 0.8, 0.2, 0.3, 0.7, 0.6, 0.4, 0.35, 0.2, 0.1])


def test_split_scores_checks_shapes():
    with pytest.raises(ValueError, match="gallery_ids"):
        split_scores(S, PROBES, GALLERY[:3])


def test_roc_points_by_hand():
    # genuine .9 .8 .4, impostor .7 .3 .2 .1; accept score >= t
    # t:   inf  .9   .8   .7   .4   .3   .2   .1
    # TAR: 0   1/3  2/3  2/3   1    1    1    1
    # FMR: 0    0    0   1/4  1/4  1/2  3/4   1
    fmr, tar, thr = roc([0.9, 0.8, 0.4], [0.7, 0.3, 0.2, 0.1])
    np.testing.assert_allclose(fmr, [0, 0, 0, 0.25, 0.25, 0.5, 0.75, 1])
    np.testing.assert_allclose(tar, [0, 1 / 3, 2 / 3, 2 / 3, 1, 1, 1, 1])
    np.testing.assert_array_equal(thr, [np.inf, 0.9, 0.8, 0.7, 0.4, 0.3, 0.2, 0.1])


def test_roc_needs_both_classes():
    with pytest.raises(ValueError, match="genuine and impostor"):
        roc([], [1.0])


def test_det_by_hand():
    # genuine 2 1, impostor 1 0: at t=1 FMR 1/2 FNMR 0; at t=2 FMR 0 FNMR 1/2.
    # sklearn keeps the points from the last FNMR=0 to the first FMR=0, thresholds increasing.
    fmr, fnmr, thr = det([2, 1], [1, 0])
    np.testing.assert_allclose(fmr, [0.5, 0])
    np.testing.assert_allclose(fnmr, [0, 0.5])
    np.testing.assert_array_equal(thr, [1, 2])


def test_eer_by_hand():
    # Points of test_roc_points_by_hand as (FMR, FNMR): t=.7 (1/4, 1/3), d = 1/12 > 0;
    # t=.4 (1/4, 0), d = -1/4. FMR is 1/4 along the segment -> EER 1/4.
    assert eer([0.9, 0.8, 0.4], [0.7, 0.3, 0.2, 0.1]) == pytest.approx(0.25)


def test_eer_interpolates_across_a_tie():
    # genuine 2 1, impostor 1 0 (genuine 1 tied with impostor 1):
    # t=2 (FMR 0, FNMR 1/2), d = 1/2; t=1 (FMR 1/2, FNMR 0), d = -1/2
    # crossing: 0 + (1/2)/(1/2+1/2) * (1/2 - 0) = 1/4 (the brute-force min max is 1/2).
    assert eer([2, 1], [1, 0]) == pytest.approx(0.25)


def test_eer_extremes():
    assert eer([3, 4], [1, 2]) == 0.0  # perfect separation: t=3 gives (0, 0)
    assert eer([1, 1, 1], [1, 1]) == pytest.approx(0.5)  # total overlap: (0,1) -> (1,0), midpoint
    assert eer([1, 2], [3, 4]) == 1.0  # reversed: t=3 gives FMR 1, FNMR 1


def test_eer_matches_brute_force_threshold_sweep():
    # Without genuine/impostor ties, consecutive ROC points change only one of FMR and FNMR,
    # so the interpolated crossing equals min over thresholds of max(FMR, FNMR).
    rng = np.random.default_rng(7)
    for mu in (0.5, 1.5, 3.0):
        genuine, impostor = rng.normal(mu, 1, 300), rng.normal(0, 1, 2000)
        t = np.r_[np.inf, np.unique(np.r_[genuine, impostor])]
        fmr = (impostor[None, :] >= t[:, None]).mean(1)
        fnmr = (genuine[None, :] < t[:, None]).mean(1)
        assert eer(genuine, impostor) == pytest.approx(np.maximum(fmr, fnmr).min(), abs=1e-12)


def test_verification_rate_with_ties():
    genuine = [5, 4, 3, 2]
    impostor = [4, 3] + [1] * 8  # 10 impostors; genuine 4 ties impostor 4
    # t=5: TAR 1/4, FMR 0; t=4: TAR 2/4, FMR 1/10; t=3: TAR 3/4, FMR 2/10; t=2: TAR 1, FMR 2/10
    assert verification_rate(genuine, impostor, 0.0) == 0.25
    assert verification_rate(genuine, impostor, 0.05) == 0.25  # the tied genuine 4 needs FMR 0.1
    assert verification_rate(genuine, impostor, 0.1) == 0.5
    assert verification_rate(genuine, impostor, 0.2) == 1.0  # t=2 accepts no further impostor
    assert verification_rate(genuine, impostor, 1.0) == 1.0
    with pytest.raises(ValueError):
        verification_rate(genuine, impostor, 5.0)


def test_verification_rate_extremes():
    assert verification_rate([3, 4], [1, 2], 0.001) == 1.0  # perfect separation
    assert verification_rate([1, 1], [1, 1], 0.5) == 0.0  # total overlap: only the +inf point has FMR <= .5


def test_cmc_by_hand():
    # ranks of probes A, B, C = 1, 2, 3 -> rank-1 1/3, rank-2 2/3, rank-3 1
    np.testing.assert_allclose(cmc(S, PROBES, GALLERY), [1 / 3, 2 / 3, 1])
    # tiebreak: ranks 1, 1, 3
    np.testing.assert_allclose(cmc(S, PROBES, GALLERY, tiebreak=T), [2 / 3, 2 / 3, 1])
    np.testing.assert_allclose(cmc(S, PROBES, GALLERY, max_rank=2), [1 / 3, 2 / 3])
    np.testing.assert_allclose(cmc(S, PROBES, GALLERY, max_rank=5), [1 / 3, 2 / 3, 1, 1, 1])


def test_cmc_ties_are_pessimistic_and_tiebreak_can_tie_too():
    # one probe, all three subjects scored 1.0 -> rank 3
    np.testing.assert_allclose(cmc([[1.0, 1.0, 1.0]], ["a"], ["a", "b", "c"]), [0, 0, 1])
    # tiebreak separates b (tb 2, above a) from c (tb 0, below a) -> rank 2
    np.testing.assert_allclose(cmc([[1.0, 1.0, 1.0]], ["a"], ["a", "b", "c"], tiebreak=[[1, 2, 0]]), [0, 1, 1])
    # tiebreak tied with b as well -> still pessimistic: rank 2
    np.testing.assert_allclose(cmc([[1.0, 1.0, 1.0]], ["a"], ["a", "b", "c"], tiebreak=[[1, 1, 0]]), [0, 1, 1])


def test_cmc_needs_an_enrolled_probe():
    with pytest.raises(ValueError, match="gallery"):
        cmc([[1.0]], ["x"], ["y"])


def test_rank_k():
    curve = np.array([0.5, 0.75, 1.0])
    assert rank_k(curve, 1) == 0.5
    assert rank_k(curve, 5) == 1.0  # fewer than 5 subjects: the last rank
    with pytest.raises(ValueError):
        rank_k(curve, 0)


def test_summarize_by_hand():
    m = summarize(S, PROBES, GALLERY, n_failed=1)
    # EER: genuine .5 .95 .8, 11 impostors (test_split_scores_skips_nan). Descending t:
    # t=.7 FMR 3/11 FNMR 1/3 (d>0); t=.6 FMR 4/11 FNMR 1/3 (d<0) -> EER = FNMR = 1/3.
    # VR: FMR <= 0.001 or 0.01 allows no impostor: t=.95 (above the .9 impostor) -> TAR 1/3.
    # *_all: 3 ranked probes + 1 failure -> factor 3/4.
    expected = {
        "n_probes": 5, "n_processed": 4, "failures": 1, "fta_rate": 0.2, "n_ranked": 3,
        "n_genuine": 3, "n_impostor": 11,
        "rank1": 1 / 3, "rank5": 1.0, "rank1_all": 0.25, "rank5_all": 0.75,
        "eer": 1 / 3, "vr_at_far_0.001": 1 / 3, "vr_at_far_0.01": 1 / 3,
        "vr_at_far_0.001_all": 0.25, "vr_at_far_0.01_all": 0.25,
    }
    assert m.keys() == expected.keys()
    for k, v in expected.items():
        assert m[k] == pytest.approx(v), k
        assert type(m[k]) in (int, float), k
    assert summarize(S, PROBES, GALLERY, tiebreak=T)["rank1"] == pytest.approx(2 / 3)


def test_summarize_undefined_metrics_are_none():
    m = summarize(np.empty((0, 2)), [], ["a", "b"], n_failed=2)
    assert m["fta_rate"] == 1.0 and m["rank1"] is None and m["eer"] is None
    assert m["rank1_all"] == 0.0  # both probes failed: both missed
    assert m["vr_at_far_0.001_all"] is None


def test_score_file_round_trip(tmp_path):
    path = tmp_path / "scores.txt"
    n = write_scores(path, S, PROBES, ["a1", "b1", "c1", "d1"], GALLERY)
    assert n == 14  # 16 comparisons, 2 NaN
    genuine, impostor = read_scores(path)
    g0, i0 = split_scores(S, PROBES, GALLERY)
    np.testing.assert_array_equal(genuine, g0)  # exact: scores are written in round-trip form
    np.testing.assert_array_equal(impostor, i0)
    rows = read_score_rows(path)
    assert path.read_text().splitlines()[0] == "A A a1 0.5"
    assert list(rows.claimed_id[:4]) == GALLERY and set(rows.probe_label) == {"a1", "b1", "c1", "d1"}
    assert rows.real_id[-1] == "D" and rows.score[-1] == 0.1


def test_score_file_errors(tmp_path):
    with pytest.raises(ValueError, match="white space"):
        write_scores(tmp_path / "s.txt", [[1.0]], ["a b"], ["x"], ["a"])
    bad = tmp_path / "bad.txt"
    bad.write_text("A A a1 0.5\n\nA B b1 zero\n")
    with pytest.raises(ValueError, match="bad.txt:3"):
        read_score_rows(bad)


def test_infinite_scores_rank_last_and_first():
    from facerec3d.evaluation.metrics import eer, verification_rate

    genuine = np.array([0.9, 0.8, np.inf])
    impostor = np.array([0.1, -np.inf, 0.85])
    # thresholds by hand: accept >= 0.9 -> TAR 2/3 (0.9, inf), FMR 0 -> VR at FMR 0 is 2/3
    assert verification_rate(genuine, impostor, 0.0) == pytest.approx(2 / 3)
    # FNMR = FMR = 1/3 between 0.85 and 0.8
    assert eer(genuine, impostor) == pytest.approx(1 / 3)
