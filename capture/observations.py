"""Photos + G-buffers → a flat list of valid samples: what the solver fits.

Geometry, cameras and lights are known, so everything that depends only on them is computed once
(DESIGN.md, "Speed: skip what a scene does not need"): the renderer's G-buffer of each view and
its :func:`renderer.shading.prepare` (per light the :class:`materials.Angles` and the irradiance
E·V of the samples it reaches). This module pairs those with the measured pixels and keeps only
the samples that can inform a material parameter. Each dropped pixel is counted under one reason,
checked in this order:

``background``   the camera ray missed the mesh;
``nonfinite``    a NaN or ±inf channel in the photo;
``clipped``      a channel at or above the saturation level (the sensor clipped, the value is a
                 lower bound, not a measurement);
``backfacing``   the interpolated shading normal faces away from the camera (n·v ≤ 0, silhouettes);
``shadowed``     some light would reach the sample geometrically but every such light is occluded;
``unlit``        no light faces the sample at all.

Measured radiance is ``photo / exposure`` in linear RGB (a PNG is decoded from sRGB first by the
dataset loader), the same unit as the irradiance E times a BRDF in 1/sr (DESIGN.md, radiometry).

An :class:`Observations` stores the kept samples flat (S of them) and, separately, the (sample,
light) *pairs* (Q of them) with their Angles and E·V, so that a model evaluation is one call over
all pairs followed by an ``index_add`` onto the samples — no loop over lights, pixels or texels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields

import torch
import torch.nn.functional as F
from torch import Tensor

from materials.geometry import Angles
from materials.model import Model
from renderer.device import per_view, release_memory
from renderer.shading import radiance_jacobian, radiance_sum
from renderer.texture import bilinear_weights, texel_of

__all__ = ["Observations", "ObservationError", "DROP_REASONS", "TexelTaps", "ViewExtractor", "ViewSamples",
           "observe_views", "synthetic_observations"]

#: Drop reasons in the order they are tested (each pixel is counted once, under the first that applies).
DROP_REASONS = ("background", "nonfinite", "clipped", "backfacing", "shadowed", "unlit")


class ObservationError(ValueError):
    """Inputs that cannot be turned into observations (shapes, sizes, no valid sample at all)."""


@dataclass
class TexelTaps:
    """The texels each of N rows (samples) reads and their weights, ragged (CSR): row i reads
    ``index[start[i]:start[i + 1]]`` with ``weight[start[i]:start[i + 1]]``, no zero weight stored.

    A ray's texture footprint reads 1 to ~30 texels, most rays 4 or fewer; padded to the widest row ``[N, K]`` in
    int64 they took 68 % of the footprint observations' memory (183 of 268 MiB for 8 views of 256², 29 columns),
    ragged in int32 one sixth of that.

    Attributes:
        start: ``[N + 1]`` int64 offsets of the rows' taps (``start[0] = 0``, ``start[N]`` = the tap count).
        index: ``[nnz]`` int32 flat texel index ``i·W + j``; weight: ``[nnz]`` the tap's weight (> 0).
    """

    start: Tensor
    index: Tensor
    weight: Tensor

    @classmethod
    def from_blocks(cls, blocks: Sequence[tuple[Tensor, Tensor, Tensor]], n_rows: int) -> TexelTaps:
        """Taps from blocks of rows ``(rows [n], index [n, K], weight [n, K])`` (each block its own width; every row
        in one block), zero weights dropped, each row's taps in column order. Placed by offsets, without a sort."""
        dev = blocks[0][0].device if blocks else torch.device("cpu")
        counts = torch.zeros(n_rows, dtype=torch.long, device=dev)
        lives = []
        for rows, _, weight in blocks:
            live = weight != 0
            counts[rows] = live.sum(1)
            lives.append(live)
        start = torch.zeros(n_rows + 1, dtype=torch.long, device=dev)
        start[1:] = counts.cumsum(0)
        nnz = int(start[-1])
        wdt = blocks[0][2].dtype if blocks else torch.float64
        index = torch.zeros(nnz, dtype=torch.int32, device=dev)
        weight = torch.zeros(nnz, dtype=wdt, device=dev)
        for (rows, idx, w), live in zip(blocks, lives, strict=True):
            dest = (start[rows][:, None] + live.long().cumsum(1) - 1)[live]
            index[dest], weight[dest] = idx[live].to(torch.int32), w[live].to(wdt)
        return cls(start, index, weight)

    @property
    def n_rows(self) -> int:
        return int(self.start.numel()) - 1

    def counts(self) -> Tensor:
        """``[N]`` int64 taps per row."""
        return self.start[1:] - self.start[:-1]

    def rows(self) -> Tensor:
        """``[nnz]`` int64 the row of each tap."""
        return torch.repeat_interleave(torch.arange(self.n_rows, device=self.start.device), self.counts())

    def read(self, flat: Tensor) -> Tensor:
        """``[N, C]`` each row's weighted sum of ``flat [T, C]`` at its texels."""
        vals = flat[self.index.long()] * self.weight.to(flat.dtype)[:, None]
        return torch.zeros(self.n_rows, flat.shape[-1], dtype=flat.dtype, device=flat.device).index_add_(
            0, self.rows(), vals)

    def select(self, keep: Tensor) -> TexelTaps:
        """The rows where ``keep [N]`` (bool) holds, in order."""
        c = self.counts()
        tap_keep = torch.repeat_interleave(keep, c)
        start = torch.zeros(int(keep.sum()) + 1, dtype=torch.long, device=self.start.device)
        start[1:] = c[keep].cumsum(0)
        return TexelTaps(start, self.index[tap_keep], self.weight[tap_keep])

    def to(self, device=None, dtype=None) -> TexelTaps:
        """Moved to ``device``, weights cast to ``dtype``."""
        return TexelTaps(self.start.to(device), self.index.to(device), self.weight.to(device=device, dtype=dtype))

    @staticmethod
    def cat(parts: Sequence[TexelTaps]) -> TexelTaps:
        """The rows of ``parts`` one after another."""
        starts, off = [torch.zeros(1, dtype=torch.long, device=parts[0].start.device)], 0
        for p in parts:
            starts.append(p.start[1:] + off)
            off += int(p.start[-1])
        return TexelTaps(torch.cat(starts), torch.cat([p.index for p in parts]), torch.cat([p.weight for p in parts]))


