"""``envmap`` step 4: the colour model ``E_h = A . phi(E_l ** gamma)`` fitted by inverse rendering
of the relightable avatar into the down-facing HMD cameras (paper Eqs. ``inv-render``,
``forward-render`` and supplement).

    argmin_{A, gamma}  mean_views  sum_s w_s L1(M_v I_render . M_s, O^-1(I_ego) . M_s)  +  w_reg L_reg(E_h)
    I_render = H(V, K Pi H; S(E_h))

* ``H`` is the frozen :class:`~egorelight_cli.stages.relight.RelightModel` on the tracked mesh
  ``V`` of a wild frame, rendered (:func:`~egorelight_cli.stages.relight.render_relit`) into the
  down-facing fisheye camera posed by the calibration
  (:func:`~egorelight_cli.io.calibration.posed_ego_camera`). The network's lighting inputs are
  recomputed differentiably from the light vector ``e = S(E_h)``
  (:class:`~egorelight_cli.render.lighting.EnvmapPooling`): the irradiance map
  ``chi = G @ (gain e)`` from the frame's cached per-texel light transfer ``G`` (N,L) (with the
  lifted normals and the mesh's shadows, exactly as ``geolift`` computes it), the Lambert term,
  and the rays' ``G_l gain_l e_l``. So gradients flow image -> Gaussians -> networks -> chi ->
  ``e`` -> ``E_h`` -> ``A, gamma``.
* ``M_v`` (3,3, per down role): the **colour synchronisation** between the avatar's HDR space (the
  studio cameras' linear radiance) and the down camera's linearised sRGB (exposure, colour
  cross-talk, white balance). Fitted once in the studio where the light is known
  (:func:`fit_colour_sync`): the avatar is rendered under the recorded light entry (flat) of
  studio frames of a sequence with ego images (``ego_train``) into the down cameras posed by the
  calibration, the ego images are aligned to the renders by the flow below, and ``M`` is the
  least-squares solution ``ego ~ M render`` over unclipped pixels of the observed body (or a gain
  per channel, ``inverse.sync.model``: :func:`sync_matrix`). The simulator (and a real headset at
  fixed exposure) keeps each camera's response over sequences, so the matrix transfers to the wild.
* ``O^-1(I_ego)``: the linearised ego image (inverse sRGB) warped onto the render by optical flow
  from the render to the ego image (:mod:`egorelight_cli.render.optical_flow`: OpenCV DIS; RAFT
  only from a local weights path), estimated once from the render under the initial model. A view
  whose flow is consistent on less than ``flow.min_consistent`` of the rendered body (a render
  too unlike the photograph for the flow to find correspondences) keeps the ego image unwarped
  (counted in the manifest).
* ``M_s``: body-part masks, the intersection of the render's parts (the character's segmentation,
  per texel, rendered as a pass) with an **observed body mask** obtained without ground truth:
  render pixels whose flow is forward-backward consistent (a render pixel whose partner in the
  ego image is background or another part breaks the consistency, as does a flow longer than
  ``flow.max`` of the image size: more than the tracking error), with the render's mask
  eroded by ``mask_erode_px`` (silhouette pixels mix background), not clipped in the ego
  image, and with the render's expected depth at least ``min_depth_m`` from the camera: a hand or
  arm at the lens (the demo's studio frames have them 1-2 cm away) is splatted with a local affine
  fisheye projection whose footprint covers the whole image, so such pixels (and views) say
  nothing about colour (measured on the cpu demo: one such view among the 3 synchronisation frames
  put the down-right gain at 0.72 against a true 1.02, with off-diagonal terms up to 1.5). Parts: upper body, lower body, arms, legs, shoes (the head is under the headset).
  Each part's L1 is a mean over its pixels and the parts weigh equally (the ego view is
  dominated by the upper body: this keeps one garment's tone from deciding the colour).
* ``L_reg(E_h) = ||max(E_h / r - 1, 0)||_2 + ||max(-E_h / r, 0)||_2`` (RMS over texels and
  channels): the paper's [0,1] range with ``r = reg_max`` the radiance the avatar's training light
  reached (``auto``: the 99.9th percentile of the capture's own environment maps).

Adam on ``A`` (init ``[I | 0]``) and ``log gamma`` (init 0), ``steps`` steps (paper 1000), a
random ``views_per_step`` subset of the views per step. Ablation rows (:data:`ROWS`) re-run the
fit without the flow or without the part masks, and without the panorama: a free low-resolution
map (:class:`FreeEnvmap`, ``free_map_height`` rows) fitted by the same objective from the ego
images alone, so the panorama's contribution is measured.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera
from egorelight_cli.io.images import srgb_to_linear, to_unit_float
from egorelight_cli.nn.colour_model import RootPolynomialColour, channel_gains
from egorelight_cli.render import optical_flow as of
from egorelight_cli.render.lighting import EnvmapPooling
from egorelight_cli.render.uv_features import irradiance_map, shadow_map, texel_lighting, texel_map
from egorelight_cli.stages import relight as rl
from egorelight_cli.stages.relight_commands import RelightData

#: Body parts of the loss: name -> the character's segmentation names in it.
PARTS = {"upper_body": ("upper_clothes",), "lower_body": ("pants",), "arms": ("left_arm", "right_arm"),
         "legs": ("left_leg", "right_leg"), "shoes": ("left_shoe", "right_shoe")}
#: Rows of the fit: name -> (use the flow, use the part masks, fit a :class:`FreeEnvmap` instead of the
#: colour model of the panorama).
ROWS = {"fitted": (True, True, False), "no_flow": (False, True, False), "no_part_masks": (True, False, False),
        "no_panorama": (True, True, True)}
#: The avatar image the fit compares with the ego images: ``full`` (``c_diff + c_spec``) or ``diffuse``
#: (``c_diff`` alone: SpecularNet never saw the down cameras' grazing, from-above view directions).
IMAGE_PASSES = ("full", "diffuse")
FREE_MAP_INIT = 0.5  # the free map's start: a uniform grey of the LDR panorama's mid level


class FreeEnvmap(torch.nn.Module):
    """The ``no_panorama`` row: a free (h,2h,3) map ``softplus(x)`` (non-negative), upsampled
    bilinearly (with wrap-around in longitude) to the panorama's size; it ignores the panorama.
    Same interface as :class:`~egorelight_cli.nn.colour_model.RootPolynomialColour`."""

    def __init__(self, height: int, init: float = FREE_MAP_INIT):
        super().__init__()
        if height < 1:
            raise EgorelightError(f"inverse.free_map_height must be >= 1, got {height}")
        start = float(np.log(np.expm1(init)))  # softplus^-1
        self.logits = torch.nn.Parameter(torch.full((3, height, 2 * height), start, dtype=torch.float64))

    def forward(self, panorama: torch.Tensor) -> torch.Tensor:
        height, width = panorama.shape[0], panorama.shape[1]
        padded = torch.cat([self.logits[..., -1:], self.logits, self.logits[..., :1]], dim=-1)  # wrap longitude
        scale = width / self.logits.shape[-1]
        up = F.interpolate(padded[None], size=(height, int(round(padded.shape[-1] * scale))), mode="bilinear",
                           align_corners=False)[0]
        border = int(round(scale))
        return F.softplus(up[..., border:border + width]).permute(1, 2, 0).to(panorama.dtype)

    def apply_numpy(self, panorama: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self(torch.from_numpy(np.asarray(panorama, np.float64))).numpy().astype(np.float32)

    def to_json(self, **extra) -> dict:
        return {"model": "free low-resolution map (no panorama)", "height": int(self.logits.shape[1]), **extra}


@dataclass(frozen=True)
class InverseSettings:
    """The ``inverse`` config section (see ``stages/envmap.yaml``)."""

    roles: tuple[str, ...]
    frames: int
    steps: int
    lr: float
    views_per_step: int
    reg_weight: float
    reg_max: float | None
    flow: str
    raft_weights: str | None
    flow_tolerance: float
    flow_max: float
    flow_min_consistent: float
    mask_erode_px: int
    min_depth_m: float
    sync_frames: int
    sync_patterns: tuple[str, ...]
    rows: tuple[str, ...]
    free_map_height: int = 8
    image_pass: str = "full"
    sync_model: str = "matrix"

    @classmethod
    def from_config(cls, cfg) -> InverseSettings:
        c = cfg.inverse
        reg_max = None if str(c.reg_max) == "auto" else float(c.reg_max)
        rows = tuple(c.rows)
        settings = cls(tuple(c.roles), int(c.frames), int(c.steps), float(c.lr), int(c.views_per_step),
                       float(c.reg_weight), reg_max, str(c.flow.method), c.flow.raft_weights or None,
                       float(c.flow.tolerance), float(c.flow.max), float(c.flow.min_consistent), int(c.mask_erode_px),
                       float(c.min_depth_m), int(c.sync.frames),
                       tuple(c.sync.patterns), rows, int(c.free_map_height), str(c.image_pass), str(c.sync.model))
        of.flow_method(settings.flow, settings.raft_weights)  # an unknown method fails here
        # value ranges: the checks of stages/envmap.yaml
        if "fitted" not in rows:
            raise EgorelightError(f"inverse.rows must hold 'fitted' and only {', '.join(ROWS)} (got {', '.join(rows)})")
        return settings


class EgoAvatarData(RelightData):
    """:class:`RelightData` of a sequence seen by the HMD cameras, whose lighting features are
    recomputed from each frame's per-texel light transfer ``G`` (N,L) (lifted normals, the mesh's
    shadows) so that any light vector, a differentiable one included, relights it
    (:meth:`lit`). Reads only the ``albedo`` and ``normal`` layers of the uvmaps (a sequence
    without a light entry, ``wild``, has no ``shadow``/``diffuse`` layers)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._transfer: dict[int, torch.Tensor] = {}

    def transfer(self, frame_id: int) -> torch.Tensor:
        if frame_id not in self._transfer:
            normals = self.read_maps(frame_id, ("normal",))["normal"][self.raster.coverage]
            lit = texel_lighting(self.raster, self.vertices(frame_id), self.character.faces, self.lightstage, normals)
            self._transfer[frame_id] = lit.transfer
        return self._transfer[frame_id]

    def known_intensities(self, frame_id: int) -> np.ndarray:
        """(L,3) the frame's recorded light entry (zeros when the sequence records none)."""
        if not self.sequence.lights:
            return np.zeros((self.lightstage.num_lights, 3))
        return super().known_intensities(frame_id)

    def frame(self, frame_id: int) -> rl.RelightFrame:
        if frame_id not in self._frames:
            maps = self.read_maps(frame_id, ("albedo", "normal"))
            transfer = self.transfer(frame_id)
            intensities = self.known_intensities(frame_id)
            maps["shadow"] = texel_map(self.raster.coverage, shadow_map(transfer).numpy()[:, None])
            maps["diffuse"] = texel_map(self.raster.coverage,
                                        irradiance_map(transfer, self.lightstage, intensities).float().numpy())
            self._frames[frame_id] = self.assemble(frame_id, maps, intensities)
        return self._frames[frame_id]

    def lit(self, frame_id: int, intensities: torch.Tensor) -> rl.RelightFrame:
        """The frame under light vector ``intensities`` (L,3) (differentiable)."""
        chi = irradiance_map(self.transfer(frame_id), self.lightstage, intensities)
        return rl.relit_frame(self.frame(frame_id), self.coverage, chi, intensities)


