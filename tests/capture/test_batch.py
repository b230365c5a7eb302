"""shadecap batch: many datasets, each into its own folder; a failure recorded without stopping the others; a second
run skips what is done; the same on a Dask cluster."""

import json
import sys

import pytest

from capture.batch import BatchError, _connect, _parse_cluster, _share_of_cores, find_datasets, reconstruct_batch
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
    for bad, why in (("local:0", "positive number"), ("local:x", "positive number"), ("nowhere", "not a scheduler"),
                     (42, "must be a string")):
        with pytest.raises(BatchError, match=why):
            reconstruct_batch([captures / "a"], tmp_path / "o", cluster=bad, log=None)
    assert not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def dask_cluster():
    """A Client of two worker processes of one thread each on this machine, as ``cluster="local:2"`` starts them (and
    as `dask scheduler` + `dask worker --nthreads 1` run them elsewhere), and its scheduler's address."""
    distributed = pytest.importorskip("distributed", reason="the cluster tests need pip install 'dask[distributed]'")
    client, local, address = _connect(distributed, *_parse_cluster("local:2"))
    yield client, address
    client.close()
    local.close()


def test_on_a_dask_cluster_each_capture_is_a_task_failures_recorded_and_a_rerun_skips_the_done_ones(
        captures, dask_cluster, tmp_path, capsys):
    client, address = dask_cluster
    out = tmp_path / "out"
    assert main(["batch", str(captures), "--out", str(out), "--model", "lambert", "--pixel-centres",
                 "--cluster", address]) == 1
    record = json.loads((out / "batch.json").read_text())
    status = {c["dataset"].rsplit("/", 1)[-1]: c for c in record["captures"]}
    assert sorted(status) == ["a", "b", "broken"] and record["counts"] == {"done": 2, "skipped": 0, "failed": 1,
                                                                         "pending": 0}
    workers = set(client.nthreads())
    assert {status[n]["worker"] for n in status} <= workers          # every capture ran in a worker process
    assert status["a"]["status"] == status["b"]["status"] == "done" and status["a"]["model"] == "lambert"
    assert status["a"]["out"] == str(out / "a") and status["a"]["seconds"] > 0
    assert status["broken"]["status"] == "failed" and "scene.json" in status["broken"]["error"]
    assert not (out / "broken").exists()
    # the worker's reconstruction is this process's: the same χ² as a capture reconstructed here
    here = reconstruct_batch([captures / "a"], tmp_path / "here", model="lambert", footprint=False, log=None)
    assert here[0].worker is None
    assert status["a"]["chi2_per_residual"] == pytest.approx(here[0].chi2_per_residual, rel=1e-5)
    report = json.loads((out / "a" / "report.json").read_text())
    assert report["fit"]["chi2_per_residual"] == pytest.approx(status["a"]["chi2_per_residual"], rel=1e-9)
    assert (out / "b" / "albedo.exr").is_file()
    text = capsys.readouterr().out
    assert f"on the Dask cluster at {address}: 2 workers, 2 captures at a time" in text
    assert "[3/3] " in text and "broken: FAILED" in text and "2 done, 0 skipped, 1 failed" in text
    # resumable, here through a Client of that cluster (left open): the done captures are skipped, the broken one
    # tried again
    mtime = (out / "a" / "report.json").stat().st_mtime_ns
    lines = []
    items = reconstruct_batch([captures], out, model="lambert", footprint=False, log=lines.append, cluster=client)
    assert client.status == "running"
    assert [it.status for it in items] == ["skipped", "skipped", "failed"] and items[2].worker in workers
    assert (out / "a" / "report.json").stat().st_mtime_ns == mtime
    assert json.loads((out / "batch.json").read_text())["counts"] == {"done": 0, "skipped": 2, "failed": 1,
                                                                      "pending": 0}
    assert lines[0].startswith("[1/3] a: skipped") and lines[1].startswith("[2/3] b: skipped")
    assert lines[2] == f"on the Dask cluster at {address}: 2 workers, 2 captures at a time"
    assert lines[3].startswith("[3/3] broken: FAILED")
    # nothing pending: no cluster is reached (this address has no scheduler)
    assert [it.status for it in reconstruct_batch([captures / "a"], out, cluster="tcp://127.0.0.1:1", log=None)] \
        == ["skipped"]


def test_local_n_workers_run_one_capture_at_a_time_each_with_its_share_of_the_cores(dask_cluster):
    from dask.system import CPU_COUNT

    client, address = dask_cluster
    nthreads = client.nthreads()
    assert address.startswith("tcp://127.0.0.1:") and sorted(nthreads.values()) == [1, 1]
    # two workers on one machine: half the cores each; a machine the batch did not know: the worker's own threads
    for by_host, share in (({"127.0.0.1": 2}, CPU_COUNT // 2), ({}, CPU_COUNT)):
        assert client.gather([client.submit(_share_of_cores, by_host, workers=[w], pure=False)
                              for w in nthreads]) == [max(1, share)] * 2


def test_a_cluster_without_dask_or_its_scheduler_is_named_with_the_fix(captures, tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="the cluster tests need pip install 'dask[distributed]'")
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "0.5s"}), \
            pytest.raises(BatchError, match="could not reach a Dask scheduler at tcp://127.0.0.1:1 .*dask worker"):
        reconstruct_batch([captures / "a"], tmp_path / "o", cluster="tcp://127.0.0.1:1", log=None)
    monkeypatch.setitem(sys.modules, "distributed", None)            # as if dask were not installed
    with pytest.raises(BatchError, match=r"pip install 'dask\[distributed\]' \(or shadecap\[cluster\]\)"):
        reconstruct_batch([captures / "a"], tmp_path / "p", cluster="local:2", log=None)
    assert not (tmp_path / "p").exists()
