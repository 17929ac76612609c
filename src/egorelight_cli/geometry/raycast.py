"""Ray casting against a triangle mesh with Intel Embree (through ``embreex``).

The acceleration structure is built once per mesh by :class:`RayCaster`; queries are batched
over any leading dims and run in float32, which is what Embree uses internally. There is no
pure-Python fallback: without ``embreex`` every entry point raises :class:`EgorelightError`.

Barycentrics follow Embree: a hit point is ``b0 * v0 + b1 * v1 + b2 * v2`` with
``(b0, b1, b2) = (1 - u - v, u, v)`` for the face's vertices in ``faces`` order.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from egorelight_cli.errors import EgorelightError

# A ray travelling no farther than this is treated as unbounded by Embree (float32 "infinity").
_EMBREE_FAR = np.float32(1e37)
# Direction lengths within this of 1 are taken as unit (float32 rounding of normalised vectors).
_UNIT_TOLERANCE = 1e-5


class RayHits(NamedTuple):
    """Closest hits of a batch of rays; shapes (...) are the rays' leading dims.

    Attributes:
        hit: (...) bool.
        face_id: (...) int32, -1 where nothing was hit.
        barycentrics: (...,3) float32 weights of the face's three vertices (0 on misses).
        distance: (...) float32 distance along the (unit) ray in metres, ``inf`` on misses.
    """

    hit: np.ndarray
    face_id: np.ndarray
    barycentrics: np.ndarray
    distance: np.ndarray


def _embreex_modules():
    """Import embreex's scene and mesh modules or raise a clear error (no slow fallback)."""
    try:
        from embreex import mesh_construction, rtcore_scene
    except ImportError as error:  # pragma: no cover - depends on the installation
        raise EgorelightError(
            f"Embree ray tracing is unavailable (cannot import embreex: {error}); "
            "install the 'embreex' package"
        ) from error
    return rtcore_scene, mesh_construction


def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert a mesh to Embree's dtypes: vertices (V,3) float32, faces (F,3) int32."""
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise EgorelightError(f"mesh vertices must be (V,3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise EgorelightError(f"mesh faces must be (F,3), got {faces.shape}")
    if len(faces) == 0:
        raise EgorelightError("mesh has no faces")
    if not np.isfinite(vertices).all():
        raise EgorelightError("mesh vertices contain NaN or infinity")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise EgorelightError(f"mesh faces index vertices outside [0, {len(vertices)})")
    return np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32)


def _row_norms(vectors: np.ndarray) -> np.ndarray:
    """Euclidean norms (N,) of rows of (N,3).

    Written as plain element-wise numpy on purpose: a BLAS matmul here leaves OpenBLAS worker
    threads spinning on the sibling hyperthread and slows the following Embree call by ~50%.
    """
    squared = vectors * vectors
    return np.sqrt(squared[:, 0] + squared[:, 1] + squared[:, 2])


def _flatten_rays(origins, dirs, near: float):
    """Broadcast rays to (N,3) float32 C-contiguous arrays for Embree.

    Directions are not rescaled (Embree's ray parameter t is in units of ``|dir|``); the
    per-ray direction lengths are returned instead, or None when all are 1 to float32
    precision (the common case, e.g. rays from ``unproject_to_rays``), so callers convert
    between metres and t only when they must. Origins are advanced by ``near`` metres along
    the ray (Embree's ray start is fixed at t = 0 by embreex).

    Returns:
        origins (N,3), dirs (N,3), the rays' leading shape, dir lengths (N,) float32 or None.
    """
    origins = np.asarray(origins, dtype=np.float32)
    dirs = np.asarray(dirs, dtype=np.float32)
    if origins.shape[-1:] != (3,) or dirs.shape[-1:] != (3,):
        raise EgorelightError(f"ray origins and directions must be (...,3), got {origins.shape} and {dirs.shape}")
    try:
        shape = np.broadcast_shapes(origins.shape, dirs.shape)
    except ValueError as error:
        raise EgorelightError(f"ray origins {origins.shape} and directions {dirs.shape} do not broadcast") from error
    lead = shape[:-1]
    dirs = np.ascontiguousarray(np.broadcast_to(dirs, shape).reshape(-1, 3))
    origins = np.ascontiguousarray(np.broadcast_to(origins, shape).reshape(-1, 3))
    lengths = _row_norms(dirs)
    if not np.all((lengths > 0) & np.isfinite(lengths)):
        raise EgorelightError("ray directions must be non-zero and finite")
    if lengths.size and float(np.abs(lengths - 1.0).max()) < _UNIT_TOLERANCE:
        lengths = None
    if near:
        step = np.float32(near) if lengths is None else (np.float32(near) / lengths)[:, None]
        origins = origins + step * dirs
    return origins, dirs, lead, lengths


