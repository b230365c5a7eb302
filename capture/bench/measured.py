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
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

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

if TYPE_CHECKING:
    from ..brdf_fit import FitResult, SampleSet

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


class _Scene(NamedTuple):
    """The rendered scene, its training dataset and what the reconstructions are scored against."""

    images: list[Tensor]
    preps: list
    regions: Tensor  # [T, T] region id per texel
    held: list[int]
    dataset: Path
    materials: tuple[str, ...]
    targets: dict  # material name → its measured model


@dataclass
class _Reference:
    """fit_brdf's pseudo ground truth: its samples and restarts, and the fits made so far by (model, material)."""

    samples: SampleSet
    restarts: int
    fits: dict[tuple[str, str], FitResult] = field(default_factory=dict)


def _prepare_scene(config: MeasuredSceneConfig, work: Path) -> _Scene:
    """Render the scene and write the training dataset (every view but the held-out ones) into ``work``."""
    images, views, preps, mesh, regions = render_measured_scene(config)
    held = _heldout(len(views))
    if not held:
        raise MeasuredSceneError("capture_benchmark: need at least 4 views (every 4th is held out)")
    train = [i for i in range(len(views)) if i not in held]
    ds_path = make_measured_scene(config, work / "dataset", overwrite=True, views=train)
    targets = dict(zip(config.materials, config.models(), strict=True))
    return _Scene(images, preps, regions, held, ds_path, config.materials, targets)


def _read_maps(out: Path, mdl) -> dict[str, Tensor]:
    """The model's maps from the reconstruction folder ``out``, each ``[H, W, channels]``."""
    maps = {}
    for spec in mdl.params:
        m = read_exr(out / f"{spec.name}.exr")
        m = m if m.dim() == 3 else m[..., None]
        maps[spec.name] = m[..., :spec.channels] if m.shape[-1] >= spec.channels else m[..., :1]
    return maps


def _heldout_scores(mdl, maps: Mapping[str, Tensor], scene: _Scene) -> tuple[float, float]:
    """Mean PSNR and SSIM of the held-out views re-rendered with ``maps``, over the lit object pixels."""
    from ..metrics import image_metrics

    ps, ss = [], []
    with torch.no_grad():
        for i in scene.held:
            prep = scene.preps[i]
            rad = shade(mdl, maps, prep, sampling="nearest")
            g = prep.gbuffer
            lit = torch.zeros(len(g), 3)
            lit[prep.sample] = 1.0
            mask = g.to_image(lit)[..., 0] > 0.999
            m = image_metrics(g.to_image(rad), scene.images[i], mask)
            ps.append(m["psnr"])
            ss.append(m["ssim"])
    return sum(ps) / len(ps), sum(ss) / len(ss)


def _unobservable(out: Path, mdl) -> dict[str, Tensor]:
    """Per parameter with an ``unobservable_<name>.png``, its ``[T, T]`` bool map (True = not constrained)."""
    unobs = {}
    for k in mdl.param_names:
        f = out / f"unobservable_{k}.png"
        if f.is_file():
            u = read_png(f, transfer="linear")
            unobs[k] = (u if u.dim() == 2 else u[..., 0]) > 0.5
    return unobs


def _fit_comparison(ref: _Reference, mdl, model: str, mat: str, target, captured: Mapping[str, Tensor]) -> dict:
    """fit_brdf's parameters of ``model`` for material ``mat`` (fitted once) and the BRDF-space relative L1 of
    the captured and the fitted parameters against it."""
    from .. import brdf_fit

    key = (model, mat)
    if key not in ref.fits:
        ref.fits[key] = brdf_fit.fit_brdf(mdl, target, ref.samples, restarts=ref.restarts)
    fr = ref.fits[key]
    meas = brdf_fit.evaluate_target(target, ref.samples)
    with torch.no_grad():
        cap = {k: v.to(torch.float64) for k, v in captured.items()}
        pred = mdl.brdf(ref.samples.g, cap)
    ec = brdf_fit.errors(pred, meas, ref.samples)
    return {"fit": {k: v.tolist() for k, v in fr.params.items()},
            "l1_capture": ec.rel_l1, "l1_capture_no_grazing": ec.rel_l1_no_grazing,
            "l1_fit": fr.errors.rel_l1, "l1_fit_no_grazing": fr.errors.rel_l1_no_grazing}


def _region_entries(scene: _Scene, mdl, model: str, maps: Mapping[str, Tensor], observed: Tensor,
                    unobs: Mapping[str, Tensor], ref: _Reference | None) -> dict[str, dict]:
    """Per material seen in the reconstruction: the captured medians, the observed texels, the observable
    fraction per parameter and, with ``ref``, the comparison with fit_brdf."""
    med = _region_medians(maps, scene.regions, observed)
    entries = {}
    for rid, mat in enumerate(scene.materials, start=1):
        if rid not in med:
            continue
        sel = (scene.regions == rid) & observed
        entry = {"params": {k: v.tolist() for k, v in med[rid].items()},
                 "observed_texels": int(sel.sum()),
                 "observable_fraction": {k: float((~u[sel]).float().mean()) for k, u in unobs.items()}}
        if ref is not None:
            entry.update(_fit_comparison(ref, mdl, model, mat, scene.targets[mat], med[rid]))
        entries[mat] = entry
    return entries


def _benchmark_model(name: str, scene: _Scene, ref: _Reference | None, work: Path, progress: bool,
                     reconstruct_options: Mapping) -> dict:
    """Reconstruct the training dataset with model ``name`` and score it: one row of :func:`capture_benchmark`."""
    from ..reconstruct import ReconstructionError, reconstruct

    T = scene.regions.shape[0]
    row = {"model": name, "chosen": None, "psnr": math.nan, "ssim": math.nan, "psnr_train": math.nan,
           "seconds": math.nan, "error": None, "regions": {}}
    t0 = time.perf_counter()
    out = work / f"recon-{name}"
    try:
        rep = reconstruct(scene.dataset, model=name, out_dir=out, force=True, texture_size=T, sampling="nearest",
                          progress=progress, **reconstruct_options)
    except (ReconstructionError, ValueError, RuntimeError) as exc:
        row["error"] = f"{type(exc).__name__}: {exc}"
        return row
    row["seconds"] = time.perf_counter() - t0
    row["chosen"] = rep.model
    row["psnr_train"] = sum(v["psnr"] for v in rep.views) / len(rep.views)
    mdl = materials.get(rep.model)
    maps = _read_maps(out, mdl)
    # held-out views: re-render with the recovered maps, compare over the lit object pixels
    row["psnr"], row["ssim"] = _heldout_scores(mdl, maps, scene)
    observed = _observed(out, T)
    unobs = _unobservable(out, mdl)
    row["regions"] = _region_entries(scene, mdl, rep.model, maps, observed, unobs, ref)
    return row


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

    config = config or measured_scene()
    tmp = None
    if work_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="measured-bench-")
        work_dir = tmp.name
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        scene = _prepare_scene(config, work)
        ref = None
        if fit_reference:
            ref = _Reference(brdf_fit.make_samples(resolution=fit_resolution, dtype=torch.float64), fit_restarts)
        return [_benchmark_model(name, scene, ref, work, progress, reconstruct_options) for name in models]
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
