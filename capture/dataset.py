"""The shadecap dataset format on disk: ``scene.json`` + mesh + images (+ ground truth), versioned.

A dataset is a folder (``docs/dataset-format.md`` is the full specification, with an example)::

    my_capture/
      scene.json          format "shadecap-dataset", version 1: mesh, encoding, saturation,
                          one entry per image (file, OpenCV camera, lights, exposure), optional gt
      mesh.obj            the object, with UVs (OBJ / PLY / GLB through trimesh)
      images/000.exr ...  linear EXR (encoding "linear") or sRGB PNG (encoding "srgb")
      gt/albedo.exr ...   synthetic scenes only: one linear EXR map per model parameter,
      gt/regions.png      and an optional region-id map (8/16-bit gray, code = region id)

Radiometry (DESIGN.md): an image's pixel value (after decoding the file's transfer function) is
``exposure · L`` with L the linear radiance (W/(m² sr) for lights in W/sr and metres);
:meth:`Dataset.load_images` divides by the exposure. A pixel whose file value reaches the
saturation level in any channel is *clipped*: its true value is unknown (≥ the level), and the
observation stage drops it.

:func:`load_dataset` validates everything it reads and raises :class:`DatasetError` (a
``ValueError``) whose message names the file, the field and the fix. Non-finite pixels are not an
error (DESIGN.md: the observation stage drops NaN pixels): the loader warns with their count
(:class:`DatasetWarning`) and keeps them, but an image with no finite pixel at all is an error.
:func:`write_dataset` writes into a temporary folder next to the destination, validates it with
:func:`load_dataset`, and moves it in place with :func:`os.replace`: a reader never sees a
half-written dataset, and a failed write leaves nothing behind.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from materials import Model, SumModel
from materials import get as get_model
from renderer.camera import Camera, CameraError
from renderer.gbuffer import check_psf_sigma
from renderer.imageio import ImageIOError, decode, read_exr, read_png, read_raster, write_exr, write_png
from renderer.lights import LightError, PointLight, light_from_dict, light_to_dict
from renderer.mesh import Mesh, MeshError, load_mesh, save_mesh

from .outputs import atomic_folder, check_output, jsonable

__all__ = [
    "FORMAT", "VERSION", "ENCODINGS", "DatasetError", "DatasetWarning", "View", "GroundTruth", "Photo", "Dataset",
    "load_dataset", "write_dataset", "model_from_spec", "model_spec", "camera_sees_mesh", "dataset_root",
    "degenerate_faces", "winding_numbers", "EXPOSURE_RANGE", "MAX_LIGHT", "JPEG_SUFFIXES", "LIGHT_FRAMES",
    "MASK_DIR", "light_to_world", "bin_pixels",
]

#: The ``format`` string of every shadecap dataset's ``scene.json``.
FORMAT = "shadecap-dataset"
#: The newest format version this code reads and the one it writes.
VERSION = 1
#: Colour encodings and the image files each accepts: "linear" → EXR (float) or 16-bit / float TIFF holding
#: exposure·L; "srgb" → 8/16-bit PNG or TIFF, or 8-bit JPEG, sRGB-encoded.
ENCODINGS = {"linear": (".exr", ".tif", ".tiff"), "srgb": (".png", ".jpg", ".jpeg", ".tif", ".tiff")}
#: Image suffixes that are JPEG: loading them warns (a camera's JPEG is not pure sRGB, see docs/dataset-format.md).
JPEG_SUFFIXES = (".jpg", ".jpeg")
#: Light ``frame`` values: "world" (default) or "camera" (the view's OpenCV camera frame, resolved at load).
LIGHT_FRAMES = ("world", "camera")
SCENE_FILE = "scene.json"
IMAGE_DIR = "images"
MASK_DIR = "masks"
GT_DIR = "gt"
_IMAGE_SUFFIXES = (".exr", ".png", ".jpg", ".jpeg", ".tif", ".tiff")
_TOP_KEYS = {"format", "version", "mesh", "encoding", "bits", "saturation", "psf_sigma", "images", "gt", "meta"}
_VIEW_KEYS = {"file", "camera", "lights", "exposure", "name", "mask"}
_GT_KEYS = {"model", "maps", "regions", "render", "photo"}
#: Exposures are accepted strictly inside this range: beyond it, pixel / exposure leaves float32's range.
EXPOSURE_RANGE = (1e-30, 1e30)
#: Light intensities and irradiances are accepted below this: squared, or times a BRDF peak, they overflow float32.
MAX_LIGHT = 1e20
#: The fields of each light type that hold its intensity or irradiance.
_LIGHT_LEVELS = {"point": ("intensity",), "directional": ("irradiance",), "hemisphere": ("upper", "lower"),
                 "sh": ("coeffs",)}


class DatasetError(ValueError):
    """A dataset that cannot be read or written; the message names the file, the field and the fix."""


class DatasetWarning(UserWarning):
    """Something in a dataset that is usable but deserves attention (non-finite pixels, unknown fields)."""


def _err(file, field_: str | None, problem: str, fix: str = "") -> DatasetError:
    where = f"{file}" + (f": field '{field_}'" if field_ else "")
    return DatasetError(f"{where}: {problem}" + (f"; {fix}" if fix else ""))


# ----------------------------------------------------------------------------------------------
# model specs


def model_spec(name_or_spec, options: Mapping | None = None) -> dict:
    """Normalise a model description to the JSON spec stored in ``scene.json``.

    Accepted: a registered name (``"microfacet"``) with ``options``; a sum written ``"a+b"`` (each
    part with default options); or a spec dict ``{"name": str, "options": {...}}`` /
    ``{"sum": [spec, ...]}``. Returns the dict form (not yet validated against the registry; see
    :func:`model_from_spec`).
    """
    if isinstance(name_or_spec, Mapping):
        if options:
            raise ValueError("model_spec: give options inside the spec dict, not separately")
        spec = dict(name_or_spec)
        if "sum" in spec:
            parts = spec["sum"]
            if not isinstance(parts, Sequence) or isinstance(parts, str) or not parts:
                raise ValueError(f"model spec 'sum' must be a non-empty list of specs, got {parts!r}")
            return {"sum": [model_spec(p) for p in parts]}
        if not isinstance(spec.get("name"), str):
            raise ValueError(f"model spec needs a 'name' (a registered model) or a 'sum' list, got {spec!r}")
        opts = spec.get("options", {}) or {}
        if not isinstance(opts, Mapping):
            raise ValueError(f"model spec 'options' must be an object, got {opts!r}")
        return {"name": spec["name"], "options": dict(opts)}
    if not isinstance(name_or_spec, str) or not name_or_spec.strip():
        raise ValueError(f"a model is a registered name or a spec dict, got {name_or_spec!r}")
    parts = [_parse_part(p, name_or_spec) for p in _split_top(name_or_spec, "+", name_or_spec)]
    if len(parts) > 1:
        if options:
            raise ValueError(f"model '{name_or_spec}': per-part options need the spec form {{'sum': [...]}} or "
                             f"the written form 'a(k=v)+b(k=v)'")
        return {"sum": parts}
    if options and parts[0]["options"]:
        raise ValueError(f"model '{name_or_spec}': options given both in the name and separately; give them once")
    return {"name": parts[0]["name"], "options": dict(options or parts[0]["options"])}


def _split_top(text: str, sep: str, whole: str) -> list[str]:
    """Split ``text`` at ``sep`` outside parentheses (a '+' inside ``1e+3`` or an option value stays)."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
            if depth < 0:
                raise ValueError(f"model '{whole}': unbalanced ')'")
        if ch == sep and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    if depth:
        raise ValueError(f"model '{whole}': unbalanced '('")
    out.append(cur)
    if any(not x.strip() for x in out):
        raise ValueError(f"model '{whole}': empty part; write names joined by '+', e.g. 'lambert+microfacet(D=ggx)'")
    return [x.strip() for x in out]


