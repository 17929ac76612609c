"""A single camera as a JSON object: the entry layout of ``rig/studio_cameras.json`` (DESIGN.md
Sec. 5: ``name``, ``model``, ``K``, ``dist``, ``T_cam_from_world``, ``width``, ``height``), for a
virtual viewpoint that no capture holds (``relight --camera-json``, ``composite --camera-json``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera


def read_camera_json(path: str | Path) -> Camera:
    """The camera of ``path``; ``name`` defaults to ``"virtual"`` and ``dist`` to none. A file
    that cannot be read, is not one object or holds a bad camera is a one-line error naming it."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EgorelightError(f"cannot read the camera JSON ({exc})", path) from None
    if not isinstance(doc, dict):
        raise EgorelightError("camera JSON must be one object (name, model, K, dist, T_cam_from_world, width, "
                              "height)", path)
    try:
        camera = Camera.from_dict({"name": "virtual", "dist": [], **doc})
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None
    except (TypeError, ValueError) as exc:  # e.g. a width that is not a number
        raise EgorelightError(f"camera JSON holds a bad value ({exc})", path) from None
    check_virtual_camera(camera, path)
    return camera


#: the largest image side a virtual camera may ask for (pixels)
MAX_IMAGE_SIDE = 16384


def check_virtual_camera(camera: Camera, path: str | Path) -> None:
    """A one-line error naming ``path`` unless ``camera`` can render: a size in 1..MAX_IMAGE_SIDE,
    positive focal lengths and a rigid ``T_cam_from_world`` (rotation orthonormal to 1e-3, det +1)."""
    if not (0 < camera.width <= MAX_IMAGE_SIDE and 0 < camera.height <= MAX_IMAGE_SIDE):
        raise EgorelightError(f"camera size {camera.width}x{camera.height} is outside 1..{MAX_IMAGE_SIDE} pixels", path)
    if not (camera.K[0, 0] > 0 and camera.K[1, 1] > 0):
        raise EgorelightError(f"camera focal lengths must be positive, got fx {camera.K[0, 0]}, fy {camera.K[1, 1]}",
                              path)
    R = np.asarray(camera.T_cam_from_world, np.float64)[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:  # 3 written decimals pass
        raise EgorelightError("T_cam_from_world is not a rigid transform (its rotation is not orthonormal with "
                              "det +1)", path)
