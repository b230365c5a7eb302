"""materials.presets: Schüler's Table 2.5.1 against its own gray levels under gamma 2.2."""

import math

import pytest
import torch

from materials import presets


def _code(r: float) -> float:
    """Unrounded 8-bit gamma-2.2 code of a reflectance."""
    return 255.0 * r ** (1 / 2.2)


def test_table_has_every_row():
    assert presets.names() == ["water", "glass", "polystyrene", "calcite", "alumina", "diamond", "silicon",
                               "copper", "gold", "silver"]


@pytest.mark.parametrize("name", ["water", "glass", "polystyrene", "calcite", "alumina"])
def test_gray_rows_give_the_papers_gray_level_within_rounding(name):
    p = presets.PRESETS[name]
    r = p["reflectance"][0]
    code = p["code"][0]
    # listed reflectance has 2 decimals (±0.005), listed code is an integer (±0.5)
    assert _code(r - 0.005) - 0.5 <= code <= _code(r + 0.005) + 0.5
    assert p["f0"] == (r, r, r)


def test_gray_goldens():
    assert round(_code(0.05)) == 65 and abs(_code(0.05) - 66) < 1  # polystyrene: table says 66
    assert round(_code(0.08)) == 81 and abs(_code(0.08) - 80) < 1  # alumina: table says 80
    assert presets.PRESETS["polystyrene"]["code"] == (66, 66, 66)
    assert presets.PRESETS["alumina"]["code"] == (80, 80, 80)


@pytest.mark.parametrize("name", ["diamond", "silicon", "copper", "gold", "silver"])
def test_coloured_rows_f0_is_the_colour_decoded(name):
    p = presets.preset(name, dtype=torch.float64)
    codes = torch.tensor(p["code"], dtype=torch.float64)
    torch.testing.assert_close(p["f0"], (codes / 255) ** 2.2)
    # re-encoding gives the listed code back exactly
    assert torch.equal(torch.round(255 * p["f0"] ** (1 / 2.2)), codes)


def test_copper_decodes_into_its_listed_range():
    cu = presets.f0("copper", dtype=torch.float64)
    torch.testing.assert_close(cu, torch.tensor([0.91577, 0.68000, 0.48781], dtype=torch.float64), atol=5e-5, rtol=0)
    assert round(cu.min().item(), 2) == 0.49 and round(cu.max().item(), 2) == 0.92


@pytest.mark.parametrize("name", ["diamond", "silicon", "copper", "gold", "silver"])
def test_consistency_flag_matches_the_numbers(name):
    p = presets.PRESETS[name]
    lo, hi = p["reflectance"]
    f0 = p["f0"]
    # decoded channel min/max within the rounding of the listed range (2 decimals, plus half a code)
    def within(value, listed, code):
        band = max(abs((code + 0.5) / 255) ** 2.2 - (code / 255) ** 2.2, 0) + 0.005
        return abs(value - listed) <= band

    i_lo, i_hi = min(range(3), key=lambda i: f0[i]), max(range(3), key=lambda i: f0[i])
    ok = within(f0[i_lo], lo, p["code"][i_lo]) and within(f0[i_hi], hi, p["code"][i_hi])
    assert ok == p["consistent"]


def test_inconsistent_rows_are_silicon_and_silver():
    assert [n for n, p in presets.PRESETS.items() if not p["consistent"]] == ["silicon", "silver"]
    assert math.isclose(presets.PRESETS["silver"]["f0"][2], (239 / 255) ** 2.2)


def test_metals_near_white_dielectrics_single_digit_percent():
    # the paper's rule of thumb
    for name, p in presets.PRESETS.items():
        if p["kind"] == "metal":
            assert max(p["f0"]) > 0.9
        elif name != "diamond" and p["kind"] == "dielectric":
            assert max(p["f0"]) < 0.1


def test_preset_returns_fresh_tensor_on_device_and_dtype(device):
    a = presets.preset("Gold", dtype=torch.float64, device=device)
    assert a["f0"].dtype == torch.float64 and a["f0"].device.type == device.type
    a["f0"].zero_()
    assert presets.f0("gold").max() > 0.9


def test_unknown_name_lists_names():
    with pytest.raises(KeyError, match="water, glass, polystyrene"):
        presets.preset("unobtainium")
