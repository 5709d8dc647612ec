"""The scene under the crosses (issue 3, point 6 on busy scenes): the joint scene estimate of
:mod:`softplot.marks.scene_tv`, the ``scene=`` models of :func:`softplot.marks.detect` and the
automatic choice between them."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.io import Scan
from softplot.marks import detect, kernels, scene_tv
from softplot.marks.detect import DetectionError
from softplot.synthetic import ScanSpec, render_scan


def _errors(det, truth):
    """Measured minus true position (px) of the visible measured crosses, (M, 2)."""
    tm = {m["name"]: m for m in truth["marks"]}
    return np.array([det.xy[i] - (tm[n]["x"], tm[n]["y"]) for i, n in enumerate(det.name)
                     if det.status[i] == "measured" and tm[n]["visible"]])


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_scene_tv_kernel_matches_numpy():
    rng = np.random.default_rng(4)
    n, h, w = 4, 33, 29
    g = rng.random((n, h, w)).astype(np.float32)
    T = (0.95 * rng.random((n, h, w))).astype(np.float32)
    B0 = rng.random((n, h, w)).astype(np.float32)
    level = rng.random(n)
    mu = np.array([0.01, 0.03, 0.1, 0.3])
    a = scene_tv.deconv_tv(g, T, level, B0, mu, 1.1, 15, compiled=True)
    b = scene_tv.deconv_tv(g, T, level, B0, mu, 1.1, 15, compiled=False)
    for x, y in zip(a, b, strict=True):
        assert x.shape == (n, h, w)
        assert np.abs(x - y).max() < 2e-5


def test_scene_tv_solves_its_problem():
    """Off the mark (T = 0) with a negligible TV weight the blurred scene is the data; under a
    wholly opaque mark (T = 1) the data say nothing and TV continues the scene across it: a
    vertical step crossing a horizontal opaque band stays a vertical step. (Each iteration
    moves a pixel without data by at most 4 tau mu: the solver needs a start near the scene,
    the opening's estimate, or many iterations, as here.)"""
    h, w = 31, 31
    x = np.arange(w)[None, :] * np.ones((h, 1))
    scene = np.where(x >= 15, 0.8, 0.2).astype(np.float32)
    k = scene_tv.gauss_taps(1.0)
    blurred = scene_tv._blur_np(scene[None], k)[0]
    T = np.zeros((h, w), np.float32)
    g, B = scene_tv.deconv_tv(blurred[None], T[None], [0.0], np.full((1, h, w), 0.5),
                              [1e-5], 1.0, 400)
    assert np.abs(g[0] - blurred)[5:-5, 5:-5].max() < 0.02
    T[12:19] = 1.0
    data = blurred * (1 - T) + 0.1 * T
    g, B = scene_tv.deconv_tv(data[None], T[None], [0.1], np.full((1, h, w), 0.5), [0.02],
                              1.0, 400)
    inside = g[0, 13:18, 5:-5]
    assert np.abs(inside - blurred[13:18, 5:-5]).max() < 0.08
    # the opaque band itself is not taken for scene
    assert np.abs(inside.mean() - blurred[13:18, 5:-5].mean()) < 0.02


def _edge_scene(x_mm, y_mm):
    """A scene edge 0.03 mm right of every reseau column (the bar is 0.04 mm wide: the edge
    lies half a pixel beside the bar's edge at 1200 dpi), 2 mm wide bright bands."""
    fx = np.mod(x_mm, 5.0)
    return np.where((fx > 0.03) & (fx < 2.0), 0.35, -0.25)


def test_joint_scene_removes_the_pull_of_an_edge_along_the_bars():
    """Every vertical bar has a scene edge along it, half a pixel outside. The opening puts
    that edge at the bar's edge and every cross is pulled by about 0.24 px in x (1200 dpi,
    blur 1 px, noise 1 %); the joint scene estimate takes most of it out (0.056 px with the
    passes that go on while a cross moves; 0.11 px with two passes of 20 iterations)."""
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=1200, scene=_edge_scene,
                                                     blur_sigma_px=1.0, noise_sigma=0.01), 5)
    sc = Scan.from_array(img, dpi=1200)
    e_open = _errors(detect(sc, "rollei-6006", scene="opening"), truth)
    det = detect(sc, "rollei-6006", scene="joint")
    assert det.scene == "joint"
    e_joint = _errors(det, truth)
    # the opening's crosses are all pulled alike, so none departs from its neighbours; of the
    # joint's, the outlier test may reject the worst (R0C7, 0.15 px off, 5 sigma)
    assert len(e_open) == 121 and len(e_joint) >= 120
    rx_open = float(np.sqrt(np.mean(e_open[:, 0] ** 2)))
    rx_joint = float(np.sqrt(np.mean(e_joint[:, 0] ** 2)))
    assert rx_open > 0.15  # the pull exists
    assert rx_joint < 0.35 * rx_open and rx_joint < 0.08
    # across the edge (y) the scene is flat along the bar: both as precise
    assert np.sqrt(np.mean(e_joint[:, 1] ** 2)) < 0.03


