"""Ray-cast G-buffers of known geometry: what every camera sample sees, computed once per view.

:func:`render_gbuffer` casts one ray per sample (k×k per pixel with ``supersample=k``, see
:meth:`renderer.camera.Camera.pixel_grid`) with embree (``trimesh.ray.ray_pyembree``, first hit
only) and keeps only the rays that hit the mesh. For each hit it recomputes the ray/triangle
intersection in float64 (Möller-Trumbore on the face embree reported) to get the exact distance
and barycentrics (b0, b1, b2) = (1 − β − γ, β, γ) — embree works in float32 — and interpolates:

- ``position = o + t·d`` (on the ray exactly; world units),
- ``normal`` = normalise(Σ b_i n_i), the interpolated shading normal,
- ``geo_normal`` = the face's unit normal from its winding,
- ``uv`` = Σ b_i uv_i,
- ``view = −d`` (unit, toward the camera).

Two-sided surfaces: where the ray hits the back of a face (geo_normal · view < 0, e.g. an open
plane seen from below or the inside of an open mesh) *both* ``geo_normal`` and ``normal`` are
flipped, so that ``geo_normal`` always faces the camera and the shading normal keeps its relation
to it; ``backface`` records where this happened. The shading normal itself may still face away
from the camera at silhouettes of coarse smooth-shaded meshes (normal · view ≤ 0): the shading
code drops those samples (no light can be reflected toward v from below the shading horizon).

All fields hold hit samples only, flat (N = number of hit rays); a camera that sees nothing gives
N = 0 and :attr:`GBuffer.coverage` 0 — the caller decides whether that is an error.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .camera import Camera, check_supersample
from .mesh import Mesh

__all__ = ["GBuffer", "render_gbuffer", "render_footprint", "face_uv", "face_planes", "FacePlanes", "intersect",
           "intersect_faces", "pixel_filter", "footprint_extent", "check_psf_sigma", "PSF_SUPPORT", "PSF_MAX_SIGMA"]


@dataclass
class GBuffer:
    """Hit samples of one view (module docstring gives the meaning of each field).

    Attributes:
        pixel: ``[N]`` int64 flat pixel index y·W + x of each sample.
        weight: ``[N]`` 1/k² (the sample's share of its pixel).
        position: ``[N, 3]`` world position of the hit.
        normal: ``[N, 3]`` unit interpolated shading normal (flipped with a back face).
        geo_normal: ``[N, 3]`` unit face normal, facing the camera.
        uv: ``[N, 2]`` texture coordinates.
        face: ``[N]`` int64 index of the hit face.
        view: ``[N, 3]`` unit direction toward the camera.
        depth: ``[N]`` distance along the ray from the camera centre (world units).
        backface: ``[N]`` bool, the ray hit the back of the face.
        height, width, supersample: image size and k.
    """

    pixel: Tensor
    weight: Tensor
    position: Tensor
    normal: Tensor
    geo_normal: Tensor
    uv: Tensor
    face: Tensor
    view: Tensor
    depth: Tensor
    backface: Tensor
    height: int
    width: int
    supersample: int = 1

    def __len__(self) -> int:
        return int(self.pixel.shape[0])

    @property
    def n_samples(self) -> int:
        return len(self)

    @property
    def coverage(self) -> float:
        """Fraction of the image area covered by the mesh, Σ weight / (H·W), in [0, 1]."""
        return float(self.weight.sum().item()) / (self.height * self.width) if len(self) else 0.0

    def pixel_weight(self) -> Tensor:
        """Per-pixel covered fraction ``[H, W]`` (1 inside, fractional on edges with supersampling)."""
        img = torch.zeros(self.height * self.width, dtype=self.weight.dtype, device=self.weight.device)
        return img.index_add(0, self.pixel, self.weight).reshape(self.height, self.width)

    def to_image(self, values: Tensor, background: float | Tensor = 0.0) -> Tensor:
        """Resolve per-sample values ``[N, C]`` (or ``[N]``) into an image ``[H, W, C]`` (or ``[H, W]``).

        Each pixel is Σ weight·value over its samples plus (1 − Σ weight)·background, i.e. the box
        filtered average of the k×k supersamples with misses showing the background. Differentiable
        with respect to ``values``.
        """
        if not isinstance(values, Tensor) or values.shape[:1] != (len(self),) or values.dim() not in (1, 2):
            raise ValueError(
                f"GBuffer.to_image: values must be a tensor [N] or [N, C] with N = {len(self)} samples, "
                f"got {tuple(getattr(values, 'shape', ()))}"
            )
        squeeze = values.dim() == 1
        v = values[:, None] if squeeze else values
        C = v.shape[1]
        w = self.weight.to(v)
        acc = torch.zeros(self.height * self.width, C, dtype=v.dtype, device=v.device)
        acc = acc.index_add(0, self.pixel.to(v.device), v * w[:, None])
        bg = torch.as_tensor(background, dtype=v.dtype, device=v.device)
        if bool((bg != 0).any()):
            cov = torch.zeros(self.height * self.width, dtype=v.dtype, device=v.device)
            cov = cov.index_add(0, self.pixel.to(v.device), w)
            acc = acc + (1.0 - cov)[:, None] * bg.reshape(1, -1)
        img = acc.reshape(self.height, self.width, C)
        return img[..., 0] if squeeze else img

    def to(self, device=None, dtype=None) -> GBuffer:
        """Move every tensor to ``device``; floating fields are cast to ``dtype`` when given."""
        out = {}
        for f in fields(self):
            x = getattr(self, f.name)
            if isinstance(x, Tensor):
                x = x.to(device=device, dtype=dtype if (dtype is not None and x.is_floating_point()) else None)
            out[f.name] = x
        return GBuffer(**out)

    def select(self, index: Tensor) -> GBuffer:
        """A G-buffer of a subset of the samples (boolean mask or index ``[M]``)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, x in out.items():
            if isinstance(x, Tensor):
                out[k] = x[index]
        return GBuffer(**out)


def intersect_faces(mesh: Mesh, origins: np.ndarray, directions: np.ndarray, faces: np.ndarray):
    """Exact (float64) Möller-Trumbore intersection of rays with given faces (one face per ray).

    Returns ``(t [M], beta [M], gamma [M])``: distance along the (unit) direction and the
    barycentrics of vertices 1 and 2. No hit test is made (the face is known to be hit); the
    determinant is guarded against 0 (ray parallel to the face → t = inf).
    """
    tri = mesh.tm.vertices[mesh.tm.faces[faces]]  # [M,3,3] float64
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    p = np.cross(directions, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-300
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origins - tri[:, 0]
    beta = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    gamma = np.einsum("ij,ij->i", directions, q) * inv
    t = np.where(ok, np.einsum("ij,ij->i", e2, q) * inv, np.inf)
    return t, beta, gamma


def intersect(mesh: Mesh, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
    """First hits of rays with ``mesh`` (float64 numpy), the G-buffer's core.

    Args:
        origins: ``[M, 3]`` or ``[1, 3]`` (shared origin). directions: ``[M, 3]`` unit.

    Returns:
        dict of arrays over the hit rays only: ``ray`` (index into the M rays), ``face``, ``t``
        (distance), ``bary [K, 3]``, ``position``, ``normal`` (interpolated, unit), ``geo_normal``,
        ``uv``, ``view`` (= −direction), ``backface``; normals flipped on back faces as described in the
        module docstring.
    """
    directions = np.asarray(directions, dtype=np.float64)
    origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), directions.shape)
    index_tri = mesh.intersector.intersects_first(ray_origins=origins, ray_directions=directions)
    ray = np.nonzero(index_tri >= 0)[0]
    face = index_tri[ray].astype(np.int64)
    d = directions[ray]
    o = origins[ray]
    t, beta, gamma = intersect_faces(mesh, o, d, face)
    # embree is float32: a hit near an edge may come out a hair outside the face; clamp and renormalise
    b = np.stack([1.0 - beta - gamma, beta, gamma], 1).clip(0.0, None)
    b /= b.sum(1, keepdims=True).clip(1e-300, None)
    t = np.where(np.isfinite(t), t, 0.0)
    pos = o + t[:, None] * d
    F = mesh.tm.faces[face]  # [K,3]
    n = np.einsum("nk,nkc->nc", b, mesh._normals64()[F])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-300, None)
    uv = np.einsum("nk,nkc->nc", b, mesh._uvs64()[F])
    tri = mesh.tm.vertices[F]
    gn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    gn /= np.linalg.norm(gn, axis=1, keepdims=True).clip(1e-300, None)
    view = -d
    back = np.einsum("ij,ij->i", gn, view) < 0
    sign = np.where(back, -1.0, 1.0)[:, None]
    return {"ray": ray, "face": face, "t": t, "bary": b, "position": pos, "normal": n * sign,
            "geo_normal": gn * sign, "uv": uv, "view": view, "backface": back}


