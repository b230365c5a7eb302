"""The Oren-Nayar family of rough-diffuse lobes, and Gotanda's spherical-harmonics lighting for it.

Every lobe is a pure function of :class:`~materials.geometry.Angles` returning the BRDF f_r in 1/sr
(no cosine), RGB ``[..., C]`` in the last dimension, and 0 unless n·l > 0 and n·v > 0. The papers
write reflected radiance ``L_r = ρ/π E0 (n·l) [...]``; a lobe returns ``L_r / (E0 n·l)``, rearranged
so that no vanishing cosine is divided by: ``min(1, n·l/n·v) / n·l = 1 / max(n·l, n·v)``. Each
lobe takes ``cosine=True`` to return ``f_r · n·l`` instead, computed without the 1/max(n·l, n·v)
factor (that product stays bounded at double-grazing incidence, where f_r itself grows without
bound — which is the model, not a numerical artefact).

Notation (all Gotanda's): ``E`` = v (eye), ``L`` = l, ``N`` = n;
``cosri = E·L − (N·E)(N·L) = sin θ_i sin θ_r cos(φ_r − φ_i)`` (Gotanda 2012 eq 18), the signed
out-of-plane term that every simplified form is written in. σ is the Oren-Nayar slope deviation
(radians, the standard deviation of the facet slope angle), ``shi``/``s`` the Blinn-Phong
exponent; the models convert the canonical perceptual roughness r with
:func:`materials.roughness.roughness_to_sigma` (σ = √(2/s), eq 21, capped at 1) or
:func:`materials.roughness.roughness_to_shininess`.

Lobes (paper, equation):

=================================  ======================================================
:func:`oren_nayar_full`            Oren & Nayar 1994 eq 27 (C1, C2, C3) + interreflection
:func:`oren_nayar_qualitative`     Oren & Nayar 1994 qualitative model = Gotanda 2012 eq 10/11
:func:`gotanda_on_simplified`      Gotanda 2012 eq 20 (σ) and eq 23 (shininess)
:func:`gotanda_on_improved`        Gotanda 2012 eq 24 and eq 25 (sign-dependent)
:func:`gotanda2014_on`             Gotanda 2014 eq 5 (eq 25 written in σ)
:func:`gotanda2014_on_fresnel`     Gotanda 2014 eq 6-7 (diffuse Fresnel)
:func:`sh_dc_scale`                Gotanda 2012 eq 27 / eq 28
:func:`sh_linear_scale`            Gotanda 2012 eq 29
=================================  ======================================================

OCR readings chosen (each checked; see ``docs/models-diffuse.md`` and the tests):

* 2012 eq 11 prints ``sqrt((1 − Max(N·L, N·E))^2 (1 − Min(N·L, N·E)^2))``; it is
  ``sqrt((1 − Max²)(1 − Min²)) = sin α sin β`` (it must equal eq 10's sin α tan β · Max, and eq 12
  drops the Max/Min by exactly this symmetry). Test: eq 11 = eq 10 from θ/φ.
* 2012 eq 18 prints ``cos(φ_r − φ_i) = (E·L + (N·E)(N·L)) / ...``; eq 17/18's first line gives
  ``E·L − (N·E)(N·L)`` (the ocr2 copy agrees with the minus in eq 18's first line).
* 2012 eq 23 constants: 0.5 (2/s)/((2/s) + 0.33) = 1/(2 + 0.33 s) and
  0.45 (2/s)/((2/s) + 0.09) = 1/(2.22222 + 0.1 s) — both exact; eq 20 = eq 23 under eq 21 (tested).
* 2012 eq 24/25 "0.65": 1/(2 + 0.65 s) = 0.5 σ²/(σ² + 0.65) under eq 21, i.e. exactly 2014 eq 5's
  constant; so 2014 eq 5 *is* 2012 eq 25 in σ (tested).
* 2014 eq 5, "otherwise" branch: printed as ``B (e·l − (n·e)(n·l))`` without the ``(n·l)`` factor
  of 2012 eq 25, which eq 5 says it reproduces ("the improved Oren-Nayar from [4]"). Read
  literally, L_r would not vanish as n·l → 0 (f_r ∝ 1/n·l, negative). We keep 2012 eq 25's
  ``(n·l)`` factor, i.e. f_r's term is ``B · cosri``.
* 2014 eq 7 prints only the ``min(1, n·l/n·e)`` case; it is eq 5 with F_diff inserted, so we apply
  eq 5's sign-dependent case split (without it f_r < 0 for backward grazing light, eq 24's flaw).
  The outer ``(1 − f0)`` of eq 7 is kept although F_diff (eq 6) holds another ``(1 − f0)``: the
  Lambert-like term carries ``(1 − f0)²``. This is the printed formula; see the docs.
* 2012 eq 29: ``S(s, x) = f(s) + (f(s) − 1)(1 − x)``. The prose after it swaps N·E (it says 0.7 at
  N·E = 0); Figure 10's table and the exact limit (at N·E = 1 every Gotanda form is A · Lambert, so
  S(s, 1) must equal f(s)) agree with the formula as printed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace

import torch
from torch import Tensor

from .environment import Environment, SHLight
from .geometry import Angles, as_param, check_angles
from .model import Model, register
from .params import ALBEDO, F0, ROUGHNESS
from .roughness import (
    roughness_to_shininess,
    roughness_to_shininess_derivative,
    roughness_to_sigma,
    roughness_to_sigma_derivative,
)

INV_PI = 1.0 / math.pi
#: Floor of max(n·l, n·v) in the 1/max(n·l, n·v) factor of f_r (not used by ``cosine=True``).
#: Below it (both directions within 1e-6 of grazing) f_r is under-estimated but finite.
MAX_COS_FLOOR = 1e-6
#: Floor of the denominators of the bounded ratios n·l/max(n·l, n·v) and n·l/(n·l + n·v) of the
#: cosine-weighted forms: finite gradients in float32 (1/x² < 3e38). Below it (both cosines < 1e-12)
#: those ratios fall to 0 instead of their direction-dependent limit.
RATIO_FLOOR = 1e-12


# -- helpers ------------------------------------------------------------------------------------
_check_angles = check_angles
_t = as_param


def _cosri(g: Angles) -> Tensor:
    """E·L − (N·E)(N·L) = sin θ_i sin θ_r cos(φ_r − φ_i) (Gotanda 2012 eq 18)."""
    return g.lv - g.nl * g.nv


def _inv_max(g: Angles, cosine: bool) -> Tensor:
    """``1/max(n·l, n·v)`` (BRDF) or ``n·l/max(n·l, n·v) = min(1, n·l/n·v)`` (cosine-weighted, eq 14)."""
    nl, nv = g.nl.clamp_min(0.0), g.nv.clamp_min(0.0)
    m = torch.maximum(nl, nv)
    if cosine:
        return nl / m.clamp_min(RATIO_FLOOR)
    return 1.0 / m.clamp_min(MAX_COS_FLOOR)


def _weight(g: Angles, cosine: bool) -> Tensor:
    """The factor turning a bracket ``[A + ...]`` of f_r into f_r (1) or f_r·n·l (n·l)."""
    return g.nl.clamp_min(0.0) if cosine else torch.ones_like(g.nl)


def _finish(g: Angles, value: Tensor, albedo: Tensor) -> Tensor:
    value = torch.broadcast_tensors(value, albedo)[0]
    return torch.where(g.front, value, torch.zeros_like(value))


def _ab_sigma(sigma: Tensor, a_const: float = 0.33) -> tuple[Tensor, Tensor]:
    """Oren-Nayar A = 1 − 0.5 σ²/(σ² + a_const), B = 0.45 σ²/(σ² + 0.09) (1994 eq 30; Gotanda eq 10)."""
    s2 = sigma.square()
    return 1.0 - 0.5 * s2 / (s2 + a_const), 0.45 * s2 / (s2 + 0.09)


def _ab_shininess(s: Tensor, a_const: float = 0.33) -> tuple[Tensor, Tensor]:
    """A = 1 − 1/(2 + a_const·s), B = 1/(2.22222 + 0.1 s) (Gotanda 2012 eq 23, 24)."""
    s = s.clamp_min(0.0)
    return 1.0 - 1.0 / (2.0 + a_const * s), 1.0 / (20.0 / 9.0 + 0.1 * s)


def _ab_sigma_derivative(sigma: Tensor, a_const: float = 0.33) -> tuple[Tensor, Tensor]:
    """``(∂A/∂σ, ∂B/∂σ)`` of :func:`_ab_sigma`: ``−σ a_const/(σ² + a_const)²`` and ``0.081 σ/(σ² + 0.09)²``."""
    s2 = sigma.square()
    return -sigma * a_const / (s2 + a_const).square(), 0.081 * sigma / (s2 + 0.09).square()


def _ab_shininess_derivative(s: Tensor, a_const: float = 0.33) -> tuple[Tensor, Tensor]:
    """``(∂A/∂s, ∂B/∂s)`` of :func:`_ab_shininess`: ``a_const/(2 + a_const s)²`` and ``−0.1/(2.22222 + 0.1 s)²``
    (0 below s = 0, where its clamp holds)."""
    keep = s >= 0.0
    s = s.clamp_min(0.0)
    da, db = a_const / (2.0 + a_const * s).square(), -0.1 / (20.0 / 9.0 + 0.1 * s).square()
    return torch.where(keep, da, torch.zeros_like(da)), torch.where(keep, db, torch.zeros_like(db))


def _safe_acos(c: Tensor) -> Tensor:
    """acos on [0, 1) with a finite derivative: the cosine is clamped to 1 − ε first (ε = 1e-6 in
    float32, 1e-12 in float64). At the clamp θ is √(2ε) instead of 0, far below any term's scale."""
    eps = 1e-6 if c.dtype in (torch.float32, torch.float16, torch.bfloat16) else 1e-12
    return torch.acos(c.clamp(0.0, 1.0 - eps))


