#!/usr/bin/env python
"""Write a synthetic shadecap dataset with ground truth (docs/dataset-format.md).

Examples::

    python scripts/make_synthetic.py --out data/demo                          # the README demo scene
    python scripts/make_synthetic.py --config small --model lambert --out /tmp/s
    python scripts/make_synthetic.py --mesh torus --views 24 --size 128 --noise 1000 --read-noise 0.002 \\
        --encoding srgb --out /tmp/torus_png
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.dataset import DatasetError  # noqa: E402
from capture.photo import PhotoError, PhotoModel  # noqa: E402
from capture.synthetic import SyntheticError, default_scene, make_synthetic, small_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", choices=("default", "small"), default="default", help="base scene (default: default)")
    ap.add_argument("--out", required=True, help="dataset folder to create (must not exist unless --overwrite)")
    ap.add_argument("--model", help="registered model name, or 'a+b' for a sum (default: ggx-lambert)")
    ap.add_argument("--model-options", help='JSON options of a single model, e.g. \'{"D": "beckmann"}\'')
    ap.add_argument("--mesh", help="uv_sphere, torus, nonconvex, plane, or a mesh file with UVs")
    ap.add_argument("--views", type=int, help="number of views")
    ap.add_argument("--size", type=int, help="image width = height (pixels)")
    ap.add_argument("--tex", type=int, help="ground-truth map size (texels)")
    ap.add_argument("--rig", choices=("orbit", "turntable", "random"), help="camera rig")
    ap.add_argument("--lights", choices=("flash", "fixed", "dome"), help="light rig")
    ap.add_argument("--n-lights", type=int, help="lights per view (flash) or in the studio")
    ap.add_argument("--exposure", type=float, default=1.0)
    ap.add_argument("--noise", type=float, metavar="FULL_WELL", help="shot noise: electrons at saturation")
    ap.add_argument("--read-noise", type=float, default=0.0, help="read noise σ (fraction of saturation)")
    ap.add_argument("--clip", action="store_true", help="clip highlights at 1 (always on for --encoding srgb)")
    ap.add_argument("--encoding", choices=("linear", "srgb"), default="linear", help="EXR float or 8-bit sRGB PNG")
    ap.add_argument("--supersample", type=int, help="k×k rays per pixel")
    ap.add_argument("--sampling", choices=("bilinear", "nearest"))
    ap.add_argument("--seed", type=int)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    try:
        photo = PhotoModel(exposure=a.exposure, full_well=a.noise, read_noise=a.read_noise,
                           clip=a.clip or a.encoding == "srgb", encoding=a.encoding)
        over = {k: v for k, v in {
            "mesh": a.mesh, "n_views": a.views, "image_size": a.size, "texture_size": a.tex, "camera_rig": a.rig,
            "light_rig": a.lights, "n_lights": a.n_lights, "supersample": a.supersample, "sampling": a.sampling,
            "seed": a.seed}.items() if v is not None}
        if a.model:
            over["model"] = a.model
            over["model_options"] = json.loads(a.model_options) if a.model_options else {}
        if a.config == "small":
            cfg = small_scene(over.pop("model", "ggx-lambert"), photo=photo, **over)
        else:
            cfg = replace(default_scene(), photo=photo, **over)
        t = time.perf_counter()
        out = make_synthetic(cfg, a.out, overwrite=a.overwrite)
    except (DatasetError, PhotoError, SyntheticError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    meta = json.loads((out / "scene.json").read_text())["meta"]
    cov = meta["highlight_coverage"]
    print(f"wrote {out} ({cfg.n_views} views {cfg.image_size[0]}×{cfg.image_size[1]}, maps {cfg.texture_size[0]}², "
          f"{time.perf_counter() - t:.2f} s); highlight coverage {100 * cov['coverage']:.1f} % of "
          f"{cov['observed_texels']} observed texels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
