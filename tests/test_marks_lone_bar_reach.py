"""A lone bar's position along it is its neighbours' prediction; where that prediction
extrapolates (a corner of a small grid), its reported standard deviation must grow with it."""
import numpy as np

from softplot.marks import grid
from softplot.marks.neighbours import local_fit, local_prediction
from softplot.marks.validation import h_parameter_jacobian, prediction_reach

# a Pentax-like 3 x 3 grid (film mm) at about 3000 dpi, mildly projective
H = np.array([[120.0, 1.5, 3000.0], [-1.2, 119.0, 2500.0], [2e-4, -1e-4, 1.0]])
FILM = np.array([[x, y] for y in (-17.0, 0.0, 17.0) for x in (-23.0, 0.0, 23.0)])
# six two-armed crosses measured in an L; R0C2 (index 2) is the corner they extrapolate to
MEAS = np.array([1, 1, 0, 1, 0, 0, 1, 1, 1], bool)


def _normalised_errors(q, trials=300, noise_px=0.3, use_reach=True):
    """The lone bar's along-bar prediction error over the standard deviation lone_arms gives
    it (the leave-one-out RMS of the measured crosses' residuals, times the reach), pooled
    over noise draws on the measured crosses' positions (pixel system)."""
    rng = np.random.default_rng(5)
    sig = np.ones(MEAS.sum())
    z2 = []
    for _ in range(trials):
        xy = grid.apply_h(H, FILM) + noise_px * rng.standard_normal((9, 2))
        Hm = grid.projective_fit(FILM[MEAS], xy[MEAS])
        r = xy - grid.apply_h(Hm, FILM)
        loo = r[MEAS] - local_prediction(FILM[MEAS], r[MEAS], sigma=sig)
        sd = float(np.sqrt(np.mean(loo**2)))
        if use_reach:
            sd *= prediction_reach(FILM[[q]], FILM[MEAS], Hm, sig)[0]
        target = grid.apply_h(Hm, FILM[[q]]) + local_fit(FILM[[q]], FILM[MEAS], r[MEAS], 16, 2,
                                                          n_sigma=sig)
        e = target[0] - grid.apply_h(H, FILM[[q]])[0]
        z2.append(np.mean(e**2) / sd**2)
    return float(np.sqrt(np.mean(z2)))


def test_a_corner_bar_extrapolated_by_the_model_gets_an_honest_sigma_along():
    without = _normalised_errors(2, use_reach=False)
    honest = _normalised_errors(2)
    assert without > 2.0  # the premise: the leave-one-out RMS alone is far too optimistic
    assert 0.8 < honest < 1.4


def test_the_reach_is_one_where_the_neighbours_surround_the_bar():
    full = np.ones(9, bool)
    full[4] = False
    reach = prediction_reach(FILM[[4]], FILM[full], H, np.ones(8))
    assert abs(reach[0] - 1.0) < 1e-12
    corner = prediction_reach(FILM[[2]], FILM[MEAS], H, np.ones(6))
    assert corner[0] > 1.6


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