# -- Oren & Nayar 1994 --------------------------------------------------------------------------
def oren_nayar_full(g: Angles, albedo: Tensor, sigma: Tensor, interreflection: bool = True,
                    cosine: bool = False, clamp: bool = True) -> Tensor:
    """The full Oren-Nayar (1994) rough-diffuse BRDF, with the interreflection term.

    Oren & Nayar, "Generalization of Lambert's Reflectance Model", SIGGRAPH 1994 — the functional
    approximation of the Gaussian V-cavity surface that Gotanda 2012 calls "Equation 27 in the
    original paper" (direct illumination, L_r¹) plus the approximation of the two-bounce
    interreflection component (L_r², the term Gotanda's qualitative model lacks)::

        L_r¹ = ρ/π E0 cos θ_i [ C1 + cos(φ_r − φ_i) C2 tan β + (1 − |cos(φ_r − φ_i)|) C3 tan((α + β)/2) ]
        C1 = 1 − 0.5 σ²/(σ² + 0.33)
        C2 = 0.45 σ²/(σ² + 0.09) sin α                       if cos(φ_r − φ_i) ≥ 0
             0.45 σ²/(σ² + 0.09) (sin α − (2β/π)³)           otherwise
        C3 = 0.125 σ²/(σ² + 0.09) (4αβ/π²)²
        L_r² = 0.17 ρ²/π E0 cos θ_i σ²/(σ² + 0.13) [1 − cos(φ_r − φ_i) (2β/π)²]
        α = max(θ_r, θ_i), β = min(θ_r, θ_i)

    The equation numbers of the original (27 for L_r¹, the interreflection term after it) are as
    cited by Gotanda 2012; the constants are the published ones. Computed from cosines:
    cos α = min(n·l, n·v), cos β = max(n·l, n·v), ``cos(φ_r − φ_i) sin θ_i sin θ_r = cosri``,
    ``tan((α + β)/2) = (sin α + sin β)/(cos α + cos β)``, α and β by a clamped acos.

    Negative as published. In the forward (specular) half, cos(φ_r − φ_i) < 0, C2's (sin α − (2β/π)³)
    and tan β meet at grazing angles: at α = β = π/2 − ε their product tends to 6/π, so the direct
    term tends to C1 − (6/π) 0.45 σ²/(σ² + 0.09) at a double-grazing mirror pair — negative for every
    σ > 0.664 (r > 0.744), −0.164 at σ = 1 (π f/ρ as ρ → 0). The interreflection term is positive
    there (0.30 ρ at σ = 1) and outweighs it for ρ ≥ 0.55. This is the published functional fit (the
    same constants and case split in independent implementations), not a misplaced term; the
    V-cavity radiance it approximates is never negative. Measured over uniform front-facing
    directions (docs/models-diffuse.md, :func:`materials.validation.negative_extent`): at σ = 1 and
    ρ → 0, 0.60 % of the pairs; with ρ and r uniform in [0, 1], 0.040 %. ``clamp=True`` (default)
    returns max(f_r, 0) of the total, as
    :func:`gotanda_on_improved` does for eq 24; ``clamp=False`` gives the published formula.

    Args:
        g: shading cosines ``[..., 1]`` (uses n·l, n·v, l·v).
        albedo: ρ ∈ [0, 1], ``[..., C]``. Enters quadratically through the interreflection term.
        sigma: σ ≥ 0 in radians, ``[..., 1]`` (Oren-Nayar fits were made for σ ≤ 1).
        interreflection: add L_r² (True, the complete model) or return L_r¹ only.
        cosine: return f_r · n·l instead of f_r.
        clamp: return max(f_r, 0) (default) or the published formula, negative in places.

    Returns:
        f_r in 1/sr (or f_r·n·l), ``[..., C]``; 0 unless n·l > 0 and n·v > 0. Reciprocal.
    """
    fn = "oren_nayar_full"
    _check_angles(g, fn)
    albedo = _t(albedo, g.nl, "albedo", fn)
    sigma = _t(sigma, g.nl, "sigma", fn).clamp_min(0.0)
    geo = _FullGeometry.of(g, cosine)
    c1, b, k3, ki = _full_coefficients(sigma)
    out = albedo * INV_PI * geo.direct(c1, b, k3)
    if interreflection:
        out = out + albedo.square() * INV_PI * geo.inter(ki)
    if clamp:
        out = out.clamp_min(0.0)
    return _finish(g, out, albedo)


