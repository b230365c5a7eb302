#!/usr/bin/env python3
"""Regression scenes whose photos are rendered by Mitsuba 3, a renderer that shares no code with shadecap.

    python scripts/make_independent_fixtures.py --out tests/fixtures/mitsuba            # the committed fixtures
    python scripts/make_independent_fixtures.py --out /tmp/independent --full           # benchmark sizes
    python scripts/make_independent_fixtures.py --out /tmp/x --only torus-lambert --spp 64
    python scripts/make_independent_fixtures.py --binned tests/fixtures/mitsuba    # binned-camera references

The scenes (mesh, cameras, lights, ground-truth maps) come from shadecap's own scene builder
(:func:`capture.synth.build_scene`); only the photos come from Mitsuba 3 (``scalar_rgb``,
pure CPU). Each scene is written with :func:`capture.dataset.write_dataset` (half-float linear
EXR photos, ``gt/`` maps and the matching shadecap model spec), so ``shadecap reconstruct`` reads
it like any other dataset. The conventions mapped between the two renderers, and the measured
agreement, are in docs/independent-renders.md.

Mitsuba is an optional dependency (``pip install mitsuba`` or ``pip install -e ".[independent]"``);
it is imported only when rendering.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from capture.dataset import GroundTruth, model_spec, write_dataset  # noqa: E402
from capture.synth import REGION_NAMES, Scene, SyntheticConfig, build_scene  # noqa: E402
from materials.roughness import roughness_to_alpha  # noqa: E402
from renderer.camera import Camera  # noqa: E402
from renderer.lights import PointLight  # noqa: E402
from renderer.mesh import Mesh  # noqa: E402

VARIANT = "scalar_rgb"
DEFAULT_SPP = 256

#: The shadecap model that Mitsuba's ``diffuse`` + ``roughconductor`` (GGX, material 'none') pair
#: reproduces: Lambert ρ/π plus D_GGX(α) · G1(l) G1(v) (separable Smith, Walter's GGX G1) · f0 / (4 n·l n·v),
#: with F = 1 and the f0 map as a plain scale (Mitsuba's ``specular_reflectance``).
GGX_LAMBERT_F1 = {"sum": [{"name": "lambert", "options": {}},
                          {"name": "microfacet", "options": {"D": "ggx", "G": "smith", "F": "none"}}]}
LAMBERT = {"name": "lambert", "options": {}}


@dataclass
class FixtureScene:
    """One independent scene: its name, the shadecap scene configuration it renders and, optionally, an albedo map
    that replaces the configuration's (``albedo(size) -> [size, size, 3]``)."""

    name: str
    config: SyntheticConfig
    note: str = ""
    albedo: Callable[[int], torch.Tensor] | None = None


def fractal_albedo(size: int, seed: int = 10) -> torch.Tensor:
    """A texture with detail at every scale, unlike the scene builder's piecewise-constant regions: per channel,
    Gaussian noise with a power spectrum ∝ 1/f^1.6 (periodic, so the torus's seams match), a shared component for
    the luminance, around a warm grey, ``[size, size, 3]`` in [0.03, 0.95]."""
    rng = np.random.default_rng(seed)
    f2 = np.fft.fftfreq(size)[:, None] ** 2 + np.fft.fftfreq(size)[None, :] ** 2
    amp = np.where(f2 > 0, f2 ** -0.8, 0.0)

    def noise() -> np.ndarray:
        x = np.real(np.fft.ifft2(amp * (rng.normal(size=(size, size)) + 1j * rng.normal(size=(size, size)))))
        return (x - x.mean()) / x.std()

    shared = noise()
    a = np.stack([base + 0.12 * noise() + 0.06 * shared for base in (0.55, 0.45, 0.35)], -1)
    return torch.from_numpy(np.clip(a, 0.03, 0.95))


