"""Gotanda's physically based Blinn-Phong (SIGGRAPH 2010; restated as eq 1 of Gotanda 2012).

Gotanda 2012, eq 1 (Blinn-Phong specular with a Neumann-Neumann visibility and a Lambert diffuse
coupled through the normal-incidence reflectance)::

    f_r = R_d/π (1 − F0) + (0.0397436 s + 0.0856832) F_schlick(F0, l·h) (n·h)^s / max(n·l, n·v)

Both OCR copies of the paper agree on the constants 0.0397436 and 0.0856832 and on the
``max(n·ω', n·ω)`` denominator. The Fresnel argument is not printed in eq 1 ("F_spec(F0) is the
Fresnel function with Schlick's approximation"); we use l·h (= v·h), the microfacet angle of a
half-vector model (Cook-Torrance, which the paper says this model resembles).

The normalisation. The linear factor approximates the closed form

    N(s) = (s + 2) / (4π (2 − 2^(−s/2)))     (:func:`gotanda_normalization_exact`)

which is ``1 / ∫_Ω (n·h)^s dω_l`` at normal viewing (v = n): the lobe normalised with the cosine
cancelled by the Neumann factor (n·l / max(n·l, n·v) = 1 wherever n·l ≥ n·v). Evidence: the
least-squares line through N(s) at the integer exponents s = 1 … 200 is
0.03974358 s + 0.08568316, i.e. Gotanda's two constants to all 6-7 printed digits
(tests/materials/test_blinn_phong.py reproduces it). The fit is 32 % low at s = 1, within 0.57 %
for s ∈ [10, 4096] (peak +0.57 % at s ≈ 17; table in docs/models-phong-layered.md). With F = 1 the directional albedo
never exceeds 1 for either normalisation (max 0.996 at s = 1000, 0.63 at s = 1): the lobe loses
energy, it does not gain it. The whole material (:class:`Gotanda2010`) does gain energy toward grazing
view: its diffuse keeps R_d(1 − F0) at every angle while the lobe adds Schlick's (1 − l·h)⁵ — directional
albedo 1.057 at R_d = 1, F0 = 0, θ_v = 75° for a mirror-like lobe (docs/models.md, "Findings").

Shininess ``s`` comes from the canonical perceptual roughness through
:func:`materials.roughness.roughness_to_shininess` (s = 2/r⁴ − 2, clamped to [0, 2^16]).

Conventions: cosines are ``[..., 1]`` (:class:`materials.geometry.Angles`), colours ``[..., 3]``;
every lobe returns the BRDF in 1/sr without the cosine and 0 unless n·l > 0 and n·v > 0.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from . import fresnel as _fresnel
from .environment import Environment, HemisphereLight, SHLight
from .geometry import Angles, clamp_cos, guarded_pow, guarded_pow_log, reflect
from .lambert import INV_PI
from .model import Model, register
from .params import ALBEDO, F0, ROUGHNESS
from .roughness import roughness_to_shininess, roughness_to_shininess_derivative

#: Gotanda's linear fit of the normalisation (2012 eq 1): N ≈ FIT_SLOPE · s + FIT_INTERCEPT.
FIT_SLOPE = 0.0397436
FIT_INTERCEPT = 0.0856832

NORMALIZATIONS = ("fit", "exact")
#: Fresnel forms of :data:`materials.fresnel.FRESNEL` (looked up when evaluated).
FRESNEL_NAMES = ("none", "schlick", "exact", "sg", "schuler")


def _tensor(x, name: str, where: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{where}: {name} must be a torch.Tensor, got {type(x).__name__}")
    return x


def _check_angles(g, where: str) -> None:
    if not isinstance(g, Angles):
        raise TypeError(f"{where}: g must be a materials.geometry.Angles (build it with Angles.from_vectors), "
                        f"got {type(g).__name__}")


def _check_choice(value: str, choices: tuple[str, ...], option: str, where: str) -> None:
    if value not in choices:
        raise ValueError(f"{where}: {option}={value!r} is not one of {list(choices)}")


def gotanda_normalization_fit(shininess: Tensor) -> Tensor:
    """Gotanda's linear normalisation 0.0397436 s + 0.0856832 (2012 eq 1), in 1/sr.

    Args:
        shininess: Blinn-Phong exponent s ≥ 0, any shape.
    """
    s = _tensor(shininess, "shininess", "gotanda_normalization_fit")
    return FIT_SLOPE * s + FIT_INTERCEPT


def gotanda_normalization_exact(shininess: Tensor) -> Tensor:
    """The closed form the linear fit approximates: N(s) = (s + 2) / (4π (2 − 2^(−s/2))), in 1/sr.

    N(s) = 1 / ∫_Ω (n·h)^s dω_l for v = n (derivation: with θ_h = θ_l/2 and c = cos θ_h,
    ∫ (n·h)^s dω_l = 8π ∫_{1/√2}^1 c^(s+1) dc = 4π (2 − 2^(−s/2)) / (s + 2)). N(0) = 1/(2π).
    Finite with a finite gradient for every s ≥ 0 (the denominator is ≥ 4π).
    """
    s = _tensor(shininess, "shininess", "gotanda_normalization_exact").clamp_min(0.0)
    return (s + 2.0) / (4.0 * math.pi * (2.0 - torch.exp2(-0.5 * s)))


def blinn_phong_normal_albedo_normalization(shininess: Tensor) -> Tensor:
    """For comparison: the factor K that makes K (n·h)^s (no Neumann term) have directional albedo 1
    at normal incidence, K = (s + 2)(s + 4) / (8π (s + 2^(−s/2))) (the usual "exact" Blinn-Phong
    normalisation; Gotanda's lobe at v = n has max(n·l, n·v) = 1, so this is also the factor that
    makes *its* albedo at normal incidence exactly 1)."""
    s = _tensor(shininess, "shininess", "blinn_phong_normal_albedo_normalization").clamp_min(0.0)
    return (s + 2.0) * (s + 4.0) / (8.0 * math.pi * (s + torch.exp2(-0.5 * s)))


def gotanda_normalization(shininess: Tensor, normalization: str = "fit") -> Tensor:
    """Dispatch: ``"fit"`` (the paper's line, default) or ``"exact"`` (the closed form)."""
    _check_choice(normalization, NORMALIZATIONS, "normalization", "gotanda_normalization")
    if normalization == "fit":
        return gotanda_normalization_fit(shininess)
    return gotanda_normalization_exact(shininess)


def gotanda_normalization_derivative(shininess: Tensor, normalization: str = "fit") -> tuple[Tensor, Tensor]:
    """:func:`gotanda_normalization` and its derivative in s: the fit's slope, or, for the exact form
    ``N = (s + 2)/(4π D)`` with ``D = 2 − 2^(−s/2)``, ``∂N/∂s = (D − (s + 2) ln2 · 2^(−s/2)/2)/(4π D²)``."""
    _check_choice(normalization, NORMALIZATIONS, "normalization", "gotanda_normalization_derivative")
    s = _tensor(shininess, "shininess", "gotanda_normalization_derivative")
    if normalization == "fit":
        return FIT_SLOPE * s + FIT_INTERCEPT, torch.full_like(s, FIT_SLOPE)
    sc = s.clamp_min(0.0)
    e = torch.exp2(-0.5 * sc)
    d = 2.0 - e
    dn = (d - (sc + 2.0) * (0.5 * math.log(2.0)) * e) / (4.0 * math.pi * d * d)
    return (sc + 2.0) / (4.0 * math.pi * d), torch.where(s >= 0.0, dn, torch.zeros_like(dn))


def _lobe_no_max(g: Angles, f0: Tensor, shininess: Tensor, normalization: str, fresnel: str) -> Tensor:
    """N(s) · F(f0, l·h) · (n·h)^s, un-masked (shared by the BRDF and its cosine form)."""
    f = _fresnel.FRESNEL[fresnel](f0, g.fresnel_cos)
    return gotanda_normalization(shininess, normalization) * f * guarded_pow(g.nh, shininess)


def _check_lobe_inputs(g, f0, shininess, where: str) -> None:
    _check_angles(g, where)
    _tensor(f0, "f0", where)
    _tensor(shininess, "shininess", where)
    if f0.dim() == 0:
        raise ValueError(f"{where}: f0 must have a channel dimension [..., 1] or [..., 3], got a scalar")


def gotanda_blinn_phong(
    g: Angles, f0: Tensor, shininess: Tensor, normalization: str = "fit", fresnel: str = "schlick"
) -> Tensor:
    """Gotanda's physically based Blinn-Phong specular BRDF (2012 eq 1, second term), 1/sr.

    ``N(s) F(f0, l·h) (n·h)^s / max(n·l, n·v)``; 0 unless n·l > 0 and n·v > 0. The max is
    floored at 1e-6 (it only matters where both cosines are below 1e-6).

    Args:
        g: shading cosines ``[..., 1]``.
        f0: normal-incidence reflectance F0 ∈ [0, 1], ``[..., C]``.
        shininess: Blinn-Phong exponent s ∈ [0, 2^16], ``[..., 1]`` (or a broadcastable scalar tensor).
        normalization: ``"fit"`` (0.0397436 s + 0.0856832, the paper) or ``"exact"``
            (:func:`gotanda_normalization_exact`).
        fresnel: a name of :data:`materials.fresnel.FRESNEL`; ``"schlick"`` is the paper's.

    Returns:
        ``[..., C]`` BRDF value.
    """
    where = "gotanda_blinn_phong"
    _check_lobe_inputs(g, f0, shininess, where)
    _check_choice(fresnel, FRESNEL_NAMES, "fresnel", where)
    lobe = _lobe_no_max(g, f0, shininess, normalization, fresnel)
    val = lobe / clamp_cos(torch.maximum(g.nl, g.nv))
    return torch.where(g.front, val, torch.zeros_like(val))


def gotanda_blinn_phong_cosine(
    g: Angles, f0: Tensor, shininess: Tensor, normalization: str = "fit", fresnel: str = "schlick"
) -> Tensor:
    """``gotanda_blinn_phong · (n·l)⁺`` written without a vanishing division:
    ``N F (n·h)^s · min(1, n·l / n·v)`` on the front side, ``[..., C]`` in 1/sr."""
    where = "gotanda_blinn_phong_cosine"
    _check_lobe_inputs(g, f0, shininess, where)
    _check_choice(fresnel, FRESNEL_NAMES, "fresnel", where)
    lobe = _lobe_no_max(g, f0, shininess, normalization, fresnel)
    nl = g.nl.clamp_min(0.0)
    ratio = nl / clamp_cos(torch.maximum(g.nl, g.nv))  # = min(1, n·l/n·v) in front
    val = lobe * ratio
    return torch.where(g.front, val, torch.zeros_like(val))


def mirror_radiance(env: Environment, n: Tensor, v: Tensor) -> Tensor:
    """Coarse pre-filtered environment radiance in the mirror direction r = 2(n·v)n − v, ``[..., 3]``.

    SHLight: the order-2 SH radiance at r (already a strongly low-passed environment), clamped ≥ 0.
    HemisphereLight: only irradiances are known; we use E(r)/π, the radiance of a uniform
    environment with that irradiance (Schüler's lerp makes it smooth across the horizon).
    """
    r = reflect(v, n)
    if isinstance(env, SHLight):
        return env.radiance(r).clamp_min(0.0)
    if isinstance(env, HemisphereLight):
        return env.irradiance(r) * INV_PI
    raise NotImplementedError(
        f"no environment response defined for {type(env).__name__}; use HemisphereLight or SHLight"
    )


class _GotandaBase(Model):
    def __init__(self, normalization: str = "fit", fresnel: str = "schlick"):
        where = f"{type(self).__name__}"
        _check_choice(normalization, NORMALIZATIONS, "normalization", where)
        _check_choice(fresnel, FRESNEL_NAMES, "fresnel", where)
        self.normalization = normalization
        self.fresnel = fresnel

    def _spec(self, g: Angles, p: Mapping[str, Tensor], cosine: bool) -> Tensor:
        s = roughness_to_shininess(p["roughness"])
        fn = gotanda_blinn_phong_cosine if cosine else gotanda_blinn_phong
        return fn(g, p["f0"], s, self.normalization, self.fresnel)

    def _spec_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """The cosine-weighted lobe ``N(s) F(f0, l·h) (n·h)^s min(1, n·l/n·v)`` on the front side and its
        derivatives: in f0 (the diagonal, ``[..., C]``) and in roughness (``[..., C, 1]``, through s: ``∂/∂s`` of
        ``N (n·h)^s`` is ``N′ (n·h)^s + N (n·h)^s ln(n·h)``, :func:`gotanda_normalization_derivative`,
        :func:`materials.roughness.roughness_to_shininess_derivative`)."""
        s, ds = roughness_to_shininess_derivative(p["roughness"])
        n, dn = gotanda_normalization_derivative(s, self.normalization)
        power, log_c = guarded_pow_log(g.nh, s)
        ratio = g.nl.clamp_min(0.0) / clamp_cos(torch.maximum(g.nl, g.nv))
        w = torch.where(g.front, ratio, torch.zeros_like(ratio))                  # min(1, n·l/n·v) in front
        f, df = _fresnel.fresnel_and_derivative(self.fresnel, p["f0"], g.fresnel_cos)
        lobe = n * power * w                                                       # [..., 1]
        dlobe = (dn + n * log_c) * power * w * ds                                  # ∂lobe/∂r
        value = lobe * f
        return value, (lobe * df).expand_as(value), (dlobe * f).unsqueeze(-1)

    def _env_specular(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor],
                      fresnel_cos: Tensor | None = None) -> Tensor:
        """IBL specular: F(f0, n·v) · L(r). A mirror-reflection stand-in for Gotanda's AmbientBRDF
        (the lobe's own albedo loss at low shininess is ignored; coarse, as in 2012 eq 7). ``fresnel_cos``
        replaces n·v as the Fresnel factor's cosine (a coat above: the angle refracted into it)."""
        nv = (n * v).sum(-1, keepdim=True)
        fc = nv if fresnel_cos is None else fresnel_cos
        f = _fresnel.FRESNEL[self.fresnel](p["f0"], fc.clamp(0.0, 1.0))
        out = f * mirror_radiance(env, n, v)
        return torch.where(nv > 0, out, torch.zeros_like(out))


