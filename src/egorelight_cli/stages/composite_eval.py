"""Scoring a ``composite`` against the simulator's truth (evaluation code only).

**The truth composite.** The oracle renderer (:class:`~egorelight_cli.synth.oracle.Oracle`) renders
the TRUE subject of User 1's frame (true surface and materials, no headset) from the same camera
moved into the studio frame by the same placement, under the TRUE light of User 2's sequence: the
wild map of ``groundtruth/envmaps`` turned by the yaw of ``groundtruth/<seq>/surroundings.json``,
expressed in the frame of the calibrated head poses
(:func:`~egorelight_cli.stages.envmap_eval.wild_truth`) and then by the placement's yaw, on the
virtual dome the simulator lights the wild sequence with (:meth:`Oracle.dome`). Its radiance goes
through the TRUE response of the background camera (``groundtruth/ego_response.json``: exposure,
colour matrix, clipping, sRGB, 8 bits; no noise) and replaces the background where the oracle's
mask is set.

**Metrics** per row: PSNR and SSIM (x100) of the 8-bit composites (in [0,1]) over the avatar mask =
the render's alpha > 0.5 or the truth's mask (:mod:`egorelight_cli.render.image_metrics`), pooled
over the masked pixels of every frame where the avatar or the truth covers pixels (PSNR of the
pooled squared error, SSIM the mean of its map over all masked pixels: a frame where the avatar
only enters the image with a few pixels weighs by those pixels, not as much as a whole body), and
the masks' IoU (mean over those frames). Rows:

* ``composite``: the stage's output (light ``S(E_h)``, the avatar mapped by ``colour.inverse``);
* ``flat_studio``: the avatar under the light stage's flat light at the same mean luminance as
  ``S(E_h)`` (no direction, no colour of the room), same colour mapping;
* ``ldr_panorama_only`` (when the envmap's colour model is not the identity): the light of the
  LDR panorama itself, ``E_l`` = the inverse colour model applied to ``E_h``, and no colour
  mapping (the paper's "no inverse rendering" ablation carried to the composite);
* ``true_light`` (an oracle, not a baseline): the avatar under the TRUE light through the TRUE
  response of the camera (exposure and colour matrix, over the studio exposure): what a perfect
  ``envmap`` would give this avatar, so the gap between it and the truth is the avatar's own
  (geometry, appearance).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from egorelight_cli import console
from egorelight_cli.stages.envmap_eval import LUMINANCE

ROWS = ("composite", "flat_studio", "ldr_panorama_only", "true_light")


@dataclass
class Evaluation:
    """``metrics`` for the manifest, contact-sheet rows (label, images), seconds spent."""

    metrics: dict
    sheet_rows: list = field(default_factory=list)
    seconds: float = 0.0


def frame_errors(image: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(4,) float64 [sum of squared errors, values, sum of SSIM, SSIM pixels] of uint8 images
    (H,W,3) in [0,1] over ``mask`` (H,W) (SSIM: the masked pixels inside its cropped border)."""
    from egorelight_cli.render.image_metrics import masked_ssim_sum

    a = torch.from_numpy(image.astype(np.float64) / 255.0)
    b = torch.from_numpy(truth.astype(np.float64) / 255.0)
    m = torch.from_numpy(mask)
    similarity, count = masked_ssim_sum(a, b, m)
    return np.array([float(((a - b) ** 2)[m].sum()), 3.0 * float(m.sum()), float(similarity), float(count)])


def pooled_scores(errors: list[np.ndarray]) -> dict:
    """``{"psnr": dB, "ssim": x100}`` of :func:`frame_errors` rows pooled over their pixels (None
    where nothing was scored)."""
    total = np.sum(errors, axis=0) if errors else np.zeros(4)
    psnr = -10.0 * np.log10(max(total[0] / total[1], 1e-20)) if total[1] > 0 else None
    return {"psnr": None if psnr is None else float(psnr),
            "ssim": 100.0 * float(total[2] / total[3]) if total[3] > 0 else None}


def flat_light(lightstage, reference: np.ndarray) -> np.ndarray:
    """(L,3) the stage's flat light scaled to the mean luminance of ``reference`` (L,3)."""
    flat = lightstage.flat(1.0)
    level = float((np.asarray(reference) @ LUMINANCE).mean())
    return flat * (level / max(float((flat @ LUMINANCE).mean()), 1e-12))


