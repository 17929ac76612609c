"""Triangle OBJ files as DDC uses them (template and embedded graph; Meshlab dialect)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.io.ddc.text import _join, _Lines, _read_text, _write_text_lines


@dataclass
class ObjMesh:
    """A triangle OBJ as DDC uses it (file units; indices 0-based).

    Attributes:
        vertices: (N,3).
        colors: (N,3) vertex colours from ``v x y z r g b`` or None.
        normals: (Nn,3) ``vn`` rows or None.
        uvs: (T,2) ``vt`` rows or None.
        faces: (F,3) vertex indices.
        face_uvs_index: (F,3) ``vt`` index per corner or None.
        face_normals_index: (F,3) ``vn`` index per corner or None.
        mtllib, usemtl: the material references, if any.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    face_uvs_index: np.ndarray | None = None
    face_normals_index: np.ndarray | None = None
    mtllib: str | None = None
    usemtl: str | None = None

    def face_corner_uvs(self) -> np.ndarray:
        """(F,3,2) per-face-corner UVs (wedge UVs); zeros when the file has none."""
        if self.uvs is None or self.face_uvs_index is None:
            return np.zeros((len(self.faces), 3, 2))
        return self.uvs[self.face_uvs_index]

    def to_json(self, scale: float = 1.0) -> dict:
        """JSON-able dict (positions multiplied by ``scale``)."""
        def lst(a):
            return None if a is None else np.asarray(a).tolist()
        return {
            "vertices": lst(np.asarray(self.vertices) * scale), "faces": lst(self.faces), "colors": lst(self.colors),
            "normals": lst(self.normals), "uvs": lst(self.uvs), "face_uvs_index": lst(self.face_uvs_index),
            "face_normals_index": lst(self.face_normals_index), "mtllib": self.mtllib, "usemtl": self.usemtl,
        }

    @classmethod
    def from_json(cls, data: dict, scale: float = 1.0) -> "ObjMesh":
        def arr(key, dtype, cols):
            value = data.get(key)
            return None if value is None else np.asarray(value, dtype=dtype).reshape(-1, cols)
        return cls(vertices=arr("vertices", np.float64, 3) * scale, faces=arr("faces", np.int64, 3),
                   colors=arr("colors", np.float64, 3), normals=arr("normals", np.float64, 3),
                   uvs=arr("uvs", np.float64, 2), face_uvs_index=arr("face_uvs_index", np.int64, 3),
                   face_normals_index=arr("face_normals_index", np.int64, 3),
                   mtllib=data.get("mtllib"), usemtl=data.get("usemtl"))


