"""Reading a capture (DESIGN.md Sec. 5): rig, sequences and their per-frame files.

The layout is documented in :mod:`egorelight_cli.synth.capture` (which writes it); this module is
the one place every stage reads it from, so a real capture converted to the same layout runs
through the same code. Nothing here reads ``groundtruth/`` (see :mod:`egorelight_cli.synth.groundtruth`).

Frame ids: ``studio``, ``masks``, ``normals``, ``recon`` and ``mocap`` files are named by studio
(master-clock) frame id; ``ego/<role>/`` files by ego frame id. The calibration's
``stream_offset`` maps one to the other (:meth:`Calibration.ego_frame_id`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from egorelight_cli.errors import EgorelightError

if TYPE_CHECKING:  # geometry.cameras imports torch: loaded on first use, not by opening a capture
    from egorelight_cli.geometry.cameras import Camera

CAPTURE_KIND = "capture"
SEQUENCES = "sequences"
PURPOSES = ("handeye", "ego_train", "relight_train", "test", "wild")


def frame_file(frame_id: int, suffix: str) -> str:
    """File name of a frame: zero-padded id plus suffix (``000012.png``)."""
    return f"{int(frame_id):06d}{suffix}"


def read_json_file(path: Path, what: str):
    """A JSON file of the capture; missing or malformed files are EgorelightErrors."""
    if not path.exists():
        raise EgorelightError(f"{what} not found", path)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise EgorelightError(f"{what} is not valid JSON ({exc})", path) from None


def _cameras(entries, key: str, what: str, path: Path, **kwargs) -> dict:
    """``{entry[key]: Camera}`` of a rig file's camera entries (``kwargs`` to
    :meth:`~egorelight_cli.geometry.cameras.Camera.from_dict`); a bad entry is an error naming ``path``."""
    from egorelight_cli.geometry.cameras import Camera

    cameras = {}
    for entry in entries:
        try:
            cameras[entry[key]] = Camera.from_dict(entry, **kwargs)
        except EgorelightError as exc:  # e.g. a field missing: said without the file
            raise EgorelightError(f"invalid {what} camera entry: {exc.message}", path) from None
        except (KeyError, ValueError, TypeError) as exc:
            raise EgorelightError(f"invalid {what} camera entry ({type(exc).__name__}: {exc})", path) from None
    return cameras


@dataclass(frozen=True)
class SequenceInfo:
    """One ``sequences/<name>/sequence.json`` and the folder it lives in.

    Attributes:
        name: sequence folder name.
        root: the sequence folder.
        doc: the parsed ``sequence.json``.
    """

    name: str
    root: Path
    doc: dict

    @property
    def purpose(self) -> str:
        return str(self.doc.get("purpose", ""))

    @property
    def fps(self) -> float:
        return float(self.doc["fps"])

    @property
    def frame_ids(self) -> np.ndarray:
        """(T,) int64 studio (master-clock) frame ids; empty without a studio stream."""
        return np.asarray(self.doc.get("frame_ids", []), dtype=np.int64)

    @property
    def ego_frame_ids(self) -> np.ndarray:
        """(T_ego,) int64 ego frame ids; empty without ego streams."""
        return np.asarray(self.doc.get("ego_frame_ids", []), dtype=np.int64)

    @property
    def content_frame_ids(self) -> np.ndarray:
        """(T_c,) int64 studio frames after the standby / sync-code prefix (wild: ego ids)."""
        ids = self.doc.get("content_frame_ids") or self.doc.get("frame_ids") or self.doc.get("ego_frame_ids", [])
        return np.asarray(ids, dtype=np.int64)

    @property
    def streams(self) -> dict:
        return dict(self.doc.get("streams", {}))

    @property
    def ego_roles(self) -> list[str]:
        return list(self.streams.get("ego", []))

    @property
    def studio_cameras(self) -> list[str]:
        return list(self.streams.get("studio", []))

    @property
    def lights(self) -> list[dict]:
        """Per studio frame light entry (pattern, envmap, yaw_deg, olat_index, scale)."""
        return list(self.doc.get("lights", []))

    def require_stream(self, stream: str) -> None:
        """An EgorelightError when this sequence lacks ``stream`` (ego, studio, mocap, recon, ...)."""
        value = self.streams.get(stream)
        if not value:
            raise EgorelightError(f"sequence {self.name!r} has no {stream} stream", self.root / "sequence.json")

    def check_frames(self, frame_ids, available: np.ndarray, what: str) -> np.ndarray:
        """``frame_ids`` as int64, each one checked to be in ``available``."""
        frame_ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        missing = np.setdiff1d(frame_ids, available)
        if missing.size:
            lo, hi = (int(available.min()), int(available.max())) if available.size else (0, -1)
            raise EgorelightError(f"{what} frame {int(missing[0])} is out of range for sequence {self.name!r} "
                                  f"(frames {lo}..{hi})", self.root / "sequence.json")
        return frame_ids

    def flat_lit(self, frame_ids) -> np.ndarray:
        """The frames of ``frame_ids`` lit ``flat`` (all of them when the sequence lists no lights)."""
        frame_ids = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        if not self.lights:
            return frame_ids
        pattern = {int(f): str(entry.get("pattern", "flat")) for f, entry in zip(self.frame_ids, self.lights)}
        return np.array([f for f in frame_ids if pattern.get(int(f), "flat") == "flat"], np.int64)

    def light_entry(self, frame_id: int) -> dict:
        """The light entry of studio frame ``frame_id`` (an EgorelightError when it has none)."""
        for f, entry in zip(self.frame_ids, self.lights):
            if int(f) == int(frame_id):
                return dict(entry)
        raise EgorelightError(f"sequence {self.name!r} lists no lighting for frame {int(frame_id)}",
                              self.root / "sequence.json")

    def ego_image_path(self, role: str, ego_frame_id: int) -> Path:
        return self.root / "ego" / role / frame_file(ego_frame_id, ".png")

    def studio_image_path(self, camera: str, frame_id: int) -> Path:
        """The studio frame file (``.exr``, else ``.png``/``.dng`` when that exists)."""
        base = self.root / "studio" / camera
        for suffix in (".exr", ".png", ".dng"):
            path = base / frame_file(frame_id, suffix)
            if path.exists():
                return path
        return base / frame_file(frame_id, ".exr")

    def mask_path(self, camera: str, frame_id: int) -> Path:
        return self.root / "masks" / camera / frame_file(frame_id, ".png")

    def normals_path(self, camera: str, frame_id: int) -> Path:
        return self.root / "normals" / camera / frame_file(frame_id, ".exr")

    def recon_path(self, frame_id: int) -> Path:
        return self.root / "recon" / frame_file(frame_id, ".ply")

    def read_ego_image(self, role: str, ego_frame_id: int) -> np.ndarray:
        """(H,W,3) uint8 sRGB ego image; a missing or unreadable file is an EgorelightError."""
        from egorelight_cli.io.images import read_image

        path = self.ego_image_path(role, ego_frame_id)
        if not path.exists():
            raise EgorelightError(f"ego image of {role} frame {ego_frame_id} not found", path)
        image = read_image(path)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        return np.ascontiguousarray(image[..., :3])

    def mocap_path(self) -> Path:
        return self.root / "mocap.npz"

    def head_pose_path(self) -> Path:
        return self.root / "head_pose.npz"


class Capture:
    """A capture directory: ``Capture(root)`` checks it is one, the rest is read on demand."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise EgorelightError("capture directory not found", self.root)
        if not (self.root / "rig").is_dir() or not (self.root / SEQUENCES).is_dir():
            raise EgorelightError("not a capture (expected rig/ and sequences/ folders)", self.root)

    @cached_property
    def hmd(self) -> dict:
        """The parsed ``rig/hmd.json`` (cameras, markers, frame description)."""
        return read_json_file(self.root / "rig" / "hmd.json", "HMD description")

    @cached_property
    def ego_cameras(self) -> dict[str, Camera]:
        """Intrinsics of every HMD camera by role (extrinsics identity: they are unknown)."""
        return _cameras(self.hmd.get("cameras", []), "role", "HMD", self.root / "rig" / "hmd.json",
                        T_cam_from_world=np.eye(4))

    def ego_camera(self, role: str) -> Camera:
        if role not in self.ego_cameras:
            raise EgorelightError(f"the HMD has no camera with role {role!r} (has {', '.join(self.ego_cameras)})",
                                  self.root / "rig" / "hmd.json")
        return self.ego_cameras[role]

    @cached_property
    def studio_cameras(self) -> dict[str, Camera]:
        """Every studio camera by name (``role`` studio or tracking in :attr:`studio_camera_roles`)."""
        path = self.root / "rig" / "studio_cameras.json"
        return _cameras(read_json_file(path, "studio camera rig").get("cameras", []), "name", "studio", path)

    @cached_property
    def studio_camera_roles(self) -> dict[str, str]:
        doc = read_json_file(self.root / "rig" / "studio_cameras.json", "studio camera rig")
        return {entry["name"]: entry.get("role", "studio") for entry in doc.get("cameras", [])}

    @cached_property
    def board(self) -> dict:
        """The parsed ``rig/board.json`` (ChArUco board of the hand-eye sequence)."""
        return read_json_file(self.root / "rig" / "board.json", "calibration board description")

    def lights_path(self) -> Path:
        return self.root / "rig" / "lights.json"

    def envmap_path(self, name: str) -> Path:
        return self.root / "envmaps" / f"{name}.exr"

    def sequence_names(self) -> list[str]:
        return sorted(p.name for p in (self.root / SEQUENCES).iterdir() if (p / "sequence.json").exists())

    def sequence(self, name: str) -> SequenceInfo:
        folder = self.root / SEQUENCES / name
        if not (folder / "sequence.json").exists():
            raise EgorelightError(f"capture has no sequence {name!r} (has {', '.join(self.sequence_names()) or 'none'})",
                                  self.root / SEQUENCES)
        doc = read_json_file(folder / "sequence.json", "sequence description")
        if not isinstance(doc, dict):
            raise EgorelightError(f"sequence description must be a JSON object, got a {type(doc).__name__}",
                                  folder / "sequence.json")
        return SequenceInfo(name, folder, doc)

    def sequences_with_purpose(self, purpose: str) -> list[SequenceInfo]:
        return [s for s in (self.sequence(n) for n in self.sequence_names()) if s.purpose == purpose]

    def groundtruth_root(self) -> Path | None:
        """The capture root when it carries ``groundtruth/`` (simulated captures), else None.

        Only evaluation code may read what lies there."""
        return self.root if (self.root / "groundtruth").is_dir() else None

    def groundtruth_file(self, sequence: str, name: str) -> Path | None:
        """``groundtruth/<sequence>/<name>`` when it exists (evaluation code only), else None."""
        path = self.root / "groundtruth" / sequence / name
        return path if path.is_file() else None


