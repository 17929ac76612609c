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

Every known failure raises :class:`~egorelight_cli.errors.EgorelightError` naming the file and,
where there is one, the line.
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.embedded_graph import bind_nodes_to_vertices, build_embedded_graph
from egorelight_cli.structures.character import Character, EmbeddedGraph
from egorelight_cli.structures.keypoints import KEYPOINT_NAMES
from egorelight_cli.structures.skeleton import JOINT_TYPE_NAMES, PRISMATIC, REVOLUTE, Skeleton

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
    "read_ddc_character", "write_ddc_character",
]

MM_PER_M = 1000.0

SKELETON_HEADER = "Skeletool Skeleton Definition V1.0"
SKIN_HEADER = "Skeletool character skinning file V1.0"
MOTION_HEADER = "Skeletool Motion File V1.0"
CALIBRATION_HEADER = "Skeletool Camera Calibration File V1.0"
CHARACTER_HEADER = "skeletool character file v1.0"

#: Human-parsing (LIP) labels used by DDC's ``segmentation.txt``.
HUMAN_PARSING_LABELS: dict[int, str] = {
    0: "background", 1: "hat", 2: "hair", 3: "glove", 4: "sunglasses", 5: "upper_clothes",
    6: "dress", 7: "coat", 8: "socks", 9: "pants", 10: "jumpsuits", 11: "scarf", 12: "skirt",
    13: "face", 14: "left_arm", 15: "right_arm", 16: "left_leg", 17: "right_leg",
    18: "left_shoe", 19: "right_shoe",
}
#: Labels of ``hand_segmentation.txt``.
HAND_SEGMENTATION_LABELS: dict[int, str] = {0: "body", 1: "left_hand", 2: "right_hand"}

_EXTRAS_KEY = "ddc"


# ---------------------------------------------------------------------------------------------
# text helpers
# ---------------------------------------------------------------------------------------------


def _read_text(path: Path, what: str) -> str:
    if not path.is_file():
        raise EgorelightError(f"{what} not found", path)
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise EgorelightError(f"{what} is not a text file (byte {exc.start} is not UTF-8)", path) from None
    except OSError as exc:
        raise EgorelightError(f"cannot read {what}: {exc.strerror}", path) from None


class _Lines:
    """Cursor over the non-empty lines of a text file, with 1-based line numbers for errors."""

    def __init__(self, path: Path, text: str, what: str):
        self.path = path
        self.what = what
        self.lines: list[tuple[int, str, list[str]]] = []
        for number, raw in enumerate(text.split("\n"), start=1):
            line = raw[:-1] if raw.endswith("\r") else raw
            tokens = line.split()
            if tokens:
                self.lines.append((number, line.strip(), tokens))
        self.pos = 0

    def error(self, message: str, line: int | None = None) -> EgorelightError:
        where = f"line {line}: " if line is not None else ""
        return EgorelightError(f"{self.what}: {where}{message}", self.path)

    def at_end(self) -> bool:
        return self.pos >= len(self.lines)

    def peek(self) -> tuple[int, str, list[str]] | None:
        return None if self.at_end() else self.lines[self.pos]

    def next(self, expecting: str) -> tuple[int, str, list[str]]:
        if self.at_end():
            last = self.lines[-1][0] if self.lines else 0
            raise self.error(f"file ends after line {last} while expecting {expecting}")
        item = self.lines[self.pos]
        self.pos += 1
        return item

    def header(self, expected: str) -> None:
        number, line, tokens = self.next(f"the header {expected!r}")
        if " ".join(tokens).lstrip("\ufeff").lower() != expected.lower():
            raise self.error(f"expected the header {expected!r}, found {_clip(line)!r}", number)

    def count(self, keyword: str) -> int:
        """Read a ``keyword N`` line (keyword may be several tokens, e.g. ``scaling joints:``)."""
        words = keyword.split()
        number, line, tokens = self.next(f"'{keyword} N'")
        if len(tokens) != len(words) + 1 or [t.lower() for t in tokens[:-1]] != [w.lower() for w in words]:
            raise self.error(f"expected '{keyword} N', found {_clip(line)!r}", number)
        return self.int(tokens[-1], number, f"the {keyword[:-1] if keyword.endswith(':') else keyword} count",
                        minimum=0)

    def float(self, token: str, line: int, what: str) -> float:
        try:
            return float(token)
        except ValueError:
            raise self.error(f"{what} {token!r} is not a number", line) from None

    def int(self, token: str, line: int, what: str, minimum: int | None = None) -> int:
        try:
            value = int(token)
        except ValueError:
            try:
                as_float = float(token)
            except ValueError:
                raise self.error(f"{what} {token!r} is not an integer", line) from None
            if not as_float.is_integer():
                raise self.error(f"{what} {token!r} is not an integer", line) from None
            value = int(as_float)
        if minimum is not None and value < minimum:
            raise self.error(f"{what} {token!r} is below {minimum}", line)
        return value

    def floats(self, tokens: list[str], line: int, what: str) -> list[float]:
        return [self.float(t, line, what) for t in tokens]


