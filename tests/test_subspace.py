"""PCA (chapter §8.7) and PCA + LDA (§8.8) on depth maps: the subspaces against their definitions, save/load,
and an end-to-end run trained on subjects disjoint from the test set."""

from dataclasses import asdict

import numpy as np
import pytest
import scipy.linalg

from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset
from facerec3d.evaluation.run import evaluate
from facerec3d.matching.depthmap import DepthMapConfig, depth_image
from facerec3d.matching.registry import load_matcher, make_matcher
from facerec3d.matching.subspace import fisher_lda, pca, scatter_matrices
from facerec3d.preprocess.resample import depth_to_scan, grid_xy
from tests.conftest import model_face

SMALL = ScannerConfig(rows=320, cols=400, focal_px=1000.0)


def fisher_ratio(w, Sw, Sb):
    return float(w @ Sb @ w / (w @ Sw @ w))


def test_pca_components_are_covariance_eigenvectors():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(40, 6)) @ rng.normal(size=(6, 6)) + rng.normal(size=6)
    mean, V, eigenvalues = pca(X, n_components=4)
    evals, evecs = np.linalg.eigh(np.cov(X, rowvar=False))
    evals, evecs = evals[::-1], evecs[:, ::-1]
    np.testing.assert_allclose(mean, X.mean(axis=0))
    np.testing.assert_allclose(eigenvalues, evals[:4], rtol=1e-10)
    np.testing.assert_allclose(np.abs(np.sum(V * evecs[:, :4], axis=0)), 1.0, rtol=1e-10)  # equal up to sign


def test_pca_fewer_samples_than_dimensions_and_retained_variance():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(10, 500)) * np.linspace(3, 0.1, 500)
    _, V, eigenvalues = pca(X)
    assert V.shape == (500, 9)  # rank N − 1 of the centred data (§8.7.2)
    np.testing.assert_allclose(V.T @ V, np.eye(9), atol=1e-10)
    total = np.var(X, axis=0, ddof=1).sum()
    np.testing.assert_allclose(eigenvalues.sum(), total, rtol=1e-10)
    _, V90, ev90 = pca(X, variance=0.9)
    k = V90.shape[1]
    assert ev90.sum() >= 0.9 * total > eigenvalues[: k - 1].sum()


def labelled(rng, n_classes, per_class, d):
    centres = rng.normal(scale=3.0, size=(n_classes, d))
    A = rng.normal(size=(d, d))  # correlated within-class spread
    X = np.concatenate([c + rng.normal(size=(per_class, d)) @ A for c in centres])
    return X, np.repeat(np.arange(n_classes), per_class)


def test_lda_maximises_the_fisher_ratio():
    rng = np.random.default_rng(2)
    X, y = labelled(rng, 5, 30, 6)
    Sw, Sb = scatter_matrices(X, y)
    W, ratios = fisher_lda(X, y)
    assert W.shape == (6, 4)
    best = scipy.linalg.eigh(Sb, Sw, eigvals_only=True)[::-1]
    np.testing.assert_allclose(ratios, best[:4], rtol=1e-8)
    np.testing.assert_allclose([fisher_ratio(w, Sw, Sb) for w in W.T], ratios, rtol=1e-8)
    random = [fisher_ratio(w, Sw, Sb) for w in rng.normal(size=(2000, 6))]
    assert max(random) < ratios[0]
    np.testing.assert_allclose(W.T @ Sw @ W, np.eye(4), atol=1e-8)  # S_w-orthonormal directions


def test_two_class_lda_is_sw_inverse_times_mean_difference():
    rng = np.random.default_rng(3)
    X, y = labelled(rng, 2, 40, 5)
    Sw, _ = scatter_matrices(X, y)
    W, _ = fisher_lda(X, y)
    assert W.shape == (5, 1)
    expected = np.linalg.solve(Sw, X[y == 1].mean(axis=0) - X[y == 0].mean(axis=0))
    cosine = W[:, 0] @ expected / (np.linalg.norm(W) * np.linalg.norm(expected))
    assert abs(cosine) == pytest.approx(1.0, abs=1e-10)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """Training subjects 100–107 (2 neutral scans each) and test subjects 0–4 (a gallery and a neutral probe
    scan each): disjoint."""
    root = tmp_path_factory.mktemp("subspace")
    train = write_dataset(root / "train", DatasetConfig(subjects=8, scans=2, seed=11, first_subject=100,
                                                         scanner=SMALL), "abs").parent
    test = write_dataset(root / "test", DatasetConfig(subjects=5, scans=2, seed=12, scanner=SMALL), "abs").parent
    return root, train, test


