"""``softplot motors``: the simulated GRBL controller and a few instrument commands."""

from __future__ import annotations

import time

import click


@click.group("motors")
def command() -> None:
    """Motor layer: simulate a GRBL 1.1 controller on a pty, query or move an instrument."""


@command.command("simulate")
@click.option(
    "--faults",
    default="",
    help="Faults to inject, comma-separated: "
    "disconnect@WHEN, alarm@WHEN, lost-steps=K@WHEN, slow=SECONDS "
    "(WHEN = moveN or Ts), e.g. 'slow=0.2,alarm@move3'.",
)
@click.option(
    "--link",
    type=click.Path(dir_okay=False),
    default=None,
    help="Also keep a symlink at this path pointing at the current pty "
    "(stable across a simulated disconnect).",
)
@click.option(
    "--time-scale",
    type=float,
    default=1.0,
    show_default=True,
    help="Simulated motion runs this many times faster than real time.",
)
@click.option("--no-homing", is_flag=True, help="Start with $22=0 (no homing, no alarm lock).")
@click.option(
    "--duration",
    type=float,
    default=None,
    help="Stop after this many seconds (default: until Ctrl-C).",
)
def simulate(faults, link, time_scale, no_homing, duration):
    """Serve a simulated GRBL 1.1 controller on a pseudo-terminal; prints the device path."""
    from softplot.motors.simulator import GrblSimulator

    sim = GrblSimulator(
        faults, link=link, time_scale=time_scale, settings={22: 0} if no_homing else None
    )
    path = sim.start()
    click.echo(path)
    if link:
        click.echo(f"# pty {sim.slave_path}", err=True)
    t_end = None if duration is None else time.monotonic() + duration
    try:
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()


def _open(port, timeout):
    from softplot.motors.grbl import GrblMotors

    return GrblMotors(port, timeout=timeout, configure=False)


@command.command("status")
@click.argument("port")
@click.option("--timeout", type=float, default=2.0, show_default=True,
              help="Seconds to wait for the controller's answer.")
def status(port, timeout):
    """Print the controller's state and DX, DY (instrument mm) on PORT."""
    with _open(port, timeout) as m:
        st = m.status()
        dx, dy = m.position()
        click.echo(f"{st.state} DX={dx:.3f} DY={dy:.3f} (MPos {st.mpos[0]:.3f},{st.mpos[1]:.3f})")


@command.command("move")
@click.argument("port")
@click.argument("dx", type=float)
@click.argument("dy", type=float)
@click.option("--timeout", type=float, default=30.0, show_default=True,
              help="Seconds to wait for the move to end.")
def move(port, dx, dy, timeout):
    """Move the secondary carriage to DX, DY (instrument mm) and wait."""
    with _open(port, timeout) as m:
        m.move_to(dx, dy, timeout=timeout)
        px, py = m.position()
        click.echo(f"DX={px:.3f} DY={py:.3f}")
