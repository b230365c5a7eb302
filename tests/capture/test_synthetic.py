"""Synthetic scenes: procedural ground truth (exact model params, ranges, regions, edges, gradients),
rigs that see the mesh, light placement and irradiance, nearest sampling, highlight coverage, speed."""

import math
import time

import pytest
import torch

import materials
from capture.dataset import camera_sees_mesh, load_dataset
from capture.photo import PhotoModel
from capture.synth import (
    REGION_NAMES,
    SyntheticConfig,
    SyntheticError,
    build_scene,
    default_scene,
    highlight_coverage,
    make_synthetic,
    procedural_maps,
    render_scene,
    small_scene,
)
from materials import presets
from materials.microfacet import ndf_ggx
from materials.roughness import half_max_angle
from renderer.gbuffer import render_gbuffer
from renderer.shading import prepare, shade
from renderer.texture import texel_of


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.nbrdf) if n == "measured" else n
                                  for n in sorted(materials.available())])
def test_procedural_maps_hold_exactly_the_model_params_in_range(name):
    model = materials.get(name)
    maps, regions = procedural_maps(model, (48, 36))
    assert set(maps) == set(model.param_names)
    for spec in model.params:
        m = maps[spec.name]
        assert m.shape == (36, 48, spec.channels) and m.dtype == torch.float32
        assert torch.isfinite(m).all() and m.min() >= spec.low and m.max() <= spec.high
        spec.check(m)
    assert regions.shape == (36, 48) and set(regions.unique().tolist()) == set(REGION_NAMES)


def test_region_layout_and_materials():
    T = 60
    maps, regions = procedural_maps(materials.get("gotanda2012-layered"), T)
    # stripes in u: column j belongs to region floor((j + 0.5)/T · 6) + 1, the same in every row
    col = ((torch.arange(T) + 0.5) / T * 6).floor().long() + 1
    assert torch.equal(regions, col.expand(T, T))
    reg = lambda k: regions == k  # noqa: E731
    gold = presets.f0("gold")
    assert torch.allclose(maps["f0"][reg(3)], gold.expand(int(reg(3).sum()), 3))
    assert torch.allclose(maps["f0"][reg(4)], presets.f0("copper").expand(int(reg(4).sum()), 3))
    assert maps["albedo"][reg(3) | reg(4)].abs().max() == 0  # metals: no diffuse
    assert maps["absorption"][~reg(5)].abs().max() == 0 and (maps["absorption"][reg(5)] > 0).all()
    assert torch.allclose(maps["roughness"][reg(1)], torch.tensor(0.75))
    assert torch.allclose(maps["roughness"][reg(2)], torch.tensor(0.25))
    # sharp edges: across every stripe border the parameters jump
    for j in range(1, T):
        if col[j] != col[j - 1]:
            jump = sum((maps[k][:, j] - maps[k][:, j - 1]).abs().max() for k in ("albedo", "f0", "roughness"))
            assert jump > 0.05, j
    # the checker inside region 1 is a sharp two-colour albedo pattern
    assert len(torch.unique(maps["albedo"][reg(1)], dim=0)) == 2
    # smooth gradients in region 6: roughness decreases with v (increases down the rows), in small steps
    r6 = maps["roughness"][:, col == 6, 0]
    d = r6[1:] - r6[:-1]
    assert (d > 0).all() and d.max() < 0.02 and r6.max() - r6.min() > 0.7
    a6 = maps["albedo"][:, col == 6, 0]
    assert ((a6[:, 1:] - a6[:, :-1]) < 0).all()


def test_pure_diffuse_model_gets_coloured_metal_regions():
    maps, regions = procedural_maps(materials.get("lambert"), 30)
    assert torch.allclose(maps["albedo"][regions == 3][0], 0.9 * presets.f0("gold"))


@pytest.mark.parametrize("mesh", ["uv_sphere", "torus", "nonconvex", "plane"])
@pytest.mark.parametrize("rig", ["orbit", "turntable", "random"])
def test_every_rig_sees_every_mesh(mesh, rig):
    cfg = small_scene(mesh=mesh, camera_rig=rig, n_views=3, image_size=32, texture_size=16,
                      elevations=(30.0, 60.0) if mesh == "plane" else (15.0, 50.0))
    scene = build_scene(cfg)
    assert len(scene.views) == 3
    for v in scene.views:
        assert camera_sees_mesh(v.camera, scene.mesh.vertices, scene.mesh.faces)[0]
        assert render_gbuffer(scene.mesh, v.camera).coverage > 0.05


