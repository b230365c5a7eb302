"""Reflectance sharing (capture/fit/sharing.py) and the edge-preserving prior of the joint refinement."""

import math

import pytest
import torch
import torch.nn.functional as F

import materials
from capture.fit import Layout, SolverError, joint, solve_fast
from capture.fit.joint import _SharingPrior
from capture.fit.sharing import (
    _albedo_prior,
    _assign,
    _box_sum,
    _excess,
    _misfit,
    _supported,
    kmeans_pp,
    share_materials,
    unmatched_texels,
)
from capture.observations import synthetic_observations


def _ggx_lambert():
    return materials.SumModel(materials.get("lambert"), materials.get("microfacet"))


def test_box_sum_matches_a_direct_sum():
    x = torch.rand(2, 7, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    for s in (1, 3, 5):
        ref = F.avg_pool2d(x[:, None], s, 1, s // 2, count_include_pad=True)[:, 0] * s * s
        torch.testing.assert_close(_box_sum(x, s), ref, rtol=0, atol=1e-12)
    # a box larger than the map sums everything
    torch.testing.assert_close(_box_sum(x, 27), x.sum((-1, -2))[:, None, None].expand_as(x), rtol=0, atol=1e-12)


def test_kmeans_pp_finds_a_small_separated_mode():
    g = torch.Generator().manual_seed(3)
    big = torch.randn(1000, 2, generator=g, dtype=torch.float64) * 0.1
    mid = torch.randn(300, 2, generator=g, dtype=torch.float64) * 0.1 + torch.tensor([5.0, 0.0], dtype=torch.float64)
    small = torch.randn(5, 2, generator=g, dtype=torch.float64) * 0.1 + torch.tensor([0.0, 8.0], dtype=torch.float64)
    c = kmeans_pp(torch.cat([big, mid, small]), 3, torch.Generator().manual_seed(0))
    want = torch.tensor([[0.0, 0.0], [5.0, 0.0], [0.0, 8.0]], dtype=torch.float64)
    d = torch.cdist(want, c).amin(1)
    assert bool((d < 0.15).all()), c
    with pytest.raises(ValueError, match="k and restarts must be"):
        kmeans_pp(big, 0)
    with pytest.raises(ValueError, match="k and restarts must be"):
        kmeans_pp(big, 2, restarts=0)


def test_kmeans_pp_restarts_make_the_clustering_independent_of_the_seed():
    # Six blobs of unequal size, four clusters: one k-means++ draw ends in one of several local minima depending on
    # the seed (within-cluster sums of squares 1059-1152 over seeds 0-9, measured); the best of 8 draws is the same
    # clustering for every seed. Draw 1 of restarts=8 is the restarts=1 draw, so it can never be worse.
    g = torch.Generator().manual_seed(3)
    blobs = torch.tensor([[0, 0], [3, 0], [0, 3], [3, 3], [1.5, 6], [6, 1.5]], dtype=torch.float64)
    x = torch.cat([torch.randn(n, 2, generator=g, dtype=torch.float64) * 0.5 + c
                   for n, c in zip([200, 150, 120, 100, 60, 40], blobs, strict=True)])

    def inertia(c):
        return float(torch.cdist(x, c).amin(1).square().sum())

    one = [inertia(kmeans_pp(x, 4, torch.Generator().manual_seed(s), restarts=1)) for s in range(10)]
    best = [inertia(kmeans_pp(x, 4, torch.Generator().manual_seed(s), restarts=8)) for s in range(10)]
    assert max(one) - min(one) > 50.0, one                       # the seed matters for a single draw
    assert max(best) - min(best) < 1e-9 and best[0] == pytest.approx(min(one)), (best, one)
    assert all(b <= o + 1e-9 for b, o in zip(best, one, strict=True))


def test_assign_lets_inconclusive_texels_borrow_but_never_take_a_rejected_candidate():
    # 1×9 strip, 3 candidates. Texels 0-1 clearly prefer 0; texels 2-6 cannot tell 0 from 1 but reject 2;
    # texel 7 clearly prefers 1; texel 8 prefers 2 by less than the evidence margin over 1.
    inf = 1e6
    c = torch.tensor([
        [0, 0, 0, 0, 0, 0, 0, 50, inf],
        [50, 50, 0, 0, 0, 0, 0, 0, 0],
        [inf, inf, 40, 40, 40, 40, 40, 50, 0],
    ], dtype=torch.float64)
    observed = torch.ones(9, dtype=torch.bool)
    label, scale = _assign(c, observed, 1, 9, evidence=10.0)
    assert label[:2].tolist() == [0, 0] and int(scale[0]) == 1
    assert int(label[7]) == 1 and int(scale[7]) == 1
    assert int(label[8]) in (1, 2)
    # the inconclusive middle borrows: never candidate 2 (its own samples reject it)
    assert bool((label[2:7] != 2).all())
    # texel 2 sits next to the 0-texels: a 3-box already holds their evidence for 0
    assert int(label[2]) == 0 and int(scale[2]) == 3
    # unobserved texels are left undecided (scale 0)
    obs2 = observed.clone()
    obs2[4] = False
    _, scale2 = _assign(c, obs2, 1, 9, evidence=10.0)
    assert int(scale2[4]) == 0


def _two_material_scene(seed=0):
    """16×16 texels, two specular materials in halves; per-texel albedo noise. Texels in the left
    columns see highlights (mirror-near samples), the others only off-peak directions."""
    H = W = 16
    g = torch.Generator().manual_seed(seed)
    albedo = torch.rand(H, W, 3, generator=g, dtype=torch.float64) * 0.5 + 0.2
    f0 = torch.empty(H, W, 3, dtype=torch.float64)
    rough = torch.empty(H, W, 1, dtype=torch.float64)
    f0[:, :8] = torch.tensor([0.9, 0.6, 0.3], dtype=torch.float64)
    rough[:, :8] = 0.3
    f0[:, 8:] = 0.04
    rough[:, 8:] = 0.5
    albedo[:, :8] = 0.0
    return {"albedo": albedo, "f0": f0, "roughness": rough}


def test_share_materials_recovers_unobservable_texels_from_their_material():
    model = _ggx_lambert()
    gt = _two_material_scene()
    # every texel: 12 samples, a third of them near the mirror direction → all observable; then drop
    # the highlight samples of most texels so that only anchors remain determined
    obs = synthetic_observations(model, gt, samples_per_texel=12, highlight_fraction=0.34, seed=1)
    layout = Layout.of(model)
    fit = solve_fast(model, obs, share=False)
    anchors = (~fit.unobservable["f0"] & ~fit.unobservable["roughness"]).reshape(-1)
    assert int(anchors.sum()) >= 100
    theta = layout.pack({k: v.reshape(-1, v.shape[-1]).double() for k, v in fit.raw.items()})
    # spoil the non-anchor texels' specular parameters (as an inconclusive per-texel fit would)
    bad = ~anchors
    bad[torch.arange(bad.numel()) % 3 != 0] = False          # a third of the texels
    spoiled = layout.unpack(theta)
    spoiled["f0"][bad] = 0.5
    spoiled["roughness"][bad] = 0.8
    anchors_cut = anchors & ~bad
    theta_s = layout.pack(spoiled)
    out, info = share_materials(model, obs, layout, theta_s, anchors_cut, candidates=4)
    rec = layout.unpack(out)
    # measured: every spoiled texel is put back on its material — f0 and roughness to < 1e-3
    for k in ("f0", "roughness"):
        err = (rec[k][bad] - gt[k].reshape(-1, gt[k].shape[-1])[bad]).abs().max()
        assert float(err) < 1e-3, (k, float(err))
    assert 2 <= len(info["materials"]) <= 4
    assert sum(info["texels_per_material"]) == 256


def _two_material_fit():
    """The two-material scene's observations (a third of the samples near the mirror direction) and its
    per-texel fit: ``(model, obs, layout, theta [256, P], anchors [256])``."""
    model = _ggx_lambert()
    obs = synthetic_observations(model, _two_material_scene(), samples_per_texel=12, highlight_fraction=0.34, seed=1)
    layout = Layout.of(model)
    fit = solve_fast(model, obs, share=False)
    anchors = (~fit.unobservable["f0"] & ~fit.unobservable["roughness"]).reshape(-1)
    theta = layout.pack({k: v.reshape(-1, v.shape[-1]).double() for k, v in fit.raw.items()})
    return model, obs, layout, theta, anchors


def test_unmatched_texels_are_those_whose_photos_reject_their_material():
    model, obs, layout, theta, anchors = _two_material_fit()
    _, info = share_materials(model, obs, layout, theta, anchors, candidates=4)
    assert not bool(unmatched_texels(model, obs, layout, theta, info).any())       # both materials found
    # no anchor among the metal's texels (as on a layered scene whose metals' base lobe is never determined): only
    # the dielectric material exists, the metal texels reject it; measured: all 128 of them, no dielectric texel
    cols = torch.arange(256) % 16
    _, info_d = share_materials(model, obs, layout, theta, anchors & (cols >= 8), candidates=1, refit_iterations=0)
    assert all(m["f0"][0] < 0.1 for m in info_d["materials"]), info_d["materials"]
    un = unmatched_texels(model, obs, layout, theta, info_d)
    assert int(un[cols < 8].sum()) >= 120 and int(un[cols >= 8].sum()) == 0, (int(un[cols < 8].sum()),
                                                                              int(un[cols >= 8].sum()))
    with pytest.raises(ValueError, match="share_materials"):
        unmatched_texels(model, obs, layout, theta, {"labels": info["labels"]})
    with pytest.raises(ValueError, match="same observations"):
        unmatched_texels(model, obs, layout, theta[:10], info)


def test_supported_drops_duplicates_and_materials_few_texels_need():
    # 10 texels prefer candidates 0 and 1 (duplicates) by 20 over candidate 2; n texels prefer 2 by 30.
    # Evidence (each texel capped at 15): duplicates 0 each → one goes, the other then holds 10 × 15 = 150;
    # candidate 2 holds n × 15: 3 texels (45) are not enough for 100, 8 (120) are
    def costs(n):
        c = torch.zeros(3, 10 + n, dtype=torch.float64)
        c[2, :10] = 20.0
        c[:2, 10:] = 30.0
        return c

    own = torch.ones(13, dtype=torch.bool)
    assert _supported(costs(3), own, 15.0, None, 100.0).tolist() == [False, True, False]
    assert _supported(costs(8), torch.ones(18, dtype=torch.bool), 15.0, None, 100.0).tolist() == [False, True, True]
    assert _supported(costs(3), own, 15.0, None, 0.0).tolist() == [True, True, True]
    # without the cap the 3 texels' 90 would still fall short; texels without samples of their own count nothing
    assert _supported(costs(3), own, None, None, 100.0).tolist() == [False, True, False]
    no_own = own.clone()
    no_own[:10] = False
    assert _supported(costs(3), no_own, 15.0, None, 40.0).tolist() == [False, False, True]


def test_share_materials_drops_unneeded_candidates():
    model, obs, layout, theta, anchors = _two_material_fit()
    # 4 candidates for 2 materials: k-means spends the spare on an outlying anchor (measured: roughness 0.189,
    # f0 0.01) that takes no texel; it is dropped, the 2 that survive are the truth
    _, info = share_materials(model, obs, layout, theta, anchors, candidates=4)
    assert info["pruned"] == 1 and info["texels_per_material"] == [128, 128], info["texels_per_material"]
    got = sorted(round(m["roughness"][0], 3) for m in info["materials"])
    assert got == [0.3, 0.5], got
    _, info_all = share_materials(model, obs, layout, theta, anchors, candidates=4, min_evidence=0.0)
    assert info_all["pruned"] == 0 and len(info_all["materials"]) == 3 and 0 in info_all["texels_per_material"]


def test_share_materials_leaves_models_without_shared_parameters_alone():
    model = materials.get("lambert")
    gt = {"albedo": torch.full((4, 4, 3), 0.5, dtype=torch.float64)}
    obs = synthetic_observations(model, gt, samples_per_texel=4)
    layout = Layout.of(model)
    theta = layout.pack({"albedo": gt["albedo"].reshape(-1, 3)})
    out, info = share_materials(model, obs, layout, theta, torch.ones(16, dtype=torch.bool))
    assert info["materials"] == [] and torch.equal(out, theta)


def _prior_check(prior, canon, layout, skip):
    """The prior's descent direction is −½∇E (the data term's convention JᵀWr) and its Gauss-Newton product is
    ½∇²E·v wherever every difference is inside the quadratic part (the texels ``skip`` and their neighbours
    excluded)."""
    T = canon.shape[0]
    g = torch.Generator().manual_seed(1)
    dp = torch.ones(T, layout.P, dtype=torch.float64)
    grad, diag = prior.linearise(canon, dp)
    x = canon.clone().requires_grad_(True)
    (gE,) = torch.autograd.grad(prior.energy_tensor(x), x)
    torch.testing.assert_close(grad, -0.5 * gE, rtol=1e-10, atol=1e-12)
    v = torch.randn(T, layout.P, generator=g, dtype=torch.float64)
    mv = prior.matvec(v)
    x2 = canon.clone().requires_grad_(True)
    (g2,) = torch.autograd.grad(prior.energy_tensor(x2), x2, create_graph=True)
    (hv,) = torch.autograd.grad((g2 * v).sum(), x2)
    keep = torch.ones(T, dtype=torch.bool)
    H, W = prior.H, prior.W
    for t in skip:
        i, j = divmod(t, W)
        for di, dj in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)):
            if 0 <= i + di < H and 0 <= j + dj < W:
                keep[(i + di) * W + j + dj] = False
    torch.testing.assert_close(mv[keep], 0.5 * hv[keep], rtol=1e-10, atol=1e-12)
    return grad, diag


