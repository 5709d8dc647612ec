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

__all__ = ["SyntheticPair", "aerial_pair"]


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
