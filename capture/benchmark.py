"""Benchmarks: model throughput and accuracy against slow references (issue 2/6).

``scripts/benchmark.py models`` calls :func:`benchmark_models`; results are written to
``docs/benchmarks.md`` by the script. Timings state the machine they were taken on
(:func:`machine_description`).
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch

import materials
from materials import Angles
from materials.model import Model


def machine_description(device: str = "cpu", threads: int | None = None) -> str:
    """One line naming the machine: CPU model and core count, torch version, torch threads (``threads``, default
    the current setting), and the GPU if used."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    n_threads = threads or torch.get_num_threads()
    desc = f"{cpu}, {os.cpu_count()} logical cores, torch {torch.__version__}, {n_threads} threads"
    if device.startswith("cuda") and torch.cuda.is_available():
        desc += f", GPU {torch.cuda.get_device_name()}"
    return desc


def random_front_angles(n: int, dtype=torch.float32, device="cpu", seed: int = 0) -> Angles:
    """``n`` random configurations with light and viewer in the upper hemisphere (cosine-weighted)."""
    gen = torch.Generator().manual_seed(seed)

    def hemi():
        u1, u2 = torch.rand(n, generator=gen, dtype=torch.float64), torch.rand(n, generator=gen, dtype=torch.float64)
        r, phi = torch.sqrt(u1), 2 * math.pi * u2
        return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1 - u1).clamp_min(1e-6))], -1)

    nrm = torch.zeros(n, 3, dtype=torch.float64)
    nrm[:, 2] = 1
    return Angles.from_vectors(nrm, hemi(), hemi()).to(device=device, dtype=dtype)


def random_params(model: Model, n: int, dtype=torch.float32, device="cpu", seed: int = 1) -> dict[str, torch.Tensor]:
    """Per-sample parameters uniform over each parameter's range (capped at 1 for unbounded ones)."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for s in model.params:
        hi = min(s.high, max(1.0, s.low + 1.0))
        out[s.name] = (s.low + (hi - s.low) * torch.rand(n, s.channels, generator=gen)).to(device=device, dtype=dtype)
    return out


@dataclass
class Throughput:
    model: str
    device: str
    samples: int
    forward_per_s: float
    forward_backward_per_s: float
    compiled: bool = False


def _time(fn: Callable[[], None], repeats: int, device: str) -> float:
    fn()  # warm-up
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best


def model_throughput(
    model: Model, n: int = 1 << 20, device: str = "cpu", repeats: int = 3, compile: bool = False
) -> Throughput:
    """Samples per second of ``model.cosine_brdf`` forward, and forward + backward to every parameter.

    Geometry (the Angles) is precomputed, as in the pipeline; the parameters are per-sample
    tensors, as sampled from maps. ``compile=True`` wraps the evaluation in ``torch.compile``.
    """
    g = random_front_angles(n, device=device)
    p = random_params(model, n, device=device)

    def evaluate(nl, nv, nh, lh, lv, *vals):
        return model.cosine_brdf(Angles(nl, nv, nh, lh, lv), dict(zip(p.keys(), vals, strict=True)))

    fn = torch.compile(evaluate, dynamic=False) if compile else evaluate
    geo = (g.nl, g.nv, g.nh, g.lh, g.lv)

    def fwd():
        with torch.no_grad():
            fn(*geo, *p.values())

    leaves = [x.detach().clone().requires_grad_() for x in p.values()]
    # A model without parameters (the measured NBRDF) is differentiated with respect to the geometry.
    geo_b = geo if leaves else tuple(x.detach().clone().requires_grad_() for x in geo)

    def fwd_bwd():
        out = fn(*geo_b, *leaves)
        out.sum().backward()

    t_f = _time(fwd, repeats, device)
    t_fb = _time(fwd_bwd, repeats, device)
    return Throughput(model.name, device, n, n / t_f, n / t_fb, compile)


def benchmark_models(
    names: list[str] | None = None, n: int = 1 << 20, device: str = "cpu", compile_names: tuple[str, ...] = ()
) -> list[dict]:
    """Throughput of every registered model (or ``names``); those in ``compile_names`` also compiled."""
    rows = []
    for name in names or list(materials.available()):
        model = materials.get(name)
        rows.append(asdict(model_throughput(model, n=n, device=device)))
        if name in compile_names:
            rows.append(asdict(model_throughput(model, n=n, device=device, compile=True)))
    return rows


#: Models timed under torch.compile by default: the ones reconstruction uses most.
COMMON_MODELS = ("lambert", "ggx-lambert", "gotanda2012")


def run_models_benchmark(n: int = 1 << 20, device: str = "cpu", compile_names=None, out: str | None = None) -> str:
    """Throughput table of every model (markdown); written into ``out``'s ``models-throughput`` section."""
    from pathlib import Path

    from .report import replace_section

    names = list(materials.available())
    compile_names = tuple(c for c in (COMMON_MODELS if compile_names is None else compile_names) if c in names)
    rows = benchmark_models(names, n=n, device=device, compile_names=compile_names)
    lines = [
        f"Machine: {machine_description(device)}; device `{device}`; {n} samples per call, best of 3.",
        "",
        "| model | mode | forward (M samples/s) | forward+backward (M samples/s) |",
        "|---|---|---|---|",
    ]
    for r in rows:
        mode = "torch.compile" if r["compiled"] else "eager"
        fwd, fwd_bwd = r["forward_per_s"] / 1e6, r["forward_backward_per_s"] / 1e6
        lines.append(f"| `{r['model']}` | {mode} | {fwd:.1f} | {fwd_bwd:.1f} |")
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "models-throughput", "## Model throughput\n\n" + table)
    return table


