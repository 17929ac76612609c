"""DDC (Skeletool) character files: readers, writers, the Character conversion, round trips."""

from __future__ import annotations

import functools
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io import ddc
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES
from egorelight_cli.structures.skeleton import PRISMATIC

FILES = ("ddc.skeleton", "ddc.skin", "ddc.motion", "ddc.obj", "ddc_graph.obj", "segmentation.txt",
         "hand_segmentation.txt")


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def _token_stream(path: Path, skin_run_together: bool = False) -> list[str]:
    """All tokens of the non-comment lines. For the original ``.skin``, strip the vertex-id suffix
    glued to every weight but the last of a row (written independently of the reader)."""
    out: list[str] = []
    text = path.read_bytes().decode()
    section = None
    for line in text.replace("\r\n", "\n").split("\n"):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if tokens == ["vertex", "weights:"]:
            section = "weights"
        elif skin_run_together and section == "weights":
            vid = tokens[0]
            fixed = [vid]
            for i, tok in enumerate(tokens[1:]):
                is_weight, is_last = i % 2 == 1, i == len(tokens) - 2
                if is_weight and not is_last:
                    assert tok.endswith(vid), (line, tok)
                    tok = tok[: -len(vid)]
                fixed.append(tok)
            tokens = fixed
        out.extend(tokens)
    return out


def _number(tok: str) -> float | None:
    try:
        return float(tok)
    except ValueError:
        return None


def _assert_same_tokens(original: Path, written: Path, skin_run_together: bool = False) -> None:
    a = _token_stream(original, skin_run_together)
    b = _token_stream(written)
    assert len(a) == len(b), f"{written.name}: {len(a)} tokens in the original, {len(b)} written"
    bad = []
    for i, (x, y) in enumerate(zip(a, b)):
        fx, fy = _number(x), _number(y)
        if fx is not None and fy is not None:
            ok = math.isclose(fx, fy, rel_tol=1e-6, abs_tol=1e-12)
        else:
            ok = x == y
        if not ok:
            bad.append((i, x, y))
    assert not bad, f"{written.name}: {len(bad)} tokens differ, first {bad[:5]}"


def _assert_ddc_text(path: Path) -> None:
    data = path.read_bytes()
    assert data.endswith(b"\r\n"), path.name
    assert b"\n" not in data.replace(b"\r\n", b""), f"{path.name} has a bare LF"
    assert b"\r" not in data.replace(b"\r\n", b""), f"{path.name} has a bare CR"
    for line in data.decode().split("\r\n")[:-1]:
        assert "  " not in line and "\t" not in line, f"{path.name}: {line!r}"
        assert line == line.strip(), f"{path.name}: {line!r}"


def _to_lf(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes().replace(b"\r\n", b"\n"))
    return dst


@functools.lru_cache(maxsize=2)
def _imported(path: str) -> Character:
    return ddc.read_ddc_character(path)


def _character(ddc_example: Path) -> Character:
    return _imported(str(ddc_example / "ddc.character"))


SMALL_SKELETON = """Skeletool Skeleton Definition V1.0
joints: 5
  Root_tx     prismatic none      0 100 0   1 0 0   1.0
  Root_ry     revolute  Root_tx   0 0 0     0 2 0   1.0
  Hand1_tz    prismatic Root_ry   10 0 0    0 0 1   1.0
  Hand1       revolute  Hand1_tz  0 0 0     0 0 -1  1.0
  Arm_rx      revolute  Root_ry   0 50 0    1 0 0   1.0
markers: 1
  M1  Hand1  point  1 2 3  10  0 1 0
scaling joints: 1
  grp 2
      Hand1
      Arm_rx
dofs: 5
  translate_x 1
      nolimits
      Root_tx 1000
  rotate_y 1
      limits -1.5 1.5
      Root_ry 3
  flex 1
      limits -1.57 0.3
      Hand1 3
  arm 1
      nolimits
      Arm 1
  knuckles 2
      nolimits
      Hand1_tz 200
      Hand1 0
"""


# ---------------------------------------------------------------------------------------------
# file-level readers on the real example
# ---------------------------------------------------------------------------------------------


