#!/usr/bin/env python3
"""Regenerate the parameter table of docs/models.md from the canonical ParamSpecs (materials/params.py).

    python scripts/param_table.py [--out docs/models.md]

Replaces the block between ``<!-- begin:parameters -->`` and ``<!-- end:parameters -->`` (appended when absent),
atomically; the text around it is left as written. tests/materials/test_core.py fails when the committed table
differs from the generated one.
"""

import argparse

from capture.report import replace_section
from materials.params import markdown_table

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/models.md")
    args = ap.parse_args()
    replace_section(args.out, "parameters", markdown_table())
    print(f"wrote the parameter table into {args.out}")
