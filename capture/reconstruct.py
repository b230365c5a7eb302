"""The main job: dataset → material maps, confidence, re-renders and a report, written atomically.

:func:`reconstruct` runs these stages (each timed in the report):

1. ``load``: :func:`capture.dataset.load_dataset` (validates; :class:`DatasetError` names file and field).
2. ``gbuffer``: one G-buffer per view (``supersample=1``) and :func:`renderer.shading.prepare`
   (shadow rays) — geometry is known, so this happens once whatever the model and solver.
3. ``observe``: :func:`capture.observations.observe_views` — valid samples only, drop reasons counted.
4. ``select`` (``model="auto"`` only): fit the candidates cheapest first — ``lambert`` →
   ``ggx-lambert`` → ``gotanda2012-layered`` (when registered) — each as the final fit would (coat
   scalars included), on all views but a held-out quarter, and stop as soon as a richer model lowers
   the held-out mean absolute error by less than ``auto_gain`` (5 %), or once a model explains its training
   photos within their noise (χ² per residual ≤ :data:`AUTO_EXPLAINED_CHI2`). Maps larger than
   :data:`AUTO_TRIAL_TEXTURE`² are judged on a coarser copy of the problem (:func:`_trial_observations`) —
   after the cheapest candidate is fitted at full size, and chosen at once if it explains the photos there
   (:func:`_explained_at_full_size`: coarse maps cannot explain a fine texture under any model).
   The chosen model is then refit on all views at full size.
5. ``solve``: :func:`capture.fit.fast.solve_fast` (default) or :func:`capture.fit.adam.solve_adam`.
6. ``write``: maps (EXR linear + PNG), confidence maps (EXR + a PNG preview with a colour bar), coverage, the
   labelled views pages (photo | re-render | relative error, :func:`capture.plots.plot_views`), ``report.json``,
   ``summary.txt`` (with advice on the directions the photos miss), ``mesh.obj`` — into a
   temporary folder next to ``out_dir`` that is renamed into place at the end, so a reader never
   sees a half-written output and a failure leaves nothing behind.

Unobservable parameters (decision): a parameter the photos do not pin down in a texel — its
marginal posterior std (:func:`capture.fit.observability.posterior_std`) at or above the threshold, e.g.
roughness and f0 where no highlight was seen, or albedo and f0 trading off — is *not* an error: it
is filled from observable neighbours (pull-push) — or, with reflectance sharing (the default for
bilinear datasets), keeps its material's estimate — flagged in ``unobservable_<name>.png``, its std
written to ``confidence_<name>.exr`` (NaN where unobserved), and counted in the report; errors
against ground truth are reported on all observed texels and on the observable ones. The report
carries a warning (``warnings``) when a parameter is unobservable in *every* observed texel (every
value of that map is a fill, not a measurement), and when in at least :data:`UNRESOLVED_WARN` of the
roughness-observable texels the fitted lobe is narrower than the photos' direction sampling resolves
(:func:`unresolved_roughness`: a near-mirror surface, whose roughness is then only an upper bound).
"""

from __future__ import annotations

import inspect
import math
import operator
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from materials import KnownParams
from materials.params import CANONICAL, preview_transfer
from materials.roughness import half_max_angle
from renderer.device import release_memory
from renderer.gbuffer import check_psf_sigma

from .fit import (
    LOSSES,
    NOISE,
    FitResult,
    Layout,
    SolverError,
    photo_noise_ratio,
    photo_sigma,
    pyramid_size,
    scaled_sigma,
    solve_adam,
    solve_fast,
    upsample_maps,
)
from .fit.options import FitOptions
from .observations import Observations, observe_views

if TYPE_CHECKING:
    from materials.model import Model

    from .dataset import Dataset
    from .footprint import PixelFootprints
    from .progress import Progress

__all__ = ["reconstruct", "Report", "ReconstructionError", "AUTO_CANDIDATES", "AUTO_EXPLAINED_CHI2",
           "AUTO_TRIAL_TEXTURE", "AUTO_TRIAL_MIN_SAMPLES", "SCALARS", "UNRESOLVED_WARN", "unresolved_roughness"]

#: Candidate models of ``model="auto"``, cheapest first (names not registered are skipped).
AUTO_CANDIDATES = ("lambert", "ggx-lambert", "gotanda2012-layered")

#: ``model="auto"`` stops at a candidate whose trial fit explains its training photos with a χ² per residual at most
#: this (:func:`_misfit`: residuals against the 1 % noise model, scaled to the photos' noise measured in image space):
#: on average within 2 σ of the noise. Measured for the model that rendered the photos (trial fits, 2 threads): 0.0
#: noise-free Lambert (nearest), 0.62 noise-free GGX + Lambert (bilinear, 128 px, 64² maps), 2.9 with shot noise of a
#: 3 000 e⁻ full well, 1.9 at 1 000 e⁻ with 8-bit sRGB; for a model poorer than the photos' 280 – 83 000 (Lambert on
#: specular scenes, GGX + Lambert on a coated one 16 700). On the default scene (256² maps judged on a 128² copy) the
#: copy itself misfits: GGX + Lambert reads 318 there and the layered trial still runs (docs/log.md, "auto stops at
#: the model that explains its photos").
AUTO_EXPLAINED_CHI2 = 4.0
#: ``model="auto"`` takes a richer candidate whose held-out error did not drop when its training χ² per residual is
#: at least this factor below the simpler one's and the simpler one does not explain its photos (χ² above
#: ``auto_chi2``): held-out errors of a few views miss what a model cannot fit at all (a grazing-only capture, a
#: chrome object: Lambert's χ² 10²–10⁸ × the specular model's), while a nested model's extra parameters lower the
#: training χ² of photos that need none by far less than 10× (a few extra parameters per texel against tens of
#: residuals).
AUTO_CHI2_GAIN = 10.0
#: The final fit's χ² per residual above which the summary warns that the photos are not explained: residuals of
#: 10 σ on average, 10 % of the signal under the 1 % noise model — far beyond noise, sub-pixel sampling or
#: quantisation (photos of the fitted model read 0–3).
UNEXPLAINED_CHI2 = 100.0
#: On a dataset with ground truth, the fit's χ² per residual above this multiple of the true maps' (both predicted
#: through the fit's own image formation, :func:`_report_truth_chi2`) and above :data:`TRUTH_CHI2_FLOOR` makes the
#: summary warn that the solver stopped short. Measured (fit / true maps, docs/image-formation.md "What to expect"):
#: 8 × 1024² photos on 256² maps without the neighbour proposals 0.535 / 0.053 (10×, 55 texels stuck at one border)
#: and with them 0.058 (1.1×); the 128² Mitsuba sphere 0.481 / 0.356 (1.35×), the 256² one 0.209 / 0.262 (0.360, 1.4×,
#: before the footprint-only texels started at their fitted neighbours' values); 32 × 512² photos 0.624 / 0.570.
TRUTH_CHI2_RATIO = 2.0
#: ... and above this χ² per residual: below it the residuals are a third of σ or less and the ratio of two fits that
#: both explain the photos far inside their noise says nothing.
TRUTH_CHI2_FLOOR = 0.1


class ReconstructionError(ValueError):
    """Bad reconstruction input: unknown model, existing output folder, nothing observable."""


@dataclass
class Report:
    """What :func:`reconstruct` did (also written as ``report.json``)."""

    model: str
    solver: str
    out_dir: str
    times: dict = field(default_factory=dict)
    samples: dict = field(default_factory=dict)
    drops: dict = field(default_factory=dict)
    coverage: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    selection: list = field(default_factory=list)
    fit: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)
    views: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    model_spec: dict = field(default_factory=dict)
    memory: dict = field(default_factory=dict)
    device: str = "cpu"             #: where the fits ran (:mod:`renderer.device`)

    def to_dict(self) -> dict:
        return asdict(self)


def _model(name, known: Mapping[str, object] | None = None):
    """The model ``name``; with ``known``, those of its parameters that it has are held at their values
    (:class:`materials.KnownParams`) — names it lacks are ignored here (``reconstruct`` checks that each
    known name belongs to some candidate)."""
    from capture.dataset import model_from_spec

    try:
        m = model_from_spec(name)
        mine = {k: v for k, v in (known or {}).items() if k in m.param_names}
        return KnownParams(m, mine) if mine else m
    except (ValueError, KeyError) as exc:
        raise ReconstructionError(f"model {name!r}: {exc}") from None


#: Tile size of the pooled material proposals that :func:`reconstruct` uses when the lights stay fixed relative to
#: the object (:func:`static_lights`). Measured on the default scene (256², 16 views) under five static rigs —
#: all-texel roughness 0.108–0.131 → 0.042–0.061 — and on two flash rigs, where they cost f0 (0.013 → 0.029 with
#: the lights 20° off the camera, 0.011 → 0.032 at 45°): docs/log.md, "pooled proposals under static lights".
POOLED_STATIC = 4


def static_lights(views) -> tuple[bool, int, int]:
    """Whether the photos' lights stay put relative to the object: ``(static, distinct lights, view-light pairs)``.

    Lamps fixed in the studio (a fixed rig, a dome) light every view from the same few positions; a flash or a
    turntable moves them with the camera in the object's frame. Static means only point and directional lights,
    at least two views, and each distinct one (position / direction rounded to 1e-4) lighting at least half of the
    views on average (a turntable whose lamps sit 180° apart shares each position between two views only).
    Under static lights a surface point sees the same few light directions in every view, so a rough material may
    show no highlight peak anywhere and give the reflectance sharing no texel to start from; :func:`reconstruct`
    then turns on pooled proposals (:data:`POOLED_STATIC`).

    Args:
        views: the dataset's views (each with a ``lights`` list of :mod:`renderer.lights` objects).
    """
    from renderer.lights import DirectionalLight, PointLight

    keys, pairs = set(), 0
    for v in views:
        for light in v.lights:
            if isinstance(light, PointLight):
                keys.add(("p", *torch.round(light.position.double() * 1e4).long().tolist()))
            elif isinstance(light, DirectionalLight):
                keys.add(("d", *torch.round(light.direction.double() * 1e4).long().tolist()))
            else:
                return False, len(keys), pairs
            pairs += 1
    return len(views) >= 2 and bool(keys) and 2 * pairs >= len(views) * len(keys), len(keys), pairs


#: The fast solver's options (every field of FitOptions but the loss, which reconstruct takes itself) and the pixel
#: footprints it fits (an input, not an option).
_FAST_KEYS = tuple(n for n in FitOptions.names() if n != "loss") + ("footprints", "refine_from", "refine_steps")
_ADAM_KEYS = ("iterations", "lr", "delta", "observable_std", "noise", "sampling", "time_budget_s")


def _check_option_names(options: Mapping[str, object]) -> None:
    unknown = sorted(set(options) - set(_FAST_KEYS) - set(_ADAM_KEYS))
    if unknown:
        raise ReconstructionError(f"unknown solver option(s) {unknown}; the fast solver takes {list(_FAST_KEYS)}, "
                                  f"adam takes {list(_ADAM_KEYS)}")


def _solve(model, obs: Observations, solver: str, loss: str, options: dict, progress) -> FitResult:
    keys = _FAST_KEYS if solver == "fast" else _ADAM_KEYS
    _check_option_names(options)
    fn = solve_fast if solver == "fast" else solve_adam
    return fn(model, obs, loss=loss, progress=progress, **{k: v for k, v in options.items() if k in keys})


#: Parameters fitted as one value for the whole object by default (the issue's "coat η and roughness as
#: known or fitted scalars": one coat over a whole object).
SCALARS = tuple(p.name for p in CANONICAL.values() if p.shared)


def _fit_scalars(model, fit: FitResult, names) -> tuple[dict[str, list[float]], dict]:
    """One value per parameter in ``names`` from a per-texel fit: the channel-wise median over the texels
    where the parameter is observable (over all observed texels, flagged ``measured: False``, when it is
    observable nowhere). Returns (values, notes for the report)."""
    values, notes = {}, {}
    for n in names:
        C = model.spec(n).channels
        ok = (fit.observed & ~fit.unobservable[n]).reshape(-1)
        src = ok if bool(ok.any()) else fit.observed.reshape(-1)
        v = fit.raw[n].reshape(-1, C)[src].double().median(0).values
        values[n] = v.tolist()
        notes[n] = {"value": v.tolist(), "from_texels": int(src.sum()), "measured": bool(ok.any())}
    return values, notes


#: ``model="auto"`` fits its candidates on maps of at most this many texels a side (:func:`_trial_observations`)...
AUTO_TRIAL_TEXTURE = 128
#: ... when that coarser copy keeps at least this many samples.
AUTO_TRIAL_MIN_SAMPLES = 10_000


