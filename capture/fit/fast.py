"""The fast path built for known geometry (:func:`solve_fast`): the orchestration of the per-texel stages
(:mod:`capture.fit.texel`), the reflectance sharing (:mod:`capture.fit.sharing`), the joint refinement
(:mod:`capture.fit.joint`) and the finalisation (:mod:`capture.fit.observability`)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from materials.model import Model
from renderer.device import release_memory

from ..observations import Observations
from .joint import refine_joint
from .layout import ACC, FitResult, Layout, SolverError, from_canonical, param_groups
from .noise import check_noise, default_delta, noise_floor, photo_noise_ratio
from .observability import anchors_at, determined, finalize, find_anchors, posterior_std, pull_push, tile_seeds
from .operators import pixel_operator
from .options import FitOptions
from .proposals import neighbour_proposals
from .sharing import material_targets, share_materials, shared_default, unmatched_texels
from .texel import (
    BILINEAR_LM_MIN,
    BILINEAR_LM_TOL,
    check_inputs,
    closed_form_init,
    data_cost,
    init_theta,
    per_texel_lm,
    separable,
)

__all__ = ["ANCHOR_RETRY_FACTOR", "MISFIT_RETRY", "FOOTPRINT_STEPS", "FOOTPRINT_FREE_STEPS",
           "FOOTPRINT_TEXTURE_PRIOR", "PYRAMID_MIN_SAMPLES", "PYRAMID_MIN_SIZE", "PYRAMID_STEPS", "pyramid_size",
           "upsample_maps", "solve_fast"]


#: When even the last factor of :data:`ANCHOR_LOOSENING` leaves fewer than :data:`ANCHOR_MIN_FRACTION` anchors, the
#: materials seeded from so few are a guess, and when the joint refinement they start then misses the photos by more
#: than ``MISFIT_RETRY`` × their noise (:func:`noise_floor`), the sharing and the refinement run again from the anchors
#: at ``ANCHOR_RETRY_FACTOR`` × the thresholds, and the fit with the lower data cost is kept (``info["share_retry"]``).
#: Measured (docs/log.md, "the layered fit 58 → 42 s"): the default-size layered scene with 3 000 e⁻
#: shot noise, 18 anchors of 46 264 at × 10, data cost 36 × its noise floor (worst view 35.6 dB) → 393 anchors
#: at × 30, 0.25 × the floor (62.5 dB); the noise-free one misses by 4.7 × (the floor of the 1 % noise model) and
#: keeps its fit.
ANCHOR_RETRY_FACTOR = 30.0
MISFIT_RETRY = 10.0


#: Joint LM steps of the final solve on the photos' pixel footprints (:func:`solve_fast` ``footprints``). It starts
#: from the pixel-centre solution, which is close wherever texels are larger than pixels, so a few steps converge;
#: each is stopped early when the cost drops by less than 1e-6 (relative).
FOOTPRINT_STEPS = 6
#: A per-texel value of a parameter no texel determines is wild above this many times the observed texels' median:
#: it is filled before the bilinear stages, which would mix it into its neighbours' predictions. Nielsen's specular
#: scale (up to SPECULAR_MAX ≈ 1e4, as it absorbs the lobe's normalisation) fitted from a lobe's tail reached 6 500
#: against a truth ≤ 1; 256² Nielsen Blinn-Phong photos then gave a χ² per residual of 2.3e5 (truth 0.19), 1.7e2 with
#: the values above 100 × the median filled and 13 above 10 × (docs/log.md, "Nielsen's fits")
WILD_FACTOR = 10.0
#: Untied footprint steps run first when the reflectance sharing anchors the materials: the sharing's materials come
#: from the pixel-centre fit, biased where pixels mix texels or highlights, so the material tie (``anchor_weight``)
#: would hold that bias. These steps run without it, the materials are re-estimated from the anchors' footprint fits
#: (median per material, :func:`material_targets`), and the :data:`FOOTPRINT_STEPS` tied steps follow. Measured on
#: the Mitsuba Lambert + GGX sphere (tests/fixtures/mitsuba): χ² per residual 1.29 → 0.55; RMSE on well-lit
#: highlight texels f0 0.016 → 0.011, roughness r 0.136 → 0.088 (12 tied steps without re-estimation: 0.52,
#: 0.015 / 0.102). Weighting the pixels by the noise model's 1/σ² instead reached χ² 0.31, below the truth's 0.37,
#: with worse roughness (0.134): the photos leave the faint broad lobes' roughness free.
FOOTPRINT_FREE_STEPS = 6
#: Weight (the ``sharing`` scale of :func:`refine_joint`) of the edge-preserving neighbour prior in the footprint
#: solve when no reflectance sharing runs (a Lambert model, or no material to share). Texels smaller than the pixels
#: that see them are left free by the photos (the operator mixes them), and without a prior they keep the noise of
#: the pixel-centre stages. Measured with ``shadecap reconstruct --model lambert`` (2-core CPU), RMSE of the albedo on
#: well-lit texels at weights 1e-3 / 3e-3 / 5e-3 / 1e-2 (docs/log.md, "the footprint prior's weight"):
#:
#: * Mitsuba torus, 12 × 256², 256² maps of stripes and a checker: 0.0106 / 0.0082 / 0.0076 / 0.0072 (χ² per
#:   residual 0.17 / 0.18 / 0.19 / 0.21); the same torus with a fractal-noise albedo (``torus-fractal-lambert``):
#:   0.0045 / 0.0038 / 0.0037 / 0.0037;
#: * ``shadecap synth`` (8 × 8 jittered rays) Lambert torus with 3 000 e⁻ shot noise: 0.028 / 0.016 / 0.012 / 0.011;
#:   blurred by a Gaussian PSF of σ = 0.7 px: 0.027 / 0.023 / 0.022 / 0.021; a Lambert sphere of 12 × 192²: 0.0117 /
#:   0.0101 / 0.0097 / 0.0095;
#: * where texels are larger than the pixels, which determine them, the prior only biases: the small Mitsuba torus
#:   (tests/fixtures/mitsuba, 64² maps), on its texels of ≥ 1 pixel 0.0012 / 0.0013 / 0.0014 / 0.0017 (χ² 0.20 /
#:   0.24 / 0.28 / 0.37); 4 views of 64 px on 32² maps blurred by the PSF (tests/capture/test_footprint.py), 0.054 /
#:   0.059 / 0.061 at 1e-3 / 3e-3 / 5e-3.
#:
#: 3e-3 takes most of the gain where the photos leave texels free and little of the bias where they determine them.
#: On photos blurred by a PSF the prior is what makes the deconvolution stable (the small scene: albedo 0.117
#: without it).
FOOTPRINT_TEXTURE_PRIOR = 3e-3


#: The per-texel stages (closed form, LM, posterior, sharing) need samples in a texel to say anything about it: on
#: maps finer than the photos resolve they see few or none (8 views of 256² on 1024² maps: 0.31 pixel centres per
#: texel their bilinear reads reach, 31 texels roughly determined, χ² per residual 132 after 568 s).
#: :func:`pyramid_size` then picks the largest map size, halving, at which the pixel centres give at least this many
#: samples per texel their reads reach; the whole fit runs there and its maps, upsampled (:func:`upsample_maps`),
#: start the footprint steps at full size (``refine_from`` of :func:`solve_fast`). At 1 the per-texel stages have a
#: sample per texel they touch; the benchmark scenes whose maps match their photos read 1.9–2.7 and are fitted as
#: before. Measured: docs/reconstruction.md, "Maps finer than the photos".
PYRAMID_MIN_SAMPLES = 1.0
#: ... but never below this size (a coarser level says too little about the layout of the materials).
PYRAMID_MIN_SIZE = 32
#: Footprint steps at full size from the coarse level's maps (``refine_from``; ``footprint_iterations`` overrides).
#: Measured (8 × 256² photos, GGX + Lambert, well-lit albedo / f0 / roughness, χ², full-size steps' time, 2-core
#: CPU): 1024² maps, 6 steps 0.0331 / 0.0989 / 0.1691, 7.3, 282 s; 3 steps 0.0332 / 0.1007 / 0.1715, 7.7, 123 s.
#: 512² maps: 6 steps 0.031 / 0.126 / 0.174; 3 steps 0.031 / 0.129 / 0.177; none 0.037 / 0.141 / 0.174 (χ² 36.7).
#: A model affine in all its parameters (Lambert) takes :data:`FOOTPRINT_STEPS`: its steps are sparse products only
#: (its Jacobian is constant), and the Mitsuba torus on 256² maps needs them — χ² 0.015, worst view 72 dB after 6
#: steps, 3.5 and 33 dB after 3, 5.9 against 5.6 s in all.
PYRAMID_STEPS = 3


def pyramid_size(obs: Observations, min_samples: float = PYRAMID_MIN_SAMPLES, min_size: int = PYRAMID_MIN_SIZE) -> int:
    """The map size at which :func:`solve_fast`'s per-texel stages see enough samples: the largest of the map size
    halved k ≥ 0 times (at least ``min_size``) where the observations' pixel centres give at least ``min_samples``
    samples per texel their reads reach (the bilinear taps' texels when the observations have them, else the
    nearest ones); the map size itself when it qualifies, or is not square, or cannot be halved."""
    H, W = obs.map_size
    if H != W or obs.n_samples == 0:
        return H
    taps = obs.bilinear_index if obs.bilinear_index is not None else obs.texel[:, None]
    i, j = taps // W, taps % W
    size = H
    while True:
        k = H // size
        per_texel = obs.n_samples / int(torch.unique((i // k) * (W // k) + j // k).numel())
        if per_texel >= min_samples or size // 2 < min_size or size % 2:
            return size
        size //= 2


def upsample_maps(maps: Mapping[str, Tensor], size: int) -> dict[str, Tensor]:
    """Maps ``name → [h, w, C]`` resampled to ``[size, size, C]`` bilinearly, texel centres aligned as the renderer
    reads them (a texel's centre at ((j + ½)/w, (i + ½)/h), clamped at the borders): values stay in each map's
    range."""
    out = {}
    for k, m in maps.items():
        x = m.permute(2, 0, 1)[None].to(torch.float64)
        out[k] = torch.nn.functional.interpolate(x, size=(size, size), mode="bilinear",
                                                 align_corners=False)[0].permute(1, 2, 0).to(m.dtype)
    return out


class _Plan(NamedTuple):
    """The options of :func:`solve_fast` whose defaults depend on the others, resolved."""

    iterations: int
    min_iterations: int
    lm_tol: float
    joint: bool
    share: bool
    grid: int


def _closed_form_is_exact(layout: Layout, sep: Mapping[str, bool], opts: FitOptions) -> bool:
    """Whether the closed-form solve (:func:`capture.fit.texel.linear_solve`) is already the minimiser of the
    per-texel LM's objective, whose iterations then cannot change the fit: one linear parameter (Lambert's albedo),
    solved channel by channel (or a scalar) — each texel's weighted least squares in one unknown, clipped into its
    range, which for one unknown is the bounded minimum (but for the 1e-4 of the range a clipped value is kept
    inside it, and the tiny ridge toward the default that decides texels with almost no data) — under the l2 loss
    and no neighbour prior. Measured on the 256² Mitsuba torus: the LM's five iterations (its floor on photos read
    bilinearly, :data:`BILINEAR_LM_MIN`) moved the cost by 7e-8 of itself in 0.36 s."""
    if not (layout.affine and len(layout.specs) == 1 and opts.loss == "l2" and not opts.smoothness):
        return False
    spec = layout.specs[0]
    return spec.channels == 1 or bool(sep.get(spec.name))


def _plan(opts: FitOptions) -> _Plan:
    """Resolve the per-texel LM's iterations and stopping rule, whether the joint refinement and the sharing run,
    and the closed-form grid."""
    iterations, min_iterations, lm_tol = opts.iterations, 0, opts.tol
    if iterations is None:
        iterations = 10 if opts.sampling == "bilinear" else 40
        if opts.sampling == "bilinear":
            min_iterations, lm_tol = BILINEAR_LM_MIN, max(opts.tol, BILINEAR_LM_TOL)
    joint = opts.sampling == "bilinear" and opts.joint_iterations != 0
    share = joint if opts.share is None else bool(opts.share)
    grid = opts.grid if opts.grid is not None else (16 if share else 32)
    return _Plan(iterations, min_iterations, lm_tol, joint, share, grid)


@dataclass(frozen=True)
class _Fit:
    """The problem of :func:`solve_fast` and its resolved options, shared by its stages."""

    model: Model
    obs: Observations
    layout: Layout
    groups: list
    opts: FitOptions
    delta: float
    noise: tuple[float, float]
    progress: Callable[[str, int, float], None] | None

    def refine(self, start: Tensor, iterations: int, cg_iterations: int, sharing: float, anchor_weight: float,
               footprints=None, anchor_target: Tensor | None = None) -> tuple[Tensor, dict]:
        """:func:`refine_joint` from θ ``start`` with the solver's loss, noise and prior parameters."""
        return refine_joint(self.model, self.obs, self.layout, start, self.groups, loss=self.opts.loss,
                            delta=self.delta, iterations=iterations, cg_iterations=cg_iterations, sharing=sharing,
                            progress=self.progress,
                            sharing_params=None if self.opts.sharing_albedo else shared_default(self.layout),
                            noise=self.noise, noise_adaptive=("albedo",), anchor_weight=anchor_weight,
                            footprints=footprints, anchor_target=anchor_target)

    def footprint_steps(self, start: Tensor, n: int, share: bool, anchor_weight: float, footprints,
                        target: Tensor | None = None) -> tuple[Tensor, dict]:
        """``n`` joint LM steps on the pixel ``footprints`` from θ ``start``: the solver's PCG iterations, the
        sharing's prior weight when materials are shared (else :data:`FOOTPRINT_TEXTURE_PRIOR`), the material tie
        ``anchor_weight`` to ``target`` (None: ``start``'s values)."""
        opts = self.opts
        return self.refine(start, n, opts.cg_iterations if opts.cg_iterations is not None else 30,
                           opts.sharing if share else FOOTPRINT_TEXTURE_PRIOR, anchor_weight, footprints=footprints,
                           anchor_target=target)


