"""How well the analytic models recover measured materials: reconstructions of a scene of
:mod:`capture.synth.measured` (regions made of NBRDF fits of MERL), scored on held-out views and against the
best fit of each model to each material.

``scripts/benchmark.py measured`` runs :func:`capture_benchmark` and prints :func:`benchmark_table`
(docs/measured-fits.md, "Capture of measured materials").

Views ``3, 7, 11, …`` (every 4th, as the auto selection of :mod:`capture.reconstruct` holds out) are kept out:
the training dataset holds the others, :func:`capture.reconstruct.reconstruct` recovers maps from it, and the
held-out views are re-rendered with the recovered maps (same geometry, "nearest" sampling) and compared with their
true images by :func:`capture.metrics.image_metrics` (PSNR with the photo's peak, SSIM) over the lit object
pixels. Per region, the recovered maps (median over the region's observed texels) are compared with a pseudo
ground truth: :func:`capture.brdf_fit.fit_brdf` of the same model to the same measured material (joint,
3 restarts, 1534 Rusinkiewicz samples — the settings of docs/measured-fits.md). Two comparisons: the parameter
differences, and the BRDF-space error — the cosine-weighted relative L1 of the captured parameters against the
material on the fit's samples, beside the fit's own (the best that model can do under that error).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

import materials
from renderer.imageio import read_exr, read_png
from renderer.shading import shade

from ..synth.measured import (
    MeasuredSceneConfig,
    MeasuredSceneError,
    make_measured_scene,
    measured_scene,
    render_measured_scene,
)

__all__ = ["BENCH_MODELS", "capture_benchmark", "benchmark_table"]

#: Models the benchmark reconstructs with by default ("auto" = reconstruct's model selection).
BENCH_MODELS = ("lambert", "ggx-lambert", "gotanda2012", "nielsen-mixture", "auto")


def _heldout(n: int) -> list[int]:
    return list(range(3, n, 4)) if n >= 4 else []


def _region_medians(maps: Mapping[str, Tensor], regions: Tensor, observed: Tensor) -> dict[int, dict[str, Tensor]]:
    out = {}
    for rid in torch.unique(regions).tolist():
        sel = (regions == rid) & observed
        if not bool(sel.any()):
            continue
        out[int(rid)] = {k: m[sel].double().median(dim=0).values for k, m in maps.items()}
    return out


def capture_benchmark(config: MeasuredSceneConfig | None = None, models: Sequence[str] = BENCH_MODELS, *,
                      work_dir=None, fit_reference: bool = True, fit_resolution: int = 16, fit_restarts: int = 3,
                      progress: bool = False, **reconstruct_options) -> list[dict]:
    """Reconstruct a measured scene with each model; score held-out re-renders and per-region maps.

    Args:
        config: the scene (default :func:`measured_scene`).
        models: registry names or ``"auto"``.
        work_dir: folder for the datasets and reconstructions (default: a temporary folder, removed).
        fit_reference: also fit each model to each material with :func:`capture.brdf_fit.fit_brdf` (the pseudo
            ground truth; ~1-5 s per model and material).
        fit_resolution, fit_restarts: :func:`capture.brdf_fit.make_samples` resolution and fit restarts.
        reconstruct_options: passed to :func:`capture.reconstruct.reconstruct` (solver, loss, iterations, …).
    Returns:
        One dict per model: ``model`` (asked), ``chosen`` (the model used; differs for "auto"), ``psnr``,
        ``ssim`` (means over held-out views), ``psnr_train`` (the reconstruction's own views), ``seconds``,
        ``error`` (a message if the reconstruction failed, else None) and ``regions``: per material,
        ``params`` (captured medians), ``fit`` (fit_brdf's), ``l1_capture`` and ``l1_fit`` (BRDF-space
        relative L1 of each parameter set against the material; ``*_no_grazing`` without θ > 80°) and
        ``observed_texels`` and ``observable_fraction`` (per parameter, the share of the region's observed
        texels where the solver found it constrained; elsewhere the map holds a pull-push fill or the default,
        and the median mixes those in).
    """
    from .. import brdf_fit
    from ..metrics import image_metrics
    from ..reconstruct import ReconstructionError, reconstruct

    config = config or measured_scene()
    tmp = None
    if work_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="measured-bench-")
        work_dir = tmp.name
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        images, views, preps, mesh, regions = render_measured_scene(config)
        held = _heldout(len(views))
        if not held:
            raise MeasuredSceneError("capture_benchmark: need at least 4 views (every 4th is held out)")
        train = [i for i in range(len(views)) if i not in held]
        ds_path = make_measured_scene(config, work / "dataset", overwrite=True, views=train)
        targets = dict(zip(config.materials, config.models(), strict=True))
        samples = brdf_fit.make_samples(resolution=fit_resolution, dtype=torch.float64) if fit_reference else None
        fits: dict[tuple[str, str], brdf_fit.FitResult] = {}
        T = regions.shape[0]
        rows = []
        for name in models:
            row = {"model": name, "chosen": None, "psnr": math.nan, "ssim": math.nan, "psnr_train": math.nan,
                   "seconds": math.nan, "error": None, "regions": {}}
            rows.append(row)
            t0 = time.perf_counter()
            out = work / f"recon-{name}"
            try:
                rep = reconstruct(ds_path, model=name, out_dir=out, force=True, texture_size=T, sampling="nearest",
                                  progress=progress, **reconstruct_options)
            except (ReconstructionError, ValueError, RuntimeError) as exc:
                row["error"] = f"{type(exc).__name__}: {exc}"
                continue
            row["seconds"] = time.perf_counter() - t0
            row["chosen"] = rep.model
            row["psnr_train"] = sum(v["psnr"] for v in rep.views) / len(rep.views)
            mdl = materials.get(rep.model)
            maps = {}
            for spec in mdl.params:
                m = read_exr(out / f"{spec.name}.exr")
                m = m if m.dim() == 3 else m[..., None]
                maps[spec.name] = m[..., :spec.channels] if m.shape[-1] >= spec.channels else m[..., :1]
            # held-out views: re-render with the recovered maps, compare over the lit object pixels
            ps, ss = [], []
            with torch.no_grad():
                for i in held:
                    rad = shade(mdl, maps, preps[i], sampling="nearest")
                    g = preps[i].gbuffer
                    lit = torch.zeros(len(g), 3)
                    lit[preps[i].sample] = 1.0
                    mask = g.to_image(lit)[..., 0] > 0.999
                    m = image_metrics(g.to_image(rad), images[i], mask)
                    ps.append(m["psnr"])
                    ss.append(m["ssim"])
            row["psnr"], row["ssim"] = sum(ps) / len(ps), sum(ss) / len(ss)
            observed = _observed(out, T)
            unobs = {}
            for k in mdl.param_names:
                f = out / f"unobservable_{k}.png"
                if f.is_file():
                    u = read_png(f, transfer="linear")
                    unobs[k] = (u if u.dim() == 2 else u[..., 0]) > 0.5
            med = _region_medians(maps, regions, observed)
            for rid, mat in enumerate(config.materials, start=1):
                if rid not in med:
                    continue
                sel = (regions == rid) & observed
                entry = {"params": {k: v.tolist() for k, v in med[rid].items()},
                         "observed_texels": int(sel.sum()),
                         "observable_fraction": {k: float((~u[sel]).float().mean()) for k, u in unobs.items()}}
                if fit_reference:
                    key = (rep.model, mat)
                    if key not in fits:
                        fits[key] = brdf_fit.fit_brdf(mdl, targets[mat], samples, restarts=fit_restarts)
                    fr = fits[key]
                    meas = brdf_fit.evaluate_target(targets[mat], samples)
                    with torch.no_grad():
                        cap = {k: v.to(torch.float64) for k, v in med[rid].items()}
                        pred = mdl.brdf(samples.g, cap)
                    entry["fit"] = {k: v.tolist() for k, v in fr.params.items()}
                    ec = brdf_fit.errors(pred, meas, samples)
                    entry["l1_capture"], entry["l1_capture_no_grazing"] = ec.rel_l1, ec.rel_l1_no_grazing
                    entry["l1_fit"], entry["l1_fit_no_grazing"] = fr.errors.rel_l1, fr.errors.rel_l1_no_grazing
                row["regions"][mat] = entry
        return rows
    finally:
        if tmp is not None:
            tmp.cleanup()


def _observed(out: Path, T: int) -> Tensor:
    """Observed texels ``[T, T]`` bool from a reconstruction's ``coverage.exr`` (channel 2)."""
    cov = read_exr(out / "coverage.exr")
    return cov[..., 2] > 0.5 if cov.dim() == 3 and cov.shape[-1] >= 3 else torch.ones(T, T, dtype=torch.bool)


def _short(x) -> str:
    if isinstance(x, list):
        return "(" + ", ".join(f"{v:.3g}" for v in x) + ")" if len(x) > 1 else f"{x[0]:.3g}"
    return f"{x:.3g}"


def benchmark_table(rows: Sequence[Mapping]) -> str:
    """Markdown: a summary table (held-out PSNR/SSIM per model) and a per-region table (captured vs fitted)."""
    lines = ["| model | chosen | held-out PSNR (dB) | held-out SSIM | training-view PSNR (dB) | mean L1 capture "
             "| mean L1 fit | seconds |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("error"):
            lines.append(f"| `{r['model']}` | — | failed: {r['error'][:80]} | | | | | |")
            continue
        reg = [e for e in r["regions"].values() if "l1_capture" in e]
        lc = sum(e["l1_capture"] for e in reg) / len(reg) if reg else math.nan
        lf = sum(e["l1_fit"] for e in reg) / len(reg) if reg else math.nan
        lines.append(f"| `{r['model']}` | `{r['chosen']}` | {r['psnr']:.2f} | {r['ssim']:.3f} | "
                     f"{r['psnr_train']:.2f} | {lc:.3f} | {lf:.3f} | {r['seconds']:.1f} |")
    lines += ["", "| model | material | texels | L1 capture (w/o grazing) | L1 fit (w/o grazing) | parameter "
              "| captured | fit_brdf |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("error"):
            continue
        for mat, e in r["regions"].items():
            first = True
            for p, val in e["params"].items():
                fit = e.get("fit", {}).get(p)
                head = (f"| `{r['chosen']}`{' (auto)' if r['model'] == 'auto' else ''} | {mat} | "
                        f"{e['observed_texels']} | {e.get('l1_capture', math.nan):.3f} "
                        f"({e.get('l1_capture_no_grazing', math.nan):.3f}) | {e.get('l1_fit', math.nan):.3f} "
                        f"({e.get('l1_fit_no_grazing', math.nan):.3f}) |") if first else "| | | | | |"
                obs = e.get("observable_fraction", {}).get(p)
                cap = _short(val) + (f" [{obs:.0%} obs.]" if obs is not None and obs < 0.995 else "")
                lines.append(f"{head} {p} | {cap} | {_short(fit) if fit is not None else '—'} |")
                first = False
    return "\n".join(lines)