def _option_value(text: str):
    """An option value as written: true/false/none, an int, a float, else the string itself."""
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null") and text != "none":
        return None
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def _parse_part(text: str, whole: str) -> dict:
    """``name`` or ``name(k=v, k2=v2)`` — the spelling the project prints (``materials.get`` names a model with
    options ``name(k=v, ...)``) — as a spec ``{"name", "options"}``."""
    if "(" not in text:
        if ")" in text or "=" in text:
            raise ValueError(f"model '{whole}': cannot read '{text}'; write name(option=value, ...)")
        return {"name": text, "options": {}}
    if not text.endswith(")"):
        raise ValueError(f"model '{whole}': '{text}' must end with ')' after its options")
    name, inner = text[:text.index("(")].strip(), text[text.index("(") + 1:-1]
    if not name:
        raise ValueError(f"model '{whole}': '{text}' has options but no model name before '('")
    opts = {}
    for item in (_split_top(inner, ",", whole) if inner.strip() else []):
        if "=" not in item:
            raise ValueError(f"model '{whole}': option '{item}' of '{name}' must be written key=value")
        k, v = (x.strip() for x in item.split("=", 1))
        if not k.isidentifier() or not v:
            raise ValueError(f"model '{whole}': option '{item}' of '{name}' must be written key=value")
        if k in opts:
            raise ValueError(f"model '{whole}': option '{k}' of '{name}' given twice")
        opts[k] = _option_value(v)
    return {"name": name, "options": opts}


def model_label(spec) -> str:
    """The written form of a spec, which :func:`model_spec` reads back: ``a(k=v, ...)+b``."""
    spec = model_spec(spec)
    if "sum" in spec:
        return "+".join(model_label(p) for p in spec["sum"])
    o = spec["options"]
    return spec["name"] + (f"({', '.join(f'{k}={v}' for k, v in sorted(o.items()))})" if o else "")


def model_from_spec(spec) -> Model:
    """Instantiate the model a spec describes (see :func:`model_spec`) via ``materials.get``.

    Raises:
        ValueError: unknown name or option (``materials.get``'s message, listing the names).
    """
    spec = model_spec(spec)
    if "sum" in spec:
        parts = [model_from_spec(p) for p in spec["sum"]]
        return parts[0] if len(parts) == 1 else SumModel(*parts)
    return get_model(spec["name"], **spec["options"])


# ----------------------------------------------------------------------------------------------
# data classes


@dataclass
class View:
    """One photo: its file, the camera that took it, the lights that lit it, its exposure.

    Attributes:
        camera: OpenCV camera (:class:`renderer.camera.Camera`); its width/height are the image's.
        lights: light objects (:mod:`renderer.lights`: point, directional, hemisphere, SH), in the
            world frame of the mesh.
        exposure: positive multiplier, dimensionless: file value = exposure · radiance.
        file: path of the image relative to the dataset folder (``images/000.exr``); on writing,
            an empty string lets :func:`write_dataset` name it.
        name: optional label.
        mask: optional mask image relative to the dataset folder (``masks/000.png``; nonzero = the object,
            usable; zero = not usable), or "" for none.
        bin: the image and mask files are read binned ``bin × bin`` (:meth:`Dataset.binned`): ``camera`` is then the
            binned image's camera and the files are ``bin`` times its size (plus up to ``bin − 1`` pixels that fill
            no block). 1 (the default): the files are ``camera``'s size.
    """

    camera: Camera
    lights: list
    exposure: float = 1.0
    file: str = ""
    name: str = ""
    mask: str = ""
    bin: int = 1


@dataclass
class GroundTruth:
    """The true material of a synthetic dataset.

    Attributes:
        model: the model spec (``{"name", "options"}`` or ``{"sum": [...]}``).
        maps: parameter name → linear map ``[H, W, C]`` float32 (row 0 = top = v = 1), exactly
            ``model.params``.
        regions: optional region-id map ``[H, W]`` int64 (same size as the maps).
        region_names: region id → name (every id in ``regions`` has a name).
        render: how the images were rendered (``supersample``, ``sampling``, ``shadows``).
        photo: the photo model's settings (a dict, see :class:`capture.photo.PhotoModel`).
        files: parameter name → relative file (``gt/albedo.exr``) once written/read.
    """

    model: dict
    maps: dict[str, Tensor]
    regions: Tensor | None = None
    region_names: dict[int, str] = field(default_factory=dict)
    render: dict = field(default_factory=dict)
    photo: dict = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)

    def build_model(self) -> Model:
        """The :class:`materials.Model` of :attr:`model`."""
        return model_from_spec(self.model)


@dataclass
class Photo:
    """One loaded image in linear radiance.

    Attributes:
        radiance: ``[H, W, 3]`` decoded pixel / exposure (W/(m² sr) in the lights' units); NaN/inf
            pixels are kept as they are for the observation stage to drop.
        saturated: ``[H, W]`` bool, some channel reached the saturation level (value unknown).
        nonfinite: ``[H, W]`` bool, some channel is NaN or inf.
        mask: ``[H, W]`` bool, True where the pixel may be used (the view's ``mask`` file is nonzero and the
            image's alpha channel, when it has one, is at least half its full value); None = every pixel.
    """

    radiance: Tensor
    saturated: Tensor
    nonfinite: Tensor
    mask: Tensor | None = None

    @property
    def unusable(self) -> Tensor:
        """``[H, W]`` bool: pixels whose value must not be fitted — saturated, or masked out (``~mask``).

        This is what the observation stage is given as its ``clipped`` masks (it counts these pixels under the
        drop reason "clipped")."""
        if self.mask is None:
            return self.saturated
        return self.saturated | ~self.mask.to(self.saturated.device)


