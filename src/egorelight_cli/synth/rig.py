"""The simulated studio: dome cameras, head-tracking cameras, the lightstage and the ChArUco board.

* **Studio cameras** (role ``studio``): pinholes with a little radial distortion on rings of a
  sphere around the subject, looking at the body centre; linear HDR.
* **Tracking cameras** (role ``tracking``): a few pinholes with a narrower field of view aimed
  at head height, so that the HMD's ArUco markers are large enough to detect at every preset
  (they are ordinary studio cameras to every stage: same file formats).
* **Lightstage**: :meth:`LightStage.dome` with a seeded per-light RGB gain (calibration spread).
* **Board**: a ChArUco board (``cv2.aruco.CharucoBoard``) for hand-eye calibration, placed in
  front of the subject; its pose is ground truth only. Board frame = OpenCV's: origin at the
  board's top-left corner, x right, y down (as seen from the front), z into the board.
"""

from __future__ import annotations

import math

import numpy as np

from egorelight_cli.geometry.cameras import Camera, look_at
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.markers import charuco_board
from egorelight_cli.render.lightstage import LightStage
from egorelight_cli.synth.textures import TexturedMesh, grid_quad

STUDIO_ROLE = "studio"
TRACKING_ROLE = "tracking"
BOARD_DICTIONARY = "DICT_5X5_100"
BOARD_TEXELS_PER_M = 1250.0


def _pinhole(width: int, height: int, vfov_deg: float, rng: np.random.Generator, k1_std: float) -> tuple:
    f = (height / 2) / math.tan(math.radians(vfov_deg) / 2) * (1 + 0.01 * rng.normal())
    cx = (width - 1) / 2 + 0.004 * width * rng.normal()
    cy = (height - 1) / 2 + 0.004 * height * rng.normal()
    k1 = k1_std * rng.normal()
    dist = np.array([k1, -0.3 * k1, 0.0, 0.0, 0.0])
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), dist


