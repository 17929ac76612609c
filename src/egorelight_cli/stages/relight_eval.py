"""Scoring relit renders like the paper (Sec. "Relighting Experiments"), against the captured images.

A view is scored on the metric tone mapping (:func:`~egorelight_cli.render.image_metrics.tonemap_for_metrics`)
inside the subject mask, with the head region excluded (the avatar is trained without the HMD,
the test frames show it): pixels where the render's ``head`` pass covers more than half of its
alpha and, with a calibration, the worn headset's pixels (:class:`HeadsetExclusion`; it sticks
out in front of the face, where the headset-less avatar draws nothing). PSNR (dB) and SSIM (x100)
for the model, its diffuse part alone ("without SpecularNet"), and the baselines: the Lambert
relighting of the flat-lit texture ``a chi / (pi rho s_flat)`` and the baked flat-lit texture,
all rendered with the model's Gaussians. LPIPS and FID need pretrained networks that cannot be downloaded: ``null``.

Per body part of the character's segmentation (:func:`part_groups`: e.g. ``pants``, the simulated
subject's shiny garment, ``upper_clothes``, its matte one) the same rows are scored again in the
pixels the part covers (its render pass over half of the alpha), as ``metrics["parts"][name][row]``
(per view ``part.<name>.<row>`` in ``scores.npz``): whether SpecularNet helps shows on the glossy
materials, not in the whole-body mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.geometry.headset import HEADSET_MARGIN_M, headset_box, headset_mask
from egorelight_cli.geometry.rotations import camera_centre
from egorelight_cli.io.capture import Capture
from egorelight_cli.render.gaussians import GaussianRender
from egorelight_cli.render.image_metrics import psnr, ssim, tonemap_for_metrics
from egorelight_cli.structures.calibration import Calibration, HeadPoses

#: metric prefix -> the tone-mapped image it scores (``render``: the model's colour, else a render pass)
ROWS = {"": "render", "diffuse_only_": "diffuse", "lambert_": "lambert", "baked_": "baked"}


SCORES_NPZ = "scores.npz"
#: light patterns of a sequence's robustness tail (one light at a time, a random group of lights:
#: synth's ``light_tail``), scored apart from its HDR-lit (``envmap``) frames as ``<pattern>_tail_*``
TAIL_PATTERNS = ("olat", "group")
SCORED_PATTERNS = ("envmap",) + TAIL_PATTERNS


class RelightScores:
    """Per-view PSNR/SSIM of the model and its baselines (one row per :meth:`start_view`)."""

    def __init__(self):
        self.views: list[dict[str, float]] = []

    def start_view(self) -> None:
        self.views.append({})

    def add(self, key: str, value: float) -> None:
        self.views[-1][key] = value

    def arrays(self) -> dict[str, np.ndarray]:
        """Per-view rows by score name (NaN where a view has no such score: an empty region)."""
        names = sorted({k for view in self.views for k in view})
        return {k: np.array([view.get(k, np.nan) for view in self.views], np.float64) for k in names}

    def metrics(self, patterns: np.ndarray | None = None) -> dict:
        return relight_metrics(self.arrays(), patterns)


def relight_metrics(rows: dict[str, np.ndarray], patterns: np.ndarray | None = None) -> dict:
    """Each score's mean over the views that have it (``rows``: :meth:`RelightScores.arrays`, or
    the merged rows of frame shards), and ``null`` LPIPS/FID with the reason.

    With the per-view light ``patterns``, the plain metrics are the HDR-lit (``envmap``) views' and
    each tail pattern present gets its own ``<pattern>_tail_<score>`` means (:data:`TAIL_PATTERNS`)."""
    def means(select: np.ndarray, prefix: str = "") -> dict:
        return {prefix + key: float(np.nanmean(v[select])) if np.isfinite(v[select]).any() else float("nan")
                for key, v in rows.items()}

    if patterns is None:
        out = means(np.ones(len(next(iter(rows.values()), [])), bool)) if rows else {}
    else:
        patterns = np.asarray(patterns).astype(str)
        out = means(patterns == "envmap")
        for pattern in TAIL_PATTERNS:
            if (patterns == pattern).any():
                out.update(means(patterns == pattern, f"{pattern}_tail_"))
                out[f"{pattern}_tail_views"] = int((patterns == pattern).sum())
    if "headset_excluded_fraction" in rows:  # NaN: a view whose frame calibration gave no head pose
        out["headset_unposed_views"] = int(np.isnan(rows["headset_excluded_fraction"]).sum())
    out.update({"lpips": None, "fid": None, "lpips_fid": "need pretrained AlexNet/Inception weights: not scored"})
    return _nest_parts(out)


def _nest_parts(metrics: dict) -> dict:
    """Move the per-part means (``[<pattern>_tail_]part.<name>.<score>``) under ``metrics["parts"][name]``
    as ``[<pattern>_tail_]<score>``."""
    out, parts = {}, {}
    for key, value in metrics.items():
        prefix, found, rest = key.partition(PART_KEY)
        if not found:
            out[key] = value
            continue
        name, _, score = rest.partition(".")
        parts.setdefault(name, {})[prefix + score] = value
    if parts:
        out["parts"] = dict(sorted(parts.items()))
    return out


def merged_metrics(root, manifests: list[dict]) -> dict:
    """The metrics of merged frame shards (:func:`egorelight_cli.sharding.merge_parts`) from the
    merged ``scores.npz``, as a single run computes them."""
    from pathlib import Path

    from egorelight_cli.io.npz import read_npz

    rows, _ = read_npz(Path(root) / SCORES_NPZ, check_finite=False)
    first = manifests[0]["metrics"]
    metrics = {k: first[k] for k in ("sequence", "cameras", "lighting", "headset_excluded") if k in first}
    metrics["views"] = int(len(rows["frame_ids"]))
    if "scored" in first:
        return {**metrics, "scored": first["scored"]}
    return {**metrics, **relight_metrics({k: v for k, v in rows.items() if k not in VIEW_KEYS}, rows.get("light"))}


#: per-view columns of ``scores.npz`` that are not scores: the frame, the camera, its light pattern
VIEW_KEYS = ("frame_ids", "camera", "light")


def tonemapped(render: GaussianRender, names) -> dict[str, torch.Tensor]:
    """The render's colour (``render``) or passes ``names`` on the metric tone mapping, (H,W,3) in [0,1]."""
    return {name: tonemap_for_metrics(render.colour if name == "render" else render.passes[name]) for name in names}


