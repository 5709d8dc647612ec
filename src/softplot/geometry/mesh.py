"""Mesh models of film deformation: one plane transform per mesh of the reseau grid.

The reseau crosses form a topologically regular grid of ``rows x cols`` nodes, each with its
calibrated **film** position (mm, from the certificate) and its measured **pixel** position
(px). The grid cells are the ``(rows-1) x (cols-1)`` quadrilaterals between four neighbouring
crosses; cell ``k = r * (cols - 1) + c`` has the corners ``TL = (r, c)``, ``TR = (r, c+1)``,
``BR = (r+1, c+1)``, ``BL = (r+1, c)`` (row 0 on top).

Three mesh kinds (``docs/correction.md``):

``mesh-homography``
    one homography per quadrilateral, mapping its four pixel corners exactly onto its four
    film corners (STEREOBIT/RESEAU for the 121-cross Rollei: 100 quads).
``mesh-affine``
    every quadrilateral is split by one diagonal into two triangles with one affine each (the
    RESEAU/PENTAX package: 3 x 3 crosses -> 8 triangles). The diagonal runs through the corner
    of the quad nearest the grid centre ("union jack"): with ``rc = (rows-2)/2``,
    ``cc = (cols-2)/2`` the quad (r, c) takes TL-BR ("\\") when ``(r-rc)(c-cc) >= 0`` and
    TR-BL ("/") otherwise, so on the Pentax grid all eight triangles meet in the central cross.
``mesh-bilinear``
    per quadrilateral, bilinear interpolation between its four corners (Robson's/Ziemann's
    local bilinear): pixel and film both run bilinearly over the cell parameters (s, t) in the
    unit square; where the film cell is a rectangle this is exactly
    ``px = a0 + a1 x + a2 y + a3 x y`` of the film coordinates. Continuous across cell edges.

All three are written in the same *isoparametric* form: each cell maps its pixel quad and its
film quad onto the unit square ``(s, t)`` (s along the columns, t down the rows) with a map of
its kind, and a point goes ``pixel -> (cell, s, t) -> film`` (or back). For the homography and
the triangles this composition *is* the per-mesh homography / affine of the paper. The
partition is conforming in both planes, the correction continuous, and the round trip exact
to rounding.

Point location is vectorised: the inverse of one global homography (plane -> fractional grid
coordinates, least squares over all crosses) predicts the cell, the cell test (0 <= s, t <= 1)
confirms it or moves the point to the neighbour in the direction of the violation, repeated
for the few points that moved. Points outside the reseau end in the nearest border cell, are
transformed by its (extrapolated) map and flagged :data:`FLAG_OUTSIDE_RESEAU`.

Missing crosses (not measured; NaN pixel position): the meshes around a missing cross are
merged with their neighbours into one transform of the mesh's kind (projective for
homography meshes, affine for triangles, bilinear for bilinear), fitted by least squares to
the measured crosses of the block around it (the 3 x 3 block, grown to 5 x 5, 7 x 7 ... until
it holds enough measured crosses in a non-degenerate layout); that block transform gives the
missing node its pixel position, after which the cells are formed as usual, so the
correction stays continuous and the round trip exact. :attr:`MeshModel.filled` reports each
such merge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.transforms import (
    MIN_POINTS,
    Conditioning,
    _bilinear_inverse,
    fit_transform,
)

__all__ = [
    "MESH_KINDS",
    "FLAG_OK",
    "FLAG_OUTSIDE_RESEAU",
    "FLAG_OUTSIDE_IMAGE",
    "FLAG_NAMES",
    "MeshModel",
    "FilledCross",
    "default_mesh_kind",
]

MESH_KINDS = ("mesh-affine", "mesh-homography", "mesh-bilinear")

#: flags of corrected points
FLAG_OK = 0
FLAG_OUTSIDE_RESEAU = 1
FLAG_OUTSIDE_IMAGE = 2
FLAG_NAMES = {
    FLAG_OK: "ok",
    FLAG_OUTSIDE_RESEAU: "outside-reseau",
    FLAG_OUTSIDE_IMAGE: "outside-image",
}

#: transform fitted over a block of crosses to merge the meshes around a missing cross
_FILL_KIND = {"mesh-affine": "affine", "mesh-homography": "projective", "mesh-bilinear": "bilinear"}

_EPS = 1e-9  # cell-test tolerance in (s, t) units: no ping-pong on shared edges


def default_mesh_kind(rows: int, cols: int) -> str:
    """The camera's default mesh: triangles with affines for a 3 x 3 grid, else homographies."""
    return "mesh-affine" if (rows, cols) == (3, 3) else "mesh-homography"


@dataclass(frozen=True)
class FilledCross:
    """A missing cross whose meshes were merged: its grid place, the block and the fit.

    ``pixel`` is the position the block transform gives it (px); ``block`` the half-size of
    the square block of crosses used (1 = 3 x 3); ``n_used`` the measured crosses in it;
    ``sigma0_px`` the block fit's sigma0 (NaN when exactly determined).
    """

    row: int
    col: int
    pixel: tuple[float, float]
    kind: str
    block: int
    n_used: int
    sigma0_px: float


