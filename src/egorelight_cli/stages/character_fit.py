"""``egorelight character fit-scan``: a person-specific template registered to a rest-pose scan.

A lab makes a subject's template by registering a default template to a 3D scan of the clothed
subject standing in the template's rest (rigging) pose. The scan is any triangle mesh (PLY/OBJ,
metres, +Y up, the template character's world frame and facing, roughly where the template
stands), with its own tessellation, noise and holes. :func:`fit_character_to_scan`:

1. aligns the template to the scan by a similarity (scale, translation, a small rotation),
2. fits the template surface non-rigidly: ICP through the character's embedded graph with a
   decreasing ARAP stiffness, then per-vertex refinement with a Laplacian regulariser
   (:mod:`egorelight_cli.geometry.registration`),
3. re-places the skeleton from the displacement of the vertices skinned to each joint
   (:mod:`egorelight_cli.geometry.skeleton_refit`; offsets in the skeleton's own
   parameterisation, keypoints moved with their joints),
4. carries over UVs, skinning weights and segmentation (same topology) and rebuilds the
   embedded graph on the fitted surface (as many nodes, farthest point sampling).

Options live in ``stages/character.yaml`` under ``fit_scan``. A scan that is missing, unreadable,
empty, without faces, with NaNs, in other units (scale factor outside ``checks``), far from the
template, or still far from it after the alignment is an :class:`EgorelightError` naming the scan.

Metrics (point-to-surface, mm, mean and p95, the direction in the key): ``fit_template_to_scan_mm``
(template vertices -> scan surface), ``fit_scan_to_template_mm`` (area-uniform scan samples ->
fitted template surface), the same for the only similarity-aligned template
(``unfitted_*``), the similarity, joint and keypoint displacements and the solver's iterations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egorelight_cli.config import Config
from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry import registration as reg
from egorelight_cli.geometry.skeleton_refit import RigRefit, refit_rig
from egorelight_cli.stages.character import embedded_graph_for
from egorelight_cli.structures.character import Character

SCAN_SUFFIXES = (".ply", ".obj")


# ------------------------------------------------------------------------------- reading a scan
def read_scan(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The scan's (vertices (V,3) float64, faces (F,3) int64) with its non-degenerate faces only.

    Raises:
        EgorelightError: naming ``path`` when it is missing, not PLY/OBJ, unreadable, or not a
            usable triangle mesh (no vertices, no faces, non-finite coordinates, zero area).
    """
    from egorelight_cli.io.meshes import read_mesh

    path = Path(path)
    if not path.is_file():
        raise EgorelightError("scan not found", path)
    if path.suffix.lower() not in SCAN_SUFFIXES:
        raise EgorelightError(f"the scan must be a triangle mesh in {' or '.join(SCAN_SUFFIXES)}", path)
    vertices, faces = read_mesh(path)
    if vertices.ndim != 2 or len(vertices) == 0:
        raise EgorelightError("the scan has no vertices (empty or unreadable mesh)", path)
    if faces.ndim != 2 or len(faces) == 0:
        raise EgorelightError("the scan has no faces (a point cloud?); fit-scan needs a triangle mesh", path)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise EgorelightError("the scan's faces index vertices that do not exist", path)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise EgorelightError(f"the scan has {int(bad.sum())} vertex(es) with NaN or infinite coordinates", path)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[area > 0]
    if len(faces) == 0:
        raise EgorelightError("the scan's faces all have zero area", path)
    return vertices, faces


# ---------------------------------------------------------------------------------- the fit
@dataclass(frozen=True)
class ScanFit:
    """A finished fit.

    Attributes:
        character: the fitted character.
        similarity: the coarse alignment (template -> scan).
        template_to_scan_m: (V,) distance of each fitted template vertex to the scan, metres.
        metrics: manifest metrics (see the module doc).
        timing: seconds per step.
    """

    character: Character
    similarity: reg.Similarity
    template_to_scan_m: np.ndarray
    metrics: dict
    timing: dict


def _stats_mm(distance_m: np.ndarray) -> dict:
    return {"mean": round(1000.0 * float(np.mean(distance_m)), 3),
            "p95": round(1000.0 * float(np.percentile(distance_m, 95)), 3)}


