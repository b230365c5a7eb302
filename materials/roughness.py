"""Every roughness parameterisation of the papers, and the exact conversions between them.

The canonical map stores *perceptual roughness* ``r`` in [0, 1] (DESIGN.md). The papers use:

====================  =========================================  =========================
quantity              definition                                 source
====================  =========================================  =========================
``alpha``             GGX / Beckmann width, ``α = r²``           Gotanda 2014 eq 1
``shininess`` ``s``   Blinn-Phong exponent, ``s = 2/α² − 2``     Walter et al. 2007; Gotanda 2010
``sigma`` ``σ``       Oren-Nayar slope deviation, ``σ = √(2/s)`` Gotanda 2012 eq 21
``glossiness`` ``g``  Schüler, ``e = 2^(12 g)``, so ``g = log2(s)/12``  Schüler 2.5, "e = 2^(12g)"
====================  =========================================  =========================

``s = 2/α² − 2`` is the standard Beckmann/Blinn-Phong correspondence: it matches the two
distributions' behaviour near the peak. At r = 1 (α = 1) it gives s = 0, a uniform lobe.

Clamping. Every forward conversion clamps its input to the documented domain and every inverse
undoes it exactly inside the clamped range: ``r -> s -> r`` is the identity for r in
[R_MIN, 1]. ``R_MIN`` keeps s finite (s ≤ S_MAX = 2^16 at r = R_MIN) so that no lobe ever sees an
infinite exponent; glossiness g ∈ [0, 4/3] covers s ∈ [1, 2^16]. All functions are differentiable
with finite gradients over the whole clamped domain, in float32 and float64.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: Largest Blinn-Phong exponent produced by a conversion (Schüler's e = 2^(12g) reaches 2^12 at
#: g = 1; we allow four more octaves for mirror-like surfaces).
S_MAX = 2.0**16
#: Smallest perceptual roughness: the r at which s = S_MAX, i.e. α² = 2/(S_MAX + 2).
R_MIN = (2.0 / (S_MAX + 2.0)) ** 0.25
#: Smallest α (= R_MIN²).
ALPHA_MIN = R_MIN**2


def _t(x) -> Tensor:
    return x if isinstance(x, Tensor) else torch.as_tensor(x, dtype=torch.get_default_dtype())


def roughness_to_alpha(r: Tensor) -> Tensor:
    """Perceptual roughness r ∈ [0, 1] → GGX/Beckmann α = r², clamped to [ALPHA_MIN, 1]."""
    return _t(r).clamp(R_MIN, 1.0).square()


def alpha_to_roughness(alpha: Tensor) -> Tensor:
    """GGX/Beckmann α → perceptual r = √α (α clamped to [ALPHA_MIN, 1])."""
    return _t(alpha).clamp(ALPHA_MIN, 1.0).sqrt()


def alpha_to_shininess(alpha: Tensor) -> Tensor:
    """α → Blinn-Phong exponent s = 2/α² − 2 ∈ [0, S_MAX]."""
    a = _t(alpha).clamp(ALPHA_MIN, 1.0)
    return (2.0 / a.square() - 2.0).clamp(0.0, S_MAX)


def alpha_to_shininess_derivative(alpha: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`alpha_to_shininess` and its derivative ``∂s/∂α = −4/α³``, 0 where a clamp holds (on α or on s) —
    the values and derivatives automatic differentiation gives; for the models' closed-form Jacobians."""
    alpha = _t(alpha)
    a = alpha.clamp(ALPHA_MIN, 1.0)
    raw = 2.0 / a.square() - 2.0
    keep = (alpha >= ALPHA_MIN) & (alpha <= 1.0) & (raw >= 0.0) & (raw <= S_MAX)
    return raw.clamp(0.0, S_MAX), torch.where(keep, -4.0 / (a * a * a), torch.zeros_like(a))