@pytest.mark.parametrize("shape", [(1, 9), (9, 1), (6, 5), (3, 3)])
@pytest.mark.parametrize("band", [None, 3])
@pytest.mark.parametrize("columns", ["every", "materials"])
def test_sharing_prior_on_thin_grids_in_bands_and_in_theta(shape, band, columns, monkeypatch):
    """One-row and one-column grids, holes that make bridges, a grid with no observed texel; in one band or in bands
    of a grid row (3 texels: bands that end inside a row on the wide grid). The gradient and product match the
    energy's derivatives, and in θ they are the canonical ones scaled by dp (the scale the product's matrix holds)."""
    if band is not None:
        monkeypatch.setattr(joint, "PRIOR_BAND", band)
    model = _ggx_lambert()
    layout = Layout.of(model)
    H, W = shape
    T = H * W
    g = torch.Generator().manual_seed(H * 10 + W)
    observed = torch.rand(T, generator=g) > 0.3
    if shape == (3, 3):
        observed[:] = False                                     # nothing observed: no edges, the anchor alone
    names = [s.name for s in layout.specs] if columns == "every" else ["f0", "roughness"]
    prior = _SharingPrior(layout, names, H, W, observed, delta=1.0)
    canon = torch.rand(T, layout.P, generator=g, dtype=torch.float64) * 0.004 + 0.3        # every difference quadratic
    prior.set_anchor(["f0", "roughness"], canon + 0.001, weight=0.1, delta=1.0)
    prior.mu, prior.nu = 0.7, 0.2
    _prior_check(prior, canon, layout, skip=[])
    dp = torch.rand(T, layout.P, generator=g, dtype=torch.float64) + 0.5
    v = torch.randn(T, layout.P, generator=g, dtype=torch.float64)
    grad, diag = prior.linearise(canon, dp)
    mv = prior.matvec(v)
    grad1, diag1 = prior.linearise(canon, torch.ones_like(dp))
    torch.testing.assert_close(grad, grad1 * dp, rtol=1e-12, atol=0)
    torch.testing.assert_close(diag, diag1 * dp * dp, rtol=1e-12, atol=0)
    torch.testing.assert_close(mv, prior.matvec(v * dp) * dp, rtol=1e-12, atol=1e-300)
    assert float(diag.abs().max()) > 0                          # (the anchor at least)


