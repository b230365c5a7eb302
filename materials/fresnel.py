"""Every Fresnel reflectance of the papers: Schlick, exact dielectric (from η or from f0), spherical
Gaussian, complex-index conductor, Schüler's lerp, and none.

Conventions (docs/architecture.md, "Fresnel API"):

- cosines come as ``[..., 1]`` (the cosine of the angle between the incident direction and the
  (micro)surface normal: ``l·h`` inside a microfacet BRDF, ``n·v`` for a macro-surface) and are
  clamped to [0, 1] inside, so back-facing or slightly negative cosines read as grazing;
- reflectances ``f0`` come as ``[..., C]`` (usually C = 3, linear RGB) in [0, 1]; indices ``eta``
  and extinction coefficients ``k`` as ``[..., C]`` or ``[..., 1]``;
- every function returns the unpolarised reflectance ``[..., C]`` in [0, 1] (broadcast shape of
  its inputs), with finite value and gradient everywhere in that domain, including cos = 0,
  f0 = 0, f0 = 1, η = 1 and total internal reflection.

``FRESNEL`` maps the names a model option uses (``none, schlick, exact, sg, schuler``) to
callables ``f(f0, cos)``.

OCR reading of Gotanda 2014 eq 2 (checked, see :func:`fresnel_from_f0`): the OCR prints
``α = sqrt(1 − (√f0 − 1)² (1 − cos²θ) / (√f0 + 1)²)``; with η = (1 + √f0)/(1 − √f0) this is
``sqrt(1 − sin²θ / η²) = cos θ_t``, the cosine of the refracted angle, and the two squared ratios
of eq 2 are then exactly r_p and r_s of the Fresnel equations. The OCR is therefore correct as
printed; ``tests/materials/test_fresnel.py`` checks eq 2 against :func:`fresnel_dielectric` to 1e-6.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

#: Smallest f0 fed to a square root (the gradient of √f0 is infinite at 0). f0 below this is
#: treated as F0_EPS: the reflectance is then < 1e-12 anyway and its f0-gradient is 0.
F0_EPS = 1e-12
#: Largest f0 used by :func:`ior_from_f0`, so that the returned index stays finite
#: (η(F0_MAX) ≈ 4.0e12 in float64; float32 rounds F0_MAX to 1 and the denominator floor of
#: :func:`ior_from_f0` then gives η ≈ 3.4e7).
F0_MAX = 1.0 - 1e-12
#: Below this a quantity under a square root, or a denominator, is treated as zero.
_TINY = 1e-30

__all__ = [
    "FRESNEL", "f0_from_ior", "ior_from_f0", "fresnel_schlick", "fresnel_dielectric", "fresnel_from_f0",
    "fresnel_spherical_gaussian", "fresnel_conductor", "fresnel_schuler", "fresnel_none", "get_fresnel",
    "fresnel_and_derivative", "fresnel_dielectric_and_derivative",
]


# -- validation helpers --------------------------------------------------------------------------
def _tensor(x, name: str, fn: str) -> Tensor:
    if isinstance(x, Tensor):
        return x
    if isinstance(x, (int, float)):
        return torch.as_tensor(float(x), dtype=torch.get_default_dtype())
    raise TypeError(f"{fn}: {name} must be a torch.Tensor or a float, got {type(x).__name__}")


def _cos(cos, fn: str) -> Tensor:
    """Validate a cosine ``[..., 1]`` and clamp it to [0, 1]."""
    cos = _tensor(cos, "cos", fn)
    if cos.dim() == 0:
        cos = cos.reshape(1)
    if cos.shape[-1] != 1:
        raise ValueError(
            f"{fn}: cos must have a trailing dimension of size 1 ([..., 1]), got shape {tuple(cos.shape)}; "
            f"use x.unsqueeze(-1)"
        )
    return cos.clamp(0.0, 1.0)


def _refl(x, name: str, fn: str) -> Tensor:
    x = _tensor(x, name, fn)
    return x.reshape(1) if x.dim() == 0 else x


def _sqrt0(x: Tensor) -> Tensor:
    """√max(x, 0) with a finite gradient everywhere (0 at x ≤ _TINY): the double-``where`` trick."""
    ok = x > _TINY
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x))


def _div(num: Tensor, den: Tensor, fallback: Tensor | float) -> Tensor:
    """``num / den`` where ``|den| > _TINY``, else ``fallback`` — finite value and gradient."""
    ok = den.abs() > _TINY
    out = num / torch.where(ok, den, torch.ones_like(den))
    return torch.where(ok, out, torch.as_tensor(fallback, dtype=out.dtype, device=out.device).expand_as(out))


# -- conversions -----------------------------------------------------------------------------------
def f0_from_ior(eta) -> Tensor:
    """Reflectance at normal incidence of a dielectric of relative index η: ((η − 1)/(η + 1))².

    Args:
        eta: relative refractive index η > 0 (η = n_material / n_outside), any shape.

    Returns:
        f0 ∈ [0, 1), same shape. η and 1/η give the same f0.
    """
    eta = _tensor(eta, "eta", "f0_from_ior")
    if not torch.isfinite(eta).all() or (eta <= 0).any():
        raise ValueError("f0_from_ior: eta must be finite and > 0 (a relative refractive index); got "
                         f"values in [{eta.min().item():.6g}, {eta.max().item():.6g}]")
    return ((eta - 1.0) / (eta + 1.0)).square()


def ior_from_f0(f0) -> Tensor:
    """Inverse of :func:`f0_from_ior` on η ≥ 1: η = (1 + √f0)/(1 − √f0).

    Args:
        f0: reflectance at normal incidence ∈ [0, 1], any shape; clamped to [0, F0_MAX] so that η
            stays finite (f0 = 1, a perfect mirror, maps to a huge finite η).

    Returns:
        η ≥ 1, same shape; ``f0_from_ior(ior_from_f0(f0)) == f0`` inside the clamped range.
    """
    f0 = _tensor(f0, "f0", "ior_from_f0")
    s = torch.sqrt(f0.clamp(F0_EPS, F0_MAX))
    s = torch.where(f0 <= 0, torch.zeros_like(s), s)
    return (1.0 + s) / (1.0 - s).clamp_min(torch.finfo(s.dtype).eps * 0.5)


# -- Fresnel forms ---------------------------------------------------------------------------------
def fresnel_none(f0, cos) -> Tensor:
    """No Fresnel effect: returns f0 broadcast against cos (``[..., C]``)."""
    f0 = _refl(f0, "f0", "fresnel_none")
    cos = _cos(cos, "fresnel_none")
    return f0 * torch.ones_like(cos)


def fresnel_schlick(f0, cos) -> Tensor:
    """Schlick's approximation F = f0 + (1 − f0)(1 − cos)^5 (Gotanda 2014 §2, "the Schlick
    approximation"; Schlick 1994).

    Args:
        f0: reflectance at normal incidence ``[..., C]`` in [0, 1].
        cos: cosine of the incidence angle on the (micro)facet ``[..., 1]`` (clamped to [0, 1]).

    Returns:
        ``[..., C]`` in [f0, 1]: f0 at cos = 1, exactly 1 at cos = 0.
    """
    f0 = _refl(f0, "f0", "fresnel_schlick")
    c = _cos(cos, "fresnel_schlick")
    return f0 + (1.0 - f0) * (1.0 - c).pow(5)


def fresnel_dielectric(eta, cos) -> Tensor:
    """Exact unpolarised Fresnel reflectance of a dielectric interface, F = (r_s² + r_p²)/2.

    With c = cos θ_i, sin²θ_t = (1 − c²)/η², c_t = cos θ_t:
    r_s = (c − η c_t)/(c + η c_t), r_p = (η c − c_t)/(η c + c_t).

    Args:
        eta: relative index η = n_transmitted / n_incident > 0, ``[..., C]`` or ``[..., 1]``.
            η < 1 (light leaving the denser medium) is allowed: past the critical angle
            (sin²θ_t ≥ 1) total internal reflection gives exactly 1. η = 1 gives 0 everywhere
            (no interface).
        cos: cosine of the incidence angle ``[..., 1]`` (clamped to [0, 1]).

    Returns:
        ``[..., C]`` in [0, 1]; ((η − 1)/(η + 1))² at cos = 1, 1 at cos = 0 (η ≠ 1).
    """
    eta, c, ct2, ct = _refracted(eta, cos, "fresnel_dielectric")
    tir = ct2 <= 0.0
    rs = _div(c - eta * ct, c + eta * ct, 1.0)
    rp = _div(eta * c - ct, eta * c + ct, 1.0)
    f = 0.5 * (rs.square() + rp.square())
    f = torch.where(tir, torch.ones_like(f), f)
    return torch.where(eta == 1.0, torch.zeros_like(f), f).clamp(0.0, 1.0)


def _refracted(eta, cos, fn: str) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(η, c, cos²θ_t, cos θ_t)`` of :func:`fresnel_dielectric` with ``η`` and ``cos`` checked (``fn`` names the
    caller), ``c`` clamped to [0, 1] and ``cos θ_t`` 0 past the critical angle."""
    eta = _refl(eta, "eta", fn)
    c = _cos(cos, fn)
    if not torch.isfinite(eta).all() or (eta <= 0).any():
        raise ValueError(f"{fn}: eta must be finite and > 0 (a relative refractive index), got "
                         f"values in [{eta.min().item():.6g}, {eta.max().item():.6g}]")
    # cos²θ_t = 1 − sin²θ_t = ((η − 1)(η + 1) + c²)/η², without the cancellation of 1 − (1 − c²)/η²: at grazing
    # incidence with η ≈ 1 float32 lost c² in 1 − c² (η 1.000001, c 1e-4: F 0.7482 against 0.7487 in float64)
    ct2 = ((eta - 1.0) * (eta + 1.0) + c * c) / (eta * eta)
    return eta, c, ct2, _sqrt0(ct2)