def roughness_to_shininess_derivative(r: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`roughness_to_shininess` and its derivative ``∂s/∂r`` (through α = r², 0 where a clamp holds)."""
    r = _t(r)
    rc = r.clamp(R_MIN, 1.0)
    s, ds = alpha_to_shininess_derivative(rc.square())
    return s, torch.where((r >= R_MIN) & (r <= 1.0), ds * 2.0 * rc, torch.zeros_like(ds))


def shininess_to_alpha(s: Tensor) -> Tensor:
    """Blinn-Phong exponent s ≥ 0 → α = √(2/(s + 2)) (s clamped to [0, S_MAX])."""
    return torch.sqrt(2.0 / (_t(s).clamp(0.0, S_MAX) + 2.0))


def roughness_to_shininess(r: Tensor) -> Tensor:
    """Perceptual r → Blinn-Phong exponent s = 2/r⁴ − 2 (r clamped to [R_MIN, 1])."""
    return alpha_to_shininess(roughness_to_alpha(r))


def shininess_to_roughness(s: Tensor) -> Tensor:
    """Blinn-Phong exponent s → perceptual r = (2/(s + 2))^(1/4)."""
    return alpha_to_roughness(shininess_to_alpha(s))


def shininess_to_sigma(s: Tensor) -> Tensor:
    """Blinn-Phong exponent → Oren-Nayar σ = √(2/s) (Gotanda 2012 eq 21).

    s is clamped to [2, S_MAX] so that σ ∈ [√(2/S_MAX), 1]: σ = 1 (a slope deviation of 45°) is the
    roughest surface the Oren-Nayar fits were made for, and s → 0 would send σ to infinity.
    """
    return torch.sqrt(2.0 / _t(s).clamp(2.0, S_MAX))


def sigma_to_shininess(sigma: Tensor) -> Tensor:
    """Oren-Nayar σ → Blinn-Phong exponent s = 2/σ² (inverse of eq 21; σ clamped to [√(2/S_MAX), 1])."""
    sig = _t(sigma).clamp(math.sqrt(2.0 / S_MAX), 1.0)
    return 2.0 / sig.square()


def roughness_to_sigma(r: Tensor) -> Tensor:
    """Perceptual r → Oren-Nayar σ through s (eq 21). σ = 1 for every r ≥ (1/2)^(1/4) ≈ 0.84."""
    return shininess_to_sigma(roughness_to_shininess(r))


def roughness_to_sigma_derivative(r: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`roughness_to_sigma` and its derivative ``∂σ/∂r = −σ/(2s) · ∂s/∂r`` (σ = √(2/s)), 0 where a clamp holds
    (r outside [R_MIN, 1], s outside [2, S_MAX]: σ = 1 for r ≥ (1/2)^(1/4)) — for the models' closed-form
    Jacobians."""
    s, ds = roughness_to_shininess_derivative(r)
    sc = s.clamp(2.0, S_MAX)
    sigma = torch.sqrt(2.0 / sc)
    keep = (s >= 2.0) & (s <= S_MAX)
    return sigma, torch.where(keep, -0.5 * sigma / sc * ds, torch.zeros_like(ds))


def sigma_to_roughness(sigma: Tensor) -> Tensor:
    """Oren-Nayar σ → perceptual r (inverse of :func:`roughness_to_sigma` on σ < 1)."""
    return shininess_to_roughness(sigma_to_shininess(sigma))


#: Glossiness range: g = log2(s)/12 for s ∈ [1, S_MAX].
G_MAX = math.log2(S_MAX) / 12.0


def glossiness_to_shininess(g: Tensor) -> Tensor:
    """Schüler glossiness g → exponent e = 2^(12 g) (Schüler 2.5, "e = 2^(12g)"), g ∈ [0, G_MAX]."""
    return torch.exp2(12.0 * _t(g).clamp(0.0, G_MAX))


def shininess_to_glossiness(s: Tensor) -> Tensor:
    """Exponent e → Schüler glossiness g = log2(e)/12, e clamped to [1, S_MAX]."""
    return torch.log2(_t(s).clamp(1.0, S_MAX)) / 12.0


def roughness_to_glossiness(r: Tensor) -> Tensor:
    """Perceptual r → Schüler g. r near 1 (s < 1) maps to g = 0, the roughest Schüler surface."""
    return shininess_to_glossiness(roughness_to_shininess(r))


def glossiness_to_roughness(g: Tensor) -> Tensor:
    """Schüler g → perceptual r (inverse of :func:`roughness_to_glossiness` for g ∈ [0, G_MAX])."""
    return shininess_to_roughness(glossiness_to_shininess(g))


def half_max_angle(r: Tensor) -> Tensor:
    """Half-maximum angle θ½ (radians) of the GGX lobe of perceptual roughness ``r`` (α = r²):
    D(θ½)/D(0) = ½ ⇔ cos²θ½ = (1 − √2 α²)/(1 − α²); θ½ ≈ 0.64 α for small α, π/2 once α² ≥ 1/√2.

    Every model here maps roughness to the same α (Blinn-Phong through s = 2/α² − 2, matched at the
    peak), so this is the width of any model's highlight to first order. Float64 for accuracy.
    """
    a2 = (_t(r).double().clamp(0, 1) ** 2) ** 2
    denom = torch.where(a2 < 1 - 1e-12, 1 - a2, torch.ones_like(a2))
    c2 = torch.where(a2 < 1 - 1e-12, (1 - math.sqrt(2) * a2) / denom, torch.zeros_like(a2)).clamp(0, 1)
    return torch.arccos(c2.sqrt())
