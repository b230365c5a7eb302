"""Gotanda 2012 dual layer (eq 2-9): the coat vanishes at η₁ = 1, goldens, absorption limits, eq 3 vs
eq 2, eq 8, IBL, gradients and extreme inputs."""

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

import materials
from materials.geometry import Angles
from materials.layered import (
    absorption_exact,
    absorption_linear,
    clamped_linear_absorption_mean,
    refracted_cos,
    relative_f0,
    relative_ior,
)
from materials.roughness import R_MIN

D64 = torch.float64
PI = math.pi


def _vec(cos, phi=0.0):
    s = math.sqrt(max(0.0, 1.0 - cos * cos))
    return torch.tensor([s * math.cos(phi), s * math.sin(phi), cos], dtype=D64)


N = _vec(1.0)


def _random(n, seed):
    g = torch.Generator().manual_seed(seed)
    nl = 0.02 + 0.98 * torch.rand(n, generator=g, dtype=D64)
    nv = 0.02 + 0.98 * torch.rand(n, generator=g, dtype=D64)
    phi = 2 * PI * torch.rand(n, generator=g, dtype=D64)
    lv = nl * nv + torch.sqrt(1 - nl**2) * torch.sqrt(1 - nv**2) * torch.cos(phi)
    return Angles.from_cosines(nl, nv, lv)


def _params(model, n, seed, **fixed):
    gen = torch.Generator().manual_seed(seed)
    p = {}
    for sp in model.params:
        lo, hi = {"ior": (1.1, 2.5), "coat_ior": (1.1, 2.0), "absorption": (0.0, 0.2)}.get(sp.name, (0.05, 0.95))
        p[sp.name] = lo + (hi - lo) * torch.rand(n, sp.channels, dtype=D64, generator=gen)
    for k, x in fixed.items():
        p[k] = torch.full((n, model.spec(k).channels), float(x), dtype=D64)
    return p


@pytest.mark.parametrize("bottom", ["gotanda2010", "nielsen-phong", "nielsen-mixture", "lambert", "gotanda2012"])
@pytest.mark.parametrize("absorption", ["linear", "exact"])
def test_coat_vanishes_at_ior_one(bottom, absorption):
    m = materials.get("gotanda2012-layered", bottom=bottom, absorption=absorption)
    b = materials.get(bottom)
    g = _random(300, 1)
    p = _params(m, 300, 2, coat_ior=1.0, absorption=0.0)
    assert torch.allclose(m.brdf(g, p), b.brdf(g, p), rtol=1e-12, atol=1e-15)
    assert torch.allclose(m.cosine_brdf(g, p), b.cosine_brdf(g, p), rtol=1e-12, atol=1e-15)


def test_constant_bottom_fresnel_uses_constant_bottom_and_vanishes_at_ior_one():
    m = materials.get("gotanda2012-layered", bottom_fresnel="constant")
    assert m.bottom_fresnel_constant
    ref = materials.get("gotanda2010", fresnel="none")
    g = _random(100, 3)
    p = _params(m, 100, 4, coat_ior=1.0, absorption=0.0)
    assert torch.allclose(m.brdf(g, p), ref.brdf(g, p), rtol=1e-12, atol=1e-15)
    # a bottom without a fresnel option (lambert) falls back to its own form
    assert not materials.get("gotanda2012-layered", bottom="lambert", bottom_fresnel="constant").bottom_fresnel_constant