# -- approximations against the exact forms they replace ---------------------------------------

#: (label, approximate model, reference model, fixed parameters). Errors are in π·f_r·cos units
#: (a Lambertian surface of albedo ρ reads ρ), over :func:`comparison_grid`.
APPROXIMATIONS: tuple[tuple[str, tuple, tuple, dict], ...] = (
    ("Fresnel: Schlick vs exact (GGX specular)", ("microfacet", {"F": "schlick"}),
     ("microfacet", {"F": "exact"}), {}),
    ("Fresnel: spherical Gaussian (2014 eq 3) vs exact", ("microfacet", {"F": "sg"}),
     ("microfacet", {"F": "exact"}), {}),
    ("Fresnel: Schüler lerp vs exact", ("microfacet", {"F": "schuler"}), ("microfacet", {"F": "exact"}), {}),
    ("Absorption: linear (2012 eq 3) vs exact (eq 2)", ("gotanda2012-layered", {"absorption": "linear"}),
     ("gotanda2012-layered", {"absorption": "exact"}), {"absorption": 0.05, "coat_ior": 1.5}),
    ("Bottom Fresnel: constant (eq 5) vs exact (eq 4)", ("gotanda2012-layered", {"bottom_fresnel": "constant"}),
     ("gotanda2012-layered", {"bottom_fresnel": "exact"}), {"absorption": 0.0, "coat_ior": 1.5}),
    ("Oren-Nayar: qualitative (eq 10/11) vs full 1994", ("oren-nayar-qualitative", {}), ("oren-nayar", {}), {}),
    ("Oren-Nayar: Gotanda simplified (eq 20) vs full", ("gotanda-on-simplified", {}), ("oren-nayar", {}), {}),
    ("Oren-Nayar: Gotanda improved (eq 25) vs full", ("gotanda-on-improved", {}), ("oren-nayar", {}), {}),
    ("Oren-Nayar: Gotanda 2014 (eq 5) vs full", ("gotanda2014-on", {}), ("oren-nayar", {}), {}),
    ("Microfacet diffuse: fitted (2014 eq 8) vs numerical (eq 4)", ("microfacet-diffuse", {"method": "fitted"}),
     ("microfacet-diffuse", {"method": "numerical"}), {}),
    ("Schüler: optimized vs CookTorranceFull", ("schuler", {"variant": "optimized"}),
     ("schuler", {"variant": "cook-torrance-full"}), {}),
    ("Schüler: CookTorranceSimplified vs CookTorranceFull", ("schuler", {"variant": "cook-torrance-simplified"}),
     ("schuler", {"variant": "cook-torrance-full"}), {}),
    ("Schüler: KelemenSzirmayKalos vs CookTorranceFull", ("schuler", {"variant": "kelemen-szirmay-kalos"}),
     ("schuler", {"variant": "cook-torrance-full"}), {}),
    ("Blinn-Phong (Gotanda 2010) vs GGX + Lambert", ("gotanda2010", {}), ("ggx-lambert", {}), {}),
    ("Blinn-Phong normalisation: linear fit vs exact", ("gotanda2010", {}),
     ("gotanda2010", {"normalization": "exact"}), {}),
)


