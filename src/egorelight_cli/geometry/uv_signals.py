"""Per-vertex signals -> UV maps, and the AnimationNet's motion signal ``Theta``.

The template and its embedded graph share one UV space (the character's face-corner UVs), so
vertex-level inputs become images a convolutional network can read (paper Sec.
"Depth-conditioned Animatable Avatar"):

* :class:`UVLayout` rasterises the character's UV triangles once
  (:func:`~egorelight_cli.render.raster.rasterize_uv`); a per-vertex signal (...,V,C) becomes a
  (...,C,H,W) map by barycentric interpolation of the three vertices of the face each texel
  samples (one sparse (H*W, V) matrix product); empty texels are 0. It also holds the UV
  coordinate of every vertex (its first face corner) and of every graph node (its vertex), where
  the network's output features are sampled.
* :func:`motion_signal` is ``Theta``: positions and normals of the skinned template at the
  current and the previous frame, both expressed in the current frame's root joint frame (the
  global rigid motion removed, the relative motion between the frames kept).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.render.raster import rasterize_uv, surface_to_texels
from egorelight_cli.structures.character import Character

#: Root DoFs: 3 translations + 3 rotations (DESIGN Sec. 4).
ROOT_DOFS = 6

_LAYOUTS: "weakref.WeakKeyDictionary[Character, dict]" = weakref.WeakKeyDictionary()


@dataclass(frozen=True, eq=False)
class UVLayout:
    """UV rasterisation of one character at one resolution.

    Attributes:
        resolution: H = W texels.
        scatter: (H*W, V) sparse float32 COO matrix: row = texel (row-major), columns = the three
            vertices of the texel's face with their barycentric weights.
        coverage: (H,W) bool texels that sample a face.
        vertex_uv: (V,2) float32 UV of each vertex (its first face corner).
        node_uv: (N,2) float32 UV of each graph node (its vertex's UV).
    """

    resolution: int
    scatter: torch.Tensor
    coverage: np.ndarray
    vertex_uv: np.ndarray
    node_uv: np.ndarray

    @classmethod
    def build(cls, character: Character, resolution: int) -> "UVLayout":
        """The layout of ``character`` at ``resolution`` (cached per character object)."""
        per_character = _LAYOUTS.setdefault(character, {})
        if int(resolution) not in per_character:
            per_character[int(resolution)] = cls._build(character, int(resolution))
        return per_character[int(resolution)]

    @classmethod
    def _build(cls, character: Character, resolution: int) -> "UVLayout":
        faces = np.asarray(character.faces, np.int64)
        face_uvs = np.asarray(character.face_uvs, np.float64)
        raster = rasterize_uv(face_uvs, resolution)
        H, W = raster.resolution
        texel = np.flatnonzero(raster.coverage.reshape(-1))
        fid = raster.face_id.reshape(-1)[texel]
        bary = raster.barycentrics.reshape(-1, 3)[texel]
        rows = np.repeat(texel, 3)
        cols = faces[fid].reshape(-1)
        scatter = torch.sparse_coo_tensor(torch.as_tensor(np.stack([rows, cols])),
                                          torch.as_tensor(bary.reshape(-1), dtype=torch.float32),
                                          (H * W, character.num_vertices), check_invariants=True).coalesce()
        vertex_uv = vertex_corner_uvs(faces, face_uvs, character.num_vertices)
        return cls(int(resolution), scatter, raster.coverage, vertex_uv.astype(np.float32),
                   vertex_uv[character.graph.node_vertex].astype(np.float32))

    def to_uv(self, values) -> torch.Tensor:
        """Per-vertex values (...,V,C) (numpy or tensor) -> UV maps (...,C,H,W) float32."""
        values = torch.as_tensor(np.asarray(values) if not torch.is_tensor(values) else values, dtype=torch.float32)
        V, C = values.shape[-2:]
        if V != self.scatter.shape[1]:
            raise EgorelightError(f"UV layout is for {self.scatter.shape[1]} vertices, got a signal of {V}")
        lead = values.shape[:-2]
        X = values.reshape(-1, V, C).permute(1, 0, 2).reshape(V, -1)
        Y = torch.sparse.mm(self.scatter, X)  # (H*W, B*C)
        R = self.resolution
        return Y.reshape(R, R, -1, C).permute(2, 3, 0, 1).reshape(lead + (C, R, R))


def vertex_corner_uvs(faces: np.ndarray, face_uvs: np.ndarray, num_vertices: int) -> np.ndarray:
    """(V,2) the UV of each vertex's first face corner (seam vertices have several; one is taken).

    Computed with :func:`~egorelight_cli.render.raster.surface_to_texels` on the corner's
    one-hot barycentrics (so it follows the UV-raster convention exactly); vertices in no face get
    UV (0, 0).
    """
    corners = np.asarray(faces, np.int64).reshape(-1)
    vertex, first = np.unique(corners, return_index=True)
    face_id, corner = np.divmod(first, 3)
    bary = np.eye(3)[corner]
    res = 1024
    xy = surface_to_texels(face_id, bary, face_uvs, res)  # texel coords, centres at integers
    uv = np.zeros((num_vertices, 2))
    uv[vertex, 0] = (xy[:, 0] + 0.5) / res
    uv[vertex, 1] = 1.0 - (xy[:, 1] + 0.5) / res
    return uv


def root_joint(character: Character) -> int:
    """Index of the deepest joint driven by the root DoFs (its frame is the body's global pose)."""
    driven = np.nonzero(np.abs(character.skeleton.dof_joint_weights[:ROOT_DOFS]).sum(0) > 0)[0]
    if driven.size == 0:
        raise EgorelightError("character skeleton has no root DoFs")
    return int(driven.max())


def root_transforms(character: Character, theta: np.ndarray) -> np.ndarray:
    """(T,4,4) float64 ``T_world_from_root`` for theta (T,D)."""
    with torch.no_grad():
        fk = forward_kinematics(torch.as_tensor(np.asarray(theta, np.float64)), character.skeleton)
    return fk[..., root_joint(character), :, :].numpy()


def motion_signal(character: Character, skinned_vertices: np.ndarray, root_T: np.ndarray,
                  previous: np.ndarray) -> np.ndarray:
    """The motion signal ``Theta`` per vertex.

    Args:
        character: supplies the faces (normals).
        skinned_vertices: (T,V,3) skinned template per frame, world metres.
        root_T: (T,4,4) ``T_world_from_root`` per frame.
        previous: (T,) int index of each frame's previous frame in the same arrays (itself for
            the first frame).
    Returns:
        (T,V,12) float32: [position_t, normal_t, position_{t-1}, normal_{t-1}] in the root frame
        of frame t (metres, unit normals).
    """
    vertices = np.asarray(skinned_vertices, np.float64)
    R = np.asarray(root_T, np.float64)[:, :3, :3]
    c = np.asarray(root_T, np.float64)[:, :3, 3]
    out = []
    for source in (np.arange(len(vertices)), np.asarray(previous, np.int64)):
        local = np.einsum("tji,tvj->tvi", R, vertices[source] - c[:, None, :])
        normals = vertex_normals(torch.as_tensor(local), character.faces).numpy()
        out += [local, normals]
    return np.concatenate(out, axis=-1).astype(np.float32)


def canonical_signal(character: Character) -> np.ndarray:
    """(V,6) float32 rest positions (metres) and unit rest normals: the template's own UV maps."""
    rest = np.asarray(character.vertices, np.float64)
    normals = vertex_normals(torch.as_tensor(rest), character.faces).numpy()
    return np.concatenate([rest, normals], axis=-1).astype(np.float32)
