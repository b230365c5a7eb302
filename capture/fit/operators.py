"""Sparse operators of the joint solves: the bilinear sampling footprint (samples × texels) and the photos'
pixel footprints (pixels × texels, :class:`PixelOperator`)."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from typing import NamedTuple

import torch
from torch import Tensor

from materials.model import Model
from renderer.device import HandedOutArrays, block_size, kept_array, memory_headroom

from .layout import ACC, Layout, SolverError
from .texel import JACOBIAN_BLOCK, derivative_pairs, jacobian_blocks

__all__ = ["CsrPattern", "csr_matrix", "csr_rows", "sampling_operator", "sampled_sum",
           "sampled_blocks", "PixelJacobian", "SampleJacobian",
           "PixelOperator", "pixel_operator", "AFFINE_TOL", "NORMAL_BLOCK", "JACOBIAN_FORMS", "ASSEMBLED_SHARE",
           "check_jacobian_form", "check_memory_budget"]

#: Largest difference, relative to the largest pixel value, between the model evaluated at other parameter values
#: and the prediction of its Jacobian for the model to count as affine (:meth:`PixelOperator.linearise`): the
#: evaluation's float32 rounding summed over a pixel's ≤ 16 samples is ~1e-6 of it; a model that is not affine
#: misses by its curvature over a halving of every parameter, far above that.
AFFINE_TOL = 1e-5
#: Entries per block of :meth:`PixelOperator.normal`'s sums: 2¹⁶ × 18 pairs × 8 bytes = 9 MB temporaries, which stay
#: in the allocator's reuse instead of fresh pages (the whole-array version took 1.8 s of page faults per call on
#: the 256² Mitsuba sphere, the blocked one 0.1 s). This and the other block sizes are the CPU's; on a GPU they are
#: :data:`renderer.device.CUDA_BLOCK_FACTOR` times larger (:func:`renderer.device.block_size`).
NORMAL_BLOCK = 1 << 16
#: Entries per block when values are placed into, or read back from, the Jacobian's matrices
#: (:class:`_Placement`): [2¹⁸, 9] int64 places are 19 MB of temporaries.
PLACE_BLOCK = 1 << 18
#: How :class:`PixelOperator` keeps a linearisation's Jacobian (``FitOptions.jacobian``, ``--jacobian``):
#: ``"assembled"`` as the sparse pixel × texel matrices :class:`PixelJacobian` (the fastest products), ``"samples"``
#: as the samples' own values :class:`SampleJacobian` (products through the sampling operators: less memory, more
#: time), ``"auto"`` assembled unless that would take more than :data:`ASSEMBLED_SHARE` of the memory available.
JACOBIAN_FORMS = ("auto", "assembled", "samples")
#: Share of the memory available at the first linearisation (:func:`renderer.device.available_memory`) that the
#: assembled matrices may take under ``"auto"``: while they are made, their values exist twice over (``A``'s and
#: ``Aᵀ``'s) beside the samples' Jacobian, and the steps' temporaries and the allocator's fragmentation come on top
#: (the 32 × 512² scene's resident memory peaks ~1.3 GB above its live tensors), so half of what is free is the most
#: they can take without the process swapping.
ASSEMBLED_SHARE = 0.5
#: Bytes per non-zero of the assembled form: ``A`` and ``Aᵀ`` each hold a 32-bit column index and a float32 value.
ASSEMBLED_BYTES = 16


class PixelJacobian(NamedTuple):
    """The pixel predictions' Jacobian at one linearisation. Of the entries' blocks ``C [E, 3, P]`` only the
    (channel, parameter) pairs ``(cs[j], ps[j])`` some sample depends on are kept (GGX + Lambert: 9 of 21), as
    the sparse CSR matrix ``A [3R, P·T]`` (rows pixel·3 + channel, columns texel·P + parameter) and its transpose
    ``At [P·T, 3R]``, so that ``J u`` and ``Jᵀ v`` are one sparse product each (10× faster than a gather, a
    batched 3 × P product and a sparse sum over the entries: 6–9 against 60–110 ms on the 256² Mitsuba torus,
    1.45 M entries, 2 threads). Where each value sits in either matrix follows from the entries' pixel and
    texel counts (:class:`_Placement`), so no permutation of the values is stored, and the values are not kept a
    third time: the normal equations' blocks read them back from ``A``. GGX + Lambert in float32: 152 bytes per
    (pixel, texel) entry (two 32-bit columns and values for each of 9 pairs, and each entry's texel in texel
    order), against 288 with the two sort permutations and a float64 copy of the values."""

    cs: Tensor
    ps: Tensor
    A: Tensor
    At: Tensor


class SampleJacobian(NamedTuple):
    """The pixel predictions' Jacobian kept per sample (``jacobian="samples"`` of :class:`PixelOperator`): the
    samples' values at the (channel, parameter) pairs ``(cs[j], ps[j])``, pair-major ``JcT [k, S]`` in the samples'
    precision. A product goes through the sampling operators — ``J u = group · Σ_j JcT_j ∘ (gather · u)_{ps_j}``
    per channel, ``Jᵀ v = gatherᵀ · Σ_j JcT_j ∘ (share · v[pixel])_{cs_j}`` per parameter — and the normal
    equations' blocks make each block of entries' values from it, so nothing of size entries × pairs is kept: 4
    bytes per sample and pair against 16 per entry and pair in :class:`PixelJacobian`. Pair-major, each term is one
    pass over contiguous values (the products of the 256² Mitsuba sphere took 11 and 13 ms against 17 and 19 with
    the sample-major ``[S, k]``, and 3 ms each assembled: the operators' rows are samples, ~5 texture taps each,
    instead of pixels, ~30 non-zeros each)."""

    cs: Tensor
    ps: Tensor
    JcT: Tensor
    n_params: int


def _block_pairs(cs: Tensor, ps: Tensor, P: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pairs ``(i, j)`` of kept values on the same channel — the terms of the per-texel blocks ``Σ_c C_cp w_c
    C_cq``, each unordered pair once (the blocks are symmetric) — and their flat places ``p·P + q`` and ``q·P + p``
    in a ``P × P`` block."""
    order = torch.arange(len(cs), device=cs.device)
    i, j = torch.nonzero((cs[:, None] == cs[None, :]) & (order[:, None] <= order[None, :]), as_tuple=True)
    return i, j, ps[i] * P + ps[j], ps[j] * P + ps[i]


