"""Many captures in one command: :func:`reconstruct_batch` reconstructs a list of datasets, each into its own folder.

- **Each capture on its own.** Every dataset is one :func:`capture.reconstruct.reconstruct` into
  ``out_root/<dataset folder name>``, written atomically as always; a capture that fails (a broken scene.json, no
  valid pixel, a model that does not fit) is recorded with its error and the batch goes on with the others.
- **Resumable.** A capture whose folder already holds a ``report.json`` is done: a second run skips it (``force``
  redoes it), so a batch that was interrupted, or whose failures were fixed, is finished by running it again.
- **A record.** ``out_root/batch.json`` lists every capture — dataset, output folder, status (``done``, ``skipped``,
  ``failed``), seconds, model, χ² per residual or the error — rewritten atomically after each capture, so it is
  current while the batch runs and after it stops (on a cluster also the worker that ran it).
- **Here or on a cluster.** By default the captures run one after another in this process, each with all its threads
  (a reconstruction already uses every core). With ``cluster`` each capture is one task on a `Dask distributed
  <https://distributed.dask.org>`_ cluster — a running scheduler's address (``tcp://host:8786``, started with
  ``dask scheduler`` and ``dask worker``), or ``"local:N"``, N worker processes started here — and the record and the
  progress lines follow the captures as they finish. Dask, not Ray: the captures are independent multi-minute jobs
  that share no data, for which pure-Python wheels and a scheduler users already run are enough; Ray's object store
  and its large binary wheel buy nothing here. Dask is optional (``pip install 'shadecap[cluster]'``).

On a cluster every worker reads the datasets and writes ``out_root`` at the same paths as this machine (a shared
filesystem) and imports shadecap from the same environment. A Dask thread runs one capture at a time, and each capture
gets its share of its machine's cores as torch threads (the cores over the Dask threads of the workers there): start
the workers of a machine with ``--nthreads K`` for K captures at a time (``--nthreads 1``: one, with every core;
``dask worker``'s default, one thread per core, runs as many captures as cores with one torch thread each).
"""

from __future__ import annotations

import re
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from .outputs import json_text
from .report import atomic_write_text

if TYPE_CHECKING:
    from distributed import Client

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
    worker: str | None = None       #: the Dask worker that reconstructed it (``cluster``); None = this process


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
                      log: Callable[[str], None] | None = print, cluster: str | Client | None = None,
                      **reconstruct_options) -> list[BatchItem]:
    """Reconstruct every dataset of ``datasets`` (folders, or folders of them: :func:`find_datasets`) into
    ``out_root/<name>`` (module docstring).

    Args:
        datasets: dataset folders or folders holding them.
        out_root: the folder the captures' output folders and ``batch.json`` go into (created if missing).
        force: redo captures that are already done (their folders are replaced).
        log: called with one line per capture (its count, name, outcome, time and the batch's ETA); None = quiet.
        cluster: where the captures run. None: one after another in this process. ``"tcp://host:8786"`` (any
            ``scheme://host:port``, or ``host:port``): the Dask scheduler at that address, one task per capture.
            ``"local:N"``: N worker processes started here for this batch (``"local"``: one per 4 cores); a script
            doing this must call it under ``if __name__ == "__main__":`` (the workers are spawned processes that
            import it). A ``distributed.Client`` is used as it is (and left open).
        **reconstruct_options: passed to every :func:`capture.reconstruct.reconstruct` (model, solver, …);
            ``progress`` defaults to False. On a cluster ``threads=None`` becomes each worker's share of its
            machine's cores.

    Returns:
        One :class:`BatchItem` per capture, in order (also ``out_root/batch.json``).

    Raises:
        BatchError: no dataset, clashing names, ``out_root`` inside a dataset, an option reconstruct takes itself
        (``out_dir``, ``dataset_path``), a ``cluster`` that is none of the forms above, Dask not installed, or a
        scheduler that cannot be reached.
    """
    taken = sorted({"out_dir", "dataset_path"} & set(reconstruct_options))
    if taken:
        raise BatchError(f"reconstruct_batch sets {taken} itself (out_root/<dataset name>); leave them out")
    where = _parse_cluster(cluster)
    distributed = _import_distributed() if where is not None else None
    found = find_datasets(datasets)
    root = Path(out_root)
    for d in found:
        if root.resolve() == d.resolve() or d.resolve() in root.resolve().parents:
            raise BatchError(f"out_root {root} is inside the dataset {d}: datasets are never written into; choose "
                             f"another folder")
    root.mkdir(parents=True, exist_ok=True)
    items = [BatchItem(dataset=str(d), out=str(root / d.name)) for d in found]
    options: Mapping = {"progress": False, **reconstruct_options}
    if where is None:
        t_done: list[float] = []
        for i in range(len(items)):
            items[i] = _run_one(items[i], force, options)
            _finished(items, i, i + 1, t_done, root, log)
    else:
        _run_on_cluster(distributed, items, where, force, options, root, log)
    return items


