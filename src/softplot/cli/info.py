"""``softplot info SCAN...``: size, bit depth, channels and dpi of scan files."""

from __future__ import annotations

import click

from softplot.errors import SoftplotError
from softplot.io import load_scan


@click.command("info")
@click.argument("scans", nargs=-1, required=True, type=click.Path(dir_okay=True))
@click.pass_context
def command(ctx: click.Context, scans: tuple[str, ...]) -> None:
    """Print size, bit depth, channels and dpi of each SCAN (TIFF, PNG, JPEG, camera RAW).

    A file that cannot be read gets one error line on stderr; the others are still
    reported, and the command then exits with code 2.
    """
    failed = 0
    for path in scans:
        try:
            scan = load_scan(path)
        except SoftplotError as exc:
            click.echo(f"softplot: error: {exc}", err=True)
            failed += 1
            continue
        click.echo(f"{path}: {scan.summary()}")
    if failed:
        ctx.exit(2)
