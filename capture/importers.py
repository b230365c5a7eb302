"""Importers: real captures from COLMAP, NeRF ``transforms.json`` or OpenCV calibration YAML → a shadecap dataset.

Each importer reads the cameras of one tool, maps its conventions onto shadecap's (OpenCV pinhole, pixel
centres at integer coordinates, world-to-camera ``R``, ``t``; ``docs/conventions.md``), and writes a dataset
folder (``docs/dataset-format.md``) with the mesh, the photos, optional masks and the lights:

- :func:`import_colmap` — ``cameras.txt``/``images.txt`` or ``cameras.bin``/``images.bin``: the quaternion
  (w, x, y, z) and t are world-to-camera in the OpenCV frame already; COLMAP's image coordinates put the centre
  of the top-left pixel at (0.5, 0.5), so cx, cy − ½.
- :func:`import_transforms_json` — NeRF / instant-ngp / nerfstudio: ``transform_matrix`` is camera-to-world in
  the OpenGL camera frame (x right, y up, looking down −z) → flip y and z, invert; ``camera_angle_x`` or
  ``fl_x``/``fl_y``/``cx``/``cy`` (cx, cy in COLMAP's corner-origin convention → − ½; default the image centre).
- :func:`import_opencv_yaml` — ``cv2.FileStorage`` YAML/XML: ``camera_matrix``/``K``,
  ``distortion_coefficients``/``D``, per image ``R``/``t`` or ``rvec``/``tvec`` (world-to-camera, as
  ``solvePnP`` gives them); the conventions are already shadecap's.

The choices every importer shares are one :class:`ImportOptions`: the mesh (and ``unwrap`` to give a mesh
without UVs an xatlas atlas), the photo folder, masks (a folder of mask images or the photos' alpha channel), a
flash fixed to the camera (:class:`Flash`, position in the camera frame: resolved here to a world-space point
light per photo), world-space lights, undistortion, colour encoding and exposure.

Images are copied byte for byte when they need no undistortion (a JPEG is never recompressed). With lens
distortion (COLMAP SIMPLE_RADIAL/RADIAL/OPENCV/FULL_OPENCV, ``k1..`` in transforms.json, ``D`` in YAML), every
image is undistorted to the *same* K (``cv2.initUndistortRectifyMap`` with ``newCameraMatrix = K``, bilinear
``cv2.remap`` on linear values) and written losslessly (16-bit sRGB PNG, or float EXR for linear input);
masks are remapped with nearest-neighbour interpolation, and a pixel whose bilinear support reaches outside the
photo or touches a saturated source pixel is masked out. The inputs are never modified or moved; the dataset is
written atomically (a temporary folder validated by :func:`capture.dataset.load_dataset`, then renamed).
"""

from __future__ import annotations

import json
import math
import numbers
import shutil
import struct
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from renderer.camera import Camera, CameraError
from renderer.imageio import ImageIOError, decode, read_exr, write_exr, write_png
from renderer.lights import LightError, PointLight, light_from_dict, light_to_dict
from renderer.mesh import Mesh, MeshError, load_mesh, save_mesh

from .dataset import (
    FORMAT,
    IMAGE_DIR,
    MASK_DIR,
    SCENE_FILE,
    VERSION,
    DatasetError,
    DatasetWarning,
    light_to_world,
    load_dataset,
    read_raster,
    scene_json_text,
)
from .outputs import atomic_folder, check_output, jsonable

__all__ = [
    "CaptureImportError", "ImportOptions", "Flash", "ImportResult", "import_colmap", "import_transforms_json",
    "import_opencv_yaml", "unwrap_mesh", "read_colmap_model", "COLMAP_MODELS", "IMAGE_SUFFIXES",
]

#: Photo file types the importers read (and the encoding each is taken in by default).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")
#: COLMAP camera models: id → (name, parameter names). Those with distortion are undistorted on import.
COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k1")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
}
_COLMAP_BY_NAME = {name: (mid, params) for mid, (name, params) in COLMAP_MODELS.items()}
#: The COLMAP models shadecap can import (pinhole, or OpenCV's radial-tangential distortion, undistorted here).
COLMAP_SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_ENCODINGS = ("auto", "srgb", "linear")


class CaptureImportError(DatasetError):
    """A capture that cannot be imported; the message names the file, the field and the fix."""


# ----------------------------------------------------------------------------------------------
# options


def _vec3(x, what: str) -> tuple[float, float, float]:
    try:
        v = tuple(float(c) for c in x)
    except (TypeError, ValueError):
        v = ()
    if len(v) != 3 or not all(math.isfinite(c) for c in v):
        raise CaptureImportError(f"{what} must be 3 finite numbers, got {x!r}")
    return v


@dataclass(frozen=True)
class Flash:
    """A light fixed to the camera: a point light at ``position`` in the *camera* frame of every photo.

    Attributes:
        position: (x, y, z) in the OpenCV camera frame (x right, y down, z forward), world units; (0, 0, 0) is
            the camera centre (a ring flash or a phone's LED a few millimetres from the lens is close to it).
        intensity: RGB radiant intensity (W/sr for metres; a scalar means grey), ≥ 0.

    Resolved by the importer to a world-space point light per photo: ``Rᵀ (position − t)``.
    """

    position: tuple = (0.0, 0.0, 0.0)
    intensity: tuple | float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "position", _vec3(self.position, "Flash.position"))
        i = self.intensity
        if isinstance(i, numbers.Real) and not isinstance(i, bool):
            i = (float(i),) * 3
        i = _vec3(i, "Flash.intensity")
        if min(i) < 0:
            raise CaptureImportError(f"Flash.intensity must be ≥ 0, got {i}")
        object.__setattr__(self, "intensity", i)

    def to_world(self, camera: Camera) -> PointLight:
        R, t = camera.R.double(), camera.t.double()
        p = R.T @ (torch.tensor(self.position, dtype=torch.float64) - t)
        return PointLight(p.tolist(), list(self.intensity))