# ---------------------------------------------------------------------------------------------
# per-kind cell maps in one plane


def _square_to_quad(P: np.ndarray) -> np.ndarray:
    """(K, 3, 3) homographies unit square -> quads; P (K, 4, 2) corners TL, TR, BR, BL.

    (s, t) = (0, 0), (1, 0), (1, 1), (0, 1) go to TL, TR, BR, BL (Heckbert's closed form).
    """
    x0, x1, x2, x3 = (P[:, i, 0] for i in range(4))
    y0, y1, y2, y3 = (P[:, i, 1] for i in range(4))
    sx = x0 - x1 + x2 - x3
    sy = y0 - y1 + y2 - y3
    dx1, dx2 = x1 - x2, x3 - x2
    dy1, dy2 = y1 - y2, y3 - y2
    det = dx1 * dy2 - dx2 * dy1
    with np.errstate(divide="ignore", invalid="ignore"):
        g = (sx * dy2 - dx2 * sy) / det
        h = (dx1 * sy - sx * dy1) / det
    H = np.empty((P.shape[0], 3, 3))
    H[:, 0, 0] = x1 - x0 + g * x1
    H[:, 0, 1] = x3 - x0 + h * x3
    H[:, 0, 2] = x0
    H[:, 1, 0] = y1 - y0 + g * y1
    H[:, 1, 1] = y3 - y0 + h * y3
    H[:, 1, 2] = y0
    H[:, 2, 0] = g
    H[:, 2, 1] = h
    H[:, 2, 2] = 1.0
    return H


def _triangle_affines(P: np.ndarray, backslash: np.ndarray) -> np.ndarray:
    """(K, 2, 6) affines (s, t) -> plane of triangles A and B of each quad.

    Affine parameters (a, b, c, d, e, f): X = a s + b t + c, Y = d s + e t + f.
    "\\" quads: A = {TL, TR, BR} (t <= s), B = {TL, BR, BL}; "/" quads: A = {TL, TR, BL}
    (s + t <= 1), B = {TR, BR, BL}.
    """
    TL, TR, BR, BL = (P[:, i] for i in range(4))
    bs = backslash[:, None]
    # triangle A: "\": X = TL + s (TR - TL) + t (BR - TR); "/": X = TL + s (TR - TL) + t (BL - TL)
    uA = TR - TL
    vA = np.where(bs, BR - TR, BL - TL)
    pA = TL
    # triangle B: "\": X = TL + s (BR - BL) + t (BL - TL); "/": X = TR - BR + BL + s (BR - BL)
    #             + t (BR - TR)
    uB = BR - BL
    vB = np.where(bs, BL - TL, BR - TR)
    pB = np.where(bs, TL, TR - BR + BL)
    out = np.empty((P.shape[0], 2, 6))
    for j, (u, v, p) in enumerate(((uA, vA, pA), (uB, vB, pB))):
        out[:, j] = np.stack([u[:, 0], v[:, 0], p[:, 0], u[:, 1], v[:, 1], p[:, 1]], axis=-1)
    return out


def _invert_affines(A: np.ndarray) -> np.ndarray:
    """Invert (..., 6) affine parameter sets."""
    a, b, c, d, e, f = (A[..., i] for i in range(6))
    det = a * e - b * d
    ia, ib, id_, ie = e / det, -b / det, -d / det, a / det
    return np.stack([ia, ib, -(ia * c + ib * f), id_, ie, -(id_ * c + ie * f)], axis=-1)


_CHUNK = 32768  # points per chunk of the vectorised path (cache-sized temporaries)
_POOLS: dict = {}