def _check_alignment(template: np.ndarray, scan: reg.ScanTarget, checks: Config, path: Path) -> None:
    """Units and placement, before the ICP: the height ratio and the bounding-box centres."""
    start = reg.initial_similarity(template, scan)
    if not checks.min_scale <= start.scale <= checks.max_scale:
        raise EgorelightError(
            f"the scan is {start.scale:.3g} times the template's height (allowed {checks.min_scale:g} to "
            f"{checks.max_scale:g}): is it in metres, +Y up?", path)
    centre = lambda x: 0.5 * (x.min(0) + x.max(0))  # noqa: E731
    offset = float(np.linalg.norm(centre(scan.vertices) - centre(template)))
    if offset > checks.max_offset_m:
        raise EgorelightError(
            f"the scan's centre is {offset:.2f} m from the template's (allowed {checks.max_offset_m:g} m): it must "
            "stand where the template character stands, in its world frame", path)


def _check_similarity(similarity: reg.Similarity, aligned_mean_m: float, cfg: Config, path: Path) -> None:
    checks = cfg.checks
    if not checks.min_scale <= similarity.scale <= checks.max_scale:
        raise EgorelightError(f"the aligned scale factor {similarity.scale:.3g} is outside {checks.min_scale:g} to "
                              f"{checks.max_scale:g}: is the scan in metres?", path)
    if similarity.rotation_deg > cfg.similarity.max_rotation_deg:
        raise EgorelightError(f"the scan is turned {similarity.rotation_deg:.0f} degrees from the template "
                              f"(allowed {cfg.similarity.max_rotation_deg:g}): it must face the way the "
                              "template faces", path)
    if aligned_mean_m > checks.max_aligned_error_m:
        raise EgorelightError(
            f"after alignment the scan is {100 * aligned_mean_m:.1f} cm from the template on average (allowed "
            f"{100 * checks.max_aligned_error_m:g} cm): is it a body scan in the template's rest pose?", path)


def _graph_schedule(cfg: Config) -> reg.GraphFitSchedule:
    graph = cfg.graph
    return reg.GraphFitSchedule(stiffness=tuple(graph.stiffness), max_distance=tuple(graph.max_distance),
                                steps=int(graph.steps), min_normal_dot=float(cfg.min_normal_dot),
                                point_weight=float(cfg.point_weight))


def fit_character_to_scan(character: Character, scan_vertices: np.ndarray, scan_faces: np.ndarray, cfg: Config,
                          scan_path: str | Path = "scan", seed: int = 0) -> ScanFit:
    """Register ``character`` to a scan (module doc) and return the fitted character.

    Args:
        character: the template character.
        scan_vertices: (M,3) metres; scan_faces: (G,3) (as :func:`read_scan` returns them).
        cfg: the ``fit_scan`` config section.
        scan_path: named in errors.
        seed: seeds the scan's surface samples.
    Raises:
        EgorelightError: the scan is in other units, far from or unlike the template.
    """
    path = Path(scan_path)
    timing: dict[str, float] = {}
    clock = time.perf_counter()
    faces = character.faces
    scan = reg.ScanTarget.from_mesh(scan_vertices, scan_faces, int(cfg.scan_samples), seed=seed)
    _check_alignment(character.vertices, scan, cfg.checks, path)
    rules = reg.PairRules(float(cfg.similarity.max_distance), float(cfg.min_normal_dot), float(cfg.point_weight))
    similarity_log = reg.FitLog()
    similarity = reg.align_similarity(character.vertices, faces, scan, int(cfg.similarity.iterations), rules,
                                      rotation=bool(cfg.similarity.rotation), log=similarity_log)
    aligned = similarity.apply(character.vertices)
    unfitted = reg.surface_distances(aligned, faces, scan)
    _check_similarity(similarity, float(np.mean(unfitted[1])), cfg, path)
    timing["similarity_s"] = time.perf_counter() - clock

    clock = time.perf_counter()
    graph_log = reg.FitLog()
    fitted = reg.fit_embedded_graph(aligned, faces, character.graph, scan, _graph_schedule(cfg), graph_log)
    timing["graph_fit_s"] = time.perf_counter() - clock
    clock = time.perf_counter()
    refine_log = reg.FitLog()
    refine = cfg.refine
    fitted = reg.refine_vertices(fitted, faces, scan, int(refine.iterations), float(refine.laplacian_weight),
                                 reg.PairRules(float(refine.max_distance), float(cfg.min_normal_dot),
                                               float(cfg.point_weight)), refine_log)
    timing["refine_s"] = time.perf_counter() - clock

    clock = time.perf_counter()
    rig = refit_rig(character, fitted, similarity.scale * similarity.R, float(cfg.joint_reg_length))
    num_nodes = int(cfg.graph_nodes) or character.graph.num_nodes
    fitted_character = _fitted_character(character, fitted, rig.skeleton, rig.keypoint_offsets,
                                         embedded_graph_for(fitted, faces, num_nodes), similarity, path)
    timing["rig_s"] = time.perf_counter() - clock
    final = reg.surface_distances(fitted, faces, scan)
    metrics = _metrics(character, similarity, unfitted, final, rig, (similarity_log, graph_log, refine_log), scan)
    return ScanFit(fitted_character, similarity, final[0], metrics, {k: round(v, 3) for k, v in timing.items()})


