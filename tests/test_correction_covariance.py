"""Film correction weights every mark by its 2 x 2 covariance: a cross measured across one
bar only (its position along the bar is a prediction with a large variance) constrains the
correction across that bar only, in every global model and in the meshes."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.correction import FilmCorrection

CAM = "rollei-6006"
PPM = 600 / 25.4
SIG = 0.03  # px, across every bar
ALONG = 1.0  # px, the true error along a lone bar (its prediction's)


def _truth(deform: float, persp: float = 1.0):
    """film mm (N, 2) -> pixel px: a projective scan (an affine one with ``persp`` 0) plus a
    smooth film deformation."""
    th = np.radians(0.7)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])

    def f(film):
        film = np.atleast_2d(film)
        p = (film * [1.0, -1.0]) @ R.T * PPM * [1.0, 1.002] + [700.0, 720.0]
        w = 1.0 + persp * (2e-5 * film[:, :1] - 1e-5 * film[:, 1:])
        p = (p - 700.0) / w + 700.0
        return p + deform * np.column_stack([np.sin(film[:, 0] / 9.0), np.cos(film[:, 1] / 11.0)])

    return f


def _detection(seed, deform, reported="honest", persp=1.0):
    """A detection dict of the certificate's crosses: 12 of them measured across one bar
    only. ``reported``: "honest" (the covariance a detector reports: across within +-30 %,
    along 0.5 px, a lone bar's prediction), "truth" (the covariances the errors were drawn
    from) or "none" (no covariance: every mark alike)."""
    cam = load_camera(CAM)
    R = cam.reseau
    film = R.film().reshape(-1, 2)
    rng = np.random.default_rng(seed)
    px = _truth(deform, persp)(film)
    lone = rng.choice(len(film), 12, replace=False)
    marks = []
    for k in range(len(film)):
        r, c = divmod(k, R.cols)
        if k in lone:
            ang = np.radians(0.7) + (np.pi / 2 if rng.uniform() < 0.5 else 0.0)
            t = np.array([np.cos(ang), np.sin(ang)])
            n = np.array([-t[1], t[0]])
            C = SIG**2 * np.outer(n, n) + ALONG**2 * np.outer(t, t)
            Crep = ((SIG * rng.uniform(0.7, 1.3)) ** 2 * np.outer(n, n)
                    + 0.5**2 * np.outer(t, t))
        else:
            C = SIG**2 * np.eye(2)
            Crep = (SIG * rng.uniform(0.7, 1.3)) ** 2 * np.eye(2)
        e = rng.multivariate_normal([0.0, 0.0], C)
        m = {"kind": "reseau", "name": f"R{r}C{c}", "row": r, "col": c, "status": "measured",
             "x": float(px[k, 0] + e[0]), "y": float(px[k, 1] + e[1])}
        if reported != "none":
            m["cov"] = (C if reported == "truth" else Crep).tolist()
        marks.append(m)
    return {"marks": marks, "width": 1400, "height": 1440}, film, lone


def _error_px(fc, film_check, deform, persp=1.0):
    """RMS error (px) of the correction at film points: true pixel -> corrected film."""
    px = _truth(deform, persp)(film_check)
    got, _ = fc.pixel_to(px, "film")
    return float(np.sqrt(np.mean((got - film_check) ** 2))) * PPM


def _check_points(film, rng, n=400):
    lo, hi = film.min(0), film.max(0)
    return rng.uniform(lo, hi, (n, 2))


@pytest.mark.parametrize("method", ["affine", "projective", "poly2"])
def test_global_models_weight_by_the_2x2_covariance(method):
    persp = 0.0 if method == "affine" else 1.0  # a scan the model can follow
    err = {k: [] for k in ("honest", "truth", "none")}
    for seed in range(12):
        for rep in err:
            det, film, _ = _detection(seed, 0.0, rep, persp)
            fc = FilmCorrection.from_detection(CAM, det, method)
            pts = _check_points(film, np.random.default_rng(100 + seed))
            err[rep].append(_error_px(fc, pts, 0.0, persp))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}
    # as accurate as the solution weighted by the true covariances, much better than
    # counting every mark alike
    assert rms["honest"] <= 1.1 * rms["truth"], rms
    assert rms["none"] >= 3.0 * rms["truth"], rms


@pytest.mark.parametrize("method", ["mesh-homography", "mesh-affine", "mesh-bilinear"])
def test_meshes_take_a_lone_bar_across_it_only(method):
    """A mesh interpolates its crosses: a lone bar's position is combined with its
    neighbours' prediction (across the bar the measurement, along it the prediction)."""
    deform = 0.4
    err = {k: [] for k in ("honest", "truth", "none")}
    for seed in range(6):
        for rep in err:
            det, film, lone = _detection(seed, deform, rep)
            fc = FilmCorrection.from_detection(CAM, det, method)
            # points around the lone crosses (within half a pitch)
            rng = np.random.default_rng(200 + seed)
            near = rng.uniform(-2.5, 2.5, (len(lone), 30, 2))
            pts = (film[lone][:, None, :] + near).reshape(-1, 2)
            err[rep].append(_error_px(fc, pts, deform))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}
    assert rms["honest"] <= 1.1 * rms["truth"], rms
    assert rms["none"] >= 3.0 * rms["truth"], rms
