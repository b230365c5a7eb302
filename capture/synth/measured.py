"""Synthetic captures of *measured* materials (NBRDF fits of MERL), and how well the analytic models recover them.

Why
---
A synthetic scene rendered with one of our models only shows that the solver inverts the renderer. Here the
regions of the object are made of measured materials — the NBRDF networks of the MERL BRDFs
(:mod:`materials.measured`; results are "NBRDF fits of MERL", see that module for the data's attribution and
terms) — so the truth is no model of ours, and reconstructing with an analytic model shows how close its maps
and re-renders get to a real material.

Scene (:func:`make_measured_scene`)
-----------------------------------
The mesh, cameras and lights are built exactly as :mod:`capture.synth.scenes` builds them
(:func:`capture.synth.build_mesh`, :func:`~capture.synth.build_cameras`,
:func:`~capture.synth.build_lights`, from a :class:`~capture.synth.SyntheticConfig` whose ``model`` is
only a placeholder). The texture is split into K vertical stripes in u (:func:`region_map`, region ids 1..K, one
material per region, like the procedural stripes of :mod:`capture.synth.scenes`), so each region wraps around the
sphere and every camera of an orbit sees several. Per view: one G-buffer and one
:func:`renderer.shading.prepare` (shadow rays), then for each light ``E·V·f_r·cos θ_i`` with f_r from
``materials.get("measured", material=NAME).cosine_brdf`` evaluated, per region, on the samples whose *nearest
texel* lies in that region (one masked, vectorised call per region and light). Sampling is therefore "nearest":
a sample is made of exactly one material, and region borders are texel edges.

Default (:func:`measured_scene`): 4 regions (two-layer-silver, violet-rubber, nickel, red-fabric2), a 48×24
UV sphere, 12 views of 96×96 px on two orbit rings (15° and 50°), 2 flash point lights per view (irradiance 1 at
the centre, 20° off the camera), 64² texels, the ideal camera (noise-free linear EXR, no clipping).

Ground truth
------------
:class:`capture.dataset.GroundTruth` needs maps of one model; a measured material has no maps, and a scene of
four materials is no single model. So the dataset is written with ``gt=None`` and the truth goes into
``meta["measured"]``: the material per region id, the region map (``[T, T]`` ids, row 0 = top = v = 1, as nested
lists), the decoder options and the attribution. :func:`read_truth` reads it back.

Benchmark (:func:`capture_benchmark`)
-------------------------------------
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
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor

import materials
from renderer.gbuffer import render_gbuffer
from renderer.shading import prepare
from renderer.texture import texel_centers

from ..dataset import View, load_dataset, write_dataset
from .scenes import SyntheticConfig, build_cameras, build_lights, build_mesh

__all__ = [
    "DEFAULT_MATERIALS", "MeasuredSceneConfig", "MeasuredSceneError", "region_map", "measured_scene",
    "render_measured", "make_measured_scene", "read_truth", "capture_benchmark", "benchmark_table",
]

#: The four materials of Nielsen et al.'s Figure 1, one region each by default.
DEFAULT_MATERIALS = ("two-layer-silver", "violet-rubber", "nickel", "red-fabric2")
ATTRIBUTION = ("NBRDF fits (Sztrajman et al., CGF 2021) of the MERL BRDFs (Matusik et al. 2003; CC-BY-SA-4.0, "
               "\"Created by Mitsubishi Electric Research Laboratories (MERL), 2003, 2007, 2023\")")


class MeasuredSceneError(ValueError):
    """An invalid measured-scene configuration or dataset (the message names the field and the fix)."""


@dataclass
class MeasuredSceneConfig:
    """A capture of an object whose regions are measured materials (module docstring).

    Attributes:
        materials: MERL names, one region each (ids 1..K in this order); 1 to 255 names.
        mesh, mesh_options, n_views, image_size, texture_size, camera_rig, elevations, fov_y_deg, distance,
            light_rig, n_lights, light_offset_deg, light_irradiance, shadows, seed: as in
            :class:`capture.synth.SyntheticConfig` (pixels, degrees, world units, W/m²).
        max_theta_deg: the decoder's mask (90 = none; 80 drops MERL's unreliable grazing angles).
        symmetric: evaluate the decoder reciprocally (mean of φ_d and π − φ_d).
    """

    materials: tuple[str, ...] = DEFAULT_MATERIALS
    mesh: str = "uv_sphere"
    mesh_options: dict = field(default_factory=lambda: {"segments": 48, "rings": 24})
    n_views: int = 12
    image_size: int | tuple[int, int] = 96
    texture_size: int | tuple[int, int] = 64
    camera_rig: str = "orbit"
    elevations: tuple[float, ...] = (15.0, 50.0)
    fov_y_deg: float = 40.0
    distance: float | None = None
    light_rig: str = "flash"
    n_lights: int = 2
    light_offset_deg: float = 20.0
    light_irradiance: float = 1.0
    shadows: bool = True
    seed: int = 0
    max_theta_deg: float = 90.0
    symmetric: bool = False

    def __post_init__(self):
        if isinstance(self.materials, str):
            self.materials = (self.materials,)
        self.materials = tuple(self.materials)
        if not 1 <= len(self.materials) <= 255 or not all(isinstance(m, str) for m in self.materials):
            raise MeasuredSceneError(f"materials must be 1 to 255 MERL names, got {self.materials!r}")
        if len(set(self.materials)) != len(self.materials):
            raise MeasuredSceneError(f"materials must be distinct (one region each), got {self.materials!r}")
        self.models()  # unknown names / missing weights fail here, before any rendering
        self.geometry()  # and so do bad geometry fields (SyntheticError names the field)

    def geometry(self) -> SyntheticConfig:
        """The :class:`~capture.synth.SyntheticConfig` of the mesh/camera/light fields (model: placeholder)."""
        return SyntheticConfig(
            mesh=self.mesh, mesh_options=dict(self.mesh_options), n_views=self.n_views, image_size=self.image_size,
            texture_size=self.texture_size, model="lambert", camera_rig=self.camera_rig,
            elevations=self.elevations, fov_y_deg=self.fov_y_deg, distance=self.distance, light_rig=self.light_rig,
            n_lights=self.n_lights, light_offset_deg=self.light_offset_deg,
            light_irradiance=self.light_irradiance, sampling="nearest", shadows=self.shadows, seed=self.seed)

    def models(self) -> list[materials.Model]:
        """One ``measured`` model per material (raises :class:`MeasuredSceneError` naming an unknown one)."""
        try:
            return [materials.get("measured", material=m, max_theta_deg=self.max_theta_deg,
                                  symmetric=self.symmetric) for m in self.materials]
        except FileNotFoundError as exc:
            raise MeasuredSceneError(str(exc)) from None
        except ValueError as exc:
            raise MeasuredSceneError(f"materials: {exc}") from None


def measured_scene(**overrides) -> MeasuredSceneConfig:
    """The default measured scene (module docstring); ``overrides`` replace any field."""
    return MeasuredSceneConfig(**overrides)


def region_map(n_regions: int, size: int | tuple[int, int]) -> Tensor:
    """Region ids ``[H, W]`` int64 in 1..K: K vertical stripes of equal width in u (texel centres).

    Args:
        n_regions: K ≥ 1.
        size: ``T`` or ``(W, H)`` texels.
    """
    if isinstance(n_regions, bool) or not isinstance(n_regions, int) or n_regions < 1:
        raise MeasuredSceneError(f"region_map: n_regions must be a positive integer, got {n_regions!r}")
    W, H = (size, size) if isinstance(size, int) else tuple(size)
    if min(W, H) < 1:
        raise MeasuredSceneError(f"region_map: size must be positive, got {size!r}")
    u = texel_centers(H, W, dtype=torch.float64)[..., 0]
    return torch.clamp(torch.floor(u * n_regions), 0, n_regions - 1).long() + 1


def render_measured(prepared, regions: Tensor, models: Sequence[materials.Model]) -> Tensor:
    """Radiance ``[N, 3]`` of one prepared view (0 where no light reaches), W/(m²·sr) for W/m² irradiance.

    Args:
        prepared: :class:`renderer.shading.Prepared` of the view.
        regions: ``[H, W]`` ids 1..K; the sample's material is ``models[id − 1]`` at its nearest texel.
        models: K BRDF models without parameters (e.g. ``measured``), each evaluated once per light on the
            samples of its region (a masked, vectorised call).
    """
    if not isinstance(regions, Tensor) or regions.dim() != 2 or regions.is_floating_point():
        raise MeasuredSceneError("render_measured: regions must be an integer tensor [H, W]")
    K = len(models)
    if int(regions.min()) < 1 or int(regions.max()) > K:
        raise MeasuredSceneError(f"render_measured: region ids must lie in 1..{K} (one per model), got "
                                 f"{int(regions.min())}..{int(regions.max())}")
    H, W = regions.shape
    tex, _ = prepared.texels(H, W, "nearest")
    rid = regions.reshape(-1).to(tex.device)[tex]  # [S] region of each kept sample
    dtype, dev = prepared.n.dtype, prepared.n.device
    out = torch.zeros(prepared.n_samples, 3, dtype=dtype, device=dev)
    for term in prepared.lights:
        r = rid[term.local]
        for k, model in enumerate(models):
            sel = torch.nonzero(r == k + 1).squeeze(-1)
            if len(sel) == 0:
                continue
            f = model.cosine_brdf(term.angles[sel], {})
            out = out.index_add(0, term.index[sel], term.irradiance[sel] * f)
    return out


def make_measured_scene(config: MeasuredSceneConfig | None = None, out_dir=None, *, overwrite: bool = False,
                        views: Sequence[int] | None = None) -> Path:
    """Render ``config`` (default :func:`measured_scene`) and write it as a dataset folder; return the folder.

    Args:
        config: the scene.
        out_dir: the dataset folder (required).
        overwrite: replace an existing folder.
        views: indices of the views to write (default all) — e.g. the training views of a held-out split.
    Returns:
        The folder. ``gt`` is absent; ``meta["measured"]`` holds the truth (module docstring).
    """
    config = config or measured_scene()
    if not isinstance(config, MeasuredSceneConfig):
        raise MeasuredSceneError(f"config must be a MeasuredSceneConfig, got {type(config).__name__}")
    if out_dir is None:
        raise MeasuredSceneError("make_measured_scene: out_dir is required (the dataset folder to write)")
    t0 = time.perf_counter()
    images, all_views, preps, mesh, regions = _render(config)
    keep = list(range(len(all_views))) if views is None else [int(i) for i in views]
    if not keep or any(not 0 <= i < len(all_views) for i in keep):
        raise MeasuredSceneError(f"views must be indices in 0..{len(all_views) - 1}, got {views!r}")
    meta = {
        "generator": "capture.synth.make_measured_scene",
        "config": asdict(config),
        "views_written": keep,
        "measured": {
            "materials": {str(k + 1): m for k, m in enumerate(config.materials)},
            "regions": regions,
            "sampling": "nearest",
            "decoder": {"model": "measured", "max_theta_deg": config.max_theta_deg, "symmetric": config.symmetric},
            "attribution": ATTRIBUTION,
        },
        "coverage_per_view": [preps[i].gbuffer.coverage for i in keep],
        "seconds": {"build_and_render": time.perf_counter() - t0},
    }
    return write_dataset(out_dir, mesh, [all_views[i] for i in keep], [images[i] for i in keep], encoding="linear",
                         gt=None, meta=meta, overwrite=overwrite)


def _render(config: MeasuredSceneConfig):
    geo = config.geometry()
    mesh = build_mesh(geo.mesh, geo.mesh_options)
    cams, rots = build_cameras(geo, mesh)
    lights = build_lights(geo, mesh, cams, rots)
    models = config.models()
    regions = region_map(len(config.materials), geo.texture_size)
    views = [View(c, ls, 1.0) for c, ls in zip(cams, lights, strict=True)]
    images, preps = [], []
    with torch.no_grad():
        for view in views:
            g = render_gbuffer(mesh, view.camera, 1)
            prep = prepare(g, mesh, view.lights, shadows=config.shadows)
            images.append(g.to_image(render_measured(prep, regions, models)))
            preps.append(prep)
    return images, views, preps, mesh, regions


def read_truth(dataset) -> tuple[Tensor, dict[int, str]]:
    """``(regions [T, T] int64, {region id: material})`` of a dataset written by :func:`make_measured_scene`.

    Args:
        dataset: a folder or a loaded :class:`capture.dataset.Dataset`.
    """
    ds = load_dataset(dataset) if isinstance(dataset, (str, Path)) else dataset
    info = (ds.meta or {}).get("measured") if hasattr(ds, "meta") else None
    if not isinstance(info, Mapping) or "regions" not in info or "materials" not in info:
        raise MeasuredSceneError("dataset has no meta.measured block (regions + materials); write it with "
                                 "capture.synth.make_measured_scene")
    return torch.tensor(info["regions"], dtype=torch.long), {int(k): v for k, v in info["materials"].items()}


# -- benchmark --------------------------------------------------------------------------------
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
    from renderer.imageio import read_exr, read_png
    from renderer.shading import shade

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
        images, views, preps, mesh, regions = _render(config)
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
    from renderer.imageio import read_exr

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
