"""Scene content of a synthetic photograph, defined in undeformed film mm.

The scene is a *scene factor* ``g(x, y)`` (dimensionless, 1 = nominal): the film's exposed
background in a positive is ``mark_level + contrast * g`` (see :mod:`softplot.synthetic.scan`),
so ``g`` scales the local contrast of a mark against its surroundings. Kinds:

* ``"none"``: g = 1 everywhere.
* ``"texture"``: smooth fractal texture, g in about [0.7, 1.3].
* ``"busy"``: texture plus sharp-edged content - blocks (buildings, fields), roads, discs,
  and cross-like features off the reseau grid - with g in [0.4, 1.6].
* a callable ``f(x_mm, y_mm) -> reflectance in [0, 1]`` (arrays of film mm in, same shape
  out): g = 0.5 + f, so reflectance 0.5 is the nominal background.

Rasters live on a grid in film mm and are sampled through per-pixel film coordinates with
``cv2.remap`` (bilinear), so the scene deforms with the film like everything exposed on it.
"""

from __future__ import annotations

import math
from typing import Callable

import cv2
import numpy as np

from softplot.errors import SoftplotError

SCENES = ("none", "texture", "busy")


def _fractal(
    shape: tuple[int, int], rng: np.random.Generator, octaves: tuple[int, ...]
) -> np.ndarray:
    """Zero-mean, unit-std fractal noise raster of ``shape`` (rows, cols), float32.

    Octave ``k`` has ``octaves[k]`` random cells across the longer side and weight 0.75^k;
    octaves are summed at a resolution of 8 px per cell of the finest one so far, and the
    sum is resized once to the full raster.
    """
    ny, nx = shape
    big = max(ny, nx)
    acc = None
    for k, cells in enumerate(octaves):
        cy = max(2, int(round(cells * ny / big))) + 3
        cx = max(2, int(round(cells * nx / big))) + 3
        grid = rng.standard_normal((cy, cx)).astype(np.float32)
        size = (min(nx, 8 * cx), min(ny, 8 * cy))  # (width, height) for OpenCV
        layer = cv2.resize(grid, size, interpolation=cv2.INTER_CUBIC)
        # soften the interpolation's grid-aligned ridges (about half a cell)
        sig = 0.5 * size[0] / cx
        layer = cv2.GaussianBlur(layer, (0, 0), sig) * np.float32(0.75**k)
        if acc is None:
            acc = layer
        else:
            if acc.shape[::-1] != size:
                acc = cv2.resize(acc, size, interpolation=cv2.INTER_LINEAR)
            acc += layer
    out = cv2.resize(acc, (nx, ny), interpolation=cv2.INTER_LINEAR) if acc.shape != shape else acc
    out -= out.mean()
    sd = float(out.std())
    return out / np.float32(sd if sd > 0 else 1.0)


