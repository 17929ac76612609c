"""Versioned on-disk artifacts: manifests, digests, cache keys and atomic output.

An artifact is either

* a **directory** holding ``manifest.json`` and payload files, or
* a **single file** (``--out motion.npz``) with a sidecar manifest ``motion.npz.json`` next to it.

The manifest (DESIGN.md Sec. 3) records kind, version, stage, resolved config, input digests,
output digests, metrics, timing and units; it is validated against ``schemas/<kind>.schema.json``.
An artifact counts as *finished* only when its manifest exists: writes go to a temporary
sibling (``.<out>.tmp-<pid>-<random>``) and are renamed into place at the end, so a killed run
never leaves a finished-looking half artifact; the next writer of the same output removes such
leftovers of processes that are gone (:func:`remove_stale_temporaries`).

A stage's **cache key** is the hash of (stage, stage version, resolved config, input digests);
re-running a stage whose output already carries the same key is skipped unless forced.
"""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import os
import shutil
import socket
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
from referencing import Registry, Resource

from egorelight_cli import __version__
from egorelight_cli.atomic_output import (MANIFEST_NAME, SIDECAR_SUFFIX, output_error, remove_stale_temporaries,
                                          replace_directory, replace_file_pair, temporary_sibling)
from egorelight_cli.digest_cache import cached_sha256_file, sha256_file  # noqa: F401 (re-exported)
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import write_npz
from egorelight_cli.resources import schemas_dir

KIND_PREFIX = "egorelight/"
BASE_SCHEMA = "manifest.schema.json"


# ----------------------------------------------------------------------------------- schemas
@lru_cache(maxsize=None)
def _schema_documents() -> dict[str, dict]:
    docs = {}
    for path in sorted(schemas_dir().glob("*.schema.json")):
        docs[path.name] = json.loads(path.read_text())
    return docs


@lru_cache(maxsize=None)
def _registry() -> Registry:
    return Registry().with_resources(
        (name, Resource.from_contents(doc)) for name, doc in _schema_documents().items()
    )


def known_kinds() -> dict[str, int]:
    """Artifact kind (short name, e.g. ``motion``) -> the version this tool reads and writes."""
    kinds = {}
    for name, doc in _schema_documents().items():
        if name == BASE_SCHEMA:
            continue
        props = doc.get("properties", {})
        kinds[props["kind"]["const"].removeprefix(KIND_PREFIX)] = int(props["version"]["const"])
    return kinds


def kind_version(kind: str) -> int:
    kinds = known_kinds()
    if kind not in kinds:
        raise EgorelightError(f"unknown artifact kind {kind!r}; known: {', '.join(sorted(kinds))}")
    return kinds[kind]


def validate_manifest(manifest: dict, path: str | Path | None = None) -> None:
    """Validate against the kind's own schema (which includes the base manifest schema through
    ``allOf``), or the base schema alone for a kind without one."""
    docs = _schema_documents()
    kind = str(manifest.get("kind", "")).removeprefix(KIND_PREFIX)
    names = [f"{kind}.schema.json"] if f"{kind}.schema.json" in docs else [BASE_SCHEMA]
    for name in names:
        validator = jsonschema.Draft202012Validator(docs[name], registry=_registry())
        error = jsonschema.exceptions.best_match(validator.iter_errors(manifest))
        if error is not None:
            where = "/".join(str(p) for p in error.absolute_path) or "(top level)"
            message = error.message if len(error.message) <= 160 else error.message[:80] + " ... " + error.message[-60:]
            raise EgorelightError(f"manifest does not match {name} at {where}: {message}", path)


