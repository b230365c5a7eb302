"""Mesh primitives, UV layouts (injective, unflipped), file round trips and bad input."""

import math

import numpy as np
import pytest
import torch
import trimesh

from renderer.mesh import Mesh, MeshError, load_mesh, nonconvex, plane, save_mesh, torus, uv_sphere


def _uv_signed_area(m: Mesh) -> torch.Tensor:
    t = m.uvs.double()[m.faces]
    a, b = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return 0.5 * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


@pytest.mark.parametrize("make", [uv_sphere, torus, plane, lambda: nonconvex(segments=32, detail=8)])
def test_primitive_consistency(make):
    m = make()
    assert m.vertices.dtype == torch.float32 and m.faces.dtype == torch.long
    assert torch.allclose(m.normals.norm(dim=-1), torch.ones(len(m.normals)), atol=1e-6)
    # winding agrees with the shading normals (outward), every face
    fn = m.face_normals()
    assert ((fn * m.normals[m.faces].mean(1)).sum(-1) > 0.5).all()
    # UVs in [0,1], no folded (mirrored) UV triangle, total UV area <= 1 (no overlap possible above 1)
    assert m.uvs.min() >= 0 and m.uvs.max() <= 1
    area = _uv_signed_area(m)
    assert (area > 0).all(), "every UV triangle keeps the orientation of its 3D face"
    assert area.sum() <= 1.0 + 1e-9


def test_sphere_and_torus_geometry():
    s = uv_sphere(radius=2.0, segments=32, rings=16, center=(1.0, 0.0, 0.0))
    r = (s.vertices - torch.tensor([1.0, 0.0, 0.0])).norm(dim=-1)
    assert torch.allclose(r, torch.full_like(r, 2.0), atol=1e-6)
    assert torch.allclose(s.normals, (s.vertices - torch.tensor([1.0, 0.0, 0.0])) / 2.0, atol=1e-6)
    t = torus(R=1.0, r=0.25, segments=32, rings=16)
    v = t.vertices.double()
    ring = torch.stack([v[:, 0], v[:, 1]], -1).norm(dim=-1)
    tube = torch.sqrt((ring - 1.0) ** 2 + v[:, 2] ** 2)
    assert torch.allclose(tube, torch.full_like(tube, 0.25), atol=1e-6)
    # surface area of a fine tessellation approaches 4π² R r (chordal error O((π/n)²) ≈ 0.05 %)
    fine = torus(R=1.0, r=0.25, segments=128, rings=64)
    assert abs(fine.tm.area - 4 * math.pi**2 * 0.25) / (4 * math.pi**2 * 0.25) < 2e-3


def test_nonconvex_texture_space_is_injective():
    """Area-sample the surface; every 128² texel must hold points from one small patch only."""
    m = nonconvex(segments=48, detail=12)
    pts, face = trimesh.sample.sample_surface(m.tm, 60000, seed=3)
    tri = m.tm.vertices[m.tm.faces[face]]
    # barycentrics of the samples
    v0, v1, v2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], pts - tri[:, 0]
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    b1, b2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    uvt = m.uvs.double().numpy()[m.tm.faces[face]]
    uv = (1 - b1 - b2)[:, None] * uvt[:, 0] + b1[:, None] * uvt[:, 1] + b2[:, None] * uvt[:, 2]
    H = W = 128
    j = np.clip(np.floor(uv[:, 0] * W), 0, W - 1).astype(int)
    i = np.clip(np.floor((1 - uv[:, 1]) * H), 0, H - 1).astype(int)
    tex = i * W + j
    mean = np.zeros((H * W, 3))
    cnt = np.zeros(H * W)
    np.add.at(mean, tex, pts)
    np.add.at(cnt, tex, 1)
    mean = mean / np.maximum(cnt, 1)[:, None]
    spread = np.linalg.norm(pts - mean[tex], axis=1)
    # a texel spans at most 2π·1.2/(128·(1-2·0.02)) ≈ 0.06 around the plate rim; two patches would be ≥ 0.05 apart
    # and the mean would sit between them, far from both
    assert spread.max() < 0.1, spread.max()
    # the layout uses the map: most texels in the charts are hit
    assert (cnt > 0).mean() > 0.5


def test_obj_round_trip(tmp_path):
    m = nonconvex(segments=24, detail=6)
    save_mesh(m, tmp_path / "a.obj")
    m2 = load_mesh(tmp_path / "a.obj")
    assert torch.equal(m2.faces, m.faces)
    assert torch.allclose(m2.vertices, m.vertices, atol=1e-6)
    assert torch.allclose(m2.uvs, m.uvs, atol=1e-7)
    assert torch.allclose(m2.normals, m.normals, atol=1e-6)
    assert not list(tmp_path.glob(".*tmp")), "no temporary file left behind"


def test_ply_round_trip_and_scene_concatenation(tmp_path):
    s = uv_sphere(segments=16, rings=8)
    save_mesh(s, tmp_path / "s.ply")
    s2 = load_mesh(tmp_path / "s.ply")
    assert torch.allclose(s2.vertices, s.vertices, atol=1e-6) and torch.allclose(s2.uvs, s.uvs, atol=1e-6)
    # a GLB scene with two textured geometries is concatenated into one mesh
    scene = trimesh.Scene()
    for mesh, off in ((s, 0.0), (plane(), 3.0)):
        tm = trimesh.Trimesh(mesh.vertices.numpy() + off, mesh.faces.numpy(), process=False)
        tm.visual = trimesh.visual.TextureVisuals(uv=mesh.uvs.numpy())
        scene.add_geometry(tm)
    (tmp_path / "two.glb").write_bytes(scene.export(file_type="glb"))
    both = load_mesh(tmp_path / "two.glb")
    assert len(both.faces) == len(s.faces) + 2
    assert both.uvs.shape == (len(both.vertices), 2)


def test_bad_files(tmp_path):
    tm = trimesh.creation.box()
    tm.export(tmp_path / "nouv.ply")
    with pytest.raises(MeshError, match=r"nouv\.ply.*UV"):
        load_mesh(tmp_path / "nouv.ply")
    (tmp_path / "junk.glb").write_bytes(b"this is not a glb file")
    with pytest.raises(MeshError, match="junk.glb"):
        load_mesh(tmp_path / "junk.glb")
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh(tmp_path / "missing.obj")
    with pytest.raises(MeshError, match="unsupported extension"):
        save_mesh(plane(), tmp_path / "x.stl")


def test_bad_arrays():
    with pytest.raises(MeshError, match="face indices"):
        Mesh.from_arrays(np.zeros((3, 3)), [[0, 1, 3]], np.zeros((3, 2)))
    with pytest.raises(MeshError, match="one row per vertex"):
        Mesh.from_arrays(np.eye(3), [[0, 1, 2]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="radius"):
        uv_sphere(radius=-1.0)
    with pytest.raises(ValueError, match="smaller"):
        torus(R=1.0, r=1.5)
