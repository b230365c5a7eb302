"""Lights: incident light, dict I/O and errors, shadow rays against a brute-force Möller-Trumbore."""

import math

import pytest
import torch

from renderer.camera import look_at
from renderer.gbuffer import render_gbuffer
from renderer.lights import (
    SHADOW_EPS,
    DirectionalLight,
    HemisphereLight,
    LightError,
    PointLight,
    SHLight,
    light_from_dict,
    light_to_dict,
    visibility,
)
from renderer.mesh import nonconvex


def test_point_light_inverse_square():
    L = PointLight((1.0, 2.0, 3.0), (4.0, 8.0, 12.0))
    p = torch.tensor([[1.0, 2.0, 1.0], [4.0, 6.0, 3.0]])
    l, E, d = L.incident(p)
    assert torch.allclose(d[:, 0], torch.tensor([2.0, 5.0]))
    assert torch.allclose(l, torch.tensor([[0.0, 0.0, 1.0], [-0.6, -0.8, 0.0]]))
    assert torch.allclose(E, torch.tensor([[1.0, 2.0, 3.0], [4 / 25, 8 / 25, 12 / 25]]))
    assert torch.equal(PointLight((0, 0, 0), 2.0).intensity, torch.tensor([2.0, 2.0, 2.0]))


def test_directional_light():
    L = DirectionalLight((0.0, 3.0, 4.0), (1.0, 0.5, 0.25))
    assert torch.allclose(L.direction, torch.tensor([0.0, 0.6, 0.8]))
    l, E, d = L.incident(torch.zeros(5, 3, dtype=torch.float64))
    assert l.dtype == torch.float64 and torch.allclose(l[3], torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64))
    assert torch.allclose(E[4], torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)) and torch.isinf(d).all()


def test_dict_round_trip_and_errors():
    hemi = HemisphereLight(torch.tensor([1.0, 1.0, 1.0]), torch.tensor([0.2, 0.1, 0.0]), torch.tensor([0.0, 0.0, 1.0]))
    lights = [PointLight((1, 2, 3), (1, 2, 3)), DirectionalLight((0, 0, 1), 2.0), hemi,
              SHLight(torch.arange(27, dtype=torch.float32).reshape(9, 3))]
    for light in lights:
        back = light_from_dict(light_to_dict(light))
        assert type(back) is type(light) and light_to_dict(back) == light_to_dict(light)
    with pytest.raises(LightError, match="unknown light type 'spot'.*point, directional, hemisphere, sh"):
        light_from_dict({"type": "spot", "position": [0, 0, 0]})
    with pytest.raises(LightError, match="intensity must be non-negative"):
        light_from_dict({"type": "point", "position": [0, 0, 0], "intensity": [1, -1, 1]})
    with pytest.raises(LightError, match="irradiance"):
        light_from_dict({"type": "directional", "direction": [0, 0, 1], "irradiance": -1.0})
    with pytest.raises(LightError, match="missing field 'position'"):
        light_from_dict({"type": "point", "intensity": 1.0})
    with pytest.raises(LightError, match="non-zero"):
        DirectionalLight((0, 0, 0), 1.0)
    with pytest.raises(LightError, match="NaN"):
        PointLight((0, 0, math.nan), 1.0)
    with pytest.raises(LightError, match="coeffs"):
        light_from_dict({"type": "sh", "coeffs": [[0, 0, 0]] * 4})


def _brute_force_occluded(mesh, origins, dirs, max_t):
    """Möller-Trumbore of every ray against every triangle in float64 torch: any hit with 0 < t < max_t."""
    tri = torch.as_tensor(mesh.tm.vertices[mesh.tm.faces])  # [F,3,3]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    occluded = torch.zeros(len(origins), dtype=torch.bool)
    for s in range(0, len(origins), 64):  # chunks bound the [64, F, 3] temporaries
        o, d = origins[s:s + 64, None], dirs[s:s + 64, None]
        p = torch.linalg.cross(d.expand(-1, len(tri), 3), e2.expand(len(o), -1, 3), dim=-1)
        det = (e1 * p).sum(-1)
        inv = 1.0 / torch.where(det.abs() > 1e-14, det, torch.ones_like(det))
        tv = o - v0
        u = (tv * p).sum(-1) * inv
        q = torch.linalg.cross(tv, e1.expand_as(tv), dim=-1)
        v = (d * q).sum(-1) * inv
        t = (e2 * q).sum(-1) * inv
        hit = (det.abs() > 1e-14) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < max_t[s:s + 64, None])
        occluded[s:s + 64] = hit.any(-1)
    return occluded


@pytest.mark.parametrize("light", [PointLight((0.9, -0.6, 1.4), 5.0), DirectionalLight((-1.0, 0.7, 0.8), 1.0)])
def test_shadow_rays_match_brute_force(light):
    m = nonconvex(segments=24, detail=6)
    g = render_gbuffer(m, look_at((2.0, -2.5, 2.2), (0.0, 0.0, 0.3), fov_y_deg=45, width=40, height=32))
    l, _, dist = light.incident(g.position.double())
    ok = ((g.geo_normal.double() * l).sum(-1) > 0)  # lit side only
    pts, ng, l, dist = g.position.double()[ok], g.geo_normal.double()[ok], l[ok], dist[ok, 0]
    pts, ng, l, dist = pts[:400], ng[:400], l[:400], dist[:400]
    V = visibility(m, pts.float(), ng.float(), light)
    origins = pts + SHADOW_EPS * m.scale * ng
    ref = _brute_force_occluded(m, origins, l, dist - SHADOW_EPS * m.scale)
    assert 20 < ref.sum() < len(ref) - 20, "the scene must have both shadowed and lit samples"
    mismatch = (V == 0) != ref
    assert mismatch.sum() <= 1, f"{mismatch.sum()} of {len(ref)} samples disagree"


def test_point_light_occluder_beyond_the_light_does_not_shadow():
    """Plate points at x ≈ −1 with a light at x = −0.8 just above: the bowl (outer radius 0.6) lies on the
    same line *beyond* the light. A point light is visible, a directional light along that line is not."""
    m = nonconvex(segments=48, detail=8)
    pts = torch.tensor([[-1.0, 0.0, 0.0], [-1.1, 0.02, 0.0], [-0.95, -0.02, 0.0]])
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    light_pos = torch.tensor([-0.8, 0.0, 0.1])
    V = visibility(m, pts, up, PointLight(light_pos, 1.0))
    assert torch.equal(V, torch.ones(3))
    direction = torch.nn.functional.normalize(light_pos - pts[0], dim=0)
    D = visibility(m, pts[:1], up[:1], DirectionalLight(direction, 1.0))
    assert torch.equal(D, torch.zeros(1))
    # moving the light past the bowl puts the bowl between: occluded
    assert torch.equal(visibility(m, pts[:1], up[:1], PointLight(pts[0] + 3.0 * direction, 1.0)), torch.zeros(1))
    with pytest.raises(LightError, match="environment"):
        visibility(m, pts, up, SHLight(torch.zeros(9, 3)))
