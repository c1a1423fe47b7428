"""The HTTP service: FastAPI on uvicorn over a `LiveGallery` (what `facerec3d serve` runs).

Every request under /v1 (but /v1/health) and /metrics carries an API key (`X-API-Key: KEY` or
`Authorization: Bearer KEY`), checked before the body is read: 401 without a known key, 403 outside its
scope. Uploads larger than the limit are refused (413) from Content-Length or while they stream in. Scan work
goes through a bounded queue: at most `concurrency` requests are worked on, `queue` more wait, and the
rest are answered 503 (queue full) or 429 (one key holding more than `per_key` places) with Retry-After.
Each request has a time limit (`timeout_s`, or less with an `X-Request-Timeout: SECONDS` header): past it
the answer is 504 and work not yet started is dropped; an enrolment that has begun committing is waited
for, so an answer never contradicts the store. Errors are one-line JSON: {"error": reason, "status": code}.

An upload may be a raw scan (preprocessed here) or a face already preprocessed by facerec3d with the gallery's
settings (an `.npz` recording the same `preprocess_fingerprint` as /v1/stats), taken as it is: answers say
which ("preprocessed_upload"), /v1/stats counts both; a face preprocessed with other settings is 422 (jobs.py).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import math
import re
import sys
import threading
import time
import traceback
from collections import Counter, defaultdict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from fastapi import FastAPI, File, Form, HTTPException, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse, PlainTextResponse

from facerec3d.errors import FaceRec3DError
from facerec3d.gallery.cascade import CascadeConfig
from facerec3d.gallery.store import Entry, GalleryError
from facerec3d.io import SUPPORTED_SUFFIXES, scan_stem, scan_suffix
from facerec3d.server.jobs import Rejected, Upload, enrol_job, probe_job
from facerec3d.server.keys import KeyFile
from facerec3d.server.live import Conflict, LiveGallery, NotFound

API = "/v1"
_LABEL = re.compile(r"^[\w.@+:-]{1,128}$")  # subject and scan ids: no spaces, slashes or control characters


@dataclass
class ServiceSettings:
    """Limits of a service (see `facerec3d serve --help`)."""

    concurrency: int = 4  # requests worked on at once
    queue: int = 32  # requests waiting beyond those; more are answered 503
    per_key: int | None = None  # requests queued or running for one key; more are 429 (default: half the places)
    timeout_s: float = 60.0  # time limit per request
    max_upload_bytes: int = 64 * 2**20  # largest request body


class ApiError(Exception):
    """An HTTP error answer: status, reason and headers."""

    def __init__(self, status: int, reason: str, headers: dict[str, str] | None = None):
        super().__init__(reason)
        self.status, self.reason, self.headers = status, reason, headers or {}


def _error(status: int, reason: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"error": " ".join(str(reason).split()), "status": status}, status, headers=headers)


# ---------------------------------------------------------------------------------------------- work queue
class Job:
    """One request's work: its deadline, and whether it was given up (time limit) or has begun committing."""

    def __init__(self, limit_s: float):
        self.limit_s = limit_s
        self.deadline = time.monotonic() + limit_s
        self.abandoned = self.committing = False
        self._lock = threading.Lock()

    def check(self) -> None:
        """Stop here (504) when the request was given up or its time is over."""
        if self.abandoned or time.monotonic() > self.deadline:
            raise ApiError(504, f"the request took longer than its time limit of {self.limit_s:g} s")

    def commit(self) -> None:
        """About to write to the store: from now on the request is waited for, whatever the time limit."""
        with self._lock:
            self.check()
            self.committing = True

    def abandon(self) -> bool:
        """Give the request up (time limit); False when it is already committing."""
        with self._lock:
            if self.committing:
                return False
            self.abandoned = True
            return True


