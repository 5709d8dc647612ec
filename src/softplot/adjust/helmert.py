"""Gauss-Helmert model: condition equations between observations and unknowns.

Model (``docs/orientation.md``): ``m`` conditions ``F(x, l + v) = 0`` on ``n`` observations with
standard errors ``sigma`` and ``u`` unknowns. Linearised at the current adjusted observations
``l_hat = l + v0`` and unknowns ``x``::

    A dx + B v + w = 0,   A = dF/dx,  B = dF/dl,  w = F(x, l_hat) - B v0
    M = B Q B',  N = A' M^-1 A,  dx = -N^-1 A' M^-1 w,
    k = -M^-1 (A dx + w),  v = Q B' k          (Q = diag(1 / p))

iterated (re-linearising at the adjusted observations) until ``dx`` and ``v`` settle: the
converged result minimises ``v'Pv`` subject to the exact nonlinear conditions. Statistics as in
:mod:`softplot.adjust.core`, with ``r = m - u_free`` and
``Qvv = Q B' M^-1 (M - A N^-1 A') M^-1 B Q``.

``B`` may be a dense array or a :mod:`scipy.sparse` matrix; when every condition has its own
observations (``M`` diagonal, e.g. one coplanarity condition per point) the solution costs
O(m u^2).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import scipy.linalg
import scipy.sparse

from softplot.adjust.core import (
    Adjustment,
    _build_adjustment,
    _solve_bordered,
    weights_from_sigma,
)
from softplot.adjust.diagnose import DEFAULT_RCOND, check_determined
from softplot.errors import SoftplotError

__all__ = ["gauss_helmert"]


class _MInverse:
    """``M^-1`` applied to vectors/matrices, for diagonal (fast path) or dense ``M``."""

    def __init__(self, B, q):
        self.q = q
        self.diag = None
        self.cho = None
        if scipy.sparse.issparse(B):
            B = scipy.sparse.csr_matrix(B)
            B.sum_duplicates()
            self.rows = np.repeat(np.arange(B.shape[0]), np.diff(B.indptr))
            self.n = B.shape[1]
            if B.nnz == 0 or np.bincount(B.indices, minlength=self.n).max() <= 1:
                # every observation in at most one condition: M is diagonal
                self.diag = np.bincount(
                    self.rows, weights=B.data**2 * q[B.indices], minlength=B.shape[0]
                )
            else:
                M = (B @ scipy.sparse.diags(q) @ B.T).toarray()
                self.cho = scipy.linalg.cho_factor(M)
        else:
            B = np.asarray(B, dtype=float)
            M = (B * q[None, :]) @ B.T
            self.cho = scipy.linalg.cho_factor(M)
        if self.diag is not None and np.any(self.diag <= 0):
            raise SoftplotError("Gauss-Helmert: a condition does not depend on any observation")
        self.B = B

    def __call__(self, y):
        if self.diag is not None:
            return y / (self.diag if y.ndim == 1 else self.diag[:, None])
        return scipy.linalg.cho_solve(self.cho, y)

    def diag_BtMiB(self):
        """Diagonal of ``B' M^-1 B`` (n,)."""
        B = self.B
        if self.diag is not None:
            return np.bincount(
                B.indices, weights=B.data**2 / self.diag[self.rows], minlength=self.n
            )
        Bd = B.toarray() if scipy.sparse.issparse(B) else B
        return np.einsum("ij,ij->j", Bd, self(Bd))

    def BT(self, y):
        """``B' y``."""
        if self.diag is not None and y.ndim == 1:
            return np.bincount(self.B.indices, weights=self.B.data * y[self.rows], minlength=self.n)
        return self.B.T @ y


