"""Geometry (Angles), the Model interface and the registry."""

import math

import pytest
import torch

import materials
from materials import Angles
from materials.geometry import safe_normalize


def _unit(*xyz):
    v = torch.tensor(xyz, dtype=torch.float64)
    return v / v.norm()


def test_angles_from_vectors_and_cosines_agree():
    g = torch.Generator().manual_seed(0)
    n = safe_normalize(torch.randn(500, 3, generator=g, dtype=torch.float64))
    l = safe_normalize(torch.randn(500, 3, generator=g, dtype=torch.float64))
    v = safe_normalize(torch.randn(500, 3, generator=g, dtype=torch.float64))
    a = Angles.from_vectors(n, l, v)
    b = Angles.from_cosines(a.nl, a.nv, a.lv)
    for f in ("nl", "nv", "nh", "lh", "lv"):
        torch.testing.assert_close(getattr(a, f), getattr(b, f), atol=1e-9, rtol=1e-9)


def test_angles_half_vector_at_opposite_directions_is_finite():
    n = _unit(0, 0, 1)
    l = _unit(1, 0, 0.2).requires_grad_()
    v = -l.detach()
    a = Angles.from_vectors(n, l, v)
    assert not a.front.item()
    (grad,) = torch.autograd.grad(a.nh.sum() + a.lh.sum(), l)
    assert torch.isfinite(grad).all()


def test_safe_normalize_gradient_of_a_tiny_vector_is_finite_and_exact_in_float32():
    # the half vector l + v of a grazing mirror pair (n·l = n·v = c) is (0, 0, 2c), tiny; a lobe's derivative
    # with respect to it can be ~1e20 (a mirror-like D at grazing angles). The backward pass of x·|x|^-1 used to
    # form x (x·g)|x|^-3: inf in float32 at |x| ≈ 1e-11, although the true (I − u uᵀ) g / |x| is ~1e31.
    g64 = torch.tensor([1e20, -3e19, 7e19], dtype=torch.float64)
    for c in (1e-3, 1e-7, 1e-11):
        x64 = (c * torch.tensor([[0.3, -0.2, 1.0]], dtype=torch.float64)).requires_grad_()
        x = x64.detach().float().requires_grad_()
        for xx in (x64, x):
            (safe_normalize(xx) * g64.to(xx.dtype)).sum().backward()
            assert torch.isfinite(xx.grad).all()
        u64 = x64.detach() / x64.detach().norm()
        expected = (g64 - u64 * (u64 * g64).sum()) / x64.detach().norm()
        torch.testing.assert_close(x64.grad, expected, rtol=1e-12, atol=0.0)
        torch.testing.assert_close(x.grad.double(), expected, rtol=1e-5, atol=0.0)
        torch.testing.assert_close(safe_normalize(x.detach()).double(), u64, rtol=1e-6, atol=1e-7)
    tiny = torch.zeros(1, 3, requires_grad=True)
    safe_normalize(tiny).sum().backward()
    assert torch.equal(tiny.grad, torch.zeros(1, 3))  # the fallback branch has no gradient


def test_mirror_cosine():
    n, l, v = _unit(0, 0, 1), _unit(1, 0, 1), _unit(-1, 0, 1)
    assert Angles.from_vectors(n, l, v).rv.item() == pytest.approx(1.0)


def test_registry_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown model 'nope'.*lambert"):
        materials.get("nope")
    with pytest.raises(ValueError, match="does not take options"):
        materials.get("lambert", colour=1)
    assert "lambert" in materials.available()


def test_lambert_golden_and_parameter_checks():
    m = materials.get("lambert")
    n = _unit(0, 0, 1)
    f = m(n, _unit(0.3, 0, 1), _unit(-0.2, 0.1, 1), albedo=torch.tensor([0.5, 0.25, 1.0], dtype=torch.float64))
    torch.testing.assert_close(f, torch.tensor([0.5, 0.25, 1.0], dtype=torch.float64) / math.pi)
    assert m(n, _unit(0, 0, -1), n).abs().max().item() == 0.0  # light below the horizon
    with pytest.raises(ValueError, match="'albedo' must lie in"):
        m(n, n, n, albedo=torch.tensor([1.5, 0.0, 0.0]))
    with pytest.raises(ValueError, match="unknown parameter"):
        m(n, n, n, f0=torch.tensor([0.04]))