class WorkQueue:
    """At most `concurrency` jobs at once on threads (which hand scans to the engine's workers), `queue` more
    waiting; beyond that 503, and 429 for a key holding more than `per_key` places."""

    def __init__(self, concurrency: int, queue: int, per_key: int | None):
        self.concurrency, self.capacity = max(1, concurrency), max(1, concurrency) + max(0, queue)
        self.per_key = per_key or max(1, self.capacity // 2)
        self.pending = self.running = 0
        self.by_key: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(self.concurrency, thread_name_prefix="facerec3d-work")

    @property
    def waiting(self) -> int:
        return self.pending - self.running

    def submit(self, who: str, job: Job, fn, *args) -> Future:
        with self._lock:
            if self.pending >= self.capacity:
                raise ApiError(503, f"the service is busy: its work queue is full ({self.pending} requests); "
                                    "retry later", {"Retry-After": "1"})
            if self.by_key[who] >= self.per_key:
                raise ApiError(429, f"too many requests in progress for key {who!r} (at most {self.per_key}); "
                                    "retry later", {"Retry-After": "1"})
            self.pending += 1
            self.by_key[who] += 1

        def run():
            with self._lock:
                self.running += 1
            try:
                job.check()
                return fn(job, *args)
            finally:
                with self._lock:
                    self.running -= 1
                    self.pending -= 1
                    self.by_key[who] -= 1
                    if not self.by_key[who]:
                        del self.by_key[who]

        return self._pool.submit(run)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


# ---------------------------------------------------------------------------------------------- metrics
BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class Metrics:
    """Request counts by endpoint and status, latency histograms by endpoint (Prometheus text format)."""

    def __init__(self):
        self._lock = threading.Lock()
        self.requests: Counter[tuple[str, str, int]] = Counter()
        self.buckets: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0] * len(BUCKETS))
        self.sums: Counter[tuple[str, str]] = Counter()
        self.counts: Counter[tuple[str, str]] = Counter()

    def observe(self, method: str, endpoint: str, status: int, seconds: float) -> None:
        with self._lock:
            self.requests[method, endpoint, status] += 1
            b = self.buckets[method, endpoint]
            for i, le in enumerate(BUCKETS):
                if seconds <= le:
                    b[i] += 1
            self.sums[method, endpoint] += seconds
            self.counts[method, endpoint] += 1

    def render(self, gauges: dict[str, tuple[str, float]]) -> str:
        out = ["# HELP facerec3d_requests_total HTTP requests answered, by method, endpoint and status.",
               "# TYPE facerec3d_requests_total counter"]
        with self._lock:
            for (m, e, s), n in sorted(self.requests.items()):
                out.append(f'facerec3d_requests_total{{method="{m}",endpoint="{e}",status="{s}"}} {n}')
            out += ["# HELP facerec3d_request_duration_seconds Time to answer a request, by method and endpoint.",
                    "# TYPE facerec3d_request_duration_seconds histogram"]
            for (m, e), b in sorted(self.buckets.items()):
                labels = f'method="{m}",endpoint="{e}"'
                for le, n in zip(BUCKETS, b):
                    out.append(f'facerec3d_request_duration_seconds_bucket{{{labels},le="{le:g}"}} {n}')
                out.append(f'facerec3d_request_duration_seconds_bucket{{{labels},le="+Inf"}} {self.counts[m, e]}')
                out.append(f"facerec3d_request_duration_seconds_sum{{{labels}}} {self.sums[m, e]:.6f}")
                out.append(f"facerec3d_request_duration_seconds_count{{{labels}}} {self.counts[m, e]}")
        for name, (text, value) in gauges.items():
            out += [f"# HELP {name} {text}", f"# TYPE {name} gauge", f"{name} {value:g}"]
        return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------- the gate
def route_of(method: str, path: str) -> tuple[str, str | None]:
    """(endpoint label for metrics, scope needed: a scope name, "any" for any valid key, None for none)."""
    fixed = {("POST", f"{API}/enrol"): "enrol", ("POST", f"{API}/identify"): "query",
             ("POST", f"{API}/verify"): "query", ("GET", f"{API}/subjects"): "admin",
             ("GET", f"{API}/entries"): "admin", ("GET", f"{API}/stats"): "any", ("GET", "/metrics"): "admin"}
    if (method, path) in fixed:
        return path, fixed[method, path]
    if path == f"{API}/health":
        return path, None
    if path.startswith(f"{API}/subjects/"):
        return f"{API}/subjects/{{ident}}", "admin"
    if path.startswith(f"{API}/") or path == "/metrics":
        return "other", "any"
    if path in ("/docs", "/openapi.json", "/redoc", "/docs/oauth2-redirect"):
        return path, None
    return "other", None


