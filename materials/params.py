"""Material parameters: what a model declares it needs, and the canonical maps that store them.

A model lists its parameters as :class:`ParamSpec` s; the renderer allocates and samples only those
maps and the solver optimises only those. The canonical specs below are the single source of everything
known about a parameter: name, channel count, range, default, its role in a fit, how its previews are
encoded, its observability threshold and prior unit in the fit, where an export stores it, and the value
the lobe figures show (DESIGN.md, "Parameters and their canonical maps"). The tables of ``capture`` that
need one of these read it from here, and ``docs/models.md``'s parameter table is generated from them
(:func:`markdown_table`, ``scripts/param_table.py``). A model that needs a different default or linearity uses
:func:`dataclasses.replace`. Adding a model with a new parameter means a new spec here and the model's file.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from .roughness import S_MAX

#: Roles of a parameter in a fit (Nielsen's stages in ``capture.brdf_fit``; the energy contract's reflectances):
#: the scale of the diffuse lobe, the scale of a specular lobe, a perceptual roughness (α = r², converted through
#: :mod:`materials.roughness`), or anything else that shapes a lobe.
ROLES = ("diffuse", "specular", "roughness", "shape")
#: Encodings of a parameter's 8-bit previews and atlas channels: colours are stored sRGB / gamma-encoded (the
#: atlas's ``transfer``), everything else linearly.
PREVIEW_TRANSFERS = ("srgb", "linear")
#: Observability threshold of a parameter that declares none: 2 % of its range (of 1 for a wider range).
DEFAULT_STD_FRACTION = 0.02


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
        role: one of :data:`ROLES`.
        shared: fitted as one value for the whole object by default, not per texel (a reconstruction's
            ``scalars``); an export stores it as a number per material, not as a map.
        transfer: one of :data:`PREVIEW_TRANSFERS`: how its previews and atlas channels are encoded.
        observable_std: posterior standard deviation (canonical units) below which the parameter counts as
            observable in a texel; None: :data:`DEFAULT_STD_FRACTION` of its range (see :attr:`threshold`).
        prior_unit: unit of the joint refinement's edge-preserving prior where it differs from the
            observability threshold; None: the threshold.
        export: where an exported material stores it (docs/export.md); None: not exported.
        diffuse_only: value an export writes for a model without this parameter (a diffuse-only model); None:
            the map is optional and left out.
        plot: value of the lobe figures (``capture.plots``) where it differs from ``default``.
    """

    name: str
    channels: int
    low: float
    high: float
    default: float
    description: str
    linear: bool = False
    unit: str = "1"
    role: str = "shape"
    shared: bool = False
    transfer: str = "linear"
    observable_std: float | None = None
    prior_unit: float | None = None
    export: str | None = None
    diffuse_only: float | None = None
    plot: float | None = None

    def __post_init__(self):
        if self.role not in ROLES:
            raise ValueError(f"ParamSpec '{self.name}': role must be one of {ROLES}, got {self.role!r}")
        if self.transfer not in PREVIEW_TRANSFERS:
            raise ValueError(f"ParamSpec '{self.name}': transfer must be one of {PREVIEW_TRANSFERS}, "
                             f"got {self.transfer!r}")
        for field in ("default", "diffuse_only", "plot"):
            v = getattr(self, field)
            if v is not None and not self.low <= v <= self.high:
                raise ValueError(f"ParamSpec '{self.name}': {field} {v} lies outside [{self.low}, {self.high}]")
        for field in ("observable_std", "prior_unit"):
            v = getattr(self, field)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"ParamSpec '{self.name}': {field} must be a positive number, got {v!r}")

    @property
    def threshold(self) -> float:
        """The observability threshold (canonical units): ``observable_std``, or :data:`DEFAULT_STD_FRACTION` of
        the range (of 1 for a wider range)."""
        if self.observable_std is not None:
            return float(self.observable_std)
        return DEFAULT_STD_FRACTION * min(self.high - self.low, 1.0)

    @property
    def plot_value(self) -> float:
        """The value of the lobe figures: ``plot``, or the default."""
        return float(self.default if self.plot is None else self.plot)

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