@dataclass
class Dataset:
    """A loaded, validated dataset (see :func:`load_dataset`).

    Attributes:
        root: the dataset folder.
        mesh: the loaded mesh (UVs checked); mesh_file: its path relative to ``root``.
        views: one :class:`View` per image, in ``scene.json`` order.
        encoding: "linear" (EXR) or "srgb" (PNG).
        bits: PNG bit depth (8 or 16) for "srgb"; None for "linear".
        saturation: clipping level in file units — an integer code for "srgb", a file value or None
            (never clipped) for "linear".
        gt: ground truth of a synthetic dataset, or None.
        meta: free-form metadata (generator, configuration, highlight coverage ...).
        warnings: the warnings raised while loading (also issued as :class:`DatasetWarning`).
        psf_sigma: σ (pixels) of the Gaussian blur in the photos' pixel filter (``scene.json`` → ``psf_sigma``;
            0: the box filter alone).
    """

    root: Path
    mesh: Mesh
    mesh_file: str
    views: list[View]
    encoding: str
    bits: int | None
    saturation: float | int | None
    gt: GroundTruth | None = None
    meta: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    psf_sigma: float = 0.0

    def __len__(self) -> int:
        return len(self.views)

    @property
    def cameras(self) -> list[Camera]:
        return [v.camera for v in self.views]

    def saturation_linear(self) -> float | None:
        """The saturation level as a decoded (linear) file value, or None when nothing clips."""
        if self.saturation is None:
            return None
        if self.encoding == "linear":
            return float(self.saturation)
        # the same float32 arithmetic as renderer.imageio.read_png, so a pixel at the level compares equal
        code = torch.tensor([float(self.saturation)], dtype=torch.float32) / np.float32((1 << self.bits) - 1)
        return float(decode(code, "srgb")[0])

    def read_file_image(self, i: int) -> Tensor:
        """View ``i``'s image as decoded file values ``[H, W, 3]`` float32 (validated, not divided by exposure)."""
        img, _, _ = _read_view_image(self.root, self.views[i], i, self.encoding, self.bits)
        return bin_pixels(img, self.views[i].bin, "mean")

    def read_mask(self, i: int) -> Tensor | None:
        """View ``i``'s usable-pixel mask ``[H, W]`` bool (mask file AND alpha), or None when it has neither."""
        _, _, alpha = _read_view_image(self.root, self.views[i], i, self.encoding, self.bits)
        mask = _combine_masks(alpha, _read_view_mask(self.root, self.views[i], i))
        return None if mask is None else bin_pixels(mask, self.views[i].bin, "all")

    def load_images(self, dtype: torch.dtype = torch.float32, device=None) -> list[Photo]:
        """Every image as linear radiance: decode (sRGB for PNG), divide by the view's exposure.

        Returns:
            one :class:`Photo` per view; ``saturated`` marks pixels whose file value reached
            :attr:`saturation` in any channel (compared in file units before dividing); ``mask`` is the
            usable-pixel mask (the view's mask file, and the alpha channel of an RGBA image), all True when
            the view has neither; :attr:`Photo.unusable` is saturated or masked out.

        Raises:
            DatasetError: an image changed on disk since loading and no longer validates.
        """
        sat = self.saturation_linear()
        out = []
        for i, view in enumerate(self.views):
            img, _, alpha = _read_view_image(self.root, view, i, self.encoding, self.bits)
            mask = _combine_masks(alpha, _read_view_mask(self.root, view, i))
            if mask is None:
                mask = torch.ones(img.shape[:2], dtype=torch.bool)
            nonfinite = ~torch.isfinite(img).all(-1)
            if sat is None:
                saturated = torch.zeros(img.shape[:2], dtype=torch.bool)
            else:
                saturated = (torch.nan_to_num(img, nan=-math.inf) >= sat * (1 - 1e-6)).any(-1)
            rad = img.to(torch.float64) / float(view.exposure)
            k = view.bin  # a block is unusable where any of its pixels is: the mean of a clipped value is no value
            rad, saturated = bin_pixels(rad, k, "mean"), bin_pixels(saturated, k, "any")
            nonfinite, mask = bin_pixels(nonfinite, k, "any"), bin_pixels(mask, k, "all")
            out.append(Photo(rad.to(dtype=dtype, device=device), saturated.to(device), nonfinite.to(device),
                             mask.to(device)))
        return out

    def binned(self, k: int) -> Dataset:
        """This dataset with its photos binned ``k × k``: each block of ``k × k`` pixels one pixel, their mean radiance
        — a pixel ``k`` times larger, whose box filter is the union of its block's boxes, so a fit that integrates
        over pixel footprints models the binned photos exactly. The cameras become the binned images' cameras
        (:meth:`renderer.camera.Camera.binned`), ``psf_sigma`` is divided by ``k`` (the blur in the binned pixels'
        units), and the readers (:meth:`load_images`, :meth:`read_file_image`, :meth:`read_mask`) bin what they
        read: a binned pixel is saturated, non-finite or masked out when any pixel of its block is. The files
        are not touched. Binning an already binned dataset multiplies the bins.

        Raises:
            DatasetError: ``k`` is not a positive integer, or a view's image is smaller than ``k`` pixels."""
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise DatasetError(f"bin must be a positive integer (1: the photos as they are), got {k!r}")
        if k == 1:
            return self
        views = []
        for i, v in enumerate(self.views):
            try:
                views.append(replace(v, camera=v.camera.binned(k), bin=v.bin * k))
            except CameraError as exc:
                raise DatasetError(f"images[{i}]: {exc}") from None
        return replace(self, views=views, psf_sigma=self.psf_sigma / k)


def bin_pixels(x: Tensor, k: int, how: str) -> Tensor:
    """``x [H, W, ...]`` binned ``k × k`` → ``[H // k, W // k, ...]``: each block's ``"mean"``, or for a bool image
    ``"any"`` / ``"all"``; the last ``H mod k`` rows and ``W mod k`` columns fill no block and are left out."""
    if k == 1:
        return x
    H, W = x.shape[0] // k, x.shape[1] // k
    blocks = x[:H * k, :W * k].reshape(H, k, W, k, *x.shape[2:])
    if how == "mean":
        return blocks.mean(dim=(1, 3))
    return blocks.any(3).any(1) if how == "any" else blocks.all(3).all(1)


# ----------------------------------------------------------------------------------------------
# checks


def camera_sees_mesh(camera: Camera, vertices: Tensor, faces: Tensor | None = None) -> tuple[bool, str]:
    """Cheap test that ``camera`` sees some of the mesh, without a G-buffer.

    The mesh is clipped at a near plane just in front of the camera (depth ε = 1e-9 × the largest
    coordinate): the vertices in front plus, with ``faces``, the points where edges cross the
    plane are the corners of the clipped mesh, so the bounding box of their projections is the
    bounding box of the visible part's projection. The camera sees the mesh iff that box overlaps
    the image ([−½, W − ½] × [−½, H − ½]). Without ``faces`` a mesh that straddles the camera plane
    is accepted (conservative). Occlusion is ignored. Returns ``(sees, reason_if_not)``.
    """
    v = vertices.detach().to("cpu", torch.float64)
    cam = camera.to(torch.float64)
    xc = cam.world_to_camera(v)
    eps = 1e-9 * max(1.0, float(v.abs().max()), float(cam.t.abs().max()))
    front = xc[:, 2] > eps
    if not bool(front.any()):
        return False, "the whole mesh is behind the camera (every vertex has depth ≤ 0)"
    pts = xc[front]
    if not bool(front.all()):
        if faces is None:
            return True, ""
        f = faces.detach().cpu().long()
        a = torch.cat([f[:, 0], f[:, 1], f[:, 2]])
        b = torch.cat([f[:, 1], f[:, 2], f[:, 0]])
        cross = front[a] != front[b]
        za, zb = xc[a[cross], 2], xc[b[cross], 2]
        s = ((eps - za) / (zb - za))[:, None]
        pts = torch.cat([pts, xc[a[cross]] + s * (xc[b[cross]] - xc[a[cross]])])
    K = cam.K.double()
    z = pts[:, 2].clamp_min(eps)
    x = K[0, 0] * pts[:, 0] / z + K[0, 1] * pts[:, 1] / z + K[0, 2]
    y = K[1, 1] * pts[:, 1] / z + K[1, 2]
    W, H = camera.width, camera.height
    lo_x, hi_x, lo_y, hi_y = float(x.min()), float(x.max()), float(y.min()), float(y.max())
    if hi_x < -0.5 or lo_x > W - 0.5 or hi_y < -0.5 or lo_y > H - 0.5:
        return False, (
            f"the mesh projects to x ∈ [{lo_x:.4g}, {hi_x:.4g}], y ∈ [{lo_y:.4g}, {hi_y:.4g}] px, "
            f"outside the {W}×{H} image"
        )
    return True, ""


def degenerate_faces(vertices: Tensor, faces: Tensor) -> int:
    """How many faces have zero area at float32 precision (area ≤ (ε₃₂ · bounding-box diagonal)²)."""
    v = vertices.detach().to("cpu", torch.float64)
    tri = v[faces.detach().cpu().long()]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1).norm(dim=-1)
    scale = float((v.max(0).values - v.min(0).values).norm()) if len(v) else 0.0
    return int((area <= (torch.finfo(torch.float32).eps * scale) ** 2).sum())


def winding_numbers(points: Tensor, vertices: Tensor, faces: Tensor) -> Tensor:
    """Generalised winding number of a triangle mesh at each of ``points`` ``[N, 3]`` → ``[N]`` float64.

    The solid angle the triangles subtend at the point, signed by their winding, over 4π (Van Oosterom &
    Strackee's formula per triangle; Jacobson et al. 2013): ±1 inside a closed mesh, 0 outside, fractional
    near the holes of an open one — so ``|w| > ½`` reads "inside" without needing a watertight mesh. Points
    outside the mesh's bounding box are outside (0) without the sum; each other point costs O(faces).
    """
    v = vertices.detach().to("cpu", torch.float64).numpy()
    tri = v[faces.detach().cpu().long().numpy()]
    pts = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3).numpy()
    out = np.zeros(len(pts))
    inside_box = ((pts >= v.min(0)) & (pts <= v.max(0))).all(-1)
    for k in np.flatnonzero(inside_box):  # numpy, not torch: one thread, no OpenMP contention (~50 ms / 100k faces)
        d = tri - pts[k]
        a, b, c = d[:, 0], d[:, 1], d[:, 2]
        la, lb, lc = (np.sqrt(np.einsum("ij,ij->i", x, x)) for x in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
               + np.einsum("ij,ij->i", b, c) * la)
        out[k] = np.arctan2(det, den).sum() / (2 * math.pi)
    return torch.from_numpy(out)


