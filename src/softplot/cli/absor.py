"""``softplot absor``: absolute orientation of a model (7-parameter similarity)."""

from __future__ import annotations

import click
import numpy as np

from softplot.cli._orient import (
    alpha_option,
    ang_out,
    angles_option,
    finite_or_none,
    input_option,
    json_option,
    read_table,
    report,
    snooping_out,
    write_json,
)
from softplot.errors import SoftplotError
from softplot.orientation.absolute import PARAMS, absolute_orientation


@click.command("absor")
@input_option("--model", "model_path", "CSV name,x,y,z: model coordinates.")
@input_option(
    "--control",
    "gcp_path",
    "CSV name,X,Y,Z[,sX,sY,sZ]: object coordinates (a blank X,Y or Z: not observed).",
)
@alpha_option
@angles_option
@json_option
def command(model_path, gcp_path, alpha0, angle_unit, json_path) -> None:
    """Absolute orientation: object = scale * M^T * model + T, from >= 3 control points.

    Closed-form start (Horn/Umeyama), then least squares weighted by sX, sY, sZ (unit weights
    without them: sigma0 is then in object units, else a ratio to the a priori errors). JSON:
    scale, omega, phi, kappa, TX, TY, TZ, sigma0, redundancy, std (same seven keys),
    covariance (7x7), residuals (name, vX, vY, vZ, flagged), points (every model point
    transformed: name, X, Y, Z), angles_unit.
    """
    mod = read_table(model_path, ("name",), ("x", "y", "z"), what="model")
    gcp = read_table(
        gcp_path,
        ("name",),
        ("X", "Y", "Z"),
        ("sX", "sY", "sZ"),
        what="control",
        blank_ok=("X", "Y", "Z"),
    )
    midx = {n: i for i, n in enumerate(mod["name"])}
    common = [(midx[n], j) for j, n in enumerate(gcp["name"]) if n in midx]
    if len(common) < 3:
        raise SoftplotError(
            f"absolute orientation needs >= 3 points in both {model_path} and {gcp_path}, "
            f"found {len(common)}"
        )
    mi = np.array([i for i, _ in common])
    gj = np.array([j for _, j in common])
    names = [gcp["name"][j] for j in gj]
    model = np.c_[mod["x"], mod["y"], mod["z"]]
    obj = np.c_[gcp["X"], gcp["Y"], gcp["Z"]][gj]
    s = np.c_[gcp["sX"], gcp["sY"], gcp["sZ"]][gj]
    from softplot.orientation.plausible import check_model_scale

    check_model_scale(model[mi], obj, names, what=f"model {model_path} / control {gcp_path}")
    r = absolute_orientation(
        model[mi], obj, s if np.isfinite(s).any() else None, names=names, alpha0=alpha0
    )
    is_ang = [p in ("omega", "phi", "kappa") for p in PARAMS]
    vals = [
        ang_out(v, angle_unit) if a else float(v) for v, a in zip(r.params, is_ang, strict=True)
    ]
    stds = [ang_out(v, angle_unit) if a else float(v) for v, a in zip(r.std, is_ang, strict=True)]
    k = np.where(is_ang, float(ang_out(1.0, angle_unit)), 1.0)
    pts = r.apply(model)
    data = dict(zip(PARAMS, vals, strict=True))
    data.update(
        sigma0=r.sigma0,
        redundancy=r.redundancy,
        std=dict(zip(PARAMS, stds, strict=True)),
        covariance=(r.covariance * k[:, None] * k[None, :]).tolist(),
        residuals=[
            {
                "name": n,
                "vX": finite_or_none(v[0]),
                "vY": finite_or_none(v[1]),
                "vZ": finite_or_none(v[2]),
                "flagged": bool(f),
            }
            for n, v, f in zip(names, r.residuals, r.flagged, strict=True)
        ],
        points=[
            {"name": n, "X": float(p[0]), "Y": float(p[1]), "Z": float(p[2])}
            for n, p in zip(mod["name"], pts, strict=True)
        ],
        angles_unit=angle_unit,
    )
    sj, snoop = snooping_out(r)
    data.update(sj)
    write_json(json_path, data, [model_path, gcp_path])
    units = ["1", angle_unit, angle_unit, angle_unit, "object", "object", "object"]
    dec = [8, 5, 5, 5, 4, 4, 4]
    unused = [n for n in gcp["name"] if n not in midx]
    notes = [f"control points not in the model (ignored): {', '.join(unused)}"] if unused else []
    click.echo(
        report(
            "ABSOLUTE ORIENTATION (7-parameter similarity)",
            [f"control points {len(names)}    model points {len(mod['name'])}"],
            [
                (p, u, v, s_, d)
                for p, u, v, s_, d in zip(PARAMS, units, vals, stds, dec, strict=True)
            ],
            r.sigma0,
            None,
            r.redundancy,
            "(unit weight)",
            ["vX", "vY", "vZ", "w X", "w Y", "w Z"],
            [
                (n, [*v, *w], f)
                for n, v, w, f in zip(
                    names, r.residuals.tolist(), r.standardized.tolist(), r.flagged, strict=True
                )
            ],
            k=r.adjustment.critical_value,
            snooping=snoop,
            alpha0=alpha0,
            w_start=3,
            notes=notes,
        )
    )
