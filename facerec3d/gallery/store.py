"""A persistent gallery: one SQLite file holding enrolled templates, the settings they were made with and
the failures to enrol (ISO/IEC 19795-1 FTE).

    with GalleryStore("g.sqlite", create=True) as store:
        store.bind(PreprocessConfig(), make_matcher("icp"))
        store.add(template, source="scan.abs.gz")
        matcher, templates = store.matcher(), store.templates()

Schema (stdlib sqlite3, WAL journal, foreign keys on):
  meta(key, value)                       "format", "preprocess" (PreprocessConfig.fingerprint()),
                                         "method", "options" (JSON), "state" (JSON attrs of a learnt matcher),
                                         "binding" (a random id of those settings, new each time they are set),
                                         "threshold" (JSON: the calibrated verification threshold, if any)
  entries(id, subject, scan_id, source UNIQUE, content UNIQUE, method, attrs JSON, nbytes, enrolled_at, checksum)
  arrays(entry → entries.id ON DELETE CASCADE, name, dtype, shape JSON, data BLOB, checksum)
  model_arrays(name, dtype, shape JSON, data BLOB, checksum)   what a learnt matcher's fit() kept
  failures(id, source UNIQUE, reason, failed_at)     the latest failure of each source not enrolled since
Arrays are stored as raw C-order bytes with their dtype string (e.g. "<f4") and shape — never pickled — and
the SHA-256 of all three, checked on reading (as is each entry's, of its subject, scan id, source, method and
attributes), so damaged bytes are refused, naming the entry, rather than matched; templates are also checked
for what compiled matching relies on (matching.checks). `content` is the SHA-256 of the scan file an entry was
enrolled from: the same scan under another path is a duplicate.
The settings are recorded by the first enrolment; while the store holds no entry (every scan of that enrolment
failed, or all were removed) another enrolment may replace them (`bind`), and a store object opened on the old
settings can then add nothing more, so a store never holds templates of two methods.
Each enrolment (an entry and its arrays) is one transaction, so a crash or kill mid-enrolment leaves every
earlier enrolment intact and the file readable (SQLite rolls the unfinished one back on the next open).
A new store file (and SQLite's -wal and -shm files beside it, which take its mode) is made with mode 0600.

A gallery service owns its store while it runs (`ServeLock`): it holds an exclusive `flock` on G.serve.lock beside
the store (its pid and URL written in it), and every write of a store object of another process (each goes
through `_transaction`) is refused with `GalleryServed`, naming the service's URL; reads go on (WAL). The kernel
lets the lock go when the service ends, however it ends (SIGKILL too): the lock file left behind blocks nothing.

Encryption at rest (optional; pip install 'facerec3d[crypto]'): with a `TemplateKey` — given, or from the
environment: FACEREC3D_GALLERY_KEY_FILE (a file holding the key) or FACEREC3D_GALLERY_KEY (the key), 64 hex
digits — every array (the templates', and a learnt matcher's) is stored as AES-256-GCM ciphertext: a random
12-byte nonce, then the ciphertext and its tag, authenticated with the row's place (table, entry, name, dtype,
shape), so that rows cannot be swapped or altered unnoticed. The key is never stored: meta "encryption" holds
the scheme and a key check (a hash that tells the right key from a wrong one). Subject ids, scan ids, sources,
template attributes and failures to enrol stay in clear. `rekey` re-encrypts everything under a new key (or
encrypts a clear store). See docs/security.md for what this does and does not protect.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import secrets
import sqlite3
import stat
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

from facerec3d.errors import FaceRec3DError, InputError
from facerec3d.matching.base import Matcher, Template
from facerec3d.matching.checks import check_template
from facerec3d.matching.registry import restore_state, stored_matcher
from facerec3d.preprocess.pipeline import PreprocessConfig

try:
    import fcntl
except ImportError:  # not Unix (Windows): no service lock, as before
    fcntl = None

FORMAT = "facerec3d-gallery-2"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS entries (
    id INTEGER PRIMARY KEY AUTOINCREMENT, subject TEXT, scan_id TEXT, source TEXT NOT NULL UNIQUE,
    content TEXT UNIQUE, method TEXT NOT NULL, attrs TEXT NOT NULL, nbytes INTEGER NOT NULL, enrolled_at REAL NOT NULL,
    checksum TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS arrays (
    entry INTEGER NOT NULL REFERENCES entries(id) ON DELETE CASCADE, name TEXT NOT NULL,
    dtype TEXT NOT NULL, shape TEXT NOT NULL, data BLOB NOT NULL, checksum TEXT NOT NULL, PRIMARY KEY (entry, name));
CREATE TABLE IF NOT EXISTS model_arrays (name TEXT PRIMARY KEY, dtype TEXT NOT NULL, shape TEXT NOT NULL,
    data BLOB NOT NULL, checksum TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS failures (id INTEGER PRIMARY KEY AUTOINCREMENT, source TEXT NOT NULL UNIQUE,
    reason TEXT NOT NULL, failed_at REAL NOT NULL);
CREATE INDEX IF NOT EXISTS entries_subject ON entries(subject);
"""


