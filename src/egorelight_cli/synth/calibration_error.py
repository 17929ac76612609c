"""Calibration as a lab has it: the camera parameters a simulated capture hands to the pipeline
carry a seeded calibration error; the true ones (those the renderer used) are ground truth only.

* **Studio cameras** (``rig/studio_cameras.json``): focal length, principal point, distortion
  (pinhole k1 k2 p1 p2; k3 stays as it is, as labs usually fix it) and pose (a rotation and a
  translation in the camera frame) are moved along a seeded random direction, scaled so that
  the RMS reprojection error between true and written cameras of the points of
  :func:`capture_volume_points` (the subject's region: x, z in +-0.5 m, y in 0..2 m) is
  ``calibration_error.studio_reprojection_px``, pooled over all cameras (each camera's own RMS
  varies around it).
* **HMD cameras** (``rig/hmd.json``): intrinsics only (focal length, principal point,
  distortion: fisheye k1..k4, pinhole k1 k2 p1 p2), scaled so that the RMS over the image (rays
  through a grid of pixels of the true camera) is ``calibration_error.ego_reprojection_px``.
  Their mounting ``T_cam_from_hmd`` is not in the rig at all (``calibrate`` recovers it).

Before scaling, every parameter's step is expressed in pixels: one unit of it moves the image by
about one pixel where the parameter matters most (focal length, rotation about the optical axis
and translation along it at the image edge; principal point, the other rotations and
translations at the centre; each distortion coefficient at the largest radius the image
reaches), so that no parameter dominates the mix. A target of 0 writes the true parameters
unchanged: the rig of a capture without calibration error.

Errors are pixels, lengths metres, angles radians. Ground truth (evaluation only)::

    groundtruth/studio_cameras.json   {"cameras": [the true cameras, as in rig/studio_cameras.json],
                                       "reprojection_rms_px": {camera name: its written camera's RMS
                                       over the capture volume (null: sees none of it), "all": pooled}}
    groundtruth/hmd_intrinsics.json   {role: {"K": 3x3, "dist": [...]}}: the true HMD intrinsics
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, pixel_grid, project_world, unproject_to_rays
from egorelight_cli.geometry.rigid import rigid_from_vector
from egorelight_cli.synth import groundtruth
from egorelight_cli.synth.hmd import EgoCamera, Hmd

#: The capture volume the studio error is measured over (metres): x, z in +-half width, y in 0..height.
VOLUME_HALF_WIDTH_M = 0.5
VOLUME_HEIGHT_M = 2.0
VOLUME_STEPS = (9, 17, 9)  # grid points along x, y, z
#: Pixel samples per image side whose rays measure an HMD camera's intrinsic error.
IMAGE_GRID = 32
#: Distortion coefficients a calibration estimates (1) or keeps fixed (0), per model.
_ESTIMATED_DIST = {"pinhole": (1, 1, 1, 1, 0), "fisheye": (1, 1, 1, 1)}
_SCALE_ITERATIONS = 12
_SCALE_TOLERANCE = 1e-3  # relative
STUDIO_TRUTH = "studio_cameras.json"
EGO_TRUTH = "hmd_intrinsics.json"


# ------------------------------------------------------------------------------ measuring
def capture_volume_points(half_width_m: float = VOLUME_HALF_WIDTH_M, height_m: float = VOLUME_HEIGHT_M,
                          steps: tuple[int, int, int] = VOLUME_STEPS) -> np.ndarray:
    """(N,3) float64 world points, metres: a regular grid with x and z in ``[-half_width_m,
    half_width_m]`` and y (up) in ``[0, height_m]``, where the subject stands."""
    x = np.linspace(-half_width_m, half_width_m, steps[0])
    y = np.linspace(0.0, height_m, steps[1])
    z = np.linspace(-half_width_m, half_width_m, steps[2])
    return np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1).reshape(-1, 3)


def _displacements_px(true_cam: Camera, written_cam: Camera, points: np.ndarray) -> np.ndarray:
    """(M,) distances in pixels between the two projections of the points (N,3, world, metres)
    that the true camera sees inside its image and both cameras project validly."""
    a, ok_a = project_world(true_cam, points, return_valid=True)
    b, ok_b = project_world(written_cam, points, return_valid=True)
    half = 0.5
    inside = ok_a & ok_b & (a[:, 0] >= -half) & (a[:, 0] <= true_cam.width - half) \
        & (a[:, 1] >= -half) & (a[:, 1] <= true_cam.height - half)
    return np.linalg.norm(a[inside] - b[inside], axis=1)


def reprojection_rms_px(true_cam: Camera, written_cam: Camera, points) -> float:
    """RMS reprojection error in pixels, ``sqrt(mean |project(true) - project(written)|^2)``, over
    the world points (N,3, metres) that ``true_cam`` sees inside its image."""
    d = _displacements_px(true_cam, written_cam, np.asarray(points, np.float64))
    if not len(d):
        raise EgorelightError(f"camera {true_cam.name!r} sees none of the {len(points)} points")
    return float(np.sqrt(np.mean(d ** 2)))


def _pooled_rms_px(true_cams: list[Camera], written_cams: list[Camera], points: list[np.ndarray]) -> float:
    """RMS reprojection error in pixels over every camera's visible points together."""
    d = np.concatenate([_displacements_px(t, w, p) for t, w, p in zip(true_cams, written_cams, points)])
    if not len(d):
        raise EgorelightError("no camera sees any of its calibration points")
    return float(np.sqrt(np.mean(d ** 2)))


