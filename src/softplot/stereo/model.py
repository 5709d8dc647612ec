"""The stereo model of two oriented photos and the four restitution modes.

Coordinates: **photo mm** are the coordinates of the collinearity equations of
:mod:`softplot.geometry.collinearity` (x right, y up; principal point ``x0, y0``, principal
distance ``c``), i.e. film coordinates after the film correction and lens distortion of each
scan; **film mm** (instrument mm) are what the plotter's carriages measure; **object**
coordinates X, Y, Z are right-handed, Z up. Photo 1 is the *left* photo (the one the DX, DY
carriage moves), photo 2 the *right* one.

With ``v_k = (x_k - x0_k, y_k - y0_k, -c_k)`` the ray of photo k is ``r_k = M_k^T v_k`` from
the projection centre ``C_k``. Everything follows from the base ``b = C2 - C1``:

* epipolar condition (coplanarity of b, r1, r2): ``h1^T F h2 = 0`` with homogeneous photo
  points ``h_k = (x_k, y_k, 1)`` and ``F = K1^T M1 [b]x M2^T K2``,
  ``K_k = [[1, 0, -x0], [0, 1, -y0], [0, 0, -c]]``;
* **single point** (STEREOBIT a): given (x2, y2) and x1, the y1 on the epipolar line,
  ``y1 = y0_1 + (q3 c1 - q1 (x1 - x0_1)) / q2`` with ``q = M1 (b x r2)`` (closed form: the
  y-parallax is removed exactly, to rounding), then the object point;
* **contour** (STEREOBIT b): the right ray meets the plane Z = Qc at
  ``P = C2 + (Qc - Z_C2) / r2_z * r2`` (Z set to Qc exactly), projected into the left photo;
* **free**: both image points -> object point (least-squares intersection of
  :func:`softplot.orientation.intersection.intersect`) and the residual y-parallax
  ``py = y1 - y1_epipolar(x1; x2, y2)`` in left photo mm;
* **drive-to**: X, Y, Z -> both photo points (collinearity).

The numpy functions are vectorised over points; :class:`FastStereo` is the scalar path of the
plotter loop (pure-Python floats: a few microseconds per call).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.collinearity import project
from softplot.geometry.rotation import rotation_matrix
from softplot.orientation.intersection import intersect

__all__ = [
    "OrientedPhoto",
    "StereoModel",
    "FastStereo",
    "Restitution",
    "closest_points",
    "invert_correction",
]


def invert_correction(forward: Callable, xy, *, iterations: int = 8, tol: float = 1e-12):
    """Invert a near-identity plane correction by fixed-point iteration.

    Solves ``forward(p) = xy`` for p with ``p <- p + (xy - forward(p))`` (converges for
    corrections whose Jacobian is close to the identity, as film corrections are).

    Parameters
    ----------
    forward : callable
        ``(N,2) mm -> (N,2) mm``.
    xy : array_like, shape (N, 2)
        Target coordinates, mm.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    p = xy.copy()
    for _ in range(iterations):
        d = xy - np.asarray(forward(p), dtype=float).reshape(-1, 2)
        p += d
        if np.max(np.abs(d), initial=0.0) < tol:
            break
    return p