@dataclass
class Observations:
    """Flat valid samples of all views (S samples, Q (sample, light) pairs).

    Attributes:
        texel: ``[S]`` int64 flat index ``i·W + j`` of the texel containing each sample's UV
            (nearest texel, :func:`renderer.texture.texel_of`).
        map_size: ``(H, W)`` of the maps the texel indices refer to.
        radiance: ``[S, 3]`` measured linear radiance (photo / exposure), ≥ 0 in practice.
        weight: ``[S]`` per-sample weight (1 by default; a noise model may lower it).
        pair_sample: ``[Q]`` int64 sample index of each (sample, light) pair.
        pair_light: ``[Q]`` int32 index of the light among the scene's lights (−1: none of them; read by nothing in
            the fit: 32 bits are half the bytes of a 64-bit index on every (sample, light) pair).
        angles: :class:`materials.Angles` of the pairs, each cosine ``[Q, 1]``.
        irradiance: ``[Q, 3]`` E·V of the pairs (visibility included).
        view: ``[S]`` int64 view index; pixel: ``[S]`` int64 flat pixel index y·W + x in its view.
        uv: ``[S, 2]``; n, v: ``[S, 3]`` unit shading normal and view direction.
        bilinear_index, bilinear_weight: ``[S, 4]`` optional texels/weights of the bilinear taps of each sample's uv.
        taps: for pixel footprints (``observe_views(texels=...)``), each ray's texture footprint as
            :class:`TexelTaps` (then ``bilinear_index`` is None): what bilinear sampling reads.
        env_terms: environment lights ``(light, sample index [E])`` (evaluated with
            ``model.environment``), usually empty.
        drops: pixels dropped per reason (:data:`DROP_REASONS`), summed over views.
        n_views: number of views; image_size: ``(height, width)`` per view.
        n_lights: number of point/directional lights in the scene.
        noise_residual: ``[S, 3]`` optional image-space noise residual of each sample's pixel
            (:func:`noise_residual`, NaN where its 3 × 3 neighbourhood leaves the valid object pixels): a
            measurement of the photos' noise that no fit enters.
    """

    texel: Tensor
    map_size: tuple[int, int]
    radiance: Tensor
    weight: Tensor
    pair_sample: Tensor
    pair_light: Tensor
    angles: Angles
    irradiance: Tensor
    view: Tensor
    pixel: Tensor
    uv: Tensor | None = None
    n: Tensor | None = None
    v: Tensor | None = None
    bilinear_index: Tensor | None = None
    bilinear_weight: Tensor | None = None
    taps: TexelTaps | None = None
    env_terms: list = field(default_factory=list)
    drops: dict = field(default_factory=dict)
    n_views: int = 1
    image_size: list = field(default_factory=list)
    n_lights: int = 1
    noise_residual: Tensor | None = None

    # -- sizes --------------------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        return int(self.texel.shape[0])

    @property
    def n_pairs(self) -> int:
        return int(self.pair_sample.shape[0])

    @property
    def n_texels(self) -> int:
        return self.map_size[0] * self.map_size[1]

    @property
    def dtype(self) -> torch.dtype:
        return self.radiance.dtype

    @property
    def device(self) -> torch.device:
        return self.radiance.device

    # -- coverage -----------------------------------------------------------------------------
    def samples_per_texel(self) -> Tensor:
        """``[H, W]`` int64: how many samples fall in each texel."""
        H, W = self.map_size
        return torch.bincount(self.texel, minlength=H * W).reshape(H, W)

    def footprint(self) -> Tensor:
        """``[T]`` bool: texels some sample reads — its nearest texel, and with bilinear observations any
        of its texels (bilinear taps or texture footprint) with a positive weight (observed too, through their
        neighbours' samples)."""
        seen = torch.zeros(self.n_texels, dtype=torch.bool, device=self.device)
        seen[self.texel] = True
        if self.bilinear_index is not None:
            seen[self.bilinear_index[self.bilinear_weight > 0]] = True
        if self.taps is not None:
            seen[self.taps.index.long()] = True
        return seen

    def views_per_texel(self) -> Tensor:
        """``[H, W]`` int64: in how many distinct views each texel was seen (by a kept sample)."""
        H, W = self.map_size
        key = torch.unique(self.texel * max(self.n_views, 1) + self.view)
        return torch.bincount(key // max(self.n_views, 1), minlength=H * W).reshape(H, W)

    def lit_texels(self) -> int:
        return int((self.samples_per_texel() > 0).sum())

    # -- evaluation ---------------------------------------------------------------------------
    def per_sample(self, maps: Mapping[str, Tensor], sampling: str = "nearest") -> dict[str, Tensor]:
        """Sample maps ``name → [H, W, C]`` at every observation → ``name → [S, C]``."""
        out = {}
        for k, m in maps.items():
            if m.dim() != 3 or tuple(m.shape[:2]) != tuple(self.map_size):
                raise ObservationError(
                    f"map '{k}' must be [H, W, C] with (H, W) = {self.map_size} (the observations' map size), "
                    f"got {tuple(m.shape)}")
            flat = m.reshape(-1, m.shape[-1])
            if sampling == "nearest":
                out[k] = flat[self.texel]
            elif sampling == "bilinear":
                if self.taps is not None:
                    out[k] = self.taps.read(flat)
                elif self.bilinear_index is None:
                    raise ObservationError("bilinear sampling needs observations built with bilinear=True")
                else:
                    out[k] = (flat[self.bilinear_index] * self.bilinear_weight.unsqueeze(-1).to(m.dtype)).sum(-2)
            else:
                raise ObservationError(f"sampling must be 'nearest' or 'bilinear', got {sampling!r}")
        return out

    def predict(self, model: Model, params: Mapping[str, Tensor]) -> Tensor:
        """Predicted radiance ``[S, 3]`` from per-sample canonical parameters ``name → [S, C]``.

        ``L_s = Σ_pairs E·V · model.cosine_brdf(angles, p_s)`` (+ environment terms), accumulated
        with ``index_add``; differentiable (reverse and forward mode) with respect to ``params``.
        """
        return self.predict_rows(model, params, 0, self.n_samples)

    def predict_rows(self, model: Model, params: Mapping[str, Tensor], start: int, stop: int) -> Tensor:
        """Predicted radiance ``[stop − start, 3]`` of the samples ``start … stop − 1`` from their canonical
        parameters ``name → [stop − start, C]``: :meth:`predict` on a block of samples, for sums whose autograd
        graph would be too large over all of them at once (:func:`capture.fit.texel.jacobian_blocks`)."""
        return radiance_sum(model, params, stop - start, *self._terms(start, stop, "predict_rows"))

    def jacobian_rows(self, model: Model, params: Mapping[str, Tensor], start: int,
                      stop: int) -> tuple[Tensor, dict[str, Tensor]] | None:
        """:meth:`predict_rows` and its derivatives with respect to ``params`` in closed form,
        ``(radiance [n, 3], {name: [n, 3, C], or the diagonal [n, 3] of a parameter acting per channel})``, or None
        where the model has none or the photos have an environment light
        (:func:`renderer.shading.radiance_jacobian`)."""
        return radiance_jacobian(model, params, stop - start, *self._terms(start, stop, "jacobian_rows"))

    def _terms(self, start: int, stop: int, fn: str) -> tuple[list, list]:
        """The light pairs and environment terms of the samples ``start … stop − 1``, in the form
        :func:`renderer.shading.radiance_sum` reads (rows and outputs numbered from ``start``)."""
        if not 0 <= start <= stop <= self.n_samples:
            raise ObservationError(f"{fn}: need 0 ≤ start ≤ stop ≤ {self.n_samples}, got {start}, {stop}")
        if start == 0 and stop == self.n_samples:
            pairs = [(self.pair_sample, self.pair_sample, self.angles, self.irradiance)]
            envs = [(light, idx, idx, self.n[idx], self.v[idx]) for light, idx in self.env_terms]
            return pairs, envs
        span = self._pair_span(start, stop)
        # a slice (views, no copy) when the pairs are sorted by sample, else the block's pairs gathered
        q = slice(*span) if span is not None else \
            torch.nonzero((self.pair_sample >= start) & (self.pair_sample < stop), as_tuple=True)[0]
        local = self.pair_sample[q] - start
        pairs = [(local, local, self.angles[q], self.irradiance[q])]
        envs = []
        for light, idx in self.env_terms:
            idx = idx[(idx >= start) & (idx < stop)]
            envs.append((light, idx - start, idx - start, self.n[idx], self.v[idx]))
        return pairs, envs

    def _pair_span(self, start: int, stop: int) -> tuple[int, int] | None:
        """``(lo, hi)``: the pairs of the samples ``start … stop − 1`` as one range of pairs when the pairs are
        sorted by sample (:func:`observe_views` sorts them; :meth:`select` keeps their order), else None. Whether
        they are is checked once per ``pair_sample`` tensor."""
        ps = self.pair_sample
        known = getattr(self, "_pairs_sorted", None)
        if known is None or known[0] is not ps:
            known = (ps, ps.numel() < 2 or bool((ps[1:] >= ps[:-1]).all()))
            self._pairs_sorted = known
        if not known[1]:
            return None
        lo, hi = torch.searchsorted(ps, torch.tensor([start, stop], dtype=ps.dtype, device=ps.device)).tolist()
        return lo, hi

    # -- subsets and casts --------------------------------------------------------------------
    def select(self, keep: Tensor) -> Observations:
        """Observations restricted to the samples where ``keep [S]`` (bool) holds (pairs follow)."""
        if keep.dtype != torch.bool or keep.shape != (self.n_samples,):
            raise ObservationError(f"select: keep must be a bool tensor [{self.n_samples}], got {keep.dtype} "
                                   f"{tuple(keep.shape)}")
        new_index = torch.full((self.n_samples,), -1, dtype=torch.long, device=self.device)
        new_index[keep] = torch.arange(int(keep.sum()), device=self.device)
        pk = keep[self.pair_sample]
        opt = lambda x: None if x is None else x[keep]  # noqa: E731
        envs = []
        for light, idx in self.env_terms:
            ek = keep[idx]
            envs.append((light, new_index[idx[ek]]))
        return Observations(
            texel=self.texel[keep], map_size=self.map_size, radiance=self.radiance[keep], weight=self.weight[keep],
            pair_sample=new_index[self.pair_sample[pk]], pair_light=self.pair_light[pk], angles=self.angles[pk],
            irradiance=self.irradiance[pk], view=self.view[keep], pixel=self.pixel[keep], uv=opt(self.uv),
            n=opt(self.n), v=opt(self.v), bilinear_index=opt(self.bilinear_index),
            bilinear_weight=opt(self.bilinear_weight), taps=self.taps.select(keep) if self.taps is not None else None,
            env_terms=envs, drops=dict(self.drops),
            n_views=self.n_views, image_size=list(self.image_size), n_lights=self.n_lights,
            noise_residual=opt(self.noise_residual))

    def select_views(self, views: Sequence[int]) -> Observations:
        """Only the samples of the given view indices."""
        v = torch.as_tensor(list(views), dtype=torch.long, device=self.device)
        return self.select(torch.isin(self.view, v))

    def to(self, device=None, dtype=None) -> Observations:
        """Move to ``device`` and cast floating tensors to ``dtype``."""
        def mv(x):
            if isinstance(x, Tensor):
                return x.to(device=device, dtype=dtype if x.is_floating_point() else None)
            if isinstance(x, (Angles, TexelTaps)):
                return x.to(device=device, dtype=dtype)
            return x
        kw = {f.name: mv(getattr(self, f.name)) for f in fields(self)}
        kw["env_terms"] = [(light, idx.to(device=device)) for light, idx in self.env_terms]
        return Observations(**kw)


def _check_image(img: Tensor, h: int, w: int, where: str) -> Tensor:
    if not isinstance(img, Tensor) or img.dim() != 3 or img.shape[-1] != 3:
        raise ObservationError(f"{where}: photo must be a tensor [H, W, 3] (linear RGB), got "
                               f"{tuple(img.shape) if isinstance(img, Tensor) else type(img).__name__}")
    if tuple(img.shape[:2]) != (h, w):
        raise ObservationError(f"{where}: photo is {img.shape[1]}×{img.shape[0]} pixels but the camera is "
                               f"{w}×{h}; resize the photo or fix the camera's width/height")
    return img


#: Immerkær's noise mask (1996): zero on planes and on the quadratic terms x², y² of an image, so that on smooth
#: shading its response is the noise; the sum of its squared entries is 36, so ``(N ∗ I) / 6`` has the noise's std.
_IMMERKAER = torch.tensor([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]]) / 6.0


