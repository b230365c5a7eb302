"""Image files: linear EXR (OpenEXR 3 Python API), PNG (OpenCV), transfer functions, atomic writes.

Every image in memory is a torch ``float32`` tensor ``[H, W, C]`` of *linear* values, row 0 at
the top of the image, channels in RGB(A) order (C = 1 gray, 3 RGB, 4 RGBA). Files are converted
at this boundary only:

========  ===================================================  ==========================================
format    on disk                                              in memory
========  ===================================================  ==========================================
EXR       half or float channels ``Y`` / ``R,G,B`` / ``RGBA``  as stored (linear, any range, float32)
PNG       8- or 16-bit, gray / RGB / RGBA, OpenCV BGR order     colour decoded by the transfer (default
                                                               sRGB); alpha is linear (PNG spec 12.4)
========  ===================================================  ==========================================

Transfer functions (``encode``: linear → file value, ``decode``: file value → linear):

- ``"srgb"`` — IEC 61966-2-1: encode ``12.92 x`` for x ≤ 0.0031308, else ``1.055 x^(1/2.4) − 0.055``;
  decode ``y/12.92`` for y ≤ 0.04045, else ``((y + 0.055)/1.055)^2.4``. Computed by kornia's
  ``linear_rgb_to_rgb`` / ``rgb_to_linear_rgb`` (kornia 0.9; both elementwise), so 0.5 → 0.735356983…
- ``"gamma2.2"`` — Schüler's display gamma ("texture colors must be raised to the power of 2.2"):
  encode ``x^(1/2.2)``, decode ``y^2.2``; negative values map to 0.
- ``"linear"`` — identity.

Writes are atomic: the file is written to a temporary name in the destination folder, flushed
with ``fsync`` and moved over the destination with :func:`os.replace`, so a reader sees either the
old file or the complete new one, never a half-written one. Every failure raises
:class:`ImageIOError` (a ``ValueError``) whose message starts with the file's path. A new file gets
the permissions the umask gives a plain ``open`` (:func:`apply_umask`; a replaced file keeps its
own), not the private ones of the temporary file.
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "ImageIOError", "ImageNotFoundError", "TRANSFERS", "decode", "encode", "read_exr", "read_image",
    "read_png", "read_raster", "write_exr", "write_image", "write_png", "write_png_codes", "atomic_write_bytes",
    "apply_umask",
    "current_umask",
    "REC709_CHROMATICITIES",
]

#: Names accepted by :func:`encode` / :func:`decode`.
TRANSFERS = ("srgb", "gamma2.2", "linear")
_ALIASES = {"srgb": "srgb", "s-rgb": "srgb", "gamma2.2": "gamma2.2", "gamma": "gamma2.2", "gamma22": "gamma2.2",
            "linear": "linear", "lin": "linear", "none": "linear"}
GAMMA = 2.2
#: Largest finite half-float value.
HALF_MAX = 65504.0
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_READ_SUFFIXES_CV = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


class ImageIOError(ValueError):
    """An image file could not be read or written; the message names the file and the fix."""


class ImageNotFoundError(ImageIOError, FileNotFoundError):
    """The image file does not exist (also a ``FileNotFoundError``)."""


# --------------------------------------------------------------------------------------------
# transfer functions


def _transfer_name(transfer: str | None) -> str:
    if transfer is None:
        return "linear"
    if not isinstance(transfer, str) or transfer.strip().lower() not in _ALIASES:
        raise ImageIOError(f"unknown transfer function {transfer!r}; use one of {list(TRANSFERS)}")
    return _ALIASES[transfer.strip().lower()]


def _kornia_elementwise(fn, x: Tensor) -> Tensor:
    """Apply kornia's (*, 3, H, W) colour functions, which are elementwise, to a tensor of any shape."""
    flat = x.reshape(-1)
    n = flat.numel()
    pad = (-n) % 3
    if pad:
        flat = F.pad(flat, (0, pad))
    return fn(flat.view(-1, 3, 1, 1)).reshape(-1)[:n].view(x.shape)


def _as_float_tensor(x, name: str) -> Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")
    return x if x.is_floating_point() else x.to(torch.get_default_dtype())


