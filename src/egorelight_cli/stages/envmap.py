"""``envmap``: the wearer's surroundings as an HDR environment map (paper Sec. "Affordable
Egocentric HDR Environment Map Capture" + supplement).

Steps 1-5 below give the paper's "no inverse rendering" row (the LDR panorama used directly):

1. **Scan frames** (:func:`scan_frames`): ``panorama.frames`` frames sampled uniformly over the
   scan, the first ``panorama.scan_s`` seconds of the sequence, among frames with a calibrated
   head pose.
2. **Views** (:func:`scan_views`): each front camera's 8-bit image, linearised with the inverse
   sRGB curve only -- the per-camera response (exposure, colour cross-talk, white balance) is
   unknown to the stages, so the panorama is in the front cameras' own linear colour space,
   clipped at their saturation -- and placed in the world by the calibration
   (``T_world_from_cam = H @ inv(Pi)``, :func:`~egorelight_cli.io.calibration.posed_ego_camera`).
   The map's frame is the frame of the sequence's calibrated head poses (for ``wild``: the
   headset tracker's gravity-aligned frame).
3. **Panorama** ``E_o`` and coverage (:func:`~egorelight_cli.render.panorama.accumulate_panorama`),
   **inpainting** to ``E_l`` (:func:`~egorelight_cli.render.panorama.inpaint_equirect`).
4. **Colour model** ``E_h = A . phi(E_l ** gamma)`` (:mod:`egorelight_cli.nn.colour_model`):
   :func:`build_envmap` applies ``A = [I | 0]``, ``gamma = 1`` (the LDR-panorama row); with the
   relight model, tracked meshes and uvmaps, the command fits ``A, gamma`` by inverse rendering
   of the avatar into the down-facing views (:mod:`egorelight_cli.stages.envmap_inverse`).
5. **Light intensities** ``S(E_h)`` on the capture's light stage
   (:meth:`~egorelight_cli.render.lightstage.LightStage.envmap_to_intensities`).

Scoring against the simulator's truth is :mod:`egorelight_cli.stages.envmap_eval`; the command
(loading, artifact writing) is :mod:`egorelight_cli.stages.envmap_commands`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.calibration import Calibration, posed_ego_camera
from egorelight_cli.io.capture import Capture, SequenceInfo
from egorelight_cli.io.images import srgb_to_linear, to_unit_float
from egorelight_cli.nn.colour_model import RootPolynomialColour
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.render.panorama import Panorama, PanoramaView, accumulate_panorama, inpaint_equirect

#: 8-bit codes at or above this count as clipped (reported, still used: the map is LDR).
CLIPPED_CODE = 254


@dataclass(frozen=True)
class PanoramaSettings:
    """The ``panorama`` and ``inpaint`` config sections."""

    roles: tuple[str, ...]
    frames: int
    scan_s: float
    height: int
    centre_weight: bool
    proxy_radius_m: float
    inpaint_method: str
    inpaint_radius_px: float

    @classmethod
    def from_config(cls, cfg) -> PanoramaSettings:
        p = cfg.panorama
        # value ranges: the checks of stages/envmap.yaml
        return cls(tuple(cfg.roles), int(p.frames), float(p.scan_s), int(p.height), bool(p.centre_weight),
                   float(p.proxy_radius_m), str(cfg.inpaint.method), float(cfg.inpaint.radius_px))


@dataclass(frozen=True)
class EnvmapResult:
    """Everything the stage computed.

    Attributes:
        frame_ids: (F,) the scan frames used (master-clock ids; for ``wild``, ego ids).
        panorama: the observed panorama ``E_o`` with its weights and coverage.
        inpainted: (H,2H,3) float32 ``E_l``.
        colour_model: the colour model applied to ``E_l``.
        envmap: (H,2H,3) float32 ``E_h``, the map written as ``envmap.exr``.
        intensities: (L,3) float64 ``S(E_h)`` on the capture's light stage.
        centre: (3,) mean head position over the scan frames (metres, pose frame).
        clipped_fraction: fraction of the used pixels at 8-bit saturation.
    """

    frame_ids: np.ndarray
    panorama: Panorama
    inpainted: np.ndarray
    colour_model: RootPolynomialColour
    envmap: np.ndarray
    intensities: np.ndarray
    centre: np.ndarray
    clipped_fraction: float


def scan_frames(calibration: Calibration, sequence: SequenceInfo, count: int, scan_s: float) -> np.ndarray:
    """(F,) up to ``count`` frame ids spread uniformly over the scan: the frames with a valid head
    pose and ego images in the sequence's first ``scan_s`` seconds (all of them for ``scan_s = 0``)."""
    if sequence.name not in calibration.head_poses:
        raise EgorelightError(f"calibration has no head poses for sequence {sequence.name!r}", calibration.source)
    poses = calibration.head_poses[sequence.name]
    if len(poses.frame_ids) == 0:
        raise EgorelightError(f"calibration has no frames for sequence {sequence.name!r}", calibration.source)
    ids = np.asarray(poses.frame_ids, dtype=np.int64)
    keep = np.asarray(poses.valid, dtype=bool).copy()
    ego_ids = np.array([calibration.ego_frame_id(sequence.name, int(f)) for f in ids], np.int64)
    keep &= np.isin(ego_ids, sequence.ego_frame_ids)  # a studio frame before the ego stream starts has no image
    if scan_s > 0:
        if "fps" not in sequence.doc:
            raise EgorelightError("sequence.json has no fps: set panorama.scan_s=0 to use the whole sequence",
                                  sequence.root / "sequence.json")
        keep &= ids < ids.min() + scan_s * float(sequence.fps)
    ids = np.sort(ids[keep])
    if ids.size == 0:
        raise EgorelightError(f"no frame of the scan ({scan_s:g} s of {sequence.name}) has a calibrated head pose "
                              "and ego images", calibration.source)
    picks = np.unique(np.round(np.linspace(0, ids.size - 1, min(int(count), ids.size))).astype(np.int64))
    return ids[picks]


