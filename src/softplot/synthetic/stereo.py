"""Synthetic stereo pairs with exact truth: orientations, a terrain, film deformations.

:func:`aerial_pair` builds a vertical aerial pair (60 % overlap) over a Gaussian hill

    Z(X, Y) = Z0 + A exp(-((X - Xc)^2 + (Y - Yc)^2) / (2 s^2))

whose contour at height H is the circle of radius ``s sqrt(2 ln(A / (H - Z0)))`` about
(Xc, Yc): the exact truth for contour restitution. Each photo may carry an affine film
deformation (photo mm -> film mm, what a scanned/shrunk film shows), so the film-correction
path of the plotter is exercised: ``film = D @ photo + t``.

Coordinates: object (m, Z up); photo mm (collinearity frame, principal point x0, y0);
film mm (instrument coordinates the plotter's carriages measure). Photo 0 is the left one.
Returns plain arrays and callables (no dependency on :mod:`softplot.stereo`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.collinearity import project
from softplot.geometry.rotation import rotation_matrix

__all__ = ["SyntheticPair", "TexturedTerrain", "aerial_pair", "rollei_pair"]


@dataclass
class SyntheticPair:
    """Truth of a synthetic stereo pair (index 0 = left, 1 = right).

    Attributes
    ----------
    X0 : ndarray (2, 3)
        Projection centres, object m.
    angles : ndarray (2, 3)
        omega, phi, kappa, radians.
    c, x0, y0 : ndarray (2,)
        Interior orientation, mm.
    hill : tuple
        ``(Xc, Yc, Z0, A, s)`` of the terrain.
    deform : ndarray (2, 2, 3)
        Affine film deformation per photo: ``film = D[:, :2] @ photo + D[:, 2]`` (mm).
    format_mm : float
        Half side of the (square) photo format, mm.
    """

    X0: np.ndarray
    angles: np.ndarray
    c: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    hill: tuple
    deform: np.ndarray
    format_mm: float = 115.0

    def M(self, k: int) -> np.ndarray:
        """Rotation object -> photo axes of photo k."""
        return rotation_matrix(*self.angles[k])

    def terrain(self, X, Y) -> np.ndarray:
        """Terrain height Z(X, Y), object m."""
        Xc, Yc, Z0, A, s = self.hill
        return Z0 + A * np.exp(
            -((np.asarray(X) - Xc) ** 2 + (np.asarray(Y) - Yc) ** 2) / (2 * s * s)
        )

    def contour_radius(self, H: float) -> float:
        """Radius of the true contour at height H (m)."""
        _, _, Z0, A, s = self.hill
        if not Z0 < H < Z0 + A:
            raise SoftplotError(f"height {H} outside the hill ({Z0}, {Z0 + A})")
        return float(s * np.sqrt(2 * np.log(A / (H - Z0))))

    def contour_truth(self, H: float, n: int = 64) -> np.ndarray:
        """``n`` points of the true contour at H, (n, 3) object m (counter-clockwise)."""
        Xc, Yc = self.hill[:2]
        r = self.contour_radius(H)
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.c_[Xc + r * np.cos(t), Yc + r * np.sin(t), np.full(n, float(H))]

    def sample_points(self, n: int, seed: int = 0) -> np.ndarray:
        """``n`` terrain points in the overlap, (n, 3) object m."""
        rng = np.random.default_rng(seed)
        Xc, Yc = self.hill[:2]
        half = 0.35 * self.ground_width
        X = Xc + rng.uniform(-half, half, n)
        Y = Yc + rng.uniform(-half, half, n)
        return np.c_[X, Y, self.terrain(X, Y)]

    @property
    def ground_width(self) -> float:
        """Ground side of one photo at the hill's base height, m."""
        return float(2 * self.format_mm / self.c[0] * (self.X0[0, 2] - self.hill[2]))

    def photo(self, k: int, XYZ) -> np.ndarray:
        """Object points -> photo mm of photo k, (N, 2)."""
        return project(XYZ, self.X0[k], self.M(k), self.c[k], self.x0[k], self.y0[k])

    def photo_to_film(self, k: int, xy) -> np.ndarray:
        """Photo mm -> film mm (apply the film deformation) of photo k."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        D = self.deform[k]
        return xy @ D[:, :2].T + D[:, 2]

    def film_to_photo(self, k: int, xy) -> np.ndarray:
        """Film mm -> photo mm (the exact film correction) of photo k."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        D = self.deform[k]
        return np.linalg.solve(D[:, :2], (xy - D[:, 2]).T).T

    def film(self, k: int, XYZ) -> np.ndarray:
        """Object points -> film mm of photo k."""
        return self.photo_to_film(k, self.photo(k, XYZ))

    def corrections(self, k: int):
        """``(film_to_photo, photo_to_film)`` callables of photo k (picklable)."""
        return partial(self.film_to_photo, k), partial(self.photo_to_film, k)