def fixture_scenes(full: bool = False) -> list[FixtureScene]:
    """The scenes: small ones for ``tests/fixtures/mitsuba`` or, with ``full``, benchmark sizes.

    ``torus-lambert``: a torus (self-shadowing, concave parts) with a textured albedo, 2 flash
    lights per view; at benchmark sizes also ``torus-fractal-lambert``, the same with
    :func:`fractal_albedo`. ``sphere-ggx-lambert``: a UV sphere, Lambert + GGX with F = 1, 3 flash lights
    per view 30° off the camera on three elevation rings, so highlights land on much of the sphere.
    """
    small_mesh = {"segments": 48, "rings": 24}
    common = dict(image_size=256 if full else 128, texture_size=256 if full else 64, camera_rig="orbit",
                  light_rig="flash", light_irradiance=1.0, supersample=1, sampling="bilinear", shadows=True, seed=0)
    torus = SyntheticConfig(mesh="torus", mesh_options={} if full else dict(small_mesh), model=LAMBERT,
                            n_views=12 if full else 8, elevations=(15.0, 50.0), n_lights=2, light_offset_deg=20.0,
                            **common)
    sphere = SyntheticConfig(mesh="uv_sphere", mesh_options={} if full else dict(small_mesh), model=GGX_LAMBERT_F1,
                             n_views=12, elevations=(-20.0, 20.0, 55.0), n_lights=3, light_offset_deg=30.0,
                             **common)
    scenes = [
        FixtureScene("torus-lambert", torus, "torus, textured Lambert albedo, 2 flash lights per view"),
        FixtureScene("sphere-ggx-lambert", sphere, "UV sphere, Lambert + GGX (separable Smith, F = 1), "
                                                   "3 flash lights per view"),
    ]
    if full:
        scenes.append(FixtureScene("torus-fractal-lambert", torus, "the torus with a fractal-noise Lambert albedo "
                                   "(detail at every scale)", albedo=fractal_albedo))
    return scenes


# ----------------------------------------------------------------------------------------------
# Mitsuba


def import_mitsuba(variant: str = VARIANT):
    """Import Mitsuba 3 and select ``variant``; exit with an install hint when it is missing."""
    try:
        import mitsuba as mi
    except ImportError:
        raise SystemExit("make_independent_fixtures: Mitsuba 3 is not installed. Install it with "
                         "`pip install mitsuba` (or `pip install -e \".[independent]\"`) and run again.") from None
    try:
        mi.set_variant(variant)
    except Exception as exc:  # an unknown or unavailable variant
        raise SystemExit(f"make_independent_fixtures: Mitsuba variant {variant!r} is unavailable: {exc}") from None
    return mi


def sensor_params(camera: Camera) -> dict:
    """Mitsuba ``perspective`` sensor parameters reproducing an OpenCV camera (no film, no sampler).

    OpenCV camera axes are x right, y down, z forward; Mitsuba's camera looks along +z with +x to the
    image's *left* and +y up, so its camera-to-world matrix is ``[Rᵀ diag(−1, −1, 1) | C]`` with C
    the camera centre. Mitsuba's film coordinate X ∈ [0, W] has pixel centres at X = x + ½ for the
    OpenCV pixel x (centres at integers). With fx = W / (2 tan(fov_x / 2)), the principal point
    (cx, cy) sits at the film centre when cx = (W − 1)/2; otherwise Mitsuba's offsets, fractions of
    the film size, are ``½ − (cx + ½)/W`` and ``½ − (cy + ½)/H``.

    Raises:
        ValueError: a camera Mitsuba's pinhole cannot represent (skew, fx ≠ fy).
    """
    K = camera.K.double()
    fx, fy, s, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 1]), float(K[0, 2]), float(K[1, 2]))
    W, H = camera.width, camera.height
    if abs(s) > 1e-9 * fx or abs(fx - fy) > 1e-6 * fx:
        raise ValueError(f"Mitsuba's perspective sensor needs square pixels without skew; got fx={fx}, fy={fy}, "
                         f"skew={s}")
    R, t = camera.R.double(), camera.t.double()
    to_world = torch.eye(4, dtype=torch.float64)
    to_world[:3, :3] = R.T @ torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    to_world[:3, 3] = -R.T @ t
    return {
        "fov": math.degrees(2.0 * math.atan(0.5 * W / fx)),
        "fov_axis": "x",
        "principal_point_offset_x": 0.5 - (cx + 0.5) / W,
        "principal_point_offset_y": 0.5 - (cy + 0.5) / H,
        "to_world": to_world.numpy(),
    }


