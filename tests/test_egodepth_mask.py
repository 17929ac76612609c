"""The depth network's body-mask threshold (stages/egodepth_mask.py): the training/validation frame
split, precision and recall per threshold against an analytic case, the choice, and the CLI: the
model stores the threshold chosen on its validation frames and ``egodepth`` uses it unless
``predict.mask_threshold`` is set."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from egorelight_cli.cli import main
from egorelight_cli.config import resolve_config
from egorelight_cli.stages import egodepth as ed
from egorelight_cli.stages.egodepth_mask import THRESHOLDS, choose_threshold, precision_recall


def run_cli(*args: str) -> int:
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", *args])
    return exit_info.value.code


def test_validation_frames_come_from_the_frames_training_leaves():
    frames = list(range(100, 200))
    training, validation = ed.split_frames(frames, 32, 8)
    assert len(training) == 32 and len(validation) == 8
    assert not set(training) & set(validation)
    assert training == list(ed.evenly_spaced(frames, 32))  # the training set does not change
    assert validation[0] > frames[0] and validation[-1] < frames[-1]
    # training takes every frame: validation is set aside first
    training, validation = ed.split_frames(frames, 0, 8)
    assert len(validation) == 8 and len(training) == 92 and not set(training) & set(validation)
    # too few frames to spare 8: no validation, training unchanged
    assert ed.split_frames(list(range(10)), 0, 8) == (list(range(10)), [])
    assert ed.split_frames(frames, 32, 0) == (list(ed.evenly_spaced(frames, 32)), [])


class _FixedMaps(torch.nn.Module):
    """A stand-in network: constant range, the given body logits, a confident scale."""

    stereo_input = False

    def __init__(self, logit: torch.Tensor):
        super().__init__()
        self.logit = logit

    def forward(self, image, rays, prior=None, stereo=None):
        shape = self.logit.shape
        return torch.full(shape, float(np.log(0.5))), self.logit[: image.shape[0]], torch.full(shape, -5.0)


def test_precision_and_recall_per_threshold_match_a_counted_case():
    """8x8 views, no lens border: the left half is body (probability 0.97), each background column
    of the right half has its own probability 0.52, 0.62, 0.72, 0.82; at threshold t the kept
    background is the columns above t. Precision = 32 / (32 + 8 * columns kept), recall 1 while
    the body passes; the lowest threshold reaching 0.99 is the first that drops every column."""
    H = W = 8
    probability = np.full((H, W), 0.97)
    probability[:, 4:] = [0.52, 0.62, 0.72, 0.82]
    supervised = np.zeros((H, W), bool)
    supervised[:, :4] = True
    logit = torch.logit(torch.from_numpy(probability).float())[None, None].repeat(2, 1, 1, 1)
    views = [ed.TrainingView(role, "s", 0, np.zeros((H, W, 3), np.uint8), np.full((H, W), 0.5, np.float32),
                             supervised, np.zeros((H, W), bool)) for role in ("a", "b")]
    ray_maps = {r: (np.zeros((H, W, 3), np.float32), np.ones((H, W), bool)) for r in ("a", "b")}
    settings = ed.PredictSettings(None, 0.07, 3.0, 0.0, 0.2)
    precision, recall = precision_recall(_FixedMaps(logit), views, ray_maps, {}, settings, torch.device("cpu"))
    columns = np.array([int((np.array([0.52, 0.62, 0.72, 0.82]) > t).sum()) for t in THRESHOLDS])
    np.testing.assert_allclose(precision, 32 / (32 + 8 * columns))
    np.testing.assert_allclose(recall, 1.0)
    assert choose_threshold(precision, THRESHOLDS, 0.99) == 0.85
    assert choose_threshold(precision, THRESHOLDS, 0.75) == 0.75  # one column left: 32 / 40 = 0.8
    # a self-occlusion mask over a background column removes it from the count
    masks = {r: np.zeros((H, W), bool) for r in ("a", "b")}
    for m in masks.values():
        m[:, 7] = True
    masked, _ = precision_recall(_FixedMaps(logit), views, ray_maps, masks, settings, torch.device("cpu"))
    assert masked[0] == pytest.approx(32 / (32 + 8 * 3))


def test_choose_threshold_takes_the_most_precise_when_none_reaches_the_target():
    precision = np.array([0.5, 0.7, 0.9, 0.8])
    assert choose_threshold(precision, (0.5, 0.6, 0.7, 0.8), 0.95) == 0.7
    assert choose_threshold(precision, (0.5, 0.6, 0.7, 0.8), 0.6) == 0.6


def test_settings_resolve_the_threshold_configured_then_the_model_s_then_the_default():
    unset = ed.PredictSettings(None, 0.07, 3.0, 0.05, 0.2)
    assert unset.for_model(0.8).mask_threshold == 0.8
    assert unset.for_model(None).mask_threshold == ed.DEFAULT_MASK_THRESHOLD
    assert ed.PredictSettings(0.6, 0.07, 3.0, 0.05, 0.2).for_model(0.8).mask_threshold == 0.6


def _common(capture, calibration):
    return ["--preset", "tiny", "--capture", str(capture), "--calibration", str(calibration)]


def _train(model, capture, calibration, validation_frames, steps):
    code = run_cli("train", "egodepth", *_common(capture, calibration), "--set",
                   f"train.validation_frames={validation_frames}", "--set", f"train.steps={steps}",
                   "--out", str(model))
    assert code == 0
    return json.loads((model / "manifest.json").read_text())["metrics"]


def test_the_model_carries_the_threshold_chosen_on_validation_frames(tiny_capture, oracle_calibration_artifact,
                                                                     tmp_path):
    """Tiny ego_train has 3 frames: one set aside for validation (2 views). The model stores the
    chosen threshold; ``egodepth`` uses it and says so, ``predict.mask_threshold`` overrides it."""
    model = tmp_path / "model"
    common = _common(tiny_capture, oracle_calibration_artifact)
    trained = _train(model, tiny_capture, oracle_calibration_artifact, validation_frames=1, steps=30)
    assert trained["validation_views"] == 2 and trained["training_views"] == 4
    assert trained["mask_threshold"] in THRESHOLDS
    curve = trained["validation_mask_curve"]
    precision = np.array([curve[f"{t:.2f}"][0] for t in THRESHOLDS])
    target = float(resolve_config("egodepth", "tiny").train.mask_precision)
    assert trained["mask_threshold"] == choose_threshold(precision, THRESHOLDS, target)
    assert trained["mask_threshold_source"] == f"lowest threshold with validation precision >= {target}"
    assert trained["validation_mask_precision"] == pytest.approx(curve[f"{trained['mask_threshold']:.2f}"][0])

    own, fixed = tmp_path / "own", tmp_path / "fixed"
    assert run_cli("egodepth", *common, "--model", str(model), "--seq", "test", "--out", str(own)) == 0
    assert run_cli("egodepth", *common, "--model", str(model), "--seq", "test", "--set",
                   "predict.mask_threshold=0.99", "--out", str(fixed)) == 0
    own_m = json.loads((own / "manifest.json").read_text())["metrics"]
    fixed_m = json.loads((fixed / "manifest.json").read_text())["metrics"]
    assert own_m["mask_threshold"] == trained["mask_threshold"]
    assert own_m["mask_threshold_source"].startswith("the model's")
    assert fixed_m["mask_threshold"] == 0.99 and fixed_m["mask_threshold_source"] == "predict.mask_threshold"
    assert fixed_m["mean_valid_points"] <= own_m["mean_valid_points"]


def test_a_model_without_validation_frames_uses_the_plain_threshold(tiny_capture, oracle_calibration_artifact,
                                                                   tmp_path, capsys):
    model = tmp_path / "model"
    common = _common(tiny_capture, oracle_calibration_artifact)
    trained = _train(model, tiny_capture, oracle_calibration_artifact, validation_frames=0, steps=5)
    assert trained["mask_threshold"] == 0.5 and trained["validation_views"] == 0
    assert trained["mask_threshold_source"] == "default (no validation frames)"
    capsys.readouterr()
    code = run_cli("egodepth", *common, "--model", str(model), "--seq", "test", "--set",
                   "predict.mask_threshold=1.5", "--out", str(tmp_path / "bad"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("egorelight: error:") and "predict.mask_threshold" in err
    assert "\n" not in err and not (tmp_path / "bad").exists()
