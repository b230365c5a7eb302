"""One progress bar over a whole job, its stages weighted by their expected cost.

A reconstruction runs stages of very different cost (loading, G-buffers, observations, footprints, the solve, the
reflectance sharing, the joint refinement, metrics, outputs), and only some of them know how many steps they will
take. :class:`Progress` shows them as one bar of ``total`` units: each stage owns a share of the total proportional
to its weight (:data:`RECONSTRUCT_STAGES`, measured costs rounded), the bar names the stage it is in, and tqdm
gives the rate and the ETA. Inside a stage whose length is unknown each :meth:`Progress.tick` moves the bar a fixed
fraction (:data:`TICK_FRACTION`) of what is left of the stage, so it never runs past the stage's share; entering the
next stage (or :meth:`Progress.close`) completes the ones before it. The position only ever grows, and a finished job
reads exactly ``total``.

``enabled=False`` shows nothing and costs nothing (the same calls, no output), so the caller needs no branches.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping

__all__ = ["Progress", "ProgressError", "RECONSTRUCT_STAGES", "TICK_FRACTION", "DELAY_S"]

#: Stage → weight (its expected share of a reconstruction's time, in percent of a typical run). Measured on the
#: default scene (`shadecap synth` defaults: 16 views of 256², 256² maps, GGX + Lambert; 2-core CPU, 2 threads; the
#: time between the bar's stage changes, 37 s in all): load 0.08 s, G-buffers 0.23 s, pixel-centre observations
#: 0.13 s, footprints 2.1 s, per-texel stages 5.1 s, sharing 0.7 s, pixel-centre joint refinement 7.4 s, footprint
#: solve with its posterior 20.6 s, metrics 0.4 s, outputs 1.1 s. (The weights measured when that footprint solve
#: took 233 s gave the per-texel stages 3 % of the bar: on the 256² Mitsuba sphere the ETA read 0:22 after the
#: footprints, 1:49 during the per-texel stages, 0:15 in the footprint solve.) ``select`` is ``model="auto"``'s trial
#: fits, left out otherwise. Stages a run skips are passed over.
RECONSTRUCT_STAGES = {"load": 0.3, "gbuffer": 0.6, "observe": 0.5, "footprints": 5.5, "select": 40.0,
                      "solve": 14.0, "sharing": 2.0, "joint": 20.0, "footprint solve": 55.0, "metrics": 1.0,
                      "outputs": 3.0}

#: Within a stage, each tick moves the bar this fraction of the stage's remaining share.
TICK_FRACTION = 0.1
#: The bar shows only once a job has run this long (seconds).
DELAY_S = 0.5


class ProgressError(ValueError):
    """Bad stage weights or an unknown stage name."""


class Progress:
    """A weighted multi-stage progress bar (see the module docstring).

    Args:
        stages: stage name → weight (> 0), in the order the stages run.
        enabled: False shows nothing.
        desc: the bar's label.
        total: the bar's length in units (default 100: percent).
        file: where the bar is written (default ``sys.stderr``).
        delay: seconds before the bar first shows (default :data:`DELAY_S`).

    Attributes:
        position: where the bar stands, in ``[0, total]``; stage: the current stage (None before the first).
    """

    def __init__(self, stages: Mapping[str, float], *, enabled: bool = True, desc: str = "reconstruct",
                 total: float = 100.0, file=None, delay: float | None = None):
        if not isinstance(stages, Mapping) or not stages:
            raise ProgressError(f"stages must be a non-empty mapping name → weight, got {stages!r}")
        bad = {k: w for k, w in stages.items()
               if not isinstance(k, str) or isinstance(w, bool) or not isinstance(w, (int, float)) or not w > 0
               or w == float("inf")}
        if bad:
            raise ProgressError(f"stage weights must be finite numbers > 0 keyed by name, got {bad}")
        if isinstance(total, bool) or not isinstance(total, (int, float)) or not 0 < total < float("inf"):
            raise ProgressError(f"total must be a finite number > 0, got {total!r}")
        self.total = float(total)
        scale = self.total / sum(float(w) for w in stages.values())
        self.names = list(stages)
        self.ends: dict[str, float] = {}
        acc = 0.0
        for k in self.names:
            acc += float(stages[k]) * scale
            self.ends[k] = acc
        self.ends[self.names[-1]] = self.total          # no rounding shortfall at the end
        self.position = 0.0
        self.stage: str | None = None
        self.note = ""
        self.desc = desc
        self._bar = None
        delay = DELAY_S if delay is None else delay
        if enabled:
            from tqdm import tqdm

            # shown after DELAY_S only: a job that fails on its input at once prints its error alone
            self._bar = tqdm(total=self.total, desc=desc, unit="%", file=file or sys.stderr, leave=False, delay=delay,
                             bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed} elapsed, ETA {remaining}")

    def _start_of(self, name: str) -> float:
        i = self.names.index(name)
        return self.ends[self.names[i - 1]] if i else 0.0

    def _move(self, to: float) -> None:
        to = min(max(to, self.position), self.total)
        if self._bar is not None:
            self._bar.update(to - self.position)
        self.position = to

    def _show(self) -> None:
        if self._bar is not None:
            # drawn with the next move (a forced refresh would show the bar before its delay)
            self._bar.set_description_str(f"{self.desc} [{self.stage}{' ' + self.note if self.note else ''}]",
                                          refresh=False)

    def start(self, name: str, note: str = "") -> None:
        """Enter stage ``name``: the stages before it count as done (also those the run skipped). Entering the
        current stage again, or a stage that comes before it, only changes the note."""
        if name not in self.ends:
            raise ProgressError(f"unknown stage {name!r}; the stages are {self.names}")
        if self.stage is None or self.names.index(name) > self.names.index(self.stage):
            self._move(self._start_of(name))
            self.stage = name
        self.note = note
        self._show()

    def tick(self, note: str = "") -> None:
        """One step of unknown count inside the current stage: move :data:`TICK_FRACTION` of what is left of it."""
        if self.stage is None:
            return
        self._move(self.position + TICK_FRACTION * (self.ends[self.stage] - self.position))
        if note:
            self.note = note
        self._show()

    def finish(self, name: str) -> None:
        """Complete stage ``name`` (and every stage before it)."""
        if name not in self.ends:
            raise ProgressError(f"unknown stage {name!r}; the stages are {self.names}")
        self._move(self.ends[name])

    def close(self) -> None:
        """Complete the job (the bar reads ``total``) and remove the bar."""
        self._move(self.total)
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def abort(self) -> None:
        """Remove the bar without completing the job (the job failed)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.abort()