def _clip(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def _fmt(x: float) -> str:
    """A number token: integers as integers, floats as the shortest text that reads back exactly."""
    if isinstance(x, (int, np.integer)) and not isinstance(x, bool):
        return str(int(x))
    x = float(x)
    if x == 0.0:
        return "0"
    s = repr(x)
    return s[:-2] if s.endswith(".0") else s


def _to_mm(values) -> np.ndarray:
    """Metres -> millimetres, rounded to 15 significant digits.

    ``x / 1000 * 1000`` is not always ``x`` in binary floating point; the rounding removes that
    last-bit noise so that ``52.3472`` is written back as ``52.3472``, not ``52.347199999999994``.
    """
    a = np.asarray(values, dtype=np.float64) * MM_PER_M
    flat = [float("%.15g" % v) for v in a.reshape(-1).tolist()]
    return np.array(flat, dtype=np.float64).reshape(a.shape)


def _join(tokens) -> str:
    return " ".join(t if isinstance(t, str) else _fmt(t) for t in tokens)


def _write_text_lines(path: Path, lines: list[str]) -> Path:
    """Write ``lines`` with CRLF endings and a final newline, atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = ("\r\n".join(lines) + "\r\n").encode("utf-8")
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with open(tmp, "xb") as fh:  # default permissions (umask), unlike mkstemp's 0600
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _base_name(name: str) -> str:
    return name.split("_", 1)[0]


# ---------------------------------------------------------------------------------------------
# .skeleton
# ---------------------------------------------------------------------------------------------


@dataclass
class SkeletonJoint:
    """One ``joints:`` row. ``offset`` in millimetres, ``axis`` as written in the file."""

    name: str
    type: str  # "revolute" | "prismatic"
    parent: str  # a joint name; anything matching no joint (normally "none") marks the root
    offset: tuple[float, float, float]
    axis: tuple[float, float, float]
    scale: float = 1.0


@dataclass
class SkeletonMarker:
    """One ``markers:`` row: ``name parent type ox oy oz [values...]``.

    ``offset`` in millimetres; ``values`` are the remaining numbers as written (for ``point``
    markers ``[size [r g b]]`` with size in millimetres, for ``oriented`` ones a quaternion).
    """

    name: str
    parent: str
    type: str
    offset: tuple[float, float, float]
    values: tuple[float, ...] = ()


@dataclass
class ScalingJoint:
    """One ``scaling joints:`` group: a name and the joints it lists."""

    name: str
    joints: list[str] = field(default_factory=list)


@dataclass
class SkeletonDof:
    """One ``dofs:`` block: name, ``(min, max)`` or ``None`` (``nolimits``), joint references.

    ``joints`` are ``(joint reference, weight)`` in file order; weights on prismatic joints are
    millimetres per DoF unit (1000 for the root translation DoFs, which are in metres).
    """

    name: str
    limits: tuple[float, float] | None
    joints: list[tuple[str, float]] = field(default_factory=list)


@dataclass
class SkeletonFile:
    """The contents of a ``.skeleton`` file (millimetres).

    ``texture_entries`` is ``None`` when the optional ``textureEntries:`` trailer is absent,
    otherwise one token list per entry (kept verbatim).
    """

    joints: list[SkeletonJoint]
    markers: list[SkeletonMarker] = field(default_factory=list)
    scaling_joints: list[ScalingJoint] = field(default_factory=list)
    dofs: list[SkeletonDof] = field(default_factory=list)
    texture_entries: list[list[str]] | None = None

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]


def resolve_joint_reference(name: str, joint_names, exact: dict[str, int] | None = None) -> int | None:
    """Index of the joint a DoF (or marker) reference ``name`` binds to, or ``None``.

    The exact name wins; only when no joint has exactly that name, the first joint (file order)
    whose name starts with ``name`` is used (the C++ prefix match, kept as a fallback).
    """
    if exact is None:
        exact = {n: i for i, n in enumerate(joint_names)}
    if name in exact:
        return exact[name]
    for i, candidate in enumerate(joint_names):
        if candidate.startswith(name):
            return i
    return None


def parse_skeleton(text: str, path: str | Path = "<skeleton>") -> SkeletonFile:
    """Parse the text of a ``.skeleton`` file."""
    path = Path(path)
    lines = _Lines(path, text, "skeleton file")
    lines.header(SKELETON_HEADER)

    nj = lines.count("joints:")
    joints: list[SkeletonJoint] = []
    for i in range(nj):
        number, line, tokens = lines.next(f"joint {i + 1} of {nj}")
        if len(tokens) != 10:
            raise lines.error(f"joint {i + 1} of {nj}: expected 10 fields "
                              f"(name type parent ox oy oz ax ay az scale), found {len(tokens)}: {_clip(line)!r}", number)
        name, jtype, parent = tokens[:3]
        if jtype not in JOINT_TYPE_NAMES:
            raise lines.error(f"joint {name!r} has unknown type {jtype!r} (expected revolute or prismatic)", number)
        values = lines.floats(tokens[3:], number, f"joint {name!r} value")
        joints.append(SkeletonJoint(name, jtype, parent, tuple(values[0:3]), tuple(values[3:6]), values[6]))
    names = [j.name for j in joints]
    exact = {n: i for i, n in enumerate(names)}
    if len(exact) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise lines.error(f"joint name {dup!r} appears twice")

    nm = lines.count("markers:")
    markers: list[SkeletonMarker] = []
    for i in range(nm):
        number, line, tokens = lines.next(f"marker {i + 1} of {nm}")
        if len(tokens) < 6 or len(tokens) > 11:
            raise lines.error(f"marker {i + 1} of {nm}: expected 6 to 11 fields "
                              f"(name parent type ox oy oz ...), found {len(tokens)}: {_clip(line)!r}", number)
        values = lines.floats(tokens[3:], number, f"marker {tokens[0]!r} value")
        if resolve_joint_reference(tokens[1], names, exact) is None:
            raise lines.error(f"marker {tokens[0]!r} names the unknown joint {tokens[1]!r}", number)
        markers.append(SkeletonMarker(tokens[0], tokens[1], tokens[2], tuple(values[0:3]), tuple(values[3:])))

    ns = lines.count("scaling joints:")
    scaling: list[ScalingJoint] = []
    for i in range(ns):
        number, line, tokens = lines.next(f"scaling joint group {i + 1} of {ns}")
        if len(tokens) != 2:
            raise lines.error(f"scaling joint group {i + 1} of {ns}: expected 'name count', found {_clip(line)!r}", number)
        count = lines.int(tokens[1], number, "scaling joint count", minimum=0)
        group = ScalingJoint(tokens[0], [])
        for k in range(count):
            number, line, tokens = lines.next(f"joint {k + 1} of scaling group {group.name!r}")
            if len(tokens) != 1:
                raise lines.error(f"scaling group {group.name!r}: expected one joint name, found {_clip(line)!r}", number)
            group.joints.append(tokens[0])
        scaling.append(group)

    nd = lines.count("dofs:")
    dofs: list[SkeletonDof] = []
    for i in range(nd):
        number, line, tokens = lines.next(f"DoF {i + 1} of {nd}")
        if len(tokens) != 2:
            raise lines.error(f"DoF {i + 1} of {nd}: expected 'name count', found {_clip(line)!r}", number)
        dof_name = tokens[0]
        count = lines.int(tokens[1], number, f"DoF {dof_name!r} joint count", minimum=0)
        number, line, tokens = lines.next(f"the limits of DoF {dof_name!r}")
        if tokens[0] == "limits" and len(tokens) == 3:
            lo, hi = lines.floats(tokens[1:], number, f"DoF {dof_name!r} limit")
            limits: tuple[float, float] | None = (lo, hi)
        elif tokens[0] == "nolimits" and len(tokens) == 1:
            limits = None
        else:
            raise lines.error(f"DoF {dof_name!r}: expected 'limits min max' or 'nolimits', found {_clip(line)!r}", number)
        dof = SkeletonDof(dof_name, limits, [])
        for k in range(count):
            number, line, tokens = lines.next(f"joint {k + 1} of {count} of DoF {dof_name!r}")
            if len(tokens) != 2:
                raise lines.error(f"DoF {dof_name!r} joint {k + 1} of {count}: expected 'joint weight', "
                                  f"found {_clip(line)!r}", number)
            if resolve_joint_reference(tokens[0], names, exact) is None:
                raise lines.error(f"DoF {dof_name!r} names the unknown joint {tokens[0]!r}", number)
            dof.joints.append((tokens[0], lines.float(tokens[1], number, f"DoF {dof_name!r} weight")))
        dofs.append(dof)

    texture_entries: list[list[str]] | None = None
    if not lines.at_end() and lines.peek()[2][0] == "textureEntries:":
        nt = lines.count("textureEntries:")
        texture_entries = []
        for i in range(nt):
            number, line, tokens = lines.next(f"texture entry {i + 1} of {nt}")
            lines.floats(tokens, number, "texture entry value")
            texture_entries.append(list(tokens))
    if not lines.at_end():
        number, line, _ = lines.peek()
        raise lines.error(f"unexpected content after the last section (the counts do not match the file?): "
                          f"{_clip(line)!r}", number)
    return SkeletonFile(joints, markers, scaling, dofs, texture_entries)


def read_skeleton(path: str | Path) -> SkeletonFile:
    """Read a ``.skeleton`` file (see :class:`SkeletonFile`)."""
    path = Path(path)
    return parse_skeleton(_read_text(path, "skeleton file"), path)


def format_skeleton(skeleton: SkeletonFile) -> list[str]:
    """The lines of a ``.skeleton`` file (no line endings)."""
    out = [SKELETON_HEADER, f"joints: {len(skeleton.joints)}"]
    for j in skeleton.joints:
        out.append(_join([j.name, j.type, j.parent, *j.offset, *j.axis, j.scale]))
    out.append(f"markers: {len(skeleton.markers)}")
    for m in skeleton.markers:
        out.append(_join([m.name, m.parent, m.type, *m.offset, *m.values]))
    out.append(f"scaling joints: {len(skeleton.scaling_joints)}")
    for s in skeleton.scaling_joints:
        out.append(_join([s.name, len(s.joints)]))
        out.extend(s.joints)
    out.append(f"dofs: {len(skeleton.dofs)}")
    for d in skeleton.dofs:
        out.append(_join([d.name, len(d.joints)]))
        out.append("nolimits" if d.limits is None else _join(["limits", *d.limits]))
        for joint, weight in d.joints:
            out.append(_join([joint, weight]))
    if skeleton.texture_entries is not None:
        out.append(f"textureEntries: {len(skeleton.texture_entries)}")
        out.extend(" ".join(entry) for entry in skeleton.texture_entries)
    return out


def write_skeleton(skeleton: SkeletonFile, path: str | Path) -> Path:
    """Write a ``.skeleton`` file (CRLF, single spaces)."""
    return _write_text_lines(Path(path), format_skeleton(skeleton))


def skeleton_from_file(sf: SkeletonFile, path: str | Path | None = None) -> tuple[Skeleton, list[list[str]]]:
    """Convert file contents to a :class:`Skeleton` in metres.

    Offsets are divided by 1000 and so are DoF weights on prismatic joints (DoF values keep their
    DDC meaning: the root translation DoFs, weight 1000 in the file, get weight 1 and are metres).
    Revolute axes are normalised. The joint whose parent names no joint is a root (-1).

    Returns:
        the skeleton and, per DoF, the names of the joints it lists in file order (resolved, for
        writing the file back in the same order).
    """
    names = sf.joint_names
    exact = {n: i for i, n in enumerate(names)}
    J = len(names)
    parents = np.array([exact.get(j.parent, -1) for j in sf.joints], dtype=np.int64)
    if np.count_nonzero(parents < 0) > 1:
        roots = [names[i] for i in np.nonzero(parents < 0)[0]]
        raise EgorelightError(f"skeleton file: several joints have a parent that is no joint "
                              f"({', '.join(f'{r} -> {sf.joints[exact[r]].parent}' for r in roots[:4])})", path)
    types = np.array([REVOLUTE if j.type == "revolute" else PRISMATIC for j in sf.joints], dtype=np.int8)
    axes = np.array([j.axis for j in sf.joints], dtype=np.float64).reshape(J, 3)
    for i in np.nonzero(types == REVOLUTE)[0]:
        n = np.linalg.norm(axes[i])
        if not n > 0:
            raise EgorelightError(f"skeleton file: revolute joint {names[i]!r} has a zero axis", path)
        axes[i] = axes[i] / n
    offsets = np.array([j.offset for j in sf.joints], dtype=np.float64).reshape(J, 3) / MM_PER_M
    scales = np.array([j.scale for j in sf.joints], dtype=np.float64)
    D = len(sf.dofs)
    weights = np.zeros((D, J))
    limits = np.tile(np.array([-np.inf, np.inf]), (D, 1))
    dof_joints: list[list[str]] = []
    for d, dof in enumerate(sf.dofs):
        if dof.limits is not None:
            limits[d] = dof.limits
        listed = []
        for ref, w in dof.joints:
            j = resolve_joint_reference(ref, names, exact)
            if j is None:
                raise EgorelightError(f"skeleton file: DoF {dof.name!r} names the unknown joint {ref!r}", path)
            weights[d, j] += w / MM_PER_M if types[j] == PRISMATIC else w
            listed.append(names[j])
        dof_joints.append(listed)
    try:
        skeleton = Skeleton(tuple(names), parents, types, axes, offsets, tuple(d.name for d in sf.dofs),
                            weights, limits, scales)
    except EgorelightError as exc:
        raise EgorelightError(f"skeleton file: {exc.message}", path) from None
    return skeleton, dof_joints


_LIMIT_CAP = 1e10  # stands in for an infinite bound when only one side is limited


def skeleton_file_from_skeleton(
    skeleton: Skeleton,
    markers: list[SkeletonMarker] | None = None,
    scaling_joints: list[ScalingJoint] | None = None,
    texture_entries: list[list[str]] | None = None,
    dof_joints: list[list[str]] | None = None,
    root_parent: str = "none",
) -> SkeletonFile:
    """Convert a :class:`Skeleton` (metres) back to file contents (millimetres).

    ``dof_joints`` (per DoF, joint names in file order, as returned by :func:`skeleton_from_file`)
    keeps each DoF's joint order and its zero-weight entries; joints with a non-zero weight that
    it does not list are appended in joint order.
    """
    names = skeleton.joint_names
    exact = {n: i for i, n in enumerate(names)}
    joints = []
    for j, name in enumerate(names):
        p = int(skeleton.parents[j])
        joints.append(SkeletonJoint(
            name, JOINT_TYPE_NAMES[int(skeleton.joint_types[j])], root_parent if p < 0 else names[p],
            tuple(_to_mm(skeleton.offsets[j]).tolist()), tuple(float(v) for v in skeleton.axes[j]),
            float(skeleton.joint_scales[j])))
    dofs = []
    for d, dof_name in enumerate(skeleton.dof_names):
        row = skeleton.dof_joint_weights[d]
        order = [n for n in (dof_joints[d] if dof_joints is not None and d < len(dof_joints) else []) if n in exact]
        seen = set(order)
        order += [names[j] for j in np.nonzero(row)[0] if names[j] not in seen]
        entries, written = [], set()
        for n in order:
            j = exact[n]
            w = 0.0 if n in written else float(row[j])
            written.add(n)
            if skeleton.joint_types[j] == PRISMATIC:
                w = float(_to_mm(w))
            entries.append((n, w))
        lo, hi = (float(v) for v in skeleton.dof_limits[d])
        if math.isinf(lo) and math.isinf(hi):
            limits = None
        else:
            limits = (max(lo, -_LIMIT_CAP), min(hi, _LIMIT_CAP))
        dofs.append(SkeletonDof(dof_name, limits, entries))
    return SkeletonFile(joints, list(markers or []), list(scaling_joints or []), dofs, texture_entries)


# ---------------------------------------------------------------------------------------------
# .skin
# ---------------------------------------------------------------------------------------------


@dataclass
class SkinFile:
    """The contents of a ``.skin`` file: bone names and, per vertex (in order), its influences
    ``(bone index, weight)`` as listed (largest first in DDC files)."""

    bones: list[str]
    influences: list[list[tuple[int, float]]]

    @property
    def num_vertices(self) -> int:
        return len(self.influences)

    def dense(self) -> np.ndarray:
        """(V,B) float64 weight matrix."""
        W = np.zeros((len(self.influences), len(self.bones)))
        for v, row in enumerate(self.influences):
            for b, w in row:
                W[v, b] += w
        return W

    @classmethod
    def from_dense(cls, bones, weights: np.ndarray) -> "SkinFile":
        """Rows with the non-zero weights, largest first (ties by bone index)."""
        weights = np.asarray(weights, dtype=np.float64)
        influences = []
        for row in weights:
            nz = np.nonzero(row)[0]
            order = nz[np.argsort(-row[nz], kind="stable")]
            influences.append([(int(b), float(row[b])) for b in order])
        return cls(list(bones), influences)


def _skin_rows_run_together(rows: list[tuple[int, list[str]]]) -> bool:
    """Whether the weight tokens carry the vertex-id suffix (see the module notes).

    True when every multi-influence row's non-last weights end with the row's vertex id, the
    stripped tokens still parse, and stripping brings the row sums at least as close to 1.
    """
    dev_plain = dev_strip = 0.0
    multi = 0
    for _, tokens in rows:
        vid = tokens[0]
        ws = tokens[2::2]
        if len(ws) < 2:
            continue
        multi += 1
        stripped = []
        for w in ws[:-1]:
            if not w.endswith(vid):
                return False
            try:
                stripped.append(float(w[: -len(vid)]))
            except ValueError:
                return False
        try:
            plain = [float(w) for w in ws]
            last = float(ws[-1])
        except ValueError:
            return False
        dev_plain += abs(sum(plain) - 1.0)
        dev_strip += abs(sum(stripped) + last - 1.0)
    return multi > 0 and dev_strip <= dev_plain


def parse_skin(text: str, path: str | Path = "<skin>", num_vertices: int | None = None) -> SkinFile:
    """Parse the text of a ``.skin`` file (handles the run-together rows)."""
    path = Path(path)
    lines = _Lines(path, text, "skin file")
    lines.header(SKIN_HEADER)
    number, line, tokens = lines.next("'bones:'")
    if tokens != ["bones:"]:
        raise lines.error(f"expected 'bones:', found {_clip(line)!r}", number)
    number, line, bones = lines.next("the bone names")
    if bones == ["vertex", "weights:"]:
        raise lines.error("the bone list is empty", number)
    if len(set(bones)) != len(bones):
        raise lines.error("a bone name appears twice", number)
    number, line, tokens = lines.next("'vertex weights:'")
    if tokens != ["vertex", "weights:"]:
        raise lines.error(f"expected 'vertex weights:', found {_clip(line)!r}", number)
    rows = []
    while not lines.at_end():
        number, line, tokens = lines.next("a vertex row")
        if len(tokens) % 2 != 1:
            raise lines.error(f"a vertex row must be 'v b w b w ...', found {len(tokens)} fields: {_clip(line)!r}", number)
        rows.append((number, tokens))
    strip = _skin_rows_run_together(rows)
    B = len(bones)
    influences: list[list[tuple[int, float]]] = []
    for expected, (number, tokens) in enumerate(rows):
        vid = lines.int(tokens[0], number, "vertex id")
        if vid != expected:
            raise lines.error(f"vertex rows must be in order: expected vertex {expected}, found {tokens[0]!r}", number)
        row = []
        pairs = tokens[1:]
        for k in range(0, len(pairs), 2):
            b = lines.int(pairs[k], number, "bone index")
            if not 0 <= b < B:
                raise lines.error(f"bone index {b} is out of range (the file lists {B} bones)", number)
            w_tok = pairs[k + 1]
            if strip and k + 2 < len(pairs):
                w_tok = w_tok[: -len(tokens[0])]
            w = lines.float(w_tok, number, "weight")
            if not math.isfinite(w):
                raise lines.error(f"weight {pairs[k + 1]!r} is not finite", number)
            row.append((b, w))
        influences.append(row)
    if num_vertices is not None and len(influences) != num_vertices:
        raise lines.error(f"the file has {len(influences)} vertex rows but the template has {num_vertices} vertices")
    return SkinFile(list(bones), influences)


def read_skin(path: str | Path, num_vertices: int | None = None) -> SkinFile:
    """Read a ``.skin`` file; ``num_vertices`` checks the row count."""
    path = Path(path)
    return parse_skin(_read_text(path, "skin file"), path, num_vertices)


def format_skin(skin: SkinFile) -> list[str]:
    out = [SKIN_HEADER, "bones:", " ".join(skin.bones), "vertex weights:"]
    for v, row in enumerate(skin.influences):
        tokens: list = [v]
        for b, w in row:
            tokens += [int(b), float(w)]
        out.append(_join(tokens))
    return out


def write_skin(skin: SkinFile, path: str | Path) -> Path:
    """Write a ``.skin`` file with clean ``v b w b w ...`` rows."""
    return _write_text_lines(Path(path), format_skin(skin))


# ---------------------------------------------------------------------------------------------
# .motion
# ---------------------------------------------------------------------------------------------


@dataclass
class MotionFile:
    """The contents of a ``.motion`` file: ``frame_ids`` (T,) int64 and ``values`` (T,D)."""

    frame_ids: np.ndarray
    values: np.ndarray

    def __post_init__(self) -> None:
        self.values = np.asarray(self.values, dtype=np.float64)
        if self.values.ndim == 1:
            self.values = self.values[None]
        self.frame_ids = np.asarray(self.frame_ids, dtype=np.int64).reshape(-1)


def read_motion(path: str | Path, num_dofs: int | None = None) -> MotionFile:
    """Read a ``.motion`` file; ``num_dofs`` checks the column count."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, "motion file"), "motion file")
    lines.header(MOTION_HEADER)
    ids, rows = [], []
    width = None
    while not lines.at_end():
        number, line, tokens = lines.next("a frame row")
        if width is None:
            width = len(tokens)
            if num_dofs is not None and width != num_dofs + 1:
                raise lines.error(f"a frame row has {width - 1} DoF values but the skeleton has {num_dofs} DoFs", number)
        elif len(tokens) != width:
            raise lines.error(f"a frame row has {len(tokens)} fields, the first row had {width}", number)
        ids.append(lines.int(tokens[0], number, "frame index"))
        rows.append(lines.floats(tokens[1:], number, "DoF value"))
    D = (width - 1) if width is not None else (num_dofs or 0)
    return MotionFile(np.array(ids, dtype=np.int64), np.array(rows, dtype=np.float64).reshape(len(rows), D))


def write_motion(motion: MotionFile, path: str | Path) -> Path:
    """Write a ``.motion`` file: one row per frame, frame index then the DoF values."""
    out = [MOTION_HEADER]
    for fid, row in zip(motion.frame_ids, motion.values):
        out.append(_join([int(fid), *(float(v) for v in row)]))
    return _write_text_lines(Path(path), out)


# ---------------------------------------------------------------------------------------------
# .calibration
# ---------------------------------------------------------------------------------------------


@dataclass
class CalibrationFrame:
    """One ``frame`` block of an animated camera."""

    frame: int
    intrinsic: np.ndarray  # (4,4)
    extrinsic: np.ndarray  # (4,4) world -> camera, millimetres
    radial: float = 0.0


@dataclass
class CalibrationCamera:
    """One camera of a ``.calibration`` file (millimetres, row-major 4x4 matrices).

    Pinhole cameras use ``intrinsic`` (K in the upper-left 3x3), ``extrinsic`` (world->camera)
    and ``radial``. Fisheye (Scaramuzza/OCamCalib) cameras add ``polynomial_c2w``,
    ``polynomial_w2c``, ``image_circle_radius`` and ``affine`` ``(c, d, e)``. Animated cameras
    have ``frames`` instead of a single intrinsic/extrinsic. Unknown keyword lines are kept in
    ``extra`` (token lists) and written back.
    """

    name: str
    sensor: tuple[float, float] = (0.0, 0.0)
    size: tuple[int, int] = (0, 0)
    animated: bool = False
    intrinsic: np.ndarray | None = None
    extrinsic: np.ndarray | None = None
    radial: float = 0.0
    polynomial_c2w: list[float] | None = None
    polynomial_w2c: list[float] | None = None
    image_circle_radius: float | None = None
    affine: tuple[float, float, float] | None = None
    frames: list[CalibrationFrame] = field(default_factory=list)
    extra: list[list[str]] = field(default_factory=list)

    @property
    def is_fisheye(self) -> bool:
        return self.polynomial_c2w is not None or self.polynomial_w2c is not None


def read_calibration(path: str | Path) -> list[CalibrationCamera]:
    """Read a ``.calibration`` file (pinhole and fisheye cameras, static or animated)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, "calibration file"), "calibration file")
    lines.header(CALIBRATION_HEADER)
    cameras: list[CalibrationCamera] = []
    cam: CalibrationCamera | None = None
    frame: CalibrationFrame | None = None

    def expect(tokens, n, number, key):
        if len(tokens) != n + 1:
            raise lines.error(f"{key!r} takes {n} value(s), found {len(tokens) - 1}", number)
        return lines.floats(tokens[1:], number, f"{key} value")

    def matrix(tokens, number, key):
        return np.array(expect(tokens, 16, number, key)).reshape(4, 4)

    def polynomial(tokens, number, key):
        if len(tokens) < 2:
            raise lines.error(f"{key!r} needs a coefficient count", number)
        n = lines.int(tokens[1], number, f"{key} coefficient count", minimum=0)
        if len(tokens) != n + 2:
            raise lines.error(f"{key!r} announces {n} coefficients but has {len(tokens) - 2}", number)
        return lines.floats(tokens[2:], number, f"{key} coefficient")

    while not lines.at_end():
        number, line, tokens = lines.next("a camera entry")
        key = tokens[0]
        if key == "name":
            cam = CalibrationCamera(name=" ".join(tokens[1:]) if len(tokens) > 1 else str(len(cameras)))
            cameras.append(cam)
            frame = None
            continue
        if cam is None:
            raise lines.error(f"expected 'name', found {_clip(line)!r}", number)
        if key == "sensor":
            cam.sensor = tuple(expect(tokens, 2, number, key))
        elif key == "size":
            expect(tokens, 2, number, key)
            cam.size = (lines.int(tokens[1], number, "image width", minimum=0),
                        lines.int(tokens[2], number, "image height", minimum=0))
        elif key == "animated":
            expect(tokens, 1, number, key)
            cam.animated = bool(lines.int(tokens[1], number, "animated flag"))
        elif key == "frame":
            if not cam.animated:
                raise lines.error(f"camera {cam.name!r} is not animated but has a 'frame' entry", number)
            expect(tokens, 1, number, key)
            frame = CalibrationFrame(lines.int(tokens[1], number, "frame"), np.eye(4), np.eye(4))
            cam.frames.append(frame)
        elif key == "intrinsic":
            if frame is not None:
                frame.intrinsic = matrix(tokens, number, key)
            else:
                cam.intrinsic = matrix(tokens, number, key)
        elif key == "extrinsic":
            if frame is not None:
                frame.extrinsic = matrix(tokens, number, key)
            else:
                cam.extrinsic = matrix(tokens, number, key)
        elif key == "radial":
            value = expect(tokens, 1, number, key)[0]
            if frame is not None:
                frame.radial = value
            cam.radial = value
        elif key in ("polynomialC2W", "polynomial"):
            cam.polynomial_c2w = polynomial(tokens, number, key)
        elif key == "polynomialW2C":
            cam.polynomial_w2c = polynomial(tokens, number, key)
        elif key == "imageCircleRadius":
            cam.image_circle_radius = expect(tokens, 1, number, key)[0]
        elif key == "affine":
            cam.affine = tuple(expect(tokens, 3, number, key))
        else:
            cam.extra.append(list(tokens))
    for cam in cameras:
        if not cam.animated and (cam.intrinsic is None or cam.extrinsic is None):
            raise lines.error(f"camera {cam.name!r} lacks its intrinsic or extrinsic matrix")
    return cameras


def write_calibration(cameras: list[CalibrationCamera], path: str | Path) -> Path:
    """Write a ``.calibration`` file."""
    out = [CALIBRATION_HEADER]
    for cam in cameras:
        out.append(_join(["name", cam.name]))
        out.append(_join(["sensor", *cam.sensor]))
        out.append(_join(["size", *(int(s) for s in cam.size)]))
        out.append(_join(["animated", int(bool(cam.animated))]))
        if cam.animated:
            for fr in cam.frames:
                out.append(_join(["frame", int(fr.frame)]))
                out.append(_join(["intrinsic", *np.asarray(fr.intrinsic, dtype=float).reshape(16)]))
                out.append(_join(["extrinsic", *np.asarray(fr.extrinsic, dtype=float).reshape(16)]))
                out.append(_join(["radial", fr.radial]))
        else:
            out.append(_join(["intrinsic", *np.asarray(cam.intrinsic, dtype=float).reshape(16)]))
            out.append(_join(["extrinsic", *np.asarray(cam.extrinsic, dtype=float).reshape(16)]))
            out.append(_join(["radial", cam.radial]))
        if cam.polynomial_c2w is not None:
            out.append(_join(["polynomialC2W", len(cam.polynomial_c2w), *cam.polynomial_c2w]))
        if cam.polynomial_w2c is not None:
            out.append(_join(["polynomialW2C", len(cam.polynomial_w2c), *cam.polynomial_w2c]))
        if cam.image_circle_radius is not None:
            out.append(_join(["imageCircleRadius", cam.image_circle_radius]))
        if cam.affine is not None:
            out.append(_join(["affine", *cam.affine]))
        out.extend(" ".join(tokens) for tokens in cam.extra)
    return _write_text_lines(Path(path), out)


# ---------------------------------------------------------------------------------------------
# .character
# ---------------------------------------------------------------------------------------------


@dataclass
class CharacterFile:
    """The contents of a ``.character`` file: referenced paths (relative to the file, as written).

    ``other`` keeps any further ``keyword`` / ``path`` pairs in order.
    """

    skeleton: str
    mesh: str
    skin: str
    pose: str | None = None
    other: list[tuple[str, str]] = field(default_factory=list)


_CHARACTER_KEYS = ("skeleton", "mesh", "skin", "pose")


def read_character_file(path: str | Path) -> CharacterFile:
    """Read a ``.character`` file (keyword line, then a path line, per entry)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, "character file"), "character file")
    lines.header(CHARACTER_HEADER)
    found: dict[str, str] = {}
    other: list[tuple[str, str]] = []
    while not lines.at_end():
        number, line, tokens = lines.next("a keyword")
        keyword = tokens[0]
        if len(tokens) > 1:  # tolerate 'keyword path' on one line
            value = line.split(None, 1)[1].strip()
        else:
            _, value, _ = lines.next(f"the path after {keyword!r}")
        if keyword in _CHARACTER_KEYS:
            if keyword in found:
                raise lines.error(f"{keyword!r} appears twice", number)
            found[keyword] = value
        else:
            other.append((keyword, value))
    missing = [k for k in ("skeleton", "mesh", "skin") if k not in found]
    if missing:
        raise lines.error(f"the file names no {', '.join(missing)}")
    return CharacterFile(found["skeleton"], found["mesh"], found["skin"], found.get("pose"), other)