def _run_one(item: BatchItem, force: bool, options: Mapping) -> BatchItem:
    """Reconstruct one capture into ``item.out``: ``item`` with its outcome (a failure never raises). Runs in this
    process or, through :func:`_run_on_worker`, in a Dask worker."""
    from .reconstruct import reconstruct

    out = Path(item.out)
    if (out / "report.json").is_file() and not force:
        return replace(item, status="skipped")
    t0 = time.perf_counter()
    try:
        report = reconstruct(item.dataset, out_dir=out, force=force, **options)
    except KeyboardInterrupt:
        raise
    except Exception as exc:            # noqa: BLE001 — one failed capture must not stop the others
        return replace(item, status="failed", error=f"{type(exc).__name__}: {exc}",
                       seconds=time.perf_counter() - t0)
    chi2 = report.fit.get("chi2_per_residual")
    return replace(item, status="done", model=report.model, seconds=time.perf_counter() - t0,
                   chi2_per_residual=float(chi2) if chi2 is not None else None)


def _finished(items: list[BatchItem], i: int, k: int, t_done: list[float], root: Path,
              log: Callable[[str], None] | None, slots: int = 1) -> None:
    """Capture ``i`` has its outcome, the ``k``-th of the batch to finish: record it and log its line."""
    if items[i].status == "done":
        t_done.append(items[i].seconds)
    _write_record(root, items)
    if log is not None:
        log(_line(k, items[i], len(items), t_done, slots))


def _write_record(root: Path, items: Sequence[BatchItem]) -> None:
    counts = {s: sum(it.status == s for it in items) for s in ("done", "skipped", "failed", "pending")}
    atomic_write_text(root / "batch.json", json_text({"counts": counts, "captures": [asdict(it) for it in items]}))


def _line(k: int, it: BatchItem, n: int, t_done: Sequence[float], slots: int = 1) -> str:
    """The log line of capture ``it``, the ``k``-th of ``n`` to finish; the ETA assumes ``slots`` captures at a time."""
    name = Path(it.dataset).name
    if it.status == "done":
        what = f"done in {it.seconds:.1f} s (model {it.model}, χ² {it.chi2_per_residual:.3g})" \
            if it.chi2_per_residual is not None else f"done in {it.seconds:.1f} s (model {it.model})"
    elif it.status == "skipped":
        what = "skipped: report.json is already there (force / --force redoes it)"
    else:
        what = f"FAILED after {it.seconds:.1f} s — {it.error}"
    if it.worker is not None:
        what += f" [{it.worker}]"
    left = n - k
    eta = f"; about {left * sum(t_done) / len(t_done) / min(slots, left):.0f} s left" if left and t_done else ""
    return f"[{k}/{n}] {name}: {what}{eta}"


# --- on a Dask cluster -------------------------------------------------------------------------------------------

_CLUSTER_FORMS = ("give cluster as 'tcp://host:8786' (the address of a running Dask scheduler), 'local:N' (N worker "
                  "processes here), or nothing (None, no --cluster: one after another in this process)")


