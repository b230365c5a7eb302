"""Importers: COLMAP (text and binary), transforms.json and OpenCV YAML captures written in each tool's own
documented format from a known synthetic scene, imported, and compared with the scene they came from."""

import dataclasses
import json
import math
import struct
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from capture.dataset import DatasetWarning, load_dataset
from capture.importers import (
    CaptureImportError,
    Flash,
    ImportOptions,
    import_colmap,
    import_opencv_yaml,
    import_transforms_json,
    read_colmap_model,
)
from capture.observations import observe_views
from capture.synth import build_scene, render_scene, small_scene
from renderer.camera import Camera
from renderer.gbuffer import render_gbuffer
from renderer.imageio import encode, read_exr, write_exr, write_png
from renderer.mesh import save_mesh
from renderer.shading import prepare

SIZE = 64
#: the flash in the camera frame (x right, y down, z forward): a little right of and above the lens
FLASH = (0.12, -0.08, 0.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A lit lambert sphere: 3 views of 64², a flash fixed to each camera, linear radiance images."""
    cfg = small_scene("lambert", image_size=SIZE, texture_size=32, n_views=3, supersample=2, n_lights=1)
    sc = build_scene(cfg)
    views = []
    for v in sc.views:
        d2 = float(v.camera.center.double().norm()) ** 2
        flash = Flash(FLASH, d2)
        views.append(dataclasses.replace(v, lights=[flash.to_world(v.camera.to(torch.float64))]))
    sc = dataclasses.replace(sc, views=views)
    images, _ = render_scene(sc, cfg)
    root = tmp_path_factory.mktemp("scene")
    save_mesh(sc.mesh, root / "mesh.obj")
    return {"scene": sc, "images": images, "mesh": root / "mesh.obj",
            "intensity": [float(v.camera.center.double().norm()) ** 2 for v in sc.views]}


def _cams(scene):
    return [v.camera.to(torch.float64) for v in scene["scene"].views]


def _flash(scene, i=0):
    return Flash(FLASH, scene["intensity"][i])


def _write_photos(scene, folder: Path, kind: str, alpha=None) -> list[str]:
    """The rendered images as camera files: png (8-bit sRGB), jpg (quality 95), exr, tif16 (linear), rgba."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, img in enumerate(scene["images"]):
        img = img.clamp(0, 1)
        if kind == "png":
            name = f"view_{i:03d}.png"
            write_png(folder / name, img)
        elif kind == "rgba":
            name = f"view_{i:03d}.png"
            write_png(folder / name, torch.cat([img, alpha[i][..., None].float()], -1))
        elif kind == "jpg":
            name = f"view_{i:03d}.jpg"
            codes = np.rint(encode(img).numpy() * 255).astype(np.uint8)[:, :, ::-1]
            assert cv2.imwrite(str(folder / name), codes, [cv2.IMWRITE_JPEG_QUALITY, 95])
        elif kind == "exr":
            name = f"view_{i:03d}.exr"
            write_exr(folder / name, img)
        elif kind == "tif16":
            name = f"view_{i:03d}.tif"
            assert cv2.imwrite(str(folder / name), np.rint(img.numpy() * 65535).astype(np.uint16)[:, :, ::-1])
        names.append(name)
    return names


# -- each tool's format, written from shadecap cameras ------------------------------------------------------------


def _colmap_pose(cam: Camera):
    R = cam.R.double().numpy()
    x, y, z, w = Rotation.from_matrix(R).as_quat()  # scipy: scalar last
    return (w, x, y, z), cam.t.double().numpy()


def write_colmap_text(folder: Path, cams, names, dist=None):
    """cameras.txt / images.txt as COLMAP documents them (doc/format.rst): PINHOLE or OPENCV cameras, principal
    point in COLMAP's image coordinates (top-left pixel centre at (0.5, 0.5))."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cams)}"]
    for k, cam in enumerate(cams, 1):
        K = cam.K.double().numpy()
        p = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        model = "PINHOLE" if dist is None else "OPENCV"
        p += [] if dist is None else list(dist)
        lines.append(f"{k} {model} {cam.width} {cam.height} " + " ".join(repr(float(x)) for x in p))
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, "
             "NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(cams)}"]
    for k, (cam, name) in enumerate(zip(cams, names, strict=True), 1):
        q, t = _colmap_pose(cam)
        lines.append(f"{k} " + " ".join(repr(float(x)) for x in (*q, *t)) + f" {k} {name}")
        lines.append("10.5 20.5 -1 30.25 12.0 7" if k % 2 else "")  # 2-D points, or none
    (folder / "images.txt").write_text("\n".join(lines) + "\n")


def write_colmap_binary(folder: Path, cams, names):
    """cameras.bin / images.bin in COLMAP's binary layout (little endian): uint64 count; per camera int32 id,
    int32 model id, uint64 width, height, float64 params; per image int32 id, float64 qw qx qy qz tx ty tz,
    int32 camera id, the name NUL-terminated, uint64 point count, per point float64 x, y and int64 point3D id."""
    folder.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<Q", len(cams))
    for k, cam in enumerate(cams, 1):
        K = cam.K.double().numpy()
        data += struct.pack("<iiQQ", k, 1, cam.width, cam.height)  # model 1 = PINHOLE
        data += struct.pack("<4d", K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5)
    (folder / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(cams))
    for k, (cam, name) in enumerate(zip(cams, names, strict=True), 1):
        q, t = _colmap_pose(cam)
        data += struct.pack("<idddddddi", k, *q, *t, k) + name.encode() + b"\0"
        pts = [(10.5, 20.5, -1), (3.0, 4.0, 17)][: k % 3]
        data += struct.pack("<Q", len(pts)) + b"".join(struct.pack("<ddq", *p) for p in pts)
    (folder / "images.bin").write_bytes(data)


def write_transforms(path: Path, cams, names, angle_only=False, dist=None):
    """transforms.json as instant-ngp / nerfstudio write it: camera-to-world in the OpenGL camera frame, fl_x/fl_y/
    cx/cy (corner-origin pixel coordinates, as colmap2nerf copies them from COLMAP) or camera_angle_x only."""
    frames = []
    for cam, name in zip(cams, names, strict=True):
        c2w = np.eye(4)
        c2w[:3, :3] = cam.R.double().numpy().T @ np.diag([1.0, -1.0, -1.0])
        c2w[:3, 3] = cam.center.double().numpy()
        frames.append({"file_path": "./" + str(Path(name).with_suffix("")), "transform_matrix": c2w.tolist()})
    K = cams[0].K.double().numpy()
    W, H = cams[0].width, cams[0].height
    doc = {"camera_angle_x": 2 * math.atan(0.5 * W / K[0, 0])} if angle_only else {
        "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5, "w": W, "h": H}
    if dist is not None:
        doc.update(dict(zip(("k1", "k2", "p1", "p2"), dist, strict=True)))
    doc["aabb_scale"] = 4
    doc["frames"] = frames
    path.write_text(json.dumps(doc, indent=2))


def write_opencv_yaml(path: Path, cams, names, dist=None, rvec=True):
    """The layout import_opencv_yaml documents, written by cv2.FileStorage."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", cams[0].width)
    fs.write("image_height", cams[0].height)
    fs.write("camera_matrix", cams[0].K.double().numpy())
    fs.write("distortion_coefficients", np.zeros((1, 5)) if dist is None else np.asarray(dist, float).reshape(1, -1))
    fs.startWriteStruct("images", cv2.FileNode_SEQ)
    for k, (cam, name) in enumerate(zip(cams, names, strict=True)):
        fs.startWriteStruct("", cv2.FileNode_MAP)
        fs.write("file", name)
        R = cam.R.double().numpy()
        if rvec and k % 2 == 0:
            fs.write("rvec", cv2.Rodrigues(R)[0])
            fs.write("tvec", cam.t.double().numpy().reshape(3, 1))
        else:
            fs.write("R", R)
            fs.write("t", cam.t.double().numpy().reshape(3, 1))
        fs.endWriteStruct()
    fs.endWriteStruct()
    fs.release()


