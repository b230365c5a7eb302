"""BRDF fitting: sampling, error bookkeeping, parameter recovery on analytic data, Nielsen's staged procedure."""

import math

import pytest
import torch

import materials
import materials.measured  # noqa: F401  registers "measured" (not yet imported by materials/__init__)
from capture import brdf_fit as F
from materials import Model
from materials.geometry import guarded_pow
from materials.params import ALBEDO, MIX, ROUGHNESS, SPECULAR
from materials.roughness import R_MIN, roughness_to_shininess

D64 = torch.float64


class _Mixture(Model):
    """Nielsen eq 3 without Fresnel, defined here so the fitter is tested independently of materials/nielsen.py:
    ρ_d/π + k_s ((1 − α) r·v + α (n·h)⁴)^s with s from the canonical roughness."""

    name = "test-mixture"
    params = (ALBEDO, SPECULAR, ROUGHNESS, MIX)

    def brdf(self, g, p):
        s = roughness_to_shininess(p["roughness"])
        c = (1 - p["mix"]) * g.rv + p["mix"] * g.nh.clamp_min(0) ** 4
        f = p["albedo"] / math.pi + p["specular"] * guarded_pow(c, s)
        return torch.where(g.front, f, torch.zeros_like(f))


def test_samples_are_front_facing_well_spread_and_deterministic():
    s = F.make_samples(resolution=16, dtype=D64)
    assert len(s) > 1000 and (s.g.nl > 0).all() and (s.g.nv > 0).all()
    torch.testing.assert_close(s.weight, s.g.nl)
    th = torch.acos(s.g.nh.clamp(-1, 1))
    assert th.max() > 1.3 and (th < 0.01).sum() > 50  # sqrt-spaced θ_h: dense near the peak, reaching 90°
    frac = s.grazing.double().mean().item()
    assert 0.05 < frac < 0.4
    again = F.make_samples(resolution=16, dtype=D64)
    assert torch.equal(again.g.nl, s.g.nl)
    # uniform hemispheres: E[cos θ] = 1/2 over a hemisphere uniform in solid angle
    h = F.make_samples("hemispheres", resolution=16, dtype=D64)
    assert h.g.nl.mean().item() == pytest.approx(0.5, abs=0.01)
    assert h.g.nv.mean().item() == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="unknown scheme"):
        F.make_samples("grid")


def test_errors_with_and_without_grazing():
    s = F.make_samples(resolution=8, dtype=D64)
    meas = torch.ones(len(s), 3, dtype=D64)
    pred = meas + s.grazing.double()  # wrong by 1 only at grazing samples
    e = F.errors(pred, meas, s)
    assert e.mae_no_grazing == 0.0 and e.rel_l1_no_grazing == 0.0
    w = s.weight.squeeze(-1)
    g = s.grazing.squeeze(-1)
    assert e.mae == pytest.approx(w[g].sum().item() / len(s))
    assert e.rel_l1 == pytest.approx(w[g].sum().item() / w.sum().item())


def test_lambert_recovered_exactly():
    s = F.make_samples(resolution=12, dtype=D64)
    truth = torch.tensor([0.62, 0.31, 0.05], dtype=D64)
    lam = materials.get("lambert")
    r = F.fit_brdf("lambert", lam, s, target_params={"albedo": truth})
    torch.testing.assert_close(r.params["albedo"], truth, atol=1e-3, rtol=0)
    assert r.errors.rel_l1 < 1e-3 and r.stages == [("albedo",)]


def test_mixture_parameters_recovered_from_its_own_data():
    s = F.make_samples(resolution=16, dtype=D64)
    truth = {"albedo": torch.tensor([0.3, 0.2, 0.1], dtype=D64), "specular": torch.tensor([2.0, 1.5, 1.0], dtype=D64),
             "roughness": torch.tensor([0.3], dtype=D64), "mix": torch.tensor([0.7], dtype=D64)}
    m = _Mixture()
    r = F.fit_brdf(m, m, s, target_params=truth, restarts=2)
    for k, v in truth.items():
        torch.testing.assert_close(r.params[k], v, atol=1e-3, rtol=1e-3, msg=k)
    assert r.errors.rel_l1 < 1e-3
    # parameters stay inside their ranges through the parameterisation (roughness ≥ R_MIN)
    r2 = F.fit_brdf(m, m, s, target_params={**truth, "roughness": torch.tensor([0.0], dtype=D64)}, restarts=1,
                    adam_steps=40, lbfgs_steps=5)
    assert R_MIN - 1e-12 <= r2.params["roughness"].item() <= 1.0
    assert 0 <= r2.params["mix"].item() <= 1 and (r2.params["specular"] >= 0).all()