def _api_key(headers: dict[bytes, bytes]) -> str | None:
    key = headers.get(b"x-api-key")
    if key is None:
        auth = headers.get(b"authorization", b"")
        if auth[:7].lower() == b"bearer ":
            key = auth[7:]
    return None if key is None else key.decode("latin-1").strip()


class Gate:
    """ASGI middleware before FastAPI: authentication and scopes (before the body is read), the upload size
    limit, and the metrics of every answer."""

    def __init__(self, app, service: "Service"):
        self.app, self.service = app, service

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        endpoint, needed = route_of(scope["method"], scope["path"])
        status = [500]
        started = [False]

        async def send_(message):
            if message["type"] == "http.response.start":
                status[0], started[0] = message["status"], True
            await send(message)

        try:
            refusal = self._check(scope, endpoint, needed)
            if refusal is not None:
                await refusal(scope, receive, send_)
                return
            limit, seen = self.service.settings.max_upload_bytes, [0]

            async def receive_():
                message = await receive()
                if message["type"] == "http.request":
                    seen[0] += len(message.get("body", b""))
                    if seen[0] > limit:
                        raise HTTPException(413, f"the upload is larger than this service's limit of {limit} bytes")
                return message

            try:
                await self.app(scope, receive_, send_)
            except HTTPException as e:  # raised while the body streamed in, outside FastAPI's handlers
                if started[0]:
                    raise
                await _error(e.status_code, e.detail)(scope, receive, send_)
        finally:
            self.service.metrics.observe(scope["method"], endpoint, status[0], time.perf_counter() - t0)

    def _check(self, scope, endpoint: str, needed: str | None):
        headers = dict(scope["headers"])
        if needed is not None:
            key = self.service.keys.authenticate(_api_key(headers))
            writes = endpoint == f"{API}/enrol" or (endpoint.startswith(f"{API}/subjects/") and scope["method"] == "DELETE")
            client = (scope.get("client") or ("?",))[0]
            if key is None:
                if writes:
                    self.service.audit("denied", reason="no valid key", endpoint=endpoint, client=client)
                given = _api_key(headers)
                return _error(401, "an API key is needed (header X-API-Key or Authorization: Bearer)" if not given
                              else "unknown API key", {"WWW-Authenticate": "Bearer"})
            if needed != "any" and needed not in key.scopes:
                if writes:
                    self.service.audit("denied", key=key.name, reason=f"no {needed} scope", endpoint=endpoint,
                                       client=client)
                return _error(403, f"key {key.name!r} has no {needed!r} scope (it has: "
                                   f"{', '.join(sorted(key.scopes))})")
            scope.setdefault("state", {})["api_key"] = key
        length = headers.get(b"content-length")
        if length is not None:
            try:
                n = int(length)
            except ValueError:
                return _error(400, "bad Content-Length header")
            if n > self.service.settings.max_upload_bytes:
                return _error(413, f"the upload ({n} bytes) is larger than this service's limit of "
                                   f"{self.service.settings.max_upload_bytes} bytes")
        return None