def read_obj(path: str | Path, what: str = "OBJ file") -> ObjMesh:
    """Read a triangle OBJ (``v [rgb]``, ``vt``, ``vn``, ``f v[/vt][/vn]``; polygons fan-split)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, what), what)
    verts, colors, normals, uvs = [], [], [], []
    faces, fuv, fn = [], [], []
    mtllib = usemtl = None
    has_color = None
    corner_kind = None  # (has vt, has vn) of the first face corner, all must agree
    for number, line, tokens in lines.lines:
        key = tokens[0]
        if key.startswith("#"):
            continue
        if key == "v":
            if len(tokens) not in (4, 7):
                raise lines.error(f"a vertex needs 3 coordinates (and optionally r g b), found {len(tokens) - 1}", number)
            values = lines.floats(tokens[1:], number, "vertex value")
            with_color = len(values) == 6
            if has_color is None:
                has_color = with_color
            elif has_color != with_color:
                raise lines.error("some vertices have colours and others do not", number)
            verts.append(values[:3])
            if with_color:
                colors.append(values[3:])
        elif key == "vt":
            if len(tokens) < 3:
                raise lines.error("a texture coordinate needs u and v", number)
            uvs.append(lines.floats(tokens[1:3], number, "texture coordinate"))
        elif key == "vn":
            if len(tokens) != 4:
                raise lines.error("a normal needs 3 values", number)
            normals.append(lines.floats(tokens[1:], number, "normal value"))
        elif key == "f":
            if len(tokens) < 4:
                raise lines.error(f"a face needs at least 3 corners, found {len(tokens) - 1}", number)
            corners = []
            for corner in tokens[1:]:
                parts = corner.split("/")
                if len(parts) > 3 or not parts[0]:
                    raise lines.error(f"bad face corner {corner!r}", number)
                idx = []
                for part, count in zip(parts + [""] * (3 - len(parts)), (len(verts), len(uvs), len(normals))):
                    if not part:
                        idx.append(None)
                        continue
                    k = lines.int(part, number, "face index")
                    k = k - 1 if k > 0 else count + k
                    if not 0 <= k < count:
                        raise lines.error(f"face index {part!r} refers to an element not defined before it", number)
                    idx.append(k)
                kind = (idx[1] is not None, idx[2] is not None)
                if corner_kind is None:
                    corner_kind = kind
                elif kind != corner_kind:
                    raise lines.error("face corners mix forms (with and without texture/normal indices)", number)
                corners.append(idx)
            for k in range(1, len(corners) - 1):
                tri = (corners[0], corners[k], corners[k + 1])
                faces.append([c[0] for c in tri])
                fuv.append([c[1] for c in tri])
                fn.append([c[2] for c in tri])
        elif key == "mtllib":
            mtllib = line.split(None, 1)[1].strip() if len(tokens) > 1 else None
        elif key == "usemtl":
            usemtl = line.split(None, 1)[1].strip() if len(tokens) > 1 else None
        # o, g, s, l and others carry nothing DDC uses
    if not verts:
        raise lines.error("the file has no vertices")
    has_uv, has_n = corner_kind if corner_kind is not None else (False, False)
    return ObjMesh(
        vertices=np.array(verts, dtype=np.float64),
        faces=np.array(faces, dtype=np.int64).reshape(-1, 3),
        colors=np.array(colors, dtype=np.float64) if has_color else None,
        normals=np.array(normals, dtype=np.float64).reshape(-1, 3) if normals else None,
        uvs=np.array(uvs, dtype=np.float64).reshape(-1, 2) if uvs else None,
        face_uvs_index=np.array(fuv, dtype=np.int64).reshape(-1, 3) if has_uv else None,
        face_normals_index=np.array(fn, dtype=np.int64).reshape(-1, 3) if has_n else None,
        mtllib=mtllib, usemtl=usemtl)


def write_obj(mesh: ObjMesh, path: str | Path, comment: str | None = None) -> Path:
    """Write an OBJ in the Meshlab layout DDC files use.

    Per vertex ``vn`` then ``v`` when the normals are per vertex, then ``usemtl`` and the faces,
    each preceded by the ``vt`` rows it is the first to use (in index order).
    """
    path = Path(path)
    V, F = len(mesh.vertices), len(mesh.faces)
    out = [f"# {comment}" if comment else "# written by egorelight", f"# Vertices: {V}", f"# Faces: {F}"]
    if mesh.mtllib:
        out.append(f"mtllib {mesh.mtllib}")
    normals = mesh.normals
    fni = mesh.face_normals_index
    per_vertex_normals = (normals is not None and fni is not None and len(normals) == V
                          and np.array_equal(fni, mesh.faces))
    for v in range(V):
        if per_vertex_normals:
            out.append(_join(["vn", *normals[v]]))
        row = ["v", *mesh.vertices[v]]
        if mesh.colors is not None:
            row += list(mesh.colors[v])
        out.append(_join(row))
    if normals is not None and not per_vertex_normals:
        out.extend(_join(["vn", *n]) for n in normals)
    out.append(f"# {V} vertices")
    if mesh.usemtl:
        out.append(f"usemtl {mesh.usemtl}")
    uvs, fti = mesh.uvs, mesh.face_uvs_index
    use_uv = uvs is not None and fti is not None
    use_n = normals is not None and fni is not None
    next_vt = 0
    for f in range(F):
        if use_uv:
            need = int(fti[f].max())
            while next_vt <= need:
                out.append(_join(["vt", *uvs[next_vt]]))
                next_vt += 1
        corners = []
        for c in range(3):
            s = str(int(mesh.faces[f, c]) + 1)
            if use_uv and use_n:
                s += f"/{int(fti[f, c]) + 1}/{int(fni[f, c]) + 1}"
            elif use_uv:
                s += f"/{int(fti[f, c]) + 1}"
            elif use_n:
                s += f"//{int(fni[f, c]) + 1}"
            corners.append(s)
        out.append("f " + " ".join(corners))
    if uvs is not None:
        out.extend(_join(["vt", *uvs[k]]) for k in range(next_vt, len(uvs)))
    out.append(f"# {F} faces")
    return _write_text_lines(path, out)


def _uv_table(face_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner UVs (F,3,2) -> unique UV rows in first-use order and (F,3) indices."""
    flat = np.asarray(face_uvs, dtype=np.float64).reshape(-1, 2)
    if len(flat) == 0:
        return np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    unique, first, inverse = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return unique[order], rank[inverse.reshape(-1)].reshape(-1, 3)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.zeros_like(vertices)
    if len(faces):
        tri = vertices[faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        for c in range(3):
            np.add.at(n, faces[:, c], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1), 0.0)
