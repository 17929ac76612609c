"""The simulated person's own body: a finer mesh, its own proportions, rig and skinning weights.

The pipeline fits a character (``default`` or one fitted to a scan) that can represent a person
only approximately. The simulated subject must not be that character, or every accuracy figure
is flattered. It is derived from the shipped template but differs from it in everything the
pipeline models:

* **mesh**: ``subdivisions`` levels of Loop subdivision (4x the faces per level), so its surface is
  smoother and finer than the template's;
* **proportions** (seeded): a global height factor and per-segment length and girth factors (upper
  arm, forearm, thigh, shin, torso, neck, hand, foot), applied by moving the joints and carrying
  the rest surface with them (rest-pose retargeting), girths by scaling the surface around each
  bone's axis;
* **rig**: joint centres moved again by a few millimetres *without* moving the surface (another
  rigger's joint placement), its own skinning weights (the template's diffused over the finer
  mesh: wider, smoother transitions), posed by **plain linear blend skinning** (the pipeline
  uses dual quaternions through its embedded graph);
* **keypoints**: the 57 names of the template, attached to the subject's own joints (offsets
  scaled with it), so the truth comes from its rig.

The body is returned as a :class:`~egorelight_cli.structures.character.Character` (its own
skeleton values, same joint/DoF names) so the motion library, FK and the HMD mount work on it.
Its embedded graph is the template's carried over the subdivision: valid, but never used to pose
the subject.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
import torch

from egorelight_cli.geometry.embedded_graph import mesh_adjacency
from egorelight_cli.geometry.skeleton import bone_transforms, forward_kinematics
from egorelight_cli.geometry.skinning import linear_blend_skinning
from egorelight_cli.geometry.subdivision import loop_subdivide
from egorelight_cli.structures.character import Character, EmbeddedGraph

#: Body segment of a skeleton bone (by its name without the DoF suffix); bones not listed: "core".
SEGMENTS = {"Arm": "upper_arm", "ForeArm": "forearm", "ForeArmRoll": "forearm", "UpLeg": "thigh", "Leg": "shin",
            "Spine": "torso", "Spine1": "torso", "Spine2": "torso", "Spine3": "torso", "Spine4": "torso",
            "Neck": "neck", "Hand": "hand", "Foot": "foot", "ToeBase": "foot", "Shoulder": "shoulder"}
#: Segments whose girth varies (the surface is scaled around the bone's axis).
GIRTH_SEGMENTS = ("upper_arm", "forearm", "thigh", "shin", "torso", "neck")


@dataclass(frozen=True)
class SubjectParams:
    """How far the subject departs from the template (standard deviations; metres)."""

    subdivisions: int = 1
    height_std: float = 0.03
    length_std: float = 0.04
    girth_std: float = 0.06
    asymmetry_std: float = 0.01
    joint_jitter_m: float = 0.008
    weight_diffusion: int = 12


def bone_segment(name: str) -> str:
    """Segment of a joint or bone name (``LeftForeArm_rx`` -> ``forearm``; fingers -> ``hand``)."""
    base = name.split("_")[0]
    for side in ("Left", "Right"):
        if base.startswith(side):
            base = base[len(side):]
    if base.startswith("Hand") and base != "Hand":
        return "hand"
    return SEGMENTS.get(base, "core")


def _side(name: str) -> str:
    return "left" if name.startswith("Left") else "right" if name.startswith("Right") else "centre"


def draw_proportions(params: SubjectParams, rng: np.random.Generator) -> dict:
    """Seeded factors: ``{"height": s, "length": {(segment, side): f}, "girth": {...}}``."""
    segments = sorted(set(SEGMENTS.values()) | {"core"})
    length, girth = {}, {}
    for seg in segments:
        common_l = 1.0 + params.length_std * rng.normal()
        common_g = 1.0 + params.girth_std * rng.normal()
        for side in ("left", "right", "centre"):
            length[(seg, side)] = float(np.clip(common_l + params.asymmetry_std * rng.normal(), 0.85, 1.15))
            girth[(seg, side)] = float(np.clip(common_g + params.asymmetry_std * rng.normal(), 0.8, 1.2))
    return {"height": float(np.clip(1.0 + params.height_std * rng.normal(), 0.9, 1.1)), "length": length,
            "girth": girth}


def _rest_joints(skeleton, rest_theta: np.ndarray) -> np.ndarray:
    return forward_kinematics(torch.as_tensor(rest_theta, dtype=torch.float64), skeleton).numpy()


def _diffuse_weights(weights: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Skinning weights averaged with their mesh neighbours ``iterations`` times (rows sum to 1)."""
    A = mesh_adjacency(faces, len(weights))
    degree = np.asarray(A.sum(axis=1)).ravel()
    M = sp.diags(1.0 / np.maximum(degree, 1)) @ A
    w = np.asarray(weights, dtype=np.float64)
    for _ in range(int(iterations)):
        w = 0.5 * w + 0.5 * (M @ w)
    w[w < 1e-4] = 0.0
    return w / w.sum(axis=1, keepdims=True)


