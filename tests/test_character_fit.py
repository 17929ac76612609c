"""`egorelight character fit-scan`: registration of the template to a scan, with an exact answer.

The known target is the default character with per-bone length/girth scaling applied through its
own skinning (true joints: its skeleton with scaled offsets) plus a smooth warp of a few cm; the
scan is that surface re-tessellated (midpoint subdivision + quadric decimation), with 1 mm
noise and a hole.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from egorelight_cli.geometry import registration as reg
from egorelight_cli.geometry.skeleton import forward_kinematics, keypoint_positions
from egorelight_cli.geometry.skeleton_refit import offsets_for_positions, refit_rig, regularised_affine, with_offsets
from egorelight_cli.io.meshes import write_obj, write_ply
from egorelight_cli.stages.character_commands import load_character, rest_pose_error_m


# ------------------------------------------------------------------------------ the known target
def _warp(x: np.ndarray) -> np.ndarray:
    """A smooth warp of a few cm: a sway, a twist-like shear and a 3 cm belly on the front (-Z)."""
    belly = 0.03 * np.exp(-((x[:, 1] - 1.0) / 0.12) ** 2) * np.exp(-(x[:, 0] / 0.15) ** 2) / (1 + np.exp(40 * x[:, 2]))
    return x + np.stack([0.015 * np.sin(2.5 * x[:, 1] + 0.3), 0.01 * np.cos(3 * x[:, 0]), 0.01 * x[:, 0] - belly], 1)


def known_target(character, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V,3), joints (J,3)) of the default character re-proportioned: per joint group a
    length factor (+-4%) on the offsets below it and a girth factor (+-6%) across its bone, height
    +-3%, skinned with the character's weights, then :func:`_warp`."""
    rng = np.random.default_rng(seed)
    sk = character.skeleton
    rest = torch.as_tensor(character.rest_theta)
    joints = forward_kinematics(rest, sk).numpy()[:, :3, 3]
    base = [name.split("_")[0] for name in sk.joint_names]
    length = {b: 1 + rng.uniform(-0.04, 0.04) for b in sorted(set(base))}
    girth = {b: 1 + rng.uniform(-0.06, 0.06) for b in sorted(set(base))}
    height = 1 + rng.uniform(-0.03, 0.03)
    scale = np.array([height * (length[base[p]] if p >= 0 else 1.0) for p in sk.parents])
    new_joints = forward_kinematics(rest, with_offsets(sk, sk.offsets * scale[:, None])).numpy()[:, :3, 3]
    V, W = character.vertices, character.skin_weights
    out = np.zeros_like(V)
    for b, j in enumerate(character.skin_bone_joints):
        m = W[:, b] > 0
        if not m.any():
            continue
        local = V[m] - joints[j]
        axis = np.linalg.eigh((local * W[m, b, None]).T @ local)[1][:, -1]  # the bone's long axis
        along = np.outer(axis, axis)
        S = girth[base[j]] * (np.eye(3) - along) + height * length[base[j]] * along
        out[m] += W[m, b, None] * (new_joints[j] + local @ S.T)
    return _warp(out), _warp(new_joints)


def retessellated_scan(vertices: np.ndarray, faces: np.ndarray, seed: int = 3, target_faces: int = 12000):
    """(vertices, faces) of another tessellation of the surface, 1 mm noise, a 4 cm hole in the back."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32)))
    ms.meshing_surface_subdivision_midpoint(iterations=1)
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=target_faces, preservetopology=True, optimalplacement=True)
    mesh = ms.current_mesh()
    v = np.asarray(mesh.vertex_matrix(), np.float64)
    f = np.asarray(mesh.face_matrix(), np.int64)
    v = v + np.random.default_rng(seed).normal(0.0, 0.001, v.shape)
    back = np.array([0.0, 1.2, v[:, 2].max()])
    f = f[np.linalg.norm(v[f].mean(axis=1) - back, axis=1) > 0.04]
    return v, f


@pytest.fixture(scope="module")
def target(character):
    vertices, joints = known_target(character)
    scan_v, scan_f = retessellated_scan(vertices, character.faces)
    return {"vertices": vertices, "joints": joints, "scan_vertices": scan_v, "scan_faces": scan_f}


@pytest.fixture(scope="module")
def fitted(target, tmp_path_factory):
    """One `character fit-scan --preset tiny` run on the target's scan (a PLY)."""
    from egorelight_cli.cli import main

    root = tmp_path_factory.mktemp("fit")
    scan = root / "scan.ply"
    write_ply(scan, target["scan_vertices"], target["scan_faces"])
    out = root / "character"
    with pytest.raises(SystemExit) as exit_info:
        main(["character", "fit-scan", "--scan", str(scan), "--out", str(out), "--preset", "tiny"])
    assert exit_info.value.code == 0
    return out