@dataclass
class ImportOptions:
    """Everything an importer needs besides the camera file (validated on construction).

    Attributes:
        mesh: the object's mesh file (OBJ, PLY, GLB), in the same world frame and unit as the cameras.
        images: folder the photo names are relative to. COLMAP and OpenCV YAML: required (COLMAP's image names
            are relative to the folder given to its feature extractor). transforms.json: default the JSON's folder.
        masks: None (no masks), a folder of mask images (PNG/any 8/16-bit image, nonzero = the object) named
            like the photos (``<name>.png``, ``<stem>.png`` or COLMAP's ``<name>.png`` with the photo's suffix
            kept), or ``"alpha"``: the photos' alpha channel (RGBA PNG) is the mask.
        flash: a light fixed to the camera (:class:`Flash`), or a sequence of them; resolved per photo.
        lights: lights for every photo as ``scene.json`` light entries (``renderer.lights.light_to_dict`` dicts,
            e.g. studio lamps in world space, or ``"frame": "camera"`` entries that move with the camera).
        undistort: undistort photos whose camera has lens distortion (default). False: the photos are taken as
            already undistorted and the coefficients are ignored (with a warning).
        encoding: "auto" (8-bit PNG/JPEG and 16-bit PNG → "srgb"; EXR, float and 16-bit TIFF → "linear"),
            "srgb" or "linear". Camera JPEGs are not pure sRGB (see docs/importing.md).
        exposure: pixel value = exposure · radiance, for every photo (> 0).
        saturation: clipping level in file units (dataset ``saturation``); None: the top code for integer
            images, nothing for float images.
        unwrap: give the mesh a new UV atlas with xatlas (``pip install xatlas``); needed for a mesh without UVs.
    """

    mesh: str | Path
    images: str | Path | None = None
    masks: str | Path | None = None
    flash: Flash | Sequence[Flash] | None = None
    lights: Sequence[Mapping] = field(default_factory=list)
    undistort: bool = True
    encoding: str = "auto"
    exposure: float = 1.0
    saturation: float | int | None = None
    unwrap: bool = False

    def __post_init__(self):
        if not isinstance(self.mesh, (str, Path)) or not str(self.mesh).strip():
            raise CaptureImportError(f"ImportOptions.mesh must be the path of the object's mesh file, got "
                                     f"{self.mesh!r}")
        self.mesh = Path(self.mesh)
        if not self.mesh.is_file():
            raise CaptureImportError(f"{self.mesh}: mesh file does not exist (ImportOptions.mesh / --mesh)")
        if self.images is not None:
            self.images = Path(self.images)
            if not self.images.is_dir():
                raise CaptureImportError(f"{self.images}: image folder does not exist (ImportOptions.images / "
                                         f"--images)")
        if self.masks is not None:
            if isinstance(self.masks, str) and self.masks == "alpha":
                pass
            else:
                self.masks = Path(self.masks)
                if not self.masks.is_dir():
                    raise CaptureImportError(f"{self.masks}: mask folder does not exist (ImportOptions.masks / "
                                             f"--masks); "
                                       "give a folder of mask images or 'alpha'")
        if isinstance(self.flash, Flash):
            self.flash = (self.flash,)
        elif self.flash is None:
            self.flash = ()
        else:
            if isinstance(self.flash, (str, bytes)) or not all(isinstance(f, Flash) for f in self.flash):
                raise CaptureImportError(f"ImportOptions.flash must be a Flash or a list of Flash, got {self.flash!r}")
            self.flash = tuple(self.flash)
        if isinstance(self.lights, Mapping) or isinstance(self.lights, (str, bytes)):
            raise CaptureImportError("ImportOptions.lights must be a list of light dicts, e.g. [{'type': 'point', "
                               "'position': [0, 0, 5], 'intensity': 10}]")
        probe = Camera(torch.eye(3, dtype=torch.float64), torch.eye(3), torch.zeros(3), 1, 1)
        for j, d in enumerate(self.lights):
            try:  # checked now; resolved per photo (a "frame": "camera" light moves with the camera)
                light_from_dict(light_to_world(dict(d) if isinstance(d, Mapping) else d, probe))
            except LightError as exc:
                raise CaptureImportError(f"ImportOptions.lights[{j}]: {exc}") from None
        self.lights = [dict(d) if isinstance(d, Mapping) else d for d in self.lights]
        if not self.flash and not self.lights:
            raise CaptureImportError("no lights: give a flash fixed to the camera (ImportOptions.flash / --flash X,Y,Z "
                               "--flash-intensity I) or world-space lights (ImportOptions.lights / --lights FILE)")
        if not isinstance(self.undistort, bool) or not isinstance(self.unwrap, bool):
            raise CaptureImportError("ImportOptions.undistort and ImportOptions.unwrap must be True or False")
        if self.encoding not in _ENCODINGS:
            raise CaptureImportError(f"ImportOptions.encoding must be one of {list(_ENCODINGS)}, got {self.encoding!r}")
        if (isinstance(self.exposure, bool) or not isinstance(self.exposure, numbers.Real)
                or not math.isfinite(self.exposure) or self.exposure <= 0):
            raise CaptureImportError(f"ImportOptions.exposure must be a finite number > 0, got {self.exposure!r}")
        if self.saturation is not None and (isinstance(self.saturation, bool) or not isinstance(
                self.saturation, numbers.Real) or not self.saturation > 0):
            raise CaptureImportError(f"ImportOptions.saturation must be a positive number or None, got "
                                     f"{self.saturation!r}")

    def world_lights(self, camera: Camera) -> list:
        """The lights of a photo taken by ``camera``: the flashes, then :attr:`lights`, in world space."""
        return [f.to_world(camera) for f in self.flash] + [light_from_dict(light_to_world(d, camera))
                                                           for d in self.lights]


@dataclass
class ImportResult:
    """What an importer wrote: the dataset folder and a summary (printed by ``shadecap import``)."""

    out: Path
    source: str
    n_images: int
    encoding: str
    bits: int | None
    undistorted: int
    masks: int
    unwrapped: bool
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> str:
        parts = [f"wrote {self.out}: {self.n_images} image(s) from {self.source}, encoding {self.encoding}"
                 + (f" ({self.bits}-bit)" if self.bits else "")]
        if self.undistorted:
            parts.append(f"{self.undistorted} undistorted to pinhole")
        if self.masks:
            parts.append(f"{self.masks} masked")
        if self.unwrapped:
            parts.append("mesh unwrapped with xatlas")
        return ", ".join(parts)


# ----------------------------------------------------------------------------------------------
# one photo as the importers see it


