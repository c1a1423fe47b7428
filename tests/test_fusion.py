"""Score normalisation and fusion (chapter §8.10) on hand-computed numbers; the fusion matcher."""

import numpy as np
import pytest

from facerec3d.config import read_settings
from facerec3d.matching.base import Template, learnt_arrays
from facerec3d.matching.fusion import FusionConfig, FusionMatcher, pack, unpack
from facerec3d.matching.normalisation import borda, fuse, hampel_location_scale, normalise
from facerec3d.matching.icp import ICPMatcher
from facerec3d.matching.registry import load_matcher, make_matcher
from facerec3d.matching.regions import RegionICPMatcher
from tests.conftest import model_face

# two sources (rows) scoring three templates (columns)
S = np.array([[1.0, 2.0, 4.0],
              [3.0, 1.0, 2.0]])


def test_min_max():
    np.testing.assert_allclose(normalise([1.0, 2.0, 4.0], "min-max"), [0.0, 1 / 3, 1.0])
    np.testing.assert_allclose(normalise([-np.inf, 1.0, 3.0], "min-max"), [0.0, 0.0, 1.0])  # no match = worst
    np.testing.assert_allclose(normalise([5.0, 5.0], "min-max"), [0.5, 0.5])


def test_z_score():
    # mean 2, population std sqrt(2/3) = 0.8164966
    np.testing.assert_allclose(normalise([1.0, 2.0, 3.0], "z-score"), [-1.2247449, 0.0, 1.2247449], atol=1e-7)
    # parameters from a reference sample: mean 1, std 1
    np.testing.assert_allclose(normalise([3.0], "z-score", reference=[0.0, 2.0]), [2.0])


def test_tanh():
    # ½(tanh(0.01 · ∓1.2247449) + 1); tanh(0.012247449) = 0.012246837
    np.testing.assert_allclose(normalise([1.0, 2.0, 3.0], "tanh"), [0.49387658, 0.5, 0.50612342], atol=1e-8)


def test_hampel_ignores_an_outlier():
    # |x − median 3.5| = 2.5, 1.5, .5, .5, 1.5, 96.5: knees a = 2 (70 %), b = 26, c = 73; 100 is beyond c (weight 0)
    # and the rest converge to their mean 3 (every |x − 3| <= a), σ = sqrt((4 + 1 + 0 + 1 + 4) / 5) = sqrt(2)
    mu, sd = hampel_location_scale(np.array([1.0, 2.0, 3.0, 4.0, 5.0, 100.0]))
    assert mu == pytest.approx(3.0, abs=1e-5) and sd == pytest.approx(np.sqrt(2.0), abs=1e-5)
    # tanh-hampel of 5: ½(tanh(0.01 · 2/√2) + 1) = ½(tanh(0.014142136) + 1) = 0.50707060
    assert normalise([5.0, 1.0, 2.0, 3.0, 4.0, 100.0], "tanh-hampel")[0] == pytest.approx(0.50707060, abs=1e-6)


def test_sum_product_weighted():
    # min-max rows: [0, 1/3, 1] and [1, 0, 1/2]
    np.testing.assert_allclose(fuse(S, "sum", "min-max")[0], [1.0, 1 / 3, 1.5])
    np.testing.assert_allclose(fuse(S, "product", "min-max")[0], [0.0, 0.0, 0.5])
    np.testing.assert_allclose(fuse(S, "weighted-sum", "min-max", weights=[2.0, 1.0])[0], [1.0, 2 / 3, 2.5])
    # z-score rows: [-1.0690450, -0.2672612, 1.3363062] and [1.2247449, -1.2247449, 0]
    np.testing.assert_allclose(fuse(S, "sum", "z-score")[0], [0.1556999, -1.4920061, 1.3363062], atol=1e-6)
    with pytest.raises(ValueError):
        fuse(S, "product", "z-score")  # negative normalised scores
    with pytest.raises(ValueError):
        fuse(S, "weighted-sum", "min-max", weights=[1.0])


