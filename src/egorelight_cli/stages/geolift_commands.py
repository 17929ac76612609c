"""The ``egorelight train geolift`` and ``egorelight geolift`` commands: load inputs, call
:mod:`egorelight_cli.stages.geolift`, write artifacts.

``train geolift`` (capture + tracked meshes of its relit training sequence + character) writes a
model artifact: ``model.pt`` (GeoLiftingNet, and in ``extra`` the UV resolution, the mean-texture
baseline, the flat lighting scale and the cameras and frames used), ``curve.json``/``curve.png``.
Its metrics hold the errors on the training views and on held-out flat-lit frames, each next to
the baselines (coarse normals, mean texture).

``geolift`` (any meshes artifact + model + character) writes a ``uvmaps`` artifact:
``maps/<frame>.exr`` with layers ``normal`` (X,Y,Z: unit world-space normals), ``albedo``
(R,G,B: flat-lit texture, linear radiance), ``coverage`` (Y: 1 on texels of the layout) and, with
``--capture`` and a sequence whose frames list their lighting, ``shadow`` (Y: rho) and
``diffuse`` (R,G,B: chi, the irradiance) from ``render/uv_features.py``; ``preview.png``; and
with ground truth in the capture, the normal and texture errors next to the baselines.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.artifacts import Artifact, ArtifactWriter, check_sequence, open_artifact
from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.capture import Capture, frame_file, open_capture
from egorelight_cli.io.mesh_sequence import load_meshes
from egorelight_cli.structures.mesh_sequence import MeshSequence
from egorelight_cli.nn.geolift_net import GeoLiftNet
from egorelight_cli.nn.training import Checkpoint, checkpoint_beside
from egorelight_cli.pipeline import StageRun
from egorelight_cli.sharding import FrameRange
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.stages import geolift as gl
from egorelight_cli.structures.character import Character

PREVIEW_PNG = "preview.png"
MAPS_DIR = "maps"


def load_character_meshes(path: Path, character: Character) -> tuple[MeshSequence, Artifact | None]:
    meshes, artifact = load_meshes(path)
    if meshes.vertices.shape[1] != len(character.vertices):
        raise EgorelightError(f"meshes have {meshes.vertices.shape[1]} vertices, the character "
                              f"{len(character.vertices)}: they were not made with this character", path)
    return meshes, artifact


def training_cameras(capture: Capture, sequence) -> list[str]:
    """The sequence's studio cameras (role ``studio``) that are not held out."""
    held_out = set(sequence.doc.get("held_out_cameras", []))
    names = [n for n in sequence.studio_cameras if capture.studio_camera_roles.get(n, "studio") == "studio"]
    return [n for n in names if n not in held_out]


