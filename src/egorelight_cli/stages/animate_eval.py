"""Scoring the animation stage against a simulated capture's ground truth (evaluation only).

Nothing here is on a stage's input path: it reads ``capture/groundtruth/`` (true meshes, the
oracle calibration) to score meshes, and builds a ground-truth point cloud for tests and
experiments while the ``egodepth`` stage is not available.

* :func:`ego_visible_vertices`: which ground-truth vertices the down-facing ego cameras see
  (inside the image, facing the camera, not occluded: an Embree ray cast per vertex);
* :func:`point_to_surface_cm`: distance of predicted vertices to the true surface (exact,
  :class:`~egorelight_cli.geometry.pointcloud_ops.SurfaceDistance`);
* :func:`groundtruth_pointcloud`: ray-cast the true mesh from the down cameras, add noise along
  the rays, and return a :class:`~egorelight_cli.io.pointcloud.PointCloudSequence`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, camera_rays_world, project_world
from egorelight_cli.geometry.normals import face_normals, vertex_normals
from egorelight_cli.geometry.pointcloud_ops import SurfaceDistance
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.calibration import posed_ego_camera
from egorelight_cli.io.capture import Capture
from egorelight_cli.io.mesh_sequence import MeshSequence, read_meshes_npz

VISIBILITY_OFFSET_M = 2e-3


def groundtruth_meshes(capture: Capture, sequence: str) -> MeshSequence | None:
    """The true mesh sequence of ``sequence`` or None when the capture has no ground truth."""
    path = capture.groundtruth_file(sequence, "meshes.npz")
    return None if path is None else read_meshes_npz(path)


def down_cameras(capture: Capture, calibration, sequence: str, frame_id: int) -> list[Camera]:
    """The down-facing ego cameras placed in the world at ``frame_id`` (via ``calibration``)."""
    out = [posed_ego_camera(capture, calibration, role, sequence, frame_id)
           for role in capture.ego_cameras if role.startswith("down")]
    if not out:
        raise EgorelightError("the HMD has no down-facing camera", capture.root / "rig" / "hmd.json")
    return out


def ego_visible_vertices(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    """(V,) bool: vertex seen by at least one camera (in the image, front-facing, unoccluded)."""
    vertices = np.asarray(vertices, np.float64)
    normals = vertex_normals(vertices, faces)
    caster = RayCaster(vertices, faces)
    visible = np.zeros(len(vertices), bool)
    for cam in cameras:
        pixels, valid = project_world(cam, vertices, return_valid=True)
        pixels = np.asarray(pixels)
        inside = np.asarray(valid) & (pixels[:, 0] >= -0.5) & (pixels[:, 0] <= cam.width - 0.5) \
            & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= cam.height - 0.5)
        to_cam = cam.centre_world[None] - vertices
        dist = np.linalg.norm(to_cam, axis=1)
        facing = np.sum(normals * to_cam, axis=1) > 0
        todo = np.flatnonzero(inside & facing & ~visible)
        if todo.size:
            origin = vertices[todo] + VISIBILITY_OFFSET_M * to_cam[todo] / dist[todo, None]
            blocked = caster.occluded(origin, to_cam[todo], max_dist=dist[todo] - VISIBILITY_OFFSET_M)
            visible[todo[~blocked]] = True
    return visible


def point_to_surface_cm(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(P,) exact distances (cm) from points (P,3) to the triangle mesh (vertices, faces)."""
    return 100.0 * SurfaceDistance(vertices, faces)(points)


def score_meshes(predicted: dict[str, np.ndarray], frame_ids: np.ndarray, truth: MeshSequence,
                 visible: dict[int, np.ndarray]) -> dict[str, float]:
    """Mean point-to-surface distance (cm) of several predictions of the same frames.

    Args:
        predicted: name -> (T,V,3) vertices (the character's topology, same as the truth's).
        frame_ids: (T,) studio ids; frames absent from the truth are skipped.
        truth: the true meshes.
        visible: frame id -> (V,) bool ego-visible true vertices.
    Returns:
        ``{<name>_p2s_cm, <name>_p2s_ego_visible_cm}`` plus ``eval_frames``.
    """
    sums = {name: [0.0, 0, 0.0, 0] for name in predicted}
    frames = 0
    for row, fid in enumerate(np.asarray(frame_ids)):
        if fid not in truth.frame_ids:
            continue
        frames += 1
        gt = truth.vertices[truth.index_of(int(fid))]
        seen = visible[int(fid)]
        for name, verts in predicted.items():
            d = point_to_surface_cm(verts[row], gt, truth.faces)
            s = sums[name]
            s[0] += d.sum(); s[1] += d.size
            s[2] += d[seen].sum(); s[3] += int(seen.sum())
    out: dict[str, float] = {"eval_frames": frames}
    for name, (total, count, vis_total, vis_count) in sums.items():
        out[f"{name}_p2s_cm"] = float(total / count) if count else float("nan")
        out[f"{name}_p2s_ego_visible_cm"] = float(vis_total / vis_count) if vis_count else float("nan")
    return out


