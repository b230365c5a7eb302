"""The options of :func:`capture.fit.fast.solve_fast` (:class:`FitOptions`): every one with its default, validated
once, when the options are made."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

from .layout import SolverError
from .noise import NOISE, check_loss, check_noise
from .operators import JACOBIAN_FORMS, check_jacobian_form

__all__ = ["FitOptions"]


def _cli(default, type_, help_: str, **argparse_kw):
    """A field with a command-line flag: ``--name`` (dashes for underscores) of ``type_`` whose help is ``help_``
    (argparse %-formatting) — :meth:`FitOptions.cli_flags` lists them, :mod:`capture.cli` adds them."""
    return dataclasses.field(default=default, metadata={"cli": {"type": type_, "help": help_, **argparse_kw}})


@dataclass(frozen=True)
class FitOptions:
    """Options of :func:`capture.fit.fast.solve_fast`, checked in ``__post_init__`` (:class:`SolverError`); the
    defaults that depend on other options (``iterations``, ``grid``, ``share``, ``joint_iterations``,
    ``cg_iterations``: None) are resolved by the solver.

    Attributes:
        loss: "l2", "huber" or "l1" (robust ones by IRLS reweighting each iteration).
        delta: Huber/L1 scale in radiance units (default 5 % of the median measured radiance).
        iterations: maximum per-texel LM iterations (all stages together); None = 40 with nearest
            sampling, 10 with bilinear (there the per-texel fit only initialises the joint
            refinement; measured on the default scene: 40 → 10 iterations saves ~10 s, same errors), which
            also stops after :data:`BILINEAR_LM_MIN` iterations once the total cost has dropped by less than
            :data:`BILINEAR_LM_TOL` (relative) in two consecutive iterations.
        grid: number of values of the main nonlinear parameter (first scalar non-linear parameter,
            e.g. roughness) tried by the closed-form initialisation (geometric spacing); 0/1 = none.
            None = 32, or 16 with ``share`` (the texels a coarse grid leaves in a wrong basin are the
            weakly observed ones, which sharing replaces; measured on the default scene: 32 → 16 saves
            4 s and changes the RMSE on observable texels by ≤ 0.001).
        refine: coarse-to-fine rounds after the grid (each tries ± h and a parabola vertex around
            every texel's best value, 3 closed-form solves, then h /= 3).
        schedule: "joint" (all parameters every iteration) or "staged" (Nielsen et al.: scale
            terms — linear parameters — first, then lobe shape — nonlinear ones — then all, each a
            third of the iterations).
        smoothness: weight μ of a prior ``μ·s̄·Σ_neighbours ||θ_t − θ_n||²`` (s̄ the mean diagonal of
            JᵀWJ, so μ is dimensionless); 0 = off. It matters where data are weak.
        tol: stop when the relative decrease of the total cost over an iteration is below this.
        observable_std: threshold(s) on the marginal posterior std (canonical units) below which a
            parameter is observable (:func:`posterior_std`, default :data:`OBSERVABLE_STD`).
        noise: photo noise model ``(relative std, floor)`` of :func:`posterior_std` (also the sharing's χ² and
            the reference of the albedo prior's noise-adaptive unit, :func:`refine_joint`).
        sampling: "nearest" (texels independent: per-texel LM is exact) or "bilinear" (the photos
            read four texels per sample: the per-texel LM — with nearest sampling — initialises
            :func:`refine_joint`, ``joint_iterations`` joint LM steps with ``cg_iterations`` PCG
            iterations each). None = 6 steps × 30 CG iterations with the sharing (whose proposal prior,
            ``anchor_weight``, makes more steps safe), 3 × 25 without it. Measured on the default scene without
            the sharing: 2 → 3 steps all-texel RMSE 0.0155 / 0.0165 / 0.0557 → 0.0161 / 0.0159 / 0.0532;
            with it 3 × 25 without the anchor 0.0089 / 0.0159 / 0.0531 (observable 0.0005 / 0.0017 /
            0.0018), 6 × 30 with it 0.0088 / 0.0134 / 0.0515 (0.0004 / 0.0011 / 0.0015), +2–3 s.
        pooled: tile size (texels) of the sharing's pooled proposals (:func:`capture.fit.sharing.share_materials`
            ``pool_block``; 0 = off, the default): tiles of non-anchor texels with no anchor nearby fit a material
            of their own on their pooled samples and propose it when it beats every candidate. For materials that
            give no anchor — a rough dielectric under fixed lights: all-texel roughness 0.109 → 0.048 there, but
            the default (flash) scene's f0 0.0126 → 0.0294 (docs/log.md, "second basins are local minima").
        anchor_weight: weight of the joint refinement's tie of each texel's material parameters to the sharing's
            proposal (:func:`refine_joint`; relative to the neighbour prior's data scale; 0 = off, only with the
            sharing). 0.03: the best of 0.01 / 0.03 / 0.1 on the default scene (6 × 50 steps: f0 0.0171 / 0.0139 /
            0.0125, roughness 0.0484 / 0.0510 / 0.0571); without it the f0 there drifts to 0.0326.
        fill_before_joint: before the joint refinement, replace the parameters that are unobservable in a texel
            by pull-push fills of the observable ones (default). Measured on the default scene (2 joint
            iterations): without the fill the RMSE on observable texels is 0.0032 / 0.0103 / 0.0395 (albedo / f0 /
            roughness) against 0.0015 / 0.0079 / 0.0109 with it; 4 joint iterations without it: 0.0038 / 0.0259 /
            0.0592 — the wild per-texel values of unconstrained parameters leak into the neighbours' bilinear
            footprint.
        share: reflectance sharing before the joint refinement (:func:`capture.fit.sharing.share_materials`):
            texels whose shared parameters (all but the albedo) their own samples do not determine take
            those of one of ``candidates`` materials clustered from the texels where they are determined,
            and the joint refinement adds the edge-preserving prior of weight ``sharing`` on every parameter
            between neighbours (:func:`refine_joint`). None = on whenever the joint refinement runs (bilinear
            sampling); it then replaces ``fill_before_joint``. Measured on the default scene (docs/
            log.md, "3 joint steps"): RMSE on all observed texels albedo / f0 / roughness 0.0089 /
            0.0159 / 0.0531 against 0.0805 / 0.1963 / 0.1892 without, on observable texels 0.0005 / 0.0017 /
            0.0018 against 0.0016 / 0.0107 / 0.0146;
            ``candidates`` 8 against 10: f0 0.021 → 0.016 here, 0.054 → 0.019 with fixed lights.
            A safeguard: when the refinement the sharing seeds ends with a higher data cost than the per-texel fit
            it started from, a material is missing (no texel determined it); the texels whose own samples reject
            their material (:func:`capture.fit.sharing.unmatched_texels`) keep their own fit, the refinement runs
            again and the lower data cost wins (``info["sharing_fallback"]``). Layered scene of 128 px, 64² maps,
            coat given: data cost 0.024 → 0.0009 (per-texel fit 0.0049); with the coat fitted, worst / mean view
            27.4 / 34.2 dB without it → 40.1 / 46.5 dB (docs/log.md, "candidate materials the photos
            do not need"); never triggered on the GGX + Lambert scenes there. A second one: seeded from scarce
            anchors, materials whose refinement misses
            the photos by more than their noise allows are seeded again from more texels, and the photos judge
            (:data:`ANCHOR_RETRY_FACTOR`, ``info["share_retry"]``).
        footprint_iterations: LM steps of that final solve (default :data:`FOOTPRINT_STEPS`).
        jacobian: how that solve keeps each linearisation's Jacobian (:data:`capture.fit.operators.JACOBIAN_FORMS`):
            "assembled" as sparse pixel × texel matrices (the fastest products), "samples" per sample (products
            through the sampling operators), "auto" (default) assembled unless that would take more than
            :data:`capture.fit.operators.ASSEMBLED_SHARE` of the memory available. docs/image-formation.md, "Memory",
            has the two forms' memory and time.
        proposals: between the footprint solve's untied and tied steps, texels whose pixels stay misfit by more than
            :data:`capture.fit.proposals.PROPOSAL_CHI2` try their neighbours' values
            (:func:`capture.fit.proposals.neighbour_proposals`; with the sharing only). Default on.
        memory_budget: GiB of memory the process may hold (None: what the machine, or its memory cgroup, has
            available, :func:`renderer.device.available_memory`). ``jacobian="auto"`` keeps the assembled matrices
            within what the budget leaves (:func:`renderer.device.memory_headroom`); nothing else is sized by it
            yet — the observations and the pixel operator are held whole — so :func:`capture.reconstruct.reconstruct`
            warns when the peak went above it.
        sharing_albedo: the joint refinement's prior links neighbouring texels' albedo too (default; see
            :func:`refine_joint` for the measurements). Where the photos determine a texel's albedo the data win;
            where they barely do (texels read only through a neighbour's bilinear footprint, the grazing band) it
            follows its neighbours, edges kept; its unit shrinks when the residuals say the photos are noisier
            than ``noise``. Default scene: all-texel albedo RMSE 0.0089 against 0.0161 without; with shot noise
            0.0264 against 0.0549; a texture finer than the texels (1.3-texel checker squares) 0.0201 against
            0.0191.
        reproject: every this many iterations re-solve the linear parameters in closed form at the
            current nonlinear ones (a variable-projection step, 1 + #linear evaluations); 0 = never.
    """

    loss: str = "l2"
    delta: float | None = _cli(None, float, "Huber/L1 scale in radiance units (default: 5 %% of the median "
                                             "measured radiance)")
    iterations: int | None = _cli(None, int, "maximum iterations (fast: per-texel LM; adam: steps)")
    grid: int | None = _cli(None, int, "fast path: grid size of the closed-form initialisation")
    refine: int = 3
    schedule: str = _cli("joint", str, "fast path: all parameters every iteration, or Nielsen's stages "
                                       "(scales, shape, all)", choices=("joint", "staged"))
    smoothness: float = _cli(0.0, float, "fast path: weight of a neighbour prior in the per-texel fit (0 = off)")
    tol: float = 1e-10
    observable_std: float | Mapping[str, float] | None = None
    noise: tuple[float, float] = NOISE
    reproject: int = 0
    sampling: str = "nearest"
    joint_iterations: int | None = _cli(None, int, "fast path: joint LM steps of the pixel-centre refinement "
                                                   "(default: 6 with the sharing, 3 without; 0 = none)")
    cg_iterations: int | None = _cli(None, int, "fast path: PCG iterations per joint or footprint step "
                                                "(default: 30, 25 for the pixel-centre refinement without the "
                                                "sharing)")
    fill_before_joint: bool = True
    share: bool | None = None
    candidates: int = _cli(8, int, "fast path: most materials the reflectance sharing clusters")
    sharing: float = _cli(1.0, float, "fast path: weight of the edge-preserving neighbour prior of the joint "
                                      "solves (0 = off)")
    sharing_albedo: bool = True
    anchor_weight: float = _cli(0.03, float, "fast path: weight of the tie of each texel's material to the "
                                             "sharing's proposal (0 = off)")
    pooled: int = _cli(0, int, "fast path: let N×N-texel tiles without an anchor propose materials of their own; "
                               "default: 4 when the lights stay fixed relative to the object (studio lamps, a "
                               "dome: a rough material may show no highlight peak), off when they move with the "
                               "camera (flash, turntable); 0 = off", metavar="N")
    footprint_iterations: int | None = _cli(None, int, "fast path: LM steps of the final solve on the photos' "
                                                       "pixel footprints (default: 6)")
    jacobian: str = _cli("auto", str, "fast path: how the footprint solve keeps its Jacobian — assembled sparse "
                                      "matrices (fastest), per sample (less memory, slower steps), or auto: "
                                      "assembled unless they would take more than half the memory available",
                         choices=JACOBIAN_FORMS)
    proposals: bool = True
    memory_budget: float | None = _cli(None, float, "GiB of memory the reconstruction may hold (default: what the "
                                                    "machine, or its memory cgroup, has available): the footprint "
                                                    "solve's auto Jacobian stays within it; the summary warns when "
                                                    "the peak went above it", metavar="GIB")

    def __post_init__(self):
        check_loss(self.loss)
        delta = self.delta
        if delta is not None and not (delta > 0 and math.isfinite(delta)):
            raise SolverError(f"delta must be a positive finite number (radiance units), got {delta!r}")
        schedule, smoothness, sampling = self.schedule, self.smoothness, self.sampling
        joint_iterations, cg_iterations = self.joint_iterations, self.cg_iterations
        anchor_weight, sharing, sharing_albedo = self.anchor_weight, self.sharing, self.sharing_albedo
        candidates, pooled, iterations, grid = self.candidates, self.pooled, self.iterations, self.grid
        if schedule not in ("joint", "staged"):
            raise SolverError(f"schedule must be 'joint' or 'staged', got {schedule!r}")
        if not (smoothness >= 0 and math.isfinite(smoothness)):
            raise SolverError(f"smoothness must be ≥ 0, got {smoothness!r}")
        for name, n in (("joint_iterations", joint_iterations), ("cg_iterations", cg_iterations)):
            if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 0):
                raise SolverError(f"{name} must be an integer ≥ 0 or None (the default), got {n!r}")
        if not (anchor_weight >= 0 and math.isfinite(anchor_weight)):
            raise SolverError(f"anchor_weight must be a finite weight ≥ 0 (0 = off), got {anchor_weight!r}")
        if not (sharing >= 0 and math.isfinite(sharing)):
            raise SolverError(f"sharing must be a finite weight ≥ 0, got {sharing!r}")
        if not isinstance(sharing_albedo, bool):
            raise SolverError(f"sharing_albedo must be True or False, got {sharing_albedo!r}")
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
            raise SolverError(f"candidates must be an integer ≥ 1 (number of shared materials), got {candidates!r}")
        if isinstance(pooled, bool) or not isinstance(pooled, int) or pooled < 0:
            raise SolverError(f"pooled must be a tile size in texels ≥ 0 (0 = no pooled proposals, 4 suits a "
                              f"fixed-light rig), got {pooled!r}")
        if (iterations is not None and iterations < 0) or (grid is not None and grid < 0):
            raise SolverError(f"iterations and grid must be ≥ 0, got {iterations}, {grid}")
        if sampling not in ("nearest", "bilinear"):
            raise SolverError(f"sampling must be 'nearest' or 'bilinear', got {sampling!r}")
        check_jacobian_form(self.jacobian)
        if not isinstance(self.proposals, bool):
            raise SolverError(f"proposals must be True or False, got {self.proposals!r}")
        budget = self.memory_budget
        if budget is not None and (isinstance(budget, bool) or not isinstance(budget, (int, float))
                                   or not (budget > 0 and math.isfinite(budget))):
            raise SolverError(f"memory_budget must be a positive number of GiB or None (what the machine has), got "
                              f"{budget!r}")
        check_noise(self.noise)

    @property
    def memory_budget_bytes(self) -> int | None:
        """``memory_budget`` in bytes (None: no budget)."""
        return None if self.memory_budget is None else int(self.memory_budget * 2 ** 30)

    @classmethod
    def of(cls, options: FitOptions | None = None, **overrides) -> FitOptions:
        """``options`` (default: the defaults) with the fields in ``overrides`` replaced; an unknown name is a
        :class:`SolverError` listing the valid ones."""
        if options is not None and not isinstance(options, FitOptions):
            raise SolverError(f"options must be a FitOptions, got {type(options).__name__}")
        names = cls.names()
        unknown = sorted(set(overrides) - set(names))
        if unknown:
            raise SolverError(f"unknown solve_fast option(s) {unknown}; the options are {list(names)}")
        base = options if options is not None else cls()
        return dataclasses.replace(base, **overrides) if overrides else base

    @classmethod
    def cli_flags(cls) -> tuple[tuple[str, dict], ...]:
        """``(name, argparse keywords)`` of the options that have a command-line flag, in declaration order. The
        flag's default is None (not given): the option's default, or what the caller decides, applies."""
        return tuple((f.name, dict(f.metadata["cli"])) for f in dataclasses.fields(cls) if "cli" in f.metadata)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The options' names, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    def to_dict(self) -> dict:
        """The options as a JSON-able dict (tuples as lists, mappings as dicts)."""
        def plain(x):
            if isinstance(x, Mapping):
                return {str(k): plain(v) for k, v in x.items()}
            if isinstance(x, (tuple, list)):
                return [plain(v) for v in x]
            return x
        return {f.name: plain(getattr(self, f.name)) for f in dataclasses.fields(self)}
