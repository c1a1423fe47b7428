"""Shared test helpers and fixtures: small synthetic range images and scans, model faces, the pyeer check.

Test modules import the helpers from here (`from tests.conftest import model_face`), never from each other.
Tests that take minutes are marked `slow` (run by default; `-m "not slow"` leaves them out).
"""

import atexit
import os
import shutil
import tempfile
from pathlib import Path
from typing import NamedTuple

# The tests never write the user's caches (~/.cache/facerec3d's preprocessed faces, matplotlib's fonts): each test
# process has its own cache home, set before facerec3d is imported (`preprocess.batch.DEFAULT_CACHE` reads it then),
# with the preprocessing cache's folder already made, so that no command's output starts with the cache's
# first-use line (`cli._cache_folder`) in one order of the tests and not in another (in a fresh HOME a test that
# expected an error line first failed).
_CACHE_HOME = tempfile.mkdtemp(prefix="facerec3d-tests-")
os.environ["XDG_CACHE_HOME"] = _CACHE_HOME
(Path(_CACHE_HOME) / "facerec3d" / "preprocessed").mkdir(parents=True)
atexit.register(shutil.rmtree, _CACHE_HOME, ignore_errors=True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from facerec3d import FaceScan  # noqa: E402
from facerec3d.datasets.frontal import CROP_MM, frontal_face  # noqa: E402


def cap_image(rows: int = 12, cols: int = 16, invalid=((0, 0), (5, 7), (11, 15)), seed: int = 1) -> FaceScan:
    """A sphere cap (radius 60 mm, 1 m in front of the camera, Z < 0) on a grid of 2 mm pixels, a few invalid."""
    r, c = np.mgrid[0:rows, 0:cols].astype(float)
    x, y = (c - cols / 2) * 2.0, (rows / 2 - r) * 2.0
    z = -1000.0 + np.sqrt(np.maximum(60.0**2 - x**2 - y**2, 0.0))
    xyz = np.stack([x, y, z], axis=-1) + np.random.default_rng(seed).normal(0, 0.01, (rows, cols, 3))
    valid = np.ones((rows, cols), bool)
    for i, j in invalid:
        valid[i, j] = False
    return FaceScan.from_range_image(xyz, valid)


def cap_face(rows: int = 12, cols: int = 16, **kw) -> FaceScan:
    """`cap_image` where preprocessing puts a face: its apex (the "nose tip") at the origin, as matchers take it."""
    return cap_image(rows, cols, **kw).transformed(np.eye(3), np.array([0.0, 0.0, 940.0]))


@pytest.fixture
def cap():
    return cap_image()


def model_face(subject: int, expression: str = "neutral", noise_mm: float = 0.2, crop_mm: float = CROP_MM) -> FaceScan:
    """A face as preprocessing leaves it, straight from the model (datasets.frontal), with depth noise and the
    model's true fiducials as landmarks; subject ids "s<n>"."""
    face = frontal_face(subject, noise_mm=noise_mm, seed=len(expression), expression=expression, crop_mm=crop_mm)
    return face.replace(meta=face.meta.replace(subject=f"s{subject}"))


class CliData(NamedTuple):
    """A small synthetic FRGC-layout dataset written by `facerec3d synth`, split for CLI tests."""

    folder: Path
    gallery: list[Path]  # each subject's first scan
    probe: Path  # the first subject's second scan (an expression)
    probe_subject: str
    other: str  # another enrolled subject


def cli_dataset(folder: Path, strength: float, subjects: int = 3, sensor: str | None = None) -> CliData:
    """`subjects` people × 2 scans (240 × 320, seed 5; the second scan a smile of this strength) via the CLI."""
    from click.testing import CliRunner

    from facerec3d.cli import main

    extra = ["--sensor", sensor] if sensor else ["--rows", "240", "--cols", "320"]
    r = CliRunner().invoke(main, ["synth", str(folder), "--subjects", str(subjects), "--scans", "2", *extra,
                                  "--seed", "5", "--expressions", "smile", "--expression-strength", str(strength),
                                  str(strength)])
    assert r.exit_code == 0, r.output
    rows = [line.split(",") for line in (folder / "manifest.csv").read_text().splitlines()[1:]]
    probe_subject = rows[1][1]
    return CliData(folder, [folder / p for p, *_ in rows[::2]], folder / rows[1][0], probe_subject,
                   next(s for _, s, *_ in rows if s != probe_subject))


def service_identify(tmp_path: Path, matcher, form: dict[str, str]) -> list[dict]:
    """The service in process (one worker) on a new gallery of `matcher`: three people enrolled from raw scans (near
    frontal, neutral), then a smiling scan of s1 identified with the `form` fields; returns the candidates."""
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from facerec3d.gallery.store import GalleryStore
    from facerec3d.io import save_scan
    from facerec3d.preprocess.pipeline import PreprocessConfig
    from facerec3d.server.app import Service, ServiceSettings, create_app
    from facerec3d.server.keys import KeyFile, add_key
    from facerec3d.server.live import AuditLog, LiveGallery

    gallery, keys = tmp_path / f"{matcher.name}.sqlite", tmp_path / f"{matcher.name}-keys.json"
    with GalleryStore(gallery, create=True) as store:
        store.bind(PreprocessConfig(), matcher)
    key = add_key(keys, "alice", "enrol,query,admin")
    scans = {}
    for s, e in ((0, "neutral"), (1, "neutral"), (2, "neutral"), (1, "smile")):
        scans[(s, e)] = tmp_path / f"{s}-{e}.npz"
        save_scan(frontal_face(s, pose_deg=3.0, shift_mm=3.0, noise_mm=0.2, seed=s, expression=e), scans[(s, e)])
    service = Service(LiveGallery(gallery, 1, audit=AuditLog(None)), KeyFile(keys), ServiceSettings(timeout_s=300))
    try:
        with TestClient(create_app(service)) as client:
            h = {"X-API-Key": key}
            for s in (0, 1, 2):
                path = scans[(s, "neutral")]
                r = client.post("/v1/enrol", headers=h, files={"scan": (path.name, path.read_bytes())},
                                data={"subject": f"s{s}"})
                assert r.status_code == 201, r.text
            probe = scans[(1, "smile")]
            r = client.post("/v1/identify", headers=h, files={"probe": (probe.name, probe.read_bytes())}, data=form)
            assert r.status_code == 200, r.text
            return r.json()["candidates"]
    finally:
        service.close()


def faceless_scans() -> dict[str, FaceScan]:
    """Range images with no face: a wall, random depths, and an empty scan."""
    r, c = np.mgrid[0:120, 0:160].astype(float)
    wall = np.stack([(c - 80) * 2.0, (60 - r) * 2.0, np.full(r.shape, -1500.0)], axis=-1)
    rng = np.random.default_rng(3)
    noise = np.stack([(c - 80) * 2.0, (60 - r) * 2.0, rng.uniform(-1500, -800, r.shape)], axis=-1)
    empty = FaceScan(points=np.zeros((0, 3)), grid=np.zeros((0, 2)), grid_shape=(4, 4))
    return {"wall": FaceScan.from_range_image(wall), "noise": FaceScan.from_range_image(noise), "empty": empty}


def check_against_pyeer(path):
    """EER and VR of a 4-column score file against pyeer's on the same scores (skips when pyeer is missing).

    pyeer (Maio et al. FVC2000 convention) evaluates FMR / FNMR at every distinct score (accept score >= t, as
    here) and reports an EER interval [eer_low, eer_high] at the threshold nearest the crossing, with their
    midpoint as its EER; our EER is the crossing itself, so it lies inside pyeer's interval. pyeer's fmr1000 is
    the FNMR at the point whose FMR is NEAREST 0.1 % (possibly above it); our VR at FMR 0.1 % is the best TAR
    with FMR <= 0.1 %, i.e. 1 - the lowest FNMR over pyeer's points with FMR <= 0.001, and equals 1 - fmr1000
    whenever pyeer's nearest point is not above 0.1 %.
    """
    eer_info = pytest.importorskip("pyeer.eer_info")
    eer_stats = pytest.importorskip("pyeer.eer_stats")
    from facerec3d.evaluation.metrics import eer, verification_rate
    from facerec3d.evaluation.scorefile import read_scores

    genuine, impostor = read_scores(path)
    with np.errstate(invalid="ignore"):  # pyeer's score statistics (mean, std) of -inf scores
        stats = eer_info.get_eer_stats(list(genuine), list(impostor))
    ours = eer(genuine, impostor)
    assert stats.eer_low - 1e-12 <= ours <= stats.eer_high + 1e-12, (ours, stats.eer_low, stats.eer_high)
    _, fmr, fnmr = eer_stats.calculate_roc(list(genuine), list(impostor))
    for far, nearest in ((0.001, stats.fmr1000), (0.01, stats.fmr100)):
        vr = verification_rate(genuine, impostor, far)
        allowed = fmr <= far
        assert vr == pytest.approx(1 - fnmr[allowed].min() if allowed.any() else 0.0)
        if fmr[np.argmin(np.abs(fmr - far))] <= far:
            assert vr == pytest.approx(1 - nearest)
    return ours, stats
