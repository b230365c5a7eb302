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
