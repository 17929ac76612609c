"""Self-describing npz payloads."""

from __future__ import annotations

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_npz, read_npz_meta, write_npz


def test_round_trip_with_meta(tmp_path):
    arrays = {"xyz": np.random.default_rng(0).normal(size=(4, 57, 3)).astype(np.float32), "ids": np.arange(4)}
    meta = {"kind": "egorelight/keypoints", "version": 1, "frame_ids": [0, 1, 2, 3], "units": {"xyz": "m"}}
    write_npz(tmp_path / "k.npz", arrays, meta)
    back, back_meta = read_npz(tmp_path / "k.npz")
    assert back_meta == meta
    np.testing.assert_array_equal(back["xyz"], arrays["xyz"])
    assert back["xyz"].dtype == np.float32
    assert read_npz_meta(tmp_path / "k.npz")["kind"] == "egorelight/keypoints"


def test_nan_is_reported_with_array_name(tmp_path):
    bad = np.zeros((3, 3), np.float32)
    bad[1, 1] = np.nan
    write_npz(tmp_path / "n.npz", {"theta": bad}, {"kind": "egorelight/motion", "version": 1})
    with pytest.raises(EgorelightError, match="'theta' holds 1 NaN/inf"):
        read_npz(tmp_path / "n.npz")
    arrays, _ = read_npz(tmp_path / "n.npz", check_finite=False)
    assert np.isnan(arrays["theta"][1, 1])


def test_corrupt_and_foreign_files(tmp_path):
    write_npz(tmp_path / "ok.npz", {"a": np.ones(1000)}, {"kind": "egorelight/motion", "version": 1})
    data = (tmp_path / "ok.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(EgorelightError, match="corrupt npz"):
        read_npz(tmp_path / "cut.npz")
    np.savez(tmp_path / "plain.npz", a=np.ones(3))
    with pytest.raises(EgorelightError, match="no __meta__"):
        read_npz(tmp_path / "plain.npz")
    with pytest.raises(EgorelightError, match="lacks 'version'"):
        write_npz(tmp_path / "x.npz", {}, {"kind": "egorelight/motion"})
