"""Stage configs: presets, typed --set overrides, errors that list valid keys."""

from __future__ import annotations

import pytest

from egorelight_cli import config as config_module
from egorelight_cli.config import coerce, resolve_config
from egorelight_cli.errors import EgorelightError

STAGE_YAML = """
stage: demo
version: 3
defaults:
  iterations: 100
  step: 0.5
  name: lm
  verbose: false
  sizes: [64, 128]
  loss:
    weight: 1.0
    kind: l1
presets:
  tiny: {iterations: 2, loss: {weight: 0.1}}
  cpu: {}
  paper: {iterations: 1000}
"""


@pytest.fixture
def stages(tmp_path, monkeypatch):
    (tmp_path / "demo.yaml").write_text(STAGE_YAML)
    monkeypatch.setattr(config_module, "stages_dir", lambda: tmp_path)
    return tmp_path


def test_defaults_presets_and_overrides(stages):
    cfg = resolve_config("demo", "tiny", ["step=2", "loss.kind=l2", "sizes=[1, 2, 3]"], seed=7)
    assert cfg.iterations == 2 and cfg.loss.weight == 0.1
    assert cfg.step == 2.0 and isinstance(cfg.step, float)
    assert cfg.loss.kind == "l2" and cfg.sizes == (1, 2, 3)
    assert cfg.seed == 7 and cfg.version == 3 and cfg.preset == "tiny"
    assert cfg.to_dict()["sizes"] == [1, 2, 3]
    assert resolve_config("demo").iterations == 100  # cpu preset is the default
    with pytest.raises(AttributeError):
        cfg.iterations = 5


def test_unknown_key_lists_valid_keys(stages):
    with pytest.raises(EgorelightError) as info:
        resolve_config("demo", "cpu", ["loss.wieght=2"])
    message = str(info.value)
    assert "unknown config key 'loss.wieght'" in message and "loss.weight" in message and "iterations" in message


@pytest.mark.parametrize("item,expected", [
    ("iterations=1.5", "takes an int"),
    ("iterations=true", "takes an int"),
    ("verbose=3", "takes a bool"),
    ("sizes=7", "takes a list"),
    ("sizes=[1, x]", "takes an int"),
    ("step=abc", "takes a float"),
])
def test_type_errors(stages, item, expected):
    with pytest.raises(EgorelightError, match=expected) as info:
        resolve_config("demo", "cpu", [item])
    assert "in --set (the type of its default in stages/demo.yaml)" in str(info.value)


def test_string_key_keeps_text(stages):
    assert resolve_config("demo", "cpu", ["name=123"]).name == "123"


def test_bad_preset_and_stage(stages):
    with pytest.raises(EgorelightError, match="unknown preset 'huge'.*tiny, cpu, paper"):
        resolve_config("demo", "huge")
    with pytest.raises(EgorelightError, match="no configuration for stage 'nope'"):
        resolve_config("nope")
    with pytest.raises(EgorelightError, match="key=value"):
        resolve_config("demo", "cpu", ["iterations"])


def test_coerce_int_to_float_only():
    assert coerce("a", 3, 1.0) == 3.0
    with pytest.raises(EgorelightError):
        coerce("a", 3.5, 1)


def test_shipped_stage_files_resolve():
    from egorelight_cli.resources import stages_dir

    files = sorted(stages_dir().glob("*.yaml"))
    assert files, "no stage configs shipped"
    for path in files:
        for preset in ("tiny", "cpu", "paper"):
            resolve_config(path.stem, preset)


CHECKED_YAML = STAGE_YAML.replace("version: 3", "version: 1") + """
checks:
  iterations: {min: 1}
  step: {above: 0, max: 1}
  name: {one_of: [lm, lbfgs]}
  sizes: {not_empty: true, min: 8}
  loss.w*: {min: 0}
"""


@pytest.fixture
def checked_stage(tmp_path, monkeypatch):
    (tmp_path / "demo.yaml").write_text(CHECKED_YAML)
    monkeypatch.setattr(config_module, "stages_dir", lambda: tmp_path)
    return tmp_path