def write_character_file(cf: CharacterFile, path: str | Path) -> Path:
    out = [CHARACTER_HEADER]
    for key in _CHARACTER_KEYS:
        value = getattr(cf, key)
        if value is not None:
            out += [key, value]
    for key, value in cf.other:
        out += [key, value]
    return _write_text_lines(Path(path), out)


# ---------------------------------------------------------------------------------------------
# OBJ (template and embedded graph; Meshlab dialect)
# ---------------------------------------------------------------------------------------------


@dataclass
class ObjMesh:
    """A triangle OBJ as DDC uses it (file units; indices 0-based).

    Attributes:
        vertices: (N,3).
        colors: (N,3) vertex colours from ``v x y z r g b`` or None.
        normals: (Nn,3) ``vn`` rows or None.
        uvs: (T,2) ``vt`` rows or None.
        faces: (F,3) vertex indices.
        face_uvs_index: (F,3) ``vt`` index per corner or None.
        face_normals_index: (F,3) ``vn`` index per corner or None.
        mtllib, usemtl: the material references, if any.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    face_uvs_index: np.ndarray | None = None
    face_normals_index: np.ndarray | None = None
    mtllib: str | None = None
    usemtl: str | None = None

    def face_corner_uvs(self) -> np.ndarray:
        """(F,3,2) per-face-corner UVs (wedge UVs); zeros when the file has none."""
        if self.uvs is None or self.face_uvs_index is None:
            return np.zeros((len(self.faces), 3, 2))
        return self.uvs[self.face_uvs_index]

    def to_json(self, scale: float = 1.0) -> dict:
        """JSON-able dict (positions multiplied by ``scale``)."""
        def lst(a):
            return None if a is None else np.asarray(a).tolist()
        return {
            "vertices": lst(np.asarray(self.vertices) * scale), "faces": lst(self.faces), "colors": lst(self.colors),
            "normals": lst(self.normals), "uvs": lst(self.uvs), "face_uvs_index": lst(self.face_uvs_index),
            "face_normals_index": lst(self.face_normals_index), "mtllib": self.mtllib, "usemtl": self.usemtl,
        }

    @classmethod
    def from_json(cls, data: dict, scale: float = 1.0) -> "ObjMesh":
        def arr(key, dtype, cols):
            value = data.get(key)
            return None if value is None else np.asarray(value, dtype=dtype).reshape(-1, cols)
        return cls(vertices=arr("vertices", np.float64, 3) * scale, faces=arr("faces", np.int64, 3),
                   colors=arr("colors", np.float64, 3), normals=arr("normals", np.float64, 3),
                   uvs=arr("uvs", np.float64, 2), face_uvs_index=arr("face_uvs_index", np.int64, 3),
                   face_normals_index=arr("face_normals_index", np.int64, 3),
                   mtllib=data.get("mtllib"), usemtl=data.get("usemtl"))


def read_obj(path: str | Path, what: str = "OBJ file") -> ObjMesh:
    """Read a triangle OBJ (``v [rgb]``, ``vt``, ``vn``, ``f v[/vt][/vn]``; polygons fan-split)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, what), what)
    verts, colors, normals, uvs = [], [], [], []
    faces, fuv, fn = [], [], []
    mtllib = usemtl = None
    has_color = None
    corner_kind = None  # (has vt, has vn) of the first face corner, all must agree
    for number, line, tokens in lines.lines:
        key = tokens[0]
        if key.startswith("#"):
            continue
        if key == "v":
            if len(tokens) not in (4, 7):
                raise lines.error(f"a vertex needs 3 coordinates (and optionally r g b), found {len(tokens) - 1}", number)
            values = lines.floats(tokens[1:], number, "vertex value")
            with_color = len(values) == 6
            if has_color is None:
                has_color = with_color
            elif has_color != with_color:
                raise lines.error("some vertices have colours and others do not", number)
            verts.append(values[:3])
            if with_color:
                colors.append(values[3:])
        elif key == "vt":
            if len(tokens) < 3:
                raise lines.error("a texture coordinate needs u and v", number)
            uvs.append(lines.floats(tokens[1:3], number, "texture coordinate"))
        elif key == "vn":
            if len(tokens) != 4:
                raise lines.error("a normal needs 3 values", number)
            normals.append(lines.floats(tokens[1:], number, "normal value"))
        elif key == "f":
            if len(tokens) < 4:
                raise lines.error(f"a face needs at least 3 corners, found {len(tokens) - 1}", number)
            corners = []
            for corner in tokens[1:]:
                parts = corner.split("/")
                if len(parts) > 3 or not parts[0]:
                    raise lines.error(f"bad face corner {corner!r}", number)
                idx = []
                for part, count in zip(parts + [""] * (3 - len(parts)), (len(verts), len(uvs), len(normals))):
                    if not part:
                        idx.append(None)
                        continue
                    k = lines.int(part, number, "face index")
                    k = k - 1 if k > 0 else count + k
                    if not 0 <= k < count:
                        raise lines.error(f"face index {part!r} refers to an element not defined before it", number)
                    idx.append(k)
                kind = (idx[1] is not None, idx[2] is not None)
                if corner_kind is None:
                    corner_kind = kind
                elif kind != corner_kind:
                    raise lines.error("face corners mix forms (with and without texture/normal indices)", number)
                corners.append(idx)
            for k in range(1, len(corners) - 1):
                tri = (corners[0], corners[k], corners[k + 1])
                faces.append([c[0] for c in tri])
                fuv.append([c[1] for c in tri])
                fn.append([c[2] for c in tri])
        elif key == "mtllib":
            mtllib = line.split(None, 1)[1].strip() if len(tokens) > 1 else None
        elif key == "usemtl":
            usemtl = line.split(None, 1)[1].strip() if len(tokens) > 1 else None
        # o, g, s, l and others carry nothing DDC uses
    if not verts:
        raise lines.error("the file has no vertices")
    has_uv, has_n = corner_kind if corner_kind is not None else (False, False)
    return ObjMesh(
        vertices=np.array(verts, dtype=np.float64),
        faces=np.array(faces, dtype=np.int64).reshape(-1, 3),
        colors=np.array(colors, dtype=np.float64) if has_color else None,
        normals=np.array(normals, dtype=np.float64).reshape(-1, 3) if normals else None,
        uvs=np.array(uvs, dtype=np.float64).reshape(-1, 2) if uvs else None,
        face_uvs_index=np.array(fuv, dtype=np.int64).reshape(-1, 3) if has_uv else None,
        face_normals_index=np.array(fn, dtype=np.int64).reshape(-1, 3) if has_n else None,
        mtllib=mtllib, usemtl=usemtl)


