"""The ``egorelight train relight`` and ``egorelight relight`` commands.

``train relight`` (capture + tracked meshes + uvmaps of its relit training sequence) fits
:class:`~egorelight_cli.stages.relight.RelightModel` on the HDR-lit frames seen by the
non-held-out studio cameras and writes a model artifact; the last frames are held out and scored
(PSNR/SSIM next to the Lambert and baked-texture baselines).

``relight`` (capture + meshes + uvmaps of a sequence + model) renders the avatar under the
sequence's own lighting into the sequence's held-out cameras (``--cameras all``: every studio
camera) and writes a ``renders`` artifact: ``<camera>/<frame>.exr`` (linear HDR, layers ``""``
RGB, ``diffuse``, ``specular``, ``alpha``) and ``<camera>/<frame>.png`` (the metric tone
mapping), ``preview.png``, and the scores of every view against the captured image. Under
another lighting than the sequence's own (:class:`LightingOverride`: ``--flat``, ``--olat i``,
``--envmap FILE`` [``--yaw``], where FILE may be an ``envmap`` artifact) every frame with UV maps
is rendered, ``rho``/``chi`` are recomputed for that light from GeoLift's normals and the mesh,
and nothing is scored (no image was captured under that light).
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
from egorelight_cli.io.exr import read_exr, write_exr_layers
from egorelight_cli.io.images import read_image, write_image
from egorelight_cli.nn.distributed import rank_share
from egorelight_cli.nn.training import Checkpoint, checkpoint_beside, train
from egorelight_cli.render.image_metrics import tonemap_for_metrics
from egorelight_cli.pipeline import StageRun
from egorelight_cli.render.lighting import CaptureEnvmaps, light_intensities
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.render.uv_features import TexelLighting, lighting_feature_maps
from egorelight_cli.stages import relight as rl
from egorelight_cli.stages.geolift_commands import (load_character_meshes, map_path, split_held_out,
                                                    training_cameras)
from egorelight_cli.sharding import FrameRange, stack_preview_rows, write_preview
from egorelight_cli.stages.relight_eval import (HEAD_PARTS, PARTS_PASS, SCORED_PATTERNS, SCORES_NPZ, RelightScores,
                                                HEADSET_NOT_EXCLUDED, HeadsetExclusion, display_images, part_channels,
                                                part_groups, score_view)

PREVIEW_PNG = "preview.png"
UVMAP_LAYERS = ("albedo", "shadow", "normal", "diffuse")
PREVIEW_COLUMNS = ("target", "render", "lambert", "baked")


@dataclass(frozen=True)
class LightingOverride:
    """Another lighting for every frame: a ``sequence.json``-style light entry (``flat``, ``olat``
    with ``olat_index``, ``envmap`` with ``envmap`` and ``yaw_deg``), the maps it names and the
    file they came from."""

    entry: dict
    envmaps: dict
    source: Path | None = None

    @classmethod
    def parse(cls, flat: bool, olat: int | None, envmap: Path | None,
              yaw_deg: float | None = None) -> "LightingOverride | None":
        """From the command's options (at most one of them; ``yaw_deg`` turns ``envmap`` and needs it,
        None: 0), or None for the sequence's own light."""
        from egorelight_cli.render.envmaps import load_envmap

        chosen = [name for name, given in (("--flat", flat), ("--olat", olat is not None), ("--envmap", envmap))
                  if given]
        if len(chosen) > 1:
            raise EgorelightError(f"give at most one lighting: {' and '.join(chosen)} were given")
        if yaw_deg is not None and envmap is None:
            raise EgorelightError("--yaw turns the map of --envmap: give --envmap FILE with it")
        yaw_deg = 0.0 if yaw_deg is None else yaw_deg
        if flat:
            return cls({"pattern": "flat", "description": "flat"}, {})
        if olat is not None:
            return cls({"pattern": "olat", "olat_index": int(olat), "description": f"olat {int(olat)}"}, {})
        if envmap is not None:
            path = Path(envmap)
            path = path / "envmap.exr" if path.is_dir() else path  # an envmap artifact
            return cls({"pattern": "envmap", "envmap": "user", "yaw_deg": float(yaw_deg),
                        "description": f"envmap {path} yaw {float(yaw_deg):g} deg"}, {"user": load_envmap(path)}, path)
        return None


