#!/usr/bin/env python3
"""Time to a map error: shadecap against Mitsuba 3's plain Adam on the same photos, in one run.

    python scripts/mitsuba_race.py DATASET [--steps 0,1,2,3,6] [--adam LR:SPP:SECONDS ...] [--adam-json FILE ...]
        [--json OUT.json] [--out docs/benchmarks.md] [--figure docs/figures/mitsuba_race.png]

shadecap fits the dataset once per footprint-step budget of ``--steps`` (``capture.bench.race.shadecap_curve``: its
error at a time budget), then Mitsuba's Adam runs for each ``--adam LR:SPP:SECONDS`` (``scripts/mitsuba_adam.py``,
the same settings; default ``0.001:4:300`` and ``0.001:16:600``, the best rate measured in docs/benchmarks.md,
"Against Mitsuba 3's Adam"). ``--adam-json`` adds runs saved by ``mitsuba_adam.py --json`` instead of running them
(their times then come from another process). The table gives, for each shadecap point, the time each Adam run
first had an error as low and the ratio of the times; ``--out`` writes it into the ``mitsuba-race`` block of a
markdown file, ``--figure`` plots the curves, ``--json`` keeps every point and evaluation.

The dataset must be a Lambert scene with ground truth (e.g. the 256² torus of
``scripts/make_independent_fixtures.py --full``); Mitsuba is optional elsewhere and needed here only for ``--adam``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[0]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.bench.race import race_figure, race_table, shadecap_curve  # noqa: E402
from capture.bench.timing import machine_description  # noqa: E402
from capture.dataset import load_dataset, model_label  # noqa: E402
from capture.report import atomic_write_text, replace_section  # noqa: E402

DEFAULT_ADAM = ("0.001:4:300", "0.001:16:600")


def _adam_spec(text: str) -> tuple[float, int, float]:
    """``LR:SPP:SECONDS`` → (lr, spp, seconds), each checked."""
    try:
        lr, spp, seconds = text.split(":")
        out = float(lr), int(spp), float(seconds)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--adam takes LR:SPP:SECONDS, e.g. 0.001:4:300; got {text!r}") from None
    if not (out[0] > 0 and math.isfinite(out[0]) and out[1] >= 1 and out[2] > 0 and math.isfinite(out[2])):
        raise argparse.ArgumentTypeError(f"--adam {text!r}: the rate and seconds must be positive, spp at least 1")
    return out


def _steps(text: str) -> list[int]:
    try:
        steps = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--steps takes footprint-step budgets like 0,1,2,3,6; got {text!r}") from None
    if not steps or any(s < 0 for s in steps):
        raise argparse.ArgumentTypeError(f"--steps needs budgets ≥ 0, at least one; got {text!r}")
    return steps


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a Lambert dataset folder with ground truth (scene.json with gt/)")
    ap.add_argument("--steps", type=_steps, default=[0, 1, 2, 3, 6],
                    help="shadecap's footprint-step budgets, comma-separated (default 0,1,2,3,6)")
    ap.add_argument("--adam", type=_adam_spec, nargs="*", default=None,
                    help=f"Mitsuba Adam runs as LR:SPP:SECONDS (default {' '.join(DEFAULT_ADAM)}; none with "
                         f"--adam-json alone)")
    ap.add_argument("--adam-json", nargs="*", default=[], help="Adam runs saved by scripts/mitsuba_adam.py --json")
    ap.add_argument("--every", type=int, default=96, help="Adam steps between evaluations (default 96)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads of shadecap's fits")
    ap.add_argument("--json", help="write every shadecap point and Adam evaluation here")
    ap.add_argument("--out", help="markdown file whose mitsuba-race block gets the table")
    ap.add_argument("--figure", help="PNG of the curves")
    args = ap.parse_args(argv)
    if args.every < 1:
        ap.error("--every must be at least 1")
    ds = load_dataset(args.dataset, check_images=False)
    if ds.gt is None or model_label(ds.gt.model) != "lambert":
        ap.error(f"{args.dataset} is not a Lambert scene with ground truth: the Adam baseline fits a Lambert albedo "
                 f"(e.g. the torus of scripts/make_independent_fixtures.py --full)")
    specs = [_adam_spec(s) for s in DEFAULT_ADAM] if args.adam is None and not args.adam_json else (args.adam or [])
    saved = []
    for f in args.adam_json:
        try:
            saved.append(json.loads(Path(f).read_text()))
        except (OSError, ValueError) as e:
            ap.error(f"--adam-json {f}: {e}")
        if not isinstance(saved[-1], dict) or not {"lr", "spp", "evaluations"} <= saved[-1].keys():
            ap.error(f"--adam-json {f}: not a run of scripts/mitsuba_adam.py --json (needs lr, spp and evaluations)")
    shadecap = shadecap_curve(args.dataset, args.steps, "lambert", threads=args.threads)
    for p in shadecap:
        print(f"shadecap, {p['steps']} footprint steps: {p['seconds']:.1f} s to the maps, "
              f"albedo RMSE (well lit) {p['albedo_rmse_well_lit']:.4f}", flush=True)
    runs = []
    if specs:
        from mitsuba_adam import run as adam_run

        runs = [adam_run(args.dataset, seconds, spp, lr, args.every) for lr, spp, seconds in specs]
    runs += saved
    table = race_table(shadecap, runs)
    print(table)
    if args.json:
        atomic_write_text(Path(args.json), json.dumps({"dataset": str(args.dataset), "shadecap": shadecap,
                                                       "adam": runs}, indent=1) + "\n")
    if args.figure:
        race_figure(shadecap, runs, args.figure)
    if args.out:
        note = (f"Machine: {machine_description()}. "
                + ("Every run in one process, one after the other." if not saved else
                   "The Adam runs from saved files ran in another process."))
        replace_section(Path(args.out), "mitsuba-race", note + "\n\n" + table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