def test_flash_lights_placement_and_irradiance():
    cfg = small_scene(n_views=4, light_offset_deg=20.0, light_irradiance=2.5)
    scene = build_scene(cfg)
    target = 0.5 * (scene.mesh.bounds[0] + scene.mesh.bounds[1]).double()
    for v in scene.views:
        c = v.camera.center.double() - target
        assert len(v.lights) == 2
        for light in v.lights:
            p = light.position.double() - target
            ang = math.degrees(math.acos((p @ c / (p.norm() * c.norm())).clamp(-1, 1)))
            assert abs(ang - 20.0) < 1e-3
            E = light.intensity.double() / (p @ p)  # irradiance at the target
            assert torch.allclose(E, torch.full((3,), 2.5, dtype=torch.float64), rtol=1e-5)


def test_turntable_studio_lights_turn_with_the_camera():
    cfg = small_scene(camera_rig="turntable", light_rig="fixed", n_views=4, n_lights=1)
    scene = build_scene(cfg)
    target = 0.5 * (scene.mesh.bounds[0] + scene.mesh.bounds[1]).double()
    angles = []
    for v in scene.views:
        c = v.camera.center.double() - target
        p = v.lights[0].position.double() - target
        angles.append(math.acos(float(p @ c / (p.norm() * c.norm()))))
    assert max(angles) - min(angles) < 1e-5  # fixed relative to the camera in the studio
    a, b = scene.views[0].lights[0].position, scene.views[1].lights[0].position
    assert (a - b).norm() > 0.5  # but moving in the object's frame


