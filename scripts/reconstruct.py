#!/usr/bin/env python
"""Recover material maps from a dataset: ``python scripts/reconstruct.py DATASET --model NAME|auto --out DIR``.

Thin wrapper over :func:`capture.reconstruct.reconstruct` (see docs/reconstruction.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# shared with `shadecap reconstruct`
from capture.cli import add_holdout_arg, add_known_args, add_pooled_arg, known_options, run  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--model", default="auto", help="registered model name, 'a+b', or 'auto'")
    ap.add_argument("--out", required=True, help="output folder (must not exist unless --force)")
    ap.add_argument("--solver", choices=("fast", "adam"), default="fast")
    ap.add_argument("--loss", choices=("l2", "huber", "l1"), default="l2")
    ap.add_argument("--tex", type=int, default=None, help="map size T (T×T); default: ground truth's or 256")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--grid", type=int, default=None, help="fast path: grid size of the closed-form initialisation")
    ap.add_argument("--schedule", choices=("joint", "staged"), default=None)
    ap.add_argument("--smoothness", type=float, default=None)
    ap.add_argument("--sampling", choices=("nearest", "bilinear"), default=None,
                    help="how samples read the maps (default: as the dataset's ground truth, else bilinear)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (1 is faster on a loaded machine)")
    ap.add_argument("--float64", action="store_true", help="evaluate the model in float64")
    add_pooled_arg(ap)
    add_known_args(ap)
    add_holdout_arg(ap)
    ap.add_argument("--force", action="store_true")
    return run("reconstruct", _reconstruct, ap.parse_args(argv))  # errors: one line, exit 2; Ctrl-C: exit 130


def _reconstruct(a) -> int:
    import torch

    from capture.reconstruct import reconstruct

    opts = {k: v for k, v in (("iterations", a.iterations), ("grid", a.grid), ("schedule", a.schedule),
                              ("smoothness", a.smoothness), ("pooled", a.pooled)) if v is not None}
    reconstruct(a.dataset, model=a.model, out_dir=a.out, force=a.force, solver=a.solver, loss=a.loss,
                texture_size=a.tex, dtype=torch.float64 if a.float64 else torch.float32, sampling=a.sampling,
                threads=a.threads, holdout=a.holdout, **known_options(a), **opts)
    print((Path(a.out) / "summary.txt").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
