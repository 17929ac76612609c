"""Face and area-weighted vertex normals."""

from __future__ import annotations

import math

import geometry_synthetic as synth
import numpy as np
import pytest
import torch

from egorelight_cli.geometry.normals import (
    face_area_normals,
    face_normals,
    vertex_normals,
)


def cube() -> tuple[torch.Tensor, np.ndarray]:
    v = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)], dtype=torch.float64)
    # index = 4x + 2y + z with x,y,z in {0,1}; counter-clockwise seen from outside
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return v, faces


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_face_normal_of_ccw_triangle(dtype):
    v = torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [0.0, 3.0, 0]], dtype=dtype)
    f = np.array([[0, 1, 2]])
    torch.testing.assert_close(face_area_normals(v, f), torch.tensor([[0.0, 0, 6.0]], dtype=dtype))  # 2 x area
    torch.testing.assert_close(face_normals(v, f), torch.tensor([[0.0, 0, 1.0]], dtype=dtype))
    torch.testing.assert_close(face_normals(v, f[:, [0, 2, 1]]), torch.tensor([[0.0, 0, -1.0]], dtype=dtype))


def test_cube_normals_point_outwards():
    v, f = cube()
    fn = face_normals(v, f)
    centres = v[torch.as_tensor(f)].mean(1)
    assert torch.all((fn * centres).sum(-1) > 0)
    vn = vertex_normals(v, f)
    torch.testing.assert_close(vn.norm(dim=-1), torch.ones(8, dtype=torch.float64))
    # each corner touches its three faces (one or two triangles each): its normal lies in its octant
    assert torch.all(vn * v > 0)


def test_area_weighting_by_hand():
    # vertex 0 is shared by a triangle in the xy plane (normal +z, area 2) and one in the xz plane
    # (normal +y, area 0.5): the vertex normal is (0, 0.5, 2) normalised
    v = torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [0.0, 2.0, 0], [0.0, 0, 1.0], [1.0, 0, 0]], dtype=torch.float64)
    f = np.array([[0, 1, 2], [0, 3, 4]])
    fa = face_area_normals(v, f)
    torch.testing.assert_close(fa, torch.tensor([[0.0, 0, 4.0], [0.0, 1.0, 0]], dtype=torch.float64))
    expected = torch.tensor([0.0, 1.0, 4.0], dtype=torch.float64) / math.sqrt(17.0)
    torch.testing.assert_close(vertex_normals(v, f)[0], expected)


def test_tube_normals_point_away_from_axis():
    verts, faces = synth.make_tube()
    v = torch.as_tensor(verts)
    vn = vertex_normals(v, faces)
    radial = torch.nn.functional.normalize(v * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64), dim=-1)
    assert torch.all((vn * radial).sum(-1) > 0.9)


def test_batched_and_isolated_vertices():
    v, f = cube()
    batch = torch.stack([v, 2.0 * v, v + 1.0])[None].expand(2, 3, 8, 3)
    vn = vertex_normals(batch, f)
    assert vn.shape == (2, 3, 8, 3)
    torch.testing.assert_close(vn[1, 1], vertex_normals(v, f))
    extra = torch.cat([v, torch.zeros(1, 3, dtype=torch.float64)])
    torch.testing.assert_close(vertex_normals(extra, f)[8], torch.zeros(3, dtype=torch.float64))


def test_normals_gradcheck():
    v, f = cube()
    v = (v + 0.1 * torch.randn_like(v)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: vertex_normals(x, f), (v,))
    assert torch.autograd.gradcheck(lambda x: face_normals(x, f), (v,))
