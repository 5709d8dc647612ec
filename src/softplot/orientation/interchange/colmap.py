"""COLMAP text models <-> softplot bundle data.

COLMAP's frames: ``x_cam = R X + t`` (``R`` from the quaternion ``QW QX QY QZ``), the camera
looks along +z, image x right and y *down*; pixel coordinates with the centre of the top-left
pixel at (0.5, 0.5). Its ``OPENCV`` model (forward: distortion added to the normalised
projection ``(u, v) = (x/z, y/z)``)::

    col = fx (u (1 + K1 r^2 + K2 r^4 [+ K3 r^6]) + 2 P1 u v + P2 (r^2 + 2 u^2)) + cx
    row = fy (v (1 + K1 r^2 + K2 r^4 [+ K3 r^6]) + P1 (r^2 + 2 v^2) + 2 P2 u v) + cy

softplot's forward lens model reproduces it exactly with a pixel size ``p`` (mm), the film
origin at the image centre ``(W/2, H/2)`` and (see ``docs/bundle.md`` for the table)::

    c = fy p,  a = fy / fx - 1,  x0 = (cx - W/2) p,  y0 = (H/2 - cy) p,
    k1 = K1 / c^2,  k2 = K2 / c^4,  k3 = K3 / c^6,  p1 = P2 / c,  p2 = -P1 / c,
    M = diag(1, -1, -1) R,  X0 = -R' t.

Supported camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and
FULL_OPENCV without the rational terms (K4 = K5 = K6 = 0). Written: OPENCV, or FULL_OPENCV
when k3 is not zero.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from softplot.errors import SoftplotError
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix
from softplot.orientation.bundle import INTRINSICS, BundleCamera, BundleData

__all__ = ["read_colmap", "write_colmap", "FLIP", "opencv_from_softplot", "softplot_from_opencv"]

#: COLMAP camera axes (y down, looking along +z) -> softplot photo axes (y up, looking along -z)
FLIP = np.diag([1.0, -1.0, -1.0])

_N_PARAMS = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "FULL_OPENCV": 12,
}


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise SoftplotError(f"missing {path.name} in {path.parent}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SoftplotError(f"cannot read {path}: {exc}") from exc
    return [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def _floats(tokens, where):
    try:
        return [float(t) for t in tokens]
    except ValueError as exc:
        raise SoftplotError(f"{where}: not a number ({exc})") from exc


def opencv_params(model: str, params) -> np.ndarray:
    """``fx, fy, cx, cy, K1, K2, P1, P2, K3`` (pixels) of a COLMAP camera model."""
    p = list(params)
    out = np.zeros(9)
    if model == "SIMPLE_PINHOLE":
        out[:4] = p[0], p[0], p[1], p[2]
    elif model == "PINHOLE":
        out[:4] = p[:4]
    elif model == "SIMPLE_RADIAL":
        out[:5] = p[0], p[0], p[1], p[2], p[3]
    elif model == "RADIAL":
        out[:6] = p[0], p[0], p[1], p[2], p[3], p[4]
    elif model == "OPENCV":
        out[:8] = p[:8]
    elif model == "FULL_OPENCV":
        if any(p[9:12]):
            raise SoftplotError(
                "FULL_OPENCV camera with rational terms K4..K6: softplot's Brown model cannot "
                "represent them"
            )
        out[:8] = p[:8]
        out[8] = p[8]
    else:
        raise SoftplotError(
            f"COLMAP camera model {model} is not supported; use one of {', '.join(_N_PARAMS)}"
        )
    return out


def softplot_from_opencv(cv, size, pixel_mm: float) -> np.ndarray:
    """softplot intrinsics (11,) of a forward-model camera from ``fx, fy, cx, cy, K1, K2, P1,
    P2, K3`` (pixels) for an image of ``size`` (W, H) pixels with pixel size ``pixel_mm``."""
    fx, fy, cx, cy, K1, K2, P1, P2, K3 = cv
    W, H = size
    c = fy * pixel_mm
    v = np.zeros(len(INTRINSICS))
    v[:3] = c, (cx - W / 2.0) * pixel_mm, (H / 2.0 - cy) * pixel_mm
    v[3:8] = K1 / c**2, K2 / c**4, K3 / c**6, P2 / c, -P1 / c
    v[10] = fy / fx - 1.0
    return v


def opencv_from_softplot(v, size, pixel_mm: float, name: str = "") -> np.ndarray:
    """Inverse of :func:`softplot_from_opencv`; refuses what OpenCV cannot represent."""
    v = np.asarray(v, float)
    if v[8] != 0 or v[9] != 0:
        raise SoftplotError(
            f"camera {name}: the affinity/shear b1, b2 have no OpenCV equivalent (use the "
            "aspect a instead of b1)"
        )
    c = v[0]
    W, H = size
    fy = c / pixel_mm
    fx = fy / (1.0 + v[10])
    cx = v[1] / pixel_mm + W / 2.0
    cy = H / 2.0 - v[2] / pixel_mm
    return np.array([fx, fy, cx, cy, v[3] * c**2, v[4] * c**4, -v[7] * c, v[6] * c, v[5] * c**6])


def read_colmap(folder, pixel_size_um: float = 1.0, sigma_px: float = 1.0) -> BundleData:
    """Read a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    Parameters
    ----------
    folder : path
        The sparse model folder.
    pixel_size_um : float
        Pixel size giving film mm (``c = fy * pixel``); any value gives the same geometry.
    sigma_px : float
        Standard error of the image points, pixels.

    Returns
    -------
    BundleData
        Forward lens model cameras (free: ``c, x0, y0, k1, k2, p1, p2`` as the COLMAP model
        has them), exterior orientations and points as approximations, no control.
    """
    root = Path(folder)
    if not root.is_dir():
        raise SoftplotError(f"COLMAP model folder not found: {root}")
    if not pixel_size_um > 0:
        raise SoftplotError("pixel size must be > 0")
    pix = pixel_size_um / 1000.0
    cams, cam_idx = [], {}
    for k, ln in enumerate(_lines(root / "cameras.txt")):
        t = ln.split()
        where = f"cameras.txt line {k + 1}"
        if len(t) < 4:
            raise SoftplotError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS")
        model = t[1]
        if model not in _N_PARAMS:
            raise SoftplotError(
                f"{where}: camera model {model} is not supported; use one of {', '.join(_N_PARAMS)}"
            )
        if len(t) != 4 + _N_PARAMS[model]:
            raise SoftplotError(f"{where}: {model} needs {_N_PARAMS[model]} parameters")
        W, H = int(t[2]), int(t[3])
        cv = opencv_params(model, _floats(t[4:], where))
        vals = softplot_from_opencv(cv, (W, H), pix)
        free = ["c", "x0", "y0"]
        if model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
            free.append("a")
        if model != "SIMPLE_PINHOLE" and model != "PINHOLE":
            free.append("k1")
        if model in ("RADIAL", "OPENCV", "FULL_OPENCV"):
            free.append("k2")
        if model in ("OPENCV", "FULL_OPENCV"):
            free += ["p1", "p2"]
        if model == "FULL_OPENCV":
            free.append("k3")
        bc = BundleCamera.build(f"cam{t[0]}", vals, free, None, pix, model="forward")
        bc.image_size = (W, H)
        bc.sigma_image_mm = sigma_px * pix
        cam_idx[t[0]] = len(cams)
        cams.append(bc)
    if not cams:
        raise SoftplotError("cameras.txt: no cameras")
    # points first (ids -> index)
    pt_ids, XYZ = [], []
    for k, ln in enumerate(_lines(root / "points3D.txt")):
        t = ln.split()
        if len(t) < 8:
            raise SoftplotError(f"points3D.txt line {k + 1}: expected POINT3D_ID X Y Z R G B ERROR")
        pt_ids.append(t[0])
        XYZ.append(_floats(t[1:4], f"points3D.txt line {k + 1}"))
    pidx = {p: i for i, p in enumerate(pt_ids)}
    path = root / "images.txt"
    raw = _lines(path) and path.read_text(encoding="utf-8").splitlines()
    lines = [ln for ln in raw if not ln.lstrip().startswith("#")]
    while lines and not lines[-1].strip():
        lines.pop()  # COLMAP pairs an image line with a (possibly empty) POINTS2D line
    names, pcam, X0, ang = [], [], [], []
    op, oq, xy = [], [], []
    for i in range(0, len(lines), 2):
        t = lines[i].split()
        where = f"images.txt image line {len(names) + 1}"
        if len(t) < 10:
            raise SoftplotError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        q = _floats(t[1:5], where)
        tt = np.array(_floats(t[5:8], where))
        if t[8] not in cam_idx:
            raise SoftplotError(f"{where}: unknown camera {t[8]}")
        cam = cams[cam_idx[t[8]]]
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        M = FLIP @ R
        f = len(names)
        names.append(" ".join(t[9:]))
        pcam.append(cam_idx[t[8]])
        X0.append(-R.T @ tt)
        ang.append(np.array(angles_from_matrix(M[None]))[:, 0])
        pts2 = lines[i + 1].split() if i + 1 < len(lines) else []
        if len(pts2) % 3:
            raise SoftplotError(f"{where}: the POINTS2D line needs triples X Y POINT3D_ID")
        W, H = cam.image_size
        pix_c = cam.pixel_size_mm
        for j in range(0, len(pts2), 3):
            pid = pts2[j + 2]
            if pid == "-1":
                continue
            if pid not in pidx:
                raise SoftplotError(f"{where}: unknown 3-D point {pid}")
            col, row = _floats(pts2[j : j + 2], where)
            op.append(f)
            oq.append(pidx[pid])
            xy.append([(col - W / 2.0) * pix_c, (H / 2.0 - row) * pix_c])
    if not names:
        raise SoftplotError("images.txt: no images")
    used = np.zeros(len(pt_ids), bool)
    used[np.asarray(oq, np.int64)] = True
    pmap = -np.ones(len(pt_ids), np.int64)
    pmap[used] = np.arange(used.sum())
    P = int(used.sum())
    sig = np.array([cams[pcam[f]].sigma_image_mm for f in op])
    return BundleData(
        cameras=cams,
        photo_names=names,
        photo_camera=np.array(pcam),
        X0=np.array(X0),
        angles=np.array(ang),
        point_names=[p for p, u in zip(pt_ids, used, strict=True) if u],
        XYZ=np.array(XYZ)[used],
        control=np.full((P, 3), np.nan),
        control_sigma=np.full((P, 3), np.nan),
        obs_photo=np.array(op),
        obs_point=pmap[np.array(oq, np.int64)],
        xy=np.array(xy),
        sigma_xy=np.column_stack([sig, sig]),
    )


def write_colmap(data: BundleData, folder, overwrite: bool = False) -> Path:
    """Write ``data`` (finite approximations) as a COLMAP text model.

    Every camera must use the forward lens model (or have no distortion), know its pixel size
    and image size, and have no affinity/shear ``b1, b2``.
    """
    root = Path(folder)
    names = ("cameras.txt", "images.txt", "points3D.txt")
    if not overwrite:
        for n in names:
            if (root / n).exists():
                raise SoftplotError(f"{root / n} exists; not overwriting")
    if not (np.all(np.isfinite(data.X0)) and np.all(np.isfinite(data.angles))):
        raise SoftplotError("export: exterior orientations missing (run the bundle first)")
    if not np.all(np.isfinite(data.XYZ)):
        raise SoftplotError("export: object coordinates missing (run the bundle first)")
    cam_lines = []
    for i, c in enumerate(data.cameras):
        _check_exportable(c)
        cv = opencv_from_softplot(c.values, c.image_size, c.pixel_size_mm, c.name)
        if cv[8] != 0:
            p = [*cv[:8], cv[8], 0.0, 0.0, 0.0]
            model = "FULL_OPENCV"
        else:
            p = list(cv[:8])
            model = "OPENCV"
        W, H = c.image_size
        cam_lines.append(f"{i + 1} {model} {W} {H} " + " ".join(repr(float(x)) for x in p))
    # point ids: the point names when they are positive integers (an imported model), else 1..P
    try:
        ids = [int(n) for n in data.point_names]
        if min(ids) < 1 or len(set(ids)) != len(ids):
            raise ValueError
    except ValueError:
        ids = list(range(1, len(data.point_names) + 1))
    M = rotation_matrix(data.angles[:, 0], data.angles[:, 1], data.angles[:, 2])
    img_lines = []
    track: dict[int, list] = {}
    for f, name in enumerate(data.photo_names):
        c = data.cameras[data.photo_camera[f]]
        R = FLIP @ M[f]
        t = -R @ data.X0[f]
        qx, qy, qz, qw = Rotation.from_matrix(R).as_quat()
        img_lines.append(
            f"{f + 1} {_r(qw)} {_r(qx)} {_r(qy)} {_r(qz)} {_r(t[0])} {_r(t[1])} {_r(t[2])} "
            f"{data.photo_camera[f] + 1} {name}"
        )
        obs = np.flatnonzero(data.obs_photo == f)
        W, H = c.image_size
        pix = c.pixel_size_mm
        items = []
        for j, o in enumerate(obs):
            col = data.xy[o, 0] / pix + W / 2.0
            row = H / 2.0 - data.xy[o, 1] / pix
            p = int(data.obs_point[o])
            items.append(f"{_r(col)} {_r(row)} {ids[p]}")
            track.setdefault(p, []).append(f"{f + 1} {j}")
        img_lines.append(" ".join(items))
    pt_lines = []
    for p in range(len(data.point_names)):
        X = data.XYZ[p]
        pt_lines.append(
            f"{ids[p]} {_r(X[0])} {_r(X[1])} {_r(X[2])} 128 128 128 0 " + " ".join(track.get(p, []))
        )
    root.mkdir(parents=True, exist_ok=True)
    hdr = "# written by softplot\n"
    (root / "cameras.txt").write_text(hdr + "\n".join(cam_lines) + "\n", encoding="utf-8")
    (root / "images.txt").write_text(hdr + "\n".join(img_lines) + "\n", encoding="utf-8")
    (root / "points3D.txt").write_text(hdr + "\n".join(pt_lines) + "\n", encoding="utf-8")
    return root


def _r(x) -> str:
    return repr(float(x))


def _check_exportable(c: BundleCamera) -> None:
    if c.pixel_size_mm is None or c.image_size is None:
        raise SoftplotError(
            f"camera {c.name}: pixel_size_um and image_width_px/image_height_px are needed for "
            "a pixel format"
        )
    if c.model != "forward" and np.any(c.values[3:10] != 0):
        raise SoftplotError(
            f"camera {c.name}: its distortion uses the inverse lens model; pixel formats use "
            'the forward model (adjust with lens = "forward" first)'
        )