def comparison_grid(dtype=torch.float64, n_cos: int = 12, n_phi: int = 7, roughness=(0.3, 0.5, 0.7, 0.9)):
    """Dense grid: n·l, n·v ∈ (0, 1] (uniform in angle up to 85°), azimuth difference ∈ [0, π],
    roughness values; returns (Angles [M,1], roughness [M,1], labels (θ_l°, θ_v°, φ°, r) [M,4])."""
    th = torch.linspace(0.0, math.radians(85.0), n_cos, dtype=dtype)
    ph = torch.linspace(0.0, math.pi, n_phi, dtype=dtype)
    r = torch.tensor(roughness, dtype=dtype)
    tl, tv, pp, rr = (x.reshape(-1, 1) for x in torch.meshgrid(th, th, ph, r, indexing="ij"))
    nl, nv = torch.cos(tl), torch.cos(tv)
    lv = nl * nv + torch.sin(tl) * torch.sin(tv) * torch.cos(pp)
    labels = torch.cat([torch.rad2deg(tl), torch.rad2deg(tv), torch.rad2deg(pp), rr], -1)
    return Angles.from_cosines(nl, nv, lv), rr, labels


def _grid_params(model: Model, roughness: torch.Tensor, fixed: dict) -> dict:
    base = {"albedo": 0.8, "f0": 0.04, "specular": 0.2, "ior": 1.5, "mix": 0.5, "coat_roughness": 0.2}
    base.update(fixed)
    m = roughness.shape[0]
    out = {}
    for s in model.params:
        if s.name == "roughness":
            out[s.name] = roughness.expand(m, s.channels)
        else:
            out[s.name] = torch.full((m, s.channels), float(base.get(s.name, s.default)), dtype=roughness.dtype)
    return out


def approximation_errors(labels_only: tuple[str, ...] | None = None, n_cost: int = 1 << 18) -> list[dict]:
    """For each entry of :data:`APPROXIMATIONS`: mean and max |π f cos| error over the grid, where the
    max occurs, and the cost (forward, forward+backward samples/s) of the approximation and the reference."""
    g, rough, labels = comparison_grid()
    rows = []
    cost_cache: dict[str, Throughput] = {}
    for label, (an, ao), (rn, ro), fixed in APPROXIMATIONS:
        if labels_only and label not in labels_only:
            continue
        approx, ref = materials.get(an, **ao), materials.get(rn, **ro)
        with torch.no_grad():
            fa = approx.cosine_brdf(g, _grid_params(approx, rough, fixed))[..., 1] * math.pi
            fr = ref.cosine_brdf(g, _grid_params(ref, rough, fixed))[..., 1] * math.pi
        err = (fa - fr).abs()
        k = int(err.argmax())
        costs = []
        for m in (approx, ref):
            if m.name not in cost_cache:
                n = n_cost if "numerical" not in m.name else 1 << 11
                cost_cache[m.name] = model_throughput(m, n=n, repeats=2)
            costs.append(cost_cache[m.name])
        tl, tv, ph, r = labels[k].tolist()
        rows.append({
            "label": label, "approx": approx.name, "reference": ref.name,
            "mean_error": float(err.mean()), "max_error": float(err.max()),
            "ref_mean": float(fr.abs().mean()),
            "worst_at": f"θl={tl:.0f}°, θv={tv:.0f}°, φ={ph:.0f}°, r={r:.1f}",
            "approx_fwd": costs[0].forward_per_s, "approx_fb": costs[0].forward_backward_per_s,
            "ref_fwd": costs[1].forward_per_s, "ref_fb": costs[1].forward_backward_per_s,
        })
    return rows


