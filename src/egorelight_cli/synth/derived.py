"""Derived inputs a real lab would have besides the raw images, made from the truth with errors.

* **masks** (studio): the subject (body and worn HMD) in each studio image, 8-bit PNG 0/255;
* **normal estimates** (the paper uses Sapiens): camera-frame unit normals (OpenCV axes) of the
  visible subject with smooth and per-pixel noise, background 0, EXR layer ``normal``;
* **multi-view reconstruction** (the paper uses NeuS2): the outer surface of the subject only
  (faces not visible from any studio camera centre or any of a set of directions around it are
  dropped: the inside of the HMD, touching skin folds), re-tessellated (quadric decimation, so
  its topology is not the template's), Taubin-smoothed and displaced along its normals by
  smooth + fine noise;
* **markerless mocap** keypoints (training supervision): true keypoints with a constant
  per-keypoint bias and temporally correlated noise, noisier on the hands.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.keypoints import Keypoints
from egorelight_cli.render.raster import face_normals, vertex_normals
from egorelight_cli.runtime import single_threaded_openmp
from egorelight_cli.structures.keypoints import BODY_SLICE
from egorelight_cli.synth.appearance import value_noise


def mask_image(subject: np.ndarray) -> np.ndarray:
    return np.where(subject, 255, 0).astype(np.uint8)


def normal_estimate(world_normals: np.ndarray, subject: np.ndarray, camera: Camera, rng: np.random.Generator,
                    smooth_noise: float, pixel_noise: float) -> np.ndarray:
    """(H,W,3) float32 camera-frame normals of the subject with estimation errors (0 elsewhere)."""
    R = camera.T_cam_from_world[:3, :3]
    n = world_normals @ R.T
    H, W = subject.shape
    sigma = max(H, W) / 40.0
    low = ndimage.gaussian_filter(rng.normal(size=(H, W, 3)), (sigma, sigma, 0)) * sigma * 2.0
    n = n + smooth_noise * low + pixel_noise * rng.normal(size=(H, W, 3))
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9)
    return np.where(subject[..., None], n, 0.0).astype(np.float32)


def sphere_directions(count: int) -> np.ndarray:
    """(count,3) near-uniform unit directions (Fibonacci sphere)."""
    k = np.arange(count) + 0.5
    y = 1 - 2 * k / count
    r = np.sqrt(1 - y * y)
    phi = np.pi * (3 - np.sqrt(5)) * k
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=-1)


def outer_faces(vertices: np.ndarray, faces: np.ndarray, caster: RayCaster, viewpoints: np.ndarray,
                directions: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """(F,) bool: faces whose front side sees a viewpoint or a direction at infinity unoccluded."""
    tri = vertices[faces]
    centroid = tri.mean(axis=1)
    normal = face_normals(vertices, faces)
    origin = centroid + eps * normal
    visible = np.zeros(len(faces), dtype=bool)
    for target in viewpoints:
        d = target - origin
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        front = np.sum(d * normal, axis=1) > 0
        todo = front & ~visible
        if todo.any():
            visible[todo] |= ~caster.occluded(origin[todo], d[todo], max_dist=dist[todo])
    for d in directions:
        todo = (normal @ d > 0) & ~visible
        if todo.any():
            visible[todo] |= ~caster.occluded(origin[todo], np.broadcast_to(d, (int(todo.sum()), 3)))
    return visible


def reconstruct(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray, rng: np.random.Generator, cfg) -> tuple[np.ndarray, np.ndarray]:
    """A NeuS2-like reconstruction of the kept faces: (vertices (V',3), faces (F',3))."""
    import pymeshlab

    sub = faces[keep]
    used, inverse = np.unique(sub, return_inverse=True)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices[used], np.float64),
                               face_matrix=inverse.reshape(-1, 3).astype(np.int32)))
    target = max(int(len(sub) * cfg.decimate_ratio), 100)
    with single_threaded_openmp():
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=target, preservetopology=False,
                                                    preserveboundary=True)
        ms.apply_coord_taubin_smoothing(stepsmoothnum=int(cfg.smooth_steps))
    mesh = ms.current_mesh()
    v = np.asarray(mesh.vertex_matrix(), np.float64)
    f = np.asarray(mesh.face_matrix(), np.int64)
    n = vertex_normals(v, f)
    offset = cfg.noise_smooth_m * value_noise(v, 0.1, rng) + cfg.noise_fine_m * rng.normal(size=len(v))
    return v + offset[:, None] * n, f


def mocap_keypoints(xyz: np.ndarray, frame_ids: np.ndarray, fps: float, rng: np.random.Generator, cfg) -> Keypoints:
    """Markerless-mocap keypoints from true ones (T,57,3)."""
    T, K, _ = xyz.shape
    scale = np.full(K, cfg.hand_noise_scale)
    scale[BODY_SLICE] = 1.0
    bias = cfg.bias_m * rng.normal(size=(1, K, 3)) * scale[None, :, None]
    sigma = max(cfg.noise_time_s * fps, 1e-3)
    jitter = ndimage.gaussian_filter1d(rng.normal(size=(T, K, 3)), sigma, axis=0, mode="nearest")
    jitter *= np.sqrt(2 * np.sqrt(np.pi) * sigma) if sigma > 0.5 else 1.0
    noisy = xyz + bias + cfg.noise_m * jitter * scale[None, :, None]
    confidence = np.where(scale > 1.0, 0.6, 0.9) * np.ones((T, 1))
    return Keypoints(noisy.astype(np.float32), confidence.astype(np.float32), np.asarray(frame_ids), fps=fps)
