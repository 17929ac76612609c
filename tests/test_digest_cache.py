"""The persistent payload digest cache (digest_cache.py): it survives the process, and any change to
a file, even one that restores its mtime, makes it hash the file again."""

from __future__ import annotations

import os
import time

import pytest

from egorelight_cli import artifacts, digest_cache
from egorelight_cli.digest_cache import DigestCache


@pytest.fixture
def settled(monkeypatch):
    """Files count as settled at once (the real cache waits SETTLE_S seconds after a write)."""
    monkeypatch.setattr(digest_cache, "SETTLE_S", 0.0)


def _write(path, data: bytes):
    path.write_bytes(data)
    time.sleep(0.05)  # past the filesystem's timestamp tick
    return os.stat(path)


def test_a_digest_persists_across_connections(tmp_path, settled):
    payload = tmp_path / "payload.bin"
    stat = _write(payload, b"x" * 1000)
    assert DigestCache(tmp_path / "cache").put(str(payload), stat, "sha256:abc")
    assert DigestCache(tmp_path / "cache").get(str(payload), stat) == "sha256:abc"  # a new process's connection


def test_an_edit_that_restores_the_mtime_is_still_seen(tmp_path, settled):
    payload = tmp_path / "payload.bin"
    before = _write(payload, b"a" * 1000)
    cache = DigestCache(tmp_path / "cache")
    cache.put(str(payload), before, "sha256:old")
    payload.write_bytes(b"b" * 1000)  # same size
    os.utime(payload, ns=(before.st_atime_ns, before.st_mtime_ns))  # mtime set back, as `touch -r` would
    after = os.stat(payload)
    assert after.st_mtime_ns == before.st_mtime_ns and after.st_size == before.st_size
    assert cache.get(str(payload), after) is None


def test_a_freshly_written_file_is_not_recorded(tmp_path):
    payload = tmp_path / "payload.bin"
    payload.write_bytes(b"fresh")
    cache = DigestCache(tmp_path / "cache")
    assert not cache.put(str(payload), os.stat(payload), "sha256:abc")  # a second write could keep its stat
    assert cache.get(str(payload), os.stat(payload)) is None


def test_cached_sha256_file_hashes_once_across_processes(tmp_path, settled, monkeypatch):
    monkeypatch.setenv("EGORELIGHT_CACHE_DIR", str(tmp_path / "cache"))
    payload = tmp_path / "payload.bin"
    _write(payload, os.urandom(4096))
    truth = digest_cache.sha256_file(payload)
    calls = []
    monkeypatch.setattr(digest_cache, "sha256_file", lambda p: calls.append(p) or truth)
    for _ in range(2):  # each round as a fresh process: empty in-process caches
        monkeypatch.setattr(digest_cache, "_DIGEST_CACHE", {})
        monkeypatch.setattr(digest_cache, "_CACHES", {})
        assert digest_cache.cached_sha256_file(payload) == truth
    assert len(calls) == 1
    payload.write_bytes(os.urandom(4096))
    monkeypatch.setattr(digest_cache, "_DIGEST_CACHE", {})
    digest_cache.cached_sha256_file(payload)
    assert len(calls) == 2  # changed on disk: hashed again


def test_an_unusable_cache_folder_falls_back_to_hashing(tmp_path, monkeypatch):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("")
    monkeypatch.setenv("EGORELIGHT_CACHE_DIR", str(blocker))
    monkeypatch.setattr(digest_cache, "_CACHES", {})
    monkeypatch.setattr(digest_cache, "_DIGEST_CACHE", {})
    assert not digest_cache.persistent_cache().enabled
    payload = tmp_path / "payload.bin"
    payload.write_bytes(b"data")
    assert digest_cache.cached_sha256_file(payload) == digest_cache.sha256_file(payload)
    monkeypatch.setenv("EGORELIGHT_CACHE_DIR", "off")
    assert digest_cache.cache_dir() is None


def test_a_manifest_is_schema_validated_once_per_content(tmp_path, monkeypatch):
    """A manifest whose bytes passed validation is not validated again; one that changes is."""
    from egorelight_cli.artifacts import ArtifactWriter, open_artifact

    monkeypatch.setenv("EGORELIGHT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(digest_cache, "_CACHES", {})
    with ArtifactWriter(tmp_path / "a", kind="motion", stage="ik") as writer:
        writer.save_npz("motion.npz", {"theta": __import__("numpy").zeros((2, 3), "float32")})
    calls = []
    real = artifacts.validate_manifest
    monkeypatch.setattr(artifacts, "validate_manifest", lambda m, p=None: calls.append(p) or real(m, p))
    open_artifact(tmp_path / "a")
    open_artifact(tmp_path / "a")
    assert len(calls) == 1
    manifest = tmp_path / "a" / "manifest.json"
    broken = manifest.read_text().replace('"outputs"', '"outputz"')
    manifest.write_text(broken)
    with pytest.raises(artifacts.EgorelightError, match="manifest does not match"):
        open_artifact(tmp_path / "a")  # other bytes: validated (and refused) again
