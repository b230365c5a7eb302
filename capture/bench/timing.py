"""What every benchmark table shares: the line naming the machine, the process's peak memory, and the growth
exponent of a time against a size."""

from __future__ import annotations

import math
import os
import platform
import resource

import torch


def machine_description(device: str = "cpu", threads: int | None = None) -> str:
    """One line naming the machine: CPU model and core count, torch version, torch threads (``threads``, default
    the current setting), and the GPU if used."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    n_threads = threads or torch.get_num_threads()
    desc = f"{cpu}, {os.cpu_count()} logical cores, torch {torch.__version__}, {n_threads} threads"
    if device.startswith("cuda") and torch.cuda.is_available():
        desc += f", GPU {torch.cuda.get_device_name()}"
    return desc


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far (MiB), from ``resource.getrusage``."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def growth_exponent(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of log y against log x (time ∝ x^k → k)."""
    lx = torch.tensor([math.log(x) for x in xs], dtype=torch.float64)
    ly = torch.tensor([math.log(max(y, 1e-9)) for y in ys], dtype=torch.float64)
    lx, ly = lx - lx.mean(), ly - ly.mean()
    return float((lx * ly).sum() / (lx * lx).sum())
