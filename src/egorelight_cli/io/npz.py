"""NumPy ``.npz`` payloads that describe themselves.

Every npz the tool writes carries a ``__meta__`` entry: a JSON string with at least ``kind``
and ``version`` (and usually ``units`` and ``frame_ids``), so a lone file found on disk can be
identified by ``egorelight inspect``. Arrays are validated for NaN/inf on request.
"""

from __future__ import annotations

import io
import json
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError

META_KEY = "__meta__"
# what numpy/zipfile raise on a truncated or bit-flipped npz: corrupt deflate data (zlib.error), an
# unknown zip version or compression method (NotImplementedError), a garbled .npy header (the
# tokenizer and literal_eval errors), an absurd shape (MemoryError, OverflowError)
CORRUPT_NPZ_ERRORS = (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError, NotImplementedError,
                      SyntaxError, tokenize.TokenError, MemoryError, OverflowError)


def require_arrays(arrays: dict[str, np.ndarray], names, what: str, path: str | Path | None = None) -> None:
    """Raise ``"<what> lacks a, b", path`` unless every array of ``names`` is in ``arrays``."""
    missing = [n for n in names if n not in arrays]
    if missing:
        raise EgorelightError(f"{what} lacks {', '.join(missing)}", path)


def checked_fps(fps, what: str, path: str | Path | None = None) -> float | None:
    """A payload's frame rate (from its metadata or its ``fps`` array) as a float: one positive
    finite number; None stays None."""
    if fps is None:
        return None
    value = np.asarray(fps).reshape(-1)[0] if np.size(fps) == 1 else None
    if value is None or not np.issubdtype(np.asarray(value).dtype, np.number):
        raise EgorelightError(f"{what}'s fps must be one number, got shape {np.shape(fps)} of "
                              f"{np.asarray(fps).dtype}", path)
    if isinstance(value, (bool, np.bool_)) or not np.isfinite(value) or value <= 0:
        raise EgorelightError(f"{what}'s fps must be a positive number, got {fps!r}", path)
    return float(value)


def write_npz(path: str | Path, arrays: dict[str, np.ndarray], meta: dict, compress: bool = True) -> None:
    """Write arrays plus a JSON ``__meta__`` entry to ``path``.

    Args:
        path: output file (written as given; atomicity is the caller's, see ``artifacts``).
        arrays: name -> array. Names must not start with ``__``.
        meta: JSON-able dict; must hold ``kind`` and ``version``.
    """
    for key in ("kind", "version"):
        if key not in meta:
            raise EgorelightError(f"npz metadata lacks {key!r}", path)
    for name in arrays:
        if name.startswith("__"):
            raise EgorelightError(f"array name {name!r} is reserved", path)
    payload = {name: np.asarray(a) for name, a in arrays.items()}
    payload[META_KEY] = np.array(json.dumps(meta, sort_keys=True))
    write_npz_deterministic(path, payload, compress)


def write_npz_deterministic(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """``np.savez`` with sorted entries and fixed zip timestamps: equal arrays give equal bytes,
    so digests (and cache keys built from them) depend on content only."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=method, allowZip64=True) as archive:
        for name in sorted(arrays):
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info.external_attr = 0o644 << 16
            archive.writestr(info, buffer.getvalue(), compresslevel=6 if compress else None)


def read_npz(path: str | Path, check_finite: bool = True, allow_inf: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], dict]:
    """Read an npz written by :func:`write_npz`: (arrays, meta).

    Raises EgorelightError for a missing or corrupt file, a missing ``__meta__`` entry, or (with
    ``check_finite``) any NaN/inf in a floating array, naming the array. Arrays named in
    ``allow_inf`` may hold +-inf (e.g. "no limit") but never NaN.
    """
    path = Path(path)
    if not path.is_file():
        raise EgorelightError("file not found", path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except CORRUPT_NPZ_ERRORS as exc:
        raise EgorelightError(f"corrupt npz ({type(exc).__name__}: {exc})", path) from None
    if META_KEY not in arrays:
        raise EgorelightError("npz has no __meta__ entry (not written by egorelight)", path)
    meta = parse_meta(arrays.pop(META_KEY), path)
    if check_finite:
        check_arrays_finite(arrays, path, allow_inf)
    return arrays, meta


def read_kind_npz(path: str | Path, kind: str, version: int, check_finite: bool = False,
                  allow_inf: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], dict]:
    """:func:`~egorelight_cli.io.npz.read_npz` with the payload's kind and version checked
    (by default without the finiteness check: callers validate their arrays)."""
    arrays, meta = read_npz(path, check_finite=check_finite, allow_inf=allow_inf)
    if meta.get("kind") != kind:
        raise EgorelightError(f"wrong payload kind: expected {kind}, found {meta.get('kind')}", path)
    if meta.get("version") != version:
        raise EgorelightError(f"{kind} version mismatch: file is version {meta.get('version')}, "
                              f"this tool reads version {version}", path)
    return arrays, meta


def read_npz_meta(path: str | Path) -> dict:
    """Only the ``__meta__`` entry of an npz (cheap: does not load the other arrays)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            if META_KEY not in data.files:
                raise EgorelightError("npz has no __meta__ entry (not written by egorelight)", path)
            entry = data[META_KEY]
    except CORRUPT_NPZ_ERRORS as exc:
        raise EgorelightError(f"corrupt npz ({type(exc).__name__}: {exc})", path) from None
    return parse_meta(entry, path)


def parse_meta(entry: np.ndarray, path: str | Path | None = None) -> dict:
    """The ``__meta__`` entry as a dict: a JSON object in a 0-d string array, else an error."""
    try:
        meta = json.loads(str(entry)) if entry.dtype.kind == "U" and entry.ndim == 0 else None
    except ValueError:
        meta = None
    if not isinstance(meta, dict):
        raise EgorelightError("npz __meta__ entry is not a JSON object", path)
    return meta


def check_arrays_finite(arrays: dict[str, np.ndarray], path: str | Path | None = None,
                        allow_inf: tuple[str, ...] = ()) -> None:
    """Raise EgorelightError naming the first floating array holding NaN or inf (only NaN for
    the arrays named in ``allow_inf``)."""
    for name, array in arrays.items():
        if not np.issubdtype(array.dtype, np.floating):
            continue
        if name in allow_inf:
            if np.isnan(array).any():
                raise EgorelightError(f"array {name!r} holds {int(np.isnan(array).sum())} NaN values", path)
        elif not np.all(np.isfinite(array)):
            bad = int(np.size(array) - np.count_nonzero(np.isfinite(array)))
            raise EgorelightError(f"array {name!r} holds {bad} NaN/inf values", path)
