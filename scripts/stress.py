#!/usr/bin/env python3
"""Stress-test every registered model: forward and gradient over the extreme domain, float32 and float64.

    python scripts/stress.py models [--random 4096] [--out docs/stability.md]
    python scripts/stress.py sampled [--samples 10000000] [--chunk 250000] [--variant-samples N]
                                     [--work /tmp/shadecap-sampled] [--model NAME ...] [--out docs/stability.md]
    python scripts/stress.py reconstruction [--work /tmp/stress] [--out docs/stability.md]

models: a grid of extreme cosines and parameters; writes a table (non-finite values/gradients, worst
float32-vs-float64 deviation, worst gradient magnitude) to stdout and, with --out, into the models section
of docs/stability.md. sampled: every model on --samples random and edge triples (grazing mirror pairs
included) per dtype, values and gradients, in chunks; each finished row is kept in --work, so an
interrupted run resumes; the table goes into the models-sampled section. Exit status 1 if anything was
not finite.
"""

import argparse
import sys

from capture.bench import model_sampled_table, model_stability_table, run_reconstruction_stress

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["models", "sampled", "reconstruction"], help="what to stress")
    ap.add_argument("--work", default=None, help="scratch folder: stress datasets (reconstruction, default "
                    "/tmp/shadecap-stress) or finished rows (sampled, default /tmp/shadecap-sampled)")
    ap.add_argument("--samples", type=int, default=10_000_000, help="sampled: triples per model and dtype")
    ap.add_argument("--chunk", type=int, default=250_000, help="sampled: triples per evaluation")
    ap.add_argument("--variant-samples", type=int, default=None,
                    help="sampled: triples per dtype for the option variants (default a tenth of --samples)")
    ap.add_argument("--model", action="append", default=None, help="sampled: only this model (repeatable)")
    ap.add_argument("--figure", default="docs/figures/reconstruction_stress.png")
    ap.add_argument("--random", type=int, default=4096, help="random (n, l, v) triples on top of the grid")
    ap.add_argument("--out", default=None, help="markdown file to write the table into")
    args = ap.parse_args()
    if args.what == "reconstruction":
        print(run_reconstruction_stress(args.work or "/tmp/shadecap-stress", out=args.out, figure=args.figure))
        sys.exit(0)
    if args.what == "sampled":
        table, ok = model_sampled_table(args.samples, args.chunk, out=args.out,
                                        work=args.work or "/tmp/shadecap-sampled", names=args.model,
                                        variant_samples=args.variant_samples)
        print(table)
        sys.exit(0 if ok else 1)
    table, ok = model_stability_table(n_random=args.random, out=args.out)
    print(table)
    sys.exit(0 if ok else 1)
