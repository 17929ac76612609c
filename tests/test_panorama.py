"""render/panorama.py: posed views gathered into an equirect panorama; wrap-around inpainting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, invert_rigid
from egorelight_cli.geometry.equirect import (
    directions_to_equirect,
    equirect_directions,
    equirect_solid_angles,
    yaw_rotation,
)
from egorelight_cli.io.calibration import Calibration, EgoCameraCalibration, HeadPoses, posed_ego_camera
from egorelight_cli.render.camera_response import render_envmap_view
from egorelight_cli.render.panorama import PanoramaView, accumulate_panorama, inpaint_equirect, pad_equirect


def _smooth_map(height: int) -> np.ndarray:
    """A smooth, coloured, non-symmetric map (H,2H,3)."""
    d = equirect_directions(height)
    out = np.stack([0.4 + 0.25 * d[..., 0] + 0.1 * d[..., 1] * d[..., 2],
                    0.5 + 0.2 * d[..., 1] - 0.1 * d[..., 0] * d[..., 1],
                    0.45 - 0.2 * d[..., 2] + 0.1 * d[..., 0]], axis=-1)
    return out.astype(np.float32)


def _pitch(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


class _Rig:
    """The piece of a Capture that posed_ego_camera reads: HMD camera intrinsics by role."""

    def __init__(self, camera: Camera):
        self.camera = camera

    def ego_camera(self, role: str) -> Camera:
        return self.camera


def _posed_cameras(yaws, pitch_deg=10.0, width=120, height=90, hfov=90.0, head=(0.0, 1.6, 0.0)):
    """Front cameras placed by a Calibration (H @ inv(Pi)): head turned by ``yaws``, camera
    pitched down and offset 8 cm forward of the HMD origin. OpenCV camera (y down, z forward)
    looking along the HMD's -Z."""
    f = 0.5 * width / math.tan(math.radians(hfov) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    intrinsics = Camera("pinhole", K, np.zeros(5), width, height, np.eye(4), "front_left")
    R_hmd_from_cam = np.diag([1.0, -1.0, -1.0]) @ _pitch(-pitch_deg)  # camera z -> HMD -Z, tilted down
    T_hmd_from_cam = np.eye(4)
    T_hmd_from_cam[:3, :3] = R_hmd_from_cam
    T_hmd_from_cam[:3, 3] = [0.03, 0.0, -0.08]
    H = np.tile(np.eye(4), (len(yaws), 1, 1))
    for i, yaw in enumerate(yaws):
        H[i, :3, :3] = yaw_rotation(yaw)
        H[i, :3, 3] = head
    frames = np.arange(len(yaws))
    calibration = Calibration({"front_left": EgoCameraCalibration("front_left", "cam", invert_rigid(T_hmd_from_cam))},
                              {"wild": 0}, {"wild": HeadPoses(H, frames, np.ones(len(yaws), bool),
                                                              np.zeros(len(yaws), np.int64), np.zeros(len(yaws)))})
    rig = _Rig(intrinsics)
    return [posed_ego_camera(rig, calibration, "front_left", "wild", int(f)) for f in frames]


def test_panorama_reprojects_a_known_map_into_its_cells():
    truth_fine = _smooth_map(128)
    cameras = _posed_cameras(np.arange(0, 360, 40.0))
    views = [PanoramaView(render_envmap_view(truth_fine, c, supersample=2), c) for c in cameras]
    pano = accumulate_panorama(views, 32)
    truth = _smooth_map(32)
    cov = pano.coverage
    assert 0.3 < pano.coverage_fraction < 0.9
    error = np.abs(pano.radiance - truth)[cov]
    assert error.max() < 0.02 and error.mean() < 0.004
    # the cap straight up and down is outside every view (90 x ~70 degree frustum pitched 10 down)
    assert not cov[0].any() and not cov[-1].any()
    assert (pano.radiance[~cov] == 0).all() and (pano.weight[~cov] <= 1e-3).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_bright_spot_lands_in_its_cell(seed):
    rng = np.random.default_rng(seed)
    height = 32
    centres = equirect_directions(height)
    fine = equirect_directions(256)
    cameras = _posed_cameras(np.arange(0, 360, 30.0), pitch_deg=5.0, width=200, height=150)
    for _ in range(3):
        row, col = int(rng.integers(11, 20)), int(rng.integers(0, 2 * height))
        d0 = centres[row, col]
        spot = np.exp(4000.0 * (fine @ d0 - 1.0))[..., None] * np.array([1.0, 0.5, 0.25]) + 0.01
        views = [PanoramaView(render_envmap_view(spot.astype(np.float32), c, supersample=2), c) for c in cameras]
        pano = accumulate_panorama(views, height)
        assert pano.coverage[row, col]
        found = np.unravel_index(np.argmax(pano.radiance[..., 0]), (height, 2 * height))
        assert found == (row, col)
        x, y = directions_to_equirect(d0, height)
        assert (int(y), int(x)) == (row, col)  # the convention's cell of the direction


def test_proxy_sphere_removes_parallax_of_a_near_room():
    truth_fine = _smooth_map(128) ** 3 * 4  # more contrast: parallax shows
    centre = np.array([0.0, 1.6, 0.0])
    cameras = _posed_cameras(np.arange(0, 360, 40.0), head=(0.25, 1.6, 0.1))  # head 27 cm off the room centre
    views = [PanoramaView(render_envmap_view(truth_fine, c, supersample=2, radius_m=1.5, centre=centre), c)
             for c in cameras]
    truth = _smooth_map(32) ** 3 * 4
    near = accumulate_panorama(views, 32, proxy_radius_m=1.5, centre=centre)
    far = accumulate_panorama(views, 32)
    err_near = np.abs(near.radiance - truth)[near.coverage].mean()
    err_far = np.abs(far.radiance - truth)[far.coverage].mean()
    assert err_near < 0.35 * err_far


def test_masked_pixels_and_bad_inputs():
    truth_fine = _smooth_map(64)
    camera = _posed_cameras([0.0])[0]
    image = render_envmap_view(truth_fine, camera)
    valid = np.ones(image.shape[:2], bool)
    valid[:, : image.shape[1] // 2] = False  # the left half is unusable (e.g. saturated)
    image[~valid] = 100.0
    pano = accumulate_panorama([PanoramaView(image, camera, valid)], 16)
    assert pano.coverage.any() and pano.radiance.max() < 1.5
    with pytest.raises(EgorelightError, match="no views"):
        accumulate_panorama([], 16)
    with pytest.raises(EgorelightError, match="shape"):
        accumulate_panorama([PanoramaView(image[:10], camera)], 16)
    with pytest.raises(EgorelightError, match="proxy"):
        accumulate_panorama([PanoramaView(image, camera)], 16, proxy_radius_m=2.0)


def test_pad_equirect_wraps_longitude_and_reflects_over_the_poles():
    a = np.arange(4 * 8).reshape(4, 8)
    p = pad_equirect(a, 2, 1)
    assert p.shape == (6, 12)
    assert (p[1:5, :2] == a[:, -2:]).all() and (p[1:5, -2:] == a[:, :2]).all()
    assert (p[0, 2:10] == np.roll(a[0], 4)).all() and (p[5, 2:10] == np.roll(a[3], 4)).all()


@pytest.mark.parametrize("method", ["telea", "push_pull"])
def test_inpainting_fills_a_band_across_the_seam(method):
    H = 32
    truth = _smooth_map(H)
    observed = np.ones((H, 2 * H), bool)
    observed[:, :5] = False       # a band across the 0/360 degree seam
    observed[:, -5:] = False
    observed[:6] = False          # and the cap around the zenith
    filled = inpaint_equirect(np.where(observed[..., None], truth, 7.0), observed, method=method)
    assert (filled[observed] == truth[observed]).all()
    holes = ~observed
    omega = equirect_solid_angles(H)[holes][:, None]
    error = float((np.abs(filled - truth)[holes] * omega).sum() / omega.sum() / 3)
    assert error < 0.03, error
    # continuity across the seam: the first and last columns differ as little as the truth's
    seam = np.abs(filled[:, 0] - filled[:, -1]).mean()
    assert seam < 2 * np.abs(truth[:, 0] - truth[:, -1]).mean() + 0.01
    # without the wrap padding the same band is filled from one side only: worse at the seam
    unwrapped = inpaint_equirect(np.where(observed[..., None], truth, 7.0), observed, method=method, pad_fraction=0.0)
    assert np.abs(unwrapped[:, 0] - unwrapped[:, -1]).mean() > seam


@pytest.mark.parametrize("method", ["telea", "push_pull"])
def test_a_uniform_map_seen_in_one_small_patch_is_filled_uniform(method):
    """A narrow scan (a few texels by the zenith): the whole map takes their value. Push-pull's
    coarsest level kept unknown cells at 0, which darkened the fill down to 0.44."""
    H = 16
    observed = np.zeros((H, 2 * H), bool)
    observed[0:2, 20:24] = True
    filled = inpaint_equirect(np.where(observed[..., None], 1.0, 0.0).astype(np.float32), observed, method=method,
                              pad_fraction=0.0)
    assert np.abs(filled - 1.0).max() < 0.01  # Telea works on 8-bit steps (1/255 of the range)


def test_inpainting_errors():
    truth = _smooth_map(8)
    with pytest.raises(EgorelightError, match="nothing to inpaint"):
        inpaint_equirect(truth, np.zeros((8, 16), bool))
    with pytest.raises(EgorelightError, match="method"):
        inpaint_equirect(truth, np.ones((8, 16), bool), method="gemini")
    assert np.array_equal(inpaint_equirect(truth, np.ones((8, 16), bool)), truth)
