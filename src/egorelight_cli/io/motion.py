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

from pathlib import Path

import numpy as np

from egorelight_cli.artifacts import resolve_payload
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import checked_fps, read_kind_npz, require_arrays, write_npz
from egorelight_cli.structures.motion import Motion

MOTION_KIND = "egorelight/motion"
MOTION_VERSION = 1
MOTION_PAYLOAD = "motion.npz"
MOTION_UNITS = {"theta": "rad (revolute DoFs) | m (prismatic DoFs)", "fitted_keypoints": "m", "residual_m": "m"}


def motion_from_arrays(arrays: dict[str, np.ndarray], meta: dict | None = None,
                       path: str | Path | None = None) -> Motion:
    require_arrays(arrays, ("theta", "dof_names", "frame_ids"), "motion payload", path)
    fps = checked_fps(arrays["fps"] if "fps" in arrays else (meta or {}).get("fps"), "motion payload", path)
    if fps is None:
        raise EgorelightError("motion payload has no fps", path)
    try:
        return Motion(arrays["theta"], tuple(str(s) for s in arrays["dof_names"]), arrays["frame_ids"], fps,
                      arrays.get("fitted_keypoints"), arrays.get("residual_m"))
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None
    except (TypeError, ValueError) as exc:  # e.g. text where numbers belong
        raise EgorelightError(f"motion payload holds arrays of the wrong type ({exc})", path) from None


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
    self-describing ``.npz``. Returns ``(Motion, Artifact | None)``; a motion of no frame is an
    error (nothing a stage can drive, fit or learn from)."""
    payload, artifact = resolve_payload(path, "motion", MOTION_PAYLOAD, "motion")
    motion = read_motion_npz(payload)
    if motion.num_frames == 0:
        raise EgorelightError("the motion holds no frame", payload)
    return motion, artifact
