"""The per-texel stages of :func:`capture.fit.fast.solve_fast`: input checks, the starting θ, the sample Jacobian and
costs, the closed-form initialisation of the linear parameters and the per-texel Levenberg-Marquardt.

With nearest-texel sampling each texel is an independent least-squares problem in P ≤ ~10 unknowns, so

1. parameters a model declares linear (``ParamSpec.linear``: albedo, f0 under Schlick-type
   Fresnel, Nielsen's k_s) are solved in *closed form*, per texel, for a grid of values of the
   main nonlinear parameter (roughness); the best grid point per texel initialises
   (:func:`closed_form_init`)
2. Levenberg-Marquardt on all parameters, vectorised over all texels (:func:`per_texel_lm`): residuals of all
   samples, the per-sample Jacobian (:func:`jacobian`: closed form or reverse-mode AD), per-texel normal equations
   ``JᵀWJ [T, P, P]`` and ``JᵀWr [T, P]`` accumulated with ``index_add``, a batched damped solve, and per-texel
   step acceptance with per-texel damping λ_t.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from materials.geometry import Angles
from materials.model import Model, SumModel
from materials.params import ParamSpec
from renderer.device import block_size

from ..observations import Observations
from .layout import ACC, MAX_STEP, Layout, SolverError, bounded, from_canonical
from .noise import check_loss, irls_weights, robust_rho

__all__ = ["BILINEAR_LM_TOL", "BILINEAR_LM_MIN", "check_inputs", "init_theta", "separable", "JACOBIAN_BLOCK",
           "derivative_pairs", "jacobian_blocks", "jacobian",
           "sample_cost", "texel_cost", "weighted_cost", "data_cost", "grid_values", "linear_solve",
           "closed_form_init", "per_texel_lm"]


def check_inputs(model: Model, obs: Observations, loss: str) -> None:
    """A :class:`SolverError` unless ``model`` is a model with parameters, ``obs`` observations with samples and
    ``loss`` one of the losses."""
    if not isinstance(model, Model):
        raise SolverError(f"model must be a materials.Model (materials.get(name)), got {type(model).__name__}")
    if not isinstance(obs, Observations):
        raise SolverError(f"obs must be capture.observations.Observations, got {type(obs).__name__}")
    if obs.n_samples == 0:
        raise SolverError("no observations to fit (0 valid samples)")
    if not model.params:
        raise SolverError(f"model '{model.name}' has no parameters to fit")
    check_loss(loss)


def init_theta(model: Model, layout: Layout, obs: Observations, init: Mapping[str, Tensor] | None) -> Tensor:
    """The starting θ ``[T, P]``: the model's defaults, with the maps of ``init`` (``name → [H, W, C]``, checked)."""
    T, dt, dev = obs.n_texels, obs.dtype, obs.device
    params = model.defaults((T,), device=dev, dtype=dt)
    if init is not None:
        for k, m in init.items():
            if k not in params:
                raise SolverError(f"init has map '{k}' that model '{model.name}' does not use; it uses "
                                  f"{list(model.param_names)}")
            if m.dim() != 3 or tuple(m.shape[:2]) != tuple(obs.map_size):
                raise SolverError(f"init map '{k}' must be [H, W, C] with (H, W) = {obs.map_size}, "
                                  f"got {tuple(m.shape)}")
            params[k] = m.reshape(T, -1).to(dtype=dt, device=dev).expand(T, model.spec(k).channels)
    return layout.pack(params)


def separable(model: Model, spec: ParamSpec, dtype) -> bool:
    """True when channel c of the RGB parameter only changes output channel c (checked numerically)."""
    if spec.channels != 3:
        return False
    gen = torch.Generator().manual_seed(1)
    nl = torch.rand(64, 1, generator=gen, dtype=dtype) * 0.9 + 0.05
    nv = torch.rand(64, 1, generator=gen, dtype=dtype) * 0.9 + 0.05
    lv = torch.rand(64, 1, generator=gen, dtype=dtype) * 1.6 - 0.8
    g = Angles.from_cosines(nl, nv, lv)
    p = {s.name: torch.rand(64, s.channels, generator=gen, dtype=dtype) * min(s.high - s.low, 1.0) * 0.8
         + s.low + 0.1 * min(s.high - s.low, 1.0) for s in model.params}
    q = dict(p)
    q[spec.name] = p[spec.name].clone()
    q[spec.name][:, 0] += 0.05 * min(spec.high - spec.low, 1.0)
    jo = model.cosine_brdf(g, q) - model.cosine_brdf(g, p)
    return bool(jo[:, 1:].abs().max() <= 1e-9 * (jo[:, :1].abs().max() + 1e-30))


#: Samples per block of :func:`jacobian_blocks`: the autograd graph of one evaluation holds ~0.68 kB per sample
#: (GGX + Lambert, float32: 1.5 GB above the Jacobian for 2.2 M samples at once), so blocks of 2¹⁸ samples bound
#: it near 180 MB whatever the capture's size — and run faster in cache (those 2.2 M samples: 2.0–2.5 s against
#: 3.7–3.9 s at once; 2¹⁷ 2.2 s, 2¹⁹ 2.7 s).
JACOBIAN_BLOCK = 1 << 18
#: Samples per block of the closed-form grid's normal equations (:func:`linear_solve`): a block's products, [2¹⁶, 3,
#: L, L] in float64 (6 MB for L = 2), stay in the allocator's reuse. Measured on 1.6 M samples, 262 144 texels, L = 2:
#: 0.24 s whole, 0.17 s in blocks of 2¹⁶ or 2¹⁴, 0.18–0.22 s in blocks of 2¹⁸.
SYSTEM_BLOCK = 1 << 16


