"""Stage 4 of the reseau path: the prediction of every cross of the certificate.

:func:`predict` maps every cross's film position through the lattice's projective model, adds
the interpolated residuals of the crosses the lattice found (:func:`idw`), searches the NCC
map near each prediction for a start position, and gives the pixel -> mark-frame affine each
cross's fit starts from. :meth:`Prediction.inside` tells, once the marks' size is known, which
crosses lie whole inside the scan (the others are cut and never fitted). The hand-over is
:class:`Prediction`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from softplot.marks import coarse, grid
from softplot.marks.candidates import search_map
from softplot.marks.lattice import Lattice
from softplot.marks.template import MarkShape

__all__ = ["Prediction", "predict", "idw"]


@dataclass
class Prediction:
    """Where every cross of the certificate is expected (hand-over of :func:`predict`).

    Attributes
    ----------
    film : (N, 2) ndarray
        The crosses' nominal positions, film system mm (row-major, as
        :meth:`softplot.camera.Reseau.film`).
    xy : (N, 2) ndarray
        Predicted positions, full-resolution pixel system: the lattice's model plus the
        interpolated residuals of the crosses it found.
    start : (N, 2) ndarray
        Start positions of the fits, pixel system: the NCC map's best position near the
        prediction where it correlates (``found``), else the prediction.
    ncc : (N,) ndarray
        The correlation at ``start`` (times the polarity's sign; -inf where none).
    found : (N,) bool
        Crosses the NCC map confirms near their prediction (correlation >= 0.3).
    A : (N, 2, 2) ndarray
        Each cross's pixel -> mark-frame affine from the model (mark frame: u along film x,
        v along film -y, nominal px).
    J : (N, 2, 2) ndarray
        The model's Jacobian d pixel / d film mm at each cross.
    H : (3, 3) ndarray
        The lattice's projective model, film mm -> pixel.
    sign : int
        The crosses' polarity (+1 bright, -1 dark).
    px_per_mm : float
        Full-resolution pixels per film mm.
    max_shift : float
        How far (px) a fit may move from its prediction: the local search's radius and a pixel.
    init_err : float
        The start positions' expected error (px, from the overview's reduction).
    s0 : float
        The starting blur sigma of the fits (px).
    """

    film: np.ndarray
    xy: np.ndarray
    start: np.ndarray
    ncc: np.ndarray
    found: np.ndarray
    A: np.ndarray
    J: np.ndarray
    H: np.ndarray
    sign: int
    px_per_mm: float
    max_shift: float
    init_err: float
    s0: float

    def shifted(self, offset) -> "Prediction":
        """The same prediction with every cross (``xy`` and ``start``) moved by ``offset``
        (mark frame px, u and v: each cross's own affine turns it into pixels)."""
        d = np.einsum("nij,j->ni", np.linalg.inv(self.A), np.asarray(offset, float))
        return replace(self, xy=self.xy + d, start=self.start + d)

    def inside(self, shape: MarkShape, width: int, height: int):
        """Which crosses of size ``shape`` (px) lie whole inside a scan of ``width`` x
        ``height`` px (N,) bool, and which have their centre on it (N,) bool."""
        pred, Jh, ppm = self.xy, self.J, self.px_per_mm
        ext = 0.5 * shape.length + 0.5 * shape.width
        tips = np.stack([pred + ext * Jh[:, :, 0] / ppm * sgn for sgn in (1, -1)]
                        + [pred + ext * Jh[:, :, 1] / ppm * sgn for sgn in (1, -1)], 1)
        tips = np.concatenate([tips, pred[:, None, :] + 0.0], 1)
        inside = ((tips[..., 0] >= 0.5) & (tips[..., 0] <= width - 1.5)
                  & (tips[..., 1] >= 0.5) & (tips[..., 1] <= height - 1.5)).all(1)
        on_img = ((pred[:, 0] >= 0) & (pred[:, 0] <= width - 1)
                  & (pred[:, 1] >= 0) & (pred[:, 1] <= height - 1))
        return inside, on_img


def predict(lat: Lattice, film: np.ndarray, px_per_mm: float, blur_px: float) -> Prediction:
    """The prediction of every cross (``film`` (N, 2) mm) from the lattice ``lat``;
    ``blur_px`` the expected blur sigma (px)."""
    g, f, sign, ppm = lat.grid, lat.factor, lat.sign, px_per_mm
    pred = grid.apply_h(g.H, film)
    cand_xy = lat.assigned_xy()
    resid = cand_xy - grid.apply_h(g.H, film[g.node])
    pred = pred + idw(film, film[g.node], resid)
    # local search in the NCC map around each prediction
    spread = float(np.sqrt(np.mean(np.sum(resid**2, 1)))) if len(resid) else 3.0
    radius_ov = max(2.0, (2.0 * spread + 2.0) / f)
    found_ov, val = search_map(lat.ncc, lat.half, sign, coarse.full_to_ov(pred, f), radius_ov)
    use = np.isfinite(found_ov).all(1) & (val >= 0.3)
    c0 = np.where(use[:, None], coarse.ov_to_full(found_ov, f), pred)
    # affine of every cross: pixel -> mark frame (u along film x, v along film -y, nominal px)
    Jh = grid.h_jacobian(g.H, film)  # d pixel / d film mm
    A0 = np.linalg.inv(Jh @ np.diag([1.0 / ppm, -1.0 / ppm]))
    return Prediction(film=film, xy=pred, start=c0, ncc=val, found=use, A=A0, J=Jh, H=g.H,
                      sign=sign, px_per_mm=ppm, max_shift=radius_ov * f + 1.0,
                      init_err=max(0.75, 0.5 * f + 0.25),
                      s0=float(np.hypot(blur_px, np.sqrt(1.0 / 12.0))))


def idw(film_all, film_known, val_known, k=4):
    """Inverse-distance interpolation of residual vectors at film points (mm)."""
    if len(film_known) == 0:
        return np.zeros((len(film_all), 2))
    k = min(k, len(film_known))
    d, j = cKDTree(film_known).query(film_all, k=k)
    d = d.reshape(len(film_all), k)
    j = j.reshape(len(film_all), k)
    w = 1.0 / np.maximum(d, 1e-6) ** 2
    return (val_known[j] * w[..., None]).sum(1) / w.sum(1)[:, None]
