"""Triangle meshes with UVs: loading, saving and primitives with good, injective UV layouts.

A :class:`Mesh` holds the geometry as torch tensors (what the shading code reads) and the
``trimesh.Trimesh`` built from the same arrays (what the ray caster reads):

- ``vertices [V, 3]`` float32, world units (the scene's length unit; the renderer never assumes metres),
- ``faces [F, 3]`` int64, counter-clockwise seen from the side the normal points to,
- ``uvs [V, 2]`` float32, texture coordinates with (0, 0) at the bottom-left of the map
  (see :mod:`renderer.texture` for the texel convention),
- ``normals [V, 3]`` float32, unit per-vertex shading normals.

UV seams need duplicated vertices (one vertex cannot carry two UVs); trimesh's OBJ loader
splits vertices at seams, and every primitive here builds seams with duplicated vertices.

The reconstruction solves per texel, so texture space must be *injective*: no two surface points
may share a texel. Every primitive here packs its charts into [0, 1]² without overlap, with a
gutter between charts (:func:`nonconvex`). World up for the primitives is +z.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

__all__ = ["Mesh", "MeshError", "load_mesh", "save_mesh", "uv_sphere", "torus", "plane", "nonconvex", "revolve"]


class MeshError(ValueError):
    """A mesh file or mesh array that cannot be used (unreadable, no UVs, degenerate)."""


def _area_weighted_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex unit normals, area-weighted over the faces around each *position*.

    Vertices duplicated at UV seams share their position, so their normals are merged across the
    seam (no shading crease at a UV seam). Isolated vertices get +z.
    """
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    # Merge by exact position (seam duplicates are bit-identical in every loader we use).
    _, key = np.unique(vertices.round(decimals=9), axis=0, return_inverse=True)
    key = key.reshape(-1)
    acc = np.zeros((key.max() + 1, 3))
    for c in range(3):
        np.add.at(acc, key[faces[:, c]], fn)
    n = acc[key]
    length = np.linalg.norm(n, axis=1, keepdims=True)
    ok = length[:, 0] > 1e-300
    out = np.tile(np.array([0.0, 0.0, 1.0]), (len(vertices), 1))
    out[ok] = n[ok] / length[ok]
    return out


