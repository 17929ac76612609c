"""The simulated head-mounted display: a textured visor with ArUco markers, a strap, and four
cameras (two down-facing stereo fisheyes seeing the own body, two front-facing pinholes).

HMD frame (metres): origin at the centre of the visor box, **x to the wearer's right, y up, z
backwards** (from the visor towards the back of the head). The visor is a box of
``size = (width, height, depth)``; markers (``cv2.aruco`` dictionary ``DICT_4X4_50``) sit on its
front (ids 0, 1), left (2), right (3) and top (4, 5) faces with a white quiet zone, each marker's
corners listed in OpenCV order (top-left, top-right, bottom-right, bottom-left as the marker is
seen from outside). The cameras' *calibrated intrinsics* are public (``rig/hmd.json``); their
true mounting ``T_cam_from_hmd`` (nominal design + a seeded manufacturing error of about a degree
and a few millimetres) is ground truth only.

The HMD is attached rigidly to the character's head joint: ``T_world_from_hmd(theta) =
G_head(theta) @ T_joint_from_hmd``, with the mount placing the visor in front of the eyes.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from egorelight_cli.errors import EgorelightError
from egorelight_cli.geometry.cameras import Camera, invert_rigid
from egorelight_cli.geometry.markers import aruco_dictionary
from egorelight_cli.geometry.skeleton import forward_kinematics, keypoint_positions
from egorelight_cli.structures.character import Character
from egorelight_cli.synth.textures import TexturedMesh, grid_quad

MARKER_DICTIONARY = "DICT_4X4_50"
EGO_ROLES = ("down_left", "down_right", "front_left", "front_right")
DOWN_ROLES = ("down_left", "down_right")
FRONT_ROLES = ("front_left", "front_right")
VISOR_SIZE = (0.19, 0.11, 0.09)  # width (x), height (y), depth (z), metres
TEXELS_PER_M = 1600.0
SHELL_ALBEDO = (0.72, 0.72, 0.74)
STRAP_ALBEDO = (0.08, 0.08, 0.09)
_MARKER_BORDER_BITS = 1


@dataclass(frozen=True)
class VisorFace:
    """One face of the visor box: centre, in-plane axes as seen from outside, half sizes."""

    name: str
    centre: tuple[float, float, float]
    right: tuple[float, float, float]
    down: tuple[float, float, float]
    half_right: float
    half_down: float


def visor_faces(size=VISOR_SIZE) -> list[VisorFace]:
    w, h, d = (s / 2 for s in size)
    return [
        VisorFace("front", (0, 0, -d), (-1, 0, 0), (0, -1, 0), w, h),
        VisorFace("left", (-w, 0, 0), (0, 0, 1), (0, -1, 0), d, h),
        VisorFace("right", (w, 0, 0), (0, 0, -1), (0, -1, 0), d, h),
        VisorFace("top", (0, h, 0), (1, 0, 0), (0, 0, 1), w, d),
        VisorFace("bottom", (0, -h, 0), (1, 0, 0), (0, 0, -1), w, d),
        VisorFace("back", (0, 0, d), (1, 0, 0), (0, -1, 0), w, h),
    ]


#: Marker id -> (face, p, q): marker centre in face coordinates (along right, along down), metres.
MARKER_LAYOUT = {0: ("front", 0.047, -0.012), 1: ("front", -0.047, -0.012), 2: ("left", 0.0, 0.0),
                 3: ("right", 0.0, 0.0), 4: ("top", 0.047, 0.0), 5: ("top", -0.047, 0.0)}


@dataclass(frozen=True, eq=False)
class EgoCamera:
    """An HMD camera: public intrinsics plus the (ground-truth) mounting."""

    role: str
    model: str
    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    T_cam_from_hmd: np.ndarray          # true (ground truth)
    T_cam_from_hmd_nominal: np.ndarray  # the design drawing

    def camera(self, T_world_from_hmd: np.ndarray) -> Camera:
        """The posed camera for a head pose."""
        T = self.T_cam_from_hmd @ invert_rigid(T_world_from_hmd)
        return Camera(model=self.model, K=self.K, dist=self.dist, width=self.width, height=self.height,
                      T_cam_from_world=T, name=self.role)

    def to_json(self) -> dict:
        """The public ``rig/hmd.json`` entry (no extrinsics)."""
        return {"name": self.role, "role": self.role, "model": self.model, "K": self.K.tolist(),
                "dist": self.dist.tolist(), "width": self.width, "height": self.height}


@dataclass(frozen=True, eq=False)
class Hmd:
    """The headset: mesh (HMD frame), cameras, markers and its mount on the head joint."""

    mesh: TexturedMesh
    cameras: dict[str, EgoCamera]
    markers: dict[int, np.ndarray]  # id -> (4,3) corners in the HMD frame
    marker_length: float
    head_joint: int
    T_joint_from_hmd: np.ndarray

    def world_from_hmd(self, T_world_from_joint: np.ndarray) -> np.ndarray:
        """(T,4,4) head poses from FK joint transforms (T,J,4,4)."""
        return T_world_from_joint[:, self.head_joint] @ self.T_joint_from_hmd

    def to_json(self) -> dict:
        """``rig/hmd.json``: public camera intrinsics and the marker layout."""
        return {
            "frame": "HMD frame: origin at the visor centre, x wearer's right, y up, z backwards; metres",
            "cameras": [self.cameras[r].to_json() for r in EGO_ROLES if r in self.cameras],
            "markers": {
                "dictionary": MARKER_DICTIONARY,
                "marker_length_m": self.marker_length,
                "markers": [{"id": int(i), "corners_hmd": c.tolist()} for i, c in sorted(self.markers.items())],
            },
        }


# --------------------------------------------------------------------------------- construction
def head_joint_index(character: Character) -> int:
    """The joint the HMD is attached to: the last joint of the head chain (``Head_rx`` here)."""
    names = character.skeleton.joint_names
    if "Head_rx" in names:
        return names.index("Head_rx")
    candidates = [i for i, n in enumerate(names) if n.lower().startswith("head") and "ee" not in n.lower()]
    if not candidates:
        raise EgorelightError(f"character {character.name!r} has no head joint to mount the HMD on")
    return candidates[-1]


def _facing(character: Character, rest_keypoints: np.ndarray) -> np.ndarray:
    if character.has_standard_keypoints:
        from egorelight_cli.render.preview import facing_direction

        return facing_direction(rest_keypoints)
    return np.array([0.0, 0.0, -1.0])


def mount_transform(character: Character, head_joint: int, size=VISOR_SIZE) -> np.ndarray:
    """``T_joint_from_hmd``: the visor centred in front of the eyes at the rest pose."""
    theta = torch.as_tensor(character.rest_theta, dtype=torch.float64)
    G = forward_kinematics(theta, character.skeleton).numpy()
    kp = keypoint_positions(theta, character).numpy()
    forward = _facing(character, kp)
    head = G[head_joint, :3, 3]
    verts = character.vertices
    top = float(verts[:, 1].max())
    eye_y = head[1] + 0.22 * (top - head[1])
    side = np.cross(forward, [0.0, 1.0, 0.0])
    band = (np.abs(verts[:, 1] - eye_y) < 0.03) & (np.abs((verts - head) @ side) < 0.05) & (verts[:, 1] > head[1] - 0.1)
    if not band.any():
        raise EgorelightError("cannot find the face to mount the HMD on")
    face_front = float(np.max((verts[band] - head) @ forward))
    centre = head + forward * (face_front - 0.012 + size[2] / 2)
    centre[1] = eye_y
    z = -forward
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T_world_from_hmd = np.eye(4)
    T_world_from_hmd[:3, :3] = np.stack([x, y, z], axis=1)
    T_world_from_hmd[:3, 3] = centre
    return invert_rigid(G[head_joint]) @ T_world_from_hmd


def _marker_corners(face: VisorFace, p: float, q: float, length: float) -> np.ndarray:
    c, r, d = (np.asarray(v, dtype=np.float64) for v in (face.centre, face.right, face.down))
    h = length / 2
    return np.stack([c + (p - h) * r + (q - h) * d, c + (p + h) * r + (q - h) * d,
                     c + (p + h) * r + (q + h) * d, c + (p - h) * r + (q + h) * d])


def _paint_face(face: VisorFace, marker_length: float, lenses: list[tuple[float, float]]):
    """(albedo, specular, roughness) tile of one face, markers and lenses painted in."""
    rows = round(2 * face.half_down * TEXELS_PER_M)
    cols = round(2 * face.half_right * TEXELS_PER_M)
    albedo = np.tile(np.asarray(SHELL_ALBEDO, np.float32), (rows, cols, 1))
    spec = np.full((rows, cols, 1), 0.05, np.float32)
    rough = np.full((rows, cols, 1), 0.35, np.float32)
    dictionary = aruco_dictionary()

    def px(p: float, q: float) -> tuple[float, float]:  # face coords -> (col, row), continuous
        return (p + face.half_right) * TEXELS_PER_M, (q + face.half_down) * TEXELS_PER_M

    cells = dictionary.markerSize + 2 * _MARKER_BORDER_BITS
    for marker_id, (name, p, q) in MARKER_LAYOUT.items():
        if name != face.name:
            continue
        quiet = marker_length / cells
        half = marker_length / 2 + quiet
        if abs(p) + half > face.half_right or abs(q) + half > face.half_down:
            raise EgorelightError(f"marker length {marker_length} m does not fit the HMD's {name} face")
        c0, r0 = px(p - half, q - half)
        c1, r1 = px(p + half, q + half)
        albedo[int(r0):int(np.ceil(r1)), int(c0):int(np.ceil(c1))] = 0.85
        spec[int(r0):int(np.ceil(r1)), int(c0):int(np.ceil(c1))] = 0.01
        rough[int(r0):int(np.ceil(r1)), int(c0):int(np.ceil(c1))] = 0.9
        size = round(marker_length * TEXELS_PER_M)
        image = cv2.aruco.generateImageMarker(dictionary, marker_id, size, borderBits=_MARKER_BORDER_BITS)
        mc, mr = px(p - marker_length / 2, q - marker_length / 2)
        mc, mr = round(mc), round(mr)
        albedo[mr:mr + size, mc:mc + size] = np.where(image[..., None] > 127, 0.85, 0.03).astype(np.float32)
    for p, q in lenses:
        cc, rr = px(p, q)
        yy, xx = np.mgrid[:rows, :cols]
        disc = (xx + 0.5 - cc) ** 2 + (yy + 0.5 - rr) ** 2 < (0.008 * TEXELS_PER_M) ** 2
        albedo[disc] = 0.02
        spec[disc] = 0.3
        rough[disc] = 0.1
    return albedo, spec, rough


def _look(axis, right_hint) -> np.ndarray:
    """(3,3) R_hmd_from_cam with optical axis ``axis`` and image x close to ``right_hint``."""
    z = np.asarray(axis, np.float64)
    z /= np.linalg.norm(z)
    x = np.asarray(right_hint, np.float64) - z * (z @ right_hint)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _camera_on_face(face: VisorFace, p: float, q: float) -> np.ndarray:
    c, r, d = (np.asarray(v, dtype=np.float64) for v in (face.centre, face.right, face.down))
    normal = np.cross(d, r)
    return c + p * r + q * d + 0.008 * normal  # the lens protrudes 8 mm


def _perturb(T: np.ndarray, rng: np.random.Generator, rot_deg: float, trans_m: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    delta = np.eye(4)
    delta[:3, :3] = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3)).as_matrix()
    delta[:3, 3] = trans_m * rng.normal(size=3)
    return delta @ T


def fisheye_intrinsics(width: int, height: int, fov_deg: float, rng: np.random.Generator):
    """K and k1..k4 of an (almost) equidistant fisheye whose ``fov_deg`` image circle fits the image."""
    k = np.array([0.015, -0.004, 0.0008, 0.0]) * (1 + 0.1 * rng.normal(size=4))
    theta = np.radians(fov_deg / 2)
    t2 = theta * theta
    theta_d = theta * (1 + k[0] * t2 + k[1] * t2 ** 2 + k[2] * t2 ** 3 + k[3] * t2 ** 4)
    f = 0.49 * min(width, height) / theta_d * (1 + 0.01 * rng.normal())
    cx = (width - 1) / 2 + rng.normal() * 0.005 * width
    cy = (height - 1) / 2 + rng.normal() * 0.005 * height
    return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), k


def pinhole_intrinsics(width: int, height: int, hfov_deg: float, rng: np.random.Generator, distortion: float = 0.05):
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2) * (1 + 0.01 * rng.normal())
    cx = (width - 1) / 2 + rng.normal() * 0.005 * width
    cy = (height - 1) / 2 + rng.normal() * 0.005 * height
    dist = np.array([-distortion, 0.3 * distortion, 0.0, 0.0, 0.0]) * (1 + 0.1 * rng.normal(size=5))
    return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), dist


def _strap(head_centre_hmd: np.ndarray, radii: tuple[float, float], height: float, segments: int = 24):
    """A band around the back of the head: vertices, faces, UVs (HMD frame), outward facing."""
    phi = np.linspace(-2.3, 2.3, segments + 1)
    a, b = radii
    ring = np.stack([a * np.sin(phi), np.zeros_like(phi), b * np.cos(phi)], axis=-1) + head_centre_hmd
    top, bottom = ring + [0, height / 2, 0], ring - [0, height / 2, 0]
    vertices = np.concatenate([top, bottom])
    n = segments + 1
    faces = []
    for i in range(segments):
        # outward normal: (bottom_i - top_i) x (top_{i+1} - top_i) points away from the head
        faces += [[i, n + i, i + 1], [i + 1, n + i, n + i + 1]]
    faces = np.asarray(faces)
    uv = np.stack([np.concatenate([phi, phi]) * 0 + 0.5, np.full(2 * n, 0.5)], axis=-1)
    return vertices, faces, uv[faces]


def make_hmd(character: Character, cfg, seed: int) -> Hmd:
    """Build the headset for ``character`` from the ``hmd`` config section."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x4D0]))
    head_joint = head_joint_index(character)
    T_joint_from_hmd = mount_transform(character, head_joint)
    marker_length = float(cfg.marker_length_m)
    faces_spec = visor_faces()
    by_name = {f.name: f for f in faces_spec}
    front, bottom = by_name["front"], by_name["bottom"]
    # Camera placement (face coordinates): front cameras below the front markers; down cameras
    # at the bottom's front corners.
    front_lens = {"front_left": (0.032, 0.038), "front_right": (-0.032, 0.038)}
    down_lens = {"down_left": (-0.06, 0.028), "down_right": (0.06, 0.028)}

    tiles, vertices, faces, uvs = [], [], [], []
    for face in faces_spec:
        lenses = list(front_lens.values()) if face.name == "front" else \
            list(down_lens.values()) if face.name == "bottom" else []
        tiles.append(_paint_face(face, marker_length, lenses))
    strap = (np.array(STRAP_ALBEDO, np.float32).reshape(1, 1, 3) * np.ones((8, 8, 1), np.float32),
             np.full((8, 8, 1), 0.02, np.float32), np.full((8, 8, 1), 0.8, np.float32))
    tiles.append(strap)
    # Lay tiles side by side in one HMD texture.
    height = max(t[0].shape[0] for t in tiles)
    width = sum(t[0].shape[1] for t in tiles)
    albedo = np.zeros((height, width, 3), np.float32)
    spec = np.zeros((height, width, 1), np.float32)
    rough = np.ones((height, width, 1), np.float32)
    x0 = 0
    boxes = []
    for a, s, r in tiles:
        h, w = a.shape[:2]
        albedo[:h, x0:x0 + w], spec[:h, x0:x0 + w], rough[:h, x0:x0 + w] = a, s, r
        boxes.append((x0 / width, 1 - h / height, (x0 + w) / width, 1.0))
        x0 += w
    offset = 0
    cells = int(cfg.mesh_cells)
    for face, box in zip(faces_spec, boxes[:-1]):
        v, f, uv = grid_quad(face.centre, face.right, face.down, face.half_right, face.half_down, cells, box)
        vertices.append(v)
        faces.append(f + offset)
        uvs.append(uv)
        offset += len(v)
    head_centre = np.array([0.0, 0.01, 0.135])
    v, f, uv = _strap(head_centre, (0.1, 0.12), 0.03)
    u0, v0, u1, v1 = boxes[-1]
    uv = np.stack([u0 + uv[..., 0] * (u1 - u0), v0 + uv[..., 1] * (v1 - v0)], axis=-1)
    vertices.append(v)
    faces.append(f + offset)
    uvs.append(uv)
    mesh = TexturedMesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces),
                        face_uvs=np.concatenate(uvs), albedo=albedo, specular=spec, roughness=rough)

    markers = {i: _marker_corners(by_name[name], p, q, marker_length) for i, (name, p, q) in MARKER_LAYOUT.items()}
    cameras = {}
    down_axis = np.array([0.0, -np.cos(np.radians(cfg.down_tilt_deg)), -np.sin(np.radians(cfg.down_tilt_deg))])
    for role in EGO_ROLES:
        if role in DOWN_ROLES:
            position = _camera_on_face(bottom, *down_lens[role])
            R = _look(down_axis, np.array([1.0, 0.0, 0.0]))
            K, dist = fisheye_intrinsics(cfg.down_width, cfg.down_height, cfg.down_fov_deg, rng)
            model, w, h = "fisheye", cfg.down_width, cfg.down_height
        else:
            position = _camera_on_face(front, *front_lens[role])
            R = _look(np.array([0.0, -np.sin(np.radians(cfg.front_tilt_deg)), -np.cos(np.radians(cfg.front_tilt_deg))]),
                      np.array([1.0, 0.0, 0.0]))
            K, dist = pinhole_intrinsics(cfg.front_width, cfg.front_height, cfg.front_hfov_deg, rng)
            model, w, h = "pinhole", cfg.front_width, cfg.front_height
        T_hmd_from_cam = np.eye(4)
        T_hmd_from_cam[:3, :3] = R
        T_hmd_from_cam[:3, 3] = position
        nominal = invert_rigid(T_hmd_from_cam)
        true = _perturb(nominal, rng, cfg.mount_error_deg, cfg.mount_error_m)
        cameras[role] = EgoCamera(role=role, model=model, K=K, dist=dist, width=int(w), height=int(h),
                                  T_cam_from_hmd=true, T_cam_from_hmd_nominal=nominal)
    return Hmd(mesh=mesh, cameras=cameras, markers=markers, marker_length=marker_length,
               head_joint=head_joint, T_joint_from_hmd=T_joint_from_hmd)

