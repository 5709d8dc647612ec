"""``softplot demo``: the whole chain on a synthetic Rollei 6006 stereo pair.

Renders two scans on the fly, detects the reseau, corrects the film, orients the pair,
restitutes contours through the virtual motors and writes DXF, GeoJSON and an HTML report;
prints the accuracy reached against the synthetic truth. See :mod:`softplot.pipeline.demo`.
"""

from __future__ import annotations

import click


@click.command("demo")
@click.option("--out", "out", default="softplot-demo", show_default=True,
              type=click.Path(file_okay=False),
              help="Output folder. A folder holding other files is not touched: the demo "
                   "then writes into a fresh sub-folder softplot-demo[-N].")
@click.option("--dpi", default=800.0, show_default=True, type=click.FloatRange(300, 1200),
              help="Scan resolution of the synthetic pair (lower is faster).")
@click.option("--interval", default=10.0, show_default=True, type=click.FloatRange(1, 50),
              help="Contour interval, m.")
@click.option("--no-scans", is_flag=True, help="Do not write the two scans and detections.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def command(out: str, dpi: float, interval: float, no_scans: bool, quiet: bool) -> None:
    """Synthetic Rollei 6006 stereo pair: scans -> marks -> correction -> orientation ->
    contours -> DXF, GeoJSON, HTML; prints the accuracy reached against the truth."""
    from softplot.pipeline.demo import DemoConfig, run_demo

    res = run_demo(out, DemoConfig(dpi=dpi, interval=interval), progress=not quiet,
                   write_scans=not no_scans)
    click.echo(f"softplot demo: Rollei 6006 stereo pair, {dpi:.0f} dpi, photo scale "
               f"1:{res.scale:.0f}, {res.seconds:.1f} s")
    click.echo("accuracy against the synthetic truth (image coordinates of tie, control and "
               "check points are their exact truth pixels, standing in for the operator):")
    click.echo(res.summary())
    click.echo("outputs:")
    for k, v in res.outputs.items():
        click.echo(f"  {k:<16} {v}")
