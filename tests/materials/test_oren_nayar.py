"""Oren-Nayar family (materials/oren_nayar.py): limits, equivalences, goldens, an independent full
model, reciprocity, energy, SH lighting, gradients and extreme inputs."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import materials
from materials import Angles
from materials import oren_nayar as on
from materials.environment import SHLight
from materials.validation import directional_albedo, hemisphere_quadrature

D64 = torch.float64
ONE = torch.ones(3, dtype=D64)


def _cfg(theta_i, theta_r, dphi, dtype=D64):
    """Angles from polar angles (radians) and azimuth difference; n = z."""
    ti, tr, ph = (torch.as_tensor(x, dtype=dtype) for x in (theta_i, theta_r, dphi))
    nl, nv = torch.cos(ti), torch.cos(tr)
    lv = nl * nv + torch.sin(ti) * torch.sin(tr) * torch.cos(ph)
    return Angles.from_cosines(nl, nv, lv)


def _random_front(m, seed=0, dtype=D64):
    gen = torch.Generator().manual_seed(seed)
    ti = torch.rand(m, generator=gen, dtype=D64) * 1.45 + 0.02
    tr = torch.rand(m, generator=gen, dtype=D64) * 1.45 + 0.02
    ph = torch.rand(m, generator=gen, dtype=D64) * 2 * math.pi
    return ti, tr, ph, _cfg(ti, tr, ph, dtype)


# every σ-parameterised lobe as f(g, albedo, sigma, cosine)
SIGMA_LOBES = {
    "full": lambda g, a, s, c=False: on.oren_nayar_full(g, a, s, True, c),
    "full-no-ir": lambda g, a, s, c=False: on.oren_nayar_full(g, a, s, False, c),
    "qualitative": lambda g, a, s, c=False: on.oren_nayar_qualitative(g, a, s, c),
    "eq20": lambda g, a, s, c=False: on.gotanda_on_simplified(g, a, sigma=s, cosine=c),
    "eq23": lambda g, a, s, c=False: on.gotanda_on_simplified(g, a, shininess=2.0 / s.square(), cosine=c),
    "eq24": lambda g, a, s, c=False: on.gotanda_on_improved(g, a, 2.0 / s.square(), "eq24", c),
    "eq25": lambda g, a, s, c=False: on.gotanda_on_improved(g, a, 2.0 / s.square(), "eq25", c),
    "2014eq5": lambda g, a, s, c=False: on.gotanda2014_on(g, a, s, c),
    "2014eq7": lambda g, a, s, c=False: on.gotanda2014_on_fresnel(g, a, s, torch.full((3,), 0.04, dtype=D64), c),
}


# -- limits and equivalences ---------------------------------------------------------------------
def test_lambert_limit_at_zero_roughness():
    _, _, _, g = _random_front(200)
    alb = torch.tensor([0.9, 0.5, 0.1], dtype=D64)
    lam = (alb / math.pi).expand(200, 3)
    zero = torch.zeros(1, dtype=D64)
    for name in ("full", "full-no-ir", "qualitative", "eq20", "2014eq5"):
        torch.testing.assert_close(SIGMA_LOBES[name](g, alb, zero), lam, rtol=0, atol=1e-15, msg=name)
    big = torch.tensor([1e12], dtype=D64)  # shininess → ∞
    torch.testing.assert_close(on.gotanda_on_simplified(g, alb, shininess=big), lam, rtol=1e-9, atol=0)
    for form in ("eq24", "eq25"):
        torch.testing.assert_close(on.gotanda_on_improved(g, alb, big, form), lam, rtol=1e-9, atol=0)
    # eq 7 at σ = 0 is (1 − f0) F_diff ρ/π (the Lambert limit "with the Fresnel effect")
    f0 = torch.tensor([0.04, 0.5, 1.0], dtype=D64)
    want = alb / math.pi * (1 - f0) * on.diffuse_fresnel(g.nl, g.nv, f0)
    torch.testing.assert_close(on.gotanda2014_on_fresnel(g, alb, zero, f0), want, rtol=0, atol=1e-15)


def test_eq20_equals_eq23_under_eq21():
    _, _, _, g = _random_front(300, seed=1)
    gen = torch.Generator().manual_seed(2)
    s = torch.rand(300, 1, generator=gen, dtype=D64) * 500 + 0.5
    sigma = torch.sqrt(2.0 / s)  # eq 21
    a = torch.rand(300, 3, generator=gen, dtype=D64)
    torch.testing.assert_close(on.gotanda_on_simplified(g, a, sigma=sigma),
                               on.gotanda_on_simplified(g, a, shininess=s), rtol=1e-12, atol=1e-14)


def test_2014_eq5_is_2012_eq25_in_sigma():
    _, _, _, g = _random_front(300, seed=3)
    sigma = torch.linspace(0.05, 1.5, 300, dtype=D64)[:, None]
    torch.testing.assert_close(on.gotanda2014_on(g, ONE, sigma),
                               on.gotanda_on_improved(g, ONE, 2.0 / sigma.square(), "eq25"), rtol=1e-12, atol=1e-14)


def test_eq11_equals_eq10_from_angles_and_eq20():
    """Eq 10 from θ/φ computed independently from vectors (acos, atan2) = eq 11 lobe = eq 20 lobe."""
    gen = torch.Generator().manual_seed(4)
    l = torch.nn.functional.normalize(torch.randn(400, 3, generator=gen, dtype=D64), dim=-1)
    v = torch.nn.functional.normalize(torch.randn(400, 3, generator=gen, dtype=D64), dim=-1)
    l[:, 2], v[:, 2] = l[:, 2].abs() + 0.01, v[:, 2].abs() + 0.01
    l, v = torch.nn.functional.normalize(l, dim=-1), torch.nn.functional.normalize(v, dim=-1)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    ti, tr = torch.acos(l[:, 2]), torch.acos(v[:, 2])
    dphi = torch.atan2(v[:, 1], v[:, 0]) - torch.atan2(l[:, 1], l[:, 0])
    sigma = 0.7
    A = 1 - 0.5 * sigma**2 / (sigma**2 + 0.33)
    B = 0.45 * sigma**2 / (sigma**2 + 0.09)
    al, be = torch.maximum(ti, tr), torch.minimum(ti, tr)
    eq10 = (A + B * torch.cos(dphi).clamp_min(0) * torch.sin(al) * torch.tan(be)) / math.pi
    g = Angles.from_vectors(n, l, v)
    s = torch.tensor([sigma], dtype=D64)
    torch.testing.assert_close(on.oren_nayar_qualitative(g, ONE, s)[:, 0], eq10, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(on.gotanda_on_simplified(g, ONE, sigma=s)[:, 0], eq10, rtol=1e-10, atol=1e-12)


# -- goldens -------------------------------------------------------------------------------------
def test_qualitative_golden():
    """θ_i = θ_r = 60°, l = v (φ = 0), σ = 1:
    A = 1 − 0.5/1.33 = 0.624060, B = 0.45/1.09 = 0.412844; sin α tan β = sin60 tan60 = 1.5;
    π f/ρ = A + 1.5 B = 1.243326."""
    g = _cfg(math.pi / 3, math.pi / 3, 0.0)
    f = on.oren_nayar_qualitative(g, ONE, torch.tensor([1.0], dtype=D64))
    assert f[0].item() * math.pi == pytest.approx(1 - 0.5 / 1.33 + 1.5 * 0.45 / 1.09, abs=1e-12)
    assert f[0].item() * math.pi == pytest.approx(1.243326, abs=1e-6)


@pytest.mark.parametrize(
    "dphi_deg, expected",
    [
        # θ_i = 60°, θ_r = 30°, σ = 1, ρ = 1: α = 60°, β = 30°, C1 = 0.624060, B = 0.412844,
        # interreflection factor 0.17/1.13 = 0.150442, (2β/π)² = 1/9, (2β/π)³ = 1/27.
        # φ = 0:   C1 + B sin60 tan30 + 0.150442 (1 − 1/9) = 0.624060 + 0.206422 + 0.133726
        (0.0, 0.964208),
        # φ = 90°: C1 + C3 tan45 + 0.150442, C3 = 0.125/1.09 (4·(π/3)(π/6)/π²)² = 0.114679·(2/9)²
        (90.0, 0.624060 + 0.114679 * (2 / 9) ** 2 + 0.150442),
        # φ = 180°: C1 − B (sin60 − 1/27) tan30 + 0.150442 (1 + 1/9)
        (180.0, 0.624060 - 0.412844 * (math.sin(math.pi / 3) - 1 / 27) * math.tan(math.pi / 6) + 0.150442 * 10 / 9),
    ],
)
def test_full_oren_nayar_golden(dphi_deg, expected):
    g = _cfg(math.pi / 3, math.pi / 6, math.radians(dphi_deg))
    f = on.oren_nayar_full(g, ONE, torch.tensor([1.0], dtype=D64))
    assert f[0].item() * math.pi == pytest.approx(expected, abs=2e-6)


def _full_independent(ti, tr, dphi, sigma, rho):
    """Oren & Nayar 1994 from θ/φ angles, written separately from the lobe."""
    s2 = sigma**2
    al, be = torch.maximum(ti, tr), torch.minimum(ti, tr)
    cp = torch.cos(dphi)
    c1 = 1 - 0.5 * s2 / (s2 + 0.33)
    c2 = torch.where(cp >= 0, 0.45 * s2 / (s2 + 0.09) * torch.sin(al),
                     0.45 * s2 / (s2 + 0.09) * (torch.sin(al) - (2 * be / math.pi) ** 3))
    c3 = 0.125 * s2 / (s2 + 0.09) * (4 * al * be / math.pi**2) ** 2
    l1 = rho / math.pi * (c1 + cp * c2 * torch.tan(be) + (1 - cp.abs()) * c3 * torch.tan((al + be) / 2))
    l2 = 0.17 * rho**2 / math.pi * s2 / (s2 + 0.13) * (1 - cp * (2 * be / math.pi) ** 2)
    return l1 + l2


def test_full_oren_nayar_matches_independent_angles_version():
    ti, tr, ph, g = _random_front(500, seed=5)
    for sigma in (0.1, 0.4, 1.0):
        f = on.oren_nayar_full(g, torch.tensor([0.8], dtype=D64), torch.tensor([sigma], dtype=D64))[:, 0]
        torch.testing.assert_close(f, _full_independent(ti, tr, ph, sigma, 0.8), rtol=1e-9, atol=1e-9)


# -- physics ---------------------------------------------------------------------------------------
def test_eq24_goes_negative_and_is_clamped():
    """n·l = n·v = 0.1, l·v = −0.98, s = 2: A = 1 − 1/3.3, B = 1/2.42222, cosri = −0.99,
    π f/ρ = A + B cosri / 0.1 = 0.696970 − 4.087156 = −3.390186 as printed; the lobe clamps to 0."""
    g = Angles.from_cosines(torch.tensor([0.1], dtype=D64), torch.tensor([0.1], dtype=D64),
                            torch.tensor([-0.98], dtype=D64))
    s = torch.tensor([2.0], dtype=D64)
    raw = on.gotanda_on_improved(g, ONE[:1], s, "eq24", clamp=False).item() * math.pi
    assert raw == pytest.approx(1 - 1 / 3.3 - 0.99 / 0.1 / (20 / 9 + 0.2), abs=1e-9)
    assert raw < -3.0
    assert on.gotanda_on_improved(g, ONE[:1], s, "eq24").item() == 0.0
    assert on.gotanda_on_improved(g, ONE[:1], s, "eq25").item() > 0.0


def test_full_model_is_negative_as_published_and_clamped_by_default():
    """Forward grazing mirror pair n·l = n·v = 0.05, l·v = 2·0.05² − 1 (cos(φ_r − φ_i) = −1), σ = 1:
    α = β = acos 0.05; C2 tan β = B (sin α − (2β/π)³) tan β with B = 0.45/1.09; C3's weight 1 − |cos φ| = 0.
    π f = ρ (C1 − C2 tan β) + ρ² 0.17/1.13 (1 + (2β/π)²): negative for dark albedo."""
    c = 0.05
    be = math.acos(c)
    direct = (1 - 0.5 / 1.33) - 0.45 / 1.09 * (math.sin(be) - (2 * be / math.pi) ** 3) * math.tan(be)
    inter = 0.17 / 1.13 * (1 + (2 * be / math.pi) ** 2)
    assert direct == pytest.approx(-0.12862, abs=1e-5)
    g = Angles.from_cosines(torch.tensor([c], dtype=D64), torch.tensor([c], dtype=D64),
                            torch.tensor([2 * c * c - 1], dtype=D64))
    sigma = torch.tensor([1.0], dtype=D64)
    for rho in (0.05, 0.2, 0.4):
        r = torch.tensor([rho], dtype=D64)
        raw = on.oren_nayar_full(g, r, sigma, clamp=False).item() * math.pi
        assert raw == pytest.approx(rho * direct + rho**2 * inter, rel=1e-9)
        assert raw < 0
        assert on.oren_nayar_full(g, r, sigma).item() == 0.0
        assert on.oren_nayar_full(g, r, sigma, cosine=True).item() == 0.0
    # ρ ≥ 0.55 never goes negative at σ = 1: the interreflection outweighs the direct term
    assert on.oren_nayar_full(g, torch.tensor([0.6], dtype=D64), sigma, clamp=False).item() > 0
    # the double-grazing limit: the direct term → C1 − (6/π) B
    gg = Angles.from_cosines(*(torch.tensor([x], dtype=D64) for x in (1e-6, 1e-6, 2e-12 - 1)))
    lim = on.oren_nayar_full(gg, ONE[:1], sigma, interreflection=False, clamp=False).item() * math.pi
    assert lim == pytest.approx((1 - 0.5 / 1.33) - 6 / math.pi * 0.45 / 1.09, abs=1e-5)
    assert lim == pytest.approx(-0.1644, abs=1e-4)


def test_printed_forms_are_model_options():
    """The unclamped (printed) oren-nayar, 2012 eq 24 and 2014 eq 7 through the registry, at their negative
    configurations; the defaults clamp at 0."""
    def at(name, g, **p):
        out = {}
        for clamp in (True, False):
            m = materials.get(name, clamp=clamp) if name != "gotanda-on-improved" else \
                materials.get(name, form="eq24", clamp=clamp)
            full = {s.name: torch.tensor([[p.get(s.name, 1.0)]], dtype=D64).expand(1, s.channels) for s in m.params}
            out[clamp] = m.brdf(g, full)[0, 0].item() * math.pi
        return out

    grazing = Angles.from_cosines(*(torch.tensor([[x]], dtype=D64) for x in (0.05, 0.05, 2 * 0.05**2 - 1)))
    r = at("oren-nayar", grazing, albedo=0.05, roughness=1.0)
    assert r[True] == 0.0 and r[False] == pytest.approx(0.05 * -0.12862 + 0.05**2 * 0.150442 * 1.93750, rel=1e-4)
    backward = Angles.from_cosines(*(torch.tensor([[x]], dtype=D64) for x in (0.1, 0.1, -0.98)))
    r = at("gotanda-on-improved", backward, roughness=1.0)  # r = 1 → s = 0: A = 1/2, B = 0.45
    assert r[True] == 0.0 and r[False] == pytest.approx(0.5 - 0.45 * 0.99 / 0.1, rel=1e-9)
    g7 = _cfg(math.radians(85), math.radians(60), math.pi)
    r = at("gotanda2014-on-fresnel", g7, roughness=1.0, f0=0.04)  # r = 1 → σ = 1 (capped)
    assert r[True] == 0.0 and r[False] == pytest.approx(-0.1027, abs=1e-4)
    with pytest.raises(ValueError, match=r"\[True, False\]"):
        materials.get("oren-nayar", clamp="no")


def test_negative_extent_measures_the_published_model_only():
    # the docs' measurement (4·10⁶ pairs: 0.60 %, min π f/ρ −0.160 at r = 1, ρ → 0) on a small sample
    from materials.validation import negative_extent
    raw = negative_extent(materials.get("oren-nayar", clamp=False), m=50_000, albedo=1e-9, roughness=1.0)
    assert 0.003 < raw["negative_fraction"] < 0.01 and -0.165 < raw["min_pi_f_over_albedo"] < -0.12
    assert negative_extent(materials.get("oren-nayar"), m=50_000)["negative_fraction"] == 0.0


@given(nl=st.floats(1e-6, 1.0), nv=st.floats(1e-6, 1.0), t=st.floats(0.0, 1.0), rho=st.floats(0.0, 1.0),
       r=st.floats(0.0, 1.0))
def test_full_model_default_is_never_negative(nl, nv, t, rho, r):
    sl, sv = math.sqrt(1 - nl * nl), math.sqrt(1 - nv * nv)
    lv = nl * nv + sl * sv * math.cos(math.pi * t)
    g = Angles.from_cosines(*(torch.tensor([[x]], dtype=D64) for x in (nl, nv, lv)))
    m = materials.get("oren-nayar")
    p = {"albedo": torch.full((1, 3), rho, dtype=D64), "roughness": torch.tensor([[r]], dtype=D64)}
    assert (m.brdf(g, p) >= 0).all() and (m.cosine_brdf(g, p) >= 0).all()


#: Directional albedo ∫ f_r (n·l) dω_l at ρ = 1 (quadrature 64 × 128), by σ and θ_v: the models
#: that gain energy, and by how much (Gotanda 2012 footnote 1). Measured; see docs/models-diffuse.md.
ENERGY_GAIN = {
    # model: (sigma, theta_v degrees, albedo measured)
    "oren-nayar": (0.25, 89.0, 1.0426),
    "oren-nayar-qualitative": (0.25, 89.0, 1.0116),
    "gotanda-on-simplified": (0.25, 89.0, 1.0116),  # = qualitative (eq 20 ≡ eq 10)
    "gotanda-on-improved": (0.25, 89.0, 1.0082),
    "gotanda2014-on": (0.25, 89.0, 1.0082),  # = eq 25
}


@pytest.mark.parametrize("name", ["oren-nayar", "oren-nayar-qualitative", "gotanda-on-simplified",
                                  "gotanda-on-improved", "gotanda2014-on", "gotanda2014-on-fresnel"])
def test_directional_albedo(name):
    m = materials.get(name)
    th = torch.tensor([0.0, 30.0, 60.0, 80.0, 89.0], dtype=D64) * math.pi / 180
    worst = 0.0
    for sigma in (0.25, 0.5, 0.75, 1.0):
        p = {"albedo": ONE, "f0": torch.zeros(3, dtype=D64),
             "roughness": materials.roughness.sigma_to_roughness(torch.tensor([sigma], dtype=D64))}
        p = {k: x for k, x in p.items() if k in m.param_names}
        a = directional_albedo(m, p, th, n_theta=64, n_phi=128)[:, 0]
        worst = max(worst, a.max().item())
        if name in ENERGY_GAIN and ENERGY_GAIN[name][0] == sigma:
            assert a[-1].item() == pytest.approx(ENERGY_GAIN[name][2], abs=2e-3)
    if name in ENERGY_GAIN:
        assert 1.0 < worst <= ENERGY_GAIN[name][2] + 2e-3  # gains energy, and only that much
    else:
        assert worst <= 1.0 + 1e-3


# -- SH lighting (Gotanda 2012 eq 26-29) -----------------------------------------------------------
def _eq26(shininess, nv):
    """Eq 26: ∫ L_r dω_i of eq 25 at ρ = 1, for views in the xz-plane with n·v = nv."""
    d, w = hemisphere_quadrature(96, 192)
    tv = torch.acos(nv)
    v = torch.stack([torch.sin(tv), torch.zeros_like(tv), torch.cos(tv)], -1)[:, None, :]
    g = Angles.from_vectors(torch.tensor([0.0, 0.0, 1.0], dtype=D64), d[None], v)
    f = on.gotanda_on_improved(g, ONE[:1], torch.tensor([shininess], dtype=D64), "eq25", cosine=True)
    return (f[..., 0] * w).sum(-1)


def test_sh_dc_scale_against_eq26_integral():
    """Eq 27/28 are exact at N·E = 1 (both = f(s)) but overestimate eq 26 toward grazing views:
    measured max |eq27 − eq26| = 0.294 at σ = 1 (g(s) = 0.413), i.e. 0.71 g(s). Eq 27 instead tracks
    f(s) + 2 g(s) P(N·E), P the integral of the cosri ≥ 0 part alone, to 0.021 g(s) (see docs)."""
    nv = torch.linspace(0.0, 1.0, 11, dtype=D64)
    for sigma, max27 in ((0.25, 0.132), (0.5, 0.236), (1.0, 0.295)):
        s = 2.0 / sigma**2
        ref = _eq26(s, nv)
        e27 = on.sh_dc_scale(torch.tensor([s], dtype=D64), nv[:, None], "eq27")[:, 0]
        e28 = on.sh_dc_scale(torch.tensor([s], dtype=D64), nv[:, None], "eq28")[:, 0]
        assert e27[-1].item() == pytest.approx(ref[-1].item(), abs=1e-6)  # N·E = 1: A · Lambert
        assert e28[-1].item() == pytest.approx(ref[-1].item(), abs=1e-6)
        assert (e27 - ref).abs().max().item() == pytest.approx(max27, abs=0.01)
        assert (e28 - ref).abs().max().item() == pytest.approx(max27, abs=0.01)  # both reach g(s)(1 − 0.288) at N·E = 0


def test_sh_linear_scale_values_and_exact_normal_view():
    s1 = torch.tensor([2.0], dtype=D64)  # σ = 1
    f = 1 - 1 / (2 + 0.65 * 2)
    assert on.sh_linear_scale(s1, torch.tensor([1.0], dtype=D64)).item() == pytest.approx(f)  # 0.697
    assert on.sh_linear_scale(s1, torch.tensor([0.0], dtype=D64)).item() == pytest.approx(2 * f - 1)  # 0.394
    assert on.sh_linear_scale(torch.tensor([1e9], dtype=D64), torch.tensor([0.3], dtype=D64)).item() == \
        pytest.approx(1.0, abs=1e-8)


def test_sh_environment_exact_at_normal_view():
    """At v = n every Gotanda improved form is A · Lambert, so eq 27-29 must reproduce the brute-force
    ∫ f_r L(ω) cos dω for any order-1 SH light (quadratic band: A too, eq 29 leaves it at 1 — so the
    test light has no quadratic band)."""
    gen = torch.Generator().manual_seed(7)
    coeffs = torch.zeros(9, 3, dtype=D64)
    coeffs[:4] = torch.rand(4, 3, generator=gen, dtype=D64)
    coeffs[0] += 2.0
    env = SHLight(coeffs)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=D64)
    m = materials.get("gotanda-on-improved")
    p = {"albedo": torch.tensor([0.8, 0.5, 0.3], dtype=D64), "roughness": torch.tensor([0.9], dtype=D64)}
    got = m.environment(env, n, n, p)
    d, w = hemisphere_quadrature(64, 128)
    g = Angles.from_vectors(n, d, n)
    brute = (m.cosine_brdf(g, p) * env.radiance(d) * w[:, None]).sum(0)
    torch.testing.assert_close(got[0], brute, rtol=1e-6, atol=1e-8)


def test_environment_rejects_other_lights_and_simplified_has_none():
    m = materials.get("gotanda2014-on", sh_dc="eq28")
    hemi = materials.HemisphereLight(torch.ones(3), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    n = torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(NotImplementedError, match="HemisphereLight"):
        m.environment(hemi, n, n, m.defaults())
    with pytest.raises(NotImplementedError):
        simplified = materials.get("gotanda-on-simplified")
        simplified.environment(SHLight(torch.zeros(9, 3)), n, n, simplified.defaults())


# -- registry --------------------------------------------------------------------------------------
def test_registry_options_list_valid_values():
    with pytest.raises(ValueError, match=r"\['sigma', 'shininess'\]"):
        materials.get("gotanda-on-simplified", form="eq99")
    with pytest.raises(ValueError, match=r"\['eq24', 'eq25'\]"):
        materials.get("gotanda-on-improved", form="eq26")
    with pytest.raises(ValueError, match=r"\['eq27', 'eq28'\]"):
        materials.get("gotanda2014-on", sh_dc="eq29")
    with pytest.raises(ValueError, match=r"\[True, False\]"):
        materials.get("oren-nayar", interreflection="yes")
    assert not materials.get("oren-nayar").spec("albedo").linear  # ρ² interreflection
    assert materials.get("oren-nayar", interreflection=False).spec("albedo").linear
    with pytest.raises(TypeError, match="Angles"):
        on.oren_nayar_full(torch.zeros(3), ONE, 0.5)
    with pytest.raises(ValueError, match="exactly one"):
        on.gotanda_on_simplified(_cfg(0.1, 0.2, 0.3), ONE)


def test_shininess_form_matches_sigma_form_below_sigma_cap():
    _, _, _, g = _random_front(100, seed=8)
    p = {"albedo": ONE, "roughness": torch.linspace(0.05, 0.8, 100, dtype=D64)[:, None]}
    a = materials.get("gotanda-on-simplified", form="sigma").brdf(g, p)
    b = materials.get("gotanda-on-simplified", form="shininess").brdf(g, p)
    torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


# -- gradients -------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["oren-nayar", "oren-nayar-qualitative", "gotanda-on-simplified",
                                  "gotanda-on-improved", "gotanda2014-on", "gotanda2014-on-fresnel"])
@pytest.mark.parametrize("cosine", [False, True])
def test_gradcheck(name, cosine):
    m = materials.get(name)
    ti = torch.tensor([0.3, 0.9, 1.2, 0.5], dtype=D64)
    tr = torch.tensor([0.7, 0.2, 1.0, 1.3], dtype=D64)
    ph = torch.tensor([0.4, 2.5, 1.0, 3.0], dtype=D64)
    nl, nv = torch.cos(ti)[:, None], torch.cos(tr)[:, None]
    lv = nl * nv + (torch.sin(ti) * torch.sin(tr) * torch.cos(ph))[:, None]
    albedo = torch.tensor([[0.3, 0.6, 0.9]], dtype=D64).expand(4, 3).clone()
    rough = torch.tensor([[0.3], [0.5], [0.7], [0.6]], dtype=D64)
    f0 = torch.tensor([[0.04, 0.2, 0.5]], dtype=D64).expand(4, 3).clone()
    names = [s.name for s in m.params]

    def fn(nl, nv, lv, albedo, rough, f0):
        p = {"albedo": albedo, "roughness": rough, "f0": f0}
        g = Angles.from_cosines(nl, nv, lv)
        p = {k: p[k] for k in names}
        return m.cosine_brdf(g, p) if cosine else m.brdf(g, p)

    inputs = tuple(x.clone().requires_grad_() for x in (nl, nv, lv, albedo, rough, f0))
    assert torch.autograd.gradcheck(fn, inputs, atol=1e-6, rtol=1e-5)


# -- extreme inputs --------------------------------------------------------------------------------
EXTREME_COS = [0.0, 1e-7, -1e-7, -1e-3, 1e-4, 0.5, 1.0 - 1e-7, 1.0]


@settings(max_examples=30)
@given(
    nl=st.sampled_from(EXTREME_COS) | st.floats(-0.2, 1.0),
    nv=st.sampled_from(EXTREME_COS) | st.floats(-0.2, 1.0),
    t=st.floats(0.0, 1.0),
    r=st.sampled_from([0.0, 1e-6, 0.84, 1.0]) | st.floats(0.0, 1.0),
    opposite=st.booleans(),
)
def test_extreme_inputs_finite_and_float32_matches(nl, nv, t, r, opposite):
    # a consistent l·v between its bounds for these polar angles, or l = −v
    sl, sv = math.sqrt(max(0.0, 1 - nl * nl)), math.sqrt(max(0.0, 1 - nv * nv))
    lv = -1.0 if opposite else nl * nv + sl * sv * (2 * t - 1)
    if opposite:
        nv = -nl
    # Both precisions must see the same inputs: round them to float32 first (e.g. n·v = 4.6e-170 is
    # front-facing in float64 but exactly 0 in float32).
    nl, nv, lv = (float(torch.tensor(x, dtype=torch.float32)) for x in (nl, nv, lv))
    for name in ["oren-nayar", "oren-nayar-qualitative", "gotanda-on-simplified", "gotanda-on-improved",
                 "gotanda2014-on", "gotanda2014-on-fresnel"]:
        m = materials.get(name)
        outs = {}
        for dt in (torch.float64, torch.float32):
            c = [torch.tensor([[x]], dtype=dt, requires_grad=True) for x in (nl, nv, lv)]
            p = {"albedo": torch.tensor([[1.0, 0.5, 0.0]], dtype=dt, requires_grad=True),
                 "roughness": torch.tensor([[r]], dtype=dt, requires_grad=True),
                 "f0": torch.tensor([[0.0, 0.04, 1.0]], dtype=dt, requires_grad=True)}
            p = {k: p[k] for k in m.param_names}
            g = Angles.from_cosines(*c)
            f = m.cosine_brdf(g, p)
            fb = m.brdf(g, p)
            grads = torch.autograd.grad(f.sum() + fb.sum(), [*c, *p.values()], allow_unused=True)
            assert torch.isfinite(f).all() and torch.isfinite(fb).all(), (name, dt)
            assert all(gr is None or torch.isfinite(gr).all() for gr in grads), (name, dt)
            outs[dt] = f.detach().double()
        torch.testing.assert_close(outs[torch.float32], outs[torch.float64], atol=2e-4, rtol=2e-3, msg=name)


def test_eq7_goes_negative_backward_grazing_and_is_clamped():
    """θ_i = 85°, θ_r = 60°, φ = 180°, σ = 1, f0 = 0.04 (F_diff kills the Lambert term, not cosri):
    π f/ρ = 0.96 [F_diff·0.696970·… ] + 0.96·0.412844·cosri·n·l/n·l… = −0.1027 as printed."""
    g = _cfg(math.radians(85), math.radians(60), math.pi)
    s, f0 = torch.tensor([1.0], dtype=D64), torch.tensor([0.04], dtype=D64)
    nl, nv = math.cos(math.radians(85)), math.cos(math.radians(60))
    cosri = -math.sin(math.radians(85)) * math.sin(math.radians(60))
    fd = 1.05 * 0.96 * (1 - (1 - nl) ** 5) * (1 - (1 - nv) ** 5)
    want = 0.96 * (fd * (1 - 0.5 / 1.65) + 0.45 / 1.09 * cosri)
    raw = on.gotanda2014_on_fresnel(g, ONE[:1], s, f0, clamp=False).item() * math.pi
    assert raw == pytest.approx(want, abs=1e-12)
    assert raw == pytest.approx(-0.1027, abs=1e-4)
    assert on.gotanda2014_on_fresnel(g, ONE[:1], s, f0).item() == 0.0
