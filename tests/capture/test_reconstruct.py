"""End-to-end reconstruction on small synthetic scenes, and bad input."""

import json

import pytest
import torch

from capture.dataset import DatasetError
from capture.reconstruct import ReconstructionError, reconstruct
from capture.synthetic import make_synthetic, small_scene


@pytest.fixture(scope="module")
def lambert_ds(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds") / "lambert"
    make_synthetic(small_scene("lambert", image_size=96, texture_size=32, n_views=4, sampling="nearest"), root)
    return root


def test_lambert_scene_recovered_exactly(lambert_ds, tmp_path):
    # measured: albedo RMSE 2.3e-8, max 1.2e-7 (float32) on the 752 observed texels
    rep = reconstruct(lambert_ds, model="lambert", out_dir=tmp_path / "out", progress=False)
    err = rep.errors["maps"]["albedo"]
    assert err["texels"] > 500 and err["rmse"] < 1e-5 and err["max"] < 1e-4
    out = tmp_path / "out"
    for name in ("albedo.exr", "albedo.png", "coverage.exr", "mesh.obj", "report.json", "summary.txt", "views.png"):
        assert (out / name).is_file(), name
    r = json.loads((out / "report.json").read_text())
    assert r["model"] == "lambert" and r["samples"]["valid"] > 0
    assert sum(r["drops"].values()) + r["samples"]["valid"] == r["samples"]["pixels"]
    assert "f0" in r["skipped"]["parameters_not_allocated"]
    assert min(v["psnr"] for v in r["views"]) > 60


def test_auto_stops_at_lambert_for_a_lambert_scene(lambert_ds, tmp_path):
    rep = reconstruct(lambert_ds, model="auto", out_dir=tmp_path / "auto", progress=False, iterations=10, grid=8)
    assert rep.model == "lambert"
    assert rep.selection[0]["model"] == "lambert" and len(rep.selection) == 2


def test_bad_input(lambert_ds, tmp_path):
    with pytest.raises(ReconstructionError, match="lambert"):          # lists available names
        reconstruct(lambert_ds, model="no-such-model", out_dir=tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()
    (tmp_path / "exists").mkdir()
    with pytest.raises(ReconstructionError, match="exists"):
        reconstruct(lambert_ds, model="lambert", out_dir=tmp_path / "exists", progress=False)
    with pytest.raises(DatasetError):
        reconstruct(tmp_path / "exists", model="lambert", out_dir=tmp_path / "y", progress=False)
    assert not (tmp_path / "y").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]     # no temporary left over


@pytest.mark.slow
def test_ggx_lambert_scene_refits_the_photos(tmp_path):
    # nearest sampling, noise free: the fitted maps re-render the photos (measured PSNR ≥ 64 dB);
    # the maps themselves are only identifiable where texels see enough distinct geometry, see
    # docs/reconstruction.md for the measured map errors
    root = tmp_path / "ggx"
    make_synthetic(small_scene("ggx-lambert", image_size=96, texture_size=32, n_views=6, sampling="nearest"), root)
    rep = reconstruct(root, model="ggx-lambert", out_dir=tmp_path / "o", progress=False, dtype=torch.float64,
                      iterations=30)
    assert min(v["psnr"] for v in rep.views) > 50
    assert rep.coverage["unobservable"]["roughness"] > 0
