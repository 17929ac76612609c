"""Triangle meshes for other tools: OBJ with per-corner UVs and vertex colours, PLY via trimesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray | None = None,
              vertex_colors: np.ndarray | None = None) -> None:
    """Write an OBJ.

    Args:
        vertices: (V,3) positions (written as given, metres in this tool).
        faces: (F,3) 0-based triangle indices.
        face_uvs: optional (F,3,2) per-corner UVs; identical corners share one ``vt``.
        vertex_colors: optional (V,3) in [0,1], written as ``v x y z r g b``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    lines = ["# written by egorelight"]
    if vertex_colors is not None:
        colors = np.asarray(vertex_colors, dtype=np.float64)
        lines += [f"v {x:.7g} {y:.7g} {z:.7g} {r:.5g} {g:.5g} {b:.5g}" for (x, y, z), (r, g, b) in zip(vertices, colors)]
    else:
        lines += [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in vertices]
    if face_uvs is not None:
        corners = np.asarray(face_uvs, dtype=np.float64).reshape(-1, 2)
        unique, corner_to_vt = np.unique(np.round(corners, 7), axis=0, return_inverse=True)
        corner_to_vt = corner_to_vt.reshape(-1, 3) + 1
        lines += [f"vt {u:.7g} {v:.7g}" for u, v in unique]
        lines += [f"f {a + 1}/{ta} {b + 1}/{tb} {c + 1}/{tc}" for (a, b, c), (ta, tb, tc) in zip(faces, corner_to_vt)]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    Path(path).write_text("\n".join(lines) + "\n")


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray | None = None,
              normals: np.ndarray | None = None, colors: np.ndarray | None = None) -> None:
    """Binary PLY of a mesh (or a point cloud when ``faces`` is None) via trimesh."""
    import trimesh

    vertices = np.asarray(vertices, dtype=np.float64)
    kwargs = {}
    if colors is not None:
        kwargs["vertex_colors"] = np.clip(np.asarray(colors) * 255, 0, 255).astype(np.uint8)
    if faces is None:
        geometry = trimesh.PointCloud(vertices, **({"colors": kwargs["vertex_colors"]} if colors is not None else {}))
    else:
        geometry = trimesh.Trimesh(vertices, np.asarray(faces), vertex_normals=normals, process=False, **kwargs)
    Path(path).write_bytes(geometry.export(file_type="ply"))


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V,3) float64, faces (F,3) int64) of a PLY/OBJ, without merging or reordering.

    A file holding only points (a point-cloud PLY) gives its points and (0,3) faces."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise EgorelightError("mesh not found", path)
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
        if len(mesh.vertices) == 0:
            points = trimesh.load(path, process=False)
            if isinstance(points, trimesh.PointCloud):
                return np.asarray(points.vertices, dtype=np.float64), np.zeros((0, 3), np.int64)
    except Exception as exc:
        raise EgorelightError(f"cannot read mesh ({exc})", path) from None
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