class FacePlanes(NamedTuple):
    """Faces' planes seen from a pinhole camera, for :meth:`uv`, which gives the texture coordinates where the rays
    through image positions meet them (:func:`face_planes`). Per face, float64: ``to_plane`` = a − o (its first
    vertex from the camera centre), ``normal`` its unit normal, ``uv_map [N, 2, 3]`` its affine UV map's linear part
    (uv = ``uv_first`` + uv_map · (x − a) for x on the plane), ``uv_first [N, 2]``; ``pixel_to_ray [3, 3]`` maps (x,
    y, 1) to the camera's (unnormalised) ray direction, Rᵀ K⁻¹."""

    to_plane: Tensor
    normal: Tensor
    uv_map: Tensor
    uv_first: Tensor
    pixel_to_ray: Tensor

    def uv(self, xy: Tensor) -> tuple[Tensor, Tensor]:
        """``(uv [N, ..., 2], ok [N, ...])`` at image positions ``xy [N, ..., 2]`` (face i's positions in row i; the
        middle dimensions, e.g. several sub-samples of a face, broadcast). For ray direction w, the plane is met at
        x = o + t·w, t = ((a − o)·n) / (w·n); uv = uv_first + uv_map · (x − a). ``ok`` and the fallback as
        :func:`face_uv`."""
        N = len(self.normal)
        if not isinstance(xy, Tensor) or xy.dim() < 2 or xy.shape[0] != N or xy.shape[-1] != 2:
            raise ValueError(f"FacePlanes.uv: xy must be [{N}, ..., 2] image positions, one row per face, got "
                             f"{tuple(getattr(xy, 'shape', ()))}")
        lead = (N,) + (1,) * (xy.dim() - 2)
        w = torch.cat([xy.to(torch.float64), torch.ones_like(xy[..., :1], dtype=torch.float64)], -1) \
            @ self.pixel_to_ray.T
        n, a_o = self.normal.view(*lead, 3), self.to_plane.view(*lead, 3)
        den = (w * n).sum(-1)
        s = (a_o * n).sum(-1)
        crossing = den.abs() > 1e-12 * w.norm(dim=-1)                  # the ray is not parallel to the plane
        t = s / torch.where(crossing, den, torch.ones_like(den))
        ok = crossing & (t > 0)
        q = t[..., None] * w - a_o                                      # x − a
        uv = self.uv_first.view(*lead, 2) + (self.uv_map.view(*lead, 2, 3) @ q[..., None]).squeeze(-1)
        return torch.where(ok[..., None], uv, self.uv_first.view(*lead, 2)), ok


