"""Pinhole cameras in the OpenCV convention, rigs, and converters to OpenGL and Blender.

Convention (DESIGN.md): camera frame x right, y down, z forward (the camera looks along +z);
world-to-camera extrinsics ``x_cam = R x_world + t``; intrinsics ``K`` in pixels,
``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``; a pixel's *centre* has integer coordinates, so pixel
(x, y) covers [x − ½, x + ½] × [y − ½, y + ½] and the image spans [−½, W − ½] × [−½, H − ½].
The flat pixel index is ``y · W + x``.

OpenGL / Blender camera frames look along −z with y up (x right): the OpenGL camera frame is
``diag(1, −1, −1)`` times the OpenCV one. Blender's camera object uses the same frame as OpenGL;
its ``matrix_world`` is camera-to-world.

The OpenCV↔OpenGL/Blender pose flips use kornia (``kornia.geometry.conversions.camtoworld_vision_to_graphics_Rt``
and its inverse). Projection does *not* use ``kornia.geometry.camera.project_points`` /
``unproject_points``: in kornia 0.9 they read only fx, fy, cx, cy and silently ignore the skew
K[0, 1] (caught by ``tests/renderer/test_camera.py``); the one-line ``K x / z`` is used instead.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import torch
from kornia.geometry.conversions import camtoworld_graphics_to_vision_Rt, camtoworld_vision_to_graphics_Rt
from torch import Tensor

__all__ = [
    "Camera", "CameraError", "look_at", "orbit", "turntable", "random_rig", "rotation_about_axis",
]

_FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))


class CameraError(ValueError):
    """Invalid camera parameters (the message names the field)."""


def _tensor(x, name: str, shape: tuple[int, ...], dtype=None) -> Tensor:
    try:
        t = torch.as_tensor(x, dtype=dtype or torch.get_default_dtype())
    except (TypeError, ValueError, RuntimeError) as exc:
        raise CameraError(f"camera {name} must be numeric with shape {shape}: {exc}") from None
    if tuple(t.shape) != shape:
        raise CameraError(f"camera {name} must have shape {shape}, got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise CameraError(f"camera {name} contains NaN or inf")
    return t


class Camera:
    """An OpenCV pinhole camera (see module docstring for the convention).

    Args:
        K: intrinsics ``[3, 3]`` in pixels (fx, fy > 0, last row [0, 0, 1], K[1, 0] = 0).
        R: world-to-camera rotation ``[3, 3]``, orthonormal with det +1 (tolerance 1e-4).
        t: world-to-camera translation ``[3]`` (world units).
        width, height: image size in pixels (positive integers).
        dtype: stored dtype (default: torch's default dtype).

    Raises:
        CameraError: naming the offending field.
    """

    def __init__(self, K, R, t, width: int, height: int, dtype=None):
        dtype = dtype or torch.get_default_dtype()
        K = _tensor(K, "K", (3, 3), dtype)
        R = _tensor(R, "R", (3, 3), dtype)
        t = _tensor(t, "t", (3,), dtype).reshape(3)
        for name, x in (("width", width), ("height", height)):
            if isinstance(x, bool) or not isinstance(x, numbers.Integral) or int(x) <= 0:
                raise CameraError(f"camera {name} must be a positive integer, got {x!r}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraError(
                f"camera K must have positive focal lengths fx, fy; got fx={K[0, 0]:.6g}, fy={K[1, 1]:.6g}"
            )
        if (K[2] - torch.tensor([0.0, 0.0, 1.0], dtype=dtype)).abs().max() > 1e-9 or K[1, 0] != 0:
            raise CameraError(f"camera K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        Rd = R.double()
        err = (Rd @ Rd.T - torch.eye(3, dtype=torch.float64)).abs().max().item()
        if err > 1e-4 or torch.linalg.det(Rd) <= 0:
            raise CameraError(
                f"camera R must be a rotation (orthonormal, det +1); |R Rᵀ − I|max = {err:.3g}, "
                f"det = {torch.linalg.det(Rd).item():.6g}. Orthonormalise it (e.g. via SVD) or check row/column order"
            )
        self.K, self.R, self.t = K, R, t
        self.width, self.height = int(width), int(height)

    # -- basic geometry -------------------------------------------------------------------------
    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates ``[3]``: ``−Rᵀ t``."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> Tensor:
        """Unit viewing direction (camera +z) in world coordinates ``[3]``."""
        return self.R[2].clone()

    @property
    def fov_y_deg(self) -> float:
        """Vertical field of view in degrees (for a centred principal point)."""
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.K[1, 1].item()))

    def to(self, dtype=None) -> Camera:
        """A copy in ``dtype``."""
        return Camera(self.K, self.R, self.t, self.width, self.height, dtype=dtype)

    def binned(self, k: int) -> Camera:
        """The camera of this one's image binned ``k × k``: pixel (x', y') is the block of pixels
        x = k·x' … k·x' + k − 1 (and likewise y), so its pixel coordinates are ``x' = (x + ½)/k − ½`` — ``fx``, the
        skew and ``fy`` divided by ``k``, ``c' = (c + ½)/k − ½`` — and its size ``W // k × H // k`` (the last
        ``W mod k`` columns and ``H mod k`` rows, which fill no block, are left out). A binned pixel's box is exactly
        the union of its block's boxes.

        Raises:
            CameraError: ``k`` is not a positive integer, or is larger than the image."""
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or int(k) < 1:
            raise CameraError(f"bin must be a positive integer, got {k!r}")
        k = int(k)
        if k > min(self.width, self.height):
            raise CameraError(f"bin {k} is larger than the {self.width}×{self.height} image; use a bin of at most "
                              f"{min(self.width, self.height)}")
        if k == 1:
            return self
        K = self.K.clone()
        K[:2, :2] = K[:2, :2] / k
        K[:2, 2] = (K[:2, 2] + 0.5) / k - 0.5
        return Camera(K, self.R, self.t, self.width // k, self.height // k, dtype=self.K.dtype)

    def world_to_camera(self, points: Tensor) -> Tensor:
        """``x_cam = R x + t`` for points ``[..., 3]``."""
        R, t = self.R.to(points), self.t.to(points)
        return points @ R.T + t

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points ``[N, 3]`` → (pixel coordinates ``[N, 2]`` (x, y), depth ``[N]`` = z_cam).

        Pixel coordinates follow the integer-centre convention. Points with depth ≤ 0 are behind the
        camera; their pixel coordinates are meaningless (kornia returns a finite placeholder) — test
        ``depth > 0``.
        """
        if not isinstance(points, Tensor) or points.dim() != 2 or points.shape[1] != 3:
            raise CameraError(f"Camera.project: points must be a tensor [N, 3], got {getattr(points, 'shape', points)}")
        xc = self.world_to_camera(points)
        z = xc[:, 2:]
        safe = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
        pix = (xc @ self.K.to(points).T)[:, :2] / safe
        return pix, xc[:, 2]

    def pixel_grid(self, supersample: int = 1, dtype=None) -> Tensor:
        """Sample positions ``[H·W·k², 2]`` (x, y) in pixel coordinates, pixel-major.

        Sample ``s`` belongs to pixel ``s // k²`` (flat index y·W + x); inside a pixel the k×k samples
        sit at offsets ``(a + ½)/k − ½``, a = 0..k−1 (row-major, x fastest). k = 1 gives the centres.
        """
        k = check_supersample(supersample)
        dtype = dtype or self.K.dtype
        off = (torch.arange(k, dtype=dtype) + 0.5) / k - 0.5
        ys = torch.arange(self.height, dtype=dtype)
        xs = torch.arange(self.width, dtype=dtype)
        # [H, W, k(y), k(x)]
        x = xs[None, :, None, None] + off[None, None, None, :]
        y = ys[:, None, None, None] + off[None, None, :, None]
        x, y = torch.broadcast_tensors(x, y)
        return torch.stack([x, y], -1).reshape(-1, 2)

    def jittered_grid(self, supersample: int, generator: torch.Generator, dtype=None) -> Tensor:
        """Like :meth:`pixel_grid`, but each of the k×k samples of a pixel lies uniformly at random inside its
        stratum (a cell of side 1/k) instead of at the stratum's centre: stratified jitter, the pixel sampling of
        a Monte Carlo renderer with a box filter. Same order and shape ``[H·W·k², 2]``; ``generator`` seeds it."""
        k = check_supersample(supersample)
        dtype = dtype or self.K.dtype
        grid = self.pixel_grid(k, dtype)
        if not isinstance(generator, torch.Generator):
            raise CameraError(f"jittered_grid: generator must be a torch.Generator, got {type(generator).__name__}")
        u = torch.rand(grid.shape, generator=generator, dtype=dtype) - 0.5
        return grid + u / k

    def rays_at(self, xy: Tensor, dtype=None) -> tuple[Tensor, Tensor]:
        """Primary rays through image positions ``xy [M, 2]`` (x, y) in pixel coordinates (pixel centres at
        integers, OpenCV). Returns origins ``[M, 3]`` (the camera centre) and unit world directions ``[M, 3]``."""
        if not isinstance(xy, Tensor) or xy.dim() != 2 or xy.shape[-1] != 2:
            raise CameraError(f"rays_at: xy must be a tensor [M, 2] of pixel coordinates, got "
                              f"{tuple(xy.shape) if isinstance(xy, Tensor) else type(xy).__name__}")
        dtype = dtype or self.K.dtype
        pix = xy.to(dtype)
        cam = torch.cat([pix, torch.ones_like(pix[:, :1])], -1) @ torch.linalg.inv(self.K.to(dtype)).T
        d = torch.nn.functional.normalize(cam @ self.R.to(dtype), dim=-1)  # Rᵀ x as row vectors
        return self.center.to(dtype).expand_as(d), d

    def rays(self, supersample: int = 1, dtype=None) -> tuple[Tensor, Tensor]:
        """Primary rays through :meth:`pixel_grid` samples.

        Returns:
            origins ``[M, 3]`` (all the camera centre) and unit world directions ``[M, 3]``,
            M = H·W·k², ordered as :meth:`pixel_grid`.
        """
        dtype = dtype or self.K.dtype
        return self.rays_at(self.pixel_grid(supersample, dtype), dtype)

    # -- OpenGL ------------------------------------------------------------------------------------
    def to_opengl(self, near: float = 0.01, far: float = 100.0) -> tuple[Tensor, Tensor]:
        """OpenGL ``(view [4, 4], projection [4, 4])`` producing the same image.

        ``view`` is world-to-camera in the OpenGL camera frame (−z forward, y up). ``projection``
        maps to clip space so that NDC x = −1/+1 are the left/right image *edges* (−½ and W − ½ in
        OpenCV pixels) and NDC y = +1 is the top edge; depth uses ``near``/``far`` (world units).
        """
        if not (0 < near < far):
            raise CameraError(f"to_opengl: need 0 < near < far, got near={near}, far={far}")
        dt = torch.float64
        view = torch.eye(4, dtype=dt)
        view[:3, :3] = _FLIP @ self.R.to(dt)
        view[:3, 3] = _FLIP @ self.t.to(dt)
        fx, s, cx = (self.K[0, 0].item(), self.K[0, 1].item(), self.K[0, 2].item())
        fy, cy = self.K[1, 1].item(), self.K[1, 2].item()
        W, H = self.width, self.height
        P = torch.zeros(4, 4, dtype=dt)
        P[0, 0], P[0, 1], P[0, 2] = 2 * fx / W, -2 * s / W, 1 - 2 * (cx + 0.5) / W
        P[1, 1], P[1, 2] = 2 * fy / H, 2 * (cy + 0.5) / H - 1
        P[2, 2], P[2, 3] = -(far + near) / (far - near), -2 * far * near / (far - near)
        P[3, 2] = -1.0
        return view.to(self.K.dtype), P.to(self.K.dtype)

    @staticmethod
    def from_opengl(view, projection=None, *, width: int, height: int, fov_y_deg: float | None = None) -> Camera:
        """Inverse of :meth:`to_opengl`: from a view matrix and either a projection matrix or a
        vertical field of view (square pixels, centred principal point)."""
        view = _tensor(view, "view", (4, 4), torch.float64)
        R = _FLIP @ view[:3, :3]
        t = _FLIP @ view[:3, 3]
        W, H = int(width), int(height)
        if projection is not None:
            P = _tensor(projection, "projection", (4, 4), torch.float64)
            if abs(P[3, 2] + 1) > 1e-9 or P[3, 3] != 0:
                raise CameraError("from_opengl: projection must be a perspective matrix with last row [0, 0, -1, 0]")
            fx, fy = P[0, 0] * W / 2, P[1, 1] * H / 2
            s = -P[0, 1] * W / 2
            cx = (1 - P[0, 2]) * W / 2 - 0.5
            cy = (P[1, 2] + 1) * H / 2 - 0.5
        elif fov_y_deg is not None:
            fy = fx = 0.5 * H / math.tan(math.radians(fov_y_deg) / 2)
            s, cx, cy = 0.0, (W - 1) / 2, (H - 1) / 2
        else:
            raise CameraError("from_opengl: give a projection matrix or fov_y_deg")
        K = torch.tensor([[float(fx), float(s), float(cx)], [0.0, float(fy), float(cy)], [0.0, 0.0, 1.0]])
        return Camera(K, R, t, W, H)

    # -- Blender -----------------------------------------------------------------------------------
    def to_blender(self, sensor_width_mm: float = 36.0) -> dict:
        """Blender camera settings reproducing this camera (sensor fit HORIZONTAL, square pixels).

        Returns a dict: ``matrix_world`` (camera-to-world ``[4, 4]`` nested list, Blender/OpenGL camera
        frame), ``lens`` (mm), ``sensor_width`` (mm), ``sensor_fit`` ("HORIZONTAL"), ``shift_x``,
        ``shift_y`` (in units of the image width, Blender's convention), ``resolution_x``,
        ``resolution_y``. Shifts use the integer-centre convention: a principal point at
        ((W − 1)/2, (H − 1)/2) gives zero shift.
        """
        fx, fy, s = self.K[0, 0].item(), self.K[1, 1].item(), self.K[0, 1].item()
        if abs(fx - fy) > 1e-6 * fx or abs(s) > 1e-9:
            raise CameraError(f"to_blender: Blender needs square pixels and no skew (fx={fx}, fy={fy}, s={s})")
        R_c2w, t_c2w = _c2w(self)
        Rg, tg = camtoworld_vision_to_graphics_Rt(R_c2w[None], t_c2w[None, :, None])
        M = torch.eye(4, dtype=torch.float64)
        M[:3, :3], M[:3, 3] = Rg[0], tg[0, :, 0]
        W, H = self.width, self.height
        return {
            "matrix_world": M.tolist(),
            "lens": fx * sensor_width_mm / W,
            "sensor_width": sensor_width_mm,
            "sensor_fit": "HORIZONTAL",
            "shift_x": -(self.K[0, 2].item() - (W - 1) / 2) / W,
            "shift_y": (self.K[1, 2].item() - (H - 1) / 2) / W,
            "resolution_x": W,
            "resolution_y": H,
        }

    @staticmethod
    def from_blender(matrix_world, lens: float, sensor_width: float, resolution_x: int, resolution_y: int,
                     shift_x: float = 0.0, shift_y: float = 0.0, sensor_fit: str = "HORIZONTAL", **_ignored) -> Camera:
        """Inverse of :meth:`to_blender` (``sensor_fit`` must be HORIZONTAL, or AUTO with width ≥ height)."""
        if sensor_fit not in ("HORIZONTAL", "AUTO") or (sensor_fit == "AUTO" and resolution_x < resolution_y):
            raise CameraError(f"from_blender: only horizontal sensor fit is supported, got {sensor_fit}")
        if not (lens > 0 and sensor_width > 0):
            raise CameraError(f"from_blender: lens and sensor_width must be positive, got {lens}, {sensor_width}")
        M = _tensor(matrix_world, "matrix_world", (4, 4), torch.float64)
        Rv, tv = camtoworld_graphics_to_vision_Rt(M[None, :3, :3], M[None, :3, 3:])
        R = Rv[0].T
        t = -R @ tv[0, :, 0]
        W, H = int(resolution_x), int(resolution_y)
        f = lens * W / sensor_width
        cx = (W - 1) / 2 - shift_x * W
        cy = (H - 1) / 2 + shift_y * W
        return Camera([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], R, t, W, H)

    # -- serialisation -------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-ready dict: ``{"model": "opencv-pinhole", "K", "R", "t", "width", "height"}``."""
        return {
            "model": "opencv-pinhole",
            "K": self.K.double().tolist(),
            "R": self.R.double().tolist(),
            "t": self.t.double().tolist(),
            "width": self.width,
            "height": self.height,
        }

    @staticmethod
    def from_dict(d: dict) -> Camera:
        """Inverse of :meth:`to_dict`; raises :class:`CameraError` naming a missing or bad field."""
        if not isinstance(d, dict):
            raise CameraError(f"camera entry must be a JSON object, got {type(d).__name__}")
        if d.get("model", "opencv-pinhole") != "opencv-pinhole":
            raise CameraError(f"camera model '{d.get('model')}' is not supported; use 'opencv-pinhole'")
        for key in ("K", "R", "t", "width", "height"):
            if key not in d:
                raise CameraError(f"camera entry is missing field '{key}'")
        return Camera(d["K"], d["R"], d["t"], d["width"], d["height"])

    def __repr__(self) -> str:
        c = [round(x, 4) for x in self.center.tolist()]
        return f"Camera({self.width}x{self.height}, f={self.K[0, 0].item():.1f}, center={c})"