def test_golden_normal_incidence():
    # l = v = n, η₁ = 1.5 (F(1.5, 1) = 0.04), coat r = 0.5 → s = 30, N = 1.2779912.
    # Bottom gotanda2010 with f0 = 0.09 (√f0 = 0.3, n2 = 1.3/0.7): √f0_rel = (1.3 − 1.5·0.7)/(1.3 + 1.5·0.7)
    # = 0.25/2.35. Bottom at l = v = n: albedo(1 − f0_rel)/π + N_b f0_rel with N_b = N(30) as well.
    # T_in T_out = 0.96², linear absorption 1 − a(1 + 1) with a = 0.1 → 0.8; exact exp(−0.1·2) (no refraction at n).
    m_lin = materials.get("gotanda2012-layered", absorption="linear")
    m_exa = materials.get("gotanda2012-layered", absorption="exact")
    p = {"albedo": torch.tensor([0.6], dtype=D64), "f0": torch.tensor([0.09], dtype=D64),
         "roughness": torch.tensor([0.5], dtype=D64), "absorption": torch.tensor([0.1], dtype=D64),
         "coat_ior": torch.tensor([1.5], dtype=D64), "coat_roughness": torch.tensor([0.5], dtype=D64)}
    nrm = 0.0397436 * 30 + 0.0856832
    f0r = (0.25 / 2.35) ** 2
    bottom = 0.6 * (1 - f0r) / PI + nrm * f0r
    lin = m_lin(N, N, N, **p).item()
    exa = m_exa(N, N, N, **p).item()
    assert lin == pytest.approx(0.04 * nrm + 0.96**2 * 0.8 * bottom, rel=1e-10)
    assert exa == pytest.approx(0.04 * nrm + 0.96**2 * math.exp(-0.2) * bottom, rel=1e-10)


def test_relative_f0_and_ior():
    f0 = torch.tensor([0.0, 0.02, 0.04, 0.3, 0.9, 1.0], dtype=D64)
    assert torch.allclose(relative_f0(f0, torch.tensor(1.0, dtype=D64)), f0, rtol=1e-12, atol=0)
    assert relative_f0(torch.tensor(1.0, dtype=D64), torch.tensor(2.0, dtype=D64)).item() == pytest.approx(1.0)
    # against the route through the index: n2 = ior_from_f0, f0_rel = ((n2 − n1)/(n2 + n1))²
    n1 = 1.7
    for x in (0.0, 0.02, 0.3, 0.9):
        n2 = (1 + math.sqrt(x)) / (1 - math.sqrt(x))
        assert relative_f0(torch.tensor(x, dtype=D64), torch.tensor(n1, dtype=D64)).item() == pytest.approx(
            ((n2 - n1) / (n2 + n1)) ** 2, rel=1e-12)
    # n2/n1 also below 1: at the refracted angle (sin θ_t ≤ 1/n1 ≤ n2/n1) no total internal reflection occurs
    assert relative_ior(torch.tensor(1.2), torch.tensor(1.5)).item() == pytest.approx(0.8)
    assert relative_ior(torch.tensor(2.4), torch.tensor(1.5)).item() == pytest.approx(1.6)


def test_golden_oblique_mirror_pair_bottom_fresnel_at_the_refracted_angle():
    # Gotanda 2012 eq 4 at θ = 60° (n·l = n·v = 1/2, l the mirror of v: h = n, l·h = 1/2), by hand.
    # Coat η₁ = 1.5: sin θ_t = sin 60°/1.5 = 1/√3, cos θ_t = √(2/3).
    #   F(1.5, 60°): r_s = (1/2 − 1.5√(2/3))/(1/2 + 1.5√(2/3)), r_p = (1.5/2 − √(2/3))/(1.5/2 + √(2/3)).
    # Bottom gotanda2010, f0 = 0.09 → f0_rel = (0.25/2.35)²; its Schlick Fresnel at cos θ_t (not at 1/2):
    #   F_b = f0_rel + (1 − f0_rel)(1 − √(2/3))⁵; bottom f = albedo(1 − f0_rel)/π + N(30) F_b / max(n·l, n·v).
    # Coat r = 0.5 → s = 30 for both lobes; N(30) = 0.0397436·30 + 0.0856832; (n·h)^s = 1.
    # Linear absorption (eq 3): 1 − 0.1 (2 + 2) = 0.6.
    m = materials.get("gotanda2012-layered")
    ct = math.sqrt(2.0 / 3.0)
    rs = (0.5 - 1.5 * ct) / (0.5 + 1.5 * ct)
    rp = (0.75 - ct) / (0.75 + ct)
    f_coat = 0.5 * (rs * rs + rp * rp)
    nrm = 0.0397436 * 30 + 0.0856832
    f0r = (0.25 / 2.35) ** 2
    f_b = f0r + (1 - f0r) * (1 - ct) ** 5
    bottom = 0.6 * (1 - f0r) / PI + nrm * f_b / 0.5
    expected = nrm * f_coat / 0.5 + (1 - f_coat) ** 2 * 0.6 * bottom
    p = {"albedo": 0.6, "f0": 0.09, "roughness": 0.5, "absorption": 0.1, "coat_ior": 1.5, "coat_roughness": 0.5}
    p = {k: torch.tensor([x], dtype=D64) for k, x in p.items()}
    got = m(N, _vec(0.5, 0.0), _vec(0.5, PI), **p).item()
    assert got == pytest.approx(expected, rel=1e-10)
    # the unrefracted reading (F_b at l·h = 1/2) would make the bottom's Fresnel 3.7 times larger here
    f_b_unrefracted = f0r + (1 - f0r) * 0.5**5
    assert f_b_unrefracted / f_b == pytest.approx(3.66, abs=0.01)