def read_reconstructions(seq: SequenceInfo, frame_ids) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Frame id -> (vertices, faces) of the multi-view reconstructions of ``frame_ids`` that exist."""
    from egorelight_cli.io.meshes import read_mesh

    out = {}
    for f in np.asarray(frame_ids, dtype=np.int64).reshape(-1):
        path = seq.recon_path(int(f))
        if path.is_file():
            v, faces = read_mesh(path)
            if not np.isfinite(v).all():
                raise EgorelightError("reconstruction holds NaN or inf vertices", path)
            out[int(f)] = (v, faces)
    return out


def open_capture(path: str | Path, sequences: Sequence[str] | None = None) -> tuple[Capture, "Artifact"]:  # noqa: F821
    """Open a capture artifact (its manifest is checked and becomes the stage's cache-key input).

    Every payload's sha256 is checked against the manifest; with ``sequences`` only those of the
    rig, the environment maps and the named sequences (and their ground truth), for a stage that
    reads no other sequence (a cpu-preset capture holds about 300 MB in 5000 files).
    """
    from egorelight_cli.artifacts import open_artifact

    artifact = open_artifact(path, kind=CAPTURE_KIND, verify=sequences is None)
    if sequences is not None:
        per_sequence = (SEQUENCES, "groundtruth")

        def read_by_stage(rel: str) -> bool:
            parts = rel.split("/")
            return parts[0] not in per_sequence or len(parts) < 3 or parts[1] in sequences

        artifact.verify(only=read_by_stage)
    if artifact.single_file:
        raise EgorelightError("a capture is a directory artifact", path)
    capture = Capture(artifact.root)
    for name in sequences or ():
        capture.sequence(name)  # a sequence the capture lacks is an error that lists the ones it has
    return capture, artifact
