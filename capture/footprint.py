"""Pixel footprints: how a camera forms a pixel, as the fit models it.

A camera pixel integrates the radiance over its square (a box filter, DESIGN.md "Data flow"); a photo's pixel is
the *area average* of the radiance over its footprint on the surface, not the radiance at the point its centre
sees. Where a pixel covers several texels (a texture seen from far or at a grazing angle) the two differ by the
texture's variation inside the pixel — the difference between fitting photos and fitting the fit's own
one-ray-per-pixel renders.

:func:`observe_footprints` builds, for every view, the valid pixels and their sub-pixel samples:

1. From the pixel-centre G-buffer, each pixel's **texel footprint** ``f``: the larger of the lengths of the
   texture-space derivatives ``∂(u·W_map, v·H_map)/∂x`` and ``/∂y`` (texels per pixel step), by central
   differences of the centre rays' UVs (one-sided where a neighbour leaves the surface).
2. Two **sample counts** per pixel, each ``k × k`` at the centres of a regular grid of strata over the pixel (the
   midpoint rule of the box filter's integral), capped at :data:`FOOTPRINT_MAX`:

   * **rays**, for the shading (highlights, falloff, shadow edges, which vary inside a pixel even on a uniform
     material): the midpoint rule with k × k points errs by about ``c / (24 k²)`` of the pixel's value, ``c`` its
     relative second difference across the pixel, read off the photo itself
     (``max(|I(x+1) + I(x−1) − 2 I(x)|, same in y) / I``), so ``k = ceil(sqrt(c / (24 · FOOTPRINT_TOLERANCE)))``.
     In a photo noisier than the fit's noise model the part of each difference its measured noise explains is left
     out (:func:`photo_noise`, :func:`_curvature`): noise is not curvature. The photo's differences also hold the
     texture's, which texture sub-samples can integrate without rays: for a model affine in its parameters
     (Lambert) the shading alone is known before any fit — the model rendered at the pixel centres with each
     parameter at 1 in turn (:func:`shading_bases`) — and its curvature sets the rays, the photo's the texture
     sub-samples (at least as many per axis as it would have asked rays);
   * **texture sub-samples**, for the maps: ``kt = ceil(f / FOOTPRINT_SPACING)``, so that neighbouring samples are
     at most :data:`FOOTPRINT_SPACING` texels apart, capped at :data:`FOOTPRINT_TEXTURE_MAX` (they cost no ray, only
     operator entries). A pixel much smaller than a texel needs one: the maps are
     read bilinearly, and the box average of a bilinear interpolant over a square inside one bilinear cell is its
     value at the square's centre, exactly.

   Pixels on silhouettes, UV seams or depth edges (a neighbour misses, jumps in UV by more than
   :data:`SEAM_TEXELS` texels or in depth) take :data:`FOOTPRINT_MAX` rays, each its own texture sample.
3. Each ray is cast (:func:`renderer.gbuffer.render_footprint`) and shaded once; its stratum is read at
   ``m × m`` texture sub-samples, ``m = ceil(kt / k)``, located without rays on the plane of the face the ray hit
   (:func:`renderer.gbuffer.face_uv`, exact inside the face, the face's UV map continued a fraction of a pixel
   beyond it) and read bilinearly (:func:`texture_footprints`). The ray's sample then reads the maps as the
   weighted sum of its distinct texels — its *texture footprint* — and its radiance is the model at those averaged
   parameters under the ray's own shading. For a model affine in its parameters (Lambert) that is the exact
   stratum average whenever the shading is constant over the stratum; for others it is the first-order term of
   the parameters' variation inside a stratum. This is what makes the footprints cheap: on the 256² Mitsuba torus
   a pixel covers ~2 texels, so every pixel needed 16 rays before (texture and shading alike); the shading asks one
   ray of half the pixels, and 0.71 M rays replace 2.0 M at the same albedo RMSE (0.0107 on well-lit texels).
4. A pixel is **kept** when every one of its rays hits the object facing the camera (a silhouette pixel is
   partly background, whose radiance the fit does not know), and its photo value is finite and not clipped.
   Rays that no light reaches stay in the pixel with radiance 0 (a shadow edge inside a pixel).

The result holds the kept rays as :class:`capture.observations.Observations` (each ray's texture footprint as its
texels and weights, every (ray, light) pair computed once) plus the ray → pixel grouping and each ray's share of
its pixel (``1/k²`` for the box): a sparse pixel × texel operator
``pixel_i = Σ_{s ∈ i} share_s · L_s(Σ_t w_st p_t)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor

from materials.model import Model
from renderer.device import per_view
from renderer.gbuffer import footprint_extent, pixel_filter, render_footprint
from renderer.shading import prepare, shade

from .fit.noise import CHI2_1_Q10, NOISE_QUANTILE, noise_ratio
from .observations import ObservationError, Observations, TexelTaps, ViewExtractor, noise_residual

__all__ = ["PixelFootprints", "observe_footprints", "footprint_counts", "photo_noise", "shading_bases",
           "texture_footprints", "FOOTPRINT_SPACING", "FOOTPRINT_MAX", "FOOTPRINT_TEXTURE_MAX", "SEAM_TEXELS"]

#: Largest distance (texels) between neighbouring sub-pixel samples: half a texel, so that every texel a pixel
#: covers is read by some sample, and the bilinear interpolant's kinks (at texel centres) are bracketed.
FOOTPRINT_SPACING = 0.5
#: Largest k (k × k rays per pixel, for the shading's need and on edges).
FOOTPRINT_MAX = 4
#: Largest kt (kt × kt texture sub-samples per pixel), above :data:`FOOTPRINT_MAX` because texture sub-samples are
#: located on the face plane without rays: 6 × 6 keeps the :data:`FOOTPRINT_SPACING` up to footprints of 3 texels
#: per pixel step. Measured on the 256² Mitsuba torus (12 views, prior weight 5e-3): 4 → 6 → 8, well-lit albedo
#: RMSE 0.00779 → 0.00756 → 0.00756, χ² per residual 0.209 → 0.189 → 0.189; texture sub-samples 2.2 → 3.6 → 4.0 M,
#: the observations +0.3 s; a synthetic Lambert sphere (`shadecap synth`, 12 × 192², 8 × 8 jittered rays) 0.0102 →
#: 0.0097 → 0.0097. Larger footprints
#: are sampled more coarsely — such texels are below what the photos resolve, and the fit's smoothness prior decides
#: them (the confidence maps say so).
FOOTPRINT_TEXTURE_MAX = 6
#: Texel footprint (texels per pixel step) up to which the texture sub-samples stay :data:`FOOTPRINT_SPACING` apart:
#: 0.5 × 6 = 3. Beyond it they skip texels — the operator aliases the map — and the photos determine no texel of
#: that size: :func:`sampled_map_size` picks the map size the footprint steps run at.
FOOTPRINT_SAMPLED = FOOTPRINT_SPACING * FOOTPRINT_TEXTURE_MAX
#: Share of the kept pixels whose footprint :func:`sampled_map_size` keeps within :data:`FOOTPRINT_SAMPLED`: the
#: median pixel. Measured (8 × 256² photos, 4 × 4 jittered rays, GGX + Lambert, 2-core CPU; docs/reconstruction.md,
#: "Maps finer than the photos"): median footprints of 2.7 / 5.4 / 10.8 texels on 512² / 1024² / 2048² maps; the
#: footprint steps at 512² and the maps upsampled give well-lit albedo / f0 / α 0.0297 / 0.0472 / 0.1452 on 1024²
#: (steps at 1024²: 0.0308 / 0.0495 / 0.1515) and 0.0294 / 0.0497 / 0.1490 on 2048² (at 2048²: 0.0355 / 0.0535 /
#: 0.1469; at 1024²: 0.0301 / 0.0515 / 0.1505), in 38.9 and 55.0 s instead of 55.9 and 123.3 s.
FOOTPRINT_SAMPLED_SHARE = 0.5
#: Relative error of a pixel's midpoint-rule average that the shading need may leave (module docstring): 0.025 %,
#: far below the 1 % photo noise the solver's noise model assumes — the error is a bias shared by neighbouring
#: pixels, not noise that averages out. Measured on the 256² Mitsuba torus: 1e-3 (0.51 M rays) left well-lit albedo
#: RMSE 0.0111 and χ² 0.198 per residual, 2.5e-4 (0.71 M rays) 0.0107 and 0.188, as 16 rays on every pixel did.
FOOTPRINT_TOLERANCE = 2.5e-4
#: Standard deviations of a photo's noise that a second difference must exceed to count as the shading's curvature
#: (:func:`_curvature`, photos noisier than the noise model only): noise alone then passes at 0.3 % of the pixels per
#: difference. Measured (2-core CPU; `shadecap synth --size 512 --tex 128 --views 8 --noise 3000`, GGX + Lambert): the
#: noise asked 16 rays of 91 % of the pixels (6.2 M rays, 77.1 s, 3.08 GiB); 3 σ with the smoothed differences 1.3 M
#: rays, 35.4 s, 1.56 GiB, well-lit albedo / f0 / roughness 0.0114 / 0.0326 / 0.1382 → 0.0113 / 0.0323 / 0.1355; 3 σ
#: without them (σ ∝ the signal) 1.5 M rays and visible-highlight f0 0.0300 → 0.0342; 1.5 σ without them 3.0 M rays,
#: 0.0336 (docs/log.md, "noisy photos' ray counts").
CURVATURE_NOISE_Z = 3.0
#: Intensity bins of equal pixel count in which :func:`photo_noise` measures a photo's noise variance, at most, and
#: the fewest residuals a bin takes (fewer bins for a small object): the 10 % quantile of 256 values of χ²₁ has a
#: standard error of 38 % of itself (√(0.1 · 0.9 / 256) / f(q), f the density at the quantile), which the line's fit
#: over the bins averages; a bin of a 256² view's object (~30 000 values in 16 bins) about 14 %.
NOISE_BINS = 16
NOISE_BIN_VALUES = 256
#: A UV jump between neighbouring pixels larger than this many texels marks a seam (the pixel straddles two
#: charts): its footprint is not measured by finite differences and it takes :data:`FOOTPRINT_MAX` samples.
SEAM_TEXELS = 8.0
#: Relative depth jump between neighbouring pixel centres that marks an occlusion edge (sampled at the maximum).
DEPTH_EDGE = 0.05


@dataclass
class PixelFootprints:
    """The valid pixels of the fitted views, each the area average of its sub-pixel samples.

    Attributes:
        samples: :class:`Observations` of the sub-pixel samples (S of them; ``samples.radiance`` holds each
            sample's pixel value, ``samples.taps`` its texels).
        group: ``[S]`` int64 index of each sample's pixel among the R kept pixels.
        share: ``[S]`` the sample's share of its pixel (``1/k²``; a pixel's shares sum to 1).
        radiance: ``[R, 3]`` measured linear radiance of each kept pixel.
        view, pixel: ``[R]`` int64 view index and flat pixel index ``y·W + x`` of each kept pixel.
        counts: ``[R]`` int64 rays per pixel (k²; each ray is one of ``samples``).
        noise_residual: ``[R, 3]`` image-space noise residual of each pixel (NaN near edges), as in
            :class:`Observations`.
        footprint_texels: ``[R]`` measured texel footprint ``f`` of each pixel (texels per pixel step).
        drops: sub-pixel samples dropped per reason (``samples_<reason>``, the reasons of
            :data:`capture.observations.DROP_REASONS`; an unlit sample stays in its pixel's average with radiance
            0, only its evaluation is skipped) and ``partial_pixels``: pixels some ray of which missed the object
            or saw its back (silhouettes), dropped whole.
        cast_rays: rays cast for the kept and dropped footprints together; uniform_rays: rays a uniform
            :data:`FOOTPRINT_MAX`² per pixel would have cast on the same pixels (the saving of the adaptive count);
            texture_samples: texture sub-samples of the kept pixels (``Σ (k·m)²``), located without rays.
        psf_sigma: σ (pixels) of the Gaussian PSF in the pixel filter (0: the box alone).
        noisy_views: views whose photo was noisier than the noise model, its noise left out of the ray counts
            (:func:`photo_noise`).
        ray_counts: what the shading's ray counts were read off: ``"photo"`` (its curvature) or ``"model"`` (the
            curvature of the model's shading, :func:`shading_bases`).
    """

    samples: Observations
    group: Tensor
    share: Tensor
    radiance: Tensor
    view: Tensor
    pixel: Tensor
    counts: Tensor
    noise_residual: Tensor
    footprint_texels: Tensor
    drops: dict
    cast_rays: int = 0
    uniform_rays: int = 0
    psf_sigma: float = 0.0
    texture_samples: int = 0
    noisy_views: int = 0
    ray_counts: str = "photo"

    @property
    def n_pixels(self) -> int:
        return int(self.radiance.shape[0])

    @property
    def n_samples(self) -> int:
        return self.samples.n_samples

    @property
    def map_size(self) -> tuple[int, int]:
        return self.samples.map_size

    @property
    def device(self) -> torch.device:
        return self.radiance.device

    def to(self, device=None, dtype=None) -> PixelFootprints:
        """Move to ``device`` and cast floating tensors to ``dtype`` (the samples with
        :meth:`capture.observations.Observations.to`)."""
        def mv(x):
            return x.to(device=device, dtype=dtype if x.is_floating_point() else None) if isinstance(x, Tensor) else x
        kw = {f.name: mv(getattr(self, f.name)) for f in fields(self)}
        kw["samples"] = self.samples.to(device=device, dtype=dtype)
        return PixelFootprints(**kw)

    def predict(self, model: Model, maps_flat: dict) -> Tensor:
        """Predicted pixel radiance ``[R, 3]``: ``Σ_{s ∈ i} share_s · L_s`` with ``L_s`` the model's radiance at
        sample s from per-sample canonical parameters (a dict ``name → [S, C]``)."""
        rad = self.samples.predict(model, maps_flat)
        return torch.zeros(self.n_pixels, 3, dtype=rad.dtype, device=rad.device).index_add(
            0, self.group, rad * self.share.to(rad.dtype)[:, None])

    def render(self, model: Model, maps: dict) -> Tensor:
        """Predicted pixel radiance ``[R, 3]`` of maps ``name → [H, W, C]`` (bilinear reads)."""
        return self.predict(model, self.samples.per_sample(maps, "bilinear"))

    def images(self, values: Tensor, view: int, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """Per-pixel values ``[R, C]`` of one view as an image ``[H, W, C]`` (0 elsewhere) and its mask."""
        H, W = size
        sel = self.view == view
        img = torch.zeros(H * W, values.shape[-1], dtype=values.dtype, device=values.device)
        img[self.pixel[sel]] = values[sel]
        mask = torch.zeros(H * W, dtype=torch.bool, device=values.device)
        mask[self.pixel[sel]] = True
        return img.reshape(H, W, -1), mask.reshape(H, W)

    def select_views(self, views: Sequence[int]) -> PixelFootprints:
        """Only the pixels (and their samples) of the given view indices."""
        v = torch.as_tensor(list(views), dtype=torch.long, device=self.device)
        return self.select(torch.isin(self.view, v))

    def select(self, keep: Tensor) -> PixelFootprints:
        """Only the pixels where ``keep [R]`` (bool) holds, with their samples."""
        if keep.dtype != torch.bool or keep.shape != (self.n_pixels,):
            raise ObservationError(f"select: keep must be a bool tensor [{self.n_pixels}], got {keep.dtype} "
                                   f"{tuple(keep.shape)}")
        keep_s = keep[self.group]
        new = torch.full((self.n_pixels,), -1, dtype=torch.long, device=self.device)
        new[keep] = torch.arange(int(keep.sum()), device=self.device)
        return PixelFootprints(
            samples=self.samples.select(keep_s), group=new[self.group[keep_s]], share=self.share[keep_s],
            radiance=self.radiance[keep], view=self.view[keep], pixel=self.pixel[keep],
            counts=self.counts[keep], noise_residual=self.noise_residual[keep],
            footprint_texels=self.footprint_texels[keep], drops=dict(self.drops), cast_rays=self.cast_rays,
            uniform_rays=self.uniform_rays, psf_sigma=self.psf_sigma, texture_samples=self.texture_samples,
            noisy_views=self.noisy_views, ray_counts=self.ray_counts)


def _grad_len(uv: Tensor, hit: Tensor, depth: Tensor, map_size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Texel footprint ``[H, W]`` of every pixel and a mask of edge pixels (silhouette, seam or depth edge)."""
    Hm, Wm = map_size
    t = torch.stack([uv[..., 0] * Wm, (1.0 - uv[..., 1]) * Hm], -1)                    # texel coordinates [H, W, 2]
    edge = torch.zeros_like(hit)

    def deriv(axis: int) -> Tensor:
        # central difference where both neighbours are on the surface, one-sided where one is, 0 where none is
        fwd = torch.roll(t, -1, axis) - t
        bwd = t - torch.roll(t, 1, axis)
        hf = torch.roll(hit, -1, axis)
        hb = torch.roll(hit, 1, axis)
        n = t.shape[axis]
        idx = torch.arange(n, device=t.device)
        last = (idx == n - 1) if axis == 1 else (idx == n - 1)[:, None]
        first = (idx == 0) if axis == 1 else (idx == 0)[:, None]
        hf = hf & ~last
        hb = hb & ~first
        dfw, dbw = fwd.norm(dim=-1), bwd.norm(dim=-1)
        seam = (hf & (dfw > SEAM_TEXELS)) | (hb & (dbw > SEAM_TEXELS))
        zf = torch.roll(depth, -1, axis)
        zb = torch.roll(depth, 1, axis)
        jump = (hf & ((zf - depth).abs() > DEPTH_EDGE * depth)) | (hb & ((zb - depth).abs() > DEPTH_EDGE * depth))
        both = hf & hb
        d = torch.where(both, 0.5 * (dfw + dbw), torch.where(hf, dfw, torch.where(hb, dbw, torch.zeros_like(dfw))))
        nonlocal edge
        edge = edge | seam | jump | ~hf | ~hb
        return d

    f = torch.maximum(deriv(1), deriv(0))
    return f, edge & hit


