"""Stress tests of the whole stack (issue 6): model stability tables for ``scripts/stress.py``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch

import materials
from materials.validation import SampledReport, check_stability, sampled_stability

from ..plots import save_figure
from ..report import replace_section
from .timing import machine_description


def model_stability_table(n_random: int = 4096, out: str | None = None) -> tuple[str, bool]:
    """Run :func:`materials.validation.check_stability` for every model in float64 and float32.

    Returns the markdown table and whether every model stayed finite. With ``out``, the table
    replaces the ``models`` section of that markdown file (created if missing).
    """
    lines = [
        f"Machine: {machine_description()}. Grid of cosines {{−1e-3, −1e-7, 0, 1e-7, 1e-4, 1e-2, 0.3, 0.7, 1}}² × 4 "
        f"azimuths, l = −v, and {n_random} random (l, v) over the sphere; every parameter cycled through its range "
        "ends, default and extremes (roughness 0/1e-6/1, f0 0/1, η 1/3, absorption 0..1e3).",
        "",
        "| model | samples | non-finite f (f64/f32) | non-finite ∇ (f64/f32) | max abs ∇ params (f64) "
        "| max abs ∇ incl. directions (f64) | worst f32 vs f64 (rel.) |",
        "|---|---|---|---|---|---|---|",
    ]
    all_ok = True
    t0 = time.perf_counter()
    for name in materials.available():
        model = materials.get(name)
        r64 = check_stability(model, torch.float64, n_random=n_random)
        r32 = check_stability(model, torch.float32, n_random=n_random)
        all_ok &= r64.ok and r32.ok
        lines.append(
            f"| `{name}` | {r64.samples} | {r64.nonfinite_value}/{r32.nonfinite_value} | "
            f"{r64.nonfinite_grad}/{r32.nonfinite_grad} | {r64.max_abs_grad_params:.3g} | {r64.max_abs_grad:.3g} | "
            f"{r32.max_rel_dev_f32:.2e} |"
        )
    verdict = "none" if all_ok else "SOME — see rows"
    lines += ["", f"Total non-finite: {verdict}; run time {time.perf_counter() - t0:.1f} s."]
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "models", "## Models: forward and gradient over the extreme domain\n\n" + table)
    return table, all_ok


#: Option variants sampled next to the registered defaults: the printed (unclamped) forms whose negative values
#: docs/models-diffuse.md documents, and options added for numerical reasons.
SAMPLED_VARIANTS = (
    ("oren-nayar", {"clamp": False}),
    ("gotanda-on-improved", {"form": "eq24", "clamp": False}),
    ("gotanda2014-on-fresnel", {"clamp": False}),
    ("microfacet", {"D": "beckmann", "beckmann_lambda": "exact"}),
    ("gotanda2012-layered", {"bottom": "nielsen-phong"}),
)


def _sampled_one(name: str, options: dict, dtype, samples: int, chunk: int, work: Path | None) -> dict:
    """:func:`materials.validation.sampled_stability` over ``samples`` triples in chunks (seed = chunk index), one
    model and dtype; with ``work`` every finished chunk is stored there and reused by a later run (resumable)."""
    label = name + "".join(f" {k}={v}" for k, v in sorted(options.items()))
    key = f"{label} {dtype} {chunk}".replace(" ", "_").replace("=", "-").replace("torch.", "")
    model = materials.get(name, **options)
    rep = SampledReport(model.name, str(dtype).replace("torch.", ""))
    seconds = 0.0
    for k, start in enumerate(range(0, samples, chunk)):
        size = min(chunk, samples - start)
        cached = work / f"{key}_{k}_{size}.json" if work is not None else None
        if cached is not None and cached.exists():
            part = json.loads(cached.read_text())
        else:
            t0 = time.perf_counter()
            part = {**sampled_stability(model, size, dtype=dtype, seed=k).__dict__, "seconds": time.perf_counter() - t0}
            if cached is not None:
                work.mkdir(parents=True, exist_ok=True)
                cached.write_text(json.dumps(part))
        seconds += part.pop("seconds")
        rep = rep.add(SampledReport(**part))
    return {"label": label, **rep.__dict__, "seconds": seconds}


def model_sampled_table(samples: int = 10_000_000, chunk: int = 250_000, out: str | None = None,
                        work: str | None = None, names=None, variants=SAMPLED_VARIANTS,
                        variant_samples: int | None = None, progress: bool = True) -> tuple[str, bool]:
    """Every registered model (and :data:`SAMPLED_VARIANTS`) on ``samples`` random and edge triples in float64 and
    float32 (:func:`materials.validation.sampled_stability`: random directions, grazing mirror pairs with n·l and
    n·v down to 1e-7, exact mirrors, l = ±v, the stress cosines, random frames; parameters uniform, at their
    stress values and near their range ends), with values and gradients (l, v, every parameter) of both
    ``brdf`` and ``cosine_brdf``. The variants get ``variant_samples`` triples (default a tenth of ``samples``).
    Returns the markdown table and whether every row stayed finite; with ``out`` the table replaces the
    ``models-sampled`` section of that file; with ``work`` each row is stored there and a rerun resumes."""
    if names is None:
        names = [n for n in materials.available() if n != "measured" or materials.measured.data_dir().exists()]
    names = list(names)
    n_variant = variant_samples if variant_samples is not None else max(samples // 10, 1)
    runs = [(n, {}, samples) for n in names] + [(v[0], v[1], n_variant) for v in (variants or ()) if v[0] in names]
    work_dir = Path(work) if work else None
    lines = [
        f"Machine: {machine_description()}. {samples:,} triples per registered model and dtype ({n_variant:,} "
        f"for the option variants below them; chunks of {chunk:,}, seeds 0, 1, …; the same triples in both dtypes), "
        "from `materials.validation.edge_vectors`: one sixth each "
        "uniform over the sphere, uniform over the upper hemisphere, grazing mirror pairs (n·v log-uniform in "
        "1e-7…1e-1, n·l equal or independently grazing, azimuth off the mirror by 0 or 1e-9…1e-1 rad), exact "
        "mirror pairs, l = −v and l = v, and the stress grid's cosines (0, ±1e-7, −1e-3 …); half of them in a "
        "random frame. Parameters (`random_params`): half uniform over the range, a quarter at the stress "
        "values, a quarter within 1e-9…1e-2 of a range end. Counts are samples with a non-finite or negative "
        "entry in `brdf` or `cosine_brdf` (values) or in the gradient of their sum w.r.t. l, v and every "
        "parameter.",
        "",
        "| model | samples per dtype | non-finite f (f64/f32) | non-finite ∇ (f64/f32) | of which ∇ w.r.t. l, v "
        "(f64/f32) | negative f (f64/f32) | min f_r, 1/sr (f64) | seconds (f64 + f32) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    all_ok = True
    t0 = time.perf_counter()
    for name, options, count in runs:
        r64 = _sampled_one(name, options, torch.float64, count, chunk, work_dir)
        r32 = _sampled_one(name, options, torch.float32, count, chunk, work_dir)
        ok = all(r[k] == 0 for r in (r64, r32) for k in ("nonfinite_value", "nonfinite_grad"))
        all_ok &= ok
        row = (f"| `{r64['label']}` | {r64['samples']:,} | {r64['nonfinite_value']}/{r32['nonfinite_value']} | "
               f"{r64['nonfinite_grad']}/{r32['nonfinite_grad']} | "
               f"{r64['nonfinite_grad_directions']}/{r32['nonfinite_grad_directions']} | "
               f"{r64['negative']}/{r32['negative']} | {r64['min_value']:.3g} | "
               f"{r64['seconds'] + r32['seconds']:.0f} |")
        lines.append(row)
        if progress:
            print(row, flush=True)
    verdict = "none" if all_ok else "SOME — see rows"
    lines += ["", f"Total non-finite: {verdict}. The seconds column adds the chunks' own times (chunks may come "
              f"from earlier, interrupted invocations); this invocation ran {time.perf_counter() - t0:.0f} s."]
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "models-sampled",
                        "## Models: random and edge samples, values and gradients\n\n" + table)
    return table, all_ok


# -- reconstruction under stress ------------------------------------------------------------------

#: Extreme ground truths of the "extreme true parameters" scenario: label → ``SyntheticConfig.uniform``
#: (the named map is set everywhere; the other maps keep the six regions).
EXTREME_TRUTH = {
    "regions": {},
    "mirror-like r 0.02": {"roughness": 0.02},
    "fully rough r 1": {"roughness": 1.0},
    "black albedo": {"albedo": 0.0},
    "white f0": {"f0": 1.0},
}

#: (scenario, SyntheticConfig field or pseudo-field, levels, label of the level). Base: a small
#: ggx-lambert sphere (96 px, 6 views, 32² maps). Pseudo-fields: "full_well" (shot noise; None = none),
#: "exposure_error" (the recorded exposure is off by this factor), "overexpose" (photo exposure, clipped).
STRESS_SCENARIOS = (
    ("shot noise", "full_well", (None, 3000.0, 300.0, 30.0), "electrons at saturation"),
    ("exposure error", "exposure_error", (1.0, 1.1, 1.5, 2.0), "recorded/true exposure"),
    ("clipped highlights", "overexpose", (1.0, 2.0, 4.0, 8.0), "exposure (clip at 1)"),
    ("few views", "n_views", (8, 4, 2, 1), "views"),
    ("light swung away from the camera", "light_offset_deg", (20.0, 45.0, 70.0, 89.0), "light-camera angle (deg)"),
    ("grazing views only", "elevations", ((50.0,), (20.0,), (8.0,), (3.0,)), "camera elevation over a plane (deg)"),
    ("extreme true parameters", "uniform", tuple(EXTREME_TRUTH), "true maps"),
)


def _stress_config(field: str, level):
    from dataclasses import replace

    from ..photo import PhotoModel
    from ..synth import small_scene

    base = small_scene("ggx-lambert", image_size=96, texture_size=32, n_views=6)
    if field == "full_well":
        return replace(base, photo=PhotoModel(full_well=level)), 1.0
    if field == "exposure_error":
        return base, level
    if field == "overexpose":
        return replace(base, photo=PhotoModel(exposure=level, clip=True)), 1.0
    if field == "uniform":
        return replace(base, uniform=EXTREME_TRUTH[level]), 1.0
    if field == "elevations":
        return replace(base, mesh="plane", mesh_options={}, elevations=level, light_rig="fixed"), 1.0
    return replace(base, **{field: level}), 1.0


def _scale_recorded_exposure(dataset: Path, factor: float) -> None:
    import json

    scene = dataset / "scene.json"
    meta = json.loads(scene.read_text())
    for img in meta["images"]:
        img["exposure"] = float(img["exposure"]) * factor
    scene.write_text(json.dumps(meta, indent=1))


def reconstruction_stress(workdir, scenarios=STRESS_SCENARIOS) -> list[dict]:
    """Reconstruct a small scene under each stress level; record errors, NaNs, warnings, crashes."""
    import math
    import warnings
    from pathlib import Path

    from renderer.imageio import read_exr

    from ..reconstruct import reconstruct
    from ..synth import make_synthetic

    workdir = Path(workdir)
    rows = []
    for name, field, levels, unit in scenarios:
        for k, level in enumerate(levels):
            row = {"scenario": name, "unit": unit, "level": level if not isinstance(level, tuple) else level[0]}
            ds, rec = workdir / f"{field}-{k}" / "dataset", workdir / f"{field}-{k}" / "recon"
            t0 = time.perf_counter()
            try:
                cfg, exposure_factor = _stress_config(field, level)
                make_synthetic(cfg, ds, overwrite=True)
                if exposure_factor != 1.0:
                    _scale_recorded_exposure(ds, exposure_factor)
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    rep = reconstruct(ds, model="ggx-lambert", out_dir=rec, force=True, progress=False)
                row["warnings"] = len(rep.warnings) + len(caught)
                row["warning_text"] = "; ".join(str(w)[:120] for w in rep.warnings[:2])
                for m in ("albedo", "f0", "roughness"):
                    row[m] = rep.errors.get("maps", {}).get(m, {}).get("rmse", math.nan)
                    row[m + "_observable"] = rep.errors.get("maps_observable", {}).get(m, {}).get("rmse", math.nan)
                    row[m + "_determined"] = rep.errors.get("maps_determined_at_truth", {}).get(m, {}).get("rmse",
                                                                                                          math.nan)
                    obs = rep.errors.get("observability", {}).get(m, {})
                    row[m + "_fraction"] = obs.get("observable_fraction", math.nan)
                    row[m + "_determined_fraction"] = obs.get("determined_fraction", math.nan)
                nan_maps = [m for m in ("albedo", "f0", "roughness") if (rec / f"{m}.exr").exists()
                            and not torch.isfinite(read_exr(rec / f"{m}.exr")).all()]
                row["nan_maps"] = ",".join(nan_maps)
                row["crash"] = ""
            except Exception as exc:  # a stress test records crashes instead of stopping
                row["crash"] = f"{type(exc).__name__}: {str(exc)[:160]}"
            row["seconds"] = time.perf_counter() - t0
            rows.append(row)
    return rows


def plot_reconstruction_stress(rows: list[dict], out_png) -> None:
    """One panel per scenario: RMSE of each map against the stress level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["scenario"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.0), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        rs = [r for r in rows if r["scenario"] == name]
        xs = list(range(len(rs)))
        for m, c in (("albedo", "tab:blue"), ("f0", "tab:orange"), ("roughness", "tab:green")):
            ax.plot(xs, [r.get(m, float("nan")) for r in rs], "o-", color=c, label=m, ms=3)
        ax.set_xticks(xs, [str(r["level"]) for r in rs], fontsize=7)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(rs[0]["unit"], fontsize=7)
        vals = [r.get(m) for r in rs for m in ("albedo", "f0", "roughness")]
        if any(isinstance(v, float) and v > 0 and v == v for v in vals):
            ax.set_yscale("log")
        for x, r in zip(xs, rs, strict=True):
            if r["crash"]:
                ax.annotate("crash", (x, 0.5), xycoords=("data", "axes fraction"), color="red", fontsize=7)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("RMSE on observed texels")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out_png, dpi=70)


