"""renderer.imageio: transfer goldens, EXR/PNG round trips, atomic writes, bad-input errors."""

import os

import numpy as np
import pytest
import torch

from renderer import imageio as io

# --------------------------------------------------------------------------------------------
# transfer functions


def test_srgb_golden_values():
    # IEC 61966-2-1: the two pieces meet at linear 0.0031308 ↔ encoded 0.04045 (12.92 · 0.0031308 = 0.040449...)
    x = torch.tensor([0.0, 0.0031308, 0.5, 0.18, 1.0], dtype=torch.float64)
    y = io.encode(x, "srgb")
    # 1.055 · 0.5^(1/2.4) − 0.055 = 0.735356983..., 1.055 · 0.18^(1/2.4) − 0.055 = 0.461356...
    expected = torch.tensor([0.0, 0.04044994, 0.7353569831, 0.4613561295, 1.0], dtype=torch.float64)
    torch.testing.assert_close(y, expected, atol=1e-8, rtol=0)
    torch.testing.assert_close(io.decode(torch.tensor([0.04045], dtype=torch.float64), "srgb"),
                               torch.tensor([0.04045 / 12.92], dtype=torch.float64))
    # continuity at the knee: both pieces agree to 1e-7
    lo = 12.92 * 0.0031308
    hi = 1.055 * 0.0031308 ** (1 / 2.4) - 0.055
    assert abs(lo - hi) < 1e-7


def test_gamma22_and_linear():
    x = torch.tensor([0.0, 0.05, 0.5, 1.0], dtype=torch.float64)
    torch.testing.assert_close(io.encode(x, "gamma2.2"), x ** (1 / 2.2))
    torch.testing.assert_close(io.decode(x, "gamma2.2"), x**2.2)
    assert torch.equal(io.encode(x, "linear"), x)
    assert io.encode(torch.tensor([-0.5]), "gamma2.2").item() == 0.0


@pytest.mark.parametrize("transfer", ["srgb", "gamma2.2", "linear"])
def test_encode_decode_inverse_and_finite_gradient(transfer):
    x = torch.linspace(0, 1, 1001, dtype=torch.float64, requires_grad=True)
    y = io.encode(x, transfer)
    torch.testing.assert_close(io.decode(y, transfer), x, atol=1e-12, rtol=0)
    y.sum().backward()
    assert torch.isfinite(x.grad).all()
    # monotone increasing
    assert (y[1:] > y[:-1]).all()


def test_unknown_transfer_lists_names():
    with pytest.raises(io.ImageIOError, match="srgb"):
        io.encode(torch.zeros(1), "rec709")


# --------------------------------------------------------------------------------------------
# EXR


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("half", [False, True])
def test_exr_round_trip(tmp_path, channels, half):
    g = torch.Generator().manual_seed(channels)
    img = torch.rand(9, 13, channels, generator=g) * 40 - 4  # linear HDR, negatives allowed
    p = tmp_path / "x.exr"
    io.write_exr(p, img, half=half)
    back = io.read_exr(p)
    assert back.shape == (9, 13, channels) and back.dtype == torch.float32
    if half:
        # half has an 11-bit significand: relative error ≤ 2^-11
        torch.testing.assert_close(back, img.half().float(), atol=0, rtol=0)
        assert ((back - img).abs() <= img.abs() * 2**-11 + 1e-7).all()
    else:
        assert torch.equal(back, img)
    assert torch.equal(io.read_image(p), back)


def test_exr_2d_input_and_float64(tmp_path):
    img = torch.linspace(0, 1, 12, dtype=torch.float64).reshape(3, 4)
    io.write_exr(tmp_path / "g.exr", img)
    back = io.read_exr(tmp_path / "g.exr")
    assert back.shape == (3, 4, 1)
    torch.testing.assert_close(back[..., 0].double(), img, atol=1e-7, rtol=0)


def test_exr_half_overflow_and_nan_refused(tmp_path):
    with pytest.raises(io.ImageIOError, match=r"x\.exr.*half"):
        io.write_exr(tmp_path / "x.exr", torch.full((2, 2, 3), 1e5), half=True)
    bad = torch.zeros(2, 2, 3)
    bad[0, 0, 1] = float("nan")
    with pytest.raises(io.ImageIOError, match="1 NaN/inf"):
        io.write_exr(tmp_path / "x.exr", bad)
    assert not (tmp_path / "x.exr").exists()
    io.write_exr(tmp_path / "x.exr", bad, allow_nonfinite=True)
    assert torch.isnan(io.read_exr(tmp_path / "x.exr")[0, 0, 1])