# ---------------------------------------------------------------------------------------------- the service
class Service:
    """The live gallery with its keys, limits, work queue, metrics and audit log."""

    def __init__(self, live: LiveGallery, keys: KeyFile, settings: ServiceSettings):
        self.live, self.keys, self.settings = live, keys, settings
        self.queue = WorkQueue(settings.concurrency, settings.queue, settings.per_key)
        self.metrics = Metrics()
        self.uploads: Counter[str] = Counter()  # scans used, by kind: "raw" (preprocessed here), "preprocessed"

    def counted(self, answer: dict) -> dict:
        """An answer whose upload was used, counted by kind (raw scan or preprocessed face)."""
        self.uploads["preprocessed" if answer.get("preprocessed_upload") else "raw"] += 1
        return answer

    def audit(self, action: str, **fields: Any) -> None:
        """An audit record of a refused request (not synced to disk one by one)."""
        self.live.audit.write(action, sync=False, **fields)

    def close(self) -> None:
        self.queue.close()
        self.live.close()

    async def run(self, request: Request, fn, *args) -> Any:
        """fn(job, *args) through the work queue under the request's time limit."""
        limit = self.settings.timeout_s
        asked = request.headers.get("x-request-timeout")
        if asked is not None:
            try:
                limit = min(limit, float(asked))
            except ValueError:
                raise ApiError(400, f"bad X-Request-Timeout header {asked!r} (seconds)") from None
            if not limit > 0:
                raise ApiError(400, "X-Request-Timeout must be positive")
        job = Job(limit)
        future = asyncio.wrap_future(self.queue.submit(request.state.api_key.name, job, fn, *args))
        try:
            return await asyncio.wait_for(asyncio.shield(future), limit)
        except asyncio.TimeoutError:
            if job.abandon():  # the job stops at its next check; nobody waits for its outcome
                future.add_done_callback(lambda f: f.cancelled() or f.exception())
                raise ApiError(504, f"the request took longer than its time limit of {limit:g} s") from None
            return await future  # committing: the answer must say what the store holds

    def who(self, request: Request) -> dict:
        return {"key": request.state.api_key.name, "client": request.client.host if request.client else "?"}


def _label(value: str | None, what: str) -> str:
    if value is None or not _LABEL.match(value):
        raise ApiError(422, f"bad {what} {value!r}: 1-128 letters, digits or . _ - @ + : (no spaces or slashes)")
    return value