def _full_coefficients(sigma: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The σ-dependent factors of :func:`oren_nayar_full`: C1, C2's ``0.45 σ²/(σ² + 0.09)``, C3's ``0.125 σ²/(σ² +
    0.09)`` and the interreflection's ``0.17 σ²/(σ² + 0.13)``."""
    s2 = sigma.square()
    return 1.0 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09), 0.125 * s2 / (s2 + 0.09), 0.17 * s2 / (s2 + 0.13)


def _full_coefficients_derivative(sigma: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``∂/∂σ`` of :func:`_full_coefficients`: ``−0.33 σ/(σ² + 0.33)²``, ``0.081 σ/(σ² + 0.09)²``,
    ``0.0225 σ/(σ² + 0.09)²``, ``0.0442 σ/(σ² + 0.13)²``."""
    s2 = sigma.square()
    d09 = (s2 + 0.09).square()
    return (-0.33 * sigma / (s2 + 0.33).square(), 0.081 * sigma / d09, 0.0225 * sigma / d09,
            0.0442 * sigma / (s2 + 0.13).square())


class _FullGeometry:
    """The angle terms of :func:`oren_nayar_full` (α, β, the azimuth cosine, tan β and tan((α + β)/2), each tangent
    times the weight 1 or n·l), made once: its direct term is linear in (C1, B, C3's factor) and its
    interreflection term in its own factor, so the same terms of the factors' derivatives are the derivatives."""

    def __init__(self, w, cos_phi, sin_a, two_beta_pi, ab2, tan_b, tan_half):
        self.w, self.cos_phi, self.sin_a, self.two_beta_pi = w, cos_phi, sin_a, two_beta_pi
        self.ab2, self.tan_b, self.tan_half = ab2, tan_b, tan_half

    @classmethod
    def of(cls, g: Angles, cosine: bool) -> _FullGeometry:
        nl = g.nl.clamp(0.0, 1.0)
        nv = g.nv.clamp(0.0, 1.0)
        cmax, cmin = torch.maximum(nl, nv), torch.minimum(nl, nv)
        alpha, beta = _safe_acos(cmin), _safe_acos(cmax)
        sin_a, sin_b = torch.sin(alpha), torch.sin(beta)
        # cos(φ_r − φ_i) = cosri / (sin θ_i sin θ_r); where undefined (a direction along n) every term it
        # multiplies vanishes, so any value in [-1, 1] will do — 0 (double-where keeps the gradient finite).
        den = sin_a * sin_b
        ok = den > 1e-12
        cos_phi = torch.where(ok, _cosri(g) / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(den))
        cos_phi = cos_phi.clamp(-1.0, 1.0)
        two_beta_pi = 2.0 * beta / math.pi
        ab2 = (4.0 * alpha * beta / math.pi**2).square()
        # tan β and tan((α+β)/2), each times the weight (1 or n·l) so that the cosine form stays bounded.
        w = _weight(g, cosine)
        tan_b = sin_b * _inv_max(g, cosine)  # sin β / cos β  (· n·l)
        half_den = (nl + nv).clamp_min(RATIO_FLOOR if cosine else MAX_COS_FLOOR)
        tan_half = (sin_a + sin_b) * w / half_den  # tan((α+β)/2) (· n·l)
        return cls(w, cos_phi, sin_a, two_beta_pi, ab2, tan_b, tan_half)

    def direct(self, c1: Tensor, b: Tensor, k3: Tensor) -> Tensor:
        """L_r¹'s bracket ``C1 + cos(φ_r − φ_i) C2 tan β + (1 − |cos(φ_r − φ_i)|) C3 tan((α + β)/2)``."""
        c2 = torch.where(self.cos_phi >= 0, b * self.sin_a, b * (self.sin_a - self.two_beta_pi.pow(3)))
        c3 = k3 * self.ab2
        return c1 * self.w + self.cos_phi * c2 * self.tan_b + (1.0 - self.cos_phi.abs()) * c3 * self.tan_half

    def inter(self, ki: Tensor) -> Tensor:
        """L_r²'s bracket without ρ²: ``0.17 σ²/(σ² + 0.13) [1 − cos(φ_r − φ_i) (2β/π)²]``."""
        return ki * (1.0 - self.cos_phi * self.two_beta_pi.square()) * self.w


def oren_nayar_qualitative(g: Angles, albedo: Tensor, sigma: Tensor, cosine: bool = False) -> Tensor:
    """Oren & Nayar's qualitative model, Gotanda 2012 eq 10 written as eq 11 (dot products)::

        L_r = ρ/π E0 cos θ_i (A + B max(0, cos(φ_r − φ_i)) sin α tan β)                 (eq 10)
        A = 1 − 0.5 σ²/(σ² + 0.33),  B = 0.45 σ²/(σ² + 0.09),  α = max(θ_r, θ_i), β = min(θ_r, θ_i)
        cos(φ_r − φ_i) = (E − N(N·E))/‖·‖ · (L − N(N·L))/‖·‖ = cosri / √((1 − (N·L)²)(1 − (N·E)²))
        sin α tan β = √((1 − Max²)(1 − Min²)) / Max,  Max/Min = max/min(N·L, N·E)          (eq 11)

    Evaluated term by term as eq 11 prints it (the azimuth cosine and sin α tan β separately);
    :func:`gotanda_on_simplified` is the algebraically identical eq 20.

    Args, returns: as :func:`oren_nayar_full` (no interreflection). Reciprocal.
    """
    fn = "oren_nayar_qualitative"
    _check_angles(g, fn)
    albedo = _t(albedo, g.nl, "albedo", fn)
    sigma = _t(sigma, g.nl, "sigma", fn).clamp_min(0.0)
    a, b = _ab_sigma(sigma)
    return _finish(g, albedo * INV_PI * _qualitative_bracket(g, a, b, cosine), albedo)


def _qualitative_bracket(g: Angles, a: Tensor, b: Tensor, cosine: bool) -> Tensor:
    """Eq 10/11's bracket ``A + B max(0, cos(φ_r − φ_i)) sin α tan β`` (times n·l with ``cosine``), linear in
    ``(a, b)``: the same function of ``(∂A, ∂B)`` is its derivative."""
    nl = g.nl.clamp(0.0, 1.0)
    nv = g.nv.clamp(0.0, 1.0)
    sin_prod_sq = ((1.0 - nl.square()) * (1.0 - nv.square())).clamp_min(0.0)
    ok = sin_prod_sq > 1e-24
    sin_prod = torch.sqrt(torch.where(ok, sin_prod_sq, torch.ones_like(sin_prod_sq)))
    cos_phi = torch.where(ok, (_cosri(g) / sin_prod).clamp(-1.0, 1.0), torch.zeros_like(sin_prod))
    sin_prod = torch.where(ok, sin_prod, torch.zeros_like(sin_prod))
    sin_a_tan_b = sin_prod * _inv_max(g, cosine)
    return a * _weight(g, cosine) + b * cos_phi.clamp_min(0.0) * sin_a_tan_b


# -- Gotanda 2012 -------------------------------------------------------------------------------
def gotanda_on_simplified(g: Angles, albedo: Tensor, sigma: Tensor | None = None,
                          shininess: Tensor | None = None, cosine: bool = False) -> Tensor:
    """Gotanda's simplified Oren-Nayar, 2012 eq 20 (σ) or eq 23 (Blinn-Phong shininess)::

        L_r = ρ/π E0 [ (N·L) A + B max(0, E·L − (N·E)(N·L)) min(1, N·L/N·E) ]           (eq 20)
        A = 1 − 0.5 σ²/(σ² + 0.33),     B = 0.45 σ²/(σ² + 0.09)
        A = 1 − 1/(2 + 0.33 s),         B = 1/(2.22222 + 0.1 s)                         (eq 23)

    so f_r = ρ/π [A + B max(0, cosri)/max(N·L, N·E)]. Eq 20 equals the qualitative model exactly;
    eq 23 equals eq 20 under σ = √(2/s) (eq 21). Pass exactly one of ``sigma`` (radians, ≥ 0) or
    ``shininess`` (≥ 0), each ``[..., 1]``.

    Returns: f_r in 1/sr (or f_r·n·l with ``cosine=True``), ``[..., C]``. Reciprocal.
    """
    fn = "gotanda_on_simplified"
    _check_angles(g, fn)
    if (sigma is None) == (shininess is None):
        raise ValueError(f"{fn}: pass exactly one of sigma= (eq 20) or shininess= (eq 23)")
    albedo = _t(albedo, g.nl, "albedo", fn)
    if sigma is not None:
        a, b = _ab_sigma(_t(sigma, g.nl, "sigma", fn).clamp_min(0.0))
    else:
        a, b = _ab_shininess(_t(shininess, g.nl, "shininess", fn))
    return _finish(g, albedo * INV_PI * _simplified_bracket(g, a, b, cosine), albedo)


def _simplified_bracket(g: Angles, a: Tensor, b: Tensor, cosine: bool) -> Tensor:
    """Eq 20/23's bracket ``A + B max(0, cosri)/max(N·L, N·E)`` (times n·l with ``cosine``), linear in ``(a, b)``."""
    return a * _weight(g, cosine) + b * _cosri(g).clamp_min(0.0) * _inv_max(g, cosine)


def _improved_bracket(g: Angles, a: Tensor, b: Tensor, form: str, cosine: bool) -> Tensor:
    cosri = _cosri(g)
    pos = b * cosri * _inv_max(g, cosine)  # B cosri min(1, N·L/N·E) / N·L
    if form == "eq24":
        term = pos
    else:  # eq25: otherwise-branch B cosri (N·L) / N·L = B cosri
        term = torch.where(cosri >= 0, pos, b * cosri * _weight(g, cosine))
    return a * _weight(g, cosine) + term


IMPROVED_FORMS = ("eq24", "eq25")


def gotanda_on_improved(g: Angles, albedo: Tensor, shininess: Tensor, form: str = "eq25",
                        cosine: bool = False, clamp: bool = True) -> Tensor:
    """Gotanda's improved Oren-Nayar, 2012 eq 24 and eq 25::

        L_r = ρ/π E0 [ (N·L)(1 − 1/(2 + 0.65 s)) + 1/(2.22222 + 0.1 s) cosri min(1, N·L/N·E) ]   (eq 24)
        eq 25: the same if cosri ≥ 0, otherwise the last term is 1/(2.22222 + 0.1 s) cosri (N·L)

    with cosri = E·L − (N·E)(N·L). Eq 24 drops eq 23's max(0, ·) (backward light darkens) and
    changes 0.33 to 0.65 (brighter Lambert part, standing in for the missing interreflection).
    Eq 24 goes negative for backward, grazing light (e.g. n·l = n·v = 0.1, l·v = −0.98, s = 2:
    f_r = −3.6 ρ/π): with ``clamp=True`` (default) the lobe returns max(f_r, 0); ``clamp=False``
    gives the printed formula. Eq 25 is ≥ 0 for every s ≥ 0 (A − B ≥ 0.28).

    Args:
        shininess: Blinn-Phong exponent s ≥ 0, ``[..., 1]``.
        form: ``"eq24"`` or ``"eq25"``.

    Returns: f_r in 1/sr (or f_r·n·l), ``[..., C]``. Reciprocal.
    """
    fn = "gotanda_on_improved"
    _check_angles(g, fn)
    if form not in IMPROVED_FORMS:
        raise ValueError(f"{fn}: unknown form {form!r}; valid forms are {list(IMPROVED_FORMS)}")
    albedo = _t(albedo, g.nl, "albedo", fn)
    a, b = _ab_shininess(_t(shininess, g.nl, "shininess", fn), a_const=0.65)
    bracket = _improved_bracket(g, a, b, form, cosine)
    if clamp:
        bracket = bracket.clamp_min(0.0)
    return _finish(g, albedo * INV_PI * bracket, albedo)


# -- Gotanda 2014 -------------------------------------------------------------------------------
def gotanda2014_on(g: Angles, albedo: Tensor, sigma: Tensor, cosine: bool = False) -> Tensor:
    """Gotanda 2014 eq 5: the improved Oren-Nayar of 2012 eq 25 written in σ::

        L_r = ρ/π E0 [ (n·l)(1 − 0.5 σ²/(σ² + 0.65)) + 0.45 σ²/(σ² + 0.09) cosri min(1, n·l/n·e) ]  cosri ≥ 0
        L_r = ρ/π E0 [ (n·l)(1 − 0.5 σ²/(σ² + 0.65)) + 0.45 σ²/(σ² + 0.09) cosri (n·l) ]           otherwise

    The "otherwise" branch keeps the (n·l) factor of 2012 eq 25 (the 2014 print lacks it; see the
    module docstring). Identical to :func:`gotanda_on_improved` ``form="eq25"`` at s = 2/σ².

    Returns: f_r in 1/sr (or f_r·n·l), ``[..., C]``. Reciprocal, ≥ 0.
    """
    fn = "gotanda2014_on"
    _check_angles(g, fn)
    albedo = _t(albedo, g.nl, "albedo", fn)
    a, b = _ab_sigma(_t(sigma, g.nl, "sigma", fn).clamp_min(0.0), a_const=0.65)
    return _finish(g, albedo * INV_PI * _improved_bracket(g, a, b, "eq25", cosine), albedo)


def diffuse_fresnel(nl: Tensor, nv: Tensor, f0: Tensor) -> Tensor:
    """Gotanda 2014 eq 6 (Shirley et al. 1997 without its 1/π): the diffuse Fresnel factor

        F_diff(l, e) = 21/20 (1 − f0)(1 − (1 − n·l)⁵)(1 − (1 − n·e)⁵).

    21/20 normalises ∫ (1 − (1 − cos)⁵) cos dω/π = 20/21. Cosines are clamped to [0, 1].

    Args:
        nl, nv: cosines ``[..., 1]``.
        f0: specular reflectance at normal incidence, ``[..., C]`` in [0, 1].

    Returns: ``[..., C]``, in [0, 21/20].
    """
    one_minus = lambda c: 1.0 - (1.0 - c.clamp(0.0, 1.0)).pow(5)
    return 1.05 * (1.0 - f0) * one_minus(nl) * one_minus(nv)


def gotanda2014_on_fresnel(g: Angles, albedo: Tensor, sigma: Tensor, f0: Tensor, cosine: bool = False,
                           clamp: bool = True) -> Tensor:
    """Gotanda 2014 eq 7: improved Oren-Nayar with the diffuse Fresnel factor of eq 6::

        L_r = ρ/π E0 (1 − f0) [ F_diff(l, e)(n·l)(1 − 0.5 σ²/(σ² + 0.65)) + 0.45 σ²/(σ² + 0.09) cosri min(1, n·l/n·e) ]

    with eq 5's case split applied to the cosri term (cosri < 0 → cosri (n·l)); see the module
    docstring for this reading and for the (1 − f0)² that the printed formula gives the first term.

    F_diff takes the Lambert-like term to 0 at grazing angles but not the (negative, backward)
    cosri term, so even with the case split the printed model goes negative for backward light
    near grazing (e.g. θ_i = 85°, θ_r = 60°, φ = 180°, σ = 1, f0 = 0.04: π f/ρ = −0.103). With
    ``clamp=True`` (default) the lobe returns max(f_r, 0); ``clamp=False`` gives the formula.

    Args:
        f0: ``[..., C]`` in [0, 1].

    Returns: f_r in 1/sr (or f_r·n·l), ``[..., C]``. Reciprocal, ≥ 0 when clamped.
    """
    fn = "gotanda2014_on_fresnel"
    _check_angles(g, fn)
    albedo = _t(albedo, g.nl, "albedo", fn)
    f0 = _t(f0, g.nl, "f0", fn)
    a, b = _ab_sigma(_t(sigma, g.nl, "sigma", fn).clamp_min(0.0), a_const=0.65)
    bracket = _fresnel_bracket(g, a, b, diffuse_fresnel(g.nl, g.nv, f0), cosine)
    if clamp:
        bracket = bracket.clamp_min(0.0)
    return _finish(g, albedo * INV_PI * (1.0 - f0) * bracket, albedo)


def _fresnel_bracket(g: Angles, a: Tensor, b: Tensor, fd: Tensor, cosine: bool) -> Tensor:
    """Eq 7's bracket ``F_diff A (n·l) + B cosri min(1, n·l/n·e)`` (eq 5's case split; times n·l with ``cosine``):
    linear in ``(a, b)``, and in ``fd`` where ``b`` is 0."""
    view = _improved_bracket(g, torch.zeros_like(a), b, "eq25", cosine)
    return fd * a * _weight(g, cosine) + view


# -- spherical-harmonics lighting (Gotanda 2012 eq 26-29) ----------------------------------------
SH_DC_FORMS = ("eq27", "eq28")


def sh_dc_scale(shininess: Tensor, nv: Tensor, form: str = "eq27") -> Tensor:
    """Scale of the SH DC band for the improved Oren-Nayar (Gotanda 2012 eq 27, or the cheaper eq 28)::

        SH'_DC = (f(s) + ½ g(s) (1 + 2 arccos(N·E)/π − N·E)) SH_DC                     (eq 27)
        SH'_DC = (f(s) + g(s)(1 − N·E)) SH_DC                                           (eq 28)
        f(s) = 1 − 1/(2 + 0.65 s),  g(s) = 1/(2.22222 + 0.1 s)

    Eq 26 is the directional albedo ∫ f_r (n·l) dω_l of eq 25 at ρ = 1. Measured against it (our
    quadrature of our eq 25 lobe): both forms are exact at N·E = 1 (= f(s), where eq 25 is
    A · Lambert) but overestimate toward grazing views, by up to 0.71 g(s) at N·E = 0 (0.29 at σ = 1):
    eq 26 of eq 25 is f + g (P − N), P = 0.5 and N = 0.21 at N·E = 0 for the positive and negative
    cosri parts. Eq 27's shape ½(1 + 2 arccos(x)/π − x) matches 2P(x) to 0.021 (eq 28's 1 − x to
    0.11): the printed fit tracks twice the positive part alone — as if the integrand had no
    backward term and twice the weight. We implement eq 27/28 as printed; see docs/models-diffuse.md.

    Args:
        shininess: s ≥ 0 ``[..., 1]``; nv: N·E ``[..., 1]`` (clamped to [0, 1]).

    Returns: ``[..., 1]``.
    """
    if form not in SH_DC_FORMS:
        raise ValueError(f"sh_dc_scale: unknown form {form!r}; valid forms are {list(SH_DC_FORMS)}")
    f, gs = _ab_shininess(shininess, a_const=0.65)
    x = nv.clamp(0.0, 1.0)
    if form == "eq27":
        return f + 0.5 * gs * (1.0 + 2.0 * _safe_acos(x) / math.pi - x)
    return f + gs * (1.0 - x)


def sh_linear_scale(shininess: Tensor, nv: Tensor) -> Tensor:
    """Scale of the SH linear band, Gotanda 2012 eq 29: S(s, N·E) = f(s) + (f(s) − 1)(1 − N·E).

    S = 1 at σ = 0 (s → ∞); at σ = 1 (s = 2) S = 0.70 for N·E = 1 and 0.39 for N·E = 0 (Figure 10:
    "0.7 · Lambert" at normal view, "comparatively flat" at grazing view). Returns ``[..., 1]``.
    """
    f, _ = _ab_shininess(shininess, a_const=0.65)
    x = nv.clamp(0.0, 1.0)
    return f + (f - 1.0) * (1.0 - x)


def _sh_environment(model: Model, env: Environment, n: Tensor, v: Tensor, albedo: Tensor,
                    shininess: Tensor, dc_form: str) -> Tensor:
    if not isinstance(env, SHLight):
        return Model.environment(model, env, n, v, {})
    for name, x in (("n", n), ("v", v)):
        if not isinstance(x, Tensor) or x.shape[-1] != 3:
            raise ValueError(f"{model.name}.environment: {name} must be a tensor [..., 3] of unit vectors")
    nv = (n * v).sum(-1, keepdim=True)
    dc = sh_dc_scale(shininess, nv, dc_form)
    lin = sh_linear_scale(shininess, nv)
    e = env.irradiance(n, scale=(dc, lin, 1.0))
    return torch.where(nv > 0, albedo * INV_PI * e, torch.zeros_like(e))


# -- registered models -----------------------------------------------------------------------------
#: Albedo enters the full model quadratically (interreflection): not solvable in closed form.
_ALBEDO_NONLINEAR = replace(ALBEDO, linear=False)


def _bracket_jacobian(g: Angles, p, bracket: Callable[[Tensor, Tensor], Tensor], in_sigma: bool, a_const: float,
                      clamp: bool) -> tuple[Tensor, dict[str, Tensor]]:
    """``cosine_brdf`` and its derivatives in closed form for a lobe ``ρ/π · [A·X + B·Y]`` (n·l included), the
    bracket ``bracket(a, b)`` linear in the Oren-Nayar coefficients — so that ``bracket(∂A/∂r, ∂B/∂r)`` is its
    derivative — with A, B of σ (``in_sigma``, :func:`_ab_sigma`) or of the shininess (:func:`_ab_shininess`), σ or
    s from the roughness with their clamps' zero derivatives, and ``clamp``: max(bracket, 0), whose derivative is 0
    where the bracket is negative. The value is computed as the lobe computes it; each albedo channel acts on its
    own colour channel (a diagonal derivative)."""
    albedo, r = p["albedo"], p["roughness"]
    if in_sigma:
        x, dx = roughness_to_sigma_derivative(r)
        x = x.clamp_min(0.0)
        a, b = _ab_sigma(x, a_const)
        da, db = _ab_sigma_derivative(x, a_const)
    else:
        x, dx = roughness_to_shininess_derivative(r)
        a, b = _ab_shininess(x, a_const)
        da, db = _ab_shininess_derivative(x, a_const)
    br = bracket(a, b)
    dbr = bracket(da * dx, db * dx)
    if clamp:
        dbr = torch.where(br >= 0.0, dbr, torch.zeros_like(dbr))
        br = br.clamp_min(0.0)
    value = _finish(g, albedo * INV_PI * br, albedo)
    d_albedo = torch.where(g.front, INV_PI * br, torch.zeros_like(br)).expand_as(value)
    d_r = torch.where(g.front, albedo * INV_PI * dbr, torch.zeros_like(value))
    return value, {"albedo": d_albedo, "roughness": d_r[..., None]}


def _check_choice(model: str, option: str, value, valid) -> None:
    if value not in valid:
        raise ValueError(f"model '{model}': unknown {option}={value!r}; valid values are {list(valid)}")


@register("oren-nayar", "Oren & Nayar 1994 full rough-diffuse model (C1, C2, C3) with interreflection")
class OrenNayar(Model):
    """Full Oren-Nayar 1994 (:func:`oren_nayar_full`); ``interreflection=False`` drops L_r².

    Options: ``interreflection`` (True/False); ``clamp`` (True: max(f_r, 0), the default; False: the
    published formula, which is negative at grazing forward-scattering pairs for σ > 0.664 and dark
    albedo — see :func:`oren_nayar_full`).

    Parameters: albedo, roughness (σ = roughness_to_sigma(r)). With interreflection albedo is not
    linear (ρ² term); without it the clamp keeps it linear (max(ρ d, 0) = ρ max(d, 0) for ρ ≥ 0).
    Cost: two acos, a few sin/sqrt — the most expensive closed form here.
    """

    def __init__(self, interreflection: bool = True, clamp: bool = True):
        _check_choice("oren-nayar", "interreflection", interreflection, (True, False))
        _check_choice("oren-nayar", "clamp", clamp, (True, False))
        self.interreflection = interreflection
        self.clamp = clamp
        self.params = (_ALBEDO_NONLINEAR if interreflection else ALBEDO, ROUGHNESS)

    def _eval(self, g, p, cosine):
        return oren_nayar_full(g, p["albedo"], roughness_to_sigma(p["roughness"]), self.interreflection, cosine,
                               self.clamp)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """In closed form: ``ρ/π D(C1, B, C3) + ρ²/π I(K)``, the direct bracket D linear in its σ-dependent factors
        and the interreflection I in its own (:class:`_FullGeometry`), so their derivatives in r are the same
        brackets of the factors' derivatives; ∂/∂ρ = (D + 2ρ I)/π per channel (diagonal). The clamp max(·, 0) of
        the total gives 0 where it holds."""
        if not self.shades_as(OrenNayar):
            return None
        albedo = p["albedo"]
        sigma, dsigma = roughness_to_sigma_derivative(p["roughness"])
        sigma = sigma.clamp_min(0.0)
        geo = _FullGeometry.of(g, True)
        c1, b, k3, ki = _full_coefficients(sigma)
        dc1, db, dk3, dki = (d * dsigma for d in _full_coefficients_derivative(sigma))
        direct = geo.direct(c1, b, k3)
        out = albedo * INV_PI * direct
        d_albedo = INV_PI * direct
        d_r = albedo * INV_PI * geo.direct(dc1, db, dk3)
        if self.interreflection:
            inter = geo.inter(ki)
            out = out + albedo.square() * INV_PI * inter
            d_albedo = d_albedo + 2.0 * albedo * INV_PI * inter
            d_r = d_r + albedo.square() * INV_PI * geo.inter(dki)
        if self.clamp:
            live = out >= 0.0
            d_albedo = torch.where(live, d_albedo, torch.zeros_like(d_albedo))
            d_r = torch.where(live, d_r, torch.zeros_like(d_r))
            out = out.clamp_min(0.0)
        value = _finish(g, out, albedo)

        def front(x: Tensor) -> Tensor:
            x = torch.broadcast_tensors(x, value)[0]
            return torch.where(g.front, x, torch.zeros_like(x))

        return value, {"albedo": front(d_albedo), "roughness": front(d_r)[..., None]}

    def brdf(self, g, p):
        return self._eval(g, p, False)

    def cosine_brdf(self, g, p):
        return self._eval(g, p, True)


@register("oren-nayar-qualitative", "Oren & Nayar's qualitative model (Gotanda 2012 eq 10/11)")
class OrenNayarQualitative(Model):
    """Qualitative Oren-Nayar (:func:`oren_nayar_qualitative`). Parameters: albedo, roughness (σ)."""

    params = (ALBEDO, ROUGHNESS)

    def brdf(self, g, p):
        return oren_nayar_qualitative(g, p["albedo"], roughness_to_sigma(p["roughness"]))

    def cosine_brdf(self, g, p):
        return oren_nayar_qualitative(g, p["albedo"], roughness_to_sigma(p["roughness"]), cosine=True)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """In closed form (:func:`_bracket_jacobian`): eq 10/11's bracket is linear in A and B."""
        if not self.shades_as(OrenNayarQualitative):
            return None
        return _bracket_jacobian(g, p, lambda a, b: _qualitative_bracket(g, a, b, True), True, 0.33, False)


@register("gotanda-on-simplified", "Gotanda 2012 simplified Oren-Nayar: eq 20 (form='sigma') or eq 23 ('shininess')")
class GotandaONSimplified(Model):
    """Gotanda 2012 eq 20 / eq 23 (:func:`gotanda_on_simplified`). Parameters: albedo, roughness.

    ``form="sigma"`` uses σ = roughness_to_sigma(r) (capped at 1); ``form="shininess"`` uses
    s = roughness_to_shininess(r) (s ∈ [0, 2^16]; equal to the σ form wherever σ < 1).
    """

    params = (ALBEDO, ROUGHNESS)
    FORMS = ("sigma", "shininess")

    def __init__(self, form: str = "sigma"):
        _check_choice("gotanda-on-simplified", "form", form, self.FORMS)
        self.form = form

    def _eval(self, g, p, cosine):
        r = p["roughness"]
        if self.form == "sigma":
            return gotanda_on_simplified(g, p["albedo"], sigma=roughness_to_sigma(r), cosine=cosine)
        return gotanda_on_simplified(g, p["albedo"], shininess=roughness_to_shininess(r), cosine=cosine)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """In closed form (:func:`_bracket_jacobian`): eq 20/23's bracket is linear in A and B."""
        if not self.shades_as(GotandaONSimplified):
            return None
        return _bracket_jacobian(g, p, lambda a, b: _simplified_bracket(g, a, b, True), self.form == "sigma", 0.33,
                                 False)

    def brdf(self, g, p):
        return self._eval(g, p, False)

    def cosine_brdf(self, g, p):
        return self._eval(g, p, True)


class _SHMixin:
    sh_dc: str = "eq27"

    def environment(self, env, n, v, p):
        """Radiance from an :class:`SHLight`: ρ/π · E(n) with the DC band scaled by Gotanda 2012
        eq 27 (or eq 28, ``sh_dc="eq28"``) and the linear band by eq 29; quadratic band unscaled."""
        s = roughness_to_shininess(p["roughness"])
        return _sh_environment(self, env, n, v, p["albedo"], s, self.sh_dc)


@register("gotanda-on-improved", "Gotanda 2012 improved Oren-Nayar: eq 24 or eq 25 (form=), SH lighting eq 27-29")
class GotandaONImproved(_SHMixin, Model):
    """Gotanda 2012 eq 24/25 (:func:`gotanda_on_improved`), s = roughness_to_shininess(r).

    Options: ``form`` ("eq25" default, "eq24"), ``clamp`` (True: max(f_r, 0), the default; False: the
    printed formula — eq 24 goes negative for backward grazing light, see the lobe; eq 25 never does),
    ``sh_dc`` ("eq27" default or "eq28") for :meth:`environment` with an :class:`SHLight`.
    """

    params = (ALBEDO, ROUGHNESS)

    def __init__(self, form: str = "eq25", sh_dc: str = "eq27", clamp: bool = True):
        _check_choice("gotanda-on-improved", "form", form, IMPROVED_FORMS)
        _check_choice("gotanda-on-improved", "sh_dc", sh_dc, SH_DC_FORMS)
        _check_choice("gotanda-on-improved", "clamp", clamp, (True, False))
        self.form, self.sh_dc, self.clamp = form, sh_dc, clamp

    def brdf(self, g, p):
        return gotanda_on_improved(g, p["albedo"], roughness_to_shininess(p["roughness"]), self.form, clamp=self.clamp)

    def cosine_brdf(self, g, p):
        return gotanda_on_improved(g, p["albedo"], roughness_to_shininess(p["roughness"]), self.form, cosine=True,
                                   clamp=self.clamp)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """In closed form (:func:`_bracket_jacobian`): eq 24/25's bracket is linear in A and B."""
        if not self.shades_as(GotandaONImproved):
            return None
        return _bracket_jacobian(g, p, lambda a, b: _improved_bracket(g, a, b, self.form, True), False, 0.65,
                                 self.clamp)


@register("gotanda2014-on", "Gotanda 2014 eq 5: improved Oren-Nayar in σ (0.65 constant), SH lighting eq 27-29")
class Gotanda2014ON(_SHMixin, Model):
    """Gotanda 2014 eq 5 (:func:`gotanda2014_on`), σ = roughness_to_sigma(r). Option ``sh_dc``.

    The SH response uses s = roughness_to_shininess(r), the same surface (eq 21) wherever σ < 1.
    """

    params = (ALBEDO, ROUGHNESS)

    def __init__(self, sh_dc: str = "eq27"):
        _check_choice("gotanda2014-on", "sh_dc", sh_dc, SH_DC_FORMS)
        self.sh_dc = sh_dc

    def brdf(self, g, p):
        return gotanda2014_on(g, p["albedo"], roughness_to_sigma(p["roughness"]))

    def cosine_brdf(self, g, p):
        return gotanda2014_on(g, p["albedo"], roughness_to_sigma(p["roughness"]), cosine=True)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """In closed form (:func:`_bracket_jacobian`): eq 5's bracket (2012 eq 25 in σ) is linear in A and B."""
        if not self.shades_as(Gotanda2014ON):
            return None
        return _bracket_jacobian(g, p, lambda a, b: _improved_bracket(g, a, b, "eq25", True), True, 0.65, False)


@register("gotanda2014-on-fresnel", "Gotanda 2014 eq 7: improved Oren-Nayar with diffuse Fresnel (eq 6)")
class Gotanda2014ONFresnel(Model):
    """Gotanda 2014 eq 6-7 (:func:`gotanda2014_on_fresnel`). Parameters: albedo, roughness (σ), f0.

    Option ``clamp``: True (default) returns max(f_r, 0); False the printed eq 7, negative for backward
    grazing light (e.g. θ_i = 85°, θ_r = 60°, φ = 180°, σ = 1, f0 = 0.04: π f/ρ = −0.103).
    """

    params = (ALBEDO, ROUGHNESS, F0)

    def __init__(self, clamp: bool = True):
        _check_choice("gotanda2014-on-fresnel", "clamp", clamp, (True, False))
        self.clamp = clamp

    def brdf(self, g, p):
        return gotanda2014_on_fresnel(g, p["albedo"], roughness_to_sigma(p["roughness"]), p["f0"], clamp=self.clamp)

    def cosine_brdf(self, g, p):
        return gotanda2014_on_fresnel(g, p["albedo"], roughness_to_sigma(p["roughness"]), p["f0"], cosine=True,
                                      clamp=self.clamp)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """In closed form: ``ρ/π (1 − f0) [F_diff(f0) A (n·l) + B ·]``, the bracket linear in A and B and in F_diff,
        whose derivative in f0 is ``−1.05 (1 − (1 − n·l)⁵)(1 − (1 − n·e)⁵)``; albedo and f0 act per channel
        (diagonal derivatives)."""
        if not self.shades_as(Gotanda2014ONFresnel):
            return None
        albedo, f0 = p["albedo"], p["f0"]
        sigma, dsigma = roughness_to_sigma_derivative(p["roughness"])
        sigma = sigma.clamp_min(0.0)
        a, b = _ab_sigma(sigma, 0.65)
        da, db = _ab_sigma_derivative(sigma, 0.65)
        fd = diffuse_fresnel(g.nl, g.nv, f0)
        br = _fresnel_bracket(g, a, b, fd, True)
        d_r = _fresnel_bracket(g, da * dsigma, db * dsigma, fd, True)
        d_f0 = _fresnel_bracket(g, a, torch.zeros_like(b), diffuse_fresnel(g.nl, g.nv, torch.full_like(f0, 2.0)),
                                True)                       # F_diff at f0 = 2 is −1.05 (…)(…): ∂F_diff/∂f0
        if self.clamp:
            live = br >= 0.0
            d_r = torch.where(live, d_r, torch.zeros_like(d_r))
            d_f0 = torch.where(live, d_f0, torch.zeros_like(d_f0))
            br = br.clamp_min(0.0)
        one_minus = 1.0 - f0
        value = _finish(g, albedo * INV_PI * one_minus * br, albedo)
        scale = albedo * INV_PI

        def front(x: Tensor) -> Tensor:
            return torch.where(g.front, x, torch.zeros_like(x))

        return value, {"albedo": front(INV_PI * one_minus * br).expand_as(value),
                       "f0": front(scale * (one_minus * d_f0 - br)),
                       "roughness": front(scale * one_minus * d_r)[..., None]}