def derivative_pairs(layout: Layout, d: Mapping[str, Tensor], kept: set[int]) -> list[tuple[int, int, Tensor]]:
    """``(channel, column, values [n])`` of the closed-form derivatives ``d`` (name → ``[n, 3, C]``, or the diagonal
    ``[n, 3]`` of a parameter acting per channel: :meth:`capture.observations.Observations.jacobian_rows`) at every
    (output channel, θ column) pair they can be non-zero at, the columns in ``kept`` only, in row-major order of the
    pairs."""
    pairs = []
    for spec, o in zip(layout.specs, layout.offsets, strict=True):
        dk = d.get(spec.name)
        for j in range(spec.channels):
            if dk is None or o + j not in kept:
                continue
            if dk.dim() == 2:       # a diagonal derivative: channel j of the parameter acts on output channel j
                pairs.append((j, o + j, dk[:, j]))
            else:
                pairs.extend((c, o + j, dk[:, c, j]) for c in range(3))
    return sorted(pairs, key=lambda t: (t[0], t[1]))


def jacobian_blocks(model: Model, layout: Layout, obs: Observations, phi: Tensor, groups, canonical: bool = False,
                    block: int | None = None, start: int = 0,
                    closed_form: bool = True) -> Iterator[tuple[int, int, Tensor, Tensor]]:
    """``(start, stop, pred [n, 3], J [n, 3, P])`` for blocks of ``block`` samples of :func:`jacobian`: the
    same values, with the autograd graph of one block alive at a time (default :data:`JACOBIAN_BLOCK` on the CPU,
    :func:`renderer.device.block_size` of it on a GPU). ``phi`` may hold only the samples ``start …
    start + len(phi) − 1`` of ``obs`` (a caller reading the samples' parameters a block at a time); the yielded
    ``start, stop`` are indices of ``obs``'s samples. ``closed_form``: take the model's closed-form derivatives
    where it has them (:meth:`capture.observations.Observations.jacobian_rows`; θ columns by the chain rule through
    :meth:`Layout.dcanonical`) instead of automatic differentiation."""
    if block is None:
        block = block_size(JACOBIAN_BLOCK, phi.device)
    if block < 1:
        raise SolverError(f"block must be a positive number of samples, got {block!r}")
    if not 0 <= start <= obs.n_samples - phi.shape[0]:
        raise SolverError(f"start must place the {phi.shape[0]} samples of phi among the {obs.n_samples} of the "
                          f"observations, got {start!r}")
    S, P = phi.shape
    unpack = layout.split if canonical else layout.unpack
    cols = sorted({c for cs in groups for c in cs})
    frozen = sorted(set(range(P)) - set(cols))
    kept = set(cols)
    for a in range(0, max(S, 1), block):
        b = min(a + block, S)
        if cols and closed_form:
            x = phi[a:b].detach().to(obs.dtype)
            res = obs.jacobian_rows(model, unpack(x), start + a, start + b)
            if res is not None:
                pred, d = res
                J = torch.zeros(b - a, 3, P, dtype=ACC, device=phi.device)       # (frozen columns stay 0)
                for c, col, values in derivative_pairs(layout, d, kept):
                    J[:, c, col] = values
                if not canonical:
                    J *= layout.dcanonical(x).to(ACC).unsqueeze(1)
                yield start + a, start + b, pred.to(ACC), J
                continue
        with torch.enable_grad():
            x = phi[a:b].detach().to(obs.dtype).requires_grad_(bool(cols))
            pred = obs.predict_rows(model, unpack(x), start + a, start + b)
            if cols and pred.requires_grad:
                # each channel's gradient copied whole into its row (a plain slice), the frozen columns zeroed
                # after: writing the kept columns through an index list took 1.8 s of 75 on 32 × 256² photos
                J = torch.empty(b - a, 3, P, dtype=ACC, device=phi.device)
                for c in range(3):
                    (g,) = torch.autograd.grad(pred[:, c].sum(), x, retain_graph=c < 2, allow_unused=True)
                    J[:, c] = 0.0 if g is None else g
                if frozen:
                    J[:, :, frozen] = 0.0
            else:
                J = torch.zeros(b - a, 3, P, dtype=ACC, device=phi.device)
        yield start + a, start + b, pred.detach().to(ACC), J


def jacobian(model: Model, layout: Layout, obs: Observations, phi: Tensor, groups,
             canonical: bool = False, out: tuple[Tensor, Tensor] | None = None,
             closed_form: bool = True) -> tuple[Tensor, Tensor]:
    """Prediction ``[S, 3]`` and Jacobian ``[S, 3, P]`` wrt per-sample θ ``phi [S, P]``: in closed form where the
    model has one (:meth:`materials.Model.cosine_brdf_jacobian`, unless ``closed_form`` is False), else by
    reverse-mode AD.

    A sample's prediction depends only on its own parameters, so the gradient of ``Σ_s pred_sc`` with
    respect to ``phi`` holds row s of ``∂pred_c/∂phi`` for every sample: one evaluation and three backward
    passes (one per colour channel) give the whole Jacobian, in blocks of samples (:func:`jacobian_blocks`). The
    columns of ``groups`` (:func:`param_groups`) are filled, the others are zero (frozen parameters). Measured on
    the default scene (204 000 samples, P = 7, 2 threads): 132–144 ms against 196–321 ms for one forward-mode
    (dual tensor) pass per group — in torch 2.13 binary ops on dual tensors run Python reference
    implementations, and the first one imports ``torch._dynamo`` (~1 s per process).

    ``canonical=True``: ``phi`` holds canonical values and the Jacobian is with respect to them. ``out``: float64
    arrays ``([S, 3], [S, 3, P])`` to write them into (every row is written).
    """
    S, P = phi.shape
    if out is None:
        pred = torch.zeros(S, 3, dtype=ACC, device=phi.device)
        J = torch.zeros(S, 3, P, dtype=ACC, device=phi.device)
    else:
        pred, J = out
        if tuple(pred.shape) != (S, 3) or tuple(J.shape) != (S, 3, P) or pred.dtype != ACC or J.dtype != ACC:
            raise SolverError(f"out must be float64 arrays of shapes ({S}, 3) and ({S}, 3, {P}), got "
                              f"{tuple(pred.shape)} {pred.dtype} and {tuple(J.shape)} {J.dtype}")
    for a, b, pb, Jb in jacobian_blocks(model, layout, obs, phi, groups, canonical, closed_form=closed_form):
        pred[a:b], J[a:b] = pb, Jb
    return pred, J


