"""The coarse-to-fine start of the footprint solve (capture.fit.fast: pyramid_size, upsample_maps, refine_from) and
its use by reconstruct on photos no shadecap code rendered."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

import materials
from capture.fit import SolverError, pyramid_size, solve_fast, upsample_maps
from capture.observations import synthetic_observations


def test_upsample_keeps_a_ramp_through_texel_centres_and_clamps_at_the_border():
    w = 8
    # a map whose value is its texel centre's u: bilinear upsampling with aligned centres reproduces u at the fine
    # centres, except within half a coarse texel of the border, where the read clamps to the first/last centre
    u = (torch.arange(w, dtype=torch.float64) + 0.5) / w
    ramp = u[None, :, None].expand(w, w, 1).contiguous()
    up = upsample_maps({"roughness": ramp, "albedo": torch.full((w, w, 3), 0.25)}, 4 * w)
    fine_u = (torch.arange(4 * w, dtype=torch.float64) + 0.5) / (4 * w)
    expect = fine_u.clamp(u[0], u[-1])
    assert up["roughness"].shape == (4 * w, 4 * w, 1) and up["roughness"].dtype == torch.float64
    assert torch.allclose(up["roughness"][3, :, 0], expect, atol=1e-12)
    assert up["albedo"].dtype == torch.float32 and bool((up["albedo"] == 0.25).all())


def _taps(size: int, step: int, region: int) -> SimpleNamespace:
    """Observations as pyramid_size reads them: one sample on every ``step``-th texel of a ``region``² corner of
    ``size``² maps, each reading the bilinear cell to its lower right."""
    i, j = torch.meshgrid(torch.arange(0, region, step), torch.arange(0, region, step), indexing="ij")
    i, j = i.reshape(-1), j.reshape(-1)
    taps = torch.stack([i * size + j, i * size + j + 1, (i + 1) * size + j, (i + 1) * size + j + 1], -1)
    return SimpleNamespace(map_size=(size, size), n_samples=int(i.numel()), texel=taps[:, 0], bilinear_index=taps)


def test_pyramid_size_halves_until_the_samples_cover_the_texels_they_read():
    # a sample on every 4th texel: at 128² it reads 4 texels of its own (0.25 per texel); at 64² its taps (4m, 4m + 1)
    # fall on one texel 2m (1 per texel), at 32² too, at 16² four samples share a texel (4 per texel)
    obs = _taps(128, 4, 64)
    assert pyramid_size(obs) == 64
    assert pyramid_size(obs, min_samples=0.25) == 128
    assert pyramid_size(obs, min_samples=2.0, min_size=16) == 16
    assert pyramid_size(obs, min_samples=2.0) == 32            # never below min_size (default 32)
    dense = _taps(128, 1, 64)                                # a sample per texel: ≈ 1 per texel read
    assert pyramid_size(dense, min_samples=0.9) == 128
    assert pyramid_size(SimpleNamespace(map_size=(128, 64), n_samples=1, texel=None, bilinear_index=None)) == 128


def test_sampled_map_size_halves_until_the_median_footprint_is_sampled():
    from capture.footprint import FOOTPRINT_SAMPLED, sampled_map_size
    from capture.observations import ObservationError

    def fp(f, size=(1024, 1024)):
        return SimpleNamespace(map_size=size, footprint_texels=torch.as_tensor(f, dtype=torch.float32))

    assert FOOTPRINT_SAMPLED == 3.0             # 6 × 6 texture sub-samples half a texel apart
    # the median pixel decides: 5.4 texels per pixel step at 1024² is 2.7 at 512²; 10.8 at 2048² too
    assert sampled_map_size(fp([1.0, 5.4, 5.4, 20.0, 5.4])) == 512
    assert sampled_map_size(fp([10.8] * 3, (2048, 2048))) == 512
    assert sampled_map_size(fp([2.7] * 3)) == 1024                    # sampled at full size: kept
    assert sampled_map_size(fp([3.0, 3.0, 100.0])) == 1024            # exactly at the limit: kept
    assert sampled_map_size(fp([1.0, 6.1, 6.1, 100.0])) == 256       # the lower median, 6.1: halved twice
    assert sampled_map_size(fp([5000.0] * 3)) == 1                    # down to the smallest size asked
    assert sampled_map_size(fp([5000.0] * 3), min_size=128) == 128
    assert sampled_map_size(fp([float("nan"), float("inf"), 5.4])) == 512   # non-finite footprints take no part
    assert sampled_map_size(fp([50.0], (1024, 512))) == 1024           # not square: as it is
    assert sampled_map_size(fp([5000.0], (24, 24))) == 3               # halved while even
    assert sampled_map_size(fp([])) == 1024
    with pytest.raises(ObservationError, match="min_size"):
        sampled_map_size(fp([5.4]), min_size=0)


def test_refine_from_checks_its_maps_and_needs_footprints():
    model = materials.get("lambert")
    gt = {"albedo": torch.full((4, 4, 3), 0.5, dtype=torch.float64)}
    obs = synthetic_observations(model, gt, samples_per_texel=4)
    with pytest.raises(SolverError, match="missing \\['albedo'\\]"):
        solve_fast(model, obs, refine_from={})
    with pytest.raises(SolverError, match="not fitted \\['f0'\\]"):
        solve_fast(model, obs, refine_from={**gt, "f0": gt["albedo"]})
    with pytest.raises(SolverError, match="footprints"):
        solve_fast(model, obs, refine_from=gt)
    with pytest.raises(SolverError, match="refine_steps must be an integer ≥ 0, got -1"):
        solve_fast(model, obs, refine_from=gt, refine_steps=-1)
    with pytest.raises(SolverError, match="refine_steps must be an integer ≥ 0, got True"):
        solve_fast(model, obs, refine_from=gt, refine_steps=True)
    with pytest.raises(SolverError, match="give the maps they start from"):
        solve_fast(model, obs, refine_steps=0)


# Measured (docs/reconstruction.md, "Maps finer than the photos"): the Mitsuba torus (8 views of 128², truth 64²)
# fitted on 256² maps — half a pixel centre per texel its reads reach — χ² per residual 0.013–0.015, albedo RMSE on
# observed texels 0.021–0.022 against the truth read at 256² (the bilinear interpolation Mitsuba renders); the same
# fit without the coarse level: χ² 0.018 and 0.236 (its texels left to the pixel-centre stages, which see
# almost none). Asserted with a 2× margin.
def test_maps_finer_than_the_photos_are_fitted_coarse_to_fine(mitsuba_scene, tmp_path):
    from capture.reconstruct import reconstruct
    from renderer.imageio import read_exr

    path = mitsuba_scene("torus-lambert")
    r = reconstruct(path, model="lambert", out_dir=tmp_path / "r", texture_size=256, progress=False)
    assert r.fit["pyramid"]["coarse_size"] == 128 and r.fit["refined_from"] == "maps"
    assert r.fit["chi2_per_residual"] < 0.03
    truth = upsample_maps({"albedo": torch.as_tensor(np.asarray(read_exr(path / "gt" / "albedo.exr")))}, 256)
    fit = torch.as_tensor(np.asarray(read_exr(tmp_path / "r" / "albedo.exr")))
    seen = torch.as_tensor(np.asarray(read_exr(tmp_path / "r" / "coverage.exr"))).reshape(256, 256, -1)[..., 0] > 0
    assert int(seen.sum()) > 15_000
    assert float((fit - truth["albedo"])[seen].square().mean().sqrt()) < 0.045


# Measured (2-core CPU): the Mitsuba torus's 8 views of 128² on 256² maps with GGX + Lambert — median footprint
# 4.3 texels per pixel step at 256², so the footprint steps run at 128² and their maps, upsampled, are judged at
# 256² without steps: albedo RMSE on observed texels 0.0277 against the truth read at 256² (0.0273 with three steps
# at 256², χ² 0.099), χ² per residual 5.2 from the upsampling between texel centres. Asserted with a 2× margin.
def test_footprint_steps_run_on_the_finest_maps_the_footprints_sample(mitsuba_scene, tmp_path):
    from capture.reconstruct import reconstruct
    from renderer.imageio import read_exr

    path = mitsuba_scene("torus-lambert")
    r = reconstruct(path, model="ggx-lambert", out_dir=tmp_path / "r", texture_size=256, progress=False)
    pyr = r.fit["pyramid"]
    assert (pyr["coarse_size"], pyr["level_size"], pyr["full_size"]) == (128, 128, 256)
    assert r.fit["refined_from"] == "maps" and "footprint_history" not in r.fit     # judged, no steps at 256²
    assert r.fit["chi2_per_residual"] < 10.5
    truth = upsample_maps({"albedo": torch.as_tensor(np.asarray(read_exr(path / "gt" / "albedo.exr")))}, 256)
    fit = torch.as_tensor(np.asarray(read_exr(tmp_path / "r" / "albedo.exr")))
    assert fit.shape[:2] == (256, 256)
    seen = torch.as_tensor(np.asarray(read_exr(tmp_path / "r" / "coverage.exr"))).reshape(256, 256, -1)[..., 0] > 0
    assert int(seen.sum()) > 15_000
    assert float((fit - truth["albedo"])[seen].square().mean().sqrt()) < 0.055


def test_the_summary_says_where_the_pyramid_ran():
    from capture.reconstruct import _pyramid_line

    before = _pyramid_line({"coarse_size": 128, "coarse_s": 1.0, "refine_s": 2.0}, 65536)   # a report without levels
    assert "ran on 128² maps first" in before and "footprint steps at full size" in before
    same = _pyramid_line({"coarse_size": 128, "level_size": 256, "full_size": 256, "coarse_s": 1.0, "refine_s": 2.0},
                         65536)
    assert same == before
    whole = _pyramid_line({"coarse_size": 128, "level_size": 128, "full_size": 256, "coarse_s": 1.0,
                           "refine_s": 2.0}, 65536)
    assert "the fit ran on 128² maps (1.0 s)" in whole and "upsampled to 256² and judged there (2.0 s)" in whole
    steps = _pyramid_line({"coarse_size": 256, "level_size": 512, "full_size": 2048, "coarse_s": 1.0, "level_s": 3.0,
                           "refine_s": 2.0}, 65536)
    assert "per-texel stages ran on 256² maps (1.0 s)" in steps and "footprint steps on 512² maps (3.0 s)" in steps
    assert "at most 3 texels per pixel step" in steps and "upsampled to 2048²" in steps