def plot_pareto(rows: list[dict], out_png) -> None:
    """Cost (forward+backward samples/s) against mean error, one arrow from each reference to its
    approximation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import save_figure

    fig, ax = plt.subplots(figsize=(9, 6))
    for i, r in enumerate(rows):
        c = plt.cm.tab20(i % 20)
        ax.scatter([r["approx_fb"] / 1e6], [max(r["mean_error"], 1e-7)], color=c, s=30, zorder=3)
        ax.scatter([r["ref_fb"] / 1e6], [1e-7], color=c, marker="x", s=30, zorder=3)
        ax.annotate("", xy=(r["approx_fb"] / 1e6, max(r["mean_error"], 1e-7)), xytext=(r["ref_fb"] / 1e6, 1e-7),
                    arrowprops={"arrowstyle": "->", "color": c, "lw": 0.8})
        ax.annotate(r["label"], (r["approx_fb"] / 1e6, max(r["mean_error"], 1e-7)), fontsize=6, color=c,
                    xytext=(3, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward+backward throughput, M samples/s (CPU, eager)")
    ax.set_ylabel("mean |π f cos| error vs the exact form (x: reference, at 1e-7)")
    ax.set_title("Approximations of the papers: cost against error")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, out_png, dpi=80)


def run_approximation_benchmark(out: str | None = None, figure: str | None = None) -> str:
    """Table (markdown) of :func:`approximation_errors`; with ``out``/``figure`` also written to docs."""
    from pathlib import Path

    from .report import replace_section

    rows = approximation_errors()
    lines = [
        f"Machine: {machine_description()}. Errors in π·f_r·cos θ_l (a Lambertian surface of albedo ρ reads ρ) "
        "over θ_l, θ_v ∈ [0°, 85°] (12 each), φ ∈ [0°, 180°] (7), roughness ∈ {0.3, 0.5, 0.7, 0.9}; albedo 0.8, "
        "f0 0.04. Cost: eager CPU throughput, M samples/s.",
        "",
        "| approximation | mean err | max err | worst at | mean of reference | approx fwd / fwd+bwd | "
        "reference fwd / fwd+bwd |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['mean_error']:.2e} | {r['max_error']:.2e} | {r['worst_at']} | {r['ref_mean']:.3f} | "
            f"{r['approx_fwd'] / 1e6:.2f} / {r['approx_fb'] / 1e6:.2f} | "
            f"{r['ref_fwd'] / 1e6:.2f} / {r['ref_fb'] / 1e6:.2f} |"
        )
    table = "\n".join(lines)
    if figure:
        plot_pareto(rows, figure)
        rel = Path(figure).name if out is None else Path(figure).relative_to(Path(out).parent)
        table += f"\n\n![cost against error]({rel})"
    if out:
        replace_section(Path(out), "approximations", "## Approximations: cost against error\n\n" + table)
    return table


# -- reconstruction: time against error (issue 4) ------------------------------------------------


def _peak_rss_mib() -> float:
    """Peak resident memory of this process so far (MiB), from ``resource.getrusage``."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def reconstruction_run(dataset, model: str = "ggx-lambert", solver: str = "fast", threads: int | None = None,
                       **options) -> dict:
    """Reconstruct ``dataset`` once into a temporary folder and return the numbers of a benchmark row.

    Returns a dict: ``seconds`` (end to end), ``times`` (per stage), ``rmse_observed`` /
    ``rmse_observable`` / ``rmse_determined`` (per map, fitted values; the last on the texels the photos determine
    at the true maps, :func:`capture.metrics.determined_at_truth`, empty when another model rendered the
    photos), ``observable_fraction`` (per map), ``fit`` (solver
    info without long lists), ``skipped``, ``peak_rss_mib`` (process peak so far), ``threads``.
    """
    import tempfile
    from pathlib import Path

    from .reconstruct import reconstruct

    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            rep = reconstruct(dataset, model=model, out_dir=Path(d) / "out", solver=solver, progress=False, **options)
            seconds = time.perf_counter() - t0
    finally:
        torch.set_num_threads(old)
    fit = {k: v for k, v in rep.fit.items() if not isinstance(v, (list, dict)) or k == "observable_fraction"}
    return {
        "seconds": seconds, "times": rep.times, "threads": threads or old,
        "rmse_observed": {k: v["rmse"] for k, v in rep.errors.get("maps", {}).items()},
        "rmse_observable": {k: v["rmse"] for k, v in rep.errors.get("maps_observable", {}).items()},
        "rmse_determined": {k: v["rmse"] for k, v in rep.errors.get("maps_determined_at_truth", {}).items()},
        "observable_fraction": rep.coverage.get("observable_fraction", {}),
        "observed_texels": rep.coverage.get("observed"), "fit": fit, "skipped": rep.skipped,
        "samples": rep.samples, "peak_rss_mib": _peak_rss_mib(),
    }