# -- checks ------------------------------------------------------------------------------------------------------


def _assert_same_cameras(ds, scene):
    verts = scene["scene"].mesh.vertices.double()
    for got, want in zip(ds.cameras, _cams(scene), strict=True):
        a, za = got.to(torch.float64).project(verts)
        b, zb = want.project(verts)
        assert (a - b).abs().max() < 1e-3, (a - b).abs().max()
        assert (za - zb).abs().max() < 1e-6
        assert (got.width, got.height) == (want.width, want.height)


def _assert_flash(ds, scene):
    for i, (view, cam) in enumerate(zip(ds.views, _cams(scene), strict=True)):
        want = cam.center + cam.R.T @ torch.tensor(FLASH, dtype=torch.float64)
        (light,) = view.lights
        assert torch.allclose(light.position.double().reshape(3), want, atol=1e-5)
        want_i = torch.full((3,), scene["intensity"][i], dtype=torch.float64)
        assert torch.allclose(light.intensity.double().reshape(3), want_i, rtol=1e-5)


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_colmap_cameras_and_flash(scene, tmp_path, kind):
    names = _write_photos(scene, tmp_path / "images", "png")
    model = tmp_path / "sparse" / "0"
    (write_colmap_text if kind == "text" else write_colmap_binary)(model, _cams(scene), names)
    assert read_colmap_model(model)[2] == kind
    opts = ImportOptions(mesh=scene["mesh"], images=tmp_path / "images", flash=[_flash(scene)])
    res = import_colmap(model, tmp_path / "ds", opts)
    assert res.n_images == 3 and res.encoding == "srgb" and res.bits == 8 and not res.undistorted
    ds = load_dataset(tmp_path / "ds")
    _assert_same_cameras(ds, scene)
    # the flash intensity is one value for all views here: compare positions, and the first view's intensity
    for view, cam in zip(ds.views, _cams(scene), strict=True):
        want = cam.center + cam.R.T @ torch.tensor(FLASH, dtype=torch.float64)
        assert torch.allclose(view.lights[0].position.double().reshape(3), want, atol=1e-5)
    # the PNG files are copied byte for byte
    for v, name in zip(ds.views, names, strict=True):
        assert (tmp_path / "ds" / v.file).read_bytes() == (tmp_path / "images" / name).read_bytes()
        assert v.name == name


