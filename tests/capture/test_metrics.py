"""Map-error metrics against ground truth, by hand."""

import math

import pytest
import torch

from capture.metrics import MetricsError, observability_errors


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
