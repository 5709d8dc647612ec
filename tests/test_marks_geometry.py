"""Mark geometry from the scan: crosses whose arm length and line width differ from the
certificate's (0.4x-2.5x, 0.5x-2x, or not stated at all) are measured as accurately as crosses
of the stated size, and the result reports the size measured (``mark_geometry``)."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from conftest import sweep
from softplot.camera import load_camera, parse_certificate, to_toml
from softplot.io import Scan
from softplot.marks import detect
from softplot.marks.crb import centre_crb, effective_noise
from softplot.marks.geometry import estimate_geometry
from softplot.marks.qc import geometry_text
from softplot.marks.template import MarkShape, cross_shape
from softplot.synthetic import ScanSpec, render_scan

CAM = "rollei-6006"
DPI = 1200.0


def _without_sizes(name: str):
    """The built-in certificate with ``arm_length_mm`` and ``line_width_mm`` left out."""
    text = "\n".join(line for line in to_toml(load_camera(name)).splitlines()
                     if not line.startswith(("arm_length_mm", "line_width_mm")))
    return parse_certificate(text)


@functools.lru_cache(maxsize=4)
def _render(arm: float, width: float, seed: int = 3):
    spec = ScanSpec(dpi=DPI, mark_arm_scale=arm, mark_width_scale=width, rotation_deg=0.6,
                    scene="none", noise_sigma=0.02)
    return render_scan(CAM, spec, seed)


def _errors(det, truth):
    tm = {m["name"]: m for m in truth["marks"]}
    err, wrong, missed, claimed = [], 0, 0, 0
    for i, name in enumerate(det.name):
        t = tm[name]
        if det.status[i] != "measured":
            missed += bool(t["visible"])
            continue
        if not t["visible"]:
            claimed += 1
            continue
        e = det.xy[i] - (t["x"], t["y"])
        if np.hypot(*e) > 1.0:
            wrong += 1
        else:
            err.append(e)
    return np.array(err).reshape(-1, 2), wrong, missed, claimed


CASES = [(a, w, c) for a in (0.4, 0.7, 1.6, 2.5) for w in (0.5, 1.0, 2.0)
         for c in ("stated",)] + [(a, w, "absent") for a, w in ((0.4, 0.5), (1.0, 1.0),
                                                                 (2.5, 2.0), (1.5, 0.7))]


@pytest.mark.parametrize("arm,width,cert", sweep(CASES, 5))
def test_crosses_of_any_size_are_measured_to_the_bound(arm, width, cert):
    img, truth = _render(arm, width)
    cam = load_camera(CAM) if cert == "stated" else _without_sizes(CAM)
    det = detect(Scan.from_array(img, dpi=truth["dpi"]), cam)
    err, wrong, missed, claimed = _errors(det, truth)
    visible = sum(bool(m["visible"]) for m in truth["marks"])
    assert wrong == 0 and claimed == 0
    assert missed <= max(1, 0.005 * visible), (missed, visible)
    # the bound of the crosses as drawn (their true size), flat scene
    r = truth["render"]
    ppm = truth["dpi"] / 25.4
    ref = load_camera(CAM).reseau
    true = MarkShape("cross", length=ref.arm_length_mm * arm * ppm,
                     width=ref.line_width_mm * width * ppm)
    crb = centre_crb(true, r["blur_sigma_px"], abs(r["contrast"]),
                     effective_noise(r["noise_sigma"], truth.get("bit_depth")))
    rms = float(np.sqrt(np.mean(err**2)))
    assert rms <= 1.5 * crb, (rms, crb)
    # the size measured on the scan
    g = det.mark_geometry
    assert g["source"] == "scan" and g["n"] >= 10
    # within 5 % or a pixel (the shortest arms are 15 px)
    assert g["arm_length_mm"] == pytest.approx(ref.arm_length_mm * arm,
                                               abs=max(0.05 * ref.arm_length_mm * arm, 1 / ppm))
    assert g["spread"]["arm_length_mm"] < 0.05 * ref.arm_length_mm * arm
    if true.width >= 3.0:  # thinner lines: width and blur are not separable
        assert g["line_width_mm"] == pytest.approx(ref.line_width_mm * width, rel=0.2)
    assert det.to_json()["mark_geometry"] == g
    assert "measured on the scan" in geometry_text(det)


def test_certificate_without_sizes_is_valid_and_round_trips():
    cam = _without_sizes(CAM)
    assert cam.reseau.sizes_stated == (False, False)
    assert cam.reseau.arm_length_mm == pytest.approx(0.8 * 1.25)  # 1 mm, at most pitch / 5
    assert 0 < cam.reseau.line_width_mm < cam.reseau.arm_length_mm
    text = to_toml(cam)
    assert "arm_length_mm" not in text and "line_width_mm" not in text
    assert parse_certificate(text).reseau.sizes_stated == (False, False)
    assert load_camera(CAM).reseau.sizes_stated == (True, True)


def test_geometry_of_profiles_without_crosses_keeps_the_guess():
    """No cross (a flat grey): the starting guess is kept and says so."""
    grey = np.full((400, 400), 0.5, np.float32)
    rng = np.random.default_rng(0)
    grey += rng.normal(0, 0.01, grey.shape).astype(np.float32)

    def at(win):
        return grey[win]

    guess = cross_shape(dataclasses.replace(load_camera(CAM)), DPI / 25.4)
    xy = np.array([[100.0, 100.0], [300.0, 100.0], [200.0, 300.0]])
    g = estimate_geometry(at, xy, np.tile(np.eye(2), (3, 1, 1)), guess, -1, pitch_px=200.0)
    assert g.source == "certificate"
    assert g.arm_px == guess.length and g.width_px == guess.width


#: thin lines under a wide blur, at low resolution: (camera, dpi, blur px, arm x, width x)
#: (a line of 0.6-0.9 px under a blur of 2-2.5 px has a few per cent of its contrast per
#: sample; each bar's profile alone is noise, their median is not)
BLURRED = [("rollei-6006", 423, 1.9, 0.78, 0.9), ("rollei-6006", 500, 2.3, 1.7, 1.1),
           ("hasselblad-mk70", 470, 2.4, 1.9, 0.75), ("rollei-6006", 600, 2.0, 2.2, 0.6)]


@pytest.mark.parametrize("cam,dpi,blur,arm,width", sweep(BLURRED, 2))
def test_arm_length_of_thin_lines_under_a_wide_blur(cam, dpi, blur, arm, width):
    spec = ScanSpec(dpi=dpi, blur_sigma_px=blur, mark_arm_scale=arm, mark_width_scale=width,
                    noise_sigma=0.01, rotation_deg=0.4, scene="texture")
    img, truth = render_scan(cam, spec, BLURRED.index((cam, dpi, blur, arm, width)) + 1)
    det = detect(Scan.from_array(img, dpi=dpi), cam)
    g = det.mark_geometry
    true_arm = load_camera(cam).reseau.arm_length_mm * arm
    # the certificate's length is 22-47 % off: the scan's must be within 12 %
    assert g["source"] == "scan" and g["n"] >= 10
    assert g["arm_length_mm"] == pytest.approx(true_arm, rel=0.12)
    err, wrong, missed, claimed = _errors(det, truth)
    assert wrong == 0 and claimed == 0 and missed == 0


def test_bar_fits_in_one_batch_equal_each_bar_fitted_alone():
    """The bars' profiles are fitted in one batch (each its own damping and stop): the same
    values as fitting each profile alone, and the true ends and width recovered (blurred
    boxes of known arm, width and blur, with noise; a flat profile has no bar)."""
    from softplot.marks.geometry import _box, _fit_across, _fit_along

    rng = np.random.default_rng(5)
    u = np.arange(-60.0, 60.0 + 1e-9, 0.5)
    v = np.arange(-9.0, 9.0 + 1e-9, 0.5)
    arms = np.array([30.0, 34.0, 38.0, 42.0, 46.0])
    blurs = np.array([0.8, 1.0, 1.3, 1.6, 2.0])
    widths = np.array([1.5, 2.0, 2.5, 3.0, 3.5])
    along = [_box(u, 0.1, 1.0, -0.5 * a + 0.7, 0.5 * a + 0.7, s) + rng.normal(0, 0.03, u.size)
             for a, s in zip(arms, blurs, strict=True)]
    along.append(rng.normal(0, 0.03, u.size))  # no bar
    across = [_box(v, 0.1, 1.0, -0.5 * w - 0.3, 0.5 * w - 0.3, 1.0)
              + rng.normal(0, 0.02, v.size) for w in widths]
    batch = _fit_along(u, along, 10.0, 40.0, centre=4.0, s0=1.0, width=2.0)
    alone = [_fit_along(u, p, 10.0, 40.0, centre=4.0, s0=1.0, width=2.0)[0] for p in along]
    assert batch[-1] is None and alone[-1] is None
    for fb, fa, a, s in zip(batch[:-1], alone[:-1], arms, blurs, strict=True):
        np.testing.assert_allclose(fb, fa, rtol=0, atol=1e-9)
        assert fb[1] - fb[0] == pytest.approx(a, abs=0.3)
        assert 0.5 * (fb[0] + fb[1]) == pytest.approx(0.7, abs=0.15)
        assert fb[2] == pytest.approx(s, rel=0.15)
    batch = _fit_across(v, across, 1.0, 2.0)
    for q, fb, w in zip(across, batch, widths, strict=True):
        np.testing.assert_allclose(fb, _fit_across(v, q, 1.0, 2.0)[0], rtol=0, atol=1e-9)
        assert fb[0] == pytest.approx(w, abs=0.4) and fb[1] == pytest.approx(-0.3, abs=0.1)


def test_profile_samples_equal_scipy_linear_interpolation():
    """The profiles' samples (both bars of a cross in one interpolation) are what
    ``map_coordinates(order=1, mode="nearest")`` gives, inside the window and beyond its
    edges."""
    from scipy.ndimage import map_coordinates

    from softplot.marks.geometry import _bilinear

    rng = np.random.default_rng(2)
    img = rng.random((60, 80)).astype(np.float32)
    rows = rng.uniform(-3.0, 63.0, (2, 500))
    cols = rng.uniform(-3.0, 83.0, (2, 500))
    rows[0, :4], cols[0, :4] = [0.0, 59.0, 59.0, 12.0], [0.0, 79.0, 0.0, 79.0]  # the corners
    got = _bilinear(img, rows, cols)
    want = np.stack([map_coordinates(img, [rows[k], cols[k]], order=1, mode="nearest")
                     for k in range(2)])
    assert got.dtype == want.dtype
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


def test_bar_samples_interpolated_on_demand_equal_the_full_grid():
    """A bar's samples are interpolated only where used (the columns asked for): the values
    of the whole sample grid interpolated by scipy, for both bars of a turned cross."""
    from scipy.ndimage import map_coordinates

    from softplot.marks.geometry import _bar_profiles, _sample_grid

    rng = np.random.default_rng(4)
    img = (0.5 + 0.02 * rng.normal(size=(200, 200))).astype(np.float32)
    yy, xx = np.mgrid[:200, :200]
    img[(np.abs(yy - 101.3) < 1.5) & (np.abs(xx - 99.6) < 30)] = 0.1
    img[(np.abs(xx - 99.6) < 1.5) & (np.abs(yy - 101.3) < 30)] = 0.1
    th = np.radians(2.0)
    A = np.array([[np.cos(th), np.sin(th)], [np.sin(th), -np.cos(th)]])  # pixel -> mark frame
    u, v = np.arange(-45.0, 45.0 + 1e-9, 0.5), np.arange(-9.0, 9.0 + 1e-9, 0.5)
    grid = _sample_grid(u, v)
    bars = _bar_profiles(lambda win: img[win], (99.6, 101.3), A, u, v, grid, 3.0, 9.0, -1,
                         45.0, 9.0)
    px = np.linalg.inv(A) @ grid
    sel = np.abs(u) < 20.0
    for b in (0, 1):
        assert bars[b] is not None and bars[b][2] > 0.3  # the bar's contrast (0.4)
        full = map_coordinates(-img, [px[b, 1] + 101.3, px[b, 0] + 99.6], order=1,
                               mode="nearest").reshape(len(v), len(u))
        np.testing.assert_allclose(bars[b][1](np.ones(len(u), bool)), full, rtol=0, atol=1e-6)
        np.testing.assert_allclose(bars[b][1](sel), full[:, sel], rtol=0, atol=1e-6)


def test_bar_fit_jacobians_written_in_place_are_the_stacked_ones():
    """The blurred box's Jacobian written column by column into one array (the along fit's
    sixth column, the other bar's cross-section, filled in place) is bit for bit the one
    stacked from its columns and concatenated, so the bars' fits are unchanged: the along
    fit by Levenberg-Marquardt from the stacked Jacobians gives exactly the same ends, blur
    and contrast (the NumPy path), and those lie within a tenth of a pixel of the true
    box's."""
    from scipy.special import erf, ndtr

    from softplot.marks import geometry
    from softplot.marks.geometry import _box, _box_jac, _fit_along, _lm

    def stacked(x, b, c, a1, a2, s):
        z1, z2 = (x - a1) / s, (x - a2) / s
        P = ndtr(z1) - ndtr(z2)
        g1 = np.exp(-0.5 * z1 * z1) / np.sqrt(2.0 * np.pi)
        g2 = np.exp(-0.5 * z2 * z2) / np.sqrt(2.0 * np.pi)
        J = np.stack(np.broadcast_arrays(1.0, P, -c * g1 / s, c * g2 / s,
                                         -c * (z1 * g1 - z2 * g2) / s), -1)
        return b + c * P, J

    rng = np.random.default_rng(11)
    u = np.arange(-40.0, 40.0 + 1e-9, 0.5)
    prm = rng.uniform([-0.1, 0.5, -20.0, 10.0, 0.4], [0.1, 1.5, -10.0, 20.0, 2.5], (7, 5))
    for s_shape in ((7, 1), ()):  # a blur per profile, one blur for all
        q = [prm[:, k, None] for k in range(4)] + [
            prm[:, 4, None] if s_shape else float(prm[0, 4])]
        f0, J0 = stacked(u, *q)
        f1, J1 = _box_jac(u, *q)
        assert np.array_equal(f0, f1) and np.array_equal(J0, J1)
    # the along fit with the old (stacked, concatenated) residuals and Jacobians
    arms, blurs, h = [24.0, 28.0, 33.0], [0.7, 1.1, 1.8], 1.0
    prof = np.array([_box(u, 0.05, 1.0, -0.5 * a + 0.4, 0.5 * a + 0.4, s)
                     + rng.normal(0, 0.02, u.size) for a, s in zip(arms, blurs, strict=True)])
    got = _fit_along(u, prof, 8.0, 20.0, centre=3.0, s0=1.0, width=2.0 * h, compiled=False)
    starts = [geometry._along_start(u, p, 8.0, 20.0, 3.0) for p in prof]
    k_max = 1.0 / max(float(erf(0.5 * h / np.sqrt(2.0))), 1e-3) - 1.0

    def rj(qq, k):
        qc = qq[:, :, None]
        f, J = stacked(u, *np.moveaxis(qc[:, :5], 1, 0))
        zp, zm = (u + h) / qc[:, 4], (u - h) / qc[:, 4]
        L = ndtr(zp) - ndtr(zm)
        gp = np.exp(-0.5 * zp * zp) / np.sqrt(2.0 * np.pi)
        gm = np.exp(-0.5 * zm * zm) / np.sqrt(2.0 * np.pi)
        J = np.concatenate([J, (qc[:, 1] * L)[..., None]], -1)
        J[..., 1] += qc[:, 5] * L
        J[..., 4] += -qc[:, 1] * qc[:, 5] * (zp * gp - zm * gm) / qc[:, 4]
        return f + qc[:, 1] * qc[:, 5] * L - prof[k], J

    ref = _lm(rj, [[b0, c0, a1, a2, 1.0, 0.0] for b0, c0, a1, a2 in starts],
              [-np.inf, 0.0, u[0], 0.0, 0.3, 0.0], [np.inf, np.inf, 0.0, u[-1], 10.0, k_max])
    for g, r, a, s in zip(got, ref, arms, blurs, strict=True):
        assert g == (r[2], r[3], r[4], r[1])  # (a1, a2, s, c), bit for bit
        assert abs(g[0] - (-0.5 * a + 0.4)) < 0.1 and abs(g[1] - (0.5 * a + 0.4)) < 0.1
        assert abs(g[2] - s) < 0.1 * s


