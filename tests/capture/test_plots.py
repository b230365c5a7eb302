"""The reconstruction's figures, by their pixels: the views pages and the confidence previews."""

import math

import matplotlib
import pytest
import torch

from capture.plots import (
    DPI,
    ERROR_CMAP,
    ERROR_RANGE,
    NO_PREDICTION_RGB,
    NO_SAMPLE_RGB,
    UNOBSERVABLE_RGB,
    PlotError,
    ViewRow,
    error_colours,
    plot_confidence,
    plot_lobes,
    plot_views,
    relative_error,
    save_figure,
    tone_map,
    views_page_size,
)
from renderer.imageio import read_png


def _rgb(path):
    return read_png(path, transfer="linear")[..., :3]   # the colours exactly as drawn (8-bit codes / 255)


def _close(img, colour, tol=2.5 / 255):
    return ((img - torch.tensor(colour, dtype=img.dtype)).abs() <= tol).all(-1)


def _colorbar_colour(img, box, lo, hi, value):
    """The colour bar's pixel at ``value`` (log scale, running from the box's bottom up), in its middle column."""
    x0, y0, x1, y1 = box
    t = (math.log(value) - math.log(lo)) / (math.log(hi) - math.log(lo))
    return img[round(y1 - t * (y1 - y0)), (x0 + x1) // 2]


def _views(n, size=(48, 64), heldout=()):
    g = torch.Generator().manual_seed(1)
    rows = []
    for i in range(n):
        photo = torch.rand(*size, 3, generator=g) + 0.1
        mask = torch.ones(size, dtype=torch.bool)
        mask[: size[0] // 4] = False                         # a quarter of the pixels without a prediction
        rows.append(ViewRow(i, photo, photo * 1.01, mask, 40.0 + i, i in heldout))
    return rows


def test_every_view_is_drawn_on_pages_of_known_size(tmp_path):
    # 10 views of 48 × 64 px, 4 a page: 3 pages of 4, 4 and 2 rows; a row is a 2.6-inch panel (1.95 in high at
    # this aspect) plus a 0.3-inch title line = 225 px at 100 dpi
    info = plot_views(tmp_path, _views(10, heldout=(2,)), per_page=4)
    assert [p.name for p in info.paths] == ["views.png", "views-2.png", "views-3.png"]
    assert info.sizes == [views_page_size(4, (48, 64))] * 2 + [views_page_size(2, (48, 64))]
    assert info.sizes[0][0] - info.sizes[2][0] == pytest.approx(2 * 225, abs=1)
    assert info.sizes[0][1] == round(DPI * (0.12 + 3 * (2.6 + 0.12) + 1.15))
    for path, (h, w) in zip(info.paths, info.sizes, strict=True):
        assert tuple(read_png(path).shape) == (h, w, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["views-2.png", "views-3.png", "views.png"]  # no temporaries


def test_the_error_colour_bar_and_panels_show_the_relative_error(tmp_path):
    lo, hi = ERROR_RANGE
    cmap = matplotlib.colormaps[ERROR_CMAP]
    info = plot_views(tmp_path, _views(2))
    img = _rgb(info.paths[0])
    # the colour bar at 0.1 %, 1 % and 10 %: the colour map at 1/4, 1/2 and 3/4 of its log range
    for value, t in ((1e-3, 0.25), (1e-2, 0.5), (1e-1, 0.75)):
        got = _colorbar_colour(img, info.colorbar[0], lo, hi, value)
        assert torch.allclose(got, torch.tensor(cmap(t)[:3], dtype=got.dtype), atol=6 / 255), (value, got)
    # every predicted pixel is 1 % off: its error colour is the bar's at 1 %, over the 3/4 of each error panel that
    # has a prediction (2 views × 260 × 195 px panels); the other quarter shows the no-prediction colour (legend too)
    panel = 2 * 260 * 195
    assert int(_close(img, cmap(0.5)[:3]).sum()) > 0.7 * panel
    assert 0.22 * panel < int(_close(img, NO_PREDICTION_RGB).sum()) < 0.26 * panel   # less the panel frames


def test_relative_error_tone_map_and_colours_by_hand():
    photo = torch.tensor([[[0.2, 0.4, 0.2], [0.0, 0.0, 0.0]], [[1.0, 1.0, 1.0], [math.nan, 0.1, 0.1]]])
    render = photo.nan_to_num(0.0) * 1.1
    mask = torch.tensor([[True, True], [True, True]])
    rel = relative_error(photo, render, mask)
    # |Σ 0.1 · photo| / Σ photo = 10 %; the black pixel has no error; a non-finite photo pixel is not judged
    assert rel[0, 0] == pytest.approx(0.1) and rel[1, 0] == pytest.approx(0.1) and rel[0, 1] == 0.0
    assert math.isnan(rel[1, 1])
    assert math.isnan(relative_error(photo, render, ~mask)[0, 0])
    cols = error_colours(rel)
    assert torch.allclose(cols[0, 0], torch.tensor(matplotlib.colormaps[ERROR_CMAP](0.75)[:3], dtype=torch.float32))
    assert torch.equal(cols[1, 1], torch.tensor(NO_PREDICTION_RGB))
    # photo and render share one scale: the same image maps to the same pixels, a brighter render to brighter ones
    a, b, scale = tone_map(photo, photo.nan_to_num(0.0), mask)
    assert torch.equal(a, b) and 0 < scale and torch.isfinite(a).all()
    _, brighter, _ = tone_map(photo, render, mask)
    assert bool((brighter >= b).all()) and bool((brighter > b).any())


def test_confidence_preview_colours_and_legend(tmp_path):
    # four texel blocks: std 1e-3 and 1e-2 (observable: the ends of the colour bar), one unobservable (grey), one
    # with no sample (NaN: black)
    std = torch.tensor([[1e-3, 1e-2], [5e-2, math.nan]]).repeat_interleave(8, 0).repeat_interleave(8, 1)[..., None]
    unobservable = torch.tensor([[False, False], [True, False]]).repeat_interleave(8, 0).repeat_interleave(8, 1)
    info = plot_confidence(tmp_path / "confidence_roughness.png", std, unobservable, "roughness")
    assert info.value_range == pytest.approx((1e-3, 1e-2))
    img = _rgb(info.paths[0])
    assert tuple(img.shape[:2]) == info.sizes[0]
    viridis = matplotlib.colormaps["viridis"]
    quarter = 200 * 200                                 # a 4-inch map at 100 dpi, one quarter per block
    for colour, share in ((viridis(0.0)[:3], 1), (viridis(1.0)[:3], 1), (UNOBSERVABLE_RGB, 1), (NO_SAMPLE_RGB, 1)):
        n = int(_close(img, colour).sum())
        assert n >= 0.95 * quarter * share, (colour, n)
    lo, hi = info.value_range
    mid = _colorbar_colour(img, info.colorbar[0], lo, hi, math.sqrt(lo * hi))
    assert torch.allclose(mid, torch.tensor(viridis(0.5)[:3], dtype=mid.dtype), atol=6 / 255)
    # nothing observable: still a figure, all grey and black
    none = plot_confidence(tmp_path / "confidence_f0.png", std, torch.ones_like(unobservable), "f0")
    assert none.paths[0].is_file()


def test_bad_figure_input_is_named(tmp_path):
    rows = _views(1)
    with pytest.raises(PlotError, match="per_page"):
        plot_views(tmp_path, rows, per_page=0)
    with pytest.raises(PlotError, match="non-empty list"):
        plot_views(tmp_path, [])
    with pytest.raises(PlotError, match="existing folder"):
        plot_views(tmp_path / "missing", rows)
    bad = ViewRow(0, rows[0].photo, rows[0].render[:10], rows[0].mask)
    with pytest.raises(PlotError, match="view 0 render must have shape"):
        plot_views(tmp_path, [bad])
    with pytest.raises(PlotError, match="bool mask"):
        plot_confidence(tmp_path / "c.png", torch.zeros(4, 4), torch.zeros(4, 4), "albedo")
    with pytest.raises(PlotError, match=r"\.png"):
        plot_confidence(tmp_path / "c.jpg", torch.zeros(4, 4), torch.zeros(4, 4, dtype=torch.bool), "albedo")
    assert list(tmp_path.iterdir()) == []


def test_bad_colour_scales_and_sizes_are_named():
    from capture.plots import confidence_colours

    with pytest.raises(PlotError, match="0 < lo < hi"):
        error_colours(torch.zeros(2, 2), 0.0, 1.0)
    with pytest.raises(PlotError, match="0 < lo < hi"):
        confidence_colours(torch.zeros(2, 2), torch.zeros(2, 2, dtype=torch.bool), 1.0, 0.5)
    with pytest.raises(PlotError, match="bool mask"):
        confidence_colours(torch.zeros(2, 2), torch.zeros(2, 2), 0.1, 1.0)
    with pytest.raises(PlotError, match="photo must be"):
        relative_error(torch.zeros(2, 2), torch.zeros(2, 2), torch.ones(2, 2, dtype=torch.bool))
    with pytest.raises(PlotError, match="rows must be"):
        views_page_size(0, (48, 64))
    with pytest.raises(PlotError, match="image_size"):
        views_page_size(2, (48,))


def test_save_figure_writes_the_drawn_pixels_atomically_into_a_new_folder(tmp_path):
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(2.0, 1.0), facecolor=(1.0, 0.0, 0.0))
    out = tmp_path / "new" / "red.png"
    assert save_figure(fig, out, dpi=50) == (50, 100)  # 1 × 2 inches at 50 dpi
    assert not plt.fignum_exists(fig.number)  # closed
    assert sorted(p.name for p in out.parent.iterdir()) == ["red.png"]  # no temporary file left
    assert torch.equal(_rgb(out), torch.tensor([1.0, 0.0, 0.0]).expand(50, 100, 3))
    lobes = plot_lobes(tmp_path / "lobes" / "lobes.png", names=["lambert"])
    assert [p.name for p in lobes.parent.iterdir()] == ["lobes.png"] and _rgb(lobes).shape == (210, 1050, 3)
