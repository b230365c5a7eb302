"""Shading: radiometry against closed forms, UV orientation, shadows, gradients, bad maps."""

import math

import pytest
import torch

import materials
from renderer.camera import look_at
from renderer.gbuffer import render_gbuffer
from renderer.lights import DirectionalLight, HemisphereLight, PointLight
from renderer.mesh import Mesh, plane, uv_sphere
from renderer.shading import ShadingError, prepare, render, shade

LAMBERT = materials.get("lambert")


def _const(value, H=2, W=2):
    return {"albedo": torch.tensor(value, dtype=torch.float32).expand(H, W, 3).clone()}


def test_lambert_sphere_point_light_closed_form():
    """L = ρ/π · I cosθ / d² at pixels, against the analytic sphere hit (independent of the mesh)."""
    rho, I = torch.tensor([0.8, 0.5, 0.2]), torch.tensor([10.0, 20.0, 30.0])
    light_pos = torch.tensor([1.5, -2.0, 2.5], dtype=torch.float64)
    m = uv_sphere(1.0, segments=256, rings=128)
    cam = look_at((0.5, -4.0, 1.0), (0.0, 0.0, 0.0), fov_y_deg=35, width=40, height=40)
    img = render(m, cam, PointLight(light_pos, I), LAMBERT, _const(rho.tolist()), sampling="nearest")
    o, d = cam.rays(1, dtype=torch.float64)
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 1.0)
    sel = torch.nonzero(disc > 0.1).squeeze(-1)  # pixels well inside the silhouette
    t = -b[sel] - disc[sel].sqrt()
    p = o[sel] + t[:, None] * d[sel]
    to_l = light_pos - p
    dist2 = (to_l * to_l).sum(-1)
    cos = ((p * to_l).sum(-1) / dist2.sqrt()).clamp_min(0)
    expect = rho.double() / math.pi * I.double() * (cos / dist2)[:, None]
    got = img.reshape(-1, 3)[sel].double()
    lit = cos > 0.05  # away from the terminator, where the tessellation decides
    assert lit.sum() > 200 and (~lit).sum() > 20
    assert torch.allclose(got[lit], expect[lit], rtol=4e-3, atol=1e-5)
    assert (got[cos == 0] == 0).all()


def test_tilted_plane_directional_light_closed_form():
    angle = math.radians(35.0)
    base = plane(2.0, subdivisions=3)
    Rx = torch.tensor([[1, 0, 0], [0, math.cos(angle), -math.sin(angle)], [0, math.sin(angle), math.cos(angle)]])
    tilted = Mesh.from_arrays(base.vertices @ Rx.T, base.faces, base.uvs, base.normals @ Rx.T)
    E = torch.tensor([2.0, 1.0, 0.5])
    light = DirectionalLight((0.3, -0.2, 1.0), E)
    cam = look_at((0.4, -3.0, 3.0), (0.0, 0.0, 0.0), fov_y_deg=40, width=32, height=32)
    img = render(tilted, cam, light, LAMBERT, _const([0.6, 0.6, 0.6]))
    n = Rx @ torch.tensor([0.0, 0.0, 1.0])
    expect = 0.6 / math.pi * E * (n @ light.direction)
    g = render_gbuffer(tilted, cam)
    inside = img.reshape(-1, 3)[g.pixel]
    assert len(g) > 300
    assert torch.allclose(inside, expect.expand_as(inside), rtol=1e-5)


def test_uv_orientation_on_plane_seen_head_on():
    """Top-left texel of the map (u≈0, v≈1) appears at the top-left of an image of the plane seen from +z with +y up."""
    albedo = torch.full((4, 4, 3), 0.1)
    albedo[0, 0] = torch.tensor([1.0, 0.0, 0.0])  # row 0 = top of the map
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_y_deg=30, width=64, height=64)
    img = render(plane(1.0), cam, DirectionalLight((0, 0, 1), math.pi), LAMBERT, {"albedo": albedo}, sampling="nearest")
    red = img[..., 0] > 0.5
    ys, xs = torch.nonzero(red, as_tuple=True)
    assert red.sum() > 10
    covered = img.sum(-1) > 0
    cy, cx = torch.nonzero(covered, as_tuple=True)
    # the red quarter-of-a-quarter sits in the top-left corner of the plane's footprint
    assert xs.max() < cx.min() + (cx.max() - cx.min()) / 4 + 1 and ys.max() < cy.min() + (cy.max() - cy.min()) / 4 + 1
    assert xs.min() == cx.min() and ys.min() == cy.min()
    assert torch.allclose(img[ys[0], xs[0]], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)  # ρ/π · π = ρ


