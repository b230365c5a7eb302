"""capture.export: atlas round trips, UV rewrite, glTF reload, reconstruction folders, bad input."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import trimesh

from capture import export as E
from materials import atlas as A
from renderer import imageio
from renderer.mesh import load_mesh, plane, save_mesh, uv_sphere

ROOT = Path(__file__).resolve().parents[2]


def _maps(h, w, seed):
    g = torch.Generator().manual_seed(seed)
    return {
        "albedo": torch.rand(h, w, 3, generator=g),
        "f0": 0.02 + 0.9 * torch.rand(h, w, 3, generator=g),
        "roughness": 0.2 + 0.6 * torch.rand(h, w, 1, generator=g),
    }


def _nearest(tex, uv):
    h, w = tex.shape[:2]
    j = torch.floor(uv[..., 0] * w).long().clamp(0, w - 1)
    i = torch.floor((1 - uv[..., 1]) * h).long().clamp(0, h - 1)
    return tex[i, j]


@pytest.fixture
def two(tmp_path):
    m1 = E.Material("sphere", _maps(32, 64, 1), uv_sphere(segments=16, rings=8))
    m2 = E.Material("slab", dict(_maps(24, 20, 2), absorption=torch.rand(24, 20, 3) * 5), plane(), coat_ior=1.4,
                    coat_roughness=0.05)
    return m1, m2


def test_round_trip_two_materials(tmp_path, two):
    m1, m2 = two
    side = E.export_atlas([m1, m2], tmp_path / "atlas", gutter=3)
    names = sorted(os.listdir(tmp_path / "atlas"))
    assert names == ["absorption.exr", "atlas.glb", "atlas.json", "coat.exr", "meshes", "tex1.png", "tex2.png",
                     "textures"]
    assert sorted(os.listdir(tmp_path)) == ["atlas"]  # no temp folder left behind
    assert json.loads((tmp_path / "atlas" / "atlas.json").read_text()) == side
    assert side["textures"]["tex2"]["channels"]["A"] == "glossiness" and side["transfer"] == "gamma2.2"
    back = E.read_atlas(tmp_path / "atlas")
    for m in (m1, m2):
        b = back[m.name]
        # 8-bit: within half a code in encoded (gamma 2.2) space
        for k in ("albedo", "f0"):
            err = (A.transfer_encode(b[k].double()) - A.transfer_encode(m.maps[k].double())).abs().max()
            assert err <= 0.5 / 255 + 1e-6, (m.name, k, err)
        g_ref = torch.log2(2 / m.maps["roughness"].double() ** 4 - 2) / 12
        assert (b["glossiness"].double() - g_ref).abs().max() <= 0.5 / 255 + 1e-6
        assert torch.equal(b["mask"], torch.ones_like(b["mask"]))
    torch.testing.assert_close(back["slab"]["absorption"], m2.maps["absorption"])  # float EXR: exact
    assert torch.all(back["slab"]["coat_ior"] == 1.4) and torch.all(back["slab"]["coat_roughness"] == 0.05)
    # the material without a coat holds "no coat": absorption 0, η 1
    assert torch.all(back["sphere"]["absorption"] == 0) and torch.all(back["sphere"]["coat_ior"] == 1.0)


def test_uv_rewrite_keeps_texel_values(tmp_path, two):
    m1, m2 = two
    side = E.export_atlas([m1, m2], tmp_path / "a", gutter=2, glb=False)
    tex1 = imageio.read_png(tmp_path / "a" / "tex1.png", transfer="linear")
    for m in (m1, m2):
        moved = load_mesh(tmp_path / "a" / "meshes" / f"{m.name}.obj")
        assert moved.uvs.shape == m.mesh.uvs.shape
        torch.testing.assert_close(moved.vertices, m.mesh.vertices)
        # sample at points inside the triangles (barycentric weights chosen off texel edges), before/after
        f = m.mesh.faces
        w = torch.tensor([0.21, 0.32, 0.47]).reshape(1, 3, 1)
        uv_old = (m.mesh.uvs[f] * w).sum(1)
        uv_new = (moved.uvs[f] * w).sum(1)
        before = torch.round(A.transfer_encode(_nearest(m.maps["albedo"], uv_old)) * 255)
        after = torch.round(_nearest(tex1, uv_new)[..., :3] * 255)
        assert torch.equal(before, after), m.name
        r = next(e for e in side["materials"] if e["name"] == m.name)["uv"]
        assert (moved.uvs[:, 0] >= r["u_min"] - 1e-6).all() and (moved.uvs[:, 0] <= r["u_max"] + 1e-6).all()
        assert (moved.uvs[:, 1] >= r["v_min"] - 1e-6).all() and (moved.uvs[:, 1] <= r["v_max"] + 1e-6).all()


def test_glb_reloads_through_trimesh(tmp_path, two):
    m1, m2 = two
    side = E.export_atlas([m1, m2], tmp_path / "a")
    scene = trimesh.load(tmp_path / "a" / "atlas.glb")
    assert isinstance(scene, trimesh.Scene) and len(scene.geometry) == 2
    by_verts = {len(g.vertices): g for g in scene.geometry.values()}
    for m in (m1, m2):
        g = by_verts[len(m.mesh.vertices)]
        assert len(g.faces) == len(m.mesh.faces)
        moved = load_mesh(tmp_path / "a" / "meshes" / f"{m.name}.obj")
        # trimesh flips glTF's top-left V back to our bottom-left convention
        torch.testing.assert_close(torch.as_tensor(g.visual.uv, dtype=torch.float32), moved.uvs, atol=1e-6, rtol=0)
        mat = g.visual.material
        assert mat.baseColorTexture.size == (side["size"]["width"], side["size"]["height"])
        assert mat.metallicFactor == 1.0  # the texture's B channel holds metallic
    js, _ = E.read_glb(tmp_path / "a" / "atlas.glb")
    # random f0 in [0.02, 0.92] with random albedo: the core mapping cannot carry every f0, the extension does
    ext = js["materials"][0]["extensions"]
    assert ext["KHR_materials_specular"]["specularColorFactor"] == [25.0] * 3 and js["extensionsUsed"] == [
        "KHR_materials_specular"]
    assert side["gltf"]["mapping"]["specular_extension"] is True


@pytest.mark.parametrize("fmt,bits", [("png", 16), ("exr", 8)])
def test_16bit_and_exr_storage(tmp_path, fmt, bits):
    m = E.Material("m", _maps(8, 8, 5))
    side = E.export_atlas([m], tmp_path / "a", fmt=fmt, bits=bits, transfer="srgb")
    assert side["textures"]["tex1"]["file"] == f"tex1.{fmt}" and side["transfer"] == "srgb"
    back = E.read_atlas(tmp_path / "a")["m"]
    tol = 0.5 / 65535 + 1e-6 if fmt == "png" else 1e-6
    enc = (A.transfer_encode(back["albedo"].double(), "srgb") - A.transfer_encode(m.maps["albedo"].double(), "srgb"))
    assert enc.abs().max() <= tol


def test_reconstruction_folders_and_script(tmp_path, capsys):
    rec = tmp_path / "rec_a"
    maps = _maps(16, 16, 7)
    maps["coverage"] = torch.ones(16, 16, 1)
    maps["coverage"][:, 12:] = 0
    E.write_maps(maps, rec)
    assert (rec / "albedo.png").exists() and (rec / "coverage.exr").exists()
    save_mesh(plane(), rec / "mesh.obj")
    (rec / "report.json").write_text(json.dumps({"coat_ior": None}))
    mat = E.load_reconstruction(rec)
    assert mat.name == "rec_a" and mat.mesh is not None and set(mat.maps) == set(maps)
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "export_atlas.py"), str(rec), "--out", str(out), "--bits", "16",
         "--transfer", "srgb"], capture_output=True, text=True, cwd=ROOT, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    side = json.loads((out / "atlas.json").read_text())
    assert side["storage"]["bits"] == 16 and side["materials"][0]["name"] == "rec_a"
    back = E.read_atlas(out)["rec_a"]
    # covered texels survive; uncovered ones were filled by dilation from their neighbours
    torch.testing.assert_close(back["albedo"][:, :12], maps["albedo"][:, :12], atol=2e-4, rtol=0)
    # the script refuses an existing folder (run in-process: a second interpreter start costs ~10 s)
    import importlib.util

    spec = importlib.util.spec_from_file_location("export_atlas_script", ROOT / "scripts" / "export_atlas.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main([str(rec), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert script.main([str(rec), "--out", str(out), "--force", "--no-glb"]) == 0


# --------------------------------------------------------------------------------------------
# bad input


def test_different_sizes_resampled_with_warning(tmp_path):
    maps = _maps(16, 16, 3)
    maps["roughness"] = torch.full((8, 8, 1), 0.5)
    with pytest.warns(E.ExportWarning, match=r"resampled \['roughness'\] to 16x16"):
        E.export_atlas({"m": maps}, tmp_path / "a")
    back = E.read_atlas(tmp_path / "a")["m"]
    assert back["roughness"].shape == (16, 16, 1)
    torch.testing.assert_close(back["roughness"], torch.full((16, 16, 1), 0.5), atol=3e-3, rtol=0)


def test_out_of_range_clamped_with_counts(tmp_path):
    maps = _maps(4, 4, 4)
    maps["albedo"][0, 0] = torch.tensor([1.5, -0.1, 0.5])
    with pytest.warns(E.ExportWarning, match=r"material 'm'.*albedo: 1 below 0, 1 above 1"):
        E.export_atlas({"m": maps}, tmp_path / "a")
    assert E.read_atlas(tmp_path / "a")["m"]["albedo"][0, 0, 0] == 1.0


def test_atlas_too_small_names_size_needed(tmp_path):
    with pytest.raises(E.ExportError, match="needs at least 60x88"):
        E.export_atlas({"a": _maps(40, 60, 0), "b": _maps(40, 60, 1)}, tmp_path / "x", atlas_size=64)
    assert not (tmp_path / "x").exists() and os.listdir(tmp_path) == []


def test_missing_unreadable_and_existing(tmp_path):
    rec = tmp_path / "rec"
    E.write_maps(_maps(8, 8, 0), rec, previews=False)
    (rec / "albedo.exr").rename(rec / "albedo.bak")
    with pytest.raises(E.ExportError, match=r"albedo\.exr.*required map 'albedo' is missing"):
        E.export_atlas_dirs([rec], tmp_path / "out")
    (rec / "albedo.bak").rename(rec / "albedo.exr")
    # a diffuse-only reconstruction (no f0, no roughness) exports with K_specular = 0 and a warning
    (rec / "f0.exr").unlink()
    (rec / "roughness.exr").unlink()
    with pytest.warns(E.ExportWarning, match="diffuse-only"):
        E.export_atlas_dirs([rec], tmp_path / "diffuse")
    back = E.read_atlas(tmp_path / "diffuse")["rec"]
    assert back["f0"].abs().max().item() == 0.0
    E.write_maps({"f0": torch.rand(8, 8, 3), "roughness": torch.rand(8, 8, 1)}, rec, previews=False)
    data = (rec / "albedo.exr").read_bytes()
    (rec / "albedo.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(E.ExportError, match=r"albedo\.exr.*cannot read map 'albedo'"):
        E.export_atlas_dirs([rec], tmp_path / "out")
    with pytest.raises(E.ExportError, match="does not exist"):
        E.load_reconstruction(tmp_path / "nope")
    with pytest.raises(E.ExportError, match=r"missing map\(s\) \['albedo'\]"):
        E.export_atlas({"m": {"f0": torch.rand(2, 2, 3), "roughness": torch.rand(2, 2, 1)}}, tmp_path / "o")
    bad = _maps(4, 4, 0)
    bad["f0"][1, 1, 1] = float("nan")
    with pytest.raises(E.ExportError, match="'f0' has 1 NaN"):
        E.export_atlas({"m": bad}, tmp_path / "o")
    # existing output: refused, then replaced with force
    E.export_atlas({"m": _maps(4, 4, 1)}, tmp_path / "o")
    stamp = (tmp_path / "o" / "atlas.json").read_text()
    with pytest.raises(E.ExportError, match="exists.*force=True"):
        E.export_atlas({"m": _maps(4, 4, 1)}, tmp_path / "o")
    E.export_atlas({"n": _maps(4, 4, 2)}, tmp_path / "o", force=True)
    assert (tmp_path / "o" / "atlas.json").read_text() != stamp
    assert list(E.read_atlas(tmp_path / "o")) == ["n"]


def test_failure_midway_leaves_previous_atlas_intact(tmp_path):
    E.export_atlas({"m": _maps(4, 4, 1)}, tmp_path / "o")
    before = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "o").rglob("*") if p.is_file()}
    tiled = plane()
    tiled.uvs[:, 0] *= 3  # a tiling texture cannot go into an atlas: fails after the textures are written
    with pytest.raises(E.ExportError, match="outside"):
        E.export_atlas([E.Material("t", _maps(4, 4, 2), tiled)], tmp_path / "o", force=True)
    assert {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "o").rglob("*") if p.is_file()} == before
    assert sorted(os.listdir(tmp_path)) == ["o"]


def test_read_atlas_errors(tmp_path):
    with pytest.raises(E.ExportError, match="sidecar is missing"):
        E.read_atlas(tmp_path)
    E.export_atlas({"m": _maps(4, 4, 1)}, tmp_path / "o")
    (tmp_path / "o" / "tex2.png").unlink()
    with pytest.raises(E.ExportError, match=r"tex2\.png.*cannot read"):
        E.read_atlas(tmp_path / "o")


# --------------------------------------------------------------------------------------------
# glTF metallic-roughness, Y-up, texture sets (docs/export.md)

GOLD, COPPER = (1.0, 0.78, 0.34), (0.95, 0.64, 0.54)


def _regions(h=64, w=64):
    """Gold, copper (metals: albedo 0), red plastic (f0 0.04), a gem-like dielectric (f0 0.08); roughness 0.25..0.7."""
    albedo, f0 = torch.zeros(h, w, 3), torch.zeros(h, w, 3)
    q = w // 4
    for k, (a, f) in enumerate([((0, 0, 0), GOLD), ((0, 0, 0), COPPER), ((0.6, 0.1, 0.08), (0.04,) * 3),
                                ((0.3, 0.45, 0.5), (0.08,) * 3)]):
        albedo[:, k * q: (k + 1) * q] = torch.tensor(a)
        f0[:, k * q: (k + 1) * q] = torch.tensor(f)
    rough = torch.linspace(0.25, 0.7, h).reshape(h, 1, 1).expand(h, w, 1).contiguous()
    return {"albedo": albedo, "f0": f0, "roughness": rough}


def _png_from_bytes(data, tmp_path, name, transfer):
    p = tmp_path / f"_{name}.png"
    p.write_bytes(data)
    return imageio.read_png(p, transfer=transfer)


def _png_chunks(data):
    out, pos = {}, 8
    while pos < len(data):
        n = int.from_bytes(data[pos: pos + 4], "big")
        out.setdefault(data[pos + 4: pos + 8].decode(), data[pos + 8: pos + 8 + n])
        pos += 12 + n
    return out


def _read_gltf_material(glb, tmp_path, use_extension=True, layering=True):
    """Parse our GLB independently of the writer: mesh in the dataset's frame, and maps read back by glTF's
    definitions (albedo = (1 - m) b, f0 = mix(t or 0.04, b, m)). ``layering``: the albedo a viewer that dims the
    diffuse under the dielectric specular layer shows on average, (1 - m) b (1 - Ē(r, F0 of that layer)), with
    Ē = E.specular_albedo (checked against the model's BRDF in test_specular_albedo_matches_the_model_brdf)."""
    import numpy as np

    from renderer.mesh import Mesh

    js, blob = E.read_glb(glb)

    def accessor(i, dtype, width):
        acc = js["accessors"][i]
        view = js["bufferViews"][acc["bufferView"]]
        arr = np.frombuffer(blob, dtype=dtype, count=acc["count"] * width, offset=view["byteOffset"])
        return arr.reshape(acc["count"], width)

    prim = js["meshes"][0]["primitives"][0]
    pos = torch.from_numpy(accessor(prim["attributes"]["POSITION"], np.float32, 3).copy())
    nrm = torch.from_numpy(accessor(prim["attributes"]["NORMAL"], np.float32, 3).copy())
    uv = torch.from_numpy(accessor(prim["attributes"]["TEXCOORD_0"], np.float32, 2).copy())
    faces = accessor(prim["indices"], np.uint32, 1).reshape(-1, 3).astype(np.int64)
    uv[:, 1] = 1 - uv[:, 1]  # glTF's top-left origin → ours
    mesh = Mesh.from_arrays(E.yup_to_zup(pos).numpy(), faces, uv.numpy(), E.yup_to_zup(nrm).numpy())

    def image(tex_index, transfer):
        view = js["bufferViews"][js["images"][js["textures"][tex_index]["source"]]["bufferView"]]
        data = blob[view["byteOffset"]: view["byteOffset"] + view["byteLength"]]
        return _png_from_bytes(data, tmp_path, f"t{tex_index}", transfer), data

    mat = js["materials"][0]
    pbr = mat["pbrMetallicRoughness"]
    base, _ = image(pbr["baseColorTexture"]["index"], "srgb")
    mr, _ = image(pbr["metallicRoughnessTexture"]["index"], "linear")
    metallic = (mr[..., 2:3] * pbr.get("metallicFactor", 1.0)).clamp(0, 1)
    spec = None
    ext = mat.get("extensions", {}).get("KHR_materials_specular")
    if ext is not None and use_extension:
        col, _ = image(ext["specularColorTexture"]["index"], "srgb")
        spec = (0.04 * torch.tensor(ext["specularColorFactor"]) * col).clamp(max=1.0) * ext.get("specularFactor", 1)
    back = E.from_metallic_roughness(base[..., :3], metallic, spec)
    albedo = back["albedo"]
    if layering:
        layer_f0 = 0.04 if spec is None else spec.amax(-1, keepdim=True)
        albedo = (albedo * (1 - E.specular_albedo(mr[..., 1:2], layer_f0))).float()
    return mesh, {"albedo": albedo, "f0": back["f0"], "roughness": mr[..., 1:2]}, js


def _psnr(a, b, mask):
    peak = b[mask].max()
    mse = ((a - b)[mask] ** 2).mean()
    return (10 * torch.log10(peak**2 / mse)).item()


def _views(mesh, maps, size=72):
    import materials
    from renderer.camera import look_at
    from renderer.lights import PointLight
    from renderer.shading import render

    model = materials.get("ggx-lambert")
    out = []
    for eye in ((3.0, -1.5, 1.2), (-2.0, -2.5, -0.8)):
        cam = look_at(eye, fov_y_deg=38, width=size, height=size)
        light = PointLight(position=torch.tensor(eye) * 1.3 + torch.tensor([0.5, 0.0, 1.0]), intensity=12.0)
        out.append(render(mesh, cam, [light], model, maps, supersample=2))
    return torch.stack(out)


def test_metallic_roughness_mapping_exact_cases_and_error():
    a = torch.tensor([[0, 0, 0], [0, 0, 0], [0.6, 0.1, 0.08], [0.3, 0.45, 0.5], [0.5, 0.5, 0.5]], dtype=torch.float64)
    f = torch.tensor([GOLD, COPPER, (0.04,) * 3, (0.08,) * 3, (0.5,) * 3], dtype=torch.float64)
    r = E.to_metallic_roughness(a, f, levels=None)
    # metals: metallic 1, base colour = f0; a 0.04 dielectric: metallic 0, base colour = albedo
    assert r["metallic"][:2].eq(1).all() and r["metallic"][2].item() == 0
    torch.testing.assert_close(r["base_color"][:2], f[:2], atol=1e-12, rtol=0)
    torch.testing.assert_close(r["base_color"][2], a[2], atol=1e-12, rtol=0)
    # the gem (f0 0.08): a little metallic raises F0 while keeping the diffuse (error 0.0013); the core F0
    # is off by up to 0.0135 where base colour is dark (red), and the extension makes F0 exact
    assert 0 < r["metallic"][3].item() < 0.15
    assert r["diffuse_error"][3].abs().max() < 2e-3 and r["f0_error_core"][3].abs().max() < 0.015
    assert r["f0_error"].abs().max() < 1e-9
    # round trip through glTF's definitions
    back = E.from_metallic_roughness(r["base_color"], r["metallic"], r["specular_f0"])
    torch.testing.assert_close(back["f0"], f, atol=1e-9, rtol=0)
    torch.testing.assert_close(back["albedo"] - a, r["diffuse_error"], atol=1e-12, rtol=0)
    # least squares: no metallic on a fine grid does better (checked by brute force)
    ms = torch.linspace(0, 1, 4001, dtype=torch.float64)
    _, cost = E._best_base(a, f, ms.expand(len(a), -1))
    _, ours = E._best_base(a, f, r["metallic"])
    assert (ours[:, 0] - cost.min(-1).values).max() < 1e-9
    with pytest.raises(E.ExportError, match="outside \\[0, 1\\]"):
        E.to_metallic_roughness(a + 2, f)
    with pytest.raises(E.ExportError, match="same shape"):
        E.to_metallic_roughness(a[:2], f)
    with pytest.raises(E.ExportError, match="levels"):
        E.to_metallic_roughness(a, f, levels=0)


def _specular_albedo_by_brute_force(r, f0, n=128, m=24):
    """Ē(r, f0) of ggx-lambert's own BRDF (albedo 0), independently of capture.export: half vectors on a midpoint
    grid distributed as D(h) n·h, l = the mirrored view, E(μ_o) = mean of f μ_i 4 v·h / (D n·h); μ_o on m
    Gauss-Legendre nodes, 2 ∫ E μ dμ."""
    import math

    import numpy as np

    import materials
    from materials.microfacet import ndf_ggx

    model = materials.get("ggx-lambert")
    alpha = r * r
    x, w = np.polynomial.legendre.leggauss(m)
    u = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    u1, u2 = (g.reshape(-1) for g in torch.meshgrid(u, u, indexing="ij"))
    cos_h = torch.sqrt((1 - u1) / (1 + (alpha**2 - 1) * u1))
    sin_h = (1 - cos_h**2).clamp_min(0).sqrt()
    h = torch.stack([sin_h * torch.cos(2 * math.pi * u2), sin_h * torch.sin(2 * math.pi * u2), cos_h], -1)
    nrm = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(h)
    total = 0.0
    for mu, wt in zip(0.5 * (x + 1), 0.5 * w, strict=True):
        v = torch.tensor([math.sqrt(1 - mu * mu), 0.0, mu], dtype=torch.float64).expand_as(h)
        vh = (v * h).sum(-1, keepdim=True)
        l = 2 * vh * h - v
        f = model(nrm, l, v, albedo=torch.zeros(3, dtype=torch.float64), f0=torch.full((3,), f0, dtype=torch.float64),
                  roughness=torch.tensor([r], dtype=torch.float64))[..., :1]
        est = f * l[..., 2:].clamp_min(0) * 4 * vh / (ndf_ggx(h[..., 2:], alpha) * h[..., 2:])
        total += 2 * wt * mu * torch.nan_to_num(est).mean().item()
    return total


def test_specular_albedo_matches_the_model_brdf():
    # the tables (visible-normal sampling) against the model's BRDF integrated another way
    for r in (0.25, 0.5, 0.75, 1.0):
        for f0 in (0.04, 1.0):
            ours = E.specular_albedo(torch.tensor(r), f0).item()
            brute = _specular_albedo_by_brute_force(r, f0)
            assert abs(ours - brute) < (4e-3 if f0 == 1 else 5e-4), (r, f0, ours, brute)  # measured ≤ 3.2e-3 / 2e-4
    # Ē(0, f0) is the mirror's: Schlick's cosine-weighted mean f0 + (1 - f0)/21
    torch.testing.assert_close(E.specular_albedo(torch.zeros(3), torch.tensor([0.0, 0.04, 1.0])),
                               torch.tensor([1 / 21, 0.04 + 0.96 / 21, 1.0], dtype=torch.float64), atol=3e-4, rtol=0)
    # broadcast roughness [..., 1] with f0 [..., 3]; decreasing in r (a rougher lobe shadows more)
    r = torch.linspace(0, 1, 41)[:, None]
    e = E.specular_albedo(r, torch.tensor([0.04, 0.5, 1.0]))
    assert e.shape == (41, 3) and (e.diff(dim=0) <= 1e-6).all()
    # multiple scattering: 1/Ā₁ for a white lobe, nothing on a mirror, more for rough than for smooth lobes
    s = E.multiscatter_factor(r, torch.tensor([0.04, 0.5, 1.0]))
    torch.testing.assert_close(s[:, 2], 1 / E.specular_albedo(r[:, 0], 1.0), atol=1e-12, rtol=0)
    assert (s[0] - 1).abs().max() < 1e-3 and (s.diff(dim=0) >= -1e-9).all()
    assert 2.4 < s[-1, 2] < 2.5 and 1.12 < E.multiscatter_factor(0.5, 0.95).item() < 1.13  # copper at r = 0.5
    with pytest.raises(E.ExportError, match="roughness must be finite and in"):
        E.specular_albedo(torch.tensor([1.5]), 0.04)
    with pytest.raises(E.ExportError, match="do not broadcast"):
        E.multiscatter_factor(torch.zeros(4, 1), torch.zeros(3, 3))


def test_compensation_of_the_glb_textures(tmp_path):
    maps = _regions(16, 16)
    r = maps["roughness"]
    none = E.gltf_textures(maps, compensation="none")
    lay = E.gltf_textures(maps, compensation="layering")
    both = E.gltf_textures(maps)
    assert E.DEFAULT_COMPENSATION == both["compensation"] == "layering+multiscatter"
    assert lay["compensation"] == "layering" and none["mapping"]["compensation"] == {"mode": "none"}
    # red plastic (metallic 0): base colour = albedo / (1 - Ē(r, t)) — t, as the gem needs the extension
    assert lay["specular"]
    layer = lay["mr"]["specular_f0"][:, 8:12].amax(-1, keepdim=True)
    want = maps["albedo"][:, 8:12] / (1 - E.specular_albedo(r[:, 8:12], layer))
    torch.testing.assert_close(lay["base_color"][:, 8:12], want.float(), atol=1e-6, rtol=0)
    assert torch.all(lay["metallic"][:, 8:12] == 0)
    ratio = lay["base_color"][:, 8, 0] / none["base_color"][:, 8, 0]
    assert 1.036 < ratio.min() and ratio.max() < 1.085 and (ratio.diff() < 0).all()  # 1/(1 - Ē): 7.8 % .. 3.7 %
    # metals (albedo 0) keep base colour = f0 under layering; multiple scattering divides it by s(r, f0)
    torch.testing.assert_close(lay["base_color"][:, :8], none["base_color"][:, :8], atol=0, rtol=0)
    s = E.multiscatter_factor(r[:, :4], torch.tensor(GOLD))
    torch.testing.assert_close(both["base_color"][:, :4], (torch.tensor(GOLD) / s).float(), atol=1e-6, rtol=0)
    torch.testing.assert_close(both["base_color"][:, 8:12], lay["base_color"][:, 8:12], atol=0, rtol=0)  # m = 0
    c = both["mapping"]["compensation"]
    assert c["mode"] == "layering+multiscatter" and c["texels_clamped"] == 0
    assert c["f0_divisor"]["min"] == 1.0 and 1.35 < c["f0_divisor"]["max"] < 1.45  # copper at r = 0.7: 1.414
    # 1.037 (F0 0.04 at r = 0.7) .. 1.102 (the gem's layer, F0 0.08, at r = 0.25)
    assert 1.03 < c["diffuse_factor"]["min"] < 1.04 and 1.09 < c["diffuse_factor"]["max"] < 1.11
    # an albedo near 1 on a smooth lobe would need more than 1: clamped and counted
    white = {"albedo": torch.full((2, 2, 3), 0.97), "f0": torch.full((2, 2, 3), 0.04),
             "roughness": torch.zeros(2, 2, 1)}
    w = E.gltf_textures(white)
    assert torch.all(w["base_color"] == 1) and w["mapping"]["compensation"]["texels_clamped"] == 4
    # the specular form: the layer is the texel's own f0 (its largest channel)
    spec = E.gltf_textures(maps, "specular", compensation="layering+multiscatter")
    want = maps["albedo"] / (1 - E.specular_albedo(r, maps["f0"].amax(-1, keepdim=True)))
    torch.testing.assert_close(spec["base_color"], want.float().clamp(max=1), atol=1e-6, rtol=0)
    spec_colour = _png_from_bytes(spec["images"]["specularColor"], tmp_path, "spec", "srgb")  # within half a code
    torch.testing.assert_close(spec_colour, (maps["f0"] / E.multiscatter_factor(r, maps["f0"])).float(),
                               atol=4.5e-3, rtol=0)
    # the sidecar says which; a bad name is refused everywhere
    side = E.export_atlas([E.Material("m", maps, plane())], tmp_path / "a", texture_sets=None,
                          compensation="layering+multiscatter")
    assert side["gltf"]["compensation"] == "layering+multiscatter"
    assert "multiple-scattering" in side["gltf"]["material"]["compensation"]
    for call in (lambda: E.gltf_textures(maps, compensation="blender"),
                 lambda: E.write_texture_sets(tmp_path / "t", maps, compensation="blender"),
                 lambda: E.export_atlas([E.Material("m", maps, plane())], tmp_path / "b", compensation="blender")):
        with pytest.raises(E.ExportError, match=r"compensation must be one of \['none', 'layering'"):
            call()
    assert not (tmp_path / "t").exists() and not (tmp_path / "b").exists()


def test_glb_material_renders_like_the_source_maps(tmp_path):
    maps = _regions()
    mesh = uv_sphere(segments=48, rings=24)
    # glTF's own BRDF: the diffuse layered under the dielectric specular, GGX scattering once (the viewer below)
    side = E.export_atlas([E.Material("m", maps, mesh)], tmp_path / "a", compensation="layering")
    assert side["size"] == {"width": 64, "height": 64}
    glb_mesh, back, js = _read_gltf_material(tmp_path / "a" / "atlas.glb", tmp_path)
    # metals are metallic 1 with base colour = f0 (8-bit sRGB codes)
    base = E.read_glb(tmp_path / "a" / "atlas.glb")
    mr = imageio.read_png(tmp_path / "a" / "textures" / "gltf_metallicRoughness.png", transfer="linear")
    bc = imageio.read_png(tmp_path / "a" / "textures" / "gltf_baseColor.png", transfer="srgb")
    assert base[0]["materials"][0]["pbrMetallicRoughness"]["metallicFactor"] == 1.0
    assert torch.all(mr[:, :16, 2] == 1) and torch.all(mr[:, 32:48, 2] == 0)
    torch.testing.assert_close(bc[:, :16, :3], torch.tensor(GOLD).expand(64, 16, 3), atol=4e-3, rtol=0)
    # the gem's f0 0.08 needs KHR_materials_specular: with it F0 is exact up to the 8-bit codes
    assert js["extensionsUsed"] == ["KHR_materials_specular"]
    torch.testing.assert_close(back["f0"], maps["f0"], atol=6e-3, rtol=0)
    torch.testing.assert_close(back["albedo"], maps["albedo"], atol=6e-3, rtol=0)
    torch.testing.assert_close(back["roughness"], maps["roughness"], atol=2.5e-3, rtol=0)
    # render the GLB (its own geometry, back in our frame) in a viewer that layers the diffuse under the dielectric
    # specular (glTF's BRDF), and the source with our renderer
    ref = _views(mesh, maps)
    got = _views(glb_mesh, back)
    obj = ref.sum(-1) > 0
    psnr = _psnr(got, ref, obj)
    assert psnr > 56, psnr  # measured 61.1 dB (8-bit textures)
    # a viewer without the extension: the core alone still gets the metals right (the old metallic-0 form
    # made gold a black dielectric there)
    _, core, _ = _read_gltf_material(tmp_path / "a" / "atlas.glb", tmp_path, use_extension=False)
    core_psnr = _psnr(_views(glb_mesh, core), ref, obj)
    assert core_psnr > 45, core_psnr  # measured 49.7 dB
    E.export_atlas([E.Material("m", maps, mesh)], tmp_path / "s", material_model="specular", texture_sets=None,
                   compensation="layering")
    _, old, js_old = _read_gltf_material(tmp_path / "s" / "atlas.glb", tmp_path, use_extension=False)
    assert js_old["materials"][0]["pbrMetallicRoughness"]["metallicFactor"] == 1.0
    old_psnr = _psnr(_views(glb_mesh, old), ref, obj)
    assert old_psnr < core_psnr - 8, (old_psnr, core_psnr)  # measured 37.6 dB
    # the compensation is what makes the layering viewer right: without it that viewer is 5 % dark on the
    # dielectrics, while a viewer that adds the lobes (our model) reads the uncompensated GLB exactly
    E.export_atlas([E.Material("m", maps, mesh)], tmp_path / "n", compensation="none", texture_sets=None)
    _, plain_layered, _ = _read_gltf_material(tmp_path / "n" / "atlas.glb", tmp_path)
    _, plain_added, _ = _read_gltf_material(tmp_path / "n" / "atlas.glb", tmp_path, layering=False)
    _, comp_added, _ = _read_gltf_material(tmp_path / "a" / "atlas.glb", tmp_path, layering=False)
    assert _psnr(_views(glb_mesh, plain_layered), ref, obj) < psnr - 15  # measured 36.7 dB
    assert _psnr(_views(glb_mesh, plain_added), ref, obj) > 52  # measured 57.8 dB
    assert _psnr(_views(glb_mesh, comp_added), ref, obj) < 40  # measured 36.5 dB
    assert not (tmp_path / "s" / "textures").exists()


def test_glb_is_y_up(tmp_path):
    mesh = uv_sphere(segments=8, rings=4)
    top = int(mesh.vertices[:, 2].argmax())  # the +Z pole of the dataset's frame
    side = E.export_atlas([E.Material("m", _maps(4, 4, 0), mesh)], tmp_path / "a", texture_sets=None)
    assert side["gltf"]["up_axis"] == "Y"
    js, blob = E.read_glb(tmp_path / "a" / "atlas.glb")
    import numpy as np

    prim = js["meshes"][0]["primitives"][0]

    def attr(name):
        acc = js["accessors"][prim["attributes"][name]]
        off = js["bufferViews"][acc["bufferView"]]["byteOffset"]
        return np.frombuffer(blob, np.float32, acc["count"] * 3, off).reshape(-1, 3)

    pos, nrm = attr("POSITION"), attr("NORMAL")
    np.testing.assert_allclose(pos[top], [0, 1, 0], atol=1e-6)  # +Z → +Y
    np.testing.assert_allclose(nrm[top], [0, 1, 0], atol=1e-6)
    v = mesh.vertices.numpy()
    np.testing.assert_allclose(pos, np.stack([v[:, 0], v[:, 2], -v[:, 1]], 1), atol=1e-6)  # (x, y, z) → (x, z, −y)
    acc = js["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose(acc["max"], pos.max(0)) and np.testing.assert_allclose(acc["min"], pos.min(0))
    torch.testing.assert_close(E.yup_to_zup(E.zup_to_yup(mesh.vertices)), mesh.vertices)


@pytest.mark.parametrize("bits", [8, 16])
def test_png_bit_depth_in_glb_and_texture_sets(tmp_path, bits):
    kw = {} if bits == 8 else {"bits": 16}
    E.export_atlas([E.Material("m", _regions(16, 16), plane())], tmp_path / "a", **kw)
    js, blob = E.read_glb(tmp_path / "a" / "atlas.glb")
    for img in js["images"]:
        view = js["bufferViews"][img["bufferView"]]
        data = blob[view["byteOffset"]: view["byteOffset"] + view["byteLength"]]
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[24] == bits  # IHDR bit depth
    for p in (tmp_path / "a" / "textures").glob("*.png"):
        assert p.read_bytes()[24] == bits, p.name
    assert (tmp_path / "a" / "tex1.png").read_bytes()[24] == bits
    # 16 bits: roughness codes within half a 16-bit code
    mr = imageio.read_png(tmp_path / "a" / "textures" / "gltf_metallicRoughness.png", transfer="linear")
    tol = 0.5 / ((1 << bits) - 1) + 1e-7
    assert (mr[..., 1:2] - _regions(16, 16)["roughness"]).abs().max() <= tol


def test_texture_sets_channels_and_tags(tmp_path):
    import OpenEXR

    maps = _regions(16, 16)
    maps["mask"] = torch.ones(16, 16, 1)
    maps["mask"][0, 0] = 0.0
    maps["coverage"] = torch.ones(16, 16, 1)  # every texel observed: the mask is kept, not filled
    side = E.export_atlas([E.Material("m", maps, plane())], tmp_path / "a")
    t = tmp_path / "a" / "textures"
    assert sorted(p.name for p in t.iterdir()) == [
        "albedo.exr", "f0.exr", "gltf_baseColor.png", "gltf_metallicRoughness.png", "gltf_specularColor.png",
        "mask.exr", "roughness.exr", "unity_BaseColorMap.png", "unity_MaskMap.png", "unreal_BaseColor.png",
        "unreal_ORM.png"]
    assert side["texture_sets"]["files"]["unreal"]["ORM"] == "unreal_ORM.png"
    r = maps["roughness"][..., 0]
    orm = imageio.read_png(t / "unreal_ORM.png", transfer="linear")
    mask_map = imageio.read_png(t / "unity_MaskMap.png", transfer="linear")
    q = 0.5 / 255 + 1e-6
    assert torch.all(orm[..., 0] == 1) and (orm[..., 1] - r).abs().max() <= q
    assert torch.all(orm[:, :8, 2] == 1) and torch.all(orm[:, 8:12, 2] == 0)  # red plastic: 0; gem: a little
    assert torch.equal(mask_map[..., 0], orm[..., 2])  # R = metallic
    assert torch.all(mask_map[..., 1] == 1) and torch.all(mask_map[..., 2] == 1)  # occlusion, detail mask
    assert (mask_map[..., 3] - (1 - r)).abs().max() <= q  # A = smoothness = 1 − perceptual roughness
    base = imageio.read_png(t / "unity_BaseColorMap.png", transfer="srgb")
    assert base[0, 0, 3] == 0 and base[1, 1, 3] == 1  # alpha = mask
    # the glTF set is the GLB's textures (compensated for the viewer's layering); the engines' sets hold the
    # uncompensated mapping, the glTF set of an export with compensation "none"
    js, blob = E.read_glb(tmp_path / "a" / "atlas.glb")
    view = js["bufferViews"][js["images"][0]["bufferView"]]
    assert bytes(blob[view["byteOffset"]: view["byteOffset"] + view["byteLength"]]) == \
        (t / "gltf_baseColor.png").read_bytes()
    E.export_atlas([E.Material("m", maps, plane())], tmp_path / "n", compensation="none", texture_sets=["gltf"])
    plain = tmp_path / "n" / "textures"
    assert (t / "unreal_BaseColor.png").read_bytes() == (plain / "gltf_baseColor.png").read_bytes() \
        != (t / "gltf_baseColor.png").read_bytes()
    assert (t / "unreal_ORM.png").read_bytes() == (plain / "gltf_metallicRoughness.png").read_bytes()
    torch.testing.assert_close(imageio.read_exr(t / "roughness.exr"), maps["roughness"])
    torch.testing.assert_close(imageio.read_exr(t / "f0.exr"), maps["f0"])
    # intent: sRGB chunk on colour, gAMA 1.0 and no sRGB on data; EXRs say Rec. 709 / D65
    for name, srgb in (("gltf_baseColor.png", True), ("gltf_specularColor.png", True), ("unreal_ORM.png", False),
                       ("unity_MaskMap.png", False)):
        chunks = _png_chunks((t / name).read_bytes())
        assert ("sRGB" in chunks) == srgb, name
        assert int.from_bytes(chunks["gAMA"], "big") == (45455 if srgb else 100000), name
    assert int.from_bytes(_png_chunks((tmp_path / "a" / "tex1.png").read_bytes())["gAMA"], "big") == 45455
    with OpenEXR.File(str(t / "albedo.exr")) as f:
        xy = f.header()["chromaticities"]
    assert [round(v, 4) for v in xy] == [0.64, 0.33, 0.3, 0.6, 0.15, 0.06, 0.3127, 0.329]
    with pytest.raises(E.ExportError, match="unknown texture set"):
        E.export_atlas([E.Material("m", maps, plane())], tmp_path / "b", texture_sets=["godot"])
    with pytest.raises(E.ExportError, match="material_model"):
        E.export_atlas([E.Material("m", maps, plane())], tmp_path / "b", material_model="phong")


def test_one_256_material_gives_a_256_atlas(tmp_path):
    maps = {"albedo": torch.full((256, 256, 3), 0.5), "f0": torch.full((256, 256, 3), 0.04),
            "roughness": torch.full((256, 256, 1), 0.5)}
    side = E.export_atlas({"m": maps}, tmp_path / "a", glb=False, texture_sets=None)
    assert side["size"] == {"width": 256, "height": 256}
    assert side["materials"][0]["rect"] == {"x": 0, "y": 0, "w": 256, "h": 256}
    assert imageio.read_png(tmp_path / "a" / "tex1.png").shape == (256, 256, 4)
    side = E.export_atlas({"m": maps}, tmp_path / "b", glb=False, texture_sets=None, atlas_size="pow2")
    assert side["size"] == {"width": 256, "height": 256}


def test_cli_export_options_and_listing(tmp_path, capsys):
    from capture.cli import main

    rec = tmp_path / "rec"
    E.write_maps(_regions(16, 16), rec, previews=False)
    save_mesh(plane(), rec / "mesh.obj")
    assert main(["export-atlas", str(rec), "--out", str(tmp_path / "o"), "--bits", "16", "--texture-sets",
                 "unreal,unity-hdrp", "--material-model", "metallic-roughness"]) == 0
    out = capsys.readouterr().out
    assert "atlas.glb" in out and "textures/unreal_ORM.png" in out and "gltf_baseColor" not in out
    assert "compensation layering+multiscatter" in out  # the default
    side = json.loads((tmp_path / "o" / "atlas.json").read_text())
    assert side["gltf"]["compensation"] == "layering+multiscatter" and "f0_divisor" in side["gltf"]["mapping"][
        "compensation"]
    assert (tmp_path / "o" / "atlas.glb").read_bytes()[:4] == b"glTF"
    assert main(["export-atlas", str(rec), "--out", str(tmp_path / "c"), "--texture-sets", "none",
                 "--compensation", "layering"]) == 0
    assert "compensation layering;" in capsys.readouterr().out
    side = json.loads((tmp_path / "c" / "atlas.json").read_text())
    assert side["gltf"]["compensation"] == "layering" and "f0_divisor" not in side["gltf"]["mapping"]["compensation"]
    assert main(["export-atlas", str(rec), "--out", str(tmp_path / "p"), "--texture-sets", "none",
                 "--material-model", "specular", "--size", "pow2"]) == 0
    assert json.loads((tmp_path / "p" / "atlas.json").read_text())["size"] == {"width": 16, "height": 16}
    assert not (tmp_path / "p" / "textures").exists()
    js, _ = E.read_glb(tmp_path / "p" / "atlas.glb")
    assert js["materials"][0]["pbrMetallicRoughness"]["metallicFactor"] == 1.0
    with pytest.raises(SystemExit) as exc:  # argparse: usage and the reason on stderr, status 2
        main(["export-atlas", str(rec), "--out", str(tmp_path / "q"), "--texture-sets", "godot"])
    assert exc.value.code == 2 and "unknown texture set(s) ['godot']" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Blender: its glTF importer and Cycles, a renderer that shares no code with ours


def _blender_compare():
    """scripts/blender_compare.py as a module, and the Blender it finds ($SHADECAP_BLENDER: a Blender executable or
    a Python with the bpy module; else `blender` on PATH; else this interpreter with bpy)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("blender_compare", ROOT / "scripts" / "blender_compare.py")
    bc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bc)
    blender = bc.find_blender()
    if blender is None:
        pytest.skip("no Blender: set SHADECAP_BLENDER or put `blender` on PATH")
    return bc, blender


def test_blender_failures_name_their_cause_and_fix(tmp_path):
    """A Blender whose glTF importer breaks on the numpy beside it (np.bool, removed in numpy 1.24; or no numpy at
    all) fails with a message naming the cause and the fix, not only its traceback (a stand-in prints the error)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("blender_compare", ROOT / "scripts" / "blender_compare.py")
    bc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bc)
    for said, hint in (("AttributeError: module 'numpy' has no attribute 'bool'", "use Blender ≥ 3.5"),
                       ("ModuleNotFoundError: No module named 'numpy'", "install numpy for that Python"),
                       ("Segmentation fault", r"missing \['view0'\]\):\n")):
        with pytest.raises(bc.BlenderError, match=hint) as err:
            bc.render(tmp_path / "x.glb", [{"name": "view0"}], tmp_path / "out",
                      blender=[sys.executable, "-c", f"print({said!r})"])
        assert said in str(err.value)


def _blender_psnr(tmp_path, maps, exports, spp=64):
    """Render GLBs of ``maps`` on a sphere in Blender (glTF importer with its defaults, Cycles, direct light, box
    filter) from two dataset cameras and compare with the photos our renderer makes from the maps: Blender's
    major version and, per export (a dict of export_atlas keywords), the PSNR of each view on object pixels."""
    import materials
    from renderer.camera import look_at
    from renderer.lights import PointLight
    from renderer.shading import render

    bc, blender = _blender_compare()
    mesh = uv_sphere(segments=64, rings=32)
    eyes = [(3.0, -1.5, 1.2), (-2.0, -2.5, -0.8)]
    cams = [look_at(eye, fov_y_deg=38, width=96, height=96) for eye in eyes]
    lights = [PointLight(position=torch.tensor(eye) * 1.3 + torch.tensor([0.5, 0.0, 1.0]), intensity=12.0)
              for eye in eyes]
    model = materials.get("ggx-lambert")
    photos = [render(mesh, cam, [light], model, maps, supersample=4) for cam, light in zip(cams, lights, strict=True)]
    views = [{"name": f"view{k}", "camera": cam.to_blender(), "lights": [bc.light_json(light)]}
             for k, (cam, light) in enumerate(zip(cams, lights, strict=True))]
    out, major = [], None
    for k, kw in enumerate(exports):
        E.export_atlas([E.Material("m", maps, mesh)], tmp_path / f"e{k}", texture_sets=None, **kw)
        version = bc.render(tmp_path / f"e{k}" / "atlas.glb", views, tmp_path / f"r{k}", spp=spp, blender=blender)
        major = int(version.split(".")[0])
        out.append([bc.psnr(imageio.read_exr(tmp_path / f"r{k}" / f"view{j}.exr"), photo, photo.sum(-1) > 0)
                    for j, photo in enumerate(photos)])
    return major, out


@pytest.mark.blender
def test_blender_cycles_renders_metals_like_the_photo(tmp_path):
    maps = _regions()
    maps["albedo"][:] = 0
    maps["f0"][:, :32] = torch.tensor(GOLD)
    maps["f0"][:, 32:] = torch.tensor(COPPER)
    major, (plain, multi, spec) = _blender_psnr(tmp_path, maps, [
        {"compensation": "layering"}, {}, {"material_model": "specular", "compensation": "layering"}])
    if major < 4:  # Principled BSDF v1: single-scattering GGX, no coloured dielectric specular
        assert min(plain) >= 57, plain  # measured 64.4 / 60.7 dB
        assert max(multi) < min(plain) - 10, multi  # measured 46.8 / 39.5 dB: the default compensates for nothing
        assert max(spec) < 30, spec  # measured 22.9 / 20.2 dB: the metallic-0 form renders gold dark, untinted
    else:  # Blender >= 4: multiple-scattering GGX (the importer's choice), Specular Tint read as F0's colour
        assert min(plain) >= 40, plain  # measured 52.4 / 42.6 dB
        assert min(multi) >= min(plain) + 3, (multi, plain)  # measured 53.0 / 47.7 dB
        assert min(spec) >= 40, spec  # measured 52.4 / 42.5 dB


@pytest.mark.blender
def test_blender_cycles_renders_dielectrics_like_the_photo(tmp_path):
    # gold, copper, red plastic, the gem (f0 0.08: KHR_materials_specular); the dielectrics set the level
    major, (plain, layered, both) = _blender_psnr(tmp_path, _regions(), [
        {"compensation": "none"}, {"compensation": "layering"}, {}])
    if major < 4:  # Burley diffuse, 5-8 % brighter than Lambert: the compensation only adds to it
        assert min(plain) >= 28, plain  # measured 31.4 / 29.8 dB
        assert max(layered) < min(plain), (layered, plain)  # measured 28.0 / 27.2 dB
    else:  # the diffuse dimmed under the dielectric layer, which the default compensation undoes
        assert max(plain) < 39, plain  # measured 37.5 / 35.1 dB
        assert min(layered) >= 40 and min(both) >= 40, (layered, both)  # measured 44.0 / 42.2, 44.9 / 42.1 dB


def test_gltf_helpers_bad_input(tmp_path):
    E.export_atlas([E.Material("m", _maps(4, 4, 0), plane())], tmp_path / "a", texture_sets=None)
    raw = (tmp_path / "a" / "atlas.glb").read_bytes()
    (tmp_path / "cut.glb").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(E.ExportError, match=r"cut\.glb: truncated or malformed GLB"):
        E.read_glb(tmp_path / "cut.glb")
    with pytest.raises(E.ExportError, match=r"atlas\.json: not a glTF 2\.0 binary"):
        E.read_glb(tmp_path / "a" / "atlas.json")
    with pytest.raises(E.ExportError, match="not a PNG"):
        E.tag_png(b"GIF89a" + bytes(40), "srgb")
    with pytest.raises(E.ExportError, match="intent"):
        E.tag_png((tmp_path / "a" / "tex1.png").read_bytes(), "p3")
    with pytest.raises(E.ExportError, match=r"\[\.\.\., 3\]"):
        E.zup_to_yup(torch.zeros(4, 2))
    with pytest.raises(E.ExportError, match="metallic must be a tensor"):
        E.from_metallic_roughness(torch.zeros(4, 3), torch.zeros(5, 1))
    with pytest.raises(E.ExportError, match="unknown texture set"):
        E.write_texture_sets(tmp_path / "t", _maps(4, 4, 0), ["godot"])
    with pytest.raises(E.ExportError, match=r"needs maps \['roughness'\]"):
        E.gltf_textures({"albedo": torch.zeros(2, 2, 3), "f0": torch.zeros(2, 2, 3)})
    with pytest.raises(E.ExportError, match="no meshes"):
        E.write_glb(tmp_path / "x.glb", [], _maps(4, 4, 0))
    assert not (tmp_path / "t").exists() and not (tmp_path / "x.glb").exists()