def test_borda_and_consensus():
    # source 0 ranks t2, t1, t0 (points 0, 1, 2 for t0, t1, t2); source 1 ranks t0, t2, t1 (points 2, 0, 1)
    np.testing.assert_allclose(borda(S), [2.0, 1.0, 3.0])
    np.testing.assert_allclose(fuse(S, "borda")[0], [2.0, 1.0, 3.0])
    np.testing.assert_allclose(borda(S, top=1), [1.0, 0.0, 1.0])  # only each source's best gets a point
    np.testing.assert_allclose(borda([[1.0, 1.0, 0.0]]), [1.5, 1.5, 0.0])  # a tie shares the average rank
    votes, tiebreak = fuse(S, "consensus")
    np.testing.assert_allclose(votes, [1.0, 0.0, 1.0])  # t2 (source 0) and t0 (source 1) are voted first
    np.testing.assert_allclose(tiebreak, [2.0, 1.0, 3.0])  # the Borda count prefers t2


def test_hampel_location_is_the_root_of_the_hampel_estimating_equation():
    # Every part of Hampel's ψ is used: knees a = 6.6, b = 10.2, c = 34 (70/85/95 % of |x − 6.5|); at μ ≈ 6.1,
    # 0..9 are within a (ψ = d), 14 and 16 between a and b (ψ = ±a), 30 between b and c (descending), 60 beyond c.
    # Reference: the root of Σ ψ(x − μ) = 0 found by bisection (brentq), σ the ψ(d)/d-weighted RMS deviation.
    from scipy.optimize import brentq

    x = np.array([0.0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 14, 16, 30, 60])
    a, b, c = np.quantile(np.abs(x - np.median(x)), (0.7, 0.85, 0.95))

    def psi(d):
        ad = np.abs(d)
        return np.sign(d) * np.where(ad <= a, ad, np.where(ad <= b, a, np.where(ad <= c, a * (c - ad) / (c - b), 0)))

    mu_ref = brentq(lambda m: psi(x - m).sum(), 0.0, 12.0)
    w = psi(x - mu_ref) / (x - mu_ref)
    sd_ref = np.sqrt(np.sum(w * (x - mu_ref) ** 2) / w.sum())
    mu, sd = hampel_location_scale(x)
    assert mu == pytest.approx(mu_ref, abs=1e-4) and sd == pytest.approx(sd_ref, abs=1e-4)
    assert abs(mu - x.mean()) > 5  # far from the mean the outliers pull up


def test_borda_and_consensus_rank_a_score_not_made_last():
    # a source that could not score a template (NaN: the member failed on it) gives it the fewest points, and the
    # other templates keep their points: one source ranks t0, t2, t1(NaN) -> points 2, 0, 1
    np.testing.assert_allclose(borda([[0.9, np.nan, 0.1]]), [2.0, 0.0, 1.0])
    np.testing.assert_allclose(borda([[0.9, np.nan, 0.1], [0.2, 0.3, 0.1]]), [3.0, 2.0, 1.0])
    votes, tiebreak = fuse(np.array([[np.nan, 0.5, 0.1], [0.2, 0.3, 0.1]]), "consensus")
    np.testing.assert_allclose(votes, [0.0, 2.0, 0.0])
    np.testing.assert_allclose(tiebreak, [1.0, 4.0, 1.0])  # t0: 0 + 1, t1: 2 + 2, t2: 1 + 0


def test_pack_unpack():
    a = Template("s1", "x", "icp", {"points": np.zeros((2, 3)), "n": np.arange(3)}, {"k": 1})
    b = Template("s1", "x", "pca", {"points": np.ones(4)}, {"k": 2})
    back = unpack(pack([a, b], "fusion"))
    assert [t.method for t in back] == ["icp", "pca"] and [t.attrs for t in back] == [{"k": 1}, {"k": 2}]
    np.testing.assert_array_equal(back[0].arrays["n"], np.arange(3))
    np.testing.assert_array_equal(back[1].arrays["points"], np.ones(4))


@pytest.fixture(scope="module")
def faces():
    gallery = [model_face(s) for s in range(5)]
    probes = [model_face(s, "smile") for s in range(5)]
    return gallery, probes


