#!/usr/bin/env python3
"""Benchmark run time against error.

    python scripts/benchmark.py models [--n 1048576] [--compile NAME ...] [--device cpu|cuda] [--out docs/benchmarks.md]

`models`: forward and forward+backward throughput (samples/s) of every registered model, and the
error of each approximation the papers propose against the exact form it replaces.
Results go to stdout and, with --out, into the generated sections of docs/benchmarks.md.
"""

import argparse

from capture.benchmark import run_models_benchmark

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["models"])
    ap.add_argument("--n", type=int, default=1 << 20, help="samples per evaluation")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", nargs="*", default=None,
                    help="models to also time under torch.compile (default: the common ones)")
    ap.add_argument("--out", default=None, help="markdown file to write results into")
    args = ap.parse_args()
    print(run_models_benchmark(n=args.n, device=args.device, compile_names=args.compile, out=args.out))
