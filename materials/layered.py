"""Gotanda 2012 dual-layer material (section 2, eq 2-9): a clear absorbing coat over ANY bottom model.

Point and directional lights (one light direction l, viewer v)::

    f = f_coat(l, v) + T_in(l) · T_out(v) · A(l, v) · f_bottom(l, v; bottom params seen through the coat)

- ``f_coat``: the coat's specular, Gotanda's physically based Blinn-Phong (eq 1,
  :func:`materials.blinn_phong.gotanda_blinn_phong`) with s from ``coat_roughness`` and the *exact*
  dielectric Fresnel of f0 = f0_from_ior(coat_ior) at l·h (``coat="ggx"`` swaps in GGX +
  height-correlated Smith from :mod:`materials.microfacet`). Exact rather than Schlick because
  Schlick at f0 = 0 still reflects (1 − l·h)^5, so the coat would not vanish at coat_ior = 1, and
  because T = 1 − F must use the same F as the reflection it complements.
- ``T_in(l) = 1 − F(n1, n·l)``: eq 4's first factor (1 − F(n1)), light entering the coat.
- ``T_out(v)``: eq 4's last factor (1 − F(1/n1)) evaluated at the refracted angle inside the coat.
  By Stokes reciprocity that is exactly 1 − F(n1, n·v), so that is how we compute it
  (``bottom_fresnel="exact"``). ``bottom_fresnel="constant"`` follows eq 5: T_in stays
  angle-dependent (F_transmittance(n1) = 1 − F(n1)) and the exit factor becomes the constant
  1 − F0(1/n1) = 1 − F0(n1); the bottom's own Fresnel is made constant too when its model takes a
  ``fresnel`` option (it is built with ``fresnel="none"``, i.e. F = F0(n2/n1)).
- ``F(n2/n1)``, the middle factor of eq 4, is the bottom's *own* Fresnel evaluated with the bottom
  interface seen from inside the coat, at the angle refracted into the coat: light reaches the
  bottom at θ_t = asin(sin θ / n1), so the bottom lobe gets its Fresnel cosine (l·h, the angle its
  Fresnel factor uses; :attr:`materials.Angles.fresnel_cos`) replaced by cos θ_t = √(1 − (1 − (l·h)²)/n1²)
  (:meth:`GotandaLayered.bottom_angles`; at a mirror pair l·h = n·l, so this is exactly eq 4's angle).
  This is the reading under which the paper's Figure 1 holds: for n1 = 1.33333 over n2 = 1.5 the
  product (1 − F(n1, θ)) F(n2/n1, θ_t) (1 − F(1/n1, θ_t)) stays within 0.0012–0.0042 for θ ∈ [0°, 85°] —
  "almost a flat line" next to the top layer's 0.020 → 0.58 — whereas F(n2/n1) at the unrefracted θ
  would rise 30-fold, to 0.095 at 80° (tests/materials/test_layered.py). A bottom characterised by f0
  has, against air, n2 = (1 + √f0)/(1 − √f0) (f0 = ((n2 − 1)/(n2 + 1))²), so against the coat its
  normal-incidence reflectance is f0_rel = ((n2 − n1)/(n2 + n1))², computed in the overflow-free form
  √f0_rel = |(1 + √f0) − n1 (1 − √f0)| / ((1 + √f0) + n1 (1 − √f0)) (finite at f0 = 1: n2 = ∞ →
  f0_rel = 1); a Fresnel-from-f0 form then follows the external-reflection curve of that interface even
  where n2 < n1 (f0_rel alone does not say which side is denser). A bottom with an ``ior`` parameter gets
  η_rel = n2/n1 exactly, also below 1: at the refracted angle sin θ_t ≤ 1/n1 ≤ n2/n1 (n2 ≥ 1), so the
  total internal reflection of η_rel < 1 is never reached. The rest of the bottom lobe (its D, G and any
  diffuse Fresnel such as Gotanda 2014 eq 6) keeps the unrefracted cosines. Bottom models with neither
  parameter (e.g. Lambert) are used as they are.
- ``A(l, v)``: absorption in the coat. ``absorption="exact"``: Bouguer-Lambert-Beer (eq 2),
  A = exp(−α d (1/cos θ_i' + 1/cos θ_r')), θ' refracted by Snell through coat_ior
  (cos θ' = √(1 − (1 − cos²θ)/n1²)), map value ``absorption`` = α·d. ``absorption="linear"``
  (eq 3, the paper's real-time form): A = max(0, 1 − α' (1/n·l + 1/n·v)), map value = α'.
  Cosines are floored at 1e-6, so 1/cos ≤ 1e6 and the value and gradient stay finite; where the
  max(0, ·) clips, the gradient is exactly 0.
- The bottom BRDF sees the *unrefracted* l and v, as in Gotanda's approximation (the refracted
  directions would narrow a bottom lobe by ~n1² in solid angle; the paper does not do it and
  neither do we).

At coat_ior = 1 and absorption = 0 the coat vanishes: F = 0, T = 1, A = 1, f0_rel = f0 → the
bottom model exactly (tested).

Image-based lighting (eq 6-9), :meth:`GotandaLayered.environment` for ``SHLight`` and
``HemisphereLight``: the coat reflects F(n1, n·v) L(r) (a mirror, L from
:func:`materials.blinn_phong.mirror_radiance`); the bottom's environment response is split into
specular and diffuse when the bottom model offers ``environment_split`` (Gotanda 2010 and the
Nielsen models do), and each part is attenuated by its own absorption factor:

- specular (eq 6-7, mirror: n·l = n·v): T_in(n·v) T_out(n·v) · max(0, 1 − 2α'/n·v)
  (exact: exp(−2 α d / cos θ_r')), the bottom's Fresnel again at the refracted angle (eq 7's F_bottom
  is eq 4 at N·E);
- diffuse (eq 8-9): T̄_in T_out(n·v) · max(0, 1 − α'(2 + 1/n·v)) (exact: exp(−αd/cos θ_r') times the
  cosine-weighted mean of exp(−αd/cos θ_i') over the hemisphere, 16-point Gauss-Legendre), where
  T̄_in = 1 − 2∫F(n1, μ) μ dμ is the cosine-weighted mean entry transmittance.

Readings: eq 7/9 write F_bottom and 1 − F_bottom; here the bottom's own Fresnel (with f0_rel)
already sits inside its specular and diffuse parts, and the coat transmittances are applied to
both, so the environment response is consistent with the point-light BRDF (the paper's eq 9 has
no transmittance on the diffuse path). A bottom without ``environment_split`` is treated as all
diffuse (eq 9 factor) — documented, coarse. Eq 8 (the Lambert-weighted mean of 1/cos θ_i + 1/cos θ_r
is 2 + 1/cos θ_r) is correct; its first line carries a stray dθ_r. Eq 9 averages the linear
attenuation *before* the max(0, ·); the clamped mean is c − 2α' + α'²/c for c = 1 − α'/cos θ_r ≥ α'
(0 otherwise) — :func:`clamped_linear_absorption_mean` — so eq 9 under-estimates by α'²/c.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import torch
from torch import Tensor

from . import fresnel as _fresnel
from .blinn_phong import NORMALIZATIONS, gotanda_blinn_phong, gotanda_blinn_phong_cosine, mirror_radiance
from .environment import Environment, HemisphereLight, SHLight
from .geometry import Angles, clamp_cos
from .model import Model, get, register
from .params import ABSORPTION, COAT_IOR, COAT_ROUGHNESS, ParamSpec
from .roughness import roughness_to_alpha, roughness_to_shininess

#: Cosine floor of the absorption path lengths (1/cos ≤ 1e6).
COS_EPS = 1e-6
ABSORPTIONS = ("exact", "linear")
BOTTOM_FRESNELS = ("exact", "constant")
COATS = ("blinn-phong", "ggx")


def _gauss_legendre_01(n: int) -> tuple[Tensor, Tensor]:
    """Gauss-Legendre nodes and weights on [0, 1] (Golub-Welsch, float64)."""
    k = torch.arange(1, n, dtype=torch.float64)
    beta = k / torch.sqrt(4.0 * k * k - 1.0)
    evals, evecs = torch.linalg.eigh(torch.diag(beta, 1) + torch.diag(beta, -1))
    return 0.5 * (evals + 1.0), evecs[0] ** 2  # weights sum to 1 on [0, 1]


_GL_X, _GL_W = _gauss_legendre_01(16)


def _check_t(name: str, x, where: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{where}: {name} must be a torch.Tensor, got {type(x).__name__}")
    return x


def refracted_cos(cos_i: Tensor, eta: Tensor) -> Tensor:
    """cos θ' of the ray refracted into a layer of relative index η ≥ 1 (Snell), ``[..., 1]``.

    cos θ' = √(1 − (1 − cos²θ)/η²), floored at 1e-6 (reached only at η = 1 and grazing incidence).
    """
    c = _check_t("cos_i", cos_i, "refracted_cos").clamp(0.0, 1.0)
    eta = _check_t("eta", eta, "refracted_cos")
    arg = 1.0 - (1.0 - c * c) / (eta * eta)
    return torch.sqrt(arg.clamp_min(COS_EPS * COS_EPS))


def absorption_exact(nl: Tensor, nv: Tensor, absorption: Tensor, coat_ior: Tensor) -> Tensor:
    """Bouguer-Lambert-Beer through the coat (Gotanda 2012 eq 2): exp(−α d (1/cos θ_i' + 1/cos θ_r')).

    Args:
        nl, nv: n·l and n·v, ``[..., 1]`` (clamped to [0, 1] inside).
        absorption: α·d ≥ 0 (dimensionless optical depth at normal incidence), ``[..., C]``.
        coat_ior: η₁ ≥ 1, ``[..., 1]``.

    Returns:
        Transmitted fraction in (0, 1], ``[..., C]``.
    """
    path = 1.0 / refracted_cos(nl, coat_ior) + 1.0 / refracted_cos(nv, coat_ior)
    return torch.exp(-_check_t("absorption", absorption, "absorption_exact") * path)


def absorption_linear(nl: Tensor, nv: Tensor, absorption: Tensor) -> Tensor:
    """Gotanda's linear absorption (2012 eq 3): max(0, 1 − α' (1/n·l + 1/n·v)), ``[..., C]``.

    Cosines are floored at 1e-6. Non-refracted path, no index: α' absorbs thickness and index.
    """
    nl = clamp_cos(_check_t("nl", nl, "absorption_linear"), COS_EPS)
    nv = clamp_cos(_check_t("nv", nv, "absorption_linear"), COS_EPS)
    a = _check_t("absorption", absorption, "absorption_linear")
    return torch.relu(1.0 - a * (1.0 / nl + 1.0 / nv))


def clamped_linear_absorption_mean(absorption: Tensor, nv: Tensor) -> Tensor:
    """Lambert-weighted hemispherical mean of eq 3 *with* its clamp, for analysis of eq 9:
    ∫ max(0, 1 − α'(1/μ + 1/cos θ_r)) 2μ dμ = c − 2α' + α'²/c for c = 1 − α'/cos θ_r ≥ α', else 0."""
    a = _check_t("absorption", absorption, "clamped_linear_absorption_mean")
    c = 1.0 - a / clamp_cos(_check_t("nv", nv, "clamped_linear_absorption_mean"), COS_EPS)
    ok = c > a
    c_safe = torch.where(ok, c, torch.ones_like(c))
    return torch.where(ok, c_safe - 2.0 * a + a * a / c_safe, torch.zeros_like(c))


def _one_value(x: Tensor) -> bool:
    """Whether ``x`` ``[..., C]`` holds one value broadcast over its batch (an expanded tensor, stride 0)."""
    return x.shape[-1] == 1 and all(st == 0 or n == 1 for st, n in zip(x.stride()[:-1], x.shape[:-1], strict=True))


def relative_f0(f0: Tensor, coat_ior: Tensor) -> Tensor:
    """Normal-incidence reflectance of a bottom of air-f0 ``f0`` under a coat of index η₁.

    f0_rel = ((n2 − n1)/(n2 + n1))² with n2 = (1 + √f0)/(1 − √f0), written without n2 (finite at
    f0 = 1). Exact identity at η₁ = 1. √f0 is cut to 0 below f0 = 1e-12 (its derivative is
    unbounded there; the physical d f0_rel/d f0 diverges as f0 → 0 when η₁ ≠ 1).
    """
    ok = f0 > 1e-12
    r = torch.where(ok, torch.sqrt(torch.where(ok, f0, torch.ones_like(f0))), torch.zeros_like(f0))
    num = (1.0 + r) - coat_ior * (1.0 - r)
    den = (1.0 + r) + coat_ior * (1.0 - r)
    return (num / den).square()


def relative_f0_derivative(f0: Tensor, coat_ior: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`relative_f0` and its derivative in f0: with r = √f0, num = (1 + r) − η₁(1 − r) and den = (1 + r) +
    η₁(1 − r), ``∂f0_rel/∂r = 8 η₁ num/den³`` (num′ den − num den′ = 4η₁) and ``∂r/∂f0 = 1/(2r)``; 0 where √f0 is
    cut (f0 ≤ 1e-12), as automatic differentiation of :func:`relative_f0` gives."""
    ok = f0 > 1e-12
    r = torch.where(ok, torch.sqrt(torch.where(ok, f0, torch.ones_like(f0))), torch.zeros_like(f0))
    num = (1.0 + r) - coat_ior * (1.0 - r)
    den = (1.0 + r) + coat_ior * (1.0 - r)
    d = 4.0 * coat_ior * num / (torch.where(ok, r, torch.ones_like(r)) * den * den * den)
    return (num / den).square(), torch.where(ok, d, torch.zeros_like(d))


def relative_ior(ior: Tensor, coat_ior: Tensor) -> Tensor:
    """η_rel = n2/n1 of the bottom interface seen from inside the coat (below 1 when the coat is denser).

    With the Fresnel factor at the refracted angle (sin θ_t ≤ 1/n1) and n2 ≥ 1, sin θ_t ≤ η_rel, so
    η_rel < 1 never reaches total internal reflection.
    """
    return ior / coat_ior


def _hemispherical_mean(fn, dtype, device) -> Tensor:
    """2∫_0^1 fn(μ) μ dμ with 16-point Gauss-Legendre; fn maps μ ``[16, 1]`` to ``[..., 16, C]``."""
    x = _GL_X.to(device=device, dtype=dtype).unsqueeze(-1)
    w = _GL_W.to(device=device, dtype=dtype).unsqueeze(-1)
    return (fn(x) * (2.0 * x * w)).sum(-2)


class GotandaLayered(Model):
    """Gotanda 2012 dual layer (eq 2-9) over any registered bottom model.

    Options:
        bottom: registered model name (default ``"gotanda2010"``) or a :class:`Model` instance.
        absorption: ``"linear"`` (eq 3, paper's real-time form, default) or ``"exact"`` (eq 2).
        bottom_fresnel: ``"exact"`` (eq 4, default) or ``"constant"`` (eq 5).
        coat: ``"blinn-phong"`` (Gotanda's, default) or ``"ggx"``.
        normalization: coat Blinn-Phong normalisation, ``"fit"`` or ``"exact"``.
        bottom_options: options passed to ``materials.get(bottom, ...)``.

    Params: the bottom's + ``absorption`` (α' or α·d), ``coat_ior`` (η₁), ``coat_roughness``.
    """

    def __init__(
        self,
        bottom: str | Model = "gotanda2010",
        absorption: str = "linear",
        bottom_fresnel: str = "exact",
        coat: str = "blinn-phong",
        normalization: str = "fit",
        bottom_options: Mapping | None = None,
    ):
        where = "gotanda2012-layered"
        for opt, val, choices in (
            ("absorption", absorption, ABSORPTIONS),
            ("bottom_fresnel", bottom_fresnel, BOTTOM_FRESNELS),
            ("coat", coat, COATS),
            ("normalization", normalization, NORMALIZATIONS),
        ):
            if val not in choices:
                raise ValueError(f"{where}: {opt}={val!r} is not one of {list(choices)}")
        opts = dict(bottom_options or {})
        self.bottom_fresnel_constant = False
        if isinstance(bottom, Model):
            self.bottom = bottom
        elif isinstance(bottom, str):
            if bottom_fresnel == "constant" and "fresnel" not in opts:
                try:
                    self.bottom = get(bottom, fresnel="none", **opts)
                    self.bottom_fresnel_constant = True
                except (ValueError, TypeError):
                    self.bottom = get(bottom, **opts)
            else:
                self.bottom = get(bottom, **opts)
        else:
            raise TypeError(f"{where}: bottom must be a registered model name or a Model, got {type(bottom).__name__}")
        clash = {s.name for s in self.bottom.params} & {"absorption", "coat_ior", "coat_roughness"}
        if clash:
            raise ValueError(f"{where}: the bottom model '{self.bottom.name}' already has coat parameters "
                             f"{sorted(clash)}; a coat over a coat is not supported")
        self.absorption = absorption
        self.bottom_fresnel = bottom_fresnel
        self.coat = coat
        self.normalization = normalization
        names = {s.name for s in self.bottom.params}
        self.params: tuple[ParamSpec, ...] = tuple(self.bottom.params) + (ABSORPTION, COAT_IOR, COAT_ROUGHNESS)
        self._has_f0 = "f0" in names
        self._has_ior = "ior" in names
        self._coat_cache = None

    # -- pieces ---------------------------------------------------------------------------------
    def bottom_angles(self, g: Angles, p: Mapping[str, Tensor]) -> Angles:
        """``g`` with the bottom's specular Fresnel cosine refracted into the coat (eq 4's F(n2/n1) at θ_t):
        cos θ_t = √(1 − (1 − c²)/n1²) for the cosine c the bottom's Fresnel would use (l·h)."""
        return g.with_fresnel_cos(refracted_cos(g.fresnel_cos, p["coat_ior"]))

    def bottom_params(self, p: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """The bottom's parameters as seen from inside the coat (f0 → f0_rel, ior → η_rel)."""
        q = dict(p)
        if self._has_f0:
            q["f0"] = relative_f0(p["f0"], p["coat_ior"])
        if self._has_ior:
            q["ior"] = relative_ior(p["ior"], p["coat_ior"])
        return q

    def coat_specular(self, g: Angles, p: Mapping[str, Tensor], cosine: bool = False) -> Tensor:
        """The top layer's specular BRDF (or BRDF·n·l), ``[..., 1]``."""
        f0c = _fresnel.f0_from_ior(p["coat_ior"])
        if self.coat == "ggx":
            from . import microfacet

            alpha = roughness_to_alpha(p["coat_roughness"])
            f = microfacet.microfacet_specular(g, f0c, alpha, D="ggx", G="smith-correlated", F="exact")
            return f * g.nl.clamp_min(0.0) if cosine else f
        s = roughness_to_shininess(p["coat_roughness"])
        fn = gotanda_blinn_phong_cosine if cosine else gotanda_blinn_phong
        return fn(g, f0c, s, self.normalization, "exact")

    def transmittance(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        """T_in(l) · T_out(v) of the coat (eq 4 or eq 5), ``[..., 1]``."""
        n1 = p["coat_ior"]
        t_in = 1.0 - _fresnel.fresnel_dielectric(n1, g.nl.clamp(0.0, 1.0))
        if self.bottom_fresnel == "exact":
            t_out = 1.0 - _fresnel.fresnel_dielectric(n1, g.nv.clamp(0.0, 1.0))
        else:
            t_out = 1.0 - _fresnel.f0_from_ior(n1)
        return t_in * t_out

    def attenuation(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        """Absorption factor A(l, v) ``[..., 3]`` (eq 2 or eq 3)."""
        if self.absorption == "exact":
            return absorption_exact(g.nl, g.nv, p["absorption"], p["coat_ior"])
        return absorption_linear(g.nl, g.nv, p["absorption"])

    def attenuation_derivative(self, g: Angles, p: Mapping[str, Tensor], atten: Tensor) -> Tensor:
        """``∂A/∂absorption`` ``[..., 3]`` of :meth:`attenuation` (each channel's own), given ``atten`` = A:
        ``−path · A`` for eq 2, ``−(1/n·l + 1/n·v)`` where eq 3's clamp does not hold (A > 0; 0 where it does)."""
        if self.absorption == "exact":
            path = 1.0 / refracted_cos(g.nl, p["coat_ior"]) + 1.0 / refracted_cos(g.nv, p["coat_ior"])
            return -path * atten
        inv = 1.0 / clamp_cos(g.nl, COS_EPS) + 1.0 / clamp_cos(g.nv, COS_EPS)
        return torch.where(atten > 0.0, -inv, torch.zeros_like(inv)).expand_as(atten)

    def cosine_brdf_jacobian_in(self, g: Angles, p: Mapping[str, Tensor],
                                names: Collection[str]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The derivatives in the bottom's parameters and the absorption, the coat's held (as a fit that measured
        the coat once holds it, :class:`materials.KnownParams`): ``top + T A(absorption) bottom(p_b)`` is the
        bottom's closed form at the refracted angles and the parameters seen from inside the coat (f0 → f0_rel,
        :func:`relative_f0_derivative`; ior → ior/η₁), scaled by the coat's transmittance T and the absorption A, and
        ``T ∂A/∂absorption · bottom``. None for the coat's own parameters, or a bottom without a closed form."""
        if not self.shades_as(GotandaLayered) or {"coat_ior", "coat_roughness"} & set(names):
            return None
        top, trans = self.coat_terms(g, p, True)
        pb, gb = self.bottom_params(p), self.bottom_angles(g, p)
        out = self.bottom.cosine_brdf_jacobian(gb, pb)
        if out is None:
            return None
        bot, dbot = out
        atten = self.attenuation(g, p)
        t = trans * atten                                                   # [..., 3]
        value = top + t * bot

        def front(x: Tensor) -> Tensor:             # (a diagonal derivative [..., 3] or a full one [..., 3, C])
            mask = g.front if x.dim() == value.dim() else g.front.unsqueeze(-1)
            return torch.where(mask, x, torch.zeros_like(x))

        def scaled(d: Tensor, chain: Tensor | None = None) -> Tensor:
            diagonal = d.dim() == value.dim()
            if chain is not None:                           # a per-channel map of the parameter (f0, ior)
                d = d * (chain if diagonal else chain.unsqueeze(-2))
            return front(d * (t if diagonal else t.unsqueeze(-1)))

        grads = {}
        for name in names:
            if name == "absorption":
                grads[name] = front(trans * self.attenuation_derivative(g, p, atten) * bot)
            elif name == "f0" and self._has_f0:
                grads[name] = scaled(dbot[name], relative_f0_derivative(p["f0"], p["coat_ior"])[1])
            elif name == "ior" and self._has_ior:
                grads[name] = scaled(dbot[name], 1.0 / p["coat_ior"])
            else:
                grads[name] = scaled(dbot[name])
        return torch.where(g.front, value, torch.zeros_like(value)), grads

    def coat_terms(self, g: Angles, p: Mapping[str, Tensor], cosine: bool) -> tuple[Tensor, Tensor]:
        """(:meth:`coat_specular`, :meth:`transmittance`), each ``[..., 1]``: functions of the angles and the coat's
        η and roughness only.

        When the coat is one value for every pair and needs no gradient — the coat fitted as two scalars for the
        object and held known (:class:`materials.KnownParams`, as ``capture.reconstruct`` fits it) — a solver
        evaluates the model hundreds of times on the same angles with the same coat, so the last result is kept
        and reused for the same :class:`Angles` object (unchanged in place), coat values and batch shape.
        Measured on the default-size layered scene's second fit (256² maps, 204 000 samples, 2 threads): 33.5–34.7 s
        with the reuse, 38.5–42.4 s without, the same maps.
        """
        n1, r = p["coat_ior"], p["coat_roughness"]
        key = None
        if _one_value(n1) and _one_value(r) and not (n1.requires_grad or r.requires_grad):
            key = (cosine, tuple(n1.shape), tuple(r.shape), n1.dtype, n1.device, float(n1.reshape(-1)[0]),
                   float(r.reshape(-1)[0]), tuple(x._version for x in (g.nl, g.nv, g.nh, g.lh, g.lv)))
            cached = self._coat_cache
            if cached is not None and cached[0] is g and cached[1] == key:
                return cached[2], cached[3]
        top, trans = self.coat_specular(g, p, cosine), self.transmittance(g, p)
        self._coat_cache = (g, key, top, trans) if key is not None else None
        return top, trans

    def _eval(self, g: Angles, p: Mapping[str, Tensor], cosine: bool) -> Tensor:
        top, trans = self.coat_terms(g, p, cosine)
        pb, gb = self.bottom_params(p), self.bottom_angles(g, p)
        bot = self.bottom.cosine_brdf(gb, pb) if cosine else self.bottom.brdf(gb, pb)
        val = top + trans * self.attenuation(g, p) * bot
        return torch.where(g.front, val, torch.zeros_like(val))

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self._eval(g, p, cosine=False)

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self._eval(g, p, cosine=True)

    # -- image-based lighting (eq 6-9) ---------------------------------------------------------
    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        """Radiance toward v ``[..., 3]`` from a :class:`SHLight` or :class:`HemisphereLight` (eq 6-9).

        See the module docstring for the approximations (mirror coat, eq 7 for the bottom
        specular, eq 9 for the bottom diffuse, coat transmittances on both).
        """
        if not isinstance(env, (HemisphereLight, SHLight)):
            return super().environment(env, n, v, p)
        n1, a = p["coat_ior"], p["absorption"]
        nv_raw = (n * v).sum(-1, keepdim=True)
        nv = nv_raw.clamp(0.0, 1.0)
        dtype, device = nv.dtype, nv.device
        f_v = _fresnel.fresnel_dielectric(n1, nv)
        coat = f_v * mirror_radiance(env, n, v)
        t_out = (1.0 - f_v) if self.bottom_fresnel == "exact" else (1.0 - _fresnel.f0_from_ior(n1))
        t_in_spec = 1.0 - f_v
        t_in_diff = 1.0 - _hemispherical_mean(
            lambda mu: _fresnel.fresnel_dielectric(n1.unsqueeze(-2), mu), dtype, device
        )
        if self.absorption == "linear":
            inv_v = 1.0 / clamp_cos(nv, COS_EPS)
            a_spec = torch.relu(1.0 - a * (2.0 * inv_v))  # eq 7
            a_diff = torch.relu(1.0 - a * (2.0 + inv_v))  # eq 9
        else:
            inv_rv = 1.0 / refracted_cos(nv, n1)
            a_spec = torch.exp(-2.0 * a * inv_rv)
            mean = _hemispherical_mean(
                lambda mu: torch.exp(-a.unsqueeze(-2) / refracted_cos(mu, n1.unsqueeze(-2))), dtype, device
            )
            a_diff = torch.exp(-a * inv_rv) * mean
        pb = self.bottom_params(p)
        split = getattr(self.bottom, "environment_split", None)
        if split is not None:
            spec_b, diff_b = split(env, n, v, pb, fresnel_cos=refracted_cos(nv, n1))
            bottom = t_in_spec * t_out * a_spec * spec_b + t_in_diff * t_out * a_diff * diff_b
        else:
            bottom = t_in_diff * t_out * a_diff * self.bottom.environment(env, n, v, pb)
        out = coat + bottom
        return torch.where(nv_raw > 0, out, torch.zeros_like(out))


register(
    "gotanda2012-layered",
    "Gotanda 2012 dual layer (eq 2-9): Blinn-Phong coat with absorption over any bottom model",
)(GotandaLayered)
