"""Microfacet D, G and the D·F·G/(4 n·l n·v) specular: goldens, normalisation, reciprocity,
energy (white furnace by quadrature), gradients, extreme inputs."""

import functools
import itertools
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

import materials
from materials import microfacet as mf
from materials import roughness as rough
from materials.fresnel import FRESNEL, fresnel_from_f0
from materials.geometry import Angles

D64 = torch.float64


def a64(x):
    return torch.tensor([x], dtype=D64)


@functools.cache
def gauss_legendre(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return torch.tensor((x + 1) / 2, dtype=D64), torch.tensor(w / 2, dtype=D64)


def hemisphere_grid(n_mu=192, n_phi=192):
    mu, w = gauss_legendre(n_mu)
    phi = (torch.arange(n_phi, dtype=D64) + 0.5) * (2 * math.pi / n_phi)
    return mu[:, None], w[:, None], phi[None, :], 2 * math.pi / n_phi


def directional_albedo(brdf, theta_v, n_mu=192, n_phi=192):
    """∫ f_r(l, v) (n·l) dω_l by Gauss-Legendre in cos θ_l × midpoint rule in φ (channel 0)."""
    mu, w, phi, w_phi = hemisphere_grid(n_mu, n_phi)
    mv, sv = math.cos(theta_v), math.sin(theta_v)
    lv = torch.sqrt(1 - mu**2) * sv * torch.cos(phi) + mu * mv
    g = Angles.from_cosines(mu.expand_as(lv), torch.full_like(lv, mv), lv)
    return float((brdf(g)[..., 0] * mu * w * w_phi).sum())


# -- D ---------------------------------------------------------------------------------------------------
def test_ndf_goldens():
    for a in (0.05, 0.3, 1.0):
        one = torch.tensor([[1.0]], dtype=D64)
        assert mf.ndf_ggx(one, a64(a)).item() == pytest.approx(1 / (math.pi * a * a), rel=1e-12)
        assert mf.ndf_beckmann(one, a64(a)).item() == pytest.approx(1 / (math.pi * a * a), rel=1e-12)
        s = 2 / a**2 - 2
        assert mf.ndf_blinn_phong(one, a64(a)).item() == pytest.approx((s + 2) / (2 * math.pi), rel=1e-12)
        assert mf.ndf_ggx(torch.tensor([[1e-9]], dtype=D64), a64(a)).item() == pytest.approx(a * a / math.pi)
    # GGX at α = 1 and Blinn-Phong at s = 0 are both the uniform 1/π
    nh = torch.linspace(0.01, 1, 7, dtype=D64)[:, None]
    torch.testing.assert_close(mf.ndf_ggx(nh, a64(1.0)), torch.full_like(nh, 1 / math.pi))
    torch.testing.assert_close(mf.ndf_blinn_phong(nh, a64(1.0)), torch.full_like(nh, 1 / math.pi))
    # Beckmann at 45° half angle: exp(−1/α²)/(π α² cos⁴) with cos⁴ = 1/4
    c = torch.tensor([[math.sqrt(0.5)]], dtype=D64)
    assert mf.ndf_beckmann(c, a64(0.5)).item() == pytest.approx(math.exp(-4) / (math.pi * 0.25 * 0.25), rel=1e-12)
    for f in (mf.ndf_ggx, mf.ndf_beckmann, mf.ndf_blinn_phong):
        assert (f(torch.tensor([[0.0], [-0.5]], dtype=D64), a64(0.5)) == 0).all()


@pytest.mark.parametrize("name", mf.DISTRIBUTIONS)
@pytest.mark.parametrize("alpha", [0.03, 0.1, 0.4, 1.0])
def test_ndf_normalised(name, alpha):
    """∫ D(h) (n·h) dω_h = 2π ∫ D(μ) μ dμ = 1, by adaptive quadrature (scipy.integrate.quad, which
    is independent of our grids) split at the lobe width 1 − μ ≈ α²."""
    from scipy.integrate import quad

    def integrand(mu):
        return 2 * math.pi * mu * mf.ndf(name, torch.tensor([[mu]], dtype=D64), a64(alpha)).item()

    split = max(0.0, 1.0 - 20 * alpha * alpha)
    total = sum(quad(integrand, lo, hi, limit=200, epsabs=1e-10)[0] for lo, hi in ((0.0, split), (split, 1.0)))
    assert total == pytest.approx(1.0, abs=1e-3)


# -- G -----------------------------------------------------------------------------------------------------
def test_smith_g1_ggx_golden_and_bounds():
    c = torch.linspace(0, 1, 101, dtype=D64)[:, None]
    for a in (rough.ALPHA_MIN, 0.1, 0.5, 1.0):
        g1 = mf.smith_g1_ggx(c, a64(a))
        assert (g1 >= 0).all() and (g1 <= 1 + 1e-15).all()
        assert g1[-1].item() == pytest.approx(1.0) and g1[0].item() == 0.0
        torch.testing.assert_close(mf.smith_g1(c, a64(a), "ggx"), g1)
    # α = 1: G1 = 2c/(c + 1)
    torch.testing.assert_close(mf.smith_g1_ggx(c, a64(1.0)), 2 * c / (c + 1))


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_beckmann_g1_rational_vs_exact(alpha):
    c = torch.linspace(0.005, 0.999, 300, dtype=D64)[:, None]
    a = c / (alpha * torch.sqrt(1 - c * c))
    lam = (torch.erf(a) - 1) / 2 + torch.exp(-a * a) / (2 * a * math.sqrt(math.pi))
    exact = 1 / (1 + lam)
    got = mf.smith_g1(c, a64(alpha), "beckmann")
    assert (got - exact).abs().max().item() < 0.0032
    assert ((got - exact).abs() / exact).max().item() < 0.0032
    assert (got <= 1).all() and (got >= 0).all()


def _beckmann_lambda_by_quadrature(cos_o: float, alpha: float) -> float:
    """The Smith Λ of the Beckmann slopes from its definition (projected area of the visible microsurface,
    Heitz 2014 eq 2): cos θ (1 + Λ) = ∫ max(0, ω·m) D(m) dω_m. With tan θ_m = α t, D(m) dω_m =
    exp(−t²) t/(π cos θ_m) dt dφ and ω·m / cos θ_m = cos θ + α t sin θ cos φ; the φ-integral of the clamped
    linear function is closed form, the t-integral is Gauss-Legendre split at its kink t = cot θ/α."""
    sin_o = math.sqrt(1 - cos_o * cos_o)
    a = cos_o / (alpha * sin_o)

    def phi_integral(t):
        A, B = cos_o, alpha * t * sin_o
        if A >= B:
            return 2 * math.pi * A
        p0 = math.acos(-A / B)
        return 2 * (A * p0 + B * math.sin(p0))

    x, w = np.polynomial.legendre.leggauss(200)
    total = 0.0
    for lo, hi in ((0.0, a), (a, max(a, 0.0) + 12.0)):
        ts = 0.5 * (hi - lo) * (x + 1) + lo
        total += sum(0.5 * (hi - lo) * wi * math.exp(-t * t) * t / math.pi * phi_integral(t)
                     for t, wi in zip(ts, w, strict=True))
    return total / cos_o - 1.0


@pytest.mark.parametrize("alpha", [0.02, 0.3, 1.0])
def test_beckmann_exact_lambda_matches_its_defining_integral(alpha):
    for c in (0.01, 0.2, 0.5, 0.9):
        got = mf.smith_lambda_cos(torch.tensor([[c]], dtype=D64), a64(alpha), "beckmann", "exact").item() / c
        ref = _beckmann_lambda_by_quadrature(c, alpha)
        assert got == pytest.approx(ref, rel=1e-7, abs=1e-12), (c, alpha)
    # cos·Λ at grazing: α/(2√π); finite value and gradient at cos = 0 and 1, in float32 too
    for dt in (torch.float64, torch.float32):
        cc = torch.tensor([[0.0], [1e-7], [0.5], [1.0]], dtype=dt, requires_grad=True)
        lam = mf.smith_lambda_cos(cc, torch.tensor([alpha], dtype=dt), "beckmann", "exact")
        lam.sum().backward()
        assert torch.isfinite(lam).all() and torch.isfinite(cc.grad).all()
        assert lam[0].item() == pytest.approx(alpha / (2 * math.sqrt(math.pi)), rel=1e-6)


def test_beckmann_rational_lambda_agrees_with_exact_within_its_stated_error():
    # Walter et al. 2007 eq 27: G1 within 0.32 % (measured max 0.313 %); G2 adds two Λ's errors, same sign: 0.63 %
    c = torch.linspace(1e-4, 1.0, 300, dtype=D64)[:, None]
    for a in (rough.ALPHA_MIN, 0.05, 0.3, 1.0):
        r, e = mf.smith_g1(c, a64(a), "beckmann"), mf.smith_g1(c, a64(a), "beckmann", "exact")
        assert ((r - e).abs() / e).max().item() < 0.0032
    nl, nv = (x.reshape(-1, 1) for x in torch.meshgrid(c[::10, 0], c[::10, 0], indexing="ij"))
    g = Angles.from_cosines(nl, nv, nl * nv)
    for d in ("beckmann", "blinn-phong"):
        for gname in ("smith", "smith-correlated"):
            r = mf.geometry_term(gname, g, a64(0.3), d)
            e = mf.geometry_term(gname, g, a64(0.3), d, "exact")
            assert ((r - e).abs() / e).max().item() < 0.0064
    m_exact = materials.get("microfacet", D="beckmann", G="smith-correlated", beckmann_lambda="exact")
    m_rat = materials.get("microfacet", D="beckmann", G="smith-correlated")
    p = {"f0": torch.full((1, 3), 0.04, dtype=D64), "roughness": torch.full((1, 1), 0.5, dtype=D64)}
    fe, fr = m_exact.brdf(g, p), m_rat.brdf(g, p)
    assert ((fe - fr).abs() / fe.clamp_min(1e-300))[fe > 0].max().item() < 0.0064
    with pytest.raises(ValueError, match="beckmann_lambda"):
        materials.get("microfacet", beckmann_lambda="erf")


def test_g2_correlated_between_separable_and_min():
    nl, nv = torch.meshgrid(torch.linspace(0.01, 1, 25, dtype=D64), torch.linspace(0.01, 1, 25, dtype=D64),
                            indexing="ij")
    nl, nv = nl[..., None], nv[..., None]
    for a in (0.1, 0.5, 1.0):
        g2 = mf.smith_g2_correlated_ggx(nl, nv, a64(a))
        g1l, g1v = mf.smith_g1_ggx(nl, a64(a)), mf.smith_g1_ggx(nv, a64(a))
        assert (g2 >= g1l * g1v - 1e-12).all() and (g2 <= torch.minimum(g1l, g1v) + 1e-12).all()
    assert mf.smith_g2_correlated_ggx(torch.tensor([[0.0]]), torch.tensor([[0.5]]), 0.5).item() == 0.0


def test_geometry_goldens():
    # n·l = 0.6, n·v = 0.8 with l, v in the same plane on opposite sides of n
    nl, nv = 0.6, 0.8
    lv = -(math.sqrt(1 - nl**2) * math.sqrt(1 - nv**2)) + nl * nv
    g = Angles.from_cosines(torch.tensor(nl, dtype=D64), torch.tensor(nv, dtype=D64), torch.tensor(lv, dtype=D64))
    lh = math.sqrt((1 + lv) / 2)
    nh = (nl + nv) / (2 * lh)
    a = a64(0.5)
    ct = min(1, 2 * nh * nv / lh, 2 * nh * nl / lh)
    assert mf.geometry_term("cook-torrance", g, a).item() == pytest.approx(ct, rel=1e-12)
    assert mf.geometry_term("kelemen", g, a).item() == pytest.approx(nl * nv / lh**2, rel=1e-12)
    assert mf.geometry_term("neumann", g, a).item() == pytest.approx(min(nl, nv), rel=1e-12)
    a2 = 0.25
    sep = (2 * nl / (nl + math.sqrt(a2 + (1 - a2) * nl**2))) * (2 * nv / (nv + math.sqrt(a2 + (1 - a2) * nv**2)))
    assert mf.geometry_term("smith", g, a).item() == pytest.approx(sep, rel=1e-12)
    lam = lambda c: (-1 + math.sqrt(1 + a2 * (1 - c * c) / (c * c))) / 2  # noqa: E731
    assert mf.geometry_term("smith-correlated", g, a).item() == pytest.approx(1 / (1 + lam(nl) + lam(nv)), rel=1e-12)
    # visibility is G/(4 n·l n·v)
    for name in mf.GEOMETRIES:
        for d in mf.DISTRIBUTIONS:
            v = mf.visibility_term(name, g, a, d).item()
            assert v * 4 * nl * nv == pytest.approx(mf.geometry_term(name, g, a, d).item(), rel=1e-12)


def test_geometry_in_unit_interval_and_zero_when_back_facing():
    nl, nv, phi = torch.meshgrid(torch.linspace(-0.2, 1, 13, dtype=D64), torch.linspace(-0.2, 1, 13, dtype=D64),
                                 torch.linspace(0, math.pi, 7, dtype=D64), indexing="ij")
    lv = torch.sqrt((1 - nl**2).clamp_min(0) * (1 - nv**2).clamp_min(0)) * torch.cos(phi) + nl * nv
    g = Angles.from_cosines(nl, nv, lv)
    for name, d in itertools.product(mf.GEOMETRIES, mf.DISTRIBUTIONS):
        gt = mf.geometry_term(name, g, a64(0.4), d)
        assert (gt >= 0).all() and (gt <= 1).all()
        assert (gt[~g.front] == 0).all()


def test_option_errors():
    g = Angles.from_cosines(torch.tensor(0.5), torch.tensor(0.5), torch.tensor(0.0))
    with pytest.raises(ValueError, match="valid choices: smith, smith-correlated, cook-torrance, kelemen, neumann"):
        mf.geometry_term("walter", g, 0.5)
    with pytest.raises(ValueError, match="valid choices: ggx, beckmann, blinn-phong"):
        mf.microfacet_specular(g, torch.ones(3), 0.5, D="phong")
    with pytest.raises(ValueError, match="valid choices: none, schlick, exact, sg, schuler"):
        mf.microfacet_specular(g, torch.ones(3), 0.5, F="fresnel")
    with pytest.raises(ValueError, match="valid choices"):
        materials.get("microfacet", G="smithy")
    with pytest.raises(TypeError, match="materials.Angles"):
        mf.microfacet_specular((0.5, 0.5), torch.ones(3), 0.5)
    with pytest.raises(ValueError, match="trailing dimension of size 1"):
        mf.ndf_ggx(torch.ones(4, 3), 0.5)


# -- the specular BRDF -----------------------------------------------------------------------------------
COMBOS = list(itertools.product(mf.DISTRIBUTIONS, mf.GEOMETRIES, FRESNEL))


def random_angles(n=64, seed=0, dtype=D64):
    gen = torch.Generator().manual_seed(seed)
    def unit(x):
        return x / x.norm(dim=-1, keepdim=True)
    nrm = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    l = unit(torch.randn(n, 3, generator=gen, dtype=dtype) + 1.5 * nrm)
    v = unit(torch.randn(n, 3, generator=gen, dtype=dtype) + 1.5 * nrm)
    return nrm, l, v


def test_specular_matches_direct_formula():
    nrm, l, v = random_angles()
    g = Angles.from_vectors(nrm, l, v)
    f0 = torch.tensor([0.04, 0.5, 0.95], dtype=D64)
    a = a64(0.35)
    for d, gname, fname in COMBOS:
        ref = (mf.ndf(d, g.nh, a) * FRESNEL[fname](f0, g.lh) * mf.geometry_term(gname, g, a, d)
               / (4 * g.nl * g.nv))
        ref = torch.where(g.front, ref, torch.zeros_like(ref))
        torch.testing.assert_close(mf.microfacet_specular(g, f0, a, d, gname, fname), ref, rtol=1e-10, atol=1e-12)


def test_white_furnace_ggx_alpha1_closed_form():
    """GGX α = 1 is the uniform D = 1/π and A = 1, so at normal view V = 0.5/(1 + n·l) and the albedo
    is 2 ∫ μ/(2(1 + μ)) dμ = 1 − ln 2."""
    one = torch.ones(3, dtype=D64)
    for gname in ("smith", "smith-correlated"):
        alb = directional_albedo(lambda g, gname=gname: mf.microfacet_specular(g, one, a64(1.0), "ggx", gname, "none"),
                                 0.0)
        assert alb == pytest.approx(1 - math.log(2), abs=1e-6)


# measured directional albedos for f0 = 1, F = none (quadrature 256 × 256, θ_v = 0, 45, 75, 85°):
# every combination stays ≤ 1 except Smith with the Blinn-Phong D at high roughness (Beckmann Λ ≠ the
# Blinn-Phong Λ when s is small): r = 0.7 → 1.017 (smith) / 1.038 (correlated) at 85°, r = 1 → 1.16 / 1.35.
@pytest.mark.parametrize("r", [0.5, 0.7, 1.0])
def test_white_furnace_energy(r):
    one = torch.ones(3, dtype=D64)
    a = rough.roughness_to_alpha(a64(r))
    worst = {}
    for d, gname in itertools.product(mf.DISTRIBUTIONS, mf.GEOMETRIES):
        def brdf(g, d=d, gname=gname):
            return mf.microfacet_specular(g, one, a, d, gname, "none")

        albs = [directional_albedo(brdf, math.radians(t), n_mu=128, n_phi=96) for t in (0, 60, 85)]
        worst[(d, gname)] = max(albs)
    for (d, gname), w in worst.items():
        if d == "blinn-phong" and gname.startswith("smith") and r > 0.5:
            continue
        assert w <= 1.0 + 2e-3, (d, gname, r, w)
    if r == 1.0:  # the documented exceedance, so that a change in it is noticed
        assert worst[("blinn-phong", "smith-correlated")] == pytest.approx(1.3457, abs=2e-3)
    if r == 0.5:  # a smooth Beckmann surface with Smith masking keeps nearly all energy at normal view
        alb = directional_albedo(lambda g: mf.microfacet_specular(g, one, a, "beckmann", "smith", "none"), 0.0)
        assert alb > 0.99


# -- models ----------------------------------------------------------------------------------------------
def test_models():
    nrm, l, v = random_angles(seed=5)
    g = Angles.from_vectors(nrm, l, v)
    p = {"albedo": torch.tensor([0.2, 0.4, 0.6], dtype=D64), "f0": torch.tensor([0.04, 0.05, 0.9], dtype=D64),
         "roughness": torch.tensor([0.45], dtype=D64)}
    a = rough.roughness_to_alpha(p["roughness"])
    m = materials.get("microfacet", D="beckmann", G="smith", F="exact")
    assert m.param_names == ("f0", "roughness") and not m.spec("f0").linear
    assert materials.get("microfacet").spec("f0").linear  # Schlick is affine in f0
    torch.testing.assert_close(m.brdf(g, p), mf.microfacet_specular(g, p["f0"], a, "beckmann", "smith", "exact"))
    ct = materials.get("cook-torrance")
    assert ct.param_names == ("albedo", "f0", "roughness")
    ref = (torch.where(g.front, p["albedo"] / math.pi, torch.zeros(3, dtype=D64))
           + mf.microfacet_specular(g, p["f0"], a, "beckmann", "cook-torrance", fresnel_from_f0))
    torch.testing.assert_close(ct.brdf(g, p), ref)
    out = ct(nrm, l[0], v[0], albedo=torch.tensor([0.5, 0.5, 0.5]))
    assert out.shape == (3,) and torch.isfinite(out).all()


# -- gradients -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("d,gname", list(itertools.product(mf.DISTRIBUTIONS, mf.GEOMETRIES)))
def test_gradcheck(d, gname):
    nl = torch.tensor([[0.3], [0.7], [0.9]], dtype=D64, requires_grad=True)
    nv = torch.tensor([[0.8], [0.4], [0.95]], dtype=D64, requires_grad=True)
    lv = torch.tensor([[-0.2], [0.1], [0.8]], dtype=D64, requires_grad=True)
    f0 = torch.tensor([0.04, 0.3, 0.9], dtype=D64, requires_grad=True)
    r = torch.tensor([0.55], dtype=D64, requires_grad=True)

    def fn(nl, nv, lv, f0, r):
        g = Angles.from_cosines(nl, nv, lv)
        return mf.microfacet_specular(g, f0, rough.roughness_to_alpha(r), d, gname, "exact")

    assert torch.autograd.gradcheck(fn, (nl, nv, lv, f0, r))


# -- extremes: hypothesis --------------------------------------------------------------------------------
COS = st.one_of(st.sampled_from([0.0, 1e-7, -1e-4, 1.0, 1.0 - 1e-7]), st.floats(-0.2, 1.0))
PHI = st.one_of(st.sampled_from([0.0, math.pi]), st.floats(0.0, math.pi))
R = st.one_of(st.sampled_from([0.0, 1.0, rough.R_MIN]), st.floats(0.0, 1.0))
F0V = st.one_of(st.sampled_from([0.0, 1.0]), st.floats(0.0, 1.0))


def _f32(x):
    return float(np.float32(x))


def _eval(nl, nv, phi, r, f0, dtype, d, gname, fname):
    nl_t = torch.tensor([nl], dtype=dtype, requires_grad=True)
    nv_t = torch.tensor([nv], dtype=dtype, requires_grad=True)
    r_t = torch.tensor([r], dtype=dtype, requires_grad=True)
    f0_t = torch.tensor([f0, f0, f0], dtype=dtype, requires_grad=True)
    sl = torch.sqrt((1 - nl_t**2).clamp_min(1e-30))  # the harness's own sqrt must not be the NaN source
    sv = torch.sqrt((1 - nv_t**2).clamp_min(1e-30))
    lv = (sl * sv * math.cos(phi) + nl_t * nv_t).clamp(-1, 1)
    g = Angles.from_cosines(nl_t, nv_t, lv)
    out = mf.microfacet_specular(g, f0_t, rough.roughness_to_alpha(r_t), d, gname, fname)
    (out * g.nl.clamp_min(0)).sum().backward()
    return out, (nl_t.grad, nv_t.grad, r_t.grad, f0_t.grad), g


@given(nl=COS, nv=COS, phi=PHI, r=R, f0=F0V, fname=st.sampled_from(list(FRESNEL)))
def test_property_finite_and_precision(nl, nv, phi, r, f0, fname):
    """Finite value and gradient in float64 and float32; the float32 lobe matches the float64 lobe
    evaluated at the same (float32) cosines and parameters. The comparison is made on the lobe's own
    inputs because float32 cosines themselves cannot resolve the sharpest lobes: at r = R_MIN
    (α² ≈ 3e-5) near grazing mirror configurations, n·h from float32 cosines is off by more than the
    lobe width (measured 12 % at n·l = 0.06, n·v = 0.016)."""
    nl, nv, phi, r, f0 = map(_f32, (nl, nv, phi, r, f0))
    for d, gname in itertools.product(mf.DISTRIBUTIONS, mf.GEOMETRIES):
        o64, g64, _ = _eval(nl, nv, phi, r, f0, D64, d, gname, fname)
        o32, g32, ang32 = _eval(nl, nv, phi, r, f0, torch.float32, d, gname, fname)
        for o, grads in ((o64, g64), (o32, g32)):
            assert torch.isfinite(o).all() and (o >= 0).all(), (d, gname, fname, o)
            assert all(x is None or torch.isfinite(x).all() for x in grads), (d, gname, fname, grads)
        a64_ = Angles(*(getattr(ang32, k).detach().double() for k in ("nl", "nv", "nh", "lh", "lv")))
        ref = mf.microfacet_specular(a64_, torch.tensor([f0] * 3, dtype=D64),
                                     rough.roughness_to_alpha(torch.tensor([r], dtype=D64)), d, gname, fname)
        torch.testing.assert_close(o32.detach().double(), ref, rtol=1e-3, atol=1e-6)


def test_extreme_grid_all_combos():
    """Every combination over a grid of extreme cosines, roughnesses and f0, batched: finite values and
    gradients, and the float32 lobe ≈ the float64 lobe at the same cosines."""
    cs = [-1e-3, 0.0, 1e-7, 1e-3, 0.5, 1.0 - 1e-7, 1.0]
    nl, nv, phi, r, f0 = (x.reshape(-1, 1) for x in torch.meshgrid(
        torch.tensor(cs, dtype=D64), torch.tensor(cs, dtype=D64), torch.tensor([0.0, 2.0, math.pi], dtype=D64),
        torch.tensor([0.0, rough.R_MIN, 0.5, 1.0], dtype=D64), torch.tensor([0.0, 0.04, 1.0], dtype=D64),
        indexing="ij"))
    for d, gname, fname in COMBOS:
        outs = {}
        for dt in (D64, torch.float32):
            xs = [x.detach().to(dt).clone().requires_grad_(True) for x in (nl, nv, r, f0)]
            sl, sv = (torch.sqrt((1 - c**2).clamp_min(1e-30)) for c in xs[:2])
            lv = (sl * sv * torch.cos(phi.to(dt)) + xs[0] * xs[1]).clamp(-1, 1)
            g = Angles.from_cosines(xs[0], xs[1], lv)
            out = mf.microfacet_specular(g, xs[3], rough.roughness_to_alpha(xs[2]), d, gname, fname)
            (out * g.nl.clamp_min(0)).sum().backward()
            assert torch.isfinite(out).all() and (out >= 0).all(), (d, gname, fname)
            assert all(x.grad is None or torch.isfinite(x.grad).all() for x in xs), (d, gname, fname)
            outs[dt] = out.detach().double()
            if dt == torch.float32:  # float64 lobe at the float32 cosines (see the property test)
                g64 = Angles(*(getattr(g, k).detach().double() for k in ("nl", "nv", "nh", "lh", "lv")))
                ref = mf.microfacet_specular(g64, f0, rough.roughness_to_alpha(r), d, gname, fname)
                torch.testing.assert_close(outs[dt], ref, rtol=1e-3, atol=1e-6)


def test_l_equals_minus_v_and_back_facing_are_zero():
    nrm = torch.tensor([0.0, 0.0, 1.0])
    l = torch.tensor([0.6, 0.0, 0.8])
    for d, gname, fname in COMBOS:
        for lv in ((l, -l), (l, torch.tensor([0.0, 0.6, -0.8])), (torch.tensor([0.0, 0.0, -1.0]), l)):
            g = Angles.from_vectors(nrm, *lv)
            out = mf.microfacet_specular(g, torch.ones(3), torch.tensor([0.5]), d, gname, fname)
            assert (out == 0).all()
