"""The ``motion`` payload: skeleton DoF values per frame.

``motion.npz`` arrays (DESIGN.md Sec. 3):

* ``theta`` (T,D) float32: DoF values, radians for rotations, metres for translations.
* ``dof_names`` (D,) str: the character's DoF names, in skeleton order.
* ``frame_ids`` (T,) int64, strictly increasing.
* ``fps`` () float32.
* optional ``fitted_keypoints`` (T,57,3) float32 world metres (FK of theta) and ``residual_m``
  (T,57) float32 distance to the keypoints it was fitted to (NaN where there was none).

A motion artifact is a directory with ``manifest.json`` + ``motion.npz``, or a single ``.npz``
with its sidecar; a lone ``.npz`` whose ``__meta__`` says ``egorelight/motion`` is read too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_kind_npz, require_arrays, resolve_payload, write_npz

MOTION_KIND = "egorelight/motion"
MOTION_VERSION = 1
MOTION_PAYLOAD = "motion.npz"
MOTION_UNITS = {"theta": "rad (revolute DoFs) | m (prismatic DoFs)", "fitted_keypoints": "m", "residual_m": "m"}


@dataclass(frozen=True, eq=False)
class Motion:
    """A motion sequence (see the module docstring). ``theta`` must be finite."""

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


def motion_from_arrays(arrays: dict[str, np.ndarray], meta: dict | None = None,
                       path: str | Path | None = None) -> Motion:
    require_arrays(arrays, ("theta", "dof_names", "frame_ids"), "motion payload", path)
    fps = float(arrays["fps"]) if "fps" in arrays else (meta or {}).get("fps")
    if fps is None:
        raise EgorelightError("motion payload has no fps", path)
    try:
        return Motion(arrays["theta"], tuple(str(s) for s in arrays["dof_names"]), arrays["frame_ids"], fps,
                      arrays.get("fitted_keypoints"), arrays.get("residual_m"))
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None


def write_motion_npz(path: str | Path, motion: Motion, **meta) -> None:
    """Write a self-describing ``motion.npz`` (outside an artifact writer)."""
    write_npz(path, motion.arrays(), {"kind": MOTION_KIND, "version": MOTION_VERSION, "units": MOTION_UNITS,
                                      "frame_ids": motion.frame_ids.tolist(), "fps": motion.fps, **meta})


def save_motion(writer, motion: Motion, name: str | None = None, **meta) -> Path:
    """Write ``motion`` into an :class:`~egorelight_cli.artifacts.ArtifactWriter` (kind motion)."""
    name = name or (writer.out.name if writer.single_file else MOTION_PAYLOAD)
    return writer.save_npz(name, motion.arrays(), frame_ids=motion.frame_ids, units=dict(MOTION_UNITS),
                           fps=motion.fps, **meta)


def read_motion_npz(path: str | Path) -> Motion:
    """Read a motion ``.npz`` (kind and version checked; residuals may hold NaN, theta may not)."""
    arrays, meta = read_kind_npz(path, MOTION_KIND, MOTION_VERSION)
    return motion_from_arrays(arrays, meta, path)


def load_motion(path: str | Path):
    """Load a motion from an artifact directory, a single ``.npz`` (+ sidecar) or a lone
    self-describing ``.npz``. Returns ``(Motion, Artifact | None)``."""
    payload, artifact = resolve_payload(path, "motion", MOTION_PAYLOAD, "motion")
    return read_motion_npz(payload), artifact
