"""The matcher interface: templates on disk, ranking with tie-breaks, identification and verification."""

import json
import zipfile

import numpy as np
import pytest

from facerec3d import FaceScan, ScanMeta
from facerec3d.matching import Matcher, Template, rank


class CentroidMatcher(Matcher):
    """A toy matcher: similarity = −distance between centroids; tiebreak = number of probe points."""

    name = "centroid"

    def enroll(self, scan):
        return Template(scan.meta.subject, scan.meta.scan_id, self.name, {"c": scan.points.mean(axis=0)},
                        {"n": scan.n_points})

    def score(self, probe, template):
        p = self._probe(probe)
        return -float(np.linalg.norm(p.arrays["c"] - template.arrays["c"]))


class TiedMatcher(CentroidMatcher):
    def scores(self, probe, templates):
        s, _ = super().scores(probe, templates)
        return s, np.array([t.attrs["n"] for t in templates])


def scan(center, n=10, subject=None):
    pts = np.asarray(center, float) + np.random.default_rng(0).normal(0, 1e-3, (n, 3))
    pts -= pts.mean(axis=0) - center  # exact centroid
    return FaceScan(pts, meta=ScanMeta(subject=subject, scan_id=f"{subject}-1"))


def test_template_save_load(tmp_path):
    arrays = {"x": np.arange(6, dtype=np.int16).reshape(2, 3), "y": np.zeros((0, 3), np.uint8),
              "z": np.array([True, False])}
    t = Template("s01", "s01-a", "demo", arrays, {"resolution": 0.1 + 0.2, "origin": [1.5, -2.0, 3.25], "name": "é",
                                                  "none": None})
    path = tmp_path / "t.npz"
    t.save(path)
    assert path.exists() and not (tmp_path / "t.npz.npz").exists()
    u = Template.load(path)
    assert (u.subject, u.scan_id, u.method, u.attrs) == (t.subject, t.scan_id, t.method, t.attrs)
    assert u.arrays.keys() == t.arrays.keys()
    for k in t.arrays:
        assert u.arrays[k].dtype == t.arrays[k].dtype
        np.testing.assert_array_equal(u.arrays[k], t.arrays[k])
    with zipfile.ZipFile(path) as z, z.open("__template__.npy") as f:  # the metadata is a JSON string, not a pickle
        assert np.lib.format.read_array(f, allow_pickle=False).dtype.kind == "U"
    assert json.loads(str(np.load(path)["__template__"]))["method"] == "demo"
    assert t.nbytes == 12 + 0 + 2


def test_template_rejects_reserved_name_and_unjsonable_attrs(tmp_path):
    for name in ("__template__", "file", "allow_pickle"):
        with pytest.raises(ValueError):
            Template(None, None, "m", {name: np.zeros(1)}).save(tmp_path / "a.npz")
    with pytest.raises(ValueError):  # object arrays would need pickle
        Template(None, None, "m", {"o": np.array([{}, None], dtype=object)}).save(tmp_path / "a.npz")
    with pytest.raises(TypeError):
        Template(None, None, "m", {}, {"bad": np.zeros(1)}).save(tmp_path / "b.npz")


def test_rank_orders_by_score_and_breaks_near_ties():
    s = np.array([-1.0, -0.5, -0.5 * (1 + 1e-12), -2.0, -0.5 * (1 + 1e-6)])
    assert rank(s).tolist() == [1, 2, 4, 0, 3]
    tb = np.array([0, 10, 50, 0, 99])
    # 1 and 2 are tied (relative gap 1e-12): the larger tiebreak first; 4 is not tied (1e-6)
    assert rank(s, tb).tolist() == [2, 1, 4, 0, 3]
    assert rank(np.array([-np.inf, 1.0, -np.inf]), np.array([1, 0, 5])).tolist() == [1, 2, 0]


