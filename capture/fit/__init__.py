"""The fit: a material model's maps from :class:`capture.observations.Observations`.

Two paths over the same objective — a (robust) weighted sum over samples s and channels c of
``ρ(y_sc − L_sc(θ_texel(s)))`` with ``L`` the model's predicted radiance:

* :func:`solve_adam` (:mod:`~capture.fit.adam`) — generic first-order path: Adam on every map at once, any model,
  nearest or bilinear sampling. Thousands of cheap iterations.
* :func:`solve_fast` (:mod:`~capture.fit.fast`) — the fast path built for known geometry. With nearest-texel
  sampling each texel is an independent least-squares problem in P ≤ ~10 unknowns, so

  1. parameters a model declares linear (``ParamSpec.linear``: albedo, f0 under Schlick-type
     Fresnel, Nielsen's k_s) are solved in *closed form*, per texel, for a grid of values of the
     main nonlinear parameter (roughness); the best grid point per texel initialises
  2. Levenberg-Marquardt on all parameters, vectorised over all texels: residuals of all samples,
     the per-sample Jacobian in the model's closed form where it has one, else by reverse-mode AD
     (one evaluation, one backward pass per colour channel: a sample's prediction depends only on
     its own parameters), per-texel
     normal equations ``JᵀWJ [T, P, P]`` and ``JᵀWr [T, P]`` accumulated with ``index_add``, a
     batched damped solve, and per-texel step acceptance with per-texel damping λ_t
     (:mod:`~capture.fit.texel`).

  Robust losses (Huber, L1 — Nielsen et al. recommend L1 for highlights) enter as IRLS weights
  (:mod:`~capture.fit.noise`); Nielsen's staged schedule (scale terms, then lobe shape, then all) and a smoothness
  prior across neighbouring texels (added to the normal equations) are options (:class:`FitOptions`). With
  bilinear sampling the reflectance sharing (:mod:`~capture.fit.sharing`) and the joint refinement
  (:mod:`~capture.fit.joint`) follow.

Parameters stay in range through their parameterisation, not by clamping: a parameter with range
[lo, hi] is ``lo + (hi − lo)·sigmoid(θ)``, one with range [lo, ∞) is ``lo + softplus(θ)``
(:class:`Layout`). The closed-form initialisation clips the linear solution into the range once,
before it is mapped to θ.

Both return a :class:`FitResult`: the canonical maps, which texels were observed, and per
parameter the marginal posterior standard deviation (:func:`posterior_std`: Gauss-Newton normal
matrix at the solution, a photo noise model of 1 % of the signal, inflated by the residual
variance where the fit is worse than that) — the confidence maps. A parameter is *unobservable*
in a texel where that std is at or above its threshold (:data:`OBSERVABLE_STD`: 0.01 for albedo
and f0, 0.02 for roughness, in canonical units); this catches trade-offs between parameters
(albedo vs f0, f0·α² of a GGX tail without a highlight) that a one-parameter test misses.
Unobservable values and unobserved texels are filled by pull-push (:func:`pull_push`) and
flagged; ``FitResult.raw`` keeps the fitted values (:mod:`~capture.fit.observability`).

Modules, each importing only those before it: ``layout`` ← ``noise`` ← ``texel`` ← ``operators`` ←
``observability`` ← ``sharing`` ← ``joint`` ← ``options`` ← ``fast``; ``adam`` beside ``fast``.
"""

from .adam import solve_adam
from .fast import pyramid_size, solve_fast, upsample_maps
from .joint import refine_joint
from .layout import FitResult, Layout, SolverError
from .noise import LOSSES, NOISE, noise_sigma, photo_noise_ratio, photo_sigma, robust_rho, scaled_sigma
from .observability import OBSERVABLE_STD, determined, posterior_std, pull_push, std_threshold
from .options import FitOptions
from .sharing import share_materials, unmatched_texels

__all__ = ["FitOptions", "Layout", "FitResult", "SolverError", "LOSSES", "OBSERVABLE_STD", "NOISE", "solve_fast",
           "solve_adam", "refine_joint", "posterior_std", "std_threshold", "determined", "pull_push", "robust_rho",
           "noise_sigma", "photo_noise_ratio", "photo_sigma", "scaled_sigma", "share_materials", "unmatched_texels",
           "pyramid_size", "upsample_maps"]
