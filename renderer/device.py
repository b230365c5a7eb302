"""Where tensors are computed: ``--device cpu|cuda|auto`` of ``reconstruct``, ``synth``, ``demo`` and the benchmarks.

What runs on the device and what stays on the CPU (docs/architecture.md, "Devices"):

- **On the device:** the shading (:func:`renderer.shading.shade` runs where its maps are) and the fit's solve —
  every model evaluation, Jacobian, sparse footprint product and PCG iteration of ``auto``'s trial fits and of the
  final one.
- **On the CPU:** ray casting (embree has no GPU path; G-buffers and shadow rays are computed once), building the
  observations from them (the views spread over the cores, one thread each: :func:`per_view`), the reflectance
  sharing's k-means (a few thousand points), the metrics and the files. The observations move to the device once
  per fit and the fitted maps come back.

``auto`` is CUDA when torch sees a GPU, else the CPU. Results agree with the CPU's within float32 rounding
(``tests/capture/test_device.py``, marked ``gpu``); CUDA's atomic float additions (``index_add``) make two runs on
the GPU differ in the last bits, which a poorly determined fit can amplify.
"""

from __future__ import annotations

import functools
import os
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import torch

__all__ = ["DEVICES", "DeviceError", "resolve_device", "per_view", "release_memory", "CUDA_BLOCK_FACTOR", "block_size",
           "tune_allocator", "MMAP_THRESHOLD", "TRIM_THRESHOLD", "available_memory", "cgroup_memory_headroom",
           "resident_memory", "memory_headroom", "kept_array", "HandedOutArrays"]

_R = TypeVar("_R")
_PARALLEL = threading.Lock()

#: the spellings ``--device`` accepts (``cuda:N`` picks a GPU by index as well)
DEVICES = ("auto", "cpu", "cuda")
#: How many times larger the solver's blocks of samples and entries are on a GPU than on the CPU
#: (:func:`block_size`). The CPU's sizes keep temporaries in cache and memory bounded; on an H100 their launches
#: left the GPU idle: 32 × 512² photos (GGX + Lambert) fitted in 12.4–13.2 s with the CPU's blocks, 6.9 s with
#: 16× larger ones (CUDA peak 7.5 → 8.5 GB), 6.7 s with 128× (11.5 GB) — the same maps.
CUDA_BLOCK_FACTOR = 16


class DeviceError(ValueError):
    """A device that is not spelled right or that this machine does not have."""


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """The :class:`torch.device` that ``device`` names: ``"auto"`` (or None) is ``cuda`` when torch sees a GPU and
    the CPU otherwise; ``"cpu"``, ``"cuda"`` and ``"cuda:N"`` as torch spells them.

    Raises:
        DeviceError: an unknown name, or CUDA asked for on a machine (or a torch build) without it — the message
            says which, and that ``cpu`` or ``auto`` runs anyway.
    """
    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    if not isinstance(device, (str, torch.device)):
        raise DeviceError(f"device must be one of {DEVICES} (or 'cuda:N'), got {type(device).__name__} {device!r}")
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise DeviceError(f"unknown device {device!r}: use one of {DEVICES} (or 'cuda:N')") from None
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise DeviceError(f"device {device!r} is not supported: use one of {DEVICES} (or 'cuda:N')")
    if not torch.cuda.is_available():
        why = ("this torch is a CPU-only build" if torch.version.cuda is None
               else "torch sees no GPU on this machine")
        raise DeviceError(f"device {device!r} asked for, but {why}: use --device cpu (or auto, which falls back "
                          f"to the CPU), or install a CUDA build of torch on a machine with an NVIDIA GPU")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise DeviceError(f"device {device!r}: this machine has {torch.cuda.device_count()} GPU(s), "
                          f"cuda:0 … cuda:{torch.cuda.device_count() - 1}")
    return dev


