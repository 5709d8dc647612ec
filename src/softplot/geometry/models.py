"""One interface for every film-correction method: pixel <-> film mm from reference marks.

A correction turns measured pixel positions of the reference marks (reseau crosses, or
fiducials for cameras without a reseau) and their calibrated film coordinates into a mapping
between the **pixel** plane of a scan (px, x right, y down) and the **film** plane (mm, x right,
y up, origin at the reseau / fiducial centre).

Methods (:data:`METHODS`; ``docs/correction.md`` compares them):

==================  ===========================================================================
``mesh``            the camera's mesh: ``mesh-affine`` for a 3 x 3 reseau, else ``mesh-homography``
``mesh-affine``     one affine per triangle (two per reseau quad; :mod:`softplot.geometry.mesh`)
``mesh-homography`` one homography per reseau quad
``mesh-bilinear``   bilinear interpolation per reseau quad
``raw-plate``       a similarity through the 4 corner crosses (or all fiducials): "raw plate";
                    on the pixel y axis reversed (pixel y down, film y up) unless the scan
                    is mirrored (whichever fits better)
``raw-plate-affine`` the same with an affine
``affine``          one affine over all crosses (fiducials without a reseau), least squares
``projective``      one homography over all crosses
``bilinear``        one bilinear over all crosses
``poly2``, ``poly3`` one polynomial of degree 2 / 3 over all crosses
==================  ===========================================================================

Every model has ``pixel_to_film(xy) -> (film, flags)``, ``film_to_pixel(xy) -> (px, flags)``
(vectorised, (N, 2)), ``pixel_to_film_point(x, y)`` (plain floats) and ``residuals_um`` at the
marks it used. ``flags`` is :data:`FLAG_OK` or :data:`FLAG_OUTSIDE_RESEAU` (the point lies
outside the area of the reseau - the polygon of its border crosses - or, without a reseau,
outside the convex hull of the fiducials); the corrected value is still returned (nearest
border mesh, or the global model's extrapolation).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.mesh import (
    _FILL_KIND,
    FLAG_OK,
    FLAG_OUTSIDE_IMAGE,
    FLAG_OUTSIDE_RESEAU,
    MESH_KINDS,
    MeshModel,
    default_mesh_kind,
)
from softplot.geometry.transforms import MIN_POINTS, PlaneTransform, fit_transform

__all__ = [
    "METHODS",
    "GLOBAL_METHODS",
    "ReferenceMarks",
    "CorrectionModel",
    "GlobalModel",
    "build_model",
    "resolve_method",
    "method_min_marks",
]

#: global methods and the plane transform each fits
GLOBAL_METHODS = {
    "raw-plate": "similarity",
    "raw-plate-affine": "affine",
    "affine": "affine",
    "projective": "projective",
    "bilinear": "bilinear",
    "poly2": "poly2",
    "poly3": "poly3",
}

METHODS = ("mesh",) + MESH_KINDS + tuple(GLOBAL_METHODS)


@dataclass(frozen=True)
class ReferenceMarks:
    """Reference marks of one scan: calibrated film mm and measured pixel positions.

    Attributes
    ----------
    grid_film, grid_pixel : ndarray (rows, cols, 2) or None
        Reseau crosses: calibrated film mm and measured pixel px (NaN where not measured).
    fid_film, fid_pixel : ndarray (F, 2)
        Fiducial marks: film mm and pixel px (NaN where not measured).
    fid_names : tuple of str
        Fiducial names, in the order of the arrays.
    grid_cov, fid_cov : ndarray (rows, cols, 2, 2) and (F, 2, 2), or None
        Covariance of each measured pixel position (px^2, pixel x, y; NaN where unknown): a
        mark measured across a line only (a cross with one bar) has a large variance along
        it. Every model weights the marks by it (:func:`build_model`).
    """

    grid_film: np.ndarray | None = None
    grid_pixel: np.ndarray | None = None
    fid_film: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fid_pixel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fid_names: tuple[str, ...] = ()
    grid_cov: np.ndarray | None = None
    fid_cov: np.ndarray | None = None

    @property
    def has_grid(self) -> bool:
        return self.grid_film is not None and self.grid_film.shape[0] * self.grid_film.shape[1] > 0

    @property
    def grid_shape(self) -> tuple[int, int]:
        return (0, 0) if not self.has_grid else self.grid_film.shape[:2]

    def grid_names(self) -> list[str]:
        r, c = self.grid_shape
        return [f"R{i}C{j}" for i in range(r) for j in range(c)]

    def reference(self) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """The marks global methods use: measured crosses, or measured fiducials without a
        reseau. Returns film (n, 2) mm, pixel (n, 2) px, names."""
        if self.has_grid:
            f = self.grid_film.reshape(-1, 2)
            p = self.grid_pixel.reshape(-1, 2)
            names = self.grid_names()
        else:
            f, p, names = self.fid_film, self.fid_pixel, list(self.fid_names)
        ok = np.all(np.isfinite(p), axis=1)
        return f[ok], p[ok], [n for n, o in zip(names, ok, strict=True) if o]

    def covariances(self, names) -> np.ndarray | None:
        """The pixel covariances (n, 2, 2) of the named marks (NaN where unknown), or None
        when no mark has one."""
        table = {}
        if self.has_grid and self.grid_cov is not None:
            table.update(zip(self.grid_names(), self.grid_cov.reshape(-1, 2, 2), strict=True))
        if self.fid_cov is not None:
            table.update(zip(self.fid_names, self.fid_cov, strict=True))
        if not table:
            return None
        nan = np.full((2, 2), np.nan)
        C = np.array([table.get(n, nan) for n in names], float).reshape(-1, 2, 2)
        return C if np.isfinite(C).all((1, 2)).any() else None

    def without(self, names) -> "ReferenceMarks":
        """A copy with the named marks treated as not measured."""
        drop = set(names)
        gp = self.grid_pixel
        if self.has_grid:
            gp = gp.copy()
            for k, n in enumerate(self.grid_names()):
                if n in drop:
                    gp.reshape(-1, 2)[k] = np.nan
        fp = self.fid_pixel.copy()
        for k, n in enumerate(self.fid_names):
            if n in drop:
                fp[k] = np.nan
        return ReferenceMarks(self.grid_film, gp, self.fid_film, fp, self.fid_names,
                              self.grid_cov, self.fid_cov)


def resolve_method(method: str, marks: ReferenceMarks) -> str:
    """The concrete method name (``mesh`` -> the camera's mesh kind); validates the name."""
    if method not in METHODS:
        raise SoftplotError(f"unknown method {method!r}: expected one of {', '.join(METHODS)}")
    if method == "mesh":
        if not marks.has_grid:
            raise SoftplotError("method mesh needs a reseau; this camera has only fiducials")
        return default_mesh_kind(*marks.grid_shape)
    return method


def method_min_marks(method: str) -> int:
    """Minimum number of measured marks a method needs."""
    if method in MESH_KINDS:
        return max(MIN_POINTS[_FILL_KIND[method]], 4)
    return MIN_POINTS[GLOBAL_METHODS[method]]


class CorrectionModel:
    """Common interface of the mesh and global correction models (pixel <-> film mm)."""

    method: str

    def pixel_to_film(self, xy, post=None, bounds=None):  # pragma: no cover - interface
        """Pixel (N, 2) -> film (N, 2) mm and flags; ``post`` chains a film -> photo map per
        chunk; ``bounds`` = (x0, x1, y0, y1) px flags points outside it ``outside-image``."""
        raise NotImplementedError

    def film_to_pixel(self, xy):  # pragma: no cover - interface
        raise NotImplementedError

    def pixel_to_film_point(self, x: float, y: float):  # pragma: no cover - interface
        raise NotImplementedError

    def film_to_pixel_point(self, x: float, y: float):  # pragma: no cover - interface
        raise NotImplementedError


class _MeshCorrection(CorrectionModel):
    """A :class:`MeshModel` behind the common interface."""

    def __init__(self, mesh: MeshModel, n_used: int) -> None:
        self.mesh = mesh
        self.method = mesh.kind
        self.n_used = n_used
        self.residuals_um = np.zeros((n_used, 2))  # a mesh interpolates its crosses

    def pixel_to_film(self, xy, post=None, bounds=None):
        return self.mesh.pixel_to_film(xy, post, bounds)

    def film_to_pixel(self, xy):
        return self.mesh.film_to_pixel(xy)

    def pixel_to_film_point(self, x, y):
        return self.mesh.pixel_to_film_point(x, y)

    def film_to_pixel_point(self, x, y):
        return self.mesh.film_to_pixel_point(x, y)

    @property
    def n_params(self) -> int:
        return 6 * self.mesh.n_cells if self.method == "mesh-affine" else 8 * self.mesh.n_cells

    def describe(self) -> str:
        return self.mesh.describe()


class _Hull:
    """Convex polygon test (vectorised), for the fiducial area."""

    def __init__(self, pts: np.ndarray) -> None:
        from scipy.spatial import ConvexHull

        self.eq = ConvexHull(pts).equations  # a x + b y + c <= 0 inside
        self.tol = 1e-9 * float(np.ptp(pts, axis=0).max())

    def inside(self, xy: np.ndarray) -> np.ndarray:
        return np.all(xy @ self.eq[:, :2].T + self.eq[:, 2] <= self.tol, axis=1)


class GlobalModel(CorrectionModel):
    """One plane transform pixel -> film mm over the reference marks, with its precision.

    ``transform`` is the fitted :class:`~softplot.geometry.transforms.PlaneTransform`
    (source pixel - with ``flip_y`` the pixel ``(x, -y)``, so that a similarity can map the
    y-down pixel plane onto the y-up film plane -, destination film mm); ``residuals_um``
    its residuals at the marks used, micrometres (fitted - calibrated); ``names`` those
    marks.
    """

    def __init__(
        self, method: str, transform: PlaneTransform, names, area, flip_y: bool = False
    ) -> None:
        self.method = method
        self.flip_y = flip_y
        self._flip = np.array([1.0, -1.0 if flip_y else 1.0])
        self.transform = transform
        self.names = list(names)
        self.residuals_um = transform.residuals * 1000.0
        self.n_used = transform.n_points
        self.n_params = transform.params.size
        self._area = area  # MeshModel (reseau area) or _Hull pair (pixel, film) or None
        self._py = None
        if transform.kind in ("similarity", "affine", "projective"):
            M = transform.matrix() @ np.diag([1.0, self._flip[1], 1.0])
            Mi = np.linalg.inv(M)
            self._py = (tuple(M.ravel().tolist()), tuple(Mi.ravel().tolist()))

    def _flags_pixel(self, xy: np.ndarray) -> np.ndarray:
        a = self._area
        if a is None:
            return np.zeros(xy.shape[0], np.uint8)
        if isinstance(a, MeshModel):
            return a.pixel_to_film(xy)[1]
        return np.where(a[0].inside(xy), FLAG_OK, FLAG_OUTSIDE_RESEAU).astype(np.uint8)

    def _flags_film(self, xy: np.ndarray) -> np.ndarray:
        a = self._area
        if a is None:
            return np.zeros(xy.shape[0], np.uint8)
        if isinstance(a, MeshModel):
            return a.film_to_pixel(xy)[1]
        return np.where(a[1].inside(xy), FLAG_OK, FLAG_OUTSIDE_RESEAU).astype(np.uint8)

    def pixel_to_film(self, xy, post=None, bounds=None):
        p = np.asarray(xy, float).reshape(-1, 2)
        out = self.transform.forward(p * self._flip)
        if post is not None:
            X, Y = post(out[:, 0].copy(), out[:, 1].copy())
            out = np.column_stack([X, Y])
        flags = self._flags_pixel(p)
        if bounds is not None:
            x0, x1, y0, y1 = bounds
            off = (p[:, 0] < x0) | (p[:, 0] > x1) | (p[:, 1] < y0) | (p[:, 1] > y1)
            flags[off] = FLAG_OUTSIDE_IMAGE
        return out, flags

    def film_to_pixel(self, xy):
        f = np.asarray(xy, float).reshape(-1, 2)
        return self.transform.inverse(f) * self._flip, self._flags_film(f)

    def pixel_to_film_point(self, x, y):
        if self._py is not None:
            m = self._py[0]
            x, y = float(x), float(y)
            w = m[6] * x + m[7] * y + m[8]
            X = (m[0] * x + m[1] * y + m[2]) / w
            Y = (m[3] * x + m[4] * y + m[5]) / w
        else:
            X, Y = self.transform.forward([[x, y]] * self._flip)[0].tolist()
        if isinstance(self._area, MeshModel):
            flag = self._area.pixel_to_film_point(x, y)[2]
        else:
            flag = int(self._flags_pixel(np.array([[x, y]], float))[0])
        return X, Y, flag

    def film_to_pixel_point(self, x, y):
        out, flags = self.film_to_pixel([[x, y]])
        return float(out[0, 0]), float(out[0, 1]), int(flags[0])

    def describe(self) -> str:
        t = self.transform
        return (
            f"{self.method}: {t.kind} over {t.n_points} marks, sigma0 "
            f"{t.sigma0 * 1000:.2f} um, rms {t.rms * 1000:.2f} um"
        )


def _raw_plate_marks(marks: ReferenceMarks) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The 4 corner crosses (nearest measured cross to each grid corner) or the fiducials."""
    if not marks.has_grid:
        return marks.reference()
    rows, cols = marks.grid_shape
    meas = np.all(np.isfinite(marks.grid_pixel), axis=2)
    rr, cc = np.nonzero(meas)
    picked: list[tuple[int, int]] = []
    for r0, c0 in ((0, 0), (0, cols - 1), (rows - 1, cols - 1), (rows - 1, 0)):
        if rr.size == 0:
            break
        d = np.maximum(np.abs(rr - r0), np.abs(cc - c0)) * 1000 + np.abs(rr - r0) + np.abs(cc - c0)
        i = int(np.argmin(d))
        if (rr[i], cc[i]) not in picked:
            picked.append((int(rr[i]), int(cc[i])))
    f = np.array([marks.grid_film[r, c] for r, c in picked]).reshape(-1, 2)
    p = np.array([marks.grid_pixel[r, c] for r, c in picked]).reshape(-1, 2)
    return f, p, [f"R{r}C{c}" for r, c in picked]


def _area(marks: ReferenceMarks):
    """Object deciding ``outside-reseau``: a mesh of the reseau, or the fiducials' hull."""
    if marks.has_grid:
        try:
            return MeshModel(marks.grid_film, marks.grid_pixel, "mesh-homography")
        except SoftplotError:
            return None
    f, p, _ = marks.reference()
    if f.shape[0] >= 3:
        try:
            return (_Hull(p), _Hull(f))
        except Exception:  # degenerate hull (collinear marks)
            return None
    return None


def _weighted_refit(kind: str, T: PlaneTransform, C: np.ndarray, flip: bool) -> PlaneTransform:
    """The fit ``T`` (unweighted) again, each mark weighted by the inverse of its error's
    covariance in the film plane: its measured pixel covariance ``C`` (n, 2, 2) carried by
    the transform's Jacobian, plus the model's own error (film deformation the transform
    does not follow: the unweighted fit's squared residuals less the marks' measurement
    variance, their median, per coordinate, isotropic). A mark without a covariance (NaN) gets the
    others' median. A mark measured across a line only thus constrains the fit across it.
    """
    src = T.src
    F = np.diag([1.0, -1.0]) if flip else np.eye(2)
    C = np.array(C, float)
    known = np.isfinite(C).all((1, 2))
    if not known.any():
        return T
    C[~known] = np.median(C[known], axis=0)
    Cs = F @ C @ F
    J = T.jacobian(src)
    Cf = np.einsum("nij,njk,nlk->nil", J, Cs, J)
    # the model's error per coordinate: a robust (median) estimate from the unweighted fit's
    # residuals less each mark's own measurement variance (the median of chi^2_2 / 2 is
    # ln 2), so that a few marks imprecise along a line do not pass for deformation
    meas = np.trace(Cf, axis1=1, axis2=2) / 2.0
    v2 = (np.asarray(T.residuals, float) ** 2).sum(1) / 2.0
    model = max(float(np.median(v2 - meas)) / np.log(2.0), 0.0)
    Cf = Cf + model * np.eye(2)
    scale = float(np.median(np.trace(Cf, axis1=1, axis2=2) / 2.0))
    if not scale > 0:
        return T
    W = np.linalg.inv(Cf / scale)
    W = 0.5 * (W + W.transpose(0, 2, 1))
    return fit_transform(kind, src, T.dst, weights=W)


def _mesh_positions(marks: ReferenceMarks, kind: str) -> np.ndarray:
    """The crosses' pixel positions a mesh interpolates: as measured, except where a
    cross's covariance is far from round (more than :data:`MESH_FUSE_RATIO` between its
    axes: measured across a line only). There the measurement is combined with the position
    its neighbours predict (a transform over the surrounding block of measured crosses, as
    :class:`~softplot.geometry.mesh.MeshModel` fills missing ones; its ``sigma0`` as the
    prediction's isotropic standard deviation) by their inverse covariances: across the line
    the measurement, along it the prediction."""
    gp = np.array(marks.grid_pixel, float)
    C = marks.grid_cov
    if C is None:
        return gp
    rows, cols = gp.shape[:2]
    meas = np.isfinite(gp).all(2)
    lam = np.full((rows, cols, 2), np.nan)
    ok = meas & np.isfinite(C).all((2, 3))
    lam[ok] = np.linalg.eigvalsh(C[ok])
    fuse = ok & (lam[..., 1] > MESH_FUSE_RATIO * np.maximum(lam[..., 0], 1e-30))
    fit_kind = _FILL_KIND.get(kind, "projective")
    need = MIN_POINTS[fit_kind]
    out = gp.copy()
    for r, c in np.argwhere(fuse):
        for half in range(1, max(rows, cols)):
            r0, r1 = max(r - half, 0), min(r + half + 1, rows)
            c0, c1 = max(c - half, 0), min(c + half + 1, cols)
            m = meas[r0:r1, c0:c1] & ~fuse[r0:r1, c0:c1]
            if m.sum() < need + 2:
                continue
            try:
                T = fit_transform(fit_kind, marks.grid_film[r0:r1, c0:c1][m],
                                  gp[r0:r1, c0:c1][m])
            except SoftplotError:
                continue
            pred = T.forward(marks.grid_film[r, c][None])[0]
            vp = max(float(T.sigma0) ** 2 if np.isfinite(T.sigma0) else 0.0, 1e-8)
            Wm = np.linalg.inv(C[r, c])
            out[r, c] = np.linalg.solve(Wm + np.eye(2) / vp, Wm @ gp[r, c] + pred / vp)
            break
    return out


#: a cross whose covariance's axes differ by more than this factor (variance) is combined
#: with its neighbours' prediction before a mesh interpolates it (:func:`_mesh_positions`)
MESH_FUSE_RATIO = 25.0


def build_model(method: str, marks: ReferenceMarks, area=True) -> CorrectionModel:
    """Fit a correction model of ``method`` (see :data:`METHODS`) to the reference marks.

    Parameters
    ----------
    method : str
        A name of :data:`METHODS`.
    marks : ReferenceMarks
        Calibrated film mm and measured pixel positions.
    area : bool or object
        Global methods: compute the ``outside-reseau`` flag (True), skip it (False: every
        point ``ok``), or reuse an area object from an earlier model (``model._area``).

    Raises
    ------
    SoftplotError
        Unknown method; a mesh without a reseau; fewer measured marks than the method needs
        (the message names the method and the counts).
    """
    m = resolve_method(method, marks)
    if m in MESH_KINDS:
        rows, cols = marks.grid_shape
        n = int(np.all(np.isfinite(marks.grid_pixel), axis=2).sum())
        need = method_min_marks(m)
        if n < need:
            raise SoftplotError(
                f"method {method} needs at least {need} measured reseau crosses, got {n} "
                f"of {rows * cols}"
            )
        return _MeshCorrection(MeshModel(marks.grid_film, _mesh_positions(marks, m), m), n)
    kind = GLOBAL_METHODS[m]
    if m.startswith("raw-plate"):
        f, p, names = _raw_plate_marks(marks)
        what = "corner crosses" if marks.has_grid else "fiducials"
    else:
        f, p, names = marks.reference()
        what = "reseau crosses" if marks.has_grid else "fiducials"
    need = MIN_POINTS[kind]
    if f.shape[0] < need:
        raise SoftplotError(
            f"method {method} needs at least {need} measured {what}, got {f.shape[0]}"
        )
    flip = False
    try:
        T = fit_transform(kind, p, f)
        if kind == "similarity":
            # a similarity cannot mirror: the y-down pixel plane of an ordinary scan maps onto
            # the y-up film plane with a reflection, a scan of the film seen from its back
            # without one; keep whichever fits
            Tf = fit_transform(kind, p * np.array([1.0, -1.0]), f)
            if not (T.rms <= Tf.rms):
                T, flip = Tf, True
        C = marks.covariances(names)
        if C is not None and T.redundancy > 0:
            T = _weighted_refit(kind, T, C, flip)
    except SoftplotError as exc:
        raise SoftplotError(f"method {method}: {exc}") from None
    if area is True:
        a = _area(marks)
    elif area is False:
        a = None
    else:
        a = area
    return GlobalModel(m, T, names, a, flip_y=flip)
