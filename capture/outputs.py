"""Output folders: checked before any work, written atomically, with the permissions the umask gives.

Every command that writes a folder — :func:`capture.dataset.write_dataset` (``shadecap synth``),
:func:`capture.reconstruct.reconstruct` and :func:`capture.export.export_atlas` — goes through here:

- :func:`check_output`, before any work: the output is not, does not contain and does not sit inside
  any input (the dataset folder, the reconstruction folders, an input file), through symbolic links
  too; it exists only when replacing was asked for; its folder can be written (a probe folder is
  created and removed). Each failure is one error naming the path and the fix.
- :func:`atomic_folder`, a context manager: the caller writes into a temporary folder next to the
  output; on success it gets the umask's permissions (``renderer.imageio.apply_umask``) and is
  renamed into place, replacing the previous output (moved aside and removed: nothing is left
  behind); on any failure — an interrupt included — the temporary folder is removed and the output
  is as it was. An ``OSError`` becomes the caller's error class naming the output path.
- :func:`jsonable` / :func:`json_text`: strict JSON (a non-finite float is written ``null``);
  :func:`na_floats` / :func:`na_text`: ``n/a`` for the non-finite numbers of a printed summary.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import secrets
import shutil
import stat
import sys
import tempfile
import warnings
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from renderer.imageio import apply_umask

__all__ = ["OutputError", "OutputWarning", "check_output", "atomic_folder", "os_error_message", "jsonable",
           "json_text", "NA", "na_floats", "na_text"]


class OutputError(ValueError):
    """An output that must not or cannot be written; the message names the path and the fix."""


class OutputWarning(UserWarning):
    """The output was written, but something next to it could not be cleaned up (the message names it)."""


def _abs(p) -> Path:
    return Path(os.path.abspath(os.fspath(p)))


def _real(p) -> Path:
    return Path(os.path.realpath(os.fspath(p)))


def _relation(out: Path, inp: Path) -> str | None:
    if out == inp:
        return "is"
    if inp in out.parents:
        return "sits inside"
    if out in inp.parents:
        return "contains"
    return None


def _same_file_relation(out: Path, inp: Path) -> str | None:
    """:func:`_relation` by file identity (``os.path.samefile``) of the paths that exist: catches what names
    do not — a case-insensitive file system (``DS`` and ``ds``), hard links."""
    def chain(p: Path) -> list[Path]:
        return [q for q in (_abs(p), *_abs(p).parents) if q.exists()]

    if not inp.exists():
        return None
    for k, q in enumerate(chain(out)):
        if os.path.samefile(q, inp):
            return "is" if k == 0 and q == _abs(out) else "sits inside"
    if out.exists():
        for q in chain(inp)[1:]:
            if os.path.samefile(q, out):
                return "contains"
    return None


def _inputs(inputs) -> list[tuple[Path, str]]:
    if inputs is None:
        return []
    if isinstance(inputs, Mapping):
        return [(Path(k), str(v)) for k, v in inputs.items()]
    if isinstance(inputs, (str, os.PathLike)):
        return [(Path(inputs), "an input")]
    out = []
    for x in inputs:
        if isinstance(x, tuple):
            out.append((Path(x[0]), str(x[1])))
        else:
            out.append((Path(x), "an input"))
    return out


def check_output(out, inputs: Mapping | Iterable | None = None, *, force: bool = False,
                 error: type[Exception] = OutputError, force_flag: str = "--force") -> Path:
    """Refuse an output path that would lose data or fail late; return it as a :class:`~pathlib.Path`.

    Args:
        out: the output folder to be written (or replaced, with ``force``).
        inputs: what the command reads: ``{path: "the dataset folder", ...}`` or paths. The output must not be an
            input, contain one (replacing it would delete the input) or sit inside one (it would write into an
            input). Compared both as written and with symbolic links resolved.
        force: an existing ``out`` may be replaced.
        error: the exception class raised (the caller's ``ValueError`` subclass).
        force_flag: how the caller spells "replace", for the message (``--force``, ``overwrite=True``).

    Raises:
        ``error``: the output overlaps an input, exists without ``force``, has a file where its folder should be,
        or its folder cannot be written.
    """
    if isinstance(out, str) and not out.strip():
        raise error("the output path is empty; give the folder to write, e.g. --out results/")
    out = Path(out)
    if out.name in ("", ".", ".."):
        raise error(f"{out}: name a new folder to write (e.g. {os.path.join(os.fspath(out), 'out')}), not "
                    f"'{out}' itself")
    for inp, what in _inputs(inputs):
        rel = _relation(_abs(out), _abs(inp)) or _relation(_real(out), _real(inp)) or _same_file_relation(out, inp)
        if rel is not None:
            harm = "writing there would change it" if rel == "sits inside" else "replacing it would delete it"
            raise error(f"{out}: the output {rel} {what} {inp}, an input: {harm}; choose an output folder outside "
                        f"every input")
    if out.exists() or out.is_symlink():
        if not force:
            kind = "folder" if out.is_dir() else "file"
            raise error(f"{out}: the output {kind} already exists; choose another folder or pass {force_flag} to "
                        f"replace it")
    # the nearest folder that exists: the output's parent, or the ancestor its parents will be created in
    anchor = out.parent
    while not (anchor.exists() or anchor.is_symlink()) and anchor != anchor.parent:
        anchor = anchor.parent
    if not anchor.is_dir():
        raise error(f"{out}: {anchor} is a file, not a folder; choose an output path in a folder")
    try:
        probe = tempfile.mkdtemp(prefix=f".{out.name}.probe-", dir=anchor)
        os.rmdir(probe)
    except OSError as exc:
        raise error(f"{out}: cannot write in {anchor} ({exc.strerror or exc}); choose an output in a folder you "
                    f"can write, or fix its permissions") from None
    return out


def os_error_message(exc: OSError, out=None, tmp=None) -> str:
    """One line for an ``OSError``: the path it names (a temporary path shown as the output), what failed, a fix."""
    name = exc.filename if exc.filename is not None else out
    text = os.fspath(name) if name is not None else ""
    if tmp is not None and out is not None:
        text = text.replace(os.fspath(tmp), os.fspath(out))
    what = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        fix = "free some space or choose an output on another disk"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        fix = "choose an output in a folder you can write, or fix its permissions"
    else:
        fix = "check the path and try again"
    where = f"{text}: " if text else ""
    tail = f" (nothing was written to {out})" if out is not None else ""
    return f"{where}{what}; {fix}{tail}"


def _remove(path: Path) -> None:
    """Remove a file, a link or a folder tree, making read-only folders writable where that stops the removal."""
    if path.is_symlink() or not path.is_dir():
        path.unlink()
        return

    def retry(func, p, _exc_info):
        parent = os.path.dirname(p)
        try:
            os.chmod(parent, stat.S_IMODE(os.stat(parent).st_mode) | stat.S_IRWXU)
            if os.path.isdir(p) and not os.path.islink(p):
                os.chmod(p, stat.S_IMODE(os.stat(p).st_mode) | stat.S_IRWXU)
        except OSError:
            pass
        func(p)

    if sys.version_info >= (3, 12):
        shutil.rmtree(path, onexc=retry)
    else:
        shutil.rmtree(path, onerror=retry)


def _discard(path: Path) -> None:
    """Remove what a replaced output left; warn, naming it, when that is impossible; finish even when interrupted."""
    interrupted = None
    for _ in range(3):
        try:
            _remove(path)
            break
        except KeyboardInterrupt as exc:  # finish the clean-up, then pass the interrupt on
            interrupted = exc
        except OSError as exc:
            warnings.warn(f"{path}: the previous output was replaced but could not be removed ({exc}); delete it",
                          OutputWarning, stacklevel=4)
            break
    if interrupted is not None:
        raise interrupted


def _swap(tmp: Path, out: Path, force: bool, error, force_flag: str) -> None:
    if not (out.exists() or out.is_symlink()):
        os.replace(tmp, out)
        return
    if not force:
        raise error(f"{out}: appeared while writing and was left alone; pass {force_flag} to replace it")
    old = out.with_name(f".{out.name}.old-{os.getpid()}-{secrets.token_hex(4)}")
    os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        os.replace(old, out)
        raise
    _discard(old)


@contextmanager
def atomic_folder(out, *, force: bool = False, error: type[Exception] = OutputError,
                  force_flag: str = "--force") -> Iterator[Path]:
    """Write the folder ``out`` atomically: yield a temporary folder next to it, then move that into place.

    On leaving the ``with`` block normally the temporary folder gets the umask's permissions and replaces
    ``out`` (with ``force``; the previous output is removed, nothing hidden is left behind). On any exception
    (a ``KeyboardInterrupt`` too) it is removed and ``out`` is as it was. An ``OSError`` is raised as ``error``
    with one line naming the output path; other errors naming the temporary folder are reworded to name ``out``.
    """
    out = Path(out)
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=parent))
    except OSError as exc:
        raise error(os_error_message(exc, out)) from None
    try:
        yield tmp
        apply_umask(tmp)
        _swap(tmp, out, force, error, force_flag)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise error(os_error_message(exc, out, tmp)) from None
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, Exception) and len(exc.args) == 1 and isinstance(exc.args[0], str):
            exc.args = (exc.args[0].replace(os.fspath(tmp), os.fspath(out)),)
        raise


def jsonable(x):
    """``x`` with tensors, arrays, numpy scalars and paths made JSON types, and non-finite floats ``None``."""
    if isinstance(x, torch.Tensor):
        return jsonable(x.detach().cpu().double().tolist())
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        return jsonable(x.item())
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def json_text(x, indent: int | None = 2) -> str:
    """Strict JSON of ``x`` (:func:`jsonable`; other objects as ``str``): never ``NaN`` or ``Infinity``."""
    return json.dumps(jsonable(x), indent=indent, allow_nan=False, default=str)


class NA(float):
    """A non-finite number that formats as ``n/a`` whatever the format spec (``f"{x:.1f}"`` → ``n/a``)."""

    def __format__(self, spec: str) -> str:
        return "n/a"

    def __str__(self) -> str:
        return "n/a"

    __repr__ = __str__


def na_floats(x):
    """``x`` (dicts, lists, tuples of numbers) with every non-finite float replaced by :class:`NA`, for printing."""
    if isinstance(x, Mapping):
        return {k: na_floats(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [na_floats(v) for v in x] if isinstance(x, list) else tuple(na_floats(v) for v in x)
    if isinstance(x, float) and not math.isfinite(x):
        return NA(x)
    return x


_NAN_TOKEN = re.compile(r"(?<![\w.-])[-+]?nan%?(?![\w-])")


def na_text(text: str) -> str:
    """``text`` with each formatted NaN (``nan``, ``nan%``; Python's lower-case spelling, not the prose "NaN") as
    ``n/a``, and a range of two of them (``n/a–n/a``) as one."""
    return _NAN_TOKEN.sub("n/a", text).replace("n/a–n/a", "n/a")
