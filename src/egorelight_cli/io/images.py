"""LDR and RAW images: PNG/JPEG (8/16-bit), sRGB <-> linear, RAW/DNG via rawpy.

All functions return RGB (not OpenCV's BGR) in (H,W,3) or (H,W) arrays. Linear images are
float32 in [0,1] for LDR sources and unbounded for RAW.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.native_output import read_quietly

RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2")


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding; input and output in [0,1] (float arrays of any shape)."""
    x = np.asarray(encoded, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding; input clipped to [0,1]."""
    x = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def tonemap(hdr: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.0) -> np.ndarray:
    """(H,W,3) uint8 sRGB of a linear HDR image scaled so the ``percentile`` (of the mask) is ~0.9."""
    values = hdr.max(axis=-1)
    values = values[mask] if mask is not None and mask.any() else values
    level = float(np.percentile(values, percentile)) if values.size else 0.0
    scale = 0.9 / level if level > 1e-8 else 1.0
    return np.round(linear_to_srgb(hdr * scale) * 255).astype(np.uint8)


def read_image(path: str | Path) -> np.ndarray:
    """Read a PNG/JPEG as stored: uint8 or uint16, (H,W) grey or (H,W,3|4) RGB(A)."""
    return decode_image(path, cv2.IMREAD_UNCHANGED, "image")


def decode_image(path: str | Path, flags: int, what: str) -> np.ndarray:
    """``cv2.imread(path, flags)`` in RGB(A) channel order; a missing or undecodable file is a
    one-line error naming ``what`` and ``path``, with libpng's or libjpeg's own complaint in it
    instead of on the terminal before it (:func:`~egorelight_cli.io.native_output.read_quietly`)."""
    path = Path(path)
    if not path.is_file():
        raise EgorelightError(f"{what} not found", path)

    def decode() -> np.ndarray:
        decoded = cv2.imread(str(path), flags)
        if decoded is None:
            raise ValueError("not a decodable file")
        return decoded

    image = read_quietly(path, decode, what)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


def to_unit_float(image: np.ndarray) -> np.ndarray:
    """uint8/uint16 -> float32 in [0,1] by the dtype's full range."""
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float32) / 65535.0
    return image.astype(np.float32)


def read_image_linear(path: str | Path) -> np.ndarray:
    """Read an sRGB-encoded PNG/JPEG or a RAW/DNG file as linear float32 RGB."""
    path = Path(path)
    if path.suffix.lower() in RAW_SUFFIXES:
        return read_raw_linear(path)
    return srgb_to_linear(to_unit_float(read_image(path)))


def write_image(path: str | Path, image: np.ndarray, bits: int = 8) -> None:
    """Write an RGB(A) or grey image. Float input is taken as [0,1] and quantised to ``bits``
    (8 or 16); integer input is written as is (uint8 or uint16)."""
    path = Path(path)
    image = np.asarray(image)
    if np.issubdtype(image.dtype, np.floating):
        if bits not in (8, 16):
            raise EgorelightError(f"bits must be 8 or 16, got {bits}", path)
        top = 255 if bits == 8 else 65535
        image = np.round(np.clip(np.nan_to_num(image), 0.0, 1.0) * top).astype(np.uint8 if bits == 8 else np.uint16)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA)
    if image.dtype == np.uint16 and path.suffix.lower() in (".jpg", ".jpeg"):
        raise EgorelightError("JPEG cannot hold 16-bit images", path)
    if not cv2.imwrite(str(path), np.ascontiguousarray(image)):
        raise EgorelightError("cannot write image", path)


def read_raw_linear(path: str | Path) -> np.ndarray:
    """Demosaic a RAW/DNG frame to linear camera-white-balanced RGB, float32 scaled so the
    sensor's white level is 1.0 (no gamma, no auto-brightening)."""
    import rawpy  # local import: only RAW users pay for it

    path = Path(path)
    if not path.is_file():
        raise EgorelightError("RAW file not found", path)
    try:
        with rawpy.imread(str(path)) as raw:
            rgb16 = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True)
    except Exception as exc:  # rawpy raises LibRawError subclasses
        raise EgorelightError(f"cannot decode RAW ({exc})", path) from None
    return rgb16.astype(np.float32) / 65535.0
