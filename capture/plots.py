"""Figures for the docs: lobe plots of every model (docs/models.md)."""

from __future__ import annotations

import math
from pathlib import Path

import torch

import materials
from materials import Angles

#: Parameters used for the lobe plots: a mid-rough dielectric, unless a model needs others.
PLOT_PARAMS = {"albedo": 0.5, "f0": 0.04, "roughness": 0.4, "specular": 0.2, "ior": 1.5, "mix": 0.5,
               "absorption": 0.05, "coat_ior": 1.5, "coat_roughness": 0.2, "mask": 1.0}


def lobe_in_plane(model, theta_v_deg: float, n: int = 361, params: dict | None = None):
    """π·f_r·(n·l) over light directions in the plane of incidence (θ_l from −90° to 90°, the
    viewer at +θ_v on the other side), green channel. Returns (θ_l in radians, value)."""
    theta_l = torch.linspace(-math.pi / 2, math.pi / 2, n, dtype=torch.float64)
    tv = math.radians(theta_v_deg)
    nl, nv = torch.cos(theta_l), torch.full_like(theta_l, math.cos(tv))
    lv = torch.cos(theta_l + tv)  # l at angle θ_l, v at −θ_v in the same plane → φ difference π for θ_l > 0
    g = Angles.from_cosines(nl, nv, lv)
    vals = dict(PLOT_PARAMS, **(params or {}))
    p = {s.name: torch.full((n, s.channels), float(vals.get(s.name, s.default)), dtype=torch.float64)
         for s in model.params}
    f = model.cosine_brdf(g, p)[..., 1] * math.pi
    return theta_l, f


def plot_lobes(out_png: str | Path, names: list[str] | None = None, views=(0.0, 45.0, 75.0)) -> Path:
    """One polar panel per model: π f_r cos θ_l in the plane of incidence for three view angles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = names or [k for k in materials.available() if k != "measured"]
    cols = 5
    rows = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(rows, cols, subplot_kw={"projection": "polar"}, figsize=(3.0 * cols, 3.0 * rows))
    for ax, name in zip(axes.flat, names, strict=False):
        model = materials.get(name)
        for tv, colour in zip(views, ("tab:blue", "tab:orange", "tab:red"), strict=True):
            th, f = lobe_in_plane(model, tv)
            ax.plot(th.numpy(), f.clamp_min(0).numpy(), color=colour, lw=1.2, label=f"θv={tv:.0f}°")
        ax.set_theta_zero_location("N")
        ax.set_thetamin(-90)
        ax.set_thetamax(90)
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=6)
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=6, loc="lower left")
    fig.suptitle("π·f_r·cos θ_l in the plane of incidence (viewer on the right at θv, mirror direction on the left); "
                 "albedo 0.5, f0 0.04, r 0.4",
                 fontsize=10)
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_png.with_name(f".{out_png.stem}.tmp.png")
    fig.savefig(tmp, dpi=70)
    plt.close(fig)
    tmp.replace(out_png)
    return out_png
