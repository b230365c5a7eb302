"""Reflectance sharing: a few candidate materials for the specular parameters, per-texel albedo.

Where a texel never shows a highlight its own samples cannot tell f0 from roughness from albedo
(docs/log.md, "Why the per-texel fit cannot reach the all-texel targets"); real objects,
however, are made of a few materials. Following Lensch et al. 2003 (basis materials fitted to
clustered lumitexels) and Nam et al. 2018 (a handful of specular materials with per-point diffuse
albedo, for exactly the flash-light setting), :func:`share_materials`

1. clusters the *anchor* texels — those whose shared parameters the per-texel fit determined
   (posterior std below threshold) — into ``candidates`` materials (k-means++ seeding, kornia's
   k-means; features are the canonical values divided by their observability thresholds);
2. assigns every observed texel to one candidate (:func:`_assign`): for each candidate the
   per-texel albedo is solved in closed form (:func:`capture.fit.texel.linear_solve`) with samples
   weighted by the photo noise model, giving a χ² cost per texel and candidate; a texel takes the
   best candidate at the finest scale where it beats the second best by ``evidence`` (χ² units),
   scales being box sums over 1, 3, 9, … texels of each texel's excess χ² capped at ``cap`` — a
   texel with no evidence of its own borrows its neighbours', counted texel by texel. Each
   material also carries an albedo distribution (:func:`_albedo_prior`), so that a texel whose
   photos cannot tell a metal's lobe from a dielectric's is not given the metal when its albedo is
   blue;
3. drops the candidates the photos do not need (:func:`_supported`: backward elimination while the
   least-needed candidate's evidence — the excess χ² its texels would pay at their next best, capped
   per texel — is below ``min_evidence``) before each assignment: with more candidates than materials
   k-means spends the spare ones on duplicates and border mixtures, and a mixture backed by too few
   anchors has no albedo statistics to reject anything, so weakly observed texels sink into it
   (default rig with 3 materials: 2 175 rough-dielectric texels took a gold–dielectric mixture);
4. refits each candidate's shared parameters on all samples of its texels (Levenberg–Marquardt per
   candidate, albedo held); steps 2–4 run ``rounds`` times.

Anchors keep their own fit. Measured on the default scene (docs/log.md, "Reflectance
sharing" and "speed, 3 joint steps"): RMSE on all observed texels albedo / f0 / roughness 0.0805 / 0.1963 / 0.1892
→ 0.0089 / 0.0159 / 0.0531 after the joint refinement (0.0161 / 0.0159 / 0.0532 without the albedo in its
prior); this stage takes ~5 s of the 20–24 (2 threads).

The result initialises the joint refinement, whose edge-preserving prior
(:func:`capture.fit.joint.refine_joint` ``sharing=``) then lets well-observed texels depart from their
material (smooth gradients) while the others keep it, and gives texels whose albedo the photos barely
determine a neighbour's.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.contrib import KMeans
from torch import Tensor

from materials.model import Model
from renderer.device import block_size

from ..observations import Observations
from .layout import ACC, MAX_STEP, Layout, from_canonical, param_groups
from .noise import moderated_misfit, noise_sigma, photo_noise_ratio
from .observability import block_index, pull_push, std_threshold
from .texel import SYSTEM_BLOCK, grid_values, jacobian, linear_solve, separable

__all__ = ["share_materials", "unmatched_texels", "kmeans_pp", "pooled_materials", "borrow_albedo",
           "material_targets", "shared_default", "MIN_EVIDENCE"]


#: χ² evidence (summed over the texels that prefer it, :func:`_supported`) below which a candidate material is
#: dropped: 10 texels' worth of the assignment's evidence margin. Measured: duplicates and border mixtures 0–82,
#: real materials ≥ 502 (docs/log.md, "candidate materials the photos do not need").
MIN_EVIDENCE = 100.0


def kmeans_pp(x: Tensor, k: int, generator: torch.Generator | None = None, iterations: int = 50,
              restarts: int = 8) -> Tensor:
    """Cluster centres ``[k', D]`` (k' = min(k, number of distinct points)) of points ``x [N, D]``.

    k-means++ seeding (each next seed drawn with probability ∝ squared distance to the nearest seed,
    so separated modes get a seed even when they hold few points), then Lloyd iterations by
    :class:`kornia.contrib.KMeans` started from those seeds; ``restarts`` draws, keeping the centres with
    the least within-cluster sum of squares (as scikit-learn's ``n_init``). One draw left the default scene's
    outcome to chance: the k-means seed alone moved its all-texel f0 / roughness over 0.013–0.030 /
    0.049–0.074 (docs/log.md, "second basins are local minima").
    """
    if x.dim() != 2 or x.shape[0] == 0:
        raise ValueError(f"kmeans_pp: x must be [N, D] with N ≥ 1, got {tuple(x.shape)}")
    if k < 1 or restarts < 1:
        raise ValueError(f"kmeans_pp: k and restarts must be ≥ 1, got {k}, {restarts}")
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    xs = x.cpu()
    best, best_ss = None, math.inf
    for _ in range(restarts):
        seeds = [int(torch.randint(xs.shape[0], (1,), generator=gen))]
        d2 = (xs - xs[seeds[0]]).square().sum(-1)
        while len(seeds) < k and float(d2.max()) > 1e-12:
            i = int(torch.multinomial(d2 / d2.sum(), 1, generator=gen))
            seeds.append(i)
            d2 = torch.minimum(d2, (xs - xs[i]).square().sum(-1))
        centres = xs[seeds].clone()
        if len(seeds) > 1:
            km = KMeans(len(seeds), centres, tolerance=1e-10, max_iterations=iterations)
            km.fit(xs)
            centres = km.cluster_centers
        ss = float(torch.cdist(xs, centres).amin(1).square().sum())
        if ss < best_ss:
            best, best_ss = centres, ss
    return best.to(x)


def _chi2_observations(obs: Observations, noise: tuple[float, float]) -> Observations:
    """The observations with weights divided by the photo noise variance (mean over channels), so
    that costs are χ² values: ``σ = rel · max(|y|, floor · median y)`` as in :func:`posterior_std`."""
    sig2 = noise_sigma(obs.radiance.double(), noise).square().mean(-1)
    return replace(obs, weight=(obs.weight.double() / sig2).to(obs.weight.dtype))


def _per_texel_specs(model: Model, layout, dtype) -> tuple[list, dict[str, bool]]:
    """The parameters each texel keeps of its own (the diffuse albedo, when it enters linearly) and, for
    :func:`capture.fit.texel.linear_solve`, whether each is a separable RGB parameter."""
    per_texel = [s for s in layout.specs if s.name == "albedo" and s.linear]
    return per_texel, {s.name: s.channels == 3 and separable(model, s, dtype) for s in per_texel}


def _box_sum(x: Tensor, s: int) -> Tensor:
    """Sum of ``x [K, H, W]`` over the s×s box (s odd) centred on each texel, zero outside (integral image)."""
    K, H, W = x.shape
    r = s // 2
    c = F.pad(x, (r + 1, r, r + 1, r)).cumsum(-1).cumsum(-2)                     # [K, H + s, W + s]
    return c[:, s:, s:] - c[:, :-s, s:] - c[:, s:, :-s] + c[:, :-s, :-s]


def _misfit(costs: Tensor, residuals: Tensor, pooled: float | None = None, unknowns: int = 3) -> Tensor:
    """``[T]`` misfit s² ≥ 1 of each texel's best candidate: its χ² per residual — and, when the photos' noise
    measured in image space exceeds the noise model (``pooled`` = :func:`capture.fit.noise.photo_noise_ratio` > 1),
    at least the estimate moderated towards it (:func:`capture.fit.noise.moderated_misfit`, dof = residuals −
    ``unknowns``: the albedo's 3 channels are solved in closed form). A texel with one sample has no misfit of its
    own (its closed-form albedo fits that sample exactly), so under photo noise far above the noise model its χ²
    differences were taken at face value: with shot noise the gold's lower band (1 sample per texel at grazing
    angles) rejected the gold by 9–24 χ² and took dark dielectrics. Unchanged on noise-free photos."""
    best = costs.min(0).values
    return torch.maximum((best / residuals.clamp_min(1)).clamp_min(1.0),
                         moderated_misfit(best, residuals - unknowns, pooled))


def _excess(costs: Tensor, residuals: Tensor | None, pooled: float | None = None) -> Tensor:
    """``[K, T]`` χ² of each candidate above the texel's best; with ``residuals`` (``[T]``) a texel that
    its best candidate explains worse than the noise model (bilinear mixing at an edge, a material no
    candidate matches, photo noise) has its differences deflated by that misfit (:func:`_misfit`)."""
    best = costs.min(0).values
    excess = costs - best
    if residuals is not None:
        excess = excess / _misfit(costs, residuals, pooled)
    return excess


def _assign(costs: Tensor, observed: Tensor, H: int, W: int, evidence: float, cap: float | None = None,
            residuals: Tensor | None = None, prior: Tensor | None = None,
            pooled: float | None = None) -> tuple[Tensor, Tensor]:
    """Per texel one candidate, decided at the finest scale where the evidence is conclusive.

    A texel's *excess* cost of a candidate is its χ² above the texel's best; the candidates it
    *admits* are those with an excess within ``evidence``. At scale s (box sizes 1, 3, 9, … texels)
    the excesses, each capped at ``cap``, are summed over the s×s box around the texel; the texel is
    decided at the first scale where, among the candidates it admits, the best box sum beats the
    second best by ``evidence``. So a texel whose own samples are inconclusive borrows the evidence
    of its neighbourhood but never takes a candidate its own samples reject, and thanks to the cap
    the neighbourhood decides by how many texels reject a candidate, not by the one texel with the
    strongest highlight (without the cap a metal's highlights reached into the next material's
    stripe: default scene f0 RMSE after sharing 0.158 → 0.078 with cap 15 and ``residuals``).

    Args:
        costs: ``[K, T]`` χ² cost of each candidate in each texel.
        cap: largest excess one texel contributes to a box (None = no cap).
        residuals: ``[T]`` number of residuals per texel; when given, a texel that its best candidate
            explains worse than the noise model (χ²/residuals = s² > 1: bilinear mixing at an edge, a
            material no candidate matches) has its excesses divided by s².
        prior: ``[K, T]`` extra cost added to the (deflated) excesses, e.g. :func:`_albedo_prior`.
        pooled: the photos' noise against the noise model (:func:`capture.fit.noise.photo_noise_ratio`), which
            the misfit deflation moderates towards (:func:`_misfit`).
    Returns:
        ``(label [T], scale [T])`` — the box size that decided each texel (0 where unobserved).
    """
    K, T = costs.shape
    label = costs.argmin(0)
    scale = torch.zeros(T, dtype=torch.long, device=costs.device)
    if K == 1:
        scale[observed] = 1
        return label, scale
    excess = _excess(costs, residuals, pooled)
    if prior is not None:
        excess = excess + prior
        excess = excess - excess.min(0).values
    rejected = excess > evidence                                                      # [K, T]
    grid = (excess if cap is None else excess.clamp_max(cap)).reshape(K, H, W)
    undecided = observed.clone()
    s = 1
    while bool(undecided.any()):
        cs = (grid if s == 1 else _box_sum(grid, s)).reshape(K, T).masked_fill(rejected, math.inf)
        best = cs.topk(2, 0, largest=False)
        last = s >= max(H, W)
        pick = undecided & ((best.values[1] - best.values[0] > evidence) | last)
        label[pick] = best.indices[0][pick]
        scale[pick] = s
        undecided &= ~pick
        if last:
            break
        s *= 3
    return label, scale


def _supported(costs: Tensor, own: Tensor, cap: float | None, residuals: Tensor | None,
               min_evidence: float, pooled: float | None = None) -> Tensor:
    """``[K]`` bool: the candidates the photos need, by backward elimination.

    A candidate's *evidence* is what the texels that prefer it would lose without it: the sum over the
    texels with samples of their own (``own``) whose best candidate it is of their excess χ² (:func:`_excess`,
    data only, misfit-deflated) at the second best, each capped at ``cap`` as in :func:`_assign`. The candidate
    with the least evidence is dropped while that is below ``min_evidence``, and the evidence recomputed — so of
    two duplicates (evidence 0 each) one goes and the other then holds their texels' evidence.
    """
    K = costs.shape[0]
    excess = _excess(costs, residuals, pooled)
    alive = torch.ones(K, dtype=torch.bool, device=costs.device)
    while int(alive.sum()) > 1:
        two = excess.masked_fill(~alive[:, None], math.inf).topk(2, 0, largest=False)
        gain = (two.values[1] - two.values[0]).clamp_max(math.inf if cap is None else cap)
        ev = torch.zeros(K, dtype=excess.dtype, device=costs.device).index_add(0, two.indices[0][own], gain[own])
        ev = ev.masked_fill(~alive, math.inf)
        j = int(ev.argmin())
        if float(ev[j]) >= min_evidence:
            break
        alive[j] = False
    return alive


def _albedo_prior(albedo: Tensor, anchors: Tensor, anchor_label: Tensor, own: Tensor,
                  floor: float = 0.02, min_anchors: int = 3) -> Tensor:
    """``[K, T]`` χ²-like cost of each texel's albedo under each candidate against that material's albedo.

    A material is a specular lobe *and* a distribution of albedo: mean μ_k and per-channel variance
    σ_k² over the anchors labelled k (their albedo is determined), floored at ``floor``². A texel's cost
    for candidate k is ``Σ_c (a_tc^(k) − μ_kc)² / (σ_kc² + floor²)`` with a^(k) its closed-form albedo
    under k — a metal (albedo ≈ 0 on all its anchors) rejects a blue texel that its few samples could
    not tell from the metal's lobe, a textured material (large σ) rejects little. 0 for materials
    with fewer than ``min_anchors`` anchors and for texels without samples of their own.
    """
    K, T, C = albedo.shape
    idx = anchors.nonzero()[:, 0]
    a = albedo[anchor_label, idx]                                                    # [A, C]
    cnt = torch.bincount(anchor_label, minlength=K).to(albedo.dtype)
    mean = torch.zeros(K, C, dtype=albedo.dtype, device=albedo.device).index_add(0, anchor_label, a)
    mean = mean / cnt.clamp_min(1)[:, None]
    var = torch.zeros(K, C, dtype=albedo.dtype, device=albedo.device).index_add(
        0, anchor_label, (a - mean[anchor_label]).square()) / cnt.clamp_min(1)[:, None]
    cost = ((albedo - mean[:, None]).square() / (var + floor ** 2)[:, None]).sum(-1)   # [K, T]
    return torch.where((cnt >= min_anchors)[:, None] & own[None], cost, torch.zeros_like(cost))


def pooled_materials(model: Model, layout, chi: Observations, pool: Tensor, *, block: int = 4,
                     grid: int = 12) -> tuple[Tensor, Tensor, Tensor] | None:
    """The best material of each ``block × block`` tile of the ``pool`` texels, fitted on their samples pooled.

    A texel whose samples never show a highlight's peak cannot tell f0 from roughness (its per-texel fit is no
    anchor), but a few neighbours of one material seen from different angles together can: a lobe shared by the
    tile, an albedo per texel. For each of ``grid`` roughness values (:func:`capture.fit.texel.grid_values`)
    the tile's f0 and its texels' albedos are the weighted least-squares solution — the albedos eliminated
    per texel (Schur complement), then f0 per tile and channel, both clipped to their range — from per-texel
    sufficient statistics, so one roughness value costs three model evaluations on the pool's samples. Each
    tile keeps its cheapest roughness.

    Applies to models whose per-texel parameter is a separable RGB albedo and whose shared ones are one
    separable RGB linear parameter (f0 under Schlick) and one scalar nonlinear one (roughness); ``None``
    otherwise.

    Args:
        chi: observations with χ² weights (:func:`_chi2_observations`); nearest texel.
        pool: ``[T]`` bool, the texels whose samples are pooled.

    Returns:
        ``(materials [B, Ps] canonical shared values in layout order, cost [B] χ² of the tile's pool texels at
        them, tile [T] index of each texel's tile)``, or None. B = ⌈H / block⌉ · ⌈W / block⌉.
    """
    per_texel = [s for s in layout.specs if s.name == "albedo" and s.linear]
    shared = [s for s in layout.specs if s not in per_texel]
    lin = [s for s in shared if s.linear]
    non = [s for s in shared if not s.linear]
    if (len(per_texel) != 1 or len(lin) != 1 or len(non) != 1 or non[0].channels != 1
            or any(s.channels != 3 or not separable(model, s, chi.dtype) for s in per_texel + lin)):
        return None
    alb, f0s, rough = per_texel[0], lin[0], non[0]
    H, W = chi.map_size
    T = H * W
    dev = pool.device
    sub = chi.select(pool[chi.texel])
    tile = block_index(H, W, block, dev)
    nb = int(tile.max()) + 1
    tex = sub.texel
    y, w = sub.radiance.to(ACC), sub.weight.to(ACC)[:, None]
    S = sub.n_samples

    def const(spec, v):
        return torch.full((S, spec.channels), float(v), dtype=sub.dtype, device=dev)

    def per_texel_sum(x):                                    # [S, 3] → [T, 3]
        return torch.zeros(T, 3, dtype=ACC, device=dev).index_add_(0, tex, x)

    def per_tile_sum(x):                                     # [T, 3] → [nb, 3]
        return torch.zeros(nb, 3, dtype=ACC, device=dev).index_add_(0, tile, x)

    best_cost = torch.full((nb,), math.inf, dtype=ACC, device=dev)
    best_f0 = torch.zeros(nb, 3, dtype=ACC, device=dev)
    best_r = torch.zeros(nb, dtype=ACC, device=dev)
    with torch.no_grad():
        for r in grid_values(rough, grid, ACC, dev).tolist():
            p = {s.name: const(s, s.default) for s in layout.specs}
            p.update({alb.name: const(alb, 0.0), f0s.name: const(f0s, 0.0), rough.name: const(rough, r)})
            b = sub.predict(model, p).to(ACC)
            a1 = sub.predict(model, {**p, alb.name: const(alb, 1.0)}).to(ACC) - b
            a2 = sub.predict(model, {**p, f0s.name: const(f0s, 1.0)}).to(ACC) - b
            r0 = y - b
            s11, s12, s22 = per_texel_sum(w * a1 * a1), per_texel_sum(w * a1 * a2), per_texel_sum(w * a2 * a2)
            t1, t2, rr = per_texel_sum(w * a1 * r0), per_texel_sum(w * a2 * r0), per_texel_sum(w * r0 * r0)
            inv = torch.where(s11 > 0, 1.0 / s11.clamp_min(1e-300), torch.zeros_like(s11))
            ft = per_tile_sum(t2 - s12 * t1 * inv) / per_tile_sum(s22 - s12 * s12 * inv).clamp_min(1e-300)
            ft = ft.clamp(f0s.low, f0s.high)                                            # [nb, 3]
            f = ft[tile]                                                                # [T, 3]
            a = ((t1 - s12 * f) * inv).clamp(alb.low, alb.high)
            cost = (rr - 2 * (a * t1 + f * t2) + a * a * s11 + 2 * a * f * s12 + f * f * s22).sum(-1)
            cost = torch.zeros(nb, dtype=ACC, device=dev).index_add_(0, tile, torch.where(pool, cost, 0.0))
            better = cost < best_cost
            best_cost = torch.where(better, cost, best_cost)
            best_f0 = torch.where(better[:, None], ft, best_f0)
            best_r = torch.where(better, torch.full_like(best_r, r), best_r)
    mats = torch.cat([best_f0 if s is f0s else best_r[:, None] for s in shared], -1)
    return mats, best_cost, tile


def _propose_pooled(model: Model, layout, chi: Observations, costs: Tensor, pool: Tensor, anchors: Tensor,
                    residuals: Tensor, thr: Tensor, block: int, evidence: float, n_max: int, gen: torch.Generator,
                    info: dict) -> Tensor | None:
    """Materials for the candidates' blind spots: ``[n, Ps]`` canonical shared values, or None.

    The tiles of :func:`pooled_materials` whose pooled material beats the best existing candidate (``costs``
    ``[K, T]``, χ²) by more than ``evidence`` summed over their ``pool`` texels propose it; the proposals are
    clustered (:func:`kmeans_pp`, features in threshold units ``thr``) into at most ``n_max`` materials. A tile
    proposes only where the anchors leave a blind spot — none in it or its 8 neighbouring tiles — and its gain
    is divided by the pooled fit's misfit (χ² per residual, ≥ 1). Records ``pooled_tiles`` (tiles that
    proposed) and ``pooled_s`` in ``info``."""
    t0 = time.perf_counter()
    res = pooled_materials(model, layout, chi, pool, block=block)
    info["pooled_tiles"] = 0
    if res is None:
        return None
    mats, cost, tile = res
    W = chi.map_size[1]
    per_tile = lambda x: torch.zeros_like(cost).index_add_(0, tile, x)  # noqa: E731  [T] → [tiles]
    existing = per_tile(torch.where(pool, costs.min(0).values, 0.0))
    # deflated by the pooled fit's misfit (χ² per residual, ≥ 1) as :func:`_excess` deflates a texel's evidence:
    # tiles across a stripe border or a bilinear edge, which no single material explains, propose nothing
    misfit = (cost / per_tile(torch.where(pool, residuals, 0.0)).clamp_min(1)).clamp_min(1.0)
    gain = (existing - cost) / misfit
    # a blind spot: no anchor in the tile or the 8 tiles around it
    near = F.max_pool2d(per_tile(anchors.to(cost.dtype)).reshape(1, 1, -1, (W + block - 1) // block), 3, 1, 1)
    win = torch.isfinite(cost) & (gain > evidence) & (near.reshape(-1) == 0)
    info["pooled_tiles"] = int(win.sum())
    info["pooled_s"] = time.perf_counter() - t0
    if not bool(win.any()):
        return None
    return kmeans_pp(mats[win] / thr, n_max, gen) * thr


def share_materials(model: Model, obs: Observations, layout, theta: Tensor, anchors: Tensor, *,
                    candidates: int = 8, rounds: int = 2, refit_iterations: int = 5, evidence: float = 10.0,
                    cap: float | None = 15.0, misfit: bool = True, albedo_prior: float = 1.0, prior_cap: float = 15.0,
                    min_evidence: float = MIN_EVIDENCE, noise: tuple[float, float] = (0.01, 0.1),
                    pool_block: int = 0, pool_evidence: float = 100.0, pool_candidates: int = 3,
                    seed: int = 0, seeds: Tensor | None = None) -> tuple[Tensor, dict]:
    """Replace the shared parameters of every observed texel by those of one of a few materials.

    Args:
        model: the material model; obs: the observations (nearest texel of each sample is used).
        layout: the solver's :class:`capture.fit.layout.Layout` of ``model``.
        theta: ``[T, P]`` per-texel fit (θ parameterisation, float64).
        anchors: ``[T]`` bool, texels whose shared parameters the per-texel fit determined.
        candidates: number of candidate materials (k-means clusters of the anchors), ≥ 1.
        rounds: assignment + refit rounds, ≥ 1.
        refit_iterations: LM iterations per refit of the candidates' parameters.
        cap, misfit: the per-texel cap on a box's evidence and the misfit deflation of :func:`_assign`.
        albedo_prior, prior_cap: weight of the materials' albedo prior (:func:`_albedo_prior`; 0 = off)
            and the cap on its cost — a texel that no material's albedo fits is left to the photos.
        min_evidence: χ² a candidate's texels must lose without it for it to stay (:func:`_supported`,
            :data:`MIN_EVIDENCE`); 0 = keep every candidate. Measured (default scene's rig, RMSE on all observed
            texels albedo / f0 / roughness): 3 materials 0.0120 / 0.0834 / 0.0858 → 0.0081 / 0.0108 / 0.0160,
            2 materials 0.0049 / 0.0025 / 0.0241 → 0.0044 / 0.0023 / 0.0112, 6 materials unchanged (every
            candidate needed); docs/log.md, "candidate materials the photos do not need", for the
            small scenes.
        evidence: χ² margin (noise model ``noise``) by which the best candidate must beat the second
            best before a texel is decided at a scale; candidates its own samples put further than
            this above their best are never assigned to it.
        noise: photo noise model ``(relative std, floor fraction)`` that turns costs into χ².
        pool_block, pool_evidence, pool_candidates: pooled proposals (0 = off, the default): before the first
            assignment, tiles of ``pool_block``² texels where the anchors leave a blind spot and whose non-anchor
            texels, pooled, fit a material of their own better than every candidate by ``pool_evidence`` χ²
            (:func:`pooled_materials`, :func:`_propose_pooled`) add up to ``pool_candidates`` materials, which
            the pruning then keeps or drops like the others. For a material that gives no anchor (a rough
            dielectric under fixed lights). Measured (docs/log.md, "second basins are local minima";
            RMSE on all observed texels albedo / f0 / roughness, off → 4): fixed-light rig 0.0104 / 0.0130 /
            0.1089 → 0.0093 / 0.0119 / 0.0481, shot noise 0.0245 / 0.1381 / 0.1589 → 0.0244 / 0.1035 / 0.1524,
            but the default scene 0.0062 / 0.0126 / 0.0510 → 0.0082 / 0.0294 / 0.0617 — hence off by default.
        seed: seed of the k-means++ draw.
        seeds: ``[N, Ps]`` canonical values of the shared parameters (layout order) clustered with the anchors'
            (:func:`capture.fit.observability.tile_seeds`: tiles whose texels agree on a material none of them
            determines alone); None = the anchors only.

    Returns:
        ``(theta [T, P], info)``: θ with the shared parameters of the assigned material and the
        albedo re-solved in closed form, except at the anchors, which keep their own fit; ``info``
        has ``materials`` (canonical values of each), ``labels`` ``[T]`` (−1 where unobserved),
        ``material_cost`` ``[T]`` (χ² of each texel's own samples under its material, nearest texel; for
        :func:`unmatched_texels`), ``decided_at`` (texel counts per box size), ``pruned`` (candidates
        the photos did not need, :func:`_supported`), ``share_s`` and the shared parameter names.
        Unchanged θ (``info["materials"] = []``) when the model has nothing to share or there are
        no anchors.
    """
    t0 = time.perf_counter()
    _check_options(candidates, rounds, refit_iterations, evidence, pool_block, pool_candidates, pool_evidence,
                   min_evidence)
    T, _ = theta.shape
    H, W = obs.map_size
    dev = theta.device
    per_texel, sep = _per_texel_specs(model, layout, obs.dtype)
    shared = [s for s in layout.specs if s not in per_texel]
    info = {"materials": [], "shared": [s.name for s in shared], "share_s": 0.0}
    observed = obs.footprint()
    anchors = anchors & observed
    if not shared or not per_texel or not bool(anchors.any()):
        info["labels"] = torch.full((T,), -1, dtype=torch.long, device=dev)
        return theta, info
    scols = [c for s in shared for c in layout.cols(s.name)]
    thr = torch.tensor([std_threshold(s) for s in shared for _ in range(s.channels)], dtype=ACC, device=dev)
    feats = layout.canonical(theta)[anchors][:, scols] / thr
    gen = torch.Generator().manual_seed(seed)
    if seeds is not None and (seeds.dim() != 2 or seeds.shape[1] != len(scols)):
        raise ValueError(f"share_materials: seeds must be [N, {len(scols)}] values of the shared parameters "
                         f"{[s.name for s in shared]}, got {tuple(seeds.shape)}")
    points = feats if seeds is None or seeds.shape[0] == 0 else torch.cat([feats, seeds.to(feats) / thr])
    centres = kmeans_pp(points, candidates, gen) * thr                                 # canonical [K, Ps]
    ctx = _Context(model, layout, _chi2_observations(obs, noise), shared, per_texel, sep, scols)
    st = _Round(theta=theta, mat=_as_materials(ctx, theta, centres),
                kmeans_label=torch.cdist(feats, centres / thr).argmin(1),
                label=torch.zeros(T, dtype=torch.long, device=dev), scale=torch.zeros(T, dtype=torch.long, device=dev))
    groups = [c for c in param_groups(layout) if all(x in scols for x in c)]
    y, w = ctx.chi.radiance.to(ACC), ctx.chi.weight.to(ACC)
    residuals = 3.0 * torch.bincount(obs.texel, minlength=T).to(ACC)
    pool_s2 = photo_noise_ratio(obs, noise) if misfit else None
    own = residuals > 0
    with torch.no_grad():
        for rnd in range(rounds):
            cands, costs = _under_each(ctx, st.theta, st.mat)                         # [K, T, P], [K, T]
            if rnd == 0 and pool_block > 0 and pool_candidates > 0:
                extra = _propose_pooled(model, layout, ctx.chi, costs, own & ~anchors, anchors, residuals, thr,
                                        pool_block, pool_evidence, pool_candidates, gen, info)
                if extra is not None:
                    cands, costs = _add_candidates(ctx, st, cands, costs, extra)
            if min_evidence > 0:
                alive = _supported(costs, observed & own, cap, residuals if misfit else None, min_evidence, pool_s2)
                if not bool(alive.all()):
                    cands, costs = _drop_candidates(st, cands, costs, alive, anchors)
            prior = None
            if albedo_prior > 0:
                stat_set, a_lab = _albedo_statistics_set(st, rnd, anchors, own)
                prior = (albedo_prior * _albedo_prior(layout.unpack(cands)[per_texel[0].name], stat_set, a_lab, own)
                         ).clamp_max(prior_cap)
            st.label, st.scale = _assign(costs, observed, H, W, evidence, cap, residuals if misfit else None, prior,
                                         pool_s2)
            st.theta = cands[st.label, torch.arange(T, device=dev)]
            st.decided = {int(x): int((st.scale == x).sum()) for x in st.scale[observed].unique()}
            st.mat = _refit(model, layout, ctx.chi, st.theta, st.mat, st.label, scols, groups, y, w, refit_iterations)
        th = st.theta.clone()
        th[:, scols] = st.mat[st.label][:, scols]
        th, material_cost = linear_solve(model, layout, ctx.chi, th, per_texel, sep, "l2", 1.0)
        # anchors keep their own fit: their samples determined it, and a material's smooth variation
        # (a roughness gradient) lives there
        out = torch.where(anchors[:, None], theta, th)
        # texels read only through a neighbour's bilinear footprint have no closed-form albedo of their own:
        # pull-push from the texels of the same material that have one (of any material where none has;
        # measured on the default scene: albedo RMSE 0.0173 → 0.0151 against any-material pull-push)
        out = borrow_albedo(layout, out, torch.where(observed, st.label, torch.full_like(st.label, -1)), own, H, W)
    K = st.mat.shape[0]
    lab = torch.where(observed, st.label, torch.full_like(st.label, -1))
    mats = layout.unpack(st.mat)
    info.update(materials=[{s.name: mats[s.name][k].tolist() for s in shared} for k in range(K)], labels=lab,
                material_cost=material_cost, decided_at=st.decided, photo_noise_ratio=pool_s2,
                texels_per_material=torch.bincount(st.label[observed], minlength=K).tolist(), pruned=st.pruned,
                share_s=time.perf_counter() - t0)
    return out, info


def _check_options(candidates: int, rounds: int, refit_iterations: int, evidence: float, pool_block: int,
                   pool_candidates: int, pool_evidence: float, min_evidence: float) -> None:
    """A ValueError naming the options of :func:`share_materials` out of their range."""
    if candidates < 1 or rounds < 1 or refit_iterations < 0 or not (evidence >= 0 and math.isfinite(evidence)):
        raise ValueError(f"share_materials: need candidates ≥ 1, rounds ≥ 1, refit_iterations ≥ 0 and a finite "
                         f"evidence ≥ 0, got {candidates}, {rounds}, {refit_iterations}, {evidence}")
    if isinstance(pool_block, bool) or not isinstance(pool_block, int) or pool_block < 0 or pool_candidates < 0 \
            or not (pool_evidence >= 0 and math.isfinite(pool_evidence)):
        raise ValueError(f"share_materials: pool_block must be an integer ≥ 0 (0 = no pooled proposals), "
                         f"pool_candidates ≥ 0 and pool_evidence a finite χ² ≥ 0, got {pool_block!r}, "
                         f"{pool_candidates!r}, {pool_evidence!r}")
    if not (min_evidence >= 0 and math.isfinite(min_evidence)):
        raise ValueError(f"share_materials: min_evidence must be a finite χ² ≥ 0 (0 keeps every candidate), "
                         f"got {min_evidence!r}")


class _Context(NamedTuple):
    """What the steps of :func:`share_materials` read: the model and its layout, the observations with χ² weights,
    the shared and the per-texel parameters (with the latter's separability) and the shared parameters' columns."""

    model: Model
    layout: Layout
    chi: Observations
    shared: list
    per_texel: list
    sep: dict[str, bool]
    scols: list[int]


@dataclass
class _Round:
    """What :func:`share_materials` carries from round to round: every texel's θ under its candidate (``theta``,
    the per-texel fit before the first round), the candidates ``mat [K, P]`` (θ rows; only the shared columns
    count), the anchors' k-means labels, each texel's candidate ``label`` and the box size that decided it
    (``scale``), the texel counts per box size and the candidates dropped so far."""

    theta: Tensor
    mat: Tensor
    kmeans_label: Tensor
    label: Tensor
    scale: Tensor
    decided: dict = field(default_factory=dict)
    pruned: int = 0


def _as_materials(ctx: _Context, theta: Tensor, c: Tensor) -> Tensor:
    """Canonical shared values ``c [k, Ps]`` → θ rows ``[k, P]`` (only the shared columns count)."""
    m = theta[:c.shape[0]].clone()
    off = 0
    for s in ctx.shared:
        m[:, ctx.layout.cols(s.name)] = _from_canon(s, c[:, off:off + s.channels])
        off += s.channels
    return m


def _under_each(ctx: _Context, theta: Tensor, m: Tensor) -> tuple[Tensor, Tensor]:
    """Per candidate row of ``m``: every texel's θ with its closed-form albedo and its χ² → ``[k, T, P]``,
    ``[k, T]``."""
    out = []
    for k in range(m.shape[0]):
        th = theta.clone()
        th[:, ctx.scols] = m[k, ctx.scols]
        out.append(linear_solve(ctx.model, ctx.layout, ctx.chi, th, ctx.per_texel, ctx.sep, "l2", 1.0))
    return torch.stack([o[0] for o in out]), torch.stack([o[1] for o in out])


def _add_candidates(ctx: _Context, st: _Round, cands: Tensor, costs: Tensor, extra: Tensor) -> tuple[Tensor, Tensor]:
    """Append the candidates of canonical shared values ``extra`` to ``st.mat`` and their texels' fits and costs to
    ``cands``, ``costs``."""
    new_mat = _as_materials(ctx, st.theta, extra)
    new_cands, new_costs = _under_each(ctx, st.theta, new_mat)
    cands, costs = torch.cat([cands, new_cands]), torch.cat([costs, new_costs])
    st.mat = torch.cat([st.mat, new_mat])
    return cands, costs


def _drop_candidates(st: _Round, cands: Tensor, costs: Tensor, alive: Tensor,
                     anchors: Tensor) -> tuple[Tensor, Tensor]:
    """Keep the ``alive`` candidates only (in ``st`` and in ``cands``, ``costs``)."""
    # a material the photos do not need exists only to absorb weakly observed texels: a duplicate,
    # a spare k-means cluster of border mixtures. Drop it; the anchors it held (k-means labels) and
    # the last round's labels move to their best remaining candidate
    K, dev = st.mat.shape[0], st.mat.device
    keep = alive.nonzero()[:, 0]
    st.pruned += int(K - keep.numel())
    remap = torch.full((K,), -1, dtype=torch.long, device=dev)
    remap[keep] = torch.arange(keep.numel(), device=dev)
    costs, cands, st.mat = costs[keep], cands[keep], st.mat[keep]
    nearest = costs.argmin(0)
    st.kmeans_label = torch.where(remap[st.kmeans_label] >= 0, remap[st.kmeans_label], nearest[anchors])
    st.label = torch.where(remap[st.label] >= 0, remap[st.label], nearest)
    return cands, costs


def _albedo_statistics_set(st: _Round, rnd: int, anchors: Tensor, own: Tensor) -> tuple[Tensor, Tensor]:
    """The texels whose albedo makes the materials' albedo statistics (:func:`_albedo_prior`) and their labels."""
    # the albedo statistics come from the anchors (labelled by k-means) and, after the first
    # round, the texels their own samples decided; not from texels labelled by their neighbours,
    # whose errors would widen a material's albedo range round after round
    if rnd == 0:
        return anchors, st.kmeans_label
    stat_set = anchors | (own & (st.scale == 1))
    a_lab = st.label[stat_set]
    a_lab[anchors[stat_set]] = st.kmeans_label
    return stat_set, a_lab

