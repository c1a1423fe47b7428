"""A small Python client of the gallery service (`facerec3d serve`).

    from facerec3d.client import Client
    with Client("http://127.0.0.1:8000", api_key="fr3d_…") as c:     # or FACEREC3D_API_KEY in the environment
        c.enrol("04200d74.abs.gz", subject="04200")               # -> {"id": 17, "subject": "04200", ...}
        c.identify("probe.abs.gz", k=5, cascade=True)["candidates"]
        c.verify("probe.abs.gz", claim="04200")["accepted"]
        c.calibrate(["04200d74.abs.gz", "04201d80.abs.gz"], ["04200", "04201"], own=True)  # the threshold's record

Errors of the service raise `ServiceError` (with `status` and the service's `reason`); a service that cannot
be reached raises it too (status 0). Busy answers (429, 503) are retried after their Retry-After, a few times.
Needs httpx: pip install 'facerec3d[service]'.

Preprocessing at the edge: `enrol`, `identify` and `verify` take `preprocess_locally=True` to preprocess the scan
here, with the service's own settings (from /v1/stats, checked against its fingerprint), and upload the face
(.npz, recording that fingerprint), which the service matches without preprocessing it again — the scan's
preprocessing (a few tenths of a core-second) is spent on the client's cores instead of the service's. A file that already is such
a face is uploaded as it is. Answers say `"preprocessed_upload": true` when the service took the face as it was.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facerec3d.errors import FaceRec3DError, InputError

API_KEY_ENV = "FACEREC3D_API_KEY"


class ServiceError(FaceRec3DError):
    """The service answered with an error (or could not be reached: status 0)."""

    def __init__(self, status: int, reason: str):
        self.status, self.reason = status, reason
        super().__init__(f"service error {status}: {reason}" if status else reason)


@dataclass(frozen=True)
class ScanUpload:
    """A scan as it is sent to the service (`Client.upload`): its file name (which tells the format and the default
    scan id), its bytes (the scan, or the face preprocessed here) and form fields (a depth frame's intrinsics).
    `enrol` and `calibrate` take one where they take a path: the same bytes sent twice are the same scan."""

    name: str
    data: bytes
    fields: dict


class Client:
    """Calls a gallery service at `url` with an API key (default: the FACEREC3D_API_KEY environment variable)."""

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 300.0, retries: int = 5):
        try:
            import httpx
        except ImportError:
            raise FaceRec3DError("the service client needs httpx: pip install 'facerec3d[service]'") from None
        self.url = url.rstrip("/")
        key = api_key if api_key is not None else os.environ.get(API_KEY_ENV)
        self.retries = retries
        try:
            self._http = httpx.Client(base_url=self.url, timeout=timeout, headers={"X-API-Key": key} if key else {})
        except httpx.InvalidURL as e:  # (not an httpx.HTTPError: it would end in a traceback)
            raise InputError(f"bad service URL {url!r}: {e}") from None
        self._httpx = httpx
        self._preprocessor = None  # the service's preprocessing, made on first use (preprocess_locally)
        self._lock = threading.Lock()

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ plumbing
    def _call(self, method: str, path: str, files: dict | list | None = None, data: dict | None = None,
              headers: dict | None = None, text: bool = False) -> Any:
        for attempt in range(self.retries + 1):
            try:
                r = self._http.request(method, path, files=files, data=data, headers=headers)
            except self._httpx.HTTPError as e:
                raise ServiceError(0, f"cannot reach the service at {self.url}: {e}") from None
            if r.status_code in (429, 503) and attempt < self.retries:
                time.sleep(min(30.0, float(r.headers.get("retry-after", 1) or 1) * (1 + attempt)))
                continue
            break
        if r.status_code >= 400:
            try:
                reason = r.json()["error"]
            except (ValueError, KeyError, TypeError):
                reason = r.text.strip()[:300] or r.reason_phrase
            raise ServiceError(r.status_code, reason)
        if r.is_redirect:  # not followed (a form is not sent twice): e.g. DELETE /v1/subjects/ for an empty id
            raise ServiceError(r.status_code, f"the service redirected {method} {path} to "
                                              f"{r.headers.get('location', '(nowhere)')[:200]}, not followed")
        if text:
            return r.text
        try:
            return r.json()
        except ValueError:  # (a proxy's page, or no body): one line, not a JSONDecodeError's traceback
            raise ServiceError(r.status_code, f"the answer to {method} {path} is not JSON: "
                                              f"{r.text.strip()[:100]!r}") from None

    @staticmethod
    def _scan(path: str | os.PathLike, field: str, intrinsics: str | os.PathLike | None = None) -> tuple[dict, dict]:
        """The multipart file of a scan (its name tells the format) and, for a depth frame, its intrinsics: the
        JSON file `intrinsics` when given, else the intrinsics.json found beside the frame."""
        from facerec3d.io import DEPTH_SUFFIXES, Intrinsics, find_intrinsics, scan_suffix

        p = Path(path)
        data = {}
        if scan_suffix(p) in DEPTH_SUFFIXES + (".npy",) and (camera := intrinsics or find_intrinsics(p)) is not None:
            Intrinsics.load(camera)  # ScanFormatError naming the file and the reason (not JSON, not UTF-8, ...),
            #                          as locally, not a JSONDecodeError's traceback
            data["intrinsics"] = json.dumps(json.loads(Path(camera).read_text()))
        return {field: (p.name, p.read_bytes(), "application/octet-stream")}, data

    def preprocessor(self):
        """A `Preprocessor` with the service's settings (GET /v1/stats), made once; `FaceRec3DError` when this
        facerec3d cannot reproduce them (its fingerprint of the settings differs from the service's)."""
        with self._lock:
            if self._preprocessor is None:
                self._preprocessor = self._service_preprocessor()
            return self._preprocessor

    def _service_preprocessor(self):
        from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor

        st = self.stats()
        try:
            config = PreprocessConfig.from_dict(st["preprocess"])
        except (FaceRec3DError, KeyError, TypeError, ValueError) as e:
            raise FaceRec3DError(f"cannot preprocess locally for {self.url}: its preprocessing settings are not "
                                 f"this facerec3d's ({e}); upload raw scans") from None
        if config.digest() != st.get("preprocess_fingerprint"):
            raise FaceRec3DError(f"cannot preprocess locally for {self.url}: this facerec3d's fingerprint of its "
                                 f"settings is {config.digest()}, the service's {st.get('preprocess_fingerprint')} "
                                 "(another version?); upload raw scans")
        return Preprocessor(config)

    def _preprocessed(self, path: str | os.PathLike, field: str,
                      intrinsics: str | os.PathLike | None = None) -> tuple[dict, dict]:
        """The multipart file of a scan preprocessed here with the service's settings, as `.npz` named after the
        scan (so the default scan id is the same); a file that already is a preprocessed face goes as it is; a
        depth frame is read with `intrinsics` when given. `FaceRec3DError` (e.g. no face found) when it cannot be
        preprocessed."""
        from facerec3d.io import load_scan, save_scan, scan_stem
        from facerec3d.preprocess.pipeline import preprocessed_with

        p = Path(path)
        scan = load_scan(p, intrinsics)
        if preprocessed_with(scan) is not None:  # already a face: the service says whether its settings fit
            return {field: (p.name, p.read_bytes(), "application/octet-stream")}, {}
        face = self.preprocessor()(scan)
        with tempfile.TemporaryDirectory(prefix="facerec3d-client-") as tmp:
            out = Path(tmp) / "face.npz"
            save_scan(face, out)
            data = out.read_bytes()
        return {field: (f"{scan_stem(p)}.npz", data, "application/octet-stream")}, {}

    def _upload(self, path: str | os.PathLike, field: str, preprocess_locally: bool,
                intrinsics: str | os.PathLike | None = None) -> tuple[dict, dict]:
        return (self._preprocessed(path, field, intrinsics) if preprocess_locally
                else self._scan(path, field, intrinsics))

    @staticmethod
    def _form(**fields: Any) -> dict:
        return {k: (str(v).lower() if isinstance(v, bool) else str(v)) for k, v in fields.items() if v is not None}

    def upload(self, path: str | os.PathLike, preprocess_locally: bool = False,
               intrinsics: str | os.PathLike | None = None) -> ScanUpload:
        """A scan file as `enrol` sends it: its bytes with a depth frame's intrinsics, or (`preprocess_locally`)
        the face preprocessed here. Kept, it can be enrolled and later calibrated on as the very same bytes."""
        files, data = self._upload(path, "scan", preprocess_locally, intrinsics)
        name, content, _ = files["scan"]
        return ScanUpload(name, content, data)

    # ------------------------------------------------------------------ the API
    def enrol(self, path: str | os.PathLike | ScanUpload, subject: str, scan_id: str | None = None,
              preprocess_locally: bool = False, intrinsics: str | os.PathLike | None = None) -> dict:
        """Enrol a scan file (or a `ScanUpload`) for a subject: the new entry (id, subject, scan_id, source, ...).
        ServiceError 409 when already enrolled, 422 for a failure to enrol (with the reason). `preprocess_locally`:
        preprocess here and upload the face (see the module's docstring). `intrinsics`: a depth frame's camera
        (JSON file; default: the intrinsics.json beside it), here and in `identify`, `verify` and `calibrate`."""
        scan = path if isinstance(path, ScanUpload) else self.upload(path, preprocess_locally, intrinsics)
        return self._call("POST", "/v1/enrol", {"scan": (scan.name, scan.data, "application/octet-stream")},
                          {**scan.fields, **self._form(subject=subject, scan_id=scan_id)})

    enroll = enrol

    def identify(self, path: str | os.PathLike, k: int = 5, cascade: bool = False, shortlist: int = 20,
                 timeout_s: float | None = None, preprocess_locally: bool = False, screen: str = "depth",
                 intrinsics: str | os.PathLike | None = None) -> dict:
        """The k best candidates for a probe scan: {"candidates": [{rank, entry, subject, scan_id, score}], ...}."""
        files, data = self._upload(path, "probe", preprocess_locally, intrinsics)
        headers = {"X-Request-Timeout": str(timeout_s)} if timeout_s else None
        return self._call("POST", "/v1/identify", files,
                          {**data, **self._form(k=k, cascade=cascade, shortlist=shortlist, screen=screen)}, headers)

    def verify(self, path: str | os.PathLike, claim: str, threshold: float | None = None,
               preprocess_locally: bool = False, intrinsics: str | os.PathLike | None = None) -> dict:
        """{"accepted", "score", "threshold", "claim", ...} for a probe scan and a claimed subject."""
        files, data = self._upload(path, "probe", preprocess_locally, intrinsics)
        return self._call("POST", "/v1/verify", files, {**data, **self._form(claim=claim, threshold=threshold)})

    def calibrate(self, scans: Sequence[str | os.PathLike | ScanUpload], subjects: Sequence[str],
                  fmr: float | None = 0.01, own: bool = False, preprocess_locally: bool = False,
                  intrinsics: str | os.PathLike | None = None) -> dict:
        """Calibrate the gallery's verification threshold on labelled scans (files or `ScanUpload`s, with their
        subjects; at most 100, in one request within the service's upload limit) at false-match rate `fmr`, or
        at the equal error rate when `fmr` is None; `own`: they are the scans the gallery was enrolled from. Each
        is scored without the entry enrolled from the same bytes. Returns the threshold's record, committed. A single
        scan (a path or a `ScanUpload`) and a single subject are taken as lists of one, not iterated (a path's
        characters were read as files)."""
        if isinstance(scans, (str, os.PathLike, ScanUpload)):
            scans = [scans]
        if isinstance(subjects, str):
            subjects = [subjects]
        uploads = [s if isinstance(s, ScanUpload) else self.upload(s, preprocess_locally, intrinsics) for s in scans]
        form: dict[str, Any] = {"subject": [str(s) for s in subjects], **self._form(fmr=fmr, eer=fmr is None, own=own)}
        cameras = [u.fields.get("intrinsics") for u in uploads]
        if any(cameras):
            form["intrinsics"] = [camera or "null" for camera in cameras]
        files = [("scan", (u.name, u.data, "application/octet-stream")) for u in uploads]
        return self._call("POST", "/v1/calibrate", files, form)["threshold"]

    def subjects(self) -> list[dict]:
        """[{"subject", "entries"}] of the gallery."""
        return self._call("GET", "/v1/subjects")["subjects"]

    def entries(self) -> dict:
        """{"entries": [...], "failures": [{"source", "reason"}]}."""
        return self._call("GET", "/v1/entries")

    def remove(self, ident: str) -> dict:
        """Remove subject IDENT's entries (or else scan IDENT's): {"removed": [ids], ...}. InputError for an id
        no entry can have ("", ".", ".."), which would make another URL."""
        from urllib.parse import quote

        if ident in ("", ".", ".."):
            raise InputError(f"remove: bad subject or scan id {ident!r}: give a non-empty id (not . or ..)")
        return self._call("DELETE", f"/v1/subjects/{quote(ident, safe='')}")

    def remove_entry(self, entry: int) -> dict:
        """Remove the entry of id ENTRY (`entries()` lists them): {"removed": [entry], ...}."""
        return self._call("DELETE", f"/v1/entries/{int(entry)}")

    def stats(self) -> dict:
        return self._call("GET", "/v1/stats")

    def health(self) -> dict:
        return self._call("GET", "/v1/health")

    def metrics(self) -> str:
        return self._call("GET", "/metrics", text=True)