def split_held_out(frames: np.ndarray, fraction: float, what: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(training, held-out) frames: the last ``fraction`` of ``frames`` (at least one) is held out,
    and at least one frame must be left to train on; ``what`` and ``path`` name them in the error."""
    held = max(1, int(round(float(fraction) * len(frames))))
    if held >= len(frames):
        raise EgorelightError(f"train.validation_fraction {fraction} holds out all {len(frames)} {what}: "
                              "lower it so that at least one frame is left to train on", path)
    return frames[:-held], frames[-held:]


def _flat_scale(sequence, frames: np.ndarray) -> float:
    scales = {float(sequence.light_entry(int(f)).get("scale", 1.0)) for f in frames} if sequence.lights else {1.0}
    return float(np.median(sorted(scales)))


def load_geolift_model(path: Path) -> tuple[GeoLiftNet, dict, Artifact]:
    """(network, extras, artifact) of a ``train geolift`` model."""
    from egorelight_cli.io.model import read_model

    artifact = open_artifact(path, kind="model")
    if artifact.single_file:
        raise EgorelightError("a geolift model is a directory artifact", path)
    payload = read_model(artifact.root, stage=gl.MODEL_STAGE)
    try:
        model = GeoLiftNet(int(payload.architecture["base_channels"]), int(payload.architecture["levels"]),
                           int(payload.architecture["uv_resolution"]))
        model.load_state_dict(payload.state_dict)
    except (KeyError, RuntimeError) as exc:
        raise EgorelightError(f"geolift model does not match the network ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0]})", path) from None
    return model.eval(), payload.extra, artifact


@dataclass(frozen=True)
class GeoliftCommands:
    """``geolift`` and ``train geolift`` over one :class:`StageRun`."""

    run: StageRun

    # ------------------------------------------------------------------------------- train
    def train(self, capture_path: Path, meshes_paths: list[Path], character_spec: str, out: Path,
              sequences: list[str] | None = None, resume: bool = False) -> Path:
        """Train on the flat-lit frames of one or more sequences, each with its tracked meshes
        (``meshes_paths[i]`` belongs to ``sequences[i]``; one meshes artifact defaults to
        ``train.sequence``). The last ``validation_fraction`` of each sequence's frames is held out."""
        from egorelight_cli.stages.character_commands import character_sources, load_character

        cfg = self.run.config()
        sequences = list(sequences or [str(cfg.train.sequence)])
        if len(sequences) != len(meshes_paths):
            raise EgorelightError(f"{len(meshes_paths)} --meshes but {len(sequences)} --seq: give one sequence per "
                                  "meshes artifact (in the same order)")
        character, character_artifact = load_character(character_spec)
        capture, capture_artifact = open_capture(capture_path)
        parts, inputs = [], [a for a in (capture_artifact, character_artifact) if a is not None]
        sources = character_sources(character_spec, character_artifact)
        for name, meshes_path in zip(sequences, meshes_paths):
            sequence = capture.sequence(name)
            sequence.require_stream("recon")
            meshes, meshes_artifact = load_character_meshes(meshes_path, character)
            check_sequence(meshes_artifact, name)
            frames = sequence.flat_lit(np.intersect1d(meshes.frame_ids, sequence.content_frame_ids))
            if len(frames) < 2:
                raise EgorelightError(f"the meshes cover {len(frames)} flat-lit frame(s) of sequence {name!r}; "
                                      "training and validation need at least 2", meshes_path)
            train_frames, val_frames = split_held_out(frames, cfg.train.validation_fraction,
                                                      f"flat-lit frame(s) of sequence {name!r}", meshes_path)
            parts.append((sequence, meshes, train_frames, val_frames, training_cameras(capture, sequence)))
            inputs += [meshes_artifact] if meshes_artifact is not None else []
            sources += [] if meshes_artifact else [meshes_path]
        self.run.compute_device()  # CPU stage: --device cuda is refused, not silently ignored
        checkpoint = checkpoint_beside(out)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.io.model import ModelPayload, write_model

            if writer.single_file:
                raise EgorelightError("a geolift model is a directory artifact: give --out a directory name", out)
            started = time.perf_counter()
            raster = rasterize_uv(character.face_uvs, int(cfg.net.uv_resolution))
            maps, starts, train_views, val_views, offset = [], [], [], [], 0
            for sequence, meshes, train_frames, val_frames, cameras in parts:
                maps.append(gl.coarse_maps(raster, meshes.vertices, character.faces, character.face_uvs))
                starts.append(np.full(meshes.num_frames, offset, np.int64))
                for frames, views in ((train_frames, train_views), (val_frames, val_views)):
                    views += gl.build_views(capture, sequence, meshes, character.faces, character.face_uvs, frames,
                                            cameras, offset)
                offset += meshes.num_frames
            coarse = gl.CoarseMaps(np.concatenate([m.normals for m in maps]), np.concatenate([m.frames for m in maps]))
            texture = gl.mean_texture(train_views, raster.resolution)
            writer.timing["views_s"] = round(time.perf_counter() - started, 3)
            console.info(f"train geolift: {len(train_views)} views of {', '.join(sequences)}, "
                         f"{len(val_views)} held-out views")
            started = time.perf_counter()
            model, curve = gl.train_geolift(train_views, coarse, np.concatenate(starts),
                                            gl.TrainSettings.from_config(cfg), cfg.net, texture,
                                            Checkpoint(checkpoint, writer.cache_key, resume))
            writer.timing["train_s"] = round(time.perf_counter() - started, 3)
            writer.metrics.update(gl.fit_report(model, train_views, coarse, texture))
            validation = gl.fit_report(model, val_views, coarse, texture)
            writer.metrics.update({k.replace("train_", "val_", 1): v for k, v in validation.items()})
            extra = {"uv_resolution": int(cfg.net.uv_resolution), "mean_texture": torch.from_numpy(texture),
                     "flat_scale": float(np.median([_flat_scale(p[0], p[2]) for p in parts])),
                     "sequences": sequences, "cameras": sorted({c for p in parts for c in p[4]}),
                     "train_frames": {p[0].name: p[2].tolist() for p in parts},
                     "val_frames": {p[0].name: p[3].tolist() for p in parts},
                     "detail_loss": "neighbour-difference L1 (substitute: no VGG weights)"}
            write_model(writer.workdir, ModelPayload(gl.MODEL_STAGE, model.architecture(), model.state_dict(), extra,
                                                     curve), curve_title="geolift training loss")
            writer.metrics.update({
                "sequences": sequences, "training_views": len(train_views), "validation_views": len(val_views),
                "loss_first": curve[0]["loss"], "loss_last": curve[-1]["loss"],
                "detail_loss": extra["detail_loss"],
            })
            writer.units.update({"rgb_l1": "linear radiance", "normal_deg": "degrees"})

        result = self.run.produce(out, "model", write, inputs=inputs, source_files=sources,
                                  options={"training_sequences": sequences})
        checkpoint.unlink(missing_ok=True)
        return result

    # ------------------------------------------------------------------------------ predict
    def predict(self, meshes_path: Path, model_path: Path, character_spec: str, capture_path: Path | None,
                seq: str, out: Path, frame_range: FrameRange = FrameRange()) -> Path:
        from egorelight_cli.stages.character_commands import character_sources, load_character

        character, character_artifact = load_character(character_spec)
        meshes, meshes_artifact = load_character_meshes(meshes_path, character)
        model, extra, model_artifact = load_geolift_model(model_path)
        capture = sequence = capture_artifact = None
        if capture_path is not None:
            capture, capture_artifact = open_capture(capture_path)
            sequence = capture.sequence(seq)
            check_sequence(meshes_artifact, seq)  # the lighting features are the sequence's
        inputs = [a for a in (character_artifact, meshes_artifact, model_artifact, capture_artifact) if a is not None]
        sources = character_sources(character_spec, character_artifact) + ([] if meshes_artifact else [meshes_path])
        self.run.compute_device()

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.stages.geolift_maps import write_uvmaps

            if writer.single_file:
                raise EgorelightError("a uvmaps artifact is a directory (it holds EXR maps): give --out a directory",
                                      out)
            write_uvmaps(writer, cfg, model, extra, character, meshes, capture, sequence, frame_range)

        return self.run.produce(out, "uvmaps", write, inputs=inputs, source_files=sources)


def map_path(frame_id: int) -> str:
    """Relative path of a frame's UV maps in a uvmaps artifact."""
    return f"{MAPS_DIR}/{frame_file(frame_id, '.exr')}"


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def train_command(run: StageRun, capture: Path, meshes: tuple[Path, ...], character: str,
                  sequences: tuple[str, ...], resume: bool, out: Path) -> Path:
    return GeoliftCommands(run).train(capture, list(meshes), character, out, list(sequences) or None, resume)


def geolift_command(run: StageRun, meshes: Path, model: Path, character: str, capture: Path | None, sequence: str,
                    out: Path, frame_range: FrameRange) -> Path:
    return GeoliftCommands(run).predict(meshes, model, character, capture, sequence, out, frame_range)
