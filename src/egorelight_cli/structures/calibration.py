"""Calibration data: head poses, ego-camera hand-eye transforms and stream offsets (the payload
of :mod:`egorelight_cli.io.calibration`, where frame ids and the unprojection are described)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError


# ``extras["head_pose_sources"][seq]`` of a sequence tracked by the studio's cameras: its head poses
# are in the studio's world (any other source, e.g. a headset tracker, has a world of its own)
STUDIO_HEAD_POSE_SOURCE = "studio ArUco markers"


@dataclass(frozen=True)
class HeadPoses:
    """Per-frame HMD poses of one sequence.

    Attributes:
        T_world_from_hmd: (T,4,4) float64, metres.
        frame_ids: (T,) int64 master-clock frame ids.
        valid: (T,) bool.
        num_markers: (T,) int64 markers (or features) that supported each pose.
        residual_px: (T,) float64 reprojection residual, NaN where invalid.
    """

    T_world_from_hmd: np.ndarray
    frame_ids: np.ndarray
    valid: np.ndarray
    num_markers: np.ndarray
    residual_px: np.ndarray

    def __post_init__(self) -> None:
        T = len(self.frame_ids)
        if np.shape(self.T_world_from_hmd) != (T, 4, 4):
            raise EgorelightError(f"head poses have shape {np.shape(self.T_world_from_hmd)}, expected ({T},4,4)")
        for name in ("valid", "num_markers", "residual_px"):
            if np.shape(getattr(self, name)) != (T,):
                raise EgorelightError(f"head pose field {name} has shape {np.shape(getattr(self, name))}, expected ({T},)")

    def _index(self, frame_id: int) -> int | None:
        index = np.nonzero(self.frame_ids == int(frame_id))[0]
        return int(index[0]) if index.size else None

    def valid_pose(self, frame_id: int) -> np.ndarray | None:
        """T_world_from_hmd of one frame, or None for unknown or flagged frames."""
        index = self._index(frame_id)
        return None if index is None or not self.valid[index] else self.T_world_from_hmd[index]

    def valid_poses(self) -> dict[int, np.ndarray]:
        """Frame id -> T_world_from_hmd (4,4) of every frame not flagged."""
        return {int(f): T for f, T, ok in zip(self.frame_ids, self.T_world_from_hmd, self.valid) if ok}

    def pose(self, frame_id: int) -> np.ndarray:
        """T_world_from_hmd of one frame; an error for unknown or flagged frames."""
        index = self._index(frame_id)
        if index is None:
            raise EgorelightError(f"frame {frame_id} has no head pose (frames {self.frame_ids.min()}..{self.frame_ids.max()})")
        if not self.valid[index]:
            raise EgorelightError(f"frame {frame_id} was flagged by calibration (too little evidence for a head pose)")
        return self.T_world_from_hmd[index]


@dataclass(frozen=True)
class EgoCameraCalibration:
    """Hand-eye result for one ego camera."""

    role: str
    name: str
    T_cam_from_hmd: np.ndarray
    residual_px: float = float("nan")
    residual_mm: float = float("nan")


@dataclass(frozen=True)
class Calibration:
    """Everything the egocentric stages need to put ego observations into the world."""

    ego_cameras: dict[str, EgoCameraCalibration]
    stream_offsets: dict[str, int]
    head_poses: dict[str, HeadPoses] = field(default_factory=dict)
    extras: dict = field(default_factory=dict)
    source: Path | None = field(default=None, compare=False)  # the file it was read from (for errors)

    def T_world_from_cam(self, role: str, sequence: str, frame_id: int) -> np.ndarray:
        """``H @ inv(Pi)`` for an ego camera at a master-clock frame."""
        if role not in self.ego_cameras:
            raise EgorelightError(f"calibration has no ego camera {role!r} (has {', '.join(self.ego_cameras)})",
                                  self.source)
        if sequence not in self.head_poses:
            raise EgorelightError(f"calibration has no head poses for sequence {sequence!r}", self.source)
        H = self.head_poses[sequence].pose(frame_id)
        return H @ np.linalg.inv(self.ego_cameras[role].T_cam_from_hmd)

    def head_poses_in_studio_world(self, sequence: str) -> bool:
        """False when the calibration says the head poses of ``sequence`` come from something other
        than the studio's marker tracking (a headset tracker's own world frame); True otherwise
        (studio tracking, or a calibration that does not say, such as the oracle)."""
        source = self.extras.get("head_pose_sources", {}).get(sequence)
        return source is None or source == STUDIO_HEAD_POSE_SOURCE

    def ego_frame_id(self, sequence: str, frame_id: int) -> int:
        """The ego-stream frame id that shows master-clock frame ``frame_id``."""
        if sequence not in self.stream_offsets:
            raise EgorelightError(f"calibration has no stream offset for sequence {sequence!r}", self.source)
        return int(frame_id) + int(self.stream_offsets[sequence])
