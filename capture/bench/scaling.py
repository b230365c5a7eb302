"""Scaling of the forward pipeline (issue 6): how time and memory grow with views, image resolution,
texture resolution and lights, with the fitted growth exponent (time ∝ x^k).

Each configuration builds a synthetic scene (capture.synth) and times the stages the
reconstruction repeats or pays once: G-buffers (once per view), ``prepare`` (once per view: per-light
Angles, shadows), and one differentiable ``shade`` forward + backward of every view (what every
solver iteration costs). ``scripts/benchmark.py scaling`` runs :func:`run_scaling_benchmark`.
"""

from __future__ import annotations

import time
from dataclasses import replace

from renderer.gbuffer import render_gbuffer
from renderer.shading import prepare, shade

from ..synth import build_scene, small_scene
from .timing import growth_exponent, machine_description, peak_rss_mib


def time_forward(config) -> dict:
    """Seconds of each stage for one configuration, and the sample-light pair count."""
    scene = build_scene(config)
    t0 = time.perf_counter()
    gbs = [render_gbuffer(scene.mesh, v.camera) for v in scene.views]
    t1 = time.perf_counter()
    preps = [prepare(gb, scene.mesh, v.lights) for gb, v in zip(gbs, scene.views, strict=True)]
    t2 = time.perf_counter()
    maps = {k: m.clone().requires_grad_() for k, m in scene.maps.items()}
    total = sum(shade(scene.model, maps, p).sum() for p in preps)
    total.backward()
    t3 = time.perf_counter()
    pairs = sum(int(t.index.numel()) for p in preps for t in p.lights)
    return {"gbuffer_s": t1 - t0, "prepare_s": t2 - t1, "shade_fb_s": t3 - t2, "pairs": pairs,
            "peak_rss_mb": peak_rss_mib()}


#: The sweeps: (axis label, SyntheticConfig field, values). Base: small_scene("ggx-lambert").
SWEEPS = (
    ("views", "n_views", (4, 8, 16, 32)),
    ("image size (px)", "image_size", (64, 128, 256, 384)),
    ("texture size (texels)", "texture_size", (64, 128, 256, 512)),
    ("lights per view", "n_lights", (1, 2, 4, 8)),
)


def best_of(config, repeats: int = 2) -> dict:
    """:func:`time_forward` ``repeats`` times; the minimum of each time (the least disturbed run)."""
    runs = [time_forward(config) for _ in range(repeats)]
    return {k: (min(r[k] for r in runs) if k.endswith("_s") else runs[-1][k]) for k in runs[0]}


def run_scaling_benchmark(out: str | None = None) -> str:
    """Run :data:`SWEEPS` and return (and with ``out`` write) a markdown table with growth exponents."""
    from pathlib import Path

    from ..report import replace_section

    base = small_scene("ggx-lambert", image_size=128, texture_size=128, n_views=8)
    lines = [
        f"Machine: {machine_description()}. Base scene: uv_sphere, 8 views of 128 px, 128² maps, ggx-lambert, 2 flash "
        "lights, shadows on; one axis varied at a time; best of 2 runs. Times in seconds; k is the fitted exponent of "
        "time ∝ x^k.",
        "",
        "| axis | values | G-buffers (s) | prepare (s) | shade fwd+bwd (s) | sample-light pairs | k G-buffer "
        "| k prepare | k shade | peak RSS (MB) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, field, values in SWEEPS:
        rows = [best_of(replace(base, **{field: v})) for v in values]
        cols = {key: ", ".join(f"{r[key]:.3g}" for r in rows) for key in ("gbuffer_s", "prepare_s", "shade_fb_s")}
        ks = [growth_exponent(list(values), [r[key] for r in rows]) for key in ("gbuffer_s", "prepare_s", "shade_fb_s")]
        lines.append(
            f"| {label} | {', '.join(map(str, values))} | {cols['gbuffer_s']} | {cols['prepare_s']} | "
            f"{cols['shade_fb_s']} | "
            f"{', '.join(str(r['pairs']) for r in rows)} | {ks[0]:.2f} | {ks[1]:.2f} | {ks[2]:.2f} | "
            f"{max(r['peak_rss_mb'] for r in rows):.0f} |"
        )
    lines += ["", "Expected: G-buffers and prepare linear in views and in pixels (k ≈ 1 in views, ≈ 2 in image size), "
              "shading linear in sample-light pairs, texture size nearly free (only the gathers read the maps)."]
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "scaling", "## Scaling of the forward pipeline\n\n" + table)
    return table
