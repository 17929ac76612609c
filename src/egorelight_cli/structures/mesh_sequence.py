"""Mesh sequences: :class:`MeshSequence` (posed vertices and the controls that made them) and
:class:`SurfaceSequence` (the topology-free part alone); arrays and files in
:mod:`egorelight_cli.io.mesh_sequence`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError


def _check_surface(vertices, faces, frame_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``vertices`` (T,V,3) float32, ``faces`` (F,3) int32, ``frame_ids`` (T,) int64."""
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    if v.ndim != 3 or v.shape[2] != 3:
        raise EgorelightError(f"meshes vertices have shape {v.shape}, expected (T, V, 3)")
    T, V = v.shape[:2]
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise EgorelightError(f"meshes faces have shape {f.shape} and dtype {f.dtype}, expected (F, 3) integers")
    if f.size and (f.min() < 0 or f.max() >= V):
        raise EgorelightError(f"meshes faces index vertices out of range (0..{V - 1})")
    ids = np.asarray(frame_ids)
    if ids.shape != (T,) or not np.issubdtype(ids.dtype, np.integer):
        raise EgorelightError(f"meshes frame_ids has shape {ids.shape}, expected ({T},) integers")
    if T > 1 and np.any(np.diff(ids) <= 0):
        raise EgorelightError("meshes frame_ids are not strictly increasing")
    if not np.isfinite(v).all():
        raise EgorelightError("meshes vertices holds NaN or inf values")
    return v, f.astype(np.int32), ids.astype(np.int64)


class _Frames:
    """Frame addressing shared by the sequences below (``vertices`` (T,...), ``frame_ids`` (T,))."""

    vertices: np.ndarray
    frame_ids: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    def index_of(self, frame_id: int) -> int:
        """Row of ``frame_id``; an error when absent."""
        rows = np.nonzero(self.frame_ids == int(frame_id))[0]
        if rows.size == 0:
            raise EgorelightError(f"meshes have no frame {frame_id}")
        return int(rows[0])


@dataclass(frozen=True, eq=False)
class SurfaceSequence(_Frames):
    """Triangle meshes of one topology over frames, and nothing else (shapes in
    :mod:`egorelight_cli.io.mesh_sequence`); what a geometric metric needs of a true surface, whatever its topology."""

    vertices: np.ndarray
    faces: np.ndarray
    frame_ids: np.ndarray
    ego_frame_ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        v, f, ids = _check_surface(self.vertices, self.faces, self.frame_ids)
        for name, value in (("vertices", v), ("faces", f), ("frame_ids", ids)):
            object.__setattr__(self, name, value)
        if self.ego_frame_ids is not None:
            object.__setattr__(self, "ego_frame_ids", np.asarray(self.ego_frame_ids, np.int64).reshape(len(ids)))


@dataclass(frozen=True, eq=False)
class MeshSequence(_Frames):
    """A mesh sequence (shapes in :mod:`egorelight_cli.io.mesh_sequence`); arrays are validated and cast."""

    vertices: np.ndarray
    faces: np.ndarray
    theta: np.ndarray
    eg_rotation: np.ndarray
    eg_translation: np.ndarray
    offsets: np.ndarray
    frame_ids: np.ndarray
    fps: float | None = None
    ego_frame_ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        v, f, ids = _check_surface(self.vertices, self.faces, self.frame_ids)
        T = v.shape[0]
        theta = np.asarray(self.theta, dtype=np.float32)
        rot = np.asarray(self.eg_rotation, dtype=np.float32)
        trans = np.asarray(self.eg_translation, dtype=np.float32)
        off = np.asarray(self.offsets, dtype=np.float32)
        if theta.ndim != 2 or theta.shape[0] != T:
            raise EgorelightError(f"meshes theta has shape {theta.shape}, expected ({T}, D)")
        if rot.ndim != 3 or rot.shape[0] != T or rot.shape[2] != 3 or trans.shape != rot.shape:
            raise EgorelightError(f"meshes eg_rotation/eg_translation have shapes {rot.shape}/{trans.shape}, "
                                  f"expected ({T}, N, 3) each")
        if off.shape != v.shape:
            raise EgorelightError(f"meshes offsets have shape {off.shape}, expected {v.shape}")
        for name, value in (("theta", theta), ("eg_rotation", rot), ("eg_translation", trans), ("offsets", off)):
            if not np.isfinite(value).all():
                raise EgorelightError(f"meshes {name} holds NaN or inf values")
        for name, value in (("vertices", v), ("faces", f), ("theta", theta), ("eg_rotation", rot),
                            ("eg_translation", trans), ("offsets", off), ("frame_ids", ids)):
            object.__setattr__(self, name, value)
        if self.ego_frame_ids is not None:
            object.__setattr__(self, "ego_frame_ids", np.asarray(self.ego_frame_ids, np.int64).reshape(T))

    def arrays(self) -> dict[str, np.ndarray]:
        out = {"vertices": self.vertices, "faces": self.faces, "theta": self.theta, "eg_rotation": self.eg_rotation,
               "eg_translation": self.eg_translation, "offsets": self.offsets, "frame_ids": self.frame_ids}
        if self.ego_frame_ids is not None:
            out["ego_frame_ids"] = self.ego_frame_ids
        return out