def test_fusion_matcher_combines_members(tmp_path, faces):
    gallery, probes = faces
    path = tmp_path / "fusion.toml"
    path.write_text('members = ["icp", "region-icp"]\nnormalisation = "min-max"\nrule = "weighted-sum"\n'
                    'weights = [1.0, 2.0]\n[member_options.region-icp]\nregions = ["nose"]\n')
    m = make_matcher("fusion", read_settings(path))
    assert isinstance(m.members[0], ICPMatcher) and isinstance(m.members[1], RegionICPMatcher)
    assert m.members[1].config.regions == ("nose",) and m.config.weights == (1.0, 2.0)
    templates = [m.enroll(g) for g in gallery]
    icp_t = [ICPMatcher().enroll(g) for g in gallery]
    icp = ICPMatcher().scores(probes[3], icp_t)[0]
    nose = m.members[1].scores(probes[3], [unpack(t)[1] for t in templates])[0]
    fused, _ = m.scores(probes[3], templates)
    # weighted sum of the members' min-max normalised scores, computed here by hand from their raw scores
    expected = (icp - icp.min()) / (icp.max() - icp.min()) + 2 * (nose - nose.min()) / (nose.max() - nose.min())
    np.testing.assert_allclose(fused, expected)
    assert int(np.argmax(fused)) == 3
    for k, p in enumerate(probes):
        assert int(np.argmax(m.scores(p, templates)[0])) == k
    m.save(tmp_path / "model.npz")
    back = load_matcher(tmp_path / "model.npz")
    assert isinstance(back, FusionMatcher) and back.config == m.config and back.options() == m.options()
    np.testing.assert_allclose(back.scores(probes[3], templates)[0], fused)


def test_fusion_matcher_passes_its_top_to_the_borda_rule(faces):
    # borda with top = 1: only each member's best template gets a point, so the fused scores are the members'
    # votes for their best template (computed here from the members' own scores), not full Borda counts
    gallery, probes = faces
    m = FusionMatcher(FusionConfig(members=("icp", "region-icp"), rule="borda", top=1))
    templates = [m.enroll(g) for g in gallery]
    raw = np.stack([member.scores(probes[2], [unpack(t)[k] for t in templates])[0]
                    for k, member in enumerate(m.members)])
    expected = np.zeros(len(gallery))
    for row in raw:
        expected[np.argmax(row)] += 1.0
    fused, _ = m.scores(probes[2], templates)
    np.testing.assert_allclose(fused, expected)
    assert fused.sum() == 2.0


def test_fusion_needs_training_when_any_member_does():
    m = FusionMatcher(FusionConfig(members=("icp", "pca")))
    assert m.members[1].needs_training and not m.members[0].needs_training
    assert m.needs_training and m.learners() == ["pca"]
    assert not FusionMatcher(FusionConfig(members=("icp", "region-icp"))).needs_training


def test_fusion_config_is_checked():
    with pytest.raises(ValueError):
        FusionConfig(members=("icp",), rule="product", normalisation="z-score")
    with pytest.raises(ValueError):
        FusionConfig(members=("icp",), member_options={"pca": {}})
    with pytest.raises(ValueError):
        FusionConfig(members=())


class _Learner(ICPMatcher):
    """An ICP matcher that 'learns' the training subjects' count, to check that fusion keeps members' state."""

    name = "icp"

    def fit(self, scans, subjects):
        self.learnt = np.array([len(set(subjects))])
        return self

    def state(self):
        return {"count": self.learnt}, {"subjects": int(self.learnt[0])}

    def set_state(self, arrays, attrs):
        self.learnt, = learnt_arrays(arrays, {"count": (1,)})
        assert attrs == {"subjects": int(self.learnt[0])}


def test_fusion_fits_members_and_keeps_their_state(faces):
    gallery, _ = faces
    m = FusionMatcher(FusionConfig(members=("icp", "region-icp")))
    m.members[0] = _Learner()
    m.fit(gallery, ["a", "b", "b", "c", "c"])
    arrays, attrs = m.state()
    assert list(arrays) == ["0__count"] and attrs == {"members": [{"subjects": 3}, {}]}
    other = FusionMatcher(FusionConfig(members=("icp", "region-icp")))
    other.members[0] = _Learner()
    other.set_state(arrays, attrs)
    np.testing.assert_array_equal(other.members[0].learnt, [3])
    with pytest.raises(ValueError, match=r"^member 'icp': 'count' of shape \(2,\), not \(1,\)$"):  # which member
        other.set_state({"0__count": np.array([3, 4])}, attrs)


