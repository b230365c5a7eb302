"""The ``shadecap`` command line.

    shadecap demo [--out DIR] [--small]                synthesise → reconstruct → export → print errors
    shadecap synth --out DIR [...]                     write a synthetic dataset (scripts/make_synthetic.py)
    shadecap reconstruct DATASET --out DIR [--model NAME|auto] [...]
    shadecap export-atlas RECON_DIR... --out DIR [...]
    shadecap import {colmap,transforms,opencv} SOURCE --mesh M --out DIR [--images DIR] [--flash X,Y,Z] [...]
    shadecap calibrate-lights DATASET (--card-masks DIR | --uv-mask FILE) --albedo 0.18 --out NEW_DATASET
    shadecap merge-hdr IMG... --times T... --out FILE.exr
    shadecap models                                    list every reflectance model

``scripts/make_synthetic.py``, ``scripts/reconstruct.py`` and ``scripts/export_atlas.py`` are these commands under
their own name (:func:`script_main`): the same parser, so every option exists in both and ``--help`` names the
script.

Errors a user can fix (bad dataset, unknown model, existing output folder, an output that would
overwrite an input, an unwritable output folder, a full disk) print one line naming the file/field
and exit with status 2; they never print a traceback. Every output folder is checked before any
work (``capture.outputs.check_output``) and written atomically. Ctrl-C prints
``interrupted; nothing written`` and exits with status 130, leaving no temporary folder behind.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, KeyError)
#: Exit status of a command stopped by Ctrl-C (128 + SIGINT, as shells report it).
EXIT_INTERRUPTED = 130


def _cmd_models(args) -> int:
    import materials

    names = materials.available()
    width = max(len(n) for n in names)
    for name, desc in names.items():
        try:
            params = "params: " + ", ".join(materials.get(name).param_names)
        except (FileNotFoundError, ValueError) as exc:  # a model whose data is missing is listed, not fatal
            params = f"unavailable here: {exc}"
        print(f"{name:<{width}}  {desc}\n{'':<{width}}  {params}")
    return 0


def _cmd_synth(args) -> int:
    from capture.outputs import check_output
    from capture.photo import PhotoModel
    from capture.synth import BUILTIN_MESHES, default_scene, make_synthetic, small_scene

    inputs = {Path(args.mesh): "the mesh file (--mesh)"} if args.mesh and args.mesh not in BUILTIN_MESHES else {}
    check_output(args.out, inputs, force=args.overwrite, force_flag="--overwrite")
    photo = PhotoModel(exposure=args.exposure, full_well=args.noise, read_noise=args.read_noise,
                       clip=args.clip or args.encoding == "srgb", encoding=args.encoding)
    over = {k: v for k, v in {
        "mesh": args.mesh, "n_views": args.views, "image_size": args.size, "texture_size": args.tex,
        "camera_rig": args.rig, "light_rig": args.lights, "n_lights": args.n_lights, "supersample": args.supersample,
        "sampling": args.sampling, "seed": args.seed}.items() if v is not None}
    if args.model:
        over["model"] = args.model
        over["model_options"] = json.loads(args.model_options) if args.model_options else {}
    over["photo"] = photo
    cfg = small_scene(**over) if args.config == "small" else default_scene(**over)
    t0 = time.perf_counter()
    out = make_synthetic(cfg, args.out, overwrite=args.overwrite, device=args.device)
    print(f"wrote {out} ({cfg.n_views} views) in {time.perf_counter() - t0:.1f} s")
    return 0


def _add_synth_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", choices=("default", "small"), default="default", help="base scene")
    p.add_argument("--out", required=True, help="dataset folder to create (must not exist unless --overwrite)")
    p.add_argument("--model", help="model as the project writes it: a registered name, 'a+b' for a sum, options in "
                   "parentheses, e.g. 'lambert+microfacet(D=ggx,G=smith,F=none)' (default: ggx-lambert)")
    p.add_argument("--model-options", help='JSON options of a single model, e.g. \'{"D": "beckmann"}\'')
    p.add_argument("--mesh", help="uv_sphere, torus, nonconvex, plane, or a mesh file with UVs")
    p.add_argument("--views", type=int, help="number of views")
    p.add_argument("--size", type=int, help="image width = height (pixels)")
    p.add_argument("--tex", type=int, help="ground-truth map size (texels)")
    p.add_argument("--rig", choices=("orbit", "turntable", "random"), help="camera rig")
    p.add_argument("--lights", choices=("flash", "fixed", "dome"), help="light rig")
    p.add_argument("--n-lights", type=int, help="lights per view (flash) or in the studio")
    p.add_argument("--exposure", type=float, default=1.0)
    p.add_argument("--noise", type=float, metavar="FULL_WELL", help="shot noise: electrons at saturation")
    p.add_argument("--read-noise", type=float, default=0.0, help="read noise σ (fraction of saturation)")
    p.add_argument("--clip", action="store_true", help="clip highlights at 1 (always on for --encoding srgb)")
    p.add_argument("--encoding", choices=("linear", "srgb"), default="linear", help="EXR float or 8-bit sRGB PNG")
    p.add_argument("--supersample", type=int, help="k×k jittered rays per pixel (default 8; 1 = pixel centres only, "
                   "the fit's own pixel-centre discretisation)")
    p.add_argument("--sampling", choices=("bilinear", "nearest"))
    p.add_argument("--seed", type=int)
    add_device_arg(p, "the shading", default="cpu")
    p.add_argument("--overwrite", "--force", dest="overwrite", action="store_true",
                   help="replace an existing dataset folder")


def _reconstruct_options(args) -> dict:
    """``reconstruct``'s keyword arguments from the flags of :func:`_add_reconstruct_args` (shared by ``reconstruct``
    and ``batch``)."""
    import torch

    return dict(model=args.model, force=args.force, solver=args.solver, loss=args.loss, texture_size=args.tex,
                holdout=args.holdout, footprint=not args.pixel_centres, sampling=args.sampling, threads=args.threads,
                device=args.device, photo_bin=args.bin,
                dtype=torch.float64 if args.float64 else torch.float32, **known_options(args),
                **fit_option_values(args))


def _cmd_reconstruct(args) -> int:
    from capture.reconstruct import reconstruct

    report = reconstruct(args.dataset, out_dir=args.out, **_reconstruct_options(args))
    summary = Path(args.out) / "summary.txt"
    print(summary.read_text() if summary.exists() else report)
    return 0


def _cmd_batch(args) -> int:
    from capture.batch import reconstruct_batch

    # interrupted: the captures finished so far are kept, and batch.json lists them
    args.completed = [Path(args.out) / "batch.json"]
    items = reconstruct_batch(args.datasets, args.out, cluster=args.cluster, **_reconstruct_options(args))
    failed = [it for it in items if it.status == "failed"]
    print(f"wrote {Path(args.out) / 'batch.json'}: {sum(it.status == 'done' for it in items)} done, "
          f"{sum(it.status == 'skipped' for it in items)} skipped, {len(failed)} failed")
    return 1 if failed else 0


def _add_reconstruct_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default="auto", help="model as the project writes it (e.g. "
                   "'lambert+microfacet(D=ggx,G=smith,F=none)'), or 'auto' (cheapest that explains the photos)")
    p.add_argument("--pixel-centres", action="store_true",
                   help="fit each pixel as the one ray through its centre instead of the area average over its "
                        "footprint (only for photos rendered that way)")
    p.add_argument("--solver", choices=("fast", "adam"), default="fast",
                   help="fast: per-texel Gauss-Newton/LM with closed-form linear parameters; adam: first order")
    p.add_argument("--loss", choices=("l2", "huber", "l1"), default="l2", help="robust loss (huber/l1 for highlights)")
    p.add_argument("--tex", type=int, default=None, help="texture size of the recovered maps (default: the dataset's)")
    p.add_argument("--bin", type=int, default=1, metavar="K",
                   help="fit the photos binned K×K (each block's mean: a pixel K times larger, modelled exactly): "
                        "K² fewer pixels, memory and time, for photos finer than the maps hold; default 1")
    p.add_argument("--sampling", choices=("nearest", "bilinear"), default=None,
                   help="how samples read the maps (default: bilinear, as a texture-mapped renderer reads them)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (1 is faster on a loaded machine)")
    add_device_arg(p, "the fits")
    p.add_argument("--float64", action="store_true", help="evaluate the model in float64 (precision studies)")
    add_fit_option_args(p)
    add_known_args(p)
    add_holdout_arg(p)
    p.add_argument("--force", action="store_true", help="replace an existing output folder")


def add_device_arg(p: argparse.ArgumentParser, what: str, default: str = "auto") -> None:
    """``--device cpu|cuda|cuda:N|auto`` (:func:`renderer.device.resolve_device`), where ``what`` runs."""
    p.add_argument("--device", default=default, metavar="auto|cpu|cuda[:N]",
                   help=f"where {what} run: auto (CUDA when torch sees a GPU), cpu, cuda or cuda:N; default {default}; "
                        f"rays are cast on the CPU either way")


def add_fit_option_args(p: argparse.ArgumentParser) -> None:
    """The solver options' flags, generated from :class:`capture.fit.options.FitOptions` (its declaration holds
    each flag's type, choices and help): ``--iterations``, ``--pooled``, ``--footprint-iterations``, … Not given =
    None, so the option's default or the caller's decision applies; :func:`fit_option_values` reads them back."""
    from capture.fit.options import FitOptions

    group = p.add_argument_group("solver options (capture.fit.options.FitOptions)")
    for name, kw in FitOptions.cli_flags():
        group.add_argument("--" + name.replace("_", "-"), dest=name, default=None, **kw)


def fit_option_values(args) -> dict:
    """The solver options given on the command line (:func:`add_fit_option_args`), by name."""
    from capture.fit.options import FitOptions

    return {name: getattr(args, name) for name, _ in FitOptions.cli_flags()
            if getattr(args, name, None) is not None}


def parse_views(text: str) -> list[int]:
    """``"3,7"`` → ``[3, 7]`` (argparse type of ``--holdout``)."""
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected view indices separated by commas, e.g. 3,7; got {text!r}") from None


def add_holdout_arg(p: argparse.ArgumentParser) -> None:
    """``--holdout 3,7``: views kept out of the fit to validate it (``reconstruct(holdout=...)``)."""
    p.add_argument("--holdout", type=parse_views, default=None, metavar="I,J",
                   help="view indices kept out of the fit and re-rendered with the recovered maps to validate them "
                        "(PSNR / SSIM in the summary); default: fit every view")


def add_known_args(p: argparse.ArgumentParser) -> None:
    """``--known NAME=VALUE`` (repeatable) and ``--scalars NAME,NAME``; :func:`known_options` reads them."""
    p.add_argument("--known", action="append", type=parse_known_value, metavar="NAME=VALUE[,VALUE,VALUE]",
                   help="hold a parameter at a known value instead of fitting it, e.g. --known coat_ior=1.5 "
                        "(repeatable; one value or one per channel)")
    p.add_argument("--scalars", default=None, metavar="NAME,NAME",
                   help="parameters fitted as one value for the whole object (default: coat_ior,coat_roughness; "
                        "'' = all per texel)")


def known_options(args) -> dict:
    """The ``known`` / ``scalars`` keyword arguments of :func:`capture.reconstruct.reconstruct` from parsed args."""
    out = {"known": dict(args.known or [])}
    if args.scalars is not None:
        out["scalars"] = tuple(n for n in args.scalars.split(",") if n)
    return out


def parse_known_value(text: str) -> tuple[str, list[float]]:
    """``"NAME=V"`` or ``"NAME=V1,V2,V3"`` → ``(NAME, [values])`` (argparse type of ``--known``)."""
    name, sep, values = text.partition("=")
    try:
        nums = [float(x) for x in values.split(",")]
    except ValueError:
        nums = []
    if not sep or not name or not nums:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE or NAME=V1,V2,V3 (e.g. coat_ior=1.5), got {text!r}")
    return name.strip(), nums


def _cmd_export(args) -> int:
    from capture.export import export_atlas_dirs

    side = export_atlas_dirs(args.recon_dirs, args.out, atlas_size=args.size, gutter=args.gutter, bits=args.bits,
                             fmt=args.format, transfer=args.transfer, force=args.force, glb=not args.no_glb,
                             material_model=args.material_model, texture_sets=args.texture_sets,
                             compensation=args.compensation)
    size = side["size"]
    out = Path(args.out)
    print(f"wrote {out} ({size['width']}x{size['height']} atlas, {len(side['materials'])} material(s), "
          f"{side['storage']['bits']}-bit)")
    gl = side.get("gltf")
    if gl:
        err = gl["mapping"].get("f0_error_core", {}).get("max")
        extra = f"; core mapping max |f0 error| {err:.4f}" if err is not None else ""
        kind = "metallic-roughness" if gl["material_model"] == "metallic-roughness" else "metallic 0"
        if gl["mapping"].get("specular_extension") or gl["material_model"] == "specular":
            kind += " + KHR_materials_specular"
        print(f"  {gl['file']}: glTF {kind}, Y-up, {gl['bits']}-bit PNG textures, compensation "
              f"{gl['compensation']}{extra}")
    for p in sorted(q for q in out.rglob("*") if q.is_file()):
        print(f"  {p.relative_to(out).as_posix()}  ({p.stat().st_size} bytes)")
    return 0


def _atlas_size(text: str) -> int | str:
    if text.strip().lower() == "pow2":
        return "pow2"
    try:
        size = int(text)
    except ValueError:
        size = 0
    if size <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of texels or 'pow2', got {text!r}")
    return size


def _texture_sets(text: str) -> tuple[str, ...]:
    from capture.export import TEXTURE_SETS

    names = tuple(t.strip() for t in text.split(",") if t.strip())
    if names in ((), ("none",)):
        return ()
    if names == ("all",):
        return TEXTURE_SETS
    bad = [t for t in names if t not in TEXTURE_SETS]
    if bad:
        raise argparse.ArgumentTypeError(f"unknown texture set(s) {bad}; choose from {', '.join(TEXTURE_SETS)}, "
                                         "'all' or 'none'")
    return names


def _add_export_args(p: argparse.ArgumentParser) -> None:
    from capture import export

    p.add_argument("--out", required=True, help="atlas folder to create")
    p.add_argument("--size", type=_atlas_size, default=None, help="square atlas size in texels, or 'pow2' for the "
                   "smallest power-of-two square (default: the tight size that fits, sides multiples of 4)")
    p.add_argument("--gutter", type=int, default=4, help="texels between materials (mip-map safety)")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8,
                   help="bits per channel of every PNG: atlas, GLB textures, texture sets (default 8)")
    p.add_argument("--format", choices=("png", "exr"), default="png")
    p.add_argument("--transfer", choices=("gamma2.2", "srgb"), default="gamma2.2",
                   help="colour encoding of K_diffuse/K_specular (Schüler: gamma 2.2)")
    p.add_argument("--material-model", choices=("metallic-roughness", "specular"), default="metallic-roughness",
                   help="GLB material: glTF metallic-roughness (metals as metallic 1; default) or metallic 0 "
                        "with f0 in KHR_materials_specular")
    p.add_argument("--compensation", choices=export.COMPENSATIONS, default=export.DEFAULT_COMPENSATION,
                   help="what the GLB's textures compensate of the viewer's BRDF: the diffuse dimmed under the "
                        "dielectric specular layer and the multiple scattering of rough metals (layering+multiscatter,"
                        " the default: Blender >= 4, three.js, Filament), the layering alone (viewers whose GGX "
                        "scatters once, as glTF's definition), or none (Blender 3.x); docs/export.md")
    p.add_argument("--texture-sets", type=_texture_sets, default="all", metavar="SETS",
                   help="comma-separated engine texture sets written into textures/: gltf, unreal, unity-hdrp; "
                        "'all' (default) or 'none'")
    p.add_argument("--no-glb", action="store_true", help="skip the glTF/GLB export")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")


def _cmd_demo(args) -> int:
    from capture.export import export_atlas_dirs
    from capture.outputs import check_output
    from capture.reconstruct import reconstruct
    from capture.synth import default_scene, make_synthetic, small_scene

    out = Path(args.out)
    check_output(out.absolute(), force=args.force)  # absolute: '--out .' names a folder the demo writes into
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: is a file; the demo writes its dataset, recon and atlas folders into a folder: "
                         f"choose another --out")
    cfg = small_scene("ggx-lambert", image_size=128, texture_size=64, n_views=8) if args.small else default_scene()
    t0 = time.perf_counter()
    size = lambda x: f"{x[0]}×{x[1]}" if isinstance(x, (tuple, list)) else f"{x}×{x}"  # noqa: E731
    model_name = cfg.model.get("name", cfg.model) if isinstance(cfg.model, dict) else cfg.model
    print(f"[1/3] synthesising the {'small' if args.small else 'default'} scene ({cfg.n_views} views of "
          f"{size(cfg.image_size)} px, {size(cfg.texture_size)} maps, model {model_name}) → {out / 'dataset'}")
    args.completed = []
    make_synthetic(cfg, out / "dataset", overwrite=True, device=args.device)
    args.completed.append(out / "dataset")
    t1 = time.perf_counter()
    print(f"      {t1 - t0:.1f} s\n[2/3] reconstructing with model {args.model} → {out / 'recon'}")
    report = reconstruct(out / "dataset", model=args.model, out_dir=out / "recon", force=True, device=args.device)
    args.completed.append(out / "recon")
    t2 = time.perf_counter()
    print(f"      {t2 - t1:.1f} s\n[3/3] exporting the Schüler atlas → {out / 'atlas'}")
    export_atlas_dirs([out / "recon"], out / "atlas", force=True)
    t3 = time.perf_counter()
    print(f"      {t3 - t2:.1f} s\n")
    summary = out / "recon" / "summary.txt"
    print(summary.read_text() if summary.exists() else json.dumps(getattr(report, "errors", {}), indent=2))
    print(f"total {t3 - t0:.1f} s; outputs in {out}")
    return 0


def _floats3(text: str, flag: str, grey: bool = False) -> list[float]:
    """``"x,y,z"`` → 3 floats (``grey``: one number means three equal ones)."""
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        vals = []
    if grey and len(vals) == 1:
        vals *= 3
    if len(vals) != 3:
        raise ValueError(f"{flag}: expected {'one number or ' if grey else ''}3 numbers separated by commas, got "
                         f"{text!r}")
    return vals


def _cmd_import(args) -> int:
    from capture.importers import Flash, ImportOptions, import_colmap, import_opencv_yaml, import_transforms_json

    flash = None
    if args.flash is not None:
        flash = Flash(_floats3(args.flash, "--flash"), _floats3(args.flash_intensity, "--flash-intensity", grey=True))
    lights = []
    if args.lights:
        lights = json.loads(Path(args.lights).read_text(encoding="utf-8"))
        if not isinstance(lights, list):
            raise ValueError(f"{args.lights}: --lights must hold a JSON list of light objects")
    masks = args.masks if args.masks in (None, "alpha") else Path(args.masks)
    opts = ImportOptions(mesh=args.mesh, images=args.images, masks=masks, flash=flash, lights=lights,
                         undistort=not args.no_undistort, encoding=args.encoding, exposure=args.exposure,
                         unwrap=args.unwrap)
    fn = {"colmap": import_colmap, "transforms": import_transforms_json, "opencv": import_opencv_yaml}[args.format]
    res = fn(args.source, args.out, opts, overwrite=args.overwrite)
    print(res.summary())
    for w in res.warnings:
        print(f"warning: {w}")
    return 0


def _add_import_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("format", choices=("colmap", "transforms", "opencv"),
                   help="colmap: a sparse model folder (cameras/images .txt or .bin); transforms: a NeRF/instant-ngp/"
                        "nerfstudio transforms.json; opencv: a cv2.FileStorage calibration YAML (docs/importing.md)")
    p.add_argument("source", help="the model folder or the camera file")
    p.add_argument("--mesh", required=True, help="the object's mesh (OBJ/PLY/GLB) in the cameras' world frame")
    p.add_argument("--out", required=True, help="dataset folder to create (must not exist unless --overwrite)")
    p.add_argument("--images", help="folder the photo names are relative to (required for colmap; default: the "
                   "camera file's folder)")
    p.add_argument("--masks", help="folder of masks named like the photos (nonzero = object), or 'alpha' (RGBA)")
    p.add_argument("--flash", metavar="X,Y,Z", help="a light fixed to the camera, at X,Y,Z in the camera frame "
                   "(OpenCV: x right, y down, z forward; world units); 0,0,0 = at the lens")
    p.add_argument("--flash-intensity", default="1", metavar="I or R,G,B", help="the flash's radiant intensity")
    p.add_argument("--lights", metavar="FILE", help="JSON list of world-space lights for every photo")
    p.add_argument("--no-undistort", action="store_true",
                   help="take the photos as already undistorted (distortion coefficients ignored)")
    p.add_argument("--encoding", choices=("auto", "srgb", "linear"), default="auto",
                   help="auto: 8-bit and 16-bit PNG/JPEG sRGB, EXR and 16-bit TIFF linear")
    p.add_argument("--exposure", type=float, default=1.0, help="pixel value = exposure · radiance")
    p.add_argument("--unwrap", action="store_true", help="give the mesh a UV atlas with xatlas (pip install xatlas)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")


def _cmd_calibrate_lights(args) -> int:
    from capture.photometric import UVRegion, calibrate_lights

    if (args.card_masks is None) == (args.uv_mask is None):
        raise ValueError("calibrate-lights: give exactly one of --card-masks DIR (per-photo masks of the card, named "
                         "like the photos) or --uv-mask FILE (a texture-space mask of the known-albedo region)")
    region = UVRegion(Path(args.uv_mask)) if args.uv_mask else Path(args.card_masks)
    albedo = _floats3(args.albedo, "--albedo", grey=True)
    cal = calibrate_lights(args.dataset, region, albedo, share=args.share, out=args.out, overwrite=args.overwrite)
    print(cal.summary())
    print(f"wrote {cal.out} (the dataset with the calibrated light intensities)")
    return 0


def _add_calibrate_lights_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="dataset folder whose light intensities are unknown or approximate")
    p.add_argument("--card-masks", metavar="DIR", help="folder of masks of the card (or known-albedo region) per "
                   "photo, named like the photos (images/000.exr → 000.png; nonzero = card); photos without one "
                   "are not used")
    p.add_argument("--uv-mask", metavar="FILE", help="texture-space mask (PNG, row 0 = v = 1, nonzero = the region) "
                   "of a known-albedo region of the mesh")
    p.add_argument("--albedo", required=True, metavar="A or R,G,B",
                   help="the region's linear diffuse albedo (0.18 for a grey card); it is taken as Lambertian")
    p.add_argument("--share", choices=("index", "each", "all"), default="index",
                   help="index: light j of every photo is one light (default); each: every entry its own; all: one "
                        "scale of the declared intensities for every light")
    p.add_argument("--out", required=True, help="new dataset folder to write (the input is not changed)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")


def _cmd_merge_hdr(args) -> int:
    import torch

    from capture.outputs import check_output
    from capture.photometric import merge_hdr
    from renderer.imageio import write_exr

    out = Path(args.out)
    if out.suffix.lower() != ".exr":
        raise ValueError(f"{out}: --out must be an .exr file (the merged linear radiance)")
    if out.exists() and not args.overwrite:
        raise ValueError(f"{out}: the output file already exists; choose another name or pass --overwrite")
    if any(Path(x).resolve() == out.resolve() for x in args.images):
        raise ValueError(f"{out}: the output is one of the brackets; choose another name")
    check_output(out.parent / f".{out.name}.check", force=True)
    res = merge_hdr(args.images, args.times, response=args.response, saturation=args.saturation)
    write_exr(out, res.radiance)
    rng = res.radiance[torch.isfinite(res.radiance)]
    print(f"wrote {out} ({res.radiance.shape[1]}x{res.radiance.shape[0]}, {len(args.images)} brackets, response "
          f"{res.response}; radiance {float(rng.min()):.4g}..{float(rng.max()):.4g}; "
          f"{int(res.saturated.sum())} px saturated in every bracket, {int(res.underexposed.sum())} px below the "
          f"noise floor in every bracket)")
    return 0


def _add_merge_hdr_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", nargs="+", help="the bracketed exposures (EXR, 16-bit TIFF/PNG linear; 8-bit "
                   "JPEG/PNG: response estimated)")
    p.add_argument("--times", nargs="+", type=float, required=True, metavar="T",
                   help="exposure time of each image, in the same order")
    p.add_argument("--response", choices=("auto", "linear", "srgb", "estimate"), default="auto",
                   help="auto: 8-bit → estimate (OpenCV Debevec), otherwise linear")
    p.add_argument("--saturation", type=float, default=None, help="clipping level in decoded units (default 1.0)")
    p.add_argument("--out", required=True, help="the merged .exr to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")


def _add_demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--model", default="ggx-lambert", help="model to reconstruct with (or 'auto')")
    p.add_argument("--small", action="store_true", help="a small, fast scene instead of the default one")
    add_device_arg(p, "the shading and the fits")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")


def _add_reconstruct_command_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="dataset folder (docs/dataset-format.md)")
    p.add_argument("--out", required=True, help="output folder")
    _add_reconstruct_args(p)


def _add_batch_command_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("datasets", nargs="+", help="dataset folders, or folders holding them")
    p.add_argument("--out", required=True, help="folder for one output folder per dataset and batch.json")
    p.add_argument("--cluster", metavar="ADDRESS", help="tcp://host:8786 of a running Dask scheduler, or local[:N] to "
                   "start N worker processes here; default: one after another in this process")
    _add_reconstruct_args(p)


def _add_export_command_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recon_dirs", nargs="+", help="reconstruction output folders")
    _add_export_args(p)


#: Every command: its one-line help, the function adding its arguments, the function running it.
COMMANDS = {
    "demo": ("synthesise the default scene, reconstruct, export the atlas, print errors", _add_demo_args, _cmd_demo),
    "synth": ("write a synthetic dataset with ground truth", _add_synth_args, _cmd_synth),
    "reconstruct": ("recover material maps from a dataset", _add_reconstruct_command_args, _cmd_reconstruct),
    "batch": ("reconstruct many datasets, each into its own folder; failures recorded, finished ones skipped",
              _add_batch_command_args, _cmd_batch),
    "export-atlas": ("pack reconstructions into a Schüler two-RGBA atlas (+ glTF)", _add_export_command_args,
                     _cmd_export),
    "import": ("import a real capture (COLMAP, transforms.json, OpenCV YAML) as a dataset", _add_import_args,
               _cmd_import),
    "calibrate-lights": ("estimate the lights' intensities from a grey card or a known-albedo region; write a new "
                         "dataset", _add_calibrate_lights_args, _cmd_calibrate_lights),
    "merge-hdr": ("merge bracketed exposures into one linear radiance EXR", _add_merge_hdr_args, _cmd_merge_hdr),
    "models": ("list every reflectance model with its parameters", lambda p: None, _cmd_models),
}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="shadecap", description="Differentiable material capture (see README.md).")
    sub = ap.add_subparsers(dest="command", required=True)
    for name, (text, add_args, func) in COMMANDS.items():
        p = sub.add_parser(name, help=text)
        add_args(p)
        p.set_defaults(func=func)
    return ap


def command_parser(command: str, prog: str) -> argparse.ArgumentParser:
    """The parser of one command on its own, named ``prog`` (a script's file name): the same arguments as
    ``shadecap COMMAND``."""
    text, add_args, func = COMMANDS[command]
    p = argparse.ArgumentParser(prog=prog, description=text[0].upper() + text[1:] + " (see README.md).")
    add_args(p)
    p.set_defaults(func=func, command=command)
    return p


def _import_eagerly() -> None:
    """Import trimesh (through ``renderer.mesh``) before any work, and re-raise a Ctrl-C its imports swallowed.

    trimesh imports its optional modules inside ``try: ... except BaseException`` and keeps the exception in a
    placeholder (``trimesh.exceptions.ExceptionWrapper``): a Ctrl-C that lands there is swallowed and the command
    goes on. Importing it here, where the interrupt is handled, and looking for such a placeholder makes that
    Ctrl-C stop the command like any other.
    """
    from trimesh.exceptions import ExceptionWrapper

    import renderer.mesh  # noqa: F401  (imports trimesh)

    for name, module in list(sys.modules.items()):
        if name != "trimesh" and not name.startswith("trimesh."):
            continue
        for value in list(vars(module).values()):
            if type(value) is ExceptionWrapper:
                kind = object.__getattribute__(value, "exception")[0]
                if isinstance(kind, type) and issubclass(kind, KeyboardInterrupt):
                    raise KeyboardInterrupt


def _error_text(exc: BaseException) -> str:
    if isinstance(exc, OSError) and not isinstance(exc, ValueError):
        from capture.outputs import os_error_message

        return os_error_message(exc)
    return " ".join(str(exc).split("\n")) if str(exc) else type(exc).__name__


def run(command: str, func, args, name: str | None = None) -> int:
    """``func(args)`` with the command line's handling: a user error is one line on stderr and status 2, Ctrl-C
    is ``interrupted; nothing written`` and status 130 (a command that finished some outputs before, as ``demo``
    does, lists them in ``args.completed``). Messages start with ``name`` (default ``shadecap COMMAND``)."""
    name = name or f"shadecap {command}"
    from renderer.device import tune_allocator

    tune_allocator()                    # the process is the command's: freed temporaries kept for reuse
    try:
        if command != "models":
            _import_eagerly()
        return func(args)
    except USER_ERRORS as exc:
        print(f"{name}: error: {_error_text(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        done = getattr(args, "completed", None)
        kept = f" by the step in progress (complete: {', '.join(map(str, done))})" if done else ""
        print(f"\n{name}: interrupted; nothing written{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run(args.command, args.func, args)


def script_main(command: str, script: str, argv: list[str] | None = None) -> int:
    """Run the command ``command`` as the script ``script`` (its file name): the command's own parser, whose
    ``--help``, usage and error lines name the script. ``argv`` defaults to ``sys.argv[1:]``."""
    args = command_parser(command, script).parse_args(sys.argv[1:] if argv is None else argv)
    return run(command, args.func, args, name=script)


if __name__ == "__main__":
    sys.exit(main())
