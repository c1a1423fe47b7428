"""Numba's just-in-time compilation of facerec3d's kernels, made visible.

The kernels are compiled on their first call and kept in Numba's on-disk cache (`__pycache__/*.nbi`, `*.nbc`
beside the modules, or NUMBA_CACHE_DIR): a first run, a new version or a changed module compiles them again,
25-30 s for preprocessing on one core, during which a command that prints nothing else looks hung.
`compilation_notice` says so in one line when, and only when, Numba starts compiling.

It listens to Numba's own "numba:compile" event (numba.core.event, documented since Numba 0.53), which fires
on a cache miss only: looking for cache files instead guesses wrong, e.g. after `facerec3d info` has compiled
its two kernels a cache exists, yet `facerec3d view` still compiles preprocessing's for about 25 s.

`guard_kernel_caches` (run by `import facerec3d`, before any kernel is defined) makes the cache of every kernel
stale when any module that defines kernels changes (Numba looks only at the kernel's own module), and turns a
damaged cache file into one line and a new compilation instead of a traceback.
"""

from __future__ import annotations

import hashlib
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from functools import lru_cache
from pathlib import Path

#: The package whose kernels `guard_kernel_caches` looks after.
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


def guard_kernel_caches(package: Path = PACKAGE) -> bool:
    """Make Numba's on-disk cache of the kernels under `package` stale whenever any module there that defines
    kernels changes, not only the kernel's own module.

    Numba keys a cached kernel on its own source file alone, yet compiles into it every kernel of another module
    that it calls ("changes in functions called by the cached function in other files are not detected", Numba's
    caching notes): after a `git pull` that changed `geometry/ball.py`, the detector's kernels that call it would
    run the old code from the cache, silently (or crash, where a signature changed). Each of Numba's own cache
    locators is put first again, for the files under `package` only, with its source stamp extended by
    `kernel_stamp`: any change there compiles the package's kernels again, once (~30 s).

    A cache file of those kernels that cannot be read (truncated, overwritten, from a full disk: Numba would stop
    the command with a traceback from `pickle`) is said in one line on stderr, removed, and the kernel compiled
    again; one that cannot be written (a read-only or full disk) leaves the kernel compiled in memory only, also
    said in one line. Returns whether all this was installed (False with a Numba whose caching internals differ:
    its own behaviour then holds)."""
    try:
        from numba.core import caching
    except ImportError:
        return False
    named = lambda name: getattr(caching, name, None) or getattr(caching, "_" + name, None)
    impl, cache = named("CacheImpl"), getattr(caching, "Cache", None)
    bases = [named(n) for n in ("UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator")]
    if (impl is None or not isinstance(getattr(impl, "_locator_classes", None), list) or None in bases
            or not all(callable(getattr(cache, m, None)) for m in ("load_overload", "save_overload"))):
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
    if not getattr(cache.load_overload, "guarded", False):
        cache.load_overload = _guarded_load(cache.load_overload)
        cache.save_overload = _guarded_save(cache.save_overload)
    return True


def _ours(cache) -> bool:
    """Whether a Numba function cache belongs to a package `guard_kernel_caches` looks after."""
    return getattr(getattr(getattr(cache, "_impl", None), "locator", None), "package_root", None) is not None


def _index_path(cache) -> str:
    return str(getattr(getattr(cache, "_cache_file", None), "_index_path", "?"))


def _guarded_load(load):
    """Numba's `Cache.load_overload`, a cache file of the package's kernels that cannot be read removed (its
    index; the data files it named are overwritten as the kernel is saved again) and the kernel compiled again."""

    def load_overload(self, sig, target_context):
        if not _ours(self):
            return load(self, sig, target_context)
        try:
            return load(self, sig, target_context)
        except Exception as e:  # whatever unpickling a damaged file raises
            index = _index_path(self)
            print(f"facerec3d: compiled-kernel cache {index} (or a .nbc data file beside it that it names): "
                  f"unreadable ({type(e).__name__}: {e}); its index removed, compiling again", file=sys.stderr,
                  flush=True)
            with suppress(OSError):
                os.remove(index)
            return None

    load_overload.guarded = True
    return load_overload


def _guarded_save(save):
    """Numba's `Cache.save_overload`: for the package's kernels, a cache that cannot be written is said, not
    raised (the kernel stays compiled in this process)."""

    def save_overload(self, sig, data):
        if not _ours(self):
            return save(self, sig, data)
        try:
            return save(self, sig, data)
        except Exception as e:  # a full or read-only disk, or an index that cannot be read
            print(f"facerec3d: compiled-kernel cache {_index_path(self)}: not saved ({type(e).__name__}: {e})",
                  file=sys.stderr, flush=True)

    save_overload.guarded = True
    return save_overload