def _scaled_skeleton(skeleton, proportions: dict):
    """Skeleton with every joint offset scaled by the height factor and its parent segment's length."""
    offsets = skeleton.offsets * proportions["height"]
    for j, parent in enumerate(skeleton.parents):
        if parent >= 0:
            pname = skeleton.joint_names[parent]
            offsets[j] *= proportions["length"][(bone_segment(pname), _side(pname))]
    return replace(skeleton, offsets=offsets)


def _retarget(vertices: np.ndarray, weights: np.ndarray, bone_joints: np.ndarray, G_from: np.ndarray,
              G_to: np.ndarray) -> np.ndarray:
    """Rest surface carried from one joint placement to another by LBS of ``G_to inv(G_from)``."""
    M = G_to[bone_joints] @ np.linalg.inv(G_from[bone_joints])  # (B,4,4)
    blended = np.einsum("vb,bij->vij", weights, M)
    return np.einsum("vij,vj->vi", blended[:, :3, :3], vertices) + blended[:, :3, 3]


def _apply_girth(vertices: np.ndarray, weights: np.ndarray, skeleton, bone_names, bone_joints: np.ndarray,
                 G: np.ndarray, proportions: dict) -> np.ndarray:
    """Scale the surface around each bone's axis (joint -> its first child) by the segment girth."""
    out = vertices.copy()
    children = {int(p): j for j, p in reversed(list(enumerate(skeleton.parents))) if p >= 0}
    for b, (name, joint) in enumerate(zip(bone_names, bone_joints)):
        seg = bone_segment(name)
        factor = proportions["girth"].get((seg, _side(name)), 1.0)
        if seg not in GIRTH_SEGMENTS or abs(factor - 1.0) < 1e-9:
            continue
        # The bone's axis: from its joint towards the first descendant at another position.
        start, child = G[joint, :3, 3], children.get(int(joint))
        while child is not None and np.linalg.norm(G[child, :3, 3] - start) < 1e-6:
            child = children.get(child)
        if child is None:
            continue
        axis = G[child, :3, 3] - start
        axis /= np.linalg.norm(axis)
        rel = vertices - start
        perp = rel - (rel @ axis)[:, None] * axis
        out += weights[:, b, None] * (factor - 1.0) * perp
    return out


def _jitter_joints(skeleton, rest_theta: np.ndarray, rng: np.random.Generator, sigma: float):
    """Every joint centre moved by its own ~``sigma`` (fingers: a quarter), independently of its
    parent's move (no drift down the chains); joints at one place (a DoF chain) move together."""
    G = _rest_joints(skeleton, rest_theta)
    positions = G[:, :3, 3]
    _, place = np.unique(np.round(positions, 6), axis=0, return_inverse=True)
    scale = np.array([0.25 if bone_segment(n) == "hand" else 1.0 for n in skeleton.joint_names])
    noise = sigma * rng.normal(size=(place.max() + 1, 3))[place.ravel()] * scale[:, None]
    noise[0] = 0.0
    offsets = skeleton.offsets.copy()
    for j, parent in enumerate(skeleton.parents):
        if parent >= 0:
            # offsets live in the parent's frame: rotate the relative move into it
            offsets[j] += G[parent, :3, :3].T @ (noise[j] - noise[parent])
    return replace(skeleton, offsets=offsets)


def _subdivided_graph(graph: EmbeddedGraph, extend_labels) -> EmbeddedGraph:
    return EmbeddedGraph(node_vertex=graph.node_vertex, node_radius=graph.node_radius, edges=graph.edges,
                         vertex_node_index=extend_labels(graph.vertex_node_index),
                         vertex_node_weight=extend_labels(graph.vertex_node_weight), faces=graph.faces)