def aerial_pair(
    *,
    seed: int = 0,
    c: float = 152.0,
    flying_height: float = 1500.0,
    overlap: float = 0.6,
    tilt_deg: float = 2.0,
    deform: bool = True,
    hill_height: float = 180.0,
) -> SyntheticPair:
    """A vertical aerial pair (23 cm format) over a Gaussian hill.

    Parameters
    ----------
    seed : int
        Random orientation perturbations and film deformations.
    c : float
        Principal distance, mm.
    flying_height : float
        Flying height above the hill's base (Z0 = 200 m), m.
    overlap : float
        Forward overlap (0.6 = 60 %).
    tilt_deg : float
        Maximum |omega|, |phi|, |kappa| perturbation, degrees.
    deform : bool
        Give each film an affine deformation (shrinkage up to 300 ppm, shear, offset).
    hill_height : float
        Amplitude A of the hill, m.
    """
    rng = np.random.default_rng(seed)
    Z0 = 200.0
    half = 115.0
    width = 2 * half / c * flying_height
    base = (1 - overlap) * width
    Xc, Yc = base / 2, 0.0
    X0 = np.array([[0.0, 0.0, Z0 + flying_height], [base, 0.0, Z0 + flying_height]])
    X0[:, :2] += rng.uniform(-5, 5, (2, 2))
    X0[:, 2] += rng.uniform(-10, 10, 2)
    angles = np.deg2rad(rng.uniform(-tilt_deg, tilt_deg, (2, 3)))
    cc = np.array([c, c])
    x0 = rng.uniform(-0.02, 0.02, 2)
    y0 = rng.uniform(-0.02, 0.02, 2)
    D = np.zeros((2, 2, 3))
    for k in range(2):
        if deform:
            sx, sy = 1 - rng.uniform(0, 3e-4, 2)
            sh = rng.uniform(-1e-4, 1e-4)
            D[k, :, :2] = [[sx, sh], [0.0, sy]]
            D[k, :, 2] = rng.uniform(-0.5, 0.5, 2)
        else:
            D[k, :, :2] = np.eye(2)
    return SyntheticPair(X0, angles, cc, x0, y0, (Xc, Yc, Z0, hill_height, 0.12 * width), D, half)


