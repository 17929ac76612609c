"""Stage configuration: YAML defaults, named presets and typed ``--set`` overrides.

Each stage has ``stages/<stage>.yaml``::

    stage: ik
    version: 1                # bump when the stage's output meaning changes (enters the cache key)
    defaults: {...}           # every key the stage reads, with its default value
    presets:
      tiny: {...}             # overrides for CI (seconds on 2 cores)
      cpu: {...}              # the demo (minutes on a laptop CPU)
      paper: {...}            # the paper's settings (CUDA GPU)

Resolution order: defaults, then the preset, then ``--set key.sub=value`` overrides, then
``--seed``. Every override must name an existing key and keep its type (an int stays an int, a
float accepts an int, a list stays a list); anything else is an :class:`EgorelightError` that
lists the valid keys. The result is a frozen :class:`Config`.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml

from egorelight_cli.errors import EgorelightError
from egorelight_cli.resources import stages_dir

PRESETS = ("tiny", "cpu", "paper")
DEFAULT_PRESET = "cpu"


class Config(Mapping):
    """A frozen, nested configuration with attribute access (``cfg.loss.weight``)."""

    def __init__(self, data: Mapping[str, Any], stage: str = "", version: int = 1, preset: str = ""):
        object.__setattr__(self, "_data", {k: Config(v) if isinstance(v, Mapping) else _freeze(v) for k, v in data.items()})
        object.__setattr__(self, "stage", stage)
        object.__setattr__(self, "version", version)
        object.__setattr__(self, "preset", preset)

    def __getitem__(self, key: str) -> Any:
        return self._data[key]

    def __getattr__(self, key: str) -> Any:
        try:
            return self._data[key]
        except KeyError:
            raise AttributeError(f"config has no key {key!r} (keys: {', '.join(self._data)})") from None

    def __setattr__(self, key: str, value: Any) -> None:
        raise AttributeError("Config is frozen")

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __repr__(self) -> str:
        return f"Config({self.to_dict()!r})"

    def to_dict(self) -> dict[str, Any]:
        """A plain, JSON-able copy (lists, not tuples)."""
        return {k: v.to_dict() if isinstance(v, Config) else _thaw(v) for k, v in self._data.items()}


def _freeze(value: Any) -> Any:
    return tuple(_freeze(v) for v in value) if isinstance(value, list) else value


def _thaw(value: Any) -> Any:
    return [_thaw(v) for v in value] if isinstance(value, tuple) else value


def stage_config_path(stage: str) -> Path:
    return stages_dir() / f"{stage}.yaml"


def load_stage_file(stage: str) -> dict[str, Any]:
    """The parsed ``stages/<stage>.yaml`` with its structure checked."""
    path = stage_config_path(stage)
    if not path.is_file():
        raise EgorelightError(f"no configuration for stage {stage!r}", path)
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise EgorelightError(f"invalid YAML ({exc})", path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("defaults"), dict):
        raise EgorelightError("stage config needs a 'defaults' mapping", path)
    if not isinstance(doc.get("version"), int):
        raise EgorelightError("stage config needs an integer 'version'", path)
    presets = doc.get("presets") or {}
    missing = [p for p in PRESETS if p not in presets]
    if missing:
        raise EgorelightError(f"stage config lacks presets {missing}", path)
    return doc


def flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mapping -> {"a.b.c": leaf}."""
    flat: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def _type_name(value: Any) -> str:
    return {bool: "bool", int: "int", float: "float", str: "str", list: "list", type(None): "null"}.get(type(value), type(value).__name__)


def coerce(key: str, new: Any, old: Any, raw: str | None = None) -> Any:
    """Check that ``new`` may replace ``old`` (the default) and return it in the default's type."""
    if old is None:
        return new
    if isinstance(old, bool):
        if isinstance(new, bool):
            return new
    elif isinstance(old, int):
        if isinstance(new, int) and not isinstance(new, bool):
            return new
    elif isinstance(old, float):
        if isinstance(new, (int, float)) and not isinstance(new, bool):
            return float(new)
    elif isinstance(old, str):
        if isinstance(new, str):
            return new
        if raw is not None and not isinstance(new, (list, dict)):
            return raw  # `--set name=123` for a string key means the text "123"
    elif isinstance(old, list):
        if isinstance(new, list):
            if old and new:
                return [coerce(f"{key}[{i}]", v, old[0]) for i, v in enumerate(new)]
            return new
    shown = raw if raw is not None else repr(new)
    raise EgorelightError(f"config key {key!r} takes a {_type_name(old)}, got {shown!r} ({_type_name(new)})")


def _assign(tree: dict[str, Any], key: str, value: Any, valid: dict[str, Any], origin: str, raw: str | None = None) -> None:
    if key not in valid:
        raise EgorelightError(f"unknown config key {key!r} in {origin}; valid keys: {', '.join(sorted(valid))}")
    parts = key.split(".")
    node = tree
    for part in parts[:-1]:
        node = node[part]
    node[parts[-1]] = coerce(key, value, valid[key], raw)


def parse_set(item: str) -> tuple[str, Any, str]:
    """``"a.b=3"`` -> ("a.b", 3, "3"); the value is parsed as YAML (numbers, bools, lists)."""
    if "=" not in item:
        raise EgorelightError(f"--set expects key=value, got {item!r}")
    key, raw = item.split("=", 1)
    key = key.strip()
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key, value, raw


def resolve_config(
    stage: str,
    preset: str | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    seed: int | None = None,
) -> Config:
    """Defaults -> preset -> ``--set`` overrides -> ``--seed``; returns a frozen Config.

    Every config carries a top-level ``seed`` (0 unless the stage file or ``--seed`` says
    otherwise), so randomness is reproducible and recorded in the manifest.
    """
    doc = load_stage_file(stage)
    preset = preset or DEFAULT_PRESET
    if preset not in doc["presets"]:
        raise EgorelightError(f"unknown preset {preset!r} for stage {stage}; presets: {', '.join(doc['presets'])}")
    tree = copy.deepcopy(doc["defaults"])
    tree.setdefault("seed", 0)
    valid = flatten(tree)
    origin = f"preset {preset} of {stage_config_path(stage).name}"
    for key, value in flatten(doc["presets"][preset] or {}).items():
        _assign(tree, key, value, valid, origin)
    for item in overrides:
        key, value, raw = parse_set(item)
        _assign(tree, key, value, valid, "--set", raw)
    if seed is not None:
        tree["seed"] = int(seed)
    return Config(tree, stage=stage, version=int(doc["version"]), preset=preset)