def fresnel_from_f0(f0, cos) -> Tensor:
    """Exact dielectric Fresnel parameterised by the normal-incidence reflectance (Gotanda 2014 eq 2).

    With s = √f0 and c = cos θ::

        F = ½ { [((s+1) c + (s−1) a) / ((s+1) c − (s−1) a)]² + [((s−1) c + (s+1) a) / ((s−1) c − (s+1) a)]² },
        a = √(1 − (s − 1)² (1 − c²) / (s + 1)²).

    OCR reading: a (printed α) is ``cos θ_t`` for η = (1 + s)/(1 − s); the first ratio is r_p and the
    second r_s, so eq 2 equals ``fresnel_dielectric(ior_from_f0(f0), cos)`` — verified in the tests.
    Written in s rather than η so that f0 = 1 (η = ∞) is exact: F ≡ 1.

    Args:
        f0: reflectance at normal incidence ``[..., C]`` in [0, 1]. f0 ≤ F0_EPS = 1e-12 is treated
            as no interface (η = 1) and returns exactly 0, also at cos = 0, where any η ≠ 1 gives 1:
            this keeps float32 (where such an f0 underflows) and float64 in agreement.
        cos: ``[..., 1]`` (clamped to [0, 1]).

    Returns:
        ``[..., C]`` in [0, 1]: f0 at cos = 1, 1 at cos = 0 (f0 > 0).
    """
    fn = "fresnel_from_f0"
    f0 = _refl(f0, "f0", fn)
    c = _cos(cos, fn)
    s = torch.sqrt(f0.clamp(F0_EPS, 1.0))
    q = ((1.0 - s) / (1.0 + s)).square()  # 1/η²
    # cos²θ_t = 1 − q (1 − c²) = (1 − q) + q c² with 1 − q = 4s / (1 + s)², without the cancellation of 1 − q(1 − c²)
    # when f0 is tiny (q → 1): float32 lost it at grazing incidence (f0 1e-9, c 0.0061: F 0.124156 against 0.124131)
    a = _sqrt0(4.0 * s / (1.0 + s).square() + q * c * c)  # cos θ_t
    rp = _div((s + 1.0) * c + (s - 1.0) * a, (s + 1.0) * c - (s - 1.0) * a, 1.0)
    rs = _div((s - 1.0) * c + (s + 1.0) * a, (s - 1.0) * c - (s + 1.0) * a, 1.0)
    f = 0.5 * (rp.square() + rs.square())
    return torch.where(f0 <= F0_EPS, torch.zeros_like(f), f).clamp(0.0, 1.0)


