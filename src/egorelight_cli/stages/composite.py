"""Telepresence composite (paper teaser, Abstract, Overview): User 1's relightable avatar, lit by
User 2's environment, inserted into User 2's front-camera view.

**Frames.** User 2's calibrated head poses define the frame everything below lives in (the
``envmap`` artifact is in it too). User 1's avatar lives in the light stage's frame ("studio",
metres, +Y up, floor at y = 0), where its lighting features are computed. Rather than moving the
avatar, the placement ``T_place`` (4,4, studio -> User 2's frame: a yaw about +Y and a
translation) moves the *camera and the light* into the studio: the camera's extrinsics become
``T_cam_from_user2 @ T_place`` and the environment map is turned by the placement's yaw
(``E_studio(d) = E(R_y(psi) d)``, i.e. ``S`` with yaw ``-psi``); both are exact for distant light.

**Placement** (:func:`place_avatar`). ``--place "x,z,yaw_deg"``: the avatar's ground point (its hips'
midpoint, dropped to the floor) stands ``x`` metres forward and ``z`` metres right of User 2's
first head pose (forward = the front camera's optical axis at that frame, made horizontal; right
= forward x up), turned so that at ``yaw_deg = 0`` it faces User 2 (its facing = up x (right hip -
left hip), made horizontal), ``yaw_deg`` turning it further about +Y (:func:`yaw_rotation`
sense). Feet on the floor: the avatar's lowest vertex at its first frame goes to the floor height
(``placement.floor``): ``head`` (default) = the height of User 2's first head pose minus the eye
height (the HMD's height above the floor when standing; ``auto``: the median HMD height of the
calibration's other (studio) sequences, whose world has its floor at y = 0), because the
headset tracker's frame has an unknown origin height; ``world`` = y = 0 of the frame, right when
the calibration's poses are in a metric world with its floor at 0 (e.g. an oracle calibration of
the simulator). The later avatar frames keep the same ``T_place`` (the avatar walks as it did).

**Colour** (:func:`avatar_to_camera`). The avatar renders radiance in the avatar's light units
(the studio cameras' linear HDR; ``E_h`` units, the studio exposure being 1 by the capture
convention). The envmap's colour model says which front-camera linear value ``E_l`` becomes
``E_h = A phi(E_l ** gamma)``; the avatar's un-premultiplied colour is mapped back into ``E_l``
(:class:`~egorelight_cli.nn.colour_inverse.CameraMapping`, ``colour.inverse``): ``diagonal``
(default) by one gain per channel fitted to the model's inverse over the envmap's texels, or
``exact`` by the model's own per-pixel inverse (Newton from the grey solution), which the
model's cross terms make extrapolate on the avatar's colours (``nn/colour_inverse.py``;
measured in ``stages/composite.yaml``). It is composited in linear light
``out = alpha x + (1 - alpha) srgb^-1(background)`` with the Gaussians' alpha, then sRGB-encoded
and quantised to 8 bits (values above 1 clip as the camera clips).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.equirect import yaw_rotation
from egorelight_cli.io.images import linear_to_srgb, srgb_to_linear, to_unit_float
from egorelight_cli.nn.colour_inverse import CameraMapping
from egorelight_cli.stages import relight as rl

UP = np.array([0.0, 1.0, 0.0])
FLOOR_MODES = ("head", "world")


@dataclass(frozen=True)
class CompositeSettings:
    """The ``composite.yaml`` config: frames, output size, placement defaults, colour inverse."""

    frames: int
    scale: float
    fps: float
    floor: str
    eye_height_m: float | None
    colour_iterations: int
    colour_inverse: str
    sheet_columns: int
    sheet_tile_width: int

    @classmethod
    def from_config(cls, cfg) -> CompositeSettings:
        eye = cfg.placement.eye_height_m
        settings = cls(int(cfg.frames), float(cfg.resolution_scale), float(cfg.video.fps), str(cfg.placement.floor),
                       None if str(eye) == "auto" else float(eye), int(cfg.colour.iterations),
                       str(cfg.colour.inverse),
                       int(cfg.preview.columns), int(cfg.preview.tile_width))
        return settings  # value ranges: the checks of stages/composite.yaml


def parse_place(text: str) -> tuple[float, float, float]:
    """``"x,z,yaw_deg"`` -> (forward m, right m, yaw deg); a one-line error otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise EgorelightError(f"--place must be 'forward_m,right_m,yaw_deg' (three numbers), got {text!r}")
    if math.hypot(values[0], values[1]) > 100:
        raise EgorelightError(f"--place puts the avatar {math.hypot(values[0], values[1]):.0f} m away (at most 100 m)")
    return values