@pytest.mark.parametrize("item,expected", [
    ("iterations=0", "'iterations' must be at least 1, got 0"),
    ("step=0", "'step' must be above 0"),
    ("step=1.5", "'step' must be at most 1"),
    ("step=.nan", "'step' must be above 0"),
    ("name=newton", "'name' must be one of lm, lbfgs, got 'newton'"),
    ("sizes=[]", "'sizes' must not be empty"),
    ("sizes=[64, 4]", "'sizes' must be at least 8"),
    ("loss.weight=-1", "'loss.weight' must be at least 0"),
])
def test_checks_reject_values_outside_the_declared_range(checked_stage, item, expected):
    with pytest.raises(EgorelightError, match=expected):
        resolve_config("demo", "cpu", [item])
    assert resolve_config("demo", "cpu", ["iterations=1", "step=1", "name=lbfgs"]).name == "lbfgs"


def test_a_check_must_name_a_key_and_a_known_rule(tmp_path, monkeypatch):
    monkeypatch.setattr(config_module, "stages_dir", lambda: tmp_path)
    for checks, expected in (("nope: {min: 1}", "matches no key"), ("iterations: {atleast: 1}", "a mapping of")):
        (tmp_path / "demo.yaml").write_text(STAGE_YAML + "checks:\n  " + checks + "\n")
        with pytest.raises(EgorelightError, match=expected):
            resolve_config("demo", "cpu")


def test_settings_dataclasses_take_their_defaults_from_the_stage_files():
    """One place for defaults: a settings class built with no arguments equals the one resolved from
    the stage file's defaults (the animate TrainSettings once said 200 steps where the file said 2000)."""
    import dataclasses

    from egorelight_cli.config import check_settings, load_stage_file
    from egorelight_cli.stages.animate import DepthSettings, NetSettings, TrainSettings
    from egorelight_cli.stages.ik_robust import ROBUST_LOSSES
    from egorelight_cli.stages.ik_settings import IKSettings

    for cls, stage in ((IKSettings, "ik"), (NetSettings, "animate"), (DepthSettings, "animate"),
                       (TrainSettings, "animate")):
        defaults = config_module.Config({**load_stage_file(stage)["defaults"], "seed": 0})
        assert cls.from_config(defaults) == cls(), cls.__name__
        assert all(f.metadata.get("key") for f in dataclasses.fields(cls)), cls.__name__
    assert TrainSettings().steps == 2000
    assert set(load_stage_file("ik")["checks"]["robust.loss"]["one_of"]) == set(ROBUST_LOSSES)
    with pytest.raises(EgorelightError, match="'lm.iterations' must be at least 1"):
        IKSettings(lm_iterations=0)  # built in code, checked against the same rules (check_settings)
    check_settings(NetSettings())


def test_config_pickles_to_an_equal_frozen_config():
    import pickle

    from egorelight_cli.config import Config

    cfg = Config({"a": {"b": [1, [2, 3]], "c": "x"}, "d": 1.5}, stage="synth", version=3, preset="cpu")
    back = pickle.loads(pickle.dumps(cfg))
    assert back == cfg and back.to_dict() == cfg.to_dict() and back.a.b == (1, (2, 3))
    assert (back.stage, back.version, back.preset) == ("synth", 3, "cpu")
    with pytest.raises(AttributeError, match="frozen"):
        back.d = 2


@pytest.mark.parametrize("stage,item,expected", [
    ("calibrate", "handeye.on_missing=abort", "one of warn, error"),          # was taken for warn
    ("calibrate", "head.corner_refinement=foo", "one of edges, contour"),    # was a KeyError deep in detection
    ("relight", "train.validation_fraction=1.0", "below 1"),
    ("geolift", "train.validation_fraction=0", "above 0"),
])
def test_shipped_stages_check_their_enumerations_and_fractions(stage, item, expected):
    with pytest.raises(EgorelightError, match=expected):
        resolve_config(stage, "cpu", [item])


@pytest.mark.parametrize("stage", ["egodepth", "egopose", "animate", "relight"])
def test_training_steps_must_be_positive(stage):
    with pytest.raises(EgorelightError, match="'train.steps' must be at least 1"):
        resolve_config(stage, "cpu", ["train.steps=-1"])
