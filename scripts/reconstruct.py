#!/usr/bin/env python
"""Recover material maps from a dataset: ``python scripts/reconstruct.py DATASET --model NAME|auto --out DIR``.

The same as `shadecap reconstruct` (one parser, every option in both); see docs/reconstruction.md.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.cli import script_main  # noqa: E402


def main(argv=None) -> int:
    return script_main("reconstruct", Path(__file__).name, argv)  # errors: one line, exit 2; Ctrl-C: exit 130


if __name__ == "__main__":
    sys.exit(main())
