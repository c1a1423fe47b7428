"""The HTTP service: FastAPI on uvicorn over a `LiveGallery` (what `facerec3d serve` runs).

Every request under /v1 (but /v1/health) and /metrics carries an API key (`X-API-Key: KEY` or
`Authorization: Bearer KEY`), checked before the body is read: 401 without a known key (503 while the key file
cannot be read), 403 outside its scope. Uploads larger than the limit are refused (413) from Content-Length or
while they stream in. Scan work goes through two bounded lanes, one for identifications and verifications (`concurrency`, `queue`) and one
for enrolments and removals (`write_concurrency`, `write_queue`), so that neither starves the other: in each,
at most so many requests are worked on, so many more wait, and the rest are answered 503 (lane full) or 429
(one key holding more than `per_key` places) with Retry-After — decided from the headers, before the body is
read. An admitted upload is spooled by the form parser (memory up to 1 MiB, then a temporary file) and read
into memory only when its work starts. Refused writes (and failed authentication, aggregated) are audited.
A worker process that dies is replaced within seconds (503 meanwhile, and /v1/health says "degraded").
Each request has a time limit (`timeout_s`, or less with an `X-Request-Timeout: SECONDS` header): past it
the answer is 504 and work not yet started is dropped; an enrolment that has begun committing is waited
for, so an answer never contradicts the store. Errors are one-line JSON: {"error": reason, "status": code}.

The verification threshold is calibrated on scans sent for it (`POST /v1/calibrate`, admin: `facerec3d enroll
--server` sends those it enrolled, since the service keeps no scan, only templates), scored against the live
gallery on a snapshot, each without the entry enrolled from the same bytes, and recorded in the store before the
answer, as `facerec3d gallery G calibrate` does for a store file (evaluation.calibrate).

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
import socket
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

from facerec3d.errors import FaceRec3DError, ScanFormatError
from facerec3d.evaluation.calibrate import MAX_SCANS, OWN_SCANS, threshold_record
from facerec3d.gallery.cascade import CascadeConfig
from facerec3d.gallery.store import Entry, GalleryError, ServeLock
from facerec3d.io import SUPPORTED_SUFFIXES, Intrinsics, scan_stem, scan_suffix
from facerec3d.io.common import MAX_POINTS
from facerec3d.server.jobs import Mismatch, Rejected, Upload, enrol_job, probe_job
from facerec3d.server.keys import KeyFile
from facerec3d.server.live import Conflict, LiveGallery, NotFound, WorkerLost

API = "/v1"
_LABEL = re.compile(r"[\w.@+:-]{1,128}")  # subject and scan ids (fullmatch): no spaces, slashes or control characters


@dataclass
class ServiceSettings:
    """Limits of a service (see `facerec3d serve --help`)."""

    concurrency: int = 4  # identifications and verifications worked on at once
    queue: int = 32  # of those, waiting beyond the ones worked on; more are answered 503
    per_key: int | None = None  # requests queued or running for one key, per lane; more are 429 (default: half
    #                             the lane's places)
    timeout_s: float = 60.0  # time limit per request
    max_upload_bytes: int = 64 * 2**20  # largest request body
    write_concurrency: int = 2  # enrolments and removals worked on at once: their own lane, so that queries
    #                             cannot starve them (and the other way round)
    write_queue: int = 16  # of those, waiting beyond the ones worked on; more are answered 503
    failed_auth_interval_s: float = 60.0  # audit failed authentication once per client and reason in this time;
    #                                       the repeats are counted and written with the next line


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


class Place:
    """A request's place in a lane, held from admission (before its body is read) until its work is done."""

    def __init__(self, lane: "Lane", who: str):
        self.lane, self.who = lane, who
        self.handed = self.released = False


