"""Where the work runs: this process, one process per core, or the workers of a Dask cluster.

    with Workers.create(jobs=4) as workers:          # or Workers.create(scheduler="tcp://host:8786")
        outcomes = list(workers.imap(preprocess_file, paths, config, cache))

One executor per worker: `jobs` = 1 runs in this process; more make one single-process `ProcessPoolExecutor`
each (dying with the parent); a Dask `distributed.Client` (or a scheduler address) gives one `ClientExecutor`
pinned to each of its workers. Every worker computes with one BLAS thread, so results do not depend on the
number or kind of workers. `imap` spreads independent calls over them, each worker kept
`depth` calls busy, and yields the results in order. `gallery.engine.Engine` is this, plus galleries sharded
over the same workers, so that one run reads, preprocesses, enrols and matches on one set of workers.

Under Dask, the functions and their arguments travel to the workers: files named by path (scans, the
preprocessing cache) must be on storage the workers see under the same paths.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from typing import Any

from facerec3d.errors import InputError

#: Local worker processes at most per core: more only queue for the cores, and each holds pipes open (--jobs 100000
#: ran out of open files before any work).
JOBS_PER_CORE = 4


def useful_jobs(jobs: int | None, items: int | None = None) -> int:
    """The local processes worth starting when `jobs` are asked for (None: all cores): no more than `items`, the
    pieces of work there are to share (a 3-entry gallery is 3 shards at most; one scan needs one process), nor
    `JOBS_PER_CORE` per core; at least 1."""
    cores = os.cpu_count() or 1
    n = min(cores if jobs is None else jobs, JOBS_PER_CORE * cores)
    return max(1, n if items is None else min(n, items))


def one_blas_thread():
    """A context in which BLAS / OpenMP run one thread, as in the workers, restored on leaving: for work done in the
    caller's own process (a probe preprocessed and matched by the CLI, `Preprocessor` called from a library). A
    thread per core makes such small linear algebra slower even on a quiet machine and many times slower on a busy
    one (`Preprocessor` on a Kinect frame and 2 / 3 mm meshes, 2 cores: 133 / 607 ms against 99 / 511 ms quiet,
    398 / 3,619 ms against 155 / 855 ms beside two busy processes). Each entry costs ~0.2 ms (threadpoolctl
    inspects the libraries loaded by then)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1)