@dataclass(eq=False)
class Mesh:
    """A triangle mesh with per-vertex UVs and shading normals (see module docstring).

    Build it with :meth:`from_arrays`, :func:`load_mesh` or a primitive; the constructor checks
    shapes, index range and finiteness. ``tm`` is built from the same arrays with ``process=False``
    so face ``i`` of ``tm`` is face ``i`` of ``faces``.
    """

    vertices: Tensor
    faces: Tensor
    uvs: Tensor
    normals: Tensor
    tm: trimesh.Trimesh = field(repr=False, default=None)
    name: str = ""

    def __post_init__(self):
        v, f, uv, n = self.vertices, self.faces, self.uvs, self.normals
        where = f"mesh '{self.name}'" if self.name else "mesh"
        for label, x, width in (("vertices", v, 3), ("faces", f, 3), ("uvs", uv, 2), ("normals", n, 3)):
            if not isinstance(x, Tensor):
                raise MeshError(f"{where}: {label} must be a torch.Tensor, got {type(x).__name__}")
            if x.dim() != 2 or x.shape[1] != width:
                raise MeshError(f"{where}: {label} must have shape [*, {width}], got {tuple(x.shape)}")
        if len(v) == 0 or len(f) == 0:
            raise MeshError(f"{where}: has no vertices or no faces")
        if len(uv) != len(v) or len(n) != len(v):
            raise MeshError(
                f"{where}: uvs {tuple(uv.shape)} and normals {tuple(n.shape)} must have one row per vertex "
                f"({len(v)}); duplicate vertices at UV seams"
            )
        if f.dtype != torch.long:
            raise MeshError(f"{where}: faces must be int64 (torch.long), got {f.dtype}")
        if f.min().item() < 0 or f.max().item() >= len(v):
            raise MeshError(f"{where}: face indices must lie in [0, {len(v) - 1}]")
        for label, x in (("vertices", v), ("uvs", uv), ("normals", n)):
            if not torch.isfinite(x).all():
                raise MeshError(f"{where}: {label} contain NaN or inf")
        if self.tm is None:
            self.tm = trimesh.Trimesh(
                vertices=v.detach().cpu().double().numpy(), faces=f.cpu().numpy(), process=False, validate=False
            )
        elif len(self.tm.faces) != len(f):
            raise MeshError(f"{where}: trimesh object has {len(self.tm.faces)} faces, tensors have {len(f)}")
        self._intersector = None

    # -- construction -----------------------------------------------------------------------
    @staticmethod
    def from_arrays(vertices, faces, uvs, normals=None, name: str = "") -> Mesh:
        """Build from array-likes; ``normals=None`` computes area-weighted vertex normals
        (merged across UV seams). Floats become float32 (torch default dtype), faces int64."""
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        uv = np.asarray(uvs, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise MeshError(f"mesh '{name}': vertices must be [V,3] and faces [F,3], got {v.shape} and {f.shape}")
        if normals is None:
            if f.size and (f.min() < 0 or f.max() >= len(v)):
                raise MeshError(f"mesh '{name}': face indices must lie in [0, {len(v) - 1}]")
            n = _area_weighted_normals(v, f)
        else:
            n = np.asarray(normals, dtype=np.float64)
            length = np.linalg.norm(n, axis=-1, keepdims=True) if n.ndim == 2 else None
            if length is not None and np.all(length > 0):
                n = n / length
        dt = torch.get_default_dtype()
        # the ray caster sees exactly the (float32-rounded) vertices the shading code sees
        v = torch.as_tensor(v, dtype=dt).double().numpy()
        tm = None
        if f.ndim == 2 and len(f) and v.ndim == 2:
            tm = trimesh.Trimesh(vertices=v, faces=f, process=False, validate=False)
        return Mesh(
            vertices=torch.as_tensor(v, dtype=dt),
            faces=torch.as_tensor(f, dtype=torch.long),
            uvs=torch.as_tensor(uv, dtype=dt),
            normals=torch.as_tensor(n, dtype=dt),
            tm=tm,
            name=name,
        )

    # -- derived quantities --------------------------------------------------------------------
    @property
    def scale(self) -> float:
        """Length of the bounding-box diagonal (world units); the yardstick for ray epsilons."""
        lo, hi = self.tm.bounds
        return float(np.linalg.norm(hi - lo))

    @property
    def bounds(self) -> Tensor:
        """Axis-aligned bounding box ``[2, 3]`` (min, max)."""
        return torch.as_tensor(np.array(self.tm.bounds), dtype=self.vertices.dtype)

    @property
    def intersector(self):
        """The embree ray intersector of ``tm`` (built once, cached)."""
        if self._intersector is None:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            self._intersector = RayMeshIntersector(self.tm)
        return self._intersector

    def _normals64(self) -> np.ndarray:
        if getattr(self, "_n64", None) is None:
            self._n64 = self.normals.detach().cpu().double().numpy()
        return self._n64

    def _uvs64(self) -> np.ndarray:
        if getattr(self, "_uv64", None) is None:
            self._uv64 = self.uvs.detach().cpu().double().numpy()
        return self._uv64

    def face_normals(self) -> Tensor:
        """Unit geometric normals ``[F, 3]`` from the winding (counter-clockwise = front)."""
        tri = self.vertices[self.faces]
        return torch.nn.functional.normalize(torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1), dim=-1)

    def __repr__(self) -> str:
        return f"Mesh('{self.name}', V={len(self.vertices)}, F={len(self.faces)})"


