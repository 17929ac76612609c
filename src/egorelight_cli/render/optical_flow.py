"""Dense optical flow between a render and a photograph, and warping one onto the other.

Used by ``envmap``'s inverse rendering (paper: "the inverse warping of optical flow [RAFT] we
estimated between the re-rendered image and the input egocentric down-facing image, which
alleviates the tracking error"). RAFT's weights cannot be downloaded here, so the flow is OpenCV's
DIS (``cv2.DISOpticalFlow_create``, in ``opencv-contrib-python-headless``); RAFT runs only from a
local weights file with torchvision installed (:func:`flow_method`, which says why it cannot).

Conventions: images are (H,W) or (H,W,C); a flow ``F`` (H,W,2) float32 from ``source`` to
``target`` holds, per source pixel ``x = (col, row)``, the displacement in pixels to where the
same point is in ``target``: ``source(x) ~ target(x + F(x))``. :func:`warp` samples ``target`` at
``x + F(x)``, which brings ``target`` onto ``source``'s pixel grid.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.images import linear_to_srgb

METHODS = ("dis", "raft", "none")


def flow_method(method: str, raft_weights: str | None) -> tuple[str, str | None]:
    """(method actually used, why it differs from ``method`` or None).

    ``raft`` needs torchvision and a local RAFT-large state dict at ``raft_weights``; without
    either the flow falls back to ``dis`` and the reason is returned (for the manifest).
    """
    if method not in METHODS:
        raise EgorelightError(f"unknown optical flow method {method!r}; choose one of {', '.join(METHODS)}")
    if method != "raft":
        return method, None
    if not raft_weights or not Path(raft_weights).is_file():
        return "dis", f"RAFT weights not found at {raft_weights or '(flow.raft_weights unset)'}: DIS used instead"
    try:
        import torchvision  # noqa: F401
    except ImportError:
        return "dis", "torchvision is not installed (RAFT needs it): DIS used instead"
    except Exception as exc:  # a torchvision built for another torch fails on import with other errors
        return "dis", f"torchvision does not import beside this torch ({type(exc).__name__}): DIS used instead"
    return "raft", None


def flow_image(linear: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(H,W) uint8 grey image for flow: luminance of linear RGB (H,W,3) scaled so that the 99th
    percentile inside ``mask`` (H,W) bool is white, then sRGB-encoded. The scaling removes the
    unknown exposure between a render and a photograph."""
    grey = np.asarray(linear, dtype=np.float32)
    if grey.ndim == 3:
        grey = grey @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    values = grey[mask] if mask is not None and mask.any() else grey.reshape(-1)
    level = float(np.percentile(values, 99.0)) if values.size else 0.0
    scaled = np.clip(grey / level, 0.0, 1.0) if level > 0 else np.zeros_like(grey)
    return np.round(linear_to_srgb(scaled) * 255.0).astype(np.uint8)


def estimate_flow(source: np.ndarray, target: np.ndarray, method: str = "dis",
                  raft_weights: str | None = None) -> np.ndarray:
    """(H,W,2) float32 flow from ``source`` to ``target`` (both (H,W) uint8, :func:`flow_image`)."""
    if source.shape != target.shape or source.ndim != 2:
        raise EgorelightError(f"flow needs two grey images of one size, got {source.shape} and {target.shape}")
    if method == "none":
        return np.zeros(source.shape + (2,), np.float32)
    if method == "raft":
        return _raft_flow(source, target, str(raft_weights))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(np.ascontiguousarray(source), np.ascontiguousarray(target), None).astype(np.float32)


def _raft_flow(source: np.ndarray, target: np.ndarray, weights: str) -> np.ndarray:
    """torchvision's RAFT-large with a local state dict (images padded to multiples of 8)."""
    import torch
    from torchvision.models.optical_flow import raft_large

    net = raft_large(weights=None)
    net.load_state_dict(torch.load(weights, map_location="cpu"))
    net.eval()
    h, w = source.shape
    pad = ((0, (-h) % 8), (0, (-w) % 8))

    def tensor(image: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(np.pad(image, pad, mode="edge").astype(np.float32) / 127.5 - 1.0)
        return x[None, None].expand(1, 3, -1, -1).contiguous()

    with torch.no_grad():
        flow = net(tensor(source), tensor(target))[-1][0]
    return flow.permute(1, 2, 0).numpy()[:h, :w].astype(np.float32)


def warp(target: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``target`` sampled at ``x + flow(x)`` (bilinear, borders replicated): ``target`` on the
    flow's source grid. target (H,W) or (H,W,C) float; flow (H,W,2)."""
    h, w = flow.shape[:2]
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(np.ascontiguousarray(target, dtype=np.float32), cols + flow[..., 0], rows + flow[..., 1],
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def consistent_flow(forward: np.ndarray, backward: np.ndarray, tolerance_px: float) -> np.ndarray:
    """(H,W) bool forward-backward consistency: ``|F(x) + B(x + F(x))| < tolerance_px`` and
    ``x + F(x)`` inside the image. Fails at occlusions and where the flow is wrong (a pixel of the
    render whose partner in the photograph is background or another body part)."""
    h, w = forward.shape[:2]
    back = warp(backward, forward)
    error = np.linalg.norm(forward + back, axis=-1)
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    inside = ((cols + forward[..., 0] >= 0) & (cols + forward[..., 0] <= w - 1)
              & (rows + forward[..., 1] >= 0) & (rows + forward[..., 1] <= h - 1))
    return (error < float(tolerance_px)) & inside