class _Placement(NamedTuple):
    """Where value ``(e, j)`` of the entries' values ``V [E, k]`` sits in a CSR matrix whose rows are
    ``(group, part)``: a group is a pixel (``A``: the parts are the channels) or a texel (``At``: the parameters),
    its entries consecutive in the order ``order`` (None: the entries' own order, by pixel), and row
    ``(g, part)`` holds the values of the group's entries at the columns ``j`` of that part, entry by entry. The
    place is ``crow[g]·k + n_g·off[part] + (position − crow[g])·size[part] + rank[j]`` — arithmetic on the
    group's row pointer ``crow`` and count ``n_g`` — instead of a stored permutation of all E·k values (36 bytes
    per entry of GGX + Lambert in 32 bits, for each matrix)."""

    crow: Tensor            # [G + 1] int64 the groups' first positions
    group: Tensor           # [E] the group of each position (int64 or int32)
    order: Tensor | None    # [E] the entry at each position (None: the identity)
    part_size: Tensor       # [parts] int64 columns per part
    part_off: Tensor        # [parts] int64 offset of each part among a group's values per entry
    col_part: Tensor        # [k] int64 each column's part
    col_rank: Tensor        # [k] int64 each column's rank in its part
    width: int              # s > 1 when every part is s consecutive columns (rows below), else 0

    @classmethod
    def of(cls, crow: Tensor, group: Tensor, order: Tensor | None, col_part: Tensor, parts: int) -> _Placement:
        size = torch.bincount(col_part, minlength=parts)
        rank = torch.tensor([int((col_part[:j] == col_part[j]).sum()) for j in range(col_part.numel())],
                            dtype=torch.long, device=col_part.device)
        off = torch.cumsum(size, 0) - size
        k = col_part.numel()
        # parts of s consecutive columns each (the channels of GGX + Lambert: 3 pairs each): then a position's values
        # in a part are s consecutive places, row (crow·parts + n·part + position − crow) of the values seen as
        # [·, s], and placing or reading them moves rows — a third of the indices, each of 24 bytes less
        s = int(size[0]) if parts else 0
        consecutive = torch.equal(off[col_part] + rank, torch.arange(k, device=rank.device))
        rows = s > 1 and bool((size == s).all()) and consecutive
        return cls(crow.long(), group, order, size, off, col_part, rank, s if rows else 0)

    def place(self, pos: Tensor) -> Tensor:
        """``[n, k]`` int64 places of the values at the positions ``pos [n]`` (int64)."""
        g = self.group[pos]
        start = self.crow[g]
        n = self.crow[g + 1] - start
        k = self.col_part.numel()
        return (start[:, None] * k + n[:, None] * self.part_off[self.col_part][None]
                + (pos - start)[:, None] * self.part_size[self.col_part][None] + self.col_rank[None])

    def rows(self, pos: Tensor) -> Tensor:
        """``[n, parts]`` int64 rows of ``values.view(-1, width)`` holding the values at the positions ``pos [n]``
        part by part (only when :attr:`width` is set)."""
        g = self.group[pos]
        start = self.crow[g]
        n = self.crow[g + 1] - start
        parts = self.part_size.numel()
        return (start * parts + (pos - start))[:, None] + n[:, None] * torch.arange(parts, device=pos.device)[None]

    def take(self, values: Tensor, pos: Tensor) -> Tensor:
        """``[n, k]`` the values (flat, ``[E·k]``) placed at the positions ``pos [n]`` (int64)."""
        k = self.col_part.numel()
        if self.width:
            return values.view(-1, self.width).index_select(0, self.rows(pos).reshape(-1)).view(-1, k)
        return values.index_select(0, self.place(pos).reshape(-1)).view(-1, k)

    def row_pointers(self) -> Tensor:
        """``[G·parts + 1]`` int64 row pointers of the rows ``(group, part)``, group-major."""
        k = self.col_part.numel()
        n = self.crow[1:] - self.crow[:-1]
        starts = (self.crow[:-1, None] * k + n[:, None] * self.part_off[None]).reshape(-1)
        return torch.cat([starts, self.crow[-1:] * k])

    def scatter(self, values_of: Callable[[int, int], Tensor], out: Tensor) -> Tensor:
        """``out`` (flat, ``[E·k]``) with each entry's values at their places, block by block of positions:
        ``values_of(a, b)`` gives the ``[b − a, k]`` values of the entries at the positions ``a … b − 1`` (the
        entries ``a … b − 1`` themselves when ``order`` is None, else ``order[a:b]``)."""
        E, step = int(self.crow[-1]), block_size(PLACE_BLOCK, out.device)
        # (index_copy_ moves the same values as out[places] = values, in 0.6 of the time on the CPU)
        for a in range(0, E, step):
            b = min(a + step, E)
            pos = torch.arange(a, b, device=out.device)
            vals = values_of(a, b).to(out.dtype)
            if self.width:
                out.view(-1, self.width).index_copy_(0, self.rows(pos).reshape(-1), vals.reshape(-1, self.width))
            else:
                out.index_copy_(0, self.place(pos).reshape(-1), vals.reshape(-1))
        return out


def sampling_operator(idx: Tensor, weight: Tensor, T: int) -> tuple[Tensor, Tensor]:
    """Sparse CSR matrices ``[S, T]`` and ``[T, S]`` of the sampling footprint: row s holds sample s's weights at its
    texels ``idx [S, K]`` (``weight [S, K]``); the transpose is built directly, not transposed. (Sums through the
    transpose alone, without keeping it: :func:`sampled_sum`.)"""
    S, K = idx.shape
    rows = torch.arange(S, device=idx.device).repeat_interleave(K)
    cols, vals = idx.reshape(-1), weight.reshape(-1)
    return _csr(rows, cols, vals, (S, T)), _csr(cols, rows, vals, (T, S))


def _add_sampled(out: Tensor, values: Tensor, idx: Tensor, weight: Tensor | None) -> None:
    """``out [T, D]`` += each of the samples' ``values [n, D]`` at its texels ``idx [n, K]`` times ``weight [n, K]``
    (None: 1), the (sample, slot) terms in the transposed sampling operator's order — sample by sample, slot by slot
    — added by one ``index_add_``, so that the sums are the operator's product's bit for bit."""
    n, K = idx.shape
    terms = values[:, None].expand(n, K, values.shape[1]) if weight is None \
        else values[:, None] * weight[:, :, None].to(values.dtype)
    out.index_add_(0, idx.reshape(-1), terms.reshape(n * K, -1))