def _c2w(cam: Camera) -> tuple[Tensor, Tensor]:
    R = cam.R.double()
    return R.T, -R.T @ cam.t.double()


def check_supersample(k) -> int:
    """The supersampling factor k (k × k rays per pixel) as an int, or ValueError naming the allowed range."""
    if isinstance(k, bool) or not isinstance(k, int) or k < 1 or k > 16:
        raise ValueError(f"supersample must be an integer in [1, 16], got {k!r}")
    return k


def _vec3(x, name) -> Tensor:
    return _tensor(x, name, (3,), torch.float64)


def _intrinsics(fov_y_deg: float, width: int, height: int) -> Tensor:
    if not (0 < fov_y_deg < 180):
        raise CameraError(f"fov_y_deg must lie in (0, 180), got {fov_y_deg}")
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov_y_deg: float = 40.0,
            width: int = 512, height: int = 512) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image.

    Rows of R are the camera axes in world coordinates: right = forward × up, down = forward × right,
    forward = (target − eye)/|·|. Square pixels, principal point at the image centre ((W−1)/2, (H−1)/2).
    """
    eye, target, up = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
    fwd = target - eye
    if fwd.norm() < 1e-12:
        raise CameraError("look_at: eye and target coincide")
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, up)
    if right.norm() < 1e-9 * max(up.norm().item(), 1e-300):
        raise CameraError(
            f"look_at: up {up.tolist()} is parallel to the viewing direction {fwd.tolist()}; pick another up"
        )
    right = right / right.norm()
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])
    return Camera(_intrinsics(fov_y_deg, width, height), R, -R @ eye, width, height)


def orbit(n_views: int, radius: float, elevation_deg: float | Sequence[float] = 30.0, target=(0.0, 0.0, 0.0),
          fov_y_deg: float = 40.0, width: int = 512, height: int = 512,
          azimuth_offset_deg: float = 0.0) -> list[Camera]:
    """Cameras on circles about the +z axis through ``target``, all looking at ``target``.

    ``n_views`` cameras at equally spaced azimuths (from +x, counter-clockwise seen from +z, starting at
    ``azimuth_offset_deg``) on each elevation ring; a sequence of elevations gives one ring per
    elevation (len(elevations) · n_views cameras, ring by ring; rings alternate a half-step azimuth
    offset). Elevation is measured from the xy plane (90° = straight above, not allowed).
    """
    if not isinstance(n_views, int) or n_views < 1:
        raise CameraError(f"orbit: n_views must be a positive integer, got {n_views!r}")
    if not radius > 0:
        raise CameraError(f"orbit: radius must be positive, got {radius}")
    elevations = [elevation_deg] if isinstance(elevation_deg, (int, float)) else list(elevation_deg)
    target = _vec3(target, "target")
    cams = []
    for ring, el in enumerate(elevations):
        if not -89.9 <= el <= 89.9:
            raise CameraError(f"orbit: elevation must lie in [-89.9, 89.9] degrees, got {el}")
        for i in range(n_views):
            az = math.radians(azimuth_offset_deg + 360.0 * (i + 0.5 * (ring % 2)) / n_views)
            e = math.radians(el)
            d = torch.tensor([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)], dtype=torch.float64)
            cams.append(look_at(target + radius * d, target, (0.0, 0.0, 1.0), fov_y_deg, width, height))
    return cams


def rotation_about_axis(axis, angle_rad: float) -> Tensor:
    """Rotation matrix ``[3, 3]`` (float64) by ``angle_rad`` about unit ``axis`` (right-hand rule, Rodrigues)."""
    a = _vec3(axis, "axis")
    x, y, z = (a / a.norm()).tolist()
    Kx = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle_rad) * Kx + (1 - math.cos(angle_rad)) * Kx @ Kx


def turntable(n_views: int, radius: float, elevation_deg: float = 20.0, target=(0.0, 0.0, 0.0), fov_y_deg: float = 40.0,
              width: int = 512, height: int = 512) -> tuple[list[Camera], list[Tensor]]:
    """A fixed camera and studio lights, the object turning about +z through ``target`` in ``n_views`` steps.

    Everything is expressed in the *object* frame (where the mesh and its maps live): step k is
    equivalent to the studio rotated by −2πk/n about the axis. Returns ``(cameras, rotations)``;
    ``rotations[k]`` ``[3, 3]`` maps studio coordinates to object coordinates at step k, so a studio
    light at position p is at ``target + rotations[k] @ (p − target)`` for view k (directions:
    ``rotations[k] @ d``). The camera of step 0 sits at azimuth 0 (on +x).
    """
    cams0 = orbit(1, radius, elevation_deg, target, fov_y_deg, width, height)[0]
    tgt = _vec3(target, "target")
    cams, rots = [], []
    for k in range(n_views):
        Q = rotation_about_axis((0.0, 0.0, 1.0), -2.0 * math.pi * k / n_views)
        # camera pose in the object frame: centre c' = tgt + Q(c − tgt), R' = R Qᵀ
        R = cams0.R.double() @ Q.T
        c = tgt + Q @ (cams0.center.double() - tgt)
        cams.append(Camera(cams0.K, R, -R @ c, width, height))
        rots.append(Q)
    return cams, rots


def random_rig(seed: int, n_views: int = 16, radius: float | tuple[float, float] = (3.0, 4.0),
               elevation_deg: tuple[float, float] = (10.0, 60.0), target=(0.0, 0.0, 0.0), target_jitter: float = 0.0,
               fov_y_deg: float = 40.0, width: int = 512, height: int = 512) -> list[Camera]:
    """``n_views`` cameras at random azimuths (uniform), elevations (uniform in ``elevation_deg``) and
    distances (uniform in ``radius``) looking at ``target`` jittered by up to ``target_jitter``
    (world units, per axis). Reproducible: same ``seed`` → same rig."""
    g = torch.Generator().manual_seed(int(seed))
    r0, r1 = (radius, radius) if isinstance(radius, (int, float)) else radius
    e0, e1 = elevation_deg
    if not (0 < r0 <= r1) or not (-89.9 <= e0 <= e1 <= 89.9):
        raise CameraError(
            f"random_rig: need 0 < radius range and elevations in [-89.9, 89.9], got {radius}, {elevation_deg}"
        )
    u = torch.rand(n_views, 4, generator=g, dtype=torch.float64)
    tgt = _vec3(target, "target")
    cams = []
    for i in range(n_views):
        az = 2 * math.pi * u[i, 0].item()
        e = math.radians(e0 + (e1 - e0) * u[i, 1].item())
        r = r0 + (r1 - r0) * u[i, 2].item()
        jit = target_jitter * (2 * torch.rand(3, generator=g, dtype=torch.float64) - 1)
        d = torch.tensor([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)], dtype=torch.float64)
        cams.append(look_at(tgt + r * d, tgt + jit, (0.0, 0.0, 1.0), fov_y_deg, width, height))
    return cams