def per_view(work: Callable[[int], _R], n: int, done: Callable[[], None] | None = None) -> list[_R]:
    """``[work(0), …, work(n − 1)]``, the views spread over the CPU cores torch may use: as many threads as
    ``torch.get_num_threads()`` (at most ``n``), each running its views with one torch thread, so the cores are not
    oversubscribed; the count is restored afterwards. For the per-view CPU work of building observations — ray
    casting (embree releases the GIL), footprints, shading terms — whose tensors are too small for torch's own
    threads to keep every core busy: the 256² Mitsuba torus's pixel footprints (12 views) took 2.5–2.9 s this way
    against 3.8–4.2 s one view at a time with 2 threads. Each view's result does not depend on the others or on the
    order they run in, and — each view running with one torch thread, as it also does one at a time with one thread
    — not on the thread count (bitwise; one view alone keeps the caller's threads). ``done()`` is called in the
    calling thread after each view, in order (a progress bar's tick). Calls from several threads at once run one
    after the other (torch's thread count is global); a call from inside a view runs in that view's thread.
    """
    workers = min(torch.get_num_threads(), n)
    if workers <= 1:
        out = []
        for i in range(n):
            out.append(work(i))
            if done is not None:
                done()
        return out
    with _PARALLEL:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            with ThreadPoolExecutor(workers) as pool:
                futures = [pool.submit(work, i) for i in range(n)]
                out = []
                for f in futures:
                    out.append(f.result())
                    if done is not None:
                        done()
                return out
        finally:
            torch.set_num_threads(threads)
            release_memory()


def release_memory() -> None:
    """Return the host memory that freed tensors left in the C allocator's heaps to the system: glibc keeps a heap
    per thread (a finished worker's would otherwise stay in the process's peak memory), and tensors below its mmap
    threshold, freed between large ones, fragment them. Called between the stages of a long job: on 32 × 256²
    photos the footprint solve began with 1.1 GB of such memory (3.2 GB resident, 2.1 GB after this). Not in inner
    loops: the pages come back as page faults (before each footprint step it cost 31 → 35 s on 8 × 256² photos).
    Nothing where there is no glibc."""
    trim = _libc_function("malloc_trim")
    if trim is not None:
        trim(0)


#: Largest allocation glibc's malloc serves from its heaps rather than from pages mapped for it alone
#: (:func:`tune_allocator`): 32 MiB, the ceiling of glibc's own adaptive threshold, fixed from the start. Every
#: temporary of the solver's inner loops is below it (a [T, P] vector of 256² maps is 3.7 MB, a block of the pixel
#: operator's entries 9–19 MB); larger arrays are still mapped and unmapped on their own, so they leave no holes.
MMAP_THRESHOLD = 32 << 20
#: Free memory at the top of a heap that glibc keeps for the next allocations instead of returning it (by default
#: twice the adaptive threshold, so the pages of each freed temporary came back as page faults at the next one).
#: Measured with both settings against glibc's defaults (2-core CPU, `shadecap reconstruct`, back to back): 256²
#: Mitsuba sphere 29.3–31.0 → 27.4 s, peak memory 1.55 → 1.62 GiB; 8 × 256² photos on 512² maps 45.6 → 42.0 s,
#: 2.27 → 2.40 GiB; with both at 1 GiB 41.3 s but 2.82 GiB (large arrays freed into the heaps fragment it).
TRIM_THRESHOLD = 256 << 20


def tune_allocator() -> bool:
    """Set glibc's malloc thresholds for a long job (:data:`MMAP_THRESHOLD`, :data:`TRIM_THRESHOLD`): freed
    temporaries stay in the heap for the next ones instead of being unmapped and faulted in again. A process-wide
    setting, so the command line and the benchmark scripts call it, the library does not; :func:`release_memory`
    still returns the heaps' free memory between stages. Returns whether it was applied (False where there is no
    glibc)."""
    mallopt = _libc_function("mallopt")
    if mallopt is None:
        return False
    # mallopt(M_MMAP_THRESHOLD = -3, bytes), mallopt(M_TRIM_THRESHOLD = -1, bytes): 1 on success
    return bool(mallopt(-3, MMAP_THRESHOLD)) and bool(mallopt(-1, TRIM_THRESHOLD))


