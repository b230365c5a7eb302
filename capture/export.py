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
- ``atlas.glb`` — the meshes, rotated to glTF's Y-up, with one glTF 2.0 metallic-roughness material over
  the atlas (see :func:`write_glb`, :func:`to_metallic_roughness`);
- ``textures/`` — the atlas's canonical maps as linear EXR and the engines' texture sets as PNG (glTF
  metallic-roughness, Unreal ORM, Unity HDRP mask map; see :func:`write_texture_sets`);
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
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from materials import atlas as A
from materials.microfacet import smith_g1_ggx, smith_g2_correlated_ggx
from materials.params import CANONICAL, preview_transfer
from materials.roughness import roughness_to_alpha
from renderer import imageio
from renderer.mesh import Mesh, MeshError, load_mesh, save_mesh

from .outputs import atomic_folder, check_output, json_text

__all__ = [
    "ATLAS_FORMAT", "COMPENSATIONS", "DEFAULT_COMPENSATION", "MATERIAL_MODELS", "TEXTURE_SETS", "ExportError",
    "ExportWarning", "Material",
    "export_atlas", "export_atlas_dirs", "from_metallic_roughness", "gltf_textures",
    "load_reconstruction", "multiscatter_factor", "read_atlas", "read_glb", "specular_albedo", "tag_png",
    "to_metallic_roughness", "write_glb", "write_maps", "write_texture_sets", "yup_to_zup", "zup_to_yup",
]

#: Version of the atlas folder format (``atlas.json`` → ``format``).
ATLAS_FORMAT = "shadecap-schuler-atlas/1"
#: Canonical maps of a reconstruction folder and their channel counts (the per-texel parameters the ParamSpecs
#: export, and the coverage).
MAP_CHANNELS = {**{p.name: p.channels for p in CANONICAL.values() if p.export and not p.shared}, "coverage": 1}
REQUIRED = ("albedo",)
#: Values of maps a diffuse-only model (e.g. Lambert) does not have: no specular reflection.
DIFFUSE_ONLY_DEFAULTS = {p.name: p.diffuse_only for p in CANONICAL.values() if p.diffuse_only is not None}
#: F0 of glTF's dielectric (ior 1.5): ((1.5 − 1)/(1.5 + 1))².
GLTF_DIELECTRIC_F0 = 0.04
#: What the GLB's textures compensate of a viewer's BRDF (docs/export.md, "Compensation"): nothing, the diffuse
#: layered under the dielectric specular, or that and the multiple scattering of the metals' GGX lobe.
COMPENSATIONS = ("none", "layering", "layering+multiscatter")
#: The default of :data:`COMPENSATIONS`: current viewers dim the diffuse under the dielectric layer (glTF's own BRDF,
#: Blender ≥ 4) and give back the energy a rough GGX lobe loses to single scattering (Blender ≥ 4's Multiscatter
#: GGX, three.js's ``BRDF_GGX_Multiscatter``, Filament's energy compensation). The demo's GLB in the Cycles of
#: Blender 4.2 and 5.0.1, 16 views, mean PSNR on object pixels: 44.5 dB with ``layering``, 45.8 dB with this
#: (docs/export.md).
DEFAULT_COMPENSATION = "layering+multiscatter"
#: GLB material models: glTF's metallic-roughness (metals as metallic = 1) or the metallic = 0 + specular form.
MATERIAL_MODELS = ("metallic-roughness", "specular")
#: Engine texture sets written into ``textures/`` (see docs/export.md).
TEXTURE_SETS = ("gltf", "unreal", "unity-hdrp")
_RANGES = {**{p.name: (p.low, p.high) for p in CANONICAL.values() if p.export and not p.shared},
           "coverage": (0.0, 1.0)}


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

    EXRs carry the Rec. 709 / D65 ``chromaticities`` attribute. Previews: colour maps (albedo, f0)
    sRGB-encoded with an sRGB chunk; scalar maps and absorption (divided by its maximum when above 1)
    written linearly with gAMA 1.0 (:func:`tag_png`). The folder is created if missing. Returns the paths.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for k, v in maps.items():
        x = _to_hwc(v, k, f"write_maps({out})")
        imageio.write_exr(out / f"{k}.exr", x, half=half, chromaticities="rec709")
        written.append(out / f"{k}.exr")
        if previews:
            transfer = preview_transfer(k)
            if k == "absorption" and x.max() > 1:
                x = x / x.max()
            _write_png(out / f"{k}.png", x, transfer=transfer)
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


class _AtlasOptions(NamedTuple):
    """The validated encoding options of :func:`export_atlas`."""

    fmt: str
    bits: int
    transfer: str
    gutter: int
    material_model: str
    compensation: str
    texture_sets: tuple[str, ...]


class _Encoded(NamedTuple):
    """Each material's texels, before packing: Schüler's tex1|tex2, the linear maps, coverage, coat."""

    tex: list[Tensor]  # [h, w, 8]: tex1 RGBA | tex2 RGBA
    lin: list[Tensor]  # [h, w, 8]: albedo, f0, roughness, mask
    coverage: list[Tensor | None]
    coat: list[Tensor]  # [h, w, 5]: absorption, coat ior, coat roughness; empty when no material has a coat
    any_coat: bool


class _Composed(NamedTuple):
    """The packed atlas: rectangles, Schüler texels, linear canonical maps and coat texels (or None)."""

    packing: A.Packing
    texels: Tensor
    lin_maps: dict[str, Tensor]
    coat: Tensor | None


def _atlas_options(fmt, bits, transfer, gutter, material_model, compensation, texture_sets) -> _AtlasOptions:
    if fmt not in ("png", "exr"):
        raise ExportError(f"fmt must be 'png' or 'exr', got {fmt!r}")
    if bits not in (8, 16):
        raise ExportError(f"bits must be 8 or 16, got {bits!r}")
    if transfer not in ("gamma2.2", "srgb"):
        raise ExportError(f"transfer must be 'gamma2.2' (Schüler) or 'srgb', got {transfer!r}")
    if material_model not in MATERIAL_MODELS:
        raise ExportError(f"material_model must be one of {list(MATERIAL_MODELS)}, got {material_model!r}")
    _check_compensation(compensation)
    if isinstance(texture_sets, str):
        texture_sets = [texture_sets]
    texture_sets = tuple(texture_sets or ())
    unknown = [t for t in texture_sets if t not in TEXTURE_SETS]
    if unknown:
        raise ExportError(f"unknown texture set(s) {unknown}; choose from {list(TEXTURE_SETS)}")
    return _AtlasOptions(fmt, bits, transfer, gutter, material_model, compensation, texture_sets)


def _has_coat(m: Material, p: Mapping[str, Tensor]) -> bool:
    return "absorption" in p or m.coat_ior is not None


def _coat_texels(m: Material, p: Mapping[str, Tensor], h: int, w: int) -> Tensor:
    """``[h, w, 5]``: absorption, coat ior, coat roughness; a material without a coat gets 0, 1, 0."""
    absorption = p.get("absorption", torch.zeros(h, w, 3))
    has_coat = _has_coat(m, p)
    ior = m.coat_ior if m.coat_ior is not None else (1.5 if has_coat else 1.0)
    rough = m.coat_roughness if m.coat_roughness is not None else (0.1 if has_coat else 0.0)
    if not 1.0 <= ior <= 3.0 or not 0.0 <= rough <= 1.0:
        raise ExportError(f"material '{m.name}': coat_ior {ior} must lie in [1, 3] and coat_roughness "
                          f"{rough} in [0, 1]")
    return torch.cat([absorption, torch.full((h, w, 1), ior), torch.full((h, w, 1), rough)], -1)


