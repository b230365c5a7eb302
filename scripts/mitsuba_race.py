#!/usr/bin/env python3
"""Time to a map error: shadecap against Mitsuba 3's plain Adam on the same photos, in one run.

    python scripts/mitsuba_race.py DATASET [--steps 0,1,2,3,6] [--adam LR:SPP:SECONDS ...] [--adam-json FILE ...]
        [--metric MAP:SET ...] [--json OUT.json] [--out docs/benchmarks.md] [--block mitsuba-race]
        [--figure docs/figures/mitsuba_race.png]
    python scripts/mitsuba_race.py DATASET --from-json OUT.json [--metric ...] [--out ...] [--block ...] [--figure ...]

shadecap fits the dataset once per footprint-step budget of ``--steps`` (``capture.bench.race.shadecap_curve``: its
error at a time budget), then Mitsuba's Adam runs for each ``--adam LR:SPP:SECONDS`` (``scripts/mitsuba_adam.py``,
the same settings; default ``0.001:4:300`` and ``0.001:16:600``, the best rate measured in docs/benchmarks.md,
"Against Mitsuba 3's Adam"). ``--adam-json`` adds runs saved by ``mitsuba_adam.py --json`` instead of running them
(their times then come from another process). The table gives, for each shadecap point, the time each Adam run
first had an error as low and the ratio of the times; ``--out`` writes it into the ``mitsuba-race`` block of a
markdown file, ``--figure`` plots the curves, ``--json`` keeps every point and evaluation.

The dataset is a scene with ground truth in a model ``mitsuba_adam.py`` maps to Mitsuba: Lambert (the 256² torus of
``scripts/make_independent_fixtures.py --full``) or Lambert + GGX with F = 1 (its 256² sphere); shadecap fits it with
the truth's model. ``--metric`` names the errors raced on, as ``MAP:SET`` (a texel set of the report's
``maps_by_texel_set``: ``well_lit``, ``well_lit_visible_highlight``, …); by default the well-lit albedo and, for the
GGX scene, albedo, f0 and roughness on the visible highlights (the texels image-formation's targets are stated on).
One table per error; ``--block`` names the markdown block (default ``mitsuba-race``). ``--from-json`` makes the tables
and the figure again from a race saved by ``--json``, without fitting or running anything. Mitsuba is optional
elsewhere and needed here only for ``--adam``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[0]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from make_independent_fixtures import GGX_LAMBERT_F1, LAMBERT  # noqa: E402

from capture.bench.race import (  # noqa: E402
    DEFAULT_KEY,
    check_evaluations,
    error_key,
    race_figure,
    race_table,
    shadecap_curve,
)
from capture.bench.timing import machine_description  # noqa: E402
from capture.dataset import load_dataset, model_label, model_spec  # noqa: E402
from capture.report import atomic_write_text, replace_section  # noqa: E402

DEFAULT_ADAM = ("0.001:4:300", "0.001:16:600")
#: The errors raced on by default: the well-lit albedo, and for a specular truth its three maps on the visible
#: highlights, where image-formation's targets for the GGX sphere are stated (docs/image-formation.md).
SPECULAR_KEYS = tuple(error_key(n, "well_lit_visible_highlight") for n in ("albedo", "f0", "roughness"))


def adam_spec(text: str) -> tuple[float, int, float]:
    """An Adam run's ``LR:SPP:SECONDS`` (``--adam``, and ``benchmark.py scale --race-adam``) → (lr, spp, seconds),
    each checked."""
    try:
        lr, spp, seconds = text.split(":")
        out = float(lr), int(spp), float(seconds)
    except ValueError:
        raise argparse.ArgumentTypeError(f"an Adam run is LR:SPP:SECONDS, e.g. 0.001:4:300; got {text!r}") from None
    if not (out[0] > 0 and math.isfinite(out[0]) and out[1] >= 1 and out[2] > 0 and math.isfinite(out[2])):
        raise argparse.ArgumentTypeError(f"Adam run {text!r}: the rate and seconds must be positive, spp at least 1")
    return out


def steps_of(text: str) -> list[int]:
    """shadecap's footprint-step budgets ``0,1,2,3,6`` (``--steps``, ``benchmark.py scale --race-steps``), checked."""
    try:
        steps = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"footprint-step budgets are written like 0,1,2,3,6; got {text!r}") from None
    if not steps or any(s < 0 for s in steps):
        raise argparse.ArgumentTypeError(f"footprint-step budgets must be ≥ 0, at least one; got {text!r}")
    return steps


