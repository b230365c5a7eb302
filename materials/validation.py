"""Numerical validation of any registered model: hemisphere quadrature, directional albedo, and the
stress domain over which every model must stay finite in value and gradient.

Used by the test suite (the cheap part), ``scripts/stress.py`` and ``scripts/benchmark.py``.
Everything here works for any :class:`materials.model.Model`, so a new model is covered by
registering it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .geometry import Angles
from .model import Model
from .params import ParamSpec


def hemisphere_quadrature(n_theta: int = 64, n_phi: int = 128, dtype=torch.float64, device=None):
    """Tensor-product quadrature of the upper hemisphere (z up).

    Gauss-Legendre in μ = cos θ ∈ [0, 1] (``n_theta`` nodes) times the midpoint rule in φ
    (``n_phi`` nodes, exact for trigonometric polynomials of degree < n_phi).

    Returns:
        directions ``[n_theta·n_phi, 3]`` (unit) and weights ``[n_theta·n_phi]`` with Σ w = 2π
        (the solid angle), so ``Σ w f(ω)`` ≈ ∫ f dω.
    """
    x, w = np.polynomial.legendre.leggauss(n_theta)
    mu = torch.as_tensor(0.5 * (x + 1.0), dtype=dtype, device=device)
    wmu = torch.as_tensor(0.5 * w, dtype=dtype, device=device)
    phi = (torch.arange(n_phi, dtype=dtype, device=device) + 0.5) * (2.0 * math.pi / n_phi)
    sin = torch.sqrt((1.0 - mu * mu).clamp_min(0.0))
    d = torch.stack(
        [
            sin[:, None] * torch.cos(phi)[None, :],
            sin[:, None] * torch.sin(phi)[None, :],
            mu[:, None].expand(-1, n_phi),
        ],
        dim=-1,
    ).reshape(-1, 3)
    weights = (wmu[:, None] * (2.0 * math.pi / n_phi)).expand(-1, n_phi).reshape(-1)
    return d, weights


def view_direction(theta_v: Tensor) -> Tensor:
    """Unit viewing directions in the xz-plane at polar angles ``theta_v`` (radians) → ``[..., 3]``."""
    return torch.stack([torch.sin(theta_v), torch.zeros_like(theta_v), torch.cos(theta_v)], -1)


def directional_albedo(
    model: Model, params: Mapping[str, Tensor], theta_v: Tensor, n_theta: int = 64, n_phi: int = 128
) -> Tensor:
    """Directional albedo ρ(v) = ∫ f_r(l, v) (n·l) dω_l for each viewing angle, by quadrature.

    Args:
        model: any model.
        params: parameters, each ``[channels]`` (one material).
        theta_v: viewing polar angles in radians ``[K]``.

    Returns:
        ``[K, 3]``. A normalised, energy-conserving lobe gives ≤ 1 for parameters ≤ 1.
        Sharp lobes (large exponents) need more nodes than the defaults.
    """
    dtype = theta_v.dtype
    d, w = hemisphere_quadrature(n_theta, n_phi, dtype=dtype, device=theta_v.device)
    v = view_direction(theta_v)[:, None, :]  # [K,1,3]
    n = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=theta_v.device)
    g = Angles.from_vectors(n, d[None, :, :], v)
    p = {k: x.to(dtype) for k, x in params.items()}
    f = model.cosine_brdf(g, p)  # [K, M, 3]
    return (f * w[None, :, None]).sum(1)


def directional_albedo_half_vector(
    model: Model, params: Mapping[str, Tensor], theta_v: float, n_t: int = 768, n_phi: int = 1024
) -> Tensor:
    """ρ(v) = ∫ f_r(l, v) (n·l) dω_l written over the half vector, an independent check of
    :func:`directional_albedo` that also resolves mirror-like lobes.

    l = 2 (v·h) h − v maps the half vectors one to one onto the sphere of l with dω_l = 4 (v·h) dω_h;
    θ_h = (π/2) t² with Gauss-Legendre t ∈ [0, 1] (``n_t`` nodes, dense at h = n, where every
    half-vector lobe sits for any view) times the midpoint rule in φ_h (``n_phi`` nodes). Directions l
    below the horizon contribute 0 (the model returns 0 there). ``theta_v`` in radians; returns ``[3]``.
    """
    dtype = torch.float64
    x, w = np.polynomial.legendre.leggauss(n_t)
    t = torch.as_tensor(0.5 * (x + 1.0), dtype=dtype)
    wt = torch.as_tensor(0.5 * w, dtype=dtype)
    th = 0.5 * math.pi * t * t
    phi = (torch.arange(n_phi, dtype=dtype) + 0.5) * (2.0 * math.pi / n_phi)
    sin = torch.sin(th)[:, None]
    h = torch.stack([sin * torch.cos(phi), sin * torch.sin(phi), torch.cos(th)[:, None].expand(n_t, n_phi)], -1)
    weight = (math.pi * t * wt * torch.sin(th))[:, None].expand(n_t, n_phi) * (2.0 * math.pi / n_phi)
    h, weight = h.reshape(-1, 3), weight.reshape(-1, 1)
    v = torch.tensor([math.sin(theta_v), 0.0, math.cos(theta_v)], dtype=dtype)
    vh = (h * v).sum(-1, keepdim=True)
    l = 2.0 * vh * h - v
    g = Angles.from_vectors(torch.tensor([0.0, 0.0, 1.0], dtype=dtype), l, v.expand_as(l))
    f = model.cosine_brdf(g, {k: x.to(dtype) for k, x in params.items()})
    return (f * 4.0 * vh.clamp_min(0.0) * weight).sum(0)


# -- the stress domain --------------------------------------------------------------------------

#: Cosines every model must survive: grazing, exactly zero, slightly negative, normal.
STRESS_COSINES = (-1e-3, -1e-7, 0.0, 1e-7, 1e-4, 1e-2, 0.3, 0.7, 1.0)


def stress_vectors(dtype=torch.float64, device=None, n_random: int = 256, seed: int = 0):
    """(n, l, v) triples covering the stress domain, each ``[M, 3]``, with ``n = +z``.

    A grid over :data:`STRESS_COSINES` for n·l and n·v at several azimuth differences
    (0, π/2, π, including l = v and the mirror configuration), the degenerate ``l = −v``, and
    random directions over the full sphere (back-facing included).
    """
    cos = torch.tensor(STRESS_COSINES, dtype=dtype, device=device)
    sin = torch.sqrt((1.0 - cos * cos).clamp_min(0.0))
    dphi = torch.tensor([0.0, 0.5 * math.pi, math.pi, 1e-4], dtype=dtype, device=device)
    ci, cv, ph = torch.meshgrid(torch.arange(len(cos)), torch.arange(len(cos)), torch.arange(len(dphi)), indexing="ij")
    ci, cv, ph = ci.reshape(-1), cv.reshape(-1), ph.reshape(-1)
    l = torch.stack([sin[ci], torch.zeros_like(sin[ci]), cos[ci]], -1)
    v = torch.stack([sin[cv] * torch.cos(dphi[ph]), sin[cv] * torch.sin(dphi[ph]), cos[cv]], -1)
    gen = torch.Generator().manual_seed(seed)
    rl = torch.nn.functional.normalize(torch.randn(n_random, 3, generator=gen, dtype=torch.float64), dim=-1)
    rv = torch.nn.functional.normalize(torch.randn(n_random, 3, generator=gen, dtype=torch.float64), dim=-1)
    l = torch.cat([l, rl.to(l), l[:8]])
    v = torch.cat([v, rv.to(v), -l[-8:]])  # the last 8: l = −v
    n = torch.zeros_like(l)
    n[:, 2] = 1.0
    return n, l, v


def stress_values(spec: ParamSpec) -> list[float]:
    """Values of one parameter to stress: its range ends, the default, and extremes inside the domain."""
    hi = spec.high if math.isfinite(spec.high) else 1e3
    vals = {spec.low, hi, spec.default, 0.5 * (spec.low + min(hi, 1.0 if not math.isfinite(spec.high) else hi))}
    if spec.name in ("roughness", "coat_roughness"):
        vals |= {0.0, 1e-6, 0.02, 1.0}
    if spec.name in ("absorption",):
        vals |= {0.0, 1e-3, 1.0, 1e3}
    if spec.name in ("ior", "coat_ior"):
        vals |= {1.0, 1.0 + 1e-6, 3.0}
    if spec.low <= 0.0 <= spec.high:
        vals.add(0.0)
    return sorted(v for v in vals if spec.low <= v <= (spec.high if math.isfinite(spec.high) else 1e3))


def stress_params(model: Model, m: int, dtype=torch.float64, device=None, seed: int = 0) -> dict[str, Tensor]:
    """Parameters ``[m, channels]`` cycling through each parameter's stress values (phases differ
    per parameter so that combinations of extremes occur)."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for k, spec in enumerate(model.params):
        vals = torch.tensor(stress_values(spec), dtype=dtype)
        idx = (torch.arange(m) * (k + 1) + torch.randint(0, len(vals), (1,), generator=gen)) % len(vals)
        x = vals[idx][:, None].expand(m, spec.channels).clone()
        if spec.channels == 3:  # decorrelate channels a little, staying in range
            x[:, 1] = vals[(idx + 1) % len(vals)]
        out[spec.name] = x.to(device)
    return out


