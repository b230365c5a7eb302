"""summary.txt by hand: the error table, maps without an observable texel named in words, the coverage advice."""

import math

from capture.outputs import na_floats, na_text
from capture.reconstruct import Report, _summary


def _report():
    r = Report(model="ggx-lambert", solver="fast", out_dir="o")
    row = lambda rmse, mx, n: {"rmse": rmse, "max": mx, "texels": n}  # noqa: E731
    r.errors = {"maps": {"albedo": row(0.01, 0.2, 100), "roughness": row(0.09, 0.3, 100)},
                "maps_observable": {"albedo": row(0.002, 0.03, 50), "roughness": row(math.nan, math.nan, 0)},
                "observability": {"albedo": {"flagged_share": 0.98}, "roughness": {"flagged_share": 1.0}}}
    r.coverage = {"observable_fraction": {"albedo": 0.5, "roughness": 0.0},
                  "directions": {"texels": 1000, "cos": 0.3, "highlight_deg": 10.0, "block": 1,
                                 "unseen": {"fraction": 0.23}, "unlit": {"fraction": 0.0},
                                 "no_highlight": {"fraction": 0.4},
                                 "advice": ["add views from below (−z; mean normal (0.00, 0.00, -1.00)): 23% of the "
                                            "surface texels are never seen at n·v > 0.3"]}}
    r.views = [{"view": 0, "psnr": 40.0, "ssim": 0.99}]
    return r


def test_summary_error_table_words_and_advice():
    text = na_text(_summary(Report(**na_floats(_report().to_dict()))))
    lines = text.splitlines()
    head = next(i for i, x in enumerate(lines) if x.startswith("errors vs ground truth"))
    # a header row naming each column, a rule, one row per map with the columns lined up under their names
    assert lines[head + 1].split() == ["map", "observed", "texels", "observable", "texels", "observable", "flagged",
                                       "share"]
    assert set(lines[head + 2].strip()) <= {"-", " "}
    albedo, rough = lines[head + 3], lines[head + 4]
    assert albedo.split()[:4] == ["albedo", "0.01000", "/", "0.20000"] and "50.0%" in albedo and "98.0%" in albedo
    assert albedo.index("0.00200") == lines[head + 1].index("observable texels")
    assert "none observable" in rough
    assert "  roughness: not measured — no texel is observable" in text
    assert "nan" not in text
    assert "true maps" not in text                      # no column of texels determined at the truth here
    assert "directions the photos miss, of 1000 surface texels: 23% never seen at n·v > 0.3" in text
    assert "advice: add views from below (−z" in text
    r = _report()
    r.coverage["directions"]["advice"] = []
    assert "advice: none" in _summary(r)


def test_a_map_without_an_observable_texel_is_named_filled_or_regularised_as_it_was_written():
    r = _report()
    r.coverage["unobservable_kept"] = {"albedo": 0, "roughness": 100}
    text = _summary(r)
    assert "  roughness: not measured texel by texel — no texel is observable on its own (its map holds the fit's " \
           "regularised values)" in text and "filled" not in text
    r.coverage["unobservable_kept"]["roughness"] = 0
    assert "  roughness: not measured — no texel is observable (its map is filled, not measured)" in _summary(r)


def _coverage_warnings(kept: bool, resolved_fraction: float | None) -> list[str]:
    """The warnings of ``_report_coverage`` for a Lambert fit whose albedo is unobservable in all 4 of its observed
    texels (of 6), its values kept or filled."""
    from types import SimpleNamespace

    import torch

    from capture.fit.layout import FitResult
    from capture.reconstruct import _report_coverage

    observed = torch.tensor([[True, True, False], [True, True, False]])
    unobservable = {"albedo": observed.clone()}
    filled = {"albedo": ~observed if kept else torch.ones_like(observed)}
    info = {} if resolved_fraction is None else {"resolved_fraction": resolved_fraction}
    fit = FitResult(maps={}, observed=observed, unobservable=unobservable, filled=filled, confidence={},
                    sensitivity={}, history=[], iterations=0, time_s=0.0, solver="fast", info=info, raw={})
    rep = Report(model="lambert", solver="fast", out_dir="o")
    _report_coverage(rep, fit, SimpleNamespace(sampling="footprint", obs=None), torch.ones(2, 3))
    assert rep.coverage["unobservable_kept"] == {"albedo": 4 if kept else 0}
    return rep.warnings


def test_the_coverage_warning_says_whether_an_unobservable_map_was_kept_or_filled_and_why():
    # kept (maps finer than the photos, fitted coarse to fine: the regularised solution), no texel resolved
    (w,) = _coverage_warnings(True, 0.0)
    assert w.startswith("parameter 'albedo' is unobservable in every observed texel (no pixel takes enough of any "
                        "texel to determine it: the maps are finer than the photos resolve): its map holds the fit's "
                        "regularised values") and "filled" not in w and "confidence_albedo.exr" in w
    (w,) = _coverage_warnings(False, 0.3)               # filled: the per-texel fit's values were arbitrary
    assert w == ("parameter 'albedo' is unobservable in every observed texel (e.g. no highlight seen anywhere): its "
                 "map is filled with defaults, not measured")
    (w,) = _coverage_warnings(True, None)               # kept without pixel footprints: the sharing's materials
    assert "(e.g. no highlight seen anywhere): its map holds the fit's regularised values" in w


def test_summary_names_the_solver_options_that_differ_from_the_defaults():
    from capture.fit.options import FitOptions

    r = _report()
    assert "solver options" not in _summary(r)                          # adam: no options in the report
    r.fit["options"] = FitOptions.of(sampling="bilinear", footprint_iterations=2).to_dict()
    assert "solver options: sampling=bilinear, footprint_iterations=2\n" in _summary(r)
    r.fit["options"] = FitOptions().to_dict()
    assert "solver options: defaults\n" in _summary(r)


def test_summary_first_line_reports_peak_memory():
    r = _report()
    assert "peak memory" not in _summary(r).splitlines()[0]
    r.memory = {"peak_rss_bytes": 3 * 2 ** 30 // 2, "cuda_peak_bytes": 2 ** 30}
    assert _summary(r).splitlines()[0].endswith("  peak memory 1.50 GiB  CUDA peak 1.00 GiB")
    r.memory["budget_bytes"] = 2 ** 31
    assert _summary(r).splitlines()[0].endswith("  peak memory 1.50 GiB  CUDA peak 1.00 GiB  budget 2.00 GiB")
