"""Map-error metrics against ground truth, by hand."""

import math

import pytest
import torch

from capture.metrics import MetricsError, determined_at_truth, observability_errors


def test_observability_errors_by_hand():
    # a 2 × 2 map with errors 0.1, 0.2, 0, 0.3; texels 1 and 3 flagged unobservable: the squared errors are
    # 0.01 + 0.04 + 0 + 0.09 = 0.14 in all, 0.13 of it flagged → share 13 / 14; observable RMSE √(0.01 / 2)
    gt = {"roughness": torch.full((2, 2, 1), 0.5)}
    fit = {"roughness": gt["roughness"] + torch.tensor([0.1, 0.2, 0.0, 0.3]).reshape(2, 2, 1)}
    observed = torch.ones(2, 2, dtype=torch.bool)
    flagged = {"roughness": torch.tensor([[False, True], [False, True]])}
    e = observability_errors(fit, gt, observed, flagged)["roughness"]
    assert e["observed"]["rmse"] == pytest.approx(math.sqrt(0.14 / 4), rel=1e-6)
    assert e["observable"]["rmse"] == pytest.approx(math.sqrt(0.01 / 2), rel=1e-6)
    assert e["observable"]["texels"] == 2 and e["observable_fraction"] == 0.5
    assert e["flagged_share"] == pytest.approx(13 / 14, rel=1e-5)
    # no error anywhere: nothing to attribute
    assert observability_errors(gt, gt, observed, flagged)["roughness"]["flagged_share"] == 0.0
    # every texel flagged: all of the error is where the report warned
    everything = {"roughness": torch.ones(2, 2, dtype=torch.bool)}
    assert observability_errors(fit, gt, observed, everything)["roughness"]["flagged_share"] == 1.0
    with pytest.raises(MetricsError, match=r"observed must be \[H, W\]"):
        observability_errors(fit, gt, observed.reshape(-1), flagged)


def test_determined_at_truth_by_hand():
    # Lambert is linear in the albedo, so a texel's posterior std per channel is exact and independent of any estimate:
    # ∂y_s/∂a = y_s / a, σ_s = 0.01 · max(y_s, 0.1 · median y) (the default noise model) and
    # std = 1 / √(Σ_s (y_s / (a σ_s))²). Each texel is determined where that std (max over channels) is below the
    # threshold — here 0.004 instead of the default 0.01, so that some bright texels with few samples are not.
    import materials
    from capture.observations import synthetic_observations

    model = materials.get("lambert")
    g = torch.Generator().manual_seed(5)
    gt = {"albedo": torch.rand(4, 4, 3, generator=g, dtype=torch.float64) * 0.9 + 0.05}
    obs = synthetic_observations(model, gt, samples_per_texel=3, seed=1)
    det = determined_at_truth(model, obs, gt, observable_std={"albedo": 0.004})["albedo"]
    y = obs.radiance.double()
    sigma = 0.01 * torch.maximum(y.abs(), torch.full_like(y, 0.1 * float(y.abs().mean(-1).median())))
    a = gt["albedo"].reshape(16, 3)[obs.texel]
    info = torch.zeros(16, 3, dtype=torch.float64).index_add_(0, obs.texel, obs.weight.double()[:, None]
                                                              * (y / (a * sigma)).square())
    by_hand = (info.rsqrt().amax(-1) < 0.004).reshape(4, 4)
    assert 0 < int(by_hand.sum()) < 16              # the threshold splits the texels: the test can tell
    assert torch.equal(det, by_hand)
    # the error over that mask is the truth's business, not the estimate's: an estimate that is off does not move it
    errs = observability_errors({"albedo": gt["albedo"] + 0.1}, gt, torch.ones(4, 4, dtype=torch.bool),
                                {"albedo": torch.zeros(4, 4, dtype=torch.bool)}, determined={"albedo": det})["albedo"]
    assert errs["determined"]["texels"] == int(by_hand.sum())
    assert errs["determined_fraction"] == pytest.approx(int(by_hand.sum()) / 16)
    assert errs["determined"]["rmse"] == pytest.approx(0.1, rel=1e-6)
    with pytest.raises(MetricsError, match="lack"):
        determined_at_truth(materials.get("ggx-lambert"), obs, gt)
    with pytest.raises(MetricsError, match="bool mask"):
        observability_errors(gt, gt, torch.ones(4, 4, dtype=torch.bool), {}, determined={"albedo": det.float()})


