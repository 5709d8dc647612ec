"""The ``softplot`` command (click). Thin: parses arguments, calls the library, prints.

Each sub-command lives in its own module of this package and exposes a click command or
group named ``command``; :data:`COMMANDS` lists them. Bad input raises
:class:`softplot.errors.SoftplotError`, which :func:`main` turns into one line on stderr and
exit code 2 - never a traceback.
"""

from __future__ import annotations

import importlib
import sys

import click

from softplot import __version__
from softplot.errors import SoftplotError

#: sub-command modules of :mod:`softplot.cli`, each exposing ``command``
COMMANDS = [
    "cameras",
    "synth",
    "demo",
    "info",
    "detect",
    "restitute",
    "motors",
    "plot",
    "resect",
    "intersect",
    "relor",
    "absor",
    "pc",
    "correct",
    "process",
    "batch",
    "bundle",
    "calibrate",
    "triangulate",
    "import_",
    "export",
    "view",
    "match",
    "epipolar",
]


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="softplot")
def cli() -> None:
    """softplot - digital softcopy plotter for scanned photogrammetric photographs."""


for _name in COMMANDS:
    cli.add_command(importlib.import_module(f"softplot.cli.{_name}").command)


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the CLI, turning :class:`SoftplotError` into exit code 2."""
    from softplot.runtime import tune_allocator

    tune_allocator()
    try:
        rv = cli.main(args=argv, prog_name="softplot", standalone_mode=False)
    except SoftplotError as exc:
        click.echo(f"softplot: error: {exc}", err=True)
        sys.exit(2)
    except click.exceptions.Abort:
        click.echo("softplot: aborted", err=True)
        sys.exit(1)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2 if exc.exit_code == 2 else exc.exit_code)
    except KeyboardInterrupt:
        click.echo("softplot: interrupted", err=True)
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)
