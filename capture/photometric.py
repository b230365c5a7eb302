"""Photometric help for real captures: light intensities from a known-albedo region, and HDR from brackets.

:func:`calibrate_lights` estimates each light's intensity (RGB, in the dataset's units: W/sr for a point light,
W/m² for a directional one, with metres) from pixels whose diffuse albedo is known — a grey card, or a region of
the object's surface given in UV space. The region is treated as **Lambertian**: its radiance is

    L_c(pixel) = ρ_c/π · Σ_l I_{l,c} · max(n·l, 0) · V_l / d_l²          (point lights; E_l = I_l/d_l²)

box-filtered over the pixel, which is linear in the intensities I. The geometric factor of each light — the
pixel's radiance under that light at unit intensity — is computed by the renderer itself
(:func:`renderer.gbuffer.render_gbuffer` → :func:`renderer.shading.prepare` → :func:`renderer.shading.shade`
with the ``lambert`` model and the known albedo; no shading is re-implemented here). Stacking every usable
region pixel of every photo gives, per channel, a linear system solved by non-negative least squares
(:func:`scipy.optimize.nnls`). Environment lights (hemisphere, SH) are held at their declared values: their
Lambertian contribution is subtracted from the photos first.

:func:`merge_hdr` merges bracketed exposures into one linear radiance image (a weighted average of
value / time, see its docstring), or, for 8-bit brackets of unknown response, runs OpenCV's Debevec
calibration and merge.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from materials import Model
from materials import get as get_model
from renderer.gbuffer import GBuffer, render_gbuffer
from renderer.imageio import ImageIOError, read_exr, read_raster
from renderer.lights import DirectionalLight, Environment, PointLight
from renderer.mesh import Mesh
from renderer.shading import prepare, shade
from renderer.texture import texel_of

from .dataset import SCENE_FILE, Dataset, DatasetWarning, Photo, View, load_dataset, scene_json_text
from .outputs import atomic_folder, check_output, jsonable

__all__ = ["CalibrationError", "HDRWarning", "UVRegion", "LightEstimate", "Calibration", "calibrate_lights",
           "write_calibrated", "HDRResult", "merge_hdr", "hat_weight", "SHARE_MODES", "RESPONSES"]

#: How lights are identified across photos: "index" — light j of every photo is the same physical light (a
#: flash, a studio lamp listed in the same place); "each" — every ``images[i].lights[j]`` entry is its own light;
#: "all" — the lights are identical up to their declared ratios: one scale per channel multiplies every declared
#: intensity.
SHARE_MODES = ("index", "each", "all")
#: Camera responses :func:`merge_hdr` understands (see its docstring).
RESPONSES = ("auto", "linear", "srgb", "estimate")
_MASK_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".exr")


class CalibrationError(ValueError):
    """Calibration or merge inputs that cannot give an answer; the message names the problem and the fix."""


class HDRWarning(UserWarning):
    """An HDR merge whose result is approximate (the camera response was estimated from the brackets)."""


# ----------------------------------------------------------------------------------------------
# light calibration


@dataclass
class UVRegion:
    """A known-albedo region on the mesh, in texture space.

    Attributes:
        mask: ``[H, W]`` bool (array, tensor, or the path of a PNG: nonzero = in the region), row 0 = the top of
            the map (v = 1), as every shadecap map. A pixel is used when all its rays hit texels of the region.
    """

    mask: object

    @classmethod
    def from_texels(cls, texels, size: tuple[int, int]) -> UVRegion:
        """A region from flat texel indices ``i·W + j`` of a ``size = (W, H)`` map."""
        W, H = size
        idx = np.asarray(texels, dtype=np.int64).reshape(-1)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= W * H:
            raise CalibrationError(f"UVRegion.from_texels: texel indices must be a non-empty set in [0, {W * H}) "
                                   f"for a {W}×{H} map")
        m = np.zeros(H * W, dtype=bool)
        m[idx] = True
        return cls(m.reshape(H, W))

    def tensor(self) -> Tensor:
        m = self.mask
        if isinstance(m, (str, os.PathLike)):
            m = _read_mask_file(Path(m), "the UV mask")
        m = torch.as_tensor(np.asarray(m.detach().cpu() if isinstance(m, Tensor) else m))
        if m.dim() == 3 and m.shape[2] in (1, 3, 4):
            m = (m[..., :3] != 0).any(-1)
        if m.dim() != 2 or m.numel() == 0:
            raise CalibrationError(f"UVRegion: the mask must be [H, W] (row 0 = v = 1), got shape {tuple(m.shape)}; "
                                   "give a 2-D array or a gray PNG of the texture's size")
        m = m != 0
        if not bool(m.any()):
            raise CalibrationError("UVRegion: the mask selects no texel; mark the known-albedo texels nonzero")
        return m


@dataclass
class LightEstimate:
    """One calibrated light (or group of lights, see :data:`SHARE_MODES`).

    Attributes:
        label: which entries it is (``images[*].lights[1]``, ``images[3].lights[0]``, ``all lights``).
        field: "intensity" (point, W/sr) or "irradiance" (directional, W/m²).
        declared: ``[3]`` the value in the dataset before calibration (first entry of the group).
        estimate: ``[3]`` the calibrated value.
        stderr: ``[3]`` its standard error (heteroscedasticity-consistent, from the residuals; photo noise only).
        residual: RMS residual over the pixels this light reaches, relative to their mean radiance.
        pixels: usable region pixels this light reaches.
        scale: ``[3]`` estimate / declared (nan where declared is 0).
    """

    label: str
    field: str
    declared: list
    estimate: list
    stderr: list
    residual: float
    pixels: int
    scale: list

    def to_dict(self) -> dict:
        return jsonable(self.__dict__)


@dataclass
class Calibration:
    """The result of :func:`calibrate_lights`.

    Attributes:
        lights: one :class:`LightEstimate` per unknown.
        values: per view, per light, the calibrated ``[3]`` value (None for environment lights, unchanged).
        share: the :data:`SHARE_MODES` entry used.
        albedo: ``[3]`` the region's known albedo.
        pixels: usable region pixels (rows of the system, per channel); views: photos that contributed.
        residual_rms: ``[3]`` RMS residual (radiance units); relative_residual: ``[3]`` that over the mean radiance.
        out: the written dataset, when one was written.
    """

    lights: list[LightEstimate]
    values: list[list]
    share: str
    albedo: list
    pixels: int
    views: int
    residual_rms: list
    relative_residual: list
    out: Path | None = None
    meta: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return jsonable({"method": "lambertian known-albedo region, non-negative least squares per channel",
                         "share": self.share, "albedo": self.albedo, "pixels": self.pixels, "views": self.views,
                         "residual_rms": self.residual_rms, "relative_residual": self.relative_residual,
                         "lights": [e.to_dict() for e in self.lights], **self.meta})

    def summary(self) -> str:
        f3 = lambda v: "(" + ", ".join(f"{x:.5g}" for x in v) + ")"  # noqa: E731
        lines = [f"calibrated {len(self.lights)} light(s) from {self.pixels} region pixel(s) in {self.views} photo(s) "
                 f"(albedo {f3(self.albedo)}, share '{self.share}'); relative residual "
                 f"{f3(self.relative_residual)}"]
        for e in self.lights:
            lines.append(f"  {e.label}: {e.field} {f3(e.estimate)} ± {f3(e.stderr)} (declared {f3(e.declared)}, "
                         f"×{f3(e.scale)}), {e.pixels} px, residual {e.residual:.3g}")
        return "\n".join(lines)


def _read_mask_file(path: Path, what: str) -> np.ndarray:
    try:
        if path.suffix.lower() == ".exr":
            arr = read_exr(path).numpy()
        else:
            arr, _ = read_raster(path)
    except ImageIOError as exc:
        raise CalibrationError(f"{path}: unreadable {what} ({exc}); write it as a gray PNG, nonzero = in the "
                               "region") from None
    return (arr[..., :3] != 0).any(-1) if arr.ndim == 3 else arr != 0


def _image_masks(region, ds: Dataset) -> list[Tensor | None]:
    """Per view the card mask ``[H, W]`` bool or None (view not used)."""
    n = len(ds.views)
    if isinstance(region, (str, os.PathLike)):
        folder = Path(region)
        if not folder.is_dir():
            raise CalibrationError(f"{folder}: the card-mask folder does not exist; give a folder of masks named like "
                                   "the photos (images/000.exr → 000.png), or a UVRegion")
        masks, expected = [], []
        for v in ds.views:
            stem = Path(v.file).stem
            found = [folder / (stem + s) for s in _MASK_SUFFIXES if (folder / (stem + s)).is_file()]
            expected.append(stem + ".png")
            masks.append(found[0] if found else None)
        if all(m is None for m in masks):
            raise CalibrationError(f"{folder}: no card mask found; name each like its photo's file stem, e.g. "
                                   f"{', '.join(expected[:3])} (nonzero = the card)")
        region = masks
    if isinstance(region, (np.ndarray, Tensor)) and getattr(region, "ndim", 0) == 2:
        raise CalibrationError("calibrate_lights: a single 2-D mask is ambiguous; give one mask per photo (a list, "
                               "None where the card is not seen) or wrap a texture-space mask as UVRegion(mask)")
    if not isinstance(region, Sequence) or isinstance(region, str):
        raise CalibrationError(f"calibrate_lights: region must be a folder of card masks, a list of per-photo masks "
                               f"or a UVRegion, got {type(region).__name__}")
    if len(region) != n:
        raise CalibrationError(f"calibrate_lights: {len(region)} card mask(s) for {n} photos; give one per photo "
                               "(None where the card is not seen)")
    out = []
    for i, (m, v) in enumerate(zip(region, ds.views, strict=True)):
        if m is None:
            out.append(None)
            continue
        if isinstance(m, (str, os.PathLike)):
            m = _read_mask_file(Path(m), f"card mask of images[{i}]")
        t = torch.as_tensor(np.asarray(m.detach().cpu() if isinstance(m, Tensor) else m))
        if t.dim() == 3:
            t = (t != 0).any(-1)
        if tuple(t.shape) != (v.camera.height, v.camera.width):
            raise CalibrationError(f"card mask of images[{i}] is {tuple(t.shape)} but the photo is "
                                   f"{v.camera.height}×{v.camera.width} (H×W); write the mask at the photo's size")
        out.append(t != 0)
    return out


def _albedo(albedo) -> Tensor:
    try:
        a = torch.as_tensor(albedo, dtype=torch.float64).reshape(-1)
    except (TypeError, ValueError, RuntimeError):
        a = torch.zeros(0)
    if a.numel() == 1:
        a = a.expand(3).clone()
    if a.numel() != 3 or not torch.isfinite(a).all() or (a <= 0).any() or (a > 1).any():
        raise CalibrationError(f"albedo must be the region's diffuse albedo, one number or R,G,B in (0, 1] (a grey "
                               f"card is 0.18), got {albedo!r}")
    return a


def _unit(light):
    if isinstance(light, PointLight):
        return PointLight(light.position, 1.0), "intensity", light.intensity
    return DirectionalLight(light.direction, 1.0), "irradiance", light.irradiance


class _Shading(NamedTuple):
    """What the region's predicted radiance is rendered with: the mesh, Lambert at the known albedo, k×k rays."""

    mesh: Mesh
    lambert: Model
    amap: dict[str, Tensor]
    supersample: int
    shadows: bool


