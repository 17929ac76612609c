"""Stage configuration: YAML defaults, named presets and typed ``--set`` overrides.

Each stage has ``stages/<stage>.yaml``::

    stage: ik
    version: 1                # bump when the stage's output meaning changes (enters the cache key)
    defaults: {...}           # every key the stage reads, with its default value
    presets:
      tiny: {...}             # overrides for CI (seconds on 2 cores)
      cpu: {...}              # the demo (minutes on a laptop CPU)
      paper: {...}            # the paper's settings (CUDA GPU)
    checks:                   # allowed values (optional), per dotted key or glob (``weights.*``)
      lm.iterations: {min: 1}
      solver: {one_of: [lm, lbfgs]}

Resolution order: defaults, then the preset, then ``--set key.sub=value`` overrides, then
``--seed``. Every override must name an existing key and keep its type (an int stays an int, a
float accepts an int, a list stays a list), and the result must pass the file's ``checks``
(:data:`CHECK_RULES`); anything else is an :class:`EgorelightError` naming the key. The result is
a frozen :class:`Config`.

The file is the one place a stage's defaults live: a settings dataclass that mirrors a section
takes its field defaults from it with :func:`setting` and is built with
:func:`settings_from_config`.
"""

from __future__ import annotations

import copy
import dataclasses
import fnmatch
import functools
import math
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
        if key.startswith("__") or key == "_data":  # unpickling looks these up before _data exists
            raise AttributeError(key)
        try:
            return self._data[key]
        except KeyError:
            raise AttributeError(f"config has no key {key!r} (keys: {', '.join(self._data)})") from None

    def __setattr__(self, key: str, value: Any) -> None:
        raise AttributeError("Config is frozen")

    def __reduce__(self):
        return (Config, (self.to_dict(), self.stage, self.version, self.preset))

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
    checks = doc.get("checks") or {}
    keys = flatten(doc["defaults"])
    for pattern, rule in checks.items():
        if not isinstance(rule, dict) or not rule or set(rule) - set(CHECK_RULES):
            raise EgorelightError(f"checks.{pattern}: a mapping of {', '.join(CHECK_RULES)}", path)
        if not fnmatch.filter(keys, pattern):
            raise EgorelightError(f"checks.{pattern} matches no key of 'defaults'", path)
    doc["checks"] = checks
    return doc


# ------------------------------------------------------------------------------------ checks
#: rule -> (test of one value, what it says when the value fails it)
CHECK_RULES = {
    "min": (lambda v, b: v >= b, "at least {}"),
    "above": (lambda v, b: v > b, "above {}"),
    "max": (lambda v, b: v <= b, "at most {}"),
    "below": (lambda v, b: v < b, "below {}"),
    "one_of": (lambda v, b: v in b, "one of {}"),
    "not_empty": (lambda v, b: True, "not empty"),
}


def check_value(key: str, value: Any, rule: Mapping[str, Any], origin: str = "") -> None:
    """Raise an :class:`EgorelightError` naming ``key`` unless ``value`` passes ``rule`` (a list
    passes when every item does; ``null`` and the text ``auto`` pass the numeric rules)."""
    where = f" ({origin})" if origin else ""
    items = list(value) if isinstance(value, (list, tuple)) else [value]
    if rule.get("not_empty") and not items:
        raise EgorelightError(f"config key {key!r} must not be empty{where}")
    for name, bound in rule.items():
        test, says = CHECK_RULES[name]
        for item in items:
            numeric = name in ("min", "above", "max", "below")
            if numeric and (item is None or item == "auto"):
                continue
            if numeric and isinstance(item, str):  # a text key that also takes numbers ("auto" or 1.6)
                try:
                    item = float(item)
                except ValueError:
                    pass
            bad = numeric and (isinstance(item, bool) or not isinstance(item, (int, float)) or math.isnan(item))
            if bad or not test(item, bound):
                shown = ", ".join(map(str, bound)) if name == "one_of" else bound
                raise EgorelightError(f"config key {key!r} must be {says.format(shown)}, got {value!r}{where}")


def check_config(flat: Mapping[str, Any], checks: Mapping[str, Mapping], origin: str = "") -> None:
    """Every key of the flattened config ``flat`` against the rules whose pattern it matches."""
    for pattern, rule in checks.items():
        for key in fnmatch.filter(flat, pattern):
            check_value(key, flat[key], rule, origin)


