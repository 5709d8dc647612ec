"""``softplot restitute``: batch stereo restitution from an oriented pair (CSV in, CSV out)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import click
import numpy as np

from softplot.cli._orient import ang_in, angles_option
from softplot.cli._outputs import guard_outputs, overwrite_option
from softplot.errors import SoftplotError

PHOTO_COLUMNS = ("photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c")
IN_COLUMNS = {
    "single": ("name", "x2", "y2", "x1"),
    "contour": ("name", "x2", "y2"),
    "free": ("name", "x1", "y1", "x2", "y2"),
    "drive-to": ("name", "X", "Y", "Z"),
}
OUT_COLUMNS = ("name", "x1", "y1", "x2", "y2", "X", "Y", "Z", "py")
#: photo coordinates and y-parallax are written to 0.1 micrometre
PHOTO_DECIMALS = 4


def object_decimals(std: np.ndarray) -> int:
    """Decimals for object coordinates: the last digit a tenth of the smallest standard
    deviation (object units), between 0 and 9."""
    s = np.asarray(std, dtype=float)
    s = s[np.isfinite(s) & (s > 0)]
    if s.size == 0:
        return 4
    return int(np.clip(np.ceil(-np.log10(s.min() / 10)), 0, 9))


def _read_csv(path: Path, columns, what: str) -> tuple[list[str], np.ndarray]:
    try:
        with path.open(newline="") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except OSError as exc:
        raise SoftplotError(f"cannot read {what} {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise SoftplotError(f"{what} {path} is not a text CSV file") from exc
    if not rows:
        raise SoftplotError(f"{what} {path} is empty")
    header = [h.strip() for h in rows[0]]
    if "name" in header:
        col = header.index("name")
        seen, dup = set(), []
        for r in rows[1:]:
            nm = r[col].strip() if col < len(r) else ""
            if nm in seen and nm not in dup:
                dup.append(nm)
            seen.add(nm)
        if dup:
            raise SoftplotError(f"{what} {path}: duplicate point name(s) {', '.join(dup[:5])}")
    missing = [c for c in columns if c not in header]
    if missing:
        raise SoftplotError(
            f"{what} {path}: missing column(s) {', '.join(missing)} (need {','.join(columns)})"
        )
    idx = [header.index(c) for c in columns]
    names, values = [], []
    for n, r in enumerate(rows[1:], start=2):
        if len(r) < len(header):
            raise SoftplotError(f"{what} {path}: line {n} has {len(r)} fields, need {len(header)}")
        names.append(r[idx[0]].strip())
        try:
            vals = [float(r[i]) for i in idx[1:]]
        except ValueError as exc:
            raise SoftplotError(f"{what} {path}: line {n}: {exc}") from exc
        if not all(math.isfinite(v) for v in vals):
            raise SoftplotError(f"{what} {path}: line {n} has a non-finite number")
        values.append(vals)
    return names, np.array(values, dtype=float).reshape(len(values), len(columns) - 1)


@click.command("restitute")
@click.option(
    "--photos",
    "photos_path",
    required=True,
    type=click.Path(path_type=Path),
    help="CSV with two rows (left first): photo,X0,Y0,Z0,omega,phi,kappa,c "
    "(angles in --angles units, c in mm).",
)
@angles_option
@click.option(
    "--mode",
    required=True,
    type=click.Choice(list(IN_COLUMNS)),
    help="single: name,x2,y2,x1; contour: name,x2,y2 (+ --height); "
    "free: name,x1,y1,x2,y2; drive-to: name,X,Y,Z.",
)
@click.option(
    "--points",
    "points_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Input points CSV (photo mm or object coordinates, by mode).",
)
@click.option("--height", type=float, default=None, help="Contour height Qc (contour mode).")
@click.option(
    "--out",
    "out_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Output CSV: name,x1,y1,x2,y2,X,Y,Z,py (photo mm and py, the residual y-parallax, to "
    "0.1 um; X, Y, Z to a tenth of their precision) and, in free mode, sX,sY,sZ (object units).",
)
@click.option("--sigma-image", type=click.FloatRange(min=0, min_open=True), default=0.005,
              show_default=True,
              help="Standard error of a photo coordinate, mm: the precision of the points "
              "(free mode's sX, sY, sZ) and the decimals written.")
@click.option("--check", "check_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="CSV name,X,Y,Z of check points (object units): print each "
              "restituted point's difference from them and the RMS.")
@overwrite_option
def command(photos_path, mode, points_path, height, out_path, angle_unit="deg",
            sigma_image=0.005, check_path=None):
    """Restitute points of an oriented stereo pair in one of the four STEREOBIT modes."""
    from softplot.stereo.model import OrientedPhoto, StereoModel

    out_path = Path(out_path)
    guard_outputs([out_path], [photos_path, points_path, check_path])
    names, ph = _read_csv(photos_path, PHOTO_COLUMNS, "photos file")
    if len(names) != 2:
        raise SoftplotError(
            f"photos file {photos_path} needs exactly 2 rows (left, right), got {len(names)}"
        )
    photos = [
        OrientedPhoto(row[0:3], ang_in(row[3:6], angle_unit), row[6], name=nm)
        for nm, row in zip(names, ph, strict=True)
    ]
    model = StereoModel(*photos)
    pnames, v = _read_csv(points_path, IN_COLUMNS[mode], "points file")
    if mode == "contour" and height is None:
        raise SoftplotError("contour mode needs --height")
    if mode != "contour" and height is not None:
        raise SoftplotError("--height is only used in contour mode")
    if not pnames:
        raise SoftplotError(f"points file {points_path} has no points")
    from softplot.orientation.plausible import check_photo_coords

    c1, c2 = float(ph[0, 6]), float(ph[1, 6])
    where = f"points file {points_path}"
    if mode in ("single", "contour"):
        check_photo_coords(v[:, 0:2], c2, what=f"{where} (right photo)")
    if mode == "single":
        check_photo_coords(np.c_[v[:, 2], np.zeros(len(v))], c1, what=f"{where} (left photo)")
    if mode == "free":
        check_photo_coords(v[:, 0:2], c1, what=f"{where} (left photo)")
        check_photo_coords(v[:, 2:4], c2, what=f"{where} (right photo)")
    if mode == "single":
        r = model.single_point(v[:, 0:2], v[:, 2])
    elif mode == "contour":
        r = model.contour(v[:, 0:2], height)
    elif mode == "free":
        r = model.free(v[:, 0:2], v[:, 2:4], sigma=sigma_image)
    else:
        r = model.drive_to(v)
    table = np.c_[r.xy1, r.xy2, r.XYZ, r.py]
    # the precision of these points in this model: the intersection's standard deviations for
    # photo coordinates of --sigma-image (free mode: written per point; other modes set the
    # decimals only, their X, Y, Z follow from the carriage positions given)
    prec = model.free(r.xy1, r.xy2, sigma=sigma_image).std if np.all(np.isfinite(table)) else None
    std = r.std if mode == "free" else None
    if not np.all(np.isfinite(table)):
        bad = [pnames[i] for i in np.flatnonzero(~np.all(np.isfinite(table), axis=1))]
        raise SoftplotError(f"no solution for point(s) {', '.join(bad[:5])}")
    try:
        with out_path.open("w", newline="") as fh:
            w = csv.writer(fh)
            dec = object_decimals(prec if prec is not None else [])
            w.writerow(OUT_COLUMNS + (("sX", "sY", "sZ") if std is not None else ()))
            for i, (nm, row) in enumerate(zip(pnames, table.tolist(), strict=True)):
                out = ([f"{x:.{PHOTO_DECIMALS}f}" for x in row[0:4]]
                       + [f"{x:.{dec}f}" for x in row[4:7]] + [f"{row[7]:.{PHOTO_DECIMALS}f}"])
                if std is not None:
                    out += [f"{s:.{dec + 1}f}" for s in std[i]]
                w.writerow([nm, *out])
    except OSError as exc:
        raise SoftplotError(f"cannot write {out_path}: {exc.strerror or exc}") from exc
    click.echo(f"{len(pnames)} point(s) restituted ({mode}) -> {out_path}")
    if check_path is not None:
        cnames, cv = _read_csv(Path(check_path), ("name", "X", "Y", "Z"), "check file")
        click.echo(check_table(pnames, r.XYZ, cnames, cv, dec))


def check_table(names, XYZ, check_names, check_XYZ, decimals: int) -> str:
    """Differences restituted - check (object units) per common point, and their RMS."""
    idx = {n: i for i, n in enumerate(check_names)}
    common = [(i, idx[n]) for i, n in enumerate(names) if n in idx]
    if not common:
        raise SoftplotError("no restituted point has a name in the check file")
    a = np.array([i for i, _ in common])
    b = np.array([j for _, j in common])
    d = np.asarray(XYZ, dtype=float)[a] - np.asarray(check_XYZ, dtype=float)[b]
    w = max(8, max(len(names[i]) for i in a) + 2)
    lines = [f"{'point':<{w}}{'dX':>12}{'dY':>12}{'dZ':>12}   (restituted - check)"]
    for i, row in zip(a, d, strict=True):
        lines.append(f"{names[i]:<{w}}" + "".join(f"{v:>12.{decimals}f}" for v in row))
    rms = np.sqrt(np.mean(d**2, axis=0))
    lines.append(f"{'RMS':<{w}}" + "".join(f"{v:>12.{decimals}f}" for v in rms)
                 + f"   over {len(a)} check point(s)")
    return "\n".join(lines)