def texel_parts(character, raster) -> torch.Tensor:
    """(N,K) float32 one-hot :data:`PARTS` membership of the covered texels (majority label of
    each texel's face corners); rows of zeros for texels in no part (head)."""
    names = character.segmentation_names
    labels = character.segmentation[character.faces[raster.face_id[raster.coverage]]]  # (N,3)
    majority = np.where(labels[:, 1] == labels[:, 2], labels[:, 1], labels[:, 0])
    out = np.zeros((len(majority), len(PARTS)), np.float32)
    for k, members in enumerate(PARTS.values()):
        out[:, k] = np.isin(majority, [label for label, name in names.items() if name in members])
    return torch.from_numpy(out)


@dataclass
class EgoView:
    """One down-facing view of one frame.

    Attributes:
        frame_id: master-clock frame id. role: HMD camera role. camera: posed by the calibration.
        ego: (H,W,3) float32 the linearised ego image. unclipped: (H,W) bool ego pixels below 8-bit
        saturation (and above black).
        target: (H,W,3) float32 tensor, the ego image on the render's pixels (warped or not).
        masks: (K,H,W) bool tensor, the part masks ``M_s`` (or one whole-body mask).
        flow_consistent_fraction: consistent flow pixels / rendered body pixels.
        near_fraction: rendered body pixels closer than ``min_depth_m`` / rendered body pixels.
        flow_used: False when the flow was not consistent enough and the ego image was used unwarped.
    """

    frame_id: int
    role: str
    camera: Camera
    ego: np.ndarray
    unclipped: np.ndarray
    target: torch.Tensor | None = None
    masks: torch.Tensor | None = None
    flow_consistent_fraction: float = float("nan")
    flow_used: bool = False
    near_fraction: float = float("nan")