@dataclass(frozen=True)
class CameraSelection:
    """The cameras ``relight`` renders into: ``"held-out"`` (the sequence's held-out studio
    cameras, default), ``"all"`` (every studio camera of the sequence), comma-separated studio
    camera names, or one virtual camera from a camera JSON (:mod:`egorelight_cli.io.camera_json`;
    it captured nothing, so its views are rendered, not scored)."""

    spec: str = "held-out"
    camera_json: Path | None = None

    def resolve(self, capture: Capture, sequence) -> tuple[list[str], dict]:
        """(camera names in render order, {name: virtual Camera} for a camera JSON)."""
        if self.camera_json is not None:
            if self.spec != "held-out":
                raise EgorelightError(f"give --cameras or --camera-json, not both (--cameras {self.spec})")
            from egorelight_cli.io.camera_json import read_camera_json

            camera = read_camera_json(self.camera_json)
            if camera.name in capture.studio_cameras:
                raise EgorelightError(f"the virtual camera is named {camera.name!r} like a studio camera of the "
                                      "capture; give it another name", self.camera_json)
            return [camera.name], {camera.name: camera}
        held_out = list(sequence.doc.get("held_out_cameras", []))
        if self.spec == "held-out":
            if not held_out:
                raise EgorelightError(f"sequence {sequence.name!r} has no held-out cameras (use --cameras all)",
                                      capture.root)
            return held_out, {}
        recorded = training_cameras(capture, sequence) + held_out
        if self.spec == "all":
            return recorded, {}
        names = [n.strip() for n in self.spec.split(",") if n.strip()]
        unknown = [n for n in names if n not in recorded]
        if unknown or not names:
            raise EgorelightError(f"--cameras {self.spec!r}: {', '.join(map(repr, unknown)) or 'no name'} is not a "
                                  f"studio camera of sequence {sequence.name!r} (it has {', '.join(recorded)}; or "
                                  "give held-out or all)", capture.root)
        return list(dict.fromkeys(names)), {}

    def key(self) -> str:
        """Its cache-key entry (a camera JSON's content enters the key as a source file)."""
        return "camera-json" if self.camera_json is not None else self.spec


