"""Where the fit runs (renderer.device, ``--device``): the spellings, the errors on a machine without CUDA, the views
spread over CPU threads (``per_view``), and — on a
machine with a GPU (``gpu`` marker; run with the device tool) — CUDA reconstructions and renders that agree with the
CPU's within float32 rounding on photos Mitsuba 3 rendered."""

import pytest
import torch

from capture.reconstruct import ReconstructionError, reconstruct
from renderer.device import DeviceError, resolve_device

NO_CUDA = not torch.cuda.is_available()


def test_auto_is_cuda_exactly_when_torch_sees_a_gpu():
    assert resolve_device("auto") == resolve_device(None)
    assert resolve_device("auto").type == ("cpu" if NO_CUDA else "cuda")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")


@pytest.mark.parametrize("bad", ["GPU0", "tpu", "cuda:x", 3, ["cpu"]])
def test_unknown_devices_name_the_spellings(bad):
    with pytest.raises(DeviceError, match="auto.*cpu.*cuda"):
        resolve_device(bad)


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_cuda_without_a_gpu_says_what_to_do_before_any_work(tmp_path, monkeypatch):
    with pytest.raises(DeviceError, match="--device cpu"):
        resolve_device("cuda")
    # reconstruct fails on its argument, before reading the dataset (the loader would raise otherwise)
    import capture.dataset

    monkeypatch.setattr(capture.dataset, "load_dataset", lambda *a, **k: pytest.fail("dataset read"))
    with pytest.raises(ReconstructionError, match="--device cpu"):
        reconstruct(tmp_path / "ds", model="lambert", out_dir=tmp_path / "out", device="cuda", progress=False)


# -- on a GPU ------------------------------------------------------------------------------------------------------

@pytest.mark.gpu
@pytest.mark.parametrize("name, model", [("torus-lambert", "lambert"),
                                         ("sphere-ggx-lambert", "lambert+microfacet(D=ggx,G=smith,F=none)")])
def test_cuda_reconstruction_matches_the_cpu(name, model, mitsuba_scene, tmp_path):
    """The same fit on both devices: the errors against the ground truth agree to a few 1e-4 (float32 sums in
    another order take the iterations along slightly different paths), χ² to 2 %."""
    runs = {d: reconstruct(mitsuba_scene(name), model=model, out_dir=tmp_path / d, device=d, progress=False)
            for d in ("cpu", "cuda")}
    assert runs["cuda"].device.startswith("cuda") and runs["cpu"].device == "cpu"
    assert runs["cuda"].memory["cuda_peak_bytes"] > 0
    chi2 = [runs[d].fit["chi2_per_residual"] for d in ("cpu", "cuda")]
    assert chi2[1] == pytest.approx(chi2[0], rel=0.02)
    for key, errs in runs["cpu"].errors["maps_by_texel_set"]["well_lit"].items():
        if key != "texels" and isinstance(errs, float):
            assert runs["cuda"].errors["maps_by_texel_set"]["well_lit"][key] == pytest.approx(errs, abs=5e-4), key


@pytest.mark.gpu
def test_cuda_synthetic_photos_match_the_cpu():
    from capture.synth import build_scene, render_scene, small_scene

    cfg = small_scene("ggx-lambert", image_size=48, texture_size=32, n_views=2, supersample=2)
    scene = build_scene(cfg)
    cpu, _ = render_scene(scene, cfg, device="cpu")
    gpu, _ = render_scene(scene, cfg, device="cuda")
    for a, b in zip(cpu, gpu, strict=True):
        assert b.device.type == "cpu"
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)