def test_known_params_model_holds_values_and_exposes_the_rest():
    base = materials.get("gotanda2012-layered")
    m = materials.KnownParams(base, {"coat_ior": 1.5, "coat_roughness": [0.1]})
    assert m.param_names == ("albedo", "f0", "roughness", "absorption")
    gen = torch.Generator().manual_seed(3)
    N = 64
    g = Angles.from_cosines(torch.rand(N, 1, generator=gen, dtype=torch.float64) * 0.9 + 0.05,
                            torch.rand(N, 1, generator=gen, dtype=torch.float64) * 0.9 + 0.05,
                            torch.rand(N, 1, generator=gen, dtype=torch.float64) * 1.6 - 0.8)
    p = {s.name: torch.rand(N, s.channels, generator=gen, dtype=torch.float64) * 0.5 + 0.1 for s in m.params}
    before = {k: v.clone() for k, v in p.items()}
    full = {**p, "coat_ior": torch.full((N, 1), 1.5, dtype=torch.float64),
            "coat_roughness": torch.full((N, 1), 0.1, dtype=torch.float64)}
    torch.testing.assert_close(m.brdf(g, p), base.brdf(g, full), rtol=0, atol=0)
    torch.testing.assert_close(m.cosine_brdf(g, p), base.cosine_brdf(g, full), rtol=0, atol=0)
    assert all(torch.equal(p[k], before[k]) for k in p)          # inputs untouched
    # a different coat value changes the result (the known value is really used)
    other = materials.KnownParams(base, {"coat_ior": 2.0, "coat_roughness": 0.1})
    assert (other.brdf(g, p) - m.brdf(g, p)).abs().max() > 1e-3
    # per-channel values and validation with messages that name the problem
    mk = materials.KnownParams(base, {"absorption": [0.1, 0.2, 0.3]})
    assert "absorption" not in mk.param_names and mk.known["absorption"].tolist() == [0.1, 0.2, 0.3]
    for bad, msg in (({"nope": 1.0}, "no such parameter"), ({"coat_ior": 0.5}, "outside its range"),
                     ({"absorption": [0.1, 0.2]}, "3 channel"), ({"coat_ior": float("nan")}, "not finite"),
                     ({}, "at least")):
        with pytest.raises(ValueError, match=msg):
            materials.KnownParams(base, bad)
    with pytest.raises(ValueError, match="nothing is left"):
        materials.KnownParams(materials.get("lambert"), {"albedo": 0.5})


