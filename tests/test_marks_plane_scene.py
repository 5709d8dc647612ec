"""A flat scene under a cross is a plane, not its opening (issue 20 point 6).

The grey opening/closing of :func:`softplot.marks.measure.scene_background` of a flat, noisy
patch is the background plus the closing's lumps of noise and, where the blurred bars meet, a
dip its disc cannot close (the nearest background lies diagonally, in the quadrants'
corners): noise and a piece of the mark in the scene estimate. Where the opening departs
from a plane, away from the cross's centre, by no more than a quarter of the noise (or one
grey step), :func:`softplot.marks.measure.plane_scenes` takes the plane, on a scan whose
crosses are all flat (:func:`softplot.marks.measure.flat_scan`). Checked against
exact synthetic truth: the patch test itself, and two sweep renders on no scene whose RMS
error was 1.57x and 2.83x their Cramer-Rao bound with the opening (1.41x, 1.96x now).
"""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks.lsm import patch_frame
from softplot.marks.measure import PLANE_GATE, plane_scenes, scene_background
from softplot.marks.template import MarkShape, render
from softplot.synthetic.sweep import make_case, run_case

SHAPE = MarkShape("cross", length=24.0, width=1.2)
BLUR = 1.0
NOISE = 0.01
HALF = 20


def _stack(texture: float, n: int = 12, seed: int = 0):
    """``n`` patches (patch pixel system) of a dark cross at the centre over the plane
    ``0.7 + 0.02 x / w`` plus a curved texture (periods 50 and 60 px) of amplitude ``texture``
    (grey units), white noise NOISE; and each patch's true scene."""
    rng = np.random.default_rng(seed)
    size = 2 * HALF + 1
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    plane = 0.7 + 0.02 * x / size
    mark = render(SHAPE, BLUR, half=HALF)  # 1 on the bars, 0 around (patch pixels)
    scenes, data = [], []
    for _ in range(n):
        ph = rng.uniform(0, 2 * np.pi, 2)
        sc = plane + texture * np.sin(2 * np.pi * x / 50 + ph[0]) * np.cos(2 * np.pi * y / 60
                                                                           + ph[1])
        scenes.append(sc)
        data.append(sc - 0.2 * mark + rng.normal(0, NOISE, sc.shape))
    return np.array(data, np.float32), np.array(scenes)


def _away(n: int) -> np.ndarray:
    """Pixels beyond ``width / 2 + 3 s + 1`` px of the centre (as the detector judges)."""
    size = 2 * HALF + 1
    u, v = patch_frame(np.zeros((n, 2)), np.full((n, 2), float(HALF)),
                       np.broadcast_to(np.eye(2), (n, 2, 2)), (n, size, size))
    return np.hypot(u, v) > 0.5 * SHAPE.width + 3 * BLUR + 1.0


def test_a_flat_patch_takes_the_plane_and_the_plane_is_nearer_the_truth():
    stack, scene = _stack(texture=0.0)
    S, _, _ = scene_background(stack, SHAPE, BLUR, -1)
    flat, P = plane_scenes(stack, S, _away(len(stack)))
    assert flat.all()
    # under the cross (where LSM reads the scene) the plane is far nearer the true scene
    # than the opening, which holds noise and part of the mark; both up to a constant (the
    # closing's offset: LSM fits a level on top)
    under = ~_away(len(stack))

    def err(est):
        e = np.where(under, est - scene, np.nan)
        e -= np.nanmean(e, axis=(1, 2))[:, None, None]
        return float(np.sqrt(np.nanmean(e**2)))

    err_open, err_plane = err(S), err(P)
    assert err_plane < 0.15 * NOISE
    assert err_plane < 0.5 * err_open


def test_a_curved_patch_keeps_its_opening():
    stack, _ = _stack(texture=3.0 * NOISE)  # a curved scene the opening follows: not flat
    S, _, _ = scene_background(stack, SHAPE, BLUR, -1)
    flat, _ = plane_scenes(stack, S, _away(len(stack)))
    assert not flat.any()
    # and the gate is what decides: wide open, the same patches pass
    flat_wide, _ = plane_scenes(stack, S, _away(len(stack)), gate=100 * PLANE_GATE)
    assert flat_wide.all()


@pytest.mark.parametrize("seed, limit, least", [
    # plate 13x18, 450 dpi, line 0.51x, contrast 0.13, RGB negative, no scene: 1.57x with
    # 145 of 163 measured with the opening; 1.41x, 162 with the plane
    (442, 1.48, 160),
    # a web copy of a Rollei (JPEG q75, 968 px) on no scene: 2.83x with the opening (a dip
    # under the cross centre), 1.96x with the plane
    (53, 2.2, 119),
])
def test_flat_sweep_renders_come_nearer_their_bound(seed, limit, least):
    sc, _ = run_case(make_case(seed))
    d = sc.to_dict()
    assert not sc.wrong and not sc.claimed
    assert sc.measured >= least
    assert d["rms_px"] <= limit * d["crb_px"], (d["rms_px"], d["crb_px"])


def test_every_patch_gets_its_own_least_squares_plane():
    # plane_scenes fits all patches at once; each plane is the least-squares plane of that
    # patch's own pixels away from the cross (each patch its own mask), as a per-patch lstsq
    rng = np.random.default_rng(7)
    n, h = 12, 31
    y, x = np.mgrid[0:h, 0:h].astype(np.float64)
    S = (rng.normal(size=(n, 1, 1)) + rng.normal(scale=0.02, size=(n, 1, 1)) * x
         + rng.normal(scale=0.02, size=(n, 1, 1)) * y
         + rng.normal(scale=0.003, size=(n, h, h))).astype(np.float32)
    stack = (S + rng.normal(scale=0.02, size=S.shape)).astype(np.float32)
    away = np.hypot(x - h / 2, y - h / 2)[None] > rng.uniform(3, 12, size=(n, 1, 1))
    stack[3, 0, 0] = np.nan  # a patch over the scan's edge: judged not flat
    flat, P = plane_scenes(stack, S, away)
    X = np.stack([np.ones(h * h), (x.ravel() - h / 2) / h, (y.ravel() - h / 2) / h], 1)
    for i in range(n):
        if i == 3:
            assert not flat[i]
            continue
        k = away[i].ravel()
        coef = np.linalg.lstsq(X[k], S[i].ravel()[k].astype(np.float64), rcond=None)[0]
        assert np.allclose(P[i].ravel(), X @ coef, atol=1e-6), i
        assert flat[i]  # a plane plus noise 0.15 of the patch's: flat
