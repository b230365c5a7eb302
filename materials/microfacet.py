"""Microfacet specular reflection f_r = D F G / (4 n·l n·v) (Gotanda 2014 eq 1; Cook & Torrance 1981;
Walter et al. 2007), with a choosable normal distribution D, geometry term G and Fresnel term F.

=====================  ==========================================================================
D (``ndf_*``)          ``ggx`` (Trowbridge-Reitz), ``beckmann``, ``blinn-phong`` (normalised,
                       s = roughness.alpha_to_shininess(α)); each ∫ D(h) (n·h) dω_h = 1, in 1/sr.
G (``geometry_term``)  ``smith`` (separable G1(l) G1(v)), ``smith-correlated`` (height-correlated
                       1/(1 + Λ(l) + Λ(v))), ``cook-torrance`` (V-cavity), ``kelemen``
                       (Kelemen & Szirmay-Kalos 2001), ``neumann`` (Neumann et al. 1999).
F                      any key of :data:`materials.fresnel.FRESNEL` (``none, schlick, exact, sg,
                       schuler``) or a callable ``f(f0, cos)``; evaluated at cos = l·h.
=====================  ==========================================================================

Smith's Λ must match D. ``smith`` and ``smith-correlated`` use the GGX Λ(θ) = (−1 + √(1 + α² tan²θ))/2
for D = ggx, and for D = beckmann and D = blinn-phong (Walter et al. 2007 §5.2: Phong's exponent s
corresponds to Beckmann's α through α = √(2/(s + 2)), the inverse of our s = 2/α² − 2) the Beckmann Λ,
in one of two forms (``beckmann_lambda``):

- ``"rational"`` (default): the approximation Walter et al. (2007) give with their eq 27
  Λ(a) = (1 − 1.259a + 0.396a²)/(3.535a + 2.181a²) for a = 1/(α tanθ) < 1.6, else 0, one division and
  no transcendental; its G1 is within 0.32 % (absolute and relative) of the exact form (tested);
- ``"exact"``: the closed form of the Smith integral for Beckmann slopes (Walter et al. 2007: eq 27's G1 is
  1/(1 + Λ) with this Λ),
  Λ(a) = (erf(a) − 1)/2 + exp(−a²)/(2 a √π), one erfc and one exp; tested against the defining integral
  Λ(ω) = ∫ max(0, ω·m) D(m) dω_m / cos θ − 1 by quadrature.

Stability. The BRDF is never computed as G / (4 n·l n·v): each G has a closed-form *visibility*
V = G/(4 n·l n·v) (see :func:`visibility_term`) in which no cosine is divided by except the
genuinely singular ones (V-cavity, Kelemen, Neumann at grazing mirror configurations, where the
true BRDF is unbounded). Those divide by cosines floored at ``COS_EPS`` = 1e-6, which changes
values only when n·l, n·v or l·h is below 1e-6 and keeps every value and gradient finite.
α is clamped to [roughness.ALPHA_MIN, 1] (the range the canonical conversions produce).
Everything returns 0 unless n·l > 0 and n·v > 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace

import torch
from torch import Tensor

from . import roughness as rough
from .fresnel import FRESNEL, fresnel_and_derivative, fresnel_from_f0
from .geometry import Angles, guarded_pow, guarded_pow_log
from .lambert import INV_PI, lambert
from .model import Model, register
from .params import ALBEDO, F0, ROUGHNESS

#: Floor for a cosine that is divided by (n·l, n·v, l·h in V-cavity/Kelemen/Neumann visibility).
COS_EPS = 1e-6
#: n·h below which the Beckmann D is exactly 0: at α ≤ 1, exp(−tan²θ_h/α²) < exp(−1e6) there.
BECKMANN_NH_MIN = 1e-3

DISTRIBUTIONS = ("ggx", "beckmann", "blinn-phong")
GEOMETRIES = ("smith", "smith-correlated", "cook-torrance", "kelemen", "neumann")
#: Forms of the Beckmann Smith Λ: Walter et al. 2007's rational approximation (eq 27) or the exact erf form.
BECKMANN_LAMBDAS = ("rational", "exact")
#: a = cot θ/α beyond which the exact Beckmann Λ is taken as 0: Λ(a) < exp(−a²)/(4 a³ √π) = 1.5e-19 at a = 6,
#: far below any cosine it is added to (and erfc(a) underflows float32 near a = 9.2).
BECKMANN_A_MAX = 6.0

__all__ = [
    "BECKMANN_LAMBDAS", "COS_EPS", "DISTRIBUTIONS", "GEOMETRIES", "ndf", "ndf_ggx", "ndf_beckmann", "ndf_blinn_phong",
    "smith_lambda_cos", "smith_g1", "smith_g1_ggx", "smith_g2_correlated_ggx", "visibility_term",
    "geometry_term", "microfacet_specular", "specular_jacobian", "Microfacet", "CookTorrance",
]


# -- validation -------------------------------------------------------------------------------------
def _cos_tensor(x, name: str, fn: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{fn}: {name} must be a torch.Tensor of cosines [..., 1], got {type(x).__name__}")
    if x.dim() == 0 or x.shape[-1] != 1:
        raise ValueError(f"{fn}: {name} must have a trailing dimension of size 1 ([..., 1]), "
                         f"got shape {tuple(x.shape)}; use x.unsqueeze(-1)")
    return x


def _alpha(alpha, fn: str) -> Tensor:
    if isinstance(alpha, (int, float)):
        alpha = torch.tensor([float(alpha)], dtype=torch.get_default_dtype())
    if not isinstance(alpha, Tensor):
        raise TypeError(f"{fn}: alpha must be a torch.Tensor [..., 1] or a float, got {type(alpha).__name__}")
    if alpha.dim() == 0:
        alpha = alpha.reshape(1)
    if alpha.shape[-1] != 1:
        raise ValueError(f"{fn}: alpha must have a trailing dimension of size 1 ([..., 1]), "
                         f"got shape {tuple(alpha.shape)}")
    return alpha.clamp(rough.ALPHA_MIN, 1.0)


def _angles(g, fn: str) -> Angles:
    if not isinstance(g, Angles):
        raise TypeError(f"{fn}: g must be a materials.Angles (build it with Angles.from_vectors), "
                        f"got {type(g).__name__}")
    return g


def _choice(value: str, valid: tuple[str, ...], what: str) -> str:
    if value not in valid:
        raise ValueError(f"unknown {what} {value!r}; valid choices: {', '.join(valid)}")
    return value


# -- normal distribution functions -----------------------------------------------------------------
def ndf_ggx(nh: Tensor, alpha) -> Tensor:
    """GGX / Trowbridge-Reitz distribution D(h) = α² / (π ((n·h)²(α² − 1) + 1)²) (Walter et al. 2007
    eq 33; the D of Gotanda 2014 eq 1).

    Args:
        nh: n·h ``[..., 1]``, any sign (0 returned for n·h ≤ 0).
        alpha: GGX width α ``[..., 1]`` (= roughness²), clamped to [ALPHA_MIN, 1].

    Returns:
        D in 1/sr ``[..., 1]``; 1/(π α²) at n·h = 1; ∫ D (n·h) dω_h = 1.
    """
    nh = _cos_tensor(nh, "nh", "ndf_ggx")
    a2 = _alpha(alpha, "ndf_ggx").square()
    c = nh.clamp(0.0, 1.0)
    d = (1.0 - c) * (1.0 + c) + c * c * a2  # = 1 + c²(α² − 1), without cancellation near c = 1
    return torch.where(nh > 0, a2 / (math.pi * d * d), torch.zeros_like(d))


def ndf_beckmann(nh: Tensor, alpha) -> Tensor:
    """Beckmann distribution D(h) = exp(−tan²θ_h / α²) / (π α² cos⁴θ_h) (Cook & Torrance 1981; Walter
    et al. 2007 eq 25).

    Args:
        nh: n·h ``[..., 1]`` (0 returned for n·h ≤ BECKMANN_NH_MIN, where D < exp(−1e6) anyway).
        alpha: Beckmann slope deviation α (the rms slope m of Cook-Torrance) ``[..., 1]``, clamped to
            [ALPHA_MIN, 1].

    Returns:
        D in 1/sr ``[..., 1]``; 1/(π α²) at n·h = 1; ∫ D (n·h) dω_h = 1.
    """
    nh = _cos_tensor(nh, "nh", "ndf_beckmann")
    a2 = _alpha(alpha, "ndf_beckmann").square()
    ok = nh > BECKMANN_NH_MIN
    c = torch.where(ok, nh.clamp(max=1.0), torch.ones_like(nh))
    c2 = c * c
    tan2 = (1.0 - c) * (1.0 + c) / c2
    d = torch.exp(-tan2 / a2) / (math.pi * a2 * c2 * c2)
    return torch.where(ok, d, torch.zeros_like(d))


def ndf_blinn_phong(nh: Tensor, alpha) -> Tensor:
    """Normalised Blinn-Phong distribution D(h) = (s + 2)/(2π) (n·h)^s with s = 2/α² − 2
    (:func:`materials.roughness.alpha_to_shininess`; Blinn 1977, normalisation of Walter et al. 2007).

    Args:
        nh: n·h ``[..., 1]`` (0 returned for n·h ≤ 0).
        alpha: α ``[..., 1]`` clamped to [ALPHA_MIN, 1]; α = 1 gives s = 0, the uniform D = 1/π.

    Returns:
        D in 1/sr ``[..., 1]``; ∫ D (n·h) dω_h = 1.
    """
    nh = _cos_tensor(nh, "nh", "ndf_blinn_phong")
    s = rough.alpha_to_shininess(_alpha(alpha, "ndf_blinn_phong"))
    d = (s + 2.0) / (2.0 * math.pi) * guarded_pow(nh.clamp(max=1.0), s)
    return torch.where(nh > 0, d, torch.zeros_like(d))


_NDF: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "ggx": ndf_ggx, "beckmann": ndf_beckmann, "blinn-phong": ndf_blinn_phong,
}


def ndf(name: str, nh: Tensor, alpha) -> Tensor:
    """The distribution ``name`` ∈ :data:`DISTRIBUTIONS` at n·h, in 1/sr ``[..., 1]``."""
    return _NDF[_choice(name, DISTRIBUTIONS, "normal distribution D")](nh, alpha)


# -- Smith masking ----------------------------------------------------------------------------------
def _ggx_root(c: Tensor, a2: Tensor) -> Tensor:
    """√(α² + (1 − α²) c²) = c √(1 + α² tan²θ), ≥ α > 0."""
    return torch.sqrt(a2 + (1.0 - a2) * c * c)


def _beckmann_lambda_cos_exact(c: Tensor, alpha: Tensor) -> Tensor:
    """cos·Λ of the exact Beckmann Λ(a) = (erf(a) − 1)/2 + exp(−a²)/(2a√π), a = cos/(α sinθ), as
    (α sinθ exp(−a²)/√π − cos erfc(a))/2: finite at cos = 0 (α/(2√π)), 0 for a ≥ BECKMANN_A_MAX."""
    sin2 = (1.0 - c) * (1.0 + c)
    ok = c * c < BECKMANN_A_MAX**2 * alpha.square() * sin2  # a < A_MAX (implies sin θ > 0)
    sin = torch.sqrt(torch.where(ok, sin2, torch.ones_like(sin2)))
    a = torch.where(ok, c / (alpha * sin), torch.zeros_like(c))
    lam = 0.5 * (alpha * sin * torch.exp(-a * a) / math.sqrt(math.pi) - c * torch.special.erfc(a))
    return torch.where(ok, lam.clamp_min(0.0), torch.zeros_like(lam))


def smith_lambda_cos(cos: Tensor, alpha, distribution: str = "ggx", beckmann_lambda: str = "rational") -> Tensor:
    """cos θ · Λ(θ), Smith's Λ multiplied by the cosine so that it stays finite at cos → 0.

    GGX: cos·Λ = (√(α² + (1 − α²) cos²) − cos)/2 (exact).
    Beckmann and Blinn-Phong, ``beckmann_lambda="rational"``: Walter et al. 2007's rational Λ(a) (eq 27),
    a = cos/(α sinθ), cos·Λ = α sinθ (1 − 1.259a + 0.396a²)/(3.535 + 2.181a) for a < 1.6, else 0 (clamped
    ≥ 0); ``"exact"``: (erf(a) − 1)/2 + exp(−a²)/(2a√π) times cos, written as
    (α sinθ exp(−a²)/√π − cos erfc(a))/2.

    Args:
        cos: n·l or n·v ``[..., 1]`` (clamped to [0, 1]).
        alpha: ``[..., 1]``, clamped to [ALPHA_MIN, 1].
        distribution: the D this Λ belongs to (one of :data:`DISTRIBUTIONS`).
        beckmann_lambda: one of :data:`BECKMANN_LAMBDAS` (ignored for GGX).
    """
    fn = "smith_lambda_cos"
    c = _cos_tensor(cos, "cos", fn).clamp(0.0, 1.0)
    alpha = _alpha(alpha, fn)
    _choice(distribution, DISTRIBUTIONS, "normal distribution D")
    _choice(beckmann_lambda, BECKMANN_LAMBDAS, "Beckmann Λ form")
    if distribution == "ggx":
        return 0.5 * (_ggx_root(c, alpha.square()) - c)
    if beckmann_lambda == "exact":
        return _beckmann_lambda_cos_exact(c, alpha)
    sin2 = (1.0 - c) * (1.0 + c)
    ok = c * c < 2.56 * alpha.square() * sin2  # a < 1.6 (implies sin θ > 0)
    sin = torch.sqrt(torch.where(ok, sin2, torch.ones_like(sin2)))
    a = c / (alpha * sin)
    lam = alpha * sin * (1.0 - 1.259 * a + 0.396 * a * a) / (3.535 + 2.181 * a)
    return torch.where(ok, lam.clamp_min(0.0), torch.zeros_like(lam))


def smith_g1(cos: Tensor, alpha, distribution: str = "ggx", beckmann_lambda: str = "rational") -> Tensor:
    """Smith's monodirectional masking G1 = 1/(1 + Λ) = cos/(cos + cos·Λ) ∈ [0, 1], ``[..., 1]``; 0 at cos ≤ 0.
    ``beckmann_lambda``: the Beckmann Λ form (:data:`BECKMANN_LAMBDAS`)."""
    c = _cos_tensor(cos, "cos", "smith_g1").clamp(0.0, 1.0)
    lc = smith_lambda_cos(c, alpha, distribution, beckmann_lambda)
    g1 = c / (c + lc)  # c + lc ≥ α/3.535 > 0 at c = 0 (both D), > 0 elsewhere
    return torch.where(cos > 0, g1, torch.zeros_like(g1))


def smith_g1_ggx(cos: Tensor, alpha) -> Tensor:
    """GGX Smith masking G1(θ) = 2 cos / (cos + √(α² + (1 − α²) cos²)) ∈ [0, 1] (Walter et al. 2007 eq 34).

    Args:
        cos: n·l or n·v ``[..., 1]``; 0 returned for cos ≤ 0.
        alpha: GGX α ``[..., 1]`` clamped to [ALPHA_MIN, 1].
    """
    c = _cos_tensor(cos, "cos", "smith_g1_ggx").clamp(0.0, 1.0)
    a2 = _alpha(alpha, "smith_g1_ggx").square()
    g1 = 2.0 * c / (c + _ggx_root(c, a2))
    return torch.where(cos > 0, g1, torch.zeros_like(g1))


def smith_g2_correlated_ggx(nl: Tensor, nv: Tensor, alpha) -> Tensor:
    """Height-correlated GGX Smith masking-shadowing G2 = 1/(1 + Λ(l) + Λ(v)) (Heitz 2014 eq 99),
    written as 2 n·l n·v / (n·v √(α² + (1−α²) n·l²) + n·l √(α² + (1−α²) n·v²)).

    Args:
        nl, nv: n·l and n·v ``[..., 1]``; 0 returned unless both > 0.
        alpha: GGX α ``[..., 1]`` clamped to [ALPHA_MIN, 1].

    Returns:
        G2 ∈ [0, 1] ``[..., 1]``; ≥ G1(l) G1(v) (correlation only removes double-counted masking).
    """
    fn = "smith_g2_correlated_ggx"
    nl = _cos_tensor(nl, "nl", fn)
    nv = _cos_tensor(nv, "nv", fn)
    a2 = _alpha(alpha, fn).square()
    front = (nl > 0) & (nv > 0)
    l = nl.clamp(COS_EPS, 1.0)
    v = nv.clamp(COS_EPS, 1.0)
    g2 = 2.0 * l * v / (v * _ggx_root(l, a2) + l * _ggx_root(v, a2))
    return torch.where(front, g2, torch.zeros_like(g2))


# -- geometry / visibility ------------------------------------------------------------------------------
def visibility_term(name: str, g: Angles, alpha, distribution: str = "ggx",
                    beckmann_lambda: str = "rational") -> Tensor:
    """V = G / (4 n·l n·v) for the geometry term ``name``, in a form that does not divide by a
    vanishing cosine (see module docstring), ``[..., 1]``; 0 unless n·l > 0 and n·v > 0.

    ================  ================================================================
    ``smith``         1 / (4 (n·l + n·l Λ_l)(n·v + n·v Λ_v))  (GGX: 1/((n·l + A_l)(n·v + A_v)))
    ``smith-corr..``  1 / (4 (n·l n·v + n·v · n·l Λ_l + n·l · n·v Λ_v))
                      (GGX: 0.5/(n·v A_l + n·l A_v), A = √(α² + (1−α²) cos²))
    ``cook-torrance`` min(1/(4 n·l n·v), n·h / (2 l·h max(n·l, n·v)))
    ``kelemen``       1 / (4 (l·h)²)
    ``neumann``       1 / (4 max(n·l, n·v))
    ================  ================================================================

    Args:
        name: one of :data:`GEOMETRIES`.
        g: shading cosines.
        alpha: ``[..., 1]`` (only the Smith terms use it), clamped to [ALPHA_MIN, 1].
        distribution: the D whose Smith Λ is used (Smith terms only).
        beckmann_lambda: the Beckmann Λ form for D = beckmann / blinn-phong (:data:`BECKMANN_LAMBDAS`).
    """
    fn = "visibility_term"
    _choice(name, GEOMETRIES, "geometry term G")
    g = _angles(g, fn)
    alpha = _alpha(alpha, fn)
    _choice(distribution, DISTRIBUTIONS, "normal distribution D")
    nl = g.nl.clamp(COS_EPS, 1.0)
    nv = g.nv.clamp(COS_EPS, 1.0)
    if name == "smith":
        lam_l = smith_lambda_cos(nl, alpha, distribution, beckmann_lambda)
        lam_v = smith_lambda_cos(nv, alpha, distribution, beckmann_lambda)
        vis = 0.25 / ((nl + lam_l) * (nv + lam_v))
    elif name == "smith-correlated":
        if distribution == "ggx":
            a2 = alpha.square()
            vis = 0.5 / (nv * _ggx_root(nl, a2) + nl * _ggx_root(nv, a2))
        else:
            lam_l = smith_lambda_cos(nl, alpha, distribution, beckmann_lambda)
            lam_v = smith_lambda_cos(nv, alpha, distribution, beckmann_lambda)
            vis = 0.25 / (nl * nv + nv * lam_l + nl * lam_v)
    elif name == "cook-torrance":
        lh = g.lh.clamp(COS_EPS, 1.0)
        nh = g.nh.clamp(0.0, 1.0)
        vis = torch.minimum(0.25 / (nl * nv), nh / (2.0 * lh * torch.maximum(nl, nv)))
    elif name == "kelemen":
        lh = g.lh.clamp(COS_EPS, 1.0)
        vis = 0.25 / (lh * lh)
    else:  # neumann
        vis = 0.25 / torch.maximum(nl, nv)
    return torch.where(g.front, vis, torch.zeros_like(vis))


def geometry_term(name: str, g: Angles, alpha, distribution: str = "ggx", beckmann_lambda: str = "rational") -> Tensor:
    """Geometric attenuation (masking-shadowing) G ∈ [0, 1], ``[..., 1]``; 0 unless front-facing.

    ================  ==============================================================================
    ``smith``         G1(l) G1(v), separable Smith (Walter et al. 2007 eq 23)
    ``smith-corr..``  1/(1 + Λ(l) + Λ(v)), height-correlated Smith (Heitz 2014 eq 99)
    ``cook-torrance`` min(1, 2 n·h n·v / v·h, 2 n·h n·l / v·h), V-cavity (Cook & Torrance 1981)
    ``kelemen``       n·l n·v / (l·h)², Kelemen & Szirmay-Kalos 2001 (G/(n·l n·v) ≈ 2/(1 + l·v));
                      ≤ 1 because l·h ≥ (n·l + n·v)/2 ≥ √(n·l n·v)
    ``neumann``       n·l n·v / max(n·l, n·v) = min(n·l, n·v), Neumann et al. 1999
    ================  ==============================================================================

    Args:
        name: one of :data:`GEOMETRIES`.
        g: shading cosines.
        alpha: ``[..., 1]`` used by the Smith terms, clamped to [ALPHA_MIN, 1].
        distribution: which D's Λ the Smith terms use (``ggx``; ``beckmann`` and ``blinn-phong``
            share the Beckmann Λ).
        beckmann_lambda: that Beckmann Λ's form, ``"rational"`` (Walter's) or ``"exact"`` (erf).
    """
    vis = visibility_term(name, g, alpha, distribution, beckmann_lambda)
    gt = 4.0 * g.nl.clamp(COS_EPS, 1.0) * g.nv.clamp(COS_EPS, 1.0) * vis
    return torch.where(g.front, gt.clamp(max=1.0), torch.zeros_like(gt))


# -- the specular BRDF ------------------------------------------------------------------------------
def _fresnel(F) -> Callable[[Tensor, Tensor], Tensor]:
    if callable(F):
        return F
    if F not in FRESNEL:
        raise ValueError(f"unknown Fresnel term F {F!r}; valid choices: {', '.join(FRESNEL)} "
                         f"(or a callable f(f0, cos))")
    return FRESNEL[F]


def microfacet_specular(g: Angles, f0: Tensor, alpha, D: str = "ggx", G: str = "smith-correlated",
                        F="schlick", beckmann_lambda: str = "rational") -> Tensor:
    """Microfacet specular BRDF f_r = D(h) F(l·h) G / (4 n·l n·v) (Gotanda 2014 eq 1), computed as
    D · F · V with V = :func:`visibility_term`.

    Args:
        g: shading cosines ``[..., 1]``.
        f0: reflectance at normal incidence ``[..., C]`` in [0, 1].
        alpha: width α = roughness² ``[..., 1]`` (roughness.roughness_to_alpha), clamped to
            [ALPHA_MIN, 1].
        D: one of :data:`DISTRIBUTIONS`.
        G: one of :data:`GEOMETRIES`; Smith terms use the Λ of D.
        F: a key of :data:`materials.fresnel.FRESNEL` or a callable ``f(f0, cos) -> [..., C]``.
        beckmann_lambda: the Smith terms' Beckmann Λ for D = beckmann / blinn-phong, ``"rational"``
            (Walter et al. 2007 eq 27, default) or ``"exact"`` (the erf form).

    Returns:
        f_r in 1/sr ``[..., C]`` (no cosine); 0 unless n·l > 0 and n·v > 0.
    """
    fn = "microfacet_specular"
    g = _angles(g, fn)
    if not isinstance(f0, Tensor):
        raise TypeError(f"{fn}: f0 must be a torch.Tensor [..., C], got {type(f0).__name__}")
    alpha = _alpha(alpha, fn)
    _choice(D, DISTRIBUTIONS, "normal distribution D")
    fres = _fresnel(F)
    vis = visibility_term(G, g, alpha, distribution=D, beckmann_lambda=beckmann_lambda)
    f = ndf(D, g.nh, alpha) * vis * fres(f0, g.fresnel_cos)
    return torch.where(g.front, f, torch.zeros_like(f))


# -- closed-form derivatives in α² ----------------------------------------------------------------------
def _ndf_derivative(name: str, nh: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`ndf` and its derivative in ``A = α²`` at an α inside [ALPHA_MIN, 1], each ``[..., 1]``.

    GGX, ``d = 1 + c²(A − 1)``: ``D = A/(π d²)``, ``∂D/∂A = (d − 2Ac²)/(π d³)``. Beckmann, ``t = tan²θ_h``:
    ``D = exp(−t/A)/(π A c⁴)``, ``∂D/∂A = D (t − A)/A²``. Blinn-Phong, ``s = 2/A − 2`` (0 where its clamp to
    [0, S_MAX] holds): ``D = (s + 2) c^s/(2π)``, ``∂D/∂s = D (1/(s + 2) + ln c)``, ``∂s/∂A = ∂s/∂α / (2α)``
    (:func:`materials.roughness.alpha_to_shininess_derivative`)."""
    A = alpha * alpha
    if name == "ggx":
        c = nh.clamp(0.0, 1.0)
        d = (1.0 - c) * (1.0 + c) + c * c * A
        inv = 1.0 / d
        lit = nh > 0
        zero = torch.zeros_like(d)
        return (torch.where(lit, A * inv * inv / math.pi, zero),
                torch.where(lit, (d - 2.0 * A * c * c) * inv * inv * inv / math.pi, zero))
    if name == "beckmann":
        ok = nh > BECKMANN_NH_MIN
        c = torch.where(ok, nh.clamp(max=1.0), torch.ones_like(nh))
        c2 = c * c
        tan2 = (1.0 - c) * (1.0 + c) / c2
        d = torch.exp(-tan2 / A) / (math.pi * A * c2 * c2)
        zero = torch.zeros_like(d)
        return torch.where(ok, d, zero), torch.where(ok, d * (tan2 - A) / (A * A), zero)
    s, ds = rough.alpha_to_shininess_derivative(alpha)
    power, log_c = guarded_pow_log(nh.clamp(max=1.0), s)
    d = (s + 2.0) / (2.0 * math.pi) * power
    dd = d * (1.0 / (s + 2.0) + log_c) * ds / (2.0 * alpha)
    lit = nh > 0
    return torch.where(lit, d, torch.zeros_like(d)), torch.where(lit, dd, torch.zeros_like(dd))


