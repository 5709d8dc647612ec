"""``softplot plot``: scripted plotting sessions (new, trace, resume, export)."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.cli._orient import ang_in, angles_option
from softplot.cli._outputs import guard_outputs, overwrite_option
from softplot.cli.restitute import PHOTO_COLUMNS, _read_csv
from softplot.errors import SoftplotError


@click.group("plot")
def command() -> None:
    """Plotting sessions in a project folder: operator input from CSV, journal, export."""


def _motors(port: str | None, timeout: float):
    from softplot.motors import AxisConfig, VirtualMotors

    if port:
        from softplot.motors.grbl import GrblMotors

        return GrblMotors(port, timeout=max(timeout, 2.0))
    fine = AxisConfig(resolution_mm=1e-6, min_mm=-500, max_mm=500, max_speed_mm_s=1e9)
    return VirtualMotors(fine, fine)


@command.command("new")
@click.argument("folder", type=click.Path(path_type=Path))
@click.option(
    "--photos",
    "photos_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Two rows, left first: photo,X0,Y0,Z0,omega,phi,kappa,c (angles in --angles "
    "units, c in mm).",
)
@angles_option
@click.option(
    "--mode", type=click.Choice(["single", "contour", "free"]), default="single", show_default=True,
    help="The STEREOBIT mode the session starts in: single points (x-parallax handwheel), "
    "contour (height locked) or free (both carriages).",
)
@click.option("--height", type=float, default=None, help="Contour height (contour mode).")
@click.option(
    "--left-offset",
    nargs=2,
    type=float,
    default=(0.0, 0.0),
    show_default=True,
    metavar="BX BY",
    help="Fixed offset of the left plate, instrument mm (left film "
    "= main carriage + offset + DX, DY).",
)
@click.option("--left-scan", type=click.Path(path_type=Path), default=None,
              help="Scan of the left photo: the carriages then move over the scans "
              "(instrument mm = scan mm from the scan's centre) and the film correction "
              "takes them to photo mm.")
@click.option("--right-scan", type=click.Path(path_type=Path), default=None,
              help="Scan of the right photo (with --left-scan).")
@click.option("--camera", default=None,
              help="Camera certificate (built-in name or TOML path) of the scans.")
@click.option("--left-detection", type=click.Path(path_type=Path), default=None,
              help="Detection JSON of the left scan (softplot detect); detected now if absent.")
@click.option("--right-detection", type=click.Path(path_type=Path), default=None,
              help="Detection JSON of the right scan; detected now if absent.")
@click.option("--method", default="mesh", show_default=True,
              help="Film-correction method (see softplot correct compare).")
@click.option("--dpi", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Scan resolution, dots per inch, when the files do not record it.")
def new(folder, photos_path, mode, height, left_offset, left_scan, right_scan, camera,
        left_detection, right_detection, method, dpi, angle_unit="deg"):
    """Start a session in FOLDER from an oriented pair (and, optionally, its scans)."""
    from softplot.pipeline.session import Session, scan_photo_map
    from softplot.stereo import OrientedPhoto, StereoModel

    names, ph = _read_csv(photos_path, PHOTO_COLUMNS, "photos file")
    if len(names) != 2:
        raise SoftplotError(f"photos file {photos_path} needs exactly 2 rows (left, right)")
    if mode == "contour" and height is None:
        raise SoftplotError("contour mode needs --height")
    if (left_scan is None) != (right_scan is None):
        raise SoftplotError("give both --left-scan and --right-scan, or neither")
    maps = [None, None]
    if left_scan is not None:
        if camera is None:
            raise SoftplotError("--left-scan/--right-scan need --camera")
        maps = [
            scan_photo_map(sc, camera, det, method=method, dpi=dpi)
            for sc, det in ((left_scan, left_detection), (right_scan, right_detection))
        ]
    elif left_detection or right_detection:
        raise SoftplotError("--left-detection/--right-detection need the scans (--left-scan ...)")
    model = StereoModel(
        *[
            OrientedPhoto(r[0:3], ang_in(r[3:6], angle_unit), r[6], name=n,
                          to_photo=m, to_film=None if m is None else m.inverse)
            for n, r, m in zip(names, ph, maps, strict=True)
        ]
    )
    s = Session.create(folder, model, mode=mode, height=height, left_offset=left_offset)
    try:
        for p in (photos_path, left_detection, right_detection):
            if p is not None:
                s.note_input(p)
    finally:
        s.close()
    click.echo(f"session created in {folder} ({mode}"
               + (", with scans" if maps[0] is not None else "") + ")")


@command.command("trace")
@click.argument("folder", type=click.Path(path_type=Path))
@click.option(
    "--input",
    "input_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Operator input CSV: X,Y (main carriage, instrument mm) and px "
    "(x-parallax handwheel, single mode).",
)
@click.option("--code", required=True, help="Feature code (DXF layer).")
@click.option(
    "--kind",
    type=click.Choice(["point", "line", "contour"]),
    default="point",
    show_default=True,
    help="point: one spot height per row; line/contour: one feature through all rows.",
)
@click.option(
    "--mode",
    type=click.Choice(["single", "contour", "free"]),
    default=None,
    help="Mode of this trace only (default: the session's; `softplot plot mode` changes "
    "the session's).",
)
@click.option("--height", type=float, default=None,
              help="Contour height of this trace only (object units).")
@click.option("--close", "close_line", is_flag=True, help="Close the line/contour.")
@click.option(
    "--port",
    default=None,
    help="Drive a GRBL instrument on this serial port instead of the virtual motors.",
)
@click.option("--timeout", type=float, default=5.0, show_default=True,
              help="Seconds to wait for the carriage to reach each point (on an instrument "
              "a carriage that takes longer is a fault: the point is not recorded).")
@click.option("--home", "home_first", is_flag=True,
              help="With --port: home the instrument ($H) first; re-establishes a position "
              "lost to a reset or a power cycle.")
@click.option("--confirm-position", is_flag=True,
              help="With --port: the operator vouches for the controller's present position "
              "(checked against a reference); unlocks it and resumes in that frame.")
def trace(folder, input_path, code, kind, mode, height, close_line, port, timeout, home_first,
          confirm_position):
    """Run the plotter over scripted operator input and record features in FOLDER.

    A row whose point the carriage cannot reach (outside its travel or the model) is not
    recorded; one line names it. With --port each point is recorded only once the instrument
    confirms that the carriage stands on it; a timeout or any motor fault stops the run
    (exit 2) and is journaled.
    """
    from softplot.pipeline.session import Session
    from softplot.stereo.plotter import NotReached

    if (home_first or confirm_position) and not port:
        raise SoftplotError("--home and --confirm-position need --port")
    with _motors(port, timeout) as mot:
        if home_first:
            mot.home(timeout=max(timeout, 60.0))
        if confirm_position:
            mot.confirm_position()
        s = Session.resume(folder, motors=mot)
        if port:
            click.echo(_position_note(mot, s.motor_state is not None))
        try:
            tmode = mode or s.mode
            theight = height if height is not None else s.height
            if kind == "contour" and tmode != "contour":
                raise SoftplotError(
                    "contours are traced in contour mode (--mode contour --height H)"
                )
            if kind == "point" and tmode == "contour":
                raise SoftplotError(
                    "a spot height is not measured in contour mode (the mark is held at the "
                    "contour height): give --mode single or free"
                )
            if tmode == "contour" and theight is None:
                raise SoftplotError("contour mode needs --height")
            cols = ("name", "X", "Y", "px") if tmode == "single" else ("name", "X", "Y")
            names, v = _read_csv(input_path, cols, "input file")
            if not names:
                raise SoftplotError(f"input file {input_path} has no rows")
            s.note_input(input_path)
            pl = s.plotter(mot)
            pl.reach_timeout = timeout
            pl.set_mode(tmode, theight)  # this trace only: the session keeps its mode
            n0, missed = len(s.features), []
            if kind != "point":
                pl.begin(code, kind)
            for name, row in zip(names, v, strict=True):
                cyc = pl.cycle(row[0], row[1], row[2] if tmode == "single" else None)
                if port and cyc.in_travel:
                    _confirm(pl, mot, timeout, name)  # a timeout on the instrument is a fault
                try:
                    if kind == "point":
                        pl.record_point(code, name=name)
                    else:
                        pl.vertex()
                except NotReached as exc:
                    missed.append(name)
                    click.echo(f"warning: {name}: not recorded: {exc}", err=True)
            if kind != "point":
                pl.end(close=close_line)
            if port:
                _confirm(pl, mot, timeout, "the last point")
            click.echo(
                f"{len(names)} input row(s) -> {len(s.features) - n0} new feature(s) in "
                f"{folder}" + (f"; {len(missed)} row(s) not recorded" if missed else "")
                + (f" (mode {tmode} for this trace; the session's is {s.mode})"
                   if tmode != s.mode else "")
            )
        finally:
            s.close()


@command.command("mode")
@click.argument("folder", type=click.Path(path_type=Path))
@click.argument("mode", type=click.Choice(["single", "contour", "free"]))
@click.option("--height", type=float, default=None,
              help="Contour height (object units), needed in contour mode.")
def set_mode(folder, mode, height):
    """Change the session's mode (and contour height) for the traces that follow."""
    import math

    from softplot.pipeline.session import Session

    s = Session.resume(folder)
    try:
        if height is None and mode == "contour":
            height = s.height
        if mode == "contour" and (height is None or not math.isfinite(height)):
            raise SoftplotError("contour mode needs --height")
        s.set_mode(mode, height)
        click.echo(f"session mode {mode}" + (f", height {height:g}" if mode == "contour" else ""))
    finally:
        s.close()


