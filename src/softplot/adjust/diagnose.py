"""Rank diagnosis of normal equations: which unknowns are not determined.

A singular or ill-conditioned adjustment must not return numbers: it raises
:class:`UndeterminedError`, whose one-line message names the unknowns involved in every
(near-)null direction of the normal matrix. The diagnosis works on the normal matrix scaled to
unit diagonal (so that unknowns of different units - metres, radians, a scale - compare), and,
with equality constraints ``G dx = 0``, on the normal matrix restricted to the null space of
``G`` (a datum fixed by constraints is determined).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from softplot.errors import SoftplotError

__all__ = ["UndeterminedError", "undetermined_directions", "check_determined", "DEFAULT_RCOND"]

#: an eigenvalue of the unit-diagonal normal matrix below ``DEFAULT_RCOND * largest`` counts as
#: zero: the reciprocal condition number at which float64 loses all but ~4 significant digits
DEFAULT_RCOND = 1e-12


class UndeterminedError(SoftplotError):
    """The adjustment is singular or ill-conditioned; ``.names`` lists the undetermined unknowns.

    Attributes
    ----------
    names : tuple of str
        Unknowns taking part in a (near-)null direction of the normal matrix.
    directions : ndarray, shape (k, u)
        The null directions in the (unit-diagonal scaled) parameter space, one per row.
    """

    def __init__(self, message: str, names=(), directions=None):
        super().__init__(message)
        self.names = tuple(names)
        self.directions = directions


def undetermined_directions(N, G=None, rcond: float = DEFAULT_RCOND):
    """Null directions of ``N`` (restricted to ``G dx = 0``), in unit-diagonal scaling.

    Parameters
    ----------
    N : ndarray, shape (u, u)
        Normal matrix ``J' P J``.
    G : ndarray, shape (c, u), optional
        Jacobian of equality constraints.
    rcond : float
        Relative eigenvalue threshold.

    Returns
    -------
    directions : ndarray, shape (k, u)
        Unit vectors (scaled parameter space) spanning the near-null space; ``k = 0`` when the
        system is determined.
    rcond_est : float
        Smallest / largest eigenvalue of the scaled (restricted) normal matrix.
    """
    N = np.asarray(N, dtype=float)
    u = N.shape[0]
    d = np.sqrt(np.clip(np.diag(N), 0.0, None))
    zero = d <= 1e-300
    s = np.where(zero, 1.0, 1.0 / np.where(zero, 1.0, d))
    Ns = N * s[:, None] * s[None, :]
    if G is not None and np.size(G):
        Gs = np.asarray(G, dtype=float) * s[None, :]
        Z = scipy.linalg.null_space(Gs)
    else:
        Z = np.eye(u)
    if Z.shape[1] == 0:
        return np.zeros((0, u)), 1.0
    R = Z.T @ Ns @ Z
    ev, V = np.linalg.eigh(0.5 * (R + R.T))
    top = max(float(ev[-1]), 1e-300)
    small = ev <= rcond * top
    dirs = (Z @ V[:, small]).T
    rc = float(max(ev[0], 0.0) / top)
    return dirs, rc


def check_determined(N, names, G=None, rcond: float = DEFAULT_RCOND, what: str = "adjustment"):
    """Raise :class:`UndeterminedError` naming the unknowns if ``N`` is (near-)singular.

    Parameters
    ----------
    N : ndarray, shape (u, u)
        Normal matrix.
    names : sequence of str, length u
        Names of the unknowns, in column order.
    G : ndarray, shape (c, u), optional
        Equality-constraint Jacobian (directions it fixes are not a defect).
    rcond : float
        Relative eigenvalue threshold (see :data:`DEFAULT_RCOND`).
    what : str
        Name of the problem, for the message.
    """
    dirs, rc = undetermined_directions(N, G, rcond)
    if dirs.shape[0] == 0:
        return
    names = list(names)
    mag = np.abs(dirs)
    involved = np.zeros(len(names), dtype=bool)
    for row in mag:
        involved |= row >= 0.1 * row.max()
    bad = [n for n, b in zip(names, involved, strict=True) if b]
    shown = ", ".join(bad[:12]) + (f" and {len(bad) - 12} more" if len(bad) > 12 else "")
    raise UndeterminedError(
        f"{what} is singular or ill-conditioned (rank defect {dirs.shape[0]}, "
        f"reciprocal condition {rc:.1e}): not determined: {shown}",
        bad,
        dirs,
    )
