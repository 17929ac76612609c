"""DDC files <-> :class:`~egorelight_cli.structures.character.Character` (millimetres <-> metres)."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.embedded_graph import bind_nodes_to_vertices, build_embedded_graph
from egorelight_cli.io.ddc.character_file import CharacterFile, read_character_file, write_character_file
from egorelight_cli.io.ddc.labels import HUMAN_PARSING_LABELS, read_labels, write_labels
from egorelight_cli.io.ddc.motion_file import MotionFile, read_motion, write_motion
from egorelight_cli.io.ddc.obj import ObjMesh, _uv_table, _vertex_normals, read_obj, write_obj
from egorelight_cli.io.ddc.skeleton_file import (
    ScalingJoint, SkeletonMarker, read_skeleton, skeleton_file_from_skeleton, skeleton_from_file, write_skeleton,
)
from egorelight_cli.io.ddc.skin_file import SkinFile, read_skin, write_skin
from egorelight_cli.io.ddc.text import MM_PER_M, _base_name, _read_text, _to_mm, _trim_trailing_blank, _write_text_lines
from egorelight_cli.structures.character import Character, EmbeddedGraph
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES

_EXTRAS_KEY = "ddc"


def bone_joint_index(bone: str, joint_names) -> int | None:
    """The LAST joint whose name up to the first ``_`` equals ``bone`` (``LeftArm`` -> ``LeftArm_ry``)."""
    found = None
    for i, name in enumerate(joint_names):
        if _base_name(name) == bone:
            found = i
    return found


def _joint_indices(items, lookup, joint_names) -> tuple[list[int], list[str]]:
    """(joint index of each item by ``lookup(item, joint_names)``, -1 where none; the items without one)."""
    found = [lookup(item, joint_names) for item in items]
    return [-1 if j is None else j for j in found], [item for item, j in zip(items, found) if j is None]


def keypoint_joint_index(keypoint: str, joint_names) -> int | None:
    """The FIRST joint whose base name equals the keypoint name (``<Side>HandWrist`` -> ``<Side>Hand``)."""
    for side in ("Left", "Right"):
        if keypoint == f"{side}HandWrist":
            keypoint = f"{side}Hand"
    for i, name in enumerate(joint_names):
        if _base_name(name) == keypoint:
            return i
    return None


def graph_edges_from_faces(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(i, j)``, ``i < j``, of a triangle list, sorted."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros((0, 2), np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0)


def _digest(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array, dtype=np.float64).tobytes()).hexdigest()[:16]


def _marker_to_json(m: SkeletonMarker) -> dict:
    return {"name": m.name, "parent": m.parent, "type": m.type,
            "offset": [v / MM_PER_M for v in m.offset], "values": list(m.values)}


def _marker_from_json(d: dict) -> SkeletonMarker:
    return SkeletonMarker(d["name"], d["parent"], d["type"], tuple(_to_mm(d["offset"]).tolist()),
                          tuple(d.get("values", ())))


def _referenced(base: Path, rel: str, what: str, character_path: Path) -> Path:
    p = Path(rel)
    p = p if p.is_absolute() else base / p
    if not p.is_file():
        raise EgorelightError(f"the {what} file {rel!r} named by {character_path.name} does not exist", p)
    return p


def _read_mtl_lines(path: Path) -> list[str] | None:
    if not path.is_file():
        return None
    text = _read_text(path, "material file")
    return _trim_trailing_blank([ln.rstrip("\r") for ln in text.split("\n")])


def ddc_character_files(path: str | Path) -> list[Path]:
    """Every file an import of ``path`` (a ``.character``) reads, for cache keys and provenance."""
    path = Path(path)
    cf = read_character_file(path)
    base = path.parent
    mesh_path = _referenced(base, cf.mesh, "mesh", path)
    files = [path, _referenced(base, cf.skeleton, "skeleton", path), mesh_path, _referenced(base, cf.skin, "skin", path)]
    if cf.pose is not None:
        files.append(_referenced(base, cf.pose, "pose", path))
    files.append(mesh_path.with_name(f"{mesh_path.stem}_graph.obj"))
    files += [p for p in (base / "segmentation.txt", base / "hand_segmentation.txt") if p.is_file()]
    return files


def read_ddc_character(
    path: str | Path,
    graph_path: str | Path | None = None,
    segmentation_path: str | Path | None = None,
    hand_segmentation_path: str | Path | None = None,
) -> Character:
    """Import a DDC character from its ``.character`` file.

    The embedded graph is ``<mesh stem>_graph.obj`` next to the mesh unless ``graph_path`` is
    given (it is required). ``segmentation.txt`` and ``hand_segmentation.txt`` next to the
    ``.character`` are optional (all zeros when absent).

    Conversion: millimetres -> metres (offsets, template and graph vertices; prismatic DoF
    weights / 1000), ``rest_theta`` = the pose file's first frame (zeros without one). Whatever
    the Character has no field for is kept in ``extras["ddc"]`` so that
    :func:`write_ddc_character` reproduces the files.
    """
    path = Path(path)
    cf = read_character_file(path)
    base = path.parent

    skeleton_path = _referenced(base, cf.skeleton, "skeleton", path)
    mesh_path = _referenced(base, cf.mesh, "mesh", path)
    skin_path = _referenced(base, cf.skin, "skin", path)
    pose_path = _referenced(base, cf.pose, "pose", path) if cf.pose is not None else None

    sf = read_skeleton(skeleton_path)
    skeleton, dof_joints = skeleton_from_file(sf, skeleton_path)
    names = skeleton.joint_names

    mesh = read_obj(mesh_path, "template OBJ")
    V = len(mesh.vertices)
    if len(mesh.faces) == 0:
        raise EgorelightError("the template OBJ has no faces", mesh_path)
    vertices = mesh.vertices / MM_PER_M

    skin = read_skin(skin_path, num_vertices=V)
    bone_joints, unbound = _joint_indices(skin.bones, bone_joint_index, names)
    if unbound:
        raise EgorelightError(f"skin bones match no skeleton joint: {', '.join(unbound)}", skin_path)

    D = skeleton.num_dofs
    rest_theta = np.zeros(D)
    pose_extra = None
    pose_frame_id = 0
    if pose_path is not None:
        motion = read_motion(pose_path, num_dofs=D)
        if len(motion.values) == 0:
            raise EgorelightError("the pose file has no frame", pose_path)
        rest_theta = motion.values[0].copy()
        pose_frame_id = int(motion.frame_ids[0])
        if len(motion.values) > 1:
            pose_extra = {"frame_ids": motion.frame_ids[1:].tolist(), "values": motion.values[1:].tolist()}

    kp_joints, missing = _joint_indices(KEYPOINT_NAMES, keypoint_joint_index, names)
    if missing:
        raise EgorelightError(f"the skeleton has no joint for the keypoints {', '.join(missing)}", skeleton_path)

    gpath = Path(graph_path) if graph_path is not None else mesh_path.with_name(f"{mesh_path.stem}_graph.obj")
    if not gpath.is_file():
        raise EgorelightError("the embedded graph OBJ of the character does not exist", gpath)
    gmesh = read_obj(gpath, "embedded graph OBJ")
    node_vertex = bind_nodes_to_vertices(gmesh.vertices, mesh.vertices)
    node_edges = graph_edges_from_faces(gmesh.faces)

    graph = build_embedded_graph(mesh.faces, V, node_vertex, node_edges, gmesh.faces, vertices=vertices)
    if graph.faces.shape[0] == 0 and len(gmesh.faces):
        graph = EmbeddedGraph(graph.node_vertex, graph.node_radius, graph.edges, graph.vertex_node_index,
                              graph.vertex_node_weight, gmesh.faces)

    seg_path = Path(segmentation_path) if segmentation_path is not None else base / "segmentation.txt"
    hand_path = Path(hand_segmentation_path) if hand_segmentation_path is not None else base / "hand_segmentation.txt"
    if segmentation_path is not None or seg_path.is_file():
        segmentation = read_labels(seg_path, V, "segmentation file")
        seg_name = seg_path.name
    else:
        segmentation, seg_name = np.zeros(V, np.int64), None
    if hand_segmentation_path is not None or hand_path.is_file():
        hand = read_labels(hand_path, V, "hand segmentation file")
        hand_name = hand_path.name
    else:
        hand, hand_name = np.zeros(V, np.int64), None

    obj_extras = {
        "mtllib": mesh.mtllib, "usemtl": mesh.usemtl,
        "mtl_lines": _read_mtl_lines(mesh_path.parent / mesh.mtllib) if mesh.mtllib else None,
        "has_uvs": mesh.face_uvs_index is not None,
        "vertices_digest": _digest(vertices),
        "normals": mesh.normals.tolist() if mesh.normals is not None else None,
        "face_normals_index": (None if mesh.face_normals_index is None or np.array_equal(mesh.face_normals_index, mesh.faces)
                               else mesh.face_normals_index.tolist()),
        "normals_per_vertex": mesh.face_normals_index is not None and np.array_equal(mesh.face_normals_index, mesh.faces),
    }
    graph_extras = gmesh.to_json(scale=1.0 / MM_PER_M)
    graph_extras["mtl_lines"] = _read_mtl_lines(gpath.parent / gmesh.mtllib) if gmesh.mtllib else None
    graph_extras["template_digest"] = obj_extras["vertices_digest"]
    extras = {_EXTRAS_KEY: {
        "files": {"character": path.name, "skeleton": cf.skeleton, "mesh": cf.mesh, "skin": cf.skin,
                  "pose": cf.pose, "graph": gpath.name, "segmentation": seg_name, "hand_segmentation": hand_name,
                  "other": [list(p) for p in cf.other]},
        "skeleton": {
            "markers": [_marker_to_json(m) for m in sf.markers],
            "scaling_joints": [{"name": s.name, "joints": list(s.joints)} for s in sf.scaling_joints],
            "texture_entries": sf.texture_entries,
            "dof_joints": dof_joints,
            "root_parent": next((j.parent for j in sf.joints if j.parent not in set(names)), "none"),
        },
        "pose": {"frame_id": pose_frame_id, "more_frames": pose_extra},
        "obj": obj_extras,
        "graph_obj": graph_extras,
        "units": "metres (markers: offset metres, values as in the file)",
    }}

    return Character(
        name=path.stem,
        skeleton=skeleton,
        rest_theta=rest_theta,
        vertices=vertices,
        faces=mesh.faces,
        face_uvs=mesh.face_corner_uvs(),
        skin_bone_names=tuple(skin.bones),
        skin_bone_joints=np.array(bone_joints, dtype=np.int64),
        skin_weights=skin.dense(),
        keypoint_names=tuple(KEYPOINT_NAMES),
        keypoint_joints=np.array(kp_joints, dtype=np.int64),
        keypoint_offsets=np.zeros((len(KEYPOINT_NAMES), 3)),
        graph=graph,
        segmentation=segmentation,
        segmentation_names=dict(HUMAN_PARSING_LABELS),
        hand_segmentation=hand,
        vertex_colors=mesh.colors,
        extras=extras,
    )


def write_ddc_character(character: Character, out_dir: str | Path, name: str = "ddc",
                        texture: str | Path | None = None) -> Path:
    """Export a Character as DDC files into ``out_dir``; returns the ``.character`` path.

    Writes ``<name>.character``, ``.skeleton``, ``.skin``, ``.motion`` (the rest pose),
    ``<name>.obj`` (+ ``.obj.mtl`` when the import had one), ``<name>_graph.obj``,
    ``segmentation.txt`` and ``hand_segmentation.txt``. Data the Character has no field for comes
    from ``character.extras["ddc"]`` when present (markers, DoF joint order, OBJ normals, the graph
    OBJ's own geometry, materials); stored OBJ normals and graph geometry are used only while the
    template vertices are unchanged. ``texture``, if given, is copied to the file name the
    material references (or ``<name>.png``).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ex = dict(character.extras.get(_EXTRAS_KEY, {})) if isinstance(character.extras, dict) else {}
    files = ex.get("files", {})
    sk_ex = ex.get("skeleton", {})
    obj_ex = ex.get("obj", {})
    g_ex = ex.get("graph_obj", {})
    skeleton = character.skeleton

    # skeleton
    sf = skeleton_file_from_skeleton(
        skeleton,
        markers=[_marker_from_json(m) for m in sk_ex.get("markers", [])],
        scaling_joints=[ScalingJoint(s["name"], list(s["joints"])) for s in sk_ex.get("scaling_joints", [])],
        texture_entries=sk_ex.get("texture_entries", []) if sk_ex else [],
        dof_joints=sk_ex.get("dof_joints"),
        root_parent=sk_ex.get("root_parent", "none"),
    )
    write_skeleton(sf, out_dir / f"{name}.skeleton")

    # skin
    write_skin(SkinFile.from_dense(character.skin_bone_names, character.skin_weights), out_dir / f"{name}.skin")

    # pose
    pose_ex = ex.get("pose", {})
    write_pose = files.get("pose") is not None or not files or bool(np.any(character.rest_theta))
    if write_pose:
        ids = [int(pose_ex.get("frame_id", 0))]
        rows = [character.rest_theta]
        more = pose_ex.get("more_frames")
        if more:
            ids += list(more["frame_ids"])
            rows += [np.asarray(r, dtype=np.float64) for r in more["values"]]
        write_motion(MotionFile(np.array(ids), np.stack(rows)), out_dir / f"{name}.motion")

    # template OBJ
    vertices_mm = _to_mm(character.vertices)
    same_template = obj_ex.get("vertices_digest") == _digest(character.vertices)
    normals = face_normals_index = None
    if same_template and obj_ex.get("normals") is not None:
        normals = np.asarray(obj_ex["normals"], dtype=np.float64).reshape(-1, 3)
        if obj_ex.get("normals_per_vertex"):
            face_normals_index = character.faces
        elif obj_ex.get("face_normals_index") is not None:
            face_normals_index = np.asarray(obj_ex["face_normals_index"], dtype=np.int64).reshape(-1, 3)
            if face_normals_index.shape != character.faces.shape:
                normals = face_normals_index = None
    if normals is None:
        normals, face_normals_index = _vertex_normals(character.vertices, character.faces), character.faces
    has_uvs = obj_ex.get("has_uvs", True)
    uvs, fti = _uv_table(character.face_uvs) if has_uvs else (None, None)
    mtl_lines = obj_ex.get("mtl_lines")
    obj_mtl = f"./{name}.obj.mtl" if mtl_lines else None
    write_obj(ObjMesh(vertices_mm, character.faces, character.vertex_colors, normals, uvs, fti, face_normals_index,
                      obj_mtl, obj_ex.get("usemtl") if mtl_lines else None),
              out_dir / f"{name}.obj", comment=f"{name}.obj, DDC template exported by egorelight")
    if mtl_lines:
        _write_text_lines(out_dir / f"{name}.obj.mtl", _trim_trailing_blank(mtl_lines))

    # graph OBJ
    graph = character.graph
    if (g_ex.get("vertices") is not None and g_ex.get("template_digest") == _digest(character.vertices)
            and len(g_ex["vertices"]) == graph.num_nodes):
        gmesh = ObjMesh.from_json(g_ex)  # positions stored in metres
        gmesh.vertices = _to_mm(gmesh.vertices)
    else:
        gfaces = graph.faces if graph.faces.shape[0] else np.zeros((0, 3), np.int64)
        gmesh = ObjMesh(vertices_mm[graph.node_vertex], gfaces,
                        character.vertex_colors[graph.node_vertex] if character.vertex_colors is not None else None)
    g_mtl = g_ex.get("mtl_lines")
    gmesh.mtllib = f"./{name}_graph.obj.mtl" if g_mtl else None
    gmesh.usemtl = gmesh.usemtl if g_mtl else None
    write_obj(gmesh, out_dir / f"{name}_graph.obj", comment=f"{name}_graph.obj, DDC embedded graph exported by egorelight")
    if g_mtl:
        _write_text_lines(out_dir / f"{name}_graph.obj.mtl", _trim_trailing_blank(g_mtl))

    # segmentation
    if not files or files.get("segmentation") is not None:
        write_labels(character.segmentation, out_dir / "segmentation.txt")
    if not files or files.get("hand_segmentation") is not None:
        write_labels(character.hand_segmentation, out_dir / "hand_segmentation.txt")

    if texture is not None:
        texture = Path(texture)
        if not texture.is_file():
            raise EgorelightError("texture image not found", texture)
        target = next((ln.split(None, 1)[1].strip() for ln in (mtl_lines or [])
                       if ln.strip().startswith("map_Kd") and len(ln.split()) > 1), f"{name}{texture.suffix}")
        shutil.copyfile(texture, out_dir / target)

    cf = CharacterFile(f"{name}.skeleton", f"{name}.obj", f"{name}.skin", f"{name}.motion" if write_pose else None,
                       [tuple(p) for p in files.get("other", [])])
    return write_character_file(cf, out_dir / f"{name}.character")
