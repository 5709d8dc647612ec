"""Detection options shared by ``detect``, ``process`` and ``batch`` (one text, one default)."""

from __future__ import annotations

import click


def _grid_part(ctx, param, value):
    """``--grid-part`` text, checked and written the one way (``cols=A:B,rows=C:D``); a bad
    text is a usage error (one line, exit 2)."""
    if value is None:
        return None
    from softplot.errors import SoftplotError
    from softplot.marks.detect import format_grid_part

    try:
        return format_grid_part(value)
    except SoftplotError as exc:
        raise click.BadParameter(str(exc).removeprefix("--grid-part "), ctx, param) from None


def detection_options(f):
    """``--polarity``, ``--mirror``, ``--rotate``, ``--grid-part`` and ``--scene`` (shown in
    that order)."""
    f = click.option(
        "--scene", type=click.Choice(["auto", "opening", "joint"]), default="auto",
        show_default=True, help="The scene under each cross: opening (the grey opening's "
        "estimate, fastest), joint (estimated jointly with the cross: about 3-5x the time, "
        "more accurate over sharp-edged scene content), auto (joint where the scene has sharp "
        "edges at the crosses).")(f)
    f = click.option(
        "--grid-part", "grid_part", default=None, callback=_grid_part, metavar="cols=A:B,rows=C:D",
        help="The part of the reseau the scan shows, when you know it: columns A to B-1 and "
        "rows C to D-1 of the certificate's grid (e.g. cols=0:12 for the left half of a "
        "23-column grid; either may be left out). Without it any part of at least 3x3 crosses "
        "is found and named from the format's edges in the scan.")(f)
    f = click.option(
        "--rotate", type=click.Choice(["0", "90", "180", "270"]), default="0",
        show_default=True, help="The photo is turned this much counter-clockwise in the scan, "
        "degrees (residual rotations of +-20 degrees are found automatically).")(f)
    f = click.option(
        "--mirror", is_flag=True, default=False,
        help="The scan is mirrored left-right (scanned through the film base, emulsion down); "
        "applied before --rotate. Results stay in the scan's own pixels.")(f)
    f = click.option(
        "--polarity", type=click.Choice(["auto", "positive", "negative"]), default="auto",
        show_default=True,
        help="positive: dark marks (print); negative: bright marks (film negative).")(f)
    return f