def _tfar(max_dist, near: float, lead: tuple[int, ...], lengths: np.ndarray | None):
    """Embree's tfar (ray parameter) per ray for a distance limit in metres.

    Returns a float32 scalar when one value serves all rays, else (N,) float32; the limit is
    ``max_dist - near`` metres, divided by the direction lengths when they are not unit.
    """
    max_dist = np.asarray(max_dist, dtype=np.float64)
    if max_dist.ndim == 0 and lengths is None:
        far = float(max_dist) - near
        if not far > 0:
            raise EgorelightError(f"max_dist must exceed near ({near}), got {float(max_dist)}")
        return np.float32(min(far, float(_EMBREE_FAR)))
    far = np.broadcast_to(max_dist, lead).reshape(-1) - near
    if lengths is not None:
        far = far / lengths
    return np.ascontiguousarray(np.clip(far, 0.0, float(_EMBREE_FAR)), dtype=np.float32)


class RayCaster:
    """Embree scene of one triangle mesh, built once and queried many times.

    Args:
        vertices: (V,3) vertex positions, metres.
        faces: (F,3) vertex indices.
        robust: Embree's robust (watertight) traversal; no rays slip between adjacent
            triangles, about 15% slower. Keep it on for rasterisation.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, robust: bool = True):
        rtcore_scene, mesh_construction = _embreex_modules()
        self.vertices, self.faces = _check_mesh(vertices, faces)
        self._scene = rtcore_scene.EmbreeScene(robust=robust)
        self._mesh = mesh_construction.TriangleMesh(self._scene, self.vertices, self.faces)
        # Commit now (embreex commits lazily on the first query) so the build cost is paid here.
        self._scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="OCCLUDED")

    @property
    def embree_scene(self):
        """The underlying ``embreex.rtcore_scene.EmbreeScene`` (for benchmarks and experts)."""
        return self._scene

    def first_hit(self, origins, dirs, max_dist=np.inf, near: float = 0.0) -> RayHits:
        """Closest intersection of each ray with the mesh.

        Args:
            origins: (...,3) ray origins, metres (broadcast against ``dirs``).
            dirs: (...,3) ray directions, any non-zero length.
            max_dist: scalar or (...) farthest distance along the ray that counts, metres.
            near: hits closer than this to the origin are ignored (self-intersection offset).

        Returns:
            :class:`RayHits` with fields shaped like the rays' leading dims; distances in metres.
        """
        origins, dirs, lead, lengths = _flatten_rays(origins, dirs, near)
        tfar = _tfar(max_dist, near, lead, lengths)
        out = self._scene.run(origins, dirs, dists=tfar, output=True)
        face_id = out["primID"]
        hit = face_id >= 0
        miss = ~hit
        barycentrics = np.empty((len(face_id), 3), dtype=np.float32)
        barycentrics[:, 1] = out["u"]
        barycentrics[:, 2] = out["v"]
        barycentrics[:, 0] = 1.0 - barycentrics[:, 1] - barycentrics[:, 2]
        barycentrics[miss] = 0.0
        distance = out["tfar"]
        if lengths is not None:
            distance *= lengths
        if near:
            distance += np.float32(near)
        distance[miss] = np.inf
        return RayHits(
            hit=hit.reshape(lead),
            face_id=face_id.reshape(lead),
            barycentrics=barycentrics.reshape(*lead, 3),
            distance=distance.reshape(lead),
        )

    def occluded(self, origins, dirs, max_dist=np.inf, near: float = 0.0) -> np.ndarray:
        """Whether anything blocks each ray within ``(near, max_dist)`` (Embree any-hit query).

        Args:
            origins: (...,3) ray origins, metres.
            dirs: (...,3) ray directions, any non-zero length.
            max_dist: scalar or (...) distance to the point being tested (e.g. a light), metres.
            near: ignore blockers closer than this (self-shadowing offset from a surface).

        Returns:
            (...) bool, True where some triangle lies on the segment.
        """
        origins, dirs, lead, lengths = _flatten_rays(origins, dirs, near)
        tfar = _tfar(max_dist, near, lead, lengths)
        geom_id = self._scene.run(origins, dirs, dists=tfar, query="OCCLUDED")
        return (geom_id != -1).reshape(lead)

    def occluded_by_first_hit(self, origins, dirs, max_dist=np.inf, near: float = 0.0) -> np.ndarray:
        """Same result as :meth:`occluded`, computed by a closest-hit query and a distance test.

        Kept for benchmarking the two strategies (see ``bench/bench_raycast.py``); the any-hit
        query of :meth:`occluded` is the faster one.
        """
        return self.first_hit(origins, dirs, max_dist=max_dist, near=near).hit