#: Observability thresholds (``observable_std``): 0.01 for the reflectances, 0.02 (the default rule) for
#: roughness, mix and mask, 0.05 for η, coat η and absorption (docs/reconstruction.md, "Observability").
#: The albedo's prior unit is 0.3: a texture, whose neighbours differ by design; in units of 0.3 (a third of
#: its range) the prior smooths differences below 0.09 and charges larger ones linearly. Measured all-texel
#: albedo RMSE with the unit 0.01 / 0.03 / 0.1 / 0.3 / 1 / 3 (and no albedo prior): default scene 0.0106 /
#: 0.0097 / 0.0090 / 0.0089 / 0.0102 / 0.0116 (0.0161); with 64² maps 0.0147 / 0.0116 / 0.0085 / 0.0063 /
#: 0.0062 / 0.0061 (0.0084); docs/log.md, "the albedo joins the joint prior".
#: ``diffuse_only``: f0 = 0 and roughness = 1 export a diffuse-only model as no specular reflection.
#: ``plot``: the lobe figures show a mid-rough dielectric (r = 0.4), a visible coat (absorption 0.05,
#: coat roughness 0.2) and Nielsen's k_s = 0.2, so that every lobe is visible next to the diffuse.
ALBEDO = ParamSpec(
    "albedo", 3, 0.0, 1.0, 0.5, "diffuse reflectance ρ_d (linear RGB)", linear=True,
    role="diffuse", transfer="srgb", observable_std=0.01, prior_unit=0.3, export="atlas tex1 RGB",
)
F0 = ParamSpec(
    "f0", 3, 0.0, 1.0, 0.04, "specular reflectance at normal incidence (linear RGB)",
    role="specular", transfer="srgb", observable_std=0.01, export="atlas tex2 RGB", diffuse_only=0.0,
)
ROUGHNESS = ParamSpec(
    "roughness", 1, 0.0, 1.0, 0.5, "perceptual roughness r (α = r²)",
    role="roughness", observable_std=0.02, export="atlas tex2 A (glossiness g)", diffuse_only=1.0, plot=0.4,
)
ABSORPTION = ParamSpec(
    "absorption", 3, 0.0, math.inf, 0.0,
    "coat absorption α' of Gotanda 2012 eq 3 (α·d for the exact eq 2), per RGB channel",
    observable_std=0.05, export="absorption.exr RGB", plot=0.05,
)
COAT_IOR = ParamSpec(
    "coat_ior", 1, 1.0, 3.0, 1.5, "refractive index η₁ of the coat layer",
    shared=True, observable_std=0.05, export="coat.exr R (one value per material)",
)
COAT_ROUGHNESS = ParamSpec(
    "coat_roughness", 1, 0.0, 1.0, 0.1, "perceptual roughness of the coat layer",
    role="roughness", shared=True, observable_std=0.02, export="coat.exr G (one value per material)", plot=0.2,
)
IOR = ParamSpec("ior", 1, 1.0, 3.0, 1.5, "refractive index η of the material (Nielsen's R_F)", observable_std=0.05)
MIX = ParamSpec("mix", 1, 0.0, 1.0, 0.5, "Phong/Blinn-Phong interpolation α of Nielsen eq 3", observable_std=0.02)
MASK = ParamSpec(
    "mask", 1, 0.0, 1.0, 1.0, "surface mask / opacity (Schüler's alpha channel)",
    observable_std=0.02, export="atlas tex1 A",
)
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
    linear=True, role="specular", observable_std=0.01, plot=0.2,
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


def preview_transfer(name: str) -> str:
    """How the 8-bit preview of the map ``name`` is encoded: its spec's ``transfer``; ``"linear"`` for a map that
    is no parameter (coverage, confidence)."""
    spec = CANONICAL.get(name)
    return spec.transfer if spec is not None else "linear"


def _number(x: float) -> str:
    return "∞" if x == math.inf else f"{x:.6g}"


def markdown_table(specs: Mapping[str, ParamSpec] | None = None) -> str:
    """The parameter table of ``docs/models.md`` (a markdown table, one row per spec, :data:`CANONICAL` by
    default), generated so that the page cannot drift from the specs."""
    specs = CANONICAL if specs is None else specs
    head = ("| parameter | channels | range | default | role | fitted | preview | observable below | prior unit "
            "| export (diffuse-only value) | lobe figures | meaning |")
    rows = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for p in specs.values():
        export = p.export or "—"
        if p.diffuse_only is not None:
            export += f" ({_number(p.diffuse_only)})"
        role = p.role + (", closed form" if p.linear else "")
        rows.append(
            f"| `{p.name}` | {p.channels} | [{_number(p.low)}, {_number(p.high)}] | {_number(p.default)} | {role} "
            f"| {'per object' if p.shared else 'per texel'} | {p.transfer} | {_number(p.threshold)} "
            f"| {_number(p.prior_unit) if p.prior_unit is not None else '= threshold'} | {export} "
            f"| {_number(p.plot_value)} | {p.description} |"
        )
    return "\n".join(rows)