def ego_view(data: RelightData, calibration, frame_id: int, role: str) -> EgoView:
    """The view of ``role`` at ``frame_id``: posed camera and linearised image."""
    from egorelight_cli.io.calibration import posed_ego_camera

    camera = posed_ego_camera(data.capture, calibration, role, data.sequence.name, frame_id)
    codes = data.sequence.read_ego_image(role, calibration.ego_frame_id(data.sequence.name, frame_id))
    if codes.shape[:2] != (camera.height, camera.width):
        raise EgorelightError(f"{role} image is {codes.shape[1]}x{codes.shape[0]}, the HMD description says "
                              f"{camera.width}x{camera.height}")
    unit = to_unit_float(codes)[..., :3]
    unclipped = (unit.max(axis=-1) < 0.995) & (unit.max(axis=-1) > 0.01)
    return EgoView(frame_id, role, camera, srgb_to_linear(unit).astype(np.float32), unclipped)


def render_view(model: rl.RelightModel, data: EgoAvatarData, view: EgoView, intensities: torch.Tensor,
                parts: torch.Tensor, image_pass: str = "full"):
    """The avatar of ``view.frame_id`` under ``intensities`` (L,3) in ``view.camera``: a
    :class:`~egorelight_cli.render.gaussians.GaussianRender` with pass ``parts`` (H,W,K) whose
    ``colour`` is the image of ``image_pass`` (:data:`IMAGE_PASSES`)."""
    if image_pass not in IMAGE_PASSES:
        raise EgorelightError(f"inverse.image_pass must be one of {', '.join(IMAGE_PASSES)}, got {image_pass!r}")
    frame = data.lit(view.frame_id, intensities)
    rays, valid = rl.camera_rays(data.ray_lighting(view.frame_id), intensities, view.camera.centre_world,
                                 data.lightstage, data.rays)
    render, _ = rl.render_relit(model, frame, data.coverage, view.camera, rays, valid, extra_passes={"parts": parts})
    return render if image_pass == "full" else dataclasses.replace(render, colour=render.passes["diffuse"])


