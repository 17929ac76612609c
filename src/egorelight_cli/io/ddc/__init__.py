"""DDC (Skeletool) character files: readers, writers and the Character conversion.

One small reader/writer pair per file type, each with a plain dataclass holding what the file
holds, in the file's own units (millimetres):

=====================  =====================================  ====================================
file                   dataclass                              functions
=====================  =====================================  ====================================
``.skeleton``          :class:`SkeletonFile`                  :func:`read_skeleton`, :func:`write_skeleton`
``.skin``              :class:`SkinFile`                      :func:`read_skin`, :func:`write_skin`
``.motion``            :class:`MotionFile`                    :func:`read_motion`, :func:`write_motion`
``.calibration``       list of :class:`CalibrationCamera`     :func:`read_calibration`, :func:`write_calibration`
``.character``         :class:`CharacterFile`                 :func:`read_character_file`, :func:`write_character_file`
template / graph OBJ   :class:`ObjMesh`                       :func:`read_obj`, :func:`write_obj`
``segmentation.txt``   (V,) int64 array                       :func:`read_labels`, :func:`write_labels`
=====================  =====================================  ====================================

and the high level pair :func:`read_ddc_character` / :func:`write_ddc_character` converting to and
from :class:`~egorelight_cli.structures.character.Character` (metres).

Reading accepts LF or CRLF, any number of spaces (and tabs) between tokens and an unterminated
last line. Writing produces what the original C++ reader needs: CRLF, a terminated last line,
single spaces, and numbers as the shortest text that reads back exactly (``repr``); lengths
converted from metres back to millimetres are first rounded to 15 significant digits, which
removes the last-bit noise of the m <-> mm round trip (``52.3472`` stays ``52.3472``).

Format quirks handled here (see ``../shared/notes/ddc_formats.md``):

* ``.skin`` rows whose ``v b w`` triplets run together: every weight but the last of a row has
  the row's vertex id glued to its end (``9 61 0.4978839 60 ...``). The reader detects this per
  file and strips the suffix; the writer writes clean ``v b w b w ...`` rows.
* DoF -> joint references match the joint name exactly, and only when no joint has that exact
  name, the first joint whose name starts with it (the C++ prefix match binds ``LeftHandIndex1``
  to ``LeftHandIndex1_tz``, which is wrong).
* Revolute axes are normalised on load, prismatic axes are not.

Modules: ``text`` (tokenised lines, number formatting, atomic CRLF writing), one per file type
(``skeleton_file``, ``skin_file``, ``motion_file``, ``calibration_file``, ``character_file``,
``obj``, ``labels``) and ``conversion`` (the Character pair); everything is importable from here.

Every known failure raises :class:`~egorelight_cli.errors.EgorelightError` naming the file and,
where there is one, the line.
"""

from __future__ import annotations

from egorelight_cli.io.ddc.calibration_file import (
    CalibrationCamera, CalibrationFrame, read_calibration, write_calibration,
)
from egorelight_cli.io.ddc.character_file import CharacterFile, read_character_file, write_character_file
from egorelight_cli.io.ddc.conversion import (
    bone_joint_index, ddc_character_files, graph_edges_from_faces, keypoint_joint_index, read_ddc_character,
    write_ddc_character,
)
from egorelight_cli.io.ddc.labels import HAND_SEGMENTATION_LABELS, HUMAN_PARSING_LABELS, read_labels, write_labels
from egorelight_cli.io.ddc.motion_file import MotionFile, read_motion, write_motion
from egorelight_cli.io.ddc.obj import ObjMesh, _uv_table, _vertex_normals, read_obj, write_obj
from egorelight_cli.io.ddc.skeleton_file import (
    ScalingJoint, SkeletonDof, SkeletonFile, SkeletonJoint, SkeletonMarker, format_skeleton, parse_skeleton,
    read_skeleton, resolve_joint_reference, skeleton_file_from_skeleton, skeleton_from_file, write_skeleton,
)
from egorelight_cli.io.ddc.skin_file import SkinFile, format_skin, parse_skin, read_skin, write_skin
from egorelight_cli.io.ddc.text import CALIBRATION_HEADER, CHARACTER_HEADER, MM_PER_M, MOTION_HEADER, SKELETON_HEADER, SKIN_HEADER

__all__ = [
    "MM_PER_M", "HUMAN_PARSING_LABELS", "HAND_SEGMENTATION_LABELS",
    "SkeletonJoint", "SkeletonMarker", "ScalingJoint", "SkeletonDof", "SkeletonFile",
    "read_skeleton", "write_skeleton", "parse_skeleton", "format_skeleton",
    "resolve_joint_reference", "skeleton_from_file", "skeleton_file_from_skeleton",
    "SkinFile", "read_skin", "write_skin", "parse_skin", "format_skin",
    "MotionFile", "read_motion", "write_motion",
    "CalibrationFrame", "CalibrationCamera", "read_calibration", "write_calibration",
    "CharacterFile", "read_character_file", "write_character_file",
    "ObjMesh", "read_obj", "write_obj",
    "read_labels", "write_labels",
    "bone_joint_index", "keypoint_joint_index", "graph_edges_from_faces",
    "read_ddc_character", "write_ddc_character", "ddc_character_files",
]
