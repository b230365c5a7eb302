"""Fitting a material model's scalar parameters to a measured BRDF (Nielsen et al.'s staged L1 procedure).

What is fitted
--------------
One value per parameter of ``model.params`` (RGB where the parameter has 3 channels), to a *target* BRDF — a
:class:`materials.Model` such as ``materials.get("measured", material="nickel")`` (the NBRDF fits of MERL) or any
callable ``Angles -> [..., 3]`` — over a fixed set of (l, v) pairs (:func:`make_samples`).

Error (Nielsen et al. 2015, "Fitting Results and Observations": L1, cosine-weighted)
-------------------------------------------------------------------------------------
With samples k, channels c and w_k = cos θ_i (n·l)::

    mae     = mean_{k,c} w_k |f_fit − f_meas|                      (1/sr)
    rel_l1  = Σ_{k,c} w_k |f_fit − f_meas| / Σ_{k,c} w_k |f_meas|  (dimensionless; the fitted objective)

Both are reported over all samples and without grazing samples (θ_i or θ_o > 80°, the angles Ngan et al. 2005
dropped). The objective is rel_l1 (scale-free, so the same step sizes work for nickel, whose peak is ~20/sr, and
red-fabric2, ~0.05/sr); it is |·| during the Adam phase and the Charbonnier form sqrt(r² + δ²) − δ with a tiny δ
during the L-BFGS phase (L-BFGS needs a smooth objective).

Parameterisation (no clamping after the fact)
---------------------------------------------
Each parameter is ``x = lo + (hi − lo)·sigmoid(u)`` on a finite range and ``x = lo + exp(u)`` on [lo, ∞);
the optimiser works on u. Ranges are the ParamSpec's, except roughness-like parameters whose lower end is raised
to ``roughness.R_MIN`` (below it every conversion clamps, so the loss would be flat there).

Procedure
---------
``procedure="nielsen"``: consecutive stages (i) ρ_d and k_s — our ``albedo`` and the specular scales
``specular`` / ``f0``; (ii) the shape parameters — ``roughness`` (Nielsen's s), ``mix`` (α), ``ior`` (η) and any
other parameter; (iii) shape + specular scales. Stages with no parameter of the model are skipped (Lambert is fitted
by stage (i) alone). ``procedure="joint"`` (default): all parameters at once.
Measured (resolution 16 = 1 534 Rusinkiewicz samples, 3 restarts, NBRDF fits of nickel, two-layer-silver,
violet-rubber and red-fabric2 with nielsen-phong,
nielsen-blinn-phong and nielsen-mixture, 12 fits): joint reached an objective lower than or equal to the staged one
in 12 of 12 (red-fabric2: 0.11-0.13 vs 0.19), in about half the time. From one bad start (roughness 0.95,
k_s 500, ρ_d 0.95, η 2.9, α 0.05) the staged procedure was better in 3 of 12 — nielsen-phong on nickel (0.392 vs
0.657) and on two-layer-silver (0.457 vs 0.459), nielsen-blinn-phong on two-layer-silver (0.369 vs 0.410) — and
worse in 8, badly for nielsen-mixture (0.71 vs 0.30 on nickel): stage (i) fits k_s to the wrong lobe shape and
stages (ii)-(iii) do not recover. Restarts, not staging, are what make the fit robust here. Each stage runs
Adam then L-BFGS. Robustness to the initial guess: ``restarts`` runs from spread initial shape parameters (the k-th
of K puts each finite-range shape parameter at fraction (k + 1)/(K + 1) of its range); the lowest objective wins.

Microfacet models that score near Lambert on metals (checked, not a fitter defect)
----------------------------------------------------------------------------------
Cook-Torrance and Schüler fitted to the NBRDF fit of MERL nickel reach an all-angle L1 of 0.97-0.99 (Lambert:
1.00). Longer runs (600 Adam + 200 L-BFGS steps, 5 restarts) and good starts (roughness 0.15, f0 0.9) end at
the same optimum (0.9662 for Cook-Torrance from every start that does not collapse to f0 → 0), so it is not a
local minimum. Fitted without the grazing samples (``exclude_grazing=True``) the same models reach L1 0.35
(Cook-Torrance) and 0.37 (Schüler) away from grazing with a narrow lobe (roughness 0.22 / 0.17), but that lobe
over-predicts the grazing samples by 20-70× (grazing-only L1 21 and 69: at θ_h ≈ 0 and θ_d → 90° the Fresnel
term → 1 and 1/(4 n·l n·v) grows while the network stays bounded), so on the all-angle objective the broad,
nearly-off lobe wins. GGX-Lambert shows the same (0.29 without grazing vs 0.79 all angles).
``tests/capture/test_brdf_fit.py`` keeps this as a test.

Sampling (:func:`make_samples`)
-------------------------------
``"rusinkiewicz"`` (default): jittered stratified samples of (θ_h, θ_d, φ_d) on MERL's own grid spacing — θ_h =
(π/2)·u² (dense near the specular peak, like MERL's sqrt binning), θ_d uniform in [0, π/2], φ_d uniform in [0, π]
(MERL's half-range; the other half follows by reciprocity) — keeping the front-facing pairs. Equal weight per
sample, as when fitting to MERL's bins (Ngan et al. 2005; Nielsen et al.). ``"hemispheres"``: l and v each uniform
in solid angle on the upper hemisphere (stratified), so the mean is the integral over both hemispheres.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

import materials
from materials import Angles, Model, ParamSpec
from materials.roughness import R_MIN

#: Angle (degrees) beyond which a sample counts as grazing.
GRAZING_DEG = 80.0


# -- samples ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class SampleSet:
    """A fixed set of (l, v) configurations to fit over.

    Attributes:
        g: the configurations' cosines, each ``[N, 1]`` (all front-facing).
        weight: ``[N, 1]`` cos θ_i (Nielsen's cosine weighting).
        grazing: bool ``[N, 1]``: θ_i or θ_o > 80°.
        scheme: how they were drawn.
    """

    g: Angles
    weight: Tensor
    grazing: Tensor
    scheme: str

    def __len__(self) -> int:
        return self.weight.shape[0]


def _strata(counts: Sequence[int], gen: torch.Generator, dtype) -> Tensor:
    """Jittered stratified points in [0, 1)^d, one per cell of a ``counts`` grid: ``[Π counts, d]``."""
    axes = [torch.arange(c, dtype=dtype) for c in counts]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, len(counts))
    jitter = torch.rand(grid.shape, generator=gen, dtype=dtype)
    return (grid + jitter) / torch.tensor(counts, dtype=dtype)


def make_samples(scheme: str = "rusinkiewicz", resolution: int = 24, seed: int = 0,
                 dtype=torch.float32, device=None) -> SampleSet:
    """Draw the fitting configurations (module docstring, "Sampling").

    Args:
        scheme: ``"rusinkiewicz"`` (θ_h, θ_d, φ_d on a ``resolution × resolution × resolution/2`` jittered grid,
            θ_h sqrt-spaced) or ``"hemispheres"`` (l and v stratified uniform in solid angle, ``(2·resolution)²``
            directions each side, paired at random).
        resolution: strata per axis, ≥ 4. The default 24 keeps ≈ 4 300 front-facing Rusinkiewicz samples.
        seed: jitter seed (the set is deterministic for a seed).
    Returns:
        A :class:`SampleSet` of front-facing configurations.
    """
    if scheme not in ("rusinkiewicz", "hemispheres"):
        raise ValueError(f"make_samples: unknown scheme '{scheme}'; use 'rusinkiewicz' or 'hemispheres'")
    if int(resolution) < 4:
        raise ValueError(f"make_samples: resolution must be ≥ 4, got {resolution}")
    res = int(resolution)
    gen = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64
    if scheme == "rusinkiewicz":
        u = _strata((res, res, max(res // 2, 2)), gen, f64)
        th = 0.5 * math.pi * u[:, 0].square()
        td = 0.5 * math.pi * u[:, 1]
        pd = math.pi * u[:, 2]
        a = torch.cos(th) * torch.cos(td)
        b = torch.sin(th) * torch.sin(td) * torch.cos(pd)
        nl, nv, lv = a - b, a + b, torch.cos(2.0 * td)
    else:
        def hemi(k):
            s = _strata((2 * res, 2 * res), gen, f64)
            s = s[torch.randperm(s.shape[0], generator=gen)]
            ct, ph = s[:, 0], 2.0 * math.pi * s[:, 1]
            st = torch.sqrt((1.0 - ct * ct).clamp_min(0.0))
            return torch.stack([st * torch.cos(ph), st * torch.sin(ph), ct], dim=-1)

        l, v = hemi(0), hemi(1)
        nl, nv, lv = l[:, 2], v[:, 2], (l * v).sum(-1)
    keep = (nl > 1e-4) & (nv > 1e-4)
    g = Angles.from_cosines(nl[keep], nv[keep], lv[keep]).to(device=device, dtype=dtype)
    c = math.cos(math.radians(GRAZING_DEG))
    grazing = (g.nl < c) | (g.nv < c)
    return SampleSet(g=g, weight=g.nl.clamp_min(0.0), grazing=grazing, scheme=scheme)


# -- parameterisation -------------------------------------------------------------------------
@dataclass(frozen=True)
class _Param:
    spec: ParamSpec
    lo: float
    hi: float

    def value(self, u: Tensor) -> Tensor:
        if math.isinf(self.hi):
            return self.lo + torch.exp(u)
        return self.lo + (self.hi - self.lo) * torch.sigmoid(u)

    def unconstrained(self, x: Tensor) -> Tensor:
        if math.isinf(self.hi):
            return torch.log((x - self.lo).clamp_min(1e-6))
        t = ((x - self.lo) / (self.hi - self.lo)).clamp(1e-4, 1.0 - 1e-4)
        return torch.log(t) - torch.log1p(-t)


def _bounds(spec: ParamSpec, overrides: Mapping[str, tuple[float, float]]) -> _Param:
    lo, hi = spec.low, spec.high
    if spec.name in overrides:
        lo, hi = overrides[spec.name]
    elif spec.role == "roughness":  # the conversions clamp r to [R_MIN, 1]: below it the loss is flat
        lo = max(lo, R_MIN)
    if not (math.isfinite(lo) and hi > lo):
        raise ValueError(f"fit: parameter '{spec.name}' needs a finite lower bound below its upper bound, "
                         f"got [{lo}, {hi}]; pass bounds={{'{spec.name}': (lo, hi)}}")
    return _Param(spec, float(lo), float(hi))


def _group(spec: ParamSpec) -> str:
    """Nielsen's stage group of a parameter (its spec's role): the diffuse scale, a specular scale, or shape."""
    return spec.role if spec.role in ("diffuse", "specular") else "shape"


# -- results ----------------------------------------------------------------------------------
@dataclass
class FitErrors:
    """Cosine-weighted L1 errors of a fit (module docstring, "Error")."""

    mae: float
    rel_l1: float
    mae_no_grazing: float
    rel_l1_no_grazing: float
    rel_l1_grazing: float = math.nan  #: over the grazing samples only (θ_i or θ_o > 80°)


@dataclass
class FitResult:
    """The outcome of :func:`fit_brdf`.

    Attributes:
        params: fitted canonical parameters, each a float64 CPU tensor ``[channels]``.
        errors: :class:`FitErrors` on the fitting samples.
        objective: the minimised objective (rel_l1, over all samples unless ``exclude_grazing``).
        restarts: objective reached from each start.
        seconds: wall time of the whole fit.
        procedure: ``"nielsen"`` or ``"joint"``.
        stages: the parameter names optimised in each stage.
    """

    params: dict[str, Tensor]
    errors: FitErrors
    objective: float
    restarts: list[float] = field(default_factory=list)
    seconds: float = 0.0
    procedure: str = "nielsen"
    stages: list[tuple[str, ...]] = field(default_factory=list)


def errors(pred: Tensor, meas: Tensor, samples: SampleSet) -> FitErrors:
    """:class:`FitErrors` of predicted vs measured BRDF values (both ``[N, 3]``, 1/sr) on ``samples``."""
    if pred.shape != meas.shape or pred.shape[0] != len(samples):
        raise ValueError(f"errors: pred {tuple(pred.shape)} and meas {tuple(meas.shape)} "
                         f"must both be [{len(samples)}, 3]")
    w = samples.weight.to(pred)
    d = (w * (pred - meas).abs()).double()
    m = (w * meas.abs()).double()
    keep = (~samples.grazing).expand_as(d)
    tiny = 1e-30
    return FitErrors(
        mae=d.mean().item(),
        rel_l1=(d.sum() / m.sum().clamp_min(tiny)).item(),
        mae_no_grazing=d[keep].mean().item(),
        rel_l1_no_grazing=(d[keep].sum() / m[keep].sum().clamp_min(tiny)).item(),
        rel_l1_grazing=(d[~keep].sum() / m[~keep].sum().clamp_min(tiny)).item() if (~keep).any() else math.nan,
    )


def evaluate_target(target: Model | Callable[[Angles], Tensor], samples: SampleSet,
                    target_params: Mapping[str, Tensor] | None = None) -> Tensor:
    """The target BRDF on the samples, ``[N, 3]`` (1/sr), without gradient."""
    with torch.no_grad():
        if isinstance(target, Model):
            p = target.defaults(device=samples.weight.device, dtype=samples.weight.dtype)
            p.update({k: torch.as_tensor(v, device=samples.weight.device, dtype=samples.weight.dtype)
                      for k, v in (target_params or {}).items()})
            out = target.brdf(samples.g, p)
        elif callable(target):
            out = target(samples.g)
        else:
            raise TypeError("fit: target must be a materials.Model or a callable Angles -> [..., 3], "
                            f"got {type(target).__name__}")
    out = torch.as_tensor(out).expand(len(samples), 3) if out.shape[-1] in (1, 3) else out
    if out.shape != (len(samples), 3):
        raise ValueError(f"fit: target returned shape {tuple(out.shape)}, expected [{len(samples)}, 3]")
    if not torch.isfinite(out).all():
        raise ValueError("fit: the target BRDF has NaN/inf values on the samples")
    return out


# -- the fit ----------------------------------------------------------------------------------
def _initial(model: Model, params: list[_Param], init: Mapping[str, Tensor] | None, k: int, restarts: int,
             dtype) -> dict[str, Tensor]:
    x = {}
    for p in params:
        s = p.spec
        if init is not None and s.name in init:
            val = torch.as_tensor(init[s.name], dtype=dtype).reshape(-1).expand(s.channels).clone()
        elif _group(s) == "shape" and math.isfinite(p.hi) and restarts > 1:
            val = torch.full((s.channels,), p.lo + (p.hi - p.lo) * (k + 1) / (restarts + 1), dtype=dtype)
        else:
            val = torch.full((s.channels,), float(s.default), dtype=dtype)
        x[s.name] = p.unconstrained(val)
    return x


def _check_fit_args(model: Model | str, procedure: str, restarts: int) -> Model:
    """The model (looked up when given by name), after checking it, the procedure and the restarts."""
    if isinstance(model, str):
        model = materials.get(model)
    if not isinstance(model, Model):
        raise TypeError(f"fit_brdf: model must be a materials.Model or a registry name, got {type(model).__name__}")
    if procedure not in ("nielsen", "joint"):
        raise ValueError(f"fit_brdf: unknown procedure '{procedure}'; use 'nielsen' or 'joint'")
    if int(restarts) < 1:
        raise ValueError(f"fit_brdf: restarts must be ≥ 1, got {restarts}")
    return model


def _stages(params: Sequence[_Param], procedure: str) -> list[tuple[str, ...]]:
    """The parameter names optimised in each stage: all at once ("joint"), or Nielsen's three stages."""
    names = [p.spec.name for p in params]
    if procedure == "joint":
        stages = [tuple(names)]
    else:
        groups = {g: tuple(p.spec.name for p in params if _group(p.spec) == g)
                  for g in ("diffuse", "specular", "shape")}
        stages = [groups["diffuse"] + groups["specular"], groups["shape"], groups["shape"] + groups["specular"]]
    return [s for s in stages if s]


