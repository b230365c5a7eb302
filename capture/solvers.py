"""Solvers: fit a material model's maps to :class:`capture.observations.Observations`.

Two paths over the same objective — a (robust) weighted sum over samples s and channels c of
``ρ(y_sc − L_sc(θ_texel(s)))`` with ``L`` the model's predicted radiance:

* :func:`solve_adam` — generic first-order path: Adam on every map at once, any model, nearest or
  bilinear sampling. Thousands of cheap iterations.
* :func:`solve_fast` — the fast path built for known geometry. With nearest-texel sampling each
  texel is an independent least-squares problem in P ≤ ~10 unknowns, so

  1. parameters a model declares linear (``ParamSpec.linear``: albedo, f0 under Schlick-type
     Fresnel, Nielsen's k_s) are solved in *closed form*, per texel, for a grid of values of the
     main nonlinear parameter (roughness); the best grid point per texel initialises
  2. Levenberg-Marquardt on all parameters, vectorised over all texels: residuals of all samples,
     the Jacobian by forward-mode AD (``torch.func.jvp``; one pass per *parameter* — an RGB
     parameter whose channels act on separate colour channels takes a single pass), per-texel
     normal equations ``JᵀWJ [T, P, P]`` and ``JᵀWr [T, P]`` accumulated with ``index_add``, a
     batched damped solve, and per-texel step acceptance with per-texel damping λ_t.

  Robust losses (Huber, L1 — Nielsen et al. recommend L1 for highlights) enter as IRLS weights;
  Nielsen's staged schedule (scale terms, then lobe shape, then all) and a smoothness prior across
  neighbouring texels (added to the normal equations) are options.

Parameters stay in range through their parameterisation, not by clamping: a parameter with range
[lo, hi] is ``lo + (hi − lo)·sigmoid(θ)``, one with range [lo, ∞) is ``lo + softplus(θ)``
(:class:`Layout`). The closed-form initialisation clips the linear solution into the range once,
before it is mapped to θ.

Both return a :class:`FitResult`: the canonical maps, which texels were observed, which
parameters were *unobservable* where (e.g. roughness where no highlight was seen: the residual's
sensitivity to a 0.1 change of the parameter is below ``observable_threshold`` of the texel's
signal), per-parameter confidence (posterior standard deviation from ``(JᵀWJ)⁻¹``, NaN where
unobserved or unobservable), and holes filled by pull-push (:func:`pull_push`) and flagged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from materials.geometry import Angles
from materials.model import Model
from materials.params import ParamSpec

from .observations import Observations

__all__ = ["Layout", "FitResult", "SolverError", "LOSSES", "solve_fast", "solve_adam", "pull_push", "robust_rho"]

LOSSES = ("l2", "huber", "l1")
_EPS_BOUND = 1e-6
#: Solver bookkeeping dtype (θ, normal equations, costs); the model is evaluated in the observations' dtype.
ACC = torch.float64
#: Largest LM step per iteration in θ units (logit/softplus), see solve_fast.
MAX_STEP = 1.0


class SolverError(ValueError):
    """Bad solver input: unknown loss/schedule, maps that do not fit the model or the observations."""


# -- parameterisation -----------------------------------------------------------------------------
def _bounded(spec: ParamSpec) -> bool:
    return math.isfinite(spec.high)


def to_canonical(spec: ParamSpec, theta: Tensor) -> Tensor:
    """Unconstrained θ → canonical value in the spec's range (sigmoid or softplus)."""
    if _bounded(spec):
        return spec.low + (spec.high - spec.low) * torch.sigmoid(theta)
    return spec.low + F.softplus(theta)


def from_canonical(spec: ParamSpec, p: Tensor) -> Tensor:
    """Canonical value → θ (inverse of :func:`to_canonical`), the value kept ``1e-6`` inside the range."""
    if _bounded(spec):
        u = ((p - spec.low) / (spec.high - spec.low)).clamp(_EPS_BOUND, 1 - _EPS_BOUND)
        return torch.log(u) - torch.log1p(-u)
    x = (p - spec.low).clamp_min(_EPS_BOUND)
    return x + torch.log(-torch.expm1(-x))


def dcanonical(spec: ParamSpec, theta: Tensor) -> Tensor:
    """dp/dθ of :func:`to_canonical` (> 0)."""
    if _bounded(spec):
        s = torch.sigmoid(theta)
        return (spec.high - spec.low) * s * (1 - s)
    return torch.sigmoid(theta)


