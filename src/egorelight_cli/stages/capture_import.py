"""``egorelight capture import SOURCE --out DIR``: a capture converted to the layout made an artifact.

A lab's own lightstage capture, converted to the capture layout (``rig/``, ``sequences/<seq>/``,
optional ``envmaps/``, ``scan/``; DESIGN.md Sec. 5), has no manifest, and every stage reads a
capture artifact (its manifest's digests are the stages' cache keys and integrity checks). This
command checks the folder the way the stages will read it, then writes it as a capture artifact:
each file hard-linked into the output where the filesystem allows (no second copy of the
frames; a later edit of a source file is then caught by the digests) or copied
(``--set link=false``). Nothing in the source is changed.

Checked, each failure a one-line error naming the file: the rig (``hmd.json``,
``studio_cameras.json``, ``lights.json``: parsed as the stages parse them), at least one
sequence, every sequence description, the cameras and ego roles it names, and that every frame
file it implies exists (studio images and masks per studio camera and frame, ego images per
role and ego frame); environment maps its light entries name. A ``groundtruth/`` folder is
carried along when present (a simulated capture's; only evaluation code reads it). The
manifest's metrics say what was found: sequences with their frame counts, files and bytes;
``preview.png`` shows each sequence's first ego frame per role and first studio frame of up to
three subject cameras (decoding them: a first frame that cannot be read is an error here).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import MANIFEST_NAME, ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.io.folders import visible_files
from egorelight_cli.pipeline import StageRun

PREVIEW_PNG = "preview.png"
#: what a stage needs of the rig (board.json only for calibrate's hand-eye sequence)
RIG_FILES = ("hmd.json", "studio_cameras.json", "lights.json")


def check_capture(source: Path) -> dict:
    """Check ``source`` as the stages will read it (see the module docstring); returns what was
    found, for the manifest's metrics."""
    from egorelight_cli.render.lightstage import LightStage

    if (source / MANIFEST_NAME).is_file():
        raise EgorelightError("already a finished artifact (it has a manifest.json): give it to the stages as it is",
                              source)
    capture = Capture(source)
    for name in RIG_FILES:
        if not (source / "rig" / name).is_file():
            raise EgorelightError(f"the rig lacks {name}", source / "rig")
    ego_roles, studio = set(capture.ego_cameras), set(capture.studio_cameras)
    lights = LightStage.from_json(capture.lights_path())
    names = capture.sequence_names()
    if not names:
        raise EgorelightError("no sequence (expected sequences/<name>/sequence.json)", source / "sequences")
    sequences = {name: _check_sequence(capture, capture.sequence(name), ego_roles, studio) for name in names}
    return {"sequences": sequences, "ego_cameras": sorted(ego_roles), "studio_cameras": len(studio),
            "lights": lights.num_lights, "board": (source / "rig" / "board.json").is_file(),
            "groundtruth": (source / "groundtruth").is_dir()}


def _check_sequence(capture: Capture, sequence: SequenceInfo, ego_roles: set[str], studio: set[str]) -> dict:
    where = sequence.root / "sequence.json"
    unknown_roles = sorted(set(sequence.ego_roles) - ego_roles)
    if unknown_roles:
        raise EgorelightError(f"names ego cameras the HMD lacks: {', '.join(unknown_roles)}", where)
    unknown = sorted(set(sequence.studio_cameras) - studio)
    if unknown:
        raise EgorelightError(f"names studio cameras the rig lacks: {', '.join(unknown[:5])}", where)
    expected = [sequence.ego_image_path(role, int(f)) for role in sequence.ego_roles for f in sequence.ego_frame_ids]
    expected += [sequence.studio_image_path(camera, int(f)) for camera in sequence.studio_cameras
                 for f in sequence.frame_ids]
    if sequence.streams.get("masks"):  # of the subject cameras (tracking cameras see the headset's markers)
        roles = capture.studio_camera_roles
        expected += [sequence.mask_path(camera, int(f)) for camera in sequence.studio_cameras
                     if roles.get(camera, "studio") == "studio" for f in sequence.frame_ids]
    if sequence.streams.get("mocap"):
        expected.append(sequence.mocap_path())
    missing = [p for p in expected if not p.is_file()]
    if missing:
        raise EgorelightError(f"{len(missing)} of the {len(expected)} frame files sequence.json implies are missing, "
                              f"the first", missing[0])
    for entry in sequence.lights:
        name = entry.get("envmap") if isinstance(entry, dict) else None
        if name and not capture.envmap_path(name).is_file():
            raise EgorelightError(f"a light entry names the environment map {name!r}, which is missing",
                                  capture.envmap_path(name))
    return {"purpose": sequence.purpose, "frames": int(len(sequence.frame_ids)),
            "ego_frames": int(len(sequence.ego_frame_ids)) if sequence.ego_roles else 0,
            "studio_cameras": len(sequence.studio_cameras)}


