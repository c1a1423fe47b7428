"""The matching engine: a gallery sharded over concurrent.futures-style executors, one per shard.

    with Engine.create(jobs=4) as engine:            # or Engine.create(scheduler="tcp://host:8786")
        templates = engine.enroll(matcher, faces)
        gallery = engine.load(matcher, templates)     # each shard's templates stay in its worker
        scores, tiebreak = gallery.scores(engine.prepare(matcher, probes))[0]
        gallery.identify(probe_face, k=5, cascade=CascadeConfig())

Executors: `jobs` = 1 runs in this process; more make one single-process `ProcessPoolExecutor` per core,
so shard i always lives in process i; a Dask `distributed.Client` (or a scheduler address) gives one
`ClientExecutor` pinned to each worker. Every shard is loaded once into a module-level cache of its
worker (`_SHARDS`); a probe is sent to every shard and the per-shard scores are concatenated in gallery
order, so the results are the same whatever the number or kind of workers.
"""

from __future__ import annotations

import os
import signal
import sys
import uuid
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from threadpoolctl import ThreadpoolController

from facerec3d.gallery.cascade import CascadeConfig, best, check_cascadable, depth_descriptor, screen_distances
from facerec3d.matching.base import Matcher, Template, rank
from facerec3d.preprocess.batch import one_thread_per_process
from facerec3d.scan import FaceScan


_THREADPOOLS = ThreadpoolController()  # made once: inspecting the loaded BLAS libraries costs milliseconds


class InlineExecutor(Executor):
    """Runs each call at once in this process (one BLAS thread), for `jobs` = 1."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        f: Future = Future()
        try:
            with _THREADPOOLS.limit(limits=1):
                f.set_result(fn(*args, **kwargs))
        except BaseException as e:  # handed to the caller by f.result()
            f.set_exception(e)
        return f


@dataclass
class Probe:
    """A probe as matching needs it: the matcher's prepared form and, for the cascade, its depth descriptor."""

    prepared: Any
    descriptor: np.ndarray | None = None


@dataclass
class _Shard:
    matcher: Matcher
    templates: list[Template]
    descriptors: dict[CascadeConfig, np.ndarray] = field(default_factory=dict)


_SHARDS: dict[str, _Shard] = {}  # this worker's shards, by key


def _load(key: str, matcher: Matcher, templates: list[Template]) -> int:
    _SHARDS[key] = _Shard(matcher, templates)
    return len(templates)


def _drop(key: str) -> None:
    _SHARDS.pop(key, None)


def _shard(key: str) -> _Shard:
    try:
        return _SHARDS[key]
    except KeyError:
        raise RuntimeError(f"gallery shard {key} is not loaded in this worker (did the worker restart?)") from None


def _scores(key: str, probe: Any, indices: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(scores, tiebreak) of a prepared probe against the shard's templates (those at `indices` if given)."""
    s = _shard(key)
    templates = s.templates if indices is None else [s.templates[i] for i in indices]
    scores, tiebreak = s.matcher.scores(probe, templates)
    return scores, np.zeros_like(scores) if tiebreak is None else tiebreak


def _partial(key: str, probe: Any) -> np.ndarray:
    """The shard's partial scores of a prepared probe (Matcher.partial_scores)."""
    s = _shard(key)
    return s.matcher.partial_scores(probe, s.templates)


def _screen(key: str, descriptor: np.ndarray, config: CascadeConfig) -> np.ndarray:
    """Cascade stage 1 on the shard: depth-screen distances (mm²); the shard's descriptors are made once."""
    s = _shard(key)
    if config not in s.descriptors:
        s.descriptors[config] = np.array([depth_descriptor(t.arrays["points"], config) for t in s.templates])
    return screen_distances(descriptor, s.descriptors[config], config.keep) if s.templates else np.zeros(0)


def _init_worker() -> None:
    """Process-pool worker start: one BLAS thread; on Linux, die with the parent process (PR_SET_PDEATHSIG),
    so a killed enrolment or identification leaves no orphaned workers."""
    one_thread_per_process()
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGKILL)


def _enroll(face: FaceScan, matcher: Matcher) -> Template:
    return matcher.enroll(face)


