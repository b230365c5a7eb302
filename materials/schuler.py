"""Schüler's efficient, physically plausible shading model (Schüler, "An Efficient and Physically
Plausible Real-Time Shading Model", 2.5 and its appendix).

Parameters (canonical maps → the paper's): ``albedo`` = K_diffuse, ``f0`` = K_specular,
``roughness`` r → glossiness g = roughness.roughness_to_glossiness(r) clamped to [0, 1]
(:func:`schuler_glossiness`) → exponent e = 2^(12 g) = roughness.glossiness_to_shininess(g) ∈ [1, 4096]
(= s = 2/r⁴ − 2 clamped to [1, 4096]).

Glossiness range. The paper derives e "from a surface glossiness parameter g in the range 0-1 (rough to
smooth)" (the paragraph after e = 2^(12g)), stores g in a texture channel (the two-RGBA layout, which
:mod:`materials.atlas` writes with g ∈ [0, 1]) and its hemisphere term divides by 1 − g, so g = 1 is its
mirror. Point lights and the two hemispheres therefore share g ∈ [0, 1], e ∈ [1, 2^12]: every
roughness below r = (2/4098)^(1/4) = 0.1487 is Schüler's smoothest surface, e = 4096 (the generic
conversions of :mod:`materials.roughness` reach g = 4/3, e = 2^16, for the other models).

Units. Schüler writes radiance as I = k_diffuse Σ N·L E for Lambert, i.e. his I is π times the
radiance of our convention L = f_r · (n·l) · E (DESIGN.md), in which Lambert is ρ/π. His
distribution D = (1 + e)/2 (N·H)^e integrates to π over the hemisphere (appendix, "normalizing
the Blinn-Phong specular highlight"), so his specular carries the same factor π. Every expression
of the paper is therefore divided by π here, diffuse and specular alike, which keeps the
diffuse/specular balance of the paper and makes the diffuse lobe exactly :func:`lambert`.

Specular variants (the four techniques of the paper's effect file; each lobe returns f_r in 1/sr,
i.e. the paper's I_specular / (π E N·L)):

=============================  =====================================================================
``optimized`` (default)        K_s (1 + e) / (8 π (L·H)³) (N·H)^e — the paper's final formula
``cook-torrance-simplified``   D F G / (4 π N·L N·V), D = (1 + e)/2 (N·H)^e,
                               F = lerp(K_s, min(60 K_s, 1), (1 − L·H)⁴),
                               G = min(2 N·H min(N·V, N·L) / L·H, 1)
``kelemen-szirmay-kalos``      D F / (4 π (L·H)²) (Kelemen's G/(N·L N·V) ≈ 1/(L·H)²)
``cook-torrance-full``         Beckmann D (α = r²), exact Fresnel from K_s (Gotanda 2014 eq 2),
                               V-cavity G: D F G / (4 N·L N·V) with the usual 1/sr Beckmann D
=============================  =====================================================================

Two-hemisphere lighting (paper §"Mathematical formulation"), for a
:class:`materials.environment.HemisphereLight` of irradiances E_upper, E_lower and up vector z:

- diffuse: K_d/π · lerp(E_lower, E_upper, (1 + N·z)/2) — the same as the Lambert model;
- specular: F(g N·V)/π · lerp(E_lower, E_upper, (1 + clamp(R·z/(1 − g), −1, 1))/2), R the mirror
  direction of V, g clamped to [0, 1] (the paper's texture range).

OCR/print reading of the specular hemisphere term: the paper prints the interpolation weight as
``clamp(R·z/(1 − g), −1, 1)``, but defines lerp(a, b, t) for 0 ≤ t ≤ 1; taken literally a
reflection vector pointing down gives 2 E_lower − E_upper (negative radiance when
E_upper > 2 E_lower) and a horizontal one gives E_lower alone. We read it, by analogy with the
diffuse weight (1 + N·z)/2, as t = (1 + clamp(R·z/(1 − g), −1, 1))/2: R up → E_upper, R down →
E_lower, horizontal → the mean, with a transition that sharpens as g → 1.

The Fresnel factor printed as F(g N·V) is, read literally, min(60 K_s, 1) for every view at g = 0:
a fully rough dielectric would mirror the whole environment, the opposite of the paper's own
sentence ("a simplified Fresnel term, scaled such that the highest values are only reached for
smooth surfaces"). The OCR has probably lost an operator. Decision (docs/models-specular.md):
``hemisphere_fresnel="scaled"`` (default) scales the Fresnel rise by g,
lerp(K_s, min(60 K_s, 1), g (1 − N·V)⁴) — K_s for rough surfaces, the full lerp Fresnel for g = 1 —
which is what the sentence describes; ``hemisphere_fresnel="printed"`` keeps F(g·N·V).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

import torch
from torch import Tensor

from . import roughness as rough
from .environment import Environment, HemisphereLight
from .fresnel import fresnel_from_f0, fresnel_schuler
from .geometry import Angles, guarded_pow, guarded_pow_log, reflect
from .lambert import INV_PI, lambert
from .microfacet import COS_EPS, microfacet_specular, visibility_term
from .model import Model, register
from .params import ALBEDO, F0, ROUGHNESS

VARIANTS = ("optimized", "cook-torrance-simplified", "kelemen-szirmay-kalos", "cook-torrance-full")
#: Largest glossiness of the paper ("g in the range 0-1"): e ≤ 2^(12·1) = 4096, for point lights and hemispheres.
SCHULER_G_MAX = 1.0
#: Floor of 1 − g in the hemisphere weight R·z/(1 − g) (g = 1 is a mirror: a hard step).
ONE_MINUS_G_EPS = 1e-6

__all__ = [
    "SCHULER_G_MAX", "VARIANTS", "schuler_glossiness", "schuler_exponent", "schuler_distribution", "schuler_optimized",
    "schuler_cook_torrance_simplified", "schuler_kelemen_szirmay_kalos", "schuler_cook_torrance_full",
    "schuler_specular", "schuler_hemisphere_diffuse", "schuler_hemisphere_specular", "Schuler",
]


def _check(g, f0, fn: str) -> None:
    if not isinstance(g, Angles):
        raise TypeError(f"{fn}: g must be a materials.Angles, got {type(g).__name__}")
    if not isinstance(f0, Tensor):
        raise TypeError(f"{fn}: f0 (K_specular) must be a torch.Tensor [..., C], got {type(f0).__name__}")


def _exponent(e, fn: str) -> Tensor:
    if not isinstance(e, Tensor):
        raise TypeError(f"{fn}: e must be a torch.Tensor [..., 1] (use schuler_exponent(roughness)), "
                        f"got {type(e).__name__}")
    if e.dim() == 0 or e.shape[-1] != 1:
        raise ValueError(f"{fn}: e must have a trailing dimension of size 1, got shape {tuple(e.shape)}")
    return e.clamp(0.0, rough.S_MAX)


def _lh(g: Angles) -> Tensor:
    return g.lh.clamp(COS_EPS, 1.0)


def schuler_glossiness(roughness: Tensor) -> Tensor:
    """Canonical roughness r → Schüler's glossiness g = roughness_to_glossiness(r) clamped to the paper's [0, 1]."""
    return rough.roughness_to_glossiness(roughness).clamp(0.0, SCHULER_G_MAX)


def schuler_exponent(roughness: Tensor) -> Tensor:
    """Canonical roughness r → Schüler's exponent e = 2^(12 g), g = :func:`schuler_glossiness`; e ∈ [1, 4096]."""
    return rough.glossiness_to_shininess(schuler_glossiness(roughness))