def test_exr_truncated_missing_and_garbage(tmp_path):
    p = tmp_path / "t.exr"
    io.write_exr(p, torch.rand(32, 32, 3))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(io.ImageIOError, match=r"t\.exr.*truncated"):
        io.read_exr(p)
    with pytest.raises(io.ImageNotFoundError, match="missing.exr"):
        io.read_exr(tmp_path / "missing.exr")
    with pytest.raises(FileNotFoundError):  # also a FileNotFoundError
        io.read_image(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(io.ImageIOError, match="junk.exr.*not an OpenEXR"):
        io.read_exr(tmp_path / "junk.exr")
    (tmp_path / "empty.exr").write_bytes(b"")
    with pytest.raises(io.ImageIOError, match="empty"):
        io.read_exr(tmp_path / "empty.exr")


def test_exr_wrong_channel_count(tmp_path):
    with pytest.raises(io.ImageIOError, match=r"C = 1 \(gray\), 3 \(RGB\) or 4"):
        io.write_exr(tmp_path / "x.exr", torch.zeros(2, 2, 2))
    with pytest.raises(io.ImageIOError, match="shape"):
        io.write_exr(tmp_path / "x.exr", torch.zeros(2))


def test_exr_reads_foreign_channel_layouts(tmp_path):
    import OpenEXR

    # a file written channel by channel, with XYZ names: refused with the names listed
    p = tmp_path / "xyz.exr"
    chans = {k: np.zeros((2, 3), np.float32) for k in ("X", "Y", "Z")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, chans) as f:
        f.write(str(p))
    with pytest.raises(io.ImageIOError, match=r"\['X', 'Y', 'Z'\]"):
        io.read_exr(p)
    # interleaved RGBA written by another tool comes back in RGBA order
    q = tmp_path / "rgba.exr"
    rgba = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"RGBA": rgba}) as f:
        f.write(str(q))
    assert np.array_equal(io.read_exr(q).numpy(), rgba)


# --------------------------------------------------------------------------------------------
# PNG


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("transfer", ["srgb", "gamma2.2", "linear"])
def test_png_round_trip_within_half_a_code(tmp_path, channels, bits, transfer):
    g = torch.Generator().manual_seed(bits + channels)
    img = torch.rand(7, 11, channels, generator=g, dtype=torch.float64)
    p = tmp_path / "x.png"
    io.write_png(p, img, bits=bits, transfer=transfer)
    back = io.read_png(p, transfer=transfer).double()
    assert back.shape == img.shape
    top = 2**bits - 1
    # in encoded space the error is the rounding: at most half a code (plus float32 noise)
    ncol = 3 if channels == 4 else channels
    enc_err = (io.encode(back[..., :ncol], transfer) - io.encode(img[..., :ncol], transfer)).abs().max()
    assert enc_err <= 0.5 / top + 1e-6
    if channels == 4:  # alpha is quantised linearly
        assert (back[..., 3] - img[..., 3]).abs().max() <= 0.5 / top + 1e-6


def test_png_16bit_exact_codes(tmp_path):
    codes = torch.tensor([0, 1, 2, 1000, 32767, 65534, 65535], dtype=torch.float64)
    img = (codes / 65535).reshape(1, -1, 1)
    io.write_png(tmp_path / "c.png", img, bits=16, transfer="linear")
    import cv2

    raw = cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.tolist() == [codes.int().tolist()]
    assert torch.equal(io.read_png(tmp_path / "c.png", "linear").double(), img.float().double())


def test_png_is_bgr_on_disk_and_srgb_coded(tmp_path):
    import cv2

    img = torch.tensor([[[1.0, 0.5, 0.0, 0.25]]])  # RGBA
    io.write_png(tmp_path / "p.png", img)
    raw = cv2.imread(str(tmp_path / "p.png"), cv2.IMREAD_UNCHANGED)
    # B, G, R, A; G = round(255 · 0.7353569) = 188; alpha linear round(63.75) = 64
    assert raw[0, 0].tolist() == [0, 188, 255, 64]


def test_png_clamps_and_refuses_nan(tmp_path):
    io.write_png(tmp_path / "c.png", torch.tensor([[[-1.0, 2.0, 0.5]]]))
    back = io.read_png(tmp_path / "c.png")
    assert back[0, 0, 0] == 0 and back[0, 0, 1] == 1
    bad = torch.zeros(3, 3, 3)
    bad[1, 1] = float("inf")
    with pytest.raises(io.ImageIOError, match=r"n\.png.*3 NaN/inf"):
        io.write_png(tmp_path / "n.png", bad)
    assert not (tmp_path / "n.png").exists()
    with pytest.raises(io.ImageIOError, match="bits must be 8 or 16"):
        io.write_png(tmp_path / "n.png", torch.zeros(2, 2, 3), bits=12)