def _second_differences(img: Tensor, step: int, less: Tensor | None, c: Tensor, ref: Tensor) -> None:
    """Raise ``c [H, W]`` to ``(|img(x + step) + img(x − step) − 2 img(x)| − less(x)) / step² / ref(x)`` in x and in
    y, the largest over the channels (``img``, ``less`` ``[H, W, 3]``; ``less`` None: nothing subtracted)."""
    s = step
    dx = (img[:, 2 * s:] + img[:, :-2 * s] - 2 * img[:, s:-s]).abs()
    dy = (img[2 * s:] + img[:-2 * s] - 2 * img[s:-s]).abs()
    if less is not None:
        dx, dy = (dx - less[:, s:-s]).clamp_min(0), (dy - less[s:-s]).clamp_min(0)
    c[:, s:-s] = torch.maximum(c[:, s:-s], (dx / (s * s * ref[:, s:-s])).amax(-1))
    c[s:-s] = torch.maximum(c[s:-s], (dy / (s * s * ref[s:-s])).amax(-1))


def _curvature(photo: Tensor, sigma: Tensor | None = None) -> Tensor:
    """``[H, W]`` relative second difference of a photo ``[H, W, 3]`` across each pixel (module docstring), the
    largest over x, y and the channels; 0 where a neighbour is missing or non-finite.

    With the photo's noise std ``sigma [H, W, 3]`` (:func:`photo_noise`), the part of each difference its noise
    explains — :data:`CURVATURE_NOISE_Z` times its std, ``√6 σ`` — is left out, and the second differences of the
    photo smoothed by a 3 × 3 box, two pixels apart and divided by 4 (std ``√(10/27) σ / 4``, the same less its
    noise), are taken too: curvature broader than a pixel that the noise hides in the pixel's own difference."""
    img = torch.nan_to_num(photo.to(torch.float64), nan=0.0, posinf=0.0, neginf=0.0)
    ref = img.abs().amax(-1, keepdim=True).clamp_min(1e-6 * max(float(img.abs().max()), 1e-30))
    c = torch.zeros(img.shape[:2], dtype=torch.float64)
    if sigma is None:
        _second_differences(img, 1, None, c, ref)
        return c
    z = CURVATURE_NOISE_Z * sigma.to(torch.float64)
    _second_differences(img, 1, z * math.sqrt(6.0), c, ref)
    _second_differences(_box_mean(img), 2, z * math.sqrt(10.0 / 27.0), c, ref)
    return c