def _position_note(mot, restored: bool) -> str:
    """One line saying why the instrument's position is trusted."""
    if mot.homed:
        return "instrument: homed; the session resumes in the homed frame"
    if mot.confirmed:
        return "instrument: position confirmed by the operator"
    if restored:
        return ("instrument: position valid (machine position and work offset as the session "
                "left them)")
    return "instrument: the controller's present position is the session's reference"


def _confirm(pl, mot, timeout: float, name: str) -> None:
    """The carriage stands on the commanded target within ``timeout`` s, or the motor fault
    (a timeout included) stops the plotter and is journaled (:class:`PlotterHalted`)."""
    from softplot.motors import MotorFault, MotorTimeout

    try:
        if not mot.wait(timeout):
            raise MotorTimeout(
                f"carriage did not reach {name} within {timeout} s (DX, DY target "
                f"{mot.target()[0]:.3f}, {mot.target()[1]:.3f} mm)"
            )
        at, want = mot.position(), mot.target()
        steps = [round((a - w) / r) for a, w, r in zip(at, want, mot.resolution, strict=True)]
        if any(steps):
            raise MotorFault(
                f"carriage stopped at DX={at[0]:.3f}, DY={at[1]:.3f} mm, not on {name} "
                f"({want[0]:.3f}, {want[1]:.3f} mm)"
            )
    except MotorFault as exc:
        pl._fault(exc)  # stops the motors, journals the fault, raises PlotterHalted