def _pool(threads):
    """A shared thread pool (``threads`` workers; default the CPU count, at most 8)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    n = int(threads) if threads else min(os.cpu_count() or 1, 8)
    if n <= 1:
        return None
    if n not in _POOLS:
        _POOLS[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="softplot-mesh")
    return _POOLS[n]


def _rows(a: np.ndarray) -> list[np.ndarray]:
    """Contiguous rows of a (m, K) coefficient table (for np.take)."""
    return [np.ascontiguousarray(r) for r in a]


class _Plane:
    """The cells of one plane (pixel or film), tables in the plane's own (raw) units.

    Cell maps: ``to_local`` plane -> (s, t) and ``from_local`` (s, t) -> plane. Coefficient
    tables are stored per coefficient (m, K) so that a chunk of points gathers them with
    :func:`numpy.take`. Homographies and affines take raw plane coordinates (the conditioning
    is folded into the tables: with cells a few hundred pixels wide the rounding stays below
    1e-12 of a cell); the bilinear inverse runs in conditioned coordinates.
    """

    def __init__(self, nodes: np.ndarray, kind: str, backslash: np.ndarray) -> None:
        rows, cols = nodes.shape[:2]
        self.rows, self.cols = rows, cols
        self.kind = kind
        flat = nodes.reshape(-1, 2)
        self.cond = cond = Conditioning.of(flat)
        self.eps_len = _EPS * cond.scale  # tolerance of edge tests in plane units
        S = cond.matrix()
        U = np.linalg.inv(S)
        # global locator: plane -> fractional grid coordinates (col, row), affine least squares
        r, c = np.mgrid[0:rows, 0:cols]
        grid = np.column_stack([c.ravel(), r.ravel()]).astype(float)
        A = np.column_stack([cond.apply(flat), np.ones(len(flat))])
        sol = np.linalg.lstsq(A, grid, rcond=None)[0]  # conditioned plane -> (col, row)
        M = sol.T @ S  # raw plane -> (col, row)
        self.locator = tuple(float(v) for v in M.ravel())
        nc = cond.apply(flat).reshape(rows, cols, 2)
        P = np.stack([nc[:-1, :-1], nc[:-1, 1:], nc[1:, 1:], nc[1:, :-1]], axis=2)
        P = P.reshape(-1, 4, 2)  # conditioned corners TL, TR, BR, BL of every quad
        self.K = P.shape[0]
        if kind == "mesh-homography":
            Hf = _square_to_quad(P)  # (s, t) -> conditioned
            Ht = np.linalg.inv(Hf)  # conditioned -> (s, t)
            self.from_raw = U[None] @ Hf  # (s, t) -> raw
            self.to_raw = Ht @ S[None]  # raw -> (s, t)
            self.from_raw /= self.from_raw[:, 2:3, 2:3]
            self.to_raw /= self.to_raw[:, 2:3, 2:3]
            # normalised (h33 = 1): 8 coefficients per cell
            self.to_T = _rows(self.to_raw.reshape(-1, 9).T[:8])
            self.from_T = _rows(self.from_raw.reshape(-1, 9).T[:8])
        elif kind not in ("mesh-bilinear", "mesh-affine"):  # pragma: no cover
            raise SoftplotError(f"unknown mesh kind {kind!r}")
        if kind in ("mesh-bilinear", "mesh-affine"):
            # bilinear cells (mesh-bilinear; mesh-affine extrapolates outside the reseau with
            # them: on a boundary edge they coincide with the border triangle's affine)
            TL, TR, BR, BL = (P[:, i] for i in range(4))
            a0, a1, a2, a3 = TL, TR - TL, BL - TL, TL - TR + BR - BL
            # order of transforms' bilinear: a0 a1 a2 a3 b0 b1 b2 b3 (conditioned plane)
            self.bil = np.stack(
                [a0[:, 0], a1[:, 0], a2[:, 0], a3[:, 0], a0[:, 1], a1[:, 1], a2[:, 1], a3[:, 1]],
                axis=-1,
            )
            raw = self.bil * cond.scale
            raw[:, 0] += cond.centre[0]
            raw[:, 4] += cond.centre[1]
            self.bil_raw = raw
            self.bil_T = _rows(self.bil.T)
            self.bil_raw_T = _rows(raw.T)
        if kind == "mesh-affine":
            # triangle affines (s, t) -> conditioned, then raw both ways
            tf = _triangle_affines(P, backslash)  # (K, 2, 6)
            sc, (cx, cy) = cond.scale, cond.centre
            raw = tf * sc
            raw[..., 2] += cx
            raw[..., 5] += cy
            self.tri_from = raw
            self.tri_to = _invert_affines(raw)
            self.tri_from_T = [_rows(self.tri_from[:, j].T) for j in range(2)]
            self.tri_to_T = [_rows(self.tri_to[:, j].T) for j in range(2)]
            # half-plane d(s, t) = alpha s + beta t + gamma > 0 selects triangle B
            self.side = np.where(
                backslash[:, None], np.array([-1.0, 1.0, 0.0]), np.array([1.0, 1.0, -1.0])
            )
            self.side_T = _rows(self.side.T)
            # cell edges as unit-normal lines in raw coordinates, oriented so that a positive
            # value means towards increasing row (h) or column (v): one line per shared edge,
            # so neighbouring cells take bit-identical decisions
            self.hedge = _edge_lines(nodes[:, :-1], nodes[:, 1:], nodes[1:2, 0])
            self.vedge = _edge_lines(nodes[:-1, :], nodes[1:, :], nodes[0:1, 1])
        self._py = None

    # -- vectorised ----------------------------------------------------------------------------

    def predict(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell row and column predicted by the global locator (clamped to the grid)."""
        a, b, c, d, e, f = self.locator
        u = a * x + b * y + c
        v = d * x + e * y + f
        np.clip(u, 0.0, self.cols - 1 - 1e-9, out=u)
        np.clip(v, 0.0, self.rows - 1 - 1e-9, out=v)
        return v.astype(np.intp), u.astype(np.intp)

    def to_local(self, k: np.ndarray, x: np.ndarray, y: np.ndarray):
        """Cell parameters (s, t) and triangle index of raw points (x, y) in cells k."""
        if self.kind == "mesh-homography":
            h = [np.take(r, k) for r in self.to_T]
            w = h[6] * x + h[7] * y + 1.0
            s = (h[0] * x + h[1] * y + h[2]) / w
            t = (h[3] * x + h[4] * y + h[5]) / w
            return s, t, None
        if self.kind == "mesh-bilinear":
            s, t = self.bil_to_local(k, x, y)
            return s, t, None
        A = [np.take(r, k) for r in self.tri_to_T[0]]
        s = A[0] * x + A[1] * y + A[2]
        t = A[3] * x + A[4] * y + A[5]
        sd = [np.take(r, k) for r in self.side_T]
        inB = sd[0] * s + sd[1] * t + sd[2] > 0
        tri = inB.astype(np.int8)
        if inB.any():
            kb = k[inB]
            B = [np.take(r, kb) for r in self.tri_to_T[1]]
            xb, yb = x[inB], y[inB]
            s[inB] = B[0] * xb + B[1] * yb + B[2]
            t[inB] = B[3] * xb + B[4] * yb + B[5]
        return s, t, tri

    def bil_to_local(self, k: np.ndarray, x: np.ndarray, y: np.ndarray):
        """Bilinear cell parameters (s, t) of raw points in cells k (closed form + Newton)."""
        cx, cy = self.cond.centre
        inv = 1.0 / self.cond.scale
        xc = (x - cx) * inv
        yc = (y - cy) * inv
        th = [np.take(r, k) for r in self.bil_T]
        st = _bilinear_inverse(th, xc, yc)
        s, t = st[:, 0], st[:, 1]
        a0, a1, a2, a3, b0, b1, b2, b3 = th
        fx = a0 + a1 * s + a2 * t + a3 * s * t - xc
        fy = b0 + b1 * s + b2 * t + b3 * s * t - yc
        j00, j01 = a1 + a3 * t, a2 + a3 * s
        j10, j11 = b1 + b3 * t, b2 + b3 * s
        det = j00 * j11 - j01 * j10
        return s - (j11 * fx - j01 * fy) / det, t - (-j10 * fx + j00 * fy) / det

    def bil_from_local(self, k: np.ndarray, s: np.ndarray, t: np.ndarray):
        b = [np.take(r, k) for r in self.bil_raw_T]
        st = s * t
        return b[0] + b[1] * s + b[2] * t + b[3] * st, b[4] + b[5] * s + b[6] * t + b[7] * st

    def from_local(self, k: np.ndarray, s: np.ndarray, t: np.ndarray, tri):
        """Raw plane coordinates X, Y of cell parameters (s, t) in cells k."""
        if self.kind == "mesh-homography":
            h = [np.take(r, k) for r in self.from_T]
            w = h[6] * s + h[7] * t + 1.0
            return (h[0] * s + h[1] * t + h[2]) / w, (h[3] * s + h[4] * t + h[5]) / w
        if self.kind == "mesh-bilinear":
            return self.bil_from_local(k, s, t)
        A = [np.take(r, k) for r in self.tri_from_T[0]]
        X = A[0] * s + A[1] * t + A[2]
        Y = A[3] * s + A[4] * t + A[5]
        inB = tri == 1
        if inB.any():
            kb = k[inB]
            B = [np.take(r, kb) for r in self.tri_from_T[1]]
            sb, tb = s[inB], t[inB]
            X[inB] = B[0] * sb + B[1] * tb + B[2]
            Y[inB] = B[3] * sb + B[4] * tb + B[5]
        ext = tri == 2
        if ext.any():
            X[ext], Y[ext] = self.bil_from_local(k[ext], s[ext], t[ext])
        return X, Y

    def moves(self, ri, ci, x, y, s, t):
        """Steps (dr, dc) in -1, 0, 1 towards the cell that holds each point."""
        if self.kind != "mesh-affine":
            dc = (s > 1 + _EPS).astype(np.intp) - (s < -_EPS)
            dr = (t > 1 + _EPS).astype(np.intp) - (t < -_EPS)
            return dr, dc
        e = self.eps_len
        top = _line_value(self.hedge, ri, ci, x, y)
        bottom = _line_value(self.hedge, ri + 1, ci, x, y)
        left = _line_value(self.vedge, ri, ci, x, y)
        right = _line_value(self.vedge, ri, ci + 1, x, y)
        dr = (bottom > e).astype(np.intp) - (top < -e)
        dc = (right > e).astype(np.intp) - (left < -e)
        return dr, dc

    def locate(self, x: np.ndarray, y: np.ndarray):
        """Cells of raw points: k, s, t, tri, inside (bool). Iterates the cell test."""
        n = x.shape[0]
        nqc = self.cols - 1
        ri, ci = self.predict(x, y)
        k = ri * nqc + ci
        s, t, tri = self.to_local(k, x, y)
        if tri is None:
            tri = np.zeros(n, np.int8)
        if self.kind == "mesh-affine":
            cand = np.arange(n)
        else:
            # fast screen: points certainly inside their cell need no move test
            cand = np.flatnonzero(
                (np.abs(s - 0.5) > 0.5 + _EPS) | (np.abs(t - 0.5) > 0.5 + _EPS)
            )
        inside = np.ones(n, bool)
        for _ in range(self.rows + self.cols):
            if cand.size == 0:
                break
            rr, cc = ri[cand], ci[cand]
            dr, dc = self.moves(rr, cc, x[cand], y[cand], s[cand], t[cand])
            nr_ = np.clip(rr + dr, 0, self.rows - 2)
            nc_ = np.clip(cc + dc, 0, self.cols - 2)
            moved = (nc_ != cc) | (nr_ != rr)
            # points that would move but are clamped: outside the reseau
            inside[cand] = (dr == 0) & (dc == 0)
            sel = cand[moved]
            if sel.size == 0:
                break
            ci[sel] = nc_[moved]
            ri[sel] = nr_[moved]
            k[sel] = ri[sel] * nqc + ci[sel]
            s2, t2, tri2 = self.to_local(k[sel], x[sel], y[sel])
            s[sel] = s2
            t[sel] = t2
            if tri2 is not None:
                tri[sel] = tri2
            cand = sel
        if self.kind == "mesh-affine" and not inside.all():
            # outside the reseau: bilinear extrapolation of the border quad (tri code 2)
            out = np.flatnonzero(~inside)
            s[out], t[out] = self.bil_to_local(k[out], x[out], y[out])
            tri[out] = 2
        return k, s, t, tri, inside

    def map_chunk(self, other: "_Plane", x: np.ndarray, y: np.ndarray, post=None, bounds=None):
        """Map one chunk of raw points (contiguous x, y) into ``other``: X, Y, flags."""
        bad = ~np.isfinite(x + y)
        anybad = bool(bad.any())
        if anybad:
            x = np.where(bad, self.cond.centre[0], x)
            y = np.where(bad, self.cond.centre[1], y)
        k, s, t, tri, ins = self.locate(x, y)
        X, Y = other.from_local(k, s, t, tri)
        if post is not None:
            X, Y = post(X, Y)
        flags = (~ins).view(np.uint8)  # FLAG_OK 0, FLAG_OUTSIDE_RESEAU 1
        if bounds is not None:
            x0, x1, y0, y1 = bounds
            off = (x < x0) | (x > x1) | (y < y0) | (y > y1)
            flags = np.where(off, np.uint8(FLAG_OUTSIDE_IMAGE), flags)
        if anybad:
            X = np.where(bad, np.nan, X)
            Y = np.where(bad, np.nan, Y)
        return X, Y, flags

    def map_to(self, other: "_Plane", xy: np.ndarray, post=None, bounds=None, threads=None):
        """Map raw points (N, 2) of this plane into ``other``: (N, 2) and flags (N,) uint8.

        Works in chunks of :data:`_CHUNK` points (cache-sized temporaries), on a thread pool
        when there are many (NumPy releases the GIL). ``post(X, Y) -> (X2, Y2)``, if given,
        is applied per chunk (e.g. the interior orientation); ``bounds`` = (x0, x1, y0, y1)
        of this plane flags points outside it :data:`FLAG_OUTSIDE_IMAGE`. Non-finite points
        give NaN.
        """
        n = xy.shape[0]
        out = np.empty((n, 2))
        flags = np.empty(n, np.uint8)

        def run(a: int) -> None:
            b = min(a + _CHUNK, n)
            x = np.ascontiguousarray(xy[a:b, 0])
            y = np.ascontiguousarray(xy[a:b, 1])
            X, Y, f = self.map_chunk(other, x, y, post, bounds)
            out[a:b, 0] = X
            out[a:b, 1] = Y
            flags[a:b] = f

        starts = range(0, n, _CHUNK)
        pool = _pool(threads) if n > 4 * _CHUNK else None
        if pool is None:
            for a in starts:
                run(a)
        else:
            list(pool.map(run, starts))
        return out, flags

    # -- single point (plain Python floats) ---------------------------------------------------

    def _prepare_py(self) -> None:
        d = {"loc": self.locator}
        if self.kind == "mesh-homography":
            d["to"] = [tuple(r) for r in self.to_raw.reshape(-1, 9).tolist()]
            d["from"] = [tuple(r) for r in self.from_raw.reshape(-1, 9).tolist()]
        if self.kind in ("mesh-bilinear", "mesh-affine"):
            d["bil"] = [tuple(r) for r in self.bil.tolist()]
            d["bil_raw"] = [tuple(r) for r in self.bil_raw.tolist()]
            d["cond"] = (self.cond.centre[0], self.cond.centre[1], 1.0 / self.cond.scale)
        if self.kind == "mesh-affine":
            d["tri_to"] = [(tuple(a), tuple(b)) for a, b in self.tri_to.tolist()]
            d["tri_from"] = [(tuple(a), tuple(b)) for a, b in self.tri_from.tolist()]
            d["side"] = [tuple(r) for r in self.side.tolist()]
            d["hedge"] = self.hedge.transpose(1, 2, 0).tolist()
            d["vedge"] = self.vedge.transpose(1, 2, 0).tolist()
        self._py = d

    def py_locate(self, X: float, Y: float):
        """Single raw point: (k, s, t, tri, inside) with plain floats."""
        if self._py is None:
            self._prepare_py()
        d = self._py
        X = float(X)
        Y = float(Y)
        a, b, c, dd, e, f = d["loc"]
        u = a * X + b * Y + c
        v = dd * X + e * Y + f
        cmax, rmax = self.cols - 2, self.rows - 2
        ci = min(max(int(math.floor(u)), 0), cmax) if u == u else 0
        ri = min(max(int(math.floor(v)), 0), rmax) if v == v else 0
        kind = self.kind
        lo, hi = -_EPS, 1 + _EPS
        el = self.eps_len
        for _ in range(self.rows + self.cols):
            k = ri * (cmax + 1) + ci
            tri = 0
            if kind == "mesh-homography":
                h = d["to"][k]
                w = h[6] * X + h[7] * Y + h[8]
                s = (h[0] * X + h[1] * Y + h[2]) / w
                t = (h[3] * X + h[4] * Y + h[5]) / w
                dc = (s > hi) - (s < lo)
                dr = (t > hi) - (t < lo)
            elif kind == "mesh-affine":
                ta, tb = d["tri_to"][k]
                s = ta[0] * X + ta[1] * Y + ta[2]
                t = ta[3] * X + ta[4] * Y + ta[5]
                sd = d["side"][k]
                if sd[0] * s + sd[1] * t + sd[2] > 0:
                    tri = 1
                    s = tb[0] * X + tb[1] * Y + tb[2]
                    t = tb[3] * X + tb[4] * Y + tb[5]
                he, ve = d["hedge"], d["vedge"]
                lt, lb = he[ri][ci], he[ri + 1][ci]
                ll, lr = ve[ri][ci], ve[ri][ci + 1]
                dr = (lb[0] * X + lb[1] * Y + lb[2] > el) - (lt[0] * X + lt[1] * Y + lt[2] < -el)
                dc = (lr[0] * X + lr[1] * Y + lr[2] > el) - (ll[0] * X + ll[1] * Y + ll[2] < -el)
            else:
                cx, cy, inv = d["cond"]
                s, t = _py_bilinear_inverse(d["bil"][k], (X - cx) * inv, (Y - cy) * inv)
                dc = (s > hi) - (s < lo)
                dr = (t > hi) - (t < lo)
            nci = ci + dc
            nri = ri + dr
            nci = 0 if nci < 0 else (cmax if nci > cmax else nci)
            nri = 0 if nri < 0 else (rmax if nri > rmax else nri)
            if nci == ci and nri == ri:
                break
            ci, ri = nci, nri
        inside = dr == 0 and dc == 0
        if kind == "mesh-affine" and not inside:
            cx, cy, inv = d["cond"]
            s, t = _py_bilinear_inverse(d["bil"][k], (X - cx) * inv, (Y - cy) * inv)
            tri = 2
        return k, s, t, tri, inside

    def py_from_local(self, k: int, s: float, t: float, tri: int) -> tuple[float, float]:
        """Single point: raw plane coordinates of (s, t) in cell k."""
        if self._py is None:
            self._prepare_py()
        d = self._py
        s = float(s)
        t = float(t)
        if self.kind == "mesh-homography":
            h = d["from"][k]
            w = h[6] * s + h[7] * t + h[8]
            return (h[0] * s + h[1] * t + h[2]) / w, (h[3] * s + h[4] * t + h[5]) / w
        if self.kind == "mesh-affine" and tri < 2:
            a = d["tri_from"][k][tri]
            return a[0] * s + a[1] * t + a[2], a[3] * s + a[4] * t + a[5]
        b = d["bil_raw"][k]
        st = s * t
        return b[0] + b[1] * s + b[2] * t + b[3] * st, b[4] + b[5] * s + b[6] * t + b[7] * st


