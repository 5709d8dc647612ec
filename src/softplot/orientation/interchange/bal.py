"""Bundle Adjustment in the Large (BAL) problems <-> softplot bundle data.

BAL's camera frame is softplot's photo frame (x right, y up, looking along -z):
``P = R X + t``, ``p = -P[:2] / P[2]``, ``pixel = f (1 + K1 |p|^2 + K2 |p|^4) p`` about the
image centre. softplot's forward lens model reproduces it exactly with a pixel size ``s``
(mm)::

    c = f s,  k1 = K1 / c^2,  k2 = K2 / c^4,  x0 = y0 = 0,  M = R,  X0 = -R' t,
    film (x, y) = pixel * s.

Every BAL camera becomes its own physical camera (``cam<i>``, photo ``img<i>``) with ``c, k1,
k2`` free; points are named by their index.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from softplot.adjust.bal import BALProblem, read_bal
from softplot.errors import SoftplotError
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix
from softplot.orientation.bundle import INTRINSICS, BundleCamera, BundleData

__all__ = ["read_bal_project", "write_bal_project", "bal_problem"]


def read_bal_project(path, pixel_size_um: float = 1.0, sigma_px: float = 1.0) -> BundleData:
    """Read a BAL file into :class:`BundleData` (forward lens model, approximations set)."""
    if not pixel_size_um > 0:
        raise SoftplotError("pixel size must be > 0")
    prob = read_bal(path)
    s = pixel_size_um / 1000.0
    C = prob.n_cameras
    R = Rotation.from_rotvec(prob.cameras[:, :3]).as_matrix()
    t = prob.cameras[:, 3:6]
    f, K1, K2 = prob.cameras[:, 6], prob.cameras[:, 7], prob.cameras[:, 8]
    if np.any(f * s <= 0):
        raise SoftplotError(f"{path}: a camera has a focal length <= 0")
    cams = []
    for i in range(C):
        c = f[i] * s
        v = np.zeros(len(INTRINSICS))
        v[0], v[3], v[4] = c, K1[i] / c**2, K2[i] / c**4
        bc = BundleCamera.build(f"cam{i}", v, ("c", "k1", "k2"), None, s, model="forward")
        bc.sigma_image_mm = sigma_px * s
        cams.append(bc)
    X0 = -np.einsum("cji,cj->ci", R, t)
    ang = np.column_stack(angles_from_matrix(R))
    P = prob.n_points
    return BundleData(
        cameras=cams,
        photo_names=[f"img{i}" for i in range(C)],
        photo_camera=np.arange(C),
        X0=X0,
        angles=ang,
        point_names=[str(j) for j in range(P)],
        XYZ=prob.points.copy(),
        control=np.full((P, 3), np.nan),
        control_sigma=np.full((P, 3), np.nan),
        obs_photo=prob.cam_index,
        obs_point=prob.point_index,
        xy=prob.xy * s,
        sigma_xy=sigma_px * s,
    )


def bal_problem(data: BundleData) -> BALProblem:
    """The BAL problem of ``data``: one BAL camera per photo (finite approximations).

    Raises
    ------
    SoftplotError
        A camera BAL cannot represent: inverse lens model with distortion, principal point,
        k3, decentering, affinity or aspect not zero, or no pixel size.
    """
    if not (np.all(np.isfinite(data.X0)) and np.all(np.isfinite(data.angles))):
        raise SoftplotError("export: exterior orientations missing (run the bundle first)")
    if not np.all(np.isfinite(data.XYZ)):
        raise SoftplotError("export: object coordinates missing (run the bundle first)")
    for c in data.cameras:
        v = c.values
        if c.pixel_size_mm is None:
            raise SoftplotError(f"camera {c.name}: pixel_size_um is needed for BAL (pixels)")
        if np.any(v[[1, 2, 5, 6, 7, 8, 9, 10]] != 0):
            raise SoftplotError(
                f"camera {c.name}: BAL has only f, K1, K2 (principal point, k3, p1, p2, b1, "
                "b2 and a must be 0)"
            )
        if c.model != "forward" and np.any(v[3:5] != 0):
            raise SoftplotError(
                f"camera {c.name}: its distortion uses the inverse lens model; BAL uses the "
                'forward model (adjust with lens = "forward" first)'
            )
    M = rotation_matrix(data.angles[:, 0], data.angles[:, 1], data.angles[:, 2])
    F = len(data.photo_names)
    cams = np.zeros((F, 9))
    cams[:, :3] = Rotation.from_matrix(M).as_rotvec()
    cams[:, 3:6] = -np.einsum("fij,fj->fi", M, data.X0)
    for f in range(F):
        cam = data.cameras[data.photo_camera[f]]
        c, s = cam.values[0], cam.pixel_size_mm
        cams[f, 6:9] = c / s, cam.values[3] * c**2, cam.values[4] * c**4
    s_obs = np.array([data.cameras[k].pixel_size_mm for k in data.photo_camera])[data.obs_photo]
    return BALProblem(
        cam_index=data.obs_photo.copy(),
        point_index=data.obs_point.copy(),
        xy=data.xy / s_obs[:, None],
        cameras=cams,
        points=data.XYZ.copy(),
    )


def write_bal_project(data: BundleData, path, overwrite: bool = False) -> Path:
    """Write ``data`` as a BAL text file (see :func:`bal_problem`)."""
    out = Path(path)
    if out.exists() and not overwrite:
        raise SoftplotError(f"{out} exists; not overwriting")
    prob = bal_problem(data)
    L = [f"{prob.n_cameras} {prob.n_points} {prob.n_observations}"]
    for o in range(prob.n_observations):
        L.append(
            f"{prob.cam_index[o]} {prob.point_index[o]} {float(prob.xy[o, 0])!r} "
            f"{float(prob.xy[o, 1])!r}"
        )
    L.extend(repr(float(x)) for x in prob.cameras.ravel())
    L.extend(repr(float(x)) for x in prob.points.ravel())
    out.write_text("\n".join(L) + "\n", encoding="utf-8")
    return out