class GalleryError(FaceRec3DError):
    """A gallery store cannot be used as asked (missing, not a store, damaged, or made with other settings)."""


class AlreadyEnrolled(GalleryError):
    """The source, or a scan with the same content, is already enrolled."""


class GalleryServed(GalleryError):
    """A gallery service holds the store (`ServeLock`): change it through the service, or stop the service."""


SERVE_LOCK_SUFFIX = ".serve.lock"
_HELD: dict[str, "ServeLock"] = {}  # the serve locks this process holds, by lock file: its own stores write freely


def serve_lock_path(path: str | PathLike) -> Path:
    """The lock file a service holds beside the store (of the file itself, a symbolic link followed)."""
    return Path(os.path.realpath(path) + SERVE_LOCK_SUFFIX)


def _holder(fd: int) -> tuple[str, str | None]:
    """(who, URL or None) of the service a lock file's content names."""
    try:
        record = json.loads(os.pread(fd, 4096, 0) or b"{}")
        pid, url = int(record["pid"]), record.get("url")
        return f"a gallery service (pid {pid}{f', {url}' if url else ''})", url if isinstance(url, str) else None
    except (OSError, ValueError, TypeError, KeyError):  # being written, or damaged
        return "a gallery service", None


def served_by(path: str | PathLike) -> tuple[str, str | None] | None:
    """(who, URL or None) of the gallery service of another process holding the store, or None when none does:
    a shared `flock` on its lock file, taken and let go at once, is refused only while a service lives."""
    lock = serve_lock_path(path)
    if fcntl is None or str(lock) in _HELD:
        return None
    try:
        fd = os.open(lock, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:  # no lock file: never served here
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None  # (let go as the file closes)
    except BlockingIOError:
        return _holder(fd)
    finally:
        os.close(fd)


class ServeLock:
    """A gallery service's hold on its store for its whole life: an exclusive `flock` on G.serve.lock (made with
    mode 0600, and left there: the next service reuses it) with the pid and `url` written in it. While it is held,
    store objects of other processes refuse every write (`GalleryServed`), and a second service is refused
    (`GalleryServed`, after `wait_s`: a writer's check holds the lock shared for an instant). `release`, or the end
    of the process however it ends, lets it go."""

    def __init__(self, path: str | PathLike, url: str | None = None, wait_s: float = 2.0):
        self.path, self.lock_path, self._fd = Path(path), serve_lock_path(path), None
        if fcntl is None:
            return
        try:
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as e:
            raise GalleryError(f"{self.path}: cannot make the service's lock file {self.lock_path} ({e.strerror}); "
                               "the gallery's folder must be writable") from None
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    who, held_url = _holder(fd)
                    os.close(fd)
                    raise GalleryServed(f"{self.path}: {who} serves this gallery already: use it "
                                        f"(--server {held_url or 'URL'}) or stop it first") from None
                time.sleep(0.05)
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps({"pid": os.getpid(), "url": url}).encode() + b"\n")
        self._fd = fd
        _HELD[str(self.lock_path)] = self

    def release(self) -> None:
        """Let the store go."""
        if self._fd is not None:
            _HELD.pop(str(self.lock_path), None)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "ServeLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _forked() -> None:
    """(in a forked child: the service's worker processes) Close the inherited lock files: a `flock` lives while any
    process holds its file open, and a worker outliving a killed service must not keep the store held."""
    for lock in _HELD.values():
        if lock._fd is not None:
            os.close(lock._fd)
            lock._fd = None
    _HELD.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forked)


@dataclass(frozen=True)
class Entry:
    """One enrolled template's row: store id, who, from which file, size (bytes) and time (Unix s)."""

    id: int
    subject: str | None
    scan_id: str | None
    source: str
    nbytes: int
    enrolled_at: float


def _checksum(*parts: str | None, data: bytes = b"") -> str:
    """SHA-256 of text fields (as SQLite's TEXT columns give them back) and bytes."""
    return hashlib.sha256(json.dumps([None if p is None else str(p) for p in parts]).encode() + data).hexdigest()


def encode_array(a: np.ndarray) -> tuple[str, str, bytes, str]:
    """(dtype string, JSON shape, raw C-order bytes, checksum) of a numeric or boolean array."""
    a = np.asarray(a)
    if a.dtype.hasobject or a.dtype.kind not in "biufc":
        raise ValueError(f"cannot store arrays of dtype {a.dtype}")
    dtype, shape, data = a.dtype.str, json.dumps(list(a.shape)), np.ascontiguousarray(a).tobytes()
    return dtype, shape, data, _checksum(dtype, shape, data=data)


