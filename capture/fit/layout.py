"""Layout of a model's parameters in the per-texel vector θ, the canonical ↔ θ transforms, and the fit's result.

Parameters stay in range through their parameterisation, not by clamping: a parameter with range
[lo, hi] is ``lo + (hi − lo)·sigmoid(θ)``, one with range [lo, ∞) is ``lo + softplus(θ)``
(:class:`Layout`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from materials.model import Model
from materials.params import ParamSpec

__all__ = ["ACC", "MAX_STEP", "INVERSE_BLOCK", "SolverError", "Layout", "FitResult", "bounded", "to_canonical",
           "from_canonical", "dcanonical", "param_groups"]


_EPS_BOUND = 1e-6
#: Solver bookkeeping dtype (θ, normal equations, costs); the model is evaluated in the observations' dtype.
ACC = torch.float64
#: Largest LM step per iteration and θ component (logit/softplus units), see solve_fast.
MAX_STEP = 1.0
#: Texels per run when per-texel ``[P, P]`` blocks are damped and inverted (the joint solves' preconditioner, the
#: posterior's covariances): 2¹⁶ × 7 × 7 float64 are 25 MB of temporaries at a time, which stay in the allocator's
#: reuse, where whole copies were one or more ``[T, P, P]`` arrays of new pages (1.6 GB each on 2048² maps).
INVERSE_BLOCK = 1 << 16


class SolverError(ValueError):
    """Bad solver input: unknown loss/schedule, maps that do not fit the model or the observations."""


# -- parameterisation -----------------------------------------------------------------------------
def bounded(spec: ParamSpec) -> bool:
    """True for a parameter with a finite upper bound (sigmoid parameterisation), False for [lo, ∞) (softplus)."""
    return math.isfinite(spec.high)


def to_canonical(spec: ParamSpec, theta: Tensor) -> Tensor:
    """Unconstrained θ → canonical value in the spec's range (sigmoid or softplus)."""
    if bounded(spec):
        return spec.low + (spec.high - spec.low) * torch.sigmoid(theta)
    return spec.low + F.softplus(theta)


def from_canonical(spec: ParamSpec, p: Tensor) -> Tensor:
    """Canonical value → θ (inverse of :func:`to_canonical`), the value kept ``1e-6`` inside the range."""
    if bounded(spec):
        u = ((p - spec.low) / (spec.high - spec.low)).clamp(_EPS_BOUND, 1 - _EPS_BOUND)
        return torch.log(u) - torch.log1p(-u)
    x = (p - spec.low).clamp_min(_EPS_BOUND)
    return x + torch.log(-torch.expm1(-x))


def dcanonical(spec: ParamSpec, theta: Tensor) -> Tensor:
    """dp/dθ of :func:`to_canonical` (> 0)."""
    if bounded(spec):
        s = torch.sigmoid(theta)
        return (spec.high - spec.low) * s * (1 - s)
    return torch.sigmoid(theta)


