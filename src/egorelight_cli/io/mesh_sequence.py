"""The ``meshes`` artifact payload: a tracked mesh sequence and the controls that made it.

``meshes.npz`` (same layout as the simulator's ``groundtruth/<seq>/meshes.npz``):

* ``vertices`` (T,V,3) float32 posed vertices, world metres;
* ``faces`` (F,3) int32 (the character's template triangles);
* ``theta`` (T,D) float32 skeleton DoFs;
* ``eg_rotation`` (T,N,3) float32 embedded-graph Euler angles alpha (rx, ry, rz), radians;
* ``eg_translation`` (T,N,3) float32 embedded-graph translations beta, canonical metres;
* ``offsets`` (T,V,3) float32 per-vertex canonical offsets o, metres (zeros when absent, as in
  the simulator's ground truth);
* ``frame_ids`` (T,) int64 master-clock (studio) frame ids, strictly increasing;
* optional ``ego_frame_ids`` (T,) int64.

A meshes artifact is a directory with ``manifest.json`` + ``meshes.npz`` (+ previews, and
``export/`` PLY/OBJ files when asked for), or a single ``.npz`` with its sidecar; a lone
self-describing ``meshes.npz`` is read too.

:class:`SurfaceSequence` is the topology-free part alone (``vertices`` (T,V',3), ``faces``
(F',3), ``frame_ids``, optional ``ego_frame_ids``), read by :func:`read_surface_npz` from any
npz that holds those arrays: the simulator's ground truth (its own topology, no control
parameters) or a real capture's reconstructions converted to a sequence.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.artifacts import resolve_payload
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_kind_npz, read_npz, require_arrays, write_npz
from egorelight_cli.structures.mesh_sequence import MeshSequence, SurfaceSequence

MESHES_KIND = "egorelight/meshes"
MESHES_VERSION = 1
MESHES_PAYLOAD = "meshes.npz"
MESHES_UNITS = {"vertices": "m", "eg_rotation": "rad", "eg_translation": "m", "offsets": "m",
                "theta": "rad (revolute DoFs) | m (prismatic DoFs)"}


def write_meshes_npz(path: str | Path, meshes: MeshSequence, **meta) -> None:
    """Write a self-describing ``meshes.npz`` (outside an artifact writer)."""
    extra = {"fps": meshes.fps} if meshes.fps is not None else {}
    write_npz(path, meshes.arrays(), {"kind": MESHES_KIND, "version": MESHES_VERSION, "units": dict(MESHES_UNITS),
                                      "frame_ids": meshes.frame_ids.tolist(), **extra, **meta})


def save_meshes(writer, meshes: MeshSequence, name: str | None = None, **meta) -> Path:
    """Write ``meshes`` into an :class:`~egorelight_cli.artifacts.ArtifactWriter` (kind meshes)."""
    name = name or (writer.out.name if writer.single_file else MESHES_PAYLOAD)
    extra = {"fps": meshes.fps} if meshes.fps is not None else {}
    return writer.save_npz(name, meshes.arrays(), frame_ids=meshes.frame_ids, units=dict(MESHES_UNITS), **extra, **meta)


def read_meshes_npz(path: str | Path) -> MeshSequence:
    """Read a ``meshes.npz`` (kind and version checked; missing ``offsets`` read as zeros)."""
    arrays, meta = read_kind_npz(path, MESHES_KIND, MESHES_VERSION)
    require_arrays(arrays, ("vertices", "faces", "theta", "eg_rotation", "eg_translation", "frame_ids"),
                   "meshes payload", path)
    offsets = arrays.get("offsets")
    if offsets is None:
        offsets = np.zeros_like(arrays["vertices"], dtype=np.float32)
    try:
        return MeshSequence(arrays["vertices"], arrays["faces"], arrays["theta"], arrays["eg_rotation"],
                            arrays["eg_translation"], offsets, arrays["frame_ids"], meta.get("fps"),
                            arrays.get("ego_frame_ids"))
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None


def read_surface_npz(path: str | Path) -> SurfaceSequence:
    """Read ``vertices``, ``faces``, ``frame_ids`` (and ``ego_frame_ids`` when present) of any
    self-describing npz, whatever its topology and whatever else it holds (e.g. the simulator's
    ``groundtruth/<seq>/meshes.npz``); other arrays are ignored, so the kind is not checked."""
    arrays, _ = read_npz(path, check_finite=False)
    require_arrays(arrays, ("vertices", "faces", "frame_ids"), "surface sequence", path)
    try:
        return SurfaceSequence(arrays["vertices"], arrays["faces"], arrays["frame_ids"], arrays.get("ego_frame_ids"))
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None


def load_meshes(path: str | Path):
    """Load from an artifact directory, a single ``.npz`` (+ sidecar) or a lone self-describing
    ``.npz``. Returns ``(MeshSequence, Artifact | None)``."""
    payload, artifact = resolve_payload(path, "meshes", MESHES_PAYLOAD, "meshes")
    return read_meshes_npz(payload), artifact


def export_sequence(folder: str | Path, meshes: MeshSequence, fmt: str = "ply", face_uvs: np.ndarray | None = None) -> list[Path]:
    """Write one mesh file per frame, ``<folder>/<frame id:06d>.<fmt>`` (``ply`` or ``obj``; OBJ
    carries the character's face-corner UVs when given)."""
    from egorelight_cli.io.meshes import write_obj, write_ply

    if fmt not in ("ply", "obj"):
        raise EgorelightError(f"mesh export format must be ply or obj, got {fmt!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for fid, v in zip(meshes.frame_ids, meshes.vertices):
        path = folder / f"{int(fid):06d}.{fmt}"
        if fmt == "ply":
            write_ply(path, v, meshes.faces)
        else:
            write_obj(path, v, meshes.faces, face_uvs)
        paths.append(path)
    return paths
