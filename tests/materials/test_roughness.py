"""Roughness conversions: exact inverses, the paper's anchor values, finite gradients at the edges."""

import math

import pytest
import torch

from materials import roughness as R


def test_anchor_values():
    # α = r², s = 2/α² − 2, σ = √(2/s) (Gotanda 2012 eq 21), e = 2^(12 g) (Schüler).
    r = torch.tensor([0.5], dtype=torch.float64)
    assert R.roughness_to_alpha(r).item() == pytest.approx(0.25)
    assert R.roughness_to_shininess(r).item() == pytest.approx(2 / 0.0625 - 2)  # 30
    assert R.shininess_to_sigma(torch.tensor(8.0, dtype=torch.float64)).item() == pytest.approx(0.5)
    assert R.glossiness_to_shininess(torch.tensor(1.0, dtype=torch.float64)).item() == pytest.approx(4096.0)
    assert R.shininess_to_glossiness(torch.tensor(64.0, dtype=torch.float64)).item() == pytest.approx(0.5)
    # r = 1 → uniform Blinn-Phong (s = 0)
    assert R.roughness_to_shininess(torch.tensor(1.0, dtype=torch.float64)).item() == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(
    "fwd,inv,lo,hi",
    [
        (R.roughness_to_alpha, R.alpha_to_roughness, R.R_MIN, 1.0),
        (R.roughness_to_shininess, R.shininess_to_roughness, R.R_MIN, 1.0),
        (R.roughness_to_sigma, R.sigma_to_roughness, R.R_MIN, 2 ** -0.25 - 1e-9),
        (R.roughness_to_glossiness, R.glossiness_to_roughness, R.R_MIN, (2 / 3) ** 0.25),
        (R.shininess_to_sigma, R.sigma_to_shininess, 2.0, R.S_MAX),
        (R.glossiness_to_shininess, R.shininess_to_glossiness, 0.0, R.G_MAX),
    ],
)
def test_exact_inverses(fwd, inv, lo, hi):
    x = torch.linspace(lo, hi, 1001, dtype=torch.float64)
    torch.testing.assert_close(inv(fwd(x)), x, rtol=1e-9, atol=1e-12)


def test_clamped_domain_and_finite_gradients():
    r = torch.tensor([-1.0, 0.0, 1e-9, 0.5, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    s = R.roughness_to_shininess(r)
    assert s.max().item() == pytest.approx(R.S_MAX)
    assert s.min().item() >= 0.0
    for fn in (R.roughness_to_shininess, R.roughness_to_sigma, R.roughness_to_glossiness):
        (g,) = torch.autograd.grad(fn(r).sum(), r)
        assert torch.isfinite(g).all(), fn.__name__
    assert R.roughness_to_sigma(torch.tensor(1.0)).item() == pytest.approx(1.0)  # σ capped at 1
    assert math.isclose(R.R_MIN ** 2, R.ALPHA_MIN)


def test_float32_matches_float64():
    r64 = torch.linspace(0, 1, 257, dtype=torch.float64)
    for fn in (R.roughness_to_alpha, R.roughness_to_shininess, R.roughness_to_sigma, R.roughness_to_glossiness):
        torch.testing.assert_close(fn(r64.float()).double(), fn(r64), rtol=2e-5, atol=1e-6)
