"""Environment lights as data, and the maths shared by every model's environment response.

A model's response to an environment (Schüler's two hemispheres, Gotanda's spherical-harmonics
Oren-Nayar, Gotanda's layered image-based lighting) is defined by its paper and therefore lives
with that model (:meth:`materials.model.Model.environment`); this module only describes the
lights and the spherical-harmonics basis.

Units: :class:`HemisphereLight` carries *irradiances* E_upper, E_lower (Schüler's
``lerp(E_lower, E_upper, (1 + N·z)/2)`` is the irradiance on a surface of normal N).
:class:`SHLight` carries the order-2 (9-coefficient) projection of the incident *radiance*
L(ω) onto the real spherical harmonics, RGB: ``coeffs[9, 3]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


class Environment:
    """Marker base class of environment lights."""


@dataclass(frozen=True)
class HemisphereLight(Environment):
    """Schüler's two-hemisphere light: irradiance ``upper`` from above, ``lower`` from below.

    Attributes:
        upper: RGB irradiance of the sky hemisphere, ``[3]``, W/m² (or any consistent unit).
        lower: RGB irradiance of the ground hemisphere, ``[3]``.
        up: unit world up direction ``[3]`` (Schüler's z).
    """

    upper: Tensor
    lower: Tensor
    up: Tensor

    def __post_init__(self):
        for name in ("upper", "lower", "up"):
            x = getattr(self, name)
            if not isinstance(x, Tensor) or x.shape != (3,):
                raise ValueError(f"HemisphereLight.{name} must be a tensor of shape (3,), got {x!r}")
        if (self.upper < 0).any() or (self.lower < 0).any():
            raise ValueError("HemisphereLight irradiances must be non-negative")

    def irradiance(self, n: Tensor) -> Tensor:
        """Irradiance on a Lambertian surface of normal n ``[..., 3]`` → ``[..., 3]`` (Schüler appendix)."""
        t = 0.5 * (1.0 + (n * self.up.to(n)).sum(-1, keepdim=True))
        return self.lower.to(n) + t * (self.upper.to(n) - self.lower.to(n))


#: Ramamoorthi-Hanrahan (2001) convolution constants Â_l for the clamped cosine, l = 0, 1, 2.
COSINE_LOBE_SH = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)


def sh_basis(d: Tensor) -> Tensor:
    """Real spherical harmonics up to order 2 at unit directions ``d[..., 3]`` → ``[..., 9]``.

    Ordering (l, m): (0,0), (1,-1), (1,0), (1,1), (2,-2), (2,-1), (2,0), (2,1), (2,2) with
    Y_1,-1 ∝ y, Y_1,0 ∝ z, Y_1,1 ∝ x (the usual graphics convention).
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    c0 = 0.5 * math.sqrt(1.0 / math.pi)
    c1 = math.sqrt(3.0 / (4.0 * math.pi))
    c2 = 0.5 * math.sqrt(15.0 / math.pi)
    c3 = 0.25 * math.sqrt(5.0 / math.pi)
    c4 = 0.25 * math.sqrt(15.0 / math.pi)
    return torch.stack(
        [
            torch.full_like(x, c0),
            c1 * y, c1 * z, c1 * x,
            c2 * x * y, c2 * y * z, c3 * (3.0 * z * z - 1.0), c2 * x * z, c4 * (x * x - y * y),
        ],
        dim=-1,
    )


@dataclass(frozen=True)
class SHLight(Environment):
    """Distant environment radiance as order-2 spherical harmonics, ``coeffs[9, 3]`` (RGB)."""

    coeffs: Tensor

    def __post_init__(self):
        if not isinstance(self.coeffs, Tensor) or self.coeffs.shape != (9, 3):
            got = getattr(self.coeffs, "shape", self.coeffs)
            raise ValueError(f"SHLight.coeffs must be a tensor of shape (9, 3), got {got}")

    def band(self, degree: int) -> Tensor:
        """Coefficients of one band: degree 0 → ``[1, 3]``, 1 → ``[3, 3]``, 2 → ``[5, 3]``."""
        return self.coeffs[(0, 1, 4)[degree] : (1, 4, 9)[degree]]

    def radiance(self, d: Tensor) -> Tensor:
        """Incident radiance from direction d ``[..., 3]`` → ``[..., 3]``."""
        return sh_basis(d) @ self.coeffs.to(d)

    def irradiance(self, n: Tensor, scale: tuple = (1.0, 1.0, 1.0)) -> Tensor:
        """Irradiance E(n) ``[..., 3]`` on a surface of normal n (Ramamoorthi-Hanrahan 2001).

        ``scale`` multiplies the DC, linear and quadratic bands after the cosine convolution —
        the hook Gotanda 2012 eq 27-29 use to turn Lambert into Oren-Nayar; each entry may be a
        float or a tensor ``[..., 1]`` broadcasting against n.
        """
        y = sh_basis(n)
        c = self.coeffs.to(n)
        out = 0.0
        for degree, (lo, hi) in enumerate(((0, 1), (1, 4), (4, 9))):
            out = out + (COSINE_LOBE_SH[degree] * scale[degree]) * (y[..., lo:hi] @ c[lo:hi])
        return out

    @staticmethod
    def from_function(radiance_fn, samples: int = 20000, device=None, dtype=torch.float64) -> SHLight:
        """Project a radiance function ``fn(d[..., 3]) -> [..., 3]`` by Monte Carlo (stratified Fibonacci)."""
        i = torch.arange(samples, device=device, dtype=dtype) + 0.5
        z = 1.0 - 2.0 * i / samples
        phi = i * math.pi * (3.0 - math.sqrt(5.0))
        rxy = torch.sqrt((1.0 - z * z).clamp_min(0.0))
        d = torch.stack([rxy * torch.cos(phi), rxy * torch.sin(phi), z], -1)
        coeffs = (sh_basis(d).unsqueeze(-1) * radiance_fn(d).unsqueeze(-2)).mean(0) * (4.0 * math.pi)
        return SHLight(coeffs.to(torch.get_default_dtype()))
