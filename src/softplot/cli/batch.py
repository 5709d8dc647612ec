"""``softplot batch 'GLOB'... --camera C --out DIR [--workers N] [--scheduler ADDRESS]``.

Many scans through dask.distributed (:mod:`softplot.pipeline.batch`): a LocalCluster of N
single-threaded worker processes by default, an existing cluster by its scheduler address.
At most 2 tasks per worker are in flight (bounded memory); a failing scan is recorded with
its error and the rest go on; a rerun skips scans whose ``<stem>.json`` is complete and was
made with the same settings, redoes missing or half-written ones, and refuses results made with
other settings unless --overwrite (which recomputes every scan). Ends with the summary table;
writes ``summary.csv`` and ``report.html``. Ctrl-C stops the run: the summary and report
cover what finished, exit code 130. Exit code otherwise: 0 every scan done or skipped; 1 some
failed; 2 bad input.
"""

from __future__ import annotations

from pathlib import Path

import click

from softplot.cli.process import common_options, task_kwargs
from softplot.errors import SoftplotError


@click.command("batch")
@click.argument("patterns", nargs=-1, required=True)
@common_options
@click.option("--workers", type=click.IntRange(1, 256), default=2, show_default=True,
              help="Worker processes of the local cluster.")
@click.option("--scheduler", default=None,
              help="Address of an existing dask scheduler (tcp://host:8786) instead.")
def command(patterns, camera, out, flatten, method, pixel_size, dpi, polarity, rotate, mirror,
            grid_part, scene, quiet, overwrite, workers, scheduler) -> int:
    """Process every scan matched by PATTERNS (quoted globs, ** allowed) on dask.distributed."""
    from softplot.pipeline.batch import check_stems, expand, run_batch
    from softplot.pipeline.process import load_results, process_scan, write_report

    scans = expand(patterns)
    if not scans:
        raise SoftplotError(f"no scan matches {' '.join(patterns)}")
    check_stems(scans)
    kw = task_kwargs(camera, method, flatten, pixel_size, dpi, polarity, rotate, scene, mirror,
                     grid_part)
    rep = run_batch(scans, Path(out), process_scan, kw, workers=workers, scheduler=scheduler,
                    progress=not quiet, overwrite=overwrite)
    report = write_report(Path(out) / "report.html", load_results(out, rep.rows),
                          title="softplot batch")
    click.echo(rep.table())
    click.echo(f"results: {Path(out)}/<scan>.json, {Path(out) / 'summary.csv'}, {report}")
    if rep.interrupted:
        click.echo(f"softplot: interrupted; {rep.interrupted} scan(s) not finished - run the "
                   "same command again to resume", err=True)
        return 130
    return 1 if rep.failed else 0
