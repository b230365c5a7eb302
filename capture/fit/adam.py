"""The generic first-order path (:func:`solve_adam`): Adam on every map at once, any model, nearest or bilinear
sampling. Thousands of cheap iterations."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

import torch
from torch import Tensor

from materials.model import Model

from ..observations import Observations
from .layout import FitResult, Layout, SolverError, param_groups
from .noise import NOISE, check_noise, default_delta, robust_rho
from .observability import finalize
from .texel import check_inputs, init_theta

__all__ = ["solve_adam"]


def solve_adam(model: Model, obs: Observations, *, loss: str = "l2", delta: float | None = None,
               iterations: int = 500, lr: float = 0.05, sampling: str = "nearest",
               init: Mapping[str, Tensor] | None = None, observable_std: float | Mapping[str, float] | None = None,
               noise=NOISE,
               progress: Callable[[str, int, float], None] | None = None, time_budget_s: float | None = None
               ) -> FitResult:
    """Adam on all maps at once (any model, nearest or bilinear sampling).

    Minimises the mean over samples and channels of ``weight·ρ(y − L)`` with respect to θ (the
    unconstrained parameterisation of every map; see module docstring), full batch, from the
    model's defaults (or ``init``). ``time_budget_s`` stops early once exceeded (for benchmarks).
    """
    t0 = time.perf_counter()
    check_inputs(model, obs, loss)
    if sampling not in ("nearest", "bilinear"):
        raise SolverError(f"sampling must be 'nearest' or 'bilinear', got {sampling!r}")
    if not (lr > 0) or iterations < 0:
        raise SolverError(f"lr must be > 0 and iterations ≥ 0, got {lr}, {iterations}")
    delta = default_delta(obs, loss, delta)
    layout = Layout.of(model)
    H, W = obs.map_size
    theta = init_theta(model, layout, obs, init).clone().requires_grad_(True)
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
    groups = param_groups(layout)
    return finalize(model, layout, obs, theta, groups, loss=loss, delta=delta, observable_std=observable_std,
                     noise=check_noise(noise), history=history, iterations=it, t0=t0, solver="adam",
                     info={"lr": lr, "sampling": sampling}, sampling=sampling)
