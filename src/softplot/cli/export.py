"""``softplot export``: a bundle project folder into another program's format."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.errors import SoftplotError


def _read(project):
    from softplot.orientation.bundle_init import initialize
    from softplot.orientation.bundle_io import read_project

    data = read_project(project)
    initialize(data)
    return data


@click.group("export")
def command() -> None:
    """Export a bundle project folder (its current values) to another program's format."""


@command.command("colmap")
@click.argument("project", type=click.Path(file_okay=False))
@click.argument("out", type=click.Path(file_okay=False))
def colmap(project, out) -> None:
    """PROJECT as a COLMAP text model in the folder OUT."""
    from softplot.orientation.interchange.colmap import write_colmap

    if Path(out).resolve() == Path(project).resolve():
        raise SoftplotError("OUT must differ from PROJECT")
    click.echo(f"wrote {write_colmap(_read(project), out)}")


@command.command("bal")
@click.argument("project", type=click.Path(file_okay=False))
@click.argument("out", type=click.Path(dir_okay=False))
def bal(project, out) -> None:
    """PROJECT as a Bundle Adjustment in the Large file OUT."""
    from softplot.orientation.interchange.bal import write_bal_project

    click.echo(f"wrote {write_bal_project(_read(project), out)}")