@pytest.mark.parametrize("kind,model", [("texture", "opening"), ("busy", "joint")])
def test_auto_takes_the_joint_scene_where_the_scene_has_sharp_edges(kind, model):
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=900, scene=kind), 11)
    det = detect(Scan.from_array(img, dpi=900), "rollei-6006")
    assert det.scene == model
    assert det.to_json()["scene"] == model


@pytest.mark.parametrize("kind", ["busy", "texture"])
def test_wrong_polarity_over_a_busy_scene_is_no_reseau(kind):
    """A negative read as a positive: over a busy scene (any model) or with the joint scene
    (any scene) some fits to scene content pass the acceptance tests, but they do not lie on
    a grid, and the scan is refused (one-line error)."""
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=650, polarity="negative",
                                                     scene=kind), 3)
    sc = Scan.from_array(img, dpi=650)
    for scene in ("auto", "joint", "opening"):
        with pytest.raises(DetectionError, match="no reseau found") as exc:
            detect(sc, "rollei-6006", polarity="positive", scene=scene)
        assert "\n" not in str(exc.value)
    assert detect(sc, "rollei-6006", polarity="negative").measured.sum() >= 119


def test_unknown_scene_model_is_an_error():
    img, _ = render_scan("rollei-6006", ScanSpec(dpi=300), 1)
    with pytest.raises(Exception, match="scene must be"):
        detect(Scan.from_array(img, dpi=300), "rollei-6006", scene="tv")


def test_joint_passes_go_on_only_for_the_crosses_still_moving(monkeypatch):
    """The joint-scene alternation (:func:`softplot.marks.measure._refit_scene`): the first
    ``REFIT_ALL_PASSES`` passes refit every cross, the later ones only the crosses the pass
    before moved by more than ``REFIT_SETTLE`` x their sigma. Over a busy scene some crosses
    (a scene edge along a bar: the pull converges slowly) still move after two passes, and the
    others have settled."""
    from softplot.camera import load_camera
    from softplot.marks import measure
    from softplot.marks.lsm import lsm as real_lsm
    from softplot.marks.measure import AcceptRules
    from softplot.marks.template import cross_shape
    from softplot.synthetic import TruthMapping

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=1200, scene="busy"), 7)
    sc = Scan.from_array(img, dpi=1200)
    ppm = 1200 / 25.4
    shape = cross_shape(load_camera("rollei-6006"), ppm)
    rs = [m for m in truth["marks"] if m["kind"] == "reseau" and m["visible"]][:30]
    film = np.array([[m["film_x"], m["film_y"]] for m in rs])
    A0 = np.linalg.inv(TruthMapping.from_truth(truth).jacobian(film)
                       @ np.diag([1.0 / ppm, -1.0 / ppm]))
    c0 = np.array([[m["x"], m["y"]] for m in rs]) + 0.2
    sign = 1 if truth["polarity"] == "negative" else -1
    calls = []

    def spy(stack, origin, c, A, shp, **kw):
        out = real_lsm(stack, origin, c, A, shp, **kw)
        calls.append((np.array(c, float), out.centre.copy(), out.sigma.copy()))
        return out

    monkeypatch.setattr(measure, "lsm", spy)
    # one LSM call per pass (on several threads a pass fits its marks in two halves)
    monkeypatch.setattr(measure, "concurrent", lambda: False)
    measure._fit(sc, shape, c0, A0, float(np.hypot(1.0, np.sqrt(1 / 12))), 0.75, sign,
                 True, True, scene_tv=4, rules=AcceptRules())
    # the first fit, then 2 joint passes of every cross, a third of those still moving, and a
    # fourth unless all had settled
    assert len(calls) in (4, 5)
    n_all = len(calls[1][0])
    assert n_all >= 28 and len(calls[2][0]) == n_all  # passes 1 and 2: every cross
    start3, _, _ = calls[3]
    assert 0 < len(start3) < n_all  # pass 3: some crosses, not all
    # pass 3 refits exactly the crosses pass 2 moved by more than REFIT_SETTLE x sigma
    c2_in, c2_out, s2 = calls[2]
    move = np.hypot(*(c2_out - c2_in).T)
    still = move > measure.REFIT_SETTLE * s2
    picked = np.array([np.isclose(start3, p).all(1).any() for p in c2_out])
    assert np.array_equal(picked, still)
    if len(calls) == 5:
        assert len(calls[4][0]) <= len(start3)


