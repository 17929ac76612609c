"""The oracle renderer: the TRUE subject of a simulated capture under any camera and lighting.

Evaluation only (never on a stage's input path). It renders exactly what the simulator rendered
-- the true outer surface of a frame (``groundtruth/<seq>/meshes.npz``), its true textures and
detail normal map (``groundtruth/appearance.exr``), the headset on the true head pose when worn
-- for

* any camera: a studio camera by name (the TRUE calibration, ``groundtruth/studio_cameras.json``
  when present), or any :class:`~egorelight_cli.geometry.cameras.Camera` (held-out, virtual);
* any lighting: a ``sequence.json`` light entry (flat, envmap + yaw, OLAT, group, ...), an OLAT
  index, an (L,3) intensity vector of the lightstage, or an environment map with a yaw on the
  virtual dome the simulator lights the in-the-wild sequence with (``lights="dome"``);

returning radiance (HDR, times the studio exposure), its diffuse and specular parts and masks.
The subject's body and headset are rebuilt from the capture's recorded synth config and seed
(deterministic), so the oracle needs nothing the simulator did not write.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.npz import read_npz
from egorelight_cli.render.envmaps import load_envmap
from egorelight_cli.render.lighting import light_intensities
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.shading import RenderResult
from egorelight_cli.synth import groundtruth
from egorelight_cli.synth.calibration_error import STUDIO_TRUTH, read_true_studio_cameras
from egorelight_cli.synth.hmd import make_hmd
from egorelight_cli.synth.scene import BODY, HMD, place, scene_layout
from egorelight_cli.synth.sensors import FrameRenderer, Timer
from egorelight_cli.synth.subject import make_subject
from egorelight_cli.synth.textures import TexturedMesh


@dataclass(frozen=True, eq=False)
class OracleRender:
    """One oracle image: ``radiance``, ``diffuse``, ``specular`` (H,W,3) float32 HDR (times the
    studio exposure), ``mask`` (H,W) subject (body + headset), ``body_mask`` (H,W) body only."""

    radiance: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    mask: np.ndarray
    body_mask: np.ndarray
    result: RenderResult


class Oracle:
    """Renders the true subject of the simulated capture at ``root`` (see the module docstring)."""

    def __init__(self, root: str | Path):
        from egorelight_cli.stages.character_commands import load_character

        self.root = Path(root)
        if not (self.root / groundtruth.GT).is_dir():
            raise EgorelightError("the oracle needs a simulated capture with ground truth", self.root / groundtruth.GT)
        manifest = json.loads((self.root / "manifest.json").read_text())
        self.cfg = Config(manifest["config"], stage="synth")
        characters = [i["path"] for i in manifest.get("inputs", []) if "character" in str(i.get("kind", ""))]
        template, _ = load_character((self.root / characters[0]).resolve() if characters else "default")
        seed = int(self.cfg.seed)
        self.subject = make_subject(template, self.cfg, seed)
        self.hmd = make_hmd(self.subject.body, self.cfg.hmd, seed)
        maps = read_exr(self.root / groundtruth.GT / "appearance.exr")
        normal_map = maps.layer("detail") if any(c.startswith("detail.") for c in maps.channels) else None
        self.textures = dict(albedo=maps.layer("albedo"), specular=maps.layer("specular"),
                             roughness=maps.layer("roughness"), normal_map=normal_map)
        self.lightstage = LightStage.from_json(self.root / "rig" / "lights.json")
        self.exposure = float(self.cfg.studio.exposure)
        self._meshes: dict[str, dict] = {}

    # ----------------------------------------------------------------------------- inputs
    def studio_camera(self, name: str) -> Camera:
        """A studio camera by name with its TRUE parameters (the rig's when the capture has no
        calibration error recorded)."""
        truth = self.root / groundtruth.GT / STUDIO_TRUTH
        cameras = read_true_studio_cameras(self.root) if truth.is_file() else {
            doc["name"]: Camera.from_dict(doc)
            for doc in json.loads((self.root / "rig" / "studio_cameras.json").read_text())["cameras"]}
        if name not in cameras:
            raise EgorelightError(f"the capture has no studio camera {name!r}", truth)
        return cameras[name]

    def _sequence(self, seq: str) -> dict:
        if seq not in self._meshes:
            arrays, _ = read_npz(self.root / groundtruth.GT / seq / "meshes.npz")
            head = self.root / groundtruth.GT / seq / "head_pose.npz"
            arrays["head"] = read_npz(head)[0]["T_world_from_hmd"] if head.is_file() else None
            arrays["lights"] = json.loads((self.root / "sequences" / seq / "sequence.json").read_text())["lights"]
            self._meshes[seq] = arrays
        return self._meshes[seq]

    def envmap(self, name: str) -> np.ndarray:
        """An environment map of the capture by name (``envmaps/`` or ``groundtruth/envmaps/``)."""
        for folder in (self.root / "envmaps", self.root / groundtruth.GT / "envmaps"):
            if (folder / f"{name}.exr").is_file():
                return load_envmap(folder / f"{name}.exr")
        raise EgorelightError(f"the capture has no environment map {name!r}", self.root / "envmaps")

    def _row(self, seq: str, frame_id: int) -> int:
        """Row of ``frame_id`` in the sequence's ground truth (an error when absent)."""
        rows = np.flatnonzero(self._sequence(seq)["frame_ids"] == int(frame_id))
        if rows.size == 0:
            raise EgorelightError(f"ground truth of {seq} has no frame {frame_id}", self.root / groundtruth.GT / seq)
        return int(rows[0])

    def _entry_intensities(self, entry: dict, stage: LightStage) -> np.ndarray:
        """(L,3) of a ``sequence.json`` light entry on ``stage``."""
        names = [entry["envmap"]] if entry.get("envmap") else []
        return light_intensities(stage, entry, {n: self.envmap(n) for n in names})

    def intensities(self, seq: str, frame_id: int) -> np.ndarray:
        """(L,3) the lightstage condition the capture recorded for a studio frame."""
        return self._entry_intensities(self._sequence(seq)["lights"][self._row(seq, frame_id)], self.lightstage)

    def dome(self) -> LightStage:
        """The virtual dome of distant lights that lights the in-the-wild sequence."""
        from egorelight_cli.synth.capture import virtual_dome

        return virtual_dome(self.cfg)

    # ----------------------------------------------------------------------------- render
    def render(self, seq: str, frame_id: int, camera: Camera | str, lighting=None, *, hmd: bool | None = None,
               lights: LightStage | None = None, background=None) -> OracleRender:
        """The true subject at ``frame_id`` of ``seq`` seen by ``camera``.

        Args:
            camera: a studio camera name (true calibration) or a :class:`Camera`.
            lighting: None (the frame's recorded light entry), a light entry dict, an int (OLAT
                index), an (L,3) intensity array, or ``(envmap (H,2H,3), yaw_deg)`` (projected
                with the lights' own S(E)).
            hmd: draw the headset (default: when the sequence has head poses).
            lights: the light rig (default the lightstage; :meth:`dome` for in-the-wild light).
        """
        arrays = self._sequence(seq)
        row = self._row(seq, frame_id)
        stage = self.lightstage if lights is None else lights
        intensities = self._resolve_lighting(seq, frame_id, lighting, stage)
        cam = self.studio_camera(camera) if isinstance(camera, str) else camera
        worn = arrays["head"] is not None if hmd is None else bool(hmd)
        if worn and arrays["head"] is None:
            raise EgorelightError(f"{seq} has no head poses: the headset cannot be drawn")
        body = TexturedMesh(vertices=arrays["vertices"][row], faces=arrays["faces"], face_uvs=arrays["face_uvs"],
                            visibility_parents=self.subject.visibility_parents, **self.textures)
        layout = scene_layout(body, self.hmd if worn else None, None)
        parts = {BODY: arrays["vertices"][row]}
        if worn:
            parts[HMD] = place(self.hmd.mesh, arrays["head"][row])
        renderer = FrameRenderer(layout, stage, int(self.cfg.render.exact_lights), Timer())
        result = renderer.prepare(layout.vertices(parts), intensities).render(cam, "oracle", background=background)
        e = self.exposure
        return OracleRender(radiance=result.radiance * e, diffuse=result.diffuse * e, specular=result.specular * e,
                            mask=layout.subject_mask(result.face_id), body_mask=layout.part_mask(result.face_id, BODY),
                            result=result)

    def _resolve_lighting(self, seq: str, frame_id: int, lighting, stage: LightStage) -> np.ndarray:
        if lighting is None:
            if stage is not self.lightstage:
                raise EgorelightError("a recorded light entry is a lightstage condition: pass lighting for other lights")
            return self.intensities(seq, frame_id)
        if isinstance(lighting, dict):
            return self._entry_intensities(lighting, stage)
        if isinstance(lighting, (int, np.integer)):
            return stage.olat(int(lighting), 1.0)
        if isinstance(lighting, tuple):
            envmap, yaw = lighting
            return stage.envmap_to_intensities(np.asarray(envmap, np.float32), float(yaw))
        return stage.check_intensities(np.asarray(lighting, dtype=np.float64))
