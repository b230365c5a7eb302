"""Outputs never lose data: checked before any work (never over, into or around an input; writable), written
atomically with the umask's permissions, nothing left behind on --force, an error or Ctrl-C; strict JSON."""

import contextlib
import errno
import io
import json
import math
import os
import stat
from pathlib import Path

import pytest
import torch

from capture.cli import main
from capture.outputs import OutputError, OutputWarning, atomic_folder, check_output, json_text, na_floats, na_text
from capture.synth import make_synthetic, small_scene
from renderer.imageio import read_exr, read_png, write_exr


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # the tiny solves below are dominated by OpenMP waiting for a busy core on a loaded machine (10× slower)
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _tree(root: Path) -> dict:
    """Every entry under ``root`` (and root itself) → (kind, size, mtime, mode): what 'untouched' means."""
    out = {}
    for p in [root, *sorted(root.rglob("*"))]:
        st = p.lstat()
        out[str(p.relative_to(root.parent))] = (stat.S_IFMT(st.st_mode), st.st_size, st.st_mtime_ns, st.st_mode)
    return out


def _run(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, err.getvalue()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A dataset, a reconstruction folder (its maps written by hand: no solve) and a mesh file, in one folder."""
    root = tmp_path_factory.mktemp("inputs")
    ds = make_synthetic(small_scene("lambert", image_size=16, texture_size=8, n_views=2), root / "ds")
    rec = root / "rec"
    rec.mkdir()
    write_exr(rec / "albedo.exr", torch.full((4, 4, 3), 0.5))
    meshes = root / "meshes"
    meshes.mkdir()
    (meshes / "m.obj").write_bytes((ds / "mesh.obj").read_bytes())
    (root / "link-to-ds").symlink_to(ds, target_is_directory=True)
    (root / "link-to-rec").symlink_to(rec, target_is_directory=True)
    return root


def test_no_command_writes_over_into_or_around_its_inputs(inputs):
    # each command with --out at, inside and around each of its inputs, with and without --force: refused before any
    # work, one line naming the input, and every input untouched (`reconstruct ds --out ds --force` deleted the
    # dataset; `export-atlas R --out R --force` the reconstruction). `demo` reads no input.
    ds, rec, mesh = inputs / "ds", inputs / "rec", inputs / "meshes" / "m.obj"
    cases = [(["reconstruct", ds, "--model", "lambert"], [ds, ds / "images", ds / "new", ds / "scene.json",
                                                           ds / "images" / "000.exr", inputs, inputs / "link-to-ds"]),
             (["reconstruct", ds / "scene.json", "--model", "lambert"], [ds, ds / "gt"]),
             (["export-atlas", rec], [rec, rec / "atlas", rec / "albedo.exr", inputs, inputs / "link-to-rec"]),
             (["export-atlas", inputs / "link-to-rec"], [rec, rec / "atlas"]),
             (["export-atlas", rec, ds], [ds, ds / "atlas"]),
             (["synth", "--config", "small", "--views", "1", "--mesh", mesh], [mesh, mesh.parent, inputs])]
    before = _tree(inputs)
    for argv, outs in cases:
        for out in outs:
            for force in ([], ["--force"]):
                rc, err = _run([*argv, "--out", out, *force])
                assert rc == 2, (argv, out, force, err)
                assert "an input" in err and "outside every input" in err and err.count("\n") == 1, err
                assert "Traceback" not in err
    assert _tree(inputs) == before


def test_an_unwritable_output_folder_is_refused_before_any_work(inputs, tmp_path, monkeypatch):
    # a read-only parent failed with an OSError traceback after the whole solve; now the probe refuses it up front
    import capture.export
    import capture.synth.scenes
    import renderer.gbuffer

    locked = tmp_path / "locked"
    locked.mkdir()
    real_mkdir = os.mkdir

    def mkdir(path, *a, **k):
        if Path(path).parent == locked:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_mkdir(path, *a, **k)

    def no_work(*a, **k):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(renderer.gbuffer, "render_gbuffer", no_work)
    monkeypatch.setattr(capture.export, "load_reconstruction", no_work)
    monkeypatch.setattr(capture.synth.scenes, "build_scene", no_work)
    for argv in (["reconstruct", inputs / "ds", "--model", "lambert"], ["export-atlas", inputs / "rec"],
                 ["synth", "--config", "small"], ["demo", "--small"]):
        rc, err = _run([*argv, "--out", locked / "out"])
        assert rc == 2, (argv, err)
        assert f"cannot write in {locked}" in err and "Permission denied" in err and "permissions" in err, err
        assert err.count("\n") == 1 and "Traceback" not in err
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_refused(tmp_path):
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="cannot write in"):
            check_output(locked / "out")
    finally:
        locked.chmod(0o755)


def test_an_os_error_while_writing_is_one_line_naming_the_output(inputs, tmp_path, monkeypatch):
    # e.g. the disk fills up half-way: one line naming the output (not the temporary folder), exit 2, nothing left
    real = Path.write_text

    def full(self, *a, **k):
        if self.name == "atlas.json":
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return real(self, *a, **k)

    monkeypatch.setattr(Path, "write_text", full)
    out = tmp_path / "atlas"
    rc, err = _run(["export-atlas", inputs / "rec", "--out", out, "--no-glb"])
    assert rc == 2 and "No space left on device" in err and str(out / "atlas.json") in err, err
    assert ".tmp" not in err and err.count("\n") == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_prints_one_line_exits_130_and_leaves_nothing(inputs, tmp_path, monkeypatch):
    import renderer.imageio

    real = renderer.imageio.write_png

    def interrupted(path, *a, **k):
        if Path(path).name == "tex2.png":
            raise KeyboardInterrupt
        return real(path, *a, **k)

    monkeypatch.setattr(renderer.imageio, "write_png", interrupted)
    rc, err = _run(["export-atlas", inputs / "rec", "--out", tmp_path / "atlas"])
    assert rc == 130 and "interrupted; nothing written" in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_ctrl_c_swallowed_by_trimesh_imports_still_stops_the_command(inputs, tmp_path, monkeypatch):
    # trimesh keeps an exception raised while importing an optional module (a Ctrl-C too) in a placeholder
    import trimesh.base
    from trimesh.exceptions import ExceptionWrapper

    monkeypatch.setattr(trimesh.base, "Index", ExceptionWrapper(KeyboardInterrupt()))
    rc, err = _run(["export-atlas", inputs / "rec", "--out", tmp_path / "atlas"])
    assert rc == 130 and "interrupted; nothing written" in err
    assert list(tmp_path.iterdir()) == []


def test_the_demo_names_the_outputs_it_finished_before_an_interrupt(capsys):
    from types import SimpleNamespace

    from capture.cli import run

    def demo(args):
        args.completed = ["out/dataset"]
        raise KeyboardInterrupt

    assert run("demo", demo, SimpleNamespace()) == 130
    assert "interrupted; nothing written by the step in progress (complete: out/dataset)" in capsys.readouterr().err


def test_the_reconstruct_script_handles_errors_like_the_command_line(inputs, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("reconstruct_script", Path(__file__).parents[2] / "scripts" /
                                                  "reconstruct.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    before = _tree(inputs / "ds")
    assert script.main([str(inputs / "ds"), "--out", str(inputs / "ds"), "--force"]) == 2
    err = capsys.readouterr().err
    assert "the output is the dataset folder" in err and err.count("\n") == 1 and "Traceback" not in err
    assert _tree(inputs / "ds") == before


# ------------------------------------------------------------------------------------------ one real run


@pytest.fixture(scope="module")
def run(inputs, tmp_path_factory):
    """Non-finite photo pixels of both signs and a view with no finite pixel on the object, reconstructed with
    --force over a *file*, then exported, under umask 022."""
    work = tmp_path_factory.mktemp("run")
    old = os.umask(0o022)
    try:
        ds = make_synthetic(small_scene("lambert", image_size=24, texture_size=8, n_views=3), work / "ds")
        img = read_exr(ds / "images" / "000.exr")
        on = torch.nonzero(img.sum(-1) > 0)
        for (y, x), v in zip(on[:3].tolist(), (-math.inf, math.inf, math.nan), strict=True):
            img[y, x, 0] = v
        write_exr(ds / "images" / "000.exr", img, allow_nonfinite=True)
        blind = torch.full_like(img, math.nan)
        blind[0, 0] = 0.0  # a background pixel: the loader refuses an image without any finite pixel
        write_exr(ds / "images" / "002.exr", blind, allow_nonfinite=True)
        (work / "recon").write_text("a stray file where the output goes")
        rc, err = _run(["reconstruct", ds, "--model", "lambert", "--holdout", "2", "--out", work / "recon",
                        "--force"])
        assert rc == 0, err
        rc, err2 = _run(["export-atlas", work / "recon", "--out", work / "atlas"])
        assert rc == 0, err2
    finally:
        os.umask(old)
    return work


def test_non_finite_pixels_of_either_sign_are_dropped_and_never_written(run):
    # a single -inf pixel failed the run at its very end ("views.png contains NaN/inf")
    report = json.loads((run / "recon" / "report.json").read_text())
    assert report["drops"]["nonfinite"] >= 3
    assert torch.isfinite(read_png(run / "recon" / "views.png")).all()
    for p in (run / "recon").glob("*.exr"):
        if not p.name.startswith("confidence_"):  # NaN there means 'not observed' (docs/reconstruction.md)
            assert torch.isfinite(read_exr(p)).all(), p


def test_report_is_strict_json_and_the_summary_prints_n_a(run):
    # the held-out view has no finite pixel on the object: no PSNR; report.json said NaN, the summary "nan–nan"
    text = (run / "recon" / "report.json").read_text()
    report = json.loads(text, parse_constant=lambda c: pytest.fail(f"report.json holds {c}"))
    held = [v for v in report["views"] if v.get("heldout")]
    assert held and held[0]["psnr"] is None
    summary = (run / "recon" / "summary.txt").read_text()
    assert "held-out views 2" in summary and "PSNR n/a" in summary and "nan" not in summary
    assert "NaN or inf" in summary  # the dataset's warnings are in the summary, their prose intact


def test_force_over_an_existing_output_leaves_nothing_behind(run):
    # the old output (here a file) was moved to a hidden .recon.old.PID and left there
    assert sorted(p.name for p in run.iterdir()) == ["atlas", "ds", "recon"]
    assert (run / "recon").is_dir()


def test_every_output_honours_the_umask(run):
    # recon and atlas folders were written 0700 / 0600 while datasets got 0755 / 0644
    for folder in ("ds", "recon", "atlas"):
        for p in [run / folder, *(run / folder).rglob("*")]:
            want = 0o755 if p.is_dir() else 0o644
            assert stat.S_IMODE(p.stat().st_mode) == want, (p, oct(p.stat().st_mode))


# ------------------------------------------------------------------------------------------ the helpers


def test_check_output_relations_and_existing(tmp_path):
    (tmp_path / "in" / "sub").mkdir(parents=True)
    inp = {tmp_path / "in": "the dataset folder"}
    for out, rel in ((tmp_path / "in", "is"), (tmp_path / "in" / "sub" / "x", "sits inside"), (tmp_path, "contains")):
        with pytest.raises(OutputError, match=f"the output {rel} the dataset folder"):
            check_output(out, inp, force=True)
    (tmp_path / "old").mkdir()
    with pytest.raises(OutputError, match="already exists.*--force"):
        check_output(tmp_path / "old", inp)
    assert check_output(tmp_path / "old", inp, force=True) == tmp_path / "old"
    assert check_output(tmp_path / "new" / "deeper", inp) == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # the probe creates nothing that stays
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_output(tmp_path / "file" / "out", inp)
    for bad in (".", "", "..", tmp_path / "."):
        with pytest.raises(OutputError):
            check_output(bad)
    # the same file under another name (a hard link here; a case-insensitive file system alike)
    (tmp_path / "in" / "mesh.obj").write_text("v")
    os.link(tmp_path / "in" / "mesh.obj", tmp_path / "hard.obj")
    with pytest.raises(OutputError, match="the output is the mesh file"):
        check_output(tmp_path / "hard.obj", {tmp_path / "in" / "mesh.obj": "the mesh file"}, force=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "hard.obj", "in", "old"]


@pytest.mark.parametrize("what", ["folder", "file", "link", "read-only subfolder"])
def test_atomic_folder_replaces_and_cleans_up(tmp_path, what):
    out, target = tmp_path / "out", tmp_path / "target"
    if what == "file":
        out.write_text("old")
    elif what == "link":
        target.mkdir()
        out.symlink_to(target, target_is_directory=True)
    else:
        (out / "sub").mkdir(parents=True)
        (out / "sub" / "f").write_text("old")
        if what == "read-only subfolder":
            (out / "sub").chmod(0o500)
    with pytest.raises(OutputError, match="already exists|appeared"), atomic_folder(out) as tmp:
        (tmp / "new").write_text("new")
    with atomic_folder(out, force=True) as tmp:
        (tmp / "new").write_text("new")
    assert (out / "new").read_text() == "new" and not out.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["out", "target"] if what == "link" else ["out"])


def test_atomic_folder_leaves_the_old_output_on_failure_or_interrupt(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep").write_text("old")
    for exc in (ValueError("bad"), KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left on device")):
        with pytest.raises((ValueError, KeyboardInterrupt, OutputError)) as info, \
                atomic_folder(out, force=True) as tmp:
            (tmp / "half").write_text("half")
            raise exc
        if isinstance(exc, OSError):
            assert info.type is OutputError and "No space left on device" in str(info.value)
            assert str(out) in str(info.value) and "nothing was written" in str(info.value)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and (out / "keep").read_text() == "old"


def test_atomic_folder_gives_the_umask_permissions(tmp_path):
    old = os.umask(0o027)
    try:
        with atomic_folder(tmp_path / "o") as tmp:
            (tmp / "d").mkdir()
            write_exr(tmp / "d" / "x.exr", torch.zeros(2, 2, 3))
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "o").stat().st_mode) == 0o750
    assert stat.S_IMODE((tmp_path / "o" / "d").stat().st_mode) == 0o750
    assert stat.S_IMODE((tmp_path / "o" / "d" / "x.exr").stat().st_mode) == 0o640


def test_a_previous_output_that_cannot_be_removed_is_named(tmp_path, monkeypatch):
    import capture.outputs

    (tmp_path / "out").mkdir()

    def stuck(path):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(capture.outputs, "_remove", stuck)
    with pytest.warns(OutputWarning, match="could not be removed.*delete it"), \
            atomic_folder(tmp_path / "out", force=True) as tmp:
        (tmp / "new").write_text("new")
    assert (tmp_path / "out" / "new").exists()


def test_strict_json_and_n_a():
    x = {"a": float("nan"), "b": [1.0, float("inf"), torch.tensor([0.5, float("-inf")])], "c": Path("p")}
    assert json.loads(json_text(x)) == {"a": None, "b": [1.0, None, [0.5, None]], "c": "p"}
    assert f"{na_floats([float('nan')])[0]:.1f}" == "n/a"
    assert na_text("PSNR nan–nan dB | nan / nan (nan%) | NaN or inf pixels") == \
        "PSNR n/a dB | n/a / n/a (n/a) | NaN or inf pixels"