def test_shadow_on_plane_under_sphere_and_drop():
    m_plane, m_sphere = plane(4.0), uv_sphere(0.5, 32, 16, center=(0.0, 0.0, 1.0))
    both = Mesh.from_arrays(torch.cat([m_plane.vertices, m_sphere.vertices]),
                            torch.cat([m_plane.faces, m_sphere.faces + len(m_plane.vertices)]),
                            torch.cat([m_plane.uvs * 0.5, m_sphere.uvs * 0.5 + 0.5]),
                            torch.cat([m_plane.normals, m_sphere.normals]))
    cam = look_at((0.0, -0.01, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_y_deg=40, width=48, height=48)
    light = DirectionalLight((0.0, 0.0, 1.0), 1.0)
    lit = render(both, cam, light, LAMBERT, _const([0.5] * 3), shadows=False)
    shadowed = render(both, cam, light, LAMBERT, _const([0.5] * 3), shadows=True)
    g = render_gbuffer(both, cam)
    on_plane = g.face < len(m_plane.faces)
    r = g.position[:, :2].norm(dim=-1)
    # seen from straight above, the sphere hides its own shadow disc; the plane around it is lit
    assert (shadowed.reshape(-1, 3)[g.pixel[on_plane & (r > 0.55)]] > 0).all()
    assert (shadowed <= lit + 1e-7).all()
    # no light below the plane: everything dark and every sample dropped
    prep = prepare(g, both, DirectionalLight((0.0, 0.0, -1.0), 1.0))
    assert len(prep.sample) == 0 and prep.lights == []
    assert torch.equal(shade(LAMBERT, _const([0.5] * 3), prep), torch.zeros(len(g), 3))


def test_shadow_visible_from_the_side():
    m_plane, m_sphere = plane(4.0), uv_sphere(0.5, 32, 16, center=(0.0, 0.0, 1.0))
    both = Mesh.from_arrays(torch.cat([m_plane.vertices, m_sphere.vertices]),
                            torch.cat([m_plane.faces, m_sphere.faces + len(m_plane.vertices)]),
                            torch.cat([m_plane.uvs * 0.5, m_sphere.uvs * 0.5 + 0.5]),
                            torch.cat([m_plane.normals, m_sphere.normals]))
    cam = look_at((0.0, -4.0, 3.0), (0.0, 0.0, 0.0), fov_y_deg=50, width=48, height=48)
    light = PointLight((1.0, 0.0, 3.0), 9.0)  # shadow centre on the plane: (−0.5, 0, 0)
    g = render_gbuffer(both, cam)
    rad = shade(LAMBERT, _const([0.5] * 3), prepare(g, both, light))
    on_plane = g.face < len(m_plane.faces)
    centre = torch.tensor([-0.5, 0.0])
    in_shadow = on_plane & ((g.position[:, :2] - centre).norm(dim=-1) < 0.3)
    out_shadow = on_plane & ((g.position[:, :2] - centre).norm(dim=-1) > 1.2)
    assert in_shadow.sum() > 5 and (rad[in_shadow] == 0).all()
    assert (rad[out_shadow] > 0).all()


def test_gradients_match_finite_differences_float64():
    model = materials.SumModel(LAMBERT, materials.get("microfacet"))
    m = plane(2.0, subdivisions=2)
    cam = look_at((0.3, -1.5, 2.5), (0.0, 0.0, 0.0), fov_y_deg=50, width=12, height=12)
    g = render_gbuffer(m, cam)
    prep = prepare(g, m, [PointLight((0.5, 0.5, 1.5), 3.0), DirectionalLight((-0.3, 0.2, 1.0), 1.0)])
    gen = torch.Generator().manual_seed(0)
    maps = {"albedo": torch.rand(3, 3, 3, generator=gen, dtype=torch.float64) * 0.8 + 0.1,
            "f0": torch.rand(3, 3, 3, generator=gen, dtype=torch.float64) * 0.5 + 0.02,
            "roughness": torch.rand(3, 3, 1, generator=gen, dtype=torch.float64) * 0.6 + 0.3}
    names = list(maps)

    def f(*xs):
        return g.to_image(shade(model, dict(zip(names, xs, strict=True)), prep).to(torch.float64))

    xs = tuple(maps[k].requires_grad_() for k in names)
    assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-6, rtol=1e-4)
    f(*xs).sum().backward()
    assert all(x.grad.abs().sum() > 0 for x in xs)


def test_hemisphere_environment_lambert():
    env = HemisphereLight(torch.tensor([1.0, 1.0, 1.0]), torch.tensor([0.2, 0.2, 0.2]), torch.tensor([0.0, 0.0, 1.0]))
    m = plane(2.0)
    cam = look_at((0.0, -2.0, 2.0), fov_y_deg=40, width=16, height=16)
    g = render_gbuffer(m, cam)
    rad = shade(LAMBERT, _const([0.5, 0.5, 0.5]), prepare(g, m, env))
    assert torch.allclose(rad, torch.full_like(rad, 0.5 / math.pi * 1.0))  # n = up: E = E_upper


