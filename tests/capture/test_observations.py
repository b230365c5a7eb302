"""Observations: flat samples, prediction, subsets, coverage, and real G-buffers."""

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