def decode_array(dtype: str, shape: str, data: bytes, checksum: str) -> np.ndarray:
    """The writable array of `encode_array`'s output; ValueError (the reason) when the row is damaged."""
    if not isinstance(data, bytes) or _checksum(str(dtype), str(shape), data=data) != checksum:
        raise ValueError("checksum mismatch (damaged bytes)")
    try:
        dims, dt = json.loads(shape), np.dtype(dtype)
    except (TypeError, ValueError):
        raise ValueError(f"bad dtype {dtype!r} or shape {shape!r}"[:200]) from None
    if dt.kind not in "biufc" or not isinstance(dims, list) or not all(type(d) is int and d >= 0 for d in dims) \
            or dt.itemsize * math.prod(dims) != len(data):
        raise ValueError(f"dtype {dtype} and shape {dims} do not fit {len(data)} bytes"[:200])
    return np.frombuffer(bytearray(data), dtype=dt).reshape(dims)


KEY_FILE_ENV = "FACEREC3D_GALLERY_KEY_FILE"  # a file holding the templates' key (64 hex digits)
KEY_ENV = "FACEREC3D_GALLERY_KEY"  # or the key itself
SCHEME = "AES-256-GCM"
_OPEN_KEY_FILES: set[str] = set()  # key files already warned about (`check_key_file_mode`), once per process


def check_key_file_mode(path: str | PathLike) -> None:
    """Warn on stderr, once per file and process, when a key file can be read or written by group or others (as
    ssh does for private keys): the key decrypts every template. A warning, not a refusal: the file is the
    owner's to protect, and file systems without Unix modes (Windows) show none."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return
    if os.name == "posix" and mode & 0o077 and str(path) not in _OPEN_KEY_FILES:
        _OPEN_KEY_FILES.add(str(path))
        print(f"warning: {path}: the gallery key file is open to others (mode {stat.S_IMODE(mode):04o}): "
              f"chmod 600 {path}", file=sys.stderr, flush=True)


class TemplateKey:
    """A 256-bit AES-GCM key for a gallery's arrays: from a file or the environment, never from the store."""

    def __init__(self, key: bytes, source: str = "key"):
        if len(key) != 32:
            raise GalleryError(f"{source}: a gallery key is 32 bytes (64 hex digits), not {len(key)}")
        try:
            from cryptography.hazmat.primitives.ciphers.aead import AESGCM
        except ImportError:
            raise GalleryError("encrypted galleries need the cryptography package: pip install 'facerec3d[crypto]'") \
                from None
        self._aead, self.source = AESGCM(key), source
        self.check = hashlib.sha256(b"facerec3d-gallery-key-check\0" + key).hexdigest()[:32]

    @classmethod
    def from_text(cls, text: str, source: str) -> "TemplateKey":
        try:
            key = bytes.fromhex(text.strip())
        except ValueError:
            raise GalleryError(f"{source}: a gallery key is 64 hex digits") from None
        return cls(key, source)

    @classmethod
    def load(cls, path: str | PathLike) -> "TemplateKey":
        """The key in a file; GalleryError naming the file when it cannot be read or is not a key; a warning when
        others may read it (`check_key_file_mode`)."""
        try:
            text = Path(path).read_text(encoding="ascii")
        except (OSError, UnicodeDecodeError) as e:
            raise GalleryError(f"{path}: cannot read the gallery key ({type(e).__name__})") from None
        check_key_file_mode(path)
        return cls.from_text(text, str(path))

    @classmethod
    def make(cls, path: str | PathLike) -> "TemplateKey":
        """A new random key, written to a new file of mode 0600 (never over an existing one)."""
        text = secrets.token_bytes(32).hex()
        key = cls.from_text(text, str(path))  # (without `cryptography` this fails here, before any file is made)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError as e:
            raise GalleryError(f"{path}: cannot make a key file ({e.strerror})") from None
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(text + "\n")
        return key

    @classmethod
    def from_environment(cls) -> "TemplateKey | None":
        """The key FACEREC3D_GALLERY_KEY_FILE or FACEREC3D_GALLERY_KEY gives, or None when neither is set."""
        path, text = os.environ.get(KEY_FILE_ENV), os.environ.get(KEY_ENV)
        if path and text:
            raise GalleryError(f"set {KEY_FILE_ENV} or {KEY_ENV}, not both")
        if path:
            return cls.load(path)
        return cls.from_text(text, KEY_ENV) if text else None

    def seal(self, data: bytes, place: str) -> bytes:
        """nonce + ciphertext + tag of `data`, bound to its `place`."""
        nonce = secrets.token_bytes(12)
        return nonce + self._aead.encrypt(nonce, data, place.encode())

    def open(self, blob: bytes, place: str) -> bytes:
        """The data `seal` sealed; ValueError when the key is wrong or the bytes or their place were changed."""
        from cryptography.exceptions import InvalidTag

        try:
            return self._aead.decrypt(blob[:12], blob[12:], place.encode())
        except (InvalidTag, ValueError):
            raise ValueError("cannot be decrypted (damaged, moved, or another key)") from None


def _place(table: str, entry: int | None, name: str, dtype: str, shape: str) -> str:
    """What an encrypted array is bound to: swapping rows, or changing their dtype or shape, fails decryption."""
    return json.dumps([table, entry, name, str(dtype), str(shape)])


