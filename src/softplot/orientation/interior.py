"""Interior orientation: film mm <-> photo mm (principal point and lens distortion).

**film** (mm, x right, y up, origin at the reseau / fiducial centre) -> **photo** (mm, reduced
to the principal point and corrected for lens distortion), with the sign convention of the
:mod:`softplot.camera` docstring: the distortion ``delta`` is the displacement the lens gave
the image point, evaluated at the *measured* point reduced to the principal point
(``xb = x - x0``, ``yb = y - y0``, ``r = hypot(xb, yb)``), and::

    photo = (xb - delta_x(xb, yb), yb - delta_y(xb, yb))

so film -> photo is explicit and photo -> film solves ``xb - delta(xb) = photo`` by Newton's
method with the analytic Jacobian (vectorised; the distortion's gradient is of the order of
1e-3, so two or three steps reach 1e-12 mm).

Distortion models (certificate ``[distortion]``):

* ``radial-table``: ``delta = (xb, yb) / r * delta_r(r)``; ``delta_r`` (um in the table) is
  interpolated by a monotone piecewise cubic (PCHIP, Fritsch-Carlson: it passes through
  every tabulated value, is C1, and never overshoots between them - a certificate table is
  measured data, not a polynomial). If the table does not start at r = 0 the point
  (0, 0) is added (no distortion on the axis). Beyond the last radius ``delta_r`` continues
  along the tangent of the last interval (linear extrapolation).
* ``brown``: ``delta_r = k1 r^3 + k2 r^5 + k3 r^7`` (radial, mm), decentering
  ``p1 (r^2 + 2 xb^2) + 2 p2 xb yb`` in x and ``2 p1 xb yb + p2 (r^2 + 2 yb^2)`` in y, and
  the affinity / shear ``b1 xb + b2 yb`` in x.
* ``none``: only the principal point.
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from scipy.interpolate import PchipInterpolator, PPoly

from softplot.camera import Camera, load_camera
from softplot.errors import SoftplotError

__all__ = ["InteriorOrientation", "interior_orientation"]


def _radial_ppoly(radius_mm, delta_r_um) -> PPoly:
    """PCHIP of delta_r (mm) over r (mm), extended linearly beyond the last radius."""
    r = np.asarray(radius_mm, float)
    d = np.asarray(delta_r_um, float) * 1e-3
    if r.size < 2:
        raise SoftplotError("radial distortion table needs at least 2 radii")
    if r[0] > 0:
        r = np.concatenate([[0.0], r])
        d = np.concatenate([[0.0], d])
    p = PchipInterpolator(r, d, extrapolate=True)
    c = p.c  # (4, m): cubic coefficients per interval, highest power first
    x = p.x
    slope = float(p.derivative()(x[-1]))
    value = float(d[-1])
    span = max(float(x[-1] - x[0]), 1.0)
    c_ext = np.concatenate([c, np.array([[0.0], [0.0], [slope], [value]])], axis=1)
    x_ext = np.concatenate([x, [x[-1] + 10.0 * span]])
    return PPoly(c_ext, x_ext, extrapolate=True)


def _brown_delta(xb, yb, r2, k, p, b):
    """Brown lens displacement (dx, dy) in mm at reduced points xb, yb (floats or arrays).

    ``r2 = xb^2 + yb^2``; radial k1..k3, decentring p1, p2, affinity/shear b1, b2.
    """
    k1, k2, k3 = k
    p1, p2 = p
    b1, b2 = b
    F = r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = xb * F + p1 * (r2 + 2 * xb * xb) + 2 * p2 * xb * yb + b1 * xb + b2 * yb
    dy = yb * F + 2 * p1 * xb * yb + p2 * (r2 + 2 * yb * yb)
    return dx, dy


def _brown_jacobian(xb, yb, r2, k, p, b):
    """Derivatives (ddx/dxb, ddx/dyb, ddy/dxb, ddy/dyb) of :func:`_brown_delta` (mm/mm)."""
    k1, k2, k3 = k
    p1, p2 = p
    b1, b2 = b
    F = r2 * (k1 + r2 * (k2 + r2 * k3))
    G = 2 * k1 + r2 * (4 * k2 + 6 * k3 * r2)
    j00 = F + G * xb * xb + 6 * p1 * xb + 2 * p2 * yb + b1
    j01 = G * xb * yb + 2 * p1 * yb + 2 * p2 * xb + b2
    j10 = G * xb * yb + 2 * p1 * yb + 2 * p2 * xb
    j11 = F + G * yb * yb + 2 * p1 * xb + 6 * p2 * yb
    return j00, j01, j10, j11


class InteriorOrientation:
    """Film <-> photo coordinates of one camera (see the module docstring).

    Parameters
    ----------
    camera : Camera or str
        Certificate (object, built-in name or TOML path).

    Attributes
    ----------
    c, x0, y0 : float
        Principal distance and principal point, film mm.
    model : str
        Distortion model: none, radial-table or brown.
    """

    def __init__(self, camera: Camera | str) -> None:
        cam = load_camera(camera)
        self.camera = cam
        self.c = float(cam.c)
        self.x0 = float(cam.x0)
        self.y0 = float(cam.y0)
        d = cam.distortion
        self.model = d.model
        self.k = (float(d.k1), float(d.k2), float(d.k3))
        self.p = (float(d.p1), float(d.p2))
        self.b = (float(d.b1), float(d.b2))
        if self.model == "radial-table":
            self._pp = _radial_ppoly(d.radius_mm, d.delta_r_um)
            self._dpp = self._pp.derivative()
            self._py_x = self._pp.x.tolist()
            self._py_c = self._pp.c.T.tolist()  # per interval: c3, c2, c1, c0
        elif self.model == "brown":
            self._pp = None
        elif self.model == "none":
            self._pp = None
        else:  # pragma: no cover - validated by the certificate reader
            raise SoftplotError(f"unknown distortion model {self.model!r}")

    # -- distortion ---------------------------------------------------------------------------

    def delta_r(self, r) -> np.ndarray:
        """Radial distortion delta_r (mm) at radii r (mm) - radial-table or Brown radial part."""
        r = np.asarray(r, float)
        if self.model == "radial-table":
            return self._pp(r)
        if self.model == "brown":
            k1, k2, k3 = self.k
            r2 = r * r
            return r * r2 * (k1 + r2 * (k2 + r2 * k3))
        return np.zeros_like(r)

    def distortion(self, xb, yb) -> tuple[np.ndarray, np.ndarray]:
        """Lens displacement (delta_x, delta_y) in mm at reduced measured points (mm)."""
        xb = np.asarray(xb, float)
        yb = np.asarray(yb, float)
        if self.model == "none":
            return np.zeros_like(xb), np.zeros_like(yb)
        r2 = xb * xb + yb * yb
        if self.model == "radial-table":
            r = np.sqrt(r2)
            with np.errstate(invalid="ignore", divide="ignore"):
                f = np.where(r > 1e-12, self._pp(r) / r, self._dpp(0.0))
            return xb * f, yb * f
        return _brown_delta(xb, yb, r2, self.k, self.p, self.b)

    def distortion_jacobian(self, xb, yb) -> np.ndarray:
        """(N, 2, 2) derivatives d(delta)/d(xb, yb) at reduced points (mm/mm)."""
        xb = np.asarray(xb, float).reshape(-1)
        yb = np.asarray(yb, float).reshape(-1)
        J = np.zeros((xb.size, 2, 2))
        if self.model == "none":
            return J
        r2 = xb * xb + yb * yb
        if self.model == "radial-table":
            r = np.sqrt(r2)
            safe = np.maximum(r, 1e-12)
            dr = self._pp(r)
            ddr = self._dpp(r)
            f = np.where(r > 1e-12, dr / safe, self._dpp(0.0))
            fp = np.where(r > 1e-12, (ddr * safe - dr) / safe**2, 0.0)  # df/dr
            g = fp / safe
            J[:, 0, 0] = f + xb * xb * g
            J[:, 0, 1] = xb * yb * g
            J[:, 1, 0] = xb * yb * g
            J[:, 1, 1] = f + yb * yb * g
            return J
        (
            J[:, 0, 0],
            J[:, 0, 1],
            J[:, 1, 0],
            J[:, 1, 1],
        ) = _brown_jacobian(xb, yb, r2, self.k, self.p, self.b)
        return J

    # -- film <-> photo, vectorised ------------------------------------------------------------

    def film_to_photo_xy(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Film x, y (mm arrays) -> photo x, y (mm arrays). Chunk-friendly form."""
        xb = x - self.x0
        yb = y - self.y0
        if self.model == "none":
            return xb, yb
        if self.model == "brown" and self.p == (0.0, 0.0) and self.b == (0.0, 0.0):
            k1, k2, k3 = self.k
            r2 = xb * xb + yb * yb
            if k2 == 0.0 and k3 == 0.0:
                F = 1.0 - k1 * r2
            else:
                F = 1.0 - r2 * (k1 + r2 * (k2 + r2 * k3))
            return xb * F, yb * F
        dx, dy = self.distortion(xb, yb)
        return xb - dx, yb - dy

    def film_to_photo(self, xy) -> np.ndarray:
        """Film (N, 2) mm -> photo (N, 2) mm."""
        a = _points(xy)
        X, Y = self.film_to_photo_xy(a[:, 0], a[:, 1])
        return np.column_stack([X, Y])

    def photo_to_film(self, xy, tol: float = 1e-13, max_iter: int = 20) -> np.ndarray:
        """Photo (N, 2) mm -> film (N, 2) mm by Newton's method (vectorised)."""
        P = _points(xy)
        xb = P.copy()
        if self.model != "none":
            active = np.arange(P.shape[0])
            for _ in range(max_iter):
                if active.size == 0:
                    break
                q = xb[active]
                dx, dy = self.distortion(q[:, 0], q[:, 1])
                f = np.column_stack([q[:, 0] - dx, q[:, 1] - dy]) - P[active]
                J = -self.distortion_jacobian(q[:, 0], q[:, 1])
                J[:, 0, 0] += 1.0
                J[:, 1, 1] += 1.0
                det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
                sx = (J[:, 1, 1] * f[:, 0] - J[:, 0, 1] * f[:, 1]) / det
                sy = (-J[:, 1, 0] * f[:, 0] + J[:, 0, 0] * f[:, 1]) / det
                xb[active, 0] -= sx
                xb[active, 1] -= sy
                active = active[np.maximum(np.abs(sx), np.abs(sy)) > tol]
        return xb + np.array([self.x0, self.y0])

    # -- single point (plain floats) ----------------------------------------------------------

    def film_to_photo_point(self, x: float, y: float) -> tuple[float, float]:
        """One film point (mm) -> photo (mm), plain Python floats."""
        xb = x - self.x0
        yb = y - self.y0
        m = self.model
        if m == "none":
            return xb, yb
        r2 = xb * xb + yb * yb
        if m == "brown":
            dx, dy = _brown_delta(xb, yb, r2, self.k, self.p, self.b)
            return xb - dx, yb - dy
        r = math.sqrt(r2)
        if r <= 1e-12:
            return xb, yb
        bx = self._py_x
        i = min(max(bisect.bisect_right(bx, r) - 1, 0), len(bx) - 2)
        c3, c2, c1, c0 = self._py_c[i]
        h = r - bx[i]
        f = (((c3 * h + c2) * h + c1) * h + c0) / r
        return xb - xb * f, yb - yb * f

    def photo_to_film_point(self, x: float, y: float) -> tuple[float, float]:
        """One photo point (mm) -> film (mm): Newton's method on plain floats."""
        if self.model == "none":
            return x + self.x0, y + self.y0
        if self.model == "radial-table":
            X, Y = self.photo_to_film(np.array([[x, y]], float))[0].tolist()
            return X, Y
        k, p, b = self.k, self.p, self.b
        xb, yb = float(x), float(y)
        for _ in range(20):
            r2 = xb * xb + yb * yb
            dx, dy = _brown_delta(xb, yb, r2, k, p, b)
            fx = xb - dx - x
            fy = yb - dy - y
            d00, d01, d10, d11 = _brown_jacobian(xb, yb, r2, k, p, b)
            j00 = 1.0 - d00
            j01 = -d01
            j10 = -d10
            j11 = 1.0 - d11
            det = j00 * j11 - j01 * j10
            sx = (j11 * fx - j01 * fy) / det
            sy = (-j10 * fx + j00 * fy) / det
            xb -= sx
            yb -= sy
            if abs(sx) <= 1e-13 and abs(sy) <= 1e-13:
                break
        return xb + self.x0, yb + self.y0

    def describe(self) -> str:
        s = f"c={self.c:.4f} mm, principal point ({self.x0:+.4f}, {self.y0:+.4f}) mm, "
        if self.model == "radial-table":
            return s + f"radial table ({len(self.camera.distortion.radius_mm)} radii, PCHIP)"
        if self.model == "brown":
            return s + "Brown k1 k2 k3 p1 p2 b1 b2 = " + " ".join(
                f"{v:.3g}" for v in self.k + self.p + self.b
            )
        return s + "no distortion"


def interior_orientation(camera) -> InteriorOrientation:
    """The :class:`InteriorOrientation` of a camera (object, built-in name or TOML path)."""
    return InteriorOrientation(camera)


def _points(xy) -> np.ndarray:
    a = np.asarray(xy, float)
    if a.ndim == 1 and a.shape[0] == 2:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 2:
        raise SoftplotError(f"expected an (N, 2) array of points, got shape {a.shape}")
    return a
