"""The ``keypoints`` payload: 57 world keypoints per frame with confidences.

``keypoints.npz`` arrays (DESIGN.md Sec. 3):

* ``xyz`` (T,57,3) float32, world metres, +Y up. NaN marks a missing keypoint.
* ``confidence`` (T,57) float32 in [0,1]; 0 means "not observed".
* ``frame_ids`` (T,) int64, strictly increasing.
* ``names`` (57,) str, the layout of :mod:`egorelight_cli.structures.keypoints`.

The ``__meta__`` entry holds kind ``egorelight/keypoints``, version, units and (optionally)
``fps``. A keypoints artifact is a directory with ``manifest.json`` + ``keypoints.npz``, or a
single ``.npz`` with its sidecar ``<file>.npz.json``; a lone ``.npz`` whose ``__meta__`` says
``egorelight/keypoints`` is read too (e.g. written by a script).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.artifacts import resolve_payload
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import checked_fps, read_kind_npz, require_arrays, write_npz
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES, KEYPOINTS_UNITS, Keypoints

__all__ = ["KEYPOINTS_KIND", "KEYPOINTS_VERSION", "KEYPOINTS_PAYLOAD", "KEYPOINTS_UNITS", "Keypoints",
           "keypoints_from_arrays", "write_keypoints_npz", "save_keypoints", "read_keypoints_npz", "load_keypoints"]

KEYPOINTS_KIND = "egorelight/keypoints"
KEYPOINTS_VERSION = 1
KEYPOINTS_PAYLOAD = "keypoints.npz"


def keypoints_from_arrays(arrays: dict[str, np.ndarray], meta: dict | None = None,
                          path: str | Path | None = None) -> Keypoints:
    """Build :class:`Keypoints` from payload arrays (errors name ``path``)."""
    require_arrays(arrays, ("xyz", "confidence", "frame_ids"), "keypoints payload", path)
    names = tuple(str(s) for s in arrays["names"]) if "names" in arrays else KEYPOINT_NAMES
    fps = (meta or {}).get("fps")
    fps = checked_fps(arrays.get("fps") if fps is None else fps, "keypoints payload", path)
    try:
        return Keypoints(arrays["xyz"], arrays["confidence"], arrays["frame_ids"], names, fps)
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None
    except (TypeError, ValueError) as exc:  # e.g. text where numbers belong
        raise EgorelightError(f"keypoints payload holds arrays of the wrong type ({exc})", path) from None


def write_keypoints_npz(path: str | Path, keypoints: Keypoints, **meta) -> None:
    """Write a self-describing ``keypoints.npz`` (outside an artifact writer)."""
    write_npz(path, keypoints.arrays(), {"kind": KEYPOINTS_KIND, "version": KEYPOINTS_VERSION,
                                         "frame_ids": keypoints.frame_ids.tolist(), **keypoints.meta(), **meta})


def save_keypoints(writer, keypoints: Keypoints, name: str | None = None, **meta) -> Path:
    """Write ``keypoints`` into an :class:`~egorelight_cli.artifacts.ArtifactWriter` (kind keypoints)."""
    name = name or (writer.out.name if writer.single_file else KEYPOINTS_PAYLOAD)
    extra = keypoints.meta()
    arrays = keypoints.arrays()
    return writer.save_npz(name, arrays, frame_ids=keypoints.frame_ids, units=extra.pop("units"),
                           rows=sorted(k for k in arrays if k != "names"), **extra, **meta)


def read_keypoints_npz(path: str | Path) -> Keypoints:
    """Read a keypoints ``.npz`` (kind and version checked; NaN xyz allowed = missing)."""
    arrays, meta = read_kind_npz(path, KEYPOINTS_KIND, KEYPOINTS_VERSION)
    return keypoints_from_arrays(arrays, meta, path)


def load_keypoints(path: str | Path):
    """Load keypoints from an artifact directory, a single ``.npz`` (+ sidecar) or a lone
    self-describing ``.npz``. Returns ``(Keypoints, Artifact | None)``."""
    payload, artifact = resolve_payload(path, "keypoints", KEYPOINTS_PAYLOAD, "keypoints")
    return read_keypoints_npz(payload), artifact