def test_example_counts(ddc_example):
    sf = ddc.read_skeleton(ddc_example / "ddc.skeleton")
    assert (len(sf.joints), len(sf.dofs), len(sf.markers)) == (173, 107, 97)
    assert sf.scaling_joints == [] and sf.texture_entries == []
    skin = ddc.read_skin(ddc_example / "ddc.skin", num_vertices=5514)
    assert (len(skin.bones), skin.num_vertices) == (69, 5514)
    mesh = ddc.read_obj(ddc_example / "ddc.obj")
    assert mesh.vertices.shape == (5514, 3) and mesh.faces.shape == (11024, 3)
    assert mesh.uvs.shape == (5964, 2) and mesh.colors.shape == (5514, 3) and mesh.normals.shape == (5514, 3)
    assert mesh.face_corner_uvs().shape == (11024, 3, 2)
    graph = ddc.read_obj(ddc_example / "ddc_graph.obj")
    assert graph.vertices.shape == (852, 3)
    motion = ddc.read_motion(ddc_example / "ddc.motion", num_dofs=107)
    assert motion.values.shape == (1, 107) and motion.frame_ids.tolist() == [0]
    assert ddc.read_labels(ddc_example / "segmentation.txt", 5514).shape == (5514,)
    hand = ddc.read_labels(ddc_example / "hand_segmentation.txt", 5514)
    assert set(np.unique(hand).tolist()) == {0, 1, 2}
    cf = ddc.read_character_file(ddc_example / "ddc.character")
    assert (cf.skeleton, cf.mesh, cf.skin, cf.pose) == ("ddc.skeleton", "ddc.obj", "ddc.skin", "ddc.motion")


def test_skin_run_together_rows(ddc_example):
    skin = ddc.read_skin(ddc_example / "ddc.skin")
    W = skin.dense()
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-5)
    assert (W > 0).sum(axis=1).max() <= 6
    assert all(len(row) <= 6 for row in skin.influences)
    # row 9: "9 61 0.4978839 60 0.4805529 62 0.02143319 59 0.0001316729 64 2.88857e-079 5 1.07143e-07"
    row = dict(skin.influences[9])
    assert row[61] == pytest.approx(0.497883, abs=1e-12)
    assert row[59] == pytest.approx(0.000131672, abs=1e-15)
    assert row[64] == pytest.approx(2.88857e-07, rel=1e-9)  # exponent weight, suffix '9' stripped
    assert row[5] == pytest.approx(1.07143e-07, rel=1e-9)  # last weight carries no suffix
    # largest influence first
    assert all(row_[0][1] == max(w for _, w in row_) for row_ in skin.influences)


def test_skin_clean_rows_are_not_stripped(tmp_path):
    # in a clean file, a weight that happens to end with the vertex id ('0.21' on vertex 1) is kept
    text = "Skeletool character skinning file V1.0\nbones:\n a b\nvertex weights:\n0 0 1\n1 0 0.21 1 0.79\n"
    (tmp_path / "a.skin").write_text(text)
    skin = ddc.read_skin(tmp_path / "a.skin")
    assert skin.influences == [[(0, 1.0)], [(0, 0.21), (1, 0.79)]]


def test_skin_writer_rows_are_clean(tmp_path, ddc_example):
    skin = ddc.read_skin(ddc_example / "ddc.skin")
    out = ddc.write_skin(skin, tmp_path / "x.skin")
    _assert_ddc_text(out)
    again = ddc.read_skin(out)
    assert again.influences == skin.influences
    row9 = out.read_bytes().decode().split("\r\n")[4 + 9]
    assert row9.split()[:3] == ["9", "61", "0.497883"]


def test_dof_binding_exact_wins_over_prefix(ddc_example):
    sf = ddc.read_skeleton(ddc_example / "ddc.skeleton")
    skeleton, _ = ddc.skeleton_from_file(sf)
    names = skeleton.joint_names
    for side in ("left", "right"):
        for finger in ("index", "middle", "ring", "pinky"):
            joint = f"{side.capitalize()}Hand{finger.capitalize()}1"
            row = skeleton.dof_joint_weights[skeleton.dof_index(f"{side}_{finger}_flex1")]
            assert np.nonzero(row)[0].tolist() == [names.index(joint)]
            assert row[names.index(joint + "_tz")] == 0  # the C++ prefix match would pick this one
            assert row[names.index(joint)] == 3.0
    assert ddc.resolve_joint_reference("LeftHandIndex1", names) == names.index("LeftHandIndex1")