def test_registered_phong_recovered_from_its_own_data():
    s = F.make_samples(resolution=16, dtype=D64)
    m = materials.get("nielsen-phong")
    truth = {"albedo": torch.tensor([0.4, 0.25, 0.1], dtype=D64), "specular": torch.tensor([1.5], dtype=D64).expand(
        m.spec("specular").channels).clone(), "roughness": torch.tensor([0.35], dtype=D64),
        "ior": torch.tensor([1.6], dtype=D64)}
    r = F.fit_brdf(m, m, s, target_params=truth, restarts=2)
    for k, v in truth.items():
        torch.testing.assert_close(r.params[k], v, atol=1e-3, rtol=1e-3, msg=k)


@pytest.mark.nbrdf
def test_staged_procedure_beats_single_stage_from_a_bad_guess_on_nickel():
    """Nielsen's claim, checked where it holds in our measurements (see capture/brdf_fit.py: it does not hold for
    every model/material; joint fits with restarts are as good or better in all 12 cases we ran)."""
    s = F.make_samples(resolution=16, dtype=torch.float32)
    target = materials.get("measured", material="nickel")
    bad = {"albedo": torch.tensor(0.95), "specular": torch.tensor(500.0), "roughness": torch.tensor(0.95),
           "ior": torch.tensor(2.9)}
    staged = F.fit_brdf("nielsen-phong", target, s, procedure="nielsen", restarts=1, init=bad)
    joint = F.fit_brdf("nielsen-phong", target, s, procedure="joint", restarts=1, init=bad)
    assert staged.stages == [("albedo", "specular"), ("roughness", "ior"), ("roughness", "ior", "specular")]
    assert staged.objective <= joint.objective + 1e-4, (staged.objective, joint.objective)
    assert staged.errors.rel_l1_no_grazing < 0.5  # measured 0.34 (float64); errors reported both ways


def test_bad_input_is_named():
    s = F.make_samples(resolution=6, dtype=D64)
    with pytest.raises(ValueError, match="unknown procedure"):
        F.fit_brdf("lambert", materials.get("lambert"), s, procedure="lm")
    with pytest.raises(ValueError, match="unknown model"):
        F.fit_brdf("no-such-model", materials.get("lambert"), s)
    with pytest.raises(ValueError, match="not parameters of"):
        F.fit_brdf("lambert", materials.get("lambert"), s, init={"f0": torch.tensor(0.1)})
    with pytest.raises(ValueError, match="NaN"):
        F.fit_brdf("lambert", lambda g: torch.full((g.nl.shape[0], 3), math.nan, dtype=D64), s)
    with pytest.raises(TypeError, match="target must be"):
        F.fit_brdf("lambert", 3.0, s)


@pytest.mark.nbrdf
def test_cook_torrance_near_lambert_on_nickel_is_the_grazing_samples_not_a_local_minimum():
    """Cook-Torrance scores near Lambert on nickel (docs/measured-fits.md) because of the grazing samples: fitted
    without them, its narrow lobe matches the rest (L1 w/o grazing 0.34 measured) but over-predicts the grazing
    samples ~27× (L1 there 26.7), so on the all-angle objective that lobe is far worse (4.8) than the broad one the
    all-angle fit finds (0.97). Measured at resolution 12 (640 samples), 2 restarts."""
    s = F.make_samples(resolution=12, dtype=D64)
    tgt = materials.get("measured", material="nickel")
    kw = dict(restarts=2, adam_steps=100, lbfgs_steps=30)
    full = F.fit_brdf("cook-torrance", tgt, s, **kw)
    nogz = F.fit_brdf("cook-torrance", tgt, s, exclude_grazing=True, **kw)
    assert full.objective > 0.9 and full.errors.rel_l1_no_grazing > 0.9
    assert nogz.errors.rel_l1_no_grazing < 0.45  # 0.34 measured: a good fit away from grazing exists
    assert nogz.errors.rel_l1_grazing > 10.0  # 26.7 measured
    assert nogz.errors.rel_l1 > 3 * full.objective  # so it is not a better minimum of the all-angle objective
    assert nogz.params["roughness"].item() < 0.3 < full.params["roughness"].item()  # 0.22 vs 0.61 measured
