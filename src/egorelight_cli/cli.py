"""The ``egorelight`` command line: no math here. The stage commands are built from their
declarations (:mod:`egorelight_cli.declarations`, :func:`stage_command`); ``inspect``, ``report``
and ``merge`` are tools over artifacts and written out below.

Global options (``--device``, ``--threads``, ``--preset``, ``--set``, ``--force``, ``--seed``, ``-v``/``-q``)
may be given before the command (``egorelight --preset tiny ik ...``) or after it
(``egorelight ik --preset tiny ...``). Known failures print ``egorelight: error: <what>, <file>``
and exit with code 2; unexpected ones print one line too and show the traceback with ``-v``.
"""

from __future__ import annotations

import json
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import click

from egorelight_cli import __version__, console
from egorelight_cli.declarations import COMMANDS
from egorelight_cli.errors import EgorelightError
from egorelight_cli.stage_spec import Command, Input, Option, Output
from egorelight_cli.runtime import DEVICES, parse_threads
from egorelight_cli.signals import Interrupted, Terminated, terminate_as_exception


@dataclass
class RunOptions:
    """Options shared by every stage command."""

    device: str = "auto"
    threads: int | None = None  # None: the cores this process may use (runtime.available_cores)
    preset: str | None = None
    sets: list[str] = field(default_factory=list)
    force: bool = False
    seed: int | None = None
    verbosity: int = 0


def _options(ctx: click.Context) -> RunOptions:
    return ctx.ensure_object(RunOptions)


def _set_value(attr: str):
    def callback(ctx: click.Context, _param: click.Parameter, value):
        opts = _options(ctx)
        if attr == "sets":
            opts.sets.extend(value or ())
        elif attr == "force":
            opts.force = opts.force or bool(value)
        elif attr in ("verbose", "quiet"):
            if value:
                opts.verbosity += value if attr == "verbose" else -value
                console.set_verbosity(opts.verbosity)
        elif value is not None:
            setattr(opts, attr, value)
        return value
    return callback


def common_options(func):
    """The global options, accepted both before and after the command name."""
    decorators = [
        click.option("--device", type=click.Choice(DEVICES), default=None, expose_value=False,
                     callback=_set_value("device"), help="Compute device (auto: CUDA when present)."),
        click.option("--threads", default=None, expose_value=False, metavar="N",
                     callback=lambda ctx, param, value: _set_value("threads")(ctx, param, parse_threads(value)),
                     help="CPU threads for torch, BLAS/OpenMP and OpenCV (default: the cores this process may "
                          "use: affinity, cgroup quota, OMP_NUM_THREADS, SLURM_CPUS_PER_TASK)."),
        click.option("--preset", default=None, expose_value=False, callback=_set_value("preset"),
                     help="Named config preset: tiny, cpu (default) or paper."),
        click.option("--set", "sets", multiple=True, expose_value=False, callback=_set_value("sets"),
                     metavar="KEY=VALUE", help="Override one config key (repeatable), e.g. --set solver.iterations=50."),
        click.option("--force", is_flag=True, default=False, expose_value=False, callback=_set_value("force"),
                     help="Re-run even when the output is up to date."),
        click.option("--seed", type=int, default=None, expose_value=False, callback=_set_value("seed"),
                     help="Random seed (recorded in the manifest)."),
        click.option("-v", "--verbose", count=True, expose_value=False, callback=_set_value("verbose"),
                     help="More output; show tracebacks of internal errors."),
        click.option("-q", "--quiet", count=True, expose_value=False, callback=_set_value("quiet"),
                     help="Only errors."),
    ]
    for decorator in reversed(decorators):
        func = decorator(func)
    return func


