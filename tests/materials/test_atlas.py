"""materials.atlas: Schüler encode/decode, packing properties, dilation, UV remapping."""

import math
import warnings

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from materials import atlas as A
from materials import presets
from materials.roughness import glossiness_to_roughness


def _maps(h=8, w=6, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return {
        "albedo": torch.rand(h, w, 3, generator=g, dtype=dtype),
        "f0": torch.rand(h, w, 3, generator=g, dtype=dtype),
        # keep r where g ∈ [0, 1]: r ∈ [0.15, 0.90]
        "roughness": 0.15 + 0.75 * torch.rand(h, w, 1, generator=g, dtype=dtype),
        "mask": (torch.rand(h, w, 1, generator=g, dtype=dtype) > 0.3).to(dtype),
    }


def _nearest(tex: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Independent nearest lookup with the DESIGN.md texel convention (u=(j+.5)/W, v=1-(i+.5)/H)."""
    h, w = tex.shape[:2]
    j = torch.floor(uv[..., 0] * w).long().clamp(0, w - 1)
    i = torch.floor((1 - uv[..., 1]) * h).long().clamp(0, h - 1)
    return tex[i, j]


# --------------------------------------------------------------------------------------------
# transfer and Schüler layout


def test_transfer_matches_renderer_imageio():
    io = pytest.importorskip("renderer.imageio")
    x = torch.linspace(0, 1, 2049, dtype=torch.float64)
    for t in ("srgb", "gamma2.2", "linear"):
        torch.testing.assert_close(A.transfer_encode(x, t), io.encode(x, t), atol=1e-12, rtol=0)
        torch.testing.assert_close(A.transfer_decode(x, t), io.decode(x, t), atol=1e-12, rtol=0)


def test_table_251_gray_levels_under_gamma22():
    # Schüler's Table 2.5.1: f0 → 8-bit gray by gamma 2.2; within the listed values' rounding
    for name, listed in (("polystyrene", 66), ("alumina", 80)):
        f0 = presets.f0(name, dtype=torch.float64)
        maps = {"albedo": torch.zeros(1, 1, 3, dtype=torch.float64), "f0": f0.expand(1, 1, 3),
                "roughness": torch.full((1, 1, 1), 0.5, dtype=torch.float64)}
        _, tex2 = A.encode_schuler(maps)
        code = 255 * tex2[0, 0, 0].item()
        assert abs(code - listed) < 1.0, (name, code)
        lo = 255 * (f0[0].item() - 0.005) ** (1 / 2.2)
        hi = 255 * (f0[0].item() + 0.005) ** (1 / 2.2)
        assert lo - 0.5 <= listed <= hi + 0.5
    # copper's listed colour 245;214;184 decodes into its listed 0.49–0.92
    tex = torch.tensor([245.0, 214.0, 184.0, 255.0], dtype=torch.float64).reshape(1, 1, 4) / 255
    f0 = A.decode_schuler(tex, tex)["f0"][0, 0]
    assert round(f0.min().item(), 2) == 0.49 and round(f0.max().item(), 2) == 0.92


@pytest.mark.parametrize("transfer", ["gamma2.2", "srgb"])
def test_round_trip_8bit_within_one_code(transfer):
    maps = _maps(16, 12, seed=3, dtype=torch.float64)
    t1, t2 = A.encode_schuler(maps, transfer)
    assert t1.shape == (16, 12, 4) and t2.shape == (16, 12, 4)
    assert 0 <= t1.min() and t1.max() <= 1 and 0 <= t2.min() and t2.max() <= 1
    q1, q2 = torch.round(t1 * 255) / 255, torch.round(t2 * 255) / 255
    back = A.decode_schuler(q1, q2, transfer)
    t1b, t2b = A.encode_schuler({k: back[k] for k in ("albedo", "f0", "roughness", "mask")}, transfer)
    # in encoded space the round trip is within the 8-bit rounding: half a code (≤ 1/255)
    assert (t1b - t1).abs().max() <= 0.5 / 255 + 1e-9
    assert (t2b - t2).abs().max() <= 0.5 / 255 + 1e-9
    # unquantised: exact inverse
    exact = A.decode_schuler(t1, t2, transfer)
    for k in ("albedo", "f0", "roughness", "mask"):
        torch.testing.assert_close(exact[k], maps[k], atol=1e-9, rtol=0)


def test_glossiness_channel_is_linear_g():
    r = torch.tensor([0.2, 0.5, 0.8], dtype=torch.float64).reshape(1, 3, 1)
    maps = {"albedo": torch.zeros(1, 3, 3, dtype=torch.float64), "f0": torch.zeros(1, 3, 3, dtype=torch.float64),
            "roughness": r}
    _, t2 = A.encode_schuler(maps)
    s = 2 / r**4 - 2
    torch.testing.assert_close(t2[..., 3:], torch.log2(s) / 12)
    # e = 2^(12 g) reproduces s
    torch.testing.assert_close(2 ** (12 * t2[..., 3:]), s)


def test_out_of_range_clamped_with_counts():
    maps = _maps(4, 4, dtype=torch.float64)
    maps["albedo"][0, 0, 0] = 1.5
    maps["albedo"][0, 1, 1] = -0.2
    maps["roughness"][1, 1, 0] = 0.05  # s > 4096 → g > 1
    maps["roughness"][2, 2, 0] = 1.0  # s = 0 → g < 0
    with pytest.warns(A.AtlasWarning, match=r"albedo: 1 below 0, 1 above 1.*glossiness g: 1 below 0, 1 above 1"):
        t1, t2 = A.encode_schuler(maps)
    assert t1[0, 0, 0] == 1 and t1[0, 1, 1] == 0
    assert t2[1, 1, 3] == 1 and t2[2, 2, 3] == 0
    # g = 0 and g = 1 decode to the ends of Schüler's range: r = (2/3)^(1/4) and (2/4098)^(1/4)
    back = A.decode_schuler(t1, t2)
    assert math.isclose(back["roughness"][2, 2, 0].item(), (2 / 3) ** 0.25, rel_tol=1e-12)
    assert math.isclose(back["roughness"][1, 1, 0].item(), (2 / 4098) ** 0.25, rel_tol=1e-12)
    torch.testing.assert_close(back["roughness"][1, 1], glossiness_to_roughness(torch.ones(1, dtype=torch.float64)))


def test_encode_bad_inputs():
    m = _maps()
    with pytest.raises(A.AtlasError, match="roughness"):
        A.encode_schuler({"albedo": m["albedo"], "f0": m["f0"]})
    bad = dict(m, f0=m["f0"].clone())
    bad["f0"][0, 0, 0] = float("nan")
    with pytest.raises(A.AtlasError, match="'f0' contains 1 NaN"):
        A.encode_schuler(bad)
    with pytest.raises(A.AtlasError, match="share one size"):
        A.encode_schuler(dict(m, roughness=torch.zeros(3, 3, 1)))
    with pytest.raises(A.AtlasError, match="transfer"):
        A.encode_schuler(m, "rec709")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        A.encode_schuler(m)  # in-range maps: no warning


# --------------------------------------------------------------------------------------------
# packing


def _check_packing(sizes, packing, gutter):
    width, height = packing.size
    occ = torch.zeros(height + 2 * gutter, width + 2 * gutter, dtype=torch.int32)
    for (w, h), r in zip(sizes, packing.rects, strict=True):
        assert (r.w, r.h) == (w, h)
        # content inside the atlas; its gutter may hang over the border (clamp-to-edge addressing)
        assert r.x >= 0 and r.y >= 0 and r.x + w <= width and r.y + h <= height
        occ[r.y: r.y + h + 2 * gutter, r.x: r.x + w + 2 * gutter] += 1
    # padded boxes never overlap: contents at least 2·gutter apart
    assert occ.max() <= 1


@given(
    sizes=st.lists(st.tuples(st.integers(1, 80), st.integers(1, 80)), min_size=1, max_size=12),
    gutter=st.integers(0, 6),
)
def test_packing_property_no_overlap_gutters(sizes, gutter):
    packing = A.pack_rectangles(sizes, None, gutter)
    _check_packing(sizes, packing, gutter)
    w, h = packing.size
    assert w % 4 == 0 and h % 4 == 0
    # tight: no side longer than one shelf of every box, and the size it reports fits as a fixed size
    assert max(w, h) <= max(sum(s[0] + 2 * gutter for s in sizes), max(s[1] for s in sizes)) + 3
    _check_packing(sizes, A.pack_rectangles(sizes, (w, h), gutter), gutter)
    p2 = A.pack_rectangles(sizes, "pow2", gutter)
    _check_packing(sizes, p2, gutter)
    side = p2.size[0]
    assert p2.size == (side, side) and side & (side - 1) == 0
    if side > 1 and side // 2 >= max(max(s) for s in sizes):  # the smallest power of two: half of it fails
        with pytest.raises(A.AtlasError, match="needs at least"):
            A.pack_rectangles(sizes, side // 2, gutter)


def test_one_material_fills_its_atlas():
    # no texel spent on a border gutter: one 256² material is a 256² atlas (100 % used)
    p = A.pack_rectangles([(256, 256)], None, gutter=4)
    assert p.size == (256, 256) and p.rects == [A.Rect(0, 0, 256, 256)]
    assert A.pack_rectangles([(256, 256)], "pow2", gutter=4).size == (256, 256)
    assert A.pack_rectangles([(250, 130)], None, gutter=4).size == (252, 132)  # multiples of 4
    # two: 2·gutter between them, nothing at the border; four 256²: a 520² square, 97 % used
    p = A.pack_rectangles([(256, 256)] * 2, None, gutter=4)
    assert p.size == (256, 520) and p.rects[1].y - (p.rects[0].y + 256) == 8
    p = A.pack_rectangles([(256, 256)] * 4, None, gutter=4)
    assert p.size == (520, 520)
    _check_packing([(256, 256)] * 4, p, 4)


def test_fixed_atlas_too_small_says_size_needed():
    with pytest.raises(A.AtlasError, match=r"atlas 64x64 is too small.*needs at least 138x200"):
        A.pack_rectangles([(100, 50), (30, 200)], 64, gutter=4)
    p = A.pack_rectangles([(100, 50), (30, 200)], (138, 200), gutter=4)
    assert p.size == (138, 200)
    _check_packing([(100, 50), (30, 200)], p, 4)
    p = A.pack_rectangles([(100, 50), (30, 200)], (300, 220), gutter=4)
    assert p.size == (300, 220)
    _check_packing([(100, 50), (30, 200)], p, 4)
    with pytest.raises(A.AtlasError, match="positive"):
        A.pack_rectangles([(0, 5)])
    with pytest.raises(A.AtlasError, match="non-empty"):
        A.pack_rectangles([])
    with pytest.raises(A.AtlasError, match="atlas_size must be"):
        A.pack_rectangles([(4, 4)], "square")
    with pytest.raises(A.AtlasError, match="gutter"):
        A.pack_rectangles([(4, 4)], None, -1)


# --------------------------------------------------------------------------------------------
# dilation


def test_dilate_rings_golden_and_keeps_covered():
    m = torch.zeros(6, 6, 1, dtype=torch.float64)
    m[2:4, 2:4, 0] = torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=torch.float64)
    cov = m[..., 0] > 0
    d1 = A.dilate(m, cov, 1)[..., 0]
    assert d1[1, 1] == 1.0  # only neighbour (2,2)
    assert d1[1, 2] == 1.5  # neighbours (2,2), (2,3)
    assert d1[2, 1] == 2.0  # (2,2), (3,2) → (1+3)/2
    assert d1[0, 0] == 0.0  # two rings away: untouched by one ring
    assert torch.equal(d1[2:4, 2:4], m[2:4, 2:4, 0])
    full = A.dilate(m, cov)  # push-pull: everything filled, covered unchanged
    assert (full[..., 0] > 0).all() and torch.equal(full[2:4, 2:4], m[2:4, 2:4])
    assert full.min() >= 1 and full.max() <= 4  # a convex combination of covered values


def test_dilate_vectorised_large_and_float32(device):
    g = torch.Generator().manual_seed(0)
    m = torch.rand(257, 129, 3, generator=g).to(device)
    cov = (torch.rand(257, 129, generator=g) > 0.9).to(device)
    out = A.dilate(m, cov)
    assert out.device.type == device.type and torch.isfinite(out).all()
    assert torch.equal(out[cov], m[cov])
    assert torch.equal(A.dilate(m, torch.zeros_like(cov)), m)


def test_pull_push_weights_each_block_by_its_known_texels():
    # 4 × 4: the top-left 2 × 2 block holds three known 0s, the top-right one known 1, the bottom half nothing
    m = torch.full((4, 4, 2), float("nan"), dtype=torch.float64)  # unknown texels may hold anything
    known = torch.zeros(4, 4, dtype=torch.bool)
    known[0, 0] = known[0, 1] = known[1, 0] = known[0, 2] = True
    m[0, 0] = m[0, 1] = m[1, 0] = 0.0
    m[0, 2] = 1.0
    out = A.pull_push(m, known)
    assert torch.equal(out[known], m[known])
    assert torch.equal(out[1, 1], torch.zeros(2, dtype=torch.float64))  # its own block's mean
    assert torch.equal(out[1, 3], torch.ones(2, dtype=torch.float64))
    # the bottom half takes the whole map's mean, each block weighted by its count: (3·0 + 1·1)/4, not (0 + 1)/2
    assert torch.equal(out[2:], torch.full((2, 4, 2), 0.25, dtype=torch.float64))
    assert torch.equal(A.dilate(m, known), out)  # the atlas gutters fill the same way
    # odd sizes: the 1 × 1 corner block of a 3 × 3 map counts its one texel, not four
    m3, k3 = torch.zeros(3, 3, 1, dtype=torch.float64), torch.zeros(3, 3, dtype=torch.bool)
    m3[2, 2], k3[0, 0], k3[2, 2] = 1.0, True, True
    assert A.pull_push(m3, k3)[0, 2, 0] == 0.5 and A.pull_push(m3, k3)[2, 0, 0] == 0.5
    assert torch.equal(A.pull_push(m, torch.zeros_like(known)).isnan(), m.isnan())  # nothing known: a copy
    with pytest.raises(A.AtlasError, match=r"\[H, W, C\]"):
        A.pull_push(m[..., 0], known)


def test_compose_no_bleed_between_materials():
    blocks = [torch.full((10, 7, 4), 0.25), torch.full((5, 9, 4), 0.75)]
    cov0 = torch.ones(10, 7, dtype=torch.bool)
    cov0[:, 3:] = False  # right part uncovered: filled from the left part
    blocks[0][:, 3:] = 9.0  # garbage in uncovered texels is replaced
    p = A.pack_rectangles([(7, 10), (9, 5)], None, 2)
    atlas = A.compose(blocks, p, 2, [cov0, None])
    r0, r1 = p.rects
    assert torch.equal(A.extract(atlas, r0), torch.full((10, 7, 4), 0.25))
    assert torch.equal(A.extract(atlas, r1), torch.full((5, 9, 4), 0.75))
    # the gutter rings (inside the atlas) hold each material's own value
    for r, value in ((r0, 0.25), (r1, 0.75)):
        ring = atlas[max(r.y - 2, 0): r.y + r.h + 2, max(r.x - 2, 0): r.x + r.w + 2]
        assert torch.equal(ring, torch.full_like(ring, value))


# --------------------------------------------------------------------------------------------
# UV remapping


def test_remap_uvs_keeps_every_texel_value():
    g = torch.Generator().manual_seed(5)
    maps = [torch.rand(12, 20, 3, generator=g), torch.rand(30, 8, 3, generator=g)]
    sizes = [(m.shape[1], m.shape[0]) for m in maps]
    p = A.pack_rectangles(sizes, None, 3)
    atlas = A.compose(maps, p, 3)
    for m, rect in zip(maps, p.rects, strict=True):
        h, w = m.shape[:2]
        # every texel centre, plus random points inside the map
        i, j = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        uv = torch.stack([(j + 0.5) / w, 1 - (i + 0.5) / h], -1).reshape(-1, 2)
        uv = torch.cat([uv, torch.rand(500, 2, generator=g) * 0.999 + 0.0005])
        before = _nearest(m, uv)
        after = _nearest(atlas, A.remap_uvs(uv, rect, p.size))
        assert torch.equal(before, after)
        lo_u, lo_v, hi_u, hi_v = A.rect_uv(rect, p.size)
        new = A.remap_uvs(uv, rect, p.size)
        assert (new[:, 0] >= lo_u).all() and (new[:, 0] <= hi_u).all()
        assert (new[:, 1] >= lo_v).all() and (new[:, 1] <= hi_v).all()


def test_remap_uvs_refuses_tiling():
    with pytest.raises(A.AtlasError, match="2 UV.*outside"):
        A.remap_uvs(torch.tensor([[1.5, 0.5], [0.2, -0.3], [0.5, 0.5]]), A.Rect(0, 0, 4, 4), (8, 8))
