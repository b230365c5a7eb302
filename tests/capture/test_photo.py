"""Photo model: exposure, Poisson shot noise (variance ∝ signal), read noise, exact clipping mask,
8/16-bit sRGB quantisation that round-trips through write_png/read_png, seeding, input checks."""

import math

import numpy as np
import pytest
import torch

from capture.photo import PhotoError, PhotoModel, quantize_srgb
from renderer.imageio import decode, encode, read_png, write_png


def _flat(level, n=200):
    return torch.full((n, n, 3), float(level))


def test_ideal_camera_is_exposure_times_radiance():
    L = torch.rand(32, 24, 3, generator=torch.Generator().manual_seed(1)) * 3
    img, clipped = PhotoModel(exposure=0.75).apply(L)
    assert img.dtype == torch.float32 and torch.equal(img, (0.75 * L.double()).float())
    assert not clipped.any()  # clipping off by default: values above 1 are kept
    assert img.max() > 1.5


@pytest.mark.parametrize("full_well,read", [(1000.0, 0.0), (400.0, 0.01), (None, 0.02)])
def test_noise_variance_proportional_to_signal(full_well, read):
    pm = PhotoModel(full_well=full_well, read_noise=read)
    g = torch.Generator().manual_seed(7)
    levels = [0.02, 0.1, 0.3, 0.6]
    var, mean = [], []
    for s in levels:
        img, _ = pm.apply(_flat(s), g)  # 120 000 samples per level
        x = img.double().reshape(-1)
        mean.append(x.mean().item())
        var.append(x.var().item())
    n = 200 * 200 * 3
    for s, m, v in zip(levels, mean, var, strict=True):
        expect = (s / full_well if full_well else 0.0) + read**2
        assert abs(m - s) < 5 * math.sqrt(expect / n)  # unbiased
        assert abs(v / expect - 1) < 0.03  # sample variance: relative s.d. sqrt(2/n) ≈ 0.4 %
    if full_well:  # slope of variance vs signal is 1/full_well (the gain)
        slope = np.polyfit(levels, var, 1)[0]
        assert abs(slope * full_well - 1) < 0.03
        assert torch.allclose(pm.variance(torch.tensor(levels, dtype=torch.float64)),
                              torch.tensor(levels, dtype=torch.float64) / full_well + read**2)


def test_shot_noise_counts_whole_electrons():
    pm = PhotoModel(full_well=50.0)
    img, _ = pm.apply(_flat(0.3, 40), 3)
    e = img.double() * 50
    assert torch.allclose(e, e.round(), atol=1e-4) and e.min() >= 0


def test_seeding():
    pm = PhotoModel(full_well=100.0, read_noise=0.01)
    a, _ = pm.apply(_flat(0.4, 16), 5)
    b, _ = pm.apply(_flat(0.4, 16), torch.Generator().manual_seed(5))
    c, _ = pm.apply(_flat(0.4, 16), 6)
    assert torch.equal(a, b) and not torch.equal(a, c)
    with pytest.raises(PhotoError, match="pass rng"):
        pm.apply(_flat(0.4, 4))


def test_clipping_mask_exact():
    L = torch.full((8, 8, 3), 0.25)
    L[1, 2, 0] = 0.51  # × exposure 2 → 1.02: clipped
    L[3, 3, :] = 0.5  # → exactly 1.0: not above 1, not clipped
    L[5, 6, 2] = 10.0
    L[7, 7, 1] = 0.5000001  # just above
    img, clipped = PhotoModel(exposure=2.0, clip=True).apply(L)
    expect = torch.zeros(8, 8, dtype=torch.bool)
    expect[1, 2] = expect[5, 6] = expect[7, 7] = True
    assert torch.equal(clipped, expect)
    assert img.max() == 1.0 and img[1, 2, 0] == 1.0 and img[1, 2, 1] == 0.5 and img[3, 3, 0] == 1.0
    # with noise the mask is still exactly "some channel above 1 before clipping"
    pm = PhotoModel(exposure=1.0, read_noise=0.05, clip=True)
    L = torch.full((64, 64, 3), 0.98)
    img, clipped = pm.apply(L, 11)
    g = torch.Generator().manual_seed(11)
    raw = L.double() + 0.05 * torch.randn((64, 64, 3), generator=g, dtype=torch.float64)
    assert torch.equal(clipped, (raw > 1).any(-1)) and 0 < clipped.float().mean() < 1
    assert torch.equal(img, raw.clamp_max(1).float())