def evaluate(capture, calibration, seq: str, role: str, avatar_sequence: str, placement, views, composites, alphas,
             render_row: Callable, envmap: np.ndarray, colour, mapping, lightstage, light: torch.Tensor,
             iterations: int = 20) -> Evaluation | None:
    """The module docstring's scores, or None without ground truth. ``alphas``: the avatar's
    masks (H,W) per view (alpha > 0.5); ``colour`` the envmap's colour model, ``mapping`` the
    composite's :class:`~egorelight_cli.nn.colour_inverse.CameraMapping`; ``render_row(light (L,3),
    mapping or None) -> composites`` renders a row over the same views."""
    from egorelight_cli.nn.colour_inverse import CameraMapping, invert_colour
    from egorelight_cli.nn.colour_model import identity_matrix
    from egorelight_cli.render.camera_response import CameraResponse
    from egorelight_cli.stages.envmap_eval import wild_truth
    from egorelight_cli.synth.oracle import Oracle

    root = capture.groundtruth_root()
    if root is None or not (root / "groundtruth" / avatar_sequence / "meshes.npz").is_file():
        return None
    poses = calibration.head_poses[seq]
    truth = wild_truth(capture, calibration, seq, poses.frame_ids[poses.valid])
    responses = root / "groundtruth" / "ego_response.json"
    if truth is None or not responses.is_file():
        return None
    started = time.perf_counter()
    response = CameraResponse.from_dict(json.loads(responses.read_text())[role])
    oracle = Oracle(root)
    dome = oracle.dome()
    truths, masks = [], []
    for view in console.progress(views, total=len(views), desc="composite truth"):
        render = oracle.render(avatar_sequence, view.avatar_frame, view.studio_camera,
                               lighting=(truth.envmap, -placement.yaw_deg), lights=dome, hmd=False)
        ldr = response.apply(render.radiance / oracle.exposure)
        truths.append(np.where(render.mask[..., None], ldr, view.background))
        masks.append(render.mask)
    rows = {"composite": composites}
    rows["flat_studio"] = render_row(torch.from_numpy(flat_light(lightstage, light.numpy())), mapping)
    identity = np.allclose(colour.A.detach().numpy(), identity_matrix()) and abs(float(colour.gamma) - 1) < 1e-9
    if not identity:
        E_l, _ = invert_colour(colour, envmap, iterations)
        rows["ldr_panorama_only"] = render_row(
            torch.from_numpy(lightstage.envmap_to_intensities(E_l, -placement.yaw_deg)), None)
    true_light = torch.from_numpy(lightstage.envmap_to_intensities(truth.envmap, -placement.yaw_deg))
    # the avatar renders studio HDR (radiance x the studio exposure), the truth scene radiance
    camera = response.exposure * response.colour_matrix / oracle.exposure
    rows["true_light"] = render_row(true_light, CameraMapping("linear", matrix=camera))
    errors = {name: [] for name in rows}
    ious = []
    for k, (truth_image, truth_mask) in enumerate(zip(truths, masks)):
        avatar_mask = alphas[k]
        mask = truth_mask | avatar_mask
        if not mask.any():
            continue
        ious.append(float((truth_mask & avatar_mask).sum() / mask.sum()))
        for name, images in rows.items():
            errors[name].append(frame_errors(images[k], truth_image, mask))
    metrics = {"truth_envmap": truth.name, "truth_frame_yaw_deg": truth.frame_yaw_deg, "scored_frames": len(ious),
               "mask_iou": float(np.mean(ious)) if ious else None,
               "colour_model_identity": bool(identity)}
    table = {name: pooled_scores(values) for name, values in errors.items()}
    metrics["rows"] = table
    metrics["psnr"], metrics["ssim"] = table["composite"]["psnr"], table["composite"]["ssim"]
    for name in rows:
        if name != "composite":
            metrics[f"{name}_psnr"], metrics[f"{name}_ssim"] = table[name]["psnr"], table[name]["ssim"]
    sheet = [("truth: true subject, true wild light, true camera response", truths)]
    sheet += [(f"{'oracle' if name == 'true_light' else 'baseline'} {name}", images)
              for name, images in rows.items() if name != "composite"]
    return Evaluation(metrics, sheet, time.perf_counter() - started)
