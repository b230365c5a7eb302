"""Ray-cast G-buffers: geometry against projection, analytic sphere, supersampling, empty views."""

import math

import numpy as np
import pytest
import torch

from renderer.camera import look_at
from renderer.gbuffer import intersect, render_gbuffer
from renderer.mesh import nonconvex, plane, uv_sphere


def test_projected_vertices_are_hit_positions():
    """Cast rays through the projections of visible vertices: the hits are those vertices."""
    m = nonconvex(segments=32, detail=8)
    cam = look_at((2.5, -2.0, 2.0), (0.0, 0.0, 0.3), fov_y_deg=45, width=200, height=160)
    V = m.vertices.double()
    pix, depth = cam.project(V.float())
    inside = (depth > 0) & (pix[:, 0] > 0) & (pix[:, 0] < 199) & (pix[:, 1] > 0) & (pix[:, 1] < 159)
    idx = torch.nonzero(inside).squeeze(-1)
    c = cam.center.double().numpy()
    d = V[idx].numpy() - c
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    hit = intersect(m, c[None], d)
    first = np.full(len(idx), np.inf)
    first[hit["ray"]] = hit["t"]
    # a vertex is visible when the first hit along its ray is the vertex itself
    visible = np.abs(first - dist) < 1e-6 * m.scale
    assert visible.sum() > 200 and (~visible).sum() > 200  # both visible and hidden vertices (self-occlusion)
    pos = np.full((len(idx), 3), np.nan)
    pos[hit["ray"]] = hit["position"]
    assert np.abs(pos[visible] - V[idx][visible].numpy()).max() < 1e-6
    # hidden vertices are behind something: the first hit is strictly closer. A ray aimed exactly at a
    # vertex on the silhouette may slip past the (float32, not watertight) embree triangles: allow a few
    # (a miss, or a hit beyond the vertex); those are silhouette vertices, a few percent
    slipped = first > dist + 1e-6 * m.scale
    assert slipped.mean() < 0.03
    assert (first[~visible & ~slipped] < dist[~visible & ~slipped]).all()


def test_gbuffer_positions_project_to_their_pixels():
    m = nonconvex(segments=32, detail=8)
    cam = look_at((0.0, -3.0, 2.0), (0.0, 0.0, 0.3), fov_y_deg=40, width=64, height=48)
    g = render_gbuffer(m, cam)
    pix, depth = cam.project(g.position)
    x, y = (g.pixel % 64).float(), (g.pixel // 64).float()
    assert (pix[:, 0] - x).abs().max() < 1e-3 and (pix[:, 1] - y).abs().max() < 1e-3
    assert torch.allclose(g.depth, (g.position - cam.center).norm(dim=-1), rtol=1e-5)
    assert torch.allclose(g.view, torch.nn.functional.normalize(cam.center - g.position, dim=-1), atol=1e-4)
    assert torch.allclose(g.normal.norm(dim=-1), torch.ones(len(g)), atol=1e-5)
    assert ((g.geo_normal * g.view).sum(-1) >= 0).all()
    assert not g.backface.any()  # a closed, outward mesh seen from outside
    assert g.uv.min() >= 0 and g.uv.max() <= 1


def test_sphere_against_analytic_intersection():
    r = 1.0
    m = uv_sphere(r, segments=128, rings=64)
    cam = look_at((0.3, -4.0, 1.0), (0.0, 0.0, 0.0), fov_y_deg=35, width=48, height=48)
    g = render_gbuffer(m, cam)
    o, d = cam.rays(1, dtype=torch.float64)
    # analytic ray/sphere: |o + t d|² = r²
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - r * r)
    hit = disc > 0
    # coverage agrees with the analytic disc except at the rim (polygonal silhouette)
    assert abs(hit.sum().item() - len(g)) <= 0.03 * hit.sum().item()
    t = -b[g.pixel] - torch.sqrt(disc[g.pixel].clamp_min(0))
    p = o[g.pixel] + t[:, None] * d[g.pixel]
    inner = disc[g.pixel] > 0.05  # away from the silhouette
    err = (g.position.double() - p).norm(dim=-1)[inner]
    chord = r * (1 - math.cos(math.pi / 64))  # max distance between a sphere and its tessellation ≈ 1.2e-3
    assert err.max() < 2 * chord
    ang = (g.normal.double()[inner] * (p[inner] / r)).sum(-1)
    assert ang.min() > math.cos(math.radians(0.5))
    # uv: u = longitude / 2π, v = (latitude + 90°)/180°
    lon = torch.atan2(p[inner, 1], p[inner, 0]) % (2 * math.pi)
    lat = torch.asin((p[inner, 2] / r).clamp(-1, 1))
    du = (g.uv.double()[inner, 0] - lon / (2 * math.pi) + 0.5) % 1.0 - 0.5
    assert du.abs().max() < 2e-3
    assert (g.uv.double()[inner, 1] - (lat / math.pi + 0.5)).abs().max() < 2e-3


