"""Benchmark: posing throughput on CPU — FK, DQS / LBS skinning, graph posing, embedded deformation.

Uses the shipped default character (``src/egorelight_cli/data/default_character.npz``, ~5000
vertices, ~60 bones) when it exists, else a synthetic tube rig of 5000 vertices around a
60-bone chain. 1000 frames of seeded random poses around the rest pose are skinned in chunks of
``CHUNK`` frames (bounded temporaries; larger chunks were not faster on CPU). Numbers are
frames per second (float32, no autograd, the process's default torch thread count).

Run ``python bench/bench_skinning.py``; it prints a JSON dict.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from egorelight_cli.geometry.embedded_graph import (
    embedded_deformation,
    pose_through_graph,
)
from egorelight_cli.geometry.rotations import invert_rigid
from egorelight_cli.geometry.skeleton import bone_transforms, forward_kinematics
from egorelight_cli.geometry.skinning import (
    dual_quaternion_skinning,
    linear_blend_skinning,
)
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.skeleton import REVOLUTE, Skeleton

FRAMES = 1000
CHUNK = 25
DEFAULT_CHARACTER = Path(__file__).resolve().parents[1] / "src" / "egorelight_cli" / "data" / "default_character.npz"


def _synthetic_rig(num_bones: int = 60, rings: int = 100, segments: int = 50, length: float = 1.5):
    """A tube (rings*segments vertices) around a chain of revolute-z joints along +y."""
    J = num_bones
    seg = length / J
    skeleton = Skeleton(
        joint_names=tuple(f"b{j}" for j in range(J)),
        parents=np.arange(J) - 1,
        joint_types=np.full(J, REVOLUTE),
        axes=np.tile([0.0, 0.0, 1.0], (J, 1)),
        offsets=np.stack([np.zeros(J), np.r_[0.0, np.full(J - 1, seg)], np.zeros(J)], 1),
        dof_names=tuple(f"d{j}" for j in range(J)),
        dof_joint_weights=np.eye(J),
        dof_limits=np.tile([-np.inf, np.inf], (J, 1)),
    )
    y = np.linspace(0.0, length, rings)
    a = 2 * np.pi * np.arange(segments) / segments
    vertices = np.stack([0.1 * np.tile(np.cos(a), rings), np.repeat(y, segments), 0.1 * np.tile(np.sin(a), rings)], 1)
    pos = np.clip(vertices[:, 1] / seg - 0.5, 0, J - 1)  # blend between the two nearest bone centres
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, J - 1)
    t = pos - lo
    weights = np.zeros((len(vertices), J))
    np.add.at(weights, (np.arange(len(vertices)), lo), 1 - t)
    np.add.at(weights, (np.arange(len(vertices)), hi), t)
    return skeleton, vertices, weights


def _time(fn, repeats: int = 3) -> float:
    """Best of ``repeats`` wall-clock seconds after one warm-up call (caches, allocator)."""
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def _chunked(fn, frames: int):
    def go():
        with torch.no_grad():
            for i in range(0, frames, CHUNK):
                fn(slice(i, min(i + CHUNK, frames)))
    return go


def run() -> dict:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    dtype = torch.float32
    results: dict = {"frames": FRAMES, "chunk_frames": CHUNK, "dtype": "float32", "torch_threads": torch.get_num_threads()}

    character = None
    if DEFAULT_CHARACTER.exists():
        with np.load(DEFAULT_CHARACTER) as data:
            character = Character.from_arrays(dict(data))
        skeleton, vertices, weights = character.skeleton, character.vertices, character.skin_weights
        rest = character.rest_theta
        results["rig"] = "default_character"
    else:
        skeleton, vertices, weights = _synthetic_rig()
        rest = np.zeros(skeleton.num_dofs)
        results["rig"] = "synthetic_tube"
    results.update(vertices=int(vertices.shape[0]), bones=int(weights.shape[1]),
                   max_influences=int((weights > 0).sum(1).max()), joints=skeleton.num_joints)

    theta = torch.as_tensor(rest + rng.normal(scale=0.15, size=(FRAMES, skeleton.num_dofs)), dtype=dtype)
    if character is not None:
        theta[:, :3] = torch.as_tensor(rest[:3], dtype=dtype)  # keep the root translation
        fk_s = _time(lambda: bone_transforms(theta, character))
        bone_T = bone_transforms(theta, character)
    else:
        fk_s = _time(lambda: forward_kinematics(theta, skeleton))
        G_rest_inv = invert_rigid(forward_kinematics(torch.as_tensor(rest, dtype=dtype), skeleton))
        bone_T = forward_kinematics(theta, skeleton) @ G_rest_inv
    results["fk_frames_per_s"] = round(FRAMES / fk_s, 1)

    points = torch.as_tensor(vertices, dtype=dtype)
    dqs_s = _time(_chunked(lambda s: dual_quaternion_skinning(points, bone_T[s], weights), FRAMES))
    lbs_s = _time(_chunked(lambda s: linear_blend_skinning(points, bone_T[s], weights), FRAMES))
    results["dqs_frames_per_s"] = round(FRAMES / dqs_s, 1)
    results["lbs_frames_per_s"] = round(FRAMES / lbs_s, 1)

    if character is not None:
        graph = character.graph
        N = graph.num_nodes
        euler = 0.05 * torch.randn(FRAMES, N, 3, dtype=dtype)
        trans = 0.005 * torch.randn(FRAMES, N, 3, dtype=dtype)
        eg_s = _time(_chunked(lambda s: embedded_deformation(points, graph, euler[s], trans[s]), FRAMES))
        graph_s = _time(_chunked(lambda s: pose_through_graph(points, bone_T[s], weights, graph), FRAMES))
        results["graph_nodes"] = N
        results["embedded_deformation_frames_per_s"] = round(FRAMES / eg_s, 1)
        results["pose_through_graph_dqs_frames_per_s"] = round(FRAMES / graph_s, 1)
    return results


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
