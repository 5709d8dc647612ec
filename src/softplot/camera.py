"""Camera certificates: read, validate, write, and the built-in catalogue.

A certificate is a TOML file (format in ``docs/certificate.md``). All lengths on a
certificate are in millimetres of the **film (plate) system** (x right, y up, origin at the
centre of the reseau or of the fiducial marks, upright photo) except lens distortion values,
which are in micrometres. Reseau row 0 is the top row (largest y), column 0 the leftmost.

Distortion convention (one for both representations): ``delta`` is the displacement the lens
gave the image point, evaluated at the *measured* point reduced to the principal point
(``xb = x - x0``, ``yb = y - y0``, ``r = hypot(xb, yb)``); the photo coordinate is
``xb - delta_x``. For a radial table ``delta_x = xb / r * delta_r(r)``; for Brown
coefficients ``delta_r = k1 r^3 + k2 r^5 + k3 r^7`` plus decentering
``p1 (r^2 + 2 xb^2) + 2 p2 xb yb`` (x) and ``2 p1 xb yb + p2 (r^2 + 2 yb^2)`` (y), plus the
affinity and shear ``b1 xb + b2 yb`` in x.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from softplot.errors import CertificateError

KINDS = ("metric", "semi-metric", "quasi-metric", "non-metric")
FIDUCIAL_SHAPES = ("cross", "dot", "circle-dot", "custom")
DISTORTION_MODELS = ("none", "radial-table", "brown")


@dataclass(frozen=True)
class Fiducial:
    """A fiducial mark: name, position in film mm, and its drawn shape.

    ``size_mm`` is the overall size (tip-to-tip length of a cross bar, diameter of a dot or
    of the outer circle); ``line_width_mm`` the stroke width of crosses and circles.
    """

    name: str
    x: float
    y: float
    shape: str = "cross"
    size_mm: float = 1.0
    line_width_mm: float = 0.05
    dot_mm: float = 0.1


def default_cross_size(pitch_x: float, pitch_y: float) -> tuple[float, float]:
    """Starting guess (arm length, line width) in mm for a reseau cross whose certificate does
    not state them: arms of 1 mm (at most a fifth of the pitch), lines of 0.05 mm (at most a
    tenth of the arm). Detection measures the real ones on the scan."""
    arm = min(1.0, 0.2 * min(pitch_x, pitch_y))
    return arm, min(0.05, 0.1 * arm)


@dataclass(frozen=True)
class Reseau:
    """A grid of reseau crosses.

    Nominal film position of cross (row, col): ``x = (col - (cols-1)/2) * pitch_x``,
    ``y = ((rows-1)/2 - row) * pitch_y`` (film mm; row 0 on top). ``calibrated``, when
    present, is a (rows, cols, 2) array of calibrated film coordinates in mm that overrides
    the nominal grid (NaN where a cross was not calibrated: the nominal value is used).
    ``arm_length_mm`` is the tip-to-tip length of each bar of a cross, ``line_width_mm`` its
    stroke width: both a starting guess for detection, which measures them on the scan
    (``sizes_stated`` False when the certificate left them out and they are the defaults of
    :func:`default_cross_size`).
    """

    rows: int
    cols: int
    pitch_x: float
    pitch_y: float
    arm_length_mm: float
    line_width_mm: float
    calibrated: np.ndarray | None = field(default=None, compare=False)
    sizes_stated: tuple[bool, bool] = field(default=(True, True), compare=False)

    @property
    def count(self) -> int:
        """Number of crosses."""
        return self.rows * self.cols

    def nominal_film(self) -> np.ndarray:
        """Nominal film coordinates (mm), shape (rows*cols, 2), row-major from the top-left."""
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        x = (c - (self.cols - 1) / 2.0) * self.pitch_x
        y = ((self.rows - 1) / 2.0 - r) * self.pitch_y
        return np.column_stack([x.ravel(), y.ravel()]).astype(float)

    def film(self) -> np.ndarray:
        """Calibrated film coordinates (mm), shape (rows*cols, 2), row-major from the top-left.

        Crosses without a calibrated value fall back to the nominal grid.
        """
        xy = self.nominal_film()
        if self.calibrated is not None:
            cal = np.asarray(self.calibrated, float).reshape(-1, 2)
            ok = np.all(np.isfinite(cal), axis=1)
            xy[ok] = cal[ok]
        return xy

    def row_col(self) -> np.ndarray:
        """(row, col) of every cross, shape (rows*cols, 2), in the order of :meth:`film`."""
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.column_stack([r.ravel(), c.ravel()])

    def names(self) -> list[str]:
        """Names of the crosses, ``R<row>C<col>`` (zero-based), in the order of :meth:`film`."""
        return [f"R{r}C{c}" for r, c in self.row_col()]


@dataclass(frozen=True)
class Distortion:
    """Lens distortion, film mm in / film mm out (see the module docstring for the convention).

    ``model`` is "none", "radial-table" (``radius_mm`` -> ``delta_r_um``) or "brown".
    """

    model: str = "none"
    radius_mm: tuple[float, ...] = ()
    delta_r_um: tuple[float, ...] = ()
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    b1: float = 0.0
    b2: float = 0.0


@dataclass(frozen=True)
class Camera:
    """A camera certificate.

    Lengths in film mm: ``format_mm`` (width, height), ``c`` the principal distance,
    ``x0``, ``y0`` the principal point, ``sigma_*`` their standard errors.
    """

    name: str
    kind: str
    format_mm: tuple[float, float]
    c: float
    x0: float = 0.0
    y0: float = 0.0
    sigma_c: float = 0.0
    sigma_x0: float = 0.0
    sigma_y0: float = 0.0
    distortion: Distortion = field(default_factory=Distortion)
    fiducials: tuple[Fiducial, ...] = ()
    reseau: Reseau | None = None
    description: str = ""
    notes: tuple[str, ...] = ()
    calibration: str = ""
    source: str = field(default="", compare=False)

    @property
    def uncalibrated(self) -> bool:
        """True when the certificate says no calibration stands behind its interior values
        (``calibration = "none"``: nominal principal distance, zero principal point, no
        distortion)."""
        return self.calibration.strip().lower() == "none"

    def with_(self, **changes: Any) -> "Camera":
        """A copy with some fields changed."""
        return replace(self, **changes)

    def fiducial_film(self) -> np.ndarray:
        """Film coordinates (mm) of the fiducial marks, shape (n, 2), certificate order."""
        return np.array([[f.x, f.y] for f in self.fiducials], float).reshape(-1, 2)


# ---------------------------------------------------------------------------------------------
# reading and validation


class _Reader:
    """Typed access to a TOML table with errors that name the file and the field."""

    def __init__(self, table: dict, where: str, prefix: str = "") -> None:
        self.table = table
        self.where = where
        self.prefix = prefix

    def _field(self, key: str) -> str:
        return f"{self.prefix}{key}"

    def fail(self, key: str, why: str) -> CertificateError:
        return CertificateError(f"{self.where}: field '{self._field(key)}': {why}")

    def sub(self, key: str, required: bool = True) -> "_Reader | None":
        v = self.table.get(key)
        if v is None:
            if required:
                raise self.fail(key, "missing table")
            return None
        if not isinstance(v, dict):
            raise self.fail(key, "must be a table")
        return _Reader(v, self.where, f"{self._field(key)}.")

    def string(self, key: str, default: str | None = None, choices: tuple = ()) -> str:
        v = self.table.get(key, default)
        if v is None:
            raise self.fail(key, "missing")
        if not isinstance(v, str):
            raise self.fail(key, f"must be a string, got {v!r}")
        if choices and v not in choices:
            raise self.fail(key, f"must be one of {', '.join(choices)}, got {v!r}")
        return v

    def number(
        self,
        key: str,
        default: float | None = None,
        positive: bool = False,
        nonneg: bool = False,
    ) -> float:
        v = self.table.get(key, default)
        if v is None:
            raise self.fail(key, "missing")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(key, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.fail(key, f"must be finite, got {v!r}")
        if positive and v <= 0:
            raise self.fail(key, f"must be positive, got {v!r}")
        if nonneg and v < 0:
            raise self.fail(key, f"must not be negative, got {v!r}")
        return v

    def integer(self, key: str, minimum: int = 1) -> int:
        v = self.table.get(key)
        if v is None:
            raise self.fail(key, "missing")
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(key, f"must be an integer, got {v!r}")
        if v < minimum:
            raise self.fail(key, f"must be at least {minimum}, got {v}")
        return v

    def numbers(self, key: str) -> tuple[float, ...]:
        v = self.table.get(key, [])
        if not isinstance(v, list):
            raise self.fail(key, "must be a list of numbers")
        out = []
        for i, e in enumerate(v):
            if isinstance(e, bool) or not isinstance(e, (int, float)) or not math.isfinite(e):
                raise self.fail(f"{key}[{i}]", f"must be a finite number, got {e!r}")
            out.append(float(e))
        return tuple(out)


def _parse(data: dict, where: str) -> Camera:
    top = _Reader(data, where)
    name = top.string("name")
    kind = top.string("kind", choices=KINDS)
    fmt = top.sub("format")
    format_mm = (fmt.number("width_mm", positive=True), fmt.number("height_mm", positive=True))
    io = top.sub("interior")
    c = io.number("principal_distance_mm", positive=True)
    x0 = io.number("x0_mm", 0.0)
    y0 = io.number("y0_mm", 0.0)
    sc = io.number("sigma_principal_distance_mm", 0.0, nonneg=True)
    sx0 = io.number("sigma_x0_mm", 0.0, nonneg=True)
    sy0 = io.number("sigma_y0_mm", 0.0, nonneg=True)

    dist = Distortion()
    d = top.sub("distortion", required=False)
    if d is not None:
        model = d.string("model", "none", choices=DISTORTION_MODELS)
        if model == "radial-table":
            r = d.numbers("radius_mm")
            dr = d.numbers("delta_r_um")
            if len(r) < 2:
                raise d.fail("radius_mm", "a radial table needs at least 2 radii")
            if len(r) != len(dr):
                raise d.fail("delta_r_um", f"has {len(dr)} values for {len(r)} radii")
            if any(b <= a for a, b in zip(r, r[1:], strict=False)) or r[0] < 0:
                raise d.fail("radius_mm", "radii must be non-negative and increasing")
            dist = Distortion(model=model, radius_mm=r, delta_r_um=dr)
        elif model == "brown":
            dist = Distortion(
                model=model,
                **{k: d.number(k, 0.0) for k in ("k1", "k2", "k3", "p1", "p2", "b1", "b2")},
            )

    fids = []
    raw_f = data.get("fiducials", [])
    if not isinstance(raw_f, list):
        raise top.fail("fiducials", "must be an array of tables ([[fiducials]])")
    seen = set()
    for i, f in enumerate(raw_f):
        if not isinstance(f, dict):
            raise top.fail(f"fiducials[{i}]", "must be a table")
        fr = _Reader(f, where, f"fiducials[{i}].")
        fname = f.get("name")
        if isinstance(fname, int) and not isinstance(fname, bool):
            fname = str(fname)  # name = 1 is read as "1"
        if fname is None or fname == "":
            raise fr.fail("name", "missing")
        if not isinstance(fname, str):
            raise fr.fail("name", f"must be a string, got {fname!r}")
        if fname in seen:
            raise fr.fail("name", f"duplicate fiducial name {fname!r}")
        seen.add(fname)
        fids.append(
            Fiducial(
                name=fname,
                x=fr.number("x_mm"),
                y=fr.number("y_mm"),
                shape=fr.string("shape", "cross", choices=FIDUCIAL_SHAPES),
                size_mm=fr.number("size_mm", 1.0, positive=True),
                line_width_mm=fr.number("line_width_mm", 0.05, positive=True),
                dot_mm=fr.number("dot_mm", 0.1, positive=True),
            )
        )

    reseau = None
    rs = top.sub("reseau", required=False)
    if rs is not None:
        rows = rs.integer("rows")
        cols = rs.integer("cols")
        cal = None
        raw_cal = rs.table.get("calibrated")
        if raw_cal is not None:
            if not isinstance(raw_cal, list):
                raise rs.fail("calibrated", "must be a list of [row, col, x_mm, y_mm]")
            cal = np.full((rows, cols, 2), np.nan)
            for i, e in enumerate(raw_cal):
                ok = (
                    isinstance(e, list)
                    and len(e) == 4
                    and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in e)
                )
                if not ok or not all(math.isfinite(v) for v in e):
                    raise rs.fail(f"calibrated[{i}]", f"must be [row, col, x_mm, y_mm], got {e!r}")
                r_, c_ = e[0], e[1]
                if int(r_) != r_ or int(c_) != c_ or not (0 <= r_ < rows and 0 <= c_ < cols):
                    raise rs.fail(f"calibrated[{i}]", f"row/col ({r_}, {c_}) outside the grid")
                cal[int(r_), int(c_)] = (e[2], e[3])
        pitch_x = rs.number("pitch_x_mm", positive=True)
        pitch_y = rs.number("pitch_y_mm", positive=True)
        arm_d, width_d = default_cross_size(pitch_x, pitch_y)
        stated = ("arm_length_mm" in rs.table, "line_width_mm" in rs.table)
        reseau = Reseau(
            rows=rows,
            cols=cols,
            pitch_x=pitch_x,
            pitch_y=pitch_y,
            arm_length_mm=rs.number("arm_length_mm", arm_d, positive=True),
            line_width_mm=rs.number("line_width_mm", width_d, positive=True),
            calibrated=cal,
            sizes_stated=stated,
        )
        if reseau.line_width_mm >= reseau.arm_length_mm:
            raise rs.fail("line_width_mm", "must be smaller than arm_length_mm")
    if reseau is None and not fids:
        raise top.fail("reseau", "a certificate needs a [reseau] or at least one [[fiducials]]")
    notes = data.get("notes", [])
    if isinstance(notes, str):
        notes = [notes]
    if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
        raise top.fail("notes", "must be a string or a list of strings")
    description = top.string("description", "")
    calibration = top.string("calibration", "")
    if calibration.strip().lower() == "none":
        # "none" promises nominal values only: no principal-point offset, no distortion
        if x0 != 0.0 or y0 != 0.0:
            raise top.fail("calibration", 'is "none" but the principal point is not (0, 0); '
                           "cite the calibration or set x0_mm = y0_mm = 0")
        if dist.model != "none":
            raise top.fail("calibration", 'is "none" but a distortion model is given; '
                           'cite the calibration or set [distortion] model = "none"')
    return Camera(
        name=name,
        kind=kind,
        format_mm=format_mm,
        c=c,
        x0=x0,
        y0=y0,
        sigma_c=sc,
        sigma_x0=sx0,
        sigma_y0=sy0,
        distortion=dist,
        fiducials=tuple(fids),
        reseau=reseau,
        description=description,
        notes=tuple(str(n) for n in notes),
        calibration=calibration,
        source=where,
    )


def read_certificate(path: str | Path) -> Camera:
    """Read and validate a certificate file; raise :class:`CertificateError` naming the field."""
    p = Path(path)
    if not p.is_file():
        raise CertificateError(f"{p}: certificate file not found")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CertificateError(f"{p}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise CertificateError(f"{p}: cannot read: {exc.strerror or exc}") from None
    return _parse(data, str(p))


def parse_certificate(text: str, where: str = "<string>") -> Camera:
    """Parse certificate TOML text (``where`` names it in error messages)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CertificateError(f"{where}: not valid TOML: {exc}") from None
    return _parse(data, where)


