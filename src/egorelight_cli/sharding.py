"""Frame shards of a per-frame stage, and merging them into the artifact one run would write.

A per-frame stage given ``--frames A:B`` (positions in the sequence's output frames, Python slice
rules) or ``--shard I/N`` (part I of N contiguous, near-equal parts, I from 0) computes only those
frames (reading whatever context frames its temporal window needs) and writes a **partial
artifact** of the stage's kind. Its manifest's ``shard`` entry says which frames it holds and of
how many, and its payloads are exactly the single run's payloads restricted to those frames:

* per-frame arrays in npz files (rows along the first axis; the npz metadata's ``rows`` names
  them), and per-frame files (``<camera>/<frame>.exr``, ``depth/<role>/<frame>.exr``);
* ``scores.npz``: per-record score statistics (a record is a frame, or a frame and camera), from
  which the stage computes its ground-truth metrics, so that the metrics of the whole sequence are
  a function of the concatenated records;
* ``preview_tiles/<position>.png``: the rows of the single run's preview that fall in the shard.

``egorelight merge PART... --out ARTIFACT`` (:func:`merge_parts`) checks that the parts are of one
kind, one stage, one cache key apart from the frame range, and cover the sequence exactly once;
concatenates the rows in frame order, copies the per-frame files, stacks the preview tiles into
``preview.png`` and asks the stage for the metrics of the merged scores: the same computation the
single run does. Where the computation is deterministic the payloads are byte-identical to a
single run's.
"""

from __future__ import annotations

import filecmp
import importlib
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli import console
from egorelight_cli.artifacts import ArtifactWriter, cache_key, is_up_to_date, open_artifact
from egorelight_cli.atomic_output import restore_interrupted_swap
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.images import read_image, write_image
from egorelight_cli.io.npz import read_npz, write_npz
from egorelight_cli.outputs import check_output

FRAMES_PATTERN = re.compile(r"^\s*(-?\d*)\s*:\s*(-?\d*)\s*$")
SHARD_PATTERN = re.compile(r"^\s*(\d+)\s*/\s*(\d+)\s*$")


def evenly_spaced(items, count: int):
    """``count`` of ``items`` (a sequence or array) at evenly spaced positions, first and last
    included, in order; all of them when ``count`` is 0 or at least their number (training-set
    subsets for learning curves)."""
    if count <= 0 or len(items) <= count:
        return items
    picks = np.linspace(0, len(items) - 1, count).round().astype(int)
    return items[picks] if isinstance(items, np.ndarray) else [items[i] for i in picks]


def split_frames(frames: Sequence[int], max_frames: int, validation_frames: int) -> tuple[list[int], list[int]]:
    """(training, validation) frames of one sequence (``train egodepth``, ``train animate``).

    Training: ``max_frames`` evenly spaced (all when 0); validation: ``validation_frames`` evenly
    spaced among the frames training leaves. When training takes every frame, the validation frames
    are set aside first, provided at least as many remain to train on; otherwise there is no
    validation frame."""
    frames = [int(f) for f in frames]
    training = list(evenly_spaced(frames, max_frames))
    rest = [f for f in frames if f not in set(training)]
    if validation_frames <= 0:
        return training, []
    if rest:
        return training, list(evenly_spaced(rest, validation_frames))
    if len(frames) < 2 * validation_frames:
        return training, []
    validation = list(evenly_spaced(frames, validation_frames))
    return list(evenly_spaced([f for f in frames if f not in set(validation)], max_frames)), validation


@dataclass(frozen=True)
class FrameRange:
    """Which of a sequence's output frames (by position) a run computes: ``frames`` (start, stop)
    or ``shard`` (index, count); neither: all of them."""

    frames: tuple[int | None, int | None] | None = None
    shard: tuple[int, int] | None = None

    @classmethod
    def parse(cls, frames: str | None = None, shard: str | None = None) -> "FrameRange":
        """From ``--frames A:B`` and/or ``--shard I/N`` (not both)."""
        if frames and shard:
            raise EgorelightError("give --frames or --shard, not both")
        if frames:
            match = FRAMES_PATTERN.match(frames)
            if not match:
                raise EgorelightError(f"--frames {frames!r} is not A:B (positions in the sequence's frames)")
            start, stop = (int(g) if g else None for g in match.groups())
            return cls(frames=(start, stop))
        if shard:
            match = SHARD_PATTERN.match(shard)
            if not match:
                raise EgorelightError(f"--shard {shard!r} is not I/N (part I of N, I from 0)")
            index, count = int(match.group(1)), int(match.group(2))
            if count < 1 or index >= count:
                raise EgorelightError(f"--shard {shard!r}: need 0 <= I < N")
            return cls(shard=(index, count))
        return cls()

    @property
    def whole(self) -> bool:
        return self.frames is None and self.shard is None

    def bounds(self, total: int) -> tuple[int, int]:
        """(start, stop) positions among ``total`` frames; an empty range is an error."""
        if self.shard is not None:
            index, count = self.shard
            start, stop = index * total // count, (index + 1) * total // count
        elif self.frames is not None:
            start, stop, _ = slice(*self.frames).indices(total)
        else:
            start, stop = 0, total
        if stop <= start:
            raise EgorelightError(f"the frame range {self.describe()} holds none of the sequence's {total} frames")
        return start, stop

    def describe(self) -> str:
        """The range as the user gave it (``--shard 1/4``), or ``all frames``."""
        return " ".join(f"--{option} {value}" for option, value in self.key().items()) or "all frames"

    def manifest(self, total: int) -> dict | None:
        """The manifest's ``shard`` entry (None for a whole run)."""
        if self.whole:
            return None
        start, stop = self.bounds(total)
        return {"start": start, "stop": stop, "sequence_frames": total}

    def key(self) -> dict:
        """The command option that enters the cache key and ``config.options`` (none for a whole run)."""
        if self.shard is not None:
            return {"shard": f"{self.shard[0]}/{self.shard[1]}"}
        if self.frames is not None:
            start, stop = ("" if v is None else v for v in self.frames)
            return {"frames": f"{start}:{stop}"}
        return {}


