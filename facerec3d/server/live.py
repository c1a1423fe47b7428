"""A gallery kept live for a long-running service: loaded once into the engine's workers, updated in place as
scans are enrolled or subjects removed, every change committed to the store before it is acknowledged.

    live = LiveGallery("g.sqlite", jobs=2)
    probe, _, _ = live.work(probe_job, upload, live.max_points, live.config, live.matcher, None)
    hits, version, n = live.identify(probe, k=5)
    entry = live.enrol(template, source="upload:sha256:…", who={"key": "gate-3"})

Consistency: identification and verification run against a *snapshot* — the sharded gallery and the entry
list of one version. An enrolment or removal commits its transaction, derives the next version from the
current one (`ShardedGallery.update`: the workers share the unchanged templates, so it costs only the new
ones) and swaps it in; probes already running finish on the version they started with, which is released
when the last of them is done. A probe therefore sees the gallery before or after a change, never half.

Durability: all store access is on one writer thread (one SQLite connection, WAL, synchronous=FULL, one
transaction per enrolment), so changes are serialised and `enrol` returns only after the commit; a kill at any
moment loses no returned entry and leaves no half-written one (SQLite rolls an open transaction back).
The service owns its store while it runs (`serve` holds its `store.ServeLock`): other processes' writes to it
are refused, since the service would not see them until restart; their reads go on.

Calibration (`calibration_scores`, `record_threshold`): scans sent for it are scored against one version, a probe
at a time with no lock held, so identifications go on between them; only the threshold's record is written on
the writer thread (one short transaction), and verification uses it from then on.
"""

from __future__ import annotations

import json
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.config import DEFAULT_METHOD
from facerec3d.errors import FaceRec3DError
from facerec3d.io.common import MAX_POINTS
from facerec3d.evaluation.calibrate import pair_scores, too_few_pairs
from facerec3d.gallery.cascade import CascadeConfig, check_cascadable
from facerec3d.gallery.engine import Engine, Probe, ShardedGallery
from facerec3d.gallery.service import gallery_threshold
from facerec3d.gallery.store import AlreadyEnrolled, Entry, GalleryError, GalleryStore, removal
from facerec3d.matching.base import rank
from facerec3d.matching.registry import make_matcher
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.server.jobs import ready, warm_up


class Conflict(FaceRec3DError):
    """The scan is already enrolled (`entry` is its entry), or a removal names entries of several subjects."""

    def __init__(self, message: str, entry: Entry | None):
        super().__init__(message)
        self.entry = entry


class NotFound(FaceRec3DError):
    """No such subject or scan in the gallery."""


class WorkerLost(FaceRec3DError):
    """A worker process died while the request needed it (it is being replaced): the request may be retried."""

    def __init__(self):
        super().__init__("a worker process of the service stopped; it is being replaced: retry in a few seconds")


def _stopped(dead: list[int]) -> str:
    return f"worker process {', '.join(map(str, dead))} stopped; it is being replaced"


@dataclass(eq=False)
class Snapshot:
    """One version of the gallery: its shards in the workers and its entries in the same order."""

    version: int
    gallery: ShardedGallery
    entries: tuple[Entry, ...]
    users: int = 0
    retired: bool = False


class AuditLog:
    """Append-only JSON lines (who enrolled or removed what, when), flushed and synced line by line."""

    def __init__(self, path: str | os.PathLike | None):
        self.path = None if path is None else Path(path)
        self._lock = threading.Lock()
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)  # who did what: for the owner
            self._file = open(fd, "a", encoding="utf-8")

    def write(self, action: str, sync: bool = True, **fields: Any) -> None:
        """Append a record; `sync=False` (refused requests) skips the fsync, so that they cannot cost one each."""
        if self.path is None:
            return
        now = time.time()
        record = {"time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(now)) + f".{int(now * 1e3) % 1000:03d}Z",
                  "action": action, **fields}
        line = json.dumps(record, ensure_ascii=False, separators=(",", ":"), default=str)
        with self._lock:
            self._file.write(line + "\n")
            self._file.flush()
            if sync:
                os.fsync(self._file.fileno())

    def close(self) -> None:
        if self.path is not None:
            self._file.close()


