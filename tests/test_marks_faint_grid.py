"""A faint grid judged as a whole (:mod:`softplot.marks.faint_grid`): crosses that each fail
the acceptance tests over a strong texture, accepted together where they lie on a projective
grid, against exact synthetic truth; fits to the noise of crosses below detection stay
refused."""

import numpy as np


def test_grid_departure_is_the_rms_off_a_projective_grid_per_spare_coordinate():
    """Nodes mapped by an exact projective transform depart by nothing; the centre node of
    3 x 3 moved by d px departs by d sqrt(1 - h) / sqrt(2 n - 8): the fitted grid absorbs
    the share h (under a half) of its move, the 10 spare coordinates share the rest."""
    from softplot.marks import grid
    from softplot.marks.faint_grid import grid_departure

    film = np.array([[x, y] for y in (-17.0, 0.0, 17.0) for x in (-23.0, 0.0, 23.0)])
    H = np.array([[10.5, 0.3, 700.0], [-0.2, -10.4, 600.0], [2e-4, -1e-4, 1.0]])
    xy = grid.apply_h(H, film)
    assert grid_departure(film, xy) < 1e-6
    moved = xy.copy()
    moved[4] += (2.0, 0.0)
    dep = grid_departure(film, moved)
    assert np.sqrt(0.5) * 2.0 / np.sqrt(10.0) < dep < 2.0 / np.sqrt(10.0)


def test_a_faint_grid_has_crosses_of_one_sign_and_alike_contrast():
    """Contrasts of the marks' sign within the spread allowed are alike; one fit of the other
    sign (texture at a node), the other sign expected, or a spread of 1.7 times the limit are
    not."""
    from softplot.marks.faint_grid import FAINT_GRID_GAIN_SPREAD, alike_contrast

    rng = np.random.default_rng(5)
    g = 0.1 * (1.0 + 0.5 * FAINT_GRID_GAIN_SPREAD * rng.standard_normal(9))
    assert alike_contrast(g, +1)
    assert not alike_contrast(g, -1)
    assert alike_contrast(-g, -1)
    flipped = g.copy()
    flipped[4] = -0.05
    assert not alike_contrast(flipped, +1)
    wide = 0.1 * (1.0 + 1.5 * FAINT_GRID_GAIN_SPREAD * np.linspace(-1.5, 1.5, 9))
    assert np.all(wide > 0) and not alike_contrast(wide, +1)


def test_a_blurred_faint_grid_over_a_texture_is_measured_as_a_whole(monkeypatch):
    """Sweep render 364 (Pentax 645, 3 x 3 crosses of contrast 0.13 blurred by 2.4 px, lines
    0.76x and arms 1.48x the certificate's, over a texture): every cross correlates 0.2-0.45
    with its fit and is refused one by one (no result); fitted alike with the global model's
    affine they lie on a projective grid, and all nine are measured with their own row and
    column, none gross, with a precision that covers their errors."""
    from softplot.marks import faint_grid
    from softplot.synthetic.sweep import make_case, run_case

    case = make_case(364)
    assert case.camera == "pentax-645" and "blur>1.5px" in case.conditions
    with monkeypatch.context() as mp:
        mp.setattr(faint_grid, "FAINT_GRID_K", 0.0)
        before, _ = run_case(case)
    assert not before.result and before.visible == 9
    sc, det = run_case(case)
    assert sc.result, sc.error
    assert not sc.wrong and not sc.claimed and not sc.gross
    assert sc.measured == sc.visible == 9
    err = np.sqrt(np.mean(sc.err2))
    assert err < 1.5  # px per axis, rms (the texture's share: about twice the bound)
    assert 0.5 < np.sqrt(np.mean(sc.z2)) < 1.5  # the errors are of the sigmas' size
    # the user is told the crosses hold only together
    assert any("too faint to hold one by one" in w for w in det.warnings), det.warnings
    assert "a faint grid" in det.summary()


def test_noise_fits_of_crosses_below_detection_are_no_faint_grid():
    """Sweep render 164 (crosses below detection, matched-filter signal-to-noise 4.8): its
    lattice's fits lie on a projective grid as well as their precision says (1.8 px each, a
    contrast to noise of 2.5): too imprecise for a faint grid, and the scan stays refused."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, _ = run_case(make_case(164))
    assert not sc.result
    assert not sc.claimed and not sc.claimed_below
