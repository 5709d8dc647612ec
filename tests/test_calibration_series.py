"""Test-field calibration: single calibration and series repeatability (Preuss's tables)."""

from __future__ import annotations

import numpy as np

from softplot.orientation.calibration import calibrate, calibrate_series, subset_photos
from softplot.synthetic.testfield import make_series, make_testfield


def test_calibration_from_scratch_with_fixed_unknowns():
    """No exterior approximations; k2..b2 held at their certificate values (zero)."""
    net = make_testfield(n_photos=16, seed=21)
    d = net.to_bundle_data(free=())
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    res = calibrate(d, free=("c", "x0", "y0", "k1"))
    err_um = (res.intrinsics[0, :3] - net.intr_true[0, :3]) * 1000
    assert np.all(np.abs(err_um) < 4 * res.intrinsics_std[0, :3] * 1000 + 1e-9)
    assert np.all(res.intrinsics_std[0, 4:] == 0)  # held constant
    assert np.all(res.intrinsics[0, 4:] == 0)


def test_series_repeatability_matches_the_true_spread():
    net = make_series(n_series=4, photos_per_series=12, spread_um=(8.0, 10.0, 7.0), seed=3)
    d = net.to_bundle_data(free=("c", "x0", "y0", "k1"))
    sr = calibrate_series(d, net.info["series"], free=("c", "x0", "y0", "k1"))
    assert sr.labels == ["S1", "S2", "S3", "S4"]
    truth = net.info["series_truth"][:, [1, 2, 0]]  # x0, y0, c
    t = sr.table()
    # every series recovers its own interior orientation to its precision (< 1.5 um)
    assert np.all(np.abs(t[:, :, 0] - truth) < np.maximum(4 * t[:, :, 1], 1e-4))
    assert np.all(t[:, :, 1] < 1.5e-3)
    # the repeatability is the spread of the true values, not the noise
    assert np.allclose(sr.std(), truth.std(axis=0, ddof=1), atol=1.5e-3)
    assert np.allclose(sr.mean(), truth.mean(axis=0), atol=1.0e-3)
    js = sr.to_json()
    assert set(js["repeatability_std"]) == {"x0", "y0", "c"} and len(js["series"]) == 4
    assert "repeatability" in sr.text()


def test_subset_keeps_only_the_photos_observations():
    net = make_testfield(n_photos=6, seed=1)
    d = net.to_bundle_data()
    s = subset_photos(d, [1, 3])
    assert s.photo_names == [d.photo_names[1], d.photo_names[3]]
    assert s.obs_photo.size == int(np.sum(np.isin(d.obs_photo, [1, 3])))
    assert set(np.unique(s.obs_photo)) == {0, 1}