def test_brdf_cosine_brdf_and_environment_validate_their_parameters_once(monkeypatch):
    g = Angles.from_cosines(torch.tensor([[0.5]]), torch.tensor([[0.6]]), torch.tensor([[0.1]]))
    bad = {"albedo": torch.tensor([[0.5, 0.5, 0.5]]), "f0": torch.tensor([[1.5, 0.04, 0.04]]),
           "roughness": torch.tensor([[0.5]])}
    for name in ("ggx-lambert", "gotanda2012", "schuler", "gotanda2012-layered"):
        m = materials.get(name)
        p = {**m.defaults((1,)), **{k: v for k, v in bad.items() if k in m.param_names}}
        for fn in (m.brdf, m.cosine_brdf):
            with pytest.raises(ValueError, match="'f0' must lie in"):
                fn(g, p)
        with pytest.raises(ValueError, match="missing parameter"):
            m.brdf(g, {})
        with pytest.raises(TypeError, match="Angles"):
            m.brdf(torch.zeros(1, 3), m.defaults((1,)))
    hemi = materials.HemisphereLight(torch.ones(3), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    n = torch.tensor([[0.0, 0.0, 1.0]])
    m = materials.get("schuler")
    with pytest.raises(ValueError, match="'albedo' contains NaN"):
        m.environment(hemi, n, n, {**m.defaults((1,)), "albedo": torch.full((1, 3), float("nan"))})
    # once, at the outermost entry: a sum of parts, a coat over a bottom and known parameters are checked once,
    # and the values a model derives for its parts (a Nielsen bottom's η relative to a denser coat, 1.2/1.5 < 1,
    # below the canonical range [1, 3]) are not checked again
    calls = []
    real = materials.Model.check
    monkeypatch.setattr(materials.Model, "check", lambda self, p: (calls.append(self.name), real(self, p))[1])
    layered = materials.get("gotanda2012-layered", bottom="nielsen-phong")
    p = {**layered.defaults((1,)), "ior": torch.tensor([[1.2]]), "coat_ior": torch.tensor([[1.5]])}
    assert torch.isfinite(layered.cosine_brdf(g, p)).all()
    known = materials.KnownParams(materials.get("ggx-lambert"), {"f0": 0.04})
    known.brdf(g, known.defaults((1,)))
    materials.get("lambert")(n[0], n[0], n[0])
    assert calls == [layered.name, known.name, "lambert"]


def test_param_spec_declares_its_fit_export_and_figure_facts_and_checks_them():
    from dataclasses import replace

    from materials.params import ALBEDO, CANONICAL, F0, IOR, ROUGHNESS, ParamSpec, preview_transfer

    # the colours' previews are sRGB-encoded, everything else (and maps that are no parameter) linear
    assert [p.name for p in CANONICAL.values() if p.transfer == "srgb"] == ["albedo", "f0"]
    assert preview_transfer("f0") == "srgb" and preview_transfer("coverage") == "linear"
    # roles: Nielsen's stage groups and the energy contract's reflectances
    assert {p.name for p in CANONICAL.values() if p.role in ("diffuse", "specular")} == {"albedo", "f0", "specular"}
    assert {p.name for p in CANONICAL.values() if p.role == "roughness"} == {"roughness", "coat_roughness"}
    assert [p.name for p in CANONICAL.values() if p.shared] == ["coat_ior", "coat_roughness"]
    # thresholds: declared, or 2 % of the range (of 1 for a wider one)
    assert (ALBEDO.threshold, ROUGHNESS.threshold, IOR.threshold) == (0.01, 0.02, 0.05)
    assert ParamSpec("t", 1, 1.0, 3.0, 1.5, "test").threshold == 0.02
    assert ParamSpec("t", 1, 0.0, 0.5, 0.1, "test").threshold == 0.01
    assert replace(ALBEDO, linear=False).prior_unit == 0.3  # a model's variant keeps every fact
    assert (F0.diffuse_only, ROUGHNESS.diffuse_only, ROUGHNESS.plot_value, F0.plot_value) == (0.0, 1.0, 0.4, 0.04)
    for bad, match in (({"role": "coat"}, "role must be one of"), ({"transfer": "gamma"}, "transfer must be one of"),
                       ({"plot": 2.0}, r"plot 2.0 lies outside \[0.0, 1.0\]"),
                       ({"observable_std": 0.0}, "observable_std must be a positive number")):
        with pytest.raises(ValueError, match=match):
            ParamSpec("t", 1, 0.0, 1.0, 0.5, "test", **bad)


def test_the_parameter_table_of_docs_models_md_is_the_generated_one():
    from pathlib import Path

    from materials.params import CANONICAL, markdown_table

    text = (Path(__file__).resolve().parents[2] / "docs" / "models.md").read_text(encoding="utf-8")
    committed = text.split("<!-- begin:parameters -->\n", 1)[1].split("\n<!-- end:parameters -->", 1)[0]
    assert committed == markdown_table(), "docs/models.md is stale: run python scripts/param_table.py"
    rows = committed.splitlines()
    assert len(rows) == 2 + len(CANONICAL) and rows[2].startswith("| `albedo` | 3 | [0, 1] | 0.5 | diffuse")
    assert "| `absorption` | 3 | [0, ∞] |" in committed and "atlas tex2 A (glossiness g) (1)" in committed


def test_the_model_table_of_docs_models_md_is_the_generated_one():
    from pathlib import Path

    import materials
    from materials.model import models_table

    text = (Path(__file__).resolve().parents[2] / "docs" / "models.md").read_text(encoding="utf-8")
    committed = text.split("<!-- begin:models -->\n", 1)[1].split("\n<!-- end:models -->", 1)[0]
    assert committed == models_table(), "docs/models.md is stale: run python scripts/param_table.py"
    rows = committed.splitlines()[2:]
    assert [r.split("`")[1] for r in rows] == list(materials.available())           # every registered model, once
    assert "| `lambert` | Lambertian diffuse ρ/π; the baseline every diffuse model reduces to | albedo |" in rows