@pytest.fixture(scope="module")
def runs(datasets):
    root, train, test = datasets
    cache = root / "cache"
    return {method: evaluate(test, method, root / method, jobs=1, cache=cache, progress=False, train=train)
            for method in ("pca", "lda")}


@pytest.mark.parametrize("method", ["pca", "lda"])
def test_end_to_end_trained_on_disjoint_subjects(runs, method):
    m = runs[method]
    assert m["n_train"] == 16 and m["n_train_subjects"] == 8 and m["n_gallery"] == 5
    assert m["subsets"]["neutral"]["rank1"] == 1.0  # against the manifest's ground-truth identities


@pytest.mark.parametrize("method", ["pca", "lda"])
def test_saved_model_round_trip(datasets, runs, method):
    root, _, test = datasets
    saved = load_matcher(root / method / "model.npz")
    fresh = make_matcher(method)
    assert saved.name == method and saved.needs_training and saved.options() == fresh.options()
    again = evaluate(test, model=root / method / "model.npz", out=root / f"{method}-loaded", jobs=1,
                     cache=root / "cache", progress=False)
    assert again["rank1"] == runs[method]["rank1"] and again["eer"] == runs[method]["eer"]
    scores = (root / method / "scores.txt").read_text()
    assert (root / f"{method}-loaded" / "scores.txt").read_text() == scores
    with np.load(root / method / "model.npz", allow_pickle=False) as data:  # no pickled objects inside
        assert {"mean", "projection", "scale"} <= set(data.files)


def test_untrained_matcher_and_unusable_training_data_are_refused():
    """Enrolling before fit, fitting on nothing or on scans and subjects of different lengths gave a RuntimeError or
    NumPy's "need at least one array to stack": facerec3d's InputError now, with what to do."""
    from facerec3d.errors import InputError

    for name in ("pca", "lda"):
        with pytest.raises(InputError, match=rf"the {name} matcher is not trained: call fit\(\) \(--train\)"):
            make_matcher(name).enroll(model_face(1))
        with pytest.raises(InputError, match=rf"{name}: 0 training scans, it learns from 2 or more"):
            make_matcher(name).fit([], [])
        with pytest.raises(InputError, match=rf"{name}: 2 training scans and 1 subjects: give one subject per scan"):
            make_matcher(name).fit([model_face(1), model_face(2)], ["s1"])


def test_options():
    matcher = make_matcher("pca", {"n_components": 3, "distance": "cosine", "depth": {"half_width_mm": 40.0}})
    assert matcher.config.n_components == 3 and matcher.config.depth.shape == (41, 41)  # 2 mm steps over ±40 mm
    with pytest.raises(ValueError, match="distance"):
        make_matcher("lda", {"distance": "manhattan"})


def test_missing_cells_filled_by_training_mean_or_nearest_cell():
    rng = np.random.default_rng(4)
    X, Y = grid_xy()
    window = DepthMapConfig(half_width_mm=10.0, step_mm=2.0, fill="mean")  # 11 × 11 cells over ±10 mm
    faces, Z = [], []
    for k in range(8):
        z = 30 - (X**2 + Y**2) / 100 + rng.normal(scale=2.0) * X / 10
        centre = (X.shape[0] - 1) // 2  # the nose tip's cell
        z[tuple(rng.choice(np.arange(centre - 8, centre + 9, 2), size=2))] = np.nan  # a hole at a sampled cell inside the window
        faces.append(depth_to_scan(z, window.grid))
        Z.append(window.window(z).ravel())
    matcher = make_matcher("pca", {"n_components": 1, "depth": asdict(window)}).fit(faces, list("aabbccdd"))
    np.testing.assert_allclose(matcher.mean_, np.nanmean(Z, axis=0))
    hole = np.isnan(Z[0])
    np.testing.assert_allclose(matcher.vector(faces[0])[hole], matcher.mean_[hole])
    nearest = make_matcher("pca", {"depth": {"half_width_mm": 10.0}}).vector(faces[0]).reshape(11, 11)
    r, c = np.argwhere(hole.reshape(11, 11))[0]
    z = window.window(depth_image(faces[0]))
    assert nearest[r, c] in [z[r + dr, c + dc] for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))]  # ties: any