@command.command("resume")
@click.argument("folder", type=click.Path(path_type=Path))
def resume(folder):
    """Re-open a session and summarise it (mode, features by code, faults)."""
    from softplot.pipeline.session import Session

    s = Session.resume(folder)
    try:
        by = {}
        for f in s.features:
            by.setdefault((f.code, f.kind), 0)
            by[(f.code, f.kind)] += 1
        click.echo(f"mode {s.mode}" + (f", height {s.height:g}" if s.height is not None else ""))
        for (code, kind), n in sorted(by.items()):
            click.echo(f"  {code:<16} {kind:<8} {n}")
        click.echo(f"{len(s.features)} feature(s), {len(s.faults)} fault(s)")
        for msg in s.faults[-3:]:
            click.echo(f"  fault: {msg}")
    finally:
        s.close()


@command.command("export")
@click.argument("folder", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@overwrite_option
def export(folder, out):
    """Write the session's features to OUT (.dxf, .geojson or .csv).

    OUT is never a session file nor a file the session was made from (its photos file,
    operator-input CSVs, scans); an existing OUT is replaced only with --overwrite.
    """
    from softplot.pipeline.session import Session

    s = Session.resume(folder)
    try:
        if s.owns(out):
            raise SoftplotError(f"{out} would overwrite a session file: choose another path")
        guard_outputs([out], s.input_files())
        s.export(out)
        click.echo(f"{len(s.features)} feature(s) -> {out}")
    finally:
        s.close()


@command.command("upgrade")
@click.argument("folder", type=click.Path(path_type=Path))
def upgrade(folder):
    """Convert a version-1 session in FOLDER (pickled film corrections) to version 2 (data).

    Reads the old pickle with an unpickler that builds only softplot and NumPy objects and
    keeps it as corrections.pkl.v1; upgrade only folders you trust.
    """
    from softplot.pipeline.session import upgrade_session

    click.echo(f"upgraded: {upgrade_session(folder)}")