def bitmap(mi, arr) -> dict:
    """A Mitsuba bitmap texture of a shadecap map ``[H, W, C]`` (row 0 = top = v = 1): raw linear values,
    bilinear, clamped at the edge. Texcoords are passed as (u, 1 − v) (:func:`mitsuba_mesh`), for which
    Mitsuba's row 0 is v' = 0 and its texel centres sit at ((j + ½)/W, (i + ½)/H), shadecap's centres."""
    a = np.ascontiguousarray(np.asarray(arr, dtype=np.float32))
    return {"type": "bitmap", "data": mi.TensorXf(a), "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}


def bsdf_passes(mi, spec: dict, maps: dict[str, torch.Tensor]) -> list[tuple[str, dict]]:
    """The Mitsuba BSDFs whose images add up to the shadecap model ``spec`` with ``maps``.

    Light transport with direct lighting only is linear in the BSDF, so a sum model is rendered one
    part per pass and the images are added. Supported: ``lambert`` (Mitsuba ``diffuse`` with the albedo
    map) and :data:`GGX_LAMBERT_F1` (plus a ``roughconductor``: GGX, material 'none' — eta 0, k 1, i.e.
    F = 1 —, alpha map = roughness², specular_reflectance map = f0).
    """
    spec = model_spec(spec)
    diffuse = ("diffuse", {"type": "diffuse", "reflectance": bitmap(mi, maps["albedo"])})
    if spec == model_spec(LAMBERT):
        return [diffuse]
    if spec == model_spec(GGX_LAMBERT_F1):
        alpha = roughness_to_alpha(maps["roughness"].double()).float()
        specular = ("specular", {"type": "roughconductor", "distribution": "ggx", "material": "none",
                                 "sample_visible": True, "alpha": bitmap(mi, alpha),
                                 "specular_reflectance": bitmap(mi, maps["f0"])})
        return [diffuse, specular]
    raise ValueError(f"no Mitsuba equivalent is mapped for the model {spec}; supported: {LAMBERT}, {GGX_LAMBERT_F1}")


def mitsuba_mesh(mi, mesh: Mesh, bsdf: dict, name: str = "object"):
    """A Mitsuba mesh built directly from shadecap's arrays: positions, unit vertex normals (smooth
    shading, interpolated and normalised as in shadecap), texcoords (u, 1 − v) and faces."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    V, F = mesh.vertices.shape[0], mesh.faces.shape[0]
    m = mi.Mesh(name, V, F, props=props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(m)
    uv = mesh.uvs.double().numpy().copy()
    uv[:, 1] = 1.0 - uv[:, 1]
    params["vertex_positions"] = mesh.vertices.double().numpy().astype(np.float32).ravel()
    params["vertex_normals"] = mesh.normals.double().numpy().astype(np.float32).ravel()
    params["vertex_texcoords"] = uv.astype(np.float32).ravel()
    params["faces"] = mesh.faces.numpy().astype(np.uint32).ravel()
    params.update()
    return m


def point_emitter(light: PointLight) -> dict:
    """Mitsuba ``point`` emitter: its ``intensity`` is radiant intensity in W/sr, irradiance I/d² —
    the same quantity as shadecap's :class:`renderer.lights.PointLight` intensity."""
    return {"type": "point", "position": [float(x) for x in light.position.double()],
            "intensity": {"type": "rgb", "value": [float(x) for x in light.intensity.double()]}}


def render_view(mi, shapes: list, camera: Camera, lights: list, spp: int, seed: int) -> np.ndarray:
    """Radiance image ``[H, W, 3]`` (float64) of one view: one Mitsuba render per (BSDF pass, light), added.

    Each render has a single emitter, so the ``direct`` integrator never picks among lights at random
    (no light-selection noise); the only Monte Carlo noise left is the pixel footprint (stratified,
    box filter).
    """
    sensor = sensor_params(camera)
    sensor.update({
        "to_world": mi.ScalarTransform4f(sensor["to_world"]),
        "near_clip": 1e-3, "far_clip": 1e4,
        "sampler": {"type": "stratified", "sample_count": spp, "jitter": True},
        "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height, "rfilter": {"type": "box"},
                 "pixel_format": "rgb", "component_format": "float32"},
        "type": "perspective",
    })
    img = np.zeros((camera.height, camera.width, 3), dtype=np.float64)
    k = 0
    for light in lights:
        if not isinstance(light, PointLight):
            raise ValueError(f"only point lights are mapped to Mitsuba, got {type(light).__name__}")
        for shape in shapes:
            scene = mi.load_dict({
                "type": "scene",
                "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
                "sensor": sensor,
                "light": point_emitter(light),
                "object": shape,
            })
            out = np.array(mi.render(scene, spp=spp, seed=seed * 7919 + k), dtype=np.float64)
            img += out[..., :3]
            k += 1
    return img


