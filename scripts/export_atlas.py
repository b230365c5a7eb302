#!/usr/bin/env python
"""Pack reconstruction folders into one Schüler two-RGBA atlas (+ sidecar, meshes, GLB).

    python scripts/export_atlas.py RECON_DIR... --out DIR [--force] [--bits 16] [--transfer srgb]
        [--format exr] [--size 1024] [--gutter 4] [--no-glb]

Thin wrapper over capture.export.export_atlas_dirs (the same function behind `shadecap export-atlas`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.export import ExportError, export_atlas_dirs  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recon_dirs", nargs="+", type=Path, help="reconstruction folders (albedo.exr, f0.exr, ...)")
    ap.add_argument("--out", required=True, type=Path, help="atlas folder to create")
    ap.add_argument("--force", action="store_true", help="replace an existing output folder")
    ap.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bit depth (default 8)")
    ap.add_argument("--transfer", choices=("gamma2.2", "srgb"), default="gamma2.2",
                    help="colour encoding of the RGB channels (default Schüler's gamma 2.2)")
    ap.add_argument("--format", dest="fmt", choices=("png", "exr"), default="png", help="texture file format")
    ap.add_argument("--size", type=int, default=None, help="square atlas size in texels (default: smallest fit)")
    ap.add_argument("--gutter", type=int, default=4, help="free texels around each material (default 4)")
    ap.add_argument("--no-glb", dest="glb", action="store_false", help="do not write atlas.glb")
    args = ap.parse_args(argv)
    try:
        side = export_atlas_dirs(args.recon_dirs, args.out, atlas_size=args.size, gutter=args.gutter,
                                 bits=args.bits, fmt=args.fmt, transfer=args.transfer, force=args.force, glb=args.glb)
    except ExportError as err:
        print(f"export_atlas: error: {err}", file=sys.stderr)
        return 2
    size = side["size"]
    print(f"wrote {args.out} ({size['width']}x{size['height']}, {len(side['materials'])} material(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