def test_golden_environment_bottom_specular_fresnel_at_the_refracted_angle():
    # eq 7: F_bottom(n1, n2) is eq 4 at N·E. Uniform environment of irradiance 1 (radiance 1/π everywhere),
    # n·v = 1/2, η₁ = 1.5, no absorption, albedo 0 (no diffuse path): coat F(1.5, 60°)/π, plus the bottom's mirror
    # specular T_in T_out F_schlick(f0_rel, cos θ_t)/π with cos θ_t = √(2/3) (values as in the BRDF golden above).
    m = materials.get("gotanda2012-layered")
    ct = math.sqrt(2.0 / 3.0)
    rs = (0.5 - 1.5 * ct) / (0.5 + 1.5 * ct)
    rp = (0.75 - ct) / (0.75 + ct)
    f_coat = 0.5 * (rs * rs + rp * rp)
    f0r = (0.25 / 2.35) ** 2
    expected = (f_coat + (1 - f_coat) ** 2 * (f0r + (1 - f0r) * (1 - ct) ** 5)) / PI
    one = torch.ones(3, dtype=D64)
    uniform = materials.HemisphereLight(one, one, torch.tensor([0.0, 0.0, 1.0], dtype=D64))
    p = {"albedo": 0.0, "f0": 0.09, "roughness": 0.5, "absorption": 0.0, "coat_ior": 1.5, "coat_roughness": 0.5}
    p = {k: torch.tensor([[x]], dtype=D64) for k, x in p.items()}
    got = m.environment(uniform, N.unsqueeze(0), _vec(0.5, 0.3).unsqueeze(0), p)
    torch.testing.assert_close(got, torch.full((1, 3), expected, dtype=D64), rtol=1e-10, atol=0.0)


def test_bottom_fresnel_product_is_almost_flat_as_in_figure_1():
    # Figure 1: n1 = 1.33333 over n2 = 1.5, F_bottom = (1 − F(n1, θ)) F(n2/n1, θ_t) (1 − F(1/n1, θ_t)) is "almost a
    # flat line" next to the top layer's F(n1, θ). Read back from the model: a Nielsen eq 2 bottom (ρ_d = 0, ρ_s = 1,
    # its R_F at η = n2/n1) at mirror pairs (h = n) reflects (s + 8)/(8π) R_F; with no absorption
    # f − f_coat = T_in T_out (s + 8)/(8π) R_F(n2/n1, θ_t) = F_bottom(θ) (s + 8)/(8π).
    m = materials.get("gotanda2012-layered", bottom="nielsen-blinn-phong")
    theta = torch.linspace(0.0, 85.0, 18, dtype=D64) * PI / 180
    c = torch.cos(theta)[:, None]
    g = Angles.from_cosines(c, c, 2 * c * c - 1)
    k = len(theta)
    p = {"albedo": torch.zeros(k, 3, dtype=D64), "specular": torch.ones(k, 3, dtype=D64),
         "roughness": torch.full((k, 1), 0.5, dtype=D64), "ior": torch.full((k, 1), 1.5, dtype=D64),
         "absorption": torch.zeros(k, 3, dtype=D64), "coat_ior": torch.full((k, 1), 1.33333, dtype=D64),
         "coat_roughness": torch.full((k, 1), 0.5, dtype=D64)}
    s = 30.0
    f_bottom = ((m.brdf(g, p) - m.coat_specular(g, p)) / ((s + 8) / (8 * PI)))[:, 0]
    top = materials.fresnel.fresnel_dielectric(torch.tensor([1.33333], dtype=D64), c)[:, 0]
    assert top[0] == pytest.approx(0.0204, abs=1e-4) and top[-1] > 0.58
    assert f_bottom.min() > 0.0011 and f_bottom.max() < 0.0043  # 0.0033 at 0°, 0.0042 at 70°, 0.0012 at 85°
    # F(n2/n1) at the unrefracted θ would climb 30-fold (0.095 at 80°): not "almost flat"
    r_unrefracted = materials.fresnel.fresnel_dielectric(torch.tensor([1.5 / 1.33333], dtype=D64), c)[:, 0]
    assert ((1 - top) ** 2 * r_unrefracted).max() > 0.09