def test_png_truncated_and_garbage(tmp_path):
    p = tmp_path / "t.png"
    io.write_png(p, torch.rand(40, 40, 3))
    data = p.read_bytes()
    p.write_bytes(data[:-20])
    with pytest.raises(io.ImageIOError, match=r"t\.png.*truncated"):
        io.read_png(p)
    (tmp_path / "g.png").write_bytes(b"garbage bytes")
    with pytest.raises(io.ImageIOError, match=r"g\.png.*not a PNG"):
        io.read_image(tmp_path / "g.png")
    with pytest.raises(io.ImageIOError, match=r"unsupported image type '\.bmp'"):
        io.read_image(tmp_path / "x.bmp")


# --------------------------------------------------------------------------------------------
# atomic writes and dispatch


def test_atomic_write_leaves_no_temp_and_keeps_old_file_on_failure(tmp_path):
    p = tmp_path / "a.png"
    io.write_image(p, torch.full((2, 2, 3), 0.5))
    before = p.read_bytes()
    with pytest.raises(io.ImageIOError):
        io.write_image(p, torch.full((2, 2, 3), float("nan")))
    assert p.read_bytes() == before
    io.write_image(tmp_path / "a.exr", torch.ones(2, 2, 3), half=True)
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "a.png"]
    with pytest.raises(io.ImageIOError, match="does not exist"):
        io.write_image(tmp_path / "nofolder" / "x.exr", torch.ones(2, 2, 3))
    with pytest.raises(io.ImageIOError, match="for writing"):
        io.write_image(tmp_path / "x.jpg", torch.ones(2, 2, 3))


def test_atomic_writes_honour_the_umask_and_keep_a_replaced_files_mode(tmp_path, monkeypatch):
    # the temporary file is private (mkstemp: 0600); a new image gets what a plain open() would give
    old = os.umask(0o027)
    try:
        io.write_image(tmp_path / "a.exr", torch.ones(2, 2, 3))
        io.atomic_write_bytes(tmp_path / "b.bin", b"x")
        (tmp_path / "c.png").write_bytes(b"")
        os.chmod(tmp_path / "c.png", 0o600)
        io.write_image(tmp_path / "c.png", torch.ones(2, 2, 3))
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()}
    assert modes == {"a.exr": 0o640, "b.bin": 0o640, "c.png": 0o600}
    # an interrupt while writing leaves no temporary file behind
    import cv2

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cv2, "imencode", lambda *a, **k: (True, np.zeros(4, np.uint8)))
    monkeypatch.setattr(io.Path, "write_bytes", interrupted)
    with pytest.raises(KeyboardInterrupt):
        io.write_image(tmp_path / "d.png", torch.ones(2, 2, 3))
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "b.bin", "c.png"]


def test_read_image_dispatch_and_transfer(tmp_path):
    img = torch.tensor([[[0.2, 0.4, 0.6]]])
    io.write_image(tmp_path / "x.png", img, bits=16)
    # default PNG transfer is sRGB
    torch.testing.assert_close(io.read_image(tmp_path / "x.png"), img, atol=2e-5, rtol=0)
    lin = io.read_image(tmp_path / "x.png", transfer="linear")
    torch.testing.assert_close(lin, io.encode(img, "srgb"), atol=2e-5, rtol=0)


def test_png_codes_are_written_as_given(tmp_path):
    import numpy as np

    g = np.random.default_rng(3)
    for shape, dtype in (((5, 7, 3), np.uint8), ((5, 7, 4), np.uint16), ((5, 7), np.uint8)):
        codes = g.integers(0, np.iinfo(dtype).max + 1, size=shape, dtype=dtype)
        io.write_png_codes(tmp_path / "c.png", codes)
        back, bits = io.read_raster(tmp_path / "c.png")
        assert bits == 8 * np.dtype(dtype).itemsize
        assert np.array_equal(back.reshape(codes.shape), codes)       # RGB(A) order on both sides
    with pytest.raises(io.ImageIOError, match="uint8 or uint16"):
        io.write_png_codes(tmp_path / "f.png", np.zeros((2, 2, 3), np.float32))
    with pytest.raises(io.ImageIOError, match="shape"):
        io.write_png_codes(tmp_path / "s.png", np.zeros((2, 2, 2), np.uint8))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.png"]    # nothing left by the refusals