def observe(view: EgoView, render_rgb: np.ndarray, alpha: np.ndarray, part_weights: np.ndarray, depth: np.ndarray,
            use_flow: bool, use_parts: bool, settings: InverseSettings, method: str) -> None:
    """Set ``view.target`` and ``view.masks`` from a render (rgb (H,W,3), alpha (H,W), part
    pass (H,W,K), expected depth (H,W) metres) of the view: the module docstring's warp and
    observed masks."""
    import cv2

    body = alpha > 0.5
    near = body & (depth < settings.min_depth_m)
    view.near_fraction = float(near.sum() / max(body.sum(), 1))
    labels = np.where(part_weights.max(axis=-1) > 0.5 * np.maximum(alpha, 1e-6), part_weights.argmax(axis=-1), -1)
    size = 2 * settings.mask_erode_px + 1
    eroded = cv2.erode(body.astype(np.uint8), np.ones((size, size), np.uint8)) > 0 if settings.mask_erode_px else body
    target, unclipped = view.ego, view.unclipped
    observed = eroded.copy()
    if use_flow:
        render_grey = of.flow_image(render_rgb, body)
        ego_grey = of.flow_image(view.ego, view.unclipped)
        forward = of.estimate_flow(render_grey, ego_grey, method, settings.raft_weights)
        backward = of.estimate_flow(ego_grey, render_grey, method, settings.raft_weights)
        scale = float(max(body.shape))
        consistent = of.consistent_flow(forward, backward, settings.flow_tolerance * scale)
        consistent &= np.linalg.norm(forward, axis=-1) <= settings.flow_max * scale
        view.flow_consistent_fraction = float((consistent & body).sum() / max(body.sum(), 1))
        view.flow_used = view.flow_consistent_fraction >= settings.flow_min_consistent
        if view.flow_used:
            target = of.warp(view.ego, forward)
            unclipped = of.warp(view.unclipped.astype(np.float32), forward) > 0.999
            observed &= consistent
    observed &= unclipped & ~near
    if use_parts:
        masks = np.stack([observed & (labels == k) for k in range(len(PARTS))])
    else:
        masks = (observed & (labels >= 0))[None]
    view.target = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32))
    view.masks = torch.from_numpy(masks)


