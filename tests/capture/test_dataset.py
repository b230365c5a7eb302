"""Dataset format: round trips (bitwise for EXR, exact codes for PNG), every bad input → DatasetError
naming the file and field, atomic writes that leave nothing behind."""

import json
import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from capture.dataset import (
    FORMAT,
    VERSION,
    DatasetError,
    DatasetWarning,
    GroundTruth,
    View,
    camera_sees_mesh,
    load_dataset,
    model_from_spec,
    write_dataset,
)
from capture.photo import PhotoModel, quantize_srgb
from capture.synth import build_scene, make_synthetic, small_scene
from renderer.camera import Camera, look_at
from renderer.gbuffer import render_gbuffer
from renderer.imageio import read_exr, read_png, write_exr, write_png
from renderer.lights import PointLight
from renderer.mesh import uv_sphere
from renderer.shading import prepare, shade


def _cfg(**kw):
    # pixel centres: the round-trip tests re-render the views bitwise from what the loader returns
    base = dict(image_size=40, texture_size=32, n_views=3, supersample=1)
    base.update(kw)
    return small_scene(**base)


@pytest.fixture(scope="module")
def exr_ds(tmp_path_factory):
    return make_synthetic(_cfg(photo=PhotoModel(exposure=2.0)), tmp_path_factory.mktemp("d") / "exr")


@pytest.fixture(scope="module")
def png_ds(tmp_path_factory):
    photo = PhotoModel(exposure=1.5, clip=True, encoding="srgb")
    return make_synthetic(_cfg(photo=photo), tmp_path_factory.mktemp("d") / "png")


def _rerender(ds):
    """Render every view again from what the loader returned (mesh, cameras, lights, gt model + maps)."""
    model = ds.gt.build_model()
    out = []
    for v in ds.views:
        g = render_gbuffer(ds.mesh, v.camera, ds.gt.render["supersample"])
        prep = prepare(g, ds.mesh, v.lights, shadows=ds.gt.render["shadows"])
        with torch.no_grad():
            out.append(g.to_image(shade(model, ds.gt.maps, prep, sampling=ds.gt.render["sampling"])))
    return out


def _copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(src, dst)
    return dst


def _edit(ds: Path, fn) -> None:
    doc = json.loads((ds / "scene.json").read_text())
    fn(doc)
    (ds / "scene.json").write_text(json.dumps(doc))


def _raises(ds, *needles):
    with pytest.raises(DatasetError) as info:
        load_dataset(ds)
    msg = str(info.value)
    for n in needles:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ------------------------------------------------------------------------------------------ round trips


def test_round_trip_exr_bitwise(exr_ds):
    ds = load_dataset(exr_ds)
    assert ds.encoding == "linear" and ds.saturation is None and len(ds) == 3
    assert ds.gt.model == {"name": "ggx-lambert", "options": {}}
    photos = ds.load_images()
    again = _rerender(ds)
    for p, r, v in zip(photos, again, ds.views, strict=True):
        assert v.exposure == 2.0
        # the file holds exposure·L; exposure 2 is exact in binary, so file/2 is the float32 rendering, bitwise
        assert torch.equal(p.radiance, r)
        assert torch.equal(ds.read_file_image(ds.views.index(v)), (2.0 * r.double()).float())
        assert not p.saturated.any() and not p.nonfinite.any()
        assert r.max() > 0.1  # something is lit


def test_round_trip_png_codes_exact(png_ds):
    ds = load_dataset(png_ds)
    assert ds.encoding == "srgb" and ds.bits == 8 and ds.saturation == 255
    again = _rerender(ds)
    for i, (p, r) in enumerate(zip(ds.load_images(), again, strict=True)):
        codes, val = quantize_srgb(1.5 * r.double().clamp_max(1 / 1.5), 8)
        raw = read_png(png_ds / ds.views[i].file, "linear")
        assert torch.equal(torch.round(raw.double() * 255).long(), codes)  # same codes
        assert torch.equal(ds.read_file_image(i), val)
        # within quantisation: |encode(loaded) − encode(true)| ≤ half a code (away from clipping)
        from renderer.imageio import encode

        ok = ~p.saturated
        err = (encode(p.radiance.double() * 1.5, "srgb") - encode((1.5 * r.double()).clamp(0, 1), "srgb")).abs()
        assert err[ok].max() <= 0.5 / 255 + 1e-6
        # the saturation mask is exactly "some channel at code 255"
        assert torch.equal(p.saturated, (codes == 255).any(-1))


