"""Export recovered materials: linear EXR maps, Schüler's two-RGBA atlas with its JSON sidecar, a GLB.

A reconstruction folder (the contract with ``capture/reconstruct.py``) holds ``albedo.exr``,
``f0.exr``, ``roughness.exr``, optionally ``absorption.exr``, ``mask.exr`` and/or ``coverage.exr``,
``mesh.obj`` (with UVs) and ``report.json`` (optional ``coat_ior`` / ``coat_roughness`` numbers).
The Python API takes maps as a dict of tensors ``[H, W, C]`` (canonical, linear, row 0 = v = 1), so
it does not depend on that folder.

An atlas folder (layout and schema in ``docs/export.md``):

- ``tex1.png`` — RGB = K_diffuse (albedo) encoded by ``transfer``, A = mask (linear);
- ``tex2.png`` — RGB = K_specular (f0) encoded by ``transfer``, A = glossiness g (linear, e = 2^(12 g));
  8-bit by default, 16-bit PNG or float EXR (same encoded values) on request;
- ``absorption.exr`` / ``coat.exr`` (only when a material has a coat) — linear float: absorption RGB,
  and (R = coat η₁, G = coat roughness, B = 0); materials without a coat hold 0 / (1, 0);
- ``meshes/<name>.obj`` — each material's mesh with its UVs rewritten into its rectangle;
- ``atlas.glb`` — the meshes with one glTF 2.0 material over the atlas (see :func:`write_glb`);
- ``atlas.json`` — the sidecar: format version, channel table, encoding, size, gutter, and each
  material's rectangle in pixels and in UV.

Everything is written into a temporary folder next to ``out`` and renamed into place at the end
(:func:`capture.outputs.atomic_folder`), so an interrupted export never leaves a half-written atlas.
``out`` is checked before any work (:func:`capture.outputs.check_output`): an existing one is
refused unless ``force=True``, and it may never be, contain or sit inside a reconstruction folder
it reads.
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from materials import atlas as A
from renderer import imageio
from renderer.mesh import Mesh, MeshError, load_mesh, save_mesh

from .outputs import atomic_folder, check_output, json_text

__all__ = [
    "ATLAS_FORMAT", "ExportError", "ExportWarning", "Material", "export_atlas", "export_atlas_dirs",
    "load_reconstruction", "read_atlas", "write_glb", "write_maps",
]

#: Version of the atlas folder format (``atlas.json`` → ``format``).
ATLAS_FORMAT = "shadecap-schuler-atlas/1"
#: Canonical maps of a reconstruction folder and their channel counts.
MAP_CHANNELS = {"albedo": 3, "f0": 3, "roughness": 1, "absorption": 3, "mask": 1, "coverage": 1}
REQUIRED = ("albedo",)
#: Values of maps a diffuse-only model (e.g. Lambert) does not have: no specular reflection.
DIFFUSE_ONLY_DEFAULTS = {"f0": 0.0, "roughness": 1.0}
_RANGES = {"albedo": (0.0, 1.0), "f0": (0.0, 1.0), "roughness": (0.0, 1.0), "mask": (0.0, 1.0),
           "coverage": (0.0, 1.0), "absorption": (0.0, math.inf)}
#: KHR_materials_specular: f0 = min(F0(ior) · specularColorFactor · texture, 1); with ior 1.5,
#: F0(ior) = 0.04, so a factor of 25 makes the texture hold f0 itself.
_SPEC_FACTOR = 25.0


class ExportError(ValueError):
    """Export cannot proceed; the message names the file, the material or the field, and the fix."""


class ExportWarning(UserWarning):
    """Inputs were resampled or clamped during export; the message gives the material and the counts."""


@dataclass
class Material:
    """One material to export: canonical maps, an optional mesh, optional coat constants."""

    name: str
    maps: dict[str, Tensor]
    mesh: Mesh | None = None
    coat_ior: float | None = None
    coat_roughness: float | None = None
    source: str = ""
    extra: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# validation and resampling


def _to_hwc(x, name: str, where: str) -> Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(x)
    if not isinstance(x, Tensor):
        raise ExportError(f"{where}: map '{name}' must be a tensor [H, W, C], got {type(x).__name__}")
    x = x.detach().to("cpu")
    x = x.float() if not x.is_floating_point() else x.to(torch.float32)
    if x.dim() == 2:
        x = x[..., None]
    want = MAP_CHANNELS.get(name)
    if want == 1 and x.dim() == 3 and x.shape[-1] in (3, 4) and bool((x[..., :3] == x[..., :1]).all()):
        x = x[..., :1]  # a grey map stored as RGB(A), as image tools write single-channel data
    if x.dim() != 3 or (want is not None and x.shape[-1] not in (want, 1)):
        raise ExportError(f"{where}: map '{name}' must have shape [H, W, {want}], got {tuple(x.shape)}")
    if want is not None and x.shape[-1] != want:
        x = x.expand(*x.shape[:2], want).contiguous()
    bad = ~torch.isfinite(x)
    if bad.any():
        raise ExportError(f"{where}: map '{name}' has {int(bad.sum())} NaN/inf value(s); fill or fix the map")
    return x


def _resize(x: Tensor, size: tuple[int, int], name: str) -> Tensor:
    """Bilinear resampling of ``[H, W, C]`` to ``size = (H, W)``; masks/coverage use nearest."""
    mode = "nearest" if name in ("mask", "coverage") else "bilinear"
    kw = {} if mode == "nearest" else {"align_corners": False, "antialias": True}
    return F.interpolate(x.permute(2, 0, 1)[None], size=size, mode=mode, **kw)[0].permute(1, 2, 0).contiguous()


def _prepare(mat: Material) -> dict[str, Tensor]:
    """Validated, same-size, clamped maps of one material (warns about every change)."""
    where = f"material '{mat.name}'"
    missing = [k for k in REQUIRED if k not in mat.maps or mat.maps[k] is None]
    if missing:
        have = sorted(k for k in mat.maps if mat.maps[k] is not None)
        raise ExportError(f"{where}: missing map(s) {missing}; have {have}")
    maps = {k: _to_hwc(v, k, where) for k, v in mat.maps.items() if v is not None and k in MAP_CHANNELS}
    absent = [k for k in DIFFUSE_ONLY_DEFAULTS if k not in maps]
    if absent:
        h, w = maps["albedo"].shape[:2]
        for k in absent:
            maps[k] = torch.full((h, w, MAP_CHANNELS[k]), DIFFUSE_ONLY_DEFAULTS[k], dtype=maps["albedo"].dtype)
        warnings.warn(f"{where}: no {absent} map (a diffuse-only model); exported as "
                      f"{ {k: DIFFUSE_ONLY_DEFAULTS[k] for k in absent} }, i.e. no specular reflection",
                      ExportWarning, stacklevel=3)
    sizes = {k: tuple(v.shape[:2]) for k, v in maps.items()}
    target = max(sizes.values(), key=lambda s: (s[0] * s[1], s))
    odd = {k: s for k, s in sizes.items() if s != target}
    if odd:
        warnings.warn(
            f"{where}: maps of different sizes {sizes}; resampled {sorted(odd)} to {target[0]}x{target[1]} (H x W)",
            ExportWarning, stacklevel=3,
        )
        maps = {k: (_resize(v, target, k) if k in odd else v) for k, v in maps.items()}
    counts = []
    for k, v in maps.items():
        lo, hi = _RANGES[k]
        below, above = int((v < lo).sum()), int((v > hi).sum())
        if below or above:
            counts.append(f"{k}: {below} below {lo:g}, {above} above {hi:g}")
            maps[k] = v.clamp(lo, hi)
    if counts:
        warnings.warn(f"{where}: out-of-range values clamped ({'; '.join(counts)})", ExportWarning, stacklevel=3)
    return maps


# --------------------------------------------------------------------------------------------
# reconstruction folders


def load_reconstruction(folder, name: str | None = None) -> Material:
    """Read a reconstruction folder (see module docstring) into a :class:`Material`.

    Raises:
        ExportError: missing folder or required map, unreadable map or mesh, bad report.json.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ExportError(f"{folder}: reconstruction folder does not exist")
    maps = {}
    for key in MAP_CHANNELS:
        p = folder / f"{key}.exr"
        if not p.exists():
            if key in REQUIRED:
                raise ExportError(f"{p}: required map '{key}' is missing from the reconstruction folder")
            continue
        try:
            maps[key] = imageio.read_exr(p)
        except imageio.ImageIOError as err:
            raise ExportError(f"{p}: cannot read map '{key}': {err}") from err
        if key == "coverage" and maps[key].shape[-1] > 1:
            # capture.reconstruct writes per-texel counts (samples, views, ...); export needs observed or not
            maps[key] = (maps[key][..., :1] > 0).to(maps[key].dtype)
    report = {}
    rp = folder / "report.json"
    if rp.exists():
        try:
            report = json.loads(rp.read_text())
        except (OSError, ValueError) as err:
            raise ExportError(f"{rp}: unreadable report ({err})") from err
        if not isinstance(report, dict):
            raise ExportError(f"{rp}: report must be a JSON object")
    mesh = None
    mp = folder / "mesh.obj"
    if mp.exists():
        try:
            mesh = load_mesh(mp)
        except MeshError as err:
            raise ExportError(f"{mp}: {err}") from err

    def num(key):
        v = report.get(key)
        if v is None:
            return None
        if not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ExportError(f"{rp}: field '{key}' must be a finite number, got {v!r}")
        return float(v)

    return Material(name or folder.name, maps, mesh, num("coat_ior"), num("coat_roughness"), source=str(folder))


