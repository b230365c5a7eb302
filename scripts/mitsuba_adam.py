#!/usr/bin/env python3
"""The plain-Adam baseline of an independent differentiable renderer: Mitsuba 3 recovers a Lambert albedo map.

    python scripts/mitsuba_adam.py DATASET [--seconds 600] [--spp 4] [--lr 0.02] [--json OUT.json]

The dataset is a Lambert scene of shadecap's format (e.g. the 256² Mitsuba torus of
``scripts/make_independent_fixtures.py --full``). Mitsuba's ``llvm_ad_rgb`` variant renders it with the same
conventions as the fixtures (the mesh, cameras, point lights and texture mapping of
``make_independent_fixtures``: docs/independent-renders.md) and a ``diffuse`` BSDF whose reflectance bitmap starts at
0.5 grey; each Adam step renders one view (views in a fixed shuffled order, ``--spp`` samples per pixel, the
``prb`` integrator with direct light only), takes the mean squared error against the photo and updates the bitmap
(clamped to [0, 1]). Every ``--every`` steps it prints the elapsed time and the albedo RMSE on shadecap's well-lit
texels (``capture.metrics.well_lit_texels``, the set of the independent benchmark), so the time Mitsuba's Adam needs
to reach an error compares with ``shadecap reconstruct``'s on the same photos (docs/benchmarks.md, "Against
Mitsuba 3's Adam"). The first steps include Mitsuba's kernel compilation; the JSON keeps every evaluation.

Mitsuba is an optional dependency (``pip install mitsuba``; the LLVM variant needs Debian's ``libllvm19``, found at
its Debian path or named by ``DRJIT_LIBLLVM_PATH``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[0]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from make_independent_fixtures import import_mitsuba, mitsuba_mesh, point_emitter, sensor_params  # noqa: E402

from capture.dataset import load_dataset, model_label  # noqa: E402
from capture.metrics import well_lit_texels  # noqa: E402
from capture.observations import observe_views  # noqa: E402
from renderer.gbuffer import render_gbuffer  # noqa: E402
from renderer.lights import PointLight  # noqa: E402
from renderer.shading import prepare  # noqa: E402

VARIANT = "llvm_ad_rgb"
#: Dr.Jit's LLVM backend picks the first libLLVM it finds; LLVM 14/15 cannot compile Mitsuba's kernels ("Cannot
#: select: f32 = fminimum"), Debian's libllvm19 can. Used when DRJIT_LIBLLVM_PATH is not set and the file exists.
LIBLLVM_19 = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"


def _scenes(mi, ds, shape, spp: int) -> list:
    """One Mitsuba scene per view (its sensor and point lights) sharing the one ``shape`` (and so its bitmap)."""
    scenes = []
    for v in ds.views:
        if not all(isinstance(x, PointLight) for x in v.lights):
            raise SystemExit("mitsuba_adam: only point lights are mapped to Mitsuba")
        sensor = sensor_params(v.camera)
        sensor.update({
            "type": "perspective", "to_world": mi.ScalarTransform4f(sensor["to_world"]),
            "near_clip": 1e-3, "far_clip": 1e4,
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {"type": "hdrfilm", "width": v.camera.width, "height": v.camera.height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        })
        d = {"type": "scene", "integrator": {"type": "prb", "max_depth": 2}, "sensor": sensor, "object": shape}
        for k, light in enumerate(v.lights):
            d[f"light{k}"] = point_emitter(light)
        scenes.append(mi.load_dict(d))
    return scenes


def run(path: str, seconds: float, spp: int, lr: float, every: int, seed: int = 0) -> dict:
    """Adam on the albedo bitmap for ``seconds`` of wall time; returns the settings and the evaluations."""
    ds = load_dataset(path)
    if ds.gt is None or model_label(ds.gt.model) != "lambert":
        raise SystemExit(f"mitsuba_adam: {path} is not a Lambert scene with ground truth; this baseline fits a Lambert "
                         f"albedo and measures it against gt/ (e.g. the torus of scripts/make_independent_fixtures.py)")
    if "DRJIT_LIBLLVM_PATH" not in os.environ and Path(LIBLLVM_19).is_file():
        os.environ["DRJIT_LIBLLVM_PATH"] = LIBLLVM_19
    mi = import_mitsuba(VARIANT)
    import drjit as dr
    photos = ds.load_images()
    gt = ds.gt.maps["albedo"].float()
    H, W = gt.shape[:2]
    preps = [prepare(render_gbuffer(ds.mesh, v.camera, 1), ds.mesh, v.lights) for v in ds.views]
    lit = well_lit_texels(observe_views(preps, [p.radiance for p in photos], (H, W)))
    bsdf = {"type": "diffuse", "reflectance": {"type": "bitmap", "data": mi.TensorXf(np.full((H, W, 3), 0.5,
                                                                                                   np.float32)),
                                               "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}}
    shape = mitsuba_mesh(mi, ds.mesh, bsdf)
    scenes = _scenes(mi, ds, shape, spp)
    params = mi.traverse(shape)
    key = "bsdf.reflectance.data"
    opt = mi.ad.Adam(lr=lr)
    opt[key] = params[key]
    params.update(opt)
    targets = [mi.TensorXf(np.nan_to_num(p.radiance.numpy().astype(np.float32))) for p in photos]

    def rmse() -> float:
        a = torch.from_numpy(np.array(params[key], dtype=np.float32)).reshape(H, W, 3)
        return float((a - gt)[lit].square().mean().sqrt())

    order = list(range(len(scenes)))
    rng = random.Random(seed)
    evals = [{"step": 0, "seconds": 0.0, "albedo_rmse_well_lit": rmse()}]
    print(f"Mitsuba {mi.__version__} ({VARIANT}), {len(scenes)} views, {spp} spp a step, Adam lr {lr}; "
          f"{int(lit.sum())} well-lit texels; start RMSE {evals[0]['albedo_rmse_well_lit']:.4f}", flush=True)
    t0 = time.perf_counter()
    step = 0
    while time.perf_counter() - t0 < seconds:
        if step % len(order) == 0:
            rng.shuffle(order)
        vi = order[step % len(order)]
        img = mi.render(scenes[vi], params, spp=spp, seed=step)
        loss = dr.mean(dr.square(img - targets[vi]))
        dr.backward(loss)
        opt.step()
        opt[key] = dr.clip(opt[key], 0.0, 1.0)
        params.update(opt)
        step += 1
        if step % every == 0:
            e = {"step": step, "seconds": time.perf_counter() - t0, "albedo_rmse_well_lit": rmse()}
            evals.append(e)
            print(f"  step {step:5d}  {e['seconds']:7.1f} s  albedo RMSE (well lit) {e['albedo_rmse_well_lit']:.4f}",
                  flush=True)
    return {"dataset": str(path), "variant": VARIANT, "mitsuba": mi.__version__, "spp": spp, "lr": lr,
            "threads": torch.get_num_threads(), "evaluations": evals}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a Lambert dataset folder (scene.json with gt/)")
    ap.add_argument("--seconds", type=float, default=600.0, help="wall-time budget of the Adam loop (default 600)")
    ap.add_argument("--spp", type=int, default=4, help="samples per pixel of each step's render (default 4)")
    ap.add_argument("--lr", type=float, default=0.02, help="Adam's learning rate (default 0.02)")
    ap.add_argument("--every", type=int, default=24, help="steps between evaluations (default 24: two passes over "
                                                         "12 views)")
    ap.add_argument("--json", help="write the settings and evaluations here")
    args = ap.parse_args(argv)
    if not (args.seconds > 0 and math.isfinite(args.seconds)) or args.spp < 1 or not args.lr > 0 or args.every < 1:
        ap.error("--seconds and --lr must be positive, --spp and --every at least 1")
    out = run(args.dataset, args.seconds, args.spp, args.lr, args.every)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