def image_rays(camera: Camera, samples: int = IMAGE_GRID) -> np.ndarray:
    """(M,3) unit rays (camera frame) through a ``samples`` x ``samples`` grid of pixels spanning
    ``camera``'s image, those the lens can produce (fisheye: inside the image circle)."""
    grid = pixel_grid(camera.width, camera.height)
    rows = np.linspace(0, camera.height - 1, samples).round().astype(int)
    cols = np.linspace(0, camera.width - 1, samples).round().astype(int)
    pixels = grid[rows][:, cols].reshape(-1, 2)
    rays, valid = unproject_to_rays(pixels, camera.K, camera.dist, camera.model, return_valid=True)
    return rays[valid]


# ------------------------------------------------------------------------------ perturbing
def _dist_size(model: str) -> int:
    return len(_ESTIMATED_DIST[model])


def _unit_steps(camera: Camera, depth_m: float | None) -> np.ndarray:
    """Per-parameter step sizes worth about one pixel each (see the module docstring).

    Parameter vector: relative focal change, principal point (u, v) px, distortion coefficients,
    then, with ``depth_m`` (the distance to what the camera sees, metres), a rotation vector
    (rad) and a translation (m) in the camera frame.
    """
    rays = image_rays(camera)
    pixels = project_world(camera, rays)
    edge_px = float(np.max(np.linalg.norm(pixels - camera.K[:2, 2], axis=1)))
    f = float(camera.K[0, 0])
    if camera.model == "pinhole":
        r = float(np.max(np.linalg.norm(rays[:, :2] / rays[:, 2:], axis=1)))  # largest tan(off-axis angle)
        dist = [1 / (f * r ** 3), 1 / (f * r ** 5), 1 / (3 * f * r ** 2), 1 / (3 * f * r ** 2), 1 / (f * r ** 7)]
    else:
        theta = float(np.max(np.arccos(np.clip(rays[:, 2], -1, 1))))
        dist = [1 / (f * theta ** (2 * i + 1)) for i in range(1, 5)]
    steps = [1 / edge_px, 1.0, 1.0] + [s * e for s, e in zip(dist, _ESTIMATED_DIST[camera.model])]
    if depth_m is not None:
        steps += [1 / f, 1 / f, 1 / edge_px, depth_m / f, depth_m / f, depth_m / edge_px]
    return np.asarray(steps)


