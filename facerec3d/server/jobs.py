"""What the service's workers do with an uploaded scan: read it within limits, preprocess it with the gallery's
settings, then enrol it (a template) or prepare it as a probe. These run in the engine's worker processes
(or Dask workers), so they take the upload's bytes, never a path: the bytes are written to a private
temporary folder under a name the service chooses (`scan` + the format suffix), read and deleted.

Preprocessing at the edge: an upload that is already a face preprocessed by facerec3d (an `.npz` written by
`facerec3d preprocess` or `save_scan`, whose `meta_json` records `preprocess_fingerprint`) is taken as it is,
without preprocessing it again, when that fingerprint is the gallery's (`PreprocessConfig.digest()`) and it
lies on the gallery's resampling grid within the crop sphere. One preprocessed with other settings, or by a
facerec3d that recorded none, is refused (`Mismatch`, 422 with both fingerprints): preprocessing a face
twice would silently make it unlike the gallery's faces, and it is no failure of the scan.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facerec3d.errors import FaceRec3DError
from facerec3d.gallery.cascade import CascadeConfig, face_descriptor
from facerec3d.gallery.engine import Probe
from facerec3d.io import DEPTH_SUFFIXES, READERS, Intrinsics, load_scan
from facerec3d.matching.base import Matcher, Template
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor, preprocessed_with
from facerec3d.scan import FaceScan


class Rejected(Exception):
    """An upload the service refuses: an HTTP status and the reason (picklable, crosses process boundaries)."""

    def __init__(self, status: int, reason: str):
        super().__init__(status, reason)
        self.status, self.reason = status, reason

    def __str__(self) -> str:
        return self.reason


class Mismatch(Rejected):
    """A preprocessed face whose settings are not the gallery's (422): refused, never a failure to enrol."""


@dataclass(frozen=True)
class Upload:
    """An uploaded scan: its bytes, its format suffix (checked against `READERS` by the service), the
    client's file name (a label in messages, never a path) and, for depth frames, camera intrinsics."""

    data: bytes
    suffix: str
    label: str = "upload"
    intrinsics: dict | None = None


def ready(i: int) -> int:
    """A no-op a worker runs to start (the pid)."""
    return os.getpid()


def warm_up(i: int, config: PreprocessConfig, matcher: Matcher) -> float:
    """What a worker does once before the service answers (seconds): a synthetic Kinect v2 frame preprocessed with
    the gallery's settings, enrolled and matched against itself, so that the first client's request does not wait
    for Numba to compile (or load) facerec3d's kernels and a model's session to open: ~20 s for the first
    enrolment and ~7 s for the first identification after an install on 2 cores, before this. A failure raises
    (the service says so in one line and serves all the same)."""
    from facerec3d.datasets.synthetic import quick_scan, sensor_profile

    t0 = time.perf_counter()
    face = Preprocessor(config)(quick_scan(i, scanner=sensor_profile("kinect-v2")).scan)
    template = matcher.enroll(face)
    template.subject, template.scan_id = "warm-up", "warm-up"
    matcher.scores(matcher.prepare(face), [template])
    return time.perf_counter() - t0


def read_upload(upload: Upload, max_points: int) -> FaceScan:
    """The scan in an upload; `Rejected` 422 (unreadable: the reader's reason) or 413 (over `max_points`)."""
    if upload.suffix not in READERS:
        raise Rejected(415, f"{upload.label}: unknown scan format {upload.suffix!r}")
    with tempfile.TemporaryDirectory(prefix="facerec3d-upload-") as tmp:
        path = Path(tmp) / f"scan{upload.suffix}"
        path.write_bytes(upload.data)
        try:
            if upload.intrinsics is not None:
                scan = load_scan(path, Intrinsics.from_dict(upload.intrinsics, "intrinsics"))
            elif upload.suffix in DEPTH_SUFFIXES:
                raise Rejected(422, f"{upload.label}: a depth frame needs the camera's intrinsics (form field "
                                    "'intrinsics': JSON with fx, fy, cx, cy)")
            else:  # the reader itself: load_scan would look for an intrinsics.json in the folders above
                scan = READERS[upload.suffix](path)
        except FaceRec3DError as e:  # the reason only: the message would name the temporary file
            raise Rejected(422, f"{upload.label}: {getattr(e, 'reason', e)}") from None
    if scan.n_points > max_points:
        raise Rejected(413, f"{upload.label}: the scan has {scan.n_points} points; this service takes at most "
                            f"{max_points}")
    return scan


_PREPROCESSORS: dict[str, Preprocessor] = {}


