"""``softplot intersect``: object points from rays of oriented photos."""

from __future__ import annotations

import click
import numpy as np

from softplot.adjust import critical_value
from softplot.cli._orient import (
    DEFAULT_SIGMA_IMAGE,
    alpha_option,
    ang_in,
    angles_option,
    input_option,
    json_option,
    read_table,
    report,
    sigma_image_option,
    write_json,
)
from softplot.errors import SoftplotError
from softplot.orientation.intersection import intersect


@click.command("intersect")
@input_option(
    "--photos",
    "photos_path",
    "CSV photo,X0,Y0,Z0,omega,phi,kappa,c (angles in --angles units, c in mm).",
)
@input_option(
    "--image-points",
    "pts_path",
    "CSV photo,name,x,y: photo coordinates in mm reduced to the principal point.",
)
@sigma_image_option()
@alpha_option
@angles_option
@json_option
def command(photos_path, pts_path, sigma_image, alpha0, angle_unit, json_path) -> None:
    """Space intersection of two or more rays per point, with the covariance of each point.

    Points seen in one photo only are skipped (listed). JSON: points (list of name, X, Y, Z,
    std [sX, sY, sZ], rms of the photo residuals in mm, rays), sigma0 (pooled, mm), skipped.
    """
    ph = read_table(
        photos_path,
        ("photo",),
        ("X0", "Y0", "Z0", "omega", "phi", "kappa", "c"),
        what="photos",
        unique="photo",
    )
    pts = read_table(pts_path, ("photo", "name"), ("x", "y"), what="image points", unique=None)
    pidx = {n: i for i, n in enumerate(ph["photo"])}
    seen = set()
    for p, n, ln in zip(pts["photo"], pts["name"], pts["_line"], strict=True):
        if p not in pidx:
            raise SoftplotError(f"image points {pts_path}: line {ln}: unknown photo {p!r}")
        if (p, n) in seen:
            raise SoftplotError(f"image points {pts_path}: line {ln}: {n!r} repeated in {p!r}")
        seen.add((p, n))
    if np.any(ph["c"] <= 0):
        raise SoftplotError(f"photos {photos_path}: principal distance c must be > 0")
    names_all = list(dict.fromkeys(pts["name"]))
    count = {n: 0 for n in names_all}
    for n in pts["name"]:
        count[n] += 1
    names = [n for n in names_all if count[n] >= 2]
    skipped = [n for n in names_all if count[n] < 2]
    if not names:
        raise SoftplotError(f"image points {pts_path}: no point is seen in two photos")
    nidx = {n: i for i, n in enumerate(names)}
    keep = np.array([count[n] >= 2 for n in pts["name"]])
    point = np.array([nidx[n] for n, k in zip(pts["name"], keep, strict=True) if k])
    photo = np.array([pidx[p] for p, k in zip(pts["photo"], keep, strict=True) if k])
    xy = np.c_[pts["x"], pts["y"]][keep]
    from softplot.orientation.plausible import check_photo_coords

    for k, pname in enumerate(ph["photo"]):
        check_photo_coords(xy[photo == k], float(ph["c"][k]),
                           what=f"image points {pts_path} (photo {pname})")
    X0 = np.c_[ph["X0"], ph["Y0"], ph["Z0"]]
    ang = np.c_[
        ang_in(ph["omega"], angle_unit),
        ang_in(ph["phi"], angle_unit),
        ang_in(ph["kappa"], angle_unit),
    ]
    r = intersect(
        xy,
        point,
        photo,
        X0,
        ang,
        ph["c"],
        sigma=sigma_image or DEFAULT_SIGMA_IMAGE,
        n_points=len(names),
        point_names=names,
        alpha0=alpha0,
        precision_known=sigma_image is not None,
    )
    sj = r.snooping_json()
    data = {
        "points": [
            {
                "name": n,
                "X": float(p[0]),
                "Y": float(p[1]),
                "Z": float(p[2]),
                "std": [float(s) for s in sd],
                "rms": float(rm),
                "rays": int(k),
                "flagged": bool(f),
            }
            for n, p, sd, rm, k, f in zip(
                names, r.XYZ, r.std, r.rms, r.n_rays, r.flagged, strict=True
            )
        ],
        "sigma0": r.sigma0_pooled,
        "redundancy": int(r.redundancy.sum()),
        "skipped": skipped,
        **sj,
    }
    write_json(json_path, data, [photos_path, pts_path])
    notes = [f"points in one photo only (skipped): {', '.join(skipped)}"] if skipped else []
    click.echo(
        report(
            "SPACE INTERSECTION",
            [
                f"photos {len(ph['photo'])}    points {len(names)}    "
                "photo sigma " + (f"{sigma_image:g} mm" if sigma_image else "not given"),
                "covariance scaled by the pooled sigma0 of all points",
            ],
            [],
            r.sigma0_pooled,
            sigma_image,
            int(r.redundancy.sum()),
            "mm",
            ["X", "Y", "Z", "sX", "sY", "sZ", "rms [mm]", "rays"],
            [
                (n, [*p, *sd, rm, float(k)], f)
                for n, p, sd, rm, k, f in zip(
                    names, r.XYZ.tolist(), r.std.tolist(), r.rms, r.n_rays, r.flagged, strict=True
                )
            ],
            k=critical_value(alpha0),
            alpha0=alpha0,
            notes=notes,
            snooping={"describe": r.snooping.describe(), "blunders": sj["blunders"]},
        )
    )
