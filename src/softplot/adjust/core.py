"""Dense weighted least squares: Gauss-Markov (Gauss-Newton) with constraints and statistics.

Model (``docs/orientation.md`` section "Least squares"): observations ``l`` (n,) with standard
errors ``sigma`` (n,), unknowns ``x`` (u,), a function ``f(x)`` with Jacobian ``J = df/dx``::

    l + v = f(x_hat),   weights  p_i = sigma0_prior**2 / sigma_i**2

and optional equality constraints ``g(x) = 0`` (c,) with Jacobian ``G``, solved by the bordered
normal equations::

    [ N  G' ] [dx]   [ J' P (l - f) ]
    [ G  0  ] [ k] = [     -g       ]      N = J' P J

Some unknowns may instead be held fixed (eliminated). Every iteration is a Gauss-Newton step,
halved while the weighted sum of squares grows (unconstrained problems only). Results:

* redundancy ``r = n - u_free + c``;
* ``sigma0 = sqrt(v' P v / r)`` (a posteriori standard error of unit weight; same unit as
  ``sigma0_prior``) - never divided by ``n`` or ``2n``;
* cofactor ``Qxx`` (top-left block of the inverse bordered matrix, ``N^-1`` without
  constraints) and covariance ``sigma0**2 Qxx`` (``sigma0_prior**2 Qxx`` when ``r = 0``);
* residuals ``v = f(x_hat) - l``, their cofactors ``qvv_i = 1/p_i - (J Qxx J')_ii``,
  redundancy numbers ``r_i = p_i qvv_i`` (they sum to ``r``);
* data snooping (:func:`data_snooping`), one test per observation, chosen by what is known:

  - the a priori precision is known (standard errors given): Baarda's w-test,
    ``w_i = v_i / (sigma0_prior sqrt(qvv_i))`` against ``k = Phi^-1(1 - alpha0/2)`` (3.29 for
    ``alpha0 = 0.001``);
  - it is not (unit weights, or standard errors known only relative to each other): Pope's
    (1976) tau test, ``tau_i = v_i / (sigma0_hat sqrt(qvv_i))`` with the a posteriori
    ``sigma0_hat``, against the critical value of the tau distribution with ``r`` degrees of
    freedom, ``sqrt(r) t / sqrt(r - 1 + t^2)``, ``t`` the Student quantile ``t(r-1, 1 -
    alpha0/2)``. ``tau_i`` is a monotone function of the externally studentised residual
    (the residual standardised by the sigma0 of the adjustment without observation ``i``), so
    a blunder that inflates ``sigma0_hat`` does not hide itself.

  ``|statistic| > k`` flags a probable blunder; the largest one is the most likely.
  Observations with ``r_i < 1e-8`` are uncontrolled (statistic ``nan``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from softplot.adjust.diagnose import DEFAULT_RCOND, check_determined
from softplot.errors import SoftplotError

__all__ = [
    "Adjustment",
    "Snooping",
    "SNOOPING_TESTS",
    "data_snooping",
    "snooping_json",
    "least_squares",
    "linear_least_squares",
    "critical_value",
    "tau_critical_value",
    "weights_from_sigma",
]

#: names of the data-snooping tests (``Snooping.test``) and what they test against
SNOOPING_TESTS = {
    "baarda-w": "Baarda's w-test against the a priori sigma0",
    "pope-tau": "Pope's tau test against the a posteriori sigma0",
    "none": "no test (too little redundancy)",
}


def critical_value(alpha0: float = 0.001) -> float:
    """Two-sided normal critical value of Baarda's w-test: 3.29 for ``alpha0 = 0.001``."""
    if not 0.0 < alpha0 < 1.0:
        raise SoftplotError(f"significance level alpha0 must be in (0, 1), got {alpha0}")
    return float(scipy.stats.norm.ppf(1.0 - alpha0 / 2.0))