#: Range of the grazing cosines of :func:`edge_vectors` (log-uniform): from where a float32 cosine is
#: pure rounding noise (1e-7) to where a lobe is no longer grazing (1e-1).
GRAZING_LOG10 = (-7.0, -1.0)


def _rotation(m: int, gen: torch.Generator) -> Tensor:
    """``m`` uniformly random rotation matrices ``[m, 3, 3]`` (float64; QR of a Gaussian, sign-fixed)."""
    q, r = torch.linalg.qr(torch.randn(m, 3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    det = torch.linalg.det(q)
    q[:, :, 2] *= det.sign().unsqueeze(-1)
    return q


def _polar(c: Tensor, phi: Tensor) -> Tensor:
    s = torch.sqrt((1.0 - c * c).clamp_min(0.0))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), c], -1)


def edge_vectors(m: int, dtype=torch.float64, device=None, seed: int = 0):
    """``m`` random (n, l, v) triples ``[m, 3]`` that concentrate on the configurations where lobes break.

    One sixth each: (1) l and v uniform over the sphere (back-facing included); (2) both uniform over
    the upper hemisphere; (3) *grazing mirror pairs*: n·v log-uniform in 10^GRAZING_LOG10, l the mirror
    of v about n with n·l either equal to n·v or independently grazing and the azimuth off the mirror by 0
    or ±10^U(−9, −1) rad; (4) exact mirror pairs at any elevation (n·v = U⁴); (5) l = −v and l = v at
    any elevation, grazing ones included; (6) n·l and n·v drawn from :data:`STRESS_COSINES` (exact 0,
    ±1e-7, −1e-3 ...) at random azimuths. Half of all triples are then turned by a random rotation, so
    that n is not +z and the cosines carry the rounding of a general frame. Built in float64, then cast.
    """
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    u = lambda k: torch.rand(k, generator=gen, dtype=f64)  # noqa: E731
    two_pi = 2.0 * math.pi
    k = m // 6
    sizes = [k] * 5 + [m - 5 * k]
    unit = lambda x: x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    parts_l, parts_v = [], []
    # (1) sphere
    parts_l.append(unit(torch.randn(sizes[0], 3, generator=gen, dtype=f64)))
    parts_v.append(unit(torch.randn(sizes[0], 3, generator=gen, dtype=f64)))
    # (2) upper hemisphere (uniform in solid angle: cos uniform)
    parts_l.append(_polar(u(sizes[1]), two_pi * u(sizes[1])))
    parts_v.append(_polar(u(sizes[1]), two_pi * u(sizes[1])))
    # (3) grazing mirror pairs
    kk = sizes[2]
    lo, hi = GRAZING_LOG10
    cv = 10.0 ** (lo + (hi - lo) * u(kk))
    cl = torch.where(u(kk) < 0.5, cv, 10.0 ** (lo + (hi - lo) * u(kk)))
    pv = two_pi * u(kk)
    off = torch.where(u(kk) < 0.25, torch.zeros(kk, dtype=f64), 10.0 ** (-9.0 + 8.0 * u(kk)))
    off = torch.where(u(kk) < 0.5, off, -off)
    parts_v.append(_polar(cv, pv))
    parts_l.append(_polar(cl, pv + math.pi + off))
    # (4) exact mirror pairs at any elevation
    c4, p4 = u(sizes[3]) ** 4, two_pi * u(sizes[3])
    parts_v.append(_polar(c4, p4))
    parts_l.append(_polar(c4, p4 + math.pi))
    # (5) l = −v and l = v, any elevation (a quarter of them grazing)
    kk = sizes[4]
    c5 = torch.where(u(kk) < 0.25, 10.0 ** (lo + (hi - lo) * u(kk)), 2.0 * u(kk) - 1.0)
    v5 = _polar(c5, two_pi * u(kk))
    parts_v.append(v5)
    parts_l.append(torch.where((u(kk) < 0.5)[:, None], -v5, v5))
    # (6) the stress grid's cosines at random azimuths
    kk = sizes[5]
    cos = torch.tensor(STRESS_COSINES, dtype=f64)
    pick = lambda: cos[torch.randint(0, len(cos), (kk,), generator=gen)]  # noqa: E731
    parts_l.append(_polar(pick(), two_pi * u(kk)))
    parts_v.append(_polar(pick(), two_pi * u(kk)))
    l, v = torch.cat(parts_l), torch.cat(parts_v)
    n = torch.zeros_like(l)
    n[:, 2] = 1.0
    turn = u(m) < 0.5
    rot = _rotation(int(turn.sum()), gen)
    for x in (n, l, v):
        x[turn] = (rot @ x[turn].unsqueeze(-1)).squeeze(-1)
    return tuple(x.to(dtype=dtype, device=device) for x in (n, l, v))


