"""Lambertian diffuse reflection: f_r = ρ_d / π.

The reference every diffuse model reduces to (Oren-Nayar at σ = 0, Gotanda's diffuse at
shininess → ∞) and Schüler's diffuse term ``k_diffuse Σ N·L E`` (Schüler 2.5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from .environment import Environment, HemisphereLight, SHLight
from .geometry import Angles
from .model import Model, register
from .params import ALBEDO

INV_PI = 1.0 / math.pi


def lambert(g: Angles, albedo: Tensor) -> Tensor:
    """Lambert BRDF ρ/π in 1/sr, ``[..., C]``; 0 unless n·l > 0 and n·v > 0.

    Args:
        g: shading cosines ``[..., 1]``.
        albedo: diffuse reflectance ρ_d ∈ [0, 1], ``[..., C]``.
    """
    return torch.where(g.front, albedo * INV_PI, torch.zeros_like(albedo))


@register("lambert", "Lambertian diffuse ρ/π; the baseline every diffuse model reduces to")
class Lambert(Model):
    """Pure Lambertian diffuse material (parameter: ``albedo``)."""

    params = (ALBEDO,)

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return lambert(g, p["albedo"])

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """``ρ (n·l)⁺/π`` on the front side; each channel's albedo acts on that channel alone, by ``(n·l)⁺/π`` (a
        diagonal derivative)."""
        if not self.shades_as(Lambert):
            return None
        albedo = p["albedo"]
        w = torch.where(g.front, g.nl.clamp_min(0.0) * INV_PI, torch.zeros_like(g.nl))   # [..., 1]
        value = albedo * w
        return value, {"albedo": w.expand_as(value)}

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        """ρ/π · E(n): Schüler's ``k_diffuse lerp(E_lower, E_upper, (1 + N·z)/2)`` for a
        :class:`HemisphereLight` (Schüler appendix), or the SH irradiance for an :class:`SHLight`."""
        visible = (n * v).sum(-1, keepdim=True) > 0
        if isinstance(env, (HemisphereLight, SHLight)):
            e = env.irradiance(n)
            return torch.where(visible, p["albedo"] * INV_PI * e, torch.zeros_like(e))
        return super().environment(env, n, v, p)
