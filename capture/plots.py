"""Figures: lobe plots of every model (docs/models.md), and the figures a reconstruction writes — the labelled
re-rendered views (:func:`plot_views`) and confidence previews with a colour bar (:func:`plot_confidence`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

import materials
from materials import CANONICAL, Angles

#: Parameters used for the lobe plots (each spec's ``plot_value``): a mid-rough dielectric, unless a model needs others.
PLOT_PARAMS = {p.name: p.plot_value for p in CANONICAL.values()}


def lobe_in_plane(model, theta_v_deg: float, n: int = 361, params: dict | None = None):
    """π·f_r·(n·l) over light directions in the plane of incidence (θ_l from −90° to 90°, the
    viewer at +θ_v on the other side), green channel. Returns (θ_l in radians, value)."""
    theta_l = torch.linspace(-math.pi / 2, math.pi / 2, n, dtype=torch.float64)
    tv = math.radians(theta_v_deg)
    nl, nv = torch.cos(theta_l), torch.full_like(theta_l, math.cos(tv))
    lv = torch.cos(theta_l + tv)  # l at angle θ_l, v at −θ_v in the same plane → φ difference π for θ_l > 0
    g = Angles.from_cosines(nl, nv, lv)
    vals = dict(PLOT_PARAMS, **(params or {}))
    p = {s.name: torch.full((n, s.channels), float(vals.get(s.name, s.default)), dtype=torch.float64)
         for s in model.params}
    f = model.cosine_brdf(g, p)[..., 1] * math.pi
    return theta_l, f


def plot_lobes(out_png: str | Path, names: list[str] | None = None, views=(0.0, 45.0, 75.0)) -> Path:
    """One polar panel per model: π f_r cos θ_l in the plane of incidence for three view angles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = names or [k for k in materials.available() if k != "measured"]
    cols = 5
    rows = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(rows, cols, subplot_kw={"projection": "polar"}, figsize=(3.0 * cols, 3.0 * rows))
    for ax, name in zip(axes.flat, names, strict=False):
        model = materials.get(name)
        for tv, colour in zip(views, ("tab:blue", "tab:orange", "tab:red"), strict=True):
            th, f = lobe_in_plane(model, tv)
            ax.plot(th.numpy(), f.clamp_min(0).numpy(), color=colour, lw=1.2, label=f"θv={tv:.0f}°")
        ax.set_theta_zero_location("N")
        ax.set_thetamin(-90)
        ax.set_thetamax(90)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=6)
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=6, loc="lower left")
    fig.suptitle("π·f_r·cos θ_l in the plane of incidence (viewer on the right at θv, mirror direction on the left); "
                 "albedo 0.5, f0 0.04, r 0.4",
                 fontsize=10)
    fig.tight_layout()
    out_png = Path(out_png)
    save_figure(fig, out_png, dpi=70)
    return out_png


# ------------------------------------------------------------------------------ reconstruction figures
#
# Figures a reconstruction writes next to its maps (docs/reconstruction.md, "Outputs"): the labelled views pages
# (:func:`plot_views`) and the confidence previews (:func:`plot_confidence`). Every axes sits at a fixed place in a
# figure of a fixed size (no tight layout), so a page's pixel size and the colour bar's pixels follow from the
# inputs alone (:class:`FigureInfo`); the pixels are written through :func:`renderer.imageio.write_png`
# (atomically, RGB, 8 bits, the colours exactly as matplotlib drew them).

