"""A single camera as a JSON object: the entry layout of ``rig/studio_cameras.json`` (DESIGN.md
Sec. 5: ``name``, ``model``, ``K``, ``dist``, ``T_cam_from_world``, ``width``, ``height``), for a
virtual viewpoint that no capture holds (``relight --camera-json``, ``composite --camera-json``)."""

from __future__ import annotations

import json
from pathlib import Path

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
        return Camera.from_dict({"name": "virtual", "dist": [], **doc})
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None