def _parse_cluster(cluster):
    """None, ``("local", n_workers)``, ``("address", address)`` or ``("client", client)``; :class:`BatchError` for
    anything else (checked before any import or work)."""
    if cluster is None:
        return None
    if not isinstance(cluster, str):
        distributed = sys.modules.get("distributed")          # a Client exists only once distributed is imported
        if distributed is not None and isinstance(cluster, distributed.Client):
            return "client", cluster
        raise BatchError(f"cluster must be a string or a distributed.Client, got {type(cluster).__name__}: "
                         f"{_CLUSTER_FORMS}")
    text = cluster.strip()
    if text == "local":
        from os import cpu_count

        return "local", max(1, (cpu_count() or 1) // 4)
    if text.startswith("local:"):
        n = text[len("local:"):]
        if not n.isdigit() or int(n) < 1:
            raise BatchError(f"cluster {cluster!r}: N in 'local:N' must be a positive number of worker processes")
        return "local", int(n)
    if re.fullmatch(r"[a-z][a-z0-9+.-]*://\S+", text) or re.fullmatch(r"[\w.-]+:\d+", text):
        return "address", text
    raise BatchError(f"cluster {cluster!r} is not a scheduler address nor local[:N]: {_CLUSTER_FORMS}")


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        raise BatchError(f"cluster needs Dask distributed, which is not installed ({exc}): pip install "
                         f"'dask[distributed]' (or shadecap[cluster]), or leave cluster out to run the captures "
                         f"here one after another") from exc
    return distributed


def _run_on_worker(item: BatchItem, force: bool, options: Mapping, threads_by_host: Mapping[str, int]) -> BatchItem:
    """:func:`_run_one` in a Dask worker, ``threads=None`` becoming :func:`_share_of_cores`."""
    from distributed import get_worker

    if options.get("threads") is None:
        options = {**options, "threads": _share_of_cores(threads_by_host)}
    return replace(_run_one(item, force, options), worker=get_worker().address)


def _share_of_cores(threads_by_host: Mapping[str, int]) -> int:
    """The torch threads of one capture in this Dask worker: its machine's cores over the Dask threads (captures at a
    time) of all the workers on the machine (``threads_by_host``, as the scheduler knew them when the batch started;
    this worker's own threads for a machine that joined later), at least 1."""
    from dask.system import CPU_COUNT
    from distributed import get_worker
    from distributed.comm import get_address_host

    worker = get_worker()
    at_once = threads_by_host.get(get_address_host(worker.address)) or worker.state.nthreads
    return max(1, CPU_COUNT // max(1, at_once))


def _run_on_cluster(distributed, items: list[BatchItem], where, force: bool, options: Mapping, root: Path,
                    log: Callable[[str], None] | None) -> None:
    """Every pending capture of ``items`` as one task on the cluster ``where`` (:func:`_parse_cluster`); ``items``
    and ``batch.json`` updated as each finishes. With nothing pending no cluster is reached or started."""
    k, t_done, pending = 0, [], []
    for i, item in enumerate(items):
        if (Path(item.out) / "report.json").is_file() and not force:
            items[i] = replace(item, status="skipped")
            k += 1
            _finished(items, i, k, t_done, root, log)
        else:
            pending.append(i)
    if not pending:
        return
    _write_record(root, items)                          # the pending ones listed from the start
    kind, value = where
    client, local, address = _connect(distributed, kind, value)
    try:
        nthreads = client.nthreads()                    # worker address → Dask threads (captures at a time)
        threads_by_host: dict[str, int] = {}
        for worker, n in nthreads.items():
            host = distributed.comm.get_address_host(worker)
            threads_by_host[host] = threads_by_host.get(host, 0) + n
        slots = max(1, sum(nthreads.values()))
        if log is not None and nthreads:
            log(f"on the Dask cluster at {address}: {len(nthreads)} worker{'s' * (len(nthreads) != 1)}, {slots} "
                f"capture{'s' * (slots != 1)} at a time")
        elif log is not None:
            log(f"no Dask worker is connected to {address} yet: the captures wait until one joins "
                f"(dask worker {address})")
        futures = {}
        for i in pending:
            item = items[i]
            # workers see the paths as this process does (a shared filesystem), not its working folder
            task = replace(item, dataset=str(Path(item.dataset).resolve()), out=str(Path(item.out).resolve()))
            futures[client.submit(_run_on_worker, task, force, options, threads_by_host, pure=False,
                                  key=f"reconstruct-{Path(item.dataset).name}-{uuid.uuid4().hex[:8]}")] = i
        for future in distributed.as_completed(list(futures)):
            i = futures.pop(future)
            if future.status == "finished":
                items[i] = replace(future.result(), dataset=items[i].dataset, out=items[i].out)
            elif future.status == "error":
                exc = future.exception()
                items[i] = replace(items[i], status="failed", error=f"{type(exc).__name__} on the cluster: {exc}")
            else:
                items[i] = replace(items[i], status="failed", error=f"the task was {future.status} on the cluster "
                                                                    f"(a worker or the scheduler went away)")
            k += 1
            _finished(items, i, k, t_done, root, log, slots)
    finally:
        if kind != "client":
            client.close()
        if local is not None:
            local.close()


def _connect(distributed, kind: str, value):
    """``(client, local cluster or None, scheduler address)`` for a parsed ``cluster`` (:func:`_parse_cluster`)."""
    if kind == "client":
        return value, None, value.scheduler.address
    if kind == "local":
        try:
            local = distributed.LocalCluster(n_workers=value, threads_per_worker=1, processes=True,
                                             dashboard_address=":0")       # any free port: 8787 may be taken
        except RuntimeError as exc:
            raise BatchError(f"could not start {value} local Dask worker processes ({exc}); a script calling "
                             f"reconstruct_batch(cluster='local…') must do so under `if __name__ == \"__main__\":` "
                             f"(the workers are spawned processes that import it)") from exc
        try:
            return distributed.Client(local), local, local.scheduler_address
        except BaseException:
            local.close()
            raise
    try:
        return distributed.Client(value), None, value
    except (OSError, ValueError) as exc:
        raise BatchError(f"could not reach a Dask scheduler at {value} ({type(exc).__name__}: {exc}): start one with "
                         f"`dask scheduler` and workers with `dask worker {value}`, or check the address") from exc