@dataclass
class _Unknowns:
    """The system's unknowns, in order of appearance: one per light or group of lights (:data:`SHARE_MODES`)."""

    share: str
    keys: list[tuple] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    declared: list[Tensor] = field(default_factory=list)
    first: dict[tuple, int] = field(default_factory=dict)

    def index(self, i: int, j: int, fld: str, value: Tensor) -> int:
        """The unknown of ``images[i].lights[j]`` (a ``fld`` light declared at ``value``), added when new."""
        share = self.share
        key = {"index": ("index", j), "each": ("entry", i, j), "all": ("all",)}[share]
        if key not in self.first:
            self.first[key] = len(self.keys)
            self.keys.append(key)
            self.labels.append({"index": f"images[*].lights[{j}]", "each": f"images[{i}].lights[{j}]",
                                "all": "all lights"}[share])
            self.kinds.append(fld)
            self.declared.append(value)
        u = self.first[key]
        if self.kinds[u] != fld and share != "all":
            kind = "point" if fld == "intensity" else "directional"
            raise CalibrationError(f"images[{i}].lights[{j}] is a {kind} light but {self.labels[u]} is not in the "
                                   f"other photos; with share='index' light j "
                                   "must be the same light in every photo — use share='each'")
        return u


class _ViewRows(NamedTuple):
    """One photo's rows of the system: region radiance less the environment's ``y`` [p, 3], and per unknown
    its column [p, 3]."""

    y: Tensor
    cols: list[tuple[int, Tensor]]


