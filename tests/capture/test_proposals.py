"""Neighbour proposals (capture.fit.proposals): texels the footprint steps leave misfit take a nearby texel's values."""

import pytest
import torch

from capture.fit import Layout
from capture.fit.layout import SolverError
from capture.fit.noise import NOISE, robust_rho
from capture.fit.operators import pixel_operator
from capture.fit.options import FitOptions
from capture.fit.proposals import PROPOSAL_CHI2, neighbour_proposals
from capture.footprint import observe_footprints
from capture.synth import build_scene, render_scene, small_scene
from renderer.gbuffer import render_gbuffer


@pytest.fixture(scope="module")
def plane_scene():
    """64 px photos (8 × 8 jittered rays) of 32² maps: texels of about two pixels, the true maps and their θ."""
    cfg = small_scene("ggx-lambert", image_size=64, texture_size=32, n_views=3)
    sc = build_scene(cfg)
    photos, _ = render_scene(sc, cfg)
    cams, lights = [v.camera for v in sc.views], [v.lights for v in sc.views]
    fp = observe_footprints(sc.mesh, cams, lights, [render_gbuffer(sc.mesh, c, 1) for c in cams], photos, (32, 32))
    op = pixel_operator(fp, 32 * 32)
    layout = Layout.of(sc.model)
    theta = layout.pack({k: v.reshape(32 * 32, -1).double() for k, v in sc.maps.items()})
    return sc, op, layout, theta


def _cost(sc, op, layout, theta):
    return float(robust_rho(op.y - op.predict(sc.model, layout, layout.canonical(theta)), "l2", 1.0).sum())


def _run(sc, op, layout, theta, **kw):
    return neighbour_proposals(sc.model, layout, theta, op, (32, 32), loss="l2", delta=1.0, noise=NOISE,
                               noise_ratio=None, **kw)


def test_at_the_true_maps_only_misfit_texels_move_and_the_data_cost_does_not_rise(plane_scene):
    """The true maps leave some texels' pixels misfit on these small photos (the footprints' discretisation, near
    the silhouettes): those are candidates and may move, but only where the data cost falls, and no other texel
    changes."""
    sc, op, layout, theta = plane_scene
    out, info = _run(sc, op, layout, theta)
    changed = (out != theta).any(1)
    assert int(changed.sum()) <= info["candidates"] < 0.2 * int(op.observed().sum())
    assert _cost(sc, op, layout, out) <= _cost(sc, op, layout, theta)


def test_a_patch_of_a_wrong_material_takes_its_surroundings_values(plane_scene):
    """Two well-seen texels inside a uniform region given another region's f0 and roughness (a compromise the steps
    could not leave): both are candidates, both take their neighbours' — the true — values, and the data cost
    falls to what the true maps give."""
    sc, op, layout, theta = plane_scene
    seen = op.observed()
    canon = layout.canonical(theta)
    # a texel whose 5 × 5 neighbourhood is seen and uniform in every parameter
    grid = canon.reshape(32, 32, -1)
    ok = seen.reshape(32, 32)
    pick = None
    for r in range(3, 29):
        for c in range(3, 28):
            win = grid[r - 2:r + 3, c - 2:c + 4]
            if bool(ok[r - 2:r + 3, c - 2:c + 4].all()) and float((win - grid[r, c]).abs().max()) < 1e-6:
                pick = (r, c)
                break
        if pick:
            break
    assert pick is not None, "the small scene has a uniform, seen 5 × 6 window"
    r, c = pick
    bad = torch.tensor([r * 32 + c, r * 32 + c + 1])
    wrong = theta.clone()
    f0, rough = layout.cols("f0"), layout.cols("roughness")
    target = layout.pack({"albedo": canon[bad][:, layout.cols("albedo")],
                          "f0": torch.full((2, len(f0)), 0.9, dtype=theta.dtype),
                          "roughness": torch.full((2, len(rough)), 0.8, dtype=theta.dtype)})
    wrong[bad] = target
    out, info = _run(sc, op, layout, wrong)
    assert info["candidates"] >= 2 and info["moved"] >= 2
    assert info["cost_after"] < info["cost_before"]
    torch.testing.assert_close(layout.canonical(out[bad]), canon[bad], atol=1e-6, rtol=0)
    assert _cost(sc, op, layout, out) <= _cost(sc, op, layout, theta) * 1.01 + 1e-12
    # elsewhere only the texels that move at the true maps too (misfit there already) changed
    at_truth, _ = _run(sc, op, layout, theta)
    elsewhere = ~_neighbourhood(bad) & (out != wrong).any(1)
    assert bool(((at_truth != theta).any(1) | ~elsewhere).all())


def _neighbourhood(idx, reach=2):
    m = torch.zeros(32, 32, dtype=torch.bool)
    for t in idx.tolist():
        r, c = divmod(t, 32)
        m[max(r - reach, 0):r + reach + 1, max(c - reach, 0):c + reach + 1] = True
    return m.reshape(-1)


def test_a_threshold_above_every_misfit_moves_nothing(plane_scene):
    sc, op, layout, theta = plane_scene
    wrong = theta.clone()
    wrong[:, layout.cols("roughness")] += 0.5
    out, info = _run(sc, op, layout, wrong, threshold=1e30)
    assert info["candidates"] == 0 and out is wrong
    assert PROPOSAL_CHI2 > 1                    # above what noise alone gives a texel's pixels


def test_inputs_are_validated(plane_scene):
    sc, op, layout, theta = plane_scene
    with pytest.raises(SolverError, match="must be \\[1024, 7\\]"):
        neighbour_proposals(sc.model, layout, theta, op, (16, 16), loss="l2", delta=1.0, noise=NOISE,
                            noise_ratio=None)
    with pytest.raises(SolverError, match="threshold must be a positive"):
        _run(sc, op, layout, theta, threshold=0.0)


def test_the_option_is_validated():
    with pytest.raises(SolverError, match="proposals must be True or False"):
        FitOptions(proposals="yes")
    assert FitOptions().proposals is True