def _py_bilinear_inverse(b, X: float, Y: float) -> tuple[float, float]:
    """Single-point closed-form bilinear inverse (conditioned units) with one Newton step."""
    a0, a1, a2, a3, b0, b1, b2, b3 = b
    Xa = X - a0
    Yb = Y - b0
    A = b3 * a2 - b2 * a3
    B = Yb * a3 - b2 * a1 + b1 * a2 - b3 * Xa
    C = Yb * a1 - b1 * Xa
    disc = math.sqrt(max(B * B - 4 * A * C, 0.0))
    q = -0.5 * (B + (disc if B >= 0 else -disc))
    y = C / q if q != 0 else 0.0
    d1 = a1 + a3 * y
    d2 = b1 + b3 * y
    x = (Xa - a2 * y) / d1 if abs(d1) >= abs(d2) else (Yb - b2 * y) / d2
    fx = a0 + a1 * x + a2 * y + a3 * x * y - X
    fy = b0 + b1 * x + b2 * y + b3 * x * y - Y
    j00, j01, j10, j11 = a1 + a3 * y, a2 + a3 * x, b1 + b3 * y, b2 + b3 * x
    det = j00 * j11 - j01 * j10
    return x - (j11 * fx - j01 * fy) / det, y - (-j10 * fx + j00 * fy) / det