def fresnel_spherical_gaussian(f0, cos) -> Tensor:
    """Gotanda's spherical-Gaussian Fresnel, fitted to η = 1.5 (Gotanda 2014 eq 3):
    F = f0 + (1 − f0) · 2^(−9.60232 cos⁸θ − 8.58092 cos θ).

    Exactly 1 at cos = 0 and f0 + (1 − f0)·3.4e-6 at cos = 1 (the fit does not reach f0 exactly).

    Args:
        f0: ``[..., C]`` in [0, 1].
        cos: ``[..., 1]`` (clamped to [0, 1]).
    """
    f0 = _refl(f0, "f0", "fresnel_spherical_gaussian")
    c = _cos(cos, "fresnel_spherical_gaussian")
    return f0 + (1.0 - f0) * torch.exp2(-9.60232 * c.pow(8) - 8.58092 * c)


def fresnel_conductor(eta, k, cos) -> Tensor:
    """Exact unpolarised Fresnel reflectance for a complex relative index η + iκ (conductor).

    The closed form of the Fresnel equations with a complex index (e.g. pbrt's FrConductor,
    Cook & Torrance 1981): with c = cos θ, s² = 1 − c²,
    t0 = η² − κ² − s², a²+b² = √(t0² + 4η²κ²), a = √((a²+b² + t0)/2),
    R_s = (a²+b² + c² − 2ac)/(a²+b² + c² + 2ac),
    R_p = R_s (c²(a²+b²) + s⁴ − 2acs²)/(c²(a²+b²) + s⁴ + 2acs²), F = (R_s + R_p)/2.

    a² is evaluated as t1²/(2(a²+b² − t0)) with t1 = 2ηκ where t0 < 0 (no cancellation).
    At normal incidence F = ((η − 1)² + κ²)/((η + 1)² + κ²). With κ = 0 it equals
    :func:`fresnel_dielectric` (total internal reflection included). Written with ``hypot`` so
    that large κ (up to ~1e18 in float32) does not overflow.

    Args:
        eta: real part η > 0 of the relative index, ``[..., C]`` or ``[..., 1]``.
        k: extinction coefficient κ ≥ 0, same broadcasting.
        cos: ``[..., 1]`` (clamped to [0, 1]).

    Returns:
        ``[..., C]`` in [0, 1].
    """
    fn = "fresnel_conductor"
    eta = _refl(eta, "eta", fn)
    k = _refl(k, "k", fn)
    c = _cos(cos, fn)
    if not torch.isfinite(eta).all() or (eta <= 0).any():
        raise ValueError(f"{fn}: eta must be finite and > 0 (real part of the index), got "
                         f"values in [{eta.min().item():.6g}, {eta.max().item():.6g}]")
    if not torch.isfinite(k).all() or (k < 0).any():
        raise ValueError(f"{fn}: k must be finite and >= 0 (extinction coefficient), got "
                         f"values in [{k.min().item():.6g}, {k.max().item():.6g}]")
    c2 = c * c
    s2 = 1.0 - c2
    # t0 = η² − κ² − s² written as (η − 1)(η + 1) − κ² + c²: at grazing incidence with η ≈ 1 the direct form loses
    # c² (1 − c² rounds to 1 in float32 for c < 2.4e-4; η = 1, κ = 1e-6, c = 6.1e-5 gave F 0.8852 against 0.8851)
    t0 = (eta - 1.0) * (eta + 1.0) - k * k + c2
    t1 = 2.0 * eta * k
    ok = (t0.abs() + t1.abs()) > _TINY
    ab2 = torch.where(ok, torch.hypot(torch.where(ok, t0, torch.ones_like(t0)), t1), torch.zeros_like(t0))
    # a² = (|z| + t0)/2 cancels when t0 < 0 (η < 1 past the critical angle, small κ); there the
    # algebraically equal t1²/(2(|z| − t0)) keeps float32 within a few ulps of float64.
    neg = t0 < 0
    a2 = torch.where(neg, 0.5 * t1 * t1 / torch.where(neg, ab2 - t0, torch.ones_like(t0)), 0.5 * (ab2 + t0))
    a = _sqrt0(a2)
    two_ac = 2.0 * a * c
    rs = _div(ab2 + c2 - two_ac, ab2 + c2 + two_ac, 1.0)
    t3 = c2 * ab2 + s2 * s2
    t4 = two_ac * s2
    rp = rs * _div(t3 - t4, t3 + t4, 1.0)
    f = 0.5 * (rs + rp)
    no_interface = (eta == 1.0) & (k == 0.0)  # as fresnel_dielectric: 0 even at cos = 0
    return torch.where(no_interface, torch.zeros_like(f), f).clamp(0.0, 1.0)