@dataclass
class Layout:
    """How a model's parameters are packed into one per-texel vector θ ``[..., P]``.

    Each parameter occupies ``channels`` consecutive columns, in ``model.params`` order.
    """

    specs: tuple[ParamSpec, ...]
    offsets: tuple[int, ...]
    P: int

    @staticmethod
    def of(model: Model) -> Layout:
        offs, o = [], 0
        for s in model.params:
            offs.append(o)
            o += s.channels
        return Layout(tuple(model.params), tuple(offs), o)

    def cols(self, name: str) -> list[int]:
        for s, o in zip(self.specs, self.offsets, strict=True):
            if s.name == name:
                return list(range(o, o + s.channels))
        raise KeyError(name)

    def unpack(self, theta: Tensor) -> dict[str, Tensor]:
        """θ ``[..., P]`` → canonical parameters ``name → [..., C]``."""
        so = zip(self.specs, self.offsets, strict=True)
        return {s.name: to_canonical(s, theta[..., o:o + s.channels]) for s, o in so}

    def pack(self, params: Mapping[str, Tensor]) -> Tensor:
        """Canonical parameters ``name → [..., C or 1]`` → θ ``[..., P]``."""
        parts = []
        for s in self.specs:
            x = params[s.name]
            if x.shape[-1] == 1 and s.channels > 1:
                x = x.expand(*x.shape[:-1], s.channels)
            parts.append(from_canonical(s, x))
        return torch.cat(parts, -1)

    def dcanonical(self, theta: Tensor) -> Tensor:
        """dp/dθ per column ``[..., P]``."""
        so = zip(self.specs, self.offsets, strict=True)
        return torch.cat([dcanonical(s, theta[..., o:o + s.channels]) for s, o in so], -1)


# -- losses ---------------------------------------------------------------------------------------
def _check_loss(loss: str) -> str:
    if loss not in LOSSES:
        raise SolverError(f"unknown loss {loss!r}; choose one of {LOSSES}")
    return loss


def robust_rho(r: Tensor, loss: str, delta: float) -> Tensor:
    """Per-residual cost: l2 ``r²``; huber ``r²`` for |r| ≤ δ else ``2δ|r| − δ²``; l1 ``2δ|r|``
    (scaled so that the three agree to first order at |r| = δ)."""
    a = r.abs()
    if loss == "l2":
        return r * r
    if loss == "huber":
        return torch.where(a <= delta, r * r, 2 * delta * a - delta * delta)
    return 2 * delta * a


def _irls(r: Tensor, loss: str, delta: float) -> Tensor:
    """IRLS weight ρ'(r)/(2r) of :func:`robust_rho`."""
    if loss == "l2":
        return torch.ones_like(r)
    a = r.abs()
    if loss == "huber":
        return torch.where(a <= delta, torch.ones_like(r), delta / a.clamp_min(1e-30))
    return delta / a.clamp_min(1e-3 * delta)


# -- result ---------------------------------------------------------------------------------------
@dataclass
class FitResult:
    """Output of a solver.

    Attributes:
        maps: canonical maps ``name → [H, W, C]``, holes filled (see ``filled``).
        observed: ``[H, W]`` bool, texels with at least one valid sample.
        unobservable: ``name → [H, W]`` bool, observed texels where the photos do not constrain
            the parameter (value filled from neighbours, flagged).
        filled: ``name → [H, W]`` bool, texels whose value was filled (unobserved or unobservable).
        confidence: ``name → [H, W, C]`` posterior standard deviation of the parameter (canonical
            units; 0 for a perfect noise-free fit), NaN where filled.
        sensitivity: ``name → [H, W]`` relative residual change for a 0.1 change of the parameter.
        history: total cost after each iteration (robust, weighted, per sample-channel mean).
        iterations: iterations run; time_s: wall time of the solve; solver: "fast" or "adam".
        info: solver-specific numbers (grid time, LM time, accepted fraction, ...).
        raw: the fitted maps before filling (what best explains the photos; use for re-renders).
    """

    maps: dict[str, Tensor]
    observed: Tensor
    unobservable: dict[str, Tensor]
    filled: dict[str, Tensor]
    confidence: dict[str, Tensor]
    sensitivity: dict[str, Tensor]
    history: list[float]
    iterations: int
    time_s: float
    solver: str
    info: dict = field(default_factory=dict)
    raw: dict = field(default_factory=dict)


# -- helpers --------------------------------------------------------------------------------------
def _check_inputs(model: Model, obs: Observations, loss: str) -> None:
    if not isinstance(model, Model):
        raise SolverError(f"model must be a materials.Model (materials.get(name)), got {type(model).__name__}")
    if not isinstance(obs, Observations):
        raise SolverError(f"obs must be capture.observations.Observations, got {type(obs).__name__}")
    if obs.n_samples == 0:
        raise SolverError("no observations to fit (0 valid samples)")
    if not model.params:
        raise SolverError(f"model '{model.name}' has no parameters to fit")
    _check_loss(loss)


def _default_delta(obs: Observations, loss: str, delta: float | None) -> float:
    if delta is not None:
        if not (delta > 0 and math.isfinite(delta)):
            raise SolverError(f"delta must be a positive finite number (radiance units), got {delta!r}")
        return float(delta)
    # 5 % of the median measured radiance: larger residuals (highlight misfits, outliers) are damped
    med = obs.radiance.abs().mean(-1).median().item()
    return 0.05 * max(med, 1e-6)


def _init_theta(model: Model, layout: Layout, obs: Observations, init: Mapping[str, Tensor] | None) -> Tensor:
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
            params[k] = m.reshape(T, -1).to(dt, dev).expand(T, model.spec(k).channels)
    return layout.pack(params)


