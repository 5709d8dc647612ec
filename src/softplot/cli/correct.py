"""``softplot correct``: film-deformation correction of a scan (points, comparison, resampling).

Spellings::

    softplot correct SCAN --camera C [--detection DET.json] [--method M]
                          --points IN.csv --out OUT.csv [--to film|photo]
    softplot correct DET.json --camera C [--method M] --points IN.csv --out OUT.csv
    softplot correct SCAN --camera C [--detection DET.json] [--method M]
                          --resample OUT.tif [--pixel-size MICRONS]
    softplot correct compare SCAN|DET.json --camera C [--json OUT.json]

``points`` and ``resample`` are also sub-command names for the first two forms. Thin: the
numerics live in :mod:`softplot.correction`.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from softplot.cli._outputs import guard_outputs, overwrite_option
from softplot.errors import SoftplotError

METHOD_NAMES = (
    "mesh",
    "mesh-affine",
    "mesh-homography",
    "mesh-bilinear",
    "raw-plate",
    "raw-plate-affine",
    "affine",
    "projective",
    "bilinear",
    "poly2",
    "poly3",
)


class _DefaultGroup(click.Group):
    """A group whose first argument, when it is not a sub-command, goes to ``apply``."""

    default_command = "apply"

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ("-h", "--help"):
            args = [self.default_command, *args]
        return super().parse_args(ctx, args)

    def format_usage(self, ctx, formatter):
        formatter.write_usage(ctx.command_path,
                              "SCAN|DET.json --camera C [OPTIONS] | COMMAND [ARGS]...")

    def format_options(self, ctx, formatter):
        """The group's options and commands, then the options of the default form (``apply``),
        which is what ``softplot correct SCAN ...`` runs."""
        super().format_options(ctx, formatter)
        apply = self.commands[self.default_command]
        sub = click.Context(apply, info_name=self.default_command, parent=ctx)
        rows = [r for p in apply.get_params(sub) if isinstance(p, click.Option)
                and p.name != "help" and (r := p.get_help_record(sub)) is not None]
        with formatter.section("Options of softplot correct SCAN|DET.json ... (the apply form)"):
            formatter.write_dl(rows)


@click.group("correct", cls=_DefaultGroup)
def command() -> None:
    """Film-deformation correction: pixel -> film / photo mm, method comparison, resampling.

    \b
    softplot correct SCAN --camera C --points IN.csv --out OUT.csv [--to film|photo]
    softplot correct DET.json --camera C --points IN.csv --out OUT.csv  (no scan needed)
    softplot correct SCAN --camera C --resample OUT.tif [--pixel-size MICRONS]
    softplot correct compare SCAN|DET.json --camera C

    Without --detection the marks are detected first (softplot detect). Methods: mesh (the
    camera's: triangles with affines for a 3x3 reseau, quads with homographies otherwise),
    mesh-affine, mesh-homography, mesh-bilinear, raw-plate, raw-plate-affine, affine,
    projective, bilinear, poly2, poly3 (docs/correction.md).
    """


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and a.resolve() == b.resolve()
    except OSError:  # pragma: no cover
        return False


def _marks(scan_path: Path | None, camera, detection: Path | None, force: bool = False):
    """(detection dict, scan or None): the marks from DET.json or a fresh detection.

    A detection made on another scan or with another camera is refused (``force``: a warning
    in the output instead)."""
    from softplot.correction import detect_marks, load_detection
    from softplot.io import fingerprint, load_scan
    from softplot.provenance import check_detection

    scan = load_scan(scan_path) if scan_path is not None else None
    if detection is not None:
        det = load_detection(detection)
        det["_source"] = detection.name
        size = (scan.width, scan.height) if scan is not None else None
        for w in check_detection(det, camera_name=camera.name, scan_path=scan_path,
                                 scan_size=size, force=force):
            click.echo(w)
        if scan is not None:
            det["width"], det["height"] = scan.width, scan.height
        return det, scan
    click.echo(f"detecting marks in {scan_path.name} ...", err=True)
    det = detect_marks(scan, camera)
    det["scan"] = fingerprint(scan_path)
    return det, scan


def _apply(scan, camera, detection, method, points, out, to, resample_out, pixel_size,
           interpolation, force=False):
    from softplot.camera import load_camera
    from softplot.correction import (
        FilmCorrection,
        default_pixel_size,
        read_points_csv,
        resample,
        write_points_csv,
        write_resampled,
    )

    scan_p = Path(scan)
    if scan_p.suffix.lower() == ".json":  # a detection alone: no scan needed for points
        if detection is not None:
            raise SoftplotError("give the detection either as SCAN or as --detection, not both")
        if resample_out is not None:
            raise SoftplotError("--resample needs the scan itself, not its detection JSON")
        detection, scan_p = str(scan_p), None
    if points is None and resample_out is None:
        raise SoftplotError(
            "nothing to do: give --points IN.csv --out OUT.csv or --resample OUT.tif"
        )
    if points is not None and out is None:
        raise SoftplotError("--points needs --out OUT.csv")
    if out is not None and points is None:
        raise SoftplotError("--out needs --points IN.csv")
    inputs = [p for p in [scan_p] if p is not None]
    inputs += [Path(p) for p in (detection, points) if p is not None]
    outputs = [Path(p) for p in (out, resample_out) if p is not None]
    if resample_out is not None:
        outputs.append(Path(resample_out).with_name(Path(resample_out).name + ".json"))
    guard_outputs(outputs, inputs)
    names = xy = None
    if points is not None:
        names, xy = read_points_csv(points)  # read before the (slow) detection
    cam = load_camera(camera)
    det, sc = _marks(scan_p, cam, Path(detection) if detection else None, force)
    fc = FilmCorrection.from_detection(cam, det, method)
    click.echo(fc.describe())
    if points is not None:
        if to == "photo" and cam.uncalibrated:
            click.echo(
                f"note: the certificate {cam.name!r} has no calibration (calibration = \"none\"): "
                "photo coordinates use its nominal principal distance, a principal point at the "
                "origin and no distortion correction"
            )
        mm, flags = fc.pixel_to(xy, to)
        Path(out).unlink(missing_ok=True)  # allowed by guard_outputs (--overwrite)
        write_points_csv(out, names, mm, flags)
        counts = {k: int((flags == v).sum()) for k, v in (("ok", 0), ("outside-reseau", 1),
                                                          ("outside-image", 2))}
        click.echo(
            f"{len(names)} points -> {out} ({to} mm): "
            + ", ".join(f"{v} {k}" for k, v in counts.items())
        )
    if resample_out is not None:
        ps = pixel_size / 1000.0 if pixel_size else default_pixel_size(fc, sc.dpi)
        res = resample(sc.data, fc, ps, interpolation)
        rp = Path(resample_out)
        if rp.suffix.lower() in (".tif", ".tiff"):  # allowed by guard_outputs (--overwrite)
            for q in (rp, rp.with_name(rp.name + ".json")):
                q.unlink(missing_ok=True)
        tif, side = write_resampled(
            resample_out,
            res,
            {"scan": scan_p.name, "camera": cam.name, "marks": det.get("_source", "detected")},
        )
        h, w = res.image.shape[:2]
        click.echo(f"{tif}: {w} x {h} px at {ps * 1000:.3f} um on the film grid; {side}")


def _apply_options(f):
    opts = [
        click.argument("scan", type=click.Path(dir_okay=False)),
        click.option("--camera", "-c", required=True,
                     help="Built-in camera name or certificate TOML."),
        click.option("--detection", "-d", type=click.Path(dir_okay=False),
                     help="Marks from `softplot detect --json` (default: detect now)."),
        click.option("--method", "-m", type=click.Choice(METHOD_NAMES), default="mesh",
                     show_default=True, help="Correction method."),
        click.option("--points", "points", type=click.Path(dir_okay=False),
                     help="CSV with columns name,x,y in pixels."),
        click.option("--out", "-o", type=click.Path(dir_okay=False),
                     help="Output CSV: name,x,y (mm),flag (ok|outside-reseau|outside-image)."),
        click.option("--to", type=click.Choice(["film", "photo"]), default="film",
                     show_default=True, help="film mm, or photo mm (interior orientation)."),
        click.option("--resample", "resample_out", type=click.Path(dir_okay=False),
                     help="Write a film-flattened TIFF (+ OUT.tif.json sidecar)."),
        click.option("--pixel-size", type=float, default=None,
                     help="Resampled pixel size in micrometres (default: the scan's)."),
        click.option("--interpolation", type=click.Choice(["linear", "cubic", "nearest"]),
                     default="linear", show_default=True, help="Resampling interpolation."),
        overwrite_option,
        click.option("--force", is_flag=True,
                     help="Apply a detection made on another scan or with another camera "
                          "(refused otherwise; a warning is printed)."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


@command.command("apply")
@_apply_options
def apply_cmd(**kw) -> None:
    """Correct points (--points/--out) and/or resample the scan (--resample)."""
    _apply(**kw)


@command.command("points")
@_apply_options
def points_cmd(**kw) -> None:
    """Same as `softplot correct SCAN ...`: correct the points of IN.csv."""
    _apply(**kw)


@command.command("resample")
@_apply_options
def resample_cmd(**kw) -> None:
    """Same as `softplot correct SCAN ...`: write a film-flattened TIFF."""
    _apply(**kw)


@command.command("compare")
@click.argument("source", type=click.Path(dir_okay=False))
@click.option("--camera", "-c", required=True, help="Built-in camera name or certificate TOML.")
@click.option("--detection", "-d", type=click.Path(dir_okay=False),
              help="Marks from `softplot detect --json` (when SOURCE is a scan).")
@click.option("--method", "methods", multiple=True, type=click.Choice(METHOD_NAMES[1:]),
              help="Only these methods (repeatable; default all).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False),
              help="Also write the table as JSON.")
@click.option("--force", is_flag=True,
              help="Use a detection made on another scan or with another camera.")
@overwrite_option
def compare_cmd(source, camera, detection, methods, json_out, force) -> None:
    """Cross-validate every method over the crosses (leave-one-out and checkerboard).

    SOURCE is a scan (marks detected, or --detection) or a detection JSON. Prints the RMS of
    the check residuals in micrometres per method and the recommended method.
    """
    from softplot.camera import load_camera
    from softplot.correction import compare, marks_from_detection

    cam = load_camera(camera)
    src = Path(source)
    guard_outputs([json_out], [src, detection])
    if src.suffix.lower() == ".json":
        det, _ = _marks(None, cam, src, force)
    else:
        det, _ = _marks(src, cam, Path(detection) if detection else None, force)
    marks = marks_from_detection(cam, det)
    cv = compare(cam, marks, list(methods) or None)
    click.echo(f"{src.name}: camera {cam.name}, {cv.n_marks} measured marks")
    click.echo(cv.table())
    if json_out is not None:
        d = cv.to_dict()
        d.update({"source": src.name, "camera": cam.name})
        Path(json_out).write_text(json.dumps(d, indent=1) + "\n", encoding="utf-8")
        click.echo(f"-> {json_out}")
