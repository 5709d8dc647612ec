"""``softplot cameras``: the built-in certificate catalogue."""

from __future__ import annotations

import click

from softplot.camera import builtin_names, describe, load_camera, to_toml


@click.group("cameras", invoke_without_command=True)
@click.pass_context
def command(ctx: click.Context) -> None:
    """List the built-in camera certificates (`softplot cameras show NAME` prints one)."""
    if ctx.invoked_subcommand is None:
        for name in builtin_names():
            cam = load_camera(name)
            grid = (
                f"reseau {cam.reseau.rows}x{cam.reseau.cols}"
                if cam.reseau is not None
                else f"{len(cam.fiducials)} fiducials"
            )
            click.echo(
                f"{name:<20} {cam.kind:<13} c={cam.c:7.2f} mm  "
                f"{cam.format_mm[0]:.0f}x{cam.format_mm[1]:.0f} mm  {grid}"
            )


@command.command("show")
@click.argument("name")
@click.option("--toml", "as_toml", is_flag=True, help="Print the certificate as TOML.")
def show(name: str, as_toml: bool) -> None:
    """Print one certificate: NAME is a built-in name or a TOML file."""
    cam = load_camera(name)
    click.echo(to_toml(cam) if as_toml else describe(cam))