def noise_residual(photo: Tensor, valid: Tensor) -> Tensor:
    """``[H, W, 3]`` image-space noise residual of a linear photo ``[H, W, 3]``: Immerkær's mask (J. Immerkær, "Fast
    noise variance estimation", CVIU 1996) divided by 6, so that on smooth shading under white noise of std σ each
    value has std σ. NaN where the 3 × 3 neighbourhood leaves ``valid [H, W]`` (bool: object pixels, finite, not
    clipped). Edges and highlights give large values at few pixels, so the noise level is read from robust
    statistics (a low quantile, :func:`capture.fit.noise.photo_noise_ratio`)."""
    img = photo.permute(2, 0, 1)[:, None]                                            # [3, 1, H, W]
    k = _IMMERKAER.to(img)[None, None]
    r = F.conv2d(F.pad(img, (1, 1, 1, 1)), k)[:, 0].permute(1, 2, 0)
    # 3 × 3 erosion, outside the image counting as invalid
    ok = -F.max_pool2d(-F.pad(valid[None, None].to(img.dtype), (1, 1, 1, 1)), 3, stride=1)[0, 0] > 0.5
    ok = ok & torch.isfinite(r).all(-1)
    return torch.where(ok[..., None], r, torch.full_like(r, float("nan")))


def observe_views(prepared: Sequence, photos: Sequence[Tensor], map_size: tuple[int, int], *,
                  exposure: Sequence[float] | float = 1.0, saturation: float | None = None,
                  lights: Sequence | None = None, bilinear: bool = False, dtype=None,
                  clipped: Sequence[Tensor] | None = None, footprints: bool = False,
                  texels: Sequence[TexelTaps] | None = None) -> Observations:
    """Build :class:`Observations` from prepared G-buffers and the photos of the same views.

    Args:
        prepared: per view a :class:`renderer.shading.Prepared` (``prepare(gbuffer, mesh, lights)``)
            from a G-buffer rendered with ``supersample=1`` (one sample per pixel centre).
        photos: per view the photo ``[H, W, 3]`` in *linear* RGB (decode PNG/sRGB first), as stored,
            i.e. before division by the exposure.
        map_size: ``(H, W)`` of the material maps.
        exposure: the linear factor between radiance and pixel value, per view or one for all (> 0).
        saturation: pixel value (before the exposure division) at or above which a channel counts as
            clipped; ``None`` = never (float EXR without a white level). 8-bit photos: pass ~0.999.
        lights: the scene's point/directional lights in order (to attribute pairs to lights and to
            tell shadowed from unlit); default: taken from the first view's prepared terms.
        bilinear: also store bilinear texel indices/weights (for bilinear-sampling solvers/renders).
        dtype: floating dtype of the result (default: the photos').
        clipped: optional per-view ``[H, W]`` bool masks of saturated pixels (e.g.
            :attr:`capture.dataset.Photo.saturated`), used in addition to ``saturation``.
        footprints: the G-buffers hold sub-pixel samples (:func:`renderer.gbuffer.render_footprint`, any number
            per pixel): each sample's ``weight`` is its G-buffer weight (its share of its pixel) and its
            ``radiance`` its pixel's value; :func:`capture.footprint.observe_footprints` groups them into pixels.
            The drop counts then count samples, and ``background`` is not counted. The samples then carry no
            ``noise_residual`` (the noise is measured per pixel, :class:`capture.footprint.PixelFootprints`), and
            no normals and view directions (``n``, ``v``: None; zeros in a view without environment lights when
            another has them) unless an environment light reads them: the fit reads the pairs' angles.
        texels: per view a :class:`TexelTaps` of one row per G-buffer sample: the texels each sample reads (its
            texture footprint, :func:`capture.footprint.texture_footprints`) instead of the bilinear read at its uv;
            with ``bilinear`` the kept samples' rows become ``taps``. The samples then carry no ``uv`` (None; their
            ``texel`` is still the one their uv falls in).

    Returns:
        :class:`Observations` with the drop counts filled in.

    Raises:
        ObservationError: mismatched lists, photo size ≠ camera size, bad exposure, no sample left.

    A caller that makes its views one at a time extracts each as it is made with a :class:`ViewExtractor` (what
    this function does for all views at once), so that no view's prepared G-buffer outlives its extraction.
    """
    if len(prepared) != len(photos):
        raise ObservationError(f"got {len(prepared)} prepared views but {len(photos)} photos; pass one photo per view")
    if texels is not None and len(texels) != len(prepared):
        raise ObservationError(f"texels: need one TexelTaps per view, got {len(texels)} for "
                               f"{len(prepared)} views")
    extractor = ViewExtractor(len(prepared), map_size, exposure=exposure, saturation=saturation, clipped=clipped,
                              footprints=footprints, dtype=dtype)
    parts = per_view(lambda vi: extractor.view(vi, prepared[vi], photos[vi],
                                               None if texels is None else texels[vi]), len(prepared))
    return extractor.observations(parts, lights=lights, bilinear=bilinear)


