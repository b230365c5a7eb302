"""Texture-space convention and sampling, against torch.nn.functional.grid_sample as an independent reference."""

import pytest
import torch
import torch.nn.functional as F

from renderer.texture import (
    bilinear_weights,
    pixel_to_uv,
    sample_bilinear,
    sample_nearest,
    texel_centers,
    texel_of,
    uv_to_pixel,
)


def test_convention_corners_and_centres():
    H, W = 4, 5
    c = texel_centers(H, W, dtype=torch.float64)
    assert torch.allclose(c[0, 0], torch.tensor([0.1, 0.875], dtype=torch.float64))  # top-left texel: u≈0, v≈1
    assert torch.allclose(c[3, 4], torch.tensor([0.9, 0.125], dtype=torch.float64))
    assert torch.equal(texel_of(torch.tensor([[0.0, 1.0], [1.0, 0.0], [0.0, 0.0], [0.99, 0.99]]), H, W),
                       torch.tensor([0, 19, 15, 4]))
    xy = uv_to_pixel(c, H, W)
    assert torch.allclose(xy[2, 3], torch.tensor([3.0, 2.0], dtype=torch.float64))
    assert torch.allclose(pixel_to_uv(xy, H, W), c)


def test_samples_at_centres_are_exact_and_nearest_agrees():
    g = torch.Generator().manual_seed(0)
    m = torch.rand(6, 7, 3, generator=g, dtype=torch.float64)
    uv = texel_centers(6, 7, dtype=torch.float64).reshape(-1, 2)
    assert torch.allclose(sample_bilinear(m, uv), m.reshape(-1, 3), atol=1e-12)
    assert torch.equal(sample_nearest(m, uv), m.reshape(-1, 3))


def test_bilinear_matches_grid_sample_with_border_clamp():
    g = torch.Generator().manual_seed(1)
    m = torch.rand(5, 8, 2, generator=g, dtype=torch.float64)
    uv = torch.rand(500, 2, generator=g, dtype=torch.float64) * 1.4 - 0.2  # includes out-of-range: clamp to edge
    ours = sample_bilinear(m, uv)
    grid = torch.stack([2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]], -1).view(1, 1, -1, 2)  # grid y = −1 is the top row
    ref = F.grid_sample(m.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    assert torch.allclose(ours, ref[0, :, 0].T, atol=1e-12)
    idx, w = bilinear_weights(uv, 5, 8)
    assert idx.min() >= 0 and idx.max() < 40 and torch.allclose(w.sum(-1), torch.ones(500, dtype=w.dtype))
    assert (w >= 0).all()


def test_gradients_reach_exactly_the_texels_read():
    m = torch.rand(4, 4, 3, dtype=torch.float64, requires_grad=True)
    uv = torch.tensor([[0.3, 0.6], [0.9, 0.1], [-0.5, 2.0]], dtype=torch.float64)
    torch.autograd.gradcheck(lambda x: sample_bilinear(x, uv), (m,))
    sample_bilinear(m, uv)[:, 0].sum().backward()
    idx, w = bilinear_weights(uv, 4, 4)
    expect = torch.zeros(16, dtype=torch.float64).index_add(0, idx.reshape(-1), w.reshape(-1))
    assert torch.allclose(m.grad[..., 0].reshape(-1), expect) and (m.grad[..., 1] == 0).all()


def test_errors():
    with pytest.raises(ValueError, match=r"\[H, W, C\]"):
        sample_bilinear(torch.zeros(4, 4), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="uv"):
        sample_nearest(torch.zeros(4, 4, 1), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="H must be"):
        texel_of(torch.zeros(1, 2), 0, 3)