# ----------------------------------------------------------------------------------------------
# agreement with shadecap's own renderer


def shadecap_images(dataset, supersample: int = 8, views=None) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """shadecap's forward render of a dataset's ground truth: per view ``(image [H, W, 3], coverage [H, W])``.

    :func:`renderer.gbuffer.render_gbuffer` with ``supersample``² rays per pixel,
    :func:`renderer.shading.prepare` (shadow rays) and :func:`renderer.shading.shade` of the ``gt/`` maps
    (bilinear), box-filtered by :meth:`renderer.gbuffer.GBuffer.to_image`, times the view's exposure.
    ``coverage`` is the fraction of each pixel the mesh covers.
    """
    from renderer.gbuffer import render_gbuffer
    from renderer.shading import prepare, shade

    model = dataset.gt.build_model()
    out = []
    idx = range(len(dataset.views)) if views is None else views
    with torch.no_grad():
        for i in idx:
            view = dataset.views[i]
            g = render_gbuffer(dataset.mesh, view.camera, supersample)
            prep = prepare(g, dataset.mesh, view.lights, shadows=True)
            rad = shade(model, dataset.gt.maps, prep, sampling="bilinear")
            out.append((view.exposure * g.to_image(rad).double(), g.pixel_weight().double()))
    return out


def relative_errors(photo: torch.Tensor, ref: torch.Tensor, coverage: torch.Tensor,
                    floor: float = 0.01) -> torch.Tensor:
    """Per-pixel relative error ``Σ_c |photo − ref| / Σ_c ref`` over the object pixels of one view.

    Object pixels: fully covered by the mesh (``coverage`` = 1, which leaves out silhouette pixels,
    whose edge is sampled differently by the two renderers) and not dark — ``Σ_c ref`` above ``floor``
    × the view's 99th percentile of it (shadowed and unlit pixels have no relative error).
    """
    ref_sum = ref.sum(-1)
    inside = coverage >= 1.0 - 1e-6
    if not bool(inside.any()):
        return ref_sum.new_zeros(0)
    level = torch.quantile(ref_sum[inside], 0.99)
    keep = inside & (ref_sum > floor * level)
    return (photo.double() - ref.double()).abs().sum(-1)[keep] / ref_sum[keep]


def agreement(path, supersample: int = 8, views=None) -> dict:
    """Median and 99th percentile of :func:`relative_errors` between a dataset's photos and shadecap's
    forward render of its ground truth, pooled over ``views`` (default all), and per view."""
    from capture.dataset import load_dataset

    ds = load_dataset(path)
    photos = ds.load_images(dtype=torch.float64)
    idx = list(range(len(ds.views))) if views is None else list(views)
    rendered = shadecap_images(ds, supersample, idx)
    per_view, pooled = [], []
    for i, (ref, cov) in zip(idx, rendered, strict=True):
        photo = photos[i].radiance.double() * ds.views[i].exposure
        e = relative_errors(photo, ref, cov)
        pooled.append(e)
        per_view.append({"view": i, "pixels": int(e.numel()), "median": float(e.median()),
                         "p99": float(torch.quantile(e, 0.99))})
    e = torch.cat(pooled)
    return {"path": str(path), "supersample": supersample, "pixels": int(e.numel()), "median": float(e.median()),
            "p99": float(torch.quantile(e, 0.99)), "max": float(e.max()), "per_view": per_view}


# ----------------------------------------------------------------------------------------------
# fixtures


def _describe(bsdf: dict) -> dict:
    """A BSDF dict for ``meta``: its plain settings, and for each texture which map it holds."""
    maps = {"reflectance": "gt albedo", "alpha": "gt roughness squared", "specular_reflectance": "gt f0"}
    return {k: (maps.get(k, "bitmap") if isinstance(v, dict) else v) for k, v in bsdf.items()}