@pytest.mark.parametrize("angle_only", [False, True])
def test_transforms_json_cameras(scene, tmp_path, angle_only):
    names = _write_photos(scene, tmp_path / "cap" / "train", "exr")
    write_transforms(tmp_path / "cap" / "transforms.json", _cams(scene), ["train/" + n for n in names], angle_only)
    flashes = [_flash(scene)]
    res = import_transforms_json(tmp_path / "cap" / "transforms.json", tmp_path / "ds",
                                 ImportOptions(mesh=scene["mesh"], flash=flashes))
    assert res.encoding == "linear"
    ds = load_dataset(tmp_path / "ds")
    _assert_same_cameras(ds, scene)
    photos = ds.load_images()
    assert torch.allclose(photos[1].radiance, scene["images"][1].clamp(0, 1), atol=1e-6)


def test_opencv_yaml_cameras_16bit_tiff(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "cap", "tif16")
    write_opencv_yaml(tmp_path / "cap" / "calib.yaml", _cams(scene), names)
    res = import_opencv_yaml(tmp_path / "cap" / "calib.yaml", tmp_path / "ds",
                             ImportOptions(mesh=scene["mesh"], flash=_flash(scene)))
    assert res.encoding == "linear" and res.bits == 16
    ds = load_dataset(tmp_path / "ds")
    _assert_same_cameras(ds, scene)
    photos = ds.load_images()
    assert (photos[0].radiance - scene["images"][0].clamp(0, 1)).abs().max() < 1.0 / 65535
    assert ds.saturation == 1.0


def test_per_view_flash_intensity_and_camera_frame_lights_at_load(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "images", "png")
    write_colmap_text(tmp_path / "m", _cams(scene), names)
    import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(mesh=scene["mesh"], images=tmp_path / "images",
                                                                    flash=_flash(scene)))
    doc = json.loads((tmp_path / "ds" / "scene.json").read_text())
    for i, e in enumerate(doc["images"]):  # the same flash written by hand in the camera frame
        e["lights"] = [{"type": "point", "frame": "camera", "position": list(FLASH),
                        "intensity": scene["intensity"][i]}]
    (tmp_path / "ds" / "scene.json").write_text(json.dumps(doc))
    _assert_flash(load_dataset(tmp_path / "ds"), scene)
    doc["images"][0]["lights"][0]["frame"] = "lens"
    (tmp_path / "ds" / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"images\[0\]\.lights\[0\].*frame"):
        load_dataset(tmp_path / "ds")