def fresnel_schuler(f0, cos) -> Tensor:
    """Schüler's simplified Fresnel: F(t) = lerp(f0, min(60 f0, 1), (1 − t)⁴) (Schüler 2.5).

    Not an approximation of the Fresnel equations at grazing: it rises to min(60 f0, 1) (so a
    dielectric with f0 < 1/60 never reaches 1), and it is linear in f0 below f0 = 1/60.

    Args:
        f0: ``[..., C]`` in [0, 1] (Schüler's K_specular).
        cos: ``[..., 1]`` (clamped to [0, 1]); l·h for a light, g·(n·v) for the hemisphere.
    """
    f0 = _refl(f0, "f0", "fresnel_schuler")
    c = _cos(cos, "fresnel_schuler")
    hi = torch.minimum(60.0 * f0, torch.ones_like(f0))
    return f0 + (hi - f0) * (1.0 - c).pow(4)


#: The Fresnel forms a model can choose by name, each ``f(f0 [..., C], cos [..., 1]) -> [..., C]``.
FRESNEL: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "none": fresnel_none,
    "schlick": fresnel_schlick,
    "exact": fresnel_from_f0,
    "sg": fresnel_spherical_gaussian,
    "schuler": fresnel_schuler,
}


def fresnel_and_derivative(name: str, f0: Tensor, cos: Tensor) -> tuple[Tensor, Tensor]:
    """The Fresnel form ``name`` (a key of :data:`FRESNEL`) and its derivative in f0, channel by channel, in
    closed form: ``(F [..., C], ∂F/∂f0)``, the derivative ``[..., C]``, or ``[..., 1]`` where it is the same for
    every channel (``none``, ``schlick``, ``sg``), the values and derivatives automatic differentiation of
    ``FRESNEL[name](f0, cos)`` gives (clamps included: 0 where one holds f0), for a model's closed-form Jacobian.

    - ``none``: 1; ``schlick``: ``1 − (1 − c)⁵``; ``sg``: ``1 − 2^(−9.60232 c⁸ − 8.58092 c)``;
    - ``schuler``: ``1 − t + t ∂min(60 f0, 1)/∂f0`` with ``t = (1 − c)⁴`` (60 below f0 = 1/60, 0 above, 30 at it
      — torch's ``minimum`` splits a tie);
    - ``exact`` (:func:`fresnel_from_f0`): with ``s = √f0``, ``u = 1 + s``, ``m = s − 1``, ``q = m²/u²`` and
      ``k = 4s/u²`` (``∂q/∂s = −∂k/∂s = 4m/u³``), ``a = √(k + q c²)`` has ``∂a/∂s = 2m(c² − 1)/(u³ a)``;
      ``F = (r_p² + r_s²)/2`` with ``r_p = (uc + ma)/(uc − ma)``, ``r_s = (mc + ua)/(mc − ua)`` differentiated as
      quotients, and ``∂s/∂f0 = 1/(2s)``.
    """
    if name not in FRESNEL:
        raise ValueError(f"unknown Fresnel form {name!r}; choose one of {sorted(FRESNEL)}")
    fn = "fresnel_and_derivative"
    f0 = _refl(f0, "f0", fn)
    c = _cos(cos, fn)
    if name == "none":
        return (f0 if f0.shape[:-1] == c.shape[:-1] else f0 * torch.ones_like(c)), torch.ones_like(c)
    if name in ("schlick", "sg"):
        t = (1.0 - c).pow(5) if name == "schlick" else torch.exp2(-9.60232 * c.pow(8) - 8.58092 * c)
        return f0 + (1.0 - f0) * t, 1.0 - t
    if name == "schuler":
        t = (1.0 - c).pow(4)
        f60 = 60.0 * f0
        hi = torch.minimum(f60, torch.ones_like(f0))
        dhi = torch.where(f60 < 1.0, 60.0, torch.where(f60 == 1.0, 30.0, 0.0)).to(f0.dtype)
        return f0 + (hi - f0) * t, 1.0 - t + t * dhi
    # exact: as fresnel_from_f0, with the derivative of each of its steps
    inside = ((f0 >= F0_EPS) & (f0 <= 1.0)).to(f0.dtype)                      # where the clamp passes f0 on
    s = torch.sqrt(f0.clamp(F0_EPS, 1.0))
    u, m = 1.0 + s, s - 1.0
    q = (-m / u).square()
    a2 = 4.0 * s / u.square() + q * c * c
    a = _sqrt0(a2)
    ok_a = a2 > _TINY
    da = torch.where(ok_a, 2.0 * m * (c * c - 1.0) / (u.pow(3) * torch.where(ok_a, a, torch.ones_like(a))),
                     torch.zeros_like(a))
    rp, drp = _quotient(u * c + m * a, u * c - m * a, c + a + m * da, c - a - m * da)
    rs, drs = _quotient(m * c + u * a, m * c - u * a, c + a + u * da, c - a - u * da)
    f = 0.5 * (rp.square() + rs.square())
    df = (rp * drp + rs * drs) * 0.5 / s * inside
    live = (f0 > F0_EPS) & (f >= 0.0) & (f <= 1.0)
    return (torch.where(f0 <= F0_EPS, torch.zeros_like(f), f).clamp(0.0, 1.0),
            torch.where(live, df, torch.zeros_like(df)))