def plot_reconstruction_pareto(rows: list[dict], out_png, caption: str = "") -> None:
    """Time against error of reconstruction rows: one panel per map, x = end-to-end seconds, y = RMSE on the
    texels where the map is observable (filled markers) and on all observed texels (open markers), one colour
    per solver setting, one marker shape per light rig."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import save_figure

    maps = ("albedo", "f0", "roughness")
    labels = list(dict.fromkeys(r["label"] for r in rows))
    rigs = list(dict.fromkeys(r["rig"] for r in rows))
    colours = plt.get_cmap("tab10")
    shapes = "osD^v"
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6), squeeze=False)
    for ax, m in zip(axes[0], maps, strict=True):
        for r in rows:
            c = colours(labels.index(r["label"]) % 10)
            mk = shapes[rigs.index(r["rig"]) % len(shapes)]
            ax.plot(r["seconds"], r["rmse_observable"].get(m, float("nan")), mk, color=c, ms=6)
            ax.plot(r["seconds"], r["rmse_observed"].get(m, float("nan")), mk, mfc="none", color=c, ms=6)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("end-to-end seconds")
        ax.set_title(m, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    axes[0][0].set_ylabel("RMSE")
    handles = [plt.Line2D([], [], color=colours(i % 10), marker="o", ls="", label=lab) for i, lab in enumerate(labels)]
    handles += [plt.Line2D([], [], color="k", marker=shapes[i % len(shapes)], ls="", mfc="none", label=f"rig {rig}")
                for i, rig in enumerate(rigs)]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), fontsize=7, frameon=False)
    fig.suptitle((caption or "Reconstruction: time against error")
                 + "\nRMSE on texels where the map is observable (filled) and on all observed texels (open)",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0.12, 1, 0.97))
    save_figure(fig, out_png, dpi=90)


#: Sweeps of the reconstruction benchmark: (label, SyntheticConfig field, values) on the default scene, flash rig.
RECONSTRUCTION_SWEEPS = (
    ("texture resolution T (T² maps)", "texture_size", (64, 128, 256)),
    ("number of materials", "materials", (1, 2, 3, 6)),
)


def reconstruction_sweeps(workdir: str | None = None, threads: int | None = None, sweeps=RECONSTRUCTION_SWEEPS,
                          base=None) -> list[str]:
    """Markdown lines: end-to-end time and error of the fast path as one scene axis varies (fitted growth exponent
    of the time, and of the solve stage alone)."""
    import tempfile
    from dataclasses import replace
    from pathlib import Path

    from .scaling import growth_exponent
    from .synth import default_scene, make_synthetic

    base = base or default_scene()
    lines = ["| axis | value | s (solve s) | albedo RMSE obs. / obsv. | f0 RMSE obs. / obsv. | roughness RMSE obs. / "
             "obsv. | observed texels |", "|---|---|---|---|---|---|---|"]
    exps = []
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        for label, field_name, values in sweeps:
            secs, solve = [], []
            for v in values:
                ds = make_synthetic(replace(base, **{field_name: v}), Path(d) / f"{field_name}_{v}", overwrite=True)
                r = reconstruction_run(ds, threads=threads)
                secs.append(r["seconds"])
                solve.append(r["times"].get("solve", float("nan")))
                cells = " | ".join(f"{r['rmse_observed'].get(m, float('nan')):.4f} / "
                                   f"{r['rmse_observable'].get(m, float('nan')):.4f}"
                                   for m in ("albedo", "f0", "roughness"))
                lines.append(f"| {label} | {v} | {r['seconds']:.1f} ({solve[-1]:.1f}) | {cells} | "
                             f"{r['observed_texels']} |")
            xs = [float(v) ** 2 if field_name == "texture_size" else float(v) for v in values]
            per = "texels T²" if field_name == "texture_size" else "materials"
            exps.append(f"time ∝ ({per})^k: k = {growth_exponent(xs, secs):.2f} end to end, "
                        f"{growth_exponent(xs, solve):.2f} for the solve")
    return lines + [""] + [f"- {label}: {e}" for (label, _, _), e in zip(sweeps, exps, strict=True)]


def run_reconstruction_benchmark(out: str | None = None, scene: str = "default", rigs=("flash", "fixed"),
                                 threads: int | None = None, adam=((0.05, 200), (0.02, 500)),
                                 fast_variants: bool = True, workdir: str | None = None, figure: str | None = None,
                                 sweeps: bool = True) -> str:
    """Time against error of the reconstruction (markdown), written into ``out``'s
    ``reconstruction`` section when given.

    ``scene="default"``: :func:`capture.synth.default_scene` (16 views of 256², 256² maps,
    GGX + Lambert, 2 point lights, bilinear, noise-free), once per light rig in ``rigs``;
    ``scene="small"``: :func:`capture.synth.small_scene` (96 px, 6 views, 32² maps). Rows: the fast
    path (default options), the fast path without reflectance sharing, without the joint bilinear
    refinement, with a coarse grid and with pooled proposals flipped from their default (on for static lights,
    :func:`capture.reconstruct.static_lights`) (``fast_variants``), and Adam for each
    ``(lr, iterations)`` of ``adam`` (bilinear sampling). Each row: end-to-end seconds, per-map RMSE on
    observed texels, on texels where the map is observable (judged at the estimate) and on those the photos
    determine at the true maps, observable fractions, and the process's peak
    memory so far. ``figure``: write the Pareto plot there (:func:`plot_reconstruction_pareto`). ``sweeps``
    (default scene only): the fast path over texture resolution and number of materials
    (:func:`reconstruction_sweeps`).
    """
    import tempfile
    from pathlib import Path

    from .reconstruct import static_lights
    from .report import replace_section
    from .synth import default_scene, make_synthetic, small_scene

    rows = []
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        for rig in rigs:
            if scene == "default":
                cfg = default_scene(light_rig=rig) if rig != "fixed" else default_scene(light_rig="fixed",
                                                                                         light_offset_deg=45.0)
            else:
                cfg = small_scene("ggx-lambert", image_size=96, texture_size=32, n_views=6, light_rig=rig)
            ds = make_synthetic(cfg, Path(d) / f"ds_{rig}")
            from .dataset import load_dataset

            loaded = load_dataset(ds)
            cov = loaded.meta.get("highlight_coverage", {}).get("coverage")
            variants = [("fast", "fast", {})]
            if fast_variants:
                # the other side of reconstruct's pooled-proposal default (on for static lights only)
                pooled = ("fast, without pooled proposals", "fast", {"pooled": 0}) if static_lights(loaded.views)[0] \
                    else ("fast, pooled proposals (4 × 4 tiles)", "fast", {"pooled": 4})
                variants += [("fast, no reflectance sharing", "fast", {"share": False}),
                             ("fast, no joint refinement (nor sharing)", "fast", {"joint_iterations": 0}),
                             ("fast, coarse grid 8 + 6 refinements", "fast", {"grid": 8, "refine": 6}), pooled]
            variants += [(f"adam lr {lr} × {it}", "adam", {"lr": lr, "iterations": it}) for lr, it in adam]
            for label, solver, opts in variants:
                r = reconstruction_run(ds, solver=solver, threads=threads, **opts)
                rows.append({"rig": rig, "highlight_coverage": cov, "label": label, **r})
    used = threads or torch.get_num_threads()
    lines = [f"Machine: {machine_description(threads=used)} (the reconstructions' setting); scene `{scene}`.", "",
             "RMSE per map on observed texels (obs.), on those where the map is observable, judged at the estimate "
             "(obsv.), and on those the photos determine at the true maps (det.; the same posterior test at the "
             "truth, a set no estimate chooses).", "",
             "| rig (highlight cov.) | solver | s | albedo obs. / obsv. / det. | f0 obs. / obsv. / det. | roughness "
             "obs. / obsv. / det. | observable % (a/f0/r) | peak MiB |", "|---|---|---|---|---|---|---|---|"]
    nan = float("nan")
    for r in rows:
        def cell(k, r=r):
            return (f"{r['rmse_observed'].get(k, nan):.4f} / {r['rmse_observable'].get(k, nan):.4f} / "
                    f"{r['rmse_determined'].get(k, nan):.4f}")
        fr = r["observable_fraction"]
        lines.append(f"| {r['rig']} ({(r['highlight_coverage'] or 0):.0%}) | {r['label']} | {r['seconds']:.1f} | "
                     f"{cell('albedo')} | {cell('f0')} | {cell('roughness')} | "
                     f"{fr.get('albedo', 0):.0%} / {fr.get('f0', 0):.0%} / {fr.get('roughness', 0):.0%} | "
                     f"{r['peak_rss_mib']:.0f} |")
    lines += ["", "Stage times of the first fast row (s): " + ", ".join(
        f"{k} {v:.1f}" for k, v in rows[0]["times"].items()) if rows else ""]
    fit0 = rows[0]["fit"] if rows else {}
    lines.append("Solver internals of that row (s): " + ", ".join(
        f"{k} {fit0[k]:.1f}" for k in ("grid_s", "lm_s", "share_s", "joint_s", "posterior_s") if k in fit0))
    if figure and rows:
        plot_reconstruction_pareto(rows, figure, f"Reconstruction of the {scene} scene: time against error "
                                   f"({machine_description(threads=used)})")
        rel = Path(figure).name if out is None else "figures/" + Path(figure).name
        lines += ["", f"![reconstruction: time against error]({rel})"]
    if sweeps and scene == "default":
        lines += ["", "### Sweeps (fast path, default scene with the flash rig, one axis varied)", ""]
        lines += reconstruction_sweeps(workdir, threads)
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "reconstruction", "## Reconstruction: time against error\n\n" + table)
    return table


#: The lines above the independent benchmark's table in docs/benchmarks.md: what it measures and how to regenerate it.
INDEPENDENT_INTRO = (
    "Reconstruction of Mitsuba 3 renders (docs/independent-renders.md) with the model that rendered them: RMSE per "
    "texel set (docs/image-formation.md, \"What to expect\"), albedo / f0 / roughness r / roughness α. Regenerate: "
    "`python scripts/make_independent_fixtures.py --out DIR --full --spp 64`, then `python scripts/benchmark.py "
    "independent --datasets tests/fixtures/mitsuba/* DIR/* --out docs/benchmarks.md`.\n\n")


def run_independent_benchmark(datasets, out: str | None = None, threads: int | None = None) -> str:
    """Reconstruct datasets whose photos another renderer made (docs/independent-renders.md) with the model that
    rendered them, fitting pixel centres and pixel footprints, and tabulate time, χ², worst view and the RMSE per
    texel set of :func:`capture.reconstruct.reconstruct`'s report (docs/image-formation.md, "What to expect").
    Each dataset's ground-truth model is the model fitted (the benchmark asks how well the fit recovers the maps
    of a known model; ``auto`` is judged elsewhere)."""
    import tempfile
    from pathlib import Path

    from capture.dataset import load_dataset, model_label
    from capture.reconstruct import reconstruct

    from .report import replace_section

    rows = [f"Machine: {machine_description('cpu', threads)}", "",
            "| scene | fit | time | χ² / residual | worst view | well lit | well lit, ≥ 1 pixel "
            "| well lit, highlight | well lit, visible highlight |",
            "|---|---|---|---|---|---|---|---|---|"]
    for path in datasets:
        ds = load_dataset(path, check_images=False)
        model = model_label(ds.gt.model)
        for fp in (False, True):
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                r = reconstruct(path, model=model, out_dir=f"{tmp}/r", progress=False, footprint=fp,
                                threads=threads)
                dt = time.perf_counter() - t0
            sets = r.errors.get("maps_by_texel_set", {})

            def cell(name, sets=sets):
                v = sets.get(name)
                if v and not v["texels"]:
                    return "no texel"
                return " / ".join(f"{e:.4f}" for n, e in v.items() if n != "texels") if v else "–"

            size = (f"{len(ds.views)} × {ds.views[0].camera.width}², "
                    f"{int(next(iter(ds.gt.maps.values())).shape[0])}² maps")
            rows.append(f"| {Path(path).name}, {size} | {'footprints' if fp else 'pixel centres'} | {dt:.1f} s | "
                        f"{r.fit['chi2_per_residual']:.3g} | {min(v['psnr'] for v in r.views):.1f} dB | "
                        f"{cell('well_lit')} | {cell('well_lit_pixel_sized')} | {cell('well_lit_highlight')} | "
                        f"{cell('well_lit_visible_highlight')} |")
            print(rows[-1], flush=True)
    text = "\n".join(rows) + "\n"
    if out:
        replace_section(Path(out), "independent", "## Photos another renderer made\n\n" + INDEPENDENT_INTRO + text)
    return text