def _region_pixels(g: GBuffer, photo: Photo, sel: Tensor, uv_mask: Tensor | None, k: int) -> Tensor:
    """``sel`` narrowed to pixels whose rays all hit the mesh (and, with ``uv_mask``, all land in the region),
    neither clipped nor non-finite in the photo."""
    n = sel.shape[0]
    full = g.pixel_weight().reshape(-1) >= 1 - 1e-6
    sel &= full & ~photo.unusable.reshape(-1).cpu() & ~photo.nonfinite.reshape(-1).cpu()
    if uv_mask is not None:
        H, W = uv_mask.shape
        inside = uv_mask.reshape(-1)[texel_of(g.uv.double(), H, W)].double()
        count = torch.zeros(n, dtype=torch.float64).index_add(0, g.pixel, inside)
        sel &= count >= k * k - 0.5
    return sel


def _unit_radiance(shading: _Shading, g: GBuffer, unit, n: int) -> tuple[Tensor, Tensor]:
    """Each pixel's Lambertian radiance under the unit-level light ``unit`` [n, 3], and how many of its rays the
    light reaches [n]."""
    prep = prepare(g, shading.mesh, [unit], shadows=shading.shadows)
    col = g.to_image(shade(shading.lambert, shading.amap, prep)).reshape(-1, 3).double()
    reached = torch.zeros(n, dtype=torch.float64)
    for term in prep.lights:
        reached.index_add_(0, g.pixel[term.index], torch.ones(len(term.index), dtype=torch.float64))
    return col, reached


