"""FK, skinning and graph posing on the real DDC example character (skips without ../shared)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from egorelight_cli.geometry.embedded_graph import build_embedded_graph, pose_character
from egorelight_cli.geometry.skeleton import forward_kinematics, keypoint_positions
from egorelight_cli.structures.skeleton import REVOLUTE

ddc_io = pytest.importorskip("egorelight_cli.io.ddc", reason="the DDC importer (io/ddc.py) is not there yet")
if not hasattr(ddc_io, "read_ddc_character"):
    pytest.skip("io/ddc.py has no read_ddc_character yet", allow_module_level=True)


DDC_EXAMPLE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ddc_example"


@pytest.fixture(scope="module")
def character():
    if not (DDC_EXAMPLE / "ddc.character").exists():
        pytest.skip("../shared/data/ddc_example is not available")
    return ddc_io.read_ddc_character(DDC_EXAMPLE / "ddc.character")


def naive_fk(theta: np.ndarray, sk) -> np.ndarray:
    """Per-joint DDC FK in numpy, straight from the notes."""
    params = theta @ sk.dof_joint_weights
    G = np.zeros((sk.num_joints, 4, 4))
    for j in range(sk.num_joints):
        L = np.eye(4)
        L[:3, 3] = sk.offsets[j]
        M = np.eye(4)
        if sk.joint_types[j] == REVOLUTE:
            a, p = sk.axes[j], params[j]
            K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            M[:3, :3] = np.eye(3) + np.sin(p) * K + (1 - np.cos(p)) * K @ K
        else:
            M[:3, 3] = sk.axes[j] * params[j]
        local = L @ M
        G[j] = local if sk.parents[j] < 0 else G[sk.parents[j]] @ local
    return G


def test_fk_matches_naive_per_joint_loop(character):
    sk = character.skeleton
    rng = np.random.default_rng(0)
    theta = character.rest_theta + rng.normal(scale=0.3, size=(3, sk.num_dofs))
    G = forward_kinematics(torch.as_tensor(theta), sk).numpy()
    assert G.shape == (3, 173, 4, 4)
    for i in range(3):
        np.testing.assert_allclose(G[i], naive_fk(theta[i], sk), atol=1e-12)


@pytest.mark.parametrize("through_graph", [True, False])
def test_rest_pose_reproduces_template(character, through_graph):
    rest = torch.as_tensor(character.rest_theta)
    template = torch.as_tensor(character.vertices)
    out = pose_character(character, rest, skinning="dqs", through_graph=through_graph)
    torch.testing.assert_close(out, template, atol=1e-9, rtol=0)
    # LBS does not renormalise: the file's 7-digit weights sum to 1 only to ~1e-6
    out = pose_character(character, rest, skinning="lbs", through_graph=through_graph)
    torch.testing.assert_close(out, template, atol=1e-5, rtol=0)
    out32 = pose_character(character, rest.float(), through_graph=through_graph)
    torch.testing.assert_close(out32, template.float(), atol=2e-5, rtol=0)


def test_graph_matches_ddc_rule(character):
    g = character.graph
    assert g.num_nodes == 852
    assert np.all(g.node_radius >= 3)
    np.testing.assert_allclose(g.vertex_node_weight.sum(1), 1.0)
    assert np.all((g.vertex_node_index >= 0).sum(1) >= 1)
    rebuilt = build_embedded_graph(character.faces, character.num_vertices, g.node_vertex, g.edges, g.faces)
    np.testing.assert_array_equal(rebuilt.vertex_node_index, g.vertex_node_index)
    np.testing.assert_allclose(rebuilt.vertex_node_weight, g.vertex_node_weight)


def test_graph_posing_is_close_to_vertex_skinning(character):
    sk = character.skeleton
    revolute_dofs = np.abs(sk.dof_joint_weights[:, sk.joint_types == REVOLUTE]).sum(1) > 0
    revolute_dofs[:6] = False  # keep the root still
    rng = np.random.default_rng(1)
    theta = torch.as_tensor(character.rest_theta + rng.normal(scale=0.1, size=(2, sk.num_dofs)) * revolute_dofs)
    a = pose_character(character, theta, through_graph=True)
    b = pose_character(character, theta, through_graph=False)
    d = (a - b).norm(dim=-1)
    body = torch.as_tensor(character.hand_segmentation == 0)
    assert d[:, body].median() < 0.002  # metres
    assert d.max() < 0.05


def test_keypoints_at_rest_are_inside_the_body(character):
    kp = keypoint_positions(torch.as_tensor(character.rest_theta), character).numpy()
    lo, hi = character.vertices.min(0), character.vertices.max(0)
    assert np.all(kp >= lo - 0.05) and np.all(kp <= hi + 0.05)
