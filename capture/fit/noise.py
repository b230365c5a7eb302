"""The photo noise model, the robust losses and their IRLS weights.

Every solver minimises a (robust) weighted sum over samples s and channels c of ``ρ(y_sc − L_sc(θ))``
(:func:`robust_rho`); robust losses enter Gauss-Newton as IRLS weights (:func:`irls_weights`). The noise model
(:data:`NOISE`, :func:`noise_sigma`) scales the posterior std and the χ² of the sharing; :func:`photo_noise_ratio`
measures the photos' own noise against it in image space.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..observations import Observations
from .layout import ACC, SolverError

__all__ = ["LOSSES", "NOISE", "NOISE_QUANTILE", "CHI2_1_Q10", "MISFIT_PRIOR_DOF", "check_loss", "robust_rho",
           "irls_weights", "default_delta", "check_noise", "noise_sigma", "photo_noise_ratio", "noise_ratio",
           "moderated_misfit", "scaled_sigma", "photo_sigma", "noise_floor"]


LOSSES = ("l2", "huber", "l1")


# -- losses ---------------------------------------------------------------------------------------
def check_loss(loss: str) -> str:
    """``loss`` if it is one of :data:`LOSSES`, else a :class:`SolverError` naming them."""
    if loss not in LOSSES:
        raise SolverError(f"unknown loss {loss!r}; choose one of {LOSSES}")
    return loss


def robust_rho(r: Tensor, loss: str, delta: float, out: Tensor | None = None) -> Tensor:
    """Per-residual cost: l2 ``r²``; huber ``r²`` for |r| ≤ δ else ``2δ|r| − δ²``; l1 ``2δ|r|``
    (scaled so that the three agree to first order at |r| = δ). ``out``: l2's ``r²`` is written there (it may be
    ``r`` itself); the others make a new array."""
    if loss == "l2":
        return r * r if out is None else torch.mul(r, r, out=out)
    a = r.abs()
    if loss == "huber":
        return torch.where(a <= delta, r * r, 2 * delta * a - delta * delta)
    return 2 * delta * a


def irls_weights(r: Tensor, loss: str, delta: float) -> Tensor:
    """IRLS weight ρ'(r)/(2r) of :func:`robust_rho`."""
    if loss == "l2":
        return torch.ones_like(r)
    a = r.abs()
    if loss == "huber":
        return torch.where(a <= delta, torch.ones_like(r), delta / a.clamp_min(1e-30))
    return delta / a.clamp_min(1e-3 * delta)


def default_delta(obs: Observations, loss: str, delta: float | None) -> float:
    """The Huber/L1 scale: ``delta`` when given (checked), else 5 % of the median measured radiance."""
    if delta is not None:
        if not (delta > 0 and math.isfinite(delta)):
            raise SolverError(f"delta must be a positive finite number (radiance units), got {delta!r}")
        return float(delta)
    # 5 % of the median measured radiance: larger residuals (highlight misfits, outliers) are damped
    med = obs.radiance.abs().mean(-1).median().item()
    return 0.05 * max(med, 1e-6)


#: Default photo noise model of the observability test: (relative std, floor as a fraction of the
#: median sample radiance) — σ_sc = rel · max(|y_sc|, floor · median).
NOISE = (0.01, 0.1)


def check_noise(noise) -> tuple[float, float]:
    """The noise model ``(relative std, floor fraction)`` as two positive finite floats, else a :class:`SolverError`."""
    try:
        rel, floor = (float(x) for x in noise)
    except (TypeError, ValueError):
        raise SolverError(f"noise must be (relative std, floor fraction), e.g. {NOISE}, got {noise!r}") from None
    if not (rel > 0 and floor > 0 and math.isfinite(rel) and math.isfinite(floor)):
        raise SolverError(f"noise must hold two positive finite numbers, got {noise!r}")
    return rel, floor


def noise_sigma(y: Tensor, noise) -> Tensor:
    """Photo noise std ``[S, 3]`` of radiances ``y [S, 3]`` under the noise model ``noise = (rel, floor)``:
    ``σ = rel · max(|y|, floor · median y)`` (1 % of the signal by default, never below 0.1 % of the median)."""
    rel, floor = check_noise(noise)
    med = float(y.abs().mean(-1).median().clamp_min(1e-12))
    return rel * torch.maximum(y.abs(), torch.full_like(y, floor * med))


#: The quantile of the squared noise residuals that :func:`photo_noise_ratio` reads, and that quantile of χ²₁.
NOISE_QUANTILE = 0.1
CHI2_1_Q10 = 0.01579077409343122


