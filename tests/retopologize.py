"""A simulated capture whose true surface has another topology than the character's, for the
tests of topology-free metrics (``import retopologize``, as ``geometry_synthetic``)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import trimesh

from egorelight_cli.artifacts import sha256_file
from egorelight_cli.io.mesh_sequence import read_surface_npz
from egorelight_cli.io.npz import write_npz


def subdivided_truth_capture(capture: Path, out: Path) -> Path:
    """A copy of ``capture`` at ``out`` with every ``groundtruth/<seq>/meshes.npz``
    midpoint-subdivided (the same surface, 4x the faces) and cut down to ``vertices``, ``faces``,
    ``frame_ids``, ``ego_frame_ids`` (no control parameters), its manifest digest updated. Every
    other file is a symlink into ``capture``: treat both as read-only."""
    shutil.copytree(capture, out, copy_function=os.symlink)
    manifest_path = out / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    entries = {entry["path"]: entry for entry in manifest["outputs"]}
    for path in sorted(out.glob("groundtruth/*/meshes.npz")):
        truth = read_surface_npz(path)
        frames = [trimesh.remesh.subdivide(v, truth.faces) for v in truth.vertices]
        arrays = {"vertices": np.stack([v for v, _ in frames]).astype(np.float32), "faces": frames[0][1],
                  "frame_ids": truth.frame_ids}
        if truth.ego_frame_ids is not None:
            arrays["ego_frame_ids"] = truth.ego_frame_ids
        path.unlink()
        write_npz(path, arrays, {"kind": "egorelight/meshes", "version": 1, "units": {"vertices": "m"},
                                 "frame_ids": truth.frame_ids.tolist(), "source": "subdivided ground truth (test)"})
        entry = entries[path.relative_to(out).as_posix()]
        entry["digest"] = sha256_file(path)
        entry.pop("arrays", None)
    manifest_path.unlink()
    manifest_path.write_text(json.dumps(manifest, indent=1))
    return out