def available_memory(device: torch.device | str = "cpu") -> int | None:
    """Bytes that new tensors on ``device`` can take now: on a GPU the free memory the driver reports, on the CPU
    Linux's estimate of what can be allocated without swapping (``MemAvailable`` of ``/proc/meminfo``: free
    memory plus the caches it can drop), and no more than the process's memory cgroup leaves it
    (:func:`cgroup_memory_headroom`: a container's or a batch job's limit, which ``/proc/meminfo`` does not show).
    None where neither can be known (another system)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        free, _total = torch.cuda.mem_get_info(dev)
        return int(free)
    known = [b for b in (_meminfo_available(), cgroup_memory_headroom()) if b is not None]
    return min(known) if known else None


def resident_memory(device: torch.device | str = "cpu") -> int | None:
    """Bytes the process holds now on ``device``: on the CPU its resident memory (``VmRSS`` of
    ``/proc/self/status``), on a GPU what torch's caching allocator has reserved there. None where it cannot be
    known (another system)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        return int(torch.cuda.memory_reserved(dev))
    return _proc_kib("/proc/self/status", "VmRSS:")


def memory_headroom(device: torch.device | str = "cpu", budget: int | None = None) -> int | None:
    """Bytes new tensors on ``device`` may take now: :func:`available_memory`, and with a ``budget`` (bytes the
    whole process may hold there) no more than the budget less what it holds (:func:`resident_memory`; 0 when it
    holds more). None where neither can be known."""
    known = [available_memory(device)]
    if budget is not None:
        held = resident_memory(device)
        known.append(max(budget - held, 0) if held is not None else budget)
    known = [b for b in known if b is not None]
    return min(known) if known else None


