"""The outlier test at marks whose neighbours' prediction extrapolates (corners, the ends of a
strip): the prediction's own error grows with the reach, and a good cross there is kept."""
import numpy as np

from softplot.marks.validation import OUTLIER_K, departure_model, expected_departure


def _departures(seed=7, n=3000):
    """Departures (px) of precise crosses (sigma 0.01-0.03 px) from their neighbours'
    prediction whose error is b = 0.04 px^2 at reach 1 and grows as the reach squared; one
    mark in ten reaches 2x (a corner)."""
    rng = np.random.default_rng(seed)
    sg = rng.uniform(0.01, 0.03, n)
    reach = np.where(rng.random(n) < 0.1, 2.0, 1.0)
    var = 1.5 * sg**2 + 0.04 * reach**2
    dev = np.sqrt(var / 2.0) * np.hypot(*rng.normal(size=(2, n)))
    return dev, sg, reach


def test_departure_model_recovers_the_prediction_term_that_grows_with_the_reach():
    dev, sg, reach = _departures()
    edge = np.zeros(len(dev), bool)
    coef = departure_model(dev, sg, edge, reach=reach)
    assert np.isclose(coef[1, 1], 0.04, rtol=0.12), coef
    exp = expected_departure(coef, sg, edge, reach)
    assert np.isclose(coef[1, 2], 0.04, rtol=0.2), coef
    assert np.allclose(exp, np.sqrt(1.5 * sg**2 + 0.04 * reach**2), rtol=0.12)


def test_good_crosses_where_the_prediction_extrapolates_are_not_outliers():
    """With the reach counted, the corners' good crosses pass the OUTLIER_K test as often as
    a Gaussian allows (exp(-K^2) = 5e-4); without it, one corner in twelve is refused."""
    dev, sg, reach = _departures(seed=11, n=20000)
    edge = np.zeros(len(dev), bool)
    far = reach > 1
    with_reach = expected_departure(departure_model(dev, sg, edge, reach=reach), sg, edge, reach)
    without = expected_departure(departure_model(dev, sg, edge), sg, edge)
    refused_with = np.mean(dev[far] > OUTLIER_K * with_reach[far])
    refused_without = np.mean(dev[far] > OUTLIER_K * without[far])
    assert refused_with < 3e-3, refused_with
    assert refused_without > 0.03, refused_without
