"""The synthetic scan renderer checked against its truth by independent measurements."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import sweep
from softplot.errors import SoftplotError
from softplot.synthetic import ScanSpec, render_scan

CLEAN = dict(noise_sigma=0.0, grain_sigma=0.0, scene="none", bits=16)


def _grey(img: np.ndarray, bits: int) -> np.ndarray:
    a = img.astype(float) / (65535.0 if bits == 16 else 255.0 if bits == 8 else 1.0)
    return a @ np.array([0.299, 0.587, 0.114]) if a.ndim == 3 else a


def _centroid(grey: np.ndarray, x: float, y: float, half: int) -> tuple[float, float]:
    """Intensity centroid of |value - background| in a window; background from its border."""
    xi, yi = int(round(x)), int(round(y))
    win = grey[yi - half : yi + half + 1, xi - half : xi + half + 1]
    ring = np.concatenate([win[0], win[-1], win[:, 0], win[:, -1]])
    w = np.abs(win - np.median(ring))
    yy, xx = np.mgrid[yi - half : yi + half + 1, xi - half : xi + half + 1]
    return float((w * xx).sum() / w.sum()), float((w * yy).sum() / w.sum())


CENTROID_CASES = [
    (dpi, rot, deform, blur, pol)
    for dpi in (600, 1200, 2400)
    for rot in (0.0, 3.7, -8.2)
    for deform in (0.0, 60.0)
    for blur, pol in ((0.5, "positive"), (1.2, "negative"))
]


@pytest.mark.parametrize("dpi,rot,deform,blur,pol", sweep(CENTROID_CASES, 5, seed=3))
def test_cross_centroid_equals_truth(dpi, rot, deform, blur, pol):
    spec = ScanSpec(dpi=dpi, rotation_deg=rot, deform_um=deform, shrink_ppm=300,
                    anisotropy_ppm=600, blur_sigma_px=blur, polarity=pol,
                    crop_mm=(14.0, 14.0, 14.0, 14.0), **CLEAN)
    img, truth = render_scan("rollei-6006", spec, seed=7)
    grey = _grey(img, 16)
    half = int(truth["render"]["arm_half_length_px"] * 1.1 + 5 * blur + 4)
    errs, rest = [], []
    for m in truth["marks"]:
        if m["state"] != "visible":
            continue
        h, w = img.shape
        if not (half <= m["x"] < w - half - 1 and half <= m["y"] < h - half - 1):
            continue
        cx, cy = _centroid(grey, m["x"], m["y"], half)
        errs.append((cx - m["x"], cy - m["y"]))
        sx, sy = m["centroid_shift_px"]
        rest.append((cx - m["x"] - sx, cy - m["y"] - sy))
    errs = np.array(errs)
    assert len(errs) >= 9
    assert np.max(np.abs(errs)) < 0.005, np.max(np.abs(errs))
    # what is left once the physical curvature shift is removed: sampling and quantisation
    assert np.max(np.abs(rest)) < 3e-4


@pytest.mark.parametrize("camera,dpi", [("zeiss-rmk-a-15-23", 300), ("wild-rc10", 250),
                                        ("zeiss-umk-10-1318", 400)])
def test_fiducial_centroid_equals_truth(camera, dpi):
    spec = ScanSpec(dpi=dpi, rotation_deg=1.3, deform_um=40, blur_sigma_px=0.7, **CLEAN)
    img, truth = render_scan(camera, spec, seed=2)
    grey = _grey(img, 16)
    s = dpi / 25.4
    for m in truth["marks"]:
        assert m["kind"] == "fiducial" and m["state"] == "visible"
        half = int(0.55 * 2.0 * s + 6)  # the largest fiducial is 2 mm across
        cx, cy = _centroid(grey, m["x"], m["y"], half)
        assert abs(cx - m["x"]) < 0.005 and abs(cy - m["y"]) < 0.005, (m["name"], cx, cy)


def test_cross_size_and_psf_moments():
    """Zeroth and second moments of a cross against its closed form (arm, width, contrast, PSF)."""
    dpi, blur = 1000.0, 0.9
    spec = ScanSpec(dpi=dpi, deform_um=0.0, blur_sigma_px=blur, contrast=0.4,
                    crop_mm=(20.0, 20.0, 20.0, 20.0), **CLEAN)
    img, truth = render_scan("rollei-6006", spec, seed=1)
    grey = _grey(img, 16)
    s = dpi / 25.4
    L, w = 0.8 * s, 0.04 * s  # px
    area = 2 * L * w - w * w
    ixx = (w * L**3 + L * w**3 - w**4) / 12 + area * (blur**2 + 1 / 12)  # Gaussian + pixel box
    m = next(k for k in truth["marks"] if k["name"] == "R5C5")
    half = int(L / 2 + 6 * blur + 4)
    xi, yi = int(round(m["x"])), int(round(m["y"]))
    win = grey[yi - half : yi + half + 1, xi - half : xi + half + 1]
    bg = truth["render"]["background"]
    wt = bg - win
    assert wt.sum() == pytest.approx(0.4 * area, rel=1e-3)
    xx = np.arange(xi - half, xi + half + 1)[None, :] - m["x"]
    yy = np.arange(yi - half, yi + half + 1)[:, None] - m["y"]
    assert (wt * xx**2).sum() / 0.4 == pytest.approx(ixx, rel=5e-3)
    assert (wt * yy**2).sum() / 0.4 == pytest.approx(ixx, rel=5e-3)
    assert truth["render"]["arm_half_length_px"] == pytest.approx(L / 2)
    assert truth["render"]["line_width_px"] == pytest.approx(w)


def test_polarity():
    kw = dict(dpi=400, deform_um=10, **CLEAN)
    pos, tp = render_scan("rollei-6006", ScanSpec(polarity="positive", **kw), seed=4)
    neg, tn = render_scan("rollei-6006", ScanSpec(polarity="negative", **kw), seed=4)
    gp, gn = _grey(pos, 16), _grey(neg, 16)
    assert np.max(np.abs(gp + gn - 1.0)) < 2.5 / 65535
    for m in tp["marks"]:
        x, y = int(round(m["x"])), int(round(m["y"]))
        assert gp[y, x] < tp["render"]["background"] - 0.1
        assert gn[y, x] > tn["render"]["background"] + 0.1
    assert tp["render"]["mark_level"] < tp["render"]["background"]
    assert tn["render"]["mark_level"] > tn["render"]["background"]


def test_covered_marks_are_hidden_and_flagged():
    kw = dict(dpi=400, deform_um=20, **CLEAN)
    img, truth = render_scan("rollei-6006", ScanSpec(cover=4, **kw), seed=9)
    ref, _ = render_scan("rollei-6006", ScanSpec(cover=0, **kw), seed=9)
    g, gr = _grey(img, 16), _grey(ref, 16)
    covered = [m for m in truth["marks"] if m["state"] == "covered"]
    assert len(covered) == 4 and not any(m["visible"] for m in covered)
    r = int(truth["render"]["arm_half_length_px"] + 2)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disc = np.hypot(xx, yy) <= r  # the blob is round: look inside the cross's circle
    for m in covered:
        x, y = int(round(m["x"])), int(round(m["y"]))
        patch = g[y - r : y + r + 1, x - r : x + r + 1][disc]
        assert patch.std() < 1e-4  # uniform: no trace of the cross
        assert gr[y - r : y + r + 1, x - r : x + r + 1][disc].std() > 0.02  # the cross was there
    visible = [m for m in truth["marks"] if m["visible"]]
    assert len(visible) == 121 - 4
    names = [m["name"] for m in covered[:2]]
    _, t2 = render_scan("rollei-6006", ScanSpec(cover=tuple(names), **kw), seed=9)
    assert [m["name"] for m in t2["marks"] if m["state"] == "covered"] == names


def test_cut_and_outside_marks_flagged_by_geometry():
    # crop the left edge through column 0 and the top edge beyond row 0
    spec = ScanSpec(dpi=300, deform_um=0, rotation_deg=0, crop_mm=(3.95, 5.2, 0, 0), **CLEAN)
    img, truth = render_scan("rollei-6006", spec, seed=0)
    h, w = img.shape
    a = truth["render"]["arm_half_length_px"]
    lw = truth["render"]["line_width_px"] / 2
    states = {}
    for m in truth["marks"]:
        x, y = m["x"], m["y"]
        # the two bars as boxes (rotation 0, no deformation)
        boxes = [(x - a, x + a, y - lw, y + lw), (x - lw, x + lw, y - a, y + a)]
        inside = [x0 >= -0.5 and x1 <= w - 0.5 and y0 >= -0.5 and y1 <= h - 0.5
                  for x0, x1, y0, y1 in boxes]
        out = [x1 < -0.5 or y1 < -0.5 or x0 > w - 0.5 or y0 > h - 0.5 for x0, x1, y0, y1 in boxes]
        expect = "visible" if all(inside) else "outside" if all(out) else "cut"
        assert m["state"] == expect, (m["name"], x, y, m["state"], expect)
        assert m["visible"] == (expect == "visible")
        states[expect] = states.get(expect, 0) + 1
    assert states.get("outside", 0) >= 11 and states.get("cut", 0) >= 10
    cut = [m for m in truth["marks"] if m["state"] == "cut"]
    assert all(0 < m["inside_fraction"] < 1 for m in cut)


def test_bit_depths_agree():
    kw = dict(dpi=300, deform_um=20, noise_sigma=0.0, scene="texture")
    i8, t8 = render_scan("pentax-645", ScanSpec(bits=8, **kw), seed=3)
    i16, t16 = render_scan("pentax-645", ScanSpec(bits=16, **kw), seed=3)
    i32, _ = render_scan("pentax-645", ScanSpec(bits=32, **kw), seed=3)
    assert i8.dtype == np.uint8 and i16.dtype == np.uint16 and i32.dtype == np.float32
    assert t8["bit_depth"] == 8 and t16["bit_depth"] == 16
    assert np.max(np.abs(i8 / 255.0 - i32)) <= 0.5 / 255 + 1e-6
    assert np.max(np.abs(i16 / 65535.0 - i32)) <= 0.5 / 65535 + 1e-6
    assert t8["marks"] == t16["marks"]


def test_rgb_positive_and_orange_negative():
    kw = dict(dpi=300, deform_um=20, rgb=True, bits=16, noise_sigma=0.0)
    pos, tp = render_scan("pentax-645", ScanSpec(scene="none", **kw), seed=1)
    assert pos.shape[2] == 3 and tp["channels"] == 3
    assert np.array_equal(pos[..., 0], pos[..., 1]) and np.array_equal(pos[..., 1], pos[..., 2])
    neg, tn = render_scan("pentax-645", ScanSpec(polarity="negative", scene="texture", **kw),
                          seed=1)
    rgb = neg.astype(float) / 65535
    border = rgb[2:6, 2:-2].reshape(-1, 3).mean(axis=0)  # unexposed film edge: clear + mask
    assert border[0] > border[1] > border[2]
    mask = np.array(tn["render"]["orange_mask"])
    assert np.allclose(border / border[0], mask / mask[0], atol=0.01)
    g = _grey(neg, 16)
    m = tn["marks"][4]
    assert g[int(round(m["y"])), int(round(m["x"]))] > tn["render"]["background"] + 0.1
    assert tn["render"]["mark_level"] == pytest.approx(g[2:6, 2:-2].mean(), abs=2e-3)


def test_noise_level_is_what_was_asked():
    spec = ScanSpec(dpi=300, scene="none", noise_sigma=0.02, bits=16, deform_um=0)
    img, truth = render_scan("hasselblad-mk70", spec, seed=5)
    g = _grey(img, 16)
    h, w = g.shape
    flat = g[h // 2 + 20 : h // 2 + 90, w // 2 + 20 : w // 2 + 90]  # between crosses
    assert flat.std() == pytest.approx(0.02, rel=0.06)
    assert truth["render"]["noise_sigma"] == 0.02


def test_same_seed_same_scan_other_seed_other_scan():
    spec = ScanSpec(dpi=300, scene="busy", dust=10, scratches=2, cover=1, grain_sigma=0.01)
    a, ta = render_scan("rollei-6006", spec, seed=21)
    b, tb = render_scan("rollei-6006", spec, seed=21)
    c, tc = render_scan("rollei-6006", spec, seed=22)
    assert np.array_equal(a, b) and ta == tb
    assert not np.array_equal(a, c) and ta["mapping"] != tc["mapping"]


def test_dust_and_scratches_flag_the_marks_they_touch():
    kw = dict(dpi=300, noise_sigma=0.0, scene="none", bits=16, deform_um=10)
    img, truth = render_scan("rollei-6006", ScanSpec(dust=150, scratches=4, **kw), seed=8)
    ref, _ = render_scan("rollei-6006", ScanSpec(**kw), seed=8)
    g, gr = _grey(img, 16), _grey(ref, 16)
    r = int(truth["render"]["arm_half_length_px"] + 1)
    n_damaged = 0
    for m in truth["marks"]:
        x, y = int(round(m["x"])), int(round(m["y"]))
        diff = np.abs(g - gr)[y - r : y + r + 1, x - r : x + r + 1].max()
        if m["damaged"]:
            n_damaged += 1
        else:
            assert diff < 0.01, m["name"]
    assert n_damaged >= 1
    assert np.abs(g - gr).max() > 0.2  # the defects are there


def test_busy_scene_keeps_marks_visible():
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=300, scene="busy"), seed=3)
    assert all(m["contrast_min"] > 0.15 for m in truth["marks"])
    assert img.std() > 20  # 8-bit; lots of content


def test_callable_scene():
    def stripes(x, y):
        return 0.5 + 0.4 * np.sign(np.sin(x / 3.0))

    img, truth = render_scan("hasselblad-mk70", ScanSpec(dpi=200, scene=stripes, **{
        k: v for k, v in CLEAN.items() if k != "scene"}), seed=0)
    assert truth["spec"]["scene"] == "callable"
    assert _grey(img, 16).std() > 0.05


def test_mark_hides_the_optically_blurred_scene():
    """An opaque mark replaces the scene, and both pass the same optics: the mark's image is
    ``(m - blur(scene)) * T`` on top of ``blur(scene)``, so ``T = (I - S) / (m - S)``, with
    ``S`` the same render without marks, is the flat-scene mark even where a sharp scene edge
    crosses an arm (an unblurred scene in the mark's amplitude would leave a sharp step in T)."""
    def step(x, y):  # a sharp edge across the right arm of the central cross, 0.2 mm out
        return np.where(x > 0.2, 0.9, 0.1)

    def flat(x, y):
        return np.full(np.shape(x), 0.5)

    base = dict(dpi=1200, blur_sigma_px=1.0, noise_sigma=0.0, deform_um=0.0, bits=32,
                rotation_deg=3.0)
    out = []
    for scene in (step, flat):
        img, truth = render_scan("rollei-6006", ScanSpec(scene=scene, **base), seed=1)
        bg, _ = render_scan("rollei-6006", ScanSpec(scene=scene, **base), seed=1, marks=False,
                            clip=False)
        m = next(k for k in truth["marks"] if k["name"] == "R5C5")
        x, y = int(round(m["x"])), int(round(m["y"]))
        win = (slice(y - 30, y + 31), slice(x - 30, x + 31))
        S = bg[win].astype(float)
        out.append((img[win] - S) / (truth["render"]["mark_level"] - S))
    assert np.abs(out[0] - out[1]).max() < 1e-4


def test_exact_occlusion_hides_the_scene_under_a_mark():
    """With ``occlusion="exact"`` the film under an opaque mark shows the mark, not the scene:
    a scene change wholly inside the central cross's bar leaves the image as it is (to the
    aliasing of the marks' area coverage), where the first-order occlusion lets it through
    ``blur(S)``; on a flat scene both occlusions give the same image; the truth records it."""
    def hidden(x, y):  # a bright stripe 0.02 mm wide along the axis of the 0.04 mm bar
        return np.where(np.abs(x) < 0.01, 0.4, 0.0) + 0.3

    def flat(x, y):
        return np.full(np.shape(x), 0.3)

    base = dict(dpi=2400, blur_sigma_px=1.0, noise_sigma=0.0, deform_um=0.0, bits=32,
                crop_mm=(26.0, 26.0, 26.0, 26.0))
    img = {}
    for occ in ("first-order", "exact"):
        for name, scene in (("hidden", hidden), ("flat", flat)):
            img[occ, name], truth = render_scan(
                "rollei-6006", ScanSpec(scene=scene, occlusion=occ, **base), seed=1)
            assert truth["render"]["occlusion"] == occ
    m = next(k for k in truth["marks"] if k["name"] == "R5C5")
    x, y = int(round(m["x"])), int(round(m["y"]))
    win = (slice(y + 10, y + 30), slice(x - 6, x + 7))  # across the lower half of the bar
    exact = np.abs(img["exact", "hidden"][win] - img["exact", "flat"][win]).max()
    first = np.abs(img["first-order", "hidden"][win] - img["first-order", "flat"][win]).max()
    assert exact < 2e-3 and first > 0.01 and first > 10 * exact, (exact, first)
    assert np.abs(img["exact", "flat"] - img["first-order", "flat"]).max() < 1e-5
    with pytest.raises(SoftplotError, match="occlusion"):
        ScanSpec(occlusion="partial").validate()


@pytest.mark.parametrize(
    "kw,word",
    [
        (dict(dpi=-3), "dpi"),
        (dict(dpi=0), "dpi"),
        (dict(contrast=0.9, background=0.8), "contrast"),
        (dict(scene="forest"), "scene"),
        (dict(bits=12), "bits"),
        (dict(file_format="jpg", bits=16), "JPEG"),
        (dict(polarity="sideways"), "polarity"),
        (dict(crop_mm=(1, 2)), "crop_mm"),
        (dict(noise_sigma=-0.1), "noise_sigma"),
        (dict(dust=-1), "dust"),
        (dict(cover=500, dpi=100), "cover"),
        (dict(cover=("R99C99",), dpi=100), "R99C99"),
        (dict(crop_mm=(40, 40, 40, 40), dpi=100), "crop"),
    ],
)
def test_bad_specs_raise_one_line(kw, word):
    with pytest.raises(SoftplotError) as e:
        render_scan("rollei-6006", ScanSpec(**kw), seed=0)
    assert word in str(e.value) and "\n" not in str(e.value)


def test_truth_keys():
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=150), seed=0)
    for key in ("image", "camera", "width", "height", "dpi", "polarity", "bit_depth", "channels",
                "seed", "marks", "mapping", "render"):
        assert key in truth
    for key in ("blur_sigma_px", "noise_sigma", "contrast", "line_width_px",
                "arm_half_length_px"):
        assert isinstance(truth["render"][key], float)
    m = truth["marks"][12]
    assert (m["kind"], m["name"], m["row"], m["col"]) == ("reseau", "R1C1", 1, 1)
    assert (m["film_x"], m["film_y"]) == (-20.0, 20.0)
    assert m["state"] in ("visible", "covered", "cut", "outside")
    # row 0 on top, col 0 on the left in the upright scan
    top_left, bottom_right = truth["marks"][0], truth["marks"][-1]
    assert top_left["x"] < bottom_right["x"] and top_left["y"] < bottom_right["y"]
    assert math.isclose(truth["dpi"], 150.0)


