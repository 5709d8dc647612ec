"""A lone bar's position along it is its neighbours' prediction; its reported variance along
the bar is that prediction's (``validation.prediction_cov``: the measured crosses' own errors
sent through it exactly, growing where it extrapolates, e.g. at a corner of a small grid)."""
import numpy as np

from softplot.marks import grid
from softplot.marks.neighbours import local_fit
from softplot.marks.validation import h_parameter_jacobian, prediction_cov

# a Pentax-like 3 x 3 grid (film mm) at about 3000 dpi, mildly projective
H = np.array([[120.0, 1.5, 3000.0], [-1.2, 119.0, 2500.0], [2e-4, -1e-4, 1.0]])
FILM = np.array([[x, y] for y in (-17.0, 0.0, 17.0) for x in (-23.0, 0.0, 23.0)])
# six two-armed crosses measured in an L; R0C2 (index 2) is the corner they extrapolate to
MEAS = np.array([1, 1, 0, 1, 0, 0, 1, 1, 1], bool)
# a 7 x 9 grid with a gap: a cross inside it, surrounded by its neighbours
BIG = np.array([[x, y] for y in np.arange(-15.0, 16.0, 5.0) for x in np.arange(-20.0, 21.0, 5.0)])


def _covs(n, seed):
    """Unequal, correlated covariances (n, 2, 2) px^2 (pixel system) of n crosses."""
    a = 0.2 * np.random.default_rng(seed).standard_normal((n, 2, 2))
    return a @ a.transpose(0, 2, 1) + 0.01 * np.eye(2)


def _prediction_errors(q, film, meas, C, trials=1500, seed=5):
    """The prediction of cross ``q`` from the crosses ``meas`` (the global model fitted to
    them, plus a local quadratic of their residuals: lone_arms' target) minus its truth,
    over noise draws of covariance ``C`` on the measured crosses (pixel system, (trials, 2))."""
    rng = np.random.default_rng(seed)
    L = np.linalg.cholesky(C)
    truth = grid.apply_h(H, film)
    out = []
    for _ in range(trials):
        xy = truth.copy()
        xy[meas] += np.einsum("nij,nj->ni", L, rng.standard_normal((meas.sum(), 2)))
        Hm = grid.projective_fit(film[meas], xy[meas])
        r = xy - grid.apply_h(Hm, film)
        sig = np.sqrt(0.5 * (C[:, 0, 0] + C[:, 1, 1]))
        target = grid.apply_h(Hm, film[[q]]) + local_fit(film[[q]], film[meas], r[meas], 16, 2,
                                                          n_sigma=sig)
        out.append(target[0] - truth[q])
    return np.array(out)


def _normalised(e, C):
    """RMS of the errors ``e`` (trials, 2) along x and y over the standard deviations the
    covariance ``C`` (2, 2) gives them."""
    return np.sqrt(np.mean(e**2, 0) / np.diag(C))


def test_a_corner_bar_extrapolated_by_the_model_gets_an_honest_variance():
    C = _covs(MEAS.sum(), 1)
    e = _prediction_errors(2, FILM, MEAS, C)
    sig = np.sqrt(0.5 * (C[:, 0, 0] + C[:, 1, 1]))
    P = prediction_cov(FILM[[2]], FILM[MEAS], H, sig, C)[0]
    assert np.all(np.abs(_normalised(e, P) - 1.0) < 0.1), _normalised(e, P)
    # the premise: the measured crosses' leave-one-out departures (own noise included) are
    # no measure of an extrapolation; a corner's prediction is far worse than theirs
    rms = np.sqrt(np.mean(np.einsum("nii->ni", C)))
    assert np.all(np.sqrt(np.diag(P)) > 1.5 * rms)


def test_inside_the_grid_the_variance_is_the_neighbours_noise_sent_through():
    keep = np.ones(len(BIG), bool)
    q = 31  # inside, away from the outline
    keep[q] = False
    C = _covs(keep.sum(), 2)
    e = _prediction_errors(q, BIG, keep, C, trials=1000)
    sig = np.sqrt(0.5 * (C[:, 0, 0] + C[:, 1, 1]))
    P = prediction_cov(BIG[[q]], BIG[keep], H, sig, C)[0]
    assert np.all(np.abs(_normalised(e, P) - 1.0) < 0.1), _normalised(e, P)
    # a prediction averages its neighbours' errors: smaller than theirs
    assert np.trace(P) < 0.5 * np.median(np.einsum("nii->n", C))
    corner = prediction_cov(FILM[[2]], FILM[MEAS], H, np.ones(6), _covs(6, 2))[0]
    assert np.trace(P) < np.trace(corner)


def test_a_query_among_the_crosses_is_left_out_of_its_own_prediction():
    """A cross measured whole and fitted again as a lone bar is predicted from the others:
    its own error does not enter (the local fit leaves it out; the model's refit takes a
    1/M share of it)."""
    C = _covs(len(BIG), 3)
    sig = np.ones(len(BIG))
    q = 31
    C2 = C.copy()
    C2[q] *= 100.0
    a = prediction_cov(BIG[[q]], BIG, H, sig, C)[0]
    b = prediction_cov(BIG[[q]], BIG, H, sig, C2)[0]
    assert np.allclose(a, b, rtol=0.05, atol=1e-6)


def test_parameter_jacobian_matches_finite_differences():
    xy = np.random.default_rng(1).uniform(-30, 30, (7, 2))
    J = h_parameter_jacobian(H, xy)
    h = H.ravel()
    for k in range(8):
        step = 1e-6 * max(abs(h[k]), 1e-3)
        Hp = H.copy()
        Hp.flat[k] += step
        num = (grid.apply_h(Hp, xy) - grid.apply_h(H, xy)).ravel() / step
        np.testing.assert_allclose(J[:, k], num, rtol=1e-5, atol=1e-6 * np.abs(J[:, k]).max())