@dataclass(frozen=True)
class _Objective:
    """The cosine-weighted relative L1 of ``model`` against ``meas`` as a function of the unconstrained
    parameters; ``smooth`` gives its pseudo-Huber form (for L-BFGS)."""

    model: Model
    params: Sequence[_Param]
    samples: SampleSet
    meas: Tensor
    w: Tensor
    norm: Tensor
    delta: Tensor

    @classmethod
    def build(cls, model: Model, params: Sequence[_Param], samples: SampleSet, meas: Tensor,
              exclude_grazing: bool) -> _Objective:
        w = samples.weight.expand_as(meas)
        if exclude_grazing:
            w = torch.where(samples.grazing.expand_as(meas), torch.zeros_like(w), w)
        norm = (w * meas.abs()).sum().clamp_min(1e-30)
        delta = 1e-4 * norm / w.numel()
        return cls(model, params, samples, meas, w, norm, delta)

    def values(self, u: Mapping[str, Tensor]) -> dict[str, Tensor]:
        return {p.spec.name: p.value(u[p.spec.name]) for p in self.params}

    def __call__(self, u: Mapping[str, Tensor], smooth: bool) -> Tensor:
        r = self.w * (self.model.brdf(self.samples.g, self.values(u)) - self.meas)
        if smooth:
            return (torch.sqrt(r * r + self.delta * self.delta) - self.delta).sum() / self.norm
        return r.abs().sum() / self.norm