def _separable(model: Model, spec: ParamSpec, dtype) -> bool:
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
    tangent = {k: torch.zeros_like(x) for k, x in p.items()}
    tangent[spec.name][:, 0] = 1.0

    def f(q):
        return model.cosine_brdf(g, q)

    _, jo = torch.func.jvp(f, (p,), (tangent,))
    return bool(jo[:, 1:].abs().max() <= 1e-9 * (jo[:, :1].abs().max() + 1e-30))


def _groups(model: Model, layout: Layout, dtype) -> list[tuple[list[int], bool]]:
    """Jacobian passes: (columns, diagonal?) — a separable RGB parameter is one diagonal pass."""
    out = []
    for s, o in zip(layout.specs, layout.offsets, strict=True):
        if s.channels == 3 and _separable(model, s, dtype):
            out.append((list(range(o, o + 3)), True))
        else:
            out.extend(([c], False) for c in range(o, o + s.channels))
    return out


def _jacobian(model: Model, layout: Layout, obs: Observations, phi: Tensor, groups) -> tuple[Tensor, Tensor]:
    """Prediction ``[S, 3]`` and Jacobian ``[S, 3, P]`` wrt per-sample θ ``phi [S, P]`` by forward-mode AD."""
    S, P = phi.shape

    phi = phi.to(obs.dtype)

    def f(x):
        return obs.predict(model, layout.unpack(x))

    J = torch.zeros(S, 3, P, dtype=ACC, device=phi.device)
    pred = None
    for cols, diag in groups:
        t = torch.zeros_like(phi)
        t[:, cols] = 1.0
        pred, jo = torch.func.jvp(f, (phi,), (t,))
        if diag:
            for c, col in enumerate(cols):
                J[:, c, col] = jo[:, c]
        else:
            J[:, :, cols[0]] = jo
    return pred.to(ACC), J


def _texel_cost(obs: Observations, pred: Tensor, loss: str, delta: float) -> Tensor:
    rho = robust_rho(obs.radiance.to(ACC) - pred.to(ACC), loss, delta).sum(-1) * obs.weight.to(ACC)
    return torch.zeros(obs.n_texels, dtype=ACC, device=pred.device).index_add(0, obs.texel, rho)


def _neighbour_sum(theta: Tensor, H: int, W: int, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Sum of the 4-neighbours' θ ``[T, P]`` over valid neighbours and their count ``[T, 1]``."""
    P = theta.shape[-1]
    x = (theta * valid[:, None]).reshape(H, W, P).permute(2, 0, 1)[None]
    m = valid.to(theta.dtype).reshape(1, 1, H, W)
    k = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=theta.dtype, device=theta.device)
    s = F.conv2d(F.pad(x, (1, 1, 1, 1)), k.expand(P, 1, 3, 3).contiguous(), groups=P)
    c = F.conv2d(F.pad(m, (1, 1, 1, 1)), k[None, None])
    return s[0].permute(1, 2, 0).reshape(-1, P), c.reshape(-1, 1)


def pull_push(values: Tensor, known: Tensor, levels: int | None = None) -> Tensor:
    """Fill unknown texels of a map ``[H, W, C]`` from known ones (``known [H, W]`` bool) by pull-push.

    Pull: average known texels into a pyramid of half-resolution levels (weighted by how many
    known texels each covers); push: from coarse to fine, every unknown texel takes the upsampled
    coarser value. Known texels are returned unchanged. Vectorised (avg_pool / interpolate per
    level, log2(max(H, W)) levels). With no known texel at all the map is returned unchanged.
    """
    if values.dim() != 3 or known.shape != values.shape[:2]:
        raise SolverError(f"pull_push: values must be [H, W, C] and known [H, W], got {tuple(values.shape)} and "
                          f"{tuple(known.shape)}")
    if not bool(known.any()):
        return values.clone()
    H, W, C = values.shape
    w = known.to(values.dtype)[None, None]
    x = (values * known[..., None]).permute(2, 0, 1)[None]
    levels = levels or max(1, math.ceil(math.log2(max(H, W))))
    pyr = [(x, w)]
    for _ in range(levels):
        x, w = pyr[-1]
        if x.shape[-1] == 1 and x.shape[-2] == 1:
            break
        x2 = F.avg_pool2d(x, 2, ceil_mode=True) * 4
        w2 = F.avg_pool2d(w, 2, ceil_mode=True) * 4
        pyr.append((x2, w2))
    # normalise each level to means where weight > 0
    means = [(x / w.clamp_min(1e-12), (w > 0).to(x.dtype)) for x, w in pyr]
    cur, cur_ok = means[-1]
    for m, ok in reversed(means[:-1]):  # noqa: B007
        up = F.interpolate(cur, size=m.shape[-2:], mode="nearest")
        cur = torch.where(ok > 0, m, up)
    out = cur[0].permute(1, 2, 0)
    return torch.where(known[..., None], values, out)