def sample_cost(obs: Observations, pred: Tensor, loss: str, delta: float) -> Tensor:
    """``[S]`` per-sample data term ``weight_s Σ_c ρ(y_sc − pred_sc)`` (``pred`` ``[S, 3]``) — what every solver
    minimises, per texel (:func:`texel_cost`) or in total (:func:`weighted_cost`)."""
    return robust_rho(obs.radiance.to(ACC) - pred.to(ACC), loss, delta).sum(-1) * obs.weight.to(ACC)


def texel_cost(obs: Observations, pred: Tensor, loss: str, delta: float) -> Tensor:
    """``[T]`` the data term per texel (:func:`sample_cost` summed over each texel's samples)."""
    return torch.zeros(obs.n_texels, dtype=ACC, device=pred.device).index_add(
        0, obs.texel, sample_cost(obs, pred, loss, delta))


def _neighbour_sum(theta: Tensor, H: int, W: int, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Sum of the 4-neighbours' θ ``[T, P]`` over valid neighbours and their count ``[T, 1]``."""
    P = theta.shape[-1]
    x = (theta * valid[:, None]).reshape(H, W, P).permute(2, 0, 1)[None]
    m = valid.to(theta.dtype).reshape(1, 1, H, W)
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=theta.dtype, device=theta.device)
    s = F.conv2d(F.pad(x, (1, 1, 1, 1)), k.expand(P, 1, 3, 3).contiguous(), groups=P)
    c = F.conv2d(F.pad(m, (1, 1, 1, 1)), k[None, None])
    return s[0].permute(1, 2, 0).reshape(-1, P), c.reshape(-1, 1)


def weighted_cost(obs: Observations, pred: Tensor, loss: str, delta: float) -> float:
    """The total data term ``Σ_s weight_s Σ_c ρ(y_sc − pred_sc)`` (:func:`sample_cost`)."""
    return float(sample_cost(obs, pred, loss, delta).sum())


def data_cost(model: Model, layout: Layout, obs: Observations, theta: Tensor, *, sampling: str, loss: str,
              delta: float) -> float:
    """The data term of θ ``[T, P]`` under ``sampling`` ("nearest" | "bilinear"), per residual (3 · Σ weight)."""
    with torch.no_grad():
        prm = {k: v.reshape(*obs.map_size, -1).to(obs.dtype) for k, v in layout.unpack(theta).items()}
        pred = obs.predict(model, obs.per_sample(prm, sampling))
    return weighted_cost(obs, pred, loss, delta) / float(3 * obs.weight.to(ACC).sum())


def grid_values(spec: ParamSpec, G: int, dtype, device) -> Tensor:
    """Grid of the main nonlinear parameter: geometric in [0.02, 1]·range for a bounded one (a
    highlight's peak scales like 1/α² = 1/r⁴, so relative spacing is what matters), log-spaced
    in [0.01, 10] for [lo, ∞)."""
    if bounded(spec):
        u = torch.logspace(math.log10(0.02), 0.0, G, dtype=dtype, device=device) * 0.98
        return spec.low + (spec.high - spec.low) * u
    return torch.logspace(-2, 1, G, dtype=dtype, device=device) + spec.low


def linear_solve(model: Model, layout: Layout, obs: Observations, theta: Tensor, lin: list[ParamSpec],
                  sep: dict[str, bool], loss: str, delta: float) -> tuple[Tensor, Tensor]:
    """Closed-form weighted least squares for the linear parameters per texel, others held at θ.

    With the nonlinear parameters fixed the prediction is ``b + A x`` (x: the linear parameters'
    channels), so per texel ``x = (AᵀWA + λI)⁻¹ (AᵀW(y − b) + λ x_default)`` with a tiny ridge λ
    toward the defaults (keeps unobserved combinations sensible). ``A`` is found by evaluating the
    model at x = 0 and at each unit x (one evaluation per parameter for separable RGB ones; for a
    :class:`materials.model.SumModel` only the parts that read that parameter). When
    every linear parameter is a separable RGB one (albedo, f0 under Schlick), the system splits
    into three independent per-channel systems of size #linear (2×2 for GGX + Lambert).
    Bounds: a solution outside the range is clipped ``1e-4``·range inside it (a value on the
    bound would saturate the sigmoid, dp/dθ = 0) and the other unknowns of that system are
    re-solved once with the clipped ones fixed (one active-set pass). Returns θ and the per-texel cost.
    """
    T = obs.n_texels
    y, w = obs.radiance.to(ACC), obs.weight.to(ACC)
    per_channel = all(s.channels == 3 and sep[s.name] for s in lin)
    b, cols = _unit_responses(model, layout, obs, theta, lin, sep, per_channel)
    system = _linear_system(obs, lin, cols, per_channel, y, w, b)
    x = _bounded_solve(system)
    xflat = x.transpose(-1, -2).reshape(T, -1) if per_channel else x[:, 0]           # [T, L] in [param][channel]
    if loss == "l2":
        # Σ_s w_s ‖y_s − b_s − A_s x‖² = c₀ − 2 xᵀ rhs + xᵀ M x per texel, from the normal equations (without
        # the ridge): no per-sample prediction. Measured on the default scene: 57 → 14 ms of a 167 ms solve
        c0 = torch.zeros(T, dtype=ACC, device=obs.device).index_add(0, obs.texel, (y - b).square().sum(-1) * w)
        cost = (c0 + (x * ((system.M @ x[..., None])[..., 0] - 2 * system.rhs)).sum((-2, -1))).clamp_min(0.0)
    else:
        if per_channel:
            pred = b + (system.A * torch.index_select(x, 0, obs.texel)).sum(-1)
        else:
            pred = b + torch.einsum("scp,sp->sc", system.A, torch.index_select(xflat, 0, obs.texel))
        cost = texel_cost(obs, pred, loss, delta)
    cand = theta.clone()
    off = 0
    for s in lin:
        cand[:, layout.cols(s.name)] = from_canonical(s, xflat[:, off:off + s.channels])
        off += s.channels
    return cand, cost