def test_bad_maps():
    m = plane(2.0)
    cam = look_at((0.0, -2.0, 2.0), fov_y_deg=40, width=8, height=8)
    prep = prepare(render_gbuffer(m, cam), m, DirectionalLight((0, 0, 1), 1.0))
    with pytest.raises(ShadingError, match=r"missing \['albedo'\]"):
        shade(LAMBERT, {}, prep)
    with pytest.raises(ShadingError, match=r"unexpected \['roughness'\]"):
        shade(LAMBERT, {**_const([0.5] * 3), "roughness": torch.zeros(2, 2, 1)}, prep)
    with pytest.raises(ShadingError, match=r"\[H, W, 3\]"):
        shade(LAMBERT, {"albedo": torch.zeros(2, 2, 2)}, prep)
    with pytest.raises(ShadingError, match=r"\[H, W, 3\]"):
        shade(LAMBERT, {"albedo": torch.zeros(4, 3)}, prep)
    with pytest.raises(ShadingError, match="sampling"):
        shade(LAMBERT, _const([0.5] * 3), prep, sampling="cubic")


def test_radiance_jacobian_is_the_automatic_derivative_of_radiance_sum():
    # two groups of (sample, light) pairs, several pairs per row: the closed-form sum against autograd of
    # radiance_sum in float64, row by row and channel by channel
    from materials import Angles
    from renderer.shading import radiance_jacobian, radiance_sum

    model = materials.get("ggx-lambert")
    gen = torch.Generator().manual_seed(5)
    S = 60

    def unit(n):
        x = torch.randn(n, 3, generator=gen, dtype=torch.float64)
        return x / x.norm(dim=-1, keepdim=True)

    def group(m):       # (local, index, angles, irradiance); about a quarter of random triples face both ways
        local = torch.randint(S, (m,), generator=gen)
        irradiance = torch.rand(m, 3, generator=gen, dtype=torch.float64) * 3
        return local, local, Angles.from_vectors(unit(m), unit(m), unit(m)), irradiance

    lights = [group(90), group(70)]
    params = {"albedo": torch.rand(S, 3, generator=gen, dtype=torch.float64),
              "f0": torch.rand(S, 3, generator=gen, dtype=torch.float64),
              "roughness": torch.rand(S, 1, generator=gen, dtype=torch.float64) * 0.9 + 0.1}
    value, grads = radiance_jacobian(model, params, S, lights)
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    ref = radiance_sum(model, leaves, S, lights)
    torch.testing.assert_close(value, ref.detach(), rtol=1e-12, atol=1e-13)
    for k, x in leaves.items():
        J = torch.stack([torch.autograd.grad(ref[:, c].sum(), x, retain_graph=True)[0] for c in range(3)], 1)
        got = torch.diag_embed(grads[k]) if grads[k].dim() == 2 else grads[k]
        assert float(J.abs().max()) > 0
        torch.testing.assert_close(got, J, rtol=1e-10, atol=1e-12 * float(J.abs().max()), msg=k)
    # no closed form: a model without one, or an environment light among the terms
    assert radiance_jacobian(materials.get("schuler", variant="kelemen-szirmay-kalos"), params, S, lights) is None
    sky = HemisphereLight(torch.ones(3), torch.full((3,), 0.2), torch.tensor([0.0, 0.0, 1.0]))
    env = (sky, torch.arange(3), torch.arange(3), unit(3), unit(3))
    assert radiance_jacobian(model, params, S, lights, [env]) is None
    # a pair writing a row other than the one it reads has no place in a per-row Jacobian
    local, _, angles, irradiance = lights[0]
    with pytest.raises(ShadingError, match="local == index"):
        radiance_jacobian(model, params, S, [(local, (local + 1) % S, angles, irradiance)])


def test_a_model_without_parameters_sums_its_radiance_in_the_irradiance_type():
    """A measured BRDF fits no parameter: the radiance sum and its Jacobian take their dtype and device from the
    irradiance (they read them off the first parameter, and raised on none): the sum is E · f(l, v) cos θ_l pair by
    pair, in float64 when E is."""
    from materials.geometry import Angles
    from renderer.shading import radiance_jacobian, radiance_sum

    m = materials.get("measured")
    assert m.params == ()
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(4, 3)
    l = torch.nn.functional.normalize(torch.tensor([[0.2, 0.0, 1.0], [0.5, 0.1, 1.0], [0.0, 0.7, 1.0],
                                                    [0.9, 0.0, 0.4]], dtype=torch.float64), dim=-1)
    ang = Angles.from_vectors(n, l, n)
    idx = torch.arange(4)
    E = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64).expand(4, 3)
    out = radiance_sum(m, {}, 6, [(idx, idx, ang, E)])
    assert out.dtype == torch.float64 and out.shape == (6, 3)
    assert torch.allclose(out[:4], E * m.cosine_brdf(ang, {})) and bool((out[4:] == 0).all())
    assert bool((out[:4] > 0).all())
    jac = radiance_jacobian(m, {}, 6, [(idx, idx, ang, E)])
    assert jac is None or (torch.allclose(jac[0], out) and jac[1] == {})
