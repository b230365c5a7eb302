"""Benchmarks: model throughput and accuracy against slow references (issue 2/6).

``scripts/benchmark.py models`` calls :func:`benchmark_models`; results are written to
``docs/benchmarks.md`` by the script. Timings state the machine they were taken on
(:func:`machine_description`).
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch

import materials
from materials import Angles
from materials.model import Model


def machine_description(device: str = "cpu") -> str:
    """One line naming the machine: CPU model and core count, torch version, and the GPU if used."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    desc = f"{cpu}, {os.cpu_count()} logical cores, torch {torch.__version__}, {torch.get_num_threads()} threads"
    if device.startswith("cuda") and torch.cuda.is_available():
        desc += f", GPU {torch.cuda.get_device_name()}"
    return desc


def random_front_angles(n: int, dtype=torch.float32, device="cpu", seed: int = 0) -> Angles:
    """``n`` random configurations with light and viewer in the upper hemisphere (cosine-weighted)."""
    gen = torch.Generator().manual_seed(seed)

    def hemi():
        u1, u2 = torch.rand(n, generator=gen, dtype=torch.float64), torch.rand(n, generator=gen, dtype=torch.float64)
        r, phi = torch.sqrt(u1), 2 * math.pi * u2
        return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1 - u1).clamp_min(1e-6))], -1)

    nrm = torch.zeros(n, 3, dtype=torch.float64)
    nrm[:, 2] = 1
    return Angles.from_vectors(nrm, hemi(), hemi()).to(device=device, dtype=dtype)


def random_params(model: Model, n: int, dtype=torch.float32, device="cpu", seed: int = 1) -> dict[str, torch.Tensor]:
    """Per-sample parameters uniform over each parameter's range (capped at 1 for unbounded ones)."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for s in model.params:
        hi = min(s.high, max(1.0, s.low + 1.0))
        out[s.name] = (s.low + (hi - s.low) * torch.rand(n, s.channels, generator=gen)).to(device=device, dtype=dtype)
    return out


@dataclass
class Throughput:
    model: str
    device: str
    samples: int
    forward_per_s: float
    forward_backward_per_s: float
    compiled: bool = False


def _time(fn: Callable[[], None], repeats: int, device: str) -> float:
    fn()  # warm-up
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best


def model_throughput(
    model: Model, n: int = 1 << 20, device: str = "cpu", repeats: int = 3, compile: bool = False
) -> Throughput:
    """Samples per second of ``model.cosine_brdf`` forward, and forward + backward to every parameter.

    Geometry (the Angles) is precomputed, as in the pipeline; the parameters are per-sample
    tensors, as sampled from maps. ``compile=True`` wraps the evaluation in ``torch.compile``.
    """
    g = random_front_angles(n, device=device)
    p = random_params(model, n, device=device)

    def evaluate(nl, nv, nh, lh, lv, *vals):
        return model.cosine_brdf(Angles(nl, nv, nh, lh, lv), dict(zip(p.keys(), vals, strict=True)))

    fn = torch.compile(evaluate, dynamic=False) if compile else evaluate
    geo = (g.nl, g.nv, g.nh, g.lh, g.lv)

    def fwd():
        with torch.no_grad():
            fn(*geo, *p.values())

    leaves = [x.detach().clone().requires_grad_() for x in p.values()]

    def fwd_bwd():
        out = fn(*geo, *leaves)
        out.sum().backward()

    t_f = _time(fwd, repeats, device)
    t_fb = _time(fwd_bwd, repeats, device)
    return Throughput(model.name, device, n, n / t_f, n / t_fb, compile)


def benchmark_models(
    names: list[str] | None = None, n: int = 1 << 20, device: str = "cpu", compile_names: tuple[str, ...] = ()
) -> list[dict]:
    """Throughput of every registered model (or ``names``); those in ``compile_names`` also compiled."""
    rows = []
    for name in names or list(materials.available()):
        model = materials.get(name)
        rows.append(asdict(model_throughput(model, n=n, device=device)))
        if name in compile_names:
            rows.append(asdict(model_throughput(model, n=n, device=device, compile=True)))
    return rows


#: Models timed under torch.compile by default: the ones reconstruction uses most.
COMMON_MODELS = ("lambert", "ggx-lambert", "gotanda2012")


def run_models_benchmark(n: int = 1 << 20, device: str = "cpu", compile_names=None, out: str | None = None) -> str:
    """Throughput table of every model (markdown); written into ``out``'s ``models-throughput`` section."""
    from pathlib import Path

    from .report import replace_section

    names = list(materials.available())
    compile_names = tuple(c for c in (COMMON_MODELS if compile_names is None else compile_names) if c in names)
    rows = benchmark_models(names, n=n, device=device, compile_names=compile_names)
    lines = [
        f"Machine: {machine_description(device)}; device `{device}`; {n} samples per call, best of 3.",
        "",
        "| model | mode | forward (M samples/s) | forward+backward (M samples/s) |",
        "|---|---|---|---|",
    ]
    for r in rows:
        mode = "torch.compile" if r["compiled"] else "eager"
        fwd, fwd_bwd = r["forward_per_s"] / 1e6, r["forward_backward_per_s"] / 1e6
        lines.append(f"| `{r['model']}` | {mode} | {fwd:.1f} | {fwd_bwd:.1f} |")
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "models-throughput", "## Model throughput\n\n" + table)
    return table