def azimuth(v: np.ndarray) -> float:
    """Azimuth (rad) of a direction, from -Z towards +X (the equirect convention)."""
    return math.atan2(float(v[0]), -float(v[2]))


def _horizontal(v: np.ndarray, what: str) -> np.ndarray:
    h = np.array([v[0], 0.0, v[2]], np.float64)
    n = np.linalg.norm(h)
    if n < 1e-6:
        raise EgorelightError(f"{what} is vertical: no horizontal direction to place the avatar by")
    return h / n


@dataclass(frozen=True)
class Placement:
    """Where the avatar stands in User 2's frame.

    Attributes:
        T: (4,4) ``T_user2_from_studio`` (yaw about +Y and translation), metres.
        yaw_deg: the yaw ``psi`` of ``T`` (:func:`yaw_rotation` sense).
        spot: (3,) the avatar's ground point in User 2's frame (on the floor).
        floor_y: the floor height used (m, User 2's frame); floor: how it was chosen.
    """

    T: np.ndarray
    yaw_deg: float
    spot: np.ndarray
    floor_y: float
    floor: str

    def camera_in_studio(self, camera: Camera) -> Camera:
        """``camera`` (posed in User 2's frame) expressed in the studio frame."""
        return Camera(camera.model, camera.K, camera.dist, camera.width, camera.height,
                      camera.T_cam_from_world @ self.T, camera.name)

    def to_json(self) -> dict:
        return {"T_user2_from_studio": self.T.tolist(), "yaw_deg": self.yaw_deg, "spot_m": self.spot.tolist(),
                "floor_y_m": self.floor_y, "floor": self.floor}


def place_avatar(vertices: np.ndarray, left_hip: np.ndarray, right_hip: np.ndarray, T_user2_from_cam: np.ndarray,
                 head_position: np.ndarray, forward_m: float, right_m: float, yaw_deg: float, floor_y: float,
                 floor: str = "head") -> Placement:
    """The module docstring's placement.

    Args:
        vertices: (V,3) the avatar's first frame in the studio frame (m).
        left_hip, right_hip: (3,) its hip joints at that frame.
        T_user2_from_cam: (4,4) User 2's front camera at User 2's first frame (its +Z is forward).
        head_position: (3,) User 2's first head position.
        forward_m, right_m, yaw_deg: ``--place``.
        floor_y: floor height in User 2's frame; floor: how it was chosen (recorded).
    """
    vertices = np.asarray(vertices, np.float64)
    forward = _horizontal(np.asarray(T_user2_from_cam, np.float64)[:3, 2], "User 2's front camera axis")
    right = np.cross(forward, UP)
    facing = _horizontal(np.cross(UP, np.asarray(right_hip, np.float64) - np.asarray(left_hip, np.float64)),
                         "the avatar's facing (hips)")
    wanted = yaw_rotation(yaw_deg) @ -forward
    psi = math.degrees(azimuth(facing) - azimuth(wanted))
    psi = (psi + 180.0) % 360.0 - 180.0
    R = yaw_rotation(psi)
    ground = 0.5 * (np.asarray(left_hip, np.float64) + np.asarray(right_hip, np.float64))
    spot = np.asarray(head_position, np.float64) + forward_m * forward + right_m * right
    spot[1] = floor_y
    T = np.eye(4)
    T[:3, :3] = R
    moved = R @ ground
    T[:3, 3] = [spot[0] - moved[0], floor_y - float((vertices @ R.T)[:, 1].min()), spot[2] - moved[2]]
    return Placement(T, psi, spot, float(floor_y), floor)


