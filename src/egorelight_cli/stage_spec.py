"""Stage declarations: what a command reads, which options it takes and what it writes, said once.

A :class:`Command` is the one place a command's surface lives (the declarations themselves are in
:mod:`egorelight_cli.declarations`). Everything else is derived from it:

* the click command: its options and arguments, their help, ``--frames``/``--shard`` of a
  per-frame stage and the global options (:mod:`egorelight_cli.cli`);
* the cache key and the manifest's ``config.options``: every :class:`Option` enters them unless it
  is declared ``keyed=False`` with the reason; an option with a ``config_key`` becomes
  ``--set config_key=value`` and so enters the key through the resolved config
  (:meth:`Command.keyed_options`, :meth:`Command.config_sets`);
* the manifest's ``inputs``: each input artifact is matched to the declared :class:`Input` it came
  through (its ``param``), an artifact of a kind that input does not accept is refused, and every
  input the user gave must have entered the key (:meth:`Command.input_params`);
* the README's command table (:func:`markdown_table`).

The handler a declaration names (``"module:function"``) is imported only when the command runs, so
``egorelight --help`` and a cached no-op stay light; it is called as
``function(run, **values)`` with one keyword per declared input, option and output (options with a
``config_key`` are consumed by the config and not passed), plus ``frame_range`` for a per-frame
stage.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Values of an :class:`Input` that name a built-in instead of a file (not a path on disk).
BUILTIN_VALUES = ("default",)


@dataclass(frozen=True)
class Input:
    """A file or artifact the command reads (its digest enters the cache key).

    Attributes:
        flag: ``--motion``, or the metavar of a positional argument (``MOTIONS``).
        name: the handler's keyword.
        help: one line for ``--help`` and the README.
        kinds: artifact kinds accepted (short names, e.g. ``("motion",)``).
        files: other things accepted, for the help and the README (``".bvh"``, ``"folder"``,
            ``"default"``: the shipped character).
        required: the command cannot run without it.
        multiple: repeatable (a positional argument takes any number).
        argument: positional instead of an option.
        default: the value when not given (``"default"`` for ``--character``).
        aliases: more flags for the same input.
        dir_okay, file_okay: what the path may be.
    """

    flag: str
    name: str
    help: str
    kinds: tuple[str, ...] = ()
    files: tuple[str, ...] = ()
    required: bool = False
    multiple: bool = False
    argument: bool = False
    default: str | None = None
    aliases: tuple[str, ...] = ()
    dir_okay: bool = True
    file_okay: bool = True

    @property
    def is_path(self) -> bool:
        """False for a value that may name a built-in (``--character default``): a plain string."""
        return self.default not in BUILTIN_VALUES


@dataclass(frozen=True)
class Option:
    """A setting of the command that is not a file.

    Attributes:
        flag, name, help, aliases: as for :class:`Input`.
        type: ``str``, ``int``, ``float`` or ``bool`` (a flag), a tuple of allowed strings, or
            ``"folder"`` (an existing directory, keyed by its path).
        default: the value when not given (None: not given, and not in the key).
        config_key: the option is a shorthand for ``--set config_key=value`` (a flag sets
            ``config_value``); it is resolved into the config, not passed to the handler.
        keyed: the value enters the cache key and ``config.options`` (the default); an option that
            cannot change the output says so with ``keyed=False`` and ``why_not_keyed``.
        minimum: smallest allowed value of an int option.
        metavar: shown in ``--help``.
        multiple: repeatable; the value is the list of all given.
    """

    flag: str
    name: str
    help: str
    type: Any = str
    default: Any = None
    aliases: tuple[str, ...] = ()
    config_key: str | None = None
    config_value: Any = None
    keyed: bool = True
    why_not_keyed: str = ""
    minimum: int | None = None
    metavar: str | None = None
    multiple: bool = False

    def __post_init__(self) -> None:
        if not self.keyed and not self.why_not_keyed:
            raise ValueError(f"option {self.flag} is not keyed: say why (why_not_keyed)")


@dataclass(frozen=True)
class Output:
    """What the command writes: an artifact of ``kind`` (``"files"``: plain files, no manifest)."""

    kind: str
    help: str
    flag: str = "--out"
    name: str = "out"
    required: bool = True
    dir_okay: bool = True
    file_okay: bool = True


@dataclass(frozen=True)
class Command:
    """One command: ``path`` (``("ik",)``, ``("train", "ik")``), the stage whose
    ``stages/<stage>.yaml`` configures it, its summary (``--help``; the first sentence goes to the
    README), the handler, and its inputs, options and output."""

    path: tuple[str, ...]
    stage: str
    summary: str
    handler: str
    output: Output
    inputs: tuple[Input, ...] = ()
    options: tuple[Option, ...] = ()
    per_frame: bool = False  # --frames/--shard: a partial artifact for `egorelight merge`

    @property
    def name(self) -> str:
        return " ".join(self.path)

    @property
    def training(self) -> bool:
        return self.path[0] == "train"

    def params(self) -> tuple[Input | Option | Output, ...]:
        return (*self.inputs, *self.options, self.output)

    def handler_function(self) -> Callable[..., Any]:
        module, _, attr = self.handler.partition(":")
        return getattr(importlib.import_module(module), attr)

    def handler_values(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """The handler's keywords from the parsed command line ``values`` (config-key options are
        consumed by the config; ``frames``/``shard`` become ``frame_range``)."""
        kwargs = {p.name: values.get(p.name) for p in self.params()
                  if not (isinstance(p, Option) and p.config_key)}
        if self.per_frame:
            from egorelight_cli.sharding import FrameRange

            kwargs["frame_range"] = FrameRange.parse(values.get("frames"), values.get("shard"))
        return kwargs

    def config_sets(self, values: Mapping[str, Any]) -> list[str]:
        """``--set`` items for the options given that stand for config keys."""
        sets = []
        for option in self.options:
            value = values.get(option.name)
            if option.config_key is None or value is None or value is False:
                continue
            value = option.config_value if option.type is bool else value
            sets.append(f"{option.config_key}={_yaml_text(value)}")
        return sets

    def keyed_options(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """The options that enter the cache key and ``config.options``: every keyed option that was
        given (None means not given), and the frame range of a partial per-frame run."""
        keyed = {}
        for option in self.options:
            value = values.get(option.name)
            if option.keyed and option.config_key is None and value is not None:
                keyed[option.name] = list(value) if isinstance(value, tuple) else value
        if self.per_frame:
            from egorelight_cli.sharding import FrameRange

            keyed.update(FrameRange.parse(values.get("frames"), values.get("shard")).key())
        return keyed

    def _given(self, values: Mapping[str, Any]) -> list[tuple[Input, int, Path]]:
        """The inputs the user gave as paths: (input, index among its values, path); built-ins left out."""
        return [(inp, i, Path(v)) for inp in self.inputs for i, v in enumerate(_as_list(values.get(inp.name)))
                if v is not None and str(v) not in BUILTIN_VALUES]

    @staticmethod
    def _source_of(path: Path, given: list[tuple[Input, int, Path]]) -> tuple[Input, int] | None:
        """The given input (and value index) a file read came through: the nearest related path
        (:func:`_nesting`), the first given on a tie; None for a file the command found itself."""
        ranked = sorted((_nesting(path, g), k) for k, (_, _, g) in enumerate(given))
        if not ranked or ranked[0][0] >= 3:
            return None
        inp, index, _ = given[ranked[0][1]]
        return inp, index

    def input_params(self, values: Mapping[str, Any], artifacts: Sequence[Any], source_files: Sequence[Path]
                     ) -> list[str | None]:
        """The declared input each artifact came through (its flag; None for an artifact the
        command found itself, e.g. inside another input), after checking the declaration holds:

        * an artifact read through an input is of a kind that input accepts;
        * every input the user gave entered the cache key, as an artifact or a source file.

        A failure is a bug in the command (it reads what it does not declare), so it raises
        ``RuntimeError``, not a user error.
        """
        given = self._given(values)
        params: list[str | None] = []
        for artifact in artifacts:
            source = self._source_of(artifact.path, given)
            if source is not None and source[0].kinds and artifact.kind not in source[0].kinds:
                raise RuntimeError(f"{self.name}: {source[0].flag} read a {artifact.kind} artifact; it declares "
                                   f"{', '.join(source[0].kinds)}")
            params.append(None if source is None else source[0].flag)
        recorded = [a.path for a in artifacts] + [Path(p) for p in source_files]
        for inp, _, path in given:
            if not any(_related(r, path) for r in recorded):
                raise RuntimeError(f"{self.name}: input {inp.flag} {path} did not enter the cache key")
        return params

    def source_params(self, values: Mapping[str, Any], source_files: Sequence[Path]) -> list[str | None]:
        """The declared input each non-artifact file read came through (as :meth:`input_params`)."""
        given = self._given(values)
        return [None if (source := self._source_of(Path(p), given)) is None else source[0].flag
                for p in source_files]

    def read_in_given_order(self, values: Mapping[str, Any], paths: Sequence[Path]) -> bool:
        """Whether the files read (``paths``, in the order their digests enter the cache key) follow
        the order the user gave each repeatable input's values in: the same files given in another
        order make another key, so a recorded key only holds for the recorded order."""
        given = self._given(values)
        last: dict[str, int] = {}
        for path in paths:
            source = self._source_of(Path(path), given)
            if source is None:
                continue
            flag, index = source[0].flag, source[1]
            if index < last.get(flag, 0):
                return False
            last[flag] = index
        return True


def _as_list(value: Any) -> list:
    if value is None:
        return []
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _nesting(artifact: Path, given: Path) -> int:
    """How an artifact's path relates to a path the user gave: 0 the same, 1 the artifact lies inside
    it (found in a given folder), 2 it lies inside the artifact (a payload named directly), 3 unrelated."""
    artifact, given = Path(artifact).resolve(), Path(given).resolve()
    if artifact == given:
        return 0
    return 1 if artifact.is_relative_to(given) else 2 if given.is_relative_to(artifact) else 3


def _related(a: Path, b: Path) -> bool:
    """``a`` and ``b`` are the same path or one lies inside the other."""
    return _nesting(a, b) < 3


def _yaml_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


# ---------------------------------------------------------------------------------- README
def _accepts(inp: Input) -> str:
    kinds = [f"`{k}`" for k in inp.kinds] + [f"`{f}`" for f in inp.files]
    return " / ".join(kinds)


def markdown_table(commands: Sequence[Command]) -> str:
    """The README's command table: per command, what it reads, its own options and what it writes."""
    rows = ["| command | reads | options | writes |", "|---|---|---|---|"]
    for command in commands:
        reads = "<br>".join(f"`{i.flag}`{'' if i.required else ' (optional)'}: {_accepts(i)}"
                            for i in command.inputs) or "-"
        options = [f"`{o.flag}`" + (f" (`{o.config_key}`)" if o.config_key else "") for o in command.options]
        if command.per_frame:
            options.append("`--frames` / `--shard`")
        writes = f"`{command.output.kind}`" if command.output.kind != "files" else "files"
        summary = command.summary.split(". ")[0].rstrip(".")
        rows.append(f"| `{command.name}`: {summary} | {reads} | {', '.join(options) or '-'} | {writes} |")
    return "\n".join(rows) + "\n"


TABLE_BEGIN = "<!-- commands: generated from src/egorelight_cli/declarations.py; do not edit -->"
TABLE_END = "<!-- commands: end -->"


def replace_table(text: str, table: str) -> str:
    """``text`` (the README) with the block between the table markers replaced by ``table``."""
    start, end = text.index(TABLE_BEGIN) + len(TABLE_BEGIN), text.index(TABLE_END)
    return text[:start] + "\n" + table + text[end:]