def schuler_distribution(nh: Tensor, e: Tensor) -> Tensor:
    """Schüler's normalised Blinn-Phong D / π = (1 + e)/(2π) (N·H)^e in 1/sr, ``[..., 1]``; 0 for N·H ≤ 0.

    The paper's (1 + e)/2 normalises ∫ D dω_h to π (appendix); the microfacet normalisation
    ∫ D (n·h) dω_h = 1 would need (e + 2)/(2π): this D has ∫ D (n·h) dω_h = (1 + e)/(2 + e).
    """
    e = _exponent(e, "schuler_distribution")
    d = (1.0 + e) / (2.0 * math.pi) * guarded_pow(nh.clamp(max=1.0), e)
    return torch.where(nh > 0, d, torch.zeros_like(d))


def schuler_optimized(g: Angles, f0: Tensor, e: Tensor) -> Tensor:
    """Schüler's "Optimized" specular: f_r = K_s (1 + e) / (8 π (L·H)³) (N·H)^e, ``[..., C]`` in 1/sr.

    The paper's final formula I = k_s Σ (1 + e)/(8 (L·H)³) (N·H)^e N·L E, divided by π (module
    docstring). Linear in K_s. L·H is floored at COS_EPS (only reached when n·l and n·v are both
    below 2e-6, since L·H ≥ (n·l + n·v)/2). 0 unless n·l > 0 and n·v > 0.
    """
    _check(g, f0, "schuler_optimized")
    e = _exponent(e, "schuler_optimized")
    inv_lh = 1.0 / _lh(g)
    # times (1/L·H)³ rather than divided by (L·H)³: the backward pass of a division forms num/den², which
    # overflows float32 at L·H ≈ 1e-6 (den² ≈ 1e-36) although the true derivative (∝ 1/(L·H)⁴ ≤ 1e24) is finite
    f = f0 * ((1.0 + e) / (8.0 * math.pi) * guarded_pow(g.nh.clamp(max=1.0), e) * (inv_lh * inv_lh * inv_lh))
    return torch.where(g.front, f, torch.zeros_like(f))


