"""Observations: flat samples, prediction, subsets, coverage, and real G-buffers."""

import math

import torch

import materials
from capture.observations import DROP_REASONS, observe_views, synthetic_observations


def test_predict_matches_direct_model_sum():
    model = materials.get("lambert")
    maps = {"albedo": torch.full((2, 2, 3), 0.5, dtype=torch.float64)}
    obs = synthetic_observations(model, maps, samples_per_texel=3, n_lights=2, irradiance=2.0)
    # Lambert: L = Σ_lights E · ρ/π · n·l
    nl = obs.angles.nl.reshape(2, -1).clamp_min(0)              # [lights, S]
    expect = (2.0 * 0.5 / torch.pi * nl).sum(0)
    torch.testing.assert_close(obs.radiance[:, 0], expect)


def test_select_views_and_coverage():
    model = materials.get("lambert")
    maps = {"albedo": torch.full((3, 3, 3), 0.5, dtype=torch.float64)}
    obs = synthetic_observations(model, maps, samples_per_texel=8, n_views=4)
    sub = obs.select_views([0, 1])
    assert set(sub.view.tolist()) <= {0, 1}
    assert sub.n_pairs == 2 * sub.n_samples
    torch.testing.assert_close(sub.radiance, obs.radiance[torch.isin(obs.view, torch.tensor([0, 1]))])
    assert obs.samples_per_texel().sum() == obs.n_samples
    assert (obs.views_per_texel() <= 4).all() and (obs.views_per_texel() >= 1).all()


def test_observe_views_counts_drops_on_a_rendered_sphere():
    from renderer.camera import look_at
    from renderer.gbuffer import render_gbuffer
    from renderer.lights import PointLight
    from renderer.mesh import uv_sphere
    from renderer.shading import prepare, shade

    mesh = uv_sphere(segments=24, rings=12)
    cam = look_at((0.0, -3.0, 0.0), width=48, height=48)
    light = PointLight((3.0, -1.0, 0.0), 9.0)                      # lights one side only
    g = render_gbuffer(mesh, cam)
    prep = prepare(g, mesh, [light])
    model = materials.get("lambert")
    maps = {"albedo": torch.full((16, 16, 3), 0.6)}
    img = g.to_image(shade(model, maps, prep, sampling="nearest"))
    img[0, 0] = float("nan")                                       # background pixel: counted as background
    ys, xs = torch.nonzero(img[..., 0] > 0, as_tuple=True)
    img[ys[0], xs[0]] = float("nan")                               # one lit pixel → nonfinite
    img[ys[1], xs[1]] = 10.0                                       # one saturated pixel → clipped
    obs = observe_views([prep], [img], (16, 16), saturation=5.0, lights=[light])
    assert set(obs.drops) == set(DROP_REASONS)
    assert obs.drops["nonfinite"] == 1 and obs.drops["clipped"] == 1
    assert obs.drops["background"] == 48 * 48 - len(g)
    assert obs.drops["unlit"] > 0                                  # the far side of the sphere
    assert sum(obs.drops.values()) + obs.n_samples == 48 * 48
    pred = obs.predict(model, obs.per_sample({"albedo": maps["albedo"]}))
    torch.testing.assert_close(pred, obs.radiance, rtol=1e-5, atol=1e-6)


def test_noise_residual_reads_the_noise_and_not_smooth_shading():
    from capture.observations import noise_residual

    gen = torch.Generator().manual_seed(0)
    H = W = 200
    y, x = torch.meshgrid(torch.linspace(0, 1, H, dtype=torch.float64), torch.linspace(0, 1, W, dtype=torch.float64),
                          indexing="ij")
    # any quadratic (planes, x², y², xy) is annihilated by Immerkær's mask: the residual is pure noise
    smooth = (0.3 + 0.2 * x - 0.1 * y + 0.4 * x * x - 0.3 * y * y + 0.25 * x * y)[..., None].expand(H, W, 3)
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[90:110, 50:70] = False                                   # a hole (background, clipped pixels)
    r = noise_residual(smooth, valid)
    ok = torch.isfinite(r).all(-1)
    assert float(r[ok].abs().max()) < 1e-12
    # NaN exactly where the 3 × 3 neighbourhood leaves the valid pixels or the image
    expect = torch.zeros(H, W, dtype=torch.bool)
    expect[1:-1, 1:-1] = True
    expect[89:111, 49:71] = False
    assert torch.equal(ok, expect)
    # white noise of std σ on top reads σ (std of the residual), per channel
    sigma = torch.tensor([0.01, 0.05, 0.2], dtype=torch.float64)
    noisy = smooth + sigma * torch.randn(H, W, 3, generator=gen, dtype=torch.float64)
    std = noise_residual(noisy, valid)[ok].std(0)
    torch.testing.assert_close(std, sigma, rtol=0.03, atol=0)