def _view_rows(shading: _Shading, i: int, view: View, photo: Photo, card: Tensor | None, uv_mask: Tensor | None,
               unknowns: _Unknowns, entry: list) -> _ViewRows | None:
    """Photo ``i``'s rows; sets ``entry[j]`` to (unknown, declared value) of each light it calibrates. ``card``:
    its card mask, or None with a UV region. None when no region pixel or no calibrated light is usable."""
    cam = view.camera
    k = shading.supersample
    n = cam.height * cam.width
    sel = torch.ones(n, dtype=torch.bool)
    if card is not None:
        sel &= card.reshape(-1)
    g = render_gbuffer(shading.mesh, cam, k)
    sel = _region_pixels(g, photo, sel, uv_mask, k)
    cols, offset = [], torch.zeros(n, 3, dtype=torch.float64)
    envs = [lt for lt in view.lights if isinstance(lt, Environment)]
    if envs:
        prep = prepare(g, shading.mesh, envs, shadows=shading.shadows)
        offset = g.to_image(shade(shading.lambert, shading.amap, prep)).reshape(-1, 3).double()
    for j, light in enumerate(view.lights):
        if isinstance(light, Environment):
            continue
        unit, fld, value = _unit(light)
        col, reached = _unit_radiance(shading, g, unit, n)
        sel &= (reached < 0.5) | (reached > k * k - 0.5)  # all of the pixel's rays, or none
        u = unknowns.index(i, j, fld, value.double())
        if unknowns.share == "all":
            col = col * value.double()  # the unknown is a scale of the declared value
        entry[j] = (u, value.double())
        cols.append((u, col))
    idx = torch.nonzero(sel).squeeze(-1)
    if len(idx) == 0 or not cols:
        return None
    y = photo.radiance.reshape(-1, 3).double()[idx] - offset[idx]
    return _ViewRows(y, [(u, c[idx]) for u, c in cols])


def _assemble(rows: Sequence[_ViewRows], labels: Sequence[str], min_pixels: int) -> tuple[Tensor, Tensor]:
    """The stacked system ``A`` [P, U, 3], ``Y`` [P, 3]; refuses too few pixels and lights never seen lit."""
    U = len(labels)
    if U == 0:
        raise CalibrationError("calibrate_lights: the photos have no point or directional light to calibrate "
                               "(environment lights are held at their declared values)")
    P = sum(len(r.y) for r in rows)
    if P < max(min_pixels, U + 1):
        raise CalibrationError(f"calibrate_lights: only {P} usable region pixel(s) (need ≥ {max(min_pixels, U + 1)}): "
                               "the region must be seen, fully covered by the mesh, unsaturated and lit; enlarge the "
                               "card masks, check they match the photos, or lower min_pixels")
    A = torch.zeros(P, U, 3, dtype=torch.float64)
    Y = torch.cat([r.y for r in rows])
    r0 = 0
    for y, cols in rows:
        for u, c in cols:
            A[r0:r0 + len(y), u] += c
        r0 += len(y)
    return A, Y