def _encode_materials(mats: Sequence[Material], prepared: Sequence[dict[str, Tensor]], transfer: str) -> _Encoded:
    """Encode each material for the atlas; the encoder's warnings are re-issued with the material's name."""
    tex, lin, coverage, coat = [], [], [], []
    any_coat = any(_has_coat(m, p) for m, p in zip(mats, prepared, strict=True))
    for m, p in zip(mats, prepared, strict=True):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t1, t2 = A.encode_schuler(p, transfer)
        for w in caught:  # stacklevel 3: attributed to export_atlas's caller
            warnings.warn(f"material '{m.name}': {w.message}", ExportWarning, stacklevel=3)
        tex.append(torch.cat([t1, t2], dim=-1))
        mask = p.get("mask", torch.ones_like(p["roughness"]))
        lin.append(torch.cat([p["albedo"], p["f0"], p["roughness"], mask], dim=-1))
        cov = p.get("coverage")
        if cov is None and "mask" in p:
            cov = p["mask"]
        coverage.append(None if cov is None else cov[..., 0] > 0)
        if any_coat:
            h, w = t1.shape[:2]
            coat.append(_coat_texels(m, p, h, w))
    return _Encoded(tex, lin, coverage, coat, any_coat)


def _compose_atlas(out: Path, enc: _Encoded, atlas_size, gutter: int) -> _Composed:
    """Pack the materials' rectangles and compose the Schüler, linear and coat atlases."""
    sizes = [(t.shape[1], t.shape[0]) for t in enc.tex]
    try:
        packing = A.pack_rectangles(sizes, atlas_size, gutter)
    except A.AtlasError as err:
        raise ExportError(f"{out}: {err}") from err
    atlas = A.compose(enc.tex, packing, gutter, enc.coverage)
    lin_atlas = A.compose(enc.lin, packing, gutter, enc.coverage)
    lin_maps = {"albedo": lin_atlas[..., 0:3], "f0": lin_atlas[..., 3:6], "roughness": lin_atlas[..., 6:7],
                "mask": lin_atlas[..., 7:8]}
    coat_atlas = A.compose(enc.coat, packing, gutter, enc.coverage) if enc.any_coat else None
    return _Composed(packing, atlas, lin_maps, coat_atlas)


