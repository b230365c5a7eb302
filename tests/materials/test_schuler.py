"""Schüler's model: the four specular variants against the paper's expressions, units, the optimized
lobe against the DFG forms it approximates, two-hemisphere lighting, gradients, extremes."""

import functools
import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

import materials
from materials import roughness as rough
from materials import schuler as sc
from materials.environment import HemisphereLight, SHLight
from materials.fresnel import fresnel_from_f0, fresnel_schuler
from materials.geometry import Angles

D64 = torch.float64


def t64(*v):
    return torch.tensor(v, dtype=D64)


def config(nl, nv, phi):
    """Angles for n·l, n·v and azimuth difference phi (π = l and v on opposite sides of n)."""
    lv = math.sqrt(1 - nl * nl) * math.sqrt(1 - nv * nv) * math.cos(phi) + nl * nv
    return Angles.from_cosines(t64(nl), t64(nv), t64(lv)), lv


@functools.cache
def _gl(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return torch.tensor((x + 1) / 2, dtype=D64), torch.tensor(w / 2, dtype=D64)


def directional_albedo(brdf, theta_v, n_mu=192, n_phi=128):
    """∫ f_r (n·l) dω_l, Gauss-Legendre in cos θ_l × midpoint in φ (channel 0)."""
    mu, w = _gl(n_mu)
    mu, w = mu[:, None], w[:, None]
    phi = ((torch.arange(n_phi, dtype=D64) + 0.5) * (2 * math.pi / n_phi))[None, :]
    mv, sv = math.cos(theta_v), math.sin(theta_v)
    lv = torch.sqrt(1 - mu**2) * sv * torch.cos(phi) + mu * mv
    g = Angles.from_cosines(mu.expand_as(lv), torch.full_like(lv, mv), lv)
    return float((brdf(g)[..., 0] * mu * w).sum() * (2 * math.pi / n_phi))


# -- goldens ---------------------------------------------------------------------------------------------
def test_exponent_and_distribution():
    assert sc.schuler_exponent(t64(rough.shininess_to_roughness(t64(4096.0)).item())).item() == pytest.approx(4096)
    assert sc.schuler_exponent(t64(1.0)).item() == 1.0  # s = 0 < 1 → g = 0 → e = 1
    # the paper's g ∈ [0, 1] ("g in the range 0-1 (rough to smooth)"): e ≤ 4096 for point lights too, as for the
    # hemisphere term (which divides by 1 − g); r = R_MIN (s = 2^16) is Schüler's smoothest surface, not 2^16
    assert sc.schuler_exponent(t64(rough.R_MIN)).item() == pytest.approx(4096)
    assert sc.schuler_glossiness(t64(rough.R_MIN)).item() == 1.0
    from scipy.integrate import quad

    for e in (1.0, 10.0, 1000.0):
        def integrand(mu, e=e):
            return 2 * math.pi * mu * sc.schuler_distribution(t64(mu)[:, None], t64(e)[:, None]).item()

        split = 1 - 20 / e if e > 20 else 0.0
        total = sum(quad(integrand, a, b, limit=200)[0] for a, b in ((0, split), (split, 1)))
        assert total == pytest.approx((1 + e) / (2 + e), abs=1e-6)  # the paper's (1+e)/2 normalisation


def test_variants_at_normal_incidence():
    """l = v = n: D = (1+e)/(2π), F = K_s, G = 1, L·H = 1 → every Blinn-Phong variant is K_s (1+e)/(8π)."""
    g = Angles.from_cosines(t64(1.0), t64(1.0), t64(1.0))
    f0 = t64(0.04, 0.5, 1.0)
    r = t64(0.4)
    e = sc.schuler_exponent(r).item()
    for variant in ("optimized", "cook-torrance-simplified", "kelemen-szirmay-kalos"):
        torch.testing.assert_close(sc.schuler_specular(g, f0, r, variant), f0 * (1 + e) / (8 * math.pi))
    alpha = 0.16
    torch.testing.assert_close(sc.schuler_specular(g, f0, r, "cook-torrance-full"), f0 / (4 * math.pi * alpha**2))


def test_variants_hand_values():
    nl, nv = 0.6, 0.8
    g, lv = config(nl, nv, math.pi)
    lh = math.sqrt((1 + lv) / 2)
    nh = (nl + nv) / (2 * lh)
    f0, r = t64(0.04, 0.3, 1.0), t64(0.5)
    e = sc.schuler_exponent(r).item()
    assert e == pytest.approx(30.0)  # r = 0.5: s = 2/0.0625 − 2 = 30
    d = (1 + e) / (2 * math.pi) * nh**e
    fs = f0 + (torch.clamp(60 * f0, max=1) - f0) * (1 - lh) ** 4
    torch.testing.assert_close(sc.schuler_optimized(g, f0, t64(e)), f0 * (1 + e) / (8 * math.pi * lh**3) * nh**e)
    torch.testing.assert_close(sc.schuler_kelemen_szirmay_kalos(g, f0, t64(e)), d * fs / (4 * lh**2))
    gct = min(2 * nh * min(nv, nl) / lh, 1.0)
    torch.testing.assert_close(sc.schuler_cook_torrance_simplified(g, f0, t64(e)), d * fs * gct / (4 * nl * nv))
    a = 0.25
    beck = math.exp(-(1 - nh**2) / (nh**2 * a * a)) / (math.pi * a * a * nh**4)
    ref = beck * fresnel_from_f0(f0, t64(lh)) * gct / (4 * nl * nv)
    torch.testing.assert_close(sc.schuler_specular(g, f0, r, "cook-torrance-full"), ref)


def test_optimized_is_kelemen_with_fresnel_over_lh_replaced():
    """Optimized / KSK = K_s / (L·H · F(L·H)) exactly: the paper trades F/(L·H)² for K_s/(L·H)³."""
    f0 = t64(0.02, 0.04, 0.5)
    e = t64(64.0)
    for nl, nv, phi in ((0.9, 0.7, 2.0), (0.3, 0.5, math.pi), (0.2, 0.2, math.pi), (0.95, 0.95, 0.0)):
        g, _ = config(nl, nv, phi)
        ratio = sc.schuler_optimized(g, f0, e) / sc.schuler_kelemen_szirmay_kalos(g, f0, e)
        torch.testing.assert_close(ratio, f0 / (g.lh * fresnel_schuler(f0, g.lh)))


def test_optimized_vs_dfg_forms_directional_albedo():
    """How close the optimized lobe is to the DFG forms it approximates (directional albedo, r = 0.5):
    for a dielectric (K_s = 0.04) within 3 % of KSK at normal view and 11 % at 45°, but only about half
    of it at 75° (the Fresnel rise is given up); for K_s = 1 it *gains* energy (albedo > 1 beyond ~30°)."""
    r = t64(0.5)
    a = {}
    for f0v in (0.04, 1.0):
        f0 = torch.full((3,), f0v, dtype=D64)
        for variant in ("optimized", "kelemen-szirmay-kalos", "cook-torrance-simplified"):
            for th in (0, 45, 75):
                a[f0v, variant, th] = directional_albedo(lambda g, f0=f0, v=variant: sc.schuler_specular(g, f0, r, v),
                                                         math.radians(th))
    # measured (384×256 quadrature): opt 0.0372/0.0496/0.0957, KSK 0.0362/0.0449/0.1789, CTS 0.0387/0.0493/0.2025
    assert a[0.04, "optimized", 0] == pytest.approx(a[0.04, "kelemen-szirmay-kalos", 0], rel=0.03)
    assert a[0.04, "optimized", 45] == pytest.approx(a[0.04, "kelemen-szirmay-kalos", 45], rel=0.12)
    assert a[0.04, "optimized", 45] == pytest.approx(a[0.04, "cook-torrance-simplified", 45], rel=0.02)
    assert a[0.04, "optimized", 75] < 0.6 * a[0.04, "kelemen-szirmay-kalos", 75]
    # energy: K_s = 1, r = 0.5 → 0.931, 1.240, 2.393 at 0°, 45°, 75° (the DFG forms stay below 1)
    assert a[1.0, "optimized", 45] == pytest.approx(1.240, abs=0.01)
    assert a[1.0, "optimized", 75] == pytest.approx(2.393, abs=0.03)
    assert max(a[1.0, v, th] for v in ("kelemen-szirmay-kalos", "cook-torrance-simplified") for th in (0, 45, 75)) < 1


def test_model_and_errors():
    m = materials.get("schuler")
    assert m.param_names == ("albedo", "f0", "roughness") and m.spec("f0").linear
    assert not materials.get("schuler", variant="cook-torrance-full").spec("f0").linear
    with pytest.raises(ValueError, match="valid choices: optimized, cook-torrance-simplified"):
        materials.get("schuler", variant="blinn")
    with pytest.raises(TypeError, match="materials.Angles"):
        sc.schuler_optimized((0.5,), t64(0.04), t64(1.0)[:, None])
    g, _ = config(0.6, 0.7, 1.0)
    p = {"albedo": t64(0.2, 0.5, 0.7), "f0": t64(0.04, 0.04, 0.04), "roughness": t64(0.4)}
    for variant in sc.VARIANTS:
        mv = materials.get("schuler", variant=variant)
        spec = sc.schuler_specular(g, p["f0"], p["roughness"], variant)
        torch.testing.assert_close(mv.brdf(g, p), p["albedo"] / math.pi + spec)


# -- two-hemisphere lighting -----------------------------------------------------------------------------
def hemi(up=(1.0, 1.0, 1.0), lo=(0.2, 0.2, 0.2)):
    return HemisphereLight(t64(*up), t64(*lo), t64(0.0, 0.0, 1.0))


def test_hemisphere_uniform_environment_is_mirror_of_reflectance_f():
    """E_upper = E_lower = E is a uniform radiance E/π: diffuse ρ/π E (as Lambert), specular F(g n·v) E/π."""
    env = hemi((2.0, 2.0, 2.0), (2.0, 2.0, 2.0))
    n = torch.nn.functional.normalize(t64(0.3, -0.2, 0.9), dim=0)[None]
    v = torch.nn.functional.normalize(t64(-0.1, 0.4, 0.8), dim=0)[None]
    p = {"albedo": t64(0.5, 0.3, 0.1), "f0": t64(0.04, 0.04, 0.04), "roughness": t64(0.5)}
    glos = rough.roughness_to_glossiness(p["roughness"]).item()
    nv = float((n * v).sum())
    out = materials.get("schuler", hemisphere_fresnel="printed").environment(env, n, v, p)
    spec = fresnel_schuler(p["f0"], t64(glos * nv)[:, None]) * 2.0 / math.pi
    torch.testing.assert_close(out, p["albedo"] * 2.0 / math.pi + spec)
    # default reading: the rise is scaled by g, F = K_s + (min(60 K_s, 1) − K_s) g (1 − n·v)⁴
    out = materials.get("schuler").environment(env, n, v, p)
    f_scaled = 0.04 + (min(60 * 0.04, 1.0) - 0.04) * glos * (1 - nv) ** 4
    torch.testing.assert_close(out, (p["albedo"] * 2.0 / math.pi + f_scaled * 2.0 / math.pi).expand_as(out))
    lam = materials.get("lambert").environment(env, n, v, {"albedo": p["albedo"]})
    torch.testing.assert_close(sc.schuler_hemisphere_diffuse(env, n, v, p["albedo"]), lam)


def test_point_lights_and_hemispheres_share_one_glossiness_range():
    # every roughness: the exponent of the point-light lobe is 2^(12 g) for the g the hemisphere term uses
    r = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)[:, None]
    g = sc.schuler_glossiness(r)
    assert g.min().item() == 0.0 and g.max().item() == 1.0
    torch.testing.assert_close(sc.schuler_exponent(r), torch.exp2(12 * g))
    # below r = (2/4098)^(1/4) the lobe no longer sharpens: same f_r at R_MIN and at the paper's e = 4096
    gg = Angles.from_cosines(t64(0.8), t64(0.8), t64(2 * 0.64 - 1))
    f0 = t64(0.04, 0.04, 0.04)
    r4096 = rough.shininess_to_roughness(t64(4096.0))
    torch.testing.assert_close(sc.schuler_specular(gg, f0, t64(rough.R_MIN)), sc.schuler_specular(gg, f0, r4096))


