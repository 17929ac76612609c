"""The person-specific character: template mesh, skeleton, skinning, embedded graph, labels.

This is the paper's DDC character (Sec. "Mesh-based Geometry Model"). A posed mesh is
``V = W(E(V_bar, alpha, beta, o), K(theta, B), W)``: embedded deformation ``E`` of the rest
template, then skinning ``W`` with the skeleton's bone transforms ``K``.

All positions are metres in the character's rest (rigging) pose ``rest_theta``; the skinning
transform of bone b is ``G_b(theta) @ inv(G_b(rest_theta))`` where ``G_b`` is the global transform
of the bone's joint. It is stored as one ``character.npz`` (see :meth:`Character.to_arrays`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES
from egorelight_cli.structures.skeleton import Skeleton


@dataclass(frozen=True, eq=False)
class EmbeddedGraph:
    """A coarse deformation graph over the template (DDC's embedded graph).

    Node k sits on template vertex ``node_vertex[k]``. Vertex v is influenced by up to K nodes:
    ``vertex_node_index`` (V,K) int64 with -1 padding and ``vertex_node_weight`` (V,K) float64
    (rows sum to 1, 0 at padding).

    Attributes:
        node_vertex: (N,) int64 template vertex index of each node.
        node_radius: (N,) float64 influence radius in BFS hops on the template.
        edges: (E,2) int64 undirected node pairs (i < j).
        vertex_node_index: (V,K) int64.
        vertex_node_weight: (V,K) float64.
        faces: (Fg,3) int64 faces of the graph mesh if it came from one (for export), may be empty.
    """

    node_vertex: np.ndarray
    node_radius: np.ndarray
    edges: np.ndarray
    vertex_node_index: np.ndarray
    vertex_node_weight: np.ndarray
    faces: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        object.__setattr__(self, "node_vertex", np.asarray(self.node_vertex, dtype=np.int64))
        object.__setattr__(self, "node_radius", np.asarray(self.node_radius, dtype=np.float64))
        object.__setattr__(self, "edges", np.asarray(self.edges, dtype=np.int64).reshape(-1, 2))
        object.__setattr__(self, "vertex_node_index", np.asarray(self.vertex_node_index, dtype=np.int64))
        object.__setattr__(self, "vertex_node_weight", np.asarray(self.vertex_node_weight, dtype=np.float64))
        faces = np.zeros((0, 3), np.int64) if self.faces is None else np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        object.__setattr__(self, "faces", faces)
        if self.vertex_node_index.shape != self.vertex_node_weight.shape:
            raise EgorelightError("embedded graph vertex_node_index and vertex_node_weight shapes differ")

    @property
    def num_nodes(self) -> int:
        return int(self.node_vertex.shape[0])

    def to_arrays(self, prefix: str = "graph_") -> dict[str, np.ndarray]:
        return {
            f"{prefix}node_vertex": self.node_vertex,
            f"{prefix}node_radius": self.node_radius,
            f"{prefix}edges": self.edges,
            f"{prefix}vertex_node_index": self.vertex_node_index,
            f"{prefix}vertex_node_weight": self.vertex_node_weight,
            f"{prefix}faces": self.faces,
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], prefix: str = "graph_") -> "EmbeddedGraph":
        return cls(**{k: arrays[f"{prefix}{k}"] for k in
                      ("node_vertex", "node_radius", "edges", "vertex_node_index", "vertex_node_weight", "faces")})


@dataclass(frozen=True, eq=False)
class Character:
    """A rigged, skinned template with an embedded graph.

    Attributes:
        name: a short identifier.
        skeleton: the kinematic tree (see :class:`Skeleton`).
        rest_theta: (D,) DoF values of the rigging pose the template was modelled in.
        vertices: (V,3) float64 rest template vertices, metres.
        faces: (F,3) int64 triangles.
        face_uvs: (F,3,2) float64 per-corner UVs in [0,1], v up (OBJ convention).
        skin_bone_names: (B,) bone names.
        skin_bone_joints: (B,) int64 skeleton joint index whose global transform moves the bone.
        skin_weights: (V,B) float64 skinning weights, rows sum to 1.
        keypoint_names: (K,) names, normally :data:`KEYPOINT_NAMES` (57).
        keypoint_joints: (K,) int64 joint index each keypoint is attached to.
        keypoint_offsets: (K,3) float64 offset in that joint's local frame, metres.
        graph: the embedded deformation graph.
        segmentation: (V,) int64 per-vertex part label.
        segmentation_names: label -> name (e.g. 13 -> "face").
        hand_segmentation: (V,) int64, 0 body, 1 left hand, 2 right hand.
        vertex_colors: (V,3) float64 in [0,1] or None.
        extras: free-form JSON-able metadata (e.g. DDC markers and file headers for round trips).
    """

    name: str
    skeleton: Skeleton
    rest_theta: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    face_uvs: np.ndarray
    skin_bone_names: tuple[str, ...]
    skin_bone_joints: np.ndarray
    skin_weights: np.ndarray
    keypoint_names: tuple[str, ...]
    keypoint_joints: np.ndarray
    keypoint_offsets: np.ndarray
    graph: EmbeddedGraph
    segmentation: np.ndarray
    segmentation_names: dict[int, str]
    hand_segmentation: np.ndarray
    vertex_colors: np.ndarray | None = None
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        cast = {
            "rest_theta": np.float64, "vertices": np.float64, "faces": np.int64, "face_uvs": np.float64,
            "skin_bone_joints": np.int64, "skin_weights": np.float64, "keypoint_joints": np.int64,
            "keypoint_offsets": np.float64, "segmentation": np.int64, "hand_segmentation": np.int64,
        }
        for name, dtype in cast.items():
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=dtype))
        if self.vertex_colors is not None:
            object.__setattr__(self, "vertex_colors", np.asarray(self.vertex_colors, dtype=np.float64))
        V, F = self.vertices.shape[0], self.faces.shape[0]
        B, K, D = len(self.skin_bone_names), len(self.keypoint_names), self.skeleton.num_dofs
        expect = {
            "rest_theta": (D,), "vertices": (V, 3), "faces": (F, 3), "face_uvs": (F, 3, 2),
            "skin_bone_joints": (B,), "skin_weights": (V, B), "keypoint_joints": (K,),
            "keypoint_offsets": (K, 3), "segmentation": (V,), "hand_segmentation": (V,),
        }
        for name, shape in expect.items():
            if getattr(self, name).shape != shape:
                raise EgorelightError(f"character field {name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.vertex_colors is not None and self.vertex_colors.shape != (V, 3):
            raise EgorelightError(f"character vertex_colors has shape {self.vertex_colors.shape}, expected {(V, 3)}")
        if self.graph.vertex_node_index.shape[0] != V:
            raise EgorelightError("character embedded graph does not cover every template vertex")
        if F and (self.faces.min() < 0 or self.faces.max() >= V):
            raise EgorelightError("character faces index vertices out of range")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def fingerprint(self) -> str:
        """A short hex digest of what poses the surface: the rest template and its faces, the
        skeleton (joints, offsets, DoFs) and the skinning weights, floats rounded to 1e-5 (10 um
        for lengths), so the same character read from an npz, a DDC file or a float64 copy keeps
        its fingerprint, while a fitted subject (another shape or skeleton) gets another. Stages
        record it beside what they make with a character and compare it where that is used with
        one (``check_same_character``)."""
        digest = hashlib.sha256()
        arrays = {"vertices": self.vertices, "faces": self.faces, "skin_weights": self.skin_weights,
                  **self.skeleton.to_arrays()}
        for key, value in sorted(arrays.items()):
            array = np.asarray(value)
            if array.dtype.kind == "f":
                array = np.round(array.astype(np.float64), 5) + 0.0  # + 0.0: -0.0 hashes as 0.0
            elif array.dtype.kind in "iub":
                array = array.astype(np.int64)
            digest.update(f"{key}:{array.dtype.str}:{array.shape};".encode())
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()[:16]

    @property
    def has_standard_keypoints(self) -> bool:
        return tuple(self.keypoint_names) == KEYPOINT_NAMES

    def to_arrays(self) -> dict[str, np.ndarray]:
        """All fields as flat arrays for ``character.npz`` (inverse of :meth:`from_arrays`)."""
        arrays = {
            "name": np.array(self.name),
            "rest_theta": self.rest_theta,
            "vertices": self.vertices,
            "faces": self.faces,
            "face_uvs": self.face_uvs,
            "skin_bone_names": np.array(self.skin_bone_names, dtype=str),
            "skin_bone_joints": self.skin_bone_joints,
            "skin_weights": self.skin_weights,
            "keypoint_names": np.array(self.keypoint_names, dtype=str),
            "keypoint_joints": self.keypoint_joints,
            "keypoint_offsets": self.keypoint_offsets,
            "segmentation": self.segmentation,
            "segmentation_names": np.array(json.dumps({str(k): v for k, v in self.segmentation_names.items()})),
            "hand_segmentation": self.hand_segmentation,
            "extras": np.array(json.dumps(self.extras)),
        }
        if self.vertex_colors is not None:
            arrays["vertex_colors"] = self.vertex_colors
        arrays.update(self.skeleton.to_arrays())
        arrays.update(self.graph.to_arrays())
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "Character":
        try:
            return cls(
                name=str(arrays["name"]),
                skeleton=Skeleton.from_arrays(arrays),
                rest_theta=arrays["rest_theta"],
                vertices=arrays["vertices"],
                faces=arrays["faces"],
                face_uvs=arrays["face_uvs"],
                skin_bone_names=tuple(str(s) for s in arrays["skin_bone_names"]),
                skin_bone_joints=arrays["skin_bone_joints"],
                skin_weights=arrays["skin_weights"],
                keypoint_names=tuple(str(s) for s in arrays["keypoint_names"]),
                keypoint_joints=arrays["keypoint_joints"],
                keypoint_offsets=arrays["keypoint_offsets"],
                graph=EmbeddedGraph.from_arrays(arrays),
                segmentation=arrays["segmentation"],
                segmentation_names={int(k): v for k, v in json.loads(str(arrays["segmentation_names"])).items()},
                hand_segmentation=arrays["hand_segmentation"],
                vertex_colors=arrays.get("vertex_colors"),
                extras=json.loads(str(arrays["extras"])),
            )
        except KeyError as exc:
            raise EgorelightError(f"character payload lacks the array {exc.args[0]!r}") from None