def _sqlite_errors(method):
    """Errors of SQLite (a locked, damaged or vanished file) become GalleryError naming the store."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except sqlite3.Error as e:
            raise GalleryError(f"{self.path}: {e}") from None

    return wrapper


class GalleryStore:
    """A gallery store file; `create=True` makes a new one (mode 0600) when the file does not exist. `key`: the
    templates' key (default: from the environment, see the module docstring): a `TemplateKey`, or its 64 hex
    digits; an encrypted store needs it."""

    def __init__(self, path: str | PathLike, create: bool = False, key: TemplateKey | str | None = None):
        self.path = Path(path)
        if not self.path.is_file() and not create:
            raise GalleryError(f"{self.path}: no such gallery (enrol into it first)")
        if not create and not self.path.stat().st_size:  # an empty file: not a store, and not made one by a reader
            raise GalleryError(f"{self.path}: an empty file, not a gallery (enrol into it first)")
        if isinstance(key, str):
            key = TemplateKey.from_text(key, "key")
        elif key is not None and not isinstance(key, TemplateKey):
            raise GalleryError(f"key: a TemplateKey or 64 hex digits, not a {type(key).__name__}")
        self.key = key if key is not None else TemplateKey.from_environment()
        if not self.path.exists():
            try:  # made here, so that SQLite's files take this mode: templates are for the owner only
                os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
            except FileExistsError:
                pass
            except OSError as e:
                raise GalleryError(f"{self.path}: cannot make the gallery ({e.strerror})") from None
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None, timeout=30.0)
            tables = {row[0] for row in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if "meta" not in tables:  # another program's database is left as it is (no tables or journal mode added)
                if tables - {"sqlite_sequence"}:
                    raise GalleryError(f"{self.path}: not a gallery store (an SQLite database of other tables: "
                                       f"{', '.join(sorted(tables))[:120]})")
                if not create:
                    raise GalleryError(f"{self.path}: an empty database, not a gallery (enrol into it first)")
            self._db.execute("PRAGMA foreign_keys = ON")
            self._db.execute("PRAGMA journal_mode = WAL")
            fmt = self._meta("format")
            if fmt is None:
                self._db.executescript(_SCHEMA)  # idempotent; executescript commits by itself
                self._db.execute("INSERT OR IGNORE INTO meta VALUES ('format', ?)", (FORMAT,))
            elif fmt != FORMAT:
                raise GalleryError(f"{self.path}: gallery format {fmt!r}, this version reads {FORMAT!r}")
            self._check_key()
            self._binding = self._meta("binding")  # the settings this object enrols under (see `bind`)
        except (sqlite3.DatabaseError, GalleryError) as e:
            if hasattr(self, "_db"):
                self._db.close()
            if isinstance(e, GalleryError):
                raise
            raise GalleryError(f"{self.path}: not a gallery store ({e})") from None

    def _check_key(self) -> None:
        """Refuse a key that is not the store's, or no key for an encrypted store; an empty clear store given a
        key becomes encrypted; a clear store with arrays given a key is refused (encrypt it with rekey)."""
        encryption = self._meta("encryption")
        if encryption is None:
            if self.key is None:
                return
            if self._db.execute("SELECT (SELECT COUNT(*) FROM arrays) + (SELECT COUNT(*) FROM model_arrays)").fetchone()[0]:
                raise GalleryError(f"{self.path}: the gallery's templates are not encrypted, but a key is given "
                                   f"({self.key.source}): encrypt them first (facerec3d gallery {self.path} rekey "
                                   f"--new-key-file FILE), or unset {KEY_FILE_ENV} and {KEY_ENV}")
            with self._transaction():
                self._db.execute("INSERT OR REPLACE INTO meta VALUES ('encryption', ?)",
                                 (json.dumps({"scheme": SCHEME, "key_check": self.key.check}),))
            return
        try:
            check = json.loads(encryption)["key_check"]
        except (ValueError, TypeError, KeyError):
            raise GalleryError(f"{self.path}: damaged encryption settings") from None
        if self.key is None:
            raise GalleryError(f"{self.path}: the gallery's templates are encrypted: give its key "
                               f"({KEY_FILE_ENV}=FILE, or {KEY_ENV})")
        if self.key.check != check:
            raise GalleryError(f"{self.path}: the key given ({self.key.source}) is not the gallery's key")

    @property
    def encrypted(self) -> bool:
        return self._meta("encryption") is not None

    def _stored(self, encoded: tuple[str, str, bytes, str], table: str, entry: int | None,
                name: str) -> tuple[str, str, str, bytes, str]:
        """(name, dtype, shape, stored bytes, checksum of what is stored) of an `encode_array` output: encrypted
        with a key, bound to its place."""
        dtype, shape, data, checksum = encoded
        if self.key is not None:
            data = self.key.seal(data, _place(table, entry, name, dtype, shape))
            checksum = _checksum(dtype, shape, data=data)
        return name, dtype, shape, data, checksum

    def _loaded(self, table: str, entry: int | None, name: str, dtype: str, shape: str, data: bytes,
                checksum: str) -> np.ndarray:
        """The array of a row `_stored` made; ValueError (the reason) when it is damaged or cannot be decrypted."""
        if self.key is None:
            return decode_array(dtype, shape, data, checksum)
        if not isinstance(data, bytes) or _checksum(str(dtype), str(shape), data=data) != checksum:
            raise ValueError("checksum mismatch (damaged bytes)")
        plain = self.key.open(data, _place(table, entry, name, dtype, shape))
        return decode_array(dtype, shape, plain, _checksum(str(dtype), str(shape), data=plain))

    @_sqlite_errors
    def check_writable(self) -> None:
        """Refuse a store that cannot be written (read-only file or folder, or a read-only file system)."""
        st = self.path.stat()
        if not st.st_mode & stat.S_IWUSR or not os.access(self.path, os.W_OK):
            raise GalleryError(f"{self.path}: the gallery is read-only (mode {stat.filemode(st.st_mode)}); make it "
                               "writable (chmod u+w) or serve a copy")
        if not os.access(self.path.parent, os.W_OK | os.X_OK):
            raise GalleryError(f"{self.path}: its folder is read-only (SQLite writes its journal beside the file)")
        try:
            with self._transaction():  # a write that is rolled back: fails on a read-only file system
                version = self._db.execute("PRAGMA user_version").fetchone()[0]
                self._db.execute(f"PRAGMA user_version = {int(version)}")
        except sqlite3.OperationalError as e:
            raise GalleryError(f"{self.path}: the gallery cannot be written ({e})") from None

    @_sqlite_errors
    def rekey(self, new: TemplateKey) -> int:
        """Re-encrypt every array under key `new` (encrypting a clear store), in one transaction, then rewrite the
        file so that no old bytes are left in it; returns the number of arrays. The old key is the store's."""
        with self._transaction():
            self._db.execute("PRAGMA secure_delete = ON")
            n = 0
            for table, key_col in (("arrays", "entry"), ("model_arrays", None)):
                rows = self._db.execute(f"SELECT {key_col or 'NULL'}, name, dtype, shape, data, checksum FROM {table}"
                                        ).fetchall()
                for entry, name, dtype, shape, data, checksum in rows:
                    try:
                        a = self._loaded(table, entry, name, dtype, shape, data, checksum)
                    except ValueError as e:
                        raise GalleryError(f"{self.path}: {table} row {entry} {name!r} is damaged: {e}") from None
                    old, self.key = self.key, new
                    try:
                        *_, sealed, sealed_checksum = self._stored(encode_array(a), table, entry, name)
                    finally:
                        self.key = old
                    where = "name = ?" + (f" AND {key_col} = ?" if key_col else "")
                    self._db.execute(f"UPDATE {table} SET data = ?, checksum = ? WHERE {where}",
                                     (sealed, sealed_checksum, name, *([entry] if key_col else [])))
                    n += 1
            self._db.execute("INSERT OR REPLACE INTO meta VALUES ('encryption', ?)",
                             (json.dumps({"scheme": SCHEME, "key_check": new.check}),))
        self.key = new
        self._db.execute("VACUUM")  # the old ciphertext (or clear text) leaves the file ...
        self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")  # ... and the write-ahead log
        return n

    # ------------------------------------------------------------------ plumbing
    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> "GalleryStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextmanager
    def _transaction(self) -> Iterator[None]:
        """A write transaction (every write is one): refused (GalleryServed) while a service of another process
        holds the store. Checked holding SQLite's write lock, so a service starting meanwhile waits for this
        transaction (its first write, `check_writable`) before it loads the gallery, and sees it."""
        self._db.execute("BEGIN IMMEDIATE")
        try:
            if (held := served_by(self.path)) is not None:
                who, url = held
                raise GalleryServed(f"{self.path}: {who} holds this gallery: change it through the service "
                                    f"(--server {url or 'URL'}), or stop the service first")
            yield
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def _meta(self, key: str) -> str | None:
        try:
            row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        except sqlite3.OperationalError as e:  # a new file: no tables yet
            if "no such table" in str(e):
                return None
            raise
        return None if row is None else row[0]

    # ------------------------------------------------------------------ settings
    @_sqlite_errors
    def bind(self, preprocess: PreprocessConfig, matcher: Matcher) -> None:
        """Record the preprocessing and matcher settings in a new store, or check that they are the stored ones.
        A store with no entries takes other settings as a new one would (a first enrolment whose every scan
        failed does not tie the store to its method): the old settings, learnt arrays and calibrated threshold
        (in the old method's scores) are replaced; the failures to enrol stay."""
        with self._transaction():  # one writer at a time: two enrolments into a new store bind it once
            if self._meta("method") is None or not self._has_entries() and not self._same(preprocess, matcher):
                self._record_settings(preprocess, matcher)
                return
            self._binding = self._meta("binding")
        self.check_preprocess(preprocess)
        self.check_matcher(matcher)

    def _has_entries(self) -> bool:
        return self._db.execute("SELECT EXISTS (SELECT 1 FROM entries)").fetchone()[0] == 1

    def _same(self, preprocess: PreprocessConfig, matcher: Matcher) -> bool:
        """Whether these are the stored settings (damaged ones are not)."""
        try:
            self.check_preprocess(preprocess)
            self.check_matcher(matcher)
        except (GalleryError, ValueError):
            return False
        return True

    def _record_settings(self, preprocess: PreprocessConfig, matcher: Matcher) -> None:
        """(in a transaction) Replace the store's settings, learnt arrays and threshold with these, under a new
        binding id: store objects that enrolled under the old one can add no more (`add`)."""
        arrays, attrs = matcher.state()
        self._db.execute("DELETE FROM meta WHERE key IN ('preprocess', 'method', 'options', 'state', 'binding', "
                         "'threshold')")
        self._db.execute("DELETE FROM model_arrays")
        self._binding = secrets.token_hex(16)
        self._db.executemany("INSERT INTO meta VALUES (?, ?)", [
            ("preprocess", preprocess.fingerprint()), ("method", matcher.name),
            ("options", json.dumps(matcher.options(), sort_keys=True)),
            ("state", json.dumps(attrs, sort_keys=True)), ("binding", self._binding)])
        self._db.executemany("INSERT INTO model_arrays VALUES (?, ?, ?, ?, ?)",
                             [self._stored(encode_array(a), "model_arrays", None, name)
                              for name, a in arrays.items()])

    @_sqlite_errors
    def preprocess_config(self) -> PreprocessConfig:
        """The preprocessing settings the gallery was enrolled with."""
        try:
            return PreprocessConfig.from_dict(json.loads(self._require("preprocess")), self.path)
        except ValueError as e:  # not JSON, or settings this version refuses
            raise GalleryError(f"{self.path}: damaged preprocessing settings ({e})") from None

    @_sqlite_errors
    def check_preprocess(self, preprocess: PreprocessConfig) -> None:
        """Refuse scans preprocessed with settings other than the gallery's."""
        stored = self.preprocess_config()  # as this version reads them: settings added since take their defaults
        if preprocess.fingerprint() != stored.fingerprint():
            diff = sorted(_differences(stored.to_dict(), preprocess.to_dict()))
            raise GalleryError(f"{self.path}: the probe is preprocessed differently from the gallery "
                               f"(differs in {', '.join(diff)}); use the gallery's settings")

    @_sqlite_errors
    def check_matcher(self, matcher: Matcher) -> None:
        """Refuse a matcher whose method or options are not the gallery's."""
        method, options = self._require("method"), self._settings("options")
        given = json.loads(json.dumps(matcher.options()))
        if matcher.name != method:
            raise GalleryError(f"{self.path}: the gallery was enrolled with method {method!r}, not "
                               f"{matcher.name!r}; leave out --method to use the gallery's, or enrol into a new "
                               "gallery file")
        if given != options:
            diff = "; ".join(f"{k}: {_field(options, k)!r} in the gallery, {_field(given, k)!r} given"
                             for k in sorted(_differences(options, given)))
            raise GalleryError(f"{self.path}: the gallery was enrolled with method {method!r} and other options "
                               f"({diff}); leave out --method-config to use the gallery's, or enrol into a new "
                               "gallery file")

    @_sqlite_errors
    def matcher(self) -> Matcher:
        """The matcher the gallery was enrolled with (method, options and what it learnt)."""
        try:
            matcher = stored_matcher(self._require("method"), self._settings("options"))
        except GalleryError:
            raise
        except (FaceRec3DError, ValueError, TypeError) as e:  # an unknown method, options this version refuses
            raise GalleryError(f"{self.path}: damaged method settings ({e})") from None
        arrays = {}
        for name, *rest in self._db.execute("SELECT name, dtype, shape, data, checksum FROM model_arrays"):
            try:
                arrays[name] = self._loaded("model_arrays", None, name, *rest)
            except ValueError as e:
                raise GalleryError(f"{self.path}: the matcher's learnt array {name!r} is damaged: {e}") from None
        state = self._settings("state")
        if arrays or state:
            restore_state(matcher, arrays, state,
                          lambda why: GalleryError(f"{self.path}: the matcher's learnt state is not usable: {why}"))
        return matcher

    def _settings(self, key: str) -> dict:
        """A stored JSON table of settings (the matcher's `options`, its learnt `state`); GalleryError naming the
        store when it is not one."""
        try:
            value = json.loads(self._require(key))
        except (ValueError, RecursionError) as e:
            raise GalleryError(f"{self.path}: damaged {key} setting (not JSON: {e})") from None
        if not isinstance(value, dict):
            raise GalleryError(f"{self.path}: damaged {key} setting (a {type(value).__name__}, not a table)")
        return value

    def _require(self, key: str) -> str:
        value = self._meta(key)
        if value is None:
            raise GalleryError(f"{self.path}: empty gallery (nothing enrolled yet)")
        return value

    @_sqlite_errors
    def set_threshold(self, record: dict) -> None:
        """Record the gallery's calibrated verification threshold (`evaluation.calibrate`): a JSON object with at
        least a finite "value", and how it was chosen."""
        if not isinstance(record.get("value"), float) or not math.isfinite(record["value"]):
            raise ValueError(f"a threshold record needs a finite float 'value', not {record.get('value')!r}")
        with self._transaction():
            self._db.execute("INSERT OR REPLACE INTO meta VALUES ('threshold', ?)", (json.dumps(record, sort_keys=True),))

    @_sqlite_errors
    def threshold(self) -> dict | None:
        """The calibrated verification threshold's record (`set_threshold`), or None when none was calibrated."""
        value = self._meta("threshold")
        if value is None:
            return None
        try:
            record = json.loads(value)
            if not math.isfinite(float(record["value"])):
                raise ValueError("not finite")
        except (ValueError, TypeError, KeyError, RecursionError) as e:
            raise GalleryError(f"{self.path}: damaged threshold record ({e})") from None
        return record

    # ------------------------------------------------------------------ entries
    @_sqlite_errors
    def add(self, template: Template, source: str, content: str | None = None) -> int:
        """Store one template (one transaction) and clear the source's failure to enrol, if any; returns its
        id. `content`: a hash of the scan file's bytes. AlreadyEnrolled when the source, or the content, is. The
        template must name its person: `Matcher.enroll` takes the scan's subject (`FaceScan.meta.subject`), which
        a depth frame or mesh does not know, so set `template.subject` first (`enroll_scans` does: it reads the
        subjects from folders and manifests)."""
        if not isinstance(template.subject, str) or not template.subject:
            raise GalleryError(f"{source}: a template needs its subject to be enrolled, not {template.subject!r} "
                               "(set template.subject)")
        encoded = {name: encode_array(a) for name, a in template.arrays.items()}
        with self._transaction():
            if self._meta("binding") != self._binding:  # an empty store was given other settings meanwhile
                raise GalleryError(f"{self.path}: the gallery's settings were replaced (now method "
                                   f"{self._meta('method')!r}) by another enrolment while it was empty; enrol again")
            held = self._meta("method") or next(iter(self._db.execute("SELECT method FROM entries LIMIT 1")), [None])[0]
            if held is not None and held != template.method:  # a store holds one method's templates
                raise GalleryError(f"{source}: a {template.method!r} template, and {self.path} holds {held!r} ones")
            twin = self._db.execute("SELECT id, source FROM entries WHERE source = ? OR content = ?",
                                    (source, content)).fetchone()
            if twin is not None:
                same = "" if twin[1] == source else f" (the same scan as {twin[1]})"
                raise AlreadyEnrolled(f"{source}: already enrolled in {self.path} as entry {twin[0]}{same}")
            fields = (template.subject, template.scan_id, source, template.method, json.dumps(template.attrs))
            cur = self._db.execute(
                "INSERT INTO entries (subject, scan_id, source, method, attrs, content, nbytes, enrolled_at, checksum) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", (*fields, content, template.nbytes, time.time(), _checksum(*fields)))
            entry = cur.lastrowid
            self._db.executemany("INSERT INTO arrays VALUES (?, ?, ?, ?, ?, ?)",
                                 [(entry, *self._stored(e, "arrays", entry, name)) for name, e in encoded.items()])
            self._db.execute("DELETE FROM failures WHERE source = ?", (source,))
        return int(entry)

    @_sqlite_errors
    def add_failure(self, source: str, reason: str) -> None:
        """Record a failure to enrol (the scan could not be read or preprocessed): the source's latest one."""
        with self._transaction():
            self._db.execute("INSERT INTO failures (source, reason, failed_at) VALUES (?, ?, ?) ON CONFLICT (source) "
                             "DO UPDATE SET reason = excluded.reason, failed_at = excluded.failed_at",
                             (source, reason, time.time()))

    @_sqlite_errors
    def sources(self) -> set[str]:
        """The sources (file paths) already enrolled."""
        return {r[0] for r in self._db.execute("SELECT source FROM entries")}

    @_sqlite_errors
    def contents(self) -> dict[int, str | None]:
        """Each entry's content hash (SHA-256 of the scan file or upload it was enrolled from), by entry id."""
        return dict(self._db.execute("SELECT id, content FROM entries"))

    @_sqlite_errors
    def entries(self, subject: str | None = None) -> list[Entry]:
        """Entries in enrolment order (of one subject when given)."""
        sql = "SELECT id, subject, scan_id, source, nbytes, enrolled_at FROM entries"
        rows = self._db.execute(sql + (" WHERE subject = ?" if subject is not None else "") + " ORDER BY id",
                                () if subject is None else (subject,))
        return [Entry(*r) for r in rows]

    @_sqlite_errors
    def templates(self, entries: Sequence[Entry] | None = None) -> list[Template]:
        """The templates of these entries (default all), in the same order, each checked (its arrays' checksums,
        and what compiled matching relies on); GalleryError naming the entry when one is damaged."""
        entries = self.entries() if entries is None else entries
        out = []
        for e in entries:
            method, attrs, checksum = self._db.execute("SELECT method, attrs, checksum FROM entries WHERE id = ?",
                                                       (e.id,)).fetchone()
            rows = self._db.execute("SELECT name, dtype, shape, data, checksum FROM arrays WHERE entry = ?", (e.id,))
            try:
                what = "entry"
                if _checksum(e.subject, e.scan_id, e.source, method, attrs) != checksum:
                    raise ValueError("checksum mismatch (damaged subject, scan id, source, method or attributes)")
                arrays = {}
                for name, *rest in rows:
                    what = f"array {name!r}"
                    arrays[name] = self._loaded("arrays", e.id, name, *rest)
                what = "template"
                template = Template(e.subject, e.scan_id, method, arrays, json.loads(attrs))
                check_template(template)
            except ValueError as error:
                raise GalleryError(f"{self.path}: entry {e.id} (subject {e.subject}, scan {e.scan_id}, {e.source}) is "
                                   f"damaged: {what}: {error}; remove it (gallery {self.path} remove --entry {e.id}) "
                                   "and enrol its scan again") from None
            out.append(template)
        return out

    @_sqlite_errors
    def remove(self, ident: str | None = None, entry: int | None = None) -> int:
        """Delete the entries `removal` picks (subject `ident`'s, or else the scan `ident`, or else entry id `entry`);
        returns how many (0 when none matches); GalleryError when `ident` is a scan id of several subjects. InputError,
        nothing deleted, for both `ident` and `entry` (as the command line: the entry may be another subject's) or
        an entry id that is not a whole number (`entry="3"` matched nothing)."""
        if ident is not None and entry is not None:
            raise InputError(f"{self.path}: remove a subject or scan id ({ident!r}) or an entry id ({entry!r}), not "
                             "both: the entry may be another subject's")
        if entry is not None and (isinstance(entry, bool) or not isinstance(entry, (int, np.integer))):
            raise InputError(f"{self.path}: an entry id is a whole number (the first column of gallery {self.path} "
                             f"list), not {entry!r}")
        if ident is not None and not isinstance(ident, str):
            raise InputError(f"{self.path}: a subject or scan id is a text, not {ident!r}")
        with self._transaction():
            try:
                ids = [e.id for e in removal(self.entries(), ident, entry)]
            except ValueError as e:
                raise GalleryError(f"{self.path}: {e} (gallery {self.path} remove --entry ID; the ids: gallery "
                                   f"{self.path} list)") from None
            self._db.executemany("DELETE FROM entries WHERE id = ?", [(i,) for i in ids])
        return len(ids)

    @_sqlite_errors
    def failures(self) -> list[tuple[str, str]]:
        """(source, reason) of each recorded failure to enrol."""
        return list(self._db.execute("SELECT source, reason FROM failures ORDER BY id"))

    @_sqlite_errors
    def stats(self) -> dict:
        """Counts, sizes and settings of the gallery."""
        n, subjects, nbytes = self._db.execute(
            "SELECT COUNT(*), COUNT(DISTINCT subject), COALESCE(SUM(nbytes), 0) FROM entries").fetchone()
        return {"entries": n, "subjects": subjects, "template_bytes": nbytes,
                "file_bytes": self.path.stat().st_size, "failures_to_enrol": len(self.failures()),
                "method": self._meta("method"), "options": self._settings("options") if self._meta("options") else None,
                "threshold": self.threshold()}


