"""Safe outputs: may a stage write its artifact at ``--out``?

Writing an artifact replaces whatever is at ``--out`` (atomically, see
:class:`~egorelight_cli.artifacts.ArtifactWriter`), so before any stage writes, :func:`check_output`
refuses, with a one-line :class:`EgorelightError` naming the path, an ``--out`` that

* is one of the stage's inputs, contains one, or lies inside one (``ik --in X --out X``,
  ``--in k.npz --out k.npz``, ``--out X/sub`` for an input artifact directory ``X``), or lies
  inside any artifact directory;
* is the current directory or one above it (``--out .``, ``--out ..``);
* exists and is not a previous egorelight artifact of the same kind: a directory without an
  egorelight ``manifest.json`` (an empty directory is fine), a file without its egorelight sidecar
  ``<file>.json``, an artifact of another kind, or an artifact directory holding files its
  manifest does not list (someone's notes would go with it);
* cannot be written: a name too long for the file system, or a folder that is not writable.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

from egorelight_cli.artifacts import KIND_PREFIX, MANIFEST_NAME, SIDECAR_SUFFIX, ArtifactWriter
from egorelight_cli.errors import EgorelightError

# longest suffix a writer appends to the output's name: ".<name>.tmp-<pid>-<8 hex>" or "<name>.json"
_TEMPORARY_NAME_EXTRA = len("..tmp--") + 10 + 8


def is_single_file_output(out: str | Path) -> bool:
    """True when ``out`` names a single payload file (``motion.npz``) rather than a directory."""
    return Path(out).suffix.lower() in ArtifactWriter.SINGLE_FILE_SUFFIXES


def _absolute(path: str | Path) -> Path:
    """Absolute path with symbolic links resolved, also for paths that do not exist yet."""
    return Path(os.path.realpath(os.path.abspath(path)))


def _within(path: Path, folder: Path) -> bool:
    """``path`` is ``folder`` or lies below it (both absolute)."""
    return path == folder or folder in path.parents


def manifest_kind(manifest_path: Path) -> str | None:
    """The kind (short name) of an egorelight manifest or sidecar, None when ``manifest_path`` is
    missing or is not one (unreadable, not UTF-8, not JSON, no ``egorelight/`` kind)."""
    try:
        manifest = json.loads(manifest_path.read_bytes())
    except (OSError, ValueError):
        return None
    kind = manifest.get("kind") if isinstance(manifest, dict) else None
    if not isinstance(kind, str) or not kind.startswith(KIND_PREFIX):
        return None
    return kind.removeprefix(KIND_PREFIX)


def _check_previous_artifact(out: Path, kind: str, single_file: bool, stage: str | None = None) -> None:
    """``out`` may be replaced only when it is nothing yet or a previous artifact of ``kind`` (for a
    ``model``, one that ``stage`` trained: every stage's model is of that one kind)."""
    if single_file:
        sidecar = out.with_name(out.name + SIDECAR_SUFFIX)
        if out.is_dir():
            raise EgorelightError("--out names a file but a directory exists there; not replacing it", out)
        if not out.exists() and not sidecar.exists():
            return
        manifest, what = sidecar, f"a file without an egorelight sidecar {sidecar.name}"
    else:
        if not out.exists():
            return
        if not out.is_dir():
            raise EgorelightError("--out names a directory but a file exists there; not replacing it", out)
        if not any(out.iterdir()):
            return
        manifest, what = out / MANIFEST_NAME, f"a directory without an egorelight {MANIFEST_NAME}"
    found = manifest_kind(manifest)
    if found is None:
        raise EgorelightError(f"--out exists and is not an egorelight artifact ({what}); not replacing it", out)
    if found != kind:
        raise EgorelightError(f"--out is an existing {KIND_PREFIX}{found} artifact and this stage writes "
                              f"{KIND_PREFIX}{kind}; not replacing it", out)
    if kind == "model" and stage is not None:
        trained_by = json.loads(manifest.read_bytes()).get("stage")
        if trained_by != stage:
            raise EgorelightError(f"--out is an existing {trained_by} model and this trains a {stage} model; "
                                  "not replacing it", out)
    if not single_file:
        _check_only_listed_files(out, manifest)


def _check_only_listed_files(out: Path, manifest_path: Path) -> None:
    """An artifact directory about to be replaced holds nothing its manifest does not list."""
    manifest = json.loads(manifest_path.read_bytes())
    outputs = manifest.get("outputs") if isinstance(manifest.get("outputs"), list) else []
    listed = {str(e.get("path")) for e in outputs if isinstance(e, dict)} | {MANIFEST_NAME}
    for path in sorted(out.rglob("*")):
        if (path.is_file() or path.is_symlink()) and path.relative_to(out).as_posix() not in listed:
            raise EgorelightError(f"--out is an artifact directory that also holds {path.relative_to(out)}, which its "
                                  "manifest does not list; not replacing it", out)


def _check_writable(out: Path) -> None:
    """A name the file system takes, in a folder (or the nearest existing one above) we may write."""
    try:
        name_max = os.pathconf(Path.cwd().anchor, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    longest = max((len(part.encode()) for part in out.parts), default=0)
    if longest > name_max or len(out.name.encode()) + _TEMPORARY_NAME_EXTRA > name_max:
        raise EgorelightError(f"--out holds a name too long for the file system ({longest} bytes; it takes "
                              f"{name_max} per name, less {_TEMPORARY_NAME_EXTRA} for the temporary copy)", out)
    folder = out.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise EgorelightError(f"cannot write the output: {folder} is not a directory", out)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise EgorelightError(f"cannot write the output: {folder} is not writable", out)


def check_output(out: str | Path, kind: str, inputs: Iterable[str | Path] = (), stage: str | None = None) -> None:
    """Refuse (:class:`EgorelightError`) an ``--out`` a stage writing an artifact of ``kind`` must
    not replace (see the module docstring); ``inputs`` are every file or artifact the stage reads
    (for a single-file artifact, its payload and its sidecar); ``stage``: the stage writing it (a
    model of another stage is not replaced)."""
    check_output_location(out, inputs)
    _check_previous_artifact(Path(out), kind, is_single_file_output(out), stage)


def check_output_location(out: str | Path, inputs: Iterable[str | Path] = ()) -> None:
    """The part of :func:`check_output` that does not depend on what exists at ``out``: not an
    input, not containing or inside one, not inside an artifact, not the current directory or
    above, a writable place with a name the file system takes. Also for outputs that are not
    artifacts (``character export-ddc``, ``character preview``)."""
    out = Path(out)
    single_file = is_single_file_output(out)
    target = _absolute(out)
    targets = [target, target.with_name(target.name + SIDECAR_SUFFIX)] if single_file else [target]
    if _within(_absolute(Path.cwd()), target):
        raise EgorelightError("--out is the current directory or one above it; refusing to replace it", out)
    for given in inputs:
        source = _absolute(given)
        for path in targets:
            if path == source:
                raise EgorelightError(f"--out is the input {given}; refusing to replace an input", out)
            if _within(source, path):
                raise EgorelightError(f"--out contains the input {given}; refusing to replace it", out)
            if _within(path, source):
                raise EgorelightError(f"--out lies inside the input {given}; refusing to write into an input", out)
    for folder in target.parents:
        if manifest_kind(folder / MANIFEST_NAME) is not None:
            raise EgorelightError(f"--out lies inside the artifact {folder}; refusing to write into it", out)
    _check_writable(out)
