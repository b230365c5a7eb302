"""Nielsen et al.'s Phong variants (eq 1-3): goldens, limits of the mixture, reciprocity, energy,
gradients and extreme inputs."""

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

import materials
from materials.geometry import Angles
from materials.nielsen import mixture, mixture_base, modified_blinn_phong, modified_phong
from materials.roughness import R_MIN

D64 = torch.float64
PI = math.pi


def fresnel_ref(eta: float, c: float) -> float:
    """Unpolarised dielectric Fresnel, written independently (Hecht): r_s, r_p with Snell."""
    st2 = (1 - c * c) / eta**2
    ct = math.sqrt(1 - st2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs * rs + rp * rp)


def _vec(cos, phi=0.0):
    s = math.sqrt(max(0.0, 1.0 - cos * cos))
    return torch.tensor([s * math.cos(phi), s * math.sin(phi), cos], dtype=D64)


N = _vec(1.0)
R30 = torch.tensor([0.5], dtype=D64)  # s = 2/r⁴ − 2 = 2·16 − 2 = 30


def _p(model, **kw):
    p = {k: v.to(D64) for k, v in model.defaults().items()}
    p.update({k: torch.as_tensor(v, dtype=D64).reshape(-1) for k, v in kw.items()})
    return p


def test_shininess_from_roughness_is_30():
    from materials.roughness import roughness_to_shininess

    assert roughness_to_shininess(R30).item() == pytest.approx(30.0, rel=1e-12)


def test_golden_phong_mirror_configuration():
    # l at 60°, v its mirror (φ = π): r·v = 2·(1/2)(1/2) − l·v, l·v = cos 120° = −1/2 → r·v = 1;
    # h = n, l·h = 1/2. f = ρ_d/π + ρ_s R_F(1/2, 1.5) (s + 2)/(2π) with s = 30.
    m = materials.get("nielsen-phong")
    l, v = _vec(0.5), _vec(0.5, math.pi)
    f = m(N, l, v, **{"albedo": torch.tensor([0.2], dtype=D64), "specular": torch.tensor([0.7], dtype=D64),
                      "roughness": R30, "ior": torch.tensor([1.5], dtype=D64)})
    expect = 0.2 / PI + 0.7 * fresnel_ref(1.5, 0.5) * 32 / (2 * PI)
    assert f.tolist() == pytest.approx([expect], rel=1e-10)


def test_golden_off_specular_all_three():
    # l at 60°, v = n: r·v = 2 (1/2)(1) − 1/2 = 1/2; n·h = l·h = cos 30°.
    l, v = _vec(0.5), N
    c30 = math.cos(math.radians(30))
    rf = fresnel_ref(1.5, c30)
    kw = {"albedo": torch.tensor([0.0], dtype=D64), "specular": torch.tensor([0.5], dtype=D64),
          "roughness": R30, "ior": torch.tensor([1.5], dtype=D64)}
    phong = materials.get("nielsen-phong")(N, l, v, **kw)
    bp = materials.get("nielsen-blinn-phong")(N, l, v, **kw)
    mixm = materials.get("nielsen-mixture")(N, l, v, **kw, mix=torch.tensor([0.25], dtype=D64))
    assert phong[0].item() == pytest.approx(0.5 * rf * 32 / (2 * PI) * 0.5**30, rel=1e-10)
    assert bp[0].item() == pytest.approx(0.5 * rf * 38 / (8 * PI) * c30**30, rel=1e-10)
    base = 0.75 * 0.5 + 0.25 * c30**4
    assert mixm[0].item() == pytest.approx(0.5 * rf * base**30, rel=1e-10)


def test_fresnel_option_removes_ior():
    on, off = materials.get("nielsen-blinn-phong"), materials.get("nielsen-blinn-phong", fresnel=False)
    assert "ior" in on.param_names and "ior" not in off.param_names
    l, v = _vec(0.8), _vec(0.6, 2.0)
    g = Angles.from_vectors(N, l, v)
    p = _p(on, albedo=0.0, specular=1.0, roughness=0.4)
    rf = fresnel_ref(1.5, g.lh.item())
    assert on.brdf(g, p)[0].item() == pytest.approx(rf * off.brdf(g, p)[0].item(), rel=1e-12)
    with pytest.raises(TypeError, match="fresnel"):
        materials.get("nielsen-phong", fresnel="yes")


def _random(n, seed):
    g = torch.Generator().manual_seed(seed)
    nl = 0.02 + 0.98 * torch.rand(n, generator=g, dtype=D64)
    nv = 0.02 + 0.98 * torch.rand(n, generator=g, dtype=D64)
    phi = 2 * PI * torch.rand(n, generator=g, dtype=D64)
    lv = nl * nv + torch.sqrt(1 - nl**2) * torch.sqrt(1 - nv**2) * torch.cos(phi)
    return nl, nv, lv


