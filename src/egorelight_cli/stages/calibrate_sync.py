"""Stream synchronisation from the lightstage's flash code.

The studio side's light schedule is known from ``sequence.json`` (per studio frame a pattern:
``flat``/``flash`` with a ``scale``, ``dark``; HDR-lit frames are left out). The ego side's is
measured: the mean brightness of every ego frame (all ego cameras averaged). The stream offset
``k`` (ego frame = studio frame + k, :mod:`egorelight_cli.io.calibration`) maximises the
correlation of the two over the sync window (the frames up to just after the flash code), with
the whole code inside the ego stream. A weak or ambiguous maximum is an error, not a guess.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.capture import SequenceInfo

KNOWN = {"flat", "flash", "dark"}


@dataclass(frozen=True)
class SyncResult:
    """Offset ``k`` (ego id = studio id + k), its correlation and the runner-up's."""

    stream_offset: int
    correlation: float
    runner_up: float
    ego_brightness: np.ndarray   # (T_ego,) mean 8-bit level per ego frame
    studio_light: np.ndarray     # (T,) light scale per studio frame (NaN: not a flat/flash/dark frame)


def studio_light_schedule(seq: SequenceInfo) -> np.ndarray:
    """(T,) light level of every studio frame: scale of flat/flash, 0 for dark, NaN otherwise."""
    lights = seq.lights
    if len(lights) != len(seq.frame_ids):
        raise EgorelightError(f"sequence {seq.name!r} lists {len(lights)} light entries for {len(seq.frame_ids)} frames",
                              seq.root / "sequence.json")
    out = np.full(len(lights), np.nan)
    for i, entry in enumerate(lights):
        pattern = entry.get("pattern")
        if pattern == "dark":
            out[i] = 0.0
        elif pattern in ("flat", "flash"):
            out[i] = float(entry.get("scale", 1.0))
    return out


def ego_brightness(seq: SequenceInfo) -> np.ndarray:
    """(T_ego,) mean 8-bit level of every ego frame, averaged over the ego cameras."""
    roles = seq.ego_roles
    levels = np.zeros(len(seq.ego_frame_ids))
    for i, e in enumerate(seq.ego_frame_ids):
        levels[i] = np.mean([seq.read_ego_image(role, int(e)).mean() for role in roles])
    return levels


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    denom = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / denom) if denom > 0 else -1.0


def find_stream_offset(seq: SequenceInfo, cfg) -> SyncResult:
    """The ego stream's offset against the studio stream (``cfg``: the ``sync`` config section)."""
    seq.require_stream("studio")
    seq.require_stream("ego")
    schedule = studio_light_schedule(seq)
    brightness = ego_brightness(seq)
    studio_ids, ego_ids = seq.frame_ids, seq.ego_frame_ids
    sync = seq.doc.get("sync") or {}
    code = list(sync.get("code", []))
    if not code:
        raise EgorelightError(f"sequence {seq.name!r} has no sync flash code (sequence.json 'sync.code')",
                              seq.root / "sequence.json")
    start = int(sync.get("code_start_frame", 0))
    code_rows = np.arange(start, start + len(code))
    window = np.arange(0, min(start + len(code) + int(cfg.after_code_frames), len(studio_ids)))
    window = window[np.isfinite(schedule[window])]
    ego_row = {int(e): i for i, e in enumerate(ego_ids)}
    scores = {}
    for k in range(int(ego_ids.min()) - int(studio_ids.max()), int(ego_ids.max()) - int(studio_ids.min()) + 1):
        if not all(int(studio_ids[r]) + k in ego_row for r in code_rows):
            continue  # the whole code must lie inside the ego stream
        rows = [r for r in window if int(studio_ids[r]) + k in ego_row]
        ego = np.array([brightness[ego_row[int(studio_ids[r]) + k]] for r in rows])
        scores[k] = _correlation(schedule[rows], ego)
    if not scores:
        raise EgorelightError(f"sequence {seq.name!r}: the ego stream cannot contain the flash code at any offset "
                              f"({len(ego_ids)} ego frames, code at studio frames {start}..{start + len(code) - 1})",
                              seq.root / "sequence.json")
    ranked = sorted(scores.items(), key=lambda kv: -kv[1])
    best, score = ranked[0]
    runner = ranked[1][1] if len(ranked) > 1 else -1.0
    if score < float(cfg.min_correlation) or score - runner < float(cfg.min_margin):
        raise EgorelightError(f"sequence {seq.name!r}: the flash code is not found in the ego images (best "
                              f"correlation {score:.2f} at offset {best}, runner-up {runner:.2f})",
                              seq.root / "ego")
    return SyncResult(int(best), float(score), float(runner), brightness, schedule)
