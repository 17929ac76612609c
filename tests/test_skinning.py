"""LBS and DQS skinning, the hemisphere sign fix, inverse skinning and gradients."""

from __future__ import annotations

import math

import geometry_synthetic as synth
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry import rotations as rot
from egorelight_cli.geometry.skeleton import bone_transforms
from egorelight_cli.geometry.skinning import (
    dual_quaternion_blend,
    dual_quaternion_skinning,
    inverse_skinning_directions,
    inverse_skinning_points,
    linear_blend_skinning,
    skin_directions,
    skin_points,
    skinning_influences,
    skinning_transforms,
)


def random_rigid(n, seed, dtype=torch.float64, batch=()):
    R = torch.as_tensor(Rotation.random(int(np.prod(batch, dtype=int)) * n, random_state=seed).as_matrix(), dtype=dtype)
    t = torch.as_tensor(np.random.default_rng(seed).normal(size=(R.shape[0], 3)), dtype=dtype)
    return rot.make_transform(R, t).reshape(batch + (n, 4, 4))


def random_weights(V, B, k, seed):
    rng = np.random.default_rng(seed)
    W = np.zeros((V, B))
    for v in range(V):
        bones = rng.choice(B, size=k, replace=False)
        w = rng.random(k) + 0.1
        W[v, bones] = w / w.sum()
    return W


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_single_bone_vertices_dqs_equals_lbs_equals_rigid(dtype):
    T = random_rigid(4, seed=0, dtype=dtype, batch=(2,))  # (2,4,4,4)
    bones = np.array([0, 1, 2, 3, 1, 2])
    W = np.eye(4)[bones]  # one-hot
    points = torch.randn(6, 3, dtype=dtype)
    expected = rot.transform_points(T[:, bones], points)
    tol = {"atol": 1e-5, "rtol": 1e-5} if dtype == torch.float32 else {}
    torch.testing.assert_close(dual_quaternion_skinning(points, T, W), expected, **tol)
    torch.testing.assert_close(linear_blend_skinning(points, T, W), expected, **tol)


def _twist_cross_section(method: str, angle: float) -> tuple[float, float]:
    """Skin a tube whose upper bone twists by ``angle`` about the tube axis; radius at the joint."""
    verts, _ = synth.make_tube(rings=41, segments=16, length=2.0, radius=0.1)
    y = verts[:, 1]
    t = np.clip((y - 0.5) / 1.0, 0.0, 1.0)  # blend over the middle half
    W = np.stack([1 - t, t], 1)
    T = torch.stack([torch.eye(4, dtype=torch.float64),
                     rot.make_transform(rot.axis_angle_to_matrix(torch.tensor([0.0, angle, 0.0], dtype=torch.float64)),
                                        torch.zeros(3, dtype=torch.float64))])
    out = skin_points(torch.as_tensor(verts), T, W, method).numpy()
    mid = np.abs(y - 1.0) < 1e-9  # the ring where both weights are 0.5
    radius = np.linalg.norm(out[mid][:, [0, 2]], axis=1)
    return float(radius.min()), float(radius.max())


def test_twist_dqs_keeps_radius_lbs_collapses():
    lbs_min, _ = _twist_cross_section("lbs", math.pi / 2)
    dqs_min, dqs_max = _twist_cross_section("dqs", math.pi / 2)
    # LBS of a 90-degree twist at weights 1/2: the ring shrinks to cos(45 deg) = 0.707 of its radius
    assert lbs_min == pytest.approx(0.1 * math.cos(math.pi / 4), rel=1e-6)
    # DQS rotates the ring by 45 degrees instead, keeping its radius
    assert dqs_min == pytest.approx(0.1, rel=1e-9) and dqs_max == pytest.approx(0.1, rel=1e-9)
    # the candy-wrapper: at 180 degrees LBS collapses the ring to the axis
    _, lbs_max_180 = _twist_cross_section("lbs", math.pi * 0.999)
    assert lbs_max_180 < 0.01 * 0.1 + 1e-9
    assert _twist_cross_section("dqs", math.pi * 0.999)[0] == pytest.approx(0.1, rel=1e-9)


def test_hemisphere_sign_fix_makes_quaternion_sign_irrelevant():
    T = random_rigid(3, seed=1)
    W = random_weights(50, 3, 3, seed=2)
    real, dual = rot.dual_quaternion_from_rigid(T)
    r0, d0 = dual_quaternion_blend(real, dual, W)
    flip = torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)[:, None]
    r1, d1 = dual_quaternion_blend(real * flip, dual * flip, W)
    # the same transform per vertex (the blended dual quaternion may differ by an overall sign)
    torch.testing.assert_close(rot.rigid_from_dual_quaternion(r0, d0), rot.rigid_from_dual_quaternion(r1, d1))
    # without the fix the naive blend would differ: check that the test case exercises it
    naive = lambda r, d: rot.rigid_from_dual_quaternion(*[torch.as_tensor(W) @ x for x in (r, d)])
    assert (naive(real, dual) - naive(real * flip, dual * flip)).abs().max() > 1e-2


