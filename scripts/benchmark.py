#!/usr/bin/env python3
"""Benchmark run time against error.

    python scripts/benchmark.py models [--n 1048576] [--compile NAME ...] [--device cpu|cuda] [--out docs/benchmarks.md]

`models`: forward, forward+backward and per-sample Jacobian throughput (samples/s) of every registered model
(capture.bench.models.run_models_benchmark).

    python scripts/benchmark.py approximations [--out docs/benchmarks.md] [--figure docs/figures/approximations.png]

`approximations`: the error of each approximation the papers propose against the exact form it replaces, and the
cost of both (capture.bench.models.run_approximation_benchmark), with its cost-against-error plot (--figure).

    python scripts/benchmark.py scaling [--out docs/benchmarks.md]

`scaling`: how the forward pipeline's time and memory grow with views, image size, texture size and lights
(capture.bench.scaling.run_scaling_benchmark).

    python scripts/benchmark.py reconstruction [--scene default|small] [--rigs flash fixed] [--threads N]
        [--adam LR:ITERS ...] [--no-sweeps] [--out docs/benchmarks.md] [--figure docs/figures/reconstruction_pareto.png]

`reconstruction`: end-to-end time against map error of the fast path (and its variants) and Adam
(capture.bench.reconstruction.run_reconstruction_benchmark), its Pareto plot (--figure), and sweeps of the fast path
over texture resolution and number of materials.

    python scripts/benchmark.py independent [--datasets tests/fixtures/mitsuba/*] [--device cpu|cuda]
        [--out docs/benchmarks.md]

`independent`: reconstruct datasets rendered by another renderer (scripts/make_independent_fixtures.py; the committed
fixtures by default, `--full` renders of the benchmark size elsewhere) with pixel centres and with pixel footprints
(capture.bench.reconstruction.run_independent_benchmark).

    python scripts/benchmark.py measured [--threads 1]

`measured`: reconstruct a scene of measured materials (NBRDF fits of MERL) with several models and score held-out
views and the per-region maps (capture.bench.measured.capture_benchmark); prints the tables of docs/measured-fits.md,
"Capture of measured materials" (needs the NBRDF weights, ≈ 5 min on one thread).

    python scripts/benchmark.py scale [--configs 8x256x256 32x512x512 ... | none] [--devices cpu cuda] [--threads N]
        [--work DIR] [--rows-json FILE] [--earlier ROWS.json ...] [--out docs/benchmarks.md]
        [--figure docs/figures/scale.png]

`scale`: time and peak memory of `shadecap reconstruct` end to end against the observed pixels (VIEWSxIMAGExMAPS
configurations), per stage and device, with growth exponents (capture.bench.scale.run_scale_benchmark).

    python scripts/benchmark.py scale --race 8x256x256 [--race-adam LR:SPP:SECONDS ...] [--race-steps 0,1,2,3,6]
        [--race-json FILE] [--race-figure docs/figures/scale_race.png] [--out docs/benchmarks.md] ...

`--race`: in the same run, shadecap against Mitsuba 3's plain Adam on one configuration's scene in the GGX + Lambert
(F = 1) model Mitsuba reproduces (capture.bench.scale.race_dataset): the time each takes to reach a map error
(scripts/mitsuba_race.py; needs Mitsuba and Debian's libllvm19), into the `scale-race` block of --out.

Results go to stdout and, with --out, into the generated sections of docs/benchmarks.md.
"""

import argparse
import glob

import torch

from capture.bench import (
    DEFAULT_SCALE_CONFIGS,
    benchmark_table,
    capture_benchmark,
    run_approximation_benchmark,
    run_independent_benchmark,
    run_models_benchmark,
    run_reconstruction_benchmark,
    run_scale_benchmark,
    run_scaling_benchmark,
)
from renderer.device import resolve_device, tune_allocator


def _config(text: str) -> tuple[int, int, int] | str:
    if text == "none":
        return text
    try:
        views, image, tex = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: write a configuration as VIEWSxIMAGExMAPS, e.g. 32x512x512") \
            from None
    return views, image, tex


