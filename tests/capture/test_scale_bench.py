"""The scale benchmark's arithmetic (capture.bench.scale): growth exponents and marginal memory from its rows, one
table per machine, and its argument checks. The runs themselves are benchmarks (docs/benchmarks.md, "Scale")."""

import pytest

from capture.bench.scale import ScaleError, scale_run, scale_table


def _row(machine, device, pixels, seconds, memory):
    return {"machine": machine, "views": 8, "image": 256, "tex": 256, "device": device, "synth_s": 0.0,
            "wall_s": seconds, "times": {"observe": 0.25 * seconds, "solve": 0.5 * seconds, "total": seconds},
            "pixels": pixels, "rays": 4 * pixels, "peak_rss_bytes": memory, "cuda_peak_bytes": None,
            "rmse": {"albedo": 0.01}}


def test_linear_time_and_affine_memory_give_exponent_one_and_the_slope():
    # time = 1e-5 s per pixel (exponent 1); memory = 500 MB fixed + 300 B per pixel (marginal 300)
    rows = [_row("box A", "cpu", px, 1e-5 * px, 500e6 + 300 * px) for px in (1e5, 4e5, 1.6e6)]
    rows.append(_row("box B", "cuda", 1e5, 3.0, 1e9))
    text = scale_table(rows)
    assert text.index("Machine: box A") < text.index("Machine: box B")
    assert "`cpu`: time ∝ pixels^1.00, solve ∝ pixels^1.00" in text
    assert "marginal memory 300 B per observed pixel" in text
    assert "`cuda`" not in text          # one configuration: no exponent is fitted from a single point
    assert text.count("| cpu | 8 × 256², 256² |") == 3


def test_a_texture_sweep_gets_its_own_exponent_and_stays_out_of_the_pixel_fit():
    # same pixels, maps 256² → 1024² (16× the texels): time 4× (texels^0.5), memory 2× (texels^0.25)
    rows = [_row("box", "cpu", 1e5, 10.0, 1e9)]
    for tex, t, m in ((512, 20.0, 1.414e9), (1024, 40.0, 2e9)):
        rows.append({**_row("box", "cpu", 1e5, t, m), "tex": tex})
    text = scale_table(rows)
    assert "`cpu`, 8 × 256², maps 256² … 1024²: time ∝ texels^0.50, peak memory ∝ texels^0.25" in text
    assert "∝ pixels^" not in text                   # one pixel count among the rows whose maps match the images


def test_the_figure_plots_a_texture_sweep_against_texels_below_the_pixel_sweep(monkeypatch, tmp_path):
    import capture.plots
    from capture.bench.scale import scale_figure

    figures = []
    monkeypatch.setattr(capture.plots, "save_figure", lambda fig, path: figures.append(fig))
    pixels = [_row("Box, 2 cores — earlier code: fast", "cpu", px, 1e-5 * px, 1e9) for px in (1e5, 4e5)]
    sweep = [{**_row("Box, 2 cores — earlier code: maps", "cpu", 1e5, t, 1e9), "tex": tex}
             for tex, t in ((256, 10.0), (1024, 40.0))]
    scale_figure(pixels + sweep, tmp_path / "f.png")
    axes = figures[0].axes
    assert len(axes) == 4
    lines = [ln for ln in axes[2].get_lines() if len(ln.get_xdata())]
    assert [list(ln.get_xdata()) for ln in lines] == [[256 ** 2, 1024 ** 2]] * 2        # total and the solve
    assert list(lines[0].get_ydata()) == [10.0, 40.0]
    # the two series' captions differ only after their colon: the legend names both whole
    texts = [t.get_text() for t in figures[0].legends[0].get_texts()]
    assert texts == ["cpu, 2 cores — earlier code: fast", "cpu, 2 cores — earlier code: maps"]
    figures.clear()
    scale_figure(pixels, tmp_path / "f.png")                    # no texture sweep: the pixel panels alone
    assert len(figures[0].axes) == 2 and [t.get_text() for t in figures[0].legends[0].get_texts()] == \
        ["cpu, 2 cores — earlier code"]


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "8"])
def test_bad_sizes_are_refused_before_any_work(bad, tmp_path):
    with pytest.raises(ScaleError, match="positive integer"):
        scale_run(bad, 64, 64, tmp_path)
    assert not any(tmp_path.iterdir())
