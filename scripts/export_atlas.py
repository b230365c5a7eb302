#!/usr/bin/env python3
"""Pack reconstruction folders into one Schüler two-RGBA atlas (+ sidecar, coat textures, meshes, GLB).

    python scripts/export_atlas.py RECON_DIR [RECON_DIR ...] --out DIR [--force] [--bits 16] [--transfer srgb]

The same as `shadecap export-atlas`; see docs/export.md.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.cli import main as cli_main  # noqa: E402


def main(argv=None) -> int:
    return cli_main(["export-atlas", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