def random_params(model: Model, m: int, dtype=torch.float64, device=None, seed: int = 0) -> dict[str, Tensor]:
    """Random parameters ``[m, channels]`` for ``model``, each channel drawn independently: half uniform
    over the declared range (log-uniform from 1e-6 to 1e3 above the low end for an unbounded range), a
    quarter from :func:`stress_values`, a quarter within 10^U(−9, −2) of one of the range's ends."""
    gen = torch.Generator().manual_seed(seed + 7919)
    out = {}
    for spec in model.params:
        shape = (m, spec.channels)
        u = torch.rand(shape, generator=gen, dtype=torch.float64)
        finite = math.isfinite(spec.high)
        span = (spec.high - spec.low) if finite else 1e3
        if finite:
            uni = spec.low + span * torch.rand(shape, generator=gen, dtype=torch.float64)
        else:
            uni = spec.low + 10.0 ** (-6.0 + 9.0 * torch.rand(shape, generator=gen, dtype=torch.float64))
        vals = torch.tensor(stress_values(spec), dtype=torch.float64)
        picked = vals[torch.randint(0, len(vals), shape, generator=gen)]
        eps = span * 10.0 ** (-9.0 + 7.0 * torch.rand(shape, generator=gen, dtype=torch.float64))
        top = spec.high if finite else spec.low + span
        near = torch.where(torch.rand(shape, generator=gen) < 0.5, spec.low + eps, top - eps)
        x = torch.where(u < 0.5, uni, torch.where(u < 0.75, picked, near))
        out[spec.name] = x.clamp(spec.low, top).to(dtype=dtype, device=device)
    return out


