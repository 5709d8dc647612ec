"""Sparse Levenberg-Marquardt with Schur elimination of the 3-D point blocks.

The problem class is the bundle adjustment's: residuals come in *observations*. Observation
``o`` has ``d`` rows (2 for image coordinates, 3 for model coordinates of the independent-model
method) and depends on

* the camera-side unknowns of its *group* ``g = obs_group[o]``: ``group_params[g]`` lists
  ``k`` indices into the flat camera-side vector (``-1`` marks a constant slot). A group is
  whatever the observation equations share: a photo (its exterior orientation plus the
  interior orientation of its physical camera, shared with other groups), a BAL camera, or an
  independent model's 3-D similarity;
* at most one object point ``p = obs_point[o]`` (three coordinates; ``-1``: none / constant).

Optional *priors* (pseudo-observations) act on single camera-side unknowns (a weighted
interior-orientation parameter) or on one point (weighted control, any 3x3 weight).

The normal equations ``[[U, W], [W', V]] [dc; dp] = -[gc; gp]`` are reduced to the camera side:
``S = U - W V^-1 W'`` with the (3x3) point blocks of ``V`` inverted in one vectorised call.
``S`` is assembled from per-group-pair products ``sum_p Y_o1 W_o2'`` (``Y = W V^-1``): the
observations sharing a point are paired once (:class:`SchurStructure`), sorted by group pair,
and every group pair costs one small GEMM, so the work is ``O(sum_p n_p^2 k^2)`` and memory
``O(observations)``. ``S`` is factorised by dense Cholesky (after Jacobi scaling) while the
camera side is small (``n_cam <= dense_limit``) and by ``scipy.sparse.linalg.splu`` beyond.

The LM damping follows Nielsen (as Ceres does): ``(J'J + lambda D) dx = -J'r`` with
``D = clip(diag(J'J), 1e-6, 1e32)``, ``lambda = 1 / radius``; after an accepted step
``radius /= max(1/3, 1 - (2 rho - 1)^3)``, after a rejected one ``radius /= v; v *= 2``.

Posterior covariance (:class:`NormalInverse`) is given as blocks without forming the full
inverse: the dense camera-side ``Qcc = S^-1``, the per-point ``Qpp`` (3x3), the camera-point
cross blocks of every observation and the ``d x d`` blocks of ``J Q J'`` needed for
redundancy numbers and data snooping.

Units and frames are the model's: this module only sees whitened residuals and Jacobians.
It imports nothing of softplot but :mod:`softplot.errors`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.sparse
import scipy.sparse.linalg

from softplot.adjust._blas import blas_threads
from softplot.errors import SoftplotError

__all__ = [
    "SchurStructure",
    "Evaluation",
    "SchurModel",
    "Linearization",
    "LMOptions",
    "LMResult",
    "levenberg_marquardt",
    "NormalInverse",
    "inv3",
]


def inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of a stack of 3x3 matrices, shape (..., 3, 3), by cofactors (vectorised)."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    g, h, i = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    co00 = e * i - f * h
    co01 = f * g - d * i
    co02 = d * h - e * g
    det = a * co00 + b * co01 + c * co02
    out = np.empty_like(A)
    inv_det = 1.0 / det
    out[..., 0, 0] = co00 * inv_det
    out[..., 1, 0] = co01 * inv_det
    out[..., 2, 0] = co02 * inv_det
    out[..., 0, 1] = (c * h - b * i) * inv_det
    out[..., 1, 1] = (a * i - c * g) * inv_det
    out[..., 2, 1] = (b * g - a * h) * inv_det
    out[..., 0, 2] = (b * f - c * e) * inv_det
    out[..., 1, 2] = (c * d - a * f) * inv_det
    out[..., 2, 2] = (a * e - b * d) * inv_det
    return out


# ---------------------------------------------------------------------------------------------
# structure


class SchurStructure:
    """Sparsity of a bundle problem; built once, reused by every iteration.

    Parameters
    ----------
    n_cam : int
        Number of camera-side unknowns (flat vector).
    n_pts : int
        Number of 3-D points (unknown blocks of 3).
    group_params : array_like of int, shape (G, k)
        Camera-side unknown indices of every group; ``-1`` for a constant slot.
    obs_group : array_like of int, shape (m,)
        Group of every observation.
    obs_point : array_like of int, shape (m,)
        Point of every observation, ``-1`` for none.
    d : int
        Residual rows per observation.
    point_free : array_like of bool, shape (n_pts, 3), optional
        ``False`` for point coordinates held constant (a datum or a height-only tie).
    dense_limit : int
        Largest ``n_cam`` solved by dense Cholesky; beyond, sparse LU (SuperLU).
    sparse_above, sparse_density : int, float
        Above ``sparse_above`` camera-side unknowns, a reduced system whose share of
        co-visible group pairs is below ``sparse_density`` (an aerial block) is solved by
        sparse LU even when it is small enough for the dense path.
    tilde_limit : float
        Largest ``(n_cam + 1) * 3 n_pts`` for which ``W V^-1 W'`` may be one dense product
        (chosen when cheaper than the pair GEMMs: many rays per point, few cameras).
    order_hint : array_like (G,), optional
        A coordinate per group (e.g. a photo's position along the block's long axis): the
        band solver orders the groups by it when that gives a narrower band than reverse
        Cuthill-McKee.
    """

    def __init__(
        self,
        n_cam: int,
        n_pts: int,
        group_params,
        obs_group,
        obs_point,
        d: int = 2,
        point_free=None,
        dense_limit: int = 4000,
        tilde_limit: float = 2e7,
        sparse_above: int = 800,
        sparse_density: float = 0.2,
        order_hint=None,
    ) -> None:
        self.n_cam = int(n_cam)
        self.n_pts = int(n_pts)
        self.d = int(d)
        gp = np.asarray(group_params, dtype=np.int64)
        if gp.ndim != 2:
            raise SoftplotError(f"group_params must be (G, k), got shape {gp.shape}")
        if gp.size and (gp.max() >= self.n_cam or gp.min() < -1):
            raise SoftplotError("group_params index outside the camera-side vector")
        self.G, self.k = gp.shape
        self.group_params = np.where(gp < 0, self.n_cam, gp)  # dummy slot n_cam
        self.obs_group = np.asarray(obs_group, dtype=np.int64).ravel()
        self.obs_point = np.asarray(obs_point, dtype=np.int64).ravel()
        self.m = self.obs_group.size
        if self.obs_point.size != self.m:
            raise SoftplotError("obs_group and obs_point differ in length")
        if self.m and (self.obs_group.min() < 0 or self.obs_group.max() >= self.G):
            raise SoftplotError("obs_group index outside the groups")
        if self.m and (self.obs_point.max() >= self.n_pts or self.obs_point.min() < -1):
            raise SoftplotError("obs_point index outside the points")
        self.point_free = (
            np.ones((self.n_pts, 3), bool)
            if point_free is None
            else np.asarray(point_free, bool).reshape(self.n_pts, 3)
        )
        self._dense_limit = dense_limit
        #: observation -> point index with the dummy point ``n_pts`` for "none"
        self.pt_ext = np.where(self.obs_point < 0, self.n_pts, self.obs_point)
        #: observation -> camera-side columns, (m, k), dummy ``n_cam`` for constant slots
        self.obs_cols = self.group_params[self.obs_group]
        self._build_groups()
        self._build_pairs()
        self._build_tilde(tilde_limit)
        #: share of the group pairs that are co-visible (block density of S)
        self.block_density = self.n_pair_blocks / max(self.G * (self.G + 1) / 2, 1)
        # dense Cholesky while small; sparse LU for large, sparse reduced systems (blocks)
        self.dense = self.n_cam <= dense_limit and not (
            self.n_cam > sparse_above and self.block_density < sparse_density
        )
        self._order_hint = None if order_hint is None else np.asarray(order_hint, float)
        self.band = None if self.dense else self._band_plan()

    def _band_plan(self, max_border: int = 1500, max_band: int = 3000):
        """Ordering of the camera side for the bordered band solver, or None.

        Unknowns shared by several groups (a physical camera's interior orientation) form
        the *border*, ordered last; the others follow the reverse Cuthill-McKee order of the
        groups' co-visibility graph (a fill-reducing, bandwidth-reducing ordering), so the
        reduced system is a band matrix bordered by a few dense rows.
        """
        import scipy.sparse.csgraph

        n, G = self.n_cam, self.G
        gp = self.group_params
        cnt = np.bincount(gp[gp < n].ravel(), minlength=n)
        border = np.flatnonzero(cnt > 1)
        if border.size > max_border:
            return None
        adj = scipy.sparse.coo_matrix(
            (np.ones(self.pair_g1.size), (self.pair_g1, self.pair_g2)), shape=(G, G)
        ).tocsr()
        adj = (adj + adj.T).tocsr()
        orders = [scipy.sparse.csgraph.reverse_cuthill_mckee(adj, symmetric_mode=True)]
        if self._order_hint is not None and self._order_hint.size == G:
            orders.append(np.argsort(self._order_hint, kind="stable"))
        best = None
        for order in orders:  # the narrowest band of the group graph
            pos = np.empty(G, np.int64)
            pos[order] = np.arange(G)
            bw = int(np.abs(pos[self.pair_g1] - pos[self.pair_g2]).max()) if G else 0
            if best is None or bw < best[0]:
                best = (bw, pos)
        pos = best[1]
        # every non-border unknown takes the position of (the first) group holding it
        first = np.full(n, np.iinfo(np.int64).max)
        rows = np.repeat(pos, gp.shape[1])
        cols = gp.ravel()
        ok = cols < n
        np.minimum.at(first, cols[ok], rows[ok])
        is_b = np.zeros(n, bool)
        is_b[border] = True
        inner = np.flatnonzero(~is_b)
        inner = inner[np.lexsort((inner, first[inner]))]
        perm = np.concatenate([inner, border])
        inv = np.empty(n, np.int64)
        inv[perm] = np.arange(n)
        # bandwidth of the inner part from the group pairs
        gi = inv[np.where(gp < n, gp, 0)]
        gi = np.where(gp < n, gi, -1)
        inner_pos = np.where((gi >= 0) & (gi < inner.size), gi, -1)
        lo = np.where(inner_pos >= 0, inner_pos, np.iinfo(np.int64).max).min(axis=1)
        hi = inner_pos.max(axis=1)
        a, b = self.pair_g1, self.pair_g2
        valid = (hi[a] >= 0) & (hi[b] >= 0)
        u = 0
        if valid.any():
            u = int(max(np.max(hi[a][valid] - lo[b][valid]), np.max(hi[b][valid] - lo[a][valid])))
        u = max(u, int(np.max(np.where(hi >= 0, hi - lo, 0))) if G else 0)
        if u > max_band:
            return None
        # scatter plan of the reduced system's entries (U blocks, pair blocks, transposes)
        # into the band / border storage, upper triangle in the new order
        N1 = n + 1
        flat = np.concatenate([self.u_flat, self.s_flat, self.s_flat_t[self.offdiag]])
        rr, cc = np.divmod(flat, N1)
        ok = (rr < n) & (cc < n)
        inv_e = np.append(inv, -1)
        r, c = inv_e[rr], inv_e[cc]
        sel = np.flatnonzero(ok & (r <= c))
        r, c = r[sel], c[sel]
        na, nb = int(inner.size), int(border.size)
        ia = c < na
        ib = (r < na) & (c >= na)
        icc = r >= na
        return {
            "perm": perm,
            "n_inner": na,
            "u": u,
            "sel": sel,
            "r": r,
            "c": c,
            "dest_a": (u + r[ia] - c[ia]) * na + c[ia],
            "ia": np.flatnonzero(ia),
            "dest_b": r[ib] * nb + (c[ib] - na),
            "ib": np.flatnonzero(ib),
            "dest_c": (r[icc] - na) * nb + (c[icc] - na),
            "ic": np.flatnonzero(icc),
            "idiag": np.flatnonzero(r == c),
        }

    # -- observations by group (for U)
    def _build_groups(self) -> None:
        order = np.argsort(self.obs_group, kind="stable")
        counts = np.bincount(self.obs_group, minlength=self.G)
        self.g_order = order
        self.g_bounds = np.concatenate([[0], np.cumsum(counts)])

    # -- pairs of observations sharing a point (for W V^-1 W')
    def _build_pairs(self) -> None:
        has = np.flatnonzero(self.obs_point >= 0)
        pts = self.obs_point[has]
        order = has[np.argsort(pts, kind="stable")]
        ps = self.obs_point[order]
        cnt = np.bincount(ps, minlength=self.n_pts)
        start = np.concatenate([[0], np.cumsum(cnt)])
        n = len(order)
        # all ordered pairs (a, b) of observations of the same point
        nn = cnt[ps]
        i1 = np.repeat(np.arange(n), nn)
        first = start[ps]
        off = np.arange(i1.size) - np.repeat(np.cumsum(nn) - nn, nn)
        i2 = np.repeat(first, nn) + off
        P1, P2 = order[i1], order[i2]
        g1, g2 = self.obs_group[P1], self.obs_group[P2]
        keep = g1 <= g2  # upper block triangle; diagonal blocks keep both orders
        P1, P2, g1, g2 = P1[keep], P2[keep], g1[keep], g2[keep]
        key = g1 * self.G + g2
        o = np.argsort(key, kind="stable")
        self.pair1, self.pair2, key = P1[o], P2[o], key[o]
        ukey, first_idx = np.unique(key, return_index=True)
        self.pair_bounds = np.append(first_idx, key.size)
        self.pair_g1 = ukey // self.G
        self.pair_g2 = ukey % self.G
        self.n_pair_blocks = ukey.size
        # ordered pairs for covariance propagation (point block sums)
        self.opair1, self.opair2 = order[i1], order[i2]
        self.obs_point_count = np.bincount(self.pt_ext, minlength=self.n_pts + 1)[: self.n_pts]
        # scatter indices of the blocks into S (dense flat or sparse coo), dummy removed
        N1 = self.n_cam + 1
        k = self.k
        rows_u = np.repeat(self.group_params[:, :, None], k, axis=2)  # (G,k,k)
        cols_u = np.repeat(self.group_params[:, None, :], k, axis=1)
        self.u_flat = (rows_u * N1 + cols_u).ravel()
        g1b, g2b = self.pair_g1, self.pair_g2
        r = np.repeat(self.group_params[g1b][:, :, None], k, axis=2)
        c = np.repeat(self.group_params[g2b][:, None, :], k, axis=1)
        self.s_flat = (r * N1 + c).ravel()  # block (g1, g2)
        self.s_flat_t = (c * N1 + r).ravel()  # its transpose (g2, g1), used where g1 != g2
        self.offdiag = np.repeat(g1b != g2b, k * k)

    def _build_tilde(self, tilde_limit: float) -> None:
        """Decide between pair GEMMs and one dense product for ``W V^-1 W'``."""
        N1, P3 = self.n_cam + 1, 3 * self.n_pts
        pair_cost = 3.0 * self.k * self.k * self.pair1.size
        dense_cost = float(N1) * N1 * P3 / 10.0  # BLAS runs ~10x faster than gathers
        self.tilde_ok = bool(self.n_pts and N1 * P3 <= tilde_limit and dense_cost < pair_cost)
        has = self.obs_point >= 0
        rows = np.repeat(self.obs_cols[:, :, None], 3, axis=2)
        cols = np.minimum(self.pt_ext, max(self.n_pts - 1, 0))[:, None, None] * 3 + np.arange(3)
        cols = np.broadcast_to(cols, rows.shape)
        self._tilde_has = has
        self._tilde_rows, self._tilde_cols = rows, cols
        self._tilde_flat = (rows * max(P3, 1) + cols)[has].ravel() if self.tilde_ok else None

    def tilde(self, Y: np.ndarray) -> np.ndarray:
        """Per-observation blocks (k, m, 3) summed into a dense (n_cam+1, 3 n_pts) matrix.

        Column block ``j`` is ``sum_{o of point j} E_o Y_o`` (row ``n_cam`` is the dummy slot,
        zeroed).
        """
        N1, P3 = self.n_cam + 1, 3 * self.n_pts
        flat = self._tilde_flat
        if flat is None:
            flat = (self._tilde_rows * P3 + self._tilde_cols)[self._tilde_has].ravel()
        Yo = Y.transpose(1, 0, 2)[self._tilde_has].ravel()
        T = np.bincount(flat, weights=Yo, minlength=N1 * P3).reshape(N1, P3)
        T[self.n_cam] = 0.0
        return T

    @property
    def n_unknowns(self) -> int:
        """Camera-side unknowns plus free point coordinates."""
        return self.n_cam + int(self.point_free.sum())


@dataclass
class Evaluation:
    """Whitened residuals (and Jacobians) of a state.

    Attributes
    ----------
    r : ndarray, shape (m, d)
        Whitened residuals of the observations.
    Jc : ndarray, shape (m, d, k) or None
        Jacobian w.r.t. the group's camera-side slots (constant slots: any value, ignored).
    Jp : ndarray, shape (m, d, 3) or None
        Jacobian w.r.t. the observation's point.
    cam_prior : tuple (idx (q,), r (q,), jac (q,)) or None
        Priors on single camera-side unknowns: whitened residual and its derivative.
    pt_prior : tuple (idx (s,), r (s, 3), J (s, 3, 3)) or None
        Priors on points: whitened residual and its Jacobian w.r.t. the point.
    """

    r: np.ndarray
    Jc: np.ndarray | None = None
    Jp: np.ndarray | None = None
    cam_prior: tuple | None = None
    pt_prior: tuple | None = None

    @property
    def cost(self) -> float:
        """``0.5 * sum(r^2)`` over observations and priors."""
        c = float(np.einsum("ij,ij->", self.r, self.r))
        if self.cam_prior is not None:
            c += float(np.dot(self.cam_prior[1], self.cam_prior[1]))
        if self.pt_prior is not None:
            c += float(np.einsum("ij,ij->", self.pt_prior[1], self.pt_prior[1]))
        return 0.5 * c


class SchurModel(Protocol):
    """What :func:`levenberg_marquardt` needs from a model."""

    structure: SchurStructure

    def evaluate(self, state: Any, jacobian: bool) -> Evaluation:  # pragma: no cover
        """Residuals (and Jacobians when ``jacobian``) at ``state``."""

    def retract(self, state: Any, d_cam: np.ndarray, d_pts: np.ndarray) -> Any:  # pragma: no cover
        """New state from camera-side increment (n_cam,) and point increments (n_pts, 3)."""


# ---------------------------------------------------------------------------------------------
# linearisation and the damped reduced solve


class Linearization:
    """Normal-equation pieces at one state: ``U`` (dense or sparse), ``W``, ``V``, gradients.

    ``W`` is stored per observation in the layout (k, m, 3), ``V`` as (n_pts, 3, 3).
    """

    def __init__(self, st: SchurStructure, ev: Evaluation) -> None:
        self.st = st
        self.ev = ev
        self._Wt = None
        m, k, N1 = st.m, st.k, st.n_cam + 1
        r, Jc, Jp = ev.r, ev.Jc, ev.Jp
        Jc = np.where((st.obs_cols == st.n_cam)[:, None, :], 0.0, Jc)  # constant slots
        Jp = Jp * st.point_free[np.minimum(st.pt_ext, st.n_pts - 1)][:, None, :] if st.n_pts else Jp
        Jp = np.where((st.obs_point < 0)[:, None, None], 0.0, Jp)
        self.Jc, self.Jp = Jc, Jp
        # gradients
        gco = np.einsum("mdk,md->mk", Jc, r)
        self.gc = np.bincount(st.obs_cols.ravel(), weights=gco.ravel(), minlength=N1)
        gpo = np.einsum("mda,md->ma", Jp, r)
        P1 = st.n_pts + 1
        self.gp = np.stack(
            [np.bincount(st.pt_ext, weights=gpo[:, a], minlength=P1) for a in range(3)], axis=1
        )
        # U per group by GEMM over group-sorted observations
        JcT = np.ascontiguousarray(Jc[st.g_order].transpose(2, 0, 1)).reshape(k, -1)
        Ug = np.empty((st.G, k, k))
        b = st.g_bounds * st.d
        for g in range(st.G):
            blk = JcT[:, b[g] : b[g + 1]]
            Ug[g] = blk @ blk.T
        self.Ug = Ug
        self.U_flat = (
            np.bincount(st.u_flat, weights=Ug.ravel(), minlength=N1 * N1) if st.dense else None
        )
        # camera priors: diagonal
        self.Udiag_extra = np.zeros(N1)
        if ev.cam_prior is not None:
            idx, pr, pj = ev.cam_prior
            idx = np.asarray(idx, np.int64)
            self.Udiag_extra += np.bincount(idx, weights=pj * pj, minlength=N1)
            self.gc += np.bincount(idx, weights=pj * pr, minlength=N1)
        # W (k, m, 3) and V (P, 3, 3)
        # W = Jc' Jp per observation, (k, m, 3) (batched matmul: faster than einsum here)
        self.W = np.ascontiguousarray(np.matmul(Jc.transpose(0, 2, 1), Jp).transpose(1, 0, 2))
        Vo = np.einsum("mda,mdb->mab", Jp, Jp).reshape(m, 9)
        V = np.stack([np.bincount(st.pt_ext, weights=Vo[:, i], minlength=P1) for i in range(9)])
        V = V.T.reshape(P1, 3, 3)
        if ev.pt_prior is not None:
            idx, pr, pJ = ev.pt_prior
            idx = np.asarray(idx, np.int64)
            pJ = pJ * st.point_free[idx][:, None, :]
            np.add.at(V, idx, np.einsum("sia,sib->sab", pJ, pJ))
            np.add.at(self.gp, idx, np.einsum("sia,si->sa", pJ, pr))
        V = V[: st.n_pts]
        self.gp = self.gp[: st.n_pts]
        fixed = ~st.point_free
        V[:, 0, 0] += fixed[:, 0]
        V[:, 1, 1] += fixed[:, 1]
        V[:, 2, 2] += fixed[:, 2]
        self.V = V
        diagU = (
            np.bincount(
                st.group_params.ravel(),
                weights=np.einsum("gii->gi", Ug).ravel(),
                minlength=N1,
            )
            + self.Udiag_extra
        )
        self.diag_c = diagU[: st.n_cam]
        self.diag_p = np.einsum("pii->pi", V)
        self.gc = self.gc[: st.n_cam]

    @property
    def gradient_norm(self) -> float:
        """Max-norm of the gradient ``J'r``."""
        gp = self.gp * self.st.point_free
        a = np.abs(self.gc).max() if self.gc.size else 0.0
        b = np.abs(gp).max() if gp.size else 0.0
        return float(max(a, b))

    def reduced(self, lam_c: np.ndarray | float, lam_p: np.ndarray | float):
        """Reduced camera system with damping added to the diagonals.

        Parameters
        ----------
        lam_c : ndarray (n_cam,) or float
            Added to the camera-side diagonal.
        lam_p : ndarray (n_pts, 3) or float
            Added to the point diagonals.

        Returns
        -------
        S : ndarray (n_cam, n_cam) or scipy.sparse.csc_matrix
        b : ndarray (n_cam,)
            Right-hand side ``-gc + W V^-1 gp``.
        Vinv : ndarray (n_pts, 3, 3)
        Y : ndarray (k, m, 3)
            ``W V^-1`` per observation.
        """
        st = self.st
        N1 = st.n_cam + 1
        Vd = self.V.copy()
        lp = np.broadcast_to(np.asarray(lam_p, float), (st.n_pts, 3))
        Vd[:, 0, 0] += lp[:, 0]
        Vd[:, 1, 1] += lp[:, 1]
        Vd[:, 2, 2] += lp[:, 2]
        Vinv = inv3(Vd) if st.n_pts else Vd
        Vinv_o = Vinv[np.minimum(st.pt_ext, max(st.n_pts - 1, 0))] if st.n_pts else None
        if st.n_pts:
            Y = np.ascontiguousarray(
                np.matmul(self.W.transpose(1, 0, 2), Vinv_o).transpose(1, 0, 2)
            )
        else:
            Y = self.W
        # pair blocks: sum over shared points of Y_o1 W_o2'
        use_tilde = st.dense and st.tilde_ok
        blocks = None if use_tilde else self._pair_blocks(Y, self.W)
        # right-hand side
        gpo = self.gp[np.minimum(st.pt_ext, max(st.n_pts - 1, 0))] if st.n_pts else None
        b = -self.gc.copy()
        if st.n_pts:
            yg = np.einsum("kma,ma->mk", Y, gpo)
            yg[st.obs_point < 0] = 0.0
            b += np.bincount(st.obs_cols.ravel(), weights=yg.ravel(), minlength=N1)[: st.n_cam]
        lc = np.broadcast_to(np.asarray(lam_c, float), (st.n_cam,))
        if use_tilde:
            # one dense product: S = U - Ytilde Wtilde'
            if self._Wt is None:
                self._Wt = st.tilde(self.W)
            S = self.U_flat.reshape(N1, N1) - st.tilde(Y) @ self._Wt.T
            S = S[: st.n_cam, : st.n_cam]
            S[np.diag_indices(st.n_cam)] += lc + self.Udiag_extra[: st.n_cam]
        elif st.dense:
            bl = blocks.ravel()
            S = self.U_flat.copy()
            S -= np.bincount(st.s_flat, weights=bl, minlength=N1 * N1)
            S -= np.bincount(st.s_flat_t[st.offdiag], weights=bl[st.offdiag], minlength=N1 * N1)
            S = S.reshape(N1, N1)[: st.n_cam, : st.n_cam]
            S[np.diag_indices(st.n_cam)] += lc + self.Udiag_extra[: st.n_cam]
        elif st.band is not None:
            bl = blocks.ravel()
            vals = np.concatenate([self.Ug.ravel(), -bl, -bl[st.offdiag]])[st.band["sel"]]
            S = BandSystem(st.band, vals, lc + self.Udiag_extra[: st.n_cam])
        else:
            bl = blocks.ravel()
            flat = np.concatenate([st.u_flat, st.s_flat, st.s_flat_t[st.offdiag]])
            vals = np.concatenate([self.Ug.ravel(), -bl, -bl[st.offdiag]])
            rr, cc = np.divmod(flat, N1)
            ok = (rr < st.n_cam) & (cc < st.n_cam)
            diag = np.arange(st.n_cam)
            S = scipy.sparse.coo_matrix(
                (
                    np.concatenate([vals[ok], lc + self.Udiag_extra[: st.n_cam]]),
                    (np.concatenate([rr[ok], diag]), np.concatenate([cc[ok], diag])),
                ),
                shape=(st.n_cam, st.n_cam),
            ).tocsc()
        return S, b, Vinv, Y

    def _pair_blocks(self, Y: np.ndarray, W: np.ndarray) -> np.ndarray:
        """``sum_p Y_o1 W_o2'`` for every group pair of :class:`SchurStructure`, (B, k, k)."""
        st = self.st
        k = st.k
        out = np.zeros((st.n_pair_blocks, k, k))
        if st.n_pair_blocks == 0:
            return out
        A = np.take(Y, st.pair1, axis=1).reshape(k, -1)
        B = np.take(W, st.pair2, axis=1).reshape(k, -1)
        bnd = 3 * st.pair_bounds
        for q in range(st.n_pair_blocks):
            s, e = bnd[q], bnd[q + 1]
            out[q] = A[:, s:e] @ B[:, s:e].T
        return out

    def back_substitute(self, dc: np.ndarray, Vinv: np.ndarray, rhs_p: np.ndarray) -> np.ndarray:
        """Point increments ``dp = V^-1 (rhs_p - W' dc)``, shape (n_pts, 3)."""
        st = self.st
        if not st.n_pts:
            return np.zeros((0, 3))
        dce = np.append(dc, 0.0)
        wd = np.einsum("kma,mk->ma", self.W, dce[st.obs_cols])
        P1 = st.n_pts + 1
        s = np.stack([np.bincount(st.pt_ext, weights=wd[:, a], minlength=P1) for a in range(3)], 1)
        t = rhs_p - s[: st.n_pts]
        return np.einsum("pab,pb->pa", Vinv, t) * st.point_free

    def model_decrease(self, dc: np.ndarray, dp: np.ndarray) -> float:
        """``L(0) - L(dx)`` of the linear model ``0.5 |r + J dx|^2`` (priors included)."""
        st = self.st
        dce = np.append(dc, 0.0)
        jd = np.einsum("mdk,mk->md", self.Jc, dce[st.obs_cols])
        if st.n_pts:
            dpe = np.vstack([dp, np.zeros((1, 3))])
            jd += np.einsum("mda,ma->md", self.Jp, dpe[st.pt_ext])
        r = self.ev.r
        dec = -float(np.einsum("md,md->", r, jd)) - 0.5 * float(np.einsum("md,md->", jd, jd))
        if self.ev.cam_prior is not None:
            idx, pr, pj = self.ev.cam_prior
            t = pj * dce[np.asarray(idx, np.int64)]
            dec += -float(pr @ t) - 0.5 * float(t @ t)
        if self.ev.pt_prior is not None:
            idx, pr, pJ = self.ev.pt_prior
            t = np.einsum("sia,sa->si", pJ * st.point_free[idx][:, None, :], dp[idx])
            dec += -float(np.einsum("si,si->", pr, t)) - 0.5 * float(np.einsum("si,si->", t, t))
        return dec

    def solve(self, lam_c, lam_p):
        """Damped Gauss-Newton step ``(dc, dp)`` or ``None`` when the system is not definite."""
        S, b, Vinv, _ = self.reduced(lam_c, lam_p)
        dc = _solve_reduced(S, b, self.st.dense, self.st.band)
        if dc is None:
            return None
        dp = self.back_substitute(dc, Vinv, -self.gp)
        return dc, dp


class BandSystem:
    """The reduced camera system in the bordered band plan of a :class:`SchurStructure`:
    upper-triangle entries (new order) and the diagonal additions (camera order)."""

    def __init__(self, plan: dict, vals: np.ndarray, diag_add: np.ndarray) -> None:
        self.plan, self.vals = plan, vals
        n = plan["perm"].size
        self.shape = (n, n)
        d = np.bincount(plan["r"][plan["idiag"]], vals[plan["idiag"]], minlength=n)
        self.diag_perm = d + diag_add[plan["perm"]]

    def diagonal(self) -> np.ndarray:
        out = np.empty_like(self.diag_perm)
        out[self.plan["perm"]] = self.diag_perm
        return out

    def toarray(self) -> np.ndarray:
        """Dense matrix (camera order; tests and small problems only)."""
        n = self.shape[0]
        p = self.plan
        M = np.zeros((n, n))
        off = p["r"] != p["c"]
        np.add.at(M, (p["r"][off], p["c"][off]), self.vals[off])
        M = M + M.T
        M[np.diag_indices(n)] = self.diag_perm
        out = np.empty_like(M)
        out[np.ix_(p["perm"], p["perm"])] = M
        return out


class BorderedBand:
    """Cholesky factor of the reduced system ``S`` (a :class:`BandSystem`, Jacobi-scaled)
    in the ordering of :meth:`SchurStructure._band_plan`: ``[[A, B], [B', C]]`` with ``A``
    banded (LAPACK ``pbtrf``), the border by its Schur complement ``C - B' A^-1 B`` (dense
    Cholesky).

    Work ``O(n u^2 + n u k + n k^2)`` for ``n`` unknowns, half-bandwidth ``u`` and ``k``
    border unknowns; memory ``O(n (u + k))``.

    Raises
    ------
    numpy.linalg.LinAlgError
        When ``S`` is not positive definite.
    """

    def __init__(self, S: BandSystem) -> None:
        p = S.plan
        perm, na, u = p["perm"], p["n_inner"], p["u"]
        n = perm.size
        dg = S.diag_perm
        if np.any(~(dg > 0)) or not np.all(np.isfinite(dg)):
            raise np.linalg.LinAlgError("non-positive diagonal")
        sp = 1.0 / np.sqrt(dg)  # new order
        self.s = np.empty(n)
        self.s[perm] = sp
        r, c = p["r"], p["c"]
        v = S.vals * sp[r] * sp[c]
        v[p["idiag"]] = 0.0
        self.perm, self.na, self.n = perm, na, n
        nb = n - na
        ab = np.bincount(p["dest_a"], v[p["ia"]], minlength=(u + 1) * na).reshape(u + 1, na)
        ab[u, :] = 1.0  # the scaled diagonal
        self.cf = scipy.linalg.cholesky_banded(ab, lower=False, check_finite=False)
        B = np.bincount(p["dest_b"], v[p["ib"]], minlength=na * nb).reshape(na, nb)
        Cb = np.bincount(p["dest_c"], v[p["ic"]], minlength=nb * nb).reshape(nb, nb)
        Cb = Cb + Cb.T
        Cb[np.diag_indices(nb)] = 1.0
        self.B = B
        self.X = scipy.linalg.cho_solve_banded((self.cf, False), B, check_finite=False)
        Sc = Cb - B.T @ self.X
        self.Sc_cf = scipy.linalg.cho_factor(Sc, lower=False, check_finite=False) if nb else None

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``S^-1 b`` for ``b`` of shape (n,) or (n, q)."""
        sc = self.s if b.ndim == 1 else self.s[:, None]
        bp = (b * sc)[self.perm]
        na = self.na
        ya = scipy.linalg.cho_solve_banded((self.cf, False), bp[:na], check_finite=False)
        if self.n > na:
            xb = scipy.linalg.cho_solve(self.Sc_cf, bp[na:] - self.B.T @ ya, check_finite=False)
            xa = ya - self.X @ xb
            xp = np.concatenate([xa, xb])
        else:
            xp = ya
        out = np.empty_like(xp)
        out[self.perm] = xp
        return out * sc

    def border_index(self) -> np.ndarray:
        """Camera-side indices of the border unknowns (order of :meth:`border_inverse`)."""
        return self.perm[self.na :]

    def border_inverse(self) -> np.ndarray:
        """The border block of ``S^-1`` (the inverse of the Schur complement, unscaled)."""
        nb = self.n - self.na
        if nb == 0:
            return np.zeros((0, 0))
        Q = scipy.linalg.cho_solve(self.Sc_cf, np.eye(nb), check_finite=False)
        sb = self.s[self.perm[self.na :]]
        return Q * sb[:, None] * sb[None, :]


def _solve_reduced(S, b, dense: bool, band: dict | None = None):
    """Solve ``S x = b`` (Jacobi-scaled Cholesky: dense, bordered band, or sparse LU);
    ``None`` if it fails."""
    if b.size == 0:
        return np.zeros(0)
    if not dense and band is not None:
        try:
            x = BorderedBand(S).solve(b)
        except (np.linalg.LinAlgError, ValueError):
            return None
        return x if np.all(np.isfinite(x)) else None
    if dense:
        dg = np.diag(S).copy()
        if not np.all(np.isfinite(dg)) or np.any(dg <= 0):
            return None
        s = 1.0 / np.sqrt(dg)
        Ss = S * s[:, None] * s[None, :]
        try:
            cf = scipy.linalg.cho_factor(Ss, lower=False, check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return None
        x = scipy.linalg.cho_solve(cf, b * s, check_finite=False) * s
    else:
        dg = S.diagonal()
        if np.any(dg <= 0) or not np.all(np.isfinite(dg)):
            return None
        s = 1.0 / np.sqrt(dg)
        D = scipy.sparse.diags(s)
        try:
            lu = scipy.sparse.linalg.splu(
                (D @ S @ D).tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}
            )
        except RuntimeError:
            return None
        x = lu.solve(b * s) * s
    if not np.all(np.isfinite(x)):
        return None
    return x


# ---------------------------------------------------------------------------------------------
# Levenberg-Marquardt


@dataclass
class LMOptions:
    """Levenberg-Marquardt settings (defaults as Ceres's trust-region LM)."""

    max_iterations: int = 100
    function_tolerance: float = 1e-6  # stop when |d cost| / cost < this on an accepted step
    gradient_tolerance: float = 1e-10  # stop when max |J'r| < this
    parameter_tolerance: float = 1e-8  # stop when |dx| < tol * (|x| + tol) (x: increments)
    initial_radius: float = 1e4  # lambda = 1 / radius
    max_radius: float = 1e16
    min_radius: float = 1e-32
    min_diagonal: float = 1e-6
    max_diagonal: float = 1e32
    min_relative_decrease: float = 1e-3
    progress: Callable[[dict], None] | None = None  # called with a dict after every iteration
    single_thread_limit: int = 6000  # camera-side size up to which BLAS runs on one thread


@dataclass
class LMResult:
    """Outcome of :func:`levenberg_marquardt`."""

    state: Any
    initial_cost: float
    cost: float
    iterations: int
    evaluations: int
    seconds: float
    converged: bool
    message: str
    history: list = field(default_factory=list)
    linearization: Linearization | None = None


def levenberg_marquardt(model: SchurModel, state, options: LMOptions | None = None) -> LMResult:
    """Minimise ``0.5 |r(state)|^2`` by Levenberg-Marquardt on the Schur-reduced system.

    Parameters
    ----------
    model : SchurModel
        Provides ``structure``, ``evaluate(state, jacobian)`` and ``retract``.
    state : any
        Starting state (the model's type).
    options : LMOptions, optional

    Returns
    -------
    LMResult
        With the final state, costs, iteration counts and the linearisation at the solution
        (Jacobians evaluated at the final state) for the covariance.
    """
    opt = options or LMOptions()
    st = model.structure
    # one BLAS thread for small systems and for the band solver (threads gain little there
    # and lose much when the cores are shared)
    threads = 1 if st.n_cam <= opt.single_thread_limit or st.band is not None else None
    with blas_threads(threads):
        return _lm(model, state, opt)


def _lm(model: SchurModel, state, opt: LMOptions) -> LMResult:
    st = model.structure
    t0 = time.perf_counter()
    ev = model.evaluate(state, True)
    n_eval = 1
    cost = ev.cost
    cost0 = cost
    if not np.isfinite(cost):
        raise SoftplotError("the starting values give a non-finite cost")
    lin = Linearization(st, ev)
    radius, v = opt.initial_radius, 2.0
    history = []
    converged, message = False, "maximum number of iterations reached"
    it = 0
    if lin.gradient_norm <= opt.gradient_tolerance:
        converged, message = True, "gradient below tolerance at the start"
    while not converged and it < opt.max_iterations:
        it += 1
        lam = 1.0 / radius
        Dc = np.clip(lin.diag_c, opt.min_diagonal, opt.max_diagonal)
        Dp = np.clip(lin.diag_p, opt.min_diagonal, opt.max_diagonal)
        step = lin.solve(lam * Dc, lam * Dp)
        accepted = False
        new_cost = np.nan
        rho = np.nan
        if step is not None:
            dc, dp = step
            pred = lin.model_decrease(dc, dp)
            new_state = model.retract(state, dc, dp)
            ev_new = model.evaluate(new_state, False)
            n_eval += 1
            new_cost = ev_new.cost
            if np.isfinite(new_cost) and pred > 0:
                rho = (cost - new_cost) / pred
                accepted = rho > opt.min_relative_decrease
            step_norm = float(np.sqrt(dc @ dc + np.einsum("pa,pa->", dp, dp)))
        if accepted:
            radius = min(opt.max_radius, radius / max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
            v = 2.0
            rel = (cost - new_cost) / max(cost, 1e-300)
            state = new_state
            cost = new_cost
            ev = model.evaluate(state, True)
            n_eval += 1
            lin = Linearization(st, ev)
            if rel < opt.function_tolerance:
                converged, message = True, "relative cost decrease below function_tolerance"
            elif lin.gradient_norm <= opt.gradient_tolerance:
                converged, message = True, "gradient below gradient_tolerance"
            elif step_norm <= opt.parameter_tolerance * (step_norm + opt.parameter_tolerance):
                converged, message = True, "step below parameter_tolerance"
        else:
            radius /= v
            v *= 2.0
            if radius < opt.min_radius:
                converged, message = True, "trust region collapsed (no further decrease possible)"
        rec = {
            "iteration": it,
            "cost": cost,
            "trial_cost": new_cost,
            "rho": rho,
            "lambda": lam,
            "accepted": accepted,
            "seconds": time.perf_counter() - t0,
        }
        history.append(rec)
        if opt.progress is not None:
            opt.progress(rec)
    return LMResult(
        state=state,
        initial_cost=cost0,
        cost=cost,
        iterations=it,
        evaluations=n_eval,
        seconds=time.perf_counter() - t0,
        converged=converged,
        message=message,
        history=history,
        linearization=lin,
    )


# ---------------------------------------------------------------------------------------------
# posterior covariance in blocks


class NormalInverse:
    """Blocks of ``Q = (J'J)^-1`` (whitened: multiply by sigma0^2 for covariances).

    Built from the undamped :class:`Linearization` at the solution. The camera side is
    ``Qcc = S^-1`` (dense, ``n_cam x n_cam``); point blocks, camera-point cross blocks per
    observation and observation-space blocks are propagated through the Schur complement
    without forming the full inverse.

    Raises
    ------
    SoftplotError
        When the reduced system is singular (an undetermined datum or parameter).
    """

    def __init__(
        self,
        lin: Linearization,
        chunk: int = 20000,
        dense_product_limit: float = 4e9,
        dense_inverse_limit: int = 8000,
    ) -> None:
        self.dense_product_limit = dense_product_limit
        self.lin = lin
        st = lin.st
        self.st = st
        self.chunk = chunk
        S, _, self.Vinv, self.Y = lin.reduced(0.0, 0.0)
        n = st.n_cam
        self._Qcc = None
        self.band = None
        if n:
            if not st.dense and n <= dense_inverse_limit:
                S = S.toarray()  # all of Qcc is wanted: a dense factor is faster than n solves
            if isinstance(S, np.ndarray):
                dg = np.diag(S).copy()
                if np.any(dg <= 0):
                    raise SoftplotError("normal matrix singular: an unknown is not observed")
                s = 1.0 / np.sqrt(dg)
                try:
                    cf = scipy.linalg.cho_factor(S * s[:, None] * s[None, :], check_finite=False)
                except np.linalg.LinAlgError as exc:
                    raise SoftplotError(
                        "normal matrix singular: datum or a parameter undetermined"
                    ) from exc
                self._solve_c = lambda b: scipy.linalg.cho_solve(cf, b * s[:, None]) * s[:, None]
                # the whole inverse from the factor (LAPACK potri: ~n^3 / 3 more flops)
                inv, info = scipy.linalg.lapack.dpotri(cf[0], lower=cf[1])
                if info != 0:
                    raise SoftplotError("normal matrix singular: datum or parameter undetermined")
                inv = np.triu(inv) if not cf[1] else np.tril(inv)
                inv = inv + inv.T - np.diag(np.diag(inv))
                self._set_qcc(inv * s[:, None] * s[None, :])
            elif isinstance(S, BandSystem):
                try:
                    self.band = BorderedBand(S)
                except (np.linalg.LinAlgError, ValueError) as exc:
                    raise SoftplotError(
                        "normal matrix singular: datum or a parameter undetermined"
                    ) from exc
                self._solve_c = lambda b: self.band.solve(b)
            else:
                s = 1.0 / np.sqrt(S.diagonal())
                D = scipy.sparse.diags(s)
                lu = scipy.sparse.linalg.splu((D @ S @ D).tocsc(), permc_spec="MMD_AT_PLUS_A")
                self._solve_c = lambda b: lu.solve(b * s[:, None]) * s[:, None]
        else:
            self._Qcc = np.zeros((0, 0))
            self._solve_c = lambda b: np.zeros((0, b.shape[1]))
        self._cross = None
        self._Qpp = None

    def _set_qcc(self, Q: np.ndarray) -> None:
        Q = 0.5 * (Q + Q.T)
        if not np.all(np.isfinite(Q)):
            raise SoftplotError("normal matrix singular: datum or a parameter undetermined")
        self._Qcc = Q

    @property
    def Qcc(self) -> np.ndarray:
        """The whole camera-side block ``S^-1`` (formed on first use for large systems:
        ``n_cam`` solves - prefer :meth:`columns`)."""
        if self._Qcc is None:
            self._set_qcc(self._solve_c(np.eye(self.st.n_cam)))
        return self._Qcc

    @property
    def has_full_qcc(self) -> bool:
        return self._Qcc is not None

    def columns(self, idx) -> np.ndarray:
        """``Qcc[:, idx]`` (n_cam, len(idx)) by solves (or from the formed ``Qcc``)."""
        idx = np.asarray(idx, np.int64)
        if self._Qcc is not None:
            return self._Qcc[:, idx]
        E = np.zeros((self.st.n_cam, idx.size))
        E[idx, np.arange(idx.size)] = 1.0
        return self._solve_c(E)

    def point_blocks_of(self, points) -> np.ndarray:
        """``Q_pp`` (len, 3, 3) of selected points without forming ``Qcc``:
        ``V_j^-1 + sum_{o, o'} Y_o' Qcc[cols_o, cols_o'] Y_o'`` over the point's observations."""
        st = self.st
        out = np.zeros((len(points), 3, 3))
        for i, j in enumerate(points):
            obs = np.flatnonzero(st.obs_point == j)
            cols = st.obs_cols[obs]  # (n, k) with dummy n_cam
            uc = np.unique(cols[cols < st.n_cam])
            Qc = self.columns(uc)[uc]  # (u, u)
            pos = np.searchsorted(uc, np.minimum(cols, st.n_cam - 1))
            valid = cols < st.n_cam
            Yj = self.Y[:, obs, :].transpose(1, 0, 2) * valid[:, :, None]  # (n, k, 3)
            Z = np.zeros((uc.size, 3))
            np.add.at(Z, pos.ravel(), Yj.reshape(-1, 3))
            Q = self.Vinv[j] + Z.T @ Qc @ Z
            Q = 0.5 * (Q + Q.T)
            out[i] = Q * (st.point_free[j][:, None] & st.point_free[j][None, :])
        return out

    def solve(self, rhs_c: np.ndarray, rhs_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Q @ [rhs_c; rhs_p]`` for several right-hand sides.

        Parameters
        ----------
        rhs_c : ndarray, shape (n_cam, q)
        rhs_p : ndarray, shape (n_pts, 3, q)

        Returns
        -------
        x_c : ndarray (n_cam, q), x_p : ndarray (n_pts, 3, q)
        """
        st, lin = self.st, self.lin
        q = rhs_c.shape[1]
        rhs_p = rhs_p * st.point_free[:, :, None]
        # b = rhs_c - W V^-1 rhs_p
        N1 = st.n_cam + 1
        pe = np.minimum(st.pt_ext, max(st.n_pts - 1, 0))
        b = rhs_c.copy()
        xc_cols = []
        for j in range(q):
            if st.n_pts:
                yg = np.einsum("kma,ma->mk", self.Y, rhs_p[pe, :, j])
                yg[st.obs_point < 0] = 0.0
                b[:, j] -= np.bincount(st.obs_cols.ravel(), weights=yg.ravel(), minlength=N1)[
                    : st.n_cam
                ]
        xc = self._solve_c(b) if st.n_cam else np.zeros((0, q))
        for j in range(q):
            xc_cols.append(lin.back_substitute(xc[:, j], self.Vinv, rhs_p[:, :, j]))
        xp = np.stack(xc_cols, axis=2) if q else np.zeros((st.n_pts, 3, 0))
        return xc, xp

    def cross_blocks(self) -> np.ndarray:
        """``Q[cols_o, point_o]`` for every observation, shape (m, k, 3) (zero without point).

        ``Qcp_j = -Qcc W_j V_j^-1``: either one dense product ``Qcc @ [W V^-1]`` (when
        ``n_cam^2 * 3 n_pts`` is moderate) or sums over the pairs of observations of each point.
        """
        if self._cross is not None:
            return self._cross
        st = self.st
        k, N1 = st.k, st.n_cam + 1
        m = st.m
        Qe = np.zeros((N1, N1))
        Qe[: st.n_cam, : st.n_cam] = self.Qcc
        has = st.obs_point >= 0
        if st.n_cam**2 * 3 * st.n_pts <= self.dense_product_limit and N1 * 3 * st.n_pts <= 3e7:
            # one dense product Qcc @ Ytilde, then gather every observation's block
            QY = Qe @ st.tilde(self.Y)
            out = -QY[st._tilde_rows, st._tilde_cols]
            out[~has] = 0.0
        else:
            acc = np.zeros(m * k * 3)
            a, b = st.opair1, st.opair2
            base = np.arange(k * 3)
            for s in range(0, a.size, self.chunk):
                aa, bb = a[s : s + self.chunk], b[s : s + self.chunk]
                ca, cb = st.obs_cols[aa], st.obs_cols[bb]
                Qab = Qe[ca[:, :, None], cb[:, None, :]]  # (n, k, k)
                Yb = self.Y[:, bb, :].transpose(1, 0, 2)  # (n, k, 3)
                contrib = -np.matmul(Qab, Yb)
                idx = (aa[:, None] * (k * 3) + base).ravel()
                acc += np.bincount(idx, weights=contrib.ravel(), minlength=m * k * 3)
            out = acc.reshape(m, k, 3)
        self._cross = out
        return out

    def point_blocks(self) -> np.ndarray:
        """``Q_pp`` per point, shape (n_pts, 3, 3): ``V^-1 - sum_o Y_o' Qcp_o``."""
        if self._Qpp is not None:
            return self._Qpp
        st = self.st
        B = self.cross_blocks()
        t = -np.einsum("kma,mkb->mab", self.Y, B)  # (m,3,3)
        P1 = st.n_pts + 1
        acc = np.stack(
            [np.bincount(st.pt_ext, weights=t[:, i // 3, i % 3], minlength=P1) for i in range(9)],
            axis=1,
        )[: st.n_pts].reshape(st.n_pts, 3, 3)
        Q = self.Vinv + acc
        Q = 0.5 * (Q + Q.transpose(0, 2, 1))
        Q *= st.point_free[:, :, None] & st.point_free[:, None, :]
        self._Qpp = Q
        return Q

    def observation_blocks(self) -> np.ndarray:
        """``J_o Q J_o'`` for every observation, shape (m, d, d) (whitened observation space).

        ``1 - diag`` of it are the redundancy numbers of the observation rows.
        """
        st, lin = self.st, self.lin
        Qe = np.zeros((st.n_cam + 1, st.n_cam + 1))
        Qe[: st.n_cam, : st.n_cam] = self.Qcc
        Jc, Jp = lin.Jc, lin.Jp
        cols = st.obs_cols
        out = np.empty((st.m, st.d, st.d))
        B = self.cross_blocks()
        Qpp = self.point_blocks() if st.n_pts else None
        for s in range(0, st.m, self.chunk):
            sl = slice(s, s + self.chunk)
            c = cols[sl]
            Qoo = Qe[c[:, :, None], c[:, None, :]]
            JcQ = np.einsum("mdk,mkl->mdl", Jc[sl], Qoo)
            q = np.einsum("mdl,mel->mde", JcQ, Jc[sl])
            if st.n_pts:
                x = np.einsum("mdk,mka,mea->mde", Jc[sl], B[sl], Jp[sl])
                q += x + x.transpose(0, 2, 1)
                pe = np.minimum(st.pt_ext[sl], st.n_pts - 1)
                q += np.einsum("mda,mab,meb->mde", Jp[sl], Qpp[pe], Jp[sl])
            out[sl] = q
        return out