def face_planes(mesh: Mesh, camera: Camera, face: Tensor) -> FacePlanes:
    """The planes of the faces ``face [N]`` as seen from ``camera``, whose :meth:`FacePlanes.uv` gives texture
    coordinates at image positions: what :func:`face_uv` computes, with the per-face quantities made once for any
    number of positions per face (a pixel's texture sub-samples all lie on its ray's face)."""
    _check_inputs(mesh, camera, "face_planes")
    if not isinstance(face, Tensor) or face.dim() != 1:
        raise ValueError(f"face_planes: face must be [N] face indices, got {tuple(getattr(face, 'shape', ()))}")
    f = mesh.faces.long()[face]
    V = torch.from_numpy(np.asarray(mesh.tm.vertices, dtype=np.float64))      # the arrays intersect() reads
    UV = torch.from_numpy(mesh._uvs64())
    a, b, c = V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]
    e0, e1 = b - a, c - a
    n = torch.linalg.cross(e0, e1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    # barycentric β, γ of a point x of the plane: (x − a)·(d11 e0 − d01 e1) / det, (x − a)·(d00 e1 − d01 e0) / det
    d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    det = (d00 * d11 - d01 * d01).clamp_min(1e-300)[:, None]
    beta = (d11[:, None] * e0 - d01[:, None] * e1) / det
    gamma = (d00[:, None] * e1 - d01[:, None] * e0) / det
    ua, ub, uc = UV[f[:, 0]], UV[f[:, 1]], UV[f[:, 2]]
    uv_map = (ub - ua)[:, :, None] * beta[:, None, :] + (uc - ua)[:, :, None] * gamma[:, None, :]
    to_ray = camera.R.to(torch.float64).T @ torch.linalg.inv(camera.K.to(torch.float64))
    return FacePlanes(a - camera.center.to(torch.float64), n, uv_map, ua, to_ray)


def face_uv(mesh: Mesh, camera: Camera, face: Tensor, xy: Tensor) -> tuple[Tensor, Tensor]:
    """Texture coordinates where the rays through image positions ``xy [M, 2]`` meet the planes of the faces
    ``face [M]``, without casting them: ``(uv [M, 2], ok [M])`` in float64 (:func:`face_planes`).

    Exact where the ray hits the face itself; beyond its edges it is the face's affine UV map continued over its
    plane, which differs from the neighbouring face's UVs by the surface's bend across the edge (second order in
    the distance). Near a hit this is the ray differential of the texture coordinates carried to finite offsets:
    how a pixel's footprint on the texture is found without a ray per sub-sample. ``ok`` is False where the ray
    runs parallel to the plane or meets it behind the camera (silhouettes); ``uv`` there is the face's first
    vertex's and must not be used.
    """
    _check_inputs(mesh, camera, "face_uv")
    if not isinstance(face, Tensor) or face.dim() != 1 or not isinstance(xy, Tensor) or xy.shape != (len(face), 2):
        raise ValueError(f"face_uv: face must be [M] face indices and xy [M, 2] image positions, got "
                         f"{tuple(getattr(face, 'shape', ()))} and {tuple(getattr(xy, 'shape', ()))}")
    return face_planes(mesh, camera, face).uv(xy)


def _check_pixels(pixels, camera: Camera, where: str) -> Tensor:
    n = camera.height * camera.width
    if not isinstance(pixels, Tensor) or pixels.dim() != 1 or pixels.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"{where}: pixels must be a 1-D integer tensor of flat pixel indices y·W + x, got "
                         f"{getattr(pixels, 'dtype', type(pixels).__name__)} {tuple(getattr(pixels, 'shape', ()))}")
    if pixels.numel() and (int(pixels.min()) < 0 or int(pixels.max()) >= n):
        raise ValueError(f"{where}: pixel indices must lie in [0, {n}) for a {camera.width}×{camera.height} camera")
    return pixels.long()


