"""Time to a map error (capture.bench.race, scripts/mitsuba_race.py): the crossing times and ratios of the table,
and shadecap's error-against-time curve on photos Mitsuba 3 rendered (tests/fixtures/mitsuba)."""

import subprocess
import sys
from pathlib import Path

import pytest

from capture.bench.race import race_figure, race_table, shadecap_curve, time_to_error

ROOT = Path(__file__).resolve().parents[2]
TORUS = ROOT / "tests" / "fixtures" / "mitsuba" / "torus-lambert"


def _ev(pairs):
    return [{"seconds": t, "albedo_rmse_well_lit": e} for t, e in pairs]


#: An Adam-like run: falls, reaches its best 0.02 at 40 s, rises again.
RUN = {"lr": 0.001, "spp": 4, "evaluations": _ev([(80, 0.025), (0, 0.2), (10, 0.05), (20, 0.03), (40, 0.02)])}


def test_time_to_error_is_the_first_evaluation_as_low_in_time_order():
    ev = RUN["evaluations"]                     # given out of time order on purpose
    assert time_to_error(ev, 0.03) == 20        # equal counts as reached
    assert time_to_error(ev, 0.025) == 40       # 80 s also has 0.025, but later
    assert time_to_error(ev, 0.2) == 0
    assert time_to_error(ev, 0.019) is None
    with pytest.raises(ValueError, match="no evaluations"):
        time_to_error([], 0.1)
    with pytest.raises(ValueError, match="non-finite"):
        time_to_error(_ev([(1.0, float("nan"))]), 0.1)
    with pytest.raises(ValueError, match="finite"):
        time_to_error(ev, float("inf"))


def test_race_table_gives_each_crossing_and_ratio():
    shadecap = [{"steps": 3, "seconds": 3.0, "albedo_rmse_well_lit": 0.01},
                {"steps": 0, "seconds": 2.0, "albedo_rmse_well_lit": 0.03}]
    table = race_table(shadecap, [RUN])
    rows = [r for r in table.splitlines() if r.startswith("| 0 ") or r.startswith("| 3 ")]
    # sorted by shadecap's time; 0.03 first reached at 20 s = 10 × shadecap's 2 s
    assert rows[0] == "| 0 | 2.0 | 0.0300 | 20 s (**10 ×**) |"
    assert rows[1] == "| 3 | 3.0 | 0.0100 | never (best 0.0200 at 40 s) |"
    # the run's best (0.02 at 40 s) against shadecap's first fit as low (3 s): 13 × sooner
    assert "| Adam lr 0.001, 4 spp | 0.0200 | 40 s | 3.0 s | **13 ×** sooner |" in table
    worse = [{"steps": 0, "seconds": 2.0, "albedo_rmse_well_lit": 0.03}]
    assert "| none of its fits | – |" in race_table(worse, [RUN])
    with pytest.raises(ValueError, match="no evaluations"):
        race_table(shadecap, [{"lr": 0.1, "spp": 1, "evaluations": []}])


def test_shadecap_curve_on_mitsuba_photos(tmp_path):
    """More footprint steps, lower error on photos another renderer made; each point timed and measured."""
    pts = shadecap_curve(TORUS, [0, 2], "lambert", work=tmp_path)
    assert [p["steps"] for p in pts] == [0, 2]
    for p in pts:
        assert 0 < p["seconds"] < p["total"]
        assert 0 < p["albedo_rmse_well_lit"] < 0.1
    # the footprint steps fit the photos as area averages: measured 0.0444 → 0.0118 on this fixture
    assert pts[1]["albedo_rmse_well_lit"] < 0.6 * pts[0]["albedo_rmse_well_lit"]
    with pytest.raises(ValueError, match="budgets"):
        shadecap_curve(TORUS, [-1], "lambert", work=tmp_path)


def test_race_figure_writes_a_png(tmp_path):
    shadecap = [{"steps": 0, "seconds": 2.0, "albedo_rmse_well_lit": 0.03},
                {"steps": 3, "seconds": 3.0, "albedo_rmse_well_lit": 0.01}]
    path = tmp_path / "race.png"
    race_figure(shadecap, [RUN], path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, said", [(["--adam", "0.001:0:10"], "spp at least 1"),
                                        (["--adam", "fast"], "LR:SPP:SECONDS"),
                                        (["--steps", "1,-2"], "budgets")])
def test_script_rejects_bad_options(args, said):
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "mitsuba_race.py"), str(TORUS), *args],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and said in p.stderr, p.stderr


def test_script_rejects_a_file_that_is_not_an_adam_run(tmp_path):
    bad = tmp_path / "run.json"
    bad.write_text('{"evaluations": []}')
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "mitsuba_race.py"), str(TORUS), "--adam-json", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "needs lr, spp and evaluations" in p.stderr, p.stderr