def _check_identifiable(A: Tensor, lit: Tensor, labels: Sequence[str]) -> None:
    """Every unknown lights some pixel, and no two light the region in the same proportions."""
    U = len(labels)
    dark = [labels[u] for u in range(U) if not bool(lit[:, u].any())]
    if dark:
        raise CalibrationError(
            f"calibrate_lights: {', '.join(dark)} never light(s) a usable region pixel in any photo (the region faces "
            f"away, is shadowed, or is not seen where they shine): their intensity cannot be measured; photograph the "
            f"card where each light reaches it, declare the lights identical (share='all'), or remove those lights")
    # lights whose contributions are proportional cannot be separated
    for c in range(3):
        An = A[..., c] / A[..., c].norm(dim=0).clamp_min(1e-300)
        s = torch.linalg.svdvals(An)
        if float(s[-1] / s[0]) < 1e-6:
            corr = An.T @ An
            corr.fill_diagonal_(-1)
            a, b = divmod(int(torch.argmax(corr)), U)
            raise CalibrationError(
                f"calibrate_lights: {labels[a]} and {labels[b]} light the region in the same proportions in every "
                f"photo, so their intensities cannot be told apart (condition {float(s[0] / s[-1]):.3g}); add photos "
                f"where they light it differently, or declare them identical (share='all')")


