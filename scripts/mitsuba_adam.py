#!/usr/bin/env python3
"""The plain-Adam baseline of an independent differentiable renderer: Mitsuba 3 recovers the maps of a scene.

    python scripts/mitsuba_adam.py DATASET [--seconds 600] [--spp 4] [--lr 0.02] [--json OUT.json]

The dataset is a scene of shadecap's format with ground truth in one of the two models Mitsuba reproduces
(``make_independent_fixtures.bsdf_passes``): Lambert (e.g. the 256² Mitsuba torus of
``scripts/make_independent_fixtures.py --full``), or Lambert + GGX with F = 1 (the 256² sphere). Mitsuba's
``llvm_ad_rgb`` variant renders it with the conventions of the fixtures (the mesh, cameras, point lights and texture
mapping of ``make_independent_fixtures``: docs/independent-renders.md): a ``diffuse`` BSDF whose reflectance bitmap
is the albedo, and for GGX a ``blendbsdf`` of weight ½ of that and a ``roughconductor`` (GGX, material 'none', its
``specular_reflectance`` bitmap the f0 map and its ``alpha`` bitmap α = r²) under lights of twice the intensity — with
point lights only the BSDFs' evaluations count, so the image is exactly the sum of the two lobes'. The bitmaps start at
shadecap's parameter defaults (albedo 0.5, f0 0.04, α 0.25) and are clamped to their ranges after each step (α to
[:data:`ALPHA_MIN`, 1]). Each Adam step renders one view (views in a fixed shuffled order, ``--spp`` samples per
pixel, the ``prb`` integrator with direct light only), takes the mean squared error against the photo and updates the
bitmaps. Every ``--every`` steps it records the elapsed time and the RMSE of each map on the texel sets of shadecap's
report (``capture.metrics.errors_by_texel_set``: well lit, and for GGX the well-lit texels seen inside a visible
highlight), as ``{map}_rmse_{set}`` (e.g. ``albedo_rmse_well_lit``), so the time Mitsuba's Adam needs to reach an error
compares with ``shadecap reconstruct``'s on the same photos (docs/benchmarks.md, "Against Mitsuba 3's Adam", and
``scripts/mitsuba_race.py``). The first steps include Mitsuba's kernel compilation; the JSON keeps every evaluation.

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
from make_independent_fixtures import (  # noqa: E402
    GGX_LAMBERT_F1,
    LAMBERT,
    bitmap,
    import_mitsuba,
    mitsuba_mesh,
    point_emitter,
    sensor_params,
)

from capture.bench.race import flat_errors  # noqa: E402
from capture.dataset import load_dataset, model_spec  # noqa: E402
from capture.metrics import errors_by_texel_set, texel_sets  # noqa: E402
from capture.observations import observe_views  # noqa: E402
from materials.params import CANONICAL  # noqa: E402
from materials.roughness import alpha_to_roughness, roughness_to_alpha  # noqa: E402
from renderer.gbuffer import render_gbuffer  # noqa: E402
from renderer.lights import PointLight  # noqa: E402
from renderer.shading import prepare  # noqa: E402

VARIANT = "llvm_ad_rgb"
#: Dr.Jit's LLVM backend picks the first libLLVM it finds; LLVM 14/15 cannot compile Mitsuba's kernels ("Cannot
#: select: f32 = fminimum"), Debian's libllvm19 can. Used when DRJIT_LIBLLVM_PATH is not set and the file exists.
LIBLLVM_19 = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
#: Smallest α the GGX bitmap is clamped to after a step: α = 0 is a mirror, whose lobe a point light never shows
#: and whose gradient is 0 (roughness 0.03; the sphere's truth starts at r = 0.15, α = 0.023).
ALPHA_MIN = 1e-3


def _bsdf(mi, spec: dict, H: int, W: int) -> tuple[dict, dict, float]:
    """``(bsdf, maps, light_scale)``: the Mitsuba BSDF of the model ``spec`` with bitmaps at shadecap's parameter
    defaults; ``maps``: traversal key → (shadecap map, low, high, to canonical); ``light_scale``: the factor on every
    light's intensity (2 for the blend of weight ½, which halves each lobe)."""
    d = {n: CANONICAL[n].default for n in ("albedo", "f0", "roughness")}
    diffuse = {"type": "diffuse", "reflectance": bitmap(mi, np.full((H, W, 3), d["albedo"], np.float32))}
    same = (lambda x: x)
    if spec == model_spec(LAMBERT):
        return diffuse, {"bsdf.reflectance.data": ("albedo", 0.0, 1.0, same)}, 1.0
    if spec == model_spec(GGX_LAMBERT_F1):
        alpha = float(roughness_to_alpha(torch.tensor(d["roughness"])))
        specular = {"type": "roughconductor", "distribution": "ggx", "material": "none", "sample_visible": True,
                    "alpha": bitmap(mi, np.full((H, W, 1), alpha, np.float32)),
                    "specular_reflectance": bitmap(mi, np.full((H, W, 3), d["f0"], np.float32))}
        maps = {"bsdf.bsdf_0.reflectance.data": ("albedo", 0.0, 1.0, same),
                "bsdf.bsdf_1.specular_reflectance.data": ("f0", 0.0, 1.0, same),
                "bsdf.bsdf_1.alpha.data": ("roughness", ALPHA_MIN, 1.0, alpha_to_roughness)}
        return {"type": "blendbsdf", "weight": 0.5, "bsdf_0": diffuse, "bsdf_1": specular}, maps, 2.0
    raise SystemExit(_unmapped(spec))