@dataclass
class _Shot:
    """A photo to import: its file, its shadecap camera, its distortion (OpenCV order) and its name."""

    image: Path
    camera: Camera
    dist: np.ndarray | None
    name: str
    mask: Path | None = None  # a per-photo mask named by the source file (nerfstudio mask_path)
    where: str = ""


def _pinhole(fx, fy, cx, cy, W, H, R, t, where: str) -> Camera:
    try:
        return Camera([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], R, t, int(W), int(H), dtype=torch.float64)
    except CameraError as exc:
        raise CaptureImportError(f"{where}: {exc}") from None


# ----------------------------------------------------------------------------------------------
# COLMAP


def _quat_to_R(q) -> np.ndarray:
    w, x, y, z = (float(c) for c in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0:
        raise ValueError("zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _read_exact(fh, n: int, path: Path, what: str) -> bytes:
    data = fh.read(n)
    if len(data) != n:
        raise CaptureImportError(f"{path}: truncated while reading {what}; re-export the model (colmap "
                                 f"model_converter)")
    return data


def read_colmap_model(model_dir) -> tuple[dict, list[dict], str]:
    """Read a COLMAP sparse model's cameras and images (text or binary, COLMAP's documented layouts).

    Returns ``(cameras, images, kind)``: cameras ``{id: {"model": NAME, "width", "height", "params": [...]}}``,
    images ``[{"id", "qvec" (w, x, y, z), "tvec", "camera_id", "name"}]`` (2-D points skipped), kind
    ``"text"``/``"binary"``. Binary is read when ``cameras.bin`` and ``images.bin`` exist, else text.

    Raises:
        CaptureImportError: missing files, a malformed line or a truncated binary file (naming the file and line).
    """
    d = Path(model_dir)
    if not d.is_dir():
        raise CaptureImportError(f"{d}: COLMAP model folder does not exist; give the folder holding "
                                 f"cameras.txt/images.txt "
                           "or cameras.bin/images.bin (e.g. sparse/0)")
    if (d / "cameras.bin").is_file() and (d / "images.bin").is_file():
        return _colmap_cameras_bin(d / "cameras.bin"), _colmap_images_bin(d / "images.bin"), "binary"
    if (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
        return _colmap_cameras_txt(d / "cameras.txt"), _colmap_images_txt(d / "images.txt"), "text"
    raise CaptureImportError(f"{d}: holds neither cameras.txt + images.txt nor cameras.bin + images.bin; give COLMAP's "
                       "model folder (e.g. sparse/0), or export it with colmap model_converter --output_type TXT")


def _data_lines(path: Path):
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield n, s


def _colmap_cameras_txt(path: Path) -> dict:
    cams = {}
    for n, s in _data_lines(path):
        f = s.split()
        try:
            cid, model, W, H = int(f[0]), f[1], int(f[2]), int(f[3])
            params = [float(x) for x in f[4:]]
        except (ValueError, IndexError):
            raise CaptureImportError(f"{path}:{n}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got "
                                     f"{s!r}") from None
        cams[cid] = _colmap_camera(path, n, model, W, H, params)
    return cams


def _colmap_camera(path, n, model, W, H, params) -> dict:
    if model not in _COLMAP_BY_NAME:
        raise CaptureImportError(f"{path}:{n}: unknown COLMAP camera model {model!r}")
    want = len(_COLMAP_BY_NAME[model][1])
    if len(params) != want:
        raise CaptureImportError(f"{path}:{n}: camera model {model} has {want} parameters, got {len(params)}")
    return {"model": model, "width": W, "height": H, "params": params}


def _colmap_images_txt(path: Path) -> list[dict]:
    imgs = []
    lines = list(_data_lines_keep_empty(path))
    k = 0
    while k < len(lines):
        n, s = lines[k]
        if not s:
            k += 1
            continue
        f = s.split(maxsplit=9)
        try:
            img = {"id": int(f[0]), "qvec": [float(x) for x in f[1:5]], "tvec": [float(x) for x in f[5:8]],
                   "camera_id": int(f[8]), "name": f[9]}
        except (ValueError, IndexError):
            raise CaptureImportError(f"{path}:{n}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got "
                                     f"{s!r}") from None
        imgs.append(img)
        k += 2  # the POINTS2D line (possibly empty) follows each image line
    return imgs


def _data_lines_keep_empty(path: Path):
    """images.txt: two lines per image, the second (2-D points) possibly empty; comments dropped."""
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        if not line.strip().startswith("#"):
            yield n, line.strip()


def _colmap_cameras_bin(path: Path) -> dict:
    cams = {}
    with open(path, "rb") as fh:
        (count,) = struct.unpack("<Q", _read_exact(fh, 8, path, "the camera count"))
        for k in range(count):
            cid, mid, W, H = struct.unpack("<iiQQ", _read_exact(fh, 24, path, f"camera {k}"))
            if mid not in COLMAP_MODELS:
                raise CaptureImportError(f"{path}: camera {cid}: unknown COLMAP model id {mid}")
            name, pnames = COLMAP_MODELS[mid]
            params = list(struct.unpack(f"<{len(pnames)}d", _read_exact(fh, 8 * len(pnames), path, f"camera {cid}")))
            cams[cid] = {"model": name, "width": W, "height": H, "params": params}
    return cams


def _colmap_images_bin(path: Path) -> list[dict]:
    imgs = []
    with open(path, "rb") as fh:
        (count,) = struct.unpack("<Q", _read_exact(fh, 8, path, "the image count"))
        for k in range(count):
            vals = struct.unpack("<idddddddi", _read_exact(fh, 64, path, f"image {k}"))
            name = b""
            while True:
                c = _read_exact(fh, 1, path, f"image {vals[0]}'s name")
                if c == b"\0":
                    break
                name += c
            (npts,) = struct.unpack("<Q", _read_exact(fh, 8, path, f"image {vals[0]}'s point count"))
            _read_exact(fh, 24 * npts, path, f"image {vals[0]}'s 2-D points")
            imgs.append({"id": vals[0], "qvec": list(vals[1:5]), "tvec": list(vals[5:8]), "camera_id": vals[8],
                         "name": name.decode("utf-8", errors="replace")})
    return imgs


def _colmap_intrinsics(cam: dict, where: str) -> tuple[float, float, float, float, np.ndarray | None]:
    """(fx, fy, cx, cy) in shadecap's integer-centre convention and OpenCV distortion, from a COLMAP camera."""
    model, p = cam["model"], cam["params"]
    if model not in COLMAP_SUPPORTED:
        raise CaptureImportError(f"{where}: COLMAP camera model {model} is not supported (supported: "
                           f"{', '.join(COLMAP_SUPPORTED)}); undistort the images first with colmap "
                           "image_undistorter, which writes PINHOLE cameras")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        k = p[3:]
        dist = np.array([k[0] if k else 0.0, k[1] if len(k) > 1 else 0.0, 0.0, 0.0]) if k else None
    else:
        fx, fy, cx, cy = p[:4]
        k = p[4:]
        if model == "OPENCV":
            dist = np.array(k, dtype=np.float64)  # k1 k2 p1 p2
        elif model == "FULL_OPENCV":
            dist = np.array(k, dtype=np.float64)  # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's own order
        else:
            dist = None
    # COLMAP: the top-left pixel's centre is (0.5, 0.5); shadecap (OpenCV): (0, 0)
    return fx, fy, cx - 0.5, cy - 0.5, dist


def import_colmap(model_dir, out, options: ImportOptions, *, overwrite: bool = False) -> ImportResult:
    """Import a COLMAP sparse model (``cameras``/``images`` as .txt or .bin) and its photos as a shadecap dataset.

    Conventions mapped: COLMAP's pose (quaternion w, x, y, z and t) is world-to-camera in the OpenCV camera frame,
    as shadecap's; its principal point is in image coordinates whose top-left pixel centre is (0.5, 0.5), so
    ``cx, cy`` are shifted by −½. Images are taken in name order; ``options.images`` is the folder COLMAP's image
    names are relative to. The mesh must be in the model's world frame and unit (e.g. meshed by COLMAP itself, or
    aligned to it).

    Args:
        model_dir: COLMAP's model folder (``sparse/0``).
        out: the dataset folder to write (must not exist unless ``overwrite``).
        options: :class:`ImportOptions` (``images`` is required).

    Raises:
        CaptureImportError (a ``ValueError``): naming the file, the field and the fix; nothing is written then.
    """
    options = _check_options(options, "import_colmap")
    if options.images is None:
        raise CaptureImportError("import_colmap: give the folder COLMAP's image names are relative to "
                           "(ImportOptions.images / --images), e.g. the project's images/ folder")
    cams, imgs, kind = read_colmap_model(model_dir)
    if not imgs:
        raise CaptureImportError(f"{model_dir}: the COLMAP model has no registered images")
    shots = []
    for img in sorted(imgs, key=lambda x: x["name"]):
        where = f"{model_dir} image {img['id']} ({img['name']})"
        cam = cams.get(img["camera_id"])
        if cam is None:
            raise CaptureImportError(f"{where}: camera {img['camera_id']} is not in the model's cameras file")
        fx, fy, cx, cy, dist = _colmap_intrinsics(cam, where)
        try:
            R = _quat_to_R(img["qvec"])
        except ValueError:
            raise CaptureImportError(f"{where}: its quaternion is zero") from None
        camera = _pinhole(fx, fy, cx, cy, cam["width"], cam["height"], R, img["tvec"], where)
        shots.append(_Shot(options.images / img["name"], camera, dist, img["name"], where=where))
    return _write(shots, out, options, overwrite, f"COLMAP {kind} model {model_dir}", {"model": Path(model_dir)})


# ----------------------------------------------------------------------------------------------
# transforms.json (NeRF / instant-ngp / nerfstudio)

_TJ_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "k1", "k2", "k3", "k4",
                  "p1", "p2", "camera_model")


def _find_image(base: Path, rel: str, where: str) -> Path:
    p = base / rel
    if p.is_file():
        return p
    if not p.suffix or p.suffix.lower() not in IMAGE_SUFFIXES:  # NeRF's Blender scenes omit the suffix
        for s in IMAGE_SUFFIXES:
            q = p.with_name(p.name + s)
            if q.is_file():
                return q
    raise CaptureImportError(f"{where}: image {p} does not exist (file_path {rel!r} is relative to {base})")


def import_transforms_json(path, out, options: ImportOptions, *, overwrite: bool = False) -> ImportResult:
    """Import a NeRF / instant-ngp / nerfstudio ``transforms.json`` and its photos as a shadecap dataset.

    Conventions mapped: ``transform_matrix`` (4×4 or 3×4) is camera-to-world with the OpenGL camera frame (x right,
    y up, looking down −z): shadecap's world-to-camera is ``R = (M₃ₓ₃ · diag(1, −1, −1))ᵀ``, ``t = −R · M[:3, 3]``.
    Intrinsics per frame or at the top level: ``fl_x``/``fl_y`` (pixels), or ``camera_angle_x`` (horizontal field
    of view, radians: fl_x = ½ w / tan(½ camera_angle_x); fl_y = fl_x unless ``fl_y``/``camera_angle_y``);
    ``cx``/``cy`` are in the corner-origin convention of COLMAP, from which these files are made (the top-left
    pixel's centre is (0.5, 0.5); default w/2, h/2), so shadecap's are ``cx − ½``, ``cy − ½``. ``w``/``h`` default
    to the image's size. ``k1, k2, p1, p2`` (and ``k3``) are OpenCV distortion (``camera_model`` "OPENCV", the
    default); "OPENCV_FISHEYE" is refused. A frame's ``mask_path`` (nerfstudio) is its mask when
    ``options.masks`` is None. instant-ngp's ``scale``/``offset``/``aabb_scale`` only place the scene in its
    training cube and are ignored: the mesh must be in the frame of ``transform_matrix``.

    Args:
        path: the ``transforms.json`` file (or its folder).
        out: the dataset folder to write.
        options: :class:`ImportOptions`; ``images`` defaults to the JSON's folder (``file_path`` is relative to it).

    Raises:
        CaptureImportError: naming the file, the frame, the field and the fix; nothing is written then.
    """
    options = _check_options(options, "import_transforms_json")
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    if not path.is_file():
        raise CaptureImportError(f"{path}: transforms.json does not exist")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CaptureImportError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise CaptureImportError(f"{path}: field 'frames' must be a non-empty list of frames "
                           "({'file_path': ..., 'transform_matrix': [[...]]})")
    if "applied_transform" in doc:
        warnings.warn(DatasetWarning(
            f"{path}: has 'applied_transform' (nerfstudio's world differs from the COLMAP model it came from): the "
            "mesh must be in the frame of transform_matrix; a mesh in COLMAP's frame needs that transform applied, or "
            "import the COLMAP model itself (shadecap import colmap)"), stacklevel=2)
    base = options.images or path.parent
    shots = []
    for k, fr in enumerate(doc["frames"]):
        where = f"{path}: frames[{k}]"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise CaptureImportError(f"{where}: needs 'file_path' and 'transform_matrix'")
        img = _find_image(base, str(fr["file_path"]), where)
        get = lambda key, fr=fr: fr.get(key, doc.get(key))  # noqa: E731 — a frame's own value wins
        model = get("camera_model") or "OPENCV"
        if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
            raise CaptureImportError(f"{where}: camera_model {model!r} is not supported (OPENCV, PINHOLE); "
                                     f"undistort the "
                               "images first (e.g. nerfstudio's or COLMAP's undistorter) and drop the coefficients")
        W, H = get("w"), get("h")
        if W is None or H is None:
            arr = _read_photo(img, where)[0]
            H, W = arr.shape[:2]
        try:
            W, H = int(W), int(H)
            if get("fl_x") is not None:
                fx = float(get("fl_x"))
            elif get("camera_angle_x") is not None:
                fx = 0.5 * W / math.tan(0.5 * float(get("camera_angle_x")))
            else:
                raise CaptureImportError(f"{where}: no focal length: give 'fl_x' (pixels) or 'camera_angle_x' "
                                         f"(radians)")
            if get("fl_y") is not None:
                fy = float(get("fl_y"))
            elif get("camera_angle_y") is not None:
                fy = 0.5 * H / math.tan(0.5 * float(get("camera_angle_y")))
            else:
                fy = fx
            cx = float(get("cx")) if get("cx") is not None else W / 2
            cy = float(get("cy")) if get("cy") is not None else H / 2
            coeffs = [float(get(key) or 0.0) for key in ("k1", "k2", "p1", "p2", "k3")]
            M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CaptureImportError(f"{where}: intrinsics and transform_matrix must be numbers ({exc})") from None
        if M.shape not in ((4, 4), (3, 4)) or not np.isfinite(M).all():
            raise CaptureImportError(f"{where}: transform_matrix must be a finite 4×4 (or 3×4) camera-to-world "
                                     f"matrix, got "
                               f"shape {M.shape}")
        if M.shape == (4, 4) and np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise CaptureImportError(f"{where}: transform_matrix's last row must be [0, 0, 0, 1], got {M[3].tolist()}")
        Rc2w = M[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenGL camera axes → OpenCV's
        R = Rc2w.T
        t = -R @ M[:3, 3]
        camera = _pinhole(fx, fy, cx - 0.5, cy - 0.5, W, H, R, t,
                          f"{where} (transform_matrix must be a rigid camera-to-world transform, no scale)")
        dist = np.array(coeffs) if any(coeffs) else None
        mask = None
        if fr.get("mask_path") and options.masks is None:
            mask = _find_image(path.parent, str(fr["mask_path"]), f"{where}: mask_path")
        shots.append(_Shot(img, camera, dist, img.name, mask, where))
    return _write(shots, out, options, overwrite, f"transforms.json {path}", {"transforms": path})


# ----------------------------------------------------------------------------------------------
# OpenCV calibration YAML (cv2.FileStorage)


def _fs_mat(node, name, where, shape=None):
    if node.empty() or node.isNone():
        return None
    if node.isSeq():
        m = np.array([node.at(k).real() for k in range(node.size())], dtype=np.float64)
    else:
        m = node.mat()
        if m is None:
            raise CaptureImportError(f"{where}: '{name}' must be an opencv-matrix or a list of numbers")
        m = np.asarray(m, dtype=np.float64)
    if shape is not None:
        if m.size != int(np.prod(shape)):
            raise CaptureImportError(f"{where}: '{name}' must have {int(np.prod(shape))} numbers ({shape}), got shape "
                               f"{m.shape}")
        m = m.reshape(shape)
    if not np.isfinite(m).all():
        raise CaptureImportError(f"{where}: '{name}' contains NaN or inf")
    return m


def _fs_get(node, names, where, shape=None):
    for n in names:
        m = _fs_mat(node.getNode(n), n, where, shape)
        if m is not None:
            return m
    return None


def import_opencv_yaml(path, out, options: ImportOptions, *, overwrite: bool = False) -> ImportResult:
    """Import an OpenCV calibration file (``cv2.FileStorage`` YAML or XML) and its photos as a shadecap dataset.

    Layout accepted (docs/importing.md)::

        %YAML:1.0
        image_width: 640                 # optional: taken from the images when absent
        image_height: 480
        camera_matrix: !!opencv-matrix   # or K: 3×3, pixels, OpenCV convention (as calibrateCamera gives it)
        distortion_coefficients: ...     # or D: 4, 5, 8, 12 or 14 numbers (k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]); optional
        images:                          # a sequence, one map per photo
          - file: "img_000.png"          # relative to ImportOptions.images (default: the YAML's folder)
            R: !!opencv-matrix ...       # 3×3 world-to-camera rotation, or rvec: 3 numbers (Rodrigues)
            t: !!opencv-matrix ...       # 3 numbers, world-to-camera translation (tvec also accepted)
            camera_matrix / K, distortion_coefficients / D   # optional per-photo intrinsics

    ``x_cam = R x_world + t`` exactly as ``cv2.solvePnP`` / ``calibrateCamera`` return them; OpenCV's pixel
    convention is shadecap's, so nothing is shifted.

    Raises:
        CaptureImportError: naming the file, the entry, the field and the fix; nothing is written then.
    """
    import cv2

    options = _check_options(options, "import_opencv_yaml")
    path = Path(path)
    if not path.is_file():
        raise CaptureImportError(f"{path}: calibration file does not exist")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CaptureImportError(f"{path}: not a readable OpenCV FileStorage YAML/XML file ({exc.err})") from None
    if not fs.isOpened():
        raise CaptureImportError(f"{path}: not a readable OpenCV FileStorage YAML/XML file")
    try:
        root = fs.root()
        K0 = _fs_get(root, ("camera_matrix", "K"), str(path), (3, 3))
        D0 = _fs_get(root, ("distortion_coefficients", "D", "dist_coeffs"), str(path))
        W0, H0 = root.getNode("image_width"), root.getNode("image_height")
        W0 = int(W0.real()) if not W0.empty() else None
        H0 = int(H0.real()) if not H0.empty() else None
        seq = root.getNode("images")
        if seq.empty() or not seq.isSeq() or seq.size() == 0:
            raise CaptureImportError(f"{path}: field 'images' must be a non-empty sequence of maps (file, "
                                     f"R/rvec, t/tvec); "
                               "see docs/importing.md")
        base = options.images or path.parent
        shots = []
        for k in range(seq.size()):
            e = seq.at(k)
            where = f"{path}: images[{k}]"
            fnode = e.getNode("file")
            if fnode.empty():
                fnode = e.getNode("image")
            if fnode.empty() or not fnode.isString():
                raise CaptureImportError(f"{where}: needs 'file', the photo's name relative to {base}")
            img = _find_image(base, fnode.string(), where)
            K = _fs_get(e, ("camera_matrix", "K"), where, (3, 3))
            K = K0 if K is None else K
            if K is None:
                raise CaptureImportError(f"{where}: no intrinsics: give 'camera_matrix' (or 'K') at the top "
                                         f"level or here")
            D = _fs_get(e, ("distortion_coefficients", "D", "dist_coeffs"), where)
            D = D0 if D is None else D
            if D is not None:
                D = D.reshape(-1)
                if D.size not in (4, 5, 8, 12, 14):
                    raise CaptureImportError(f"{where}: distortion coefficients must be 4, 5, 8, 12 or 14 numbers "
                                       f"(OpenCV's k1 k2 p1 p2 [k3 ...]), got {D.size}")
            R = _fs_get(e, ("R",), where, (3, 3))
            if R is None:
                rvec = _fs_get(e, ("rvec",), where, (3,))
                if rvec is None:
                    raise CaptureImportError(f"{where}: needs 'R' (3×3 world-to-camera rotation) or 'rvec' (Rodrigues)")
                R = cv2.Rodrigues(rvec.reshape(3, 1))[0]
            t = _fs_get(e, ("t", "tvec"), where, (3,))
            if t is None:
                raise CaptureImportError(f"{where}: needs 't' (or 'tvec'): the world-to-camera translation")
            W, H = W0, H0
            if W is None or H is None:
                arr = _read_photo(img, where)[0]
                H, W = arr.shape[:2]
            if abs(K[1, 0]) > 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
                raise CaptureImportError(f"{where}: camera_matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
            try:
                camera = Camera(K, R, t, int(W), int(H), dtype=torch.float64)
            except CameraError as exc:
                raise CaptureImportError(f"{where}: {exc}") from None
            dist = D if D is not None and np.any(D != 0) else None
            shots.append(_Shot(img, camera, dist, img.name, where=where))
    finally:
        fs.release()
    return _write(shots, out, options, overwrite, f"OpenCV calibration {path}", {"calibration": path})


# ----------------------------------------------------------------------------------------------
# mesh


def unwrap_mesh(path) -> Mesh:
    """Load a mesh file (UVs or not) and give it a new UV atlas with xatlas (``pip install xatlas``).

    xatlas cuts the surface into charts and packs them without overlap (an injective texture space, which the
    per-texel fit needs); vertices on chart seams are duplicated. Normals: area-weighted, merged across seams.

    Raises:
        CaptureImportError: xatlas is not installed (the message gives the install command) or the file is unreadable.
    """
    try:
        import xatlas
    except ImportError:
        raise CaptureImportError("unwrapping a mesh needs the optional package xatlas: pip install xatlas (or "
                                 "pip install "
                           "'shadecap[unwrap]'), or unwrap it yourself (Blender: UV > Smart UV Project)") from None
    import trimesh

    path = Path(path)
    try:
        tm = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise CaptureImportError(f"{path}: cannot read the mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise CaptureImportError(f"{path}: holds no triangles")
    v = np.asarray(tm.vertices, dtype=np.float32)
    f = np.asarray(tm.faces, dtype=np.uint32)
    vmap, idx, uv = xatlas.parametrize(v, f)
    try:
        return Mesh.from_arrays(v[vmap].astype(np.float64), idx.astype(np.int64), uv.astype(np.float64),
                                name=path.name)
    except MeshError as exc:
        raise CaptureImportError(f"{path}: the unwrapped mesh is unusable: {exc}") from None


def _load_mesh(options: ImportOptions) -> Mesh:
    if options.unwrap:
        return unwrap_mesh(options.mesh)
    try:
        return load_mesh(options.mesh)
    except MeshError as exc:
        msg = str(exc)
        if "UVs" in msg:
            msg += "; or let the importer unwrap it (ImportOptions(unwrap=True) / --unwrap, needs pip install xatlas)"
        raise CaptureImportError(msg) from None


# ----------------------------------------------------------------------------------------------
# writing


def _check_options(options, who: str) -> ImportOptions:
    if not isinstance(options, ImportOptions):
        raise CaptureImportError(f"{who}: options must be an ImportOptions (ImportOptions(mesh=..., "
                                 f"flash=Flash(...), ...)), "
                           f"got {type(options).__name__}")
    return options


def _read_photo(path: Path, where: str) -> tuple[np.ndarray, int | None]:
    """(array [H, W, C] as stored, bits: 8/16, None for float) of a photo; EXR as float32."""
    try:
        if path.suffix.lower() == ".exr":
            return read_exr(path).numpy(), None
        return read_raster(path)
    except ImageIOError as exc:
        raise CaptureImportError(f"{where}: {exc}") from None


def _encoding_of(path: Path, bits: int | None, requested: str) -> str:
    if requested != "auto":
        return requested
    s = path.suffix.lower()
    if s == ".exr" or bits is None or (s in (".tif", ".tiff") and bits == 16):
        return "linear"
    return "srgb"


def _mask_for(shot: _Shot, options: ImportOptions, shape, where: str) -> np.ndarray | None:
    """A photo's mask as bool [H, W] (True = usable) from the mask folder or the shot's own mask file."""
    src = shot.mask
    if isinstance(options.masks, Path):
        name = Path(shot.name)
        cands = [options.masks / (shot.name + ".png"), options.masks / name.with_suffix(".png")]
        cands += [options.masks / name.with_suffix(s) for s in IMAGE_SUFFIXES if s != ".png"]
        src = next((c for c in cands if c.is_file()), None)
        if src is None:
            raise CaptureImportError(f"{where}: no mask for {shot.name} in {options.masks} (looked for "
                               f"{', '.join(c.name for c in cands[:2])}); give every photo a mask or drop --masks")
    if src is None:
        return None
    arr = _read_photo(src, f"{where}: mask")[0]
    if arr.shape[:2] != tuple(shape):
        raise CaptureImportError(f"{src}: mask is {arr.shape[1]}×{arr.shape[0]}, its photo is "
                                 f"{shape[1]}×{shape[0]}; write "
                           "the mask at the photo's size")
    colour = arr[..., :3] if arr.shape[2] >= 3 else arr[..., :1]
    return (colour != 0).any(-1)


def _undistort_maps(camera: Camera, dist: np.ndarray):
    import cv2

    K = camera.K.double().numpy()
    return cv2.initUndistortRectifyMap(K, dist.astype(np.float64), None, K, (camera.width, camera.height),
                                       cv2.CV_32FC1)


class _Format(NamedTuple):
    """How the photos are stored and how the dataset will hold them."""

    encoding: str
    bits: int | None  # the photos' bits per sample, None for float
    saturation: float | int | None  # in the photos' units: an integer code for sRGB, a value for linear
    undistort: bool

    @property
    def top(self) -> int | None:
        """The photos' largest integer code (None for float photos)."""
        return (1 << self.bits) - 1 if self.bits else None

    @property
    def out_bits(self) -> int | None:
        """Bits per sample of the written images: undistorted sRGB photos become 16-bit PNG."""
        return 16 if (self.undistort and self.encoding == "srgb") else self.bits


def _check_import_output(out: Path, shots: Sequence[_Shot], options: ImportOptions, overwrite: bool,
                         inputs: dict) -> None:
    """``out`` may be written: not existing (unless ``overwrite``), and none of the inputs inside it."""
    ins = {options.mesh: "the mesh file (--mesh)", **{p: f"the {k} input" for k, p in inputs.items()}}
    if options.images is not None:
        ins[options.images] = "the image folder (--images)"
    if isinstance(options.masks, Path):
        ins[options.masks] = "the mask folder (--masks)"
    for s in shots:
        ins.setdefault(s.image, f"the photo {s.image.name}")
    check_output(out, ins, force=overwrite, error=CaptureImportError, force_flag="overwrite=True (--overwrite)")


def _scan_photos(shots: Sequence[_Shot]) -> list[tuple[int, int | None]]:
    """Each photo's (channels, bits), read once, after checking it has its camera's size."""
    photos = []
    for s in shots:
        arr, bits = _read_photo(s.image, s.where)
        if arr.shape[0] != s.camera.height or arr.shape[1] != s.camera.width:
            raise CaptureImportError(f"{s.where}: the photo {s.image} is {arr.shape[1]}×{arr.shape[0]} px but "
                                     f"its camera is "
                                     f"{s.camera.width}×{s.camera.height}; give the photos the cameras were computed "
                                     "from (not resized copies)")
        photos.append((arr.shape[2], bits))  # only what the checks need: the pixels are read again to write
        del arr
    return photos


def _common_encoding(shots: Sequence[_Shot], photos: Sequence[tuple], requested: str) -> tuple[str, int | None]:
    """The one (encoding, bits) of every photo; refuses mixed photos and impossible encodings."""
    encs = {(_encoding_of(s.image, b, requested), b) for s, (_, b) in zip(shots, photos, strict=True)}
    if len({e for e, _ in encs}) > 1 or len(encs) > 1:
        raise CaptureImportError(f"the photos mix sample types / encodings {sorted(encs, key=str)}; a dataset has one: "
                                 "convert them to one type (e.g. all 8-bit JPEG/PNG, or all 16-bit TIFF)")
    encoding, bits = next(iter(encs))
    if encoding == "srgb" and bits is None:
        raise CaptureImportError("float images hold linear values; use encoding 'linear' (or 'auto')")
    if encoding == "linear" and bits == 8:
        raise CaptureImportError("8-bit photos cannot be taken as linear (too few levels); use encoding 'srgb' "
                                 "or 16-bit "
                                 "/ float images")
    return encoding, bits


def _distortion_notes(shots: Sequence[_Shot], has_dist: Sequence[bool], options: ImportOptions,
                      undistort: bool) -> list[str]:
    """Warnings (issued, and returned for the result) about JPEGs written as PNG and ignored distortion."""
    msgs: list[str] = []
    jpegs = [s.image.name for s in shots if s.image.suffix.lower() in (".jpg", ".jpeg")]
    if undistort and jpegs:  # written as PNG: the loader cannot tell any more, so say it here
        msgs.append(f"{len(jpegs)} photo(s) were JPEG ({', '.join(jpegs[:3])}{' ...' if len(jpegs) > 3 else ''}): a "
                    "camera's JPEG is not pure sRGB, so the recovered albedo is approximate (docs/importing.md)")
        warnings.warn(DatasetWarning(msgs[-1]), stacklevel=4)  # the importer's caller, through _write
    if any(has_dist) and not options.undistort:
        msgs.append(f"{sum(has_dist)} photo(s) have lens distortion coefficients, ignored (undistort=False): the "
                    "photos are taken as already undistorted")
        warnings.warn(DatasetWarning(msgs[-1]), stacklevel=4)
    return msgs


def _import_saturation(options: ImportOptions, encoding: str, bits: int | None, undistort: bool):
    """The photos' clipping level: the option, else the largest code (sRGB), 1.0 (integer linear) or None."""
    top = (1 << bits) - 1 if bits else None
    if options.saturation is not None:
        saturation = options.saturation
    else:
        saturation = (top if encoding == "srgb" else (1.0 if bits else None))
    if encoding == "srgb" and not undistort and (not isinstance(saturation, numbers.Integral)
                                                 or not 1 <= saturation <= top):
        raise CaptureImportError(f"ImportOptions.saturation must be an integer code in [1, {top}] for "
                                 f"{bits}-bit sRGB photos, "
                                 f"got {saturation!r}")
    return saturation


def _undistort_photo(arr: np.ndarray, b: int | None, s: _Shot, mask: np.ndarray | None,
                     fmt: _Format) -> tuple[np.ndarray, np.ndarray]:
    """(undistorted linear image [H, W, C], usable mask [H, W]) of one photo: pixels whose footprint touches a
    clipped pixel, the border, a masked-out pixel or a transparent one are not usable."""
    import cv2

    encoding, saturation, top = fmt.encoding, fmt.saturation, fmt.top
    m1, m2 = _undistort_maps(s.camera, s.dist if s.dist is not None else np.zeros(4))
    x = arr.astype(np.float32)
    if b:
        x /= np.float32(top)
    alpha = None
    if x.shape[2] in (2, 4):
        alpha = x[..., -1] >= 0.5
        x = x[..., :-1]
    if saturation is None:
        sat = np.zeros(x.shape[:2], bool)
    else:  # x is in file units: code / top for integer photos, as stored for float ones
        level = saturation / top if (b and encoding == "srgb") else float(saturation)
        sat = (x >= level * (1 - 1e-6)).any(-1)
    lin = decode(torch.from_numpy(np.ascontiguousarray(x)), "srgb").numpy() if encoding == "srgb" else x
    und = cv2.remap(np.ascontiguousarray(lin), m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if und.ndim == 2:
        und = und[:, :, None]
    good = cv2.remap((~sat).astype(np.float32), m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0.0) >= 1 - 1e-4
    for extra in (mask, alpha):
        if extra is not None:
            good &= cv2.remap(extra.astype(np.uint8), m1, m2, cv2.INTER_NEAREST,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return und, good


def _write_shot(tmp: Path, i: int, s: _Shot, b: int | None, options: ImportOptions, fmt: _Format) -> dict:
    """Write photo ``i`` (copied as it is, or undistorted) and its mask into ``tmp``; returns its scene entry."""
    arr = _read_photo(s.image, s.where)[0] if fmt.undistort else None
    mask = _mask_for(s, options, (s.camera.height, s.camera.width), s.where)
    if fmt.undistort:
        und, mask = _undistort_photo(arr, b, s, mask, fmt)
        if fmt.encoding == "srgb":
            rel = f"{IMAGE_DIR}/{i:03d}.png"
            write_png(tmp / rel, und, bits=16, transfer="srgb")
        else:
            rel = f"{IMAGE_DIR}/{i:03d}.exr"
            write_exr(tmp / rel, und)
    else:
        rel = f"{IMAGE_DIR}/{i:03d}{s.image.suffix.lower()}"
        shutil.copyfile(s.image, tmp / rel)
    entry = {"file": rel, "name": s.name, "camera": s.camera.to_dict(),
             "lights": [light_to_dict(x) for x in options.world_lights(s.camera)],
             "exposure": float(options.exposure)}
    if mask is not None:
        mrel = f"{MASK_DIR}/{i:03d}.png"
        (tmp / MASK_DIR).mkdir(exist_ok=True)
        write_png(tmp / mrel, torch.from_numpy(mask.astype(np.float64)), bits=8, transfer="linear")
        entry["mask"] = mrel
    return entry


def _import_scene_doc(entries: list[dict], fmt: _Format, options: ImportOptions, source: str) -> dict:
    doc = {"format": FORMAT, "version": VERSION, "mesh": "mesh.obj", "encoding": fmt.encoding}
    if fmt.encoding == "srgb":
        doc["bits"] = fmt.out_bits
        doc["saturation"] = (1 << fmt.out_bits) - 1 if fmt.undistort else int(fmt.saturation)
    else:
        doc["saturation"] = fmt.saturation
    doc["images"] = entries
    doc["meta"] = {"importer": source, "undistorted": bool(fmt.undistort), "unwrapped": options.unwrap,
                   "flash_camera_frame": [{"position": list(f.position), "intensity": list(f.intensity)}
                                          for f in options.flash]}
    return doc


def _validate_import(tmp: Path, out: Path) -> list[str]:
    """Load the written dataset: its errors become CaptureImportErrors, its warnings are returned (naming ``out``)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DatasetWarning)
        try:
            load_dataset(tmp)
        except CaptureImportError:
            raise
        except DatasetError as exc:
            hint = ("; the mesh must be in the cameras' world frame and unit (the tool's own mesh, or one aligned "
                    "to its cameras)") if "does not see the mesh" in str(exc) else ""
            raise CaptureImportError(f"{exc}{hint} (nothing was written to {out})") from None
    return [str(w.message).replace(str(tmp), str(out)) for w in caught if issubclass(w.category, DatasetWarning)]


def _write(shots: list[_Shot], out, options: ImportOptions, overwrite: bool, source: str,
           inputs: dict) -> ImportResult:
    out = Path(out)
    _check_import_output(out, shots, options, overwrite, inputs)
    mesh = _load_mesh(options)
    photos = _scan_photos(shots)  # per photo (channels, bits)
    encoding, bits = _common_encoding(shots, photos, options.encoding)
    has_dist = [s.dist is not None and bool(np.any(s.dist != 0)) for s in shots]
    undistort = options.undistort and any(has_dist)
    msgs = _distortion_notes(shots, has_dist, options, undistort)
    if options.masks == "alpha" and any(c not in (2, 4) for c, _ in photos):
        bad = next(s.image for s, (c, _) in zip(shots, photos, strict=True) if c not in (2, 4))
        raise CaptureImportError(f"{bad}: has no alpha channel, but masks = 'alpha'; write the photos as RGBA "
                                 f"PNG or give "
                                 "a mask folder")
    fmt = _Format(encoding, bits, _import_saturation(options, encoding, bits, undistort), undistort)

    with atomic_folder(out, force=overwrite, error=CaptureImportError, force_flag="overwrite=True "
                                                                                  "(--overwrite)") as tmp:
        (tmp / IMAGE_DIR).mkdir()
        save_mesh(mesh, tmp / "mesh.obj")
        entries, n_masks = [], 0
        for i, (s, (_, b)) in enumerate(zip(shots, photos, strict=True)):
            entry = _write_shot(tmp, i, s, b, options, fmt)
            if "mask" in entry or options.masks == "alpha":
                n_masks += 1
            entries.append(entry)
        doc = _import_scene_doc(entries, fmt, options, source)
        (tmp / SCENE_FILE).write_text(scene_json_text(jsonable(doc)) + "\n", encoding="utf-8")
        msgs += _validate_import(tmp, out)
    return ImportResult(out, source, len(shots), encoding, fmt.out_bits if encoding == "srgb" else bits,
                        len(shots) if undistort else 0, n_masks, options.unwrap, msgs)