PREVIEW_TILES = "preview_tiles"
#: per shardable stage, the module whose ``merged_metrics(root, part_manifests)`` computes the merged
#: artifact's metrics from its merged payloads (as the stage's single run does)
MERGED_METRICS = {"egopose": "egorelight_cli.stages.egopose_scores", "relight": "egorelight_cli.stages.relight_eval",
                  "egodepth": "egorelight_cli.stages.egodepth_scores", "geolift": "egorelight_cli.stages.geolift_eval"}
SHARD_OPTIONS = ("frames", "shard")


def write_preview(writer, rows: dict[int, np.ndarray], frame_range: FrameRange, name: str = "preview.png") -> None:
    """A whole run's preview ``name``: the rows (position -> (H,W,3) uint8) stacked in position
    order; a shard's: each row as ``preview_tiles/<position>.png`` for :func:`merge_parts`."""
    if frame_range.whole:
        if rows:
            write_image(writer.path(name), stack_preview_rows([rows[p] for p in sorted(rows)]))
        return
    for position, image in rows.items():
        write_image(writer.path(f"{PREVIEW_TILES}/{position:06d}.png"), image)


def stack_preview_rows(rows: list[np.ndarray]) -> np.ndarray:
    """Preview rows (one per frame) stacked vertically, narrower rows padded with white on the right."""
    from egorelight_cli.render.sheets import stack_rows

    return stack_rows(rows, max_width=None, fill=255)


# ------------------------------------------------------------------------------------- merge
def _base_config(manifest: dict) -> dict:
    """A part's keyed config without its frame range: the single run's."""
    config = dict(manifest.get("config") or {})
    options = {k: v for k, v in (config.get("options") or {}).items() if k not in SHARD_OPTIONS}
    config.pop("options", None)
    if options:
        config["options"] = options
    return config


def _check_parts(parts) -> list:
    """The parts sorted by their first frame; one stage run's shards covering its frames once."""
    for part in parts:
        if part.single_file:
            raise EgorelightError("merge joins directory artifacts (shards of a per-frame stage)", part.path)
        if not isinstance(part.manifest.get("shard"), dict):
            raise EgorelightError("not a frame shard (written without --frames/--shard)", part.manifest_path)
    first = parts[0].manifest
    for part in parts[1:]:
        m = part.manifest
        for field, what in (("kind", "kind"), ("stage", "stage"), ("stage_version", "stage version")):
            if m.get(field) != first.get(field):
                raise EgorelightError(f"parts differ in {what} ({m.get(field)} vs {first.get(field)})", part.manifest_path)
        if _base_config(m) != _base_config(first):
            raise EgorelightError("parts were made with different config or options", part.manifest_path)
        if [(i.get("kind"), i.get("digest")) for i in m.get("inputs", [])] != \
                [(i.get("kind"), i.get("digest")) for i in first.get("inputs", [])]:
            raise EgorelightError("parts were made from different inputs", part.manifest_path)
        if [i.get("digest") for i in m.get("sources", [])] != [i.get("digest") for i in first.get("sources", [])]:
            raise EgorelightError("parts were made from different input files", part.manifest_path)
        if m["shard"]["sequence_frames"] != first["shard"]["sequence_frames"]:
            raise EgorelightError("parts are shards of sequences of different lengths", part.manifest_path)
    ordered = sorted(parts, key=lambda p: p.manifest["shard"]["start"])
    position = 0
    for part in ordered:
        shard = part.manifest["shard"]
        if shard["start"] != position:
            what = "overlap" if shard["start"] < position else f"leave frames {position}..{shard['start'] - 1} out"
            raise EgorelightError(f"the parts {what}", part.manifest_path)
        position = shard["stop"]
    if position != first["shard"]["sequence_frames"]:
        raise EgorelightError(f"the parts end at frame {position} of {first['shard']['sequence_frames']}: "
                              "a shard is missing", ordered[-1].manifest_path)
    return ordered