def _unmapped(spec) -> str:
    return (f"mitsuba_adam: no Mitsuba BSDF is mapped for the model {spec}; this baseline fits {LAMBERT} or "
            f"{GGX_LAMBERT_F1} scenes (e.g. the torus and sphere of scripts/make_independent_fixtures.py)")


def _scenes(mi, ds, shape, spp: int, light_scale: float) -> list:
    """One Mitsuba scene per view (its sensor and point lights, intensities × ``light_scale``) sharing the one
    ``shape`` (and so its bitmaps)."""
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
            e = point_emitter(light)
            e["intensity"]["value"] = [light_scale * x for x in e["intensity"]["value"]]
            d[f"light{k}"] = e
        scenes.append(mi.load_dict(d))
    return scenes


def run(path: str, seconds: float, spp: int, lr: float, every: int, seed: int = 0) -> dict:
    """Adam on the model's bitmaps for ``seconds`` of wall time; returns the settings and the evaluations."""
    ds = load_dataset(path)
    if ds.gt is None:
        raise SystemExit(f"mitsuba_adam: {path} has no ground truth (gt/); the baseline's errors are measured "
                         f"against it")
    spec = model_spec(ds.gt.model)
    if spec not in (model_spec(LAMBERT), model_spec(GGX_LAMBERT_F1)):
        raise SystemExit(_unmapped(spec))
    if "DRJIT_LIBLLVM_PATH" not in os.environ and Path(LIBLLVM_19).is_file():
        os.environ["DRJIT_LIBLLVM_PATH"] = LIBLLVM_19
    mi = import_mitsuba(VARIANT)
    import drjit as dr
    photos = ds.load_images()
    truth = {k: v.float() for k, v in ds.gt.maps.items()}
    H, W = truth["albedo"].shape[:2]
    bsdf, maps, light_scale = _bsdf(mi, spec, H, W)
    preps = [prepare(render_gbuffer(ds.mesh, v.camera, 1), ds.mesh, v.lights) for v in ds.views]
    # the texel sets the errors are taken on, made once (they depend on the truth and the photos only)
    sets = texel_sets({n: truth[n] for n, *_ in maps.values()},
                      observe_views(preps, [p.radiance for p in photos], (H, W)))
    shape = mitsuba_mesh(mi, ds.mesh, bsdf)
    scenes = _scenes(mi, ds, shape, spp, light_scale)
    params = mi.traverse(shape)
    opt = mi.ad.Adam(lr=lr)
    for key in maps:
        opt[key] = params[key]
    params.update(opt)
    targets = [mi.TensorXf(np.nan_to_num(p.radiance.numpy().astype(np.float32))) for p in photos]

    def errors() -> dict:
        fitted = {}
        for key, (name, _, _, canonical) in maps.items():
            a = torch.from_numpy(np.array(params[key], dtype=np.float32)).reshape(H, W, -1)
            fitted[name] = canonical(a)
        return flat_errors(errors_by_texel_set(fitted, {n: truth[n] for n in fitted}, sets=sets))

    order = list(range(len(scenes)))
    rng = random.Random(seed)
    evals = [{"step": 0, "seconds": 0.0, **errors()}]
    names = [m for m, *_ in maps.values()]
    print(f"Mitsuba {mi.__version__} ({VARIANT}), {len(scenes)} views, {spp} spp a step, Adam lr {lr} on "
          f"{', '.join(names)}; start {_line(evals[0], names)}", flush=True)
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
        for key, (_, low, high, _) in maps.items():
            opt[key] = dr.clip(opt[key], low, high)
        params.update(opt)
        step += 1
        if step % every == 0:
            e = {"step": step, "seconds": time.perf_counter() - t0, **errors()}
            evals.append(e)
            print(f"  step {step:5d}  {e['seconds']:7.1f} s  {_line(e, names)}", flush=True)
    return {"dataset": str(path), "variant": VARIANT, "mitsuba": mi.__version__, "model": spec, "spp": spp,
            "lr": lr, "start": {n: CANONICAL[n].default for n in names}, "alpha_min": ALPHA_MIN,
            "threads": torch.get_num_threads(), "evaluations": evals}


def _line(e: dict, names) -> str:
    """One evaluation's errors for the log: each map on the well-lit texels, and on the visible highlights."""
    sets = [("well_lit", "well lit"), ("well_lit_visible_highlight", "visible highlight")]
    return "; ".join(f"{label} " + " / ".join(f"{n} {e[f'{n}_rmse_{k}']:.4f}" for n in names
                                              if f"{n}_rmse_{k}" in e)
                     for k, label in sets if any(f"{n}_rmse_{k}" in e for n in names))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="a Lambert or Lambert + GGX (F = 1) dataset folder with ground truth (gt/)")
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
