"""Figures for the diffuse model family (docs/models-diffuse.md): in-plane slices of every
Oren-Nayar form (Gotanda 2012 figures 4-6), the microfacet diffuse fit vs its numerical reference
(Gotanda 2014 figures 11-14), and the SH DC scale eq 27/28 vs the eq 26 integral (figures 7-9).

Usage: python scripts/plot_diffuse.py OUT_DIR     (writes PNGs; nothing is committed)
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from capture.plots import save_figure  # noqa: E402
from materials import Angles  # noqa: E402
from materials import microfacet_diffuse as md  # noqa: E402
from materials import oren_nayar as on  # noqa: E402
from materials.validation import hemisphere_quadrature  # noqa: E402

D64 = torch.float64


def _in_plane(theta_e: float, n: int = 181) -> tuple[torch.Tensor, Angles]:
    """Light swept over the plane of incidence: x = signed θ_l (negative = light on the viewer's side)."""
    x = torch.linspace(-89.0, 89.0, n, dtype=D64) * math.pi / 180
    nl = torch.cos(x)[:, None]
    ne = torch.full_like(nl, math.cos(theta_e))
    lv = torch.cos(x + theta_e)[:, None]  # v = (−sin θ_e, 0, cos θ_e), l = (sin x, 0, cos x)
    return x * 180 / math.pi, Angles.from_cosines(nl, ne, lv)


def plot_oren_nayar(out: Path) -> None:
    one = torch.ones(1, dtype=D64)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for ax, te in zip(axes, (0.0, 45.0, 80.0), strict=True):
        x, g = _in_plane(math.radians(te))
        s = torch.tensor([1.0], dtype=D64)
        curves = {
            "Lambert": (g.nl.clamp_min(0) / math.pi).expand(-1, 1),
            "O-N 1994 full": on.oren_nayar_full(g, one, s, cosine=True),
            "O-N 1994 w/o interrefl.": on.oren_nayar_full(g, one, s, False, cosine=True),
            "qualitative eq 10 / eq 20": on.oren_nayar_qualitative(g, one, s, cosine=True),
            "improved eq 24": on.gotanda_on_improved(g, one, 2 / s**2, "eq24", cosine=True),
            "improved eq 25 / 2014 eq 5": on.gotanda_on_improved(g, one, 2 / s**2, "eq25", cosine=True),
            "2014 eq 7 (f0 = 0.04)": on.gotanda2014_on_fresnel(g, one, s, torch.tensor([0.04], dtype=D64),
                                                              cosine=True),
        }
        for k, y in curves.items():
            ax.plot(x, math.pi * y[:, 0], label=k)
        ax.set_title(f"σ = 1, θ_e = {te:.0f}°, in plane (ρ = 1)")
        ax.set_xlabel("signed θ_l (deg); negative = same side as the viewer")
        ax.set_ylabel("π f_r cos θ_l")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "oren_nayar_in_plane.png", dpi=110)


def plot_microfacet(out: Path) -> None:
    one, zero = torch.ones(1, dtype=D64), torch.zeros(1, dtype=D64)
    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    for row, alpha in zip(axes, (0.3, 0.8), strict=True):
        for ax, te in zip(row, (0.0, 45.0, 75.0), strict=True):
            x, g = _in_plane(math.radians(te), n=91)
            a = torch.tensor([alpha], dtype=D64)
            ref = md.microfacet_diffuse_numerical(g, one, a, zero, cosine=True)
            ax.plot(x, math.pi * ref[:, 0], "k--", label="eq 4 numerical")
            for reading in ("paper", "ue4"):
                fit = md.microfacet_diffuse_fitted(g, one, a, zero, reading=reading, cosine=True)
                ax.plot(x, math.pi * fit[:, 0], label=f"eq 8 '{reading}'")
            ax.set_title(f"α = σ = {alpha}, θ_e = {te:.0f}°")
            ax.set_ylim(-0.2, 1.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "microfacet_diffuse_fit.png", dpi=110)


def plot_sh(out: Path) -> None:
    x = torch.linspace(0.0, 1.0, 41, dtype=D64)
    d, w = hemisphere_quadrature(96, 192)
    tv = torch.acos(x)
    v = torch.stack([torch.sin(tv), torch.zeros_like(tv), torch.cos(tv)], -1)[:, None, :]
    g = Angles.from_vectors(torch.tensor([0.0, 0.0, 1.0], dtype=D64), d[None], v)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for sigma in (0.25, 0.5, 1.0):
        s = torch.tensor([2.0 / sigma**2], dtype=D64)
        f = on.gotanda_on_improved(g, torch.ones(1, dtype=D64), s, "eq25", cosine=True)
        axes[0].plot(x, (f[..., 0] * w).sum(-1), label=f"eq 26 of eq 25, σ = {sigma}")
        axes[0].plot(x, on.sh_dc_scale(s, x[:, None], "eq27")[:, 0], "--", label=f"eq 27, σ = {sigma}")
        axes[0].plot(x, on.sh_dc_scale(s, x[:, None], "eq28")[:, 0], ":", label=f"eq 28, σ = {sigma}")
        axes[1].plot(x, on.sh_linear_scale(s, x[:, None])[:, 0], label=f"eq 29 S, σ = {sigma}")
    axes[0].set_xlabel("N·E")
    axes[0].set_title("SH DC scale vs the integral it fits")
    axes[1].set_xlabel("N·E")
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "sh_scales.png", dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="folder for the PNGs (created)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    plot_oren_nayar(args.out)
    plot_microfacet(args.out)
    plot_sh(args.out)
    print(f"wrote {sorted(p.name for p in args.out.glob('*.png'))} to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
