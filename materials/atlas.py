"""Schüler's two-RGBA texture layout and the maths of packing many materials into one atlas.

Pure torch, no file I/O (``capture/export.py`` writes the files). Schüler (ShaderX7 2.5, "Authoring
model parameters"): K_diffuse, K_specular, the glossiness g and a surface mask "are four
parameters, two colors and two scalars, which fit nicely in two RGBA textures", which "allows us
to batch a large collection of different appearances onto a single texture atlas".

=========  =======  =================================  =====================================
texture    channel  content                            encoding
=========  =======  =================================  =====================================
tex1       RGB      K_diffuse = ``albedo``             ``transfer`` (gamma 2.2 default, sRGB)
tex1       A        ``mask`` (surface mask / opacity)  linear
tex2       RGB      K_specular = ``f0``                ``transfer`` (gamma 2.2 default, sRGB)
tex2       A        glossiness g, e = 2^(12 g)         linear, g ∈ [0, 1]
=========  =======  =================================  =====================================

"The specular color on a texture, after gamma conversion, becomes K_specular": colours are stored
gamma-encoded (Schüler's display gamma 2.2: ``y = x^(1/2.2)``; or IEC 61966-2-1 sRGB on request);
the alpha channels are linear. The canonical roughness r converts to g through
:mod:`materials.roughness` (g = log2(s)/12, s = 2/r⁴ − 2). The texture holds g ∈ [0, 1], i.e.
s ∈ [1, 4096]: r < 0.1487 (s > 4096) clamps to g = 1 and r > 0.9036 (s < 1) to g = 0; both are
counted and reported with an :class:`AtlasWarning`.

Atlas geometry. Pixel rectangles use image coordinates: ``x`` column, ``y`` row, origin at the
top-left texel, so a map ``[h, w, C]`` placed at rect ``(x, y, w, h)`` occupies
``atlas[y:y+h, x:x+w]``. UVs follow the texture-space convention of DESIGN.md: texel (i, j) of a
``[H, W]`` map has its centre at ``u = (j + 0.5)/W``, ``v = 1 − (i + 0.5)/H``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from .geometry import guarded_pow
from .roughness import glossiness_to_roughness, roughness_to_shininess

__all__ = [
    "AtlasError", "AtlasWarning", "Packing", "Rect", "TRANSFERS", "compose", "decode_schuler", "dilate",
    "encode_schuler", "extract", "pack_rectangles", "pull_push", "rect_uv", "remap_uvs", "transfer_decode",
    "transfer_encode",
]

#: Colour encodings of the atlas colour channels.
TRANSFERS = ("gamma2.2", "srgb", "linear")
GAMMA = 2.2


class AtlasError(ValueError):
    """An atlas cannot be built as asked (too small, bad sizes, bad maps); the message says the fix."""


class AtlasWarning(UserWarning):
    """Values were clamped or resampled while building an atlas; the message gives the counts."""


# --------------------------------------------------------------------------------------------
# transfer functions (duplicated from renderer.imageio, which materials may not import; the
# tests check that both agree)


def _transfer(transfer: str) -> str:
    t = transfer.strip().lower() if isinstance(transfer, str) else transfer
    if t not in TRANSFERS:
        raise AtlasError(f"unknown atlas transfer {transfer!r}; use one of {list(TRANSFERS)}")
    return t


def transfer_encode(x: Tensor, transfer: str = "gamma2.2") -> Tensor:
    """Linear [0, 1] → encoded: gamma 2.2 ``x^(1/2.2)``; sRGB IEC 61966-2-1; or linear. Finite gradients."""
    t = _transfer(transfer)
    if t == "linear":
        return x
    if t == "gamma2.2":
        return guarded_pow(x, 1.0 / GAMMA)
    hi = 1.055 * guarded_pow(x.clamp_min(0.0031308), 1.0 / 2.4) - 0.055
    return torch.where(x > 0.0031308, hi, 12.92 * x)


def transfer_decode(y: Tensor, transfer: str = "gamma2.2") -> Tensor:
    """Encoded → linear; exact inverse of :func:`transfer_encode` on [0, 1]."""
    t = _transfer(transfer)
    if t == "linear":
        return y
    if t == "gamma2.2":
        return guarded_pow(y, GAMMA)
    hi = guarded_pow((y.clamp_min(0.04045) + 0.055) / 1.055, 2.4)
    return torch.where(y > 0.04045, hi, y / 12.92)


# --------------------------------------------------------------------------------------------
# Schüler encode / decode


def _clamp_count(x: Tensor, lo: float, hi: float, name: str, counts: dict) -> Tensor:
    below = int((x < lo).sum())
    above = int((x > hi).sum())
    if below or above:
        counts[name] = (below, above, lo, hi)
    return x.clamp(lo, hi)


def _hw(x: Tensor, name: str, channels: int) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"map '{name}' must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() == 2 and channels == 1:
        x = x[..., None]
    if x.dim() != 3 or x.shape[-1] not in (channels, 1):
        raise AtlasError(f"map '{name}' must have shape [H, W, {channels}], got {tuple(x.shape)}")
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    bad = ~torch.isfinite(x)
    if bad.any():
        raise AtlasError(f"map '{name}' contains {int(bad.sum())} NaN/inf value(s); fix or fill the map first")
    return x.expand(*x.shape[:2], channels)


def _warn_counts(counts: dict, where: str) -> None:
    if counts:
        parts = [
            f"{name}: {b} below {lo:g}, {a} above {hi:g}" for name, (b, a, lo, hi) in counts.items()
        ]
        warnings.warn(f"{where}: values clamped ({'; '.join(parts)})", AtlasWarning, stacklevel=3)


def encode_schuler(maps: Mapping[str, Tensor], transfer: str = "gamma2.2") -> tuple[Tensor, Tensor]:
    """Canonical maps → Schüler's two RGBA textures, values in [0, 1] (not yet quantised).

    Args:
        maps: ``albedo [H, W, 3]``, ``f0 [H, W, 3]``, ``roughness [H, W, 1]`` (or ``[H, W]``), optional
            ``mask [H, W, 1]`` (default 1). Linear, all on one device and of one size.
        transfer: encoding of the colour channels, ``"gamma2.2"`` (Schüler, default), ``"srgb"`` or ``"linear"``.

    Returns:
        ``tex1 [H, W, 4]`` = (encoded albedo, mask), ``tex2 [H, W, 4]`` = (encoded f0, g), same dtype.

    Out-of-range values (albedo, f0, mask outside [0, 1]; roughness whose g falls outside [0, 1]) are
    clamped and reported in one :class:`AtlasWarning` with the counts; NaN/inf raise :class:`AtlasError`.
    """
    missing = [k for k in ("albedo", "f0", "roughness") if k not in maps]
    if missing:
        raise AtlasError(f"encode_schuler needs maps {missing} (have {sorted(maps)})")
    albedo = _hw(maps["albedo"], "albedo", 3)
    f0 = _hw(maps["f0"], "f0", 3)
    rough = _hw(maps["roughness"], "roughness", 1)
    mask = _hw(maps["mask"], "mask", 1) if maps.get("mask") is not None else torch.ones_like(rough)
    sizes = {k: tuple(v.shape[:2]) for k, v in (("albedo", albedo), ("f0", f0), ("roughness", rough), ("mask", mask))}
    if len(set(sizes.values())) != 1:
        raise AtlasError(f"maps must share one size, got {sizes}; resample them first")
    counts: dict = {}
    albedo = _clamp_count(albedo, 0.0, 1.0, "albedo", counts)
    f0 = _clamp_count(f0, 0.0, 1.0, "f0", counts)
    mask = _clamp_count(mask, 0.0, 1.0, "mask", counts)
    rough = _clamp_count(rough, 0.0, 1.0, "roughness", counts)
    # unclamped glossiness log2(s)/12 (s ∈ [0, 2^16]); s = 0 (r = 1) → g = -inf → clamps to 0
    s = roughness_to_shininess(rough)
    g_raw = torch.log2(s.clamp_min(1e-30)) / 12.0
    g = _clamp_count(g_raw, 0.0, 1.0, "glossiness g", counts)
    _warn_counts(counts, "encode_schuler")
    tex1 = torch.cat([transfer_encode(albedo, transfer), mask], dim=-1)
    tex2 = torch.cat([transfer_encode(f0, transfer), g], dim=-1)
    return tex1, tex2


def decode_schuler(tex1: Tensor, tex2: Tensor, transfer: str = "gamma2.2") -> dict[str, Tensor]:
    """Schüler's two RGBA textures → canonical maps.

    Args:
        tex1, tex2: ``[H, W, 4]`` in [0, 1] (8-bit codes / 255, 16-bit codes / 65535, or floats).
        transfer: how the colour channels were encoded.

    Returns:
        ``albedo [H, W, 3]``, ``f0 [H, W, 3]`` (linear), ``roughness [H, W, 1]`` (= glossiness_to_roughness(g),
        so in [0.1487, 0.9036] for g ∈ [0, 1]), ``glossiness [H, W, 1]``, ``mask [H, W, 1]``.
    """
    for name, t in (("tex1", tex1), ("tex2", tex2)):
        if not isinstance(t, Tensor) or t.dim() != 3 or t.shape[-1] != 4:
            shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise AtlasError(f"{name} must be a tensor [H, W, 4], got {shape}")
    if tex1.shape != tex2.shape:
        raise AtlasError(f"tex1 and tex2 must have the same size, got {tuple(tex1.shape)} and {tuple(tex2.shape)}")
    tex1 = tex1.clamp(0.0, 1.0)
    tex2 = tex2.clamp(0.0, 1.0)
    g = tex2[..., 3:4]
    return {
        "albedo": transfer_decode(tex1[..., :3], transfer),
        "f0": transfer_decode(tex2[..., :3], transfer),
        "roughness": glossiness_to_roughness(g),
        "glossiness": g,
        "mask": tex1[..., 3:4],
    }


# --------------------------------------------------------------------------------------------
# packing


class Rect(NamedTuple):
    """A pixel rectangle in the atlas: column ``x``, row ``y`` of the top-left texel, width ``w``, height ``h``."""

    x: int
    y: int
    w: int
    h: int


class Packing(NamedTuple):
    """Result of :func:`pack_rectangles`: one :class:`Rect` per input (content, gutter excluded), in input
    order, and the atlas ``size = (width, height)``."""

    rects: list[Rect]
    size: tuple[int, int]


def _shelf(padded: list[tuple[int, int]], width: int, height: int) -> list[tuple[int, int]] | None:
    """First-fit decreasing-height shelf packing of padded (w, h) boxes; top-left corners or None."""
    order = sorted(range(len(padded)), key=lambda i: (-padded[i][1], -padded[i][0], i))
    shelves: list[list[int]] = []  # [y, height, used width]
    top = 0
    pos: list[tuple[int, int] | None] = [None] * len(padded)
    for i in order:
        w, h = padded[i]
        if w > width:
            return None
        for shelf in shelves:
            if shelf[2] + w <= width and h <= shelf[1]:
                pos[i] = (shelf[2], shelf[0])
                shelf[2] += w
                break
        else:
            if top + h > height:
                return None
            shelves.append([top, h, w])
            pos[i] = (0, top)
            top += h
    return pos  # type: ignore[return-value]


def _check_sizes(sizes) -> list[tuple[int, int]]:
    if not isinstance(sizes, Sequence) or len(sizes) == 0:
        raise AtlasError("pack_rectangles needs a non-empty list of (width, height) sizes")
    out = []
    for k, s in enumerate(sizes):
        try:
            w, h = (int(v) for v in s)
        except (TypeError, ValueError):
            raise AtlasError(f"size #{k} must be a (width, height) pair of integers, got {s!r}") from None
        if w <= 0 or h <= 0 or (w, h) != tuple(s):
            raise AtlasError(f"size #{k} must be positive integers (width, height), got {s!r}")
        out.append((w, h))
    return out


def _ceil(x: int, multiple: int) -> int:
    return -(-x // multiple) * multiple


def _extent(padded: list[tuple[int, int]], pos: list[tuple[int, int]], gutter: int) -> tuple[int, int]:
    """Atlas (width, height) covering the placed padded boxes, their outer gutter hanging over the border."""
    return (max(x + w for (x, _), (w, _) in zip(pos, padded, strict=True)) - 2 * gutter,
            max(y + h for (_, y), (_, h) in zip(pos, padded, strict=True)) - 2 * gutter)


def _tight(padded: list[tuple[int, int]], gutter: int, multiple: int) -> tuple[int, int]:
    """The atlas with the shortest longest side (then the smallest area) over a few shelf widths."""
    order = sorted(range(len(padded)), key=lambda i: (-padded[i][1], -padded[i][0], i))
    widths, run = {max(w for w, _ in padded)}, 0
    for i in order:  # a first shelf holding the k tallest boxes, for every k
        run += padded[i][0]
        widths.add(run)
    area = sum(w * h for w, h in padded)
    widths.add(max(max(w for w, _ in padded), math.isqrt(area) + 1))
    best = None
    for width in sorted(widths):
        if width < max(w for w, _ in padded):
            continue
        pos = _shelf(padded, width, 1 << 62)
        w, h = _extent(padded, pos, gutter)
        w, h = _ceil(w, multiple), _ceil(h, multiple)
        key = (max(w, h), w * h, w)
        if best is None or key < best[0]:
            best = (key, (w, h))
    return best[1]


def _pow2(padded: list[tuple[int, int]], gutter: int) -> tuple[int, int]:
    """Smallest power-of-two square in which the shelf packer fits the padded boxes."""
    side = max(max(w for w, _ in padded), max(h for _, h in padded), math.isqrt(sum(w * h for w, h in padded)))
    side = 1 << max(side - 2 * gutter - 1, 0).bit_length()
    while _shelf(padded, side + 2 * gutter, side + 2 * gutter) is None:
        side *= 2
    return side, side


def pack_rectangles(
    sizes: Sequence[tuple[int, int]], atlas_size: int | tuple[int, int] | str | None = None, gutter: int = 4,
    multiple: int = 4,
) -> Packing:
    """Place rectangles of the given (width, height) in pixels into one atlas, without overlap.

    Each rectangle is padded by ``gutter`` texels on every side and the padded boxes are shelf-packed
    (first fit, decreasing height) into the atlas grown by ``gutter`` on every side: two materials are
    at least 2·gutter apart, but a material may touch the atlas border, its outer gutter falling off the
    image. The atlas is sampled with clamp-to-edge addressing (the GLB says so), where the border texel
    is its own gutter at every mip level, so no texel is spent on a border gutter: one 256² material
    gives a 256² atlas.

    Args:
        sizes: ``(width, height)`` of each rectangle, positive integers.
        atlas_size: None — the tight size: the shortest longest side, then the smallest area, over a few
            shelf widths (the first shelf holding the k tallest boxes, for every k),
            each side rounded up to ``multiple``; ``"pow2"`` — the smallest power-of-two square that fits;
            an int — that square; a ``(width, height)`` pair — used as given.
        gutter: free texels around each rectangle, ≥ 0. multiple: automatic sizes are multiples of it
            (4: block-compressed formats want whole 4×4 blocks).

    Raises:
        AtlasError: bad sizes, gutter or size, or a fixed atlas too small — the message says the size needed.
    """
    sizes = _check_sizes(sizes)
    if not isinstance(gutter, int) or isinstance(gutter, bool) or gutter < 0:
        raise AtlasError(f"gutter must be an integer ≥ 0, got {gutter!r}")
    if not isinstance(multiple, int) or isinstance(multiple, bool) or multiple < 1:
        raise AtlasError(f"multiple must be an integer ≥ 1, got {multiple!r}")
    padded = [(w + 2 * gutter, h + 2 * gutter) for w, h in sizes]
    if atlas_size is None:
        size = _tight(padded, gutter, multiple)
    elif atlas_size == "pow2":
        size = _pow2(padded, gutter)
    else:
        try:
            size = (atlas_size, atlas_size) if isinstance(atlas_size, int) else tuple(int(v) for v in atlas_size)
        except (TypeError, ValueError):
            size = ()
        if isinstance(atlas_size, (bool, str)) or len(size) != 2 or min(size) <= 0:
            raise AtlasError(f"atlas_size must be None, 'pow2', a positive int or (width, height), got {atlas_size!r}")
    pos = _shelf(padded, size[0] + 2 * gutter, size[1] + 2 * gutter)
    if pos is None:
        need = _tight(padded, gutter, 1)
        area = sum(w * h for w, h in sizes)
        raise AtlasError(
            f"atlas {size[0]}x{size[1]} is too small for {len(sizes)} rectangle(s) of sizes {sizes} with gutter "
            f"{gutter} ({area} texels of content); it needs at least {need[0]}x{need[1]} — pass that size, "
            "or None to choose it automatically"
        )
    rects = [Rect(px, py, w, h) for (px, py), (w, h) in zip(pos, sizes, strict=True)]
    return Packing(rects, (int(size[0]), int(size[1])))


# --------------------------------------------------------------------------------------------
# dilation (push coverage outward so that bilinear filtering and mip-maps do not bleed)


def _mask_hw1(mask: Tensor, shape: tuple[int, int]) -> Tensor:
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask must be a torch.Tensor, got {type(mask).__name__}")
    m = mask[..., 0] if mask.dim() == 3 else mask
    if m.dim() != 2 or tuple(m.shape) != shape:
        raise AtlasError(f"mask must be [H, W] or [H, W, 1] matching the map's {shape}, got {tuple(mask.shape)}")
    return m > 0


def pull_push(values: Tensor, known: Tensor) -> Tensor:
    """Fill the unknown texels of a map ``[H, W, C]`` from its known ones (``known [H, W]`` bool) by pull-push.

    Pull: sum the known texels and their count into a pyramid of half-resolution levels down to 1 × 1; push: from
    coarse to fine, every texel whose block holds no known texel takes the value of its parent. Each unknown texel
    thus gets the mean of the known texels in the smallest pyramid block around it that has any, weighted by how
    many each block holds. Known texels are returned unchanged (their values only, so unknown texels may hold
    anything, NaN included). Vectorised: one ``avg_pool2d`` and one ``interpolate`` per level, log2(max(H, W))
    levels. With no known texel at all a copy of the map is returned.

    The one fill of the project: :func:`dilate` (and so the atlas gutters) and the fit's unobserved texels.
    """
    if not isinstance(values, Tensor) or not isinstance(known, Tensor):
        raise TypeError("pull_push: values and known must be torch.Tensors")
    if values.dim() != 3 or tuple(known.shape) != tuple(values.shape[:2]):
        raise AtlasError(f"pull_push: values must be [H, W, C] and known [H, W], got {tuple(values.shape)} and "
                         f"{tuple(known.shape)}")
    known = known.bool()
    if not bool(known.any()):
        return values.clone()
    w = known.to(values.dtype)[None, None]
    x = torch.where(known[..., None], values, torch.zeros((), dtype=values.dtype, device=values.device))
    x = x.permute(2, 0, 1)[None]
    pyramid = [(x, w)]
    while pyramid[-1][0].shape[-2:] != (1, 1):
        x, w = pyramid[-1]
        # sums, not 4 × means: a ceil_mode edge block of an odd size averages fewer texels
        pyramid.append((F.avg_pool2d(x, 2, ceil_mode=True, divisor_override=1),
                        F.avg_pool2d(w, 2, ceil_mode=True, divisor_override=1)))
    # each level's means where it holds a known texel; the floor only keeps 0/0 out of the discarded branch
    cur = pyramid[-1][0] / pyramid[-1][1].clamp_min(1e-12)
    for x, w in reversed(pyramid[:-1]):
        up = F.interpolate(cur, size=x.shape[-2:], mode="nearest")
        cur = torch.where(w > 0, x / w.clamp_min(1e-12), up)
    return torch.where(known[..., None], values, cur[0].permute(1, 2, 0))


def _rings(x: Tensor, valid: Tensor, pixels: int) -> tuple[Tensor, Tensor]:
    """``pixels`` rings of 3×3 mean-of-covered-neighbours growth on ``x [1, C, H, W]``, ``valid [1, 1, H, W]``."""
    kernel = torch.ones(1, 1, 3, 3, dtype=x.dtype, device=x.device)
    c, hw = x.shape[1], x.shape[-2:]
    for _ in range(pixels):
        wv = valid.to(x.dtype)
        num = F.conv2d((x * wv).reshape(c, 1, *hw), kernel, padding=1).reshape(1, c, *hw)
        den = F.conv2d(wv, kernel, padding=1)
        grow = (~valid) & (den > 0)
        if not grow.any():
            break
        x = torch.where(grow, num / den.clamp_min(1e-30), x)
        valid = valid | grow
    return x, valid


def dilate(map: Tensor, mask: Tensor, pixels: int | None = None) -> Tensor:
    """Push the values of covered texels outward into uncovered ones (edge padding).

    Args:
        map: ``[H, W, C]`` (any float dtype, device).
        mask: ``[H, W]`` or ``[H, W, 1]``; texels with mask > 0 are covered and keep their values exactly.
        pixels: number of rings to grow: each ring sets every uncovered texel that has a covered
            8-neighbour to the mean of those neighbours (one vectorised 3×3 convolution per ring).
            None fills *every* uncovered texel with a push-pull pyramid (each uncovered texel takes
            the coverage-weighted mean of the finest coarser level that has one), O(HW).

    Returns:
        ``[H, W, C]``. With no covered texel at all the map is returned unchanged.
    """
    if not isinstance(map, Tensor) or map.dim() != 3:
        raise AtlasError(f"map must be a tensor [H, W, C], got {tuple(map.shape) if isinstance(map, Tensor) else map}")
    if not map.is_floating_point():
        raise AtlasError(f"map must be floating point, got {map.dtype}")
    valid = _mask_hw1(mask, tuple(map.shape[:2]))[None, None]
    x = map.permute(2, 0, 1)[None]
    if pixels is None:
        return pull_push(map, valid[0, 0])
    if not isinstance(pixels, int) or pixels < 0:
        raise AtlasError(f"pixels must be an integer ≥ 0 or None, got {pixels!r}")
    return _rings(x, valid, pixels)[0][0].permute(1, 2, 0)


# --------------------------------------------------------------------------------------------
# composition and UVs


def compose(
    blocks: Sequence[Tensor], packing: Packing, gutter: int, coverage: Sequence[Tensor | None] | None = None,
    background: float = 0.0,
) -> Tensor:
    """Paste each material's texture ``[h, w, C]`` into its rectangle, dilated into its gutter.

    Each block is padded by ``gutter`` texels, its uncovered texels (``coverage`` ≤ 0, default none) and its
    gutter are filled by :func:`dilate` (``gutter`` rings, then push-pull for anything left), and the padded
    block is pasted. Padded boxes never overlap, so no material bleeds into another. Unused atlas texels
    are ``background``.

    Returns:
        ``[H_atlas, W_atlas, C]`` with the blocks' dtype and device.
    """
    if len(blocks) != len(packing.rects):
        raise AtlasError(f"got {len(blocks)} blocks for {len(packing.rects)} rectangles")
    coverage = list(coverage) if coverage is not None else [None] * len(blocks)
    width, height = packing.size
    ch = {b.shape[-1] for b in blocks}
    if len(ch) != 1:
        raise AtlasError(f"blocks must share a channel count, got {sorted(ch)}")
    ref = blocks[0]
    atlas = torch.full((height, width, ch.pop()), background, dtype=ref.dtype, device=ref.device)
    for k, (block, rect, cov) in enumerate(zip(blocks, packing.rects, coverage, strict=True)):
        if tuple(block.shape[:2]) != (rect.h, rect.w):
            raise AtlasError(f"block #{k} has size {tuple(block.shape[:2])} (h, w) but its rectangle is {rect}")
        valid = torch.ones(rect.h, rect.w, dtype=torch.bool, device=block.device)
        if cov is not None:
            valid = _mask_hw1(cov, (rect.h, rect.w))
        g = gutter
        x = F.pad(block.permute(2, 0, 1)[None], (g, g, g, g))
        pvalid = F.pad(valid[None, None].to(torch.uint8), (g, g, g, g)) > 0
        x, grown = _rings(x, pvalid, g)
        filled = pull_push(x[0].permute(1, 2, 0), grown[0, 0])
        y0, x0 = rect.y - g, rect.x - g
        y1, x1 = rect.y + rect.h + g, rect.x + rect.w + g
        sy0, sx0 = max(y0, 0), max(x0, 0)
        sy1, sx1 = min(y1, height), min(x1, width)
        atlas[sy0:sy1, sx0:sx1] = filled[sy0 - y0: sy1 - y0, sx0 - x0: sx1 - x0]
    return atlas


def extract(atlas: Tensor, rect: Rect) -> Tensor:
    """The ``[h, w, C]`` content of one rectangle (a view)."""
    if rect.y < 0 or rect.x < 0 or rect.y + rect.h > atlas.shape[0] or rect.x + rect.w > atlas.shape[1]:
        raise AtlasError(f"rectangle {rect} lies outside the atlas of size (h, w) {tuple(atlas.shape[:2])}")
    return atlas[rect.y: rect.y + rect.h, rect.x: rect.x + rect.w]


def rect_uv(rect: Rect, atlas_size: tuple[int, int]) -> tuple[float, float, float, float]:
    """The rectangle's UV bounds ``(u_min, v_min, u_max, v_max)`` (edges, not texel centres)."""
    width, height = atlas_size
    return (rect.x / width, 1.0 - (rect.y + rect.h) / height, (rect.x + rect.w) / width, 1.0 - rect.y / height)


