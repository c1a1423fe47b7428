"""The engine: one set of workers (facerec3d.workers) for all the work of a run, holding galleries sharded over them.

    with Engine.create(jobs=4) as engine:            # or Engine.create(scheduler="tcp://host:8786")
        faces = [o.face for o in engine.preprocess(paths, config, cache=cache)]   # read, preprocess (cached)
        templates = engine.enroll(matcher, faces)
        gallery = engine.load(matcher, templates)     # each shard's templates stay in its worker
        scores, tiebreak = gallery.scores(engine.prepare(matcher, probes))[0]
        gallery.identify(probe_face, k=5, cascade=CascadeConfig())

Workers: `jobs` = 1 runs in this process; more make one single-process `ProcessPoolExecutor` per core,
so shard i always lives in process i; a Dask `distributed.Client` (or a scheduler address) gives one
`ClientExecutor` pinned to each worker. Reading and preprocessing (`preprocess`), enrolment and probe
preparation are spread over all of them; the gallery is loaded once as one contiguous shard per worker into a
module-level cache of that worker (`_SHARDS`); a probe is sent to every shard and the per-shard scores are
joined in gallery order, so the results are the same whatever the number or kind of workers.
"""

from __future__ import annotations

import uuid
from concurrent.futures import BrokenExecutor
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.gallery.cascade import Cascade, CascadeConfig, CascadeScores
from facerec3d.matching.base import GalleryScores, Matcher, Template, best_k, merge_shard_scores, shard_scores
from facerec3d.preprocess.batch import Outcome, preprocess_files
from facerec3d.preprocess.pipeline import PreprocessConfig
from facerec3d.scan import FaceScan
from facerec3d.workers import Workers


@dataclass
class Probe:
    """A probe as matching needs it: the matcher's prepared form and, for the cascade, its depth descriptor."""

    prepared: Any
    descriptor: np.ndarray | None = None


@dataclass
class Shard:
    """One worker's part of a loaded gallery. `derived`: per-template data made on the worker (the cascade's
    descriptors), by key: (function of a template, its rows), kept up to date when the gallery is updated."""

    matcher: Matcher
    templates: list[Template]
    derived: dict[Hashable, tuple[Callable[[Template], Any], np.ndarray]] = field(default_factory=dict)


_SHARDS: dict[str, Shard] = {}  # this worker's shards, by key


def _load(key: str, matcher: Matcher, templates: list[Template]) -> int:
    _SHARDS[key] = Shard(matcher, templates)
    return len(templates)


def _drop(key: str) -> None:
    _SHARDS.pop(key, None)


def _shard(key: str) -> Shard:
    try:
        return _SHARDS[key]
    except KeyError:
        raise RuntimeError(f"gallery shard {key} is not loaded in this worker (did the worker restart?)") from None


def _on_shard(key: str, fn: Callable, *args: Any) -> Any:
    """fn(shard, *args) on this worker's shard `key`."""
    return fn(_shard(key), *args)