def _uint8(images: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    return {k: (v.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8) for k, v in images.items()}


def display_images(render: GaussianRender) -> dict:
    """The render and its baseline passes on the metric tone mapping, uint8 (H,W,3) by name."""
    return _uint8(tonemapped(render, ("render", "lambert", "baked")))


#: segmentation names that make up the head: excluded from every score, never a part of their own
HEAD_PARTS = ("hair", "face")
#: per-view score names of a part start with ``part.<name>.``
PART_KEY = "part."
#: render pass holding the per-part coverage (one channel per :func:`part_groups` entry)
PARTS_PASS = "parts"


def part_groups(segmentation_names: dict[int, str]) -> dict[str, list[int]]:
    """The character's segmentation labels grouped into the parts scored apart: the left and
    right of a limb form one part (``left_leg`` + ``right_leg`` -> ``leg``); the head parts
    (:data:`HEAD_PARTS`) are left out. Ordered by name."""
    groups: dict[str, list[int]] = {}
    for label, name in sorted(segmentation_names.items()):
        if name in HEAD_PARTS:
            continue
        groups.setdefault(name.removeprefix("left_").removeprefix("right_"), []).append(int(label))
    return dict(sorted(groups.items()))


def part_channels(segmentation: np.ndarray, groups: dict[str, list[int]], vertex_of_texel: np.ndarray) -> torch.Tensor:
    """(N,P) float32 one-hot part of each texel (``vertex_of_texel`` (N,): a vertex of its face)
    over the parts ``groups`` (:func:`part_groups`), for the :data:`PARTS_PASS` render pass."""
    labels = segmentation[vertex_of_texel]
    return torch.from_numpy(np.stack([np.isin(labels, ids) for ids in groups.values()], axis=1).astype(np.float32))


def _covered(render: GaussianRender, name: str) -> torch.Tensor:
    """(H,W,C) bool: pixels where the pass ``name`` holds over half of the render's alpha."""
    return render.passes[name] > 0.5 * render.alpha.clamp_min(1e-6)[..., None]


def _add_rows(scores: RelightScores, display: dict, region: torch.Tensor, prefix: str = "") -> None:
    for row, name in ROWS.items():
        scores.add(f"{prefix}{row}psnr", float(psnr(display[name], display["target"], region)))
        scores.add(f"{prefix}{row}ssim", 100.0 * float(ssim(display[name], display["target"], region)))


def score_view(scores: RelightScores, render: GaussianRender, target: torch.Tensor, mask: torch.Tensor,
               parts: tuple[str, ...] = (), headset: torch.Tensor | None = None, unposed_headset: bool = False) -> dict:
    """Score one render against its captured image, in the subject ``mask`` without the head (the
    render's head and, when given, the ``headset`` (H,W) bool pixels of :class:`HeadsetExclusion`;
    ``unposed_headset``: they should have been, but the frame has no head pose),
    and per part of ``parts`` (the channels of the render's :data:`PARTS_PASS`, when given; a
    part covering fewer than 16 scored pixels gets no row). Returns the tone-mapped uint8 images by name."""
    head = _covered(render, "head")[..., 0]
    if headset is not None:
        scores.add("headset_excluded_fraction", _fraction(headset & ~head, mask))
        head = head | headset
    elif unposed_headset:
        scores.add("headset_excluded_fraction", float("nan"))
    region = mask & ~head
    display = {"target": tonemap_for_metrics(target), **tonemapped(render, ROWS.values())}
    if bool(region.any()):
        _add_rows(scores, display, region)
        covered = _covered(render, PARTS_PASS) if parts else None
        for k, part in enumerate(parts):
            part_region = region & covered[..., k]
            if int(part_region.sum()) >= 16:
                _add_rows(scores, display, part_region, f"{PART_KEY}{part}.")
    scores.add("head_excluded_fraction", _fraction(head, mask))
    return _uint8(display)


def _fraction(pixels: torch.Tensor, mask: torch.Tensor) -> float:
    """The fraction of ``mask``'s pixels (H,W bool) that ``pixels`` (H,W bool) covers; 0 for an empty mask."""
    return float(pixels[mask].float().mean()) if bool(mask.any()) else 0.0


#: the manifest's ``headset_excluded`` without a calibration
HEADSET_NOT_EXCLUDED = ("no: without --calibration the worn headset's pixels outside the rendered head are scored "
                        "(the avatar has no headset)")


@dataclass(frozen=True)
class HeadsetExclusion:
    """The worn headset's pixels in a sequence's studio views (:mod:`egorelight_cli.geometry.headset`):
    a box around the HMD markers (``rig/hmd.json``) and the ego cameras (the calibration's hand-eye),
    posed by the calibration's head poses of the sequence. Part of the head region the scores
    exclude: the avatar is trained and rendered without a headset.

    ``box`` (2,3): the box's min and max corners, metres, in the HMD frame; ``poses``: the
    sequence's head poses (``T_world_from_hmd`` per frame)."""

    box: np.ndarray
    poses: HeadPoses

    @classmethod
    def from_calibration(cls, capture: Capture, calibration: Calibration, sequence: str) -> "HeadsetExclusion":
        from egorelight_cli.stages.calibrate_head import MarkerLayout

        if sequence not in calibration.head_poses:
            raise EgorelightError(f"calibration has no head poses for sequence {sequence!r} (the headset's place "
                                  "in its views)", calibration.source)
        if not calibration.head_poses_in_studio_world(sequence):
            raise EgorelightError(f"the calibration's head poses of sequence {sequence!r} are not in the studio's "
                                  "world: they cannot place the headset in its studio views", calibration.source)
        corners = np.stack(list(MarkerLayout.from_hmd(capture).corners.values()))
        centres = [camera_centre(cam.T_cam_from_hmd) for cam in calibration.ego_cameras.values()]
        return cls(headset_box(corners, np.reshape(centres, (-1, 3))), calibration.head_poses[sequence])

    def pixels(self, frame_id: int, camera: Camera, render: GaussianRender) -> torch.Tensor | None:
        """(H,W) bool headset pixels of ``camera`` at ``frame_id`` that ``render`` does not cover
        in front of the headset (alpha over half, depth nearer than the box); None where
        calibration has no valid head pose for the frame (nothing is excluded then: counted as
        ``headset_unposed_views``)."""
        T_world_from_hmd = self.poses.valid_pose(frame_id)
        if T_world_from_hmd is None:
            return None
        inside, nearest_m = headset_mask(self.box, T_world_from_hmd, camera)
        in_front = (render.alpha > 0.5) & (render.expected_depth < nearest_m)
        return torch.from_numpy(inside) & ~in_front

    def describe(self) -> str:
        size_cm = 100 * (self.box[1] - self.box[0])
        return (f"yes: a {size_cm[0]:.0f} x {size_cm[1]:.0f} x {size_cm[2]:.0f} cm box around the HMD markers and ego "
                f"cameras (margin {100 * HEADSET_MARGIN_M:g} cm), posed by the calibration's head poses")