def remap_uvs(uv: Tensor, rect: Rect, atlas_size: tuple[int, int], tolerance: float = 1e-6) -> Tensor:
    """Rewrite UVs of a material's own map into its rectangle of the atlas.

    ``u' = (x + u·w)/W``, ``v' = 1 − (y + (1 − v)·h)/H``: an affine map that sends the centre of texel
    (i, j) of the material's ``[h, w]`` map to the centre of atlas texel (y + i, x + j), so nearest and
    bilinear lookups inside the rectangle return the same values as before.

    Args:
        uv: ``[..., 2]`` in [0, 1] (values within ``tolerance`` outside are clamped).
        rect: the material's :class:`Rect`. atlas_size: ``(width, height)``.

    Raises:
        AtlasError: UVs outside [0, 1] — tiled (wrapping) textures cannot share an atlas.
    """
    if not isinstance(uv, Tensor) or uv.shape[-1] != 2:
        raise AtlasError(f"uv must be a tensor [..., 2], got {tuple(uv.shape) if isinstance(uv, Tensor) else uv}")
    out = (uv < -tolerance) | (uv > 1 + tolerance)
    if out.any():
        raise AtlasError(
            f"{int(out.any(-1).sum())} UV(s) lie outside [0, 1] (range {uv.min().item():.4g}..{uv.max().item():.4g});"
            " a tiled (wrapping) texture cannot be packed into an atlas — unwrap the mesh into [0, 1] first"
        )
    uv = uv.clamp(0.0, 1.0)
    width, height = atlas_size
    u = (rect.x + uv[..., 0] * rect.w) / width
    v = 1.0 - (rect.y + (1.0 - uv[..., 1]) * rect.h) / height
    return torch.stack([u, v], dim=-1)