def _box_mean(img: Tensor) -> Tensor:
    """``[H, W, C]`` the 3 × 3 box mean of ``img [H, W, C]`` (over the pixels inside the image at its border)."""
    return F.avg_pool2d(img.permute(2, 0, 1)[None], 3, stride=1, padding=1, count_include_pad=False)[0].permute(1, 2, 0)


def photo_noise(photo: Tensor, hit: Tensor) -> Tensor | None:
    """``[H, W, 3]`` noise std of a photo ``[H, W, 3]`` at its object pixels ``hit [H, W]`` (0 elsewhere), or None
    when the photo is no noisier than the default noise model (:data:`capture.fit.noise.NOISE`, 1 % of the signal —
    whatever ``noise`` a fit is given: the question is whether noise could pass for curvature;
    :func:`capture.fit.noise.noise_ratio` of its image-space noise residual at most 1; noise-free renders read
    0–0.11): its second differences are then the shading's.

    The std is a sensor's signal-dependent noise, ``σ² = a·I + b`` (shot noise and read noise; Foi et al., "Practical
    Poissonian-Gaussian noise modeling and fitting for single-image raw-data", IEEE TIP 2008), fitted to
    :data:`NOISE_BINS` bins of equal count of the object's pixel values (3 × 3 box means, so that a pixel's own
    noise does not choose its bin; fewer for a small object, :data:`NOISE_BIN_VALUES`), each bin's variance read as
    the residual's robust :data:`capture.fit.noise.NOISE_QUANTILE` quantile of ``e²`` over that quantile of χ²₁
    (edges and highlights inflate a few residuals, noise all of them), ``a, b ≥ 0`` by :func:`_variance_line`."""
    img = torch.nan_to_num(photo.to(torch.float64), nan=0.0, posinf=0.0, neginf=0.0)
    valid = hit & torch.isfinite(photo).all(-1)
    if int(valid.sum()) < 100:
        return None
    e = noise_residual(img, valid)
    ratio = noise_ratio(e[valid], img[valid])
    if ratio is None or ratio <= 1.0:
        return None
    # the levels of the 3 × 3 box mean: a pixel's own value would sort its own noise into the bins
    level_img = _box_mean(img)
    y, r = level_img[valid].reshape(-1), e[valid].reshape(-1)
    ok = torch.isfinite(r) & (y > 0)
    y, r2 = y[ok], r[ok].square()
    if y.numel() < 100:                 # the ratio's own minimum, and every bin a handful of values
        return None
    order = torch.argsort(y)
    level, var = [], []
    for chunk in torch.tensor_split(order, max(1, min(NOISE_BINS, y.numel() // NOISE_BIN_VALUES))):
        q = r2[chunk]
        level.append(float(y[chunk].median()))
        var.append(float(q.kthvalue(max(1, int(NOISE_QUANTILE * q.numel()))).values) / CHI2_1_Q10)
    a, b = _variance_line(torch.tensor(level, dtype=torch.float64), torch.tensor(var, dtype=torch.float64))
    sigma = torch.zeros_like(img)
    sigma[valid] = (a * level_img[valid] + b).clamp_min(0).sqrt()
    return sigma


def _variance_line(level: Tensor, var: Tensor) -> tuple[float, float]:
    """``a, b ≥ 0`` of the line ``a·I + b`` through bins' noise variances ``var`` at levels ``level``: weighted least
    squares with weights ``1 / (a·I + b)²`` — each bin's error relative to the line's own variance there, three
    rounds from the median —, each round the best of the unconstrained line (when both its coefficients are ≥ 0)
    and the two one-parameter lines. Relative to the *measured* variances instead, the bins read low by chance would
    pull the line down (a strip of 38 noisy pixels read σ 0.003 for 0.05)."""
    ab = (0.0, float(var.median()))
    for _ in range(3):
        w = 1.0 / (ab[0] * level + ab[1]).clamp_min(1e-30)
        cands = []
        sol = torch.linalg.lstsq(torch.stack([level, torch.ones_like(level)], -1) * w[:, None],
                                 (var * w)[:, None]).solution[:, 0]
        if bool((sol >= 0).all()):
            cands.append((float(sol[0]), float(sol[1])))
        cands.append((0.0, float((var * w * w).sum() / (w * w).sum())))
        cands.append((float((level * var * w * w).sum() / (level * level * w * w).sum().clamp_min(1e-300)), 0.0))
        ab = min(cands, key=lambda c: float((((c[0] * level + c[1] - var) * w) ** 2).sum()))
    return ab


def footprint_max(psf_sigma: float = 0.0, cap: int = FOOTPRINT_MAX) -> int:
    """Largest k for a pixel filter: ``cap`` (:data:`FOOTPRINT_MAX` for rays, :data:`FOOTPRINT_TEXTURE_MAX` for
    texture sub-samples) over the box's square, as many per pixel width over the wider square of a Gaussian PSF
    (:func:`renderer.gbuffer.footprint_extent`), at most 16."""
    return min(16, math.ceil(cap * footprint_extent(psf_sigma) - 1e-9))


def _object_pixels(gbuffer) -> Tensor:
    """``[H, W]`` bool: the pixels of a pixel-centre G-buffer whose centre ray hits the object."""
    hit = torch.zeros(gbuffer.height * gbuffer.width, dtype=torch.bool)
    hit[gbuffer.pixel] = True
    return hit.reshape(gbuffer.height, gbuffer.width)


def shading_bases(model: Model, prepared) -> Tensor | None:
    """``[B, H, W, 3]``: noise-free images of one view whose relative curvature bounds its shading's (module
    docstring, step 2), for a model affine in its parameters (every ``ParamSpec.linear``: Lambert), else None.

    ``prepared`` is the view's pixel-centre G-buffer with its shading (:func:`renderer.shading.prepare`). The images
    are the model rendered there with every parameter 0 (the radiance no parameter scales) and, for each
    parameter channel, that channel at 1 less it. A pixel's radiance is their sum weighted by its parameters (≥ 0),
    so its relative second difference is at most the largest of theirs — the shading's, without the texture's
    (which the texture sub-samples resolve) or any noise. A model with a nonlinear parameter (a lobe's roughness)
    has a shading that depends on values no fit has found yet: None, and the photo's curvature is used."""
    specs = list(model.params)
    if not specs or not all(s.linear for s in specs):
        return None
    g = getattr(prepared, "gbuffer", None)
    if g is None:
        raise ObservationError("shading_bases: prepared must be a view's shading prepared from its G-buffer "
                               "(renderer.shading.prepare(render_gbuffer(mesh, camera, 1), mesh, lights))")
    dtype = prepared.n.dtype

    def render(name: str | None = None, channel: int = 0) -> Tensor:
        maps = {s.name: torch.zeros(1, 1, s.channels, dtype=dtype) for s in specs}
        if name is not None:
            maps[name][..., channel] = 1.0
        img = torch.zeros(g.height * g.width, 3, dtype=torch.float64)
        img[g.pixel] = shade(model, maps, prepared).to(torch.float64)
        return img.reshape(g.height, g.width, 3)

    base = render()
    images = [render(s.name, c) - base for s in specs for c in range(s.channels)]
    if bool(base.abs().max() > 0):
        images.append(base)
    return torch.stack(images)


def footprint_counts(gbuffer, map_size: tuple[int, int], photo: Tensor | None = None, psf_sigma: float = 0.0,
                     noise: Tensor | None | str = "measure",
                     shading: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per pixel of a pixel-centre G-buffer: which pixels to cast, their ray count ``k``, their texture sample
    count ``kt`` and texel footprint ``f`` (module docstring, step 2).

    With a Gaussian PSF (``psf_sigma`` pixels) the samples cover the filter's wider square
    (:func:`renderer.gbuffer.footprint_extent`), so both needs are multiplied by its side and the cap is
    :func:`footprint_max`.

    Returns ``(pixels [M], k [M], kt [M], f [M])`` for the M pixels whose centre ray hits the object, plus the
    pixels next to them (a pixel whose centre misses may still be partly covered; it is cast at the cap so that the
    coverage test sees it, and dropped as partial). ``k`` is the shading's need (the photo's curvature; the cap on
    edges), ``kt ≥ k`` the texture's (on edges ``kt = k``): each ray's stratum is read at ``ceil(kt / k)²`` texture
    sub-samples. ``noise``: the photo's noise std ``[H, W, 3]`` left out of its curvature (:func:`_curvature`), None
    for none, or ``"measure"`` (default) for :func:`photo_noise` of the photo at the G-buffer's object pixels.
    ``shading``: noise-free images ``[B, H, W, 3]`` of the view's shading (:func:`shading_bases`) whose largest
    curvature is the shading's need instead of the photo's; the photo's, when given too, then sets the texture's
    (``kt`` at least its ray count: the texture's variation inside the pixel, a kink of the bilinear map at an
    albedo edge, is integrated by texture sub-samples instead of rays)."""
    H, W = gbuffer.height, gbuffer.width
    uv = torch.zeros(H * W, 2, dtype=torch.float64)
    depth = torch.zeros(H * W, dtype=torch.float64)
    uv[gbuffer.pixel] = gbuffer.uv.to(torch.float64)
    depth[gbuffer.pixel] = gbuffer.depth.to(torch.float64)
    hit2 = _object_pixels(gbuffer)
    hit = hit2.reshape(-1)
    f, edge = _grad_len(uv.reshape(H, W, 2), hit2, depth.reshape(H, W), map_size)
    extent, kmax = footprint_extent(psf_sigma), footprint_max(psf_sigma)
    kt = torch.ceil(f * extent / FOOTPRINT_SPACING)
    k = torch.ones_like(kt)
    k_photo = None
    if photo is not None:
        if isinstance(noise, str):
            if noise != "measure":
                raise ObservationError(f"footprint_counts: noise must be a tensor, None or 'measure', got {noise!r}")
            noise = photo_noise(photo, hit2)
        k_photo = torch.ceil(extent * torch.sqrt(_curvature(photo, noise) / (24.0 * FOOTPRINT_TOLERANCE)))
    if shading is not None:
        if shading.ndim != 4 or tuple(shading.shape[1:3]) != (H, W):
            raise ObservationError(f"footprint_counts: shading must be [B, {H}, {W}, 3] images of the view, got "
                                   f"{tuple(shading.shape)}")
        curvature = torch.stack([_curvature(img) for img in shading]).amax(0)
        k = torch.ceil(extent * torch.sqrt(curvature / (24.0 * FOOTPRINT_TOLERANCE)))
        if k_photo is not None:
            # what the photo's curvature holds beyond the shading's is the texture's variation inside the pixel:
            # texture sub-samples integrate it (as the rays it asked for did), without rays
            kt = torch.maximum(kt, k_photo.clamp(1, kmax))
    elif k_photo is not None:
        k = k_photo
    k = k.clamp(1, kmax).long()
    k = torch.where(edge, torch.full_like(k, kmax), k)
    kt = torch.maximum(kt.clamp(1, footprint_max(psf_sigma, FOOTPRINT_TEXTURE_MAX)).long(), k)
    kt = torch.where(edge, k, kt)
    # a pixel next to a hit pixel but missing at its centre may be partly covered: cast it too (dropped later as
    # partial) — only so that no partly covered pixel is kept as a full one, which it never is (its own rays miss)
    reach = 1 + math.ceil((extent - 1.0) / 2.0)       # pixels whose filter square may reach a hit pixel
    near = F.max_pool2d(hit2[None, None].float(), 2 * reach + 1, stride=1, padding=reach)[0, 0] > 0
    cast = (hit2 | near).reshape(-1)
    kk = torch.where(hit, k.reshape(-1), torch.full_like(k.reshape(-1), kmax))
    kkt = torch.where(hit, kt.reshape(-1), kk)
    pixels = torch.nonzero(cast).squeeze(-1)
    return pixels, kk[pixels], kkt[pixels], f.reshape(-1)[pixels]


def texture_footprints(mesh, camera, g, k: Tensor, kt: Tensor, map_size: tuple[int, int],
                       psf_sigma: float = 0.0) -> tuple[Tensor, TexelTaps]:
    """The texels each ray of a footprint G-buffer stands for (module docstring, step 3).

    ``g`` holds the rays of :func:`renderer.gbuffer.render_footprint`; ``k [N]``, ``kt [N]`` are the ray count and
    texture count of each ray's pixel. A ray's stratum (side ``extent / k`` pixels) is read at ``m × m`` texture
    sub-samples, ``m = ceil(kt / k)``, at the centres of a regular grid over it, each located on the plane of the
    face the ray hit (:func:`renderer.gbuffer.face_planes`) and read bilinearly; over the pixel they form the
    ``(k·m)²`` midpoint grid of the filter's square, weighted by the pixel filter (uniform for the box).

    Returns ``(share [N], taps)``: the ray's share of its pixel (the filter weights of its sub-samples, summing to 1
    over the pixel) and its distinct texels with weights summing to 1 (:class:`capture.observations.TexelTaps`, one
    row per ray)."""
    from renderer.gbuffer import face_planes
    from renderer.texture import bilinear_weights

    H, W = map_size
    extent = footprint_extent(psf_sigma)
    N = len(g)
    m = _sub_samples(k, kt)
    rows = []
    share = torch.zeros(N, dtype=torch.float64)
    xy, _ = camera.project(g.position.to(torch.float64))
    centre = torch.stack([(g.pixel % g.width).double(), (g.pixel // g.width).double()], -1)
    pair = k * 256 + m                                           # k, m ≤ 16: one key per (k, m) group
    for key in torch.unique(pair).tolist():
        kk, mm = divmod(key, 256)
        sel = torch.nonzero(pair == key).squeeze(-1)
        n = kk * mm
        off = ((torch.arange(n, dtype=torch.float64) + 0.5) / n - 0.5) * extent     # the pixel's sub-sample grid
        w1 = pixel_filter(off, psf_sigma)
        w1 = w1 / w1.sum()
        # the ray's stratum (ix, iy) from its position (the stratum centre, to rounding) and its sub-samples
        strat = torch.round(((xy[sel] - centre[sel]) / extent + 0.5) * kk - 0.5).long().clamp(0, kk - 1)
        j = torch.arange(mm)
        ix = strat[:, 0:1] * mm + j[None]                                             # [n_sel, m]
        iy = strat[:, 1:2] * mm + j[None]
        wsub = (w1[iy][:, :, None] * w1[ix][:, None, :]).reshape(len(sel), -1)       # [n_sel, m²] (y-major)
        if mm == 1:
            uv = g.uv[sel].to(torch.float64)[:, None]
        else:
            sub_xy = torch.stack([off[ix][:, None, :].expand(-1, mm, -1), off[iy][:, :, None].expand(-1, -1, mm)],
                                 -1).reshape(len(sel), -1, 2) + centre[sel][:, None]
            uv, ok = face_planes(mesh, camera, g.face[sel]).uv(sub_xy)                  # [n_sel, m², 2]
            uv = torch.where(ok[..., None], uv, g.uv[sel].to(torch.float64)[:, None])
        bi, bw = bilinear_weights(uv, H, W)                                           # [n_sel, m², 4]
        s_ray = wsub.sum(-1)
        share[sel] = s_ray
        wt = (bw * (wsub / s_ray.clamp_min(1e-300)[:, None])[..., None]).reshape(len(sel), -1)
        rows.append((sel, *_distinct(bi.reshape(len(sel), -1), wt)))
    return share, TexelTaps.from_blocks(rows, N)


def _sub_samples(k: Tensor, kt: Tensor) -> Tensor:
    """``m = ceil(kt / k)``: texture sub-samples per axis of each ray's stratum (``k`` rays per axis of the pixel, of
    which ``kt`` texture samples are needed; 0 where ``k`` is, for pixels not cast)."""
    return torch.div(kt + k - 1, k.clamp_min(1), rounding_mode="floor")


def _distinct(index: Tensor, weight: Tensor) -> tuple[Tensor, Tensor]:
    """Each row's distinct indices with their weights summed, ``[N, K']`` with ``K'`` the most distinct indices of
    any row (shorter rows padded with their first index at weight 0): a ray's sub-samples share most texels (16
    sub-samples over 2 × 2 texels read ~9 distinct texels of their 64 bilinear taps)."""
    N, L = index.shape
    if L <= 1 or N == 0:
        return index, weight
    si, order = torch.sort(index, dim=1)
    sw = torch.gather(weight, 1, order)
    new = torch.ones_like(si, dtype=torch.bool)
    new[:, 1:] = si[:, 1:] != si[:, :-1]
    pos = new.long().cumsum(1) - 1                                                   # slot of each tap
    K = int(pos[:, -1].max()) + 1
    out_w = torch.zeros(N, K, dtype=weight.dtype).scatter_add_(1, pos, sw)
    out_i = si[:, :1].expand(N, K).clone()
    out_i.scatter_(1, torch.where(new, pos, torch.zeros_like(pos)), torch.where(new, si, si[:, :1].expand_as(si)))
    return out_i, out_w


def observe_footprints(mesh, cameras: Sequence, lights_per_view: Sequence, centre_gbuffers: Sequence,
                       photos: Sequence[Tensor], map_size: tuple[int, int], *, lights: Sequence | None = None,
                       clipped: Sequence[Tensor] | None = None, dtype=None, shadows: bool = True,
                       psf_sigma: float = 0.0, shading: Sequence[Tensor] | None = None) -> PixelFootprints:
    """The pixel footprints of every view (module docstring).

    Args:
        mesh: the object; cameras: one :class:`renderer.camera.Camera` per view; lights_per_view: each view's
            lights; centre_gbuffers: each view's pixel-centre G-buffer (``render_gbuffer(mesh, camera, 1)``).
        photos: per view the linear photo ``[H, W, 3]`` in radiance units (exposure divided out).
        map_size: ``(H, W)`` of the maps. lights: the scene's point/directional lights in order (see
            :func:`capture.observations.observe_views`). clipped: per view ``[H, W]`` saturated-pixel masks.
        psf_sigma: σ (pixels) of a Gaussian lens/demosaicing blur convolved with the box filter (0: box only;
            :func:`renderer.gbuffer.render_footprint`).
        shading: per view the model's shading images (:func:`shading_bases`), whose curvature then sets the ray
            counts instead of the photos' (None: the photos'), the photos' setting the texture sub-samples.

    Raises:
        ObservationError: mismatched lists or no valid pixel in any view.
    """

    n = len(cameras)
    if not (len(lights_per_view) == len(centre_gbuffers) == len(photos) == n) or n == 0:
        raise ObservationError(f"observe_footprints: need one camera, light list, centre G-buffer and photo per "
                               f"view, got {n}, {len(lights_per_view)}, {len(centre_gbuffers)}, {len(photos)}")
    if shading is not None and len(shading) != n:
        raise ObservationError(f"observe_footprints: shading needs one set of images per view, got {len(shading)} "
                               f"for {n} views")

    extractor = ViewExtractor(n, map_size, clipped=clipped, footprints=True, dtype=dtype)

    def one(vi):
        # one view's rays, texture footprints and shading terms, made into its kept samples at once: the prepared
        # rays of all views held until every view was made took twice the samples' memory more
        g0 = centre_gbuffers[vi]
        sigma = photo_noise(photos[vi], _object_pixels(g0))
        pixels, k, kt, f = footprint_counts(g0, map_size, photos[vi], psf_sigma, noise=sigma,
                                            shading=None if shading is None else shading[vi])
        g = render_footprint(mesh, cameras[vi], pixels, k, psf_sigma=psf_sigma)
        cast = int((k * k).sum())
        # a pixel is whole when all its rays hit the object facing the camera
        facing = (g.normal * g.view).sum(-1) > 0
        HW = g.height * g.width
        covered = torch.zeros(HW, dtype=torch.float64).index_add(0, g.pixel, g.weight.double() * facing.double())
        whole = torch.zeros(HW, dtype=torch.bool)
        whole[pixels] = (covered[pixels] > 1.0 - 1e-6)
        uniform = int(whole.sum()) * footprint_max(psf_sigma) ** 2
        partial = int((~whole[pixels]).sum()) - int((covered[pixels] == 0).sum())
        g = g.select(whole[g.pixel])
        k_of = torch.zeros(HW, dtype=torch.long)
        kt_of = torch.zeros(HW, dtype=torch.long)
        k_of[pixels], kt_of[pixels] = k, kt
        share, taps = texture_footprints(mesh, cameras[vi], g, k_of[g.pixel], kt_of[g.pixel], map_size, psf_sigma)
        g.weight = share.to(g.weight.dtype)
        sub = int(((k_of * _sub_samples(k_of, kt_of))[whole] ** 2).sum())
        part = extractor.view(vi, prepare(g, mesh, lights_per_view[vi], shadows=shadows), photos[vi], taps)
        kk = torch.zeros(HW, dtype=torch.long)
        kk[pixels] = k * k
        ff = torch.zeros(HW, dtype=torch.float64)
        ff[pixels] = f
        # the image-space noise residual at the view's kept pixels, in pixel order (the order of its rows among the
        # grouped pixels below), made here in the view's thread rather than view after view once they are joined
        kept = torch.unique(part.columns["pixel"])
        valid = torch.zeros(HW, dtype=torch.bool)
        valid[kept] = True
        photo = torch.nan_to_num(photos[vi].to(part.columns["radiance"].dtype), nan=0.0, posinf=0.0, neginf=0.0)
        noise = noise_residual(photo, valid.reshape(g.height, g.width)).reshape(-1, 3)[kept]
        return part, kk, ff, noise, cast, uniform, partial, sub, int(sigma is not None)

    parts, counts, fps, noises, *tallies = zip(*per_view(one, n), strict=True)
    cast, uniform, partial, sub, noisy = (sum(t) for t in tallies)
    samples = extractor.observations(list(parts), lights=lights, bilinear=True)
    del parts
    # group the kept samples by (view, pixel): every sample of a kept pixel survives (only unlit ones are dropped,
    # and they contribute 0), so a pixel's value is Σ share · L over its kept samples
    key = samples.view * (max(h * w for h, w in samples.image_size) + 1) + samples.pixel
    uniq, group = torch.unique(key, return_inverse=True)
    R = int(uniq.numel())
    first = torch.full((R,), samples.n_samples, dtype=torch.long).scatter_reduce(
        0, group, torch.arange(samples.n_samples), "amin")
    view = samples.view[first]
    pixel = samples.pixel[first]
    counts_r = torch.stack([torch.nn.functional.pad(c, (0, HWmax - len(c))) for c in counts])[view, pixel] \
        if (HWmax := max(len(c) for c in counts)) else torch.zeros(0, dtype=torch.long)
    foot_r = torch.stack([torch.nn.functional.pad(c, (0, HWmax - len(c))) for c in fps])[view, pixel]
    share = samples.weight                       # observe_views carries the G-buffer weight 1/k² for footprints
    # the grouped pixels are in (view, pixel) order, so each view's rows are its kept pixels in pixel order
    noise = torch.cat(noises)
    del noises
    if noise.shape[0] != R:
        raise ObservationError(f"observe_footprints: the views measured the noise at {noise.shape[0]} kept pixels but "
                               f"their samples group into {R}; the views' samples were joined out of step (a bug: "
                               f"please report it with the dataset)")
    drops = {f"samples_{k}": v for k, v in samples.drops.items() if k != "background"}
    drops["partial_pixels"] = max(partial, 0)
    samples.weight = torch.ones_like(share)
    return PixelFootprints(samples=samples, group=group, share=share, radiance=samples.radiance[first].clone(),
                           view=view, pixel=pixel, counts=counts_r, noise_residual=noise, footprint_texels=foot_r,
                           drops=drops, cast_rays=cast, uniform_rays=uniform, psf_sigma=float(psf_sigma),
                           texture_samples=sub, noisy_views=noisy,
                           ray_counts="photo" if shading is None else "model")


def sampled_map_size(fp: PixelFootprints, min_size: int = 1) -> int:
    """The largest of the map size halved k ≥ 0 times (at least ``min_size``) at which the footprints of
    :data:`FOOTPRINT_SAMPLED_SHARE` of the kept pixels are within :data:`FOOTPRINT_SAMPLED` texels per pixel step
    (a footprint of ``f`` texels on the full-size maps is ``f / 2^k`` on maps halved k times): the finest maps
    the pixel footprints sample without skipping texels. The map size itself when it qualifies, or is not square,
    or cannot be halved, or no pixel is kept."""
    if not isinstance(min_size, int) or isinstance(min_size, bool) or min_size < 1:
        raise ObservationError(f"sampled_map_size: min_size must be an integer ≥ 1, got {min_size!r}")
    H, W = fp.map_size
    # (the lower median of the finite footprints: a pixel whose UV derivative is not finite takes no part)
    f = fp.footprint_texels[torch.isfinite(fp.footprint_texels)].to(torch.float64)
    if H != W or f.numel() == 0:
        return H
    level = float(torch.kthvalue(f.cpu(), max(1, math.ceil(FOOTPRINT_SAMPLED_SHARE * f.numel()))).values)
    size = H
    while level > FOOTPRINT_SAMPLED and size // 2 >= min_size and size % 2 == 0:
        size //= 2
        level /= 2
    return size


def saving(fp: PixelFootprints) -> float:
    """Fraction of rays the adaptive count saves against :data:`FOOTPRINT_MAX`² rays on every kept pixel."""
    return 1.0 - float(fp.counts.sum()) / max(fp.n_pixels * footprint_max(fp.psf_sigma) ** 2, 1) if fp.n_pixels \
        else 0.0