def _trial_observations(observe, obs: Observations, texture_size: int, fit_views: list[int]) -> Observations:
    """The observations ``model="auto"`` judges its candidates on: the fitted views, re-observed on maps of
    :data:`AUTO_TRIAL_TEXTURE`² texels when the maps are larger, with the samples thinned by the same area ratio
    (a fixed-seed draw) so a texel keeps as many samples as at full size. The question a trial answers — which
    reflectance model explains the photos — does not need the full resolution, and a trial's cost grows with the
    samples and texels (default scene, 256² maps: the three trial fits 44 s → 16 s, same choice; docs/log.md,
    "auto's trials as the final fit"). Otherwise — maps of at most that size (on a 64² layered scene halving them
    made ggx-lambert gain < 5 % over lambert, and auto stopped before the layered model), or a copy with fewer than
    :data:`AUTO_TRIAL_MIN_SAMPLES` samples (small photos of large maps) — the full observations ``obs`` (of the
    fitted views)."""
    size = min(texture_size, AUTO_TRIAL_TEXTURE)
    if size == texture_size:
        return obs
    trial = observe(size)
    gen = torch.Generator().manual_seed(0)
    keep = torch.rand(trial.n_samples, generator=gen) < (size / texture_size) ** 2
    trial = trial.select(keep.to(trial.device)).select_views(fit_views)
    return trial if trial.n_samples >= AUTO_TRIAL_MIN_SAMPLES else obs


#: The coat scalars' first fit keeps the observed texels that came closest to a mirror configuration — the
#: largest n·h over their own (sample, light) pairs — in this top fraction of the observed texels ...
SCALAR_TEXEL_FRACTION = 0.05
#: ... but at least this many texels (maps with fewer observed texels keep them all).
SCALAR_MIN_TEXELS = 4096


def _highlight_observations(obs: Observations) -> Observations:
    """The samples of the texels that saw a highlight best, for the coat scalars' first fit (:func:`_fit`).

    The coat's η and roughness are measured where its specular lobe was seen — near the mirror configuration
    (n·h → 1); elsewhere the coat is a faint Fresnel term that trades against the base's lobe and absorption.
    So the per-texel fit whose only product is their median over the texels that determine them needs only the
    :data:`SCALAR_TEXEL_FRACTION` (at least :data:`SCALAR_MIN_TEXELS`) of the observed texels with the largest
    n·h. Measured on the default-size layered scene (256² maps, 51 870 observed texels, 4 096 kept;
    docs/log.md, "the layered fit 58 → 42 s"): first fit 20.7 → 6.1 s on 24 360 of its 204 000 samples, coat η
    1.49991 from 22 texels instead of 29 and roughness 0.10000 from 79 instead of 86, the same to 5 digits; with
    3 000 e⁻ shot noise η / roughness 1.49990 / 0.09998 from 11 / 43 texels (1.49988 / 0.09998 from 13 / 48 with
    all). Samples lit by environment lights only have no n·h and are left out; without any (sample, light) pair
    the observations are kept whole.
    """
    H, W = obs.map_size
    if obs.n_pairs == 0:
        return obs
    nh = obs.angles.nh.reshape(-1).to(torch.float64)
    best = torch.full((H * W,), -2.0, dtype=torch.float64, device=obs.device)
    best = best.scatter_reduce(0, obs.texel[obs.pair_sample], nh, reduce="amax")
    seen = best > -2.0
    n_seen = int(seen.sum())
    keep = max(math.ceil(SCALAR_TEXEL_FRACTION * n_seen), SCALAR_MIN_TEXELS)
    if keep >= n_seen:
        return obs
    threshold = best[seen].topk(keep).values[-1]
    return obs.select(best[obs.texel] >= threshold)


def _fit(model, obs: Observations, solver: str, loss: str, options: dict, progress,
         scalars) -> tuple[FitResult, object, dict]:
    """Fit ``model`` as :func:`reconstruct` fits it — the final fit and ``auto``'s trial fits alike. With parameters
    of ``scalars`` to fit (the coat's η and roughness), a per-texel fit first, on the samples of the texels that saw
    a highlight best (:func:`_highlight_observations`) — the fast solver's without the
    reflectance sharing, which would replace a texel's own coat by a few materials' (bilinear layered scene: coat η
    1.645 against 1.5006 from the 3 texels that determine it) — then each scalar's median where it is observable
    (:func:`_fit_scalars`), held fixed in a second fit of the rest. Returns (fit, the model fitted — with the
    scalars as known values —, notes on the scalars for the report)."""
    to_fit = [n for n in scalars if n in model.param_names]
    first, first_obs = options, (_highlight_observations(obs) if to_fit else obs)
    if to_fit and solver == "fast":
        # only the scalars are kept from it, taken where they are observable: 16 roughness values do
        # (bilinear 256² layered scene: 24.9 → 18.6 s, coat η and roughness unchanged to 5 digits)
        first = dict(options, joint_iterations=0, share=False, footprints=None,
                     grid=16 if options.get("grid") is None else options["grid"])
    fit = _solve(model, first_obs, solver, loss, first, progress)
    if not to_fit:
        return fit, model, {}
    values, notes = _fit_scalars(model, fit, to_fit)
    for n in notes:
        notes[n]["first_fit_samples"] = first_obs.n_samples
    model = KnownParams(getattr(model, "base", model), {**getattr(model, "known", {}), **values})
    return _solve(model, obs, solver, loss, options, progress), model, notes


def _render(model, maps: Mapping[str, Tensor], obs: Observations, sampling: str) -> Tensor:
    """The radiance ``[S, 3]`` that ``maps`` (name → ``[H, W, C]``) predict for every sample of ``obs``, no gradient."""
    with torch.no_grad():
        return obs.predict(model, obs.per_sample({k: v.to(obs.dtype) for k, v in maps.items()}, sampling))


def _heldout_error(model, fit: FitResult, obs: Observations, sampling: str = "nearest") -> float:
    """Mean absolute error of the held-out views re-rendered with the fit's *filled* maps — the maps a user
    gets: where the training views left a parameter unobservable the raw per-texel value is arbitrary, and
    judging a model by it penalised exactly the models with more (hence more often unobservable) parameters.

    Mean absolute, not RMSE: held-out squared errors are dominated by the few highlight pixels
    no model predicts from other views — on the measured-material scene 1 % of the pixels held 91 % of the
    squared error, so the RMSE moved by 2 % between models whose held-out PSNR on the benchmark's own views
    differs by 11 dB (docs/reconstruction.md, "Model selection")."""
    return float((_render(model, fit.maps, obs, sampling) - obs.radiance).abs().mean())


def _auto_verdict(tried: list[dict], params, err: float, chi2: float, best_err: float, auto_gain: float,
                  auto_chi2: float) -> tuple[str, str]:
    """``model="auto"``'s judgement of a candidate after the ones ``tried`` (report rows with ``params``,
    ``train_chi2``, ``model`` and, for failed ones, ``failed_fit``): ``("failed" | "better" | "stop", why)``.

    * failed — it contains the last candidate that did not fail (its parameters are a superset) yet fits its
      training photos clearly worse (χ² above 1.1 × that one's + 1: 10 % and more than the noise): a failed fit, not
      evidence against the richer model; it decides nothing and the search goes on;
    * better — its held-out error dropped by more than ``auto_gain``, or its training χ² is at least
      :data:`AUTO_CHI2_GAIN` × below that of a previous candidate that does not explain its photos (χ² above
      ``auto_chi2``) — then ``why`` says so;
    * stop — neither: richer models are not tried.
    """
    prev = next((x for x in reversed(tried) if not x.get("failed_fit")), None)
    if prev is not None and set(prev["params"]) <= set(params) and chi2 > 1.1 * prev["train_chi2"] + 1.0:
        return "failed", (f"fits its training photos worse (χ² {chi2:.3g}) than {prev['model']} "
                          f"({prev['train_chi2']:.3g}), which it contains")
    dropped = err < best_err * (1 - auto_gain)
    much_better = prev is not None and prev["train_chi2"] > auto_chi2 and chi2 * AUTO_CHI2_GAIN <= prev["train_chi2"]
    if much_better and not dropped:
        return "better", (f"training χ² {chi2:.3g} ≥ {AUTO_CHI2_GAIN:g}× below {prev['model']}'s "
                          f"{prev['train_chi2']:.3g}, which does not explain its photos (held-out error alone would "
                          f"have stopped)")
    return ("better" if dropped else "stop"), ""


def _footprint_misfit(model, fit: FitResult, fp, obs: Observations, noise=NOISE, pred: Tensor | None = None) -> float:
    """:func:`_misfit` of the photos' pixels as the footprint operator predicts them (:mod:`capture.footprint`;
    :func:`_pixel_chi2`). ``pred``: that prediction when it is already made (:func:`_fitted_prediction`)."""
    if pred is None:
        pred = _fitted_prediction(model, fit, obs, fp, "bilinear")
    return _pixel_chi2(pred, fp, obs, noise)


def _pixel_chi2(pred: Tensor, fp, obs: Observations, noise=NOISE) -> float:
    """χ² per residual of the pixels of ``fp`` predicted as ``pred [R, 3]``: σ from the noise model at each pixel's
    value, scaled by the noise measured in image space (``obs``)."""
    y = fp.radiance.to(torch.float64)
    sigma = scaled_sigma(y, noise, photo_noise_ratio(obs, noise))
    return float((((pred.to(torch.float64) - y) / sigma) ** 2).mean())


def _fitted_prediction(model, fit: FitResult, obs: Observations, fp, sampling: str) -> Tensor:
    """The fitted views' values as the fit models them, from the fit's own (raw) maps: pixels (area averages over
    their footprints, ``[R, 3]``) when ``fp`` is given, else the samples ``[S, 3]`` of ``obs``. Made once and shared
    by the χ² check and the views' re-renders (on 32 × 512² photos each made its own: 2 s apiece on 16 cores)."""
    if fp is None:
        return _render(model, fit.raw, obs, sampling)
    with torch.no_grad():
        return fp.render(model, {k: v.to(fp.radiance.dtype) for k, v in fit.raw.items()})


def _misfit(model, fit: FitResult, obs: Observations, sampling: str, noise=NOISE, pred: Tensor | None = None) -> float:
    """How well a fit explains the photos it was fitted to: the weighted mean over samples and channels of
    ``(r / σ)²``, ``r`` the residual of the fit's own (raw) maps and σ the photos' noise
    (:func:`capture.fit.noise.photo_sigma`: the 1 % noise model, scaled to the noise measured in image space where the
    photos are noisier) — a χ² per residual, about 1 or less when the model explains the photos as well as their
    noise allows."""
    if pred is None:
        pred = _fitted_prediction(model, fit, obs, None, sampling)
    return _sample_chi2(pred, obs, noise)


def _sample_chi2(pred: Tensor, obs: Observations, noise=NOISE) -> float:
    """The weighted χ² per residual of the samples of ``obs`` predicted as ``pred [S, 3]`` (:func:`_misfit`)."""
    sigma = photo_sigma(obs, noise, photo_noise_ratio(obs, noise))
    w = obs.weight.to(sigma.dtype)
    chi2 = (((pred - obs.radiance) / sigma) ** 2).sum(-1)
    return float((chi2 * w).sum() / (3 * w.sum()))


#: Fraction of the roughness-observable texels with an unresolved highlight peak above which the report warns.
UNRESOLVED_WARN = 0.5


