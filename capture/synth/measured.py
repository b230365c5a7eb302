"""Synthetic captures of *measured* materials (NBRDF fits of MERL).

Why
---
A synthetic scene rendered with one of our models only shows that the solver inverts the renderer. Here the
regions of the object are made of measured materials — the NBRDF networks of the MERL BRDFs
(:mod:`materials.measured`; results are "NBRDF fits of MERL", see that module for the data's attribution and
terms) — so the truth is no model of ours, and reconstructing with an analytic model shows how close its maps
and re-renders get to a real material.

Scene (:func:`make_measured_scene`)
-----------------------------------
The mesh, cameras and lights are built exactly as :mod:`capture.synth.scenes` builds them
(:func:`capture.synth.build_mesh`, :func:`~capture.synth.build_cameras`,
:func:`~capture.synth.build_lights`, from a :class:`~capture.synth.SyntheticConfig` whose ``model`` is
only a placeholder). The texture is split into K vertical stripes in u (:func:`region_map`, region ids 1..K, one
material per region, like the procedural stripes of :mod:`capture.synth.scenes`), so each region wraps around the
sphere and every camera of an orbit sees several. Per view: one G-buffer and one
:func:`renderer.shading.prepare` (shadow rays), then for each light ``E·V·f_r·cos θ_i`` with f_r from
``materials.get("measured", material=NAME).cosine_brdf`` evaluated, per region, on the samples whose *nearest
texel* lies in that region (one masked, vectorised call per region and light). Sampling is therefore "nearest":
a sample is made of exactly one material, and region borders are texel edges.

Default (:func:`measured_scene`): 4 regions (two-layer-silver, violet-rubber, nickel, red-fabric2), a 48×24
UV sphere, 12 views of 96×96 px on two orbit rings (15° and 50°), 2 flash point lights per view (irradiance 1 at
the centre, 20° off the camera), 64² texels, the ideal camera (noise-free linear EXR, no clipping).

Ground truth
------------
:class:`capture.dataset.GroundTruth` needs maps of one model; a measured material has no maps, and a scene of
four materials is no single model. So the dataset is written with ``gt=None`` and the truth goes into
``meta["measured"]``: the material per region id, the region map (``[T, T]`` ids, row 0 = top = v = 1, as nested
lists), the decoder options and the attribution. :func:`read_truth` reads it back.

How well the analytic models recover these materials: :mod:`capture.bench.measured`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor

import materials
from renderer.gbuffer import render_gbuffer
from renderer.shading import prepare
from renderer.texture import texel_centers

from ..dataset import View, load_dataset, write_dataset
from .scenes import SyntheticConfig, build_cameras, build_lights, build_mesh

__all__ = [
    "DEFAULT_MATERIALS", "MeasuredSceneConfig", "MeasuredSceneError", "region_map", "measured_scene",
    "render_measured", "render_measured_scene", "make_measured_scene", "read_truth",
]

#: The four materials of Nielsen et al.'s Figure 1, one region each by default.
DEFAULT_MATERIALS = ("two-layer-silver", "violet-rubber", "nickel", "red-fabric2")
ATTRIBUTION = ("NBRDF fits (Sztrajman et al., CGF 2021) of the MERL BRDFs (Matusik et al. 2003; CC-BY-SA-4.0, "
               "\"Created by Mitsubishi Electric Research Laboratories (MERL), 2003, 2007, 2023\")")


class MeasuredSceneError(ValueError):
    """An invalid measured-scene configuration or dataset (the message names the field and the fix)."""


@dataclass
class MeasuredSceneConfig:
    """A capture of an object whose regions are measured materials (module docstring).

    Attributes:
        materials: MERL names, one region each (ids 1..K in this order); 1 to 255 names.
        mesh, mesh_options, n_views, image_size, texture_size, camera_rig, elevations, fov_y_deg, distance,
            light_rig, n_lights, light_offset_deg, light_irradiance, shadows, seed: as in
            :class:`capture.synth.SyntheticConfig` (pixels, degrees, world units, W/m²).
        max_theta_deg: the decoder's mask (90 = none; 80 drops MERL's unreliable grazing angles).
        symmetric: evaluate the decoder reciprocally (mean of φ_d and π − φ_d).
    """

    materials: tuple[str, ...] = DEFAULT_MATERIALS
    mesh: str = "uv_sphere"
    mesh_options: dict = field(default_factory=lambda: {"segments": 48, "rings": 24})
    n_views: int = 12
    image_size: int | tuple[int, int] = 96
    texture_size: int | tuple[int, int] = 64
    camera_rig: str = "orbit"
    elevations: tuple[float, ...] = (15.0, 50.0)
    fov_y_deg: float = 40.0
    distance: float | None = None
    light_rig: str = "flash"
    n_lights: int = 2
    light_offset_deg: float = 20.0
    light_irradiance: float = 1.0
    shadows: bool = True
    seed: int = 0
    max_theta_deg: float = 90.0
    symmetric: bool = False

    def __post_init__(self):
        if isinstance(self.materials, str):
            self.materials = (self.materials,)
        self.materials = tuple(self.materials)
        if not 1 <= len(self.materials) <= 255 or not all(isinstance(m, str) for m in self.materials):
            raise MeasuredSceneError(f"materials must be 1 to 255 MERL names, got {self.materials!r}")
        if len(set(self.materials)) != len(self.materials):
            raise MeasuredSceneError(f"materials must be distinct (one region each), got {self.materials!r}")
        self.models()  # unknown names / missing weights fail here, before any rendering
        self.geometry()  # and so do bad geometry fields (SyntheticError names the field)

    def geometry(self) -> SyntheticConfig:
        """The :class:`~capture.synth.SyntheticConfig` of the mesh/camera/light fields (model: placeholder)."""
        return SyntheticConfig(
            mesh=self.mesh, mesh_options=dict(self.mesh_options), n_views=self.n_views, image_size=self.image_size,
            texture_size=self.texture_size, model="lambert", camera_rig=self.camera_rig,
            elevations=self.elevations, fov_y_deg=self.fov_y_deg, distance=self.distance, light_rig=self.light_rig,
            n_lights=self.n_lights, light_offset_deg=self.light_offset_deg,
            light_irradiance=self.light_irradiance, sampling="nearest", shadows=self.shadows, seed=self.seed)

    def models(self) -> list[materials.Model]:
        """One ``measured`` model per material (raises :class:`MeasuredSceneError` naming an unknown one)."""
        try:
            return [materials.get("measured", material=m, max_theta_deg=self.max_theta_deg,
                                  symmetric=self.symmetric) for m in self.materials]
        except FileNotFoundError as exc:
            raise MeasuredSceneError(str(exc)) from None
        except ValueError as exc:
            raise MeasuredSceneError(f"materials: {exc}") from None


def measured_scene(**overrides) -> MeasuredSceneConfig:
    """The default measured scene (module docstring); ``overrides`` replace any field."""
    return MeasuredSceneConfig(**overrides)


def region_map(n_regions: int, size: int | tuple[int, int]) -> Tensor:
    """Region ids ``[H, W]`` int64 in 1..K: K vertical stripes of equal width in u (texel centres).

    Args:
        n_regions: K ≥ 1.
        size: ``T`` or ``(W, H)`` texels.
    """
    if isinstance(n_regions, bool) or not isinstance(n_regions, int) or n_regions < 1:
        raise MeasuredSceneError(f"region_map: n_regions must be a positive integer, got {n_regions!r}")
    W, H = (size, size) if isinstance(size, int) else tuple(size)
    if min(W, H) < 1:
        raise MeasuredSceneError(f"region_map: size must be positive, got {size!r}")
    u = texel_centers(H, W, dtype=torch.float64)[..., 0]
    return torch.clamp(torch.floor(u * n_regions), 0, n_regions - 1).long() + 1


def render_measured(prepared, regions: Tensor, models: Sequence[materials.Model]) -> Tensor:
    """Radiance ``[N, 3]`` of one prepared view (0 where no light reaches), W/(m²·sr) for W/m² irradiance.

    Args:
        prepared: :class:`renderer.shading.Prepared` of the view.
        regions: ``[H, W]`` ids 1..K; the sample's material is ``models[id − 1]`` at its nearest texel.
        models: K BRDF models without parameters (e.g. ``measured``), each evaluated once per light on the
            samples of its region (a masked, vectorised call).
    """
    if not isinstance(regions, Tensor) or regions.dim() != 2 or regions.is_floating_point():
        raise MeasuredSceneError("render_measured: regions must be an integer tensor [H, W]")
    K = len(models)
    if int(regions.min()) < 1 or int(regions.max()) > K:
        raise MeasuredSceneError(f"render_measured: region ids must lie in 1..{K} (one per model), got "
                                 f"{int(regions.min())}..{int(regions.max())}")
    H, W = regions.shape
    tex, _ = prepared.texels(H, W, "nearest")
    rid = regions.reshape(-1).to(tex.device)[tex]  # [S] region of each kept sample
    dtype, dev = prepared.n.dtype, prepared.n.device
    out = torch.zeros(prepared.n_samples, 3, dtype=dtype, device=dev)
    for term in prepared.lights:
        r = rid[term.local]
        for k, model in enumerate(models):
            sel = torch.nonzero(r == k + 1).squeeze(-1)
            if len(sel) == 0:
                continue
            f = model.cosine_brdf(term.angles[sel], {})
            out = out.index_add(0, term.index[sel], term.irradiance[sel] * f)
    return out


def make_measured_scene(config: MeasuredSceneConfig | None = None, out_dir=None, *, overwrite: bool = False,
                        views: Sequence[int] | None = None) -> Path:
    """Render ``config`` (default :func:`measured_scene`) and write it as a dataset folder; return the folder.

    Args:
        config: the scene.
        out_dir: the dataset folder (required).
        overwrite: replace an existing folder.
        views: indices of the views to write (default all) — e.g. the training views of a held-out split.
    Returns:
        The folder. ``gt`` is absent; ``meta["measured"]`` holds the truth (module docstring).
    """
    config = config or measured_scene()
    if not isinstance(config, MeasuredSceneConfig):
        raise MeasuredSceneError(f"config must be a MeasuredSceneConfig, got {type(config).__name__}")
    if out_dir is None:
        raise MeasuredSceneError("make_measured_scene: out_dir is required (the dataset folder to write)")
    t0 = time.perf_counter()
    images, all_views, preps, mesh, regions = render_measured_scene(config)
    keep = list(range(len(all_views))) if views is None else [int(i) for i in views]
    if not keep or any(not 0 <= i < len(all_views) for i in keep):
        raise MeasuredSceneError(f"views must be indices in 0..{len(all_views) - 1}, got {views!r}")
    meta = {
        "generator": "capture.synth.make_measured_scene",
        "config": asdict(config),
        "views_written": keep,
        "measured": {
            "materials": {str(k + 1): m for k, m in enumerate(config.materials)},
            "regions": regions,
            "sampling": "nearest",
            "decoder": {"model": "measured", "max_theta_deg": config.max_theta_deg, "symmetric": config.symmetric},
            "attribution": ATTRIBUTION,
        },
        "coverage_per_view": [preps[i].gbuffer.coverage for i in keep],
        "seconds": {"build_and_render": time.perf_counter() - t0},
    }
    return write_dataset(out_dir, mesh, [all_views[i] for i in keep], [images[i] for i in keep], encoding="linear",
                         gt=None, meta=meta, overwrite=overwrite)


def render_measured_scene(config: MeasuredSceneConfig):
    """Every view of ``config`` rendered, nothing written: ``(images, views, prepared, mesh, regions)`` — the linear
    radiance images ``[H, W, 3]``, the :class:`capture.dataset.View` s, each view's
    :func:`renderer.shading.prepare` result, the mesh and the region map (:func:`region_map`)."""
    geo = config.geometry()
    mesh = build_mesh(geo.mesh, geo.mesh_options)
    cams, rots = build_cameras(geo, mesh)
    lights = build_lights(geo, mesh, cams, rots)
    models = config.models()
    regions = region_map(len(config.materials), geo.texture_size)
    views = [View(c, ls, 1.0) for c, ls in zip(cams, lights, strict=True)]
    images, preps = [], []
    with torch.no_grad():
        for view in views:
            g = render_gbuffer(mesh, view.camera, 1)
            prep = prepare(g, mesh, view.lights, shadows=config.shadows)
            images.append(g.to_image(render_measured(prep, regions, models)))
            preps.append(prep)
    return images, views, preps, mesh, regions


def read_truth(dataset) -> tuple[Tensor, dict[int, str]]:
    """``(regions [T, T] int64, {region id: material})`` of a dataset written by :func:`make_measured_scene`.

    Args:
        dataset: a folder or a loaded :class:`capture.dataset.Dataset`.
    """
    ds = load_dataset(dataset) if isinstance(dataset, (str, Path)) else dataset
    info = (ds.meta or {}).get("measured") if hasattr(ds, "meta") else None
    if not isinstance(info, Mapping) or "regions" not in info or "materials" not in info:
        raise MeasuredSceneError("dataset has no meta.measured block (regions + materials); write it with "
                                 "capture.synth.make_measured_scene")
    return torch.tensor(info["regions"], dtype=torch.long), {int(k): v for k, v in info["materials"].items()}
