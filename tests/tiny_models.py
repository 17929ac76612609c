"""Shared setup of the appearance stages' tests: the CLI in-process and tiny geolift uvmaps."""

from __future__ import annotations

from pathlib import Path


def cli_exit_code(*args) -> int:
    """Run ``egorelight ARGS`` in-process (as the console script does); returns its exit code."""
    from egorelight_cli.cli import main

    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def tiny_geolift_uvmaps(root: Path, capture: Path, skinned_meshes: Path, sequences) -> Path:
    """Train a tiny geolift model on ``relight_train`` into ``root/geolift`` and write
    ``root/uvmaps_<seq>`` (with the lighting features) for each of ``sequences``; returns ``root``."""
    assert cli_exit_code("--preset", "tiny", "-q", "train", "geolift", "--capture", capture, "--meshes",
                         skinned_meshes / "relight_train.npz", "--out", root / "geolift") == 0
    for seq in sequences:
        assert cli_exit_code("--preset", "tiny", "-q", "geolift", "--meshes", skinned_meshes / f"{seq}.npz", "--model",
                             root / "geolift", "--capture", capture, "--seq", seq, "--out", root / f"uvmaps_{seq}") == 0
    return root


def assert_shards_merge_into(whole: Path, parts: list[Path], merged: Path) -> dict:
    """``egorelight merge PARTS --out MERGED`` (given in reverse order) writes ``whole``'s payloads
    byte for byte, its metrics and its cache key; returns the merged manifest."""
    import json

    assert cli_exit_code("merge", *reversed(parts), "--out", merged) == 0

    def manifest(path: Path) -> dict:
        return json.loads((path / "manifest.json").read_text())

    def payloads(path: Path) -> dict[str, str]:
        return {o["path"]: o["digest"] for o in manifest(path)["outputs"]}

    shards = [manifest(p)["shard"] for p in parts]
    assert sum(s["stop"] - s["start"] for s in shards) == shards[0]["sequence_frames"]
    assert payloads(merged) == payloads(whole)
    assert manifest(merged)["metrics"] == manifest(whole)["metrics"]
    assert manifest(merged)["cache_key"] == manifest(whole)["cache_key"]
    assert "shard" not in manifest(merged) and len(manifest(merged)["parts"]) == len(parts)
    return manifest(merged)


def assert_resumes_to_the_same_model(args: list, out: Path, whole: Path, monkeypatch, module, function: str,
                                     fail_at_call: int, resumed_from_call: int) -> None:
    """``egorelight ARGS --out OUT`` interrupted (Ctrl-C) inside the ``fail_at_call``-th call of
    ``module.function``, then run again with ``--resume``, ends with the weights of the uninterrupted
    ``egorelight ARGS --out WHOLE`` and skips the calls its checkpoint holds (the first
    ``resumed_from_call``: a run that started over would redo them, with the same weights, training
    being seeded); the interrupted run leaves no output but its checkpoint, and the resumed run
    removes the checkpoint. The resumed run checkpoints every step (how often is no part of the cache
    key), and so does a run over WHOLE, which finds it up to date, as ``ARGS`` does once WHOLE's
    manifest is rewritten as a model from before that (:func:`record_as_before_unkeyed`). ``ARGS``
    ends with the command (``train <stage> ...``)."""
    import torch

    from egorelight_cli.io.model import read_model
    from egorelight_cli.nn.training import checkpoint_beside

    original, calls = getattr(module, function), {"n": 0, "fail_at": None}

    def counted(*a, **k):
        calls["n"] += 1
        if calls["n"] == calls["fail_at"]:
            raise KeyboardInterrupt
        return original(*a, **k)

    monkeypatch.setattr(module, function, counted)
    assert cli_exit_code(*args, "--out", whole) == 0
    whole_calls = calls["n"]
    calls.update(n=0, fail_at=fail_at_call)
    assert cli_exit_code(*args, "--out", out) == 130
    assert not out.exists() and checkpoint_beside(out).is_file()
    calls.update(n=0, fail_at=None)
    command = args.index("train")
    every_step = [*args[:command], "--set", "train.checkpoint_every=1", *args[command:]]
    assert cli_exit_code(*every_step, "--resume", "--out", out) == 0
    assert calls["n"] == whole_calls - resumed_from_call, (calls["n"], whole_calls)
    assert not checkpoint_beside(out).exists()
    calls.update(n=0)
    assert cli_exit_code(*every_step, "--out", whole) == 0 and calls["n"] == 0  # up to date
    record_as_before_unkeyed(whole)  # a model from before: up to date under the value it recorded
    assert cli_exit_code(*args, "--out", whole) == 0 and calls["n"] == 0
    expected, resumed = read_model(whole).state_dict, read_model(out).state_dict
    assert expected.keys() == resumed.keys()
    for key, value in expected.items():
        torch.testing.assert_close(resumed[key], value, msg=key)


def record_as_before_unkeyed(out: Path) -> None:
    """Rewrite the manifest of ``out`` as a run from before ``pipeline.UNKEYED_NAMES`` wrote it:
    those keys in its config, and in its cache key."""
    import json

    from egorelight_cli.artifacts import cache_key, manifest_path_for

    path, _ = manifest_path_for(out)
    manifest = json.loads(path.read_text())
    config = manifest["config"]
    for dotted, value in manifest["runtime"].pop("unkeyed_config").items():
        *parents, name = dotted.split(".")
        node = config
        for parent in parents:
            node = node.setdefault(parent, {})
        node[name] = value
    digests = [entry["digest"] for entry in manifest.get("inputs", []) + manifest.get("sources", [])]
    manifest["cache_key"] = cache_key(manifest["stage"], manifest["stage_version"], config, digests)
    path.write_text(json.dumps(manifest, indent=2))