@pytest.mark.parametrize("band", [None, 7])
def test_sharing_prior_gradient_and_matvec_match_its_energy(band, monkeypatch):
    # band 7: the energy summed a grid row at a time and the product's pattern made 7 texels at a time (bands that
    # end inside a row), instead of in one band
    if band is not None:
        monkeypatch.setattr(joint, "PRIOR_BAND", band)
    model = _ggx_lambert()
    layout = Layout.of(model)
    H = W = 5
    T = H * W
    observed = torch.ones(T, dtype=torch.bool)
    observed[7] = False
    prior = _SharingPrior(layout, ["f0", "roughness"], H, W, observed, delta=1.0)
    prior.mu = 0.7
    g = torch.Generator().manual_seed(0)
    canon = torch.rand(T, layout.P, generator=g, dtype=torch.float64) * 0.01 + 0.3
    canon[3, layout.cols("roughness")] += 0.5                  # one large jump: the Huber (linear) branch
    grad, diag = _prior_check(prior, canon, layout, skip=[3])
    assert float(grad[:, layout.cols("albedo")].abs().max()) == 0.0       # albedo is not shared
    assert float(grad[7].abs().max()) == 0.0                              # unobserved texel: no edges
    assert bool((diag[:, layout.cols("f0")][observed] > 0).all())
    # the energy by hand: 40 edges of a 5 × 5 grid, 4 of them touch the unobserved texel 7 (all quadratic but
    # the 3 edges of texel 3, whose roughness jumped by 0.5 = 25 units: Huber 2·1·|d| − 1 there), plus the two
    # pairs that bridge texel 7: (1, 1)–(1, 3) along u and (0, 2)–(2, 2) along v
    d = (canon[:, prior.cols] / prior.thr).reshape(H, W, -1)
    ok = observed.reshape(H, W)
    pairs = [((i, j), (i, j + 1)) for i in range(H) for j in range(W - 1)] + \
        [((i, j), (i + 1, j)) for i in range(H - 1) for j in range(W)]
    pairs = [(a, b) for a, b in pairs if ok[a] and ok[b]] + [((1, 1), (1, 3)), ((0, 2), (2, 2))]
    assert len(pairs) == 38
    by_hand = 0.0
    for a, b in pairs:
        r = d[a] - d[b]
        by_hand += float(torch.where(r.abs() <= 1, r * r, 2 * r.abs() - 1).sum())
    assert prior.energy(canon) == pytest.approx(0.7 * by_hand, rel=1e-12)