def _response_columns(lin: list[ParamSpec], sep: dict[str, bool], per_channel: bool,
                      whole: Callable[[ParamSpec], Tensor],
                      single: Callable[[ParamSpec, int], Tensor]) -> list[Tensor]:
    """:func:`_unit_responses`' columns from the ``[S, 3]`` responses to a unit value of every channel of a
    parameter (``whole``) or of its channel c alone (``single``): one column per parameter that is scalar or, per
    channel, separable; a separable RGB one otherwise split into its channels' parts; the others one per channel."""
    cols = []
    for s in lin:
        if sep[s.name] or s.channels == 1:
            a = whole(s)
            if s.channels == 1 or per_channel:
                cols.append(a)
            else:
                for c in range(3):
                    e = torch.zeros_like(a)
                    e[:, c] = a[:, c]
                    cols.append(e)
        else:
            cols.extend(single(s, c) for c in range(s.channels))
    return cols


def _closed_form_responses(closed: tuple[Tensor, dict[str, Tensor]], lin: list[ParamSpec], sep: dict[str, bool],
                           per_channel: bool) -> tuple[Tensor, list[Tensor]]:
    """:func:`_unit_responses` from the model's closed form at the linear parameters' zero (value and derivatives,
    :meth:`capture.observations.Observations.jacobian_rows`): a parameter the prediction is affine in has its unit
    response as its derivative, so one evaluation gives every column."""
    b, d = closed

    def zero() -> Tensor:                                 # the response to a parameter the model does not read
        return torch.zeros(b.shape[0], 3, dtype=ACC, device=b.device)

    def whole(s: ParamSpec) -> Tensor:                    # a diagonal derivative [S, 3] is this response already
        dk = d.get(s.name)
        return zero() if dk is None else dk.to(ACC) if dk.dim() == 2 else dk.to(ACC).sum(-1)

    def single(s: ParamSpec, c: int) -> Tensor:
        dk = d.get(s.name)
        if dk is None or dk.dim() == 3:
            return zero() if dk is None else dk[:, :, c].to(ACC)
        e = zero()
        e[:, c] = dk[:, c]
        return e

    cols = _response_columns(lin, sep, per_channel, whole, single)
    return b.to(ACC), cols


def _unit_responses(model: Model, layout: Layout, obs: Observations, theta: Tensor, lin: list[ParamSpec],
                    sep: dict[str, bool], per_channel: bool) -> tuple[Tensor, list[Tensor]]:
    """For :func:`linear_solve`: the prediction ``b [S, 3]`` with the linear parameters at 0 (the others at θ) and
    per unknown column the ``[S, 3]`` response to a unit value of it (one column per parameter when
    ``per_channel``, the channels' systems being separate)."""
    p = {k: torch.index_select(x, 0, obs.texel) for k, x in layout.unpack(theta.to(obs.dtype)).items()}
    for s in lin:
        p[s.name] = torch.zeros_like(p[s.name])
    closed = obs.jacobian_rows(model, p, 0, obs.n_samples)
    if closed is not None:
        return _closed_form_responses(closed, lin, sep, per_channel)
    # a sum of lobes is evaluated part by part, so that a unit change of a linear parameter re-evaluates only the
    # parts that read it: GGX + Lambert costs 2 specular + 2 Lambert evaluations instead of 3 of both (measured on
    # the default scene, 2 threads: 56 against 83 ms). Environment lights are evaluated by the whole model.
    parts = list(model.parts) if isinstance(model, SumModel) and not obs.env_terms else [model]
    at_zero = [obs.predict(part, p).to(ACC) for part in parts]
    b = sum(at_zero[1:], at_zero[0])

    def response(q: dict, name: str) -> Tensor:         # change of the prediction from p to q (q differs in `name`)
        return sum(obs.predict(part, q).to(ACC) - at_zero[j] for j, part in enumerate(parts)
                   if name in part.param_names)

    def whole(s: ParamSpec) -> Tensor:
        q = dict(p)
        q[s.name] = torch.ones_like(p[s.name])
        return response(q, s.name)

    def single(s: ParamSpec, c: int) -> Tensor:
        q = dict(p)
        e = torch.zeros_like(p[s.name])
        e[:, c] = 1.0
        q[s.name] = e
        return response(q, s.name)

    return b, _response_columns(lin, sep, per_channel, whole, single)


class _LinearSystem(NamedTuple):
    """The per-texel normal equations of :func:`linear_solve`: ``M [T, K, n, n]``, ``rhs [T, K, n]`` — K = 3
    per-channel systems over the parameters, or one over all channels —, the responses ``A`` and per unknown the
    bounds ``lo``, ``hi`` (``1e-4``·range inside the range) and the default."""

    A: Tensor
    M: Tensor
    rhs: Tensor
    lo: Tensor
    hi: Tensor
    default: Tensor