def eye_height(calibration, exclude: str) -> float:
    """Median HMD height (m) over the valid head poses of the calibration's sequences other than
    ``exclude`` whose poses lie in the studio's world (floor at y = 0; a headset tracker's own frame,
    as in ``wild``, has another origin): the wearer's standing eye height."""
    heights = [p.T_world_from_hmd[p.valid, 1, 3] for name, p in calibration.head_poses.items()
               if name != exclude and calibration.head_poses_in_studio_world(name)]
    heights = np.concatenate(heights) if heights else np.zeros(0)
    if not heights.size:
        raise EgorelightError("placement.eye_height_m: auto needs head poses of a studio sequence in the calibration "
                              "(set a number with --set placement.eye_height_m=1.6)", calibration.source)
    return float(np.median(heights))


def render_avatar(model: rl.RelightModel, data, frame_id: int, camera: Camera, intensities: torch.Tensor):
    """(premultiplied linear colour (H,W,3), alpha (H,W)) float32 numpy of the avatar's frame
    ``frame_id`` under light ``intensities`` (L,3) on the capture's light stage, in ``camera``
    (studio frame); ``data`` an :class:`~egorelight_cli.stages.envmap_inverse.EgoAvatarData`."""
    with torch.no_grad():
        frame = data.lit(frame_id, intensities)
        rays, valid = rl.camera_rays(data.ray_lighting(frame_id), intensities, camera.centre_world, data.lightstage,
                                     data.rays)
        render, _ = rl.render_relit(model, frame, data.coverage, camera, rays, valid)
    return render.colour.numpy().astype(np.float32), render.alpha.numpy().astype(np.float32)


def avatar_to_camera(colour: np.ndarray, alpha: np.ndarray, mapping: CameraMapping | None,
                     min_alpha: float = 1e-3) -> tuple[np.ndarray, float]:
    """(premultiplied camera-linear colour (H,W,3) float32, 99th-percentile relative residual of
    the mapping) of a premultiplied avatar render (H,W,3) with ``alpha`` (H,W): un-premultiply, map
    (``None``: identity), premultiply again. Pixels below ``min_alpha`` are 0."""
    out = np.zeros_like(colour, dtype=np.float32)
    covered = alpha > min_alpha
    if not covered.any():
        return out, 0.0
    straight = np.maximum(colour[covered] / alpha[covered, None], 0.0)
    if mapping is None:
        mapped, residual = straight, np.zeros(1)
    else:
        mapped, residual = mapping.apply(straight)
    out[covered] = mapped * alpha[covered, None]
    return out, float(np.percentile(residual, 99))


def composite_image(background: np.ndarray, avatar: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(H,W,3) uint8 sRGB: ``alpha``-blend a premultiplied camera-linear ``avatar`` over an sRGB
    ``background`` (uint8 or float in [0,1]) in linear light, encode, quantise."""
    linear = srgb_to_linear(to_unit_float(background)[..., :3])
    out = avatar + (1.0 - alpha[..., None]) * linear
    return np.round(linear_to_srgb(np.clip(out, 0.0, 1.0)) * 255).astype(np.uint8)


def scaled_camera(camera: Camera, scale: float) -> Camera:
    """``camera`` with its image ``scale`` times as large (intrinsics scaled; pixel centres kept)."""
    if scale == 1.0:
        return camera
    K = np.array(camera.K, np.float64)
    K[:2] *= scale
    K[0, 2] = (camera.K[0, 2] + 0.5) * scale - 0.5
    K[1, 2] = (camera.K[1, 2] + 0.5) * scale - 0.5
    width, height = max(int(round(camera.width * scale)), 1), max(int(round(camera.height * scale)), 1)
    return Camera(camera.model, K, camera.dist, width, height, camera.T_cam_from_world, camera.name)
