"""The shadecap command line: listing, user errors (one line, exit 2, nothing written), the demo."""

import pytest

import materials
from capture.cli import main


def test_models_lists_every_model_with_its_parameters(capsys):
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    for name in materials.available():
        assert name in out
    assert "params: albedo, f0, roughness" in out


def test_models_lists_a_model_whose_data_is_missing_and_says_why(tmp_path, monkeypatch, capsys):
    # without the MERL NBRDF weights (a checkout without shared/, or $SHADECAP_NBRDF_DIR elsewhere) the listing still
    # works: the measured model is named with the reason it cannot be built here
    monkeypatch.setenv("SHADECAP_NBRDF_DIR", str(tmp_path))
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert "measured" in out and "unavailable here: NBRDF weights not found" in out and str(tmp_path) in out
    assert "params: albedo, f0, roughness" in out


def test_user_errors_print_one_line_and_exit_2(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("shadecap reconstruct: error:") and "missing" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_unknown_model_is_named_with_the_alternatives(tmp_path, capsys):
    assert main(["synth", "--config", "small", "--model", "no-such-model", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "no-such-model" in err and "lambert" in err
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_small_demo_runs_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--small", "--model", "lambert", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "[3/3]" in text and "total" in text
    for rel in ("dataset/scene.json", "recon/albedo.exr", "recon/report.json", "atlas/atlas.json"):
        assert (out / rel).exists(), rel
    assert main(["demo", "--small", "--out", str(out)]) == 2  # exists, no --force


def test_known_values_are_parsed_and_bad_ones_named(tmp_path, capsys):
    import argparse

    from capture.cli import parse_known_value

    assert parse_known_value("coat_ior=1.5") == ("coat_ior", [1.5])
    assert parse_known_value("absorption=0.1,0.2,0.3") == ("absorption", [0.1, 0.2, 0.3])
    for bad in ("coat_ior", "coat_ior=", "=1.5", "coat_ior=high"):
        with pytest.raises(argparse.ArgumentTypeError, match="NAME=VALUE"):
            parse_known_value(bad)
    with pytest.raises(SystemExit):
        main(["reconstruct", str(tmp_path / "d"), "--out", str(tmp_path / "o"), "--known", "coat_ior"])
    assert "NAME=VALUE" in capsys.readouterr().err


def test_pooled_zero_on_the_command_line_turns_the_static_light_default_off(tmp_path, capsys):
    # `--pooled 0` must reach reconstruct as pooled=0 (off), not be dropped as falsy and become the rig's default
    import json

    from capture.synth import make_synthetic, small_scene

    make_synthetic(small_scene("ggx-lambert", image_size=32, texture_size=8, n_views=3, light_rig="fixed"),
                   tmp_path / "d")
    for flag, block in ((["--pooled", "0"], 0), ([], 4)):
        out = tmp_path / f"o{block}"
        assert main(["reconstruct", str(tmp_path / "d"), "--model", "ggx-lambert", "--out", str(out), *flag]) == 0
        assert json.loads((out / "report.json").read_text())["fit"]["pooled"]["block"] == block
    capsys.readouterr()


def test_holdout_views_on_the_command_line(tmp_path, capsys):
    # `--holdout 0,2` reaches reconstruct: those views are re-rendered but not fitted; a bad list is named, exit 2
    import argparse
    import json

    from capture.cli import parse_views
    from capture.synth import make_synthetic, small_scene

    assert parse_views("3,7") == [3, 7] and parse_views("4") == [4]
    with pytest.raises(argparse.ArgumentTypeError, match="separated by commas"):
        parse_views("3;7")
    make_synthetic(small_scene("ggx-lambert", image_size=32, texture_size=8, n_views=3), tmp_path / "d")
    assert main(["reconstruct", str(tmp_path / "d"), "--model", "ggx-lambert", "--out", str(tmp_path / "o"),
                 "--holdout", "0,2"]) == 0
    views = json.loads((tmp_path / "o" / "report.json").read_text())["views"]
    assert [v["view"] for v in views if v.get("heldout")] == [0, 2]
    assert main(["reconstruct", str(tmp_path / "d"), "--model", "ggx-lambert", "--out", str(tmp_path / "x"),
                 "--holdout", "0,1,2"]) == 2
    assert "leaves no view to fit" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_bin_on_the_command_line_fits_the_binned_photos(mitsuba_scene, tmp_path, capsys):
    # `--bin 2` reaches reconstruct as photo_bin=2: the report counts the binned pixels and the summary says so
    import json

    out = tmp_path / "o"
    assert main(["reconstruct", str(mitsuba_scene("torus-lambert")), "--model", "lambert", "--out", str(out),
                 "--bin", "2"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["samples"]["bin"] == 2 and report["samples"]["pixels"] == 8 * 64 * 64
    assert "(photos binned 2×2)" in (out / "summary.txt").read_text()
    assert main(["reconstruct", str(mitsuba_scene("torus-lambert")), "--model", "lambert", "--out",
                 str(tmp_path / "x"), "--bin", "0"]) == 2
    assert "photo_bin must be a positive integer" in capsys.readouterr().err


def _script(name: str):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"{name}_script", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_scripts_are_the_commands_under_their_own_name(tmp_path, capsys):
    # one parser per command: the script's --help, usage and error lines name the script, not `shadecap ...`
    import json

    from capture.cli import COMMANDS, build_parser, command_parser
    from capture.synth import make_synthetic, small_scene

    for script, command in (("reconstruct", "reconstruct"), ("export_atlas", "export-atlas"),
                            ("make_synthetic", "synth")):
        with pytest.raises(SystemExit):
            _script(script).main(["--help"])
        out = capsys.readouterr().out
        assert out.startswith(f"usage: {script}.py ") and "shadecap" not in out.split("\n\n")[0]
        sub = build_parser()._subparsers._group_actions[0].choices[command]
        flags = lambda p: [(tuple(a.option_strings), a.dest, a.default) for a in p._actions]  # noqa: E731
        assert flags(command_parser(command, f"{script}.py")) == flags(sub)
    assert set(COMMANDS) == {"demo", "synth", "reconstruct", "batch", "export-atlas", "import", "calibrate-lights",
                             "merge-hdr", "models"}
    assert _script("reconstruct").main([str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.startswith("reconstruct.py: error:")
    # the fast path's options the script used to have alone reach the solver from either entry point
    make_synthetic(small_scene("ggx-lambert", image_size=32, texture_size=8, n_views=3), tmp_path / "d")
    flags = ["--iterations", "3", "--grid", "4", "--schedule", "staged", "--smoothness", "0.5",
             "--sampling", "nearest", "--threads", "1", "--float64"]
    assert _script("reconstruct").main([str(tmp_path / "d"), "--model", "ggx-lambert", "--out", str(tmp_path / "o"),
                                        *flags]) == 0
    options = json.loads((tmp_path / "o" / "report.json").read_text())["fit"]["options"]
    assert (options["iterations"], options["grid"], options["schedule"], options["smoothness"],
            options["sampling"]) == (3, 4, "staged", 0.5, "nearest")
    capsys.readouterr()


def test_solver_flags_are_generated_from_the_fit_options():
    """Every FitOptions field declared with a flag is a `reconstruct` flag of its type and choices, parsed back to
    the option's name; a flag not given stays out (the option's default applies); a bad value is argparse's error."""
    import dataclasses

    from capture.cli import build_parser, fit_option_values
    from capture.fit.options import FitOptions

    flags = dict(FitOptions.cli_flags())
    assert {"iterations", "pooled", "footprint_iterations", "cg_iterations", "anchor_weight"} <= set(flags)
    assert set(flags) <= set(FitOptions.names())
    parser = build_parser()
    args = parser.parse_args(["reconstruct", "d", "--out", "o", "--footprint-iterations", "2", "--schedule", "staged",
                              "--anchor-weight", "0.1", "--pooled", "0"])
    assert fit_option_values(args) == {"footprint_iterations": 2, "schedule": "staged", "anchor_weight": 0.1,
                                       "pooled": 0}
    assert fit_option_values(parser.parse_args(["reconstruct", "d", "--out", "o"])) == {}
    # every generated value is one FitOptions accepts
    dataclasses.replace(FitOptions(), **fit_option_values(args))
    with pytest.raises(SystemExit):
        parser.parse_args(["reconstruct", "d", "--out", "o", "--schedule", "sometimes"])
