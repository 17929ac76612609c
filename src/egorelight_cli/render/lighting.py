"""The lighting of a frame as lightstage light intensities, and a differentiable S(E).

A lighting condition is an (L,3) array of light intensities (``render/lightstage.py``). Stages
get it from:

* a capture's ``sequence.json`` light entry (pattern ``flat``/``flash``, ``dark``, ``olat`` or
  ``envmap`` + ``yaw_deg``, times ``scale``) with the capture's own ``envmaps/<name>.exr``:
  :func:`light_intensities` and :class:`CaptureEnvmaps`;
* any environment map (a user's file, an ``envmap`` artifact): the paper's ``S(E)``,
  :meth:`LightStage.envmap_to_intensities` in numpy, or :class:`EnvmapPooling` in torch, which
  is the same solid-angle-weighted average written as a fixed sparse (L, H*W) matrix, so that
  gradients flow from light intensities back to the map (``envmap``'s inverse rendering).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.equirect import equirect_bilinear_weights, equirect_solid_angles, yaw_rotation
from egorelight_cli.render.lightstage import LightStage

LIGHT_PATTERNS = ("flat", "flash", "dark", "olat", "group", "envmap")


def light_intensities(lightstage: LightStage, entry: Mapping, envmaps: Mapping[str, np.ndarray]) -> np.ndarray:
    """(L,3) lighting condition of one ``sequence.json`` light entry.

    Args:
        lightstage: the capture's lights.
        entry: ``{"pattern": ..., "scale": s, "olat_index": i, "envmap": name, "yaw_deg": yaw}``
            (``"light_ids": [...]`` for ``group``: those lights at the flat level).
        envmaps: name -> (H,2H,3) map, for ``envmap`` patterns (e.g. :class:`CaptureEnvmaps`).
    """
    pattern, scale = entry.get("pattern"), float(entry.get("scale", 1.0))
    if pattern in ("flat", "flash"):
        return lightstage.flat(scale)
    if pattern == "dark":
        return np.zeros((lightstage.num_lights, 3))
    if pattern == "olat":
        return lightstage.olat(int(entry["olat_index"]), scale)
    if pattern == "group":
        ids = np.asarray(entry.get("light_ids", []), dtype=np.int64)
        if ids.size == 0 or ids.min() < 0 or ids.max() >= lightstage.num_lights:
            raise EgorelightError(f"group light entry needs light_ids in 0..{lightstage.num_lights - 1}")
        out = np.zeros((lightstage.num_lights, 3))
        out[ids] = lightstage.flat(scale)[ids]
        return out
    if pattern == "envmap":
        name = entry.get("envmap")
        if name not in envmaps:
            raise EgorelightError(f"light entry names environment map {name!r}, which the capture does not have")
        return scale * lightstage.envmap_to_intensities(envmaps[name], float(entry.get("yaw_deg", 0.0)))
    raise EgorelightError(f"unknown light pattern {pattern!r}; expected one of {', '.join(LIGHT_PATTERNS)}")


class CaptureEnvmaps(Mapping):
    """A capture's ``envmaps/<name>.exr``, loaded on first use (name -> (H,2H,3) float32)."""

    def __init__(self, root: str | Path):
        self.directory = Path(root) / "envmaps"
        self._loaded: dict[str, np.ndarray] = {}

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._loaded:
            from egorelight_cli.render.envmaps import load_envmap

            path = self.directory / f"{name}.exr"
            if not path.is_file():
                raise KeyError(name)
            self._loaded[name] = load_envmap(path)
        return self._loaded[name]

    def __contains__(self, name) -> bool:
        return isinstance(name, str) and (name in self._loaded or (self.directory / f"{name}.exr").is_file())

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(p.stem for p in self.directory.glob("*.exr")))

    def __len__(self) -> int:
        return len(list(self.directory.glob("*.exr")))


def envmap_pooling_matrix(lightstage: LightStage, height: int, width: int | None = None,
                          yaw_deg: float = 0.0) -> torch.Tensor:
    """The sparse (L, H*W) float64 matrix ``S`` with ``S @ E.reshape(H*W, 3) = S(E)``.

    Row ``l`` holds the solid-angle weights of the texels nearest light ``l`` (normalised to
    sum to 1); a light whose cell holds no texel centre gets the bilinear weights of its
    direction, exactly as :meth:`LightStage.envmap_to_intensities` (the tests hold them equal).
    """
    width = 2 * height if width is None else width
    nearest = lightstage._texel_assignment(height, width, yaw_deg)
    weights = equirect_solid_angles(height, width).reshape(-1)
    total = np.bincount(nearest, weights=weights, minlength=lightstage.num_lights)
    filled = total > 0
    rows = [nearest[filled[nearest]]]
    cols = [np.flatnonzero(filled[nearest])]
    values = [weights[cols[0]] / total[rows[0]]]
    empty = np.flatnonzero(~filled)
    if empty.size:
        directions = lightstage.directions[empty] @ yaw_rotation(yaw_deg)
        indices, bilinear = equirect_bilinear_weights(directions, height, width)
        rows.append(np.repeat(empty, 4))
        cols.append(indices.reshape(-1))
        values.append(bilinear.reshape(-1))
    index = torch.from_numpy(np.stack([np.concatenate(rows), np.concatenate(cols)]))
    matrix = torch.sparse_coo_tensor(index, torch.from_numpy(np.concatenate(values)),
                                     (lightstage.num_lights, height * width), check_invariants=True)
    return matrix.coalesce()


class EnvmapPooling(torch.nn.Module):
    """Differentiable ``S(E)``: an equirect map (H,2H,3) tensor -> (L,3) light intensities.

    Built once per map size and yaw; ``forward`` is one sparse matrix product.
    """

    def __init__(self, lightstage: LightStage, height: int, width: int | None = None, yaw_deg: float = 0.0):
        super().__init__()
        matrix = envmap_pooling_matrix(lightstage, height, width, yaw_deg)
        self.shape = (height, matrix.shape[1] // height)
        self.register_buffer("matrix", matrix, persistent=False)

    def forward(self, envmap: torch.Tensor) -> torch.Tensor:
        if tuple(envmap.shape[:2]) != self.shape or envmap.dim() != 3:
            raise EgorelightError(f"S(E) was built for {self.shape} maps, got {tuple(envmap.shape)}")
        flat = envmap.reshape(-1, envmap.shape[2])
        return torch.sparse.mm(self.matrix.to(flat.dtype), flat)