# ------------------------------------------------------------------------------------- (a) exact
def test_fit_recovers_the_known_template_and_joints(fitted, target, character):
    fit, _ = load_character(fitted)
    manifest = json.loads((fitted / "manifest.json").read_text())
    metrics = manifest["metrics"]
    assert fit.faces.shape == character.faces.shape and np.array_equal(fit.faces, character.faces)
    # the baseline: the default template only similarity-aligned to the scan
    stored = fit.extras["fit_scan"]["similarity"]
    similarity = reg.Similarity(stored["scale"], np.asarray(stored["rotation"]), np.asarray(stored["translation_m"]))
    assert similarity.scale == pytest.approx(metrics["similarity"]["scale"], rel=1e-5)
    baseline = np.linalg.norm(similarity.apply(character.vertices) - target["vertices"], axis=1).mean()
    error = np.linalg.norm(fit.vertices - target["vertices"], axis=1)
    assert error.mean() < 0.004, (error.mean(), baseline)
    assert error.mean() < 0.3 * baseline
    assert np.percentile(error, 95) < 0.01

    rest = torch.as_tensor(fit.rest_theta)
    joints = forward_kinematics(rest, fit.skeleton).numpy()[:, :3, 3]
    joint_error = np.linalg.norm(joints - target["joints"], axis=1)
    aligned_joints = similarity.apply(forward_kinematics(rest, character.skeleton).numpy()[:, :3, 3])
    joint_baseline = np.linalg.norm(aligned_joints - target["joints"], axis=1)
    assert joint_error.mean() < 0.006 and joint_error.max() < 0.015, (joint_error.mean(), joint_error.max())
    assert joint_error.mean() < 0.5 * joint_baseline.mean()
    # keypoints moved with their joints (the default's keypoints sit on them)
    keypoints = keypoint_positions(rest, fit).numpy()
    np.testing.assert_allclose(keypoints, joints[fit.keypoint_joints], atol=1e-9)

    # metrics: the fit is close to the scan both ways, far closer than the unfitted template
    for direction in ("template_to_scan", "scan_to_template"):
        assert metrics[f"fit_{direction}_mm"]["mean"] < 1.5
        assert metrics[f"fit_{direction}_mm"]["mean"] < 0.4 * metrics[f"unfitted_{direction}_mm"]["mean"]
        assert metrics[f"fit_{direction}_mm"]["p95"] >= metrics[f"fit_{direction}_mm"]["mean"]
    assert metrics["rest_pose_skinning_error_mm"] < 1e-6 and rest_pose_error_m(fit) < 1e-9
    assert metrics["iterations"]["graph_gauss_newton"] > 0 and manifest["timing"]["graph_fit_s"] > 0
    assert metrics["joint_displacement_after_alignment_mm"]["mean"] > 0


def test_fit_carries_over_weights_and_rebuilds_the_graph(fitted, character):
    fit, _ = load_character(fitted)
    np.testing.assert_array_equal(fit.skin_weights, character.skin_weights)
    np.testing.assert_array_equal(fit.segmentation, character.segmentation)
    np.testing.assert_array_equal(fit.face_uvs, character.face_uvs)
    assert fit.graph.num_nodes == character.graph.num_nodes
    assert fit.skeleton.joint_names == character.skeleton.joint_names
    assert not np.array_equal(fit.graph.node_vertex, character.graph.node_vertex)  # chosen on the new surface
    np.testing.assert_allclose(fit.graph.vertex_node_weight.sum(axis=1), 1.0)


