"""Many captures in one command: :func:`reconstruct_batch` reconstructs a list of datasets, each into its own folder.

- **Each capture on its own.** Every dataset is one :func:`capture.reconstruct.reconstruct` into
  ``out_root/<dataset folder name>``, written atomically as always; a capture that fails (a broken scene.json, no
  valid pixel, a model that does not fit) is recorded with its error and the batch goes on with the others.
- **Resumable.** A capture whose folder already holds a ``report.json`` is done: a second run skips it (``force``
  redoes it), so a batch that was interrupted, or whose failures were fixed, is finished by running it again.
- **A record.** ``out_root/batch.json`` lists every capture — dataset, output folder, status (``done``, ``skipped``,
  ``failed``), seconds, model, χ² per residual or the error — rewritten atomically after each capture, so it is
  current while the batch runs and after it stops.

The captures run one after another on this machine, each with all its threads: a reconstruction already uses every
core, so running two side by side on one machine gains nothing. Distributing captures over a cluster is not built.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from .outputs import json_text
from .report import atomic_write_text

__all__ = ["BatchItem", "BatchError", "find_datasets", "reconstruct_batch"]


class BatchError(ValueError):
    """Arguments a batch cannot start with (no dataset found, two datasets with the same folder name, …)."""


@dataclass
class BatchItem:
    """One capture of a batch (a row of ``batch.json``)."""

    dataset: str
    out: str
    status: str = "pending"         #: "done", "skipped" (report.json already there), "failed" or "pending"
    seconds: float = 0.0
    model: str | None = None
    chi2_per_residual: float | None = None
    error: str | None = None


def find_datasets(paths: Iterable) -> list[Path]:
    """The dataset folders among ``paths``: a folder holding ``scene.json`` is one; a folder without it stands for
    the folders directly inside it that hold one (sorted by name). Raises :class:`BatchError` for a path that does
    not exist, a folder with no dataset in or under it, or two datasets whose folder names (the output folders'
    names) are the same."""
    found: list[Path] = []
    for p in map(Path, paths):
        if not p.is_dir():
            raise BatchError(f"{p} is not a folder: give dataset folders (with scene.json) or folders holding them")
        if (p / "scene.json").is_file():
            found.append(p)
            continue
        inner = sorted(q for q in p.iterdir() if q.is_dir() and (q / "scene.json").is_file())
        if not inner:
            raise BatchError(f"{p} holds no scene.json and no folder with one: give dataset folders "
                             f"(docs/dataset-format.md) or a folder of them")
        found.extend(inner)
    names: dict[str, Path] = {}
    for p in found:
        if p.name in names and names[p.name].resolve() != p.resolve():
            raise BatchError(f"two datasets are named {p.name!r} ({names[p.name]} and {p}); their outputs would "
                             f"share one folder — rename one, or run them in separate batches")
        names[p.name] = p
    return list({p.resolve(): p for p in found}.values())


def reconstruct_batch(datasets: Sequence, out_root, *, force: bool = False,
                      log: Callable[[str], None] | None = print, **reconstruct_options) -> list[BatchItem]:
    """Reconstruct every dataset of ``datasets`` (folders, or folders of them: :func:`find_datasets`) into
    ``out_root/<name>`` (module docstring).

    Args:
        datasets: dataset folders or folders holding them.
        out_root: the folder the captures' output folders and ``batch.json`` go into (created if missing).
        force: redo captures that are already done (their folders are replaced).
        log: called with one line per capture (its index, name, outcome, time and the batch's ETA); None = quiet.
        **reconstruct_options: passed to every :func:`capture.reconstruct.reconstruct` (model, solver, …);
            ``progress`` defaults to False.

    Returns:
        One :class:`BatchItem` per capture, in order (also ``out_root/batch.json``).

    Raises:
        BatchError: no dataset, clashing names, ``out_root`` inside a dataset, or an option reconstruct
        takes itself (``out_dir``, ``dataset_path``).
    """
    from .reconstruct import reconstruct

    taken = sorted({"out_dir", "dataset_path"} & set(reconstruct_options))
    if taken:
        raise BatchError(f"reconstruct_batch sets {taken} itself (out_root/<dataset name>); leave them out")
    found = find_datasets(datasets)
    root = Path(out_root)
    for d in found:
        if root.resolve() == d.resolve() or d.resolve() in root.resolve().parents:
            raise BatchError(f"out_root {root} is inside the dataset {d}: datasets are never written into; choose "
                             f"another folder")
    root.mkdir(parents=True, exist_ok=True)
    items = [BatchItem(dataset=str(d), out=str(root / d.name)) for d in found]
    options: Mapping = {"progress": False, **reconstruct_options}
    t_done: list[float] = []
    for i, item in enumerate(items):
        _run_one(item, reconstruct, force, options)
        if item.status == "done":
            t_done.append(item.seconds)
        _write_record(root, items)
        if log is not None:
            log(_line(i, items, t_done))
    return items


def _run_one(item: BatchItem, reconstruct, force: bool, options: Mapping) -> None:
    """Reconstruct one capture into ``item.out``, recording its outcome on ``item`` (a failure never raises)."""
    out = Path(item.out)
    if (out / "report.json").is_file() and not force:
        item.status = "skipped"
        return
    t0 = time.perf_counter()
    try:
        report = reconstruct(item.dataset, out_dir=out, force=force, **options)
    except KeyboardInterrupt:
        raise
    except Exception as exc:            # noqa: BLE001 — one failed capture must not stop the others
        item.status, item.error = "failed", f"{type(exc).__name__}: {exc}"
    else:
        item.status, item.model = "done", report.model
        chi2 = report.fit.get("chi2_per_residual")
        item.chi2_per_residual = float(chi2) if chi2 is not None else None
    item.seconds = time.perf_counter() - t0


def _write_record(root: Path, items: Sequence[BatchItem]) -> None:
    counts = {s: sum(it.status == s for it in items) for s in ("done", "skipped", "failed", "pending")}
    atomic_write_text(root / "batch.json", json_text({"counts": counts, "captures": [asdict(it) for it in items]}))


def _line(i: int, items: Sequence[BatchItem], t_done: Sequence[float]) -> str:
    it, n = items[i], len(items)
    name = Path(it.dataset).name
    if it.status == "done":
        what = f"done in {it.seconds:.1f} s (model {it.model}, χ² {it.chi2_per_residual:.3g})" \
            if it.chi2_per_residual is not None else f"done in {it.seconds:.1f} s (model {it.model})"
    elif it.status == "skipped":
        what = "skipped: report.json is already there (force / --force redoes it)"
    else:
        what = f"FAILED after {it.seconds:.1f} s — {it.error}"
    left = n - i - 1
    eta = f"; about {left * sum(t_done) / len(t_done):.0f} s left" if left and t_done else ""
    return f"[{i + 1}/{n}] {name}: {what}{eta}"