def _warn_inside(scene: Path, mesh: Mesh, views: list[View], msgs: list[str]) -> None:
    """Warn about cameras and point lights inside the object: such a view sees only the inside, such a light
    lights only the inside (every pixel it should light is dropped as shadowed)."""
    points, where = [], []
    for i, view in enumerate(views):
        points.append(view.camera.center.detach().to("cpu", torch.float64))
        where.append((i, None))
        for j, light in enumerate(view.lights):
            if isinstance(light, PointLight):
                points.append(light.position.detach().to("cpu", torch.float64).reshape(3))
                where.append((i, j))
    if not points:
        return
    w = winding_numbers(torch.stack(points), mesh.vertices, mesh.faces)
    lights: dict[tuple, list[str]] = {}
    for (i, j), p, wk in zip(where, points, w.tolist(), strict=True):
        if abs(wk) <= 0.5:
            continue
        at = "(" + ", ".join(f"{x:.4g}" for x in p.tolist()) + ")"
        if j is None:
            _warn(msgs, f"{scene}: images[{i}].camera: the camera centre {at} is inside the mesh (winding number "
                  f"{wk:.2f}): the view sees only the inside of the object and none of its pixels can be used; check "
                  f"R and t (world-to-camera) and the mesh units")
        else:
            lights.setdefault((at, round(wk, 2)), []).append(f"images[{i}].lights[{j}]")
    for (at, wk), names in lights.items():
        more = f" and {len(names) - 3} more" if len(names) > 3 else ""
        _warn(msgs, f"{scene}: {', '.join(names[:3])}{more}: the point light at {at} is inside the mesh (winding "
              f"number {wk:.2f}): it lights only the inside of the object, so it adds nothing to the photos; check "
              f"its position and the mesh units")


def _number(x, file, fld, *, positive=False, nonneg=False, allow_none=False):
    if x is None and allow_none:
        return None
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not math.isfinite(float(x)):
        raise _err(file, fld, f"must be a finite number, got {x!r}")
    x = float(x)
    if positive and x <= 0:
        raise _err(file, fld, f"must be positive, got {x!r}")
    if nonneg and x < 0:
        raise _err(file, fld, f"must be non-negative, got {x!r}")
    return x


def _relative_file(root: Path, rel, file, fld) -> Path:
    if not isinstance(rel, str) or not rel.strip():
        raise _err(file, fld, f"must be a file path relative to the dataset folder, got {rel!r}")
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        raise _err(file, fld, f"'{rel}' must be relative to the dataset folder and stay inside it",
                   "copy the file into the dataset folder and give its relative path")
    real, base = os.path.realpath(root / p), os.path.realpath(root)
    if os.path.commonpath([real, base]) != base:
        raise _err(file, fld, f"'{rel}' leads outside the dataset folder through a symbolic link (to {real}); a "
                   f"dataset's files stay inside its folder", "copy the file (or folder) into the dataset folder "
                   "instead of linking to it")
    return root / p


def _png_bit_depth(path: Path) -> int | None:
    with open(path, "rb") as fh:
        head = fh.read(26)
    if len(head) >= 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return head[24]
    return None


def _read_view_image(root: Path, view: View, i: int, encoding: str,
                     bits: int | None) -> tuple[Tensor, int, Tensor | None]:
    """Read and check one view's image → (decoded file values ``[H, W, 3]`` float32, non-finite pixel count,
    alpha mask ``[H, W]`` bool — alpha at least half its full value — or None when the image has no alpha)."""
    path = root / view.file
    fld = f"images[{i}].file"
    suffix = path.suffix.lower()
    if suffix not in ENCODINGS[encoding]:
        raise _err(SCENE_FILE, fld, f"'{view.file}' is not a {'/'.join(ENCODINGS[encoding])} file, but the "
                   f"dataset's encoding is '{encoding}'", "convert the image or fix 'encoding'")
    if not path.is_file():
        raise _err(path, None, f"image listed in {SCENE_FILE} ({fld}) does not exist",
                   "add the file or remove its entry")
    try:
        if suffix == ".exr":
            img = read_exr(path)
        else:
            arr, depth = read_raster(path)
            kind = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG"}.get(suffix, "TIFF")
            if encoding == "srgb":
                if depth is None:
                    raise _err(path, None, f"{kind} holds float samples, which are linear values, but the dataset's "
                               "encoding is 'srgb'", "set \"encoding\": \"linear\" or write 8/16-bit sRGB images")
                if depth != bits:
                    raise _err(path, None, f"{kind} has {depth}-bit samples but {SCENE_FILE} says bits = {bits}",
                               f"write the image with {bits} bits or fix 'bits'")
            elif depth == 8:
                raise _err(path, None, f"{kind} has 8-bit samples, too coarse for linear values (the shadows "
                           "would lose most of their levels)", "write 16-bit or float TIFF / EXR linear images, "
                           "or set \"encoding\": \"srgb\" for sRGB-encoded 8-bit images")
            x = arr.astype(np.float32)
            if depth is not None:
                x /= np.float32((1 << depth) - 1)
            img = torch.from_numpy(x)
            if encoding == "srgb":
                ncol = 3 if img.shape[2] == 4 else (1 if img.shape[2] == 2 else img.shape[2])
                img = torch.cat([decode(img[..., :ncol], "srgb"), img[..., ncol:]], dim=-1)
    except ImageIOError as exc:
        raise _err(path, None, f"unreadable image ({fld}): {exc}", "rewrite the file") from None
    if img.shape[0] // view.bin != view.camera.height or img.shape[1] // view.bin != view.camera.width:
        size = f"{view.camera.width}×{view.camera.height}" + (f" binned {view.bin}×{view.bin}" if view.bin > 1 else "")
        raise _err(path, None, f"image is {img.shape[1]}×{img.shape[0]} px but its camera ({SCENE_FILE} "
                   f"images[{i}].camera) is {size}", "resize the image or fix the camera's width/height and K")
    H, W = img.shape[:2]
    c = img.shape[2]
    alpha = None
    if c in (2, 4):  # gray+alpha or RGBA: alpha is the mask (linear, never sRGB-decoded)
        alpha = img[..., -1] >= 0.5
        img = img[..., :-1]
        c -= 1
    if c == 1:
        img = img.expand(H, W, 3).contiguous()
    elif c != 3:
        raise _err(path, None, f"image has {c} channels; a photo must be RGB (3) or gray (1), optionally with an "
                   "alpha channel (the mask)", "write it as RGB or RGBA")
    finite = torch.isfinite(img).all(-1)
    bad = int((~finite).sum())
    if bad == H * W:
        raise _err(path, None, f"every pixel ({bad}) is NaN or inf", "re-export the image")
    return img, bad, alpha


def _read_view_mask(root: Path, view: View, i: int) -> Tensor | None:
    """View ``i``'s mask file as ``[H, W]`` bool (nonzero in some colour channel = usable), or None without one."""
    if not view.mask:
        return None
    path = root / view.mask
    fld = f"images[{i}].mask"
    if path.suffix.lower() != ".png":
        raise _err(SCENE_FILE, fld, f"'{view.mask}' must be a .png mask (lossless; nonzero = the object)",
                   "convert the mask to PNG")
    if not path.is_file():
        raise _err(path, None, f"mask listed in {SCENE_FILE} ({fld}) does not exist",
                   "add the file or remove the entry's 'mask'")
    try:
        arr, _ = read_raster(path)
    except ImageIOError as exc:
        raise _err(path, None, f"unreadable mask ({fld}): {exc}", "rewrite the file") from None
    H, W = view.camera.height, view.camera.width
    if arr.shape[0] // view.bin != H or arr.shape[1] // view.bin != W:
        raise _err(path, None, f"mask is {arr.shape[1]}×{arr.shape[0]} px but its image's camera is {W}×{H}"
                   + (f" binned {view.bin}×{view.bin}" if view.bin > 1 else ""), "write the mask at the image's size")
    colour = arr[..., :3] if arr.shape[2] >= 3 else arr[..., :1]
    return torch.from_numpy((colour != 0).any(-1))