def fresnel_dielectric_and_derivative(eta: Tensor, cos: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`fresnel_dielectric` and its derivative in η, in closed form (0 where total internal reflection, η = 1
    or the final clamp holds — the derivatives automatic differentiation gives), for a model's closed-form Jacobian.

    With ``q = c_t² = 1 − (1 − c²)/η²``, ``∂q/∂η = 2(1 − c²)/η³`` and ``∂c_t/∂η = ∂q/∂η / (2c_t)``;
    ``r_s = (c − ηc_t)/(c + ηc_t)`` and ``r_p = (ηc − c_t)/(ηc + c_t)`` differentiated as quotients;
    ``∂F/∂η = r_s ∂r_s/∂η + r_p ∂r_p/∂η``."""
    eta, c, ct2, ct = _refracted(eta, cos, "fresnel_dielectric_and_derivative")
    tir = ct2 <= 0.0
    ok_t = ct2 > _TINY
    dct = torch.where(ok_t, (1.0 - c * c) / (eta * eta * eta * torch.where(ok_t, ct, torch.ones_like(ct))),
                      torch.zeros_like(ct))
    rs, drs = _quotient(c - eta * ct, c + eta * ct, -(ct + eta * dct), ct + eta * dct)
    rp, drp = _quotient(eta * c - ct, eta * c + ct, c - dct, c + dct)
    f = 0.5 * (rs.square() + rp.square())
    df = rs * drs + rp * drp
    f = torch.where(tir, torch.ones_like(f), f)
    live = ~tir & (eta != 1.0) & (f >= 0.0) & (f <= 1.0)
    return (torch.where(eta == 1.0, torch.zeros_like(f), f).clamp(0.0, 1.0),
            torch.where(live, df, torch.zeros_like(df)))


def _quotient(num: Tensor, den: Tensor, dnum: Tensor, dden: Tensor) -> tuple[Tensor, Tensor]:
    """``num / den`` as :func:`_div` with fallback 1, and its derivative from ``dnum``, ``dden`` (0 where the
    fallback holds)."""
    ok = den.abs() > _TINY
    safe = torch.where(ok, den, torch.ones_like(den))
    value = torch.where(ok, num / safe, torch.ones_like(num))
    return value, torch.where(ok, (dnum * safe - num * dden) / (safe * safe), torch.zeros_like(num))


def get_fresnel(name: str) -> Callable[[Tensor, Tensor], Tensor]:
    """The Fresnel form called ``name`` (a key of :data:`FRESNEL`); unknown names list the valid ones."""
    if name not in FRESNEL:
        raise ValueError(f"unknown Fresnel form {name!r}; choose one of {sorted(FRESNEL)}")
    return FRESNEL[name]