def unmatched_texels(model: Model, obs: Observations, layout, theta: Tensor, info: dict, *, evidence: float = 10.0,
                     noise: tuple[float, float] = (0.01, 0.1)) -> Tensor:
    """``[T]`` bool: texels whose own per-texel fit ``theta`` beats their shared material by more than
    ``evidence`` χ² (noise model ``noise``; albedo re-solved in closed form for both, nearest texel) — the
    photos reject the material the texel was given, e.g. a dielectric on a metal when no metal material was
    found.

    ``info`` is :func:`share_materials`'s (its ``material_cost`` and ``labels``). The difference is divided
    by the misfit s² = max(1, χ²_best / residuals) as in :func:`_assign`. On the default scene (a good
    material set) 4 % of the observed texels are unmatched — stripe borders, whose nearest-texel fit
    absorbs the bilinear mixing, and the roughness gradient; on a layered scene whose metals gave no
    anchor, 37 %. :func:`capture.fit.fast.solve_fast` uses them only when the sharing has failed.
    """
    if "material_cost" not in info:
        raise ValueError("unmatched_texels: info must come from share_materials (it has no 'material_cost')")
    if theta.dim() != 2 or theta.shape[0] != obs.n_texels or info["material_cost"].shape != (obs.n_texels,):
        raise ValueError(f"unmatched_texels: theta must be [T, P] and info from share_materials on the same "
                         f"observations (T = {obs.n_texels}), got theta {tuple(theta.shape)} and material_cost "
                         f"{tuple(info['material_cost'].shape)}")
    per_texel, sep = _per_texel_specs(model, layout, obs.dtype)
    chi = _chi2_observations(obs, noise)
    with torch.no_grad():
        _, own_cost = linear_solve(model, layout, chi, theta, per_texel, sep, "l2", 1.0)
    mcost = info["material_cost"]
    residuals = 3.0 * torch.bincount(obs.texel, minlength=theta.shape[0]).to(mcost)
    s2 = (torch.minimum(own_cost, mcost) / residuals.clamp_min(1)).clamp_min(1.0)
    return (info["labels"] >= 0) & (residuals > 0) & ((mcost - own_cost) / s2 > evidence)


