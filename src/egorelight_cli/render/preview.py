"""Preview images a person can look at: the character's rest pose with skeleton and keypoints,
and a template fitted to a scan coloured by its distance to it."""

from __future__ import annotations

import cv2
import numpy as np

from egorelight_cli.geometry.cameras import Camera, look_at, project_world
from egorelight_cli.render.raster import rasterize
from egorelight_cli.structures.character import Character
from egorelight_cli.structures.keypoints import BODY_SLICE, LEFT_HAND_SLICE, RIGHT_HAND_SLICE

#: RGB colours for LIP human-parsing labels (others: grey).
LABEL_COLOURS = {
    2: (60, 40, 30), 5: (70, 110, 190), 9: (60, 60, 70), 13: (225, 180, 150), 14: (215, 170, 140),
    15: (215, 170, 140), 16: (210, 165, 135), 17: (210, 165, 135), 18: (40, 35, 35), 19: (40, 35, 35),
}
DEFAULT_COLOUR = (190, 190, 190)
KEYPOINT_COLOURS = {"body": (255, 60, 40), "left": (40, 200, 60), "right": (40, 120, 255)}


def framing_camera(vertices: np.ndarray, view_dir: np.ndarray, width: int, height: int, name: str) -> Camera:
    """A pinhole camera looking along ``view_dir`` at the mesh's bounding box, filling ~90% of
    the image height."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre = 0.5 * (lo + hi)
    extent = float(np.max(hi - lo))
    distance = 3.0 * extent
    fy = 0.9 * height * distance / max(float(hi[1] - lo[1]), 1e-6)
    fy = min(fy, 0.9 * width * distance / max(extent, 1e-6) * 2.0)
    K = np.array([[fy, 0, (width - 1) / 2], [0, fy, (height - 1) / 2], [0, 0, 1]])
    eye = centre - distance * np.asarray(view_dir, dtype=np.float64)
    return Camera(model="pinhole", K=K, dist=np.zeros(5), width=width, height=height,
                  T_cam_from_world=look_at(eye, centre), name=name)


def shade_mesh(character: Character, vertices: np.ndarray, camera: Camera) -> np.ndarray:
    """(H,W,3) uint8: segmentation colours with head-light Lambert shading on white."""
    raster = rasterize(vertices, character.faces, camera)
    palette = np.array([LABEL_COLOURS.get(int(l), DEFAULT_COLOUR) for l in character.segmentation], np.float32)
    face_colour = palette[character.faces].mean(axis=1)
    colour = np.full((camera.height, camera.width, 3), 255.0, np.float32)
    mask = raster.mask
    to_camera = camera.centre_world[None, :] - raster.points[mask]
    to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
    lambert = np.abs(np.sum(raster.normal[mask] * to_camera, axis=1))
    colour[mask] = face_colour[raster.face_id[mask]] * (0.35 + 0.65 * lambert)[:, None]
    return np.clip(colour, 0, 255).astype(np.uint8)


def root_translation_joints(parents: np.ndarray, joint_types: np.ndarray) -> np.ndarray:
    """(J,) bool: the prismatic chain at the root (global translation), not a body segment."""
    from egorelight_cli.structures.skeleton import PRISMATIC

    flags = np.zeros(len(parents), dtype=bool)
    for j, parent in enumerate(parents):
        flags[j] = joint_types[j] == PRISMATIC and (parent < 0 or flags[parent])
    return flags


def draw_skeleton(image: np.ndarray, joints_world: np.ndarray, parents: np.ndarray, joint_types: np.ndarray,
                  keypoints_world: np.ndarray, camera: Camera) -> None:
    """Draw bones (parent-child segments longer than 1 mm, without the root translation chain)
    and the 57 keypoints in place."""
    scale = max(1, image.shape[0] // 400)
    joints_px = np.asarray(project_world(camera, joints_world))
    skip = root_translation_joints(parents, joint_types)
    for child, parent in enumerate(parents):
        if parent < 0 or skip[child] or np.linalg.norm(joints_world[child] - joints_world[parent]) < 1e-3:
            continue
        a, b = joints_px[child], joints_px[parent]
        if np.all(np.isfinite([a, b])):
            cv2.line(image, tuple(int(round(v)) for v in a), tuple(int(round(v)) for v in b), (30, 30, 30),
                     scale, cv2.LINE_AA)
    keypoints_px = np.asarray(project_world(camera, keypoints_world))
    groups = (("body", BODY_SLICE, 4), ("left", LEFT_HAND_SLICE, 2), ("right", RIGHT_HAND_SLICE, 2))
    for group, part, radius in groups:
        for point in keypoints_px[part]:
            if np.all(np.isfinite(point)):
                cv2.circle(image, (int(round(point[0])), int(round(point[1]))), radius * scale,
                           KEYPOINT_COLOURS[group], -1, cv2.LINE_AA)


def facing_direction(keypoints: np.ndarray) -> np.ndarray:
    """Unit horizontal direction the character faces, from ankle-to-toe vectors (57 keypoints).

    Characters differ (the shipped default faces -Z, the public DDC example +Z), so previews
    derive it instead of assuming one.
    """
    from egorelight_cli.structures.keypoints import KEYPOINT_NAMES

    index = KEYPOINT_NAMES.index
    forward = sum(keypoints[index(f"{s}ToeBase")] - keypoints[index(f"{s}Foot")] for s in ("Left", "Right"))
    forward = np.array([forward[0], 0.0, forward[2]])
    norm = np.linalg.norm(forward)
    return forward / norm if norm > 1e-6 else np.array([0.0, 0.0, -1.0])


def character_preview_image(character: Character, width: int = 384, height: int = 640) -> np.ndarray:
    """(height, 2*width, 3) uint8 RGB: front and side view of the rest pose with the skeleton
    and keypoints (body red, left hand green, right hand blue), with a caption."""
    import torch

    from egorelight_cli.geometry.skeleton import forward_kinematics, keypoint_positions

    theta = torch.as_tensor(character.rest_theta, dtype=torch.float64)
    T_world_from_joint = forward_kinematics(theta, character.skeleton)
    joints = T_world_from_joint[..., :3, 3].numpy()
    keypoints = keypoint_positions(theta, character, T_world_from_joint).numpy()
    views = []
    forward = facing_direction(keypoints) if character.has_standard_keypoints else np.array([0.0, 0.0, -1.0])
    side = np.cross(forward, [0.0, 1.0, 0.0])  # the character's right
    for name, view_dir in (("front", -forward), ("side", side)):
        camera = framing_camera(character.vertices, view_dir, width, height, name)
        image = shade_mesh(character, character.vertices, camera)
        draw_skeleton(image, joints, character.skeleton.parents, character.skeleton.joint_types, keypoints, camera)
        views.append(image)
    image = np.concatenate(views, axis=1)
    caption = (f"{character.name}: {character.num_vertices} verts, {character.skeleton.num_dofs} DoF, "
               f"{len(character.skin_bone_names)} bones, {character.graph.num_nodes} graph nodes")
    cv2.putText(image, caption, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return image


# -------------------------------------------------------------- surfaces coloured by distance
def distance_colours(distance: np.ndarray, max_distance: float) -> np.ndarray:
    """(N,3) float32 RGB in [0,255] for distances (N,): blue (0) -> red (``max_distance`` and
    more), OpenCV's JET map."""
    level = np.clip(np.asarray(distance, np.float64) / max_distance, 0, 1) * 255
    bgr = cv2.applyColorMap(level.astype(np.uint8)[:, None], cv2.COLORMAP_JET)[:, 0]
    return bgr[:, ::-1].astype(np.float32)