@dataclass
class OrientedPhoto:
    """One oriented photo: exterior and interior orientation and the film correction.

    Parameters
    ----------
    X0 : array_like, shape (3,)
        Projection centre, object frame.
    angles : array_like, shape (3,)
        ``omega, phi, kappa``, radians (M = Mk Mp Mo, object -> photo axes).
    c : float
        Principal distance, mm.
    x0, y0 : float
        Principal point, photo mm.
    to_photo : callable, optional
        Film mm -> photo mm of this scan (film correction, lens distortion), vectorised
        ``(N,2) -> (N,2)``; identity when None.
    to_film : callable, optional
        Photo mm -> film mm, the inverse; computed by fixed-point iteration of ``to_photo``
        when None (and ``to_photo`` is given).
    name : str
    """

    X0: np.ndarray
    angles: np.ndarray
    c: float
    x0: float = 0.0
    y0: float = 0.0
    to_photo: Callable | None = None
    to_film: Callable | None = None
    name: str = ""
    M: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.X0 = np.asarray(self.X0, dtype=float).reshape(3)
        self.angles = np.asarray(self.angles, dtype=float).reshape(3)
        if not (np.all(np.isfinite(self.X0)) and np.all(np.isfinite(self.angles))):
            raise SoftplotError(f"photo {self.name or '?'}: orientation is not finite")
        self.c = float(self.c)
        if not self.c > 0:
            raise SoftplotError(f"photo {self.name or '?'}: principal distance must be > 0 mm")
        self.x0, self.y0 = float(self.x0), float(self.y0)
        self.M = rotation_matrix(*self.angles)

    def film_to_photo(self, xy) -> np.ndarray:
        """Film (instrument) mm -> photo mm, (N,2)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.to_photo is None:
            return xy.copy()
        return np.asarray(self.to_photo(xy), dtype=float).reshape(-1, 2)

    def photo_to_film(self, xy) -> np.ndarray:
        """Photo mm -> film (instrument) mm, (N,2)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if self.to_photo is None:
            return xy.copy()
        if self.to_film is not None:
            return np.asarray(self.to_film(xy), dtype=float).reshape(-1, 2)
        return invert_correction(self.to_photo, xy)

    def ray(self, xy) -> np.ndarray:
        """Ray directions (not normalised) ``M^T (x - x0, y - y0, -c)``, object frame, (N,3)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        v = np.empty((xy.shape[0], 3))
        v[:, 0] = xy[:, 0] - self.x0
        v[:, 1] = xy[:, 1] - self.y0
        v[:, 2] = -self.c
        return v @ self.M

    def project(self, XYZ) -> np.ndarray:
        """Object points (N,3) -> photo mm (N,2)."""
        return project(XYZ, self.X0, self.M, self.c, self.x0, self.y0)

    @property
    def K(self) -> np.ndarray:
        """Homogeneous photo point -> camera vector ``(x - x0, y - y0, -c)``."""
        return np.array([[1.0, 0.0, -self.x0], [0.0, 1.0, -self.y0], [0.0, 0.0, -self.c]])

    def to_dict(self) -> dict:
        """JSON-serialisable orientation (angles in radians; corrections not included)."""
        return {
            "name": self.name,
            "X0": self.X0.tolist(),
            "angles_rad": self.angles.tolist(),
            "c": self.c,
            "x0": self.x0,
            "y0": self.y0,
        }

    @classmethod
    def from_dict(cls, d: dict, to_photo=None, to_film=None) -> "OrientedPhoto":
        return cls(
            d["X0"],
            d["angles_rad"],
            d["c"],
            d.get("x0", 0.0),
            d.get("y0", 0.0),
            to_photo,
            to_film,
            d.get("name", ""),
        )


def closest_points(C1, r1, C2, r2):
    """Closest points of two families of lines ``C1 + s r1`` and ``C2 + t r2``.

    Returns
    -------
    P1, P2 : ndarray, shape (N, 3)
        Closest points on each line; their midpoint is the closed-form intersection and
        ``|P1 - P2|`` the miss distance (object units).
    """
    w0 = C1 - C2
    a = np.einsum("ij,ij->i", r1, r1)
    bb = np.einsum("ij,ij->i", r1, r2)
    c = np.einsum("ij,ij->i", r2, r2)
    d = np.einsum("ij,ij->i", r1, w0)
    e = np.einsum("ij,ij->i", r2, w0)
    den = a * c - bb * bb
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (bb * e - c * d) / den
        t = (a * e - bb * d) / den
    return C1 + s[:, None] * r1, C2 + t[:, None] * r2


@dataclass
class Restitution:
    """Result of a restitution mode (N points).

    Attributes
    ----------
    xy1, xy2 : ndarray, shape (N, 2)
        Left and right photo points, mm.
    XYZ : ndarray, shape (N, 3)
        Object points.
    py : ndarray, shape (N,)
        Residual y-parallax ``y1 - y1_epipolar``, left photo mm (0 by construction in the
        single, contour and drive-to modes up to rounding).
    gap : ndarray, shape (N,)
        Miss distance of the two rays, object units.
    std : ndarray, shape (N, 3) or None
        Standard deviations of X, Y, Z (free mode, from the least-squares intersection).
    """

    xy1: np.ndarray
    xy2: np.ndarray
    XYZ: np.ndarray
    py: np.ndarray
    gap: np.ndarray
    std: np.ndarray | None = None


class StereoModel:
    """Stereo model of a left (1) and a right (2) oriented photo.

    Parameters
    ----------
    left, right : OrientedPhoto
    """

    def __init__(self, left: OrientedPhoto, right: OrientedPhoto):
        self.left = left
        self.right = right
        self.base = right.X0 - left.X0
        if not np.linalg.norm(self.base) > 0:
            raise SoftplotError("stereo model: the two projection centres coincide (no base)")

    # ----------------------------------------------------------- epipolar geometry
    def fundamental(self) -> np.ndarray:
        """``F`` (3,3) with ``[x1, y1, 1] F [x2, y2, 1]^T = 0`` for homologous photo points."""
        b = self.base
        bx = np.array([[0.0, -b[2], b[1]], [b[2], 0.0, -b[0]], [-b[1], b[0], 0.0]])
        return self.left.K.T @ self.left.M @ bx @ self.right.M.T @ self.right.K

    def epipolar_lines_left(self, xy2) -> np.ndarray:
        """Epipolar lines in the left photo of right photo points.

        Returns
        -------
        ndarray, shape (N, 3)
            ``(a, b, c)`` with ``a x1 + b y1 + c = 0`` in left photo mm, normalised so that
            ``a^2 + b^2 = 1`` (the value at a point is then its distance to the line, mm).
        """
        xy2 = np.asarray(xy2, dtype=float).reshape(-1, 2)
        h = np.c_[xy2, np.ones(len(xy2))]
        lines = h @ self.fundamental().T
        return lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]

    def epipolar_lines_right(self, xy1) -> np.ndarray:
        """Epipolar lines ``(a, b, c)`` in the right photo of left photo points (normalised)."""
        xy1 = np.asarray(xy1, dtype=float).reshape(-1, 2)
        h = np.c_[xy1, np.ones(len(xy1))]
        lines = h @ self.fundamental()
        return lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]

    def epipolar_y1(self, x1, xy2) -> np.ndarray:
        """The left y1 on the epipolar line of ``xy2`` at abscissa ``x1`` (photo mm), (N,)."""
        xy2 = np.asarray(xy2, dtype=float).reshape(-1, 2)
        x1 = np.broadcast_to(np.asarray(x1, dtype=float).reshape(-1), (len(xy2),))
        r2 = self.right.ray(xy2)
        q = np.cross(self.base, r2) @ self.left.M.T  # q = M1 (b x r2), left photo axes
        L = self.left
        with np.errstate(divide="ignore", invalid="ignore"):
            y1 = L.y0 + (q[:, 2] * L.c - q[:, 0] * (x1 - L.x0)) / q[:, 1]
        if not np.all(np.isfinite(y1)):
            raise SoftplotError("epipolar line parallel to the y axis of the left photo")
        return y1

    def y_parallax(self, xy1, xy2) -> np.ndarray:
        """Residual y-parallax ``y1 - y1_epipolar(x1; x2, y2)``, left photo mm, (N,)."""
        xy1 = np.asarray(xy1, dtype=float).reshape(-1, 2)
        return xy1[:, 1] - self.epipolar_y1(xy1[:, 0], xy2)

    # ----------------------------------------------------------- projection
    def project(self, XYZ) -> tuple[np.ndarray, np.ndarray]:
        """Object points (N,3) -> (left photo mm (N,2), right photo mm (N,2))."""
        XYZ = np.asarray(XYZ, dtype=float).reshape(-1, 3)
        return self.left.project(XYZ), self.right.project(XYZ)

    def _closed_form(self, xy1, xy2):
        r1 = self.left.ray(xy1)
        r2 = self.right.ray(xy2)
        n = len(r1)
        P1, P2 = closest_points(
            np.broadcast_to(self.left.X0, (n, 3)), r1, np.broadcast_to(self.right.X0, (n, 3)), r2
        )
        return 0.5 * (P1 + P2), np.linalg.norm(P1 - P2, axis=1)

    # ----------------------------------------------------------- the four modes
    def single_point(self, xy2, x1) -> Restitution:
        """Single-point mode: right (x2, y2) and left x1 -> y1 free of y-parallax, object point.

        Parameters
        ----------
        xy2 : array_like, shape (N, 2)
            Right photo points, mm.
        x1 : array_like, shape (N,)
            Left photo abscissae, mm (the x-parallax handwheel).
        """
        xy2 = np.asarray(xy2, dtype=float).reshape(-1, 2)
        x1 = np.broadcast_to(np.asarray(x1, dtype=float).reshape(-1), (len(xy2),))
        y1 = self.epipolar_y1(x1, xy2)
        xy1 = np.c_[x1, y1]
        XYZ, gap = self._closed_form(xy1, xy2)
        return Restitution(xy1, xy2, XYZ, np.zeros(len(xy2)), gap)

    def contour(self, xy2, Z) -> Restitution:
        """Contour mode: right (x2, y2) and height Qc -> object point on Z = Qc, left point.

        Parameters
        ----------
        xy2 : array_like, shape (N, 2)
            Right photo points, mm.
        Z : float or array_like (N,)
            Contour height Qc, object units.
        """
        xy2 = np.asarray(xy2, dtype=float).reshape(-1, 2)
        Z = np.broadcast_to(np.asarray(Z, dtype=float).reshape(-1), (len(xy2),))
        r2 = self.right.ray(xy2)
        if np.any(np.abs(r2[:, 2]) <= 1e-12 * np.linalg.norm(r2, axis=1)):
            raise SoftplotError("contour: a right ray is parallel to the contour plane")
        lam = (Z - self.right.X0[2]) / r2[:, 2]
        if np.any(lam <= 0):
            raise SoftplotError(
                f"contour: the plane Z = {Z[np.argmin(lam)]:g} is behind the right camera for "
                f"{int(np.sum(lam <= 0))} point(s)"
            )
        XYZ = self.right.X0 + lam[:, None] * r2
        XYZ[:, 2] = Z
        xy1 = self.left.project(XYZ)
        return Restitution(xy1, xy2, XYZ, self.y_parallax(xy1, xy2), np.zeros(len(xy2)))

    def free(self, xy1, xy2, *, sigma: float = 0.005) -> Restitution:
        """Free mode: both photo points -> object point (least squares) and y-parallax.

        Parameters
        ----------
        xy1, xy2 : array_like, shape (N, 2)
            Left and right photo points, mm.
        sigma : float
            A priori standard error of a photo coordinate, mm (scales ``std``).
        """
        xy1 = np.asarray(xy1, dtype=float).reshape(-1, 2)
        xy2 = np.asarray(xy2, dtype=float).reshape(-1, 2)
        if xy1.shape != xy2.shape:
            raise SoftplotError("free mode: left and right need the same number of points")
        n = len(xy1)
        idx = np.arange(n)
        L, R = self.left, self.right
        res = intersect(
            np.r_[xy1, xy2],
            np.r_[idx, idx],
            np.r_[np.zeros(n, int), np.ones(n, int)],
            np.vstack([L.X0, R.X0]),
            np.vstack([L.angles, R.angles]),
            np.array([L.c, R.c]),
            np.array([L.x0, R.x0]),
            np.array([L.y0, R.y0]),
            sigma=sigma,
            n_points=n,
            covariance="prior",
        )
        _, gap = self._closed_form(xy1, xy2)
        return Restitution(xy1, xy2, res.XYZ, self.y_parallax(xy1, xy2), gap, res.std)

    def drive_to(self, XYZ) -> Restitution:
        """Drive-to mode: object points -> both photo points."""
        XYZ = np.asarray(XYZ, dtype=float).reshape(-1, 3)
        xy1, xy2 = self.project(XYZ)
        return Restitution(xy1, xy2, XYZ.copy(), self.y_parallax(xy1, xy2), np.zeros(len(XYZ)))

    def fast(self) -> "FastStereo":
        """Scalar path for the plotter loop."""
        return FastStereo(self)


class FastStereo:
    """Scalar (one point, pure-Python floats) restitution for the plotter cycle.

    Same equations as :class:`StereoModel`, precomputed into tuples of floats; every method
    takes and returns photo mm / object coordinates as plain floats.
    """

    __slots__ = ("M1", "M2", "C1", "C2", "b", "c1", "c2", "x01", "y01", "x02", "y02")

    def __init__(self, model: StereoModel):
        L, R = model.left, model.right
        self.M1 = tuple(tuple(float(v) for v in row) for row in L.M)
        self.M2 = tuple(tuple(float(v) for v in row) for row in R.M)
        self.C1 = tuple(float(v) for v in L.X0)
        self.C2 = tuple(float(v) for v in R.X0)
        self.b = tuple(float(v) for v in model.base)
        self.c1, self.c2 = L.c, R.c
        self.x01, self.y01, self.x02, self.y02 = L.x0, L.y0, R.x0, R.y0

    def ray2(self, x2: float, y2: float) -> tuple[float, float, float]:
        """Right ray direction ``M2^T (x2 - x0, y2 - y0, -c)``, object frame."""
        u, v, w = x2 - self.x02, y2 - self.y02, -self.c2
        (a, b, c), (d, e, f), (g, h, i) = self.M2
        return (a * u + d * v + g * w, b * u + e * v + h * w, c * u + f * v + i * w)

    def project1(self, X: float, Y: float, Z: float) -> tuple[float, float]:
        """Object point -> left photo mm."""
        dx, dy, dz = X - self.C1[0], Y - self.C1[1], Z - self.C1[2]
        (a, b, c), (d, e, f), (g, h, i) = self.M1
        w = g * dx + h * dy + i * dz
        return (
            self.x01 - self.c1 * (a * dx + b * dy + c * dz) / w,
            self.y01 - self.c1 * (d * dx + e * dy + f * dz) / w,
        )

    def single(self, x2: float, y2: float, x1: float) -> tuple[float, float, float, float]:
        """Single-point mode: returns ``(y1, X, Y, Z)``."""
        rx, ry, rz = self.ray2(x2, y2)
        bx, by, bz = self.b
        nx, ny, nz = by * rz - bz * ry, bz * rx - bx * rz, bx * ry - by * rx
        (a, b, c), (d, e, f), (g, h, i) = self.M1
        q1 = a * nx + b * ny + c * nz
        q2 = d * nx + e * ny + f * nz
        q3 = g * nx + h * ny + i * nz
        y1 = self.y01 + (q3 * self.c1 - q1 * (x1 - self.x01)) / q2
        # left ray and closest point to the right ray (the rays are coplanar now)
        u, v, w = x1 - self.x01, y1 - self.y01, -self.c1
        sx, sy, sz = a * u + d * v + g * w, b * u + e * v + h * w, c * u + f * v + i * w
        w0x, w0y, w0z = -bx, -by, -bz  # C1 - C2
        aa = sx * sx + sy * sy + sz * sz
        ab = sx * rx + sy * ry + sz * rz
        cc = rx * rx + ry * ry + rz * rz
        dd = sx * w0x + sy * w0y + sz * w0z
        ee = rx * w0x + ry * w0y + rz * w0z
        den = aa * cc - ab * ab
        s = (ab * ee - cc * dd) / den
        t = (aa * ee - ab * dd) / den
        C1, C2 = self.C1, self.C2
        X = 0.5 * (C1[0] + s * sx + C2[0] + t * rx)
        Y = 0.5 * (C1[1] + s * sy + C2[1] + t * ry)
        Z = 0.5 * (C1[2] + s * sz + C2[2] + t * rz)
        return y1, X, Y, Z

    def contour(self, x2: float, y2: float, Z: float) -> tuple[float, float, float, float]:
        """Contour mode: returns ``(x1, y1, X, Y)`` on the plane ``Z``."""
        rx, ry, rz = self.ray2(x2, y2)
        lam = (Z - self.C2[2]) / rz
        X = self.C2[0] + lam * rx
        Y = self.C2[1] + lam * ry
        x1, y1 = self.project1(X, Y, Z)
        return x1, y1, X, Y