class _Budget(NamedTuple):
    """Per-stage optimiser budget."""

    adam_steps: int
    adam_lr: float
    lbfgs_steps: int


def _adam(objective: _Objective, u: dict[str, Tensor], leaves: list[Tensor], steps: int, lr: float) -> None:
    """Adam with a cosine-annealed rate on ``leaves`` (in place); ends at the best iterate seen."""
    opt = torch.optim.Adam(leaves, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps, eta_min=lr * 0.05)
    best, best_u = math.inf, [x.detach().clone() for x in leaves]
    for _ in range(steps):
        opt.zero_grad(set_to_none=True)
        loss = objective(u, smooth=False)
        if loss.item() < best:
            best, best_u = loss.item(), [x.detach().clone() for x in leaves]
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        if objective(u, smooth=False).item() > best:
            for x, b in zip(leaves, best_u, strict=True):
                x.copy_(b)


def _lbfgs(objective: _Objective, u: dict[str, Tensor], leaves: list[Tensor], steps: int) -> None:
    """L-BFGS on the smooth objective (in place); undone when it does not lower the L1 objective."""
    before = [x.detach().clone() for x in leaves]
    with torch.no_grad():
        loss_before = objective(u, smooth=False).item()
    opt = torch.optim.LBFGS(leaves, lr=1.0, max_iter=steps, history_size=20,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-10, tolerance_change=1e-12)

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = objective(u, smooth=True)
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        after = objective(u, smooth=False).item()
        if not math.isfinite(after) or after > loss_before:
            for x, b in zip(leaves, before, strict=True):
                x.copy_(b)