class Scene:
    """A scene factor g over the film, sampled at per-pixel undeformed film mm.

    Parameters
    ----------
    kind : str or callable
        "none", "texture", "busy", or ``f(x_mm, y_mm) -> reflectance in [0, 1]``.
    extent_mm : (xmin, xmax, ymin, ymax)
        Film area (undeformed film mm) the raster must cover.
    px_per_mm : float
        Scan resolution; rasters are not finer than the scan.
    rng : numpy.random.Generator
        Source of the scene's content.
    rgb : bool
        Also make a per-channel tint (three slightly different colour factors).
    avoid_mm : ndarray, shape (M, 2), optional
        Film mm of the reseau/fiducial marks: cross-like scene features keep away from them.
    avoid_radius_mm : float
        Clearance around ``avoid_mm``.
    cross_mm : (float, float)
        Arm length and line width (film mm) of the cross-like scene features.
    """

    def __init__(
        self,
        kind: str | Callable,
        extent_mm: tuple[float, float, float, float],
        px_per_mm: float,
        rng: np.random.Generator,
        rgb: bool = False,
        avoid_mm: np.ndarray | None = None,
        avoid_radius_mm: float = 1.0,
        cross_mm: tuple[float, float] = (0.8, 0.04),
    ) -> None:
        if not callable(kind) and kind not in SCENES:
            raise SoftplotError(f"unknown scene {kind!r} (use {', '.join(SCENES)} or a function)")
        self.kind = kind
        self.rgb = rgb
        self.x0, x1, self.y0, y1 = extent_mm
        self.raster = None
        self.tint = None
        size = max(x1 - self.x0, y1 - self.y0)
        cap = 4096 if kind == "busy" else 2048
        self.pitch = max(size / cap, 1.0 / px_per_mm)
        if callable(kind) or kind == "none":
            return  # no raster; RGB stays neutral
        nx = int(math.ceil((x1 - self.x0) / self.pitch)) + 2
        ny = int(math.ceil((y1 - self.y0) / self.pitch)) + 2
        tex = _fractal((ny, nx), rng, (3, 6, 12, 24, 48, 96, 192))
        amp = 0.15 if kind == "texture" else 0.22
        g = 1.0 + np.float32(amp) * tex
        if kind == "busy":
            g = self._busy(g, rng, avoid_mm, avoid_radius_mm, cross_mm)
        lo, hi = (0.7, 1.3) if kind == "texture" else (0.4, 1.6)
        self.raster = np.clip(g, lo, hi).astype(np.float32)
        if rgb:
            small = (max(8, ny // 8), max(8, nx // 8))
            self.tint = [
                cv2.resize(
                    (1.0 + 0.06 * _fractal(small, rng, (2, 4, 8))).astype(np.float32),
                    (nx, ny),
                    interpolation=cv2.INTER_LINEAR,
                )
                for _ in range(3)
            ]

    # -- content ---------------------------------------------------------------------------

    def _to_raster(self, xy_mm: np.ndarray) -> np.ndarray:
        """Raster (col, row) coordinates of film mm points (film y up, raster rows down)."""
        xy = np.asarray(xy_mm, float)
        return np.column_stack(
            [(xy[:, 0] - self.x0) / self.pitch, (xy[:, 1] - self.y0) / self.pitch]
        )

    def _busy(self, g, rng, avoid_mm, avoid_radius_mm, cross_mm):
        ny, nx = g.shape
        w_mm, h_mm = nx * self.pitch, ny * self.pitch
        area = w_mm * h_mm
        scale = math.sqrt(area) / 56.0  # feature sizes relative to a 56 mm frame
        shift = 4
        one = 1 << shift

        def fix(pts_mm: np.ndarray) -> np.ndarray:
            return np.round(self._to_raster(pts_mm) * one).astype(np.int32)

        def rand_xy(n: int) -> np.ndarray:
            return np.column_stack(
                [rng.uniform(self.x0, self.x0 + w_mm, n), rng.uniform(self.y0, self.y0 + h_mm, n)]
            )

        # blocks: rotated rectangles
        n_blocks = 200
        centres = rand_xy(n_blocks)
        for (cx, cy), sz, ang, val in zip(
            centres,
            rng.uniform(0.3, 4.0, (n_blocks, 2)) * scale,
            rng.uniform(0, math.pi, n_blocks),
            rng.uniform(0.4, 1.6, n_blocks), strict=False,
        ):
            c, s = math.cos(ang), math.sin(ang)
            hw, hh = sz / 2
            corners = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]]) @ np.array(
                [[c, s], [-s, c]]
            ) + (cx, cy)
            cv2.fillPoly(g, [fix(corners)], float(val), cv2.LINE_8, shift)
        # roads: polylines
        n_roads = 25
        for _ in range(n_roads):
            steps = rng.integers(3, 8)
            start = rand_xy(1)[0]
            heading = rng.uniform(0, 2 * math.pi)
            pts = [start]
            for _ in range(steps):
                heading += rng.normal(0, 0.4)
                length = rng.uniform(3, 12) * scale
                pts.append(pts[-1] + length * np.array([math.cos(heading), math.sin(heading)]))
            width = max(1, int(round(rng.uniform(0.08, 0.5) * scale / self.pitch)))
            val = float(rng.choice([0.45, 1.55]))
            cv2.polylines(g, [fix(np.array(pts))], False, val, width, cv2.LINE_8, shift)
        # discs (trees, tanks)
        n_discs = 80
        radii = rng.uniform(0.05, 0.6, n_discs) * scale
        for (cx, cy), r, val in zip(
            rand_xy(n_discs), radii, rng.uniform(0.4, 1.6, n_discs), strict=True
        ):
            ctr = fix(np.array([[cx, cy]]))[0]
            cv2.circle(g, (int(ctr[0]), int(ctr[1])), int(r / self.pitch * one), float(val), -1,
                       cv2.LINE_8, shift)
        # cross-like features off the grid, the size of the reseau crosses
        arm, lw = cross_mm
        cand = rand_xy(200)
        if avoid_mm is not None and len(avoid_mm):
            dx = cand[:, None, 0] - avoid_mm[None, :, 0]
            dy = cand[:, None, 1] - avoid_mm[None, :, 1]
            d = np.min(np.hypot(dx, dy), axis=1)
            cand = cand[d > avoid_radius_mm]
        width = max(1, int(round(lw / self.pitch)))
        for (cx, cy), val in zip(cand[:30], rng.choice([0.4, 1.6], 30), strict=False):
            for dx, dy in ((arm / 2, 0.0), (0.0, arm / 2)):
                seg = fix(np.array([[cx - dx, cy - dy], [cx + dx, cy + dy]]))
                cv2.line(g, tuple(int(v) for v in seg[0]), tuple(int(v) for v in seg[1]),
                         float(val), width, cv2.LINE_8, shift)
        return g

    # -- sampling --------------------------------------------------------------------------

    def sample(self, ux: np.ndarray, uy: np.ndarray) -> np.ndarray:
        """Scene factor at undeformed film mm ``ux``, ``uy`` (arrays (h, w)).

        Returns
        -------
        ndarray, float32
            Shape (h, w), or (h, w, 3) when the scene was made with ``rgb=True``.
        """
        if callable(self.kind):
            g = 0.5 + np.asarray(self.kind(ux.astype(float), uy.astype(float)), np.float32)
            g = np.broadcast_to(g, ux.shape).astype(np.float32)
        elif self.raster is None:
            g = np.ones(ux.shape, np.float32)
        else:
            mx = ((ux - self.x0) / self.pitch).astype(np.float32)
            my = ((uy - self.y0) / self.pitch).astype(np.float32)
            g = cv2.remap(self.raster, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if not self.rgb:
            return g
        if self.tint is None:
            return np.repeat(g[..., None], 3, axis=2)
        mx = ((ux - self.x0) / self.pitch).astype(np.float32)
        my = ((uy - self.y0) / self.pitch).astype(np.float32)
        layers = [
            g * cv2.remap(t, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            for t in self.tint
        ]
        return np.stack(layers, axis=2)

    def sample_points(self, xy_mm: np.ndarray) -> np.ndarray:
        """Grey scene factor (N,) at film mm points (N, 2)."""
        xy = np.asarray(xy_mm, float).reshape(-1, 2)
        g = self.sample(xy[:, 0:1].astype(np.float32), xy[:, 1:2].astype(np.float32))
        g = np.asarray(g, np.float32)
        if g.ndim == 3:
            g = g.mean(axis=2)
        return g[:, 0]