def _finalize(model: Model, layout: Layout, obs: Observations, theta: Tensor, groups, *, loss: str, delta: float,
              observable_threshold: float, history: list[float], iterations: int, t0: float, solver: str,
              info: dict) -> FitResult:
    """Confidence, observability, pull-push filling → :class:`FitResult`."""
    H, W = obs.map_size
    T, P = obs.n_texels, layout.P
    theta = theta.to(ACC)
    with torch.no_grad():
        pred, J = _jacobian(model, layout, obs, theta[obs.texel], groups)
        r = obs.radiance.to(ACC) - pred
        w = (obs.weight.to(ACC)[:, None] * _irls(r, loss, delta))
        JtJ = torch.zeros(T, P, P, dtype=theta.dtype, device=theta.device).index_add(
            0, obs.texel, torch.einsum("scp,sc,scq->spq", J, w, J))
        n_res = torch.zeros(T, dtype=theta.dtype, device=theta.device).index_add(
            0, obs.texel, 3 * obs.weight.to(ACC))
        sig2 = torch.zeros(T, dtype=theta.dtype, device=theta.device).index_add(
            0, obs.texel, (w * r * r).sum(-1))
        signal = torch.zeros(T, dtype=theta.dtype, device=theta.device).index_add(
            0, obs.texel, obs.weight.to(ACC) * obs.radiance.to(ACC).square().sum(-1))
        observed = n_res > 0
        dp = layout.dcanonical(theta)                                              # [T, P]
        diag = torch.diagonal(JtJ, dim1=-2, dim2=-1) / dp.square().clamp_min(1e-300)  # canonical units
        rms_signal = (signal / n_res.clamp_min(1)).sqrt().clamp_min(1e-12)
        # marginal information of each parameter with the others re-optimised: 1 / [(JᵀWJ)⁻¹]_pp,
        # from a ridge-regularised inverse so that a direction no residual constrains (fewer
        # residuals than parameters, or a trade-off such as albedo vs f0 without highlights) gets
        # a huge variance instead of pinv's zero
        # observability in *relative* residuals (each sample weighted by 1/y², floored at 1 % of
        # the texel's mean radiance), so that bright highlights do not hide the diffuse samples
        y = obs.radiance.to(ACC)
        ymean = torch.zeros(T, dtype=ACC, device=y.device).index_add(0, obs.texel, y.abs().mean(-1))
        cnt = torch.bincount(obs.texel, minlength=T).to(ACC).clamp_min(1)
        floor = (0.01 * ymean / cnt)[obs.texel][:, None]
        wrel = obs.weight.to(ACC)[:, None] / (y.square() + floor.square()).clamp_min(1e-300)
        JtJr = torch.zeros(T, P, P, dtype=ACC, device=y.device).index_add(
            0, obs.texel, torch.einsum("scp,sc,scq->spq", J, wrel, J))
        ridge = 1e-10 * (torch.diagonal(JtJr, dim1=-2, dim2=-1).amax(-1, keepdim=True) + 1e-30)
        A = JtJr + torch.diag_embed(ridge.expand(T, P))
        A = torch.where(observed[:, None, None], A, torch.eye(P, dtype=A.dtype, device=A.device))
        eyeT = torch.eye(P, dtype=A.dtype, device=A.device).expand(T, P, P)
        cov_rel = torch.diagonal(torch.linalg.solve(A, eyeT), dim1=-2, dim2=-1).clamp_min(1e-300)
        marginal = 1.0 / (cov_rel * dp.square().clamp_min(1e-300))             # canonical units
        sens = 0.1 * (marginal / n_res.clamp_min(1)[:, None]).sqrt()            # [T, P] relative change
        del rms_signal
        ridge = 1e-10 * (torch.diagonal(JtJ, dim1=-2, dim2=-1).amax(-1, keepdim=True) + 1e-30)
        A = JtJ + torch.diag_embed(ridge.expand(T, P))
        A = torch.where(observed[:, None, None], A, torch.eye(P, dtype=A.dtype, device=A.device))
        cov_diag = torch.diagonal(torch.linalg.solve(A, eyeT), dim1=-2, dim2=-1).clamp_min(0)
        del diag
        # posterior std: sigma² (JᵀWJ)⁻¹ in θ, mapped by dp/dθ
        dof = (n_res - P).clamp_min(1)
        s2 = sig2 / dof
        std = (s2[:, None] * cov_diag.clamp_min(0)).sqrt() * dp
    params = layout.unpack(theta.detach().to(obs.dtype))
    maps, unobs, filled, conf, sensitivity = {}, {}, {}, {}, {}
    obs_hw = observed.reshape(H, W)
    for s, o in zip(layout.specs, layout.offsets, strict=True):
        sl = slice(o, o + s.channels)
        sp = sens[:, sl].amax(-1)
        bad = observed & (sp < observable_threshold)
        val = params[s.name].reshape(H, W, s.channels)
        known = (observed & ~bad).reshape(H, W)
        fill_val = pull_push(val, known) if bool(known.any()) else s.full((H, W), device=val.device, dtype=val.dtype)
        maps[s.name] = torch.where(known[..., None], val, fill_val)
        unobs[s.name] = bad.reshape(H, W)
        filled[s.name] = ~known
        c = std[:, sl].reshape(H, W, s.channels).clone()
        c[~known] = float("nan")
        conf[s.name] = c
        sensitivity[s.name] = torch.where(obs_hw, sp.reshape(H, W), torch.full_like(sp.reshape(H, W), float("nan")))
    return FitResult(maps=maps, observed=obs_hw, unobservable=unobs, filled=filled, confidence=conf,
                     sensitivity=sensitivity, history=history, iterations=iterations, time_s=time.perf_counter() - t0,
                     solver=solver, info=info,
                     raw={k: v.reshape(H, W, -1) for k, v in params.items()})


