"""Observability: the marginal posterior std of every parameter in every texel, which texels determine a parameter
(and the sharing's anchors among them), pull-push filling, and the finalisation of a fit into a :class:`FitResult`.

A parameter is *unobservable* in a texel where its posterior std (:func:`posterior_std`: Gauss-Newton normal
matrix at the solution, a photo noise model of 1 % of the signal, inflated by the residual variance where the fit
is worse than that) is at or above its threshold (:data:`OBSERVABLE_STD`: 0.01 for albedo and f0, 0.02 for
roughness, in canonical units); this catches trade-offs between parameters (albedo vs f0, f0·α² of a GGX tail
without a highlight) that a one-parameter test misses. Unobservable values and unobserved texels are filled by
pull-push (:func:`pull_push`) and flagged; ``FitResult.raw`` keeps the fitted values.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from materials.atlas import pull_push  # the one pull-push fill; re-exported by capture.fit
from materials.model import Model
from materials.params import CANONICAL, ParamSpec
from renderer.device import block_size

from ..observations import Observations
from .layout import ACC, INVERSE_BLOCK, FitResult, Layout, SolverError
from .noise import NOISE, check_noise, irls_weights, moderated_misfit, noise_sigma, photo_noise_ratio
from .operators import NORMAL_BLOCK, pixel_operator, sampled_blocks, sampled_sum
from .texel import jacobian

__all__ = ["OBSERVABLE_STD", "RESOLVED_SHARE", "ANCHOR_MIN_FRACTION", "ANCHOR_LOOSENING", "SEED_BLOCK",
           "SEED_SPREAD", "std_threshold", "pull_push", "posterior_std", "finalize", "determined", "find_anchors",
           "anchors_at", "block_index", "tile_seeds"]


#: Default thresholds on the marginal posterior standard deviation (canonical units) below which a
#: parameter counts as observable in a texel (see :func:`posterior_std`): each parameter's
#: ``ParamSpec.threshold`` (materials/params.py, where they are declared with their reasons).
OBSERVABLE_STD = {p.name: p.threshold for p in CANONICAL.values()}


def std_threshold(spec: ParamSpec, observable_std: float | Mapping[str, float] | None = None) -> float:
    """The observability threshold of a parameter (canonical units), see :data:`OBSERVABLE_STD`."""
    if isinstance(observable_std, (int, float)) and not isinstance(observable_std, bool):
        return float(observable_std)
    table = dict(OBSERVABLE_STD)
    if observable_std is not None:
        table.update(observable_std)
    if spec.name in table:
        return float(table[spec.name])
    return spec.threshold


def posterior_std(model: Model, layout: Layout, obs: Observations, canon: Tensor, groups, *, loss: str = "l2",
                  delta: float = 1.0, noise=NOISE, sampling: str = "nearest",
                  footprints=None) -> tuple[Tensor, Tensor, Tensor]:
    """Marginal posterior standard deviation of every parameter column in every texel.

    Gauss-Newton at the solution: with ``J`` the Jacobian of the predicted radiance with respect
    to the texel's *canonical* parameters (albedo, f0, roughness, … in their own units), the photo
    noise model ``σ_sc = rel · max(|y_sc|, floor · median(y))`` (``noise = (rel, floor)``; default
    1 % of the signal — a well-exposed photo — never below 0.1 % of the median radiance) and IRLS
    weights ``w`` of a robust loss, the posterior covariance of a texel is
    ``C = s² (Jᵀ diag(w/σ²) J)⁻¹`` with ``s² = max(1, χ²/dof)`` (the residual variance, when the
    fit explains the photos worse than the noise model says) — and, when the photos' noise measured in image space
    exceeds the model's (:func:`photo_noise_ratio`), at least :func:`moderated_misfit`: a texel with few samples
    cannot tell its noise from its χ², which its unknowns absorb. The marginal std of a parameter is
    ``sqrt(C_pp)``: it accounts for every trade-off with the other parameters (albedo vs f0, the
    f0·α² degeneracy of a GGX tail seen without a highlight), which a one-parameter test misses.
    A direction no residual constrains gets a variance of ~1e12 (a 1e-12 relative ridge).

    ``sampling="bilinear"``: each sample reads four texels; the texel's block of the normal matrix
    is ``Σ_s w_sk² J_sᵀ W J_s`` (neighbours held fixed — a lower bound on the joint variance).

    ``footprints`` (:class:`capture.footprint.PixelFootprints`): the residuals are the photos' pixels and the
    texel's block is ``Σ_i C_itᵀ W_i C_it`` through the footprint operator (:class:`PixelOperator`); a pixel's χ²
    and residual count go to its texels by their shares. ``pred`` is then per pixel ``[R, 3]``.

    Args:
        canon: ``[T, P]`` canonical parameters (packed in :class:`Layout` order).

    Returns:
        ``(std [T, P], observed [T] bool, pred [S, 3])`` — std is +inf where unobserved.
    """
    check_noise(noise)
    T, P = canon.shape
    with torch.no_grad():
        if footprints is not None:
            op = pixel_operator(footprints, T)
            y = op.y
            # the blocks alone: the Jacobian's matrices and the gradient are the solve's, not the posterior's
            pred, w, A = op.information(model, layout, canon, groups,
                                        lambda p: irls_weights(y - p, loss, delta) / noise_sigma(y, noise).square())
            r = y - pred
            chi_e = (w * r * r).sum(-1)[op.e_pix] * op.e_share
            chi = op.texel_sum(chi_e)
            nres = op.texel_sum(3.0 * op.e_share)
            return _posterior_tail(A, chi, nres, obs, noise, P, y.device) + (pred,)
        if sampling == "bilinear":
            idx, bw = obs.bilinear_index, obs.bilinear_weight.to(ACC)
            # the corners' weighted sum a block of samples at a time ([S, 4, P] whole: 0.36 GB on 1.6 M pixel centres)
            per = torch.empty(obs.n_samples, P, dtype=canon.dtype, device=canon.device)
            step = block_size(NORMAL_BLOCK, canon.device)
            for a in range(0, obs.n_samples, step):
                b = min(a + step, obs.n_samples)
                torch.sum(canon[idx[a:b]] * bw[a:b, :, None], -2, out=per[a:b])
        else:
            idx, bw = obs.texel[:, None], None
            per = canon[obs.texel]
        pred, J = jacobian(model, layout, obs, per, groups, canonical=True)
        per = None
        y = obs.radiance.to(ACC)
        r = y - pred
        w = obs.weight.to(ACC)[:, None] * irls_weights(r, loss, delta) / noise_sigma(y, noise).square()   # [S, 3]
        chi_s = (w * r * r).sum(-1)
        per_sample = torch.stack([chi_s, 3.0 * (obs.weight.to(ACC) > 0)], -1)         # [S, 2]
        # Σ_s w_sk² J_sᵀWJ_s per texel, and the weight-shared χ² and residual counts (as in refine_joint)
        A = sampled_blocks(J, w, idx, None if bw is None else bw.square(), T)
        chi, nres = sampled_sum(per_sample, idx, bw, T).unbind(-1)
    return _posterior_tail(A, chi, nres, obs, noise, P, y.device) + (pred,)


def _posterior_tail(A: Tensor, chi: Tensor, nres: Tensor, obs: Observations, noise, P: int,
                    device) -> tuple[Tensor, Tensor]:
    """``(std [T, P], observed [T])`` from the per-texel information blocks ``A [T, P, P]``, χ² and residual counts
    (:func:`posterior_std`)."""
    with torch.no_grad():
        observed = nres > 0
        eye = torch.eye(P, dtype=ACC, device=device)
        T = A.shape[0]
        # an unobserved texel's variance is never read (its std is ∞ below): it keeps 1, the inverse of the identity
        # it once took, and only the observed texels' blocks are inverted (on 2048² maps fitted from 8 × 256² photos
        # most texels are unobserved by the pixel centres)
        var = torch.ones(T, P, dtype=ACC, device=device)
        singular = torch.zeros(T, dtype=torch.bool, device=device)
        seen = torch.nonzero(observed).squeeze(1)
        # a run of observed texels at a time (each block's inverse is its own): whole, the ridged blocks and the
        # covariances were more [T, P, P] arrays (4.9 GB on 2048² maps), of which only the diagonal is kept
        step = block_size(INVERSE_BLOCK, device)
        for a in range(0, len(seen), step):
            ids = seen[a:a + step]
            Ab = A[ids]
            dmax = torch.diagonal(Ab, dim1=-2, dim2=-1).amax(-1).clamp_min(1e-30)
            Ab = Ab + (1e-12 * dmax)[:, None, None] * eye
            cov, info = torch.linalg.inv_ex(Ab)
            var[ids] = torch.diagonal(cov, dim1=-2, dim2=-1)
            singular[ids] = info != 0
        bad = singular[:, None] | ~torch.isfinite(var) | (var < 0)
        var = torch.where(bad, torch.full_like(var, 1e12), var)
        s2 = torch.maximum((chi / (nres - P).clamp_min(1)).clamp_min(1.0),
                           moderated_misfit(chi, nres - P, photo_noise_ratio(obs, noise)))
        std = (var * s2[:, None]).sqrt()
        std = torch.where(observed[:, None], std, torch.full_like(std, math.inf))
    return std, observed


def finalize(model: Model, layout: Layout, obs: Observations, theta: Tensor, groups, *, loss: str, delta: float,
              observable_std, noise, history: list[float], iterations: int, t0: float, solver: str,
              info: dict, sampling: str = "nearest", keep_unobservable: bool = False, footprints=None) -> FitResult:
    """Posterior std, observability, pull-push filling → :class:`FitResult`.

    ``keep_unobservable``: the values of observed but unobservable texels are estimates worth keeping
    (reflectance sharing gave them their material's parameters), so only unobserved texels are filled;
    they stay flagged in ``unobservable``. Otherwise (a per-texel fit, where such values are arbitrary)
    they are replaced by pull-push fills of the observable ones. Measured on the default scene: the
    exported maps' RMSE on observed texels is 0.185 / 0.248 / 0.143 (albedo / f0 / roughness) with the
    fill and 0.017 / 0.021 / 0.056 keeping the shared values (10 candidates)."""
    H, W = obs.map_size
    t_post = time.perf_counter()
    theta = theta.to(ACC)
    params_acc = layout.unpack(theta)
    canon = torch.cat([params_acc[s.name] for s in layout.specs], -1)
    std, observed, _ = posterior_std(model, layout, obs, canon, groups, loss=loss, delta=delta, noise=noise,
                                     sampling=sampling, footprints=footprints)
    resolved = None
    if footprints is not None:
        # through the footprint operator the block std holds the neighbours fixed: a texel every pixel mixes
        # with its neighbours is not determined by the data alone, however small that std
        resolved = pixel_operator(footprints, H * W).dominance() >= RESOLVED_SHARE
        info["resolved_fraction"] = float(resolved[observed].float().mean()) if bool(observed.any()) else 0.0
    info["posterior_s"] = time.perf_counter() - t_post
    params = layout.unpack(theta.detach().to(obs.dtype))
    maps, unobs, filled, conf, ratio = {}, {}, {}, {}, {}
    obs_hw = observed.reshape(H, W)
    for s, o in zip(layout.specs, layout.offsets, strict=True):
        sl = slice(o, o + s.channels)
        thr = std_threshold(s, observable_std)
        sp = std[:, sl].amax(-1) / thr
        bad = observed & ~(sp < 1.0)
        if resolved is not None:
            bad = bad | (observed & ~resolved)
        val = params[s.name].reshape(H, W, s.channels)
        known = (observed if keep_unobservable else observed & ~bad).reshape(H, W)
        fill_val = pull_push(val, known) if bool(known.any()) else s.full((H, W), device=val.device, dtype=val.dtype)
        maps[s.name] = torch.where(known[..., None], val, fill_val)
        unobs[s.name] = bad.reshape(H, W)
        filled[s.name] = ~known
        c = std[:, sl].clamp_max(1e6).reshape(H, W, s.channels).to(obs.dtype).clone()
        c[~obs_hw] = float("nan")
        conf[s.name] = c
        ratio[s.name] = torch.where(obs_hw, sp.reshape(H, W), torch.full_like(sp.reshape(H, W), float("nan")))
    info["observable_fraction"] = {k: (1.0 - float(v[obs_hw].float().mean())) if bool(obs_hw.any()) else 0.0
                                   for k, v in unobs.items()}
    return FitResult(maps=maps, observed=obs_hw, unobservable=unobs, filled=filled, confidence=conf,
                     sensitivity=ratio, history=history, iterations=iterations, time_s=time.perf_counter() - t0,
                     solver=solver, info=info,
                     raw={k: v.reshape(H, W, -1) for k, v in params.items()})


#: A texel is *resolved* by the photos when some kept pixel takes at least this share of its value from it. A
#: texel covering exactly one pixel, centred, has the share (∫ over the pixel of its bilinear tent)² = 0.75² = 0.56;
#: below 0.5 every pixel that reads it mixes it with neighbours at least as much, and the data alone do not tell it
#: from them — its value is the prior's (neighbours, material), flagged unobservable.
RESOLVED_SHARE = 0.5


#: The reflectance sharing's anchors — texels whose own photos determine every shared parameter — are its seeds. When
#: fewer than ``ANCHOR_MIN_FRACTION`` of the observed texels qualify at the observability thresholds, the thresholds are
#: multiplied by the next factor of ``ANCHOR_LOOSENING`` until enough do: the material refit then fits each material on
#: all its texels' photos, so roughly determined seeds are refined, while 37 or 5 seeds leave whole materials without
#: one. Measured (2 threads, cached observations; all observed / determined at the truth, albedo / f0 / roughness [/
#: absorption]): shot noise 3 000 e⁻ (37 anchors of 46 264 → 4 760 at × 10) 0.0241 / 0.1380 / 0.1520 → 0.0216 / 0.0881
#: / 0.1165, determined 0.0045 / 0.0098 / 0.0126 → 0.0044 / 0.0091 / 0.0101; the layered 128-px scene (5 of 3 218 → 38
#: at × 10) 0.167 / 0.202 / 0.175 / 0.474 → 0.140 / 0.144 / 0.220 / 0.492, determined 0.149 / 0.105 / 0.078 / 0.153 →
#: 0.024 / 0.035 / 0.074 / 0.163. The default scene (7 % anchors), its fixed-light rig (12 %), 2 and 3 materials (1.5 %,
#: 4 %) are unchanged. Loosening there too (× 3) cost the default scene f0 0.0131 → 0.0160 and roughness 0.0489 →
#: 0.0587.
ANCHOR_MIN_FRACTION = 0.01
ANCHOR_LOOSENING = (1.0, 3.0, 10.0)


def determined(layout: Layout, std: Tensor, observed: Tensor, observable_std=None,
               factor: float = 1.0) -> dict[str, Tensor]:
    """Per parameter ``[T]`` bool: the ``observed`` texels whose marginal posterior std (``std [T, P]``,
    :func:`posterior_std`) is below ``factor`` × the parameter's observability threshold in every channel."""
    return {s_.name: observed & (std[:, o:o + s_.channels].amax(-1) < factor * std_threshold(s_, observable_std))
            for s_, o in zip(layout.specs, layout.offsets, strict=True)}


def find_anchors(layout: Layout, std: Tensor, observed: Tensor, names: Sequence[str],
             observable_std) -> tuple[Tensor, float, bool]:
    """``([T] bool anchors, factor, scarce)``: the observed texels whose posterior std (``std [T, P]``) is below
    ``factor`` × the observability threshold for every parameter in ``names``, with the smallest factor of
    :data:`ANCHOR_LOOSENING` that gives at least :data:`ANCHOR_MIN_FRACTION` of the observed texels (the largest
    otherwise, ``scarce`` True). All observed texels when ``names`` is empty."""
    if not names:
        return observed, 1.0, False
    need = ANCHOR_MIN_FRACTION * int(observed.sum())
    for factor in ANCHOR_LOOSENING:
        anchors = anchors_at(layout, std, observed, names, observable_std, factor)
        if int(anchors.sum()) >= need:
            return anchors, factor, False
    return anchors, factor, True


def anchors_at(layout: Layout, std: Tensor, observed: Tensor, names: Sequence[str], observable_std,
                factor: float) -> Tensor:
    """``[T]`` bool: the observed texels that determine every parameter in ``names`` at ``factor`` × the thresholds."""
    good = determined(layout, std, observed, observable_std, factor)
    return torch.stack([good[n] for n in names]).all(0)


def block_index(H: int, W: int, block: int, device) -> Tensor:
    """``[H·W]`` index of the ``block × block`` tile each texel of an ``H × W`` map lies in (row-major tiles)."""
    i = torch.arange(H, device=device)[:, None] // block
    j = torch.arange(W, device=device)[None, :] // block
    return (i * ((W + block - 1) // block) + j).reshape(-1)


#: Side in texels of the tiles of :func:`tile_seeds`.
SEED_BLOCK = 4
#: Largest spread of a tile's per-texel estimates (1.4826 × their median absolute deviation), in units of their median
#: posterior std, for :func:`tile_seeds` to count them as one material seen through noise: twice what noise alone
#: gives. Estimates that scatter more than their posterior says are not trusted (a misfit, a model the texels do not
#: follow); a tile across a border seeds the material most of its texels have (median and MAD ignore the rest).
SEED_SPREAD = 2.0


def tile_seeds(layout: Layout, canon: Tensor, std: Tensor, observed: Tensor, anchors: Tensor, names: Sequence[str],
               map_size: tuple[int, int], observable_std=None, block: int = SEED_BLOCK, factor: float = 1.0) -> Tensor:
    """Material seeds where no texel is an anchor but a tile of texels agrees: ``[N, C]`` canonical values of the
    columns of ``names`` (in that order), one per tile of the ``map_size = (H, W)`` grid that qualifies.

    A rough material's lobe, seen off its peak, leaves each texel's f0 and roughness too uncertain to be an anchor
    (:func:`find_anchors`), while many texels of it, estimated independently, scatter around the truth. For each
    ``block × block`` tile of observed non-anchor texels (at least half of it) the median of their estimates
    (``canon [T, P]``) is a seed when it is determined — its standard error, 1.2533 × the median posterior std
    (``std [T, P]``) / √n, below the parameter's observability threshold in every column — and the texels agree —
    their spread (1.4826 × MAD) at most :data:`SEED_SPREAD` × that median std. The seeds join the anchors as points
    of the reflectance sharing's clustering only (:func:`capture.fit.sharing.share_materials` ``seeds``); no texel
    keeps its own fit because of them. ``factor``: the anchors' loosening (:func:`find_anchors`), which multiplies
    the thresholds here too.

    Measured (docs/log.md, "tile seeds"): on the 256² Mitsuba sphere 191 seeds gave its rough green dielectric (2
    anchors in 3 469 texels) a material of its own, visible-highlight albedo / f0 / α 0.0097 / 0.0174 / 0.132 →
    0.0059 / 0.0091 / 0.016; the demo scene with 3 000 e⁻ shot noise (anchors at × 10): 365 seeds, all-observed f0
    0.088 → 0.076, well-lit f0 0.047 → 0.048."""
    H, W = map_size
    if isinstance(block, bool) or not isinstance(block, int) or block < 1 or not (factor > 0 and math.isfinite(factor)):
        raise SolverError(f"tile_seeds: block must be an integer ≥ 1 and factor a finite number > 0, got {block!r}, "
                          f"{factor!r}")
    if canon.dim() != 2 or std.shape != canon.shape or canon.shape[0] != H * W or canon.shape[1] != layout.P:
        raise SolverError(f"tile_seeds: canon and std must both be [H·W, P] = [{H * W}, {layout.P}], got "
                          f"{tuple(canon.shape)} and {tuple(std.shape)}")
    cols = [c for n in names for c in layout.cols(n)]
    spec = {s_.name: s_ for s_ in layout.specs}
    thr = factor * torch.tensor([std_threshold(spec[n], observable_std) for n in names
                                 for _ in range(spec[n].channels)], dtype=canon.dtype, device=canon.device)
    if not cols:
        return canon.new_zeros(0, 0)
    b = block
    tile = block_index(H, W, b, canon.device)
    slot = ((torch.arange(H, device=canon.device)[:, None] % b) * b
            + torch.arange(W, device=canon.device)[None, :] % b).reshape(-1)
    n_tiles = int(tile.max()) + 1
    x, sd = canon[:, cols], std[:, cols]
    use = (observed.reshape(-1).bool() & ~anchors.reshape(-1) & torch.isfinite(sd).all(-1)
           & torch.isfinite(x).all(-1))
    xs = torch.full((n_tiles, b * b, len(cols)), float("nan"), dtype=canon.dtype, device=canon.device)
    ss = xs.clone()
    xs[tile[use], slot[use]] = x[use]
    ss[tile[use], slot[use]] = sd[use]
    n = (~torch.isnan(xs[..., 0])).sum(1)
    med = xs.nanmedian(1).values
    spread = 1.4826 * (xs - med[:, None]).abs().nanmedian(1).values
    sigma = ss.nanmedian(1).values
    se = 1.2533 * sigma / n.clamp_min(1).sqrt()[:, None]
    ok = (2 * n >= b * b) & (se < thr).all(-1) & (spread <= SEED_SPREAD * sigma).all(-1)
    return med[ok]