def _combine_masks(a: Tensor | None, b: Tensor | None) -> Tensor | None:
    if a is None:
        return b
    return a if b is None else a & b


def light_to_world(d: Mapping, camera: Camera) -> dict:
    """A light entry of ``scene.json`` with its optional ``"frame"`` resolved: the same entry in world coordinates.

    ``"frame": "world"`` (the default) changes nothing. ``"frame": "camera"`` means the light's vectors are in the
    view's OpenCV camera frame (x right, y down, z forward, world units): a flash fixed to the camera at
    ``position`` p_c is at ``Rᵀ (p_c − t)`` in the world (the camera centre plus ``Rᵀ p_c``); a ``directional``
    light's ``direction`` and a ``hemisphere`` light's ``up`` are rotated by ``Rᵀ``. An ``sh`` light cannot be
    given in the camera frame. The returned dict has no ``frame`` key.

    Raises:
        LightError: an unknown frame, a camera-frame SH light, or a vector that is not 3 finite numbers.
    """
    if not isinstance(d, Mapping):
        return d  # light_from_dict names the problem
    frame = d.get("frame", "world")
    out = {k: v for k, v in d.items() if k != "frame"}
    if frame not in LIGHT_FRAMES:
        raise LightError(f"'frame' must be one of {list(LIGHT_FRAMES)}, got {frame!r}")
    if frame == "world":
        return out
    kind = d.get("type")
    keys = {"point": "position", "directional": "direction", "hemisphere": "up"}
    if kind == "sh":
        raise LightError("an 'sh' light cannot be given in the camera frame; give its coefficients in world "
                         "coordinates (drop \"frame\": \"camera\")")
    key = keys.get(kind)
    if key is None or key not in d:
        return out  # unknown type or a missing field: light_from_dict names it
    try:
        vec = np.asarray(d[key], dtype=np.float64)
    except (TypeError, ValueError):
        vec = np.zeros(0)
    if vec.shape != (3,) or not np.isfinite(vec).all():
        raise LightError(f"{kind} light: '{key}' must be 3 finite numbers, got {d[key]!r}")
    R = camera.R.detach().cpu().double().numpy()
    t = camera.t.detach().cpu().double().numpy()
    out[key] = (R.T @ (vec - t)).tolist() if kind == "point" else (R.T @ vec).tolist()
    return out


def _as_list(x, file, fld, nonempty=True) -> list:
    if not isinstance(x, list):
        raise _err(file, fld, f"must be a JSON list, got {type(x).__name__}")
    if nonempty and not x:
        raise _err(file, fld, "must not be empty")
    return x


def _as_obj(x, file, fld) -> dict:
    if not isinstance(x, dict):
        raise _err(file, fld, f"must be a JSON object, got {type(x).__name__}")
    return x


def _warn(msgs: list[str], msg: str, stacklevel: int = 3) -> None:
    """Collect ``msg`` and warn with it; the default stacklevel names the caller of the function calling this,
    a helper of that function passes one more per level of nesting."""
    msgs.append(msg)
    warnings.warn(DatasetWarning(msg), stacklevel=stacklevel)


# ----------------------------------------------------------------------------------------------
# loading


def dataset_root(path) -> Path:
    """The dataset folder of ``path``: the folder itself, or the folder of its ``scene.json``."""
    p = Path(path)
    return p.parent if p.name == SCENE_FILE or p.is_file() else p


def load_dataset(path, *, check_images: bool = True) -> Dataset:
    """Load and validate a dataset folder (or its ``scene.json``).

    Checks, each failure a :class:`DatasetError` naming the file, the field and the fix:
    ``scene.json`` exists and is valid JSON; ``format`` and ``version`` (≤ :data:`VERSION`);
    required fields and their types; ``encoding`` ("linear"/"srgb"), ``bits``, ``saturation``;
    per image: ``file`` (relative, inside the folder, the encoding's suffix, listed once),
    ``camera`` (:meth:`Camera.from_dict`), ``lights`` (:func:`renderer.lights.light_from_dict`:
    known type, non-negative intensities), ``exposure`` > 0, the camera sees the mesh
    (:func:`camera_sees_mesh`); the mesh loads and has UVs; the image files in ``images/`` are
    exactly the listed ones (count mismatch); with ``check_images``: every image is readable, not
    truncated, RGB, of its camera's size, with some finite pixel; the ``gt`` block: the model
    exists (``materials.get``), maps are exactly the model's parameters, same size, right channels,
    finite and within each parameter's range; the region map's ids all have names; no path leads
    out of the folder through a symbolic link; exposures in :data:`EXPOSURE_RANGE`, light levels
    below :data:`MAX_LIGHT`.

    Warnings (:class:`DatasetWarning`, also collected in :attr:`Dataset.warnings`): zero-area faces
    (:func:`degenerate_faces`), a camera centre or a point light inside the mesh
    (:func:`winding_numbers`), non-finite pixels (counted; kept in the images, the observation stage
    drops them), unknown fields (ignored).
    """
    root = dataset_root(path)
    scene = root / SCENE_FILE
    msgs: list[str] = []
    doc = _read_scene(root, scene, msgs)
    enc = _scene_encoding(scene, doc)
    mesh = _load_scene_mesh(root, scene, doc, msgs)
    views = _load_views(root, scene, doc, mesh, msgs)
    _warn_inside(scene, mesh, views, msgs)
    _warn_jpegs(scene, views, msgs)
    _check_image_folder(root, scene, views)
    if check_images:
        _check_view_images(root, views, enc, msgs)

    gt = None
    if "gt" in doc and doc["gt"] is not None:
        gt = _load_gt(root, scene, doc["gt"], msgs)
    meta = doc.get("meta", {}) or {}
    if not isinstance(meta, dict):
        raise _err(scene, "meta", f"must be a JSON object, got {type(meta).__name__}")
    return Dataset(root, mesh, str(Path(doc["mesh"]).as_posix()), views, enc.encoding, enc.bits, enc.saturation, gt,
                   meta, msgs, psf_sigma=float(enc.psf_sigma))


class _Encoding(NamedTuple):
    """How a dataset's image files hold radiance: ``encoding``, sRGB ``bits``, clipping level, pixel filter."""

    encoding: str
    bits: int | None
    saturation: float | int | None
    psf_sigma: float


