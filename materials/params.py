"""Material parameters: what a model declares it needs, and the canonical maps that store them.

A model lists its parameters as :class:`ParamSpec` s; the renderer allocates and samples only those
maps and the solver optimises only those. The canonical specs below are the single source of each
parameter's name, channel count, range and default (DESIGN.md, "Parameters and their canonical
maps"). A model that needs a different default or linearity uses :func:`dataclasses.replace`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from .roughness import S_MAX


@dataclass(frozen=True)
class ParamSpec:
    """One material parameter.

    Attributes:
        name: canonical name (the map's file name stem).
        channels: 1 (scalar map) or 3 (RGB map).
        low, high: closed range of valid values (``high`` may be ``math.inf``).
        default: value used when a caller does not supply one.
        description: one line for docs and ``materials.available()``.
        linear: True when the BRDF is an affine function of this parameter, channel by channel,
            with every other parameter fixed. The solver may then eliminate it in closed form.
        unit: physical unit or ``"1"`` for dimensionless.
    """

    name: str
    channels: int
    low: float
    high: float
    default: float
    description: str
    linear: bool = False
    unit: str = "1"

    def full(self, shape: tuple[int, ...] = (), device=None, dtype=None) -> Tensor:
        """A tensor ``[*shape, channels]`` filled with the default."""
        return torch.full((*shape, self.channels), self.default, device=device, dtype=dtype)

    def check(self, value: Tensor, where: str = "") -> None:
        """Raise ``ValueError`` naming the parameter if ``value`` has the wrong channels or range."""
        prefix = f"{where}: " if where else ""
        if not isinstance(value, Tensor):
            raise TypeError(f"{prefix}parameter '{self.name}' must be a torch.Tensor, got {type(value).__name__}")
        if value.dim() == 0 or value.shape[-1] not in (1, self.channels):
            raise ValueError(
                f"{prefix}parameter '{self.name}' must have a last dimension of {self.channels}"
                f"{' (or 1, broadcast)' if self.channels != 1 else ''}, got shape {tuple(value.shape)}"
            )
        if value.numel() == 0:
            return
        # one pass and one synchronisation: min and max propagate NaN, and an inf is the min or the max
        lo, hi = (float(x) for x in torch.stack(torch.aminmax(value.detach())).tolist())
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"{prefix}parameter '{self.name}' contains NaN or inf values")
        if lo < self.low - 1e-6 or hi > self.high + 1e-6:
            raise ValueError(
                f"{prefix}parameter '{self.name}' must lie in [{self.low}, {self.high}], "
                f"got values in [{lo:.6g}, {hi:.6g}]; clamp it or fix its source"
            )


ALBEDO = ParamSpec("albedo", 3, 0.0, 1.0, 0.5, "diffuse reflectance ρ_d (linear RGB)", linear=True)
F0 = ParamSpec("f0", 3, 0.0, 1.0, 0.04, "specular reflectance at normal incidence (linear RGB)")
ROUGHNESS = ParamSpec("roughness", 1, 0.0, 1.0, 0.5, "perceptual roughness r (α = r²)")
ABSORPTION = ParamSpec(
    "absorption", 3, 0.0, math.inf, 0.0,
    "coat absorption α' of Gotanda 2012 eq 3 (α·d for the exact eq 2), per RGB channel",
)
COAT_IOR = ParamSpec("coat_ior", 1, 1.0, 3.0, 1.5, "refractive index η₁ of the coat layer")
COAT_ROUGHNESS = ParamSpec("coat_roughness", 1, 0.0, 1.0, 0.1, "perceptual roughness of the coat layer")
IOR = ParamSpec("ior", 1, 1.0, 3.0, 1.5, "refractive index η of the material (Nielsen's R_F)")
MIX = ParamSpec("mix", 1, 0.0, 1.0, 0.5, "Phong/Blinn-Phong interpolation α of Nielsen eq 3")
MASK = ParamSpec("mask", 1, 0.0, 1.0, 1.0, "surface mask / opacity (Schüler's alpha channel)")
#: Upper bound of the ``specular`` map: Nielsen eq 3's k_s replaces ρ_s times the lobe's energy-conserving
#: normalisation, which for the Phong lobe of eq 1 is (s + 2)/(2π); with ρ_s ≤ 1 and the sharpest exponent the
#: roughness conversions produce (s = S_MAX = 2^16) that is (S_MAX + 2)/(2π) = 10 430.7. A larger k_s reflects
#: more than it receives at normal incidence for every exponent in range. For eq 1-2 (ρ_s, normalisation
#: explicit) the bound is loose on purpose: ρ_s multiplies a dielectric R_F that is only f0(η) at normal
#: incidence (0.04 at η = 1.5), so a fitted ρ_s may well exceed 1. Bounded, f_r ≤ SPECULAR_MAX · (S_MAX + 2)/(2π)
#: ≈ 1.1e8 (eq 1's peak) stays far from float32 overflow (an unbounded map accepted 3e38 and returned inf).
SPECULAR_MAX = (S_MAX + 2.0) / (2.0 * math.pi)
SPECULAR = ParamSpec(
    "specular", 3, 0.0, SPECULAR_MAX, 1.0,
    "specular scale: ρ_s of Nielsen eq 1-2, k_s of eq 3 (absorbs the lobe normalisation), linear RGB",
    linear=True,
)

#: Every canonical parameter by name.
CANONICAL: dict[str, ParamSpec] = {
    p.name: p for p in (ALBEDO, F0, ROUGHNESS, ABSORPTION, COAT_IOR, COAT_ROUGHNESS, IOR, MIX, MASK, SPECULAR)
}


def check_params(specs: tuple[ParamSpec, ...], params: Mapping[str, Tensor], where: str) -> None:
    """Validate a parameter dict against a model's specs: missing names, channels and ranges."""
    missing = [s.name for s in specs if s.name not in params]
    if missing:
        raise ValueError(
            f"{where}: missing parameter(s) {missing}; this model needs {[s.name for s in specs]}"
        )
    for s in specs:
        s.check(params[s.name], where)
