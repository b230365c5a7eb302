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
* :func:`coverage_advice` — which directions the photos miss (texels never seen, never lit, never shown a
  highlight at useful angles), where those texels' normals point, and what views or lights to add;
  :func:`texel_normals` gives it the surface's normal per texel from the mesh.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

__all__ = ["map_errors", "observability_errors", "determined_at_truth", "image_metrics", "MetricsError",
           "texel_normals", "coverage_advice", "HIGHLIGHT_DEG", "ADVICE_MIN_FRACTION", "well_lit_texels",
           "pixel_sized_texels", "highlight_texels", "visible_lobe_texels", "VISIBLE_LOBE_RATIO",
           "errors_by_texel_set", "texel_sets"]


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
    judged at the estimate). Default scene (pixel-centre fit, docs/log.md "where the rest of the error is"):
    0.998 / 1.000 / 1.000 for albedo / f0 / roughness.

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
    *at the true maps* ``gt`` — the marginal posterior std of :func:`capture.fit.observability.posterior_std` (same
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
    from .fit.layout import ACC, Layout, param_groups
    from .fit.noise import NOISE
    from .fit.observability import determined, posterior_std

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
    std, observed, _ = posterior_std(model, layout, obs, canon, param_groups(layout), noise=NOISE if noise is None
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


#: Smallest peak ratio of a GGX lobe to the diffuse term under which a highlight counts as visible
#: (:func:`visible_lobe_texels`): a lobe at a quarter of the diffuse radiance is 25 × the 1 % photo noise the
#: solver assumes. The broad, faint lobe of a rough dielectric (f0 0.04, r 0.75 over albedo 0.54: ratio 0.06)
#: is below it: its roughness hardly changes a pixel (docs/image-formation.md, "What to expect").
VISIBLE_LOBE_RATIO = 0.25


def visible_lobe_texels(maps: Mapping[str, Tensor], min_ratio: float = VISIBLE_LOBE_RATIO) -> Tensor:
    """``[H, W]`` bool: texels whose GGX lobe peaks at least ``min_ratio`` × their Lambert term at normal
    incidence, ``f0 · D(n·h = 1) / 4  ≥  min_ratio · ρ / π`` with ``D(1) = 1 / (π α²)``, i.e.
    ``f0 / (4 α² ρ) ≥ min_ratio`` (channel means; α = r²). ``maps``: canonical maps with ``f0`` and ``roughness``,
    ``albedo`` optional (0: any lobe is visible)."""
    if "f0" not in maps or "roughness" not in maps:
        raise MetricsError(f"visible_lobe_texels needs 'f0' and 'roughness' maps, got {sorted(maps)}")
    from materials.roughness import roughness_to_alpha

    f0 = maps["f0"].double().mean(-1)
    alpha = roughness_to_alpha(maps["roughness"].double().mean(-1))
    rho = maps["albedo"].double().mean(-1) if "albedo" in maps else torch.zeros_like(f0)
    return f0 >= min_ratio * 4.0 * alpha.square() * rho


def highlight_texels(obs, roughness: Tensor, min_angle_deg: float = 1.0) -> Tensor:
    """``[H, W]`` bool: texels seen inside a highlight — some (sample, light) pair with the half vector within the
    half-maximum angle of the GGX lobe of the texel's roughness ``[H, W, 1]`` (at least ``min_angle_deg``) of the
    normal, the criterion of :func:`capture.synth.highlight_coverage`."""
    from materials.roughness import half_max_angle

    H, W = obs.map_size
    theta = half_max_angle(roughness.reshape(-1).double()).clamp_min(math.radians(min_angle_deg))
    tex = obs.texel[obs.pair_sample]
    ok = obs.angles.nh.reshape(-1).double() >= torch.cos(theta.to(obs.device))[tex]
    out = torch.zeros(H * W, dtype=torch.bool, device=obs.device)
    out[tex[ok]] = True
    return out.reshape(H, W)


def texel_sets(truth: Mapping[str, Tensor], obs, fp=None) -> dict[str, Tensor]:
    """``{name: [H, W] bool}``: the texel sets the image-formation targets are stated on (docs/image-formation.md) —
    well lit (:func:`well_lit_texels` of the pixel-centre observations ``obs``), of those the ones that cover at
    least a pixel in some view (with the pixel footprints ``fp``) and, for specular truths, seen inside a highlight
    (:func:`highlight_texels`) and of those the ones whose lobe is visible (:func:`visible_lobe_texels`)."""
    lit = well_lit_texels(obs)
    sets = {"well_lit": lit}
    if fp is not None:
        sets["well_lit_pixel_sized"] = lit & pixel_sized_texels(fp)
    if "roughness" in truth and tuple(truth["roughness"].shape[:2]) == tuple(obs.map_size):
        sets["well_lit_highlight"] = lit & highlight_texels(obs, truth["roughness"])
        if "f0" in truth:
            # of those, the texels whose lobe stands out of the diffuse term (a faint broad lobe barely shapes a
            # pixel, and its roughness trades with the albedo inside the noise)
            sets["well_lit_visible_highlight"] = sets["well_lit_highlight"] & visible_lobe_texels(truth)
    return sets


def errors_by_texel_set(raw: Mapping[str, Tensor], truth: Mapping[str, Tensor], obs=None, fp=None,
                        sets: Mapping[str, Tensor] | None = None) -> dict:
    """RMSE of the maps ``raw`` (canonical ``[H, W, C]``) against ``truth`` on the :func:`texel_sets` of ``obs`` and
    ``fp`` (or on ``sets`` made by it once, for an optimiser measured at every few steps) — the report's
    ``errors.maps_by_texel_set``, and what the Mitsuba baseline (``scripts/mitsuba_adam.py``) is measured on:
    ``{set: {"texels": n, map: rmse, …}}``. Roughness is also given as GGX/Beckmann α = r² (``roughness_alpha``)."""
    from materials.roughness import roughness_to_alpha

    if sets is None:
        if obs is None:
            raise MetricsError("errors_by_texel_set needs the observations (obs) or the texel sets (sets)")
        sets = texel_sets(truth, obs, fp)
    # roughness also as GGX/Beckmann α = r², the unit most renderers take
    with_alpha = (lambda d: {**d, "roughness_alpha": roughness_to_alpha(d["roughness"])}
                  if "roughness" in d else d)
    fitted_a, truth_a = with_alpha(dict(raw)), with_alpha(dict(truth))
    return {k: {"texels": int(m.sum()), **{n: e["rmse"] for n, e in map_errors(fitted_a, truth_a, m).items()}}
            for k, m in sets.items()}


# ----------------------------------------------------------------------------------- coverage advice

#: :func:`coverage_advice`: a (sample, light) pair shows a texel's highlight when its half vector is within this many
#: degrees of the normal (a GGX lobe of roughness 0.3 falls to half its peak at ~4°, of roughness 0.5 at ~12°)...
HIGHLIGHT_DEG = 10.0
#: ... and a direction is named in the advice when at least this fraction of the surface texels misses it.
ADVICE_MIN_FRACTION = 0.01


def texel_normals(mesh, map_size: tuple[int, int], samples_per_texel: float = 8.0, seed: int = 0,
                  chunk: int = 1 << 20, max_points: int = 1 << 23) -> tuple[Tensor, Tensor]:
    """The surface's normal in each texel of a ``map_size`` map, from the mesh's UV charts.

    Points are drawn on the faces in proportion to their area *in UV space* (``samples_per_texel`` per texel of the
    charts on average, at most ``max_points`` in all, fixed seed), their UVs and interpolated shading normals are
    accumulated per texel (:func:`renderer.texture.texel_of`) and normalised. A random draw leaves a texel of the
    charts uncovered with probability about e^(−points per texel): 0.03 % at the default 8 (256² maps); 2K maps are
    capped at 2 per texel (13 % uncovered, left out of the surface — the fractions of :func:`coverage_advice` are
    still those of the surface).

    Args:
        mesh: a :class:`renderer.mesh.Mesh` (UVs and normals per vertex).
        map_size: ``(H, W)`` of the maps.

    Returns:
        ``(normals [H, W, 3] float32 in the dataset frame, zero where no chart covers the texel; covered [H, W] bool)``.
    """
    from renderer.texture import texel_of

    if not (isinstance(map_size, (tuple, list)) and len(map_size) == 2
            and all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in map_size)):
        raise MetricsError(f"texel_normals: map_size must be (H, W), two positive integers, got {map_size!r}")
    if isinstance(samples_per_texel, bool) or not isinstance(samples_per_texel, (int, float)) \
            or not 0 < samples_per_texel <= 64:
        raise MetricsError(f"texel_normals: samples_per_texel must be a number in (0, 64], got {samples_per_texel!r}")
    for attr in ("faces", "uvs", "normals"):
        if not isinstance(getattr(mesh, attr, None), Tensor):
            raise MetricsError(f"texel_normals: mesh must be a renderer.mesh.Mesh (with {attr}), got "
                               f"{type(mesh).__name__}")
    H, W = map_size
    f = mesh.faces.long()
    uv = mesh.uvs.double()[f]                                     # [F, 3, 2]
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).abs()
    acc = torch.zeros(H * W, 3, dtype=torch.float64)
    total = float(area.sum())
    if total > 0:
        # each point: a face drawn by its UV area (the inverse of the areas' cumulative sum), then a uniform point of
        # it as a corner plus its two edges weighted — in float32 (UVs to 6e-8, far inside a texel of 8K maps),
        # accumulated in float64. The 8 M points of 2048² maps: 1.08 against 2.0 s for torch.multinomial and a
        # float64 barycentric sum over [k, 3, ·] gathers (2 threads)
        cdf = torch.cumsum(area, 0)
        cdf = cdf / cdf[-1]
        nrm = mesh.normals.float()[f]                              # [F, 3, 3]
        corner_uv, e1_uv, e2_uv = uv[:, 0].float(), e1.float(), e2.float()
        corner_n, e1_n, e2_n = nrm[:, 0], nrm[:, 1] - nrm[:, 0], nrm[:, 2] - nrm[:, 0]
        n_points = min(max(int(math.ceil(samples_per_texel * total * H * W)), 1), max_points)
        gen = torch.Generator().manual_seed(seed)
        for start in range(0, n_points, chunk):
            k = min(chunk, n_points - start)
            face = torch.searchsorted(cdf, torch.rand(k, generator=gen, dtype=torch.float64)).clamp_(max=len(f) - 1)
            a, b = torch.rand(k, 1, generator=gen), torch.rand(k, 1, generator=gen)
            flip = a + b > 1
            a, b = torch.where(flip, 1 - a, a), torch.where(flip, 1 - b, b)
            p_uv = torch.addcmul(torch.addcmul(corner_uv[face], e1_uv[face], a), e2_uv[face], b).clamp_(0, 1)
            p_n = torch.addcmul(torch.addcmul(corner_n[face], e1_n[face], a), e2_n[face], b)
            acc.index_add_(0, texel_of(p_uv, H, W), p_n.double())
    length = acc.norm(dim=-1, keepdim=True)
    covered = length[:, 0] > 1e-12
    normals = torch.where(covered[:, None], acc / length.clamp_min(1e-300), torch.zeros_like(acc))
    return normals.float().reshape(H, W, 3), covered.reshape(H, W)


