"""Shared fixtures: the device matrix (CPU always, CUDA when present) and float64 helpers."""

import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="no CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(params=DEVICES)
def device(request):
    """Every test taking ``device`` runs on CPU, and on CUDA when a GPU is present."""
    return torch.device(request.param)


@pytest.fixture
def rng():
    return torch.Generator().manual_seed(1234)


# Property tests: bounded example counts so the whole suite stays within CI's budget. Under CI the
# examples are derandomised (the same inputs every run, so a landing is reproducible); locally each
# run explores new inputs, and what it finds gets fixed and pinned.
try:
    import os

    from hypothesis import HealthCheck, settings

    settings.register_profile(
        "shadecap", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow],
        derandomize=bool(os.environ.get("CI")),
    )
    settings.load_profile("shadecap")
except ImportError:  # pragma: no cover
    pass