def test_mixture_limits():
    nl, nv, lv = _random(300, 4)
    g = Angles.from_cosines(nl, nv, lv)
    s = torch.full((300, 1), 20.0, dtype=D64)
    ks = torch.full((300, 3), 0.3, dtype=D64)
    one = torch.ones_like(ks)
    # α = 0: k_s (r·v)^s, i.e. eq 1 with its normalisation divided out
    a0 = mixture(g, ks, s, torch.zeros(300, 1, dtype=D64))
    assert torch.allclose(a0, modified_phong(g, ks, s) * 2 * PI / (s + 2), rtol=1e-12, atol=1e-300)
    # α = 1: k_s ((n·h)^4)^s = k_s (n·h)^(4s): eq 2's lobe at 4s without its normalisation, not eq 2 at s
    a1 = mixture(g, ks, s, torch.ones(300, 1, dtype=D64))
    assert torch.allclose(a1, modified_blinn_phong(g, one, 4 * s) * 8 * PI / (4 * s + 8) * ks, rtol=1e-10, atol=0)
    assert not torch.allclose(a1, modified_blinn_phong(g, ks, s) * 8 * PI / (s + 8), rtol=1e-3)


def test_negative_base_is_clamped_with_finite_gradient():
    # l = v at 60° off the normal, same side: r·v = 2·(1/4) − 1 = −1/2 < 0 → Phong lobe 0.
    g = Angles.from_vectors(N, _vec(0.5), _vec(0.5))
    assert g.rv.item() == pytest.approx(-0.5)
    s = torch.tensor([3.5], dtype=D64, requires_grad=True)
    mix = torch.tensor([0.0], dtype=D64, requires_grad=True)
    out = modified_phong(g, torch.ones(3, dtype=D64), s) + mixture(g, torch.ones(3, dtype=D64), s, mix)
    assert (out == 0).all()
    out.sum().backward()
    assert torch.isfinite(s.grad).all() and torch.isfinite(mix.grad).all()
    assert mixture_base(g, mix).item() == pytest.approx(-0.5)


def _albedo_phong_like(lobe, nv, nth=800, nphi=256):
    """∫ lobe(g) n·l dω_l over the light hemisphere (midpoint in μ = n·l, φ), float64."""
    mu = (torch.arange(nth, dtype=D64) + 0.5) / nth
    phi = (torch.arange(nphi, dtype=D64) + 0.5) / nphi * 2 * PI
    nl = mu[:, None].expand(nth, nphi)
    lv = nl * nv + torch.sqrt(1 - nl**2) * math.sqrt(1 - nv**2) * torch.cos(phi)[None, :]
    g = Angles.from_cosines(nl, torch.full_like(nl, nv), lv)
    return (lobe(g) * g.nl).mean().item() * 2 * PI


@pytest.mark.parametrize("s", [1.0, 10.0, 100.0])
def test_energy_phong_and_blinn_phong(s):
    """ρ_s = 1, no Fresnel. Phong eq 1: albedo 1 exactly at v = n ((s+2)/(2π) · 2π/(s+2)), below 1
    elsewhere. Blinn-Phong eq 2 GAINS energy at v = n: (s+8)(s + 2^(−s/2))/((s+2)(s+4)) = 1.024
    (s = 1), 1.075 (s = 10), 1.018 (s = 100); peak 1.0752 near s = 9."""
    one = torch.ones(1, dtype=D64)
    st_ = torch.tensor([s], dtype=D64)
    ph = [_albedo_phong_like(lambda g: modified_phong(g, one, st_), nv) for nv in (1.0, 0.5, 0.1)]
    assert ph[0] == pytest.approx(1.0, rel=2e-3)
    assert max(ph) <= 1.0 + 2e-3
    bp = _albedo_phong_like(lambda g: modified_blinn_phong(g, one, st_), 1.0)
    closed = (s + 8) * (s + 2 ** (-s / 2)) / ((s + 2) * (s + 4))
    assert bp == pytest.approx(closed, rel=2e-3)
    assert closed > 1.0  # energy gained at normal incidence for every s tested