def _atlas_sidecar(mats: Sequence[Material], packing: A.Packing, opts: _AtlasOptions, any_coat: bool) -> dict:
    """``atlas.json`` without the entries of what is written later (texture sets, glTF)."""
    fmt, transfer = opts.fmt, opts.transfer
    width, height = packing.size
    sidecar = {
        "format": ATLAS_FORMAT,
        "layout": "schuler-2rgba",
        "size": {"width": width, "height": height},
        "gutter": opts.gutter,
        "transfer": transfer,
        "storage": {"format": fmt, "bits": opts.bits if fmt == "png" else 32},
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
    return sidecar


def _all_have_meshes(mats: Sequence[Material]) -> bool:
    """Whether a GLB can be written; warns when only some materials lack a mesh."""
    without = [m.name for m in mats if m.mesh is None]
    if without and len(without) < len(mats):  # all without a mesh: nothing to put in a GLB, silently
        warnings.warn(f"no atlas.glb: material(s) {without} have no mesh", ExportWarning, stacklevel=3)
    return not without


def _write_atlas_images(tmp: Path, composed: _Composed, opts: _AtlasOptions) -> None:
    """tex1/tex2 in ``opts.fmt``, and absorption.exr/coat.exr when some material has a coat."""
    atlas = composed.texels
    for k, t in (("tex1", atlas[..., :4]), ("tex2", atlas[..., 4:])):
        if opts.fmt == "png":  # values already encoded by `transfer`: written as is, tagged with it
            _write_png(tmp / f"{k}.png", t, bits=opts.bits, transfer="linear", intent=opts.transfer)
        else:
            imageio.write_exr(tmp / f"{k}.exr", t)
    coat_atlas = composed.coat
    if coat_atlas is not None:
        imageio.write_exr(tmp / "absorption.exr", coat_atlas[..., :3], chromaticities="rec709")
        zero = torch.zeros_like(coat_atlas[..., :1])
        imageio.write_exr(tmp / "coat.exr", torch.cat([coat_atlas[..., 3:5], zero], -1))


def _write_atlas_meshes(tmp: Path, mats: Sequence[Material], packing: A.Packing) -> list[Mesh]:
    """Each material's mesh with its UVs moved into its rectangle, as ``meshes/<name>.obj``; returns them."""
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
    return meshes


def export_atlas(
    materials, out, *, atlas_size: int | tuple[int, int] | None = None, gutter: int = 4, bits: int = 8,
    fmt: str = "png", transfer: str = "gamma2.2", force: bool = False, glb: bool = True,
    material_model: str = "metallic-roughness", texture_sets: Sequence[str] | None = TEXTURE_SETS,
    compensation: str = DEFAULT_COMPENSATION,
) -> dict:
    """Pack one or many materials into Schüler's two-RGBA atlas and write the atlas folder ``out``.

    Args:
        materials: a :class:`Material`, a reconstruction folder, a list of either, or ``{name: maps}``.
        out: the atlas folder to create (refused if it exists, unless ``force``).
        atlas_size: None (the tight size, sides multiples of 4: one 256² material gives 256²), ``"pow2"``
            (smallest power-of-two square), an int (square) or (width, height); see
            :func:`materials.atlas.pack_rectangles`.
        gutter: texels between materials, filled by dilation (mip levels up to log2(gutter) stay clean);
            none at the atlas border (sampled clamp-to-edge).
        bits: 8 or 16 for every PNG (atlas, GLB textures, texture sets).
        fmt: ``"png"`` or ``"exr"`` (float EXR of the same encoded values) for tex1/tex2.
        transfer: colour encoding of the RGB channels, ``"gamma2.2"`` (Schüler) or ``"srgb"``.
        force: replace an existing ``out``. glb: also write ``atlas.glb`` (needs every material to have a mesh).
        material_model: the GLB's material, ``"metallic-roughness"`` (default; :func:`to_metallic_roughness`)
            or ``"specular"`` (metallic 0, f0 in KHR_materials_specular).
        texture_sets: engine texture sets written into ``textures/`` with the linear EXR maps
            (:func:`write_texture_sets`); None or ``()`` writes no ``textures/`` folder.
        compensation: what the GLB's (and the ``gltf`` set's) textures compensate of the viewer's BRDF,
            one of :data:`COMPENSATIONS` (:func:`gltf_textures`; docs/export.md, "Compensation").

    Returns:
        The sidecar dict written to ``out/atlas.json``.

    Raises:
        ExportError: bad inputs, ``out`` exists, atlas too small (with the size needed), unwritable output.
    """
    out = Path(out)
    opts = _atlas_options(fmt, bits, transfer, gutter, material_model, compensation, texture_sets)
    check_output(out, _input_folders(materials), force=force, error=ExportError, force_flag="force=True (--force)")
    mats = _materials(materials)
    enc = _encode_materials(mats, [_prepare(m) for m in mats], transfer)
    composed = _compose_atlas(out, enc, atlas_size, gutter)
    sidecar = _atlas_sidecar(mats, composed.packing, opts, enc.any_coat)
    glb = glb and _all_have_meshes(mats)
    lin_maps = composed.lin_maps
    gl_tex = gltf_textures(lin_maps, material_model, bits, compensation) if glb or opts.texture_sets else None
    set_tex = gl_tex if material_model == "metallic-roughness" else None

    # -- write everything into a temp folder, then rename into place
    with atomic_folder(out, force=force, error=ExportError, force_flag="force=True (--force)") as tmp:
        _write_atlas_images(tmp, composed, opts)
        if opts.texture_sets:
            written = write_texture_sets(tmp / "textures", lin_maps, opts.texture_sets, bits, set_tex, compensation)
            sidecar["texture_sets"] = {"folder": "textures", "files": written, "bits": bits,
                                       "layout": "same UVs as the atlas (docs/export.md, texture sets)"}
        meshes = _write_atlas_meshes(tmp, mats, composed.packing)
        if glb:
            sidecar["gltf"] = write_glb(tmp / "atlas.glb", meshes, lin_maps, material_model=material_model,
                                        bits=bits, textures=gl_tex, compensation=compensation)
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
# glTF metallic-roughness mapping


#: An F0 error of the core mapping above this (half an 8-bit code) makes the GLB carry KHR_materials_specular.
SPECULAR_TOLERANCE = 0.5 / 255
_CHUNK = 1 << 15


def _rgb01(x, name: str) -> Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(x)
    if not isinstance(x, Tensor) or x.dim() < 1 or x.shape[-1] != 3:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ExportError(f"{name} must be a tensor [..., 3] (linear RGB), got {shape}")
    if not x.is_floating_point():
        raise ExportError(f"{name} must be floating point, got {x.dtype}")
    bad = ~torch.isfinite(x)
    if bad.any():
        raise ExportError(f"{name} has {int(bad.sum())} NaN/inf value(s)")
    out = (x < 0) | (x > 1)
    if out.any():
        raise ExportError(f"{name} has {int(out.sum())} value(s) outside [0, 1] (range {x.min().item():.4g}.."
                          f"{x.max().item():.4g}); clamp the map first")
    return x


def _best_base(a: Tensor, f: Tensor, m: Tensor) -> tuple[Tensor, Tensor]:
    """For metallic ``m [N, K]``: the least-squares base colour ``[N, K, 3]`` (clamped, exact: the cost is a
    separable convex quadratic in each channel) and the cost ``[N, K]``."""
    m3, k = m[..., None], (1.0 - m[..., None])
    a, f = a[:, None], f[:, None]
    b = ((k * a + m3 * (f - GLTF_DIELECTRIC_F0 * k)) / (k * k + m3 * m3)).clamp(0.0, 1.0)
    cost = ((k * b - a) ** 2 + (GLTF_DIELECTRIC_F0 * k + m3 * b - f) ** 2).sum(-1)
    return b, cost


def _metallic(a: Tensor, f: Tensor) -> Tensor:
    """Per-texel metallic ``[N]`` minimising the core cost: exact dielectrics (cost 0 at m = 0) and exact
    metals (cost 0 at m = 1) directly, the others by a 17-point grid and four 9-point zooms (step 1/16384)."""
    m = torch.zeros(a.shape[0], dtype=a.dtype)
    ends = torch.tensor([0.0, 1.0], dtype=a.dtype).expand(a.shape[0], 2)
    _, cost = _best_base(a, f, ends)
    exact0, exact1 = cost[:, 0] <= 1e-12, cost[:, 1] <= 1e-12
    m[~exact0 & exact1] = 1.0
    rest = ~(exact0 | exact1)
    if not rest.any():
        return m
    a, f = a[rest], f[rest]
    grid = torch.linspace(0.0, 1.0, 17, dtype=a.dtype)
    _, cost = _best_base(a, f, grid.expand(a.shape[0], -1))
    best = grid[cost.argmin(-1)]  # ties: the smallest metallic (first minimum)
    step = 1.0 / 16
    offsets = torch.linspace(-1.0, 1.0, 9, dtype=a.dtype)
    for _ in range(4):
        cand = (best[:, None] + step * offsets).clamp(0.0, 1.0)
        _, cost = _best_base(a, f, cand)
        best = cand.gather(1, cost.argmin(-1, keepdim=True))[:, 0]
        step /= 4
    m[rest] = best
    return m


def to_metallic_roughness(albedo: Tensor, f0: Tensor, levels: int | None = 255) -> dict[str, Tensor]:
    """Our (albedo, f0) → glTF metallic-roughness (base colour, metallic) plus the dielectric F0 of
    KHR_materials_specular, per texel.

    glTF 2.0 (Appendix B) defines, for base colour b and metallic m: diffuse colour c_diff = (1 − m)·b and
    F0 = mix(0.04, b, m) = 0.04·(1 − m) + m·b; with KHR_materials_specular the 0.04 becomes the dielectric
    F0 t = min(0.04 · specularColorFactor · specularColorTexture, 1). Two steps:

    1. core: (b, m) minimise |(1 − m) b − albedo|² + |0.04 (1 − m) + m b − f0|² over b ∈ [0, 1]³,
       m ∈ [0, 1] — exact for dielectrics with f0 = 0.04 (m = 0, b = albedo) and for metals with albedo 0
       (m = 1, b = f0); the best blend in between. For a fixed m the best b is closed-form per channel;
       m is found by a grid search and four zooms (resolution 1/16384), then rounded to ``levels``
       (the code of the texture that stores it; None: not rounded) and b re-solved for the stored m.
    2. extension: t = clamp((f0 − m b)/(1 − m), 0, 1) makes F0 exact wherever the core left an error
       (t = 0.04 where m = 1).

    Args:
        albedo, f0: ``[..., 3]`` linear, in [0, 1]. levels: quantisation of metallic, e.g. 255 or 65535.

    Returns:
        ``base_color [..., 3]``, ``metallic [..., 1]``, ``specular_f0 [..., 3]`` (t), and the errors of what a
        viewer reads back (:func:`from_metallic_roughness`): ``diffuse_error``, ``f0_error_core`` (without the
        extension), ``f0_error`` (with it), each ``[..., 3]`` signed (read back − ours).

    Raises:
        ExportError: shapes that differ or are not ``[..., 3]``, NaN/inf, values outside [0, 1], bad ``levels``.
    """
    albedo, f0 = _rgb01(albedo, "albedo"), _rgb01(f0, "f0")
    if albedo.shape != f0.shape:
        raise ExportError(f"albedo {tuple(albedo.shape)} and f0 {tuple(f0.shape)} must have the same shape")
    if levels is not None and (not isinstance(levels, int) or isinstance(levels, bool) or levels < 1):
        raise ExportError(f"levels must be a positive integer (255 for 8 bits) or None, got {levels!r}")
    shape, dtype = albedo.shape, albedo.dtype
    work = torch.float64 if dtype == torch.float64 else torch.float32
    a = albedo.reshape(-1, 3).to(work)
    f = f0.reshape(-1, 3).to(work)
    m = torch.cat([_metallic(a[i: i + _CHUNK], f[i: i + _CHUNK]) for i in range(0, a.shape[0], _CHUNK)]) \
        if a.shape[0] else a.new_zeros(0)
    if levels is not None:
        m = torch.round(m * levels) / levels
    b, _ = _best_base(a, f, m[:, None])
    b, m = b[:, 0], m[:, None]
    k = 1.0 - m
    t = torch.where(k > 1e-9, (f - m * b) / k.clamp_min(1e-9), torch.full_like(f, GLTF_DIELECTRIC_F0)).clamp(0.0, 1.0)
    core = from_metallic_roughness(b, m)
    ext = from_metallic_roughness(b, m, t)
    out = {"base_color": b, "metallic": m, "specular_f0": t, "diffuse_error": core["albedo"] - a,
           "f0_error_core": core["f0"] - f, "f0_error": ext["f0"] - f}
    return {key: v.reshape(*shape[:-1], v.shape[-1]).to(dtype) for key, v in out.items()}


def from_metallic_roughness(base_color: Tensor, metallic: Tensor, specular_f0: Tensor | None = None
                            ) -> dict[str, Tensor]:
    """glTF metallic-roughness → our (albedo, f0), by glTF 2.0's definitions (Appendix B):
    albedo = (1 − m)·b, f0 = (1 − m)·t + m·b with t = ``specular_f0`` (KHR_materials_specular's dielectric
    F0) or 0.04 without the extension.

    Args:
        base_color: ``[..., 3]`` linear in [0, 1]. metallic: ``[..., 1]`` (or ``[...]``) in [0, 1].
        specular_f0: None or ``[..., 3]`` in [0, 1].

    Raises:
        ExportError: bad shapes, NaN/inf, values outside [0, 1].
    """
    b = _rgb01(base_color, "base_color")
    if isinstance(metallic, Tensor) and metallic.dim() == b.dim() - 1:
        metallic = metallic[..., None]
    if not isinstance(metallic, Tensor) or metallic.shape != (*b.shape[:-1], 1):
        shape = tuple(metallic.shape) if isinstance(metallic, Tensor) else type(metallic).__name__
        raise ExportError(f"metallic must be a tensor [..., 1] matching base_color {tuple(b.shape)}, got {shape}")
    m = _rgb01(metallic.expand(b.shape), "metallic")[..., :1]
    t = torch.full_like(b, GLTF_DIELECTRIC_F0) if specular_f0 is None else _rgb01(specular_f0, "specular_f0")
    if t.shape != b.shape:
        raise ExportError(f"specular_f0 {tuple(t.shape)} must match base_color {tuple(b.shape)}")
    return {"albedo": (1.0 - m) * b, "f0": (1.0 - m) * t + m * b}


# --------------------------------------------------------------------------------------------
# What a viewer adds to glTF's BRDF: diffuse layering, multiple scattering (docs/export.md, "Compensation")

#: Roughness nodes of the albedo tables, r = k/32: linear interpolation is within 0.0032 (Ā₁) and 1e-4 (Ā₅) of the
#: integral at the midpoints (measured against a table at r = k/64).
_TABLE_NODES = 33
#: Visible normals per viewing angle (a 64 × 64 midpoint grid) and Gauss-Legendre nodes in μ_o: within 0.0033 (Ā₁)
#: and 1e-4 (Ā₅) of a 512² grid with 64 nodes (measured; 1 s against 450 s).
_VNDF_GRID = 64
_MU_NODES = 32


@lru_cache(maxsize=1)
def _albedo_tables() -> tuple[Tensor, Tensor]:
    """Ā₁(r), Ā₅(r) at the nodes r = k/32: cosine-weighted hemispherical averages 2∫E(μ)μ dμ of the directional
    albedo E(μ_o) = ∫ f μ_i dω_i of ggx-lambert's specular lobe (GGX D, Smith height-correlated G2) with the
    Fresnel factor replaced by 1 (Ā₁) and by (1 − v·h)⁵ (Ā₅), so that Schlick's F gives f0 (Ā₁ − Ā₅) + Ā₅.

    Visible-normal sampling (Heitz 2018, "Sampling the GGX Distribution of Visible Normals") makes E(μ_o) the
    mean of G2(l, v)/G1(v) · F over the visible normals; they are taken on a midpoint grid, μ_o on Gauss-Legendre
    nodes. Deterministic, about 1 s once per process."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small tensors: 1.1 s on one thread, 9.5 s on two threads of a loaded 2-core CPU
    try:
        return _integrate_albedo_tables()
    finally:
        torch.set_num_threads(threads)


def _integrate_albedo_tables() -> tuple[Tensor, Tensor]:
    x, w = np.polynomial.legendre.leggauss(_MU_NODES)
    mu = torch.from_numpy(0.5 * (x + 1.0))[:, None]  # [M, 1]
    weight = torch.from_numpy(w)[:, None] * mu  # 2 ∫₀¹ E μ dμ = Σ w_k μ_k E(μ_k) on [−1, 1] mapped to [0, 1]
    u = (torch.arange(_VNDF_GRID, dtype=torch.float64) + 0.5) / _VNDF_GRID
    u1, u2 = (g.reshape(1, -1) for g in torch.meshgrid(u, u, indexing="ij"))
    t1, t2 = u1.sqrt() * torch.cos(2 * math.pi * u2), u1.sqrt() * torch.sin(2 * math.pi * u2)  # [1, S]
    sin_o = (1.0 - mu * mu).sqrt()
    v = torch.stack([sin_o.expand(-1, t1.shape[1]), torch.zeros_like(t1).expand(mu.shape[0], -1),
                     mu.expand(-1, t1.shape[1])], -1)  # [M, S, 3], azimuth 0
    a1, a5 = [], []
    for r in torch.linspace(0.0, 1.0, _TABLE_NODES, dtype=torch.float64):
        alpha = roughness_to_alpha(r).item()
        # the view stretched to α = 1, in the x-z plane: frame T1 = y, T2 = vs × T1
        vs = torch.cat([alpha * sin_o, mu], -1)
        vs = vs / vs.norm(dim=-1, keepdim=True)  # [M, 2] = (x, z)
        sx, sz = vs[:, :1], vs[:, 1:]
        blend = 0.5 * (1.0 + sz)
        t2b = (1.0 - blend) * (1.0 - t1 * t1).sqrt() + blend * t2
        up = (1.0 - t1 * t1 - t2b * t2b).clamp_min(0.0).sqrt()
        nx, ny, nz = -t2b * sz + up * sx, t1.expand_as(t2b), t2b * sx + up * sz
        h = torch.stack([alpha * nx, alpha * ny, nz.clamp_min(0.0)], -1)
        h = h / h.norm(dim=-1, keepdim=True)
        vh = (v * h).sum(-1, keepdim=True)
        mu_i = (2.0 * vh * h[..., 2:] - v[..., 2:])  # n·l of the mirrored view
        ratio = smith_g2_correlated_ggx(mu_i, mu[:, :, None].expand_as(mu_i), alpha) \
            / smith_g1_ggx(mu[:, :, None].expand_as(mu_i), alpha)
        ratio = torch.where(mu_i > 0, ratio, torch.zeros_like(ratio))[..., 0]
        e1, e5 = ratio.mean(-1), (ratio * (1.0 - vh[..., 0]).clamp(0.0, 1.0) ** 5).mean(-1)
        a1.append((weight[:, 0] * e1).sum())
        a5.append((weight[:, 0] * e5).sum())
    return torch.stack(a1), torch.stack(a5)


def _interp(table: Tensor, roughness: Tensor) -> Tensor:
    x = roughness.to(torch.float64).clamp(0.0, 1.0) * (_TABLE_NODES - 1)
    i = x.floor().clamp(0, _TABLE_NODES - 2).long()
    t = x - i
    return table[i] * (1.0 - t) + table[i + 1] * t


def _roughness_f0(roughness, f0, fn: str) -> tuple[Tensor, Tensor]:
    r = torch.as_tensor(roughness, dtype=torch.float64)
    f = torch.as_tensor(f0, dtype=torch.float64)
    for name, x in (("roughness", r), ("f0", f)):
        if not torch.isfinite(x).all() or (x < 0).any() or (x > 1).any():
            raise ExportError(f"{fn}: {name} must be finite and in [0, 1]")
    try:
        torch.broadcast_shapes(r.shape, f.shape)
    except RuntimeError:
        raise ExportError(f"{fn}: roughness {tuple(r.shape)} and f0 {tuple(f.shape)} do not broadcast") from None
    return r, f


def specular_albedo(roughness, f0) -> Tensor:
    """Ē(r, f0): the cosine-weighted hemispherical average of the directional albedo of ggx-lambert's specular
    lobe (single scattering: GGX, Smith height-correlated, Schlick F with ``f0``) at perceptual roughness r —
    the share of light, arriving evenly, that the lobe reflects. f0 (Ā₁(r) − Ā₅(r)) + Ā₅(r) from tables at
    r = k/32 (:func:`_albedo_tables`), linear in r between them.

    ``roughness`` and ``f0`` broadcast (e.g. ``[..., 1]`` and ``[..., 3]``); float64 result of their shape.
    E.g. f0 = 0.04: 0.086 at r = 0, 0.053 at r = 0.5, 0.019 at r = 1.
    """
    r, f = _roughness_f0(roughness, f0, "specular_albedo")
    a1, a5 = _albedo_tables()
    return f * (_interp(a1, r) - _interp(a5, r)) + _interp(a5, r)


def multiscatter_factor(roughness, f0) -> Tensor:
    """s(r, f0) ≥ 1: how much a GGX lobe with multiple scattering reflects over the single-scattering lobe of
    ggx-lambert, averaged over the hemisphere — Kulla & Conty 2017 ("Revisiting Physically Based Shading at
    Imageworks"): the energy 1 − Ā₁ lost by single scattering comes back weighted by
    F_ms = F̄² Ā₁ / (1 − F̄ (1 − Ā₁)), F̄ = f0 + (1 − f0)/21 (Schlick's cosine-weighted average), so
    s = 1 + F_ms (1 − Ā₁) / Ē(r, f0). 1/Ā₁ for f0 = 1; 1 at r = 0. Shapes as :func:`specular_albedo`.
    """
    r, f = _roughness_f0(roughness, f0, "multiscatter_factor")
    a1, _ = _albedo_tables()
    e1 = _interp(a1, r)
    f_avg = f + (1.0 - f) / 21.0
    f_ms = f_avg * f_avg * e1 / (1.0 - f_avg * (1.0 - e1))
    return 1.0 + f_ms * (1.0 - e1) / specular_albedo(r, f)


def _layered(albedo: Tensor, roughness: Tensor, dielectric_f0) -> tuple[Tensor, Tensor]:
    """albedo / (1 − Ē(r, F0 of the dielectric layer)), clamped to 1; returns it and the factor ``[..., 1]``."""
    factor = 1.0 / (1.0 - specular_albedo(roughness, dielectric_f0))
    return (albedo.to(torch.float64) * factor).clamp(max=1.0).to(albedo.dtype), factor


def zup_to_yup(x) -> Tensor:
    """The dataset's Z-up world → glTF's Y-up: a rotation of −90° about X, (x, y, z) → (x, z, −y).

    Applies to positions and normals alike (a rotation: lengths and winding are kept). ``x``: ``[..., 3]``.
    """
    x = torch.as_tensor(x)
    if x.dim() < 1 or x.shape[-1] != 3:
        raise ExportError(f"zup_to_yup needs points [..., 3], got {tuple(x.shape)}")
    return torch.stack([x[..., 0], x[..., 2], -x[..., 1]], dim=-1)


def yup_to_zup(x) -> Tensor:
    """Inverse of :func:`zup_to_yup`: (x, y, z) → (x, −z, y) (what glTF importers such as Blender's apply)."""
    x = torch.as_tensor(x)
    if x.dim() < 1 or x.shape[-1] != 3:
        raise ExportError(f"yup_to_zup needs points [..., 3], got {tuple(x.shape)}")
    return torch.stack([x[..., 0], -x[..., 2], x[..., 1]], dim=-1)


# --------------------------------------------------------------------------------------------
# PNG with colour intent


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


#: cHRM of Rec. 709 / sRGB (white D65, red, green, blue; CIE xy × 100000).
_CHRM = struct.pack(">8I", 31270, 32900, 64000, 33000, 30000, 60000, 15000, 6000)
_INTENT_CHUNKS = {
    # sRGB (rendering intent 0, perceptual) with the gAMA and cHRM the PNG spec asks writers to add
    "srgb": _chunk(b"sRGB", b"\x00") + _chunk(b"gAMA", struct.pack(">I", 45455)) + _chunk(b"cHRM", _CHRM),
    "gamma2.2": _chunk(b"gAMA", struct.pack(">I", 45455)) + _chunk(b"cHRM", _CHRM),  # Schüler's 1/2.2 encoding
    "linear": _chunk(b"gAMA", struct.pack(">I", 100000)),  # data, not colour: gamma 1, no sRGB chunk
}


def tag_png(data: bytes, intent: str) -> bytes:
    """Insert the colour-intent chunks of ``intent`` right after IHDR of the PNG ``data``.

    ``"srgb"``: sRGB (perceptual) + gAMA 0.45455 + cHRM (Rec. 709, D65), for sRGB-encoded colour;
    ``"gamma2.2"``: gAMA 0.45455 + cHRM (Schüler's atlas colours); ``"linear"``: gAMA 1.0 only, for data
    (roughness, metallic, masks). Existing gAMA, sRGB, cHRM and iCCP chunks are dropped first.
    """
    if intent not in _INTENT_CHUNKS:
        raise ExportError(f"PNG intent must be one of {sorted(_INTENT_CHUNKS)}, got {intent!r}")
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        raise ExportError("tag_png: not a PNG (no signature or IHDR chunk)")
    out, pos = [data[:8]], 8
    while pos < len(data):
        if pos + 12 > len(data):
            raise ExportError("tag_png: truncated PNG chunk")
        n = struct.unpack(">I", data[pos: pos + 4])[0]
        kind, end = data[pos + 4: pos + 8], pos + 12 + n
        if kind not in (b"gAMA", b"sRGB", b"cHRM", b"iCCP"):
            out.append(data[pos:end])
        if kind == b"IHDR":
            out.append(_INTENT_CHUNKS[intent])
        pos = end
    return b"".join(out)


def _png_bytes(img: Tensor, bits: int = 8, transfer: str = "srgb", intent: str | None = None,
               name: str = "image.png") -> bytes:
    """PNG file bytes of a linear image (encoded by ``transfer``), tagged with ``intent`` (default: by transfer).
    Encoded by :func:`renderer.imageio.write_png` into a private temporary folder, as a file called ``name``."""
    with tempfile.TemporaryDirectory(prefix="shadecap-png-") as tmp:
        p = Path(tmp) / name
        imageio.write_png(p, img, bits=bits, transfer=transfer)
        data = p.read_bytes()
    return tag_png(data, intent or transfer)


def _write_png(path, img: Tensor, bits: int = 8, transfer: str = "srgb", intent: str | None = None) -> None:
    imageio.atomic_write_bytes(path, _png_bytes(img, bits, transfer, intent, Path(path).name))


# --------------------------------------------------------------------------------------------
# glTF textures, engine texture sets, GLB


_COMPENSATION_DOC = {
    "none": "none: base colour from the albedo as it is",
    "layering": "diffuse divided by (1 - E), E the hemispherical albedo of the dielectric specular layer at the "
                "texel's roughness (viewers that dim the diffuse under it: glTF's fresnel_mix, Blender >= 4)",
    "layering+multiscatter": "layering, and the metals' F0 divided by the multiple-scattering gain of GGX at the "
                             "texel's roughness (Kulla & Conty 2017; Blender >= 4's Cycles)",
}


def _gltf_doc(model: str, specular: bool, compensation: str = "none") -> dict:
    if model == "specular":
        return {
            "model": "glTF 2.0 pbrMetallicRoughness with metallic 0 + KHR_materials_specular",
            "baseColorTexture": "RGB = albedo (sRGB), A = mask (linear)",
            "metallicRoughnessTexture": "R = 1 (occlusion, unused), G = roughness r (perceptual, alpha = r^2), "
                                        "B = metallic = 0; linear",
            "specularColorTexture": "RGB = f0 (sRGB); specularColorFactor 25, so F0 = 0.04 * 25 * texture = f0",
            "compensation": _COMPENSATION_DOC[compensation],
        }
    doc = {
        "model": "glTF 2.0 pbrMetallicRoughness" + (" + KHR_materials_specular" if specular else ""),
        "baseColorTexture": "RGB = base colour b (sRGB), A = mask (linear); albedo = (1 - m) b",
        "metallicRoughnessTexture": "R = 1 (occlusion, unused), G = roughness r (perceptual, alpha = r^2, as ours), "
                                    "B = metallic m; linear",
        "mapping": "per texel least squares of (1-m) b = albedo and 0.04 (1-m) + m b = f0 (docs/export.md)",
        "compensation": _COMPENSATION_DOC[compensation],
    }
    if specular:
        doc["specularColorTexture"] = ("RGB = dielectric F0 t (sRGB), specularColorFactor 25: "
                                       "f0 = (1 - m) t + m b exactly")
    return doc


def _check_compensation(compensation) -> str:
    if compensation not in COMPENSATIONS:
        raise ExportError(f"compensation must be one of {list(COMPENSATIONS)}, got {compensation!r}")
    return compensation


def gltf_textures(maps: Mapping[str, Tensor], material_model: str = "metallic-roughness", bits: int = 8,
                  compensation: str = DEFAULT_COMPENSATION) -> dict:
    """The glTF textures of linear canonical maps (albedo, f0, roughness, optional mask), as tagged PNG bytes.

    Returns ``{"images": {"baseColor", "metallicRoughness"[, "specularColor"]: bytes}, "specular": bool,
    "alpha_mask": bool, "doc": dict, "mapping": dict of error statistics, "mr": to_metallic_roughness(...)}``.
    ``material_model`` ``"metallic-roughness"`` (default) uses :func:`to_metallic_roughness` and adds
    KHR_materials_specular only when the core mapping's F0 error exceeds :data:`SPECULAR_TOLERANCE`
    somewhere; ``"specular"`` writes metallic 0 with f0 in the specular colour (the older form).

    ``compensation`` (:data:`COMPENSATIONS`, default :data:`DEFAULT_COMPENSATION`): ``"layering"`` maps
    albedo / (1 − Ē(r, F0_d)) instead of the albedo, where glTF's BRDF (and Blender ≥ 4, three.js) dims the
    diffuse under the dielectric specular layer of F0_d = 0.04 (the extension's t where the GLB carries it; f0 in
    the specular form), Ē its hemispherical albedo (:func:`specular_albedo`): the diffuse lobe then reflects our
    albedo's energy. Clamped to 1. ``"layering+multiscatter"`` (the default) also divides the metals' F0 (the base
    colour, by metallic: b / (1 + m (s − 1)); the specular colour in the specular form) by
    :func:`multiscatter_factor` s for viewers whose GGX gives back what single scattering loses (Blender ≥ 4,
    three.js's node materials, Filament). ``"none"``: the maps as they are (viewers that add the lobes: Blender 3.x).
    """
    if material_model not in MATERIAL_MODELS:
        raise ExportError(f"material_model must be one of {list(MATERIAL_MODELS)}, got {material_model!r}")
    _check_compensation(compensation)
    if bits not in (8, 16):
        raise ExportError(f"bits must be 8 or 16, got {bits!r}")
    missing = [k for k in ("albedo", "f0", "roughness") if k not in maps]
    if missing:
        raise ExportError(f"gltf_textures needs maps {missing} (have {sorted(maps)})")
    albedo, f0 = maps["albedo"], maps["f0"]
    rough = maps["roughness"]
    if rough.dim() == 2:
        rough = rough[..., None]
    mask = maps.get("mask")
    mask = torch.ones_like(rough) if mask is None else (mask[..., None] if mask.dim() == 2 else mask)
    if not (albedo.shape[:2] == f0.shape[:2] == rough.shape[:2] == mask.shape[:2]) or rough.shape[-1] != 1 \
            or mask.shape[-1] != 1:
        raise ExportError(f"gltf_textures: maps must share one size, with 3 channels for albedo/f0 and 1 for "
                          f"roughness/mask; got { {k: tuple(v.shape) for k, v in maps.items()} }")
    rough = rough.clamp(0.0, 1.0)
    mask = mask.clamp(0.0, 1.0)
    one = torch.ones_like(rough)
    layered = compensation != "none"
    multi = compensation == "layering+multiscatter"

    def span(x):
        return {"min": round(x.min().item(), 6), "max": round(x.max().item(), 6)} if x.numel() else {}

    if material_model == "specular":
        base, metal, spec, use_spec = albedo, torch.zeros_like(rough), f0, True
        mr, mapping = None, {"rule": "metallic 0; specularColor = f0 (factor 25)"}
        if layered:
            base, factor = _layered(albedo, rough, f0.amax(-1, keepdim=True))
        if multi:
            divisor = multiscatter_factor(rough, f0)
            spec = (f0 / divisor).to(f0.dtype)
    else:
        target = albedo
        if layered:
            target, factor = _layered(albedo, rough, GLTF_DIELECTRIC_F0)
        mr = to_metallic_roughness(target, f0, levels=(1 << bits) - 1)
        core_max = mr["f0_error_core"].abs().max().item() if mr["f0_error_core"].numel() else 0.0
        use_spec = core_max > SPECULAR_TOLERANCE
        if layered and use_spec:  # with the extension, the dielectric layer's F0 is t: map again with it
            target, factor = _layered(albedo, rough, mr["specular_f0"].amax(-1, keepdim=True))
            mr = to_metallic_roughness(target, f0, levels=(1 << bits) - 1)
            core_max = mr["f0_error_core"].abs().max().item() if mr["f0_error_core"].numel() else 0.0
            use_spec = core_max > SPECULAR_TOLERANCE
        base, metal, spec = mr["base_color"], mr["metallic"], mr["specular_f0"]
        if multi:
            divisor = 1.0 + metal * (multiscatter_factor(rough, base) - 1.0)
            base = (base / divisor).to(base.dtype)

        def stats(e):
            return {"max": round(e.abs().max().item(), 6) if e.numel() else 0.0,
                    "rms": round(e.pow(2).mean().sqrt().item(), 6) if e.numel() else 0.0}

        mapping = {
            "rule": "least squares per texel (docs/export.md); metallic rounded to the stored code",
            "texels_metallic": int((metal > 0.5).sum()), "texels": int(metal.numel()),
            "diffuse_error": stats(mr["diffuse_error"]), "f0_error_core": stats(mr["f0_error_core"]),
            "f0_error_with_specular_extension": stats(mr["f0_error"]),
            "specular_extension": use_spec,
        }
    mapping["compensation"] = {"mode": compensation}
    if layered:
        mapping["compensation"]["diffuse_factor"] = span(factor)
        mapping["compensation"]["texels_clamped"] = int(((albedo.to(torch.float64) * factor) > 1).any(-1).sum())
    if multi:
        mapping["compensation"]["f0_divisor"] = span(divisor)
    images = {
        "baseColor": _png_bytes(torch.cat([base, mask], -1), bits, "srgb"),
        "metallicRoughness": _png_bytes(torch.cat([one, rough, metal], -1), bits, "linear"),
    }
    if use_spec:
        images["specularColor"] = _png_bytes(spec, bits, "srgb")
    return {"images": images, "specular": use_spec, "alpha_mask": bool((mask < 1).any()),
            "doc": _gltf_doc(material_model, use_spec, compensation), "mapping": mapping, "mr": mr,
            "compensation": compensation,
            "base_color": base, "metallic": metal, "roughness": rough, "mask": mask}


def write_texture_sets(folder, maps: Mapping[str, Tensor], sets: Sequence[str] = TEXTURE_SETS, bits: int = 8,
                       textures: dict | None = None, compensation: str = DEFAULT_COMPENSATION) -> dict:
    """Write the engines' texture sets of linear canonical maps into ``folder`` (created if missing).

    Always the canonical maps as linear float EXR (``albedo``, ``f0``, ``roughness``, ``mask``; Rec. 709
    chromaticities); then per set (``sets`` ⊆ :data:`TEXTURE_SETS`), PNGs of ``bits`` bits:

    - ``gltf``: ``gltf_baseColor.png`` (sRGB; A = mask), ``gltf_metallicRoughness.png`` (linear;
      R = 1, G = roughness, B = metallic), ``gltf_specularColor.png`` (sRGB) when the mapping needs it;
    - ``unreal``: ``unreal_BaseColor.png`` (sRGB; A = mask), ``unreal_ORM.png`` (linear; R = occlusion 1,
      G = roughness, B = metallic);
    - ``unity-hdrp``: ``unity_BaseColorMap.png`` (sRGB; A = mask), ``unity_MaskMap.png`` (linear;
      R = metallic, G = occlusion 1, B = detail mask 1, A = smoothness 1 − roughness).

    ``compensation`` applies to the ``gltf`` set only (the GLB's textures, :func:`gltf_textures`); the engines'
    sets hold the uncompensated mapping. Colour PNGs carry an sRGB chunk, data PNGs gAMA 1.0 (:func:`tag_png`).
    ``textures``: a result of :func:`gltf_textures` with the metallic-roughness model to reuse where its
    compensation fits. Returns ``{set: {role: file name}}``.
    """
    folder = Path(folder)
    sets = tuple(sets)
    unknown = [s for s in sets if s not in TEXTURE_SETS]
    if unknown:
        raise ExportError(f"unknown texture set(s) {unknown}; choose from {list(TEXTURE_SETS)}")
    _check_compensation(compensation)
    done = {} if textures is None or textures.get("mr") is None else {textures["compensation"]: textures}

    def textures_for(mode: str) -> dict:
        if mode not in done:
            done[mode] = gltf_textures(maps, "metallic-roughness", bits, mode)
        return done[mode]

    textures = textures_for(compensation if "gltf" in sets else "none")
    folder.mkdir(parents=True, exist_ok=True)
    written: dict = {"exr": {}}
    for k, img in (("albedo", maps["albedo"]), ("f0", maps["f0"]), ("roughness", textures["roughness"]),
                   ("mask", textures["mask"])):
        imageio.write_exr(folder / f"{k}.exr", img, chromaticities="rec709")
        written["exr"][k] = f"{k}.exr"
    img = textures["images"]
    files = {}
    if "gltf" in sets:
        files["gltf"] = {"baseColor": ("gltf_baseColor.png", img["baseColor"]),
                         "metallicRoughness": ("gltf_metallicRoughness.png", img["metallicRoughness"])}
        if "specularColor" in img:
            files["gltf"]["specularColor"] = ("gltf_specularColor.png", img["specularColor"])
    if "unreal" in sets or "unity-hdrp" in sets:
        textures = textures_for("none")
        img = textures["images"]
    if "unreal" in sets:
        files["unreal"] = {"BaseColor": ("unreal_BaseColor.png", img["baseColor"]),
                           "ORM": ("unreal_ORM.png", img["metallicRoughness"])}  # same channels as glTF's
    if "unity-hdrp" in sets:
        one = torch.ones_like(textures["roughness"])
        mask_map = torch.cat([textures["metallic"], one, one, 1.0 - textures["roughness"]], -1)
        # the alpha channel of write_png is linear, like the others here
        files["unity-hdrp"] = {"BaseColorMap": ("unity_BaseColorMap.png", img["baseColor"]),
                               "MaskMap": ("unity_MaskMap.png", _png_bytes(mask_map, bits, "linear"))}
    for name, roles in files.items():
        written[name] = {}
        for role, (fname, data) in roles.items():
            imageio.atomic_write_bytes(folder / fname, data)
            written[name][role] = fname
    return written


class _GlbBuffer:
    """The GLB's binary chunk with its bufferViews and accessors, each view 4-byte aligned."""

    def __init__(self):
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add_view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.blob.extend(data)
        self.views.append(view)
        return len(self.views) - 1

    def add_accessor(self, arr: np.ndarray, kind: str, ctype: int, target: int, minmax: bool = False) -> int:
        acc = {"bufferView": self.add_view(arr.tobytes(), target), "componentType": ctype,
               "count": int(arr.shape[0]), "type": kind}
        if minmax:
            acc["min"] = arr.min(0).tolist()
            acc["max"] = arr.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _glb_meshes(buf: _GlbBuffer, meshes: Sequence[Mesh]) -> tuple[list[dict], list[dict]]:
    """glTF meshes and nodes of ``meshes``: rotated to Y-up, v flipped, their arrays appended to ``buf``."""
    gl_meshes, nodes = [], []
    for k, m in enumerate(meshes):
        v = zup_to_yup(m.vertices.detach().cpu().double()).numpy().astype(np.float32)
        n = zup_to_yup(m.normals.detach().cpu().double()).numpy().astype(np.float32)
        uv = m.uvs.detach().cpu().numpy().astype(np.float32).copy()
        uv[:, 1] = 1.0 - uv[:, 1]
        idx = m.faces.cpu().numpy().astype(np.uint32).reshape(-1)
        attrs = {"POSITION": buf.add_accessor(v, "VEC3", 5126, 34962, True),
                 "NORMAL": buf.add_accessor(n, "VEC3", 5126, 34962),
                 "TEXCOORD_0": buf.add_accessor(uv, "VEC2", 5126, 34962)}
        ind = buf.add_accessor(idx[:, None], "SCALAR", 5125, 34963)
        gl_meshes.append({"name": m.name or f"mesh{k}", "primitives": [{"attributes": attrs, "indices": ind,
                                                                         "material": 0, "mode": 4}]})
        nodes.append({"name": m.name or f"mesh{k}", "mesh": k})
    return gl_meshes, nodes


def _glb_material(textures: dict) -> dict:
    """The one glTF material over the atlas textures (indices 0, 1 and, with the specular extension, 2)."""
    alpha_mode = "MASK" if textures["alpha_mask"] else "OPAQUE"
    material = {
        "name": "schuler_atlas",
        "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
                                 "metallicFactor": 1.0, "roughnessFactor": 1.0},
        "alphaMode": alpha_mode,
    }
    if textures["specular"]:
        material["extensions"] = {"KHR_materials_specular": {
            "specularColorTexture": {"index": 2}, "specularColorFactor": [1.0 / GLTF_DIELECTRIC_F0] * 3,
            "specularFactor": 1.0}}
    if alpha_mode == "MASK":
        material["alphaCutoff"] = 0.5
    return material


def _glb_bytes(gltf: dict, buf: _GlbBuffer) -> bytes:
    """The GLB container: header, JSON chunk (space-padded), BIN chunk (zero-padded); sets ``gltf["buffers"]``."""
    blob = buf.blob
    while len(blob) % 4:
        blob.append(0)
    gltf["buffers"] = [{"byteLength": len(blob)}]
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob))


def write_glb(path, meshes: Sequence[Mesh], maps: Mapping[str, Tensor], *,
              material_model: str = "metallic-roughness", bits: int = 8, textures: dict | None = None,
              compensation: str = DEFAULT_COMPENSATION) -> dict:
    """Write ``meshes`` (UVs already in atlas space) as one GLB with one material over the atlas ``maps``.

    ``maps``: linear canonical albedo, f0, roughness, optional mask ``[H, W, C]``. The material follows
    :func:`gltf_textures` (default: glTF metallic-roughness, metals as metallic 1; KHR_materials_specular
    only where a dielectric's f0 ≠ 0.04; ``compensation`` as there, ignored when ``textures`` is given).
    Textures are PNGs of ``bits`` (8 or 16) bits per channel: baseColor RGB sRGB + alpha linear (mask;
    ``alphaMode`` MASK when some mask < 1), metallicRoughness linear (G = roughness, B = metallic),
    specularColor sRGB. Sampler: linear, mip-mapped, clamp to edge.
    Geometry: the dataset's Z-up world is rotated to glTF's Y-up, (x, y, z) → (x, z, −y), normals too;
    glTF's UV origin is the top-left, so ``v_gltf = 1 − v``. Written atomically.

    Returns:
        The ``gltf`` entry of the sidecar: file name, material description, mapping error statistics.
    """
    path = Path(path)
    if not meshes:
        raise ExportError(f"{path}: no meshes to write")
    if any(not isinstance(m, Mesh) for m in meshes):
        raise ExportError(f"{path}: meshes must be renderer.mesh.Mesh objects")
    if textures is None:
        textures = gltf_textures(maps, material_model, bits, compensation)
    images = [textures["images"]["baseColor"], textures["images"]["metallicRoughness"]]
    if textures["specular"]:
        images.append(textures["images"]["specularColor"])
    buf = _GlbBuffer()
    gl_meshes, nodes = _glb_meshes(buf, meshes)
    image_ids = [buf.add_view(b) for b in images]
    gltf = {
        "asset": {"version": "2.0", "generator": "shadecap capture.export",
                  "extras": {"up_axis": "Y (the dataset's Z-up world rotated: (x, y, z) -> (x, z, -y))"}},
        "scene": 0, "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes, "meshes": gl_meshes,
        "materials": [_glb_material(textures)],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"bufferView": i, "mimeType": "image/png"} for i in image_ids],
        "textures": [{"source": i, "sampler": 0} for i in range(len(image_ids))],
        "accessors": buf.accessors, "bufferViews": buf.views,
    }
    if textures["specular"]:
        gltf["extensionsUsed"] = ["KHR_materials_specular"]
    imageio.atomic_write_bytes(path, _glb_bytes(gltf, buf))
    return {"file": path.name, "up_axis": "Y", "frame": "(x, y, z) dataset -> (x, z, -y) glTF",
            "bits": bits, "material_model": material_model, "compensation": textures["compensation"],
            "material": textures["doc"],
            "mapping": textures["mapping"]}