def test_eq3_agrees_with_eq2_to_first_order():
    # At η₁ = 1 (no refraction) exp(−aL) − max(0, 1 − aL) = a²L²/2 + O(a³), L = 1/n·l + 1/n·v.
    nl = torch.tensor([[0.3], [0.7], [1.0]], dtype=D64)
    nv = torch.tensor([[0.5], [0.2], [1.0]], dtype=D64)
    L = 1 / nl + 1 / nv
    one = torch.ones(1, dtype=D64)
    for a in (1e-2, 1e-3, 1e-4):
        at = torch.full((3, 1), a, dtype=D64)
        diff = absorption_exact(nl, nv, at, one) - absorption_linear(nl, nv, at)
        assert torch.allclose(diff / a**2, L**2 / 2, rtol=3 * a * L.max().item())
    # With η₁ > 1 the exact path is shorter (refracted): the first-order slopes differ by design —
    # Gotanda's α' absorbs it. Slope ratio at n·l = n·v = 0.5, η₁ = 1.5:
    h = 1e-6
    half = torch.tensor([0.5], dtype=D64)
    ratio = (1 - absorption_exact(half, half, torch.tensor([h], dtype=D64), torch.tensor([1.5], dtype=D64))) / (4 * h)
    ct = math.sqrt(1 - 0.75 / 2.25)
    assert ratio.item() == pytest.approx(0.5 / ct, rel=1e-5)


@pytest.mark.parametrize("absorption", ["linear", "exact"])
def test_huge_absorption_leaves_only_the_coat_with_finite_gradients(absorption):
    m = materials.get("gotanda2012-layered", absorption=absorption)
    g = _random(50, 5)
    p = _params(m, 50, 6, absorption=1e3)
    p = {k: x.requires_grad_() for k, x in p.items()}
    out = m.brdf(g, p)
    coat = m.coat_specular(g, p)
    assert torch.allclose(out, coat.expand_as(out), rtol=1e-12, atol=1e-300)
    out.sum().backward()
    for k, x in p.items():
        assert torch.isfinite(x.grad).all(), k
    assert (p["albedo"].grad == 0).all()


def test_linear_absorption_grazing_value_and_gradient():
    nl = torch.tensor([[0.0], [1e-7], [1e-3], [0.5]], dtype=D64, requires_grad=True)
    nv = torch.full((4, 1), 0.9, dtype=D64, requires_grad=True)
    a = torch.full((4, 3), 1e-4, dtype=D64, requires_grad=True)
    out = absorption_linear(nl, nv, a)
    assert out[0].tolist() == [0.0] * 3 and out[1].tolist() == [0.0] * 3
    assert out[3, 0].item() == pytest.approx(1 - 1e-4 * (2 + 1 / 0.9))
    out.sum().backward()
    assert torch.isfinite(nl.grad).all() and torch.isfinite(a.grad).all()