def test_hemisphere_specular_weight():
    env = hemi((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    f0 = t64(1.0, 1.0, 1.0)  # F ≡ 1 → the output is the interpolated irradiance / π
    sharp, rough_r = t64(rough.R_MIN), t64(1.0)  # g = 1 (clamped from 4/3) and g = 0
    a = math.radians(30)
    n_side = t64(1.0, 0.0, 0.0)[None]
    v_side = t64(math.cos(a), 0.0, math.sin(a))[None]  # R = (cos a, 0, −sin a): points down
    n_up = t64(0.0, 0.0, 1.0)[None]
    v_up = t64(math.sin(a), 0.0, math.cos(a))[None]  # R·z = cos a > 0
    n_45 = torch.nn.functional.normalize(t64(1.0, 0.0, 1.0), dim=0)[None]
    v_45 = t64(0.0, 0.0, 1.0)[None]  # R = 2 (n·v) n − v = (1, 0, 0): horizontal
    spec = sc.schuler_hemisphere_specular
    assert spec(env, n_up, v_up, f0, sharp)[0, 0].item() == pytest.approx(1 / math.pi)  # sky
    assert spec(env, n_side, v_side, f0, sharp)[0, 0].item() == pytest.approx(0.0, abs=1e-12)  # ground
    assert spec(env, n_45, v_45, f0, sharp)[0, 0].item() == pytest.approx(0.5 / math.pi)  # horizon: mean
    # g = 0: t = (1 + R·z)/2; printed F(g N·V) = min(60 K_s, 1) for every view, the scaled default F = K_s
    rz = -math.sin(a)
    assert spec(env, n_side, v_side, f0, rough_r)[0, 0].item() == pytest.approx((1 + rz) / 2 / math.pi)
    ks = t64(0.04, 0.01, 0.0)
    f_low = spec(env, n_up, v_up, ks, rough_r, fresnel="printed")[0] * math.pi / ((1 + math.cos(a)) / 2)
    torch.testing.assert_close(f_low, t64(1.0, 0.6, 0.0))
    f_low = spec(env, n_up, v_up, ks, rough_r)[0] * math.pi / ((1 + math.cos(a)) / 2)
    torch.testing.assert_close(f_low, ks)
    with pytest.raises(ValueError, match="valid: scaled, printed"):
        spec(env, n_up, v_up, ks, rough_r, fresnel="nope")
    # never negative, whatever the irradiances (the literal lerp(…, clamp(…, −1, 1)) would be)
    env2 = hemi((5.0, 5.0, 5.0), (1.0, 1.0, 1.0))
    assert (spec(env2, n_side, v_side, f0, sharp) >= 0).all()
    # back-facing view → 0
    assert (spec(env, n_up, -v_up, f0, sharp) == 0).all()


def test_environment_rejects_other_lights():
    with pytest.raises(NotImplementedError, match="defines no response"):
        m = materials.get("schuler")
        m.environment(SHLight(torch.zeros(9, 3)), torch.tensor([[0.0, 0, 1]]), torch.tensor([[0.0, 0, 1]]),
                      m.defaults())


# -- gradients -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", sc.VARIANTS)
def test_gradcheck(variant):
    nl = t64(0.3, 0.7, 0.9)[:, None].requires_grad_(True)
    nv = t64(0.8, 0.4, 0.95)[:, None].requires_grad_(True)
    lv = t64(-0.2, 0.1, 0.8)[:, None].requires_grad_(True)
    f0 = t64(0.005, 0.3, 0.9).requires_grad_(True)
    r = t64(0.55).requires_grad_(True)

    def fn(nl, nv, lv, f0, r):
        return sc.schuler_specular(Angles.from_cosines(nl, nv, lv), f0, r, variant)

    assert torch.autograd.gradcheck(fn, (nl, nv, lv, f0, r))


def test_gradcheck_environment():
    env = hemi((1.0, 0.8, 0.6), (0.1, 0.2, 0.3))
    n = torch.nn.functional.normalize(t64(0.3, -0.2, 0.9), dim=0)[None].expand(3, 3)
    v = torch.nn.functional.normalize(torch.tensor([[0.5, 0.1, 0.8], [-0.6, 0.0, 0.3], [0.0, 0.9, 0.2]],
                                                   dtype=D64), dim=-1)
    albedo = t64(0.5, 0.3, 0.1).requires_grad_(True)
    f0 = t64(0.004, 0.04, 0.6).requires_grad_(True)
    r = t64(0.3, 0.6, 0.8)[:, None].requires_grad_(True)
    m = materials.get("schuler")
    assert torch.autograd.gradcheck(lambda a, f, rr: m.environment(env, n, v, {"albedo": a, "f0": f, "roughness": rr}),
                                    (albedo, f0, r))


# -- extremes --------------------------------------------------------------------------------------------
COS = st.one_of(st.sampled_from([0.0, 1e-7, -1e-4, 1.0, 1.0 - 1e-7]), st.floats(-0.2, 1.0))
PHI = st.one_of(st.sampled_from([0.0, math.pi]), st.floats(0.0, math.pi))
R = st.one_of(st.sampled_from([0.0, 1.0, rough.R_MIN]), st.floats(0.0, 1.0))
F0V = st.one_of(st.sampled_from([0.0, 1.0, 1.0 / 60]), st.floats(0.0, 1.0))


def _eval(nl, nv, phi, r, f0, dtype):
    nl_t, nv_t, r_t = (torch.tensor([x], dtype=dtype, requires_grad=True) for x in (nl, nv, r))
    f0_t = torch.tensor([f0] * 3, dtype=dtype, requires_grad=True)
    s = lambda c: torch.sqrt((1 - c**2).clamp_min(1e-30))  # noqa: E731
    lv = (s(nl_t) * s(nv_t) * math.cos(phi) + nl_t * nv_t).clamp(-1, 1)
    g = Angles.from_cosines(nl_t, nv_t, lv)
    outs = []
    for variant in sc.VARIANTS:
        out = sc.schuler_specular(g, f0_t, r_t, variant)
        (out * g.nl.clamp_min(0)).sum().backward(retain_graph=True)
        outs.append(out.detach().double())
    return outs, [x.grad for x in (nl_t, nv_t, r_t, f0_t)], g


@given(nl=COS, nv=COS, phi=PHI, r=R, f0=F0V)
def test_property_finite_and_precision(nl, nv, phi, r, f0):
    """Finite values and gradients; float32 lobes ≈ float64 lobes at the same float32 cosines
    (see tests/materials/test_microfacet.py::test_property_finite_and_precision for why)."""
    nl, nv, phi, r, f0 = (float(np.float32(x)) for x in (nl, nv, phi, r, f0))
    o64, g64, _ = _eval(nl, nv, phi, r, f0, D64)
    o32, g32, ang = _eval(nl, nv, phi, r, f0, torch.float32)
    for outs, grads in ((o64, g64), (o32, g32)):
        assert all(torch.isfinite(o).all() and (o >= 0).all() for o in outs), outs
        assert all(x is None or torch.isfinite(x).all() for x in grads), grads
    ang64 = Angles(*(getattr(ang, k).detach().double() for k in ("nl", "nv", "nh", "lh", "lv")))
    for variant, o in zip(sc.VARIANTS, o32, strict=True):
        ref = sc.schuler_specular(ang64, torch.tensor([f0] * 3, dtype=D64), torch.tensor([r], dtype=D64), variant)
        torch.testing.assert_close(o, ref, rtol=1e-3, atol=1e-6)


@given(nz=st.floats(-1.0, 1.0), vx=st.floats(-1.0, 1.0), r=R, f0=F0V)
def test_property_environment_finite(nz, vx, r, f0):
    env = hemi((1.0, 0.5, 0.2), (0.3, 0.3, 0.3))
    n = torch.nn.functional.normalize(t64(math.sqrt(max(0.0, 1 - nz * nz)) + 1e-9, 0.0, nz), dim=0)[None]
    v = torch.nn.functional.normalize(t64(vx, 0.3, 0.5), dim=0)[None]
    rr = t64(r)[:, None].requires_grad_(True)
    ff = t64(f0, f0, f0).requires_grad_(True)
    out = materials.get("schuler").environment(env, n, v, {"albedo": t64(0.5, 0.5, 0.5), "f0": ff, "roughness": rr})
    out.sum().backward()
    assert torch.isfinite(out).all() and (out >= 0).all()
    assert torch.isfinite(rr.grad).all() and torch.isfinite(ff.grad).all()
