"""The ``pointcloud`` artifact payload: the fused egocentric point cloud per frame.

``pointcloud.npz`` holds

* ``points`` (T,P,3) float32, world metres (P = 20,000 by default);
* ``normals`` (T,P,3) float32 unit normals, oriented towards the ego camera that saw the point;
* ``valid`` (T,P) bool (invalid entries are zero in ``points`` and ``normals``);
* ``frame_ids`` (T,) int64 master-clock (studio) frame ids, see :mod:`egorelight_cli.io.calibration`.

The artifact directory may also hold per-frame depth EXRs per ego camera (``depth/<role>/<frame>.exr``,
channel ``Z``, metres along the optical axis, 0 = no depth); they are not part of this payload.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_kind_npz, require_arrays, resolve_payload, write_npz

POINTCLOUD_KIND = "egorelight/pointcloud"
POINTCLOUD_VERSION = 1
POINTCLOUD_PAYLOAD = "pointcloud.npz"
POINTCLOUD_UNITS = {"points": "m", "normals": "unit"}


@dataclass(frozen=True)
class PointCloudSequence:
    """Per-frame point clouds of one sequence (shapes in the module docstring)."""

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


def write_pointcloud_npz(path: str | Path, cloud: PointCloudSequence, **meta) -> None:
    """Write a self-describing ``pointcloud.npz`` (outside an artifact writer)."""
    extra = {"fps": cloud.fps} if cloud.fps is not None else {}
    write_npz(path, cloud.arrays(), {"kind": POINTCLOUD_KIND, "version": POINTCLOUD_VERSION,
                                     "units": dict(POINTCLOUD_UNITS), "frame_ids": cloud.frame_ids.tolist(),
                                     **extra, **meta})


def save_pointcloud(writer, cloud: PointCloudSequence, name: str | None = None, **meta) -> Path:
    """Write ``cloud`` into an :class:`~egorelight_cli.artifacts.ArtifactWriter` (kind pointcloud)."""
    name = name or (writer.out.name if writer.single_file else POINTCLOUD_PAYLOAD)
    extra = {"fps": cloud.fps} if cloud.fps is not None else {}
    return writer.save_npz(name, cloud.arrays(), frame_ids=cloud.frame_ids, units=dict(POINTCLOUD_UNITS),
                           **extra, **meta)


def read_pointcloud_npz(path: str | Path) -> PointCloudSequence:
    """Read a ``pointcloud.npz`` (kind, version, shapes and finiteness checked)."""
    arrays, meta = read_kind_npz(path, POINTCLOUD_KIND, POINTCLOUD_VERSION, check_finite=True)
    require_arrays(arrays, ("points", "normals", "valid", "frame_ids"), "pointcloud payload", path)
    try:
        return PointCloudSequence(arrays["points"], arrays["normals"], arrays["valid"], arrays["frame_ids"],
                                  meta.get("fps"))
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None


def load_pointcloud(path: str | Path):
    """Load from an artifact directory, a single ``.npz`` (+ sidecar) or a lone self-describing
    ``.npz``. Returns ``(PointCloudSequence, Artifact | None)``."""
    payload, artifact = resolve_payload(path, "pointcloud", POINTCLOUD_PAYLOAD, "pointcloud")
    return read_pointcloud_npz(payload), artifact
