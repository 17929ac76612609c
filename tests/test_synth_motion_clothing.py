"""The motion library and the clothing model of the simulator."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from egorelight_cli.config import resolve_config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.skeleton import keypoint_positions
from egorelight_cli.geometry.subdivision import unique_edges
from egorelight_cli.synth.clothing import ClothingModel
from egorelight_cli.synth.motions import (
    MOTIONS,
    SCRIPTED,
    Segment,
    check_motion_dofs,
    compose_motion,
)
from egorelight_cli.synth.sequences import plan_sequence


def test_every_motion_type_is_finite_within_limits_and_grounded(character):
    limits = character.skeleton.dof_limits
    names = character.keypoint_names
    for motion in MOTIONS:
        theta = compose_motion(character, [Segment(motion, 3.0)], fps=10, num_frames=30, seed=1)
        assert np.isfinite(theta).all()
        assert np.all(theta >= limits[:, 0] - 1e-9) and np.all(theta <= limits[:, 1] + 1e-9), motion
        kp = keypoint_positions(torch.as_tensor(theta), character).numpy()
        # lowest foot point: ankles 72 mm and toes 16 mm above the floor at rest
        feet = np.stack([kp[:, names.index(f"{s}Foot"), 1] - 0.072 for s in ("Left", "Right")]
                        + [kp[:, names.index(f"{s}ToeBase"), 1] - 0.016 for s in ("Left", "Right")], 1)
        assert np.all(feet.min(axis=1) > -1e-6), motion  # never below the floor
        if motion != "celebrating":  # jumps
            assert np.allclose(feet.min(axis=1), 0, atol=1e-6), motion  # and on it


def test_motion_instances_differ_by_seed_and_types_differ(character):
    a = compose_motion(character, [Segment("waving", 2.0)], 10, 20, seed=1)
    b = compose_motion(character, [Segment("waving", 2.0)], 10, 20, seed=2)
    c = compose_motion(character, [Segment("boxing", 2.0)], 10, 20, seed=1)
    assert not np.allclose(a, b) and not np.allclose(a, c)
    again = compose_motion(character, [Segment("waving", 2.0)], 10, 20, seed=1)
    np.testing.assert_array_equal(a, again)


def test_hand_motions_move_the_fingers(character):
    theta = compose_motion(character, [Segment("typing", 3.0)], 30, 90, seed=0)
    fingers = [character.skeleton.dof_index(f"left_{f}_flex1") for f in ("index", "middle", "ring", "pinky")]
    assert np.all(theta[:, fingers].std(axis=0) > 0.05)
    fist = compose_motion(character, [Segment("boxing", 1.0)], 10, 10, seed=0)
    assert np.all(fist[:, fingers] < -1.0)  # hinges curl with negative values


def test_segments_are_cross_faded_smoothly(character):
    theta = compose_motion(character, [Segment(m, 1.0) for m in SCRIPTED[:6]], fps=30, num_frames=180, seed=3)
    rotations = [i for i, n in enumerate(character.skeleton.dof_names) if not n.startswith("translate")]
    step = np.abs(np.diff(theta[:, rotations], axis=0))
    assert step.max() < 0.6  # rad per frame at 30 fps (punches and kicks are fast): no jumps
    heading = character.skeleton.dof_index("rotate_y")
    assert np.abs(np.diff(theta[:, heading])).max() < 0.3
    position = theta[:, [character.skeleton.dof_index("translate_x"), character.skeleton.dof_index("translate_z")]]
    assert np.abs(np.diff(position, axis=0)).max() < 0.08 and np.abs(position).max() < 0.7  # stays in the dome


def test_character_without_the_dof_names_needs_a_motion_file(character):
    renamed = dataclasses.replace(character, skeleton=dataclasses.replace(
        character.skeleton, dof_names=tuple(f"dof{i}" for i in range(character.skeleton.num_dofs))))
    with pytest.raises(EgorelightError, match="--motion"):
        check_motion_dofs(renamed)
    # with a motion file the library is not needed
    cfg = resolve_config("synth", "tiny")
    motion = np.zeros((5, character.skeleton.num_dofs))
    motion[:, 0] = np.arange(5)
    plan = plan_sequence("ego_train", cfg, renamed, 0, ["a"], ["b"], ["c"], [], motion_theta=motion)
    assert np.allclose(plan.theta[:, 0], np.arange(plan.num_frames) % 5)


# ------------------------------------------------------------------------------------ clothing
def _pcs(values: np.ndarray, k: int = 5) -> np.ndarray:
    """(T,k) the temporal principal components: the leading left singular vectors of the centred
    (T, V*3) values, by a truncated SVD (the full one took ~25 s of the suite; same vectors up to sign,
    which the absolute correlations ignore)."""
    from scipy.sparse.linalg import svds

    y = values.reshape(len(values), -1)
    y = y - y.mean(0)
    u, s, _ = svds(y, k=k, random_state=0)
    return u[:, np.argsort(-s)]


def _zscore(a: np.ndarray) -> np.ndarray:
    return (a - a.mean(0)) / a.std(0)


def _max_correlation(components: np.ndarray, features: np.ndarray, shift: int) -> float:
    p = _zscore(np.roll(components, shift, axis=0))
    return float(np.abs(p.T @ features / len(features)).max())


def test_random_clothing_part_is_uncorrelated_with_pose(character):
    """The random part's strongest correlation with any pose feature is what chance gives (the
    same statistic under circular time shifts, which break any real relation); the pose part's
    stands out."""
    model = ClothingModel(character, seed=1)
    theta = compose_motion(character, [Segment(m, 4.0) for m in SCRIPTED] * 2, fps=30, num_frames=3000, seed=2)
    pose_part, random_part = model.deform(theta, 30, seed=5)
    features = np.concatenate([theta, np.abs(theta)], axis=1)
    features = _zscore(features[:, features.std(0) > 1e-6])
    shifts = range(150, 2850, 60)
    pose_part, random_part = _pcs(pose_part), _pcs(random_part)
    null_random = [_max_correlation(random_part, features, s) for s in shifts]
    null_pose = [_max_correlation(pose_part, features, s) for s in shifts]
    assert _max_correlation(random_part, features, 0) < np.percentile(null_random, 95)
    assert _max_correlation(pose_part, features, 0) > max(null_pose)
    # the random part does not even look at the motion
    other = compose_motion(character, [Segment("boxing", 100.0)], fps=30, num_frames=300, seed=9)
    np.testing.assert_array_equal(model.random_part(300, 30, seed=5), model.deform(other, 30, seed=5)[1])


def test_clothing_parts_are_smooth_bounded_and_on_the_garments(character):
    model = ClothingModel(character, seed=1)
    theta = compose_motion(character, [Segment("jogging", 3.0), Segment("picking_up", 3.0)], 30, 180, seed=4)
    pose_part, random_part = model.deform(theta, 30, seed=7)
    skin = model.cloth_weight == 0
    assert np.all(pose_part[:, skin] == 0) and np.all(random_part[:, skin] == 0)
    assert 0.003 < np.sqrt((random_part[:, ~skin] ** 2).sum(-1).mean()) < 0.03
    assert np.abs(pose_part).max() < 0.05 and np.abs(pose_part).max() > 0.002
    # temporally smooth: frame-to-frame change much smaller than the amplitude
    assert np.abs(np.diff(random_part, axis=0)).max() < 0.25 * np.abs(random_part).max()
    # spatially smooth: neighbouring garment vertices move alike
    edges, _ = unique_edges(model.faces)
    both = ~skin[edges].any(1)
    neighbour = np.linalg.norm(random_part[:, edges[both, 0]] - random_part[:, edges[both, 1]], axis=-1).mean()
    assert neighbour < 0.75 * np.linalg.norm(random_part[:, ~skin], axis=-1).mean()
