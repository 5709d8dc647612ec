"""``softplot relor``: relative orientation of a stereo pair (dependent or independent)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from softplot.cli._orient import (
    DEFAULT_SIGMA_IMAGE,
    alpha_option,
    ang_out,
    angles_option,
    camera_options,
    check_photo,
    json_option,
    read_table,
    report,
    sigma_image_option,
    snooping_out,
    write_json,
    write_points_csv,
)
from softplot.cli._orient import principal_distance as resolve_c
from softplot.errors import SoftplotError
from softplot.orientation.relative import relative_orientation


@click.command("relor")
@camera_options
@click.option("--left", "left_path", type=click.Path(dir_okay=False, path_type=Path),
              help="CSV name,x,y: left photo coordinates, mm, reduced to the principal point.")
@click.option("--right", "right_path", type=click.Path(dir_okay=False, path_type=Path),
              help="CSV name,x,y: right photo coordinates, mm.")
# -- automatic model set-up (softplot match): relor --auto LEFT_SCAN RIGHT_SCAN --camera C
@click.argument("scans", nargs=-1, type=click.Path(path_type=Path))
@click.option("--auto", is_flag=True,
              help="Automatic: tie points matched in the two scans SCANS (detection, film "
                   "correction, matching; softplot match) instead of --left/--right.")
@click.option("--ties", "ties_dir", type=click.Path(file_okay=False, path_type=Path),
              help="With --auto: keep the tie points (softplot match outputs) in this folder.")
@click.option(
    "--bx",
    type=float,
    default=100.0,
    show_default=True,
    help="Fixed base component bx (sets the model scale), model units.",
)
@click.option(
    "--independent",
    is_flag=True,
    help="Independent pairs (phi1, kappa1, omega2, phi2, kappa2; base along x) "
    "instead of dependent (by, bz, omega2, phi2, kappa2).",
)
@sigma_image_option()
@alpha_option
@angles_option
@json_option
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the model points as name,x,y,z (model units), the file "
              "`softplot absor --model` takes.")
def command(
    camera,
    principal_distance,
    left_path,
    right_path,
    bx,
    independent,
    sigma_image,
    alpha0,
    angle_unit,
    json_path,
    scans=(),
    csv_path=None,
    auto=False,
    ties_dir=None,
) -> None:
    """Relative orientation by the coplanarity condition, started from the essential matrix.

    The left photo is at the origin of the model frame (unrotated for dependent pairs).
    Points are matched by name (>= 5). JSON keys: omega, phi, kappa (right photo), bx, by,
    bz, sigma0 (mm), redundancy, std (omega, phi, kappa, by, bz; plus phi1, kappa1 when
    independent), points (name, X, Y, Z, py - y-parallax in mm), mode, phi1, kappa1,
    flagged, angles_unit.
    """
    c = resolve_c(camera, principal_distance)
    if auto:  # tie points from the scans, as photo mm CSVs
        from softplot.cli.match import auto_photo_ties

        left_path, right_path = auto_photo_ties(scans, camera, ties_dir)
    elif scans or left_path is None or right_path is None:
        raise SoftplotError("give --left and --right photo CSVs, or --auto LEFT RIGHT (scans)")
    L = read_table(left_path, ("name",), ("x", "y"), what="left points")
    R = read_table(right_path, ("name",), ("x", "y"), what="right points")
    ridx = {n: i for i, n in enumerate(R["name"])}
    common = [(i, ridx[n]) for i, n in enumerate(L["name"]) if n in ridx]
    if len(common) < 5:
        raise SoftplotError(
            f"relative orientation needs >= 5 points in both {left_path} and {right_path}, "
            f"found {len(common)}"
        )
    li = np.array([i for i, _ in common])
    ri = np.array([j for _, j in common])
    names = [L["name"][i] for i in li]
    mode = "independent" if independent else "dependent"
    check_photo(np.c_[L["x"], L["y"]][li], camera, c, f"left points {left_path}")
    check_photo(np.c_[R["x"], R["y"]][ri], camera, c, f"right points {right_path}")
    r = relative_orientation(
        np.c_[L["x"], L["y"]][li],
        np.c_[R["x"], R["y"]][ri],
        c,
        bx=bx,
        mode=mode,
        sigma=sigma_image or DEFAULT_SIGMA_IMAGE,
        names=names,
        alpha0=alpha0,
        precision_known=sigma_image is not None,
    )
    sj, snoop = snooping_out(r)
    std = r.std
    a2 = [ang_out(v, angle_unit) for v in r.angles2]
    data = {
        "omega": a2[0],
        "phi": a2[1],
        "kappa": a2[2],
        "bx": r.value("bx"),
        "by": r.value("by"),
        "bz": r.value("bz"),
        "sigma0": r.sigma0,
        "redundancy": r.redundancy,
    }
    sd = {
        "omega": ang_out(std["omega2"], angle_unit),
        "phi": ang_out(std["phi2"], angle_unit),
        "kappa": ang_out(std["kappa2"], angle_unit),
    }
    if independent:
        sd.update(phi1=ang_out(std["phi1"], angle_unit), kappa1=ang_out(std["kappa1"], angle_unit))
        data.update(
            phi1=ang_out(r.value("phi1"), angle_unit), kappa1=ang_out(r.value("kappa1"), angle_unit)
        )
    else:
        sd.update(by=std["by"], bz=std["bz"])
    data["std"] = sd
    data["points"] = [
        {"name": n, "X": float(p[0]), "Y": float(p[1]), "Z": float(p[2]), "py": float(py)}
        for n, p, py in zip(names, r.points.XYZ, r.py, strict=True)
    ]
    data.update(
        mode=mode,
        flagged=[n for n, f in zip(names, r.flagged, strict=True) if f],
        **sj,
        angles_unit=angle_unit,
        principal_distance=c,
    )
    write_json(json_path, data, [left_path, right_path])
    write_points_csv(csv_path, names, r.points.XYZ, [left_path, right_path],
                     decimals=int(max(0, np.ceil(6 - np.log10(abs(bx))))))
    au = angle_unit
    if independent:
        params = [
            ("phi1", au, data["phi1"], sd["phi1"], 5),
            ("kappa1", au, data["kappa1"], sd["kappa1"], 5),
        ]
    else:
        params = [("by", "model", data["by"], sd["by"], 4),
                  ("bz", "model", data["bz"], sd["bz"], 4)]
    params += [
        ("omega2", au, a2[0], sd["omega"], 5),
        ("phi2", au, a2[1], sd["phi"], 5),
        ("kappa2", au, a2[2], sd["kappa"], 5),
    ]
    w = r.adjustment.standardized.reshape(-1, 4)
    wmax = np.nanmax(np.abs(np.nan_to_num(w, nan=0.0)), axis=1)
    click.echo(
        report(
            f"RELATIVE ORIENTATION ({mode})",
            [
                f"principal distance c = {c:.4f} mm    points {len(names)}    bx = {bx:g} (fixed)"
                f"    photo sigma " + (f"{sigma_image:g} mm" if sigma_image else "not given")
            ],
            params,
            r.sigma0,
            sigma_image,
            r.redundancy,
            "mm",
            ["X", "Y", "Z", "py [mm]", "|w|"],
            [
                (n, [*p, py, wm], f)
                for n, p, py, wm, f in zip(
                    names, r.points.XYZ.tolist(), r.py, wmax, r.flagged, strict=True
                )
            ],
            k=r.adjustment.critical_value,
            snooping=snoop,
            alpha0=alpha0,
            w_start=4,
            notes=[
                f"unmatched points ignored: {len(L['name']) - len(names)} left, "
                f"{len(R['name']) - len(names)} right"
            ]
            if len(names) < max(len(L["name"]), len(R["name"]))
            else [],
        )
    )
