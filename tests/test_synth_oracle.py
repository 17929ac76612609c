"""The oracle renderer reproduces the simulated capture and renders any lighting."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.exr import read_exr
from egorelight_cli.synth.oracle import Oracle


@pytest.fixture(scope="module")
def oracle(tiny_capture):
    return Oracle(tiny_capture)


def _sequence(root, seq="test"):
    return json.loads((root / "sequences" / seq / "sequence.json").read_text())


def _captured(root, seq, cam, fid):
    return read_exr(root / "sequences" / seq / "studio" / cam / f"{fid:06d}.exr").layer("")


def test_oracle_reproduces_the_captured_test_images(oracle, tiny_capture):
    """Within the capture's own noise: its half-float storage (relative 2^-11) and nothing else."""
    seq = _sequence(tiny_capture)
    patterns = set()
    for fid in seq["content_frame_ids"]:
        patterns.add(seq["lights"][fid]["pattern"])
        for cam in seq["streams"]["studio"]:
            rendered = oracle.render("test", fid, cam)
            captured = _captured(tiny_capture, "test", cam, fid)
            error = np.abs(rendered.radiance - captured)
            # every pixel but the odd shadow-ray edge case (Embree float order) within half-float rounding
            assert np.mean(error <= 4e-3 * np.abs(captured) + 2e-3 * captured.max()) > 0.9999
            assert error.max() < 0.05 * captured.max() and error.mean() < 1e-3 * captured.mean()
            mask = cv2.imread(str(tiny_capture / "sequences" / "test" / "masks" / cam / f"{fid:06d}.png"), 0) > 0
            np.testing.assert_array_equal(rendered.mask, mask)
            np.testing.assert_allclose((rendered.diffuse + rendered.specular)[rendered.mask],
                                       rendered.radiance[rendered.mask], rtol=1e-5, atol=1e-7)
    assert {"envmap", "olat", "group"} <= patterns  # the OLAT/group tail is there


def test_oracle_olat_matches_the_olat_tail(oracle, tiny_capture):
    seq = _sequence(tiny_capture)
    (fid, entry), = [(i, e) for i, e in enumerate(seq["lights"]) if e["pattern"] == "olat"]
    cam = seq["streams"]["studio"][0]
    one_light = oracle.render("test", fid, cam, lighting=int(entry["olat_index"]))
    captured = _captured(tiny_capture, "test", cam, fid)
    np.testing.assert_allclose(one_light.radiance * entry["scale"], captured, rtol=4e-3, atol=2e-3 * captured.max())
    # another light gives another image: the tail really is one light at a time
    other = oracle.render("test", fid, cam, lighting=(int(entry["olat_index"]) + 7) % oracle.lightstage.num_lights)
    assert np.abs(other.radiance * entry["scale"] - captured).mean() > 0.1 * captured.mean()


def test_oracle_renders_virtual_cameras_without_the_headset_and_under_the_wild_light(oracle, tiny_capture):
    seq = _sequence(tiny_capture)
    fid = seq["content_frame_ids"][0]
    cam = oracle.studio_camera(seq["streams"]["studio"][0])
    with_hmd = oracle.render("test", fid, cam)
    without = oracle.render("test", fid, cam, hmd=False)
    assert without.mask.sum() < with_hmd.mask.sum()
    np.testing.assert_array_equal(without.mask, without.body_mask)
    dome = oracle.dome()
    wild = oracle.render("test", fid, cam, lighting=(oracle.envmap(_wild_name(tiny_capture)), 30.0), lights=dome,
                         hmd=False)
    assert wild.radiance[wild.mask].mean() > 0
    with pytest.raises(EgorelightError, match="no frame"):
        oracle.render("test", 10_000, cam)


def _wild_name(root) -> str:
    return json.loads((root / "groundtruth" / "wild" / "surroundings.json").read_text())["envmap"]