def test_gt_and_regions_round_trip(exr_ds):
    cfg = _cfg(photo=PhotoModel(exposure=2.0))
    scene = build_scene(cfg)
    ds = load_dataset(exr_ds)
    for k, m in scene.maps.items():
        assert torch.equal(ds.gt.maps[k], m)
    assert torch.equal(ds.gt.regions, scene.regions)
    assert ds.gt.region_names[3] == "gold"
    assert set(ds.gt.files) == {"albedo", "f0", "roughness"}
    assert ds.meta["highlight_coverage"]["observed_texels"] > 0


def test_model_spec_sum_equals_registered():
    a = model_from_spec({"sum": [{"name": "lambert"}, {"name": "microfacet"}]})
    b = model_from_spec("ggx-lambert")
    assert set(a.param_names) == set(b.param_names) == {"albedo", "f0", "roughness"}
    with pytest.raises(ValueError, match="unknown model 'nope'"):
        model_from_spec("nope")


# ------------------------------------------------------------------------------------------ bad inputs


def test_missing_scene_json(tmp_path):
    _raises(tmp_path, "scene.json", "missing")


def test_malformed_json(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    (ds / "scene.json").write_text('{"format": "shadecap-dataset", "version": 1,,}')
    _raises(ds, "scene.json", "malformed JSON at line 1")


@pytest.mark.parametrize("version", [2, 0, "1"])
def test_unknown_version(exr_ds, tmp_path, version):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d.__setitem__("version", version))
    _raises(ds, "scene.json", "field 'version'")


def test_wrong_format(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d.__setitem__("format", "something-else"))
    _raises(ds, "field 'format'", FORMAT)


@pytest.mark.parametrize("path,needle", [
    (("images", 0, "exposure"), "images[0].exposure"),
    (("images", 1, "camera"), "images[1].camera"),
    (("mesh",), "field 'mesh'"),
    (("encoding",), "field 'encoding'"),
])
def test_missing_fields(exr_ds, tmp_path, path, needle):
    ds = _copy(exr_ds, tmp_path)

    def drop(d):
        for k in path[:-1]:
            d = d[k]
        del d[path[-1]]

    _edit(ds, drop)
    _raises(ds, "scene.json", needle, "missing")


def test_unknown_light_type(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][1]["lights"][0].__setitem__("type", "spot"))
    _raises(ds, "scene.json", "images[1].lights[0]", "unknown light type 'spot'")


def test_negative_intensity(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][0]["lights"][1].__setitem__("intensity", [1.0, -2.0, 1.0]))
    _raises(ds, "images[0].lights[1]", "non-negative")


@pytest.mark.parametrize("value", [0.0, -1.0, "1", float("nan")])
def test_bad_exposure(exr_ds, tmp_path, value):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][2].__setitem__("exposure", value))
    _raises(ds, "images[2].exposure")