def _lambda_cos_derivative(c: Tensor, alpha: Tensor, distribution: str,
                           beckmann_lambda: str) -> tuple[Tensor, Tensor]:
    """:func:`smith_lambda_cos` of the Beckmann Λ (D = beckmann, blinn-phong) at a cosine ``c`` in [0, 1] and its
    derivative in ``A = α²``, each ``[..., 1]``. With ``a = c/(α sinθ)``: rational
    ``cos·Λ = α sinθ P(a)/Q(a)``, ``∂/∂α = sinθ (P/Q − a (P′Q − PQ′)/Q²)`` (``∂a/∂α = −a/α``); exact,
    ``∂/∂α = sinθ exp(−a²)/(2√π)`` (the erfc term's and the exponential's parts cancel); ``∂α/∂A = 1/(2α)``;
    0 where the form's clamp at 0 holds."""
    sin2 = (1.0 - c) * (1.0 + c)
    limit2 = BECKMANN_A_MAX**2 if beckmann_lambda == "exact" else 2.56     # (as smith_lambda_cos writes them)
    ok = c * c < limit2 * alpha.square() * sin2
    sin = torch.sqrt(torch.where(ok, sin2, torch.ones_like(sin2)))
    a = torch.where(ok, c / (alpha * sin), torch.zeros_like(c))
    if beckmann_lambda == "exact":
        e = torch.exp(-a * a)
        lam = 0.5 * (alpha * sin * e / math.sqrt(math.pi) - c * torch.special.erfc(a))
        dlam = 0.5 * sin * e / math.sqrt(math.pi)
    else:
        P, Q = 1.0 - 1.259 * a + 0.396 * a * a, 3.535 + 2.181 * a
        lam = alpha * sin * P / Q
        dlam = sin * (P / Q - a * ((-1.259 + 0.792 * a) * Q - P * 2.181) / (Q * Q))
    keep = ok & (lam >= 0.0)
    zero = torch.zeros_like(lam)
    return torch.where(ok, lam.clamp_min(0.0), zero), torch.where(keep, dlam / (2.0 * alpha), zero)