@dataclass
class ViewSamples:
    """The kept samples of one view (:meth:`ViewExtractor.view`), sample indices local to the view.

    Attributes:
        view: the view's index; size: its ``(height, width)``.
        columns: the per-sample tensors (``radiance``, ``pixel``, ``weight``; ``uv``, ``n``, ``v``, ``noise``, each
            None where the samples do not keep it, and ``texel`` in place of ``uv`` with texture footprints) and
            ``tex`` (:class:`TexelTaps` or None), consumed by :meth:`ViewExtractor.observations`.
        pairs: the kept (sample, light) pairs in sample order, consumed like ``columns``: ``sample``, ``term`` (the
            pair's light as its index among ``term_lights``), ``irradiance`` and the cosines by :class:`Angles` field.
        term_lights: the lights of the prepared G-buffer's terms, in order (which also decide the scene's lights
            when none are given: the first view's).
        envs: environment terms ``(light, sample index)``; drops: this view's drop counts (:data:`DROP_REASONS`).
        n_samples: the kept samples.
    """

    view: int
    size: tuple[int, int]
    columns: dict
    pairs: dict
    term_lights: list
    envs: list
    drops: dict
    n_samples: int


_ANGLE_FIELDS = ("nl", "nv", "nh", "lh", "lv")


class ViewExtractor:
    """:func:`observe_views` one view at a time: :meth:`view` keeps a view's valid samples from its prepared
    G-buffer and photo (which the caller may free at once), :meth:`observations` joins the views' samples, releasing
    each view's tensors as soon as they are copied. Options as :func:`observe_views`'s, validated here once.

    Holding every view's prepared G-buffer until all were extracted, and every view's samples until all were joined,
    took three times the result's memory: the pixel footprints of 32 photos of 256² (0.48 GiB) raised the resident
    memory by 1.50 GiB.
    """

    def __init__(self, n_views: int, map_size: tuple[int, int], *, exposure: Sequence[float] | float = 1.0,
                 saturation: float | None = None, clipped: Sequence[Tensor] | None = None, footprints: bool = False,
                 dtype=None):
        if n_views == 0:
            raise ObservationError("no views: pass at least one prepared G-buffer and its photo")
        if not (isinstance(map_size, Sequence) and len(map_size) == 2 and all(int(x) >= 1 for x in map_size)):
            raise ObservationError(f"map_size must be (H, W) with positive integers, got {map_size!r}")
        exposures = ([float(exposure)] * n_views if isinstance(exposure, (int, float))
                     else [float(e) for e in exposure])
        if len(exposures) != n_views or any(not (e > 0 and e < float("inf")) for e in exposures):
            raise ObservationError(f"exposure must be one positive finite number or one per view, got {exposure!r}")
        if clipped is not None and len(clipped) != n_views:
            raise ObservationError(f"clipped: need one mask per view, got {len(clipped)} for {n_views} views")
        self.n_views = n_views
        self.map_size = (int(map_size[0]), int(map_size[1]))
        self.exposures, self.saturation, self.clipped = exposures, saturation, clipped
        self.footprints, self.dtype = footprints, dtype

    def view(self, vi: int, prep, photo: Tensor, texels: TexelTaps | None = None) -> ViewSamples:
        """The kept samples of view ``vi``: its prepared G-buffer ``prep``, its photo ``[H, W, 3]`` and, for pixel
        footprints, its rays' texture footprints ``texels`` (one row per G-buffer sample)."""
        if not 0 <= vi < self.n_views:
            raise ObservationError(f"view index {vi} is outside the {self.n_views} views")
        g = prep.gbuffer
        if g is None:
            raise ObservationError(f"view {vi}: Prepared has no G-buffer; call renderer.shading.prepare(gbuffer, ...)")
        if g.supersample != 1 and not self.footprints:
            raise ObservationError(f"view {vi}: observations need a G-buffer with supersample=1 (one sample per "
                                   f"pixel), got supersample={g.supersample}")
        drops = dict.fromkeys(DROP_REASONS, 0)
        photo = _check_image(photo, g.height, g.width, f"view {vi}")
        dt = self.dtype or (photo.dtype if photo.is_floating_point() else torch.float32)
        photo = photo.to(dtype=dt, device=g.position.device)
        flat = photo.reshape(-1, 3)
        n_pix = g.height * g.width
        drops["background"] += 0 if self.footprints else n_pix - len(g)
        pix = flat[g.pixel]                                    # [N, 3] for every hit sample
        finite = torch.isfinite(pix).all(-1)
        saturation = self.saturation
        clipped_s = finite & ((pix >= saturation).any(-1) if saturation is not None else torch.zeros_like(finite))
        if self.clipped is not None:
            clipped_s = clipped_s | (finite & self.clipped[vi].to(finite.device).reshape(-1)[g.pixel])
        facing = (g.normal * g.view).sum(-1) > 0
        lit = torch.zeros(len(g), dtype=torch.bool, device=finite.device)
        lit[prep.sample] = True
        # samples one of the view's lights faces geometrically (for shadowed vs unlit), as prepare found them
        could = prep.faced if prep.faced is not None else lit
        ok = finite & ~clipped_s & facing & lit
        drops["nonfinite"] += int((~finite).sum())
        drops["clipped"] += int(clipped_s.sum())
        rest = finite & ~clipped_s
        drops["backfacing"] += int((rest & ~facing).sum())
        rest = rest & facing
        drops["shadowed"] += int((rest & ~lit & could).sum())
        drops["unlit"] += int((rest & ~lit & ~could).sum())
        keep_g = torch.nonzero(ok).squeeze(-1)                 # G-buffer indices kept
        local = torch.full((len(g),), -1, dtype=torch.long, device=finite.device)
        local[keep_g] = torch.arange(len(keep_g), device=finite.device)
        pairs = _view_pairs(prep, ok, local, dt)
        envs = [(e.light, local[e.index[ok[e.index]]]) for e in prep.envs]
        exposure = self.exposures[vi]
        tex = None
        if texels is not None:
            if not isinstance(texels, TexelTaps) or texels.n_rows != len(g):
                raise ObservationError(f"view {vi}: texels must be TexelTaps with one row per G-buffer sample "
                                       f"({len(g)}), got {type(texels).__name__}"
                                       + (f" of {texels.n_rows} rows" if isinstance(texels, TexelTaps) else ""))
            tex = texels.select(ok).to(dtype=dt)
        columns = dict(tex=tex, radiance=pix[keep_g] / exposure, pixel=g.pixel[keep_g],
                       weight=g.weight[keep_g].to(dt) if self.footprints else torch.ones(len(keep_g), dtype=dt))
        # sub-pixel samples keep only what the fit and the metrics read of them (the normals, view directions and
        # a noise per sample are 32 bytes per sample, 0.17 GB on the 5.3 M rays of 32 × 512² photos), and with
        # texture footprints their texel instead of their uv
        uv = g.uv[keep_g].to(dt)
        if tex is not None:
            columns.update(texel=texel_of(uv, *self.map_size), uv=None)
        else:
            columns.update(uv=uv)
        del uv
        if self.footprints:
            # (environment lights read each sample's normal and view direction: kept in a view that has them)
            vec = (lambda x: x[keep_g].to(dt)) if envs else (lambda x: None)  # noqa: E731
            columns.update(n=vec(g.normal), v=vec(g.view), noise=None)
        else:
            valid = torch.zeros(n_pix, dtype=torch.bool, device=finite.device)
            valid[g.pixel] = finite & ~clipped_s
            resid = noise_residual(torch.nan_to_num(photo / exposure), valid.reshape(g.height, g.width))
            columns.update(n=g.normal[keep_g].to(dt), v=g.view[keep_g].to(dt),
                           noise=resid.reshape(-1, 3)[g.pixel[keep_g]])
        return ViewSamples(vi, (g.height, g.width), columns, pairs, [t.light for t in prep.lights], envs, drops,
                           len(keep_g))

    def observations(self, parts: list[ViewSamples], *, lights: Sequence | None = None,
                     bilinear: bool = False) -> Observations:
        """The views' samples ``parts`` (one :meth:`view` each, in view order) as one :class:`Observations`, sample
        indices offset per view. ``lights``: the scene's point/directional lights in order (None: the first view's
        terms'). Each view's tensors are released from ``parts`` as they are copied, so the parts cannot be joined
        twice."""
        if len(parts) != self.n_views or any(not isinstance(p, ViewSamples) for p in parts):
            raise ObservationError(f"need the {self.n_views} views' samples (ViewExtractor.view), got {len(parts)}")
        if any(not p.columns for p in parts):
            raise ObservationError("these views' samples were already joined: extract the views again")
        with_tex = [p.columns["tex"] is not None for p in parts]
        if any(with_tex) and not all(with_tex):
            raise ObservationError("some views have texture footprints (texels) and some not: give every view's or "
                                   "none")
        if lights is None:
            lights = []
            for x in parts[0].term_lights:
                if all(x is not y for y in lights):
                    lights.append(x)
        light_id = {id(x): i for i, x in enumerate(lights)}
        drops = {k: sum(p.drops[k] for p in parts) for k in DROP_REASONS}
        H, W = self.map_size
        offs, S = [], 0
        for p in parts:
            offs.append(S)
            S += p.n_samples
        if S == 0:
            raise ObservationError(f"no valid sample in any view (dropped: {drops}); check that the cameras see the "
                                   f"mesh, the lights face it, and the photos are not saturated or NaN")

        columns, pairs = [p.columns for p in parts], [p.pairs for p in parts]

        def cat(key):           # one column of every view, each view's tensor released once copied
            have = [c[key] for c in columns if c[key] is not None]
            if not have:        # a column no view keeps (the sub-pixel samples' vectors and noise)
                for c in columns:
                    c.pop(key)
                return None
            for c, p in zip(columns, parts, strict=True):      # zeros in the views that do not keep it (read by
                if c[key] is None:                              # nothing: their samples have no term that reads it)
                    c[key] = have[0].new_zeros(p.n_samples, *have[0].shape[1:])
            return _take(columns, key)

        for o, p in zip(offs, pairs, strict=True):      # the pairs' samples and lights in the joined numbering
            p["sample"] = p["sample"] + o
        for lts, p in zip((q.term_lights for q in parts), pairs, strict=True):
            table = [light_id.get(id(x), -1) for x in lts] or [-1]
            p["term"] = torch.tensor(table, dtype=torch.int32, device=p["term"].device)[p["term"]]
        pair_sample, pair_light, irradiance = (_take(pairs, f) for f in ("sample", "term", "irradiance"))
        angles = Angles(*(_take(pairs, f) for f in _ANGLE_FIELDS))
        envs_all: dict[int, tuple] = {}
        for o, p in zip(offs, parts, strict=True):
            for light, idx in p.envs:
                envs_all.setdefault(id(light), (light, []))[1].append(idx + o)
            p.envs = []
        uv = cat("uv")
        texel = cat("texel") if "texel" in columns[0] else texel_of(uv, H, W)
        view = torch.cat([torch.full((p.n_samples,), p.view, dtype=torch.long) for p in parts])
        bi = bw = taps = None
        tex = [c.pop("tex") for c in columns]
        if bilinear and with_tex[0]:
            # TexelTaps.cat's rows, each view's arrays released once copied (the taps are the samples' largest part)
            start = TexelTaps.cat([TexelTaps(t.start, t.index[:0], t.weight[:0]) for t in tex]).start
            tex = [{"index": t.index, "weight": t.weight} for t in tex]
            taps = TexelTaps(start, _take(tex, "index"), _take(tex, "weight"))
        elif bilinear:
            bi, bw = bilinear_weights(uv, H, W)
        del tex
        return Observations(
            texel=texel, map_size=(H, W), radiance=cat("radiance"),
            weight=cat("weight").to(texel.device), pair_sample=pair_sample, pair_light=pair_light, angles=angles,
            irradiance=irradiance, view=view.to(texel.device), pixel=cat("pixel"), uv=uv, n=cat("n"), v=cat("v"),
            bilinear_index=bi, bilinear_weight=bw, taps=taps,
            env_terms=[(light, torch.cat(idx)) for light, idx in envs_all.values()], drops=drops,
            n_views=len(parts), image_size=[p.size for p in parts], n_lights=max(len(lights), 1),
            noise_residual=cat("noise"))


