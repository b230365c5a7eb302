#!/usr/bin/env python3
"""Stress-test every registered model: forward and gradient over the extreme domain, float32 and float64.

    python scripts/stress.py models [--random 4096] [--out docs/stability.md]
    python scripts/stress.py reconstruction [--work /tmp/stress] [--out docs/stability.md]

Writes a table (non-finite values/gradients, worst float32-vs-float64 deviation, worst gradient
magnitude) to stdout and, with --out, into the models section of docs/stability.md.
"""

import argparse
import sys

from capture.stress import model_stability_table, run_reconstruction_stress

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["models", "reconstruction"], help="what to stress")
    ap.add_argument("--work", default="/tmp/shadecap-stress", help="scratch folder for the stress datasets")
    ap.add_argument("--figure", default="docs/figures/reconstruction_stress.png")
    ap.add_argument("--random", type=int, default=4096, help="random (n, l, v) triples on top of the grid")
    ap.add_argument("--out", default=None, help="markdown file to write the table into")
    args = ap.parse_args()
    if args.what == "reconstruction":
        print(run_reconstruction_stress(args.work, out=args.out, figure=args.figure))
        sys.exit(0)
    table, ok = model_stability_table(n_random=args.random, out=args.out)
    print(table)
    sys.exit(0 if ok else 1)
