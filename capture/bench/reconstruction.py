"""Benchmarks of the reconstruction: end-to-end time against map error of the fast path, its variants and Adam on
synthetic scenes, with sweeps over texture resolution and number of materials, and of photos another renderer made.

``scripts/benchmark.py reconstruction`` runs :func:`run_reconstruction_benchmark`, ``scripts/benchmark.py
independent`` :func:`run_independent_benchmark`; with ``--out`` the tables go into the generated sections of
``docs/benchmarks.md``.
"""

from __future__ import annotations

import time

import torch

from renderer.device import resolve_device

from .timing import growth_exponent, machine_description, peak_rss_mib


def reconstruction_run(dataset, model: str = "ggx-lambert", solver: str = "fast", threads: int | None = None,
                       **options) -> dict:
    """Reconstruct ``dataset`` once into a temporary folder and return the numbers of a benchmark row.

    Returns a dict: ``seconds`` (end to end), ``times`` (per stage), ``rmse_observed`` /
    ``rmse_observable`` / ``rmse_determined`` (per map, fitted values; the last on the texels the photos determine
    at the true maps, :func:`capture.metrics.determined_at_truth`, empty when another model rendered the
    photos), ``observable_fraction`` (per map), ``fit`` (solver
    info without long lists), ``skipped``, ``peak_rss_mib`` (process peak so far), ``threads``. The fit runs on the
    CPU unless ``device`` is among ``options`` (the CPU benchmark tables say so).
    """
    import tempfile
    from pathlib import Path

    from ..reconstruct import reconstruct

    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(int(threads))
    try:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            rep = reconstruct(dataset, model=model, out_dir=Path(d) / "out", solver=solver, progress=False,
                              **{"device": "cpu", **options})
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
        "samples": rep.samples, "peak_rss_mib": peak_rss_mib(),
    }


def plot_reconstruction_pareto(rows: list[dict], out_png, caption: str = "") -> None:
    """Time against error of reconstruction rows: one panel per map, x = end-to-end seconds, y = RMSE on the
    texels where the map is observable (filled markers) and on all observed texels (open markers), one colour
    per solver setting, one marker shape per light rig."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import save_figure

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

    from ..synth import default_scene, make_synthetic

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

    from ..reconstruct import static_lights
    from ..report import replace_section
    from ..synth import default_scene, make_synthetic, small_scene

    rows = []
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        for rig in rigs:
            if scene == "default":
                cfg = default_scene(light_rig=rig) if rig != "fixed" else default_scene(light_rig="fixed",
                                                                                         light_offset_deg=45.0)
            else:
                cfg = small_scene("ggx-lambert", image_size=96, texture_size=32, n_views=6, light_rig=rig)
            ds = make_synthetic(cfg, Path(d) / f"ds_{rig}")
            from ..dataset import load_dataset

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
    "texel set (docs/image-formation.md, \"What to expect\"), albedo / f0 / roughness r / roughness α; in brackets the "
    "χ² of the true maps through the same image formation (the floor the photos and the fit's pixel model leave). "
    "Regenerate: "
    "`python scripts/make_independent_fixtures.py --out DIR --full --spp 64`, then `python scripts/benchmark.py "
    "independent --datasets tests/fixtures/mitsuba/* DIR/* --out docs/benchmarks.md`.\n\n")


def run_independent_benchmark(datasets, out: str | None = None, threads: int | None = None,
                              device: str = "cpu") -> str:
    """Reconstruct datasets whose photos another renderer made (docs/independent-renders.md) with the model that
    rendered them, fitting pixel centres and pixel footprints, and tabulate time, χ², worst view and the RMSE per
    texel set of :func:`capture.reconstruct.reconstruct`'s report (docs/image-formation.md, "What to expect").
    Each dataset's ground-truth model is the model fitted (the benchmark asks how well the fit recovers the maps
    of a known model; ``auto`` is judged elsewhere). ``device``: where the fits run (:mod:`renderer.device`)."""
    import tempfile
    from pathlib import Path

    from ..dataset import load_dataset, model_label
    from ..reconstruct import reconstruct
    from ..report import replace_section

    dev = str(resolve_device(device))
    rows = [f"Machine: {machine_description(dev, threads)}; fits on `{dev}`", "",
            "| scene | fit | time | χ² / residual (true maps) | worst view | well lit | well lit, ≥ 1 pixel "
            "| well lit, highlight | well lit, visible highlight |",
            "|---|---|---|---|---|---|---|---|---|"]
    for path in datasets:
        ds = load_dataset(path, check_images=False)
        model = model_label(ds.gt.model)
        for fp in (False, True):
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                r = reconstruct(path, model=model, out_dir=f"{tmp}/r", progress=False, footprint=fp,
                                threads=threads, device=dev)
                dt = time.perf_counter() - t0
            sets = r.errors.get("maps_by_texel_set", {})

            def cell(name, sets=sets):
                v = sets.get(name)
                if v and not v["texels"]:
                    return "no texel"
                return " / ".join(f"{e:.4f}" for n, e in v.items() if n != "texels") if v else "–"

            truth = f" ({r.errors['chi2_at_truth']:.3g})" if "chi2_at_truth" in r.errors else ""
            size = (f"{len(ds.views)} × {ds.views[0].camera.width}², "
                    f"{int(next(iter(ds.gt.maps.values())).shape[0])}² maps")
            rows.append(f"| {Path(path).name}, {size} | {'footprints' if fp else 'pixel centres'} | {dt:.1f} s | "
                        f"{r.fit['chi2_per_residual']:.3g}{truth} | {min(v['psnr'] for v in r.views):.1f} dB | "
                        f"{cell('well_lit')} | {cell('well_lit_pixel_sized')} | {cell('well_lit_highlight')} | "
                        f"{cell('well_lit_visible_highlight')} |")
            print(rows[-1], flush=True)
    text = "\n".join(rows) + "\n"
    if out:
        replace_section(Path(out), "independent", "## Photos another renderer made\n\n" + INDEPENDENT_INTRO + text)
    return text