def _run_stage(objective: _Objective, u: dict[str, Tensor], free: tuple[str, ...], budget: _Budget,
               device) -> dict[str, Tensor]:
    """One stage: Adam then L-BFGS on the ``free`` parameters, the others held."""
    u = {k: v.detach().clone().to(device) for k, v in u.items()}
    leaves = [u[n].requires_grad_() for n in free]
    if budget.adam_steps > 0:
        _adam(objective, u, leaves, budget.adam_steps, budget.adam_lr)
    if budget.lbfgs_steps > 0:
        _lbfgs(objective, u, leaves, budget.lbfgs_steps)
    return {k: v.detach() for k, v in u.items()}


def fit_brdf(model: Model | str, target: Model | Callable[[Angles], Tensor], samples: SampleSet | None = None, *,
             procedure: str = "joint", restarts: int = 3, init: Mapping[str, Tensor] | None = None,
             target_params: Mapping[str, Tensor] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
             adam_steps: int = 150, adam_lr: float = 0.08, lbfgs_steps: int = 40, exclude_grazing: bool = False,
             ) -> FitResult:
    """Fit ``model``'s scalar parameters to ``target`` by minimising the cosine-weighted relative L1.

    Args:
        model: a :class:`materials.Model` or a registry name (``materials.get(name)``).
        target: the measured BRDF (a Model, evaluated with ``target_params`` / its defaults, or a callable
            ``Angles -> [N, 3]``).
        samples: configurations (default ``make_samples()``, float64 on CPU).
        procedure: ``"joint"`` (all parameters in one stage, default) or ``"nielsen"`` (staged, module docstring).
        restarts: number of starts (≥ 1); the best objective wins.
        init: initial canonical values by name (override the restart spread and the defaults).
        bounds: per-parameter ``(lo, hi)`` overriding the ParamSpec range during the fit.
        adam_steps, adam_lr, lbfgs_steps: per-stage optimiser budget.
        exclude_grazing: fit without the grazing samples (the errors are still reported both ways).
    Returns:
        :class:`FitResult`.
    """
    t0 = time.perf_counter()
    model = _check_fit_args(model, procedure, restarts)
    if samples is None:
        samples = make_samples(dtype=torch.float64)
    if init is not None:
        unknown = set(init) - set(model.param_names)
        if unknown:
            raise ValueError(f"fit_brdf: init names {sorted(unknown)} are not parameters of '{model.name}' "
                             f"{list(model.param_names)}")
    dtype, device = samples.weight.dtype, samples.weight.device
    meas = evaluate_target(target, samples, target_params)
    params = [_bounds(s, bounds or {}) for s in model.params]
    stages = _stages(params, procedure)
    objective = _Objective.build(model, params, samples, meas, exclude_grazing)
    budget = _Budget(adam_steps, adam_lr, lbfgs_steps)

    spread = any(_group(p.spec) == "shape" and math.isfinite(p.hi) for p in params)
    n_starts = int(restarts) if spread else 1  # identical starts would repeat the same fit
    best_u, best_obj, per_restart = None, math.inf, []
    for k in range(n_starts):
        u = {n: v.to(device) for n, v in _initial(model, params, init, k, n_starts, dtype).items()}
        for free in stages:
            u = _run_stage(objective, u, free, budget, device)
        with torch.no_grad():
            obj = objective(u, smooth=False).item()
        per_restart.append(obj)
        if obj < best_obj:
            best_obj, best_u = obj, u
    with torch.no_grad():
        final = objective.values(best_u)
        errs = errors(model.brdf(samples.g, final), meas, samples)
    return FitResult(
        params={k: v.detach().to("cpu", torch.float64) for k, v in final.items()},
        errors=errs, objective=best_obj, restarts=per_restart, seconds=time.perf_counter() - t0,
        procedure=procedure, stages=stages,
    )