def preview(capture: Capture) -> np.ndarray:
    """(H,W,3) uint8 contact sheet: per sequence, its first ego frame of each role and its first
    studio frame (tone-mapped) of up to three subject cameras (EXR or PNG)."""
    from egorelight_cli.stages.calibrate_head import studio_image
    from egorelight_cli.render.sheets import contact_sheet

    rows = []
    for name in capture.sequence_names():
        sequence = capture.sequence(name)
        tiles = [(f"{name} {role}", sequence.read_ego_image(role, int(sequence.ego_frame_ids[0])))
                 for role in sequence.ego_roles if len(sequence.ego_frame_ids)]
        subject = [c for c in sequence.studio_cameras if capture.studio_camera_roles.get(c, "studio") == "studio"]
        for camera in subject[:3] if len(sequence.frame_ids) else []:
            if sequence.studio_image_path(camera, int(sequence.frame_ids[0])).suffix in (".exr", ".png"):
                tiles.append((f"{name} {camera}", studio_image(sequence, camera, int(sequence.frame_ids[0]), 99.0)[0]))
        rows.append(tiles)
    return contact_sheet(rows, title=f"imported capture: {len(rows)} sequences", tile_height=160)


def place(source: Path, target: Path, link: bool) -> bool:
    """Put ``source`` at ``target``: a hard link when ``link`` and the filesystem allows it (True),
    else a copy (False)."""
    if link:
        try:
            os.link(source, target)
            return True
        except OSError:  # another filesystem, or one without hard links
            pass
    shutil.copy2(source, target)
    return False


def import_command(run: StageRun, source: Path, out: Path) -> Path:
    source = Path(source)
    if not source.is_dir():
        raise EgorelightError("capture folder not found", source)
    folder, target = source.resolve(), Path(out).resolve()
    if target.is_relative_to(folder) or folder.is_relative_to(target):
        raise EgorelightError("--out lies inside the capture folder it imports (or holds it): give another folder", out)
    found = check_capture(source)
    files = [path.relative_to(source) for path in visible_files(source)]  # labs link large frame folders in
    console.info(f"capture import: {len(found['sequences'])} sequences, {len(files)} files")

    def write(writer: ArtifactWriter, cfg: Config) -> None:
        if writer.single_file:
            raise EgorelightError("a capture is a directory: give --out a directory", out)
        from egorelight_cli.io.images import write_image

        if Path(PREVIEW_PNG) not in files:  # (one the source brings is kept as it is)
            write_image(writer.path(PREVIEW_PNG), preview(Capture(source)))
        linked = sum(place(source / rel, writer.path(rel.as_posix()), bool(cfg.link)) for rel in files)
        size = sum((source / rel).stat().st_size for rel in files)
        writer.metrics.update({**found, "files": len(files), "bytes": size, "hard_linked_files": int(linked)})
        writer.extra["source"] = str(source.resolve())

    return run.produce(out, "capture", write, source_files=[source / rel for rel in files])
