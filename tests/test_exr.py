"""EXR round trips and agreement with a second reader (OpenCV)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.exr import layer_channels, read_exr, read_exr_header, write_exr, write_exr_layers


def test_float32_rgb_round_trip(tmp_path):
    rgb = np.random.default_rng(0).uniform(0, 50, (7, 11, 3)).astype(np.float32)
    write_exr_layers(tmp_path / "a.exr", {"": rgb})
    back = read_exr(tmp_path / "a.exr")
    assert set(back.channels) == {"R", "G", "B"}
    np.testing.assert_array_equal(back.layer(""), rgb)
    assert back.channels["R"].dtype == np.float32


def test_half_round_trip_is_float16_exact(tmp_path):
    values = np.random.default_rng(1).uniform(-4, 4, (5, 6)).astype(np.float16)
    write_exr(tmp_path / "h.exr", {"Y": values}, half=True)
    back = read_exr(tmp_path / "h.exr").channels["Y"]
    assert back.dtype == np.float16
    np.testing.assert_array_equal(back, values)


def test_multichannel_named_layers_and_attributes(tmp_path):
    rng = np.random.default_rng(2)
    normal = rng.normal(size=(8, 9, 3)).astype(np.float32)
    albedo = rng.uniform(size=(8, 9, 3)).astype(np.float32)
    shadow = rng.uniform(size=(8, 9)).astype(np.float32)
    attrs = {"frame_id": 17, "exposure": 0.25, "camera": "down_left", "kind": "egorelight/uvmaps"}
    write_exr_layers(tmp_path / "uv.exr", {"normal": normal, "albedo": albedo, "shadow": shadow}, attributes=attrs)
    back = read_exr(tmp_path / "uv.exr")
    assert {"normal.X", "normal.Y", "normal.Z", "albedo.R", "albedo.G", "albedo.B", "shadow.Y"} == set(back.channels)
    np.testing.assert_array_equal(back.layer("normal"), normal)
    np.testing.assert_array_equal(back.layer("albedo"), albedo)
    np.testing.assert_array_equal(back.layer("shadow")[..., 0], shadow)
    for key, value in attrs.items():
        assert back.attributes[key] == pytest.approx(value) if isinstance(value, float) else back.attributes[key] == value
    assert read_exr_header(tmp_path / "uv.exr")["camera"] == "down_left"


def test_non_contiguous_input_is_written_correctly(tmp_path):
    base = np.arange(6 * 10 * 3, dtype=np.float32).reshape(6, 10, 3)
    strided = base[:, ::2, :]            # non-contiguous view
    transposed = base[..., 0].T          # Fortran-ordered view
    assert not strided.flags.c_contiguous and not transposed.flags.c_contiguous
    write_exr_layers(tmp_path / "s.exr", {"": strided})
    np.testing.assert_array_equal(read_exr(tmp_path / "s.exr").layer(""), strided)
    write_exr(tmp_path / "t.exr", {"Y": transposed})
    np.testing.assert_array_equal(read_exr(tmp_path / "t.exr").channels["Y"], transposed)


def test_opencv_reads_our_exr_identically(tmp_path):
    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
    import cv2

    rgb = np.random.default_rng(3).uniform(0, 1000, (9, 13, 3)).astype(np.float32)
    write_exr_layers(tmp_path / "cv.exr", {"": rgb})
    bgr = cv2.imread(str(tmp_path / "cv.exr"), cv2.IMREAD_UNCHANGED)
    assert bgr is not None, "OpenCV could not read the EXR"
    np.testing.assert_array_equal(bgr[..., ::-1], rgb)


def test_layer_channel_names():
    assert list(layer_channels("normal", np.zeros((2, 2, 3)))) == ["normal.X", "normal.Y", "normal.Z"]
    assert list(layer_channels("albedo", np.zeros((2, 2, 3)))) == ["albedo.R", "albedo.G", "albedo.B"]
    assert list(layer_channels("", np.zeros((2, 2, 4)))) == ["R", "G", "B", "A"]


def test_errors(tmp_path):
    with pytest.raises(EgorelightError, match="not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(EgorelightError, match="cannot read EXR"):
        read_exr(tmp_path / "junk.exr")
    with pytest.raises(EgorelightError, match="share one"):
        write_exr(tmp_path / "bad.exr", {"R": np.zeros((2, 2)), "G": np.zeros((3, 2))})
    write_exr_layers(tmp_path / "ok.exr", {"": np.zeros((2, 2, 3))})
    with pytest.raises(EgorelightError, match="no layer"):
        read_exr(tmp_path / "ok.exr").layer("normal")


def test_a_truncated_exr_is_said_once_in_the_error(tmp_path):
    """OpenEXR prints its complaints on stdout and stderr itself: they are taken into the one-line
    error instead of surrounding it (a process of its own: pytest's capture bypasses the fds)."""
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    write_exr(tmp_path / "ok.exr", {c: rng.random((64, 64)).astype(np.float32) for c in "RGB"})
    data = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[:len(data) // 2])
    result = subprocess.run([sys.executable, "-m", "egorelight_cli.cli", "inspect", str(tmp_path / "cut.exr")],
                            capture_output=True, text=True)
    assert result.returncode == 2 and result.stdout == "", result.stdout
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("egorelight: error: cannot read EXR") and "cut.exr" in lines[0]
    good = subprocess.run([sys.executable, "-m", "egorelight_cli.cli", "inspect", str(tmp_path / "ok.exr")],
                          capture_output=True, text=True)
    assert good.returncode == 0 and "(64, 64) float32" in good.stdout and good.stderr == ""
