"""Posing the scene of a frame: the clothed subject, the HMD on the head, the calibration board.

The renderer sees one mesh per frame: the parts are concatenated in a fixed order (body, then
the HMD when worn, then the board when present) with one texture atlas (:func:`pack_scene`), so
a rendered ``face_id`` tells which part a pixel shows (:meth:`SceneLayout.part_of_faces`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from egorelight_cli.geometry.cameras import transform_points
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.structures.character import Character
from egorelight_cli.synth.appearance import Appearance
from egorelight_cli.synth.hmd import Hmd
from egorelight_cli.synth.subject import Subject
from egorelight_cli.synth.textures import SceneAtlas, TexturedMesh, pack_scene

BODY, HMD, BOARD = "body", "hmd", "board"


def subject_mesh(subject: Subject, appearance: Appearance) -> TexturedMesh:
    """The subject's outer surface (rest pose) with its textures and detail normal map."""
    return TexturedMesh(vertices=subject.rest_vertices(), faces=subject.faces, face_uvs=subject.face_uvs,
                        albedo=appearance.albedo, specular=appearance.specular, roughness=appearance.roughness,
                        normal_map=appearance.normal_map, visibility_parents=subject.visibility_parents)


def joint_transforms(character: Character, theta: np.ndarray) -> np.ndarray:
    """(T,J,4,4) float64 FK of a motion."""
    return forward_kinematics(torch.as_tensor(np.asarray(theta, dtype=np.float64)), character.skeleton).numpy()


@dataclass(frozen=True, eq=False)
class SceneLayout:
    """The parts of a sequence's scene and their shared atlas."""

    parts: tuple[str, ...]
    atlas: SceneAtlas
    meshes: tuple[TexturedMesh, ...]

    def vertices(self, part_vertices: dict[str, np.ndarray]) -> np.ndarray:
        """Concatenate per-part world vertices (each (V_p,3)) in layout order."""
        return np.concatenate([np.asarray(part_vertices[p], dtype=np.float64) for p in self.parts])

    def part_of_faces(self, face_id: np.ndarray) -> np.ndarray:
        """Per-pixel part index (into ``parts``) of a face-id image; -1 for background."""
        return self.atlas.face_owner(face_id)

    def subject_mask(self, face_id: np.ndarray) -> np.ndarray:
        """Pixels showing the subject (body or worn HMD), not the board or background."""
        owner = self.part_of_faces(face_id)
        keep = [i for i, p in enumerate(self.parts) if p in (BODY, HMD)]
        return np.isin(owner, keep)

    def part_mask(self, face_id: np.ndarray, part: str) -> np.ndarray:
        if part not in self.parts:
            return np.zeros(np.shape(face_id), dtype=bool)
        return self.part_of_faces(face_id) == self.parts.index(part)

    def subject_faces(self) -> np.ndarray:
        """(F_s,3) faces of the body and HMD in the concatenated vertex numbering."""
        off = self.atlas.face_offsets
        keep = [self.atlas.faces[off[i]:off[i + 1]] for i, p in enumerate(self.parts) if p in (BODY, HMD)]
        return np.concatenate(keep)

    @cached_property
    def visibility_parents(self) -> np.ndarray:
        """(V,2) visibility parents of the concatenated vertices (see :class:`TexturedMesh`)."""
        off = self.atlas.vertex_offsets
        out = []
        for i, mesh in enumerate(self.meshes):
            own = np.arange(off[i], off[i + 1])
            parents = mesh.visibility_parents
            out.append(np.stack([own, own], 1) if parents is None else np.asarray(parents, np.int64) + off[i])
        return np.concatenate(out)

    def subject_vertex_count(self) -> int:
        off = self.atlas.vertex_offsets
        return int(sum(off[i + 1] - off[i] for i, p in enumerate(self.parts) if p in (BODY, HMD)))


def scene_layout(body: TexturedMesh, hmd: Hmd | None, board: TexturedMesh | None) -> SceneLayout:
    parts, meshes = [BODY], [body]
    if hmd is not None:
        parts.append(HMD)
        meshes.append(hmd.mesh)
    if board is not None:
        parts.append(BOARD)
        meshes.append(board)
    return SceneLayout(parts=tuple(parts), atlas=pack_scene(meshes), meshes=tuple(meshes))


def place(mesh: TexturedMesh, T_world_from_local: np.ndarray) -> np.ndarray:
    """World vertices of a rigid part."""
    return transform_points(T_world_from_local, mesh.vertices)
