"""Benchmarks of the models: throughput, and the error of each approximation the papers propose against the exact
form it replaces, with its cost.

``scripts/benchmark.py models`` runs :func:`run_models_benchmark`, ``scripts/benchmark.py approximations``
:func:`run_approximation_benchmark`; with ``--out`` the tables go into the generated sections of
``docs/benchmarks.md``. Timings state the machine they were taken on (:func:`capture.bench.timing.machine_description`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch

import materials
from materials import Angles
from materials.model import Model

from .timing import machine_description


def random_front_angles(n: int, dtype=torch.float32, device="cpu", seed: int = 0) -> Angles:
    """``n`` random configurations with light and viewer in the upper hemisphere (cosine-weighted)."""
    gen = torch.Generator().manual_seed(seed)

    def hemi():
        u1, u2 = torch.rand(n, generator=gen, dtype=torch.float64), torch.rand(n, generator=gen, dtype=torch.float64)
        r, phi = torch.sqrt(u1), 2 * math.pi * u2
        return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1 - u1).clamp_min(1e-6))], -1)

    nrm = torch.zeros(n, 3, dtype=torch.float64)
    nrm[:, 2] = 1
    return Angles.from_vectors(nrm, hemi(), hemi()).to(device=device, dtype=dtype)


def random_params(model: Model, n: int, dtype=torch.float32, device="cpu", seed: int = 1) -> dict[str, torch.Tensor]:
    """Per-sample parameters uniform over each parameter's range (capped at 1 for unbounded ones)."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for s in model.params:
        hi = min(s.high, max(1.0, s.low + 1.0))
        out[s.name] = (s.low + (hi - s.low) * torch.rand(n, s.channels, generator=gen)).to(device=device, dtype=dtype)
    return out


@dataclass
class Throughput:
    model: str
    device: str
    samples: int
    forward_per_s: float
    forward_backward_per_s: float
    compiled: bool = False
    #: the fit's per-sample Jacobian (value and every derivative, per colour channel): None when not timed
    jacobian_per_s: float | None = None
    #: whether that Jacobian was the model's closed form (else one forward and three backward passes)
    jacobian_closed_form: bool | None = None


def _time(fn: Callable[[], None], repeats: int, device: str) -> float:
    fn()  # warm-up
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best


def model_throughput(
    model: Model, n: int = 1 << 20, device: str = "cpu", repeats: int = 3, compile: bool = False
) -> Throughput:
    """Samples per second of ``model.cosine_brdf`` forward, forward + backward to every parameter, and — eager
    only — the per-sample Jacobian the fit takes: the model's closed form
    (:meth:`materials.Model.cosine_brdf_jacobian`) where it has one, else one forward and one backward pass per
    colour channel (``jacobian_closed_form`` says which; not timed for a model without parameters).

    Geometry (the Angles) is precomputed, as in the pipeline; the parameters are per-sample
    tensors, as sampled from maps. ``compile=True`` wraps the evaluation in ``torch.compile``.
    """
    g = random_front_angles(n, device=device)
    p = random_params(model, n, device=device)

    def evaluate(nl, nv, nh, lh, lv, *vals):
        return model.cosine_brdf(Angles(nl, nv, nh, lh, lv), dict(zip(p.keys(), vals, strict=True)))

    fn = torch.compile(evaluate, dynamic=False) if compile else evaluate
    geo = (g.nl, g.nv, g.nh, g.lh, g.lv)

    def fwd():
        with torch.no_grad():
            fn(*geo, *p.values())

    leaves = [x.detach().clone().requires_grad_() for x in p.values()]
    # A model without parameters (the measured NBRDF) is differentiated with respect to the geometry.
    geo_b = geo if leaves else tuple(x.detach().clone().requires_grad_() for x in geo)

    def fwd_bwd():
        out = fn(*geo_b, *leaves)
        out.sum().backward()

    t_f = _time(fwd, repeats, device)
    t_fb = _time(fwd_bwd, repeats, device)
    if compile or not leaves:
        return Throughput(model.name, device, n, n / t_f, n / t_fb, compile)
    with torch.no_grad():
        closed = model.cosine_brdf_jacobian(g, p) is not None

    def jacobian():
        if closed:
            with torch.no_grad():
                model.cosine_brdf_jacobian(g, p)
            return
        out = fn(*geo, *leaves)
        for c in range(3):
            torch.autograd.grad(out[..., c].sum(), leaves, retain_graph=c < 2, allow_unused=True)

    t_j = _time(jacobian, repeats, device)
    return Throughput(model.name, device, n, n / t_f, n / t_fb, compile, n / t_j, closed)