def _preprocess(scan: FaceScan, config: PreprocessConfig, label: str) -> FaceScan:
    """The preprocessed face; `Rejected` 422 with the reason when no face can be found (failure to acquire)."""
    pre = _PREPROCESSORS.setdefault(config.fingerprint(), Preprocessor(config))
    try:
        return pre(scan)
    except FaceRec3DError as e:
        raise Rejected(422, f"{label}: {getattr(e, 'reason', e)}") from None


def face_of(scan: FaceScan, config: PreprocessConfig, label: str) -> tuple[FaceScan, bool]:
    """(the face to enrol or match, whether the upload was already preprocessed): a face preprocessed by
    facerec3d with the gallery's settings as it is, any other scan preprocessed here. `Mismatch` 422 for a
    preprocessed face with other or unknown settings, `Rejected` 422 for one that is off the gallery's grid."""
    recorded = preprocessed_with(scan)
    if recorded is None:
        return _preprocess(scan, config, label), False
    own = config.digest()
    if recorded != own:
        said = (f"with other settings (preprocess_fingerprint {recorded[:64]!r})" if recorded else
                "with unknown settings (it records no preprocess_fingerprint: an older facerec3d)")
        raise Mismatch(422, f"{label}: a face preprocessed {said}; this service's preprocess_fingerprint is {own!r} "
                            "(GET /v1/stats): upload the raw scan, or preprocess it with the service's settings "
                            "(--preprocess-locally)")
    size, radius = config.resample.size, config.crop_radius_mm
    if scan.grid_shape != (size, size):
        raise Rejected(422, f"{label}: a preprocessed face must lie on the {size}×{size} resampling grid, not "
                            f"{'no grid' if scan.grid_shape is None else '×'.join(map(str, scan.grid_shape))}")
    far = float(np.sqrt((scan.points**2).sum(axis=1).max()))
    if far > radius + 10.0:  # the crop sphere (denoising may move the rim by a little)
        raise Rejected(422, f"{label}: a preprocessed face lies within {radius:g} mm of its nose tip; this one "
                            f"reaches {far:.0f} mm")
    return scan, True


def enrol_job(upload: Upload, max_points: int, config: PreprocessConfig, matcher: Matcher, subject: str,
              scan_id: str) -> tuple[Template | None, str | None, dict, bool]:
    """(template, None, timings, preprocessed upload) or (None, reason, timings, False) when the scan cannot be
    read, preprocessed or enrolled (a failure to enrol); `Rejected` 413/415 for an upload outside the limits,
    `Mismatch` 422 for a face preprocessed with other settings (see `face_of`)."""
    t0 = time.perf_counter()
    try:
        scan = read_upload(upload, max_points)
        t1 = time.perf_counter()
        face, given = face_of(scan, config, upload.label)
        t2 = time.perf_counter()
        try:
            template = matcher.enroll(face)
        except ValueError as e:  # e.g. too few points to enrol
            raise Rejected(422, f"{upload.label}: {e}") from None
    except Rejected as e:
        if e.status != 422 or isinstance(e, Mismatch):
            raise
        return None, e.reason, {"total_ms": 1e3 * (time.perf_counter() - t0)}, False
    template.subject, template.scan_id = subject, scan_id
    t3 = time.perf_counter()
    return template, None, {"read_ms": 1e3 * (t1 - t0), "preprocess_ms": 1e3 * (t2 - t1),
                            "enrol_ms": 1e3 * (t3 - t2)}, given


def probe_job(upload: Upload, max_points: int, config: PreprocessConfig, matcher: Matcher,
              cascade: CascadeConfig | None) -> tuple[Probe, dict, bool]:
    """The upload as a probe ready for matching (with its depth descriptor for the cascade), timings, and
    whether the upload was a face already preprocessed with the gallery's settings (then taken as it is:
    `preprocess_ms` is the check only); `Rejected` when it cannot be used."""
    t0 = time.perf_counter()
    scan = read_upload(upload, max_points)
    t1 = time.perf_counter()
    face, given = face_of(scan, config, upload.label)
    t2 = time.perf_counter()
    described = cascade is not None and cascade.screen != "keypoints"
    try:
        probe = Probe(matcher.prepare(face), face_descriptor(face, cascade) if described else None)
    except ValueError as e:
        raise Rejected(422, f"{upload.label}: {e}") from None
    t3 = time.perf_counter()
    return probe, {"read_ms": 1e3 * (t1 - t0), "preprocess_ms": 1e3 * (t2 - t1), "prepare_ms": 1e3 * (t3 - t2)}, given