#: Rows (views) per page of :func:`plot_views`; the pages are ``views.png``, ``views-2.png``, ...
VIEWS_PER_PAGE = 8
#: :func:`plot_views`: |relative error| shown on a log scale over this range (values outside are clipped to its ends).
ERROR_RANGE = (1e-4, 1.0)
#: Error colour map (perceptually uniform, dark = small error) and the colour of pixels the fit does not predict.
ERROR_CMAP = "magma"
NO_PREDICTION_RGB = (0.55, 0.62, 0.7)
#: :func:`plot_views`: the frame of a held-out view's panels (matplotlib's "tab:red", 2 px).
HELDOUT_FRAME = ((0.839, 0.153, 0.157), 2)
#: :func:`plot_views`: photo and re-render are both scaled so this percentile of the photo's on-object pixels
#: (largest channel) is white, then sRGB-encoded.
TONE_PERCENTILE = 99.5
#: :func:`plot_confidence`: colour map of the posterior std, colour of unobservable texels (grey) and of texels
#: without any sample (black).
CONFIDENCE_CMAP = "viridis"
UNOBSERVABLE_RGB = (0.6, 0.6, 0.6)
NO_SAMPLE_RGB = (0.0, 0.0, 0.0)
DPI = 100


class PlotError(ValueError):
    """Figure inputs that cannot be drawn (shapes, types, an empty list of views)."""


@dataclass
class ViewRow:
    """One view of :func:`plot_views`.

    Attributes:
        index: the view's index in the dataset; photo, render: ``[H, W, 3]`` linear radiance (non-finite photo
        pixels are shown black); mask: ``[H, W]`` bool, the pixels the fit predicts; psnr: dB or None / NaN (printed
        "n/a"); heldout: kept out of the fit (validation view).
    """

    index: int
    photo: Tensor
    render: Tensor
    mask: Tensor
    psnr: float | None = None
    heldout: bool = False