# ---------------------------------------------------------------------- settings dataclasses
@functools.lru_cache(maxsize=None)
def _stage_defaults(stage: str) -> dict[str, Any]:
    return load_stage_file(stage)["defaults"]


@functools.lru_cache(maxsize=None)
def _stage_checks(stage: str) -> dict[str, Any]:
    return load_stage_file(stage)["checks"]


def setting(stage: str, key: str, default: Any = dataclasses.MISSING) -> Any:
    """A dataclass field mirroring config key ``key`` of ``stages/<stage>.yaml``, its default taken
    from that file (a list becomes a tuple, a mapping a fresh dict) unless given (``seed``)."""
    value = _lookup(_stage_defaults(stage), key, {}, default)
    if value is dataclasses.MISSING:
        raise KeyError(f"stages/{stage}.yaml has no default for {key!r}")
    metadata = {"stage": stage, "key": key}
    if isinstance(value, Mapping):
        return dataclasses.field(default_factory=lambda: dict(value), metadata=metadata)
    return dataclasses.field(default=tuple(value) if isinstance(value, list) else value, metadata=metadata)


def settings_from_config(cls: type, cfg: Mapping[str, Any]) -> Any:
    """An instance of the settings dataclass ``cls`` (fields made with :func:`setting`) from a
    resolved config, each value in its default's type."""
    flat = flatten(cfg)
    values = {}
    for f in dataclasses.fields(cls):
        key = f.metadata.get("key")
        if key is None:
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        value = _lookup(cfg, key, flat, default)
        if isinstance(default, dict):
            values[f.name] = {k: type(default.get(k, v))(v) for k, v in dict(value).items()}
        elif isinstance(default, tuple):
            values[f.name] = tuple(value)
        elif default is None or value is None:
            values[f.name] = value
        else:
            values[f.name] = type(default)(value)
    return cls(**values)


def _lookup(cfg: Mapping[str, Any], key: str, flat: Mapping[str, Any], default: Any) -> Any:
    """The value of dotted ``key`` (a leaf from ``flat``, or a whole section of ``cfg``), else ``default``."""
    if key in flat:
        return flat[key]
    node: Any = cfg
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def check_settings(settings: Any) -> None:
    """Check every :func:`setting` field of a settings dataclass against its stage file's checks
    (for settings built in code rather than resolved from a config)."""
    for f in dataclasses.fields(settings):
        stage, key = f.metadata.get("stage"), f.metadata.get("key")
        if stage is None:
            continue
        value = getattr(settings, f.name)
        for pattern, rule in _stage_checks(stage).items():
            if fnmatch.fnmatch(key, pattern):
                check_value(key, value, rule, f"stages/{stage}.yaml")


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
    kind = _type_name(old)
    raise EgorelightError(f"config key {key!r} takes {'an' if kind[0] in 'aeiou' else 'a'} {kind}, got {shown!r} "
                          f"({_type_name(new)})")


def _assign(tree: dict[str, Any], key: str, value: Any, valid: dict[str, Any], origin: str, defaults: str,
            raw: str | None = None) -> None:
    """Set ``key`` of ``tree`` to ``value`` from ``origin``, in the type of its default in the
    stage file ``defaults`` (both named in the error)."""
    if key not in valid:
        raise EgorelightError(f"unknown config key {key!r} in {origin}; valid keys: {', '.join(sorted(valid))}")
    parts = key.split(".")
    node = tree
    for part in parts[:-1]:
        node = node[part]
    try:
        node[parts[-1]] = coerce(key, value, valid[key], raw)
    except EgorelightError as exc:
        raise EgorelightError(f"{exc.message} in {origin} (the type of its default in {defaults})") from None


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
    defaults = f"stages/{stage}.yaml"
    origin = f"preset {preset} of {stage_config_path(stage).name}"
    for key, value in flatten(doc["presets"][preset] or {}).items():
        _assign(tree, key, value, valid, origin, defaults)
    for item in overrides:
        key, value, raw = parse_set(item)
        _assign(tree, key, value, valid, "--set", defaults, raw)
    if seed is not None:
        tree["seed"] = int(seed)
    check_config(flatten(tree), doc["checks"], defaults)
    return Config(tree, stage=stage, version=int(doc["version"]), preset=preset)