def test_dof_binding_prefix_fallback_and_units(tmp_path):
    (tmp_path / "s.skeleton").write_text(SMALL_SKELETON)
    sf = ddc.read_skeleton(tmp_path / "s.skeleton")
    skeleton, dof_joints = ddc.skeleton_from_file(sf)
    W = skeleton.dof_joint_weights
    j = skeleton.joint_index
    assert W[skeleton.dof_index("flex"), j("Hand1")] == 3.0 and W[skeleton.dof_index("flex"), j("Hand1_tz")] == 0
    assert W[skeleton.dof_index("arm"), j("Arm_rx")] == 1.0  # 'Arm' matches no joint exactly: prefix
    assert W[skeleton.dof_index("translate_x"), j("Root_tx")] == 1.0  # 1000 mm per metre -> 1
    assert W[skeleton.dof_index("knuckles"), j("Hand1_tz")] == pytest.approx(0.2)  # prismatic / 1000
    assert dof_joints[skeleton.dof_index("knuckles")] == ["Hand1_tz", "Hand1"]
    np.testing.assert_allclose(skeleton.offsets[j("Root_tx")], [0, 0.1, 0])
    np.testing.assert_allclose(skeleton.axes[j("Root_ry")], [0, 1, 0])  # revolute axes normalised
    assert skeleton.parents.tolist() == [-1, 0, 1, 2, 1]
    assert skeleton.joint_types[j("Hand1_tz")] == PRISMATIC
    assert np.isinf(skeleton.dof_limits[0]).all()
    np.testing.assert_allclose(skeleton.dof_limits[skeleton.dof_index("rotate_y")], [-1.5, 1.5])
    # back to file contents: weights in mm again, zero-weight entries kept in order, the prefix
    # reference written as the joint's full name
    back = ddc.skeleton_file_from_skeleton(skeleton, sf.markers, sf.scaling_joints, sf.texture_entries, dof_joints)
    by_name = {d.name: d for d in back.dofs}
    assert by_name["knuckles"].joints == [("Hand1_tz", 200.0), ("Hand1", 0.0)]
    assert by_name["arm"].joints == [("Arm_rx", 1.0)]
    assert by_name["translate_x"].joints == [("Root_tx", 1000.0)] and by_name["translate_x"].limits is None
    assert back.joints[0].parent == "none" and back.joints[0].offset == (0.0, 100.0, 0.0)
    assert back.scaling_joints[0].joints == ["Hand1", "Arm_rx"]
    assert back.texture_entries is None  # no trailer in, none out


def test_skeleton_file_round_trip(tmp_path, ddc_example):
    sf = ddc.read_skeleton(ddc_example / "ddc.skeleton")
    out = ddc.write_skeleton(sf, tmp_path / "ddc.skeleton")
    _assert_ddc_text(out)
    _assert_same_tokens(ddc_example / "ddc.skeleton", out)
    assert ddc.read_skeleton(out) == sf


@pytest.mark.parametrize("name", ["ddc.obj", "ddc_graph.obj"])
def test_obj_file_round_trip(tmp_path, ddc_example, name):
    mesh = ddc.read_obj(ddc_example / name)
    out = ddc.write_obj(mesh, tmp_path / name)
    _assert_ddc_text(out)
    _assert_same_tokens(ddc_example / name, out)


def test_motion_and_labels_round_trip(tmp_path, ddc_example):
    motion = ddc.read_motion(ddc_example / "ddc.motion")
    out = ddc.write_motion(motion, tmp_path / "ddc.motion")
    _assert_ddc_text(out)
    _assert_same_tokens(ddc_example / "ddc.motion", out)
    for name in ("segmentation.txt", "hand_segmentation.txt"):
        out = ddc.write_labels(ddc.read_labels(ddc_example / name), tmp_path / name)
        _assert_ddc_text(out)
        _assert_same_tokens(ddc_example / name, out)


