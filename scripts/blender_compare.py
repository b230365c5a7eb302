"""Render an exported GLB in Blender Cycles from a dataset's cameras and compare it with the dataset's photos.

    python scripts/blender_compare.py DATASET GLB [--views 0,5,10,15] [--spp 64] [--blender CMD] [--out DIR]

Blender's glTF importer reads the GLB with its defaults (nothing Blender-specific is set afterwards: what a GLB
means in Blender is what the file says); Cycles renders direct light only (the photos' image formation), a box
pixel filter of width 1, the Standard view transform, no denoising, a fixed seed. Cameras come from
``Camera.to_blender``, each view's point lights become Cycles point lights of power 4π·I (Cycles: I = P / 4π
W/sr) and radius 0. The figure is the PSNR on object pixels (where the photo is non-zero), peak = the photo's
maximum there, per view and averaged (docs/export.md, "Checked by rendering").

Blender: ``--blender`` or ``$SHADECAP_BLENDER`` — a Blender executable (e.g. Debian's ``/usr/bin/blender``), or a
Python interpreter whose ``import bpy`` works (PyPI's ``bpy`` module: ``/path/to/venv/bin/python``); else
``blender`` on PATH; else this interpreter when it imports bpy. Rendering is single-threaded (``--threads``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

#: Runs inside Blender: ``blender -b --factory-startup --python-expr BLENDER_SCRIPT -- JOB.json`` or
#: ``python -c BLENDER_SCRIPT -- JOB.json`` with the bpy module. JOB: {glb, out, spp, threads, views: [{name,
#: camera: Camera.to_blender(), lights: [{position, intensity: [r, g, b]}]}]}; writes OUT/NAME.exr (RGBA, float).
BLENDER_SCRIPT = r"""
import json, math, sys
import bpy
from mathutils import Matrix

job = json.load(open(sys.argv[sys.argv.index("--") + 1]))
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=job["glb"])  # glTF Y-up -> Blender Z-up: the dataset's own frame
print("SHADECAP_BLENDER_VERSION", bpy.app.version_string, flush=True)
scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = job["spp"]
scene.cycles.use_adaptive_sampling = False
scene.cycles.use_denoising = False
scene.cycles.seed = 1
scene.cycles.max_bounces = 0  # direct light only: the image formation of the photos
scene.cycles.pixel_filter_type = "BOX"
scene.cycles.filter_width = 1.0
scene.render.threads_mode = "FIXED"
scene.render.threads = job["threads"]
scene.render.film_transparent = True  # alpha = coverage
world = bpy.data.worlds.new("black")
world.color = (0.0, 0.0, 0.0)
if world.node_tree is not None:  # Blender >= 5: a new world has nodes, a grey Background lighting the scene
    for node in world.node_tree.nodes:
        if node.type == "BACKGROUND":
            node.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
            node.inputs["Strength"].default_value = 0.0
scene.world = world
scene.view_settings.view_transform = "Standard"
scene.view_settings.look = "None"
scene.view_settings.exposure = 0.0
scene.view_settings.gamma = 1.0
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
scene.render.image_settings.color_mode = "RGBA"
for view in job["views"]:
    for obj in [o for o in scene.objects if o.type in ("LIGHT", "CAMERA")]:
        bpy.data.objects.remove(obj)
    for k, light in enumerate(view["lights"]):
        peak = max(light["intensity"])
        data = bpy.data.lights.new(f"light{k}", "POINT")
        data.energy = 4 * math.pi * peak  # Cycles point light: I = P / (4 pi) W/sr
        data.color = [c / peak if peak > 0 else 0.0 for c in light["intensity"]]
        data.shadow_soft_size = 0.0
        obj = bpy.data.objects.new(f"light{k}", data)
        obj.location = light["position"]
        scene.collection.objects.link(obj)
    cam = view["camera"]
    data = bpy.data.cameras.new("camera")
    data.lens, data.sensor_width, data.sensor_fit = cam["lens"], cam["sensor_width"], cam["sensor_fit"]
    data.shift_x, data.shift_y = cam["shift_x"], cam["shift_y"]
    obj = bpy.data.objects.new("camera", data)
    obj.matrix_world = Matrix(cam["matrix_world"])
    scene.collection.objects.link(obj)
    scene.camera = obj
    scene.render.resolution_x, scene.render.resolution_y = cam["resolution_x"], cam["resolution_y"]
    scene.render.resolution_percentage = 100
    scene.render.filepath = f"{job['out']}/{view['name']}.exr"
    bpy.ops.render.render(write_still=True)