def test_galleries_stored_before_the_plane_capped_score_keep_the_books_score(tmp_path):
    """ICP's plane-capped score (plane_cap_mm, December 2026) changes what a score means, so a calibrated threshold
    too: options stored before it existed (an icp, region-icp or fusion gallery) load with it off, options stored
    now keep it, and options a user gives take today's default."""
    import json
    import sqlite3

    from facerec3d.gallery.store import GalleryStore
    from facerec3d.matching.registry import stored_matcher
    from facerec3d.preprocess import PreprocessConfig

    def caps(matcher):
        members = matcher.members if isinstance(matcher, FusionMatcher) else [matcher]
        return [m.config.plane_cap_mm if isinstance(m, ICPMatcher) else m.config.icp.plane_cap_mm
                for m in members if isinstance(m, (ICPMatcher, RegionICPMatcher))]

    icp_today = make_matcher("icp").options()
    assert caps(stored_matcher("icp", icp_today)) == [3.0]
    assert caps(stored_matcher("icp", {k: v for k, v in icp_today.items() if k != "plane_cap_mm"})) == [0.0]
    region_today = make_matcher("region-icp").options()
    region_old = {**region_today, "icp": {k: v for k, v in region_today["icp"].items() if k != "plane_cap_mm"}}
    assert caps(stored_matcher("region-icp", region_today)) == [3.0]
    assert caps(stored_matcher("region-icp", region_old)) == [0.0]
    assert caps(make_matcher("region-icp", {"icp": {"seed": 1}})) == [3.0]

    path = tmp_path / "fusion.sqlite"
    with GalleryStore(path, create=True) as store:
        store.bind(PreprocessConfig(), make_matcher("fusion"))
    with GalleryStore(path) as store:
        assert caps(store.matcher()) == [3.0, 3.0]
        store.check_matcher(make_matcher("fusion"))  # a gallery stored today takes today's default matcher
    db = sqlite3.connect(path)
    with db:
        options = json.loads(db.execute("SELECT value FROM meta WHERE key = 'options'").fetchone()[0])
        assert options["member_options"]["icp"] == {"plane_cap_mm": 3.0}
        options["member_options"] = {}  # as a fusion stored its options before
        db.execute("UPDATE meta SET value = ? WHERE key = 'options'", (json.dumps(options),))
    db.close()
    with GalleryStore(path) as store:
        old = store.matcher()
    assert caps(old) == [0.0, 0.0]
    assert stored_matcher("fusion", old.options()).options() == old.options()  # and it stays so when stored again
    assert caps(make_matcher("fusion", {"member_options": {}})) == [3.0, 3.0]


@pytest.mark.parametrize("weights", ["[1, 2]", "[0, 0, 0]"])
def test_a_method_config_with_weights_its_rule_ignores_is_refused(tmp_path, weights):
    """`weights` with the sum rule in a --method-config file (too few of them, or all 0) was taken and the weights
    silently ignored; `fuse --weights` refused it. The fusion config refuses it alike: one line naming the file and
    the setting."""
    from facerec3d.errors import SettingsError

    path = tmp_path / "fusion.toml"
    path.write_text(f'members = ["icp", "region-icp", "embedding"]\nrule = "sum"\nweights = {weights}\n')
    with pytest.raises(SettingsError) as e:
        make_matcher("fusion", read_settings(path))
    assert str(e.value) == f"{path}: weights are for the weighted-sum rule: sum does not use them"


def test_a_gallery_stored_with_weights_its_rule_ignored_loads_as_it_scored():
    """Until 2026-12-06 a fusion (and region ICP) with weights and the sum rule was taken, the weights unused, and a
    gallery stored it so; refusing such a method config must not lock that gallery out: its stored options load,
    without the unused weights, in the member options too, and score as the weights never counted."""
    from facerec3d.matching.fusion import FusionMatcher

    stored = FusionMatcher().options()
    stored["weights"] = [1.0, 2.0]
    stored["member_options"] = {"region-icp": {"rule": "sum", "weights": [0.0, 0.0, 0.0]}}
    matcher = FusionMatcher.from_stored(stored)
    assert matcher.config.weights == () and matcher.config.rule == "sum"
    region = next(m for m in matcher.members if m.name == "region-icp")
    assert region.config.weights == () and region.config.rule == "sum"
    weighted = dict(stored, rule="weighted-sum", weights=[1.0, 2.0, 0.5], member_options={})
    assert FusionMatcher.from_stored(weighted).config.weights == (1.0, 2.0, 0.5)  # used weights are kept