def _meminfo_available() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes; None without the file or the line."""
    return _proc_kib("/proc/meminfo", "MemAvailable:")


def _proc_kib(path: str, key: str) -> int | None:
    """The line ``key`` of a ``/proc`` file whose values are in kiB (``/proc/meminfo``, ``/proc/self/status``), in
    bytes; None without the file, the line or a number on it."""
    try:
        with open(path, encoding="ascii") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


#: cgroup v1 writes "no limit" as the largest page-aligned 63-bit number; any limit from 2⁶⁰ bytes up is taken as none.
_NO_LIMIT = 1 << 60


def cgroup_memory_headroom(cgroup_file: str | os.PathLike = "/proc/self/cgroup",
                           root: str | os.PathLike = "/sys/fs/cgroup") -> int | None:
    """Bytes the process's memory cgroup lets it allocate before the limit: at its own level and every ancestor's
    with a limit, ``limit − usage + inactive file pages`` (page cache the kernel reclaims before it would kill), the
    smallest of them. cgroup v2 (``memory.max``, ``memory.current``, ``memory.stat``) or v1 (the ``memory``
    controller's ``memory.limit_in_bytes``, ``memory.usage_in_bytes``, ``total_inactive_file``), found from
    ``cgroup_file`` (the ``/proc/self/cgroup`` lines ``id:controllers:path``) under ``root``. None where no level
    sets a limit or nothing can be read (not Linux, no cgroup file system)."""
    try:
        lines = Path(cgroup_file).read_text(encoding="ascii").splitlines()
    except OSError:
        return None
    levels = []             # (the hierarchy's root folder, limit file, usage file, inactive-file key, the path)
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == "":
            levels.append((Path(root), "memory.max", "memory.current", "inactive_file", path))
        elif "memory" in controllers.split(","):
            levels.append((Path(root) / "memory", "memory.limit_in_bytes", "memory.usage_in_bytes",
                           "total_inactive_file", path))
    headroom = None
    for base, limit_name, usage_name, inactive_key, path in levels:
        folder = base / path.lstrip("/")
        while True:
            room = _cgroup_level_headroom(folder, limit_name, usage_name, inactive_key)
            if room is not None:
                headroom = room if headroom is None else min(headroom, room)
            if folder == base or base not in folder.parents:
                break
            folder = folder.parent
    return headroom


def _cgroup_level_headroom(folder: Path, limit_name: str, usage_name: str, inactive_key: str) -> int | None:
    """One cgroup level's ``limit − usage + inactive file pages`` (≥ 0); None without a limit or its files."""
    try:
        limit = (folder / limit_name).read_text(encoding="ascii").strip()
        if limit == "max" or int(limit) >= _NO_LIMIT:
            return None
        usage = int((folder / usage_name).read_text(encoding="ascii").strip())
    except (OSError, ValueError):
        return None
    inactive = 0
    try:
        for line in (folder / "memory.stat").read_text(encoding="ascii").splitlines():
            key, _, value = line.partition(" ")
            if key == inactive_key:
                inactive = int(value)
                break
    except (OSError, ValueError):
        pass
    return max(int(limit) - usage + inactive, 0)


def block_size(cpu_block: int, device: torch.device | str) -> int:
    """The size of a block of work (samples, entries) on ``device``: ``cpu_block``, the size chosen for the CPU,
    times :data:`CUDA_BLOCK_FACTOR` on a GPU."""
    if isinstance(cpu_block, bool) or not isinstance(cpu_block, int) or cpu_block < 1:
        raise ValueError(f"block size must be a positive integer, got {cpu_block!r}")
    return cpu_block * CUDA_BLOCK_FACTOR if torch.device(device).type == "cuda" else cpu_block


def kept_array(store: dict, key, shape: tuple[int, ...], dtype: torch.dtype,
               device: torch.device | str) -> torch.Tensor:
    """The array ``store[key]`` of ``shape``, ``dtype`` and ``device``, made (uninitialised) only when it is missing
    or of another kind: a working array reused by every call of a hot loop. An array over glibc's mmap ceiling
    (:data:`MMAP_THRESHOLD`, 32 MiB: 7 parameters of 1024² texels in float64 are 59 MB) made afresh is new pages that
    the kernel zeroes at first touch — on 1024² maps a PCG iteration's vector work took 230 ms with fresh arrays
    against 48 ms in kept ones."""
    shape, device = tuple(shape), torch.device(device)
    buf = store.get(key)
    if buf is None or tuple(buf.shape) != shape or buf.dtype != dtype or buf.device != device:
        buf = store[key] = torch.empty(shape, dtype=dtype, device=device)
    return buf


class HandedOutArrays:
    """Kept working arrays (:func:`kept_array`) from which a caller gets results it may hold: the next call reuses
    them once nothing holds what the last one handed out (weak references to it), and otherwise makes new ones,
    leaving the held results their arrays. For results remade at the same size at every step of a solver, whose
    fresh pages above glibc's mmap ceiling the kernel would zero at each step."""

    def __init__(self):
        self.store: dict = {}
        self._handed = ()

    def held(self) -> bool:
        """Whether something still holds a result of the last call."""
        return any(ref() is not None for ref in self._handed)

    def arrays(self, specs, device: torch.device | str) -> list[torch.Tensor]:
        """The arrays ``(key, shape, dtype)`` of ``specs``, uninitialised: the kept ones unless :meth:`held`."""
        if self.held():
            self.store = {}
        self._handed = ()
        return [kept_array(self.store, key, shape, dtype, device) for key, shape, dtype in specs]

    def hand_out(self, *results) -> None:
        """Record the results made from the arrays (tensors, weakly referenced) before they go to the caller."""
        self._handed = tuple(weakref.ref(r) for r in results)

    def release(self) -> None:
        """Drop the kept arrays (held results keep theirs)."""
        self.store = {}


@functools.cache
def _libc_function(name: str):
    """glibc's function ``name`` (``malloc_trim``, ``mallopt``), looked up once (``find_library`` runs ``ldconfig``:
    ~18 ms a call), or None."""
    import ctypes
    import ctypes.util

    try:
        return getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):
        return None
