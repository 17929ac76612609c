"""Scoring geometry against a simulated capture's true surface, of any topology (evaluation only).

Nothing here is on a stage's input path: it reads ``capture/groundtruth/`` (true meshes, the
oracle calibration) to score meshes, and builds a ground-truth point cloud for tests and
experiments while the ``egodepth`` stage is not available.

The truth is read without assuming anything about its topology (:func:`groundtruth_meshes`: the
``vertices`` (T,V',3), ``faces`` (F',3) and ``frame_ids`` of ``groundtruth/<seq>/meshes.npz``,
nothing else): the subject may have its own tessellation, a body skin with separate garment
sheets over it, or be a real capture's reconstruction. Every distance is point-to-surface
(:class:`~egorelight_cli.geometry.pointcloud_ops.SurfaceDistance`), never vertex to vertex,
and its direction is in the metric's name:

* :func:`outer_faces`: the faces of a mesh that face the outside world. Skin under a garment
  is no surface a camera, a reconstruction or a clothed prediction can show, a closed pocket
  (a mouth cavity) neither: metrics compare the outer surface of a prediction with the outer
  surface of the truth;
* :class:`OuterSurface`: that outer surface of one mesh, points spread uniformly by area over
  it (the quadrature of true->pred) and which of them the down-facing ego cameras see;
* :func:`score_meshes`: predicted->true and true->predicted distances (cm) of several
  predictions, over the whole body and over the ego-visible surface;
* :func:`ego_visible_points` / :func:`ego_visible_vertices`: which points the down-facing ego
  cameras see (inside the image, unoccluded: an Embree ray cast per point; no facing test, so
  garment sheets of either winding count);
* :func:`groundtruth_pointcloud`: ray-cast the true mesh from the down cameras, add noise along
  the rays, and return a :class:`~egorelight_cli.io.pointcloud.PointCloudSequence`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, camera_rays_world, project_world
from egorelight_cli.geometry.normals import face_normals
from egorelight_cli.geometry.pointcloud_ops import SurfaceDistance
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.io.calibration import posed_ego_camera
from egorelight_cli.io.capture import Capture
from egorelight_cli.io.mesh_sequence import read_surface_npz
from egorelight_cli.structures.mesh_sequence import SurfaceSequence

VISIBILITY_OFFSET_M = 2e-3
# outer_faces: rays leave a face's centroid this far off the face, along the normal and along
# rings of directions at these polar angles (degrees) and counts around it, on either side.
OUTER_LIFT_M = 1e-4
OUTER_RINGS = ((40.0, 6), (75.0, 8))
# points per true surface and frame for the true->pred mean (standard error ~1% of the mean)
SURFACE_SAMPLES = 10000
# what score_meshes measures per prediction: <name>_p2s_<measure>_cm
SCORED = ("pred_to_true", "true_to_pred", "ego_visible_pred_to_true", "ego_visible_true_to_pred")


def groundtruth_meshes(capture: Capture, sequence: str) -> SurfaceSequence | None:
    """The true surface sequence of ``sequence`` (any topology) or None when the capture has no
    ground truth."""
    path = capture.groundtruth_file(sequence, "meshes.npz")
    return None if path is None else read_surface_npz(path)


def down_cameras(capture: Capture, calibration, sequence: str, frame_id: int) -> list[Camera]:
    """The down-facing ego cameras placed in the world at ``frame_id`` (via ``calibration``)."""
    out = [posed_ego_camera(capture, calibration, role, sequence, frame_id)
           for role in capture.ego_cameras if role.startswith("down")]
    if not out:
        raise EgorelightError("the HMD has no down-facing camera", capture.root / "rig" / "hmd.json")
    return out


def ego_visible_points(points: np.ndarray, caster: RayCaster, cameras: list[Camera]) -> np.ndarray:
    """(N,) bool: point (N,3) on the mesh of ``caster`` seen by at least one camera (projects
    inside its image, and the segment from the point lifted ``VISIBILITY_OFFSET_M`` towards the
    camera to the camera's centre hits nothing). No facing test: a point on the far side of a
    closed body is hidden by the body itself, and an open sheet is seen from either side."""
    points = np.asarray(points, np.float64)
    visible = np.zeros(len(points), bool)
    for cam in cameras:
        pixels, valid = project_world(cam, points, return_valid=True)
        pixels = np.asarray(pixels)
        inside = np.asarray(valid) & (pixels[:, 0] >= -0.5) & (pixels[:, 0] <= cam.width - 0.5) \
            & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= cam.height - 0.5)
        to_cam = cam.centre_world[None] - points
        dist = np.linalg.norm(to_cam, axis=1)
        todo = np.flatnonzero(inside & ~visible & (dist > VISIBILITY_OFFSET_M))
        if todo.size:
            origin = points[todo] + VISIBILITY_OFFSET_M * to_cam[todo] / dist[todo, None]
            blocked = caster.occluded(origin, to_cam[todo], max_dist=dist[todo] - VISIBILITY_OFFSET_M)
            visible[todo[~blocked]] = True
    return visible


def ego_visible_vertices(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera]) -> np.ndarray:
    """(V,) bool: vertex of the mesh (vertices, faces) seen by at least one camera
    (:func:`ego_visible_points`)."""
    vertices = np.asarray(vertices, np.float64)
    return ego_visible_points(vertices, RayCaster(vertices, faces), cameras)


def _hemisphere_directions(normals: np.ndarray) -> np.ndarray:
    """(K,N,3) unit directions around each unit normal (N,3): the normal, then ``OUTER_RINGS``."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    out = [normals]
    for ring, (polar_deg, count) in enumerate(OUTER_RINGS):
        polar = np.radians(polar_deg)
        for k in range(count):
            azimuth = 2 * np.pi * (k + 0.5 * ring) / count
            out.append(np.cos(polar) * normals + np.sin(polar) * (np.cos(azimuth) * t1 + np.sin(azimuth) * t2))
    return np.stack(out)


def outer_faces(vertices: np.ndarray, faces: np.ndarray, caster: RayCaster | None = None) -> np.ndarray:
    """(F,) bool: faces on the outside of the mesh: from the centroid, on one side of the face or
    the other, at least one ray (the normal and ``OUTER_RINGS`` around it) leaves the mesh without
    hitting it. Skin under a garment is enclosed (the garment on one side, the body on the other)
    and is not outer; a closed body alone is outer everywhere but in crevices no ray leaves.
    Faces of zero area are not outer. Winding does not matter.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    caster = caster or RayCaster(vertices, faces)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    solid = np.flatnonzero(double_area > 0)
    normals = cross[solid] / double_area[solid, None]
    centroids = tri[solid].mean(axis=1)
    outer = np.zeros(len(faces), bool)
    todo = np.arange(len(solid))
    for directions in _hemisphere_directions(normals):
        for side in (1.0, -1.0):
            if not todo.size:
                return outer
            origin = centroids[todo] + side * OUTER_LIFT_M * normals[todo]
            free = ~caster.occluded(origin, side * directions[todo])
            outer[solid[todo[free]]] = True
            todo = todo[~free]
    return outer


class OuterSurface:
    """The outer part (:func:`outer_faces`) of one triangle mesh, as every metric here sees a
    surface, the truth's and a prediction's alike: a metric compares what a camera could see of
    one with what it could see of the other, so hidden skin under a garment and closed pockets
    (a mouth cavity) count on neither side.

    Visibility is decided at the very points measured (a ray from each point to the cameras,
    :func:`ego_visible_points`), never per face or vertex, so it does not depend on the
    tessellation either.

    Attributes:
        faces: (K,3) the outer faces (rows of ``faces``).
        vertex_outer: (V,) bool, vertex of an outer face.
        distance: :class:`SurfaceDistance` to the outer faces.
        samples: (S,3) points spread uniformly by area over the outer faces (``samples`` of them,
            the same barycentric positions on every frame of one topology: ``seed``).
        sample_visible: (S,) bool, sample seen by ``cameras`` (all False without cameras).

    ``caster``: a :class:`RayCaster` of the same mesh when the caller has one.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera] = (),
                 caster: RayCaster | None = None, samples: int = SURFACE_SAMPLES, seed: int = 0):
        vertices = np.asarray(vertices, np.float64)
        faces = np.asarray(faces, np.int64)
        self.caster = caster or RayCaster(vertices, faces)
        self.cameras = list(cameras)
        self.faces = faces[outer_faces(vertices, faces, self.caster)]
        if not len(self.faces):
            raise EgorelightError("the mesh has no outer face")
        self.vertex_outer = np.zeros(len(vertices), bool)
        self.vertex_outer[self.faces.reshape(-1)] = True
        self.distance = SurfaceDistance(vertices, self.faces)
        tri = vertices[self.faces]
        areas = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        rng = np.random.default_rng(seed)
        face = rng.choice(len(tri), size=int(samples), p=areas / areas.sum())
        self.samples = np.einsum("sk,skd->sd", rng.dirichlet(np.ones(3), size=int(samples)), tri[face])
        self.sample_visible = self.seen(self.samples)

    def seen(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: points (P,3) on this mesh seen by its cameras."""
        if not self.cameras:
            return np.zeros(len(points), bool)
        return ego_visible_points(points, self.caster, self.cameras)

    @property
    def visible_area_fraction(self) -> float:
        return float(self.sample_visible.mean())

    def distance_cm(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distances (P,) cm of points (P,3) to the outer surface, and (P,) bool: the closest
        point is seen by the cameras."""
        closest, _, distance = self.distance.closest(points)
        return 100.0 * distance, self.seen(closest)


def true_surfaces(capture: Capture, calibration, sequence: str, truth: SurfaceSequence,
                  frame_ids: np.ndarray) -> dict[int, OuterSurface]:
    """Frame id -> the true :class:`OuterSurface` for the frames of ``frame_ids`` in the truth,
    its ego visibility from the down cameras placed by ``calibration``.

    A sequence without head poses (the HMD is not worn, e.g. ``relight_train``) has no ego view:
    nothing is ego-visible (the ego-visible metrics are NaN, the full-body ones still hold).
    """
    worn = sequence in calibration.head_poses
    out = {}
    for fid in np.asarray(frame_ids):
        if fid in truth.frame_ids:
            cameras = down_cameras(capture, calibration, sequence, int(fid)) if worn else []
            out[int(fid)] = OuterSurface(truth.vertices[truth.index_of(int(fid))], truth.faces, cameras)
    return out


def score_meshes(predicted: dict[str, np.ndarray], faces: np.ndarray, frame_ids: np.ndarray,
                 surfaces: dict[int, OuterSurface]) -> dict[str, float]:
    """Point-to-surface distances (cm) between several predictions of the same frames and the
    truth, both ways; the predictions' topology (``faces``) and the truth's are independent. Both
    sides are their outer surfaces (:class:`OuterSurface`).

    Args:
        predicted: name -> (T,V,3) vertices of the mesh ``faces``.
        faces: (F,3) predicted triangles.
        frame_ids: (T,) studio ids; frames without a true surface in ``surfaces`` are skipped.
        surfaces: frame id -> the true :class:`OuterSurface` (:func:`true_surfaces`).
    Returns:
        ``eval_frames`` and, per name (all frames pooled):

        * ``<name>_p2s_pred_to_true_cm`` (accuracy): mean over the predicted (outer) vertices of
          their distance to the true surface;
        * ``<name>_p2s_true_to_pred_cm`` (completeness): mean over the true surface (its
          area-uniform samples) of the distance to the predicted surface;
        * ``<name>_p2s_ego_visible_pred_to_true_cm``: the first, over the predicted vertices whose
          closest true point the down-facing ego cameras see;
        * ``<name>_p2s_ego_visible_true_to_pred_cm``: the second, over the ego-visible true surface;
        * ``<name>_p2s_cm`` / ``<name>_p2s_ego_visible_cm``: the two pred->true values under
          the names they had when the truth had to share the character's topology (the
          ego-visible vertices were then picked by vertex index); kept for continuity.

        NaN where a region is empty (no ego view).
    """
    sums = {f"{name}_p2s_{measure}_cm": [0.0, 0.0] for name in predicted for measure in SCORED}

    def add(key: str, values: np.ndarray) -> None:
        sums[key][0] += float(values.sum())
        sums[key][1] += len(values)

    frames = 0
    for row, fid in enumerate(np.asarray(frame_ids)):
        truth = surfaces.get(int(fid))
        if truth is None:
            continue
        frames += 1
        for name, vertices in predicted.items():
            prediction = OuterSurface(vertices[row], faces, samples=0)
            to_true, seen = truth.distance_cm(np.asarray(vertices[row])[prediction.vertex_outer])
            to_pred, _ = prediction.distance_cm(truth.samples)
            add(f"{name}_p2s_pred_to_true_cm", to_true)
            add(f"{name}_p2s_ego_visible_pred_to_true_cm", to_true[seen])
            add(f"{name}_p2s_true_to_pred_cm", to_pred)
            add(f"{name}_p2s_ego_visible_true_to_pred_cm", to_pred[truth.sample_visible])
    out: dict[str, float] = {"eval_frames": frames}
    for key, (total, weight) in sums.items():
        out[key] = float(total / weight) if weight > 0 else float("nan")
    for name in predicted:
        out[f"{name}_p2s_cm"] = out[f"{name}_p2s_pred_to_true_cm"]
        out[f"{name}_p2s_ego_visible_cm"] = out[f"{name}_p2s_ego_visible_pred_to_true_cm"]
    return out


def groundtruth_pointcloud(capture_root: str | Path, sequence: str, noise_m: float = 0.003, max_points: int = 20000,
                           stride: int = 1, seed: int = 0):
    """A point cloud like ``egodepth``'s, made from the truth (tests and experiments only).

    Rays through every ``stride``-th pixel of each down camera (oracle calibration) hit the true
    mesh; hits get Gaussian noise of ``noise_m`` along the ray; normals are the true face normals
    oriented towards the camera. Frames without a head pose are left empty.
    """
    from egorelight_cli.structures.pointcloud import PointCloudSequence
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