def _metric(text: str) -> str:
    """``MAP:SET`` → the evaluation key of that error."""
    name, sep, texel_set = text.partition(":")
    if not (sep and name and texel_set):
        raise argparse.ArgumentTypeError(f"--metric takes MAP:SET, e.g. roughness:well_lit_visible_highlight; got "
                                         f"{text!r}")
    return error_key(name, texel_set)


class RaceError(ValueError):
    """A race that cannot be run: a scene the Adam baseline does not map, or an error one side does not measure."""


def race_keys(dataset, metric: Sequence[str] | None = None) -> list[str]:
    """The errors to race on for ``dataset`` (``metric``: evaluation keys, or None for the defaults), each checked
    to be one both sides measure on its scene, before anything is fitted."""
    return _keys_of(load_dataset(dataset, check_images=False), dataset, metric)


def _keys_of(ds, dataset, metric: Sequence[str] | None) -> list[str]:
    """:func:`race_keys` of the loaded dataset ``ds`` (``dataset``: its path, for the messages)."""
    spec = None if ds.gt is None else model_spec(ds.gt.model)
    if spec not in (model_spec(LAMBERT), model_spec(GGX_LAMBERT_F1)):
        raise RaceError(f"{dataset} is not a Lambert or Lambert + GGX (F = 1) scene with ground truth, the models the "
                        f"Adam baseline maps to Mitsuba (e.g. the torus and sphere of "
                        f"scripts/make_independent_fixtures.py --full)")
    specular = spec == model_spec(GGX_LAMBERT_F1)
    keys = list(metric) if metric else [DEFAULT_KEY, *(SPECULAR_KEYS if specular else ())]
    # what both sides measure: the truth's maps (roughness also as α) on the texel sets mitsuba_adam.py evaluates
    names = set(ds.gt.maps) | ({"roughness_alpha"} if "roughness" in ds.gt.maps else set())
    sets = ["well_lit", *(("well_lit_highlight", "well_lit_visible_highlight") if specular else ())]
    measured = {error_key(n, k) for n in names for k in sets}
    for k in keys:
        if k not in measured:
            raise RaceError(f"--metric: {k} is not an error both sides measure on this scene; choose maps from "
                            f"{sorted(names)} and texel sets from {sets}")
    return keys


def race(dataset, steps: Sequence[int], specs: Sequence[tuple[float, int, float]], saved: Sequence[dict] = (), *,
         keys: Sequence[str] | None = None, every: int = 96, threads: int | None = None, json_path=None, figure=None,
         out=None, block: str = "mitsuba-race") -> str:
    """shadecap's fits at the footprint-step budgets ``steps``, then Mitsuba's Adam for each ``(lr, spp, seconds)``
    of ``specs`` (plus the ``saved`` runs), raced on ``keys`` (:func:`race_keys`); returns the tables (one per
    error), and writes the JSON of every point, the figure and the ``block`` of the markdown file ``out`` when
    given."""
    ds = load_dataset(dataset, check_images=False)
    keys = _keys_of(ds, dataset, keys)
    try:                                # the saved runs checked before minutes of fitting, not after
        for run in saved:
            for k in keys:
                check_evaluations(run.get("evaluations", ()), f"the saved Adam run (lr {run.get('lr')}, "
                                  f"{run.get('spp')} spp)", k)
    except ValueError as e:
        raise RaceError(str(e)) from None
    label = model_label(ds.gt.model)

    def said(p: dict) -> None:
        print(f"shadecap, {p['steps']} footprint steps: {p['seconds']:.1f} s to the maps, "
              + ", ".join(f"{k} {p[k]:.4f}" for k in keys), flush=True)

    print(f"shadecap: {len(steps)} fits of {dataset} with {label} (footprint steps {', '.join(map(str, steps))})",
          flush=True)
    shadecap = shadecap_curve(dataset, steps, label, threads=threads, on_point=said)
    runs = []
    if specs:
        from mitsuba_adam import run as adam_run

        runs = [adam_run(str(dataset), seconds, spp, lr, every) for lr, spp, seconds in specs]
    runs += list(saved)
    note = ("Every run in one process, one after the other." if not saved else
            "The Adam runs from saved files ran in another process.")
    machine = machine_description()
    if json_path:
        atomic_write_text(Path(json_path), json.dumps({"dataset": str(dataset), "machine": machine, "note": note,
                                                       "shadecap": shadecap, "adam": runs}, indent=1) + "\n")
    return write_race(shadecap, runs, keys, f"Machine: {machine}. {note}", figure=figure, out=out, block=block)


