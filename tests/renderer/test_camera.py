"""OpenCV cameras: projection, rays, rigs, OpenGL/Blender/JSON round trips, validation."""

import json
import math

import pytest
import torch

from renderer.camera import Camera, CameraError, look_at, orbit, random_rig, turntable


@pytest.fixture
def cam():
    K = [[300.0, 0.5, 40.3], [0.0, 310.0, 29.1], [0.0, 0.0, 1.0]]
    c = look_at((3.0, 1.0, 2.0), (0.0, 0.2, 0.3), fov_y_deg=35, width=80, height=60)
    return Camera(K, c.R, c.t, 80, 60, dtype=torch.float64)


def test_look_at_frame():
    c = look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov_y_deg=60, width=101, height=81)
    assert torch.allclose(c.center, torch.tensor([0.0, -4.0, 0.0]), atol=1e-6)
    # the target projects to the principal point (the image centre (W-1)/2, (H-1)/2)
    pix, depth = c.project(torch.tensor([[0.0, 0.0, 0.0]]))
    assert torch.allclose(pix, torch.tensor([[50.0, 40.0]]), atol=1e-4) and abs(depth.item() - 4.0) < 1e-6
    # world +z (up) appears up in the image (smaller y), world +x to the right
    pix, _ = c.project(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    assert pix[0, 1] < 40 and abs(pix[0, 0] - 50) < 1e-4
    assert pix[1, 0] > 50 and abs(pix[1, 1] - 40) < 1e-4
    # focal from the field of view: f = (H/2)/tan(fov/2)
    assert math.isclose(c.K[1, 1].item(), 40.5 / math.tan(math.radians(30)), rel_tol=1e-6)
    assert math.isclose(c.fov_y_deg, 60.0, rel_tol=1e-6)


def test_project_matches_manual(cam):
    X = torch.randn(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.5
    xc = X @ cam.R.T + cam.t
    uvw = xc @ cam.K.T
    pix, depth = cam.project(X)
    assert torch.allclose(pix, uvw[:, :2] / uvw[:, 2:], atol=1e-9)
    assert torch.allclose(depth, xc[:, 2], atol=1e-12)


@pytest.mark.parametrize("k", [1, 3])
def test_rays_hit_their_pixels(cam, k):
    o, d = cam.rays(k)
    assert o.shape == d.shape == (80 * 60 * k * k, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(len(d), dtype=d.dtype), atol=1e-12)
    pix, depth = cam.project(o + 2.5 * d)
    assert (depth > 0).all()
    grid = cam.pixel_grid(k)
    # R came from a float32 look_at: orthonormal to ~1e-7 only, so Rᵀ ≠ R⁻¹ at that level
    assert torch.allclose(pix, grid, atol=1e-5)
    # sample s belongs to pixel s // k²: its position lies within half a pixel of that pixel's centre
    s = torch.arange(len(grid))
    p = s // (k * k)
    centre = torch.stack([p % 80, p // 80], -1).to(grid)
    assert (grid - centre).abs().max() < 0.5
    if k == 1:
        assert torch.equal(grid, centre)


def test_opengl_round_trip_and_ndc(cam):
    view, P = cam.to_opengl(near=0.1, far=50.0)
    back = Camera.from_opengl(view, P, width=80, height=60)
    for a, b in ((back.K, cam.K), (back.R, cam.R), (back.t, cam.t)):
        assert torch.allclose(a.double(), b, atol=1e-5)
    # a world point lands at the same pixel: NDC x = 2(u + ½)/W − 1, y = 1 − 2(v + ½)/H
    X = torch.tensor([[0.1, 0.2, 0.3], [-0.4, 0.5, 0.1]], dtype=torch.float64)
    clip = torch.cat([X, torch.ones(2, 1, dtype=X.dtype)], 1) @ (P @ view).T
    ndc = clip[:, :3] / clip[:, 3:]
    pix, depth = cam.project(X)
    assert torch.allclose(ndc[:, 0], 2 * (pix[:, 0] + 0.5) / 80 - 1, atol=1e-9)
    assert torch.allclose(ndc[:, 1], 1 - 2 * (pix[:, 1] + 0.5) / 60, atol=1e-9)
    assert (ndc[:, 2].abs() < 1).all()
    fov = Camera.from_opengl(view, width=80, height=60, fov_y_deg=40.0)
    assert math.isclose(fov.fov_y_deg, 40.0, rel_tol=1e-6)  # stored in float32


def test_blender_round_trip():
    c = look_at((2.0, -3.0, 1.5), (0.1, 0.0, 0.2), fov_y_deg=30, width=96, height=64)
    K = c.K.clone()
    K[0, 2] += 3.0
    K[1, 2] -= 2.0
    c = Camera(K, c.R, c.t, 96, 64, dtype=torch.float64)
    b = c.to_blender()
    json.dumps(b)
    M = torch.tensor(b["matrix_world"], dtype=torch.float64)
    # Blender's camera looks along its local −z; its +y is image up (= −OpenCV y)
    assert torch.allclose(-M[:3, 2], c.R[2], atol=1e-9)
    assert torch.allclose(M[:3, 1], -c.R[1], atol=1e-9)
    assert torch.allclose(M[:3, 3], c.center, atol=1e-9)
    back = Camera.from_blender(**b)
    for a, e in ((back.K, c.K), (back.R, c.R), (back.t, c.t)):
        assert torch.allclose(a.double(), e, atol=1e-5)


def test_dict_round_trip(cam):
    d = json.loads(json.dumps(cam.to_dict()))
    back = Camera.from_dict(d)
    assert torch.allclose(back.K.double(), cam.K, atol=1e-5) and back.width == 80 and back.height == 60
    with pytest.raises(CameraError, match="missing field 'R'"):
        Camera.from_dict({k: v for k, v in d.items() if k != "R"})


def test_validation():
    R, t = torch.eye(3), torch.zeros(3)
    with pytest.raises(CameraError, match="positive focal"):
        Camera([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]], R, t, 10, 10)
    with pytest.raises(CameraError, match="rotation"):
        Camera(torch.eye(3), R * 1.1, t, 10, 10)
    with pytest.raises(CameraError, match="rotation"):
        Camera(torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, -1.0])), t, 10, 10)
    with pytest.raises(CameraError, match="shape"):
        Camera(torch.eye(2), R, t, 10, 10)
    with pytest.raises(CameraError, match="width"):
        Camera(torch.eye(3), R, t, 0, 10)
    with pytest.raises(CameraError, match="parallel"):
        look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="supersample"):
        look_at((0.0, 3.0, 0.0)).rays(0)