@dataclass
class Layout:
    """How a model's parameters are packed into one per-texel vector θ ``[..., P]``.

    Each parameter occupies ``channels`` consecutive columns, in ``model.params`` order.
    """

    specs: tuple[ParamSpec, ...]
    offsets: tuple[int, ...]
    P: int

    @staticmethod
    def of(model: Model) -> Layout:
        offs, o = [], 0
        for s in model.params:
            offs.append(o)
            o += s.channels
        return Layout(tuple(model.params), tuple(offs), o)

    @property
    def affine(self) -> bool:
        """Whether every parameter is flagged linear: the model is affine in its parameters (Lambert), so its
        Jacobian is constant and a footprint step costs sparse products only."""
        return all(s.linear for s in self.specs)

    def cols(self, name: str) -> list[int]:
        for s, o in zip(self.specs, self.offsets, strict=True):
            if s.name == name:
                return list(range(o, o + s.channels))
        raise KeyError(name)

    def unpack(self, theta: Tensor) -> dict[str, Tensor]:
        """θ ``[..., P]`` → canonical parameters ``name → [..., C]``."""
        so = zip(self.specs, self.offsets, strict=True)
        return {s.name: to_canonical(s, theta[..., o:o + s.channels]) for s, o in so}

    def canonical(self, theta: Tensor) -> Tensor:
        """θ ``[..., P]`` → the canonical parameters packed in the same columns ``[..., P]``."""
        so = zip(self.specs, self.offsets, strict=True)
        return torch.cat([to_canonical(s, theta[..., o:o + s.channels]) for s, o in so], -1)

    def pack(self, params: Mapping[str, Tensor]) -> Tensor:
        """Canonical parameters ``name → [..., C or 1]`` → θ ``[..., P]``."""
        parts = []
        for s in self.specs:
            x = params[s.name]
            if x.shape[-1] == 1 and s.channels > 1:
                x = x.expand(*x.shape[:-1], s.channels)
            parts.append(from_canonical(s, x))
        return torch.cat(parts, -1)

    def split(self, x: Tensor) -> dict[str, Tensor]:
        """Canonical values packed ``[..., P]`` → ``name → [..., C]`` (no transform)."""
        return {s.name: x[..., o:o + s.channels] for s, o in zip(self.specs, self.offsets, strict=True)}

    def dcanonical(self, theta: Tensor) -> Tensor:
        """dp/dθ per column ``[..., P]``."""
        so = zip(self.specs, self.offsets, strict=True)
        return torch.cat([dcanonical(s, theta[..., o:o + s.channels]) for s, o in so], -1)


@dataclass
class FitResult:
    """Output of a solver.

    Attributes:
        maps: canonical maps ``name → [H, W, C]``, holes filled (see ``filled``).
        observed: ``[H, W]`` bool, texels with at least one valid sample.
        unobservable: ``name → [H, W]`` bool, observed texels where the photos do not constrain
            the parameter (value filled from neighbours, flagged).
        filled: ``name → [H, W]`` bool, texels whose value was filled: unobserved ones, and unobservable
            ones unless reflectance sharing estimated them (then they keep the shared value, still flagged
            in ``unobservable``).
        confidence: ``name → [H, W, C]`` posterior standard deviation of the parameter (canonical
            units; 0 for a perfect noise-free fit), NaN where filled.
        sensitivity: ``name → [H, W]`` relative residual change for a 0.1 change of the parameter.
        history: total cost after each iteration (robust, weighted, per sample-channel mean).
        iterations: iterations run; time_s: wall time of the solve; solver: "fast" or "adam".
        info: solver-specific numbers (grid time, LM time, accepted fraction, ...).
        raw: the fitted maps before filling (what best explains the photos; use for re-renders).
    """

    maps: dict[str, Tensor]
    observed: Tensor
    unobservable: dict[str, Tensor]
    filled: dict[str, Tensor]
    confidence: dict[str, Tensor]
    sensitivity: dict[str, Tensor]
    history: list[float]
    iterations: int
    time_s: float
    solver: str
    info: dict = field(default_factory=dict)
    raw: dict = field(default_factory=dict)

    def to(self, device) -> FitResult:
        """The result with every map on ``device`` (the solver's numbers — history, info — as they are)."""
        def mv(maps: dict) -> dict:
            return {k: v.to(device) for k, v in maps.items()}
        return replace(self, maps=mv(self.maps), observed=self.observed.to(device), unobservable=mv(self.unobservable),
                       filled=mv(self.filled), confidence=mv(self.confidence), sensitivity=mv(self.sensitivity),
                       raw=mv(self.raw))


def param_groups(layout: Layout) -> list[list[int]]:
    """The θ columns of each parameter. A caller freezes parameters by leaving their group out; :func:`jacobian`
    fills the columns of the groups it is given and leaves the others zero."""
    return [list(range(o, o + s.channels)) for s, o in zip(layout.specs, layout.offsets, strict=True)]
