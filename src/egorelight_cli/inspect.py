"""``egorelight inspect``: say what any artifact or payload file is.

:func:`describe` returns a JSON-able dict for a manifest, an artifact directory, a single-file
artifact, an npz, an EXR or a PNG/JPEG; :func:`format_description` renders it for people.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from egorelight_cli.artifacts import MANIFEST_NAME, manifest_path_for, open_artifact
from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.exr import read_exr
from egorelight_cli.io.images import read_image
from egorelight_cli.io.npz import META_KEY, parse_meta

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_CHAIN_DEPTH = 12


def array_stats(array: np.ndarray) -> dict[str, Any]:
    """shape, dtype, min, max and NaN/inf count of an array (stats only for numbers)."""
    stats: dict[str, Any] = {"shape": list(array.shape), "dtype": str(array.dtype)}
    if array.size and (np.issubdtype(array.dtype, np.number) or array.dtype == bool):
        values = array.astype(np.float64) if array.dtype != np.float64 else array
        finite = np.isfinite(values)
        stats["nonfinite"] = int(values.size - np.count_nonzero(finite))
        if finite.any():
            stats["min"] = float(values[finite].min())
            stats["max"] = float(values[finite].max())
    elif array.size and array.dtype.kind == "U" and array.size <= 4:
        stats["value"] = [str(v)[:80] for v in array.ravel()]
    return stats


def describe_npz(path: Path) -> dict[str, Any]:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except Exception as exc:
        raise EgorelightError(f"corrupt npz ({type(exc).__name__}: {exc})", path) from None
    meta = None
    if META_KEY in arrays:
        try:
            meta = parse_meta(arrays.pop(META_KEY), path)
        except EgorelightError:
            meta = {"error": "__meta__ is not a JSON object"}
    out: dict[str, Any] = {"type": "npz", "path": str(path), "meta": meta,
                           "arrays": {n: array_stats(a) for n, a in arrays.items()}}
    if meta:
        out["kind"], out["version"] = meta.get("kind"), meta.get("version")
    return out


def describe_exr(path: Path) -> dict[str, Any]:
    image = read_exr(path)
    attributes = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in image.attributes.items()}
    attributes = {k: v if isinstance(v, (str, int, float, list, bool, type(None))) else str(v) for k, v in attributes.items()}
    return {"type": "exr", "path": str(path), "attributes": attributes,
            "channels": {n: array_stats(a) for n, a in image.channels.items()}}


def describe_image(path: Path) -> dict[str, Any]:
    image = read_image(path)
    return {"type": "image", "path": str(path), "format": path.suffix.lower().lstrip("."),
            "image": array_stats(image)}


def describe_payload(path: Path) -> dict[str, Any]:
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return describe_npz(path)
    if suffix == ".exr":
        return describe_exr(path)
    if suffix in IMAGE_SUFFIXES:
        return describe_image(path)
    return {"type": "file", "path": str(path), "bytes": path.stat().st_size}


def input_chain(manifest: dict, root: Path, depth: int = 0, seen: set | None = None) -> list[dict[str, Any]]:
    """The inputs an artifact was made from, recursively, with whether each still matches."""
    seen = set() if seen is None else seen
    chain = []
    for entry in manifest.get("inputs", []):
        node: dict[str, Any] = {"kind": entry["kind"], "path": entry["path"], "digest": entry["digest"]}
        if entry.get("param"):
            node["param"] = entry["param"]  # the declared input of the command it was read through
        target = (root / entry["path"]) if not Path(entry["path"]).is_absolute() else Path(entry["path"])
        try:
            parent = open_artifact(target, verify=False)
        except EgorelightError as exc:
            node["status"] = f"unavailable ({exc.message})"
        else:
            node["status"] = "ok" if parent.digest == entry["digest"] else "changed since"
            node["stage"] = parent.manifest.get("stage")
            key = str(parent.manifest_path.resolve())
            if depth < MAX_CHAIN_DEPTH and key not in seen:
                seen.add(key)
                node["inputs"] = input_chain(parent.manifest, parent.root, depth + 1, seen)
        chain.append(node)
    return chain


def describe(path: str | Path) -> dict[str, Any]:
    """Everything ``inspect`` knows about ``path``."""
    path = Path(path)
    if not path.exists():
        raise EgorelightError("path not found", path)
    manifest_path, single = manifest_path_for(path)
    is_artifact = manifest_path.is_file() and (path.is_dir() or path.name in (MANIFEST_NAME,) or single)
    if not is_artifact:
        if path.is_dir():
            raise EgorelightError(f"directory is not an artifact (no {MANIFEST_NAME})", path)
        return describe_payload(path)
    artifact = open_artifact(path, verify=False)
    m = artifact.manifest
    out: dict[str, Any] = {
        "type": "artifact", "path": str(artifact.path), "manifest": str(artifact.manifest_path),
        "kind": m["kind"], "version": m["version"], "stage": m["stage"], "created": m["created"],
        "tool_version": m["tool_version"], "digest": artifact.digest,
        "preset": m.get("config", {}).get("preset"), "config": m.get("config", {}),
        "metrics": m.get("metrics", {}), "timing": m.get("timing", {}), "units": m.get("units", {}),
        "outputs": [{"name": o["name"], **({"arrays": o["arrays"]} if "arrays" in o else {})} for o in m["outputs"]],
        "inputs": input_chain(m, artifact.root),
        "payload_problems": [{"problem": problem, "path": str(p)} for problem, p in artifact.payload_problems()],
    }
    if artifact.single_file:
        out["payload"] = describe_payload(artifact.path)
    return out


def _fmt_stats(stats: dict[str, Any]) -> str:
    text = f"{tuple(stats['shape'])} {stats['dtype']}"
    if "min" in stats:
        text += f"  min {stats['min']:.6g}  max {stats['max']:.6g}"
    if stats.get("nonfinite"):
        text += f"  NaN/inf {stats['nonfinite']}"
    if "value" in stats:
        text += f"  = {', '.join(stats['value'])}"
    return text


def _fmt_chain(chain: list[dict], indent: int) -> list[str]:
    lines = []
    for node in chain:
        stage = f" ({node['stage']})" if node.get("stage") else ""
        via = f" via {node['param']}" if node.get("param") else ""
        lines.append(" " * indent + f"<- {node['kind']}{stage}{via} {node['path']} [{node['status']}]")
        lines += _fmt_chain(node.get("inputs", []), indent + 3)
    return lines


def format_description(info: dict[str, Any]) -> str:
    """Human-readable text for :func:`describe`'s result."""
    kind = info.get("type")
    lines: list[str] = []
    if kind == "artifact":
        lines.append(f"{info['path']}: {info['kind']} v{info['version']} (stage {info['stage']}, {info['created']}, "
                     f"egorelight {info['tool_version']})")
        lines.append(f"  digest {info['digest']}")
        lines.append("  outputs:")
        for out in info["outputs"][:40]:
            lines.append(f"    {out['name']}")
            for name, arr in (out.get("arrays") or {}).items():
                lines.append(f"      {name}: {tuple(arr['shape'])} {arr['dtype']}")
        if len(info["outputs"]) > 40:
            lines.append(f"    ... and {len(info['outputs']) - 40} more")
        problems = info["payload_problems"]
        lines.append(f"  payloads: {len(problems)} of {len(info['outputs'])} missing or modified" if problems
                     else f"  payloads: all {len(info['outputs'])} intact (sha256 matches the manifest)")
        lines += [f"    {p['problem'].upper()}: {p['path']}" for p in problems]
        if info["metrics"]:
            lines.append("  metrics:")
            lines += [f"    {k}: {v}" for k, v in info["metrics"].items()]
        if info["timing"]:
            lines.append("  timing: " + ", ".join(f"{k} {v}" for k, v in info["timing"].items()))
        lines.append("  made from:" if info["inputs"] else "  made from: (no inputs)")
        lines += _fmt_chain(info["inputs"], 4)
        if "payload" in info:
            lines.append(format_description(info["payload"]))
    elif kind == "npz":
        meta = info.get("meta") or {}
        head = f"{meta.get('kind')} v{meta.get('version')}" if meta else "npz without __meta__ (not written by egorelight)"
        lines.append(f"{info['path']}: npz, {head}")
        lines += [f"  {n}: {_fmt_stats(s)}" for n, s in info["arrays"].items()]
    elif kind == "exr":
        lines.append(f"{info['path']}: EXR")
        lines += [f"  {n}: {_fmt_stats(s)}" for n, s in info["channels"].items()]
        lines += [f"  attribute {k} = {v}" for k, v in info["attributes"].items()]
    elif kind == "image":
        lines.append(f"{info['path']}: {info['format'].upper()} image {_fmt_stats(info['image'])}")
    else:
        lines.append(f"{info['path']}: file of {info.get('bytes')} bytes")
    return "\n".join(lines)