def test_lf_parses_like_crlf(tmp_path, ddc_example):
    lf = {name: _to_lf(ddc_example / name, tmp_path / name) for name in FILES + ("ddc.character",)}
    assert b"\r" not in lf["ddc.skeleton"].read_bytes()
    assert ddc.read_skeleton(lf["ddc.skeleton"]) == ddc.read_skeleton(ddc_example / "ddc.skeleton")
    assert ddc.read_skin(lf["ddc.skin"]).influences == ddc.read_skin(ddc_example / "ddc.skin").influences
    a, b = ddc.read_obj(lf["ddc.obj"]), ddc.read_obj(ddc_example / "ddc.obj")
    for field in ("vertices", "faces", "colors", "normals", "uvs", "face_uvs_index", "face_normals_index"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.mtllib == b.mtllib == "./ddc.obj.mtl"
    np.testing.assert_array_equal(ddc.read_motion(lf["ddc.motion"]).values, ddc.read_motion(ddc_example / "ddc.motion").values)
    assert ddc.read_character_file(lf["ddc.character"]) == ddc.read_character_file(ddc_example / "ddc.character")
    # an unterminated last line and tabs/extra spaces are fine too
    text = lf["ddc.motion"].read_text().rstrip("\n").replace(" ", "\t  ")
    (tmp_path / "t.motion").write_text(text)
    np.testing.assert_array_equal(ddc.read_motion(tmp_path / "t.motion").values,
                                  ddc.read_motion(ddc_example / "ddc.motion").values)


# ---------------------------------------------------------------------------------------------
# failures
# ---------------------------------------------------------------------------------------------


def _error(fn, *args) -> str:
    with pytest.raises(EgorelightError) as info:
        fn(*args)
    return str(info.value)


def test_truncated_skeleton(tmp_path, ddc_example):
    text = (ddc_example / "ddc.skeleton").read_text()
    bad = tmp_path / "bad.skeleton"
    bad.write_text(text.replace("joints: 173", "joints: 200"))
    msg = _error(ddc.read_skeleton, bad)
    assert "joint 174 of 200" in msg and "line 176" in msg and str(bad) in msg
    # cut in the middle of the DoFs
    lines = text.splitlines()
    (tmp_path / "cut.skeleton").write_text("\n".join(lines[:400]))
    msg = _error(ddc.read_skeleton, tmp_path / "cut.skeleton")
    assert "file ends after line 400" in msg and "cut.skeleton" in msg
    # fewer DoFs announced than present
    (tmp_path / "few.skeleton").write_text(text.replace("dofs: 107", "dofs: 100"))
    assert "unexpected content" in _error(ddc.read_skeleton, tmp_path / "few.skeleton")


@pytest.mark.parametrize("old,new,expect", [
    ("Skeletool Skeleton Definition V1.0", "Skeletool Skeleton Definition V2.0", "expected the header"),
    ("Root_ty              prismatic Root_tx                       0          0          0",
     "Root_ty              prismatic Root_tx                       0          x          0", "line 4"),
    ("Root_ty              prismatic", "Root_ty              spherical", "unknown type"),
    ("      LeftHandIndex1                3", "      NoSuchJoint                3", "unknown joint 'NoSuchJoint'"),
    ("      nolimits\r\n      Root_tx", "      limits 1\r\n      Root_tx", "expected 'limits min max'"),
])
def test_garbled_skeleton(tmp_path, ddc_example, old, new, expect):
    data = (ddc_example / "ddc.skeleton").read_bytes().decode()
    assert old in data
    (tmp_path / "g.skeleton").write_bytes(data.replace(old, new, 1).encode())
    msg = _error(ddc.read_skeleton, tmp_path / "g.skeleton")
    assert expect in msg and "g.skeleton" in msg


def test_garbled_skin_motion_obj_labels(tmp_path, ddc_example):
    text = (ddc_example / "ddc.skin").read_bytes().decode()
    (tmp_path / "a.skin").write_bytes(text.replace("\r\n9 61 ", "\r\n9 99 ", 1).encode())
    assert "bone index 99 is out of range" in _error(ddc.read_skin, tmp_path / "a.skin")
    assert "5514 vertex rows but the template has 5000" in _error(ddc.read_skin, ddc_example / "ddc.skin", 5000)
    (tmp_path / "b.skin").write_bytes(text.replace("\r\n9 61 ", "\r\n8 61 ", 1).encode())
    assert "expected vertex 9" in _error(ddc.read_skin, tmp_path / "b.skin")
    assert "107 DoF values but the skeleton has 100" in _error(ddc.read_motion, ddc_example / "ddc.motion", 100)
    (tmp_path / "c.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")
    assert "line 3" in _error(ddc.read_obj, tmp_path / "c.obj")
    assert "5514 labels but the template has 10" in _error(ddc.read_labels, ddc_example / "segmentation.txt", 10)
    (tmp_path / "bin.skin").write_bytes(b"\xff\xfe\x00garbage")
    assert "not a text file" in _error(ddc.read_skin, tmp_path / "bin.skin")
    assert "not found" in _error(ddc.read_skin, tmp_path / "none.skin")


def test_missing_referenced_file(tmp_path, ddc_example):
    for name in ("ddc.character", "ddc.skeleton", "ddc.obj"):
        shutil.copy(ddc_example / name, tmp_path / name)
    msg = _error(ddc.read_ddc_character, tmp_path / "ddc.character")
    assert "skin file 'ddc.skin' named by ddc.character does not exist" in msg
    assert str(tmp_path / "ddc.skin") in msg
    assert "character file not found" in _error(ddc.read_ddc_character, tmp_path / "nope.character")
    (tmp_path / "x.character").write_text("skeletool character file v1.0\nskeleton\n ddc.skeleton\n")
    assert "names no mesh, skin" in _error(ddc.read_ddc_character, tmp_path / "x.character")


def test_missing_graph_file(tmp_path, ddc_example):
    for name in ("ddc.character", "ddc.skeleton", "ddc.obj", "ddc.skin", "ddc.motion"):
        shutil.copy(ddc_example / name, tmp_path / name)
    msg = _error(ddc.read_ddc_character, tmp_path / "ddc.character")
    assert "embedded graph" in msg and "ddc_graph.obj" in msg


# ---------------------------------------------------------------------------------------------
# OBJ and calibration details
# ---------------------------------------------------------------------------------------------


def test_obj_corner_forms_and_wedge_uvs(tmp_path):
    (tmp_path / "q.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\n"
        "f 1/1 2/2 3/3 4/4\nf -4/5 -2/3 -1/4\n")
    mesh = ddc.read_obj(tmp_path / "q.obj")
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 3]]
    uv = mesh.face_corner_uvs()
    assert uv.shape == (3, 3, 2) and uv[2, 0].tolist() == [0.5, 0.5] and uv[1, 2].tolist() == [0, 1]
    assert mesh.colors is None and mesh.normals is None and mesh.face_normals_index is None
    (tmp_path / "n.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n")
    assert ddc.read_obj(tmp_path / "n.obj").face_normals_index.tolist() == [[0, 0, 0]]
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nf 1/1 2 3\n")
    assert "mix forms" in _error(ddc.read_obj, tmp_path / "m.obj")