class Lane:
    """At most `concurrency` jobs at once on threads (which hand scans to the engine's workers), `queue` more
    admitted and waiting; beyond that 503, and 429 for a key holding more than `per_key` places. A place is
    taken when the request arrives, before its upload is read, so a refused request costs no memory."""

    def __init__(self, name: str, concurrency: int, queue: int, per_key: int | None):
        self.name = name
        self.concurrency, self.capacity = max(1, concurrency), max(1, concurrency) + max(0, queue)
        self.per_key = per_key or max(1, self.capacity // 2)
        self.pending = self.running = 0
        self.by_key: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(self.concurrency, thread_name_prefix=f"facerec3d-{name}")

    @property
    def waiting(self) -> int:
        return self.pending - self.running

    def admit(self, who: str) -> Place:
        """A place for key `who`, or ApiError 503 (the lane is full) / 429 (the key holds too many places)."""
        with self._lock:
            if self.pending >= self.capacity:
                raise ApiError(503, f"the service is busy: its {self.name} queue is full ({self.pending} requests); "
                                    "retry later", {"Retry-After": "1"})
            if self.by_key[who] >= self.per_key:
                raise ApiError(429, f"too many {self.name} requests in progress for key {who!r} (at most "
                                    f"{self.per_key}); retry later", {"Retry-After": "1"})
            self.pending += 1
            self.by_key[who] += 1
        return Place(self, who)

    def release(self, place: Place) -> None:
        """Give a place back (once; later calls do nothing)."""
        with self._lock:
            if place.released:
                return
            place.released = True
            self.pending -= 1
            self.by_key[place.who] -= 1
            if not self.by_key[place.who]:
                del self.by_key[place.who]

    def submit(self, place: Place, job: Job, fn, *args) -> Future:
        """fn(job, *args) on a thread of the lane; the place is given back when it is done."""
        place.handed = True

        def run():
            with self._lock:
                self.running += 1
            try:
                job.check()
                return fn(job, *args)
            finally:
                with self._lock:
                    self.running -= 1
                self.release(place)

        try:
            return self._pool.submit(run)
        except BaseException:
            self.release(place)
            raise

    def stats(self) -> dict:
        return {"running": self.running, "waiting": self.waiting, "concurrency": self.concurrency,
                "capacity": self.capacity, "per_key": self.per_key}

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


#: the lane of each endpoint that does scan work or changes the gallery, by (method, endpoint label)
LANES = {("POST", f"{API}/identify"): "query", ("POST", f"{API}/verify"): "query",
         ("POST", f"{API}/enrol"): "write", ("DELETE", f"{API}/subjects/{{ident}}"): "write",
         ("DELETE", f"{API}/entries/{{entry}}"): "write", ("POST", f"{API}/calibrate"): "write"}


class FailedAuthLog:
    """Audit lines for failed authentication, at most one per (client, reason) every `interval_s`: the repeats
    in between are counted and written with the next line (`repeated`), or on close. At most `clients` pairs
    are followed; beyond them, requests are counted under client "*"."""

    def __init__(self, write, interval_s: float, clients: int = 1024):
        self._write, self.interval_s, self.clients = write, interval_s, clients
        self._seen: dict[tuple[str, str], list] = {}  # (client, reason) -> [time of the last line, repeats since]
        self._lock = threading.Lock()

    def __call__(self, client: str, reason: str, **fields: Any) -> None:
        now = time.monotonic()
        with self._lock:
            if (client, reason) not in self._seen and len(self._seen) >= self.clients:
                client = "*"
            seen = self._seen.get((client, reason))
            if seen is not None and now - seen[0] < self.interval_s:
                seen[1] += 1
                return
            repeated = seen[1] if seen is not None else 0
            self._seen[client, reason] = [now, 0]
        self._write("denied", **fields, reason=reason, client=client, **({"repeated": repeated} if repeated else {}))

    def close(self) -> None:
        """Write the repeats not written yet."""
        with self._lock:
            left = [(c, r, n) for (c, r), (_, n) in self._seen.items() if n]
            self._seen.clear()
        for client, reason, n in left:
            self._write("denied", reason=reason, client=client, repeated=n)


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
             ("GET", f"{API}/entries"): "admin", ("GET", f"{API}/stats"): "any", ("GET", "/metrics"): "admin",
             ("POST", f"{API}/calibrate"): "admin"}
    if (method, path) in fixed:
        return path, fixed[method, path]
    if path == f"{API}/health":
        return path, None
    if path.startswith(f"{API}/subjects/"):
        return f"{API}/subjects/{{ident}}", "admin"
    if path.startswith(f"{API}/entries/"):
        return f"{API}/entries/{{entry}}", "admin"
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
    """ASGI middleware before FastAPI: authentication and scopes, the upload size limit and admission to the
    work queue's lanes, all before the body is read; the metrics of every answer; and the audit lines of every
    refused write (failed authentication aggregated, see `FailedAuthLog`)."""

    def __init__(self, app, service: "Service"):
        self.app, self.service = app, service

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        method = scope["method"]
        endpoint, needed = route_of(method, scope["path"])
        status, started, body = [500], [False], bytearray()

        async def send_(message):
            if message["type"] == "http.response.start":
                status[0], started[0] = message["status"], True
            elif message["type"] == "http.response.body" and status[0] >= 400 and len(body) < 2048:
                body.extend(message.get("body", b"")[:2048])
            await send(message)

        place = None
        try:
            refusal, place = self._check(scope, endpoint, needed)
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
            if place is not None and not place.handed:
                place.lane.release(place)
            self.service.metrics.observe(method, endpoint, status[0], time.perf_counter() - t0)
            if LANES.get((method, endpoint)) == "write" and started[0] and status[0] >= 400 \
                    and status[0] not in (401, 403):  # (401 and 403 are audited as "denied", see _check)
                key = scope.get("state", {}).get("api_key")
                self.service.audit("refused", status=status[0], reason=_reason(bytes(body)), endpoint=endpoint,
                                   path=scope["path"], key=key.name if key else None, client=_client(scope))

    def _check(self, scope, endpoint: str, needed: str | None):
        """(an error answer or None, the request's place in its lane or None)."""
        headers = dict(scope["headers"])
        lane = LANES.get((scope["method"], endpoint))
        key = None
        if needed is not None:
            key = self.service.keys.authenticate(_api_key(headers))
            audited = lane == "write"
            if key is None and self.service.keys.unreadable is not None:  # the log names the file and the reason
                return _error(503, "the service cannot read its API keys (see its log); retry later",
                              {"Retry-After": "5"}), None
            if key is None:
                given = _api_key(headers)
                if audited:
                    self.service.failed_auth(_client(scope), "unknown API key" if given else "no API key",
                                             endpoint=endpoint)
                return _error(401, "an API key is needed (header X-API-Key or Authorization: Bearer)" if not given
                              else "unknown API key", {"WWW-Authenticate": "Bearer"}), None
            if needed != "any" and needed not in key.scopes:
                if audited:
                    self.service.failed_auth(_client(scope), f"no {needed} scope", key=key.name, endpoint=endpoint)
                return _error(403, f"key {key.name!r} has no {needed!r} scope (it has: "
                                   f"{', '.join(sorted(key.scopes))})"), None
            scope.setdefault("state", {})["api_key"] = key
        length = headers.get(b"content-length")
        if length is not None:
            try:
                n = int(length)
            except ValueError:
                return _error(400, "bad Content-Length header"), None
            if n > self.service.settings.max_upload_bytes:
                return _error(413, f"the upload ({n} bytes) is larger than this service's limit of "
                                   f"{self.service.settings.max_upload_bytes} bytes"), None
        if lane is not None and key is not None:
            try:
                place = self.service.lanes[lane].admit(key.name)
            except ApiError as e:
                return _error(e.status, e.reason, e.headers), None
            scope["state"]["place"] = place
            return None, place
        return None, None