class TexturedTerrain:
    """Ground of a :class:`SyntheticPair` with a fractal texture, seen by one photo.

    A picklable scene callable for :func:`softplot.synthetic.render_scan`:
    ``__call__(x_mm, y_mm)`` takes undeformed (certificate) film mm and returns the
    reflectance in [0, 1] of the first surface the ray meets - exact per pixel (no raster of
    the geometry): film mm -> photo mm (``interior.film_to_photo``) -> ray (the true exterior
    orientation) -> the surface, which is the Gaussian hill plus, optionally, a flat-roofed
    box (a building whose walls occlude the ground behind them).

    The texture is fractal noise on an object-space raster of ``pitch`` m (bilinear), mean
    0.5 and standard deviation ``0.15 * contrast``; inside ``blank`` (X0, X1, Y0, Y1, object m)
    the ground is uniform (0.5): nothing there to match.

    Parameters
    ----------
    pair : SyntheticPair
    k : int
        Photo index (0 left, 1 right).
    interior : object with ``film_to_photo((N, 2)) -> (N, 2)`` (mm)
    seed : int
        Texture seed (the same for both photos of a pair: it is the ground's).
    pitch : float
        Texture raster pitch, object m.
    box : (X0, X1, Y0, Y1, Ztop) or None
        A building: vertical walls over the rectangle, flat roof at Ztop (object m).
    blank : (X0, X1, Y0, Y1) or None
        A uniform area of the ground.
    """

    def __init__(self, pair: SyntheticPair, k: int, interior, *, seed: int = 0,
                 pitch: float = 0.1, contrast: float = 2.0, box=None, blank=None):
        self.pair, self.k, self.io = pair, int(k), interior
        self.box = None if box is None else tuple(float(v) for v in box)
        self.blank = None if blank is None else tuple(float(v) for v in blank)
        self.pitch = float(pitch)
        self.contrast = float(contrast)
        self.seed = int(seed)
        Xc, Yc = pair.hill[:2]
        half = 0.75 * pair.ground_width + 0.6 * abs(pair.X0[1, 0] - pair.X0[0, 0])
        self.origin = (Xc - half, Yc - half)
        self.n = int(np.ceil(2 * half / self.pitch)) + 2
        self._raster = None

    def _tex(self) -> np.ndarray:
        if self._raster is None:
            from softplot.synthetic.scene import _fractal

            rng = np.random.default_rng(self.seed + 4242)
            cells = max(8, int(self.n * self.pitch / 0.5))
            octaves = tuple(c for c in (cells // 64, cells // 32, cells // 16, cells // 8,
                                        cells // 4, cells // 2, cells) if c >= 2)
            t = _fractal((self.n, self.n), rng, octaves)
            self._raster = np.clip(0.5 + 0.15 * self.contrast * t, 0.02, 0.98).astype(np.float32)
        return self._raster

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_raster"] = None
        return d

    # -- geometry ---------------------------------------------------------------------

    def surface(self, X, Y) -> np.ndarray:
        """Height of the visible top surface (hill, or the roof over the box), object m."""
        Z = self.pair.terrain(X, Y)
        if self.box is not None:
            x0, x1, y0, y1, zt = self.box
            X, Y = np.asarray(X), np.asarray(Y)
            inside = (X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1)
            Z = np.where(inside, np.maximum(Z, zt), Z)
        return Z

    def rays(self, xy_photo) -> tuple[np.ndarray, np.ndarray]:
        """Projection centre (3,) and ray directions (N, 3) of photo mm points."""
        p = self.pair
        xy = np.asarray(xy_photo, float).reshape(-1, 2)
        v = np.column_stack([xy[:, 0] - p.x0[self.k], xy[:, 1] - p.y0[self.k],
                             np.full(len(xy), -p.c[self.k])])
        return p.X0[self.k], v @ p.M(self.k)

    def intersect(self, xy_photo) -> np.ndarray:
        """First surface point (N, 3) of the rays of photo mm points, object m."""
        C, r = self.rays(xy_photo)
        Xc, Yc, Z0, A, s = self.pair.hill
        t = (Z0 + 0.5 * A - C[2]) / r[:, 2]
        for _ in range(7):
            X = C[0] + t * r[:, 0]
            Y = C[1] + t * r[:, 1]
            e = A * np.exp(-((X - Xc) ** 2 + (Y - Yc) ** 2) / (2 * s * s))
            h = C[2] + t * r[:, 2] - (Z0 + e)
            dh = r[:, 2] + ((X - Xc) * r[:, 0] + (Y - Yc) * r[:, 1]) / (s * s) * e
            t = t - h / dh
        if self.box is not None:
            x0, x1, y0, y1, zt = self.box
            with np.errstate(divide="ignore", invalid="ignore"):
                tlo = np.full(len(t), -np.inf)
                thi = np.full(len(t), np.inf)
                for lo, hi, o, d in ((x0, x1, C[0], r[:, 0]), (y0, y1, C[1], r[:, 1]),
                                     (-1e9, zt, C[2], r[:, 2])):
                    a = (lo - o) / d
                    b = (hi - o) / d
                    tlo = np.maximum(tlo, np.minimum(a, b))
                    thi = np.minimum(thi, np.maximum(a, b))
            hit = (tlo <= thi) & (tlo > 0) & (tlo < t)
            t = np.where(hit, tlo, t)
        return C + t[:, None] * r

    def visible(self, XYZ, tol: float = 0.05) -> np.ndarray:
        """True where the object point (N, 3) is the first surface along this photo's ray."""
        XYZ = np.asarray(XYZ, float).reshape(-1, 3)
        P = self.intersect(self.pair.photo(self.k, XYZ))
        return np.linalg.norm(P - XYZ, axis=1) < tol

    # -- texture ----------------------------------------------------------------------

    def texture(self, XYZ) -> np.ndarray:
        """Reflectance (N,) of surface points (N, 3); walls take their texture by X+Z, Y+Z."""
        import cv2

        XYZ = np.asarray(XYZ, float).reshape(-1, 3)
        X, Y, Z = XYZ.T
        if self.box is not None:
            wall = np.abs(Z - self.surface(X, Y)) > 1e-3
            X = np.where(wall, X + Z, X)
            Y = np.where(wall, Y + Z, Y)
        n = len(X)
        w = 1024
        pad = (-n) % w
        mx = ((np.r_[X, np.zeros(pad)] - self.origin[0]) / self.pitch).reshape(-1, w)
        my = ((np.r_[Y, np.zeros(pad)] - self.origin[1]) / self.pitch).reshape(-1, w)
        f = cv2.remap(self._tex(), mx.astype(np.float32), my.astype(np.float32),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).ravel()[:n]
        if self.blank is not None:
            x0, x1, y0, y1 = self.blank
            f = np.where((XYZ[:, 0] >= x0) & (XYZ[:, 0] <= x1) & (XYZ[:, 1] >= y0)
                         & (XYZ[:, 1] <= y1), np.float32(0.5), f)
        return f

    def __call__(self, x_mm, y_mm):
        x = np.asarray(x_mm, float)
        shape = x.shape
        film = np.column_stack([x.ravel(), np.asarray(y_mm, float).ravel()])
        out = np.empty(len(film), np.float32)
        step = 1 << 18
        for i in range(0, len(film), step):
            P = self.intersect(self.io.film_to_photo(film[i:i + step]))
            out[i:i + step] = self.texture(P)
        return out.reshape(shape)


def rollei_pair(seed: int = 6006):
    """The Rollei 6006 pair of ``softplot demo`` (1:7500, B/H 0.56, hill of 60 m): truth."""
    from softplot.camera import load_camera
    from softplot.pipeline.demo import make_pair

    return make_pair(load_camera("rollei-6006"), seed)
