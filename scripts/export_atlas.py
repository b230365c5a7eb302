#!/usr/bin/env python3
"""Pack reconstruction folders into one Schüler two-RGBA atlas (+ sidecar, coat textures, meshes, GLB).

    python scripts/export_atlas.py RECON_DIR [RECON_DIR ...] --out DIR [--force] [--bits 16] [--transfer srgb]

The same as `shadecap export-atlas` (one parser, every option in both); see docs/export.md.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.cli import script_main  # noqa: E402


def main(argv=None) -> int:
    return script_main("export-atlas", Path(__file__).name, argv)


if __name__ == "__main__":
    sys.exit(main())