def part_l1(image: torch.Tensor, target: torch.Tensor, masks: torch.Tensor) -> torch.Tensor | None:
    """Mean over the non-empty masks (K,H,W) of each mask's mean channel-mean ``|image - target|``
    (images (H,W,3)); None when every mask is empty."""
    residual = (image - target).abs().mean(dim=-1)
    terms = [residual[m].mean() for m in masks if bool(m.any())]
    return torch.stack(terms).mean() if terms else None


def range_regulariser(envmap: torch.Tensor, reg_max: float) -> torch.Tensor:
    """``L_reg``: RMS of ``max(E / reg_max - 1, 0)`` plus RMS of ``max(-E / reg_max, 0)``."""
    r = envmap / reg_max
    return (torch.relu(r - 1.0) ** 2).mean().add(1e-24).sqrt() + (torch.relu(-r) ** 2).mean().add(1e-24).sqrt()


@dataclass
class Fit:
    """A fitted colour model with its loss curve (``[{"step", "loss", "image", "reg"}]``)."""

    colour: RootPolynomialColour
    curve: list[dict]


def fit_colour_model(panorama: torch.Tensor, pooling: EnvmapPooling, views: Sequence,
                     render: Callable[[object, torch.Tensor], torch.Tensor], steps: int, lr: float,
                     views_per_step: int, reg_weight: float, reg_max: float, seed: int = 0,
                     colour: torch.nn.Module | None = None) -> Fit:
    """Adam on ``A`` and ``gamma`` of a :class:`RootPolynomialColour` (from the identity), or on
    the parameters of ``colour`` (any module panorama -> map, e.g. :class:`FreeEnvmap`).

    Args:
        panorama: (H,2H,3) ``E_l`` (float64 tensor).
        pooling: ``S``, built for ``E_l``'s size.
        views: objects with ``target`` (h,w,3) and ``masks`` (K,h,w) tensors.
        render: ``render(view, intensities (L,3)) -> (h,w,3)`` image in the target's colour space,
            differentiable in ``intensities``.
        steps, lr: Adam; views_per_step: views drawn (seeded) per step; reg_weight, reg_max: ``L_reg``.
    """
    usable = [v for v in views if bool(v.masks.any())]
    if not usable:
        raise EgorelightError("no down-facing view has an observed body pixel: nothing to fit the colour model to")
    colour = RootPolynomialColour() if colour is None else colour
    optimiser = torch.optim.Adam(colour.parameters(), lr=lr)
    rng = np.random.default_rng(seed)
    curve = []
    for step in range(steps):
        pick = rng.choice(len(usable), size=min(views_per_step, len(usable)), replace=False)
        optimiser.zero_grad()
        envmap = colour(panorama)
        intensities = pooling(envmap)
        terms = [part_l1(render(usable[i], intensities), usable[i].target, usable[i].masks) for i in pick]
        image = torch.stack([t for t in terms if t is not None]).mean()
        reg = range_regulariser(envmap, reg_max)
        loss = image + reg_weight * reg
        loss.backward()
        optimiser.step()
        curve.append({"step": step, "loss": float(loss.detach()), "image": float(image.detach()), "reg": float(reg.detach())})
    return Fit(colour, curve)