def _scores(shard: Shard, probe: Any, indices: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(scores, tiebreak) of a prepared probe against the shard's templates (those at `indices` if given)."""
    templates = shard.templates if indices is None else [shard.templates[i] for i in indices]
    scores, tiebreak = shard.matcher.scores(probe, templates)
    return scores, np.zeros_like(scores) if tiebreak is None else tiebreak


def _shard_scores(shard: Shard, probe: Any) -> np.ndarray:
    """The shard's part of a prepared probe's scores (matching.base.shard_scores)."""
    return shard_scores(shard.matcher, probe, shard.templates)


def _derive(key: str, base: str, keep: np.ndarray | None, add: list[Template]) -> int:
    """Load shard `key`: shard `base`'s templates at local indices `keep` (all when None), then `add`. The
    templates are shared and the derived data reused (made only for `add`); `base` is left as it was."""
    s = _shard(base)
    kept = s.templates if keep is None else [s.templates[i] for i in keep]
    derived = {}
    for name, (fn, rows) in s.derived.items():
        new = list(rows if keep is None else rows[keep]) + [fn(t) for t in add]
        if new:
            derived[name] = fn, np.array(new)
    _SHARDS[key] = Shard(s.matcher, kept + list(add), derived)
    return len(_SHARDS[key].templates)


def _enroll(face: FaceScan, matcher: Matcher) -> Template:
    return matcher.enroll(face)


def _prepare(face: FaceScan, matcher: Matcher, cascade: CascadeConfig | None) -> Probe:
    return Probe(matcher.prepare(face), None if cascade is None else Cascade(cascade).probe_descriptor(face))


def merged(matcher: Matcher, rows: np.ndarray) -> GalleryScores:
    """A probe's scores against the whole gallery from its shards' joined `shard_scores` rows."""
    scores, tiebreak = merge_shard_scores(matcher, rows)
    return GalleryScores(scores, np.zeros_like(scores) if tiebreak is None else tiebreak)


class Engine(Workers):
    """Workers that run a whole run's work and hold its galleries; `create` makes them, `close` shuts them down."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self._loaded: list[ShardedGallery] = []

    def close(self) -> None:
        """Drop the galleries still loaded, then shut the workers down."""
        for gallery in list(self._loaded):
            gallery.release()
        super().close()

    def preprocess(self, paths: Sequence[str | Path], config: PreprocessConfig = PreprocessConfig(), *,
                   cache: str | Path | None = None, intrinsics: str | Path | None = None) -> Iterator[Outcome]:
        """Read and preprocess scan files on the workers (preprocess.batch.preprocess_files), in order."""
        return preprocess_files(paths, config, workers=self, cache=cache, intrinsics=intrinsics)

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

    @property
    def shards(self) -> int:
        return len(self.keys)

    def release(self) -> None:
        """Drop the shards from the workers. A worker that died (Ctrl-C ends them with the run) took its shard
        with it: nothing to drop there (closing the engine of an interrupted run raised BrokenProcessPool)."""
        futures = []
        for ex, key in zip(self.engine.executors, self.keys):
            try:
                futures.append(ex.submit(_drop, key))
            except BrokenExecutor:
                pass
        for f in futures:
            try:
                f.result()
            except BrokenExecutor:
                pass
        if self in self.engine._loaded:
            self.engine._loaded.remove(self)

    def update(self, add: Sequence[Template] = (), remove: Sequence[int] = ()) -> tuple["ShardedGallery", np.ndarray]:
        """A new gallery: this one without the entries at gallery indices `remove`, with `add` appended to its
        smallest shard; and `order`, for each of its entries the index in this gallery (len(self) + j for
        add[j]). This gallery stays loaded and unchanged (a consistent snapshot for the probes already using
        it) until released; the workers share the templates between the two, so an update costs only the
        new templates (and their cascade descriptors), not a reload."""
        n = len(self)
        gone = np.unique(np.asarray(remove, dtype=np.int64))
        if len(gone) and (gone[0] < 0 or gone[-1] >= n):
            raise IndexError(f"gallery index out of range 0..{n - 1}")
        kept = [np.setdiff1d(np.arange(a, b), gone) for a, b in zip(self.bounds[:-1], self.bounds[1:])]
        target = int(np.argmin([len(k) for k in kept]))
        keys = [f"{uuid.uuid4().hex}-{i}" for i in range(len(self.keys))]
        order, sizes, futures = [], [], []
        for i, (ex, key, base, mine, a, b) in enumerate(zip(self.engine.executors, keys, self.keys, kept,
                                                            self.bounds[:-1], self.bounds[1:])):
            extra = list(add) if i == target else []
            keep = None if len(mine) == b - a else mine - a
            futures.append(ex.submit(_derive, key, base, keep, extra))
            order += [*mine.tolist(), *range(n, n + len(extra))]
            sizes.append(len(mine) + len(extra))
        try:
            for f in futures:
                f.result()
        except BaseException:
            for f in [ex.submit(_drop, key) for ex, key in zip(self.engine.executors, keys)]:
                f.result()
            raise
        gallery = ShardedGallery(self.engine, self.matcher, keys, np.concatenate([[0], np.cumsum(sizes)]).astype(int))
        self.engine._loaded.append(gallery)
        return gallery, np.asarray(order, dtype=np.int64)

    def per_shard(self, calls: Sequence[Sequence[tuple | None]]) -> list[list[Any]]:
        """Run calls[p][s] = (fn, *args) as fn(shard s, *args) on shard s's worker (None: nothing), all at once;
        the results in the same layout."""
        futures = [[None if c is None else ex.submit(_on_shard, key, *c)
                    for c, ex, key in zip(row, self.engine.executors, self.keys)] for row in calls]
        return [[None if f is None else f.result() for f in row] for row in futures]

    def _local(self, indices: np.ndarray) -> list[np.ndarray | None]:
        """Global gallery indices split into each shard's local indices (None where a shard has none)."""
        out = []
        for a, b in zip(self.bounds[:-1], self.bounds[1:]):
            mine = indices[(indices >= a) & (indices < b)] - a
            out.append(mine if len(mine) else None)
        return out

    def scores(self, probes: Sequence[Probe]) -> list[GalleryScores]:
        """(scores (n,), tiebreak (n,)) of each probe against the whole gallery (exhaustive): the shards'
        scores joined, then merged as one gallery (matching.base.merge_shard_scores)."""
        return [merged(self.matcher, rows) for rows in self.shard_rows(probes)]

    def shard_rows(self, probes: Sequence[Probe]) -> list[np.ndarray]:
        """Each prepared probe's `matching.base.shard_scores` against the whole gallery, the shards' joined: what
        `merge_shard_scores` makes its scores of, over all the entries or over any subset of them (its columns:
        a method that normalises over the gallery then normalises over that subset alone)."""
        return [np.concatenate(row, axis=-1)
                for row in self.per_shard([[(_shard_scores, p.prepared)] * self.shards for p in probes])]

    def scores_at_many(self, probes: Sequence[Probe], indices: Sequence[Sequence[int]]) -> list[GalleryScores]:
        """(scores, tiebreak) of each prepared probe against the entries at its gallery indices, in increasing
        index order (a shortlist; a claimed subject's entries, for verification)."""
        wanted = [np.unique(np.asarray(i, dtype=np.int64)) for i in indices]
        calls = [[None if loc is None else (_scores, p.prepared, loc) for loc in self._local(idx)]
                 for p, idx in zip(probes, wanted)]
        out = []
        for row in self.per_shard(calls):
            done = [r for r in row if r is not None]
            out.append(GalleryScores(np.concatenate([r[0] for r in done]), np.concatenate([r[1] for r in done]))
                       if done else GalleryScores(np.zeros(0), np.zeros(0)))
        return out

    def scores_at(self, probe: Probe, indices: Sequence[int]) -> GalleryScores:
        """`scores_at_many` of one probe."""
        return self.scores_at_many([probe], [indices])[0]

    def describe(self, config: CascadeConfig) -> None:
        """Make the shards' cascade descriptors for `config` now rather than on the first cascade probe."""
        Cascade(config).describe(self)

    def cascade(self, probes: Sequence[Probe], config: CascadeConfig,
                screen: Sequence[GalleryScores] | None = None) -> list[CascadeScores]:
        """Each probe through the cascade (gallery.cascade.Cascade.search)."""
        return Cascade(config).search(self, probes, screen)

    def identify(self, face: FaceScan, k: int = 5, cascade: CascadeConfig | None = None) -> list[tuple[int, float]]:
        """The k best gallery entries for a probe face as (gallery index, score), best first."""
        probe = self.engine.prepare(self.matcher, [face], cascade)
        result = (self.scores(probe) if cascade is None else self.cascade(probe, cascade))[0]
        return [(int(i), float(result.scores[i])) for i in best_k(result.scores, result.tiebreak, k)]