def studio_cameras(cfg, seed: int) -> list[tuple[Camera, str]]:
    """Dome and tracking cameras as ``(Camera, role)`` from the ``studio`` config section."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57D]))
    out: list[tuple[Camera, str]] = []
    n = int(cfg.num_cameras)
    rings = list(cfg.ring_elevations_deg)
    target = np.asarray(cfg.target, dtype=np.float64)
    for i in range(n):
        ring = i % len(rings)
        k = i // len(rings)
        per_ring = -(-n // len(rings))
        azimuth = 2 * math.pi * (k + 0.5 * (ring % 2)) / per_ring + 0.05 * rng.normal()
        elevation = math.radians(rings[ring] + 2.0 * rng.normal())
        radius = cfg.radius * (1 + 0.03 * rng.normal())
        direction = np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
                              -math.cos(elevation) * math.cos(azimuth)])
        eye = target + radius * direction
        aim = target + 0.05 * rng.normal(size=3)
        K, dist = _pinhole(cfg.width, cfg.height, cfg.vfov_deg, rng, cfg.k1_std)
        out.append((Camera("pinhole", K, dist, cfg.width, cfg.height, look_at(eye, aim), name=f"cam{i:02d}"),
                    STUDIO_ROLE))
    t = cfg.tracking
    head = np.asarray(t.target, dtype=np.float64)
    for i, azimuth_deg in enumerate(list(t.azimuths_deg)[: int(t.num_cameras)]):
        azimuth, elevation = math.radians(azimuth_deg), math.radians(t.elevation_deg)
        direction = np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
                              -math.cos(elevation) * math.cos(azimuth)])
        eye = head + t.radius * direction
        K, dist = _pinhole(t.width, t.height, t.vfov_deg, rng, 0.5 * cfg.k1_std)
        out.append((Camera("pinhole", K, dist, t.width, t.height, look_at(eye, head), name=f"track{i}"),
                    TRACKING_ROLE))
    return out


def held_out_cameras(cameras: list[tuple[Camera, str]], count: int) -> list[str]:
    """Names of ``count`` studio (not tracking) cameras spread around the dome, held out for testing."""
    studio = [c.name for c, role in cameras if role == STUDIO_ROLE]
    if count <= 0 or not studio:
        return []
    picks = np.linspace(0, len(studio), num=min(count, len(studio)), endpoint=False).astype(int) + 1
    return [studio[p % len(studio)] for p in picks]


def make_lightstage(cfg, seed: int) -> LightStage:
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x11D]))
    stage = LightStage.dome(num_lights=int(cfg.num_lights), radius=float(cfg.radius),
                            min_elevation_deg=float(cfg.min_elevation_deg), centre=tuple(cfg.centre))
    gain = np.clip(1.0 + cfg.gain_spread * rng.normal(size=stage.positions.shape), 0.5, 1.5)
    return LightStage(positions=stage.positions, rgb_gain=gain, radius=stage.radius, centre=stage.centre)


# ---------------------------------------------------------------------------------------- board
def board_json(cfg) -> dict:
    """``rig/board.json``: the ChArUco board definition (its pose is not part of the rig)."""
    return {"type": "charuco", "squares_x": int(cfg.squares_x), "squares_y": int(cfg.squares_y),
            "square_length_m": float(cfg.square_length_m), "marker_length_m": float(cfg.marker_length_m),
            "dictionary": BOARD_DICTIONARY, "legacy_pattern": False,
            "frame": "OpenCV CharucoBoard frame: origin at the top-left board corner, x right, y down, "
                     "z into the board; metres"}


def board_mesh(cfg) -> TexturedMesh:
    """The board as a textured mesh in the board frame (printed front, grey backing)."""
    try:
        board = charuco_board(cfg)
    except ValueError as exc:
        raise EgorelightError(f"config section 'board': {exc}") from None
    width = cfg.squares_x * cfg.square_length_m
    height = cfg.squares_y * cfg.square_length_m
    cols, rows = round(width * BOARD_TEXELS_PER_M), round(height * BOARD_TEXELS_PER_M)
    image = board.generateImage((cols, rows), marginSize=0, borderBits=1)
    front = np.where(image[..., None] > 127, 0.85, 0.03).astype(np.float32) * np.ones(3, np.float32)
    back_col = np.full((rows, 16, 3), 0.4, np.float32)
    albedo = np.concatenate([front, back_col], axis=1)
    W = albedo.shape[1]
    centre = np.array([width / 2, height / 2, 0.0])
    v1, f1, uv1 = grid_quad(centre, (1, 0, 0), (0, 1, 0), width / 2, height / 2, 4, (0.0, 0.0, cols / W, 1.0))
    v2, f2, uv2 = grid_quad(centre + [0, 0, 0.006], (-1, 0, 0), (0, 1, 0), width / 2, height / 2, 2,
                            ((cols + 4) / W, 0.0, (cols + 12) / W, 1.0))
    spec = np.full(albedo.shape[:2] + (1,), 0.01, np.float32)
    rough = np.full(albedo.shape[:2] + (1,), 0.9, np.float32)
    return TexturedMesh(vertices=np.concatenate([v1, v2]), faces=np.concatenate([f1, f2 + len(v1)]),
                        face_uvs=np.concatenate([uv1, uv2]), albedo=albedo, specular=spec, roughness=rough)


def board_pose(cfg, head_position: np.ndarray, forward: np.ndarray, seed: int) -> np.ndarray:
    """``T_world_from_board``: the board in front of the head, facing it (seeded jitter)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xB0A]))
    forward = np.asarray(forward, np.float64) / np.linalg.norm(forward)
    centre = head_position + cfg.distance_m * forward + np.array([0.0, -cfg.drop_m, 0.0]) + 0.03 * rng.normal(size=3)
    z = centre - head_position
    z /= np.linalg.norm(z)
    right = np.cross(forward, [0.0, 1.0, 0.0])  # the viewer's right
    x = right - z * (z @ right)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    width = cfg.squares_x * cfg.square_length_m
    height = cfg.squares_y * cfg.square_length_m
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = centre - x * width / 2 - y * height / 2
    return T