def test_uv_table_first_use_order():
    face_uvs = np.array([[[0.5, 0.5], [0.1, 0.2], [0.5, 0.5]], [[0.3, 0.3], [0.1, 0.2], [0.9, 0.9]]])
    uvs, idx = ddc._uv_table(face_uvs)
    assert uvs.tolist() == [[0.5, 0.5], [0.1, 0.2], [0.3, 0.3], [0.9, 0.9]]
    assert idx.tolist() == [[0, 1, 0], [2, 1, 3]]
    np.testing.assert_array_equal(uvs[idx], face_uvs)


def test_calibration_pinhole_and_fisheye_round_trip(tmp_path):
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = 766.3206, 765.7619, 635.1871, 448.8466
    E = np.array([[-0.453446, -0.3859819, -0.8033708, 703.8229], [0.6526945, -0.7576083, -0.004404724, 150.761],
                  [-0.6069403, -0.5263531, 0.5954627, 4868.044], [0, 0, 0, 1]])
    cams = [
        ddc.CalibrationCamera("0", (14.1864, 10.3776), (1285, 940), False, K, E, -0.01),
        ddc.CalibrationCamera("ego_left", (10.0, 10.0), (1280, 1024), False, K.copy(), np.eye(4), 0.0,
                              polynomial_c2w=[-340.2, 0.0, 0.00061, -2.1e-07, 4.4e-10],
                              polynomial_w2c=[512.1, 301.5, -12.25, 20.0, 3.5, -1.0 / 3.0],
                              image_circle_radius=490.5, affine=(1.0001, -0.0002, 0.0003)),
        ddc.CalibrationCamera("anim", (1.0, 1.0), (64, 48), True, frames=[
            ddc.CalibrationFrame(3, K, E, 0.1), ddc.CalibrationFrame(7, K, np.eye(4), 0.0)]),
    ]
    out = ddc.write_calibration(cams, tmp_path / "rig.calibration")
    _assert_ddc_text(out)
    back = ddc.read_calibration(out)
    assert [c.name for c in back] == ["0", "ego_left", "anim"]
    assert [c.is_fisheye for c in back] == [False, True, False]
    for a, b in zip(cams, back):
        assert a.sensor == b.sensor and a.size == b.size and a.animated == b.animated
        assert a.radial == b.radial and a.polynomial_c2w == b.polynomial_c2w and a.polynomial_w2c == b.polynomial_w2c
        assert a.image_circle_radius == b.image_circle_radius and a.affine == b.affine
        if not a.animated:
            np.testing.assert_array_equal(a.intrinsic, b.intrinsic)
            np.testing.assert_array_equal(a.extrinsic, b.extrinsic)
        for fa, fb in zip(a.frames, b.frames, strict=True):
            assert fa.frame == fb.frame and fa.radial == fb.radial
            np.testing.assert_array_equal(fa.extrinsic, fb.extrinsic)
    text = out.read_bytes().decode()
    assert text.startswith("Skeletool Camera Calibration File V1.0\r\nname 0\r\nsensor 14.1864 10.3776\r\n")
    assert "polynomialC2W 5 -340.2 0 0.00061 -2.1e-07 4.4e-10\r\n" in text
    # the legacy 'polynomial' keyword and a bad coefficient count
    (tmp_path / "b.calibration").write_text(text.replace("polynomialC2W 5", "polynomial 5"))
    assert ddc.read_calibration(tmp_path / "b.calibration")[1].polynomial_c2w == cams[1].polynomial_c2w
    (tmp_path / "c.calibration").write_text(text.replace("polynomialC2W 5", "polynomialC2W 6"))
    assert "announces 6 coefficients" in _error(ddc.read_calibration, tmp_path / "c.calibration")


