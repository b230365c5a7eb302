"""Time to a map error, shadecap against another optimiser on the same photos (``scripts/mitsuba_race.py``).

shadecap's fit is not an anytime optimiser: its error at a time budget is measured by fitting again with fewer
footprint steps (:func:`shadecap_curve`, ``footprint_iterations`` 0, 1, 2, …), each fit timed from loading the
dataset to the maps (the report's total without the ground-truth metrics and the output files). The other
optimiser's curve is its own evaluations over time (``{"seconds", "albedo_rmse_well_lit"}`` entries, as
``scripts/mitsuba_adam.py`` writes them). For each shadecap point the table gives the time the other run first had
an error as low (:func:`time_to_error`, an upper bound at the run's evaluation spacing) and the ratio of the two
times.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Sequence
from pathlib import Path

__all__ = ["time_to_error", "shadecap_curve", "race_table", "race_figure"]

#: Report times that are not part of reaching the maps: the error against the ground truth and the output files.
_NOT_FITTING = ("metrics", "write")


def _check_evaluations(evaluations: Sequence[dict], what: str) -> None:
    if not evaluations:
        raise ValueError(f"{what} has no evaluations: give a run with at least one (seconds, error) entry")
    for e in evaluations:
        if not (math.isfinite(float(e["seconds"])) and math.isfinite(float(e["albedo_rmse_well_lit"]))):
            raise ValueError(f"{what} has a non-finite evaluation {e}: every entry needs finite seconds and error")


def _check_curves(shadecap: Sequence[dict], runs: Sequence[dict]) -> None:
    _check_evaluations(shadecap, "shadecap's curve")
    for run in runs:
        _check_evaluations(run.get("evaluations", ()), _run_name(run))


def time_to_error(evaluations: Sequence[dict], error: float) -> float | None:
    """The first ``seconds`` of ``evaluations`` (in time order) whose ``albedo_rmse_well_lit`` is at most
    ``error``; None when none is."""
    if not math.isfinite(error):
        raise ValueError(f"error must be finite, got {error!r}")
    _check_evaluations(evaluations, "the run")
    for e in sorted(evaluations, key=lambda e: float(e["seconds"])):
        if float(e["albedo_rmse_well_lit"]) <= error:
            return float(e["seconds"])
    return None


def _best(evaluations: Sequence[dict]) -> dict:
    return min(evaluations, key=lambda e: float(e["albedo_rmse_well_lit"]))


def shadecap_curve(dataset, steps: Sequence[int], model: str, work=None, threads: int | None = None) -> list[dict]:
    """Fit ``dataset`` with ``model`` once per footprint-step budget in ``steps``; per fit the budget, the seconds
    to the maps (the report's total without :data:`_NOT_FITTING`), the report's total and the well-lit albedo RMSE
    (``albedo_rmse_well_lit``). ``work``: folder for the fits' outputs (default a temporary one)."""
    from ..reconstruct import reconstruct

    steps = [int(n) for n in steps]
    if not steps or any(n < 0 for n in steps):
        raise ValueError(f"steps must be footprint-step budgets ≥ 0, at least one, got {list(steps)}")
    tmp = None if work else tempfile.TemporaryDirectory()
    root = Path(work or tmp.name)
    points = []
    try:
        for n in steps:
            r = reconstruct(dataset, model=model, out_dir=root / f"steps{n}", force=True, progress=False,
                            threads=threads, footprint_iterations=n)
            well_lit = r.errors.get("maps_by_texel_set", {}).get("well_lit", {}).get("albedo")
            if well_lit is None:
                raise ValueError(f"{dataset}: the report has no well-lit albedo error (a dataset with ground truth "
                                 f"and a model with an albedo is needed)")
            total = float(r.times["total"])
            points.append({"steps": n, "seconds": total - sum(float(r.times.get(k, 0.0)) for k in _NOT_FITTING),
                           "total": total, "albedo_rmse_well_lit": float(well_lit)})
    finally:
        if tmp is not None:
            tmp.cleanup()
    return points


def _run_name(run: dict) -> str:
    return f"Adam lr {run['lr']:g}, {run['spp']} spp"


def race_table(shadecap: Sequence[dict], runs: Sequence[dict]) -> str:
    """Markdown: one row per shadecap point (footprint steps, seconds, well-lit albedo RMSE) and, per other run
    (``runs``: dicts with ``lr``, ``spp`` and ``evaluations``), the time it first had that error and its ratio to
    shadecap's time, or its best error and when, when it never had it; then, per run, its best error, when, and
    the time of shadecap's first fit (by time) with an error as low."""
    _check_curves(shadecap, runs)
    head = "| footprint steps | shadecap: seconds to the maps | well-lit albedo RMSE |" + "".join(
        f" {_run_name(r)}: time to it |" for r in runs)
    lines = [head, "|" + "---|" * (3 + len(runs))]
    for p in sorted(shadecap, key=lambda p: p["seconds"]):
        cells = []
        for run in runs:
            t = time_to_error(run["evaluations"], p["albedo_rmse_well_lit"])
            if t is None:
                b = _best(run["evaluations"])
                cells.append(f"never (best {b['albedo_rmse_well_lit']:.4f} at {b['seconds']:.0f} s)")
            else:
                cells.append(f"{t:.0f} s (**{t / p['seconds']:.0f} ×**)")
        lines.append(f"| {p['steps']} | {p['seconds']:.1f} | {p['albedo_rmse_well_lit']:.4f} | "
                     + " | ".join(cells) + " |")
    if runs:
        # the other way round: each run's best error, and how soon shadecap's fits had it
        lines += ["", "| run | its best well-lit albedo RMSE | at | shadecap: first fit as low | ratio |",
                  "|---|---|---|---|---|"]
        for run in runs:
            b = _best(run["evaluations"])
            t = time_to_error(shadecap, b["albedo_rmse_well_lit"])
            first = "none of its fits" if t is None else f"{t:.1f} s"
            ratio = "–" if t is None else f"**{b['seconds'] / t:.0f} ×** sooner"
            lines.append(f"| {_run_name(run)} | {b['albedo_rmse_well_lit']:.4f} | {b['seconds']:.0f} s | {first} | "
                         f"{ratio} |")
    return "\n".join(lines)


def race_figure(shadecap: Sequence[dict], runs: Sequence[dict], path) -> None:
    """Well-lit albedo RMSE against seconds (log–log): shadecap's points by footprint-step budget, each run's
    evaluations as a line."""
    _check_curves(shadecap, runs)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    fig, ax = plt.subplots(figsize=(7, 4.5))
    pts = sorted(shadecap, key=lambda p: p["seconds"])
    ax.plot([p["seconds"] for p in pts], [p["albedo_rmse_well_lit"] for p in pts], "o-", color="black", lw=2,
            label="shadecap (points: footprint steps)")
    for p in pts:
        ax.annotate(str(p["steps"]), (p["seconds"], p["albedo_rmse_well_lit"]), textcoords="offset points",
                    xytext=(4, 4), fontsize=8)
    for run in runs:
        ev = [e for e in sorted(run["evaluations"], key=lambda e: e["seconds"]) if e["seconds"] > 0]
        ax.plot([e["seconds"] for e in ev], [e["albedo_rmse_well_lit"] for e in ev], "-", label=_run_name(run))
    ax.set(xscale="log", yscale="log", xlabel="seconds", ylabel="albedo RMSE, well-lit texels",
           title="time to a map error on the same photos")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)                      # (which closes the figure)