def test_the_best_other_person_is_taken_off_without_moving_any_rank():
    from facerec3d.matching.normalisation import minus_best_other

    fused = np.array([5.0, 1.0, 4.0, -2.0, 3.0])
    people = np.array(["a", "b", "a", "c", "d"])  # a has two templates: neither is the other's cohort
    out = minus_best_other(fused, people, 0.5)
    # a's templates: less half of d's 3.0 (the best of the others); everyone else's: less half of a's 5.0
    np.testing.assert_allclose(out, [3.5, -1.5, 2.5, -4.5, 0.5])
    assert np.array_equal(np.argsort(out), np.argsort(fused))
    np.testing.assert_array_equal(minus_best_other(fused, people, 0.0), fused)
    np.testing.assert_array_equal(minus_best_other(fused[[0, 2]], people[[0, 2]], 0.5), fused[[0, 2]])  # one person
    # a match not found (-inf) is no cohort, and keeps its own score
    out = minus_best_other(np.array([2.0, -np.inf, 1.0]), np.array(["x", "y", "z"]), 1.0)
    np.testing.assert_allclose(out, [1.0, -np.inf, -1.0])
    rng = np.random.default_rng(0)
    for _ in range(50):  # random galleries with repeated people: the people's order (by best template) kept
        s, who = rng.normal(size=12), rng.integers(0, 5, 12)
        out = minus_best_other(s, who, rng.uniform())
        people = np.unique(who)
        best_before = [s[who == p].max() for p in people]
        best_after = [out[who == p].max() for p in people]
        assert np.array_equal(np.argsort(best_after), np.argsort(best_before))
        for p in people:  # and each person's own templates keep theirs
            assert np.array_equal(np.argsort(out[who == p]), np.argsort(s[who == p]))


def test_the_cohort_takes_the_best_other_person_off_however_the_gallery_is_sharded(faces):
    """`cohort` (off by default) takes off a share of the best other person's fused score; a gallery split into
    shards scores the same (each template's subject travels with its shard's scores); the option is stored."""
    from facerec3d.matching.base import merge_shard_scores, shard_scores

    gallery, probes = faces
    m = FusionMatcher(FusionConfig(members=("icp", "region-icp"), cohort=0.5))
    assert FusionConfig().cohort == 0.0 and FusionMatcher.from_stored(m.options()).config.cohort == 0.5
    templates = [m.enroll(g) for g in gallery]
    plain = FusionMatcher(FusionConfig(members=("icp", "region-icp"))).scores(probes[1], templates)[0]
    with_cohort = m.scores(probes[1], templates)[0]
    others = np.array([np.max(np.delete(plain, i)) for i in range(len(plain))])
    np.testing.assert_allclose(with_cohort, plain - 0.5 * others)
    halves = np.concatenate([shard_scores(m, probes[1], templates[:2]), shard_scores(m, probes[1], templates[2:])],
                            axis=1)
    np.testing.assert_allclose(merge_shard_scores(m, halves)[0], with_cohort)