class _Group(click.Group):
    """The root group: Ctrl-C inside a command leaves it as :class:`~egorelight_cli.signals.Interrupted`
    (click would print an empty line and turn it into ``Abort``)."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as exc:
            raise Interrupted() from exc


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="egorelight")
@common_options
def cli() -> None:
    """EgoRelight as a batch tool: egocentric capture -> relightable avatar -> HDR light."""


# ------------------------------------------------------------------------------------ inspect
@cli.command("inspect")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@common_options
def inspect_command(path: Path, as_json: bool) -> None:
    """Say what an artifact, manifest, npz, EXR or PNG is: kind, version, arrays, metrics and
    the chain of inputs it was made from. Exits 2 after the description when a payload of the
    artifact is missing or no longer matches its manifest (a health check)."""
    from egorelight_cli.inspect import describe, format_description

    info = describe(path)
    click.echo(json.dumps(info, indent=2) if as_json else format_description(info))
    problems = info.get("payload_problems") or []
    if problems:
        raise EgorelightError(f"{len(problems)} payload(s) missing or modified, the first {problems[0]['path']}", path)


# ------------------------------------------------------------------------------------- report
@cli.command("report")
@click.argument("subject", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Report folder (default: SUBJECT/report); holds index.html and assets/.")
@common_options
def report_command(subject: Path, out: Path | None) -> None:
    """One HTML page for a subject directory: every stage's inputs, config, timing, metrics next to
    their baselines and the paper's figures, previews and curves. Reads artifacts only."""
    from egorelight_cli.report import build_report

    click.echo(str(build_report(subject, out)))


# --------------------------------------------------------------------------- command groups
@cli.group("character")
def character_group() -> None:
    """Characters: the shipped default, DDC (Skeletool) import/export, previews, fit to a scan."""


@cli.group("capture")
def capture_group() -> None:
    """Captures: a real capture converted to the layout made an artifact every stage takes."""


@cli.group("train")
def train_group() -> None:
    """Fit the learned model of a stage (writes a model artifact)."""


@cli.command("merge")
@click.argument("parts", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path), help="The merged artifact directory.")
@common_options
@click.pass_context
def merge_command(ctx: click.Context, parts: tuple[Path, ...], out: Path) -> None:
    """Join the frame shards PARTS of one per-frame stage run (--frames / --shard) into the artifact
    a single run over all frames writes."""
    from egorelight_cli.sharding import merge_parts

    merge_parts(parts, out, force=_options(ctx).force)


# ---------------------------------------------------------------------- declared stage commands
def _stage_run(ctx: click.Context, declared: Command, values: dict):
    """The :class:`~egorelight_cli.pipeline.StageRun` of one declared command: the global options,
    plus the ``--set`` items its config-key options stand for."""
    from egorelight_cli.config import parse_set
    from egorelight_cli.pipeline import StageRun

    opts = _options(ctx)
    shorthand = declared.config_sets(values)
    given = {}  # key -> (value, the --set item)
    for item in opts.sets:
        key, value, _ = parse_set(item)
        given[key] = (value, item)
    for item in shorthand:  # an option and a --set of the key it stands for must agree (as the config reads them)
        key, value, _ = parse_set(item)
        if key in given and given[key][0] != value:
            option = next(o.flag for o in declared.options if o.config_key == key)
            raise EgorelightError(f"{option} sets {item} but --set {given[key][1]} says otherwise: give one of them")
    return StageRun(declared.stage, preset=opts.preset, sets=(*opts.sets, *shorthand),
                    seed=opts.seed, force=opts.force, device=opts.device, threads=opts.threads,
                    training=declared.training, command=declared, values=values)


def _path_type(dir_okay: bool = True, file_okay: bool = True, exists: bool = False) -> click.Path:
    return click.Path(path_type=Path, dir_okay=dir_okay, file_okay=file_okay, exists=exists)


def _input_decorator(inp: Input):
    kind = _path_type(inp.dir_okay, inp.file_okay) if inp.is_path else str
    if inp.argument:
        return click.argument(inp.name, nargs=-1 if inp.multiple else 1, type=kind,
                              required=inp.required)
    return click.option(inp.flag, *inp.aliases, inp.name, required=inp.required, multiple=inp.multiple, type=kind,
                        default=inp.default, show_default=inp.default is not None, help=inp.help)