def benchmark_models(
    names: list[str] | None = None, n: int = 1 << 20, device: str = "cpu", compile_names: tuple[str, ...] = ()
) -> list[dict]:
    """Throughput of every registered model (or ``names``); those in ``compile_names`` also compiled."""
    rows = []
    for name in names or list(materials.available()):
        model = materials.get(name)
        rows.append(asdict(model_throughput(model, n=n, device=device)))
        if name in compile_names:
            rows.append(asdict(model_throughput(model, n=n, device=device, compile=True)))
    return rows


#: Models timed under torch.compile by default: the ones reconstruction uses most.
COMMON_MODELS = ("lambert", "ggx-lambert", "gotanda2012")


def run_models_benchmark(n: int = 1 << 20, device: str = "cpu", compile_names=None, out: str | None = None) -> str:
    """Throughput table of every model (markdown); written into ``out``'s ``models-throughput`` section."""
    from pathlib import Path

    from ..report import replace_section

    names = list(materials.available())
    compile_names = tuple(c for c in (COMMON_MODELS if compile_names is None else compile_names) if c in names)
    rows = benchmark_models(names, n=n, device=device, compile_names=compile_names)
    lines = [
        f"Machine: {machine_description(device)}; device `{device}`; {n} samples per call, best of 3.",
        "",
        "The Jacobian column is the fit's per-sample Jacobian (value and every derivative, per colour channel): the "
        "model's closed form where it has one (`cosine_brdf_jacobian`), else one forward and three backward passes.",
        "",
        "| model | mode | forward (M samples/s) | forward+backward (M samples/s) | Jacobian (M samples/s) |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        mode = "torch.compile" if r["compiled"] else "eager"
        fwd, fwd_bwd = r["forward_per_s"] / 1e6, r["forward_backward_per_s"] / 1e6
        jac = "–" if r["jacobian_per_s"] is None else \
            f"{r['jacobian_per_s'] / 1e6:.1f} ({'closed form' if r['jacobian_closed_form'] else 'autograd'})"
        lines.append(f"| `{r['model']}` | {mode} | {fwd:.1f} | {fwd_bwd:.1f} | {jac} |")
    table = "\n".join(lines)
    if out:
        replace_section(Path(out), "models-throughput", "## Model throughput\n\n" + table)
    return table


# -- approximations against the exact forms they replace ---------------------------------------

#: (label, approximate model, reference model, fixed parameters). Errors are in π·f_r·cos units
#: (a Lambertian surface of albedo ρ reads ρ), over :func:`comparison_grid`.
APPROXIMATIONS: tuple[tuple[str, tuple, tuple, dict], ...] = (
    ("Fresnel: Schlick vs exact (GGX specular)", ("microfacet", {"F": "schlick"}),
     ("microfacet", {"F": "exact"}), {}),
    ("Fresnel: spherical Gaussian (2014 eq 3) vs exact", ("microfacet", {"F": "sg"}),
     ("microfacet", {"F": "exact"}), {}),
    ("Fresnel: Schüler lerp vs exact", ("microfacet", {"F": "schuler"}), ("microfacet", {"F": "exact"}), {}),
    ("Absorption: linear (2012 eq 3) vs exact (eq 2)", ("gotanda2012-layered", {"absorption": "linear"}),
     ("gotanda2012-layered", {"absorption": "exact"}), {"absorption": 0.05, "coat_ior": 1.5}),
    ("Bottom Fresnel: constant (eq 5) vs exact (eq 4)", ("gotanda2012-layered", {"bottom_fresnel": "constant"}),
     ("gotanda2012-layered", {"bottom_fresnel": "exact"}), {"absorption": 0.0, "coat_ior": 1.5}),
    ("Oren-Nayar: qualitative (eq 10/11) vs full 1994", ("oren-nayar-qualitative", {}), ("oren-nayar", {}), {}),
    ("Oren-Nayar: Gotanda simplified (eq 20) vs full", ("gotanda-on-simplified", {}), ("oren-nayar", {}), {}),
    ("Oren-Nayar: Gotanda improved (eq 25) vs full", ("gotanda-on-improved", {}), ("oren-nayar", {}), {}),
    ("Oren-Nayar: Gotanda 2014 (eq 5) vs full", ("gotanda2014-on", {}), ("oren-nayar", {}), {}),
    ("Microfacet diffuse: fitted (2014 eq 8) vs numerical (eq 4)", ("microfacet-diffuse", {"method": "fitted"}),
     ("microfacet-diffuse", {"method": "numerical"}), {}),
    ("Schüler: optimized vs CookTorranceFull", ("schuler", {"variant": "optimized"}),
     ("schuler", {"variant": "cook-torrance-full"}), {}),
    ("Schüler: CookTorranceSimplified vs CookTorranceFull", ("schuler", {"variant": "cook-torrance-simplified"}),
     ("schuler", {"variant": "cook-torrance-full"}), {}),
    ("Schüler: KelemenSzirmayKalos vs CookTorranceFull", ("schuler", {"variant": "kelemen-szirmay-kalos"}),
     ("schuler", {"variant": "cook-torrance-full"}), {}),
    ("Blinn-Phong (Gotanda 2010) vs GGX + Lambert", ("gotanda2010", {}), ("ggx-lambert", {}), {}),
    ("Blinn-Phong normalisation: linear fit vs exact", ("gotanda2010", {}),
     ("gotanda2010", {"normalization": "exact"}), {}),
)


def comparison_grid(dtype=torch.float64, n_cos: int = 12, n_phi: int = 7, roughness=(0.3, 0.5, 0.7, 0.9)):
    """Dense grid: n·l, n·v ∈ (0, 1] (uniform in angle up to 85°), azimuth difference ∈ [0, π],
    roughness values; returns (Angles [M,1], roughness [M,1], labels (θ_l°, θ_v°, φ°, r) [M,4])."""
    th = torch.linspace(0.0, math.radians(85.0), n_cos, dtype=dtype)
    ph = torch.linspace(0.0, math.pi, n_phi, dtype=dtype)
    r = torch.tensor(roughness, dtype=dtype)
    tl, tv, pp, rr = (x.reshape(-1, 1) for x in torch.meshgrid(th, th, ph, r, indexing="ij"))
    nl, nv = torch.cos(tl), torch.cos(tv)
    lv = nl * nv + torch.sin(tl) * torch.sin(tv) * torch.cos(pp)
    labels = torch.cat([torch.rad2deg(tl), torch.rad2deg(tv), torch.rad2deg(pp), rr], -1)
    return Angles.from_cosines(nl, nv, lv), rr, labels


def _grid_params(model: Model, roughness: torch.Tensor, fixed: dict) -> dict:
    base = {"albedo": 0.8, "f0": 0.04, "specular": 0.2, "ior": 1.5, "mix": 0.5, "coat_roughness": 0.2}
    base.update(fixed)
    m = roughness.shape[0]
    out = {}
    for s in model.params:
        if s.name == "roughness":
            out[s.name] = roughness.expand(m, s.channels)
        else:
            out[s.name] = torch.full((m, s.channels), float(base.get(s.name, s.default)), dtype=roughness.dtype)
    return out


def approximation_errors(labels_only: tuple[str, ...] | None = None, n_cost: int = 1 << 18) -> list[dict]:
    """For each entry of :data:`APPROXIMATIONS`: mean and max |π f cos| error over the grid, where the
    max occurs, and the cost (forward, forward+backward samples/s) of the approximation and the reference."""
    g, rough, labels = comparison_grid()
    rows = []
    cost_cache: dict[str, Throughput] = {}
    for label, (an, ao), (rn, ro), fixed in APPROXIMATIONS:
        if labels_only and label not in labels_only:
            continue
        approx, ref = materials.get(an, **ao), materials.get(rn, **ro)
        with torch.no_grad():
            fa = approx.cosine_brdf(g, _grid_params(approx, rough, fixed))[..., 1] * math.pi
            fr = ref.cosine_brdf(g, _grid_params(ref, rough, fixed))[..., 1] * math.pi
        err = (fa - fr).abs()
        k = int(err.argmax())
        costs = []
        for m in (approx, ref):
            if m.name not in cost_cache:
                n = n_cost if "numerical" not in m.name else 1 << 11
                cost_cache[m.name] = model_throughput(m, n=n, repeats=2)
            costs.append(cost_cache[m.name])
        tl, tv, ph, r = labels[k].tolist()
        rows.append({
            "label": label, "approx": approx.name, "reference": ref.name,
            "mean_error": float(err.mean()), "max_error": float(err.max()),
            "ref_mean": float(fr.abs().mean()),
            "worst_at": f"θl={tl:.0f}°, θv={tv:.0f}°, φ={ph:.0f}°, r={r:.1f}",
            "approx_fwd": costs[0].forward_per_s, "approx_fb": costs[0].forward_backward_per_s,
            "ref_fwd": costs[1].forward_per_s, "ref_fb": costs[1].forward_backward_per_s,
        })
    return rows


def plot_pareto(rows: list[dict], out_png) -> None:
    """Cost (forward+backward samples/s) against mean error, one arrow from each reference to its
    approximation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    fig, ax = plt.subplots(figsize=(9, 6))
    for i, r in enumerate(rows):
        c = plt.cm.tab20(i % 20)
        ax.scatter([r["approx_fb"] / 1e6], [max(r["mean_error"], 1e-7)], color=c, s=30, zorder=3)
        ax.scatter([r["ref_fb"] / 1e6], [1e-7], color=c, marker="x", s=30, zorder=3)
        ax.annotate("", xy=(r["approx_fb"] / 1e6, max(r["mean_error"], 1e-7)), xytext=(r["ref_fb"] / 1e6, 1e-7),
                    arrowprops={"arrowstyle": "->", "color": c, "lw": 0.8})
        ax.annotate(r["label"], (r["approx_fb"] / 1e6, max(r["mean_error"], 1e-7)), fontsize=6, color=c,
                    xytext=(3, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward+backward throughput, M samples/s (CPU, eager)")
    ax.set_ylabel("mean |π f cos| error vs the exact form (x: reference, at 1e-7)")
    ax.set_title("Approximations of the papers: cost against error")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, out_png, dpi=80)


def run_approximation_benchmark(out: str | None = None, figure: str | None = None) -> str:
    """Table (markdown) of :func:`approximation_errors`; with ``out``/``figure`` also written to docs."""
    from pathlib import Path

    from ..report import replace_section

    rows = approximation_errors()
    lines = [
        f"Machine: {machine_description()}. Errors in π·f_r·cos θ_l (a Lambertian surface of albedo ρ reads ρ) "
        "over θ_l, θ_v ∈ [0°, 85°] (12 each), φ ∈ [0°, 180°] (7), roughness ∈ {0.3, 0.5, 0.7, 0.9}; albedo 0.8, "
        "f0 0.04. Cost: eager CPU throughput, M samples/s.",
        "",
        "| approximation | mean err | max err | worst at | mean of reference | approx fwd / fwd+bwd | "
        "reference fwd / fwd+bwd |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['mean_error']:.2e} | {r['max_error']:.2e} | {r['worst_at']} | {r['ref_mean']:.3f} | "
            f"{r['approx_fwd'] / 1e6:.2f} / {r['approx_fb'] / 1e6:.2f} | "
            f"{r['ref_fwd'] / 1e6:.2f} / {r['ref_fb'] / 1e6:.2f} |"
        )
    table = "\n".join(lines)
    if figure:
        plot_pareto(rows, figure)
        rel = Path(figure).name if out is None else Path(figure).relative_to(Path(out).parent)
        table += f"\n\n![cost against error]({rel})"
    if out:
        replace_section(Path(out), "approximations", "## Approximations: cost against error\n\n" + table)
    return table
