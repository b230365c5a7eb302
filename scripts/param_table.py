#!/usr/bin/env python3
"""Regenerate the tables of docs/models.md: the parameters from the canonical ParamSpecs (materials/params.py) and
the registered models from the registry (materials/model.py).

    python scripts/param_table.py [--out docs/models.md]

Replaces the blocks between ``<!-- begin:parameters -->`` and ``<!-- end:parameters -->`` and between
``<!-- begin:models -->`` and ``<!-- end:models -->`` (appended when absent), atomically; the text around them is
left as written. tests/materials/test_core.py fails when a committed table differs from the generated one.
"""

import argparse

from capture.report import replace_section
from materials.model import models_table
from materials.params import markdown_table

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/models.md")
    args = ap.parse_args()
    replace_section(args.out, "parameters", markdown_table())
    replace_section(args.out, "models", models_table())
    print(f"wrote the parameter and model tables into {args.out}")
