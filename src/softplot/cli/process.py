"""``softplot process SCAN... --camera C --out DIR [--flatten]``: detection, film correction
and quality control of scans, one after the other in this process.

Writes ``DIR/<stem>.json`` per scan (atomic, ``"complete": true``), ``DIR/summary.csv``,
``DIR/report.html`` (self-contained) and, with ``--flatten``, ``DIR/<stem>.film.tif``.
Exit code: 0 every scan done; 1 at least one scan failed (recorded in the summary with its
error, the others are done); 2 bad input (no scan, unknown camera, bad option).
Numerics in :mod:`softplot.pipeline.process`.
"""

from __future__ import annotations

from pathlib import Path

import click

from softplot.cli._detect_opts import detection_options
from softplot.errors import SoftplotError


def common_options(f):
    """Options shared by ``process`` and ``batch`` (applied bottom-up: --camera shows first)."""
    from softplot.cli.correct import METHOD_NAMES

    f = click.option("--quiet", is_flag=True, help="No progress bar.")(f)
    f = click.option("--overwrite", is_flag=True,
                     help="Recompute and replace existing results in --out (without it an "
                     "existing result is refused, or resumed by batch when made with the same "
                     "settings).")(f)
    f = detection_options(f)
    f = click.option("--dpi", type=click.FloatRange(min=0, min_open=True), default=None,
                     help="Scan resolution when the files do not say.")(f)
    f = click.option("--pixel-size", "pixel_size", type=float, default=None,
                     help="Pixel size of flattened images, um (default: the scan's).")(f)
    f = click.option("--method", type=click.Choice(METHOD_NAMES), default=None,
                     help="Correction method to apply (default: the cross-validation's "
                          "recommendation).")(f)
    f = click.option("--flatten", is_flag=True,
                     help="Also write film-flattened images <stem>.film.tif.")(f)
    f = click.option("--out", "out", required=True, type=click.Path(file_okay=False),
                     help="Output folder (created).")(f)
    f = click.option("--camera", "camera", required=True,
                     help="Camera certificate: built-in name or TOML path.")(f)
    return f


def task_kwargs(camera, method, flatten, pixel_size, dpi, polarity="auto", rotate="0",
                scene="auto", mirror=False, grid_part=None) -> dict:
    from softplot.camera import load_camera

    load_camera(camera)  # bad camera: one line, exit 2, before any work
    if pixel_size is not None and not pixel_size > 0:
        raise SoftplotError(f"--pixel-size must be > 0 um, got {pixel_size}")
    return {"camera": camera, "method": method, "flatten": flatten,
            "pixel_size_um": pixel_size, "dpi": dpi, "polarity": polarity,
            "rotate": float(rotate), "mirror": bool(mirror), "scene": scene,
            "grid_part": grid_part}


@click.command("process")
@click.argument("scans", nargs=-1, required=True, type=click.Path(dir_okay=False))
@common_options
def command(scans, camera, out, flatten, method, pixel_size, dpi, polarity, rotate, mirror,
            grid_part, scene, quiet, overwrite) -> int:
    """Detect marks, cross-validate film corrections and check quality of SCANS.

    Exit code 0 when every scan is done, 1 when some failed (see summary.csv), 2 on bad
    input.
    """
    from softplot.pipeline.batch import check_stems
    from softplot.pipeline.process import load_results, process_scans, write_report

    paths = [Path(s) for s in scans]
    for p in paths:
        if not p.is_file():
            raise SoftplotError(f"{p}: scan file not found")
    check_stems(paths)
    kw = task_kwargs(camera, method, flatten, pixel_size, dpi, polarity, rotate, scene, mirror,
                     grid_part)
    rep = process_scans(paths, out, progress=not quiet, overwrite=overwrite, **kw)
    report = write_report(Path(out) / "report.html", load_results(out, rep.rows))
    click.echo(rep.table())
    click.echo(f"results: {Path(out)}/<scan>.json, {Path(out) / 'summary.csv'}, {report}")
    return 1 if rep.failed else 0