# ---------------------------------------------------------------------------------------------
# the Character (needs geometry.embedded_graph)
# ---------------------------------------------------------------------------------------------


def test_character_import(ddc_example):
    c = _character(ddc_example)
    sk = c.skeleton
    assert (sk.num_joints, sk.num_dofs, c.num_vertices, len(c.skin_bone_names), c.graph.num_nodes) == (173, 107, 5514, 69, 852)
    assert len(c.extras["ddc"]["skeleton"]["markers"]) == 97
    assert c.faces.shape == (11024, 3) and c.face_uvs.shape == (11024, 3, 2) and c.vertex_colors.shape == (5514, 3)
    # units: metres, root parent -1, translation DoF weight 1
    np.testing.assert_allclose(sk.offsets[sk.joint_index("Root_tx")], [0, 0.4, 0.069])
    assert sk.parents[0] == -1
    assert sk.dof_joint_weights[sk.dof_index("translate_x"), sk.joint_index("Root_tx")] == 1.0
    assert sk.dof_joint_weights[sk.dof_index("shoulder_scale"), sk.joint_index("LeftArm_tx")] == 1.0
    assert sk.dof_joint_weights[sk.dof_index("arm_scale"), sk.joint_index("LeftArmScale")] == pytest.approx(1e-3)
    assert 0.0 < c.vertices[:, 1].min() and c.vertices[:, 1].max() < 2.0
    np.testing.assert_array_equal(c.rest_theta, ddc.read_motion(ddc_example / "ddc.motion").values[0])
    # skin bones: the last joint of the bone's base name
    names = sk.joint_names
    bone = dict(zip(c.skin_bone_names, (names[j] for j in c.skin_bone_joints)))
    assert bone["LeftArm"] == "LeftArm_ry" and bone["Spine4"] == "Spine4_rx" and bone["GlobalScale"] == "GlobalScale"
    np.testing.assert_allclose(c.skin_weights.sum(1), 1.0, atol=1e-5)
    # keypoints: the first joint of the base name, <Side>HandWrist on <Side>Hand
    assert c.has_standard_keypoints
    kp = dict(zip(KEYPOINT_NAMES, (names[j] for j in c.keypoint_joints)))
    assert kp["LeftHandWrist"] == kp["LeftHand"] == "LeftHand_rx"
    assert kp["LeftHandIndex1"] == "LeftHandIndex1_tz" and kp["RightToeBase"] == "RightToeBase_rx"
    assert kp["Neck"] == "Neck_ry" and kp["LeftHandThumbEE"] == "LeftHandThumbEE"
    assert not c.keypoint_offsets.any()
    # embedded graph: distinct bound vertices near the graph OBJ nodes, edges from its faces
    graph_obj = ddc.read_obj(ddc_example / "ddc_graph.obj")
    assert len(set(c.graph.node_vertex.tolist())) == 852
    d = np.linalg.norm(c.vertices[c.graph.node_vertex] - graph_obj.vertices / 1000, axis=1)
    assert d.max() < 0.05
    assert c.graph.vertex_node_index.shape[0] == 5514
    np.testing.assert_array_equal(np.sort(c.graph.edges, axis=1), c.graph.edges)
    # labels
    assert c.segmentation_names[13] == "face" and c.segmentation_names[14] == "left_arm"
    left, right = c.vertices[c.hand_segmentation == 1].mean(0), c.vertices[c.hand_segmentation == 2].mean(0)
    lhand = c.vertices[c.skin_weights[:, c.skin_bone_names.index("LeftHand")] > 0.5].mean(0)
    assert np.linalg.norm(left - lhand) < np.linalg.norm(right - lhand)  # label 1 is the left hand


