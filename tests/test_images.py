"""PNG/JPEG I/O and the sRGB transfer functions."""

from __future__ import annotations

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.images import linear_to_srgb, read_image, read_image_linear, srgb_to_linear, write_image


def test_srgb_known_values_and_inverse():
    assert srgb_to_linear(np.array([0.0, 1.0]))[1] == pytest.approx(1.0)
    assert srgb_to_linear(np.array(0.5)) == pytest.approx(0.21404, abs=1e-5)
    assert linear_to_srgb(np.array(0.18)) == pytest.approx(0.46135, abs=1e-5)
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)


@pytest.mark.parametrize("bits,dtype", [(8, np.uint8), (16, np.uint16)])
def test_png_round_trip_keeps_rgb_order(tmp_path, bits, dtype):
    rng = np.random.default_rng(bits)
    top = np.iinfo(dtype).max
    image = rng.integers(0, top, (5, 7, 3), endpoint=True).astype(dtype)
    image[0, 0] = [top, 0, 0]  # pure red stays red (no BGR swap)
    write_image(tmp_path / "a.png", image)
    back = read_image(tmp_path / "a.png")
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, image)


def test_float_image_quantised_and_linearised(tmp_path):
    encoded = np.full((4, 4, 3), 0.5, np.float32)
    write_image(tmp_path / "g.png", encoded, bits=16)
    lin = read_image_linear(tmp_path / "g.png")
    assert lin.dtype == np.float32
    np.testing.assert_allclose(lin, 0.21404, atol=1e-4)


def test_grey_and_jpeg(tmp_path):
    grey = (np.arange(64, dtype=np.uint8).reshape(8, 8) * 4)
    write_image(tmp_path / "m.png", grey)
    np.testing.assert_array_equal(read_image(tmp_path / "m.png"), grey)
    write_image(tmp_path / "j.jpg", np.full((8, 8, 3), 128, np.uint8))
    assert abs(int(read_image(tmp_path / "j.jpg").mean()) - 128) <= 1
    with pytest.raises(EgorelightError, match="16-bit"):
        write_image(tmp_path / "j16.jpg", np.zeros((2, 2, 3), np.uint16))


def test_errors(tmp_path):
    with pytest.raises(EgorelightError, match="not found"):
        read_image(tmp_path / "nope.png")
    (tmp_path / "bad.png").write_bytes(b"garbage")
    with pytest.raises(EgorelightError, match="cannot read image"):
        read_image(tmp_path / "bad.png")
    (tmp_path / "bad.dng").write_bytes(b"garbage")
    with pytest.raises(EgorelightError, match="cannot decode RAW"):
        read_image_linear(tmp_path / "bad.dng")


def test_a_corrupt_png_is_said_once_in_the_error(tmp_path):
    """libpng prints its complaint on file descriptor 2 itself: it goes into the one-line error
    instead of before it (a process of its own: pytest's capture bypasses the fds)."""
    import subprocess
    import sys

    write_image(tmp_path / "ok.png", np.random.default_rng(0).integers(0, 255, (64, 64, 3)).astype(np.uint8))
    data = bytearray((tmp_path / "ok.png").read_bytes())
    data[200] ^= 0x10  # inside the image data: a CRC error
    (tmp_path / "flipped.png").write_bytes(bytes(data))
    script = ("import sys\nfrom egorelight_cli.io.images import read_image\nfrom egorelight_cli.errors import EgorelightError\n"
              "try:\n    read_image(sys.argv[1])\nexcept EgorelightError as exc:\n    print('error:', exc)\n")
    result = subprocess.run([sys.executable, "-c", script, str(tmp_path / "flipped.png")], capture_output=True, text=True)
    assert result.returncode == 0 and result.stderr == "", result.stderr
    assert result.stdout.startswith("error: cannot read image (") and "CRC" in result.stdout and "flipped.png" in result.stdout
    good = subprocess.run([sys.executable, "-c", script, str(tmp_path / "ok.png")], capture_output=True, text=True)
    assert good.returncode == 0 and good.stdout == good.stderr == ""


def test_an_image_is_read_where_native_output_cannot_be_captured(tmp_path, monkeypatch):
    """No room for the capture files, or a process started with stdout closed: the image is read
    as it is, not an error about the capture (it was UnboundLocalError)."""
    import os
    import subprocess
    import sys
    import tempfile

    image = np.arange(48, dtype=np.uint8).reshape(4, 4, 3)
    write_image(tmp_path / "a.png", image)

    def no_room(*args, **kwargs):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(tempfile, "TemporaryFile", no_room)
        np.testing.assert_array_equal(read_image(tmp_path / "a.png"), image)
    script = "import sys\nfrom egorelight_cli.io.images import read_image\nprint(read_image(sys.argv[1]).shape, file=sys.stderr)\n"
    result = subprocess.run([sys.executable, "-c", script, str(tmp_path / "a.png")], capture_output=True, text=True,
                            preexec_fn=lambda: os.close(1))
    assert result.returncode == 0 and result.stderr.strip() == "(4, 4, 3)", result.stderr