def schuler_cook_torrance_simplified(g: Angles, f0: Tensor, e: Tensor) -> Tensor:
    """Schüler's "CookTorranceSimplified": f_r = D F G / (4 π N·L N·V) with D = (1 + e)/2 (N·H)^e,
    F = lerp(K_s, min(60 K_s, 1), (1 − L·H)⁴), G = min(2 N·H min(N·V, N·L)/L·H, 1) (appendix),
    ``[..., C]`` in 1/sr. G/(4 N·L N·V) is evaluated as the V-cavity visibility of
    :func:`materials.microfacet.visibility_term`.
    """
    _check(g, f0, "schuler_cook_torrance_simplified")
    vis = visibility_term("cook-torrance", g, torch.ones_like(g.nl))
    f = schuler_distribution(g.nh, e) * fresnel_schuler(f0, g.fresnel_cos) * vis
    return torch.where(g.front, f, torch.zeros_like(f))


def schuler_kelemen_szirmay_kalos(g: Angles, f0: Tensor, e: Tensor) -> Tensor:
    """Schüler's "KelemenSzirmayKalos": f_r = D F / (4 π (L·H)²), D and F as in
    :func:`schuler_cook_torrance_simplified` (appendix: I = Σ D F/(4 (L·H)²) N·L E), ``[..., C]``."""
    _check(g, f0, "schuler_kelemen_szirmay_kalos")
    lh = _lh(g)
    f = schuler_distribution(g.nh, e) * fresnel_schuler(f0, g.fresnel_cos) / (4.0 * lh * lh)
    return torch.where(g.front, f, torch.zeros_like(f))


def schuler_cook_torrance_full(g: Angles, f0: Tensor, alpha: Tensor) -> Tensor:
    """Schüler's "CookTorranceFull": the original Cook-Torrance specular D F G/(4 N·L N·V) with
    Beckmann D (width α = r², our convention; the paper's effect file is not available), the full
    Fresnel equations from K_s (Gotanda 2014 eq 2) and the V-cavity G, ``[..., C]`` in 1/sr.
    """
    _check(g, f0, "schuler_cook_torrance_full")
    return microfacet_specular(g, f0, alpha, D="beckmann", G="cook-torrance", F=fresnel_from_f0)


