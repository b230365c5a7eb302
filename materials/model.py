"""The Model interface every material implements, and the registry that names them.

A *lobe* is a pure function ``lobe(g: Angles, ...) -> Tensor[..., C]`` returning a BRDF value in
1/sr (no cosine), 0 where ``g.front`` is false. It lives in the file of its model family
(``fresnel.py``, ``oren_nayar.py``, ``microfacet.py`` ...).

A *model* composes lobes into a whole material and declares the parameters it needs, so that the
renderer allocates, samples and the solver optimises only those (DESIGN.md, "skip what a scene
does not need"). Models are registered by name::

    import materials
    model = materials.get("gotanda2014", diffuse="fitted")
    f = model.brdf(materials.Angles.from_vectors(n, l, v), {"albedo": a, "f0": f0, "roughness": r})

Radiometry (DESIGN.md): reflected radiance from one light of irradiance E (perpendicular to its
direction) and visibility V is ``E · V · model.cosine_brdf(g, p)``, where
``cosine_brdf = f_r · (n·l)⁺``.
"""

from __future__ import annotations

import contextvars
import functools
import inspect
from collections.abc import Callable, Collection, Mapping
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .geometry import Angles, check_angles
from .params import ParamSpec, check_params

if TYPE_CHECKING:
    from .environment import Environment

#: How many validated entry points (brdf, cosine_brdf, environment) are running in this context: only the
#: outermost one checks its parameters (a model that calls its parts, its bottom layer or its base model
#: hands them values it derived — e.g. a coat's relative index below 1 — that are not canonical maps).
_ENTRY_DEPTH: contextvars.ContextVar[int] = contextvars.ContextVar("materials_model_entry_depth", default=0)
#: The entry points validated, and the position of their parameter dict after ``self``.
_ENTRY_POINTS = {"brdf": 1, "cosine_brdf": 1, "cosine_brdf_jacobian": 1, "environment": 3}


def _validated(fn: Callable, name: str) -> Callable:
    """Wrap a public entry point of a :class:`Model` so that its outermost call validates the parameters."""
    if getattr(fn, "_validates_params", False):
        return fn
    index = _ENTRY_POINTS[name]

    @functools.wraps(fn)
    def entry(self, *args, **kwargs):
        depth = _ENTRY_DEPTH.get()
        if depth == 0:
            if name != "environment":
                check_angles(args[0] if args else kwargs.get("g"), f"model '{self.name}'.{name}")
            p = args[index] if len(args) > index else kwargs.get("p")
            p = {} if p is None else p  # a model without parameters may be called without a dict
            if not isinstance(p, Mapping):
                raise TypeError(f"model '{self.name}'.{name}: p must be a mapping of parameter name → tensor, "
                                f"got {type(p).__name__}")
            self.check(p)
        token = _ENTRY_DEPTH.set(depth + 1)
        try:
            return fn(self, *args, **kwargs)
        finally:
            _ENTRY_DEPTH.reset(token)

    entry._validates_params = True
    return entry


