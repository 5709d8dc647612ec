"""Collinearity equations: object points -> photo mm, analytic Jacobians, image rays.

Convention (``docs/conventions.md``): object/model frame right-handed, Z up;
photo frame x right, y up, z backward (the camera looks along -z), principal distance
``c > 0``; ``M = Mk @ Mp @ Mo`` from :mod:`softplot.geometry.rotation` rotates object axes into
photo axes. With ``u = M @ (X - X0)``::

    x = x0 - c * u[0] / u[2]
    y = y0 - c * u[1] / u[2]

A point in front of the camera has ``u[2] < 0``.

Every function broadcasts over points: the exterior orientation (``X0``, angles / ``M``) and
the interior one (``c``, ``x0``, ``y0``) may be given once or per point (the bundle helper
passes per-observation arrays).
"""

from __future__ import annotations

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.rotation import rotation_derivatives, rotation_matrix

__all__ = ["project", "project_jacobian", "JACOBIAN_COLUMNS", "image_rays", "camera_coordinates"]

#: column order of the Jacobian returned by :func:`project_jacobian`
JACOBIAN_COLUMNS = ("X0", "Y0", "Z0", "omega", "phi", "kappa", "X", "Y", "Z", "c", "x0", "y0")


def _points(XYZ) -> np.ndarray:
    XYZ = np.asarray(XYZ, dtype=float)
    if XYZ.ndim == 1:
        XYZ = XYZ[None, :]
    if XYZ.ndim != 2 or XYZ.shape[1] != 3:
        raise SoftplotError(f"object points must be (N,3), got shape {np.shape(XYZ)}")
    return XYZ


def camera_coordinates(XYZ, X0, M) -> np.ndarray:
    """``u = M @ (X - X0)`` for every point: object -> photo-axis frame (same unit as object).

    Parameters
    ----------
    XYZ : array_like, shape (N, 3)
        Object (or model) coordinates.
    X0 : array_like, shape (3,) or (N, 3)
        Projection centre, object frame.
    M : array_like, shape (3, 3) or (N, 3, 3)
        Rotation object -> photo axes.

    Returns
    -------
    ndarray, shape (N, 3)
        Photo-axis coordinates; points in front of the camera have a negative third component.
    """
    XYZ = _points(XYZ)
    d = XYZ - np.asarray(X0, dtype=float)
    M = np.asarray(M, dtype=float)
    if M.ndim == 2:
        return d @ M.T
    return np.einsum("nij,nj->ni", M, d)


def project(XYZ, X0, M, c, x0=0.0, y0=0.0) -> np.ndarray:
    """Project object points into the photo by the collinearity equations.

    Parameters
    ----------
    XYZ : array_like, shape (N, 3)
        Object (or model) coordinates.
    X0 : array_like, shape (3,) or (N, 3)
        Projection centre in the object frame.
    M : array_like, shape (3, 3) or (N, 3, 3)
        Rotation object -> photo axes (:func:`softplot.geometry.rotation.rotation_matrix`).
    c : float or array_like (N,)
        Principal distance, mm (> 0).
    x0, y0 : float or array_like (N,)
        Principal point, photo mm.

    Returns
    -------
    ndarray, shape (N, 2)
        Photo coordinates, mm (x right, y up).
    """
    u = camera_coordinates(XYZ, X0, M)
    c = np.asarray(c, dtype=float)
    out = np.empty((u.shape[0], 2))
    out[:, 0] = np.asarray(x0, dtype=float) - c * u[:, 0] / u[:, 2]
    out[:, 1] = np.asarray(y0, dtype=float) - c * u[:, 1] / u[:, 2]
    return out


def project_jacobian(XYZ, X0, angles, c, x0=0.0, y0=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Photo coordinates and their analytic Jacobian.

    Parameters
    ----------
    XYZ : array_like, shape (N, 3)
        Object (or model) coordinates.
    X0 : array_like, shape (3,) or (N, 3)
        Projection centre, object frame.
    angles : array_like, shape (3,) or (N, 3)
        ``(omega, phi, kappa)`` in radians.
    c, x0, y0 : float or array_like (N,)
        Principal distance and principal point, mm.

    Returns
    -------
    xy : ndarray, shape (N, 2)
        Photo coordinates, mm.
    J : ndarray, shape (N, 2, 12)
        ``J[n, k, j] = d xy[n, k] / d p_j`` with ``p`` ordered as :data:`JACOBIAN_COLUMNS`:
        X0, Y0, Z0, omega, phi, kappa, X, Y, Z, c, x0, y0. The derivative w.r.t. X0 is minus
        the one w.r.t. X.
    """
    XYZ = _points(XYZ)
    angles = np.asarray(angles, dtype=float)
    om, ph, ka = angles[..., 0], angles[..., 1], angles[..., 2]
    M = rotation_matrix(om, ph, ka)
    dMs = rotation_derivatives(om, ph, ka)
    d = XYZ - np.asarray(X0, dtype=float)
    n = d.shape[0]
    if M.ndim == 2:
        u = d @ M.T
        du_ang = [d @ dM.T for dM in dMs]
        Mn = np.broadcast_to(M, (n, 3, 3))
    else:
        u = np.einsum("nij,nj->ni", M, d)
        du_ang = [np.einsum("nij,nj->ni", dM, d) for dM in dMs]
        Mn = M
    c = np.broadcast_to(np.asarray(c, dtype=float), (n,))
    w = u[:, 2]
    qx = u[:, 0] / w
    qy = u[:, 1] / w
    xy = np.empty((n, 2))
    xy[:, 0] = np.asarray(x0, dtype=float) - c * qx
    xy[:, 1] = np.asarray(y0, dtype=float) - c * qy
    # d xy / d u  (N, 2, 3)
    A = np.zeros((n, 2, 3))
    A[:, 0, 0] = -c / w
    A[:, 0, 2] = c * qx / w
    A[:, 1, 1] = -c / w
    A[:, 1, 2] = c * qy / w
    J = np.zeros((n, 2, 12))
    dXYZ = np.einsum("nkj,nji->nki", A, Mn)  # d xy / d X
    J[:, :, 6:9] = dXYZ
    J[:, :, 0:3] = -dXYZ
    for i, du in enumerate(du_ang):
        J[:, :, 3 + i] = np.einsum("nkj,nj->nk", A, du)
    J[:, 0, 9] = -qx
    J[:, 1, 9] = -qy
    J[:, 0, 10] = 1.0
    J[:, 1, 11] = 1.0
    return xy, J


def image_rays(xy, M, c, x0=0.0, y0=0.0) -> np.ndarray:
    """Unit ray directions in the object frame of photo points.

    Parameters
    ----------
    xy : array_like, shape (N, 2)
        Photo coordinates, mm.
    M : array_like, shape (3, 3) or (N, 3, 3)
        Rotation object -> photo axes.
    c, x0, y0 : float or array_like (N,)
        Principal distance and principal point, mm.

    Returns
    -------
    ndarray, shape (N, 3)
        ``M.T @ (x - x0, y - y0, -c)`` normalised: the direction from the projection centre
        towards the object point, object frame.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    n = xy.shape[0]
    v = np.empty((n, 3))
    v[:, 0] = xy[:, 0] - np.asarray(x0, dtype=float)
    v[:, 1] = xy[:, 1] - np.asarray(y0, dtype=float)
    v[:, 2] = -np.broadcast_to(np.asarray(c, dtype=float), (n,))
    M = np.asarray(M, dtype=float)
    r = v @ M if M.ndim == 2 else np.einsum("nji,nj->ni", M, v)
    return r / np.linalg.norm(r, axis=1, keepdims=True)