def _footprint_info(finfo: dict) -> dict:
    """The footprint steps' :func:`refine_joint` info under the report's ``footprint_`` names."""
    return {f"footprint_{k.removeprefix('joint_')}": v for k, v in finfo.items()}


@dataclass
class _Sharing:
    """The reflectance sharing's state in :func:`solve_fast`: the per-texel fit it started from, the posterior std
    that chose its anchors, whether they were scarce, its info and the (labels, anchors) of the materials kept."""

    theta_texel: Tensor
    names: list[str]
    std: dict
    observed_n: Tensor
    scarce: bool
    sinfo: dict
    material_of: tuple


def _share(fit: _Fit, theta: Tensor, std: dict, observed_n: Tensor, info: dict) -> tuple[Tensor, _Sharing]:
    """The reflectance sharing (:func:`share_materials`) from the per-texel fit θ, with its anchors; records it in
    ``info``."""
    opts, layout = fit.opts, fit.layout
    shared_names = shared_default(layout)
    anchors, factor, scarce = find_anchors(layout, std, observed_n, shared_names, opts.observable_std)
    # tiles whose texels agree on a material none of them determines alone seed the clustering too, at the anchors'
    # thresholds (a rough dielectric under a flash had 2 anchors in 3 469 texels, and no material of its own)
    seeds = tile_seeds(layout, layout.canonical(theta), std, observed_n, anchors, shared_names, fit.obs.map_size,
                       opts.observable_std, factor=factor)
    theta_texel = theta
    theta, sinfo = share_materials(fit.model, fit.obs, layout, theta, anchors, candidates=opts.candidates,
                                   noise=fit.noise, pool_block=opts.pooled, seeds=seeds)
    info["share_seeds"] = int(seeds.shape[0])
    material_of = (sinfo.get("labels"), anchors)
    info.update(share_s=sinfo["share_s"], materials=sinfo["materials"], shared=sinfo["shared"],
                share_anchors=int(anchors.sum()), share_anchor_factor=factor, share_pruned=sinfo.get("pruned", 0),
                pooled_tiles=sinfo.get("pooled_tiles", 0), photo_noise_ratio=sinfo.get("photo_noise_ratio"))
    return theta, _Sharing(theta_texel, shared_names, std, observed_n, scarce, sinfo, material_of)