def write_maps(maps: Mapping[str, Tensor], out, previews: bool = True, half: bool = False) -> list[Path]:
    """Write each map as ``<name>.exr`` (linear float, or half) and, with ``previews``, ``<name>.png``.

    Previews: colour maps (albedo, f0) sRGB-encoded; scalar maps and absorption (divided by its
    maximum when above 1) written linearly. The folder is created if missing. Returns the paths.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for k, v in maps.items():
        x = _to_hwc(v, k, f"write_maps({out})")
        imageio.write_exr(out / f"{k}.exr", x, half=half)
        written.append(out / f"{k}.exr")
        if previews:
            transfer = "srgb" if k in ("albedo", "f0") else "linear"
            if k == "absorption" and x.max() > 1:
                x = x / x.max()
            imageio.write_png(out / f"{k}.png", x, transfer=transfer)
            written.append(out / f"{k}.png")
    return written


# --------------------------------------------------------------------------------------------
# the atlas


def _materials(inputs) -> list[Material]:
    if isinstance(inputs, Mapping):
        mats = [Material(str(k), dict(v)) for k, v in inputs.items()]
    elif isinstance(inputs, (str, os.PathLike, Material)):
        mats = [inputs]
    else:
        mats = list(inputs)
    out = []
    for m in mats:
        out.append(load_reconstruction(m) if isinstance(m, (str, os.PathLike)) else m)
    if not out:
        raise ExportError("export_atlas: no materials given")
    names = [m.name for m in out]
    for m in out:
        if not isinstance(m, Material):
            raise ExportError(
                f"export_atlas: expected Material, folder path or name→maps mapping, got {type(m).__name__}"
            )
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", m.name):
            raise ExportError(f"material name {m.name!r} must use letters, digits, '_', '-', '.' only")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ExportError(f"material names must be unique, got duplicates {dup}; pass names explicitly")
    return out


def export_atlas(
    materials, out, *, atlas_size: int | tuple[int, int] | None = None, gutter: int = 4, bits: int = 8,
    fmt: str = "png", transfer: str = "gamma2.2", force: bool = False, glb: bool = True,
) -> dict:
    """Pack one or many materials into Schüler's two-RGBA atlas and write the atlas folder ``out``.

    Args:
        materials: a :class:`Material`, a reconstruction folder, a list of either, or ``{name: maps}``.
        out: the atlas folder to create (refused if it exists, unless ``force``).
        atlas_size: None (smallest power-of-two square that fits), an int (square) or (width, height).
        gutter: free texels around each material, filled by dilation (mip levels up to log2(gutter) stay clean).
        bits: 8 or 16 for PNG textures. fmt: ``"png"`` or ``"exr"`` (float EXR of the same encoded values).
        transfer: colour encoding of the RGB channels, ``"gamma2.2"`` (Schüler) or ``"srgb"``.
        force: replace an existing ``out``. glb: also write ``atlas.glb`` (needs every material to have a mesh).

    Returns:
        The sidecar dict written to ``out/atlas.json``.

    Raises:
        ExportError: bad inputs, ``out`` exists, atlas too small (with the size needed), unwritable output.
    """
    out = Path(out)
    if fmt not in ("png", "exr"):
        raise ExportError(f"fmt must be 'png' or 'exr', got {fmt!r}")
    if bits not in (8, 16):
        raise ExportError(f"bits must be 8 or 16, got {bits!r}")
    if transfer not in ("gamma2.2", "srgb"):
        raise ExportError(f"transfer must be 'gamma2.2' (Schüler) or 'srgb', got {transfer!r}")
    check_output(out, _input_folders(materials), force=force, error=ExportError, force_flag="force=True (--force)")
    mats = _materials(materials)
    prepared = [_prepare(m) for m in mats]
    tex, coverage, coat = [], [], []
    any_coat = any("absorption" in p or m.coat_ior is not None for m, p in zip(mats, prepared, strict=True))
    for m, p in zip(mats, prepared, strict=True):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t1, t2 = A.encode_schuler(p, transfer)
        for w in caught:
            warnings.warn(f"material '{m.name}': {w.message}", ExportWarning, stacklevel=2)
        tex.append(torch.cat([t1, t2], dim=-1))
        cov = p.get("coverage")
        if cov is None and "mask" in p:
            cov = p["mask"]
        coverage.append(None if cov is None else cov[..., 0] > 0)
        if any_coat:
            h, w = t1.shape[:2]
            absorption = p.get("absorption", torch.zeros(h, w, 3))
            has_coat = "absorption" in p or m.coat_ior is not None
            ior = m.coat_ior if m.coat_ior is not None else (1.5 if has_coat else 1.0)
            rough = m.coat_roughness if m.coat_roughness is not None else (0.1 if has_coat else 0.0)
            if not 1.0 <= ior <= 3.0 or not 0.0 <= rough <= 1.0:
                raise ExportError(f"material '{m.name}': coat_ior {ior} must lie in [1, 3] and coat_roughness "
                                  f"{rough} in [0, 1]")
            coat.append(torch.cat([absorption, torch.full((h, w, 1), ior), torch.full((h, w, 1), rough)], -1))
    sizes = [(t.shape[1], t.shape[0]) for t in tex]
    try:
        packing = A.pack_rectangles(sizes, atlas_size, gutter)
    except A.AtlasError as err:
        raise ExportError(f"{out}: {err}") from err
    atlas = A.compose(tex, packing, gutter, coverage)
    coat_atlas = A.compose(coat, packing, gutter, coverage) if any_coat else None
    width, height = packing.size

    sidecar = {
        "format": ATLAS_FORMAT,
        "layout": "schuler-2rgba",
        "size": {"width": width, "height": height},
        "gutter": gutter,
        "transfer": transfer,
        "storage": {"format": fmt, "bits": bits if fmt == "png" else 32},
        "uv_convention": "u right, v up, (0,0) at the bottom-left of the image; texel (i, j) centre at "
                         "u=(j+0.5)/W, v=1-(i+0.5)/H; rect x = column, y = row of its top-left texel",
        "textures": {
            "tex1": {"file": f"tex1.{fmt}", "channels": {
                "R": "albedo.r", "G": "albedo.g", "B": "albedo.b", "A": "mask"},
                "encoding": {"RGB": transfer, "A": "linear"}},
            "tex2": {"file": f"tex2.{fmt}", "channels": {
                "R": "f0.r", "G": "f0.g", "B": "f0.b", "A": "glossiness"},
                "encoding": {"RGB": transfer, "A": "linear"},
                "glossiness": "g in [0,1]; Blinn-Phong exponent e = 2^(12 g); roughness r = (2/(e+2))^(1/4)"},
        },
        "materials": [],
    }
    if any_coat:
        sidecar["textures"]["absorption"] = {"file": "absorption.exr", "channels": {
            "R": "absorption.r", "G": "absorption.g", "B": "absorption.b"}, "encoding": {"RGB": "linear float"},
            "meaning": "Gotanda 2012 eq 3 alpha' (alpha*d for eq 2), >= 0"}
        sidecar["textures"]["coat"] = {"file": "coat.exr", "channels": {
            "R": "coat_ior", "G": "coat_roughness", "B": "reserved (0)"}, "encoding": {"RGB": "linear float"},
            "meaning": "coat ior 1 and absorption 0 mean no coat"}
    for m, rect in zip(mats, packing.rects, strict=True):
        u0, v0, u1, v1 = A.rect_uv(rect, packing.size)
        entry = {"name": m.name, "rect": {"x": rect.x, "y": rect.y, "w": rect.w, "h": rect.h},
                 "uv": {"u_min": u0, "v_min": v0, "u_max": u1, "v_max": v1}}
        if m.source:
            entry["source"] = m.source
        if m.mesh is not None:
            entry["mesh"] = f"meshes/{m.name}.obj"
        sidecar["materials"].append(entry)
    if glb:
        without = [m.name for m in mats if m.mesh is None]
        glb = not without
        if without and len(without) < len(mats):  # all without a mesh: nothing to put in a GLB, silently
            warnings.warn(f"no atlas.glb: material(s) {without} have no mesh", ExportWarning, stacklevel=2)
    if glb:
        sidecar["gltf"] = {"file": "atlas.glb", "material": _GLTF_DOC}

    # -- write everything into a temp folder, then rename into place
    with atomic_folder(out, force=force, error=ExportError, force_flag="force=True (--force)") as tmp:
        for k, t in (("tex1", atlas[..., :4]), ("tex2", atlas[..., 4:])):
            if fmt == "png":
                imageio.write_png(tmp / f"{k}.png", t, bits=bits, transfer="linear")
            else:
                imageio.write_exr(tmp / f"{k}.exr", t)
        if coat_atlas is not None:
            imageio.write_exr(tmp / "absorption.exr", coat_atlas[..., :3])
            zero = torch.zeros_like(coat_atlas[..., :1])
            imageio.write_exr(tmp / "coat.exr", torch.cat([coat_atlas[..., 3:5], zero], -1))
        meshes = []
        for m, rect in zip(mats, packing.rects, strict=True):
            if m.mesh is None:
                continue
            try:
                uv = A.remap_uvs(m.mesh.uvs, rect, packing.size)
            except A.AtlasError as err:
                raise ExportError(f"material '{m.name}' mesh: {err}") from err
            moved = Mesh.from_arrays(m.mesh.vertices.numpy(), m.mesh.faces.numpy(), uv.numpy(),
                                     m.mesh.normals.numpy(), name=m.name)
            (tmp / "meshes").mkdir(exist_ok=True)
            save_mesh(moved, tmp / "meshes" / f"{m.name}.obj")
            meshes.append(moved)
        if glb:
            dec = A.decode_schuler(atlas[..., :4], atlas[..., 4:], transfer)
            write_glb(tmp / "atlas.glb", meshes, dec)
        (tmp / "atlas.json").write_text(json_text(sidecar) + "\n")
    return sidecar


def _input_folders(materials) -> dict:
    """The folders (and files) an export reads: reconstruction folders given as paths, materials' sources."""
    items = [materials] if isinstance(materials, (str, os.PathLike, Material)) or isinstance(materials, Mapping) \
        else list(materials)
    out = {}
    for m in items:
        if isinstance(m, (str, os.PathLike)):
            out[Path(m)] = "the reconstruction folder"
        elif isinstance(m, Material) and m.source:
            out[Path(m.source)] = f"the source of material '{m.name}'"
    return out