def _name_direction(d: Tensor | None, up: Tensor) -> str:
    """Words for a mean normal ``d`` (unit or None) in the dataset frame with ``up``: above / below / the side."""
    if d is None:
        return "all around (no single direction)"
    axes = ["+x", "−x", "+y", "−y", "+z", "−z"]
    comp = torch.stack([d, -d], 1).reshape(-1)                 # +x, −x, +y, −y, +z, −z
    axis = axes[int(comp.argmax())]
    vec = f"({float(d[0]):.2f}, {float(d[1]):.2f}, {float(d[2]):.2f})"
    u = float((d * up).sum())
    where = "above" if u > 0.7 else "below" if u < -0.7 else "the side"
    return f"{where} ({axis}; mean normal {vec})"


def _check_advice_args(cos, highlight_deg, block, up) -> Tensor:
    """Validate :func:`coverage_advice`'s options; returns ``up`` as a unit float64 vector."""
    if isinstance(cos, bool) or not isinstance(cos, (int, float)) or not -1 < cos < 1:
        raise MetricsError(f"coverage_advice: cos must be a number in (−1, 1), got {cos!r}")
    if isinstance(highlight_deg, bool) or not isinstance(highlight_deg, (int, float)) or not 0 < highlight_deg < 90:
        raise MetricsError(f"coverage_advice: highlight_deg must be a number of degrees in (0, 90), got "
                           f"{highlight_deg!r}")
    if block is not None and (isinstance(block, bool) or not isinstance(block, int) or block < 1):
        raise MetricsError(f"coverage_advice: block must be a positive integer or None, got {block!r}")
    up_t = torch.as_tensor(up, dtype=torch.float64).reshape(-1)
    if up_t.numel() != 3 or not bool(torch.isfinite(up_t).all()) or float(up_t.norm()) == 0:
        raise MetricsError(f"coverage_advice: up must be a non-zero 3-vector, got {up!r}")
    return up_t / up_t.norm()