def _take(parts: list[dict], key: str) -> Tensor:
    """``torch.cat`` of the entry ``key`` of every dict in ``parts``, each removed from its dict, and the heap memory
    they leave freed returned (:func:`renderer.device.release_memory`)."""
    out = torch.cat([p.pop(key) for p in parts])
    release_memory()
    return out


def _view_pairs(prep, ok: Tensor, local: Tensor, dt) -> dict:
    """The kept (sample, light) pairs of a view, sorted by sample (:attr:`ViewSamples.pairs`): ``sample`` by its index
    ``local`` among the view's kept ones, ``term`` the light's index in ``prep.lights``, ``irradiance`` E·V and the
    cosines by :class:`Angles` field."""
    pairs = []
    for ti, t in enumerate(prep.lights):
        sel = ok[t.index]
        if not bool(sel.any()):
            continue
        pairs.append((local[t.index[sel]], torch.full((int(sel.sum()),), ti, dtype=torch.long, device=ok.device),
                      t.angles[sel].to(dtype=dt), t.irradiance[sel].to(dt)))
    if not pairs:
        empty = torch.zeros(0, 1, dtype=dt, device=ok.device)
        no = torch.zeros(0, dtype=torch.long, device=ok.device)
        return {"sample": no, "term": no, "irradiance": torch.zeros(0, 3, dtype=dt, device=ok.device),
                **dict.fromkeys(_ANGLE_FIELDS, empty)}
    s = torch.cat([p[0] for p in pairs])
    # the lights' pairs merged in sample order here, a view at a time, so that the views' pairs concatenated
    # (offset by view) are sorted by sample with no permutation of all of them: Observations.predict_rows then
    # reads a block's pairs as one slice
    one = len(pairs) == 1 and bool((s[1:] >= s[:-1]).all())
    order = None if one else torch.argsort(s, stable=True)

    def merged(values):
        return values[0] if one else torch.cat(values)[order]

    return {"sample": merged([p[0] for p in pairs]), "term": merged([p[1] for p in pairs]),
            "irradiance": merged([p[3] for p in pairs]),
            **{f: merged([getattr(p[2], f) for p in pairs]) for f in _ANGLE_FIELDS}}