# -- file I/O -----------------------------------------------------------------------------------
def _uvs_of(tm: trimesh.Trimesh) -> np.ndarray | None:
    uv = getattr(tm.visual, "uv", None)
    if uv is None:
        return None
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape != (len(tm.vertices), 2):
        return None
    return uv


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Load an OBJ, PLY, GLB or glTF file with per-vertex UVs into a :class:`Mesh`.

    The file is read by trimesh (``force='mesh'``, so a scene of several geometries is
    concatenated, with their transforms applied, into one mesh) without merging or reordering
    vertices; trimesh's OBJ loader duplicates vertices at UV seams. Normals stored in the file are
    used when present, else area-weighted normals are computed (merged across UV seams).

    Raises:
        MeshError: the file does not exist, cannot be parsed, holds no triangles, or has no UVs
            (the message names the file and says how to add them).
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file '{path}' does not exist")
    try:
        loaded = trimesh.load(str(path), process=False)
        if isinstance(loaded, trimesh.Trimesh):
            tm = loaded
            # normals read from the file sit in the cache; computed ones would not be there yet
            file_normals = "vertex_normals" in tm._cache.cache
        else:  # a Scene: concatenate every geometry with its transform, as force='mesh' does
            tm = trimesh.load(str(path), force="mesh", process=False)
            file_normals = False
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshError(f"cannot read mesh file '{path}': {type(exc).__name__}: {exc}") from None
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise MeshError(f"mesh file '{path}' holds no triangles (got {type(tm).__name__})")
    uv = _uvs_of(tm)
    if uv is None:
        raise MeshError(
            f"mesh file '{path}' has no per-vertex texture coordinates (UVs); shadecap stores materials in "
            f"texture space. Unwrap the mesh (e.g. Blender: UV > Smart UV Project, or xatlas) and export it "
            f"as OBJ/GLB with UVs"
        )
    normals = np.asarray(tm.vertex_normals, dtype=np.float64) if file_normals else None
    return Mesh.from_arrays(tm.vertices, tm.faces, uv, normals, name=path.name)


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    from .imageio import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)