def unresolved_roughness(obs: Observations, roughness: Tensor, mask: Tensor, neighbourhood: int = 5,
                         far: float = 3.0) -> tuple[float, float]:
    """How often the fitted highlight is narrower than the direction sampling could resolve.

    Per texel, θ_min = the smallest angle between the normal and a half vector of the (sample, light)
    pairs of the texels in its ``neighbourhood``² block; the fitted lobe is *unresolved* when even
    ``far`` times its half-maximum angle (:func:`materials.roughness.half_max_angle`) is below θ_min —
    every sample near it saw only the far tail (beyond 3 θ½ a GGX lobe is below 5 % of its peak,
    where it falls like α²/θ⁴ and trades roughness against f0), so a narrower lobe with a brighter
    peak would explain the photos as well: a near-mirror surface. Flash rigs see most texels on the
    flank of their highlight, which does determine the roughness of a wider lobe; hence the block
    and the factor. Measured, fraction of the roughness-observable texels called unresolved with
    (block, far) = (5, 1) / (5, 2) / (5, 3): small stress sphere (96 px, 6 views, 32² maps), normal
    maps 19 / 11 / 7 %; default scene 62 / 23 / 7 %; true roughness 0.02 or 0.05 everywhere
    100 / 92 / 80 %, 0.1: 100 / 98 / 91 %; fully rough 2 / 0 / 0 %.

    Args:
        roughness: ``[H, W, 1]`` fitted roughness; mask: ``[H, W]`` bool, the texels to judge (those
            without a sample of their own — read through a bilinear footprint — are skipped).
    Returns:
        ``(fraction of ``mask`` texels unresolved, median fitted roughness over ``mask``)``; (0, nan)
        for an empty mask.
    """
    H, W = obs.map_size
    tex = obs.texel[obs.pair_sample]
    best = torch.full((H * W,), -2.0, dtype=torch.float64, device=obs.device)
    best = best.scatter_reduce(0, tex, obs.angles.nh.reshape(-1).double(), reduce="amax")
    m = mask.reshape(-1) & (best > -2.0)              # only texels with pairs of their own can be judged
    if not bool(m.any()):
        return 0.0, float("nan")
    if neighbourhood > 1:
        best = F.max_pool2d(best.reshape(1, 1, H, W), neighbourhood, 1, neighbourhood // 2).reshape(-1)
    theta_min = torch.arccos(best.clamp(-1.0, 1.0))
    r = roughness.reshape(-1).double()
    unresolved = far * half_max_angle(r) < theta_min
    return float(unresolved[m].float().mean()), float(r[m].median())


def _stages(model: str, solver: str, footprint: bool, sampling: str | None) -> dict[str, float]:
    """The progress bar's stages of a run (:data:`capture.progress.RECONSTRUCT_STAGES`, weighted by their expected
    cost), less those it skips: auto's trial fits for a named model, footprints, sharing and the joint refinement
    where the solver does not run them."""
    import materials

    from .progress import RECONSTRUCT_STAGES

    auto = model == "auto" and sum(m in materials.available() for m in AUTO_CANDIDATES) > 1
    fits_footprints = footprint and solver == "fast" and sampling in (None, "bilinear")
    return {k: w for k, w in RECONSTRUCT_STAGES.items()
            if (k != "select" or auto) and (k not in ("footprints", "footprint solve") or fits_footprints)
            and (k not in ("sharing", "joint") or solver == "fast")}


def reconstruct(dataset_path, model: str = "auto", out_dir=None, *, force: bool = False, solver: str = "fast",
                loss: str = "l2", texture_size: int | None = None, dtype: torch.dtype = torch.float32,
                progress: bool = True, auto_gain: float = 0.05, auto_chi2: float = AUTO_EXPLAINED_CHI2,
                max_grid_views: int = 8, sampling: str | None = None,
                threads: int | None = None, known: Mapping[str, object] | None = None,
                scalars: tuple[str, ...] | list[str] = SCALARS, holdout: Sequence[int] | None = None,
                footprint: bool = True, psf_sigma: float | None = None, device: str = "auto", photo_bin: int = 1,
                **options) -> Report:
    """Recover the material maps of a dataset and write them to ``out_dir`` (see module docstring).

    Args:
        dataset_path: dataset folder (docs/dataset-format.md).
        model: a registered model name, ``"a+b"``, or ``"auto"``.
        out_dir: output folder; must not exist unless ``force`` (then it is replaced at the end).
        solver: "fast" (per-texel LM) or "adam".
        loss: "l2", "huber" or "l1".
        texture_size: size T of the recovered T×T maps (default: the ground truth's, else 256).
        dtype: dtype of the model evaluations (float32 default; float64 for precision studies).
        progress: show one bar over the whole job with its stage, the live loss and an ETA
            (:mod:`capture.progress`; a :class:`capture.progress.Progress` is used as given); False shows nothing.
        auto_gain: ``model="auto"`` stops when the held-out mean absolute error drops by less than this
            fraction.
        auto_chi2: ``model="auto"`` also stops once a candidate explains its training photos within their noise: its
            fit's χ² per residual (:func:`_misfit`) at most this (default :data:`AUTO_EXPLAINED_CHI2`); 0 turns
            that off. A model that leaves nothing but noise leaves a richer one nothing to explain.
        max_grid_views: views per page of the labelled views figure (``views.png``, ``views-2.png``, …; every
            view is shown, the held-out ones first).
        sampling: how a sample reads the maps: "nearest" or "bilinear"; None = "bilinear" (a texture-mapped
            surface; the ground truth, when a dataset has one, is never read to decide how to fit). Bilinear runs
            the per-texel solve and then the joint refinement (:func:`capture.fit.joint.refine_joint`).
        footprint: fit the photos' pixels as area averages over their footprints (:mod:`capture.footprint`,
            the fast solver's final joint solve, default) — how every camera and every renderer forms a pixel.
            False fits one ray per pixel centre only: exact only for photos rendered that way.
        psf_sigma: σ (pixels of the photos as stored, before ``photo_bin``) of a Gaussian blur (lens, demosaicing) in
            the photos' pixel filter, convolved with the box; None = the dataset's ``psf_sigma`` (0 when scene.json
            has none).
        device: where the fits run: "cpu", "cuda" (or "cuda:N") or "auto" (CUDA when torch sees a GPU, the default);
            the ray casting, observations and metrics stay on the CPU (:mod:`renderer.device`).
        photo_bin: fit the photos binned ``k × k`` (:meth:`capture.dataset.Dataset.binned`: each block's mean, a pixel
            ``k`` times larger, which the footprint fit models exactly): about ``k²`` fewer pixels, so ``k²`` less
            memory and time in every stage that scales with them, for photos finer than the maps hold. 1 (default):
            the photos as they are. Every output (views, re-renders, PSNR) is then at the binned size.
        threads: torch intra-op threads for this call (restored after); None = leave as is. On a
            machine where another process holds a core, 1 thread is much faster than 2 (measured
            ~70× on small index_add ops: OpenMP threads wait for the busy core).
        known: parameter name → value (a number, or one per channel, canonical units) held fixed
            instead of fitted — e.g. ``{"coat_ior": 1.5, "coat_roughness": 0.1}``, the coat of a
            layered material measured once for the whole object (the issue's "coat η and roughness
            as known scalars"). Each name must belong to the model (with ``"auto"``: to some
            candidate; candidates without it fit as usual). Known maps are written as constant maps
            and listed in the report (``skipped.parameters_per_object``, with the fitted scalars), not
            allocated per texel.
        scalars: parameters fitted as *one* value for the whole object rather than per texel (default
            :data:`SCALARS`: the coat's η and roughness; names the model lacks are ignored): a per-texel
            fit (fast solver: without the sharing and the joint refinement, which replace a texel's own values by
            a material's), then each one's median over the texels where it is observable (``fit.scalars`` in the
            report, with a warning where it is observable nowhere), held fixed in a second fit of the
            rest. Known values take precedence. ``()`` = everything per texel. ``model="auto"``'s trial fits
            fit them the same way (fitted with a coat per texel, the layered trial lost even on layered scenes).
        holdout: view indices kept out of the fit and used only to validate it: each is re-rendered with the
            recovered (filled) maps — what a user gets — and compared with its photo (PSNR / SSIM in
            ``report.views``, flagged ``heldout``, and the summary). The only check of the maps on real photos,
            which have no ground truth. None = every view is fitted. ``model="auto"`` splits the fitted views
            only.
        **options: passed to the solver (iterations, grid, schedule, smoothness, delta, lr, ...). The fast
            solver's ``pooled`` (pooled material proposals, :func:`capture.fit.fast.solve_fast`) defaults to
            :data:`POOLED_STATIC` when :func:`static_lights` says the lights stay fixed relative to the object
            and to 0 (off) otherwise; pass ``pooled=0`` or a tile size to decide yourself (``report.fit["pooled"]``
            says what was used and why).

    Returns:
        :class:`Report` (also ``report.json`` in ``out_dir``).

    Raises:
        DatasetError: the dataset does not validate. ReconstructionError: unknown model (lists the
        names), output folder exists, bad solver/loss, no valid observation.
    """
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ReconstructionError(f"threads must be a positive integer or None, got {threads!r}")
        old = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            # every argument passed on as given (one call, so a new parameter cannot be dropped here)
            args = {k: v for k, v in locals().items() if k in _RECONSTRUCT_ARGS}
            return reconstruct(**{**args, "threads": None}, **options)
        finally:
            torch.set_num_threads(old)
    from .progress import Progress

    if progress is True:
        # one bar over the whole job, removed however the job ends (an error's message then stands alone)
        with Progress(_stages(model, solver, footprint, sampling)) as bar:
            args = {k: v for k, v in locals().items() if k in _RECONSTRUCT_ARGS}
            return reconstruct(**{**args, "progress": bar}, **options)
    times: dict[str, float] = {}
    with _timed(times, "load"):
        inputs = _check_inputs(dataset_path, model, out_dir, force, solver, loss, auto_chi2, known, scalars, options,
                               device)
        prog = progress if isinstance(progress, Progress) else Progress(_stages(model, solver, footprint, sampling),
                                                                        enabled=False)
        data = _load(dataset_path, holdout, photo_bin, prog)
    with _timed(times, "gbuffer"):
        views = _PreparedViews(_gbuffers(data.ds, prog))
    with _timed(times, "observe"):
        seen = _observe(data, views, solver, sampling, texture_size, footprint, psf_sigma, dtype, options, prog,
                        _model(inputs.candidates[0], inputs.known) if len(inputs.candidates) == 1 else None)
    del views
    report = Report(model="", solver=solver, out_dir=str(inputs.out_dir), device=str(inputs.device))
    _report_samples(report, data, seen, footprint, solver)
    if seen.fp_all is not None and seen.fp_all is not seen.fp:
        # with held-out views the fitted and held-out footprints are copies: the whole set was only counted
        seen = replace(seen, fp_all=None)
    fitter = _Fitter(solver, loss, seen.options, inputs.scalars, _solver_progress(prog), inputs.device)

    ready = None                        # auto's full-size fit of the model it chose, when it made one
    with _timed(times, "select"):
        if len(inputs.candidates) > 1:
            model, ready = _select_model(inputs.candidates, inputs.known, data.fit_views, seen, fitter, auto_gain,
                                         auto_chi2, prog, report)
    mdl = _model(model, inputs.known)
    report.model, report.model_spec = model, _model_spec(model)
    with _timed(times, "solve"):
        fitted = _final_fit(mdl, seen, fitter, data.fit_views, prog, report, ready)
    pred = _fitted_prediction(fitted.model, fitted.fit, seen.obs, seen.fp, seen.sampling)
    chi2 = _check_misfit(report, fitted, seen, pred)
    known_maps = _known_maps(fitted.model, seen.obs.map_size)
    spt, vpt = seen.obs.samples_per_texel(), seen.obs.views_per_texel()
    _report_coverage(report, fitted.fit, seen, spt)
    _report_fit(report, fitted, chi2, seen, solver)
    _report_skipped(report, fitted.model, data.ds, seen, times["solve"])

    with _timed(times, "metrics"):
        prog.start("metrics")
        _report_errors(report, data.ds, fitted, seen, known_maps)
        renders = _rerender_views(report, data, fitted, seen, pred)

    report.memory = _peak_memory()
    _report_budget(report, seen.options.get("memory_budget"))
    _write_outputs(inputs.out_dir, data.ds, fitted.fit, seen.obs, renders, seen.photos, report, times, force,
                   max_grid_views, spt, vpt, known_maps, prog)
    return report


#: reconstruct's own parameters, passed on unchanged when it re-enters itself with a thread count set
_RECONSTRUCT_ARGS = tuple(p for p in inspect.signature(reconstruct).parameters if p != "options")


@contextmanager
def _timed(times: dict[str, float], stage: str) -> Iterator[None]:
    """Record the seconds the ``with`` block takes as ``times[stage]`` (the report's ``times``; nothing when it
    raises)."""
    t = time.perf_counter()
    yield
    times[stage] = time.perf_counter() - t


# -- validate ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Inputs:
    """:func:`reconstruct`'s arguments once checked."""

    out_dir: Path                   #: the checked output folder (written at the end, atomically)
    candidates: list[str]           #: the models to fit: ``[model]``, or auto's registered candidates
    known: dict[str, object]        #: parameters held at given values
    scalars: tuple[str, ...]        #: parameters fitted as one value per object, less the known ones
    device: torch.device            #: where the fits run


def _check_inputs(dataset_path, model: str, out_dir, force: bool, solver: str, loss: str, auto_chi2,
                  known: Mapping[str, object] | None, scalars, options: Mapping[str, object], device) -> _Inputs:
    """Check :func:`reconstruct`'s arguments before any work (the dataset is not read yet): a ReconstructionError
    naming the fix for a missing or unusable output folder, a loaded dataset instead of its folder, an unknown
    solver, solver option, loss or model, a bad ``auto_chi2``, ``scalars`` or known value."""
    if out_dir is None:
        raise ReconstructionError("out_dir is required: the folder to write the maps and report into")
    from capture.dataset import dataset_root
    from capture.outputs import check_output

    if not isinstance(dataset_path, (str, os.PathLike)):
        raise ReconstructionError(f"dataset_path must be the dataset's folder (a str or a path), got "
                                  f"{type(dataset_path).__name__}: pass the folder load_dataset() was given")

    # before any work: never the dataset or inside it, an existing folder only with force, a folder we can write in
    out_dir = check_output(out_dir, {dataset_root(dataset_path): "the dataset folder"}, force=force,
                           error=ReconstructionError, force_flag="force=True (--force)")
    if solver not in ("fast", "adam"):
        raise ReconstructionError(f"solver must be 'fast' or 'adam', got {solver!r}")
    _check_option_names(options)  # before any work: a misspelt option fails now, not after the observations
    if loss not in LOSSES:
        raise ReconstructionError(f"loss must be one of {LOSSES}, got {loss!r}")
    if isinstance(auto_chi2, bool) or not isinstance(auto_chi2, (int, float)) or not auto_chi2 >= 0:
        raise ReconstructionError(f"auto_chi2 must be a number ≥ 0 (0 turns the rule off), got {auto_chi2!r}")
    import materials

    if model == "auto":
        candidates = [m for m in AUTO_CANDIDATES if m in materials.available()]
    else:
        candidates = [model]
    known = dict(known or {})
    if isinstance(scalars, str) or not all(isinstance(n, str) for n in scalars):
        raise ReconstructionError(f"scalars must be a tuple of parameter names, got {scalars!r}")
    scalars = tuple(n for n in scalars if n not in known)
    if known:
        params = set().union(*(_model(c).param_names for c in candidates))
        stray = sorted(set(known) - params)
        if stray:
            raise ReconstructionError(f"known parameter(s) {stray} belong to no model tried ({candidates}); "
                                      f"their parameters are {sorted(params)}")
    for c in candidates:
        _model(c, known)  # unknown names and bad known values fail before any work
    from renderer.device import DeviceError, resolve_device

    try:
        dev = resolve_device(device)
    except DeviceError as e:
        raise ReconstructionError(str(e)) from None
    return _Inputs(out_dir, candidates, known, scalars, dev)


# -- load dataset and G-buffers ---------------------------------------------------------------------


@dataclass(frozen=True)
class _Loaded:
    """The dataset and how its views divide between the fit and the validation (``holdout``)."""

    ds: Dataset
    fit_views: list[int]            #: view indices fitted, ascending
    held_views: list[int]           #: view indices held out, ascending (may be empty)


def _load(dataset_path, holdout, photo_bin: int, prog: Progress) -> _Loaded:
    """Load (and validate) the dataset, binned ``photo_bin × photo_bin``, and check ``holdout`` against its views."""
    from capture.dataset import DatasetError, load_dataset

    if isinstance(photo_bin, bool) or not isinstance(photo_bin, int) or photo_bin < 1:
        raise ReconstructionError(f"photo_bin must be a positive integer (1: the photos as they are), got "
                                  f"{photo_bin!r}")
    prog.start("load")
    ds = load_dataset(dataset_path)
    try:
        ds = ds.binned(photo_bin)
    except DatasetError as exc:
        raise ReconstructionError(f"photo_bin: {exc}") from None
    held_views = _check_holdout(holdout, len(ds.views))
    return _Loaded(ds, [i for i in range(len(ds.views)) if i not in held_views], held_views)


class _PreparedViews:
    """The views' pixel-centre G-buffers with their shading prepared (:func:`_gbuffers`), which the observations are
    made of, until :meth:`release`: the final fit reads only the observations, so its stage frees them (0.36 GiB on
    32 × 512² photos)."""

    def __init__(self, preps: list):
        self._preps = preps

    def get(self) -> list:
        if self._preps is None:
            raise ReconstructionError("internal: the views' G-buffers were released before a stage that needs them")
        return self._preps

    def release(self) -> None:
        self._preps = None


def _gbuffers(ds: Dataset, prog: Progress) -> list:
    """One G-buffer per view with its shading prepared (shadow rays): geometry is known, so this happens once
    whatever the model and solver."""
    from renderer.device import per_view
    from renderer.gbuffer import render_gbuffer
    from renderer.shading import prepare

    prog.start("gbuffer", f"{len(ds.views)} views")
    views = ds.views
    return per_view(lambda i: prepare(render_gbuffer(ds.mesh, views[i].camera, 1), ds.mesh, views[i].lights,
                                      shadows=True), len(views), prog.tick)


# -- observations -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Observed:
    """The photos as the fits see them: samples (and pixel footprints), all views and split by ``holdout``, with the
    settings every fit of the run shares."""

    photos: list                    #: the dataset's photos (:class:`capture.dataset.Photo`)
    lights: list                    #: the distinct lights of all views
    texture_size: int               #: T of the fitted T×T maps
    sampling: str                   #: "nearest" or "bilinear"
    dtype: torch.dtype              #: dtype of the model evaluations
    options: dict                   #: the solver's options, with ``sampling`` and (fast solver) ``pooled`` decided
    pooled_auto: dict | None        #: why ``pooled`` was chosen, when it was not given (the report's ``fit.pooled``)
    psf: float                      #: σ (pixels) of the photos' Gaussian pixel blur
    views: _PreparedViews           #: what ``observe`` and ``footprints`` make them of, until the final fit
    observe: Callable[[int], Observations]                  #: the observations on maps of a given size
    footprints: Callable[[int], PixelFootprints] | None      #: the same for pixel footprints; None: not fitted
    all_obs: Observations           #: samples of all views
    obs: Observations               #: samples of the fitted views
    held_obs: Observations | None   #: samples of the held-out views
    fp_all: PixelFootprints | None  #: footprints of all views (None once counted, when views are held out)
    fp: PixelFootprints | None      #: the fitted views' footprints
    held_fp: PixelFootprints | None  #: the held-out views' footprints


def _distinct_lights(views) -> list:
    """The lights of all ``views``, each light object once (by identity), in order of appearance."""
    all_lights = []
    for v in views:
        for x in v.lights:
            if all(x is not y for y in all_lights):
                all_lights.append(x)
    return all_lights


def _solver_settings(views, solver: str, sampling: str | None,
                     options: Mapping[str, object]) -> tuple[str, dict, dict | None]:
    """``(sampling, solver options, pooled_auto)``: the sampling checked (None → "bilinear") and added to the
    options, and the fast solver's ``pooled`` decided from the lights when not given (:func:`static_lights`;
    ``pooled_auto`` says why, None when it was given or the solver is adam)."""
    if sampling is None:
        sampling = "bilinear"
    if sampling not in ("nearest", "bilinear"):
        raise ReconstructionError(f"sampling must be 'nearest' or 'bilinear', got {sampling!r}")
    options = {**options, "sampling": sampling}
    pooled_auto = None
    if solver == "fast" and options.get("pooled") is None:
        static, n_lights, n_pairs = static_lights(views)
        options["pooled"] = POOLED_STATIC if static else 0
        pooled_auto = {"block": options["pooled"], "auto": True, "static_lights": static, "distinct_lights": n_lights,
                       "view_light_pairs": n_pairs}
    return sampling, options, pooled_auto


def _footprint_observer(ds: Dataset, views: _PreparedViews, photos: list, lights: list, dtype: torch.dtype,
                        psf: float, model: Model | None) -> Callable[[int], PixelFootprints]:
    """The photos' pixel footprints (:func:`capture.footprint.observe_footprints`) on maps of a given size; their
    ray counts from ``model``'s shading when it is the one model to fit and affine in its parameters
    (:func:`capture.footprint.shading_bases`), else from the photos."""
    from .footprint import observe_footprints, shading_bases

    bases: list = []

    def footprints(size: int) -> PixelFootprints:
        if model is not None and not bases:
            bases.append([shading_bases(model, p) for p in views.get()])
        shading = bases[0] if bases and all(b is not None for b in bases[0]) else None
        return observe_footprints(ds.mesh, [v.camera for v in ds.views], [v.lights for v in ds.views],
                                  [p.gbuffer for p in views.get()], [p.radiance for p in photos], (size, size),
                                  lights=lights, clipped=[p.unusable for p in photos], dtype=dtype,
                                  psf_sigma=psf, shading=shading)

    return footprints


def _observe(data: _Loaded, views: _PreparedViews, solver: str, sampling: str | None, texture_size: int | None,
             footprint: bool, psf_sigma: float | None, dtype: torch.dtype, options: Mapping[str, object],
             prog: Progress, model: Model | None = None) -> _Observed:
    """The valid samples of every view (:func:`capture.observations.observe_views`) and, for the fast solver's
    bilinear fit, the photos' pixel footprints (their ray counts from ``model``'s shading where
    :func:`_footprint_observer` can); both split into fitted and held-out views."""
    ds = data.ds
    prog.start("observe")
    photos = ds.load_images(dtype=dtype)
    if texture_size is None:
        texture_size = int(next(iter(ds.gt.maps.values())).shape[0]) if ds.gt is not None else 256
    all_lights = _distinct_lights(ds.views)
    sampling, options, pooled_auto = _solver_settings(ds.views, solver, sampling, options)

    def observe(size: int) -> Observations:
        return observe_views(views.get(), [p.radiance for p in photos], (size, size), exposure=1.0,
                             clipped=[p.unusable for p in photos], lights=all_lights, dtype=dtype,
                             bilinear=sampling == "bilinear")

    all_obs = observe(texture_size)
    fp_all = fp = held_fp = footprints = None
    try:
        # a σ given here is in the photos' own pixels, as the dataset's is before binning divides it
        psf = ds.psf_sigma if psf_sigma is None else check_psf_sigma(psf_sigma) / ds.views[0].bin
    except ValueError as exc:
        raise ReconstructionError(f"{exc}; or None for the dataset's") from None
    if footprint and solver == "fast" and sampling == "bilinear":
        footprints = _footprint_observer(ds, views, photos, all_lights, dtype, psf, model)
        prog.start("footprints")
        fp_all = footprints(texture_size)
        fp = fp_all.select_views(data.fit_views) if data.held_views else fp_all
        held_fp = fp_all.select_views(data.held_views) if data.held_views else None
    obs, held_obs = all_obs, None
    if data.held_views:
        obs, held_obs = all_obs.select_views(data.fit_views), all_obs.select_views(data.held_views)
        if obs.n_samples == 0:
            raise ReconstructionError(f"the views left to fit ({data.fit_views}) have no valid sample; hold out "
                                      f"fewer views (holdout={data.held_views})")
    release_memory()                    # (the per-view pieces concatenated above)
    return _Observed(photos, all_lights, texture_size, sampling, dtype, options, pooled_auto, psf, views, observe,
                     footprints, all_obs, obs, held_obs, fp_all, fp, held_fp)


def _n_pixels(ds: Dataset) -> int:
    """The pixels of all the dataset's photos."""
    return sum(v.camera.width * v.camera.height for v in ds.views)


def _report_samples(report: Report, data: _Loaded, seen: _Observed, footprint: bool, solver: str) -> None:
    """The report's ``samples`` and ``drops``, and a warning when the photos' pixel blur goes unmodelled."""
    obs, fp_all, psf = seen.all_obs, seen.fp_all, seen.psf
    report.samples = {"pixels": _n_pixels(data.ds), "valid": obs.n_samples, "pairs": obs.n_pairs,
                      "lights": len(seen.lights), "views": len(data.ds.views), "bin": data.ds.views[0].bin}
    report.drops = dict(obs.drops)
    if psf > 0 and fp_all is None:
        report.warnings.append(f"the photos' pixel filter has a Gaussian blur (psf_sigma {psf:g} px) that only the "
                               f"footprint fit models; this fit ({'pixel centres' if not footprint else solver}) "
                               f"ignores it — use the fast solver with footprints")
    if fp_all is not None:
        from .footprint import saving

        report.samples["footprints"] = {
            "pixels": fp_all.n_pixels, "samples": fp_all.n_samples,
            "samples_per_pixel": dict(zip(*(x.tolist() for x in torch.unique(fp_all.counts, return_counts=True)),
                                          strict=True)),
            "rays_cast": fp_all.cast_rays, "rays_saved_vs_uniform": saving(fp_all),
            "texture_samples": fp_all.texture_samples, "drops": fp_all.drops,
            "psf_sigma": float(psf), "noisy_views": fp_all.noisy_views, "ray_counts": fp_all.ray_counts}
    if data.held_views:
        report.samples.update(heldout_views=data.held_views, heldout_samples=seen.held_obs.n_samples,
                              fitted_samples=seen.obs.n_samples)


# -- fit: model selection and solve -----------------------------------------------------------------


def _solver_progress(prog: Progress) -> Callable[[str, int, float], None]:
    """The solvers' progress callback: each of their steps moves the bar to its stage and shows the loss."""

    def cb(stage, it, cost):
        # the solver's steps: its per-texel LM stages (the schedule's names), "share", "joint", "footprint", "adam"
        if prog.stage != "select":
            prog.start({"share": "sharing", "joint": "joint", "footprint": "footprint solve"}.get(stage, "solve"))
        prog.tick(f"{'' if stage in ('share', 'joint', 'footprint', 'adam') else stage + ' '}loss {cost:.3e}")

    return cb


@dataclass(frozen=True)
class _Fitter:
    """How every fit of a run is made — auto's trial fits and the final fit alike (:func:`_fit`)."""

    solver: str
    loss: str
    options: dict                   #: the solver's options (:attr:`_Observed.options`)
    scalars: tuple[str, ...]        #: parameters fitted as one value per object
    progress: Callable[[str, int, float], None]
    device: torch.device = torch.device("cpu")     #: where the fits run

    def fit(self, model, obs: Observations, footprints: PixelFootprints | None = None,
            refine_from: Mapping[str, Tensor] | None = None,
            refine_steps: int | None = None) -> tuple[FitResult, object, dict]:
        """:func:`_fit` of ``model`` to ``obs`` (and, when given, the pixel ``footprints``; the fast solver's
        ``refine_from`` maps and ``refine_steps``) on :attr:`device`: the observations go there for the fit and the
        result comes back to the CPU."""
        moved = obs.device != self.device
        if moved:
            obs = obs.to(self.device)
            footprints = footprints.to(self.device) if footprints is not None else None
        options = {**self.options, "footprints": footprints} if footprints is not None else self.options
        if refine_from is not None:
            options = {**options, "refine_from": {k: v.to(self.device) for k, v in refine_from.items()}}
            if refine_steps is not None:
                options["refine_steps"] = refine_steps
        fit, model, notes = _fit(model, obs, self.solver, self.loss, options, self.progress, self.scalars)
        return (fit.to("cpu") if moved else fit), model, notes


class _Trial(NamedTuple):
    """What ``model="auto"`` fits its candidates to (``train_*``) and judges them on (``test_*``)."""

    train_obs: Observations
    test_obs: Observations
    train_fp: PixelFootprints | None
    test_fp: PixelFootprints | None


def _trial_problem(seen: _Observed, fit_views: list[int], report: Report) -> _Trial:
    """Auto's trial problem: the fitted views (on a coarser copy for large maps, :func:`_trial_observations`), every
    fourth of them held out when there are at least four; the report's ``samples.auto_trials`` says its size."""
    obs, fp, texture_size = seen.obs, seen.fp, seen.texture_size
    trial = _trial_observations(seen.observe, obs, texture_size, fit_views)
    held = fit_views[3::4] if len(fit_views) >= 4 else []
    train_obs = trial.select_views([i for i in fit_views if i not in held]) if held else trial
    test_obs = trial.select_views(held) if held else trial
    report.samples["auto_trials"] = {"texture_size": int(trial.map_size[0]), "samples": trial.n_samples,
                                     "sample_fraction": trial.n_samples / max(obs.n_samples, 1)}
    train_fp = test_fp = None
    if fp is not None:
        # the trials judge the photos' pixels as the final fit does: footprints on the trial's maps, thinned
        # by the trial's area ratio as its pixel-centre samples are
        size = int(trial.map_size[0])
        tfp = fp if size == texture_size else seen.footprints(size).select_views(fit_views)
        if size != texture_size:
            gen = torch.Generator().manual_seed(0)
            tfp = tfp.select(torch.rand(tfp.n_pixels, generator=gen) < (size / texture_size) ** 2)
        train_fp = tfp.select_views([i for i in fit_views if i not in held]) if held else tfp
        test_fp = tfp.select_views(held) if held else tfp
    return _Trial(train_obs, test_obs, train_fp, test_fp)


def _trial_errors(model, fit: FitResult, trial: _Trial, seen: _Observed) -> tuple[float, float]:
    """``(held-out mean absolute error, training χ² per residual)`` of a trial fit: of the pixels as the footprint
    operator predicts them when the trials fit footprints, else of the samples (:func:`_heldout_error`,
    :func:`_misfit`)."""
    if trial.train_fp is not None:
        with torch.no_grad():
            err = float((trial.test_fp.render(model, {k: v.to(seen.dtype) for k, v in fit.maps.items()})
                         - trial.test_fp.radiance).abs().mean())
        return err, _footprint_misfit(model, fit, trial.train_fp, trial.train_obs)
    return (_heldout_error(model, fit, trial.test_obs, seen.sampling),
            _misfit(model, fit, trial.train_obs, seen.sampling))


def _select_model(candidates: list[str], known: Mapping[str, object], fit_views: list[int], seen: _Observed,
                  fitter: _Fitter, auto_gain: float, auto_chi2: float, prog: Progress,
                  report: Report) -> tuple[str, tuple | None]:
    """``model="auto"``: fit the ``candidates`` cheapest first on the trial problem (:func:`_trial_problem`) and
    return the one chosen (module docstring, step 4) with, when the cheapest was chosen at full size
    (:func:`_explained_at_full_size`), that fit ``(fit, model, scalar notes)`` for :func:`_final_fit` (else None);
    each trial is a row of ``report.selection``, the candidates not tried are ``report.skipped["models_not_tried"]``."""
    prog.start("select", f"{len(candidates)} candidates")
    if seen.texture_size > AUTO_TRIAL_TEXTURE:
        ready = _explained_at_full_size(candidates[0], known, seen, fitter, auto_chi2, report, prog)
        if ready is not None:
            report.skipped["models_not_tried"] = list(candidates[1:])
            return candidates[0], ready
    trial = _trial_problem(seen, fit_views, report)
    best_err, chosen = math.inf, candidates[0]
    for name in candidates:
        fit, m, notes, params, ts = _fit_candidate(name, known, fitter, trial.train_obs, trial.train_fp, "trial", prog)
        err, chi2 = _trial_errors(m, fit, trial, seen)
        report.selection.append({"model": name, "heldout_mae": err, "train_chi2": chi2,
                                 "seconds": time.perf_counter() - ts,
                                 "params": params,
                                 **({"scalars": {k: v["value"] for k, v in notes.items()}} if notes else {})})
        trials = [s for s in report.selection[:-1] if not s.get("full_size")]    # (a full-size χ² is not comparable)
        verdict, why = _auto_verdict(trials, params, err, chi2, best_err, auto_gain, auto_chi2)
        if verdict == "failed":
            report.selection[-1]["failed_fit"] = why
            report.warnings.append(f"auto: the trial fit of {name} failed ({why}); it was not used to choose the "
                                   f"model")
            continue
        if why:
            report.selection[-1]["chosen_by"] = why
        if verdict == "better":
            best_err, chosen = min(err, best_err), name
            if chi2 <= auto_chi2 and name != candidates[-1]:
                report.selection[-1]["stopped"] = f"explains its training photos within their noise (χ² per " \
                                                  f"residual {chi2:.3g} ≤ {auto_chi2:g}); richer models skipped"
                break
        else:
            report.selection[-1]["stopped"] = "held-out error did not drop by more than " \
                                              f"{auto_gain:.0%}; richer models skipped"
            break
    skipped = [c for c in candidates if c not in [s["model"] for s in report.selection]]
    report.skipped["models_not_tried"] = skipped
    return chosen, None


def _fit_candidate(name: str, known: Mapping[str, object], fitter: _Fitter, obs: Observations, fp, what: str,
                   prog: Progress) -> tuple[FitResult, object, dict, list[str], float]:
    """Fit auto's candidate ``name`` to ``obs`` (and the footprints ``fp``): ``(fit, the model fitted, its scalars'
    notes, its parameter names, the start time)``; a solver error is a :class:`ReconstructionError` naming the
    ``what`` fit (the progress bar removed first)."""
    m = _model(name, known)
    params = list(m.param_names)
    ts = time.perf_counter()
    try:
        fit, m, notes = fitter.fit(m, obs, fp)
    except SolverError as exc:
        prog.abort()
        raise ReconstructionError(f"auto, {what} fit of {name}: {exc}") from None
    return fit, m, notes, params, ts


def _explained_at_full_size(name: str, known: Mapping[str, object], seen: _Observed, fitter: _Fitter,
                            auto_chi2: float, report: Report, prog: Progress) -> tuple | None:
    """The fit ``(fit, model, scalar notes)`` of the candidate ``name`` (auto's cheapest) at the maps' full size when
    it explains the fitted views' photos within their noise (χ² per residual ≤ ``auto_chi2``), else None; recorded
    as a row of ``report.selection`` (``full_size``, no held-out error). The fit is the final fit's own call, which
    :func:`_final_fit` then takes instead of repeating it.

    The trials judge larger maps on a coarser copy (:func:`_trial_observations`), where no model can explain a
    texture finer than the copy: every trial then misfits, and a richer model wins by absorbing part of that
    misfit in its extra maps. Measured on the 256² Mitsuba torus (a Lambert albedo of stripes and checks; trials
    on 128² maps): Lambert's trial χ² 90.7 and held-out error 0.026 against GGX + Lambert's 100 and 0.0057, so auto
    chose GGX + Lambert — 56 s, well-lit albedo 0.0177. Lambert at full size reads χ² 0.18, which ends the
    selection, and is the final fit: 0.0082 in 6.3 s."""
    fit, m, notes, params, ts = _fit_candidate(name, known, fitter, seen.obs, seen.fp, "full-size", prog)
    chi2 = _footprint_misfit(m, fit, seen.fp, seen.obs) if seen.fp is not None else \
        _misfit(m, fit, seen.obs, seen.sampling)
    row = {"model": name, "full_size": True, "train_chi2": chi2, "seconds": time.perf_counter() - ts,
           "params": params, **({"scalars": {k: v["value"] for k, v in notes.items()}} if notes else {})}
    report.selection.append(row)
    if chi2 <= auto_chi2:
        row["stopped"] = f"explains its photos at the maps' full size within their noise (χ² per residual " \
                         f"{chi2:.3g} ≤ {auto_chi2:g}); richer models skipped"
        return fit, m, notes
    return None


def _model_spec(name: str) -> dict:
    """The report's ``model_spec``: the model's specification and its name as written."""
    from capture.dataset import model_label, model_spec

    return {"spec": model_spec(name), "written": model_label(name)}


class _Fitted(NamedTuple):
    """The final fit."""

    fit: FitResult
    model: object                   #: the model fitted, with the fitted scalars as known values
    scalar_notes: dict              #: notes on the fitted scalars (the report's ``fit.scalars``)


def _final_fit(mdl, seen: _Observed, fitter: _Fitter, fit_views: list[int], prog: Progress,
               report: Report, ready: tuple | None = None) -> _Fitted:
    """Fit the chosen model on the fitted views at full size; warn of scalars observable in no texel. With the fast
    solver and pixel footprints, maps finer than the photos are fitted on a pyramid (the report's ``fit.pyramid``):
    when the pixel centres sample them too sparsely for the per-texel stages (:func:`capture.fit.pyramid_size`),
    the whole fit runs on coarser maps first and its maps, upsampled, start the footprint steps; and those steps
    run on maps no finer than the pixel footprints sample (:func:`capture.footprint.sampled_map_size`), whose
    maps, upsampled to full size, are judged there without further steps."""
    from .footprint import sampled_map_size

    prog.start("solve", report.model)
    pyramid = fitter.solver == "fast" and seen.fp is not None
    size = pyramid_size(seen.obs) if pyramid else seen.texture_size
    # (a model affine in its parameters takes its footprint steps at full size: they are sparse products only, and
    # they explain the photos there — the Mitsuba torus, 8 × 128² photos on 256² maps, χ² 0.013 after six steps
    # at 256², 3.45 judged from the fit at 128², the finest its footprints sample)
    level = sampled_map_size(seen.fp, size) if pyramid and not Layout.of(mdl).affine else seen.texture_size
    full = seen.texture_size
    try:
        if size < full or level < full:
            # the whole fit on the pixel centres' level (or, where they sample the full size and the footprints do
            # not, on the footprints' level)
            t0 = time.perf_counter()
            first = size if size < full else level
            cobs = seen.observe(first).select_views(fit_views)
            cfp = seen.footprints(first).select_views(fit_views)
            if level in (first, full):
                seen.views.release()    # nothing after this makes observations
            coarse, mdl, scalar_notes = fitter.fit(mdl, cobs, cfp)
            note = {"coarse_size": first, "coarse_samples": cobs.n_samples, "coarse_s": time.perf_counter() - t0,
                    "coarse_fit": {k: v for k, v in coarse.info.items()
                                   if isinstance(v, (int, float, str)) and k != "accepted"},
                    "level_size": level, "full_size": full}
            del cobs, cfp               # the coarse problem is not needed beside the finer ones
            # steps follow from the filled maps; judged without steps, the maps are the fit's own (unfilled: the
            # fills of texels no pixel determines on their own would not explain the photos)
            maps = coarse.maps if level > first else coarse.raw
            del coarse
            if first < level < full:
                # the footprint steps on the finest maps the footprints sample, from the coarse fit's maps
                t1 = time.perf_counter()
                lobs = seen.observe(level).select_views(fit_views)
                lfp = seen.footprints(level).select_views(fit_views)
                seen.views.release()
                lfit, _, _ = fitter.fit(mdl, lobs, lfp, refine_from=upsample_maps(maps, level))
                del lobs, lfp
                maps = lfit.raw
                note["level_s"] = time.perf_counter() - t1
                del lfit
            t1 = time.perf_counter()
            fit, _, _ = fitter.fit(mdl, seen.obs, seen.fp, refine_from=upsample_maps(maps, full),
                                   refine_steps=0 if level < full else None)
            fit.info["pyramid"] = {**note, "refine_s": time.perf_counter() - t1}
        else:
            seen.views.release()
            # (auto's full-size fit of this model is this very call: taken as it is, ``ready``)
            fit, mdl, scalar_notes = ready if ready is not None else fitter.fit(mdl, seen.obs, seen.fp)
    except SolverError as exc:
        prog.abort()
        raise ReconstructionError(str(exc)) from None
    for n, note in scalar_notes.items():
        if not note["measured"]:
            report.warnings.append(f"parameter '{n}' is fitted as one value for the object but is "
                                   f"unobservable in every texel; its value {note['value']} is a guess")
    return _Fitted(fit, mdl, scalar_notes)


# -- report on the fit ------------------------------------------------------------------------------


def _check_misfit(report: Report, fitted: _Fitted, seen: _Observed, pred: Tensor) -> float:
    """The final fit's χ² per residual (of the pixels when it fitted footprints) from its prediction ``pred``
    (:func:`_fitted_prediction`); a warning above :data:`UNEXPLAINED_CHI2`."""
    mdl, fit, fp, obs = fitted.model, fitted.fit, seen.fp, seen.obs
    chi2 = (_footprint_misfit(mdl, fit, fp, obs, pred=pred) if fp is not None
            else _misfit(mdl, fit, obs, seen.sampling, pred=pred))
    if chi2 > UNEXPLAINED_CHI2:
        report.warnings.append(
            f"the fitted maps do not explain the photos: χ² per residual {chi2:.3g} against ≤ ~4 for photos explained "
            f"within their noise (residuals of {math.sqrt(chi2):.0f} σ on average). Likely causes: cameras in another "
            f"convention (OpenGL/Blender: y up, z backward — renderer.camera converts them), light intensities in "
            f"other units or a wrong exposure, a model too simple for the material (try --model auto or a richer "
            f"one), a lens blur or pixel filter other than a box, or a mesh that does not match the photos; the "
            f"error column of views.png shows where")
    return chi2


def _known_maps(mdl, map_size: tuple[int, int]) -> dict[str, Tensor]:
    """The model's known parameters as constant ``[H, W, C]`` float32 maps."""
    H, W = map_size
    return {k: t_.to(torch.float32).expand(H, W, t_.numel()) for k, t_ in getattr(mdl, "known", {}).items()}


def _report_coverage(report: Report, fit: FitResult, seen: _Observed, spt: Tensor) -> None:
    """The report's ``coverage`` (``spt``: samples per texel), with warnings for a parameter unobservable in every
    observed texel and for roughness the photos' direction sampling does not resolve (:func:`unresolved_roughness`)."""
    observed = fit.observed
    report.coverage = {"texels": int(observed.numel()), "observed": int(observed.sum()),
                       "unobserved_filled": int((~observed).sum()),
                       "unobservable": {k: int(v.sum()) for k, v in fit.unobservable.items()},
                       "observable_fraction": {k: 1.0 - float(v[observed].float().mean()) if bool(observed.any())
                                               else 0.0 for k, v in fit.unobservable.items()},
                       "sampling": seen.sampling,
                       "samples_per_observed_texel": float(spt[observed].float().mean()) if bool(observed.any()) else 0,
                       # observed texels the photos do not determine on their own whose fitted values were kept (the
                       # sharing's materials, or the regularised fit of maps finer than the photos), not filled
                       "unobservable_kept": {k: int((v & ~fit.filled[k]).sum()) for k, v in fit.unobservable.items()}}
    # no texel resolved by any pixel: the maps are finer than the photos resolve (through the pixel footprints)
    too_fine = fit.info.get("resolved_fraction") == 0.0
    for k, v in fit.unobservable.items():
        if bool(observed.any()) and int(v.sum()) == int(observed.sum()):
            cause = ("no pixel takes enough of any texel to determine it: the maps are finer than the photos resolve"
                     if too_fine else "e.g. no highlight seen anywhere")
            if report.coverage["unobservable_kept"][k]:
                report.warnings.append(
                    f"parameter '{k}' is unobservable in every observed texel ({cause}): its map holds the fit's "
                    f"regularised values, which the photos constrain only together with the neighbouring texels and "
                    f"the prior — not measured texel by texel (confidence_{k}.exr says how loosely)")
            else:
                report.warnings.append(f"parameter '{k}' is unobservable in every observed texel ({cause}): its map "
                                       f"is filled with defaults, not measured")
    if "roughness" in fit.raw:
        frac, med = unresolved_roughness(seen.obs, fit.raw["roughness"], observed & ~fit.unobservable["roughness"])
        report.coverage["roughness_unresolved_fraction"] = frac
        if frac >= UNRESOLVED_WARN:
            report.warnings.append(
                f"roughness: in {frac:.0%} of the texels where it is called observable no half vector of theirs or "
                f"their neighbours' came within 3 half-maximum angles of the fitted lobe (median fitted roughness "
                f"{med:.3f}) — the highlight peak was never seen, so the roughness there is an upper bound set by "
                f"how densely the photos "
                f"sample directions (a near-mirror surface), not a measurement; more views or light positions, "
                f"or higher resolution, resolve it")


def _report_fit(report: Report, fitted: _Fitted, chi2: float, seen: _Observed, solver: str) -> None:
    """The report's ``fit``, with a warning when the reflectance sharing fell back to the texels' own fits."""
    fit = fitted.fit
    fb = fit.info.get("sharing_fallback")
    if fb and fb["kept"] == "fallback":
        report.warnings.append(
            f"reflectance sharing: the {len(fit.info.get('materials', []))} materials found explain the photos worse "
            f"than the per-texel fit (data cost {fb['shared_data_cost']:.3g} against {fb['per_texel_data_cost']:.3g}); "
            f"the {fb['own_fit_texels']} texels whose own samples reject their material keep their own fit (data cost "
            f"{fb['fallback_data_cost']:.3g}) — a material of the object gave no texel that determines it (more views "
            f"or lights off the camera axis would)")
    report.fit = {"iterations": fit.iterations, "final_cost": fit.history[-1] if fit.history else None,
                  "chi2_per_residual": chi2, "image_formation": "pixel footprints" if seen.fp is not None else
                  "one ray per pixel centre",
                  "seconds": fit.time_s, **{k: v for k, v in fit.info.items() if k != "accepted"}}
    if fitted.scalar_notes:
        report.fit["scalars"] = fitted.scalar_notes
    if solver == "fast":
        report.fit["pooled"] = seen.pooled_auto or {"block": int(seen.options.get("pooled") or 0), "auto": False}


def _report_skipped(report: Report, mdl, ds: Dataset, seen: _Observed, solve_s: float) -> None:
    """The report's ``skipped``: parameters not allocated or given per object, pixels not evaluated and the time
    that saved (:func:`_time_saved`)."""
    import materials
    from renderer.lights import DirectionalLight, PointLight

    known_used = getattr(mdl, "known", {})
    unused = sorted(set(materials.CANONICAL) - set(mdl.param_names) - set(known_used))
    report.skipped["parameters_not_allocated"] = unused
    if known_used:
        report.skipped["parameters_per_object"] = {k: t_.tolist() for k, t_ in known_used.items()}
    obs = seen.obs
    report.skipped["pixels_not_evaluated"] = {k: v for k, v in obs.drops.items()}
    report.skipped["pixel_fraction_skipped"] = 1 - obs.n_samples / max(_n_pixels(ds), 1)
    report.skipped["time_saved_estimate_s"] = _time_saved(
        seen.all_obs, [sum(isinstance(x, (PointLight, DirectionalLight)) for x in v.lights) for v in ds.views],
        solve_s, obs.n_pairs, report.selection, report.skipped.get("models_not_tried", []))


# -- metrics vs ground truth ------------------------------------------------------------------------


def _report_errors(report: Report, ds: Dataset, fitted: _Fitted, seen: _Observed,
                   known_maps: Mapping[str, Tensor]) -> None:
    """The report's ``errors`` against the dataset's ground truth, when it has one of the fitted maps' size (else a
    warning saying why there are none)."""
    from .metrics import determined_at_truth, errors_by_texel_set, map_errors, observability_errors

    if ds.gt is None:
        return
    fit, mdl, obs = fitted.fit, fitted.model, seen.obs
    gt_size = tuple(next(iter(ds.gt.maps.values())).shape[:2])
    if gt_size != tuple(obs.map_size):
        report.warnings.append(f"no texel errors against the ground truth: its maps are {gt_size[1]}×{gt_size[0]}, "
                               f"the fitted ones {obs.map_size[1]}×{obs.map_size[0]} (texture_size / --tex "
                               f"left unset fits at the truth's size)")
        return
    # fitted values (raw) on every observed texel, on the texels where each map is observable (judged at the
    # estimate) and, when the photos were rendered by the fitted model, on those it is determined at the truth
    observed = fit.observed
    determined = None
    gt_model = ds.gt.build_model()
    if gt_model.name == getattr(mdl, "base", mdl).name:
        determined = determined_at_truth(gt_model, obs, ds.gt.maps, sampling=seen.sampling,
                                         noise=seen.options.get("noise"),
                                         observable_std=seen.options.get("observable_std"))
    both = observability_errors(fit.raw, ds.gt.maps, observed, fit.unobservable, ds.gt.regions,
                                ds.gt.region_names, determined=determined)
    report.errors["maps"] = {k: v["observed"] for k, v in both.items()}
    report.errors["maps_observable"] = {k: v["observable"] for k, v in both.items()}
    if determined is not None:
        report.errors["maps_determined_at_truth"] = {k: v["determined"] for k, v in both.items()
                                                     if "determined" in v}
    report.errors["maps_filled"] = map_errors(fit.maps, ds.gt.maps, observed, None, None)
    report.errors["maps_by_texel_set"] = errors_by_texel_set(fit.raw, ds.gt.maps, obs, seen.fp)
    report.errors["observability"] = both
    if known_maps:  # how far the given values are from the truth, over the observed texels
        report.errors["known"] = map_errors(known_maps, ds.gt.maps, observed, None, None)
    report.errors["gt_model"] = ds.gt.model
    _report_truth_chi2(report, ds, gt_model, mdl, seen)


def _report_truth_chi2(report: Report, ds: Dataset, gt_model, mdl, seen: _Observed) -> None:
    """The χ² per residual of the true maps under the true model, predicted as the fit predicts its photos (through
    the pixel footprints, or at the samples), into ``report.errors["chi2_at_truth"]``: the floor the photos and the
    fit's image formation leave. A fit far above it stopped short of what the photos allow
    (:data:`TRUTH_CHI2_RATIO`), and the summary warns."""
    maps = ds.gt.maps
    if not set(gt_model.param_names) <= set(maps):
        return
    fp, obs = seen.fp, seen.obs
    if fp is not None:
        with torch.no_grad():
            truth = _pixel_chi2(fp.render(gt_model, {k: v.to(fp.radiance.dtype) for k, v in maps.items()}), fp, obs)
    else:
        truth = _sample_chi2(_render(gt_model, maps, obs, seen.sampling), obs)
    report.errors["chi2_at_truth"] = truth
    fit = report.fit.get("chi2_per_residual")
    if fit is None or not math.isfinite(truth):
        return
    if fit > TRUTH_CHI2_RATIO * truth and fit > TRUTH_CHI2_FLOOR:
        same = gt_model.name == getattr(mdl, "base", mdl).name
        cause = ("the solver stopped short of what the photos allow (texels stuck in a compromise, too few steps, or "
                 "the neighbour prior and the material tie holding texels the photos determine): part of the map "
                 "error is the fit's, not the photos'" if same else
                 f"the fitted model ({report.model_spec['written']}) explains less than the true one "
                 f"({gt_model.name}), or the solver stopped short")
        times = f"{fit / truth:.1f}× " if truth > 0 else "far "
        report.warnings.append(
            f"the fit explains its photos {times}worse than the true maps do through the same image formation (χ² per "
            f"residual {fit:.3g} against {truth:.3g}): {cause}")


def _rerender_views(report: Report, data: _Loaded, fitted: _Fitted, seen: _Observed, pred: Tensor) -> list[tuple]:
    """Every view re-rendered, compared with its photo (``report.views``): the fitted views with the fitted values
    (``pred``, :func:`_fitted_prediction`), the held-out ones with the filled maps a user gets (texels only they see
    are unobserved in the fit). Returns ``(view, image, mask)`` rows for the views pages, the held-out views first."""
    from .metrics import image_metrics

    fit, mdl, obs, held_obs, fp, held_fp = fitted.fit, fitted.model, seen.obs, seen.held_obs, seen.fp, seen.held_fp
    held_views, dtype = data.held_views, seen.dtype
    renders = []
    if fp is not None:
        # the held-out views' pixels as the fit models pixels (area averages over their footprints)
        with torch.no_grad():
            held_pred = held_fp.render(mdl, {k: v.to(dtype) for k, v in fit.maps.items()}) \
                if held_fp is not None else None
    else:
        held_pred = _render(mdl, fit.maps, held_obs, seen.sampling) if held_obs is not None else None
    for i, v in enumerate(data.ds.views):
        src, values = (held_obs, held_pred) if i in held_views else (obs, pred)
        H, W = v.camera.height, v.camera.width
        if fp is not None:
            img, mask = (held_fp if i in held_views else fp).images(values, i, (H, W))
        else:
            img = torch.zeros(H * W, 3, dtype=values.dtype)
            sel = src.view == i
            img[src.pixel[sel]] = values[sel]
            img = img.reshape(H, W, 3)
            mask = torch.zeros(H * W, dtype=torch.bool)
            mask[src.pixel[sel]] = True
            mask = mask.reshape(H, W)
        m = image_metrics(img, seen.photos[i].radiance, mask)
        report.views.append({"view": i, **({"heldout": True} if i in held_views else {}), **m})
        renders.append((i, img, mask))
    # the grid shows the held-out views first
    renders.sort(key=lambda r: r[0] not in held_views)
    return renders


# -- write ------------------------------------------------------------------------------------------


def _write_outputs(out_dir: Path, ds, fit: FitResult, obs, renders, photos, report: Report, times, force,
                   max_grid_views, spt: Tensor, vpt: Tensor, known_maps: Mapping[str, Tensor], prog=None) -> None:
    """Write everything into ``out_dir`` atomically (module docstring, step 6): maps, confidence EXRs with their
    previews, coverage, the labelled views pages (``max_grid_views`` views a page), the mesh, ``report.json`` and
    ``summary.txt`` — after adding to the report which directions the photos miss (``coverage.directions``,
    :func:`capture.metrics.coverage_advice`). ``prog``: the job's :class:`capture.progress.Progress` (closed at the
    end)."""
    from capture.metrics import coverage_advice, texel_normals
    from capture.outputs import atomic_folder, json_text, na_floats, na_text
    from capture.plots import ViewRow, plot_confidence, plot_views
    from renderer.imageio import write_exr, write_png

    from .progress import Progress

    prog = prog if prog is not None else Progress({"outputs": 1.0}, enabled=False)
    prog.start("outputs")
    t = time.perf_counter()
    # which directions the photos miss, from the observations' geometry and the mesh's texel normals
    normals, covered = texel_normals(ds.mesh, tuple(obs.map_size))
    report.coverage["directions"] = coverage_advice(obs, normals, covered,
                                                    specular=any(k in fit.raw for k in ("f0", "roughness")))
    # atomic: a temporary folder next to out_dir, moved into place at the end (the umask's permissions, the old
    # output removed); any failure or interrupt removes it; an OSError is one line naming out_dir
    with atomic_folder(out_dir, force=force, error=ReconstructionError, force_flag="force=True (--force)") as tmp:
        for k, m in {**fit.maps, **known_maps}.items():
            write_exr(tmp / f"{k}.exr", m.float())
            png = m if m.shape[-1] in (1, 3) else m[..., :3]
            if math.isfinite(float(m.max())) and float(m.max()) > 1:
                png = png / float(png.max())
            write_png(tmp / f"{k}.png", png.float().clamp(0, 1),
                      transfer=preview_transfer(k))
            if k in known_maps:
                continue
            write_exr(tmp / f"confidence_{k}.exr", fit.confidence[k].float(), allow_nonfinite=True)
            plot_confidence(tmp / f"confidence_{k}.png", fit.confidence[k], fit.unobservable[k].cpu(), k)
            write_png(tmp / f"unobservable_{k}.png", fit.unobservable[k].float()[..., None], transfer="linear")
            prog.tick(k)
        write_exr(tmp / "coverage.exr", torch.stack([spt.float(), vpt.float(), fit.observed.float()], -1))
        # every view, labelled: photo | re-render | |relative error| (capture.plots.plot_views), max_grid_views a page
        psnr = {v["view"]: v.get("psnr") for v in report.views}
        held = {v["view"] for v in report.views if v.get("heldout")}
        plot_views(tmp, [ViewRow(i, photos[i].radiance, img, mask, psnr.get(i), i in held) for i, img, mask in renders],
                   per_page=max(int(max_grid_views), 1))
        prog.tick("views")
        mesh_src = Path(ds.root) / ds.mesh_file
        if mesh_src.suffix.lower() == ".obj":
            shutil.copyfile(mesh_src, tmp / "mesh.obj")
        else:
            from renderer.mesh import save_mesh

            save_mesh(ds.mesh, tmp / "mesh.obj")
        times["write"] = time.perf_counter() - t
        times["total"] = sum(v for k, v in times.items() if k != "total")
        report.times = dict(times)
        report.warnings[:0] = [w for w in ds.warnings if w not in report.warnings]  # the dataset's, e.g. NaN pixels
        (tmp / "report.json").write_text(json_text(report.to_dict()))  # strict JSON: non-finite numbers are null
        printed = Report(**na_floats(report.to_dict()))  # non-finite numbers print as n/a, not nan
        (tmp / "summary.txt").write_text(na_text(_summary(printed)))
    prog.close()


def _check_holdout(holdout, n_views: int) -> list[int]:
    """The sorted held-out view indices of ``holdout`` (None → []), or a ReconstructionError naming the fix."""
    if holdout is None:
        return []
    try:
        if isinstance(holdout, (str, bytes)):
            raise TypeError
        holdout = list(holdout)
        if any(isinstance(i, bool) for i in holdout):
            raise TypeError
        holdout = [operator.index(i) for i in holdout]          # ints, numpy integers; not floats or bools
    except TypeError:
        raise ReconstructionError(f"holdout must be a list of view indices (integers), e.g. [3, 7], "
                                  f"got {holdout!r}") from None
    held = sorted(set(holdout))
    if len(held) != len(holdout) or any(i < 0 or i >= n_views for i in held):
        raise ReconstructionError(f"holdout must list distinct view indices in [0, {n_views}) (the dataset has "
                                  f"{n_views} views), got {list(holdout)}")
    if len(held) >= n_views:
        raise ReconstructionError(f"holdout {held} leaves no view to fit; hold out fewer than {n_views} views")
    return held


def _time_saved(obs: Observations, lights_per_view: list[int], solve_s: float, fitted_pairs: int,
                selection: list[dict], not_tried: list[str]) -> dict:
    """What the skips saved, in seconds estimated from this run's own costs (the report's ``skipped``).

    * ``pairs_upper_s``: the (sample, light) pairs (``pairs_not_evaluated``) that a shader of every pixel on the
      object with every light of its view would have evaluated and this run did not — pixels dropped as backfacing,
      shadowed, unlit, clipped or non-finite, and the lights that do not reach a kept sample (all views, ``obs``) —
      priced at the solve's *mean* cost per pair it evaluated (``fitted_pairs``). An upper bound: part of the solve
      is per texel, not per pair (default scene, 2 threads: solve 9.0 / 11.8 / 17.9 s for 4 / 8 / 16 views, a
      marginal 28–31 µs per pair against a mean of 45 µs at 16 views). Background pixels are not counted: no
      surface, nothing to shade.
    * ``models_not_tried_lower_s``: ``model="auto"`` stopped before the richer candidates; each would have cost at
      least the last tried model's fit (a richer model has more parameters to fit) — a lower bound.

    ``lights_per_view``: the point and directional lights of each view (environment lights have no pairs).
    """
    per_view = torch.bincount(obs.view, minlength=len(lights_per_view)).tolist()
    full = sum(n * k for n, k in zip(per_view, lights_per_view, strict=True))
    on_object_dropped = sum(v for k, v in obs.drops.items() if k != "background")
    mean_lights = sum(lights_per_view) / max(len(lights_per_view), 1)
    skipped_pairs = int(full - obs.n_pairs + round(on_object_dropped * mean_lights))
    out = {"pairs_not_evaluated": skipped_pairs, "pairs_evaluated": int(obs.n_pairs),
           "pairs_upper_s": skipped_pairs * solve_s / max(fitted_pairs, 1)}
    if not_tried and selection:
        out["models_not_tried_lower_s"] = len(not_tried) * float(selection[-1]["seconds"])
    return out


def _cell(row: dict | None, what: str) -> str:
    """``RMSE / max`` of an error row, or words where it has no texel."""
    if not row or not row.get("texels"):
        return f"none {what}"
    return f"{row['rmse']:.5f} / {row['max']:.5f}"


def _error_table(r: Report) -> list[str]:
    """The summary's errors against the ground truth: a table with a header row naming each column, a key under
    it, and a line in words for each map with no observable texel."""
    truth = r.errors.get("maps_determined_at_truth", {})
    frac = r.coverage.get("observable_fraction", {})
    head = ["map", "observed texels", "observable texels", "observable", "flagged share"]
    if truth:
        head.append("determined at truth (fraction)")
    rows, unmeasured = [], []
    for k, v in r.errors["maps"].items():
        o = r.errors.get("maps_observable", {}).get(k, {})
        ob = r.errors.get("observability", {}).get(k, {})
        f = frac.get(k)
        row = [k, _cell(v, "observed"), _cell(o, "observable"), "n/a" if f is None else f"{f:.1%}",
               "n/a" if "flagged_share" not in ob else f"{ob['flagged_share']:.1%}"]
        if truth:
            row.append(f"{_cell(truth[k], 'determined')} ({ob.get('determined_fraction', 0.0):.1%})" if k in truth
                       else "n/a")
        rows.append(row)
        if v.get("texels") and not o.get("texels"):
            unmeasured.append(
                f"{k}: not measured texel by texel — no texel is observable on its own (its map holds the fit's "
                f"regularised values)" if r.coverage.get("unobservable_kept", {}).get(k) else
                f"{k}: not measured — no texel is observable (its map is filled, not measured)")
    widths = [max(len(x[c]) for x in [head, *rows]) for c in range(len(head))]
    fmt = lambda row: "  " + "  ".join(x.ljust(w) for x, w in zip(row, widths, strict=True)).rstrip()  # noqa: E731
    key = ("  columns: observed texels / observable texels = on all observed texels / on texels where the map is "
           "observable; observable = their fraction; flagged share = share of the squared error in texels flagged "
           "unobservable (near 100 %: the error is where the report warned)")
    if truth:
        key += "; determined at truth = on texels the photos determine at the true maps (their fraction)"
    return (["errors vs ground truth, RMSE / max |error| (canonical units):", fmt(head),
             fmt(["-" * w for w in widths]), *map(fmt, rows), key] + [f"  {u}" for u in unmeasured])


def _direction_lines(d: dict | None) -> list[str]:
    """The summary's coverage advice (:func:`capture.metrics.coverage_advice` in ``report.coverage``)."""
    if not d or not d.get("texels"):
        return []
    c, hd = d["cos"], d["highlight_deg"]
    parts = [f"{d['unseen']['fraction']:.0%} never seen at n·v > {c:g}",
             f"{d['unlit']['fraction']:.0%} seen but never lit at n·l > {c:g}"]
    if "no_highlight" in d:
        parts.append(f"{d['no_highlight']['fraction']:.0%} seen and lit but never with a half vector within {hd:g}° "
                     f"of the normal (no highlight)")
    out = [f"directions the photos miss, of {d['texels']} surface texels: " + "; ".join(parts)]
    out.extend(f"advice: {a}" for a in d.get("advice", []))
    if not d.get("advice"):
        out.append("advice: none — every direction judged is covered for at least 99 % of the surface texels")
    return out


def _peak_memory() -> dict:
    """The process's peak resident memory so far (``peak_rss_bytes``; the reconstruction's own peak when it is the
    process's main work, as with the command line) and, where CUDA is in use, torch's peak allocation on the
    device (``cuda_peak_bytes``)."""
    out = {}
    try:
        import resource
        import sys

        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        out["peak_rss_bytes"] = int(rss if sys.platform == "darwin" else rss * 1024)    # Linux reports KiB
    except (ImportError, OSError):       # no getrusage (Windows): not reported
        pass
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        out["cuda_peak_bytes"] = int(torch.cuda.max_memory_allocated())
    return out


def _report_budget(report: Report, budget: float | None) -> None:
    """With a memory budget (GiB, ``FitOptions.memory_budget``): ``report.memory["budget_bytes"]``, and a warning
    when the peak went above it, saying what the budget sized and what it did not."""
    if budget is None:
        return
    limit = FitOptions(memory_budget=budget).memory_budget_bytes
    report.memory["budget_bytes"] = limit
    peak = report.memory.get("cuda_peak_bytes" if report.device.startswith("cuda") else "peak_rss_bytes")
    if peak is not None and peak > limit:
        form = report.fit.get("footprint_jacobian")
        pixels = report.samples.get("footprints", {}).get("pixels", report.samples.get("valid"))
        report.warnings.append(
            f"peak memory {peak / 2 ** 30:.2f} GiB went above the memory budget of {budget:g} GiB: the budget sizes "
            f"only the footprint solve's Jacobian (kept {form or 'as asked'}); the observations of the {pixels} "
            f"observed pixels and their pixel operator are held whole. Fit the photos binned (--bin 2: about 4× "
            f"fewer pixels, photo_bin=2), smaller maps (--tex) or a dataset of fewer views, or raise the budget")


def _memory_text(memory: Mapping[str, int]) -> str:
    parts = [f"{name} {memory[key] / 2 ** 30:.2f} GiB" for key, name in
             (("peak_rss_bytes", "peak memory"), ("cuda_peak_bytes", "CUDA peak"), ("budget_bytes", "budget"))
             if key in memory]
    return ("  " + "  ".join(parts)) if parts else ""


def _options_lines(options: Mapping[str, object] | None) -> list[str]:
    """The fast solver's options that differ from :class:`FitOptions`' defaults, as one summary line (none for the
    adam solver, whose report has no options; report.json holds them all)."""
    if not options:
        return []
    default = FitOptions().to_dict()
    changed = {k: v for k, v in options.items() if default.get(k, v) != v}
    return ["solver options: " + (", ".join(f"{k}={v}" for k, v in changed.items()) if changed else "defaults")]


def _pyramid_line(pyr: dict, texels: int) -> str:
    """The summary's line on the map pyramid of a fit (the report's ``fit.pyramid``, :func:`_final_fit`)."""
    from .footprint import FOOTPRINT_SAMPLED

    coarse, level, full = pyr["coarse_size"], pyr.get("level_size"), pyr.get("full_size")
    sampled = (f"the finest the pixel footprints sample: at most {FOOTPRINT_SAMPLED:g} texels per pixel step for "
               f"the median pixel")
    if level is None or level == full:
        return (f"coarse to fine: the photos' pixel centres sample the {texels} texels too sparsely for per-texel "
                f"fits, so the fit ran on {coarse}² maps first ({pyr['coarse_s']:.1f} s) and its maps, upsampled, "
                f"started the footprint steps at full size ({pyr['refine_s']:.1f} s); texels finer than the photos "
                f"resolve hold the regularised solution")
    upsampled = (f"upsampled to {full}² and judged there ({pyr['refine_s']:.1f} s): texels finer than the photos "
                 f"resolve hold the upsampled solution")
    if level == coarse:
        return (f"coarse to fine: the fit ran on {level}² maps ({pyr['coarse_s']:.1f} s), {sampled}; its maps were "
                f"{upsampled}")
    return (f"coarse to fine: the per-texel stages ran on {coarse}² maps ({pyr['coarse_s']:.1f} s), where the photos' "
            f"pixel centres sample the texels densely enough, the footprint steps on {level}² maps "
            f"({pyr['level_s']:.1f} s), {sampled}; their maps were {upsampled}")


def _summary(r: Report) -> str:
    lines = [f"model {r.model}  solver {r.solver}  device {r.device}  total {r.times.get('total', 0):.1f} s  "
             + "  ".join(f"{k} {v:.1f}s" for k, v in r.times.items() if k != "total") + _memory_text(r.memory),
             f"samples {r.samples.get('valid')} valid of {r.samples.get('pixels')} pixels"
             + (f" (photos binned {r.samples['bin']}×{r.samples['bin']})" if r.samples.get("bin", 1) > 1 else "")
             + "; dropped "
             + ", ".join(f"{k} {v}" for k, v in r.drops.items() if v),
             f"texels observed {r.coverage.get('observed')} / {r.coverage.get('texels')}; unobservable "
             + ", ".join(f"{k} {v}" for k, v in r.coverage.get("unobservable", {}).items())]
    lines.extend(_options_lines(r.fit.get("options")))
    fps = r.samples.get("footprints")
    if fps:
        lines.append(f"image formation: pixel footprints, {fps['pixels']} whole pixels of {fps['samples']} shaded rays "
                     f"(per pixel: " + ", ".join(f"{k}: {v}" for k, v in fps["samples_per_pixel"].items())
                     + f"; {fps['rays_saved_vs_uniform']:.0%} fewer than 16 per pixel) reading the maps at "
                     f"{fps.get('texture_samples', 0)} texture sub-samples; fit χ² per residual "
                     f"{r.fit.get('chi2_per_residual', float('nan')):.3g}"
                     + (f"; in {fps['noisy_views']} of {r.samples.get('views')} views the photo's noise (σ² = a·I + b, "
                        f"measured) is not taken for shading curvature" if fps.get("noisy_views") else "")
                     + ("; ray counts from the model's shading (affine in its parameters), the photos' curvature "
                        "setting the texture sub-samples" if fps.get("ray_counts") == "model" else ""))
    saved = r.skipped.get("time_saved_estimate_s", {})
    skips = [f"parameters not allocated: {', '.join(r.skipped['parameters_not_allocated']) or 'none'}"] \
        if "parameters_not_allocated" in r.skipped else []
    if saved:
        skips.append(f"{saved['pairs_not_evaluated']} (sample, light) pairs on the object not evaluated "
                     f"(saved ≤ {saved['pairs_upper_s']:.1f} s)")
    if r.skipped.get("models_not_tried"):
        skips.append(f"models not tried: {', '.join(r.skipped['models_not_tried'])} (saved ≥ "
                     f"{saved.get('models_not_tried_lower_s', 0.0):.1f} s)")
    if skips:
        lines.append("skipped: " + "; ".join(skips) + (" — times estimated from this run's costs" if saved else ""))
    per_object = r.skipped.get("parameters_per_object", {})
    if per_object:
        fitted = r.fit.get("scalars", {})
        lines.append("one value per object: " + ", ".join(
            f"{k} {', '.join(f'{x:.4g}' for x in v)} "
            + (f"(fitted: median of {fitted[k]['from_texels']} texels)" if k in fitted else "(given)")
            for k, v in per_object.items()))
    pyr = r.fit.get("pyramid")
    if pyr:
        lines.append(_pyramid_line(pyr, r.coverage.get("texels", 0)))
    if r.fit.get("share_anchor_factor", 1.0) > 1.0:
        lines.append(f"reflectance sharing seeded from {r.fit['share_anchors']} roughly determined texels "
                     f"(thresholds × {r.fit['share_anchor_factor']:g}: fewer than 1 % of the texels determine every "
                     f"material parameter)")
    retry = r.fit.get("share_retry")
    if retry:
        floor = retry["noise_floor"]
        kept = (f"the second fit ({retry['retry_data_cost'] / floor:.2g}× the noise)" if retry["kept"] == "retry"
                else "the first (the second fitted no better)")
        lines.append(f"the materials from so few texels missed the photos by {retry['data_cost'] / floor:.0f}× "
                     f"their noise; seeded again from {retry['anchors']} texels (thresholds × {retry['factor']:g}): "
                     f"kept {kept}")
    prop = r.fit.get("footprint_proposals")
    if prop and prop.get("moved"):
        lines.append(f"{prop['moved']} moves of {prop['candidates']} texels the footprint steps left misfit to nearby "
                     f"values (material borders): data cost {prop['cost_before']:.3g} → {prop['cost_after']:.3g}")
    ratio = r.fit.get("photo_noise_ratio")
    if ratio is not None and ratio > 1:
        lines.append(f"photo noise: {math.sqrt(ratio):.1f}× the noise model's std (measured in image space); the "
                     f"confidence maps and the reflectance sharing weigh each texel's photos accordingly")
    pooled = r.fit.get("pooled", {})
    if pooled.get("block"):
        why = (f"the lights stay fixed: {pooled['distinct_lights']} positions for {pooled['view_light_pairs']} "
               f"view-light pairs; pooled=0 / --pooled 0 turns them off" if pooled.get("auto") else "as asked")
        lines.append(f"pooled material proposals: {pooled['block']} × {pooled['block']}-texel tiles ({why})")
    if r.selection:
        lines.append("auto: " + " → ".join(f"{s['model']} (" + (f"at full size, χ² per residual {s['train_chi2']:.3g}"
                                                                if s.get("full_size") else
                                                                f"held-out MAE {s['heldout_mae']:.4g}, training χ² "
                                                                f"per residual {s['train_chi2']:.3g}") + ")"
                                           for s in r.selection)
                     + (f"; stopped: {r.selection[-1]['stopped']}" if "stopped" in r.selection[-1] else ""))
        tr = r.samples.get("auto_trials")
        if tr and tr["sample_fraction"] < 1:
            lines.append(f"auto's trial fits ran on {tr['texture_size']}² maps with {tr['sample_fraction']:.0%} of the "
                         f"samples ({tr['samples']}); the chosen model was then fitted at full size")
    if "maps" in r.errors:
        lines.extend(_error_table(r))
        if "chi2_at_truth" in r.errors:
            fit_chi2 = r.fit.get("chi2_per_residual", float("nan"))
            lines.append(f"χ² per residual of the true maps through the same image formation "
                         f"{r.errors['chi2_at_truth']:.3g} (the fit's {fit_chi2:.3g}): the floor the photos and the "
                         f"fit's pixel model leave")
        sets = r.errors.get("maps_by_texel_set", {})
        if sets:
            lines.append("RMSE by texel set: " + "; ".join(
                f"{k.replace('_', ' ')} ({v['texels']}) " + " / ".join(f"{n} {e:.4f}" for n, e in v.items()
                                                                       if n != "texels")
                for k, v in sets.items()))
    for label, vs in (("re-render", [v for v in r.views if not v.get("heldout")]),
                      ("held-out views " + ", ".join(str(v["view"]) for v in r.views if v.get("heldout"))
                       + " (not fitted; filled maps)", [v for v in r.views if v.get("heldout")])):
        if vs:
            ps = [v["psnr"] for v in vs]
            lines.append(f"{label}: PSNR {min(ps):.1f}–{max(ps):.1f} dB, SSIM mean "
                         f"{sum(v['ssim'] for v in vs) / len(vs):.4f}")
    lines.extend(_direction_lines(r.coverage.get("directions")))
    lines.extend(f"WARNING: {w}" for w in r.warnings)
    return "\n".join(lines) + "\n"