def sampled_sum(values: Tensor, idx: Tensor, weight: Tensor | None, T: int) -> Tensor:
    """``[T, …]``: each sample's ``values [S, …]`` added to the texels it reads, ``idx [S, K]``, times its weight
    there (``weight [S, K]``; None: 1) — the transposed sampling operator's product (:func:`sampling_operator`)
    without the operator, the same sums bit for bit (on the CPU), a block of :data:`NORMAL_BLOCK` (sample, slot)
    terms at a time."""
    S, K = idx.shape
    if values.shape[0] != S or (weight is not None and tuple(weight.shape) != (S, K)):
        raise SolverError(f"sampled_sum: {values.shape[0]} samples' values for texels {tuple(idx.shape)} and weights "
                          f"{None if weight is None else tuple(weight.shape)}; give one row of each per sample")
    flat = values.reshape(S, -1)
    out = torch.zeros(T, flat.shape[1], dtype=values.dtype, device=values.device)
    step = max(block_size(NORMAL_BLOCK, values.device) // K, 1)
    for a in range(0, S, step):
        b = min(a + step, S)
        _add_sampled(out, flat[a:b], idx[a:b], None if weight is None else weight[a:b])
    return out.reshape(T, *values.shape[1:])


def sampled_blocks(J: Tensor, w: Tensor, idx: Tensor, weight: Tensor | None, T: int) -> Tensor:
    """Per-texel Gauss-Newton blocks ``[T, P, P]``: ``Σ_s Σ_k weight_sk J_sᵀ diag(w_s) J_s`` over the samples
    ``s`` that read texel ``t = idx[s, k]`` (``J [S, C, P]``, ``w [S, C]``, ``idx``, ``weight [S, K]``; None: 1).
    Made a block of samples at a time, summed as :func:`sampled_sum` sums (the transposed sampling operator's sums
    bit for bit on the CPU): the products of all samples at once were an ``[S, P, P]`` array (0.63 GB on the 1.6 M pixel
    centres of 32 × 512² photos, 5.1 GB on 16 × 2048²), and the operator that summed them one more ``[K·S]``
    matrix."""
    S, C, P = J.shape
    if tuple(w.shape) != (S, C):
        raise SolverError(f"sampled_blocks: weights {tuple(w.shape)} for a Jacobian {tuple(J.shape)}; give "
                          f"[S, C] weights")
    if idx.shape[0] != S or (weight is not None and tuple(weight.shape) != tuple(idx.shape)):
        raise SolverError(f"sampled_blocks: texels {tuple(idx.shape)} and slot weights "
                          f"{None if weight is None else tuple(weight.shape)} for {S} samples; give [S, K] of both")
    out = torch.zeros(T, P * P, dtype=J.dtype, device=J.device)
    step = max(block_size(NORMAL_BLOCK, J.device) // idx.shape[1], 1)
    for a in range(0, S, step):
        b = min(a + step, S)
        Jb = J[a:b]
        JWJ = torch.bmm((Jb * w[a:b, :, None].to(J.dtype)).transpose(1, 2), Jb)          # [n, P, P]
        _add_sampled(out, JWJ.reshape(b - a, P * P), idx[a:b], None if weight is None else weight[a:b])
    return out.reshape(T, P, P)


class CsrPattern(NamedTuple):
    """The structure of a sparse CSR matrix built from triplets: the stable sort of the rows (``order``; None when
    they come in order), the row pointers and the sorted columns, in 32-bit integers wherever they fit. Matrices with
    the same triplet positions and new values reuse it (:meth:`matrix`): one gather instead of a sort, and the CSR
    shares the pattern's index arrays. 32 bits halve what the kept patterns hold: the pixel operator's two patterns
    took 288 bytes per (pixel, texel) entry of GGX + Lambert in 64 bits (9 non-zeros each)."""

    order: Tensor | None
    crow: Tensor
    col: Tensor
    shape: tuple[int, int]

    @classmethod
    def of(cls, rows: Tensor, cols: Tensor, shape: tuple[int, int]) -> CsrPattern:
        small = max(shape) < 2 ** 31 and rows.numel() < 2 ** 31
        itype = torch.int32 if small else torch.long
        # rows already in order (a sampling operator's, the entries' pixels) need no sort: one pass to check
        if rows.numel() < 2 or bool((rows[1:] >= rows[:-1]).all()):
            order = None
        else:
            # 32-bit keys sort 1.6× faster (0.30 against 0.48 s for 13 M keys, 2 threads), same stable order
            order = torch.argsort(rows.to(torch.int32) if shape[0] < 2 ** 31 else rows, stable=True).to(itype)
        crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
        crow[1:] = torch.bincount(rows, minlength=shape[0]).cumsum(0)
        return cls(order, crow.to(itype), (cols if order is None else cols[order]).to(itype), shape)

    def matrix(self, vals: Tensor) -> Tensor:
        """The CSR matrix with ``vals`` at the triplet positions (in the order the pattern was built from)."""
        # index_select with 32-bit indices: 139 against 278 ms for x[order] of 9 M values (2 threads)
        return csr_matrix(self.crow, self.col, vals if self.order is None else torch.index_select(vals, 0, self.order),
                          self.shape)


def csr_matrix(crow: Tensor, col: Tensor, vals: Tensor, shape: tuple[int, int]) -> Tensor:
    """A sparse CSR matrix, with 32-bit indices wherever they fit: a product reads half the index bytes (1.6×
    faster: 7.7 against 12.3 ms for a float64 ``torch.mv`` of 4.4 M non-zeros, 2 threads), exactly the same."""
    if max(shape) < 2 ** 31 and int(vals.numel()) < 2 ** 31:
        crow, col = crow.to(torch.int32), col.to(torch.int32)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(crow, col, vals, shape)


def csr_rows(M: Tensor, a: int, b: int) -> Tensor:
    """The rows ``a … b − 1`` of the sparse CSR matrix ``M`` as a CSR matrix of their own, sharing ``M``'s column
    indices and values (slices, no copy): products a block of rows at a time keep their operands and results to the
    block's size, with each row's sum the whole product's."""
    crow = M.crow_indices()
    lo, hi = int(crow[a]), int(crow[b])
    return csr_matrix(crow[a:b + 1] - lo, M.col_indices()[lo:hi], M.values()[lo:hi], (b - a, M.shape[1]))


def _csr(rows: Tensor, cols: Tensor, vals: Tensor, shape: tuple[int, int]) -> Tensor:
    """A CSR matrix of the triplets ``(rows, cols, vals)``, built by one stable sort of the rows. Repeated
    (row, col) pairs are kept as separate entries, which the sparse products sum — no coalescing sort over both
    keys (5× faster to build: 0.10 s against 0.51 s for 2 M entries), same products to 1e-14."""
    return CsrPattern.of(rows, cols, shape).matrix(vals)


class PixelOperator:
    """The sparse pixel × texel operator of :class:`capture.footprint.PixelFootprints`, built once.

    A pixel's prediction is ``Σ_{s ∈ i} a_s L(p_s)`` with ``p_s = Σ_k w_sk p_k`` the read of sample s's texture
    footprint (bilinear reads at its texture sub-samples, :func:`capture.footprint.texture_footprints`; share
    ``a_s``). Linearised at the current maps, pixel i depends on texel t through the block
    ``C_it = Σ_{s ∈ i, k: idx_sk = t} a_s w_sk J_s`` (3 × P, ``J_s`` the sample's Jacobian with respect to its
    canonical parameters): one *entry* per (pixel, texel) pair the footprints touch, stored flat
    (``e_pix``, ``e_tex``). The Gauss-Newton matrix-vector product is then two gathers, two batched 3 × P
    products and two sparse sums (CSR), never the P·T × P·T matrix; the per-texel P × P blocks
    ``Σ_i C_itᵀ W_i C_it`` (the preconditioner, and the posterior's information) are exact.
    """

    def __init__(self, fp, T: int, jacobian: str = "auto", memory_budget: int | None = None):
        check_jacobian_form(jacobian)
        check_memory_budget(memory_budget)
        so = fp.samples
        if so.taps is None:
            raise SolverError("pixel footprints need each sample's texture footprint (observe_footprints builds it)")
        self.fp, self.T = fp, T
        self.R, S = fp.n_pixels, so.n_samples
        dev = so.taps.index.device
        # the footprints' (sample, texel, weight) triplets are the taps, sample-major. One stable sort of their
        # (pixel, texel) keys gives the entries (its runs) and the samples → entries operator (its order), instead of
        # a unique and a second sort. Each tap-sized temporary is freed as soon as it is used, the key made in place:
        # holding them all (rows, texels and weights in 64 bits, the products, the sorted keys) took 2.7 GB above
        # the operator on 32 × 512² photos (28 M taps), the peak of a fit that keeps its Jacobian per sample
        key = fp.group[so.taps.rows()]
        key.mul_(T).add_(so.taps.index)
        skey, perm = torch.sort(key, stable=True)
        del key
        ekey, e_sorted, counts = torch.unique_consecutive(skey, return_inverse=True, return_counts=True)
        del skey
        self.e_pix, self.e_tex = ekey // T, ekey % T
        E = int(ekey.numel())
        self.E = E
        del ekey
        # the entries by pixel (their own order) and by texel: row pointers, and the entries in texel order — the
        # patterns of the Jacobian's two matrices (no values: sums over them are index_adds, texel_sum)
        by_pix, by_tex = CsrPattern.of(self.e_pix, self.e_pix, (self.R, E)), CsrPattern.of(self.e_tex, self.e_tex,
                                                                                            (T, E))
        self.pix_crow = by_pix.crow
        self.tex_crow, self.tex_order = by_tex.crow, (by_tex.order if by_tex.order is not None
                                                      else torch.arange(E, device=dev))
        del by_pix, by_tex
        # samples → entries: each sample's texels (its texture footprint) and weights (the tap's weight times its
        # ray's share of the pixel), repeated pairs summed
        crow = torch.zeros(E + 1, dtype=torch.long, device=dev)
        crow[1:] = counts.cumsum(0)
        del counts
        t_s = so.taps.rows()[perm]                      # each sorted tap's sample
        coef = so.taps.weight[perm].to(ACC)
        del perm
        coef.mul_(fp.share.to(ACC)[t_s])
        # the two sampling operators' values in the samples' precision (float32: 4 bytes per texture tap less
        # each; the model reads its parameters in that precision anyway)
        vdt = so.dtype if so.dtype.is_floating_point else ACC
        self.corner_op = csr_matrix(crow, t_s, coef.to(vdt), (E, S))
        del t_s, crow
        # each entry's share of its pixel (Σ over a pixel's entries = 1): how much of the pixel the texel is
        self.e_share = torch.zeros(E, dtype=ACC, device=dev).index_add_(0, e_sorted, coef)
        del e_sorted, coef
        # texels → samples: the taps are sample-major, so the matrix is the taps' own row pointers, texel indices
        # (int32) and weights, shared rather than copied where their types are the matrix's (0.25 GB on 32 × 512²)
        self.gather_op = csr_matrix(so.taps.start, so.taps.index, so.taps.weight.to(vdt), (S, T))
        # the entries' pixels and texels in 32 bits (indices only, no arithmetic; index_add takes them as int64: its
        # 32-bit path is 2.4× slower on the CPU)
        if max(self.R, T) < 2 ** 31:
            self.e_pix, self.e_tex = self.e_pix.to(torch.int32), self.e_tex.to(torch.int32)
        self.y = fp.radiance.to(ACC)
        self._pattern = None            # the Jacobian matrices' index arrays and value placements
        self._affine = None             # (canon, pred, J) once the model is found affine in its parameters
        self._affine_checked = False
        self._blocks = None             # (J, w, blocks) of the last normal(), reused while both are unchanged
        self.jacobian = jacobian        # the form asked for (JACOBIAN_FORMS)
        self.memory_budget = memory_budget      # bytes the process may hold (None: what the machine has)
        self.jacobian_form = None       # the form used, decided at the first linearisation
        self._gather_t = None           # gather_op's transpose, made for the first product of the samples' form
        self._kept = {}                 # the products' texel-sized conversions (_scratch)
        self._values = HandedOutArrays()    # the assembled Jacobian's value arrays, reused by the next (_value_arrays)

    def observed(self) -> Tensor:
        """``[T]`` bool: texels some kept pixel reads with a positive weight."""
        seen = torch.zeros(self.T, dtype=torch.bool, device=self.y.device)
        seen[self.e_tex[self.e_share > 0]] = True
        return seen

    def texel_sum(self, x: Tensor) -> Tensor:
        """``[T]``: the sum over each texel's entries of the per-entry values ``x [E]``."""
        return torch.zeros(self.T, dtype=x.dtype, device=x.device).index_add_(0, self.e_tex.long(), x)

    def dominance(self) -> Tensor:
        """``[T]`` the largest share any kept pixel takes from each texel (0 where none reads it)."""
        return torch.zeros(self.T, dtype=ACC, device=self.y.device).scatter_reduce(
            0, self.e_tex.long(), self.e_share, "amax", include_self=True)

    @property
    def affine(self) -> bool:
        """True once :meth:`linearise` found the model affine in its parameters (its Jacobian is then reused)."""
        return self._affine is not None

    def predict(self, model: Model, layout: Layout, canon: Tensor, out: Tensor | None = None) -> Tensor:
        """Pixel predictions ``[R, 3]`` of canonical texel parameters ``canon [T, P]`` (for a model found affine
        in its parameters, :meth:`linearise`, from the stored linearisation without evaluating the model), into
        ``out [R, 3]`` (float64) when given."""
        if self._affine is not None:
            canon0, pred0, J = self._affine
            if out is None:
                return pred0 + self.apply(J, canon - canon0)
            return torch.add(pred0, self.apply(J, canon - canon0, out=out), out=out)
        return self._pixel_radiance(model, layout, canon, out)

    def _sample_blocks(self, device: torch.device) -> Iterator[tuple[int, int]]:
        """``(a, b)``: the blocks of samples ``a … b − 1`` of :data:`JACOBIAN_BLOCK` that the evaluations and the
        samples' products work in."""
        S, step = self.fp.samples.n_samples, block_size(JACOBIAN_BLOCK, device)
        for a in range(0, S, step):
            yield a, min(a + step, S)

    def _read(self, x: Tensor, a: int, b: int) -> Tensor:
        """``[b − a, P]`` the texture reads of the samples ``a … b − 1`` from texel values ``x [T, P]`` (in
        ``gather_op``'s precision): its rows, sliced without a copy."""
        return csr_rows(self.gather_op, a, b) @ x

    def _add_to_pixels(self, out: Tensor, x: Tensor, a: int, b: int) -> None:
        """Add the values ``x [b − a, C]`` of the samples ``a … b − 1``, times their shares, to their pixels' rows of
        ``out [R, C]``: a block of the sum of each pixel's samples (in the samples' order, as a sparse product of
        the pixels' rows would add them), with no pixels × samples matrix kept (0.07 GB on 32 × 512² photos)."""
        out.index_add_(0, self.fp.group[a:b], x.to(out.dtype) * self.fp.share[a:b, None].to(out.dtype))

    def _pixel_radiance(self, model: Model, layout: Layout, canon: Tensor, out: Tensor | None = None) -> Tensor:
        """``[R, 3]`` the pixels' radiance at canonical texel parameters ``canon [T, P]`` (into ``out`` when given):
        the samples evaluated and summed into their pixels in blocks of :data:`JACOBIAN_BLOCK` samples, so that
        neither the model's temporaries nor the samples' reads and radiance are ever whole (32 × 256² photos, 2.2 M
        samples, GGX + Lambert: the model's temporaries whole took 0.44–0.64 GB, in blocks 0.12–0.25 GB in the same
        time; 32 × 512², 5.3 M samples, the reads and radiance whole 0.27 GB more)."""
        so = self.fp.samples
        x = canon.to(self.gather_op.dtype)
        out = torch.zeros(self.R, 3, dtype=ACC, device=canon.device) if out is None else out.zero_()
        with torch.no_grad():
            for a, b in self._sample_blocks(canon.device):
                rad = so.predict_rows(model, layout.split(self._read(x, a, b).to(so.dtype)), a, b)
                self._add_to_pixels(out, rad.to(ACC), a, b)
        return out

    def linearise(self, model: Model, layout: Layout, canon: Tensor, groups) -> tuple[Tensor, PixelJacobian]:
        """``(pred [R, 3], J)`` at ``canon [T, P]``: the pixel predictions and their Jacobian
        (:class:`PixelJacobian`).

        A model that is affine in all its parameters (Lambert: ``L = ρ·E``) has a constant Jacobian: the first
        linearisation checks it — every parameter flagged ``linear`` and one more evaluation at other values
        matching the linear prediction — and later ones, and :meth:`predict`, reuse it (``pred0 + J·Δ``), so a
        Gauss-Newton step costs sparse products only."""
        if self._affine is not None:
            return self.predict(model, layout, canon), self._affine[2]
        P = canon.shape[1]
        self._blocks = None             # (the last linearisation's blocks and Jacobian freed before the new ones)
        pred, JcT, mask = self._sample_jacobian(model, layout, canon, groups)
        if self._form(int(mask.sum()), JcT.device) == "assembled":
            J = self._jacobian(JcT, mask, P)
        else:
            cs, ps = torch.nonzero(mask, as_tuple=True)
            J = SampleJacobian(cs, ps, JcT, P)
        del JcT
        if not self._affine_checked:
            self._affine_checked = True
            free = sorted({c for cs in groups for c in cs}) == list(range(P))
            if free and layout.affine:
                # other values: half of each parameter (inside every range that holds 0 and the value)
                other = 0.5 * canon
                direct = self._pixel_radiance(model, layout, other)
                linear = pred + self.apply(J, other - canon)
                scale = float(pred.abs().max()) + 1e-30
                if float((direct - linear).abs().max()) <= AFFINE_TOL * scale:
                    self._affine = (canon.clone(), pred, J)
        return pred, J

    def _sample_jacobian(self, model: Model, layout: Layout, canon: Tensor, groups) -> tuple[Tensor, Tensor, Tensor]:
        """``(pred [R, 3], JcT [k, S], mask [3, P])``: the pixels' predictions and, of the samples' Jacobian, only
        the ``k`` (channel, parameter) pairs of ``mask`` that some sample depends on (GGX + Lambert: 9 of 21, the
        albedo and f0 act on their own channel), pair-major (:class:`SampleJacobian`'s layout, which the assembled
        form reads too: made sample-major, the samples' form took a transposed copy, 0.19 GB more on 32 × 512²
        photos), block by block (:func:`jacobian_blocks`) so that neither the whole ``[S, 3, P]`` Jacobian nor the
        whole autograd graph is ever held; the samples' parameters are read a block at a time too (whole, 0.15 GB of
        new pages a linearisation on 32 × 512² photos). (``JcT`` is made afresh: kept for the next call, its 0.19 GB
        there would be held through the steps' products, whose peak it raised by as much.)"""
        x = canon.to(self.gather_op.dtype)
        S, P = self.gather_op.shape[0], x.shape[1]
        dev = x.device
        pred = torch.zeros(self.R, 3, dtype=ACC, device=dev)
        # the union of the blocks' pairs, in their row-major order; a block that lacks some of them has zeros there.
        # Each block's values go straight into JcT, which grows (a copy) when a block brings a pair the earlier ones
        # lacked: keeping the blocks' values until all were seen held a second one (0.38 GB on 32 × 512² photos)
        mask = torch.zeros(3, P, dtype=torch.bool, device=dev)
        # the values in the precision the model is evaluated in (float32 gradients are exact in it): half the bytes
        # of float64 at the linearisation's peak (0.38 GB on 32 × 512² photos)
        jdt = self.gather_op.dtype
        JcT = where = None                              # where: each kept pair's row in JcT
        for a, b, pb, m, vals in self._pair_blocks(model, layout, x, groups):
            self._add_to_pixels(pred, pb, a, b)
            if JcT is None or bool((m & ~mask).any()):
                union = mask | m
                grown = torch.zeros(int(union.sum()), S, dtype=jdt, device=dev)
                new_where = torch.cumsum(union.reshape(-1), 0).reshape(3, P) - 1
                if JcT is not None:
                    grown[new_where[mask]] = JcT
                JcT, mask, where = grown, union, new_where
            JcT[where[m], a:b] = vals.to(jdt)
            del vals
        if JcT is None:                                 # no samples
            JcT = torch.zeros(0, S, dtype=jdt, device=pred.device)
        return pred, JcT, mask

    def _pair_blocks(self, model: Model, layout: Layout, x: Tensor,
                     groups) -> Iterator[tuple[int, int, Tensor, Tensor, Tensor]]:
        """``(a, b, pred [b − a, 3], mask [3, P], values [k, b − a])`` per block of samples at texel values
        ``x [T, P]`` (in ``gather_op``'s precision): the block's predictions and, pair-major, its Jacobian's values
        at the (channel, parameter) pairs of ``mask`` in their row-major order. In the model's closed form
        (:meth:`capture.observations.Observations.jacobian_rows`) the pairs are those it can depend on — a diagonal
        derivative's own channels, a full one's every channel — of the parameters ``groups`` keeps, taken as they
        are; else the block's :func:`jacobian_blocks` values, and the pairs some sample of it depends on. Each
        block's parameters are read on its own (:meth:`_read`: the rows of the whole product, bit for bit)."""
        so = self.fp.samples
        P = x.shape[1]
        step = block_size(JACOBIAN_BLOCK, x.device)
        kept = {c for cs in groups for c in cs}
        for a in range(0, max(so.n_samples, 1), step):
            b = min(a + step, so.n_samples)
            phi = self._read(x, a, b)
            res = so.jacobian_rows(model, layout.split(phi), a, b) if kept else None
            if res is None:
                for a_, b_, pb, Jb in jacobian_blocks(model, layout, so, phi, groups, canonical=True, block=step,
                                                      start=a):
                    m = (Jb != 0).any(0)
                    cs, ps = torch.nonzero(m, as_tuple=True)
                    yield a_, b_, pb, m, Jb[:, cs, ps].t()
                continue
            pb, d = res
            mask = torch.zeros(3, P, dtype=torch.bool, device=x.device)
            values = []
            for c, col, v in derivative_pairs(layout, d, kept):
                mask[c, col] = True
                values.append(v)
            yield a, b, pb.to(ACC), mask, torch.stack(values) if values else \
                torch.zeros(0, b - a, dtype=x.dtype, device=x.device)

    def _form(self, k: int, device: torch.device) -> str:
        """The Jacobian's form (:data:`JACOBIAN_FORMS`), decided once, at the first linearisation, for ``k`` kept
        pairs: ``"auto"`` is ``"assembled"`` unless its ``E·k`` non-zeros would take more than
        :data:`ASSEMBLED_SHARE` of the memory available — what the machine has, and within ``memory_budget`` what
        the budget leaves (:func:`renderer.device.memory_headroom`) — or that cannot be known."""
        if self.jacobian_form is None:
            form = self.jacobian
            if form == "auto":
                avail = memory_headroom(device, self.memory_budget)
                need = self.E * k * ASSEMBLED_BYTES
                form = "samples" if avail is not None and need > ASSEMBLED_SHARE * avail else "assembled"
            self.jacobian_form = form
        return self.jacobian_form

    def _n_params(self, J: PixelJacobian | SampleJacobian) -> int:
        """The parameters per texel, P, of a linearisation."""
        return J.n_params if isinstance(J, SampleJacobian) else J.At.shape[0] // self.T

    def _entry_values(self, JcT: Tensor, a: int, b: int, dtype: torch.dtype | None = None) -> Tensor:
        """``[b − a, k]`` the values of the entries ``a … b − 1``: their rows of ``corner_op · JcTᵀ``, summed in
        ``dtype`` (None: ``JcT``'s). Only the run of samples they read is copied sample-major (and converted): the
        rays are made pixel by pixel, so a block of entries (of pixels) reads a short run (on 32 × 256² photos the
        runs of the blocks of :data:`PLACE_BLOCK` entries add up to 1.3 × the samples)."""
        crow, col, cval = self.corner_op.crow_indices(), self.corner_op.col_indices(), self.corner_op.values()
        lo, hi = int(crow[a]), int(crow[b])
        dtype = JcT.dtype if dtype is None else dtype
        cols, s0, s1 = col[lo:hi], 0, 0
        if hi > lo:
            s0, s1 = int(cols.min()), int(cols.max()) + 1
            cols = cols - s0
        run = JcT[:, s0:s1].t().to(dtype=dtype, memory_format=torch.contiguous_format)     # (one copy)
        return csr_matrix(crow[a:b + 1] - lo, cols, cval[lo:hi].to(dtype), (b - a, s1 - s0)) @ run

    def _transposed_gather(self) -> Tensor:
        """``[T, S]`` the transpose of ``gather_op`` (samples → texels), made once from its triplets."""
        if self._gather_t is None:
            G = self.gather_op
            tex = G.col_indices()
            # the taps by texel (a stable sort: by sample within a texel) with their samples in 32 bits, instead of
            # every tap's sample and texel in 64 bits beside the sort's copies
            order = torch.argsort(tex, stable=True)
            crow = torch.zeros(self.T + 1, dtype=torch.long, device=tex.device)
            crow[1:] = torch.bincount(tex, minlength=self.T).cumsum(0)
            g_crow = G.crow_indices()
            itype = torch.int32 if G.shape[0] < 2 ** 31 else torch.long
            sample = torch.repeat_interleave(torch.arange(G.shape[0], dtype=itype, device=tex.device),
                                             (g_crow[1:] - g_crow[:-1]).long())[order]
            self._gather_t = csr_matrix(crow, sample, G.values()[order], (self.T, G.shape[0]))
        return self._gather_t

    def _jacobian(self, JcT: Tensor, mask: Tensor, P: int) -> PixelJacobian:
        """The :class:`PixelJacobian` of the samples' Jacobian ``JcT [k, S]`` at the (channel, parameter) pairs of
        ``mask [3, P]`` (the pairs some sample depends on; Lambert's albedo: the diagonal, a third of the block):
        the entries' values ``V = corner_op · JcTᵀ`` ``[E, k]``, made block by block of entries straight into their
        places in ``A`` and read from there into ``At`` (V whole would be 72 bytes per entry more at the peak). The
        matrices' index arrays depend on the pattern only and are kept across linearisations."""
        key = tuple(mask.reshape(-1).tolist())
        E, k = self.E, JcT.shape[0]
        dev = JcT.device
        if self._pattern is None or self._pattern[0] != key:
            self._pattern = None                # (the old index arrays freed before the new ones are built)
            cs, ps = torch.nonzero(mask, as_tuple=True)
            itype = torch.int32 if max(3 * self.R, P * self.T, E * k) < 2 ** 31 else torch.long
            perm = self.tex_order               # the entries in texel order (32-bit where E fits: 0.13 GB less)
            by_pix = _Placement.of(self.pix_crow, self.e_pix, None, cs, 3)
            by_tex = _Placement.of(self.tex_crow, self.e_tex[perm], perm, ps, P)
            col_a = by_pix.scatter(lambda a, b: self.e_tex[a:b, None].long() * P + ps[None],
                                   torch.empty(E * k, dtype=itype, device=dev))
            col_t = by_tex.scatter(lambda a, b: self.e_pix[perm[a:b], None].long() * 3 + cs[None],
                                   torch.empty(E * k, dtype=itype, device=dev))
            self._pattern = (key, cs, ps, by_pix, by_tex, (by_pix.row_pointers().to(itype), col_a),
                             (by_tex.row_pointers().to(itype), col_t))
        _, cs, ps, by_pix, by_tex, a_idx, t_idx = self._pattern
        # the values in the precision the model was evaluated in (JcT's): float32 evaluations make float32 values, whose
        # products read half the bytes (with 32-bit indices 5.2 against 7.7 ms per product of 4.4 M non-zeros)
        vdt = JcT.dtype
        a_vals, t_vals = self._value_arrays(E * k, vdt, dev)
        # (summed in float64 from the float32 samples: the sums' rounding moved the ill-conditioned fits — one view
        # of the stress scene, roughness on observable texels 0.0020 → 0.0041)
        by_pix.scatter(lambda a, b: self._entry_values(JcT, a, b, ACC), a_vals)
        perm = by_tex.order
        by_tex.scatter(lambda a, b: by_pix.take(a_vals, perm[a:b]), t_vals)
        J = PixelJacobian(cs, ps, csr_matrix(*a_idx, a_vals, (3 * self.R, P * self.T)),
                          csr_matrix(*t_idx, t_vals, (P * self.T, 3 * self.R)))
        self._values.hand_out(J.A, J.At)
        return J

    def _value_arrays(self, n: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
        """The ``[n]`` value arrays of a new assembled Jacobian's ``A`` and ``At``: the last one's, overwritten in
        place, once nothing holds that Jacobian any more (the solver frees each step's before the next
        linearisation), else new ones. Fresh, each is new pages the kernel zeroes at first touch: on 32 × 512² photos
        (150 M values each, 0.6 GB) placing them took ~1 s more per linearisation than in kept arrays, and the
        footprint steps 137 → 121 s."""
        a_vals, t_vals = self._values.arrays([("A", (n,), dtype), ("At", (n,), dtype)], device)
        return a_vals, t_vals

    def release(self) -> None:
        """Free what only further linearisations would use — the kept value arrays and, unless the model is affine
        (whose kept Jacobian :meth:`normal` reads through them), the matrices' index arrays — once the steps are
        done (1.2 GB each on 32 × 512² photos). A later :meth:`linearise` makes them again. The index arrays stay
        while a Jacobian made with them is still held."""
        self._values.release()
        self._kept = {}
        if self._affine is None and not self._values.held():
            self._pattern = None

    def normal(self, J: PixelJacobian | SampleJacobian, w: Tensor, wr: Tensor) -> tuple[Tensor, Tensor]:
        """``(Jᵀ W r [T, P], blocks Σ_i C_itᵀ W_i C_it [T, P, P])`` with residual weights ``w [R, 3]`` and
        ``wr = w·r [R, 3]``. The blocks sum only the products of kept values on the same channel (GGX + Lambert:
        27 of the 147 of the dense 3 × 7 blocks), whose values are read back from ``A`` (or, for a
        :class:`SampleJacobian`, made from the samples' values block by block). The blocks are the caller's to
        change in place."""
        cached = self._blocks
        # the same Jacobian (an affine model's) with the same weights (L2: all ones) has the same blocks (a copy)
        if cached is not None and cached[0] is J and torch.equal(cached[1], w):
            return self.apply_t(J, wr), cached[2].clone()
        if isinstance(J, SampleJacobian):       # the entries' values made from the samples', a run of them per block
            B = self._block_sums(J.cs, J.ps, J.n_params, w, lambda a, b: self._entry_values(J.JcT, a, b).to(ACC))
        else:                                   # … or read back from A
            vals, by_pix = J.A.values(), self._pattern[3]
            B = self._block_sums(J.cs, J.ps, self._n_params(J), w,
                                 lambda a, b: by_pix.take(vals, torch.arange(a, b, device=w.device)).to(ACC))
        if self._affine is not None:    # (only an affine model's Jacobian comes back; others' blocks would be held
            self._blocks = (J, w, B)    # for nothing until the next linearisation; the caller gets a copy)
            return self.apply_t(J, wr), B.clone()
        return self.apply_t(J, wr), B

    def information(self, model: Model, layout: Layout, canon: Tensor, groups,
                    weights: Callable[[Tensor], Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """``(pred [R, 3], w [R, 3], blocks [T, P, P])``: the pixels' predictions at ``canon [T, P]``, their weights
        ``w = weights(pred)`` and the normal matrix's per-texel blocks ``Σ_i C_itᵀ W_i C_it`` — what a posterior
        reads — the same to the last bit as :meth:`linearise` then :meth:`normal` give them, without the gradient
        and without placing the values in ``A`` and ``Aᵀ``: each block of entries' values is made from the samples'
        as ``A`` would hold it (summed in float64, kept in the samples' precision), or, in the samples' form, as
        :meth:`normal` makes it. On 32 × 512² photos the placing is ~2 s and the two matrices 2.3 GB."""
        if self._affine is not None:            # (the affine model's Jacobian and blocks are kept: nothing to make)
            pred, J = self.linearise(model, layout, canon, groups)
            w = weights(pred)
            return pred, w, self.normal(J, w, torch.zeros_like(w))[1]
        pred, JcT, mask = self._sample_jacobian(model, layout, canon, groups)
        w = weights(pred)
        cs, ps = torch.nonzero(mask, as_tuple=True)
        if self._form(int(mask.sum()), JcT.device) == "assembled":
            def values(a: int, b: int) -> Tensor:
                return self._entry_values(JcT, a, b, ACC).to(JcT.dtype).to(ACC)
        else:
            def values(a: int, b: int) -> Tensor:
                return self._entry_values(JcT, a, b).to(ACC)
        return pred, w, self._block_sums(cs, ps, canon.shape[1], w, values)

    def _block_sums(self, cs: Tensor, ps: Tensor, P: int, w: Tensor,
                    values: Callable[[int, int], Tensor]) -> Tensor:
        """``Σ_i C_itᵀ W_i C_it`` ``[T, P, P]`` from the entries' values ``values(a, b) [b − a, k]`` (float64) at the
        pairs ``(cs, ps)``: the sums over a texel's entries of ``V_i w V_j``, in blocks of entries (the ``[E, pairs]``
        products whole are 300 MB on GGX + Lambert at 256², that cost more to allocate than to fill)."""
        i, j, pq, qp = _block_pairs(cs, ps, P)
        terms = torch.zeros(self.T, len(i), dtype=ACC, device=w.device)
        step = block_size(NORMAL_BLOCK, w.device)
        # the same s values on each channel, channel by channel (GGX + Lambert: albedo, f0, roughness; Lambert: the
        # albedo): the pairs are each channel's upper triangle, made as s(s + 1)/2 products of [n, 3] columns into
        # one buffer instead of gathering both factors' columns — the same products, 1.5 → 0.8 s a call on 32 ×
        # 512² photos
        k = len(cs)
        s = k // 3 if k % 3 == 0 else 0
        tri = [(p, q) for p in range(s) for q in range(p, s)]
        ch = torch.arange(3, device=cs.device)
        by_channel = s > 0 and torch.equal(cs, ch.repeat_interleave(s)) and \
            torch.equal(i, (ch[:, None] * s + torch.tensor([p for p, _ in tri], device=cs.device)).reshape(-1)) and \
            torch.equal(j, (ch[:, None] * s + torch.tensor([q for _, q in tri], device=cs.device)).reshape(-1))
        buf = torch.empty(min(step, self.E), 3, len(tri), dtype=ACC, device=w.device) if by_channel else None
        for a in range(0, self.E, step):
            b = min(a + step, self.E)
            V = values(a, b)
            if by_channel:
                Vc = V.view(b - a, 3, s)
                Vw = Vc * w.index_select(0, self.e_pix[a:b])[:, :, None]
                X = buf[:b - a]
                for t, (p, q) in enumerate(tri):
                    torch.mul(Vw[:, :, p], Vc[:, :, q], out=X[:, :, t])
                X = X.view(b - a, -1)
            else:
                Vw = V * w[self.e_pix[a:b]][:, cs]
                X = Vw[:, i] * V[:, j]
            terms.index_add_(0, self.e_tex[a:b].long(), X)      # (int32 indices: 2.4× slower)
        off = pq != qp                  # (a parameter pair repeats over channels: roughness with itself on each)
        B = torch.zeros(self.T, P * P, dtype=terms.dtype, device=terms.device).index_add_(1, pq, terms)
        return B.index_add_(1, qp[off], terms[:, off]).reshape(self.T, P, P)

    def apply(self, J: PixelJacobian | SampleJacobian, u: Tensor, out: Tensor | None = None) -> Tensor:
        """``J u`` ``[R, 3]`` for texel updates ``u [T, P]``, into ``out [R, 3]`` (of ``u``'s dtype) when given: a
        solver's product then makes no pixel-sized array (32 × 512² photos: its float32 result and float64 copy, 58
        MB, had been new pages at each of ~400 products, 4.4 s of the kernel's time)."""
        if isinstance(J, SampleJacobian):
            # block by block of samples: their changes and radiance changes whole were 0.34 GB of fresh pages per
            # product on 32 × 512² photos (5.3 M samples)
            x = u if u.dtype == self.gather_op.dtype else \
                self._scratch(u.numel(), self.gather_op.dtype, u.device).view(u.shape).copy_(u)
            acc = out if out is not None and out.dtype == ACC else torch.empty(self.R, 3, dtype=ACC, device=u.device)
            acc.zero_()
            pairs = list(zip(J.cs.tolist(), J.ps.tolist(), strict=True))
            for a, b in self._sample_blocks(u.device):
                d = self._read(x, a, b)                                             # [n, P] the samples' changes
                q = torch.zeros(b - a, 3, dtype=d.dtype, device=d.device)
                for j, (c, p) in enumerate(pairs):
                    q[:, c].addcmul_(J.JcT[j, a:b], d[:, p])
                self._add_to_pixels(acc, q, a, b)
            if out is None:
                return acc.to(u.dtype)
            return acc if acc is out else out.copy_(acc)
        x = u.reshape(-1)
        if x.dtype != J.A.dtype:                    # (converted into the kept scratch array, not a fresh one)
            x = self._scratch(x.numel(), J.A.dtype, x.device).copy_(x)
        if out is None:
            return torch.mv(J.A, x).to(u.dtype).reshape(self.R, 3)
        if out.dtype == J.A.dtype:
            torch.mv(J.A, x, out=out.view(-1))
            return out
        res = kept_array(self._kept, "pixel_scratch", (3 * self.R,), J.A.dtype, x.device)
        out.view(-1).copy_(torch.mv(J.A, x, out=res))
        return out

    def _scratch(self, n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
        """A ``[n]`` array of ``dtype`` kept for the products' texel-sized conversions (:meth:`apply`,
        :meth:`apply_t`), each used and done with before the next (:func:`renderer.device.kept_array`)."""
        return kept_array(self._kept, "scratch", (n,), dtype, device)

    def apply_t(self, J: PixelJacobian | SampleJacobian, v: Tensor, out: Tensor | None = None) -> Tensor:
        """``Jᵀ v`` ``[T, P]`` for pixel values ``v [R, 3]``, into ``out [T, P]`` when given."""
        if isinstance(J, SampleJacobian):
            dt = J.JcT.dtype
            vd = v.to(dt)
            z = torch.zeros(J.JcT.shape[1], self._n_params(J), dtype=dt, device=v.device)
            pairs = list(zip(J.cs.tolist(), J.ps.tolist(), strict=True))
            for a, b in self._sample_blocks(v.device):
                vs = vd[self.fp.group[a:b]] * self.fp.share[a:b, None].to(dt)      # [n, 3] each sample's part
                for j, (c, p) in enumerate(pairs):
                    z[a:b, p].addcmul_(J.JcT[j, a:b], vs[:, c])
            if out is None:
                return (self._transposed_gather() @ z).to(v.dtype)
            if out.dtype == dt:
                return torch.mm(self._transposed_gather(), z, out=out)
            res = self._scratch(out.numel(), dt, out.device).view(out.shape)
            return out.copy_(torch.mm(self._transposed_gather(), z, out=res))
        x = v.reshape(-1).to(J.At.dtype)
        if out is None:
            return torch.mv(J.At, x).to(v.dtype).reshape(self.T, -1)
        if out.dtype == J.At.dtype:
            torch.mv(J.At, x, out=out.view(-1))
            return out
        out.view(-1).copy_(torch.mv(J.At, x, out=self._scratch(out.numel(), J.At.dtype, out.device)))
        return out


def check_jacobian_form(jacobian) -> None:
    """A :class:`SolverError` unless ``jacobian`` is one of :data:`JACOBIAN_FORMS`."""
    if jacobian not in JACOBIAN_FORMS:
        raise SolverError(f"jacobian must be one of {list(JACOBIAN_FORMS)} (how the footprint solve keeps its "
                          f"Jacobian), got {jacobian!r}")


def check_memory_budget(budget) -> None:
    """A :class:`SolverError` unless ``budget`` is None or a positive whole number of bytes."""
    if budget is not None and (isinstance(budget, bool) or not isinstance(budget, int) or budget <= 0):
        raise SolverError(f"memory_budget must be a positive number of bytes or None (what the machine has), "
                          f"got {budget!r}")


def pixel_operator(footprints, T: int, jacobian: str = "auto", memory_budget: int | None = None) -> PixelOperator:
    """``footprints`` as a :class:`PixelOperator` over ``T`` texels keeping its Jacobian in the form ``jacobian``
    (:data:`JACOBIAN_FORMS`; ``"auto"`` within ``memory_budget`` bytes, None: the machine's memory): an operator is
    passed through (built once by :func:`capture.fit.fast.solve_fast` for all its stages, with its own form), pixel
    footprints are built into one."""
    check_jacobian_form(jacobian)
    check_memory_budget(memory_budget)
    if isinstance(footprints, PixelOperator):
        if footprints.T != T:
            raise SolverError(f"the pixel operator covers {footprints.T} texels, the maps {T}")
        return footprints
    return PixelOperator(footprints, T, jacobian, memory_budget)