@pytest.mark.parametrize("band", [None, 6])
def test_sharing_prior_anchor_term_ties_the_material_parameters_to_the_proposal(band, monkeypatch):
    # the unary term ν Σ ρ_H((p − m) / t): zero at the proposal, only on the material columns (not the albedo),
    # Huber beyond anchor_delta units, and consistent with its own gradient and Gauss-Newton product (band 6: in
    # bands of one grid row and of 6 texels, as test_sharing_prior_gradient_and_matvec_match_its_energy)
    if band is not None:
        monkeypatch.setattr(joint, "PRIOR_BAND", band)
    model = _ggx_lambert()
    layout = Layout.of(model)
    H = W = 4
    T = H * W
    names = [s.name for s in layout.specs]
    prior = _SharingPrior(layout, names, H, W, torch.ones(T, dtype=torch.bool), delta=0.3)
    g = torch.Generator().manual_seed(2)
    proposal = torch.rand(T, layout.P, generator=g, dtype=torch.float64) * 1e-3 + 0.3   # smooth
    prior.set_anchor(["f0", "roughness"], proposal, weight=0.1, delta=1.0)
    prior.mu, prior.nu = 0.0, 2.0                              # the unary term alone
    assert prior.energy(proposal) == 0.0
    moved = proposal.clone()
    moved[5, layout.cols("albedo")] += 0.3                     # the albedo is not anchored: no cost
    assert prior.energy(moved) == 0.0
    moved[5, layout.cols("roughness")] += 0.01                 # 0.5 units (roughness unit 0.02): quadratic
    assert prior.energy(moved) == pytest.approx(2.0 * 0.25, rel=1e-9)
    moved[6, layout.cols("f0")[0]] += 0.05                     # 5 units (f0 unit 0.01): linear, 2·1·5 − 1
    assert prior.energy(moved) == pytest.approx(2.0 * (0.25 + 9.0), rel=1e-9)
    prior.mu = 0.5                                             # both terms together
    grad, _ = _prior_check(prior, moved, layout, skip=[5, 6])
    assert float(grad[5, layout.cols("roughness")[0]]) < 0    # pulled back towards the proposal


def test_sharing_prior_weight_is_calibrated_on_the_material_parameters():
    # every parameter is in the prior by default; μ comes from the f0 / roughness columns only (the albedo's
    # larger curvature raised μ for all of them: default scene, albedo in units of 0.01, f0 0.0171 against
    # 0.0161)
    layout = Layout.of(_ggx_lambert())
    names = [s.name for s in layout.specs]
    prior = _SharingPrior(layout, names, 2, 2, torch.ones(4, dtype=torch.bool), 0.3)
    cols = [c for n in names for c in layout.cols(n)]
    assert sorted(cols[i] for i in prior.calibrate) == sorted(layout.cols("f0") + layout.cols("roughness"))
    only_albedo = _SharingPrior(layout, ["albedo"], 2, 2, torch.ones(4, dtype=torch.bool), 0.3)
    assert only_albedo.calibrate == [0, 1, 2]


def test_share_option_validation():
    model = _ggx_lambert()
    gt = _two_material_scene()
    obs = synthetic_observations(model, gt, samples_per_texel=2)
    with pytest.raises(SolverError, match="candidates"):
        solve_fast(model, obs, candidates=0)
    with pytest.raises(SolverError, match="sharing"):
        solve_fast(model, obs, sharing=-1.0)
    with pytest.raises(SolverError, match="anchor_weight must be a finite weight"):
        solve_fast(model, obs, anchor_weight=float("nan"))
    with pytest.raises(SolverError, match="joint_iterations must be an integer"):
        solve_fast(model, obs, joint_iterations=-1)
    with pytest.raises(SolverError, match="cg_iterations must be an integer"):
        solve_fast(model, obs, cg_iterations=2.5)
    with pytest.raises(SolverError, match="sharing_albedo must be True or False"):
        solve_fast(model, obs, sharing_albedo="no")
    layout = Layout.of(model)
    theta = layout.pack({k: v.reshape(-1, v.shape[-1]) for k, v in gt.items()})
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="min_evidence must be a finite"):
            share_materials(model, obs, layout, theta, torch.ones(256, dtype=torch.bool), min_evidence=bad)


def test_albedo_prior_by_hand():
    # two materials: 0 = a metal whose 3 anchors have albedo 0, 1 = a textured one (albedo 0.2 / 0.6 / 0.4)
    # texel 5 (own samples) has albedo (0.5, 0.5, 0.5) under both candidates; texel 6 has no own samples
    T = 7
    albedo = torch.zeros(2, T, 3, dtype=torch.float64)
    albedo[1, 3:6] = torch.tensor([0.2, 0.6, 0.4], dtype=torch.float64)[:, None]
    albedo[:, 5] = 0.5
    albedo[:, 6] = 0.9
    anchors = torch.tensor([1, 1, 1, 1, 1, 0, 0], dtype=torch.bool)
    lab = torch.tensor([0, 0, 0, 1, 1])
    own = torch.tensor([1, 1, 1, 1, 1, 1, 0], dtype=torch.bool)
    c = _albedo_prior(albedo, anchors, lab, own, floor=0.1, min_anchors=2)
    # material 0: mean 0, var 0 → (0.5² / 0.01) × 3 = 75; material 1 (anchors 3, 4: 0.2, 0.6): mean 0.4,
    # var 0.04 → (0.1² / 0.05) × 3 = 0.6
    torch.testing.assert_close(c[:, 5], torch.tensor([75.0, 0.6], dtype=torch.float64))
    assert float(c[:, 6].abs().max()) == 0.0                     # no own samples: no prior
    c3 = _albedo_prior(albedo, anchors, lab, own, floor=0.1, min_anchors=3)
    assert float(c3[1].abs().max()) == 0.0                       # material 1 has 2 < 3 anchors: no prior


