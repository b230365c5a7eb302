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