def test_nearest_sampling_each_pixel_reads_one_texel():
    cfg = small_scene(model="lambert", n_views=1, image_size=48, texture_size=16, sampling="nearest")
    scene = build_scene(cfg)
    view = scene.views[0]
    g = render_gbuffer(scene.mesh, view.camera, 1)
    prep = prepare(g, scene.mesh, view.lights)
    base = shade(scene.model, scene.maps, prep, sampling="nearest")
    tex = texel_of(g.uv, 16, 16)
    k = int(tex[prep.sample][len(prep.sample) // 2])  # a texel that is seen and lit
    maps = {"albedo": scene.maps["albedo"].clone()}
    maps["albedo"].view(-1, 3)[k] += 0.1
    changed = (shade(scene.model, maps, prep, sampling="nearest") != base).any(-1)
    assert changed.any() and torch.equal(changed, (tex == k) & changed)
    # bilinear spreads the same change over neighbouring texels' samples
    base_b = shade(scene.model, scene.maps, prep, sampling="bilinear")
    changed_b = (shade(scene.model, maps, prep, sampling="bilinear") != base_b).any(-1)
    assert changed_b.sum() > changed.sum()


def test_half_max_angle_is_the_ggx_half_maximum():
    r = torch.tensor([0.1, 0.3, 0.5, 0.7, 0.8], dtype=torch.float64)
    theta = half_max_angle(r)
    alpha = (r**2)[:, None]
    ratio = ndf_ggx(torch.cos(theta)[:, None], alpha) / ndf_ggx(torch.ones_like(alpha), alpha)
    assert torch.allclose(ratio, torch.full_like(ratio, 0.5), rtol=1e-6)
    assert torch.allclose(theta[:2], 0.6436 * r[:2] ** 2, rtol=0.02)  # ≈ sqrt(√2 − 1)·α for small α
    assert half_max_angle(torch.tensor([0.95, 1.0], dtype=torch.float64)).eq(math.pi / 2).all()


def test_highlight_coverage_brute_force():
    cfg = small_scene(n_views=3, image_size=40, texture_size=16)
    scene = build_scene(cfg)
    _, preps = render_scene(scene, cfg)
    rough = scene.maps["roughness"]
    cov = highlight_coverage(preps, (16, 16), rough, scene.regions)
    # brute force over every (sample, light) pair
    cos_t = torch.cos(half_max_angle(rough.reshape(-1)).clamp_min(math.radians(1.0)))
    seen, high = set(), set()
    for p in preps:
        seen |= set(texel_of(p.uv, 16, 16).tolist())
        for t in p.lights:
            n = p.n[t.local].double()
            h = torch.nn.functional.normalize(t.l.double() + p.v[t.local].double(), dim=-1)
            tex = texel_of(p.uv[t.local], 16, 16)
            ok = (n * h).sum(-1) >= cos_t[tex] - 1e-6
            high |= set(tex[ok].tolist())
    assert cov["observed_texels"] == len(seen)
    assert abs(cov["highlight_texels"] - len(high)) <= 2  # float32 angles vs float64 vectors at the threshold
    assert 0 < cov["coverage"] < 1
    # a fully rough surface shows "highlights" wherever it is lit
    assert highlight_coverage(preps, (16, 16), torch.ones(16, 16, 1))["coverage"] == 1.0


def test_small_scene_is_cheap_and_loads(tmp_path):
    make_synthetic(small_scene(n_views=1, image_size=16, texture_size=8), tmp_path / "warm")
    # Timed on one intra-op thread: on a loaded 2-core CI machine torch's OpenMP threads oversubscribe
    # and this scene of many tiny ops took 3.2-3.8 s with 2 threads against 0.4 s with 1 (measured).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t = time.perf_counter()
        out = make_synthetic(small_scene(), tmp_path / "s")
        dt = time.perf_counter() - t
    finally:
        torch.set_num_threads(threads)
    assert dt < 2.0, f"small_scene took {dt:.2f} s"
    ds = load_dataset(out)
    assert len(ds) == 4 and ds.views[0].camera.width == 96 and ds.gt.maps["albedo"].shape == (64, 64, 3)
    assert ds.meta["config"]["model"] == {"name": "ggx-lambert", "options": {}}
    cov = ds.meta["highlight_coverage"]
    assert 0 < cov["coverage"] <= 1 and set(cov["per_region"]) == {str(k) for k in REGION_NAMES}


def test_noisy_png_scene_records_photo_and_clipping(tmp_path):
    photo = PhotoModel(exposure=1.0, full_well=500.0, read_noise=0.003, clip=True, encoding="srgb")
    out = make_synthetic(small_scene(n_views=2, image_size=48, texture_size=32, photo=photo, seed=3), tmp_path / "n")
    ds = load_dataset(out)
    assert ds.encoding == "srgb" and ds.gt.photo["full_well"] == 500.0
    clipped = ds.meta["clipped_pixels"]
    sat = [int(p.saturated.sum()) for p in ds.load_images()]
    assert all(s >= c for s, c in zip(sat, clipped, strict=True)) and sum(clipped) > 0  # GGX highlights exceed 1


def test_default_scene_matches_the_readme_demo():
    cfg = default_scene()
    assert cfg.n_views == 16 and cfg.image_size == (256, 256) and cfg.texture_size == (256, 256)
    assert cfg.model == {"name": "ggx-lambert", "options": {}} and cfg.n_lights == 2
    assert cfg.photo.noise_free and cfg.photo.encoding == "linear" and not cfg.photo.clip
    assert default_scene(n_views=4).n_views == 4


@pytest.mark.parametrize("bad,match", [
    (dict(n_views=0), "n_views"), (dict(camera_rig="crane"), "camera_rig"), (dict(light_rig="sun"), "light_rig"),
    (dict(sampling="cubic"), "sampling"), (dict(image_size=(0, 4)), "image_size"),
    (dict(model="nope"), "unknown model"),
    (dict(elevations=(95.0,)), "elevations"), (dict(light_irradiance=-1.0), "light_irradiance"),
    (dict(materials=0), "materials"), (dict(materials=7), "materials"),
    (dict(uniform={"sheen": 0.5}), "no parameter 'sheen'"), (dict(uniform={"roughness": 1.5}), "outside its range"),
    (dict(uniform={"f0": [0.1, 0.2]}), "3 channel"), (dict(uniform={"albedo": "red"}), "number"),
])
def test_config_validation(bad, match):
    with pytest.raises(SyntheticError, match=match):
        SyntheticConfig(**bad)


def test_number_of_materials_and_uniform_overrides():
    model = materials.get("ggx-lambert")
    maps, regions = procedural_maps(model, 48, n_materials=2)
    assert set(torch.unique(regions).tolist()) == {1, 2}
    # stripe 2 is the smooth dielectric of the table: r = 0.25 everywhere in it
    assert torch.allclose(maps["roughness"][regions == 2], torch.tensor(0.25))
    maps, _ = procedural_maps(model, 48, uniform={"roughness": 0.02, "f0": [1.0, 1.0, 1.0]})
    assert torch.equal(maps["roughness"], torch.full_like(maps["roughness"], 0.02))
    assert torch.equal(maps["f0"], torch.ones_like(maps["f0"]))
    assert not torch.equal(maps["albedo"], torch.ones_like(maps["albedo"]))  # untouched maps stay procedural
    cfg = SyntheticConfig(model="ggx-lambert", uniform={"albedo": 0.0}, materials=3)
    assert cfg.uniform == {"albedo": [0.0]} and cfg.to_dict()["materials"] == 3
