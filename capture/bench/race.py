"""Time to a map error, shadecap against another optimiser on the same photos (``scripts/mitsuba_race.py``).

shadecap's fit is not an anytime optimiser: its error at a time budget is measured by fitting again with fewer
footprint steps (:func:`shadecap_curve`, ``footprint_iterations`` 0, 1, 2, …), each fit timed from loading the
dataset to the maps (the report's total without the ground-truth metrics and the output files). The other
optimiser's curve is its own evaluations over time (``{"seconds", "<map>_rmse_<texel set>", …}`` entries, as
``scripts/mitsuba_adam.py`` writes them). Errors are named by :func:`error_key` — a map's RMSE on one texel set of
``capture.metrics.errors_by_texel_set`` (``albedo_rmse_well_lit``, ``roughness_rmse_well_lit_visible_highlight``,
…) — and every function takes the key it races on. For each shadecap point the table gives the time the other run
first had an error as low (:func:`time_to_error`, an upper bound at the run's evaluation spacing) and the ratio of
the two times.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

__all__ = ["time_to_error", "shadecap_curve", "race_table", "race_figure", "error_key", "flat_errors",
           "check_evaluations", "DEFAULT_KEY"]

#: Report times that are not part of reaching the maps: the error against the ground truth and the output files.
_NOT_FITTING = ("metrics", "write")
#: The error raced on unless another is named: the albedo on the well-lit texels (every model has an albedo).
DEFAULT_KEY = "albedo_rmse_well_lit"
_SET_WORDS = {"well_lit": "well-lit", "well_lit_pixel_sized": "well-lit pixel-sized",
              "well_lit_highlight": "well-lit highlight", "well_lit_visible_highlight": "visible-highlight"}


def error_key(name: str, texel_set: str) -> str:
    """The evaluation key of map ``name``'s RMSE on ``texel_set`` (a key of ``errors_by_texel_set``)."""
    return f"{name}_rmse_{texel_set}"


def flat_errors(by_set: Mapping[str, Mapping[str, float]]) -> dict:
    """``errors_by_texel_set``'s ``{set: {map: rmse, "texels": n}}`` → ``{error_key(map, set): rmse}``."""
    return {error_key(m, k): float(v) for k, row in by_set.items() for m, v in row.items() if m != "texels"}


def _describe(key: str) -> str:
    """``albedo_rmse_well_lit`` → ``well-lit albedo RMSE``."""
    name, _, texel_set = key.partition("_rmse_")
    return f"{_SET_WORDS.get(texel_set, texel_set.replace('_', ' '))} {name} RMSE" if texel_set else key


def check_evaluations(evaluations: Sequence[dict], what: str, key: str) -> None:
    """A ValueError naming ``what`` unless every one of ``evaluations`` has finite ``seconds`` and ``key`` error."""
    if not evaluations:
        raise ValueError(f"{what} has no evaluations: give a run with at least one (seconds, error) entry")
    for e in evaluations:
        if key not in e:
            have = sorted(k for k in e if "_rmse_" in k)
            raise ValueError(f"{what} has no {key!r} error (it has {have or 'none'}): race on an error both sides "
                             f"measured")
        if not (math.isfinite(float(e["seconds"])) and math.isfinite(float(e[key]))):
            raise ValueError(f"{what} has a non-finite evaluation {e}: every entry needs finite seconds and error")


def _check_curves(shadecap: Sequence[dict], runs: Sequence[dict], key: str) -> None:
    check_evaluations(shadecap, "shadecap's curve", key)
    for run in runs:
        check_evaluations(run.get("evaluations", ()), _run_name(run), key)


def time_to_error(evaluations: Sequence[dict], error: float, key: str = DEFAULT_KEY) -> float | None:
    """The first ``seconds`` of ``evaluations`` (in time order) whose ``key`` error is at most ``error``; None when
    none is."""
    if not math.isfinite(error):
        raise ValueError(f"error must be finite, got {error!r}")
    check_evaluations(evaluations, "the run", key)
    for e in sorted(evaluations, key=lambda e: float(e["seconds"])):
        if float(e[key]) <= error:
            return float(e["seconds"])
    return None


def _best(evaluations: Sequence[dict], key: str) -> dict:
    return min(evaluations, key=lambda e: float(e[key]))


def shadecap_curve(dataset, steps: Sequence[int], model: str, work=None, threads: int | None = None,
                   on_point: Callable[[dict], None] | None = None) -> list[dict]:
    """Fit ``dataset`` with ``model`` once per footprint-step budget in ``steps``; per fit the budget, the seconds
    to the maps (the report's total without :data:`_NOT_FITTING`), the report's total and every map's RMSE on every
    texel set of the report (:func:`flat_errors`; ``albedo_rmse_well_lit`` at least). ``work``: folder for the fits'
    outputs (default a temporary one); ``on_point``: called with each point as soon as its fit ends (progress)."""
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
            errors = flat_errors(r.errors.get("maps_by_texel_set", {}))
            if DEFAULT_KEY not in errors:
                raise ValueError(f"{dataset}: the report has no well-lit albedo error (a dataset with ground truth "
                                 f"and a model with an albedo is needed)")
            total = float(r.times["total"])
            points.append({"steps": n, "seconds": total - sum(float(r.times.get(k, 0.0)) for k in _NOT_FITTING),
                           "total": total, **errors})
            if on_point is not None:
                on_point(points[-1])
    finally:
        if tmp is not None:
            tmp.cleanup()
    return points


