"""The ``synth`` stage: a simulated lightstage + HMD capture of a synthetic subject, with ground truth.

``egorelight synth --out DIR [--character C] [--envmap PATH ...] [--motion PATH]`` writes a
capture artifact (DESIGN.md Sec. 5; formats in :mod:`egorelight_cli.synth.capture`). The subject is
the default character (or ``--character``); its motions come from the built-in library
(:mod:`egorelight_cli.synth.motions`), which needs the default character's DoF names, or from a
motion artifact (``--motion``). ``--envmap`` adds user HDR maps (``.exr``/``.hdr``) to the test
lighting.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from egorelight_cli.artifacts import MANIFEST_NAME, Artifact, ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.pipeline import StageRun
from egorelight_cli.structures.character import Character

STAGE = "synth"


def synthesize(writer: ArtifactWriter, cfg: Config, character: Character, envmap_paths=(), motion=None) -> None:
    """Fill ``writer`` (kind ``capture``) with a simulated capture.

    Args:
        writer: the capture artifact writer.
        cfg: the resolved ``synth`` config.
        character: the subject.
        envmap_paths: user HDR maps added to the test lighting (named by file stem, prefixed ``user_``).
        motion: a :class:`~egorelight_cli.io.motion.Motion` replacing the motion library, or None.
    """
    from egorelight_cli.render.envmaps import load_envmap
    from egorelight_cli.synth.capture import write_capture
    from egorelight_cli.synth.motions import check_motion_dofs

    user = {}
    for path in envmap_paths:
        name = f"user_{Path(path).stem}"
        if name in user:
            raise EgorelightError(f"two --envmap files share the name {Path(path).stem!r}", path)
        user[name] = load_envmap(path, height=int(cfg.envmaps.height))
    motion_theta = None
    if motion is not None:
        motion.check_dofs(character.skeleton.dof_names)
        motion_theta = motion.theta
    else:
        check_motion_dofs(character)
    write_capture(writer, cfg, character, user, motion_theta)


@dataclass(frozen=True)
class SynthCommand:
    """``egorelight synth`` over one :class:`StageRun` (the global options)."""

    run: StageRun

    def __call__(self, out: Path, character: str | None, envmaps: tuple[Path, ...], motion: Path | None) -> Path:
        from egorelight_cli.io.motion import load_motion
        from egorelight_cli.stages.character_commands import load_character

        _keep_an_imported_capture(Path(out), self.run.force)
        subject, character_artifact = load_character(character or "default")
        inputs: list[Artifact] = [a for a in (character_artifact,) if a is not None]
        sources: list[Path] = [Path(p) for p in envmaps]
        loaded_motion = None
        if motion is not None:
            loaded_motion, motion_artifact = load_motion(motion)
            if motion_artifact is not None:
                inputs.append(motion_artifact)
            else:
                sources.append(Path(motion))
        if character and character_artifact is None and character != "default":
            sources.append(Path(character))
        return self.run.produce(out, "capture", lambda w, cfg: synthesize(w, cfg, subject, envmaps, loaded_motion),
                                inputs=inputs, source_files=sources)


def _keep_an_imported_capture(out: Path, force: bool) -> None:
    """A capture ``capture import`` made (a lab's real one) is not replaced by a simulated one
    unless ``--force`` says so (make re-runs synth when the venv is reinstalled)."""
    from egorelight_cli.atomic_output import restore_interrupted_swap

    if force:
        return
    restore_interrupted_swap(out)  # an import a kill left half swapped is judged as the capture it was
    manifest = out / MANIFEST_NAME
    if not manifest.is_file():
        return
    try:
        stage = json.loads(manifest.read_text()).get("stage")
    except (OSError, ValueError, AttributeError):
        return  # not ours to judge here: the output checks that follow say what is wrong
    if stage == "capture":
        raise EgorelightError("--out holds an imported capture (`capture import`), not a simulated one: synth does "
                              "not replace it (--force does)", out)


def synth_command(run: StageRun, character: str, envmaps: tuple[Path, ...], motion: Path | None, out: Path) -> Path:
    """``egorelight synth`` (declared in :mod:`egorelight_cli.declarations`)."""
    return SynthCommand(run)(out, character, envmaps, motion)