def test_eq8_integral_and_clamped_mean():
    # ∫ (1/cos θ_r + 1/cos θ_i) cos θ_i/π dω_i = 2 + 1/cos θ_r (midpoint rule in μ = cos θ_i; φ trivial)
    n = 200000
    mu = (torch.arange(n, dtype=D64) + 0.5) / n
    for cr in (1.0, 0.5, 0.1):
        val = ((1 / cr + 1 / mu) * mu / PI).mean().item() * 2 * PI
        assert val == pytest.approx(2 + 1 / cr, rel=1e-9)
    # the clamped mean used to judge eq 9: c − 2a + a²/c
    for a, cr in ((0.01, 0.8), (0.05, 0.5), (0.2, 0.9), (0.4, 0.5)):
        num = (torch.relu(1 - a * (1 / mu + 1 / cr)) * 2 * mu).mean().item()
        closed = clamped_linear_absorption_mean(torch.tensor(a, dtype=D64), torch.tensor(cr, dtype=D64)).item()
        assert closed == pytest.approx(num, abs=1e-6)
        eq9 = max(0.0, 1 - a * (2 + 1 / cr))
        if closed > 0:
            c = 1 - a / cr
            assert closed - eq9 == pytest.approx(a * a / c, abs=1e-9)


def test_refracted_cos():
    c = refracted_cos(torch.tensor([[0.0], [0.6], [1.0]], dtype=D64), torch.tensor(1.5, dtype=D64))
    expect = [math.sqrt(1 - (1 - x * x) / 2.25) for x in (0.0, 0.6, 1.0)]
    assert c.squeeze(-1).tolist() == pytest.approx(expect, rel=1e-12)


def _sky(l0=1.0):
    coeffs = torch.zeros(9, 3, dtype=D64)
    coeffs[0] = 2 * math.sqrt(PI) * l0
    return materials.SHLight(coeffs.float())


def test_environment_coat_vanishes_and_eq7_eq9_factors():
    env = _sky()
    n = N.unsqueeze(0)
    v = _vec(1.0).unsqueeze(0)
    b = materials.get("gotanda2010")
    m = materials.get("gotanda2012-layered")
    p = {"albedo": torch.tensor([[0.5, 0.4, 0.3]], dtype=D64), "f0": torch.tensor([[0.04, 0.04, 0.04]], dtype=D64),
         "roughness": torch.tensor([[0.4]], dtype=D64), "absorption": torch.tensor([[0.0, 0.0, 0.0]], dtype=D64),
         "coat_ior": torch.tensor([[1.0]], dtype=D64), "coat_roughness": torch.tensor([[0.2]], dtype=D64)}
    assert torch.allclose(m.environment(env, n, v, p), b.environment(env, n, v, p), rtol=1e-6)
    # absorption a = 0.1, n·v = 1, η₁ = 1: specular × (1 − 2a) (eq 7), diffuse × (1 − 3a) (eq 9)
    p["absorption"] = torch.full((1, 3), 0.1, dtype=D64)
    spec, diff = b.environment_split(env, n, v, p)
    expect = 0.8 * spec + 0.7 * diff
    assert torch.allclose(m.environment(env, n, v, p), expect, rtol=1e-6)
    # HemisphereLight and the exact absorption path run and stay finite and below the no-absorption value
    hemi = materials.HemisphereLight(torch.tensor([1.0, 1.0, 1.0]), torch.tensor([0.2, 0.2, 0.2]),
                                     torch.tensor([0.0, 0.0, 1.0]))
    me = materials.get("gotanda2012-layered", absorption="exact")
    p["coat_ior"] = torch.tensor([[1.5]], dtype=D64)
    v2 = _vec(0.3, 1.0).unsqueeze(0)
    absorbed = me.environment(hemi, n, v2, p)
    p0 = dict(p, absorption=torch.zeros(1, 3, dtype=D64))
    clear = me.environment(hemi, n, v2, p0)
    assert torch.isfinite(absorbed).all() and (absorbed < clear).all()


def test_environment_fallback_for_bottom_without_split():
    env = _sky()
    m = materials.get("gotanda2012-layered", bottom="lambert")
    n, v = N.unsqueeze(0), _vec(1.0).unsqueeze(0)
    p = {"albedo": torch.tensor([[0.5, 0.5, 0.5]], dtype=D64), "absorption": torch.full((1, 3), 0.1, dtype=D64),
         "coat_ior": torch.tensor([[1.0]], dtype=D64), "coat_roughness": torch.tensor([[0.2]], dtype=D64)}
    assert torch.allclose(m.environment(env, n, v, p), torch.full((1, 3), 0.5 * 0.7, dtype=D64), rtol=1e-6)