def _client(scope) -> str:
    return (scope.get("client") or ("?",))[0]


def _reason(body: bytes) -> str:
    """The reason of a one-line JSON error answer (or its start)."""
    try:
        return str(json.loads(body)["error"])
    except (ValueError, KeyError, TypeError):
        return body[:200].decode("utf-8", "replace")


# ---------------------------------------------------------------------------------------------- the service
class Service:
    """The live gallery with its keys, limits, work queue lanes, metrics and audit log."""

    def __init__(self, live: LiveGallery, keys: KeyFile, settings: ServiceSettings):
        self.live, self.keys, self.settings = live, keys, settings
        self.lanes = {"query": Lane("query", settings.concurrency, settings.queue, settings.per_key),
                      "write": Lane("write", settings.write_concurrency, settings.write_queue, settings.per_key)}
        self.metrics = Metrics()
        self.uploads: Counter[str] = Counter()  # scans used, by kind: "raw" (preprocessed here), "preprocessed"
        self.failed_auth = FailedAuthLog(self.audit, settings.failed_auth_interval_s)

    def counted(self, answer: dict) -> dict:
        """An answer whose upload was used, counted by kind (raw scan or preprocessed face)."""
        self.uploads["preprocessed" if answer.get("preprocessed_upload") else "raw"] += 1
        return answer

    def audit(self, action: str, **fields: Any) -> None:
        """An audit record of a refused request (not synced to disk one by one)."""
        self.live.audit.write(action, sync=False, **fields)

    def close(self) -> None:
        for lane in self.lanes.values():
            lane.close()
        self.failed_auth.close()
        self.live.close()

    async def run(self, request: Request, fn, *args) -> Any:
        """fn(job, *args) on the request's lane (its place was taken by the `Gate`) under its time limit."""
        limit = self.settings.timeout_s
        asked = request.headers.get("x-request-timeout")
        if asked is not None:
            try:
                limit = min(limit, float(asked))
            except ValueError:
                raise ApiError(400, f"bad X-Request-Timeout header {asked[:40]!r} (seconds)") from None
            if not limit > 0:
                raise ApiError(400, "X-Request-Timeout must be positive")
        job = Job(limit)
        place: Place = request.state.place
        future = asyncio.wrap_future(place.lane.submit(place, job, fn, *args))
        try:
            return await asyncio.wait_for(asyncio.shield(future), limit)
        except asyncio.TimeoutError:
            if job.abandon():  # the job stops at its next check; nobody waits for its outcome
                future.add_done_callback(lambda f: f.cancelled() or f.exception())
                raise ApiError(504, f"the request took longer than its time limit of {limit:g} s") from None
            return await future  # committing: the answer must say what the store holds

    def who(self, request: Request) -> dict:
        return {"key": request.state.api_key.name, "client": request.client.host if request.client else "?"}