def test_photo_noise_ratio_by_hand():
    from types import SimpleNamespace

    from capture.fit.noise import NOISE, noise_sigma, photo_noise_ratio

    gen = torch.Generator().manual_seed(1)
    y = torch.rand(20000, 3, generator=gen, dtype=torch.float64) * 2
    sig = noise_sigma(y, NOISE)
    for k in (0.5, 3.0):
        e = k * sig * torch.randn(20000, 3, generator=gen, dtype=torch.float64)
        e[:500] = float("nan")                                        # pixels whose neighbourhood left the object
        e[500:700] = 100.0                                            # edges, highlights: outliers the quantile ignores
        ratio = photo_noise_ratio(SimpleNamespace(radiance=y, noise_residual=e), NOISE)
        # the 10 % quantile of 58 500 χ²₁ values has a relative std of 2.5 % (p(1 − p) / (n f(q)²))
        assert abs(ratio / k**2 - 1) < 0.1, (k, ratio)
    # a noise model of 3 % instead of 1 %: the same photos read 9× less
    assert abs(photo_noise_ratio(SimpleNamespace(radiance=y, noise_residual=e), (0.03, 0.1)) / 1.0 - 1) < 0.1
    assert photo_noise_ratio(SimpleNamespace(radiance=y, noise_residual=None), NOISE) is None
    assert photo_noise_ratio(SimpleNamespace(radiance=y[:30], noise_residual=e[600:630]), NOISE) is None
    # a channel the material absorbs entirely reads 0 in every pixel, residual 0: left out, not a quiet photo
    y0, e0 = y.clone(), e.clone()
    y0[:, 2], e0[:, 2] = 0.0, 0.0
    ratio = photo_noise_ratio(SimpleNamespace(radiance=y0, noise_residual=e0), NOISE)
    assert abs(ratio / 9.0 - 1) < 0.1, ratio


def test_noise_floor_by_hand():
    # the data cost per residual of residuals one noise σ large: σ = 1 % of the radiance above a floor of 10 % of the
    # median, times √ratio when the photos are noisier than that model; weighted like the data term
    from types import SimpleNamespace

    from capture.fit.noise import NOISE, noise_floor

    y = torch.tensor([[1.0, 2.0, 4.0], [0.1, 0.0, 3.0], [2.0, 2.0, 2.0]], dtype=torch.float64)
    w = torch.tensor([1.0, 3.0, 2.0], dtype=torch.float64)
    # the samples' mean radiances 7/3, 1.1/3, 2: median 2, so σ ≥ 0.01 · 0.2
    sig = 0.01 * torch.tensor([[1.0, 2.0, 4.0], [0.2, 0.2, 3.0], [2.0, 2.0, 2.0]], dtype=torch.float64)
    by_hand = float((sig.square().sum(-1) * w).sum() / (3 * w.sum()))
    obs = SimpleNamespace(radiance=y, weight=w)
    assert math.isclose(noise_floor(obs, NOISE, None, "l2", 1.0), by_hand, rel_tol=1e-12)
    assert math.isclose(noise_floor(obs, NOISE, 0.3, "l2", 1.0), by_hand, rel_tol=1e-12)      # never below the model
    assert math.isclose(noise_floor(obs, NOISE, 25.0, "l2", 1.0), 25.0 * by_hand, rel_tol=1e-12)
    # huber with δ below some residuals: 2δ|r| − δ² there
    d = 0.02
    rho = torch.where(sig <= d, sig.square(), 2 * d * sig - d * d)
    assert math.isclose(noise_floor(obs, NOISE, None, "huber", d), float((rho.sum(-1) * w).sum() / (3 * w.sum())),
                        rel_tol=1e-12)


# -- TexelTaps: ragged texture footprints -----------------------------------------------------------------------------