@pytest.mark.parametrize("absorption,bottom_fresnel,coat", [("linear", "exact", "blinn-phong"),
                                                            ("exact", "constant", "blinn-phong"),
                                                            ("exact", "exact", "ggx")])
def test_gradcheck(absorption, bottom_fresnel, coat):
    m = materials.get("gotanda2012-layered", absorption=absorption, bottom_fresnel=bottom_fresnel, coat=coat)
    g = _random(4, 7)
    p = _params(m, 4, 8)
    keys = list(p)
    vals = [p[k].requires_grad_() for k in keys]
    assert torch.autograd.gradcheck(lambda *xs: m.brdf(g, dict(zip(keys, xs, strict=True))), vals)


def test_gradcheck_environment():
    m = materials.get("gotanda2012-layered", absorption="exact")
    env = _sky()
    n = N.expand(3, 3)
    v = torch.stack([_vec(0.9, 0.1), _vec(0.5, 1.0), _vec(0.2, 2.0)])
    p = _params(m, 3, 9)
    keys = list(p)
    vals = [p[k].requires_grad_() for k in keys]
    assert torch.autograd.gradcheck(lambda *xs: m.environment(env, n, v, dict(zip(keys, xs, strict=True))), vals)


def test_ggx_coat_vanishes_at_ior_one():
    m = materials.get("gotanda2012-layered", coat="ggx")
    g = _random(50, 10)
    p = _params(m, 50, 11, coat_ior=1.0)
    assert (m.coat_specular(g, p) == 0).all()


def test_bad_options():
    with pytest.raises(ValueError, match="absorption"):
        materials.get("gotanda2012-layered", absorption="beer")
    with pytest.raises(ValueError, match="bottom_fresnel"):
        materials.get("gotanda2012-layered", bottom_fresnel="x")
    with pytest.raises(ValueError, match="unknown model"):
        materials.get("gotanda2012-layered", bottom="nope")
    with pytest.raises(ValueError, match="coat over a coat"):
        materials.get("gotanda2012-layered", bottom="gotanda2012-layered")


def test_directional_albedo_white_bottom_below_one():
    """Energy: albedo 1, f0 = 0.04 bottom under a clear η₁ = 1.5 coat, measured by quadrature over l."""
    m = materials.get("gotanda2012-layered")
    nth, nphi = 400, 128
    mu = (torch.arange(nth, dtype=D64) + 0.5) / nth
    phi = (torch.arange(nphi, dtype=D64) + 0.5) / nphi * 2 * PI
    for nv in (1.0, 0.5, 0.1):
        nl = mu[:, None].expand(nth, nphi)
        lv = nl * nv + torch.sqrt(1 - nl**2) * math.sqrt(1 - nv**2) * torch.cos(phi)[None, :]
        g = Angles.from_cosines(nl, torch.full_like(nl, nv), lv)
        p = {"albedo": torch.ones(1, 3, dtype=D64), "f0": torch.full((1, 3), 0.04, dtype=D64),
             "roughness": torch.tensor([[0.6]], dtype=D64), "absorption": torch.zeros(1, 3, dtype=D64),
             "coat_ior": torch.tensor([[1.5]], dtype=D64), "coat_roughness": torch.tensor([[0.6]], dtype=D64)}
        alb = m.cosine_brdf(g, p).mean(dim=(0, 1)) * 2 * PI
        assert (alb <= 1.0).all(), (nv, alb)


_COS = st.one_of(st.sampled_from([0.0, 1e-7, -1e-7, -1e-3, 1e-3, 0.5, 1.0]), st.floats(-0.2, 1.0))
_R = st.one_of(st.sampled_from([0.0, R_MIN, 0.5, 1.0]), st.floats(0.0, 1.0))


@given(nl=_COS, nv=_COS, phi=st.floats(0, 2 * PI), anti=st.booleans(), r=_R, rc=_R,
       f0=st.one_of(st.sampled_from([0.0, 1.0]), st.floats(0.0, 1.0)),
       eta=st.one_of(st.sampled_from([1.0, 3.0]), st.floats(1.0, 3.0)),
       a=st.one_of(st.sampled_from([0.0, 1e3]), st.floats(0.0, 1e3)),
       absorption=st.sampled_from(["linear", "exact"]), bottom_fresnel=st.sampled_from(["exact", "constant"]))