def write_obj(mesh: ObjMesh, path: str | Path, comment: str | None = None) -> Path:
    """Write an OBJ in the Meshlab layout DDC files use.

    Per vertex ``vn`` then ``v`` when the normals are per vertex, then ``usemtl`` and the faces,
    each preceded by the ``vt`` rows it is the first to use (in index order).
    """
    path = Path(path)
    V, F = len(mesh.vertices), len(mesh.faces)
    out = [f"# {comment}" if comment else "# written by egorelight", f"# Vertices: {V}", f"# Faces: {F}"]
    if mesh.mtllib:
        out.append(f"mtllib {mesh.mtllib}")
    normals = mesh.normals
    fni = mesh.face_normals_index
    per_vertex_normals = (normals is not None and fni is not None and len(normals) == V
                          and np.array_equal(fni, mesh.faces))
    for v in range(V):
        if per_vertex_normals:
            out.append(_join(["vn", *normals[v]]))
        row = ["v", *mesh.vertices[v]]
        if mesh.colors is not None:
            row += list(mesh.colors[v])
        out.append(_join(row))
    if normals is not None and not per_vertex_normals:
        out.extend(_join(["vn", *n]) for n in normals)
    out.append(f"# {V} vertices")
    if mesh.usemtl:
        out.append(f"usemtl {mesh.usemtl}")
    uvs, fti = mesh.uvs, mesh.face_uvs_index
    use_uv = uvs is not None and fti is not None
    use_n = normals is not None and fni is not None
    next_vt = 0
    for f in range(F):
        if use_uv:
            need = int(fti[f].max())
            while next_vt <= need:
                out.append(_join(["vt", *uvs[next_vt]]))
                next_vt += 1
        corners = []
        for c in range(3):
            s = str(int(mesh.faces[f, c]) + 1)
            if use_uv and use_n:
                s += f"/{int(fti[f, c]) + 1}/{int(fni[f, c]) + 1}"
            elif use_uv:
                s += f"/{int(fti[f, c]) + 1}"
            elif use_n:
                s += f"//{int(fni[f, c]) + 1}"
            corners.append(s)
        out.append("f " + " ".join(corners))
    if uvs is not None:
        out.extend(_join(["vt", *uvs[k]]) for k in range(next_vt, len(uvs)))
    out.append(f"# {F} faces")
    return _write_text_lines(path, out)