def _linear_system(obs: Observations, lin: list[ParamSpec], cols: list[Tensor], per_channel: bool, y: Tensor,
                   w: Tensor, b: Tensor) -> _LinearSystem:
    """The normal equations of :func:`linear_solve` from the unit responses ``cols`` and the prediction ``b`` at 0."""
    T, dt, dev = obs.n_texels, ACC, obs.device
    lo = torch.cat([torch.full((s.channels,), float(s.low), dtype=dt, device=dev) for s in lin])
    hi = torch.cat([torch.full((s.channels,), float(s.high), dtype=dt, device=dev) for s in lin])
    span = torch.where(torch.isfinite(hi), hi - lo, torch.ones_like(hi))
    lo_m, hi_m = lo + 1e-4 * span, torch.where(torch.isfinite(hi), hi - 1e-4 * span, hi)
    dflt = torch.cat([s.full((), dtype=dt, device=dev).expand(s.channels) for s in lin])
    A = torch.stack(cols, -1)                                             # [S, 3, L]
    S, L = A.shape[0], A.shape[-1]
    # the per-sample products summed into the texels a block of samples at a time, in place: whole, they were an
    # [S, 3, L, L] array and the sums a fresh copy of the zeros (0.24 → 0.17 s per call on 1.6 M samples, the same
    # values to the last bit: index_add_ adds in the samples' order either way)
    step = block_size(SYSTEM_BLOCK, dev)
    if per_channel:
        # unknowns ordered [param][channel] → per channel c a system over the params
        M = torch.zeros(T, 3, L, L, dtype=dt, device=dev)
        rhs = torch.zeros(T, 3, L, dtype=dt, device=dev)
        for i in range(0, S, step):
            j = min(i + step, S)
            Ab, tex = A[i:j], obs.texel[i:j]
            M.index_add_(0, tex, Ab[..., :, None] * Ab[..., None, :] * w[i:j, None, None, None])
            rhs.index_add_(0, tex, Ab * ((y[i:j] - b[i:j]) * w[i:j, None])[..., None])
        perm = lambda v: v.reshape(L, 3).T  # noqa: E731  [L] in [param][channel] order → [3, L]
        return _LinearSystem(A, M, rhs, perm(lo_m), perm(hi_m), perm(dflt))
    M = torch.zeros(T, L, L, dtype=dt, device=dev)
    rhs = torch.zeros(T, L, dtype=dt, device=dev)
    for i in range(0, S, step):
        j = min(i + step, S)
        Ab, tex = A[i:j], obs.texel[i:j]
        M.index_add_(0, tex, torch.einsum("scp,s,scq->spq", Ab, w[i:j], Ab))
        rhs.index_add_(0, tex, torch.einsum("scp,s,sc->sp", Ab, w[i:j], y[i:j] - b[i:j]))
    M, rhs = M[:, None], rhs[:, None]
    return _LinearSystem(A, M, rhs, lo_m[None], hi_m[None], dflt[None])


def _bounded_solve(system: _LinearSystem) -> Tensor:
    """``x [T, K, n]``: the solution of ``system`` with a tiny ridge toward the defaults, clipped into the bounds,
    the unknowns of a system with a clipped one re-solved once with those fixed."""
    M, rhs, lo_c, hi_c, d_c = system.M, system.rhs, system.lo, system.hi, system.default
    n = M.shape[-1]
    eye = torch.eye(n, dtype=ACC, device=M.device)
    lam = 1e-9 * (torch.diagonal(M, dim1=-2, dim2=-1).mean(-1) + 1e-20)                 # [T, K]
    Mr = M + lam[..., None, None] * eye
    rr = rhs + lam[..., None] * d_c
    x = torch.linalg.solve_ex(Mr, rr)[0]
    clip = (x < lo_c) | (x > hi_c)
    if bool(clip.any()):
        xc = x.clamp(lo_c, hi_c)
        # active set: fixed (clipped) unknowns leave the system; the free ones are re-solved
        free = ~clip
        fm = free[..., :, None] & free[..., None, :]
        Mf = torch.where(fm, Mr, eye.expand_as(Mr))
        rf = torch.where(free, rr - torch.einsum("...pq,...q->...p", torch.where(free[..., None, :], 0.0, Mr),
                                                 torch.where(clip, xc, torch.zeros_like(xc))), xc)
        x2 = torch.linalg.solve_ex(Mf, rf)[0]
        x = torch.where(clip, xc, x2).clamp(lo_c, hi_c)
    return x

def _start_values(spec: ParamSpec) -> list[float]:
    """Starting values of a secondary nonlinear parameter for the closed-form initialisation: its
    default, or for a bounded RGB one (e.g. f0 where it is not linear: Gotanda's diffuse·(1 − f0), the
    coat-relative f0 of the layered model) 10 % and 90 % of its range. A metal's f0 is a different
    basin from a dielectric's, which LM from 0.04 did not reach (gold under a coat: cost 20 from one
    start, 3e-21 from both), and f0 = 0.04 under a coat of η 1.5 is a stationary point (the bottom is
    index-matched: relative f0 = 0 with zero derivative), so the default itself is not a start."""
    if spec.channels == 3 and bounded(spec) and not spec.linear:
        return [spec.low + 0.1 * (spec.high - spec.low), spec.low + 0.9 * (spec.high - spec.low)]
    return [spec.default]


def closed_form_init(model: Model, layout: Layout, obs: Observations, theta: Tensor, grid: int,
                      loss: str, delta: float, sep: dict[str, bool], refine: int = 3,
                      fixed: Sequence[str] = ()) -> tuple[Tensor, dict]:
    """Closed-form linear parameters per texel for each of ``grid`` values of the main nonlinear
    one; keep the best per texel, then coarse to fine: ``refine`` rounds, each trying the best
    value ± h (log units) and the vertex of the parabola through those three costs (three
    closed-form solves with per-texel values), keeping the best and dividing h by 3.

    The other nonlinear parameters stay at θ — or, when some have several :func:`_start_values`
    (and are not in ``fixed``, i.e. given by the caller's ``init``), the search runs once per
    combination of starts and each texel keeps its cheapest."""
    lin = [s for s in layout.specs if s.linear]
    nonlin = [s for s in layout.specs if not s.linear]
    info = {"linear": [s.name for s in lin], "grid_param": None, "grid": 0}
    if not lin:
        return theta, info
    primary = next((s for s in nonlin if s.channels == 1), None)
    with torch.no_grad():
        if primary is None or grid <= 1:
            cand, _ = linear_solve(model, layout, obs, theta, lin, sep, loss, delta)
            return cand, info
        values = grid_values(primary, grid, ACC, obs.device)
        info.update(grid_param=primary.name, grid=len(values))
        multi = [s for s in nonlin if s is not primary and s.name not in fixed and len(_start_values(s)) > 1]
        best, best_cost, n_solves = None, None, 0
        for combo in itertools.product(*(_start_values(s) for s in multi)):
            th = theta.clone()
            for s, val in zip(multi, combo, strict=True):
                th[:, layout.cols(s.name)] = from_canonical(s, torch.full_like(th[:, layout.cols(s.name)], val))
            cand, cost, n = _grid_search(model, layout, obs, th, primary, values, lin, sep, loss, delta, refine)
            n_solves += n
            if best is None:
                best, best_cost = cand, cost
            else:
                better = cost < best_cost
                best = torch.where(better[:, None], cand, best)
                best_cost = torch.where(better, cost, best_cost)
        info["grid_solves"] = n_solves
        if multi:
            info["grid_starts"] = {s.name: _start_values(s) for s in multi}
    return best, info