class LiveGallery:
    """A gallery store served from memory: `jobs` local worker processes (or a Dask `scheduler`'s workers)
    hold its shards. A store without settings yet is bound to `method` (with `options`) and `config`."""

    def __init__(self, path: str | os.PathLike, jobs: int | None = None, scheduler: Any = None,
                 method: str | None = None, options: dict | None = None, config: PreprocessConfig | None = None,
                 audit: AuditLog | None = None, max_points: int = MAX_POINTS):
        self.path = Path(path)
        self.audit = audit or AuditLog(None)
        self.max_points = max_points
        self.engine = Engine.create(jobs, scheduler)
        self._lock = threading.Lock()
        self._busy = [0] * self.engine.workers  # jobs in flight per executor (work goes to the least busy)
        self.degraded: str | None = None  # a lasting note (an in-memory update failed and the store was reloaded)
        self.restarting: str | None = None  # while dead worker processes are replaced
        self.restarts = 0  # worker replacements so far
        try:
            self.engine.map(ready, range(self.engine.workers))  # start the workers before any thread exists
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="facerec3d-store")
            self._janitor = ThreadPoolExecutor(1, thread_name_prefix="facerec3d-release")
            self._writer.submit(self._open, method, options, config).result()
        except BaseException:
            self.engine.close()
            raise
        self._stop = threading.Event()
        self._watchdog = threading.Thread(target=self._watch, name="facerec3d-watchdog", daemon=True)
        self._watchdog.start()

    def warm_up(self) -> list[float]:
        """Each worker preprocesses, enrols and matches a synthetic frame once (`jobs.warm_up`), so that the first
        request finds facerec3d's kernels compiled; the seconds each took. The gallery is not touched."""
        return self.engine.map(warm_up, range(self.engine.workers), self.config, self.matcher)

    # ------------------------------------------------------------------ dead workers (watchdog thread)
    WATCH_S = 0.5  # how often the worker processes are looked at

    def health(self) -> str | None:
        """Why the service is degraded (a worker process died and is being replaced, or a lasting note), or None."""
        dead = self.engine.broken()
        return _stopped(dead) if dead else self.restarting or self.degraded

    def _watch(self) -> None:
        """Replace dead worker processes (killed, out of memory) and reload the gallery into them."""
        while not self._stop.wait(self.WATCH_S):
            dead = self.engine.broken()
            if not dead and not self.restarting:  # (a failed replacement is tried again)
                continue
            self.restarting = _stopped(dead) if dead else self.restarting
            print(f"facerec3d service: {self.restarting}", file=sys.stderr, flush=True)
            try:
                self._writer.submit(self._recover).result()
            except Exception as e:  # noqa: BLE001 - tried again at the next look
                print(f"facerec3d service: replacing worker processes failed ({type(e).__name__}: {e}); retrying",
                      file=sys.stderr, flush=True)
                continue
            self.restarting = None

    def _recover(self) -> None:
        """(writer thread, so that no change is under way) New processes for the dead ones, the gallery reloaded."""
        dead = self.engine.broken()
        self.restarts += 1
        for i in dead:
            self.engine.replace(i)
        self._reload()
        print(f"facerec3d service: worker process {', '.join(map(str, dead))} replaced, the gallery reloaded "
              f"({len(self._snap.entries)} entries)", file=sys.stderr, flush=True)

    # ------------------------------------------------------------------ set-up (writer thread)
    def _open(self, method: str | None, options: dict | None, config: PreprocessConfig | None) -> None:
        self._store = store = GalleryStore(self.path, create=True)
        store.check_writable()  # the service writes every enrolment: refuse a read-only gallery now, not then
        # every commit synced to disk (SQLite's usual default, made sure of): an acknowledged enrolment survives
        # a power cut too, not only a killed process
        store._db.execute("PRAGMA synchronous = FULL")
        if store.stats()["method"] is None:
            matcher = make_matcher(method or DEFAULT_METHOD, options)
            if matcher.needs_training:
                raise GalleryError(f"method {matcher.name!r} must be trained: enrol a first scan with "
                                   f"`facerec3d enroll --method {matcher.name} --train DATA` and serve that gallery")
            store.bind(config or PreprocessConfig(), matcher)
        else:
            if config is not None:
                store.check_preprocess(config)
            if method is not None:
                store.check_matcher(make_matcher(method, options))
        self.config = store.preprocess_config()
        self.matcher = store.matcher()
        self._default_threshold: tuple[float, float | None] | None = None  # read once: (the store's calibration, or
        #   the method's; the false-match rate to expect of a calibration on too few impostor pairs, else None)
        entries = store.entries()
        gallery = self.engine.load(self.matcher, store.templates(entries))
        self.cascadable = True
        try:
            check_cascadable(self.matcher)
        except ValueError:
            self.cascadable = False
        if self.cascadable:
            self._describe(gallery)
        self._snap = Snapshot(1, gallery, tuple(entries))

    @staticmethod
    def _describe(gallery) -> None:
        """The cascade screens' descriptors (depth, learned embedding) of every enrolled face, made now rather than at
        the first cascade probe."""
        for screen in ("depth", "embedding"):
            gallery.describe(CascadeConfig(screen=screen))

    def close(self) -> None:
        """Release the gallery, stop the workers and close the store."""
        self._stop.set()
        self._watchdog.join()
        self._janitor.shutdown(wait=True)
        self._writer.submit(self._store.close).result()
        self._writer.shutdown(wait=True)
        self.engine.close()
        self.audit.close()

    # ------------------------------------------------------------------ running work
    def work(self, fn: Callable, *args: Any) -> Any:
        """fn(*args) on the least busy worker (blocks; call from a request thread)."""
        dead = set(self.engine.broken())
        with self._lock:
            i = min((b, i) for i, b in enumerate(self._busy) if i not in dead)[1] if len(dead) < len(self._busy) \
                else None
            if i is None:
                raise WorkerLost()
            self._busy[i] += 1
        try:
            return self.engine.executors[i].submit(fn, *args).result()
        except BrokenProcessPool:
            raise WorkerLost() from None
        finally:
            with self._lock:
                self._busy[i] -= 1

    @contextmanager
    def snapshot(self) -> Iterator[Snapshot]:
        """The current version, kept loaded until the caller is done with it."""
        with self._lock:
            snap = self._snap
            snap.users += 1
            restarts = self.restarts
        try:
            yield snap
        except BrokenProcessPool:
            raise WorkerLost() from None
        except RuntimeError:  # a shard missing from a worker put in the place of a dead one
            if snap.retired or self.restarting or self.restarts != restarts or self.engine.broken():
                raise WorkerLost() from None
            raise
        finally:
            with self._lock:
                snap.users -= 1
                done = snap.retired and snap.users == 0
            if done:
                self._janitor.submit(snap.gallery.release)

    @property
    def version(self) -> int:
        return self._snap.version

    @property
    def entries(self) -> tuple[Entry, ...]:
        return self._snap.entries

    # ------------------------------------------------------------------ queries (request threads)
    def identify(self, probe: Probe, k: int, cascade: CascadeConfig | None = None,
                 ) -> tuple[list[tuple[Entry, float]], int, int]:
        """(the k best (entry, score), best first; the gallery version and size they come from). Under the
        cascade, faces off the shortlist are not candidates."""
        with self.snapshot() as snap:
            if not snap.entries:
                raise GalleryError("the gallery is empty")
            if cascade is not None:
                scores, tiebreak, _ = snap.gallery.cascade([probe], cascade)[0]
            else:
                scores, tiebreak = snap.gallery.scores([probe])[0]
            hits = [(snap.entries[i], float(scores[i])) for i in rank(scores, tiebreak)[:k] if np.isfinite(scores[i])]
            return hits, snap.version, len(snap.entries)

    def default_threshold(self) -> tuple[float, float | None]:
        """(the gallery's calibrated threshold, else the method's default; the false-match rate to expect of that
        calibration when it rests on too few impostor pairs for the rate asked, `evaluation.calibrate.too_few_pairs`,
        else None), read together."""
        if self._default_threshold is None:
            self._default_threshold = self._writer.submit(self._read_threshold).result()
        return self._default_threshold

    def _read_threshold(self) -> tuple[float, float | None]:
        return gallery_threshold(self._store, self.matcher.name), too_few_pairs(self._store.threshold())

    def calibration_scores(self, probes: list[Probe], subjects: list[str], contents: list[str],
                           check: Callable[[], None] = lambda: None) -> tuple[np.ndarray, np.ndarray, int]:
        """(genuine scores, impostor scores, gallery size) of calibration probes, each with its subject and the
        SHA-256 of its upload, against the current version, each without its own entry (the one enrolled from the
        same bytes), each pair as `evaluation.calibrate.pair_scores` scores it (as a gallery's scans are scored).
        One probe at a time (`check()` between them, e.g. the request's time limit): queries are served in between."""
        with self.snapshot() as snap:
            if not snap.entries:
                raise GalleryError("the gallery is empty")
            stored = self._writer.submit(self._store.contents).result()  # (committed before the snapshot was made)
            hashes = np.array([stored.get(e.id) or "" for e in snap.entries])
            owners = np.array([str(e.subject) for e in snap.entries])
            genuine: list[float] = []
            impostor: list[float] = []
            for probe, subject, content in zip(probes, subjects, contents):
                check()
                rows = snap.gallery.shard_rows([probe])[0]
                g, i = pair_scores(self.matcher, rows, hashes == content, owners == str(subject))
                genuine += g.tolist()
                impostor += i.tolist()
            return np.array(genuine), np.array(impostor), len(snap.entries)

    def verify(self, probe: Probe, claim: str) -> tuple[float, int]:
        """(the probe's best score against the claimed subject's entries, the gallery version). Methods that
        normalise over the gallery score the probe against all of it."""
        with self.snapshot() as snap:
            claimed = [i for i, e in enumerate(snap.entries) if e.subject == claim]
            if not claimed:
                raise NotFound(f"subject {claim!r} is not enrolled")
            if self.matcher.cohort_scores:
                scores = snap.gallery.scores([probe])[0][0][claimed]
            else:
                scores = snap.gallery.scores_at(probe, claimed)[0]
            return float(np.max(scores)), snap.version

    # ------------------------------------------------------------------ changes (writer thread)
    def enrol(self, template, source: str, content: str | None = None, who: dict | None = None) -> Entry:
        """Commit a template to the store, then make it visible to queries; returns its entry. `Conflict` when
        the source, or a scan with the same `content` (SHA-256 of its bytes), is already enrolled."""
        return self._writer.submit(self._enrol, template, source, content, who or {}).result()

    def _enrol(self, template, source: str, content: str | None, who: dict) -> Entry:
        old = next((e for e in self._snap.entries if e.source == source), None)
        if old is None:
            try:
                ident = self._store.add(template, source, content)  # one transaction, committed on return
            except AlreadyEnrolled as e:  # the same scan enrolled from a file (by content), or by another process
                twin = re.search(r"as entry (\d+)", str(e))
                old = next((x for x in self._snap.entries if twin and x.id == int(twin.group(1))), None)
                if old is None:
                    raise Conflict("this scan is already enrolled", None) from None
        if old is not None:
            raise Conflict(f"this scan is already enrolled: entry {old.id} of subject {old.subject!r}", old)
        entry = next(e for e in self._store.entries(subject=template.subject) if e.id == ident)
        self.audit.write("enrol", entry=entry.id, subject=entry.subject, scan=entry.scan_id, source=source, **who)
        self._swap(add=[template], added=[entry])
        return entry

    def record_failure(self, source: str, reason: str, who: dict | None = None) -> None:
        """Record a failure to enrol (committed before return)."""
        self._writer.submit(self._record_failure, source, reason, who or {}).result()

    def _record_failure(self, source: str, reason: str, who: dict) -> None:
        self._store.add_failure(source, reason)
        self.audit.write("enrol-failed", source=source, reason=reason, **who)

    def record_threshold(self, record: dict, who: dict | None = None) -> None:
        """Commit a calibrated verification threshold's record (`evaluation.calibrate.threshold_record`) to the
        store; verification uses it once this returns."""
        self._writer.submit(self._record_threshold, record, who or {}).result()

    def _record_threshold(self, record: dict, who: dict) -> None:
        self._store.set_threshold(record)
        self._default_threshold = (float(record["value"]), too_few_pairs(record))
        self.audit.write("calibrate", value=record["value"], rule=record["rule"], data=record["data"],
                         scans=record["scans"], **who)

    def remove(self, ident: str | None, who: dict | None = None, entry: int | None = None) -> list[Entry]:
        """Remove subject `ident`'s entries, or else the entries of scan `ident` (one subject's), or entry id `entry`
        (`store.removal`); returns them. `NotFound` when none exists, `Conflict` for a scan id of several subjects."""
        return self._writer.submit(self._remove, ident, who or {}, entry).result()

    def _remove(self, ident: str | None, who: dict, entry: int | None = None) -> list[Entry]:
        entries = self._snap.entries
        try:
            removed = removal(entries, ident, entry)
        except ValueError as e:
            raise Conflict(f"{e} (DELETE /v1/entries/ID; the ids: GET /v1/entries)", None) from None
        if not removed:
            raise NotFound(f"no entry {entry}" if entry is not None else f"no subject or scan {ident!r}")
        ids = {e.id for e in removed}
        gone = [i for i, e in enumerate(entries) if e.id in ids]
        n = self._store.remove(entry=entry) if entry is not None else self._store.remove(ident)
        if n != len(gone):  # the store was changed by another process: reload it whole
            self._reload()
        else:
            self._swap(remove=gone)
        self.audit.write("remove", ident=ident if entry is None else f"entry {entry}", entries=[e.id for e in removed],
                         subjects=sorted({str(e.subject) for e in removed}), **who)
        return removed

    def _swap(self, add=(), added=(), remove=()) -> None:
        """Install the next version: this one with `remove` (indices) taken out and `add` (with their entries
        `added`) put in."""
        old = self._snap
        try:
            gallery, order = old.gallery.update(list(add), list(remove))
        except Exception as e:  # a worker failed: rebuild the gallery from the store
            self.degraded = f"in-memory update failed ({type(e).__name__}: {e}); reloaded from the store"
            self._reload()
            return
        combined = old.entries + tuple(added)
        self._install(Snapshot(old.version + 1, gallery, tuple(combined[i] for i in order)))

    def _reload(self) -> None:
        entries = self._store.entries()
        gallery = self.engine.load(self.matcher, self._store.templates(entries))
        if self.cascadable:
            self._describe(gallery)
        self._install(Snapshot(self._snap.version + 1, gallery, tuple(entries)))

    def _install(self, snap: Snapshot) -> None:
        with self._lock:
            old, self._snap = self._snap, snap
            old.retired = True
            done = old.users == 0
        if done:
            self._janitor.submit(old.gallery.release)

    def stats(self) -> dict:
        """The store's counts and settings with the live version and workers."""
        return self._writer.submit(self._stats).result()

    def _stats(self) -> dict:
        st = self._store.stats()
        fingerprint = self.config.fingerprint()
        return {**st, "preprocess": json.loads(fingerprint),
                "preprocess_fingerprint": self.config.digest(),
                "gallery_version": self._snap.version, "workers": self.engine.workers,
                "cascade": self.cascadable}

    def cpu_seconds(self) -> float:
        """CPU seconds used so far by this process and its local worker processes (Linux /proc; the service's
        own process only elsewhere, or with Dask workers)."""
        total = time.process_time()
        tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        for ex in self.engine.executors:
            for pid in list(getattr(ex, "_processes", None) or {}):
                try:
                    with open(f"/proc/{pid}/stat") as f:
                        fields = f.read().rsplit(")", 1)[1].split()
                    total += (int(fields[11]) + int(fields[12])) / tick  # utime + stime
                except (OSError, IndexError, ValueError):
                    pass
        return total

    def failures(self) -> list[tuple[str, str]]:
        return self._writer.submit(self._store.failures).result()
