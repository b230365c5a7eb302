"""Errors of recovered maps against ground truth, and of re-rendered views against photos.

* :func:`map_errors` — per map RMSE and max |error| over a texel mask (normally the observed
  texels, optionally also excluding texels where the parameter was unobservable), overall and
  per material region of a region-id map.
* :func:`observability_errors` — the same on all observed texels *and* on the texels where each
  map is observable, with the observable fraction and the share of the error in the texels flagged
  unobservable (what the report's error table shows).
* :func:`determined_at_truth` — the texels where the photos determine each map *at the true maps*: the
  estimate-independent counterpart of the fit's observability (judged at its estimate), for synthetic scenes.
* :func:`image_metrics` — PSNR and SSIM (``kornia.metrics``) of a re-rendered view against its
  photo, over the image (background is 0 in both), with the peak taken as the photo's maximum.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

__all__ = ["map_errors", "observability_errors", "determined_at_truth", "image_metrics", "MetricsError"]


class MetricsError(ValueError):
    """Maps or images that cannot be compared (missing names, shape mismatch, empty mask)."""


def _stats(d: Tensor) -> dict:
    """RMSE and max over the rows of ``d [K, C]`` (all channels pooled)."""
    if d.numel() == 0:
        return {"rmse": float("nan"), "max": float("nan"), "texels": 0}
    return {"rmse": float(d.square().mean().sqrt()), "max": float(d.abs().max()), "texels": int(d.shape[0])}


def map_errors(maps: Mapping[str, Tensor], gt: Mapping[str, Tensor], mask: Tensor,
               regions: Tensor | None = None, region_names: Mapping[int, str] | None = None,
               exclude: Mapping[str, Tensor] | None = None) -> dict:
    """Per-map RMSE / max |error| of ``maps`` against ``gt`` over ``mask``.

    Args:
        maps, gt: name → ``[H, W, C]`` (the names of ``maps`` present in ``gt`` are compared; a gt
            map of another size is resized with nearest sampling — flagged in the result).
        mask: ``[H, W]`` bool, texels to include (e.g. the observed ones).
        regions: optional ``[H, W]`` int region ids (same size as the maps); region_names: id → name.
        exclude: optional name → ``[H, W]`` bool texels to leave out for that map (e.g. unobservable).

    Returns:
        ``{name: {"rmse", "max", "texels", "regions": {region name: {...}}}}``.
    """
    if mask.dim() != 2:
        raise MetricsError(f"mask must be [H, W] bool, got {tuple(mask.shape)}")
    out = {}
    for name, m in maps.items():
        if name not in gt:
            continue
        g = gt[name].to(m.dtype)
        if g.shape[:2] != m.shape[:2]:
            g = torch.nn.functional.interpolate(g.permute(2, 0, 1)[None], size=m.shape[:2], mode="nearest")[0]
            g = g.permute(1, 2, 0)
        if g.shape[-1] != m.shape[-1]:
            g = g.expand(*g.shape[:2], m.shape[-1]) if g.shape[-1] == 1 else g.mean(-1, keepdim=True)
        sel = mask.clone()
        if exclude is not None and name in exclude:
            sel &= ~exclude[name]
        d = (m - g)
        row = _stats(d[sel])
        if regions is not None:
            row["regions"] = {}
            for rid in torch.unique(regions[sel]).tolist() if bool(sel.any()) else []:
                r = sel & (regions == rid)
                key = (region_names or {}).get(int(rid), str(int(rid)))
                row["regions"][key] = _stats(d[r])
        out[name] = row
    return out


def observability_errors(maps: Mapping[str, Tensor], gt: Mapping[str, Tensor], observed: Tensor,
                         unobservable: Mapping[str, Tensor], regions: Tensor | None = None,
                         region_names: Mapping[int, str] | None = None,
                         determined: Mapping[str, Tensor] | None = None) -> dict:
    """Per map: errors on all observed texels, on the observed texels where the map is observable,
    the observable fraction of the observed texels, and the share of the squared error on all observed texels
    that lies in the texels flagged unobservable (``flagged_share``, in [0, 1]; 0 when there is no error).
    With ``determined`` (name → ``[H, W]`` bool, :func:`determined_at_truth`) also the errors on the observed
    texels the photos determine at the true maps (``"determined"``) and their fraction (``determined_fraction``).

    ``flagged_share`` says whether the tool knew where it was wrong: near 1, the error is where the report
    warned that the photos cannot tell; well below 1, texels called determined are wrong (e.g. a second basin
    judged at the estimate). Default scene (docs/reconstruction.md, session 9): 0.998 / 1.000 / 1.000 for
    albedo / f0 / roughness.

    Args:
        maps: fitted maps name → ``[H, W, C]`` (the solver's raw values, not the filled ones);
        gt: true maps; observed: ``[H, W]`` bool; unobservable: name → ``[H, W]`` bool.
        regions, region_names: optional per-region breakdown of both tables, as in :func:`map_errors`.

    Returns:
        ``{name: {"observed": {rmse, max, texels}, "observable": {...}, "observable_fraction": f,
        "flagged_share": s}}``, plus ``"determined"`` and ``"determined_fraction"`` for the names in
        ``determined``.
    """
    if observed.dim() != 2:
        raise MetricsError(f"observed must be [H, W] bool, got {tuple(observed.shape)}")
    for k, m in (determined or {}).items():
        if m.shape != observed.shape or m.dtype != torch.bool:
            raise MetricsError(f"determined['{k}'] must be an [H, W] bool mask like observed "
                               f"{tuple(observed.shape)}, got {m.dtype} {tuple(m.shape)}")
    all_ = map_errors(maps, gt, observed, regions, region_names)
    obs_ = map_errors(maps, gt, observed, regions, region_names, exclude=unobservable)
    n = max(int(observed.sum()), 1)

    def squared(row: dict) -> float:            # the summed squared error behind an RMSE over `texels` rows
        return row["rmse"] ** 2 * row["texels"] if row["texels"] else 0.0

    out = {}
    for k in all_:
        total = squared(all_[k])
        out[k] = {"observed": all_[k], "observable": obs_[k],
                  "observable_fraction": float((observed & ~unobservable[k]).sum()) / n if k in unobservable else 1.0,
                  "flagged_share": min(max(1.0 - squared(obs_[k]) / total, 0.0), 1.0) if total > 0 else 0.0}
        if determined is not None and k in determined:
            out[k]["determined"] = map_errors({k: maps[k]}, gt, observed & determined[k], regions, region_names)[k]
            out[k]["determined_fraction"] = float((observed & determined[k]).sum()) / n
    return out


def determined_at_truth(model, obs, gt: Mapping[str, Tensor], *, sampling: str = "nearest",
                        noise=None, observable_std=None) -> dict[str, Tensor]:
    """Per parameter of ``model``: ``[H, W]`` bool, the observed texels whose value the photos determine
    *at the true maps* ``gt`` — the marginal posterior std of :func:`capture.solvers.posterior_std` (same
    noise model, sampling and thresholds as a fit's observability test) evaluated at the truth, below the
    parameter's threshold.

    A fit judges observability at its own estimate, so a texel stuck in a wrong basin can be called
    determined, and the error "where observable" is measured on a set the estimate chose. This mask does not
    depend on any estimate: the error over it says how well the solver recovers what the photos *can* tell,
    and a large error there is a texel the photos decide that the solver got wrong. Only for synthetic scenes
    whose ``model`` rendered the photos (its true maps known).

    Args:
        model: the model that rendered the photos (every parameter's true map in ``gt``).
        obs: the observations (:class:`capture.observations.Observations`) of the fit.
        gt: name → true map ``[H, W, C]`` in canonical units, ``(H, W) = obs.map_size``.
        sampling: "nearest" or "bilinear", as the fit's; noise, observable_std: as the fit's (None = defaults).
    """
    from .solvers import ACC, NOISE, Layout, _groups, determined, posterior_std

    H, W = obs.map_size
    layout = Layout.of(model)
    missing = [s.name for s in layout.specs if s.name not in gt]
    if missing:
        raise MetricsError(f"determined_at_truth: the true maps lack {missing} of model '{model.name}'; pass the "
                           f"maps of the model that rendered the photos")
    bad = [s.name for s in layout.specs if tuple(gt[s.name].shape) != (H, W, s.channels)]
    if bad:
        raise MetricsError(f"determined_at_truth: true maps {bad} are not [{H}, {W}, C] like the observations' "
                           f"map size; resample them to the fit's texture size")
    if sampling not in ("nearest", "bilinear"):
        raise MetricsError(f"determined_at_truth: sampling must be 'nearest' or 'bilinear', got {sampling!r}")
    T = H * W
    canon = torch.cat([gt[s.name].reshape(T, s.channels).to(obs.device, ACC) for s in layout.specs], -1)
    std, observed, _ = posterior_std(model, layout, obs, canon, _groups(layout), noise=NOISE if noise is None
                                     else noise, sampling=sampling)
    return {k: m.reshape(H, W) for k, m in determined(layout, std, observed, observable_std).items()}


def image_metrics(rendered: Tensor, photo: Tensor, mask: Tensor | None = None) -> dict:
    """PSNR (dB) and SSIM of a re-rendered linear image against the photo, both ``[H, W, 3]``.

    Non-finite photo pixels and pixels outside ``mask`` are set to 0 in both. PSNR uses the photo's
    maximum as the peak (linear radiance has no fixed white); SSIM (kornia, 11×11 Gaussian window)
    is computed on both images divided by that peak.
    """
    import kornia

    if rendered.shape != photo.shape or rendered.dim() != 3:
        raise MetricsError(f"rendered and photo must both be [H, W, 3], got {tuple(rendered.shape)} and "
                           f"{tuple(photo.shape)}")
    ok = torch.isfinite(photo).all(-1)
    if mask is not None:
        ok &= mask
    a = torch.where(ok[..., None], rendered, torch.zeros_like(rendered)).float()
    b = torch.where(ok[..., None], photo, torch.zeros_like(photo)).float()
    peak = float(b.max().clamp_min(1e-12))
    a, b = a / peak, b / peak
    mse = float((a - b).square()[ok].mean()) if bool(ok.any()) else float("nan")
    psnr = float(10 * torch.log10(torch.tensor(1.0 / max(mse, 1e-20)))) if mse == mse else float("nan")
    A, B = a.permute(2, 0, 1)[None].clamp(0, 1), b.permute(2, 0, 1)[None].clamp(0, 1)
    ssim = float(kornia.metrics.ssim(A, B, 11).mean())
    return {"psnr": psnr, "ssim": ssim, "rmse_linear": (mse ** 0.5) * peak if mse == mse else float("nan")}


#: Cosine above which a texel counts as well lit and well seen (:func:`well_lit_texels`): n·v > 0.3 and n·l > 0.3
#: (within 72.5° of the normal) for some (view, light) pair — the texels whose photos are not grazing.
WELL_LIT_COS = 0.3


def well_lit_texels(obs) -> Tensor:
    """``[H, W]`` bool: texels some pixel-centre sample sees with n·v > :data:`WELL_LIT_COS` under a light with
    n·l > :data:`WELL_LIT_COS` (``obs``: :class:`capture.observations.Observations`)."""
    H, W = obs.map_size
    ok = (obs.angles.nl.reshape(-1) > WELL_LIT_COS) & (obs.angles.nv.reshape(-1) > WELL_LIT_COS)
    out = torch.zeros(H * W, dtype=torch.bool, device=obs.device)
    out[obs.texel[obs.pair_sample[ok]]] = True
    return out.reshape(H, W)


def pixel_sized_texels(fp) -> Tensor:
    """``[H, W]`` bool: texels that cover at least one pixel in some view — read by a sample of a pixel whose texel
    footprint is at most one texel per pixel step (``fp``: :class:`capture.footprint.PixelFootprints`)."""
    H, W = fp.map_size
    small = fp.footprint_texels[fp.group] <= 1.0
    out = torch.zeros(H * W, dtype=torch.bool, device=fp.device)
    out[fp.samples.texel[small]] = True
    return out.reshape(H, W)


def highlight_texels(obs, roughness: Tensor, min_angle_deg: float = 1.0) -> Tensor:
    """``[H, W]`` bool: texels seen inside a highlight — some (sample, light) pair with the half vector within the
    half-maximum angle of the GGX lobe of the texel's roughness ``[H, W, 1]`` (at least ``min_angle_deg``) of the
    normal, the criterion of :func:`capture.synthetic.highlight_coverage`."""
    from materials.roughness import half_max_angle

    H, W = obs.map_size
    theta = half_max_angle(roughness.reshape(-1).double()).clamp_min(math.radians(min_angle_deg))
    tex = obs.texel[obs.pair_sample]
    ok = obs.angles.nh.reshape(-1).double() >= torch.cos(theta.to(obs.device))[tex]
    out = torch.zeros(H * W, dtype=torch.bool, device=obs.device)
    out[tex[ok]] = True
    return out.reshape(H, W)