class Model:
    """Base class of a material model.

    Subclasses set :attr:`params` and implement :meth:`brdf`; they may override
    :meth:`cosine_brdf` when the product with n·l is cheaper or better conditioned than the BRDF
    alone (e.g. Gotanda's 1/max(n·l, n·v)), and :meth:`environment` when their paper defines a
    response to environment lighting.

    Validation. :meth:`brdf`, :meth:`cosine_brdf` and :meth:`environment` (the base class's and every
    subclass's override, wrapped when the subclass is defined) check the parameter dict once, at the
    public entry: names, channels, finiteness and declared ranges (:meth:`check`), raising ``ValueError``
    that names the parameter; ``brdf``/``cosine_brdf`` also check that ``g`` is an :class:`Angles`. Calls
    made from inside a model (its parts, its bottom layer, its base) are not checked again. The check is
    one min/max pass per parameter (a few ms per 10⁶ samples, against tens of ms for the lobes).

    Attributes:
        name: registry name (set by :func:`register`).
        description: one line for :func:`available`.
        params: the parameters this model reads, in canonical form.
    """

    name: str = ""
    description: str = ""
    params: tuple[ParamSpec, ...] = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        for entry in _ENTRY_POINTS:  # as resolved through the MRO: a mixin's method is an entry point too
            fn = getattr(cls, entry)
            if not getattr(fn, "_validates_params", False):
                setattr(cls, entry, _validated(fn, entry))

    # -- to implement -------------------------------------------------------------------------
    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        """BRDF value f_r in 1/sr, shape ``[..., 3]``; 0 where n·l ≤ 0 or n·v ≤ 0.

        Args:
            g: shading cosines, each ``[..., 1]``.
            p: canonical parameters by name, each ``[..., channels]`` broadcastable against ``g``.
        """
        raise NotImplementedError(f"{type(self).__name__}.brdf")

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        """``f_r · max(n·l, 0)``, shape ``[..., 3]``: radiance per unit irradiance (1/sr)."""
        return self.brdf(g, p) * g.nl.clamp_min(0.0)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """:meth:`cosine_brdf` and its derivatives in closed form, or None where the model has none (the default).

        Returns ``(value [..., 3], {name: ∂value/∂p[name]})`` for every parameter of ``p`` the model reads, with
        the derivatives automatic differentiation of :meth:`cosine_brdf` gives, clamps included (0 where a clamp
        holds the parameter). A derivative is ``[..., 3, C]`` (output channel, parameter channel), or ``[..., 3]``
        — the value's shape — for a three-channel parameter each of whose channels acts on its own output
        channel alone (an albedo, an f0): the diagonal, the other entries 0. A solver linearising millions of
        samples takes it instead of one forward and three backward passes (one per colour channel). A subclass
        that changes :meth:`brdf` or :meth:`cosine_brdf` gets None from its parent's closed form
        (:meth:`shades_as`) until it writes its own.
        """
        return None

    def cosine_brdf_jacobian_in(self, g: Angles, p: Mapping[str, Tensor],
                                names: Collection[str]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """:meth:`cosine_brdf_jacobian` with the derivatives in ``names`` alone (the others' values held: a
        :class:`KnownParams` asks its base for the free parameters'). By default the whole closed form, filtered; a
        model whose closed form covers only some parameters (:class:`materials.layered.GotandaLayered`: not the
        coat's) answers here when ``names`` are among them."""
        out = self.cosine_brdf_jacobian(g, p)
        if out is None:
            return None
        return out[0], {name: d for name, d in out[1].items() if name in names}

    def shades_as(self, cls: type) -> bool:
        """Whether this model's :meth:`brdf` and :meth:`cosine_brdf` are those of ``cls``: a closed-form Jacobian
        written for ``cls`` holds for this model only then."""
        t = type(self)
        return t.brdf is cls.brdf and t.cosine_brdf is cls.cosine_brdf

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        """Radiance ``[..., 3]`` reflected toward ``v`` from an environment light ``env``.

        ``n`` and ``v`` are unit vectors ``[..., 3]``. Models whose paper defines an environment
        response override this; the default raises so that no approximation is invented silently.
        """
        raise NotImplementedError(
            f"model '{self.name}' defines no response to {type(env).__name__} lighting; "
            f"use directional/point lights or a model that supports it (see docs/models.md)"
        )

    # -- shared behaviour ---------------------------------------------------------------------
    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.params)

    def spec(self, name: str) -> ParamSpec:
        for s in self.params:
            if s.name == name:
                return s
        raise KeyError(f"model '{self.name}' has no parameter '{name}'; it has {list(self.param_names)}")

    def defaults(self, shape: tuple[int, ...] = (), device=None, dtype=None) -> dict[str, Tensor]:
        """Default value of every parameter, each ``[*shape, channels]``."""
        return {s.name: s.full(shape, device=device, dtype=dtype) for s in self.params}

    def check(self, p: Mapping[str, Tensor]) -> None:
        """Validate a parameter dict (names, channels, ranges) with a message naming the problem."""
        check_params(self.params, p, where=f"model '{self.name}'")

    def __call__(self, n: Tensor, l: Tensor, v: Tensor, **params: Tensor) -> Tensor:
        """Convenience: BRDF from vectors, with defaults for omitted parameters, checked."""
        g = Angles.from_vectors(n, l, v)
        unknown = set(params) - set(self.param_names)
        if unknown:
            raise ValueError(
                f"model '{self.name}' got unknown parameter(s) {sorted(unknown)}; "
                f"it takes {list(self.param_names)}"
            )
        full = self.defaults(device=g.nl.device, dtype=g.nl.dtype)
        full.update({k: torch.as_tensor(x, dtype=g.nl.dtype, device=g.nl.device) for k, x in params.items()})
        full = {k: (x.unsqueeze(-1) if x.dim() == 0 else x) for k, x in full.items()}
        return self.brdf(g, full)  # checked there

    def __repr__(self) -> str:
        return f"<{type(self).__name__} '{self.name}' params={list(self.param_names)}>"


