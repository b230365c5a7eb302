"""Neighbour proposals for texels the footprint steps leave unexplained (:func:`neighbour_proposals`).

At a border between two very different materials (a metal beside a dielectric) the texels on either side can settle
in a compromise — the metal's f0 lowered and its roughness raised, the dielectric's roughness raised — that the
Gauss-Newton steps do not leave: every small step from it raises the cost, though the photos determine those texels.
On 8 × 1024² photos of 256² maps (`shadecap synth --views 8 --size 1024 --tex 256`) the 60 texels of the fit with
the highest misfit, all on one such border, carried 88 % of the footprint χ² (0.535); set to the truth, χ² fell to
0.066 (docs/log.md, "texels stuck at material borders"). A discrete move reaches what the steps cannot: each such
texel tries the values of its neighbours, and keeps the one that explains the pixels reading it best.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from materials.model import Model

from .layout import ACC, Layout, SolverError
from .noise import robust_rho, scaled_sigma
from .operators import PixelOperator, pixel_operator

__all__ = ["PROPOSAL_CHI2", "PROPOSAL_OFFSETS", "neighbour_proposals"]

#: A texel is a candidate when the pixels reading it (weighted by their share of it) are misfit by more than this χ²
#: per residual under the photos' noise. Noise-free fits sit near 0.002 (the median texel of the 1024 → 256 scene);
#: the border texels above read 30–1 600; 10 keeps the 380 texels that carry 92 % of that fit's χ².
PROPOSAL_CHI2 = 10.0
#: Where a candidate takes its proposals from: the 4-neighbours and the texels two away in the same directions (at a
#: border both sides are compromised, so the nearest neighbour across it holds a compromise too).
PROPOSAL_OFFSETS = ((0, 1), (0, -1), (1, 0), (-1, 0), (0, 2), (0, -2), (2, 0), (-2, 0))
#: Candidates are changed together when they lie this many texels apart in both directions (classes of ``(row mod
#: k, column mod k)``), so that a pixel rarely reads two of them at once; the classes run one after another.
CLASS_SPACING = 3
#: A move is kept only when it takes at least this fraction off the cost of the pixels reading the texel: the
#: neighbour prior is not priced, and a small gain in the data can be a loss in the prior that the steps after undo.
MIN_GAIN = 0.2
#: The first pass moves a candidate to the values of a texel whose pixels are misfit by at most this χ² per residual
#: (explained to the noise) ...
EXPLAINED_CHI2 = 1.0
#: ... found within this many texels in one of the four directions.
WALK = 8


def _pixel_chi2(y: Tensor, pred: Tensor, sigma: Tensor) -> Tensor:
    """``[R]`` χ² of each pixel, summed over its channels."""
    return ((pred - y) / sigma).square().sum(-1)


def _texel_means(op: PixelOperator, per_pixel: Tensor) -> tuple[Tensor, Tensor]:
    """``(Σ_p a_pt x_p, Σ_p a_pt)`` over the pixels p reading each texel t, ``a_pt`` its share of the pixel."""
    w = op.e_share
    num = op.texel_sum(w * per_pixel[op.e_pix.long()])
    return num, op.texel_sum(w)


def _shifted(rows: Tensor, cols: Tensor, d_row: int, d_col: int, H: int, W: int) -> tuple[Tensor, Tensor]:
    """``(inside, index)``: whether the texels at ``(rows + d_row, cols + d_col)`` lie on the ``H × W`` map, and their
    flat indices (clamped to the map where they do not)."""
    r2, c2 = rows + d_row, cols + d_col
    inside = (r2 >= 0) & (r2 < H) & (c2 >= 0) & (c2 < W)
    return inside, r2.clamp(0, H - 1) * W + c2.clamp(0, W - 1)


def neighbour_proposals(model: Model, layout: Layout, theta: Tensor, op: PixelOperator, map_size: tuple[int, int], *,
                        loss: str, delta: float, noise, noise_ratio: float | None,
                        threshold: float = PROPOSAL_CHI2) -> tuple[Tensor, dict]:
    """Texels whose pixels the maps θ ``[T, P]`` leave unexplained take a neighbour's values where that explains them
    better: ``(theta, info)``.

    Candidates: texels whose pixels, weighted by their share of the texel, have a mean χ² per residual above
    ``threshold`` (σ: the noise model ``noise`` times √max(1, ``noise_ratio``), as the report's χ²). Two passes, each
    priced on the pixels that read some candidate only (their own :class:`PixelOperator`), by the data cost (the fit's
    ``loss``) of the pixels reading each moved texel:

    1. all candidates at once take the values of the nearest explained texel (:data:`EXPLAINED_CHI2`) within
       :data:`WALK` texels in one of the four directions, the one closest to their own values — the move that takes
       both sides of a compromised border back to their own materials together;
    2. class by class (:data:`CLASS_SPACING`), the candidates try the θ of the texels at :data:`PROPOSAL_OFFSETS`,
       all the class's members one offset at a time, each keeping its best.

    A move is kept where it takes at least :data:`MIN_GAIN` off the cost of the pixels reading the texel. At the end
    the whole data cost is priced once more, and every move is undone if it did not fall (pixels reading two moved
    texels make the local prices approximate). The neighbour prior is not priced.
    """
    t0 = time.perf_counter()
    H, W = map_size
    T = H * W
    if T != op.T or theta.shape != (T, layout.P):
        raise SolverError(f"neighbour_proposals: θ must be [{op.T}, {layout.P}] on maps of the operator's {op.T} "
                          f"texels, got θ {tuple(theta.shape)} and map_size {tuple(map_size)}")
    if not (threshold > 0 and math.isfinite(threshold)):
        raise SolverError(f"threshold must be a positive χ² per residual, got {threshold!r}")
    info = {"candidates": 0, "moved": 0, "seconds": 0.0}
    with torch.no_grad():
        y = op.y
        sigma = scaled_sigma(y, noise, noise_ratio)
        pred = op.predict(model, layout, layout.canonical(theta))
        num, den = _texel_means(op, _pixel_chi2(y, pred, sigma))
        seen = den > 0
        cand = seen & (num > threshold * 3.0 * den)
        n_cand = int(cand.sum())
        info["candidates"] = n_cand
        if n_cand == 0:
            info["seconds"] = time.perf_counter() - t0
            return theta, info
        before = float(robust_rho(y - pred, loss, delta).sum())
        # the pixels that read a candidate, and their own operator
        reads = cand[op.e_tex.long()] & (op.e_share > 0)
        keep = torch.zeros(op.R, dtype=torch.bool, device=y.device)
        keep[op.e_pix.long()[reads]] = True
        sub = pixel_operator(op.fp.select(keep), T)
        e_pix, e_tex = sub.e_pix.long(), sub.e_tex.long()
        rows = torch.arange(T, device=y.device) // W
        cols = torch.arange(T, device=y.device) % W
        new = theta.clone()

        def local_cost(th: Tensor) -> Tensor:
            r = sub.y - sub.predict(model, layout, layout.canonical(th))
            return robust_rho(r, loss, delta).sum(-1)

        def prices(change: Tensor, members: Tensor) -> Tensor:
            """``[T]`` each member's price: the cost change ``change [R_sub]`` of the pixels reading it."""
            on = members[e_tex]
            return torch.zeros(T, dtype=ACC, device=y.device).index_add_(0, e_tex[on], change[e_pix[on]])

        cur = local_cost(new)
        moved = 0
        # first all candidates at once, each taking the values of the nearest texel whose pixels are explained
        # (EXPLAINED_CHI2) in one of the four directions (up to WALK texels away) — the one whose values are closest
        # to its own: at a border the compromise spans a few texels on either side (the metal's f0 lowered, the
        # dielectric's roughness raised), some of them below the candidates' threshold, and the candidates leave it
        # only together, each towards its own side
        canon = layout.canonical(new)
        idx = torch.nonzero(cand).reshape(-1)
        best_src = idx.clone()
        best_d = torch.full((idx.numel(),), math.inf, dtype=canon.dtype, device=y.device)
        for dr, dc in PROPOSAL_OFFSETS[:4]:
            found = torch.full_like(idx, -1)
            for step in range(1, WALK + 1):
                ok, src = _shifted(rows[idx], cols[idx], step * dr, step * dc, H, W)
                hit = ok & (found < 0) & seen[src] & (num[src] <= EXPLAINED_CHI2 * 3.0 * den[src])
                found = torch.where(hit, src, found)
            has = found >= 0
            dist = (canon[found.clamp_min(0)] - canon[idx]).square().sum(-1)
            better = has & (dist < best_d)
            best_src, best_d = torch.where(better, found, best_src), torch.where(better, dist, best_d)
        trial = new.clone()
        trial[idx] = new[best_src]
        gain = prices(local_cost(trial) - cur, cand)[idx]
        take = (gain < -MIN_GAIN * prices(cur, cand)[idx]) & (best_src != idx)
        if bool(take.any()):
            new[idx[take]] = trial[idx[take]]
            moved += int(take.sum())
            cur = local_cost(new)
        k = CLASS_SPACING
        for cls in range(k * k):
            members = cand & (rows % k == cls // k) & (cols % k == cls % k)
            idx = torch.nonzero(members).reshape(-1)
            if idx.numel() == 0:
                continue
            best_gain = torch.zeros(idx.numel(), dtype=ACC, device=y.device)
            own = prices(cur, members)[idx]                 # the cost of the pixels reading each member
            best_src = torch.full((idx.numel(),), -1, dtype=torch.long, device=y.device)
            for dr, dc in PROPOSAL_OFFSETS:
                ok, src = _shifted(rows[idx], cols[idx], dr, dc, H, W)
                ok &= seen[src]
                if not bool(ok.any()):
                    continue
                trial = new.clone()
                trial[idx[ok]] = new[src[ok]]
                price = prices(local_cost(trial) - cur, members)[idx]
                better = ok & (price < best_gain) & (price < -MIN_GAIN * own)
                best_gain = torch.where(better, price, best_gain)
                best_src = torch.where(better, src, best_src)
            take = best_src >= 0
            if bool(take.any()):
                new[idx[take]] = new[best_src[take]]
                moved += int(take.sum())
                cur = local_cost(new)
        info["moved"] = moved
        if moved:
            after = float(robust_rho(y - op.predict(model, layout, layout.canonical(new)), loss, delta).sum())
            info.update(cost_before=before, cost_after=after)
            if after < before:
                theta = new
            else:
                info["moved"] = 0
        info["seconds"] = time.perf_counter() - t0
    return theta, info