def test_a_damaged_model_file_is_refused_when_loaded_naming_the_file_and_the_array(tmp_path):
    """A model.npz whose projection was cut to 100 rows crashed `evaluate --model` with NumPy's matmul ValueError, a
    shorter mean with a broadcast one; one of NaNs gave rank-1 0 % and gallery entries scoring nan, no error. The
    learnt arrays are checked when loaded: shapes against each other and the settings' depth window, finite."""
    from facerec3d.errors import FaceRec3DError
    from facerec3d.matching.base import Template

    rng = np.random.default_rng(5)
    X, Y = grid_xy()
    window = DepthMapConfig(half_width_mm=10.0)  # 11 × 11 cells: d = 121
    faces = [depth_to_scan(30 - (X**2 + Y**2) / 100 + rng.normal(scale=2.0) * X / 10 + rng.normal(), window.grid)
             for _ in range(8)]
    options = {"depth": asdict(window)}
    for method in ("pca", "lda"):
        matcher = make_matcher(method, options).fit(faces, list("aabbccdd"))
        matcher.save(tmp_path / "good.npz")
        np.testing.assert_array_equal(load_matcher(tmp_path / "good.npz").prepare(faces[0]), matcher.prepare(faces[0]))
        arrays, attrs = matcher.state()
        k = arrays["projection"].shape[1]
        for change, reason in (({"projection": arrays["projection"][:100]}, f"'projection' of shape (100, {k}), not "
                                                                          f"(121, {k})"),
                               ({"mean": arrays["mean"][:60]}, "'mean' of shape (60,), not (121,)"),
                               ({"scale": np.ones(k + 1)}, f"'scale' of shape ({k + 1},), not ({k},)"),
                               ({name: np.full_like(a, np.nan) for name, a in arrays.items()},
                                "'mean' holds NaN or infinite values"),
                               ({"projection": np.where(np.eye(121, k) > 0, np.inf, arrays["projection"])},
                                "'projection' holds NaN or infinite values"),
                               ({"scale": np.zeros(k)}, "'scale' holds values of 0 or less"),
                               ({"mean": arrays["mean"].astype(str)}, "'mean' holds <U32 values, not numbers")):
            bad = tmp_path / "bad.npz"
            Template(None, None, method, {**arrays, **change}, {"options": matcher.options(), "state": attrs}).save(bad)
            with pytest.raises(FaceRec3DError) as e:
                load_matcher(bad)
            assert str(e.value).startswith(f"{bad}: not a usable {method} model ({reason}"), str(e.value)
        Template(None, None, method, {"mean": arrays["mean"]}, {"options": matcher.options(), "state": {}}).save(bad)
        with pytest.raises(FaceRec3DError, match=r"bad.npz: not a usable .* model \(no 'projection' array\)"):
            load_matcher(bad)


def test_lda_refuses_training_scans_with_no_variation_within_a_person():
    """Copies of one scan per person leave S_w singular: scipy's LinAlgError ("leading minor ... not positive
    definite") was a traceback; one line saying why now."""
    from facerec3d.errors import InputError

    f, g = model_face(1), model_face(2)
    for scans in ([f] * 4, [f, f, g, g]):
        with pytest.raises(InputError, match="lda: the training scans show no variation within a person"):
            make_matcher("lda").fit(scans, ["a", "a", "b", "b"])
