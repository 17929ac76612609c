"""Textured meshes and texture atlases: one scene mesh with one :class:`Material` for the renderer.

A :class:`TexturedMesh` is a mesh in its own frame with per-corner UVs into its own textures
(albedo RGB, specular, roughness). :func:`pack_scene` concatenates several meshes (already posed
into the world) into one mesh whose UVs index one atlas holding every texture side by side
(with replicated borders so bilinear lookups never bleed across tiles).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from egorelight_cli.render.shading import Material

_PAD = 2  # texels of replicated border around each atlas tile


@dataclass(frozen=True, eq=False)
class TexturedMesh:
    """A mesh with its own textures.

    Attributes:
        vertices: (V,3) float64 positions in the mesh's own frame, metres.
        faces: (F,3) int64.
        face_uvs: (F,3,2) UVs into the textures (row 0 = v = 1).
        albedo: (H,W,3) float32 linear albedo.
        specular: (H,W,1) float32 specular albedo.
        roughness: (H,W,1) float32 roughness.
        normal_map: (H,W,3) float32 tangent-space normal map, or None (flat: (0,0,1)).
        visibility_parents: None, or (V,2) int64: vertex ``v`` takes its per-vertex light
            visibility from vertices ``visibility_parents[v]`` (both visible: visible) instead of
            casting its own rays; ``(v, v)`` for the vertices that are traced.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_uvs: np.ndarray
    albedo: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    normal_map: np.ndarray | None = None
    visibility_parents: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class SceneAtlas:
    """Several textured meshes packed into one atlas (the layout is fixed for a capture).

    Attributes:
        material: the renderer :class:`Material` (atlas textures).
        face_uvs: (F,3,2) atlas UVs of all meshes' faces, concatenated in order.
        faces: (F,3) faces with vertex indices offset for the concatenated vertices.
        vertex_offsets: (M+1,) start of each mesh's vertices in the concatenation.
        face_offsets: (M+1,) start of each mesh's faces.
    """

    material: Material
    face_uvs: np.ndarray
    faces: np.ndarray
    vertex_offsets: np.ndarray
    face_offsets: np.ndarray

    def face_owner(self, face_id: np.ndarray) -> np.ndarray:
        """Index of the mesh owning each face id (-1 for background ids < 0)."""
        face_id = np.asarray(face_id)
        owner = np.searchsorted(self.face_offsets, face_id, side="right") - 1
        return np.where(face_id >= 0, owner, -1)


def _tile(texture: np.ndarray) -> np.ndarray:
    texture = np.asarray(texture, dtype=np.float32)
    if texture.ndim == 2:
        texture = texture[..., None]
    return texture


def pack_scene(meshes: list[TexturedMesh]) -> SceneAtlas:
    """Pack meshes side by side into one atlas; returns faces/UVs of the concatenated mesh."""
    heights = [m.albedo.shape[0] + 2 * _PAD for m in meshes]
    widths = [m.albedo.shape[1] + 2 * _PAD for m in meshes]
    H, W = max(heights), sum(widths)
    layers = {"albedo": np.zeros((H, W, 3), np.float32), "specular": np.zeros((H, W, 1), np.float32),
              "roughness": np.ones((H, W, 1), np.float32)}
    detailed = any(m.normal_map is not None for m in meshes)
    if detailed:
        layers["normal_map"] = np.zeros((H, W, 3), np.float32)
        layers["normal_map"][..., 2] = 1.0
    uvs, faces = [], []
    vertex_offsets, face_offsets = [0], [0]
    x0 = 0
    for mesh, w in zip(meshes, widths):
        h_t, w_t = mesh.albedo.shape[:2]
        for name, layer in layers.items():
            texture = getattr(mesh, name)
            if texture is None:  # a mesh without a normal map: keep the flat (0,0,1) default
                continue
            tile = _tile(texture)
            padded = cv2.copyMakeBorder(tile, _PAD, _PAD, _PAD, _PAD, cv2.BORDER_REPLICATE)
            if padded.ndim == 2:
                padded = padded[..., None]
            layer[:h_t + 2 * _PAD, x0:x0 + w] = padded
        # Tile texel (r, c) sits at atlas texel (r + PAD, x0 + PAD + c); UVs follow (row 0 = v 1).
        uv = np.asarray(mesh.face_uvs, dtype=np.float64)
        u = (x0 + _PAD + uv[..., 0] * w_t) / W
        v = 1.0 - (_PAD + (1.0 - uv[..., 1]) * h_t) / H
        uvs.append(np.stack([u, v], axis=-1))
        faces.append(np.asarray(mesh.faces, dtype=np.int64) + vertex_offsets[-1])
        vertex_offsets.append(vertex_offsets[-1] + len(mesh.vertices))
        face_offsets.append(face_offsets[-1] + len(mesh.faces))
        x0 += w
    material = Material(albedo=layers["albedo"], specular=layers["specular"], roughness=layers["roughness"],
                        normal_map=layers.get("normal_map"))
    return SceneAtlas(material=material, face_uvs=np.concatenate(uvs), faces=np.concatenate(faces),
                      vertex_offsets=np.asarray(vertex_offsets), face_offsets=np.asarray(face_offsets))


def grid_quad(centre, right, down, half_right: float, half_down: float, cells: int,
              uv_box: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat rectangle split into ``cells x cells`` quads (2 triangles each).

    Points are ``centre + p right + q down`` with ``p`` in [-half_right, half_right], ``q`` in
    [-half_down, half_down]; the outward normal is ``down x right`` (the side seen by a viewer
    for whom ``right`` points right and ``down`` points down). ``uv_box = (u0, v0, u1, v1)`` maps
    the rectangle's top-left (p, q minimal) to (u0, v1) and bottom-right to (u1, v0).

    Returns vertices (n*n,3), faces (2 cells^2, 3), face UVs (2 cells^2, 3, 2).
    """
    centre, right, down = (np.asarray(x, dtype=np.float64) for x in (centre, right, down))
    n = cells + 1
    s = np.linspace(0.0, 1.0, n)
    ss, tt = np.meshgrid(s, s, indexing="xy")  # ss along right, tt along down
    p = (2 * ss - 1) * half_right
    q = (2 * tt - 1) * half_down
    vertices = centre + p[..., None] * right + q[..., None] * down
    u0, v0, u1, v1 = uv_box
    uv = np.stack([u0 + ss * (u1 - u0), v1 - tt * (v1 - v0)], axis=-1).reshape(-1, 2)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # (down, right) order gives the normal down x right: a -> c (down) -> b (right).
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return vertices.reshape(-1, 3), faces, uv[faces]
