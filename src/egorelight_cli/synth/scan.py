"""A rest-pose 3D scan of the clothed subject, as a lab's scanner would give it (``capture/scan/``).

The subject stands in its rigging pose without the headset; the scanner sees the outer surface
(skin and garments at rest, eased but not folded) and returns it

* with its own tessellation: isotropic remeshing (pymeshlab) at ``edge_m`` (the subject's own
  triangles are not reproduced),
* with noise: ``noise_m`` along the normals, smooth over a couple of centimetres plus a fine part,
* with holes where scanners lose the surface: ``holes`` random patches of ``hole_radius_m`` are
  dropped, and the soles are never seen.

It is written to ``capture/scan/scan.ply`` (a capture input: ``character fit-scan`` registers the
template to it). Nothing about it is ground truth.
"""

from __future__ import annotations

import numpy as np

from egorelight_cli.geometry.normals import vertex_normals
from egorelight_cli.runtime import single_threaded_openmp
from egorelight_cli.synth.appearance import value_noise
from egorelight_cli.synth.subject import Subject


def isotropic_remesh(vertices: np.ndarray, faces: np.ndarray, edge_m: float, iterations: int = 3) -> tuple:
    """(vertices (V',3) float64, faces (F',3) int64) remeshed to about ``edge_m`` edges (pymeshlab)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    with single_threaded_openmp():
        ms.meshing_merge_close_vertices(threshold=pymeshlab.PureValue(1e-5))
        ms.meshing_isotropic_explicit_remeshing(iterations=int(iterations),
                                                targetlen=pymeshlab.PureValue(float(edge_m)))
    mesh = ms.current_mesh()
    return mesh.vertex_matrix().astype(np.float64), mesh.face_matrix().astype(np.int64)


def scan_subject(subject: Subject, cfg, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The scan (vertices (V,3), faces (F,3)) of the subject from the ``scan`` config section."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CA]))
    v, f = isotropic_remesh(subject.rest_vertices(), subject.faces, float(cfg.edge_m))
    n = vertex_normals(v, f)
    noise = float(cfg.noise_m) * (0.7 * value_noise(v, 0.03, rng) + 0.3 * rng.normal(size=len(v)))
    v = v + noise[:, None] * n
    keep = np.ones(len(f), bool)
    centres = v[f].mean(axis=1)
    keep &= centres[:, 1] > 0.004  # soles
    for _ in range(int(cfg.holes)):
        centre = centres[rng.integers(len(centres))]
        keep &= np.linalg.norm(centres - centre, axis=1) > float(cfg.hole_radius_m)
    f = f[keep]
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]
