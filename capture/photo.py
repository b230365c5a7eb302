"""The photo model: what a camera makes of the radiance reaching it. Every stage is switchable.

In order, for a linear radiance image L ``[H, W, C]`` (W/(m² sr) in the lights' units):

1. **exposure**: signal ``s = exposure · L`` in units of the sensor's saturation (s = 1 fills
   the well). DESIGN.md: a linear EXR pixel is exposure · L.
2. **shot noise** (``full_well`` electrons at s = 1; None = off): the sensor counts
   ``Poisson(s · full_well)`` electrons, so ``s' = Poisson(s · full_well) / full_well`` has mean s
   and variance ``s / full_well`` (variance ∝ signal; the gain is 1/full_well in s units per
   electron). Sampled with :func:`torch.poisson` (exact Poisson, not a Gaussian approximation).
3. **read noise** (``read_noise`` = σ in s units; 0 = off): ``s'' = s' + σ · N(0, 1)``,
   independent per pixel and channel. Total variance ``s/full_well + σ²``.
4. **clipping** (``clip``): a pixel whose signal exceeds 1 in any channel is *clipped*: the
   channels above 1 become 1 and the pixel is flagged in the returned mask. The mask is exact:
   ``clipped = any_c(s''_c > 1)``. Negative values (read noise) are kept for EXR (an unbiased raw
   value) and become 0 in a PNG.
5. **encoding**: ``"linear"`` → float32 (``half`` rounds to float16, what a half EXR stores);
   ``"srgb"`` → the sRGB (IEC 61966-2-1) code ``q = round(encode(clamp(s'', 0, 1)) · (2^bits − 1))``,
   returned *decoded* (``decode(q / (2^bits − 1))``, float32) — exactly the value
   :func:`renderer.imageio.read_png` returns for that code, so writing it with
   :func:`renderer.imageio.write_png` reproduces ``q`` and reading it back reproduces the image.

A PNG cannot hold values above 1, so ``encoding="srgb"`` requires ``clip=True``.

Randomness: :meth:`PhotoModel.apply` takes a ``torch.Generator`` (or an int seed); the same
generator state gives the same image. Noise is drawn on the CPU in float64 and the result moved
to the input's device, so results do not depend on the device.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from renderer.imageio import decode, encode

__all__ = ["PhotoModel", "PhotoError", "quantize_srgb"]

ENCODINGS = ("linear", "srgb")


class PhotoError(ValueError):
    """Invalid photo-model settings or input (the message names the field)."""


def quantize_srgb(x: Tensor, bits: int = 8) -> tuple[Tensor, Tensor]:
    """sRGB-encode and quantise linear values to integer codes, as :func:`renderer.imageio.write_png` does.

    Args:
        x: linear values, any shape (clamped to [0, 1]).
        bits: 8 or 16.

    Returns:
        (codes int64 in [0, 2^bits − 1], decoded float32 linear values ``decode(code / (2^bits − 1))``
        computed with the same float32 arithmetic as :func:`renderer.imageio.read_png`).
    """
    if bits not in (8, 16):
        raise PhotoError(f"bits must be 8 or 16, got {bits!r}")
    top = (1 << bits) - 1
    xc = x.detach().to("cpu", torch.float64).clamp(0.0, 1.0)
    code = torch.round(encode(xc, "srgb").clamp(0.0, 1.0) * top).to(torch.int64)
    # read_png: codes.astype(float32) / float32(top), then kornia's sRGB decode
    val = torch.from_numpy(code.numpy().astype(np.float32) / np.float32(top))
    return code, decode(val, "srgb")


@dataclass
class PhotoModel:
    """Camera photo model (module docstring gives the stages and their order).

    Attributes:
        exposure: positive multiplier on radiance (dimensionless; s = exposure · L).
        full_well: electrons at s = 1 (shot-noise variance s/full_well); None disables shot noise.
        read_noise: σ of the Gaussian read noise in s units (≥ 0; 0 disables it).
        clip: clip highlights at s = 1 and flag them (required for "srgb").
        encoding: "linear" (float, EXR) or "srgb" (integer codes, PNG).
        bits: PNG bit depth for "srgb" (8 or 16).
        half: for "linear", round to float16 (a half-float EXR).

    The default is the ideal camera: exposure 1, no noise, no clipping, linear float.
    """

    exposure: float = 1.0
    full_well: float | None = None
    read_noise: float = 0.0
    clip: bool = False
    encoding: str = "linear"
    bits: int = 8
    half: bool = False

    def __post_init__(self):
        if isinstance(self.exposure, bool) or not (isinstance(self.exposure, (int, float)) and
                                                   math.isfinite(self.exposure) and self.exposure > 0):
            raise PhotoError(f"PhotoModel.exposure must be a positive finite number, got {self.exposure!r}")
        if self.full_well is not None and not (isinstance(self.full_well, (int, float)) and
                                               math.isfinite(self.full_well) and self.full_well > 0):
            raise PhotoError(f"PhotoModel.full_well must be a positive number of electrons or None, got "
                             f"{self.full_well!r}")
        if not (isinstance(self.read_noise, (int, float)) and math.isfinite(self.read_noise) and self.read_noise >= 0):
            raise PhotoError(f"PhotoModel.read_noise must be a finite σ ≥ 0, got {self.read_noise!r}")
        if self.encoding not in ENCODINGS:
            raise PhotoError(f"PhotoModel.encoding must be one of {ENCODINGS}, got {self.encoding!r}")
        if self.bits not in (8, 16):
            raise PhotoError(f"PhotoModel.bits must be 8 or 16, got {self.bits!r}")
        if self.encoding == "srgb" and not self.clip:
            raise PhotoError("PhotoModel: encoding 'srgb' (PNG) cannot store values above 1; set clip=True "
                             "or use encoding 'linear'")
        self.exposure = float(self.exposure)

    @property
    def noise_free(self) -> bool:
        return self.full_well is None and self.read_noise == 0

    @property
    def saturation(self) -> float | int | None:
        """The dataset's saturation level in file units: the top code for "srgb", 1.0 if clipping, else None."""
        if self.encoding == "srgb":
            return (1 << self.bits) - 1
        return 1.0 if self.clip else None

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> PhotoModel:
        if not isinstance(d, dict):
            raise PhotoError(f"PhotoModel.from_dict: expected a dict, got {type(d).__name__}")
        unknown = set(d) - set(PhotoModel.__dataclass_fields__)
        if unknown:
            raise PhotoError(f"PhotoModel.from_dict: unknown field(s) {sorted(unknown)}")
        return PhotoModel(**d)

    def variance(self, signal: Tensor) -> Tensor:
        """Noise variance at signal ``s`` (before clipping and quantisation): s/full_well + σ²."""
        var = torch.full_like(signal, self.read_noise**2)
        if self.full_well is not None:
            var = var + signal.clamp_min(0) / self.full_well
        return var

    def apply(self, radiance: Tensor, rng: torch.Generator | int | None = None) -> tuple[Tensor, Tensor]:
        """Make a photo of ``radiance``.

        Args:
            radiance: linear radiance ``[H, W, C]`` (C = 1 or 3), finite, ≥ 0 (tiny negative values
                from round-off are clamped to 0).
            rng: a ``torch.Generator`` (CPU) or an int seed; required when noise is on.

        Returns:
            ``(image [H, W, C] float32, clipped [H, W] bool)`` on the input's device: the file values
            (see module docstring) and the exact mask of pixels clipped in some channel.

        Raises:
            PhotoError: bad shape, non-finite or clearly negative radiance, noise without rng.
        """
        if not isinstance(radiance, Tensor) or radiance.dim() != 3 or radiance.shape[-1] not in (1, 3):
            raise PhotoError(f"PhotoModel.apply: radiance must be a tensor [H, W, C] with C = 1 or 3, got "
                             f"{getattr(radiance, 'shape', type(radiance).__name__)}")
        if not torch.isfinite(radiance).all():
            raise PhotoError(f"PhotoModel.apply: radiance has {int((~torch.isfinite(radiance)).sum())} NaN/inf "
                             f"value(s); fix the renderer input")
        device = radiance.device
        L = radiance.detach().to("cpu", torch.float64)
        if float(L.min()) < -1e-6 * max(1.0, float(L.abs().max())):
            raise PhotoError(f"PhotoModel.apply: radiance must be ≥ 0, got min {float(L.min()):.6g}")
        s = self.exposure * L.clamp_min(0.0)
        if not self.noise_free:
            if rng is None:
                raise PhotoError("PhotoModel.apply: noise is on; pass rng (a torch.Generator or an int seed)")
            if isinstance(rng, int) and not isinstance(rng, bool):
                rng = torch.Generator().manual_seed(rng)
            if not isinstance(rng, torch.Generator):
                raise PhotoError(f"PhotoModel.apply: rng must be a torch.Generator or an int, got {type(rng).__name__}")
            if self.full_well is not None:
                s = torch.poisson(s * self.full_well, generator=rng) / self.full_well
            if self.read_noise > 0:
                s = s + self.read_noise * torch.randn(s.shape, generator=rng, dtype=torch.float64)
        if self.clip:
            clipped = (s > 1.0).any(-1)
            s = s.clamp_max(1.0)
        else:
            clipped = torch.zeros(s.shape[:2], dtype=torch.bool)
        if self.encoding == "srgb":
            _, img = quantize_srgb(s, self.bits)
        elif self.half:
            img = s.to(torch.float16).to(torch.float32)
        else:
            img = s.to(torch.float32)
        return img.to(device), clipped.to(device)