def test_identify_verify_and_default_scores():
    m = CentroidMatcher()
    gallery = [m.enroll(scan([i * 10.0, 0, 0], subject=f"s{i}")) for i in range(5)]
    probe = scan([21.0, 0, 0])
    s, tb = m.scores(probe, gallery)
    assert tb is None and s.shape == (5,)
    top = m.identify(probe, gallery, k=3)
    assert [i for i, _ in top] == [2, 3, 1]
    assert top[0][1] == pytest.approx(-1.0)
    prepared = m.prepare(probe)
    assert m.identify(prepared, gallery, k=10) == m.identify(probe, gallery, k=10)
    assert len(m.identify(probe, gallery, k=10)) == 5
    assert m.verify(probe, gallery[2], threshold=-1.5)
    assert not m.verify(probe, gallery[3], threshold=-1.5)
    assert m.fit([probe], ["x"]) is m
    from facerec3d.errors import InputError

    for k in (0, -1, 2.5, True):  # k = -1 returned all but the last candidate, 0 none
        with pytest.raises(InputError, match="k must be a whole number of 1 or more"):
            m.identify(probe, gallery, k=k)


def test_identify_uses_tiebreak():
    m = TiedMatcher()
    gallery = [m.enroll(scan([1.0, 0, 0], n=5)), m.enroll(scan([-1.0, 0, 0], n=9)), m.enroll(scan([0, 3.0, 0]))]
    assert [i for i, _ in m.identify(scan([0, 0, 0]), gallery)] == [1, 0, 2]


class LearntMatcher(CentroidMatcher):
    """A toy learnt matcher: fit stores the training centroids' mean, subtracted at enrolment."""

    name = "learnt"

    def __init__(self):
        self.offset = None

    def fit(self, scans, subjects):
        self.offset = np.mean([s.points.mean(axis=0) for s in scans], axis=0)
        return self

    def state(self):
        return {"offset": self.offset}, {"n": 1}

    def set_state(self, arrays, attrs):
        assert attrs == {"n": 1}
        self.offset = arrays["offset"]


def test_matcher_settings_and_learnt_state_survive_save_and_load(tmp_path, monkeypatch):
    from facerec3d.matching import registry

    m = registry.make_matcher("icp", {"variant": "point-to-plane", "fine_points": 500})
    assert (m.config.variant, m.config.fine_points) == ("point-to-plane", 500)
    m.save(tmp_path / "icp.npz")
    assert registry.load_matcher(tmp_path / "icp.npz").config == m.config
    with pytest.raises(ValueError, match="colour: unknown setting"):
        registry.make_matcher("icp", {"colour": 1})
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        registry.make_matcher("nope")

    monkeypatch.setitem(registry.METHODS, "learnt", f"{__name__}:LearntMatcher")
    rng = np.random.default_rng(0)
    learnt = LearntMatcher().fit([FaceScan(rng.normal(size=(50, 3)) + 5) for _ in range(3)], ["a", "b", "c"])
    learnt.save(tmp_path / "learnt.npz")
    back = registry.load_matcher(tmp_path / "learnt.npz")
    assert isinstance(back, LearntMatcher)
    np.testing.assert_array_equal(back.offset, learnt.offset)
    assert not zipfile.ZipFile(tmp_path / "learnt.npz").testzip()


