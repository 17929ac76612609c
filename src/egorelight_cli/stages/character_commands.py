"""The ``egorelight character`` commands: default, from-makehuman, import-ddc, export-ddc, preview,
fit-scan.

A character artifact is a directory (or ``.npz`` + sidecar) holding ``character.npz`` (all
arrays, see :class:`~egorelight_cli.structures.character.Character`) and ``template.obj`` for
viewing. Its manifest metrics are the counts and the rest-pose self-check: skinning the template
at the rigging pose must reproduce it.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.artifacts import Artifact, ArtifactWriter, manifest_path_for, open_artifact
from egorelight_cli.atomic_output import remove_stale_temporaries, replace_directory, temporary_sibling
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.character import default_character_path, read_character_npz, write_character_npz
from egorelight_cli.io.meshes import write_obj
from egorelight_cli.outputs import check_output_location
from egorelight_cli.pipeline import StageRun
from egorelight_cli.structures.character import Character

CHARACTER_PAYLOAD = "character.npz"
DEFAULT_CHARACTER_NAME = "default"


def load_character(spec: str | Path) -> tuple[Character, Artifact | None]:
    """Load a character from ``default``, a character artifact (directory or ``.npz`` with
    sidecar), a bare ``character.npz`` or a DDC ``.character`` file.

    Returns the character and the artifact it came from (None for non-artifact sources).
    """
    if str(spec) == DEFAULT_CHARACTER_NAME:
        path = default_character_path()
        if not path.is_file():
            raise EgorelightError("the shipped default character is missing from the installation", path)
        return read_character_npz(path), None
    path = Path(spec)
    if not path.exists():
        raise EgorelightError("character not found", path)
    if path.suffix == ".character":
        from egorelight_cli.io.ddc import read_ddc_character

        return read_ddc_character(path), None
    manifest_path, _ = manifest_path_for(path)
    if path.is_file() and path.suffix == ".npz" and not manifest_path.is_file():
        return read_character_npz(path), None
    artifact = open_artifact(path, kind="character")
    return read_character_npz(artifact.output(CHARACTER_PAYLOAD) if not artifact.single_file else artifact.path), artifact


CHARACTER_FINGERPRINT = "character_fingerprint"  # a manifest key (Character.fingerprint), from writer.extra


def check_same_character(artifact: Artifact | None, character: Character, what: str) -> None:
    """Error when ``artifact`` (a motion, a model) records the fingerprint of another character
    than ``character``: posed with another template or skeleton it would run and be wrong (the
    default character in place of the subject's fitted one has the same topology). Artifacts from
    before the fingerprint, and files that are not artifacts, are not checked."""
    if artifact is None:
        return
    recorded = artifact.manifest.get(CHARACTER_FINGERPRINT)  # writer.extra lands at the top level
    if recorded is None or recorded == character.fingerprint():
        return
    named = artifact.made_from(param="--character")
    hint = (f" ({named[0]})" if named else f" ({DEFAULT_CHARACTER_NAME})"
            if default_character_path() in artifact.made_from() else "")
    raise EgorelightError(f"the {what} was made with another character{hint}: give that one with --character, or "
                          f"re-make the {what} if that character has changed since", artifact.path)


def rest_pose_error_m(character: Character) -> float:
    """Max distance (m) between the template and the template skinned at the rigging pose."""
    import torch

    from egorelight_cli.geometry.skinning import dual_quaternion_skinning
    from egorelight_cli.geometry.skeleton import bone_transforms

    theta = torch.as_tensor(character.rest_theta, dtype=torch.float64)
    bones = bone_transforms(theta, character)
    verts = torch.as_tensor(character.vertices, dtype=torch.float64)
    posed = dual_quaternion_skinning(verts, bones, torch.as_tensor(character.skin_weights))
    return float((posed - verts).norm(dim=-1).max())


def character_metrics(character: Character) -> dict:
    sk = character.skeleton
    return {
        "num_vertices": character.num_vertices,
        "num_faces": int(character.faces.shape[0]),
        "num_joints": sk.num_joints,
        "num_dofs": sk.num_dofs,
        "num_skin_bones": len(character.skin_bone_names),
        "num_graph_nodes": character.graph.num_nodes,
        "num_keypoints": len(character.keypoint_names),
        "standard_57_keypoints": character.has_standard_keypoints,
        "height_m": float(np.ptp(character.vertices[:, 1])),
        "rest_pose_skinning_error_mm": 1000.0 * rest_pose_error_m(character),
    }


def write_character(writer: ArtifactWriter, character: Character, **meta) -> None:
    """Fill a character artifact: ``character.npz`` (+ ``template.obj`` for directories)."""
    payload = writer.out.name if writer.single_file else CHARACTER_PAYLOAD
    write_character_npz(writer.path(payload), character, **meta)
    if not writer.single_file:
        write_obj(writer.path("template.obj"), character.vertices, character.faces,
                  face_uvs=character.face_uvs, vertex_colors=character.vertex_colors)
    writer.units.update({"length": "m", "angle": "rad"})
    writer.metrics.update(character_metrics(character))


def _character_paths(spec: str | Path, artifact: Artifact | None) -> list[Path]:
    """Every file a character was read from (an output must not replace any of them)."""
    return [artifact.path, artifact.manifest_path] if artifact is not None else character_sources(str(spec), None)


#: image files ``character preview`` writes
PREVIEW_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class CharacterCommands:
    """The ``character`` sub-commands over one :class:`StageRun` (global options)."""

    run: StageRun

    def default(self, out: Path) -> Path:
        source = default_character_path()
        return self.run.produce(out, "character", lambda w, cfg: write_character(w, read_character_npz(source)),
                                source_files=[source])

    def from_makehuman(self, out: Path, data_dir_: Path | None) -> Path:
        from egorelight_cli.stages.character import character_from_makehuman

        def write(w: ArtifactWriter, cfg: Config) -> None:
            character = character_from_makehuman(data_dir_, target_vertices=cfg.target_vertices,
                                                 num_graph_nodes=cfg.graph_nodes, seed=cfg.seed)
            write_character(w, character)
        return self.run.produce(out, "character", write)

    def import_ddc(self, path: Path, out: Path) -> Path:
        from egorelight_cli.io.ddc import ddc_character_files, read_ddc_character

        if not path.is_file():
            raise EgorelightError("DDC character file not found", path)
        sources = ddc_character_files(path)
        return self.run.produce(out, "character", lambda w, cfg: write_character(w, read_ddc_character(path)),
                                source_files=sources)

    def export_ddc(self, character_path: Path, out_dir: Path, name: str) -> Path:
        from egorelight_cli.io.ddc import write_ddc_character

        character, artifact = load_character(character_path)
        check_output_location(out_dir, _character_paths(character_path, artifact))
        if out_dir.exists() and not out_dir.is_dir():
            raise EgorelightError("--out names a folder but a file exists there; not replacing it", out_dir)
        if out_dir.is_dir() and any(out_dir.iterdir()) and not any(out_dir.glob("*.character")):
            raise EgorelightError("--out exists and is not a DDC export (no .character file); not replacing it", out_dir)
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(out_dir)
        tmp = temporary_sibling(out_dir)
        tmp.mkdir()
        try:
            write_ddc_character(character, tmp, name=name)
            replace_directory(tmp, out_dir)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return out_dir / f"{name}.character"

    def fit_scan(self, scan: Path, character_spec: str, out: Path) -> Path:
        """Register ``character_spec`` to the scan (:mod:`egorelight_cli.stages.character_fit`) and
        write the fitted character with its fit metrics and ``preview.png``."""
        from egorelight_cli.io.images import write_image
        from egorelight_cli.render.preview import scan_fit_image
        from egorelight_cli.stages.character_fit import fit_character_to_scan, fit_units, read_scan

        if not scan.is_file():
            raise EgorelightError("scan not found", scan)
        character, artifact = load_character(character_spec)
        sources = [scan] + character_sources(character_spec, artifact)

        def write(w: ArtifactWriter, cfg: Config) -> None:
            scan_vertices, scan_faces = read_scan(scan)
            fit = fit_character_to_scan(character, scan_vertices, scan_faces, cfg.fit_scan, scan, seed=cfg.seed)
            write_character(w, fit.character)
            w.metrics.update(fit.metrics)
            w.units.update(fit_units())
            w.timing.update(fit.timing)
            if not w.single_file:
                write_image(w.path("preview.png"), scan_fit_image(
                    fit.character, scan_vertices, scan_faces, fit.template_to_scan_m,
                    width=cfg.preview_width, height=cfg.preview_height))
        return self.run.produce(out, "character", write, inputs=[artifact] if artifact is not None else [],
                                source_files=sources)

    def preview(self, character_path: Path, out: Path) -> Path:
        from egorelight_cli.io.images import write_image
        from egorelight_cli.render.preview import character_preview_image

        character, artifact = load_character(character_path)
        check_output_location(out, _character_paths(character_path, artifact))
        if out.suffix.lower() not in PREVIEW_SUFFIXES:
            raise EgorelightError(f"--out must name an image file ({', '.join(PREVIEW_SUFFIXES)})", out)
        if out.exists() and not self.run.force:
            raise EgorelightError("--out exists; not replacing it (--force replaces it)", out)
        cfg = self.run.config()
        image = character_preview_image(character, width=cfg.preview_width, height=cfg.preview_height)
        out.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(out)
        tmp = temporary_sibling(out, suffix=out.suffix)
        try:
            write_image(tmp, image)
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)
        return out


def character_sources(spec: str, artifact: Artifact | None) -> list[Path]:
    """Files a character came from that are not an artifact (cache keys, provenance)."""
    if artifact is not None:
        return []
    if str(spec) == "default":
        return [default_character_path()]
    path = Path(spec)
    if path.suffix == ".character":
        from egorelight_cli.io.ddc import ddc_character_files

        return ddc_character_files(path)
    return [path]


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def default_command(run: StageRun, out: Path) -> Path:
    return CharacterCommands(run).default(out)


def from_makehuman_command(run: StageRun, data_dir: Path | None, out: Path) -> Path:
    return CharacterCommands(run).from_makehuman(out, data_dir)


def import_ddc_command(run: StageRun, path: Path, out: Path) -> Path:
    return CharacterCommands(run).import_ddc(path, out)


def export_ddc_command(run: StageRun, character: Path, name: str, out: Path) -> Path:
    return CharacterCommands(run).export_ddc(character, out, name)


def fit_scan_command(run: StageRun, scan: Path, character: str, out: Path) -> Path:
    return CharacterCommands(run).fit_scan(scan, character, out)


def preview_command(run: StageRun, character: Path, out: Path) -> Path:
    return CharacterCommands(run).preview(character, out)
