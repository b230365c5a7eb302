"""Gotanda 2014 microfacet diffuse: Lambertian facets with Fresnel, GGX D and Smith G.

Gotanda, "Designing Reflectance Models for New Consoles", SIGGRAPH 2014 course, section 3.

Numerical reference (eq 4)::

    f_r(n, l, e) = 1/(π (n·l)(n·e)) ∫_Ω (m·l)(m·e) D(m) F_diff(m, l, e) G(m, l, e) dω_m

with (footnote 3) D = GGX, G = Smith height-correlated (Heitz 2014), F = Schlick. Our reading of
the facet term: each facet is Lambertian *with diffuse Fresnel*, i.e. eq 6 written for the facet
normal m ("the Fresnel component is added to the geometry surface instead of the microfacet.
Ideally, it should be added to each microfacet")::

    F_diff(m, l, e) = 21/20 (1 − f0)(1 − (1 − m·l)⁵)(1 − (1 − m·e)⁵)
                    = 21/(20 (1 − f0)) (1 − F_Schlick(m·l))(1 − F_Schlick(m·e))

Evidence: (a) at α → 0 eq 4 then reduces to eq 6/π ("When roughness σ is zero, the model becomes
Lambertian with the Fresnel effect"); (b) the fit, eq 8, carries exactly the prefactor
21/(20π)(1 − f0) of this F_diff, and f0 then factors out of the integral (the paper's footnote 4:
"even though f0 can be factored out"). G(m, l, e) = χ⁺(m·l) χ⁺(m·e) G2(l, e): the Smith G2 depends on
m only through the facet's visibility, which the clamped (m·l)⁺(m·e)⁺ already carries. Albedo ρ
multiplies the whole (the facets' reflectance).

Fit (eq 8)::

    L_r = 21/(20π) (1 − f0) (F_r(e, σ) L_m(l, σ) + V_d(e, l, σ) B_p(e, l)) E0 ρ

whose OCR is damaged and whose terms circulate in two incompatible forms; the reading we use and
the measurements that chose it are in :func:`microfacet_diffuse_fitted` and docs/models-diffuse.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from .geometry import Angles, as_param, check_angles
from .model import Model, register
from .params import ALBEDO, F0, ROUGHNESS
from .roughness import R_MIN, roughness_to_alpha

INV_PI = 1.0 / math.pi
#: Default quadrature: Gauss-Legendre nodes in ψ (the GGX-warped polar angle) × midpoint nodes in φ.
DEFAULT_NODES = (48, 96)
#: Elements (samples × nodes) evaluated at once; bounds memory to a few hundred MB in float64.
CHUNK_ELEMENTS = 1 << 21
#: Floor of the denominator n·e a_l + n·l a_e of G2/(n·l n·e) in the BRDF (not in cosine form).
VIS_FLOOR = 1e-9


_check_angles = check_angles
_t = as_param


def _sqrt0(x: Tensor) -> Tensor:
    """√max(x, 0) with a finite (zero) gradient where x ≤ 1e-30."""
    ok = x > 1e-30
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x))


@lru_cache(maxsize=8)
def _nodes_np(n_psi: int, n_phi: int):
    x, w = np.polynomial.legendre.leggauss(n_psi)
    psi = 0.25 * math.pi * (x + 1.0)  # [0, π/2]
    wpsi = 0.25 * math.pi * w
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    return psi, wpsi, phi


def ggx_quadrature(alpha: Tensor, nodes: tuple[int, int] = DEFAULT_NODES):
    """Facet normals and weights for ∫ h(m) D_GGX(m) dω_m ≈ Σ_k w_k h(m_k).

    The change of variables tan θ_m = α tan ψ is the GGX sampling map u = sin²ψ (u uniform ↔ m
    distributed as D(m) cos θ_m), so that D(m) dω_m = 2 sin ψ √(cos²ψ + α² sin²ψ) dψ dφ/(2π): a
    smooth, bounded weight for every α in (0, 1] — no peak for the nodes to miss, even at
    α = 0.0055. ψ: Gauss-Legendre on [0, π/2]; φ: midpoint rule on [0, 2π) (periodic).

    Args:
        alpha: GGX α ``[B, 1]``.
        nodes: (n_psi, n_phi).

    Returns:
        m ``[B, K, 3]`` (unit, z = n) and weights ``[B, K]``, K = n_psi·n_phi;
        Σ_k w_k ≈ ∫ D dω_m (= 2 at α = 1).
    """
    n_psi, n_phi = int(nodes[0]), int(nodes[1])
    psi_np, wpsi_np, phi_np = _nodes_np(n_psi, n_phi)
    dt, dev = alpha.dtype, alpha.device
    psi = torch.as_tensor(psi_np, dtype=dt, device=dev)
    wpsi = torch.as_tensor(wpsi_np, dtype=dt, device=dev)
    phi = torch.as_tensor(phi_np, dtype=dt, device=dev)
    a = alpha.reshape(-1, 1)  # [B, 1]
    c, s = torch.cos(psi), torch.sin(psi)  # [P]
    q = torch.sqrt(c.square() + a.square() * s.square())  # [B, P]
    cos_m, sin_m = c / q, a * s / q
    w = (wpsi * 2.0 * s * q / n_phi)[:, :, None].expand(-1, -1, n_phi)  # [B, P, F]
    m = torch.stack(
        [sin_m[:, :, None] * torch.cos(phi), sin_m[:, :, None] * torch.sin(phi),
         cos_m[:, :, None].expand(-1, -1, n_phi)], dim=-1,
    )  # [B, P, F, 3]
    b = a.shape[0]
    return m.reshape(b, n_psi * n_phi, 3), w.reshape(b, n_psi * n_phi)


def _local_frame(nl: Tensor, nv: Tensor, lv: Tensor):
    """Vectors realising the cosines: n = z, e = (sin θ_e, 0, n·e), l = (l_x, l_y ≥ 0, n·l)."""
    nl = nl.clamp(0.0, 1.0)
    nv = nv.clamp(0.0, 1.0)
    se = _sqrt0(1.0 - nv.square())
    sl2 = (1.0 - nl.square()).clamp_min(0.0)
    ok = se > 1e-9
    lx = torch.where(ok, (lv - nl * nv) / torch.where(ok, se, torch.ones_like(se)), _sqrt0(sl2))
    lx = torch.maximum(torch.minimum(lx, _sqrt0(sl2)), -_sqrt0(sl2))
    ly = _sqrt0(sl2 - lx.square())
    e = torch.cat([se, torch.zeros_like(se), nv], -1)
    l = torch.cat([lx, ly, nl], -1)
    return l, e


def facet_integral(nl: Tensor, nv: Tensor, lv: Tensor, alpha: Tensor, nodes: tuple[int, int] = DEFAULT_NODES) -> Tensor:
    """I(l, e; α) = ∫ (m·l)⁺ (m·e)⁺ (1 − (1 − m·l)⁵)(1 − (1 − m·e)⁵) D_GGX(m) dω_m by quadrature.

    The f0-free part of eq 4's integral (Schlick's 1 − F = (1 − f0)(1 − (1 − c)⁵) factors f0 out).
    Inputs broadcast, each ``[..., 1]``; returns ``[..., 1]``. Vectorised over samples and nodes,
    evaluated in chunks of :data:`CHUNK_ELEMENTS` elements to bound memory. Differentiable.
    """
    nl, nv, lv, alpha = torch.broadcast_tensors(nl, nv, lv, alpha)
    shape = nl.shape
    nl, nv, lv, alpha = (x.reshape(-1, 1) for x in (nl, nv, lv, alpha))
    k = int(nodes[0]) * int(nodes[1])
    step = max(1, CHUNK_ELEMENTS // k)
    out = []
    for i in range(0, nl.shape[0], step):  # chunks of samples, not a loop over samples
        sl = slice(i, i + step)
        l, e = _local_frame(nl[sl], nv[sl], lv[sl])  # [b, 3]
        m, w = ggx_quadrature(alpha[sl], nodes)  # [b, K, 3], [b, K]
        ml = (m * l[:, None, :]).sum(-1).clamp(0.0, 1.0)
        me = (m * e[:, None, :]).sum(-1).clamp(0.0, 1.0)
        h = ml * me * (1.0 - (1.0 - ml).pow(5)) * (1.0 - (1.0 - me).pow(5))
        out.append((w * h).sum(-1, keepdim=True))
    return torch.cat(out, 0).reshape(shape) if out else torch.zeros(shape, dtype=nl.dtype, device=nl.device)


def _g2_over_cos(nl: Tensor, nv: Tensor, alpha: Tensor, cosine: bool) -> Tensor:
    """G2(l, e)/(n·l n·e) = 2/(n·e a_l + n·l a_e), a_x = √(α² + (1 − α²) x²) (height-correlated
    Smith GGX, Heitz 2014 eq 99, rearranged). With ``cosine`` it returns G2/n·e = 2 n·l/(...)."""
    a2 = alpha.square()
    l = nl.clamp(0.0, 1.0)
    v = nv.clamp(0.0, 1.0)
    al = torch.sqrt(a2 + (1.0 - a2) * l.square())
    av = torch.sqrt(a2 + (1.0 - a2) * v.square())
    den = v * al + l * av
    if cosine:
        return 2.0 * l / den.clamp_min(1e-12)
    return 2.0 / den.clamp_min(VIS_FLOOR)


def microfacet_diffuse_numerical(g: Angles, albedo: Tensor, alpha: Tensor, f0: Tensor,
                                 nodes: tuple[int, int] = DEFAULT_NODES, cosine: bool = False) -> Tensor:
    """Gotanda 2014 eq 4 by numerical integration: the slow reference of the microfacet diffuse.

    f_r = ρ/π · 21/20 (1 − f0) · G2(l, e)/((n·l)(n·e)) · I(l, e; α), with I from
    :func:`facet_integral` (GGX-warped tensor quadrature, ``nodes`` = (n_ψ, n_φ), default 48 × 96 =
    4608 nodes). Convergence (docs/models-diffuse.md): max relative error vs 192 × 384 nodes
    2.0e-3 (mean 4e-6) over a 1470-point grid; the integrand has kinks where m·l = 0 or m·e = 0, so the error falls
    like N^-2, not exponentially.

    Args:
        g: cosines ``[..., 1]`` (n·l, n·v, l·v used).
        albedo: ρ ``[..., C]`` in [0, 1]; f0: ``[..., C]`` in [0, 1].
        alpha: GGX α ``[..., 1]`` in (0, 1] (materials.roughness.roughness_to_alpha).
        cosine: return f_r · n·l.

    Returns:
        f_r in 1/sr ``[..., C]`` (or f_r·n·l); 0 unless n·l > 0 and n·v > 0. Reciprocal.
        Gradients flow to every input (except, at exactly in-plane configurations, the path
        through the azimuth of l, which the frame construction cuts to stay finite).
    """
    fn = "microfacet_diffuse_numerical"
    _check_angles(g, fn)
    albedo = _t(albedo, g.nl, "albedo", fn)
    f0 = _t(f0, g.nl, "f0", fn)
    alpha = _t(alpha, g.nl, "alpha", fn)
    if len(nodes) != 2 or min(nodes) < 2:
        raise ValueError(f"{fn}: nodes must be (n_psi, n_phi) with each ≥ 2, got {nodes}")
    integral = facet_integral(g.nl, g.nv, g.lv, alpha, nodes)
    vis = _g2_over_cos(g.nl, g.nv, alpha, cosine)
    out = albedo * (1.0 - f0) * (1.05 * INV_PI) * vis * integral
    out = torch.broadcast_tensors(out, albedo)[0]
    return torch.where(g.front, out, torch.zeros_like(out))


# -- the fit, eq 8 ---------------------------------------------------------------------------------
def _one_minus_pow_over_x(x: Tensor, p: Tensor) -> Tensor:
    """(1 − (1 − x)^p)/x for x ∈ [0, 1], p > 0, finite with finite gradients (→ p at x = 0)."""
    small = x < 1e-4
    xs = torch.where(small, torch.ones_like(x), x)
    base = (1.0 - xs).clamp_min(0.0)
    ok = base > 1e-12
    powv = torch.where(ok, torch.where(ok, base, torch.ones_like(base)).pow(p), torch.zeros_like(base))
    big = (1.0 - powv) / xs
    series = p * (1.0 - 0.5 * (p - 1.0) * x)
    return torch.where(small, series, big)


def _gpow(base: Tensor, p) -> Tensor:
    ok = base > 1e-12
    return torch.where(ok, torch.where(ok, base, torch.ones_like(base)).pow(p), torch.zeros_like(base))


#: Readings of the damaged eq 8 (see :func:`microfacet_diffuse_fitted`). The default is the one that
#: fits eq 4; the others are kept so that the choice stays testable.
FIT_READINGS = {
    # the course notes as printed: L_m ∝ (1 − σ/2) n·l + σ/2 (n·l)², V_d·B_p
    "paper": dict(lm="paper", combine="product"),
    "ue4": dict(lm="ue4", combine="sum"),  # the widely copied shader: L_m n·l (1 − σ/2 (n·l − 1)), V_d + B_p
    "paper-lm-ue4": dict(lm="ue4", combine="product"),
    "ue4-lm-paper": dict(lm="paper", combine="sum"),
}


class _FitParts:
    """The pieces of eq 8's bracket (:func:`_fit_terms`) at σ ``[..., 1]``: F_r's three factors, L_m's two, V_d's
    σ-dependent factor and the rest of the view term, kept so that :meth:`derivative` can differentiate in σ by hand
    (a closed form for the fit's Jacobian)."""

    def __init__(self, nl: Tensor, nv: Tensor, cosri: Tensor, sigma: Tensor, reading: str, cosine: bool):
        r = FIT_READINGS[reading]
        self.rules, self.cosine, self.cosri = r, cosine, cosri
        s = self.s = sigma
        s2 = self.s2 = s.square()
        x = self.x = nl.clamp(0.0, 1.0)
        e = self.e = nv.clamp(0.0, 1.0)
        one_e = self.one_e = 1.0 - e
        a13 = self.a13 = s2 + 1.36053
        self.p5 = _gpow(one_e, 5.0 - 4.0 * s2)
        self.k = -0.733996 * s2 * s + 1.50912 * s2 - 1.16402 * s
        self.p1 = _gpow(one_e, 1.0 + 1.0 / (39.0 * s2.square() + 1.0))
        self.t1 = 1.0 - (0.542026 * s2 + 0.303573 * s) / a13
        self.t2 = 1.0 - self.p5 / a13
        self.t3 = self.k * self.p1 + 1.0
        self.fr = self.t1 * self.t2 * self.t3
        self.fresnel5 = 1.0 - (1.0 - x).pow(5)
        self.lm_a = torch.clamp(1.0 - 2.0 * s, min=0.0) * self.fresnel5 + torch.clamp(2.0 * s, max=1.0)
        if r["lm"] == "paper":
            self.lm_b = (1.0 - 0.5 * s) + 0.5 * s * x  # ((1 − σ/2) n·l + σ/2 (n·l)²)/n·l
        else:
            self.lm_b = 1.0 - 0.5 * s * (x - 1.0)  # (1 − σ/2 (n·l − 1)) n·l / n·l
        self.vd_c = s2 / ((s2 + 0.09) * (1.31072 + 0.995584 * e))
        self.pexp = (1.0 - 0.3726732 * e.square()) / (0.188566 + 0.388410 * e)
        self.w = x if cosine else torch.ones_like(x)

    def view(self, vd_c: Tensor, with_bp: bool = True) -> Tensor:
        """V_d B_p (or V_d + B_p) divided by n·l, V_d's σ factor ``vd_c``: linear in it but for the sum reading's
        B_p, which ``with_bp`` leaves out (its σ derivative is 0)."""
        x, e, cosri, w = self.x, self.e, self.cosri, self.w
        if self.rules["combine"] == "product":
            # V_d B_p / n·l: B_p = cosri (≥ 0) or 1.4 n·e n·l cosri (< 0)
            q = _one_minus_pow_over_x(x, self.pexp)  # (1 − (1 − n·l)^p)/n·l
            pos = vd_c * q * cosri * w
            neg = vd_c * (1.0 - _gpow(1.0 - x, self.pexp)) * 1.4 * e * cosri * w
            return torch.where(cosri >= 0, pos, neg)
        # V_d + B_p, each / n·l (printed without an n·l factor: unbounded as n·l → 0)
        inv = w / x.clamp_min(1e-6) if not self.cosine else torch.ones_like(x)
        bp = torch.where(cosri >= 0, cosri * inv, 1.4 * e * cosri * w) if with_bp else torch.zeros_like(x)
        return vd_c * (1.0 - _gpow(1.0 - x, self.pexp)) * inv + bp

    def bracket(self) -> Tensor:
        return self.fr * self.lm_a * self.lm_b * self.w + self.view(self.vd_c)

    def derivative(self) -> Tensor:
        """``∂ bracket/∂σ``, the derivatives automatic differentiation gives (a clamp's: 0 where it holds; a power
        of a base at 0: 0, :func:`_gpow`)."""
        s, s2, a13, one_e = self.s, self.s2, self.a13, self.one_e
        ln_1e = torch.where(one_e > 1e-12, torch.log(torch.where(one_e > 1e-12, one_e, torch.ones_like(one_e))),
                            torch.zeros_like(one_e))
        num1 = 0.542026 * s2 + 0.303573 * s
        dt1 = -((2.0 * 0.542026 * s + 0.303573) * a13 - num1 * 2.0 * s) / a13.square()
        dp5 = self.p5 * ln_1e * (-8.0 * s)
        dt2 = -(dp5 * a13 - self.p5 * 2.0 * s) / a13.square()
        q4 = 39.0 * s2.square() + 1.0
        dp1 = self.p1 * ln_1e * (-156.0 * s2 * s / q4.square())
        dk = -3.0 * 0.733996 * s2 + 2.0 * 1.50912 * s - 1.16402
        dt3 = dk * self.p1 + self.k * dp1
        dfr = dt1 * self.t2 * self.t3 + self.t1 * dt2 * self.t3 + self.t1 * self.t2 * dt3
        zero = torch.zeros_like(s)
        dlm_a = torch.where(1.0 - 2.0 * s >= 0.0, -2.0 * self.fresnel5, zero) + torch.where(2.0 * s <= 1.0, 2.0 + zero,
                                                                                            zero)
        dlm_b = (-0.5 + 0.5 * self.x) if self.rules["lm"] == "paper" else -0.5 * (self.x - 1.0)
        dvd_c = 0.18 * s / ((s2 + 0.09).square() * (1.31072 + 0.995584 * self.e))
        return ((dfr * self.lm_a * self.lm_b + self.fr * dlm_a * self.lm_b + self.fr * self.lm_a * dlm_b) * self.w
                + self.view(dvd_c, with_bp=False))


def _fit_terms(nl: Tensor, nv: Tensor, cosri: Tensor, sigma: Tensor, reading: str, cosine: bool) -> Tensor:
    """The bracket F_r L_m + V_d B_p of eq 8 divided by n·l (times n·l with ``cosine``)."""
    return _FitParts(nl, nv, cosri, sigma, reading, cosine).bracket()


SIGMA_MAPS = ("alpha", "roughness", "oren-nayar")


def fit_sigma(roughness: Tensor, sigma_is: str = "alpha") -> Tensor:
    """σ of eq 8 from perceptual roughness r: ``"alpha"`` (GGX α = r², the default, see docs),
    ``"roughness"`` (r itself) or ``"oren-nayar"`` (σ = √(2/s), s = 2/α² − 2, capped at 1)."""
    from .roughness import roughness_to_sigma

    if sigma_is == "alpha":
        return roughness_to_alpha(roughness)
    if sigma_is == "roughness":
        return roughness.clamp(0.0, 1.0)
    if sigma_is == "oren-nayar":
        return roughness_to_sigma(roughness)
    raise ValueError(f"fit_sigma: unknown sigma_is={sigma_is!r}; valid values are {list(SIGMA_MAPS)}")


def microfacet_diffuse_fitted(g: Angles, albedo: Tensor, sigma: Tensor, f0: Tensor, reading: str = "paper",
                              cosine: bool = False) -> Tensor:
    """Gotanda 2014 eq 8, the closed-form fit of the microfacet diffuse eq 4.

    As read (``reading="paper"``)::

        f_r = ρ 21/(20π) (1 − f0) (F_r L_m + V_d B_p) / n·l
        F_r = (1 − (0.542026 σ² + 0.303573 σ)/(σ² + 1.36053)) (1 − (1 − n·e)^(5 − 4σ²)/(σ² + 1.36053))
              ((−0.733996 σ³ + 1.50912 σ² − 1.16402 σ)(1 − n·e)^(1 + 1/(39σ⁴ + 1)) + 1)
        L_m = (max(1 − 2σ, 0)(1 − (1 − n·l)⁵) + min(2σ, 1)) ((1 − 0.5σ) n·l + 0.5σ (n·l)²)
        V_d = σ²/((σ² + 0.09)(1.31072 + 0.995584 n·e))
              (1 − (1 − n·l)^((1 − 0.3726732 (n·e)²)/(0.188566 + 0.388410 n·e)))
        B_p = 1.4 (n·e)(n·l) cosri  if cosri < 0,  cosri otherwise;   cosri = e·l − (n·e)(n·l)

    Readings settled against the numerical reference (grid of angles and σ; numbers in
    docs/models-diffuse.md and tests/materials/test_microfacet_diffuse.py):

    * ``(n·e^2)`` in V_d's exponent is (n·e)²; the exponent 5 − 4σ² is as printed; σ is the GGX α.
    * L_m: the course notes print ((1 − 0.5σ) n·l + 0.5σ (n·l)²); a widely copied shader has
      n·l (1 − 0.5σ (n·l − 1)). The notes' form fits eq 4 better (see docs).
    * V_d B_p (product, as printed) vs V_d + B_p (the shader): the product fits; the sum does not
      vanish as n·l → 0 and is off by far more.

    ``reading`` selects one of :data:`FIT_READINGS` (kept for the comparison tests).

    Args:
        g: cosines ``[..., 1]``; albedo, f0 ``[..., C]``; sigma ``[..., 1]`` in [0, 1] (GGX α).

    Returns:
        f_r in 1/sr ``[..., C]`` (or f_r·n·l); 0 unless n·l > 0 and n·v > 0. Not reciprocal (a fit).
    """
    fn = "microfacet_diffuse_fitted"
    _check_angles(g, fn)
    if reading not in FIT_READINGS:
        raise ValueError(f"{fn}: unknown reading {reading!r}; valid readings are {list(FIT_READINGS)}")
    albedo = _t(albedo, g.nl, "albedo", fn)
    f0 = _t(f0, g.nl, "f0", fn)
    sigma = _t(sigma, g.nl, "sigma", fn).clamp(0.0, 1.0)
    bracket = _fit_terms(g.nl, g.nv, g.lv - g.nl * g.nv, sigma, reading, cosine)
    out = albedo * (1.0 - f0) * (1.05 * INV_PI) * bracket
    out = torch.broadcast_tensors(out, albedo)[0]
    return torch.where(g.front, out, torch.zeros_like(out))


METHODS = ("numerical", "fitted")


@register("microfacet-diffuse", "Gotanda 2014 microfacet diffuse: eq 4 by quadrature (method='numerical') or eq 8 fit")
class MicrofacetDiffuse(Model):
    """Gotanda 2014 microfacet diffuse. Parameters: albedo, roughness (α = r²), f0.

    Options: ``method`` ("fitted" default, eq 8; "numerical", eq 4 — slow: ~4608 evaluations of the
    integrand per sample), ``nodes`` (quadrature for "numerical"), ``reading`` (eq 8 reading).
    """

    params = (ALBEDO, ROUGHNESS, F0)

    def __init__(self, method: str = "fitted", nodes: tuple[int, int] = DEFAULT_NODES, reading: str = "paper"):
        if method not in METHODS:
            raise ValueError(f"model 'microfacet-diffuse': unknown method={method!r}; valid values are {list(METHODS)}")
        if reading not in FIT_READINGS:
            raise ValueError(f"model 'microfacet-diffuse': unknown reading={reading!r}; "
                             f"valid values are {list(FIT_READINGS)}")
        self.method, self.nodes, self.reading = method, tuple(nodes), reading

    def _eval(self, g: Angles, p: Mapping[str, Tensor], cosine: bool) -> Tensor:
        alpha = roughness_to_alpha(p["roughness"])
        if self.method == "numerical":
            return microfacet_diffuse_numerical(g, p["albedo"], alpha, p["f0"], self.nodes, cosine)
        return microfacet_diffuse_fitted(g, p["albedo"], alpha, p["f0"], self.reading, cosine)

    def brdf(self, g, p):
        return self._eval(g, p, False)

    def cosine_brdf(self, g, p):
        return self._eval(g, p, True)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The eq 8 fit in closed form (``method="numerical"``: None): ``ρ (1 − f0) 21/(20π) · bracket(σ)``, the
        bracket's σ derivative by hand (:class:`_FitParts`), σ = α = r² inside its clamps; ρ and f0 act per channel
        (diagonal derivatives)."""
        if self.method != "fitted" or not self.shades_as(MicrofacetDiffuse):
            return None
        albedo, f0, r = p["albedo"], p["f0"], p["roughness"]
        sigma = roughness_to_alpha(r).clamp(0.0, 1.0)
        parts = _FitParts(g.nl, g.nv, g.lv - g.nl * g.nv, sigma, self.reading, True)
        bracket = parts.bracket()
        scale = 1.05 * INV_PI
        value = albedo * (1.0 - f0) * scale * bracket
        value = torch.where(g.front, torch.broadcast_tensors(value, albedo)[0], torch.zeros_like(value))
        inside = (r >= R_MIN) & (r <= 1.0)
        dsigma = torch.where(inside, 2.0 * r.clamp(R_MIN, 1.0), torch.zeros_like(r))
        dbracket = parts.derivative() * dsigma

        def front(x: Tensor) -> Tensor:
            x = torch.broadcast_tensors(x, value)[0]
            return torch.where(g.front, x, torch.zeros_like(x))

        return value, {"albedo": front((1.0 - f0) * scale * bracket), "f0": front(-albedo * scale * bracket),
                       "roughness": front(albedo * (1.0 - f0) * scale * dbracket)[..., None]}