def _advice_normals(obs, normals: Tensor | None) -> Tensor:
    """``[T, 3]`` float64 texel normals: the given ones, or the mean of each texel's samples' normals."""
    H, W = obs.map_size
    T = H * W
    dev = obs.device
    if normals is None:
        if obs.n is None:
            raise MetricsError("coverage_advice: the observations carry no normals (obs.n); pass normals= "
                               "(capture.metrics.texel_normals of the mesh)")
        acc = torch.zeros(T, 3, dtype=torch.float64, device=dev).index_add_(0, obs.texel, obs.n.double())
        return acc / acc.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    if not isinstance(normals, Tensor) or tuple(normals.shape) != (H, W, 3):
        raise MetricsError(f"coverage_advice: normals must be a [{H}, {W}, 3] tensor like the observations' maps, "
                           f"got {getattr(normals, 'shape', type(normals).__name__)}")
    return normals.reshape(T, 3).double().to(dev)


def _advice_surface(obs, surface: Tensor | None, nrm: Tensor, given_normals: bool, read: Tensor) -> Tensor:
    """``[T]`` bool, the surface texels: ``surface``, else where the given normals are set; always those ``read``."""
    H, W = obs.map_size
    T = H * W
    dev = obs.device
    if surface is None:
        surf = nrm.norm(dim=-1) > 0.5 if given_normals else torch.zeros(T, dtype=torch.bool, device=dev)
    else:
        if not isinstance(surface, Tensor) or surface.dtype != torch.bool or tuple(surface.shape) != (H, W):
            raise MetricsError(f"coverage_advice: surface must be an [{H}, {W}] bool tensor, got "
                               f"{getattr(surface, 'dtype', type(surface).__name__)} "
                               f"{tuple(getattr(surface, 'shape', ()))}")
        surf = surface.reshape(T).to(dev)
    return surf | read


