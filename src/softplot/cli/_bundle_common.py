"""Shared plumbing of the bundle, calibrate and triangulate commands (no numerics)."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from softplot.errors import SoftplotError


def output_options(plots_help: str = "Write residual plots (PNG) into this folder."):
    """The ``--json OUT``, ``--report OUT`` and ``--plots DIR`` options (in that order)."""

    def deco(f):
        f = click.option("--plots", "plots_dir", type=click.Path(file_okay=False), help=plots_help)(
            f
        )
        f = click.option(
            "--report",
            "report_out",
            type=click.Path(dir_okay=False),
            help="Write the text report to a file (else it is printed).",
        )(f)
        return click.option(
            "--json", "json_out", type=click.Path(dir_okay=False), help="Write results JSON."
        )(f)

    return deco


def emit_report(txt: str, report_out, *, newline: bool = False) -> None:
    """Write the text report to ``report_out`` (saying so on stderr), else print it.

    ``newline`` appends a final newline to the file.
    """
    if report_out:
        Path(report_out).write_text(txt + ("\n" if newline else ""), encoding="utf-8")
        click.echo(f"wrote {report_out}", err=True)
    else:
        click.echo(txt)


def emit_plots(res, plots_dir) -> None:
    """Write the residual plots of a bundle result into ``plots_dir`` (if given)."""
    if plots_dir:
        from softplot.orientation.bundle_report import write_plots

        for p in write_plots(res, plots_dir):
            click.echo(f"wrote {p}", err=True)


def apply_free(data, free) -> None:
    """Free the intrinsics named in ``free`` (sigma inf) of every camera; fix the others.

    A parameter not in ``free`` keeps its certificate sigma unless it was free (then 0: fixed).
    ``free`` None leaves the cameras as cameras.toml says.
    """
    if free is None:
        return
    from softplot.orientation.bundle import INTRINSICS

    for c in data.cameras:
        c.sigma[:] = [
            np.inf if n in free else (0.0 if np.isinf(s) else s)
            for n, s in zip(INTRINSICS, c.sigma, strict=True)
        ]
        c.choose_model()


def refuse_existing_truth(root: Path) -> None:
    """--make-synthetic never overwrites an existing truth.json."""
    if (root / "truth.json").exists():
        raise SoftplotError(f"{root / 'truth.json'} exists; not overwriting")


def lm_progress(desc: str):
    """An LMOptions.progress callback drawing a tqdm bar on stderr; returns (callback, close)."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="it", leave=False, disable=None)

    def cb(rec):
        bar.update(1)
        bar.set_postfix(cost=f"{rec['cost']:.6g}")

    return cb, bar.close


def guard_output(out, inputs) -> Path | None:
    """Refuse to write over an input file."""
    if out is None:
        return None
    p = Path(out).resolve()
    for i in inputs:
        if i is not None and Path(i).exists() and Path(i).resolve() == p:
            raise SoftplotError(f"refusing to overwrite the input file {out}")
    return p


def project_inputs(folder) -> list:
    root = Path(folder)
    from softplot.orientation.bundle_io import FILES

    return [root / f for f in FILES]


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else float(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def write_json(obj, path) -> None:
    Path(path).write_text(json.dumps(_clean(obj), indent=1) + "\n", encoding="utf-8")
    click.echo(f"wrote {path}", err=True)


def parse_free(text: str | None):
    if text is None:
        return None
    from softplot.orientation.bundle import INTRINSICS

    names = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [n for n in names if n not in INTRINSICS]
    if bad:
        raise SoftplotError(f"--free: unknown parameter(s) {bad}; use {', '.join(INTRINSICS)}")
    return names


def write_residuals_csv(res, path) -> None:
    """Every image observation's residual of a bundle result as CSV (header row)."""
    import csv

    t = res.residual_table()
    keys = list(t)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(keys)
        for i in range(len(t["photo"])):
            row = []
            for k in keys:
                v = t[k][i]
                if isinstance(v, (float, np.floating)):
                    row.append("" if not np.isfinite(v) else f"{float(v):.6g}")
                elif isinstance(v, (bool, np.bool_)):
                    row.append(int(v))
                else:
                    row.append(v)
            w.writerow(row)
    click.echo(f"wrote {path}", err=True)