def _grid_search(model: Model, layout: Layout, obs: Observations, theta: Tensor, primary: ParamSpec,
                 values: Tensor, lin: list[ParamSpec], sep: dict[str, bool], loss: str, delta: float,
                 refine: int) -> tuple[Tensor, Tensor, int]:
    """One grid + coarse-to-fine search of :func:`closed_form_init` → (θ [T, P], cost [T], solves)."""
    T, dt, dev = obs.n_texels, ACC, obs.device
    pc = layout.cols(primary.name)
    ar = torch.arange(T, device=dev)

    def at(x):                       # closed-form solve at per-texel log-values x [T]
        th = theta.clone()
        th[:, pc] = from_canonical(primary, torch.exp(x)[:, None].clamp(primary.low, primary.high))
        return linear_solve(model, layout, obs, th, lin, sep, loss, delta)

    costs, cands = [], []
    for val in values:
        th = theta.clone()
        th[:, pc] = from_canonical(primary, val.expand(T, 1))
        cand, cost = linear_solve(model, layout, obs, th, lin, sep, loss, delta)
        costs.append(cost)
        cands.append(cand)
    costs_t = torch.stack(costs)                                       # [G, T]
    k = costs_t.argmin(0)
    best = torch.stack(cands)[k, ar]
    best_cost = costs_t[k, ar]
    del cands
    n_solves = len(values)
    # coarse to fine (variable projection in 1-D: every trial re-solves the linear parameters):
    # each round tries x ± h and the vertex of the parabola through the three costs, keeps
    # the best of the four per texel and shrinks h by 3
    xl = torch.log(values.clamp_min(1e-12))
    h = (xl[1:] - xl[:-1]).mean() if len(values) > 1 else torch.tensor(0.5, dtype=dt, device=values.device)
    x = xl[k]
    lo, hi = math.log(max(primary.low, 1e-4)), math.log(primary.high)
    for _ in range(refine):
        xm, xp = (x - h).clamp(lo, hi), (x + h).clamp(lo, hi)
        candm, cm = at(xm)
        candp, cp = at(xp)
        den = cm - 2 * best_cost + cp
        ok = den > 0
        xv = torch.where(ok, x + 0.5 * h * (cm - cp) / den.where(ok, torch.ones_like(den)), x)
        xv = torch.minimum(torch.maximum(xv, xm), xp)
        candv, cv = at(xv)
        n_solves += 3
        for c_, k_, x_ in ((candm, cm, xm), (candp, cp, xp), (candv, cv, xv)):
            better = k_ < best_cost
            best = torch.where(better[:, None], c_, best)
            best_cost = torch.where(better, k_, best_cost)
            x = torch.where(better, x_, x)
        h = h / 3
    return best, best_cost, n_solves


#: With bilinear sampling the per-texel LM only starts the joint refinement; by default it stops after at least
#: ``BILINEAR_LM_MIN`` of its (at most 10) iterations once the total cost has dropped by less than ``BILINEAR_LM_TOL``
#: (relative) twice in a row. Measured (2 threads, cached observations; per-texel cost drops per iteration): the default
#: scene and its 2-material, 3-material and shot-noise variants drop by 1e-4–6e-4 from the first iteration and stop at
#: 5 — LM 3.2–3.4 → 1.4–2.0 s, the same maps to 4 decimals but 3 materials (0.0057 / 0.0078 / 0.0132 → 0.0059 /
#: 0.0069 / 0.0134, observable and determined-at-the-truth texels unchanged); the fixed-light rig (drops of 2e-3–6e-3
#: until the 14th) and the layered 128-px scene (1e-2–5e-1 for 20 iterations) run all 10, as before. A fixed 5 broke
#: the layered fallback test scene, which keeps dropping fast; 40 with this rule let the layered scene run
#: 33 (determined-at-the-truth 0.149 / 0.105 / 0.078 / 0.153 → 0.094 / 0.088 / 0.077 / 0.136 but all-texel f0 0.202
#: → 0.217 and more texels called observable at a wrong albedo; docs/log.md, "errors on what the photos
#: determine at the truth") — not the default.
BILINEAR_LM_TOL = 1e-3
BILINEAR_LM_MIN = 5