@register("gotanda2010-specular", "Gotanda's physically based Blinn-Phong specular lobe alone (2012 eq 1, 2nd term)")
class GotandaBlinnPhong(_GotandaBase):
    """Specular-only Gotanda Blinn-Phong (params ``f0``, ``roughness``).

    Options: ``normalization`` ``"fit"`` (paper) | ``"exact"``; ``fresnel`` a
    :data:`materials.fresnel.FRESNEL` name (``"schlick"`` is the paper's).
    """

    params = (F0, ROUGHNESS)

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self._spec(g, p, cosine=False)

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self._spec(g, p, cosine=True)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The lobe's closed form (:meth:`_spec_jacobian`)."""
        if not self.shades_as(GotandaBlinnPhong):
            return None
        value, df0, dr = self._spec_jacobian(g, p)
        return value, {"f0": df0, "roughness": dr}

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        return self._env_specular(env, n, v, p)


@register("gotanda2010", "Gotanda 2010 physically based Blinn-Phong + Lambert·(1 − F0) (Gotanda 2012 eq 1)")
class Gotanda2010(_GotandaBase):
    """The complete 2012-eq-1 material: ``albedo/π (1 − f0) + gotanda_blinn_phong``.

    Params ``albedo`` (R_d), ``f0`` (F0, RGB; also the diffuse coupling 1 − F0) and ``roughness``.
    Options as :class:`GotandaBlinnPhong`. Reciprocal (every factor is symmetric in l and v).
    """

    params = (ALBEDO, F0, ROUGHNESS)

    def _diffuse(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        d = p["albedo"] * (1.0 - p["f0"]) * INV_PI
        return torch.where(g.front, d, torch.zeros_like(d))

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self._diffuse(g, p) + self._spec(g, p, cosine=False)

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self._diffuse(g, p) * g.nl.clamp_min(0.0) + self._spec(g, p, cosine=True)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """``ρ (1 − f0)(n·l)⁺/π`` plus the lobe's closed form (:meth:`_spec_jacobian`): f0 acts on both terms,
        ``−ρ (n·l)⁺/π`` on the diffuse one; each channel on its own (diagonal derivatives)."""
        if not self.shades_as(Gotanda2010):
            return None
        spec, df0, dr = self._spec_jacobian(g, p)
        w = torch.where(g.front, g.nl.clamp_min(0.0) * INV_PI, torch.zeros_like(g.nl))
        albedo, f0 = p["albedo"], p["f0"]
        value = albedo * (1.0 - f0) * w + spec
        return value, {"albedo": ((1.0 - f0) * w).expand_as(value), "f0": df0 - albedo * w, "roughness": dr}

    def environment_split(
        self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor], fresnel_cos: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """(specular, diffuse) radiance ``[..., 3]`` toward v: F(f0, n·v) L(r) and
        albedo (1 − f0)/π · E(n). Used by the layered model (Gotanda 2012 eq 7, 9), which passes the
        refracted cosine as ``fresnel_cos`` (the Fresnel factor's cosine, default n·v)."""
        if not isinstance(env, (HemisphereLight, SHLight)):
            raise NotImplementedError(f"no environment response for {type(env).__name__}")
        nv = (n * v).sum(-1, keepdim=True)
        diff = p["albedo"] * (1.0 - p["f0"]) * INV_PI * env.irradiance(n)
        diff = torch.where(nv > 0, diff, torch.zeros_like(diff))
        return self._env_specular(env, n, v, p, fresnel_cos), diff

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        s, d = self.environment_split(env, n, v, p)
        return s + d