def shade_vertex_colours(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray, camera: Camera,
                         ambient: float = 0.45) -> np.ndarray:
    """(H,W,3) uint8: per-vertex RGB colours (V,3) in [0,255] interpolated over the faces, with
    head-light Lambert shading (``ambient + (1 - ambient) |n.l|``) on white."""
    raster = rasterize(vertices, faces, camera)
    image = np.full((camera.height, camera.width, 3), 255.0, np.float32)
    mask = raster.mask
    corner = np.asarray(colours, np.float32)[np.asarray(faces)[raster.face_id[mask]]]  # (P,3,3)
    colour = np.einsum("pkc,pk->pc", corner, raster.barycentrics[mask])
    to_camera = camera.centre_world[None] - raster.points[mask]
    to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
    lambert = np.abs(np.sum(raster.normal[mask] * to_camera, axis=1))
    image[mask] = colour * (ambient + (1.0 - ambient) * lambert)[:, None]
    return np.clip(image, 0, 255).astype(np.uint8)


def scan_fit_image(character: Character, scan_vertices: np.ndarray, scan_faces: np.ndarray, distance: np.ndarray,
                   max_distance: float = 0.01, width: int = 384, height: int = 640) -> np.ndarray:
    """(height, 3*width, 3) uint8 RGB: the scan (grey, front) and the character fitted to it
    (front with its skeleton and keypoints, and side), coloured by ``distance`` (V,) metres of
    each template vertex to the scan (blue 0 -> red ``max_distance``), with a caption."""
    import torch

    from egorelight_cli.geometry.skeleton import forward_kinematics, keypoint_positions

    theta = torch.as_tensor(character.rest_theta, dtype=torch.float64)
    T_world_from_joint = forward_kinematics(theta, character.skeleton)
    keypoints = keypoint_positions(theta, character, T_world_from_joint).numpy()
    forward = facing_direction(keypoints) if character.has_standard_keypoints else np.array([0.0, 0.0, -1.0])
    side = np.cross(forward, [0.0, 1.0, 0.0])
    both = np.concatenate([scan_vertices, character.vertices])
    grey = np.full((len(scan_vertices), 3), 190.0, np.float32)
    scan_view = shade_vertex_colours(scan_vertices, scan_faces, grey, framing_camera(both, -forward, width, height, "scan"))
    colours = distance_colours(distance, max_distance)
    views = [scan_view]
    for name, view_dir in (("front", -forward), ("side", side)):
        camera = framing_camera(both, view_dir, width, height, name)
        image = shade_vertex_colours(character.vertices, character.faces, colours, camera)
        if name == "front":
            draw_skeleton(image, T_world_from_joint[..., :3, 3].numpy(), character.skeleton.parents,
                          character.skeleton.joint_types, keypoints, camera)
        views.append(image)
    image = np.concatenate(views, axis=1)
    lines = (f"scan ({len(scan_vertices)} verts) | {character.name} fitted: template->scan mean "
             f"{1000 * float(np.mean(distance)):.1f} mm",
             f"colour: distance to the scan, blue 0 -> red {100 * max_distance:g} cm")
    for row, text in enumerate(lines):
        cv2.putText(image, text, (8, 20 + 18 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return image


# ------------------------------------------------------------------- ik: skeleton fit previews
def draw_target_keypoints(image: np.ndarray, keypoints_world: np.ndarray, camera: Camera,
                          colour=(0, 0, 0)) -> None:
    """Rings at target keypoints (rows with NaN, i.e. missing keypoints, are skipped)."""
    scale = max(1, image.shape[0] // 400)
    finite = np.isfinite(keypoints_world).all(axis=-1)
    if not finite.any():
        return
    pixels = np.asarray(project_world(camera, keypoints_world[finite]))
    for point in pixels:
        if np.all(np.isfinite(point)):
            cv2.circle(image, (int(round(point[0])), int(round(point[1]))), 5 * scale, colour, scale, cv2.LINE_AA)


def skeleton_fit_image(character: Character, thetas: np.ndarray, targets: np.ndarray | None = None,
                       width: int = 320, height: int = 480, labels=()) -> np.ndarray:
    """(height, n*width, 3) uint8 RGB: for each pose in ``thetas`` (n,D), the skeleton and its
    keypoints (filled: body red, left hand green, right hand blue) over the target keypoints
    ``targets`` (n,K,3) (black rings; NaN = missing), seen from the front, with a label."""
    import torch

    from egorelight_cli.geometry.skeleton import forward_kinematics, keypoint_positions

    views = []
    for i, theta in enumerate(np.asarray(thetas, dtype=np.float64)):
        theta_t = torch.as_tensor(theta)
        T_world_from_joint = forward_kinematics(theta_t, character.skeleton)
        joints = T_world_from_joint[..., :3, 3].numpy()
        keypoints = keypoint_positions(theta_t, character, T_world_from_joint).numpy()
        target = None if targets is None else np.asarray(targets[i], dtype=np.float64)
        body_joints = joints[~root_translation_joints(character.skeleton.parents, character.skeleton.joint_types)]
        points = np.concatenate([keypoints, body_joints]
                                + ([target[np.isfinite(target).all(axis=1)]] if target is not None else []))
        forward = facing_direction(keypoints) if character.has_standard_keypoints else np.array([0.0, 0.0, -1.0])
        camera = framing_camera(points, -forward, width, height, f"view{i}")
        image = np.full((height, width, 3), 255, np.uint8)
        draw_skeleton(image, joints, character.skeleton.parents, character.skeleton.joint_types, keypoints, camera)
        if target is not None:
            draw_target_keypoints(image, target, camera)
        if i < len(labels):
            cv2.putText(image, str(labels[i]), (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        views.append(image)
    return np.concatenate(views, axis=1)