def visibility_of_truth(capture: Capture, calibration, sequence: str, truth: MeshSequence,
                        frame_ids: np.ndarray) -> dict[int, np.ndarray]:
    """Frame id -> (V,) ego-visible true vertices for the frames of ``frame_ids`` in the truth.

    A sequence without head poses (the HMD is not worn, e.g. ``relight_train``) has no ego view:
    every vertex is then unseen (the ego-visible metrics are NaN, the full-body ones still hold).
    """
    worn = sequence in calibration.head_poses
    out = {}
    for fid in np.asarray(frame_ids):
        if fid in truth.frame_ids:
            vertices = truth.vertices[truth.index_of(int(fid))]
            if not worn:
                out[int(fid)] = np.zeros(len(vertices), bool)
                continue
            cams = down_cameras(capture, calibration, sequence, int(fid))
            out[int(fid)] = ego_visible_vertices(vertices, truth.faces, cams)
    return out


def groundtruth_pointcloud(capture_root: str | Path, sequence: str, noise_m: float = 0.003, max_points: int = 20000,
                           stride: int = 1, seed: int = 0):
    """A point cloud like ``egodepth``'s, made from the truth (tests and experiments only).

    Rays through every ``stride``-th pixel of each down camera (oracle calibration) hit the true
    mesh; hits get Gaussian noise of ``noise_m`` along the ray; normals are the true face normals
    oriented towards the camera. Frames without a head pose are left empty.
    """
    from egorelight_cli.io.pointcloud import PointCloudSequence
    from egorelight_cli.synth.groundtruth import oracle_calibration

    capture = Capture(capture_root)
    calibration = oracle_calibration(capture_root)
    truth = groundtruth_meshes(capture, sequence)
    if truth is None:
        raise EgorelightError(f"capture has no ground-truth meshes for {sequence!r}", capture_root)
    rng = np.random.default_rng(seed)
    T = truth.num_frames
    points = np.zeros((T, max_points, 3), np.float32)
    normals = np.zeros((T, max_points, 3), np.float32)
    valid = np.zeros((T, max_points), bool)
    for t, fid in enumerate(truth.frame_ids):
        try:
            cams = down_cameras(capture, calibration, sequence, int(fid))
        except EgorelightError:
            continue
        verts = truth.vertices[t].astype(np.float64)
        caster = RayCaster(verts, truth.faces)
        fn = face_normals(verts, truth.faces)
        pts, nrm = [], []
        for cam in cams:
            origins, dirs, ok = camera_rays_world(cam)
            origins, dirs, ok = origins[::stride, ::stride], dirs[::stride, ::stride], ok[::stride, ::stride]
            hits = caster.first_hit(origins[ok], dirs[ok])
            d = hits.distance[hits.hit] + noise_m * rng.normal(size=int(hits.hit.sum()))
            pts.append(origins[ok][hits.hit] + d[:, None] * dirs[ok][hits.hit])
            n = fn[hits.face_id[hits.hit]]
            n = np.where((np.sum(n * dirs[ok][hits.hit], axis=1) > 0)[:, None], -n, n)
            nrm.append(n)
        pts, nrm = np.concatenate(pts), np.concatenate(nrm)
        if len(pts) > max_points:
            keep = rng.choice(len(pts), max_points, replace=False)
            pts, nrm = pts[keep], nrm[keep]
        points[t, :len(pts)], normals[t, :len(pts)], valid[t, :len(pts)] = pts, nrm, True
    return PointCloudSequence(points, normals, valid, truth.frame_ids)
