"""Mono measurement for model set-up: tie and control points pointed in each scan.

Points are kept per side (name -> pixel x, y; pixel system: x right = column, y down = row,
(0, 0) the centre of the top-left pixel) and written, after every change, as the ``name,x,y``
pixel CSVs that ``softplot correct points`` reads (and, reduced to photo mm, ``softplot
relor``): ``SESSION/measurements/left.pixels.csv`` and ``right.pixels.csv``.

:func:`refine_right` offers a sub-pixel position of a point in the right scan: least-squares
matching (shift and a linear radiometric change, Gauss-Newton on bilinearly resampled grey
values) of the left scan's patch around the left point, started from the operator's click
(after an integer normalised cross-correlation search nearby). It is a proposal: the page
asks the operator to accept it.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from softplot.errors import SoftplotError

__all__ = ["Measurements", "refine_right", "lsm_shift"]

FOLDER = "measurements"


class Measurements:
    """The points measured in a session's scans (see the module docstring)."""

    def __init__(self, session_folder: Path, sizes: dict):
        self.folder = Path(session_folder) / FOLDER
        self.sizes = sizes  # side -> (width, height) px
        self.points: dict[str, dict[str, tuple[float, float]]] = {"left": {}, "right": {}}
        from softplot.correction import read_points_csv

        for side in self.points:
            p = self.path(side)
            if p.is_file():
                names, xy = read_points_csv(p)
                self.points[side] = {n: (float(x), float(y)) for n, (x, y) in zip(names, xy,
                                                                                 strict=True)}

    def path(self, side: str) -> Path:
        return self.folder / f"{side}.pixels.csv"

    def set(self, side: str, name: str, x: float, y: float) -> None:
        """Record (or replace) point ``name`` at pixel (x, y) of the ``side`` scan."""
        if side not in self.points:
            raise SoftplotError(f"side must be left or right, got {side!r}")
        if not name or "," in name or len(name) > 40:
            raise SoftplotError("a point name is 1-40 characters without a comma")
        w, h = self.sizes[side]
        if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
            raise SoftplotError(f"({x:.1f}, {y:.1f}) lies outside the {side} scan")
        self.points[side][name] = (float(x), float(y))
        self._write(side)

    def delete(self, side: str, name: str) -> None:
        if self.points.get(side, {}).pop(name, None) is not None:
            self._write(side)

    def _write(self, side: str) -> None:
        self.folder.mkdir(exist_ok=True)
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["name", "x", "y"])
        for n, (x, y) in self.points[side].items():
            w.writerow([n, f"{x:.4f}", f"{y:.4f}"])
        p = self.path(side)
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(buf.getvalue())
        os.replace(tmp, p)

    def as_dict(self) -> dict:
        return {s: [[n, x, y] for n, (x, y) in pts.items()] for s, pts in self.points.items()}


def _patch(img: np.ndarray, x: float, y: float, half: int) -> np.ndarray:
    """Bilinear grey values on the (2 half + 1)^2 grid centred on pixel (x, y)."""
    jj, ii = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    return map_coordinates(img, [y + jj, x + ii], order=1, mode="nearest")


def lsm_shift(tmpl: np.ndarray, img: np.ndarray, x: float, y: float, *, iterations: int = 30,
              tol: float = 1e-4) -> tuple[float, float, float]:
    """Least-squares matching of ``tmpl`` ((2h+1)^2, centred) in ``img`` from (x, y) px.

    Model ``tmpl = r0 + r1 * img(p + (dx, dy))``; returns the matched centre (x, y) and the
    standard deviation of the shift, px (NaN when the patch has no texture).
    """
    half = tmpl.shape[0] // 2
    t = tmpl.astype(np.float64).ravel()
    r0, r1 = 0.0, 1.0
    sig = np.nan
    for _ in range(iterations):
        g = _patch(img, x, y, half + 1)
        gi = g[1:-1, 1:-1].ravel()
        gx = ((g[1:-1, 2:] - g[1:-1, :-2]) / 2).ravel()
        gy = ((g[2:, 1:-1] - g[:-2, 1:-1]) / 2).ravel()
        A = np.c_[r1 * gx, r1 * gy, np.ones_like(gi), gi]
        res = t - (r0 + r1 * gi)
        N = A.T @ A
        try:
            d = np.linalg.solve(N, A.T @ res)
        except np.linalg.LinAlgError:
            raise SoftplotError("no texture to match in this patch") from None
        x, y, r0, r1 = x + d[0], y + d[1], r0 + d[2], r1 + d[3]
        red = max(t.size - 4, 1)
        s0 = float(np.sqrt(((res - A @ d) ** 2).sum() / red))
        Ninv = np.linalg.inv(N)
        sig = s0 * float(np.sqrt(max(Ninv[0, 0], Ninv[1, 1])))
        if abs(d[0]) < tol and abs(d[1]) < tol:
            break
    return float(x), float(y), sig


def refine_right(left: np.ndarray, right: np.ndarray, lxy, rxy, *, half: int = 10,
                 search: int = 8) -> dict:
    """A sub-pixel proposal for the right point of a pair (see the module docstring).

    ``left``, ``right``: the scans' grey levels (level 0, pixel system); ``lxy`` the left
    point, ``rxy`` the operator's right point (px). Returns ``{"x", "y", "sigma", "ncc",
    "shift"}`` (the proposal, px).
    """
    lx, ly = map(float, lxy)
    rx, ry = map(float, rxy)
    tmpl = _patch(np.asarray(left, np.float32), lx, ly, half).astype(np.float32)
    if float(tmpl.std()) < 1e-6:
        raise SoftplotError("the left patch is uniform: nothing to match")
    x0, y0 = int(round(rx)), int(round(ry))
    r = half + search
    h, w = right.shape
    win = np.asarray(right[max(y0 - r, 0):y0 + r + 1, max(x0 - r, 0):x0 + r + 1], np.float32)
    if win.shape[0] < tmpl.shape[0] or win.shape[1] < tmpl.shape[1]:
        raise SoftplotError("the right point is too close to the scan's edge to match")
    cc = cv2.matchTemplate(win, tmpl, cv2.TM_CCOEFF_NORMED)
    _, best, _, (bx, by) = cv2.minMaxLoc(cc)
    sx = max(x0 - r, 0) + bx + half
    sy = max(y0 - r, 0) + by + half
    y_lo, y_hi = max(int(sy) - half - 4, 0), min(int(sy) + half + 5, h)
    x_lo, x_hi = max(int(sx) - half - 4, 0), min(int(sx) + half + 5, w)
    sub = np.asarray(right[y_lo:y_hi, x_lo:x_hi], np.float64)
    fx, fy, sig = lsm_shift(tmpl, sub, sx - x_lo, sy - y_lo)
    fx, fy = fx + x_lo, fy + y_lo
    if not (abs(fx - sx) < 2 and abs(fy - sy) < 2):
        raise SoftplotError("least-squares matching did not converge near the click")
    return {"x": fx, "y": fy, "sigma": sig, "ncc": float(best), "shift": [fx - rx, fy - ry]}
