"""The animation stage's building blocks without a capture: depth encoding xi, UV signals,
AnimationNet + character model, mesh losses, the meshes payload."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.depth_encoding import encode_depth, encode_depth_frame, skinned_template
from egorelight_cli.geometry.embedded_graph import pose_character


@pytest.fixture(scope="module")
def posed(character):
    """Two frames of a non-trivial pose (elbows and knees bent, body turned)."""
    rng = np.random.default_rng(3)
    theta = np.tile(character.rest_theta, (2, 1)).astype(np.float64)
    theta[:, 6:] += rng.normal(scale=0.15, size=theta[:, 6:].shape)
    theta[1, 3] += 0.4
    theta[:, 0:3] += [0.1, 0.0, -0.2]
    return theta, skinned_template(character, theta)


# --------------------------------------------------------------------------- depth encoding
def test_skinned_template_is_the_character_model(character, posed):
    theta, template = posed
    ref = pose_character(character, torch.as_tensor(theta)).numpy()
    np.testing.assert_allclose(template.vertices, ref, atol=1e-9)
    from egorelight_cli.geometry.rigid import project_to_rotation

    R = project_to_rotation(template.vertex_T[..., :3, :3])
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_xi_is_zero_where_no_cloud_point_is_close(posed):
    _, template = posed
    v, n = template.vertices[0], template.normals[0]
    far = v[:500] + np.array([0.0, 0.0, 1.0])  # 1 m away from everything
    xi, mask = encode_depth_frame(v, n, template.vertex_T[0], far, n[:500], eps_d=0.03, eps_n=0.5)
    assert not mask.any()
    assert np.all(xi == 0)
    xi, mask = encode_depth(template, [None, (np.zeros((0, 3)), np.zeros((0, 3)))], 0.03, 0.5)
    assert not mask.any() and np.all(xi == 0)


def test_xi_unwarps_the_residual_to_canonical_space(character, posed):
    _, template = posed
    t = 1
    v, n, R = template.vertices[t], template.normals[t], template.vertex_T[t]
    offset = 0.01
    cloud = v + offset * n  # every vertex has a point 1 cm out along its normal, same normal
    xi, mask = encode_depth_frame(v, n, R, cloud, n, eps_d=0.03, eps_n=0.5)
    assert mask.mean() > 0.85  # thin parts (fingers) find a point of the other side first
    length = np.linalg.norm(xi[mask], axis=1)
    assert abs(np.median(length) - offset) < 5e-4 and length.max() < 0.03
    # xi is W^-1 of the posed residual: rotating it back gives the residual direction
    from egorelight_cli.geometry.rigid import project_to_rotation

    back = np.einsum("vij,vj->vi", project_to_rotation(R[mask][:, :3, :3]), xi[mask])
    cos = np.sum(back * n[mask], axis=1) / np.linalg.norm(back, axis=1)
    assert np.median(cos) > 0.99
    # in canonical space the encoding points along the rest normals where the pose is rigid
    from egorelight_cli.geometry.uv_signals import canonical_signal

    rest_n = canonical_signal(character)[:, 3:]
    cos_rest = np.sum(xi[mask] * rest_n[mask], axis=1) / np.linalg.norm(xi[mask], axis=1)
    assert np.median(cos_rest) > 0.95


def test_normal_filter_rejects_an_opposite_facing_point(posed):
    _, template = posed
    v, n, R = template.vertices[0], template.normals[0], template.vertex_T[0]
    for i in np.random.default_rng(0).choice(len(v), 10, replace=False):
        point = v[i:i + 1] + 0.005 * n[i:i + 1]
        xi, same = encode_depth_frame(v, n, R, point, n[i:i + 1], 0.03, 0.5)
        assert same[i] and np.linalg.norm(xi[i]) == pytest.approx(0.005, abs=1e-5)
        xi, opposite = encode_depth_frame(v, n, R, point, -n[i:i + 1], 0.03, 0.5)
        assert not opposite[i] and np.all(xi[i] == 0)
        # 80 degrees off is rejected at eps_n = 0.5 (60 degrees), accepted at eps_n = 0.9
        side = np.cross(n[i], [0.0, 1.0, 0.0] if abs(n[i, 1]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        tilted = (np.cos(np.radians(80)) * n[i] + np.sin(np.radians(80)) * side)[None]
        assert not encode_depth_frame(v, n, R, point, tilted, 0.03, 0.5)[1][i]
        assert encode_depth_frame(v, n, R, point, tilted, 0.03, 0.9)[1][i]
    with pytest.raises(EgorelightError):
        encode_depth_frame(v, n, R, v, n, 0.0, 0.5)


# ------------------------------------------------------------------------------ UV signals
def test_uv_layout_round_trip(character):
    from egorelight_cli.geometry.uv_signals import UVLayout, canonical_signal
    from egorelight_cli.nn.unet import sample_feature_map

    layout = UVLayout.build(character, 64)
    assert UVLayout.build(character, 64) is layout  # cached
    ones = layout.to_uv(np.ones((character.num_vertices, 1)))
    np.testing.assert_allclose(ones[0].numpy()[layout.coverage], 1.0, atol=1e-5)
    assert np.all(ones[0].numpy()[~layout.coverage] == 0)
    rest = canonical_signal(character)[:, :3]
    maps = layout.to_uv(np.stack([rest, rest + 1.0]))  # leading batch dims are kept
    assert maps.shape == (2, 3, 64, 64)
    sampled = sample_feature_map(maps[:1], torch.as_tensor(layout.vertex_uv))[0].numpy()
    # a smooth signal survives rasterisation + bilinear sampling at the vertex UVs (most vertices)
    err = np.linalg.norm(sampled - rest, axis=1)
    assert np.median(err) < 0.02


def test_motion_signal_removes_global_rigid_motion(character, posed):
    from egorelight_cli.geometry.uv_signals import motion_signal, root_transforms

    theta, _ = posed
    moved = theta.copy()
    moved[:, 0:3] += [1.0, 0.2, -0.5]  # translate
    moved[:, 3] += 0.7  # turn about the vertical axis
    signals = []
    for th in (theta, moved):
        template = skinned_template(character, th)
        signals.append(motion_signal(character, template.vertices, root_transforms(character, th), np.array([0, 0])))
    np.testing.assert_allclose(signals[0], signals[1], atol=1e-4)
    assert signals[0].shape == (2, character.num_vertices, 12)


# ------------------------------------------------------------------ network + character model
@pytest.fixture(scope="module")
def tiny_model(character):
    from egorelight_cli.stages.animate import AnimationModel, DepthSettings, NetSettings

    torch.manual_seed(0)
    return AnimationModel(character, NetSettings(uv_resolution=64, base_channels=8, hidden=16), DepthSettings())


def test_zero_network_output_gives_the_skinned_template(tiny_model, posed):
    theta, template = posed
    inputs, _, _ = tiny_model.uv_inputs(theta, np.array([0, 0]), None, template)
    assert inputs.shape == (2, 22, 64, 64)
    out = tiny_model.predict(inputs, theta)
    assert np.all(out["offsets"] == 0) and np.all(out["eg_rotation"] == 0) and np.all(out["eg_translation"] == 0)
    np.testing.assert_allclose(out["vertices"], template.vertices, atol=2e-5)


def test_gradients_reach_the_network_through_the_character_model(tiny_model, posed):
    theta, template = posed
    model = tiny_model
    inputs, _, _ = model.uv_inputs(theta, np.array([0, 0]), None, template)
    state = {k: v.clone() for k, v in model.net.state_dict().items()}
    try:
        torch.manual_seed(1)
        for head in (model.net.node_head, model.net.vertex_head):  # leave the zero start
            torch.nn.init.normal_(head[-1].weight, std=0.1)
        model.net.zero_grad()
        alpha, beta, off = model.net(inputs, model.node_uv, model.vertex_uv)
        posed_v, _ = model.pose(torch.as_tensor(theta, dtype=torch.float32), alpha, beta, off)
        target = torch.as_tensor(template.vertices, dtype=torch.float32) + 0.01
        ((posed_v - target) ** 2).sum().backward()
        for name in ("unet.stem.0.weight", "node_head.0.weight", "vertex_head.0.weight", "node_head.4.weight"):
            grad = dict(model.net.named_parameters())[name].grad
            assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name
    finally:
        model.net.load_state_dict(state)


def test_animation_net_shapes_and_scales():
    from egorelight_cli.nn.animation_net import AnimationNet

    net = AnimationNet(5, base_channels=8, levels=3, hidden=8, rotation_scale=0.5)
    torch.nn.init.constant_(net.node_head[-1].bias, 1.0)
    x = torch.randn(3, 5, 32, 32)
    alpha, beta, off = net(x, torch.rand(7, 2), torch.rand(11, 2))
    assert alpha.shape == (3, 7, 3) and beta.shape == (3, 7, 3) and off.shape == (3, 11, 3)
    torch.testing.assert_close(alpha, torch.full_like(alpha, 0.5))
    torch.testing.assert_close(beta, torch.full_like(beta, 0.02))


# -------------------------------------------------------------------------------- losses
def test_filtered_chamfer_drops_opposite_normal_pairs():
    from egorelight_cli.nn.mesh_losses import filtered_chamfer

    rng = np.random.default_rng(0)
    pts = torch.as_tensor(rng.uniform(-0.1, 0.1, size=(200, 3)), dtype=torch.float32)
    up = torch.tensor([0.0, 1.0, 0.0]).expand(200, 3)
    assert float(filtered_chamfer(pts, up, pts, up)) < 1e-4
    shifted = pts + torch.tensor([0.0, 0.01, 0.0])
    assert abs(float(filtered_chamfer(pts, up, shifted, up)) - 1.0) < 0.2  # about 1 cm
    # the same target facing the other way (an inner surface) is ignored entirely
    assert float(filtered_chamfer(pts, up, shifted, -up)) == 0.0
    # far-away pairs are dropped too
    assert float(filtered_chamfer(pts, up, pts + 1.0, up, max_distance=0.1)) == 0.0
    v = pts.clone().requires_grad_(True)
    filtered_chamfer(v, up, shifted, up).backward()
    assert v.grad[:, 1].mean() < 0  # pulled up towards the target
    # point-to-plane: sliding samples along the surface costs nothing, leaving it does
    plane = torch.stack([pts[:, 0], torch.zeros(200), pts[:, 2]], -1)
    slid = plane + torch.tensor([0.004, 0.0, 0.0])
    assert float(filtered_chamfer(plane, up, slid, up)) > 0.1
    assert float(filtered_chamfer(plane, up, slid, up, point_to_plane=True)) < 1e-3
    lifted = slid + torch.tensor([0.0, 0.01, 0.0])
    assert abs(float(filtered_chamfer(plane, up, lifted, up, point_to_plane=True)) - 1.0) < 1e-3


def test_graph_arap_is_zero_for_a_rigid_motion_and_positive_otherwise(character):
    from egorelight_cli.geometry.rotations import euler_to_matrix
    from egorelight_cli.nn.mesh_losses import graph_arap

    g = torch.as_tensor(character.vertices[character.graph.node_vertex], dtype=torch.float64)
    edges = torch.as_tensor(character.graph.edges)
    N = len(g)
    euler = torch.tensor([0.1, -0.3, 0.2], dtype=torch.float64).expand(N, 3)
    R = euler_to_matrix(euler)
    t = (R @ g[..., None])[..., 0] - g + torch.tensor([0.1, 0.0, 0.3], dtype=torch.float64)
    assert float(graph_arap(g, euler, t, edges)) < 1e-8
    bumped = t.clone()
    bumped[0] += 0.01
    assert float(graph_arap(g, euler, bumped, edges)) > 1e-4


def test_offset_terms(character):
    from egorelight_cli.geometry.embedded_graph import mesh_edges
    from egorelight_cli.nn.mesh_losses import offset_isometry, offset_smoothness

    rest = torch.as_tensor(character.vertices, dtype=torch.float64)
    edges = torch.as_tensor(mesh_edges(character.faces))
    constant = torch.full_like(rest, 0.01)
    assert float(offset_smoothness(constant, edges)) < 1e-12
    assert float(offset_isometry(rest, constant, edges)) < 1e-8
    noisy = torch.as_tensor(np.random.default_rng(0).normal(scale=0.005, size=rest.shape))
    assert float(offset_smoothness(noisy, edges)) > 0.1
    assert float(offset_isometry(rest, noisy, edges)) > 0.01


# ---------------------------------------------------------------------------- meshes payload
def test_meshes_payload_round_trip_and_errors(tmp_path, character, posed):
    from egorelight_cli.io.mesh_sequence import MeshSequence, export_sequence, load_meshes, write_meshes_npz

    theta, template = posed
    N, V = character.graph.num_nodes, character.num_vertices
    meshes = MeshSequence(template.vertices, character.faces, theta, np.zeros((2, N, 3)), np.ones((2, N, 3)) * 0.01,
                          np.zeros((2, V, 3)), np.array([4, 5]), 30.0)
    write_meshes_npz(tmp_path / "meshes.npz", meshes)
    back, artifact = load_meshes(tmp_path / "meshes.npz")
    assert artifact is None
    np.testing.assert_allclose(back.vertices, meshes.vertices)
    np.testing.assert_array_equal(back.frame_ids, [4, 5])
    assert back.fps == 30.0 and back.faces.dtype == np.int32
    paths = export_sequence(tmp_path / "export", back, "obj", character.face_uvs)
    assert [p.name for p in paths] == ["000004.obj", "000005.obj"]
    with pytest.raises(EgorelightError, match="offsets"):
        MeshSequence(template.vertices, character.faces, theta, np.zeros((2, N, 3)), np.zeros((2, N, 3)),
                     np.zeros((2, V + 1, 3)), np.array([4, 5]))
    with pytest.raises(EgorelightError, match="increasing"):
        MeshSequence(template.vertices, character.faces, theta, np.zeros((2, N, 3)), np.zeros((2, N, 3)),
                     np.zeros((2, V, 3)), np.array([5, 4]))
    bad = template.vertices.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(EgorelightError, match="NaN"):
        MeshSequence(bad, character.faces, theta, np.zeros((2, N, 3)), np.zeros((2, N, 3)), np.zeros((2, V, 3)),
                     np.array([4, 5]))


def test_depth_skip_adds_the_sampled_xi_channels_to_the_offsets():
    from egorelight_cli.nn.animation_net import AnimationNet

    net = AnimationNet(6, base_channels=8, hidden=8, skip_channels=(2, 5))
    x = torch.zeros(1, 6, 32, 32)
    x[:, 2:5] = torch.tensor([0.5, -1.0, 2.0])[:, None, None]
    _, _, off = net(x, torch.rand(4, 2), torch.rand(9, 2))
    assert torch.all(off == 0)  # the gain starts at zero
    with torch.no_grad():
        net.skip_gain.fill_(0.03)
    _, _, off = net(x, torch.rand(4, 2), torch.rand(9, 2))
    torch.testing.assert_close(off, torch.tensor([0.015, -0.03, 0.06]).expand(1, 9, 3))
    with pytest.raises(ValueError):
        AnimationNet(6, skip_channels=(0, 2))


def test_observed_cell_mean_averages_only_the_observed_texels():
    from egorelight_cli.nn.animation_net import observed_cell_mean

    values = torch.arange(16.0).reshape(1, 1, 4, 4)
    mask = torch.zeros(1, 1, 4, 4)
    mask[0, 0, 0, 0] = mask[0, 0, 1, 1] = 1.0  # top-left cell: texels 0 and 5
    mask[0, 0, 2:, 2:] = 1.0  # bottom-right cell: texels 10, 11, 14, 15
    mean = observed_cell_mean(values * mask, mask, 2)  # xi is zero where unobserved, as in the inputs
    torch.testing.assert_close(mean, torch.tensor([[[[2.5, 0.0], [0.0, 12.5]]]]))


def test_node_skip_moves_the_nodes_by_the_observed_xi_around_them():
    from egorelight_cli.nn.animation_net import AnimationNet

    net = AnimationNet(7, base_channels=8, hidden=8, node_level_downsample=2, skip_channels=(2, 5),
                       node_skip_mask_channel=5)
    x = torch.zeros(1, 7, 32, 32)
    x[:, 5, :16] = 1.0  # the rows of v > 0.5 are observed ...
    x[:, 2:5, :16] = torch.tensor([0.5, -1.0, 2.0])[:, None, None]  # ... with this xi
    nodes = torch.tensor([[0.3, 0.8], [0.7, 0.9], [0.5, 0.2]])  # two in the observed half, one not
    _, beta, _ = net(x, nodes, torch.rand(9, 2))
    assert torch.all(beta == 0)  # both gains start at zero
    with torch.no_grad():
        net.node_skip_gain.fill_(0.02)
    _, beta, off = net(x, nodes, torch.rand(9, 2))
    torch.testing.assert_close(beta[0, :2], torch.tensor([0.01, -0.02, 0.04]).expand(2, 3))
    torch.testing.assert_close(beta[0, 2], torch.zeros(3))
    assert torch.all(off == 0)  # the vertex skip has its own gain
    with pytest.raises(ValueError):
        AnimationNet(7, node_skip_mask_channel=5)  # the node skip needs the xi channels


def test_a_model_written_before_the_node_skip_loads_without_one():
    from egorelight_cli.stages.animate import NetSettings

    current = NetSettings(uv_resolution=32, base_channels=8, levels=3, node_level_downsample=2, hidden=8,
                          rotation_scale=0.1, translation_scale=0.02, offset_scale=0.01, depth_skip=True,
                          depth_node_skip=True)
    old_architecture = {k: v for k, v in current.to_dict().items() if k != "depth_node_skip"}
    old = NetSettings.from_architecture(old_architecture)
    assert old.depth_node_skip is False and NetSettings.from_architecture(current.to_dict()) == current
    old_weights = {k: v for k, v in current.build_net().state_dict().items() if k != "node_skip_gain"}
    old.build_net().load_state_dict(old_weights)  # strict: the same keys