def per_texel_lm(model: Model, obs: Observations, layout: Layout, theta: Tensor, groups, *, loss: str, delta: float,
                 iterations: int, schedule: str, smoothness: float, reproject: int, sep: dict[str, bool],
                 lm_tol: float, min_iterations: int = 0,
                 progress: Callable[[str, int, float], None] | None = None) -> tuple[Tensor, list[float], dict]:
    """The per-texel Levenberg-Marquardt stages of :func:`capture.fit.fast.solve_fast` from θ ``[T, P]`` (the
    closed-form initialisation): ``schedule`` "joint" (all parameters every iteration) or "staged" (scale terms,
    lobe shape, then all), ``smoothness`` the weight of the neighbour prior, ``reproject`` the variable-projection
    period, ``sep`` the linear parameters' separability (:func:`separable`). Stops after ``iterations`` (all stages
    together) or, from ``min_iterations`` on, once the total cost drops by less than ``lm_tol`` (relative) twice in a
    row, or when no texel is active.

    Returns:
        ``(theta [T, P], history, info)`` — the cost after each iteration (first: the starting cost) and
        ``lm_s``, ``lm_iterations``, ``accepted`` (accepted fraction per iteration), ``stages``.
    """
    P = layout.P
    stages = _stages(layout, schedule, iterations)
    n_res_total = float(3 * obs.weight.to(ACC).sum())
    accepted = []
    it = 0
    t_lm = time.perf_counter()
    lm = _TexelLM(model, obs, layout, theta, loss=loss, delta=delta, smoothness=smoothness, reproject=reproject,
                  sep=sep)
    history: list[float] = [float(lm.cost_t.sum()) / n_res_total]
    for stage, cols, n_it in stages:
        free = torch.zeros(P, dtype=torch.bool, device=obs.device)
        free[cols] = True
        sgroups = [c for c in groups if all(free[x] for x in c)]
        stall = 0
        active = lm.observed.clone()
        for _ in range(n_it):
            it += 1
            with torch.no_grad():
                acc, live, active = lm.iterate(stage, free, sgroups, active, it)
            accepted.append(float(acc.sum()) / max(int(live.sum()), 1))
            tot = float(lm.cost_t.sum()) / n_res_total
            if progress is not None:
                progress(stage, it, tot)
            prev = history[-1]
            history.append(tot)
            if prev - tot <= lm_tol * max(prev, 1e-300):
                stall += 1
                if stall >= 2 and it >= min_iterations:
                    break
            else:
                stall = 0
            if not bool(active.any()):
                break
    info = {"lm_s": time.perf_counter() - t_lm, "lm_iterations": it, "accepted": accepted,
            "stages": [s[0] for s in stages]}
    return lm.theta, history, info