def test_extremes_finite_and_float32_matches_float64(nl, nv, phi, anti, r, rc, f0, eta, a, absorption, bottom_fresnel,
                                                    finite_and_float32_matches):
    m = materials.get("gotanda2012-layered", absorption=absorption, bottom_fresnel=bottom_fresnel)
    l = _vec(nl).clone().requires_grad_()
    v = (-l.detach() if anti else _vec(nv, phi)).clone().requires_grad_()
    p = {"albedo": torch.tensor([0.5, 0.1, 1.0], dtype=D64), "f0": torch.full((3,), f0, dtype=D64),
         "roughness": torch.tensor([r], dtype=D64), "absorption": torch.tensor([a, 0.0, 1.0], dtype=D64),
         "coat_ior": torch.tensor([eta], dtype=D64), "coat_roughness": torch.tensor([rc], dtype=D64)}
    p = {k: x.requires_grad_() for k, x in p.items()}
    g = Angles.from_vectors(N, l, v)
    finite_and_float32_matches(lambda g_, p_: m.brdf(g_, p_) + m.cosine_brdf(g_, p_), m.cosine_brdf, g, p,
                               (l, v, *p.values()), rtol=5e-4)


def test_known_coat_terms_are_reused_only_while_angles_and_coat_are_unchanged():
    # a KnownParams coat is one expanded value per pair: the coat's terms are kept for the same Angles object. Every
    # evaluation must still equal a fresh model's — after either coat value changes, for the BRDF after its cosine
    # form, on other angles, after the angles change in place, with a per-pair coat, and with a coat that needs a
    # gradient (which must flow)
    base = materials.get("gotanda2012-layered")
    free = {k: v for k, v in _params(base, 64, 3).items() if k not in ("coat_ior", "coat_roughness")}
    g = _random(64, 4)

    def known(eta, r, model=None):
        return materials.KnownParams(model or materials.get("gotanda2012-layered"),
                                     {"coat_ior": eta, "coat_roughness": r})

    m1 = known(1.5, 0.6, base)
    first = m1.cosine_brdf(g, free)
    assert float(base._coat_cache[2].amax()) > 0.01                                   # a coat lobe that counts
    assert base.coat_terms(g, m1.full(free), True)[0] is base._coat_cache[2]          # kept, and reused
    assert torch.equal(m1.cosine_brdf(g, free), first)
    assert torch.equal(first, known(1.5, 0.6).cosine_brdf(g, free))
    for eta, r in ((1.3, 0.6), (1.3, 0.4), (1.5, 0.6)):                               # one value changes at a time
        assert torch.equal(known(eta, r, base).cosine_brdf(g, free), known(eta, r).cosine_brdf(g, free))
    assert torch.equal(m1.brdf(g, free), known(1.5, 0.6).brdf(g, free))               # the cosine flag is in the key
    m1.cosine_brdf(g, free)
    g2 = _random(64, 5)                                                                 # other angles, same shape
    assert torch.equal(m1.cosine_brdf(g2, free), known(1.5, 0.6).cosine_brdf(g2, free))
    m1.cosine_brdf(g, free)
    g.nh.mul_(0.9)                                                                      # angles changed in place
    assert torch.equal(m1.cosine_brdf(g, free), known(1.5, 0.6).cosine_brdf(g, free))
    one_r = torch.tensor([0.6], dtype=D64).expand(64, 1)
    for lo in (1.2, 1.4):                                                               # η per pair, same first value
        per_pair = dict(free, coat_ior=torch.linspace(1.2, lo + 0.3, 64, dtype=D64)[:, None], coat_roughness=one_r)
        assert torch.equal(base.cosine_brdf(g, per_pair),
                           materials.get("gotanda2012-layered").cosine_brdf(g, per_pair))
    assert base._coat_cache is None                                                     # not one value: not kept
    eta = torch.tensor([1.5], dtype=D64, requires_grad=True)
    grad_p = dict(free, coat_ior=eta.expand(64, 1), coat_roughness=one_r)
    (d_eta,) = torch.autograd.grad(base.cosine_brdf(g, grad_p).sum(), eta)
    assert base._coat_cache is None and float(d_eta.abs()) > 0
