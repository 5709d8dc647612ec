"""Photogrammetric bundle adjustment with self-calibration on the sparse Schur LM engine.

Frames (docs/conventions.md): object right-handed, Z up (any consistent unit, "m" in reports); image
observations are *film* mm (x right, y up, origin at the fiducial / reseau centre) of the
measured points; rotations ``M = Mk Mp Mo`` object -> photo axes.

Observation equation of image point ``(x, y)`` (film mm) of object point ``X`` in a photo with
projection centre ``X0``, rotation ``M`` and physical camera ``(c, x0, y0, k1..b2, a)``: the
pinhole point ``xp = -c u1/u3, yp = -c u2/u3`` with ``u = M (X - X0)``, and the lens
displacement ``(dx, dy)`` of :mod:`softplot.camera` (radial ``x (k1 r^2 + k2 r^4 + k3 r^6)``,
decentering ``p1 (r^2 + 2 x^2) + 2 p2 x y`` / ``2 p1 x y + p2 (r^2 + 2 y^2)``, affinity/shear
``b1 x + b2 y`` in x). Per camera, one of two lens models:

* ``forward``: the distortion is added to the projected point, ``xa = xp + dx(xp, yp)``,
  predicted ``x = x0 + xa / (1 + a)``, ``y = y0 + yp + dy(xp, yp)``; the residual lives in
  the measurement space (unbiased sigma0 whatever the distortion);
* ``inverse``: the measured point is corrected, ``xa = (1 + a)(x - x0)``, ``ya = y - y0``,
  residual ``(xp, yp) - ((xa, ya) - d(xa, ya))``.

``a`` is the aspect as PhotoModeler and DBAT define it (x scaled before the distortion). The
residual is ``predicted - measured`` (mm), whitened by the observation's 2x2 covariance
(Cholesky factor).

Unknowns: per photo ``X0, Y0, Z0`` and a rotation increment (three small angles about the photo
axes, ``M <- exp([d]x) M``: no gimbal lock; ``omega, phi, kappa`` and their standard deviations
are reported by propagation); per physical camera ``c, x0, y0, k1, k2, k3, p1, p2, b1, b2``,
each free, fixed or weighted by an a priori standard error; object points. Control
coordinates are fixed (sigma 0), weighted (sigma > 0) or absent. Without control the datum is
a free network: during the iterations seven point coordinates chosen by pivoted QR of the
similarity null space are held, then the solution is moved by the 7-parameter similarity that
best fits the adjusted points to their approximations (the inner-constraint, minimum-trace
datum over the points) and the covariance is S-transformed (Baarda) to that datum
``Q_C = S Q S'``, ``S = I - G (C'G)^-1 C'``. Optionally the scale comes from one distance
between two points instead of from the approximations.

Results (:class:`BundleResult`): sigma0 (a posteriori / a priori), redundancy, residuals in um
and px, camera parameters with standard deviations and correlation matrices (warning above
0.9, also against the exterior orientations), exterior orientations and points with standard
deviations (posterior covariance blocks), Baarda's w and data-snooping flags.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from scipy.spatial.transform import Rotation

from softplot.adjust._blas import blas_threads
from softplot.adjust.core import critical_value, tau_critical_value
from softplot.adjust.sparse_bundle import (
    Evaluation,
    LMOptions,
    NormalInverse,
    SchurStructure,
    levenberg_marquardt,
)
from softplot.errors import SoftplotError
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix

__all__ = [
    "INTRINSICS",
    "EO_NAMES",
    "BundleCamera",
    "BundleData",
    "BundleOptions",
    "BundleResult",
    "bundle_adjust",
    "distortion",
    "similarity_null_space",
]

#: interior-orientation parameters per physical camera (mm; k's in mm^-2, mm^-4, mm^-6;
#: p's in mm^-1; b's and the aspect ``a`` unitless)
INTRINSICS = ("c", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2", "a")
#: lens models: where the distortion is evaluated (see the module docstring)
LENS_MODELS = ("inverse", "forward")
#: exterior-orientation parameters per photo (object units; radians)
EO_NAMES = ("X0", "Y0", "Z0", "omega", "phi", "kappa")
FREE = math.inf


@dataclass
class BundleCamera:
    """A physical camera in the bundle.

    Attributes
    ----------
    name : str
    values : ndarray, shape (11,)
        Start (or fixed) values of :data:`INTRINSICS` (a 10-vector gets ``a = 0``).
    sigma : ndarray, shape (11,)
        Per parameter: ``0`` fixed, ``inf`` free, a positive number = a priori standard error
        (weighted towards ``values``).
    pixel_size_mm : float or None
        Scan pixel size, for residuals in px.
    sigma_image_mm : float or None
        Default standard error of its image coordinates (project files).
    model : str
        ``"inverse"`` (the distortion evaluated at the measured point, as
        :mod:`softplot.camera` corrects it) or ``"forward"`` (the distortion added to the
        projected point, as OpenCV and COLMAP model it).
    image_size : (width, height) or None
        Image size in pixels of a digital camera (film origin at the image centre, x right,
        y up); needed to write pixel formats (COLMAP).
    """

    name: str
    values: np.ndarray
    sigma: np.ndarray
    pixel_size_mm: float | None = None
    sigma_image_mm: float | None = None
    model: str = "inverse"
    image_size: tuple | None = None
    model_auto: bool = False

    def choose_model(self) -> None:
        """With ``model_auto`` (no lens model given): ``forward`` when a distortion parameter
        (k1..b2, a) is free or weighted - self-calibration -, else ``inverse``."""
        if self.model_auto:
            self.model = "forward" if np.any(self.sigma[3:] != 0) else "inverse"

    def __post_init__(self) -> None:
        n = len(INTRINSICS)
        self.values = np.asarray(self.values, float).ravel()
        self.sigma = np.asarray(self.sigma, float).ravel()
        if self.values.size == n - 1:  # before the aspect parameter
            self.values = np.append(self.values, 0.0)
        if self.sigma.size == n - 1:
            self.sigma = np.append(self.sigma, 0.0)
        if self.values.size != n or self.sigma.size != n:
            raise SoftplotError(f"camera {self.name}: {n} interior parameters expected")
        if self.model not in LENS_MODELS:
            raise SoftplotError(
                f"camera {self.name}: lens model must be one of {LENS_MODELS}, got {self.model!r}"
            )
        if not (1.0 + self.values[10]) > 0:
            raise SoftplotError(f"camera {self.name}: aspect a must be > -1")

    @classmethod
    def from_certificate(cls, cam, free=(), weighted=None, pixel_size_mm=None) -> "BundleCamera":
        """From a :class:`softplot.camera.Camera`; ``free`` names free parameters,
        ``weighted`` maps names to a priori standard errors; all others are fixed."""
        d = cam.distortion
        if d.model == "radial-table":
            raise SoftplotError(
                f"camera {cam.name}: a radial-table distortion cannot be a bundle unknown; "
                "give Brown coefficients"
            )
        vals = np.array(
            [cam.c, cam.x0, cam.y0, d.k1, d.k2, d.k3, d.p1, d.p2, d.b1, d.b2, 0.0], float
        )
        return cls.build(cam.name, vals, free, weighted, pixel_size_mm)

    @classmethod
    def build(
        cls, name, values, free=(), weighted=None, pixel_size_mm=None, model="inverse"
    ) -> "BundleCamera":
        """From values (11,) or (10,) and the names of free / weighted parameters."""
        sig = np.zeros(len(INTRINSICS))
        for n in free:
            if n not in INTRINSICS:
                raise SoftplotError(f"camera {name}: unknown parameter {n!r}; use {INTRINSICS}")
            sig[INTRINSICS.index(n)] = FREE
        for n, s in (weighted or {}).items():
            if n not in INTRINSICS:
                raise SoftplotError(f"camera {name}: unknown parameter {n!r}; use {INTRINSICS}")
            if not s > 0:
                raise SoftplotError(f"camera {name}: a priori sigma of {n} must be > 0")
            sig[INTRINSICS.index(n)] = float(s)
        return cls(name, np.asarray(values, float).copy(), sig, pixel_size_mm, model=model)


@dataclass
class BundleData:
    """Everything a bundle needs; NaN approximations are filled by :mod:`.bundle_init`.

    Attributes
    ----------
    cameras : list of BundleCamera
    photo_names : list of str
    photo_camera : ndarray of int, shape (F,)
    X0 : ndarray, shape (F, 3)
        Approximate projection centres, object frame (NaN: unknown).
    angles : ndarray, shape (F, 3)
        Approximate omega, phi, kappa, radians (NaN: unknown).
    point_names : list of str
    XYZ : ndarray, shape (P, 3)
        Approximate object coordinates (NaN: unknown).
    control : ndarray, shape (P, 3)
        Control coordinates (NaN: no control for that coordinate).
    control_sigma : ndarray, shape (P, 3)
        ``0`` fixed, ``> 0`` weighted, NaN no control.
    obs_photo, obs_point : ndarray of int, shape (m,)
    xy : ndarray, shape (m, 2)
        Measured film coordinates, mm.
    sigma_xy : ndarray, shape (m, 2)
        Their standard errors, mm.
    cov_xy : ndarray, shape (m,), optional
        Covariance of x and y of every observation, mm^2 (correlated measurements, e.g.
        least-squares matching); ``None`` or 0: uncorrelated.
    photo_fixed : ndarray of bool, shape (F,)
        Exterior orientation held fixed.
    check : ndarray of bool, shape (P,)
        Check points: known coordinates in ``control`` not used as control.
    series : list of str, optional
        Series label of every photo (test-field calibration in series).
    precision_given : bool
        True when the image standard errors are stated (``sigma_image_um`` or the
        observations' ``sx, sy``): data snooping by Baarda's w-test. False: they are only
        a default, known relative to each other at best, and the observations are tested by
        Pope's tau test against the a posteriori sigma0.
    """

    cameras: list
    photo_names: list
    photo_camera: np.ndarray
    X0: np.ndarray
    angles: np.ndarray
    point_names: list
    XYZ: np.ndarray
    control: np.ndarray
    control_sigma: np.ndarray
    obs_photo: np.ndarray
    obs_point: np.ndarray
    xy: np.ndarray
    sigma_xy: np.ndarray
    photo_fixed: np.ndarray | None = None
    check: np.ndarray | None = None
    series: list | None = None
    cov_xy: np.ndarray | None = None
    precision_given: bool = True

    def __post_init__(self) -> None:
        F, P = len(self.photo_names), len(self.point_names)
        self.photo_camera = np.asarray(self.photo_camera, np.int64).reshape(F)
        self.X0 = np.asarray(self.X0, float).reshape(F, 3)
        self.angles = np.asarray(self.angles, float).reshape(F, 3)
        self.XYZ = np.asarray(self.XYZ, float).reshape(P, 3)
        self.control = np.asarray(self.control, float).reshape(P, 3)
        self.control_sigma = np.asarray(self.control_sigma, float).reshape(P, 3)
        self.obs_photo = np.asarray(self.obs_photo, np.int64).ravel()
        self.obs_point = np.asarray(self.obs_point, np.int64).ravel()
        m = self.obs_photo.size
        self.xy = np.asarray(self.xy, float).reshape(m, 2)
        self.sigma_xy = np.broadcast_to(np.asarray(self.sigma_xy, float), (m, 2)).copy()
        self.photo_fixed = (
            np.zeros(F, bool) if self.photo_fixed is None else np.asarray(self.photo_fixed, bool)
        )
        self.check = np.zeros(P, bool) if self.check is None else np.asarray(self.check, bool)
        if self.obs_point.size != m:
            raise SoftplotError("observations: photo and point columns differ in length")
        if m and (self.obs_photo.min() < 0 or self.obs_photo.max() >= F):
            raise SoftplotError("an observation refers to an unknown photo")
        if m and (self.obs_point.min() < 0 or self.obs_point.max() >= P):
            raise SoftplotError("an observation refers to an unknown point")
        if F and (self.photo_camera.min() < 0 or self.photo_camera.max() >= len(self.cameras)):
            raise SoftplotError("a photo refers to an unknown camera")
        if np.any(~(self.sigma_xy > 0)):
            raise SoftplotError("image standard errors must be > 0")
        if self.cov_xy is not None:
            self.cov_xy = np.broadcast_to(np.asarray(self.cov_xy, float), (m,)).copy()
            rho = self.cov_xy / (self.sigma_xy[:, 0] * self.sigma_xy[:, 1])
            if not np.all(np.abs(rho) < 1.0):
                bad = int(np.flatnonzero(~(np.abs(rho) < 1.0))[0])
                raise SoftplotError(
                    f"observation {bad + 1}: covariance sxy gives |correlation| >= 1 "
                    "(the 2x2 covariance must be positive definite)"
                )
            if not np.any(self.cov_xy):
                self.cov_xy = None
        key = self.obs_photo * max(P, 1) + self.obs_point
        if np.unique(key).size != m:
            raise SoftplotError("a point is measured twice in the same photo")
        if not np.all(np.isfinite(self.xy)):
            raise SoftplotError("image coordinates must be finite")

    @property
    def control_used(self) -> np.ndarray:
        """(P, 3) bool: coordinates acting as control (fixed or weighted; not check points)."""
        has = np.isfinite(self.control) & np.isfinite(self.control_sigma)
        has &= self.control_sigma >= 0
        return has & ~self.check[:, None]


@dataclass
class BundleOptions:
    """Bundle settings.

    ``datum``: "auto" (control if it fixes the datum - seven or more control coordinates, or
    fixed exterior orientations - else free), "control" or "free".
    ``scale_distance``: ``(point_a, point_b, distance)`` fixing the scale of a free network.
    ``alpha0``: data-snooping significance level (3.29 for 0.001).
    ``corr_warn``: correlation magnitude that raises a warning.
    ``covariance``: ``True`` / ``"auto"`` (every block while the camera side has at most
    ``full_covariance_limit`` unknowns, else as ``"interior"``), ``"full"`` (every block:
    exterior orientations, points, redundancy numbers and data snooping), ``"interior"``
    (the interior orientation only, plus the photos and points named in
    ``covariance_photos`` / ``covariance_points``: no redundancy numbers, no snooping) or
    ``False``.
    """

    datum: str = "auto"
    scale_distance: tuple | None = None
    alpha0: float = 0.001
    corr_warn: float = 0.9
    lm: LMOptions = field(default_factory=lambda: LMOptions(function_tolerance=1e-10))
    covariance: bool | str = True
    covariance_photos: tuple = ()
    covariance_points: tuple = ()
    full_covariance_limit: int = 3000


# ---------------------------------------------------------------------------------------------
# distortion


def distortion(xb, yb, p):
    """Lens displacement and its derivatives at reduced measured points (film mm).

    Parameters
    ----------
    xb, yb : ndarray (m,)
        Measured film coordinates reduced to the principal point, mm.
    p : ndarray (m, 11) or (11,)
        :data:`INTRINSICS` per point.

    Returns
    -------
    d : ndarray (m, 2)
        ``(dx, dy)``, mm (photo = reduced - d).
    dd_dxy : ndarray (m, 2, 2)
        ``d(dx, dy) / d(xb, yb)``.
    dd_dk : ndarray (m, 2, 7)
        ``d(dx, dy) / d(k1, k2, k3, p1, p2, b1, b2)``.
    """
    p = np.broadcast_to(p, (xb.size, np.shape(p)[-1]))
    k1, k2, k3, p1, p2, b1, b2 = (p[:, i] for i in range(3, 10))
    r2 = xb * xb + yb * yb
    rad = r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d rad / d r2
    m = xb.size
    d = np.empty((m, 2))
    d[:, 0] = xb * rad + p1 * (r2 + 2 * xb * xb) + 2 * p2 * xb * yb + b1 * xb + b2 * yb
    d[:, 1] = yb * rad + 2 * p1 * xb * yb + p2 * (r2 + 2 * yb * yb)
    J = np.empty((m, 2, 2))
    xy2 = 2 * xb * yb * drad
    J[:, 0, 0] = rad + 2 * xb * xb * drad + 6 * p1 * xb + 2 * p2 * yb + b1
    J[:, 0, 1] = xy2 + 2 * p1 * yb + 2 * p2 * xb + b2
    J[:, 1, 0] = xy2 + 2 * p1 * yb + 2 * p2 * xb
    J[:, 1, 1] = rad + 2 * yb * yb * drad + 2 * p1 * xb + 6 * p2 * yb
    K = np.zeros((m, 2, 7))
    K[:, 0, 0], K[:, 1, 0] = xb * r2, yb * r2
    K[:, 0, 1], K[:, 1, 1] = xb * r2 * r2, yb * r2 * r2
    K[:, 0, 2], K[:, 1, 2] = xb * r2**3, yb * r2**3
    K[:, 0, 3], K[:, 1, 3] = r2 + 2 * xb * xb, 2 * xb * yb
    K[:, 0, 4], K[:, 1, 4] = 2 * xb * yb, r2 + 2 * yb * yb
    K[:, 0, 5] = xb
    K[:, 0, 6] = yb
    return d, J, K


# ---------------------------------------------------------------------------------------------
# model for the engine


@dataclass
class _State:
    X0: np.ndarray  # (F,3)
    M: np.ndarray  # (F,3,3)
    intr: np.ndarray  # (C,10)
    XYZ: np.ndarray  # (P,3)


class _Model:
    """Collinearity + distortion model for :func:`levenberg_marquardt` (groups = photos)."""

    def __init__(self, data: BundleData, point_free: np.ndarray, dense_limit: int = 4000):
        self.data = data
        F, C = len(data.photo_names), len(data.cameras)
        # camera-side unknown layout: EO blocks then intrinsic blocks
        eo_idx = -np.ones((F, 6), np.int64)
        n = 0
        for f in range(F):
            if not data.photo_fixed[f]:
                eo_idx[f] = np.arange(n, n + 6)
                n += 6
        in_idx = -np.ones((C, len(INTRINSICS)), np.int64)
        for c, cam in enumerate(data.cameras):
            act = cam.sigma != 0
            in_idx[c, act] = np.arange(n, n + act.sum())
            n += int(act.sum())
        self.eo_idx, self.in_idx, self.n_cam = eo_idx, in_idx, n
        gp = np.hstack([eo_idx, in_idx[data.photo_camera]])
        #: Jacobian slots (EO, then interior parameters) that are unknown in some photo: the
        #: others (fixed everywhere) are dropped from the engine's blocks
        self.slots = np.flatnonzero((gp >= 0).any(axis=0)) if gp.size else np.zeros(0, int)
        if self.slots.size == 0:
            self.slots = np.arange(min(gp.shape[1], 1))
        gp = gp[:, self.slots]
        # photos along the block's long axis (a narrow band for strips of aerial photos)
        hint = None
        X0 = data.X0
        if F > 2 and np.all(np.isfinite(X0)):
            c = X0 - X0.mean(axis=0)
            hint = c @ np.linalg.svd(c, full_matrices=False)[2][0]
        self.structure = SchurStructure(
            n,
            len(data.point_names),
            gp,
            data.obs_photo,
            data.obs_point,
            2,
            point_free,
            dense_limit=dense_limit,
            order_hint=hint,
        )
        # priors on intrinsics
        pri_i, pri_s, pri_v = [], [], []
        for c, cam in enumerate(data.cameras):
            w = np.isfinite(cam.sigma) & (cam.sigma > 0)
            pri_i.append(in_idx[c, w])
            pri_s.append(cam.sigma[w])
            pri_v.append(np.flatnonzero(w) + len(INTRINSICS) * c)
        self.pri_idx = np.concatenate(pri_i) if pri_i else np.zeros(0, np.int64)
        self.pri_sig = np.concatenate(pri_s) if pri_s else np.zeros(0)
        self.pri_flat = np.concatenate(pri_v) if pri_v else np.zeros(0, np.int64)
        self.pri_val = np.array([cam.values for cam in data.cameras]).ravel()[self.pri_flat]
        # point priors (weighted control)
        used = data.control_used
        wt = used & (data.control_sigma > 0)
        self.cp_idx = np.flatnonzero(wt.any(axis=1))
        s = np.where(wt, data.control_sigma, np.inf)[self.cp_idx]
        self.cp_w = 1.0 / s  # 0 where not weighted
        self.cp_val = np.where(wt, data.control, 0.0)[self.cp_idx]
        self.isig = 1.0 / data.sigma_xy
        #: whitening matrices L^-1 (m, 2, 2) of correlated observations (Sigma = L L')
        self.wh = None
        if data.cov_xy is not None:
            sx, sy, sxy = data.sigma_xy[:, 0], data.sigma_xy[:, 1], data.cov_xy
            l21 = sxy / sx
            l22 = np.sqrt(sy * sy - l21 * l21)
            wh = np.zeros((sx.size, 2, 2))
            wh[:, 0, 0] = 1.0 / sx
            wh[:, 1, 1] = 1.0 / l22
            wh[:, 1, 0] = -l21 / (sx * l22)
            self.wh = wh
        fwd = np.array([c.model == "forward" for c in data.cameras], bool)
        self.forward = fwd[data.photo_camera[data.obs_photo]] if fwd.size else np.zeros(0, bool)
        self.all_forward = bool(self.forward.all())
        self.all_inverse = not self.forward.any()

    def whiten(self, a: np.ndarray) -> np.ndarray:
        """Whiten (m, 2, ...) residual rows or Jacobian blocks."""
        if self.wh is None:
            return a * self.isig.reshape(self.isig.shape + (1,) * (a.ndim - 2))
        return np.einsum("mij,mj...->mi...", self.wh, a)

    def unwhiten(self, r: np.ndarray) -> np.ndarray:
        """Residuals (m, 2) in mm from whitened ones."""
        if self.wh is None:
            return r * self.data.sigma_xy
        L = np.linalg.inv(self.wh)
        return np.einsum("mij,mj->mi", L, r)

    @property
    def n_prior_rows(self) -> int:
        return int(self.pri_idx.size + np.count_nonzero(self.cp_w))

    def _subsets(self):
        """(index, forward) pairs covering the observations, one per lens model."""
        if self.all_inverse:
            return [(slice(None), False)]
        if self.all_forward:
            return [(slice(None), True)]
        return [(np.flatnonzero(~self.forward), False), (np.flatnonzero(self.forward), True)]

    def evaluate(self, state: _State, jacobian: bool) -> Evaluation:
        d = self.data
        ph, pt = d.obs_photo, d.obs_point
        cam = d.photo_camera[ph]
        P = state.intr[cam]  # (m,11)
        M = state.M[ph]
        dX = state.XYZ[pt] - state.X0[ph]
        u = np.einsum("mij,mj->mi", M, dX)
        w = u[:, 2]
        qx, qy = u[:, 0] / w, u[:, 1] / w
        c, x0, y0 = P[:, 0], P[:, 1], P[:, 2]
        s_a = 1.0 + P[:, 10]  # aspect: xa = (1 + a) xb
        m = w.size
        raw = np.empty((m, 2))
        if jacobian:
            Jc = np.zeros((m, 2, 6 + len(INTRINSICS)))
            C2 = np.empty((m, 2, 2))  # d residual / d (pinhole point)
        for idx, fwd in self._subsets():
            Pi, si = P[idx], s_a[idx]
            xp, yp = -c[idx] * qx[idx], -c[idx] * qy[idx]  # pinhole point, reduced (mm)
            if not fwd:
                # residual = pinhole - (xa - d(xa)), xa = ((1 + a) (x - x0), y - y0)
                xb = d.xy[idx, 0] - x0[idx]
                xa, ya = si * xb, d.xy[idx, 1] - y0[idx]
                dist, dJ, dK = distortion(xa, ya, Pi)
                raw[idx, 0] = xp - xa + dist[:, 0]
                raw[idx, 1] = yp - ya + dist[:, 1]
                if jacobian:
                    T = -dJ
                    T[:, 0, 0] += 1.0
                    T[:, 1, 1] += 1.0  # I - d(dx)/dx
                    C2[idx] = np.eye(2)
                    Jc[idx, :, 7] = T[:, :, 0] * si[:, None]
                    Jc[idx, :, 8] = T[:, :, 1]
                    Jc[idx, :, 9:16] = dK
                    Jc[idx, :, 16] = -T[:, :, 0] * xb[:, None]
            else:
                # residual = (x0 + (xp + dx(xp)) / (1 + a), y0 + yp + dy(xp)) - measured
                dist, dJ, dK = distortion(xp, yp, Pi)
                xa, ya = xp + dist[:, 0], yp + dist[:, 1]
                raw[idx, 0] = x0[idx] + xa / si - d.xy[idx, 0]
                raw[idx, 1] = y0[idx] + ya - d.xy[idx, 1]
                if jacobian:
                    D = dJ.copy()
                    D[:, 0, 0] += 1.0
                    D[:, 1, 1] += 1.0
                    D[:, 0, :] /= si[:, None]
                    C2[idx] = D
                    Jc[idx, 0, 7] = 1.0
                    Jc[idx, 1, 8] = 1.0
                    Jc[idx, :, 9:16] = dK
                    Jc[idx, 0, 9:16] /= si[:, None]
                    Jc[idx, 0, 16] = -xa / (si * si)
        r = self.whiten(raw)
        cam_prior = None
        if self.pri_idx.size:
            vals = state.intr.ravel()[self.pri_flat]
            cam_prior = (self.pri_idx, (vals - self.pri_val) / self.pri_sig, 1.0 / self.pri_sig)
        pt_prior = None
        if self.cp_idx.size:
            rr = (state.XYZ[self.cp_idx] - self.cp_val) * self.cp_w
            J = np.zeros((self.cp_idx.size, 3, 3))
            J[:, 0, 0], J[:, 1, 1], J[:, 2, 2] = self.cp_w[:, 0], self.cp_w[:, 1], self.cp_w[:, 2]
            pt_prior = (self.cp_idx, rr, J)
        if not jacobian:
            return Evaluation(r, cam_prior=cam_prior, pt_prior=pt_prior)
        A = np.zeros((m, 2, 3))  # d(-c q)/du
        A[:, 0, 0] = -c / w
        A[:, 0, 2] = c * qx / w
        A[:, 1, 1] = -c / w
        A[:, 1, 2] = c * qy / w
        if not self.all_inverse:
            A = np.matmul(C2, A)
        Jp = np.matmul(A, M)
        Jc[:, :, 0:3] = -Jp
        # rotation increment: du/dd = -[u]x
        Jc[:, :, 3] = A[:, :, 2] * u[:, 1, None] - A[:, :, 1] * u[:, 2, None]
        Jc[:, :, 4] = A[:, :, 0] * u[:, 2, None] - A[:, :, 2] * u[:, 0, None]
        Jc[:, :, 5] = A[:, :, 1] * u[:, 0, None] - A[:, :, 0] * u[:, 1, None]
        Jc[:, :, 6] = -np.einsum("mij,mj->mi", C2, np.column_stack([qx, qy]))
        if self.slots.size != Jc.shape[2]:
            Jc = Jc[:, :, self.slots]
        return Evaluation(r, self.whiten(Jc), self.whiten(Jp), cam_prior, pt_prior)

    def retract(self, state: _State, d_cam, d_pts) -> _State:
        de = np.append(d_cam, 0.0)
        X0 = state.X0 + de[self.eo_idx[:, :3]] * (self.eo_idx[:, :3] >= 0)
        rv = de[self.eo_idx[:, 3:]] * (self.eo_idx[:, 3:] >= 0)
        M = np.matmul(Rotation.from_rotvec(rv).as_matrix(), state.M)
        intr = state.intr + de[self.in_idx] * (self.in_idx >= 0)
        return _State(X0, M, intr, state.XYZ + d_pts)


# ---------------------------------------------------------------------------------------------
# datum helpers


def similarity_null_space(XYZ, X0, M, centre=None):
    """Columns of the 7-parameter similarity null space, split by unknown kind.

    A small similarity ``X <- X + t + theta x (X - g) + s (X - g)`` about ``g``.

    Returns
    -------
    Gp : ndarray (P, 3, 7)
        For the points.
    Gx : ndarray (F, 3, 7)
        For the projection centres.
    Gr : ndarray (F, 3, 7)
        For the rotation increments (``d = -M theta``).
    """
    g = XYZ.mean(axis=0) if centre is None else centre

    def rows(X):
        Y = X - g
        G = np.zeros((X.shape[0], 3, 7))
        G[:, 0, 0] = G[:, 1, 1] = G[:, 2, 2] = 1.0
        # -[Y]x theta
        G[:, 0, 4], G[:, 0, 5] = Y[:, 2], -Y[:, 1]
        G[:, 1, 3], G[:, 1, 5] = -Y[:, 2], Y[:, 0]
        G[:, 2, 3], G[:, 2, 4] = Y[:, 1], -Y[:, 0]
        G[:, :, 6] = Y
        return G

    Gr = np.zeros((M.shape[0], 3, 7))
    Gr[:, :, 3:6] = -M
    return rows(XYZ), rows(X0), Gr


def _choose_datum_coordinates(Gp, point_ok):
    """Seven point coordinates whose fixing removes the similarity defect (pivoted QR)."""
    P = Gp.shape[0]
    G = (Gp * point_ok[:, None, None]).reshape(3 * P, 7)
    scale = np.linalg.norm(G, axis=0)
    scale[scale == 0] = 1.0
    _, _, piv = scipy.linalg.qr((G / scale).T, pivoting=True, mode="economic")
    return piv[:7]


def _helmert_to(src, dst):
    """Similarity ``dst ~ s R src + t`` (Umeyama), returns (s, R, t)."""
    ms, md = src.mean(0), dst.mean(0)
    A, B = src - ms, dst - md
    U, d, Vt = np.linalg.svd(B.T @ A)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ D @ Vt
    s = float(np.sum(d * np.diag(D)) / np.sum(A * A))
    return s, R, md - s * R @ ms


# ---------------------------------------------------------------------------------------------
# results


@dataclass
class BundleResult:
    """Outcome of :func:`bundle_adjust` (see the module docstring for units and frames).

    Covariances are a posteriori (``sigma0^2 Q``) when the redundancy is positive.
    """

    data: BundleData
    sigma0: float
    redundancy: int
    n_observations: int
    n_unknowns: int
    datum: str
    cost: float
    initial_cost: float
    iterations: int
    seconds: float
    converged: bool
    message: str
    intrinsics: np.ndarray  # (C,10)
    intrinsics_std: np.ndarray  # (C,10), 0 for fixed
    intrinsics_corr: list  # per camera (n_free, n_free) with names
    X0: np.ndarray
    angles: np.ndarray
    M: np.ndarray
    eo_std: np.ndarray  # (F,6)
    XYZ: np.ndarray
    XYZ_cov: np.ndarray  # (P,3,3)
    residuals_mm: np.ndarray  # (m,2) predicted - measured
    w: np.ndarray  # (m,2) Baarda
    redundancy_numbers: np.ndarray  # (m,2)
    flagged: np.ndarray  # (m,) bool
    critical: float
    warnings: list
    correlation_eo_max: list  # per camera: {param: (max |corr|, photo, eo name)}
    history: list = field(default_factory=list)
    #: "baarda-w" (w against the stated precision), "pope-tau" (tau = w / sigma0, the
    #: precision not stated) or "none"; ``critical`` is that test's critical value
    snooping_test: str = "baarda-w"
    _internals: dict | None = field(default=None, repr=False)

    def full_point_covariance(self) -> np.ndarray:
        """Full (3P, 3P) covariance of all points in the result's datum (small networks only).

        Built column by column from the Schur solver (``P`` solves of size ``n_cam``); the
        per-point blocks of it are :attr:`XYZ_cov`. Used to verify the inner constraints.
        """
        it = self._internals
        if it is None:
            raise SoftplotError("no covariance was computed for this result")
        inv, model, st = it["inv"], it["model"], it["state"]
        P = st.XYZ.shape[0]
        rc = np.zeros((model.n_cam, 3 * P))
        rp = np.eye(3 * P).reshape(P, 3, 3 * P)
        _, xp = inv.solve(rc, rp)
        Q = xp.reshape(3 * P, 3 * P)
        if self.datum.startswith("free"):
            Gc, Gp, Cc, Cp = _null_space_matrices(model, st, it["ok"], it["opt"], self.data)
            CtG = Cc.T @ Gc + np.einsum("pai,paj->ij", Cp, Gp)
            A = np.linalg.inv(CtG)
            Tc, Tp = inv.solve(Cc, Cp)
            CtQC = Cc.T @ Tc + np.einsum("pai,paj->ij", Cp, Tp)
            G = Gp.reshape(3 * P, 7)
            T = Tp.reshape(3 * P, 7)
            Q = Q - G @ A @ T.T - T @ A.T @ G.T + G @ A @ CtQC @ A.T @ G.T
        var = self.sigma0**2 if self.redundancy > 0 else 1.0
        return var * 0.5 * (Q + Q.T)

    @property
    def XYZ_std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.einsum("pii->pi", self.XYZ_cov), 0, None))

    def rms_image_um(self) -> dict:
        v = self.residuals_mm * 1000.0
        return {
            "x": float(np.sqrt(np.mean(v[:, 0] ** 2))),
            "y": float(np.sqrt(np.mean(v[:, 1] ** 2))),
            "xy": float(np.sqrt(np.mean(np.sum(v**2, axis=1)))),
        }

    def rms_image_px(self) -> dict | None:
        px = np.array([c.pixel_size_mm or np.nan for c in self.data.cameras])
        p = px[self.data.photo_camera[self.data.obs_photo]]
        if not np.all(np.isfinite(p)):
            return None
        v = self.residuals_mm / p[:, None]
        return {
            "x": float(np.sqrt(np.mean(v[:, 0] ** 2))),
            "y": float(np.sqrt(np.mean(v[:, 1] ** 2))),
            "xy": float(np.sqrt(np.mean(np.sum(v**2, axis=1)))),
        }

    def check_point_errors(self) -> np.ndarray:
        """(n_check, 3) adjusted minus known coordinates of the check points."""
        d = self.data
        ok = d.check & np.all(np.isfinite(d.control), axis=1)
        return self.XYZ[ok] - d.control[ok]

    def check_rms(self) -> dict | None:
        e = self.check_point_errors()
        if not e.size:
            return None
        r = np.sqrt(np.mean(e**2, axis=0))
        return {"n": int(e.shape[0]), "X": float(r[0]), "Y": float(r[1]), "Z": float(r[2])}

    def largest_residuals(self, n: int = 10) -> list:
        """The ``n`` observations with the largest |w| (dicts)."""
        d = self.data
        wmax = np.nanmax(np.abs(np.nan_to_num(self.w, nan=0.0)), axis=1)
        order = np.argsort(-wmax)[:n]
        return [
            {
                "photo": d.photo_names[d.obs_photo[o]],
                "point": d.point_names[d.obs_point[o]],
                "vx_um": float(self.residuals_mm[o, 0] * 1000),
                "vy_um": float(self.residuals_mm[o, 1] * 1000),
                "wx": _f(self.w[o, 0]),
                "wy": _f(self.w[o, 1]),
                "flagged": bool(self.flagged[o]),
            }
            for o in order
        ]

    def _pixel_of_obs(self) -> np.ndarray:
        """(m,) pixel size (mm) of every observation's camera, NaN when unknown."""
        px = np.array([c.pixel_size_mm or np.nan for c in self.data.cameras], float)
        return px[self.data.photo_camera[self.data.obs_photo]]

    def residual_table(self) -> dict:
        """Every image observation: photo, point, residual (um, px), redundancy numbers and
        Baarda's w per coordinate, flag - as columns (lists / arrays of length m)."""
        d = self.data
        v_um = self.residuals_mm * 1000.0
        v_px = self.residuals_mm / self._pixel_of_obs()[:, None]
        return {
            "photo": [d.photo_names[f] for f in d.obs_photo],
            "point": [d.point_names[p] for p in d.obs_point],
            "vx_um": v_um[:, 0],
            "vy_um": v_um[:, 1],
            "vx_px": v_px[:, 0],
            "vy_px": v_px[:, 1],
            "rx": self.redundancy_numbers[:, 0],
            "ry": self.redundancy_numbers[:, 1],
            "wx": self.w[:, 0],
            "wy": self.w[:, 1],
            "flagged": self.flagged,
        }

    def _group_stats(self, key: np.ndarray, n_groups: int) -> dict:
        v = self.residuals_mm * 1000.0
        n = np.bincount(key, minlength=n_groups)
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = np.sqrt(np.bincount(key, v[:, 0] ** 2, n_groups) / n)
            sy = np.sqrt(np.bincount(key, v[:, 1] ** 2, n_groups) / n)
            px = self._pixel_of_obs()
            pxm = np.bincount(key, px, n_groups) / n
        aw = np.nan_to_num(np.abs(self.w), nan=0.0).max(axis=1)
        wmax = np.zeros(n_groups)
        np.maximum.at(wmax, key, aw)
        rsum = np.bincount(key, np.nansum(self.redundancy_numbers, axis=1), n_groups)
        # not computed (covariance limited to the interior orientation): null
        known = np.bincount(key, np.isfinite(self.redundancy_numbers).any(axis=1), n_groups)
        wmax[known == 0] = np.nan
        rsum[known == 0] = np.nan
        return {
            "n": n,
            "rms_x_um": sx,
            "rms_y_um": sy,
            "rms_xy_um": np.sqrt(sx**2 + sy**2),
            "rms_xy_px": np.sqrt(sx**2 + sy**2) / 1000.0 / pxm,
            "max_abs_w": wmax,
            "flagged": np.bincount(key, self.flagged.astype(float), n_groups).astype(int),
            "redundancy": rsum,
        }

    def photo_statistics(self) -> list:
        """Per photo: observations, RMS residuals (um, px), max |w|, flagged, sum of the
        redundancy numbers of its observations."""
        st = self._group_stats(self.data.obs_photo, len(self.data.photo_names))
        return [
            {
                "photo": n,
                **{
                    k: _f(v[i]) if k != "n" and k != "flagged" else int(v[i]) for k, v in st.items()
                },
            }
            for i, n in enumerate(self.data.photo_names)
        ]

    def point_statistics(self) -> list:
        """Per point: rays, RMS image residuals (um, px), max |w|, flagged observations."""
        st = self._group_stats(self.data.obs_point, len(self.data.point_names))
        return [
            {
                "point": n,
                **{
                    k: _f(v[i]) if k != "n" and k != "flagged" else int(v[i]) for k, v in st.items()
                },
            }
            for i, n in enumerate(self.data.point_names)
        ]

    def to_json(self) -> dict:
        """JSON-ready dict (keys documented in docs/bundle.md)."""
        d = self.data
        cams = []
        for c, cam in enumerate(d.cameras):
            cams.append(
                {
                    "name": cam.name,
                    "parameters": {
                        n: {
                            "value": float(self.intrinsics[c, i]),
                            "std": float(self.intrinsics_std[c, i]),
                            "status": _status(cam.sigma[i]),
                        }
                        for i, n in enumerate(INTRINSICS)
                    },
                    "correlation": self.intrinsics_corr[c],
                    "max_correlation_with_eo": self.correlation_eo_max[c],
                    "pixel_size_mm": cam.pixel_size_mm,
                    "lens": cam.model,
                }
            )
        photos = []
        for f, name in enumerate(d.photo_names):
            photos.append(
                {
                    "name": name,
                    "camera": d.cameras[d.photo_camera[f]].name,
                    **{
                        k: {"value": float(v), "std": float(s)}
                        for k, v, s in zip(
                            EO_NAMES,
                            [*self.X0[f], *self.angles[f]],
                            self.eo_std[f],
                            strict=True,
                        )
                    },
                    "angle_unit": "rad",
                }
            )
        std = self.XYZ_std
        points = [
            {
                "name": n,
                "X": {"value": float(self.XYZ[p, 0]), "std": float(std[p, 0])},
                "Y": {"value": float(self.XYZ[p, 1]), "std": float(std[p, 1])},
                "Z": {"value": float(self.XYZ[p, 2]), "std": float(std[p, 2])},
                "control": [_status_ctl(d, p, a) for a in range(3)],
                "check": bool(d.check[p]),
            }
            for p, n in enumerate(d.point_names)
        ]
        return {
            "sigma0": self.sigma0,
            "redundancy": self.redundancy,
            "observations": self.n_observations,
            "unknowns": self.n_unknowns,
            "datum": self.datum,
            "rms_image_um": self.rms_image_um(),
            "rms_image_px": self.rms_image_px(),
            "cost": self.cost,
            "initial_cost": self.initial_cost,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "converged": self.converged,
            "message": self.message,
            "critical_value": self.critical,
            "flagged": int(self.flagged.sum()),
            "largest_residuals": self.largest_residuals(),
            "residuals": _records(self.residual_table()),
            "photo_statistics": self.photo_statistics(),
            "point_statistics": self.point_statistics(),
            "check_points_rms": self.check_rms(),
            "warnings": list(self.warnings),
            "cameras": cams,
            "photos": photos,
            "points": points,
        }


def _f(x):
    return None if not np.isfinite(x) else float(x)


def _records(table: dict) -> list:
    """Column table -> list of row dicts (NaN -> None)."""
    keys = list(table)
    cols = []
    for k in keys:
        c = table[k]
        if isinstance(c, np.ndarray) and c.dtype.kind == "f":
            cols.append([None if not np.isfinite(x) else float(x) for x in c.tolist()])
        elif isinstance(c, np.ndarray):
            cols.append(c.tolist())
        else:
            cols.append(list(c))
    return [dict(zip(keys, row, strict=True)) for row in zip(*cols, strict=True)]


def _status(s):
    if s == 0:
        return "fixed"
    if not np.isfinite(s):
        return "free"
    return f"weighted({s:g})"


def _status_ctl(d, p, a):
    if d.check[p]:
        return "check" if np.isfinite(d.control[p, a]) else "none"
    if not d.control_used[p, a]:
        return "none"
    return "fixed" if d.control_sigma[p, a] == 0 else "weighted"


# ---------------------------------------------------------------------------------------------
# the adjustment


def bundle_adjust(data: BundleData, options: BundleOptions | None = None) -> BundleResult:
    """Adjust a bundle block (all approximations must be finite: see :mod:`.bundle_init`).

    Parameters
    ----------
    data : BundleData
    options : BundleOptions, optional

    Returns
    -------
    BundleResult

    Raises
    ------
    SoftplotError
        Missing approximations, a singular system (undetermined datum or parameter), or a
        point with fewer than two rays and no control.
    """
    opt = options or BundleOptions()
    n_cam_est = 6 * len(data.photo_names) + 10 * len(data.cameras)
    with blas_threads(1 if n_cam_est <= opt.lm.single_thread_limit else None):
        return _bundle_adjust(data, opt)


def _bundle_adjust(data: BundleData, opt: BundleOptions) -> BundleResult:
    d = data
    F, P = len(d.photo_names), len(d.point_names)
    if not (np.all(np.isfinite(d.X0)) and np.all(np.isfinite(d.angles))):
        raise SoftplotError("bundle: exterior orientation approximations missing (initialise)")
    if not np.all(np.isfinite(d.XYZ)):
        bad = [d.point_names[i] for i in np.flatnonzero(~np.all(np.isfinite(d.XYZ), axis=1))]
        raise SoftplotError(f"bundle: no approximate coordinates for point(s) {bad[:5]}")
    rays = np.bincount(d.obs_point, minlength=P)
    used = d.control_used
    weak = (rays < 2) & ~used.all(axis=1)
    if np.any(weak & (rays > 0)) or np.any((rays == 0) & ~used.all(axis=1)):
        bad = [d.point_names[i] for i in np.flatnonzero(weak)]
        raise SoftplotError(
            f"bundle: point(s) {bad[:5]} have fewer than two rays and are not full control"
        )
    # datum
    fixed_ctl = used & (d.control_sigma == 0)
    datum = opt.datum
    if datum not in ("auto", "control", "free"):
        raise SoftplotError(f"unknown datum {datum!r}; use auto, control or free")
    n_ctl = int(used.sum())
    n_fixed = int(d.photo_fixed.sum())
    if datum == "auto":
        # control, or the exterior orientations held (a fixed-pose rig: two photos fix it)
        datum = "control" if n_ctl >= 7 or n_fixed >= 2 or (n_fixed and n_ctl) else "free"
    point_free = np.ones((P, 3), bool)
    XYZ0 = d.XYZ.copy()
    if datum == "control":
        point_free &= ~fixed_ctl
        XYZ0[fixed_ctl] = d.control[fixed_ctl]
    M0 = rotation_matrix(d.angles[:, 0], d.angles[:, 1], d.angles[:, 2])
    X00 = d.X0.copy()
    fixed7 = None
    if datum == "free":
        if d.photo_fixed.any():
            raise SoftplotError("free network: no exterior orientation may be fixed")
        Gp, _, _ = similarity_null_space(XYZ0, X00, M0)
        fixed7 = _choose_datum_coordinates(Gp, rays >= 2)
        pf = point_free.reshape(-1)
        pf[fixed7] = False
        point_free = pf.reshape(P, 3)
        dd = BundleData(**{**d.__dict__})
        dd.control_sigma = np.full((P, 3), np.nan)  # control ignored as control
        d_model = dd
    else:
        d_model = d
    model = _Model(d_model, point_free)
    intr0 = np.array([c.values for c in d.cameras], float).reshape(-1, len(INTRINSICS))
    state = _State(X00, M0, intr0, XYZ0)
    res = levenberg_marquardt(model, state, opt.lm)
    st: _State = res.state
    X0, M, intr, XYZ = st.X0, st.M, st.intr, st.XYZ
    # free network: move to the inner-constraint datum
    if datum == "free":
        ok = rays >= 2
        s, R, t = _helmert_to(XYZ[ok], XYZ0[ok])
        if opt.scale_distance is not None:
            a, b, dist = opt.scale_distance
            ia, ib = d.point_names.index(a), d.point_names.index(b)
            cur = s * np.linalg.norm(XYZ[ia] - XYZ[ib])
            g = (s * XYZ[ok] @ R.T + t).mean(axis=0)
            f = float(dist) / cur
            s, t = s * f, f * (t - g) + g
        XYZ = s * XYZ @ R.T + t
        X0 = s * X0 @ R.T + t
        M = M @ R.T
        st = _State(X0, M, intr, XYZ)
    ev = model.evaluate(st, False)
    cost = ev.cost
    n_obs = 2 * d.obs_photo.size + model.n_prior_rows
    n_unk = model.structure.n_unknowns
    redundancy = n_obs - n_unk
    sigma0 = math.sqrt(2 * cost / redundancy) if redundancy > 0 else float("nan")
    var = sigma0**2 if redundancy > 0 else 1.0
    resid = model.unwhiten(ev.r)  # mm
    crit = critical_value(opt.alpha0)
    warnings: list[str] = []
    if not res.converged:
        warnings.append(f"not converged: {res.message}")
    C = len(d.cameras)
    m = d.obs_photo.size
    in_std = np.zeros((C, len(INTRINSICS)))
    eo_std = np.zeros((F, 6))
    XYZ_cov = np.zeros((P, 3, 3))
    corr_list = [{"names": [], "matrix": []} for _ in range(C)]
    eo_max = [{} for _ in range(C)]
    w = np.full((m, 2), np.nan)
    rnum = np.full((m, 2), np.nan)
    angles = np.column_stack(angles_from_matrix(M))
    internals = None
    mode = opt.covariance
    if mode is True or mode == "auto":
        mode = "full" if model.n_cam <= opt.full_covariance_limit else "interior"
    if mode not in (False, None, "full", "interior"):
        raise SoftplotError(f"unknown covariance mode {opt.covariance!r}; use auto, full, interior")
    if mode == "interior" and datum == "free":
        warnings.append("free network: covariance needs the full camera-side inverse; skipped")
        mode = False
    if mode == "interior":
        lin = model_linearize(model, st)
        inv = NormalInverse(lin, dense_inverse_limit=0)
        internals = {"inv": inv, "model": model, "state": st, "ok": rays >= 2, "opt": opt}
        eo_std[:] = np.nan
        XYZ_cov[:] = np.nan
        _selected_covariance(
            inv, model, d, opt, var, M, in_std, eo_std, XYZ_cov, corr_list, warnings
        )
        warnings.append(
            "covariance limited to the interior orientation (and the photos/points asked "
            "for): no redundancy numbers or data snooping (use covariance 'full')"
        )
    elif mode == "full":
        lin = model_linearize(model, st)
        inv = NormalInverse(lin)
        internals = {"inv": inv, "model": model, "state": st, "ok": rays >= 2, "opt": opt}
        Qcc, Qpp = inv.Qcc, inv.point_blocks()
        if datum == "free":
            Qcc, Qpp = _s_transform(inv, model, st, point_free, rays >= 2, opt, d)
        Ccc = var * Qcc
        cd = np.sqrt(np.clip(np.diag(Ccc), 0, None))
        ei = model.eo_idx
        act_f = np.flatnonzero(ei[:, 0] >= 0)
        if act_f.size:
            eo_std[act_f, :3] = cd[ei[act_f, :3]]
            Jang = _angle_jacobian(M[act_f])  # (n, 3, 3)
            rc = ei[act_f, 3:]
            Cr = Ccc[rc[:, :, None], rc[:, None, :]]  # (n, 3, 3) rotation-increment blocks
            ca = np.einsum("nij,njk,nlk->nil", Jang, Cr, Jang)
            eo_std[act_f, 3:] = np.sqrt(np.clip(np.einsum("nii->ni", ca), 0, None))
        for c in range(C):
            act = model.in_idx[c] >= 0
            idx = model.in_idx[c, act]
            in_std[c, act] = cd[idx]
            names = [n for n, a in zip(INTRINSICS, act, strict=True) if a]
            sd = cd[idx]
            with np.errstate(invalid="ignore", divide="ignore"):
                R_ = Ccc[np.ix_(idx, idx)] / np.outer(sd, sd)
            corr_list[c] = {"names": names, "matrix": np.round(R_, 4).tolist()}
            for i, j in zip(*np.triu_indices(len(idx), 1), strict=True):
                if abs(R_[i, j]) > opt.corr_warn:
                    warnings.append(
                        f"camera {d.cameras[c].name}: correlation {names[i]}-{names[j]} = "
                        f"{R_[i, j]:+.3f}"
                    )
            # against the exterior orientations of the photos of this camera
            phs = np.flatnonzero((d.photo_camera == c) & (ei[:, 0] >= 0))
            if phs.size and idx.size:
                eocols = ei[phs].ravel()
                with np.errstate(invalid="ignore", divide="ignore"):
                    Rx = Ccc[np.ix_(idx, eocols)] / np.outer(sd, cd[eocols])
                Rx = np.nan_to_num(Rx)
                for i, nme in enumerate(names):
                    j = int(np.argmax(np.abs(Rx[i])))
                    val = float(Rx[i, j])
                    eo_max[c][nme] = {
                        "corr": round(val, 4),
                        "photo": d.photo_names[phs[j // 6]],
                        "eo": EO_NAMES[j % 6],
                    }
                    if abs(val) > opt.corr_warn:
                        warnings.append(
                            f"camera {d.cameras[c].name}: correlation {nme}-"
                            f"{EO_NAMES[j % 6]}({d.photo_names[phs[j // 6]]}) = {val:+.3f}"
                        )
        XYZ_cov = var * Qpp
        q = inv.observation_blocks()
        if model.wh is None:
            qvv = 1.0 - np.einsum("mii->mi", q)
            rnum = qvv
            num = ev.r
        else:
            # correlated observations (Sigma = L L', whitening L^-1): redundancy numbers
            # diag(Qvv P) = diag(L (I - q) L^-1); Baarda's w_i = (P v)_i / sqrt((P Qvv P)_ii)
            # with P v = L^-T r and P Qvv P = L^-T (I - q) L^-1
            Rw = np.eye(2) - q
            Wh = model.wh
            Lm = np.linalg.inv(Wh)
            rnum = np.einsum("mii->mi", Lm @ Rw @ Wh)
            num = np.einsum("mji,mj->mi", Wh, ev.r)
            qvv = np.einsum("mii->mi", Wh.transpose(0, 2, 1) @ Rw @ Wh)
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = (rnum > 1e-8) & (qvv > 0)
            w = np.where(ok, num / np.sqrt(np.clip(qvv, 1e-300, None)), np.nan)
    test, stat = "baarda-w", w
    if not d.precision_given:
        # the precision is a default: standardise by the a posteriori sigma0 (Pope's tau)
        crit = tau_critical_value(int(redundancy), opt.alpha0)
        test = "pope-tau" if np.isfinite(crit) and sigma0 > 0 else "none"
        stat = w / sigma0 if test == "pope-tau" else np.full_like(w, np.nan)
    flagged = np.nan_to_num(np.abs(stat), nan=0.0).max(axis=1) > crit
    if flagged.any():
        sym = "tau" if test == "pope-tau" else "w"
        warnings.append(
            f"{int(flagged.sum())} observation(s) fail data snooping (|{sym}| > {crit:.2f})"
        )
    return BundleResult(
        data=d,
        sigma0=sigma0,
        redundancy=int(redundancy),
        n_observations=int(n_obs),
        n_unknowns=int(n_unk),
        datum=(
            "free+distance"
            if datum == "free" and opt.scale_distance is not None
            else "fixed-eo"
            if datum == "control" and n_ctl < 7
            else datum
        ),
        cost=cost,
        initial_cost=res.initial_cost,
        iterations=res.iterations,
        seconds=res.seconds,
        converged=res.converged,
        message=res.message,
        intrinsics=intr,
        intrinsics_std=in_std,
        intrinsics_corr=corr_list,
        X0=X0,
        angles=angles,
        M=M,
        eo_std=eo_std,
        XYZ=XYZ,
        XYZ_cov=XYZ_cov,
        residuals_mm=resid,
        w=w,
        redundancy_numbers=rnum,
        flagged=flagged,
        critical=crit,
        snooping_test=test,
        warnings=warnings,
        correlation_eo_max=eo_max,
        history=res.history,
        _internals=internals,
    )


def _selected_covariance(inv, model, d, opt, var, M, in_std, eo_std, XYZ_cov, corr, warnings):
    """Interior orientation (and selected photos / points) covariance by solves only."""
    for c in range(len(d.cameras)):
        act = model.in_idx[c] >= 0
        idx = model.in_idx[c, act]
        if not idx.size:
            continue
        Q = var * inv.columns(idx)[idx]
        sd = np.sqrt(np.clip(np.diag(Q), 0, None))
        in_std[c, act] = sd
        names = [n for n, a in zip(INTRINSICS, act, strict=True) if a]
        with np.errstate(invalid="ignore", divide="ignore"):
            R_ = Q / np.outer(sd, sd)
        corr[c] = {"names": names, "matrix": np.round(R_, 4).tolist()}
        for i, j in zip(*np.triu_indices(len(idx), 1), strict=True):
            if abs(R_[i, j]) > opt.corr_warn:
                warnings.append(
                    f"camera {d.cameras[c].name}: correlation {names[i]}-{names[j]} = "
                    f"{R_[i, j]:+.3f}"
                )
    for name in opt.covariance_photos:
        if name not in d.photo_names:
            raise SoftplotError(f"covariance_photos: unknown photo {name!r}")
        f = d.photo_names.index(name)
        ei = model.eo_idx[f]
        if ei[0] < 0:
            eo_std[f] = 0.0
            continue
        Cr = var * inv.columns(ei)[ei]
        eo_std[f, :3] = np.sqrt(np.clip(np.diag(Cr)[:3], 0, None))
        J = _angle_jacobian(M[f][None])[0]
        eo_std[f, 3:] = np.sqrt(np.clip(np.diag(J @ Cr[3:, 3:] @ J.T), 0, None))
    pts = []
    for name in opt.covariance_points:
        if name not in d.point_names:
            raise SoftplotError(f"covariance_points: unknown point {name!r}")
        pts.append(d.point_names.index(name))
    if pts:
        XYZ_cov[pts] = var * inv.point_blocks_of(pts)


def model_linearize(model, state):
    """Undamped linearisation of ``model`` at ``state`` (for the covariance)."""
    from softplot.adjust.sparse_bundle import Linearization

    return Linearization(model.structure, model.evaluate(state, True))


def _angle_jacobian(M):
    """d(omega, phi, kappa) / d(rotation increment) at ``M`` (n, 3, 3): central differences."""
    h = 1e-7
    J = np.empty(M.shape[:-2] + (3, 3))
    for i in range(3):  # three increments, vectorised over the photos
        e = np.zeros(3)
        e[i] = h
        a = np.stack(angles_from_matrix(Rotation.from_rotvec(e).as_matrix() @ M), axis=-1)
        b = np.stack(angles_from_matrix(Rotation.from_rotvec(-e).as_matrix() @ M), axis=-1)
        J[..., :, i] = (np.mod(a - b + np.pi, 2 * np.pi) - np.pi) / (2 * h)
    return J


def _null_space_matrices(model, st, ok, opt, d):
    """G (camera part (n_cam,7), point part (P,3,7)) and C (same split) of the free datum."""
    Gp, Gx, Gr = similarity_null_space(st.XYZ, st.X0, st.M, st.XYZ[ok].mean(axis=0))
    n = model.n_cam
    Gc = np.zeros((n + 1, 7))
    ei = model.eo_idx
    Gc[ei[:, :3].ravel()] = Gx.reshape(-1, 7)
    Gc[ei[:, 3:].ravel()] = Gr.reshape(-1, 7)
    Gc = Gc[:n]
    Cp = Gp * ok[:, None, None]
    Cc = np.zeros((n, 7))
    if opt.scale_distance is not None:
        a, b, _ = opt.scale_distance
        ia, ib = d.point_names.index(a), d.point_names.index(b)
        e = st.XYZ[ia] - st.XYZ[ib]
        e /= np.linalg.norm(e)
        Cp = Cp.copy()
        Cp[:, :, 6] = 0.0
        Cp[ia, :, 6] = e
        Cp[ib, :, 6] = -e
    return Gc, Gp, Cc, Cp


def _s_transform(inv: NormalInverse, model, st, point_free, ok, opt, d):
    """Qcc and Qpp blocks moved from the 7-coordinate datum to the inner-constraint one."""
    # C covers every point coordinate (the held seven included: Q is zero there)
    Gc, Gp, Cc_full, Cp_full = _null_space_matrices(model, st, ok, opt, d)
    CtG = Cc_full.T @ Gc + np.einsum("pai,paj->ij", Cp_full, Gp)
    A = np.linalg.inv(CtG)
    Tc, Tp = inv.solve(Cc_full, Cp_full)  # Q C
    CtQC = Cc_full.T @ Tc + np.einsum("pai,paj->ij", Cp_full, Tp)
    Qcc = inv.Qcc
    H = A @ CtQC @ A.T
    Qcc = Qcc - Gc @ A @ Tc.T - Tc @ A.T @ Gc.T + Gc @ H @ Gc.T
    Qpp = inv.point_blocks()
    GA = np.einsum("pai,ij->paj", Gp, A)
    X = np.einsum("paj,pbj->pab", GA, Tp)
    Qpp = Qpp - X - X.transpose(0, 2, 1) + np.einsum("pai,ij,pbj->pab", Gp, H, Gp)
    return 0.5 * (Qcc + Qcc.T), Qpp