def test_missing_image(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    (ds / "images" / "001.exr").unlink()
    _raises(ds, "001.exr", "does not exist", "images[1].file")


@pytest.mark.parametrize("which", ["exr", "png"])
def test_truncated_image(exr_ds, png_ds, tmp_path, which):
    ds = _copy(exr_ds if which == "exr" else png_ds, tmp_path)
    f = ds / "images" / f"002.{which}"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    msg = _raises(ds, str(f), "unreadable image (images[2].file)")
    assert "truncated" in msg


def test_unreadable_garbage_image(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    (ds / "images" / "000.exr").write_bytes(b"not an image at all")
    _raises(ds, "000.exr", "not an OpenEXR file")


def test_image_size_mismatch(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)

    def shrink(d):
        cam = d["images"][1]["camera"]
        cam["width"], cam["height"] = 32, 32
        cam["K"][0][2] = cam["K"][1][2] = 15.5

    _edit(ds, shrink)
    _raises(ds, "001.exr", "image is 40×40 px but its camera", "is 32×32")


def test_image_count_mismatch(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    shutil.copy(ds / "images" / "000.exr", ds / "images" / "003.exr")
    _raises(ds, "field 'images'", "lists 3 image(s)", "holds 4", "images/003.exr")
    ds2 = _copy(exr_ds, tmp_path / "b")
    _edit(ds2, lambda d: d["images"].pop())
    _raises(ds2, "lists 2 image(s)", "holds 3", "images/002.exr")


def test_duplicate_image_entry(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][2].__setitem__("file", "images/000.exr"))
    _raises(ds, "images[2].file", "listed twice")


def test_wrong_suffix_for_encoding(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d.__setitem__("encoding", "srgb"))
    _raises(ds, "images[0].file", "is not a .png/", "file")


def test_nan_pixels_warn_with_count_and_are_kept(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    f = ds / "images" / "001.exr"
    img = read_exr(f)
    img[3, 5, 1] = float("nan")
    img[7, 2, :] = float("inf")
    img[9, 9, 0] = float("nan")
    write_exr(f, img, allow_nonfinite=True)
    with pytest.warns(DatasetWarning, match=r"001\.exr: 3 of 1600 pixel\(s\) are NaN or inf"):
        d = load_dataset(ds)
    assert any("3 of 1600" in w for w in d.warnings)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DatasetWarning)
        p = d.load_images()[1]
    assert int(p.nonfinite.sum()) == 3 and bool(p.nonfinite[7, 2]) and torch.isnan(p.radiance[3, 5, 1])


def test_all_nan_image_is_an_error(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    write_exr(ds / "images" / "000.exr", torch.full((40, 40, 3), float("nan")), allow_nonfinite=True)
    _raises(ds, "000.exr", "every pixel (1600) is NaN or inf")


def test_camera_that_does_not_see_the_mesh(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)

    def turn_around(d):
        cam = d["images"][0]["camera"]
        R = np.array(cam["R"])
        flip = np.diag([-1.0, 1.0, -1.0])  # rotate 180° about the camera's y axis: looks away
        cam["R"] = (flip @ R).tolist()
        cam["t"] = (flip @ np.array(cam["t"])).tolist()

    _edit(ds, turn_around)
    _raises(ds, "images[0].camera", "does not see the mesh", "behind the camera")


def test_camera_sees_mesh_cases():
    mesh = uv_sphere(segments=16, rings=8)
    v = mesh.vertices
    front = look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 40.0, 32, 32)
    assert camera_sees_mesh(front, v)[0]
    aside = look_at((0.0, -4.0, 0.0), (30.0, -4.0, 0.0), (0.0, 0.0, 1.0), 40.0, 32, 32)  # looks along +x
    sees, why = camera_sees_mesh(aside, v, mesh.faces)  # the sphere straddles the camera plane, beside it
    assert not sees and "outside the 32×32 image" in why
    assert camera_sees_mesh(aside, v)[0]  # without faces: conservative
    inside = look_at((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 40.0, 32, 32)  # inside the sphere
    assert camera_sees_mesh(inside, v, mesh.faces)[0]
    # agrees with the ray-cast G-buffer on a sweep of view directions
    for ang in range(0, 360, 30):
        a = math.radians(ang)
        cam = look_at((0.0, -4.0, 0.0), (4 * math.sin(a), -4.0 + 4 * math.cos(a), 0.3), (0.0, 0.0, 1.0), 40.0, 32, 32)
        assert camera_sees_mesh(cam, v, mesh.faces)[0] == (len(render_gbuffer(mesh, cam)) > 0), ang


def test_mesh_without_uvs(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    lines = (ds / "mesh.obj").read_text().splitlines()
    out = []
    for ln in lines:
        if ln.startswith("vt "):
            continue
        if ln.startswith("f "):
            ln = "f " + " ".join(f"{c.split('/')[0]}//{c.split('/')[2]}" for c in ln.split()[1:])
        out.append(ln)
    (ds / "mesh.obj").write_text("\n".join(out) + "\n")
    _raises(ds, "field 'mesh'", "mesh.obj", "no per-vertex texture coordinates")


def test_unknown_gt_model(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["gt"].__setitem__("model", {"name": "phong-2000", "options": {}}))
    _raises(ds, "gt.model", "unknown model 'phong-2000'", "ggx-lambert")


def test_gt_maps_must_match_model(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["gt"]["maps"].pop("f0"))
    _raises(ds, "gt.maps", "missing ['f0']")


def test_gt_map_out_of_range(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    f = ds / "gt" / "roughness.exr"
    m = read_exr(f)
    m[0, 0] = 1.5
    write_exr(f, m)
    _raises(ds, "roughness.exr", "must lie in [0.0, 1.0]")


def test_region_ids_need_names(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["gt"]["regions"]["names"].pop("4"))
    _raises(ds, "gt.regions.names", "[4]")


def test_bad_saturation_and_bits(png_ds, tmp_path):
    ds = _copy(png_ds, tmp_path)
    _edit(ds, lambda d: d.__setitem__("saturation", 300))
    _raises(ds, "field 'saturation'", "[1, 255]")
    _edit(ds, lambda d: (d.__setitem__("saturation", 255), d.__setitem__("bits", 16)))
    _raises(ds, "000.png", "8-bit samples", "bits = 16")


def test_path_outside_dataset_rejected(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d.__setitem__("mesh", "../elsewhere/mesh.obj"))
    _raises(ds, "field 'mesh'", "stay inside it")


@pytest.mark.parametrize("what", ["image", "mesh", "images folder"])
def test_symlink_out_of_the_dataset_rejected(exr_ds, tmp_path, what):
    # the docs say a dataset's files stay inside its folder; a link must not lead out of it (an output folder
    # checked against the dataset folder would not protect the files it points to)
    ds = _copy(exr_ds, tmp_path)
    away = tmp_path / "elsewhere"
    away.mkdir()
    rel = {"image": "images/000.exr", "mesh": "mesh.obj", "images folder": "images"}[what]
    (ds / rel).rename(away / Path(rel).name)
    (ds / rel).symlink_to(away / Path(rel).name, target_is_directory=what == "images folder")
    field = "mesh" if what == "mesh" else "images[0].file"
    _raises(ds, f"field '{field}'", "outside the dataset folder through a symbolic link", str(away))


def test_symlink_inside_the_dataset_is_fine(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    (ds / "meshes").mkdir()
    (ds / "mesh.obj").rename(ds / "meshes" / "object.obj")
    (ds / "mesh.obj").symlink_to(Path("meshes") / "object.obj")
    load_dataset(ds, check_images=False)


@pytest.mark.parametrize("value", [1e-30, 1e-31, 1e30, 1e300])
def test_exposure_outside_float32_range(exr_ds, tmp_path, value):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][1].__setitem__("exposure", value))
    _raises(ds, "field 'images[1].exposure'", "overflow or vanish", "rescale")


def test_huge_light_intensity(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][2]["lights"][1].__setitem__("intensity", [1.0, 1e20, 1.0]))
    _raises(ds, "field 'images[2].lights[1].intensity'", "1e+20", "exposure")
    _edit(ds, lambda d: d["images"][2]["lights"][1].__setitem__("intensity", [1.0, 1e19, 1.0]))
    load_dataset(ds, check_images=False)


def test_camera_inside_the_mesh_warns(exr_ds, tmp_path):
    # a camera inside the object sees only its inside: every pixel is dropped; the view is named
    ds = _copy(exr_ds, tmp_path)
    _edit(ds, lambda d: d["images"][1]["camera"].__setitem__("t", [0.0, 0.0, 0.0]))  # centre -Rᵀt at the origin
    with pytest.warns(DatasetWarning, match=r"images\[1\]\.camera: the camera centre \(0, 0, 0\) is inside the mesh"):
        d = load_dataset(ds, check_images=False)
    assert len(d.warnings) == 1


def test_light_inside_the_mesh_warns(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)

    def inside(d):
        for view in d["images"]:
            view["lights"][0]["position"] = [0.0, 0.1, 0.2]

    _edit(ds, inside)
    with pytest.warns(DatasetWarning, match=r"images\[0\]\.lights\[0\], images\[1\]\.lights\[0\], "
                                            r"images\[2\]\.lights\[0\]: the point light at \(0, 0\.1, 0\.2\) is "
                                            r"inside the mesh"):
        d = load_dataset(ds, check_images=False)
    assert len(d.warnings) == 1  # one warning per position, naming every entry


def test_degenerate_faces_warn_with_their_count(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    with open(ds / "mesh.obj", "a") as fh:
        fh.write("f 1/1/1 1/1/1 2/2/2\nf 3/3/3 4/4/4 3/3/3\n")
    with pytest.warns(DatasetWarning, match=r"mesh\.obj: 2 of \d+ faces have zero area"):
        load_dataset(ds, check_images=False)


def test_inside_tests_by_hand():
    from capture.dataset import degenerate_faces, winding_numbers

    sphere = uv_sphere(segments=16, rings=8)
    w = winding_numbers(torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.3, -0.2], [0.0, 0.0, 1.5], [3.0, 0.0, 0.0]]),
                        sphere.vertices, sphere.faces)
    assert torch.allclose(w.abs(), torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-9)
    assert degenerate_faces(sphere.vertices, sphere.faces) == 0
    v = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2.0, 0.0, 0.0]])
    assert degenerate_faces(v, torch.tensor([[0, 1, 2], [0, 0, 1], [0, 1, 3]])) == 2  # repeated, collinear