def make_subject_body(template: Character, params: SubjectParams, seed: int) -> tuple[Character, dict, np.ndarray]:
    """The subject's body (see the module docstring), a description of what the seed chose, and
    (V,2) *visibility parents*: the two vertices of the previous subdivision level a vertex sits
    between (itself twice for a vertex of that level)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5B7]))
    vertices, faces, uvs = template.vertices, template.faces, template.face_uvs
    weights, seg, hands, graph = template.skin_weights, template.segmentation, template.hand_segmentation, template.graph
    parents = np.repeat(np.arange(len(vertices))[:, None], 2, axis=1)
    for _ in range(int(params.subdivisions)):
        sub = loop_subdivide(vertices, faces, uvs)
        vertices, faces, uvs = sub.vertices, sub.faces, sub.face_uvs
        weights, seg, hands = sub.extend(weights), sub.extend_labels(seg), sub.extend_labels(hands)
        graph = _subdivided_graph(graph, sub.extend_labels)
        parents = np.concatenate([np.repeat(np.arange(sub.num_original)[:, None], 2, axis=1), sub.edges])
    proportions = draw_proportions(params, rng)
    sk0 = template.skeleton
    G0 = _rest_joints(sk0, template.rest_theta)
    scaled = _scaled_skeleton(sk0, proportions)
    G1 = _rest_joints(scaled, template.rest_theta)
    s = proportions["height"]
    G0_scaled = G0.copy()
    G0_scaled[:, :3, 3] *= s  # the template uniformly scaled: same rotations, joints s times further out
    vertices = _retarget(vertices * s, weights, template.skin_bone_joints, G0_scaled, G1)
    vertices = _apply_girth(vertices, weights, scaled, template.skin_bone_names, template.skin_bone_joints, G1,
                            proportions)
    # Feet back on the floor: the lowest rest point keeps its height.
    lift = float(template.vertices[:, 1].min() - vertices[:, 1].min())
    vertices[:, 1] += lift
    root_offsets = scaled.offsets.copy()
    root_offsets[0, 1] += lift
    skeleton = _jitter_joints(replace(scaled, offsets=root_offsets), template.rest_theta, rng, params.joint_jitter_m)
    body = Character(
        name=f"subject-{int(seed)}", skeleton=skeleton, rest_theta=template.rest_theta, vertices=vertices,
        faces=faces, face_uvs=uvs, skin_bone_names=template.skin_bone_names,
        skin_bone_joints=template.skin_bone_joints,
        skin_weights=_diffuse_weights(weights, faces, params.weight_diffusion),
        keypoint_names=template.keypoint_names, keypoint_joints=template.keypoint_joints,
        keypoint_offsets=template.keypoint_offsets * s, graph=graph, segmentation=seg,
        segmentation_names=template.segmentation_names, hand_segmentation=hands,
        extras={"source": "synth subject (not a pipeline character)"})
    description = {
        "vertices": int(len(vertices)), "faces": int(len(faces)), "subdivisions": int(params.subdivisions),
        "height_factor": round(s, 4), "skinning": "linear blend (own weights)",
        "length_factors": {f"{k[0]}_{k[1]}": round(v, 4) for k, v in proportions["length"].items() if k[1] != "centre"
                           or k[0] in ("torso", "neck", "core")},
        "girth_factors": {f"{k[0]}_{k[1]}": round(v, 4) for k, v in proportions["girth"].items()
                          if k[0] in GIRTH_SEGMENTS},
        "joint_jitter_m": params.joint_jitter_m,
    }
    return body, description, parents


def pose_lbs(body: Character, theta: np.ndarray, rest_points: np.ndarray | None = None,
             weights: np.ndarray | None = None, joint_transforms: np.ndarray | None = None) -> np.ndarray:
    """(T,P,3) float64 world positions of rest points (P,3) (default the body's vertices) skinned
    with ``weights`` (P,B) (default the body's) by plain LBS at motion ``theta`` (T,D).

    ``rest_points`` may also be per frame, (T,P,3) (a rest surface displaced frame by frame).
    """
    points = body.vertices if rest_points is None else rest_points
    w = body.skin_weights if weights is None else weights
    th = torch.as_tensor(np.asarray(theta, dtype=np.float64))
    G = None if joint_transforms is None else torch.as_tensor(joint_transforms)
    bone_T = bone_transforms(th, body, G)
    return linear_blend_skinning(torch.as_tensor(np.asarray(points, np.float64)), bone_T,
                                 torch.as_tensor(w)).numpy()


# ------------------------------------------------------------------------------ the whole person
class Subject:
    """The simulated person: body, garments, and their *outer surface* (what cameras see).

    The outer surface is the body's faces not covered by a garment plus the garments' faces, over
    a compact vertex list: the body vertices those faces use, then every garment vertex.

    Attributes:
        body: the subject's own body (:func:`make_subject_body`).
        clothing: its garments (:class:`~egorelight_cli.synth.clothing.ClothingModel`).
        body_keep: (Vb,) body vertices on the outer surface.
        faces: (F,3) outer-surface triangles; face_uvs (F,3,2) in the body's UV layout.
        garment_faces: (F,) bool, faces that belong to a garment.
        description: what the seed chose.
    """

    def __init__(self, body: Character, clothing, description: dict, parents: np.ndarray | None = None):
        self.body, self.clothing, self.description = body, clothing, description
        open_faces = body.faces[~clothing.covered_faces]
        self.body_keep = np.unique(open_faces)
        remap = np.full(body.num_vertices, -1, np.int64)
        remap[self.body_keep] = np.arange(len(self.body_keep))
        nb = len(self.body_keep)
        self.faces = np.concatenate([remap[open_faces], clothing.faces + nb])
        self.face_uvs = np.concatenate([body.face_uvs[~clothing.covered_faces], clothing.face_uvs])
        self.garment_faces = np.r_[np.zeros(len(open_faces), bool), np.ones(len(clothing.faces), bool)]
        self.visibility_parents = self._outer_parents(remap, parents)

    def _outer_parents(self, remap: np.ndarray, parents: np.ndarray | None) -> np.ndarray:
        """(V,2) outer-surface visibility parents: a vertex between two vertices of the previous
        subdivision level (both on the outer surface, in the same garment or both skin) takes its
        light visibility from them; every other vertex is traced (its own parent)."""
        nb = len(self.body_keep)
        own = np.repeat(np.arange(self.num_vertices)[:, None], 2, axis=1)
        if parents is None:
            return own
        out = own.copy()
        body_parents = remap[parents[self.body_keep]]  # (nb,2), -1 where a parent is under a garment
        ok = np.all(body_parents >= 0, axis=1)
        out[:nb][ok] = body_parents[ok]
        clothing = self.clothing
        for g in range(len(clothing.names)):
            rows = np.flatnonzero(clothing.garment == g)
            local = np.full(self.body.num_vertices, -1, np.int64)
            local[clothing.body_vertex[rows]] = rows + nb
            garment_parents = local[parents[clothing.body_vertex[rows]]]
            ok = np.all(garment_parents >= 0, axis=1)
            out[rows[ok] + nb] = garment_parents[ok]
        return out

    @property
    def num_vertices(self) -> int:
        return len(self.body_keep) + self.clothing.num_vertices

    def rest_vertices(self, displacement: np.ndarray | None = None) -> np.ndarray:
        """(V,3) outer-surface rest positions (garments eased; plus a (G,3) displacement if given)."""
        garments = self.clothing.rest if displacement is None else self.clothing.rest + displacement
        return np.concatenate([self.body.vertices[self.body_keep], garments])

    def pose(self, theta: np.ndarray, displacement: np.ndarray, joint_transforms: np.ndarray | None = None,
             chunk: int = 64) -> np.ndarray:
        """(T,V,3) float32 posed outer surface of a motion (T,D) with garment displacements (T,G,3)."""
        out = np.empty((len(theta), self.num_vertices, 3), np.float32)
        nb = len(self.body_keep)
        weights = self.body.skin_weights[self.body_keep]
        for start in range(0, len(theta), chunk):
            rows = slice(start, start + chunk)
            G = None if joint_transforms is None else joint_transforms[rows]
            out[rows, :nb] = pose_lbs(self.body, theta[rows], self.body.vertices[self.body_keep], weights, G)
            out[rows, nb:] = pose_lbs(self.body, theta[rows], self.clothing.rest[None] + displacement[rows],
                                      self.clothing.skin_weights, G)
        return out


def make_subject(template: Character, cfg, seed: int) -> Subject:
    """The subject of a capture from the ``subject`` and ``clothing`` config sections."""
    from egorelight_cli.synth.clothing import ClothingModel, ClothingParams

    body, description, parents = make_subject_body(template, SubjectParams(**cfg.subject.to_dict()), seed)
    clothing = ClothingModel(body, ClothingParams(**cfg.clothing.to_dict()), seed=seed)
    description = {**description, "garments": list(clothing.names), "garment_vertices": int(clothing.num_vertices)}
    return Subject(body, clothing, description, parents)