def write_race(shadecap: Sequence[dict], runs: Sequence[dict], keys: Sequence[str], caption: str, *, figure=None,
               out=None, block: str = "mitsuba-race") -> str:
    """The race's tables (one per error of ``keys``), printed, plotted into ``figure`` and written under
    ``caption`` into the ``block`` of the markdown file ``out`` when given."""
    try:
        table = "\n\n".join(race_table(shadecap, runs, k) for k in keys)
    except ValueError as e:
        raise RaceError(str(e)) from None
    print(table)
    if figure:
        race_figure(shadecap, runs, figure, keys)
    if out:
        replace_section(Path(out), block, f"{caption}\n\n{table}\n")
    return table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a Lambert or Lambert + GGX (F = 1) dataset folder with ground truth (gt/)")
    ap.add_argument("--steps", type=steps_of, default=[0, 1, 2, 3, 6],
                    help="shadecap's footprint-step budgets, comma-separated (default 0,1,2,3,6)")
    ap.add_argument("--adam", type=adam_spec, nargs="*", default=None,
                    help=f"Mitsuba Adam runs as LR:SPP:SECONDS (default {' '.join(DEFAULT_ADAM)}; none with "
                         f"--adam-json alone)")
    ap.add_argument("--adam-json", nargs="*", default=[], help="Adam runs saved by scripts/mitsuba_adam.py --json")
    ap.add_argument("--every", type=int, default=96, help="Adam steps between evaluations (default 96)")
    ap.add_argument("--metric", type=_metric, nargs="+", default=None,
                    help="errors to race on as MAP:SET (default: albedo:well_lit and, for GGX, albedo, f0 and "
                         "roughness on well_lit_visible_highlight)")
    ap.add_argument("--block", default="mitsuba-race", help="the --out file's block (default mitsuba-race)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads of shadecap's fits")
    ap.add_argument("--json", help="write every shadecap point and Adam evaluation here")
    ap.add_argument("--out", help="markdown file whose --block block gets the tables")
    ap.add_argument("--figure", help="PNG of the curves")
    ap.add_argument("--from-json", help="make the tables and the figure from a race saved by --json, without running")
    args = ap.parse_args(argv)
    if args.every < 1:
        ap.error("--every must be at least 1")
    specs = [adam_spec(s) for s in DEFAULT_ADAM] if args.adam is None and not args.adam_json else (args.adam or [])
    saved = []
    for f in args.adam_json:
        try:
            saved.append(json.loads(Path(f).read_text()))
        except (OSError, ValueError) as e:
            ap.error(f"--adam-json {f}: {e}")
        if not isinstance(saved[-1], dict) or not {"lr", "spp", "evaluations"} <= saved[-1].keys():
            ap.error(f"--adam-json {f}: not a run of scripts/mitsuba_adam.py --json (needs lr, spp and evaluations)")
    if args.from_json:
        try:
            saved_race = json.loads(Path(args.from_json).read_text())
            shadecap, runs = saved_race["shadecap"], saved_race["adam"]
            caption = (f"Machine: {saved_race['machine']}. {saved_race['note']} (Tables made from "
                       f"{Path(args.from_json).name}.)")
        except (OSError, ValueError, KeyError, TypeError) as e:
            ap.error(f"--from-json {args.from_json}: not a race saved by --json ({e!r})")
        try:
            write_race(shadecap, runs, race_keys(args.dataset, args.metric), caption, figure=args.figure,
                       out=args.out, block=args.block)
        except RaceError as e:
            ap.error(str(e))
        return 0
    try:
        race(args.dataset, args.steps, specs, saved, keys=args.metric, every=args.every, threads=args.threads,
             json_path=args.json, figure=args.figure, out=args.out, block=args.block)
    except RaceError as e:
        ap.error(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
