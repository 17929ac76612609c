"""LDR camera responses (ego and front-facing HMD cameras) and views of an environment map.

A :class:`CameraResponse` turns linear scene radiance (H,W,3) into the 8-bit sRGB image an HMD
camera records, in this order (:meth:`CameraResponse.apply`):

1. exposure: ``x = exposure * L`` (one scalar gain: shutter x gain x aperture, fixed per camera);
2. colour: ``x = colour_matrix @ x`` per pixel (3,3; the sensor's colour cross-talk and white
   balance, unknown to the method);
3. clipping to [0, 1] (sensor saturation; ``clip=False`` keeps values, the encoder still clips);
4. noise: additive Gaussian, standard deviation ``noise_std`` in linear units, plus optional
   shot noise ``shot_noise * sqrt(x)``;
5. encoding: the sRGB curve (``gamma="srgb"``) or a pure power ``x ** (1 / gamma)`` (float gamma);
6. quantisation to ``bits`` (8 -> uint8, up to 16 -> uint16), rounding.

:meth:`CameraResponse.linearize` inverts steps 5, 2 and 1 (ignoring clipping, noise and
quantisation) for evaluation. :func:`random_ego_response` draws a plausible unknown response
(for down-facing ego cameras, and for the front-facing ones with their own draw);
:func:`exposure_for` picks a fixed exposure from a reference frame.

:func:`render_envmap_view` renders what a camera (front-facing HMD camera, any model) sees of an
environment map, at infinity (only the camera's rotation matters) or painted on a sphere around
the wearer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, pixel_grid, unproject_to_rays
from egorelight_cli.geometry.equirect import check_envmap, sample_equirect, yaw_rotation
from egorelight_cli.io.images import linear_to_srgb, srgb_to_linear
from egorelight_cli.runtime import single_torch_thread


@dataclass(eq=False)
class CameraResponse:
    """A fixed LDR camera response (see the module docstring for the pipeline).

    Attributes:
        exposure: scalar gain from scene radiance to sensor units (1.0 = radiance 1 saturates).
        colour_matrix: (3,3) linear RGB -> camera RGB matrix (white balance folded in).
        gamma: ``"srgb"`` or a positive float (encoding ``x ** (1 / gamma)``).
        noise_std: additive Gaussian noise in linear units (after clipping).
        bits: output bit depth, 1..16 (uint8 up to 8 bits, uint16 above).
        clip: clip to [0, 1] before adding noise.
        shot_noise: signal-dependent noise scale (std ``shot_noise * sqrt(x)``), 0 = off.
    """

    exposure: float = 1.0
    colour_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    gamma: str | float = "srgb"
    noise_std: float = 0.0
    bits: int = 8
    clip: bool = True
    shot_noise: float = 0.0

    def __post_init__(self) -> None:
        self.colour_matrix = np.array(self.colour_matrix, dtype=np.float64)
        if self.colour_matrix.shape != (3, 3) or not np.isfinite(self.colour_matrix).all():
            raise EgorelightError(f"colour_matrix must be a finite 3x3 matrix, got shape {self.colour_matrix.shape}")
        if abs(np.linalg.det(self.colour_matrix)) < 1e-9:
            raise EgorelightError("colour_matrix must be invertible")
        if not (np.isfinite(self.exposure) and self.exposure > 0):
            raise EgorelightError(f"exposure must be positive, got {self.exposure}")
        if self.gamma != "srgb" and not (isinstance(self.gamma, (int, float)) and self.gamma > 0):
            raise EgorelightError(f"gamma must be 'srgb' or a positive number, got {self.gamma!r}")
        if not 1 <= int(self.bits) <= 16:
            raise EgorelightError(f"bits must be in 1..16, got {self.bits}")
        if self.noise_std < 0 or self.shot_noise < 0:
            raise EgorelightError("noise levels must be non-negative")
        self.exposure, self.bits = float(self.exposure), int(self.bits)

    @property
    def max_code(self) -> int:
        return (1 << self.bits) - 1

    def _encode(self, x: np.ndarray) -> np.ndarray:
        if self.gamma == "srgb":
            return linear_to_srgb(x)
        return np.power(np.clip(x, 0.0, 1.0), 1.0 / float(self.gamma)).astype(np.float32)

    def _decode(self, y: np.ndarray) -> np.ndarray:
        if self.gamma == "srgb":
            return srgb_to_linear(y)
        return np.power(np.clip(y, 0.0, 1.0), float(self.gamma)).astype(np.float32)

    def sensor(self, linear: np.ndarray) -> np.ndarray:
        """Steps 1-2: (...,3) float32 camera-linear values ``colour_matrix @ (exposure * L)`` (not clipped)."""
        linear = np.asarray(linear, dtype=np.float32)
        if linear.shape[-1:] != (3,):
            raise EgorelightError(f"linear image must be (...,3), got {linear.shape}")
        matrix = (self.exposure * self.colour_matrix).astype(np.float32)
        return np.einsum("ij,...j->...i", matrix, linear)

    def apply(self, linear: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """Linear radiance (H,W,3) -> quantised encoded image (uint8 for bits <= 8, else uint16).

        ``rng`` drives the noise; None means no noise even if ``noise_std`` > 0.
        """
        x = self.sensor(linear)
        if self.clip:
            x = np.clip(x, 0.0, 1.0)
        if rng is not None and (self.noise_std > 0 or self.shot_noise > 0):
            std = np.float32(self.noise_std)
            if self.shot_noise > 0:
                std = np.sqrt(std ** 2 + np.float32(self.shot_noise) ** 2 * np.maximum(x, 0.0))
            x = x + std * rng.standard_normal(x.shape, dtype=np.float32)
        codes = np.rint(self._encode(x) * self.max_code)
        return codes.astype(np.uint8 if self.bits <= 8 else np.uint16)

    def linearize(self, image: np.ndarray) -> np.ndarray:
        """Approximate inverse of :meth:`apply`: encoded image (H,W,3) -> linear radiance (float32).

        Undoes the encoding, the colour matrix and the exposure; clipped, noisy and quantised
        values are not recovered.
        """
        image = np.asarray(image)
        y = image.astype(np.float32) / self.max_code if np.issubdtype(image.dtype, np.integer) else image
        camera_linear = self._decode(y)
        inverse = (np.linalg.inv(self.colour_matrix) / self.exposure).astype(np.float32)
        return np.einsum("ij,...j->...i", inverse, camera_linear)

    def to_dict(self) -> dict:
        """JSON-able description (ground truth for the simulator)."""
        return {"exposure": self.exposure, "colour_matrix": self.colour_matrix.tolist(), "gamma": self.gamma,
                "noise_std": self.noise_std, "shot_noise": self.shot_noise, "bits": self.bits, "clip": self.clip}

    @classmethod
    def from_dict(cls, data: dict) -> CameraResponse:
        return cls(**{k: data[k] for k in ("exposure", "colour_matrix", "gamma", "noise_std", "bits", "clip",
                                           "shot_noise") if k in data})


def exposure_for(linear: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.0,
                 target: float = 0.9) -> float:
    """Exposure that maps the ``percentile`` of the (masked) max-channel radiance to ``target``.

    A helper to fix a camera's exposure once per sequence from a reference frame.
    """
    values = np.asarray(linear, dtype=np.float64).max(axis=-1)
    if mask is not None:
        values = values[np.asarray(mask, dtype=bool)]
    values = values[np.isfinite(values)]
    level = float(np.percentile(values, percentile)) if values.size else 0.0
    return target / level if level > 0 else 1.0


def random_ego_response(rng: np.random.Generator, exposure: float = 1.0, exposure_stops: float = 0.5,
                        crosstalk: float = 0.08, white_balance: float = 0.15,
                        noise_std: tuple[float, float] = (0.002, 0.01)) -> CameraResponse:
    """A plausible, unknown ego-camera response.

    Args:
        rng: random generator.
        exposure: nominal exposure (e.g. from :func:`exposure_for`), jittered by
            ``2 ** U(-exposure_stops, exposure_stops)``.
        crosstalk: off-diagonal colour mixing, each entry ``U(-c/2, c)``; rows then sum to 1 so
            grey stays grey before white balance.
        white_balance: per-channel gains ``1 + U(-w, w)`` (green fixed at 1), applied after mixing.
        noise_std: range of the additive noise level.
    """
    mixing = np.eye(3) + rng.uniform(-crosstalk / 2, crosstalk, size=(3, 3)) * (1.0 - np.eye(3))
    mixing /= mixing.sum(axis=1, keepdims=True)
    gains = 1.0 + rng.uniform(-white_balance, white_balance, size=3)
    gains[1] = 1.0
    return CameraResponse(
        exposure=float(exposure) * 2.0 ** rng.uniform(-exposure_stops, exposure_stops),
        colour_matrix=gains[:, None] * mixing,
        gamma="srgb",
        noise_std=float(rng.uniform(*noise_std)),
        bits=8,
        clip=True,
    )


def render_envmap_view(envmap: np.ndarray, camera: Camera, yaw_deg: float = 0.0, supersample: int = 2,
                       radius_m: float | None = None, centre=None, floor_y: float | None = None) -> np.ndarray:
    """What ``camera`` sees of an environment map: (H,W,3) float32 linear radiance.

    By default the map is at infinity and only the rotation of ``camera.T_cam_from_world``
    matters. With ``radius_m`` the map is painted on a sphere of that radius around ``centre``
    (world, metres; the camera must be inside): a ray ``o + t d`` sees the map in the direction
    of its hit point from the centre, so moving the camera shows parallax (a room or a street
    around the wearer). ``floor_y`` (world height, below the centre) adds a ground plane: rays
    that meet it before the sphere see the map there (the map's lower half painted on the floor,
    like a ground-projected environment), which gives the scene near points and depth variation.
    The map is the one of ``rotate_envmap(envmap, yaw_deg)`` (sampled
    without resampling the map). Each pixel averages ``supersample x supersample`` bilinear
    samples over its footprint; pixels without a ray (outside a fisheye's image circle) are 0.
    """
    envmap = check_envmap(envmap)
    supersample = max(int(supersample), 1)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = pixel_grid(camera.width, camera.height)  # (H,W,2), centres at integers
    sub = np.stack(np.meshgrid(offsets, offsets, indexing="xy"), axis=-1).reshape(-1, 2)  # (S,2) (du, dv)
    pixels = grid[:, :, None, :] + sub[None, None]
    with single_torch_thread():
        dirs_cam, valid = unproject_to_rays(pixels, camera.K, camera.dist, camera.model, return_valid=True)
    R_world_from_cam = camera.T_cam_from_world[:3, :3].T
    dirs = np.einsum("ij,...j->...i", R_world_from_cam, dirs_cam)
    if radius_m is not None:
        origin = camera.centre_world - np.asarray(centre, dtype=np.float64)
        c = float(origin @ origin) - float(radius_m) ** 2
        if c >= 0:
            raise EgorelightError(f"camera at {camera.centre_world.round(3).tolist()} is outside the surroundings' "
                                  f"sphere (radius {radius_m} m)")
        b = dirs @ origin
        t = -b + np.sqrt(b * b - c)  # the far root: the hit in front of the camera
        if floor_y is not None:
            height = float(floor_y) - float(camera.centre_world[1])
            if height >= 0:
                raise EgorelightError(f"camera at {camera.centre_world.round(3).tolist()} is below the floor ({floor_y} m)")
            down = dirs[..., 1] < 0
            t = np.where(down, np.minimum(t, height / np.where(down, dirs[..., 1], -1.0)), t)
        dirs = origin + t[..., None] * dirs
    # The rotated map is looked up at R_y(yaw)^T d.
    samples = sample_equirect(envmap, dirs @ yaw_rotation(yaw_deg)) * valid[..., None]
    count = np.maximum(valid.sum(axis=-1), 1)[..., None]
    return (samples.sum(axis=2) / count).astype(np.float32)
