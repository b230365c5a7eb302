"""Shading geometry: the cosines every lobe is written in, computed once per (n, l, v).

Conventions (DESIGN.md): all vectors are unit length, world space, last dimension 3; ``n`` is
the surface normal, ``l`` points toward the light, ``v`` toward the viewer (the papers' E, ω_o,
V) and ``h = normalize(l + v)``. Tensors broadcast over any leading shape.

Every lobe in :mod:`materials` is an isotropic function of five cosines, so the renderer and the
solver compute an :class:`Angles` once per sample and light (geometry is known and fixed) and the
lobes never touch vectors again. Each cosine keeps a trailing dimension of size 1 so that it
broadcasts against RGB parameters ``[..., 3]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

#: Squared-length floor below which a vector is treated as zero by :func:`safe_normalize`.
NORM_EPS = 1e-24
#: Squared length below which :func:`safe_normalize` rescales a vector before normalising it (|x| < 1e-3).
SCALE_BELOW_SQ = 1e-6


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last dimension, keeping it: ``[..., 3] x [..., 3] -> [..., 1]``."""
    return (a * b).sum(dim=-1, keepdim=True)


def safe_normalize(x: Tensor, fallback: Tensor | None = None) -> Tensor:
    """Normalise ``x`` over its last dimension; where ``|x|`` vanishes return ``fallback``.

    The gradient is finite everywhere (the double-``where`` trick: the invalid branch never sees
    a zero length). ``fallback`` defaults to +z.

    A short ``x`` (|x| ≤ 1e-3) is first divided by its largest absolute component (a constant for
    autograd: the unit vector is scale-invariant, so value and gradient are unchanged), so the
    normalisation works on a vector of length in [1, √3]. Without it the backward pass of
    ``x · |x|^-1`` forms ``x (x·g) |x|^-3``, which overflows float32 for |x| ≈ 1e-11 (e.g. the half
    vector l + v of a grazing mirror pair, n·l = n·v ≈ 1e-11) although the true gradient
    (I − u uᵀ) g / |x| is finite. Longer vectors keep the plain ``x · |x|^-1`` (bit for bit the
    usual result; there the intermediate |x|^-3 (x·g) ≤ 1e6 |g| stays finite for any |g| < 3e32).
    """
    sq = dot(x, x)
    ok = sq > NORM_EPS
    big = sq > SCALE_BELOW_SQ
    plain = x * torch.rsqrt(torch.where(big, sq, torch.ones_like(sq)))
    scale = x.detach().abs().amax(dim=-1, keepdim=True)
    scale = torch.where(ok & ~big, scale, torch.ones_like(scale))
    y = x / scale
    yy = torch.where(ok & ~big, dot(y, y), torch.ones_like(sq))
    unit = torch.where(big, plain, y * torch.rsqrt(yy))
    if fallback is None:
        fallback = torch.zeros_like(x)
        fallback[..., 2] = 1.0
    return torch.where(ok, unit, fallback.expand_as(unit))


def reflect(l: Tensor, n: Tensor) -> Tensor:
    """Mirror direction of ``l`` about ``n``: ``r = 2 (n·l) n − l`` (Nielsen's ω_r)."""
    return 2.0 * dot(n, l) * n - l


