"""3DGS PLY export: round trip, the standard layout read by plyfile, one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.gaussian_ply import PROPERTIES, SH_C0, read_gaussian_ply, write_gaussian_ply
from egorelight_cli.structures.gaussians import GaussianSet


def _gaussians(n: int = 50) -> GaussianSet:
    g = torch.Generator().manual_seed(0)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    return GaussianSet(torch.randn(n, 3, generator=g), quats, torch.rand(n, 3, generator=g) * 0.05 + 1e-3,
                       torch.rand(n, generator=g) * 0.98 + 0.01, torch.rand(n, 4, generator=g))


def test_round_trip(tmp_path):
    gaussians = _gaussians()
    path = tmp_path / "avatar.ply"
    write_gaussian_ply(path, gaussians)
    back, rgb = read_gaussian_ply(path)
    np.testing.assert_allclose(back.means.numpy(), gaussians.means.numpy(), atol=1e-6)
    np.testing.assert_allclose(back.quats.numpy(), gaussians.quats.numpy(), atol=1e-6)
    np.testing.assert_allclose(back.scales.numpy(), gaussians.scales.numpy(), rtol=1e-5)
    np.testing.assert_allclose(back.opacities.numpy(), gaussians.opacities.numpy(), atol=1e-5)
    np.testing.assert_allclose(rgb, gaussians.colours[:, :3].numpy(), atol=1e-5)


def test_file_has_the_standard_3dgs_layout(tmp_path):
    gaussians = _gaussians(7)
    path = tmp_path / "frame.ply"
    write_gaussian_ply(path, gaussians, rgb=np.full((7, 3), 0.75))
    header = path.read_bytes().split(b"end_header\n")[0].decode("ascii")
    assert "format binary_little_endian 1.0" in header
    assert "element vertex 7" in header
    declared = [line.split()[2] for line in header.splitlines() if line.startswith("property")]
    assert declared == PROPERTIES and len(PROPERTIES) == 62
    assert all(line.split()[1] == "float" for line in header.splitlines() if line.startswith("property"))
    vertex = PlyData.read(str(path))["vertex"]  # an independent reader
    np.testing.assert_allclose(vertex["f_dc_0"], (0.75 - 0.5) / SH_C0, rtol=1e-6)
    np.testing.assert_allclose(vertex["opacity"], torch.logit(gaussians.opacities.double()).numpy(), rtol=1e-4)
    np.testing.assert_allclose(vertex["scale_1"], np.log(gaussians.scales[:, 1].numpy()), rtol=1e-5)
    np.testing.assert_allclose(vertex["rot_0"], gaussians.quats[:, 0].numpy(), atol=1e-6)  # w first
    assert not np.any(vertex["f_rest_44"]) and not np.any(vertex["nx"])


@pytest.mark.parametrize("damage", ["truncate", "garbage", "not_gaussians"])
def test_bad_files_give_one_line_errors(tmp_path, damage):
    path = tmp_path / "bad.ply"
    write_gaussian_ply(path, _gaussians(20))
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) - 100])
    elif damage == "garbage":
        path.write_bytes(b"\x00\xff" * 50)
    else:
        path.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1.0\n")
    with pytest.raises(EgorelightError) as info:
        read_gaussian_ply(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
