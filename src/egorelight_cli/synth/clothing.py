"""Clothing that moves beyond skinning, as embedded-graph node translations in canonical space.

The true surface of a frame is ``pose_character(character, theta, node_translation=beta)`` with
``beta = beta_pose + beta_random`` (N,3) per frame, both restricted to clothing nodes (shirt and
trousers; a node's *cloth weight* is 1 inside a garment, tapering to 0 at its border):

* ``beta_pose`` -- a deterministic function of the motion (what a motion-driven avatar can learn):
  *wrinkles* at bent joints (elbows, knees, hips, shoulders, spine) whose depth grows with the
  bend angle, along each node's rest normal with a fixed spatial pattern, and *garment lag*: loose
  cloth trails behind the low-passed velocity of its joint (expressed in the joint's frame);
* ``beta_random`` -- a smooth, temporally correlated random field that no function of the pose
  predicts: Gaussian-process noise over the nodes' rest positions (length scale ~12 cm) driven
  by an independent random stream, low-passed in time (correlation time ~0.5 s). Only a sensor
  that sees the surface (the egocentric depth) can explain it: this is what makes the paper's
  depth conditioning measurable.

The parts are returned separately (ground truth) by :meth:`ClothingModel.deform`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from egorelight_cli.geometry.skeleton import forward_kinematics
from egorelight_cli.render.raster import vertex_normals
from egorelight_cli.structures.character import Character
from egorelight_cli.synth.appearance import CLOTH_MATERIALS, vertex_materials

#: (DoF, joint, sign): a bend DoF, the joint whose rest position centres its wrinkles, and the
#: sign that makes the DoF's bending direction positive (hinges curl with negative values).
WRINKLE_DOFS = (
    ("left_elbow", "LeftForeArm_rx", -1.0), ("right_elbow", "RightForeArm_rx", -1.0),
    ("left_knee", "LeftLeg_rx", -1.0), ("right_knee", "RightLeg_rx", -1.0),
    ("left_hip_flex", "LeftUpLeg_rx", 1.0), ("right_hip_flex", "RightUpLeg_rx", 1.0),
    ("left_shoulder_abduct", "LeftArm_rz", 1.0), ("right_shoulder_abduct", "RightArm_rz", 1.0),
    ("spine1_bend", "Spine1_ry", 1.0), ("spine3_bend", "Spine3_ry", 1.0),
)


@dataclass(frozen=True)
class ClothingParams:
    """Amplitudes (metres) and time constants (seconds) of the clothing model."""

    wrinkle_depth: float = 0.012
    wrinkle_radius: float = 0.14
    wrinkle_wavelength: float = 0.07
    lag_gain: float = 0.02
    lag_time: float = 0.15
    lag_max: float = 0.025
    random_amplitude: float = 0.008
    random_length: float = 0.12
    random_time: float = 0.5


class ClothingModel:
    """Clothing deformation of one character (see the module docstring)."""

    def __init__(self, character: Character, params: ClothingParams = ClothingParams(), seed: int = 0):
        self.character = character
        self.params = params
        graph = character.graph
        rest = character.vertices
        self.node_rest = rest[graph.node_vertex]
        self.node_normal = vertex_normals(rest, character.faces)[graph.node_vertex]
        cloth_vertex = np.isin(vertex_materials(character), CLOTH_MATERIALS)
        self.cloth_weight = self._cloth_weights(cloth_vertex[graph.node_vertex].astype(float))
        sk = character.skeleton
        rest_fk = forward_kinematics(torch.as_tensor(character.rest_theta), sk).numpy()
        rng = np.random.default_rng(seed)
        self.wrinkles = []  # (dof index, sign, (N,) amplitude pattern)
        for dof, joint, sign in WRINKLE_DOFS:
            if dof not in sk.dof_names or joint not in sk.joint_names:
                continue
            centre = rest_fk[sk.joint_index(joint), :3, 3]
            distance = np.linalg.norm(self.node_rest - centre, axis=1)
            falloff = np.exp(-0.5 * (distance / params.wrinkle_radius) ** 2)
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            phase = rng.uniform(0, 2 * np.pi)
            pattern = np.sin(2 * np.pi * (self.node_rest - centre) @ axis / params.wrinkle_wavelength + phase)
            self.wrinkles.append((sk.dof_index(dof), sign, falloff * pattern * self.cloth_weight))
        # Each node trails its nearest skin bone's joint.
        node_skin = character.skin_weights[graph.node_vertex]
        self.node_joint = character.skin_bone_joints[np.argmax(node_skin, axis=1)]
        # Spatial covariance factor of the random field over the node rest positions.
        d2 = np.sum((self.node_rest[:, None] - self.node_rest[None]) ** 2, axis=-1)
        cov = np.exp(-0.5 * d2 / params.random_length ** 2) + 1e-6 * np.eye(len(d2))
        evals, evecs = np.linalg.eigh(cov)
        self.spatial_factor = evecs * np.sqrt(np.clip(evals, 0, None))[None]

    def _cloth_weights(self, indicator: np.ndarray) -> np.ndarray:
        """Node cloth weights: 1 inside a garment, tapering over one graph ring at its border."""
        graph = self.character.graph
        n = len(indicator)
        edges = graph.edges
        skin_neighbour = np.zeros(n, dtype=bool)
        if len(edges):
            a, b = edges[:, 0], edges[:, 1]
            skin_neighbour[a[indicator[b] == 0]] = True
            skin_neighbour[b[indicator[a] == 0]] = True
        return np.where(indicator > 0, np.where(skin_neighbour, 0.5, 1.0), 0.0)

    # ------------------------------------------------------------------------------- parts
    def pose_part(self, theta: np.ndarray, fps: float) -> np.ndarray:
        """(T,N,3) float64 pose- and velocity-dependent node translations of a motion (T,D)."""
        theta = np.asarray(theta, dtype=np.float64)
        T = len(theta)
        p = self.params
        out = np.zeros((T, len(self.node_rest), 3))
        for dof, sign, pattern in self.wrinkles:
            bend = np.clip(sign * (theta[:, dof] - self.character.rest_theta[dof]), 0, None)
            out += (p.wrinkle_depth * np.tanh(bend))[:, None, None] * (pattern[:, None] * self.node_normal)[None]
        if T > 1:
            fk = forward_kinematics(torch.as_tensor(theta), self.character.skeleton).numpy()
            position = fk[:, self.node_joint][..., :3, 3]  # (T,N,3)
            velocity = np.gradient(position, 1.0 / fps, axis=0)
            sigma = max(p.lag_time * fps, 1e-3)
            smoothed = ndimage.gaussian_filter1d(velocity, sigma, axis=0, mode="nearest")
            # World velocity into the canonical frame: joints are world-aligned at rest, so the
            # joint's current rotation takes canonical directions to world ones.
            R = fk[:, self.node_joint][..., :3, :3]
            local = np.sum(R * smoothed[..., :, None], axis=-2)  # R^T v
            lag = -p.lag_gain * local
            norm = np.linalg.norm(lag, axis=-1, keepdims=True)
            lag *= np.minimum(1.0, p.lag_max / np.maximum(norm, 1e-12))
            out += lag * self.cloth_weight[None, :, None]
        return out

    def random_part(self, num_frames: int, fps: float, seed: int) -> np.ndarray:
        """(T,N,3) float64 smooth, temporally correlated random node translations (pose-independent)."""
        p = self.params
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0C107]))
        sigma = max(p.random_time * fps, 1e-3)
        pad = int(np.ceil(4 * sigma))
        white = rng.normal(size=(num_frames + 2 * pad, len(self.node_rest), 3))
        smooth = ndimage.gaussian_filter1d(white, sigma, axis=0, mode="wrap")[pad:pad + num_frames]
        # Unit variance after the temporal filter: the filter's gain is sqrt(sum(kernel^2)).
        smooth /= np.sqrt(1.0 / (2.0 * np.sqrt(np.pi) * sigma)) if sigma > 0.5 else 1.0
        N = len(self.node_rest)
        field = (self.spatial_factor @ smooth.transpose(1, 0, 2).reshape(N, -1)).reshape(N, num_frames, 3)
        field = field.transpose(1, 0, 2)
        return p.random_amplitude * field * self.cloth_weight[None, :, None]

    def deform(self, theta: np.ndarray, fps: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(beta_pose, beta_random), each (T,N,3) float64 metres, canonical space."""
        return self.pose_part(theta, fps), self.random_part(len(theta), fps, seed)