@dataclass
class StabilityReport:
    """What :func:`check_stability` found for one model and dtype."""

    model: str
    dtype: str
    samples: int
    nonfinite_value: int
    nonfinite_grad: int
    max_abs_grad: float
    max_abs_grad_params: float = 0.0  # worst |∂f/∂parameter| alone (the solver's concern; directions are fixed)
    max_rel_dev_f32: float | None = None  # worst |f32 − f64| / max(|f64|, floor), float32 runs only

    @property
    def ok(self) -> bool:
        return self.nonfinite_value == 0 and self.nonfinite_grad == 0


def check_stability(model: Model, dtype=torch.float64, device=None, n_random: int = 256) -> StabilityReport:
    """Evaluate ``model.cosine_brdf`` and ``brdf`` over the stress domain and back-propagate to every
    parameter and to l and v; count non-finite values and gradients."""
    n, l, v = stress_vectors(dtype=dtype, device=device, n_random=n_random)
    m = n.shape[0]
    params = {k: x.requires_grad_() for k, x in stress_params(model, m, dtype=dtype, device=device).items()}
    l = l.clone().requires_grad_()
    v = v.clone().requires_grad_()
    g = Angles.from_vectors(n, l, v)
    f = model.cosine_brdf(g, params)
    fb = model.brdf(g, params)
    bad_value = int((~torch.isfinite(f)).sum() + (~torch.isfinite(fb)).sum())
    inputs = [l, v, *params.values()]
    grads = torch.autograd.grad((f.sum() + fb.sum()), inputs, allow_unused=True)
    bad_grad, max_grad, max_param_grad = 0, 0.0, 0.0
    for k, gr in enumerate(grads):
        if gr is None:
            continue
        bad_grad += int((~torch.isfinite(gr)).sum())
        fin = gr[torch.isfinite(gr)]
        if fin.numel():
            max_grad = max(max_grad, float(fin.abs().max()))
            if k >= 2:
                max_param_grad = max(max_param_grad, float(fin.abs().max()))
    report = StabilityReport(model.name, str(dtype).replace("torch.", ""), m, bad_value, bad_grad, max_grad,
                             max_param_grad)
    if dtype == torch.float32:
        with torch.no_grad():
            g64 = Angles.from_vectors(n.double(), l.double(), v.double())
            f64 = model.cosine_brdf(g64, {k: x.double() for k, x in params.items()})
            floor = max(float(f64.abs().max()), 1e-6) * 1e-3
            dev = (f.detach().double() - f64).abs() / f64.abs().clamp_min(floor)
            report.max_rel_dev_f32 = float(dev[torch.isfinite(dev)].max()) if torch.isfinite(dev).any() else math.inf
    return report


