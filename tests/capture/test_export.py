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
    assert names == ["absorption.exr", "atlas.glb", "atlas.json", "coat.exr", "meshes", "tex1.png", "tex2.png"]
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
        assert mat.metallicFactor == 0.0
    raw = (tmp_path / "a" / "atlas.glb").read_bytes()
    js = json.loads(raw[20: 20 + int.from_bytes(raw[12:16], "little")])
    ext = js["materials"][0]["extensions"]
    assert ext["KHR_materials_specular"]["specularColorFactor"] == [25.0] * 3 and ext["KHR_materials_ior"]["ior"] == 1.5


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
    with pytest.raises(E.ExportError, match="needs at least 128x128"):
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
    before = {p.name: p.read_bytes() for p in (tmp_path / "o").iterdir()}
    tiled = plane()
    tiled.uvs[:, 0] *= 3  # a tiling texture cannot go into an atlas: fails after the textures are written
    with pytest.raises(E.ExportError, match="outside"):
        E.export_atlas([E.Material("t", _maps(4, 4, 2), tiled)], tmp_path / "o", force=True)
    assert {p.name: p.read_bytes() for p in (tmp_path / "o").iterdir()} == before
    assert sorted(os.listdir(tmp_path)) == ["o"]


def test_read_atlas_errors(tmp_path):
    with pytest.raises(E.ExportError, match="sidecar is missing"):
        E.read_atlas(tmp_path)
    E.export_atlas({"m": _maps(4, 4, 1)}, tmp_path / "o")
    (tmp_path / "o" / "tex2.png").unlink()
    with pytest.raises(E.ExportError, match=r"tex2\.png.*cannot read"):
        E.read_atlas(tmp_path / "o")
