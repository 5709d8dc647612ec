"""Synthetic photogrammetric networks with exact truth (shared by test field and block).

A :class:`Network` holds plain arrays: photos (true and approximate exterior orientation),
physical cameras (true interior orientation and the certificate values given to the
adjustment), object points (true, control with standard errors, check flags) and image
observations in *film* mm (x right, y up) with their noise. :meth:`Network.to_bundle_data`
converts it for :func:`softplot.orientation.bundle.bundle_adjust`.

Image observations are generated exactly as the bundle models them (``softplot.camera``
distortion convention): the photo point ``-c u1/u3`` is the *measured* point reduced to the
principal point minus the lens displacement evaluated at the measured point, solved by fixed
point iteration, then noise is added.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softplot.geometry.rotation import angles_from_matrix, rotation_matrix

__all__ = ["Network", "film_from_object", "look_at"]

INTRINSICS = ("c", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2")


def _displacement(xb, yb, p):
    k1, k2, k3, p1, p2, b1, b2 = p[3:10]
    r2 = xb * xb + yb * yb
    rad = r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = xb * rad + p1 * (r2 + 2 * xb * xb) + 2 * p2 * xb * yb + b1 * xb + b2 * yb
    dy = yb * rad + 2 * p1 * xb * yb + p2 * (r2 + 2 * yb * yb)
    return dx, dy


def film_from_object(XYZ, X0, M, intr):
    """Film coordinates (mm) of object points in one photo, distortion included.

    Parameters
    ----------
    XYZ : ndarray (N, 3)
        Object points.
    X0 : ndarray (3,)
        Projection centre.
    M : ndarray (3, 3)
        Rotation object -> photo axes.
    intr : ndarray (10,)
        ``c, x0, y0, k1, k2, k3, p1, p2, b1, b2``.

    Returns
    -------
    xy : ndarray (N, 2)
        Film mm.
    in_front : ndarray of bool (N,)
        In front of the camera and within 1 m of the principal point (else ``xy`` is NaN).
    """
    u = (np.asarray(XYZ, float) - X0) @ M.T
    c, x0, y0 = intr[:3]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        px, py = -c * u[:, 0] / u[:, 2], -c * u[:, 1] / u[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        front = (u[:, 2] < 0) & (np.abs(px) < 1e3) & (np.abs(py) < 1e3)
    px, py = np.where(front, px, 0.0), np.where(front, py, 0.0)  # behind / far out: not imaged
    xb, yb = px.copy(), py.copy()
    for _ in range(50):  # xb - d(xb) = px
        dx, dy = _displacement(xb, yb, intr)
        nxb, nyb = px + dx, py + dy
        if max(np.abs(nxb - xb).max(initial=0), np.abs(nyb - yb).max(initial=0)) < 1e-13:
            xb, yb = nxb, nyb
            break
        xb, yb = nxb, nyb
    xy = np.column_stack([xb + x0, yb + y0])
    xy[~front] = np.nan
    return xy, front


def look_at(C, target, roll=0.0, up=(0.0, 0.0, 1.0)):
    """Rotation ``M`` (object -> photo) of a camera at ``C`` looking at ``target``.

    Photo axes: x right, y up, z backwards (the camera looks along -z); ``roll`` (radians)
    turns the photo about its axis.
    """
    C, target, up = (np.asarray(v, float) for v in (C, target, up))
    zc = C - target
    zc /= np.linalg.norm(zc)
    xc = np.cross(up, zc)
    if np.linalg.norm(xc) < 1e-9:
        xc = np.cross([0.0, 1.0, 0.0], zc)
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    M = np.vstack([xc, yc, zc])
    cr, sr = np.cos(roll), np.sin(roll)
    Rz = np.array([[cr, sr, 0], [-sr, cr, 0], [0, 0, 1]])
    return Rz @ M


@dataclass
class Network:
    """A synthetic network with exact truth (object units m, image mm, angles rad)."""

    camera_names: list
    intr_true: np.ndarray  # (C, 10)
    intr_given: np.ndarray  # (C, 10) start values given to the adjustment
    format_mm: list  # per camera (w, h)
    photo_names: list
    photo_camera: np.ndarray  # (F,)
    X0_true: np.ndarray  # (F, 3)
    M_true: np.ndarray  # (F, 3, 3)
    X0_approx: np.ndarray
    angles_approx: np.ndarray
    point_names: list
    XYZ_true: np.ndarray  # (P, 3)
    XYZ_approx: np.ndarray
    control: np.ndarray  # (P, 3) known coordinates (noisy by control_sigma), nan = unknown
    control_sigma: np.ndarray  # (P, 3) 0 fixed, >0 weighted, nan none
    check: np.ndarray  # (P,) bool
    obs_photo: np.ndarray
    obs_point: np.ndarray
    xy: np.ndarray  # (m, 2) film mm, noisy
    xy_true: np.ndarray  # (m, 2) film mm, exact
    sigma_xy: float  # mm
    info: dict = field(default_factory=dict)

    @property
    def angles_true(self) -> np.ndarray:
        return np.column_stack(angles_from_matrix(self.M_true))

    def to_bundle_data(self, free=("c", "x0", "y0", "k1"), weighted=None, pixel_size_mm=None):
        """:class:`softplot.orientation.bundle.BundleData` of this network.

        ``free`` / ``weighted`` apply to every camera (see ``BundleCamera.build``).
        """
        from softplot.orientation.bundle import BundleCamera, BundleData

        cams = [
            BundleCamera.build(n, self.intr_given[i], free, weighted, pixel_size_mm)
            for i, n in enumerate(self.camera_names)
        ]
        return BundleData(
            cameras=cams,
            photo_names=list(self.photo_names),
            photo_camera=self.photo_camera,
            X0=self.X0_approx,
            angles=self.angles_approx,
            point_names=list(self.point_names),
            XYZ=self.XYZ_approx,
            control=self.control,
            control_sigma=self.control_sigma,
            obs_photo=self.obs_photo,
            obs_point=self.obs_point,
            xy=self.xy,
            sigma_xy=self.sigma_xy,
            check=self.check,
        )


def observe(intr, photo_camera, X0, M, XYZ, format_mm, noise_mm, rng, min_rays=2):
    """Observations of every point in every photo where it falls inside the format.

    Returns ``obs_photo, obs_point, xy_true (film mm)``, sorted by photo then point.
    """
    op, oq, oxy = [], [], []
    for f in range(X0.shape[0]):
        cam = photo_camera[f]
        xy, front = film_from_object(XYZ, X0[f], M[f], intr[cam])
        w, h = format_mm[cam]
        inside = front & (np.abs(xy[:, 0]) < w / 2) & (np.abs(xy[:, 1]) < h / 2)
        idx = np.flatnonzero(inside)
        op.append(np.full(idx.size, f))
        oq.append(idx)
        oxy.append(xy[idx])
    op, oq, oxy = np.concatenate(op), np.concatenate(oq), np.vstack(oxy)
    return op, oq, oxy


def perturb_eo(X0, M, rng, sx, sa):
    """Approximate exterior orientations: positions +- ``sx``, angles +- ``sa`` radians."""
    Xa = X0 + rng.normal(0, sx, X0.shape)
    o, p, k = angles_from_matrix(M)
    ang = np.column_stack([o, p, k]) + rng.normal(0, sa, (X0.shape[0], 3))
    return Xa, ang


def rotation_of(angles):
    return rotation_matrix(angles[..., 0], angles[..., 1], angles[..., 2])
