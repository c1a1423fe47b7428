"""Evaluation metrics against hand-computed cases, and the bob score file format."""

import numpy as np
import pytest

from facerec3d.evaluation.metrics import (cmc, det, eer, open_set, rank_k, roc, split_scores, summarize,
                                          verification_rate)
from facerec3d.errors import InputError
from facerec3d.evaluation.scorefile import read_score_matrix, read_score_rows, read_scores, write_scores
from tests.conftest import check_against_pyeer

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
    # Thresholds: the EER crossing lies between t=.7 (d = 1/3 - 3/11 = 2/33) and t=.6 (d = 1/3 - 4/11 = -1/33):
    # the nearer is t=.6. FMR <= 0.1 % or 1 %: the highest threshold with the highest TAR is .95.
    # Open set: best non-mated scores A .9, B .8, C .7, D .4 (4 searches); rank-1 hit A at .95 of 3 mated searches.
    # FPIR <= 0.1 %, 1 %, 10 %: no non-mated score accepted -> t = .95, FNIR = 2/3.
    expected = {
        "n_probes": 5, "n_processed": 4, "failures": 1, "fta_rate": 0.2, "n_ranked": 3,
        "n_genuine": 3, "n_impostor": 11, "n_subjects": 4, "n_nonmated": 4,
        "rank1": 1 / 3, "rank5": 1.0, "rank1_all": 0.25, "rank5_all": 0.75,
        "eer": 1 / 3, "vr_at_far_0.001": 1 / 3, "vr_at_far_0.01": 1 / 3,
        "vr_at_far_0.001_all": 0.25, "vr_at_far_0.01_all": 0.25,
        "threshold_at_eer": 0.6, "threshold_at_far_0.001": 0.95, "threshold_at_far_0.01": 0.95,
        "fnir_at_fpir_0.001": 2 / 3, "fnir_at_fpir_0.01": 2 / 3, "fnir_at_fpir_0.1": 2 / 3,
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
    with pytest.raises(ValueError, match="gallery id is empty"):
        write_scores(tmp_path / "s.txt", [[1.0]], ["a"], ["x"], [""])
    # ids with white space (a bob CSV's, a manifest's "person a") stay one field each, percent-encoded, and distinct
    write_scores(tmp_path / "s.txt", [[1.0, 0.5, 0.2]], ["person a"], ["x y"], ["person a", "person%20a", "b\tc"])
    assert (tmp_path / "s.txt").read_text().splitlines() == [
        "person%20a person%20a x%20y 1.0", "person%2520a person%20a x%20y 0.5", "b%09c person%20a x%20y 0.2"]
    genuine, impostor = read_scores(tmp_path / "s.txt")
    assert genuine.tolist() == [1.0] and impostor.tolist() == [0.5, 0.2]
    latin = tmp_path / "latin1.txt"
    latin.write_bytes("Jos\xe9 Jos\xe9 p1 1.0\n".encode("latin-1"))
    with pytest.raises(InputError, match=r"latin1\.txt: not UTF-8 text \(a byte b'\\xe9'\): save it as UTF-8"):
        read_score_rows(latin)
    wide = tmp_path / "wide.csv"
    wide.write_text("probe_subject_id,probe_template_id,bio_ref_subject_id,score\na," + "x" * 200_000 + ",a,1\n")
    with pytest.raises(InputError, match=r"wide\.csv: not a readable CSV file \(field larger than field limit"):
        read_score_matrix(wide, "csv")
    for missing in (tmp_path / "missing.txt", tmp_path):  # no such file, a folder: InputError, not an OSError
        with pytest.raises(InputError, match=rf"{missing.name}: cannot read \("):
            read_score_matrix(missing)
    bad = tmp_path / "bad.txt"
    bad.write_text("A A a1 0.5\n\nA B b1 zero\n")
    with pytest.raises(ValueError, match="bad.txt:3"):
        read_score_rows(bad)
    bad.write_text("A A a1 0.5\nA B b1 -inf\nA C c1 nan\n")  # −inf is a score (no match found), NaN none
    with pytest.raises(ValueError, match="bad.txt:3: the score nan is not a number"):
        read_score_rows(bad)


def test_infinite_scores_rank_last_and_first():
    from facerec3d.evaluation.metrics import eer, verification_rate

    genuine = np.array([0.9, 0.8, np.inf])
    impostor = np.array([0.1, -np.inf, 0.85])
    # thresholds by hand: accept >= 0.9 -> TAR 2/3 (0.9, inf), FMR 0 -> VR at FMR 0 is 2/3
    assert verification_rate(genuine, impostor, 0.0) == pytest.approx(2 / 3)
    # FNMR = FMR = 1/3 between 0.85 and 0.8
    assert eer(genuine, impostor) == pytest.approx(1 / 3)


def test_roc_drops_only_collinear_points_like_sklearn():
    from sklearn.metrics import roc_curve

    rng = np.random.default_rng(3)
    genuine, impostor = np.round(rng.normal(1, 1, 200), 1), np.round(rng.normal(0, 1, 500), 1)
    fmr, tar, thr = roc(genuine, impostor, drop_intermediate=True)
    ref = roc_curve(np.r_[np.ones(200), np.zeros(500)], np.r_[genuine, impostor], drop_intermediate=True)
    np.testing.assert_allclose(fmr, ref[0])
    np.testing.assert_allclose(tar, ref[1])
    np.testing.assert_array_equal(thr[1:], ref[2][1:])


def test_thresholds_at_the_operating_points_by_hand():
    # genuine .9 .8 .4, impostor .7 .3 .2 .1 (test_roc_points_by_hand): the EER crossing is between t=.7
    # (d = 1/12) and t=.4 (d = -1/4); .7 is nearer. FMR <= 0.1 %: TAR 2/3 first reached at t=.8.
    m = summarize([[0.9, 0.7], [0.8, 0.3], [0.4, 0.2], [0.1, nan]], ["a", "a", "a", "b"], ["a", "c"])
    assert m["eer"] == pytest.approx(0.25) and m["threshold_at_eer"] == 0.7
    assert m["vr_at_far_0.001"] == pytest.approx(2 / 3) and m["threshold_at_far_0.001"] == 0.8


def test_open_set_by_hand():
    # gallery subjects a, b, c; probes: a (a .9 beats b .5), b (a .7 beats b .6: rank 2), c (c .8, best other .3),
    # x (not enrolled, best .65). Non-mated scores: .5 .7 .3 .65; rank-1 mated scores: a .9, c .8 (b is a miss).
    S = [[0.9, 0.5, 0.1], [0.7, 0.6, 0.2], [0.3, 0.1, 0.8], [0.65, 0.2, 0.1]]
    fpir, fnir, thr = open_set(S, ["a", "b", "c", "x"], ["a", "b", "c"])
    # thresholds: inf .9 .8 .7 .65 .6 .5 .3 .2 .1 (every distinct score of the two sets; .6 and .2, .1 are not)
    np.testing.assert_array_equal(thr, [np.inf, 0.9, 0.8, 0.7, 0.65, 0.5, 0.3])
    np.testing.assert_allclose(fpir, [0, 0, 0, 1 / 4, 2 / 4, 3 / 4, 1])
    np.testing.assert_allclose(fnir, [1, 2 / 3, 1 / 3, 1 / 3, 1 / 3, 1 / 3, 1 / 3])
    m = summarize(S, ["a", "b", "c", "x"], ["a", "b", "c"])
    assert m["n_nonmated"] == 4 and m["fnir_at_fpir_0.1"] == pytest.approx(1 / 3)  # t=.8: FPIR 0


def test_bootstrap_resamples_subjects_not_scores():
    # 10 subjects x 4 probes; subjects 0 and 1 miss every probe, the others hit every one: rank-1 = 0.8.
    # Drawing 10 subjects, the misses drawn X ~ Binomial(10, 0.2): P(X <= 5) = 0.9936, P(X <= 4) = 0.967,
    # P(X = 0) = 0.107, so the 2.5 % and 97.5 % points of rank-1 = 1 - X/10 are 0.5 and 1.0. (Resampling the
    # 40 probes instead would give Binomial(40, 0.2) / 40 and a lower bound near 0.675.)
    gallery = [f"s{i}" for i in range(10)]
    probes = [f"s{i}" for i in range(10) for _ in range(4)]
    S = np.zeros((40, 10))
    for row, subject in enumerate(probes):
        k = int(subject[1:])
        S[row, k] = 1.0 if k >= 2 else -1.0
    m = summarize(S, probes, gallery, bootstrap=4000, seed=1)
    assert m["rank1"] == pytest.approx(0.8)
    assert m["ci95"]["rank1"] == [0.5, 1.0]


def random_scores(n_subjects: int, seed: int, n_gallery: int = 100, probes_each: int = 3):
    """Probes of the first n_subjects of a fixed gallery; genuine scores shifted by 2.5 plus a subject effect."""
    rng = np.random.default_rng(seed)
    gallery = [f"s{i:03d}" for i in range(n_gallery)]
    rows = np.repeat(np.arange(n_subjects), probes_each)
    S = rng.normal(0, 1, (rows.size, n_gallery))
    S[np.arange(rows.size), rows] += 2.5 + rng.normal(0, 0.7, n_subjects)[rows]
    return S, [gallery[i] for i in rows], gallery


def test_intervals_contain_the_estimate_and_shrink_as_subjects_are_added():
    figures = ("rank1", "eer", "vr_at_far_0.01", "fnir_at_fpir_0.1", "threshold_at_eer")
    widths = []
    for n in (6, 24, 96):
        m = summarize(*random_scores(n, seed=n), bootstrap=300, seed=0)
        for k in figures:
            lo, hi = m["ci95"][k]
            assert lo <= m[k] <= hi, (n, k)
        widths.append([m["ci95"][k][1] - m["ci95"][k][0] for k in figures])
    widths = np.array(widths)
    assert (widths[1:] < widths[:-1]).all(), widths


def test_score_matrix_from_bob5_and_csv_files(tmp_path):
    from facerec3d.evaluation.scorefile import read_score_matrix

    lines = [("A", "a1", "A", "p1", 0.9), ("B", "b1", "A", "p1", 0.2), ("A", "a2", "A", "p1", 0.5),
             ("A", "a1", "B", "p2", 0.4), ("B", "b1", "B", "p2", 0.8)]
    (tmp_path / "s5.txt").write_text("".join(f"{c} {m} {r} {p} {s}\n" for c, m, r, p, s in lines))
    (tmp_path / "s.csv").write_text("probe_template_id,probe_subject_id,bio_ref_template_id,bio_ref_subject_id,score\n"
                                    + "".join(f"{p},{r},{m},{c},{-s}\n" for c, m, r, p, s in lines))
    expected = summarize([[0.9, 0.5, 0.2], [0.4, np.nan, 0.8]], ["A", "B"], ["A", "A", "B"], bootstrap=50)
    for name, fmt, higher in (("s5.txt", "bob5", True), ("s.csv", "csv", False)):
        m = read_score_matrix(tmp_path / name, fmt, higher)
        assert list(m.probe_labels) == ["p1", "p2"] and list(m.probe_ids) == ["A", "B"]
        assert sorted(m.gallery_ids) == ["A", "A", "B"] and np.isnan(m.S).sum() == 1
        assert summarize(m.S, m.probe_ids, m.gallery_ids, bootstrap=50) == expected
    (tmp_path / "bad.csv").write_text("probe_subject_id,score\nA,1\n")
    with pytest.raises(ValueError, match="bio_ref_subject_id"):
        read_score_matrix(tmp_path / "bad.csv", "csv")
    (tmp_path / "twice.txt").write_text("A a1 A p1 0.9\nA a1 A p1 0.8\n")
    with pytest.raises(ValueError, match="twice"):
        read_score_matrix(tmp_path / "twice.txt", "bob5")
    (tmp_path / "clash.txt").write_text("A A p1 0.9\nB C p1 0.8\n")
    with pytest.raises(ValueError, match="two subjects"):
        read_score_matrix(tmp_path / "clash.txt", "bob4")


def test_eer_and_vr_agree_with_pyeer_on_a_score_file(tmp_path):
    # 50 probes against 101 subjects: 5,000 distinct impostor scores, so FMR 0.1 % and 1 % are reached exactly
    # and pyeer's fmr1000 / fmr100 equal ours too
    rng = np.random.default_rng(11)
    gallery = [f"g{i}" for i in range(101)]
    S = rng.normal(0, 1, (50, 101))
    S[np.arange(50), np.arange(50)] += 2.5
    write_scores(tmp_path / "s.txt", S, gallery[:50], [f"p{i}" for i in range(50)], gallery)
    ours, stats = check_against_pyeer(tmp_path / "s.txt")
    assert 0 < ours < 0.5
    assert verification_rate(*read_scores(tmp_path / "s.txt"), 0.001) == pytest.approx(1 - stats.fmr1000)


def test_fused_score_files_are_the_fusion_of_their_rows(tmp_path):
    """`facerec3d fuse` (evaluation.scorefile.fuse_score_files): each probe's rows of each file normalised over the
    gallery and combined, the `fusion` method's computation; files written in different orders pair by label."""
    from click.testing import CliRunner

    from facerec3d.cli import main
    from facerec3d.evaluation.scorefile import read_score_matrix
    from facerec3d.matching.base import rank
    from facerec3d.matching.normalisation import fuse

    rng = np.random.default_rng(5)
    gallery = [f"g{i}" for i in range(8)]
    subjects = [gallery[i % 8] for i in range(16)]
    labels = [f"p{i}" for i in range(16)]
    truth = np.array([[s == g for g in gallery] for s in subjects], float)
    A = truth * 1.0 + rng.normal(0, 0.6, truth.shape)  # two noisy systems, each wrong on some probes
    B = 3.0 * truth + rng.normal(0, 2.5, truth.shape) - 40.0  # another scale entirely
    write_scores(tmp_path / "a.txt", A, subjects, labels, gallery)
    order = rng.permutation(16)  # the second file lists its probes and gallery in another order
    cols = rng.permutation(8)
    write_scores(tmp_path / "b.txt", B[order][:, cols], [subjects[i] for i in order], [labels[i] for i in order],
                 [gallery[j] for j in cols])
    run = lambda *args: CliRunner().invoke(main, ["fuse", str(tmp_path / "a.txt"), str(tmp_path / "b.txt"), *args])

    result = run("--out", str(tmp_path / "f.txt"))
    assert result.exit_code == 0, result.output
    f = read_score_matrix(tmp_path / "f.txt")
    assert list(f.probe_labels) == labels and list(f.gallery_ids) == gallery
    plain = np.stack([fuse(np.stack([A[i], B[i]]), "sum", "z-score")[0] for i in range(16)])
    np.testing.assert_allclose(f.S, plain, rtol=1e-12)
    # --cohort: less that share of the best other person's fused score (the fusion method's `cohort`)
    assert run("--out", str(tmp_path / "f5.txt"), "--cohort", "0.5").exit_code == 0
    others = np.array([[np.max(np.delete(row, j)) for j in range(8)] for row in plain])
    np.testing.assert_allclose(read_score_matrix(tmp_path / "f5.txt").S, plain - 0.5 * others, rtol=1e-12)
    hits = lambda S: np.mean(S.argmax(axis=1) == np.arange(16) % 8)
    assert hits(f.S) >= max(hits(A), hits(B))  # on this draw the fusion is right where either is
    # beside it, the impostor pairs fused without the probe's own person (strangers' claims)
    st = read_score_matrix(tmp_path / "f.strangers.txt")
    assert list(st.probe_labels) == labels and np.isnan(st.S[truth.astype(bool)]).all()
    for i in range(16):
        others = np.flatnonzero(~truth[i].astype(bool))
        np.testing.assert_allclose(st.S[i, others], fuse(np.stack([A[i, others], B[i, others]]), "sum", "z-score")[0],
                                   rtol=1e-12)
    assert run("--out", str(tmp_path / "f.txt")).exit_code == 2  # both files there: --overwrite needed
    (tmp_path / "f.txt").unlink()
    r = run("--out", str(tmp_path / "f.txt"))
    assert r.exit_code == 2 and "f.strangers.txt: exists" in r.output, r.output

    run("--out", str(tmp_path / "w.txt"), "--rule", "weighted-sum", "--weights", "3,1")
    expected = np.stack([fuse(np.stack([A[i], B[i]]), "weighted-sum", "z-score", (3.0, 1.0))[0] for i in range(16)])
    np.testing.assert_allclose(read_score_matrix(tmp_path / "w.txt").S, expected, rtol=1e-12)

    # consensus: votes, ties broken by the Borda count, in one score that ranks as the matchers do
    run("--out", str(tmp_path / "c.txt"), "--rule", "consensus")
    c = read_score_matrix(tmp_path / "c.txt").S
    for i in range(16):
        votes, borda = fuse(np.stack([A[i], B[i]]), "consensus", "z-score")
        assert list(np.argsort(-c[i], kind="stable")) == list(rank(votes, borda))

    # a comparison that one file lacks is left out, and said so; an existing file is not overwritten
    (tmp_path / "b.txt").write_text("".join(line for line in (tmp_path / "b.txt").read_text().splitlines(True)
                                            if not line.startswith("g3 ") or " p3 " not in line))
    result = run("--out", str(tmp_path / "f.txt"), "--overwrite")
    assert result.exit_code == 0 and "1 comparisons missing from some file left out" in result.output
    assert np.isnan(read_score_matrix(tmp_path / "f.txt").S[3, 3]) and not np.isnan(read_score_matrix(tmp_path / "f.txt").S[3, 2])
    result = run("--out", str(tmp_path / "f.txt"))
    assert result.exit_code == 2 and "exists" in result.output and "Traceback" not in result.output

    # files that disagree on a probe's subject, or settings fuse would refuse: one line, exit 2
    (tmp_path / "b.txt").write_text("g0 g5 p0 0.5\n")
    result = run("--out", str(tmp_path / "x.txt"))
    assert result.exit_code == 2 and "'p0'" in result.output and "b.txt" in result.output
    result = run("--out", str(tmp_path / "x.txt"), "--rule", "weighted-sum", "--weights", "1")
    assert result.exit_code == 2 and "one weight per source" in result.output
    assert not (tmp_path / "x.txt").exists()


@pytest.mark.parametrize("args, reason", [
    (["--rule", "weighted-sum", "--weights", "2,nan"], "--weights: must be a finite number, not nan"),
    (["--rule", "weighted-sum", "--weights", "-1,2"], "--weights: must be >= 0, not -1.0"),
    (["--rule", "borda", "--top", "-3"], "--top: must be >= 0, not -3"),
    (["--rule", "weighted-sum", "--weights", "0,0"], "all weights are 0"),
    (["--weights", "1,2"], "weights are for the weighted-sum rule: sum does not use them"),
])
def test_fuse_refuses_the_settings_the_fusion_method_refuses(tmp_path, args, reason):
    """`facerec3d fuse` checks its settings as the `fusion` method's config does (ranges, weights that leave every
    score 0) and refuses weights a rule would ignore: one line, nothing written (was: an empty file for a NaN weight,
    all scores 0, a negative --top taken, weights ignored)."""
    from click.testing import CliRunner

    from facerec3d.cli import main

    write_scores(tmp_path / "s.txt", np.array([[1.0, 0.2], [0.1, 0.9]]), ["a", "b"], ["p1", "p2"], ["a", "b"])
    result = CliRunner().invoke(main, ["fuse", str(tmp_path / "s.txt"), str(tmp_path / "s.txt"),
                                       "--out", str(tmp_path / "f.txt"), *args])
    assert result.exit_code == 2 and result.output.startswith("error: ") and reason in result.output
    assert result.output.count("\n") == 1 and not (tmp_path / "f.txt").exists()


def test_csv_score_file_with_an_empty_id_is_named_by_line(tmp_path):
    """A bob CSV score file with an empty (or missing) subject or probe id: an InputError naming the file, line and
    column, from `metrics` and `fuse` alike (was: `ValueError: gallery id is empty` from writing scores.txt)."""
    from click.testing import CliRunner

    from facerec3d.cli import main

    header = "bio_ref_subject_id,probe_subject_id,probe_template_id,score\na,a,p1,1\nb,a,p1,0\n"
    (tmp_path / "c7.csv").write_text(header + ",a,p2,1\n")
    (tmp_path / "c8.csv").write_text(header + "b,a\n")
    with pytest.raises(InputError, match=r"c7\.csv:4: the bio_ref_subject_id field is empty"):
        read_score_matrix(tmp_path / "c7.csv", "csv")
    with pytest.raises(InputError, match=r"c8\.csv:4: the probe_template_id field is empty"):
        read_score_matrix(tmp_path / "c8.csv", "csv")
    for args in (["metrics", str(tmp_path / "c7.csv"), "--format", "csv", "--out", str(tmp_path / "m")],
                 ["fuse", str(tmp_path / "c7.csv"), str(tmp_path / "c7.csv"), "--format", "csv",
                  "--out", str(tmp_path / "f.txt")]):
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 2 and result.output == f"error: {tmp_path / 'c7.csv'}:4: the bio_ref_subject_id " \
                                                          "field is empty\n"


def test_a_probe_of_a_subject_not_enrolled_is_a_non_mated_search_by_its_best_score_whichever_subject_gives_it():
    # x is not in the gallery: every subject is a non-mated candidate, the last one in name order included
    # (x sorts after c, z between a and b: the subject it would be filed under must not be skipped).
    from facerec3d.evaluation.metrics import search

    S = [[0.1, 0.2, 0.9], [0.1, 0.8, 0.3], [0.9, 0.5, 0.1]]
    s = search(S, ["x", "ab", "a"], ["a", "b", "c"])
    np.testing.assert_array_equal(s.ranked, [False, False, True])
    np.testing.assert_allclose(s.nonmated, [0.9, 0.8, 0.5])  # max over every subject; a's own .9 left out
    # open set by hand: non-mated .9 .8 .5, one mated search (a, rank 1, .9): at t = .9 FPIR 1/3, FNIR 0
    fpir, fnir, thr = open_set(S, ["x", "ab", "a"], ["a", "b", "c"])
    np.testing.assert_array_equal(thr, [np.inf, 0.9, 0.8, 0.5])
    np.testing.assert_allclose(fpir, [0, 1 / 3, 2 / 3, 1])
    np.testing.assert_allclose(fnir, [1, 0, 0, 0])


def test_threshold_at_far_is_the_highest_threshold_reaching_the_rate():
    # one genuine score 10; 100 impostors: one at 9, the others at 0, -1, ..., -98. FMR <= 1 % allows one impostor,
    # but TAR is already 1 at t = 10 (FMR 0): the threshold at FMR 1 % is 10, and it accepts no impostor.
    impostors = np.r_[9.0, -np.arange(99.0)]
    S = np.r_[10.0, impostors][None, :]
    m = summarize(S, ["a"], ["a", *(f"i{k}" for k in range(100))], identification=False)
    assert m["vr_at_far_0.01"] == 1.0 and m["threshold_at_far_0.01"] == 10.0
    assert (impostors >= m["threshold_at_far_0.01"]).sum() == 0
    assert m["vr_at_far_0.001"] == 1.0 and m["threshold_at_far_0.001"] == 10.0


def test_det_with_minus_infinity_is_the_det_of_a_score_below_every_finite_one():
    # -inf (a comparison that could not be aligned) must rank below every finite score, as a very low score does
    rng = np.random.default_rng(0)
    genuine, impostor = rng.normal(1, 1, 50), rng.normal(0, 1, 80)
    genuine[:3], impostor[:5] = -np.inf, -np.inf
    fmr, fnmr, _ = det(genuine, impostor)
    low = lambda x: np.where(np.isinf(x), -1e6, x)  # noqa: E731
    ref_fmr, ref_fnmr, _ = det(low(genuine), low(impostor))
    np.testing.assert_allclose(fmr, ref_fmr)
    np.testing.assert_allclose(fnmr, ref_fnmr)
    # and the same rule against sklearn directly, +inf too
    from sklearn.metrics import det_curve

    genuine[3] = np.inf
    y = np.r_[np.ones(50), np.zeros(80)]
    ref = det_curve(y, np.clip(np.r_[genuine, impostor], -1e6, 1e6))
    got = det(genuine, impostor)
    np.testing.assert_allclose(got[0], ref[0])
    np.testing.assert_allclose(got[1], ref[1])