def _mitsuba_scene(mi, fx: FixtureScene, cfg: SyntheticConfig) -> tuple[Scene, list, list]:
    """The scene of ``cfg`` built by shadecap (with the fixture's own albedo, if any), its BSDF passes and one
    Mitsuba shape per pass."""
    scene: Scene = build_scene(cfg)
    if fx.albedo is not None:
        old = scene.maps["albedo"]
        scene = replace(scene, maps={**scene.maps, "albedo": fx.albedo(old.shape[0]).to(old)})
    passes = bsdf_passes(mi, scene.model_spec, scene.maps)
    return scene, passes, [mitsuba_mesh(mi, scene.mesh, bsdf, name=f"object-{name}") for name, bsdf in passes]


def make_fixture(fx: FixtureScene, out_dir: Path, spp: int, overwrite: bool = True, views: int | None = None,
                 log=print) -> Path:
    """Build the scene with shadecap, render every view with Mitsuba, write the dataset folder."""
    mi = import_mitsuba()
    cfg = fx.config if views is None else replace(fx.config, n_views=views)
    scene, passes, shapes = _mitsuba_scene(mi, fx, cfg)
    images, seconds = [], []
    for i, view in enumerate(scene.views):
        t0 = time.perf_counter()
        rad = render_view(mi, shapes, view.camera, view.lights, spp, seed=i + 1)
        images.append(torch.from_numpy(view.exposure * rad).float())
        seconds.append(time.perf_counter() - t0)
        log(f"  {fx.name}: view {i + 1}/{len(scene.views)} ({len(view.lights)} light(s) × {len(passes)} pass(es)) "
            f"{seconds[-1]:.1f} s")
    gt = GroundTruth(model=scene.model_spec, maps=scene.maps, regions=scene.regions,
                     region_names=dict(REGION_NAMES), render={"sampling": "bilinear", "shadows": True})
    # the scene's configuration, less what only shadecap's own photo rendering reads
    cfg_dict = {k: v for k, v in cfg.to_dict().items() if k not in ("photo", "supersample", "jitter")}
    meta = {
        "generator": "scripts/make_independent_fixtures.py",
        "scene": fx.name,
        "description": fx.note,
        "renderer": {
            "name": "mitsuba", "version": mi.__version__, "variant": VARIANT,
            "integrator": "direct (emitter_samples 1, bsdf_samples 0)", "sampler": "stratified (jittered)",
            "spp": spp, "rfilter": "box", "background": "black (no environment emitter)",
            "renders_per_view": "one per (light, BSDF pass), images added",
            "passes": {name: _describe(bsdf) for name, bsdf in passes},
            "texcoords": "(u, 1 - v); bitmaps hold the gt maps as stored (row 0 = v = 1), raw, bilinear, clamp",
            "conventions": "docs/independent-renders.md",
        },
        "photos": "linear radiance, half-float EXR, exposure 1, noise-free apart from Mitsuba's sampling",
        "config": cfg_dict,
    }
    return write_dataset(out_dir, scene.mesh, scene.views, images, encoding="linear", half=True, gt=gt, meta=meta,
                         overwrite=overwrite)


#: The binned-camera references: the first :data:`BINNED_VIEWS` views of each scene, binned :data:`BINNED_BIN` × itself.
BINNED_BIN = 2
BINNED_VIEWS = 3


def make_binned_references(fx: FixtureScene, folder: Path, spp: int, k: int = BINNED_BIN, views: int = BINNED_VIEWS,
                           log=print) -> Path:
    """Render the first ``views`` views of the scene ``fx``, whose fixture is ``folder``, with Mitsuba
    through its cameras binned ``k × k`` (:meth:`renderer.camera.Camera.binned`) into ``folder/binned-k/``:
    ``NNN.exr`` (half-float radiance) and ``cameras.json`` (the binned cameras). A photo binned by
    :meth:`capture.dataset.Dataset.binned` must equal these up to Mitsuba's sampling noise: the check of the
    binned camera's convention against a renderer that shares no code with shadecap."""
    from renderer.imageio import write_exr

    mi = import_mitsuba()
    scene, _, shapes = _mitsuba_scene(mi, fx, fx.config)
    out = folder / f"binned-{k}"
    out.mkdir(exist_ok=True)
    cameras = []
    for i, view in enumerate(scene.views[:views]):
        cam = view.camera.binned(k)
        rad = render_view(mi, shapes, cam, view.lights, spp, seed=1000 + i)
        write_exr(out / f"{i:03d}.exr", torch.from_numpy(view.exposure * rad).float(), half=True)
        cameras.append(cam.to_dict())
        log(f"  {fx.name}: view {i} binned {k}×{k} → {cam.width}×{cam.height}")
    (out / "cameras.json").write_text(json.dumps({"bin": k, "spp": spp, "renderer": f"mitsuba {mi.__version__} "
                                                 f"({VARIANT})", "cameras": cameras}, indent=1) + "\n")
    return out


