"""`inspect` on every payload type and on artifacts with an input chain."""

from __future__ import annotations

import numpy as np

from egorelight_cli.artifacts import ArtifactWriter, open_artifact
from egorelight_cli.inspect import describe, format_description
from egorelight_cli.io.exr import write_exr_layers
from egorelight_cli.io.images import write_image
from egorelight_cli.io.npz import write_npz


def make_chain(tmp_path):
    with ArtifactWriter(tmp_path / "kp", kind="keypoints", stage="egopose", config={"a": 1}) as w:
        w.save_npz("keypoints.npz", {"xyz": np.zeros((2, 57, 3), np.float32)}, frame_ids=[4, 5])
        w.metrics["mpjpe_cm"] = 3.25
    kp = open_artifact(tmp_path / "kp")
    with ArtifactWriter(tmp_path / "motion.npz", kind="motion", stage="ik", config={}, inputs=[kp]) as w:
        w.save_npz("motion.npz", {"theta": np.ones((2, 9), np.float32)}, frame_ids=[4, 5])
    return tmp_path / "kp", tmp_path / "motion.npz"


def test_artifact_and_chain(tmp_path):
    kp, motion = make_chain(tmp_path)
    info = describe(motion)
    assert info["type"] == "artifact" and info["kind"] == "egorelight/motion"
    (parent,) = info["inputs"]
    assert parent["kind"] == "egorelight/keypoints" and parent["status"] == "ok" and parent["stage"] == "egopose"
    assert info["payload"]["arrays"]["theta"]["shape"] == [2, 9]
    text = format_description(info)
    assert "<- egorelight/keypoints (egopose)" in text and "theta: (2, 9) float32" in text
    # the same through the directory, the manifest file and the sidecar
    assert describe(kp)["metrics"] == {"mpjpe_cm": 3.25}
    assert describe(kp / "manifest.json")["kind"] == "egorelight/keypoints"
    assert describe(tmp_path / "motion.npz.json")["kind"] == "egorelight/motion"
    # a changed input is flagged
    with ArtifactWriter(kp, kind="keypoints", stage="egopose", config={"a": 2}) as w:
        w.save_npz("keypoints.npz", {"xyz": np.ones((2, 57, 3), np.float32)})
    assert describe(motion)["inputs"][0]["status"] == "changed since"


def test_npz_stats_count_nan(tmp_path):
    values = np.arange(6, dtype=np.float32).reshape(2, 3)
    values[0, 0] = np.nan
    write_npz(tmp_path / "a.npz", {"v": values}, {"kind": "egorelight/motion", "version": 1})
    stats = describe(tmp_path / "a.npz")["arrays"]["v"]
    assert stats == {"shape": [2, 3], "dtype": "float32", "nonfinite": 1, "min": 1.0, "max": 5.0}
    np.savez(tmp_path / "plain.npz", x=np.ones(2))
    assert "without __meta__" in format_description(describe(tmp_path / "plain.npz"))


def test_exr_and_png(tmp_path):
    write_exr_layers(tmp_path / "uv.exr", {"normal": np.ones((4, 4, 3)), "albedo": np.zeros((4, 4, 3))},
                     attributes={"frame_id": 3})
    info = describe(tmp_path / "uv.exr")
    assert info["channels"]["normal.X"]["max"] == 1.0 and info["attributes"]["frame_id"] == 3
    write_image(tmp_path / "p.png", np.full((5, 6, 3), 200, np.uint8))
    info = describe(tmp_path / "p.png")
    assert info["image"]["shape"] == [5, 6, 3] and info["image"]["max"] == 200.0