def encode(x: Tensor, transfer: str = "srgb") -> Tensor:
    """Linear values → encoded (file) values by ``transfer`` (see the module docstring).

    Args:
        x: any shape, linear, usually in [0, 1]; float32 or float64, any device. Differentiable
            with finite gradients (the gamma branch is guarded at 0).
        transfer: ``"srgb"`` (IEC 61966-2-1), ``"gamma2.2"`` (Schüler) or ``"linear"``.

    Returns:
        Tensor of the same shape and dtype. No clamping beyond what the curve needs: values above 1
        follow the curve's formula, sRGB's linear segment extends below 0, gamma 2.2 maps x < 0 to 0.
    """
    x = _as_float_tensor(x, "x")
    t = _transfer_name(transfer)
    if t == "linear":
        return x
    if t == "srgb":
        from kornia.color import linear_rgb_to_rgb

        return _kornia_elementwise(linear_rgb_to_rgb, x)
    from materials.geometry import guarded_pow

    return guarded_pow(x, 1.0 / GAMMA)


def decode(y: Tensor, transfer: str = "srgb") -> Tensor:
    """Encoded (file) values → linear values; the exact inverse of :func:`encode` on [0, 1]."""
    y = _as_float_tensor(y, "y")
    t = _transfer_name(transfer)
    if t == "linear":
        return y
    if t == "srgb":
        from kornia.color import rgb_to_linear_rgb

        return _kornia_elementwise(rgb_to_linear_rgb, y)
    from materials.geometry import guarded_pow

    return guarded_pow(y, GAMMA)


# --------------------------------------------------------------------------------------------
# helpers


def _path(path) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    return Path(path)


def _image_array(path: Path, img, what: str) -> np.ndarray:
    """Validate an image to be written: tensor/array [H, W] or [H, W, C], C in 1, 3, 4 → float64 numpy HWC."""
    if isinstance(img, Tensor):
        arr = img.detach().to("cpu", torch.float64).numpy()
    elif isinstance(img, np.ndarray):
        arr = img.astype(np.float64, copy=False)
    else:
        raise ImageIOError(f"{path}: {what} must be a torch.Tensor or numpy array, got {type(img).__name__}")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4):
        raise ImageIOError(
            f"{path}: {what} must have shape [H, W] or [H, W, C] with C = 1 (gray), 3 (RGB) or 4 (RGBA), "
            f"got {tuple(arr.shape)}"
        )
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ImageIOError(f"{path}: {what} is empty, shape {tuple(arr.shape)}")
    return arr


def current_umask() -> int:
    """The process's file-creation mask (from ``/proc/self/status`` where there is one, else set and restored)."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def apply_umask(path) -> None:
    """Give ``path`` — a file, or a folder and everything under it — the permissions a plain ``open`` /
    ``mkdir`` would: ``0o666`` / ``0o777`` less the umask.

    ``tempfile.mkstemp`` / ``mkdtemp`` create private entries (0600 / 0700); every output written under a
    temporary name and then renamed into place gets this first, so outputs honour the umask like any file the
    user writes. Symbolic links are left alone (their targets are not ours).
    """
    path = _path(path)
    mask = current_umask()
    fmode, dmode = 0o666 & ~mask, 0o777 & ~mask
    if path.is_symlink():
        return
    if not path.is_dir():
        os.chmod(path, fmode)
        return
    os.chmod(path, dmode)
    for dirpath, dirnames, filenames in os.walk(path):
        for name in dirnames:
            p = os.path.join(dirpath, name)
            if not os.path.islink(p):
                os.chmod(p, dmode)
        for name in filenames:
            p = os.path.join(dirpath, name)
            if not os.path.islink(p):
                os.chmod(p, fmode)


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, :func:`os.replace`)."""
    path = _path(path)
    _atomic(path, lambda tmp: Path(tmp).write_bytes(data))


