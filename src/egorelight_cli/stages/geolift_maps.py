"""Writing a ``uvmaps`` artifact: GeoLift's maps per frame, lighting features, scores and preview.

Called by ``egorelight geolift`` (:mod:`egorelight_cli.stages.geolift_commands`); the layout of
the artifact is described there.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter
from egorelight_cli.config import Config
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.io.exr import write_exr_layers
from egorelight_cli.io.images import tonemap
from egorelight_cli.structures.mesh_sequence import MeshSequence
from egorelight_cli.nn.geolift_net import GeoLiftNet
from egorelight_cli.render.lighting import CaptureEnvmaps, light_intensities
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.raster import rasterize_uv
from egorelight_cli.render.uv_features import lighting_feature_maps, texel_map, texel_surface
from egorelight_cli.stages import geolift as gl
from egorelight_cli.sharding import FrameRange, write_preview
from egorelight_cli.stages.geolift_eval import SCORES_NPZ, GeoLiftScores, GeoLiftTruth
from egorelight_cli.structures.character import Character

PREVIEW_TILE = 128  # pixels per UV map in the preview


def _normal_image(maps: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """(3,H,W) unit normals -> (T,T,3) uint8 (0.5 n + 0.5), grey off the layout."""
    image = np.where(coverage[..., None], 0.5 * np.moveaxis(maps, 0, -1) + 0.5, 0.5)
    image = cv2.resize(image.astype(np.float32), (PREVIEW_TILE, PREVIEW_TILE), interpolation=cv2.INTER_NEAREST)
    return np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8)


def _texture_image(maps: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    image = tonemap(np.moveaxis(maps, 0, -1), mask=coverage)
    return cv2.resize(image, (PREVIEW_TILE, PREVIEW_TILE), interpolation=cv2.INTER_NEAREST)


def write_uvmaps(writer: ArtifactWriter, cfg: Config, model: GeoLiftNet, extra: dict, character: Character,
                 meshes: MeshSequence, capture: Capture | None, sequence: SequenceInfo | None,
                 frame_range: FrameRange = FrameRange()) -> None:
    """Run GeoLift on the mesh frames of ``frame_range`` (all by default) and write maps, features,
    per-frame scores, metrics and the preview (or, for a shard, its preview tiles)."""
    from egorelight_cli.stages.geolift_commands import PREVIEW_PNG, map_path

    raster = rasterize_uv(character.face_uvs, int(extra["uv_resolution"]))
    coverage = raster.coverage
    coarse = gl.coarse_maps(raster, meshes.vertices, character.faces, character.face_uvs)
    normal_maps = coarse.normals
    mean_texture = extra["mean_texture"].numpy()
    lit = capture is not None and sequence is not None and bool(cfg.lighting.features) and bool(sequence.lights)
    lightstage = LightStage.from_json(capture.lights_path()) if lit else None
    envmaps = CaptureEnvmaps(capture.root) if lit else None
    lit_frames = set(int(f) for f in sequence.frame_ids) if lit else set()
    truth = None
    if capture is not None and sequence is not None:
        truth = GeoLiftTruth(capture, sequence.name, raster)
    scores = GeoLiftScores()
    T = meshes.num_frames
    preview_at = set(np.linspace(0, T - 1, max(min(int(cfg.preview.frames), T), 1)).round().astype(int).tolist())
    start, stop = frame_range.bounds(T)  # the network reads neighbouring coarse maps: all T are computed
    if not frame_range.whole:
        writer.extra["shard"] = frame_range.manifest(T)
    rows, timing = {}, {"network_s": 0.0, "features_s": 0.0}
    network_used = "geolift" in (str(cfg.predict.normals), str(cfg.predict.texture))  # else both maps are baselines
    featured = 0
    for t in console.progress(range(start, stop), total=stop - start, desc="geolift"):
        f = int(meshes.frame_ids[t])
        started = time.perf_counter()
        normals, texture = gl.predict_maps(model, coarse, t) if network_used else (None, None)
        if str(cfg.predict.normals) == "coarse":
            normals = normal_maps[t]
        if str(cfg.predict.texture) == "mean":
            texture = mean_texture
        timing["network_s"] += time.perf_counter() - started
        layers = {"normal": np.moveaxis(normals, 0, -1) * coverage[..., None],
                  "albedo": np.moveaxis(texture, 0, -1) * coverage[..., None],
                  "coverage": coverage.astype(np.float32)}
        if f in lit_frames:
            started = time.perf_counter()
            intensities = light_intensities(lightstage, sequence.light_entry(f), envmaps)
            layers["shadow"], layers["diffuse"] = lighting_feature_maps(raster, meshes.vertices[t], character.faces,
                                                                       normals, lightstage, intensities)
            timing["features_s"] += time.perf_counter() - started
            featured += 1
        write_exr_layers(writer.path(map_path(f)), layers)
        truth_normals = None
        if truth is not None and truth.has(f):
            surface = texel_surface(raster, meshes.vertices[t], character.faces)
            scores.add(truth, f, surface.points, normals, normal_maps[t], texture, mean_texture)
            truth_normals = truth.frame(f)[0]
        if t in preview_at:
            tiles = [_normal_image(normal_maps[t], coverage), _normal_image(normals, coverage),
                     _texture_image(texture, coverage)]
            if truth_normals is not None:
                tiles.append(_normal_image(np.moveaxis(texel_map(coverage, truth_normals), -1, 0), coverage))
            rows[t] = np.concatenate(tiles, axis=1)
    write_preview(writer, rows, frame_range, PREVIEW_PNG)
    T = stop - start
    if truth is not None:
        arrays = scores.arrays()
        writer.save_npz(SCORES_NPZ, arrays, rows=sorted(arrays), units={"normal_deg": "degrees"},
                        description="per scored frame: the errors of the maps and of their baselines (NaN: not "
                                    "scored), the metrics' source")
    writer.metrics.update({"frames": T, "sequence": sequence.name if sequence is not None else None,
                           "flat_scale": float(extra.get("flat_scale", 1.0)),
                           "uv_resolution": int(extra["uv_resolution"]), "frames_with_lighting_features": featured,
                           "normals_from": str(cfg.predict.normals), "texture_from": str(cfg.predict.texture),
                           "preview_columns": "coarse normals | GeoLift normals | flat-lit texture | true normals"})
    if truth is not None and truth.available:
        writer.metrics.update(scores.metrics())
    elif truth is not None:
        writer.metrics["groundtruth"] = truth.reason
    writer.timing.update({"network_ms_per_frame": round(1000 * timing["network_s"] / max(T, 1), 2),
                          "features_ms_per_frame": round(1000 * timing["features_s"] / max(featured, 1), 2)})
    writer.units.update({"normal": "unit vector, world frame", "albedo": "linear radiance (flat-lit)",
                         "shadow": "rho = sum_l G_l / pi", "diffuse": "chi, irradiance (lights' units)",
                         "normal_deg": "degrees", "texture_l1": "linear radiance"})

