"""Shared learning blocks: U-Net, UV feature sampling, colour jitter, training loop, model payload."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.model import ModelPayload, read_model, write_model
from egorelight_cli.nn.augment import ColourJitter, ShadingJitter, apply_colour_jitter
from egorelight_cli.nn.training import BestOnValidation, Checkpoint, train
from egorelight_cli.nn.unet import UNet, sample_feature_map


def test_unet_shapes_any_size_and_gradients():
    net = UNet(5, 3, base_channels=8, levels=3)
    x = torch.randn(2, 5, 37, 50, requires_grad=True)
    y = net(x)
    assert y.shape == (2, 3, 37, 50)
    feats = net.decoder_features(x)
    assert [f.shape[-2:] for f in feats] == [(5, 7), (10, 13), (19, 25), (37, 50)]
    y.square().mean().backward()
    assert x.grad is not None and all(p.grad is not None for p in net.parameters())


def test_sample_feature_map_hits_texel_centres():
    H, W = 4, 6
    features = torch.arange(H * W, dtype=torch.float64).reshape(1, 1, H, W)
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    u = (cols + 0.5) / W
    v = 1 - (rows + 0.5) / H  # row 0 is v = 1
    uv = torch.as_tensor(np.stack([u.ravel(), v.ravel()], -1))
    sampled = sample_feature_map(features, uv)
    np.testing.assert_allclose(sampled[0, :, 0].numpy(), np.arange(H * W), atol=1e-9)


def test_colour_jitter_identity_and_properties():
    g = torch.Generator().manual_seed(0)
    images = torch.rand(3, 3, 8, 8, generator=g)
    identity = torch.tensor([[1.0, 1.0, 1.0, 0.0]]).repeat(3, 1)
    torch.testing.assert_close(apply_colour_jitter(images, identity), images, atol=1e-5, rtol=0)
    full_turn = identity.clone()
    full_turn[:, 3] = 2 * math.pi
    torch.testing.assert_close(apply_colour_jitter(images, full_turn), images, atol=1e-5, rtol=0)
    grey = torch.full((1, 3, 4, 4), 0.4)
    hue_only = torch.tensor([[1.0, 1.0, 1.0, 1.3]])
    torch.testing.assert_close(apply_colour_jitter(grey, hue_only), grey, atol=1e-5, rtol=0)
    darker = torch.tensor([[0.5, 1.0, 1.0, 0.0]])
    torch.testing.assert_close(apply_colour_jitter(grey, darker), grey * 0.5, atol=1e-5, rtol=0)
    out = ColourJitter(0.8, 0.8, 0.8, 0.5)(images, generator=g)
    assert out.min() >= 0 and out.max() <= 1 and not torch.allclose(out, images)


def test_shading_jitter_is_a_smooth_positive_gain_field_of_the_given_strength():
    images = torch.rand(2, 3, 17, 17, generator=torch.Generator().manual_seed(1)) * 0.5
    torch.testing.assert_close(ShadingJitter(0.0, 3, 0.0)(images), images)
    shading = ShadingJitter(0.7, 3, 0.1)
    log_gain = torch.log(shading.field(4000, 17, 17, torch.Generator().manual_seed(0)))
    # at the grid nodes (corners, centre) the log gain is the draw: std sqrt(0.7^2 + 0.1^2)
    nodes = log_gain[:, :, ::8, ::8]
    assert abs(float(nodes.std()) - math.hypot(0.7, 0.1)) < 0.02 and abs(float(nodes.mean())) < 0.02
    # linear between nodes 8 px apart: along a node row every step is the node difference / 8
    step = (log_gain[..., ::8, 1:] - log_gain[..., ::8, :-1])
    node_step = (nodes[..., 1:] - nodes[..., :-1]).repeat_interleave(8, dim=-1) / 8
    torch.testing.assert_close(step, node_step, atol=1e-4, rtol=1e-4)
    # the three channels share the shading and differ only by the tint
    assert float((log_gain[:, 0] - log_gain[:, 1]).std()) < 0.25
    same = ShadingJitter(0.7)(images, torch.Generator().manual_seed(3))
    torch.testing.assert_close(same, ShadingJitter(0.7)(images, torch.Generator().manual_seed(3)))
    assert same.min() >= 0 and same.max() <= 1 and not torch.allclose(same, images)


def _regression_problem():
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    w_true = torch.tensor([[1.0, -2.0, 0.5]])

    def step_fn(step):
        g = torch.Generator().manual_seed(step)
        x = torch.randn(32, 3, generator=g)
        return {"loss": (model(x) - x @ w_true.T).square().mean()}
    return model, optimizer, step_fn


def test_training_converges_and_resume_matches_uninterrupted(tmp_path):
    model, optimizer, step_fn = _regression_problem()
    curve = train(model, optimizer, step_fn, 60, log_every=10)
    assert curve[-1]["loss"] < 1e-3 * curve[0]["loss"] and len(curve) == 6
    reference = [p.detach().clone() for p in model.parameters()]

    model, optimizer, step_fn = _regression_problem()
    ckpt = tmp_path / "ckpt.pt"
    train(model, optimizer, step_fn, 30, checkpoint=ckpt, checkpoint_every=10, log_every=10)
    model, optimizer, step_fn = _regression_problem()   # a fresh process resumes
    curve = train(model, optimizer, step_fn, 60, checkpoint=ckpt, checkpoint_every=10, log_every=10)
    assert [row["step"] for row in curve] == [10, 20, 30, 40, 50, 60]
    for p, q in zip(model.parameters(), reference):
        torch.testing.assert_close(p.detach(), q)


def _pulled_past_the_validation_optimum():
    """One parameter p pulled from 0 to 2 by SGD on (p - 2)^2 (lr 0.05: p_k = 2 (1 - 0.9^k)), scored
    on validation by (p - 1)^2: best at step 7 (p = 1.0434; step 6 gives 0.9371)."""
    model = torch.nn.Linear(1, 1, bias=False)
    torch.nn.init.zeros_(model.weight)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.05)
    selection = BestOnValidation(lambda: float((model.weight[0, 0] - 1.0) ** 2), every=1)
    return model, optimizer, (lambda step: {"loss": (model.weight[0, 0] - 2.0) ** 2}), selection


def test_best_on_validation_ends_with_the_best_weights_and_resumes_to_the_same(tmp_path):
    model, optimizer, step_fn, selection = _pulled_past_the_validation_optimum()
    curve = train(model, optimizer, step_fn, 20, log_every=1, selection=selection)
    assert selection.first == pytest.approx(1.0) and selection.best_step == 7
    assert float(model.weight.detach()) == pytest.approx(2 * (1 - 0.9 ** 7), rel=1e-5)
    assert selection.best == pytest.approx((2 * (1 - 0.9 ** 7) - 1) ** 2, rel=1e-4)
    scores = [row["validation"] for row in curve]
    assert len(scores) == 20 and min(scores) == pytest.approx(selection.best) and scores[-1] > 10 * selection.best
    # interrupted after step 5 (before the optimum) and after step 12 (past it): the same result
    for stop in (5, 12):
        ckpt = tmp_path / f"ckpt{stop}.pt"
        model, optimizer, step_fn, selection = _pulled_past_the_validation_optimum()
        train(model, optimizer, step_fn, stop, checkpoint=Checkpoint(ckpt), log_every=1, selection=selection)
        model, optimizer, step_fn, selection = _pulled_past_the_validation_optimum()  # a fresh process
        train(model, optimizer, step_fn, 20, checkpoint=Checkpoint(ckpt, resume=True), log_every=1,
              selection=selection)
        assert selection.best_step == 7 and selection.first == pytest.approx(1.0), stop
        assert float(model.weight.detach()) == pytest.approx(2 * (1 - 0.9 ** 7), rel=1e-5), stop


def test_training_stops_on_nan():
    model = torch.nn.Linear(1, 1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    with pytest.raises(EgorelightError, match="loss became nan"):
        train(model, optimizer, lambda s: {"loss": model(torch.ones(1, 1)).sum() * float("nan")}, 5)


def test_model_payload_round_trip_and_errors(tmp_path):
    net = UNet(3, 1, base_channels=4, levels=2)
    payload = ModelPayload("egodepth", {"base_channels": 4, "levels": 2}, net.state_dict(),
                           extra={"depth_scale": 2.0}, curve=[{"step": 10, "loss": 1.0}, {"step": 20, "loss": 0.5}])
    write_model(tmp_path, payload)
    back = read_model(tmp_path, stage="egodepth")
    assert back.architecture == {"base_channels": 4, "levels": 2} and back.extra["depth_scale"] == 2.0
    for name, value in net.state_dict().items():
        torch.testing.assert_close(back.state_dict[name], value)
    assert (tmp_path / "curve.png").stat().st_size > 0 and back.curve[-1]["loss"] == 0.5
    with pytest.raises(EgorelightError, match="trained for stage 'egodepth', not 'egopose'"):
        read_model(tmp_path, stage="egopose")
    (tmp_path / "model.pt").write_bytes(b"garbage")
    with pytest.raises(EgorelightError, match="cannot load model"):
        read_model(tmp_path)


def test_depth_net_corrects_the_stereo_range_where_stereo_has_one():
    """With the stereo input and a zero correction, the network returns the stereo log range
    where stereo has a range and its training median elsewhere; without a stereo map it refuses."""
    from egorelight_cli.errors import EgorelightError
    from egorelight_cli.nn.depth_net import DepthNet

    torch.manual_seed(0)
    net = DepthNet(base_channels=4, levels=2, log_range_mean=-1.2, stereo_input=True).eval()
    torch.nn.init.zeros_(net.unet.head.weight)
    torch.nn.init.zeros_(net.unet.head.bias)
    image, rays = torch.rand(2, 3, 16, 20), torch.randn(2, 3, 16, 20)
    stereo = torch.rand(2, 1, 16, 20) * 0.8 + 0.1
    stereo[:, :, :, :7] = 0  # no stereo range in the left columns
    log_range, _, log_scale = net(image, rays, None, stereo)
    assert log_scale is None
    has = stereo > 0
    torch.testing.assert_close(log_range[has], torch.log(stereo[has]))
    torch.testing.assert_close(log_range[~has], torch.full_like(log_range[~has], -1.2))
    with pytest.raises(EgorelightError, match="stereo"):
        net(image, rays)
    # the architecture round trip keeps the stereo input; models written before it are monocular
    assert DepthNet.from_architecture(net.architecture()).stereo_input
    assert not DepthNet.from_architecture({"base_channels": 4, "levels": 2, "prior_channels": 0}).stereo_input