# -- fast path ------------------------------------------------------------------------------------
def _grid_values(spec: ParamSpec, G: int, dtype, device) -> Tensor:
    """Grid of the main nonlinear parameter: geometric in [0.02, 1]·range for a bounded one (a
    highlight's peak scales like 1/α² = 1/r⁴, so relative spacing is what matters), log-spaced
    in [0.01, 10] for [lo, ∞)."""
    if _bounded(spec):
        u = torch.logspace(math.log10(0.02), 0.0, G, dtype=dtype, device=device) * 0.98
        return spec.low + (spec.high - spec.low) * u
    return torch.logspace(-2, 1, G, dtype=dtype, device=device) + spec.low


def _linear_solve(model: Model, layout: Layout, obs: Observations, theta: Tensor, lin: list[ParamSpec],
                  sep: dict[str, bool], loss: str, delta: float) -> tuple[Tensor, Tensor]:
    """Closed-form weighted least squares for the linear parameters per texel, others held at θ.

    With the nonlinear parameters fixed the prediction is ``b + A x`` (x: the linear parameters'
    channels), so per texel ``x = (AᵀWA + λI)⁻¹ (AᵀW(y − b) + λ x_default)`` with a tiny ridge λ
    toward the defaults (keeps unobserved combinations sensible). ``A`` is found by evaluating the
    model at x = 0 and at each unit x (one evaluation per parameter for separable RGB ones). The
    solution is clipped 1 % inside the range (see below) and returned as θ with its per-texel cost.
    """
    T, dt, dev = obs.n_texels, ACC, obs.device
    L = sum(s.channels for s in lin)
    y, w = obs.radiance.to(ACC), obs.weight.to(ACC)
    p = {k: x[obs.texel] for k, x in layout.unpack(theta.to(obs.dtype)).items()}
    for s in lin:
        p[s.name] = torch.zeros_like(p[s.name])
    b = obs.predict(model, p).to(ACC)
    A = torch.zeros(obs.n_samples, 3, L, dtype=dt, device=dev)
    col = 0
    for s in lin:
        if sep[s.name] or s.channels == 1:
            q = dict(p)
            q[s.name] = torch.ones_like(p[s.name])
            a = obs.predict(model, q).to(ACC) - b
            if s.channels == 1:
                A[:, :, col] = a
            else:
                for c in range(3):
                    A[:, c, col + c] = a[:, c]
        else:
            for c in range(s.channels):
                q = dict(p)
                e = torch.zeros_like(p[s.name])
                e[:, c] = 1.0
                q[s.name] = e
                A[:, :, col + c] = obs.predict(model, q).to(ACC) - b
        col += s.channels
    M = torch.zeros(T, L, L, dtype=dt, device=dev).index_add(0, obs.texel, torch.einsum("scp,s,scq->spq", A, w, A))
    rhs = torch.zeros(T, L, dtype=dt, device=dev).index_add(0, obs.texel, torch.einsum("scp,s,sc->sp", A, w, y - b))
    dflt = torch.cat([s.full((), dtype=dt, device=dev).expand(s.channels) for s in lin])
    lam = 1e-9 * (torch.diagonal(M, dim1=-2, dim2=-1).mean(-1) + 1e-20)
    M = M + lam[:, None, None] * torch.eye(L, dtype=dt, device=dev)
    x = torch.linalg.solve(M, rhs + lam[:, None] * dflt)
    xs, col = [], 0
    for s in lin:
        # clipped a little inside the range: a value on the bound would saturate the
        # sigmoid/softplus (dp/dθ ≈ 0) and LM could never move it back
        m = 0.01 * (s.high - s.low) if _bounded(s) else 1e-3
        hi = s.high - m if _bounded(s) else math.inf
        xs.append(x[:, col:col + s.channels].clamp(s.low + m, hi))
        col += s.channels
    x = torch.cat(xs, -1)
    pred = b + torch.einsum("scp,sp->sc", A, x[obs.texel])
    cost = _texel_cost(obs, pred, loss, delta)
    cand = theta.clone()
    off = 0
    for s in lin:
        cand[:, layout.cols(s.name)] = from_canonical(s, x[:, off:off + s.channels])
        off += s.channels
    return cand, cost