def test_supersampling_and_to_image():
    m = uv_sphere(1.0, 32, 16)
    cam = look_at((0.0, -4.0, 0.0), fov_y_deg=40, width=32, height=32)
    g1, g3 = render_gbuffer(m, cam, 1), render_gbuffer(m, cam, 3)
    assert torch.allclose(g3.weight, torch.full((len(g3),), 1 / 9))
    assert g3.supersample == 3
    assert abs(g1.coverage - g3.coverage) < 0.02 and 0.1 < g3.coverage < 0.5
    w = g3.pixel_weight()
    assert torch.allclose(g3.to_image(torch.ones(len(g3))), w)
    assert w.max() <= 1 + 1e-6 and ((w > 0) & (w < 1)).any()  # fractional edge pixels
    img = g3.to_image(torch.ones(len(g3), 3), background=torch.tensor([0.0, 0.5, 1.0]))
    # background fills the uncovered fraction of each pixel
    assert torch.allclose(img[..., 2], torch.ones(32, 32)) and torch.allclose(img[..., 1], 0.5 + 0.5 * w)
    with pytest.raises(ValueError, match="samples"):
        g3.to_image(torch.ones(len(g3) + 1, 3))


def test_empty_view_and_backfaces():
    m = plane(2.0)
    away = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 6.0), up=(0.0, 1.0, 0.0), width=16, height=16)
    g = render_gbuffer(m, away)
    assert len(g) == 0 and g.coverage == 0.0 and g.position.shape == (0, 3)
    assert torch.equal(g.to_image(torch.zeros(0, 3)), torch.zeros(16, 16, 3))
    below = look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=16, height=16)
    g = render_gbuffer(m, below)
    assert len(g) > 0 and g.backface.all()
    assert torch.allclose(g.geo_normal, torch.tensor([0.0, 0.0, -1.0]).expand(len(g), 3))
    assert torch.allclose(g.normal, torch.tensor([0.0, 0.0, -1.0]).expand(len(g), 3))
    with pytest.raises(TypeError, match="Camera"):
        render_gbuffer(m, "camera")


def test_footprint_rays_are_the_supersampling_strata():
    """render_footprint with k × k per pixel casts exactly render_gbuffer(k)'s rays for those pixels, and k = 1
    is the pixel centre; mixed counts give each pixel weights 1/k² summing to its covered fraction."""
    from renderer.gbuffer import render_footprint

    m = uv_sphere(segments=32, rings=16)
    cam = look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0), fov_y_deg=40, width=40, height=30)
    pixels = torch.tensor([15 * 40 + 20, 14 * 40 + 19, 3, 15 * 40 + 21])   # two inside, a corner miss, one inside
    for k in (1, 3):
        g = render_footprint(m, cam, pixels, torch.full((4,), k))
        ref = render_gbuffer(m, cam, k, pixels=pixels)
        assert torch.equal(g.pixel, ref.pixel) and torch.allclose(g.uv, ref.uv) and torch.allclose(g.weight, ref.weight)
    g = render_footprint(m, cam, pixels, torch.tensor([1, 2, 4, 3]))
    cover = torch.zeros(40 * 30, dtype=torch.float64).index_add(0, g.pixel, g.weight.double())
    assert cover[pixels[[0, 1, 3]]].tolist() == pytest.approx([1.0, 1.0, 1.0])
    assert cover[3] == 0.0 and len(g) == 1 + 4 + 9


def test_jittered_samples_stay_in_their_strata_and_differ_from_the_centres():
    cam = look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=6, height=5)
    k = 4
    centres = cam.pixel_grid(k, torch.float64)
    jit = cam.jittered_grid(k, torch.Generator().manual_seed(1), torch.float64)
    d = (jit - centres).abs()
    assert float(d.max()) <= 0.5 / k + 1e-12        # inside the stratum of side 1/k around its centre
    assert float(d.mean()) > 0.25 * 0.5 / k          # uniform in the stratum: mean |offset| = 1/(4k) per axis
    again = cam.jittered_grid(k, torch.Generator().manual_seed(1), torch.float64)
    assert torch.equal(jit, again)


