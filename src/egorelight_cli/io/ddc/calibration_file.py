"""``.calibration`` files (Skeletool cameras: pinhole and fisheye, static or animated)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egorelight_cli.io.ddc.text import CALIBRATION_HEADER, _clip, _join, _Lines, _read_text, _write_text_lines


@dataclass
class CalibrationFrame:
    """One ``frame`` block of an animated camera."""

    frame: int
    intrinsic: np.ndarray  # (4,4)
    extrinsic: np.ndarray  # (4,4) world -> camera, millimetres
    radial: float = 0.0


@dataclass
class CalibrationCamera:
    """One camera of a ``.calibration`` file (millimetres, row-major 4x4 matrices).

    Pinhole cameras use ``intrinsic`` (K in the upper-left 3x3), ``extrinsic`` (world->camera)
    and ``radial``. Fisheye (Scaramuzza/OCamCalib) cameras add ``polynomial_c2w``,
    ``polynomial_w2c``, ``image_circle_radius`` and ``affine`` ``(c, d, e)``. Animated cameras
    have ``frames`` instead of a single intrinsic/extrinsic. Unknown keyword lines are kept in
    ``extra`` (token lists) and written back.
    """

    name: str
    sensor: tuple[float, float] = (0.0, 0.0)
    size: tuple[int, int] = (0, 0)
    animated: bool = False
    intrinsic: np.ndarray | None = None
    extrinsic: np.ndarray | None = None
    radial: float = 0.0
    polynomial_c2w: list[float] | None = None
    polynomial_w2c: list[float] | None = None
    image_circle_radius: float | None = None
    affine: tuple[float, float, float] | None = None
    frames: list[CalibrationFrame] = field(default_factory=list)
    extra: list[list[str]] = field(default_factory=list)

    @property
    def is_fisheye(self) -> bool:
        return self.polynomial_c2w is not None or self.polynomial_w2c is not None


def read_calibration(path: str | Path) -> list[CalibrationCamera]:
    """Read a ``.calibration`` file (pinhole and fisheye cameras, static or animated)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, "calibration file"), "calibration file")
    lines.header(CALIBRATION_HEADER)
    cameras: list[CalibrationCamera] = []
    cam: CalibrationCamera | None = None
    frame: CalibrationFrame | None = None

    def expect(tokens, n, number, key):
        if len(tokens) != n + 1:
            raise lines.error(f"{key!r} takes {n} value(s), found {len(tokens) - 1}", number)
        return lines.floats(tokens[1:], number, f"{key} value")

    def matrix(tokens, number, key):
        return np.array(expect(tokens, 16, number, key)).reshape(4, 4)

    def polynomial(tokens, number, key):
        if len(tokens) < 2:
            raise lines.error(f"{key!r} needs a coefficient count", number)
        n = lines.int(tokens[1], number, f"{key} coefficient count", minimum=0)
        if len(tokens) != n + 2:
            raise lines.error(f"{key!r} announces {n} coefficients but has {len(tokens) - 2}", number)
        return lines.floats(tokens[2:], number, f"{key} coefficient")

    while not lines.at_end():
        number, line, tokens = lines.next("a camera entry")
        key = tokens[0]
        if key == "name":
            cam = CalibrationCamera(name=" ".join(tokens[1:]) if len(tokens) > 1 else str(len(cameras)))
            cameras.append(cam)
            frame = None
            continue
        if cam is None:
            raise lines.error(f"expected 'name', found {_clip(line)!r}", number)
        if key == "sensor":
            cam.sensor = tuple(expect(tokens, 2, number, key))
        elif key == "size":
            expect(tokens, 2, number, key)
            cam.size = (lines.int(tokens[1], number, "image width", minimum=0),
                        lines.int(tokens[2], number, "image height", minimum=0))
        elif key == "animated":
            expect(tokens, 1, number, key)
            cam.animated = bool(lines.int(tokens[1], number, "animated flag"))
        elif key == "frame":
            if not cam.animated:
                raise lines.error(f"camera {cam.name!r} is not animated but has a 'frame' entry", number)
            expect(tokens, 1, number, key)
            frame = CalibrationFrame(lines.int(tokens[1], number, "frame"), np.eye(4), np.eye(4))
            cam.frames.append(frame)
        elif key == "intrinsic":
            if frame is not None:
                frame.intrinsic = matrix(tokens, number, key)
            else:
                cam.intrinsic = matrix(tokens, number, key)
        elif key == "extrinsic":
            if frame is not None:
                frame.extrinsic = matrix(tokens, number, key)
            else:
                cam.extrinsic = matrix(tokens, number, key)
        elif key == "radial":
            value = expect(tokens, 1, number, key)[0]
            if frame is not None:
                frame.radial = value
            cam.radial = value
        elif key in ("polynomialC2W", "polynomial"):
            cam.polynomial_c2w = polynomial(tokens, number, key)
        elif key == "polynomialW2C":
            cam.polynomial_w2c = polynomial(tokens, number, key)
        elif key == "imageCircleRadius":
            cam.image_circle_radius = expect(tokens, 1, number, key)[0]
        elif key == "affine":
            cam.affine = tuple(expect(tokens, 3, number, key))
        else:
            cam.extra.append(list(tokens))
    for cam in cameras:
        if not cam.animated and (cam.intrinsic is None or cam.extrinsic is None):
            raise lines.error(f"camera {cam.name!r} lacks its intrinsic or extrinsic matrix")
    return cameras


def write_calibration(cameras: list[CalibrationCamera], path: str | Path) -> Path:
    """Write a ``.calibration`` file."""
    out = [CALIBRATION_HEADER]
    for cam in cameras:
        out.append(_join(["name", cam.name]))
        out.append(_join(["sensor", *cam.sensor]))
        out.append(_join(["size", *(int(s) for s in cam.size)]))
        out.append(_join(["animated", int(bool(cam.animated))]))
        if cam.animated:
            for fr in cam.frames:
                out.append(_join(["frame", int(fr.frame)]))
                out.append(_join(["intrinsic", *np.asarray(fr.intrinsic, dtype=float).reshape(16)]))
                out.append(_join(["extrinsic", *np.asarray(fr.extrinsic, dtype=float).reshape(16)]))
                out.append(_join(["radial", fr.radial]))
        else:
            out.append(_join(["intrinsic", *np.asarray(cam.intrinsic, dtype=float).reshape(16)]))
            out.append(_join(["extrinsic", *np.asarray(cam.extrinsic, dtype=float).reshape(16)]))
            out.append(_join(["radial", cam.radial]))
        if cam.polynomial_c2w is not None:
            out.append(_join(["polynomialC2W", len(cam.polynomial_c2w), *cam.polynomial_c2w]))
        if cam.polynomial_w2c is not None:
            out.append(_join(["polynomialW2C", len(cam.polynomial_w2c), *cam.polynomial_w2c]))
        if cam.image_circle_radius is not None:
            out.append(_join(["imageCircleRadius", cam.image_circle_radius]))
        if cam.affine is not None:
            out.append(_join(["affine", *cam.affine]))
        out.extend(" ".join(tokens) for tokens in cam.extra)
    return _write_text_lines(Path(path), out)