def test_excess_deflates_texels_the_best_candidate_cannot_explain():
    costs = torch.tensor([[10.0, 400.0], [40.0, 800.0]], dtype=torch.float64)   # [K=2, T=2]
    residuals = torch.tensor([30.0, 100.0], dtype=torch.float64)
    e = _excess(costs, residuals)
    # texel 0 fits within the noise (χ²/n = 1/3 → s² = 1): excess 30; texel 1: s² = 4 → 400 / 4 = 100
    torch.testing.assert_close(e, torch.tensor([[0.0, 0.0], [30.0, 100.0]], dtype=torch.float64))
    torch.testing.assert_close(_excess(costs, None)[1], torch.tensor([30.0, 400.0], dtype=torch.float64))


def test_misfit_is_moderated_towards_the_photos_noise():
    # texels: one sample fitted exactly (3 residuals, 3 albedo unknowns: dof 0), 10 samples within the noise model,
    # 10 samples at 40× the model
    costs = torch.tensor([[0.0, 27.0, 1200.0], [5.0, 40.0, 1300.0]], dtype=torch.float64)
    residuals = torch.tensor([3.0, 30.0, 30.0], dtype=torch.float64)
    torch.testing.assert_close(_misfit(costs, residuals), torch.tensor([1.0, 1.0, 40.0], dtype=torch.float64))
    # photos measured at 25× the noise model: (χ²_best + 6 · 25) / (dof + 6) = 150 / 6, 177 / 33 and 1350 / 33
    # (above its own 40)
    torch.testing.assert_close(_misfit(costs, residuals, 25.0),
                               torch.tensor([25.0, 177.0 / 33.0, 1350.0 / 33.0], dtype=torch.float64))
    # noise-free photos (ratio ≤ 1) change nothing
    torch.testing.assert_close(_misfit(costs, residuals, 0.3), _misfit(costs, residuals))
    torch.testing.assert_close(_excess(costs, residuals, 25.0)[1], torch.tensor([5.0 / 25.0, 13.0 * 33.0 / 177.0,
                                                                                 100.0 * 33.0 / 1350.0],
                                                                                dtype=torch.float64))


def test_one_sample_texels_under_photo_noise_follow_the_albedo_prior():
    # a row of 9 texels with one sample each: noise makes the true material (0) look 20 χ² worse than a wrong one
    # (1), whose albedo distribution rejects the texels' albedo (prior 14). Taken at face value the photos outweigh
    # the albedo and every texel takes the wrong material (the gold's grazing band under shot noise: 9–24 χ²); with
    # the photos measured at 25× the noise model the 20 χ² are noise and the albedo decides, at one texel.
    T = 9
    costs = torch.stack([torch.full((T,), 20.0), torch.zeros(T)]).double()
    prior = torch.stack([torch.zeros(T), torch.full((T,), 14.0)]).double()
    residuals = torch.full((T,), 3.0, dtype=torch.float64)
    observed = torch.ones(T, dtype=torch.bool)
    label, _ = _assign(costs, observed, 1, T, evidence=10.0, cap=15.0, residuals=residuals, prior=prior)
    assert label.tolist() == [1] * T
    label, scale = _assign(costs, observed, 1, T, evidence=10.0, cap=15.0, residuals=residuals, prior=prior,
                           pooled=25.0)
    assert label.tolist() == [0] * T and scale.tolist() == [1] * T


def test_footprint_counts_bilinear_neighbours_with_positive_weight_only():
    from dataclasses import replace

    model = materials.get("lambert")
    obs = synthetic_observations(model, {"albedo": torch.full((2, 3, 3), 0.5, dtype=torch.float64)},
                                 samples_per_texel=1)
    assert obs.footprint().tolist() == [True] * 6                    # nearest: every texel has its sample
    keep = obs.select(obs.texel == 0)                                # one sample, in texel 0
    assert keep.footprint().tolist() == [True] + [False] * 5
    bil = replace(keep, bilinear_index=torch.tensor([[0, 1, 3, 4]]),
                  bilinear_weight=torch.tensor([[0.7, 0.3, 0.0, 0.0]], dtype=keep.weight.dtype))
    assert bil.footprint().tolist() == [True, True, False, False, False, False]


def test_refine_joint_rejects_bad_sharing_options():
    from capture.fit.joint import refine_joint
    from capture.fit.layout import param_groups

    model = _ggx_lambert()
    obs = synthetic_observations(model, _two_material_scene(), samples_per_texel=2)
    layout = Layout.of(model)
    theta = torch.zeros(obs.n_texels, layout.P, dtype=torch.float64)
    groups = param_groups(layout)
    with pytest.raises(SolverError, match="not parameters"):
        refine_joint(model, obs, layout, theta, groups, loss="l2", delta=1.0, sampling="nearest", sharing=1.0,
                     sharing_params=["gloss"])
    with pytest.raises(SolverError, match="sharing must be"):
        refine_joint(model, obs, layout, theta, groups, loss="l2", delta=1.0, sampling="nearest", sharing=-1.0)
    with pytest.raises(SolverError, match="noise_adaptive"):
        refine_joint(model, obs, layout, theta, groups, loss="l2", delta=1.0, sampling="nearest", sharing=1.0,
                     noise_adaptive=["gloss"])