def save_mesh(mesh: Mesh, path: str | os.PathLike) -> None:
    """Write ``mesh`` atomically (temporary file + rename, never half-written).

    ``.obj``: ``v``, ``vt``, ``vn`` and ``f v/vt/vn`` lines, one index per vertex, so
    :func:`load_mesh` returns the same arrays (up to the 9 printed significant digits).
    ``.ply``/``.glb``/``.gltf``: through trimesh's exporter with the UVs as texture coordinates.
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"save_mesh: expected a Mesh, got {type(mesh).__name__}")
    path = Path(path)
    ext = path.suffix.lower()
    v = mesh.vertices.detach().cpu().double().numpy()
    uv = mesh.uvs.detach().cpu().double().numpy()
    n = mesh.normals.detach().cpu().double().numpy()
    f = mesh.faces.cpu().numpy() + 1
    if ext == ".obj":
        lines = ["# written by shadecap renderer.mesh.save_mesh", f"# {mesh.name}"]
        lines += [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v]
        lines += [f"vt {a:.9g} {b:.9g}" for a, b in uv]
        lines += [f"vn {a:.9g} {b:.9g} {c:.9g}" for a, b, c in n]
        lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in f]
        _atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())
    elif ext in (".ply", ".glb", ".gltf"):
        tm = trimesh.Trimesh(vertices=v, faces=f - 1, vertex_normals=n, process=False)
        tm.visual = trimesh.visual.TextureVisuals(uv=uv)
        data = tm.export(file_type=ext[1:])
        if isinstance(data, dict):  # .gltf exports a dict of files
            raise MeshError(f"save_mesh: write '{path}' as .glb (single file) instead of .gltf")
        _atomic_write_bytes(path, data if isinstance(data, bytes) else data.encode())
    else:
        raise MeshError(f"save_mesh: unsupported extension '{ext}' for '{path}'; use .obj, .ply or .glb")


# -- primitives -----------------------------------------------------------------------------------
def revolve(
    pieces: list[np.ndarray],
    segments: int,
    charts: list[tuple[float, float, float, float]],
    piece_normals: list[np.ndarray | None] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Surface of revolution about +z of profile pieces, each unwrapped to its own UV rectangle.

    Args:
        pieces: profile polylines ``[P_k, 2]`` of (r ≥ 0, z) points, each traversed with the solid on
            its left (in the (r, z) half-plane, r to the right, z up) so that normals point outward.
            Pieces are separate charts with their own vertices, so a corner between pieces is a
            sharp crease.
        segments: number of quads around the axis.
        charts: per piece its UV rectangle ``(u0, v0, u1, v1)``; u runs around the axis (angle
            0 → u0 at +x, counter-clockwise seen from +z), v along the profile.
        piece_normals: optional per piece exact 2D profile normals ``[P_k, 2]`` (unit, (n_r, n_z));
            default: from central differences of the polyline (exact for lines and for interior
            points of uniformly sampled circular arcs).

    Returns:
        vertices [V,3], faces [F,3], uvs [V,2], normals [V,3] as numpy arrays. Triangles that
        collapse on the axis (r = 0) are removed.
    """
    verts, faces, uvs, norms = [], [], [], []
    base = 0
    theta = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    c, s = np.cos(theta), np.sin(theta)
    for k, prof in enumerate(pieces):
        prof = np.asarray(prof, dtype=np.float64)
        m = len(prof)
        if piece_normals is not None and piece_normals[k] is not None:
            n2 = np.asarray(piece_normals[k], dtype=np.float64)
        else:
            tang = np.gradient(prof, axis=0)
            n2 = np.stack([tang[:, 1], -tang[:, 0]], axis=1)
            n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
        r, z = prof[:, 0:1], prof[:, 1:2]
        # grid [m, segments+1]
        x = r * c[None]
        y = r * s[None]
        zz = np.broadcast_to(z, x.shape)
        verts.append(np.stack([x, y, zz], -1).reshape(-1, 3))
        norms.append(np.stack([n2[:, :1] * c[None], n2[:, :1] * s[None], np.broadcast_to(n2[:, 1:], x.shape)], -1)
                     .reshape(-1, 3))
        u0, v0, u1, v1 = charts[k]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(prof, axis=0), axis=1))])
        tt = arc / arc[-1]
        uu = u0 + (u1 - u0) * (theta / (2.0 * math.pi))
        vv = v0 + (v1 - v0) * tt
        uvs.append(np.stack(np.broadcast_arrays(uu[None, :], vv[:, None]), -1).reshape(-1, 2))
        i, j = np.meshgrid(np.arange(m - 1), np.arange(segments), indexing="ij")
        a = i * (segments + 1) + j
        b, cc, d = a + 1, a + segments + 2, a + segments + 1  # (i,j+1), (i+1,j+1), (i+1,j)
        tri = np.concatenate([np.stack([a, b, cc], -1).reshape(-1, 3), np.stack([a, cc, d], -1).reshape(-1, 3)])
        faces.append(tri + base)
        base += m * (segments + 1)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    t = v[f]
    area2 = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    f = f[area2 > 1e-12 * max(1.0, float(np.abs(v).max()) ** 2)]
    used = np.zeros(len(v), dtype=bool)
    used[f.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f], np.concatenate(uvs)[used], np.concatenate(norms)[used]


def _check_positive(**kw):
    for k, x in kw.items():
        if not (isinstance(x, (int, float)) and math.isfinite(x) and x > 0):
            raise ValueError(f"{k} must be a positive finite number, got {x!r}")


def _check_count(minimum=3, **kw):
    for k, x in kw.items():
        if not isinstance(x, (int, np.integer)) or x < minimum:
            raise ValueError(f"{k} must be an integer ≥ {minimum}, got {x!r}")