# ------------------------------------------------------------------------------ (b) the CLI round trip
def test_cli_round_trip_is_a_character_that_preview_accepts(fitted, run, tmp_path):
    from egorelight_cli.artifacts import open_artifact
    from egorelight_cli.io.images import read_image

    artifact = open_artifact(fitted, kind="character", verify=True)
    assert {o["name"] for o in artifact.manifest["outputs"]} >= {"character.npz", "template.obj", "preview.png"}
    assert read_image(fitted / "preview.png").shape[:2] == (640, 3 * 384)  # scan, fit front, fit side
    png = tmp_path / "fit.png"
    result = run("character", "preview", str(fitted), "--out", str(png))
    assert result.returncode == 0, result.stderr
    assert read_image(png).shape[0] > 0
    scan = artifact.manifest["sources"][0]["path"]
    again = run("character", "fit-scan", "--scan", scan, "--out", str(fitted), "--preset", "tiny")
    assert again.returncode == 0 and "up to date" in again.stderr


# ------------------------------------------------------------------------------------ (c) bad input
def _scan_files(tmp_path, character):
    """{case: (path, expected words)} of bad scans."""
    v, f = character.vertices, character.faces
    files = {}

    def mesh(name, vertices, faces=f):
        path = tmp_path / name
        (write_ply if name.endswith(".ply") else write_obj)(path, vertices, faces)
        return path

    files["missing"] = (tmp_path / "nothing.ply", "scan not found")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\x00\x01garbage")
    files["unreadable"] = (garbage, "cannot read mesh")
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    files["empty"] = (empty, "no vertices")
    files["no_faces"] = (mesh("points.ply", v, None), "no faces")
    nan = v.copy()
    nan[10] = np.nan
    files["nan"] = (mesh("nan.obj", nan), "NaN")
    files["millimetres"] = (mesh("mm.ply", v * 1000.0), "metres")
    files["far"] = (mesh("far.ply", v + [5.0, 0.0, 0.0]), "from the template")
    import trimesh

    blob = trimesh.creation.icosphere(subdivisions=3, radius=0.85)
    files["not_a_body"] = (mesh("ball.ply", blob.vertices + [0.0, 0.85, 0.0], blob.faces), "after alignment")
    text = tmp_path / "scan.txt"
    text.write_text("not a mesh")
    files["suffix"] = (text, ".ply or .obj")
    return files


def test_bad_scans_are_one_line_errors_without_output(tmp_path, run, character):
    for case, (path, words) in _scan_files(tmp_path, character).items():
        out = tmp_path / f"out_{case}"
        result = run("character", "fit-scan", "--scan", str(path), "--out", str(out), "--preset", "tiny")
        assert result.returncode == 2, (case, result.stderr)
        line = result.stderr.strip()
        assert line.startswith("egorelight: error:") and words in line and path.name in line, (case, line)
        assert "Traceback" not in result.stderr and len(line.splitlines()) == 1, (case, line)
        assert not out.exists() and not list(tmp_path.glob(f".out_{case}*")), case


# ----------------------------------------------------------------------------------- core pieces
def test_similarity_transform_is_exact_and_affine_regularised():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(50, 3))
    R = reg.Rotation.from_rotvec([0.05, -0.1, 0.02]).as_matrix()
    target = 1.07 * source @ R.T + [0.1, -0.2, 0.3]
    fit = reg.similarity_transform(source, target)
    np.testing.assert_allclose(fit.apply(source), target, atol=1e-9)
    assert fit.rotation_deg == pytest.approx(np.degrees(np.linalg.norm([0.05, -0.1, 0.02])))
    # an affine map is recovered where points spread, the prior kept across a flat cloud
    A = np.diag([1.1, 0.9, 1.0])
    flat = source * [1.0, 1.0, 1e-4]
    A_fit, c = regularised_affine(flat, flat @ A.T + 0.5, np.ones(50), np.eye(3), 0.01)
    np.testing.assert_allclose(A_fit[:2, :2], A[:2, :2], atol=1e-3)
    assert A_fit[2, 2] == pytest.approx(1.0, abs=1e-3)