def _lambert_refinement():
    """A 6 × 6 Lambert problem for refine_joint (two samples a texel, random albedo): model, obs, layout, θ = 0."""
    model = materials.get("lambert")
    g = torch.Generator().manual_seed(0)
    albedo = 0.2 + 0.6 * torch.rand(6, 6, 3, generator=g, dtype=torch.float64)
    obs = synthetic_observations(model, {"albedo": albedo}, samples_per_texel=2)
    layout = Layout.of(model)
    return model, obs, layout, torch.zeros(obs.n_texels, layout.P, dtype=torch.float64)


def test_refinement_goes_on_when_the_noise_units_change_its_objective():
    # the noise-adaptive units are updated from the second iteration on; the prior's energy under the new units can
    # exceed the whole cost of the step before (here 0.021 → 0.33 per residual). The stopping rule must compare
    # each step with the cost of its own objective: comparing with the previous entry of the history stopped this
    # refinement after two of its five steps, every step being accepted
    from capture.fit.joint import refine_joint
    from capture.fit.layout import param_groups

    model, obs, layout, theta = _lambert_refinement()
    _, info = refine_joint(model, obs, layout, theta, param_groups(layout), loss="l2", delta=1.0, sampling="nearest",
                           sharing=1.0, iterations=5, noise_adaptive=("albedo",))
    h = info["joint_history"]
    assert h[2] > h[1]                                   # the units' update raised the recorded cost
    assert len(h) == 6 and info["joint_accepted"] == [True] * 5
    assert all(b < a for a, b in zip(h[2:-1], h[3:], strict=True))   # and each later step lowered it


def test_refinement_prices_each_trial_once_and_nothing_else(monkeypatch):
    # a data cost is a full prediction of the photos; the units' update and the prior's calibration change only the
    # prior, so the refinement renders once at the start and once per trial step — the same fit as re-pricing
    from capture.fit import joint
    from capture.fit.layout import param_groups

    model, obs, layout, theta = _lambert_refinement()
    calls = []
    cost = joint._JointData.cost
    monkeypatch.setattr(joint._JointData, "cost", lambda self, th: calls.append(1) or cost(self, th))
    th, info = joint.refine_joint(model, obs, layout, theta, param_groups(layout), loss="l2", delta=1.0,
                                  sampling="nearest", sharing=1.0, iterations=5, noise_adaptive=("albedo",))
    assert len(calls) == 1 + len(info["joint_accepted"])
    # the data cost kept is the final θ's, not a rejected trial's
    data = joint._JointData(model, obs, layout, param_groups(layout), obs.n_texels, sampling="nearest",
                            footprints=None, loss="l2", delta=1.0)
    assert info["joint_data_cost"] == pytest.approx(cost(data, th) / data.n_res, rel=1e-12)


class _Quadratic:
    """A damped system for ``_damped_step`` of the cost Σ (θ − t)²: Hessian 2·I, Gauss-Newton step t − θ."""

    def __init__(self, theta, target):
        T, P = theta.shape
        self.B = 2.0 * torch.eye(P, dtype=torch.float64).expand(T, P, P).clone()
        self.diag = torch.full((T, P), 2.0, dtype=torch.float64)
        self.live = torch.ones(T, dtype=torch.bool)
        self.g = 2.0 * (target - theta)

    def matvec(self, v, lam, out):
        return out.copy_(2.0 * v + lam * self.diag * v)


def test_joint_steps_trust_region_grows_when_cut_and_tries_half_a_rejected_step():
    # the exact step to θ = 5 is cut by the box: 1, then (radius doubled) 2, then 3 (TRUST_MAX) — θ 1, 3, 5 where a
    # fixed box of 1 reaches 3 after three steps
    from capture.fit.joint import MAX_STEP, TRUST_MAX, _damped_step

    assert MAX_STEP == 1.0 and TRUST_MAX == 3.0
    target = torch.full((4, 2), 5.0, dtype=torch.float64)

    def cost_of(th):
        return float((th - target).square().sum())

    theta, lam, radius, accepted = torch.zeros(4, 2, dtype=torch.float64), 1e-12, MAX_STEP, []
    seen = []
    for _ in range(3):
        theta, cost, lam, radius = _damped_step(_Quadratic(theta, target), theta, cost_of(theta), lam, radius,
                                                cost_of, 10, accepted)
        seen.append((float(theta[0, 0]), radius))
    assert [round(t, 6) for t, _ in seen] == [1.0, 3.0, 5.0] and [r for _, r in seen] == [2.0, 3.0, 3.0]
    assert accepted == [True] * 3
    # a wall: any component moved by more than 1.5 costs infinitely much. The step clamped to the radius (2) is
    # rejected, the one clamped to half of it accepted at once — one solve, and the radius is the half
    theta, accepted = torch.zeros(4, 2, dtype=torch.float64), []

    def walled(th):
        return math.inf if bool((th.abs() > 1.5).any()) else cost_of(th)

    theta, _, lam2, radius = _damped_step(_Quadratic(theta, target), theta, walled(theta), 1e-12, 2.0, walled, 10,
                                          accepted)
    assert accepted == [False, True] and radius == 1.0 and float(theta.max()) == pytest.approx(1.0)
    assert lam2 == pytest.approx(1e-9)   # an accepted step: λ / 3, floored
    # a wall at 0.3: both trials of the first solve fail (radius 1 and 0.5), λ grows ×4 and the radius halves; the
    # second solve's trials are 0.5 (rejected) and 0.25 (kept)
    theta, accepted = torch.zeros(4, 2, dtype=torch.float64), []

    def near(th):
        return math.inf if bool((th.abs() > 0.3).any()) else cost_of(th)

    theta, _, lam3, radius = _damped_step(_Quadratic(theta, target), theta, near(theta), 1e-3, 1.0, near, 10,
                                          accepted)
    assert accepted == [False, False, False, True] and radius == 0.25 and float(theta.max()) == pytest.approx(0.25)
    assert lam3 == pytest.approx(4e-3 / 3)