def _merge_npz(paths: list, target) -> None:
    """Concatenate the row arrays (``rows`` in the npz metadata) of ``paths`` in order; every other
    array and the metadata (but ``frame_ids``) must agree."""
    loaded = [read_npz(p, check_finite=False) for p in paths]
    arrays, meta = loaded[0]
    rows = meta.get("rows")
    if not isinstance(rows, list):
        raise EgorelightError("this npz has no per-frame rows to merge (no 'rows' in its metadata)", paths[0])
    merged = {}
    for name, value in arrays.items():
        if name in rows:
            merged[name] = np.concatenate([a[name] for a, _ in loaded], axis=0)
        else:
            for (other, _), path in zip(loaded[1:], paths[1:]):
                if name not in other or not np.array_equal(other[name], value):
                    raise EgorelightError(f"array {name!r} differs between the parts", path)
            merged[name] = value
    frame_ids = [f for _, m in loaded for f in m.get("frame_ids", [])]
    for (_, m), path in zip(loaded[1:], paths[1:]):
        if {k: v for k, v in m.items() if k != "frame_ids"} != {k: v for k, v in meta.items() if k != "frame_ids"}:
            raise EgorelightError("npz metadata differs between the parts", path)
    write_npz(target, merged, {**meta, "frame_ids": frame_ids} if "frame_ids" in meta else meta)


def merge_parts(paths, out, force: bool = False, preview_name: str = "preview.png"):
    """Join frame shards ``paths`` into ``out`` (see the module docstring); returns ``out``."""
    out = Path(out)
    parts = _check_parts([open_artifact(p) for p in paths])
    first = parts[0].manifest
    inputs = []
    for entry in first.get("inputs", []):
        inputs.append(open_artifact(parts[0].manifest_path.parent / entry["path"]))
        if inputs[-1].digest != entry["digest"]:
            raise EgorelightError("an input changed since the parts were made", inputs[-1].path)
    sources = first.get("sources", [])
    config = _base_config(first)
    key = cache_key(first["stage"], int(first["stage_version"]), config,
                    [a.digest for a in inputs] + [s["digest"] for s in sources])
    kind = parts[0].kind
    restore_interrupted_swap(out)  # a merge a kill left half swapped: the previous output first
    check_output(out, kind, [p.path for p in parts] + [a.path for a in inputs])
    if not force and is_up_to_date(out, key, kind):
        console.info(f"{out}: up to date, skipped (--force re-runs it)")
        return out
    files: dict[str, list[Path]] = {}
    for part in parts:
        for entry in part.manifest["outputs"]:
            files.setdefault(entry["path"], []).append(part.root / entry["path"])
    with ArtifactWriter(out, kind=kind, stage=first["stage"], config=config, inputs=inputs, key=key) as writer:
        writer.stage_version = int(first["stage_version"])
        if sources:
            writer.extra["sources"] = sources
        writer.extra["parts"] = [{"path": str(p.path), "digest": p.digest, "shard": p.manifest["shard"]} for p in parts]
        tiles = sorted(name for name in files if name.startswith(f"{PREVIEW_TILES}/"))
        if tiles:
            write_image(writer.path(preview_name), stack_preview_rows([read_image(files[name][0]) for name in tiles]))
        for name, copies in files.items():
            if name in tiles:
                continue
            if name.endswith(".npz") and len(copies) == len(parts):
                _merge_npz(copies, writer.path(name))
            elif len(copies) == 1 or all(filecmp.cmp(copies[0], c, shallow=False) for c in copies[1:]):
                shutil.copyfile(copies[0], writer.path(name))
            else:
                raise EgorelightError(f"{name} differs between the parts and cannot be merged", copies[1])
        if first["stage"] not in MERGED_METRICS:
            raise EgorelightError(f"stage {first['stage']} has no frame shards to merge", parts[0].manifest_path)
        scores = importlib.import_module(MERGED_METRICS[first["stage"]])
        writer.metrics.update(scores.merged_metrics(writer.workdir, [p.manifest for p in parts]))
        writer.units.update(first.get("units", {}))
        writer.runtime.update({k: first.get("runtime", {}).get(k) for k in ("device", "preset")})
        writer.runtime["merged_parts"] = len(parts)
        writer.timing["parts_wall_s"] = round(sum(float(p.manifest.get("timing", {}).get("wall_s", 0.0)) for p in parts), 3)
    console.info(f"{out}: merged {len(parts)} parts into {kind}")
    return out