def _four_texel_observations():
    """A 2 × 2 map, one sample per texel and one light each, built by hand (normals +z except texel 3's, −z):
    texel 0 seen and lit at the mirror configuration (h = n); texel 1 seen, lit at n·l = 0.196 only; texel 2 seen
    and lit, half vector 28.6° off the normal (n·h = 0.878); texel 3 seen only at grazing n·v = 0.0995."""
    from capture.observations import DROP_REASONS, Observations
    from materials.geometry import Angles

    unit = lambda *x: torch.nn.functional.normalize(torch.tensor(x, dtype=torch.float64), dim=-1)  # noqa: E731
    up, down = unit(0, 0, 1), unit(0, 0, -1)
    v0 = unit(0.3, 0, 1)
    n = torch.stack([up, up, up, down])
    v = torch.stack([v0, v0, v0, unit(1, 0, -0.1)])
    l = torch.stack([unit(-0.3, 0, 1), unit(1, 0, 0.2), unit(0, 0.8, 0.6), down])
    ang = Angles.from_vectors(n, l, v)
    angles = Angles(*(getattr(ang, f)[:, None] for f in ("nl", "nv", "nh", "lh", "lv")))
    return Observations(texel=torch.arange(4), map_size=(2, 2), radiance=torch.ones(4, 3, dtype=torch.float64),
                        weight=torch.ones(4, dtype=torch.float64), pair_sample=torch.arange(4),
                        pair_light=torch.zeros(4, dtype=torch.long), angles=angles,
                        irradiance=torch.ones(4, 3, dtype=torch.float64), view=torch.zeros(4, dtype=torch.long),
                        pixel=torch.arange(4), n=n, v=v, drops=dict.fromkeys(DROP_REASONS, 0))


@pytest.mark.parametrize("block,H,W", [(1, 5, 7), (3, 9, 6), (5, 8, 13), (7, 4, 4)])
def test_grow_dilates_by_the_square_block_at_every_texel_and_border(block, H, W):
    from capture.metrics import _grow

    m = torch.rand(H * W, generator=torch.Generator().manual_seed(block + H)) < 0.15
    grid = m.reshape(H, W)
    r = block // 2
    want = torch.zeros(H, W, dtype=torch.bool)
    for i in range(H):                      # each texel: is any texel of the square around it (clipped) set
        for j in range(W):
            want[i, j] = bool(grid[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].any())
    assert torch.equal(_grow(m, block, H, W), want.reshape(-1))


def test_coverage_advice_on_a_constructed_observation_set():
    from capture.metrics import coverage_advice

    obs = _four_texel_observations()
    normals = obs.n.reshape(2, 2, 3).float()
    for a in (coverage_advice(obs, normals, torch.ones(2, 2, dtype=torch.bool)), coverage_advice(obs)):
        # one texel in each set: unseen (texel 3, facing −z), unlit (texel 1), no highlight (texel 2), of 4
        assert a["texels"] == 4 and a["block"] == 1
        for key in ("unseen", "unlit", "no_highlight"):
            assert a[key]["texels"] == 1 and a[key]["fraction"] == 0.25, (key, a[key])
        assert a["unseen"]["direction"] == pytest.approx([0.0, 0.0, -1.0])
        assert a["unlit"]["direction"] == pytest.approx([0.0, 0.0, 1.0])
        assert a["unseen"]["named"].startswith("below (−z") and a["unlit"]["named"].startswith("above (+z")
        assert len(a["advice"]) == 3
        assert a["advice"][0].startswith("add views from below (−z") and "25% of the surface texels are never seen " \
            "at n·v > 0.3" in a["advice"][0]
    # a wider highlight cone takes texel 2 in (n·h = 0.878 is 28.6°); without a specular lobe nothing is judged
    assert coverage_advice(obs, highlight_deg=30.0)["no_highlight"]["texels"] == 0
    assert "no_highlight" not in coverage_advice(obs, specular=False)
    with pytest.raises(MetricsError, match="cos must be"):
        coverage_advice(obs, cos=1.5)
    with pytest.raises(MetricsError, match=r"normals must be a \[2, 2, 3\]"):
        coverage_advice(obs, torch.zeros(4, 3))
    with pytest.raises(MetricsError, match="surface must be"):
        coverage_advice(obs, normals, torch.ones(2, 2))
    with pytest.raises(MetricsError, match="highlight_deg"):
        coverage_advice(obs, highlight_deg=0)


def test_coverage_advice_counts_texels_no_sample_reads_and_fills_blocks():
    from dataclasses import replace

    from capture.metrics import coverage_advice

    obs = _four_texel_observations()
    # the same four samples on a 2 × 4 map whose right half is surface no sample reads, facing −y
    wide = replace(obs, texel=torch.tensor([0, 1, 4, 5]), map_size=(2, 4))
    normals = torch.zeros(2, 4, 3)
    normals[..., 2] = 1.0
    normals[1, 1] = torch.tensor([0.0, 0.0, -1.0])
    normals[:, 2:] = torch.tensor([0.0, -1.0, 0.0])
    a = coverage_advice(wide, normals, block=1)
    assert a["texels"] == 8 and a["unseen"]["texels"] == 5 and a["unseen"]["fraction"] == 5 / 8
    mean = torch.tensor([0.0, -4.0, -1.0]) / 5
    assert a["unseen"]["direction"] == pytest.approx((mean / mean.norm()).tolist(), abs=1e-6)
    assert a["unseen"]["named"].startswith("the side (−y")
    # a 3 × 3 block: a texel next to a well-seen one counts as seen (only texels 3 and 7 are two columns away)
    assert coverage_advice(wide, normals, block=3)["unseen"]["texels"] == 2


