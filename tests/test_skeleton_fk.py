"""Forward kinematics (DDC semantics) against hand-computed chains."""

from __future__ import annotations

import math

import geometry_synthetic as synth
import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.skeleton import (
    bone_transforms,
    forward_kinematics,
    joint_params,
    joint_positions,
    keypoint_positions,
)
from egorelight_cli.structures.skeleton import PRISMATIC, REVOLUTE, Skeleton


def three_joint_chain() -> Skeleton:
    """j0 revolute z at (1,0,0); j1 prismatic x at (0,2,0); j2 revolute x at (0,0,3).

    DoF 'bend' drives j0 (weight 1) and j2 (weight 0.5); DoF 'slide' drives j1 (weight 1).
    """
    return Skeleton(
        joint_names=("j0", "j1", "j2"),
        parents=np.array([-1, 0, 1]),
        joint_types=np.array([REVOLUTE, PRISMATIC, REVOLUTE]),
        axes=np.array([[0, 0, 1], [1, 0, 0], [1, 0, 0]], dtype=float),
        offsets=np.array([[1, 0, 0], [0, 2, 0], [0, 0, 3]], dtype=float),
        dof_names=("bend", "slide"),
        dof_joint_weights=np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]]),
        dof_limits=np.array([[-1.0, 1.0], [0.0, 0.1]]),  # FK ignores limits
    )


def Rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def Rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_three_joint_chain_by_hand(dtype):
    sk = three_joint_chain()
    theta = torch.tensor([math.pi / 2, 0.5], dtype=dtype)  # bend 90 deg (j2 gets 45 deg), slide 0.5 m
    torch.testing.assert_close(joint_params(theta, sk), torch.tensor([math.pi / 2, 0.5, math.pi / 4], dtype=dtype))
    G = forward_kinematics(theta, sk)
    assert G.shape == (3, 4, 4) and G.dtype == dtype
    # j0: T(1,0,0) Rz(90)
    # j1: + Rz(90) (0.5, 2, 0) = (-2, 0.5, 0) -> origin (-1, 0.5, 0), rotation Rz(90)
    # j2: + Rz(90) (0, 0, 3) -> origin (-1, 0.5, 3), rotation Rz(90) Rx(45)
    expected_origins = torch.tensor([[1.0, 0, 0], [-1.0, 0.5, 0], [-1.0, 0.5, 3.0]], dtype=dtype)
    expected_R = torch.as_tensor(np.stack([Rz(math.pi / 2), Rz(math.pi / 2), Rz(math.pi / 2) @ Rx(math.pi / 4)]), dtype=dtype)
    tol = {"atol": 1e-6, "rtol": 1e-6}
    torch.testing.assert_close(G[:, :3, 3], expected_origins, **tol)
    torch.testing.assert_close(G[:, :3, :3], expected_R, **tol)
    torch.testing.assert_close(G[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=dtype).expand(3, 4))
    # a point (0,1,0) in j2's frame: Rx(45) -> (0, .707, .707); Rz(90) -> (-.707, 0, .707)
    p = G[2, :3, :3] @ torch.tensor([0.0, 1, 0], dtype=dtype) + G[2, :3, 3]
    s = math.sqrt(0.5)
    torch.testing.assert_close(p, torch.tensor([-1 - s, 0.5, 3 + s], dtype=dtype), **tol)


def test_rest_pose_is_cumulative_offsets():
    sk = three_joint_chain()
    G = forward_kinematics(torch.zeros(2, dtype=torch.float64), sk)
    torch.testing.assert_close(G[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    torch.testing.assert_close(G[:, :3, 3], torch.tensor([[1.0, 0, 0], [1, 2, 0], [1, 2, 3]], dtype=torch.float64))


def test_prismatic_axis_is_not_normalised():
    sk = Skeleton(("p",), np.array([-1]), np.array([PRISMATIC]), np.array([[2.0, 0, 0]]), np.zeros((1, 3)),
                  ("d",), np.ones((1, 1)), np.array([[-np.inf, np.inf]]))
    torch.testing.assert_close(joint_positions(torch.tensor([0.25]), sk), torch.tensor([[0.5, 0.0, 0.0]]))


def test_batched_numpy_and_dtypes():
    sk = three_joint_chain()
    theta = np.random.default_rng(0).normal(size=(2, 3, 2))
    G64 = forward_kinematics(theta, sk)  # numpy -> float64
    assert G64.shape == (2, 3, 3, 4, 4) and G64.dtype == torch.float64
    G32 = forward_kinematics(torch.as_tensor(theta, dtype=torch.float32), sk)
    torch.testing.assert_close(G32.double(), G64, atol=1e-5, rtol=1e-5)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(forward_kinematics(torch.as_tensor(theta[i, j]), sk), G64[i, j])


def test_wrong_theta_shape_raises():
    with pytest.raises(EgorelightError, match="DoFs"):
        forward_kinematics(torch.zeros(3), three_joint_chain())


def test_fk_gradcheck():
    sk = three_joint_chain()
    theta = torch.tensor([[0.3, 0.2], [-1.0, 0.4]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: forward_kinematics(t, sk), (theta,))
    tube = synth.make_skeleton()
    theta = torch.randn(7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: forward_kinematics(t, tube), (theta,))


def test_keypoints_and_bone_transforms_on_tube():
    rest = np.array([0.1, 0.2, 0.3, 0.4, 0.5, -0.3, 0.7])
    char = synth.make_character(rest_theta=rest)
    L = synth.BONE_LENGTH
    # at theta = 0: keypoints are the joint origins (0,0,0), (0,L,0), tip (0,3L,0)
    kp = keypoint_positions(torch.zeros(7, dtype=torch.float64), char)
    torch.testing.assert_close(kp, torch.tensor([[0, 0, 0], [0, L, 0], [0, 3 * L, 0]], dtype=torch.float64))
    # a root translation moves every keypoint
    kp_t = keypoint_positions(torch.tensor([1.0, 2.0, 3.0, 0, 0, 0, 0], dtype=torch.float64), char)
    torch.testing.assert_close(kp_t, kp + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    # bend0 = 90 deg: the chain lies along -x
    kp_b = keypoint_positions(torch.tensor([0, 0, 0, 0, math.pi / 2, 0, 0], dtype=torch.float64), char)
    torch.testing.assert_close(kp_b, torch.tensor([[0, 0, 0], [-L, 0, 0], [-3 * L, 0, 0]], dtype=torch.float64))
    # skinning transforms are the identity at the rest pose, for both dtypes
    for dtype in (torch.float32, torch.float64):
        T = bone_transforms(torch.as_tensor(rest, dtype=dtype), char)
        assert T.shape == (3, 4, 4) and T.dtype == dtype
        torch.testing.assert_close(T, torch.eye(4, dtype=dtype).expand(3, 4, 4), atol=1e-6, rtol=1e-6)
    # and G(theta) @ inv(G(rest)) otherwise
    theta = torch.tensor([0.0, 0, 0, 0, 0.3, 0.2, 0.1], dtype=torch.float64)
    G = forward_kinematics(theta, char.skeleton)[list(synth.BONE_JOINTS)]
    G0 = forward_kinematics(torch.as_tensor(rest), char.skeleton)[list(synth.BONE_JOINTS)]
    torch.testing.assert_close(bone_transforms(theta, char), G @ torch.linalg.inv(G0))