@dataclass
class SampledReport:
    """What :func:`sampled_stability` found for one model, dtype and set of random samples.

    ``nonfinite_*`` count samples (rows) with at least one non-finite entry; ``negative`` counts samples
    where f_r < 0 in some channel and ``min_value`` is the most negative f_r (1/sr; 0 if none).
    """

    model: str
    dtype: str
    samples: int = 0
    nonfinite_value: int = 0
    nonfinite_grad: int = 0
    nonfinite_grad_directions: int = 0
    negative: int = 0
    min_value: float = 0.0

    @property
    def ok(self) -> bool:
        return self.nonfinite_value == 0 and self.nonfinite_grad == 0

    def add(self, other: SampledReport) -> SampledReport:
        """The two reports of disjoint sample sets merged into one."""
        return SampledReport(
            self.model, self.dtype, self.samples + other.samples, self.nonfinite_value + other.nonfinite_value,
            self.nonfinite_grad + other.nonfinite_grad,
            self.nonfinite_grad_directions + other.nonfinite_grad_directions,
            self.negative + other.negative, min(self.min_value, other.min_value),
        )


def sampled_stability(model: Model, m: int, dtype=torch.float64, device=None, seed: int = 0) -> SampledReport:
    """Evaluate ``model.brdf`` and ``model.cosine_brdf`` on ``m`` triples of :func:`edge_vectors` with
    :func:`random_params`, back-propagate to l, v and every parameter, and count the samples with a
    non-finite value or gradient and those with a negative value."""
    n, l, v = edge_vectors(m, dtype=dtype, device=device, seed=seed)
    params = {k: x.requires_grad_() for k, x in random_params(model, m, dtype=dtype, device=device, seed=seed).items()}
    l.requires_grad_()
    v.requires_grad_()
    g = Angles.from_vectors(n, l, v)
    f = model.cosine_brdf(g, params)
    fb = model.brdf(g, params)
    grads = torch.autograd.grad(f.sum() + fb.sum(), [l, v, *params.values()], allow_unused=True)
    def bad(x: Tensor | None) -> Tensor:
        return torch.zeros(m, dtype=torch.bool, device=f.device) if x is None else ~torch.isfinite(x).all(-1)

    bad_dir = bad(grads[0]) | bad(grads[1])
    bad_grad = bad_dir.clone()
    for gr in grads[2:]:
        bad_grad |= bad(gr)
    with torch.no_grad():
        neg = ((f < 0) | (fb < 0)).any(-1)
        fin = fb[torch.isfinite(fb)]
        low = float(fin.min()) if fin.numel() else 0.0
    return SampledReport(model.name, str(dtype).replace("torch.", ""), m, int((bad(f) | bad(fb)).sum()),
                         int(bad_grad.sum()), int(bad_dir.sum()), int(neg.sum()), min(low, 0.0))


