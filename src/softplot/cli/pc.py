"""``softplot pc``: projection centres of analogue plotters (Birardi 1980)."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from softplot.cli._orient import (
    ang_out,
    angles_option,
    finite_or_none,
    input_option,
    json_option,
    read_table,
    report,
    write_json,
)
from softplot.errors import SoftplotError
from softplot.orientation.resection import EO_NAMES
from softplot.orientation.two_planes import differential, fiducial_resection, two_planes


def _snooping(adj, names) -> dict:
    """``blunders`` (point names, most likely first) and ``snooping_test`` of an adjustment
    whose observations come point by point, the same number per point."""
    from softplot.adjust import snooping_json

    k = adj.flagged.size // max(1, len(names))
    return snooping_json(adj.snooping, [n for n in names for _ in range(k)])


@click.group("pc")
def command() -> None:
    """Projection centres of analogue plotters (Birardi, ISP Hamburg 1980).

    \b
    two-planes    centre (and f) from grid points read in two planes Z1, Z2
    resect        centre and attitude from fiducial marks read in one plane
    differential  two-plane centre + (model resection - reference resection)

    Coordinates are instrument mm; the JSON of two-planes and resect feed differential.
    """


@command.command("two-planes")
@input_option(
    "--readings",
    "path",
    "CSV name,X1,Y1,X2,Y2[,x,y][,Z1,Z2]: readings in the planes Z1 and Z2 "
    "(instrument mm) and the photo coordinates x,y of the points (for f).",
)
@click.option("--z1", type=float, default=None, help="Height of the first (lower) plane.")
@click.option("--z2", type=float, default=None, help="Height of the second plane.")
@click.option(
    "--method",
    type=click.Choice(["rigorous", "birardi"]),
    default="rigorous",
    show_default=True,
    help="rigorous: adjust the readings; birardi: his linear system (3).",
)
@click.option(
    "--f-weights",
    type=click.Choice(["birardi", "rigorous"]),
    default="birardi",
    show_default=True,
    help="Weights of the mean f: (a^2+b^2)^2 or a^2+b^2.",
)
@click.option(
    "--sigma",
    type=float,
    default=0.001,
    show_default=True,
    help="Standard error of one reading, mm.",
)
@json_option
def two_planes_cmd(path, z1, z2, method, f_weights, sigma, json_path) -> None:
    """Projection centre by space intersection of rays read in two planes (Birardi 2.1).

    Solves c*dx + a*dz + kx = vx, c*dy + b*dz + ky = vy (a = X2-X1, b = Y2-Y1, c = Z1-Z2)
    for X0, Y0, Z0 with covariance, and f_i = -c*sqrt(x^2+y^2)/sqrt(a^2+b^2) with the
    weighted mean f. JSON: X0, Y0, Z0, std [3], covariance (3x3), sigma0, redundancy, f,
    f_std, f_i (list of name, f_i, p_i), residuals (name, vX1, vY1, vX2, vY2), method.
    """
    t = read_table(
        path, ("name",), ("X1", "Y1", "X2", "Y2"), ("x", "y", "Z1", "Z2"), what="readings"
    )
    Z1 = t["Z1"] if z1 is None else np.full(len(t["name"]), z1)
    Z2 = t["Z2"] if z2 is None else np.full(len(t["name"]), z2)
    if not (np.all(np.isfinite(Z1)) and np.all(np.isfinite(Z2))):
        raise SoftplotError(f"readings {path}: give --z1/--z2 or Z1,Z2 columns on every line")
    has_xy = bool(np.all(np.isfinite(t["x"])) and np.all(np.isfinite(t["y"])))
    r = two_planes(
        np.c_[t["X1"], t["Y1"]],
        Z1,
        np.c_[t["X2"], t["Y2"]],
        Z2,
        np.c_[t["x"], t["y"]] if has_xy else None,
        sigma=sigma,
        method=method,
        f_weights=f_weights,
    )
    names = t["name"]
    data = {
        "X0": float(r.X0[0]),
        "Y0": float(r.X0[1]),
        "Z0": float(r.X0[2]),
        "std": r.std.tolist(),
        "covariance": r.covariance.tolist(),
        "sigma0": r.sigma0,
        "redundancy": r.redundancy,
        "f": r.f,
        "f_std": r.f_std,
        "method": method,
    }
    if r.f_i is not None:
        data["f_i"] = [
            {"name": n, "f_i": finite_or_none(f), "p_i": float(p)}
            for n, f, p in zip(names, r.f_i, r.p_i, strict=True)
        ]
    data["residuals"] = [
        {
            "name": n,
            "vX1": finite_or_none(v[0]),
            "vY1": finite_or_none(v[1]),
            "vX2": finite_or_none(v[2]),
            "vY2": finite_or_none(v[3]),
        }
        for n, v in zip(names, r.residuals, strict=True)
    ]
    data.update(_snooping(r.adjustment, names))
    write_json(json_path, data, [path])
    params = [(k, "mm", v, s, 4) for k, v, s in zip(("X0", "Y0", "Z0"), r.X0, r.std, strict=True)]
    if r.f is not None:
        params.append(("f", "mm", r.f, r.f_std, 4))
    fl = r.adjustment.flagged.reshape(len(names), -1).any(axis=1)
    click.echo(
        report(
            f"PROJECTION CENTRE BY TWO PLANES ({method})",
            [f"points {len(names)}    reading sigma {sigma:g} mm    f weights {f_weights}"],
            params,
            r.sigma0,
            sigma,
            r.redundancy,
            "mm",
            ["vX1", "vY1", "vX2", "vY2", "f_i"],
            [
                (n, [*v, f], b)
                for n, v, f, b in zip(
                    names,
                    r.residuals.tolist(),
                    (r.f_i if r.f_i is not None else np.full(len(names), np.nan)),
                    fl,
                    strict=True,
                )
            ],
            k=r.adjustment.critical_value,
        )
    )


@command.command("resect")
@input_option(
    "--marks",
    "path",
    "CSV name,x,y,X,Y: photo coordinates of the marks (mm) and their readings "
    "(instrument mm) in the plane --z.",
)
@click.option("--z", "z", type=float, required=True, help="Height of the reading plane.")
@click.option(
    "--principal-distance",
    "f",
    type=float,
    required=True,
    help="Principal distance, mm (e.g. f of two-planes).",
)
@click.option(
    "--sigma",
    type=float,
    default=0.001,
    show_default=True,
    help="Standard error of one reading, mm.",
)
@angles_option
@json_option
def resect_cmd(path, z, f, sigma, angle_unit, json_path) -> None:
    """Space resection on fiducial marks read in one plane (Birardi 2.2), any attitude.

    JSON: X0, Y0, Z0, omega, phi, kappa, std (six keys), covariance (6x6, angles in --angles
    units), sigma0, redundancy, residuals (name, vX, vY), angles_unit.
    """
    if not f > 0:
        raise SoftplotError(f"principal distance must be > 0, got {f}")
    t = read_table(path, ("name",), ("x", "y", "X", "Y"), what="marks")
    r = fiducial_resection(np.c_[t["x"], t["y"]], np.c_[t["X"], t["Y"]], z, f, sigma=sigma)
    vals = [*r.X0.tolist(), *[ang_out(a, angle_unit) for a in r.angles]]
    stds = [*r.std[:3].tolist(), *[ang_out(s, angle_unit) for s in r.std[3:]]]
    k = np.array([1.0, 1.0, 1.0, *[float(ang_out(1.0, angle_unit))] * 3])
    data = dict(zip(EO_NAMES, vals, strict=True))
    data.update(
        std=dict(zip(EO_NAMES, stds, strict=True)),
        covariance=(r.covariance * k[:, None] * k[None, :]).tolist(),
        sigma0=r.sigma0,
        redundancy=r.redundancy,
        residuals=[
            {"name": n, "vX": float(v[0]), "vY": float(v[1])}
            for n, v in zip(t["name"], r.residuals, strict=True)
        ],
        angles_unit=angle_unit,
    )
    data.update(_snooping(r.adjustment, list(t["name"])))
    write_json(json_path, data, [path])
    units = ["mm"] * 3 + [angle_unit] * 3
    fl = r.adjustment.flagged.reshape(-1, 2).any(axis=1)
    click.echo(
        report(
            "PROJECTION CENTRE BY RESECTION ON MARKS (one plane)",
            [
                f"marks {len(t['name'])}    plane Z = {z:g}    f = {f:g} mm    "
                f"reading sigma {sigma:g} mm"
            ],
            [
                (nm, u, v, s, 4 if u == "mm" else 5)
                for nm, u, v, s in zip(EO_NAMES, units, vals, stds, strict=True)
            ],
            r.sigma0,
            sigma,
            r.redundancy,
            "mm",
            ["vX", "vY"],
            [(n, list(v), b) for n, v, b in zip(t["name"], r.residuals.tolist(), fl, strict=True)],
            k=r.adjustment.critical_value,
        )
    )


def _load_pc(path: Path, what: str):
    try:
        d = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise SoftplotError(f"{what} {path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SoftplotError(f"{what} {path}: not a JSON result ({exc})") from None
    try:
        X0 = np.array([float(d["X0"]), float(d["Y0"]), float(d["Z0"])])
        cov = np.asarray(d.get("covariance", np.zeros((3, 3))), dtype=float)[:3, :3]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise SoftplotError(f"{what} {path}: needs X0, Y0, Z0 (and covariance): {exc}") from None
    if cov.shape != (3, 3):
        raise SoftplotError(f"{what} {path}: covariance must be at least 3x3")

    class _PC:
        pass

    p = _PC()
    p.X0, p.covariance = X0, cov
    return p


@command.command("differential")
@input_option("--two-planes", "a_path", "JSON of 'pc two-planes' at the reference epoch (a).")
@input_option(
    "--reference",
    "b_path",
    "JSON of 'pc resect' on the marks at the same epoch, lower plane (b).",
)
@input_option("--model", "c_path", "JSON of 'pc resect' on the marks in the oriented model (c).")
@json_option
def differential_cmd(a_path, b_path, c_path, json_path) -> None:
    """Birardi's differential procedure: PC = PC_a + (PC_c - PC_b).

    The shift of the resection on the carrier marks between the reference epoch and the
    model is applied to the two-plane centre: it is independent of the calibration of the
    marks and of the interior orientation. JSON: X0, Y0, Z0, std [3], covariance (3x3; the
    sum of the three), delta [dX0, dY0, dZ0].
    """
    d = differential(
        _load_pc(a_path, "two-planes result"),
        _load_pc(b_path, "reference"),
        _load_pc(c_path, "model"),
    )
    data = {
        "X0": float(d.X0[0]),
        "Y0": float(d.X0[1]),
        "Z0": float(d.X0[2]),
        "std": d.std.tolist(),
        "covariance": d.covariance.tolist(),
        "delta": d.delta.tolist(),
    }
    write_json(json_path, data, [a_path, b_path, c_path])
    ds = np.sqrt(np.diag(d.delta_covariance))
    params = [(k, "mm", v, s, 4) for k, v, s in zip(("X0", "Y0", "Z0"), d.X0, d.std, strict=True)]
    params += [
        (k, "mm", v, s, 4) for k, v, s in zip(("dX0", "dY0", "dZ0"), d.delta, ds, strict=True)
    ]
    click.echo(
        report(
            "PROJECTION CENTRE, DIFFERENTIAL PROCEDURE",
            ["PC = two-planes + (model resection - reference resection)"],
            params,
            float("nan"),
            None,
            None,
            "mm",
        )
    )
