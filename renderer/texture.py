"""Texture space: the UV ↔ texel convention and differentiable map sampling.

Convention (docs/architecture.md, "Texture-space convention"): a map is a tensor ``[H, W, C]``
whose row 0 is the *top* of the image (v = 1), exactly as written to a file. UV (0, 0) is the
bottom-left corner of the map, (1, 1) the top-right. Texel (i, j) (row i, column j) covers
u ∈ [j/W, (j+1)/W], v ∈ [1 − (i+1)/H, 1 − i/H] and has its centre at

    u = (j + 0.5) / W,        v = 1 − (i + 0.5) / H.

In continuous texel coordinates (x = column, y = row, centres at integers)
``x = u·W − 0.5`` and ``y = (1 − v)·H − 0.5``. The flat texel index is ``i·W + j``.

Bilinear sampling interpolates between the four nearest texel centres and clamps to the edge
(outside the outermost centres the edge texel's value is returned). Nearest sampling returns the
texel whose square contains (u, v) (clamped to the map). Both are gathers, so gradients of a
sample reach exactly the texels it reads.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "uv_to_pixel", "pixel_to_uv", "texel_centers", "bilinear_weights", "texel_of",
    "sample_bilinear", "sample_nearest", "gather",
]


def _check_uv(uv: Tensor, where: str) -> None:
    if not isinstance(uv, Tensor) or uv.dim() < 1 or uv.shape[-1] != 2:
        raise ValueError(f"{where}: uv must be a tensor [..., 2], got {getattr(uv, 'shape', type(uv))}")
    if not uv.is_floating_point():
        raise ValueError(f"{where}: uv must be floating point, got {uv.dtype}")


def _check_size(H: int, W: int, where: str) -> None:
    for name, x in (("H", H), ("W", W)):
        if isinstance(x, bool) or not isinstance(x, int) or x < 1:
            raise ValueError(f"{where}: {name} must be a positive integer, got {x!r}")


def _check_map(texture: Tensor, where: str) -> None:
    if not isinstance(texture, Tensor) or texture.dim() != 3:
        raise ValueError(f"{where}: map must be a tensor [H, W, C], got {getattr(texture, 'shape', type(texture))}")


def uv_to_pixel(uv: Tensor, H: int, W: int) -> Tensor:
    """Continuous texel coordinates ``[..., 2]`` = (x, y) = (u·W − ½, (1 − v)·H − ½); centres are integers."""
    _check_uv(uv, "uv_to_pixel")
    _check_size(H, W, "uv_to_pixel")
    return torch.stack([uv[..., 0] * W - 0.5, (1.0 - uv[..., 1]) * H - 0.5], -1)


def pixel_to_uv(xy: Tensor, H: int, W: int) -> Tensor:
    """Inverse of :func:`uv_to_pixel`: (x, y) → (u, v) = ((x + ½)/W, 1 − (y + ½)/H)."""
    _check_uv(xy, "pixel_to_uv")
    _check_size(H, W, "pixel_to_uv")
    return torch.stack([(xy[..., 0] + 0.5) / W, 1.0 - (xy[..., 1] + 0.5) / H], -1)


def texel_centers(H: int, W: int, dtype=None, device=None) -> Tensor:
    """UV of every texel centre, ``[H, W, 2]`` (row 0 at v = 1 − 0.5/H)."""
    _check_size(H, W, "texel_centers")
    i = torch.arange(H, dtype=dtype, device=device)
    j = torch.arange(W, dtype=dtype, device=device)
    u = ((j + 0.5) / W)[None, :].expand(H, W)
    v = (1.0 - (i + 0.5) / H)[:, None].expand(H, W)
    return torch.stack([u, v], -1)


def texel_of(uv: Tensor, H: int, W: int) -> Tensor:
    """Flat index ``[...]`` (int64, i·W + j) of the texel containing each uv (clamped to the map)."""
    _check_uv(uv, "texel_of")
    _check_size(H, W, "texel_of")
    j = torch.floor(uv[..., 0].detach() * W).clamp(0, W - 1).long()
    i = torch.floor((1.0 - uv[..., 1].detach()) * H).clamp(0, H - 1).long()
    return i * W + j


def bilinear_weights(uv: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    """The four texels and weights of bilinear sampling at ``uv [..., 2]``, clamped to the edge.

    Returns:
        index ``[..., 4]`` int64 flat texel indices (top-left, top-right, bottom-left, bottom-right
        around the sample, i.e. (y0, x0), (y0, x1), (y1, x0), (y1, x1)), and weight ``[..., 4]`` in the
        dtype of ``uv``, each in [0, 1] and summing to 1. A sample equals Σ weight · map[index].
        Weights are not differentiated with respect to uv (geometry is fixed).
    """
    _check_uv(uv, "bilinear_weights")
    _check_size(H, W, "bilinear_weights")
    uv = uv.detach()
    x = (uv[..., 0] * W - 0.5).clamp(0.0, W - 1.0)
    y = ((1.0 - uv[..., 1]) * H - 0.5).clamp(0.0, H - 1.0)
    x0f, y0f = torch.floor(x), torch.floor(y)
    fx, fy = x - x0f, y - y0f
    x0, y0 = x0f.long(), y0f.long()
    x1, y1 = (x0 + 1).clamp_max(W - 1), (y0 + 1).clamp_max(H - 1)
    index = torch.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1], -1)
    weight = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    return index, weight


def gather(texture: Tensor, index: Tensor, weight: Tensor | None = None) -> Tensor:
    """Sample a map ``[H, W, C]`` from precomputed texel indices.

    ``index [..., K]`` with ``weight [..., K]`` → Σ_k weight·map[index] ``[..., C]`` (bilinear: K = 4);
    ``index [...]`` without weights → map[index] ``[..., C]`` (nearest). Differentiable with respect
    to the map (the gradient of a texel is the sum of the weights that read it).
    """
    _check_map(texture, "gather")
    flat = texture.reshape(-1, texture.shape[-1])
    if weight is None:
        return flat[index]
    return (flat[index] * weight.unsqueeze(-1).to(texture.dtype)).sum(-2)


def sample_bilinear(texture: Tensor, uv: Tensor) -> Tensor:
    """Bilinear, edge-clamped sample of ``texture [H, W, C]`` at ``uv [N, 2]`` → ``[N, C]`` (see module docstring)."""
    _check_map(texture, "sample_bilinear")
    index, weight = bilinear_weights(uv, texture.shape[0], texture.shape[1])
    return gather(texture, index, weight)


def sample_nearest(texture: Tensor, uv: Tensor) -> Tensor:
    """Nearest-texel sample of ``texture [H, W, C]`` at ``uv [N, 2]`` → ``[N, C]``."""
    _check_map(texture, "sample_nearest")
    return gather(texture, texel_of(uv, texture.shape[0], texture.shape[1]))
