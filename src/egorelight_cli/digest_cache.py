"""Payload digests (sha256), remembered within a process and across runs, so that a cached no-op
does not re-hash a gigabyte capture.

Every stage verifies the sha256 of the payloads it reads against their manifests
(:meth:`~egorelight_cli.artifacts.Artifact.verify`). Within a process a digest is remembered by the
file's identity; this module also keeps it on disk, in an SQLite file under the user's cache folder
(``$EGORELIGHT_CACHE_DIR``, else ``$XDG_CACHE_HOME/egorelight``, else ``~/.cache/egorelight``;
``EGORELIGHT_CACHE_DIR=off`` turns it off).

A record is keyed by the file's real path and its ``stat`` identity: device, inode, size,
``mtime_ns`` and ``ctime_ns``. Any write to the file changes its mtime and ctime, and the ctime
cannot be set back by a user tool (``touch -r``, ``cp -p`` and ``os.utime`` restore the mtime
only), so an edited, truncated or replaced payload misses the record and is hashed again. A file
whose timestamps are less than :data:`SETTLE_S` old when it is hashed is not recorded: a second
write within the same timestamp tick could leave its stat unchanged (git's "racy clean" case).

It also remembers which manifests (by the sha256 of their bytes) passed schema validation
against which schemas (:meth:`DigestCache.validated`): a capture's manifest lists thousands of
payloads and takes longer to validate than to read.

The cache is an accelerator only: any failure to open, read or write it (a read-only home, a
locked or corrupt database) falls back to hashing, silently.
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
import time
from pathlib import Path

#: seconds a file's mtime and ctime must lie in the past before its digest is recorded
SETTLE_S = 2.0
DB_NAME = "digests.sqlite"


def cache_dir() -> Path | None:
    """The folder of the persistent digest cache, or None when it is turned off."""
    explicit = os.environ.get("EGORELIGHT_CACHE_DIR")
    if explicit is not None:
        return None if explicit.strip().lower() in ("", "off", "0", "none") else Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "egorelight"


def _identity(stat: os.stat_result) -> tuple[int, int, int, int, int]:
    return (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns)


class DigestCache:
    """``get``/``put`` of sha256 digests by (real path, stat identity) in one SQLite file."""

    def __init__(self, folder: Path | None):
        self._db: sqlite3.Connection | None = None
        if folder is None:
            return
        try:
            folder.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(str(folder / DB_NAME), timeout=2.0, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("CREATE TABLE IF NOT EXISTS digests (path TEXT PRIMARY KEY, identity TEXT NOT NULL, "
                             "digest TEXT NOT NULL)")
            self._db.execute("CREATE TABLE IF NOT EXISTS validated (manifest TEXT NOT NULL, schemas TEXT NOT NULL, "
                             "PRIMARY KEY (manifest, schemas))")
        except (OSError, sqlite3.Error):
            self._db = None

    @property
    def enabled(self) -> bool:
        return self._db is not None

    def get(self, path: str, stat: os.stat_result) -> str | None:
        """The recorded digest of ``path`` when its stat identity is the recorded one."""
        if self._db is None:
            return None
        try:
            row = self._db.execute("SELECT identity, digest FROM digests WHERE path = ?", (path,)).fetchone()
        except sqlite3.Error:
            return None
        return row[1] if row is not None and row[0] == repr(_identity(stat)) else None

    def put(self, path: str, stat: os.stat_result, digest: str) -> bool:
        """Record ``digest`` for ``path`` unless the file is too fresh (see the module docstring)."""
        if self._db is None or time.time_ns() - max(stat.st_mtime_ns, stat.st_ctime_ns) < SETTLE_S * 1e9:
            return False
        try:
            self._db.execute("INSERT OR REPLACE INTO digests VALUES (?, ?, ?)", (path, repr(_identity(stat)), digest))
        except sqlite3.Error:
            return False
        return True


    def validated(self, manifest_digest: str, schemas_digest: str) -> bool:
        """Whether a manifest with these bytes passed validation against these schemas before."""
        if self._db is None:
            return False
        try:
            return self._db.execute("SELECT 1 FROM validated WHERE manifest = ? AND schemas = ?",
                                    (manifest_digest, schemas_digest)).fetchone() is not None
        except sqlite3.Error:
            return False

    def mark_validated(self, manifest_digest: str, schemas_digest: str) -> None:
        if self._db is None:
            return
        try:
            self._db.execute("INSERT OR IGNORE INTO validated VALUES (?, ?)", (manifest_digest, schemas_digest))
        except sqlite3.Error:
            pass


_CACHES: dict[tuple, DigestCache] = {}


def persistent_cache() -> DigestCache:
    """The process's :class:`DigestCache` for the current :func:`cache_dir` (opened once per
    setting of the variables that choose it)."""
    setting = tuple(os.environ.get(name) for name in ("EGORELIGHT_CACHE_DIR", "XDG_CACHE_HOME", "HOME"))
    if setting not in _CACHES:
        _CACHES[setting] = DigestCache(cache_dir())
    return _CACHES[setting]


# ---------------------------------------------------------------------------------- hashing
def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """``"sha256:<hex>"`` of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return "sha256:" + digest.hexdigest()


_DIGEST_CACHE: dict[tuple, str] = {}


def cached_sha256_file(path: str | Path) -> str:
    """:func:`sha256_file`, remembered by (path, device, inode, size, mtime_ns, ctime_ns): a
    file verified once is not hashed again unless it changed on disk; for this process, and across
    runs in the :func:`persistent_cache`."""
    stat = os.stat(path)
    absolute = os.path.abspath(path)  # the stat identity (device, inode) names the file; this is the record's key
    key = (absolute, stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns)
    if key not in _DIGEST_CACHE:
        cache = persistent_cache()
        digest = cache.get(absolute, stat)
        if digest is None:
            digest = sha256_file(path)
            cache.put(absolute, stat, digest)
        _DIGEST_CACHE[key] = digest
    return _DIGEST_CACHE[key]