def check(folder: Path, only=None, supersample: int = 8) -> int:
    """Print the agreement of every scene folder under ``folder`` (those of ``only`` if given)."""
    names = [s.name for s in fixture_scenes()]
    found = [n for n in names if (folder / n / "scene.json").is_file() and (not only or n in only)]
    if not found:
        print(f"no scene folder of {names} under {folder}", file=sys.stderr)
        return 2
    for n in found:
        t0 = time.perf_counter()
        a = agreement(folder / n, supersample)
        print(f"{n}: shadecap (supersample {supersample}) vs Mitsuba photos over {a['pixels']} object pixels: "
              f"median relative error {a['median']:.2e}, p99 {a['p99']:.2e}, max {a['max']:.2e} "
              f"({time.perf_counter() - t0:.1f} s)")
        for v in a["per_view"]:
            print(f"  view {v['view']:2d}: {v['pixels']:6d} px  median {v['median']:.2e}  p99 {v['p99']:.2e}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="folder receiving one dataset folder per scene")
    ap.add_argument("--check", metavar="FOLDER", default=None,
                    help="render nothing: compare the scenes under FOLDER with shadecap's forward render of their "
                         "ground truth and print median / p99 relative errors (needs no Mitsuba)")
    ap.add_argument("--supersample", type=int, default=8, help="--check: shadecap's k×k rays per pixel (default 8)")
    ap.add_argument("--full", action="store_true", help="benchmark sizes: 12 views of 256², 256² maps")
    ap.add_argument("--spp", type=int, default=DEFAULT_SPP,
                    help=f"samples per pixel, a perfect square (stratified sampler; default {DEFAULT_SPP})")
    ap.add_argument("--only", action="append", default=None, metavar="NAME", help="render only this scene (repeatable)")
    ap.add_argument("--views", type=int, default=None, help="render only the first N views (quick checks)")
    ap.add_argument("--binned", metavar="FOLDER", default=None,
                    help=f"render the first {BINNED_VIEWS} views of each scene under FOLDER through its cameras binned "
                         f"{BINNED_BIN} × {BINNED_BIN} into SCENE/binned-{BINNED_BIN}/ (references for the photos' "
                         "binning)")
    args = ap.parse_args(argv)
    if args.check:
        return check(Path(args.check), args.only, args.supersample)
    if args.binned:
        for fx in fixture_scenes():
            if (Path(args.binned) / fx.name / "scene.json").is_file() and (not args.only or fx.name in args.only):
                print(f"{fx.name}: wrote {make_binned_references(fx, Path(args.binned) / fx.name, args.spp)}")
        return 0
    if not args.out:
        ap.error("--out is required (or --check FOLDER)")
    if args.spp < 1 or math.isqrt(args.spp) ** 2 != args.spp:
        ap.error(f"--spp must be a perfect square (the stratified sampler's grid), got {args.spp}")
    mi = import_mitsuba()
    scenes = fixture_scenes(args.full)
    if args.only:
        known = {s.name for s in scenes}
        unknown = sorted(set(args.only) - known)
        if unknown:
            ap.error(f"unknown scene(s) {unknown}; choose from {sorted(known)}")
        scenes = [s for s in scenes if s.name in args.only]
    out = Path(args.out)
    print(f"Mitsuba {mi.__version__} ({VARIANT}), {args.spp} spp, box filter → {out}")
    for fx in scenes:
        t0 = time.perf_counter()
        print(f"{fx.name}: {fx.note}")
        path = make_fixture(fx, out / fx.name, args.spp, views=args.views)
        size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
        print(f"{fx.name}: wrote {path} ({size / 1e6:.2f} MB) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