def fit_colour_sync(model: rl.RelightModel, data: EgoAvatarData, calibration, frames: np.ndarray,
                    settings: InverseSettings, parts: torch.Tensor, method: str) -> dict[str, dict]:
    """Per down role ``{"matrix": M (3,3) rows, "gain": mean row sum (grey's gain), "pixels",
    "residual_l1", "frames", "near_fraction": per frame, the rendered body's share left out as too near}``
    with ``ego ~ M render`` (module docstring), from studio ``frames`` under their known light."""
    out = {}
    for role in settings.roles:
        renders, observed, near = [], [], []
        for f in frames:
            view = ego_view(data, calibration, int(f), role)
            with torch.no_grad():
                render = render_view(model, data, view, torch.as_tensor(data.known_intensities(int(f))), parts,
                                     settings.image_pass)
            rgb, alpha = render.colour.numpy(), render.alpha.numpy()
            observe(view, rgb, alpha, render.passes["parts"].numpy(), render.expected_depth.numpy(), True, False,
                    settings, method)
            mask = view.masks[0].numpy() & (alpha > 0.99)
            near.append(view.near_fraction)
            renders.append(rgb[mask])
            observed.append(view.target.numpy()[mask])
        X, Y = np.concatenate(renders).astype(np.float64), np.concatenate(observed).astype(np.float64)
        if len(X) < 30:
            raise EgorelightError(f"colour synchronisation of {role}: only {len(X)} observed body pixels in "
                                  f"{len(frames)} studio frame(s) of {data.sequence.name}")
        M = sync_matrix(X, Y, settings.sync_model)
        residual = float(np.abs(X @ M.T - Y).mean())
        out[role] = {"matrix": M.tolist(), "gain": float(M.sum(axis=1).mean()),
                     "pixels": int(len(X)), "residual_l1": residual, "frames": [int(f) for f in frames],
                     "near_fraction": [round(float(x), 4) for x in near]}
    return out


SYNC_MODELS = ("diagonal", "matrix")


def sync_matrix(render: np.ndarray, ego: np.ndarray, model: str) -> np.ndarray:
    """(3,3) ``M`` with ``ego ~ M render`` by least squares over pixel pairs (P,3) each.

    ``diagonal``: one gain per channel (exposure and white balance). ``matrix``: a full 3x3 (colour
    cross-talk too). The pairs come from a tracked avatar's render and a photograph aligned by flow, so
    both sides disagree pixel by pixel and the body's channels are strongly correlated; a full matrix
    then trades its diagonal for off-diagonal terms (cpu capture, down cameras: largest error against the
    simulator's true matrix 0.19 / 0.19 with ``matrix``, 0.057 / 0.048 with ``diagonal``; the true
    off-diagonal terms are at most 0.06). The envmap fitted through either is about as good
    (``stages/envmap.yaml``), so ``matrix`` stays the default.
    """
    if model == "matrix":
        return np.linalg.lstsq(render, ego, rcond=None)[0].T
    if model != "diagonal":
        raise EgorelightError(f"inverse.sync.model must be one of {', '.join(SYNC_MODELS)}, got {model!r}")
    return np.diag(channel_gains(render, ego))


def usable_frames(data: RelightData, calibration, roles: Sequence[str], count: int,
                  patterns: Sequence[str] | None = None) -> np.ndarray:
    """Up to ``count`` frames (uniform) with a mesh, uvmaps, a valid head pose, an image of every
    role, and (with ``patterns``: studio frames of known light) a content light entry of one of
    ``patterns``."""
    seq = data.sequence
    poses = calibration.head_poses.get(seq.name)
    if poses is None:
        raise EgorelightError(f"calibration has no head poses for sequence {seq.name!r}", calibration.source)
    valid = {int(f) for f, ok in zip(poses.frame_ids, poses.valid) if ok}
    entries = {int(f): e for f, e in zip(seq.frame_ids, seq.lights)}

    def usable(f: int) -> bool:
        if f not in valid or not data.has_maps(f):
            return False
        if patterns is not None and not (entries.get(f, {}).get("pattern") in patterns and entries[f].get("content", True)):
            return False
        ego = calibration.ego_frame_id(seq.name, f)
        return all(seq.ego_image_path(role, ego).is_file() for role in roles)

    frames = [int(f) for f in data.meshes.frame_ids if usable(int(f))]
    if not frames:
        light = f", a {'/'.join(patterns)} light entry" if patterns is not None else ""
        raise EgorelightError(f"no frame of {seq.name} has a mesh, uvmaps, a head pose{light} and images of "
                              f"{', '.join(roles)}", data.uvmaps.root)
    return np.array(frames)[np.unique(np.round(np.linspace(0, len(frames) - 1, min(count, len(frames)))).astype(int))]