def _cast(mesh: Mesh, camera: Camera, xy: Tensor, pixel: Tensor, weight: Tensor, k: int) -> GBuffer:
    """A :class:`GBuffer` of the rays through image positions ``xy [M, 2]`` (pixel coordinates), each belonging
    to pixel ``pixel [M]`` with share ``weight [M]`` of it; only hits are kept."""
    origins_t, dirs_t = camera.rays_at(xy, dtype=torch.float64)
    hit = intersect(mesh, origins_t[:1].numpy(), dirs_t.numpy())
    ray = torch.from_numpy(hit["ray"].astype(np.int64))
    dt = torch.get_default_dtype()
    f32 = lambda x: torch.from_numpy(np.ascontiguousarray(x)).to(dt)
    return GBuffer(
        pixel=pixel[ray],
        weight=weight[ray].to(dt),
        position=f32(hit["position"]),
        normal=f32(hit["normal"]),
        geo_normal=f32(hit["geo_normal"]),
        uv=f32(hit["uv"]),
        face=torch.from_numpy(hit["face"]),
        view=f32(hit["view"]),
        depth=f32(hit["t"]),
        backface=torch.from_numpy(hit["backface"]),
        height=camera.height,
        width=camera.width,
        supersample=k,
    )


#: Support of a Gaussian pixel filter's tail beyond the pixel's square, in σ: the box ⊗ Gaussian filter is cut
#: where it has fallen below 0.14 % of its peak (the Gaussian's mass beyond 3σ on one side is 0.13 %).
PSF_SUPPORT = 3.0


