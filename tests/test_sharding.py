"""Frame shards of per-frame stages (``--frames`` / ``--shard``) and ``egorelight merge``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.sharding import FrameRange, evenly_spaced
from tiny_models import assert_shards_merge_into, cli_exit_code


def test_evenly_spaced_subsets_keep_the_ends_and_the_order():
    assert evenly_spaced(list("abcdefghi"), 3) == ["a", "e", "i"]
    np.testing.assert_array_equal(evenly_spaced(np.arange(10, 20), 4), [10, 13, 16, 19])
    assert evenly_spaced([1, 2], 5) == [1, 2] and evenly_spaced([1, 2, 3], 0) == [1, 2, 3]


def test_frame_ranges_cover_a_sequence_once():
    for total in (1, 7, 11):
        for count in range(1, total + 1):
            spans = [FrameRange.parse(shard=f"{i}/{count}").bounds(total) for i in range(count)]
            assert spans[0][0] == 0 and spans[-1][1] == total
            assert all(a[1] == b[0] for a, b in zip(spans, spans[1:]))
            assert all(stop > start for start, stop in spans)
    assert FrameRange.parse(frames="2:5").bounds(11) == (2, 5)
    assert FrameRange.parse(frames=":4").bounds(11) == (0, 4)
    assert FrameRange.parse(frames="-3:").bounds(11) == (8, 11)
    assert FrameRange.parse().whole and FrameRange.parse().key() == {}
    assert FrameRange.parse(shard="1/4").key() == {"shard": "1/4"}


@pytest.mark.parametrize("frames, shard, message", [
    ("2-5", None, "not A:B"), (None, "4/4", "0 <= I < N"), (None, "a/b", "not I/N"), ("1:2", "0/2", "not both")])
def test_bad_frame_ranges_are_errors(frames, shard, message):
    with pytest.raises(EgorelightError, match=message):
        FrameRange.parse(frames, shard)
    with pytest.raises(EgorelightError, match="holds none"):
        FrameRange.parse(frames="5:5").bounds(11)


@pytest.fixture(scope="module")
def egopose_runs(tiny_capture, oracle_calibration_artifact, tmp_path_factory):
    """A tiny egopose model, its whole run on ``test`` and the same run as 2 and 4 shards."""
    root = tmp_path_factory.mktemp("sharding")
    common = ["--preset", "tiny", "-q", "--capture", tiny_capture, "--calibration", oracle_calibration_artifact]
    assert cli_exit_code("train", "egopose", *common, "--out", root / "model") == 0
    run = [*common, "--model", root / "model", "--seq", "test"]
    assert cli_exit_code("egopose", *run, "--out", root / "whole") == 0
    for count in (2, 4):
        for i in range(count):
            assert cli_exit_code("egopose", *run, "--shard", f"{i}/{count}", "--out", root / f"part{i}of{count}") == 0
    return root, run


@pytest.mark.parametrize("count", [2, 4])
def test_merged_egopose_shards_equal_the_single_run(egopose_runs, count):
    root, run = egopose_runs
    merged = assert_shards_merge_into(root / "whole", [root / f"part{i}of{count}" for i in range(count)],
                                      root / f"merged{count}")
    # the single run finds the merged artifact up to date: nothing is recomputed
    assert cli_exit_code("egopose", *run, "--out", root / f"merged{count}") == 0
    assert json.loads((root / f"merged{count}" / "manifest.json").read_text()) == merged


def test_merge_refuses_incomplete_overlapping_or_mismatched_parts(egopose_runs, tmp_path, capsys):
    root, _ = egopose_runs
    cases = {
        "a shard is missing": [root / "part0of4", root / "part1of4", root / "part2of4"],
        "overlap": [root / "part0of2", root / "part0of4", root / "part1of4", root / "part1of2"],
        "not a frame shard": [root / "whole"],
    }
    # a shard made from another lone input file (its digest in the manifest's sources)
    import shutil

    other = tmp_path / "part1of2_other"
    shutil.copytree(root / "part1of2", other)
    manifest = json.loads((other / "manifest.json").read_text())
    manifest["sources"] = [{"path": "weights.safetensors", "digest": "sha256:" + "0" * 64}]
    (other / "manifest.json").write_text(json.dumps(manifest))
    cases["different input files"] = [root / "part0of2", other]
    for i, (message, parts) in enumerate(cases.items()):
        capsys.readouterr()
        assert cli_exit_code("merge", *parts, "--out", tmp_path / f"m{i}") == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
        assert not (tmp_path / f"m{i}").exists()