def _option_decorator(option: Option):
    if option.type is bool:
        return click.option(option.flag, *option.aliases, option.name, is_flag=True, default=bool(option.default),
                            help=option.help)
    if isinstance(option.type, tuple):
        kind = click.Choice(option.type)
    elif option.type == "folder":
        kind = _path_type(file_okay=False, exists=True)
    elif option.type is int and option.minimum is not None:
        kind = click.IntRange(min=option.minimum)
    else:
        kind = option.type
    return click.option(option.flag, *option.aliases, option.name, type=kind, default=option.default,
                        multiple=option.multiple, metavar=option.metavar,
                        show_default=option.default is not None and option.default is not False, help=option.help)


def _output_decorator(output: Output):
    return click.option(output.flag, output.name, required=output.required, help=output.help,
                        type=_path_type(output.dir_okay, output.file_okay))


def _frame_decorators():
    """``--frames A:B`` / ``--shard I/N`` of a per-frame stage (see
    :class:`~egorelight_cli.sharding.FrameRange`); ``egorelight merge`` joins the parts."""
    return [click.option("--frames", default=None, metavar="A:B",
                         help="Compute only the output frames at positions A..B-1: a partial artifact for "
                              "`egorelight merge`."),
            click.option("--shard", default=None, metavar="I/N",
                         help="Compute part I of N contiguous frame shards (I from 0): a partial artifact for "
                              "`egorelight merge`.")]


def stage_command(declared: Command) -> click.Command:
    """The click command of a declaration: its inputs, options and output in declared order, then
    ``--frames``/``--shard`` for a per-frame stage, then the global options."""

    @click.pass_context
    def callback(ctx: click.Context, **values) -> None:
        run = _stage_run(ctx, declared, values)
        if run.recorded_up_to_date(values[declared.output.name]):
            return  # a cached no-op: the handler (and torch) is never imported
        declared.handler_function()(run, **declared.handler_values(values))

    decorators = ([_input_decorator(i) for i in declared.inputs] + [_option_decorator(o) for o in declared.options]
                  + [_output_decorator(declared.output)] + (_frame_decorators() if declared.per_frame else []))
    func = common_options(callback)
    for decorator in reversed(decorators):
        func = decorator(func)
    return click.command(declared.path[-1], help=declared.summary)(func)


def _register_stage_commands() -> None:
    groups = {("character",): character_group, ("capture",): capture_group, ("train",): train_group}
    for declared in COMMANDS:
        groups.get(declared.path[:-1], cli).add_command(stage_command(declared))


_register_stage_commands()


# ------------------------------------------------------------------------------- entry point
def main(argv: list[str] | None = None) -> None:
    """Console-script entry: maps failures to one line and an exit code."""
    console.set_verbosity(console.NORMAL)  # -q/-v of an earlier in-process call must not leak into this one
    try:
        with terminate_as_exception():  # SIGTERM cleans up like Ctrl-C (egorelight_cli.signals)
            cli.main(args=argv, prog_name="egorelight", standalone_mode=False)
        code = 0
    except click.exceptions.Exit as exc:
        code = exc.exit_code
    except click.exceptions.NoArgsIsHelpError as exc:  # a group without a command: its help
        exc.show()
        code = exc.exit_code
    except click.UsageError as exc:  # one line, like every other bad input
        command = exc.ctx.command_path if exc.ctx is not None else "egorelight"
        click.echo(f"egorelight: error: {exc.format_message()} (see '{command} --help')", err=True)
        code = 2
    except click.ClickException as exc:
        click.echo(f"egorelight: error: {exc.format_message()}", err=True)
        code = exc.exit_code
    except click.exceptions.Abort:
        click.echo("egorelight: aborted", err=True)
        code = 130
    except EgorelightError as exc:
        click.echo(f"egorelight: error: {exc}", err=True)
        if console.verbosity() > 0:
            traceback.print_exc()
        code = 2
    except (KeyboardInterrupt, Interrupted):
        click.echo("egorelight: interrupted", err=True)
        code = 130
    except Terminated:
        click.echo("egorelight: terminated", err=True)
        code = 143
    except Exception as exc:  # a bug: one line, the traceback with -v
        if console.verbosity() > 0:
            traceback.print_exc()
        click.echo(f"egorelight: internal error: {type(exc).__name__}: {exc} (run with -v for the traceback)", err=True)
        code = 1
    sys.exit(code)


if __name__ == "__main__":
    main()
