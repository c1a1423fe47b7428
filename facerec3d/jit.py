"""Numba's just-in-time compilation of facerec3d's kernels, made visible.

The kernels are compiled on their first call and kept in Numba's on-disk cache (`__pycache__/*.nbi`, `*.nbc`
beside the modules, or NUMBA_CACHE_DIR): a first run, a new version or a changed module compiles them again,
25-30 s for preprocessing on one core, during which a command that prints nothing else looks hung.
`compilation_notice` says so in one line when, and only when, Numba starts compiling.

It listens to Numba's own "numba:compile" event (numba.core.event, documented since Numba 0.53), which fires
on a cache miss only: looking for cache files instead guesses wrong, e.g. after `facerec3d info` has compiled
its two kernels a cache exists, yet `facerec3d view` still compiles preprocessing's for about 25 s.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

#: The line `compilation_notice` prints.
COMPILING = "compiling facerec3d's numerical kernels (first run only, ~30 s) ..."


@contextmanager
def compilation_notice(echo: Callable[[str], object], line: str = COMPILING) -> Iterator[None]:
    """Call `echo(line)` once, as Numba starts compiling a kernel inside the block (its on-disk cache is cold);
    nothing when every kernel comes from the cache or was compiled earlier in this process. Work in other
    processes (a command's workers) is not seen."""
    try:
        from numba.core import event
    except ImportError:  # a Numba without its event API: no notice, the work is the same
        yield
        return

    class FirstCompile(event.Listener):
        said = False

        def on_start(self, ev) -> None:
            if not self.said:
                self.said = True
                echo(line)

        def on_end(self, ev) -> None:
            pass

    with event.install_listener("numba:compile", FirstCompile()):
        yield