@dataclass
class InverseResult:
    """Per row (:data:`ROWS`) the fit; the colour synchronisation; the views (of the main row)."""

    fits: dict[str, Fit]
    sync: dict[str, dict]
    views: list[EgoView]
    frames: np.ndarray
    flow: str
    flow_note: str | None
    reg_max: float
    panorama: np.ndarray
    image_pass: str = "full"


def inverse_render(model: rl.RelightModel, wild: EgoAvatarData, studio: EgoAvatarData, calibration,
                   panorama: np.ndarray, settings: InverseSettings, seed: int, reg_max: float) -> InverseResult:
    """Colour synchronisation on ``studio``, then every row's fit on ``wild`` (module docstring)."""
    method, note = of.flow_method(settings.flow, settings.raft_weights)
    parts = texel_parts(wild.character, wild.raster)
    studio_frames = usable_frames(studio, calibration, settings.roles, settings.sync_frames, settings.sync_patterns)
    sync = fit_colour_sync(model, studio, calibration, studio_frames, settings, parts, method)
    matrices = {role: torch.tensor(s["matrix"], dtype=torch.float32) for role, s in sync.items()}
    E_l = torch.from_numpy(np.asarray(panorama, np.float64))
    pooling = EnvmapPooling(wild.lightstage, panorama.shape[0], panorama.shape[1])
    with torch.no_grad():
        initial = pooling(RootPolynomialColour()(E_l))
    frames = usable_frames(wild, calibration, settings.roles, settings.frames)
    base = [ego_view(wild, calibration, int(f), role) for f in frames for role in settings.roles]
    first = {}
    for view in base:  # the initial render: flow and part labels
        with torch.no_grad():
            render = render_view(model, wild, view, initial, parts, settings.image_pass)
        rgb = (render.colour @ matrices[view.role].T).numpy()
        first[id(view)] = (rgb, render.alpha.numpy(), render.passes["parts"].numpy(), render.expected_depth.numpy())

    def synced(view, intensities):
        return render_view(model, wild, view, intensities, parts, settings.image_pass).colour @ matrices[view.role].T

    fits, main_views = {}, []
    for row in settings.rows:
        use_flow, use_parts, free_map = ROWS[row]
        views = []
        for view in base:
            copy = EgoView(view.frame_id, view.role, view.camera, view.ego, view.unclipped)
            observe(copy, *first[id(view)], use_flow and method != "none", use_parts, settings, method)
            views.append(copy)
        fits[row] = fit_colour_model(E_l, pooling, views, synced, settings.steps, settings.lr,
                                     settings.views_per_step, settings.reg_weight, reg_max, seed,
                                     FreeEnvmap(settings.free_map_height) if free_map else None)
        if row == "fitted":
            main_views = views
    return InverseResult(fits, sync, main_views, frames, method, note, reg_max, np.asarray(panorama),
                         settings.image_pass)


def auto_reg_max(capture, trained_on: str | None = None) -> float:
    """The 99.9th percentile of the radiance the avatar was trained under: the environment maps the
    light entries of ``capture``'s sequence ``trained_on`` name (the relight model's training
    sequence; every sequence's when None or not in the capture), each times its entry's ``scale``,
    channel maximum per texel; 1.0 when there are none."""
    from egorelight_cli.render.lighting import CaptureEnvmaps

    names = capture.sequence_names()
    names = [trained_on] if trained_on in names else names
    envmaps = CaptureEnvmaps(capture.root)
    lights = {(str(entry["envmap"]), float(entry.get("scale", 1.0))) for name in names
              for entry in capture.sequence(name).lights
              if entry.get("pattern") == "envmap" and str(entry.get("envmap")) in envmaps}
    values = [scale * np.asarray(envmaps[name], np.float32).max(axis=-1).reshape(-1) for name, scale in sorted(lights)]
    if not values:
        return 1.0
    level = float(np.percentile(np.concatenate(values), 99.9))
    return level if level > 0 and math.isfinite(level) else 1.0