def _entry(e: Entry) -> dict:
    return {"id": e.id, "subject": e.subject, "scan_id": e.scan_id, "source": e.source, "bytes": e.nbytes,
            "enrolled_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(e.enrolled_at))}


def _number(x: float) -> float | None:
    return x if math.isfinite(x) else None


MAX_INTRINSICS_BYTES = 64 * 1024  # an intrinsics.json is a few hundred bytes


async def _upload(file: UploadFile, fmt: str | None, intrinsics: str | UploadFile | None) -> Upload:
    """The uploaded scan: its format from `fmt` or the file name's suffix (a label only, never a path); the
    intrinsics as a text field or a file part (`curl -F intrinsics=@intrinsics.json`)."""
    name = Path((file.filename or "upload").replace("\\", "/")).name or "upload"
    suffix = ("." + fmt.lower().lstrip(".")) if fmt else scan_suffix(name)
    if suffix not in SUPPORTED_SUFFIXES:
        raise ApiError(415, f"{name}: unknown scan format {suffix or '(none)'!r}: name the file with one of "
                            f"{', '.join(SUPPORTED_SUFFIXES)} or give the form field 'format'")
    data = await file.read()
    if not data:
        raise ApiError(422, f"{name}: the upload is empty")
    camera = None
    if intrinsics is not None and not isinstance(intrinsics, str):  # a file part
        raw = await intrinsics.read(MAX_INTRINSICS_BYTES + 1)
        if len(raw) > MAX_INTRINSICS_BYTES:
            raise ApiError(413, f"the intrinsics are over {MAX_INTRINSICS_BYTES // 1024} KiB")
        intrinsics = raw.decode("utf-8", errors="replace")
    if intrinsics:
        try:
            camera = json.loads(intrinsics)
        except json.JSONDecodeError as e:
            raise ApiError(422, f"the intrinsics are not JSON ({e})") from None
        if not isinstance(camera, dict):
            raise ApiError(422, "the intrinsics must be a JSON object with fx, fy, cx, cy")
    return Upload(data, suffix, name[:128], camera)


def _work(job: Job, live: LiveGallery, fn, *args):
    """A worker job, its refusals as HTTP errors."""
    try:
        result = live.work(fn, *args)
    except Rejected as e:
        raise ApiError(e.status, e.reason) from None
    job.check()
    return result


def _enrol(job: Job, live: LiveGallery, upload: Upload, subject: str, scan_id: str, content: str, who: dict) -> dict:
    source = f"upload:sha256:{content}"
    old = next((e for e in live.entries if e.source == source), None)
    if old is not None:
        raise ApiError(409, f"{upload.label}: this scan is already enrolled: entry {old.id} of subject {old.subject!r}")
    template, reason, timings, given = _work(job, live, enrol_job, upload, live.max_points, live.config,
                                             live.matcher, subject, scan_id)
    job.commit()
    if template is None:
        live.record_failure(source, reason, {**who, "subject": subject})
        raise ApiError(422, f"failure to enrol: {reason}")
    try:
        entry = live.enrol(template, source, content, who)
    except Conflict as e:
        raise ApiError(409, f"{upload.label}: {e}") from None
    return {**_entry(entry), "gallery_version": live.version, "preprocessed_upload": given, "timings": timings}


def _identify(job: Job, live: LiveGallery, upload: Upload, k: int, cascade: CascadeConfig | None) -> dict:
    probe, timings, given = _work(job, live, probe_job, upload, live.max_points, live.config, live.matcher, cascade)
    t0 = time.perf_counter()
    hits, version, n = live.identify(probe, k, cascade)
    timings["match_ms"] = 1e3 * (time.perf_counter() - t0)
    return {"candidates": [{"rank": r, "entry": e.id, "subject": e.subject, "scan_id": e.scan_id, "score": s}
                           for r, (e, s) in enumerate(hits, start=1)],
            "method": live.matcher.name, "cascade": cascade is not None, "gallery_entries": n,
            "gallery_version": version, "preprocessed_upload": given, "timings": timings}


def _verify(job: Job, live: LiveGallery, upload: Upload, claim: str, threshold: float) -> dict:
    probe, timings, given = _work(job, live, probe_job, upload, live.max_points, live.config, live.matcher, None)
    t0 = time.perf_counter()
    score, version = live.verify(probe, claim)
    timings["match_ms"] = 1e3 * (time.perf_counter() - t0)
    return {"claim": claim, "accepted": bool(score >= threshold), "score": _number(score), "threshold": threshold,
            "method": live.matcher.name, "gallery_version": version, "preprocessed_upload": given, "timings": timings}


def _remove(job: Job, live: LiveGallery, ident: str, who: dict) -> dict:
    job.commit()
    removed = live.remove(ident, who)
    return {"removed": [e.id for e in removed], "subjects": sorted({str(e.subject) for e in removed}),
            "gallery_version": live.version}


def create_app(service: Service):
    """The ASGI application of a service: the FastAPI app (OpenAPI at /docs) behind the `Gate`."""
    live = service.live
    app = FastAPI(title="facerec3d gallery service", version="1",
                  description="Enrol 3D face scans into a gallery, identify and verify probes against it. "
                              "Give the API key in the X-API-Key header (or Authorization: Bearer).")
    app.state.service = service

    @app.exception_handler(ApiError)
    async def _api_error(request, e: ApiError):
        return _error(e.status, e.reason, e.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request, e: StarletteHTTPException):
        return _error(e.status_code, e.detail, getattr(e, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request, e: RequestValidationError):
        parts = []
        for err in e.errors()[:5]:
            where = ".".join(str(p) for p in err.get("loc", ())[1:]) or "request"
            parts.append(f"{where}: {err.get('msg', 'invalid')}")
        return _error(422, "; ".join(parts) or "invalid request")

    @app.exception_handler(Conflict)
    async def _conflict(request, e):
        return _error(409, str(e))

    @app.exception_handler(NotFound)
    async def _not_found(request, e):
        return _error(404, str(e))

    @app.exception_handler(FaceRec3DError)
    async def _facerec3d_error(request, e):
        return _error(409 if isinstance(e, GalleryError) else 422, str(e))

    @app.exception_handler(Exception)
    async def _internal(request, e):
        traceback.print_exception(e, file=sys.stderr)
        return _error(500, f"internal error ({type(e).__name__}); see the service's log")

    scan_doc = ("The scan file: any format facerec3d reads (" + ", ".join(SUPPORTED_SUFFIXES) + "), named by its "
                "suffix; or a face already preprocessed by facerec3d with this service's settings (.npz recording "
                "its preprocess_fingerprint, see /v1/stats), used without preprocessing it again.")

    @app.post(f"{API}/enrol", status_code=201, summary="Enrol a scan for a subject (scope enrol)")
    async def enrol(request: Request, scan: UploadFile = File(..., description=scan_doc),
                    subject: str = Form(..., description="Subject id"),
                    scan_id: str | None = Form(None, description="Scan id (default: the file name's stem)"),
                    format: str | None = Form(None, description="Format suffix when the file name has none, e.g. abs.gz"),
                    intrinsics: str | UploadFile | None = Form(None, description="Depth frames: camera "
                                                               "intrinsics JSON, as text or a file")):
        """The new entry (201), or: 409 already enrolled (the same bytes), 422 a failure to enrol with its reason
        (recorded in the gallery's failures to enrol), 413 / 415 outside the limits. Answered only after the
        entry is committed to the store."""
        subject = _label(subject, "subject")
        upload = await _upload(scan, format, intrinsics)
        scan_id = _label(scan_id, "scan_id") if scan_id is not None else \
            (_LABEL.match(scan_stem(upload.label)) and scan_stem(upload.label)) or "upload"
        content = hashlib.sha256(upload.data).hexdigest()  # the store's content hash: a scan enrolled twice is found
        return JSONResponse(service.counted(await service.run(request, _enrol, live, upload, subject, scan_id,
                                                              content, service.who(request))), 201)

    @app.post(f"{API}/identify", summary="The best-matching enrolled entries for a probe (scope query)")
    async def identify(request: Request, probe: UploadFile = File(..., description=scan_doc),
                       k: int = Form(5, ge=1, le=1000, description="Candidates to list"),
                       cascade: bool = Form(False, description="ICP: depth screen, then full ICP on a shortlist"),
                       shortlist: int = Form(20, ge=1, le=100000, description="Cascade shortlist length"),
                       format: str | None = Form(None), intrinsics: str | UploadFile | None = Form(None)):
        """Candidates best first (rank, entry, subject, scan_id, score: higher is more similar). Under the
        cascade, faces off the shortlist are not listed."""
        config = None
        if cascade:
            if not live.cascadable:
                raise ApiError(422, f"the cascade works with the icp method, not {live.matcher.name!r}")
            config = CascadeConfig(shortlist=shortlist)
        if not live.entries:
            raise ApiError(409, "the gallery is empty")
        upload = await _upload(probe, format, intrinsics)
        return service.counted(await service.run(request, _identify, live, upload, k, config))

    @app.post(f"{API}/verify", summary="Is a probe the claimed subject? (scope query)")
    async def verify(request: Request, probe: UploadFile = File(..., description=scan_doc),
                     claim: str = Form(..., description="Claimed subject id"),
                     threshold: float | None = Form(None, description="Accept scores >= this (default: the method's)"),
                     format: str | None = Form(None), intrinsics: str | UploadFile | None = Form(None)):
        """The decision, the score and the threshold used; 404 when the claimed subject is not enrolled."""
        try:
            threshold = live.threshold(threshold)
        except GalleryError as e:
            raise ApiError(422, str(e)) from None
        if not math.isfinite(threshold):
            raise ApiError(422, "the threshold must be a finite number")
        if not any(e.subject == claim for e in live.entries):
            raise ApiError(404, f"subject {claim!r} is not enrolled")
        upload = await _upload(probe, format, intrinsics)
        return service.counted(await service.run(request, _verify, live, upload, claim, threshold))

    @app.get(f"{API}/subjects", summary="Enrolled subjects and their entry counts (scope admin)")
    async def subjects():
        counts = Counter(str(e.subject) for e in live.entries)
        return {"subjects": [{"subject": s, "entries": n} for s, n in sorted(counts.items())],
                "gallery_version": live.version}

    @app.get(f"{API}/subjects/{{ident}}", summary="One subject's entries (scope admin)")
    async def subject(ident: str):
        found = [_entry(e) for e in sorted(live.entries, key=lambda e: e.id) if e.subject == ident]
        if not found:
            raise ApiError(404, f"subject {ident!r} is not enrolled")
        return {"subject": ident, "entries": found}

    @app.delete(f"{API}/subjects/{{ident}}", summary="Remove a subject's entries, or else a scan's (scope admin)")
    async def remove(request: Request, ident: str):
        """Removes subject IDENT's entries, or else the entries of scan id IDENT (as `facerec3d gallery remove`);
        404 when neither is enrolled. Answered after the removal is committed."""
        return await service.run(request, _remove, live, ident, service.who(request))

    @app.get(f"{API}/entries", summary="Every entry and the failures to enrol (scope admin)")
    async def entries():
        failures = await asyncio.to_thread(live.failures)
        return {"entries": [_entry(e) for e in sorted(live.entries, key=lambda e: e.id)],
                "failures": [{"source": s, "reason": r} for s, r in failures], "gallery_version": live.version}

    @app.get(f"{API}/stats", summary="Gallery counts and settings, queue and limits (any valid key)")
    async def stats():
        st = await asyncio.to_thread(live.stats)
        q = service.queue
        return {**st, "queue": {"running": q.running, "waiting": q.waiting, "concurrency": q.concurrency,
                                "capacity": q.capacity, "per_key": q.per_key},
                "uploads": {"raw": service.uploads["raw"], "preprocessed": service.uploads["preprocessed"]},
                "limits": {**asdict(service.settings), "max_points": live.max_points}, "degraded": live.degraded}

    @app.get(f"{API}/health", summary="Liveness (no key needed)")
    async def health():
        return {"status": "degraded" if live.degraded else "ok", "entries": len(live.entries),
                "gallery_version": live.version}

    @app.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (scope admin)")
    async def metrics():
        q = service.queue
        text = service.metrics.render({
            "facerec3d_queue_length": ("Requests waiting for a worker.", q.waiting),
            "facerec3d_requests_in_progress": ("Requests being worked on.", q.running),
            "facerec3d_gallery_entries": ("Entries in the live gallery.", len(live.entries)),
            "facerec3d_gallery_version": ("Changes applied to the live gallery since start (+1).", live.version),
            "facerec3d_cpu_seconds": ("CPU seconds used by the service and its local worker processes.",
                                      live.cpu_seconds())})
        return PlainTextResponse(text, media_type="text/plain; version=0.0.4")

    return Gate(app, service)


def serve(gallery: str | Path, keys: str | Path, host: str = "127.0.0.1", port: int = 8000, jobs: int | None = None,
          scheduler: str | None = None, method: str | None = None, options: dict | None = None, config=None,
          settings: ServiceSettings | None = None, max_points: int = 5_000_000, audit: str | Path | None = None,
          ssl_certfile: str | None = None, ssl_keyfile: str | None = None, echo=print) -> None:
    """Load the gallery into `jobs` worker processes (or a Dask cluster's workers) and answer HTTP on host:port
    until interrupted (SIGINT / SIGTERM: in-flight requests finish, the workers stop)."""
    import uvicorn

    from facerec3d.preprocess.batch import one_thread_per_process
    from facerec3d.server.live import AuditLog

    settings = settings or ServiceSettings()
    key_file = KeyFile(keys)  # refuse to start without keys
    one_thread_per_process()  # the service's own BLAS: one thread (work runs on the workers)
    live = LiveGallery(gallery, jobs, scheduler, method, options, config,
                       AuditLog(audit if audit is not None else Path(str(gallery) + ".audit.jsonl")), max_points)
    service = Service(live, key_file, settings)
    try:
        server = uvicorn.Server(uvicorn.Config(create_app(service), host=host, port=port, log_level="warning",
                                               access_log=False, ssl_certfile=ssl_certfile, ssl_keyfile=ssl_keyfile,
                                               timeout_graceful_shutdown=max(5, int(settings.timeout_s))))
        scheme = "https" if ssl_certfile else "http"
        echo(f"facerec3d service: {gallery} ({len(live.entries)} entries, method {live.matcher.name}, "
             f"{live.engine.workers} worker{'s' * (live.engine.workers != 1)}) on {scheme}://{host}:{port} "
             f"(API docs: /docs)")
        server.run()
    finally:
        service.close()