def _is_label(value: str | None) -> bool:
    """Whether `value` can be a subject or scan id (`_LABEL`; not "." or "..", which URL paths lose)."""
    return value is not None and bool(_LABEL.fullmatch(value)) and value not in (".", "..")


def _label(value: str | None, what: str) -> str:
    if not _is_label(value):
        raise ApiError(422, f"bad {what} {value!r}: 1-128 letters, digits or . _ - @ + : (no spaces, slashes or "
                            "line breaks; not . or ..)"[:300])
    return value


def _entry(e: Entry) -> dict:
    return {"id": e.id, "subject": e.subject, "scan_id": e.scan_id, "source": e.source, "bytes": e.nbytes,
            "enrolled_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(e.enrolled_at))}


def _number(x: float) -> float | None:
    return x if math.isfinite(x) else None


MAX_INTRINSICS_CHARS = 4096  # a camera's intrinsics are a few numbers


@dataclass
class Received:
    """An upload as the request received it: spooled by the form parser (in memory up to 1 MiB, then in a
    temporary file), read only when its job starts, so that requests waiting in the queue hold no copy."""

    file: UploadFile
    suffix: str
    label: str
    intrinsics: dict | None

    def read(self) -> Upload:
        """The upload's bytes (`Upload`); ApiError 422 when it is empty."""
        self.file.file.seek(0)
        data = self.file.file.read()
        if not data:
            raise ApiError(422, f"{self.label}: the upload is empty")
        return Upload(data, self.suffix, self.label, self.intrinsics)


def _intrinsics(text: str) -> dict:
    """Camera intrinsics from the form field's JSON; ApiError 422 with the reason when they cannot be used."""
    if len(text) > MAX_INTRINSICS_CHARS:
        raise ApiError(422, f"the intrinsics are longer than {MAX_INTRINSICS_CHARS} characters")
    try:
        camera = json.loads(text)
    except json.JSONDecodeError as e:
        raise ApiError(422, f"the intrinsics are not JSON ({e})") from None
    except (ValueError, RecursionError) as e:  # an integer of thousands of digits, nesting too deep
        raise ApiError(422, f"the intrinsics are not usable JSON ({type(e).__name__})") from None
    try:
        Intrinsics.from_dict(camera, "intrinsics")
    except ScanFormatError as e:
        raise ApiError(422, str(e)) from None
    return camera


def _upload(file: UploadFile, fmt: str | None, intrinsics: str | UploadFile | None) -> Received:
    """The uploaded scan: its format from `fmt` or the file name's suffix (a label only, never a path); the
    intrinsics as a text field or a file part (`curl -F intrinsics=@intrinsics.json`)."""
    name = Path((file.filename or "upload").replace("\\", "/")).name[:128] or "upload"
    suffix = ("." + fmt.lower().lstrip(".")) if fmt else scan_suffix(name)
    if suffix not in SUPPORTED_SUFFIXES:
        raise ApiError(415, f"{name}: unknown scan format {suffix[:20] or '(none)'!r}: name the file with one of "
                            f"{', '.join(SUPPORTED_SUFFIXES)} or give the form field 'format'")
    intrinsics = _part_text(intrinsics)
    return Received(file, suffix, name, _intrinsics(intrinsics) if intrinsics else None)


def _part_text(part: str | UploadFile | None) -> str | None:
    """An intrinsics form part as text: a text field as it is, a file part read no further than a field holds."""
    if part is None or isinstance(part, str):
        return part
    return part.file.read(MAX_INTRINSICS_CHARS + 1).decode("utf-8", errors="replace")


async def _once(request: Request, *several: str) -> None:
    """ApiError 422 naming a form field (or file part) given more than once, but for the fields `several` that take
    one value per scan: the form parser keeps only the last of a repeated field, so `-F subject=a -F subject=b`
    enrolled b, and of two `scan` parts the first was dropped unsaid. Called first, before anything is done."""
    counts = Counter(name for name, _ in (await request.form()).multi_items())
    repeated = [name for name, n in counts.items() if n > 1 and name not in several]
    if repeated:
        raise ApiError(422, f"form field {repeated[0][:40]!r} is given {counts[repeated[0]]} times: give it once")


def _work(job: Job, live: LiveGallery, fn, *args):
    """A worker job, its refusals as HTTP errors."""
    try:
        result = live.work(fn, *args)
    except Rejected as e:
        raise ApiError(e.status, e.reason) from None
    job.check()
    return result


def _enrol(job: Job, live: LiveGallery, received: Received, subject: str, scan_id: str | None, who: dict) -> dict:
    upload = received.read()
    content = hashlib.sha256(upload.data).hexdigest()  # the store's content hash: a scan enrolled twice is found
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


def _identify(job: Job, live: LiveGallery, received: Received, k: int, cascade: CascadeConfig | None) -> dict:
    upload = received.read()
    probe, timings, given = _work(job, live, probe_job, upload, live.max_points, live.config, live.matcher, cascade)
    t0 = time.perf_counter()
    hits, version, n = live.identify(probe, k, cascade)
    timings["match_ms"] = 1e3 * (time.perf_counter() - t0)
    return {"candidates": [{"rank": r, "entry": e.id, "subject": e.subject, "scan_id": e.scan_id, "score": s}
                           for r, (e, s) in enumerate(hits, start=1)],
            "method": live.matcher.name, "cascade": cascade is not None, "gallery_entries": n,
            "gallery_version": version, "preprocessed_upload": given, "timings": timings}


def _verify(job: Job, live: LiveGallery, received: Received, claim: str, threshold: float,
            expected_fmr: float | None = None) -> dict:
    """The answer of /v1/verify; `expected_fmr` (the gallery's threshold calibrated on too few impostor pairs:
    `evaluation.calibrate.too_few_pairs`) is added when given."""
    upload = received.read()
    probe, timings, given = _work(job, live, probe_job, upload, live.max_points, live.config, live.matcher, None)
    t0 = time.perf_counter()
    score, version = live.verify(probe, claim)
    timings["match_ms"] = 1e3 * (time.perf_counter() - t0)
    return {"claim": claim, "accepted": bool(score >= threshold), "score": _number(score), "threshold": threshold,
            **({"expected_fmr": expected_fmr} if expected_fmr is not None else {}),
            "method": live.matcher.name, "gallery_version": version, "preprocessed_upload": given, "timings": timings}


def _cameras(intrinsics: list[str | UploadFile] | None, n: int) -> list[str | None]:
    """Each of `n` calibration scans' intrinsics (JSON text or None), from text fields or file parts: none given,
    one for all, or one per scan ("null" for a scan without); ApiError 422 for another count."""
    given = [None if text.strip() in ("", "null") else text for text in map(_part_text, intrinsics or [])]
    if len(given) > 1 and len(given) != n:
        raise ApiError(422, f"{len(given)} intrinsics for {n} scans: give one for all of them, or one per scan "
                            "('null' for a scan without)")
    return given if len(given) > 1 else (given or [None]) * n


def _calibration_probe(job: Job, live: LiveGallery, received: Received) -> tuple[Any, str | None, str]:
    """(a calibration scan prepared as a probe, or None and the reason it cannot be used; the SHA-256 of its
    bytes, which its own entry records). A face preprocessed with other settings refuses the whole request."""
    job.check()
    upload = received.read()
    content = hashlib.sha256(upload.data).hexdigest()
    try:
        probe, _, _ = live.work(probe_job, upload, live.max_points, live.config, live.matcher, None)
    except Mismatch as e:  # the client's settings, not the scan
        raise ApiError(e.status, e.reason) from None
    except Rejected as e:  # unreadable, no face, too large: a scan that fails, as in a local calibration
        return None, e.reason, content
    return probe, None, content


def _calibrate(job: Job, live: LiveGallery, received: list[Received], subjects: list[str], fmr: float | None,
               own: bool, who: dict) -> dict:
    """Prepare the scans on the workers (as many at once as there are workers), score them against the gallery,
    then commit the threshold's record: answered only once it is in the store."""
    pool = ThreadPoolExecutor(live.engine.workers, thread_name_prefix="facerec3d-calibrate")
    try:
        prepared = list(pool.map(lambda r: _calibration_probe(job, live, r), received))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    kept = [(probe, subject, content) for (probe, _, content), subject in zip(prepared, subjects) if probe is not None]
    if not kept:
        raise ApiError(422, f"none of the {len(received)} calibration scans could be used; {prepared[0][1]}")
    probes, kept_subjects, contents = map(list, zip(*kept))
    genuine, impostor, entries = live.calibration_scores(probes, kept_subjects, contents, job.check)
    try:
        record = threshold_record(genuine, impostor, fmr, scans=len(received), failed=len(received) - len(kept),
                                  data=OWN_SCANS if own else "calibration scans", entries=entries)
    except ValueError as e:
        raise ApiError(422, str(e)) from None
    job.commit()
    live.record_threshold(record, who)
    return {"threshold": record, "gallery_version": live.version}


def _remove(job: Job, live: LiveGallery, ident: str | None, who: dict, entry: int | None = None) -> dict:
    job.commit()
    removed = live.remove(ident, who, entry=entry)
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

    @app.exception_handler(WorkerLost)
    async def _worker_lost(request, e):
        return _error(503, str(e), {"Retry-After": "2"})

    @app.exception_handler(FaceRec3DError)
    async def _facerec3d_error(request, e):
        if isinstance(e, GalleryError) and str(live.path) in str(e):  # the store failed: its path stays in the log
            print(f"error: {e}", file=sys.stderr, flush=True)
            return _error(503, "the gallery store failed to read or write (see the service's log); retry later",
                          {"Retry-After": "5"})
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
        await _once(request)
        subject = _label(subject, "subject")
        upload = _upload(scan, format, intrinsics)
        scan_id = _label(scan_id, "scan_id") if scan_id is not None else \
            (scan_stem(upload.label) if _is_label(scan_stem(upload.label)) else "upload")
        return JSONResponse(service.counted(await service.run(request, _enrol, live, upload, subject, scan_id,
                                                              service.who(request))), 201)

    @app.post(f"{API}/identify", summary="The best-matching enrolled entries for a probe (scope query)")
    async def identify(request: Request, probe: UploadFile = File(..., description=scan_doc),
                       k: int = Form(5, ge=1, le=1000, description="Candidates to list"),
                       cascade: bool = Form(False, description="ICP: a screen, then full ICP on a shortlist"),
                       shortlist: int = Form(20, ge=1, le=100000, description="Cascade shortlist length"),
                       screen: str = Form("depth", pattern="^(depth|embedding)$",
                                          description="Cascade screen: depth descriptor or learned embedding"),
                       format: str | None = Form(None), intrinsics: str | UploadFile | None = Form(None)):
        """Candidates best first (rank, entry, subject, scan_id, score: higher is more similar). Under the
        cascade, faces off the shortlist are not listed."""
        await _once(request)
        config = None
        if cascade:
            if not live.cascadable:
                raise ApiError(422, f"the cascade works with the icp method, not {live.matcher.name!r}")
            config = CascadeConfig(shortlist=shortlist, screen=screen)
        if not live.entries:
            raise ApiError(409, "the gallery is empty")
        upload = _upload(probe, format, intrinsics)
        return service.counted(await service.run(request, _identify, live, upload, k, config))

    @app.post(f"{API}/verify", summary="Is a probe the claimed subject? (scope query)")
    async def verify(request: Request, probe: UploadFile = File(..., description=scan_doc),
                     claim: str = Form(..., description="Claimed subject id"),
                     threshold: float | None = Form(None, description="Accept scores >= this (default: the "
                                                                      "gallery's calibrated one, else the method's)"),
                     format: str | None = Form(None), intrinsics: str | UploadFile | None = Form(None)):
        """The decision, the score and the threshold used; 404 when the claimed subject is not enrolled."""
        await _once(request)
        try:
            threshold, expected = (float(threshold), None) if threshold is not None else live.default_threshold()
        except GalleryError as e:
            raise ApiError(422, str(e)) from None
        if not math.isfinite(threshold):
            raise ApiError(422, "the threshold must be a finite number")
        if not any(e.subject == claim for e in live.entries):
            raise ApiError(404, f"subject {claim!r} is not enrolled")
        upload = _upload(probe, format, intrinsics)
        return service.counted(await service.run(request, _verify, live, upload, claim, threshold, expected))

    @app.post(f"{API}/calibrate", summary="Calibrate the verification threshold on labelled scans (scope admin)")
    async def calibrate(request: Request,
                        scan: list[UploadFile] = File(..., description=f"The scans (at most {MAX_SCANS}), read as "
                                                      "for enrol: e.g. those the gallery was enrolled from"),
                        subject: list[str] = Form(..., description="Each scan's subject id, in the same order"),
                        intrinsics: list[str | UploadFile] | None = Form(None, description="Depth frames: camera "
                                                                          "intrinsics JSON, as text or files, one for "
                                                                          "all the scans or one per scan ('null' for "
                                                                          "a scan without)"),
                        fmr: float = Form(0.01, gt=0, le=1, description="False-match rate the threshold keeps"),
                        eer: bool = Form(False, description="The threshold at the equal error rate instead "
                                                            "(needs two scans of some subjects)"),
                        own: bool = Form(False, description="The scans are the ones the gallery was enrolled from: "
                                                            "the record says so, and a later `facerec3d enroll "
                                                            "--server` calibrates again (others it keeps)")):
        """Scores each scan against the gallery without the entry enrolled from the same bytes (its own) and
        records the threshold, as `facerec3d gallery G calibrate SCANS` does for a store file; verify uses it
        from then on. The record (value, rule, pair counts, ...), answered after it is committed; 422 when the
        scans cannot give one (none usable, a single subject), 409 for an empty gallery."""
        await _once(request, "scan", "subject", "intrinsics")
        if not live.entries:
            raise ApiError(409, "the gallery is empty")
        if len(scan) > MAX_SCANS:
            raise ApiError(422, f"{len(scan)} scans: a calibration takes at most {MAX_SCANS} (an even selection)")
        if len(subject) != len(scan):
            raise ApiError(422, f"{len(subject)} subjects for {len(scan)} scans: give each scan's subject, in order")
        subjects = [_label(s, "subject") for s in subject]
        received = [_upload(f, None, camera) for f, camera in zip(scan, _cameras(intrinsics, len(scan)))]
        return await service.run(request, _calibrate, live, received, subjects, None if eer else fmr, own,
                                 service.who(request))

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
        404 when neither is enrolled, 409 when IDENT is a scan id of several subjects (remove one entry by its id).
        Answered after the removal is committed."""
        return await service.run(request, _remove, live, ident, service.who(request))

    @app.delete(f"{API}/entries/{{entry}}", summary="Remove one entry by its id (scope admin)")
    async def remove_entry(request: Request, entry: int):
        """Removes the entry of id ENTRY (the ids: GET /v1/entries; as `facerec3d gallery remove --entry`); 404 when
        there is none. Answered after the removal is committed."""
        return await service.run(request, _remove, live, None, service.who(request), entry)

    @app.get(f"{API}/entries", summary="Every entry and the failures to enrol (scope admin)")
    async def entries():
        failures = await asyncio.to_thread(live.failures)
        return {"entries": [_entry(e) for e in sorted(live.entries, key=lambda e: e.id)],
                "failures": [{"source": s, "reason": r} for s, r in failures], "gallery_version": live.version}

    @app.get(f"{API}/stats", summary="Gallery counts and settings, queue and limits (any valid key)")
    async def stats():
        st = await asyncio.to_thread(live.stats)
        return {**st, "queue": service.lanes["query"].stats(), "write_queue": service.lanes["write"].stats(),
                "uploads": {"raw": service.uploads["raw"], "preprocessed": service.uploads["preprocessed"]},
                "limits": {**asdict(service.settings), "max_points": live.max_points}, "degraded": live.health()}

    @app.get(f"{API}/health", summary="Liveness (no key needed): 'degraded' while a worker process is replaced")
    async def health():
        trouble = live.health()
        return {"status": "degraded" if trouble else "ok", **({"reason": trouble} if trouble else {}),
                "entries": len(live.entries), "gallery_version": live.version}

    @app.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (scope admin)")
    async def metrics():
        lanes = service.lanes.values()
        text = service.metrics.render({
            "facerec3d_queue_length": ("Requests waiting for a worker.", sum(q.waiting for q in lanes)),
            "facerec3d_requests_in_progress": ("Requests being worked on.", sum(q.running for q in lanes)),
            "facerec3d_gallery_entries": ("Entries in the live gallery.", len(live.entries)),
            "facerec3d_gallery_version": ("Changes applied to the live gallery since start (+1).", live.version),
            "facerec3d_cpu_seconds": ("CPU seconds used by the service and its local worker processes.",
                                      live.cpu_seconds())})
        return PlainTextResponse(text, media_type="text/plain; version=0.0.4")

    return Gate(app, service)


def bind_address(host: str, port: int) -> socket.socket:
    """A socket bound to host:port and listening, for uvicorn to serve on (`uvicorn.Server.run(sockets=[...])`):
    the address is held from this check until the service answers, so no other process can take it in between
    (binding to check and letting go, then binding again in uvicorn, left that gap). Connections that arrive
    while the gallery loads wait in the backlog and are answered once the service is up. An address this process
    cannot listen on (in use, not this machine's) is refused with an OSError naming host:port (`error:
    127.0.0.1:8000: address already in use` on the command line). SO_REUSEADDR as uvicorn sets it: a port whose
    earlier connections linger in TIME_WAIT can be listened on again at once. Made with `IPPROTO_TCP` named, as
    uvicorn's own socket is: asyncio turns Nagle's algorithm off (TCP_NODELAY) only on connections whose socket
    says so, and with it on every answer waited ~40 ms for the client's delayed ACK (p95 96 against 50 ms)."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen()  # listening: another socket cannot bind the address, SO_REUSEADDR or not
    except OSError as e:
        sock.close()
        e.filename = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        raise
    return sock


def warm(live: LiveGallery, echo=print) -> None:
    """The workers' warm-up (`LiveGallery.warm_up`) before the service answers, said in a line; a failure is a
    warning line and the service starts all the same (its first requests are then slow, not wrong)."""
    echo(f"warming up {live.engine.workers} worker{'s' * (live.engine.workers != 1)} (on a first run this compiles "
         "facerec3d's kernels, ~30 s) ...")
    try:
        seconds = live.warm_up()
    except Exception as e:  # noqa: BLE001 - any failure of a synthetic frame: say it, serve anyway
        echo(f"warning: the warm-up failed ({type(e).__name__}: {e}); the first requests will be slower")
        return
    echo(f"warmed up in {max(seconds):.1f} s")


def serve(gallery: str | Path, keys: str | Path, host: str = "127.0.0.1", port: int = 8000, jobs: int | None = None,
          scheduler: str | None = None, method: str | None = None, options: dict | None = None, config=None,
          settings: ServiceSettings | None = None, max_points: int = MAX_POINTS, audit: str | Path | None = None,
          ssl_certfile: str | None = None, ssl_keyfile: str | None = None, echo=print) -> None:
    """Load the gallery into `jobs` worker processes (or a Dask cluster's workers) and answer HTTP on host:port
    until interrupted (SIGINT / SIGTERM: in-flight requests finish, the workers stop). The address is bound first
    and held until uvicorn serves on that very socket (`bind_address`): one in use is refused before anything
    loads, with an OSError naming it. Port 0 takes a free port, which the banner names."""
    import uvicorn

    from facerec3d.preprocess.batch import one_thread_per_process
    from facerec3d.server.live import AuditLog

    settings = settings or ServiceSettings()
    sock = bind_address(host, port)  # before the gallery loads and the banner says the service is up
    hold = None
    scheme = "https" if ssl_certfile else "http"
    try:
        port = sock.getsockname()[1]
        key_file = KeyFile(keys)  # refuse to start without keys
        # the store is the service's while it runs: other processes' writes to it, and a second service, are refused
        hold = ServeLock(gallery, f"{scheme}://{f'[{host}]' if ':' in host else host}:{port}")
        one_thread_per_process()  # the service's own BLAS: one thread (work runs on the workers)
        live = LiveGallery(gallery, jobs, scheduler, method, options, config,
                           AuditLog(audit if audit is not None else Path(str(gallery) + ".audit.jsonl")), max_points)
        service = Service(live, key_file, settings)
        try:
            warm(live, echo)
            server = uvicorn.Server(uvicorn.Config(create_app(service), host=host, port=port, log_level="warning",
                                                   access_log=False, ssl_certfile=ssl_certfile,
                                                   ssl_keyfile=ssl_keyfile,
                                                   timeout_graceful_shutdown=max(5, int(settings.timeout_s))))
            echo(f"facerec3d service: {gallery} ({len(live.entries)} entries, method {live.matcher.name}, "
                 f"{live.engine.workers} worker{'s' * (live.engine.workers != 1)}) on {scheme}://{host}:{port} "
                 f"(API docs: /docs)")
            server.run(sockets=[sock])  # the socket bound above, held all along
        finally:
            service.close()
    finally:
        if hold is not None:
            hold.release()
        sock.close()  # uvicorn closes it on shutdown; here also when loading failed
