"""One-to-many attention: equals naive multi-head attention with the folded weights, ignores ray order."""

from __future__ import annotations

import torch

from egorelight_cli.nn.attention import OneToManyAttention, RayEmbedding, multi_head_reference


def _inputs(seed: int = 0, B: int = 2, C: int = 8, H: int = 3, W: int = 4, r: int = 5):
    g = torch.Generator().manual_seed(seed)
    features = torch.randn(B, C, H, W, generator=g, dtype=torch.float64)
    rays = torch.randn(B, H, W, r, 6, generator=g, dtype=torch.float64)
    valid = torch.rand(B, H, W, r, generator=g) > 0.3
    valid[0, 0, 0] = False  # a texel without any lit ray
    return features, rays, valid


def test_equals_naive_multi_head_attention():
    torch.manual_seed(0)
    features, rays, valid = _inputs()
    embed = RayEmbedding(8).double()
    attention = OneToManyAttention(8, heads=2).double()
    embedded = embed(rays)
    flat_features = features.permute(0, 2, 3, 1).reshape(-1, 8)
    expected = multi_head_reference(flat_features, embedded.reshape(-1, 5, 8), attention.query.weight, 2,
                                    valid.reshape(-1, 5))
    actual = attention.attend(features.permute(0, 2, 3, 1), embedded, valid).reshape(-1, 8)
    torch.testing.assert_close(actual, expected, rtol=1e-10, atol=1e-12)
    assert torch.all(actual[0] == 0)  # no valid ray, no update
    out = attention(features, embedded, valid)
    torch.testing.assert_close(out - features, attention.out(actual.reshape(2, 3, 4, 8)).permute(0, 3, 1, 2))


def test_permutation_invariant_over_the_rays():
    torch.manual_seed(1)
    features, rays, valid = _inputs(seed=3)
    embed = RayEmbedding(8).double()
    attention = OneToManyAttention(8, heads=4).double()
    order = torch.randperm(5)
    first = attention(features, embed(rays), valid)
    second = attention(features, embed(rays[..., order, :]), valid[..., order])
    torch.testing.assert_close(first, second, rtol=1e-10, atol=1e-12)


def test_gradients_flow_to_rays_and_features():
    features, rays, valid = _inputs(seed=5)
    features.requires_grad_(True)
    rays.requires_grad_(True)
    embed = RayEmbedding(8).double()
    attention = OneToManyAttention(8, heads=2).double()
    attention(features, embed(rays), valid).square().sum().backward()
    assert features.grad.abs().sum() > 0 and rays.grad.abs().sum() > 0
    assert torch.all(rays.grad[~valid] == 0)  # masked rays do not influence the result