def scan_views(capture: Capture, calibration: Calibration, sequence: SequenceInfo, frame_ids: np.ndarray,
               roles: tuple[str, ...]) -> tuple[list[PanoramaView], np.ndarray, float]:
    """(views, head positions (F,3) metres, clipped pixel fraction) of the scan frames: every role's
    image linearised by the inverse sRGB curve and its camera posed by the calibration."""
    views, clipped, total = [], 0, 0
    for role in roles:
        if role not in calibration.ego_cameras:
            raise EgorelightError(f"calibration has no hand-eye for camera {role!r} (has {', '.join(calibration.ego_cameras)})",
                                  calibration.source)
        if role not in sequence.ego_roles:
            raise EgorelightError(f"sequence {sequence.name} has no ego images of {role!r} "
                                  f"(has {', '.join(sequence.ego_roles) or 'none'})", sequence.root)
    for f in frame_ids:
        ego_id = calibration.ego_frame_id(sequence.name, int(f))
        for role in roles:
            camera = posed_ego_camera(capture, calibration, role, sequence.name, int(f))
            codes = sequence.read_ego_image(role, ego_id)
            if codes.shape[:2] != (camera.height, camera.width):
                raise EgorelightError(f"{role} image is {codes.shape[1]}x{codes.shape[0]}, the HMD description says "
                                      f"{camera.width}x{camera.height}", sequence.ego_image_path(role, ego_id))
            if codes.dtype == np.uint8:
                clipped += int((codes.max(axis=-1) >= CLIPPED_CODE).sum())
                total += codes.shape[0] * codes.shape[1]
            views.append(PanoramaView(srgb_to_linear(to_unit_float(codes)), camera))
    heads = np.stack([calibration.head_poses[sequence.name].pose(int(f))[:3, 3] for f in frame_ids])
    return views, heads, clipped / max(total, 1)


def build_envmap(capture: Capture, calibration: Calibration, sequence: SequenceInfo, settings: PanoramaSettings,
                 lightstage: LightStage) -> EnvmapResult:
    """Steps 1-5 of the module docstring (the LDR-panorama row: ``A = [I | 0]``, ``gamma = 1``)."""
    frame_ids = scan_frames(calibration, sequence, settings.frames, settings.scan_s)
    views, heads, clipped = scan_views(capture, calibration, sequence, frame_ids, settings.roles)
    centre = heads.mean(axis=0)
    radius = settings.proxy_radius_m if settings.proxy_radius_m > 0 else None
    panorama = accumulate_panorama(views, settings.height, settings.centre_weight, radius, centre)
    if not panorama.coverage.any():
        raise EgorelightError(f"no panorama texel was observed by {', '.join(settings.roles)} in the scan frames")
    inpainted = inpaint_equirect(panorama.radiance, panorama.coverage, settings.inpaint_method,
                                 settings.inpaint_radius_px)
    model = RootPolynomialColour()
    envmap = model.apply_numpy(inpainted)
    intensities = lightstage.envmap_to_intensities(envmap)
    return EnvmapResult(frame_ids, panorama, inpainted, model, envmap, intensities, centre, clipped)