@pytest.mark.parametrize("name", ["nielsen-phong", "nielsen-blinn-phong", "nielsen-mixture"])
@pytest.mark.parametrize("fresnel", [True, False])
def test_gradcheck(name, fresnel):
    nl, nv, lv = _random(5, 11)
    # keep the Phong bases positive so that the lobe is smooth at the test points
    g = Angles.from_cosines(nl, nv, lv)
    m = materials.get(name, fresnel=fresnel)
    gen = torch.Generator().manual_seed(13)
    keys = list(m.param_names)
    lo_hi = {"ior": (1.1, 2.5), "roughness": (0.3, 0.9)}
    vals = []
    for sp in m.params:
        lo, hi = lo_hi.get(sp.name, (0.1, 0.9))
        vals.append((lo + (hi - lo) * torch.rand(5, sp.channels, dtype=D64, generator=gen)).requires_grad_())
    assert torch.autograd.gradcheck(lambda *xs: m.brdf(g, dict(zip(keys, xs, strict=True))), vals)


_COS = st.one_of(st.sampled_from([0.0, 1e-7, -1e-7, -1e-3, 1e-3, 0.5, 1.0]), st.floats(-0.2, 1.0))
_R = st.one_of(st.sampled_from([0.0, R_MIN, 0.5, 1.0]), st.floats(0.0, 1.0))


@given(nl=_COS, nv=_COS, phi=st.floats(0, 2 * PI), anti=st.booleans(), r=_R,
       eta=st.one_of(st.sampled_from([1.0, 3.0]), st.floats(1.0, 3.0)), mix=st.floats(0.0, 1.0),
       name=st.sampled_from(["nielsen-phong", "nielsen-blinn-phong", "nielsen-mixture"]))
def test_extremes_finite_and_float32_matches_float64(nl, nv, phi, anti, r, eta, mix, name, finite_and_float32_matches):
    m = materials.get(name)
    l = _vec(nl).clone().requires_grad_()
    v = (-l.detach() if anti else _vec(nv, phi)).clone().requires_grad_()
    p = {k: x.to(D64) for k, x in m.defaults().items()}
    p.update(roughness=torch.tensor([r], dtype=D64), ior=torch.tensor([eta], dtype=D64))
    if "mix" in p:
        p["mix"] = torch.tensor([mix], dtype=D64)
    p = {k: x.clone().requires_grad_() for k, x in p.items()}
    g = Angles.from_vectors(N, l, v)
    finite_and_float32_matches(m.brdf, m.brdf, g, p, (l, v, *p.values()), rtol=2e-4)


def test_environment_constant_sky():
    coeffs = torch.zeros(9, 3)
    coeffs[0] = 2 * math.sqrt(PI)  # uniform radiance 1
    env = materials.SHLight(coeffs)
    m = materials.get("nielsen-phong")
    n = torch.tensor([[0.0, 0.0, 1.0]])
    v = _vec(0.8).float().unsqueeze(0)
    p = {"albedo": torch.tensor([[0.5, 0.5, 0.5]]), "specular": torch.tensor([[0.3, 0.3, 0.3]]),
         "roughness": torch.tensor([[0.5]]), "ior": torch.tensor([[1.5]])}
    out = m.environment(env, n, v, p)
    assert torch.allclose(out, torch.full((1, 3), 0.5 + 0.3 * fresnel_ref(1.5, 0.8)), atol=1e-5)


@pytest.mark.parametrize("name", ["nielsen-phong", "nielsen-blinn-phong", "nielsen-mixture"])
def test_specular_is_bounded_by_the_sharpest_normalised_lobe(name):
    # the bound: k_s = ρ_s (s + 2)/(2π) at ρ_s = 1 and s = S_MAX (Nielsen eq 1's normalisation, absorbed by eq 3's k_s)
    from materials.params import SPECULAR_MAX
    from materials.roughness import S_MAX
    assert SPECULAR_MAX == pytest.approx((S_MAX + 2) / (2 * math.pi))
    m = materials.get(name)
    assert m.spec("specular").high == SPECULAR_MAX
    n = torch.tensor([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="'specular' must lie in"):
        m(n, n, n, specular=torch.full((3,), 3e38))  # was accepted, and overflowed to inf in float32
    # at the bound, float32 stays finite in value and gradient, mirror-like lobe included
    g = materials.Angles.from_cosines(torch.tensor([[1.0], [0.3]]), torch.tensor([[1.0], [0.3]]),
                                      torch.tensor([[1.0], [2 * 0.09 - 1]]))
    p = {s.name: s.full((2,)) for s in m.params}
    p["specular"] = torch.full((2, 3), SPECULAR_MAX, requires_grad=True)
    p["roughness"] = torch.zeros(2, 1)
    f = m.brdf(g, p)
    f.sum().backward()
    assert torch.isfinite(f).all() and f.max() < 2e8 and torch.isfinite(p["specular"].grad).all()
