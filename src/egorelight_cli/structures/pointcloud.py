"""The :class:`PointCloudSequence`: fused egocentric point clouds per frame (the payload of
:mod:`egorelight_cli.io.pointcloud`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError


@dataclass(frozen=True)
class PointCloudSequence:
    """Per-frame point clouds of one sequence (shapes in :mod:`egorelight_cli.io.pointcloud`)."""

    points: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    frame_ids: np.ndarray
    fps: float | None = None

    def __post_init__(self) -> None:
        points = np.ascontiguousarray(self.points, dtype=np.float32)
        normals = np.ascontiguousarray(self.normals, dtype=np.float32)
        valid = np.ascontiguousarray(self.valid, dtype=bool)
        ids = np.asarray(self.frame_ids)
        if points.ndim != 3 or points.shape[2] != 3:
            raise EgorelightError(f"pointcloud points have shape {points.shape}, expected (T, P, 3)")
        if normals.shape != points.shape:
            raise EgorelightError(f"pointcloud normals have shape {normals.shape}, expected {points.shape}")
        if valid.shape != points.shape[:2]:
            raise EgorelightError(f"pointcloud valid has shape {valid.shape}, expected {points.shape[:2]}")
        if ids.shape != (points.shape[0],) or not np.issubdtype(ids.dtype, np.integer):
            raise EgorelightError(f"pointcloud frame_ids has shape {ids.shape} and dtype {ids.dtype}, "
                                  f"expected ({points.shape[0]},) integers")
        if ids.size > 1 and np.any(np.diff(ids) <= 0):
            raise EgorelightError("pointcloud frame_ids are not strictly increasing")
        if not (np.isfinite(points).all() and np.isfinite(normals).all()):
            raise EgorelightError("pointcloud holds NaN or inf values")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "normals", normals)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "frame_ids", ids.astype(np.int64))

    @property
    def num_frames(self) -> int:
        return int(self.points.shape[0])

    def frame(self, frame_id: int) -> tuple[np.ndarray, np.ndarray]:
        """The valid ``(points (n,3), normals (n,3))`` of one frame id."""
        index = np.nonzero(self.frame_ids == int(frame_id))[0]
        if index.size == 0:
            raise EgorelightError(f"pointcloud has no frame {frame_id} "
                                  f"(frames {self.frame_ids.min()}..{self.frame_ids.max()})")
        keep = self.valid[index[0]]
        return self.points[index[0]][keep], self.normals[index[0]][keep]

    def arrays(self) -> dict[str, np.ndarray]:
        return {"points": self.points, "normals": self.normals, "valid": self.valid, "frame_ids": self.frame_ids}
