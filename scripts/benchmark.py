#!/usr/bin/env python3
"""Benchmark run time against error.

    python scripts/benchmark.py models [--n 1048576] [--compile NAME ...] [--device cpu|cuda] [--out docs/benchmarks.md]

`models`: forward and forward+backward throughput (samples/s) of every registered model, and the
error of each approximation the papers propose against the exact form it replaces.

    python scripts/benchmark.py reconstruction [--scene default|small] [--rigs flash fixed] [--threads N]
        [--adam LR:ITERS ...] [--no-sweeps] [--out docs/benchmarks.md] [--figure docs/figures/reconstruction_pareto.png]

`reconstruction`: end-to-end time against map error of the fast path (and its variants) and Adam
(capture.benchmark.run_reconstruction_benchmark), its Pareto plot (--figure), and sweeps of the fast path over texture
resolution and number of materials.

    python scripts/benchmark.py independent [--datasets tests/fixtures/mitsuba/*] [--out docs/benchmarks.md]

`independent`: reconstruct datasets rendered by another renderer (scripts/make_independent_fixtures.py; the committed
fixtures by default, `--full` renders of the benchmark size elsewhere) with pixel centres and with pixel footprints
(capture.benchmark.run_independent_benchmark).
Results go to stdout and, with --out, into the generated sections of docs/benchmarks.md.
"""

import argparse
import glob

from capture.benchmark import run_independent_benchmark, run_models_benchmark, run_reconstruction_benchmark

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["models", "reconstruction", "independent"])
    ap.add_argument("--datasets", nargs="+", default=sorted(glob.glob("tests/fixtures/mitsuba/*/")),
                    help="independent: dataset folders rendered by another renderer")
    ap.add_argument("--scene", choices=["default", "small"], default="default")
    ap.add_argument("--rigs", nargs="+", default=["flash", "fixed"])
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--adam", nargs="*", default=["0.05:200", "0.02:500"], help="Adam runs as LR:ITERATIONS")
    ap.add_argument("--no-variants", action="store_true", help="fast path with default options only")
    ap.add_argument("--n", type=int, default=1 << 20, help="samples per evaluation")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", nargs="*", default=None,
                    help="models to also time under torch.compile (default: the common ones)")
    ap.add_argument("--out", default=None, help="markdown file to write results into")
    ap.add_argument("--figure", default=None, help="reconstruction: Pareto plot PNG")
    ap.add_argument("--no-sweeps", action="store_true", help="reconstruction: skip the texture/material sweeps")
    args = ap.parse_args()
    if args.what == "independent":
        print(run_independent_benchmark(args.datasets, out=args.out, threads=args.threads))
    elif args.what == "models":
        print(run_models_benchmark(n=args.n, device=args.device, compile_names=args.compile, out=args.out))
    else:
        adam = tuple((float(a.split(":")[0]), int(a.split(":")[1])) for a in args.adam)
        print(run_reconstruction_benchmark(out=args.out, scene=args.scene, rigs=tuple(args.rigs), threads=args.threads,
                                           adam=adam, fast_variants=not args.no_variants, figure=args.figure,
                                           sweeps=not args.no_sweeps))