def _uv_table(face_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner UVs (F,3,2) -> unique UV rows in first-use order and (F,3) indices."""
    flat = np.asarray(face_uvs, dtype=np.float64).reshape(-1, 2)
    if len(flat) == 0:
        return np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    unique, first, inverse = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return unique[order], rank[inverse.reshape(-1)].reshape(-1, 3)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.zeros_like(vertices)
    if len(faces):
        tri = vertices[faces]
        fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        for c in range(3):
            np.add.at(n, faces[:, c], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1), 0.0)


# ---------------------------------------------------------------------------------------------
# segmentation.txt / hand_segmentation.txt
# ---------------------------------------------------------------------------------------------


def read_labels(path: str | Path, num_vertices: int | None = None, what: str = "segmentation file") -> np.ndarray:
    """Read one integer label per vertex (one per line)."""
    path = Path(path)
    lines = _Lines(path, _read_text(path, what), what)
    labels = []
    for number, line, tokens in lines.lines:
        for t in tokens:
            labels.append(lines.int(t, number, "label"))
    if num_vertices is not None and len(labels) != num_vertices:
        raise lines.error(f"the file has {len(labels)} labels but the template has {num_vertices} vertices")
    return np.array(labels, dtype=np.int64)


def write_labels(labels: np.ndarray, path: str | Path) -> Path:
    return _write_text_lines(Path(path), [str(int(x)) for x in np.asarray(labels).reshape(-1)])


# ---------------------------------------------------------------------------------------------
# Character conversion
# ---------------------------------------------------------------------------------------------


def bone_joint_index(bone: str, joint_names) -> int | None:
    """The LAST joint whose name up to the first ``_`` equals ``bone`` (``LeftArm`` -> ``LeftArm_ry``)."""
    found = None
    for i, name in enumerate(joint_names):
        if _base_name(name) == bone:
            found = i
    return found


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
    bone_joints = []
    unbound = []
    for bone in skin.bones:
        j = bone_joint_index(bone, names)
        if j is None:
            unbound.append(bone)
        bone_joints.append(-1 if j is None else j)
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

    kp_joints, missing = [], []
    for kp in KEYPOINT_NAMES:
        j = keypoint_joint_index(kp, names)
        if j is None:
            missing.append(kp)
        kp_joints.append(-1 if j is None else j)
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


def _trim_trailing_blank(lines: list[str]) -> list[str]:
    lines = list(lines)
    while lines and not lines[-1].strip():
        lines.pop()
    return lines