def test_texel_taps_read_select_cat_and_move_like_the_padded_rows():
    """Ragged taps built from one block of padded rows (zero weights dropped) read a map as the dense weighted gather
    does; a selection keeps its rows' taps in order, a concatenation appends rows, and ``to`` casts the weights
    only."""
    from capture.observations import TexelTaps

    gen = torch.Generator().manual_seed(3)
    N, K, T = 50, 7, 40
    idx = torch.randint(0, T, (N, K), generator=gen)
    w = torch.rand(N, K, generator=gen, dtype=torch.float64) * (torch.rand(N, K, generator=gen) < 0.5)
    w[:, 0] += 0.1                                               # every row reads at least one texel
    taps = TexelTaps.from_blocks([(torch.arange(N), idx, w)], N)                # one block of padded rows
    assert taps.n_rows == N and int(taps.start[-1]) == int((w != 0).sum()) and taps.index.dtype == torch.int32
    assert bool((taps.weight > 0).all()) and torch.equal(taps.counts(), (w != 0).sum(1))
    flat = torch.rand(T, 3, generator=gen, dtype=torch.float64)
    dense = (flat[idx] * w[..., None]).sum(1)
    assert torch.allclose(taps.read(flat), dense, rtol=0, atol=1e-12)
    keep = torch.rand(N, generator=gen) < 0.4
    assert torch.allclose(taps.select(keep).read(flat), dense[keep], rtol=0, atol=1e-12)
    both = TexelTaps.cat([taps.select(keep), taps.select(~keep)])
    assert torch.allclose(both.read(flat), torch.cat([dense[keep], dense[~keep]]), rtol=0, atol=1e-12)
    f32 = taps.to(dtype=torch.float32)
    assert f32.weight.dtype == torch.float32 and f32.index.dtype == torch.int32 and torch.equal(f32.start, taps.start)
    # blocks of rows in any order and of their own widths: the same taps, each row's in column order
    perm = torch.randperm(N, generator=gen)
    a, b = perm[:20], perm[20:]
    blocks = TexelTaps.from_blocks([(a, idx[a], w[a]), (b, idx[b, :5], w[b, :5])], N)
    w5 = w.clone()
    w5[b, 5:] = 0
    assert torch.allclose(blocks.read(flat), (flat[idx] * w5[..., None]).sum(1), rtol=0, atol=1e-12)
    row0 = int(a[0])
    assert torch.equal(blocks.index[blocks.start[row0]:blocks.start[row0 + 1]].long(), idx[row0][w[row0] != 0])


def _two_view_sphere(swap: bool = True):
    """Two views of a lit sphere, prepared, with their photos and the scene's lights; the second view lists its
    lights in the other order than the scene when ``swap``."""
    from renderer.camera import look_at
    from renderer.gbuffer import render_gbuffer
    from renderer.lights import PointLight
    from renderer.mesh import uv_sphere
    from renderer.shading import prepare, shade

    mesh = uv_sphere(segments=24, rings=12)
    lights = [PointLight((3.0, -1.0, 0.0), 9.0), PointLight((-2.0, -2.0, 1.0), 4.0)]
    cams = [look_at((0.0, -3.0, 0.0), width=32, height=32), look_at((2.0, -2.0, 1.0), width=40, height=40)]
    views = [[lights[0]], [lights[1], lights[0]] if swap else lights]
    model = materials.get("lambert")
    maps = {"albedo": torch.rand(16, 16, 3, generator=torch.Generator().manual_seed(1))}
    preps, photos = [], []
    for cam, lt in zip(cams, views, strict=True):
        g = render_gbuffer(mesh, cam)
        preps.append(prepare(g, mesh, lt))
        photos.append(g.to_image(shade(model, maps, preps[-1], sampling="nearest")))
    return preps, photos, lights


def test_view_extractor_one_view_at_a_time_equals_observe_views():
    from capture.observations import ViewExtractor

    preps, photos, lights = _two_view_sphere()
    for given in (lights, None):                             # None: the first view's lights
        whole = observe_views(preps, photos, (16, 16), lights=given, bilinear=True, exposure=[1.0, 2.0])
        ex = ViewExtractor(2, (16, 16), exposure=[1.0, 2.0])
        parts = [ex.view(i, preps[i], photos[i]) for i in range(2)]
        streamed = ex.observations(parts, lights=given, bilinear=True)
        for f in ("texel", "radiance", "weight", "pair_sample", "pair_light", "irradiance", "view", "pixel", "uv",
                  "n", "v", "bilinear_index", "bilinear_weight", "noise_residual"):
            a, b = getattr(whole, f), getattr(streamed, f)
            assert a.shape == b.shape and torch.allclose(a, b, rtol=0, atol=0, equal_nan=True), f
        assert whole.drops == streamed.drops and whole.n_lights == streamed.n_lights
        # the pairs name the scene's lights, not a view's own order of them (by default the first view's lights:
        # the second light, which the first view lacks, is then -1)
        pair_view = whole.view[whole.pair_sample]
        assert set(whole.pair_light[pair_view == 0].tolist()) == {0}
        assert set(whole.pair_light[pair_view == 1].tolist()) == ({0, 1} if given else {0, -1})
    # the same pairs, each with the same light and irradiance, as when the view lists its lights in the scene's order
    o_preps, o_photos, o_lights = _two_view_sphere(swap=False)
    ordered = observe_views(o_preps, o_photos, (16, 16), lights=o_lights)
    whole = observe_views(preps, photos, (16, 16), lights=lights)

    def pairs(o):
        return sorted(zip(o.pair_sample.tolist(), o.pair_light.tolist(), o.irradiance[:, 0].tolist(), strict=True))
    assert pairs(whole) == pairs(ordered)