def test_rigs():
    cams = orbit(6, 3.0, [10.0, 45.0], target=(0.0, 0.0, 0.5), width=32, height=32)
    assert len(cams) == 12
    for c in cams:
        assert math.isclose((c.center - torch.tensor([0.0, 0.0, 0.5])).norm().item(), 3.0, rel_tol=1e-6)
        pix, _ = c.project(torch.tensor([[0.0, 0.0, 0.5]]))
        assert torch.allclose(pix, torch.tensor([[15.5, 15.5]]), atol=1e-4)
    el = [math.degrees(math.asin((c.center[2].item() - 0.5) / 3.0)) for c in cams]
    assert all(abs(e - 10) < 1e-4 for e in el[:6]) and all(abs(e - 45) < 1e-4 for e in el[6:])
    a, b = random_rig(7, 5), random_rig(7, 5)
    assert all(torch.equal(x.R, y.R) and torch.equal(x.t, y.t) for x, y in zip(a, b, strict=True))
    assert not torch.equal(random_rig(8, 5)[0].t, a[0].t)


def test_turntable_keeps_studio_geometry():
    """On a turntable the light is fixed relative to the camera: in each view's camera frame the
    rotated studio light sits at the same place."""
    cams, rots = turntable(5, 3.0, 20.0)
    light = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    in_cam = [c.world_to_camera((Q @ light)[None].to(c.R.dtype)) for c, Q in zip(cams, rots, strict=True)]
    for x in in_cam[1:]:
        assert torch.allclose(x, in_cam[0], atol=1e-5)
    assert not torch.allclose(cams[1].center, cams[0].center)