@dataclass(frozen=True)
class Angles:
    """The isotropic shading configuration of one or many (n, l, v) triples.

    All fields are cosines of shape ``[..., 1]`` clamped to [-1, 1]; back-facing values are kept
    (negative) so that a lobe can decide how to treat them — every lobe returns 0 unless
    :attr:`front` holds.

    Attributes:
        nl: n·l, cosine of the incidence angle θ_i (the papers' N·L, cos θ_i).
        nv: n·v, cosine of the viewing angle θ_r (the papers' N·E, cos θ_o).
        nh: n·h, cosine of the half-vector angle θ_h.
        lh: l·h = v·h, cosine of half the phase angle (Fresnel's angle on a microfacet).
        lv: l·v, cosine of the phase angle (the papers' E·L).
        fresnel_lh: the cosine at which a lobe evaluates its specular Fresnel factor, or ``None`` for
            :attr:`lh` (every lobe reads it through :attr:`fresnel_cos`). A layer above the surface sets it:
            under Gotanda's coat the bottom's Fresnel is taken at the angle refracted into the coat (2012
            eq 4, :meth:`materials.layered.GotandaLayered.bottom_angles`) while the rest of the bottom lobe
            keeps the unrefracted cosines.
    """

    nl: Tensor
    nv: Tensor
    nh: Tensor
    lh: Tensor
    lv: Tensor
    fresnel_lh: Tensor | None = None

    @staticmethod
    def from_vectors(n: Tensor, l: Tensor, v: Tensor) -> Angles:
        """Build from unit vectors ``n, l, v`` of shape ``[..., 3]`` (broadcastable).

        Where ``l = −v`` the half vector is undefined; it falls back to ``n`` (such a pair is
        never front-facing on both sides, so every lobe returns 0 there anyway).
        """
        for name, x in (("n", n), ("l", l), ("v", v)):
            if not isinstance(x, Tensor):
                raise TypeError(f"Angles.from_vectors: {name} must be a torch.Tensor, got {type(x).__name__}")
            if x.shape[-1] != 3:
                raise ValueError(
                    f"Angles.from_vectors: {name} must have a last dimension of 3 (a 3-vector), "
                    f"got shape {tuple(x.shape)}"
                )
        n, l, v = torch.broadcast_tensors(n, l, v)
        h = safe_normalize(l + v, fallback=n)
        c = lambda a, b: dot(a, b).clamp(-1.0, 1.0)
        return Angles(nl=c(n, l), nv=c(n, v), nh=c(n, h), lh=c(l, h), lv=c(l, v))

    @staticmethod
    def from_cosines(nl: Tensor, nv: Tensor, lv: Tensor) -> Angles:
        """Build from the three independent cosines of an isotropic configuration.

        ``n·h`` and ``l·h`` follow from |l + v|² = 2 + 2 l·v:
        ``l·h = sqrt((1 + l·v) / 2)`` and ``n·h = (n·l + n·v) / (2 l·h)``.
        Shapes broadcast; a trailing size-1 dimension is added if the last dimension is not 1.
        """
        nl, nv, lv = torch.broadcast_tensors(*(torch.as_tensor(x) for x in (nl, nv, lv)))
        if nl.dim() == 0 or nl.shape[-1] != 1:
            nl, nv, lv = nl.unsqueeze(-1), nv.unsqueeze(-1), lv.unsqueeze(-1)
        half_sq = ((1.0 + lv) * 0.5).clamp_min(0.0)
        ok = half_sq > 1e-12
        lh = torch.sqrt(torch.where(ok, half_sq, torch.ones_like(half_sq)))
        nh = torch.where(ok, (nl + nv) / (2.0 * lh), torch.ones_like(lh))
        lh = torch.where(ok, lh, torch.zeros_like(lh))
        c = lambda x: x.clamp(-1.0, 1.0)
        return Angles(nl=c(nl), nv=c(nv), nh=c(nh), lh=c(lh), lv=c(lv))

    @property
    def fresnel_cos(self) -> Tensor:
        """The cosine of the specular Fresnel factor: :attr:`fresnel_lh` if set, else l·h, ``[..., 1]``."""
        return self.lh if self.fresnel_lh is None else self.fresnel_lh

    def with_fresnel_cos(self, cos: Tensor) -> Angles:
        """These angles with the specular Fresnel factor evaluated at ``cos`` ``[..., 1]`` instead of l·h."""
        return Angles(self.nl, self.nv, self.nh, self.lh, self.lv, cos)

    @property
    def front(self) -> Tensor:
        """Boolean ``[..., 1]``: both light and viewer strictly above the surface."""
        return (self.nl > 0) & (self.nv > 0)

    @property
    def rv(self) -> Tensor:
        """r·v with r the mirror direction of l: ``2 (n·l)(n·v) − l·v`` (Nielsen eq 1)."""
        return (2.0 * self.nl * self.nv - self.lv).clamp(-1.0, 1.0)

    @property
    def shape(self) -> torch.Size:
        return self.nl.shape

    def to(self, *args, **kwargs) -> Angles:
        """Move/cast every field (``Tensor.to`` semantics)."""
        return Angles(*(None if (x := getattr(self, f)) is None else x.to(*args, **kwargs) for f in _FIELDS))

    def __getitem__(self, index) -> Angles:
        """Index the leading dimensions of every field alike (e.g. a boolean mask of samples)."""
        return Angles(*(None if (x := getattr(self, f)) is None else x[index] for f in _FIELDS))


_FIELDS = ("nl", "nv", "nh", "lh", "lv", "fresnel_lh")


def clamp_cos(x: Tensor, eps: float = 1e-6) -> Tensor:
    """A cosine safe to divide by: ``max(x, eps)``. Use only under a :attr:`Angles.front` mask."""
    return x.clamp_min(eps)


#: :func:`guarded_pow`'s floor: a base at or below it gives 0 (and no derivative).
POW_EPS = 1e-12


def guarded_pow_log(base: Tensor, exponent: Tensor | float) -> tuple[Tensor, Tensor]:
    """:func:`guarded_pow` and ``ln base`` where it is taken (0 elsewhere): ``∂/∂exponent`` of the power is their
    product, as automatic differentiation of :func:`guarded_pow` gives it — for closed-form Jacobians."""
    ok = base > POW_EPS
    safe = torch.where(ok, base, torch.ones_like(base))
    zero = torch.zeros_like(safe)
    return torch.where(ok, safe.pow(exponent), zero), torch.where(ok, torch.log(safe), zero)


def guarded_pow(base: Tensor, exponent: Tensor | float, eps: float = POW_EPS) -> Tensor:
    """``max(base, 0) ** exponent`` with finite value and gradient for base → 0 and any exponent ≥ 0.

    ``pow`` at a zero base has an infinite (or NaN) derivative with respect to the exponent and,
    for exponents below 1, with respect to the base; both branches are guarded with ``where``.
    """
    ok = base > eps
    safe = torch.where(ok, base, torch.ones_like(base))
    return torch.where(ok, safe.pow(exponent), torch.zeros_like(safe))


def check_angles(g, fn: str) -> None:
    """Raise ``TypeError`` naming ``fn`` unless ``g`` is an :class:`Angles`."""
    if not isinstance(g, Angles):
        raise TypeError(f"{fn}: g must be a materials.Angles, got {type(g).__name__}; build one with "
                        f"Angles.from_vectors(n, l, v) or Angles.from_cosines(nl, nv, lv)")


def as_param(x, like: Tensor, name: str, fn: str) -> Tensor:
    """A lobe argument as a tensor ``[..., C]``: floats become ``[1]`` tensors of ``like``'s dtype and
    device, 0-d tensors gain a dimension; anything else raises ``TypeError`` naming ``fn`` and ``name``."""
    if isinstance(x, (int, float)):
        return torch.full((1,), float(x), dtype=like.dtype, device=like.device)
    if not isinstance(x, Tensor):
        raise TypeError(f"{fn}: {name} must be a tensor or a float, got {type(x).__name__}")
    return x.reshape(1) if x.dim() == 0 else x
