"""Reference specular reflectances: Schüler's Table 2.5.1 as named presets.

Schüler (ShaderX7 2.5, "An Efficient and Physically Plausible Real-Time Shading Model"), Table 2.5.1:
"Reflectivity and corresponding specular color by gamma conversion of selected materials", derived
from LuxPop spectral data. Each row lists the normal-incidence reflectance (a single value for the
dielectrics, a min–max range for the rest) and the 8-bit texture value that encodes it under the
paper's display gamma 2.2: ``code = 255 · f0^(1/2.2)``, ``f0 = (code/255)^2.2``.

=============  ===================  ===============  ====================================
name           reflectance listed   gray / colour    f0 used here (linear RGB)
=============  ===================  ===============  ====================================
water          0.02                 44               0.02
glass          0.03                 56               0.03
polystyrene    0.05                 66               0.05  (typical plastic / organic)
calcite        0.06                 72               0.06  (typical rock mineral)
alumina        0.08                 80               0.08  (typical rock mineral; sapphire, ruby)
diamond        0.17–0.18            114;115;117      colour decoded: 0.170, 0.173, 0.180
silicon        0.34–0.49            157;163;187      colour decoded: 0.344, 0.374, 0.505
copper         0.49–0.92            245;214;184      colour decoded: 0.916, 0.680, 0.488
gold           0.39–0.96            251;233;166      colour decoded: 0.966, 0.820, 0.389
silver         0.94–0.99            252;250;239      colour decoded: 0.974, 0.957, 0.867
=============  ===================  ===============  ====================================

Decisions and checks (OCR of ``seeds/schuler-efficient-shading-model.md``, table near the end):

- Single-value rows are gray: ``f0`` is the listed reflectance in all three channels, and the listed
  gray level is kept as ``code``. With the listed values rounded to 2 decimals and the codes to
  integers, every gray row is consistent with gamma 2.2: e.g. polystyrene 255·0.05^(1/2.2) = 65.3 → 66
  and alumina 255·0.08^(1/2.2) = 80.9 → 80 lie within the rounding of the listed reflectance
  (±0.005); glass (0.03 → 51.8, listed 56) only at the edge of it (0.035 → 55.6).
- Coloured rows: ``f0`` is the listed colour decoded by gamma 2.2 — the colour is the only RGB
  information the table gives. The listed range is a *spectral* range (min–max over wavelengths),
  not the channel range: it matches the decoded channels' min–max for diamond, copper and gold
  (copper's 245;214;184 decodes to 0.916, 0.680, 0.488 ↔ 0.49–0.92), but not for silicon (blue
  187 decodes to 0.505 against 0.49) and silver (239 decodes to 0.867 against 0.94). Those two rows
  carry ``consistent=False``; their colour is used as printed.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: The paper's display gamma.
GAMMA = 2.2

# name: (kind, listed reflectance (lo, hi), listed 8-bit code(s), note)
_TABLE_2_5_1 = {
    "water": ("dielectric", (0.02, 0.02), (44,), ""),
    "glass": ("dielectric", (0.03, 0.03), (56,), ""),
    "polystyrene": ("dielectric", (0.05, 0.05), (66,), "typical for plastics and organic materials"),
    "calcite": ("dielectric", (0.06, 0.06), (72,), "typical for rock minerals"),
    "alumina": ("dielectric", (0.08, 0.08), (80,), "typical for rock minerals; sapphires and rubies"),
    "diamond": ("dielectric", (0.17, 0.18), (114, 115, 117), ""),
    "silicon": ("semiconductor", (0.34, 0.49), (157, 163, 187), ""),
    "copper": ("metal", (0.49, 0.92), (245, 214, 184), "pure and clean metal"),
    "gold": ("metal", (0.39, 0.96), (251, 233, 166), "pure and clean metal"),
    "silver": ("metal", (0.94, 0.99), (252, 250, 239), "pure and clean metal"),
}

#: Rows whose listed colour does not decode (gamma 2.2) into the listed reflectance range.
_INCONSISTENT = frozenset({"silicon", "silver"})


def _decode_code(code: int) -> float:
    return (code / 255.0) ** GAMMA


def _build() -> dict[str, dict]:
    out = {}
    for name, (kind, (lo, hi), codes, note) in _TABLE_2_5_1.items():
        code = tuple(codes) * 3 if len(codes) == 1 else tuple(codes)
        f0 = (lo, lo, lo) if len(codes) == 1 else tuple(_decode_code(c) for c in codes)
        out[name] = {
            "name": name,
            "kind": kind,
            "f0": f0,
            "reflectance": (lo, hi),
            "code": code,
            "consistent": name not in _INCONSISTENT,
            "note": note,
            "source": "Schüler 2009, ShaderX7 2.5, Table 2.5.1 (LuxPop spectral data), gamma 2.2",
        }
    return out


#: name → preset dict (plain Python values; see :func:`preset` for tensors):
#: ``f0`` (3 floats, linear RGB in [0, 1]), ``reflectance`` (listed (lo, hi); lo = hi for single
#: values), ``code`` (listed 8-bit gamma-2.2 value per RGB channel), ``kind`` (dielectric,
#: semiconductor, metal), ``consistent`` (listed colour decodes into the listed range), ``note``, ``source``.
PRESETS: dict[str, dict] = _build()


def names() -> list[str]:
    """Preset names in table order."""
    return list(PRESETS)


def preset(name: str, dtype: torch.dtype | None = None, device=None) -> dict:
    """One Table 2.5.1 preset, as a fresh dict whose ``f0`` is a tensor ``[3]`` (linear RGB).

    Args:
        name: case-insensitive preset name, e.g. ``"copper"``.
        dtype, device: of the ``f0`` tensor (default float dtype, CPU).

    Raises:
        KeyError: unknown name; the message lists the available names.
    """
    if not isinstance(name, str) or name.strip().lower() not in PRESETS:
        raise KeyError(f"unknown reflectance preset {name!r}; available: {', '.join(PRESETS)}")
    p = dict(PRESETS[name.strip().lower()])
    p["f0"] = torch.tensor(p["f0"], dtype=dtype or torch.get_default_dtype(), device=device)
    return p


def f0(name: str, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Shortcut: the preset's linear RGB f0 tensor ``[3]``."""
    return preset(name, dtype=dtype, device=device)["f0"]