def _perturbed(camera: Camera, step: np.ndarray) -> Camera:
    """``camera`` with the parameter step of :func:`_unit_steps`'s layout applied (pose only when
    ``step`` carries the six pose entries)."""
    n = _dist_size(camera.model)
    K = camera.K.copy()
    K[0, 0] *= 1 + step[0]
    K[1, 1] *= 1 + step[0]
    K[:2, 2] += step[1:3]
    dist = np.pad(camera.dist, (0, n - camera.dist.size)) + step[3:3 + n]
    T = camera.T_cam_from_world
    if len(step) > 3 + n:
        T = rigid_from_vector(step[3 + n:]) @ T
    return dataclasses.replace(camera, K=K, dist=dist, T_cam_from_world=T)


def _scaled_to_rms(cameras: list[Camera], points: list[np.ndarray], directions: list[np.ndarray],
                   target_px: float) -> tuple[list[Camera], float]:
    """Written cameras ``cameras[i]`` moved by ``s * directions[i]``, with the scale ``s`` found so
    that the pooled RMS reprojection error over ``points`` is ``target_px``; and that RMS."""
    scale = 1.0
    for _ in range(_SCALE_ITERATIONS):
        written = [_perturbed(cam, scale * d) for cam, d in zip(cameras, directions)]
        achieved = _pooled_rms_px(cameras, written, points)
        if achieved <= 0:
            raise EgorelightError("a calibration error direction leaves every projection unchanged")
        if abs(achieved / target_px - 1) < _SCALE_TOLERANCE:
            break
        scale *= target_px / achieved
    return written, achieved


def _directions(rng: np.random.Generator, cameras: list[Camera], depths: list[float | None]) -> list[np.ndarray]:
    out = []
    for cam, depth in zip(cameras, depths):
        steps = _unit_steps(cam, depth)
        out.append(steps * rng.normal(size=steps.shape))
    return out


def perturb_studio_cameras(cameras: list[tuple[Camera, str]], cfg, seed: int,
                           points: np.ndarray | None = None) -> tuple[list[tuple[Camera, str]], float]:
    """Studio cameras as a lab's calibration would give them.

    Args:
        cameras: the true ``(Camera, role)`` list (:func:`~egorelight_cli.synth.rig.studio_cameras`).
        cfg: the ``calibration_error`` config section (``studio_reprojection_px``: target RMS, px).
        seed: the capture's seed.
        points: (N,3) world points (metres) the error is measured over; default
            :func:`capture_volume_points`.

    Returns:
        the written ``(Camera, role)`` list in the same order (names, sizes and roles unchanged)
        and the achieved RMS reprojection error over ``points``, pixels, pooled over all cameras
        (0 and the true cameras when the target is 0).
    """
    target = float(cfg.studio_reprojection_px)
    if target <= 0:
        return list(cameras), 0.0
    points = capture_volume_points() if points is None else np.asarray(points, np.float64)
    true = [cam for cam, _ in cameras]
    depths = []
    for cam in true:
        seen = points @ cam.T_cam_from_world[:3, :3].T + cam.T_cam_from_world[:3, 3]
        depths.append(float(np.median(seen[:, 2])))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xCA1]))
    written, rms = _scaled_to_rms(true, [points] * len(true), _directions(rng, true, depths), target)
    return [(cam, role) for cam, (_, role) in zip(written, cameras)], rms


def _at_origin(role: str, cam: EgoCamera) -> Camera:
    return Camera(cam.model, cam.K, cam.dist, cam.width, cam.height, np.eye(4), name=role)


