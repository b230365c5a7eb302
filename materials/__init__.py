"""shadecap.materials — what a surface is: BRDF lobes, Fresnel, roughness conversions, material
models and their registry, reference reflectances, atlas export.

Quick start::

    import torch, materials
    print(materials.available())                 # every model name with a one-line description
    model = materials.get("lambert")
    n = torch.tensor([0.0, 0.0, 1.0]); l = v = n
    model(n, l, v, albedo=torch.tensor([0.8, 0.5, 0.2]))   # f_r in 1/sr

Conventions: DESIGN.md and docs/conventions.md. This package depends on torch only.
"""

from . import roughness
from .environment import Environment, HemisphereLight, SHLight, sh_basis
from .geometry import Angles, dot, safe_normalize
from .model import KnownParams, Model, SumModel, available, get, register
from .params import CANONICAL, ParamSpec

# Model families: importing them registers their models.
from . import lambert  # noqa: E402,F401  isort: skip
from . import fresnel  # noqa: E402,F401  isort: skip
from . import microfacet  # noqa: E402,F401  isort: skip
from . import blinn_phong  # noqa: E402,F401  isort: skip
from . import nielsen  # noqa: E402,F401  isort: skip
from . import schuler  # noqa: E402,F401  isort: skip
from . import oren_nayar  # noqa: E402,F401  isort: skip
from . import microfacet_diffuse  # noqa: E402,F401  isort: skip
from . import layered  # noqa: E402,F401  isort: skip
from . import catalog  # noqa: E402,F401  isort: skip
from . import presets  # noqa: E402,F401  isort: skip
from . import measured  # noqa: E402,F401  isort: skip

__all__ = [
    "Angles", "CANONICAL", "Environment", "HemisphereLight", "KnownParams", "Model", "ParamSpec", "SHLight",
    "SumModel", "available", "dot", "get", "register", "roughness", "safe_normalize", "sh_basis",
]
