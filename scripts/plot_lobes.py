#!/usr/bin/env python3
"""Lobe plots of every registered model → docs/figures/lobes.png (or --out).

    python scripts/plot_lobes.py [--out docs/figures/lobes.png] [--models NAME ...]
"""

import argparse

from capture.plots import plot_lobes

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/figures/lobes.png")
    ap.add_argument("--models", nargs="*", default=None)
    args = ap.parse_args()
    print(plot_lobes(args.out, args.models))
