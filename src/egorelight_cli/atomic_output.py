"""Putting a finished output in place so that it is, at every moment, the old one or the new one.

Writers build an output in a hidden temporary sibling (:func:`temporary_sibling`,
``.<name>.tmp-<pid>-<random>``) and swap it in at the end: a directory with
:func:`replace_directory`, a payload file and its sidecar manifest with :func:`replace_file_pair`.
The previous output is first moved aside (``.<name>.old-<pid>-<random>``), the new one renamed
into place, then the old one removed. The swap runs with SIGINT and SIGTERM deferred
(:mod:`egorelight_cli.signals`) and rolls back on an OSError; a SIGKILL or power cut half-way
leaves the old output aside, and the next writer of the same output puts it back
(:func:`remove_stale_temporaries`) before anything else.
"""

from __future__ import annotations

import glob
import os
import shutil
import uuid
from pathlib import Path

from egorelight_cli.errors import EgorelightError
from egorelight_cli.signals import signals_deferred

TEMPORARY_TAGS = ("tmp", "old")  # work directory of a writer; previous output being replaced
SIDECAR_SUFFIX = ".json"  # a single-file artifact's manifest: <file>.json beside it (egorelight_cli.artifacts)
MANIFEST_NAME = "manifest.json"  # a directory artifact's manifest: what marks it finished


def temporary_sibling(path: str | Path, tag: str = "tmp", suffix: str = "") -> Path:
    """A hidden sibling ``.<name>.<tag>-<pid>-<random><suffix>`` of ``path`` for atomic writes;
    the pid lets :func:`remove_stale_temporaries` tell a killed run's leftovers from a live one's."""
    path = Path(path)
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}-{uuid.uuid4().hex[:8]}{suffix}")


def _process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs, this one excepted: whatever carries our own pid when we look
    is a killed run's that had it before us (in a container every run may be pid 1); this
    process's own temporaries are made after the look."""
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _dead_leftovers(path: Path, tag: str) -> list[Path]:
    """The ``tag`` siblings of ``path`` whose process is gone (or that carry no pid), newest first."""
    found = []
    for match in glob.glob(str(path.with_name(f".{glob.escape(path.name)}.{tag}-*"))):
        leftover = Path(match)
        parts = leftover.name[len(path.name) + len(tag) + 3:].split("-")
        if len(parts) >= 2 and parts[0].isdigit() and _process_alive(int(parts[0])):
            continue
        found.append(leftover)
    return sorted(found, key=_mtime, reverse=True)


def _mtime(path: Path) -> float:
    try:
        return path.lstat().st_mtime
    except OSError:  # gone meanwhile (another run cleaned it up)
        return 0.0


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def restore_interrupted_swap(path: str | Path) -> list[Path]:
    """Put back the previous output of ``path`` where a killed swap left it aside: a directory
    artifact (it holds its manifest) whose place is empty, or a payload / sidecar pair of which
    one is missing. Returns what was restored (the paths put back)."""
    path = Path(path)
    if path.name in ("", ".", ".."):  # not an output's own name: nothing of ours can lie beside it
        return []
    sidecar = path.with_name(path.name + SIDECAR_SUFFIX)
    aside = {target: _dead_leftovers(target, "old") for target in (path, sidecar)}
    if not aside[path] and not aside[sidecar]:
        return []
    if aside[path] and aside[path][0].is_dir():  # a directory output
        if path.exists() or not (aside[path][0] / MANIFEST_NAME).is_file():
            return []
        os.replace(aside[path][0], path)
        return [path]
    if path.is_file() and sidecar.is_file():  # the swap got as far as the new sidecar: the new pair stands
        return []
    restored = []
    for target in (path, sidecar):  # the new half (if any) goes, the old pair comes back
        if aside[target]:
            if target.exists():
                _remove(target)
            os.replace(aside[target][0], target)
            restored.append(target)
    return restored


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Repair and clean up after runs that were killed while writing ``path``: first put back a
    previous output a killed swap left aside (:func:`restore_interrupted_swap`), then remove the
    temporary siblings (of ``path`` and of its sidecar) whose process is gone, and those of the
    older ``<tag>-<random>`` naming without a pid. Returns what was removed."""
    path = Path(path)
    if path.name in ("", ".", ".."):
        return []
    restore_interrupted_swap(path)
    removed = []
    for target in (path, path.with_name(path.name + SIDECAR_SUFFIX)):
        for tag in TEMPORARY_TAGS:
            for leftover in _dead_leftovers(target, tag):
                _remove(leftover)
                removed.append(leftover)
    return removed


def replace_directory(workdir: Path, out: Path) -> None:
    """Move the finished directory ``workdir`` (a :func:`temporary_sibling` of ``out``) to ``out``
    after syncing it to disk; a previous ``out`` directory is swapped aside and removed, so
    ``out`` is at every moment either the old or the new directory."""
    _fsync_tree(workdir)
    with signals_deferred():
        old = None
        if out.exists():
            if not out.is_dir():
                raise EgorelightError("output exists and is not a directory", out)
            old = temporary_sibling(out, "old")
            os.replace(out, old)
        try:
            os.replace(workdir, out)
        except OSError:
            if old is not None:
                os.replace(old, out)
            raise
        _fsync_dir(out.parent)
    if old is not None:  # outside the deferral: removing a large old output stays interruptible
        shutil.rmtree(old, ignore_errors=True)


def replace_file_pair(payload: Path, sidecar: Path, out: Path, out_sidecar: Path) -> None:
    """Move a finished ``payload`` and its ``sidecar`` manifest (synced, in a temporary folder)
    to ``out`` and ``out_sidecar``. The previous pair is moved aside first and the sidecar goes
    last, so a reader finds the old pair, nothing, or the new pair; an OSError half-way puts the
    old pair back."""
    _fsync_tree(payload.parent)
    with signals_deferred():
        moved: list[tuple[Path, Path]] = []  # (target, where its previous content went)
        placed: list[Path] = []
        try:
            for target in (out, out_sidecar):
                if target.exists():
                    aside = temporary_sibling(target, "old")
                    os.replace(target, aside)
                    moved.append((target, aside))
            for source, target in ((payload, out), (sidecar, out_sidecar)):
                os.replace(source, target)
                placed.append(target)
        except OSError:
            for target in placed:
                target.unlink(missing_ok=True)
            for target, aside in moved:
                os.replace(aside, target)
            raise
        _fsync_dir(out.parent)
        for _, aside in moved:
            aside.unlink(missing_ok=True)


def output_error(exc: OSError, out: str | Path) -> EgorelightError:
    """A one-line error for an output that cannot be written (read-only, disk full, name too long, ...)."""
    return EgorelightError(f"cannot write the output ({exc.strerror or exc})", exc.filename or out)


def _fsync_tree(root: Path) -> None:
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            fd = os.open(os.path.join(dirpath, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
    _fsync_dir(root)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