def _atomic(path: Path, writer) -> None:
    """Run ``writer(tmp_path)`` on a temp file next to ``path`` (same suffix), fsync it and move it in place."""
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ImageIOError(f"{path}: the folder {folder} does not exist; create it first")
    if path.is_dir():
        raise ImageIOError(f"{path}: is a folder, not an image file path")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=folder)
    os.close(fd)
    try:
        writer(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        try:  # a replaced file keeps its mode; a new one gets the umask's, not mkstemp's private 0600
            mode = stat.S_IMODE(os.stat(path).st_mode)
        except OSError:
            mode = 0o666 & ~current_umask()
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except ImageIOError:
        _unlink(tmp)
        raise
    except BaseException as err:  # OSError, RuntimeError from OpenEXR, cv2.error; an interrupt too
        _unlink(tmp)
        if not isinstance(err, Exception):
            raise
        raise ImageIOError(f"{path}: could not be written ({type(err).__name__}: {err})") from err
    try:  # make the rename durable; not every platform can fsync a folder
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def _unlink(p) -> None:
    try:
        os.unlink(p)
    except OSError:
        pass


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise ImageNotFoundError(f"{path}: no such image file")
    if path.is_dir():
        raise ImageIOError(f"{path}: is a folder, not an image file")
    if not os.access(path, os.R_OK):
        raise ImageIOError(f"{path}: is not readable (permission denied)")
    if path.stat().st_size == 0:
        raise ImageIOError(f"{path}: is empty (0 bytes); the file was truncated or never written")


# --------------------------------------------------------------------------------------------
# EXR


#: CIE xy of the Rec. 709 / sRGB primaries and the D65 white point, as the EXR ``chromaticities`` attribute
#: orders them: red x, y, green x, y, blue x, y, white x, y.
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def _openexr():
    """The OpenEXR module, its (de)compression on as many worker threads as torch's (the library's default is none:
    a 2048² RGB map ZIP-compressed in 0.20 s on the calling thread, 0.12 s with 2 workers)."""
    import OpenEXR

    if OpenEXR.global_thread_count() == 0:
        OpenEXR.set_global_thread_count(max(torch.get_num_threads(), 1))
    return OpenEXR


def write_exr(path, img, half: bool = False, allow_nonfinite: bool = False, chromaticities=None) -> None:
    """Write a linear image as an OpenEXR file (ZIP compression), atomically.

    Args:
        path: destination ``.exr`` file; its folder must exist.
        img: ``[H, W]`` or ``[H, W, C]`` with C = 1 (channel ``Y``), 3 (``R, G, B``) or 4 (``R, G, B, A``);
            torch tensor (any device, any float dtype) or numpy array; linear values, any range.
        half: store 16-bit half floats (≈ 3 significant digits, |x| ≤ 65504) instead of 32-bit floats.
        allow_nonfinite: write NaN/inf values instead of refusing them.
        chromaticities: None (no attribute, the default), ``"rec709"`` (:data:`REC709_CHROMATICITIES`: the
            sRGB primaries, D65 white) or 8 numbers (red, green, blue, white CIE xy) for the file's
            ``chromaticities`` attribute, which says what the RGB values mean.

    Raises:
        ImageIOError: wrong shape, NaN/inf (unless allowed), values beyond the half range with
            ``half=True``, or an unwritable destination; the message names the file.
    """
    OpenEXR = _openexr()
    path = _path(path)
    arr = _image_array(path, img, "image")
    finite = np.isfinite(arr)
    if not allow_nonfinite and not finite.all():
        raise ImageIOError(
            f"{path}: image contains {int((~finite).sum())} NaN/inf value(s); fix the source or pass "
            "allow_nonfinite=True"
        )
    if half:
        over = finite & (np.abs(arr) > HALF_MAX)
        if over.any():
            raise ImageIOError(
                f"{path}: {int(over.sum())} value(s) exceed the half-float range ±{HALF_MAX:g} "
                f"(max |x| = {np.abs(arr[finite]).max():.6g}); write with half=False"
            )
    dtype = np.float16 if half else np.float32
    c = arr.shape[2]
    names = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}[c]
    channels = {name: np.ascontiguousarray(arr[:, :, k].astype(dtype)) for k, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if chromaticities is not None:
        xy = REC709_CHROMATICITIES if isinstance(chromaticities, str) and chromaticities.lower() == "rec709" \
            else chromaticities
        try:
            xy = tuple(float(v) for v in xy)
        except (TypeError, ValueError):
            xy = ()
        if len(xy) != 8 or not all(np.isfinite(xy)):
            raise ImageIOError(f"{path}: chromaticities must be 'rec709' or 8 finite numbers (red, green, blue, "
                               f"white CIE xy), got {chromaticities!r}")
        header["chromaticities"] = xy

    def writer(tmp):
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))

    _atomic(path, writer)