def test_gaussian_pixel_filter_is_the_box_convolved_with_the_gaussian():
    """pixel_filter's closed form (erf) against the convolution of the unit box with a Gaussian integrated
    numerically (trapezoid, 20 001 points), and the 2-D weights of render_footprint with a PSF: they sum to 1 per
    pixel, are centred on the pixel, and their variance per axis is the box's 1/12 plus σ² (variances add under
    convolution; 3σ truncation and the k-point quadrature keep it within 2 %)."""
    from renderer.gbuffer import footprint_extent, pixel_filter, render_footprint

    sigma = 0.6
    x = torch.linspace(-2.5, 2.5, 21, dtype=torch.float64)
    t = np.linspace(-0.5, 0.5, 20001)
    ref = [np.trapezoid(np.exp(-0.5 * ((xi - t) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi)), t)
           for xi in x.tolist()]
    assert pixel_filter(x, sigma).tolist() == pytest.approx(ref, abs=1e-8)
    assert pixel_filter(torch.tensor([0.0, 0.49, 0.51]), 0.0).tolist() == [1.0, 1.0, 0.0]
    assert footprint_extent(sigma) == pytest.approx(1 + 6 * sigma)
    with pytest.raises(ValueError, match="psf_sigma"):
        footprint_extent(-0.1)

    m = plane(size=4.0)
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_y_deg=30, width=20, height=20)
    pixels = torch.tensor([10 * 20 + 10])
    g = render_footprint(m, cam, pixels, torch.tensor([16]), psf_sigma=sigma)
    assert len(g) == 256 and float(g.weight.double().sum()) == pytest.approx(1.0, abs=1e-6)
    xy, _ = cam.project(g.position.double())
    off = xy - torch.tensor([10.0, 10.0], dtype=torch.float64)
    w = g.weight.double()[:, None]
    assert (w * off).sum(0).abs().max() < 1e-6
    assert ((w * off ** 2).sum(0) / (1 / 12 + sigma ** 2)).tolist() == pytest.approx([1.0, 1.0], abs=0.02)


def test_face_uv_is_the_cast_rays_uv_inside_the_face_and_its_plane_beyond():
    """Rays through offsets of up to half a pixel from the hits of a sphere: where a cast ray hits the same face,
    face_uv gives its UV exactly (float64, 1e-9); where it hits a neighbour, the plane's continuation differs by the
    surface's bend only — far less than the offset's UV step; a ray off the plane's side is flagged."""
    from renderer.gbuffer import face_uv

    mesh = uv_sphere()
    cam = look_at((0.0, -3.0, 1.0), (0.0, 0.0, 0.0), fov_y_deg=40, width=48, height=48)
    g = render_gbuffer(mesh, cam, 1)
    xy, _ = cam.project(g.position.double())
    uv0, ok0 = face_uv(mesh, cam, g.face, xy)
    assert ok0.all() and float((uv0 - g.uv.double()).abs().max()) < 1e-6          # the hit itself (float32 uv)
    gen = torch.Generator().manual_seed(0)
    off = torch.rand(len(g), 2, generator=gen, dtype=torch.float64) - 0.5
    uv, ok = face_uv(mesh, cam, g.face, xy + off)
    o, d = cam.rays_at(xy + off, dtype=torch.float64)
    hit = intersect(mesh, o[:1].numpy(), d.numpy())
    ray = torch.from_numpy(hit["ray"])
    cast_uv, cast_face = torch.from_numpy(hit["uv"]), torch.from_numpy(hit["face"])
    same = cast_face == g.face[ray]
    assert int(same.sum()) > len(g) // 2
    assert float((uv[ray][same] - cast_uv[same]).abs().max()) < 1e-9
    step = (uv[ray] - uv0[ray]).norm(dim=-1)
    seam = (cast_uv - uv0[ray]).norm(dim=-1) > 0.25                                # the sphere's u = 0/1 seam
    other = ~same & ~seam
    assert float(((uv[ray][other] - cast_uv[other]).norm(dim=-1)).median()) < 0.05 * float(step.median())
    with pytest.raises(ValueError, match="face must be"):
        face_uv(mesh, cam, g.face, xy[:3])


def test_face_planes_read_many_positions_per_face_as_face_uv_reads_each():
    """A face's plane made once and read at L positions per face (the texture sub-samples of a pixel, [N, L, 2])
    gives each position's face_uv, including the flag of rays that miss the plane's front (positions far outside
    the image, behind the horizon of a grazing face)."""
    from renderer.gbuffer import face_planes, face_uv

    mesh = uv_sphere()
    cam = look_at((0.0, -3.0, 1.0), (0.0, 0.0, 0.0), fov_y_deg=40, width=48, height=48)
    g = render_gbuffer(mesh, cam, 1)
    xy, _ = cam.project(g.position.double())
    gen = torch.Generator().manual_seed(1)
    L = 5
    sub = xy[:, None] + (torch.rand(len(g), L, 2, generator=gen, dtype=torch.float64) - 0.5) * 2.0
    sub[::7, 0] += 1e4                                           # far off: some of these rays miss the plane
    uv, ok = face_planes(mesh, cam, g.face).uv(sub)
    assert uv.shape == (len(g), L, 2) and ok.shape == (len(g), L)
    ref_uv, ref_ok = face_uv(mesh, cam, g.face.repeat_interleave(L), sub.reshape(-1, 2))
    assert torch.equal(ok.reshape(-1), ref_ok) and 0 < int((~ok).sum()) < ok.numel() // 7
    assert torch.allclose(uv.reshape(-1, 2), ref_uv, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="face must be"):
        face_planes(mesh, cam, g.face[:, None])
    with pytest.raises(ValueError, match="one row per face"):
        face_planes(mesh, cam, g.face).uv(sub[:-1])