def test_view_extractor_refuses_what_it_cannot_join():
    import pytest

    from capture.observations import ObservationError, TexelTaps, ViewExtractor

    preps, photos, lights = _two_view_sphere()
    ex = ViewExtractor(2, (16, 16))
    with pytest.raises(ObservationError, match="outside the 2 views"):
        ex.view(2, preps[0], photos[0])
    with pytest.raises(ObservationError, match="need the 2 views"):
        ex.observations([ex.view(0, preps[0], photos[0])])
    parts = [ex.view(i, preps[i], photos[i]) for i in range(2)]
    ex.observations(parts, lights=lights)
    with pytest.raises(ObservationError, match="already joined"):
        ex.observations(parts, lights=lights)
    # one view with texture footprints and the other without
    fx = ViewExtractor(2, (16, 16), footprints=True)
    n0 = preps[0].gbuffer.pixel.numel()
    taps = TexelTaps(torch.arange(n0 + 1), torch.zeros(n0, dtype=torch.int32), torch.ones(n0))
    mixed = [fx.view(0, preps[0], photos[0], taps), fx.view(1, preps[1], photos[1])]
    with pytest.raises(ObservationError, match="some views have texture footprints"):
        fx.observations(mixed, bilinear=True)
    with pytest.raises(ObservationError, match="some views have texture footprints"):   # refused before any change
        fx.observations(mixed, bilinear=True)
    with pytest.raises(ObservationError, match="one mask per view"):
        ViewExtractor(2, (16, 16), clipped=[torch.zeros(32, 32, dtype=torch.bool)])


def test_sub_pixel_samples_keep_only_what_is_read():
    """With texture footprints, the sub-pixel samples keep their texel (the one their uv falls in) but no uv, and no
    normals, view directions or noise per sample — unless an environment light reads the normals and view
    directions: then they are kept, and a view without one has zeros there. What they keep equals the full
    extraction's."""
    from capture.observations import TexelTaps, ViewExtractor
    from renderer.lights import HemisphereLight
    from renderer.shading import prepare

    preps, photos, lights = _two_view_sphere()
    full = observe_views(preps, photos, (16, 16), lights=lights)

    def footprints(ps):
        fx = ViewExtractor(2, (16, 16), footprints=True)
        taps = [TexelTaps(torch.arange(len(p.gbuffer) + 1), torch.zeros(len(p.gbuffer), dtype=torch.int32),
                          torch.ones(len(p.gbuffer))) for p in ps]
        return fx.observations([fx.view(i, ps[i], photos[i], taps[i]) for i in range(2)], lights=lights,
                               bilinear=True)

    sub = footprints(preps)
    assert sub.uv is None and sub.n is None and sub.v is None and sub.noise_residual is None
    for f in ("texel", "radiance", "pair_sample", "pair_light", "irradiance", "view", "pixel"):
        assert torch.equal(getattr(sub, f), getattr(full, f)), f
    # an environment light in the second view only: its samples' vectors are kept, the first view's are zeros
    from renderer.mesh import uv_sphere

    sky = HemisphereLight(torch.tensor([0.2, 0.3, 0.4]), torch.tensor([0.05, 0.05, 0.05]), torch.tensor([0.0, 0.0, 1.]))
    env = [preps[0], prepare(preps[1].gbuffer, uv_sphere(segments=24, rings=12), [lights[1], lights[0], sky])]
    full = observe_views(env, photos, (16, 16), lights=lights)
    sub = footprints(env)
    first = sub.view == 0
    assert sub.n is not None and sub.v is not None and len(sub.env_terms) == 1
    assert not bool(sub.n[first].any()) and not bool(sub.v[first].any())
    assert torch.equal(sub.n[~first], full.n[~first]) and torch.equal(sub.v[~first], full.v[~first])
    assert torch.equal(sub.texel, full.texel) and torch.equal(sub.env_terms[0][1], full.env_terms[0][1])