def _film_quadrature_centroid(mapping, centre, shape) -> np.ndarray:
    """Exact pixel centroid of a deformed mark: integrate p(f) |det J(f)| over its film shape."""
    xg, wg = np.polynomial.legendre.leggauss(24)  # the mapping is smooth over a mark
    num, den = np.zeros(2), 0.0

    def add(pts, w, sign):
        nonlocal num, den
        det = np.abs(np.linalg.det(mapping.jacobian(pts)))
        num = num + sign * (w * det) @ mapping.film_to_pixel(pts)
        den = den + sign * float((w * det).sum())

    def panels(h):
        e = np.linspace(-h, h, 3)
        a, b = e[:-1, None], e[1:, None]
        xs = ((xg[None, :] + 1) / 2 * (b - a) + a).ravel()
        ws = (wg[None, :] / 2 * (b - a)).ravel()
        return xs, ws

    for hx, hy, sign in shape.rects:
        (x, wx), (y, wy) = panels(hx), panels(hy)
        xx, yy = np.meshgrid(x, y)
        add(centre + np.column_stack([xx.ravel(), yy.ravel()]), np.outer(wy, wx).ravel(), sign)
    nth = 96  # trapezoid rule on a smooth periodic integrand
    th = (np.arange(nth) + 0.5) * 2 * np.pi / nth
    for rad, sign in shape.discs:
        r = (xg + 1) / 2 * rad
        rr, tt = np.meshgrid(r, th)
        w = np.outer(np.full(nth, 2 * np.pi / nth), wg / 2 * rad * r)
        pts = centre + np.column_stack([(rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel()])
        add(pts, w.ravel(), sign)
    return num / den


@pytest.mark.parametrize("dpi,rot,blur", [(600, 0.0, 0.5), (1500, 3.7, 1.0), (2400, -6.0, 0.7)])
def test_deformed_mark_centroid_matches_film_quadrature(dpi, rot, blur):
    """Through the full mapping: the imaged mark's centroid is that of the deformed shape."""
    from softplot.synthetic.mapping import Deformation, Scanner, TruthMapping
    from softplot.synthetic.marks import circle_dot_shape, cross_shape, render_marks

    d = Deformation.random((56.0, 56.0), 100.0, 500.0, np.random.default_rng(1))
    m = TruthMapping(d, Scanner(dpi, rot, 800.0, 3000.0, 3000.0))
    centres = np.array([[24.0, 24.0], [20.3, -17.1], [-11.0, 3.0]])
    for shape in (cross_shape(0.8, 0.04), circle_dot_shape(1.6, 0.08, 0.15)):
        idx, col, row, val, blurred = render_marks(m, centres, shape, blur)
        assert blurred
        shifts = []
        for k, c in enumerate(centres):
            sel = idx == k
            got = np.array([(val[sel] * col[sel]).sum(), (val[sel] * row[sel]).sum()])
            got /= val[sel].sum()
            ref = _film_quadrature_centroid(m, c, shape)
            assert np.max(np.abs(got - ref)) < 2e-4, (shape.kind, got - ref)
            shifts.append(np.max(np.abs(ref - m.film_to_pixel(c))))
        if shape.kind == "circle-dot" and dpi >= 1500:
            assert max(shifts) > 2e-3  # the curvature is really there (and rendered)


def test_truth_reports_the_curvature_shift():
    spec = ScanSpec(dpi=600, deform_um=100, crop_mm=(15, 15, 15, 15), **CLEAN)
    img, truth = render_scan("rollei-6006", spec, seed=4)
    from softplot.synthetic import TruthMapping
    from softplot.synthetic.marks import cross_shape

    m = TruthMapping.from_truth(truth)
    for k in [k for k in truth["marks"] if k["state"] == "visible"][:5]:
        ref = _film_quadrature_centroid(m, np.array([k["film_x"], k["film_y"]]),
                                        cross_shape(0.8, 0.04))
        shift = ref - np.array([k["x"], k["y"]])
        assert np.allclose(k["centroid_shift_px"], shift, atol=5e-5)
