"""Time to a map error (capture.bench.race, scripts/mitsuba_race.py): the crossing times and ratios of the table,
and shadecap's error-against-time curve on photos Mitsuba 3 rendered (tests/fixtures/mitsuba)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from capture.bench.race import error_key, flat_errors, race_figure, race_table, shadecap_curve, time_to_error

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


def test_race_on_another_error_names_it_and_needs_it_on_both_sides():
    key = error_key("roughness", "well_lit_visible_highlight")
    assert key == "roughness_rmse_well_lit_visible_highlight"
    by_set = {"well_lit": {"texels": 10, "albedo": 0.1, "roughness": 0.3},
              "well_lit_visible_highlight": {"texels": 4, "roughness": 0.05}}
    assert flat_errors(by_set) == {"albedo_rmse_well_lit": 0.1, "roughness_rmse_well_lit": 0.3, key: 0.05}
    run = {"lr": 0.01, "spp": 4, "evaluations": [{"seconds": 0, key: 0.2}, {"seconds": 30, key: 0.04},
                                                 {"seconds": 60, key: 0.03}]}
    shadecap = [{"steps": 0, "seconds": 2.0, key: 0.05}, {"steps": 6, "seconds": 6.0, key: 0.01}]
    table = race_table(shadecap, [run], key)
    assert "| footprint steps | shadecap: seconds to the maps | visible-highlight roughness RMSE |" in table
    assert "| 0 | 2.0 | 0.0500 | 30 s (**15 ×**) |" in table          # 0.04 ≤ 0.05 first at 30 s
    assert "| 6 | 6.0 | 0.0100 | never (best 0.0300 at 60 s) |" in table
    assert "| Adam lr 0.01, 4 spp | 0.0300 | 60 s | 6.0 s | **10 ×** sooner |" in table
    # a run whose start was its best never improved: no ratio; a run at its best before shadecap's first fit was
    # sooner, and the table says by how much shadecap was later
    flat = {"lr": 0.02, "spp": 4, "evaluations": [{"seconds": 0, key: 0.09}, {"seconds": 30, key: 0.2}]}
    early = {"lr": 0.05, "spp": 4, "evaluations": [{"seconds": 0, key: 0.5}, {"seconds": 1, key: 0.06},
                                                   {"seconds": 9, key: 0.3}]}
    table = race_table(shadecap, [flat, early], key)
    assert "| 0 | 2.0 | 0.0500 | never (best 0.0900 its start) | never (best 0.0600 at 1 s) |" in table
    assert "| Adam lr 0.02, 4 spp | 0.0900 | its start (never improved) | 2.0 s | – |" in table
    assert "| Adam lr 0.05, 4 spp | 0.0600 | 1 s | 2.0 s | 2.0 × later |" in table
    with pytest.raises(ValueError, match="no 'albedo_rmse_well_lit' error"):
        race_table(shadecap, [run])                                    # the default key: neither side has it
    with pytest.raises(ValueError, match="keys must name"):
        race_figure(shadecap, [run], "unused.png", keys=[])


def test_shadecap_curve_on_mitsuba_photos(tmp_path):
    """More footprint steps, lower error on photos another renderer made; each point timed and measured."""
    seen = []
    pts = shadecap_curve(TORUS, [0, 2], "lambert", work=tmp_path, on_point=seen.append)
    assert [p["steps"] for p in pts] == [0, 2] and seen == pts          # each point reported as its fit ends
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
    # one panel per error
    both = [{**p, "f0_rmse_well_lit": 2 * p["albedo_rmse_well_lit"]} for p in shadecap]
    run = {**RUN, "evaluations": [{**e, "f0_rmse_well_lit": 0.1} for e in RUN["evaluations"]]}
    race_figure(both, [run], tmp_path / "two.png", keys=["albedo_rmse_well_lit", "f0_rmse_well_lit"])
    assert (tmp_path / "two.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, said", [(["--adam", "0.001:0:10"], "spp at least 1"),
                                        (["--adam", "fast"], "LR:SPP:SECONDS"),
                                        (["--steps", "1,-2"], "budgets"),
                                        (["--metric", "albedo"], "MAP:SET"),
                                        (["--metric", "f0:well_lit"], "not an error both sides measure")])
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


def test_scale_race_twin_is_a_scene_the_adam_baseline_maps(tmp_path):
    """benchmark.py scale --race: the configuration's twin in the GGX + Lambert (F = 1) model is raced on the
    albedo and the three maps on the visible highlights; the scale scene itself (Schlick Fresnel) is refused."""
    import importlib.util

    from capture.bench.scale import RACE_MODEL, race_dataset
    from capture.dataset import load_dataset, model_spec

    spec = importlib.util.spec_from_file_location("mitsuba_race_script", ROOT / "scripts" / "mitsuba_race.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    twin = race_dataset(2, 32, 16, tmp_path)
    assert model_spec(load_dataset(twin, check_images=False).gt.model) == model_spec(RACE_MODEL)
    assert module.race_keys(twin) == ["albedo_rmse_well_lit", *module.SPECULAR_KEYS]
    assert race_dataset(2, 32, 16, tmp_path) == twin                      # made once
    schlick = tmp_path / "schlick"
    subprocess.run([sys.executable, "-m", "capture.cli", "synth", "--out", str(schlick), "--views", "2", "--size", "32",
                    "--tex", "16"], check=True, capture_output=True, timeout=300)
    with pytest.raises(module.RaceError, match="not a Lambert or Lambert \\+ GGX"):
        module.race_keys(schlick)
    # the twin differs from the scale scene in its Fresnel term only: the same maps (and rig)
    a, b = load_dataset(twin, check_images=False), load_dataset(schlick, check_images=False)
    assert all(torch.equal(a.gt.maps[k], b.gt.maps[k]) for k in ("albedo", "f0", "roughness"))
    assert all(torch.equal(v.camera.K, w.camera.K) and torch.equal(v.camera.R, w.camera.R)
               for v, w in zip(a.views, b.views, strict=True))


def test_scale_race_options_are_checked_before_any_work(tmp_path):
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "benchmark.py"), "scale", "--configs", "none",
                        "--race", "2x32x16", "--race-steps", "1,-2", "--work", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "budgets must be ≥ 0" in p.stderr, p.stderr
    assert not any(tmp_path.iterdir())


def test_script_makes_the_tables_again_from_a_saved_race(tmp_path):
    saved = {"dataset": str(TORUS), "machine": "box", "note": "Every run in one process.",
             "shadecap": [{"steps": 0, "seconds": 2.0, "albedo_rmse_well_lit": 0.03}], "adam": [RUN]}
    path = tmp_path / "race.json"
    path.write_text(json.dumps(saved))
    out = tmp_path / "bench.md"
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "mitsuba_race.py"), str(TORUS), "--from-json",
                        str(path), "--out", str(out), "--block", "race-test"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    text = out.read_text()
    assert "<!-- begin:race-test -->\nMachine: box. Every run in one process. (Tables made from race.json.)" in text
    assert "| 0 | 2.0 | 0.0300 | 20 s (**10 ×**) |" in text
    path.write_text('{"shadecap": []}')
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "mitsuba_race.py"), str(TORUS), "--from-json",
                        str(path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "not a race saved by --json" in p.stderr, p.stderr
