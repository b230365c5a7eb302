"""Every registered model, forward and backward, over the stress domain: no NaN or inf anywhere, and
float32 within tolerance of float64. New models are covered by registering them."""

import math

import pytest
import torch

import materials
from materials import validation
from materials.measured import data_dir

# "measured" needs the NBRDF weights of ../shared/data/merl (present in CI beside the clone).
MODELS = sorted(n for n in materials.available() if n != "measured" or data_dir().exists())


def test_quadrature_integrates_cosine_and_constant():
    d, w = validation.hemisphere_quadrature(32, 64)
    assert w.sum().item() == pytest.approx(2 * math.pi, rel=1e-12)
    assert (w * d[:, 2]).sum().item() == pytest.approx(math.pi, rel=1e-12)


def test_lambert_directional_albedo_is_the_albedo():
    m = materials.get("lambert")
    theta = torch.tensor([0.0, 0.7, 1.5], dtype=torch.float64)
    rho = validation.directional_albedo(m, {"albedo": torch.tensor([1.0, 0.5, 0.2], dtype=torch.float64)}, theta)
    torch.testing.assert_close(rho, torch.tensor([[1.0, 0.5, 0.2]] * 3, dtype=torch.float64), rtol=1e-9, atol=1e-9)


def test_stress_domain_contains_the_edges():
    n, l, v = validation.stress_vectors(n_random=4)
    g = materials.Angles.from_vectors(n, l, v)
    assert (g.nl == 0).any() and (g.nl < 0).any() and (g.nl.abs() < 1e-6).any()
    assert ((l + v).norm(dim=-1) < 1e-12).any()  # l = −v


@pytest.mark.parametrize("name", MODELS)
def test_every_model_is_finite_in_value_and_gradient(name):
    model = materials.get(name)
    for dtype in (torch.float64, torch.float32):
        rep = validation.check_stability(model, dtype=dtype, n_random=64)
        assert rep.ok, rep


@pytest.mark.parametrize("name", MODELS)
def test_every_model_float32_matches_float64(name):
    rep = validation.check_stability(materials.get(name), dtype=torch.float32, n_random=64)
    # Relative to the largest value of the lobe over the domain (floor 1e-3 of the max): float32 has
    # ~7 digits; exponents up to 2^16 amplify the cosine's rounding by s·ε ≈ 1e-2 near the peak.
    assert rep.max_rel_dev_f32 < 5e-2, rep


def _grazing_mirror_pairs(dtype):
    """Exact and nearly exact mirror pairs at n·l, n·v = 1e-12 … 1e-1, and l = −v, in a turned frame."""
    c = torch.logspace(-12, -1, 23, dtype=torch.float64)
    phi = torch.tensor([0.1, 1.3, 2.9, 4.4], dtype=torch.float64)
    c, phi = (x.reshape(-1) for x in torch.meshgrid(c, phi, indexing="ij"))
    polar = lambda cc, pp: torch.stack([torch.sqrt(1 - cc * cc) * torch.cos(pp),  # noqa: E731
                                        torch.sqrt(1 - cc * cc) * torch.sin(pp), cc], -1)
    v = polar(c, phi)
    l = torch.cat([polar(c, phi + math.pi), polar(c, phi + math.pi + 1e-6), polar(c.flip(0), phi + math.pi), -v])
    v = torch.cat([v, v, v, v])
    rot = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64))[0]
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(v)
    return [torch.cat([x, x @ rot.T]).to(dtype) for x in (n, l, v)]


@pytest.mark.parametrize("name", MODELS)
def test_float32_gradients_are_finite_at_grazing_mirror_pairs(name):
    # where the mirror-like lobes (s up to 2^16) divide by grazing cosines: the half vector is tiny there
    model = materials.get(name)
    n, l, v = _grazing_mirror_pairs(torch.float32)
    params = {k: x.requires_grad_() for k, x in validation.stress_params(model, len(n), torch.float32).items()}
    l.requires_grad_()
    v.requires_grad_()
    g = materials.Angles.from_vectors(n, l, v)
    out = model.brdf(g, params).sum() + model.cosine_brdf(g, params).sum()
    grads = torch.autograd.grad(out, [l, v, *params.values()], allow_unused=True)
    assert torch.isfinite(out)
    for gr in grads:
        assert gr is None or torch.isfinite(gr).all()


@pytest.mark.parametrize("name", MODELS)
def test_random_and_edge_samples_are_finite(name):
    # the cheap version of `python scripts/stress.py sampled` (docs/stability.md): a few thousand samples
    for dtype in (torch.float64, torch.float32):
        rep = validation.sampled_stability(materials.get(name), 3000, dtype=dtype, seed=11)
        assert rep.ok, rep
