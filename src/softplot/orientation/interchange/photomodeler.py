"""PhotoModeler's text export (the format DBAT reads) -> softplot bundle data.

The file (whitespace-separated; blocks end with a blank line)::

    TITLE
    TOLERANCE MAX_ITERATIONS [IMAGE_WIDTH IMAGE_HEIGHT]          (pixels)
    default std: photo coordinates (mm), control, object points, camera position, angles
    default camera: C XP YP FW FH K1 K2 [K3] P1 P2                (mm)
    default camera std
    per photo N (0-based), six lines:
        N FILE_NAME
        N X Y Z KAPPA PHI OMEGA                                   (object units, degrees)
        N their std
        N covariances of X, Y, Z (may be empty)
        N C XP YP FW FH K1 K2 [K3] P1 P2
        N their std (0: fixed)
    (blank)
    control points: ID X Y Z SX SY SZ
    (blank)
    object points: ID X Y Z SX SY SZ                              (approximations)
    (blank)
    marked points: PHOTO ID COL ROW SX SY                         (pixels; std in mm, 0: default)

PhotoModeler's camera (a correction model in mm, y up, the principal point ``XP, YP`` measured
from the top-left corner of the format, *downwards*): ``corrected = m + m (K1 r^2 + K2 r^4 +
K3 r^6) + (P1 (r^2 + 2 x^2) + 2 P2 x y, P2 (r^2 + 2 y^2) + 2 P1 x y)`` with ``m`` the measured
point reduced to the principal point. softplot's inverse lens model with film origin at the
format centre reproduces it exactly::

    c = C,  x0 = XP - FW/2,  y0 = FH/2 - YP,  k = -K,  p1 = -P1,  p2 = -P2,
    film x = COL * FW / W - FW/2,  film y = FH/2 - ROW * FH / H.

An estimated format width (its std not 0) is PhotoModeler's scale of the measured x: it becomes
the aspect ``a`` (free). Angles: ``M = Mk Mp Mo`` of omega, phi, kappa; exterior orientations
that do not reproduce the image points are dropped and initialised by resection instead.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from softplot.errors import SoftplotError
from softplot.orientation.bundle import INTRINSICS, BundleCamera, BundleData

__all__ = ["read_photomodeler", "read_control_file", "pm_to_softplot"]


def pm_to_softplot(c, xp, yp, fw, fh, K, P) -> np.ndarray:
    """softplot intrinsics (11,) of a PhotoModeler camera (``K`` = K1..K3, ``P`` = P1, P2)."""
    v = np.zeros(len(INTRINSICS))
    K = list(K) + [0.0] * (3 - len(K))
    v[:3] = c, xp - fw / 2.0, fh / 2.0 - yp
    v[3:6] = -K[0], -K[1], -K[2]
    v[6:8] = -P[0], -P[1]
    return v


def _nums(tokens, where):
    try:
        return [float(t) for t in tokens]
    except ValueError as exc:
        raise SoftplotError(f"{where}: not a number ({exc})") from exc


def _camera(vals, where):
    """C XP YP FW FH K1 K2 [K3] P1 P2 -> (c, xp, yp, fw, fh, K, P)."""
    if len(vals) == 10:
        c, xp, yp, fw, fh, k1, k2, k3, p1, p2 = vals
    elif len(vals) == 9:
        c, xp, yp, fw, fh, k1, k2, p1, p2 = vals
        k3 = 0.0
    else:
        raise SoftplotError(f"{where}: camera needs C XP YP FW FH K1 K2 [K3] P1 P2")
    return c, xp, yp, fw, fh, (k1, k2, k3), (p1, p2)


def read_photomodeler(path, image_size=None, control=None) -> BundleData:
    """Read a PhotoModeler text export into :class:`BundleData`.

    Parameters
    ----------
    path : path
    image_size : (W, H) pixels, optional
        Overrides the size on line 2 (needed when the file has none).
    control : path, optional
        A control file (:func:`read_control_file`) replacing the export's control points.

    Returns
    -------
    BundleData
        One physical camera per distinct camera of the photos (inverse lens model, the
        parameters with a std > 0 free), exterior orientations and object points as
        approximations, control fixed (std 0) or weighted.
    """
    p = Path(path)
    if not p.is_file():
        raise SoftplotError(f"PhotoModeler file not found: {p}")
    try:
        lines = p.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise SoftplotError(f"cannot read {p}: {exc}") from exc
    if len(lines) < 6:
        raise SoftplotError(f"{p}: too short for a PhotoModeler export (5 header lines)")
    head = _nums(lines[1].split(), f"{p} line 2")
    if image_size is None:
        if len(head) < 4:
            raise SoftplotError(f"{p}: no image size on line 2; give it (--image-size W H)")
        image_size = (head[2], head[3])
    W, H = (float(v) for v in image_size)
    def_std = _nums(lines[2].split(), f"{p} line 3")
    sig_img = def_std[0] if def_std and def_std[0] > 0 else 0.001
    i = 5
    photos = []
    while i < len(lines) and lines[i].strip():
        t = lines[i].split(None, 1)
        where = f"{p} line {i + 1}"
        if len(t) < 2 or i + 5 >= len(lines):
            raise SoftplotError(f"{where}: a photo block needs 6 lines (N NAME, outer, ...)")
        name = t[1].strip()
        outer = _nums(lines[i + 1].split()[1:], f"{p} line {i + 2}")
        inner = _nums(lines[i + 4].split()[1:], f"{p} line {i + 5}")
        inner_std = _nums(lines[i + 5].split()[1:], f"{p} line {i + 6}")
        if len(outer) != 6:
            raise SoftplotError(f"{p} line {i + 2}: X Y Z KAPPA PHI OMEGA expected")
        photos.append((name, outer, _camera(inner, f"{p} line {i + 5}"), inner_std))
        i += 6
    if not photos:
        raise SoftplotError(f"{p}: no photos")

    def table(i, ncol, what):
        rows = []
        while i < len(lines) and lines[i].strip():
            v = lines[i].split()
            if len(v) < ncol:
                raise SoftplotError(f"{p} line {i + 1}: {what} needs {ncol} columns")
            rows.append((v[0], _nums(v[1:ncol], f"{p} line {i + 1}")))
            i += 1
        return rows, i + 1

    ctl_rows, i = table(i + 1, 7, "a control point")
    obj_rows, i = table(i, 7, "an object point")
    mark_rows, i = table(i, 6, "a marked point")
    if not mark_rows:
        raise SoftplotError(f"{p}: no marked points")
    # cameras: one per distinct (c, xp, yp, fw, fh, K, P)
    cams, cam_of, fmt = [], [], []
    keys: dict = {}
    for _name, _, cam, std in photos:
        key = (cam[:5], cam[5], cam[6])
        if key not in keys:
            c, xp, yp, fw, fh, K, P = cam
            vals = pm_to_softplot(c, xp, yp, fw, fh, K, P)
            std = list(std)
            if len(std) == 9:  # no K3
                std = std[:7] + [0.0] + std[7:]
            std += [0.0] * (10 - len(std))
            sc, sxp, syp, sfw, _sfh, sk1, sk2, sk3, sp1, sp2 = std[:10]
            free = [
                n
                for n, s in zip(
                    ("c", "x0", "y0", "a", "k1", "k2", "k3", "p1", "p2"),
                    (sc, sxp, syp, sfw, sk1, sk2, sk3, sp1, sp2),
                    strict=True,
                )
                if s > 0
            ]
            bc = BundleCamera.build(f"pm{len(cams)}", vals, free, None, None, model="inverse")
            bc.sigma_image_mm = sig_img
            bc.pixel_size_mm = fw / W
            bc.image_size = (int(round(W)), int(round(H)))
            fmt.append((fw, fh))
            keys[key] = len(cams)
            cams.append(bc)
        cam_of.append(keys[key])
    from softplot.geometry.rotation import to_radians

    F = len(photos)
    X0 = np.array([ph[1][:3] for ph in photos], float)
    kpo = np.array([ph[1][3:] for ph in photos], float)
    ang = np.column_stack(
        [to_radians(kpo[:, 2], "deg"), to_radians(kpo[:, 1], "deg"), to_radians(kpo[:, 0], "deg")]
    )
    # points: ids of marked points, control, object approximations
    pt_idx: dict[str, int] = {}
    op, oq, xy, sxy = [], [], [], []
    for ph, v in mark_rows:  # PHOTO ID COL ROW SX SY
        if not _is_int(ph) or not 0 <= int(float(ph)) < F:
            raise SoftplotError(f"{p}: a marked point refers to photo {ph} (have 0..{F - 1})")
        f = int(float(ph))
        pid = repr(v[0]) if not float(v[0]).is_integer() else str(int(v[0]))
        fw, fh = fmt[cam_of[f]]
        col, row, sx, sy = v[1], v[2], v[3], v[4]
        key = str(int(float(pid))) if _is_int(pid) else pid
        op.append(f)
        oq.append(pt_idx.setdefault(key, len(pt_idx)))
        xy.append([col * fw / W - fw / 2.0, fh / 2.0 - row * fh / H])
        sxy.append([sx if sx > 0 else sig_img, sy if sy > 0 else sig_img])
    P = len(pt_idx)
    XYZ = np.full((P, 3), np.nan)
    for pid, v in obj_rows:
        key = str(int(float(pid))) if _is_int(pid) else pid
        if key in pt_idx:
            XYZ[pt_idx[key]] = v[:3]
    ctl_xyz = np.full((P, 3), np.nan)
    csig = np.full((P, 3), np.nan)
    ctl = (
        read_control_file(control)
        if control is not None
        else [(pid, v[:3], v[3:6]) for pid, v in ctl_rows]
    )
    for pid, xyz, sd in ctl:
        key = str(int(float(pid))) if _is_int(pid) else pid
        if key in pt_idx:
            ctl_xyz[pt_idx[key]] = xyz
            csig[pt_idx[key]] = sd
    names = [None] * P
    for n, j in pt_idx.items():
        names[j] = n
    data = BundleData(
        cameras=cams,
        photo_names=[ph[0] for ph in photos],
        photo_camera=np.array(cam_of),
        X0=X0,
        angles=ang,
        point_names=names,
        XYZ=XYZ,
        control=ctl_xyz,
        control_sigma=csig,
        obs_photo=np.array(op),
        obs_point=np.array(oq),
        xy=np.array(xy),
        sigma_xy=np.array(sxy),
    )
    _drop_inconsistent_orientations(data)
    return data


def _is_int(s: str) -> bool:
    try:
        return float(s) == int(float(s))
    except ValueError:
        return False


def _drop_inconsistent_orientations(d: BundleData, tol_mm: float = 1.0) -> None:
    """Exterior orientations whose projection of the known object points misses the marked
    points by more than ``tol_mm`` (RMS) are set to NaN (initialised by resection)."""
    from softplot.geometry.rotation import rotation_matrix

    known = np.all(np.isfinite(d.XYZ), axis=1)
    M = rotation_matrix(d.angles[:, 0], d.angles[:, 1], d.angles[:, 2])
    for f in range(len(d.photo_names)):
        o = np.flatnonzero((d.obs_photo == f) & known[d.obs_point])
        if o.size < 3 or not np.all(np.isfinite(d.X0[f])):
            continue
        cam = d.cameras[d.photo_camera[f]].values
        u = (d.XYZ[d.obs_point[o]] - d.X0[f]) @ M[f].T
        with np.errstate(divide="ignore", invalid="ignore"):
            pred = -cam[0] * u[:, :2] / u[:, 2:3] + cam[1:3]
        rms = float(np.sqrt(np.mean((pred - d.xy[o]) ** 2)))
        if not math.isfinite(rms) or rms > tol_mm or np.any(u[:, 2] >= 0):
            d.X0[f] = np.nan
            d.angles[f] = np.nan


def read_control_file(path) -> list:
    """Control points ``ID X Y Z [SX SY SZ]`` (whitespace or commas; ``#`` comments; std 0
    or absent: fixed). Returns ``[(id, (X, Y, Z), (sX, sY, sZ)), ...]``."""
    p = Path(path)
    if not p.is_file():
        raise SoftplotError(f"control file not found: {p}")
    out = []
    for k, ln in enumerate(p.read_text(encoding="utf-8").splitlines()):
        ln = ln.split("#", 1)[0].replace(",", " ").strip()
        if not ln:
            continue
        t = ln.split()
        if len(t) not in (4, 7):
            raise SoftplotError(f"{p} line {k + 1}: expected ID X Y Z [SX SY SZ]")
        v = _nums(t[1:], f"{p} line {k + 1}")
        sd = v[3:6] if len(v) == 6 else [0.0, 0.0, 0.0]
        if min(sd) < 0:
            raise SoftplotError(f"{p} line {k + 1}: negative standard error")
        out.append((t[0], v[:3], sd))
    if not out:
        raise SoftplotError(f"{p}: no control points")
    return out
