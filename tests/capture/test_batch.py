"""shadecap batch: many datasets, each into its own folder; a failure recorded without stopping the others; a second
run skips what is done."""

import json

import pytest

from capture.batch import BatchError, find_datasets, reconstruct_batch
from capture.cli import main
from capture.synth import make_synthetic, small_scene


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("captures")
    for name, seed in (("a", 0), ("b", 1)):
        make_synthetic(small_scene("lambert", image_size=24, texture_size=8, n_views=2, seed=seed), root / name)
    (root / "broken").mkdir()
    (root / "broken" / "scene.json").write_text("{not json")
    (root / "notes").mkdir()                                   # no scene.json: not a dataset, ignored
    return root


def test_a_failed_capture_is_recorded_and_the_others_finish_then_a_rerun_skips_them(captures, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["batch", str(captures), "--out", str(out), "--model", "lambert", "--pixel-centres"]) == 1
    record = json.loads((out / "batch.json").read_text())
    status = {c["dataset"].rsplit("/", 1)[-1]: c for c in record["captures"]}
    assert sorted(status) == ["a", "b", "broken"] and record["counts"] == {"done": 2, "skipped": 0, "failed": 1,
                                                                         "pending": 0}
    assert status["a"]["status"] == status["b"]["status"] == "done" and status["a"]["model"] == "lambert"
    assert status["a"]["chi2_per_residual"] is not None and status["a"]["seconds"] > 0
    assert status["broken"]["status"] == "failed" and "scene.json" in status["broken"]["error"]
    assert (out / "a" / "albedo.exr").is_file() and (out / "b" / "report.json").is_file()
    assert not (out / "broken").exists()
    text = capsys.readouterr().out
    assert "[3/3] broken: FAILED" in text and "2 done, 0 skipped, 1 failed" in text
    # resumable: the finished captures are skipped (their outputs untouched), the failed one is tried again
    mtime = (out / "a" / "report.json").stat().st_mtime_ns
    items = reconstruct_batch([captures], out, model="lambert", footprint=False, log=None)
    assert [it.status for it in items] == ["skipped", "skipped", "failed"]
    assert (out / "a" / "report.json").stat().st_mtime_ns == mtime


def test_bad_batches_fail_before_any_work(captures, tmp_path):
    with pytest.raises(BatchError, match="holds no scene.json"):
        find_datasets([captures / "notes"])
    with pytest.raises(BatchError, match="is not a folder"):
        find_datasets([tmp_path / "missing"])
    (tmp_path / "x" / "a").mkdir(parents=True)
    (tmp_path / "x" / "a" / "scene.json").write_text("{}")
    with pytest.raises(BatchError, match="two datasets are named 'a'"):
        find_datasets([captures / "a", tmp_path / "x"])
    assert find_datasets([captures / "a", captures / "a"]) == [captures / "a"]      # the same folder once
    with pytest.raises(BatchError, match="inside the dataset"):
        reconstruct_batch([captures / "a"], captures / "a" / "out", log=None)
    with pytest.raises(BatchError, match="sets \\['out_dir'\\] itself"):
        reconstruct_batch([captures / "a"], tmp_path / "o", out_dir="x", log=None)