def _closed_form_init(model: Model, layout: Layout, obs: Observations, theta: Tensor, grid: int,
                      loss: str, delta: float, sep: dict[str, bool]) -> tuple[Tensor, dict]:
    """Closed-form linear parameters per texel for each grid value of the main nonlinear one; keep
    the best per texel, then refine the grid value by a parabola through the best and its two
    neighbours (one more closed-form solve)."""
    lin = [s for s in layout.specs if s.linear]
    nonlin = [s for s in layout.specs if not s.linear]
    info = {"linear": [s.name for s in lin], "grid_param": None, "grid": 0}
    if not lin:
        return theta, info
    T, dt, dev = obs.n_texels, ACC, obs.device
    primary = next((s for s in nonlin if s.channels == 1), None)
    with torch.no_grad():
        if primary is None or grid <= 1:
            cand, _ = _linear_solve(model, layout, obs, theta, lin, sep, loss, delta)
            return cand, info
        values = _grid_values(primary, grid, dt, dev)
        info.update(grid_param=primary.name, grid=len(values))
        pc = layout.cols(primary.name)
        costs, cands = [], []
        for val in values:
            th = theta.clone()
            th[:, pc] = from_canonical(primary, val.expand(T, 1))
            cand, cost = _linear_solve(model, layout, obs, th, lin, sep, loss, delta)
            costs.append(cost)
            cands.append(cand)
        costs_t = torch.stack(costs)                                       # [G, T]
        k = costs_t.argmin(0)
        best = torch.stack(cands)[k, torch.arange(T, device=dev)]
        best_cost = costs_t[k, torch.arange(T, device=dev)]
        # parabolic refinement in log(value) through (k-1, k, k+1)
        G = len(values)
        km, kp = (k - 1).clamp(0, G - 1), (k + 1).clamp(0, G - 1)
        ar = torch.arange(T, device=dev)
        x = torch.log(values.clamp_min(1e-12))
        x0, x1, x2 = x[km], x[k], x[kp]
        c0, c1, c2 = costs_t[km, ar], costs_t[k, ar], costs_t[kp, ar]
        den = (x0 - x1) * (x0 - x2) * (x1 - x2)
        aa = (x2 * (c1 - c0) + x1 * (c0 - c2) + x0 * (c2 - c1))
        bb = (x2 * x2 * (c0 - c1) + x1 * x1 * (c2 - c0) + x0 * x0 * (c1 - c2))
        ok = (k > 0) & (k < G - 1) & (aa / den.where(den != 0, torch.ones_like(den)) > 0) & (den != 0)
        xv = torch.where(ok, -bb / (2 * aa.where(aa != 0, torch.ones_like(aa))), x1).clamp(torch.minimum(x0, x2),
                                                                                            torch.maximum(x0, x2))
        th = best.clone()
        th[:, pc] = from_canonical(primary, torch.exp(xv)[:, None].clamp(primary.low, primary.high))
        cand, cost = _linear_solve(model, layout, obs, th, lin, sep, loss, delta)
        better = cost < best_cost
        best = torch.where(better[:, None], cand, best)
        info["grid_refined"] = float(better.float().mean())
    return best, info


