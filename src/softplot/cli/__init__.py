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

#: the sub-commands: (name, module of this package exposing ``command``, one-line help).
#: The help is repeated here so that ``softplot --help`` lists every command without importing
#: any of them (each pulls in NumPy, SciPy, OpenCV...); tests/test_cli_lazy.py checks that it
#: is each command's own first help line.
COMMAND_TABLE: list[tuple[str, str, str]] = [
    ("cameras", "cameras",
     "List the built-in camera certificates (`softplot cameras show NAME` prints one)."),
    ("synth", "synth",
     "Render synthetic scans of CAMERA's film frame into OUTDIR, each with "
     "<stem>.truth.json."),
    ("demo", "demo",
     "Synthetic Rollei 6006 stereo pair: scans -> marks -> correction -> orientation -> "
     "contours -> DXF, GeoJSON, HTML; prints the accuracy reached against the truth."),
    ("info", "info",
     "Print size, bit depth, channels and dpi of each SCAN (TIFF, PNG, JPEG, camera RAW)."),
    ("detect", "detect",
     "Detect and measure the reseau crosses or fiducial marks of SCAN..."),
    ("restitute", "restitute",
     "Restitute points of an oriented stereo pair in one of the four STEREOBIT modes."),
    ("motors", "motors",
     "Motor layer: simulate a GRBL 1.1 controller on a pty, query or move an instrument."),
    ("plot", "plot",
     "Plotting sessions in a project folder: operator input from CSV, journal, export."),
    ("resect", "resect",
     "Space resection: X0, Y0, Z0, omega, phi, kappa of one photo from >= 3 control "
     "points."),
    ("intersect", "intersect",
     "Space intersection of two or more rays per point, with the covariance of each point."),
    ("relor", "relor",
     "Relative orientation by the coplanarity condition, started from the essential "
     "matrix."),
    ("absor", "absor",
     "Absolute orientation: object = scale * M^T * model + T, from >= 3 control points."),
    ("pc", "pc",
     "Projection centres of analogue plotters (Birardi, ISP Hamburg 1980)."),
    ("correct", "correct",
     "Film-deformation correction: pixel -> film / photo mm, method comparison, "
     "resampling."),
    ("process", "process",
     "Detect marks, cross-validate film corrections and check quality of SCANS."),
    ("batch", "batch",
     "Process every scan matched by PATTERNS (quoted globs, ** allowed) on "
     "dask.distributed."),
    ("bundle", "bundle",
     "Bundle adjustment of PROJECT (folder, see docs/bundle.md) or of a BAL file (--bal)."),
    ("calibrate", "calibrate",
     "Calibrate the camera of PROJECT (a test field: control = target coordinates)."),
    ("triangulate", "triangulate",
     "Aerial triangulation of PROJECT; the report gives the RMS at check points."),
    ("import", "import_",
     "Import a project of another program into a bundle project folder (docs/bundle.md)."),
    ("export", "export",
     "Export a bundle project folder (its current values) to another program's format."),
    ("view", "view",
     "Open plotting SESSION in the browser: stereo view, floating mark, plotting."),
    ("match", "match",
     "Tie points of a stereo pair (two scans) or a block (more: a bundle project)."),
    ("epipolar", "epipolar",
     "Normalised images of the oriented pair of a plotting SESSION folder."),
    ("dsm", "dsm",
     "Dense surface of the oriented pair of a plotting SESSION, with automatic contours."),
]

#: sub-command modules of :mod:`softplot.cli`, each exposing ``command``.
#: A new command is one row of COMMAND_TABLE, not a line here.
COMMANDS = [module for _, module, _ in COMMAND_TABLE]


class LazyGroup(click.Group):
    """A click group that imports a sub-command's module only when that command runs (or its
    own ``--help`` is asked for); the group's ``--help`` lists the commands from
    :data:`COMMAND_TABLE` without importing them."""

    _table = {name: (module, short) for name, module, short in COMMAND_TABLE}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return [name for name, _, _ in COMMAND_TABLE]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self._table:
            return None
        return importlib.import_module(f"softplot.cli.{self._table[cmd_name][0]}").command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        limit = formatter.width - 6 - max(len(name) for name, _, _ in COMMAND_TABLE)
        rows = []
        for name, _, short in COMMAND_TABLE:
            text = click.Command(name, help=short).get_short_help_str(limit)
            rows.append((name, text))
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(
    cls=LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.version_option(__version__, prog_name="softplot")
def cli() -> None:
    """softplot - digital softcopy plotter for scanned photogrammetric photographs."""


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the CLI, turning :class:`SoftplotError` into exit code 2."""
    from softplot.runtime import tune_allocator

    tune_allocator()
    try:
        rv = cli.main(args=argv, prog_name="softplot", standalone_mode=False)
    except SoftplotError as exc:
        click.echo(f"softplot: error: {exc}", err=True)
        sys.exit(2)
    except click.exceptions.Abort as exc:
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):  # Ctrl-C
            click.echo("softplot: interrupted", err=True)
            sys.exit(130)
        click.echo("softplot: aborted", err=True)
        sys.exit(1)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2 if exc.exit_code == 2 else exc.exit_code)
    except KeyboardInterrupt:
        click.echo("softplot: interrupted", err=True)
        sys.exit(130)
    sys.exit(rv if isinstance(rv, int) else 0)
