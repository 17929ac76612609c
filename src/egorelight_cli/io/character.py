"""``character.npz``: a :class:`Character` as one self-describing npz payload, and the shipped
default character."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egorelight_cli.errors import EgorelightError
from egorelight_cli.io.npz import read_kind_npz, read_npz, write_npz
from egorelight_cli.resources import data_dir
from egorelight_cli.structures.character import Character

CHARACTER_KIND = "egorelight/character"
CHARACTER_VERSION = 1
DEFAULT_CHARACTER_FILE = "default_character.npz"

#: Arrays stored in single precision / 32-bit ints by ``compact`` writes (the Character casts
#: them back to float64/int64 on load).
COMPACT_FLOAT32 = ("vertices", "face_uvs", "skin_weights", "graph_vertex_node_weight", "vertex_colors")
COMPACT_INT32 = ("faces", "graph_vertex_node_index", "graph_edges", "graph_faces", "graph_node_vertex",
                 "segmentation", "hand_segmentation")


def character_arrays(character: Character, compact: bool = False) -> dict[str, np.ndarray]:
    """``character.to_arrays()``, with the large arrays in float32/int32 when ``compact``."""
    arrays = character.to_arrays()
    if compact:
        for name in COMPACT_FLOAT32:
            if name in arrays:
                arrays[name] = np.ascontiguousarray(arrays[name], dtype=np.float32)
        for name in COMPACT_INT32:
            if name in arrays:
                arrays[name] = np.ascontiguousarray(arrays[name], dtype=np.int32)
    return arrays


def write_character_npz(path: str | Path, character: Character, compact: bool = False, **meta) -> None:
    """Write ``character`` with a ``__meta__`` entry (deterministic bytes for equal content)."""
    counts = {"vertices": character.num_vertices, "faces": int(character.faces.shape[0]),
              "bones": len(character.skin_bone_names), "dofs": character.skeleton.num_dofs,
              "joints": character.skeleton.num_joints, "graph_nodes": character.graph.num_nodes}
    write_npz(path, character_arrays(character, compact),
              {"kind": CHARACTER_KIND, "version": CHARACTER_VERSION, "units": {"length": "m", "angle": "rad"},
               "name": character.name, "counts": counts, **meta})


def read_character_arrays(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """The raw arrays and ``__meta__`` of a character npz, kind and version checked."""
    arrays, meta = read_kind_npz(path, CHARACTER_KIND, CHARACTER_VERSION, check_finite=True,
                                 allow_inf=("skeleton_dof_limits",))  # +-inf = no limit
    return arrays, meta


def read_character_npz(path: str | Path) -> Character:
    """Read a ``character.npz``; wrong kind/version or missing fields are EgorelightErrors."""
    arrays, _ = read_character_arrays(path)
    try:
        return Character.from_arrays(arrays)
    except EgorelightError as exc:
        raise EgorelightError(exc.message, path) from None
    except (ValueError, TypeError, IndexError) as exc:
        raise EgorelightError(f"invalid character payload ({type(exc).__name__}: {exc})", path) from None


def default_character_path() -> Path:
    """The shipped default character (built by ``egorelight character from-makehuman``)."""
    return data_dir() / DEFAULT_CHARACTER_FILE


def load_default_character() -> Character:
    """The shipped default character; needs no ``anny``."""
    path = default_character_path()
    if not path.is_file():
        raise EgorelightError("the shipped default character is missing from the installation; rebuild it "
                              "with `python -m egorelight_cli.stages.character`", path)
    return read_character_npz(path)