def tau_critical_value(redundancy: int, alpha0: float = 0.001) -> float:
    """Critical value of Pope's tau test for ``r`` degrees of freedom (nan when r < 2).

    ``tau_c = sqrt(r) t / sqrt(r - 1 + t^2)`` with ``t = t(r - 1, 1 - alpha0/2)`` (Student),
    the two-sided ``alpha0`` quantile of the tau distribution (Pope 1976). It tends to the
    normal critical value as ``r`` grows and is always below ``sqrt(r)``, the largest value a
    single ``tau_i`` can take.
    """
    critical_value(alpha0)  # validates alpha0
    r = int(redundancy)
    if r < 2:
        return float("nan")
    t = float(scipy.stats.t.ppf(1.0 - alpha0 / 2.0, r - 1))
    return float(np.sqrt(r) * t / np.sqrt(r - 1 + t * t))


@dataclass(frozen=True)
class Snooping:
    """Result of :func:`data_snooping`: one test statistic per observation and its verdict.

    Attributes
    ----------
    test : str
        ``"baarda-w"`` (a priori sigma0 known), ``"pope-tau"`` (a posteriori sigma0) or
        ``"none"`` (redundancy too small to locate a blunder).
    alpha0 : float
        Significance level of the test of one observation.
    critical_value : float
        Threshold of ``|statistic|`` (nan for ``"none"``).
    statistic : ndarray, shape (n,)
        ``w_i`` or ``tau_i`` (nan for uncontrolled observations).
    flagged : ndarray of bool, shape (n,)
        ``|statistic| > critical_value``.
    sigma0 : float
        The standard error of unit weight the residuals were standardised with (a priori for
        the w-test, a posteriori for the tau test).
    redundancy : int
    """

    test: str
    alpha0: float
    critical_value: float
    statistic: np.ndarray
    flagged: np.ndarray
    sigma0: float
    redundancy: int

    def ranked(self, labels=None) -> list:
        """Flagged observations (or their labels), most likely blunder first.

        Parameters
        ----------
        labels : sequence (n,), optional
            A label per observation (e.g. the point name of every coordinate); observations
            sharing a label are one candidate, ranked by its largest ``|statistic|``.

        Returns
        -------
        list
            Labels (or observation indices without ``labels``), by decreasing ``|statistic|``.
        """
        idx = np.nonzero(self.flagged)[0]
        order = idx[np.argsort(-np.abs(self.statistic[idx]), kind="stable")]
        if labels is None:
            return [int(i) for i in order]
        if len(labels) != self.flagged.size:
            raise SoftplotError(
                f"data snooping: {len(labels)} labels for {self.flagged.size} observations"
            )
        return list(dict.fromkeys(_plain(labels[i]) for i in order))

    def blunders(self, labels=None) -> list:
        """Alias of :meth:`ranked`: the names of the flagged observations, most likely first."""
        return self.ranked(labels)

    def describe(self) -> str:
        """One line naming the test and its critical value (for text reports)."""
        if self.test == "baarda-w":
            return (
                f"Baarda's w-test, a priori sigma0 = {self.sigma0:.4g}, alpha0 = {self.alpha0:g}, "
                f"|w| > {self.critical_value:.2f}"
            )
        if self.test == "pope-tau":
            return (
                f"Pope's tau test, a posteriori sigma0 = {self.sigma0:.4g} (a priori precision "
                f"not given), r = {self.redundancy}, alpha0 = {self.alpha0:g}, "
                f"|tau| > {self.critical_value:.2f}"
            )
        return f"no blunder test: redundancy r = {self.redundancy} is too small to locate one"

    def to_json(self) -> dict:
        """``{"test", "critical_value", "alpha0", "sigma0", "redundancy"}`` (nan -> None)."""
        def fin(x):
            return float(x) if np.isfinite(x) else None

        return {
            "test": self.test,
            "critical_value": fin(self.critical_value),
            "alpha0": float(self.alpha0),
            "sigma0": fin(self.sigma0),
            "redundancy": int(self.redundancy),
        }