def _prepare(face: FaceScan, matcher: Matcher, cascade: CascadeConfig | None) -> Probe:
    depth = cascade is not None and cascade.screen == "depth"
    return Probe(matcher.prepare(face), depth_descriptor(face.points, cascade) if depth else None)


def _call(fn: Callable, item: Any, args: tuple) -> Any:
    return fn(item, *args)


class Engine:
    """Executors to run work and hold gallery shards on; `create` makes them, `close` shuts them down."""

    def __init__(self, executors: Sequence[Executor], client: Any = None, own_client: bool = False,
                 addresses: Sequence[str] = ()):
        """`client`, with its worker `addresses` (one per executor): a Dask client, shut down on `close`
        when `own_client`; shards are then scattered to their workers rather than sent with the load call."""
        if not executors:
            raise ValueError("an engine needs at least one executor")
        self.executors = list(executors)
        self._client, self._own_client, self._addresses = client, own_client, list(addresses)
        self._loaded: list[ShardedGallery] = []

    @classmethod
    def create(cls, jobs: int | None = None, scheduler: Any = None) -> "Engine":
        """`jobs` local processes (None: all cores; 1: this process), or the workers of a Dask scheduler
        (an address such as "tcp://host:8786", or a `distributed.Client`)."""
        if scheduler is not None:
            try:
                from distributed import Client
            except ImportError:
                raise ValueError("a Dask scheduler needs dask.distributed: pip install 'facerec3d[distributed]'") \
                    from None
            own = not isinstance(scheduler, Client)
            client = Client(scheduler) if own else scheduler
            workers = sorted(client.scheduler_info()["workers"])
            if not workers:
                if own:
                    client.close()
                raise ValueError(f"the Dask scheduler {client.scheduler.address} has no workers")
            return cls([client.get_executor(workers=[w], allow_other_workers=False, pure=False) for w in workers],
                       client, own, workers)
        if jobs is None:
            jobs = os.cpu_count() or 1
        if jobs <= 1:
            return cls([InlineExecutor()])
        return cls([ProcessPoolExecutor(1, initializer=_init_worker) for _ in range(jobs)])

    def __enter__(self) -> "Engine":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Drop the galleries still loaded, then shut the executors (and an own Dask client) down."""
        for gallery in list(self._loaded):
            gallery.release()
        for ex in self.executors:
            ex.shutdown(wait=True)
        if self._own_client:
            self._client.close()

    @property
    def workers(self) -> int:
        return len(self.executors)

    def imap(self, fn: Callable, items: Sequence, *args: Any) -> Iterator[Any]:
        """fn(item, *args) for each item, spread round-robin over the executors; results in item order."""
        futures = [self.executors[i % self.workers].submit(_call, fn, item, args) for i, item in enumerate(items)]
        for f in futures:
            yield f.result()

    def map(self, fn: Callable, items: Sequence, *args: Any) -> list[Any]:
        """The list of `imap`."""
        return list(self.imap(fn, items, *args))

    def enroll(self, matcher: Matcher, faces: Sequence[FaceScan]) -> list[Template]:
        """The gallery templates of faces, in parallel."""
        return self.map(_enroll, faces, matcher)

    def prepare(self, matcher: Matcher, faces: Sequence[FaceScan], cascade: CascadeConfig | None = None) -> list[Probe]:
        """Probes prepared for matching (with depth descriptors for the cascade), in parallel."""
        return self.map(_prepare, faces, matcher, cascade)

    def load(self, matcher: Matcher, templates: Sequence[Template]) -> "ShardedGallery":
        """Split the gallery into one contiguous shard per executor and load each into its worker."""
        bounds = np.linspace(0, len(templates), self.workers + 1).round().astype(int)
        keys = [f"{uuid.uuid4().hex}-{i}" for i in range(self.workers)]
        shards: list[Any] = [list(templates[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]
        if self._client is not None:  # scatter: the data goes straight to its worker, not into the task graph
            shards = [self._client.scatter([shard], workers=[w])[0] for shard, w in zip(shards, self._addresses)]
        loads = [ex.submit(_load, key, matcher, shard) for ex, key, shard in zip(self.executors, keys, shards)]
        for f in loads:
            f.result()
        gallery = ShardedGallery(self, matcher, keys, bounds)
        self._loaded.append(gallery)
        return gallery


class ShardedGallery:
    """A gallery loaded into an engine's workers (shard i = templates bounds[i]:bounds[i + 1])."""

    def __init__(self, engine: Engine, matcher: Matcher, keys: list[str], bounds: np.ndarray):
        self.engine, self.matcher, self.keys, self.bounds = engine, matcher, keys, bounds

    def __len__(self) -> int:
        return int(self.bounds[-1])

    def release(self) -> None:
        """Drop the shards from the workers."""
        for f in [ex.submit(_drop, key) for ex, key in zip(self.engine.executors, self.keys)]:
            f.result()
        if self in self.engine._loaded:
            self.engine._loaded.remove(self)

    def _per_shard(self, calls: Sequence[Sequence[tuple | None]]) -> list[list[Any]]:
        """Run calls[p][s] = (fn, *args) (or None: nothing) on shard s's executor, for every probe p."""
        futures = [[None if c is None else ex.submit(c[0], key, *c[1:])
                    for c, ex, key in zip(row, self.engine.executors, self.keys)] for row in calls]
        return [[None if f is None else f.result() for f in row] for row in futures]

    def _local(self, indices: np.ndarray) -> list[np.ndarray | None]:
        """Global gallery indices split into each shard's local indices (None where a shard has none)."""
        out = []
        for a, b in zip(self.bounds[:-1], self.bounds[1:]):
            mine = indices[(indices >= a) & (indices < b)] - a
            out.append(mine if len(mine) else None)
        return out

    def scores(self, probes: Sequence[Probe]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(scores (n,), tiebreak (n,)) of each probe against the whole gallery (exhaustive): the shards'
        partial scores joined, then merged as one gallery (Matcher.merge_scores)."""
        rows = self._per_shard([[(_partial, p.prepared)] * len(self.keys) for p in probes])
        out = []
        for row in rows:
            scores, tiebreak = self.matcher.merge_scores(np.concatenate(row, axis=-1))
            out.append((scores, np.zeros_like(scores) if tiebreak is None else tiebreak))
        return out

    def cascade(self, probes: Sequence[Probe], config: CascadeConfig,
                screen: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
                ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(scores, tiebreak, shortlist) of each probe through the cascade: full-ICP scores for the shortlisted
        gallery indices (sorted), −inf (tiebreak 0) elsewhere. The shortlist is the best of the depth screen,
        or of `screen`: each probe's (scores, tiebreak) against the whole gallery by another matcher (e.g.
        a keypoint gallery's `scores`)."""
        check_cascadable(self.matcher)
        n = len(self)
        if screen is None:
            if config.screen != "depth":
                raise ValueError(f"a {config.screen} screen needs that matcher's scores against the gallery (screen=)")
            if any(p.descriptor is None for p in probes):
                raise ValueError("cascade probes need depth descriptors: Engine.prepare(..., cascade=config)")
            rows = self._per_shard([[(_screen, p.descriptor, config)] * len(self.keys) for p in probes])
            shortlists = [np.sort(best(-np.concatenate(row), config.shortlist)) for row in rows]
        else:
            shortlists = [np.sort(best(s, config.shortlist, t)) for s, t in screen]
        calls = [[None if loc is None else (_scores, p.prepared, loc) for loc in self._local(sl)]
                 for p, sl in zip(probes, shortlists)]
        out = []
        for sl, row in zip(shortlists, self._per_shard(calls)):
            scores, tiebreak = np.full(n, -np.inf), np.zeros(n)
            done = [r for r in row if r is not None]
            if done:
                scores[sl] = np.concatenate([r[0] for r in done])
                tiebreak[sl] = np.concatenate([r[1] for r in done])
            out.append((scores, tiebreak, sl))
        return out

    def identify(self, face: FaceScan, k: int = 5, cascade: CascadeConfig | None = None) -> list[tuple[int, float]]:
        """The k best gallery entries for a probe face as (gallery index, score), best first."""
        probe = self.engine.prepare(self.matcher, [face], cascade)
        scores, tiebreak = (self.scores(probe) if cascade is None else self.cascade(probe, cascade))[0][:2]
        return [(int(i), float(scores[i])) for i in rank(scores, tiebreak)[:k]]
