"""Running one stage: resolve its config, refuse an unsafe ``--out`` (:mod:`egorelight_cli.outputs`),
skip it when up to date, write its artifact atomically.

This is the glue every CLI command uses, so that the commands themselves stay thin::

    run = StageRun("ik", preset="cpu", sets=("solver.iterations=50",))
    run.produce(out, kind="motion", inputs=[keypoints], write=lambda w: ...)
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from egorelight_cli import console
from egorelight_cli.artifacts import Artifact, ArtifactWriter, cache_key, cached_sha256_file, is_up_to_date
from egorelight_cli.atomic_output import output_error, remove_stale_temporaries
from egorelight_cli.config import Config, resolve_config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.outputs import check_output
from egorelight_cli.runtime import apply_threads, available_cores, resolve_device
from egorelight_cli.stage_spec import Command


@dataclass(frozen=True)
class StageRun:
    """One invocation of a stage with the user's global options."""

    stage: str
    preset: str | None = None
    sets: tuple[str, ...] = ()
    seed: int | None = None
    force: bool = False
    device: str = "auto"
    threads: int | None = None  # --threads; None: runtime.available_cores()
    training: bool = False  # a `train <stage>` command: may run data-parallel under torchrun
    #: the declaration of the command this run serves (:mod:`egorelight_cli.declarations`) and its parsed
    #: command-line values: its keyed options enter the cache key, its inputs label the manifest's
    command: Command | None = None
    values: Mapping[str, Any] = field(default_factory=dict, compare=False)

    def config(self) -> Config:
        return resolve_config(self.stage, self.preset, self.sets, self.seed)

    def compute_device(self) -> "torch.device":  # noqa: F821
        """The device this stage runs on for ``--device`` (:func:`~egorelight_cli.runtime.resolve_device`:
        ``cuda`` without a GPU, or for a CPU-only stage, is an error)."""
        return resolve_device(self.device, stage=self.stage)

    def cache_key(self, inputs: Sequence[Artifact] = (), source_files: Sequence[str | Path] = (),
                  options: Mapping[str, Any] | None = None, unkeyed: bool = False) -> tuple[str, list[dict]]:
        """(cache key, manifest ``sources`` entries): hash of the stage, its version, the resolved
        config plus the command's output-affecting ``options``, and the digests of every input.
        ``unkeyed``: the key as runs made it before :data:`UNKEYED_NAMES` left it (their config whole)."""
        config = self.config()
        sources = []
        for path in source_files:
            path = Path(path)
            if not path.is_file():
                raise EgorelightError("input file not found", path)
            sources.append({"path": str(path), "digest": cached_sha256_file(path)})
        digests = [a.digest for a in inputs] + [s["digest"] for s in sources]
        return (cache_key(self.stage, config.version, _keyed_config(config, self.options(options), unkeyed), digests),
                sources)

    def options(self, explicit: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """The options that enter the cache key and ``config.options``: the declared command's keyed
        options (:meth:`~egorelight_cli.stage_spec.Command.keyed_options`) and the ones the command
        derives itself (``explicit``, e.g. a parsed lighting), under other names (a clash is a bug)."""
        declared = self.command.keyed_options(self.values) if self.command is not None else {}
        clash = set(declared) & set(explicit or {})
        if clash:  # a derived option must not shadow a declared one (the early cache check compares them)
            raise RuntimeError(f"{self.stage}: options {sorted(clash)} are both declared and derived")
        return {**declared, **(explicit or {})}

    def recorded_up_to_date(self, out: str | Path) -> bool:
        """The cache check from the output's own manifest, before the command imports or loads
        anything (a cached no-op in well under a second): True when ``out`` holds an intact
        artifact of the declared kind made by this stage and version with the same resolved
        config and declared options, every input and source file it records is unchanged, and
        every input given on the command line is one of them. Any doubt returns False and the
        command runs its own check (:meth:`up_to_date`), which is the same key computed from
        what it loads."""
        command = self.command
        if (self.force or command is None or command.output.kind == "files" or self.device == "cuda"
                or os.environ.get("WORLD_SIZE", "1").strip() not in ("", "1")):
            return False
        try:
            return self._recorded_key_holds(Path(out), command)
        except (EgorelightError, OSError, KeyError, TypeError, ValueError, RuntimeError):
            return False  # e.g. a given input that is not a recorded one (input_params raises)

    def _recorded_key_holds(self, out: Path, command: Command) -> bool:
        from egorelight_cli.artifacts import manifest_path_for, open_artifact

        manifest_path, _ = manifest_path_for(out)
        if not manifest_path.is_file():
            return False
        artifact = open_artifact(out, kind=command.output.kind, verify=False)
        manifest, config = artifact.manifest, self.config()
        recorded = dict(manifest.get("config") or {})
        recorded_options = recorded.pop("options", {}) or {}
        whole = config.to_dict()
        declared = json.loads(json.dumps(_keyed_config(Config({}), command.keyed_options(self.values))))
        declared = declared.get("options", {})
        names = {o.name for o in command.options} | ({"frames", "shard"} if command.per_frame else set())
        if (manifest.get("stage") != self.stage or manifest.get("stage_version") != config.version
                # (a manifest from before UNKEYED_NAMES recorded the whole config, and holds with it)
                or recorded not in (split_unkeyed(whole)[0], whole)
                or {k: v for k, v in recorded_options.items() if k in names} != declared):
            return False
        recorded_inputs, recorded_sources = manifest.get("inputs", []), manifest.get("sources", [])
        inputs = [open_artifact(artifact.root / entry["path"]) for entry in recorded_inputs]
        if [a.digest for a in inputs] != [entry["digest"] for entry in recorded_inputs]:
            return False
        sources = [Path(entry["path"]) for entry in recorded_sources]
        if [cached_sha256_file(p) for p in sources] != [entry["digest"] for entry in recorded_sources]:
            return False
        # every given input is a recorded one (else input_params raises), each came through the flag it
        # was recorded under (an input left out, or two files swapped, is another key), in the given order
        if (command.input_params(self.values, inputs, sources) != [e.get("param") for e in recorded_inputs]
                or command.source_params(self.values, sources) != [e.get("param") for e in recorded_sources]
                or not command.read_in_given_order(self.values, [a.path for a in inputs])
                or not command.read_in_given_order(self.values, sources)):
            return False
        key = cache_key(self.stage, config.version, {**recorded, **({"options": recorded_options}
                                                                     if recorded_options else {})},
                        [a.digest for a in inputs] + [entry["digest"] for entry in recorded_sources])
        if key != manifest.get("cache_key") or artifact.payload_problems():
            return False
        console.info(f"{out}: up to date, skipped (--force re-runs it)")
        return True

    def up_to_date(self, out: str | Path, kind: str, inputs: Sequence[Artifact] = (),
                   source_files: Sequence[str | Path] = (), options: Mapping[str, Any] | None = None) -> bool:
        """The cache check alone (False with ``--force``): a command calls it with its opened (and
        so verified) inputs before loading anything heavy, and returns at once when it holds."""
        if self.force:
            return False
        key, _ = self.cache_key(inputs, source_files, options)
        if not is_up_to_date(out, key, kind) and not (  # or made before UNKEYED_NAMES left the key
                split_unkeyed(self.config().to_dict())[1]
                and is_up_to_date(out, self.cache_key(inputs, source_files, options, unkeyed=True)[0], kind)):
            return False
        console.info(f"{out}: up to date, skipped (--force re-runs it)")
        return True

    def produce(
        self,
        out: str | Path,
        kind: str,
        write: Callable[[ArtifactWriter, Config], None],
        inputs: Sequence[Artifact] = (),
        source_files: Sequence[str | Path] = (),
        options: Mapping[str, Any] | None = None,
    ) -> Path:
        """Write artifact ``out`` of ``kind`` unless it is up to date.

        Args:
            out: artifact directory, or a single payload file (``x.npz``) with a sidecar.
            kind: artifact kind (short name).
            write: fills the writer (payloads, metrics); raising discards the partial output.
            inputs: artifacts read; their digests enter the cache key and the manifest.
            source_files: non-artifact files read (e.g. DDC files); their digests enter the cache
                key and the manifest's ``sources``.
            options: the command's options that change the output and are not config keys
                (``sequence``, flags): they enter the cache key and the manifest's ``config.options``.
        """
        out = Path(out)
        threads, threads_source = (self.threads, "--threads") if self.threads is not None else available_cores()
        apply_threads(threads)  # before the stage's work (every command works inside ``write``)
        config = self.config()
        device = self.compute_device()
        try:  # killed runs' leftovers: a half-done swap undone (the output checks then see the previous
            remove_stale_temporaries(out)  # output, which may be up to date), the rest removed, even if skipped
        except OSError as exc:
            raise output_error(exc, out) from None
        check_output(out, kind, [p for a in inputs for p in (a.path, a.manifest_path)] + list(source_files),
                     self.stage)
        if self.up_to_date(out, kind, inputs, source_files, options):
            return out
        group = self._join_process_group(device)
        key, sources = self.cache_key(inputs, source_files, options)
        started = time.perf_counter()
        params = (self.command.input_params(self.values, inputs, [Path(p) for p in source_files])
                  if self.command is not None else None)
        if self.command is not None:  # the declared input each source file came through (the early cache check)
            source_params = self.command.source_params(self.values, [Path(s["path"]) for s in sources])
            sources = [{**s, "param": param} if param is not None else s for s, param in zip(sources, source_params)]
        with ArtifactWriter(out, kind=kind, stage=self.stage, config=config, inputs=inputs, key=key,
                            keep=group is None or group.primary, input_params=params) as writer:
            writer.config = _keyed_config(config, self.options(options))
            unkeyed = split_unkeyed(config.to_dict())[1]
            if unkeyed:
                writer.runtime["unkeyed_config"] = unkeyed
            if self.command is not None:
                writer.runtime["command"] = self.command.name
            if sources:
                writer.extra["sources"] = sources
            writer.runtime["device"] = device.type
            writer.runtime["device_requested"] = self.device
            writer.runtime["threads"] = threads
            writer.runtime["threads_source"] = threads_source
            writer.runtime["preset"] = config.preset
            if group is not None and group.distributed:
                writer.runtime["distributed"] = group.manifest()
            write(writer, config)
            writer.timing["wall_s"] = round(time.perf_counter() - started, 3)
        if group is not None and group.distributed:
            _leave_process_group()  # after rank 0 has committed
        console.info(f"{out}: wrote {kind} ({writer.timing['wall_s']:.1f} s)")
        return out

    def _join_process_group(self, device):
        """The torchrun process group of a ``train`` command (a single process without torchrun);
        None for other commands, which refuse to run under torchrun (their ranks would race for one
        output) and do not import torch for it."""
        world_size = os.environ.get("WORLD_SIZE", "1").strip() or "1"
        if not self.training:
            if world_size != "1":
                raise EgorelightError(f"{self.stage} does not run under torchrun (WORLD_SIZE={world_size}): only "
                                      "`train <stage>` is data-parallel; shard a per-frame stage with --shard and "
                                      "`egorelight merge` instead")
            return None
        from egorelight_cli.nn import distributed

        group = distributed.init_from_environment(device)
        if not group.primary:
            console.set_verbosity(console.QUIET)  # rank 0 speaks for the group
        return group


def _leave_process_group() -> None:
    from egorelight_cli.nn import distributed

    distributed.barrier()
    distributed.shutdown()


#: config keys (by name, at any depth) that say how often a run saves what it could be resumed
#: from, never what it writes: left out of the cache key and the manifest's ``config`` (recorded in
#: its ``runtime``), so that changing one neither re-runs an up-to-date output nor refuses ``--resume``
UNKEYED_NAMES = frozenset({"checkpoint_every"})


def split_unkeyed(tree: Mapping[str, Any], prefix: str = "") -> tuple[dict, dict[str, Any]]:
    """(``tree`` without its :data:`UNKEYED_NAMES` keys, ``{"dotted.key": value}`` of those)."""
    keyed: dict[str, Any] = {}
    unkeyed: dict[str, Any] = {}
    for name, value in tree.items():
        if isinstance(value, Mapping):
            keyed[name], inner = split_unkeyed(value, f"{prefix}{name}.")
            unkeyed.update(inner)
        elif name in UNKEYED_NAMES:
            unkeyed[f"{prefix}{name}"] = value
        else:
            keyed[name] = value
    return keyed, unkeyed


def _keyed_config(config: Config, options: Mapping[str, Any] | None, unkeyed: bool = False) -> dict:
    """The resolved config as the cache key and the manifest see it (without its
    :data:`UNKEYED_NAMES` keys, unless ``unkeyed``), with the command's options (paths as strings)
    under ``options``."""
    tree = config.to_dict() if unkeyed else split_unkeyed(config.to_dict())[0]
    if options:
        tree["options"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in sorted(options.items())}
    return tree