def _rig_follows_a_similarity(character):
    """A similarity of the template moves joints and keypoints (given offsets) by that similarity,
    in the skeleton's own parameterisation (rotated joint frames, non-zero rest pose for DDC)."""
    rest = torch.as_tensor(character.rest_theta)
    offsets = np.random.default_rng(2).normal(0.0, 0.02, character.keypoint_offsets.shape)
    character = dataclasses.replace(character, keypoint_offsets=offsets)
    G = forward_kinematics(rest, character.skeleton).numpy()
    wanted = G[:, :3, 3] + np.random.default_rng(1).normal(0, 0.01, (character.skeleton.num_joints, 3))
    moved = with_offsets(character.skeleton, offsets_for_positions(character.skeleton, G, wanted))
    np.testing.assert_allclose(forward_kinematics(rest, moved).numpy()[:, :3, 3], wanted, atol=1e-12)

    similarity = reg.Similarity(1.05, reg.Rotation.from_rotvec([0.02, 0.1, -0.03]).as_matrix(), np.array([0.1, 0.0, -0.2]))
    rig = refit_rig(character, similarity.apply(character.vertices), similarity.scale * similarity.R)
    np.testing.assert_allclose(rig.joints_after, similarity.apply(G[:, :3, 3]), atol=1e-9)
    refitted = dataclasses.replace(character, skeleton=rig.skeleton, keypoint_offsets=rig.keypoint_offsets)
    np.testing.assert_allclose(keypoint_positions(rest, refitted).numpy(),
                               similarity.apply(keypoint_positions(rest, character).numpy()), atol=1e-9)


def test_rig_follows_a_similarity(character):
    _rig_follows_a_similarity(character)


def test_rig_follows_a_similarity_on_a_ddc_skeleton(ddc_example):
    from egorelight_cli.io.ddc import read_ddc_character

    _rig_follows_a_similarity(read_ddc_character(ddc_example / "ddc.character"))


def test_closest_points_lie_on_the_surface():
    from egorelight_cli.geometry.pointcloud_ops import SurfaceDistance

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1], [1, 0, 1]], float)
    f = np.array([[0, 2, 1], [1, 2, 3]])
    points = np.array([[0.25, 0.3, 0.5], [2.0, -1.0, 0.5]])
    closest, face, distance = SurfaceDistance(v, f).closest(points)
    np.testing.assert_allclose(closest, [[0.25, 0, 0.5], [1.0, 0, 0.5]], atol=1e-12)
    np.testing.assert_allclose(distance, [0.3, np.sqrt(2.0)], atol=1e-12)
    assert face[0] in (0, 1) and face[1] == 1


def test_graph_jacobians_match_finite_differences(character):
    rng = np.random.default_rng(4)
    rest, graph = character.vertices, character.graph
    links, nodes = reg._Links.of(graph), rest[graph.node_vertex]
    state = reg.GraphState(reg.Rotation.from_rotvec(rng.normal(0, 0.1, (graph.num_nodes, 3))).as_matrix(),
                           rng.normal(0, 0.01, (graph.num_nodes, 3)))
    J = reg.graph_jacobian(rest, nodes, links, state)
    A, r = reg.arap_system(nodes, graph.edges, state)
    delta = np.zeros(6 * graph.num_nodes)
    delta[rng.choice(len(delta), 40, replace=False)] = rng.normal(0, 1e-6, 40)
    moved = reg._apply_update(state, delta)
    change = reg.deform(rest, nodes, links, moved) - reg.deform(rest, nodes, links, state)
    np.testing.assert_allclose(change.ravel(), J @ delta, atol=1e-11)
    np.testing.assert_allclose(reg.arap_system(nodes, graph.edges, moved)[1] - r, A @ delta, atol=1e-11)