def _per_texel(texels: Tensor, T: int, device) -> Tensor:
    out = torch.zeros(T, dtype=torch.bool, device=device)
    out[texels] = True
    return out


def _seen_lit_highlighted(obs, cos: float, highlight_deg: float) -> tuple[Tensor, Tensor, Tensor]:
    """``[T]`` bool each: the texels some sample sees at n·v > cos, some pair also lights at n·l > cos, and some
    pair's half vector comes within ``highlight_deg`` of the normal."""
    H, W = obs.map_size
    T = H * W
    dev = obs.device
    nv_s = obs.v is not None and obs.n is not None
    nv = (obs.n * obs.v).sum(-1) if nv_s else None
    tex_pair = obs.texel[obs.pair_sample]
    nv_pair, nl_pair = obs.angles.nv.reshape(-1), obs.angles.nl.reshape(-1)
    if nv is None:          # no per-sample vectors: the pairs' cosines (samples without a pair are not judged)
        seen = _per_texel(tex_pair[nv_pair > cos], T, dev)
    else:
        seen = _per_texel(obs.texel[nv > cos], T, dev)
    lit = _per_texel(tex_pair[(nv_pair > cos) & (nl_pair > cos)], T, dev)
    hl = _per_texel(tex_pair[obs.angles.nh.reshape(-1) >= math.cos(math.radians(highlight_deg))], T, dev)
    return seen, lit, hl


def _auto_block(obs, n_surf: int) -> int:
    """About the texel spacing of one view's samples, odd, in [1, 15] (see :func:`coverage_advice`)."""
    views = max(int(obs.n_views), 1)
    b = math.ceil(math.sqrt(max(n_surf, 1) * views / (2 * max(obs.n_samples, 1))))
    block = min(max(b, 1), 15)
    return block + 1 - block % 2


