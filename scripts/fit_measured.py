#!/usr/bin/env python
"""Fit every registered analytic model to the NBRDF fits of the MERL materials; write docs/measured-fits.md.

    python scripts/fit_measured.py --materials all --models all --out docs/ --figures docs/figures/

Writes ``<out>/measured-fits.md`` (error table per model per material, a per-model summary in the manner of
Ngan et al. 2005, the Nielsen comparison) and, for the figure materials among those fitted, one PNG per material
under ``--figures``: spheres rendered with the measured BRDF and each fitted model, lit by a glancing (NE) and a
grazing (SW) directional light as in Nielsen et al.'s Figure 1. The spheres are analytic: orthographic view of a
unit sphere, one normal per pixel, no ray casting. Data: shared/data/merl (see materials/measured.py).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import materials  # noqa: E402
import materials.measured as measured  # noqa: E402
from capture import brdf_fit  # noqa: E402
from capture.plots import save_figure  # noqa: E402
from capture.report import atomic_write_text  # noqa: E402

#: Everything from this line on in an existing measured-fits.md is hand-written and kept when the file is re-generated.
KEEP_MARKER = "<!-- hand-written below: kept by scripts/fit_measured.py -->"
FIGURE_MATERIALS = ("two-layer-silver", "violet-rubber", "nickel", "red-fabric2")
#: Directional lights of the sphere figure (unit, world space, viewer along +z, y up): glancing from the NE,
#: grazing from the SW and slightly behind the sphere.
LIGHTS = (torch.tensor([1.0, 1.0, 1.0]) / math.sqrt(3.0), torch.tensor([-1.0, -1.0, -0.3]) / math.sqrt(2.09))


def sphere_image(model, params, size: int) -> torch.Tensor:
    """Radiance ``[size, size, 3]`` of an orthographic unit sphere (row 0 = top), E = 1 per light, 0 outside."""
    c = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-c, c, indexing="ij")
    r2 = x * x + y * y
    inside = r2 < 1
    n = torch.stack([x, y, torch.sqrt((1 - r2).clamp_min(0))], -1)[inside]
    v = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(n)
    p = {k: t.to(torch.float64) for k, t in params.items()}
    rad = sum(model.cosine_brdf(materials.Angles.from_vectors(n, l.to(n).expand_as(n), v), p) for l in LIGHTS)
    img = torch.zeros(size, size, 3, dtype=torch.float64)
    img[inside] = rad
    return img


def render_figure(material, fits, path: Path, size: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    target = materials.get("measured", material=material)
    panels = [("NBRDF fit of MERL", sphere_image(target, {}, size))]
    for name, (model, res) in fits.items():
        panels.append((f"{name}\nL1 {res.errors.rel_l1:.2f} ({res.errors.rel_l1_no_grazing:.2f})",
                       sphere_image(model, res.params, size)))
    lit = panels[0][1][panels[0][1].sum(-1) > 0]
    exposure = 1.0 / max(torch.quantile(lit.flatten(), 0.995).item(), 1e-6) if lit.numel() else 1.0
    cols = min(len(panels), 7)
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(1.45 * cols, 1.65 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (title, img) in zip(axes.flat, panels, strict=False):
        ax.imshow((img * exposure).clamp(0, 1).pow(1 / 2.2).numpy(), interpolation="nearest")
        ax.set_title(title, fontsize=5.5)
    fig.suptitle(f"{material}: measured (NBRDF fit of MERL) vs fitted models; glancing NE + grazing SW light",
                 fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def _fmt(x: float) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.3f}"


def nielsen_comparison(results) -> list[str]:
    """Sentences comparing the Phong, Blinn-Phong and mixture fits, computed from the results only."""
    need = ("nielsen-phong", "nielsen-blinn-phong", "nielsen-mixture")
    lines = []
    for mat, row in results.items():
        if not all(m in row for m in need):
            continue
        p, b, x = (row[m].errors for m in need)
        better = "Phong" if p.rel_l1_grazing < b.rel_l1_grazing else "Blinn-Phong"
        lines.append(
            f"- **{mat}**: grazing-only L1 Phong {_fmt(p.rel_l1_grazing)}, Blinn-Phong {_fmt(b.rel_l1_grazing)}, "
            f"mixture {_fmt(x.rel_l1_grazing)} → grazing behaviour more **{better}**-like; overall L1 Phong "
            f"{_fmt(p.rel_l1)}, Blinn-Phong {_fmt(b.rel_l1)}, mixture {_fmt(x.rel_l1)} (mixture "
            f"{'≤' if x.rel_l1 <= min(p.rel_l1, b.rel_l1) + 1e-4 else '>'} the better of the two; "
            f"fitted α = {row['nielsen-mixture'].params['mix'].item():.2f}, 1 = Blinn-Phong)."
        )
    if lines:
        ph = [ln.split("**")[1] for ln in lines if "**Phong**" in ln]
        bp = [ln.split("**")[1] for ln in lines if "**Blinn-Phong**" in ln]
        lines += ["", "Nielsen et al. report Phong-like grazing reflectance for two-layer-silver and Blinn-Phong-like "
                  f"for nickel, and the mixture fitting both. On these fits, grazing behaviour is Phong-like for "
                  f"{', '.join(ph) or 'none'} and Blinn-Phong-like for {', '.join(bp) or 'none'}. Caveats: our "
                  "targets are the NBRDF networks, not MERL's bins (the networks are fitted with a log loss and are "
                  "least constrained exactly at grazing angles); our L1 weights samples stratified on MERL's grid "
                  "rather than every MERL bin; the paper does not give its sampling, weights or optimiser. "
                  "The sqrt-spaced θ_h sampling gives the "
                  "peak core (θ_h < 1°) a large share of the weight, so a model that matches the core but not the "
                  "broad base of a highlight can score better than one that matches the base: compare the spheres "
                  "before trusting a ranking."]
    return lines


def uniform_errors(model, params, target_uniform: torch.Tensor, uniform) -> brdf_fit.FitErrors:
    """Errors of fitted ``params`` on the uniform-hemisphere samples (a second ranking, not the fitted objective)."""
    with torch.no_grad():
        pred = model.brdf(uniform.g, {k: v.to(torch.float64) for k, v in params.items()})
    return brdf_fit.errors(pred.expand_as(target_uniform), target_uniform, uniform)


def ranking_lines(results, uniform, models, n_samples: int) -> list[str]:
    """A second per-model summary under the uniform-hemisphere L1 (``uniform``: material → model → FitErrors on
    ``n_samples`` uniform pairs), and how far it reorders the first."""
    mats = [m for m in results if results[m]]
    rows = []
    for m in models:
        a = torch.tensor([results[mat][m].errors.rel_l1 for mat in mats if m in results[mat]], dtype=torch.float64)
        u = torch.tensor([uniform[mat][m].rel_l1 for mat in mats if m in uniform.get(mat, {})], dtype=torch.float64)
        if a.numel() and u.numel():
            rows.append((m, a.median().item(), u.median().item()))
    if not rows:
        return []
    best = {m: 0 for m in models}
    for mat in mats:
        if uniform.get(mat):
            best[min(uniform[mat], key=lambda k: uniform[mat][k].rel_l1)] += 1
    by_a = [r[0] for r in sorted(rows, key=lambda r: r[1])]
    by_u = [r[0] for r in sorted(rows, key=lambda r: r[2])]
    n = len(rows)
    d2 = sum((by_a.index(m) - by_u.index(m)) ** 2 for m in by_a)
    rho = 1.0 - 6.0 * d2 / (n * (n * n - 1)) if n > 1 else 1.0
    lines = ["", "## Second ranking: uniform-hemisphere L1", "",
             f"The fits above are scored on Rusinkiewicz samples whose sqrt-spaced θ_h gives the specular core a large "
             f"share of the weight. Here the same fitted parameters are scored on {n_samples} (l, v) "
             "pairs drawn uniformly in solid angle on both hemispheres (`make_samples(\"hemispheres\", 24)`, "
             "cosine-weighted relative L1, not re-fitted), which weights the broad base of a lobe and the diffuse "
             f"body by their share of the hemisphere. Spearman rank correlation between the two rankings of the "
             f"models by median: **{rho:.2f}**.", "",
             "| model | median L1 (uniform) | rank (uniform) | rank (Rusinkiewicz) | best on (uniform) |",
             "|---|---|---|---|---|"]
    for m in by_u:
        med = next(r[2] for r in rows if r[0] == m)
        lines.append(f"| `{m}` | {med:.3f} | {by_u.index(m) + 1} | {by_a.index(m) + 1} | {best[m]} |")
    return lines


def write_markdown(path: Path, results, models, settings, figures, seconds, uniform=None, n_uniform: int = 0) -> None:
    mats = list(results)
    lines = [
        "# Analytic models fitted to NBRDF fits of MERL",
        "",
        "Generated by `scripts/fit_measured.py` — do not edit by hand; re-run it when models change.",
        "",
        "**Data.** The targets are the NBRDF neural fits (Sztrajman et al., *Neural BRDF Representation and Importance "
        "Sampling*, CGF 2021) of the MERL measured BRDFs (Matusik et al., *A Data-Driven Reflectance Model*, "
        "ACM TOG 2003; MERL data CC-BY-SA-4.0, \"Created by Mitsubishi Electric Research Laboratories (MERL), 2003, "
        "2007, 2023\"). They are not the raw measurements: every number below is for the NBRDF fits of MERL. "
        "Decoder: `materials/measured.py` (domain, masking and the network's known asymmetries are documented there).",
        "",
        f"**Method.** `capture/brdf_fit.py`: {settings}. Error = cosine-weighted relative L1 "
        "Σ cos θ_i |f_fit − f_meas| / Σ cos θ_i |f_meas| over the samples (Nielsen et al.'s L1), shown as "
        "*all angles (without grazing > 80°)*. 0 is a perfect fit; 1 is as bad as predicting 0.",
        "",
        f"**Coverage.** {len(mats)} material(s) × {len(models)} model(s): {', '.join(f'`{m}`' for m in models)}. "
        f"Total fitting time {seconds:.0f} s on this machine.",
        "",
        "## Summary per model (in the manner of Ngan et al. 2005)",
        "",
        "| model | median L1 | mean L1 | median L1 w/o grazing | best on (materials) |",
        "|---|---|---|---|---|",
    ]
    best = {m: 0 for m in models}
    for mat in mats:
        row = results[mat]
        if row:
            best[min(row, key=lambda k: row[k].errors.rel_l1)] += 1
    summary = []
    for m in models:
        v = torch.tensor([results[mat][m].errors.rel_l1 for mat in mats if m in results[mat]], dtype=torch.float64)
        w = torch.tensor([results[mat][m].errors.rel_l1_no_grazing for mat in mats if m in results[mat]],
                         dtype=torch.float64)
        if v.numel():
            summary.append((v.median().item(), m, v.mean().item(), w.median().item()))
    for med, m, mean, wmed in sorted(summary):
        lines.append(f"| `{m}` | {med:.3f} | {mean:.3f} | {wmed:.3f} | {best[m]} |")
    if uniform:
        lines += ranking_lines(results, uniform, models, n_uniform)
    lines += ["", "## Nielsen et al.'s observation, checked on our fits", ""]
    cmp = nielsen_comparison(results)
    lines += cmp or ["(needs nielsen-phong, nielsen-blinn-phong and nielsen-mixture in the fitted models)"]
    if figures:
        lines += ["", "## Spheres: measured vs fitted (glancing NE + grazing SW light, as in Nielsen's Fig. 1)", "",
                  "Orthographic unit sphere, per-material exposure set on the measured sphere (99.5th percentile), "
                  "gamma 2.2. Panel titles give L1 (without grazing).", ""]
        lines += [f"![{m}]({rel})" for m, rel in figures]
    lines += ["", "## Error per material (L1, all angles (without grazing))", ""]
    for i in range(0, len(models), 6):
        chunk = models[i:i + 6]
        lines += ["| material | " + " | ".join(f"`{m}`" for m in chunk) + " |",
                  "|---|" + "---|" * len(chunk)]
        for mat in mats:
            cells = []
            for m in chunk:
                r = results[mat].get(m)
                cells.append(f"{_fmt(r.errors.rel_l1)} ({_fmt(r.errors.rel_l1_no_grazing)})" if r else "—")
            lines.append(f"| {mat} | " + " | ".join(cells) + " |")
        lines.append("")
    text = "\n".join(lines) + "\n"
    if path.is_file():  # keep the hand-written sections below the marker (e.g. the capture benchmark)
        old = path.read_text()
        if KEEP_MARKER in old:
            text += "\n" + old[old.index(KEEP_MARKER):]
    atomic_write_text(path, text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--materials", nargs="+", default=["all"], help="'all' or MERL names")
    ap.add_argument("--models", nargs="+", default=["all"], help="'all' or registry names (never 'measured')")
    ap.add_argument("--out", type=Path, default=Path("docs"), help="folder for measured-fits.md")
    ap.add_argument("--figures", type=Path, default=None, help="folder for the sphere PNGs (default <out>/figures)")
    ap.add_argument("--resolution", type=int, default=16, help="sampling strata per axis (make_samples)")
    ap.add_argument("--restarts", type=int, default=3)
    ap.add_argument("--procedure", choices=("joint", "nielsen"), default="joint")
    ap.add_argument("--size", type=int, default=96, help="sphere size in pixels")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--partial", action="store_true", help="rewrite the markdown after every material")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    names = measured.available_materials()
    mats = names if args.materials == ["all"] else args.materials
    unknown = [m for m in mats if m not in names]
    if unknown:
        ap.error(f"unknown material(s) {unknown}; available: {', '.join(names)}")
    registry = [m for m in materials.available() if m != "measured"]
    models = registry if args.models == ["all"] else args.models
    bad = [m for m in models if m not in registry]
    if bad:
        ap.error(f"unknown or unfittable model(s) {bad}; available: {', '.join(registry)}")
    figdir = args.figures or args.out / "figures"

    samples = brdf_fit.make_samples(resolution=args.resolution, dtype=torch.float64)
    settings = (f"{args.procedure} procedure, {args.restarts} restarts, {len(samples)} Rusinkiewicz-stratified "
                f"samples (resolution {args.resolution}, θ_h sqrt-spaced, φ_d ∈ [0, π]), Adam then L-BFGS, float64")
    uniform_samples = brdf_fit.make_samples("hemispheres", resolution=24, dtype=torch.float64)
    uniform: dict[str, dict] = {}
    t0 = time.perf_counter()
    results: dict[str, dict] = {}
    figures = []
    for mat in mats:
        target = materials.get("measured", material=mat)
        results[mat] = {}
        fits = {}
        for m in models:
            model = materials.get(m)
            res = brdf_fit.fit_brdf(model, target, samples, procedure=args.procedure, restarts=args.restarts)
            results[mat][m] = res
            fits[m] = (model, res)
            print(f"{mat:28s} {m:24s} L1 {res.errors.rel_l1:.4f} (w/o grazing {res.errors.rel_l1_no_grazing:.4f}) "
                  f"{res.seconds:.1f} s", flush=True)
        mix = results[mat].get("nielsen-mixture")
        for nested, a in (("nielsen-phong", 0.02), ("nielsen-blinn-phong", 0.98)):
            # The mixture contains Phong (α = 0) and Blinn-Phong (α = 1), but its spread restarts (α = ¼, ½, ¾)
            # can miss both ends (measured: alumina-oxide 0.329 vs Blinn-Phong 0.171). Warm-start it from each
            # nested fit and keep the best (measured: alumina-oxide 0.329 → 0.166; beige-fabric 0.073 → 0.064, still
            # above Blinn-Phong's 0.060: Adam's first steps leave the nested optimum, so this narrows, not closes,
            # the gap).
            if mix is None or nested not in results[mat]:
                continue
            init = {k: v for k, v in results[mat][nested].params.items() if k in mix.params}
            init["mix"] = torch.tensor(a, dtype=torch.float64)
            warm = brdf_fit.fit_brdf(fits["nielsen-mixture"][0], target, samples, procedure=args.procedure,
                                     restarts=1, init=init)
            if warm.objective < mix.objective:
                warm.seconds += mix.seconds
                warm.restarts = mix.restarts + warm.restarts
                mix = results[mat]["nielsen-mixture"] = warm
                fits["nielsen-mixture"] = (fits["nielsen-mixture"][0], warm)
                print(f"{mat:28s} nielsen-mixture warm-started from {nested}: L1 {warm.errors.rel_l1:.4f}", flush=True)
        target_uniform = brdf_fit.evaluate_target(target, uniform_samples)
        uniform[mat] = {m: uniform_errors(fits[m][0], results[mat][m].params, target_uniform, uniform_samples)
                        for m in results[mat]}
        if mat in FIGURE_MATERIALS:
            png = figdir / f"measured-{mat}.png"
            render_figure(mat, fits, png, args.size)
            try:
                rel = png.resolve().relative_to(args.out.resolve())
            except ValueError:
                rel = png.resolve()
            figures.append((mat, rel.as_posix()))
        if args.partial:  # rewrite after every material so that an interrupted run leaves its table
            write_markdown(args.out / "measured-fits.md", results, models, settings, figures,
                           time.perf_counter() - t0, uniform, len(uniform_samples))
    write_markdown(args.out / "measured-fits.md", results, models, settings, figures, time.perf_counter() - t0,
                   uniform, len(uniform_samples))
    print(f"wrote {args.out / 'measured-fits.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
