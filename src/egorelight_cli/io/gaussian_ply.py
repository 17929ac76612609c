"""3D Gaussians as the standard 3DGS PLY file, which common splat viewers open.

Layout (graphdeco-inria ``gaussian-splatting``; ``../shared/notes/appearance.md`` Sec. 2.7):
binary little-endian, one ``vertex`` element, every property float32, in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_44  opacity  scale_0..2  rot_0..3

* ``x y z``: means, world metres; ``nx ny nz``: zeros (written by Inria, ignored by viewers);
* ``f_dc``: the degree-0 spherical-harmonic coefficient, ``(rgb - 0.5) / C0`` with
  ``C0 = 0.28209479177387814``, so a viewer shows ``rgb = 0.5 + C0 f_dc``;
* ``f_rest``: higher SH bands, channel-major; this tool's colours are not SH, so they are zeros
  (45 of them: degree 3, the most widely accepted layout);
* ``opacity``: logit of the opacity; ``scale_*``: log of the standard deviations (metres);
* ``rot_*``: quaternion ``(w, x, y, z)``, normalised by readers.

An avatar's colours are HDR and lighting-dependent: the caller passes the display colour to
export (for example a tone-mapped render colour for one lighting).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.structures.gaussians import GaussianSet

SH_C0 = 0.28209479177387814
SH_REST = 45  # degree-3 spherical harmonics beyond the DC term, 15 per channel
PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(SH_REST)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)
_OPACITY_EPS = 1e-6  # opacities are clipped to [eps, 1 - eps] before the logit


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    return np.log(p) - np.log1p(-p)


def write_gaussian_ply(path: str | Path, gaussians: GaussianSet, rgb=None) -> None:
    """Write ``gaussians`` as a 3DGS PLY.

    Args:
        path: output ``.ply`` (written as given; atomic outputs are the caller's).
        gaussians: N Gaussians (any dtype/device; detached and converted to float32).
        rgb: (N,3) display colour in [0,1] to store; default the first three colour channels
            (a one-channel set is repeated as grey), clipped to [0,1].
    """
    from plyfile import PlyData, PlyElement

    means, quats, scales, opacities, colours = (t.detach().cpu().double().numpy() for t in gaussians.tensors())
    if rgb is None:
        rgb = colours[:, :3] if colours.shape[1] >= 3 else np.repeat(colours[:, :1], 3, axis=1)
    rgb = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)
    if rgb.shape != (len(gaussians), 3):
        raise EgorelightError(f"PLY export needs rgb of shape ({len(gaussians)}, 3), got {rgb.shape}", path)
    if np.any(scales <= 0) or not np.all(np.isfinite(scales)):
        raise EgorelightError("PLY export needs positive, finite scales", path)
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    if np.any(norms == 0):
        raise EgorelightError("PLY export needs non-zero quaternions", path)
    columns = [means, np.zeros_like(means), (rgb - 0.5) / SH_C0, np.zeros((len(means), SH_REST)),
               _logit(opacities)[:, None], np.log(scales), quats / norms]
    table = np.ascontiguousarray(np.concatenate(columns, axis=1), dtype=np.float32)
    vertices = np.empty(len(table), dtype=[(name, "<f4") for name in PROPERTIES])
    for i, name in enumerate(PROPERTIES):
        vertices[name] = table[:, i]
    PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<").write(str(path))


def read_gaussian_ply(path: str | Path) -> tuple[GaussianSet, np.ndarray]:
    """Read a 3DGS PLY (this tool's or another's).

    Returns:
        (gaussians, rgb): float32 :class:`GaussianSet` with ``colours`` the DC display colour
        (N,3) (``0.5 + C0 f_dc``, not clipped), and the same rgb as a numpy array. Higher SH
        bands, when present, are ignored.
    Raises:
        EgorelightError: not a PLY, truncated, or lacking a 3DGS property (named).
    """
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    try:
        data = PlyData.read(str(path))
        vertex = data["vertex"]
        names = [p.name for p in vertex.properties]
        missing = [n for n in PROPERTIES[:9] + PROPERTIES[-8:] if n not in names and n not in ("nx", "ny", "nz")]
        if missing:
            raise EgorelightError(f"not a 3D Gaussian PLY: lacks {', '.join(missing)}", path)
        table = {n: np.asarray(vertex[n], dtype=np.float64) for n in names}
    except EgorelightError:
        raise
    except (PlyParseError, KeyError, ValueError, EOFError, OSError, UnicodeDecodeError, IndexError) as error:
        raise EgorelightError(f"cannot read Gaussian PLY ({type(error).__name__}: {error})".replace("\n", " "),
                              path) from error

    def stack(*keys):
        return np.stack([table[k] for k in keys], axis=1)

    arrays = {
        "means": stack("x", "y", "z"),
        "quats": stack("rot_0", "rot_1", "rot_2", "rot_3"),
        "scales": np.exp(stack("scale_0", "scale_1", "scale_2")),
        "opacities": 1.0 / (1.0 + np.exp(-table["opacity"])),
        "colours": 0.5 + SH_C0 * stack("f_dc_0", "f_dc_1", "f_dc_2"),
    }
    bad = [name for name, array in arrays.items() if not np.all(np.isfinite(array))]
    if bad or np.any(np.linalg.norm(arrays["quats"], axis=1) == 0):
        raise EgorelightError(f"Gaussian PLY has non-finite or zero values in {', '.join(bad) or 'quats'}", path)
    gaussians = GaussianSet(*(torch.from_numpy(np.ascontiguousarray(arrays[k], dtype=np.float32))
                              for k in ("means", "quats", "scales", "opacities", "colours")))
    return gaussians, arrays["colours"]