def read_exr(path) -> Tensor:
    """Read an OpenEXR file → float32 ``[H, W, C]``, values as stored (linear).

    Channels: a lone channel (``Y`` or any name) gives C = 1; ``R, G, B`` gives C = 3; ``R, G, B, A``
    gives C = 4, in that order whatever the file's order. Half and uint channels are converted to
    float32. Multi-part files: the first part is read.

    Raises:
        ImageNotFoundError: the file does not exist.
        ImageIOError: not an EXR, truncated or corrupt, or channels that are not one of the layouts above.
    """
    OpenEXR = _openexr()

    path = _path(path)
    _check_readable(path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != _EXR_MAGIC:
        raise ImageIOError(f"{path}: is not an OpenEXR file (bad magic number {magic!r})")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            chans = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as err:
        raise ImageIOError(
            f"{path}: could not be read as OpenEXR ({type(err).__name__}: {err}); the file is truncated or corrupt"
        ) from err
    names = set(chans)
    if len(chans) == 1:
        order = list(chans)
    elif names == {"R", "G", "B"}:
        order = ["R", "G", "B"]
    elif names == {"R", "G", "B", "A"}:
        order = ["R", "G", "B", "A"]
    else:
        raise ImageIOError(
            f"{path}: unsupported EXR channels {sorted(names)}; expected one channel, R,G,B or R,G,B,A"
        )
    shapes = {chans[n].shape for n in order}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ImageIOError(f"{path}: channels have inconsistent shapes {sorted(shapes)} (subsampled channels?)")
    arr = np.stack([chans[n].astype(np.float32) for n in order], axis=-1)
    return torch.from_numpy(np.ascontiguousarray(arr))


# --------------------------------------------------------------------------------------------
# PNG (and 8/16-bit reads of other OpenCV formats)


def write_png(path, img, bits: int = 8, transfer: str = "srgb") -> None:
    """Write a linear image in [0, 1] as an 8- or 16-bit PNG, atomically.

    Colour channels (gray, or RGB) are clamped to [0, 1], encoded by ``transfer`` and rounded to the
    nearest code ``round(encode(x) · (2^bits − 1))``; alpha (the 4th channel) is clamped and quantised
    linearly, as PNG defines. RGB is reordered to OpenCV's BGR.

    Args:
        path: destination ``.png``; its folder must exist.
        img: ``[H, W]`` / ``[H, W, 1]`` gray, ``[H, W, 3]`` RGB or ``[H, W, 4]`` RGBA, linear.
        bits: 8 or 16.
        transfer: ``"srgb"`` (default), ``"gamma2.2"`` or ``"linear"``.

    Raises:
        ImageIOError: NaN/inf values (a PNG cannot hold them), wrong shape, bad ``bits``, unwritable path.
    """
    path = _path(path)
    if bits not in (8, 16):
        raise ImageIOError(f"{path}: bits must be 8 or 16, got {bits!r}")
    t = _transfer_name(transfer)
    arr = _image_array(path, img, "image")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ImageIOError(
            f"{path}: image contains {int(bad.sum())} NaN/inf value(s), which a PNG cannot store; fix the "
            "source (or write an EXR)"
        )
    arr = np.clip(arr, 0.0, 1.0)
    c = arr.shape[2]
    ncol = 3 if c == 4 else c
    col = encode(torch.from_numpy(arr[:, :, :ncol].copy()), t).numpy()
    arr = np.concatenate([np.clip(col, 0.0, 1.0), arr[:, :, ncol:]], axis=2)
    top = (1 << bits) - 1
    _encode_png(path, np.rint(arr * top).astype(np.uint8 if bits == 8 else np.uint16))


def write_png_codes(path, codes: np.ndarray) -> None:
    """Write integer codes as a PNG as they are, atomically: ``codes`` ``uint8`` or ``uint16`` ``[H, W]`` gray or
    ``[H, W, C]`` with C = 1, 3 (RGB) or 4 (RGBA). For pixels that are already codes — a drawn figure's — where
    :func:`write_png` would convert them to floats and back (a 1 900 × 960 figure page: 0.2 s there).

    Raises:
        ImageIOError: another dtype or shape, unwritable path.
    """
    path = _path(path)
    if not isinstance(codes, np.ndarray) or codes.dtype not in (np.uint8, np.uint16):
        raise ImageIOError(f"{path}: codes must be a uint8 or uint16 numpy array, got "
                           f"{getattr(codes, 'dtype', type(codes).__name__)}")
    q = codes[:, :, None] if codes.ndim == 2 else codes
    if q.ndim != 3 or q.shape[2] not in (1, 3, 4) or q.shape[0] == 0 or q.shape[1] == 0:
        raise ImageIOError(f"{path}: codes must have shape [H, W] or [H, W, C] with C = 1, 3 or 4 and no empty side, "
                           f"got {tuple(codes.shape)}")
    _encode_png(path, q)


def _encode_png(path: Path, q: np.ndarray) -> None:
    """Encode codes ``q [H, W, C]`` (RGB(A) order) as a PNG and write it atomically."""
    import cv2

    c = q.shape[2]
    if c == 3:
        q = q[:, :, ::-1]
    elif c == 4:
        q = q[:, :, [2, 1, 0, 3]]
    else:
        q = q[:, :, 0]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(q))
    if not ok:
        raise ImageIOError(f"{path}: OpenCV could not encode the PNG")
    atomic_write_bytes(path, buf.tobytes())