def uv_sphere(radius: float = 1.0, segments: int = 64, rings: int = 32, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Sphere of ``radius`` about ``center``: u = longitude/2π (from +x, counter-clockwise about +z),
    v = (latitude + 90°)/180° (v = 0 at the south pole −z, 1 at the north pole +z).
    Exact analytic normals. One seam (u = 0 ≡ 1) with duplicated vertices."""
    _check_positive(radius=radius)
    _check_count(segments=segments, rings=rings, minimum=3)
    phi = np.linspace(-0.5 * math.pi, 0.5 * math.pi, rings + 1)  # bottom to top: solid on the left
    prof = np.stack([radius * np.cos(phi), radius * np.sin(phi)], 1)
    prof[0, 0] = prof[-1, 0] = 0.0
    n2 = np.stack([np.cos(phi), np.sin(phi)], 1)
    v, f, uv, n = revolve([prof], segments, [(0.0, 0.0, 1.0, 1.0)], [n2])
    return Mesh.from_arrays(v + np.asarray(center, dtype=np.float64), f, uv, n, name="uv_sphere")


def torus(R: float = 1.0, r: float = 0.35, segments: int = 64, rings: int = 32, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Torus about +z (major radius ``R``, minor ``r`` < R): u = angle about z / 2π, v = angle about the
    tube / 2π starting at the innermost point. Exact normals; two seams with duplicated vertices."""
    _check_positive(R=R, r=r)
    _check_count(segments=segments, rings=rings, minimum=3)
    if r >= R:
        raise ValueError(f"torus: minor radius r={r} must be smaller than major radius R={R}")
    psi = np.linspace(-math.pi, math.pi, rings + 1)  # inner point first, moving down there: solid on the left
    n2 = np.stack([np.cos(psi), np.sin(psi)], 1)
    prof = np.stack([R + r * n2[:, 0], r * n2[:, 1]], 1)
    v, f, uv, n = revolve([prof], segments, [(0.0, 0.0, 1.0, 1.0)], [n2])
    return Mesh.from_arrays(v + np.asarray(center, dtype=np.float64), f, uv, n, name="torus")


def plane(size: float = 2.0, subdivisions: int = 1, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Square ``size`` × ``size`` in the z = center_z plane, normal +z, single-sided geometry
    (the G-buffer treats it as two-sided). ``u = (x − x0)/size + 1/2``, ``v = (y − y0)/size + 1/2``:
    seen from +z with +y up on screen, the map appears upright (row 0 of the map at +y)."""
    _check_positive(size=size)
    _check_count(subdivisions=subdivisions, minimum=1)
    t = np.linspace(0.0, 1.0, subdivisions + 1)
    uu, vv = np.meshgrid(t, t, indexing="xy")  # rows: v, columns: u
    uv = np.stack([uu, vv], -1).reshape(-1, 2)
    v = np.concatenate([(uv - 0.5) * size, np.zeros((len(uv), 1))], 1) + np.asarray(center, dtype=np.float64)
    s = subdivisions + 1
    i, j = np.meshgrid(np.arange(subdivisions), np.arange(subdivisions), indexing="ij")
    a = i * s + j
    f = np.concatenate([np.stack([a, a + 1, a + s + 1], -1).reshape(-1, 3), np.stack([a, a + s + 1, a + s], -1)
                        .reshape(-1, 3)])
    n = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    return Mesh.from_arrays(v, f, uv, n, name="plane")


def _arc(cx, cz, radius, a0, a1, count, outward=True):
    """Profile arc about (cx, cz) from angle a0 to a1 (radians, measured from +r toward +z)."""
    a = np.linspace(a0, a1, count)
    d = np.stack([np.cos(a), np.sin(a)], 1)
    pts = np.array([cx, cz]) + radius * d
    pts[np.abs(pts[:, 0]) < 1e-12, 0] = 0.0
    return pts, (d if outward else -d)


def _line(p0, p1, count):
    t = np.linspace(0.0, 1.0, count)[:, None]
    return (1 - t) * np.asarray(p0, float) + t * np.asarray(p1, float)


def nonconvex(segments: int = 96, detail: int = 24, gutter: float = 0.02) -> Mesh:
    """A sphere resting in a thick bowl standing on a round base plate: strong concavities,
    self-shadowing (the bowl shades its own inside and the sphere; both shade the plate) and
    inter-object occlusion, as one closed-by-parts mesh with one injective UV layout.

    Geometry (z up, units arbitrary, about 2.4 wide and 0.9 tall):
    plate: disk of radius 1.2, thickness 0.05, top at z = 0;
    bowl: hemispherical shell, outer radius 0.6, inner 0.5, opening up, centre at z = 0.602
    (its bottom floats 0.002 above the plate);
    sphere: radius 0.35 resting 0.005 above the bowl's inner bottom.

    UV layout: each of the 7 smooth pieces (plate bottom/side/top, bowl outside/rim/inside,
    sphere) is a rectangle spanning u ∈ [0, 1] around the axis, stacked in v with heights
    proportional to the piece's profile length and ``gutter`` between charts, so no texel is
    shared by two surface points (for maps ≥ 1/gutter texels high; 0.02 → 50, bilinear needs
    about twice that). Creases between pieces have separate vertices and sharp normals.

    Args:
        segments: quads around the axis. detail: profile points per unit of profile length × 10
            (about 24 → a smooth shell).
    """
    _check_count(segments=segments, detail=detail, minimum=3)
    if not (0.0 <= gutter < 0.1):
        raise ValueError(f"nonconvex: gutter must lie in [0, 0.1), got {gutter}")
    n_of = lambda length: max(2, int(math.ceil(length * detail * 10 / 2.4)) + 1)
    pieces, normals = [], []
    # plate: rectangle r in [0, 1.2], z in [-0.05, 0], counter-clockwise (solid on the left)
    for p0, p1, n in (([0.0, -0.05], [1.2, -0.05], [0, -1]), ([1.2, -0.05], [1.2, 0.0], [1, 0]),
                      ([1.2, 0.0], [0.0, 0.0], [0, 1])):
        pts = _line(p0, p1, n_of(np.linalg.norm(np.subtract(p1, p0))))
        pieces.append(pts)
        normals.append(np.tile(np.asarray(n, float), (len(pts), 1)))
    zc, ro, ri = 0.602, 0.6, 0.5
    # bowl outside: from the bottom pole to the rim (angle -90° → 0°), normals outward
    pts, n = _arc(0.0, zc, ro, -0.5 * math.pi, 0.0, n_of(0.5 * math.pi * ro))
    pieces.append(pts)
    normals.append(n)
    pts = _line([ro, zc], [ri, zc], n_of(ro - ri))
    pieces.append(pts)
    normals.append(np.tile([0.0, 1.0], (len(pts), 1)))
    # bowl inside: from the rim down to the inner bottom (0° → -90°), normals toward the centre
    pts, n = _arc(0.0, zc, ri, 0.0, -0.5 * math.pi, n_of(0.5 * math.pi * ri), outward=False)
    pieces.append(pts)
    normals.append(n)
    rs = 0.35
    zs = zc - ri + rs + 0.005
    pts, n = _arc(0.0, zs, rs, -0.5 * math.pi, 0.5 * math.pi, n_of(math.pi * rs))
    pieces.append(pts)
    normals.append(n)
    lengths = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in pieces])
    lengths = np.maximum(lengths, 0.1 * lengths.max())  # thin pieces still get usable texels
    avail = 1.0 - gutter * (len(pieces) + 1)
    heights = avail * lengths / lengths.sum()
    charts, v0 = [], gutter
    for h in heights:
        charts.append((gutter, v0, 1.0 - gutter, v0 + h))
        v0 += h + gutter
    v, f, uv, nn = revolve(pieces, segments, charts, normals)
    return Mesh.from_arrays(v, f, uv, nn, name="nonconvex")