def test_pooled_materials_recover_a_tile_lobe_that_no_single_texel_determines():
    # 8×8 texels in four 4×4 tiles; each tile one lobe (f0, roughness on the pooled fit's roughness grid), each
    # texel its own albedo. Three samples per texel, none near the mirror direction: one texel's samples cannot
    # tell f0 from roughness, the 48 samples of a tile can. Noise-free and rendered by the same model, so the
    # pooled least squares must return the tile's lobe and a zero cost.
    from capture.fit.sharing import _chi2_observations, pooled_materials
    from capture.fit.texel import grid_values

    model = _ggx_lambert()
    layout = Layout.of(model)
    rough_spec = next(s for s in layout.specs if s.name == "roughness")
    values = grid_values(rough_spec, 12, torch.float64, "cpu")
    lobes = [((0.9, 0.6, 0.3), values[7]), ((0.04, 0.04, 0.04), values[10]),
             ((0.05, 0.08, 0.12), values[9]), ((0.5, 0.5, 0.5), values[5])]
    g = torch.Generator().manual_seed(4)
    maps = {"albedo": torch.rand(8, 8, 3, generator=g, dtype=torch.float64) * 0.6 + 0.2,
            "f0": torch.empty(8, 8, 3, dtype=torch.float64), "roughness": torch.empty(8, 8, 1, dtype=torch.float64)}
    for t, (f0, r) in enumerate(lobes):
        rows, cols = slice(4 * (t // 2), 4 * (t // 2) + 4), slice(4 * (t % 2), 4 * (t % 2) + 4)
        maps["f0"][rows, cols] = torch.tensor(f0, dtype=torch.float64)
        maps["roughness"][rows, cols] = float(r)
    obs = synthetic_observations(model, maps, samples_per_texel=3, highlight_fraction=0.0, seed=2)
    chi = _chi2_observations(obs, (0.01, 0.1))
    mats, cost, tile = pooled_materials(model, layout, chi, torch.ones(64, dtype=torch.bool), block=4)
    assert mats.shape == (4, 4) and tile.reshape(8, 8)[5, 2].item() == 2
    for t, (f0, r) in enumerate(lobes):
        torch.testing.assert_close(mats[t], torch.tensor([*f0, float(r)], dtype=torch.float64), rtol=0, atol=1e-6)
    assert float(cost.max()) < 1e-8
    # a pool that leaves a tile empty gives it no cost; a model without a separable lobe is not poolable
    part = torch.ones(64, dtype=torch.bool)
    part[tile == 3] = False
    assert float(pooled_materials(model, layout, chi, part, block=4)[1][3]) == 0.0
    lam = materials.get("lambert")
    assert pooled_materials(lam, Layout.of(lam), chi, part) is None


def test_tile_seeds_take_the_median_of_tiles_whose_texels_agree_within_their_noise():
    # 8 × 8 texels, four 4 × 4 tiles, no anchor; thresholds t (f0 0.01 per channel, roughness 0.02). Tile 0: every
    # texel's estimate within ±σ of the truth, σ = 2t (no texel an anchor), lower median at the truth; standard error
    # 1.2533 · 2t / 4 = 0.63 t < t, spread 1.4826 · 0.5 σ = 0.74 σ ≤ 2 σ → one seed, the truth. Tile 1: same but
    # σ = 4t (standard error 1.25 t). Tile 2: estimates ±3σ (spread 2.2 σ). Tile 3: 7 of 16 texels observed.
    from capture.fit.observability import SEED_SPREAD, std_threshold, tile_seeds

    model = _ggx_lambert()
    layout = Layout.of(model)
    names = ["f0", "roughness"]
    thr = torch.tensor([std_threshold(s) for s in layout.specs if s.name in names for _ in range(s.channels)],
                       dtype=torch.float64)
    cols = [c for n in names for c in layout.cols(n)]
    truth = torch.tensor([0.04, 0.05, 0.06, 0.6], dtype=torch.float64)
    steps = torch.tensor([-1, -1, -1, -1, -0.5, -0.5, -0.5, 0, 0, 0.5, 0.5, 0.5, 1, 1, 1, 1], dtype=torch.float64)
    canon = torch.zeros(64, layout.P, dtype=torch.float64)
    std = torch.zeros(64, layout.P, dtype=torch.float64)
    observed = torch.ones(64, dtype=torch.bool)
    tile = (torch.arange(8)[:, None] // 4 * 2 + torch.arange(8)[None, :] // 4).reshape(-1)
    for t, (sigma, scale) in enumerate([(2.0, 1.0), (4.0, 1.0), (2.0, 3.0), (2.0, 1.0)]):
        idx = torch.nonzero(tile == t).squeeze(-1)
        canon[idx[:, None], torch.tensor(cols)] = truth + scale * sigma * steps[:, None] * thr
        std[idx[:, None], torch.tensor(cols)] = sigma * thr
    observed[torch.nonzero(tile == 3).squeeze(-1)[7:]] = False
    assert 1.4826 * 0.5 * 3.0 > SEED_SPREAD           # tile 2's estimates scatter more than their std allows
    seeds = tile_seeds(layout, canon, std, observed, torch.zeros(64, dtype=torch.bool), names, (8, 8))
    torch.testing.assert_close(seeds, truth[None], rtol=0, atol=1e-12)
    # at the anchors' loosening × 2 tile 1 (standard error 1.25 t) qualifies too; tiles 2 and 3 still do not
    loose = tile_seeds(layout, canon, std, observed, torch.zeros(64, dtype=torch.bool), names, (8, 8), factor=2.0)
    torch.testing.assert_close(loose, truth[None].expand(2, -1), rtol=0, atol=1e-12)
    # texels that are anchors already are not pooled again: with tile 0's anchored, no seed is left
    anchors = tile == 0
    assert tile_seeds(layout, canon, std, observed, anchors, names, (8, 8)).shape == (0, 4)
    with pytest.raises(SolverError, match="block must be"):
        tile_seeds(layout, canon, std, observed, anchors, names, (8, 8), block=0)
    with pytest.raises(SolverError, match=r"\[16, 7\]"):
        tile_seeds(layout, canon, std, observed, anchors, names, (4, 4))


def test_tile_seeds_give_the_sharing_a_material_whose_texels_are_no_anchors():
    # the two-material scene with the dielectric half's anchors removed (as a rough material under a flash gives
    # none): the one material left, the metal, serves both halves without seeds (measured: interior f0 0.46 off);
    # the tiles of the dielectric's per-texel fits, which agree, seed its material and the interior recovers
    # (f0, roughness within 0.005)
    from capture.fit.observability import tile_seeds

    model, obs, layout, theta, anchors = _two_material_fit()
    right = (torch.arange(256) % 16) >= 8
    cut = anchors & ~right
    interior = right & ((torch.arange(256) % 16) >= 12)
    fit = solve_fast(model, obs, share=False)
    std = torch.cat([fit.confidence[s.name].reshape(256, -1).double() for s in layout.specs], -1)   # canonical
    seeds = tile_seeds(layout, layout.canonical(theta), std, fit.observed.reshape(-1), cut, ["f0", "roughness"],
                       (16, 16))
    assert seeds.shape[0] >= 4
    without, _ = share_materials(model, obs, layout, theta, cut, candidates=2)
    out, info = share_materials(model, obs, layout, theta, cut, candidates=2, seeds=seeds)
    assert float((layout.unpack(without)["f0"][interior] - 0.04).abs().max()) > 0.1
    rec = layout.unpack(out)
    assert float((rec["f0"][interior] - 0.04).abs().max()) < 0.005
    assert float((rec["roughness"][interior, 0] - 0.5).abs().max()) < 0.005
    assert any(abs(m["f0"][0] - 0.04) < 0.005 for m in info["materials"]), info["materials"]
    with pytest.raises(ValueError, match="seeds must be"):
        share_materials(model, obs, layout, theta, cut, candidates=2, seeds=seeds[:, :2])


def test_pooled_proposals_add_a_material_the_anchors_miss_and_nothing_where_they_suffice():
    model, obs, layout, theta, anchors = _two_material_fit()
    # the right half (f0 0.04, roughness 0.5) loses its anchors (126 of the 253): without pooling the one material
    # left must serve both halves (measured: the right half's interior f0 0.11 off, roughness 0.016), with it a
    # tile proposes the dielectric (f0 0.001 off, roughness 0.0005)
    right = (torch.arange(256) % 16) >= 8
    cut = anchors & ~right
    spoiled = layout.unpack(theta)
    spoiled["f0"][right] = 0.5
    spoiled["roughness"][right] = 0.8
    theta_s = layout.pack(spoiled)
    interior = right & ((torch.arange(256) % 16) >= 12)       # texels ≥ 2 tiles from the last anchor
    _, off = share_materials(model, obs, layout, theta_s, cut, candidates=2)
    out, on = share_materials(model, obs, layout, theta_s, cut, candidates=2, pool_block=4)
    assert off.get("pooled_tiles") is None and len(off["materials"]) == 1
    assert on["pooled_tiles"] >= 4
    rec = layout.unpack(out)
    err = (rec["roughness"][interior, 0] - 0.5).abs().max()
    assert float(err) < 0.005, float(err)
    assert float((rec["f0"][interior] - 0.04).abs().max()) < 0.005
    # with every anchor present no tile is a blind spot: nothing is proposed, the result is unchanged
    a, ia = share_materials(model, obs, layout, theta, anchors, candidates=4)
    b, ib = share_materials(model, obs, layout, theta, anchors, candidates=4, pool_block=4)
    assert ib["pooled_tiles"] == 0
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(ValueError, match="pool_block"):
        share_materials(model, obs, layout, theta, anchors, pool_block=-1)
    with pytest.raises(SolverError, match="pooled"):
        solve_fast(model, obs, pooled=2.5)


def test_refit_recovers_the_materials_and_stops_those_that_have_settled():
    # Noise-free two-material scene, every texel's albedo at the truth: the left material starts at its truth
    # (cost at rounding level: it settles at once and its samples leave the later iterations), the right one 0.1
    # off in roughness and f0. The refit brings it back to 1e-17 (measured) and ends where refitting every
    # material on every sample for all iterations (rtol = 0) ends.
    from capture.fit.layout import ACC, param_groups
    from capture.fit.sharing import _chi2_observations, _refit

    model = _ggx_lambert()
    gt = _two_material_scene()
    obs = _chi2_observations(synthetic_observations(model, gt, samples_per_texel=12, highlight_fraction=0.34, seed=1),
                             (0.01, 0.1))
    layout = Layout.of(model)
    theta = layout.pack({k: v.reshape(256, -1) for k, v in gt.items()})
    label = (torch.arange(256) % 16 >= 8).long()
    scols = layout.cols("f0") + layout.cols("roughness")
    groups = [c for c in param_groups(layout) if all(x in scols for x in c)]
    truth = theta[[0, 8]].clone()
    start = layout.unpack(truth)
    start["roughness"][1] += 0.1
    start["f0"][1] += 0.1
    mat = layout.pack(start)
    y, w = obs.radiance.to(ACC), obs.weight.to(ACC)
    out = _refit(model, layout, obs, theta, mat, label, scols, groups, y, w, 8)
    full = _refit(model, layout, obs, theta, mat, label, scols, groups, y, w, 8, rtol=0.0)
    for k in ("f0", "roughness"):
        err = (layout.unpack(out)[k] - layout.unpack(truth)[k]).abs().amax(-1)
        # the metal's albedo 0 is 1e-6 in the θ parameterisation (sigmoid), so its f0 settles 2e-6 off (measured)
        assert float(err[0]) < 1e-5 and float(err[1]) < 1e-9, (k, err)
    torch.testing.assert_close(out, full, rtol=0, atol=1e-6)