def schuler_specular(g: Angles, f0: Tensor, roughness: Tensor, variant: str = "optimized") -> Tensor:
    """Schüler's specular lobe ``variant`` (one of :data:`VARIANTS`) from canonical roughness, ``[..., C]``."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown Schüler variant {variant!r}; valid choices: {', '.join(VARIANTS)}")
    if variant == "cook-torrance-full":
        return schuler_cook_torrance_full(g, f0, rough.roughness_to_alpha(roughness))
    e = schuler_exponent(roughness)
    lobe = {"optimized": schuler_optimized, "cook-torrance-simplified": schuler_cook_torrance_simplified,
            "kelemen-szirmay-kalos": schuler_kelemen_szirmay_kalos}[variant]
    return lobe(g, f0, e)


def _check_env(env, n, v, fn):
    if not isinstance(env, HemisphereLight):
        raise TypeError(f"{fn}: env must be a HemisphereLight, got {type(env).__name__}")
    for name, x in (("n", n), ("v", v)):
        if not isinstance(x, Tensor) or x.shape[-1] != 3:
            raise ValueError(f"{fn}: {name} must be a tensor [..., 3] of unit vectors, got "
                             f"{getattr(x, 'shape', type(x).__name__)}")


def schuler_hemisphere_diffuse(env: HemisphereLight, n: Tensor, v: Tensor, albedo: Tensor) -> Tensor:
    """Diffuse radiance under two hemispheres: K_d/π · lerp(E_lower, E_upper, (1 + N·z)/2), ``[..., 3]``;
    0 where n·v ≤ 0 (as the Lambert model)."""
    _check_env(env, n, v, "schuler_hemisphere_diffuse")
    e = env.irradiance(n)
    visible = (n * v).sum(-1, keepdim=True) > 0
    return torch.where(visible, albedo * INV_PI * e, torch.zeros_like(e))


HEMISPHERE_FRESNEL = ("scaled", "printed")


def schuler_hemisphere_specular(env: HemisphereLight, n: Tensor, v: Tensor, f0: Tensor, roughness: Tensor,
                                fresnel: str = "scaled") -> Tensor:
    """Specular radiance under two hemispheres (Schüler, I_specular hemisphere, divided by π):
    F/π · lerp(E_lower, E_upper, (1 + clamp(R·z/(1 − g), −1, 1))/2), ``[..., 3]``, with
    F = lerp(K_s, min(60 K_s, 1), g (1 − N·V)⁴) for ``fresnel="scaled"`` (default) or the printed
    F(g N·V) = lerp(K_s, min(60 K_s, 1), (1 − g N·V)⁴) for ``"printed"`` (module docstring).

    R = 2 (N·V) N − V; g = :func:`schuler_glossiness` (∈ [0, 1], as for point lights); F = Schüler's lerp Fresnel.
    See the module docstring for the reading of the interpolation weight. 0 where n·v ≤ 0.
    A uniform environment (E_upper = E_lower = E, radiance E/π) gives F(g N·V) · E/π: a mirror of
    reflectance F, as expected.
    """
    _check_env(env, n, v, "schuler_hemisphere_specular")
    nv = (n * v).sum(-1, keepdim=True)
    glos = schuler_glossiness(roughness)
    r = reflect(v, n)
    rz = (r * env.up.to(r)).sum(-1, keepdim=True)
    t = 0.5 * (1.0 + (rz / (1.0 - glos).clamp_min(ONE_MINUS_G_EPS)).clamp(-1.0, 1.0))
    lo, hi = env.lower.to(r), env.upper.to(r)
    e = lo + t * (hi - lo)
    if fresnel not in HEMISPHERE_FRESNEL:
        raise ValueError(f"unknown hemisphere Fresnel reading {fresnel!r}; valid: {', '.join(HEMISPHERE_FRESNEL)}")
    if fresnel == "printed":
        fres = fresnel_schuler(f0, glos * nv.clamp(0.0, 1.0))
    else:
        rise = glos * (1.0 - nv.clamp(0.0, 1.0)).pow(4)
        fres = f0 + (torch.clamp(60.0 * f0, max=1.0) - f0) * rise
    out = fres * INV_PI * e
    return torch.where(nv > 0, out, torch.zeros_like(out))


@register("schuler", "Schüler 2.5: Lambert + optimized (1+e)/(8(l·h)³)(n·h)^e specular, option variant; "
                     "two-hemisphere lighting")
class Schuler(Model):
    """Schüler's shading model: Lambert diffuse (K_d/π) + a specular variant, and the two-hemisphere
    environment response.

    Options:
        variant: ``optimized`` (default), ``cook-torrance-simplified``, ``kelemen-szirmay-kalos``,
            ``cook-torrance-full`` (see :data:`VARIANTS` and the module docstring).

    Parameters: ``albedo`` (K_diffuse), ``f0`` (K_specular), ``roughness`` (g = :func:`schuler_glossiness`,
    the paper's [0, 1], for point lights and hemispheres alike).
    """

    def __init__(self, variant: str = "optimized", hemisphere_fresnel: str = "scaled"):
        if variant not in VARIANTS:
            raise ValueError(f"unknown Schüler variant {variant!r}; valid choices: {', '.join(VARIANTS)}")
        if hemisphere_fresnel not in HEMISPHERE_FRESNEL:
            valid = ", ".join(HEMISPHERE_FRESNEL)
            raise ValueError(f"unknown hemisphere_fresnel {hemisphere_fresnel!r}; valid: {valid}")
        self.variant = variant
        self.hemisphere_fresnel = hemisphere_fresnel
        self.params = (ALBEDO, replace(F0, linear=variant == "optimized"), ROUGHNESS)

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        spec = schuler_specular(g, p["f0"], p["roughness"], self.variant)
        return lambert(g, p["albedo"]) + spec

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The ``optimized`` variant in closed form (the others: None, automatic differentiation): ``(K_d/π + K_s k)
        (n·l)⁺`` with ``k = (1 + e)/(8π) (N·H)^e / (L·H)³``, K_d and K_s per channel (diagonal derivatives), and
        ``∂k/∂e = ((N·H)^e + (1 + e)(N·H)^e ln N·H)/(8π (L·H)³)``; ``e = 2^(12 g) = s`` wherever neither g's clamp to
        [0, 1] nor s's to [1, S_MAX] holds, so ``∂e/∂r = ∂s/∂r`` there (0 elsewhere)."""
        if self.variant != "optimized" or not self.shades_as(Schuler):
            return None
        f0 = p["f0"]
        nl = g.nl.clamp_min(0.0)
        value = self.brdf(g, p) * nl                                    # (as Model.cosine_brdf computes it)
        s, ds = rough.roughness_to_shininess_derivative(p["roughness"])
        e = schuler_exponent(p["roughness"])
        keep = (s >= 1.0) & (s <= 2.0 ** (12.0 * SCHULER_G_MAX))
        de = torch.where(keep, e / s.clamp_min(1.0) * ds, torch.zeros_like(ds))
        power, log_nh = guarded_pow_log(g.nh.clamp(max=1.0), e)
        inv_lh = 1.0 / _lh(g)
        scale = inv_lh * inv_lh * inv_lh / (8.0 * math.pi)
        w = torch.where(g.front, nl, torch.zeros_like(nl))                # (n·l)⁺ on the front side
        k = (1.0 + e) * power * scale * w
        dk = (power + (1.0 + e) * power * log_nh) * scale * w * de
        return value, {"albedo": (INV_PI * w).expand_as(value), "f0": k.expand_as(value),
                       "roughness": (f0 * dk).unsqueeze(-1)}

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        """Two-hemisphere radiance (diffuse + specular, module docstring); other environments raise."""
        if not isinstance(env, HemisphereLight):
            return super().environment(env, n, v, p)
        return (schuler_hemisphere_diffuse(env, n, v, p["albedo"])
                + schuler_hemisphere_specular(env, n, v, p["f0"], p["roughness"], self.hemisphere_fresnel))
