"""Find a subject's artifacts by their manifests and place them in the pipeline's stage order.

Only manifests are read (and payload files stat'ed): the report never opens payload arrays,
never verifies digests of large captures and never runs a stage.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from egorelight_cli.artifacts import KIND_PREFIX, MANIFEST_NAME, SIDECAR_SUFFIX, known_kinds, validate_manifest
from egorelight_cli.errors import EgorelightError


@dataclass(frozen=True)
class StageInfo:
    """One section of the report: a pipeline stage, the artifact kinds it writes, and where the
    Makefile puts them (for the "not run" list)."""

    name: str
    title: str
    kinds: tuple[str, ...]
    layout: tuple[str, ...]


#: The pipeline DAG in order (DESIGN.md Sec. 1-2); a model artifact goes to the stage that trained it.
STAGES: tuple[StageInfo, ...] = (
    StageInfo("synth", "capture (synth)", ("capture",), ("capture/",)),
    StageInfo("character", "character", ("character",), ("character/",)),
    StageInfo("calibrate", "calibrate", ("calibration",), ("calibration/",)),
    StageInfo("egopose", "egopose: ego images -> 57 keypoints", ("keypoints",), ("models/egopose/", "keypoints/<seq>/")),
    StageInfo("ik", "ik: keypoints -> skeleton motion", ("motion",),
              ("models/ik/", "models/ik_default/", "motion/<seq>/", "motion_mocap/<seq>/", "motion_bootstrap/<seq>/")),
    StageInfo("egodepth", "egodepth: ego images -> point cloud", ("pointcloud",),
              ("models/egodepth/", "pointcloud/<seq>/")),
    StageInfo("animate", "animate: motion + depth -> tracked meshes", ("meshes",),
              ("models/animate/", "meshes/<seq>/", "meshes_student/<seq>/")),
    StageInfo("geolift", "geolift: meshes -> UV normals + texture", ("uvmaps",), ("models/geolift/", "uvmaps/<seq>/")),
    StageInfo("relight", "relight: relit Gaussian avatar renders", ("renders",), ("models/relight/", "renders/<seq>/")),
    StageInfo("envmap", "envmap: HDR light from the headset", ("envmap",), ("envmap/<seq>/",)),
    StageInfo("composite", "composite: telepresence", ("composite",), ("composite/<name>/",)),
)
OTHER = StageInfo("other", "other artifacts", (), ())
#: Manifest ``stage`` names that differ from the section's name.
STAGE_ALIASES = {"capture": "synth", "calibration": "calibrate"}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class Found:
    """One artifact of the subject as its manifest describes it.

    Attributes:
        root: directory its output paths are relative to.
        manifest_path: ``manifest.json`` or a single file's sidecar.
        manifest: parsed JSON (``{}`` when it could not be read).
        rel: its path relative to the subject directory (what a person calls it).
        problems: what is wrong with it (unreadable, schema/version mismatch, missing payloads).
    """

    root: Path
    manifest_path: Path
    manifest: dict
    rel: str
    problems: list[str] = field(default_factory=list)

    @property
    def kind(self) -> str:
        return str(self.manifest.get("kind", "?")).removeprefix(KIND_PREFIX)

    @property
    def section(self) -> str:
        """Name of the report section (:data:`STAGES`) it belongs to."""
        stage = STAGE_ALIASES.get(str(self.manifest.get("stage", "")), str(self.manifest.get("stage", "")))
        if self.kind == "model" and any(s.name == stage for s in STAGES):
            return stage
        for info in STAGES:
            if self.kind in info.kinds:
                return info.name
        return OTHER.name

    @property
    def anchor(self) -> str:
        """An HTML id for this artifact."""
        return "a-" + "".join(c if c.isalnum() else "-" for c in self.rel).strip("-")

    def outputs(self) -> list[dict]:
        return [o for o in self.manifest.get("outputs", []) if isinstance(o, dict) and "path" in o]

    def images(self) -> list[str]:
        """Output paths of the images listed in the manifest."""
        return [o["path"] for o in self.outputs() if str(o["path"]).lower().endswith(IMAGE_SUFFIXES)]


def read_found(manifest_path: Path, subject: Path) -> Found:
    """Read one manifest without failing: problems are recorded, not raised."""
    root = manifest_path.parent
    rel_target = root if manifest_path.name == MANIFEST_NAME else manifest_path.with_name(
        manifest_path.name.removesuffix(SIDECAR_SUFFIX))
    rel = os.path.relpath(rel_target, subject)
    found = Found(root=root, manifest_path=manifest_path, manifest={}, rel=Path(rel).as_posix())
    try:
        manifest = json.loads(manifest_path.read_bytes())
    except (OSError, ValueError) as exc:
        found.problems.append(f"unreadable manifest ({exc})")
        return found
    if not isinstance(manifest, dict):
        found.problems.append("manifest is not a JSON object")
        return found
    found.manifest = manifest
    kinds = known_kinds()
    if found.kind not in kinds:
        found.problems.append(f"unknown kind {manifest.get('kind')!r}")
    elif manifest.get("version") != kinds[found.kind]:
        found.problems.append(f"version {manifest.get('version')} (this tool reads {kinds[found.kind]})")
    else:
        try:
            validate_manifest(manifest, manifest_path)
        except EgorelightError as exc:
            found.problems.append(exc.message)
    missing = [o["path"] for o in found.outputs() if not (root / o["path"]).is_file()]
    if missing:
        found.problems.append(f"{len(missing)} payload file(s) missing, e.g. {missing[0]}")
    return found


def _is_sidecar(directory: Path, name: str) -> bool:
    if not name.endswith(SIDECAR_SUFFIX) or name == MANIFEST_NAME:
        return False
    if not (directory / name.removesuffix(SIDECAR_SUFFIX)).is_file():
        return False
    try:
        with open(directory / name, "rb") as handle:
            head = handle.read(200)
    except OSError:
        return False
    return KIND_PREFIX.encode() in head


def discover(subject: str | Path, skip: Path | None = None) -> list[Found]:
    """Every artifact under ``subject`` (directories with ``manifest.json``, and single files with
    a sidecar), without descending into an artifact; hidden entries (temporaries of running or
    killed writers, checkpoints) and ``skip`` (the report's own folder) are passed over. Sorted
    by section (pipeline order), models first, then by path."""
    subject = Path(subject)
    skip = skip.resolve() if skip is not None else None
    found: list[Found] = []
    for dirpath, dirnames, filenames in os.walk(subject):
        directory = Path(dirpath)
        if skip is not None and directory.resolve() == skip:
            dirnames[:] = []
            continue
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        if MANIFEST_NAME in filenames:
            found.append(read_found(directory / MANIFEST_NAME, subject))
            dirnames[:] = []
            continue
        for name in sorted(filenames):
            if not name.startswith(".") and _is_sidecar(directory, name):
                found.append(read_found(directory / name, subject))
    order = {info.name: i for i, info in enumerate(STAGES + (OTHER,))}
    found.sort(key=lambda f: (order[f.section], f.kind != "model", f.rel))
    return found


def loose_previews(subject: str | Path) -> list[Path]:
    """Images in ``<subject>/previews/`` (written by commands that make no artifact, e.g.
    ``character preview``)."""
    folder = Path(subject) / "previews"
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