def read_glb(path) -> tuple[dict, bytes]:
    """Parse a GLB → (its JSON as a dict, its binary chunk). Raises ExportError on a malformed file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ExportError(f"{path}: cannot read ({err})") from err
    if len(raw) < 20 or raw[:4] != b"glTF" or struct.unpack("<I", raw[4:8])[0] != 2:
        raise ExportError(f"{path}: not a glTF 2.0 binary (GLB) file")
    total, n = struct.unpack("<I", raw[8:12])[0], struct.unpack("<I", raw[12:16])[0]
    if total != len(raw) or raw[16:20] != b"JSON" or 20 + n > len(raw):
        raise ExportError(f"{path}: truncated or malformed GLB (header length {total}, file {len(raw)} bytes)")
    try:
        js = json.loads(raw[20: 20 + n])
    except ValueError as err:
        raise ExportError(f"{path}: JSON chunk is not valid JSON ({err})") from err
    pos, blob = 20 + n, b""
    if pos + 8 <= len(raw):
        m = struct.unpack("<I", raw[pos: pos + 4])[0]
        if raw[pos + 4: pos + 8] != b"BIN\x00":
            raise ExportError(f"{path}: second chunk is not BIN")
        blob = raw[pos + 8: pos + 8 + m]
    return js, blob
