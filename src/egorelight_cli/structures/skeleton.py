"""The kinematic skeleton, with DDC (Skeletool) semantics.

A skeleton is a tree of single-parameter joints. Each joint is *revolute* (rotates about its
axis by its parameter, radians) or *prismatic* (translates along its axis by its parameter,
metres). Its local transform is ``translate(offset) @ motion(param)`` and its global transform is
``parent_global @ local``. Degrees of freedom (DoFs) drive joints linearly: every frame each
joint parameter starts at 0 and each DoF adds ``weight * value`` to every joint it names, i.e.
``joint_params = theta @ dof_joint_weights`` with ``dof_joint_weights`` of shape (D, J).

Units: metres and radians. DDC files are in millimetres; the importer divides offsets and
prismatic DoF weights by 1000 so that DoF values keep their DDC meaning (the root translation
DoFs, weight 1000 in DDC files, have weight 1 here and are in metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egorelight_cli.errors import EgorelightError

REVOLUTE = 0
PRISMATIC = 1
JOINT_TYPE_NAMES = ("revolute", "prismatic")


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A DDC-style skeleton.

    Attributes:
        joint_names: (J,) unique joint names, parents before children.
        parents: (J,) int64 parent index, -1 for a root.
        joint_types: (J,) int8, ``REVOLUTE`` or ``PRISMATIC``.
        axes: (J,3) float64 joint axes in the parent-offset frame (revolute axes unit length;
            prismatic axes as given, not normalised, as in DDC).
        offsets: (J,3) float64 translation from the parent joint, metres.
        dof_names: (D,) unique DoF names.
        dof_joint_weights: (D,J) float64; joint_params = theta @ dof_joint_weights.
        dof_limits: (D,2) float64 [min, max]; -inf/+inf where unlimited. FK does not enforce them.
        joint_scales: (J,) float64, the DDC per-joint ``scale`` column (kept for round trips).
    """

    joint_names: tuple[str, ...]
    parents: np.ndarray
    joint_types: np.ndarray
    axes: np.ndarray
    offsets: np.ndarray
    dof_names: tuple[str, ...]
    dof_joint_weights: np.ndarray
    dof_limits: np.ndarray
    joint_scales: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        J, D = len(self.joint_names), len(self.dof_names)
        object.__setattr__(self, "parents", np.asarray(self.parents, dtype=np.int64))
        object.__setattr__(self, "joint_types", np.asarray(self.joint_types, dtype=np.int8))
        object.__setattr__(self, "axes", np.asarray(self.axes, dtype=np.float64))
        object.__setattr__(self, "offsets", np.asarray(self.offsets, dtype=np.float64))
        object.__setattr__(self, "dof_joint_weights", np.asarray(self.dof_joint_weights, dtype=np.float64))
        object.__setattr__(self, "dof_limits", np.asarray(self.dof_limits, dtype=np.float64))
        scales = np.ones(J) if self.joint_scales is None else np.asarray(self.joint_scales, dtype=np.float64)
        object.__setattr__(self, "joint_scales", scales)
        expect = {
            "parents": (J,), "joint_types": (J,), "axes": (J, 3), "offsets": (J, 3),
            "dof_joint_weights": (D, J), "dof_limits": (D, 2), "joint_scales": (J,),
        }
        for name, shape in expect.items():
            if getattr(self, name).shape != shape:
                raise EgorelightError(f"skeleton field {name} has shape {getattr(self, name).shape}, expected {shape}")
        if len(set(self.joint_names)) != J:
            raise EgorelightError("skeleton joint names are not unique")
        if len(set(self.dof_names)) != D:
            raise EgorelightError("skeleton DoF names are not unique")
        idx = np.arange(J)
        if np.any(self.parents >= idx):
            bad = int(np.nonzero(self.parents >= idx)[0][0])
            raise EgorelightError(f"skeleton joint {self.joint_names[bad]} is listed before its parent")

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_dofs(self) -> int:
        return len(self.dof_names)

    def joint_index(self, name: str) -> int:
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise EgorelightError(f"skeleton has no joint named {name!r}") from None

    def dof_index(self, name: str) -> int:
        try:
            return self.dof_names.index(name)
        except ValueError:
            raise EgorelightError(f"skeleton has no DoF named {name!r}") from None

    def to_arrays(self, prefix: str = "skeleton_") -> dict[str, np.ndarray]:
        """Flat arrays for an npz payload (see :meth:`from_arrays`)."""
        return {
            f"{prefix}joint_names": np.array(self.joint_names, dtype=str),
            f"{prefix}parents": self.parents,
            f"{prefix}joint_types": self.joint_types,
            f"{prefix}axes": self.axes,
            f"{prefix}offsets": self.offsets,
            f"{prefix}dof_names": np.array(self.dof_names, dtype=str),
            f"{prefix}dof_joint_weights": self.dof_joint_weights,
            f"{prefix}dof_limits": self.dof_limits,
            f"{prefix}joint_scales": self.joint_scales,
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], prefix: str = "skeleton_") -> "Skeleton":
        return cls(
            joint_names=tuple(str(s) for s in arrays[f"{prefix}joint_names"]),
            parents=arrays[f"{prefix}parents"],
            joint_types=arrays[f"{prefix}joint_types"],
            axes=arrays[f"{prefix}axes"],
            offsets=arrays[f"{prefix}offsets"],
            dof_names=tuple(str(s) for s in arrays[f"{prefix}dof_names"]),
            dof_joint_weights=arrays[f"{prefix}dof_joint_weights"],
            dof_limits=arrays[f"{prefix}dof_limits"],
            joint_scales=arrays[f"{prefix}joint_scales"],
        )
