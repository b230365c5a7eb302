"""The joint refinement over all texels at once (:func:`refine_joint`) with its edge-preserving neighbour prior
(:class:`_SharingPrior`): the bilinear sampling footprint, or the photos' pixel footprints."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from materials.model import Model
from materials.params import CANONICAL
from renderer.device import HandedOutArrays, block_size, kept_array

from ..observations import Observations
from .layout import ACC, INVERSE_BLOCK, MAX_STEP, Layout, SolverError
from .noise import NOISE, irls_weights, noise_sigma, photo_noise_ratio, robust_rho
from .observability import std_threshold
from .operators import CsrPattern, csr_matrix, csr_rows, pixel_operator, sampled_blocks, sampling_operator
from .sharing import shared_default
from .texel import JACOBIAN_BLOCK, jacobian, weighted_cost

__all__ = ["PRIOR_UNIT", "JOINT_ATTEMPTS", "refine_joint"]


#: Units of the joint refinement's edge-preserving prior where they differ from the observability thresholds
#: (:func:`std_threshold`): each parameter's ``ParamSpec.prior_unit`` (materials/params.py, with the measurement
#: that chose the albedo's).
PRIOR_UNIT = {p.name: p.prior_unit for p in CANONICAL.values() if p.prior_unit is not None}
#: Texels per band of the neighbour prior's energy and weights (whole grid rows) and of its matrix's pattern
#: (:class:`_SharingPrior`), on the CPU (:func:`renderer.device.block_size`: larger on a GPU): 3.7 MB per ``[n, 7]``
#: float64 temporary, which stays in the cache and is not a fresh mapping at each call.
PRIOR_BAND = 2 ** 16


class _SharingPrior:
    """Edge-preserving prior that lets neighbouring texels share parameters (see :func:`refine_joint`).

    Energy ``μ Σ_edges Σ_c ρ_H((p_ic − p_jc) / t_c)`` over the edges (i, j): 4-neighbour pairs of observed
    texels, and *bridges* — observed texels two apart along a row or column with an unobserved one between them —,
    ``p`` the canonical values of the shared parameters' channels, ``t_c`` their units — the
    observability thresholds (:func:`std_threshold`), or :data:`PRIOR_UNIT` where it gives one — and ρ_H the
    Huber cost of :func:`robust_rho` with scale δ: quadratic — smoothing — for differences below δ units
    (smooth gradients of a material), linear beyond (region borders keep their jump). Gauss-Newton enters it
    through IRLS weights.

    Optionally (:meth:`set_anchor`) a second, unary term ``ν Σ_i Σ_c ρ_H((p_ic − m_ic) / t_c)`` ties the
    material parameters to a proposal ``m`` (the sharing's materials): see ``anchor_weight`` of
    :func:`refine_joint`.

    The texels form the ``H × W`` grid of the maps, so the differences are taken on that grid by slicing
    (measured on the default scene, 65 536 texels, 7 channels, 2 threads: 4.7 ms per product against 16 ms with
    index lists of the 101 122 edges).
    """

    def __init__(self, layout: Layout, names: Sequence[str], H: int, W: int, observed: Tensor, delta: float):
        self.cols = [c for n in names for c in layout.cols(n)]
        self.every_column = self.cols == list(range(layout.P))
        self.P = layout.P
        # the columns whose data curvature sets μ (refine_joint): those of the material parameters when the
        # prior has any. The albedo's curvature is larger (a texel's colour is seen wherever the texel is), and
        # calibrating on it too raised μ for every parameter (default scene, albedo in units of 0.01: f0 0.0171
        # against 0.0161)
        material = set(shared_default(layout))
        col_names = [n for n in names for _ in layout.cols(n)]
        self.calibrate = [i for i, n in enumerate(col_names) if n in material] or list(range(len(col_names)))
        dev = observed.device
        spec = {s.name: s for s in layout.specs}
        self.col_names = col_names
        self.thr = torch.tensor([PRIOR_UNIT.get(n, std_threshold(spec[n])) for n in col_names], dtype=ACC, device=dev)
        ok = observed.reshape(H, W)
        self.H, self.W = H, W
        # 1 on the edges between two observed texels: along u (row-wise) [H, W−1, 1] and along v [H−1, W, 1]
        self.edge_u = (ok[:, :-1] & ok[:, 1:]).to(ACC)[..., None]
        self.edge_v = (ok[:-1] & ok[1:]).to(ACC)[..., None]
        # bridges: observed texels two apart along a row or column with an unobserved one between them, as flat
        # index pairs [B] (few: 1 212 on the default scene, against 101 122 edges). Near a UV sphere's poles texels
        # are narrower than a pixel and some are read by no sample; without the bridges such a texel cut the chain
        # and its observed neighbour was tied to one side only (default scene, docs/log.md "bridges
        # across unobserved texels": all-texel albedo 0.0088 → 0.0062)
        flat = torch.arange(H * W, device=dev).reshape(H, W)
        row = ok[:, :-2] & ~ok[:, 1:-1] & ok[:, 2:]
        col = ok[:-2] & ~ok[1:-1] & ok[2:]
        self.bridge_i = torch.cat([flat[:, :-2][row], flat[:-2][col]])
        self.bridge_j = torch.cat([flat[:, 2:][row], flat[2:][col]])
        # the pairs that count — edges along u, along v, then the bridges — as flat texel indices: the sparse
        # matrices of the product hold only them (:meth:`_laplacian`), their weights picked from the grid's
        # by the edges' places (``_at_u``, ``_at_v``)
        self._at_u = torch.nonzero(self.edge_u.reshape(-1) > 0).reshape(-1)
        self._at_v = torch.nonzero(self.edge_v.reshape(-1) > 0).reshape(-1)
        self.pair_i = torch.cat([flat[:, :-1].reshape(-1)[self._at_u], flat[:-1].reshape(-1)[self._at_v],
                                 self.bridge_i])
        self.pair_j = torch.cat([flat[:, 1:].reshape(-1)[self._at_u], flat[1:].reshape(-1)[self._at_v],
                                 self.bridge_j])
        self._pattern = None
        self.lap = None
        self.delta = float(delta)
        self.mu = 0.0
        self.target = None           # [T, C] canonical proposal of the unary term (set_anchor)
        self.anchored = None         # [C] 1 on the columns it ties
        self.anchor_weight = 0.0
        self.anchor_delta = 1.0
        self.nu = 0.0
        self._kept = {}              # matvec's kept working arrays

    def set_units(self, units: Mapping[str, float]) -> None:
        """Replace the units of the parameters in ``units`` (name → unit): the energy's at once, the product's at the
        next :meth:`linearise` (its matrix holds the units it was made with)."""
        for i, n in enumerate(self.col_names):
            if n in units:
                self.thr[i] = float(units[n])

    def set_anchor(self, names: Sequence[str], canon: Tensor, weight: float, delta: float) -> None:
        """Tie the prior's columns of the parameters ``names`` to their values in ``canon`` ``[T, P]`` (canonical):
        weight ``weight`` × the data-calibrated scale (ν = weight · μ / sharing, set by :func:`refine_joint`),
        Huber scale ``delta`` units."""
        self.target = self._columns(canon).clone()
        self.anchored = torch.tensor([float(n in set(names)) for n in self.col_names], dtype=ACC,
                                     device=canon.device)
        self.anchor_weight, self.anchor_delta = float(weight), float(delta)

    def _columns(self, x: Tensor) -> Tensor:
        return x if self.every_column else x[:, self.cols]

    def _full(self, x: Tensor) -> Tensor:
        if self.every_column:
            return x
        out = torch.zeros(x.shape[0], self.P, dtype=x.dtype, device=x.device)
        out[:, self.cols] = x
        return out

    def _band_rows(self, device: torch.device) -> int:
        """Grid rows per band of :meth:`energy_tensor` and :meth:`linearise` (:data:`PRIOR_BAND` texels)."""
        return max(1, block_size(PRIOR_BAND, device) // self.W)

    def _band(self, canon: Tensor, a: int, b: int) -> tuple[Tensor, Tensor, slice, slice]:
        """The differences in units of the grid rows ``a … b − 1`` of ``canon [T, P]``: ``(du, dv, top, bottom)`` —
        along u ``[b − a, W − 1, C]``; along v over the edges ``(r, r + 1)`` from the row before the band to the last
        that stays in the grid (the rows either side: the edges across the band's borders); and the slices of ``dv``
        whose edges have their upper texel in the band (``top``) and their lower one (``bottom``)."""
        H, W = self.H, self.W
        a0, b1 = max(a - 1, 0), min(b + 1, H)
        c = (self._columns(canon[a0 * W:b1 * W]) / self.thr).reshape(b1 - a0, W, -1)
        du = c[a - a0:b - a0, :-1] - c[a - a0:b - a0, 1:]
        return du, c[:-1] - c[1:], slice(a - a0, min(b, H - 1) - a0), slice(max(a, 1) - 1 - a0, b - 1 - a0)

    def energy_tensor(self, canon: Tensor) -> Tensor:
        """The prior's energy at ``canon`` ``[T, P]`` as a (differentiable) scalar tensor, summed a band of
        :data:`PRIOR_BAND` texels' rows at a time: whole, each trial's differences and their costs were a dozen
        fresh ``[T, C]`` arrays, new pages each above glibc's mmap ceiling (1024² maps: 0.36 s a call, in bands
        0.05 s)."""
        H, W = self.H, self.W
        rows = self._band_rows(canon.device)
        huber = self.delta
        anchored = self.target is not None and self.nu > 0
        e = torch.zeros((), dtype=canon.dtype, device=canon.device)
        for a in range(0, H, rows):
            b = min(a + rows, H)
            du, dv, top, _ = self._band(canon, a, b)
            e = e + self.mu * ((robust_rho(du, "huber", huber) * self.edge_u[a:b]).sum()
                               + (robust_rho(dv[top], "huber", huber) * self.edge_v[a:min(b, H - 1)]).sum())
            if anchored:
                da = (self._columns(canon[a * W:b * W]) - self.target[a * W:b * W]) / self.thr * self.anchored
                e = e + self.nu * robust_rho(da, "huber", self.anchor_delta).sum()
        if self.bridge_i.shape[0]:
            db = self._columns(canon[self.bridge_i]) / self.thr - self._columns(canon[self.bridge_j]) / self.thr
            e = e + self.mu * robust_rho(db, "huber", huber).sum()
        return e

    def energy(self, canon: Tensor) -> float:
        with torch.no_grad():
            return float(self.energy_tensor(canon))

    def linearise(self, canon: Tensor, dp: Tensor) -> tuple[Tensor, Tensor]:
        """IRLS weights at ``canon``; returns (descent gradient [T, P] in θ, preconditioner diagonal [T, P]), and makes
        the product's matrix (:meth:`_laplacian`).

        The edges are weighed a band of :data:`PRIOR_BAND` texels' rows at a time (with the rows either side, for the
        edges across the band's borders), each texel's sums taken in the order of a whole pass — its edge to the
        right, to the left, below, above, then the bridges and the anchor — so the gradient and diagonal are those of
        the whole grid's arrays to the last bit; whole, the differences, weights and their products were some twenty
        fresh ``[T, C]`` arrays (2048² maps: 235 MB each, new pages at every linearisation)."""
        H, W, T, C = self.H, self.W, canon.shape[0], len(self.cols)
        g = torch.zeros(T, C, dtype=canon.dtype, device=canon.device)
        deg = torch.zeros_like(g)
        G, D = g.view(H, W, C), deg.view(H, W, C)
        n_u = self._at_u.shape[0]
        wp = torch.empty(self.pair_i.shape[0], C, dtype=canon.dtype, device=canon.device)     # the edges' weights
        rows = self._band_rows(canon.device)
        for a in range(0, H, rows):
            b = min(a + rows, H)
            du, dv, top, bottom = self._band(canon, a, b)
            wu = self.mu * irls_weights(du, "huber", self.delta) * self.edge_u[a:b]
            fu = wu * du
            G[a:b, :-1] -= fu
            G[a:b, 1:] += fu
            D[a:b, :-1] += wu
            D[a:b, 1:] += wu
            wv = self.mu * irls_weights(dv, "huber", self.delta) * self.edge_v[max(a - 1, 0):min(b, H - 1)]
            fv = wv * dv
            G[a:min(b, H - 1)] -= fv[top]                                      # the band's texels above an edge
            D[a:min(b, H - 1)] += wv[top]
            G[max(a, 1):b] += fv[bottom]                                        # … and below one
            D[max(a, 1):b] += wv[bottom]
            lo, hi = (int(x) for x in torch.searchsorted(self._at_u, torch.tensor([a, b], device=canon.device)
                                                         * (W - 1)))
            wp[lo:hi] = wu.reshape(-1, C)[self._at_u[lo:hi] - a * (W - 1)]
            lo, hi = (int(x) for x in torch.searchsorted(self._at_v, torch.tensor([a, min(b, H - 1)],
                                                                                  device=canon.device) * W))
            wp[n_u + lo:n_u + hi] = wv[top].reshape(-1, C)[self._at_v[lo:hi] - a * W]
        if self.bridge_i.shape[0]:
            db = self._columns(canon[self.bridge_i]) / self.thr - self._columns(canon[self.bridge_j]) / self.thr
            wb = self.mu * irls_weights(db, "huber", self.delta)
            g.index_add_(0, self.bridge_i, -1.0 * (wb * db)).index_add_(0, self.bridge_j, wb * db)
            deg.index_add_(0, self.bridge_i, wb).index_add_(0, self.bridge_j, wb)
            wp[n_u + self._at_v.shape[0]:] = wb
        if self.target is not None and self.nu > 0:
            for a in range(0, T, rows * W):
                b = min(a + rows * W, T)
                da = (self._columns(canon[a:b]) - self.target[a:b]) / self.thr * self.anchored
                omega = self.nu * irls_weights(da, "huber", self.anchor_delta) * self.anchored
                g[a:b] -= omega * da
                deg[a:b] += omega
        scale = self._columns(dp) / self.thr
        self.lap = None                 # (the last linearisation's matrix freed before the new one is made)
        self.lap = self._laplacian(wp, deg, scale)
        return self._full(g * scale), self._full(deg * scale.square())

    def _laplacian(self, wp: Tensor, deg: Tensor, scale: Tensor) -> Tensor:
        """The prior's Gauss-Newton matrix in θ, ``S (Σ_edges w_c (e_i − e_j)(e_i − e_j)ᵀ + Ω) S`` for each column c
        (``S`` the θ-to-units scale ``scale [T, C]``, ``Ω`` the anchor's weights), from the edges' weights ``wp
        [edges, C]`` and ``deg [T, C]``, each texel's edge and anchor weights summed (the diagonal): one sparse CSR
        matrix, ``[T·C] × [T·P]``, whose row ``t·C + c`` is texel t's column c and whose columns are θ's entries
        texel by texel, so that a product reads θ's ``[T, P]`` array as it lies, writes ``[T, C]`` as it lies, and
        the scale is in the values. Its pattern is built once (:meth:`_lap_pattern`), its values placed by one
        gather. Measured on 1024² maps, 7 columns, 2 threads: 12 ms a product, against 40 ms for one ``T × T``
        matrix per column with an entry per edge end on the diagonal (6.2 non-zeros per texel) and the scale applied
        at each product, 34 ms for those with one diagonal entry per texel (3.6; the columns' strided copies and
        scaling were half of it), and 23 ms for one matrix whose rows take the columns one after the other (each
        column's sweep reads every cache line of θ, and the result is transposed). One ``T·C × T·C`` matrix sorted
        from every pair of the grid (an earlier form) took 5.8 s to build and peaked at 4.7 GB there."""
        T, C = deg.shape
        if self._pattern is None:
            self._pattern = self._lap_pattern(T, C)
        crow, col, src = self._pattern
        # every entry's value in the triplets' order (i → j, j → i, the diagonal), the scale of its row and of its
        # column in, then placed by one gather (the rows' scale repeated per entry instead took 2.6 s on 2048² maps)
        n_e = wp.shape[0]
        S = scale.contiguous()
        Si, Sj = torch.index_select(S, 0, self.pair_i), torch.index_select(S, 0, self.pair_j)
        z = torch.empty(2 * n_e + T, C, dtype=wp.dtype, device=wp.device)
        torch.mul(-wp, Si, out=z[:n_e]).mul_(Sj)
        torch.mul(-wp, Sj, out=z[n_e:2 * n_e]).mul_(Si)
        del Si, Sj
        torch.mul(deg, S, out=z[2 * n_e:]).mul_(S)
        vals = torch.index_select(z.view(-1), 0, src)
        del z
        return csr_matrix(crow, col, vals, (C * T, T * self.P))

    def _lap_pattern(self, T: int, C: int) -> tuple[Tensor, Tensor, Tensor]:
        """``(crow, col, src)`` of :meth:`_laplacian`'s matrix: its row pointers, its columns and, for each entry,
        where its value is among the triplets' values ``[2·edges + T, C]`` flattened. It is one column's ``T × T``
        pattern — the edges both ways and one diagonal entry per texel, sorted by row — repeated for each column,
        with the columns moved to θ's places (``t·P + column``): texel t's rows are its ``L_t`` entries once per
        column, made a band of texels at a time (:data:`PRIOR_BAND`) without a sort."""
        i, j = self.pair_i, self.pair_j
        dev = i.device
        d = torch.arange(T, device=dev)
        one = CsrPattern.of(torch.cat([i, j, d]), torch.cat([j, i, d]), (T, T))
        n = one.col.shape[0]
        itype = torch.int32 if max(C * n, T * self.P) < 2 ** 31 else torch.long
        crow1 = one.crow.long()
        lens = crow1[1:] - crow1[:-1]
        crow = torch.empty(T * C + 1, dtype=torch.long, device=dev)
        crow[:-1] = (C * crow1[:-1, None] + lens[:, None] * torch.arange(C, device=dev)).reshape(-1)
        crow[-1] = C * n
        # each entry of one: its triplet (i → j, j → i, then the diagonal), the row of its value in _laplacian
        q = one.order.long() if one.order is not None else torch.arange(n, device=dev)
        cols = torch.tensor(self.cols, dtype=torch.long, device=dev)
        src = torch.empty(C * n, dtype=itype, device=dev)
        col = torch.empty(C * n, dtype=itype, device=dev)
        band = block_size(PRIOR_BAND, dev)
        for a in range(0, T, band):
            b = min(a + band, T)
            L, start = lens[a:b], crow1[a:b]
            lo, hi = C * int(crow1[a]), C * int(crow1[b])
            first = C * (start - crow1[a])                  # where each texel's rows start, in the band's places
            t = torch.zeros(hi - lo, dtype=torch.long, device=dev)
            t[first[1:]] = 1
            t = t.cumsum_(0)                                # each place's texel (in the band; every texel has a row)
            r = torch.arange(hi - lo, device=dev) - first[t]                             # its place in the texel's rows
            Lt = L[t]
            c = torch.div(r, Lt, rounding_mode="floor")
            k = start[t] + r - c * Lt                                                   # its entry of one
            src[lo:hi] = q[k] * C + c
            col[lo:hi] = one.col[k].long() * self.P + cols[c]
        return crow.to(itype), col, src

    def matvec(self, v: Tensor, out: Tensor | None = None) -> Tensor:
        """The prior's Gauss-Newton product with ``v [T, P]`` in θ, at the weights and scale of the last
        :meth:`linearise`, into ``out [T, P]`` when given (as :meth:`_Normal.matvec`: no temporary of the size of
        ``v`` when the prior is on every column)."""
        T = v.shape[0]
        x = v.reshape(-1)
        if self.every_column:
            if out is None:
                out = torch.empty_like(v)
            torch.mv(self.lap, x, out=out.view(-1))
            return out
        acc = kept_array(self._kept, "acc", (T, len(self.cols)), v.dtype, v.device)
        torch.mv(self.lap, x, out=acc.view(-1))
        if out is None:
            return self._full(acc)                  # (a fresh [T, P] array: acc is kept)
        out.zero_()
        out[:, self.cols] = acc
        return out


#: Trial steps per outer iteration of :func:`refine_joint`, the damping λ growing ×4 after each rejected one
#: (from ≥ 1e-9 up to ≥ 1e-3·4¹¹ ≈ 4 000 × the diagonal). With 4 attempts a scene whose first step needed
#: λ ≈ 0.26 never moved: the small fixed-rig scene (96 px, 32² maps) kept the sharing's proposal, all-texel albedo /
#: f0 / roughness 0.078 / 0.082 / 0.255, worst view 29.8 dB; with 12 its 5th attempt is accepted and the refinement
#: goes on: 0.031 / 0.059 / 0.155, 63.9 dB. Scenes whose steps are accepted at once are unchanged.
JOINT_ATTEMPTS = 12
#: Largest trust-region radius of :func:`refine_joint` (θ units per component). It starts at :data:`MAX_STEP`, the
#: per-texel LM's fixed box, doubles after an accepted step the box cut and halves after a rejected one
#: (:func:`_damped_step`). With the box fixed at 1, 8–13 % of the components of every step of the Mitsuba sphere
#: were cut, and the steps converged slowly: on the GGX scenes (`shadecap reconstruct`, 2-core CPU) χ² per residual /
#: well-lit albedo, f0, α RMSE went, fixed box → radius from 1 up to 3: Mitsuba sphere 256² 0.68 → 0.41, 0.0175 /
#: 0.0273 / 0.1346 → 0.0171 / 0.0262 / 0.1323, visible highlights 0.0060 / 0.0093 / 0.0159 → 0.0056 / 0.0089 / 0.0155;
#: the small sphere 0.55 → 0.49, α 0.119 → 0.115; the default synthetic scene (8 × 8 jittered rays) 0.57 → 0.23,
#: 0.0134 / 0.0141 / 0.0590 → 0.0130 / 0.0136 / 0.0583; with 3 000 e⁻ shot noise 1.91 → 1.88, 0.0324 / 0.0481 /
#: 0.1678 → 0.0330 / 0.0488 / 0.1648; the same times within the machine's drift. Starting at 3 (or at 2 with 2 the
#: largest) lowered χ² as much (sphere 0.27, default scene 0.23) but lost α on the default scene (0.0612) and on the
#: sphere's visible highlights (0.0170); a box fixed at 10 diverged (χ² 132). docs/log.md, "the joint solves' trust
#: region".
TRUST_MAX = 3.0
#: Smallest radius: a streak of rejections halves it each time, and the damping λ, growing ×4 per rejection, is what
#: shortens the steps beyond that; the floor keeps a long streak from leaving the next steps a box too small to
#: regrow from in a few steps (×2 per cut step).
TRUST_MIN = 1.0 / 64


class _JointData:
    """The data term of :func:`refine_joint`: the photos' pixels through the pixel operator (``footprints``), or one
    sample per pixel centre reading the texels through the sampling operator (``sampling``): its cost, its
    linearisation, normal equations and matrix-free Gauss-Newton product."""

    def __init__(self, model: Model, obs: Observations, layout: Layout, groups, T: int, *, sampling: str, footprints,
                 loss: str, delta: float):
        if sampling == "bilinear":
            if obs.bilinear_index is None:
                raise SolverError("joint bilinear refinement needs observations built with bilinear=True")
            idx, bw = obs.bilinear_index, obs.bilinear_weight.to(ACC)
        else:
            idx, bw = obs.texel[:, None], torch.ones(obs.n_samples, 1, dtype=ACC, device=obs.device)
        self.model, self.obs, self.layout, self.groups, self.loss, self.delta = model, obs, layout, groups, loss, delta
        self.T, self.P = T, layout.P
        self.pix = pixel_operator(footprints, T) if footprints is not None else None
        self._kept = {}                 # matvec's kept per-sample or pixel-sized array (the cost's too)
        self._jac = HandedOutArrays()   # the pixel-centre linearisation's arrays, reused (_jacobian_arrays)
        self.y = self.pix.y if self.pix is not None else obs.radiance.to(ACC)
        self.n_res = float(3 * self.pix.R) if self.pix is not None else float(3 * obs.weight.to(ACC).sum())
        # the sampling operator as sparse CSR matrices (K non-zeros per row): per-sample values are
        # S_op @ x, the transpose scatters back. Measured on the default scene (204 000 samples, 65 536
        # texels, P = 7, 2 threads): 4.9 ms and 2.6 ms against 112 ms and 28 ms for gather + weighted sum
        # and K index_adds
        if self.pix is None:
            self.S_op, self.S_t = sampling_operator(idx, bw, T)
            self.idx, self.bw_sq = idx, bw.square()          # the normal equations' blocks (sampled_blocks)

    def gather(self, x: Tensor) -> Tensor:
        """``[T, P]`` → per-sample ``[S, P]``."""
        return self.S_op @ x

    def scatter(self, g: Tensor) -> Tensor:
        """Per-sample ``[S, P]`` → ``[T, P]``."""
        return self.S_t @ g

    def cost(self, th: Tensor) -> float:
        """The data cost of θ ``[T, P]``."""
        with torch.no_grad():
            canon = self.layout.canonical(th)
            if self.pix is not None:    # (the prediction, residual and l2 cost in the products' kept pixel array)
                pred = self.pix.predict(self.model, self.layout, canon,
                                        out=kept_array(self._kept, "pixels", (self.pix.R, 3), ACC, canon.device))
                r = torch.sub(self.y, pred, out=pred)
                return float(robust_rho(r, self.loss, self.delta, out=r).sum())
            pred = self.obs.predict(self.model, self.layout.split(self.gather(canon).to(self.obs.dtype)))
            return weighted_cost(self.obs, pred, self.loss, self.delta)

    def linearise(self, canon: Tensor) -> tuple[Tensor, Tensor]:
        """Residuals and Jacobian wrt the canonical parameters ``canon [T, P]`` (per sample, or a
        :class:`PixelJacobian`)."""
        if self.pix is not None:
            pred, J = self.pix.linearise(self.model, self.layout, canon, self.groups)       # J: a PixelJacobian
        else:
            pred, J = jacobian(self.model, self.layout, self.obs, self.gather(canon), self.groups, canonical=True,
                               out=self._jacobian_arrays(canon.device))
        return self.y - pred, J

    def _jacobian_arrays(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """``(pred [S, 3], J [S, 3, P])`` for a pixel-centre linearisation: the last one's arrays, overwritten in
        place, once nothing holds its Jacobian (:func:`refine_joint` frees each step's system before the next
        linearisation), else new ones. Fresh, ``J`` is new pages at every step (0.27 GB on the 1.6 M pixel centres
        of 32 × 512² photos)."""
        S = self.obs.n_samples
        pred, J = self._jac.arrays([("pred", (S, 3), ACC), ("J", (S, 3, self.P), ACC)], device)
        J = J.view(J.shape)             # (a tensor of its own, whose life says whether the Jacobian is held)
        self._jac.hand_out(J)
        return pred, J

    def normal(self, J, r: Tensor, dp: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """IRLS weights of the residuals ``r``, the descent gradient JᵀWr in θ ``[T, P]`` and the exact per-texel
        blocks ``[T, P, P]`` (canonical; the caller's own, which :meth:`_Normal.of` scales in place)."""
        if self.pix is not None:
            w = irls_weights(r, self.loss, self.delta)                                       # [R, 3]
            g, B = self.pix.normal(J, w, w * r)                                        # exact per-texel blocks
            return w, g * dp, B
        T = self.T
        w = self.obs.weight.to(ACC)[:, None] * irls_weights(r, self.loss, self.delta)      # [S, 3]
        g = self.scatter(torch.einsum("scp,sc->sp", J, w * r)) * dp                  # JᵀWr in θ
        B = sampled_blocks(J, w, self.idx, self.bw_sq, T)                     # Σ_s w_sk² J_sᵀWJ_s
        return w, g, B

    def matvec(self, v: Tensor, dp: Tensor, J, w: Tensor, out: Tensor | None = None) -> Tensor:
        """The data term's Gauss-Newton product with ``v [T, P]`` in θ, into ``out [T, P]`` when given."""
        if self.pix is not None:
            if out is None:
                return self.pix.apply_t(J, w * self.pix.apply(J, v * dp)) * dp
            # (out holds v·dp until J's product; the pixel-sized product in a kept array)
            y = self.pix.apply(J, torch.mul(v, dp, out=out),
                               out=kept_array(self._kept, "pixels", (self.pix.R, 3), v.dtype, v.device))
            return self.pix.apply_t(J, y.mul_(w), out=out).mul_(dp)
        # J_sᵀ W_s J_s u_s as two batched products (bmm: 5.4 ms against 9.4 ms for einsum, S = 204 000), a block of
        # samples at a time: the samples' reads and radiance changes whole were 0.13 GB of fresh pages per product
        # on 32 × 512² photos (1.6 M samples); only the result, which the scatter reads whole, is made whole
        x = v * dp if out is None else torch.mul(v, dp, out=out)      # (out holds v·dp until the scatter)
        S = J.shape[0]
        per = kept_array(self._kept, "per", (S, self.P), J.dtype, J.device)
        step = block_size(JACOBIAN_BLOCK, J.device)
        for a in range(0, S, step):
            b = min(a + step, S)
            u = csr_rows(self.S_op, a, b) @ x                                  # [n, P]
            ju = torch.bmm(J[a:b], u[:, :, None])[..., 0] * w[a:b]            # [n, 3]
            per[a:b] = torch.bmm(ju[:, None, :], J[a:b])[:, 0]
        if out is None:
            return self.scatter(per) * dp
        return torch.mm(self.S_t, per, out=out).mul_(dp)


def _prior_names(model: Model, layout: Layout, sharing: float, sharing_params: Sequence[str] | None) -> list[str]:
    """The parameters of :func:`refine_joint`'s neighbour prior (``sharing_params``, default: all), checked."""
    if not (sharing >= 0 and math.isfinite(sharing)):
        raise SolverError(f"sharing must be a finite weight ≥ 0, got {sharing!r}")
    names = list(sharing_params) if sharing_params is not None else [s_.name for s_ in layout.specs]
    unknown = [n for n in names if n not in {s.name for s in layout.specs}]
    if unknown:
        raise SolverError(f"sharing_params {unknown} are not parameters of model '{model.name}' "
                          f"({[s.name for s in layout.specs]})")
    return names


def _observed(data: _JointData, obs: Observations, sampling: str, theta: Tensor) -> Tensor:
    """``[T]`` bool: the texels the data term reads, those the neighbour prior links."""
    if data.pix is not None:
        return data.pix.observed()
    if sampling == "bilinear":
        return obs.footprint()
    observed = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    observed[obs.texel] = True
    return observed


def _adaptive_names(model: Model, layout: Layout, noise_adaptive: Sequence[str], names: Sequence[str]) -> list[str]:
    """The parameters of ``noise_adaptive`` (checked) that are in the prior's ``names``."""
    bad = [n for n in noise_adaptive if n not in {s_.name for s_ in layout.specs}]
    if bad:
        raise SolverError(f"noise_adaptive {bad} are not parameters of model '{model.name}' "
                          f"({[s_.name for s_ in layout.specs]})")
    return [n for n in noise_adaptive if n in names]


class _NoiseUnits:
    """The prior units that follow the photos' noise (``noise_adaptive`` of :func:`refine_joint`)."""

    def __init__(self, prior: _SharingPrior, names: Sequence[str], obs: Observations, noise):
        self.prior, self.names, self.noise = prior, list(names), noise
        self.base = {n: float(prior.thr[prior.col_names.index(n)]) for n in self.names}
        self.ratios: list[float] = []
        self.image_ratio = photo_noise_ratio(obs, noise)

    def update(self, r: Tensor, y: Tensor) -> None:
        """Shrink the units by the noise ratio of the residuals ``r`` of the radiance ``y``."""
        # the photos' noise against the noise model, from the residuals of the bilinear fit so far (at
        # it = 0 they still hold the sharing's misfit) and, where the observations carry image-space
        # residuals, at least the noise measured there; the adaptive units shrink with it
        ratio = max(self.image_ratio or 0.0, float((r / noise_sigma(y, self.noise)).square().mean(-1).median()))
        self.prior.set_units({n: self.base[n] / max(1.0, ratio) for n in self.names})
        self.ratios.append(ratio)

    def units(self) -> dict[str, float]:
        return {n: float(self.prior.thr[self.prior.col_names.index(n)]) for n in self.names}


def _calibrate(prior: _SharingPrior, B: Tensor, sharing: float) -> None:
    """Set the prior's μ (and the anchor's ν) from the data blocks ``B [T, P, P]`` (canonical)."""
    # μ in units of the data term: its curvature for a one-threshold change of a material
    # parameter in a typical (median) observed texel
    dc = torch.diagonal(B, dim1=-2, dim2=-1)[:, prior.cols] * prior.thr.square()
    ref = dc[dc.sum(-1) > 0]
    prior.mu = sharing * (float(ref[:, prior.calibrate].median(0).values.mean()) if ref.numel() else 0.0)
    prior.nu = prior.anchor_weight * prior.mu / sharing


@dataclass
class _Normal:
    """One linearisation of :func:`refine_joint`: the normal equations in θ, data + prior — gradient ``g [T, P]``,
    per-texel blocks ``B [T, P, P]`` (the preconditioner), damping diagonal ``diag [T, P]``, ``live`` texels — and
    their matrix-free product."""

    data: _JointData
    prior: _SharingPrior | None
    dp: Tensor
    J: object
    w: Tensor
    g: Tensor
    B: Tensor
    diag: Tensor
    live: Tensor
    kept: dict = field(default_factory=dict)        # the products' kept texel-sized arrays (matvec)

    @classmethod
    def of(cls, data: _JointData, prior: _SharingPrior | None, canon: Tensor, dp: Tensor, J, w: Tensor, g: Tensor,
           B: Tensor) -> _Normal:
        """From the data term's weights, gradient (θ) and blocks (canonical), adding the prior's."""
        if prior is not None:
            pg, pdiag = prior.linearise(canon, dp)
            g = g + pg
        # the data blocks (the caller's own) scaled in place: a fresh array per operation held two more beside them
        # at once (0.2 GB on 512² maps, 3.3 GB on 2048²), and one fresh array was still one more, whose new pages
        # cost 0.1–0.2 s a step on 512² maps; the same values to the last bit
        B.mul_(dp[:, :, None]).mul_(dp[:, None, :])
        diag = torch.diagonal(B, dim1=-2, dim2=-1).clone()
        if prior is not None:
            B.diagonal(dim1=-2, dim2=-1).add_(pdiag)
        live = diag.sum(-1) > 0
        diag = diag + 1e-9 * diag.mean(-1, keepdim=True).clamp_min(1e-30)
        return cls(data, prior, dp, J, w, g, B, diag, live)

    def matvec(self, v: Tensor, lam: float, out: Tensor | None = None) -> Tensor:
        """The damped product with ``v [T, P]``, into ``out [T, P]`` when given; identity on the texels that are not
        live. With ``out`` its texel-sized temporaries are the system's two kept arrays
        (:func:`renderer.device.kept_array`), the same values to the last bit."""
        if out is None:
            out = torch.empty_like(v)
        data = self.data.matvec(v, self.dp, self.J, self.w, out=kept_array(self.kept, "data", v.shape, v.dtype,
                                                                            v.device))
        if self.prior is not None:
            data.add_(self.prior.matvec(v, out=kept_array(self.kept, "prior", v.shape, v.dtype, v.device)))
        torch.mul(self.diag, lam, out=out).mul_(v).add_(data)
        return torch.where(self.live[:, None], out, v, out=out)


def _pcg(system: _Normal, lam: float, rhs: Tensor, Minv: Tensor, iterations: int,
         live: Tensor | None = None) -> Tensor:
    """Preconditioned conjugate gradients on ``system`` damped by ``lam`` from 0, with the per-texel block inverses
    ``Minv``: at most ``iterations`` products, stopped early on a non-positive curvature or a residual reduced by
    1e-20. ``Minv`` is ``[T, P, P]``, or, with ``live`` (the indices of the live texels), the live texels' blocks
    alone: the others' are the identity on a residual that stays 0 (their rows of the system are the identity and
    their right-hand side 0), so their preconditioned residual is 0 without reading a block."""
    # every vector updated in place and every product's temporary in a kept array (:func:`renderer.device.kept_array`:
    # fresh ones over glibc's mmap ceiling are new pages at each use), the same values to the last bit
    x = torch.zeros_like(rhs)
    res = rhs.clone()
    z, Ad, tmp = torch.zeros_like(rhs), torch.empty_like(rhs), torch.empty_like(rhs)
    if live is not None:
        res_l, z_l = (torch.empty(live.shape[0], rhs.shape[1], dtype=rhs.dtype, device=rhs.device) for _ in range(2))

    def precondition() -> None:
        if live is None:
            torch.bmm(Minv, res[:, :, None], out=z[:, :, None])
        else:
            torch.index_select(res, 0, live, out=res_l)
            torch.bmm(Minv, res_l[:, :, None], out=z_l[:, :, None])
            z.index_copy_(0, live, z_l)

    precondition()
    d = z.clone()
    rz = float(torch.mul(res, z, out=tmp).sum())
    rz0 = rz
    for _ in range(iterations):
        system.matvec(d, lam, out=Ad)
        dAd = float(torch.mul(d, Ad, out=tmp).sum())
        if not dAd > 0:
            break
        a = rz / dAd
        x.add_(torch.mul(d, a, out=tmp))
        res.sub_(torch.mul(Ad, a, out=tmp))
        precondition()
        rz_new = float(torch.mul(res, z, out=tmp).sum())
        if rz_new <= 1e-20 * rz0:
            break
        d.mul_(rz_new / rz).add_(z)
        rz = rz_new
    return x


def _live_blocks(live: Tensor, P: int) -> Tensor | None:
    """The indices of the live texels (``live [T]`` bool) when the preconditioner is to keep their ``P × P`` blocks
    alone, else None: where enough texels are not live (texels no pixel reads: 37 % of 2048² maps under 8 × 256²
    photos), a PCG iteration then reads no block of the T − L others and copies the L live texels' P residuals out
    and back, which pays when (T − L)·P² > 2·L·P."""
    L, T = int(live.sum()), live.shape[0]
    return torch.nonzero(live).reshape(-1) if L * (P + 2) < T * P else None


def _damped_step(system: _Normal, theta: Tensor, cost: float, lam: float, radius: float,
                 total_of: Callable[[Tensor], float], cg_iterations: int,
                 accepted: list[bool]) -> tuple[Tensor, float, float, float]:
    """Trial steps of one outer iteration of :func:`refine_joint` until one lowers the total cost: each solves the
    damped system (:func:`_pcg`) and clamps it to the trust region ``|Δθ_i| ≤ radius``; kept when it lowers the
    cost (λ / 3; the radius doubles, up to :data:`TRUST_MAX`, when the clamp cut some component); else, if the clamp
    cut the step, the step clamped to half the radius is tried (a cost evaluation, no solve), and when that fails too
    (or there was no cut) λ grows ×4 and the system is solved again within the halved radius. Appends each trial's
    outcome to ``accepted``; returns ``(theta, cost, lam, radius)``."""
    # up to JOINT_ATTEMPTS damping increases (×4 each) before the step is given up: after a failed outer
    # iteration the loop stops, so 4 attempts (λ ≤ 0.064) ended the refinement before its first step on the
    # small fixed-rig scene
    T = system.B.shape[0]
    eye = torch.eye(theta.shape[1], dtype=ACC, device=theta.device)
    step = block_size(INVERSE_BLOCK, theta.device)
    rhs = torch.where(system.live[:, None], system.g, torch.zeros_like(system.g))      # (the same for every trial)
    live = _live_blocks(system.live, system.B.shape[1])
    n = T if live is None else live.shape[0]
    for _attempt in range(JOINT_ATTEMPTS):
        Minv = torch.empty(n, *system.B.shape[1:], dtype=system.B.dtype, device=system.B.device)
        # the damped blocks made and inverted a run of texels at a time (each block's inverse is its own, so the
        # values are those of one batched inverse): whole, the damped copy was one more [T, P, P] array beside the
        # system's and the inverse (1.6 GB on 2048² maps), new pages at every trial
        for a in range(0, n, step):
            b = min(a + step, n)
            if live is None:            # (every texel's block, identities on those not live)
                M = system.B[a:b].clone()
                M.diagonal(dim1=-2, dim2=-1).add_(lam * system.diag[a:b])
                M[~system.live[a:b]] = eye
            else:
                M = system.B.index_select(0, live[a:b])
                M.diagonal(dim1=-2, dim2=-1).add_(lam * system.diag.index_select(0, live[a:b]))
            Minv[a:b] = torch.linalg.inv_ex(M)[0]
        x = _pcg(system, lam, rhs, Minv, cg_iterations, live)
        Minv = None                     # (not held while the trials are priced: the prior's energy needs the room)
        cut = bool((x.abs() > radius).any())
        for r in (radius, radius / 2):
            trial = theta + x.clamp(-r, r)
            new_cost = total_of(trial)
            accepted.append(new_cost < cost)
            if new_cost < cost:
                theta, cost = trial, new_cost
                lam = max(lam / 3, 1e-9)
                radius = min(2 * r, TRUST_MAX) if cut and r == radius else r
                return theta, cost, lam, radius
            if not cut:
                break
        lam *= 4
        radius = max(radius / 2, TRUST_MIN)
    return theta, cost, lam, radius


def refine_joint(model: Model, obs: Observations, layout: Layout, theta: Tensor, groups, *, loss: str, delta: float,
                 iterations: int = 4, cg_iterations: int = 25, sampling: str = "bilinear",
                 sharing: float = 0.0, sharing_params: Sequence[str] | None = None, sharing_delta: float = 0.3,
                 noise=NOISE, noise_adaptive: Sequence[str] = (), anchor_weight: float = 0.0,
                 anchor_delta: float = 1.0, footprints=None, anchor_target: Tensor | None = None,
                 progress: Callable[[str, int, float], None] | None = None) -> tuple[Tensor, dict]:
    """Levenberg-Marquardt over *all* texels at once with the true (bilinear) sampling footprint.

    ``footprints`` (:class:`capture.footprint.PixelFootprints`): the residuals are the photos' *pixels*, each the
    area average of its sub-pixel samples' radiance (:class:`PixelOperator`), instead of one sample per pixel
    centre; ``obs`` then only supplies the photos' measured noise for the noise-adaptive prior. Everything else —
    the prior, the damping, the PCG — is the same.

    With bilinear sampling a sample reads ``Σ_k w_sk p_k`` of four texels, so texels are coupled
    and the per-texel solve is only an approximation. Starting from it, each outer iteration
    linearises the full render (per-sample Jacobian ``J_s`` wrt canonical parameters, reverse-mode
    AD, stored once) and solves ``(JᵀWJ + λ·diag) δ = JᵀWr`` for all texels jointly by
    preconditioned conjugate gradients (matrix-free: a product gathers δ at the four texels,
    applies ``J_s``, ``J_sᵀW`` and scatters back with the weights; the preconditioner is the exact
    per-texel P×P block). A step is kept when it lowers the total cost, else λ grows ×4 and the
    step is re-solved. Variables are θ (the sigmoid/softplus parameterisation), with the same
    trust region |Δθ_i| ≤ radius per component, the radius adapted from :data:`MAX_STEP` (:func:`solve_fast`'s fixed
    box) up to :data:`TRUST_MAX` (:func:`_damped_step`).

    ``sharing > 0`` adds the edge-preserving prior of :class:`_SharingPrior` between 4-neighbour
    observed texels (and observed texels two apart with an unobserved one between them)
    on ``sharing_params`` (default: every parameter, the albedo included): Huber on the
    differences in units of the observability thresholds, quadratic below ``sharing_delta``, with
    weight μ = ``sharing`` × the median data curvature of a one-threshold change (so ``sharing`` is
    dimensionless). It enters the normal equations through IRLS weights, the matrix-free product and
    the preconditioner's diagonal, and the step acceptance compares data + prior. Measured on the
    default scene after :func:`capture.fit.sharing.share_materials` (2 outer iterations): RMSE on all
    observed texels albedo / f0 / roughness 0.026 / 0.031 / 0.079 without the prior, 0.017 / 0.024 /
    0.058 with μ = 1, δ = 1, 0.017 / 0.021 / 0.056 with δ = 0.3 (the default; 10 candidates); μ = 0.3 or 3 change
    them by < 0.003. The albedo is in the prior's default set (leaving it out — it varies per texel by design — was
    measured worse, below), in units of :data:`PRIOR_UNIT` (0.3): where the photos
    determine a texel's albedo the data win, where they barely do — texels read only through a neighbour's
    bilinear footprint, the grazing band — it follows its neighbours with the edges kept. μ is still calibrated
    on the material parameters (calibrating on the albedo's larger curvature too raised it for all: f0 0.0171
    instead of 0.0161). Measured, 3 outer iterations, RMSE on all observed texels albedo / f0 / roughness:
    default scene 0.0161 / 0.0159 / 0.0532 → 0.0089 / 0.0159 / 0.0531 (observable texels unchanged, 0.0005 /
    0.0017 / 0.0018); the same with 64² maps albedo 0.0084 → 0.0063; with shot noise (full well 3000 e⁻) 0.0549
    → 0.0425 (0.0264 with the noise-adaptive unit below); fixed-light rig 0.0193 → 0.0118; small scenes (6 views)
    of 96 px photos and 32² maps with shot noise 0.0596 → 0.0438 (0.0378 adaptive), of 64 px and 64² maps
    0.0668 → 0.0522 (0.0510), of 96 px and 32² maps noise-free 0.0191 → 0.0195 (0.0201; its checker squares are
    1.3 texels wide). In units of the albedo's observability threshold (0.01) the noisy scene gained more
    (0.0241) but fine textures lost (64² maps 0.0147, the 1.3-texel checker 0.0288).

    ``noise_adaptive`` names prior parameters whose unit follows the photos' noise (solve_fast: the albedo):
    from the second outer iteration on, unit = base unit / max(1, ratio), with ratio the median χ² per residual
    of the current bilinear fit under the noise model ``noise`` (:func:`noise_sigma`) — noisier photos, a
    stronger prior, in proportion to the noise variance as a prior's weight against χ²-weighted data would be.
    At the first iteration the residuals still hold the sharing's misfit, so the base unit is kept. Measured
    ratios (2nd, 3rd iteration): default scene 0.0018, 0.0003; fixed rig 0.011, 0.0045; 1.3-texel checker
    1.6, 0.047; shot noise 3 000 e⁻ 24.7, 18.9 (unit 0.016) and on the small scene 59.9, 40.1 (unit 0.0075).
    All-texel albedo with / without the adaptation: shot noise 0.0264 / 0.0425, small scene with shot noise
    0.0378 / 0.0438, 1.3-texel checker 0.0201 / 0.0195, noise-free scenes unchanged (ratio < 1). The
    ratio is at least the photos' noise measured in image space (:func:`photo_noise_ratio`) when the
    observations carry residuals: default scene with 3 000 e⁻ all-texel albedo 0.0212 → 0.0191, with 1 000 e⁻ sRGB
    0.0333 → 0.0303 (f0 and roughness within ±0.0002). Using it instead of the fit's ratio, from the first iteration
    on, changed the noise-free stress rows whose fit misfits (grazing 3°, black albedo: worse) and cost the 300 e⁻
    row 0.0605 → 0.0698; as a floor from the second iteration on only the noisy rows move (docs/stability.md).

    ``anchor_weight > 0`` (with ``sharing > 0``) adds a unary term to the prior that ties every texel's material
    parameters (all but the per-texel ones, i.e. f0 and roughness for GGX + Lambert) to their values in the
    starting ``theta`` — the sharing's proposal: ``ν Σ_i Σ_c ρ_H((p_ic − m_ic) / t_c)``, Huber scale
    ``anchor_delta`` units, ν = ``anchor_weight`` × the data-curvature scale of μ. Without it the neighbour prior
    alone ties a region to its material only through chains of neighbours, so where the photos leave a direction
    flat (f0 against roughness in a metal seen without a highlight) more steps let whole regions drift along it:
    default scene, 6 steps × 50 CG iterations, f0 0.0159 → 0.0326 (gold and the smooth dielectric away from the
    highlights). With it (``anchor_weight`` 0.03, solve_fast's default) the same steps give 0.0087 / 0.0139 /
    0.0510, and 6 × 30 — the default — 0.0088 / 0.0134 / 0.0515 against 0.0089 / 0.0159 / 0.0531 for 3 × 25
    without the anchor; docs/log.md, "the sharing's proposal as a prior", for the other scenes and weights.

    Returns:
        ``(theta [T, P], info)`` with the cost history, accepted steps and time.
    """
    t0 = time.perf_counter()
    if not (anchor_weight >= 0 and math.isfinite(anchor_weight) and anchor_delta > 0 and math.isfinite(anchor_delta)):
        raise SolverError(f"anchor_weight must be a finite weight ≥ 0 and anchor_delta a finite scale > 0, got "
                          f"{anchor_weight!r}, {anchor_delta!r}")
    data = _JointData(model, obs, layout, groups, theta.shape[0], sampling=sampling, footprints=footprints, loss=loss,
                      delta=delta)
    names = _prior_names(model, layout, sharing, sharing_params)
    prior = None
    if sharing > 0 and names:
        prior = _SharingPrior(layout, names, *obs.map_size, _observed(data, obs, sampling, theta), sharing_delta)
        if anchor_weight > 0:
            prior.set_anchor(shared_default(layout),
                             layout.canonical(theta) if anchor_target is None else anchor_target,
                             anchor_weight, anchor_delta)
    adapt = _adaptive_names(model, layout, noise_adaptive, names if prior is not None else [])
    units = _NoiseUnits(prior, adapt, obs, noise) if adapt else None

    # the data cost of the current θ is kept (``data_cost``): the units' update and the prior's calibration change
    # only the prior's energy, so re-pricing θ under them needs no new render of the photos (a data cost is a full
    # prediction: 0.13–0.2 s on the 256² Mitsuba sphere's footprints, twice per step before)
    trial_data = 0.0                    # the data cost of the last θ priced by total_of

    def prior_of(th):
        return prior.energy(layout.canonical(th)) if prior is not None else 0.0

    def total_of(th):
        nonlocal trial_data
        trial_data = data.cost(th)
        return trial_data + prior_of(th)

    lam, radius = 1e-3, MAX_STEP
    cost = total_of(theta)
    data_cost = trial_data
    history, accepted = [cost / data.n_res], []
    for it in range(iterations):
        with torch.no_grad():
            canon = layout.canonical(theta)
            dp = layout.dcanonical(theta)
            system = J = w = g = B = None   # the last step's system freed before the new linearisation
            r, J = data.linearise(canon)
            if units is not None and it >= 1:
                units.update(r, data.y)
                cost = data_cost + prior_of(theta)
            w, g, B = data.normal(J, r, dp)
            if prior is not None and it == 0:
                _calibrate(prior, B, sharing)
                cost = data_cost + prior_of(theta)
                history[0] = cost / data.n_res
            system = _Normal.of(data, prior, canon, dp, J, w, g, B)
            B = None                    # (the data blocks: the system holds its own, scaled, for the steps)
            # the step's gain is measured against the cost under this iteration's objective: the units' update
            # above re-weighs the prior, so the previous entry of the history may be of another objective
            before = cost
            theta, cost, lam, radius = _damped_step(system, theta, cost, lam, radius, total_of, cg_iterations,
                                                    accepted)
            if cost < before:           # a trial was kept: the last one priced (_damped_step returns at once)
                data_cost = trial_data
        history.append(cost / data.n_res)
        if progress is not None:
            progress("footprint" if data.pix is not None else "joint", it + 1, history[-1])
        if before - cost <= 1e-6 * before:
            break
    out = {"joint_s": time.perf_counter() - t0, "joint_history": history, "joint_accepted": accepted,
           "joint_sampling": "footprint" if data.pix is not None else sampling,
           "joint_data_cost": data_cost / data.n_res}
    if data.pix is not None:    # the form the pixel operator keeps its Jacobian in (auto: decided by the memory)
        out["joint_jacobian"] = data.pix.jacobian_form
    if adapt:   # the ratios measured (none when the refinement stopped after one iteration) and the final units
        out["noise_ratio"] = units.ratios
        out["prior_units"] = units.units()
    return theta, out
