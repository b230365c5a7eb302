"""Photometric help: light intensities from a known-albedo region (capture.photometric.calibrate_lights) and the
HDR merge of bracketed exposures (merge_hdr), on synthetic scenes and images whose true values are known."""

import json
import warnings

import numpy as np
import pytest
import torch

from capture.cli import main
from capture.dataset import load_dataset
from capture.photo import PhotoModel
from capture.photometric import CalibrationError, HDRWarning, UVRegion, calibrate_lights, merge_hdr
from capture.synth import make_synthetic, small_scene
from renderer.imageio import encode, write_exr, write_png

#: the unknown factors the declared intensities are off by, per light index (red-ish first light)
FACTORS = [(2.7, 1.9, 1.3), (0.5, 0.6, 0.8)]


def _scene(tmp_path, name, *, rig="fixed", photo=None, supersample=4):
    """A Lambert sphere (albedo 0.18 everywhere) rendered with the true intensities; scene.json then declares each
    light's intensity divided by its factor. Returns (folder, true intensities per view and light)."""
    out = tmp_path / name
    cfg = small_scene("lambert", image_size=64, n_views=4, light_rig=rig, uniform={"albedo": 0.18},
                      supersample=supersample, photo=photo or PhotoModel())
    make_synthetic(cfg, out)
    doc = json.loads((out / "scene.json").read_text())
    true = [[list(light["intensity"]) for light in e["lights"]] for e in doc["images"]]
    for e in doc["images"]:
        for j, light in enumerate(e["lights"]):
            light["intensity"] = [x / f for x, f in zip(light["intensity"], FACTORS[j], strict=True)]
    (out / "scene.json").write_text(json.dumps(doc))
    return out, true


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return _scene(tmp_path_factory.mktemp("clean"), "ds")


def test_calibration_recovers_the_true_intensities_and_writes_a_new_dataset(clean, tmp_path):
    ds, true = clean
    before = (ds / "scene.json").read_text()
    cal = calibrate_lights(ds, UVRegion(np.ones((64, 64), bool)), 0.18, out=tmp_path / "calibrated")
    assert len(cal.lights) == 2 and cal.pixels > 1000 and cal.views == 4
    for j, e in enumerate(cal.lights):
        err = np.abs(np.array(e.estimate) / np.array(true[0][j]) - 1)
        assert err.max() < 0.01, (e.label, e.estimate, true[0][j])
        assert np.allclose(e.scale, FACTORS[j], rtol=0.01)
        assert all(s > 0 for s in e.stderr) and e.residual < 0.05
    assert (ds / "scene.json").read_text() == before          # input untouched
    written = load_dataset(tmp_path / "calibrated")
    got = written.views[2].lights[1].intensity.double().numpy()
    assert np.allclose(got, true[2][1], rtol=0.01)
    assert "photometric_calibration" in written.meta
    assert not list(tmp_path.glob(".calibrated.tmp-*"))
    with pytest.raises(CalibrationError, match="already exists"):
        calibrate_lights(ds, UVRegion(np.ones((64, 64), bool)), 0.18, out=tmp_path / "calibrated")


def test_pixel_centre_photos_give_the_intensities_exactly(tmp_path):
    ds, true = _scene(tmp_path, "centres", supersample=1)
    cal = calibrate_lights(ds, UVRegion(np.ones((64, 64), bool)), 0.18, supersample=1)
    for j, e in enumerate(cal.lights):
        assert np.allclose(e.estimate, true[0][j], rtol=1e-5)
    assert max(cal.relative_residual) < 1e-5


def test_standard_error_covers_the_error_with_photo_noise(tmp_path):
    ds, true = _scene(tmp_path, "noisy", photo=PhotoModel(full_well=300.0, read_noise=0.01))
    cal = calibrate_lights(ds, UVRegion(np.ones((64, 64), bool)), 0.18)
    z = []
    for j, e in enumerate(cal.lights):
        z += list(np.abs(np.array(e.estimate) - np.array(true[0][j])) / np.array(e.stderr))
        assert np.abs(np.array(e.estimate) / np.array(true[0][j]) - 1).max() < 0.05
    assert max(z) < 4.0, z   # within 4 standard errors on each of the 6 estimates


def test_card_masks_from_a_folder_and_a_shared_scale(clean, tmp_path):
    ds, true = clean
    masks = tmp_path / "cards"
    masks.mkdir()
    for i in range(4):
        m = np.zeros((64, 64), bool)
        m[16:48, 16:48] = True
        write_png(masks / f"{i:03d}.png", torch.from_numpy(m).double(), bits=8, transfer="linear")
    cal = calibrate_lights(ds, masks, [0.18, 0.18, 0.18])
    assert cal.meta["region"] == "image masks"
    for j, e in enumerate(cal.lights):
        assert np.abs(np.array(e.estimate) / np.array(true[0][j]) - 1).max() < 0.01
    # share='all': one scale per channel for lights declared alike; here they are not (different factors), so
    # the residual says the single scale does not explain the photos
    one = calibrate_lights(ds, masks, 0.18, share="all")
    assert len(one.lights) == 1 and one.lights[0].residual > 10 * cal.lights[0].residual


def test_a_light_that_never_lights_the_region_is_refused(clean, tmp_path):
    ds, _ = clean
    doc = json.loads((ds / "scene.json").read_text())
    bad = tmp_path / "bad"
    import shutil

    shutil.copytree(ds, bad)
    for e in doc["images"]:
        # a third light behind the sphere as seen from each camera: it lights only what no photo shows
        R, t = np.array(e["camera"]["R"]), np.array(e["camera"]["t"])
        centre = -R.T @ t
        e["lights"].append({"type": "point", "position": (-3.0 * centre).tolist(), "intensity": [10.0, 10.0, 10.0]})
    (bad / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=r"images\[\*\]\.lights\[2\] never light"):
        calibrate_lights(bad, UVRegion(np.ones((64, 64), bool)), 0.18)


