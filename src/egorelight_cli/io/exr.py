"""OpenEXR images: HDR frames and multi-channel UV maps with named layers.

Channels are addressed by their full EXR names (``R``, ``normal.X``, ``albedo.G``). A *layer*
is a group of channels sharing a prefix: ``normal`` -> ``normal.X``, ``normal.Y``, ``normal.Z``.
RGB images are the unnamed layer ``""`` with channels ``R``, ``G``, ``B`` (and ``A``).

Arrays are always made C-contiguous before they reach OpenEXR: the Python binding writes a
non-contiguous array silently wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import OpenEXR

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.native_output import read_quietly

#: Channel suffixes used when a (H,W,C) array is stored as a layer.
LAYER_SUFFIXES = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
VECTOR_SUFFIXES = ("X", "Y", "Z")

_RESERVED_HEADER = {
    "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
    "screenWindowCenter", "screenWindowWidth", "type", "tiles", "chunkCount", "name", "version",
}


@dataclass
class ExrImage:
    """A decoded EXR file.

    Attributes:
        channels: full channel name -> (H,W) array (float32 or float16, as stored).
        attributes: user header attributes (str, int, float, numpy arrays).
    """

    channels: dict[str, np.ndarray]
    attributes: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        first = next(iter(self.channels.values()))
        return first.shape

    def layer(self, name: str, suffixes: tuple[str, ...] | None = None) -> np.ndarray:
        """Stack a layer's channels into (H,W,C) float32.

        ``name`` is the layer prefix (``"normal"``) or ``""`` for the plain ``R,G,B`` channels.
        Without ``suffixes`` the first of X/Y/Z, R/G/B/A or Y that is fully present is used.
        """
        prefix = f"{name}." if name else ""
        options = [suffixes] if suffixes else [VECTOR_SUFFIXES, ("R", "G", "B", "A"), ("R", "G", "B"), ("Y",)]
        for option in options:
            names = [prefix + s for s in option]
            if all(n in self.channels for n in names):
                return np.stack([self.channels[n].astype(np.float32) for n in names], axis=-1)
        raise EgorelightError(f"EXR has no layer {name or 'RGB'!r} (channels: {', '.join(sorted(self.channels))})")


def layer_channels(name: str, array: np.ndarray, vector: bool | None = None) -> dict[str, np.ndarray]:
    """Split an (H,W) or (H,W,C) array into named EXR channels.

    ``vector=True`` names 3 channels ``X,Y,Z`` (normals, positions); otherwise colour names are
    used (``R,G,B[,A]``, or ``Y`` for one channel). ``name=""`` gives bare ``R``, ``G``, ``B``.
    """
    array = np.asarray(array)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3:
        raise EgorelightError(f"EXR layer {name!r} must be (H,W) or (H,W,C), got shape {array.shape}")
    C = array.shape[-1]
    if vector is None:
        vector = name in ("normal", "position", "points")
    if vector and C == 3:
        suffixes = VECTOR_SUFFIXES
    elif C in LAYER_SUFFIXES:
        suffixes = LAYER_SUFFIXES[C]
    else:
        suffixes = tuple(str(i) for i in range(C))
    prefix = f"{name}." if name else ""
    return {prefix + s: array[..., i] for i, s in enumerate(suffixes)}


def write_exr(
    path: str | Path,
    channels: dict[str, np.ndarray],
    attributes: dict | None = None,
    half: bool = False,
    compression: str = "zip",
) -> None:
    """Write named (H,W) channels to an EXR file.

    Args:
        path: output file.
        channels: channel name -> (H,W) array; all the same shape. Use :func:`layer_channels`
            to build them from (H,W,C) arrays.
        attributes: extra header attributes (str, int, float or small numpy arrays).
        half: store as float16 instead of float32.
        compression: ``zip``, ``piz``, ``none``.
    """
    if not channels:
        raise EgorelightError("no channels to write", path)
    shapes = {np.shape(a) for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise EgorelightError(f"EXR channels must share one (H,W) shape, got {sorted(shapes)}", path)
    dtype = np.float16 if half else np.float32
    data = {name: np.ascontiguousarray(np.asarray(a), dtype=dtype) for name, a in channels.items()}
    comp = {"zip": OpenEXR.ZIP_COMPRESSION, "piz": OpenEXR.PIZ_COMPRESSION, "none": OpenEXR.NO_COMPRESSION}
    header = {"compression": comp[compression], "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        if key in _RESERVED_HEADER:
            raise EgorelightError(f"EXR attribute name {key!r} is reserved", path)
        header[key] = value
    try:
        with OpenEXR.File(header, data) as exr:
            exr.write(str(path))
    except Exception as exc:  # OpenEXR raises bare RuntimeError/TypeError
        raise EgorelightError(f"cannot write EXR ({exc})", path) from None


def write_exr_layers(
    path: str | Path,
    layers: dict[str, np.ndarray],
    attributes: dict | None = None,
    half: bool = False,
) -> None:
    """Write (H,W,C) layers, e.g. ``{"normal": n, "albedo": a}`` or ``{"": rgb}``."""
    channels: dict[str, np.ndarray] = {}
    for name, array in layers.items():
        channels.update(layer_channels(name, array))
    write_exr(path, channels, attributes, half)


def read_exr(path: str | Path) -> ExrImage:
    """Read every channel of an EXR file (kept in its stored dtype) and its user attributes."""
    path = Path(path)
    if not path.is_file():
        raise EgorelightError("EXR file not found", path)

    def read():
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            header = dict(exr.header())  # the binding empties its dict on close
            return header, {name: np.ascontiguousarray(ch.pixels) for name, ch in exr.channels().items()}

    header, channels = read_quietly(path, read, "EXR")
    attributes = {k: v for k, v in header.items() if k not in _RESERVED_HEADER}
    for name, array in channels.items():
        if array.ndim != 2:
            raise EgorelightError(f"EXR channel {name} is not a plain (H,W) channel", path)
    return ExrImage(channels=channels, attributes=attributes)


def read_exr_header(path: str | Path) -> dict:
    """The full header of an EXR file without decoding its pixels."""
    path = Path(path)
    if not path.is_file():
        raise EgorelightError("EXR file not found", path)

    def read():
        with OpenEXR.File(str(path), header_only=True) as exr:
            return dict(exr.header())

    return read_quietly(path, read, "EXR header")