#: Largest Gaussian PSF σ (pixels): its filter square is then 25 pixels wide, which the 16 × 16 cap of
#: :func:`render_footprint` samples 1.6 pixels apart — coarser would no longer integrate it.
PSF_MAX_SIGMA = 4.0


def check_psf_sigma(psf_sigma) -> float:
    """A Gaussian PSF σ in pixels as a float, or ValueError naming the allowed range (the one check of every
    place that takes it: scene.json, synthetic scenes, reconstruct, the footprints)."""
    if isinstance(psf_sigma, bool) or not isinstance(psf_sigma, (int, float)) or not 0 <= psf_sigma <= PSF_MAX_SIGMA:
        raise ValueError(f"psf_sigma must be a blur σ in pixels in [0, {PSF_MAX_SIGMA:g}] (0 = the box filter "
                         f"alone), got {psf_sigma!r}")
    return float(psf_sigma)


def footprint_extent(psf_sigma: float) -> float:
    """Side (pixels) of the square a pixel's filter covers: 1 for the box, ``1 + 2·PSF_SUPPORT·σ`` with a
    Gaussian PSF of σ pixels."""
    return 1.0 + 2.0 * PSF_SUPPORT * check_psf_sigma(psf_sigma)


def pixel_filter(offset: Tensor, psf_sigma: float) -> Tensor:
    """1-D pixel filter at ``offset`` (pixels from the pixel centre): the unit box, or with ``psf_sigma`` > 0 the
    box convolved with a Gaussian of σ pixels, ``½ [erf((x + ½)/(σ√2)) − erf((x − ½)/(σ√2))]`` (integral 1). The
    2-D filter is the product of the filters along x and y."""
    x = torch.as_tensor(offset, dtype=torch.float64)
    if psf_sigma == 0:
        return ((x >= -0.5) & (x <= 0.5)).to(torch.float64)
    s = float(psf_sigma) * 2.0 ** 0.5
    return 0.5 * (torch.erf((x + 0.5) / s) - torch.erf((x - 0.5) / s))