class RelightData:
    """Frames (uvmaps + meshes + lighting) and studio views of one sequence, loaded on demand."""

    def __init__(self, capture: Capture, sequence, meshes, uvmaps: Artifact, character, resolution: int,
                 attention_level: int, rays: int, lighting: LightingOverride | None = None):
        self.capture, self.sequence, self.meshes = capture, sequence, meshes
        self.lighting = lighting
        self.uvmaps, self.character = uvmaps, character
        self.raster = rasterize_uv(character.face_uvs, resolution)
        self.low_raster = rl.low_resolution_raster(character.face_uvs, resolution, attention_level)
        self.coverage = torch.from_numpy(self.raster.coverage)
        self.lightstage = LightStage.from_json(capture.lights_path())
        self.envmaps = CaptureEnvmaps(capture.root)
        self.rays = rays
        names = character.segmentation_names
        self.head_vertices = np.isin(character.segmentation, [k for k, v in names.items() if v in HEAD_PARTS])
        #: the parts scored apart and each covered texel's part (N,P), from the character's segmentation
        groups = part_groups(names)
        self.parts = tuple(groups)
        texel_vertex = character.faces[self.raster.face_id[self.raster.coverage], 0]
        self.part_texels = part_channels(character.segmentation, groups, texel_vertex) if groups else None
        self._frames: dict[int, rl.RelightFrame] = {}
        self._lighting: dict[int, TexelLighting] = {}
        self._rays: dict[tuple[int, str], tuple[torch.Tensor, torch.Tensor]] = {}
        #: cameras by name: the capture's studio cameras, plus any virtual ones (``add_virtual_cameras``)
        self.cameras = dict(capture.studio_cameras)
        self.virtual: set[str] = set()
        #: the worn headset's pixels, excluded from the scores with the head (``--calibration``)
        self.headset: HeadsetExclusion | None = None

    def add_virtual_cameras(self, cameras: dict) -> None:
        """Views from cameras no capture holds: rendered, never scored."""
        self.cameras.update(cameras)
        self.virtual |= set(cameras)

    def scored(self, camera: str) -> bool:
        """Whether views of ``camera`` are compared with a captured image: the sequence's own
        lighting into a studio camera."""
        return self.lighting is None and camera not in self.virtual

    def has_maps(self, frame_id: int) -> bool:
        return (self.uvmaps.root / map_path(frame_id)).is_file()

    def read_maps(self, frame_id: int, layers: tuple[str, ...] = UVMAP_LAYERS) -> dict[str, np.ndarray]:
        """The frame's uvmaps ``layers`` (H,W,C each), checked against the model's resolution."""
        path = self.uvmaps.root / map_path(frame_id)
        exr = read_exr(path)
        if exr.shape != self.raster.resolution:
            raise EgorelightError(f"uvmaps are {exr.shape[1]}x{exr.shape[0]}, the model works at "
                                  f"{self.raster.resolution[1]}x{self.raster.resolution[0]}", self.uvmaps.root)
        missing = [n for n in layers if not any(c.startswith(f"{n}.") for c in exr.channels)]
        if missing:
            raise EgorelightError(f"uvmaps frame lacks the {', '.join(missing)} layer(s) (run geolift with "
                                  "--capture for the lighting features)", path)
        return {name: exr.layer(name) for name in layers}

    def vertices(self, frame_id: int) -> np.ndarray:
        return self.meshes.vertices[self.meshes.index_of(frame_id)].astype(np.float64)

    def known_intensities(self, frame_id: int) -> np.ndarray:
        """(L,3) the frame's recorded light entry (or the override's)."""
        if self.lighting is not None:
            return light_intensities(self.lightstage, self.lighting.entry, self.lighting.envmaps)
        return light_intensities(self.lightstage, self.sequence.light_entry(frame_id), self.envmaps)

    def assemble(self, frame_id: int, maps: dict[str, np.ndarray], intensities: np.ndarray) -> rl.RelightFrame:
        """:func:`~egorelight_cli.stages.relight.frame_inputs` of the frame's mesh and ``maps``."""
        return rl.frame_inputs(self.raster, maps, self.vertices(frame_id), self.character.faces,
                               self.character.face_uvs, intensities, self.head_vertices,
                               float(self.uvmaps.manifest["metrics"].get("flat_scale", 1.0)))

    def frame(self, frame_id: int) -> rl.RelightFrame:
        if frame_id not in self._frames:
            intensities = self.known_intensities(frame_id)
            if self.lighting is None:
                maps = self.read_maps(frame_id)
            else:  # rho/chi of the uvmaps belong to the captured light: recompute them for this one
                maps = self.read_maps(frame_id, ("albedo", "normal"))
                maps["shadow"], maps["diffuse"] = lighting_feature_maps(
                    self.raster, self.vertices(frame_id), self.character.faces, np.moveaxis(maps["normal"], -1, 0),
                    self.lightstage, intensities)
            self._frames[frame_id] = self.assemble(frame_id, maps, intensities)
        return self._frames[frame_id]

    def ray_lighting(self, frame_id: int) -> TexelLighting:
        """The frame's view-independent ray lighting (:func:`~egorelight_cli.stages.relight.ray_lighting`),
        computed once (shadow rays per frame)."""
        if frame_id not in self._lighting:
            self._lighting[frame_id] = rl.ray_lighting(self.frame(frame_id), self.low_raster, self.character.faces,
                                                       self.lightstage)
        return self._lighting[frame_id]

    def view_rays(self, frame_id: int, camera: str) -> tuple[torch.Tensor, torch.Tensor]:
        key = (frame_id, camera)
        if key not in self._rays:
            centre = self.cameras[camera].centre_world
            self._rays[key] = rl.camera_rays(self.ray_lighting(frame_id), self.frame(frame_id).intensities, centre,
                                             self.lightstage, self.rays)
        return self._rays[key]

    def target(self, frame_id: int, camera: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(image (H,W,3) linear, subject mask (H,W) bool) captured by ``camera`` at ``frame_id``."""
        image = read_exr(self.sequence.studio_image_path(camera, frame_id)).layer("", ("R", "G", "B"))
        return torch.from_numpy(np.ascontiguousarray(image)), torch.from_numpy(self.subject_mask(frame_id, camera))

    def subject_mask(self, frame_id: int, camera: str) -> np.ndarray:
        """The subject mask (H,W) bool of ``camera`` at ``frame_id`` (the mask image's first channel > 127)."""
        mask = read_image(self.sequence.mask_path(camera, frame_id))
        return mask.reshape(mask.shape[0], mask.shape[1], -1)[..., 0] > 127


def _lit_frames(sequence, meshes, uvmaps: Artifact, patterns: tuple[str, ...] | None = ("envmap",)) -> np.ndarray:
    """Frames whose light entry has one of ``patterns`` (any entry for None), a mesh and a uvmaps file."""
    entries = {int(f): e for f, e in zip(sequence.frame_ids, sequence.lights)}
    frames = [int(f) for f in meshes.frame_ids
              if (patterns is None or entries.get(int(f), {}).get("pattern") in patterns)
              and (uvmaps.root / map_path(int(f))).is_file()]
    return np.array(frames, np.int64)


def light_patterns(sequence, frames) -> np.ndarray:
    """(N,) str: the light pattern of each of ``frames`` in the sequence's own lighting."""
    entries = {int(f): str(e.get("pattern", "flat")) for f, e in zip(sequence.frame_ids, sequence.lights)}
    return np.array([entries.get(int(f), "flat") for f in frames])


def baseline_passes(frame: rl.RelightFrame, coverage: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per texel colours of the baselines: the Lambert relighting and the baked flat-lit texture ``a``."""
    return {"lambert": frame.lambert, "baked": frame.maps.permute(1, 2, 0)[coverage][:, 0:3]}


def preview_views(count: int, preview_count: int) -> set[int]:
    """Positions among ``count`` views that the preview shows (``preview_count`` evenly spread)."""
    if not preview_count or not count:
        return set()
    return set(np.linspace(0, count - 1, min(preview_count, count)).round().astype(int).tolist())


def evaluate(model: rl.RelightModel, data: RelightData, views: list[tuple[int, str]], writer: ArtifactWriter | None,
             preview_count: int = 0, export_ply: bool = False,
             preview_at: set[int] | None = None) -> tuple[RelightScores, dict[int, np.ndarray]]:
    """Render and score ``views`` (not scored under a lighting override); write EXR/PNG renders
    when ``writer`` is given, and with ``export_ply`` each frame's Gaussians (as seen by its first
    view) as a 3DGS PLY. Returns the per-view scores and the preview rows by view position
    (``preview_at``, default ``preview_count`` views spread over ``views``)."""
    scores, previews = RelightScores(), {}
    if preview_at is None:
        preview_at = preview_views(len(views), preview_count)
    with torch.no_grad():
        for i, (f, camera_name) in enumerate(console.progress(views, total=len(views), desc="relight")):
            frame = data.frame(f)
            rays, valid = data.view_rays(f, camera_name)
            head = torch.from_numpy(frame.head.astype(np.float32))[:, None]
            extra = {**baseline_passes(frame, data.coverage), "head": head}
            scored = data.scored(camera_name)
            if scored and data.part_texels is not None:
                extra[PARTS_PASS] = data.part_texels
            render, avatar = rl.render_relit(model, frame, data.coverage, data.cameras[camera_name],
                                             rays, valid, extra_passes=extra)
            if scored:
                scores.start_view()
                target, mask = data.target(f, camera_name)
                headset = None if data.headset is None else data.headset.pixels(f, data.cameras[camera_name], render)
                tonemapped = score_view(scores, render, target, mask, data.parts if PARTS_PASS in extra else (),
                                        headset, unposed_headset=data.headset is not None and headset is None)
            else:
                tonemapped = display_images(render)
            if writer is not None:
                stem = f"{camera_name}/{frame_file(f, '')}"
                write_exr_layers(writer.path(f"{stem}.exr"), {
                    "": render.colour.numpy(), "diffuse": render.passes["diffuse"].numpy(),
                    "specular": render.passes["specular"].numpy(), "alpha": render.alpha.numpy()[..., None]})
                write_image(writer.path(f"{stem}.png"), tonemapped["render"])
                ply = writer.path(f"gaussians/{frame_file(f, '.ply')}") if export_ply else None
                if ply is not None and not ply.exists():  # one file per frame, whichever camera came first
                    from egorelight_cli.io.gaussian_ply import write_gaussian_ply

                    write_gaussian_ply(ply, avatar.gaussians, rgb=tonemap_for_metrics(avatar.gaussians.colours).numpy())
            if i in preview_at:
                previews[i] = np.concatenate([tonemapped[k] for k in PREVIEW_COLUMNS if k in tonemapped], 1)
    return scores, previews


def scored_metrics(scores: RelightScores, data: RelightData, patterns: np.ndarray | None = None) -> dict:
    """The metrics of ``scores`` (none under a lighting override or from a virtual camera: nothing
    was captured to compare); with the views' light ``patterns``, the tail scored apart."""
    if data.lighting is not None:
        return {"scored": f"no: lighting {data.lighting.entry['description']} was not captured"}
    if data.virtual:
        return {"scored": f"no: the virtual camera {', '.join(sorted(data.virtual))} captured nothing"}
    return scores.metrics(patterns)


def load_relight_model(path: Path) -> tuple[rl.RelightModel, dict, Artifact]:
    """(model in eval mode, its data settings ``{"uv_resolution", "attention_level", "rays"}`` and
    training sequence ``"sequence"`` (None for a model that does not record it), artifact) of a
    ``train relight`` model."""
    from egorelight_cli.io.model import read_model

    artifact = open_artifact(path, kind="model")
    payload = read_model(artifact.root, stage=rl.MODEL_STAGE)
    arch = payload.architecture
    net = {"uv_resolution": payload.extra["uv_resolution"], "attention_level": arch["attention_level"],
           "rays": arch["rays"], "sequence": payload.extra.get("sequence")}
    model = rl.RelightModel.from_architecture(arch)
    try:
        model.load_state_dict(payload.state_dict)
    except RuntimeError as exc:
        raise EgorelightError(f"relight model does not fit its architecture ({str(exc).splitlines()[0]})",
                              path) from None
    model.eval()
    return model, net, artifact


@dataclass(frozen=True)
class RelightCommands:
    """``relight`` and ``train relight`` over one :class:`StageRun`."""

    run: StageRun

    def _load(self, capture_path: Path, meshes_path: Path, uvmaps_path: Path, character_spec: str, seq: str,
              net: dict, lighting: LightingOverride | None = None, patterns: tuple[str, ...] = ("envmap",)):
        from egorelight_cli.stages.character_commands import character_sources, load_character

        character, character_artifact = load_character(character_spec)
        capture, capture_artifact = open_capture(capture_path)
        sequence = capture.sequence(seq)
        meshes, meshes_artifact = load_character_meshes(meshes_path, character)
        uvmaps = open_artifact(uvmaps_path, kind="uvmaps")
        for artifact in (meshes_artifact, uvmaps):
            check_sequence(artifact, seq)
        data = RelightData(capture, sequence, meshes, uvmaps, character, int(net["uv_resolution"]),
                           int(net["attention_level"]), int(net["rays"]), lighting)
        frames = _lit_frames(sequence, meshes, uvmaps, None if lighting is not None else patterns)
        if not len(frames):
            what = "frame" if lighting is not None else "HDR-lit frame"
            raise EgorelightError(f"no {what} of sequence {seq!r} has both a mesh and UV maps", uvmaps_path)
        inputs = [a for a in (capture_artifact, character_artifact, meshes_artifact, uvmaps) if a is not None]
        # the files read that are not artifacts (a lone meshes npz, a character file) enter the key as sources
        sources = character_sources(character_spec, character_artifact) + ([] if meshes_artifact else [meshes_path])
        return data, frames, inputs, sources

    def train(self, capture_path: Path, meshes_path: Path, uvmaps_path: Path, character_spec: str, out: Path,
              resume: bool = False) -> Path:
        cfg = self.run.config()
        net = {k: cfg.net[k] for k in ("uv_resolution", "attention_level", "rays")}
        data, frames, inputs, sources = self._load(capture_path, meshes_path, uvmaps_path, character_spec,
                                          str(cfg.train.sequence), net)
        if len(frames) < 2:
            raise EgorelightError(f"{len(frames)} HDR-lit frame(s): training and validation need at least 2",
                                  uvmaps_path)
        if int(cfg.net.attention_level) > int(cfg.net.levels):
            raise EgorelightError(f"config key 'net.attention_level' must be at most net.levels "
                                  f"({cfg.net.levels}), got {cfg.net.attention_level}")
        train_frames, val_frames = split_held_out(frames, cfg.train.validation_fraction,
                                                  f"HDR-lit frame(s) of {cfg.train.sequence!r}", uvmaps_path)
        cameras = training_cameras(data.capture, data.sequence)
        # a view whose camera barely sees the subject has nothing to learn from (and no SSIM box)
        train_views = [(int(f), c) for f in train_frames for c in cameras
                       if data.subject_mask(int(f), c).sum() >= rl.MIN_SUBJECT_PIXELS]
        if not train_views:
            raise EgorelightError(f"no training camera sees the subject (at least {rl.MIN_SUBJECT_PIXELS} mask "
                                  f"pixels) in the {len(train_frames)} training frame(s)", capture_path)
        val_views = [(int(f), c) for f in val_frames for c in cameras]
        self.run.compute_device()
        checkpoint = checkpoint_beside(out)

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            from egorelight_cli.io.model import ModelPayload, write_model

            if writer.single_file:
                raise EgorelightError("a relight model is a directory artifact: give --out a directory name", out)
            net, t = cfg.net, cfg.train
            torch.manual_seed(int(cfg.seed))
            model = rl.RelightModel.from_architecture(net)
            if model.config["albedo"] == "texture":
                seen_frames = sorted({f for f, _ in train_views})
                start = rl.median_albedo([data.frame(f) for f in seen_frames], data.coverage)
                model.start_albedo(start, data.coverage)
            optimizer = torch.optim.Adam(model.parameters(), lr=float(t.lr))
            steps = int(t.steps)

            weights = {name: float(t.weights[name]) for name in rl.LOSS_WEIGHTS}

            def view_loss(f: int, camera_name: str, scale: float) -> dict[str, torch.Tensor]:
                rays, valid = data.view_rays(f, camera_name)
                render, avatar = rl.render_relit(model, data.frame(f), data.coverage,
                                                 data.capture.studio_cameras[camera_name], rays, valid, scale)
                target, mask = data.target(f, camera_name)
                return rl.relight_loss(render, target * scale, mask, avatar.regulariser, str(t.loss_space), weights)

            def step(k: int) -> dict[str, torch.Tensor]:
                rng = np.random.default_rng([int(cfg.seed), k])
                draws = []  # the step's global batch: (view, intensity scale) pairs
                for _ in range(int(t.views_per_step)):
                    f, camera_name = train_views[int(rng.integers(len(train_views)))]
                    scale = float(rng.uniform(0, 1)) if k >= steps // 2 and rng.uniform() < float(t.augment_p) else 1.0
                    draws.append((f, camera_name, scale))
                losses = [view_loss(*draw) for draw in rank_share(draws)]  # this process's share under torchrun
                return {name: torch.stack([loss[name] for loss in losses]).mean() for name in losses[0]}

            started = time.perf_counter()
            curve = train(model, optimizer, step, steps, checkpoint=Checkpoint(checkpoint, writer.cache_key, resume),
                          checkpoint_every=int(t.checkpoint_every), log_every=int(t.log_every), desc="train relight")
            writer.timing["train_s"] = round(time.perf_counter() - started, 3)
            model.eval()
            validation, previews = evaluate(model, data, val_views, None, int(cfg.preview.frames))
            writer.metrics.update({f"val_{k}": v for k, v in scored_metrics(validation, data).items()})
            if previews:
                write_image(writer.path(PREVIEW_PNG), stack_preview_rows([previews[i] for i in sorted(previews)]))
            extra = {"uv_resolution": int(net.uv_resolution), "sequence": data.sequence.name, "cameras": cameras,
                     "train_frames": train_frames.tolist(), "val_frames": val_frames.tolist()}
            write_model(writer.workdir, ModelPayload(rl.MODEL_STAGE, model.architecture(), model.state_dict(), extra,
                                                     curve), curve_title="relight training loss")
            loss_terms = (f"{weights['l1']:g} L1 + {weights['ssim']:g} (1 - SSIM) + {weights['reg']:g} L_reg + "
                          f"{weights['diffuse']:g} L1(diffuse) + {weights['l2']:g} L2")
            writer.metrics.update({"training_views": len(train_views), "validation_views": len(val_views),
                                   "loss_first": curve[0]["loss"], "loss_last": curve[-1]["loss"],
                                   "id_mrf": "not used: needs VGG weights (cannot be downloaded); loss is "
                                             f"{loss_terms}, in {t.loss_space} space"})

        result = self.run.produce(out, "model", write, inputs=inputs, source_files=sources)
        checkpoint.unlink(missing_ok=True)
        return result

    def predict(self, capture_path: Path, meshes_path: Path, uvmaps_path: Path, model_path: Path,
                character_spec: str, seq: str, selection: CameraSelection, out: Path,
                lighting: LightingOverride | None = None, frame_range: FrameRange = FrameRange(),
                calibration_path: Path | None = None) -> Path:
        model, net, model_artifact = load_relight_model(model_path)
        # the sequence's own lighting: its HDR-lit frames and its OLAT/group tail, scored apart
        data, frames, inputs, sources = self._load(capture_path, meshes_path, uvmaps_path, character_spec, seq, net,
                                                   lighting, SCORED_PATTERNS)
        olat = lighting.entry.get("olat_index") if lighting is not None else None
        if olat is not None and not 0 <= olat < data.lightstage.num_lights:
            raise EgorelightError(f"--olat {olat}: the light stage has {data.lightstage.num_lights} lights (0 to "
                                  f"{data.lightstage.num_lights - 1})", data.capture.lights_path())
        if calibration_path is not None:  # the headset's pixels leave the scores with the head
            from egorelight_cli.io.calibration import open_calibration

            calibration, calibration_artifact = open_calibration(calibration_path)
            inputs.append(calibration_artifact)
            if seq in calibration.head_poses:  # none: a sequence recorded without the headset
                data.headset = HeadsetExclusion.from_calibration(data.capture, calibration, seq)
        cameras, virtual = selection.resolve(data.capture, data.sequence)
        data.add_virtual_cameras(virtual)
        start, stop = frame_range.bounds(len(frames))  # a shard renders the views of its frames
        views = [(int(f), c) for f in frames[start:stop] for c in cameras]
        first_view = start * len(cameras)
        self.run.compute_device()

        def write(writer: ArtifactWriter, cfg: Config) -> None:
            if writer.single_file:
                raise EgorelightError("a renders artifact is a directory: give --out a directory name", out)
            shown = {p - first_view for p in preview_views(len(frames) * len(cameras), int(cfg.preview.frames))
                     if first_view <= p < first_view + len(views)}
            scores, previews = evaluate(model, data, views, writer, export_ply=cfg.export == "ply", preview_at=shown)
            scored = lighting is None and not virtual
            patterns = light_patterns(data.sequence, [f for f, _ in views]) if scored else None
            writer.metrics.update({"sequence": seq, "cameras": cameras, "views": len(views),
                                   **scored_metrics(scores, data, patterns)})
            if scored:
                writer.metrics["headset_excluded"] = (
                    data.headset.describe() if data.headset is not None else HEADSET_NOT_EXCLUDED
                    if calibration_path is None else f"no: the calibration has no head poses of {seq!r} (no headset)")
            rows = {"frame_ids": np.array([f for f, _ in views], np.int64), "camera": np.array([c for _, c in views]),
                    **({"light": patterns, **scores.arrays()} if scored else {})}
            writer.save_npz(SCORES_NPZ, rows, rows=sorted(rows), units={"psnr": "dB", "ssim": "x100"},
                            description="per view (frame, camera, light pattern): PSNR/SSIM of the render and its "
                                        "baselines (NaN: an empty scoring region), head_excluded_fraction (the head and "
                                        "the headset), headset_excluded_fraction (NaN: no head pose for the view); "
                                        "the metrics are their means over the HDR-lit views, "
                                        "olat_tail_*/group_tail_* over the tail's")
            write_preview(writer, {first_view + i: image for i, image in previews.items()}, frame_range, PREVIEW_PNG)
            if not frame_range.whole:
                writer.extra["shard"] = frame_range.manifest(len(frames))
            writer.metrics["lighting"] = "the sequence's own" if lighting is None else lighting.entry["description"]
            writer.units.update({"psnr": "dB on the metric tone mapping (exposure 1, sRGB, clipped)", "ssim": "x100",
                                 "preview": ("captured | " if lighting is None else "") + "relit | Lambert | baked"})

        light = None if lighting is None else {k: v for k, v in lighting.entry.items() if k != "description"}
        sources += [lighting.source] if lighting is not None and lighting.source is not None else []
        sources += [Path(selection.camera_json)] if selection.camera_json is not None else []
        return self.run.produce(out, "renders", write, inputs=inputs + [model_artifact], source_files=sources,
                                options={"camera_selection": selection.key(), "lighting": light})


# ------------------------------------------------------------- handlers (egorelight_cli.declarations)
def train_command(run: StageRun, capture: Path, meshes: Path, uvmaps: Path, character: str, resume: bool,
                  out: Path) -> Path:
    return RelightCommands(run).train(capture, meshes, uvmaps, character, out, resume)


def relight_command(run: StageRun, capture: Path, meshes: Path, uvmaps: Path, model: Path, character: str,
                    camera_json: Path | None, envmap: Path | None, calibration: Path | None, sequence: str, cameras: str,
                    flat: bool, olat: int | None, yaw: float | None, out: Path, frame_range: FrameRange) -> Path:
    lighting = LightingOverride.parse(flat, olat, envmap, yaw)
    return RelightCommands(run).predict(capture, meshes, uvmaps, model, character, sequence,
                                        CameraSelection(cameras, camera_json), out, lighting, frame_range, calibration)
