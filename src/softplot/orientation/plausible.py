"""Units that cannot be right, refused before an adjustment turns them into a "result".

Photo coordinates are millimetres in the photo system (reduced to the principal point,
docs/conventions.md). Pixel coordinates (thousands, all positive) or film coordinates of
another camera given in their place make every orientation converge to nonsense with a
"blunder" somewhere; these checks refuse them in one line with the fix.

* :func:`check_photo_coords` - no point may lie farther from the principal point than 1.5
  times the half-diagonal of the camera's format (when the format is known), nor farther than
  :data:`MAX_FIELD_RATIO` times the principal distance (a half field angle of 72 degrees, wider
  than any film mapping lens).
* :func:`check_model_scale` - model (or object) coordinates and control coordinates of the
  same points must agree on one scale: each point's median distance ratio to the others
  within a factor :data:`MAX_SCALE_SPREAD` of the median over the points (mixed units - metres and
  millimetres, a model in photo mm - break this).
"""

from __future__ import annotations

import warnings

import numpy as np

from softplot.errors import SoftplotError

__all__ = ["check_photo_coords", "check_model_scale", "MAX_FIELD_RATIO", "MAX_SCALE_SPREAD"]

#: photo radius / principal distance above which coordinates cannot be photo mm
MAX_FIELD_RATIO = 3.0
#: per-point scale (control distance / model distance) may differ from the median by this
MAX_SCALE_SPREAD = 10.0

FIX_PHOTO = ("convert scan pixels to photo mm first: softplot correct SCAN --camera CAMERA "
             "--points IN.csv --out OUT.csv --to photo")


def check_photo_coords(xy, c: float, *, what: str, format_mm=None, camera: str = "") -> None:
    """Refuse photo coordinates (n, 2) mm that cannot be of a camera with principal distance
    ``c`` mm (and format ``format_mm`` = (width, height) mm, when known)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if xy.size == 0:
        return
    r = np.hypot(xy[:, 0], xy[:, 1])
    rmax = float(np.nanmax(r))
    cam = f" of {camera}" if camera else ""
    if format_mm is not None:
        lim = 1.5 * 0.5 * float(np.hypot(*format_mm))
        if rmax > lim:
            raise SoftplotError(
                f"{what}: photo coordinates reach {rmax:.1f} mm from the principal point, "
                f"beyond the {format_mm[0]:g} x {format_mm[1]:g} mm format{cam}; not photo mm? "
                + FIX_PHOTO
            )
    lim = MAX_FIELD_RATIO * float(c)
    if rmax > lim:
        raise SoftplotError(
            f"{what}: photo coordinates reach {rmax:.1f} mm from the principal point, more than "
            f"{MAX_FIELD_RATIO:g} x the principal distance ({c:g} mm); not photo mm? " + FIX_PHOTO
        )


def check_model_scale(model, control, names, *, what: str) -> None:
    """Refuse model coordinates (n, 3) and control coordinates (n, 3) of the same points
    (``names``) that do not share one scale (a point whose distances to the others give a
    scale more than :data:`MAX_SCALE_SPREAD` times off the median)."""
    m = np.asarray(model, float).reshape(-1, 3)
    g = np.asarray(control, float).reshape(-1, 3)
    fin = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(g), axis=1)
    m, g, names = m[fin], g[fin], np.asarray(names, dtype=object)[fin]
    if len(m) < 3:
        return
    dm = np.linalg.norm(m[:, None] - m[None], axis=2)
    dg = np.linalg.norm(g[:, None] - g[None], axis=2)
    if dm.max() <= 0 or dg.max() <= 0:
        raise SoftplotError(f"{what}: all points coincide; no scale can be found")
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a row of coincident points: NaN
        ratio = np.where(dm > 1e-6 * dm.max(), dg / dm, np.nan)
        np.fill_diagonal(ratio, np.nan)
        s = np.nanmedian(ratio, axis=1)  # each point's scale against all the others
    ok = np.isfinite(s) & (s > 0)
    if ok.sum() < 3:
        return
    s = s[ok]
    med = float(np.median(s))
    off = np.abs(np.log(s / med))
    worst = int(np.argmax(off))
    if off[worst] > np.log(MAX_SCALE_SPREAD):
        name = names[ok][worst]
        raise SoftplotError(
            f"{what}: point {name} gives a model -> control scale of {s[worst]:.4g}, the others "
            f"{med:.4g}: no one scale fits (mixed units, or a point's coordinates in another "
            "system?); give every coordinate of a file in one unit"
        )