# ----------------------------------------------------------------------------------- hashing
def sha256_bytes(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


#: manifest fields that say when, where and how fast an artifact was made, not what it holds: left
#: out of its digest, so re-making an artifact with the same content keeps what depends on it current
VOLATILE_FIELDS = ("created", "timing", "runtime", "tool_version")


def content_digest(manifest: dict) -> str:
    """An artifact's digest: sha256 of its manifest's canonical JSON without :data:`VOLATILE_FIELDS`,
    its ``inputs`` and ``sources`` entries reduced to what they are (kind, digest, the flag they came
    through), not the path they were given by. It lists every output's digest, so it identifies the
    artifact's content and what it was made from."""
    def entries(name: str) -> list[dict]:
        return [{k: e.get(k) for k in ("kind", "digest", "param")} for e in manifest.get(name) or []
                if isinstance(e, dict)]

    kept = {k: v for k, v in manifest.items() if k not in VOLATILE_FIELDS and k not in ("inputs", "sources")}
    kept.update(inputs=entries("inputs"), sources=entries("sources"))
    return sha256_bytes(json.dumps(kept, sort_keys=True, separators=(",", ":"), default=str).encode())


def cache_key(stage: str, stage_version: int, config: dict, input_digests: list[str]) -> str:
    """hash(stage, stage version, resolved config, input digests) — order of inputs matters."""
    blob = json.dumps(
        {"stage": stage, "version": stage_version, "config": config, "inputs": list(input_digests)},
        sort_keys=True, separators=(",", ":"),
    )
    return sha256_bytes(blob.encode())


# ----------------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class Artifact:
    """A finished artifact on disk.

    Attributes:
        manifest_path: the ``manifest.json`` or sidecar ``<file>.json``.
        manifest: its parsed content.
        digest: :func:`content_digest` of the manifest (it lists every output digest, so it
            identifies the whole artifact's content; when and how fast it was made is left out).
        single_file: True for a file + sidecar artifact.
    """

    manifest_path: Path
    manifest: dict
    digest: str
    single_file: bool

    @property
    def kind(self) -> str:
        return self.manifest["kind"].removeprefix(KIND_PREFIX)

    @property
    def version(self) -> int:
        return int(self.manifest["version"])

    @property
    def root(self) -> Path:
        """Directory that output paths are relative to."""
        return self.manifest_path.parent

    @property
    def path(self) -> Path:
        """What a user names: the directory, or the single payload file."""
        if self.single_file:
            return self.manifest_path.with_name(self.manifest_path.name.removesuffix(SIDECAR_SUFFIX))
        return self.root

    @property
    def metrics(self) -> dict:
        return self.manifest.get("metrics", {})

    def output(self, name: str) -> Path:
        """Path of the named payload; error if the manifest does not list it, or it is missing
        or no longer matches its digest."""
        for entry in self.manifest["outputs"]:
            if entry["name"] == name:
                return self._checked(entry)
        names = ", ".join(e["name"] for e in self.manifest["outputs"][:10])
        raise EgorelightError(f"artifact has no output {name!r} (has: {names})", self.manifest_path)

    def payload_problems(self) -> list[tuple[str, Path]]:
        """``("missing" | "modified", path)`` for every listed payload that is gone or whose
        sha256 no longer matches the manifest (digests cached per process)."""
        problems = []
        for entry in self.manifest["outputs"]:
            path = self.root / entry["path"]
            if not path.is_file():
                problems.append(("missing", path))
            elif cached_sha256_file(path) != entry["digest"]:
                problems.append(("modified", path))
        return problems

    def verify(self, only: Callable[[str], bool] | None = None) -> None:
        """Check every payload (or those whose manifest path ``only`` accepts) against its manifest
        digest; error naming the first bad one."""
        for entry in self.manifest["outputs"]:
            if only is None or only(entry["path"]):
                self._checked(entry)

    def _checked(self, entry: dict) -> Path:
        path = self.root / entry["path"]
        if not path.is_file():
            raise EgorelightError(f"{self.kind} artifact payload is missing", path)
        if cached_sha256_file(path) != entry["digest"]:
            raise EgorelightError(f"{self.kind} artifact payload does not match its manifest digest (modified or "
                                  "half-written)", path)
        return path

    def made_from(self, kind: str | None = None, param: str | None = None) -> list[Path]:
        """Where the inputs and source files the manifest records were (relative paths taken from
        this artifact's folder), in the recorded order; only those of artifact ``kind`` (short
        name) and/or given through ``param`` (``--character``) when said."""
        entries = (self.manifest.get("inputs") or []) + (self.manifest.get("sources") or [])
        return [Path(os.path.normpath(self.root / e["path"])) for e in entries  # an absolute path stays as it is
                if (kind is None or e.get("kind") == KIND_PREFIX + kind) and (param is None or e.get("param") == param)]

    def as_input(self, relative_to: str | Path | None = None) -> dict:
        """The manifest ``inputs`` entry for this artifact; ``path`` is relative to
        ``relative_to`` (the consuming manifest's directory) when given."""
        path = Path(os.path.relpath(self.path.resolve(), Path(relative_to).resolve())) if relative_to else self.path
        return {"kind": self.manifest["kind"], "path": path.as_posix(), "digest": self.digest}


def manifest_path_for(path: str | Path) -> tuple[Path, bool]:
    """Where the manifest of ``path`` lives: (manifest path, single_file)."""
    path = Path(path)
    if path.is_dir():
        return path / MANIFEST_NAME, False
    if path.name == MANIFEST_NAME:
        return path, False
    if path.name.endswith(SIDECAR_SUFFIX) and path.with_name(path.name.removesuffix(SIDECAR_SUFFIX)).is_file():
        return path, True
    return path.with_name(path.name + SIDECAR_SUFFIX), True


def open_artifact(path: str | Path, kind: str | None = None, verify: bool = True) -> Artifact:
    """Open a finished artifact and check its kind and version.

    Args:
        path: the artifact directory, its ``manifest.json``, a single payload file or its sidecar.
        kind: expected kind (short name, ``motion``); None accepts any known kind.
        verify: check every payload's sha256 against the manifest (default; digests are cached
            per process). ``False`` only reads the manifest (``inspect`` reports problems itself).
    """
    path = Path(path)
    if not path.exists():
        raise EgorelightError("input not found", path)
    manifest_path, single_file = manifest_path_for(path)
    if not manifest_path.is_file():
        what = "directory" if path.is_dir() else "file"
        raise EgorelightError(f"not a finished egorelight artifact ({what} has no {manifest_path.name})", path)
    raw = manifest_path.read_bytes()
    try:
        manifest = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise EgorelightError(f"manifest is not valid JSON ({exc.msg} at line {exc.lineno})", manifest_path) from None
    except ValueError as exc:  # not UTF-8 text
        raise EgorelightError(f"manifest is not UTF-8 JSON text ({exc})", manifest_path) from None
    if not isinstance(manifest, dict) or not str(manifest.get("kind", "")).startswith(KIND_PREFIX):
        raise EgorelightError("manifest has no egorelight kind", manifest_path)
    found = manifest["kind"].removeprefix(KIND_PREFIX)
    if kind is not None and found != kind:
        raise EgorelightError(f"wrong artifact kind: expected {KIND_PREFIX}{kind}, found {KIND_PREFIX}{found}", path)
    known = known_kinds()
    if found not in known:
        raise EgorelightError(f"unknown artifact kind {KIND_PREFIX}{found}", path)
    if manifest.get("version") != known[found]:
        raise EgorelightError(
            f"{KIND_PREFIX}{found} version mismatch: artifact is version {manifest.get('version')}, "
            f"this tool ({__version__}) reads version {known[found]}", path)
    _validate_once(manifest, manifest_path, sha256_bytes(raw))  # the bytes: what was validated
    artifact = Artifact(manifest_path=manifest_path, manifest=manifest, digest=content_digest(manifest),
                        single_file=single_file)
    if verify:
        artifact.verify()
    return artifact


@lru_cache(maxsize=1)
def _schemas_digest() -> str:
    return sha256_bytes(json.dumps(_schema_documents(), sort_keys=True).encode())


def _validate_once(manifest: dict, manifest_path: Path, digest: str) -> None:
    """:func:`validate_manifest`, skipped for manifest bytes that passed against the same schemas
    before (remembered in :mod:`egorelight_cli.digest_cache`)."""
    from egorelight_cli.digest_cache import persistent_cache

    cache = persistent_cache()
    if cache.validated(digest, _schemas_digest()):
        return
    validate_manifest(manifest, manifest_path)
    cache.mark_validated(digest, _schemas_digest())


def resolve_payload(path: str | Path, kind: str, payload: str, what: str):
    """Where the ``payload`` npz of an artifact of ``kind`` (short name) lives.

    ``path`` may be the artifact directory, a single ``.npz`` with its sidecar, or a lone
    ``.npz`` without one (then the caller checks the npz's own ``__meta__`` kind).
    Returns ``(npz path, Artifact | None)``.
    """
    path = Path(path)
    if not path.exists():
        raise EgorelightError(f"{what} input not found", path)
    manifest_path, _ = manifest_path_for(path)
    if path.is_file() and path.suffix == ".npz" and not manifest_path.is_file():
        return path, None
    artifact = open_artifact(path, kind=kind)
    return (artifact.path if artifact.single_file else artifact.output(payload)), artifact


# ----------------------------------------------------------------------------------- writing
def check_sequence(artifact: Artifact | None, sequence: str) -> None:
    """An EgorelightError when ``artifact`` was made for another sequence than ``sequence`` (its
    manifest's ``config.options.sequence``, trusted only when the artifact was made from a capture:
    without one, ``--seq`` keeps its default and says nothing): inputs of two sequences mixed up.
    Nothing to check for an artifact that records none (a motion, a lone npz) or for None."""
    if artifact is None or not any(entry.get("kind") == KIND_PREFIX + "capture"
                                   for entry in artifact.manifest.get("inputs") or []):
        return
    recorded = ((artifact.manifest.get("config") or {}).get("options") or {}).get("sequence")
    if recorded is not None and str(recorded) != str(sequence):
        raise EgorelightError(f"was made for sequence {recorded!r}, not {sequence!r} (inputs of two sequences "
                              "mixed up?)", artifact.path)


def _array_entry(path: Path) -> dict[str, Any]:
    """Shape/dtype of the main arrays of an npz, for the manifest."""
    if path.suffix != ".npz":
        return {}
    with np.load(path, allow_pickle=False) as data:
        arrays = {n: (list(data[n].shape), str(data[n].dtype)) for n in data.files if n != "__meta__"}
    return {"arrays": {n: {"shape": s, "dtype": d} for n, (s, d) in arrays.items()}}


def is_up_to_date(out: str | Path, key: str, kind: str) -> bool:
    """True when ``out`` is a finished artifact of ``kind`` made with cache key ``key`` whose
    payloads are all present and intact."""
    manifest_path, _ = manifest_path_for(out)
    if not manifest_path.is_file():
        return False
    try:
        artifact = open_artifact(out, kind=kind, verify=False)
    except EgorelightError:
        return False
    return artifact.manifest.get("cache_key") == key and not artifact.payload_problems()


class ArtifactWriter:
    """Collects an artifact's payloads in a temporary location and commits them atomically.

    Usage::

        with ArtifactWriter(out, kind="motion", stage="ik", config=cfg, inputs=[kp]) as w:
            w.save_npz("motion.npz", arrays, frame_ids=ids, units={"theta": "rad|m"})
            w.metrics["mpjpe_cm"] = 1.2
        # committed here; an exception inside the block discards everything

    ``out`` ending in a payload suffix (``.npz``, ``.exr``, ``.png``, ``.json``, ``.obj``,
    ``.ply``) makes a single-file artifact: exactly one payload, named like ``out``, with a
    sidecar manifest ``<out>.json``. ``keep=False`` discards the payloads at the end of the block
    instead of committing them (the non-zero ranks of a distributed training run).
    """

    SINGLE_FILE_SUFFIXES = (".npz", ".exr", ".png", ".json", ".obj", ".ply")

    def __init__(self, out: str | Path, kind: str, stage: str, config: Any = None,
                 inputs: list[Artifact] | tuple[Artifact, ...] = (), key: str | None = None, keep: bool = True,
                 input_params: list[str | None] | None = None):
        self.out = Path(out)
        self.keep = keep
        self.kind = kind
        self.version = kind_version(kind)
        self.stage = stage
        self.config = config.to_dict() if hasattr(config, "to_dict") else dict(config or {})
        self.stage_version = int(getattr(config, "version", 1))
        self.inputs = list(inputs)
        self.input_params = list(input_params) if input_params is not None else [None] * len(self.inputs)
        self.cache_key = key or cache_key(stage, self.stage_version, self.config, [a.digest for a in self.inputs])
        self.single_file = self.out.suffix.lower() in self.SINGLE_FILE_SUFFIXES
        self.metrics: dict[str, Any] = {}
        self.timing: dict[str, Any] = {}
        self.units: dict[str, Any] = {}
        self.runtime: dict[str, Any] = {}
        self.extra: dict[str, Any] = {}
        self._started = _dt.datetime.now(_dt.timezone.utc)
        self._committed = False
        try:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temporaries(self.out)
            self.workdir = temporary_sibling(self.out)
            self.workdir.mkdir()
        except OSError as exc:
            raise output_error(exc, self.out) from None

    @property
    def manifest_dir(self) -> Path:
        """The directory the finished manifest will live in (paths in it are relative to it)."""
        return self.out.parent if self.single_file else self.out

    # -- payloads --------------------------------------------------------------------------
    def path(self, name: str) -> Path:
        """Temporary path for payload ``name`` (may contain sub-directories)."""
        if self.single_file and name != self.out.name:
            raise EgorelightError(f"single-file output {self.out.name} cannot hold a payload named {name}", self.out)
        target = self.workdir / name
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def npz_meta(self, frame_ids: Any = None, units: dict | None = None, **extra: Any) -> dict:
        meta = {"kind": KIND_PREFIX + self.kind, "version": self.version, "stage": self.stage,
                "units": units or {}, **extra}
        if frame_ids is not None:
            meta["frame_ids"] = [int(f) for f in np.asarray(frame_ids).ravel()]
        return meta

    def save_npz(self, name: str, arrays: dict[str, np.ndarray], frame_ids: Any = None,
                 units: dict | None = None, **meta: Any) -> Path:
        path = self.path(name)
        write_npz(path, arrays, self.npz_meta(frame_ids, units, **meta))
        if units:
            self.units.update(units)
        return path

    def save_json(self, name: str, data: Any) -> Path:
        path = self.path(name)
        path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
        return path

    # -- commit ----------------------------------------------------------------------------
    def _outputs(self) -> list[dict]:
        entries = []
        for file in sorted(p for p in self.workdir.rglob("*") if p.is_file()):
            rel = file.relative_to(self.workdir).as_posix()
            if rel == MANIFEST_NAME:
                continue
            entries.append({"name": rel, "path": rel, "digest": sha256_file(file), **_array_entry(file)})
        return entries

    def manifest(self) -> dict:
        finished = _dt.datetime.now(_dt.timezone.utc)
        self.timing.setdefault("wall_s", round((finished - self._started).total_seconds(), 3))
        runtime = {"host": socket.gethostname(), **self.runtime}
        manifest = {
            "kind": KIND_PREFIX + self.kind,
            "version": self.version,
            "stage": self.stage,
            "stage_version": self.stage_version,
            "created": finished.isoformat(timespec="seconds"),
            "tool_version": __version__,
            "cache_key": self.cache_key,
            "config": self.config,
            "inputs": [_with_param(a.as_input(self.manifest_dir), param)
                       for a, param in zip(self.inputs, self.input_params)],
            "outputs": self._outputs(),
            "metrics": _jsonable(self.metrics),
            "timing": _jsonable(self.timing),
            "units": self.units,
            "runtime": runtime,
            **_jsonable(self.extra),
        }
        return manifest

    def commit(self) -> Path:
        """Write the manifest and move everything into place atomically; returns ``out``."""
        if self._committed:
            return self.out
        files = [p for p in self.workdir.rglob("*") if p.is_file()]
        if self.single_file and [p.name for p in files] != [self.out.name]:
            raise EgorelightError(f"single-file output needs exactly the payload {self.out.name}", self.out)
        manifest = self.manifest()
        validate_manifest(manifest, self.out)
        try:
            if self.single_file:
                self._commit_single(manifest)
            else:
                self._commit_directory(manifest)
        except OSError as exc:
            raise output_error(exc, self.out) from None
        self._committed = True
        return self.out

    def _commit_directory(self, manifest: dict) -> None:
        (self.workdir / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2) + "\n")
        replace_directory(self.workdir, self.out)

    def _commit_single(self, manifest: dict) -> None:
        entry = manifest["outputs"][0]
        entry["path"] = self.out.name
        tmp_sidecar = self.workdir / (self.out.name + SIDECAR_SUFFIX)
        tmp_sidecar.write_text(json.dumps(manifest, indent=2) + "\n")
        replace_file_pair(self.workdir / self.out.name, tmp_sidecar, self.out,
                          self.out.with_name(self.out.name + SIDECAR_SUFFIX))
        shutil.rmtree(self.workdir, ignore_errors=True)

    def abort(self) -> None:
        shutil.rmtree(self.workdir, ignore_errors=True)

    def __enter__(self) -> "ArtifactWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None and self.keep:
            try:
                self.commit()
            finally:
                if not self._committed:
                    self.abort()
        else:
            self.abort()
            if isinstance(exc, OSError) and self._is_output_failure(exc):
                raise output_error(exc, self.out) from None
        return False

    def _is_output_failure(self, exc: OSError) -> bool:
        """Whether ``exc`` came from writing the output: the disk or quota is full, or it names a
        file of the work directory."""
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            return True
        return exc.filename is not None and Path(os.fsdecode(exc.filename)).is_relative_to(self.workdir)


def _with_param(entry: dict, param: str | None) -> dict:
    """A manifest ``inputs`` entry labelled with the declared input it came through (``--motion``)."""
    return {**entry, "param": param} if param is not None else entry


def _jsonable(value: Any) -> Any:
    """numpy scalars/arrays -> JSON types; NaN/inf -> None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if np.isfinite(value) else None
    return value
