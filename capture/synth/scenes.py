"""Synthetic captures with known ground truth: meshes, camera and light rigs, procedural maps.

:func:`make_synthetic` turns a :class:`SyntheticConfig` into a dataset folder
(:mod:`capture.dataset`): it builds the mesh, the cameras and the lights, draws ground-truth maps
for the chosen model (:func:`procedural_maps`), renders every view with
:func:`renderer.shading.prepare` / :func:`renderer.shading.shade` (G-buffer and shadow rays
once per view), applies the photo model (:class:`capture.photo.PhotoModel`) and writes the
result atomically with :func:`capture.dataset.write_dataset`, ground truth under ``gt/``.

Ground truth (:func:`procedural_maps`): six regions of distinct materials laid out as vertical
stripes in u (so each region wraps around a primitive and every camera of an orbit sees several):

====  ==================  ===============================================================
id    name                material
====  ==================  ===============================================================
1     rough-dielectric    red-brown diffuse in a sharp 2-colour checker, f0 0.04, r = 0.75
2     smooth-dielectric   blue plastic (f0 = Schüler's polystyrene 0.05), r = 0.25
3     gold                metal: no diffuse, f0 = Schüler's gold (coloured), r = 0.35
4     copper              metal: no diffuse, f0 = Schüler's copper (coloured), r = 0.5
5     coated              green base, r = 0.6, under a clear coat (coat_ior 1.5, coat r = 0.05)
                          with coloured absorption α' = (0.2, 0.8, 2.0)
6     gradient            smooth gradients: albedo light → dark along u, roughness
                          0.15 → 0.9 along v, f0 0.02 → 0.08 along v
====  ==================  ===============================================================

Stripe borders are sharp edges in every parameter. The maps hold exactly ``model.params``; every
canonical parameter has a value per region (absorption is 0 outside the coated region), clamped
to the model's declared range. For a model without ``f0`` (pure diffuse), the metal regions get
a diffuse albedo of 0.9·f0 instead of black, so that every region is visible.

Light rigs (``SyntheticConfig.light_rig``), all point lights of intensity I = E·d² so that each
delivers irradiance ``light_irradiance`` at the object's centre:

- ``"flash"``: ``n_lights`` lights per view travelling with the camera, each ``light_offset_deg``
  away from the camera as seen from the target, spread evenly around it. A highlight needs
  h ≈ n; with l ≈ v, h ≈ v, so every view puts ``n_lights`` highlights near the centre of what it
  sees, and an orbit over two elevation rings spreads them over the object.
- ``"fixed"``: ``n_lights`` world-fixed lights, light k near camera k·N/n_lights (raised by
  ``light_offset_deg``) — a studio with lamps beside some cameras.
- ``"dome"``: ``n_lights`` world-fixed lights spread over the upper hemisphere (Fibonacci).

With a turntable rig, fixed/dome lights are fixed in the studio, i.e. they turn with the camera in
the object's frame.

Highlight coverage (:func:`highlight_coverage`) measures how much of the surface shows a
highlight in some view: the fraction of observed texels (reached by some lit sample) with a
(sample, light) pair whose half vector lies within the GGX lobe's half-maximum angle θ½ of the
normal, θ½ from D(θ)/D(0) = ½: cos²θ½ = (1 − √2 α²)/(1 − α²), α = r² (θ½ ≈ 0.64 α for small α;
90° for α² ≥ 1/√2), floored at ``min_angle_deg``. It is written to ``scene.json`` under
``meta.highlight_coverage``.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from materials import Model
from materials import presets as _presets
from materials.fresnel import ior_from_f0
from materials.roughness import half_max_angle
from renderer.camera import Camera, orbit, random_rig, turntable
from renderer.gbuffer import check_psf_sigma, render_gbuffer
from renderer.lights import PointLight
from renderer.mesh import Mesh, load_mesh, nonconvex, plane, save_mesh, torus, uv_sphere
from renderer.shading import prepare, shade
from renderer.texture import texel_centers, texel_of

from ..dataset import GroundTruth, View, model_from_spec, model_spec, write_dataset
from ..photo import PhotoModel

__all__ = [
    "SyntheticConfig", "SyntheticError", "Scene", "BUILTIN_MESHES", "CAMERA_RIGS", "LIGHT_RIGS", "REGION_NAMES",
    "build_mesh", "build_cameras", "build_lights", "procedural_maps", "build_scene", "render_scene",
    "highlight_coverage", "make_synthetic", "default_scene", "small_scene",
]

BUILTIN_MESHES = {"uv_sphere": uv_sphere, "sphere": uv_sphere, "torus": torus, "nonconvex": nonconvex, "plane": plane}
CAMERA_RIGS = ("orbit", "turntable", "random")
LIGHT_RIGS = ("flash", "fixed", "dome")
SAMPLING = ("bilinear", "nearest")

#: Region id → name of the procedural ground truth.
REGION_NAMES = {1: "rough-dielectric", 2: "smooth-dielectric", 3: "gold", 4: "copper", 5: "coated", 6: "gradient"}


class SyntheticError(ValueError):
    """An invalid synthetic-scene configuration (the message names the field)."""


@dataclass
class SyntheticConfig:
    """Everything that defines a synthetic capture.

    Attributes:
        mesh: a built-in name (:data:`BUILTIN_MESHES`: uv_sphere, torus, nonconvex, plane) or the path
            of a mesh file with UVs.
        mesh_options: keyword arguments of the built-in primitive (e.g. ``{"segments": 32}``).
        n_views: number of views.
        image_size: ``W`` (square) or ``(W, H)`` in pixels.
        texture_size: ground-truth maps are ``T × T`` texels (or ``(W, H)``).
        model: registered model name, ``"a+b"`` for a sum, or a spec dict (:func:`capture.dataset.model_spec`).
        model_options: options of a single named model.
        camera_rig: "orbit" (rings at ``elevations``), "turntable" (fixed camera at ``elevations[0]``,
            object turning) or "random" (random azimuths, elevations within ``elevations``' range).
        elevations: ring elevations in degrees (orbit: ``n_views`` split evenly over the rings).
        fov_y_deg: vertical field of view (degrees).
        distance: camera distance from the target (world units); None → the mesh's bounding sphere fills
            about 90 % of the field of view.
        light_rig: "flash", "fixed" or "dome" (module docstring).
        n_lights: lights per view (flash) or in the studio (fixed, dome).
        light_offset_deg: flash/fixed: angle between a light and its camera seen from the target.
        light_irradiance: irradiance (RGB scalar) each light delivers at the target.
        photo: the photo model.
        supersample: k×k rays per pixel, each at a random position inside its stratum of the pixel (``jitter``):
            how a camera integrates light over a pixel and how a Monte Carlo renderer anti-aliases. The default 8
            (64 rays) is finer than, and differently placed from, any pixel sampling the fit uses
            (:mod:`capture.footprint`: at most 4 × 4 at the strata's centres), so the photos cannot flatter the
            fit. 1 renders the pixel centres only — the fit's own discretisation, for exactness tests of a solver.
        jitter: random positions inside the strata (default); False puts them at the strata's centres.
        psf_sigma: σ (pixels) of a Gaussian lens/demosaicing blur applied before the pixel's box filter (0: none).
            The blur is applied to the image of the k × k strata (σ·k strata wide, so it is finer than and
            placed differently from the fit's quadrature of the same filter); needs ``supersample`` ≥ 4.
        sampling: map sampling, "bilinear" (default) or "nearest" (each sample reads one texel).
        shadows: cast shadow rays.
        seed: seeds the random rig and the photo noise (view i uses seed·1000003 + i).
        materials: number of distinct materials in the ground truth, 1–6: the first ``materials`` rows
            of the region table (module docstring), as that many stripes in u.
        uniform: parameter name → value (a number, or one per channel) written into every texel of the
            ground truth after the procedural maps — e.g. ``{"roughness": 0.02}`` for a mirror-like
            scene; the value must lie in the parameter's range.
    """

    mesh: str = "uv_sphere"
    mesh_options: dict = field(default_factory=dict)
    n_views: int = 16
    image_size: int | tuple[int, int] = 256
    texture_size: int | tuple[int, int] = 256
    model: str | dict = "ggx-lambert"
    model_options: dict = field(default_factory=dict)
    camera_rig: str = "orbit"
    elevations: tuple[float, ...] = (15.0, 50.0)
    fov_y_deg: float = 40.0
    distance: float | None = None
    light_rig: str = "flash"
    n_lights: int = 2
    light_offset_deg: float = 20.0
    light_irradiance: float = 1.0
    photo: PhotoModel = field(default_factory=PhotoModel)
    supersample: int = 8
    jitter: bool = True
    psf_sigma: float = 0.0
    sampling: str = "bilinear"
    shadows: bool = True
    seed: int = 0
    materials: int = len(REGION_NAMES)
    uniform: dict = field(default_factory=dict)

    def __post_init__(self):
        if isinstance(self.photo, dict):
            self.photo = PhotoModel.from_dict(self.photo)
        if not isinstance(self.photo, PhotoModel):
            raise SyntheticError(f"photo must be a PhotoModel, got {type(self.photo).__name__}")
        if not isinstance(self.mesh, str) or not self.mesh:
            raise SyntheticError(f"mesh must be a built-in name {sorted(BUILTIN_MESHES)} or a file path, "
                                 f"got {self.mesh!r}")
        for name in ("n_views", "n_lights", "supersample", "seed"):
            x = getattr(self, name)
            if isinstance(x, bool) or not isinstance(x, int) or x < (0 if name == "seed" else 1):
                raise SyntheticError(f"{name} must be a {'non-negative' if name == 'seed' else 'positive'} integer, "
                                     f"got {x!r}")
        try:
            check_psf_sigma(self.psf_sigma)
        except ValueError as exc:
            raise SyntheticError(str(exc)) from None
        if self.psf_sigma > 0 and self.supersample < 4:
            raise SyntheticError(f"psf_sigma > 0 blurs the image of the sub-pixel strata and needs supersample ≥ 4, "
                                 f"got supersample={self.supersample}")
        self.image_size = _size(self.image_size, "image_size")
        self.texture_size = _size(self.texture_size, "texture_size")
        if self.camera_rig not in CAMERA_RIGS:
            raise SyntheticError(f"camera_rig must be one of {CAMERA_RIGS}, got {self.camera_rig!r}")
        if self.light_rig not in LIGHT_RIGS:
            raise SyntheticError(f"light_rig must be one of {LIGHT_RIGS}, got {self.light_rig!r}")
        if self.sampling not in SAMPLING:
            raise SyntheticError(f"sampling must be one of {SAMPLING}, got {self.sampling!r}")
        if isinstance(self.elevations, (int, float)):
            self.elevations = (float(self.elevations),)
        self.elevations = tuple(float(e) for e in self.elevations)
        if not self.elevations or any(not -89.9 <= e <= 89.9 for e in self.elevations):
            raise SyntheticError(f"elevations must be degrees in [-89.9, 89.9], got {self.elevations}")
        if not 0 < self.fov_y_deg < 180:
            raise SyntheticError(f"fov_y_deg must lie in (0, 180), got {self.fov_y_deg}")
        if self.distance is not None and not self.distance > 0:
            raise SyntheticError(f"distance must be positive or None, got {self.distance}")
        if not (math.isfinite(self.light_irradiance) and self.light_irradiance > 0):
            raise SyntheticError(f"light_irradiance must be positive, got {self.light_irradiance}")
        if not 0 <= self.light_offset_deg < 90:
            raise SyntheticError(f"light_offset_deg must lie in [0, 90), got {self.light_offset_deg}")
        if (isinstance(self.materials, bool) or not isinstance(self.materials, int)
                or not 1 <= self.materials <= len(REGION_NAMES)):
            raise SyntheticError(f"materials must be an integer in [1, {len(REGION_NAMES)}], got {self.materials!r}")
        try:
            self.model = model_spec(self.model, self.model_options)
            self.model_options = {}
            model = model_from_spec(self.model)  # unknown names and options fail here, not after rendering
        except ValueError as exc:
            raise SyntheticError(f"model: {exc}") from None
        if not isinstance(self.uniform, Mapping):
            raise SyntheticError(f"uniform must be a dict parameter name → value, got {type(self.uniform).__name__}")
        self.uniform = {k: _uniform_value(model, k, v) for k, v in self.uniform.items()}

    def to_dict(self) -> dict:
        d = asdict(self)
        d["photo"] = self.photo.to_dict()
        return d


def _uniform_value(model: Model, name: str, value) -> list[float]:
    """Validate one ``uniform`` entry against the model; return it as a list of channel values."""
    if name not in model.param_names:
        raise SyntheticError(f"uniform: model '{model.name}' has no parameter '{name}'; it has "
                             f"{list(model.param_names)}")
    spec = model.spec(name)
    vals = [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    try:
        vals = [float(x) for x in vals]
    except (TypeError, ValueError):
        raise SyntheticError(f"uniform: '{name}' must be a number or {spec.channels} numbers, got {value!r}") from None
    if len(vals) not in (1, spec.channels):
        raise SyntheticError(f"uniform: '{name}' has {spec.channels} channel(s), got {len(vals)} values")
    if any(not (spec.low <= x <= spec.high) for x in vals):
        raise SyntheticError(f"uniform: '{name}' = {vals} is outside its range [{spec.low}, {spec.high}]")
    return vals


def _size(x, name) -> tuple[int, int]:
    if isinstance(x, int) and not isinstance(x, bool):
        x = (x, x)
    if (not isinstance(x, (tuple, list)) or len(x) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in x)):
        raise SyntheticError(f"{name} must be a positive integer or a (width, height) pair, got {x!r}")
    return (int(x[0]), int(x[1]))


# ----------------------------------------------------------------------------------------------
# scene parts


def build_mesh(name: str, options: Mapping | None = None) -> Mesh:
    """A built-in primitive by name, or a mesh file with UVs, canonicalised through an OBJ round trip.

    The OBJ round trip (:func:`renderer.mesh.save_mesh` → :func:`renderer.mesh.load_mesh`) makes the
    mesh bit-identical to what :func:`capture.dataset.load_dataset` will read from the written
    dataset, so re-rendering a loaded dataset reproduces its images exactly.
    """
    options = dict(options or {})
    if name in BUILTIN_MESHES:
        mesh = BUILTIN_MESHES[name](**options)
    else:
        if options:
            raise SyntheticError(f"mesh_options apply to built-in meshes only, not to the file '{name}'")
        mesh = load_mesh(name)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "mesh.obj"
        save_mesh(mesh, path)
        out = load_mesh(path)
    out.name = mesh.name
    return out


def _target_and_radius(mesh: Mesh) -> tuple[Tensor, float]:
    b = mesh.bounds.double()
    return 0.5 * (b[0] + b[1]), 0.5 * float((b[1] - b[0]).norm())


def build_cameras(config: SyntheticConfig, mesh: Mesh) -> tuple[list[Camera], list[Tensor] | None]:
    """Cameras of the config's rig looking at the mesh's bounding-box centre.

    Returns ``(cameras, rotations)``; ``rotations`` (turntable only, else None) maps studio to object
    coordinates per view (:func:`renderer.camera.turntable`).
    """
    target, R = _target_and_radius(mesh)
    dist = config.distance or R / math.sin(math.radians(0.45 * config.fov_y_deg))
    W, H = config.image_size
    kw = dict(fov_y_deg=config.fov_y_deg, width=W, height=H)
    tgt = tuple(target.tolist())
    if config.camera_rig == "orbit":
        rings = config.elevations
        n_r = len(rings)
        counts = [config.n_views // n_r + (1 if k < config.n_views % n_r else 0) for k in range(n_r)]
        cams = []
        for k, (el, n) in enumerate(zip(rings, counts, strict=True)):
            if n:
                cams += orbit(n, dist, el, tgt, azimuth_offset_deg=(180.0 / n) * (k % 2), **kw)
        return cams, None
    if config.camera_rig == "turntable":
        return turntable(config.n_views, dist, config.elevations[0], tgt, **kw)
    lo, hi = min(config.elevations), max(config.elevations)
    return random_rig(config.seed, config.n_views, dist, (lo, hi), tgt, **kw), None


def _frame(d: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors perpendicular to unit ``d`` (right, up), up as close to +z as possible."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    right = torch.linalg.cross(d, z)
    if right.norm() < 1e-6:
        right = torch.linalg.cross(d, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    right = right / right.norm()
    return right, torch.linalg.cross(right, d)


def build_lights(config: SyntheticConfig, mesh: Mesh, cameras: list[Camera],
                 rotations: list[Tensor] | None = None) -> list[list[PointLight]]:
    """Per view, the point lights of the config's light rig (module docstring)."""
    target, _ = _target_and_radius(mesh)
    E = config.light_irradiance
    off = math.radians(config.light_offset_deg)

    def light_at(direction: Tensor, dist: float) -> PointLight:
        pos = target + dist * direction
        return PointLight(pos.tolist(), E * dist * dist)

    def around(center_dir: Tensor, k: int, n: int) -> Tensor:
        right, up = _frame(center_dir)
        phi = 2.0 * math.pi * k / n + 0.5 * math.pi
        return math.cos(off) * center_dir + math.sin(off) * (math.cos(phi) * right + math.sin(phi) * up)

    out = []
    if config.light_rig == "flash":
        for cam in cameras:
            c = cam.center.double() - target
            d = float(c.norm())
            out.append([light_at(around(c / d, k, config.n_lights), d) for k in range(config.n_lights)])
        return out
    # studio lights: defined relative to the studio (view 0's frame for a turntable)
    c0 = [cam.center.double() - target for cam in cameras]
    if rotations is not None:  # back to the studio frame: p_studio = Qᵀ p_object
        c0 = [rotations[i].T @ c for i, c in enumerate(c0)]
    dist = float(torch.stack([c.norm() for c in c0]).mean())
    dirs = []
    if config.light_rig == "fixed":
        for k in range(config.n_lights):
            c = c0[(k * len(c0)) // config.n_lights]
            c = c / c.norm()
            right, up = _frame(c)
            dirs.append(math.cos(off) * c + math.sin(off) * up)
    else:  # dome: Fibonacci points on the upper hemisphere, elevation ≥ 10°
        golden = math.pi * (3.0 - math.sqrt(5.0))
        zmin = math.sin(math.radians(10.0))
        for k in range(config.n_lights):
            z = 1.0 - (1.0 - zmin) * (k + 0.5) / config.n_lights
            r = math.sqrt(max(0.0, 1.0 - z * z))
            dirs.append(torch.tensor([r * math.cos(golden * k), r * math.sin(golden * k), z], dtype=torch.float64))
    for i in range(len(cameras)):
        Q = rotations[i] if rotations is not None else torch.eye(3, dtype=torch.float64)
        out.append([light_at(Q @ d, dist) for d in dirs])
    return out


# ----------------------------------------------------------------------------------------------
# ground-truth maps


def _region_table(has_f0: bool) -> dict[int, dict[str, Tensor]]:
    t = lambda *x: torch.tensor(x, dtype=torch.float64)
    gold, copper = _presets.f0("gold", torch.float64), _presets.f0("copper", torch.float64)
    plastic = _presets.f0("polystyrene", torch.float64)
    zero3 = t(0.0, 0.0, 0.0)
    # a parameter a row does not give keeps its ParamSpec default (no coat: absorption 0, coat η 1.5, mask 1)
    return {
        1: {"albedo": t(0.70, 0.25, 0.15), "f0": t(0.04, 0.04, 0.04), "roughness": t(0.75), "mix": t(0.3)},
        2: {"albedo": t(0.10, 0.25, 0.60), "f0": plastic, "roughness": t(0.25), "mix": t(0.7)},
        3: {"albedo": 0.9 * gold if not has_f0 else zero3, "f0": gold, "roughness": t(0.35), "mix": t(0.5)},
        4: {"albedo": 0.9 * copper if not has_f0 else zero3, "f0": copper, "roughness": t(0.5), "mix": t(0.5)},
        5: {"albedo": t(0.15, 0.55, 0.20), "f0": t(0.04, 0.04, 0.04), "roughness": t(0.6), "mix": t(0.5),
            "absorption": t(0.2, 0.8, 2.0), "coat_ior": t(1.5), "coat_roughness": t(0.05)},
        6: {},  # gradients, filled per texel
    }


def procedural_maps(model: Model, size: int | tuple[int, int] = 256, n_materials: int = len(REGION_NAMES),
                    uniform: Mapping[str, object] | None = None) -> tuple[dict[str, Tensor], Tensor]:
    """Ground-truth maps for ``model`` and the region-id map (see the module docstring's table).

    Args:
        model: any registered model; the maps hold exactly ``model.params``.
        size: ``T`` or ``(W, H)`` texels.
        n_materials: how many of the table's regions (the first ones), as that many stripes in u.
        uniform: parameter name → value(s) written into every texel afterwards (:class:`SyntheticConfig`).

    Returns:
        ``(maps, regions)``: maps name → ``[H, W, C]`` float32 (C = the parameter's channels, values
        inside its declared range, row 0 = top = v = 1), regions ``[H, W]`` int64 with ids of
        :data:`REGION_NAMES`.
    """
    if not isinstance(model, Model):
        raise SyntheticError(f"procedural_maps: model must be a materials.Model, got {type(model).__name__}")
    W, H = _size(size, "size")
    uv = texel_centers(H, W, dtype=torch.float64)
    u, v = uv[..., 0], uv[..., 1]
    if isinstance(n_materials, bool) or not isinstance(n_materials, int) or not 1 <= n_materials <= len(REGION_NAMES):
        raise SyntheticError(f"procedural_maps: n_materials must be an integer in [1, {len(REGION_NAMES)}], "
                             f"got {n_materials!r}")
    n_reg = n_materials
    stripe = torch.clamp(torch.floor(u * n_reg), 0, n_reg - 1).long()
    regions = stripe + 1
    has_f0 = "f0" in model.param_names
    table = _region_table(has_f0)
    # position inside the stripe, 0..1, for the gradient region and the checker
    su = u * n_reg - stripe.double()
    grad = {
        "albedo": torch.stack([0.9 - 0.7 * su, 0.85 - 0.65 * su, 0.8 - 0.6 * su], -1),
        "f0": (0.02 + 0.06 * v)[..., None].expand(H, W, 3),
        "roughness": (0.9 - 0.75 * v)[..., None],
        "mix": su[..., None],
        "coat_roughness": (0.05 + 0.3 * v)[..., None],
    }
    checker = ((torch.floor(su * 4) + torch.floor(v * 4 * n_reg / 1.0)) % 2 == 1)
    maps = {}
    for spec in model.params:
        C = spec.channels
        out = torch.full((H, W, C), float(spec.default), dtype=torch.float64)
        for rid, row in table.items():
            mask = regions == rid
            val = _derived(spec.name, grad if rid == 6 else row)
            if val is None:
                continue
            val = _fit(val, C)
            out[mask] = val[mask] if val.dim() == 3 else val.to(out)
        if spec.name == "albedo":  # a sharp two-colour checker inside the rough dielectric
            alt = torch.tensor([0.85, 0.75, 0.55], dtype=torch.float64)
            sel = (regions == 1) & checker
            out[sel] = alt[:C] if C == 3 else alt.mean().reshape(1)
        if uniform and spec.name in uniform:
            vals = _uniform_value(model, spec.name, uniform[spec.name])
            out[:] = torch.tensor(vals, dtype=torch.float64).expand(C)
        maps[spec.name] = out.clamp(spec.low, spec.high).to(torch.float32)
    return maps, regions


def _fit(val: Tensor, C: int) -> Tensor:
    """Adapt a value's channels (last dim) to C: broadcast 1 → C, average 3 → 1."""
    if val.shape[-1] == C:
        return val
    if val.shape[-1] == 1:
        return val.expand(*val.shape[:-1], C)
    return val.mean(-1, keepdim=True)


def _derived(name: str, row: Mapping[str, Tensor]) -> Tensor | None:
    """A parameter's value from a region row, including the derived ones (ior, specular)."""
    if name in row:
        return row[name]
    if name == "ior" and "f0" in row:
        f0 = row["f0"].mean(-1, keepdim=True).clamp(1e-4, 0.25)
        return ior_from_f0(f0).clamp(1.0, 3.0)
    if name == "specular" and "f0" in row:
        return row["f0"]
    return None


# ----------------------------------------------------------------------------------------------
# rendering


@dataclass
class Scene:
    """A built synthetic scene: mesh, views (cameras + lights), model, maps, regions."""

    mesh: Mesh
    views: list[View]
    model: Model
    model_spec: dict
    maps: dict[str, Tensor]
    regions: Tensor


def build_scene(config: SyntheticConfig) -> Scene:
    """Mesh, cameras, lights, model and ground-truth maps of ``config`` (no rendering)."""
    if not isinstance(config, SyntheticConfig):
        raise SyntheticError(f"config must be a SyntheticConfig, got {type(config).__name__}")
    mesh = build_mesh(config.mesh, config.mesh_options)
    cams, rots = build_cameras(config, mesh)
    lights = build_lights(config, mesh, cams, rots)
    try:
        model = model_from_spec(config.model)
    except ValueError as exc:
        raise SyntheticError(f"model: {exc}") from None
    maps, regions = procedural_maps(model, config.texture_size, config.materials, config.uniform)
    views = [View(c, ls, config.photo.exposure) for c, ls in zip(cams, lights, strict=True)]
    return Scene(mesh, views, model, config.model, maps, regions)


def highlight_coverage(prepared: list, texture_size: tuple[int, int], roughness: Tensor | None = None,
                       regions: Tensor | None = None, min_angle_deg: float = 1.0,
                       nominal_roughness: float = 0.5) -> dict:
    """Fraction of observed texels that show a highlight in some view (module docstring).

    Args:
        prepared: per view, a :class:`renderer.shading.Prepared`.
        texture_size: (W, H) of the maps.
        roughness: ``[H, W, 1]`` roughness map (per-texel lobe width); None → ``nominal_roughness``.
        regions: optional ``[H, W]`` region ids for a per-region breakdown.
        min_angle_deg: floor of the acceptance angle.

    Returns:
        dict with ``coverage`` (highlight texels / observed texels), ``observed_texels``,
        ``highlight_texels``, ``criterion`` and, with regions, ``per_region`` {id: coverage}.
    """
    W, H = texture_size
    observed = torch.zeros(H * W, dtype=torch.bool)
    high = torch.zeros(H * W, dtype=torch.bool)
    if roughness is not None:
        theta = half_max_angle(roughness.reshape(-1))
    else:
        theta = half_max_angle(torch.full((H * W,), float(nominal_roughness)))
    theta = theta.clamp_min(math.radians(min_angle_deg))
    cos_t = torch.cos(theta)
    for prep in prepared:
        observed[texel_of(prep.uv.double(), H, W)] = True
        for term in prep.lights:
            tex = texel_of(prep.uv[term.local].double(), H, W)
            ok = term.angles.nh.reshape(-1).double() >= cos_t[tex]
            high[tex[ok]] = True
    n_obs = int(observed.sum())
    out = {
        "coverage": float((high & observed).sum()) / max(n_obs, 1),
        "observed_texels": n_obs,
        "highlight_texels": int((high & observed).sum()),
        "criterion": f"angle(n, h) <= max(GGX half-max angle of the texel's roughness, {min_angle_deg} deg)",
    }
    if regions is not None:
        r = regions.reshape(-1)
        out["per_region"] = {
            int(k): float((high & observed & (r == k)).sum()) / max(int((observed & (r == k)).sum()), 1)
            for k in torch.unique(r).tolist()
        }
    return out


#: Rays per block when :func:`render_scene` renders a view in blocks of pixels (bounded memory: ~1 KB per ray
#: through the G-buffer, the shadow rays and the shading).
RENDER_BLOCK_RAYS = 1 << 20


def render_scene(scene: Scene, config: SyntheticConfig, device="cpu") -> tuple[list[Tensor], list]:
    """Linear radiance images ``[H, W, 3]`` of every view, and the per-view pixel-centre :class:`Prepared`.

    Per view, blocks of pixels of at most :data:`RENDER_BLOCK_RAYS` rays: a G-buffer of ``config.supersample``²
    rays per pixel (jittered inside their strata with ``config.jitter``, seeded by ``config.seed`` and the view),
    :func:`renderer.shading.prepare` (shadow rays), :func:`renderer.shading.shade` with ``config.sampling``, and the
    box-filtered average per pixel (misses count as a black background). The returned ``Prepared`` are of the
    pixel centres (one ray per pixel), for statistics such as :func:`highlight_coverage`.

    ``device`` (:func:`renderer.device.resolve_device`): where the shading runs; the rays are cast on the CPU and the
    images are returned there. The CPU by default: a synthetic dataset is then the same, bit for bit, on every
    machine (the same photos on CUDA differ in the last bits).
    """
    from renderer.device import per_view, resolve_device

    dev = resolve_device(device)
    maps = {name: m.to(dev) for name, m in scene.maps.items()}
    k = config.supersample

    def one(vi: int) -> tuple[Tensor, object]:                 # one view: its photo and pixel-centre Prepared
        view = scene.views[vi]
        cam = view.camera
        g1 = render_gbuffer(scene.mesh, cam, 1)
        prep1 = prepare(g1, scene.mesh, view.lights, shadows=config.shadows)
        n_pix = cam.height * cam.width
        if k == 1:
            return g1.to_image(shade(scene.model, maps, prep1, sampling=config.sampling).cpu()), prep1
        # only pixels whose centre or a neighbour's hits the object can see it (an object thinner than a pixel
        # that no centre ray hits would be missed; the built-in meshes have none)
        hit = torch.zeros(n_pix)
        hit[g1.pixel] = 1.0
        near = F.max_pool2d(hit.reshape(1, 1, cam.height, cam.width), 3, stride=1, padding=1).reshape(-1) > 0
        todo = torch.nonzero(near).squeeze(-1)
        gen = torch.Generator().manual_seed(config.seed * 7919 + vi) if config.jitter else None
        step = max(1, RENDER_BLOCK_RAYS // (k * k))
        acc = torch.zeros(n_pix, 3)
        sub = torch.zeros(cam.height * k, cam.width * k, 3) if config.psf_sigma > 0 else None
        for start in range(0, len(todo), step):
            g = render_gbuffer(scene.mesh, cam, k, jitter=gen, pixels=todo[start:start + step])
            if len(g) == 0:
                continue
            prep = prepare(g, scene.mesh, view.lights, shadows=config.shadows)
            rad = shade(scene.model, maps, prep, sampling=config.sampling).cpu()
            if sub is None:
                acc.index_add_(0, g.pixel, rad.to(acc.dtype) * g.weight[:, None].to(acc.dtype))
            else:
                # the ray's stratum: its hit projected back (integer pixel centres: pixel x spans [x − ½, x + ½])
                xy, _ = cam.project(g.position.to(torch.float64))
                px, py = g.pixel % cam.width, g.pixel // cam.width
                sx = torch.minimum(torch.maximum(torch.floor((xy[:, 0] + 0.5) * k).long(), px * k), px * k + k - 1)
                sy = torch.minimum(torch.maximum(torch.floor((xy[:, 1] + 0.5) * k).long(), py * k), py * k + k - 1)
                sub[sy, sx] = rad.to(sub.dtype)
        if sub is not None:
            acc = _blur_strata(sub, config.psf_sigma * k, k).reshape(-1, 3)
        return acc.reshape(cam.height, cam.width, 3), prep1

    with torch.no_grad():
        # the views in parallel threads, one torch thread each (renderer.device.per_view): the same photos bit for
        # bit whatever the cores
        out = per_view(one, len(scene.views))
    images, preps = [o[0] for o in out], [o[1] for o in out]
    return images, preps


def _blur_strata(sub: Tensor, sigma: float, k: int) -> Tensor:
    """The image ``[H, W, 3]`` of a strata image ``[H·k, W·k, 3]``: a Gaussian blur of ``sigma`` strata (separable,
    cut at 4σ, black beyond the image), then the k × k box of each pixel."""
    r = max(1, math.ceil(4.0 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    w = (w / w.sum()).to(sub.dtype)
    img = sub.permute(2, 0, 1)[:, None]                                          # [3, 1, Hk, Wk]
    img = F.conv2d(img, w.view(1, 1, 1, -1), padding=(0, r))
    img = F.conv2d(img, w.view(1, 1, -1, 1), padding=(r, 0))
    return F.avg_pool2d(img, k)[:, 0].permute(1, 2, 0)


def make_synthetic(config: SyntheticConfig, out_dir, overwrite: bool = False, device="cpu") -> Path:
    """Render ``config`` and write it as a dataset folder with ground truth; return the folder. ``device``: where the
    shading runs (:func:`render_scene`).

    Steps: :func:`build_scene` → :func:`render_scene` → photo model per view (seeded
    ``config.seed·1000003 + i``) → :func:`capture.dataset.write_dataset` (atomic, validated).
    ``meta`` records the config, the highlight coverage, the clipped-pixel counts and the timings.
    """
    t0 = time.perf_counter()
    scene = build_scene(config)
    t1 = time.perf_counter()
    radiance, preps = render_scene(scene, config, device)
    t2 = time.perf_counter()
    images, clipped = [], []
    for i, rad in enumerate(radiance):
        gen = torch.Generator().manual_seed(config.seed * 1000003 + i)
        img, mask = config.photo.apply(rad, gen)
        images.append(img)
        clipped.append(int(mask.sum()))
    rough = scene.maps.get("roughness")
    cov = highlight_coverage(preps, config.texture_size, rough, scene.regions)
    gt = GroundTruth(
        model=scene.model_spec, maps=scene.maps, regions=scene.regions, region_names=dict(REGION_NAMES),
        render={"supersample": config.supersample, "jitter": config.jitter, "psf_sigma": config.psf_sigma,
                "sampling": config.sampling, "shadows": config.shadows},
        photo=config.photo.to_dict(),
    )
    meta = {
        "generator": "capture.synth.make_synthetic",
        "config": config.to_dict(),
        "highlight_coverage": cov,
        "clipped_pixels": clipped,
        "coverage_per_view": [p.gbuffer.coverage for p in preps],
        "seconds": {"build": t1 - t0, "render": t2 - t1},
    }
    photo = config.photo
    return write_dataset(out_dir, scene.mesh, scene.views, images, encoding=photo.encoding, bits=photo.bits,
                         saturation=photo.saturation, half=photo.half, gt=gt, meta=meta, overwrite=overwrite,
                         psf_sigma=float(config.psf_sigma))


# ----------------------------------------------------------------------------------------------
# presets


def default_scene(**overrides) -> SyntheticConfig:
    """The README demo's scene: a UV sphere, 16 views of 256×256 on two orbit rings, 256² maps,
    ``ggx-lambert`` (Lambert + GGX / Smith height-correlated / Schlick, materials.catalog), 2 flash point
    lights per view,
    noise-free linear EXR. ``overrides`` replace any :class:`SyntheticConfig` field."""
    cfg = SyntheticConfig(
        mesh="uv_sphere", n_views=16, image_size=256, texture_size=256,
        model="ggx-lambert",
        camera_rig="orbit", elevations=(15.0, 50.0), light_rig="flash", n_lights=2, photo=PhotoModel(),
        sampling="bilinear", seed=0,
    )
    return replace(cfg, **overrides) if overrides else cfg


def small_scene(model: str | dict = "ggx-lambert", *, image_size: int = 96, texture_size: int = 64,
                n_views: int = 4, mesh: str = "uv_sphere", **overrides) -> SyntheticConfig:
    """A cheap regression scene (well under 2 s to make): a coarse mesh, a few views of 64–128 px,
    64² maps, 2 flash lights per view, noise-free linear EXR. ``overrides`` replace any field."""
    mesh_options = {"uv_sphere": {"segments": 48, "rings": 24}, "sphere": {"segments": 48, "rings": 24},
                    "torus": {"segments": 48, "rings": 24}, "nonconvex": {"segments": 48, "detail": 12}}.get(mesh, {})
    cfg = dict(mesh=mesh, mesh_options=mesh_options, n_views=n_views, image_size=image_size,
               texture_size=texture_size, model=model, camera_rig="orbit", elevations=(15.0, 50.0),
               light_rig="flash", n_lights=2, photo=PhotoModel(), seed=0)
    cfg.update(overrides)
    return SyntheticConfig(**cfg)