def _edge_lines(A: np.ndarray, B: np.ndarray, probe: np.ndarray) -> np.ndarray:
    """(3, ...) unit-normal lines through A -> B, positive on the side of ``probe``'s row/col.

    ``probe`` is a node one row below (for horizontal edges) or one column right (vertical
    edges) of the first node of A, fixing the orientation for the whole plane.
    """
    d = B - A
    ln = np.hypot(d[..., 0], d[..., 1])
    a = -d[..., 1] / ln
    b = d[..., 0] / ln
    c = -(a * A[..., 0] + b * A[..., 1])
    p = probe.reshape(2)
    sign = np.sign(a.ravel()[0] * p[0] + b.ravel()[0] * p[1] + c.ravel()[0]) or 1.0
    return np.stack([a * sign, b * sign, c * sign])


def _line_value(lines: np.ndarray, r: np.ndarray, c: np.ndarray, x: np.ndarray, y: np.ndarray):
    a = lines[0][r, c]
    b = lines[1][r, c]
    cc = lines[2][r, c]
    return a * x + b * y + cc


# ---------------------------------------------------------------------------------------------
# the model


class MeshModel:
    """Per-mesh film-deformation correction between pixel and film mm.

    Parameters
    ----------
    film : array_like (rows, cols, 2)
        Calibrated film coordinates of the reseau crosses, mm (row 0 on top).
    pixel : array_like (rows, cols, 2)
        Measured pixel positions of the crosses, px; NaN where a cross was not measured.
    kind : str
        ``mesh-affine``, ``mesh-homography`` or ``mesh-bilinear`` (see the module docstring),
        or ``mesh`` for :func:`default_mesh_kind`.

    Raises
    ------
    SoftplotError
        Fewer measured crosses than the mesh needs (the message names the method and counts),
        a grid smaller than 2 x 2, or film coordinates that are not finite.
    """

    def __init__(self, film, pixel, kind: str = "mesh") -> None:
        film = np.asarray(film, float)
        pixel = np.asarray(pixel, float)
        if film.ndim != 3 or film.shape[2] != 2 or pixel.shape != film.shape:
            raise SoftplotError(
                f"mesh: film and pixel must both be (rows, cols, 2) arrays, got "
                f"{film.shape} and {pixel.shape}"
            )
        rows, cols = film.shape[:2]
        if kind == "mesh":
            kind = default_mesh_kind(rows, cols)
        if kind not in MESH_KINDS:
            raise SoftplotError(f"unknown mesh kind {kind!r}: expected mesh or {MESH_KINDS}")
        if rows < 2 or cols < 2:
            raise SoftplotError(
                f"{kind} needs a reseau of at least 2 x 2 crosses, got {rows} x {cols}"
            )
        if not np.all(np.isfinite(film)):
            raise SoftplotError(f"{kind}: calibrated film coordinates must be finite")
        self.kind = kind
        self.rows, self.cols = rows, cols
        self.film_nodes = film.copy()
        measured = np.all(np.isfinite(pixel), axis=2)
        self.measured = measured
        need = max(MIN_POINTS[_FILL_KIND[kind]], 4)
        n_meas = int(measured.sum())
        if n_meas < need:
            raise SoftplotError(
                f"{kind} needs at least {need} measured reseau crosses, got {n_meas} "
                f"of {rows * cols}"
            )
        pixel = pixel.copy()
        self.filled: list[FilledCross] = []
        if n_meas < rows * cols:
            pixel, self.filled = _fill_missing(film, pixel, measured, _FILL_KIND[kind])
        self.pixel_nodes = pixel
        r, c = np.mgrid[0 : rows - 1, 0 : cols - 1]
        rc, cc = (rows - 2) / 2.0, (cols - 2) / 2.0
        self.backslash = ((r - rc) * (c - cc) >= 0).ravel()
        self._px = _Plane(pixel, kind, self.backslash)
        self._film = _Plane(film, kind, self.backslash)
        self._check_orientation()

    def _check_orientation(self) -> None:
        """Refuse folded grids (a cell whose pixel corners turn the other way)."""
        def signed_area(P):
            TL, TR, BR, BL = P[:-1, :-1], P[:-1, 1:], P[1:, 1:], P[1:, :-1]
            x = np.stack([TL[..., 0], TR[..., 0], BR[..., 0], BL[..., 0]])
            y = np.stack([TL[..., 1], TR[..., 1], BR[..., 1], BL[..., 1]])
            return 0.5 * (x * np.roll(y, -1, axis=0) - np.roll(x, -1, axis=0) * y).sum(axis=0)

        a_px = signed_area(self.pixel_nodes)
        a_f = signed_area(self.film_nodes)
        ratio = a_px * np.sign(np.median(a_px)) / np.abs(a_px).max()
        if np.any(ratio <= 0.05) or np.any(a_f * np.sign(np.median(a_f)) <= 0):
            bad = np.argwhere(ratio <= 0.05)
            where = f" (cell row {bad[0][0]}, col {bad[0][1]})" if bad.size else ""
            raise SoftplotError(
                f"{self.kind}: the reseau grid is folded or degenerate{where}: check the "
                "measured cross positions"
            )

    # -- properties -----------------------------------------------------------------------

    @property
    def n_cells(self) -> int:
        """Number of meshes: quads, or triangles for ``mesh-affine``."""
        k = (self.rows - 1) * (self.cols - 1)
        return 2 * k if self.kind == "mesh-affine" else k

    @property
    def method(self) -> str:
        return self.kind

    def describe(self) -> str:
        what = "triangles" if self.kind == "mesh-affine" else "quadrilaterals"
        s = f"{self.kind}: {self.rows} x {self.cols} crosses, {self.n_cells} {what}"
        if self.filled:
            s += ", merged around missing " + ", ".join(
                f"R{f.row}C{f.col}" for f in self.filled
            )
        return s

    # -- vectorised -----------------------------------------------------------------------

    def pixel_to_film(self, xy, post=None, bounds=None, threads=None):
        """Pixel (N, 2) px -> film (N, 2) mm, and flags (N,) uint8.

        Flags: 0 ok, 1 outside-reseau (nearest border mesh used), 2 outside-image when
        ``bounds`` = (x0, x1, y0, y1) in px is given and the point lies outside it.
        ``post(x_mm, y_mm) -> (x, y)``, if given, is applied chunk by chunk to the film
        coordinates (used to chain the interior orientation without another pass over N).
        ``threads``: worker threads for large N (default: the CPU count; 1 = none).
        Non-finite input points give NaN.
        """
        return self._px.map_to(self._film, _points(xy), post, bounds, threads)

    def film_to_pixel(self, xy, threads=None) -> tuple[np.ndarray, np.ndarray]:
        """Film (N, 2) mm -> pixel (N, 2) px, and flags (N,) uint8 (0 ok, 1 outside-reseau)."""
        return self._film.map_to(self._px, _points(xy), None, None, threads)

    def cells_of_pixel(self, xy) -> np.ndarray:
        """Quad index ``r * (cols-1) + c`` of pixel points (N,), nearest border quad outside."""
        p = _points(xy)
        return self._px.locate(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]))[0]

    def cells_of_film(self, xy) -> np.ndarray:
        """Quad index ``r * (cols-1) + c`` of film points (N,), nearest border quad outside."""
        p = _points(xy)
        return self._film.locate(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]))[0]

    # -- single point -------------------------------------------------------------------------

    def pixel_to_film_point(self, x: float, y: float) -> tuple[float, float, int]:
        """One pixel point -> (film x mm, film y mm, flag): plain floats, no numpy overhead."""
        k, s, t, tri, inside = self._px.py_locate(x, y)
        X, Y = self._film.py_from_local(k, s, t, tri)
        return X, Y, (FLAG_OK if inside else FLAG_OUTSIDE_RESEAU)

    def film_to_pixel_point(self, x: float, y: float) -> tuple[float, float, int]:
        """One film point (mm) -> (pixel x, pixel y, flag): plain floats."""
        k, s, t, tri, inside = self._film.py_locate(x, y)
        X, Y = self._px.py_from_local(k, s, t, tri)
        return X, Y, (FLAG_OK if inside else FLAG_OUTSIDE_RESEAU)

    # -- cells for resampling -----------------------------------------------------------------

    def film_quads(self) -> np.ndarray:
        """(K, 4, 2) film corners TL, TR, BR, BL of every quad, mm."""
        f = self.film_nodes
        P = np.stack([f[:-1, :-1], f[:-1, 1:], f[1:, 1:], f[1:, :-1]], axis=2)
        return P.reshape(-1, 4, 2)

    def film_cell_homographies(self) -> np.ndarray | None:
        """(K, 3, 3) film mm -> pixel homographies per quad (``mesh-homography`` only)."""
        if self.kind != "mesh-homography":
            return None
        H = self._px.from_raw @ np.linalg.inv(self._film.from_raw)
        return H / H[:, 2:3, 2:3]


