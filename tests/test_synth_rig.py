"""The simulated rig: HMD geometry, markers and cameras, studio cameras, appearance, CLI errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from egorelight_cli.cli import main
from egorelight_cli.config import resolve_config
from egorelight_cli.geometry.cameras import Camera, project, project_world
from egorelight_cli.geometry.embedded_graph import pose_character
from egorelight_cli.geometry.raycast import RayCaster
from egorelight_cli.geometry.skeleton import keypoint_positions
from egorelight_cli.io.character import write_character_npz
from egorelight_cli.synth.appearance import SHIRT, SKIN, TROUSERS, make_appearance
from egorelight_cli.synth.hmd import DOWN_ROLES, EGO_ROLES, VISOR_SIZE, make_hmd
from egorelight_cli.synth.rig import (
    STUDIO_ROLE,
    TRACKING_ROLE,
    held_out_cameras,
    make_lightstage,
    studio_cameras,
)
from egorelight_cli.synth.scene import joint_transforms, place


@pytest.fixture(scope="module")
def cfg():
    return resolve_config("synth", "cpu")


@pytest.fixture(scope="module")
def hmd(character, cfg):
    return make_hmd(character, cfg.hmd, seed=3)


def test_markers_lie_on_the_visor_and_face_outwards(hmd):
    half = np.asarray(VISOR_SIZE) / 2
    corners = np.concatenate(list(hmd.markers.values()))
    on_face = np.isclose(np.abs(corners), half, atol=1e-9)  # on one face of the visor box ...
    assert np.all(on_face.sum(axis=1) == 1) and np.all(np.abs(corners) <= half + 1e-9)  # ... inside its edges
    for corners in hmd.markers.values():
        side = np.linalg.norm(np.diff(np.vstack([corners, corners[:1]]), axis=0), axis=1)
        np.testing.assert_allclose(side, hmd.marker_length, atol=1e-9)
        # OpenCV order is clockwise seen from outside: the normal (TL->TR) x (TL->BL) points inwards
        inward = np.cross(corners[1] - corners[0], corners[3] - corners[0])
        assert inward @ corners.mean(axis=0) < 0  # the visor centre is the HMD origin


def test_ego_cameras_sit_outside_the_visor_and_see_their_field_of_view(hmd, character):
    hi = np.asarray(VISOR_SIZE) / 2
    lo = -hi
    for role, cam in hmd.cameras.items():
        centre = -cam.T_cam_from_hmd[:3, :3].T @ cam.T_cam_from_hmd[:3, 3]
        inside = np.all((centre > lo + 1e-4) & (centre < hi - 1e-4))
        assert not inside, role
    for role in DOWN_ROLES:
        cam = hmd.cameras[role]
        # a ray 94 degrees off-axis still lands inside the image
        direction = np.array([np.sin(np.radians(94)), 0.0, np.cos(np.radians(94))])
        px, valid = project(direction[None], cam.K, cam.dist, cam.model, return_valid=True)
        assert valid[0] and 0 <= px[0, 0] < cam.width
    # the down cameras see the wearer's chest and hands at the rest pose
    theta = character.rest_theta[None]
    T_world_from_hmd = hmd.world_from_hmd(joint_transforms(character, theta))[0]
    kp = keypoint_positions(torch.as_tensor(character.rest_theta), character).numpy()
    cam = hmd.cameras["down_left"].camera(T_world_from_hmd)
    names = character.keypoint_names
    px, valid = project_world(cam, kp[[names.index("LeftHand"), names.index("RightHand")]], return_valid=True)
    assert valid.all() and np.all((px >= 0) & (px < [cam.width, cam.height]))


def test_hmd_sits_on_the_face(hmd, character):
    theta = torch.as_tensor(character.rest_theta)
    body = pose_character(character, theta).numpy()
    T = hmd.world_from_hmd(joint_transforms(character, character.rest_theta[None]))[0]
    visor = place(hmd.mesh, T)
    caster = RayCaster(body, character.faces)
    # from the visor's back face towards the head, the face is within a few centimetres
    back = T[:3, 3] + T[:3, 2] * 0.045
    hit = caster.first_hit(back[None], T[:3, 2][None])
    assert hit.hit[0] and hit.distance[0] < 0.05
    assert visor[:, 1].min() > 1.4  # at head height


def test_hmd_json_describes_the_cameras(hmd):
    data = hmd.to_json()
    assert [c["role"] for c in data["cameras"]] == list(EGO_ROLES)
    for entry in data["cameras"]:
        cam = Camera.from_dict(entry, T_cam_from_world=np.eye(4))
        assert cam.model == ("fisheye" if entry["role"] in DOWN_ROLES else "pinhole")
    truth = hmd.cameras["down_left"]
    assert not np.allclose(truth.T_cam_from_hmd, truth.T_cam_from_hmd_nominal)  # unknown mounting error
    error = np.linalg.norm(truth.T_cam_from_hmd[:3, 3] - truth.T_cam_from_hmd_nominal[:3, 3])
    assert error < 0.02


def test_studio_cameras_look_at_the_subject(cfg):
    cameras = studio_cameras(cfg.studio, seed=0)
    roles = [r for _, r in cameras]
    assert roles.count(STUDIO_ROLE) == cfg.studio.num_cameras and roles.count(TRACKING_ROLE) == cfg.studio.tracking.num_cameras
    for cam, role in cameras:
        target = np.array(cfg.studio.target if role == STUDIO_ROLE else cfg.studio.tracking.target)
        px = project_world(cam, target)
        assert np.all(np.abs(px - [cam.width / 2, cam.height / 2]) < 0.15 * cam.height)
    held = held_out_cameras(cameras, 3)
    assert len(set(held)) == 3 and all(n.startswith("cam") for n in held)
    stage = make_lightstage(cfg.lights, seed=0)
    assert stage.num_lights == cfg.lights.num_lights and 0.8 < stage.rgb_gain.min() <= stage.rgb_gain.max() < 1.2


def test_appearance_has_skin_pattern_and_a_shiny_garment(character):
    appearance = make_appearance(character, 128, seed=5)
    assert appearance.albedo.shape == (128, 128, 3)
    assert 0 < appearance.albedo.min() and appearance.albedo.max() <= 0.95
    ks = appearance.specular[..., 0]
    material = appearance.material
    assert ks[material == TROUSERS].mean() > 3 * ks[material == SHIRT].mean()
    assert ks[material == SKIN].mean() > ks[material == SHIRT].mean()
    shirt = appearance.albedo[(material == SHIRT) & appearance.coverage]
    assert shirt.std(axis=0).max() > 0.05  # patterned
    other = make_appearance(character, 128, seed=6)
    assert not np.allclose(appearance.albedo, other.albedo)


def test_synth_refuses_a_character_without_the_motion_dofs(character, tmp_path, capsys):
    renamed = dataclasses.replace(character, skeleton=dataclasses.replace(
        character.skeleton, dof_names=tuple(f"dof{i}" for i in range(character.skeleton.num_dofs))))
    path = tmp_path / "odd.npz"
    write_character_npz(path, renamed)
    with pytest.raises(SystemExit) as exit_info:
        main(["synth", "--preset", "tiny", "--character", str(path), "--out", str(tmp_path / "cap")])
    assert exit_info.value.code == 2
    assert "--motion" in capsys.readouterr().err
    assert not (tmp_path / "cap").exists()