def borrow_albedo(layout, theta: Tensor, label: Tensor, own: Tensor, H: int, W: int) -> Tensor:
    """θ with the per-texel (albedo) parameters of the texels read only through a neighbour's bilinear
    footprint (``label ≥ 0`` and not ``own``: no sample of their own) replaced by a pull-push fill from
    the texels of the same material that have samples (of any material where none has). Returns a new θ.

    Their own data are a few percent of a neighbour's sample, so a neighbour's error δ moves them by
    ~δ / weight; measured on the default scene: albedo RMSE on all observed texels 0.0173 → 0.0151
    against a pull-push from texels of any material."""
    borrowed = (label >= 0) & ~own
    theta = theta.clone()
    if not bool(borrowed.any()) or not bool(own.any()):
        return theta
    T = theta.shape[0]
    for s in (s_ for s_ in layout.specs if s_.name == "albedo" and s_.linear):
        cols = torch.tensor(layout.cols(s.name), device=theta.device)
        vals = layout.unpack(theta)[s.name].reshape(H, W, -1)
        filled = pull_push(vals, own.reshape(H, W)).reshape(T, -1)
        for k in label[borrowed].unique().tolist():
            src = own & (label == k)
            if bool(src.any()):
                fk = pull_push(vals, src.reshape(H, W)).reshape(T, -1)
                filled = torch.where((label == k)[:, None], fk, filled)
        rows = borrowed.nonzero()[:, 0]
        theta[rows[:, None], cols] = from_canonical(s, filled[rows])
    return theta