def _run_name(run: dict) -> str:
    return f"Adam lr {run['lr']:g}, {run['spp']} spp"


def race_table(shadecap: Sequence[dict], runs: Sequence[dict], key: str = DEFAULT_KEY) -> str:
    """Markdown: one row per shadecap point (footprint steps, seconds, its ``key`` error) and, per other run
    (``runs``: dicts with ``lr``, ``spp`` and ``evaluations``), the time it first had that error and its ratio to
    shadecap's time, or its best error and when, when it never had it; then, per run, its best error, when, and
    the time of shadecap's first fit (by time) with an error as low — no ratio when the run's best was its start
    (it never improved), "later" when the run had it before shadecap's first fit."""
    _check_curves(shadecap, runs, key)
    what = _describe(key)
    head = f"| footprint steps | shadecap: seconds to the maps | {what} |" + "".join(
        f" {_run_name(r)}: time to it |" for r in runs)
    lines = [head, "|" + "---|" * (3 + len(runs))]
    for p in sorted(shadecap, key=lambda p: p["seconds"]):
        cells = []
        for run in runs:
            t = time_to_error(run["evaluations"], p[key], key)
            if t is None:
                b = _best(run["evaluations"], key)
                at = "its start" if float(b["seconds"]) <= 0 else f"at {b['seconds']:.0f} s"
                cells.append(f"never (best {b[key]:.4f} {at})")
            else:
                cells.append(f"{t:.0f} s (**{t / p['seconds']:.0f} ×**)")
        lines.append(f"| {p['steps']} | {p['seconds']:.1f} | {p[key]:.4f} | " + " | ".join(cells) + " |")
    if runs:
        # the other way round: each run's best error, and how soon shadecap's fits had it
        lines += ["", f"| run | its best {what} | at | shadecap: first fit as low | ratio |", "|---|---|---|---|---|"]
        for run in runs:
            b = _best(run["evaluations"], key)
            t = time_to_error(shadecap, b[key], key)
            first = "none of its fits" if t is None else f"{t:.1f} s"
            if float(b["seconds"]) <= 0:
                # the start was the run's best: it never improved on its initial maps
                at, ratio = "its start (never improved)", "–"
            else:
                at = f"{b['seconds']:.0f} s"
                ratio = "–" if t is None else _ratio(b["seconds"] / t)
            lines.append(f"| {_run_name(run)} | {b[key]:.4f} | {at} | {first} | {ratio} |")
    return "\n".join(lines)


def _ratio(r: float) -> str:
    """How much sooner shadecap's fit was than the run (``r`` = the run's time / shadecap's)."""
    return f"**{r:.0f} ×** sooner" if r >= 1 else f"{1 / r:.1f} × later"


def race_figure(shadecap: Sequence[dict], runs: Sequence[dict], path, keys: Sequence[str] = (DEFAULT_KEY,)) -> None:
    """Each error of ``keys`` against seconds (log–log, one panel per key): shadecap's points by footprint-step
    budget, each run's evaluations as a line."""
    keys = list(keys)
    if not keys:
        raise ValueError("keys must name at least one error to plot")
    for key in keys:
        _check_curves(shadecap, runs, key)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    fig, axes = plt.subplots(1, len(keys), figsize=(7 if len(keys) == 1 else 4.2 * len(keys), 4.5), squeeze=False)
    pts = sorted(shadecap, key=lambda p: p["seconds"])
    for ax, key in zip(axes[0], keys, strict=True):
        ax.plot([p["seconds"] for p in pts], [p[key] for p in pts], "o-", color="black", lw=2,
                label="shadecap (points: footprint steps)")
        for p in pts:
            ax.annotate(str(p["steps"]), (p["seconds"], p[key]), textcoords="offset points", xytext=(4, 4),
                        fontsize=8)
        for run in runs:
            ev = [e for e in sorted(run["evaluations"], key=lambda e: e["seconds"]) if e["seconds"] > 0]
            ax.plot([e["seconds"] for e in ev], [e[key] for e in ev], "-", label=_run_name(run))
        ax.set(xscale="log", yscale="log", xlabel="seconds", ylabel=_describe(key))
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("time to a map error on the same photos")
    if len(keys) == 1:
        axes[0][0].legend(fontsize=8)
        fig.tight_layout()
    else:                                       # one legend below the panels, clear of every curve
        handles, labels = axes[0][0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
        fig.tight_layout(rect=(0, 0.07, 1, 1))
    save_figure(fig, path)                      # (which closes the figure)