def _profiles(rng, u, v, K):
    """K noisy blurred boxes along (arm 12-50 px, blur 0.4-3 px, off centre by up to 2 px,
    a darker crossing) and across (width 0.6-4 px, blur 1 px) at the samples ``u``, ``v``
    (mark frame px), a profile without a bar among each."""
    from softplot.marks.geometry import _box

    arms, blurs = rng.uniform(12.0, 50.0, K), rng.uniform(0.4, 3.0, K)
    off, widths = rng.uniform(-2.0, 2.0, K), rng.uniform(0.6, 4.0, K)
    along = [_box(u, 0.1, 1.0, o - 0.5 * a, o + 0.5 * a, s) + 0.3 * _box(u, 0, 1.0, -1, 1, s)
             + rng.normal(0, 0.04, u.size) for a, s, o in zip(arms, blurs, off, strict=True)]
    across = [_box(v, 0.1, 1.0, o - 0.5 * w, o + 0.5 * w, 1.0) + rng.normal(0, 0.03, v.size)
              for w, o in zip(widths, 0.2 * off, strict=True)]
    along[K // 2] = rng.normal(0, 0.04, u.size)
    across[K // 3] = np.full(v.size, -0.05)  # no contrast
    return along, across, arms, widths


@pytest.mark.parametrize("seed", range(4))
def test_compiled_profile_fits_are_the_numpy_fits(seed):
    """The profiles' Levenberg-Marquardt fits compiled (the model, its Jacobian and the
    damped steps in one pass per bar) give the NumPy batch's ends, blur, contrast and
    widths to 1e-9 px, the same bars refused (no bar, no contrast), and the true arms
    and (lines of twice the blur and more) widths."""
    from softplot.marks import kernels
    from softplot.marks.geometry import _fit_across, _fit_along

    if not kernels.ready():
        pytest.skip("numba unavailable")
    rng = np.random.default_rng(seed)
    u = np.arange(-60.0, 60.0 + 1e-9, 0.5)
    v = np.arange(-9.0, 9.0 + 1e-9, 0.25)
    along, across, arms, widths = _profiles(rng, u, v, 12)
    for s0 in (1.0, 2.5):
        fc = _fit_along(u, along, 5.0, 40.0, centre=4.0, s0=s0, width=2.0, compiled=True)
        fn = _fit_along(u, along, 5.0, 40.0, centre=4.0, s0=s0, width=2.0, compiled=False)
        assert [f is None for f in fc] == [f is None for f in fn]
        assert fc[6] is None and sum(f is not None for f in fc) >= 10
        for a, b, arm in zip(fc, fn, arms, strict=True):
            if a is not None:
                np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
                assert a[1] - a[0] == pytest.approx(arm, abs=max(0.75, 0.04 * arm))
    fc = _fit_across(v, across, 1.0, 2.0, compiled=True)
    fn = _fit_across(v, across, 1.0, 2.0, compiled=False)
    assert [f is None for f in fc] == [f is None for f in fn] and fc[4] is None
    for a, b, w in zip(fc, fn, widths, strict=True):
        if a is not None:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
            if w >= 2.0:  # resolved: twice the blur
                assert a[0] == pytest.approx(w, abs=0.35)


def test_compiled_profile_fit_steps_as_numpy():
    """The compiled Levenberg-Marquardt takes NumPy's steps: after 1, 3 and 30 iterations
    the same parameters to 1e-9, its bounds held (the far end stopped at its bound), and a
    fit with nothing to improve (a zero profile from a zero contrast) left at its start."""
    from softplot.marks import kernels
    from softplot.marks.geometry import _ACROSS, _ALONG, _box, _box_jac, _lm, _lm_compiled

    if not kernels.ready():
        pytest.skip("numba unavailable")
    u = np.arange(-30.0, 30.0 + 1e-9, 0.5)
    prof = np.stack([_box(u, 0.0, 1.0, -10.0, 12.0, 1.2), np.zeros_like(u)])
    p0 = [[0.0, 0.8, -8.0, 9.0, 1.0, 0.0], [0.0, 0.0, -8.0, 9.0, 1.0, 0.0]]
    lo, hi = [-np.inf, 0.0, -30.0, 0.0, 0.3, 0.0], [np.inf, np.inf, 0.0, 11.0, 10.0, 0.5]

    def rj(q, k):
        qc = q[:, :, None]
        f, J = _box_jac(u, *np.moveaxis(qc[:, :5], 1, 0), cols=6)
        J[..., 5] = 0.0  # h = 0: the crossing adds nothing
        return f - prof[k], J

    for it in (1, 3, 30):
        got = _lm_compiled(_ALONG, u, prof, p0, lo, hi, h=0.0, iterations=it)
        want = _lm(lambda q, k: rj(q, k), p0, lo, hi, iterations=it)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9, equal_nan=True)
    assert np.array_equal(got[1], p0[1])
    assert got[0, 3] == 11.0 and got[0, 2] == pytest.approx(-10.0, abs=0.2)  # held at 11
    across = _lm_compiled(_ACROSS, u, prof[:1], [[0.0, 0.5, 0.0, 10.0]], -np.inf, np.inf,
                          s_fix=1.2)
    assert across[0] == pytest.approx([0.0, 1.0, 1.0, 22.0], abs=1e-6)


def test_compiled_bilinear_samples_are_numpy_bit_for_bit():
    """The profiles' samples interpolated in one compiled pass are NumPy's to the bit (the
    same float64 weights, the result rounded to the image's dtype, laid out in memory as
    NumPy lays it out, so that means over an axis add alike), inside the window, beyond its
    edges and on a window of 2 x 2 pixels."""
    from softplot.marks import kernels
    from softplot.marks.geometry import _bilinear, _bilinear_numpy

    if not kernels.ready():
        pytest.skip("numba unavailable")
    rng = np.random.default_rng(8)
    for h, w in ((2, 2), (37, 61), (90, 3)):
        img = (rng.normal(0.3, 0.2, (h, w)) * (-1) ** h).astype(np.float32)
        rows = rng.uniform(-3.0, h + 3.0, (2, 9, 17))
        cols = rng.uniform(-3.0, w + 3.0, (2, 9, 17))
        rows[0, 0, :3], cols[0, 0, :3] = [0.0, h - 1.0, h - 1.0], [0.0, w - 1.0, 0.0]
        sel = rng.random(17) < 0.5
        # laid out in C order, and in F order as a column selection leaves it
        for r, c in ((rows, cols), (rows[0][:, sel], cols[0][:, sel]),
                     (rows[:, :, sel], cols[:, :, sel])):
            got = _bilinear(img, r, c, compiled=True)
            want = _bilinear_numpy(img, r, c)
            assert got.dtype == want.dtype == np.float32 and got.shape == want.shape
            assert got.strides == want.strides and np.array_equal(got, want)
            for ax in range(got.ndim):  # a mean adds in the same order
                assert np.array_equal(got.mean(ax), want.mean(ax))


def test_geometry_of_a_scan_compiled_is_the_numpy_geometry(monkeypatch):
    """The mark geometry of a rendered scan (the call detection makes) with the compiled fits
    and samples is the NumPy path's: to 1e-9 px (arm, blur, arm spread, centre offset), to
    1e-5 px the width of a line hardly wider than the blur (the fits' stop leaves its width
    that much play), and the arm it measures is the true one."""
    from softplot.marks import geometry, kernels, marksize

    if not kernels.ready():
        pytest.skip("numba unavailable")
    img, truth = _render(1.0, 1.0)
    calls = []

    def keep(*args, **kw):
        calls.append((args, kw))
        return estimate_geometry(*args, **kw)

    monkeypatch.setattr(marksize, "estimate_geometry", keep)
    detect(Scan.from_array(img, dpi=truth["dpi"]), load_camera(CAM))
    args, kw = calls[0]
    out = {}
    for flag in (True, False):
        monkeypatch.setattr(geometry, "_compiled", lambda f, v=flag: v if f is None else f)
        out[flag] = estimate_geometry(*args, **kw)
    a, b = out[True], out[False]
    assert a.source == b.source == "scan" and a.n == b.n >= 10
    for k in ("arm_px", "width_px", "arm_spread_px", "width_spread_px", "blur_px"):
        # a line about 1.7 blurs wide: width and contrast trade off along a flat valley,
        # where the fits stop (a cost change of 1e-10 of it) within about 1e-6 px
        tol = 1e-5 if k.startswith("width") else 1e-9
        assert getattr(a, k) == pytest.approx(getattr(b, k), abs=tol), k
    np.testing.assert_allclose(a.offset_px, b.offset_px, rtol=0, atol=1e-9)
    true_arm = load_camera(CAM).reseau.arm_length_mm * truth["dpi"] / 25.4
    assert a.arm_px == pytest.approx(true_arm, rel=0.05)
