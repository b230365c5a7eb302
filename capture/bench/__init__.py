"""Benchmarks and stress tests behind ``scripts/benchmark.py`` and ``scripts/stress.py``; each writes its table into
a generated section of a doc page (``docs/benchmarks.md``, ``docs/stability.md``) with ``out``.

- :mod:`capture.bench.models`: model throughput, and the approximations of the papers against the exact forms;
- :mod:`capture.bench.reconstruction`: reconstruction time against map error, on synthetic scenes and on photos
  another renderer made;
- :mod:`capture.bench.scaling`: how the forward pipeline's time and memory grow with views, pixels, texels, lights;
- :mod:`capture.bench.scale`: end-to-end time and peak memory of ``shadecap reconstruct`` against observed pixels and
  texels, per device;
- :mod:`capture.bench.stress`: model stability over extreme and random inputs, reconstruction under stress;
- :mod:`capture.bench.measured`: reconstructions of measured materials (:mod:`capture.synth.measured`);
- :mod:`capture.bench.timing`: the machine line, peak memory and growth exponent every table shares.

The package exports the entry points; the helpers stay in their modules.
"""

from .measured import benchmark_table, capture_benchmark
from .models import run_approximation_benchmark, run_models_benchmark
from .reconstruction import run_independent_benchmark, run_reconstruction_benchmark
from .scale import DEFAULT_SCALE_CONFIGS, run_scale_benchmark
from .scaling import run_scaling_benchmark
from .stress import model_sampled_table, model_stability_table, run_reconstruction_stress

__all__ = [
    "benchmark_table", "capture_benchmark", "model_sampled_table", "model_stability_table",
    "run_approximation_benchmark", "run_independent_benchmark", "run_models_benchmark",
    "run_reconstruction_benchmark", "run_reconstruction_stress", "run_scaling_benchmark", "run_scale_benchmark",
    "DEFAULT_SCALE_CONFIGS",
]
