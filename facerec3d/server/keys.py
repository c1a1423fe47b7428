"""API keys for the gallery service: a JSON file of key names, scopes and SHA-256 hashes (never the keys).

    key = add_key("keys.json", "gate-3", ["query"])   # shown once; only its hash is written
    keys = KeyFile("keys.json"); keys.authenticate(key)  # -> ApiKey("gate-3", frozenset({"query"}))

A key is "fr3d_" + 43 URL-safe characters (32 random bytes from `secrets`): with 256 bits of entropy a
plain SHA-256 cannot be brute-forced, so no slow password hash is needed and checking a key costs a
microsecond. The file is written atomically (a temporary file renamed over it) with mode 0600, and a
running service picks up changes at the next request: a key removed, or the whole file deleted, no longer
works (each reload is logged). A changed file that cannot be read (an edit half done, a typo) lets no key in
until it can (the service answers 503), and the log says so: keeping the keys last read kept a removed key working.

File format: {"format": "facerec3d-keys-1", "keys": [{"name", "scopes": [...], "sha256", "created"}]}
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import secrets
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from facerec3d.errors import FaceRec3DError

FORMAT = "facerec3d-keys-1"
PREFIX = "fr3d_"
#: enrol: add scans to the gallery; query: identify and verify; admin: list and remove subjects, metrics.
SCOPES = ("enrol", "query", "admin")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")  # (fullmatch)
log = logging.getLogger("facerec3d.server")


class KeyFileError(FaceRec3DError):
    """A key file cannot be read or changed as asked."""


@dataclass(frozen=True)
class ApiKey:
    """Who a key belongs to and what it may do."""

    name: str
    scopes: frozenset[str]


def key_hash(key: str) -> str:
    """The hex SHA-256 of a key (what the file stores)."""
    return hashlib.sha256(key.encode("utf-8", "surrogateescape")).hexdigest()


def parse_scopes(text: str | list[str] | tuple[str, ...]) -> list[str]:
    """Scopes from "enrol,query" (or a list), checked and in canonical order."""
    items = [s.strip() for s in (text.split(",") if isinstance(text, str) else text) if s.strip()]
    if not items:
        raise KeyFileError(f"no scopes given (use some of {', '.join(SCOPES)})")
    unknown = sorted(set(items) - set(SCOPES))
    if unknown:
        raise KeyFileError(f"unknown scope {', '.join(unknown)} (use some of {', '.join(SCOPES)})")
    return [s for s in SCOPES if s in items]


def read_keys(path: str | os.PathLike) -> list[dict]:
    """The key records of a key file ([] when it does not exist)."""
    p = Path(path)
    if not p.exists():
        return []
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise KeyFileError(f"{p}: not a key file ({e})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("keys"), list):
        raise KeyFileError(f"{p}: not a key file (expected format {FORMAT!r})")
    out = []
    for i, k in enumerate(data["keys"]):
        if not (isinstance(k, dict) and isinstance(k.get("name"), str) and isinstance(k.get("sha256"), str)
                and re.fullmatch(r"[0-9a-f]{64}", k["sha256"]) and isinstance(k.get("scopes"), list)):
            raise KeyFileError(f"{p}: key record {i} is malformed (needs name, scopes, sha256)")
        parse_scopes(k["scopes"])
        out.append(k)
    return out


def _write(path: Path, records: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".keys-", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump({"format": FORMAT, "keys": records}, f, indent=1)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o600)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def add_key(path: str | os.PathLike, name: str, scopes: str | list[str]) -> str:
    """Make a new key NAME with these scopes in the key file (made if missing); returns the key, which is not
    stored anywhere (only its hash)."""
    if not _NAME.fullmatch(name):
        raise KeyFileError(f"bad key name {name!r}: 1-64 letters, digits, '.', '_', '@' or '-'")
    scopes = parse_scopes(scopes)
    records = read_keys(path)
    if any(k["name"] == name for k in records):
        raise KeyFileError(f"{path}: a key named {name!r} exists (remove it first)")
    key = PREFIX + secrets.token_urlsafe(32)
    records.append({"name": name, "scopes": scopes, "sha256": key_hash(key),
                    "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
    _write(Path(path), records)
    return key


def remove_key(path: str | os.PathLike, name: str) -> None:
    """Delete key NAME from the key file."""
    records = read_keys(path)
    kept = [k for k in records if k["name"] != name]
    if len(kept) == len(records):
        raise KeyFileError(f"{path}: no key named {name!r}")
    _write(Path(path), kept)


class KeyFile:
    """A key file as a running service reads it: reloaded when it changes on disk.

    A changed file that cannot be read (an edit half done, a JSON typo) fails closed: no key works (`unreadable`
    says why, and the service answers 503) until the file reads again, since keeping the keys last read would
    keep a key just removed working, unsaid. Each such change is logged in one line naming the file and the reason.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._lock = threading.Lock()
        self._stamp: tuple | None = None
        self._loaded = False  # the first load is not a change; every later one (a file put back too) is logged
        self._keys: dict[str, ApiKey] = {}
        self.unreadable: str | None = None  # why the file, changed, cannot be read (no key works meanwhile)
        self._load()
        if not self._keys:
            raise KeyFileError(f"{self.path}: no keys (make one: facerec3d keys add NAME --scopes "
                               f"enrol,query,admin --keys {self.path})")

    def _load(self) -> None:
        try:
            st = self.path.stat()
        except FileNotFoundError:
            raise KeyFileError(f"{self.path}: no such key file (make one: facerec3d keys add NAME --scopes "
                               f"enrol,query,admin --keys {self.path})") from None
        stamp = (st.st_mtime_ns, st.st_size, st.st_ino)
        if stamp == self._stamp:
            return
        with self._lock:
            records = read_keys(self.path)
            keys = {k["sha256"]: ApiKey(k["name"], frozenset(k["scopes"])) for k in records}
            if self._loaded:
                log.warning("facerec3d service: key file %s changed: %d keys (%s)", self.path, len(keys),
                            ", ".join(sorted(k.name for k in keys.values()))[:500])
            if os.name == "posix" and st.st_mode & 0o022:  # hashes are no secret, but whoever can write adds keys
                log.warning("facerec3d service: key file %s can be written by group or others (mode %04o): anyone "
                            "who can write it can add a key; chmod 600 %s", self.path, st.st_mode & 0o7777, self.path)
            self._keys, self._stamp, self.unreadable, self._loaded = keys, stamp, None, True

    def _reload(self) -> None:
        """Reload the file if it changed; once it is gone, or while it cannot be read, no key works."""
        try:
            self._load()
        except (KeyFileError, OSError) as e:
            with self._lock:
                if not self.path.exists():  # deleted: every key is revoked
                    if self._keys:
                        log.warning("facerec3d service: key file %s removed: all %d keys revoked", self.path,
                                    len(self._keys))
                    self._keys, self._stamp, self.unreadable = {}, None, None
                    return
                try:
                    st = self.path.stat()
                    stamp = (st.st_mtime_ns, st.st_size, st.st_ino)
                except OSError:
                    stamp = None
                reason = str(e)  # names the file
                if (stamp, reason) != (self._stamp, self.unreadable):  # once per change, not at every request
                    log.warning("facerec3d service: %s: no key works until the key file can be read", reason)
                self._keys, self._stamp, self.unreadable = {}, stamp, reason

    def authenticate(self, key: str | None) -> ApiKey | None:
        """The key's owner and scopes, or None for a missing or unknown key (every key, once the file is gone or
        while it cannot be read: see `unreadable`)."""
        if not key:
            return None
        self._reload()
        # a lookup by hash: its timing depends on the hash of the guess, which tells nothing about a real key
        return self._keys.get(key_hash(key))
