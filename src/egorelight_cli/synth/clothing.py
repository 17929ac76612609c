"""Clothing as separate garment surfaces over the subject's body (shirt and trousers).

Each garment is its own mesh, cut from the body faces its material covers and lifted off the skin
by an *ease* (a few millimetres to 2 cm, loosest mid-garment, sewn to the skin at its openings so
the outer surface stays closed). The hidden body under it is not part of the subject's outer
surface. A garment vertex is posed by plain LBS of its rest position plus a per-frame
displacement in the canonical (rest) frame:

* ``pose part`` -- a deterministic function of the motion (what a motion-driven avatar can learn):
  *folds* at bent joints (elbows, knees, hips, shoulders, spine) whose depth grows with the bend,
  rings around the limb at a wavelength of a few centimetres, and *lag*: loose cloth trails
  behind the low-passed velocity of its joint (expressed in the joint's frame);
* ``random part`` -- a smooth, temporally correlated random field that no function of the pose
  predicts: a Gaussian process over the rest positions (squared-exponential, length ~7 cm, by
  random Fourier features) driven by an independent random stream and low-passed in time
  (correlation time ~0.5 s). Only a sensor that sees the surface (the egocentric depth) can
  explain it: this is what makes the paper's depth conditioning measurable.

Both parts fade to zero at the garment's openings (the *taper*: 0 on the border, 1 two rings in).
Folds at a few centimetres and a random field of ~7 cm are finer than the pipeline's embedded
graph (~500 nodes, ~8 cm apart): no node translation field reproduces them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.geometry.subdivision import unique_edges
from egorelight_cli.structures.character import Character
from egorelight_cli.synth.appearance import SHIRT, TROUSERS, value_noise, vertex_materials

#: (DoF, joint, sign): a bend DoF, the joint whose rest position centres its folds, and the sign
#: that makes the DoF's bending direction positive (hinges curl with negative values).
WRINKLE_DOFS = (
    ("left_elbow", "LeftForeArm_rx", -1.0), ("right_elbow", "RightForeArm_rx", -1.0),
    ("left_knee", "LeftLeg_rx", -1.0), ("right_knee", "RightLeg_rx", -1.0),
    ("left_hip_flex", "LeftUpLeg_rx", 1.0), ("right_hip_flex", "RightUpLeg_rx", 1.0),
    ("left_shoulder_abduct", "LeftArm_rz", 1.0), ("right_shoulder_abduct", "RightArm_rz", 1.0),
    ("spine1_bend", "Spine1_ry", 1.0), ("spine3_bend", "Spine3_ry", 1.0),
)
GARMENT_MATERIALS = {"shirt": SHIRT, "trousers": TROUSERS}
_FEATURES = 96  # random Fourier features of the random field


@dataclass(frozen=True)
class ClothingParams:
    """Amplitudes (metres) and time constants (seconds) of the garments."""

    ease_m: float = 0.012
    ease_variation_m: float = 0.006
    wrinkle_depth: float = 0.012
    wrinkle_radius: float = 0.14
    wrinkle_wavelength: float = 0.045
    lag_gain: float = 0.02
    lag_time: float = 0.15
    lag_max: float = 0.025
    random_amplitude: float = 0.008
    random_length: float = 0.07
    random_time: float = 0.5


def border_taper(faces: np.ndarray, num_vertices: int, rings: int = 2) -> np.ndarray:
    """(V,) 0 on the open border of a mesh, ``k / rings`` k edge rings in, 1 beyond."""
    edges, face_edges = unique_edges(faces)
    count = np.bincount(face_edges.ravel(), minlength=len(edges))
    level = np.full(num_vertices, np.inf)
    level[edges[count == 1].ravel()] = 0.0
    for k in range(1, rings + 1):
        reached = np.isfinite(level)
        grow = np.zeros(num_vertices, bool)
        grow[edges[reached[edges[:, 0]] | reached[edges[:, 1]]].ravel()] = True
        level[grow & ~reached] = float(k)
    return np.clip(level / rings, 0.0, 1.0)


class ClothingModel:
    """The garments of one subject body (see the module docstring).

    Attributes:
        rest: (G,3) float64 rest positions of all garment vertices (eased off the skin).
        faces: (Fg,3) garment triangles (indices into ``rest``).
        face_uvs: (Fg,3,2) their UVs (the body's layout).
        skin_weights: (G,B) the body's weights at the vertices they were cut from.
        body_vertex: (G,) the body vertex each garment vertex was cut from.
        garment: (G,) index into ``names`` of the garment each vertex belongs to.
        names: garment names.
        cloth_weight: (G,) the taper (0 at the openings, 1 inside).
        covered_faces: (Fb,) bool, body faces hidden under a garment.
    """

    def __init__(self, body: Character, params: ClothingParams = ClothingParams(), seed: int = 0):
        self.body = body
        self.params = params
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xC107]))
        material = vertex_materials(body)
        face_material = material[body.faces]
        rest_normals = vertex_normals(body.vertices, body.faces)
        rest, faces, uvs, weights, source, garment, tapers = [], [], [], [], [], [], []
        self.covered_faces = np.zeros(len(body.faces), bool)
        self.names = tuple(GARMENT_MATERIALS)
        offset = 0
        for g, name in enumerate(self.names):
            on = np.all(face_material == GARMENT_MATERIALS[name], axis=1)
            self.covered_faces |= on
            used = np.unique(body.faces[on])
            local = np.full(body.num_vertices, -1, np.int64)
            local[used] = np.arange(len(used))
            f = local[body.faces[on]]
            taper = border_taper(f, len(used))
            tapers.append(taper)
            ease = params.ease_m + params.ease_variation_m * value_noise(body.vertices[used], 0.12, rng)
            rest.append(body.vertices[used] + (taper * np.clip(ease, 0.002, None))[:, None] * rest_normals[used])
            faces.append(f + offset)
            uvs.append(body.face_uvs[on])
            weights.append(body.skin_weights[used])
            source.append(used)
            garment.append(np.full(len(used), g))
            offset += len(used)
        self.rest = np.concatenate(rest)
        self.faces = np.concatenate(faces)
        self.face_uvs = np.concatenate(uvs)
        self.skin_weights = np.concatenate(weights)
        self.body_vertex = np.concatenate(source)
        self.garment = np.concatenate(garment)
        self.cloth_weight = np.concatenate(tapers)
        self.rest_normal = vertex_normals(self.rest, self.faces)
        self._folds(rng)
        # Each vertex trails its strongest bone's joint.
        self.node_joint = body.skin_bone_joints[np.argmax(self.skin_weights, axis=1)]
        # Random Fourier features of a squared-exponential GP over the rest positions.
        self.frequencies = rng.normal(size=(_FEATURES, 3)) / params.random_length
        self.phases = rng.uniform(0, 2 * np.pi, size=_FEATURES)

    def _folds(self, rng: np.random.Generator) -> None:
        sk, p = self.body.skeleton, self.params
        rest_fk = forward_kinematics(torch.as_tensor(self.body.rest_theta), sk).numpy()
        children = {int(q): j for j, q in reversed(list(enumerate(sk.parents))) if q >= 0}
        self.wrinkles = []  # (dof index, sign, (G,) depth pattern)
        for dof, joint, sign in WRINKLE_DOFS:
            if dof not in sk.dof_names or joint not in sk.joint_names:
                continue
            j = sk.joint_index(joint)
            centre = rest_fk[j, :3, 3]
            child = children.get(j)
            while child is not None and np.linalg.norm(rest_fk[child, :3, 3] - centre) < 1e-6:
                child = children.get(child)
            axis = rng.normal(size=3) if child is None else rest_fk[child, :3, 3] - centre
            axis = axis / np.linalg.norm(axis) + 0.25 * rng.normal(size=3)  # rings, slightly skewed
            axis /= np.linalg.norm(axis)
            distance = np.linalg.norm(self.rest - centre, axis=1)
            falloff = np.exp(-0.5 * (distance / p.wrinkle_radius) ** 2)
            pattern = np.sin(2 * np.pi * (self.rest - centre) @ axis / p.wrinkle_wavelength + rng.uniform(0, 2 * np.pi))
            self.wrinkles.append((sk.dof_index(dof), sign, falloff * pattern * self.cloth_weight))

    @property
    def num_vertices(self) -> int:
        return len(self.rest)

    # ------------------------------------------------------------------------------- parts
    def pose_part(self, theta: np.ndarray, fps: float) -> np.ndarray:
        """(T,G,3) float64 pose- and velocity-dependent displacements of a motion (T,D)."""
        theta = np.asarray(theta, dtype=np.float64)
        T, p = len(theta), self.params
        out = np.zeros((T, self.num_vertices, 3))
        for dof, sign, pattern in self.wrinkles:
            bend = np.clip(sign * (theta[:, dof] - self.body.rest_theta[dof]), 0, None)
            out += (p.wrinkle_depth * np.tanh(bend))[:, None, None] * (pattern[:, None] * self.rest_normal)[None]
        if T > 1:
            fk = forward_kinematics(torch.as_tensor(theta), self.body.skeleton).numpy()
            joints = np.unique(self.node_joint)
            position = fk[:, joints][..., :3, 3]
            velocity = np.gradient(position, 1.0 / fps, axis=0)
            sigma = max(p.lag_time * fps, 1e-3)
            smoothed = ndimage.gaussian_filter1d(velocity, sigma, axis=0, mode="nearest")
            # World velocity into the canonical frame: joints are world-aligned at rest, so the
            # joint's current rotation takes canonical directions to world ones.
            local = np.einsum("tjab,tja->tjb", fk[:, joints][..., :3, :3], smoothed)  # R^T v
            lag = -p.lag_gain * local
            norm = np.linalg.norm(lag, axis=-1, keepdims=True)
            lag *= np.minimum(1.0, p.lag_max / np.maximum(norm, 1e-12))
            out += lag[:, np.searchsorted(joints, self.node_joint)] * self.cloth_weight[None, :, None]
        return out

    def random_part(self, num_frames: int, fps: float, seed: int) -> np.ndarray:
        """(T,G,3) float64 smooth, temporally correlated random displacements (pose-independent)."""
        p = self.params
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0C107]))
        sigma = max(p.random_time * fps, 1e-3)
        pad = int(np.ceil(4 * sigma))
        white = rng.normal(size=(num_frames + 2 * pad, _FEATURES, 3))
        smooth = ndimage.gaussian_filter1d(white, sigma, axis=0, mode="wrap")[pad:pad + num_frames]
        # Unit variance after the temporal filter: the filter's gain is sqrt(sum(kernel^2)).
        smooth /= np.sqrt(1.0 / (2.0 * np.sqrt(np.pi) * sigma)) if sigma > 0.5 else 1.0
        features = np.sqrt(2.0 / _FEATURES) * np.cos(self.rest @ self.frequencies.T + self.phases)  # (G,K)
        field = np.einsum("gk,tkc->tgc", features, smooth)
        return p.random_amplitude * field * self.cloth_weight[None, :, None]

    def deform(self, theta: np.ndarray, fps: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(pose part, random part), each (T,G,3) float64 metres, canonical space."""
        return self.pose_part(theta, fps), self.random_part(len(theta), fps, seed)