def _grow(m: Tensor, block: int, H: int, W: int) -> Tensor:
    """``[H·W]`` bool ``m`` dilated by a ``block`` × ``block`` square: a row pass then a column pass (the square's
    maximum is the maximum of its rows' maxima; the same masks as one square pool, which took 0.51 against 0.16 s
    per mask at 2048² with the 15-texel block, 2 threads)."""
    import torch.nn.functional as F

    x = m.reshape(1, 1, H, W).float()
    x = F.max_pool2d(x, (1, block), 1, (0, block // 2))
    return F.max_pool2d(x, (block, 1), 1, (block // 2, 0)).reshape(H * W) > 0.5


def _advice_sentence(key: str, named: str, frac: float, cos: float, highlight_deg: float) -> str:
    pct = f"{frac:.0%}"
    if key == "unseen":
        return f"add views from {named}: {pct} of the surface texels are never seen at n·v > {cos:g}"
    if key == "unlit":
        return (f"add light directions from {named}: {pct} of the surface texels are seen but never lit "
                f"at n·l > {cos:g} in a view that sees them at n·v > {cos:g}")
    return (f"add a light near the mirror direction of a view for texels facing {named}: {pct} of "
            f"the surface texels are seen and lit but never show a highlight (no half vector within "
            f"{highlight_deg:g}° of the normal), so their f0 and roughness rest on the lobe's tail")


def _texel_set(m: Tensor, nrm: Tensor, n_surf: int, up: Tensor) -> dict:
    """A set's entry of :func:`coverage_advice`: texels, fraction, mean normal direction and its name."""
    k = int(m.sum())
    frac = k / n_surf if n_surf else 0.0
    d = None
    if k:
        mean = nrm[m].sum(0) / k
        if float(mean.norm()) >= 0.3:
            d = mean / mean.norm()
    named = _name_direction(d.cpu() if d is not None else None, up)
    return {"texels": k, "fraction": frac, "direction": d.tolist() if d is not None else None, "named": named}


def coverage_advice(obs, normals: Tensor | None = None, surface: Tensor | None = None, *, cos: float = WELL_LIT_COS,
                    highlight_deg: float = HIGHLIGHT_DEG, specular: bool = True, block: int | None = None,
                    up=(0.0, 0.0, 1.0)) -> dict:
    """Which directions the photos miss: the surface texels never seen well, never lit well, or never shown a
    highlight, where their normals point on average, and what to add.

    Per texel of the surface (``surface``; default: the texels some sample reads), three disjoint sets:

    * ``unseen`` — no sample sees it with n·v > ``cos`` (never seen at all, or only grazing): add *views* facing the
      set's mean normal;
    * ``unlit`` — seen so, but no (sample, light) pair has n·v > ``cos`` and n·l > ``cos``: add *lights* from there;
    * ``no_highlight`` (``specular`` only) — well seen and lit, but no pair's half vector comes within
      ``highlight_deg`` of the normal: no highlight was seen, so f0 and roughness rest on the lobe's tail; add a light
      near the mirror direction of a view (e.g. beside the camera, for surfaces facing it).

    A texel counts as seen / lit / highlighted when a texel within ``block`` × ``block`` of it is (a square
    neighbourhood): photos with fewer pixels than the maps have texels no pixel centre falls in even where a view
    faces them. ``block=None`` takes about the texel spacing of one view's samples, ⌈√(surface texels · views /
    (2 · samples))⌉ clamped to [1, 15] and made odd (each view sees about half the surface); 1 judges each texel alone.

    Args:
        obs: :class:`capture.observations.Observations` (with ``n``, the samples' shading normals, when ``normals``
            is None).
        normals: ``[H, W, 3]`` texel normals in the dataset frame (:func:`texel_normals`); None = the mean of each
            observed texel's samples' normals (then texels no sample reads are not part of the surface).
        surface: ``[H, W]`` bool, the texels on the object (default: where ``normals`` is non-zero, else the texels
            some sample reads); the texels some sample reads always count.
        cos: the cosine a view or light must exceed (default :data:`WELL_LIT_COS`, 72.5° from the normal).
        highlight_deg: the half-vector angle of a highlight (default :data:`HIGHLIGHT_DEG`).
        specular: also judge highlights (the model has a specular lobe).
        up: the dataset frame's up direction, to name a direction above / below / at the side (default +z).

    Returns:
        ``{"texels": surface texels, "block": b, "cos": cos, "highlight_deg": …, "unseen" | "unlit" | "no_highlight":
        {"texels", "fraction" (of the surface texels), "direction" (unit mean normal as a list, or None when the
        normals spread so that their mean is shorter than 0.3), "named" (words)}, "advice": [sentences]}``;
        ``no_highlight`` only with ``specular``. Advice names each set of at least :data:`ADVICE_MIN_FRACTION`.
    """
    H, W = obs.map_size
    up_t = _check_advice_args(cos, highlight_deg, block, up)
    read = obs.footprint().reshape(H * W).to(obs.device)
    nrm = _advice_normals(obs, normals)
    surf = _advice_surface(obs, surface, nrm, normals is not None, read)
    n_surf = int(surf.sum())
    seen, lit, hl = _seen_lit_highlighted(obs, cos, highlight_deg)
    if block is None:
        block = _auto_block(obs, n_surf)
    if block > 1:
        seen, lit, hl = (_grow(m, block, H, W) for m in (seen, lit, hl))

    sets = {"unseen": surf & ~seen, "unlit": surf & seen & ~lit}
    if specular:
        sets["no_highlight"] = surf & seen & lit & ~hl
    out = {"texels": n_surf, "block": block, "cos": float(cos), "highlight_deg": float(highlight_deg)}
    advice = []
    for key, m in sets.items():
        out[key] = _texel_set(m, nrm, n_surf, up_t)
        if out[key]["fraction"] >= ADVICE_MIN_FRACTION:
            advice.append(_advice_sentence(key, out[key]["named"], out[key]["fraction"], cos, highlight_deg))
    out["advice"] = advice
    return out
