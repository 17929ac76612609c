"""The headset's own tracker stream (``sequences/<seq>/head_pose.npz``, DESIGN.md Sec. 3).

``T_world_from_hmd`` (M,4,4) in the tracker's own world frame, ``frame_ids`` (M,) (the ego frame
taken with a sample, -1 for samples between frames) and ``timestamps_s`` (M,) (optional when every
sample is an ego frame: then ``id / fps``). :func:`egorelight_cli.stages.calibrate_wild` aligns it
to visual odometry; without a calibration, stages fall back to :func:`tracker_head_poses`.
"""

from __future__ import annotations

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.calibration import HeadPoses
from egorelight_cli.io.capture import SequenceInfo
from egorelight_cli.io.npz import read_npz, require_arrays


def read_tracker(seq: SequenceInfo) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_tracker_from_hmd (M,4,4), frame ids (M,), timestamps (M,) s) of the headset tracker,
    sorted by time. ``frame_ids`` are the ego frame taken with a sample, -1 for samples between
    frames; without ``timestamps_s`` every sample is an ego frame at ``id / fps``."""
    path = seq.head_pose_path()
    if not path.exists():
        raise EgorelightError(f"sequence {seq.name!r} has no headset tracker poses (head_pose.npz)", path)
    arrays, _ = read_npz(path)
    require_arrays(arrays, ("T_world_from_hmd", "frame_ids"), "tracker payload", path)
    T, ids = np.asarray(arrays["T_world_from_hmd"], np.float64), np.asarray(arrays["frame_ids"], np.int64)
    if T.shape != (len(ids), 4, 4):
        raise EgorelightError(f"tracker poses have shape {T.shape} for {len(ids)} frame ids", path)
    if "timestamps_s" in arrays:
        times = np.asarray(arrays["timestamps_s"], np.float64)
        if times.shape != ids.shape:
            raise EgorelightError(f"tracker timestamps have shape {times.shape} for {len(ids)} frame ids", path)
    elif (ids < 0).any():
        raise EgorelightError("tracker samples between ego frames (frame id -1) need timestamps_s", path)
    else:
        times = ids / seq.fps
    if not (np.isfinite(T).all() and np.isfinite(times).all()):
        raise EgorelightError("tracker poses or timestamps contain NaN or infinity", path)
    order = np.argsort(times, kind="stable")
    if np.any(np.diff(times[order]) <= 0):
        raise EgorelightError("tracker timestamps repeat", path)
    return T[order], ids[order], times[order]


def tracker_head_poses(seq: SequenceInfo) -> HeadPoses:
    """The tracker's samples taken with ego frames, as they are (its own world frame, latency
    and drift uncorrected), as head poses by ego frame id."""
    T, ids, _ = read_tracker(seq)
    keep = ids >= 0
    n = int(keep.sum())
    return HeadPoses(T[keep], ids[keep], np.ones(n, bool), np.zeros(n, np.int64), np.full(n, np.nan))