def _points(xy) -> np.ndarray:
    a = np.asarray(xy, float)
    if a.ndim == 1 and a.shape[0] == 2:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 2:
        raise SoftplotError(f"expected an (N, 2) array of points, got shape {a.shape}")
    return a


def _fill_missing(film, pixel, measured, fit_kind):
    """Pixel positions for missing crosses from a transform over the block around each."""
    rows, cols = measured.shape
    filled = []
    out = pixel.copy()
    need = MIN_POINTS[fit_kind]
    for r, c in np.argwhere(~measured):
        done = False
        for half in range(1, max(rows, cols)):
            r0, r1 = max(r - half, 0), min(r + half + 1, rows)
            c0, c1 = max(c - half, 0), min(c + half + 1, cols)
            m = measured[r0:r1, c0:c1]
            if m.sum() < need:
                continue
            f = film[r0:r1, c0:c1][m]
            p = pixel[r0:r1, c0:c1][m]
            try:
                T = fit_transform(fit_kind, f, p)
            except SoftplotError:
                continue
            xy = T.forward(film[r, c][None])[0]
            out[r, c] = xy
            filled.append(
                FilledCross(int(r), int(c), (float(xy[0]), float(xy[1])), fit_kind, half,
                            int(m.sum()), T.sigma0)
            )
            done = True
            break
        if not done:
            raise SoftplotError(
                f"mesh: cannot merge the meshes around missing cross R{r}C{c}: too few "
                f"measured crosses in a usable layout ({fit_kind} needs {need})"
            )
    return out, filled