# ------------------------------------------------------------------------------------------ atomic writes


def _tiny(width=16):
    mesh = uv_sphere(segments=12, rings=6)
    cam = look_at((0.0, -4.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 40.0, width, width)
    return mesh, [View(cam, [PointLight([0.0, -4.0, 2.0], 16.0)], 1.0)]


def test_write_then_load_minimal(tmp_path):
    mesh, views = _tiny()
    out = write_dataset(tmp_path / "ok", mesh, views, [torch.rand(16, 16, 3)])
    ds = load_dataset(out)
    assert ds.gt is None and len(ds) == 1 and ds.views[0].file == "images/000.exr"
    assert json.loads((out / "scene.json").read_text())["version"] == VERSION
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok"]  # no temp folder left


def test_failed_write_leaves_nothing(tmp_path):
    mesh, views = _tiny()
    away = look_at((0.0, -4.0, 0.0), (0.0, -8.0, 0.0), (0.0, 0.0, 1.0), 40.0, 16, 16)  # looks away from the sphere
    with pytest.raises(DatasetError, match=r"images\[0\]\.camera.*does not see the mesh.*nothing was written"):
        write_dataset(tmp_path / "bad", mesh, [View(away, views[0].lights, 1.0)], [torch.rand(16, 16, 3)])
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(DatasetError, match="is 8×8 but views"):
        write_dataset(tmp_path / "bad", mesh, views, [torch.rand(8, 8, 3)])
    with pytest.raises(DatasetError, match="gt.maps must hold exactly"):
        write_dataset(tmp_path / "bad", mesh, views, [torch.rand(16, 16, 3)],
                      gt=GroundTruth({"name": "lambert"}, {"f0": torch.zeros(4, 4, 3)}))
    with pytest.raises(DatasetError, match="gt.model"):
        write_dataset(tmp_path / "bad", mesh, views, [torch.rand(16, 16, 3)],
                      gt=GroundTruth({"name": "nope"}, {}))
    assert list(tmp_path.iterdir()) == []


def test_existing_folder_protected_and_overwrite_atomic(tmp_path):
    mesh, views = _tiny()
    out = write_dataset(tmp_path / "d", mesh, views, [torch.full((16, 16, 3), 0.25)])
    with pytest.raises(DatasetError, match="already exists"):
        write_dataset(out, mesh, views, [torch.full((16, 16, 3), 0.5)])
    assert float(read_exr(out / "images" / "000.exr")[0, 0, 0]) == 0.25
    # a failing overwrite keeps the old dataset
    away = look_at((0.0, -4.0, 0.0), (0.0, -8.0, 0.0), (0.0, 0.0, 1.0), 40.0, 16, 16)
    with pytest.raises(DatasetError):
        write_dataset(out, mesh, [View(away, views[0].lights, 1.0)], [torch.rand(16, 16, 3)], overwrite=True)
    assert float(read_exr(out / "images" / "000.exr")[0, 0, 0]) == 0.25
    write_dataset(out, mesh, views, [torch.full((16, 16, 3), 0.5)], overwrite=True)
    assert float(read_exr(out / "images" / "000.exr")[0, 0, 0]) == 0.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def test_exposure_divides(tmp_path):
    mesh, views = _tiny()
    views[0].exposure = 4.0
    out = write_dataset(tmp_path / "e", mesh, views, [torch.full((16, 16, 3), 0.5)], saturation=1.0)
    ds = load_dataset(out)
    p = ds.load_images()[0]
    assert torch.all(p.radiance == 0.125) and not p.saturated.any()
    assert math.isclose(ds.saturation_linear(), 1.0)


def test_linear_saturation_mask(tmp_path):
    mesh, views = _tiny()
    img = torch.full((16, 16, 3), 0.5)
    img[2, 3, 1] = 1.0
    img[4, 4, :] = 0.999
    out = write_dataset(tmp_path / "s", mesh, views, [img], saturation=1.0)
    sat = load_dataset(out).load_images()[0].saturated
    assert sat.sum() == 1 and sat[2, 3]


def test_camera_dict_round_trip_is_exact():
    cam = look_at((0.3, -4.1, 1.7), (0.0, 0.1, 0.0), (0.0, 0.0, 1.0), 37.0, 64, 48)
    back = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert torch.equal(back.K, cam.K) and torch.equal(back.R, cam.R) and torch.equal(back.t, cam.t)


def test_model_written_as_the_project_prints_it_is_read_back():
    """`--model` takes the spelling the project prints: a sum of parts, each with options in parentheses; the label
    of a spec reads back to the same spec and model; malformed spellings are named."""
    from capture.dataset import model_from_spec, model_label, model_spec

    spec = model_spec("lambert+microfacet(D=ggx,G=smith,F=none)")
    assert spec == {"sum": [{"name": "lambert", "options": {}},
                            {"name": "microfacet", "options": {"D": "ggx", "G": "smith", "F": "none"}}]}
    m = model_from_spec(spec)
    assert m.name == "lambert+microfacet(D=ggx, F=none, G=smith)" == model_label(spec)
    assert model_spec(m.name) == spec and model_from_spec(m.name).param_names == ("albedo", "f0", "roughness")
    assert model_spec("gotanda2012-layered(exact=true)") == {"name": "gotanda2012-layered",
                                                              "options": {"exact": True}}
    assert model_spec("x(a=1e+3, b=2)")["options"] == {"a": 1000.0, "b": 2}       # '+' inside a value stays
    for bad, word in (("lambert+", "empty part"), ("microfacet(D=ggx", "unbalanced"), ("microfacet(D)", "key=value"),
                      ("microfacet(D=a,D=b)", "twice"), ("(D=ggx)", "no model name")):
        with pytest.raises(ValueError, match=word):
            model_spec(bad)
    with pytest.raises(ValueError, match="unknown model 'nope'"):
        model_from_spec("lambert+nope(a=1)")


# ------------------------------------------------------------------------------------------ masks, JPEG, TIFF


def test_write_dataset_masks_round_trip(png_ds, tmp_path):
    ds = load_dataset(png_ds)
    imgs = [ds.read_file_image(i) for i in range(len(ds))]
    masks = [torch.zeros(v.camera.height, v.camera.width, dtype=torch.bool) for v in ds.views]
    masks[0][:, :10] = True
    out = write_dataset(tmp_path / "m", ds.mesh, ds.views, imgs, encoding="srgb", masks=[masks[0], None, masks[2]])
    with pytest.warns(DatasetWarning, match=r"images\[2\]: the mask excludes every pixel"):
        back = load_dataset(out)
    assert back.views[0].mask == "masks/000.png" and back.views[1].mask == ""
    photos = back.load_images()
    assert torch.equal(photos[0].mask, masks[0]) and bool(photos[1].mask.all()) and not bool(photos[2].mask.any())
    assert torch.equal(photos[0].unusable, photos[0].saturated | ~masks[0])
    with pytest.raises(DatasetError, match="masks must hold one entry"):
        write_dataset(tmp_path / "x", ds.mesh, ds.views, imgs, encoding="srgb", masks=[None])


def test_mask_errors_are_named(png_ds, tmp_path):
    ds = _copy(png_ds, tmp_path)
    _edit(ds, lambda d: d["images"][1].__setitem__("mask", "masks/001.png"))
    _raises(ds, "images[1].mask", "does not exist")
    (ds / "masks").mkdir()
    write_png(ds / "masks" / "001.png", torch.ones(8, 8), transfer="linear")
    _raises(ds, "001.png", "mask is 8×8")
    write_png(ds / "masks" / "001.png", torch.zeros(40, 40), transfer="linear")
    with pytest.warns(DatasetWarning, match="excludes every pixel"):
        load_dataset(ds)


def test_rgba_png_alpha_is_the_mask(png_ds, tmp_path):
    ds = _copy(png_ds, tmp_path)
    img = read_png(ds / "images" / "000.png")
    alpha = torch.zeros(40, 40, 1)
    alpha[20:] = 1.0
    write_png(ds / "images" / "000.png", torch.cat([img, alpha], -1))
    photos = load_dataset(ds).load_images()
    assert torch.equal(photos[0].mask, alpha[..., 0] > 0.5)
    assert torch.allclose(photos[0].radiance * 1.5, img, atol=1e-6)


def test_jpeg_warns_and_16bit_tiff_reads(png_ds, tmp_path):
    import cv2

    ds = _copy(png_ds, tmp_path)
    codes = cv2.imread(str(ds / "images" / "000.png"), cv2.IMREAD_UNCHANGED)
    (ds / "images" / "000.png").unlink()
    cv2.imwrite(str(ds / "images" / "000.jpg"), codes, [cv2.IMWRITE_JPEG_QUALITY, 100])
    _edit(ds, lambda d: d["images"][0].__setitem__("file", "images/000.jpg"))
    with pytest.warns(DatasetWarning, match="JPEG.*not pure sRGB"):
        loaded = load_dataset(ds)
    assert (loaded.read_file_image(0) - read_png(png_ds / "images" / "000.png")).abs().mean() < 0.01
    _edit(ds, lambda d: d.__setitem__("bits", 16))
    with pytest.warns(DatasetWarning, match="JPEG"):
        _raises(ds, "000.jpg", "JPEG has 8-bit samples", "bits = 16")
    # 16-bit TIFF holding linear values
    lin = tmp_path / "lin"
    shutil.copytree(png_ds, lin)
    for i in range(3):
        img = read_png(lin / "images" / f"{i:03d}.png")
        (lin / "images" / f"{i:03d}.png").unlink()
        cv2.imwrite(str(lin / "images" / f"{i:03d}.tif"), np.rint(img.numpy() * 65535).astype(np.uint16)[:, :, ::-1])
    _edit(lin, lambda d: (d.__setitem__("encoding", "linear"), d.__setitem__("saturation", 1.0), d.pop("bits"),
                          [e.__setitem__("file", e["file"].replace(".png", ".tif")) for e in d["images"]]))
    back = load_dataset(lin)
    assert (back.read_file_image(1) - read_png(png_ds / "images" / "001.png")).abs().max() <= 0.5 / 65535 + 1e-7
    cv2.imwrite(str(lin / "images" / "001.tif"), np.zeros((40, 40, 3), np.uint8))
    _raises(lin, "001.tif", "8-bit samples, too coarse for linear")


def test_light_in_the_camera_frame_resolved_at_load(exr_ds, tmp_path):
    ds = _copy(exr_ds, tmp_path)
    base = load_dataset(ds)
    cam = base.views[0].camera.to(torch.float64)
    world = base.views[0].lights[0].position.double().reshape(3)
    p_cam = (cam.R @ world + cam.t).tolist()
    _edit(ds, lambda d: d["images"][0]["lights"][0].update({"frame": "camera", "position": p_cam}))
    got = load_dataset(ds).views[0].lights[0].position.double().reshape(3)
    assert torch.allclose(got, world, atol=1e-5)
    _edit(ds, lambda d: d["images"][0]["lights"][0].update({"frame": "sensor"}))
    _raises(ds, "images[0].lights[0]", "'frame' must be one of")
