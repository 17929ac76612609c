"""The :class:`Motion` sequence: skeleton DoF values per frame (the payload of
:mod:`egorelight_cli.io.motion`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError


@dataclass(frozen=True, eq=False)
class Motion:
    """A motion sequence (arrays in :mod:`egorelight_cli.io.motion`). ``theta`` must be finite."""

    theta: np.ndarray
    dof_names: tuple[str, ...]
    frame_ids: np.ndarray
    fps: float
    fitted_keypoints: np.ndarray | None = None
    residual_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        theta = np.asarray(self.theta, dtype=np.float32)
        names = tuple(str(n) for n in self.dof_names)
        ids = np.asarray(self.frame_ids)
        if theta.ndim != 2 or theta.shape[1] != len(names):
            raise EgorelightError(f"motion theta has shape {theta.shape}, expected (T, {len(names)}) for {len(names)} DoF names")
        T = theta.shape[0]
        if not np.isfinite(theta).all():
            raise EgorelightError(f"motion theta holds {int((~np.isfinite(theta)).sum())} NaN/inf values")
        if ids.shape != (T,) or not np.issubdtype(ids.dtype, np.integer):
            raise EgorelightError(f"motion frame_ids has shape {ids.shape}, expected ({T},) integers")
        if T > 1 and np.any(np.diff(ids) <= 0):
            raise EgorelightError("motion frame_ids are not strictly increasing")
        if not (np.isfinite(self.fps) and float(self.fps) > 0):
            raise EgorelightError(f"motion fps must be positive, got {self.fps}")
        for name in ("fitted_keypoints", "residual_m"):
            value = getattr(self, name)
            if value is None:
                continue
            value = np.asarray(value, dtype=np.float32)
            if value.shape[0] != T:
                raise EgorelightError(f"motion {name} has {value.shape[0]} frames, theta has {T}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "theta", theta)
        object.__setattr__(self, "dof_names", names)
        object.__setattr__(self, "frame_ids", ids.astype(np.int64))
        object.__setattr__(self, "fps", float(self.fps))

    @property
    def num_frames(self) -> int:
        return int(self.theta.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        arrays = {"theta": self.theta, "dof_names": np.array(self.dof_names, dtype=str),
                  "frame_ids": self.frame_ids, "fps": np.array(self.fps, dtype=np.float32)}
        if self.fitted_keypoints is not None:
            arrays["fitted_keypoints"] = self.fitted_keypoints
        if self.residual_m is not None:
            arrays["residual_m"] = self.residual_m
        return arrays

    def check_dofs(self, dof_names, path: str | Path | None = None) -> "Motion":
        """Raise unless this motion's DoF names equal ``dof_names`` (a character's)."""
        dof_names = tuple(dof_names)
        if self.dof_names != dof_names:
            if len(self.dof_names) != len(dof_names):
                raise EgorelightError(f"motion has {len(self.dof_names)} DoFs but the character has {len(dof_names)}", path)
            bad = next(i for i, (a, b) in enumerate(zip(self.dof_names, dof_names)) if a != b)
            raise EgorelightError(f"motion DoF {bad} is {self.dof_names[bad]!r} but the character's is {dof_names[bad]!r}", path)
        return self