def test_sign_fix_takes_the_short_way_across_180_degrees():
    """Bones at +170 and -170 degrees about y are 20 degrees apart: the blend is at 180 degrees."""
    R = [rot.axis_angle_to_matrix(torch.tensor([0.0, a, 0.0], dtype=torch.float64)) for a in (math.radians(170), math.radians(-170))]
    T = rot.make_transform(torch.stack(R), torch.zeros(2, 3, dtype=torch.float64))
    W = np.array([[0.6, 0.4]])
    p = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    out = dual_quaternion_skinning(p, T, W)
    # nlerp of the half-angle quaternions at 85 and 95 degrees (-170 taken as +190)
    h1, h2 = math.radians(85), math.radians(95)
    expected_angle = 2 * math.atan2(0.6 * math.sin(h1) + 0.4 * math.sin(h2), 0.6 * math.cos(h1) + 0.4 * math.cos(h2))
    assert expected_angle == pytest.approx(math.radians(178), abs=math.radians(0.01))
    expected = torch.tensor([[math.cos(expected_angle), 0.0, -math.sin(expected_angle)]], dtype=torch.float64)
    torch.testing.assert_close(out, expected)


@pytest.mark.parametrize("method", ["dqs", "lbs"])
def test_inverse_skinning_inverts_skinning(method):
    T = random_rigid(5, seed=3, batch=(3,))
    T[..., :3, :3] = rot.axis_angle_to_matrix(0.5 * rot.matrix_to_axis_angle(T[..., :3, :3]))  # keep LBS invertible
    W = random_weights(40, 5, 3, seed=4)
    points = torch.randn(40, 3, dtype=torch.float64)
    normals = torch.nn.functional.normalize(torch.randn(40, 3, dtype=torch.float64), dim=-1)
    vertex_T = skinning_transforms(T, W, method)
    posed = skin_points(points, T, W, method)
    torch.testing.assert_close(rot.transform_points(vertex_T, points), posed)
    rigid = method == "dqs"
    torch.testing.assert_close(inverse_skinning_points(posed, vertex_T, rigid=rigid), points.expand(3, 40, 3))
    torch.testing.assert_close(inverse_skinning_points(posed, vertex_T), points.expand(3, 40, 3))
    posed_n = skin_directions(normals, T, W, method, normalize=False)
    torch.testing.assert_close(inverse_skinning_directions(posed_n, vertex_T, rigid=rigid), normals.expand(3, 40, 3))


def test_dqs_normals_are_rotated_unit_vectors():
    T = random_rigid(3, seed=5)
    W = random_weights(30, 3, 2, seed=6)
    n = torch.nn.functional.normalize(torch.randn(30, 3, dtype=torch.float64), dim=-1)
    out = skin_directions(n, T, W)
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(30, dtype=torch.float64))
    R = skinning_transforms(T, W)[..., :3, :3]
    torch.testing.assert_close(out, (R @ n[..., None])[..., 0])
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand(30, 3, 3))


def test_influences_are_exact_and_sorted():
    W = random_weights(20, 8, 3, seed=7)
    W[0] = 0
    W[0, 5] = 1.0  # a single-influence row gets padding
    index, weight = skinning_influences(W, torch.float64)
    assert index.shape == (20, 3)
    assert torch.all(weight[:, :-1] >= weight[:, 1:])
    dense = torch.zeros(20, 8, dtype=torch.float64).scatter_add(1, index, weight)
    torch.testing.assert_close(dense, torch.as_tensor(W))
    assert index[0].tolist() == [5, 5, 5]


def test_unknown_method_raises():
    with pytest.raises(EgorelightError, match="skinning method"):
        skin_points(torch.zeros(1, 3), torch.eye(4)[None], np.ones((1, 1)), "xyz")


@pytest.mark.parametrize("method", ["dqs", "lbs"])
def test_skinning_gradcheck_through_fk(method):
    char = synth.make_character()
    points = torch.as_tensor(char.vertices[::37])
    weights = char.skin_weights[::37].copy()

    def posed(params):
        theta = torch.cat([torch.zeros(4, dtype=params.dtype), params])
        return skin_points(points, bone_transforms(theta, char), weights, method)

    params = torch.tensor([0.3, -0.4, 0.8], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(posed, (params,))


def test_skinning_gradcheck_wrt_points_and_weights():
    T = random_rigid(3, seed=8)
    points = torch.randn(6, 3, dtype=torch.float64, requires_grad=True)
    W = torch.as_tensor(random_weights(6, 3, 3, seed=9)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p, w: dual_quaternion_skinning(p, T, w), (points, W))
    assert torch.autograd.gradcheck(lambda p, w: linear_blend_skinning(p, T, w), (points, W))


def test_tube_dqs_float32_matches_float64():
    char = synth.make_character()
    theta = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, -0.6, 1.2], dtype=torch.float64)
    out64 = skin_points(torch.as_tensor(char.vertices), bone_transforms(theta, char), char.skin_weights)
    out32 = skin_points(torch.as_tensor(char.vertices, dtype=torch.float32), bone_transforms(theta.float(), char), char.skin_weights)
    torch.testing.assert_close(out32.double(), out64, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("method", ["dqs", "lbs"])
def test_sparse_plan_and_gather_paths_agree(method):
    """Constant weights use sparse matrices; weights requiring grad use a gather: same result."""
    T = random_rigid(6, seed=10, batch=(2, 3))
    W = random_weights(30, 6, 4, seed=11)
    points = torch.randn(30, 3, dtype=torch.float64)
    a = skin_points(points, T, W, method)  # numpy: cached sparse plan
    b = skin_points(points, T, torch.as_tensor(W), method)  # tensor without grad: sparse plan
    c = skin_points(points, T, torch.as_tensor(W).requires_grad_(True), method)  # gather
    assert a.shape == (2, 3, 30, 3)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(a, c)