def _fill_undetermined(layout: Layout, theta: Tensor, canon: Tensor, good: dict, observed: Tensor, H: int, W: int,
                       partial: bool = True) -> None:
    """Replace in place per-texel parameters of θ by pull-push fills: with ``partial``, those the photos do not
    determine (``good``) of a parameter some texels determine, by fills of the determined ones; for a parameter no
    texel determines, the wild values — above :data:`WILD_FACTOR` × the observed texels' median (``observed [T]``
    bool), per channel — by fills of the others."""
    T = H * W
    # per-texel parameters the photos do not determine vary wildly from texel to texel; under
    # bilinear sampling they would mix into the neighbours' predictions, so they are replaced
    # by pull-push fills of the observable ones before the joint refinement
    for s_, o in zip(layout.specs, layout.offsets, strict=True):
        sl = slice(o, o + s_.channels)
        ok = good[s_.name]
        if bool(ok.all()) or (bool(ok.any()) and not partial) or not bool(observed.any()):
            continue
        if not bool(ok.any()):
            x = canon[:, sl]
            tame = (x <= WILD_FACTOR * x[observed].median(0).values.clamp_min(1e-12)).all(-1)
            if bool(tame[observed].all()) or not bool((tame & observed).any()):
                continue
            ok = tame & observed
        filled_c = pull_push(canon[:, sl].reshape(H, W, -1), ok.reshape(H, W)).reshape(T, -1)
        theta[:, sl] = from_canonical(s_, filled_c)


