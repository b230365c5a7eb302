"""Measured materials: a torch decoder for the NBRDF neural fits of the MERL BRDFs.

Data and attribution
--------------------
The weights are the "NBRDF" networks of A. Sztrajman, G. Rainer, T. Ritschel, T. Weyrich, *Neural BRDF
Representation and Importance Sampling*, Computer Graphics Forum 40(6), 2021 (``asztr/Neural-BRDF``,
``data/merl_nbrdf.zip``), one small MLP per material fitted to the MERL measured isotropic BRDFs of
W. Matusik, H. Pfister, M. Brand, L. McMillan, *A Data-Driven Reflectance Model*, ACM TOG 22(3), 2003
(MERL data: CC-BY-SA-4.0, "Created by Mitsubishi Electric Research Laboratories (MERL), 2003, 2007, 2023").
Results computed from them are "NBRDF fits of MERL", never "MERL". The weights are not part of this
repository: they are read from ``$SHADECAP_NBRDF_DIR`` or, by default, ``<checkout>/../shared/data/merl/nbrdf``
(see that folder's README.md). This module is our own code, written from the README's description of the
network; none of the Neural-BRDF code is used.

The network (README, "How to decode an NBRDF")
-----------------------------------------------
``x(6) -> Dense(21, relu) -> Dense(21, relu) -> Dense(3, linear) -> exp(y) - 1``, with the input the
Rusinkiewicz half/difference vectors at φ_h = 0:
``x = [sin θ_h, 0, cos θ_h, sin θ_d cos φ_d, sin θ_d sin φ_d, cos θ_d]``. The output is linear RGB f_r in 1/sr,
already in MERL's scaled units (the 1/1500, 1.15/1500, 1.66/1500 factors were applied before training), without
the cosine. The only transform to undo is the final ``exp(y) − 1``, which is part of :meth:`NBRDF.forward`.

From our cosines to the network's angles (isotropic)
----------------------------------------------------
MERL is isotropic, so every model here is a function of :class:`~materials.geometry.Angles`. The difference
vector d is l expressed in the frame where h is the pole (rotate by −φ_h about n, then by −θ_h about the
bitangent), so with h = (sin θ_h, 0, cos θ_h)::

    n·l = cos θ_h cos θ_d − sin θ_h sin θ_d cos φ_d
    n·v = cos θ_h cos θ_d + sin θ_h sin θ_d cos φ_d        (v = 2 (l·h) h − l)

hence cos θ_h = n·h, cos θ_d = l·h and ``sin θ_d cos φ_d = (n·v − n·l) / (2 sin θ_h)``. The five cosines fix
cos φ_d but not the sign of sin φ_d: (φ_d, −φ_d) are mirror images about the plane of n and h and are equal for
an isotropic material. We take sin φ_d ≥ 0, i.e. φ_d ∈ [0, π] — the half-range MERL tabulates (its 180 φ_d bins
cover [0, π)). At θ_h = 0 or θ_d = 0, φ_d is undefined; we use cos φ_d = 0 (φ_d = π/2), the value
``reference_values.json`` uses at θ_h = 0. Physically φ_d is irrelevant at θ_h = 0, but the network is not
φ_d-invariant there: over φ_d ∈ [0, π] at θ_h = 0 its value spreads by 2-13 % at θ_d = 0.3 and 9-47 % at
θ_d = 1.4 (six reference materials). In float32, 1 − (n·h)² underflows for θ_h ≲ 3e-4 rad, φ_d is then lost and
the value can jump by that spread; float64 cosines resolve it.
Swapping l and v maps φ_d → π − φ_d, so reciprocity of this decoder is exactly the network's symmetry
f(φ_d) = f(π − φ_d), which the network does not enforce: measured over the
front-facing domain it holds to a median relative difference of 1-4 % (90th percentile 5-23 %, worst for chrome
and blue-metallic-paint). ``symmetric=True`` averages the two, making the decoder exactly reciprocal at twice
the cost; the default evaluates the network as fitted.

Domain: what is trusted and what is masked
------------------------------------------
MERL measured only configurations with both directions above the surface (negative table entries mark the rest,
and NBRDF training dropped them). So :meth:`MeasuredBRDF.brdf` returns exactly 0 where n·l ≤ 0 or n·v ≤ 0 (as
every lobe does), and also where θ_i or θ_o exceeds ``max_theta_deg`` (default 90°: no extra mask). Near grazing
(θ > 80°) MERL's data is sparse and noisy and the NBRDF training loss (cos θ_i-weighted log error) barely
constrains it; Ngan et al. 2005 excluded those angles. The values there are returned (Nielsen's point is the
grazing behaviour) but :func:`trusted_mask` flags them, and the fitter reports errors with and without them.
The network output exp(y) − 1 can be negative in principle (≥ −1); over 200 000 random front-facing
configurations none of the six reference materials produced a negative value. ``brdf`` clamps at 0 anyway
(the gradient is 0 there), and :meth:`MeasuredBRDF.raw` returns the unclamped, unmasked network.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import Tensor

from .geometry import Angles
from .model import Model, register

#: Environment variable naming the folder with ``merl_nbrdf_weights.npz`` (and the ``*.h5`` files).
ENV_DIR = "SHADECAP_NBRDF_DIR"
#: Default data folder: the shared data next to the checkout.
DEFAULT_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "merl" / "nbrdf"
#: File with all 100 materials (README: keys ``<material>.W0 (6,21)``, ``.b0``, ``.W1``, ``.b1``, ``.W2``, ``.b2``).
NPZ_NAME = "merl_nbrdf_weights.npz"
#: Angle beyond which MERL's measurement is unreliable (Ngan et al. 2005 exclude it; Nielsen's "grazing").
GRAZING_DEG = 80.0

_KEYS = ("W0", "b0", "W1", "b1", "W2", "b2")
_SHAPES = {"W0": (6, 21), "b0": (21,), "W1": (21, 21), "b1": (21,), "W2": (21, 3), "b2": (3,)}
_H5_KEYS = {
    "W0": "dense_1/dense_1/kernel:0", "b0": "dense_1/dense_1/bias:0",
    "W1": "dense_2/dense_2/kernel:0", "b1": "dense_2/dense_2/bias:0",
    "W2": "dense_3/dense_3/kernel:0", "b2": "dense_3/dense_3/bias:0",
}
_SIN_EPS = 1e-10  # sin² below which θ_h or θ_d counts as 0 (φ_d undefined)


def data_dir() -> Path:
    """The folder the weights are read from: ``$SHADECAP_NBRDF_DIR`` or :data:`DEFAULT_DIR`."""
    return Path(os.environ.get(ENV_DIR, DEFAULT_DIR))


def _check_weights(w: Mapping[str, Tensor], source: str) -> dict[str, Tensor]:
    out = {}
    for k in _KEYS:
        if k not in w:
            raise ValueError(f"{source}: missing weight '{k}' (need {list(_KEYS)})")
        t = torch.as_tensor(w[k]).to(torch.float64)
        if tuple(t.shape) != _SHAPES[k]:
            raise ValueError(f"{source}: weight '{k}' has shape {tuple(t.shape)}, expected {_SHAPES[k]}")
        if not torch.isfinite(t).all():
            raise ValueError(f"{source}: weight '{k}' contains NaN or inf")
        out[k] = t
    return out


@functools.lru_cache(maxsize=8)
def _load_cached(path: str) -> dict[str, dict[str, Tensor]]:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(
            f"NBRDF weights not found: {p}. Put merl_nbrdf_weights.npz there or set ${ENV_DIR} to the folder "
            f"holding it (see shared/data/merl/README.md)"
        )
    if p.suffix == ".npz":
        import numpy as np

        try:
            with np.load(p) as z:
                raw = {k: z[k] for k in z.files}
        except Exception as exc:  # truncated / not a zip
            raise ValueError(f"{p}: cannot read as .npz ({exc})") from None
        names = sorted({k.rsplit(".", 1)[0] for k in raw})
        return {m: _check_weights({k: raw[f"{m}.{k}"] for k in _KEYS if f"{m}.{k}" in raw}, f"{p}[{m}]")
                for m in names}
    if p.suffix in (".h5", ".hdf5"):
        import h5py

        try:
            with h5py.File(p, "r") as f:
                raw = {k: f[v][()] for k, v in _H5_KEYS.items() if v in f}
        except OSError as exc:
            raise ValueError(f"{p}: cannot read as HDF5 ({exc})") from None
        return {p.stem: _check_weights(raw, str(p))}
    raise ValueError(f"{p}: unknown weight file type '{p.suffix}'; expected .npz (all materials) or .h5 (Keras)")


def load_weights(path: str | os.PathLike | None = None) -> dict[str, dict[str, Tensor]]:
    """Read NBRDF weights: ``{material: {"W0": [6,21], "b0": [21], "W1": [21,21], "b1": [21], "W2": [21,3],
    "b2": [3]}}`` as float64 tensors.

    Args:
        path: an ``.npz`` holding ``<material>.<key>`` arrays (all materials), or a Keras ``.h5`` weight file
            (layout ``dense_{1,2,3}/dense_{1,2,3}/{kernel,bias}:0``; the material is the file stem). Default:
            ``data_dir()/merl_nbrdf_weights.npz``. Files are cached per process.
    Raises:
        FileNotFoundError: the file does not exist (the message says where to put it).
        ValueError: unreadable file, missing key, wrong shape, NaN.
    """
    p = Path(path) if path is not None else data_dir() / NPZ_NAME
    return _load_cached(str(p.resolve()))


def available_materials(path: str | os.PathLike | None = None) -> list[str]:
    """Sorted material names in the weight file (100 for the default file)."""
    return sorted(load_weights(path))


class NBRDF:
    """One material's network, ``x [..., 6] -> f_r [..., 3]`` (1/sr, linear RGB, no cosine).

    Holds float64 master weights and caches a copy per (device, dtype) on first use, so it works on any
    device in the caller's precision. Differentiable in x.
    """

    def __init__(self, weights: Mapping[str, Tensor], name: str = ""):
        self.name = name
        self._w = _check_weights(weights, f"NBRDF '{name}'")
        self._cache: dict[tuple, dict[str, Tensor]] = {}

    def weights(self, device, dtype) -> dict[str, Tensor]:
        key = (torch.device(device), dtype)
        if key not in self._cache:
            self._cache[key] = {k: v.to(device=device, dtype=dtype) for k, v in self._w.items()}
        return self._cache[key]

    def forward(self, x: Tensor) -> Tensor:
        """``exp(W2ᵀ relu(W1ᵀ relu(W0ᵀ x + b0) + b1) + b2) − 1``; x ``[..., 6]`` → ``[..., 3]`` (may be < 0)."""
        if not isinstance(x, Tensor) or x.shape[-1] != 6:
            raise ValueError(f"NBRDF.forward: x must be a tensor [..., 6], got {getattr(x, 'shape', type(x))}")
        w = self.weights(x.device, x.dtype)
        h = torch.relu(x @ w["W0"] + w["b0"])
        h = torch.relu(h @ w["W1"] + w["b1"])
        return torch.expm1(h @ w["W2"] + w["b2"])

    __call__ = forward


def _guarded_sqrt(x: Tensor, eps: float = _SIN_EPS) -> tuple[Tensor, Tensor]:
    """``(sqrt(x) where x > eps else 0, ok)`` with a finite gradient everywhere (double where)."""
    ok = x > eps
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x)), ok


def nbrdf_input(theta_h: Tensor, theta_d: Tensor, phi_d: Tensor) -> Tensor:
    """Network input ``[..., 6]`` from Rusinkiewicz angles in radians (each ``[...]``), φ_h = 0 (README)."""
    th, td, pd = torch.broadcast_tensors(*(torch.as_tensor(a) for a in (theta_h, theta_d, phi_d)))
    return torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th),
                        torch.sin(td) * torch.cos(pd), torch.sin(td) * torch.sin(pd), torch.cos(td)], dim=-1)


def nbrdf_input_from_angles(g: Angles, mirror: bool = False) -> Tensor:
    """Network input ``[..., 6]`` from our isotropic cosines, with φ_d ∈ [0, π] (module docstring).

    ``cos θ_h = n·h``, ``cos θ_d = l·h``, ``sin θ_d cos φ_d = (n·v − n·l)/(2 sin θ_h)`` (0 where θ_h = 0),
    ``sin θ_d sin φ_d = +sqrt(sin²θ_d − (sin θ_d cos φ_d)²)``. ``mirror=True`` gives φ_d → π − φ_d (l ↔ v).
    Only meaningful where ``g.front``; elsewhere the result is finite but arbitrary. Gradients are finite
    everywhere (guarded square roots and divisions).
    """
    nh = g.nh.clamp(0.0, 1.0)
    lh = g.lh.clamp(0.0, 1.0)
    sin_h, ok_h = _guarded_sqrt(1.0 - nh * nh)
    sin_d, _ = _guarded_sqrt(1.0 - lh * lh)
    diff = g.nv - g.nl
    dx = torch.where(ok_h, diff / (2.0 * torch.where(ok_h, sin_h, torch.ones_like(sin_h))), torch.zeros_like(diff))
    dx = torch.maximum(torch.minimum(dx, sin_d), -sin_d)
    if mirror:
        dx = -dx
    dy, _ = _guarded_sqrt(sin_d * sin_d - dx * dx, eps=1e-14)
    return torch.cat([sin_h, torch.zeros_like(sin_h), nh, dx, dy, lh], dim=-1)


def trusted_mask(g: Angles, max_theta_deg: float = GRAZING_DEG) -> Tensor:
    """Boolean ``[..., 1]``: front-facing and both θ_i, θ_o ≤ ``max_theta_deg`` (the well-measured domain)."""
    c = math.cos(math.radians(max_theta_deg))
    return g.front & (g.nl >= c) & (g.nv >= c)


@functools.lru_cache(maxsize=256)
def _network(material: str, path: str) -> NBRDF:
    table = _load_cached(path)
    if material not in table:
        raise ValueError(
            f"unknown measured material '{material}'. Available ({len(table)}): {', '.join(sorted(table))}"
        )
    return NBRDF(table[material], name=material)


@register("measured", "NBRDF fit of a MERL measured isotropic BRDF (option material=NAME; data in shared/)")
class MeasuredBRDF(Model):
    """A measured material: the NBRDF fit of one MERL BRDF, evaluated by :class:`NBRDF`. No parameters.

    Options:
        material: MERL name (e.g. ``"nickel"``, ``"red-fabric2"``); :func:`available_materials` lists them and an
            unknown name raises ``ValueError`` listing them. Default ``"nickel"``.
        max_theta_deg: return 0 where θ_i or θ_o exceeds it (default 90: only the horizon is masked; 80 drops
            MERL's unreliable grazing angles).
        symmetric: average the network at φ_d and π − φ_d, making the decoder exactly reciprocal (2× cost).
        path: weight file (``.npz`` or ``.h5``); default ``data_dir()/merl_nbrdf_weights.npz``.

    ``brdf`` returns f_r in 1/sr, ``[..., 3]`` linear RGB, no cosine, clamped ≥ 0; exactly 0 outside the
    measured domain (n·l ≤ 0 or n·v ≤ 0) and beyond ``max_theta_deg``. Differentiable in the cosines.
    """

    params = ()

    def __init__(self, material: str = "nickel", max_theta_deg: float = 90.0, symmetric: bool = False,
                 path: str | None = None):
        if not isinstance(material, str):
            raise TypeError(f"measured: material must be a name (str), got {type(material).__name__}")
        if not (0.0 < float(max_theta_deg) <= 90.0):
            raise ValueError(f"measured: max_theta_deg must be in (0, 90], got {max_theta_deg}")
        p = Path(path) if path is not None else data_dir() / NPZ_NAME
        self.network = _network(material, str(p.resolve()))
        self.material = material
        self.max_theta_deg = float(max_theta_deg)
        self.symmetric = bool(symmetric)
        self.description = f"NBRDF fit of MERL '{material}'"

    def raw(self, g: Angles) -> Tensor:
        """The network output ``[..., 3]`` at φ_d ∈ [0, π] (or the symmetric mean), unmasked and unclamped."""
        out = self.network(nbrdf_input_from_angles(g))
        if self.symmetric:
            out = 0.5 * (out + self.network(nbrdf_input_from_angles(g, mirror=True)))
        return out

    def domain(self, g: Angles) -> Tensor:
        """Boolean ``[..., 1]``: where :meth:`brdf` returns the network (front-facing, θ ≤ ``max_theta_deg``)."""
        if self.max_theta_deg >= 90.0:
            return g.front
        return trusted_mask(g, self.max_theta_deg)

    def brdf(self, g: Angles, p: Mapping[str, Tensor] | None = None) -> Tensor:
        if not isinstance(g, Angles):
            raise TypeError(f"model '{self.name}': brdf takes an Angles, got {type(g).__name__}")
        val = self.raw(g).clamp_min(0.0)
        return torch.where(self.domain(g), val, torch.zeros_like(val))