def run_reconstruction_stress(workdir, out: str | None = None, figure: str | None = None) -> str:
    """Markdown table (and plot) of :func:`reconstruction_stress`."""
    import json
    from pathlib import Path

    nan, MAPS = float("nan"), ("albedo", "f0", "roughness")  # noqa: N806
    rows = reconstruction_stress(workdir)
    Path(workdir).mkdir(parents=True, exist_ok=True)
    (Path(workdir) / "stress_rows.json").write_text(json.dumps(rows, indent=1, default=str))
    lines = [
        f"Machine: {machine_description()}. Base: small ggx-lambert sphere (96 px, 6 views, 32² maps, 2 flash lights), "
        "reconstructed with `model=\"ggx-lambert\"`, fast solver; one stress at a time. RMSE over observed texels "
        "(all), over those where the map is observable at the estimate (obsv.) and over those the photos determine at "
        "the true maps (det., `capture.metrics.determined_at_truth`).",
        "",
        "| stress | level | albedo RMSE all / obsv. / det. | f0 RMSE all / obsv. / det. | roughness RMSE all / obsv. / "
        "det. | observable % (a/f0/r) | determined at the truth % | NaN maps | warnings | crash | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['level']} ({r['unit']}) | "
            + " | ".join(f"{r.get(m, nan):.3g} / {r.get(m + '_observable', nan):.3g} / "
                         f"{r.get(m + '_determined', nan):.3g}" for m in MAPS)
            + " | " + "/".join(f"{100 * r.get(m + '_fraction', nan):.0f}" for m in MAPS)
            + " | " + "/".join(f"{100 * r.get(m + '_determined_fraction', nan):.0f}" for m in MAPS)
            + f" | {r.get('nan_maps') or 'none'} | "
            f"{r.get('warnings', '—')} | {r['crash'] or 'no'} | {r['seconds']:.1f} |"
        )
    table = "\n".join(lines)
    if figure:
        plot_reconstruction_stress(rows, figure)
        rel = Path(figure).name if out is None else "figures/" + Path(figure).name
        table += f"\n\n![reconstruction under stress]({rel})"
    if out:
        replace_section(Path(out), "reconstruction-stress", "## Reconstruction under stress\n\n" + table)
    return table