def _race_args(ap: argparse.ArgumentParser, args):
    """``scale --race``: its options checked before anything runs; returns the race to run after the scale rows."""
    import tempfile
    from pathlib import Path

    from mitsuba_race import RaceError, adam_spec, race, steps_of

    from capture.bench.scale import race_dataset

    if args.race == "none":
        ap.error("--race takes one VIEWSxIMAGExMAPS configuration")
    try:
        specs = [adam_spec(s) for s in args.race_adam]
        steps = steps_of(args.race_steps)
    except argparse.ArgumentTypeError as e:
        ap.error(str(e))

    def run() -> None:
        tmp = None if args.work else tempfile.TemporaryDirectory()
        try:
            data = race_dataset(*args.race, Path(args.work or tmp.name), args.threads)
            race(data, steps, specs, threads=args.threads, json_path=args.race_json, figure=args.race_figure,
                 out=args.out, block="scale-race")
        except RaceError as e:
            ap.error(str(e))
        finally:
            if tmp is not None:
                tmp.cleanup()

    return run


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["models", "approximations", "scaling", "reconstruction", "independent", "measured",
                                     "scale"])
    ap.add_argument("--datasets", nargs="+", default=sorted(glob.glob("tests/fixtures/mitsuba/*/")),
                    help="independent: dataset folders rendered by another renderer")
    ap.add_argument("--scene", choices=["default", "small"], default="default")
    ap.add_argument("--rigs", nargs="+", default=["flash", "fixed"])
    ap.add_argument("--threads", type=int, default=None,
                    help="reconstruction, independent: torch threads of the reconstructions; measured: torch threads "
                         "(default: torch's)")
    ap.add_argument("--adam", nargs="*", default=["0.05:200", "0.02:500"], help="Adam runs as LR:ITERATIONS")
    ap.add_argument("--no-variants", action="store_true", help="fast path with default options only")
    ap.add_argument("--n", type=int, default=1 << 20, help="samples per evaluation")
    ap.add_argument("--device", default="cpu", help="models, independent: where the evaluations and fits run "
                    "(cpu, cuda, cuda:N or auto)")
    ap.add_argument("--configs", nargs="+", type=_config, default=list(DEFAULT_SCALE_CONFIGS),
                    help="scale: VIEWSxIMAGExMAPS configurations")
    ap.add_argument("--devices", nargs="+", default=["cpu"], help="scale: devices to run each configuration on")
    ap.add_argument("--work", default=None, help="scale: folder for the datasets and reconstructions (kept)")
    ap.add_argument("--rows-json", default=None, help="scale: also write the rows as JSON")
    ap.add_argument("--earlier", nargs="+", default=[], help="scale: JSON rows of earlier runs to show beside "
                    "(e.g. from a GPU machine); with --configs none, the table is made from them alone")
    ap.add_argument("--race", type=_config, default=None,
                    help="scale: also race shadecap against Mitsuba's Adam on this VIEWSxIMAGExMAPS configuration")
    ap.add_argument("--race-adam", nargs="+", default=["0.005:4:300"],
                    help="scale --race: Mitsuba Adam runs as LR:SPP:SECONDS (default 0.005:4:300)")
    ap.add_argument("--race-steps", default="0,1,2,3,6", help="scale --race: shadecap's footprint-step budgets")
    ap.add_argument("--race-json", default=None, help="scale --race: write every point and evaluation here")
    ap.add_argument("--race-figure", default=None, help="scale --race: the race's plot")
    ap.add_argument("--compile", nargs="*", default=None,
                    help="models to also time under torch.compile (default: the common ones)")
    ap.add_argument("--out", default=None, help="markdown file to write results into")
    ap.add_argument("--figure", default=None, help="approximations, reconstruction, scale: the plot's PNG")
    ap.add_argument("--no-sweeps", action="store_true", help="reconstruction: skip the texture/material sweeps")
    args = ap.parse_args()
    args.device = str(resolve_device(args.device))
    tune_allocator()                    # as the command line does: the figures are what its users see
    if args.what == "scale":
        race = _race_args(ap, args) if args.race is not None else None
        configs = [] if args.configs == ["none"] else args.configs
        if configs or args.earlier or race is None:
            print(run_scale_benchmark(configs, args.devices, work=args.work, threads=args.threads, out=args.out,
                                      figure=args.figure, rows_json=args.rows_json, earlier=args.earlier))
        if race is not None:
            race()
    elif args.what == "independent":
        print(run_independent_benchmark(args.datasets, out=args.out, threads=args.threads, device=args.device))
    elif args.what == "models":
        print(run_models_benchmark(n=args.n, device=args.device, compile_names=args.compile, out=args.out))
    elif args.what == "approximations":
        print(run_approximation_benchmark(out=args.out, figure=args.figure))
    elif args.what == "scaling":
        print(run_scaling_benchmark(out=args.out))
    elif args.what == "measured":
        if args.threads is not None:
            torch.set_num_threads(args.threads)
        print(benchmark_table(capture_benchmark()))
    else:
        adam = tuple((float(a.split(":")[0]), int(a.split(":")[1])) for a in args.adam)
        print(run_reconstruction_benchmark(out=args.out, scene=args.scene, rigs=tuple(args.rigs), threads=args.threads,
                                           adam=adam, fast_variants=not args.no_variants, figure=args.figure,
                                           sweeps=not args.no_sweeps))
