"""Nielsen, Frisvad, Conradsen, Aanæs, "Addressing Grazing Angle Reflections in Phong Models".

Three Phong variants, each with the Lambert diffuse term of the paper's equations:

- eq 1, modified Phong:        f = ρ_d/π + ρ_s R_F (s + 2)/(2π) (r·v)^s
- eq 2, modified Blinn-Phong:  f = ρ_d/π + ρ_s R_F (s + 8)/(8π) (n·h)^s
- eq 3, the mixture:           f = ρ_d/π + k_s R_F ((1 − α) r·v + α (n·h)^4)^s

with r = 2(n·l)n − l the mirror direction of the light (so r·v = 2 (n·l)(n·v) − l·v, no vector
needed), h the half vector and R_F(l·h, η) the exact unpolarised dielectric Fresnel reflectance
(:func:`materials.fresnel.fresnel_dielectric`). The paper multiplies ρ_s (eq 1-2, "As in previous
work ... multiply the specular reflectance ρ_s by the Fresnel reflectance") and k_s (eq 3, "We
multiply k_s by R_F") by R_F; eq 1-2 take ``fresnel=False`` to drop it (the textbook forms).

Parameterisation (canonical maps, DESIGN.md): ``albedo`` = ρ_d; ``roughness`` → s through
:func:`materials.roughness.roughness_to_shininess`; ``specular`` = ρ_s (eq 1-2) or k_s (eq 3),
RGB, linear — Nielsen's ρ_s and k_s are not f0 (f0 is R_F at normal incidence, set by η);
``ior`` = η; ``mix`` = α of eq 3. Note that in eq 3 k_s absorbs the normalisation, so k_s ≈
ρ_s (s + ε)/(sπ) — a mirror-like surface has a large k_s.

Negative bases ((r·v) < 0 behind the mirror direction, or the mixture's base) are clamped at 0
(:func:`materials.geometry.guarded_pow`). At α = 1 the mixture is ((n·h)^4)^s = (n·h)^(4s): a
Blinn-Phong lobe of exponent 4s without eq 2's normalisation — not eq 2 (the 4th power is the
paper's "the Phong exponent is roughly 4 times stronger than the Blinn-Phong exponent"). At α = 0
it is k_s R_F (r·v)^s. All three are reciprocal (r·v, n·h and l·h are symmetric in l and v).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from . import fresnel as _fresnel
from .environment import Environment, HemisphereLight, SHLight
from .geometry import POW_EPS, Angles, guarded_pow, guarded_pow_log
from .lambert import INV_PI
from .model import Model, register
from .params import ALBEDO, IOR, MIX, ROUGHNESS, SPECULAR
from .roughness import roughness_to_shininess, roughness_to_shininess_derivative


def _check(g, where: str, **tensors) -> None:
    if not isinstance(g, Angles):
        raise TypeError(f"{where}: g must be a materials.geometry.Angles, got {type(g).__name__}")
    for name, x in tensors.items():
        if not isinstance(x, Tensor):
            raise TypeError(f"{where}: {name} must be a torch.Tensor, got {type(x).__name__}")


def _masked(g: Angles, val: Tensor) -> Tensor:
    return torch.where(g.front, val, torch.zeros_like(val))


def nielsen_fresnel(g: Angles, ior: Tensor) -> Tensor:
    """R_F(l·h, η): exact dielectric Fresnel at the microfacet angle, ``[..., 1]``."""
    _check(g, "nielsen_fresnel", ior=ior)
    return _fresnel.fresnel_dielectric(ior, g.fresnel_cos)


def modified_phong(g: Angles, rho_s: Tensor, shininess: Tensor) -> Tensor:
    """Specular term of Nielsen eq 1: ρ_s (s + 2)/(2π) (r·v)^s, 1/sr, ``[..., C]`` (no Fresnel).

    Args:
        g: shading cosines ``[..., 1]``; r·v = 2 (n·l)(n·v) − l·v.
        rho_s: specular reflectance ρ_s ≥ 0, ``[..., C]``.
        shininess: exponent s ≥ 0, ``[..., 1]``.
    """
    _check(g, "modified_phong", rho_s=rho_s, shininess=shininess)
    val = rho_s * (shininess + 2.0) / (2.0 * math.pi) * guarded_pow(g.rv, shininess)
    return _masked(g, val)


def modified_blinn_phong(g: Angles, rho_s: Tensor, shininess: Tensor) -> Tensor:
    """Specular term of Nielsen eq 2: ρ_s (s + 8)/(8π) (n·h)^s, 1/sr, ``[..., C]`` (no Fresnel)."""
    _check(g, "modified_blinn_phong", rho_s=rho_s, shininess=shininess)
    val = rho_s * (shininess + 8.0) / (8.0 * math.pi) * guarded_pow(g.nh, shininess)
    return _masked(g, val)


def mixture_base(g: Angles, mix: Tensor) -> Tensor:
    """The base of Nielsen eq 3: (1 − α) r·v + α (n·h)^4, ``[..., 1]`` (may be negative)."""
    _check(g, "mixture_base", mix=mix)
    nh4 = g.nh.clamp_min(0.0).square().square()
    return (1.0 - mix) * g.rv + mix * nh4


def mixture(g: Angles, k_s: Tensor, shininess: Tensor, mix: Tensor) -> Tensor:
    """Specular term of Nielsen eq 3: k_s ((1 − α) r·v + α (n·h)^4)^s, 1/sr, ``[..., C]`` (no Fresnel).

    Args:
        k_s: specular coefficient (absorbs the normalisation), ≥ 0, ``[..., C]``.
        shininess: exponent s ≥ 0, ``[..., 1]``.
        mix: α ∈ [0, 1], ``[..., 1]``; 0 → Phong cosine, 1 → (n·h)^4.
    """
    _check(g, "mixture", k_s=k_s, shininess=shininess, mix=mix)
    val = k_s * guarded_pow(mixture_base(g, mix), shininess)
    return _masked(g, val)


def _normalised_power(base: Tensor, s: Tensor, k: float) -> tuple[Tensor, Tensor]:
    """``L = (s + k)/(kπ) · guarded_pow(base, s)`` and ``∂L/∂s = L (1/(s + k) + ln base)``, each ``[..., 1]``."""
    power, log_b = guarded_pow_log(base, s)
    lobe = (s + k) / (k * math.pi) * power
    return lobe, lobe * (1.0 / (s + k) + log_b)


class _Nielsen(Model):
    variant = ""

    def __init__(self, fresnel: bool = True):
        if not isinstance(fresnel, bool):
            raise TypeError(f"{type(self).__name__}: fresnel must be True or False, got {fresnel!r}")
        self.fresnel = fresnel
        self.params = (ALBEDO, SPECULAR, ROUGHNESS) + ((IOR,) if fresnel else ())

    def _specular(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        raise NotImplementedError

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        diffuse = _masked(g, p["albedo"] * INV_PI)
        spec = self._specular(g, p)
        if self.fresnel:
            spec = spec * nielsen_fresnel(g, p["ior"])
        return diffuse + spec

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """``(ρ_d/π + c_s L(s) R_F(l·h, η)) (n·l)⁺`` on the front side with ``L`` the variant's lobe
        (:meth:`_lobe_derivative`: ``L = (s + k)/(kπ) b^s``, ``∂L/∂s = L (1/(s + k) + ln b)`` for eq 1 (b = r·v, k = 2)
        and eq 2 (b = n·h, k = 8); ``L = b^s``, ``∂L/∂s = L ln b``, ``∂L/∂α = L s (n·h⁴ − r·v)/b`` for eq 3), ``s``
        from roughness (:func:`materials.roughness.roughness_to_shininess_derivative`) and ``R_F`` with its
        η-derivative (:func:`materials.fresnel.fresnel_dielectric_and_derivative`; 1 without Fresnel). ρ_d and the
        specular coefficient act per channel (diagonal derivatives). Each variant's ``_lobe_derivative`` gives its
        lobe without coefficient and Fresnel factor ``[..., 1]``, the derivative in s and those in its other
        parameters (``{name: [..., 1]}``); None where the class that wrote the lobe (``_specular``) wrote no
        derivative beside it (a subclass that changes the lobe)."""
        owner = next(c for c in type(self).__mro__ if "_specular" in c.__dict__)
        if not (self.shades_as(_Nielsen) and "_lobe_derivative" in owner.__dict__):
            return None
        s, ds = roughness_to_shininess_derivative(p["roughness"])
        lobe, dlobe, extra = self._lobe_derivative(g, s, p)
        w = torch.where(g.front, g.nl.clamp_min(0.0), torch.zeros_like(g.nl))              # the front side's (n·l)⁺
        if self.fresnel:
            rf, drf = _fresnel.fresnel_dielectric_and_derivative(p["ior"], g.fresnel_cos)
        else:
            rf, drf = torch.ones_like(lobe), None
        ks = p["specular"]
        spec = w * lobe * rf                                                                  # [..., 1]
        value = p["albedo"] * (w * INV_PI) + ks * spec
        grads = {"albedo": (w * INV_PI).expand_as(value), "specular": spec.expand_as(value),
                 "roughness": (ks * (w * dlobe * ds * rf)).unsqueeze(-1)}
        for name, d in extra.items():
            grads[name] = (ks * (w * d * rf)).unsqueeze(-1)
        if drf is not None:
            grads["ior"] = (ks * (w * lobe * drf)).unsqueeze(-1)
        return value, grads

    def environment_split(
        self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor], fresnel_cos: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """(specular, diffuse) radiance toward v from an environment, ``[..., 3]`` each.

        Diffuse ρ_d/π E(n) (exact for Lambert). Specular: a mirror approximation,
        ρ_s (or k_s-derived albedo 1) · R_F(n·v, η) · L(r); the lobes' own normalisations make their
        albedo ≈ ρ_s at normal incidence for eq 1-2. Coarse (as Gotanda 2012 eq 7); for eq 3 the
        lobe's albedo depends on s and α and is not modelled: we use k_s · 2π/(s + 2) (the Phong
        lobe's integral) as its albedo. ``fresnel_cos`` replaces n·v as R_F's cosine (the layered model
        passes the angle refracted into its coat, Gotanda 2012 eq 4/7).
        """
        from .blinn_phong import mirror_radiance

        if not isinstance(env, (HemisphereLight, SHLight)):
            raise NotImplementedError(f"no environment response for {type(env).__name__}")
        nv = (n * v).sum(-1, keepdim=True)
        diff = torch.where(nv > 0, p["albedo"] * INV_PI * env.irradiance(n), torch.zeros_like(p["albedo"]))
        scale = p["specular"]
        if self.variant == "mixture":
            s = roughness_to_shininess(p["roughness"])
            scale = scale * (2.0 * math.pi) / (s + 2.0)
        if self.fresnel:
            fc = nv if fresnel_cos is None else fresnel_cos
            scale = scale * _fresnel.fresnel_dielectric(p["ior"], fc.clamp(0.0, 1.0))
        spec = scale * mirror_radiance(env, n, v)
        return torch.where(nv > 0, spec, torch.zeros_like(spec)), diff

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        s, d = self.environment_split(env, n, v, p)
        return s + d


@register("nielsen-phong", "Nielsen eq 1: Lambert + modified Phong ρ_s R_F (s+2)/(2π) (r·v)^s")
class NielsenPhong(_Nielsen):
    """Nielsen eq 1. Params albedo (ρ_d), specular (ρ_s), roughness (→ s), ior (η, when fresnel=True)."""

    variant = "phong"

    def _specular(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return modified_phong(g, p["specular"], roughness_to_shininess(p["roughness"]))

    def _lobe_derivative(self, g: Angles, s: Tensor, p: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, dict]:
        return (*_normalised_power(g.rv, s, 2.0), {})


@register("nielsen-blinn-phong", "Nielsen eq 2: Lambert + modified Blinn-Phong ρ_s R_F (s+8)/(8π) (n·h)^s")
class NielsenBlinnPhong(_Nielsen):
    """Nielsen eq 2. Params albedo (ρ_d), specular (ρ_s), roughness (→ s), ior (η, when fresnel=True)."""

    variant = "blinn-phong"

    def _specular(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return modified_blinn_phong(g, p["specular"], roughness_to_shininess(p["roughness"]))

    def _lobe_derivative(self, g: Angles, s: Tensor, p: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, dict]:
        return (*_normalised_power(g.nh, s, 8.0), {})


@register("nielsen-mixture", "Nielsen eq 3: Lambert + k_s R_F ((1−α) r·v + α (n·h)^4)^s, the Phong/Blinn-Phong mixture")
class NielsenMixture(_Nielsen):
    """Nielsen eq 3. Params albedo (ρ_d), specular (k_s), roughness (→ s), mix (α), ior (η)."""

    variant = "mixture"

    def __init__(self, fresnel: bool = True):
        super().__init__(fresnel)
        self.params = self.params + (MIX,)

    def _specular(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return mixture(g, p["specular"], roughness_to_shininess(p["roughness"]), p["mix"])

    def _lobe_derivative(self, g: Angles, s: Tensor, p: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, dict]:
        nh4 = g.nh.clamp_min(0.0).square().square()
        base = mixture_base(g, p["mix"])
        lobe, log_b = guarded_pow_log(base, s)
        # (∂b^s/∂b = s b^s / b where the power is taken; where it is not the lobe is 0, and so is the quotient)
        return lobe, lobe * log_b, {"mix": lobe * s * (nh4 - g.rv) / base.clamp_min(POW_EPS)}