def read_raster(path) -> tuple[np.ndarray, int | None]:
    """Read a PNG, JPEG or TIFF file as stored → ``(array [H, W, C], bits)``, C = 1, 3 or 4 in RGB(A) order.

    ``cv2.imdecode(..., IMREAD_UNCHANGED)``: no colour conversion, no EXIF rotation (pixels are used as stored,
    which is how calibration tools see them). ``bits`` is 8 or 16 for integer samples (the array is ``uint8`` /
    ``uint16``), None for float TIFF (``float32``). A ``.png`` without the PNG signature, a PNG without its IEND
    chunk and a JPEG without its end-of-image marker are refused.

    Raises:
        ImageNotFoundError: no such file.
        ImageIOError: unreadable, truncated, not an image, or an unsupported sample type or channel count; the
            message names the file.
    """
    import cv2

    path = _path(path)
    _check_readable(path)
    data = path.read_bytes()
    if path.suffix.lower() == ".png" or data[:8] == _PNG_SIGNATURE:
        if data[:8] != _PNG_SIGNATURE:
            raise ImageIOError(f"{path}: is not a PNG file (bad signature)")
        if not data.rstrip(b"\0").endswith(_PNG_IEND):
            raise ImageIOError(f"{path}: PNG is truncated (no IEND chunk at the end); rewrite the file")
    if data[:2] == b"\xff\xd8" and not data.rstrip(b"\0").endswith(b"\xff\xd9"):
        raise ImageIOError(f"{path}: JPEG is truncated (no end-of-image marker); copy the file again")
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ImageIOError(f"{path}: OpenCV could not decode the image; the file is corrupt or not an image")
    bits = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16, np.dtype(np.float32): None}.get(arr.dtype, 0)
    if bits == 0:
        raise ImageIOError(f"{path}: unsupported sample type {arr.dtype}; use 8/16-bit integer or 32-bit float "
                           "samples")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    c = arr.shape[2]
    if c == 3:
        arr = arr[:, :, ::-1]
    elif c == 4:
        arr = arr[:, :, [2, 1, 0, 3]]
    elif c != 1:
        raise ImageIOError(f"{path}: unsupported channel count {c}; expected 1, 3 or 4")
    return np.ascontiguousarray(arr), bits


def read_png(path, transfer: str = "srgb") -> Tensor:
    """Read an 8/16-bit PNG (or JPEG/TIFF) → float32 ``[H, W, C]`` linear (C = 1, 3 or 4, RGB order).

    Codes are divided by 255 or 65535, colour channels decoded by ``transfer``; alpha stays linear.
    Gray+alpha files come back as RGBA (OpenCV expands them). The file is read by :func:`read_raster`.

    Raises:
        ImageNotFoundError: no such file.
        ImageIOError: not an image, truncated (a PNG must end with its IEND chunk), or an unsupported
            pixel type; the message names the file.
    """
    t = _transfer_name(transfer)
    arr, bits = read_raster(path)
    if bits is None:
        raise ImageIOError(f"{_path(path)}: unsupported pixel type {arr.dtype}; expected 8- or 16-bit integers")
    x = torch.from_numpy(arr.astype(np.float32) / np.float32((1 << bits) - 1))
    c = x.shape[-1]
    ncol = 3 if c == 4 else c
    if t != "linear":
        x = torch.cat([decode(x[..., :ncol], t), x[..., ncol:]], dim=-1)
    return x.contiguous()


# --------------------------------------------------------------------------------------------
# dispatch


def read_image(path, transfer: str | None = None) -> Tensor:
    """Read any supported image → float32 ``[H, W, C]`` linear.

    EXR: values as stored (already linear); a ``transfer`` other than None/"linear" decodes them by it.
    PNG/JPEG/TIFF: decoded by ``transfer``, default ``"srgb"``.
    """
    path = _path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        img = read_exr(path)
        return img if transfer is None else decode(img, transfer)
    if suffix in _READ_SUFFIXES_CV:
        return read_png(path, "srgb" if transfer is None else transfer)
    raise ImageIOError(f"{path}: unsupported image type {suffix!r}; use .exr or .png")


def write_image(path, img, *, half: bool = False, bits: int = 8, transfer: str = "srgb",
                allow_nonfinite: bool = False) -> None:
    """Write ``img`` (linear ``[H, W(, C)]``) by the file's suffix: ``.exr`` → :func:`write_exr` (``half``,
    ``allow_nonfinite``), ``.png`` → :func:`write_png` (``bits``, ``transfer``)."""
    path = _path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        write_exr(path, img, half=half, allow_nonfinite=allow_nonfinite)
    elif suffix == ".png":
        write_png(path, img, bits=bits, transfer=transfer)
    else:
        raise ImageIOError(f"{path}: unsupported image type {suffix!r} for writing; use .exr or .png")