def export_atlas_dirs(recon_dirs: Sequence, out, **kwargs) -> dict:
    """Export reconstruction folders into one atlas; the entry point of ``scripts/export_atlas.py`` and
    ``shadecap export-atlas``. Material names are the folder names (made unique with a suffix)."""
    check_output(out, {Path(d): "the reconstruction folder" for d in recon_dirs}, force=kwargs.get("force", False),
                 error=ExportError, force_flag="force=True (--force)")
    mats, seen = [], {}
    for d in recon_dirs:
        base = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(d).resolve().name) or "material"
        seen[base] = seen.get(base, 0) + 1
        mats.append(load_reconstruction(d, base if seen[base] == 1 else f"{base}-{seen[base]}"))
    return export_atlas(mats, out, **kwargs)


# --------------------------------------------------------------------------------------------
# import


def read_atlas(folder) -> dict[str, dict[str, Tensor]]:
    """Read an atlas folder back → ``{material name: maps}`` (albedo, f0, roughness, glossiness, mask,
    and absorption / coat_ior / coat_roughness when the atlas has a coat texture), each ``[h, w, C]``.

    Raises:
        ExportError: missing folder or sidecar, unknown format, missing or mis-sized textures.
    """
    folder = Path(folder)
    sp = folder / "atlas.json"
    if not sp.is_file():
        raise ExportError(f"{sp}: atlas sidecar is missing; is {folder} an atlas folder?")
    try:
        side = json.loads(sp.read_text())
        fmt_ok = side.get("format") == ATLAS_FORMAT
        width, height = side["size"]["width"], side["size"]["height"]
        transfer = side["transfer"]
        files = {k: side["textures"][k]["file"] for k in side["textures"]}
        rects = {m["name"]: A.Rect(m["rect"]["x"], m["rect"]["y"], m["rect"]["w"], m["rect"]["h"])
                 for m in side["materials"]}
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise ExportError(f"{sp}: malformed sidecar ({type(err).__name__}: {err})") from err
    if not fmt_ok:
        raise ExportError(f"{sp}: unknown format {side.get('format')!r}; expected {ATLAS_FORMAT!r}")
    tex = {}
    for k, f in files.items():
        p = folder / f
        try:
            tex[k] = imageio.read_image(p, transfer="linear")
        except imageio.ImageIOError as err:
            raise ExportError(f"{p}: cannot read atlas texture '{k}': {err}") from err
        if tuple(tex[k].shape[:2]) != (height, width):
            raise ExportError(f"{p}: size {tuple(tex[k].shape[:2])} (h, w) but the sidecar says {height}x{width}")
    out = {}
    for name, rect in rects.items():
        maps = A.decode_schuler(A.extract(tex["tex1"], rect), A.extract(tex["tex2"], rect), transfer)
        if "absorption" in tex:
            maps["absorption"] = A.extract(tex["absorption"], rect).clone()
            c = A.extract(tex["coat"], rect)
            maps["coat_ior"], maps["coat_roughness"] = c[..., 0:1].clone(), c[..., 1:2].clone()
        out[name] = maps
    return out