def builtin_names() -> list[str]:
    """Names of the built-in certificates, sorted."""
    files = resources.files("softplot.cameras")
    return sorted(f.name[:-5] for f in files.iterdir() if f.name.endswith(".toml"))


def load_camera(name_or_path: str | Path | Camera) -> Camera:
    """A :class:`Camera` from a built-in name, a certificate path, or a Camera (returned as is)."""
    if isinstance(name_or_path, Camera):
        return name_or_path
    s = str(name_or_path)
    if s in builtin_names():
        res = resources.files("softplot.cameras").joinpath(f"{s}.toml")
        return parse_certificate(res.read_text(encoding="utf-8"), where=f"built-in:{s}")
    p = Path(s)
    if p.suffix.lower() == ".toml" or p.exists():
        return read_certificate(p)
    raise CertificateError(
        f"unknown camera {s!r}: not a built-in ({', '.join(builtin_names())}) nor a file"
    )


# ---------------------------------------------------------------------------------------------
# writing


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        # a TOML basic string: JSON escapes are valid TOML escapes; DEL must be escaped too
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(float(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(e) for e in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")


def to_toml(cam: Camera) -> str:
    """Certificate TOML text for ``cam``; :func:`parse_certificate` reads it back unchanged."""
    out = [f"name = {_fmt(cam.name)}", f"kind = {_fmt(cam.kind)}"]
    if cam.description:
        out.append(f"description = {_fmt(cam.description)}")
    if cam.calibration:
        out.append(f"calibration = {_fmt(cam.calibration)}")
    if cam.notes:
        out.append("notes = [")
        out += [f"  {_fmt(n)}," for n in cam.notes]
        out.append("]")
    out += [
        "",
        "[format]",
        f"width_mm = {_fmt(cam.format_mm[0])}",
        f"height_mm = {_fmt(cam.format_mm[1])}",
        "",
        "[interior]",
        f"principal_distance_mm = {_fmt(cam.c)}",
        f"sigma_principal_distance_mm = {_fmt(cam.sigma_c)}",
        f"x0_mm = {_fmt(cam.x0)}",
        f"y0_mm = {_fmt(cam.y0)}",
        f"sigma_x0_mm = {_fmt(cam.sigma_x0)}",
        f"sigma_y0_mm = {_fmt(cam.sigma_y0)}",
        "",
        "[distortion]",
        f"model = {_fmt(cam.distortion.model)}",
    ]
    d = cam.distortion
    if d.model == "radial-table":
        out += [
            f"radius_mm = {_fmt(list(d.radius_mm))}",
            f"delta_r_um = {_fmt(list(d.delta_r_um))}",
        ]
    elif d.model == "brown":
        out += [f"{k} = {_fmt(getattr(d, k))}" for k in ("k1", "k2", "k3", "p1", "p2", "b1", "b2")]
    for f in cam.fiducials:
        out += [
            "",
            "[[fiducials]]",
            f"name = {_fmt(f.name)}",
            f"x_mm = {_fmt(f.x)}",
            f"y_mm = {_fmt(f.y)}",
            f"shape = {_fmt(f.shape)}",
            f"size_mm = {_fmt(f.size_mm)}",
            f"line_width_mm = {_fmt(f.line_width_mm)}",
            f"dot_mm = {_fmt(f.dot_mm)}",
        ]
    if cam.reseau is not None:
        r = cam.reseau
        out += [
            "",
            "[reseau]",
            f"rows = {r.rows}",
            f"cols = {r.cols}",
            f"pitch_x_mm = {_fmt(r.pitch_x)}",
            f"pitch_y_mm = {_fmt(r.pitch_y)}",
        ]
        if r.sizes_stated[0]:
            out.append(f"arm_length_mm = {_fmt(r.arm_length_mm)}")
        if r.sizes_stated[1]:
            out.append(f"line_width_mm = {_fmt(r.line_width_mm)}")
        if r.calibrated is not None:
            cal = np.asarray(r.calibrated, float)
            out.append("calibrated = [")
            for i in range(r.rows):
                for j in range(r.cols):
                    if np.all(np.isfinite(cal[i, j])):
                        out.append(f"  [{i}, {j}, {_fmt(float(cal[i, j, 0]))}, "
                                   f"{_fmt(float(cal[i, j, 1]))}],")
            out.append("]")
    return "\n".join(out) + "\n"


def write_certificate(cam: Camera, path: str | Path, overwrite: bool = False) -> Path:
    """Write ``cam`` as TOML to ``path``; refuses to overwrite an existing file unless asked."""
    p = Path(path)
    if p.exists() and not overwrite:
        raise CertificateError(f"{p}: exists; refusing to overwrite")
    p.write_text(to_toml(cam), encoding="utf-8")
    return p


def describe(cam: Camera) -> str:
    """A human-readable summary of a certificate (what ``softplot cameras show`` prints)."""
    lines = [
        f"{cam.name}  ({cam.kind})",
        f"  {cam.description}" if cam.description else None,
        f"  format            {cam.format_mm[0]:.3f} x {cam.format_mm[1]:.3f} mm",
        f"  principal dist.   c  = {cam.c:.4f} mm  +- {cam.sigma_c * 1000:.1f} um",
        f"  principal point   x0 = {cam.x0:+.4f} mm  +- {cam.sigma_x0 * 1000:.1f} um,"
        f"  y0 = {cam.y0:+.4f} mm  +- {cam.sigma_y0 * 1000:.1f} um",
    ]
    d = cam.distortion
    if d.model == "radial-table":
        lines.append("  distortion        radial table (r mm -> delta-r um):")
        lines += [
            f"      {r:8.2f} {dr:+8.2f}"
            for r, dr in zip(d.radius_mm, d.delta_r_um, strict=True)
        ]
    elif d.model == "brown":
        lines.append(
            "  distortion        Brown: "
            + ", ".join(
                f"{k}={getattr(d, k):.6g}" for k in ("k1", "k2", "k3", "p1", "p2", "b1", "b2")
            )
        )
    else:
        lines.append("  distortion        none")
    if cam.fiducials:
        lines.append(f"  fiducials         {len(cam.fiducials)}:")
        lines += [
            f"      {f.name:>6} x={f.x:+9.3f} y={f.y:+9.3f} mm  {f.shape}, size {f.size_mm} mm"
            for f in cam.fiducials
        ]
    if cam.reseau is not None:
        r = cam.reseau
        cal = "calibrated" if r.calibrated is not None else "nominal"
        lines.append(
            f"  reseau            {r.rows} x {r.cols} crosses, pitch {r.pitch_x} x {r.pitch_y} mm, "
            f"arm {r.arm_length_mm} mm, line {r.line_width_mm} mm ({cal} coordinates)"
        )
    if cam.uncalibrated:
        lines.append("  calibration       none: nominal interior values, no distortion model")
    elif cam.calibration:
        lines.append(f"  calibration       {cam.calibration}")
    for n in cam.notes:
        lines.append(f"  note: {n}")
    lines.append(f"  source: {cam.source}")
    return "\n".join(line for line in lines if line is not None)