def test_inputs_are_validated_with_the_fix(clean, tmp_path):
    ds, _ = clean
    with pytest.raises(CalibrationError, match="grey card is 0.18"):
        calibrate_lights(ds, UVRegion(np.ones((64, 64), bool)), 1.5)
    with pytest.raises(CalibrationError, match="ambiguous"):
        calibrate_lights(ds, np.ones((64, 64), bool), 0.18)
    with pytest.raises(CalibrationError, match="share must be"):
        calibrate_lights(ds, UVRegion(np.ones((64, 64), bool)), 0.18, share="some")
    with pytest.raises(CalibrationError, match="no card mask found"):
        calibrate_lights(ds, tmp_path, 0.18)
    with pytest.raises(CalibrationError, match="selects no texel"):
        calibrate_lights(ds, UVRegion(np.zeros((8, 8), bool)), 0.18)


# ----------------------------------------------------------------------------------------------
# HDR


def _brackets(L, times, bits):
    top = (1 << bits) - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    return [np.round(np.clip(L * t, 0, 1) * top).astype(dtype) for t in times]


def _truth(seed=0):
    rng = np.random.default_rng(seed)
    L = np.exp(rng.uniform(np.log(1e-3), np.log(1e2), (48, 48, 3)))
    L[:3] = 2500.0          # saturated in every bracket (t_min = 1e-3 → 2.5 × the level)
    L[3, :, 0] = 5000.0     # one channel so
    return L


@pytest.mark.parametrize("bits", [16, 8])
def test_merge_recovers_a_known_linear_image(bits):
    L = _truth()
    times = np.geomspace(1e-3, 1.0, 11)
    br = _brackets(L, times, bits)
    r = merge_hdr(br, times, response="linear")
    rad = r.radiance.double().numpy()
    top = (1 << bits) - 1
    codes = np.stack(br).astype(np.int64)
    unsat = (codes < top).any(0)                                   # per channel, some bracket unsaturated
    best = np.where(codes < top, codes, 0).max(0)                  # its best-exposed code
    well = unsat & (best >= (50 if bits == 8 else 0))
    rel = np.abs(rad / L - 1)
    assert rel[well].max() < 0.01, rel[well].max()
    assert well.mean() > (0.45 if bits == 8 else 0.9)
    assert np.array_equal(r.saturated.numpy(), (~unsat).any(-1))
    assert r.saturated[:4].all() and not r.saturated[4:].any()
    assert np.allclose(rad[:3], 1.0 / 1e-3)                        # the lower bound there


def test_merge_of_float_brackets_and_files(tmp_path):
    L = _truth(1)[8:]
    times = [1e-3, 1e-2, 1e-1, 1.0]
    files = []
    for k, t in enumerate(times):
        files.append(tmp_path / f"b{k}.exr")
        write_exr(files[-1], torch.from_numpy(np.clip(L * t, 0, 1)).float())
    r = merge_hdr(files, times)
    rel = np.abs(r.radiance.double().numpy() / L - 1)
    assert np.nanmax(rel[L * 1e-3 < 1]) < 1e-3
    out = tmp_path / "merged.exr"
    assert main(["merge-hdr", *map(str, files), "--times", *map(str, times), "--out", str(out)]) == 0
    assert out.is_file()


def test_opencv_estimates_the_response_of_8bit_srgb_brackets():
    L = _truth(2)[4:]
    times = np.geomspace(1e-3, 1.0, 6)
    br = [(encode(torch.from_numpy(np.clip(L * t, 0, 1)), "srgb").numpy() * 255).round().astype(np.uint8)
          for t in times]
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        r = merge_hdr(br, times)
    assert any(issubclass(x.category, HDRWarning) and "estimated" in str(x.message) for x in w)
    assert r.response == "estimate" and np.isfinite(r.radiance.numpy()).all()
    assert r.radiance.shape == (44, 48, 3)


def test_merge_inputs_are_validated():
    with pytest.raises(CalibrationError, match="one time per exposure"):
        merge_hdr([np.zeros((4, 4, 3))] * 2, [1.0])
    with pytest.raises(CalibrationError, match="positive"):
        merge_hdr([np.zeros((4, 4, 3))] * 2, [1.0, 0.0])
    with pytest.raises(CalibrationError, match="differ in size"):
        merge_hdr([np.zeros((4, 4, 3)), np.zeros((5, 4, 3))], [1.0, 2.0])


def test_cli_calibrate_lights(clean, tmp_path, capsys):
    ds, true = clean
    uv = tmp_path / "uv.png"
    write_png(uv, torch.ones(64, 64, dtype=torch.float64), bits=8, transfer="linear")
    assert main(["calibrate-lights", str(ds), "--uv-mask", str(uv), "--albedo", "0.18",
                 "--out", str(tmp_path / "new")]) == 0
    text = capsys.readouterr().out
    assert "wrote" in text and "images[*].lights[0]" in text
    got = load_dataset(tmp_path / "new").views[0].lights[0].intensity.double().numpy()
    assert np.allclose(got, true[0][0], rtol=0.01)
    assert main(["calibrate-lights", str(ds), "--albedo", "0.18", "--out", str(tmp_path / "x")]) == 2
