"""``softplot import``: other programs' projects into a bundle project folder."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.errors import SoftplotError


def _write(data, out) -> None:
    from softplot.orientation.bundle_io import write_project

    root = Path(out)
    if root.exists() and not root.is_dir():
        raise SoftplotError(f"--out {out} is a file, not a folder")
    write_project(root, data)
    click.echo(
        f"wrote {root}: {len(data.cameras)} camera(s), {len(data.photo_names)} photos, "
        f"{len(data.point_names)} points, {data.obs_photo.size} image observations"
    )


def _pixel_option(f):
    f = click.option(
        "--sigma-px",
        type=float,
        default=1.0,
        show_default=True,
        help="Standard error of the image points, pixels.",
    )(f)
    return click.option(
        "--pixel-size-um",
        type=float,
        default=1.0,
        show_default=True,
        help="Pixel size giving film mm (the geometry does not depend on it).",
    )(f)


@click.group("import")
def command() -> None:
    """Import a project of another program into a bundle project folder (docs/bundle.md)."""


@command.command("colmap")
@click.argument("sparse_dir", type=click.Path(file_okay=False))
@click.option("--out", "out", required=True, type=click.Path(), help="Project folder to write.")
@_pixel_option
def colmap(sparse_dir, out, pixel_size_um, sigma_px) -> None:
    """COLMAP text model SPARSE_DIR (cameras.txt, images.txt, points3D.txt)."""
    from softplot.orientation.interchange.colmap import read_colmap

    _write(read_colmap(sparse_dir, pixel_size_um, sigma_px), out)


@command.command("bal")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(), help="Project folder to write.")
@_pixel_option
def bal(file, out, pixel_size_um, sigma_px) -> None:
    """Bundle Adjustment in the Large problem FILE."""
    from softplot.orientation.interchange.bal import read_bal_project

    _write(read_bal_project(file, pixel_size_um, sigma_px), out)


@command.command("photomodeler")
@click.argument("export_file", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(), help="Project folder to write.")
@click.option(
    "--control",
    "control",
    type=click.Path(dir_okay=False),
    help="Control points ID X Y Z [SX SY SZ] replacing the export's (std 0: fixed).",
)
@click.option(
    "--image-size",
    nargs=2,
    type=int,
    default=None,
    help="Image WIDTH HEIGHT in pixels (when line 2 of the export has none).",
)
def photomodeler(export_file, out, control, image_size) -> None:
    """PhotoModeler text export EXPORT_FILE (the format DBAT reads)."""
    from softplot.orientation.interchange.photomodeler import read_photomodeler

    _write(read_photomodeler(export_file, image_size, control), out)
