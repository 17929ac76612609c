"""Rotations, quaternions and dual quaternions against scipy and hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from egorelight_cli.geometry import rotations as rot

DTYPES = [torch.float32, torch.float64]


def _tol(dtype):
    return {"atol": 1e-5, "rtol": 1e-5} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-12}


def _random_axis_angle(n, seed=0, scale=2.0):
    return torch.as_tensor(np.random.default_rng(seed).normal(size=(n, 3)) * scale)


@pytest.mark.parametrize("dtype", DTYPES)
def test_axis_angle_matches_scipy(dtype):
    aa = _random_axis_angle(50)
    R = rot.axis_angle_to_matrix(aa.to(dtype))
    expected = torch.as_tensor(Rotation.from_rotvec(aa.numpy()).as_matrix(), dtype=dtype)
    torch.testing.assert_close(R, expected, **_tol(dtype))
    assert R.dtype == dtype


def test_axis_angle_batched_and_zero():
    aa = torch.zeros(2, 3, 3, dtype=torch.float64)
    R = rot.axis_angle_to_matrix(aa)
    assert R.shape == (2, 3, 3, 3)
    torch.testing.assert_close(R, torch.eye(3, dtype=torch.float64).expand(2, 3, 3, 3))


def test_axis_angle_gradient_at_and_near_zero():
    for value in (0.0, 1e-6, 1e-3, 0.7):
        aa = torch.full((2, 3), value, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(rot.axis_angle_to_matrix, (aa,))
    aa = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = rot.axis_angle_to_matrix(aa)
    (g,) = torch.autograd.grad(R[1, 0], aa)  # dR/domega at 0 is the skew generator: R[1,0] = omega_z
    torch.testing.assert_close(g, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_axis_angle_rotation_matches_vector_form():
    axis = torch.nn.functional.normalize(_random_axis_angle(10, seed=1), dim=-1)
    angle = torch.linspace(-3, 3, 10, dtype=torch.float64)
    torch.testing.assert_close(rot.axis_angle_rotation(axis, angle), rot.axis_angle_to_matrix(axis * angle[:, None]))


def test_matrix_to_axis_angle_roundtrip():
    aa = _random_axis_angle(40, seed=2, scale=1.0)
    aa = aa * (torch.rand(40, 1, dtype=torch.float64) * 3.0 / aa.norm(dim=-1, keepdim=True))  # angles < pi
    torch.testing.assert_close(rot.matrix_to_axis_angle(rot.axis_angle_to_matrix(aa)), aa, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(rot.matrix_to_axis_angle(torch.eye(3, dtype=torch.float64)), torch.zeros(3, dtype=torch.float64))


@pytest.mark.parametrize("dtype", DTYPES)
def test_euler_is_rz_ry_rx(dtype):
    e = torch.as_tensor(np.random.default_rng(3).uniform(-3, 3, size=(30, 3)))
    R = rot.euler_to_matrix(e.to(dtype))
    # scipy upper-case = intrinsic axes: intrinsic Z-Y-X with angles (z, y, x) is Rz @ Ry @ Rx
    expected = Rotation.from_euler("ZYX", e.numpy()[:, ::-1]).as_matrix()
    torch.testing.assert_close(R, torch.as_tensor(expected, dtype=dtype), **_tol(dtype))
    # hand value: rz = 90 deg maps x to y
    R90 = rot.euler_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=dtype))
    torch.testing.assert_close(R90 @ torch.tensor([1.0, 0, 0], dtype=dtype), torch.tensor([0.0, 1, 0], dtype=dtype), **_tol(dtype))


def test_matrix_to_euler_roundtrip():
    rng = np.random.default_rng(4)
    e = torch.as_tensor(np.stack([rng.uniform(-3, 3, 30), rng.uniform(-1.5, 1.5, 30), rng.uniform(-3, 3, 30)], 1))
    torch.testing.assert_close(rot.matrix_to_euler(rot.euler_to_matrix(e)), e, atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quaternion_matrix_roundtrip(dtype):
    R = torch.as_tensor(Rotation.random(100, random_state=5).as_matrix(), dtype=dtype)
    q = rot.matrix_to_quaternion(R)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(100, dtype=dtype), **_tol(dtype))
    torch.testing.assert_close(rot.quaternion_to_matrix(q), R, **_tol(dtype))
    # agrees with scipy up to sign (scipy is x, y, z, w)
    qs = torch.as_tensor(Rotation.from_matrix(R.double().numpy()).as_quat()[:, [3, 0, 1, 2]], dtype=dtype)
    dots = (q * qs).sum(-1).abs()
    torch.testing.assert_close(dots, torch.ones(100, dtype=dtype), **_tol(dtype))


def test_matrix_to_quaternion_half_turns():
    """180-degree rotations (trace = -1) are the ill-conditioned case for the naive formula."""
    for axis in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]):
        a = torch.tensor(axis, dtype=torch.float64)
        R = rot.axis_angle_to_matrix(a / a.norm() * math.pi)
        torch.testing.assert_close(rot.quaternion_to_matrix(rot.matrix_to_quaternion(R)), R)


def test_matrix_to_quaternion_gradcheck():
    R = torch.as_tensor(Rotation.random(4, random_state=6).as_matrix()).requires_grad_(True)
    assert torch.autograd.gradcheck(rot.matrix_to_quaternion, (R,))


def test_quaternion_multiply_composes_rotations():
    Ra = torch.as_tensor(Rotation.random(20, random_state=7).as_matrix())
    Rb = torch.as_tensor(Rotation.random(20, random_state=8).as_matrix())
    qa, qb = rot.matrix_to_quaternion(Ra), rot.matrix_to_quaternion(Rb)
    torch.testing.assert_close(rot.quaternion_to_matrix(rot.quaternion_multiply(qa, qb)), Ra @ Rb)
    v = torch.randn(20, 3, dtype=torch.float64)
    torch.testing.assert_close(rot.quaternion_rotate(qa, v), (Ra @ v[..., None])[..., 0])
    # hand value: i * j = k
    i, j = torch.tensor([0.0, 1, 0, 0]), torch.tensor([0.0, 0, 1, 0])
    torch.testing.assert_close(rot.quaternion_multiply(i, j), torch.tensor([0.0, 0, 0, 1]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_dual_quaternion_roundtrip(dtype):
    R = torch.as_tensor(Rotation.random(30, random_state=9).as_matrix(), dtype=dtype)
    t = torch.as_tensor(np.random.default_rng(10).normal(size=(30, 3)), dtype=dtype)
    T = rot.make_transform(R, t)
    real, dual = rot.dual_quaternion_from_rigid(T)
    torch.testing.assert_close((real * dual).sum(-1), torch.zeros(30, dtype=dtype), **_tol(dtype))  # unit DQ
    torch.testing.assert_close(rot.rigid_from_dual_quaternion(real, dual), T, **_tol(dtype))
    # -q is the same transform
    torch.testing.assert_close(rot.rigid_from_dual_quaternion(-real, -dual), T, **_tol(dtype))
    p = torch.randn(30, 3, dtype=dtype)
    torch.testing.assert_close(rot.dual_quaternion_transform_points(real, dual, p), rot.transform_points(T, p), **_tol(dtype))


def test_invert_rigid():
    R = torch.as_tensor(Rotation.random(5, random_state=11).as_matrix())
    T = rot.make_transform(R, torch.randn(5, 3, dtype=torch.float64))
    torch.testing.assert_close(rot.invert_rigid(T) @ T, torch.eye(4, dtype=torch.float64).expand(5, 4, 4))
    # numpy in, numpy out: the same numbers, and the same as a general matrix inverse
    inverse = rot.invert_rigid(T.numpy())
    assert isinstance(inverse, np.ndarray) and inverse.dtype == np.float64
    np.testing.assert_allclose(inverse, rot.invert_rigid(T).numpy(), atol=1e-12)
    np.testing.assert_allclose(inverse, np.linalg.inv(T.numpy()), atol=1e-10)


def test_make_transform_broadcasts():
    T = rot.make_transform(torch.eye(3), torch.zeros(4, 3))
    assert T.shape == (4, 4, 4)
    torch.testing.assert_close(T, torch.eye(4).expand(4, 4, 4))


def test_camera_centre_is_the_point_the_transform_maps_to_the_origin():
    R = Rotation.from_rotvec(np.random.default_rng(3).normal(size=(4, 3))).as_matrix()
    centres = np.random.default_rng(4).normal(size=(4, 3))
    T_cam_from_x = np.tile(np.eye(4), (4, 1, 1))
    T_cam_from_x[:, :3, :3] = R
    T_cam_from_x[:, :3, 3] = -np.einsum("nij,nj->ni", R, centres)  # t = -R c
    np.testing.assert_allclose(rot.camera_centre(T_cam_from_x), centres, atol=1e-12)
    np.testing.assert_allclose(rot.camera_centre(T_cam_from_x[0]), centres[0], atol=1e-12)