def test_evaluate_takes_the_best_other_person_off_as_identify_does(tmp_path):
    """`evaluate` enrolled depth frames whose scans did not know their person (the manifest names them), so every
    template had the same subject and the cohort found no other person: its scores were the plain sum while
    `identify` on a gallery took the best other person off. Both now score alike."""
    import collections

    from click.testing import CliRunner

    from facerec3d.cli import main

    run = CliRunner()
    data = tmp_path / "frames"
    assert run.invoke(main, ["synth", str(data), "--sensor", "kinect-v2", "--format", "png", "--subjects", "4",
                             "--scans", "2"]).exit_code == 0
    scores = {}
    for share in (0.0, 0.5):
        cfg = tmp_path / f"c{share}.toml"
        cfg.write_text(f'members = ["icp", "embedding"]\ncohort = {share}\n')
        r = run.invoke(main, ["evaluate", str(data), "--method", "fusion", "--method-config", str(cfg), "--out",
                              str(tmp_path / f"run{share}"), "--jobs", "1", "--cache", str(tmp_path / "cache")])
        assert r.exit_code == 0, r.output
        S = collections.defaultdict(dict)
        for line in (tmp_path / f"run{share}" / "scores.txt").read_text().splitlines():
            g, _, p, s = line.split()
            S[p][g] = float(s)
        scores[share] = S
    assert len(scores[0.0]) == 4
    for probe, plain in scores[0.0].items():
        people = sorted(plain)
        v = np.array([plain[g] for g in people])
        others = np.array([np.max(np.delete(v, i)) for i in range(len(v))])
        np.testing.assert_allclose([scores[0.5][probe][g] for g in people], v - 0.5 * others, atol=1e-9)


def test_evaluate_scores_impostors_also_as_strangers_claims(tmp_path):
    """A method normalised over the gallery scores an enrolled impostor among his own entries (whose high scores
    push the others down) but a stranger among entries none of which is his: `evaluate` gives both. Each impostor
    pair of scores.strangers.txt is the members' raw scores fused over the gallery without the probe's subject
    (computed here from the members' own runs); metrics.json's `strangers` figures take their impostors from it and
    their genuine scores from scores.txt; a method whose scores do not depend on the gallery has one set."""
    import collections
    import json

    from click.testing import CliRunner

    from facerec3d.cli import main

    run = CliRunner()
    data = tmp_path / "frames"
    assert run.invoke(main, ["synth", str(data), "--sensor", "kinect-v2", "--format", "png", "--subjects", "5",
                             "--scans", "2"]).exit_code == 0
    cfg = tmp_path / "f.toml"
    cfg.write_text('members = ["icp", "embedding"]\n')

    def scores(folder, name="scores.txt"):
        S = collections.defaultdict(dict)
        for line in (folder / name).read_text().splitlines():
            g, real, p, s = line.split()
            S[(real, p)][g] = float(s)
        return S

    runs = {}
    for method in ("fusion", "icp", "embedding"):
        r = run.invoke(main, ["evaluate", str(data), "--method", method, "--out", str(tmp_path / method), "--jobs",
                              "1", "--cache", str(tmp_path / "cache"), "--bootstrap", "0",
                              *(["--method-config", str(cfg)] if method == "fusion" else [])])
        assert r.exit_code == 0, r.output
        runs[method] = json.loads((tmp_path / method / "metrics.json").read_text())
    assert "strangers" not in runs["icp"] and not (tmp_path / "icp" / "scores.strangers.txt").exists()
    fused, strangers = scores(tmp_path / "fusion"), scores(tmp_path / "fusion", "scores.strangers.txt")
    members = [scores(tmp_path / m) for m in ("icp", "embedding")]
    assert len(fused) == 5 and set(strangers) == set(fused)
    higher = 0
    for (real, probe), row in strangers.items():
        others = sorted(row)
        assert real not in others and sorted([*others, real]) == sorted(fused[(real, probe)])
        expected, _ = fuse(np.array([[m[(real, probe)][g] for g in others] for m in members]), "sum", "z-score")
        np.testing.assert_allclose([row[g] for g in others], expected, atol=1e-9)
        higher += np.mean([row[g] for g in others]) > np.mean([fused[(real, probe)][g] for g in others])
    assert higher == 5  # without the probe's own high score in the cohort, every impostor's z-score rises
    st, plain = runs["fusion"]["strangers"], runs["fusion"]
    assert (st["n_genuine"], st["n_impostor"]) == (plain["n_genuine"], plain["n_impostor"]) == (5, 20)
    assert st["rank1"] is None and st["eer"] is not None
    genuine = np.array([row[real] for (real, _), row in fused.items()])
    impostor = np.array([s for row in strangers.values() for s in row.values()])
    from facerec3d.evaluation.metrics import eer

    assert st["eer"] == pytest.approx(eer(genuine, impostor))
