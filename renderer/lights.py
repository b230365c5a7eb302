"""Lights and shadow rays.

Radiometry (DESIGN.md): a light delivers irradiance E measured *perpendicular to its direction*;
the radiance reflected toward v is ``E · V · f_r(l, v) · (n·l)⁺`` (V: visibility).

- :class:`PointLight`: isotropic point source of radiant intensity I (RGB, W/sr);
  E = I / d² at distance d (inverse-square law).
- :class:`DirectionalLight`: distant source; ``direction`` points *toward* the light, E as given.
- :class:`HemisphereLight`, :class:`SHLight` (re-exported from :mod:`materials.environment`):
  environment lights; each model defines its own response (``Model.environment``); they are not
  shadowed.

:func:`visibility` casts shadow rays with embree (via trimesh).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from materials.environment import Environment, HemisphereLight, SHLight

from .mesh import Mesh

__all__ = [
    "PointLight", "DirectionalLight", "HemisphereLight", "SHLight", "Environment", "LightError",
    "light_from_dict", "light_to_dict", "visibility", "LIGHT_TYPES", "SHADOW_EPS",
]

#: Shadow-ray origin offset along the geometric normal, relative to the mesh's bounding-box diagonal.
SHADOW_EPS = 1e-4

LIGHT_TYPES = ("point", "directional", "hemisphere", "sh")


class LightError(ValueError):
    """A light that cannot be used (unknown type, negative intensity, bad shape, missing field)."""


def _rgb(x, name: str, where: str, nonneg: bool = True) -> Tensor:
    try:
        t = torch.as_tensor(x, dtype=torch.get_default_dtype())
    except (TypeError, ValueError, RuntimeError) as exc:
        raise LightError(f"{where}: {name} must be numeric, got {x!r} ({exc})") from None
    if t.dim() == 0:
        t = t.expand(3).clone()
    if t.shape != (3,):
        raise LightError(f"{where}: {name} must be a scalar or an RGB triple, got shape {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise LightError(f"{where}: {name} contains NaN or inf")
    if nonneg and (t < 0).any():
        raise LightError(f"{where}: {name} must be non-negative, got {t.tolist()}")
    return t


def _vec(x, name: str, where: str, unit: bool = False) -> Tensor:
    t = _rgb(x, name, where, nonneg=False)
    if unit:
        norm = t.norm()
        if norm < 1e-12:
            raise LightError(f"{where}: {name} must be a non-zero vector, got {t.tolist()}")
        t = t / norm
    return t


def _check_points(points: Tensor, where: str) -> None:
    if not isinstance(points, Tensor) or points.dim() != 2 or points.shape[1] != 3:
        raise LightError(f"{where}: points must be a tensor [N, 3], got {getattr(points, 'shape', type(points))}")


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light.

    Attributes:
        position: ``[3]`` world position (world units).
        intensity: ``[3]`` RGB radiant intensity I ≥ 0 in W/sr (a scalar is broadcast to RGB).
    """

    position: Tensor
    intensity: Tensor

    def __post_init__(self):
        object.__setattr__(self, "position", _vec(self.position, "position", "PointLight"))
        object.__setattr__(self, "intensity", _rgb(self.intensity, "intensity", "PointLight"))

    def incident(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Light arriving at ``points [N, 3]``.

        Returns:
            l ``[N, 3]`` unit direction toward the light, E ``[N, 3]`` = I/d² irradiance (W/m² for
            metres), distance d ``[N, 1]``. A point at the light itself (d < 1e-12) gets l = +z and a
            finite E = I/1e-24 (never evaluated in practice).
        """
        _check_points(points, "PointLight.incident")
        delta = self.position.to(points) - points
        d2 = (delta * delta).sum(-1, keepdim=True).clamp_min(1e-24)
        d = d2.sqrt()
        l = delta / d
        l = torch.where(d > 1e-12, l, torch.tensor([0.0, 0.0, 1.0], dtype=points.dtype, device=points.device))
        return l, self.intensity.to(points) / d2, d


@dataclass(frozen=True)
class DirectionalLight:
    """Distant light.

    Attributes:
        direction: ``[3]`` unit vector *toward* the light (normalised on construction).
        irradiance: ``[3]`` RGB irradiance E ≥ 0 on a surface perpendicular to ``direction``.
    """

    direction: Tensor
    irradiance: Tensor

    def __post_init__(self):
        object.__setattr__(self, "direction", _vec(self.direction, "direction", "DirectionalLight", unit=True))
        object.__setattr__(self, "irradiance", _rgb(self.irradiance, "irradiance", "DirectionalLight"))

    def incident(self, points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(l [N, 3], E [N, 3], distance [N, 1] = inf)`` at ``points [N, 3]``."""
        _check_points(points, "DirectionalLight.incident")
        n = points.shape[0]
        l = self.direction.to(points).expand(n, 3)
        e = self.irradiance.to(points).expand(n, 3)
        return l, e, torch.full((n, 1), math.inf, dtype=points.dtype, device=points.device)


Light = PointLight | DirectionalLight | HemisphereLight | SHLight


def light_to_dict(light) -> dict:
    """JSON-ready dict with a ``type`` of :data:`LIGHT_TYPES` (inverse of :func:`light_from_dict`)."""
    if isinstance(light, PointLight):
        return {"type": "point", "position": light.position.tolist(), "intensity": light.intensity.tolist()}
    if isinstance(light, DirectionalLight):
        return {"type": "directional", "direction": light.direction.tolist(), "irradiance": light.irradiance.tolist()}
    if isinstance(light, HemisphereLight):
        return {"type": "hemisphere", "upper": light.upper.tolist(), "lower": light.lower.tolist(),
                "up": light.up.tolist()}
    if isinstance(light, SHLight):
        return {"type": "sh", "coeffs": light.coeffs.tolist()}
    raise LightError(f"light_to_dict: unknown light object {type(light).__name__}; expected one of {LIGHT_TYPES}")


def light_from_dict(d: dict):
    """Build a light from a dict such as ``{"type": "point", "position": [x, y, z], "intensity": [r, g, b]}``.

    Fields per type: point (position, intensity W/sr), directional (direction toward the light,
    irradiance), hemisphere (upper, lower irradiances, optional up = +z), sh (coeffs ``[9][3]``).
    Intensities may be scalars (grey).

    Raises:
        LightError: unknown type (lists the known ones), missing field, wrong shape, negative or
            non-finite intensity.
    """
    if not isinstance(d, dict):
        raise LightError(f"a light must be a JSON object, got {type(d).__name__}")
    kind = d.get("type")
    if kind not in LIGHT_TYPES:
        raise LightError(f"unknown light type {kind!r}; known types: {', '.join(LIGHT_TYPES)}")
    required = {"point": ("position", "intensity"), "directional": ("direction", "irradiance"),
                "hemisphere": ("upper", "lower"), "sh": ("coeffs",)}[kind]
    for key in required:
        if key not in d:
            raise LightError(f"{kind} light is missing field '{key}' (needs {', '.join(required)})")
    if kind == "point":
        return PointLight(d["position"], d["intensity"])
    if kind == "directional":
        return DirectionalLight(d["direction"], d["irradiance"])
    where = f"{kind} light"
    if kind == "hemisphere":
        up = _vec(d.get("up", (0.0, 0.0, 1.0)), "up", where, unit=True)
        return HemisphereLight(_rgb(d["upper"], "upper", where), _rgb(d["lower"], "lower", where), up)
    coeffs = torch.as_tensor(d["coeffs"], dtype=torch.get_default_dtype())
    if coeffs.shape != (9, 3) or not torch.isfinite(coeffs).all():
        raise LightError(f"{where}: coeffs must be 9 finite RGB triples ([9][3]), got shape {tuple(coeffs.shape)}")
    return SHLight(coeffs)


def visibility(mesh: Mesh, points: Tensor, normals: Tensor, light, eps: float = SHADOW_EPS) -> Tensor:
    """Shadow-ray visibility ``[N]`` (1 = the light reaches the point, 0 = occluded).

    Each ray starts at ``p + ε·s·n_g`` with n_g the *geometric* normal, s = sign(n_g·l) (the side
    the light is on) and ε = ``eps`` × the mesh's bounding-box diagonal, and goes toward the light.
    Directional lights: any hit occludes. Point lights: only the first hit closer than the light
    (distance − ε) occludes. Points are not tested for facing the light; callers mask n·l ≤ 0.

    Args:
        mesh: the occluding mesh.
        points: ``[N, 3]`` world positions on the surface.
        normals: ``[N, 3]`` unit geometric normals (``GBuffer.geo_normal``).
        light: a :class:`PointLight` or :class:`DirectionalLight`.
        eps: relative offset (default :data:`SHADOW_EPS`).

    Returns:
        ``[N]`` float tensor of 0/1 in the dtype and on the device of ``points``.
    """
    _check_points(points, "visibility")
    if not isinstance(normals, Tensor) or normals.shape != points.shape:
        raise LightError(f"visibility: normals must match points {tuple(points.shape)}, got "
                         f"{getattr(normals, 'shape', type(normals))}")
    if isinstance(light, Environment):
        raise LightError("visibility: environment lights are not shadowed (no single direction); "
                         "use point or directional lights")
    if not isinstance(light, (PointLight, DirectionalLight)):
        raise LightError(f"visibility: unknown light {type(light).__name__}")
    n = points.shape[0]
    if n == 0:
        return points.new_zeros(0)
    p = points.detach().cpu().double()
    l, _, dist = light.incident(p)
    ng = normals.detach().cpu().double()
    side = torch.where((ng * l).sum(-1, keepdim=True) >= 0, 1.0, -1.0)
    offset = eps * mesh.scale
    origins = (p + offset * side * ng).numpy()
    dirs = l.numpy()
    hit_face = mesh.intersector.intersects_first(ray_origins=origins, ray_directions=dirs)
    occluded = hit_face >= 0
    if isinstance(light, PointLight) and occluded.any():
        from .gbuffer import intersect_faces

        idx = np.nonzero(occluded)[0]
        t, _, _ = intersect_faces(mesh, origins[idx], dirs[idx], hit_face[idx])
        occluded[idx] = t < dist[idx, 0].numpy() - offset
    return torch.from_numpy(~occluded).to(dtype=points.dtype, device=points.device)