def _distort(img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The photo a lens with ``dist`` takes of the pinhole image ``img``: D(p_d) = U(undistort(p_d))."""
    H, W = img.shape[:2]
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([xs.ravel(), ys.ravel()], -1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, K, dist, P=K,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(H, W, 2)
    return cv2.remap(img, und[..., 0].astype(np.float32), und[..., 1].astype(np.float32), cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_REPLICATE)


def test_distorted_photo_undistorts_back(scene, tmp_path):
    cams = _cams(scene)
    K = cams[0].K.double().numpy()
    dist = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
    (tmp_path / "cap").mkdir()
    names = []
    xs, ys = np.meshgrid(np.arange(SIZE), np.arange(SIZE))
    wall = torch.from_numpy(0.3 + 0.2 * np.sin(2 * np.pi * xs / 16) * np.sin(2 * np.pi * ys / 14)).float()[..., None]
    truth = []
    for i, img in enumerate(scene["images"]):  # the object in front of a textured wall: content up to the corners
        truth.append(torch.where(img.sum(-1, keepdim=True) > 0, img, wall.expand(SIZE, SIZE, 3)))
        names.append(f"d{i}.exr")
        write_exr(tmp_path / "cap" / names[-1], _distort(truth[-1].numpy(), K, dist))
    write_opencv_yaml(tmp_path / "cap" / "calib.yml", cams, names, dist=dist)
    res = import_opencv_yaml(tmp_path / "cap" / "calib.yml", tmp_path / "ds",
                             ImportOptions(mesh=scene["mesh"], flash=_flash(scene)))
    assert res.undistorted == 3 and res.masks == 3
    ds = load_dataset(tmp_path / "ds")
    _assert_same_cameras(ds, scene)  # the same K: the undistorted photos are the pinhole camera's
    photos = ds.load_images()
    for p, want, name in zip(photos, truth, names, strict=True):
        m = p.mask
        assert m.float().mean() > 0.8  # the corners the lens never saw are masked out
        err = (p.radiance - want)[m].abs()
        raw = (read_exr(tmp_path / "cap" / name) - want)[m].abs()
        assert err.mean() < 0.2 * raw.mean(), (err.mean(), raw.mean())  # measured 0.15: bilinear blur only
        assert err.max() < 0.6 * raw.max(), (err.max(), raw.max())  # the silhouette edges, blurred twice
    with pytest.warns(DatasetWarning, match="distortion"):  # off: taken as already undistorted
        res = import_opencv_yaml(tmp_path / "cap" / "calib.yml", tmp_path / "ds2",
                                 ImportOptions(mesh=scene["mesh"], flash=_flash(scene), undistort=False))
    assert res.undistorted == 0


def _half_masks(scene, folder: Path, names):
    folder.mkdir()
    masks = []
    for name in names:
        m = np.zeros((SIZE, SIZE), np.uint8)
        m[:, SIZE // 2:] = 255
        cv2.imwrite(str(folder / (Path(name).stem + ".png")), m)
        masks.append(torch.from_numpy(m > 0))
    return masks


def test_masks_exclude_pixels_from_the_observations(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "images", "png")
    write_colmap_text(tmp_path / "m", _cams(scene), names)
    masks = _half_masks(scene, tmp_path / "masks", names)
    res = import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(
        mesh=scene["mesh"], images=tmp_path / "images", masks=tmp_path / "masks", flash=_flash(scene)))
    assert res.masks == 3
    ds = load_dataset(tmp_path / "ds")
    photos = ds.load_images()
    for p, m in zip(photos, masks, strict=True):
        assert torch.equal(p.mask, m)
        assert torch.equal(p.unusable, p.saturated | ~m)
    preps = [prepare(render_gbuffer(ds.mesh, v.camera, 1), ds.mesh, v.lights) for v in ds.views]
    lights = [v.lights[0] for v in ds.views]
    rad = [p.radiance for p in photos]
    full = observe_views(preps, rad, (32, 32), exposure=1.0, clipped=[p.saturated for p in photos], lights=lights)
    kept = observe_views(preps, rad, (32, 32), exposure=1.0, clipped=[p.unusable for p in photos], lights=lights)
    assert (full.pixel % SIZE < SIZE // 2).any()
    assert not (kept.pixel % SIZE < SIZE // 2).any()  # no sample from a masked-out pixel
    assert 0.3 * full.n_samples < kept.n_samples < 0.7 * full.n_samples
    assert kept.drops["clipped"] - full.drops["clipped"] >= full.n_samples - kept.n_samples


def test_rgba_alpha_is_the_mask(scene, tmp_path):
    alpha = [torch.zeros(SIZE, SIZE, dtype=torch.bool) for _ in scene["images"]]
    for a in alpha:
        a[: SIZE // 3] = True
    names = _write_photos(scene, tmp_path / "images", "rgba", alpha)
    write_colmap_text(tmp_path / "m", _cams(scene), names)
    with pytest.raises(CaptureImportError, match="alpha"):  # masks='alpha' needs an alpha channel
        other = _write_photos(scene, tmp_path / "rgb", "png")
        write_colmap_text(tmp_path / "m2", _cams(scene), other)
        import_colmap(tmp_path / "m2", tmp_path / "x", ImportOptions(mesh=scene["mesh"], images=tmp_path / "rgb",
                                                                       masks="alpha", flash=_flash(scene)))
    import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(mesh=scene["mesh"], images=tmp_path / "images",
                                                                    masks="alpha", flash=_flash(scene)))
    photos = load_dataset(tmp_path / "ds").load_images()
    for p, a in zip(photos, alpha, strict=True):
        assert torch.equal(p.mask, a)


def test_jpeg_loads_with_the_warning(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "images", "jpg")
    write_colmap_binary(tmp_path / "m", _cams(scene), names)
    res = import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(mesh=scene["mesh"], images=tmp_path / "images",
                                                                          flash=_flash(scene)))
    assert any("JPEG" in w for w in res.warnings)
    with pytest.warns(DatasetWarning, match="JPEG.*not pure sRGB"):
        ds = load_dataset(tmp_path / "ds")
    assert ds.views[0].file.endswith(".jpg")
    photos = ds.load_images()
    err = (photos[0].radiance - scene["images"][0].clamp(0, 1)).abs()
    assert err.mean() < 0.01


def test_bad_input_is_named(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "images", "png")
    write_colmap_text(tmp_path / "m", _cams(scene), names)
    with pytest.raises(CaptureImportError, match="no lights"):
        ImportOptions(mesh=scene["mesh"])
    with pytest.raises(CaptureImportError, match="mesh file does not exist"):
        ImportOptions(mesh=tmp_path / "nope.obj", flash=_flash(scene))
    with pytest.raises(CaptureImportError, match="--images"):
        import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(mesh=scene["mesh"], flash=_flash(scene)))
    text = (tmp_path / "m" / "cameras.txt").read_text().replace("PINHOLE 64 64", "OPENCV_FISHEYE 64 64")
    text = "\n".join(ln + (" 0 0 0 0" if "FISHEYE" in ln else "") for ln in text.splitlines())
    (tmp_path / "m2").mkdir()
    (tmp_path / "m2" / "cameras.txt").write_text(text)
    (tmp_path / "m2" / "images.txt").write_text((tmp_path / "m" / "images.txt").read_text())
    opts = ImportOptions(mesh=scene["mesh"], images=tmp_path / "images", flash=_flash(scene))
    with pytest.raises(CaptureImportError, match="OPENCV_FISHEYE.*image_undistorter"):
        import_colmap(tmp_path / "m2", tmp_path / "ds", opts)
    small = tmp_path / "small"
    small.mkdir()
    for n in names:
        write_png(small / n, torch.zeros(32, 32, 3))
    with pytest.raises(CaptureImportError, match="32×32 px but its camera is 64×64"):
        import_colmap(tmp_path / "m", tmp_path / "ds", dataclasses.replace(opts, images=small))
    with pytest.raises(CaptureImportError, match="already exists"):
        (tmp_path / "exists").mkdir()
        import_colmap(tmp_path / "m", tmp_path / "exists", opts)
    assert not (tmp_path / "ds").exists()


def _obj_without_uvs(mesh, path: Path):
    v = mesh.vertices.double().numpy()
    f = mesh.faces.numpy() + 1
    lines = [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in v] + [f"f {a} {b} {c}" for a, b, c in f]
    path.write_text("\n".join(lines))


def test_mesh_without_uvs_needs_unwrap(scene, tmp_path, monkeypatch):
    names = _write_photos(scene, tmp_path / "images", "png")
    write_colmap_text(tmp_path / "m", _cams(scene), names)
    _obj_without_uvs(scene["scene"].mesh, tmp_path / "bare.obj")
    opts = ImportOptions(mesh=tmp_path / "bare.obj", images=tmp_path / "images", flash=_flash(scene))
    with pytest.raises(CaptureImportError, match="--unwrap"):
        import_colmap(tmp_path / "m", tmp_path / "ds", opts)
    with monkeypatch.context() as mp:  # xatlas missing: the message says how to install it
        mp.setitem(sys.modules, "xatlas", None)
        with pytest.raises(CaptureImportError, match="pip install xatlas"):
            import_colmap(tmp_path / "m", tmp_path / "ds", dataclasses.replace(opts, unwrap=True))
    pytest.importorskip("xatlas")
    res = import_colmap(tmp_path / "m", tmp_path / "ds", dataclasses.replace(opts, unwrap=True))
    assert res.unwrapped
    ds = load_dataset(tmp_path / "ds")
    assert ds.mesh.uvs.min() >= 0 and ds.mesh.uvs.max() <= 1
    _assert_same_cameras(ds, scene)


def test_end_to_end_colmap_flash_jpeg_masks_reconstruct(scene, tmp_path):
    """A COLMAP model + a flash + JPEG photos + masks: one import command, then reconstruct, no glue."""
    from capture.cli import main
    from capture.reconstruct import reconstruct

    names = _write_photos(scene, tmp_path / "images", "jpg")
    write_colmap_binary(tmp_path / "sparse", _cams(scene), names)
    masks = tmp_path / "masks"
    masks.mkdir()
    for i, n in enumerate(names):  # the object's silhouette, a little eroded, as a segmentation tool gives it
        g = render_gbuffer(scene["scene"].mesh, _cams(scene)[i], 1)
        m = np.zeros(SIZE * SIZE, np.uint8)
        m[g.pixel.numpy()] = 255
        m = cv2.erode(m.reshape(SIZE, SIZE), np.ones((3, 3), np.uint8))
        cv2.imwrite(str(masks / (n + ".png")), m)  # COLMAP's own mask naming: <image name>.png
    inten = scene["intensity"][0]
    rc = main(["import", "colmap", str(tmp_path / "sparse"), "--images", str(tmp_path / "images"), "--mesh",
               str(scene["mesh"]), "--masks", str(masks), "--flash", ",".join(map(str, FLASH)),
               "--flash-intensity", str(inten), "--out", str(tmp_path / "ds")])
    assert rc == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DatasetWarning)
        reconstruct(tmp_path / "ds", model="lambert", out_dir=tmp_path / "rec", texture_size=32, progress=False,
                    threads=1)
    albedo = read_exr(tmp_path / "rec" / "albedo.exr")
    observed = read_exr(tmp_path / "rec" / "coverage.exr")[..., 2] > 0.5
    # observable texels: albedo's posterior std below 0.01 (docs/conventions.md); the rest are fills
    std = read_exr(tmp_path / "rec" / "confidence_albedo.exr")
    observable = torch.isfinite(std).all(-1) & (std.amax(-1) < 0.01)
    gt = scene["scene"].maps["albedo"]
    scale = [i / inten for i in scene["intensity"]]  # one flash intensity fits every view (equal distances)
    assert max(scale) - min(scale) < 1e-6
    assert observed.float().mean() > 0.5 and observable.sum() >= 20
    err = (albedo - gt)[observable].abs()
    assert err.mean() < 0.03 and err.max() < 0.15, (err.mean(), err.max())  # measured 0.013, 0.11


def test_lights_option_in_the_camera_frame_equals_the_flash(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "images", "png")
    write_colmap_text(tmp_path / "m", _cams(scene), names)
    light = {"type": "point", "frame": "camera", "position": list(FLASH), "intensity": scene["intensity"][0]}
    import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(mesh=scene["mesh"], images=tmp_path / "images",
                                                                    lights=[light]))
    ds = load_dataset(tmp_path / "ds")
    for view, cam in zip(ds.views, _cams(scene), strict=True):
        want = cam.center + cam.R.T @ torch.tensor(FLASH, dtype=torch.float64)
        assert torch.allclose(view.lights[0].position.double().reshape(3), want, atol=1e-5)
    with pytest.raises(CaptureImportError, match=r"lights\[0\].*sh.*camera frame"):
        ImportOptions(mesh=scene["mesh"], lights=[{"type": "sh", "frame": "camera", "coeffs": [[0.0] * 3] * 9}])


def _wall_scene_photos(scene):
    """The renders in front of a smooth textured wall: content up to the image corners."""
    xs, ys = np.meshgrid(np.arange(SIZE), np.arange(SIZE))
    wall = torch.from_numpy(0.3 + 0.2 * np.sin(2 * np.pi * xs / 16) * np.sin(2 * np.pi * ys / 14)).float()[..., None]
    return [torch.where(img.sum(-1, keepdim=True) > 0, img, wall.expand(SIZE, SIZE, 3)) for img in scene["images"]]


def _tree(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("source", ["colmap", "transforms"])
def test_distorted_srgb_photos_undistort_to_16bit_png(scene, tmp_path, source):
    """COLMAP OPENCV cameras and transforms.json k1/k2 with 8-bit sRGB photos: written back as 16-bit sRGB PNG."""
    cams = _cams(scene)
    K = cams[0].K.double().numpy()
    dist = [-0.2, 0.05, 0.001, -0.0005]
    truth = _wall_scene_photos(scene)
    cap = tmp_path / "cap"
    cap.mkdir()
    names = []
    for i, img in enumerate(truth):
        names.append(f"p{i}.png")
        write_png(cap / names[-1], torch.from_numpy(_distort(img.numpy(), K, np.array(dist + [0.0]))))
    if source == "colmap":
        write_colmap_text(cap / "model", cams, names, dist=dist)
        (cap / "masks").mkdir()
        for n in names:  # everything usable but the top rows
            m = np.full((SIZE, SIZE), 255, np.uint8)
            m[:4] = 0
            cv2.imwrite(str(cap / "masks" / (n + ".png")), m)
        opts = ImportOptions(mesh=scene["mesh"], images=cap, masks=cap / "masks", flash=_flash(scene))
    else:
        write_transforms(cap / "transforms.json", cams, names, dist=dist)
        opts = ImportOptions(mesh=scene["mesh"], flash=_flash(scene))
    before = _tree(cap)
    fn = import_colmap if source == "colmap" else import_transforms_json
    res = fn(cap / "model" if source == "colmap" else cap / "transforms.json", tmp_path / "ds", opts)
    assert _tree(cap) == before  # the inputs are never modified
    assert res.undistorted == 3 and res.encoding == "srgb" and res.bits == 16
    ds = load_dataset(tmp_path / "ds")
    assert ds.bits == 16 and ds.saturation == 65535 and ds.views[0].file.endswith(".png")
    _assert_same_cameras(ds, scene)
    for p, want in zip(ds.load_images(), truth, strict=True):
        if source == "colmap":
            assert not p.mask[:3].any()  # the user's mask, undistorted with it
        err = (p.radiance - want)[p.mask].abs().mean()
        assert err < 0.006, err  # 8-bit quantisation and two interpolations


def test_a_failed_import_leaves_nothing(scene, tmp_path):
    names = _write_photos(scene, tmp_path / "images", "png")
    cams = _cams(scene)
    away = Camera(cams[1].K, cams[1].R, cams[1].t + torch.tensor([0.0, 0.0, -20.0], dtype=torch.float64),
                  SIZE, SIZE, dtype=torch.float64)  # the object behind this camera
    write_colmap_binary(tmp_path / "m", [cams[0], away, cams[2]], names)
    with pytest.raises(CaptureImportError, match=r"images\[1\]\.camera.*does not see the mesh"):
        import_colmap(tmp_path / "m", tmp_path / "ds", ImportOptions(mesh=scene["mesh"], images=tmp_path / "images",
                                                                        flash=_flash(scene)))
    assert not (tmp_path / "ds").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".ds")]