def _fitted_character(character: Character, vertices: np.ndarray, skeleton, keypoint_offsets: np.ndarray, graph,
                      similarity: reg.Similarity, scan_path: Path) -> Character:
    extras = dict(character.extras)
    extras["fit_scan"] = {"template": character.name, "scan": scan_path.name,
                          "similarity": {"scale": similarity.scale, "rotation": similarity.R.tolist(),
                                         "translation_m": similarity.t.tolist()}}
    return Character(
        name=f"{character.name}_fit", skeleton=skeleton, rest_theta=character.rest_theta, vertices=vertices,
        faces=character.faces, face_uvs=character.face_uvs, skin_bone_names=character.skin_bone_names,
        skin_bone_joints=character.skin_bone_joints, skin_weights=character.skin_weights,
        keypoint_names=character.keypoint_names, keypoint_joints=character.keypoint_joints,
        keypoint_offsets=keypoint_offsets, graph=graph, segmentation=character.segmentation,
        segmentation_names=character.segmentation_names, hand_segmentation=character.hand_segmentation,
        vertex_colors=character.vertex_colors, extras=extras)


def _distance_stats_mm(a: np.ndarray, b: np.ndarray, names: tuple[str, ...]) -> dict:
    """Mean, p95 and max (with the joint's name) of |a - b| over rows (J,3), millimetres."""
    mm = 1000.0 * np.linalg.norm(a - b, axis=1)
    worst = int(np.argmax(mm))
    return {"mean": round(float(mm.mean()), 3), "p95": round(float(np.percentile(mm, 95)), 3),
            "max": round(float(mm[worst]), 3), "max_joint": names[worst]}


def _metrics(character: Character, similarity: reg.Similarity, unfitted, final, rig: RigRefit,
             logs: tuple[reg.FitLog, reg.FitLog, reg.FitLog], scan: reg.ScanTarget) -> dict:
    names = character.skeleton.joint_names
    similarity_log, graph_log, refine_log = logs
    return {
        "fit_template_to_scan_mm": _stats_mm(final[0]),
        "fit_scan_to_template_mm": _stats_mm(final[1]),
        "unfitted_template_to_scan_mm": _stats_mm(unfitted[0]),
        "unfitted_scan_to_template_mm": _stats_mm(unfitted[1]),
        "similarity": {"scale": round(similarity.scale, 6), "rotation_deg": round(similarity.rotation_deg, 3),
                       "translation_m": [round(float(v), 6) for v in similarity.t]},
        "joint_displacement_mm": _distance_stats_mm(rig.joints_after, rig.joints_before, names),
        "joint_displacement_after_alignment_mm": _distance_stats_mm(
            rig.joints_after, similarity.apply(rig.joints_before), names),
        "iterations": {"similarity": similarity_log.steps, "graph_gauss_newton": graph_log.steps,
                       "refine": refine_log.steps},
        "last_pairs": {"template_to_scan": refine_log.pair_counts[-1][0] if refine_log.steps else 0,
                       "scan_to_template": refine_log.pair_counts[-1][1] if refine_log.steps else 0},
        "scan_vertices": int(len(scan.vertices)), "scan_faces": int(len(scan.faces)),
        "scan_samples": int(len(scan.samples)),
    }


def fit_units() -> dict:
    """The manifest ``units`` entries of the fit metrics."""
    return {
        "fit_template_to_scan_mm": "mm, distance of the fitted template's vertices to the scan surface (mean, p95)",
        "fit_scan_to_template_mm": "mm, distance of area-uniform scan samples to the fitted template surface",
        "unfitted_template_to_scan_mm": "mm, as fit_template_to_scan_mm for the template only similarity-aligned",
        "unfitted_scan_to_template_mm": "mm, as fit_scan_to_template_mm for the template only similarity-aligned",
        "joint_displacement_mm": "mm, how far each joint moved from the template's (mean, p95, max)",
        "joint_displacement_after_alignment_mm": "mm, the same from the similarity-aligned template's joints",
        "last_pairs": "closest-point pairs kept in the last refinement step (template vertices, scan samples)",
    }