print("SHADECAP_BLENDER_DONE", flush=True)
"""


class BlenderError(RuntimeError):
    """Blender could not be found or did not render."""


def _is_python(exe: str) -> bool:
    return Path(exe).name.lower().startswith("python")


def find_blender(explicit: str | None = None) -> list[str] | None:
    """The command that runs :data:`BLENDER_SCRIPT`: ``[blender, -b, --factory-startup, --python-expr]`` or
    ``[python, -c]``; from ``explicit``, ``$SHADECAP_BLENDER``, ``blender`` on PATH, this interpreter with bpy.
    None when there is none."""
    exe = explicit or os.environ.get("SHADECAP_BLENDER")
    if exe:
        found = shutil.which(exe)
        if found is None:
            raise BlenderError(f"Blender command {exe!r} not found")
        return [found, "-c"] if _is_python(found) else [found, "-b", "--factory-startup", "--python-expr"]
    found = shutil.which("blender")
    if found:
        return [found, "-b", "--factory-startup", "--python-expr"]
    if importlib.util.find_spec("bpy") is not None:
        return [sys.executable, "-c"]
    return None


def render(glb, views: list[dict], out, *, spp: int = 64, threads: int = 1, blender: list[str] | None = None,
           timeout: float = 1800) -> str:
    """Render ``glb`` for ``views`` ([{name, camera: Camera.to_blender(), lights: [{position, intensity}]}]) into
    ``out/NAME.exr``; returns Blender's version string. The bpy module may crash at interpreter exit after
    finishing, so the run counts as done when the script said so and every image exists."""
    blender = blender or find_blender()
    if blender is None:
        raise BlenderError("no Blender: pass --blender, set SHADECAP_BLENDER, or put `blender` on PATH")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    job = {"glb": str(Path(glb).resolve()), "out": str(out.resolve()), "spp": int(spp), "threads": int(threads),
           "views": views}
    with tempfile.TemporaryDirectory() as tmp:
        job_file = Path(tmp) / "job.json"
        job_file.write_text(json.dumps(job))
        proc = subprocess.run([*blender, BLENDER_SCRIPT, "--", str(job_file)], capture_output=True, text=True,
                              timeout=timeout)
    log = proc.stdout + proc.stderr
    missing = [v["name"] for v in views if not (out / f"{v['name']}.exr").exists()]
    if "SHADECAP_BLENDER_DONE" not in proc.stdout or missing:
        raise BlenderError(f"Blender failed (status {proc.returncode}, missing {missing}){_known_cause(log)}:\n"
                           f"{log[-3000:]}")
    return next(line.split(None, 1)[1] for line in proc.stdout.splitlines()
                if line.startswith("SHADECAP_BLENDER_VERSION"))


def _known_cause(log: str) -> str:
    """A hint naming the cause and the fix of a Blender failure this project has met, from Blender's output."""
    if "has no attribute 'bool'" in log:
        return (" — this Blender's glTF importer uses numpy's `np.bool`, which numpy 1.24 removed (Blender ≤ 3.4 "
                "beside a newer numpy, e.g. Debian 12's blender 3.4 and python3-numpy 1.24): use Blender ≥ 3.5, by "
                "SHADECAP_BLENDER=/path/to/blender or --blender, or a Python with the `bpy` wheel")
    if "No module named 'numpy'" in log:
        return (" — Blender's Python has no numpy, which its glTF importer needs: install numpy for that Python "
                "(Debian: python3-numpy) or use a Blender that bundles it")
    return ""


def light_json(light) -> dict:
    """A renderer.lights.PointLight as the job's light."""
    if type(light).__name__ != "PointLight":
        raise BlenderError(f"only point lights are rendered, got {type(light).__name__}")
    return {"position": [float(x) for x in light.position.reshape(-1)],
            "intensity": [float(x) for x in light.intensity.reshape(-1).expand(3)]}


def psnr(image: torch.Tensor, photo: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR on ``mask`` with the photo's maximum there as peak (dB)."""
    peak = photo[mask].max()
    mse = ((image[..., :3] - photo[..., :3])[mask] ** 2).mean()
    return (10 * torch.log10(peak**2 / mse)).item()


def compare(dataset, glb, views: list[int], out, *, spp: int = 64, threads: int = 1,
            blender: list[str] | None = None) -> dict:
    """Render ``glb`` from the dataset's ``views`` and compare with its photos: {version, psnr: {view: dB}, mean}."""
    from capture.dataset import load_dataset
    from renderer import imageio

    ds = load_dataset(dataset)
    bad = [i for i in views if not 0 <= i < len(ds.views)]
    if bad:
        raise BlenderError(f"views {bad} out of range (the dataset has {len(ds.views)})")
    jobs = [{"name": f"view{i:03d}", "camera": ds.views[i].camera.to_blender(),
             "lights": [light_json(li) for li in ds.views[i].lights]} for i in views]
    version = render(glb, jobs, out, spp=spp, threads=threads, blender=blender)
    photos = ds.load_images()
    result = {}
    for i, job in zip(views, jobs, strict=True):
        photo = photos[i].radiance
        image = imageio.read_exr(Path(out) / f"{job['name']}.exr")
        result[i] = psnr(image, photo, photo.sum(-1) > 0)
    return {"version": version, "psnr": result, "mean": sum(result.values()) / len(result)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", help="dataset folder (scene.json)")
    p.add_argument("glb", help="the GLB to render (e.g. ATLAS/atlas.glb)")
    p.add_argument("--views", default="0,5,10,15", help="comma-separated view indices (default 0,5,10,15)")
    p.add_argument("--spp", type=int, default=64, help="Cycles samples per pixel (default 64)")
    p.add_argument("--threads", type=int, default=1, help="Cycles render threads (default 1)")
    p.add_argument("--blender", default=None, help="Blender executable or a Python with bpy (see above)")
    p.add_argument("--out", default=None, help="folder for the renders (default: a temporary one)")
    args = p.parse_args(argv)
    views = [int(v) for v in args.views.split(",") if v.strip()]
    with tempfile.TemporaryDirectory() as tmp:
        res = compare(args.dataset, args.glb, views, args.out or tmp, spp=args.spp, threads=args.threads,
                      blender=find_blender(args.blender))
    print(f"Blender {res['version']}, {args.spp} spp: " + " / ".join(f"{v:.1f}" for v in res["psnr"].values())
          + f" dB (views {', '.join(map(str, res['psnr']))}), mean {res['mean']:.1f} dB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