@dataclass
class FigureInfo:
    """What a figure function wrote: the files, each page's size in pixels ``(height, width)`` and the colour bar's
    box in pixels ``(x0, y0, x1, y1)`` (x right, y down, the value range running from ``y1`` up to ``y0``), with
    the colour scale's ``(low, high)`` (log scale)."""

    paths: list
    sizes: list
    colorbar: list
    value_range: tuple


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: float | None = None) -> tuple[int, int]:
    """Draw ``fig`` (at ``dpi`` when given) and write its pixels as an RGB PNG, closing the figure; returns
    ``(height, width)``.

    The one way a figure reaches a file: through :func:`renderer.imageio.write_png`, so atomically (a reader never
    sees half a PNG, an interrupt leaves nothing behind) and with the umask's permissions. The folder is created.
    """
    import numpy as np

    from renderer.imageio import write_png_codes

    plt = _pyplot()
    path = Path(path)
    try:
        if dpi is not None:
            fig.set_dpi(dpi)
        fig.canvas.draw()
        rgb = np.array(np.asarray(fig.canvas.buffer_rgba())[..., :3])
    finally:
        plt.close(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png_codes(path, rgb)                  # the 8-bit codes matplotlib drew, as they are
    return int(rgb.shape[0]), int(rgb.shape[1])


def _panel(fig, image: Tensor, rect, fig_w: float, fig_h: float, frame: tuple | None = None) -> None:
    """Draw ``image`` (``[h, w, 3]`` in [0, 1]) filling the figure rectangle ``rect`` (left, bottom, width, height in
    figure fractions) at the figure's pixels — nearest-neighbour resampling, as ``imshow(interpolation="nearest")``
    — inside a frame: 1 px black, or ``frame = (rgb, width px)``. Placed with ``figimage``, without an axes: a page
    of 8 views took 0.7 s to draw with three axes a view (their ticks and spines), most of the figure's time."""
    import numpy as np

    x0, y0, x1, y1 = _box(fig_w, fig_h, rect)
    w, h = max(x1 - x0, 1), max(y1 - y0, 1)
    src = image.detach().cpu().float()
    rows = ((torch.arange(h) + 0.5) * src.shape[0] / h).long().clamp_max(src.shape[0] - 1)
    cols = ((torch.arange(w) + 0.5) * src.shape[1] / w).long().clamp_max(src.shape[1] - 1)
    px = src[rows][:, cols].clamp(0, 1).numpy().astype(np.float32)
    colour, width = frame if frame is not None else ((0.0, 0.0, 0.0), 1)
    width = min(width, h // 2, w // 2)
    if width > 0:
        for band in (px[:width], px[-width:], px[:, :width], px[:, -width:]):
            band[...] = colour
    fig.figimage(px, xo=x0, yo=round(fig_h * DPI) - y1, origin="upper")


def _box(fig_w: float, fig_h: float, rect) -> tuple[int, int, int, int]:
    """Pixel box (x0, y0, x1, y1) of an axes ``rect`` (left, bottom, width, height in figure fractions)."""
    l, b, w, h = rect
    return (round(l * fig_w * DPI), round((1 - b - h) * fig_h * DPI), round((l + w) * fig_w * DPI),
            round((1 - b) * fig_h * DPI))


def _image(x, name: str, shape=None) -> Tensor:
    if not isinstance(x, Tensor):
        raise PlotError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if shape is not None and tuple(x.shape) != tuple(shape):
        raise PlotError(f"{name} must have shape {tuple(shape)}, got {tuple(x.shape)}")
    return x.detach().cpu()


def _percentile(x: Tensor, q: float) -> float:
    import numpy as np

    return float(np.percentile(x.double().numpy(), q))           # torch.quantile refuses > 2^24 values


def _shrink(photo: Tensor, render: Tensor, mask: Tensor, height: int, width: int):
    """Area-average photo and render (non-finite photo pixels as 0) by the integer factor that brings them to at most
    ``height`` × ``width`` pixels; a pixel of the result is predicted when any of its pixels is."""
    f = max(math.ceil(photo.shape[0] / height), math.ceil(photo.shape[1] / width), 1)
    if f == 1:
        return photo, render, mask
    H, W = photo.shape[:2]
    h, w = math.ceil(H / f), math.ceil(W / f)

    def pool(x):                    # block means over f × f (edge blocks padded with zeros), float32
        x = x.detach().cpu().float()
        x = torch.nn.functional.pad(x, (0, 0, 0, w * f - W, 0, h * f - H)) if x.dim() == 3 else \
            torch.nn.functional.pad(x, (0, w * f - W, 0, h * f - H))
        return x.reshape(h, f, w, f, *x.shape[2:]).mean((1, 3))

    photo = photo.detach().cpu().float().nan_to_num(nan=0.0, posinf=0.0, neginf=0.0)
    return pool(photo), pool(render), pool(mask.float()) > 0


def tone_map(photo: Tensor, render: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor, float]:
    """Photo and re-render ``[H, W, 3]`` (linear) → display sRGB in [0, 1], both with the *same* scale: the
    :data:`TONE_PERCENTILE` percentile of the photo's largest channel over its positive finite pixels (and the
    ``mask`` pixels) becomes white. Non-finite pixels are shown black. Returns ``(photo, render, scale)``."""
    from renderer.imageio import encode

    photo = _image(photo, "photo").float()
    render = _image(render, "render", photo.shape).float()
    if photo.dim() != 3 or photo.shape[-1] != 3:
        raise PlotError(f"photo must be [H, W, 3], got {tuple(photo.shape)}")
    top = photo.nan_to_num(nan=0.0, posinf=0.0, neginf=0.0).amax(-1)
    sel = top > 0
    if mask is not None:
        sel = sel | (_image(mask, "mask", photo.shape[:2]).bool() & (top > 0))
    peak = _percentile(top[sel], TONE_PERCENTILE) if bool(sel.any()) else 0.0
    scale = 1.0 / peak if peak > 0 else 1.0

    def show(x):
        x = x.nan_to_num(nan=0.0, posinf=0.0, neginf=0.0)
        return encode((x * scale).clamp(0, 1), "srgb").clamp(0, 1)

    return show(photo), show(render), scale


def relative_error(photo: Tensor, render: Tensor, mask: Tensor, floor: float = 0.01) -> Tensor:
    """``[H, W]`` |relative error| of a re-render: Σ_c |render − photo| / max(Σ_c photo, ``floor`` · the
    :data:`TONE_PERCENTILE` percentile of Σ_c photo) — relative to the photo, with a floor so that dark pixels do
    not blow up. NaN outside ``mask`` and where the photo is not finite (no prediction to judge)."""
    photo = _image(photo, "photo").double()
    if photo.dim() != 3 or photo.shape[-1] != 3:
        raise PlotError(f"photo must be [H, W, 3], got {tuple(photo.shape)}")
    render = _image(render, "render", photo.shape).double()
    mask = _image(mask, "mask", photo.shape[:2]).bool()
    if isinstance(floor, bool) or not isinstance(floor, (int, float)) or not floor > 0:
        raise PlotError(f"floor must be a number > 0, got {floor!r}")
    ok = mask & torch.isfinite(photo).all(-1)
    s = photo.nan_to_num(nan=0.0, posinf=0.0, neginf=0.0).sum(-1)
    pos = s[ok & (s > 0)]
    ref = _percentile(pos, TONE_PERCENTILE) if pos.numel() else 1.0
    den = s.clamp_min(floor * ref if ref > 0 else 1e-30)
    err = (render - photo.nan_to_num(nan=0.0, posinf=0.0, neginf=0.0)).abs().sum(-1) / den
    return torch.where(ok, err, torch.full_like(err, float("nan"))).float()


def _check_range(lo, hi) -> None:
    ok = all(not isinstance(x, bool) and isinstance(x, (int, float)) and 0 < x < math.inf for x in (lo, hi))
    if not ok or not lo < hi:
        raise PlotError(f"the colour scale needs 0 < lo < hi (a log scale), got lo={lo!r}, hi={hi!r}")


def _log_colours(values: Tensor, cmap: str, lo: float, hi: float) -> Tensor:
    """RGB ``[..., 3]`` of a colour map on a log scale over [lo, hi] (clipped), NaN entries left NaN."""
    import matplotlib
    import numpy as np

    x = values.double()
    t = ((x.clamp(lo, hi).log() - math.log(lo)) / (math.log(hi) - math.log(lo))) if hi > lo else torch.zeros_like(x)
    rgb = torch.from_numpy(matplotlib.colormaps[cmap](np.nan_to_num(t.numpy(), nan=0.0))[..., :3]).float()
    return torch.where(torch.isnan(x)[..., None], torch.full_like(rgb, float("nan")), rgb)


def error_colours(rel: Tensor, lo: float = ERROR_RANGE[0], hi: float = ERROR_RANGE[1]) -> Tensor:
    """``[H, W, 3]`` display colours of a :func:`relative_error` image: :data:`ERROR_CMAP` on a log scale over
    ``[lo, hi]``, :data:`NO_PREDICTION_RGB` where it is NaN."""
    _check_range(lo, hi)
    rgb = _log_colours(_image(rel, "rel"), ERROR_CMAP, lo, hi)
    return torch.where(torch.isnan(rgb), torch.tensor(NO_PREDICTION_RGB), rgb)


def _percent(x: float) -> str:
    return f"{x * 100:g} %"


#: :func:`plot_views` page layout, inches: panel width, gaps, title line above each row, header, colour bar area.
_PANEL_W, _GAP, _TITLE, _HEADER, _FOOTER, _LEFT, _CBAR_AREA = 2.6, 0.12, 0.3, 0.75, 0.15, 0.12, 1.15


def views_page_size(rows: int, image_size: tuple[int, int]) -> tuple[int, int]:
    """Pixel size ``(height, width)`` of a :func:`plot_views` page of ``rows`` views whose largest image is
    ``image_size = (H, W)`` pixels."""
    if isinstance(rows, bool) or not isinstance(rows, int) or rows < 1:
        raise PlotError(f"rows must be a positive integer, got {rows!r}")
    if not (isinstance(image_size, (tuple, list)) and len(image_size) == 2
            and all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in image_size)):
        raise PlotError(f"image_size must be (H, W), two positive integers, got {image_size!r}")
    fw, fh, _ = _views_layout(rows, image_size)
    return round(fh * DPI), round(fw * DPI)


def _views_layout(rows: int, image_size) -> tuple[float, float, float]:
    H, W = image_size
    panel_h = _PANEL_W * H / W
    fw = _LEFT + 3 * (_PANEL_W + _GAP) + _CBAR_AREA
    fh = _HEADER + rows * (panel_h + _TITLE) + _FOOTER
    return fw, fh, panel_h


def plot_views(out_dir, rows, per_page: int = VIEWS_PER_PAGE, name: str = "views") -> FigureInfo:
    """Pages of labelled re-render rows: per view "photo | re-render | |relative error|".

    Each row is titled with the view index and its PSNR, held-out views marked "held out (not fitted)". Photo and
    re-render share one tone mapping per view (:func:`tone_map`); the error is :func:`relative_error` in
    :data:`ERROR_CMAP` on a log scale over :data:`ERROR_RANGE` with a colour bar of labelled ticks; pixels without a
    prediction (background, dropped pixels) are :data:`NO_PREDICTION_RGB`. All views are drawn, ``per_page`` rows a
    page: ``<name>.png``, ``<name>-2.png``, ... in the order given.

    Args:
        out_dir: existing folder to write into.
        rows: :class:`ViewRow` list (at least one).
        per_page: rows per page (≥ 1).
        name: file name stem of the pages.

    Returns:
        :class:`FigureInfo` (paths, page sizes, the error colour bar's pixel box per page, :data:`ERROR_RANGE`).
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise PlotError(f"out_dir {out_dir} is not an existing folder")
    rows = list(rows)
    if not rows or not all(isinstance(r, ViewRow) for r in rows):
        raise PlotError("rows must be a non-empty list of capture.plots.ViewRow")
    if isinstance(per_page, bool) or not isinstance(per_page, int) or per_page < 1:
        raise PlotError(f"per_page must be a positive integer, got {per_page!r}")
    if not isinstance(name, str) or not name or "/" in name or "\\" in name:
        raise PlotError(f"name must be a file name stem, got {name!r}")
    for r in rows:
        _image(r.photo, f"view {r.index} photo")
        if r.photo.dim() != 3 or r.photo.shape[-1] != 3:
            raise PlotError(f"view {r.index}: photo must be [H, W, 3], got {tuple(r.photo.shape)}")
        _image(r.render, f"view {r.index} render", r.photo.shape)
        _image(r.mask, f"view {r.index} mask", r.photo.shape[:2])
    plt = _pyplot()
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LogNorm

    size = (max(int(r.photo.shape[0]) for r in rows), max(int(r.photo.shape[1]) for r in rows))
    lo, hi = ERROR_RANGE
    info = FigureInfo(paths=[], sizes=[], colorbar=[], value_range=(lo, hi))
    pages = [rows[i:i + per_page] for i in range(0, len(rows), per_page)]
    for p, page in enumerate(pages):
        fw, fh, panel_h = _views_layout(len(page), size)
        fig = plt.figure(figsize=(fw, fh), dpi=DPI)
        fig.text(_LEFT / fw, 1 - 0.12 / fh, f"re-rendered views — page {p + 1} of {len(pages)}", fontsize=11,
                 va="top", weight="bold")
        fig.text(_LEFT / fw, 1 - 0.36 / fh,
                 "photo and re-render: the same exposure per view (its photo's 99.5th percentile white), sRGB; "
                 "error: |render − photo| / photo (summed over RGB), log scale", fontsize=7, va="top")
        for j, label in enumerate(("photo", "re-render (fitted maps)", "|relative error|")):
            fig.text((_LEFT + j * (_PANEL_W + _GAP) + _PANEL_W / 2) / fw, 1 - 0.6 / fh, label, ha="center",
                     va="top", fontsize=9)
        for k, r in enumerate(page):
            top = fh - _HEADER - k * (panel_h + _TITLE)
            # drawn at about twice the panel's pixels: 12-Mpx photos are area-averaged first
            ph, rd, mk = _shrink(r.photo, r.render, r.mask, 2 * round(panel_h * DPI), 2 * round(_PANEL_W * DPI))
            photo, render, _ = tone_map(ph, rd, mk)
            err = error_colours(relative_error(ph, rd, mk))
            psnr = "n/a" if r.psnr is None or not math.isfinite(r.psnr) else f"{r.psnr:.1f} dB"
            title = f"view {r.index} — PSNR {psnr}" + ("  —  HELD OUT (not fitted)" if r.heldout else "")
            fig.text(_LEFT / fw, (top - 0.04) / fh, title, fontsize=9, va="top",
                     color="tab:red" if r.heldout else "black", weight="bold" if r.heldout else "normal")
            # a view smaller or of another aspect than the page's largest keeps its aspect, top-left in its panel
            fit = min(_PANEL_W / r.photo.shape[1], panel_h / r.photo.shape[0])
            w_in, h_in = r.photo.shape[1] * fit, r.photo.shape[0] * fit
            for j, im in enumerate((photo, render, err)):
                _panel(fig, im, ((_LEFT + j * (_PANEL_W + _GAP)) / fw, (top - _TITLE - h_in) / fh, w_in / fw,
                                 h_in / fh), fw, fh, HELDOUT_FRAME if r.heldout else None)
        cb_rect = ((_LEFT + 3 * (_PANEL_W + _GAP) + 0.1) / fw, (fh - _HEADER - min(len(page), 2) * (panel_h + _TITLE)
                                                                + _TITLE) / fh, 0.18 / fw,
                   (min(len(page), 2) * (panel_h + _TITLE) - _TITLE) / fh)
        cax = fig.add_axes(cb_rect)
        cb = fig.colorbar(ScalarMappable(LogNorm(lo, hi), ERROR_CMAP), cax=cax)
        ticks = [10.0 ** e for e in range(round(math.log10(lo)), round(math.log10(hi)) + 1)]
        cb.set_ticks(ticks)
        cb.set_ticklabels([_percent(t) for t in ticks])
        cb.ax.tick_params(labelsize=7)
        cb.ax.minorticks_off()                  # (their labels are off anyway; laying them out was 0.1 s a page)
        cb.set_label("|relative error|", fontsize=8)
        fig.text(cb_rect[0], cb_rect[1] - 0.1 / fh, "■", color=NO_PREDICTION_RGB, fontsize=10, va="top")
        fig.text(cb_rect[0] + 0.16 / fw, cb_rect[1] - 0.12 / fh, "no prediction\n(background,\ndropped pixel)",
                 fontsize=6, va="top")
        path = out_dir / (f"{name}.png" if p == 0 else f"{name}-{p + 1}.png")
        info.sizes.append(save_figure(fig, path))
        info.paths.append(path)
        info.colorbar.append(_box(fw, fh, cb_rect))
    return info


def _confidence_layout(image_size) -> tuple[float, float, tuple, tuple]:
    H, W = image_size
    map_w = 4.0
    map_h = map_w * H / W
    fw, fh = 0.2 + map_w + 1.6, 0.55 + map_h + 0.95
    map_rect = (0.2 / fw, 0.95 / fh, map_w / fw, map_h / fh)
    cb_rect = ((0.2 + map_w + 0.2) / fw, 0.95 / fh, 0.2 / fw, map_h / fh)
    return fw, fh, map_rect, cb_rect


def confidence_colours(std: Tensor, unobservable: Tensor, lo: float, hi: float) -> Tensor:
    """``[H, W, 3]`` display colours of a confidence map: the posterior std (``[H, W]``; NaN = no sample) in
    :data:`CONFIDENCE_CMAP` on a log scale over ``[lo, hi]``, :data:`UNOBSERVABLE_RGB` (grey) where ``unobservable``,
    :data:`NO_SAMPLE_RGB` (black) where NaN."""
    _check_range(lo, hi)
    std = _image(std, "std")
    unobservable = _image(unobservable, "unobservable", std.shape)
    if std.dim() != 2 or unobservable.dtype != torch.bool:
        raise PlotError(f"std must be [H, W] and unobservable an [H, W] bool mask, got {tuple(std.shape)} and "
                        f"{unobservable.dtype}")
    rgb = _log_colours(std, CONFIDENCE_CMAP, lo, hi)
    rgb = torch.where(unobservable[..., None], torch.tensor(UNOBSERVABLE_RGB), rgb)
    return torch.where(torch.isnan(rgb), torch.tensor(NO_SAMPLE_RGB), rgb)


def plot_confidence(path, std: Tensor, unobservable: Tensor, name: str, units: str = "canonical units") -> FigureInfo:
    """A preview PNG of a confidence map with its colour bar: the marginal posterior std per texel (the largest over
    channels), observable texels in :data:`CONFIDENCE_CMAP` on a log scale over their own range (lower = better
    determined), unobservable texels grey and texels without a sample black, both named in the legend.

    Args:
        path: the ``.png`` to write (its folder must exist).
        std: ``[H, W]`` or ``[H, W, C]`` posterior std (NaN where no sample reads the texel), as in
            ``confidence_<name>.exr``.
        unobservable: ``[H, W]`` bool, the observed texels where the photos do not determine the parameter.
        name: the parameter's name, for the title; units: the std's unit, for the colour bar.

    Returns:
        :class:`FigureInfo` (one page; ``value_range`` the colour bar's (low, high)).
    """
    path = Path(path)
    if path.suffix.lower() != ".png" or not path.parent.is_dir():
        raise PlotError(f"path must be a .png in an existing folder, got {path}")
    std = _image(std, "std")
    if std.dim() == 3:
        std = torch.where(torch.isnan(std).any(-1), torch.full_like(std[..., 0], float("nan")), std.amax(-1))
    if std.dim() != 2:
        raise PlotError(f"std must be [H, W] or [H, W, C], got {tuple(std.shape)}")
    unobservable = _image(unobservable, "unobservable", std.shape)
    if unobservable.dtype != torch.bool:
        raise PlotError(f"unobservable must be a bool mask, got {unobservable.dtype}")
    if not isinstance(name, str) or not name:
        raise PlotError(f"name must be a non-empty string, got {name!r}")
    std = std.double()
    ok = torch.isfinite(std) & ~unobservable & (std > 0)
    if bool(ok.any()):
        lo, hi = float(std[ok].min()), float(std[ok].max())
    else:
        lo, hi = 1e-4, 1e-1
    if hi <= lo * 1.0001:
        lo, hi = lo / 2, hi * 2
    plt = _pyplot()
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Patch

    fw, fh, map_rect, cb_rect = _confidence_layout(tuple(std.shape))
    fig = plt.figure(figsize=(fw, fh), dpi=DPI)
    n_obs, n_un = int(ok.sum()), int(unobservable.sum())
    fig.text(0.2 / fw, 1 - 0.1 / fh, f"confidence of {name}", fontsize=11, weight="bold", va="top")
    fig.text(0.2 / fw, 1 - 0.33 / fh, f"{n_obs} texels observable, {n_un} unobservable"
             + ("" if n_obs else f" — {name} is not measured anywhere"), fontsize=8, va="top")
    _panel(fig, confidence_colours(std, unobservable, lo, hi), map_rect, fw, fh)
    cax = fig.add_axes(cb_rect)
    cb = fig.colorbar(ScalarMappable(LogNorm(lo, hi), CONFIDENCE_CMAP), cax=cax)
    cb.ax.tick_params(labelsize=7)
    cb.set_label(f"posterior std of {name} ({units}); lower = better determined", fontsize=7)
    fig.legend(handles=[Patch(facecolor=UNOBSERVABLE_RGB, edgecolor="k", label="grey: unobservable — the photos do "
                              "not determine it here (value filled, not measured)"),
                        Patch(facecolor=NO_SAMPLE_RGB, edgecolor="k", label="black: no sample (texel not seen, or "
                              "outside the UV charts)")],
               loc="lower left", bbox_to_anchor=(0.2 / fw, 0.05 / fh), fontsize=7, frameon=False)
    size = save_figure(fig, path)
    return FigureInfo(paths=[path], sizes=[size], colorbar=[_box(fw, fh, cb_rect)], value_range=(lo, hi))