def _visibility_derivative(name: str, g: Angles, alpha: Tensor, distribution: str,
                           beckmann_lambda: str) -> tuple[Tensor, Tensor]:
    """:func:`visibility_term` and its derivative in ``A = α²`` (0 for the terms without α), each ``[..., 1]``, on the
    front side (elsewhere finite, not 0: the caller's ``(n·l)⁺`` factor zeroes them).
    Separable Smith ``V = 1/(4 (n·l + λ_l)(n·v + λ_v))``, ``λ = cos·Λ``: ``∂V/∂A = −V (λ_l′/(n·l + λ_l) +
    λ_v′/(n·v + λ_v))``; height-correlated ``V = 1/(4 (n·l n·v + n·v λ_l + n·l λ_v))``:
    ``∂V/∂A = −4V² (n·v λ_l′ + n·l λ_v′)``. GGX's ``λ = (R − cos)/2`` enters through ``R``."""
    nl = g.nl.clamp(COS_EPS, 1.0)
    nv = g.nv.clamp(COS_EPS, 1.0)
    if name in ("smith", "smith-correlated") and distribution == "ggx":
        # GGX's Smith terms through R = √(A + (1 − A) cos²) = cos + 2 cos·Λ, ∂R/∂A = (1 − cos²)/(2R): the
        # height-correlated V as visibility_term writes it, the separable one as 1/((n·l + R_l)(n·v + R_v))
        a2 = alpha.square()
        root_l, root_v = _ggx_root(nl, a2), _ggx_root(nv, a2)
        droot_l, droot_v = 0.5 * (1.0 - nl * nl) / root_l, 0.5 * (1.0 - nv * nv) / root_v
        if name == "smith":
            sum_l, sum_v = nl + root_l, nv + root_v
            vis = 1.0 / (sum_l * sum_v)
            dvis = -vis * (droot_l / sum_l + droot_v / sum_v)
        else:
            vis = 0.5 / (nv * root_l + nl * root_v)
            dvis = -2.0 * vis * vis * (nv * droot_l + nl * droot_v)
    elif name in ("smith", "smith-correlated"):
        lam_l, dlam_l = _lambda_cos_derivative(nl, alpha, distribution, beckmann_lambda)
        lam_v, dlam_v = _lambda_cos_derivative(nv, alpha, distribution, beckmann_lambda)
        if name == "smith":
            sum_l, sum_v = nl + lam_l, nv + lam_v
            vis = 0.25 / (sum_l * sum_v)
            dvis = -vis * (dlam_l / sum_l + dlam_v / sum_v)
        else:
            vis = 0.25 / (nl * nv + nv * lam_l + nl * lam_v)
            dvis = -4.0 * vis * vis * (nv * dlam_l + nl * dlam_v)
    else:
        vis = visibility_term(name, g, alpha, distribution, beckmann_lambda)
        dvis = torch.zeros_like(vis)
    return vis, dvis