def test_a_cross_the_scan_edge_cuts_leaves_its_set_the_joint_scene():
    """A patch the scan's edge cuts (NaN pixels) has no scene-edge figure and no joint scene;
    the other crosses fitted with it keep theirs: their scene figures and joint-scene
    positions are those of a set without it. (Such a patch in a set took both from every
    cross of it: "auto" chose the opening for a busy quarter frame, and a busy scan's joint
    refits depended on which chunk a cut cross fell in, 0.025 px here.)"""
    from softplot.camera import load_camera
    from softplot.marks import measure
    from softplot.marks.measure import AcceptRules
    from softplot.marks.template import cross_shape
    from softplot.synthetic import TruthMapping

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=1200, scene="busy"), 7)
    ppm = 1200 / 25.4
    shape = cross_shape(load_camera("rollei-6006"), ppm)
    rs = [m for m in truth["marks"] if m["kind"] == "reseau" and m["visible"]]
    xs = np.array([m["x"] for m in rs])
    x0 = int(xs.min()) - 6  # the leftmost column 6 px from the cropped scan's edge
    sc = Scan.from_array(np.ascontiguousarray(img[:, x0:]), dpi=1200)
    cut = [m for m in rs if m["x"] < xs.min() + 1][:1]
    inner = [m for m in rs if m["x"] > xs.min() + 50][:12]
    mp = TruthMapping.from_truth(truth)
    sign = 1 if truth["polarity"] == "negative" else -1

    def fit(ms):
        film = np.array([[m["film_x"], m["film_y"]] for m in ms])
        A0 = np.linalg.inv(mp.jacobian(film) @ np.diag([1.0 / ppm, -1.0 / ppm]))
        t = np.array([[m["x"] - x0, m["y"]] for m in ms])  # truth, cropped pixel system
        res, edge = measure._fit(sc, shape, t + 0.2, A0, float(np.hypot(1.0, np.sqrt(1 / 12))),
                                 0.75, sign, True, True, scene_tv=2, rules=AcceptRules(),
                                 edges=True)
        return res.centre - t, edge

    e_alone, edge_alone = fit(inner)
    e_with, edge_with = fit(inner + cut)
    assert np.isfinite(edge_alone).all() and np.isnan(edge_with[-1])
    np.testing.assert_allclose(edge_with[:-1], edge_alone, rtol=1e-6)
    # the same joint-scene fits (the TV weight, from the set's median noise, may differ a
    # little); without their joint scene they moved 0.025 px
    assert np.abs(e_with[:-1] - e_alone).max() < 0.005
    assert np.sqrt(np.mean(e_with[:-1] ** 2)) < 0.02  # against the truth