def _random_unit(n: int, gen: torch.Generator, dtype) -> Tensor:
    x = torch.randn(n, 3, generator=gen, dtype=dtype)
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def synthetic_observations(model: Model, maps: Mapping[str, Tensor], samples_per_texel: int = 16, n_lights: int = 2,
                           n_views: int = 8, irradiance: float = 3.0, seed: int = 0, noise: float = 0.0,
                           highlight_fraction: float = 0.5, dtype=torch.float64) -> Observations:
    """Observations built directly from :class:`materials.Angles` and a model — no renderer.

    For solver tests: every texel of the maps gets ``samples_per_texel`` samples with random
    normal/light/view in the upper hemisphere of a per-sample frame (front-facing for every
    light), each assigned to a random "view" in ``range(n_views)``. A fraction
    ``highlight_fraction`` of the pairs has the light near the mirror direction of the view
    (within ~0.3 rad), so that specular lobes are observed. Radiance is rendered by ``model``
    from ``maps`` with nearest sampling, plus Gaussian noise of relative std ``noise``.

    Args:
        model: the material model; maps: ``name → [H, W, C]`` holding exactly ``model.params``.
        irradiance: E of every light (white).
    """
    if samples_per_texel < 1 or n_lights < 1 or n_views < 1:
        raise ObservationError("samples_per_texel, n_lights and n_views must be ≥ 1")
    H, W = next(iter(maps.values())).shape[:2]
    gen = torch.Generator().manual_seed(seed)
    T = H * W
    S = T * samples_per_texel
    texel = torch.arange(T).repeat_interleave(samples_per_texel)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)

    def upper(n):
        d = _random_unit(n, gen, dtype)
        d[:, 2] = d[:, 2].abs() * 0.95 + 0.05
        return d / d.norm(dim=-1, keepdim=True)

    v = upper(S)
    n = z.expand(S, 3)
    ps, pl, ang = [], [], []
    for k in range(n_lights):
        l = upper(S)
        mirror = 2 * v[:, 2:3] * z - v
        near = mirror + 0.3 * _random_unit(S, gen, dtype) * torch.rand(S, 1, generator=gen, dtype=dtype)
        near[:, 2] = near[:, 2].clamp_min(0.05)
        near = near / near.norm(dim=-1, keepdim=True)
        pick = torch.rand(S, 1, generator=gen, dtype=dtype) < highlight_fraction
        l = torch.where(pick, near, l)
        ps.append(torch.arange(S))
        pl.append(torch.full((S,), k, dtype=torch.int32))
        ang.append(Angles.from_vectors(n, l, v))
    angles = Angles(*(torch.cat([getattr(a, f) for a in ang]) for f in ("nl", "nv", "nh", "lh", "lv")))
    Q = S * n_lights
    obs = Observations(
        texel=texel, map_size=(H, W), radiance=torch.zeros(S, 3, dtype=dtype), weight=torch.ones(S, dtype=dtype),
        pair_sample=torch.cat(ps), pair_light=torch.cat(pl), angles=angles,
        irradiance=torch.full((Q, 3), float(irradiance), dtype=dtype),
        view=torch.randint(0, n_views, (S,), generator=gen), pixel=torch.arange(S), n=n.clone(), v=v,
        drops=dict.fromkeys(DROP_REASONS, 0), n_views=n_views, n_lights=n_lights)
    with torch.no_grad():
        clean = obs.predict(model, obs.per_sample({k: m.to(dtype) for k, m in maps.items()}))
    if noise > 0:
        clean = clean * (1 + noise * torch.randn(clean.shape, generator=gen, dtype=dtype))
    obs.radiance = clean
    return obs