def _plain(x):
    """A numpy scalar label as the Python object (str, int) it stands for."""
    return x.item() if isinstance(x, np.generic) else x


def snooping_json(snooping: Snooping, labels=None) -> dict:
    """The ``blunders`` and ``snooping_test`` keys of an adjustment's JSON.

    ``blunders``: the flagged labels, most likely first (:meth:`Snooping.ranked`);
    ``snooping_test``: :meth:`Snooping.to_json`.
    """
    return {"blunders": snooping.ranked(labels), "snooping_test": snooping.to_json()}


def data_snooping(
    residuals,
    qvv,
    weights,
    redundancy: int,
    *,
    sigma0_prior: float | None = None,
    alpha0: float = 0.001,
) -> Snooping:
    """Test every observation for a blunder: Baarda's w-test or Pope's tau test.

    Parameters
    ----------
    residuals : array_like, shape (n,)
        ``v`` (adjusted minus observed), unit of the observations.
    qvv : array_like, shape (n,)
        Diagonal cofactors of the residuals (same scale as ``1 / weights``).
    weights : array_like, shape (n,)
        ``p_i`` (0 for an observation that does not take part).
    redundancy : int
        ``r`` of the adjustment.
    sigma0_prior : float, optional
        The a priori standard error of unit weight when it is KNOWN (the observations'
        standard errors were given): Baarda's w-test. None: the precision is not known (unit
        weights, or standard errors known only relative to each other): Pope's tau test
        against the a posteriori ``sigma0_hat = sqrt(v'Pv / r)``.
    alpha0 : float
        Significance level of the test of one observation.

    Returns
    -------
    Snooping
        Test ``"none"`` (nothing flagged) when ``r = 0`` (w) or ``r < 2`` (tau).
    """
    v = np.asarray(residuals, dtype=float).ravel()
    q = np.asarray(qvv, dtype=float).ravel()
    p = np.asarray(weights, dtype=float).ravel()
    if not (v.size == q.size == p.size):
        raise SoftplotError(
            f"data snooping: {v.size} residuals, {q.size} cofactors and {p.size} weights"
        )
    r = int(redundancy)
    ri = np.clip(p * q, 0.0, 1.0)
    controlled = ri > 1e-8
    k_w = critical_value(alpha0)
    if sigma0_prior is not None:
        s0 = float(sigma0_prior)
        if not (np.isfinite(s0) and s0 > 0):
            raise SoftplotError(f"data snooping: a priori sigma0 must be > 0, got {s0}")
        test, k = ("baarda-w", k_w) if r > 0 else ("none", float("nan"))
    else:
        vtpv = float(np.sum(p * v**2))
        s0 = float(np.sqrt(vtpv / r)) if r > 0 else float("nan")
        k = tau_critical_value(r, alpha0)
        test = "pope-tau" if np.isfinite(k) else "none"
    with np.errstate(invalid="ignore", divide="ignore"):
        if test == "none":
            stat = np.full(v.size, np.nan)
        elif s0 > 0:
            stat = np.where(controlled, v / (s0 * np.sqrt(q)), np.nan)
        else:  # exact fit: nothing to test against, nothing departs
            stat = np.where(controlled, 0.0, np.nan)
    flagged = np.abs(np.nan_to_num(stat, nan=0.0)) > (k if np.isfinite(k) else np.inf)
    return Snooping(
        test=test,
        alpha0=float(alpha0),
        critical_value=float(k),
        statistic=stat,
        flagged=flagged,
        sigma0=s0,
        redundancy=r,
    )


def weights_from_sigma(sigma, n: int, sigma0_prior: float = 1.0) -> np.ndarray:
    """Weights ``p_i = sigma0_prior**2 / sigma_i**2`` (unit weights when ``sigma`` is None)."""
    if sigma is None:
        return np.ones(n)
    s = np.broadcast_to(np.asarray(sigma, dtype=float), (n,))
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise SoftplotError("standard errors of the observations must be finite and > 0")
    return (sigma0_prior / s) ** 2