def test_character_export_reproduces_files(tmp_path, ddc_example):
    c = _character(ddc_example)
    # through the character.npz payload first: everything must survive to_arrays/from_arrays
    c = Character.from_arrays({k: np.asarray(v) for k, v in c.to_arrays().items()})
    path = ddc.write_ddc_character(c, tmp_path / "out")
    assert path == tmp_path / "out" / "ddc.character"
    for name in FILES + ("ddc.character",):
        _assert_ddc_text(tmp_path / "out" / name)
        _assert_same_tokens(ddc_example / name, tmp_path / "out" / name, skin_run_together=name.endswith(".skin"))
    for name in ("ddc.obj.mtl", "ddc_graph.obj.mtl"):
        assert (tmp_path / "out" / name).is_file()
    # and it imports back to the same character
    again = ddc.read_ddc_character(path)
    a, b = c.to_arrays(), again.to_arrays()
    assert a.keys() == b.keys()
    for key in a:
        if a[key].dtype.kind == "f":
            np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=1e-15, err_msg=key)
        else:
            np.testing.assert_array_equal(b[key], a[key], err_msg=key)


def test_character_export_with_another_name_and_lf_input(tmp_path, ddc_example):
    src = tmp_path / "lf"
    src.mkdir()
    for name in FILES + ("ddc.character", "ddc.obj.mtl", "ddc_graph.obj.mtl"):
        _to_lf(ddc_example / name, src / name)
    c_lf = ddc.read_ddc_character(src / "ddc.character")
    c = _character(ddc_example)
    np.testing.assert_array_equal(c_lf.vertices, c.vertices)
    np.testing.assert_array_equal(c_lf.skin_weights, c.skin_weights)
    np.testing.assert_array_equal(c_lf.skeleton.dof_joint_weights, c.skeleton.dof_joint_weights)
    np.testing.assert_array_equal(c_lf.graph.node_vertex, c.graph.node_vertex)
    out = ddc.write_ddc_character(c_lf, tmp_path / "x", name="actor")
    cf = ddc.read_character_file(out)
    assert (cf.skeleton, cf.mesh, cf.skin, cf.pose) == ("actor.skeleton", "actor.obj", "actor.skin", "actor.motion")
    assert ddc.read_obj(tmp_path / "x" / "actor.obj").mtllib == "./actor.obj.mtl"
    assert ddc.read_obj(tmp_path / "x" / "actor_graph.obj").mtllib == "./actor_graph.obj.mtl"
    for name in ("actor.obj.mtl", "actor_graph.obj.mtl", "segmentation.txt", "hand_segmentation.txt"):
        assert (tmp_path / "x" / name).is_file()


def test_character_export_without_ddc_extras(tmp_path, ddc_example):
    # a Character from elsewhere (no extras["ddc"]): files are derived from its fields alone
    from dataclasses import replace

    c = replace(_character(ddc_example), extras={})
    out = ddc.write_ddc_character(c, tmp_path / "plain", name="plain")
    for p in (tmp_path / "plain").iterdir():
        _assert_ddc_text(p)
    again = ddc.read_ddc_character(out)
    a, b = c.to_arrays(), again.to_arrays()
    for key in a.keys() - {"name", "extras"}:
        if a[key].dtype.kind == "f":
            np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=1e-15, err_msg=key)
        else:
            np.testing.assert_array_equal(b[key], a[key], err_msg=key)
    assert ddc.read_skeleton(tmp_path / "plain" / "plain.skeleton").texture_entries == []