def _strata(pixels: Tensor, k: int, width: int, extent: float = 1.0) -> Tensor:
    """Image positions ``[M·k², 2]`` of the k × k strata centres over each pixel's filter square of side ``extent``
    (pixel-major, x fastest inside a pixel — the order of :meth:`renderer.camera.Camera.pixel_grid`)."""
    off = ((torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5) * extent
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    centre = torch.stack([(pixels % width).double(), (pixels // width).double()], -1)
    return (centre[:, None, :] + torch.stack([ox.reshape(-1), oy.reshape(-1)], -1)[None]).reshape(-1, 2)


def _check_inputs(mesh, camera, where: str) -> None:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{where}: mesh must be a renderer.mesh.Mesh, got {type(mesh).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"{where}: camera must be a renderer.camera.Camera, got {type(camera).__name__}")


def render_gbuffer(mesh: Mesh, camera: Camera, supersample: int = 1, *, jitter: torch.Generator | None = None,
                   pixels: Tensor | None = None) -> GBuffer:
    """Ray-cast the G-buffer of ``mesh`` seen by ``camera`` (see module docstring).

    Args:
        mesh: the object (its embree scene is built once and cached on the mesh).
        camera: an OpenCV camera.
        supersample: k, casting k×k rays per pixel (1 = pixel centres).
        jitter: a generator → each ray at a uniform random position inside its stratum
            (:meth:`renderer.camera.Camera.jittered_grid`, how a Monte Carlo renderer integrates a box-filtered
            pixel); None → at the strata's centres.
        pixels: optional flat pixel indices ``[M]``: cast only these pixels' rays (to bound memory, render an
            image in blocks of pixels); None = every pixel.

    Returns:
        A :class:`GBuffer` of float32 (torch default dtype) tensors on the CPU.
    """
    _check_inputs(mesh, camera, "render_gbuffer")
    k = check_supersample(supersample)
    if pixels is None:
        grid = camera.jittered_grid(k, jitter, torch.float64) if jitter is not None else \
            camera.pixel_grid(k, torch.float64)
        pixel = torch.arange(camera.height * camera.width).repeat_interleave(k * k)
    else:
        # the same strata (pixel-major, x fastest inside a pixel) for the given pixels only
        pixels = _check_pixels(pixels, camera, "render_gbuffer")
        grid = _strata(pixels, k, camera.width)
        if jitter is not None:
            grid = grid + (torch.rand(grid.shape, generator=jitter, dtype=torch.float64) - 0.5) / k
        pixel = pixels.repeat_interleave(k * k)
    return _cast(mesh, camera, grid, pixel, torch.full((len(pixel),), 1.0 / (k * k), dtype=torch.float64), k)


def render_footprint(mesh: Mesh, camera: Camera, pixels: Tensor, counts: Tensor, *,
                     psf_sigma: float = 0.0) -> GBuffer:
    """The G-buffer of pixel footprints with a sample count chosen per pixel.

    Pixel ``pixels[i]`` (flat index y·W + x) is covered by ``counts[i]``² rays at the centres of a regular
    ``counts[i] × counts[i]`` grid of strata over its square (the box filter's footprint), each of weight
    ``1 / counts[i]²``; ``counts[i] = 1`` is the pixel centre. Misses are dropped as in :func:`render_gbuffer`, so
    a pixel whose weights sum to less than 1 is partly background. ``supersample`` records the largest count.

    ``psf_sigma`` > 0 (pixels): the pixel filter is the box convolved with a Gaussian of that σ (lens blur,
    demosaicing; :func:`pixel_filter`). The strata then cover the square grown by :data:`PSF_SUPPORT` σ on every
    side (:func:`footprint_extent`) and each ray's weight is the filter's value at its stratum times the stratum's
    area, normalised to sum 1 over the pixel.
    """
    _check_inputs(mesh, camera, "render_footprint")
    pixels = _check_pixels(pixels, camera, "render_footprint")
    extent = footprint_extent(psf_sigma)
    counts = torch.as_tensor(counts).long()
    if counts.shape != pixels.shape or (counts.numel() and (int(counts.min()) < 1 or int(counts.max()) > 16)):
        raise ValueError(f"render_footprint: counts must hold one integer in [1, 16] per pixel ({tuple(pixels.shape)}),"
                         f" got {tuple(counts.shape)}")
    xy, pix, wt = [], [], []
    W = camera.width
    for k in torch.unique(counts).tolist():
        p = pixels[counts == k]
        xy.append(_strata(p, k, W, extent))
        pix.append(p.repeat_interleave(k * k))
        off = ((torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5) * extent
        w1 = pixel_filter(off, psf_sigma)
        w2 = (w1[:, None] * w1[None, :]).reshape(-1)
        wt.append((w2 / w2.sum()).repeat(len(p)))
    if not xy:
        xy, pix, wt = [torch.zeros(0, 2, dtype=torch.float64)], [torch.zeros(0, dtype=torch.long)], \
            [torch.zeros(0, dtype=torch.float64)]
    kmax = int(counts.max()) if counts.numel() else 1
    return _cast(mesh, camera, torch.cat(xy), torch.cat(pix), torch.cat(wt), kmax)
