"""``softplot resect``: space resection of one photo from control points."""

from __future__ import annotations

import click
import numpy as np

from softplot.cli._orient import (
    DEFAULT_SIGMA_IMAGE,
    alpha_option,
    ang_out,
    angles_option,
    camera_options,
    check_photo,
    input_option,
    json_option,
    read_table,
    report,
    scale_angles,
    sigma_image_option,
    snooping_out,
    write_json,
)
from softplot.cli._orient import principal_distance as resolve_c
from softplot.errors import SoftplotError
from softplot.orientation.resection import EO_NAMES, resect


@click.command("resect")
@camera_options
@input_option(
    "--image-points",
    "pts_path",
    "CSV name,x,y: photo coordinates in mm, reduced to the principal point.",
)
@input_option(
    "--control",
    "gcp_path",
    "CSV name,X,Y,Z[,sX,sY,sZ]: object coordinates; with sX.. the point is weighted "
    "control, without it is fixed.",
)
@sigma_image_option("Standard error of the photo coordinates, mm (the a priori sigma0).")
@alpha_option
@angles_option
@json_option
def command(
    camera, principal_distance, pts_path, gcp_path, sigma_image, alpha0, angle_unit, json_path
) -> None:
    """Space resection: X0, Y0, Z0, omega, phi, kappa of one photo from >= 3 control points.

    No initial values are needed (P3P / SQPnP start, then least squares). Points are matched
    by name; photo points without control are ignored. JSON keys: X0, Y0, Z0, omega, phi,
    kappa, sigma0 (mm), redundancy, std (same six keys), covariance (6x6 in that order,
    angles in --angles units), residuals (name, vx, vy in mm), flagged, angles_unit.
    """
    c = resolve_c(camera, principal_distance)
    pts = read_table(pts_path, ("name",), ("x", "y"), what="image points")
    gcp = read_table(gcp_path, ("name",), ("X", "Y", "Z"), ("sX", "sY", "sZ"), what="control")
    gidx = {n: i for i, n in enumerate(gcp["name"])}
    common = [(i, gidx[n]) for i, n in enumerate(pts["name"]) if n in gidx]
    if len(common) < 3:
        raise SoftplotError(
            f"resection needs >= 3 points present in both {pts_path} and {gcp_path}, "
            f"found {len(common)}"
        )
    ip = np.array([i for i, _ in common])
    gp = np.array([j for _, j in common])
    names = [pts["name"][i] for i in ip]
    xy = np.c_[pts["x"][ip], pts["y"][ip]]
    check_photo(xy, camera, c, f"image points {pts_path}")
    XYZ = np.c_[gcp["X"][gp], gcp["Y"][gp], gcp["Z"][gp]]
    sXYZ = np.c_[gcp["sX"][gp], gcp["sY"][gp], gcp["sZ"][gp]]
    r = resect(
        xy,
        XYZ,
        c,
        sigma_xy=sigma_image or DEFAULT_SIGMA_IMAGE,
        sigma_XYZ=sXYZ if np.isfinite(sXYZ).any() else None,
        names=names,
        alpha0=alpha0,
        precision_known=sigma_image is not None,
    )
    sj, snoop = snooping_out(r)
    is_ang = [False, False, False, True, True, True]
    vals = [*r.X0.tolist(), *[ang_out(a, angle_unit) for a in r.angles]]
    stds = [*r.std[:3].tolist(), *[ang_out(s, angle_unit) for s in r.std[3:6]]]
    data = {k: v for k, v in zip(EO_NAMES, vals, strict=True)}
    data.update(
        sigma0=r.sigma0,
        redundancy=r.redundancy,
        std=dict(zip(EO_NAMES, stds, strict=True)),
        covariance=scale_angles(r.covariance, is_ang, angle_unit),
        residuals=[
            {"name": n, "vx": float(v[0]), "vy": float(v[1])}
            for n, v in zip(names, r.residuals, strict=True)
        ],
        flagged=[n for n, f in zip(names, r.flagged, strict=True) if f],
        **sj,
        angles_unit=angle_unit,
        principal_distance=c,
        ambiguous=r.ambiguous,
    )
    write_json(json_path, data, [pts_path, gcp_path])
    unused = [n for n in pts["name"] if n not in gidx]
    notes = [f"photo points without control (ignored): {', '.join(unused)}"] if unused else []
    if r.ambiguous:
        notes.append(
            "WARNING: three points - P3P has other exact solutions; the least tilted "
            "camera was taken"
        )
    au = angle_unit
    click.echo(
        report(
            "SPACE RESECTION",
            [
                f"principal distance c = {c:.4f} mm    control points {len(names)}    "
                f"photo sigma " + (f"{sigma_image:g} mm" if sigma_image else "not given")
            ],
            [
                ("X0", "", vals[0], stds[0], 4),
                ("Y0", "", vals[1], stds[1], 4),
                ("Z0", "", vals[2], stds[2], 4),
                ("omega", au, vals[3], stds[3], 5),
                ("phi", au, vals[4], stds[4], 5),
                ("kappa", au, vals[5], stds[5], 5),
            ],
            r.sigma0,
            sigma_image,
            r.redundancy,
            "mm",
            ["vx [mm]", "vy [mm]", "w x", "w y"],
            [
                (n, [*v, *w], f)
                for n, v, w, f in zip(
                    names, r.residuals.tolist(), r.standardized.tolist(), r.flagged, strict=True
                )
            ],
            k=r.adjustment.critical_value,
            snooping=snoop,
            alpha0=alpha0,
            w_start=2,
            notes=notes,
        )
    )