def _solve(A: Tensor, Y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per channel non-negative least squares: estimates [U, 3], their standard errors [U, 3], residuals [P, 3]."""
    from scipy.optimize import nnls

    P, U = A.shape[:2]
    est = torch.zeros(U, 3, dtype=torch.float64)
    se = torch.zeros(U, 3, dtype=torch.float64)
    res = torch.zeros(P, 3, dtype=torch.float64)
    for c in range(3):
        a, y = A[..., c], Y[:, c]
        norm = a.norm(dim=0)
        x, _ = nnls((a / norm).numpy(), y.numpy())
        x = torch.from_numpy(x) / norm
        est[:, c] = x
        r = y - a @ x
        res[:, c] = r
        # heteroscedasticity-consistent (HC1) covariance: photo noise grows with the signal
        inv = torch.linalg.inv(a.T @ a)
        meat = (a * (r * r)[:, None]).T @ a
        cov = inv @ meat @ inv * (P / max(P - U, 1))
        se[:, c] = cov.diagonal().clamp_min(0).sqrt()
    return est, se, res


def _light_estimates(unknowns: _Unknowns, est: Tensor, se: Tensor, res: Tensor, Y: Tensor,
                     lit: Tensor) -> list[LightEstimate]:
    share = unknowns.share
    lights = []
    for u in range(len(unknowns.keys)):
        m = lit[:, u]
        rel = float(res[m].pow(2).mean().sqrt() / Y[m].mean().abs().clamp_min(1e-300))
        dec = unknowns.declared[u]
        value = est[u] * dec if share == "all" else est[u]
        err = se[u] * dec if share == "all" else se[u]
        scale = [float(v / d) if d > 0 else math.nan for v, d in zip(value.tolist(), dec.tolist(), strict=True)]
        lights.append(LightEstimate(unknowns.labels[u], unknowns.kinds[u], dec.tolist(), value.tolist(),
                                    err.tolist(), rel, int(m.sum()), scale))
    return lights


def calibrate_lights(dataset, region, albedo, *, share: str = "index", supersample: int = 4, shadows: bool = True,
                     min_pixels: int = 20, out=None, overwrite: bool = False) -> Calibration:
    """Estimate the lights' intensities from a region of known diffuse albedo seen in the photos.

    Args:
        dataset: a :class:`capture.dataset.Dataset` or its folder.
        region: the known-albedo pixels — a folder of card masks named like the photos (``images/000.exr`` →
            ``000.png``; nonzero = card; photos without one are not used), a list of per-photo masks (arrays or
            files, None for none), or a :class:`UVRegion` (texels on the mesh). The region must be part of the
            mesh: its geometry comes from the G-buffer.
        albedo: the region's diffuse albedo, a number (0.18 for a grey card) or R,G,B, linear.
        share: :data:`SHARE_MODES`.
        supersample: k×k rays per pixel for the predicted radiance (pixels the rays do not all hit — silhouette
            — and pixels a light reaches with only some of its rays — terminator, shadow edges — are skipped).
        shadows: cast shadow rays (V_l).
        min_pixels: fewest usable region pixels accepted.
        out: when given, write the dataset with the calibrated values there (:func:`write_calibrated`).
        overwrite: replace an existing ``out``.

    Returns:
        :class:`Calibration`.

    Raises:
        CalibrationError: bad inputs; too few usable pixels; a light that never lights a usable region pixel; lights
            whose contributions cannot be told apart.
    """
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    if share not in SHARE_MODES:
        raise CalibrationError(f"share must be one of {SHARE_MODES} (index: light j of every photo is one light; "
                               f"each: every entry its own; all: one scale for every light), got {share!r}")
    if isinstance(supersample, bool) or not isinstance(supersample, int) or not 1 <= supersample <= 8:
        raise CalibrationError(f"supersample must be an integer in 1..8, got {supersample!r}")
    rho = _albedo(albedo)
    if out is not None:
        check_output(out, {ds.root: "the dataset folder"}, force=overwrite, error=CalibrationError,
                     force_flag="overwrite=True (--overwrite)")
    uv_mask = region.tensor() if isinstance(region, UVRegion) else None
    masks = None if uv_mask is not None else _image_masks(region, ds)
    lambert = get_model("lambert")
    amap = {"albedo": rho.to(torch.get_default_dtype()).reshape(1, 1, 3)}
    photos = ds.load_images()
    k = supersample
    shading = _Shading(ds.mesh, lambert, amap, k, shadows)

    unknowns = _Unknowns(share)
    rows: list[_ViewRows] = []                    # per view with usable pixels: y [P_view, 3], columns
    entry_unknown: list[list] = []
    for i, (view, photo) in enumerate(zip(ds.views, photos, strict=True)):
        entry_unknown.append([None] * len(view.lights))
        if masks is not None and masks[i] is None:
            continue
        card = masks[i] if masks is not None else None
        view_rows = _view_rows(shading, i, view, photo, card, uv_mask, unknowns, entry_unknown[i])
        if view_rows is not None:
            rows.append(view_rows)
    used_views = len(rows)
    A, Y = _assemble(rows, unknowns.labels, min_pixels)
    P = len(Y)
    lit = (A > 0).any(-1)                    # [P, U]
    _check_identifiable(A, lit, unknowns.labels)
    est, se, res = _solve(A, Y)
    mean_y = Y.mean(0).abs().clamp_min(1e-300)
    rms = res.pow(2).mean(0).sqrt()
    lights = _light_estimates(unknowns, est, se, res, Y, lit)
    values = []
    for row in entry_unknown:
        values.append([None if e is None else ((est[e[0]] * e[1]) if share == "all" else est[e[0]]).tolist()
                       for e in row])
    cal = Calibration(lights, values, share, rho.tolist(), P, used_views, rms.tolist(), (rms / mean_y).tolist(),
                      meta={"region": "uv" if uv_mask is not None else "image masks", "supersample": k})
    if out is not None:
        cal.out = write_calibrated(ds, cal, out, overwrite=overwrite)
    return cal


def write_calibrated(dataset, calibration: Calibration, out, *, overwrite: bool = False) -> Path:
    """Copy ``dataset`` to the new folder ``out`` with the calibrated intensities; the input is untouched.

    Every file is copied as it is; ``scene.json`` gets the calibrated ``intensity`` (point) / ``irradiance``
    (directional) of each light entry (positions and frames unchanged) and ``meta.photometric_calibration``
    (:meth:`Calibration.to_dict`). Written atomically (:func:`capture.outputs.atomic_folder`) and validated with
    :func:`capture.dataset.load_dataset` before it is moved in place.
    """
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    if not isinstance(calibration, Calibration) or len(calibration.values) != len(ds.views):
        raise CalibrationError("write_calibrated: calibration must be calibrate_lights' result for this dataset")
    out = check_output(out, {ds.root: "the dataset folder"}, force=overwrite, error=CalibrationError,
                       force_flag="overwrite=True (--overwrite)")
    doc = json.loads((ds.root / SCENE_FILE).read_text(encoding="utf-8"))
    for entry, vals in zip(doc["images"], calibration.values, strict=True):
        for light, v in zip(entry["lights"], vals, strict=True):
            if v is None:
                continue
            light["intensity" if light.get("type") == "point" else "irradiance"] = [float(x) for x in v]
    meta = doc.get("meta") if isinstance(doc.get("meta"), dict) else {}
    meta["photometric_calibration"] = calibration.to_dict()
    doc["meta"] = meta
    with atomic_folder(out, force=overwrite, error=CalibrationError, force_flag="overwrite=True (--overwrite)") as tmp:
        shutil.copytree(ds.root, tmp, symlinks=True, dirs_exist_ok=True)
        (tmp / SCENE_FILE).write_text(scene_json_text(jsonable(doc)) + "\n", encoding="utf-8")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DatasetWarning)
            load_dataset(tmp)
    return out


# ----------------------------------------------------------------------------------------------
# HDR merge


@dataclass
class HDRResult:
    """The result of :func:`merge_hdr`.

    Attributes:
        radiance: ``[H, W, 3]`` float32 linear radiance (value / time; for the estimated response, OpenCV's
            relative radiance).
        saturated: ``[H, W]`` bool, some channel saturated in every bracket: its radiance is only a lower bound (the
            saturation level / the shortest time).
        underexposed: ``[H, W]`` bool, some channel below the noise floor in every bracket where it is not saturated
            (value / time of the longest bracket).
        weight: ``[H, W, 3]`` the summed weights (0 where a fallback was used).
        response: "linear", "srgb" or "estimate".
    """

    radiance: Tensor
    saturated: Tensor
    underexposed: Tensor
    weight: Tensor
    response: str


def hat_weight(z: Tensor, floor: float) -> Tensor:
    """The merge weight of a normalised code z = value / saturation in [0, 1]: the hat
    ``max(0, min(z − floor, 1 − z))`` — 0 in the noise floor (z ≤ ``floor``) and at saturation (z = 1), largest
    at mid-range."""
    return torch.clamp(torch.minimum(z - floor, 1.0 - z), min=0.0)


def _bracket(x, i: int):
    """One bracket as (float64 array [H, W, C], bits or None)."""
    if isinstance(x, (str, os.PathLike)):
        path = Path(x)
        try:
            if path.suffix.lower() == ".exr":
                return read_exr(path).double().numpy(), None
            arr, bits = read_raster(path)
        except ImageIOError as exc:
            raise CalibrationError(f"exposures[{i}]: {exc}") from None
        return arr, bits
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if arr.dtype == np.uint8:
        return arr, 8
    if arr.dtype == np.uint16:
        return arr, 16
    if not np.issubdtype(arr.dtype, np.floating):
        raise CalibrationError(f"exposures[{i}]: unsupported sample type {arr.dtype}; give float (linear), uint8 or "
                               "uint16 images")
    return arr.astype(np.float64), None


def merge_hdr(exposures, times, *, response: str = "auto", saturation: float | None = None,
              floor: float | None = None) -> HDRResult:
    """Merge bracketed exposures of a static scene into one linear radiance image.

    Linear brackets (float, or 16-bit integer read as code / 65535, or any depth with ``response="linear"``;
    ``response="srgb"`` decodes integer codes with the sRGB curve first): each bracket k gives the estimate
    ``value_k / t_k``; the merge is, per pixel and channel, their weighted average with weight
    ``hat_weight(z_k, floor) · t_k``, z_k = value_k / ``saturation`` the normalised code (:func:`hat_weight`: 0 in
    the noise floor and at the top; the factor t_k trusts longer exposures, whose value / t has the smaller noise).
    A channel at or above ``saturation`` in a bracket gets weight 0 there (excluded). A channel saturated in every
    bracket gets the lower bound saturation / t_min (the ``saturated`` mask: some channel so); a channel below the
    floor in every bracket gets the longest bracket's value / t (the ``underexposed`` mask).

    8-bit brackets with ``response="auto"`` (or ``"estimate"``), e.g. JPEGs: their response is unknown, so OpenCV
    estimates it from the brackets (``cv2.createCalibrateDebevec().process(images, times)``) and merges with it
    (``cv2.createMergeDebevec().process(images, times, response)``); an :class:`HDRWarning` says the result is
    approximate and relative (unknown scale). The saturated mask is then the pixels at code 255 in some channel in
    every bracket.

    Args:
        exposures: 2 or more images ``[H, W, 3]`` (or ``[H, W]``) of the same size: arrays, tensors or files (EXR,
            PNG, TIFF, JPEG).
        times: exposure times, one per image, positive (seconds or any unit; the radiance is per that unit).
        response: :data:`RESPONSES`.
        saturation: the clipping level in the images' (decoded) units; default 1.0 (full code for integer images).
        floor: the noise floor as a fraction of ``saturation``; default 2 codes of the integer depth (2/255,
            2/65535), or 1e-4 for float images.

    Raises:
        CalibrationError: fewer than 2 brackets, sizes or counts that disagree, bad times or options.
    """
    if response not in RESPONSES:
        raise CalibrationError(f"response must be one of {RESPONSES}, got {response!r}")
    if isinstance(exposures, (str, os.PathLike, np.ndarray, Tensor)) or not isinstance(exposures, Sequence):
        raise CalibrationError("exposures must be a list of 2 or more bracketed images (arrays, tensors or files)")
    n = len(exposures)
    try:
        t = np.asarray(times, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        t = np.zeros(0)
    if n < 2 or len(t) != n:
        raise CalibrationError(f"merge_hdr needs 2 or more exposures and one time per exposure, got {n} image(s) and "
                               f"{len(t)} time(s)")
    if not np.isfinite(t).all() or (t <= 0).any():
        raise CalibrationError(f"exposure times must be positive finite numbers, got {t.tolist()}")
    imgs = [_bracket(x, i) for i, x in enumerate(exposures)]
    shapes = {a.shape for a, _ in imgs}
    if len(shapes) != 1:
        raise CalibrationError(f"the brackets differ in size {sorted(shapes)}; give aligned images of one size")
    depths = {b for _, b in imgs}
    if len(depths) != 1:
        raise CalibrationError(f"the brackets mix sample depths {sorted(str(d) for d in depths)}; give them all the "
                               "same way (all 8-bit, all 16-bit or all float)")
    bits = depths.pop()
    arrs = [a if a.ndim == 3 else a[:, :, None] for a, _ in imgs]
    arrs = [a[:, :, :3] if a.shape[2] >= 3 else np.repeat(a[:, :, :1], 3, 2) for a in arrs]
    mode = response
    if mode == "auto":
        mode = "estimate" if bits == 8 else "linear"
    if mode == "estimate":
        return _merge_debevec(arrs, t, bits)
    if saturation is not None and (not math.isfinite(saturation) or saturation <= 0):
        raise CalibrationError(f"saturation must be a positive level in the images' units, got {saturation!r}")
    vals = []
    for a in arrs:
        x = torch.from_numpy(a.astype(np.float64))
        if bits is not None:
            x = x / float((1 << bits) - 1)
        if mode == "srgb":
            from renderer.imageio import decode

            x = decode(x.clamp(0, 1), "srgb").double()
        vals.append(x)
    sat = 1.0 if saturation is None else float(saturation)
    fl = floor if floor is not None else (2.0 / ((1 << bits) - 1) if bits else 1e-4)
    if not 0 <= fl < 0.5:
        raise CalibrationError(f"floor must be a fraction of the saturation level in [0, 0.5), got {fl!r}")
    num = torch.zeros_like(vals[0])
    den = torch.zeros_like(vals[0])
    sat_all = torch.ones_like(vals[0], dtype=torch.bool)     # per channel: at the level in every bracket
    for x, tk in zip(vals, t.tolist(), strict=True):
        z = x / sat
        clipped = z >= 1 - 1e-6
        w = torch.where(clipped, 0.0, hat_weight(z, fl) * tk)
        num += w * x / tk
        den += w
        sat_all &= clipped
    out = num / den.clamp_min(1e-300)
    short, long_ = int(np.argmin(t)), int(np.argmax(t))
    none = den <= 0
    fallback = torch.where(sat_all, torch.full_like(out, sat / t[short]), vals[long_] / t[long_])
    out = torch.where(none, fallback, out)
    dark_all = (none & ~sat_all).any(-1)
    sat_all = sat_all.any(-1)
    return HDRResult(out.float(), sat_all, dark_all & ~sat_all, den.float(), mode)


def _merge_debevec(arrs, t: np.ndarray, bits) -> HDRResult:
    import cv2

    if bits != 8:
        raise CalibrationError("response='estimate' needs 8-bit brackets (OpenCV's Debevec calibration works on 256 "
                               "codes); give 16-bit or float brackets with response='linear'")
    warnings.warn(HDRWarning("merge_hdr: the camera response was estimated from the 8-bit brackets "
                             "(cv2.createCalibrateDebevec); the radiance is approximate and relative (unknown scale)"),
                  stacklevel=3)
    imgs = [np.ascontiguousarray(a.astype(np.uint8)) for a in arrs]
    times = t.astype(np.float32)
    resp = cv2.createCalibrateDebevec().process(imgs, times)
    hdr = cv2.createMergeDebevec().process(imgs, times, resp)
    sat_all = np.ones(imgs[0].shape[:2], dtype=bool)
    dark_all = np.ones(imgs[0].shape[:2], dtype=bool)
    for a in imgs:
        sat_all &= (a >= 255).any(-1)
        dark_all &= (a <= 2).all(-1)
    rad = torch.from_numpy(np.nan_to_num(hdr.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0))
    return HDRResult(rad, torch.from_numpy(sat_all), torch.from_numpy(dark_all & ~sat_all),
                     torch.ones_like(rad), "estimate")
