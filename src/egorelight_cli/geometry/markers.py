"""Fiducial markers: ArUco dictionaries, ChArUco boards and their detection (OpenCV ``aruco``).

Shared by the simulator (which paints and checks them) and the ``calibrate`` stage (which
measures with them). Images are 8-bit RGB (H,W,3) or grey (H,W); corners are pixels in OpenCV
order (top-left, top-right, bottom-right, bottom-left of each marker as seen from the front).
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np

HMD_MARKER_DICTIONARY = "DICT_4X4_50"


def aruco_dictionary(name: str = HMD_MARKER_DICTIONARY):
    """An OpenCV predefined ArUco dictionary by name (``DICT_4X4_50``, ...); a ValueError for
    another name."""
    value = getattr(cv2.aruco, str(name), None) if str(name).startswith("DICT_") else None
    if not isinstance(value, int):
        raise ValueError(f"unknown ArUco dictionary {name!r} (OpenCV's predefined DICT_..., e.g. DICT_4X4_50)")
    return cv2.aruco.getPredefinedDictionary(value)


def grey(image: np.ndarray) -> np.ndarray:
    """(H,W) uint8 from an 8-bit RGB or grey image."""
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def _field(spec, name: str):
    return spec[name] if isinstance(spec, Mapping) else getattr(spec, name)


def charuco_board(spec):
    """A ``cv2.aruco.CharucoBoard`` from a board description (``rig/board.json`` dict or a config
    section with ``squares_x``, ``squares_y``, ``square_length_m``, ``marker_length_m`` and
    optionally ``dictionary``/``legacy_pattern``); a ValueError naming what is wrong with it."""
    try:
        name = _field(spec, "dictionary")
    except (KeyError, AttributeError):
        name = "DICT_5X5_100"
    try:
        squares = int(_field(spec, "squares_x")), int(_field(spec, "squares_y"))
        square, marker = float(_field(spec, "square_length_m")), float(_field(spec, "marker_length_m"))
    except (KeyError, AttributeError) as exc:
        raise ValueError(f"the board description lacks {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"the board description has a field that is not a number ({exc})") from None
    if min(squares) < 2 or not 0 < marker < square:
        raise ValueError(f"the board needs at least 2x2 squares and 0 < marker_length_m < square_length_m, got "
                         f"{squares[0]}x{squares[1]} squares of {square} m with {marker} m markers")
    dictionary = aruco_dictionary(name)
    if (squares[0] * squares[1]) // 2 > dictionary.bytesList.shape[0]:
        raise ValueError(f"{name} holds {dictionary.bytesList.shape[0]} markers, too few for "
                         f"{squares[0]}x{squares[1]} squares")
    board = cv2.aruco.CharucoBoard(squares, square, marker, dictionary)
    try:
        board.setLegacyPattern(bool(_field(spec, "legacy_pattern")))
    except (KeyError, AttributeError):
        pass
    return board


#: ``refinement`` names -> OpenCV corner refinement methods. On rendered markers of ~20 px,
#: ``contour`` (line fits to the marker's contour) gave the least biased head poses; ``subpix``
#: pulls the outer corners inwards and ``apriltag`` scales the markers (a depth bias).
CORNER_REFINEMENT = {"none": cv2.aruco.CORNER_REFINE_NONE, "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
                     "contour": cv2.aruco.CORNER_REFINE_CONTOUR, "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG}


def detect_markers(image: np.ndarray, dictionary: str = HMD_MARKER_DICTIONARY,
                   refinement: str = "none") -> tuple[np.ndarray, np.ndarray]:
    """ArUco markers in an 8-bit image: ids (N,) int64 and corners (N,4,2) float64 pixels.

    ``refinement``: a key of :data:`CORNER_REFINEMENT`."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = CORNER_REFINEMENT[refinement]
    corners, ids, _ = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params).detectMarkers(grey(image))
    if ids is None:
        return np.zeros(0, np.int64), np.zeros((0, 4, 2))
    return ids.ravel().astype(np.int64), np.stack([c.reshape(4, 2) for c in corners]).astype(np.float64)