def removal(entries: Sequence[Entry], ident: str | None, entry: int | None) -> list[Entry]:
    """The entries a removal means: with `entry`, the entry of that id; else subject `ident`'s entries, or else those
    of scan id `ident` when they are one subject's. A scan id shared by several subjects (every depth-camera person
    has a `front_1`) is refused (ValueError, the reason), never taken as all of them."""
    if entry is not None:
        return [e for e in entries if e.id == entry]
    if not ident:
        raise ValueError("a removal names a subject, a scan id or an entry id")
    chosen = [e for e in entries if e.subject == ident] or [e for e in entries if e.scan_id == ident]
    if len(subjects := {e.subject for e in chosen}) > 1:
        raise ValueError(f"scan {ident!r} names {len(chosen)} entries of {len(subjects)} subjects; remove one by its "
                         "entry id")
    return chosen


def _field(d: dict, dotted: str):
    """The value at a dotted name of nested dicts (None where a level is missing)."""
    for key in dotted.split("."):
        d = d.get(key) if isinstance(d, dict) else None
    return d


def _differences(a, b, prefix: str = "") -> Iterator[str]:
    """Dotted names of the fields where two nested dicts differ."""
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            yield from _differences(x, y, f"{prefix}{key}.")
        elif x != y:
            yield f"{prefix}{key}"
