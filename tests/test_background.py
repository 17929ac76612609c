"""Background replacement of egocentric training views (nn/background.py, stages/egopose_augment.py)."""

import numpy as np
import pytest
import torch

from egorelight_cli.nn.background import TORSO, BackgroundSwap, body_masks, value_noise
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES, NUM_KEYPOINTS, keypoint_edges


def _skeleton_pixels(size: int = 64) -> np.ndarray:
    """(J,2) pixels of a stick figure in the lower half of a size x size image, hands and feet
    collapsed on their wrists and ankles; NaN for the keypoints of nothing."""
    p = np.full((NUM_KEYPOINTS, 2), np.nan)
    named = {"Neck": (32, 40), "LeftArm": (24, 42), "RightArm": (40, 42), "LeftForeArm": (14, 34),
             "RightForeArm": (50, 34), "LeftHand": (8, 22), "RightHand": (56, 22), "LeftUpLeg": (27, 56),
             "RightUpLeg": (37, 56), "LeftLeg": (27, 62), "RightLeg": (37, 62)}
    for name, xy in named.items():
        p[KEYPOINT_NAMES.index(name)] = xy
    for side in ("Left", "Right"):
        wrist = p[KEYPOINT_NAMES.index(f"{side}Hand")]
        for j, name in enumerate(KEYPOINT_NAMES):
            if name.startswith(f"{side}Hand") and name != f"{side}Hand":
                p[j] = wrist
    return p


def test_body_mask_covers_the_bones_and_leaves_the_far_background():
    pixels = _skeleton_pixels()[None, None]  # (1,1,J,2)
    ranges = np.full(pixels.shape[:3], 0.5)
    mask = body_masks(pixels, ranges, np.array([40.0]), 1.0, (64, 64), 0.05, 0.0)[0, 0]
    assert mask.shape == (64, 64) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 1}
    p = pixels[0, 0]
    for a, b in keypoint_edges():
        if np.isfinite(p[[a, b]]).all():
            mid = np.round((p[a] + p[b]) / 2).astype(int)
            assert mask[mid[1], mid[0]] == 1.0, (KEYPOINT_NAMES[a], KEYPOINT_NAMES[b])
    torso = np.round(p[list(TORSO)].mean(0)).astype(int)
    assert mask[torso[1], torso[0]] == 1.0
    assert mask[:12, :].sum() == 0  # above the hands: background only
    assert mask[2, 32] == 0.0 and mask[30, 32] == 0.0  # between the raised arms


def test_body_mask_limbs_grow_as_they_come_closer_and_with_the_margin():
    pixels = _skeleton_pixels()[None, None].repeat(2, axis=1)  # two views, one frame
    ranges = np.stack([np.full(NUM_KEYPOINTS, 1.0), np.full(NUM_KEYPOINTS, 0.25)])[None]
    far, near = body_masks(pixels, ranges, np.array([40.0, 40.0]), 1.0, (64, 64), 0.05, 0.0)[0]
    assert near.sum() > far.sum() and (near >= far).all()  # radius 8 px vs 2 px
    grown = body_masks(pixels[:, :1], ranges[:, :1], np.array([40.0]), 1.0, (64, 64), 0.05, 3.0)[0, 0]
    assert grown.sum() > far.sum() and (grown >= far).all()
    # the same view from a camera of twice the resolution (pixels and focal length doubled), drawn at half
    half = body_masks(pixels[:, :1] * 2.0, ranges[:, :1], np.array([80.0]), 0.5, (64, 64), 0.05, 0.0)[0, 0]
    np.testing.assert_array_equal(half, far)


def test_body_mask_skips_keypoints_that_do_not_project():
    pixels = np.full((1, 1, NUM_KEYPOINTS, 2), np.nan)
    mask = body_masks(pixels, np.ones(pixels.shape[:3]), np.array([40.0]), 1.0, (32, 32), 0.05, 2.0)
    assert mask.sum() == 0


def test_value_noise_is_a_seeded_texture_in_the_unit_range():
    a = value_noise(3, 40, 30, 3, torch.Generator().manual_seed(1))
    b = value_noise(3, 40, 30, 3, torch.Generator().manual_seed(1))
    c = value_noise(3, 40, 30, 3, torch.Generator().manual_seed(2))
    assert a.shape == (3, 3, 40, 30)
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a, c)
    assert float(a.std(dim=(2, 3)).min()) > 0.01  # a texture, not a flat colour


@pytest.mark.parametrize("probability", [0.0, 1.0])
def test_background_swap_keeps_the_body_and_replaces_the_rest(probability):
    g = torch.Generator().manual_seed(0)
    images = torch.full((2, 2, 3, 32, 32), 0.25)
    keep = torch.zeros(2, 2, 32, 32)
    keep[..., 8:24, 8:24] = 1.0
    out = BackgroundSwap(probability, octaves=2, feather_px=2)(images, keep, g)
    assert out.shape == images.shape
    inner = (slice(None), slice(None), slice(None), slice(11, 21), slice(11, 21))
    torch.testing.assert_close(out[inner], images[inner])  # the body, beyond the feathered edge
    outside = out[..., :5, :]
    if probability == 0.0:
        torch.testing.assert_close(out, images)
    else:
        assert (outside - 0.25).abs().amax(dim=(2, 3, 4)).min() > 0.05  # every view got a texture
        assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0


def test_background_swap_takes_the_drawn_uint8_masks():
    images = torch.rand(1, 2, 3, 16, 16, generator=torch.Generator().manual_seed(5))
    keep = torch.zeros(1, 2, 16, 16, dtype=torch.uint8)
    keep[..., 4:12, 4:12] = 1
    g = torch.Generator().manual_seed(6)
    out = BackgroundSwap(1.0, octaves=1, feather_px=0)(images, keep, g)
    torch.testing.assert_close(out[..., 4:12, 4:12], images[..., 4:12, 4:12])
    assert not torch.allclose(out[..., :4, :], images[..., :4, :])


def test_background_swap_draws_per_view():
    images = torch.full((8, 2, 3, 16, 16), 0.5)
    keep = torch.zeros(8, 2, 16, 16)
    out = BackgroundSwap(0.5, octaves=1, feather_px=0)(images, keep, torch.Generator().manual_seed(4))
    swapped = ((out - images).abs().flatten(2).amax(-1) > 1e-6)  # (8,2)
    assert 0 < int(swapped.sum()) < 16