def perturb_ego_intrinsics(cameras: Mapping[str, EgoCamera], cfg, seed: int) -> tuple[dict[str, EgoCamera], float]:
    """HMD camera intrinsics as an intrinsic calibration would give them.

    Args:
        cameras: the true HMD cameras by role (:attr:`Hmd.cameras`).
        cfg: the ``calibration_error`` config section (``ego_reprojection_px``: target RMS, px).
        seed: the capture's seed.

    Returns:
        the written cameras by role (``K`` and ``dist`` changed, the mounting kept) and the
        achieved RMS reprojection error in pixels over :func:`image_rays` of every camera
        (0 and the true cameras when the target is 0).
    """
    target = float(cfg.ego_reprojection_px)
    if target <= 0:
        return dict(cameras), 0.0
    true = [_at_origin(role, cam) for role, cam in cameras.items()]
    rays = [image_rays(cam) for cam in true]  # camera frame = world frame at the origin
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xCA2]))
    written, rms = _scaled_to_rms(true, rays, _directions(rng, true, [None] * len(true)), target)
    return {role: dataclasses.replace(cameras[role], K=cam.K, dist=cam.dist)
            for role, cam in zip(cameras, written)}, rms


# ------------------------------------------------------------------------------ files
def studio_rig_json(cameras: list[tuple[Camera, str]]) -> dict:
    """The ``rig/studio_cameras.json`` document: ``{"cameras": [Camera.to_dict() + {"role"}]}``."""
    return {"cameras": [{**cam.to_dict(), "role": role} for cam, role in cameras]}


def write_calibrations(writer, cameras: list[tuple[Camera, str]], hmd: Hmd, cfg, seed: int) -> dict:
    """Write the rig's camera files with calibration error and their truth.

    Writes ``rig/studio_cameras.json`` and ``rig/hmd.json`` (written cameras, through ``writer``,
    an :class:`~egorelight_cli.artifacts.ArtifactWriter`) and ``groundtruth/studio_cameras.json``
    and ``groundtruth/hmd_intrinsics.json`` (the true ones). ``cameras`` and ``hmd`` are the true
    rig; ``cfg`` the ``calibration_error`` section. Returns the capture's metrics
    ``studio_calibration_rms_px`` and ``ego_intrinsics_rms_px`` (pixels).
    """
    studio, studio_rms = perturb_studio_cameras(cameras, cfg, seed)
    ego, ego_rms = perturb_ego_intrinsics(hmd.cameras, cfg, seed)
    writer.save_json("rig/studio_cameras.json", studio_rig_json(studio))
    writer.save_json("rig/hmd.json", dataclasses.replace(hmd, cameras=ego).to_json())
    points = capture_volume_points()
    per_camera = {}
    for (true, _), (written, _) in zip(cameras, studio):
        d = _displacements_px(true, written, points)
        per_camera[true.name] = float(np.sqrt(np.mean(d ** 2))) if len(d) else None
    root = writer.workdir / groundtruth.GT
    groundtruth.write_json(root / STUDIO_TRUTH, {**studio_rig_json(cameras),
                                                 "reprojection_rms_px": {**per_camera, "all": studio_rms}})
    groundtruth.write_json(root / EGO_TRUTH, {role: {"K": cam.K.tolist(), "dist": cam.dist.tolist()}
                                              for role, cam in hmd.cameras.items()})
    return {"studio_calibration_rms_px": studio_rms, "ego_intrinsics_rms_px": ego_rms}


def read_true_studio_cameras(root: str | Path) -> dict[str, Camera]:
    """The true studio cameras of simulated capture ``root`` by name (evaluation only)."""
    return {entry["name"]: Camera.from_dict(entry) for entry in groundtruth.read_json(root, STUDIO_TRUTH)["cameras"]}


def read_true_ego_intrinsics(root: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The true HMD intrinsics of simulated capture ``root``: role -> (K (3,3) px, dist) (evaluation only)."""
    return {role: (np.asarray(doc["K"], np.float64), np.asarray(doc["dist"], np.float64))
            for role, doc in groundtruth.read_json(root, EGO_TRUTH).items()}