def test_per_view_keeps_the_order_ticks_in_order_and_restores_the_thread_count():
    import threading

    from renderer.device import per_view

    threads = torch.get_num_threads()
    seen, ticks = {}, []
    torch.set_num_threads(2)
    try:
        def work(i):
            seen[i] = (torch.get_num_threads(), threading.get_ident())
            return i * i

        out = per_view(work, 5, done=lambda: ticks.append(len(ticks)))
        assert out == [0, 1, 4, 9, 16] and ticks == [0, 1, 2, 3, 4]
        assert {n for n, _ in seen.values()} == {1}                 # one torch thread in each worker
        assert torch.get_num_threads() == 2                         # restored
        torch.set_num_threads(1)                                    # one core: in the calling thread, as it is
        seen.clear()
        assert per_view(work, 3) == [0, 1, 4]
        assert {t for _, t in seen.values()} == {threading.get_ident()}
        with pytest.raises(ZeroDivisionError):                      # a view's error reaches the caller
            per_view(lambda i: 1 // (i - 1), 3)
    finally:
        torch.set_num_threads(threads)


def test_block_sizes_grow_on_a_gpu_only():
    from renderer.device import CUDA_BLOCK_FACTOR, block_size

    assert block_size(1 << 18, "cpu") == 1 << 18
    assert block_size(97, torch.device("cpu")) == 97
    assert block_size(97, "cuda") == 97 * CUDA_BLOCK_FACTOR > 97      # a device name: no GPU needed to ask
    for bad in (0, -3, 2.5, True, "8"):
        with pytest.raises(ValueError, match="positive integer"):
            block_size(bad, "cpu")


def test_the_command_line_keeps_freed_temporaries_in_glibcs_heap(monkeypatch):
    # tune_allocator sets glibc's mmap threshold (M_MMAP_THRESHOLD = -3) and trim threshold (M_TRIM_THRESHOLD = -1) to
    # the module's values, says False where there is no glibc, and every command runs after it
    import renderer.device as device
    from capture import cli

    calls = []

    def fake(name):
        return (lambda param, value: calls.append((param, value)) or 1) if name == "mallopt" else None

    monkeypatch.setattr(device, "_libc_function", fake)
    assert device.tune_allocator() is True
    assert calls == [(-3, 32 << 20), (-1, 256 << 20)] == [(-3, device.MMAP_THRESHOLD), (-1, device.TRIM_THRESHOLD)]
    monkeypatch.setattr(device, "_libc_function", lambda name: None)
    assert device.tune_allocator() is False
    order = []
    monkeypatch.setattr(device, "tune_allocator", lambda: order.append("tune"))
    assert cli.run("models", lambda args: order.append("command") or 0, None) == 0
    assert order == ["tune", "command"]


def test_available_memory_reads_memavailable_and_says_none_where_it_cannot(monkeypatch):
    # /proc/meminfo's MemAvailable in bytes (the file's unit is kiB); None where the file or the line is missing
    import builtins
    import io

    import renderer.device as device

    monkeypatch.setattr(device, "cgroup_memory_headroom", lambda: None)          # whatever this machine's cgroup
    real_open = builtins.open

    def fake(text):
        return lambda path, *a, **k: io.StringIO(text) if path == "/proc/meminfo" else real_open(path, *a, **k)

    monkeypatch.setattr(builtins, "open", fake("MemTotal:  16000 kB\nMemFree:  100 kB\nMemAvailable:  12345 kB\n"))
    assert device.available_memory("cpu") == 12345 * 1024
    monkeypatch.setattr(builtins, "open", fake("MemTotal:  16000 kB\n"))
    assert device.available_memory("cpu") is None
    monkeypatch.setattr(builtins, "open", fake("MemAvailable: lots\n"))
    assert device.available_memory("cpu") is None

    def missing(path, *a, **k):
        raise FileNotFoundError(path)

    monkeypatch.setattr(builtins, "open", missing)
    assert device.available_memory(torch.device("cpu")) is None


def test_memory_headroom_is_what_the_machine_and_the_budget_leave(monkeypatch):
    import renderer.device as device

    assert device.resident_memory("cpu") > 0                        # this process's VmRSS
    monkeypatch.setattr(device, "available_memory", lambda dev: 8_000)
    monkeypatch.setattr(device, "resident_memory", lambda dev: 3_000)
    assert device.memory_headroom("cpu") == 8_000                   # no budget: the machine's
    assert device.memory_headroom("cpu", 10_000) == 7_000           # the budget less what the process holds
    assert device.memory_headroom("cpu", 20_000) == 8_000           # ... but never more than the machine has
    assert device.memory_headroom("cpu", 2_000) == 0                # a budget already spent leaves nothing
    monkeypatch.setattr(device, "resident_memory", lambda dev: None)
    assert device.memory_headroom("cpu", 5_000) == 5_000            # what the process holds unknown: the budget
    monkeypatch.setattr(device, "available_memory", lambda dev: None)
    assert device.memory_headroom("cpu") is None and device.memory_headroom("cpu", 5_000) == 5_000


def test_cgroup_headroom_is_the_tightest_limit_less_usage_plus_reclaimable_cache(monkeypatch, tmp_path):
    # v2: the process's own cgroup and its ancestors (a container's limit sits above the job's); "max" is no limit
    import renderer.device as device

    v2 = tmp_path / "v2"
    for folder, limit, usage, inactive in (("", None, None, None), ("pod", "8000", "5000", 1000),
                                           ("pod/job", "max", "4000", 500)):
        d = v2 / folder
        d.mkdir(parents=True, exist_ok=True)
        if limit is not None:
            (d / "memory.max").write_text(limit + "\n")
            (d / "memory.current").write_text(usage + "\n")
            (d / "memory.stat").write_text(f"anon 123\ninactive_file {inactive}\nactive_file 9\n")
    (tmp_path / "cg2").write_text("0::/pod/job\n")
    assert device.cgroup_memory_headroom(tmp_path / "cg2", v2) == 8000 - 5000 + 1000
    (v2 / "pod" / "job" / "memory.max").write_text("4200\n")                   # the job's own limit is tighter
    assert device.cgroup_memory_headroom(tmp_path / "cg2", v2) == 4200 - 4000 + 500
    # v1: the memory controller's line; 2^63 rounded down to a page is "no limit"; usage above the limit gives 0
    v1 = tmp_path / "v1" / "memory" / "docker" / "abc"
    v1.mkdir(parents=True)
    (v1 / "memory.limit_in_bytes").write_text("2000\n")
    (v1 / "memory.usage_in_bytes").write_text("1500\n")
    (v1 / "memory.stat").write_text("inactive_file 7\ntotal_inactive_file 300\n")
    (v1.parent / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    (v1.parent / "memory.usage_in_bytes").write_text("99999\n")
    (tmp_path / "cg1").write_text("5:cpu,cpuacct:/docker/abc\n4:memory:/docker/abc\n0::/\n")
    assert device.cgroup_memory_headroom(tmp_path / "cg1", tmp_path / "v1") == 2000 - 1500 + 300
    (v1 / "memory.usage_in_bytes").write_text("2600\n")
    assert device.cgroup_memory_headroom(tmp_path / "cg1", tmp_path / "v1") == 0
    # no limit anywhere, no files, no cgroup file: None; available_memory takes the tighter of the two
    (tmp_path / "cg0").write_text("0::/\n")
    assert device.cgroup_memory_headroom(tmp_path / "cg0", v2) is None
    assert device.cgroup_memory_headroom(tmp_path / "missing", v2) is None
    monkeypatch.setattr(device, "_meminfo_available", lambda: 10_000)
    monkeypatch.setattr(device, "cgroup_memory_headroom", lambda: 700)
    assert device.available_memory("cpu") == 700
    monkeypatch.setattr(device, "cgroup_memory_headroom", lambda: None)
    assert device.available_memory("cpu") == 10_000


def test_kept_array_is_reused_until_its_kind_changes():
    from renderer.device import kept_array

    store = {}
    a = kept_array(store, "x", (3, 4), torch.float64, "cpu")
    assert a.shape == (3, 4) and a.dtype == torch.float64 and kept_array(store, "x", [3, 4], torch.float64, "cpu") is a
    assert kept_array(store, "y", (3, 4), torch.float64, "cpu") is not a             # another key, another array
    b = kept_array(store, "x", (4, 3), torch.float64, "cpu")
    assert b is not a and store["x"] is b
    assert kept_array(store, "x", (4, 3), torch.float32, "cpu").dtype == torch.float32


def test_handed_out_arrays_are_reused_only_once_their_results_are_dropped():
    from renderer.device import HandedOutArrays

    h = HandedOutArrays()
    (a,) = h.arrays([("x", (5,), torch.float64)], "cpu")
    result = a.view(5)
    h.hand_out(result)
    assert h.held()
    (b,) = h.arrays([("x", (5,), torch.float64)], "cpu")
    assert b.data_ptr() != a.data_ptr()                 # the held result keeps its array
    h.hand_out(b.view(5))                               # (that view is dropped at once)
    assert not h.held()
    (c,) = h.arrays([("x", (5,), torch.float64)], "cpu")
    assert c is b
    h.release()
    assert h.store == {}