def test_a_file_that_is_not_a_model_is_refused_by_name(tmp_path):
    from facerec3d.errors import FaceRec3DError
    from facerec3d.matching.registry import load_matcher

    bad = tmp_path / "model.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(FaceRec3DError, match=r"model.npz: not a facerec3d model file \(not an .npz archive\)$"):
        load_matcher(bad)  # not numpy's advice to unpickle it
    # a saved model damaged: truncated, or a byte of its data flipped (the zip's CRC), is one line too
    from facerec3d.matching.icp import ICPMatcher
    good = tmp_path / "icp.npz"
    ICPMatcher().save(good)
    assert load_matcher(good).name == "icp"
    data = good.read_bytes()
    with zipfile.ZipFile(good) as z:
        info = max(z.infolist(), key=lambda i: i.compress_size)
    flipped = bytearray(data)
    flipped[info.header_offset + 30 + len(info.filename) + info.compress_size // 2] ^= 0xFF
    for name, content in (("truncated.npz", data[: len(data) // 2]), ("flipped.npz", bytes(flipped))):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(FaceRec3DError, match=f"{name}: not a facerec3d model file, or a damaged one"):
            load_matcher(tmp_path / name)


@pytest.mark.parametrize("name", ["icp", "region-icp", "curvature", "keypoints", "pca", "lda", "afm", "morph-id",
                                  "embedding", "fusion"])
def test_every_method_refuses_a_scan_that_preprocessing_did_not_make(name):
    """A raw scan (a cap 1 m in front of the camera) given to a matcher scored −inf (icp, afm), 0 (morph-id,
    keypoints) or raised a KeyError (region-icp, fusion); an empty face was enrolled as zeros (morph-id). Every
    method now refuses both, saying to preprocess first."""
    from facerec3d.errors import InputError
    from facerec3d.matching.registry import make_matcher
    from tests.conftest import cap_image

    matcher = make_matcher(name)
    raw = cap_image(30, 40)
    for call in (matcher.enroll, matcher.prepare):
        with pytest.raises(InputError, match=r"not a preprocessed face \(its points lie 9\d\d mm or more from the "
                                             r"origin"):
            call(raw)
        with pytest.raises(InputError, match="an empty face, nothing to match"):
            call(FaceScan(np.zeros((0, 3))))


def test_region_icp_names_the_landmarks_a_face_lacks():
    from facerec3d.errors import InputError
    from facerec3d.matching.registry import make_matcher
    from tests.conftest import cap_face

    with pytest.raises(InputError, match="no nose_tip, nose_bridge, left_eye_inner, right_eye_inner landmark"):
        make_matcher("region-icp").prepare(cap_face(30, 40))  # a probe: its regions are placed by them


def _numbers(config, prefix: str = ""):
    """Dotted names of a config's numeric settings (nested ones too) that must not be negative."""
    import dataclasses

    from facerec3d.config import RANGES

    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numbers(value, f"{prefix}{f.name}.")
        elif type(value) in (int, float) and RANGES.get(f.name, (0.0,))[0] == 0.0:
            yield prefix + f.name


def _replaced(config, dotted: str, value):
    import dataclasses

    head, _, rest = dotted.partition(".")
    return dataclasses.replace(config, **{head: _replaced(getattr(config, head), rest, value) if rest else value})


@pytest.mark.parametrize("name", ["icp", "region-icp", "curvature", "keypoints", "pca", "lda", "afm", "morph-id",
                                  "embedding", "fusion"])
def test_every_method_checks_settings_built_in_python_as_a_file_is(name):
    """`ICPMatcher(ICPConfig(max_iterations=-3))` was taken, and failed later or never (a settings file with the same
    value was refused): now each method's config, nested tables included, is range-checked when the matcher gets it,
    naming the field, and a dict in its place is refused in one line. (Values a config's own check refuses as it is
    built never get that far.)"""
    from facerec3d.errors import InputError, SettingsError
    from facerec3d.matching.registry import matcher_class

    cls = matcher_class(name)
    config = cls.config_class()
    checked = []
    for dotted in _numbers(config):
        for value, why in ((-1, r"must be (> 0|>= 0|in \[0, 1\]), not -1"), (float("nan"), "must be a finite number, not nan")):
            try:
                bad = _replaced(config, dotted, value)
            except ValueError as e:  # the config's own check, naming the field
                assert dotted.rsplit(".", 1)[-1] in str(e), f"{name}: {dotted} = {value}: {e}"
                continue
            with pytest.raises(SettingsError, match=f"^{dotted}: {why}$"):
                cls(bad)
            checked.append(dotted)
    with pytest.raises(InputError, match=f"method {name!r} takes {cls.config_class.__name__} settings, not a dict"):
        cls({"seed": 1})
    assert cls(config).config == config  # the defaults pass


def test_a_config_without_range_checks_of_its_own_is_checked_by_the_matcher():
    from facerec3d.errors import SettingsError
    from facerec3d.matching.icp import ICPConfig, ICPMatcher

    config = ICPConfig(max_iterations=-3, max_normal_angle=float("inf"))  # its own checks let both through
    with pytest.raises(SettingsError, match="^max_iterations: must be > 0, not -3$"):
        ICPMatcher(config)
    with pytest.raises(SettingsError, match="^max_normal_angle: must be a finite number, not inf$"):
        ICPMatcher(ICPConfig(max_normal_angle=float("inf")))  # a `float | None` setting


def test_cascade_settings_built_in_python_are_checked():
    from facerec3d.errors import SettingsError
    from facerec3d.gallery.cascade import CascadeConfig

    with pytest.raises(SettingsError, match="^cell_mm: must be a finite number, not nan$"):
        CascadeConfig(cell_mm=float("nan"))
    with pytest.raises(SettingsError, match="^radius_mm: must be > 0, not -64$"):
        CascadeConfig(radius_mm=-64)
    assert CascadeConfig(min_y_mm=-30.0).min_y_mm == -30.0  # a height below the nose tip, as the default's -15


@pytest.mark.parametrize("name", ["icp", "region-icp", "curvature", "keypoints", "pca", "lda", "afm", "morph-id",
                                  "embedding", "fusion"])
def test_every_method_names_what_it_takes_when_given_the_wrong_type(name):
    """An array of points as a probe reached the ICP kernel (a Numba TypingError 7 frames deep), a matmul or
    broadcast (pca, lda, morph-id), a wrong diagnosis (embedding: "enrolled with another model") or an
    AttributeError; so did enrolling one; a threshold "1.0" was Python's TypeError and NaN rejected everything
    silently. One InputError line naming what was expected now, from the base class (probes, thresholds) and
    check_face (scans)."""
    from facerec3d.errors import InputError
    from facerec3d.matching.registry import make_matcher

    matcher = make_matcher(name)
    template = Template(None, None, name, {"features": np.zeros(4)})
    points = np.zeros((50, 3))
    for bad, shown in ((points, "ndarray" if name in ("icp", "region-icp", "curvature", "keypoints", "afm", "fusion")
                        else r"an array of shape \(50, 3\)"), (None, "NoneType")):
        for call in (lambda: matcher.score(bad, template), lambda: matcher.scores(bad, [template]),
                     lambda: matcher.identify(bad, [template]), lambda: matcher.verify(bad, template, 0.0)):
            with pytest.raises(InputError, match=rf"^probe must be a FaceScan or a prepared probe \({name}: .*{shown}"):
                call()
        with pytest.raises(InputError, match=f"^scan must be a FaceScan, not {type(bad).__name__}$"):
            matcher.enroll(bad)
    scan = FaceScan(points=points)  # a scan where a template belongs: an AttributeError deep in each matcher
    for call in (lambda: matcher.score(scan, scan), lambda: matcher.scores(scan, [template, scan]),
                 lambda: matcher.identify(scan, [scan]), lambda: matcher.verify(scan, scan, 0.0)):
        with pytest.raises(InputError, match=rf"^{name} scores a probe against gallery templates \(from enroll\(\)\), "
                                             "not FaceScan$"):
            call()
    for threshold in ("1.0", float("nan"), None, float("inf")):
        with pytest.raises(InputError, match="^a verification threshold is a finite number, not "):
            matcher.verify(points, template, threshold)
    if name in ("pca", "morph-id"):  # a vector of another length: the Euclidean distance broadcast it silently
        with pytest.raises(InputError, match="a probe of 1 features against templates of 4"):
            matcher.score(np.zeros(1), Template(None, None, name, {"features": np.zeros(4), "identity": np.zeros(4)}))