@dataclass
class Adjustment:
    """Result of a least-squares adjustment (Gauss-Markov or Gauss-Helmert).

    Attributes
    ----------
    names : tuple of str
        Unknowns in order.
    x : ndarray, shape (u,)
        Estimates (fixed unknowns keep their given value).
    cofactor : ndarray, shape (u, u)
        ``Qxx`` (rows/columns of fixed unknowns are zero).
    sigma0 : float
        A posteriori standard error of unit weight ``sqrt(v'Pv / r)`` (nan when r = 0).
    sigma0_prior : float
        A priori standard error of unit weight.
    redundancy : int
        ``r = n - u_free + c``.
    residuals : ndarray, shape (n,)
        ``v`` (adjusted minus observed), unit of the observations.
    qvv : ndarray, shape (n,)
        Diagonal cofactors of the residuals.
    redundancy_numbers : ndarray, shape (n,)
        ``r_i = p_i qvv_i`` (sum = r).
    standardized : ndarray, shape (n,)
        The statistic of data snooping: Baarda's ``w_i`` (a priori precision known) or Pope's
        ``tau_i`` (it is not; see :attr:`snooping`); nan for uncontrolled observations.
    critical_value : float
        Threshold of that test.
    alpha0 : float
        Significance level of that test.
    flagged : ndarray of bool, shape (n,)
        ``|standardized_i| > critical_value``.
    fixed : ndarray of bool, shape (u,)
        Unknowns held fixed.
    n_obs, n_constraints : int
    iterations : int
    converged : bool
    history : list of float
        ``v'Pv`` after every iteration.
    weights : ndarray, shape (n,)
    snooping : Snooping
        The data-snooping test used (its name, critical value, statistic and flags).
    """

    names: tuple
    x: np.ndarray
    cofactor: np.ndarray
    sigma0: float
    sigma0_prior: float
    redundancy: int
    residuals: np.ndarray
    qvv: np.ndarray
    redundancy_numbers: np.ndarray
    standardized: np.ndarray
    critical_value: float
    alpha0: float
    flagged: np.ndarray
    fixed: np.ndarray
    n_obs: int
    n_constraints: int
    iterations: int
    converged: bool
    weights: np.ndarray
    history: list = field(default_factory=list)
    snooping: Snooping | None = None

    @property
    def snooping_test(self) -> str:
        """``"baarda-w"``, ``"pope-tau"`` or ``"none"`` (see :func:`data_snooping`)."""
        return self.snooping.test if self.snooping is not None else "baarda-w"

    def blunders(self, labels=None) -> list:
        """Flagged observations (or their ``labels``), most likely blunder first."""
        return self.snooping.ranked(labels)

    @property
    def vtpv(self) -> float:
        """Weighted sum of squared residuals ``v'Pv``."""
        return float(np.sum(self.weights * self.residuals**2))

    @property
    def n_unknowns(self) -> int:
        """Number of free unknowns."""
        return int(np.count_nonzero(~self.fixed))

    @property
    def sigma0_used(self) -> float:
        """The sigma0 that scales the covariance (a posteriori, or a priori when r = 0)."""
        return self.sigma0 if self.redundancy > 0 else self.sigma0_prior

    @property
    def covariance(self) -> np.ndarray:
        """Covariance of the unknowns ``sigma0**2 Qxx``, shape (u, u)."""
        return self.sigma0_used**2 * self.cofactor

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the unknowns, shape (u,)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the unknowns (0 on rows of fixed unknowns), shape (u, u)."""
        s = self.std
        with np.errstate(invalid="ignore", divide="ignore"):
            R = self.covariance / np.outer(s, s)
        return np.where(np.outer(s, s) > 0, R, 0.0)

    @property
    def global_test_p(self) -> float:
        """p-value of the global test ``v'Pv / sigma0_prior**2 ~ chi2(r)`` (nan when r = 0)."""
        if self.redundancy <= 0:
            return float("nan")
        return float(scipy.stats.chi2.sf(self.vtpv / self.sigma0_prior**2, self.redundancy))

    def index(self, name: str) -> int:
        """Column of unknown ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise SoftplotError(f"no unknown named {name!r}") from None

    def value(self, name: str) -> float:
        """Estimate of unknown ``name``."""
        return float(self.x[self.index(name)])

    def std_of(self, name: str) -> float:
        """Standard deviation of unknown ``name``."""
        return float(self.std[self.index(name)])

    def summary(self) -> str:
        """Convergence and precision report: unknowns with std, sigma0, r, flagged observations."""
        head = (
            f"{'converged' if self.converged else 'NOT converged'} after {self.iterations} "
            f"iteration(s); n = {self.n_obs}, u = {self.n_unknowns}, c = {self.n_constraints}, "
            f"r = {self.redundancy}; sigma0 = {self.sigma0:.6g} (a priori {self.sigma0_prior:.6g})"
        )
        lines = [head]
        for nm, x, s, f in zip(self.names, self.x, self.std, self.fixed, strict=True):
            lines.append(f"  {nm:<16}{x:>20.10g}  " + ("fixed" if f else f"+- {s:.4g}"))
        k = self.blunders()
        sym = "tau" if self.snooping_test == "pope-tau" else "w"
        lines.append(
            f"data snooping ({self.snooping.describe()}): "
            + (", ".join(f"obs {i} ({sym} = {self.standardized[i]:.2f})" for i in k[:10])
               or "none")
        )
        return "\n".join(lines)

    def sub_covariance(self, names: Sequence[str]) -> np.ndarray:
        """Covariance block of the unknowns ``names`` (in that order)."""
        idx = [self.index(n) for n in names]
        return self.covariance[np.ix_(idx, idx)]


def _gauss_markov_qvv(J, Qxx, p):
    """Residual cofactors qvv of a Gauss-Markov model (J, Qxx over the free unknowns)."""
    with np.errstate(divide="ignore"):
        qll = np.where(p > 0, 1.0 / p, np.inf)
    h = np.sum((J @ Qxx) * J, axis=1)
    return np.clip(qll - h, 0.0, None)


def _build_adjustment(
    *, names, x, free, Qf, qvv, p, v, r, sigma0_prior, alpha0, fixed, n, c, it, converged,
    history, precision_known=True,
) -> Adjustment:
    """The :class:`Adjustment` at the solution from the free-unknown cofactors ``Qf`` and qvv.

    Shared by the Gauss-Markov (:func:`least_squares`) and Gauss-Helmert models: sigma0 from
    ``v'Pv / r``, data snooping (:func:`data_snooping`; the w-test when ``precision_known``,
    else the tau test), and ``Qf`` embedded into the full ``(u, u)`` cofactor matrix
    (zero rows/columns for fixed unknowns).
    """
    vtpv = float(np.sum(p * v**2))
    sigma0 = float(np.sqrt(vtpv / r)) if r > 0 else float("nan")
    ri = np.clip(p * qvv, 0.0, 1.0)
    sn = data_snooping(
        v, qvv, p, r, sigma0_prior=sigma0_prior if precision_known else None, alpha0=alpha0
    )
    u = x.size
    Q = np.zeros((u, u))
    Q[np.ix_(free, free)] = Qf
    return Adjustment(
        names=names,
        x=x,
        cofactor=Q,
        sigma0=sigma0,
        sigma0_prior=float(sigma0_prior),
        redundancy=r,
        residuals=v,
        qvv=qvv,
        redundancy_numbers=ri,
        standardized=sn.statistic,
        critical_value=sn.critical_value,
        alpha0=float(alpha0),
        flagged=sn.flagged,
        fixed=fixed,
        n_obs=n,
        n_constraints=c,
        iterations=it,
        converged=converged,
        weights=p,
        history=history,
        snooping=sn,
    )


def _solve_bordered(N, b, G=None, g=None):
    """Solve the (bordered) normal equations in unit-diagonal scaling; return dx and Qxx."""
    u = N.shape[0]
    d = np.sqrt(np.diag(N))
    s = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
    Ns = N * s[:, None] * s[None, :]
    bs = b * s
    if G is None or G.shape[0] == 0:
        try:
            Qs = np.linalg.inv(Ns)
        except np.linalg.LinAlgError as exc:  # pragma: no cover - caught by check_determined
            raise SoftplotError("normal equations are singular") from exc
        dx = Qs @ bs
        return dx * s, Qs * s[:, None] * s[None, :]
    c = G.shape[0]
    Gs = G * s[None, :]
    K = np.zeros((u + c, u + c))
    K[:u, :u] = Ns
    K[:u, u:] = Gs.T
    K[u:, :u] = Gs
    try:
        Ki = np.linalg.inv(K)
    except np.linalg.LinAlgError as exc:
        msg = "bordered normal equations are singular (dependent constraints?)"
        raise SoftplotError(msg) from exc
    sol = Ki @ np.r_[bs, -g]
    Qs = Ki[:u, :u]
    return sol[:u] * s, Qs * s[:, None] * s[None, :]


def least_squares(
    fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    x0,
    obs,
    sigma=None,
    *,
    names: Sequence[str] | None = None,
    sigma0_prior: float = 1.0,
    fixed=None,
    constraints: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    max_iter: int = 50,
    tol: float = 1e-10,
    alpha0: float = 0.001,
    rcond: float = DEFAULT_RCOND,
    what: str = "adjustment",
    require_convergence: bool = True,
    precision_known: bool | None = None,
) -> Adjustment:
    """Nonlinear weighted least squares (Gauss-Markov model, Gauss-Newton iterations).

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (f, J)``: model values (n,) and Jacobian (n, u) at ``x``.
    x0 : array_like, shape (u,)
        Initial values.
    obs : array_like, shape (n,)
        Observations ``l``.
    sigma : float or array_like (n,), optional
        Standard errors of the observations (unit weights if None).
    names : sequence of str, optional
        Names of the unknowns (used in the singularity error and the result).
    sigma0_prior : float
        A priori standard error of unit weight; weights ``p = sigma0_prior**2 / sigma**2``.
    fixed : array_like of bool (u,), optional
        Unknowns held at their initial value (eliminated).
    constraints : callable, optional
        ``constraints(x) -> (g, G)``: values (c,) and Jacobian (c, u) of ``g(x) = 0``.
    max_iter : int
        Maximum number of Gauss-Newton iterations.
    tol : float
        Convergence when every step is below ``tol`` times the a priori standard deviation of
        its unknown, or below ``1e-14`` of its magnitude.
    alpha0 : float
        Significance level of Baarda's w-test.
    rcond : float
        Rank threshold (see :func:`softplot.adjust.diagnose.check_determined`).
    what : str
        Name of the problem in error messages.
    require_convergence : bool
        Raise :class:`SoftplotError` when not converged after ``max_iter``.
    precision_known : bool, optional
        Whether ``sigma`` and ``sigma0_prior`` state the observations' precision (Baarda's
        w-test) or only their relative weights (Pope's tau test against the a posteriori
        sigma0). Default: known when ``sigma`` is given, not known for unit weights.

    Returns
    -------
    Adjustment

    Raises
    ------
    UndeterminedError
        The normal matrix at the initial values is singular or ill-conditioned; the message
        names the unknowns that are not determined.
    """
    x = np.array(x0, dtype=float).ravel()
    u = x.size
    obs = np.asarray(obs, dtype=float).ravel()
    n = obs.size
    names = tuple(names) if names is not None else tuple(f"x{i}" for i in range(u))
    if len(names) != u:
        raise SoftplotError(f"{what}: {len(names)} names for {u} unknowns")
    fixed = np.zeros(u, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool).ravel()
    free = ~fixed
    free_names = [nm for nm, f in zip(names, free, strict=True) if f]
    p = weights_from_sigma(sigma, n, sigma0_prior)

    def evaluate(xx):
        f, J = fun(xx)
        f = np.asarray(f, dtype=float).ravel()
        J = np.asarray(J, dtype=float).reshape(n, u)
        if f.size != n:
            raise SoftplotError(f"{what}: model returned {f.size} values for {n} observations")
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(J))):
            raise SoftplotError(f"{what}: the model is not finite at the current unknowns")
        return f, J

    f, J = evaluate(x)
    c = 0
    history = []
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - `it` reported after the loop
        Jf = J[:, free]
        lres = obs - f
        N = Jf.T @ (p[:, None] * Jf)
        b = Jf.T @ (p * lres)
        G = g = None
        if constraints is not None:
            g, Gfull = constraints(x)
            g = np.asarray(g, dtype=float).ravel()
            G = np.asarray(Gfull, dtype=float).reshape(g.size, u)[:, free]
            c = g.size
        if it == 1:
            if n - free.sum() + c < 0:
                raise SoftplotError(
                    f"{what}: {n} observations and {c} constraints for {int(free.sum())} unknowns"
                )
            check_determined(N, free_names, G, rcond=rcond, what=what)
        dx, Qxx = _solve_bordered(N, b, G, g)
        vtpv = float(np.sum(p * lres**2))
        t = 1.0
        for _ in range(30):
            xt = x.copy()
            xt[free] += t * dx
            try:
                ft, Jt = evaluate(xt)
            except SoftplotError:
                if constraints is not None:
                    raise
                t *= 0.5
                continue
            vt = float(np.sum(p * (obs - ft) ** 2))
            if constraints is not None or vt <= vtpv * (1 + 1e-9) + 1e-24 * n:
                break
            t *= 0.5
        else:
            raise SoftplotError(f"{what}: no step reduces the sum of squares (bad start?)")
        x, f, J = xt, ft, Jt
        history.append(vt)
        step = np.abs(t * dx)
        scale = np.sqrt(np.clip(np.diag(Qxx), 0.0, None))
        if np.all((step <= tol * scale) | (step <= 1e-14 * np.abs(x[free]))):
            converged = True
            break
    if not converged and require_convergence:
        raise SoftplotError(f"{what}: no convergence after {max_iter} iterations")
    # statistics at the solution
    Jf = J[:, free]
    N = Jf.T @ (p[:, None] * Jf)
    G = None
    if constraints is not None:
        g, Gfull = constraints(x)
        G = np.asarray(Gfull, dtype=float).reshape(np.size(g), u)[:, free]
        c = G.shape[0]
    _, Qf = _solve_bordered(N, np.zeros(N.shape[0]), G, np.zeros(c) if G is not None else None)
    v = f - obs
    r = int(n - free.sum() + c)
    qvv = _gauss_markov_qvv(Jf, Qf, p)
    return _build_adjustment(
        names=names, x=x, free=free, Qf=Qf, qvv=qvv, p=p, v=v, r=r, sigma0_prior=sigma0_prior,
        alpha0=alpha0, fixed=fixed, n=n, c=c, it=it, converged=converged, history=history,
        precision_known=sigma is not None if precision_known is None else precision_known,
    )


def linear_least_squares(A, l, sigma=None, **kwargs) -> Adjustment:
    """Linear Gauss-Markov model ``l + v = A x`` (one step; same options as least_squares).

    Parameters
    ----------
    A : array_like, shape (n, u)
        Design matrix.
    l : array_like, shape (n,)
        Observations.
    sigma : float or array_like (n,), optional
        Standard errors of the observations.
    **kwargs
        Passed to :func:`least_squares` (names, sigma0_prior, fixed, constraints, alpha0, ...).
    """
    A = np.asarray(A, dtype=float)
    if A.ndim != 2:
        raise SoftplotError(f"design matrix must be 2-D, got shape {A.shape}")
    x0 = kwargs.pop("x0", np.zeros(A.shape[1]))
    return least_squares(lambda x: (A @ x, A), x0, l, sigma, **kwargs)
