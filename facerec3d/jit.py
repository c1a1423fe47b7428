"""Numba's just-in-time compilation of facerec3d's kernels, made visible.

The kernels are compiled on their first call and kept in Numba's on-disk cache (`__pycache__/*.nbi`, `*.nbc`
beside the modules, or NUMBA_CACHE_DIR): a first run, a new version or a changed module compiles them again,
25-30 s for preprocessing on one core, during which a command that prints nothing else looks hung.
`compilation_notice` says so in one line when, and only when, Numba starts compiling.

It listens to Numba's own "numba:compile" event (numba.core.event, documented since Numba 0.53), which fires
on a cache miss only: looking for cache files instead guesses wrong, e.g. after `facerec3d info` has compiled
its two kernels a cache exists, yet `facerec3d view` still compiles preprocessing's for about 25 s.

`stamp_kernel_caches` (run by `import facerec3d`, before any kernel is defined) makes the cache of every kernel
stale when any module that defines kernels changes: Numba looks only at the kernel's own module.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

#: The package whose kernels `stamp_kernel_caches` looks after.
PACKAGE = Path(__file__).resolve().parent

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


def kernel_sources(package: Path) -> list[Path]:
    """The modules under `package` that define compiled kernels (their text names `njit`), sorted."""
    return sorted(p for p in package.rglob("*.py") if "njit" in p.read_text(encoding="utf-8", errors="replace"))


@lru_cache(maxsize=None)
def kernel_stamp(package: Path) -> str:
    """A digest of the text of every module under `package` that defines kernels (`kernel_sources`)."""
    digest = hashlib.sha256()
    for path in kernel_sources(package):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def stamp_kernel_caches(package: Path = PACKAGE) -> bool:
    """Make Numba's on-disk cache of the kernels under `package` stale whenever any module there that defines
    kernels changes, not only the kernel's own module.

    Numba keys a cached kernel on its own source file alone, yet compiles into it every kernel of another module
    that it calls ("changes in functions called by the cached function in other files are not detected", Numba's
    caching notes): after a `git pull` that changed `geometry/ball.py`, the detector's kernels that call it would
    run the old code from the cache, silently (or crash, where a signature changed). Each of Numba's own cache
    locators is put first again, for the files under `package` only, with its source stamp extended by
    `kernel_stamp`: any change there compiles the package's kernels again, once (~30 s). Returns whether it was
    installed (False with a Numba whose caching internals differ: its own behaviour then holds)."""
    try:
        from numba.core import caching
    except ImportError:
        return False
    named = lambda name: getattr(caching, name, None) or getattr(caching, "_" + name, None)
    impl = named("CacheImpl")
    bases = [named(n) for n in ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator")]
    if impl is None or not isinstance(getattr(impl, "_locator_classes", None), list) or None in bases:
        return False
    root = package.resolve()
    if any(getattr(cls, "package_root", None) == root for cls in impl._locator_classes):
        return True  # installed already

    def within(base: type) -> type:
        class PackageLocator(base):
            package_root = root

            @classmethod
            def from_function(cls, py_func, py_file):
                try:
                    inside = Path(py_file).resolve().is_relative_to(root)
                except (OSError, ValueError):
                    inside = False
                return super().from_function(py_func, py_file) if inside else None

            def get_source_stamp(self):
                return super().get_source_stamp(), kernel_stamp(root)

        PackageLocator.__name__ = PackageLocator.__qualname__ = "Package" + base.__name__.lstrip("_")
        return PackageLocator

    impl._locator_classes[:0] = [within(base) for base in bases]
    return True