def _read_scene(root: Path, scene: Path, msgs: list[str]) -> dict:
    """``scene.json`` parsed, with its header (format, version) and required fields checked."""
    if not root.is_dir():
        raise _err(root, None, "dataset folder does not exist")
    if not scene.is_file():
        raise _err(scene, None, "missing; a dataset folder must hold scene.json", "see docs/dataset-format.md")
    try:
        doc = json.loads(scene.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise _err(scene, None, f"malformed JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}",
                   "fix the syntax (e.g. python -m json.tool scene.json)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise _err(scene, None, f"cannot be read: {exc}") from None
    doc = _as_obj(doc, scene, "(top level)")
    if doc.get("format") != FORMAT:
        raise _err(scene, "format", f"must be '{FORMAT}', got {doc.get('format')!r}",
                   "this is not a shadecap dataset, or its header is damaged")
    version = doc.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise _err(scene, "version", f"must be an integer, got {version!r}")
    if version < 1 or version > VERSION:
        raise _err(scene, "version", f"unknown version {version}; this shadecap reads versions 1..{VERSION}",
                   "upgrade shadecap" if version > VERSION else "fix the version")
    for key in ("mesh", "encoding", "images"):
        if key not in doc:
            raise _err(scene, key, "is missing", "see docs/dataset-format.md for the required fields")
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        _warn(msgs, f"{scene}: ignoring unknown top-level field(s) {unknown}", stacklevel=4)
    return doc


def _scene_encoding(scene: Path, doc: Mapping) -> _Encoding:
    encoding = doc["encoding"]
    if encoding not in ENCODINGS:
        raise _err(scene, "encoding", f"must be one of {sorted(ENCODINGS)}, got {encoding!r}")
    bits = None
    if encoding == "srgb":
        bits = doc.get("bits", 8)
        if bits not in (8, 16) or isinstance(bits, bool):
            raise _err(scene, "bits", f"must be 8 or 16 for sRGB PNG images, got {bits!r}")
    saturation = doc.get("saturation")
    if encoding == "srgb":
        top = (1 << bits) - 1
        if saturation is None:
            saturation = top
        if isinstance(saturation, bool) or not isinstance(saturation, int) or not 1 <= saturation <= top:
            raise _err(scene, "saturation", f"must be an integer code in [1, {top}] for {bits}-bit PNG, got "
                       f"{saturation!r}", f"use {top} (the largest code) unless the camera clips lower")
    else:
        saturation = _number(saturation, scene, "saturation", positive=True, allow_none=True)
    # the photos' pixel filter: the box, convolved with a Gaussian of psf_sigma pixels (lens blur, demosaicing)
    try:
        psf_sigma = check_psf_sigma(doc.get("psf_sigma", 0.0))
    except ValueError as exc:
        raise _err(scene, "psf_sigma", str(exc), "measure it from a slanted edge, or leave it out for a sharp "
                   "camera (box filter)") from None
    return _Encoding(encoding, bits, saturation, psf_sigma)


def _load_scene_mesh(root: Path, scene: Path, doc: Mapping, msgs: list[str]) -> Mesh:
    mesh_path = _relative_file(root, doc["mesh"], scene, "mesh")
    try:
        mesh = load_mesh(mesh_path)
    except MeshError as exc:
        raise _err(scene, "mesh", str(exc)) from None
    n_degenerate = degenerate_faces(mesh.vertices, mesh.faces)
    if n_degenerate:
        _warn(msgs, f"{mesh_path}: {n_degenerate} of {len(mesh.faces)} faces have zero area (degenerate triangles: "
              f"no surface, no normal); remove them (e.g. Blender: Mesh > Clean Up > Degenerate Dissolve)",
              stacklevel=4)
    return mesh


def _view_lights(scene: Path, i: int, e: Mapping, cam: Camera) -> list:
    """The lights of ``images[i]``, in the world frame, each level below :data:`MAX_LIGHT`."""
    lights_raw = _as_list(e["lights"], scene, f"images[{i}].lights")
    lights = []
    for j, d in enumerate(lights_raw):
        try:
            d = light_to_world(d, cam)
            lights.append(light_from_dict(d))
        except LightError as exc:
            raise _err(scene, f"images[{i}].lights[{j}]", str(exc)) from None
        for key in _LIGHT_LEVELS[d["type"]]:
            level = float(np.abs(np.asarray(d[key], dtype=np.float64)).max())
            if level >= MAX_LIGHT:
                raise _err(scene, f"images[{i}].lights[{j}].{key}", f"{level:.3g} is beyond the {MAX_LIGHT:.0e} "
                           f"shadecap computes with (float32 radiometry overflows)", "give the lights in smaller "
                           "units and scale the exposure instead (pixel = exposure · radiance)")
    return lights


def _load_view(root: Path, scene: Path, i: int, e, mesh: Mesh, seen: dict[str, int], msgs: list[str]) -> View:
    """Entry ``images[i]`` validated into a :class:`View`; ``seen`` (normalised file → index) catches repeats."""
    e = _as_obj(e, scene, f"images[{i}]")
    for key in ("file", "camera", "lights", "exposure"):
        if key not in e:
            raise _err(scene, f"images[{i}].{key}", "is missing",
                       'add it (e.g. "exposure": 1.0)' if key == "exposure" else "see docs/dataset-format.md")
    extra = sorted(set(e) - _VIEW_KEYS)
    if extra:  # stacklevel 5: through _load_views, attributed to load_dataset's caller
        _warn(msgs, f"{scene}: images[{i}]: ignoring unknown field(s) {extra}", stacklevel=5)
    _relative_file(root, e["file"], scene, f"images[{i}].file")
    key = os.path.normpath(e["file"])
    if key in seen:
        raise _err(scene, f"images[{i}].file", f"'{e['file']}' is listed twice (also images[{seen[key]}])")
    seen[key] = i
    try:
        cam = Camera.from_dict(e["camera"])
    except CameraError as exc:
        raise _err(scene, f"images[{i}].camera", str(exc)) from None
    lights = _view_lights(scene, i, e, cam)
    exposure = _number(e["exposure"], scene, f"images[{i}].exposure", positive=True)
    if not EXPOSURE_RANGE[0] < exposure < EXPOSURE_RANGE[1]:
        raise _err(scene, f"images[{i}].exposure", f"{exposure:.3g} is outside ({EXPOSURE_RANGE[0]:.0e}, "
                   f"{EXPOSURE_RANGE[1]:.0e}): the radiances (pixel / exposure) would overflow or vanish in "
                   "float32",
                   "rescale the exposure together with the light intensities")
    name = e.get("name", "")
    if not isinstance(name, str):
        raise _err(scene, f"images[{i}].name", f"must be a string, got {name!r}")
    sees, why = camera_sees_mesh(cam, mesh.vertices, mesh.faces)
    if not sees:
        raise _err(scene, f"images[{i}].camera", f"the camera does not see the mesh: {why}",
                   "check R and t (world-to-camera, OpenCV: x right, y down, z forward) and the mesh units")
    mask = e.get("mask") or ""
    if mask:
        _relative_file(root, mask, scene, f"images[{i}].mask")
        mask = str(Path(mask).as_posix())
    return View(cam, lights, exposure, str(Path(e["file"]).as_posix()), name, mask)


def _load_views(root: Path, scene: Path, doc: Mapping, mesh: Mesh, msgs: list[str]) -> list[View]:
    entries = _as_list(doc["images"], scene, "images")
    seen: dict[str, int] = {}
    views: list[View] = []
    for i, e in enumerate(entries):  # a loop: a comprehension frame would shift _load_view's warning stacklevel
        views.append(_load_view(root, scene, i, e, mesh, seen, msgs))
    return views


def _warn_jpegs(scene: Path, views: Sequence[View], msgs: list[str]) -> None:
    jpegs = [v.file for v in views if Path(v.file).suffix.lower() in JPEG_SUFFIXES]
    if jpegs:
        _warn(msgs, f"{scene}: {len(jpegs)} image(s) are JPEG ({', '.join(jpegs[:3])}{' ...' if len(jpegs) > 3 else ''}"
              "): a camera's JPEG is not pure sRGB (its maker's tone curve, white balance, sharpening, noise "
              "reduction and compression change the values), so the recovered albedo is approximate; for "
              "measurements convert the RAW files to linear 16-bit TIFF or EXR (docs/importing.md)", stacklevel=4)


def _check_image_folder(root: Path, scene: Path, views: Sequence[View]) -> None:
    """The ``images/`` folder, when there is one, holds exactly the listed images (and masks)."""
    img_dir = root / IMAGE_DIR
    if img_dir.is_dir():
        on_disk = sorted(f"{IMAGE_DIR}/{f.name}" for f in img_dir.iterdir()
                         if f.is_file() and f.suffix.lower() in _IMAGE_SUFFIXES and not f.name.startswith("."))
        listed = {os.path.normpath(v.file) for v in views} | {os.path.normpath(v.mask) for v in views if v.mask}
        unlisted = [f for f in on_disk if os.path.normpath(f) not in listed]
        if unlisted:
            raise _err(scene, "images", f"lists {len(views)} image(s) but {img_dir} holds {len(on_disk)} image "
                       f"file(s); not listed: {unlisted[:5]}{' ...' if len(unlisted) > 5 else ''}",
                       "add an entry for each image or remove the extra files")


def _check_view_images(root: Path, views: Sequence[View], enc: _Encoding, msgs: list[str]) -> None:
    """Read every image and mask: errors for unusable files, warnings for empty masks and non-finite pixels."""
    for i, view in enumerate(views):
        _, bad, alpha = _read_view_image(root, view, i, enc.encoding, enc.bits)
        mask = _combine_masks(alpha, _read_view_mask(root, view, i))
        if mask is not None and not bool(mask.any()):
            _warn(msgs, f"{root / (view.mask or view.file)}: images[{i}]: the mask excludes every pixel; the view "
                  "adds nothing to the fit (check the mask's polarity: nonzero = the object)", stacklevel=4)
        if bad:
            H, W = view.camera.height, view.camera.width
            _warn(msgs, f"{root / view.file}: {bad} of {H * W} pixel(s) are NaN or inf; they are kept and the "
                  f"observation stage drops them", stacklevel=4)


def _load_gt(root: Path, scene: Path, g, msgs: list[str]) -> GroundTruth:
    g = _as_obj(g, scene, "gt")
    for key in ("model", "maps"):
        if key not in g:
            raise _err(scene, f"gt.{key}", "is missing")
    extra = sorted(set(g) - _GT_KEYS)
    if extra:
        _warn(msgs, f"{scene}: gt: ignoring unknown field(s) {extra}")
    try:
        spec = model_spec(g["model"])
        model = model_from_spec(spec)
    except ValueError as exc:
        raise _err(scene, "gt.model", str(exc), "use a name from materials.available()") from None
    maps_raw = _as_obj(g["maps"], scene, "gt.maps")
    names = set(model.param_names)
    missing, unexpected = sorted(names - set(maps_raw)), sorted(set(maps_raw) - names)
    if missing or unexpected:
        raise _err(scene, "gt.maps", f"must hold exactly the parameters of model '{model.name}' {sorted(names)}"
                   + (f"; missing {missing}" if missing else "") + (f"; unexpected {unexpected}" if unexpected else ""))
    maps, files, size = {}, {}, None
    for spec_p in model.params:
        rel = maps_raw[spec_p.name]
        fpath = _relative_file(root, rel, scene, f"gt.maps.{spec_p.name}")
        if fpath.suffix.lower() != ".exr":
            raise _err(scene, f"gt.maps.{spec_p.name}", f"'{rel}' must be a linear .exr map")
        try:
            m = read_exr(fpath)
        except ImageIOError as exc:
            raise _err(fpath, None, f"unreadable ground-truth map (gt.maps.{spec_p.name}): {exc}") from None
        if m.shape[2] not in (1, spec_p.channels):
            raise _err(fpath, None, f"map '{spec_p.name}' has {m.shape[2]} channel(s), the parameter has "
                       f"{spec_p.channels}")
        if size is None:
            size = tuple(m.shape[:2])
        elif tuple(m.shape[:2]) != size:
            raise _err(fpath, None, f"map is {m.shape[1]}×{m.shape[0]} but the other gt maps are {size[1]}×{size[0]}",
                       "write every map at the same size")
        try:
            spec_p.check(m, where=str(fpath))
        except ValueError as exc:
            raise _err(fpath, None, str(exc)) from None
        maps[spec_p.name] = m
        files[spec_p.name] = str(Path(rel).as_posix())
    regions, region_names = None, {}
    if g.get("regions") is not None:
        r = _as_obj(g["regions"], scene, "gt.regions")
        if "file" not in r:
            raise _err(scene, "gt.regions.file", "is missing")
        rpath = _relative_file(root, r["file"], scene, "gt.regions.file")
        try:
            raw = read_png(rpath, "linear")
        except ImageIOError as exc:
            raise _err(rpath, None, f"unreadable region map (gt.regions.file): {exc}") from None
        depth = _png_bit_depth(rpath) or 8
        if raw.shape[2] != 1:
            raise _err(rpath, None, f"region map must be a 1-channel gray PNG, got {raw.shape[2]} channels")
        regions = torch.round(raw[..., 0].double() * ((1 << depth) - 1)).long()
        if size is not None and tuple(regions.shape) != size:
            raise _err(rpath, None, f"region map is {regions.shape[1]}×{regions.shape[0]}, the maps are "
                       f"{size[1]}×{size[0]}")
        names_raw = _as_obj(r.get("names", {}), scene, "gt.regions.names")
        try:
            region_names = {int(k): str(v) for k, v in names_raw.items()}
        except ValueError:
            raise _err(scene, "gt.regions.names", "keys must be integer region ids (as strings)") from None
        ids = sorted(int(x) for x in torch.unique(regions))
        unnamed = [k for k in ids if k not in region_names]
        if unnamed:
            raise _err(scene, "gt.regions.names", f"region id(s) {unnamed} in {rpath.name} have no name",
                       "name every id that occurs in the map")
    render = _as_obj(g.get("render", {}) or {}, scene, "gt.render")
    photo = _as_obj(g.get("photo", {}) or {}, scene, "gt.photo")
    return GroundTruth(spec, maps, regions, region_names, dict(render), dict(photo), files)


# ----------------------------------------------------------------------------------------------
# writing


def scene_json_text(x, indent: int = 0) -> str:
    """JSON with objects indented and lists of numbers (and of number lists, e.g. K) on one line."""
    pad, inner = " " * indent, " " * (indent + 2)
    flat = lambda v: not isinstance(v, (dict, list)) or (isinstance(v, list) and all(
        not isinstance(w, (dict, list)) for w in v))
    if isinstance(x, dict):
        if not x:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {scene_json_text(v, indent + 2)}" for k, v in x.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(x, list):
        if all(flat(v) for v in x):
            return json.dumps(x, allow_nan=False, separators=(", ", ": "))
        return "[\n" + ",\n".join(inner + scene_json_text(v, indent + 2) for v in x) + "\n" + pad + "]"
    return json.dumps(x, allow_nan=False)


def write_dataset(
    out_dir,
    mesh: Mesh,
    views: Sequence[View],
    images: Sequence[Tensor],
    *,
    encoding: str = "linear",
    bits: int = 8,
    saturation: float | int | None = None,
    half: bool = False,
    gt: GroundTruth | None = None,
    meta: Mapping | None = None,
    overwrite: bool = False,
    validate: bool = True,
    masks: Sequence[Tensor | None] | None = None,
    psf_sigma: float = 0.0,
) -> Path:
    """Write a dataset folder atomically and return its path.

    Everything is written into a temporary folder in ``out_dir``'s parent (``.NAME.tmp-*``), then
    (with ``validate``) read back with :func:`load_dataset`, then moved in place with
    :func:`os.replace` (:func:`capture.outputs.atomic_folder`: files and folders get the umask's
    permissions, a replaced dataset is removed). ``out_dir`` is checked before anything is written
    (:func:`capture.outputs.check_output`: it exists only with ``overwrite``, its folder can be
    written). On any failure the temporary folder is removed and ``out_dir`` is left as it was
    (absent, or the previous dataset with ``overwrite``).

    Args:
        out_dir: destination folder; must not exist unless ``overwrite``.
        mesh: the object (written as ``mesh.obj`` with UVs and normals).
        views: one :class:`View` per image; an empty ``file`` is named ``images/NNN.exr|png``.
        images: per view ``[H, W, 3]`` (or ``[H, W]``) linear file values — exposure·L as the photo
            model made them (for "srgb", values in [0, 1] that are encoded and quantised on write).
        encoding: "linear" (float EXR; ``half`` for 16-bit half floats) or "srgb" (PNG of ``bits``).
        saturation: clipping level in file units; default: ``2^bits − 1`` for "srgb", None for "linear".
        gt: optional ground truth: maps go to ``gt/<param>.exr`` (float32), regions to ``gt/regions.png``.
        meta: free-form JSON-able metadata.
        overwrite: replace an existing ``out_dir``.
        validate: load the written folder before moving it in place (recommended).
        masks: optional, per view a ``[H, W]`` bool mask (True = the object, usable) or None; each given one is
            written as an 8-bit PNG (255 / 0) at the view's ``mask`` path or ``masks/NNN.png``.
        psf_sigma: σ (pixels) of a Gaussian blur in the photos' pixel filter, written when > 0.

    Raises:
        DatasetError: bad arguments, ``out_dir`` exists, or validation of the written folder failed.
    """
    out = Path(out_dir)
    if encoding not in ENCODINGS:
        raise DatasetError(f"write_dataset: encoding must be one of {sorted(ENCODINGS)}, got {encoding!r}")
    if encoding == "srgb" and bits not in (8, 16):
        raise DatasetError(f"write_dataset: bits must be 8 or 16, got {bits!r}")
    if not isinstance(mesh, Mesh):
        raise DatasetError(f"write_dataset: mesh must be a renderer.mesh.Mesh, got {type(mesh).__name__}")
    if len(views) == 0 or len(views) != len(images):
        raise DatasetError(f"write_dataset: need one image per view and at least one view, got {len(views)} views "
                           f"and {len(images)} images")
    if masks is not None and len(masks) != len(views):
        raise DatasetError(f"write_dataset: masks must hold one entry (a mask or None) per view, got {len(masks)} for "
                           f"{len(views)} views")
    try:
        psf_sigma = check_psf_sigma(psf_sigma)
    except ValueError as exc:
        raise DatasetError(f"write_dataset: {exc}") from None
    check_output(out, force=overwrite, error=DatasetError, force_flag="overwrite=True (--overwrite)")
    if encoding == "srgb" and saturation is None:
        saturation = (1 << bits) - 1
    ext = ".exr" if encoding == "linear" else ".png"

    try:
        with atomic_folder(out, force=overwrite, error=DatasetError,
                           force_flag="overwrite=True (--overwrite)") as tmp:
            _write_into(tmp, mesh, views, images, encoding, ext, bits, saturation, half, gt, meta, validate, masks,
                        psf_sigma)
    except DatasetError as exc:
        raise DatasetError(f"{exc} (nothing was written to {out})" if "nothing was written" not in str(exc)
                           else str(exc)) from None
    return out


def _write_into(tmp: Path, mesh, views, images, encoding, ext, bits, saturation, half, gt, meta, validate,
                masks=None, psf_sigma: float = 0.0) -> None:
    """Write a dataset's files into the (temporary) folder ``tmp`` and, with ``validate``, load it back."""
    (tmp / IMAGE_DIR).mkdir()
    save_mesh(mesh, tmp / "mesh.obj")
    entries = []
    for i, (view, img) in enumerate(zip(views, images, strict=True)):
        if not isinstance(view, View):
            raise DatasetError(f"write_dataset: views[{i}] must be a View, got {type(view).__name__}")
        rel = view.file or f"{IMAGE_DIR}/{i:03d}{ext}"
        if Path(rel).suffix.lower() != ext:
            raise DatasetError(f"write_dataset: views[{i}].file '{rel}' must end in {ext} for encoding "
                               f"'{encoding}'")
        dest = _relative_file(tmp, rel, "write_dataset", f"views[{i}].file")
        if not isinstance(img, Tensor) or img.dim() not in (2, 3):
            raise DatasetError(f"write_dataset: images[{i}] must be a tensor [H, W, 3], got "
                               f"{getattr(img, 'shape', type(img).__name__)}")
        if img.shape[0] != view.camera.height or img.shape[1] != view.camera.width:
            raise DatasetError(f"write_dataset: images[{i}] is {img.shape[1]}×{img.shape[0]} but views[{i}].camera "
                               f"is {view.camera.width}×{view.camera.height}")
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            if encoding == "linear":
                write_exr(dest, img, half=half, allow_nonfinite=True)
            else:
                write_png(dest, torch.nan_to_num(img.detach().cpu(), nan=0.0), bits=bits, transfer="srgb")
        except ImageIOError as exc:
            raise DatasetError(f"write_dataset: images[{i}]: {exc}") from None
        entry = {"file": rel, "camera": view.camera.to_dict(),
                 "lights": [light_to_dict(light) for light in view.lights], "exposure": float(view.exposure)}
        if view.name:
            entry["name"] = view.name
        m = masks[i] if masks is not None else None
        if m is not None:
            if not isinstance(m, Tensor) or tuple(m.shape) != (view.camera.height, view.camera.width):
                raise DatasetError(f"write_dataset: masks[{i}] must be a bool tensor [H, W] = "
                                   f"[{view.camera.height}, {view.camera.width}], got "
                                   f"{tuple(m.shape) if isinstance(m, Tensor) else type(m).__name__}")
            mrel = view.mask or f"{MASK_DIR}/{i:03d}.png"
            mdest = _relative_file(tmp, mrel, "write_dataset", f"views[{i}].mask")
            mdest.parent.mkdir(parents=True, exist_ok=True)
            write_png(mdest, m.detach().cpu().bool().double(), bits=8, transfer="linear")
            entry["mask"] = mrel
        elif view.mask:
            raise DatasetError(f"write_dataset: views[{i}].mask names '{view.mask}' but no mask was given for it; "
                               "pass masks=[...] or clear the view's mask")
        entries.append(entry)
    doc = {"format": FORMAT, "version": VERSION, "mesh": "mesh.obj", "encoding": encoding}
    if encoding == "srgb":
        doc["bits"] = bits
    doc["saturation"] = saturation
    if psf_sigma:
        doc["psf_sigma"] = float(psf_sigma)
    doc["images"] = entries
    if gt is not None:
        doc["gt"] = _write_gt(tmp, gt)
    doc["meta"] = jsonable(dict(meta or {}))
    text = scene_json_text(jsonable(doc))
    (tmp / SCENE_FILE).write_text(text + "\n", encoding="utf-8")
    if validate:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DatasetWarning)
            load_dataset(tmp)


def _write_gt(tmp: Path, gt: GroundTruth) -> dict:
    try:
        spec = model_spec(gt.model)
        model = model_from_spec(spec)
    except ValueError as exc:
        raise DatasetError(f"write_dataset: gt.model: {exc}") from None
    names = set(model.param_names)
    if set(gt.maps) != names:
        raise DatasetError(f"write_dataset: gt.maps must hold exactly {sorted(names)} (model '{model.name}'), got "
                           f"{sorted(gt.maps)}")
    (tmp / GT_DIR).mkdir()
    maps = {}
    for p in model.params:
        rel = f"{GT_DIR}/{p.name}.exr"
        try:
            p.check(gt.maps[p.name], where="write_dataset: gt")
            write_exr(tmp / rel, gt.maps[p.name])
        except (ValueError, TypeError) as exc:
            raise DatasetError(f"write_dataset: gt.maps.{p.name}: {exc}") from None
        maps[p.name] = rel
    out = {"model": spec, "maps": maps}
    if gt.regions is not None:
        r = gt.regions
        if not isinstance(r, Tensor) or r.dim() != 2 or r.is_floating_point() or r.min() < 0 or r.max() > 65535:
            raise DatasetError("write_dataset: gt.regions must be an integer tensor [H, W] of ids in [0, 65535]")
        rbits = 8 if int(r.max()) <= 255 else 16
        write_png(tmp / GT_DIR / "regions.png", r.double() / ((1 << rbits) - 1), bits=rbits, transfer="linear")
        out["regions"] = {"file": f"{GT_DIR}/regions.png", "names": {str(k): v for k, v in gt.region_names.items()}}
    if gt.render:
        out["render"] = dict(gt.render)
    if gt.photo:
        out["photo"] = dict(gt.photo)
    return out
