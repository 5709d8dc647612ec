"""Shared plumbing of the orientation commands (resect, intersect, relor, absor, pc).

CSV tables with a header, angle units, the principal distance, JSON output that never
overwrites an input, and the certificate-like text report. No numerics here beyond unit
conversion and formatting.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import click
import numpy as np

from softplot import __version__
from softplot.cli._outputs import guard_outputs, overwrite_option
from softplot.errors import SoftplotError
from softplot.geometry.rotation import from_radians, to_radians

ANGLE_HELP = (
    "Unit of every angle read and written: deg (default), gon (400/turn) or rad. "
    "(--angle-unit is the older name.)"
)


def angles_option(f):
    """The ``--angles deg|gon|rad`` option, the same name and default in every command."""
    return click.option(
        "--angles",
        "--angle-unit",
        "angle_unit",
        type=click.Choice(["deg", "gon", "rad"]),
        default="deg",
        show_default=True,
        help=ANGLE_HELP,
    )(f)


def input_option(flag: str, dest: str, help: str):  # noqa: A002
    """A required input-file option (``flag`` FILE, stored as ``dest``, a Path)."""
    return click.option(flag, dest, required=True,
                        type=click.Path(dir_okay=False, path_type=Path), help=help)


def json_option(f):
    """The ``--json OUT.json`` option and ``--overwrite`` (:mod:`softplot.cli._outputs`)."""
    f = overwrite_option(f)
    return click.option(
        "--json",
        "json_path",
        type=click.Path(dir_okay=False, path_type=Path),
        default=None,
        help="Write the result as JSON to this file (never an input file; an existing file "
        "only with --overwrite).",
    )(f)


def alpha_option(f):
    """The ``--alpha`` data-snooping significance level (parameter ``alpha0``)."""
    return click.option(
        "--alpha",
        "alpha0",
        type=float,
        default=0.001,
        show_default=True,
        help="Significance level of data snooping.",
    )(f)


def sigma_image_option(help: str = "Standard error of the photo coordinates, mm."):  # noqa: A002
    """The ``--sigma-image MM`` option with the given help text. Not given (None): the photo
    coordinates are weighted with 0.005 mm but their precision is not known, so data snooping
    tests against the a posteriori sigma0 (Pope's tau test); given: Baarda's w-test."""
    return click.option(
        "--sigma-image", type=float, default=None,
        help=help + " Given: blunders are tested against it (Baarda's w-test); not given: "
        "weights of 0.005 mm and Pope's tau test against the a posteriori sigma0.",
    )


#: photo-coordinate weight when --sigma-image is not given, mm
DEFAULT_SIGMA_IMAGE = 0.005


def snooping_out(result) -> tuple[dict, dict]:
    """(JSON keys ``blunders``, ``snooping_test``; the ``snooping`` argument of
    :func:`report`) of an orientation result with ``snooping_json()``."""
    sj = result.snooping_json()
    return sj, {"describe": result.adjustment.snooping.describe(), "blunders": sj["blunders"]}


def finite_or_none(v):
    """``float(v)``, or None (JSON null) when it is not finite."""
    v = float(v)
    return v if np.isfinite(v) else None


def camera_options(f):
    """``--camera CERT`` / ``--principal-distance MM`` (one of them)."""
    f = click.option(
        "--principal-distance",
        "principal_distance",
        type=float,
        default=None,
        help="Principal distance c in mm (instead of --camera).",
    )(f)
    return click.option(
        "--camera",
        "camera",
        default=None,
        help="Camera certificate (built-in name or TOML file) giving c.",
    )(f)


def principal_distance(camera: str | None, c: float | None) -> float:
    """c from ``--camera`` or ``--principal-distance`` (exactly one)."""
    if (camera is None) == (c is None):
        raise SoftplotError("give exactly one of --camera CERT or --principal-distance MM")
    if camera is not None:
        from softplot.camera import load_camera

        c = load_camera(camera).c
    if not (math.isfinite(c) and c > 0):
        raise SoftplotError(f"principal distance must be a positive number of mm, got {c}")
    return float(c)


def check_photo(xy, camera: str | None, c: float, what: str) -> None:
    """Refuse photo coordinates (n, 2) that cannot be photo mm of this camera
    (:func:`softplot.orientation.plausible.check_photo_coords`)."""
    from softplot.orientation.plausible import check_photo_coords

    fmt = name = None
    if camera is not None:
        from softplot.camera import load_camera

        cam = load_camera(camera)
        fmt, name = cam.format_mm, cam.name
    check_photo_coords(xy, c, what=what, format_mm=fmt, camera=name or "")


def read_table(
    path: Path,
    text: tuple[str, ...],
    numeric: tuple[str, ...],
    optional: tuple[str, ...] = (),
    what: str = "table",
    blank_ok: tuple[str, ...] = (),
    unique: str | None = "name",
) -> dict:
    """Read a CSV file with a header line.

    Parameters
    ----------
    path : Path
    text : tuple of str
        Required text columns (e.g. ``name``).
    numeric : tuple of str
        Required numeric columns.
    optional : tuple of str
        Optional numeric columns (absent or blank cell -> nan).
    what : str
        Name of the file's role, for messages.
    blank_ok : tuple of str
        Required numeric columns whose cells may be blank (-> nan).
    unique : str or None
        Text column whose values must not repeat.

    Returns
    -------
    dict
        Column name -> list of str (text) or float ndarray (numeric); ``"_line"`` -> line
        numbers of the rows.
    """
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except FileNotFoundError:
        raise SoftplotError(f"{what} {path}: no such file") from None
    except OSError as exc:
        raise SoftplotError(f"{what} {path}: cannot read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise SoftplotError(f"{what} {path}: not a text CSV file ({exc})") from None
    lines = [(i + 1, r) for i, r in enumerate(rows) if r and any(c.strip() for c in r)]
    lines = [(i, r) for i, r in lines if not r[0].lstrip().startswith("#")]
    if not lines:
        raise SoftplotError(f"{what} {path}: empty file (need a header line)")
    hline, header = lines[0]
    header = [h.strip() for h in header]
    missing = [c for c in (*text, *numeric) if c not in header]
    if missing:
        raise SoftplotError(
            f"{what} {path}: line {hline}: header lacks column(s) {', '.join(missing)} "
            f"(need {','.join((*text, *numeric))})"
        )
    out: dict = {c: [] for c in (*text, *numeric, *optional)}
    out["_line"] = []
    for ln, r in lines[1:]:
        cells = [c.strip() for c in r]
        if len(cells) < len(header):
            cells += [""] * (len(header) - len(cells))
        if len(cells) > len(header) and any(cells[len(header) :]):
            raise SoftplotError(
                f"{what} {path}: line {ln}: {len(cells)} fields for {len(header)} columns"
            )
        for c in text:
            v = cells[header.index(c)]
            if not v:
                raise SoftplotError(f"{what} {path}: line {ln}: empty {c}")
            out[c].append(v)
        for c in (*numeric, *optional):
            if c not in header:
                out[c].append(math.nan)
                continue
            v = cells[header.index(c)]
            if v == "" and (c in optional or c in blank_ok):
                out[c].append(math.nan)
                continue
            try:
                x = float(v)
            except ValueError:
                raise SoftplotError(
                    f"{what} {path}: line {ln}: {c} = {v!r} is not a number"
                ) from None
            if not math.isfinite(x):
                raise SoftplotError(f"{what} {path}: line {ln}: {c} = {v!r} is not finite")
            out[c].append(x)
        out["_line"].append(ln)
    if not out["_line"]:
        raise SoftplotError(f"{what} {path}: no data lines after the header")
    for c in (*numeric, *optional):
        out[c] = np.array(out[c], dtype=float)
    if unique is not None:
        seen: dict = {}
        for n, ln in zip(out[unique], out["_line"], strict=True):
            if n in seen:
                raise SoftplotError(
                    f"{what} {path}: line {ln}: {unique} {n!r} repeated (first on line {seen[n]})"
                )
            seen[n] = ln
    return out


def write_json(path: Path | None, data: dict, inputs: list[Path]) -> None:
    """Write ``data`` as JSON, refusing to overwrite one of the ``inputs``."""
    if path is None:
        return
    path = Path(path)
    guard_outputs([path], inputs)
    try:
        path.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n")
    except OSError as exc:
        raise SoftplotError(f"cannot write {path}: {exc.strerror or exc}") from None


def write_points_csv(path: Path | None, names, XYZ, inputs: list[Path], decimals: int = 6,
                     flag: str = "--csv") -> None:
    """Write model/object points as ``name,x,y,z`` (what ``absor --model`` reads), refusing to
    overwrite one of the ``inputs``."""
    if path is None:
        return
    import csv

    path = Path(path)
    for p in inputs:
        if p is not None and Path(p).exists() and path.resolve() == Path(p).resolve():
            raise SoftplotError(f"{flag} {path} would overwrite the input file {p}")
    try:
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["name", "x", "y", "z"])
            for n, p in zip(names, np.asarray(XYZ, dtype=float).tolist(), strict=True):
                w.writerow([n, *(f"{v:.{decimals}f}" for v in p)])
    except OSError as exc:
        raise SoftplotError(f"cannot write {path}: {exc.strerror or exc}") from None


def ang_out(v, unit: str):
    """Radians -> output unit (float or list)."""
    a = from_radians(np.asarray(v, dtype=float), unit)
    return a.tolist() if np.ndim(a) else float(a)


def ang_in(v, unit: str):
    """Input unit -> radians."""
    return to_radians(np.asarray(v, dtype=float), unit)


def scale_angles(cov, is_angle, unit: str):
    """Covariance (radians) -> covariance with angle rows/columns in ``unit``."""
    k = np.where(np.asarray(is_angle), float(from_radians(1.0, unit)), 1.0)
    return (np.asarray(cov) * k[:, None] * k[None, :]).tolist()


def fnum(x, d=4) -> str:
    """Format a number (nan -> '-')."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{d}f}"


def report(
    title: str,
    header: list[str],
    params: list[tuple[str, str, float, float, int]],
    sigma0: float,
    sigma0_prior: float | None,
    redundancy: int | None,
    unit0: str,
    table_head: list[str] | None = None,
    table: list[tuple[str, list[float], bool]] | None = None,
    digits: int = 4,
    k: float | None = None,
    alpha0: float = 0.001,
    w_start: int | None = None,
    notes: list[str] | None = None,
    snooping: dict | None = None,
) -> str:
    """The certificate-like report.

    Parameters
    ----------
    title : str
    header : list of str
        Free lines under the title.
    params : list of (name, unit, value, std, decimals)
    sigma0, sigma0_prior : float
    redundancy : int or None
        None: no adjustment (the sigma0 line is left out).
    unit0 : str
        Unit of sigma0.
    table_head : list of str
        Column titles of the residual table (after the point name).
    table : list of (name, values, flagged)
    digits : int
        Decimals of the residual table.
    k : float
        Critical value of the w-test (for the legend).
    alpha0 : float
        Significance level of the w-test.
    w_start : int, optional
        Index of the first standardised-residual column of ``table`` values (to name the
        largest |w|).
    notes : list of str
    snooping : dict, optional
        ``{"describe": one line naming the test, "blunders": names, most likely first}``
        (from the adjustment's :class:`softplot.adjust.Snooping`); replaces the w-test legend.
    """
    bar = "=" * 72
    out = [bar, f"{title}".ljust(52) + f"softplot {__version__}".rjust(20), bar]
    out += header
    if redundancy is not None:
        s0p = f" (a priori {fnum(sigma0_prior, 4)} {unit0})" if sigma0_prior else ""
        out.append(f"sigma0 = {fnum(sigma0, 4)} {unit0}{s0p}   redundancy r = {redundancy}")
    if params:
        out.append("")
        out.append(f"{'parameter':<14}{'unit':<8}{'value':>22}{'std':>16}")
        out.append("-" * 60)
    for name, unit, val, std, dec in params:
        # a standard deviation shows two significant digits (never "0.0000"); its value as many
        if std is not None and np.isfinite(std) and std > 0:
            dec = int(min(12, max(dec, np.ceil(-np.log10(std)) + 1)))
        out.append(f"{name:<14}{unit:<8}{fnum(val, dec):>22}{fnum(std, dec):>16}")
    if table:
        out.append("")
        w = max(8, max(len(t[0]) for t in table) + 2)
        out.append(f"{'point':<{w}}" + "".join(f"{h:>12}" for h in table_head))
        out.append("-" * (w + 12 * len(table_head)))
        for name, vals, flag in table:
            out.append(
                f"{name:<{w}}"
                + "".join(f"{fnum(v, digits):>12}" for v in vals)
                + ("   << blunder?" if flag else "")
            )
        flagged = [t[0] for t in table if t[2]]
        out.append("")
        if snooping is not None:
            bl = snooping["blunders"]
            out.append(f"data snooping ({snooping['describe']}): "
                       + (", ".join(bl) if bl else "no blunder flagged"))
            if bl:
                out.append(f"most likely blunder: {bl[0]} - remove it and adjust again "
                           "(a blunder also raises the statistic of its neighbours)")
        elif k is not None:
            out.append(
                f"data snooping (Baarda, alpha0 = {alpha0:g}, |w| > {k:.2f}): "
                + (", ".join(flagged) if flagged else "no blunder flagged")
            )
            if flagged and w_start is not None:
                worst = max(
                    table,
                    key=lambda t: max(
                        (abs(v) for v in t[1][w_start:] if math.isfinite(v)), default=0.0
                    ),
                )
                wmax = max(abs(v) for v in worst[1][w_start:] if math.isfinite(v))
                out.append(
                    f"largest |w| = {wmax:.2f} at {worst[0]}: the most likely blunder - remove it "
                    "and adjust again (a blunder also raises the w of its neighbours)"
                )
    for n in notes or []:
        out.append(n)
    out.append(bar)
    return "\n".join(out)