def specular_jacobian(g: Angles, f0: Tensor, roughness: Tensor, D: str = "ggx", G: str = "smith-correlated",
                      F: str = "schlick", beckmann_lambda: str = "rational") -> tuple[Tensor, Tensor, Tensor]:
    """:func:`microfacet_specular` times ``(n·l)⁺`` at perceptual ``roughness`` (α = r², its clamp included) and its
    derivatives in closed form, for a named F (:data:`materials.fresnel.FRESNEL`).

    ``value = D V F (n·l)⁺`` on the front side, so ``∂/∂f0 = D V (n·l)⁺ ∂F/∂f0`` (channel by channel,
    :func:`materials.fresnel.fresnel_and_derivative`) and ``∂/∂r = (D′V + DV′) F (n·l)⁺ · 4r³``, with ``′`` the
    derivatives in ``A = α²`` (:func:`_ndf_derivative`, :func:`_visibility_derivative`) and ``∂A/∂r = 4r³`` inside
    the roughness clamp, 0 on it. Returns ``(value [..., C], ∂value/∂f0 [..., C] (the diagonal),
    ∂value/∂r [..., C, 1])``; the tests compare each D, G and F with automatic differentiation in float64."""
    fn = "specular_jacobian"
    g = _angles(g, fn)
    if not isinstance(f0, Tensor):
        raise TypeError(f"{fn}: f0 must be a torch.Tensor [..., C], got {type(f0).__name__}")
    if not isinstance(roughness, Tensor) or roughness.dim() == 0 or roughness.shape[-1] != 1:
        raise ValueError(f"{fn}: roughness must be a torch.Tensor [..., 1] of perceptual roughness, got "
                         f"{tuple(roughness.shape) if isinstance(roughness, Tensor) else type(roughness).__name__}")
    _choice(D, DISTRIBUTIONS, "normal distribution D")
    _choice(G, GEOMETRIES, "geometry term G")
    _choice(beckmann_lambda, BECKMANN_LAMBDAS, "Beckmann Λ form")
    rc = roughness.clamp(rough.R_MIN, 1.0)
    inside = ((roughness >= rough.R_MIN) & (roughness <= 1.0)).to(roughness.dtype)
    alpha = rc * rc
    dist, ddist = _ndf_derivative(D, g.nh, alpha)
    vis, dvis = _visibility_derivative(G, g, alpha, D, beckmann_lambda)
    fres, dfres = fresnel_and_derivative(F, f0, g.fresnel_cos)
    w = torch.where(g.front, g.nl.clamp_min(0.0), torch.zeros_like(g.nl))               # the front side's (n·l)⁺
    dv = w * dist * vis                                                                  # [..., 1]
    dr = w * (ddist * vis + dist * dvis) * (4.0 * rc * alpha * inside)                   # ∂(D V (n·l)⁺)/∂r
    value = dv * fres
    return value, (dv * dfres).expand_as(value), (dr * fres).unsqueeze(-1)