def test_srgb_quantisation_step_and_codes():
    x = torch.linspace(0, 1, 100001, dtype=torch.float64).reshape(1, -1, 1).expand(1, -1, 3)
    img, clipped = PhotoModel(clip=True, encoding="srgb").apply(x)
    enc = encode(img.double(), "srgb") * 255
    assert torch.allclose(enc, enc.round(), atol=2e-4)  # every value is a code
    assert len(torch.unique(enc.round())) == 256  # and every code occurs on the ramp
    assert (enc - encode(x, "srgb") * 255).abs().max() <= 0.5 + 1e-4  # nearest code
    # the step in linear units is the sRGB code step: 1/255/12.92 at the bottom, larger at the top
    codes = torch.arange(256, dtype=torch.float64) / 255
    steps = decode(codes[1:], "srgb") - decode(codes[:-1], "srgb")
    assert math.isclose(steps[0].item(), 1 / 255 / 12.92, rel_tol=1e-6) and steps[-1] > 0.008
    assert not clipped.any()


@pytest.mark.parametrize("bits", [8, 16])
def test_quantised_values_round_trip_through_png(tmp_path, bits):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(33, 17, 3, generator=g, dtype=torch.float64) ** 2
    codes, val = quantize_srgb(x, bits)
    write_png(tmp_path / "a.png", val, bits=bits, transfer="srgb")
    back = read_png(tmp_path / "a.png", "srgb")
    assert torch.equal(back, val)
    raw = read_png(tmp_path / "a.png", "linear")
    assert torch.equal(torch.round(raw.double() * ((1 << bits) - 1)).long(), codes)


def test_png_values_clamped_negative_noise():
    img, _ = PhotoModel(read_noise=0.05, clip=True, encoding="srgb").apply(torch.zeros(32, 32, 3), 1)
    assert img.min() == 0.0 and img.max() > 0
    lin, _ = PhotoModel(read_noise=0.05).apply(torch.zeros(32, 32, 3), 1)
    assert lin.min() < 0  # linear EXR keeps the unbiased negative values


def test_half_rounding():
    L = torch.rand(8, 8, 3, generator=torch.Generator().manual_seed(2))
    img, _ = PhotoModel(half=True).apply(L)
    assert torch.equal(img, L.half().float())


def test_settings_validation_and_dict_round_trip():
    for bad in (dict(exposure=0.0), dict(exposure=float("nan")), dict(full_well=-1.0), dict(read_noise=-0.1),
                dict(encoding="jpeg"), dict(bits=12), dict(encoding="srgb", clip=False)):
        with pytest.raises(PhotoError):
            PhotoModel(**bad)
    pm = PhotoModel(exposure=2.0, full_well=300.0, read_noise=0.01, clip=True, encoding="srgb", bits=16)
    assert PhotoModel.from_dict(pm.to_dict()) == pm and pm.saturation == 65535
    assert PhotoModel().saturation is None and PhotoModel(clip=True).saturation == 1.0


def test_input_validation():
    pm = PhotoModel()
    with pytest.raises(PhotoError, match="NaN"):
        pm.apply(torch.tensor([[[float("nan"), 0.0, 0.0]]]))
    with pytest.raises(PhotoError, match="≥ 0"):
        pm.apply(torch.full((2, 2, 3), -0.5))
    with pytest.raises(PhotoError, match=r"\[H, W, C\]"):
        pm.apply(torch.zeros(4, 3))