def detect_hmd_markers(image: np.ndarray) -> np.ndarray:
    """Ids of the HMD markers OpenCV detects in an 8-bit RGB or grey image."""
    return detect_markers(image)[0]


def detect_charuco(image: np.ndarray, board) -> tuple[np.ndarray, np.ndarray]:
    """ChArUco corners of ``board`` in an 8-bit image: ids (N,) int64 and pixels (N,2) float64."""
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(grey(image))
    if corners is None or ids is None:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    return ids.ravel().astype(np.int64), corners.reshape(-1, 2).astype(np.float64)


def detect_board(image: np.ndarray, spec) -> int:
    """Number of ChArUco corners OpenCV finds in an 8-bit RGB or grey image."""
    return len(detect_charuco(image, charuco_board(spec))[0])


def _bilinear(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples of a (H,W) float image at pixel positions (...,2) (centres at integers)."""
    h, w = image.shape
    x = np.clip(points[..., 0], 0, w - 1.001)
    y = np.clip(points[..., 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1])
            + fy * ((1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]))


def _line_through(points: np.ndarray) -> np.ndarray:
    """(a, b, c) of the total-least-squares line a x + b y + c = 0 (|(a,b)| = 1)."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre)
    normal = vt[1]
    return np.array([normal[0], normal[1], -normal @ centre])


def refine_marker_edges(intensity: np.ndarray, corners: np.ndarray, cells: int = 6, samples: int = 12) -> np.ndarray:
    """Corners (4,2) of a dark-bordered square marker re-measured from its four edges.

    OpenCV's contour-based corners follow the centres of the outermost dark pixels, half a pixel
    inside the true edge; here each edge is located where the intensity profile across it crosses
    half-way between the dark border and the light quiet zone (bilinear, so a hard edge between two
    pixel centres is found in the middle), a line is fitted per edge and the corners are the
    intersections of adjacent lines. ``intensity``: (H,W) float, linear in radiance; ``cells``:
    marker width in cells (bits + border); returns the input where an edge cannot be measured.
    """
    corners = np.asarray(corners, np.float64)
    centre = corners.mean(axis=0)
    side = np.mean(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1))
    reach = min(2.5, 0.45 * side / cells)
    if reach < 0.75:
        return corners
    offsets = np.linspace(-reach, reach, int(np.ceil(2 * reach / 0.1)) + 1)
    lines = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([-d[1], d[0]])
        if n @ ((a + b) / 2 - centre) < 0:
            n = -n  # outward
        base = a[None] + np.linspace(0.2, 0.8, samples)[:, None] * (b - a)[None]
        profile = _bilinear(intensity, base[:, None, :] + offsets[None, :, None] * n[None, None, :])
        points = []
        for p, values in zip(base, profile):
            dark, light = values[0], values[-1]
            if light - dark <= 0.2 * max(abs(light), 1e-12):
                continue
            above = np.flatnonzero(values >= 0.5 * (dark + light))
            j = above[0] if above.size else 0
            if j == 0:
                continue
            v0, v1 = values[j - 1], values[j]
            s = offsets[j - 1] + (0.5 * (dark + light) - v0) / (v1 - v0) * (offsets[j] - offsets[j - 1])
            points.append(p + s * n)
        if len(points) < 3:
            return corners
        lines.append(_line_through(np.array(points)))
    out = np.zeros((4, 2))
    for i in range(4):
        l1, l2 = lines[(i - 1) % 4], lines[i]
        x = np.cross(l1, l2)
        if abs(x[2]) < 1e-12:
            return corners
        out[i] = x[:2] / x[2]
    return out if np.all(np.linalg.norm(out - corners, axis=1) < 2.0) else corners