def front_uniform_angles(m: int, dtype=torch.float64, seed: int = 0) -> Angles:
    """``m`` (l, v) pairs, each uniform in solid angle over the front hemisphere of n = +z, as :class:`Angles`."""
    gen = torch.Generator().manual_seed(seed)
    c = torch.rand(2, m, generator=gen, dtype=torch.float64)
    phi = 2.0 * math.pi * torch.rand(2, m, generator=gen, dtype=torch.float64)
    l, v = _polar(c[0], phi[0]), _polar(c[1], phi[1])
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return Angles.from_vectors(n, l, v).to(dtype)


def negative_extent(model: Model, m: int = 4_000_000, seed: int = 0, chunk: int = 1_000_000,
                    **fixed: float) -> dict[str, float]:
    """How often and how far ``model.brdf`` goes below 0 over front-facing directions (float64).

    Pairs from :func:`front_uniform_angles`; every parameter uniform over its range (an unbounded one
    over [low, low + 1]) unless given in ``fixed`` (one value for every channel). Returns the fraction
    of negative pairs (any channel), the most negative π f_r and, for models with an albedo, the most
    negative π f_r / ρ among them.
    """
    neg, low, low_rel = 0, 0.0, 0.0
    gen = torch.Generator().manual_seed(seed + 1)
    for k, start in enumerate(range(0, m, chunk)):
        size = min(chunk, m - start)
        g = front_uniform_angles(size, seed=seed * 1_000_003 + k)
        p = {}
        for s in model.params:
            if s.name in fixed:
                p[s.name] = torch.full((1, s.channels), float(fixed[s.name]), dtype=torch.float64)
            else:
                top = s.high if math.isfinite(s.high) else s.low + 1.0
                p[s.name] = s.low + (top - s.low) * torch.rand(size, s.channels, generator=gen, dtype=torch.float64)
        f = math.pi * model.brdf(g, p)
        bad = f < 0
        neg += int(bad.any(-1).sum())
        if bad.any():
            low = min(low, float(f.min()))
            if "albedo" in p:
                rho = p["albedo"].expand_as(f)
                low_rel = min(low_rel, float((f[bad] / rho[bad]).min()))
    return {"negative_fraction": neg / m, "min_pi_f": low, "min_pi_f_over_albedo": low_rel}