def solve_fast(model: Model, obs: Observations, *, loss: str = "l2", delta: float | None = None,
               iterations: int = 60, grid: int = 32, schedule: str = "joint", smoothness: float = 0.0,
               init: Mapping[str, Tensor] | None = None, tol: float = 1e-10, observable_threshold: float = 0.01,
               reproject: int = 0, progress: Callable[[str, int, float], None] | None = None) -> FitResult:
    """Per-texel Levenberg-Marquardt with closed-form initialisation of the linear parameters.

    Objective: ``Σ_s weight_s Σ_c ρ(y_sc − L_sc)`` with nearest-texel sampling (each sample reads
    the texel containing its UV), so texels are independent and every texel has its own damping
    λ_t and step acceptance. One iteration costs one forward-mode pass per parameter (separable RGB
    parameters: one pass for all three channels) plus one trial evaluation.

    Args:
        model: the material model; obs: the observations.
        loss: "l2", "huber" or "l1" (robust ones by IRLS reweighting each iteration).
        delta: Huber/L1 scale in radiance units (default 5 % of the median measured radiance).
        iterations: maximum LM iterations (all stages together).
        grid: number of values of the main nonlinear parameter (first scalar non-linear parameter,
            e.g. roughness) tried by the closed-form initialisation; 0/1 = none.
        schedule: "joint" (all parameters every iteration) or "staged" (Nielsen et al.: scale
            terms — linear parameters — first, then lobe shape — nonlinear ones — then all, each a
            third of the iterations).
        smoothness: weight μ of a prior ``μ·s̄·Σ_neighbours ||θ_t − θ_n||²`` (s̄ the mean diagonal of
            JᵀWJ, so μ is dimensionless); 0 = off. It matters where data are weak.
        init: optional starting maps ``name → [H, W, C]`` (skips the grid for the nonlinear ones
            only if grid ≤ 1).
        tol: stop when the relative decrease of the total cost over an iteration is below this.
        observable_threshold: a parameter is unobservable in a texel where changing it by 0.1
            changes the RMS residual by less than this fraction of the texel's RMS radiance.
        reproject: every this many iterations re-solve the linear parameters in closed form at the
            current nonlinear ones (a variable-projection step, 1 + #linear evaluations); 0 = never.
        progress: callback ``(stage, iteration, cost)``.

    Returns:
        :class:`FitResult` (``info`` holds grid/LM times and the accepted-step fractions).
    """
    t0 = time.perf_counter()
    _check_inputs(model, obs, loss)
    if schedule not in ("joint", "staged"):
        raise SolverError(f"schedule must be 'joint' or 'staged', got {schedule!r}")
    if not (smoothness >= 0 and math.isfinite(smoothness)):
        raise SolverError(f"smoothness must be ≥ 0, got {smoothness!r}")
    if iterations < 0 or grid < 0:
        raise SolverError(f"iterations and grid must be ≥ 0, got {iterations}, {grid}")
    delta = _default_delta(obs, loss, delta)
    layout = Layout.of(model)
    T, P, H, W = obs.n_texels, layout.P, *obs.map_size
    dt, dev = ACC, obs.device
    theta = _init_theta(model, layout, obs, init).to(ACC)
    groups = _groups(model, layout, obs.dtype)
    t_grid = time.perf_counter()
    lin_specs = [s for s in layout.specs if s.linear]
    sep = {s.name: (s.channels == 3 and _separable(model, s, obs.dtype)) for s in lin_specs}
    theta, info = _closed_form_init(model, layout, obs, theta, grid, loss, delta, sep)
    info["grid_s"] = time.perf_counter() - t_grid
    info["jacobian_passes"] = len(groups)
    observed = torch.zeros(T, dtype=torch.bool, device=dev)
    observed[obs.texel] = True
    lin_cols = [c for s in layout.specs if s.linear for c in layout.cols(s.name)]
    non_cols = [c for s in layout.specs if not s.linear for c in layout.cols(s.name)]
    if schedule == "staged" and lin_cols and non_cols:
        k = max(iterations // 3, 1)
        stages = [("scale", lin_cols, k), ("shape", non_cols, k), ("all", list(range(P)), max(iterations - 2 * k, 1))]
    else:
        stages = [("all", list(range(P)), iterations)]
    lam = torch.full((T,), 1e-3, dtype=dt, device=dev)
    history: list[float] = []
    n_res_total = float(3 * obs.weight.to(ACC).sum())
    accepted = []
    it = 0
    t_lm = time.perf_counter()
    with torch.no_grad():
        pred = obs.predict(model, layout.unpack(theta[obs.texel].to(obs.dtype)))
    cost_t = _texel_cost(obs, pred, loss, delta)
    history.append(float(cost_t.sum()) / n_res_total)
    eye = torch.eye(P, dtype=dt, device=dev)
    for stage, cols, n_it in stages:
        free = torch.zeros(P, dtype=torch.bool, device=dev)
        free[cols] = True
        sgroups = [(c, d) for c, d in groups if all(free[x] for x in c)]
        stall = 0
        active = observed.clone()
        for _ in range(n_it):
            it += 1
            sub = obs if bool(active.all()) or float(active.float().mean()) > 0.8 else obs.select(active[obs.texel])
            with torch.no_grad():
                pred_s, J = _jacobian(model, layout, sub, theta[sub.texel], sgroups)
                r = sub.radiance.to(ACC) - pred_s
                wgt = sub.weight.to(ACC)[:, None] * _irls(r, loss, delta)
                Jw = J * wgt[..., None]
                JtJ = torch.zeros(T, P, P, dtype=dt, device=dev).index_add(
                    0, sub.texel, torch.einsum("scp,scq->spq", Jw, J))
                Jtr = torch.zeros(T, P, dtype=dt, device=dev).index_add(0, sub.texel, torch.einsum("scp,sc->sp", Jw, r))
                d = torch.diagonal(JtJ, dim1=-2, dim2=-1)
                scale = d.mean(-1, keepdim=True).clamp_min(1e-30)
                if smoothness > 0:
                    mu = smoothness * float(d[observed].mean()) if bool(observed.any()) else 0.0
                    nsum, cnt = _neighbour_sum(theta, H, W, observed)
                    JtJ = JtJ + mu * cnt[:, :, None] * eye
                    Jtr = Jtr + mu * (nsum - cnt * theta)
                    d = torch.diagonal(JtJ, dim1=-2, dim2=-1)
                A = JtJ + lam[:, None, None] * torch.diag_embed(d + 1e-9 * scale)
                # frozen columns: identity rows, zero right-hand side → zero step
                fmask = free[None, :].expand(T, P)
                A = torch.where(fmask[:, :, None] & fmask[:, None, :], A, torch.diag_embed((~fmask).to(dt)))
                rhs = torch.where(fmask, Jtr, torch.zeros_like(Jtr))
                live = active & (d.sum(-1) > 0)
                A = torch.where(live[:, None, None], A, eye)
                rhs = torch.where(live[:, None], rhs, torch.zeros_like(rhs))
                step, ok = torch.linalg.solve_ex(A, rhs)
                step = torch.where((ok == 0)[:, None] & torch.isfinite(step), step, torch.zeros_like(step))
                # trust region in θ: a step of more than MAX_STEP (in logit/softplus units) is scaled
                # down, so that a poor linearisation cannot throw a parameter into the flat tail of
                # its sigmoid (dp/dθ ≈ 0) from where it would never return
                big = step.abs().amax(-1, keepdim=True)
                step = step * (MAX_STEP / big.clamp_min(MAX_STEP))
                trial = theta + step
                pred_t = obs.predict(model, layout.unpack(trial[obs.texel].to(obs.dtype))) if sub is obs else None
                if pred_t is None:
                    pred_t_sub = sub.predict(model, layout.unpack(trial[sub.texel].to(obs.dtype)))
                    new_cost = cost_t.clone()
                    new_cost[active] = 0
                    new_cost = new_cost + _texel_cost(sub, pred_t_sub, loss, delta)
                else:
                    new_cost = _texel_cost(obs, pred_t, loss, delta)
                old_cost = cost_t
                if smoothness > 0:
                    nsum, cnt = _neighbour_sum(theta, H, W, observed)
                    def prior(th, mu=mu, cnt=cnt, nsum=nsum):
                        return mu * ((cnt * th.square() - 2 * th * nsum).sum(-1))

                    new_cost_c, old_cost_c = new_cost + prior(trial), cost_t + prior(theta)
                else:
                    new_cost_c, old_cost_c = new_cost, old_cost
                acc = live & (new_cost_c < old_cost_c)
                theta = torch.where(acc[:, None], trial, theta)
                cost_t = torch.where(acc, new_cost, cost_t)
                lam = torch.where(acc, (lam / 3).clamp_min(1e-12), (lam * 4).clamp_max(1e12))
                # texels converged: tiny relative improvement or step
                rel = (old_cost_c - torch.where(acc, new_cost_c, old_cost_c)) / old_cost_c.clamp_min(1e-300)
                small = (step.abs().amax(-1) < 1e-9) | (acc & (rel < 1e-12)) | (lam >= 1e12) | (cost_t <= 1e-30)
                active = active & ~small
                if reproject and lin_specs and stage == "all" and it % reproject == 0 and sub is obs:
                    # variable-projection step: re-solve the linear parameters in closed form at the
                    # current nonlinear ones; keep it per texel where it lowers the cost
                    cand, ccost = _linear_solve(model, layout, obs, theta, lin_specs, sep, loss, delta)
                    better = observed & (ccost < cost_t)
                    theta = torch.where(better[:, None], cand, theta)
                    cost_t = torch.where(better, ccost, cost_t)
            accepted.append(float(acc.sum()) / max(int(live.sum()), 1))
            tot = float(cost_t.sum()) / n_res_total
            if progress is not None:
                progress(stage, it, tot)
            prev = history[-1]
            history.append(tot)
            if prev - tot <= tol * max(prev, 1e-300):
                stall += 1
                if stall >= 2:
                    break
            else:
                stall = 0
            if not bool(active.any()):
                break
    info["lm_s"] = time.perf_counter() - t_lm
    info["accepted"] = accepted
    info["stages"] = [s[0] for s in stages]
    return _finalize(model, layout, obs, theta, groups, loss=loss, delta=delta,
                     observable_threshold=observable_threshold, history=history, iterations=it, t0=t0,
                     solver="fast", info=info)


# -- generic path ---------------------------------------------------------------------------------
def solve_adam(model: Model, obs: Observations, *, loss: str = "l2", delta: float | None = None,
               iterations: int = 500, lr: float = 0.05, sampling: str = "nearest",
               init: Mapping[str, Tensor] | None = None, observable_threshold: float = 0.01,
               progress: Callable[[str, int, float], None] | None = None, time_budget_s: float | None = None
               ) -> FitResult:
    """Adam on all maps at once (any model, nearest or bilinear sampling).

    Minimises the mean over samples and channels of ``weight·ρ(y − L)`` with respect to θ (the
    unconstrained parameterisation of every map; see module docstring), full batch, from the
    model's defaults (or ``init``). ``time_budget_s`` stops early once exceeded (for benchmarks).
    """
    t0 = time.perf_counter()
    _check_inputs(model, obs, loss)
    if sampling not in ("nearest", "bilinear"):
        raise SolverError(f"sampling must be 'nearest' or 'bilinear', got {sampling!r}")
    if not (lr > 0) or iterations < 0:
        raise SolverError(f"lr must be > 0 and iterations ≥ 0, got {lr}, {iterations}")
    delta = _default_delta(obs, loss, delta)
    layout = Layout.of(model)
    H, W = obs.map_size
    theta = _init_theta(model, layout, obs, init).clone().requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=lr)
    n_res = float(3 * obs.weight.sum())
    history = []
    it = 0
    for it in range(1, iterations + 1):
        opt.zero_grad(set_to_none=True)
        maps = {k: v.reshape(H, W, -1) for k, v in layout.unpack(theta).items()}
        pred = obs.predict(model, obs.per_sample(maps, sampling))
        lossv = (robust_rho(obs.radiance - pred, loss, delta).sum(-1) * obs.weight).sum() / n_res
        lossv.backward()
        opt.step()
        history.append(float(lossv.detach()))
        if progress is not None:
            progress("adam", it, history[-1])
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
    theta = theta.detach()
    groups = _groups(model, layout, obs.dtype)
    return _finalize(model, layout, obs, theta, groups, loss=loss, delta=delta,
                     observable_threshold=observable_threshold, history=history, iterations=it, t0=t0,
                     solver="adam", info={"lr": lr, "sampling": sampling})
