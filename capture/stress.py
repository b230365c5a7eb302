"""Stress tests of the whole stack (issue 6): model stability tables for ``scripts/stress.py``."""

from __future__ import annotations

import time
from pathlib import Path

import torch

import materials
from materials.validation import check_stability

from .benchmark import machine_description
from .report import replace_section


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
