"""The full paper models of materials/catalog.py against the lobes they are assembled from."""

import pytest
import torch

import materials
from materials import Angles
from materials.roughness import R_MIN


def _angles(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    nl, nv = torch.rand(n, 1, generator=g, dtype=torch.float64), torch.rand(n, 1, generator=g, dtype=torch.float64)
    lv = -1 + 2 * torch.rand(n, 1, generator=g, dtype=torch.float64)
    # keep lv feasible: |φ| any → lv ∈ [nl nv − sl sv, nl nv + sl sv]
    s = torch.sqrt((1 - nl**2) * (1 - nv**2))
    lv = nl * nv + s * (2 * lv.clamp(-1, 1) - 1).clamp(-1, 1) * 0.999
    return Angles.from_cosines(nl, nv, lv)


def _params(n, rough, seed=1):
    g = torch.Generator().manual_seed(seed)
    return {
        "albedo": torch.rand(n, 3, generator=g, dtype=torch.float64),
        "f0": torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.5,
        "roughness": torch.full((n, 1), rough, dtype=torch.float64),
    }


def test_ggx_lambert_is_the_sum_of_its_lobes():
    g, p = _angles(), _params(400, 0.4)
    spec = materials.get("microfacet", D="ggx", G="smith-correlated", F="schlick")
    expect = materials.get("lambert").brdf(g, p) + spec.brdf(g, p)
    torch.testing.assert_close(materials.get("ggx-lambert").brdf(g, p), expect)


def test_gotanda2012_tends_to_gotanda2010_as_the_surface_gets_smooth():
    # eq 25 at s → ∞: 1 − 1/(2 + 0.65 s) → 1 and 1/(2.22222 + 0.1 s) → 0, i.e. Lambert; s = 2^16 at R_MIN.
    g, p = _angles(), _params(400, R_MIN)
    a = materials.get("gotanda2012").cosine_brdf(g, p)
    b = materials.get("gotanda2010").cosine_brdf(g, p)
    diffuse_scale = (p["albedo"] * (1 - p["f0"])).max().item() / torch.pi
    assert (a - b).abs().max().item() < 1e-4 * diffuse_scale + 1e-12


def test_gotanda2012_diffuse_is_one_minus_f0_weighted_oren_nayar():
    g, p = _angles(), _params(400, 0.8)
    zero_f0 = dict(p, f0=torch.zeros_like(p["f0"]))
    on = materials.get("gotanda-on-improved").brdf(g, zero_f0)
    spec = materials.get("gotanda2010-specular").brdf(g, zero_f0)
    torch.testing.assert_close(materials.get("gotanda2012").brdf(g, zero_f0), on + spec)


def test_gotanda2014_is_fitted_diffuse_plus_ggx():
    g, p = _angles(), _params(400, 0.6)
    d = materials.get("microfacet-diffuse", method="fitted").brdf(g, p)
    s = materials.get("microfacet", D="ggx", G="smith-correlated", F="schlick").brdf(g, p)
    torch.testing.assert_close(materials.get("gotanda2014").brdf(g, p), d + s)


@pytest.mark.parametrize("name", ["ggx-lambert", "gotanda2012", "gotanda2014"])
def test_catalog_gradcheck(name):
    m = materials.get(name)
    g = _angles(6, seed=3)
    p = {k: v.requires_grad_() for k, v in _params(6, 0.55, seed=4).items()}
    names = list(p)
    fn = lambda *vals: m.cosine_brdf(g, dict(zip(names, vals, strict=True)))
    assert torch.autograd.gradcheck(fn, tuple(p.values()))
