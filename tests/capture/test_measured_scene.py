"""Captures of measured materials (NBRDF fits of MERL): region layout, rendering through the decoder, the dataset's
truth block, and one reconstruction as a regression test."""


import pytest
import torch

import materials
import materials.measured  # noqa: F401  registers "measured"
from capture.bench.measured import capture_benchmark
from capture.dataset import load_dataset
from capture.synth import measured as M
from renderer.shading import shade

pytestmark = pytest.mark.nbrdf


def _small(**kw):
    base = dict(n_views=4, image_size=48, texture_size=32, mesh_options={"segments": 24, "rings": 12})
    base.update(kw)
    return M.measured_scene(**base)


def test_region_map_is_equal_vertical_stripes():
    r = M.region_map(4, 64)
    assert r.shape == (64, 64) and r.dtype == torch.long
    assert torch.equal(r[0], r[-1])  # stripes in u: every row alike
    assert r[0].tolist() == [1] * 16 + [2] * 16 + [3] * 16 + [4] * 16
    assert M.region_map(3, (30, 10)).shape == (10, 30)
    with pytest.raises(M.MeasuredSceneError, match="n_regions"):
        M.region_map(0, 8)


def test_config_rejects_unknown_or_repeated_materials():
    with pytest.raises(M.MeasuredSceneError, match="unknown measured material 'unobtainium'"):
        M.measured_scene(materials=("nickel", "unobtainium"))
    with pytest.raises(M.MeasuredSceneError, match="distinct"):
        M.measured_scene(materials=("nickel", "nickel"))


def _views(cfg):
    images, views, preps, mesh, regions = M.render_measured_scene(cfg)
    return images, views, preps, mesh, regions


def test_one_material_scene_equals_the_renderers_own_shading():
    """With one region, render_measured must equal renderer.shading.shade of the measured model (no maps)."""
    cfg = _small(materials=("red-fabric2",))
    images, views, preps, mesh, regions = _views(cfg)
    model = materials.get("measured", material="red-fabric2")
    for img, prep in zip(images, preps, strict=True):
        ref = prep.gbuffer.to_image(shade(model, {}, prep, sampling="nearest"))
        torch.testing.assert_close(img, ref, rtol=0, atol=0)
        assert img.max() > 0.01  # lit


def test_each_pixel_is_made_of_its_nearest_texels_material():
    """Independent path: evaluate every material on every sample and pick by the nearest texel's region."""
    cfg = _small(materials=("nickel", "red-fabric2", "violet-rubber"))
    images, views, preps, mesh, regions = _views(cfg)
    models = cfg.models()
    seen = set()
    for img, prep in zip(images, preps, strict=True):
        tex, _ = prep.texels(*regions.shape, "nearest")
        rid = regions.reshape(-1)[tex]
        out = torch.zeros(prep.n_samples, 3)
        for term in prep.lights:
            every = torch.stack([m.cosine_brdf(term.angles, {}) for m in models])  # [K, M, 3]
            pick = every[rid[term.local] - 1, torch.arange(len(term.local))]
            out.index_add_(0, term.index, term.irradiance * pick)
        torch.testing.assert_close(img, prep.gbuffer.to_image(out), rtol=1e-6, atol=1e-7)
        seen |= set(rid.unique().tolist())
    assert seen == {1, 2, 3}  # the orbit sees every region


def test_dataset_has_no_gt_maps_and_records_the_truth_in_meta(tmp_path):
    cfg = _small()
    path = M.make_measured_scene(cfg, tmp_path / "ds", views=[0, 2])
    ds = load_dataset(path)
    assert ds.gt is None and len(ds.views) == 2
    regions, names = M.read_truth(ds)
    assert torch.equal(regions, M.region_map(4, 32))
    assert names == dict(enumerate(M.DEFAULT_MATERIALS, start=1))
    assert "NBRDF fits" in ds.meta["measured"]["attribution"]
    # the written images are the rendered ones (linear EXR, float32)
    images, *_ = _views(cfg)
    torch.testing.assert_close(ds.load_images()[1].radiance, images[2], rtol=1e-6, atol=1e-7)
    with pytest.raises(M.MeasuredSceneError, match="views"):
        M.make_measured_scene(cfg, tmp_path / "bad", views=[7])


def test_geometry_matches_capture_synthetic():
    """Same cameras and lights as capture.synth builds for the same fields."""
    from capture.synth import build_cameras, build_lights, build_mesh, small_scene

    cfg = M.measured_scene()
    syn = small_scene("lambert", image_size=96, texture_size=64, n_views=12)
    mesh = build_mesh(syn.mesh, syn.mesh_options)
    cams, rots = build_cameras(syn, mesh)
    lights = build_lights(syn, mesh, cams, rots)
    _, views, _, _, _ = _views(cfg)
    for c, ls, v in zip(cams, lights, views, strict=True):
        torch.testing.assert_close(c.center, v.camera.center)
        torch.testing.assert_close(torch.as_tensor(ls[0].position), torch.as_tensor(v.lights[0].position))


@pytest.mark.slow
def test_capture_of_the_default_measured_scene_regression(tmp_path):
    """The default scene (4 NBRDF fits of MERL, 12 views, every 4th held out), reconstructed with lambert and
    ggx-lambert. Measured (docs/measured-fits.md, "Capture of measured materials"): held-out PSNR 17.8 / 23.4 dB,
    SSIM 0.961 / 0.980; the Lambert albedo of red-fabric2 (nearly Lambertian) within 5 % of fit_brdf's Lambert fit
    of the same material on every channel. Thresholds leave ~1.5 dB / 0.01 SSIM of margin."""
    from capture import brdf_fit

    rows = capture_benchmark(M.measured_scene(), models=("lambert", "ggx-lambert"), work_dir=tmp_path,
                             fit_reference=False)
    lam, ggx = rows
    assert lam["error"] is None and ggx["error"] is None
    assert lam["psnr"] > 16.0 and lam["ssim"] > 0.95
    assert ggx["psnr"] > 21.5 and ggx["ssim"] > 0.97
    assert ggx["psnr"] > lam["psnr"] + 3.0  # a specular lobe matters on silver/nickel
    assert ggx["psnr_train"] > ggx["psnr"] + 10.0  # per-texel fits overfit the few views each texel sees
    fit = brdf_fit.fit_brdf("lambert", materials.get("measured", material="red-fabric2"),
                            brdf_fit.make_samples(resolution=16, dtype=torch.float64), restarts=1)
    cap = torch.tensor(lam["regions"]["red-fabric2"]["params"]["albedo"], dtype=torch.float64)
    torch.testing.assert_close(cap, fit.params["albedo"], rtol=0.08, atol=0.0)
    assert lam["regions"]["red-fabric2"]["observed_texels"] > 600


@pytest.mark.slow
def test_auto_picks_the_specular_model_on_the_measured_scene(tmp_path):
    """auto judges by the held-out mean absolute error (docs/reconstruction.md, "Model selection"): on its own
    split of the 9 training views measured lambert 0.0423, ggx-lambert 0.0398 (−6 %), gotanda2012-layered 0.0439 →
    ggx-lambert, 28.8 dB on the benchmark's held-out views. With the RMSE (highlight pixels dominate) it kept
    lambert (17.8 dB). The 6 % gain is near the 5 % threshold: a failure here means the selection changed, to be
    looked at."""
    (row,) = capture_benchmark(M.measured_scene(), models=("auto",), work_dir=tmp_path, fit_reference=False)
    assert row["error"] is None
    assert row["chosen"] == "ggx-lambert", row["chosen"]
    assert row["psnr"] > 25.0
