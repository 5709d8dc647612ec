"""Detection options shared by ``detect``, ``process`` and ``batch`` (one text, one default)."""

from __future__ import annotations

import click


def detection_options(f):
    """``--polarity``, ``--mirror``, ``--rotate`` and ``--scene`` (shown in that order)."""
    f = click.option(
        "--scene", type=click.Choice(["auto", "opening", "joint"]), default="auto",
        show_default=True, help="The scene under each cross: opening (the grey opening's "
        "estimate, fastest), joint (estimated jointly with the cross: about 3-5x the time, "
        "more accurate over sharp-edged scene content), auto (joint where the scene has sharp "
        "edges at the crosses).")(f)
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