def gauss_helmert(
    fun: Callable[[np.ndarray, np.ndarray], tuple],
    x0,
    obs,
    sigma=None,
    *,
    names: Sequence[str] | None = None,
    sigma0_prior: float = 1.0,
    fixed=None,
    max_iter: int = 50,
    tol: float = 1e-10,
    alpha0: float = 0.001,
    rcond: float = DEFAULT_RCOND,
    what: str = "adjustment",
    require_convergence: bool = True,
    precision_known: bool | None = None,
) -> Adjustment:
    """Iterated Gauss-Helmert adjustment of condition equations ``F(x, l + v) = 0``.

    Parameters
    ----------
    fun : callable
        ``fun(x, l_hat) -> (F, A, B)``: condition values (m,), ``dF/dx`` (m, u) and ``dF/dl``
        (m, n) - dense or scipy.sparse.
    x0 : array_like, shape (u,)
        Initial unknowns.
    obs : array_like, shape (n,)
        Observations.
    sigma, names, sigma0_prior, fixed, max_iter, tol, alpha0, rcond, what, require_convergence,
    precision_known
        As in :func:`softplot.adjust.least_squares`.

    Returns
    -------
    Adjustment
        ``residuals`` are the corrections ``v`` of the observations (adjusted minus observed).
    """
    x = np.array(x0, dtype=float).ravel()
    u = x.size
    l = np.asarray(obs, dtype=float).ravel()
    n = l.size
    names = tuple(names) if names is not None else tuple(f"x{i}" for i in range(u))
    if len(names) != u:
        raise SoftplotError(f"{what}: {len(names)} names for {u} unknowns")
    fixed = np.zeros(u, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool).ravel()
    free = ~fixed
    free_names = [nm for nm, f in zip(names, free, strict=True) if f]
    p = weights_from_sigma(sigma, n, sigma0_prior)
    q = 1.0 / p
    v = np.zeros(n)
    history = []
    converged = False
    it = 0
    m = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        F, A, B = fun(x, l + v)
        F = np.asarray(F, dtype=float).ravel()
        m = F.size
        A = np.asarray(A, dtype=float).reshape(m, u)[:, free]
        w = F - B @ v
        Mi = _MInverse(B, q)
        MiA = Mi(A)
        N = A.T @ MiA
        if it == 1:
            if m - free.sum() < 0:
                raise SoftplotError(f"{what}: {m} conditions for {int(free.sum())} unknowns")
            check_determined(N, free_names, rcond=rcond, what=what)
        dx, Qxx = _solve_bordered(N, -(MiA.T @ w))
        k = -Mi(A @ dx + w)
        v_new = q * np.asarray(Mi.BT(k)).ravel()
        x[free] += dx
        dv = v_new - v
        v = v_new
        history.append(float(np.sum(p * v**2)))
        scale = np.sqrt(np.clip(np.diag(Qxx), 0.0, None))
        ok_x = np.all((np.abs(dx) <= tol * scale) | (np.abs(dx) <= 1e-14 * np.abs(x[free])))
        ok_v = np.all(np.abs(dv) * np.sqrt(p) <= max(tol, 1e-12))
        if ok_x and ok_v:
            converged = True
            break
    if not converged and require_convergence:
        raise SoftplotError(f"{what}: no convergence after {max_iter} iterations")
    F, A, B = fun(x, l + v)
    A = np.asarray(A, dtype=float).reshape(np.size(F), u)[:, free]
    Mi = _MInverse(B, q)
    MiA = Mi(A)
    N = A.T @ MiA
    _, Qf = _solve_bordered(N, np.zeros(N.shape[0]))
    H = q[:, None] * np.asarray(Mi.BT(MiA))  # Q B' M^-1 A  (n, u)
    qvv = np.clip(q**2 * Mi.diag_BtMiB() - np.sum((H @ Qf) * H, axis=1), 0.0, None)
    r = int(m - free.sum())
    return _build_adjustment(
        names=names, x=x, free=free, Qf=Qf, qvv=qvv, p=p, v=v, r=r, sigma0_prior=sigma0_prior,
        alpha0=alpha0, fixed=fixed, n=n, c=0, it=it, converged=converged, history=history,
        precision_known=sigma is not None if precision_known is None else precision_known,
    )
