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
    "disconnect@WHEN, alarm@WHEN, lost-steps=K@WHEN, reboot@WHEN, power-loss@WHEN, "
    "homing-fail[=8|9], slow=SECONDS (WHEN = moveN or Ts), e.g. 'slow=0.2,alarm@move3'.",
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
    help="The controller runs this many times faster than real time (motion, dwells, "
    "homing, the 0.5 s alarm pause, byte timing); 0.5 = a controller at half clock.",
)
@click.option(
    "--homing",
    is_flag=True,
    help="Start with $22=1 (homing enabled: alarm-locked at power-up until $H). "
    "Default: the firmware's own $22=0.",
)
@click.option(
    "--soft-limits",
    is_flag=True,
    help="Start with $20=1 and $22=1 (soft limits: machine travel [-$130, 0] mm).",
)
@click.option(
    "--encoders",
    is_flag=True,
    help="Answer the $ENC encoder read-out extension (instruments with carriage "
    "encoders); a stock controller answers error:2.",
)
@click.option(
    "--duration",
    type=float,
    default=None,
    help="Stop after this many seconds (default: until Ctrl-C).",
)
def simulate(faults, link, time_scale, homing, soft_limits, encoders, duration):
    """Serve a simulated GRBL 1.1h controller on a pseudo-terminal; prints the device path."""
    from softplot.motors.simulator import GrblSimulator

    if not time_scale > 0:
        raise click.BadParameter("must be > 0", param_hint="--time-scale")
    settings = {}
    if homing or soft_limits:
        settings[22] = 1
    if soft_limits:
        settings[20] = 1
    sim = GrblSimulator(
        faults, link=link, time_scale=time_scale, settings=settings, encoders=encoders
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


def _open(port, timeout, reset=False):
    from softplot.motors.grbl import GrblMotors

    return GrblMotors(port, timeout=timeout, configure=False, reset=reset)


_reset_option = click.option(
    "--reset",
    is_flag=True,
    help="Soft-reset the controller first (by default a running controller is left alone; "
    "a reset during a move raises ALARM:3).",
)


@command.command("status")
@click.argument("port")
@click.option(
    "--timeout",
    type=float,
    default=2.0,
    show_default=True,
    help="Seconds to wait for the controller's answer.",
)
@_reset_option
def status(port, timeout, reset):
    """Print the controller's state and DX, DY (instrument mm) on PORT (reads only)."""
    with _open(port, timeout, reset) as m:
        st = m.status()
        dx, dy = m.position()
        note = "" if m.position_valid else " position not valid: home or confirm"
        click.echo(
            f"{st.state} DX={dx:.3f} DY={dy:.3f} (MPos {st.mpos[0]:.3f},{st.mpos[1]:.3f})" + note
        )


@command.command("move")
@click.argument("port")
@click.argument("dx", type=float)
@click.argument("dy", type=float)
@click.option(
    "--timeout",
    type=float,
    default=30.0,
    show_default=True,
    help="Seconds to wait for the move to end.",
)
@_reset_option
@click.option("--confirm-position", is_flag=True,
              help="The operator vouches for the controller's present position (checked "
              "against a reference): lifts an alarm lock ($X) first.")
def move(port, dx, dy, timeout, reset, confirm_position):
    """Move the secondary carriage to DX, DY (instrument mm) and wait."""
    with _open(port, timeout, reset) as m:
        if confirm_position:
            m.confirm_position()
        m.move_to(dx, dy, timeout=timeout)
        px, py = m.position()
        click.echo(f"DX={px:.3f} DY={py:.3f}")


@command.command("home")
@click.argument("port")
@click.option(
    "--timeout",
    type=float,
    default=60.0,
    show_default=True,
    help="Seconds to wait for the homing cycle.",
)
def home(port, timeout):
    """Home the instrument on PORT ($H, needs $22=1): re-establishes a lost position."""
    with _open(port, 2.0) as m:
        m.home(timeout=timeout)
        px, py = m.position()
        click.echo(f"homed: DX={px:.3f} DY={py:.3f}")