def photo_noise_ratio(obs: Observations, noise=NOISE) -> float | None:
    """The photos' noise variance relative to the noise model ``noise`` (:func:`noise_sigma`), measured in image
    space: the :data:`NOISE_QUANTILE` quantile over samples and channels of ``(e / σ)²``, with ``e`` the samples'
    noise residual (:func:`capture.observations.noise_residual`), divided by the same quantile of χ²₁ — about 1
    when the model's σ is the photos' noise. No fit enters it, so neither does a model's misfit. A low quantile, not
    the median, because texture and shading the mask does not annihilate are structure at many pixels of a small or
    foreshortened image, while noise is at all of them: noise-free renderings read 0.0000–0.11 (the median read
    0.27–11.6 on the stress table's grazing planes, 0.77 on a 64-px sphere), shot noise of a 3 000 e⁻ full well
    27.5 (median 29.6), 300 e⁻ 210 (median 234). Channels whose radiance is 0 are left out: a colour channel the
    material absorbs entirely (the layered scene's coat takes G and B of its base) reads 0 in every pixel, noise or
    not, and held the quantile at 0 on a noisy layered scene. None when the observations carry no residuals or fewer
    than 100 sample channels have one."""
    e = obs.noise_residual
    if e is None:
        return None
    return noise_ratio(e, obs.radiance, noise)


def noise_ratio(e: Tensor, y: Tensor, noise=NOISE) -> float | None:
    """:func:`photo_noise_ratio` of noise residuals ``e [N, 3]`` (NaN where not measured) at radiances ``y [N, 3]`` —
    the samples', or one photo's object pixels (:func:`capture.footprint.footprint_counts` measures each view's noise
    with it; the noise model's floor is relative to the median of ``y``)."""
    y = y.to(ACC)
    ok = torch.isfinite(e) & (y > 0)
    if int(ok.sum()) < 100:
        return None
    z2 = (e.to(ACC) / noise_sigma(y, noise))[ok].square()
    return float(z2.kthvalue(max(1, int(NOISE_QUANTILE * z2.numel()))).values) / CHI2_1_Q10


#: Prior weight (degrees of freedom) of the photos' measured noise in a texel's misfit (:func:`moderated_misfit`).
MISFIT_PRIOR_DOF = 6.0


def moderated_misfit(chi2: Tensor, dof: Tensor, pooled: float | None) -> Tensor:
    """A texel's residual variance in units of the noise model, ``(χ² + ν₀ s²) / (dof + ν₀)`` with ``s²`` =
    ``pooled`` (:func:`photo_noise_ratio`, the photos' noise measured in image space) and ν₀ =
    :data:`MISFIT_PRIOR_DOF` — the texel's own estimate χ²/dof shrunk towards the measured noise, as much as its few
    degrees of freedom need (none for a texel whose unknowns fit its samples exactly). Zeros (no floor) when
    ``pooled`` is None or ≤ 1: on noise-free photos the callers keep their own estimate unchanged."""
    if pooled is None or pooled <= 1.0:
        return torch.zeros_like(chi2)
    return (chi2 + MISFIT_PRIOR_DOF * pooled) / (dof.clamp_min(0) + MISFIT_PRIOR_DOF)


def scaled_sigma(y: Tensor, noise, ratio: float | None) -> Tensor:
    """The noise std of values ``y [..., 3]``: σ of the noise model ``noise`` (:func:`noise_sigma`) times
    √max(1, ratio), ``ratio`` the photos' noise measured in image space relative to it (:func:`photo_noise_ratio`;
    None = 1) — the model's σ unless the photos are noisier."""
    return noise_sigma(y, noise) * math.sqrt(max(1.0, ratio or 1.0))


def photo_sigma(obs: Observations, noise, ratio: float | None) -> Tensor:
    """The photos' noise std ``[S, 3]`` (float64) of each sample (:func:`scaled_sigma` of their radiance)."""
    return scaled_sigma(obs.radiance.to(ACC), noise, ratio)


def noise_floor(obs: Observations, noise, ratio: float | None, loss: str, delta: float) -> float:
    """The data cost per residual (as :func:`data_cost` reports it) of residuals as large as the photos' noise: the
    weighted mean of ρ(σ_sc), σ from :func:`photo_sigma`."""
    sigma = photo_sigma(obs, noise, ratio)
    total = float((robust_rho(sigma, loss, delta).sum(-1) * obs.weight.to(ACC)).sum())
    return total / float(3 * obs.weight.to(ACC).sum())
