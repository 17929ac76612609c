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

from pathlib import Path

from egorelight_cli.artifacts import resolve_payload
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_kind_npz, require_arrays, write_npz
from egorelight_cli.structures.pointcloud import PointCloudSequence

POINTCLOUD_KIND = "egorelight/pointcloud"
POINTCLOUD_VERSION = 1
POINTCLOUD_PAYLOAD = "pointcloud.npz"
POINTCLOUD_UNITS = {"points": "m", "normals": "unit"}


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
    arrays = cloud.arrays()
    return writer.save_npz(name, arrays, frame_ids=cloud.frame_ids, units=dict(POINTCLOUD_UNITS), rows=sorted(arrays),
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
