"""Closed-form derivatives of ``Model.cosine_brdf_jacobian`` against automatic differentiation in float64."""

import pytest
import torch

import materials
from materials import Angles, KnownParams, SumModel
from materials.fresnel import FRESNEL, fresnel_and_derivative, fresnel_dielectric, fresnel_dielectric_and_derivative
from materials.lambert import Lambert
from materials.microfacet import BECKMANN_LAMBDAS, DISTRIBUTIONS, GEOMETRIES, Microfacet
from materials.nielsen import NielsenPhong
from materials.params import ALBEDO
from materials.roughness import R_MIN


def _angles(n: int, gen: torch.Generator) -> Angles:
    # random directions: about a quarter of the triples face both light and viewer; the others test the zeros
    def unit():
        x = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        return x / x.norm(dim=-1, keepdim=True)
    return Angles.from_vectors(unit(), unit(), unit())


def _params(model, n: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    p = {}
    for s in model.params:
        high = s.high if s.high < float("inf") else s.low + 2.0          # (an absorption has no upper end)
        x = torch.rand(n, s.channels, generator=gen, dtype=torch.float64) * (high - s.low) + s.low
        if s.name == "roughness":   # the clamp's inside, its ends and below R_MIN (held there: derivative 0)
            x[:8] = torch.tensor([0.0, R_MIN * 0.5, 1.0, 1.0, 0.999, 0.02, 0.5, 0.9], dtype=torch.float64)[:, None]
        p[s.name] = x
    return p


def _autograd(model, g: Angles, p: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    leaves = {k: v.clone().requires_grad_(True) for k, v in p.items()}
    value = model.cosine_brdf(g, leaves)
    grads = {}
    for name, x in leaves.items():
        rows = [torch.autograd.grad(value[:, c].sum(), x, retain_graph=True, allow_unused=True)[0] for c in range(3)]
        grads[name] = torch.stack([torch.zeros_like(x) if r is None else r for r in rows], 1)   # [n, 3, C]
    return value.detach(), grads


def _full(d: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    return torch.diag_embed(d) if d.dim() == value.dim() else d


CLOSED = {
    "ggx-lambert": lambda: materials.get("ggx-lambert"),
    "lambert": lambda: materials.get("lambert"),
    "microfacet": lambda: materials.get("microfacet"),
    "ggx smith, F none (the Mitsuba sphere's)": lambda: SumModel(Lambert(), Microfacet(G="smith", F="none")),
    "ggx smith, schlick": lambda: Microfacet(G="smith"),
    "ggx smith-correlated, F none": lambda: Microfacet(F="none"),
    "roughness known": lambda: KnownParams(materials.get("ggx-lambert"), {"roughness": 0.4}),
    "albedo and f0 known": lambda: KnownParams(materials.get("ggx-lambert"), {"albedo": 0.5, "f0": [0.9, 0.6, 0.3]}),
    "a shared part twice": lambda: SumModel(Microfacet(), Microfacet(G="smith", F="none")),
    "cook-torrance": lambda: materials.get("cook-torrance"),
    "cook-torrance, roughness known": lambda: KnownParams(materials.get("cook-torrance"), {"roughness": 0.3}),
    "blinn-phong D + Lambert": lambda: SumModel(Lambert(), Microfacet(D="blinn-phong")),
}
CLOSED.update({f"{name}, fresnel={fres}": (lambda name=name, fres=fres: materials.get(name, fresnel=fres))
               for name in ("nielsen-phong", "nielsen-blinn-phong", "nielsen-mixture") for fres in (True, False)})
CLOSED["nielsen-mixture, ior known"] = lambda: KnownParams(materials.get("nielsen-mixture"), {"ior": 1.33})
CLOSED.update({
    "gotanda2010": lambda: materials.get("gotanda2010"),
    "gotanda2010, exact normalisation, exact Fresnel": lambda: materials.get("gotanda2010", normalization="exact",
                                                                            fresnel="exact"),
    "gotanda2010-specular": lambda: materials.get("gotanda2010-specular"),
    "gotanda2010-specular, exact normalisation, Schüler's Fresnel": lambda: materials.get(
        "gotanda2010-specular", normalization="exact", fresnel="schuler"),
})
# every Oren-Nayar lobe (each form and clamp option), Gotanda 2012 and 2014, the microfacet diffuse fit, Schüler's
# optimized lobe
CLOSED.update({
    "oren-nayar": lambda: materials.get("oren-nayar"),
    "oren-nayar, no interreflection": lambda: materials.get("oren-nayar", interreflection=False),
    "oren-nayar, unclamped": lambda: materials.get("oren-nayar", clamp=False),
    "oren-nayar-qualitative": lambda: materials.get("oren-nayar-qualitative"),
    "gotanda-on-simplified, sigma": lambda: materials.get("gotanda-on-simplified"),
    "gotanda-on-simplified, shininess": lambda: materials.get("gotanda-on-simplified", form="shininess"),
    "gotanda-on-improved, eq25": lambda: materials.get("gotanda-on-improved"),
    "gotanda-on-improved, eq24": lambda: materials.get("gotanda-on-improved", form="eq24"),
    "gotanda-on-improved, eq24 unclamped": lambda: materials.get("gotanda-on-improved", form="eq24", clamp=False),
    "gotanda2014-on": lambda: materials.get("gotanda2014-on"),
    "gotanda2014-on, roughness known": lambda: KnownParams(materials.get("gotanda2014-on"), {"roughness": 0.6}),
    "gotanda2014-on-fresnel": lambda: materials.get("gotanda2014-on-fresnel"),
    "gotanda2014-on-fresnel unclamped": lambda: materials.get("gotanda2014-on-fresnel", clamp=False),
    "gotanda2012": lambda: materials.get("gotanda2012"),
    "microfacet-diffuse": lambda: materials.get("microfacet-diffuse"),
    "microfacet-diffuse, ue4 reading": lambda: materials.get("microfacet-diffuse", reading="ue4"),
    "gotanda2014": lambda: materials.get("gotanda2014"),
    "schuler": lambda: materials.get("schuler"),
    # the layered model with its coat held known, as the fit holds it (its Jacobian in the free parameters only)
    "gotanda2012-layered, coat known": lambda: KnownParams(materials.get("gotanda2012-layered"),
                                                           {"coat_ior": 1.5, "coat_roughness": 0.2}),
    "gotanda2012-layered (exact absorption, constant bottom Fresnel), coat known": lambda: KnownParams(
        materials.get("gotanda2012-layered", absorption="exact", bottom_fresnel="constant"),
        {"coat_ior": 1.6, "coat_roughness": 0.4}),
})
# every D, G and Beckmann Λ form (GGX has one Λ), and every named F
CLOSED.update({f"microfacet D={d} G={g} {lam}": (lambda d=d, g=g, lam=lam: Microfacet(D=d, G=g, beckmann_lambda=lam))
               for d in DISTRIBUTIONS for g in GEOMETRIES for lam in BECKMANN_LAMBDAS
               if not (d == "ggx" and lam == "exact")})
CLOSED.update({f"microfacet F={f}": (lambda f=f: Microfacet(G="smith", F=f)) for f in FRESNEL})


@pytest.mark.parametrize("name", list(CLOSED))
def test_the_closed_forms_are_the_automatic_derivatives_in_float64(name):
    model = CLOSED[name]()
    gen = torch.Generator().manual_seed(7)
    n = 3000
    g, p = _angles(n, gen), _params(model, n, gen)
    out = model.cosine_brdf_jacobian(g, p)
    assert out is not None
    value, grads = out
    ref_value, ref_grads = _autograd(model, g, p)
    torch.testing.assert_close(value, ref_value, rtol=1e-12, atol=1e-13)
    assert set(grads) == set(ref_grads) == set(model.param_names)
    for k, ref in ref_grads.items():
        assert float(ref.abs().max()) > 0, k            # the comparison is not between zeros
        torch.testing.assert_close(_full(grads[k], value), ref, rtol=1e-10, atol=1e-12 * float(ref.abs().max()),
                                   msg=k)
    # the clamp holds roughness below R_MIN: no derivative there (rows 0 and 1), one at r = 1 (rows 2 and 3)
    if "roughness" in grads:
        r = _full(grads["roughness"], value)
        assert bool((r[:2] == 0).all())


def test_a_diagonal_derivative_acts_on_its_own_channel_only():
    model = materials.get("ggx-lambert")
    gen = torch.Generator().manual_seed(2)
    g, p = _angles(500, gen), _params(model, 500, gen)
    value, grads = model.cosine_brdf_jacobian(g, p)
    assert grads["albedo"].shape == value.shape == grads["f0"].shape == (500, 3)
    assert grads["roughness"].shape == (500, 3, 1)
    _, ref = _autograd(model, g, p)
    off = ~torch.eye(3, dtype=torch.bool)
    assert bool((ref["albedo"][:, off] == 0).all()) and bool((ref["f0"][:, off] == 0).all())


class _Tinted(Microfacet):
    """A subclass that changes the BRDF: its parent's closed form no longer holds."""

    def brdf(self, g, p):
        return super().brdf(g, p) * 0.5


class _SharperPhong(NielsenPhong):
    """A Nielsen variant whose lobe differs from its parent's: the parent's closed form no longer holds."""

    def _specular(self, g, p):
        return super()._specular(g, p).square()


def _callable_fresnel() -> Microfacet:
    m = Microfacet()
    m.F = lambda f0, cos: f0 * torch.ones_like(cos)     # a Fresnel form of one's own: no derivative known
    return m


@pytest.mark.parametrize("make", [
    lambda: materials.get("microfacet-diffuse", method="numerical"),
    lambda: SumModel(Microfacet(), materials.get("microfacet-diffuse", method="numerical")),
    lambda: materials.get("gotanda2012-layered"),
    lambda: KnownParams(materials.get("gotanda2012-layered"), {"coat_ior": 1.5}),
    lambda: _Tinted(),
    _callable_fresnel,
    lambda: _SharperPhong(),
])
def test_models_without_a_closed_form_return_none(make):
    model = make()
    gen = torch.Generator().manual_seed(3)
    g, p = _angles(50, gen), _params(model, 50, gen)
    assert model.cosine_brdf_jacobian(g, p) is None
    assert model.cosine_brdf(g, p).shape == (50, 3)     # the model itself still shades


def test_the_closed_form_checks_its_parameters():
    model = materials.get("ggx-lambert")
    gen = torch.Generator().manual_seed(4)
    g, p = _angles(10, gen), _params(model, 10, gen)
    p["roughness"] = p["roughness"].expand(10, 3)
    with pytest.raises(ValueError, match="roughness"):
        model.cosine_brdf_jacobian(g, p)
    p["roughness"] = torch.full((10, 1), float("nan"), dtype=torch.float64)
    with pytest.raises(ValueError, match="roughness"):
        model.cosine_brdf_jacobian(g, p)


class _GreyAlbedo(materials.Model):
    """A lobe whose albedo channels mix (ρ̄/π on every channel): its derivative is a full 3 × 3 one."""

    params = (ALBEDO,)

    def brdf(self, g, p):
        grey = p["albedo"].mean(-1, keepdim=True) / torch.pi
        return torch.where(g.front, grey, torch.zeros_like(grey)).expand(*grey.shape[:-1], 3)

    def cosine_brdf_jacobian(self, g, p):
        w = torch.where(g.front, g.nl.clamp_min(0.0), torch.zeros_like(g.nl)) / torch.pi
        value = (p["albedo"].mean(-1, keepdim=True) * w).expand(*w.shape[:-1], 3)
        return value, {"albedo": (w / 3.0).unsqueeze(-1).expand(*w.shape[:-1], 3, 3)}


def test_a_sum_of_a_diagonal_and_a_full_derivative_is_the_full_one():
    model = SumModel(Lambert(), _GreyAlbedo())
    gen = torch.Generator().manual_seed(6)
    g, p = _angles(400, gen), _params(model, 400, gen)
    value, grads = model.cosine_brdf_jacobian(g, p)
    assert grads["albedo"].shape == (400, 3, 3)
    ref_value, ref = _autograd(model, g, p)
    torch.testing.assert_close(value, ref_value, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(grads["albedo"], ref["albedo"], rtol=1e-12, atol=1e-13)
    assert bool((ref["albedo"][:, 0, 1] != 0).any())      # the channels do mix


@pytest.mark.parametrize("name", list(FRESNEL))
def test_fresnel_derivatives_at_their_edges(name):
    # f0 at 0, below and at the exact form's floor, at Schüler's kink 1/60 (a tie of its minimum) and at 1; normal,
    # grazing and nearly grazing cosines, and one outside [0, 1] (clamped)
    f0 = torch.tensor([0.0, 1e-13, 1e-12, 1.0 / 60.0, 0.04, 0.5, 1.0], dtype=torch.float64)
    cos = torch.tensor([0.0, 1e-9, 0.3, 1.0, 1.5], dtype=torch.float64)
    f0_grid = f0[:, None, None].expand(-1, len(cos), 3).clone()
    cos_grid = cos[None, :, None].expand(len(f0), -1, 1)
    leaf = f0_grid.clone().requires_grad_(True)
    ref = FRESNEL[name](leaf, cos_grid)
    (dref,) = torch.autograd.grad(ref.sum(), leaf)
    value, d = fresnel_and_derivative(name, f0_grid, cos_grid)
    torch.testing.assert_close(value.expand_as(ref), ref.detach(), rtol=1e-14, atol=0.0)
    torch.testing.assert_close(d.expand_as(dref), dref, rtol=1e-10, atol=1e-14)
    assert float(dref.abs().max()) > 0


def test_the_specular_jacobian_checks_what_it_is_given():
    from materials.microfacet import specular_jacobian

    gen = torch.Generator().manual_seed(8)
    g = _angles(5, gen)
    f0 = torch.full((5, 3), 0.04, dtype=torch.float64)
    with pytest.raises(ValueError, match="roughness"):
        specular_jacobian(g, f0, torch.full((5, 3), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="geometry term"):
        specular_jacobian(g, f0, torch.full((5, 1), 0.5, dtype=torch.float64), G="walter")
    with pytest.raises(ValueError, match="Fresnel"):
        specular_jacobian(g, f0, torch.full((5, 1), 0.5, dtype=torch.float64), F="fresnel")


def test_the_dielectric_fresnel_derivative_at_its_edges():
    # η at 1 (no interface), just above it, below 1 (total internal reflection past the critical angle) and high;
    # normal, grazing and nearly grazing cosines, and one outside [0, 1]
    eta = torch.tensor([1.0, 1.0000001, 0.7, 1.33, 1.5, 3.0], dtype=torch.float64)
    cos = torch.tensor([0.0, 1e-9, 0.3, 0.6, 1.0, 1.5], dtype=torch.float64)
    eta_grid = eta[:, None, None].expand(-1, len(cos), 1).clone()
    cos_grid = cos[None, :, None].expand(len(eta), -1, 1)
    leaf = eta_grid.clone().requires_grad_(True)
    ref = fresnel_dielectric(leaf, cos_grid)
    (dref,) = torch.autograd.grad(ref.sum(), leaf)
    value, d = fresnel_dielectric_and_derivative(eta_grid, cos_grid)
    torch.testing.assert_close(value, ref.detach(), rtol=1e-14, atol=0.0)
    torch.testing.assert_close(d, dref, rtol=1e-10, atol=1e-14)
    assert float(dref.abs().max()) > 0 and bool((d[2] == 0).any())      # η 0.7: reflected totally at grazing


def test_schulers_other_variants_leave_their_jacobian_to_autograd():
    """Only Schüler's default ``optimized`` lobe has a closed form; the paper's other variants answer None, and the
    fit differentiates their forward pass."""
    gen = torch.Generator().manual_seed(3)
    for variant in ("cook-torrance-simplified", "kelemen-szirmay-kalos", "cook-torrance-full"):
        model = materials.get("schuler", variant=variant)
        assert model.cosine_brdf_jacobian(_angles(10, gen), _params(model, 10, gen)) is None