# -- models -----------------------------------------------------------------------------------------
#: Fresnel forms under which the BRDF is affine in f0 (a closed-form solve is possible).
_AFFINE_IN_F0 = ("none", "schlick", "sg")


@register("microfacet", "microfacet specular D·F·G/(4 n·l n·v), options D, G, F (Gotanda 2014 eq 1); f0, roughness")
class Microfacet(Model):
    """Specular-only microfacet material (Gotanda 2014 eq 1) with choosable terms.

    Options:
        D: ``ggx`` (default), ``beckmann``, ``blinn-phong``.
        G: ``smith-correlated`` (default), ``smith``, ``cook-torrance``, ``kelemen``, ``neumann``.
        F: ``schlick`` (default), ``none``, ``exact`` (Gotanda eq 2), ``sg`` (eq 3), ``schuler``.
        beckmann_lambda: the Smith Λ of D = beckmann / blinn-phong, ``rational`` (Walter et al. 2007
            eq 27, default; G1 within 0.32 % of exact) or ``exact`` (the erf form).

    Parameters: ``f0`` (RGB), ``roughness`` (α = roughness.roughness_to_alpha(r) = r²).
    """

    def __init__(self, D: str = "ggx", G: str = "smith-correlated", F: str = "schlick",
                 beckmann_lambda: str = "rational"):
        self.D = _choice(D, DISTRIBUTIONS, "microfacet option D")
        self.G = _choice(G, GEOMETRIES, "microfacet option G")
        self.F = _choice(F, tuple(FRESNEL), "microfacet option F")
        self.beckmann_lambda = _choice(beckmann_lambda, BECKMANN_LAMBDAS, "microfacet option beckmann_lambda")
        self.params = (replace(F0, linear=F in _AFFINE_IN_F0), ROUGHNESS)

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        alpha = rough.roughness_to_alpha(p["roughness"])
        return microfacet_specular(g, p["f0"], alpha, D=self.D, G=self.G, F=self.F,
                                   beckmann_lambda=self.beckmann_lambda)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """Closed form for every D, G and named F (:func:`specular_jacobian`); None for a callable F."""
        if not (self.shades_as(Microfacet) and isinstance(self.F, str)):
            return None
        value, df0, dr = specular_jacobian(g, p["f0"], p["roughness"], self.D, self.G, self.F, self.beckmann_lambda)
        return value, {"f0": df0, "roughness": dr}