def _stages(layout: Layout, schedule: str, iterations: int) -> list[tuple[str, list[int], int]]:
    """The stages of :func:`per_texel_lm` as ``(name, columns, iterations)``: with ``schedule`` "staged" (and
    linear and nonlinear parameters) the scale terms, the lobe shape, then all; else all at once."""
    P = layout.P
    lin_cols = [c for s in layout.specs if s.linear for c in layout.cols(s.name)]
    non_cols = [c for s in layout.specs if not s.linear for c in layout.cols(s.name)]
    if schedule == "staged" and lin_cols and non_cols:
        k = max(iterations // 3, 1)
        return [("scale", lin_cols, k), ("shape", non_cols, k), ("all", list(range(P)), max(iterations - 2 * k, 1))]
    return [("all", list(range(P)), iterations)]


class _Smoothness(NamedTuple):
    """The neighbour prior of :func:`per_texel_lm` linearised at θ: weight ``mu``, the sum of the 4-neighbours' θ
    ``nsum [T, P]`` and their count ``cnt [T, 1]``."""

    mu: float
    nsum: Tensor
    cnt: Tensor

    def cost(self, th: Tensor) -> Tensor:
        """``[T]`` the prior's per-texel cost at ``th`` (up to a constant)."""
        return self.mu * ((self.cnt * th.square() - 2 * th * self.nsum).sum(-1))


class _TexelLM:
    """The state of :func:`per_texel_lm`: θ ``[T, P]``, the per-texel data cost ``cost_t [T]`` and damping ``lam
    [T]``, with one iteration's linearisation, damped solve and per-texel step acceptance (:meth:`iterate`)."""

    def __init__(self, model: Model, obs: Observations, layout: Layout, theta: Tensor, *, loss: str, delta: float,
                 smoothness: float, reproject: int, sep: dict[str, bool]):
        self.model, self.obs, self.layout, self.loss, self.delta = model, obs, layout, loss, delta
        self.smoothness, self.reproject, self.sep = smoothness, reproject, sep
        T, P = obs.n_texels, layout.P
        self.H, self.W = obs.map_size
        self.lin_specs = [s for s in layout.specs if s.linear]
        self.observed = torch.zeros(T, dtype=torch.bool, device=obs.device)
        self.observed[obs.texel] = True
        self.lam = torch.full((T,), 1e-3, dtype=ACC, device=obs.device)
        self.eye = torch.eye(P, dtype=ACC, device=obs.device)
        self.theta = theta
        with torch.no_grad():
            pred = obs.predict(model, layout.unpack(torch.index_select(theta, 0, obs.texel).to(obs.dtype)))
        self.cost_t = texel_cost(obs, pred, loss, delta)

    def iterate(self, stage: str, free: Tensor, sgroups, active: Tensor, it: int) -> tuple[Tensor, Tensor, Tensor]:
        """One LM iteration on the ``free`` columns of the ``active`` texels → ``(accepted, live, active)`` ``[T]``
        bool: the texels whose step was kept, those that took one, and those still active."""
        obs = self.obs
        sub = obs if bool(active.all()) or float(active.float().mean()) > 0.8 else obs.select(active[obs.texel])
        JtJ, Jtr = self._normal(sub, sgroups)
        d = torch.diagonal(JtJ, dim1=-2, dim2=-1).clone()
        scale = d.mean(-1, keepdim=True).clamp_min(1e-30)
        prior = None
        if self.smoothness > 0:
            observed = self.observed
            mu = self.smoothness * float(d[observed].mean()) if bool(observed.any()) else 0.0
            prior = _Smoothness(mu, *_neighbour_sum(self.theta, self.H, self.W, observed))
            JtJ = JtJ + mu * prior.cnt[:, :, None] * self.eye
            Jtr = Jtr + mu * (prior.nsum - prior.cnt * self.theta)
            d = torch.diagonal(JtJ, dim1=-2, dim2=-1).clone()
        step, live = self._damped_step(JtJ, Jtr, d, scale, free, active)
        trial = self.theta + step
        new_cost = self._trial_cost(trial, sub, active)
        if prior is not None:
            new_cost_c, old_cost_c = new_cost + prior.cost(trial), self.cost_t + prior.cost(self.theta)
        else:
            new_cost_c, old_cost_c = new_cost, self.cost_t
        acc = live & (new_cost_c < old_cost_c)
        self.theta = torch.where(acc[:, None], trial, self.theta)
        self.cost_t = torch.where(acc, new_cost, self.cost_t)
        self.lam = torch.where(acc, (self.lam / 3).clamp_min(1e-12), (self.lam * 4).clamp_max(1e12))
        # texels converged: tiny relative improvement or step
        rel = (old_cost_c - torch.where(acc, new_cost_c, old_cost_c)) / old_cost_c.clamp_min(1e-300)
        small = (step.abs().amax(-1) < 1e-9) | (acc & (rel < 1e-12)) | (self.lam >= 1e12) | (self.cost_t <= 1e-30)
        active = active & ~small
        if self.reproject and self.lin_specs and stage == "all" and it % self.reproject == 0 and sub is obs:
            self._reproject()
        return acc, live, active

    def _normal(self, sub: Observations, sgroups) -> tuple[Tensor, Tensor]:
        """Per-texel normal equations ``JᵀWJ [T, P, P]`` and ``JᵀWr [T, P]`` of the samples ``sub`` (IRLS weights)."""
        T, P = self.obs.n_texels, self.layout.P
        JtJ = torch.zeros(T, P, P, dtype=ACC, device=self.obs.device)
        Jtr = torch.zeros(T, P, dtype=ACC, device=self.obs.device)
        # block by block of samples: the Jacobian, its weighted copy and the [S, P, P] products whole raised the
        # resident memory by 0.9 GB on the 1.6 M pixel centres of 32 × 512² photos; blocked, the per-texel LM also
        # runs faster (32 × 256²: 5.5 → 3.5 s, the same fit to the last bit)
        phi = torch.index_select(self.theta, 0, sub.texel)
        for a, b, pred_s, J in jacobian_blocks(self.model, self.layout, sub, phi, sgroups):
            r = sub.radiance[a:b].to(ACC) - pred_s
            wgt = sub.weight[a:b].to(ACC)[:, None] * irls_weights(r, self.loss, self.delta)
            Jw = J * wgt[..., None]
            JtJ.index_add_(0, sub.texel[a:b], torch.einsum("scp,scq->spq", Jw, J))
            Jtr.index_add_(0, sub.texel[a:b], torch.einsum("scp,sc->sp", Jw, r))
        return JtJ, Jtr

    def _damped_step(self, JtJ: Tensor, Jtr: Tensor, d: Tensor, scale: Tensor, free: Tensor,
                     active: Tensor) -> tuple[Tensor, Tensor]:
        """The damped per-texel step (zero on frozen columns and on texels that are not live), clamped to the trust
        region, and the live texels ``[T]``. Overwrites ``JtJ``."""
        # in place on the [T, P, P] blocks: fresh [T, P, P] temporaries (diag_embed, where) cost
        # ~40 ms each on the default scene, several per iteration
        A = JtJ
        A.diagonal(dim1=-2, dim2=-1).add_(self.lam[:, None] * (d + 1e-9 * scale))
        rhs = Jtr
        if not bool(free.all()):
            # frozen columns: identity rows, zero right-hand side → zero step
            A[:, ~free, :] = 0.0
            A[:, :, ~free] = 0.0
            A[:, ~free, ~free] = 1.0
            rhs = torch.where(free[None, :], rhs, torch.zeros_like(rhs))
        live = active & (d.sum(-1) > 0)
        A[~live] = self.eye
        rhs = torch.where(live[:, None], rhs, torch.zeros_like(rhs))
        step, ok = torch.linalg.solve_ex(A, rhs)
        step = torch.where((ok == 0)[:, None] & torch.isfinite(step), step, torch.zeros_like(step))
        # trust region in θ: each component of the step is clamped to ±MAX_STEP (logit/softplus
        # units), so that a poor linearisation cannot throw a parameter into the flat tail of
        # its sigmoid (dp/dθ ≈ 0) from where it would never return. Per component, not by
        # scaling the whole step: a near-null column (absorption on its softplus floor) has an
        # enormous damped step, and scaling by it froze every other parameter
        return step.clamp(-MAX_STEP, MAX_STEP), live

    def _trial_cost(self, trial: Tensor, sub: Observations, active: Tensor) -> Tensor:
        """``[T]`` the data cost at θ ``trial``: re-evaluated on the samples ``sub`` of the active texels, the
        others keep their cost."""
        obs, model, layout = self.obs, self.model, self.layout
        if sub is obs:
            pred_t = obs.predict(model, layout.unpack(torch.index_select(trial, 0, obs.texel).to(obs.dtype)))
            return texel_cost(obs, pred_t, self.loss, self.delta)
        trial_s = torch.index_select(trial, 0, sub.texel).to(obs.dtype)
        pred_t_sub = sub.predict(model, layout.unpack(trial_s))
        new_cost = self.cost_t.clone()
        new_cost[active] = 0
        return new_cost + texel_cost(sub, pred_t_sub, self.loss, self.delta)

    def _reproject(self) -> None:
        """Variable projection: re-solve the linear parameters in closed form at the current nonlinear ones; keep
        it per texel where it lowers the cost."""
        cand, ccost = linear_solve(self.model, self.layout, self.obs, self.theta, self.lin_specs, self.sep, self.loss,
                                   self.delta)
        better = self.observed & (ccost < self.cost_t)
        self.theta = torch.where(better[:, None], cand, self.theta)
        self.cost_t = torch.where(better, ccost, self.cost_t)