def one_thread_per_process() -> None:
    """Worker initialiser: one BLAS/OpenMP thread per process, so N processes use N cores, not N²."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


def _init_worker() -> None:
    """Process-pool worker start: Ctrl-C handled as `_call` says (the worker starts with SIGINT held, `_WorkerPool`,
    until the handler is in place); one BLAS thread; on Linux, die with the parent process (PR_SET_PDEATHSIG), so a
    killed run leaves no orphaned workers."""
    signal.signal(signal.SIGINT, _note_interrupt)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    one_thread_per_process()
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGKILL)


_interrupted = False  # in a worker process: Ctrl-C came while it was not computing


def _note_interrupt(signum, frame) -> None:
    global _interrupted
    _interrupted = True


def _call(fn: Callable, /, *args: Any, **kwargs: Any) -> Any:
    """fn(*args, **kwargs) in a local worker process. Ctrl-C (SIGINT, sent to the whole process group) ends the
    worker at once, quietly (the parent alone says `interrupted`), while it computes; while it waits for work or
    hands a result back it is only noted, and ends the worker before its next call (the parent, interrupted too,
    shuts the pool down). A worker killed half-way through sending a result left the parent waiting for the rest
    forever; and each worker printed a KeyboardInterrupt traceback."""
    if _interrupted:
        os._exit(128 + signal.SIGINT)
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        return fn(*args, **kwargs)
    finally:
        signal.signal(signal.SIGINT, _note_interrupt)


class _WorkerPool(ProcessPoolExecutor):
    """A local worker: a process pool whose calls run through `_call`. A submit may start the worker process: it
    does so with SIGINT held, which the process inherits until `_init_worker` has put its handler in place (Ctrl-C
    while a worker started was a KeyboardInterrupt traceback of the worker's)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return super().submit(_call, fn, *args, **kwargs)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)


class InlineExecutor(Executor):
    """Runs each call at once in this process (one BLAS thread), for `jobs` = 1."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        f: Future = Future()
        try:
            with one_blas_thread():
                f.set_result(fn(*args, **kwargs))
        except BaseException as e:  # handed to the caller by f.result()
            f.set_exception(e)
        return f


class Workers:
    """Executors to run work on, one per worker; `create` makes them, `close` shuts them down."""

    def __init__(self, executors: Sequence[Executor], client: Any = None, own_client: bool = False,
                 addresses: Sequence[str] = ()):
        """`client`, with its worker `addresses` (one per executor): a Dask client, shut down on `close`
        when `own_client`."""
        if not executors:
            raise ValueError("at least one executor is needed")
        self.executors = list(executors)
        self._client, self._own_client, self._addresses = client, own_client, list(addresses)

    @classmethod
    def create(cls, jobs: int | None = None, scheduler: Any = None, items: int | None = None):
        """`jobs` local processes (None: all cores; 1: this process), capped at what is useful for `items` pieces
        of work (`useful_jobs`), or the workers of a Dask scheduler (an address such as "tcp://host:8786", or a
        `distributed.Client`)."""
        if scheduler is not None:
            try:
                from distributed import Client
            except ImportError:
                raise InputError("a Dask scheduler needs dask.distributed: pip install 'facerec3d[distributed]'") \
                    from None
            own = not isinstance(scheduler, Client)
            try:
                client = Client(scheduler) if own else scheduler
            except (ValueError, TypeError) as e:  # distributed's parse of the address
                raise InputError(f"scheduler {scheduler!r}: not a Dask scheduler's address ({e}); give one such as "
                                 "tcp://host:8786") from None
            except OSError as e:  # nothing answers there
                raise InputError(f"scheduler {scheduler!r}: {e}") from None
            workers = sorted(client.scheduler_info()["workers"])
            if not workers:
                if own:
                    client.close()
                raise InputError(f"the Dask scheduler {client.scheduler.address} has no workers")
            client.run(one_thread_per_process)  # as on local workers (Dask's nanny does it for worker processes)
            return cls([client.get_executor(workers=[w], allow_other_workers=False, pure=False) for w in workers],
                       client, own, workers)
        jobs = useful_jobs(jobs, items)
        if jobs <= 1:
            return cls([InlineExecutor()])
        return cls([_WorkerPool(1, initializer=_init_worker) for _ in range(jobs)])

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Shut the executors (and an own Dask client) down."""
        for ex in self.executors:
            ex.shutdown(wait=True)
        if self._own_client:
            self._client.close()

    @property
    def workers(self) -> int:
        return len(self.executors)

    def broken(self) -> list[int]:
        """The indices of local worker processes that died (killed, out of memory): their executors are broken.
        Dask workers are looked after by Dask's nannies and never listed."""
        return [i for i, ex in enumerate(self.executors)
                if isinstance(ex, ProcessPoolExecutor) and getattr(ex, "_broken", False)]

    def replace(self, i: int) -> None:
        """Put a new worker process in the place of worker `i` (one that died). It is spawned, not forked: the
        caller may have threads by now."""
        import multiprocessing

        old = self.executors[i]
        new = _WorkerPool(1, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker)
        new.submit(os.getpid).result()  # started and ready
        self.executors[i] = new
        old.shutdown(wait=False, cancel_futures=True)

    def imap(self, fn: Callable, items: Sequence, *args: Any, depth: int = 2) -> Iterator[Any]:
        """fn(item, *args) for each item, in item order. The first items go one to each worker, then each worker
        gets the next item as soon as it has fewer than `depth` in hand, so uneven calls (a cached scan, a
        slow one) keep every worker busy. An error is raised when its item's turn comes; the calls not yet
        started are then cancelled."""
        items = list(items)
        pending: dict[Future, tuple[int, int]] = {}  # future -> (item, worker)
        done: dict[int, Future] = {}
        following = 0

        def submit(w: int) -> None:
            nonlocal following
            pending[self.executors[w].submit(fn, items[following], *args)] = following, w
            following += 1

        try:
            for _ in range(depth):
                for w in range(self.workers):
                    if following < len(items):
                        submit(w)
            for i in range(len(items)):
                while i not in done:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for f in finished:
                        k, w = pending.pop(f)
                        done[k] = f
                        if following < len(items):
                            submit(w)
                yield done.pop(i).result()
        finally:
            for f in pending:
                f.cancel()

    def map(self, fn: Callable, items: Sequence, *args: Any) -> list[Any]:
        """The list of `imap`."""
        return list(self.imap(fn, items, *args))