@register("cook-torrance", "Cook & Torrance 1981: Lambert + Beckmann D, V-cavity G, exact Fresnel from f0")
class CookTorrance(Model):
    """Cook-Torrance 1981: f_r = ρ/π + D_Beckmann F_exact(f0, l·h) G_V-cavity / (4 n·l n·v).

    The two lobes are simply added, as in the original paper (no (1 − F) coupling). Beckmann's m is
    α = roughness² (roughness.roughness_to_alpha); F is the exact dielectric Fresnel from f0
    (Gotanda 2014 eq 2, :func:`materials.fresnel.fresnel_from_f0`).

    Parameters: ``albedo``, ``f0``, ``roughness``.
    """

    params = (ALBEDO, F0, ROUGHNESS)

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        alpha = rough.roughness_to_alpha(p["roughness"])
        spec = microfacet_specular(g, p["f0"], alpha, D="beckmann", G="cook-torrance", F=fresnel_from_f0)
        return lambert(g, p["albedo"]) + spec

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """Lambert's ``ρ (n·l)⁺/π`` plus :func:`specular_jacobian` with D = beckmann, G = cook-torrance, F = exact."""
        if not self.shades_as(CookTorrance):
            return None
        spec, df0, dr = specular_jacobian(g, p["f0"], p["roughness"], D="beckmann", G="cook-torrance", F="exact")
        w = torch.where(g.front, g.nl.clamp_min(0.0) * INV_PI, torch.zeros_like(g.nl))   # Lambert's, as lambert()
        value = p["albedo"] * w + spec
        return value, {"albedo": w.expand_as(value), "f0": df0, "roughness": dr}