class SumModel(Model):
    """Sum of independent models' BRDFs (e.g. a diffuse lobe plus a specular lobe).

    Parameters are the union of the parts' (by name); a parameter shared by two parts is shared.
    """

    def __init__(self, *parts: Model, name: str = "", description: str = ""):
        if not parts:
            raise ValueError("SumModel needs at least one part")
        self.parts = parts
        self.name = name or "+".join(p.name for p in parts)
        self.description = description
        seen: dict[str, ParamSpec] = {}
        for part in parts:
            for s in part.params:
                seen.setdefault(s.name, s)
        self.params = tuple(seen.values())

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return sum(part.brdf(g, p) for part in self.parts)

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return sum(part.cosine_brdf(g, p) for part in self.parts)

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The parts' closed forms summed (a parameter two parts read gets both derivatives); None unless every
        part has one."""
        if not self.shades_as(SumModel):
            return None
        value, grads = 0.0, {}
        for part in self.parts:
            out = part.cosine_brdf_jacobian(g, p)
            if out is None:
                return None
            value = value + out[0]
            for name, d in out[1].items():
                if name in grads and grads[name].dim() != d.dim():     # a diagonal and a full derivative
                    grads[name], d = _full_derivative(grads[name], value), _full_derivative(d, value)
                grads[name] = grads[name] + d if name in grads else d
        return value, grads


def _full_derivative(d: Tensor, value: Tensor) -> Tensor:
    """A derivative of :meth:`Model.cosine_brdf_jacobian` as ``[..., 3, C]``: a diagonal one (the ``value``'s
    number of dimensions) spread onto its matrix, a full one as it is."""
    return torch.diag_embed(d.expand_as(value)) if d.dim() == value.dim() else d


class KnownParams(Model):
    """A model with some parameters held at known values: it exposes only the others.

    ``params`` are the base model's minus the known ones, so a solver that allocates and fits
    ``model.params`` never allocates, fits or reports the known ones (e.g. the coat's η and
    roughness of :mod:`materials.layered` measured once for a whole object). :meth:`brdf`,
    :meth:`cosine_brdf` and :meth:`environment` pass the known values, broadcast to the batch of
    the free parameters, to the base model. :meth:`full` completes a parameter dict for the base.

    Args:
        base: the model to restrict.
        known: parameter name → value: a number (every channel) or ``[channels]`` values in canonical
            units, inside the parameter's declared range.

    Raises:
        ValueError: a name the base model does not have, a wrong channel count, a value out of
            range or not finite, or every parameter known (nothing left to fit).
    """

    def __init__(self, base: Model, known: Mapping[str, object]):
        if not isinstance(base, Model):
            raise TypeError(f"KnownParams: base must be a materials.Model, got {type(base).__name__}")
        if not known:
            raise ValueError("KnownParams: give at least one known parameter (name → value)")
        values = {}
        for name, val in known.items():
            if name not in base.param_names:
                raise ValueError(f"known parameter '{name}': model '{base.name}' has no such parameter; it has "
                                 f"{list(base.param_names)}")
            spec = base.spec(name)
            try:
                t = torch.as_tensor(val, dtype=torch.float64).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"known parameter '{name}': expected a number or {spec.channels} numbers, "
                                 f"got {val!r}") from None
            if t.numel() == 1:
                t = t.expand(spec.channels)
            if t.numel() != spec.channels:
                raise ValueError(f"known parameter '{name}' has {spec.channels} channel(s), got {t.numel()} values")
            if not bool(torch.isfinite(t).all()) or bool((t < spec.low).any()) or bool((t > spec.high).any()):
                raise ValueError(f"known parameter '{name}' = {t.tolist()} is outside its range "
                                 f"[{spec.low}, {spec.high}] or not finite")
            values[name] = t.clone()
        if len(values) == len(base.params):
            raise ValueError(f"KnownParams: every parameter of '{base.name}' is known; nothing is left to fit")
        self.base = base
        self.known = values
        self.name = base.name
        self.description = base.description
        self.params = tuple(s for s in base.params if s.name not in values)

    def full(self, p: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """``p`` (free parameters, each ``[..., C]``) plus the known values broadcast to their batch."""
        free = [x for x in p.values() if isinstance(x, Tensor)]
        ref = free[0] if free else torch.zeros(1, dtype=torch.float64)
        batch = torch.broadcast_shapes(*(x.shape[:-1] for x in free)) if free else ()
        out = dict(p)
        for k, t in self.known.items():
            out[k] = t.to(dtype=ref.dtype, device=ref.device).expand(*batch, t.numel())
        return out

    def brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self.base.brdf(g, self.full(p))

    def cosine_brdf(self, g: Angles, p: Mapping[str, Tensor]) -> Tensor:
        return self.base.cosine_brdf(g, self.full(p))

    def cosine_brdf_jacobian(self, g: Angles, p: Mapping[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]] | None:
        """The base model's closed form at the completed parameters, the known ones' derivatives left out."""
        if not self.shades_as(KnownParams):
            return None
        return self.base.cosine_brdf_jacobian_in(g, self.full(p), frozenset(p))

    def environment(self, env: Environment, n: Tensor, v: Tensor, p: Mapping[str, Tensor]) -> Tensor:
        return self.base.environment(env, n, v, self.full(p))

    def __repr__(self) -> str:
        known = ", ".join(f"{k}={[round(x, 6) for x in t.tolist()]}" for k, t in self.known.items())
        return f"<KnownParams '{self.name}' params={list(self.param_names)} known: {known}>"


for _entry in _ENTRY_POINTS:  # the base class's own entry points (cosine_brdf = brdf · n·l, environment, …)
    setattr(Model, _entry, _validated(Model.__dict__[_entry], _entry))


# -- registry ---------------------------------------------------------------------------------
_REGISTRY: dict[str, tuple[Callable[..., Model], str]] = {}


def register(name: str, description: str) -> Callable:
    """Decorator: register a Model subclass or a factory ``(**options) -> Model`` under ``name``."""

    def deco(factory):
        if name in _REGISTRY:
            raise ValueError(f"model name '{name}' registered twice")
        _REGISTRY[name] = (factory, description)
        return factory

    return deco


def get(name: str, **options) -> Model:
    """Instantiate the registered model ``name`` with its ``options``.

    Raises:
        ValueError: unknown name (the message lists every available name) or an option the
            model does not take (the message lists the options it takes).
    """
    if name not in _REGISTRY:
        raise ValueError(
            f"unknown model '{name}'. Available models: {', '.join(sorted(_REGISTRY))} "
            f"(materials.available() describes each)"
        )
    factory, description = _REGISTRY[name]
    try:
        inspect.signature(factory).bind(**options)
    except TypeError as exc:
        sig = inspect.signature(factory)
        raise ValueError(f"model '{name}' does not take options {sorted(options)}: {exc}; signature {sig}") from None
    model = factory(**options)
    model.name = name if not options else f"{name}({', '.join(f'{k}={v}' for k, v in sorted(options.items()))})"
    model.description = model.description or description
    return model


def available() -> dict[str, str]:
    """Registered model names with their one-line descriptions, sorted by name."""
    return {k: _REGISTRY[k][1] for k in sorted(_REGISTRY)}


def models_table() -> str:
    """The markdown table of every registered model — name, description, parameters — as ``docs/models.md`` holds it
    (``scripts/param_table.py`` writes it). A model whose data is missing on this machine (``measured``) is listed
    with its class's declared parameters, the same as where it loads."""
    rows = ["| name | what | parameters |", "|---|---|---|"]
    for name in sorted(_REGISTRY):
        factory, description = _REGISTRY[name]
        try:
            specs = get(name).params
        except (FileNotFoundError, OSError) as exc:     # data missing here: the class's declaration
            if not (isinstance(factory, type) and issubclass(factory, Model)):
                raise ValueError(f"model '{name}' cannot be built here ({exc}) and declares no parameters") from exc
            specs = factory.params
        names = ", ".join(sp.name for sp in specs) or "none"
        rows.append(f"| `{name}` | {description} | {names} |")
    return "\n".join(rows) + "\n"