def _from_canon(spec, x: Tensor) -> Tensor:
    return from_canonical(spec, x.clamp(spec.low + 1e-6 * min(spec.high - spec.low, 1.0),
                                        spec.high - 1e-6 * min(spec.high - spec.low, 1.0)))


def _refit(model, layout, obs, theta, mat, label, scols, groups, y, w, iterations, rtol: float = 1e-5):
    """Levenberg–Marquardt on each material's shared parameters over the samples of its texels
    (per-texel albedo in ``theta`` held), one damping factor and acceptance per material.

    A material stops once an accepted step lowers its cost by less than ``rtol`` (relative) and later
    iterations work on the samples of the materials still moving only. Measured (default scene, 2 threads):
    every material of the noise-free scenes settles within 2–3 iterations (relative change < 1e-6 after
    the second), one of the shot-noise scene's still drops 2 % at the fourth. Sharing stage 5.2 → 3.5 s on
    the default scene, 5.0 → 4.3 s with shot noise, maps unchanged to 4 decimals (docs/log.md,
    "k-means restarts and reverse-mode Jacobians")."""
    K = mat.shape[0]
    Ps = len(scols)
    dev = y.device
    lab_all = label[obs.texel]
    lam = torch.full((K,), 1e-3, dtype=ACC, device=dev)
    active = torch.ones(K, dtype=torch.bool, device=dev)
    sub, lab_s, ys, ws, th_s = obs, lab_all, y, w, theta[obs.texel]     # the samples of the active materials

    def per_sample(m):
        ph = th_s.clone()
        ph[:, scols] = m[lab_s][:, scols]
        return ph

    def cost_of(m):          # [K]: exact for the active materials (all their samples are in ``sub``)
        pred = sub.predict(model, layout.unpack(per_sample(m).to(sub.dtype))).to(ACC)
        return torch.zeros(K, dtype=ACC, device=dev).index_add(0, lab_s, ((ys - pred) ** 2).sum(-1) * ws)

    cur = cost_of(mat)
    for _ in range(iterations):
        if not bool(active[lab_s].all()):                  # drop the samples of settled materials
            keep = active[lab_all]
            sub, lab_s, ys, ws, th_s = obs.select(keep), lab_all[keep], y[keep], w[keep], theta[obs.texel[keep]]
        start = cur
        pred, J = jacobian(model, layout, sub, per_sample(mat), groups)
        r = ys - pred
        # the materials' normal equations a block of samples at a time, summed in the samples' order (the same
        # values to the last bit): the shared columns' copy and the products of all samples at once were three
        # [S, 3·Ps]-sized arrays beside the Jacobian
        A = torch.zeros(K, Ps, Ps, dtype=ACC, device=dev)
        g = torch.zeros(K, Ps, dtype=ACC, device=dev)
        step = block_size(SYSTEM_BLOCK, dev)
        for i in range(0, J.shape[0], step):
            j = min(i + step, J.shape[0])
            Js, lab = J[i:j][:, :, scols], lab_s[i:j]
            A.index_add_(0, lab, torch.einsum("scp,s,scq->spq", Js, ws[i:j], Js))
            g.index_add_(0, lab, torch.einsum("scp,s,sc->sp", Js, ws[i:j], r[i:j]))
        d = torch.diagonal(A, dim1=-2, dim2=-1)
        for _attempt in range(4):
            M = A + lam[:, None, None] * torch.diag_embed(d + 1e-12 * d.mean(-1, keepdim=True).clamp_min(1e-30))
            step = torch.nan_to_num(torch.linalg.solve_ex(M, g)[0])
            step = step.clamp(-MAX_STEP, MAX_STEP)
            trial = mat.clone()
            trial[:, scols] = trial[:, scols] + step
            new = cost_of(trial)
            acc = (new < cur) & active
            mat = torch.where(acc[:, None], trial, mat)
            cur = torch.where(acc, new, cur)
            lam = torch.where(acc, (lam / 3).clamp_min(1e-12), (lam * 4).clamp_max(1e12))
            if bool(acc[active].all()):
                break
        # settled: a step was taken and it changed the cost by less than rtol (a material whose every attempt
        # failed keeps its raised damping for the next iteration, as before)
        active = active & ((cur == start) | (start - cur > rtol * start))
        if not bool(active.any()):
            break
    return mat


def material_targets(layout: Layout, canon: Tensor, labels: Tensor, anchors: Tensor) -> Tensor:
    """``canon [T, P]`` with the shared parameters (:func:`shared_default`) of every labelled texel replaced by its
    material's median over that material's anchors (over all its texels where it has no anchor): the sharing's
    materials re-estimated from the current fit. Unlabelled texels (``labels`` −1) keep their own values."""
    out = canon.clone()
    cols = [c for s_, o in zip(layout.specs, layout.offsets, strict=True) if s_.name in shared_default(layout)
            for c in range(o, o + s_.channels)]
    if not cols:
        return out
    for k in torch.unique(labels[labels >= 0]).tolist():
        member = labels == k
        pick = member & anchors if bool((member & anchors).any()) else member
        out[member.nonzero()[:, 0][:, None], torch.tensor(cols, device=canon.device)] = \
            canon[pick][:, cols].median(0).values.to(out.dtype)
    return out


def shared_default(layout: Layout) -> list[str]:
    """Parameters a material shares (:func:`capture.fit.sharing.share_materials`; the anchors are the texels that
    determine all of them): every one but the diffuse albedo, which is a texture."""
    return [s.name for s in layout.specs if s.name != "albedo"]