# --------------------------------------------------------------------------------------------
# glTF 2.0 binary


_GLTF_DOC = {
    "model": "glTF 2.0 pbrMetallicRoughness (metallic 0) + KHR_materials_specular + KHR_materials_ior (1.5)",
    "baseColorTexture": "RGB = albedo, sRGB (glTF mandates sRGB); A = mask, linear",
    "metallicRoughnessTexture": "R = 0 (unused), G = roughness r (linear, perceptual; glTF alpha = r^2 like ours), "
                                "B = metallic = 0",
    "specularColorTexture": "RGB = f0 / 1, sRGB; specularColorFactor 25 so that f0 = 0.04 * 25 * texture",
}


def _png_bytes(img: Tensor, transfer: str) -> bytes:
    fd, tmp = tempfile.mkstemp(suffix=".png")
    os.close(fd)
    try:
        imageio.write_png(tmp, img, bits=8, transfer=transfer)
        return Path(tmp).read_bytes()
    finally:
        os.unlink(tmp)


def write_glb(path, meshes: Sequence[Mesh], maps: Mapping[str, Tensor]) -> None:
    """Write ``meshes`` (UVs already in atlas space) as one GLB with one material over the atlas ``maps``.

    Channel colour spaces (glTF 2.0 §3.9 and the extensions' specs): baseColor RGB sRGB + alpha linear
    (mask; ``alphaMode`` MASK when some mask < 1); metallicRoughness linear (G = roughness, B = metallic = 0);
    KHR_materials_specular ``specularColorTexture`` RGB sRGB holding f0 with ``specularColorFactor`` 25 and
    KHR_materials_ior 1.5, so F0 = 0.04 · 25 · f0 = f0 (the spec clamps it to 1). The specular scalar is 1.
    glTF's UV origin is the top-left, so ``v_gltf = 1 − v``. Written atomically.
    """
    path = Path(path)
    if not meshes:
        raise ExportError(f"{path}: no meshes to write")
    albedo, f0, rough, mask = maps["albedo"], maps["f0"], maps["roughness"], maps["mask"]
    images = [
        _png_bytes(torch.cat([albedo, mask], -1), "srgb"),
        _png_bytes(torch.cat([torch.zeros_like(rough), rough, torch.zeros_like(rough)], -1), "linear"),
        _png_bytes(f0, "srgb"),
    ]
    blob = bytearray()
    views, accessors = [], []

    def add_view(data: bytes, target: int | None = None) -> int:
        while len(blob) % 4:
            blob.append(0)
        view = {"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        blob.extend(data)
        views.append(view)
        return len(views) - 1

    def add_accessor(arr: np.ndarray, kind: str, ctype: int, target: int, minmax: bool = False) -> int:
        acc = {"bufferView": add_view(arr.tobytes(), target), "componentType": ctype, "count": int(arr.shape[0]),
               "type": kind}
        if minmax:
            acc["min"] = arr.min(0).tolist()
            acc["max"] = arr.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    gl_meshes, nodes = [], []
    for k, m in enumerate(meshes):
        v = m.vertices.detach().cpu().numpy().astype(np.float32)
        n = m.normals.detach().cpu().numpy().astype(np.float32)
        uv = m.uvs.detach().cpu().numpy().astype(np.float32).copy()
        uv[:, 1] = 1.0 - uv[:, 1]
        idx = m.faces.cpu().numpy().astype(np.uint32).reshape(-1)
        attrs = {"POSITION": add_accessor(v, "VEC3", 5126, 34962, True),
                 "NORMAL": add_accessor(n, "VEC3", 5126, 34962),
                 "TEXCOORD_0": add_accessor(uv, "VEC2", 5126, 34962)}
        ind = add_accessor(idx[:, None], "SCALAR", 5125, 34963)
        gl_meshes.append({"name": m.name or f"mesh{k}", "primitives": [{"attributes": attrs, "indices": ind,
                                                                         "material": 0, "mode": 4}]})
        nodes.append({"name": m.name or f"mesh{k}", "mesh": k})
    image_ids = [add_view(b) for b in images]
    alpha_mode = "MASK" if bool((mask < 1).any()) else "OPAQUE"
    material = {
        "name": "schuler_atlas",
        "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
                                 "metallicFactor": 0.0, "roughnessFactor": 1.0},
        "alphaMode": alpha_mode,
        "extensions": {"KHR_materials_specular": {"specularColorTexture": {"index": 2},
                                                  "specularColorFactor": [_SPEC_FACTOR] * 3, "specularFactor": 1.0},
                       "KHR_materials_ior": {"ior": 1.5}},
    }
    if alpha_mode == "MASK":
        material["alphaCutoff"] = 0.5
    gltf = {
        "asset": {"version": "2.0", "generator": "shadecap capture.export"},
        "extensionsUsed": ["KHR_materials_specular", "KHR_materials_ior"],
        "scene": 0, "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes, "meshes": gl_meshes,
        "materials": [material],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"bufferView": i, "mimeType": "image/png"} for i in image_ids],
        "textures": [{"source": i, "sampler": 0} for i in range(len(image_ids))],
        "accessors": accessors, "bufferViews": views,
    }
    while len(blob) % 4:
        blob.append(0)
    gltf["buffers"] = [{"byteLength": len(blob)}]
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    data = (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob))
    imageio.atomic_write_bytes(path, data)