def _fill_footprint_only(theta: Tensor, fitted: Tensor, read: Tensor, H: int, W: int) -> int:
    """Give the texels that the pixel footprints read but the pixel-centre stages never fitted (``read & ~fitted``,
    ``[T]`` bool each) the values of the nearest fitted texel on the map, in place: they start the footprint steps
    at a neighbour's material instead of the parameters' defaults. Returns how many were given."""
    import cv2

    only = read & ~fitted
    n = int(only.sum())
    if n == 0 or not bool(fitted.any()):
        return 0
    # the nearest fitted texel of every texel: OpenCV's distance transform labels each texel with its nearest zero
    unknown = (~fitted).reshape(H, W).to(torch.uint8).cpu().numpy()
    _, labels = cv2.distanceTransformWithLabels(unknown, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    labels = torch.from_numpy(labels.astype("int64")).reshape(-1).to(theta.device)
    source = torch.zeros(int(labels.max()) + 1, dtype=torch.long, device=theta.device)
    source[labels[fitted]] = torch.nonzero(fitted).reshape(-1)
    idx = torch.nonzero(only).reshape(-1)
    theta[idx] = theta[source[labels[idx]]]
    return n


def _joint_stage(fit: _Fit, theta: Tensor, share: bool, sharing: _Sharing | None, info: dict) -> tuple[Tensor, dict]:
    """The joint refinement on the pixel centres (:func:`refine_joint`), from the sharing's proposal when ``share``
    (then with its fallback and, where the anchors were scarce, its retry, recorded in ``info``)."""
    opts = fit.opts
    # more steps are safe once the sharing's proposal anchors the material parameters (anchor_weight)
    steps = opts.joint_iterations if opts.joint_iterations is not None else (6 if share else 3)
    cg_steps = opts.cg_iterations if opts.cg_iterations is not None else (30 if share else 25)

    def joint_from(start):
        return fit.refine(start, steps, cg_steps, opts.sharing if share else 0.0, opts.anchor_weight if share else 0.0)

    if not share:
        return joint_from(theta)
    theta, jinfo, fallback_report = _shared_joint(fit, joint_from, theta, sharing.sinfo, sharing.theta_texel)
    floor = (noise_floor(fit.obs, fit.noise, info.get("photo_noise_ratio"), opts.loss, fit.delta) if sharing.scarce
             else math.inf)
    if jinfo["joint_data_cost"] > MISFIT_RETRY * floor:
        theta, jinfo, fallback_report = _reseed(fit, joint_from, sharing, floor, (theta, jinfo, fallback_report),
                                                info)
    if fallback_report is not None:
        info["sharing_fallback"] = fallback_report
    return theta, jinfo


def _shared_joint(fit: _Fit, joint_from: Callable[[Tensor], tuple[Tensor, dict]], shared_start: Tensor, sinfo: dict,
                  theta_texel: Tensor) -> tuple[Tensor, dict, dict | None]:
    """The joint refinement from the sharing's proposal ``shared_start``, and from the texels' own fits where the
    photos reject their material when the proposal's fit misses the photos more than the per-texel fit did:
    ``(theta, jinfo, fallback report or None)``."""
    opts = fit.opts
    theta, jinfo = joint_from(shared_start)
    # the sharing is a proposal. When the refinement it seeds fits the photos worse than the per-texel fit
    # did, the materials miss part of the object (a layered scene whose metals gave no anchor: every metal
    # texel took a dielectric, worst view 27 dB): the texels whose own samples reject their material
    # keep their own fit, the refinement runs again, and the lower data cost wins
    texel_cost = data_cost(fit.model, fit.layout, fit.obs, theta_texel, sampling=opts.sampling, loss=opts.loss,
                           delta=fit.delta)
    if jinfo["joint_data_cost"] > texel_cost:
        own = unmatched_texels(fit.model, fit.obs, fit.layout, theta_texel, sinfo, noise=fit.noise)
        retry, rinfo = joint_from(torch.where(own[:, None], theta_texel, shared_start))
        fallback = rinfo["joint_data_cost"] < jinfo["joint_data_cost"]
        report = {"per_texel_data_cost": texel_cost, "shared_data_cost": jinfo["joint_data_cost"],
                  "own_fit_texels": int(own.sum()), "fallback_data_cost": rinfo["joint_data_cost"],
                  "kept": "fallback" if fallback else "shared"}
        seconds = jinfo["joint_s"] + rinfo["joint_s"]
        if fallback:
            theta, jinfo = retry, rinfo
        jinfo["joint_s"] = seconds
        return theta, jinfo, report
    return theta, jinfo, None


def _reseed(fit: _Fit, joint_from: Callable[[Tensor], tuple[Tensor, dict]], sharing: _Sharing, floor: float,
            first: tuple[Tensor, dict, dict | None], info: dict) -> tuple[Tensor, dict, dict | None]:
    """The sharing and joint refinement again from the anchors at :data:`ANCHOR_RETRY_FACTOR` × the thresholds
    (:data:`MISFIT_RETRY`); the ``first`` result ``(theta, jinfo, fallback report)`` or the retry's, whichever has
    the lower data cost. Records ``share_retry`` in ``info`` (and the retry's materials when it is kept)."""
    opts, layout = fit.opts, fit.layout
    theta, jinfo, fallback_report = first
    anchors2 = anchors_at(layout, sharing.std, sharing.observed_n, sharing.names, opts.observable_std,
                          ANCHOR_RETRY_FACTOR)
    start2, sinfo2 = share_materials(fit.model, fit.obs, layout, sharing.theta_texel, anchors2,
                                     candidates=opts.candidates, noise=fit.noise, pool_block=opts.pooled)
    retry = {"noise_floor": floor, "data_cost": jinfo["joint_data_cost"], "anchors": int(anchors2.sum()),
             "factor": ANCHOR_RETRY_FACTOR, "share_s": sinfo2["share_s"], "kept": "first"}
    if sinfo2["materials"]:
        theta2, jinfo2, fallback2 = _shared_joint(fit, joint_from, start2, sinfo2, sharing.theta_texel)
        retry.update(retry_data_cost=jinfo2["joint_data_cost"], joint_s=jinfo2["joint_s"])
        if jinfo2["joint_data_cost"] < jinfo["joint_data_cost"]:
            retry["kept"] = "retry"
            theta, jinfo, fallback_report = theta2, jinfo2, fallback2
            sharing.material_of = (sinfo2.get("labels"), anchors2)
            info.update(materials=sinfo2["materials"], share_anchors=int(anchors2.sum()),
                        share_anchor_factor=ANCHOR_RETRY_FACTOR, share_pruned=sinfo2.get("pruned", 0),
                        pooled_tiles=sinfo2.get("pooled_tiles", 0))
    info["share_retry"] = retry
    return theta, jinfo, fallback_report


def _footprint_stage(fit: _Fit, theta: Tensor, footprints, share: bool,
               sharing: _Sharing | None) -> tuple[Tensor, dict | None]:
    """The joint LM steps on the photos' pixel footprints (``footprints``: a :class:`PixelOperator`):
    ``(theta, their info)``, or ``(theta, None)`` when there are none to take."""
    opts = fit.opts
    steps = FOOTPRINT_STEPS if opts.footprint_iterations is None else int(opts.footprint_iterations)
    if not steps > 0:
        return theta, None

    def footprint_steps(start, n, weight, target=None):
        return fit.footprint_steps(start, n, share, weight, footprints, target)

    if share and opts.anchor_weight > 0 and sharing.material_of[0] is not None and FOOTPRINT_FREE_STEPS > 0:
        # the sharing's materials were estimated on the pixel-centre residuals, biased wherever a pixel
        # mixes texels or a highlight; the first steps run untied, the materials are re-estimated from
        # the anchors' footprint fits, and the tie resumes to those
        theta, finfo_free = footprint_steps(theta, FOOTPRINT_FREE_STEPS, 0.0)
        pinfo = None
        if opts.proposals:
            theta, pinfo = neighbour_proposals(fit.model, fit.layout, theta, footprints, fit.obs.map_size,
                                               loss=opts.loss, delta=fit.delta, noise=fit.noise,
                                               noise_ratio=photo_noise_ratio(fit.obs, fit.noise))
        target = material_targets(fit.layout, fit.layout.canonical(theta), *sharing.material_of)
        theta, finfo = footprint_steps(theta, steps, opts.anchor_weight, target)
        finfo["joint_s"] += finfo_free["joint_s"]
        finfo["joint_history"] = finfo_free["joint_history"] + finfo["joint_history"][1:]
        finfo["joint_accepted"] = finfo_free["joint_accepted"] + finfo["joint_accepted"]
        if pinfo is not None:
            finfo["joint_proposals"] = pinfo
    else:
        theta, finfo = footprint_steps(theta, steps, opts.anchor_weight if share else 0.0)
    return theta, finfo


def _refine_from(fit: _Fit, maps: Mapping[str, Tensor], footprints, t0: float, steps: int | None) -> FitResult:
    """:func:`solve_fast` with ``refine_from``: ``steps`` footprint steps from ``maps`` (None: the default), then the
    finalisation."""
    model, layout, obs, opts = fit.model, fit.layout, fit.obs, fit.opts
    missing = [n for n in model.param_names if n not in maps]
    extra = [n for n in maps if n not in model.param_names]
    if missing or extra:
        raise SolverError(f"refine_from must give a map of every fitted parameter of '{model.name}' "
                          f"({list(model.param_names)}) and no other; missing {missing}, not fitted {extra}")
    if footprints is None:
        raise SolverError("refine_from runs only the footprint steps: give the photos' pixel footprints "
                          "(footprints=...)")
    theta = init_theta(model, layout, obs, maps).to(ACC)
    footprints = pixel_operator(footprints, obs.n_texels, opts.jacobian, opts.memory_budget_bytes)
    share = bool(shared_default(layout)) and opts.share is not False
    if steps is None:
        steps = (FOOTPRINT_STEPS if layout.affine else PYRAMID_STEPS) \
            if opts.footprint_iterations is None else int(opts.footprint_iterations)
    info = {"options": opts.to_dict(), "refined_from": "maps"}
    history = []
    if steps > 0:
        theta, finfo = fit.footprint_steps(theta, steps, share, opts.anchor_weight if share else 0.0, footprints)
        footprints.release()
        info.update(_footprint_info(finfo))
        history = list(finfo["joint_history"])
    return finalize(model, layout, obs, theta, fit.groups, loss=opts.loss, delta=fit.delta,
                    observable_std=opts.observable_std, noise=fit.noise, history=history, iterations=0, t0=t0,
                    solver="fast", info=info, sampling=opts.sampling, keep_unobservable=True, footprints=footprints)


def solve_fast(model: Model, obs: Observations, options: FitOptions | None = None, *,
               init: Mapping[str, Tensor] | None = None, footprints=None,
               refine_from: Mapping[str, Tensor] | None = None, refine_steps: int | None = None,
               progress: Callable[[str, int, float], None] | None = None, **overrides) -> FitResult:
    """Per-texel Levenberg-Marquardt with closed-form initialisation of the linear parameters.

    Objective: ``Σ_s weight_s Σ_c ρ(y_sc − L_sc)`` with nearest-texel sampling (each sample reads
    the texel containing its UV), so texels are independent and every texel has its own damping
    λ_t and step acceptance. One iteration costs the Jacobian (:func:`jacobian`: the model's closed form, or one
    evaluation with three backward passes) plus one trial evaluation.

    Args:
        model: the material model; obs: the observations.
        options: the solver's options (:class:`capture.fit.options.FitOptions`; None = the defaults).
        **overrides: options by name (``loss="huber"``), replacing those of ``options``; an unknown name is a
            :class:`SolverError` that lists the valid ones.
        init: optional starting maps ``name → [H, W, C]`` (skips the grid for the nonlinear ones
            only if grid ≤ 1).
        footprints: :class:`capture.footprint.PixelFootprints` of the same photos: after the stages above (which
            treat each pixel as one ray through its centre and give the starting maps), ``footprint_iterations``
            more joint LM steps fit the photos' *pixels* as area averages of their sub-pixel samples
            (:func:`refine_joint` with ``footprints``), with the same prior; the posterior std and the
            observability are then judged through the footprint operator (:func:`posterior_std`). None = the
            pixel-centre model only (photos the fit's own pixel-centre renderer made).
        refine_from: maps ``name → [H, W, C]`` of every fitted parameter, e.g. a coarser fit's upsampled
            (:func:`pyramid_size`, :func:`upsample_maps`): the per-texel stages, the sharing and the pixel-centre
            refinement are skipped, and only the footprint steps run from these maps (``footprints`` required),
            with the neighbour prior, and the material parameters tied to these maps by ``anchor_weight`` where
            the model has any; their values are kept where the photos leave a texel undetermined.
        refine_steps: footprint steps from ``refine_from`` (None: ``footprint_iterations`` when given, else
            :data:`PYRAMID_STEPS`, or :data:`FOOTPRINT_STEPS` for a model affine in its parameters); 0 takes
            the maps as they are and only judges them (posterior std, observability) through ``footprints``.
        progress: callback ``(stage, iteration, cost)``.

    Returns:
        :class:`FitResult` (``info`` holds grid/LM times and the accepted-step fractions).
    """
    t0 = time.perf_counter()
    opts = FitOptions.of(options, **overrides)
    check_inputs(model, obs, opts.loss)
    plan = _plan(opts)
    delta = default_delta(obs, opts.loss, opts.delta)
    layout = Layout.of(model)
    T, H, W = obs.n_texels, *obs.map_size
    theta = init_theta(model, layout, obs, init).to(ACC)
    groups = param_groups(layout)
    t_grid = time.perf_counter()
    lin_specs = [s for s in layout.specs if s.linear]
    sep = {s.name: (s.channels == 3 and separable(model, s, obs.dtype)) for s in lin_specs}
    if opts.sampling == "bilinear" and obs.bilinear_index is None:
        raise SolverError("sampling='bilinear' needs observations built with bilinear=True (observe_views)")
    fit = _Fit(model, obs, layout, groups, opts, delta, check_noise(opts.noise), progress)
    if refine_steps is not None:
        if not isinstance(refine_steps, int) or isinstance(refine_steps, bool) or refine_steps < 0:
            raise SolverError(f"refine_steps must be an integer ≥ 0, got {refine_steps!r}")
        if refine_from is None:
            raise SolverError("refine_steps counts the footprint steps from refine_from: give the maps they start "
                              "from (refine_from=...)")
    if refine_from is not None:
        return _refine_from(fit, refine_from, footprints, t0, refine_steps)
    theta, info = closed_form_init(model, layout, obs, theta, plan.grid, opts.loss, delta, sep, opts.refine,
                                    fixed=tuple(init or ()))
    info["grid_s"] = time.perf_counter() - t_grid
    info["options"] = opts.to_dict()
    iterations = 0 if opts.iterations is None and _closed_form_is_exact(layout, sep, opts) else plan.iterations
    theta, history, lm_info = per_texel_lm(model, obs, layout, theta, groups, loss=opts.loss, delta=delta,
                                           iterations=iterations, schedule=opts.schedule,
                                           smoothness=opts.smoothness, reproject=opts.reproject, sep=sep,
                                           lm_tol=plan.lm_tol, min_iterations=plan.min_iterations, progress=progress)
    info.update(lm_info)
    it = lm_info["lm_iterations"]
    share, joint, sharing = plan.share, plan.joint, None
    if share or (joint and opts.fill_before_joint):
        canon = layout.canonical(theta)
        std, observed_n, _ = posterior_std(model, layout, obs, canon, groups, loss=opts.loss, delta=delta,
                                           noise=fit.noise)
        good = determined(layout, std, observed_n, opts.observable_std)
    if share:
        theta, sharing = _share(fit, theta, std, observed_n, info)
        if progress is not None:
            progress("share", it, history[-1])
        # nothing to share from (no texel determined the shared parameters, or the model has none):
        # fall back to the fill, as without sharing
        share = bool(sharing.sinfo["materials"])
    # with pixel footprints and nothing shared, the footprint solve is the joint solve over all texels: the
    # pixel-centre one (and its fill) before it only moves the start (Mitsuba torus, 12 × 256², Lambert: well-lit
    # albedo 0.0110 with it, 0.0107 without, χ² per residual 0.19 both)
    joint = joint and (share or footprints is None or opts.joint_iterations is not None)
    if plan.joint and opts.fill_before_joint and not share:     # (before the footprint steps too: wild values only)
        _fill_undetermined(layout, theta, canon, good, observed_n, H, W, partial=joint)
    if joint:
        theta, jinfo = _joint_stage(fit, theta, share, sharing, info)
        info.update(jinfo)
        history.append(jinfo["joint_history"][-1])
    if footprints is not None:
        release_memory()                                # (what the pixel-centre stages freed, before the largest)
        footprints = pixel_operator(footprints, T, opts.jacobian, opts.memory_budget_bytes)  # once, for all stages
        # texels no pixel centre falls in were never fitted by the per-texel stages (on the 256² Mitsuba sphere
        # 12 202 of them, mostly near the poles, the farthest still at the parameters' defaults) but the footprints
        # read them
        info["footprint_filled"] = _fill_footprint_only(theta, obs.samples_per_texel().reshape(-1) > 0,
                                                        footprints.observed(), H, W)
        theta, finfo = _footprint_stage(fit, theta, footprints, share, sharing)
        footprints.release()                            # (the posterior needs no matrices)
        if finfo is not None:
            info.update(_footprint_info(finfo))
            history.append(finfo["joint_history"][-1])
    return finalize(model, layout, obs, theta, groups, loss=opts.loss, delta=delta,
                     observable_std=opts.observable_std, noise=fit.noise, history=history, iterations=it, t0=t0,
                     solver="fast", info=info, sampling=opts.sampling, keep_unobservable=share, footprints=footprints)
