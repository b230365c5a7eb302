"""Helpers behind the benchmark and doc tools: growth exponents, generated markdown sections."""

import math

import pytest

from capture.bench.timing import growth_exponent
from capture.report import replace_section


@pytest.mark.parametrize("k", [0.5, 1.0, 2.0, 3.0])
def test_growth_exponent_recovers_a_power_law(k):
    xs = [4, 8, 16, 32, 64]
    assert growth_exponent(xs, [3.0 * x**k for x in xs]) == pytest.approx(k, abs=1e-12)


def test_growth_exponent_of_constant_plus_linear_is_between_0_and_1():
    xs = [1, 2, 4, 8]
    k = growth_exponent(xs, [10.0 + x for x in xs])
    assert 0.0 < k < 1.0 and not math.isnan(k)


def test_replace_section_keeps_hand_written_text(tmp_path):
    doc = tmp_path / "d.md"
    doc.write_text("# Title\n\nintro\n")
    replace_section(doc, "t", "first")
    replace_section(doc, "u", "other")
    replace_section(doc, "t", "second")
    text = doc.read_text()
    assert text.startswith("# Title\n\nintro\n")
    assert "second" in text and "first" not in text and "other" in text
    assert text.count("<!-- begin:t -->") == 1 and text.index("begin:t") < text.index("begin:u")
    assert [p.name for p in tmp_path.iterdir()] == ["d.md"]  # no temporary files left behind


def test_pareto_plot_writes_a_png(tmp_path):
    from capture.bench.reconstruction import plot_reconstruction_pareto

    rows = [{"rig": rig, "label": lab, "seconds": s, "rmse_observed": {"albedo": 0.1, "f0": 0.2, "roughness": 0.3},
             "rmse_observable": {"albedo": 0.001, "f0": 0.01, "roughness": float("nan")}}
            for rig in ("flash", "fixed") for lab, s in (("fast", 30.0), ("adam", 50.0))]
    png = tmp_path / "p.png"
    plot_reconstruction_pareto(rows, png)
    import cv2

    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] > 500 and img.std() > 1  # a real, non-blank figure


def test_extreme_truth_stress_configs():
    from capture.bench.stress import EXTREME_TRUTH, STRESS_SCENARIOS, _stress_config
    from capture.synth import build_scene

    (levels,) = [lv for _, field, lv, _ in STRESS_SCENARIOS if field == "uniform"]
    assert set(levels) == set(EXTREME_TRUTH)
    cfg, factor = _stress_config("uniform", "white f0")
    assert factor == 1.0 and cfg.uniform == {"f0": [1.0]}
    maps = build_scene(cfg).maps
    assert bool((maps["f0"] == 1.0).all()) and not bool((maps["roughness"] == maps["roughness"].flatten()[0]).all())
