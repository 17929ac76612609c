"""The ``keypoints`` payload: 57 world keypoints per frame with confidences.

``keypoints.npz`` arrays (DESIGN.md Sec. 3):

* ``xyz`` (T,57,3) float32, world metres, +Y up. NaN marks a missing keypoint.
* ``confidence`` (T,57) float32 in [0,1]; 0 means "not observed".
* ``frame_ids`` (T,) int64, strictly increasing.
* ``names`` (57,) str, the layout of :mod:`egorelight_cli.structures.keypoints`.

The ``__meta__`` entry holds kind ``egorelight/keypoints``, version, units and (optionally)
``fps``. A keypoints artifact is a directory with ``manifest.json`` + ``keypoints.npz``, or a
single ``.npz`` with its sidecar ``<file>.npz.json``; a lone ``.npz`` whose ``__meta__`` says
``egorelight/keypoints`` is read too (e.g. written by a script).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_kind_npz, require_arrays, resolve_payload, write_npz
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES, NUM_KEYPOINTS

KEYPOINTS_KIND = "egorelight/keypoints"
KEYPOINTS_VERSION = 1
KEYPOINTS_PAYLOAD = "keypoints.npz"
KEYPOINTS_UNITS = {"xyz": "m", "confidence": "1"}


@dataclass(frozen=True, eq=False)
class Keypoints:
    """A keypoint sequence (see the module docstring for the arrays).

    Construction validates shapes and values: ``xyz`` must be (T,K,3) with K = len(names),
    ``confidence`` (T,K) finite in [0,1], ``frame_ids`` (T,) strictly increasing. Entries whose
    ``xyz`` is not finite get confidence 0 (and xyz NaN), so consumers only need ``confidence``.
    """

    xyz: np.ndarray
    confidence: np.ndarray
    frame_ids: np.ndarray
    names: tuple[str, ...] = KEYPOINT_NAMES
    fps: float | None = None

    def __post_init__(self) -> None:
        xyz = np.array(self.xyz, dtype=np.float32)
        conf = np.array(self.confidence, dtype=np.float32)
        ids = np.asarray(self.frame_ids)
        names = tuple(str(n) for n in self.names)
        K = len(names)
        if xyz.ndim != 3 or xyz.shape[1:] != (K, 3):
            raise EgorelightError(f"keypoints xyz has shape {xyz.shape}, expected (T, {K}, 3)")
        T = xyz.shape[0]
        if conf.shape != (T, K):
            raise EgorelightError(f"keypoints confidence has shape {conf.shape}, expected ({T}, {K})")
        if ids.shape != (T,) or not np.issubdtype(ids.dtype, np.integer):
            raise EgorelightError(f"keypoints frame_ids has shape {ids.shape} and dtype {ids.dtype}, expected ({T},) integers")
        ids = ids.astype(np.int64)
        if T > 1 and np.any(np.diff(ids) <= 0):
            raise EgorelightError("keypoints frame_ids are not strictly increasing")
        if np.isnan(conf).any():
            raise EgorelightError(f"keypoints confidence holds {int(np.isnan(conf).sum())} NaN values")
        if conf.size and (conf.min() < 0 or conf.max() > 1):
            raise EgorelightError(f"keypoints confidence outside [0, 1] (range {conf.min():.3g}..{conf.max():.3g})")
        missing = ~np.isfinite(xyz).all(axis=-1)
        if missing.any():
            xyz[missing] = np.nan
            conf[missing] = 0.0
        if self.fps is not None and not (np.isfinite(self.fps) and self.fps > 0):
            raise EgorelightError(f"keypoints fps must be positive, got {self.fps}")
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "frame_ids", ids)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "fps", None if self.fps is None else float(self.fps))

    @property
    def num_frames(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def has_standard_layout(self) -> bool:
        return self.names == KEYPOINT_NAMES

    def require_standard_layout(self, path: str | Path | None = None) -> "Keypoints":
        """Raise unless the names are the 57-keypoint layout (in order)."""
        if len(self.names) != NUM_KEYPOINTS:
            raise EgorelightError(f"keypoints have {len(self.names)} keypoints, expected {NUM_KEYPOINTS}", path)
        if not self.has_standard_layout:
            bad = next(i for i, (a, b) in enumerate(zip(self.names, KEYPOINT_NAMES)) if a != b)
            raise EgorelightError(f"keypoint {bad} is named {self.names[bad]!r}, expected {KEYPOINT_NAMES[bad]!r}", path)
        return self

    def select(self, rows) -> "Keypoints":
        """The frames at positions ``rows`` (slice, index array or boolean mask)."""
        return Keypoints(self.xyz[rows], self.confidence[rows], self.frame_ids[rows], self.names, self.fps)

    def arrays(self) -> dict[str, np.ndarray]:
        """The payload arrays (float32 xyz/confidence, int64 frame ids, str names)."""
        return {"xyz": self.xyz, "confidence": self.confidence, "frame_ids": self.frame_ids,
                "names": np.array(self.names, dtype=str)}

    def meta(self) -> dict:
        """``__meta__`` extras: units and, when known, fps."""
        meta: dict = {"units": dict(KEYPOINTS_UNITS)}
        if self.fps is not None:
            meta["fps"] = self.fps
        return meta


def keypoints_from_arrays(arrays: dict[str, np.ndarray], meta: dict | None = None,
                          path: str | Path | None = None) -> Keypoints:
    """Build :class:`Keypoints` from payload arrays (errors name ``path``)."""
    require_arrays(arrays, ("xyz", "confidence", "frame_ids"), "keypoints payload", path)
    names = tuple(str(s) for s in arrays["names"]) if "names" in arrays else KEYPOINT_NAMES
    fps = (meta or {}).get("fps")
    if fps is None and "fps" in arrays:
        fps = float(arrays["fps"])
    try:
        return Keypoints(arrays["xyz"], arrays["confidence"], arrays["frame_ids"], names, fps)
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None


def write_keypoints_npz(path: str | Path, keypoints: Keypoints, **meta) -> None:
    """Write a self-describing ``keypoints.npz`` (outside an artifact writer)."""
    write_npz(path, keypoints.arrays(), {"kind": KEYPOINTS_KIND, "version": KEYPOINTS_VERSION,
                                         "frame_ids": keypoints.frame_ids.tolist(), **keypoints.meta(), **meta})


def save_keypoints(writer, keypoints: Keypoints, name: str | None = None, **meta) -> Path:
    """Write ``keypoints`` into an :class:`~egorelight_cli.artifacts.ArtifactWriter` (kind keypoints)."""
    name = name or (writer.out.name if writer.single_file else KEYPOINTS_PAYLOAD)
    extra = keypoints.meta()
    return writer.save_npz(name, keypoints.arrays(), frame_ids=keypoints.frame_ids, units=extra.pop("units"),
                           **extra, **meta)


def read_keypoints_npz(path: str | Path) -> Keypoints:
    """Read a keypoints ``.npz`` (kind and version checked; NaN xyz allowed = missing)."""
    arrays, meta = read_kind_npz(path, KEYPOINTS_KIND, KEYPOINTS_VERSION)
    return keypoints_from_arrays(arrays, meta, path)


def load_keypoints(path: str | Path):
    """Load keypoints from an artifact directory, a single ``.npz`` (+ sidecar) or a lone
    self-describing ``.npz``. Returns ``(Keypoints, Artifact | None)``."""
    payload, artifact = resolve_payload(path, "keypoints", KEYPOINTS_PAYLOAD, "keypoints")
    return read_keypoints_npz(payload), artifact