def test_texel_normals_of_a_plane():
    from capture.metrics import texel_normals
    from renderer.mesh import plane

    normals, covered = texel_normals(plane(subdivisions=2), (16, 16))
    # 8 random points per texel: all 256 texels covered (e^-8 each), every normal +z
    assert covered.all()
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, 1.0]).expand(16, 16, 3))
    with pytest.raises(MetricsError, match="map_size"):
        texel_normals(plane(), (16, 0))
    with pytest.raises(MetricsError, match="Mesh"):
        texel_normals(object(), (16, 16))


def test_texel_normals_interpolate_the_vertex_normals_at_the_texel_centres():
    from capture.metrics import texel_normals
    from renderer.mesh import uv_sphere

    # a coarse sphere (faces of 45° × 45°, each spanning many texels) so that a texel's normal is the faces' linear
    # interpolation of the vertex normals, not the sphere's radial direction: the mean over the points drawn in a
    # texel is that interpolation at its centre, up to the normalisation's curvature and the draw's noise. The
    # reference: each texel centre located in its UV face by brute force, its barycentric weights applied to the
    # vertex normals (texels whose centre falls in no face — the poles' degenerate cells — left out). Measured
    # median 0.33°, largest 1.62° (weights swapped between two corners: median 15°); asserted with a 2× margin
    H = W = 32
    mesh = uv_sphere(segments=8, rings=4)
    normals, covered = texel_normals(mesh, (H, W), samples_per_texel=64)
    f = mesh.faces.long()
    uv, nv = mesh.uvs.double()[f], mesh.normals.double()[f]                   # [F, 3, 2], [F, 3, 3]
    u = ((torch.arange(W, dtype=torch.float64) + 0.5) / W)[None].expand(H, W)
    v = (1 - (torch.arange(H, dtype=torch.float64) + 0.5) / H)[:, None].expand(H, W)
    p = torch.stack([u, v], -1).reshape(-1, 1, 2)                               # [N, 1, 2]

    def cross(x, y):
        return x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]

    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    den = cross(e1, e2)
    safe = torch.where(den.abs() > 1e-12, den, torch.ones_like(den))
    d = p - uv[None, :, 0]                                                       # [N, F, 2]
    w1, w2 = cross(d, e2[None]) / safe, cross(e1[None], d) / safe
    w0 = 1 - w1 - w2
    inside = (den.abs() > 1e-12) & (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
    face, rows = inside.double().argmax(1), torch.arange(H * W)
    want = sum(w[rows, face, None] * nv[face, k] for k, w in enumerate((w0, w1, w2)))
    want = want / want.norm(dim=-1, keepdim=True)
    angle = torch.rad2deg(torch.acos((normals.reshape(-1, 3).double() * want).sum(-1).clamp(-1, 1)))
    located = inside.any(1)
    assert float(located.double().mean()) == 0.75            # the top and bottom rows of cells are half triangles
    assert bool(covered.reshape(-1)[located].all())
    assert float(angle[located].median()) < 0.7 and float(angle[located].max()) < 3.5


def test_visible_lobe_texels_compare_the_ggx_peak_with_the_lambert_term():
    """f0 / (4 α² ρ) against VISIBLE_LOBE_RATIO, by hand: the rough dielectric of the synthetic regions (f0 0.04,
    r 0.75, ρ 0.54) has 0.04 / (4 · 0.5625² · 0.54) = 0.059, a smooth dielectric (f0 0.05, r 0.25, ρ 0.32) 9.8,
    gold (f0 0.72, r 0.35, ρ 0) is always visible; the threshold is inclusive."""
    from capture.metrics import VISIBLE_LOBE_RATIO, MetricsError, visible_lobe_texels

    f0 = torch.tensor([0.04, 0.05, 0.72, 0.25]).reshape(2, 2, 1).expand(2, 2, 3)
    r = torch.tensor([0.75, 0.25, 0.35, 1.0]).reshape(2, 2, 1)
    rho = torch.tensor([0.54, 0.32, 0.0, 0.25]).reshape(2, 2, 1).expand(2, 2, 3)
    assert VISIBLE_LOBE_RATIO == 0.25
    got = visible_lobe_texels({"f0": f0, "roughness": r, "albedo": rho})
    assert got.tolist() == [[False, True], [True, True]]          # 0.25 / (4 · 1 · 0.25) = 0.25: on the threshold
    assert visible_lobe_texels({"f0": f0, "roughness": r}).all()
    with pytest.raises(MetricsError, match="roughness"):
        visible_lobe_texels({"f0": f0})
