"""The model throughput benchmark's rows (capture.bench.models)."""

import math

import materials
from capture.bench.models import model_throughput, run_models_benchmark


def test_throughput_rows_say_which_jacobian_the_fit_takes():
    closed = model_throughput(materials.get("cook-torrance"), n=2048, repeats=1)
    auto = model_throughput(materials.get("gotanda2012-layered"), n=2048, repeats=1)
    assert closed.jacobian_closed_form is True and auto.jacobian_closed_form is False
    for row in (closed, auto):
        for rate in (row.forward_per_s, row.forward_backward_per_s, row.jacobian_per_s):
            assert rate is not None and math.isfinite(rate) and rate > 0
    # a model without parameters (the measured NBRDF) has no per-sample Jacobian to time
    assert model_throughput(materials.get("measured"), n=256, repeats=1).jacobian_per_s is None


def test_the_table_has_a_jacobian_column(monkeypatch):
    monkeypatch.setattr(materials, "available", lambda: ["lambert", "gotanda2012-layered"])
    table = run_models_benchmark(n=512, compile_names=())
    rows = [line for line in table.splitlines() if line.startswith("| `")]
    assert len(rows) == 2
    assert rows[0].endswith("(closed form) |") and rows[1].endswith("(autograd) |")
