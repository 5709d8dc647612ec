"""One rule for every output file of every command.

* An output is never one of the command's inputs: refused, even with ``--overwrite``.
* An existing output is refused unless ``--overwrite`` is given.
* A missing parent folder is created; one that cannot be (a file in the way, no permission)
  is refused in one line.

All checks run before any work, so a refused run leaves every file as it was.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import click

from softplot.errors import SoftplotError

__all__ = ["guard_outputs", "same_file", "overwrite_option", "OVERWRITE_KEY"]

OVERWRITE_KEY = "softplot_overwrite"


def same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name the same file (existing or not)."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except OSError:
        return False


def _make_parent(o: Path) -> None:
    parent = o.parent
    for p in (parent, *parent.parents):
        if p.exists() and not p.is_dir():
            raise SoftplotError(f"{o}: cannot create its folder: {p} is a file")
        if p.exists():
            break
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SoftplotError(f"{o}: cannot create its folder {parent}: "
                            f"{exc.strerror or exc}") from None


def guard_outputs(outputs: Iterable, inputs: Iterable = (), overwrite: bool | None = None) -> None:
    """Apply the output rule to ``outputs`` (paths or None) against ``inputs``.

    ``overwrite`` None: taken from the command's ``--overwrite`` (:func:`overwrite_option`).
    Raises :class:`SoftplotError` (one line naming the file) before anything is written.
    """
    if overwrite is None:
        ctx = click.get_current_context(silent=True)
        overwrite = bool(ctx and ctx.find_root().meta.get(OVERWRITE_KEY))
    outs = [Path(o) for o in outputs if o is not None]
    ins = [Path(i) for i in inputs if i is not None]
    for o in outs:
        for i in ins:
            if same_file(o, i):
                raise SoftplotError(f"{o}: is an input file; refusing to overwrite it")
        if o.is_dir():
            raise SoftplotError(f"{o}: is a folder, not a file")
        if o.exists() and not overwrite:
            raise SoftplotError(f"{o}: exists; refusing to overwrite (use --overwrite)")
    for o in outs:
        _make_parent(o)


def _store(ctx, _param, value):
    ctx.find_root().meta[OVERWRITE_KEY] = bool(value)
    return value


def overwrite_option(f):
    """``--overwrite``: replace existing outputs (never an input). Read by
    :func:`guard_outputs`; not passed to the command function."""
    return click.option("--overwrite", is_flag=True, expose_value=False, callback=_store,
                        is_eager=True,
                        help="Replace existing output files (an input file is never replaced).")(f)
