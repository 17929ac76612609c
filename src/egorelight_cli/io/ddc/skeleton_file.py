"""``.skeleton`` files: contents, parsing, writing and conversion to/from :class:`Skeleton`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.ddc.text import MM_PER_M, SKELETON_HEADER, _clip, _join, _Lines, _read_text, _to_mm, _write_text_lines
from egorelight_cli.structures.skeleton import JOINT_TYPE_NAMES, PRISMATIC, REVOLUTE, Skeleton


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
