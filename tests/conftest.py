"""Shared fixtures: the device matrix (CPU always, CUDA when present), float64 helpers, and the paths of the
scenes rendered by Mitsuba 3."""

from pathlib import Path

import pytest
import torch

import materials.measured as measured

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


#: The MERL NBRDF weights the ``measured`` model needs (shared/data/merl; ``$SHADECAP_NBRDF_DIR``).
NBRDF_WEIGHTS = measured.data_dir() / measured.NPZ_NAME


def pytest_collection_modifyitems(config, items):
    """Skip tests marked ``gpu`` without a CUDA device and ``nbrdf`` without the NBRDF weights."""
    skips = {}
    if not torch.cuda.is_available():
        skips["gpu"] = pytest.mark.skip(reason="no CUDA device")
    if not NBRDF_WEIGHTS.is_file():
        skips["nbrdf"] = pytest.mark.skip(reason=f"NBRDF weights not found: {NBRDF_WEIGHTS} (see "
                                                 f"shared/data/merl/README.md)")
    for item in items:
        for key, mark in skips.items():
            if key in item.keywords:
                item.add_marker(mark)


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


def _finite_and_float32_matches(forward, compare, g, p, leaves, rtol, atol=1e-6):
    """The stability body the model families' property tests share.

    ``forward(g, p)`` (float64, ``p`` and ``leaves`` requiring grad) must be finite with finite gradients
    for every leaf; ``compare(g, p)`` evaluated in float32 must match float64 *on the same float32-rounded
    inputs* within ``rtol`` and ``atol · (1 + max |value|)``.
    """
    out = forward(g, p)
    assert torch.isfinite(out).all()
    out.sum().backward()
    for x in leaves:
        assert torch.isfinite(x.grad).all()
    g32 = g.to(torch.float32)
    p32 = {k: x.detach().float() for k, x in p.items()}
    a32 = compare(g32, p32).double()
    a64 = compare(g32.to(torch.float64), {k: x.double() for k, x in p32.items()})
    assert torch.allclose(a32, a64, rtol=rtol, atol=atol * (1 + a64.abs().max().item()))


@pytest.fixture(scope="session")
def finite_and_float32_matches():
    """:func:`_finite_and_float32_matches` (session-scoped, so hypothesis' ``@given`` tests may use it)."""
    return _finite_and_float32_matches


#: Dataset folders whose photos Mitsuba 3 rendered (docs/independent-renders.md): scene name → folder.
MITSUBA_FIXTURES_DIR = Path(__file__).resolve().parent / "fixtures" / "mitsuba"
MITSUBA_SCENES = ("torus-lambert", "sphere-ggx-lambert")


def mitsuba_fixture_path(name: str) -> Path:
    """The dataset folder of the Mitsuba-rendered scene ``name`` (one of :data:`MITSUBA_SCENES`), ready for
    :func:`capture.dataset.load_dataset`."""
    if name not in MITSUBA_SCENES:
        raise KeyError(f"unknown Mitsuba fixture {name!r}; the fixtures are {list(MITSUBA_SCENES)}")
    path = MITSUBA_FIXTURES_DIR / name
    if not (path / "scene.json").is_file():
        pytest.fail(f"{path} is missing; regenerate it with `python scripts/make_independent_fixtures.py "
                    f"--out tests/fixtures/mitsuba` (needs `pip install mitsuba`)")
    return path


@pytest.fixture(scope="session")
def mitsuba_scene():
    """``mitsuba_scene(name)`` → the dataset folder of a Mitsuba-rendered scene (:func:`mitsuba_fixture_path`)."""
    return mitsuba_fixture_path
