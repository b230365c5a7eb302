"""Helpers behind the benchmark and doc tools: growth exponents, generated markdown sections."""

import math

import pytest

from capture.report import replace_section
from capture.scaling import growth_exponent


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
