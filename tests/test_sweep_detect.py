"""The detection robustness sweep (``softplot.synthetic.sweep``, ``tools/sweep_detect.py``):
its cases do what they say, and detection meets the targets on a sample of them.

Targets, per condition (pooled over that condition's renders): every scan that shows 3 x 3
detectable crosses gives a result, at least 99.5 % of the detectable crosses measured (crosses
below detection, ``mark_snr``, are neither required nor claims unless measured grossly off),
0 wrong row/col, 0 claims on invisible crosses, RMS at most 1.25x the Cramer-Rao bound
(one-armed crosses across their bar against their own bound), normalised-error RMS within
0.67-1.5. Each condition runs ``RENDERS`` renders that
have it; the default run samples the conditions (``conftest.sweep``), SOFTPLOT_FULL=1 runs
them all. The full sweep (520 renders) is ``tools/sweep_detect.py --full``.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import sweep
from softplot.synthetic.scan import render_scan
from softplot.synthetic.sweep import (
    CONDITIONS,
    LAYOUTS,
    aggregate,
    failure_lines,
    make_case,
    misses,
    run_case,
    table,
)

#: renders per condition in the test (the first seeds from SEED0 that have it and render
#: at most MAX_PX pixels: the test's sample keeps to scans of moderate size)
RENDERS = 2
SEED0 = 10_000
MAX_PX = 9e6

#: conditions whose sample still missed a target with the detector of c20eec3 (run at
#: 01:30 UTC on 2026-12-04), and what it missed there (xfail, not strict: they pass as the
#: detector improves; then remove them here). The failing cases, one by one:
#: tools/sweep_detect.py --failures
FAILING: dict[str, str] = {
    "arm<0.7x": (
        "result on 1/2 scans; measured 92.91 % of visible; RMS 12.75x CRB; normalised-"
        "error RMS 4.64"),
    "arm>1.5x": "result on 0/2 scans; measured 0.00 % of visible",
    "width<0.75x": "RMS 2.09x CRB; normalised-error RMS 3.58",
    "width>1.5x": (
        "result on 1/2 scans; measured 27.27 % of visible; RMS 1.64x CRB; one-armed RMS "
        "3.48x CRB; normalised-error RMS 1.75"),
    "rotation>2deg": "measured 99.22 % of visible; RMS 12.32x CRB; normalised-error RMS 4.48",
    "quarter-turn": "result on 0/2 scans; measured 0.00 % of visible",
    "half-turn": "RMS 2.09x CRB; one-armed RMS 3.48x CRB; normalised-error RMS 3.61",
    "anisotropy": (
        "result on 1/2 scans; measured 67.11 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "off-centre": (
        "result on 1/2 scans; measured 92.59 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "half-frame": "result on 0/2 scans; measured 0.00 % of visible",
    "quarter-frame": "result on 0/2 scans; measured 0.00 % of visible",
    "dpi<400": "result on 0/2 scans; measured 0.00 % of visible",
    "dpi>=2000": "result on 0/2 scans; measured 0.00 % of visible",
    "blur>1.5px": "result on 1/2 scans; measured 15.52 % of visible",
    "jpeg": "result on 0/2 scans; measured 0.00 % of visible",
    "web-copy": (
        "result on 1/2 scans; measured 92.59 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "16-bit": "result on 1/2 scans; measured 14.04 % of visible",
    "rgb": "result on 0/2 scans; measured 0.00 % of visible",
    "negative": (
        "result on 1/2 scans; measured 50.00 % of visible; RMS 1.64x CRB; one-armed RMS "
        "3.48x CRB; normalised-error RMS 1.75"),
    "colour-negative": (
        "result on 1/2 scans; measured 92.59 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "low-contrast": "result on 0/2 scans; measured 0.00 % of visible",
    "dust": (
        "result on 1/2 scans; measured 92.59 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "scratches": (
        "result on 1/2 scans; measured 92.59 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "busy": "result on 0/2 scans; measured 0.00 % of visible",
    "one-armed": (
        "result on 1/2 scans; measured 10.23 % of visible; RMS 1.64x CRB; one-armed RMS "
        "3.48x CRB; normalised-error RMS 1.75"),
    "centre-cross": "measured 99.22 % of visible; RMS 12.32x CRB; normalised-error RMS 4.48",
    # since the dark band lies over rows the scan shows (before, on parts of the frame it
    # often fell outside them): run on 2026-12-04 08:30 UTC, detector of 25b0aec
    "dark-rows": "measured 98.97 % of visible",
    "layout:rollei-6006": (
        "result on 1/2 scans; measured 67.11 % of visible; RMS 2.09x CRB; normalised-"
        "error RMS 3.72"),
    "layout:hasselblad-mk70": "result on 0/2 scans; measured 0.00 % of visible",
    "layout:plate-13x18-reseau": "result on 0/2 scans; measured 0.00 % of visible",
    "layout:aerial-23x47": "result on 0/2 scans; measured 0.00 % of visible",
}


def _seeds(cond: str, k: int = RENDERS) -> list[int]:
    out = []
    s = SEED0
    while len(out) < k and s < SEED0 + 5000:
        c = make_case(s)
        if cond in c.conditions:
            img_px = _pixels(c)
            if img_px <= MAX_PX:
                out.append(s)
        s += 1
    return out


def _pixels(case) -> float:
    """Pixels of a case's render without rendering it (the frame's size at its dpi, crop)."""
    from softplot.camera import load_camera

    cam = load_camera(case.camera)
    ppm = case.spec.dpi / 25.4
    crop = np.ravel(np.asarray(case.spec.crop_mm, float))
    crop = np.array([crop[0], crop[0], 0, 0]) if crop.size == 1 else crop
    m = 2 * case.spec.margin_mm
    w = (cam.format_mm[0] + m) * ppm
    h = (cam.format_mm[1] + m) * ppm
    if abs(((case.spec.rotation_deg + 45) % 180) - 45) > 45:  # a quarter turn
        w, h = h, w
    return max(w - (crop[0] + crop[2]) * ppm, 16) * max(h - (crop[1] + crop[3]) * ppm, 16)


ROWS = list(CONDITIONS) + [f"layout:{n}" for n in LAYOUTS]


def _params(k: int) -> list:
    """``conftest.sweep`` of the rows, the still failing ones marked xfail."""
    out = []
    for c in sweep(ROWS, k, seed=20):
        if isinstance(c, str) and c in FAILING:
            c = pytest.param(c, marks=pytest.mark.xfail(reason=FAILING[c], strict=False))
        out.append(c)
    return out


@pytest.mark.parametrize("cond", _params(5))
def test_sweep_condition_meets_the_targets(cond):
    seeds = _seeds(cond)
    assert seeds, f"no case of {cond}"
    results = []
    notes = []
    for s in seeds:
        case = make_case(s)
        sc, _ = run_case(case)
        results.append((case, sc))
        notes += [f"seed {s}: {b}" for b in failure_lines(case, sc)]
    agg = aggregate(results)
    row = agg[cond]
    bad = misses(row)
    assert not bad, f"{cond}: {'; '.join(bad)}\n{table({cond: row})}\n" + "\n".join(notes)


# -- the cases themselves -----------------------------------------------------------------


def test_cases_are_seeded_and_cover_every_condition():
    a, b = make_case(123), make_case(123)
    assert a.spec == b.spec and a.conditions == b.conditions and a.jpeg == b.jpeg
    seen = {c: 0 for c in ROWS}
    for s in range(520):
        for c in make_case(s).conditions:
            seen[c] += 1
    # every condition appears in the full run, most of them in dozens of renders
    assert min(seen.values()) >= 15, seen
    assert sorted(seen.values())[len(seen) // 2] >= 60


def test_case_ranges_are_the_sweeps():
    cases = [make_case(s) for s in range(400)]
    arm = np.array([c.spec.mark_arm_scale for c in cases])
    wid = np.array([c.spec.mark_width_scale for c in cases])
    opa = np.array([c.spec.mark_opacity for c in cases])
    dpi = np.array([c.spec.dpi for c in cases])
    blur = np.array([c.spec.blur_sigma_px for c in cases])
    rot = np.array([(c.spec.rotation_deg - c.rotate) for c in cases])
    q = np.array([c.jpeg for c in cases if c.jpeg])
    assert arm.min() < 0.45 and arm.max() > 2.4 and wid.min() < 0.55 and wid.max() > 1.9
    assert 0.6 <= opa.min() < 0.65 and opa.max() <= 1.0
    assert dpi.min() < 260 and dpi.max() > 3000
    assert 0.5 <= blur.min() < 0.6 and 2.4 < blur.max() <= 2.5
    assert np.abs(rot).max() <= 5.0 and np.abs(rot).max() > 4.8
    assert {c.rotate for c in cases} == {0.0, 90.0, 180.0, 270.0}
    assert q.min() < 45 and q.max() > 90
    aniso = np.array([abs(c.spec.anisotropy_ppm) for c in cases])
    assert aniso.max() > 2800 and aniso.max() <= 3000


@pytest.mark.parametrize("cond", ["half-frame", "quarter-frame", "crop"])
def test_partial_frames_show_at_least_3x3_crosses(cond):
    """A part of the frame always shows a block of at least 3 x 3 whole crosses (the least
    the detector is asked to work with), and a half or quarter frame hides some."""
    for s in _seeds(cond, 3):
        case = make_case(s)
        img, truth = render_scan(case.camera, case.spec, case.seed)
        vis = [(m["row"], m["col"]) for m in truth["marks"] if m["state"] in ("visible", "dark")]
        rows = {r for r, _ in vis}
        cols = {c for _, c in vis}
        assert len(rows) >= 3 and len(cols) >= 3, (s, case.describe())
        # an edge of the frame on each axis: the first or the last row and col are shown
        nr = max(m["row"] for m in truth["marks"]) + 1
        nc = max(m["col"] for m in truth["marks"]) + 1
        assert {0, nr - 1} & rows and {0, nc - 1} & cols, (s, case.describe())
        if cond != "crop":
            assert len(vis) < len(truth["marks"])


def test_web_copies_are_about_1000_px():
    for s in _seeds("web-copy", 3):
        case = make_case(s)
        img, _ = render_scan(case.camera, case.spec, case.seed)
        assert 800 <= max(img.shape[:2]) <= 1300 and case.jpeg and case.jpeg <= 75


def test_scoring_counts_what_went_wrong():
    """The score of a detection against its truth: an exact detection scores everything
    measured with no error; a cross given the neighbour's position is a wrong row/col, a
    cross claimed under a dark region is a claim on an invisible cross."""
    from types import SimpleNamespace

    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import score

    _, truth = render_scan("rollei-6006", ScanSpec(dpi=400, dark_rows=((0, 0),)), 3)
    ms = truth["marks"]
    xy = np.array([[m["x"], m["y"]] for m in ms])
    det = SimpleNamespace(
        name=[m["name"] for m in ms], kind=["reseau"] * len(ms),
        status=["missing" if m["state"] == "dark" else "measured" for m in ms],
        reason=[""] * len(ms), xy=xy.copy(), sigma_xy=np.full((len(ms), 2), 0.01))
    bounds = {m["name"]: 0.01 for m in ms}
    sc = score(det, truth, bounds)
    assert sc.measured == sc.visible == 110 and not (sc.wrong or sc.claimed or sc.missed)
    assert max(sc.err2) < 1e-20
    det.xy[20] = xy[21]  # R1C9 at R1C10
    det.status[0] = "measured"  # R0C0 under the dark region
    det.xy[30] += (1.5, 0.0)  # 1.5 px off: gross (and in the RMS)
    sc = score(det, truth, bounds)
    assert len(sc.wrong) == 1 and "R1C9" in sc.wrong[0]
    assert sc.claimed == ["R0C0 (dark)"]
    assert len(sc.gross) == 1 and sc.measured == 109
    assert max(sc.err2) == pytest.approx(1.5**2 / 2)


def test_renders_that_cannot_show_their_rows_are_recognised():
    """A part of the frame names its rows only where it shows an end row of the grid and the
    format's edge beyond it: a flat dark region over the only end row shown hides both."""
    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import identifiable

    part = dict(dpi=250, crop_mm=(0.0, 0.0, 19.0, 19.0))  # the top-left of the frame
    _, truth = render_scan("rollei-6006", ScanSpec(**part), 1)
    assert identifiable(truth) == ""
    _, truth = render_scan("rollei-6006", ScanSpec(**part, dark_rows=((0, 0),)), 1)
    assert "row" in identifiable(truth) and "col" not in identifiable(truth)
    # the same dark row on the whole frame: the last row and the bottom edge name the rows
    _, truth = render_scan("rollei-6006", ScanSpec(dpi=250, dark_rows=((0, 0),)), 1)
    assert identifiable(truth) == ""
    # a 30-50 % dark region leaves its crosses visible, and the edge
    _, truth = render_scan("rollei-6006", ScanSpec(**part, dark_rows=((0, 0),),
                                                  dark_level=0.4), 1)
    assert identifiable(truth) == ""
    assert all(m["state"] == "visible" for m in truth["marks"] if m["row"] == 0
               and m["col"] <= 5)
    _, truth = render_scan("rollei-6006", ScanSpec(**part, dark_rows=((0, 4),)), 1)
    assert identifiable(truth).startswith("fewer than 3 x 3")


def test_dark_rows_of_the_sweep_lie_in_the_part_shown_and_leave_3x3():
    """The sweep's flat dark regions cover rows the scan shows (else the condition would be
    a label only) and leave at least 3 rows of it exposed."""
    n = 0
    for s in range(300):
        c = make_case(s)
        if "dark-rows" not in c.conditions:
            continue
        n += 1
        (r0, r1), = c.spec.dark_rows
        c0, c1, p0, p1 = c.part
        assert p0 <= r0 <= r1 < p1 and (p1 - p0) - (r1 - r0 + 1) >= 3, (s, c.part, r0, r1)
    assert n >= 30


def test_an_ambiguous_render_is_scored_by_what_the_detection_says():
    """On a render that cannot show its rows, a grid named one row off is a measurement of
    the crosses it sits on when the detection says that its rows are ambiguous, and wrong
    row/col when it guesses silently."""
    from types import SimpleNamespace

    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import identifiable, score

    _, truth = render_scan("rollei-6006", ScanSpec(dpi=250, crop_mm=(0.0, 0.0, 19.0, 19.0),
                                                   dark_rows=((0, 0),)), 1)
    why = identifiable(truth)
    assert why
    ms = [m for m in truth["marks"] if m["kind"] == "reseau"]
    by = {(m["row"], m["col"]): m for m in ms}
    # every visible cross named one row up (R1C0's cross as R0C0, ...)
    xy = np.full((len(ms), 2), np.nan)
    status = []
    for k, m in enumerate(ms):
        below = by.get((m["row"] + 1, m["col"]))
        if below is not None and below["state"] == "visible":
            xy[k] = (below["x"], below["y"])
            status.append("measured")
        else:
            status.append("missing")
    det = SimpleNamespace(name=[m["name"] for m in ms], kind=["reseau"] * len(ms),
                          status=status, reason=[""] * len(ms), xy=xy,
                          sigma_xy=np.full((len(ms), 2), 0.01), warnings=[],
                          ids_ambiguous=False)
    bounds = {m["name"]: 0.01 for m in ms}
    silent = score(det, truth, bounds, why)
    assert len(silent.wrong) == silent.visible and silent.measured == 0
    assert not silent.claimed  # on crosses, not on nothing
    assert failure_lines(make_case(0), silent)[0].startswith("wrong row/col")
    det.ids_ambiguous = True
    said = score(det, truth, bounds, why)
    assert not said.wrong and not said.claimed and not said.missed
    assert said.measured == said.visible == len(said.ambiguous) > 9
    assert max(said.err2) < 1e-20
    # on a render that shows its rows, saying "ambiguous" does not excuse a wrong name
    assert score(det, truth, bounds, "").wrong


def test_renders_are_cached_exactly(tmp_path):
    """A render kept by ``render_case(case, cache)`` comes back the same, bit for bit, and a
    case that differs gets its own render."""
    from dataclasses import replace

    from softplot.synthetic.sweep import render_case

    seed = min(range(40), key=lambda s: _pixels(make_case(s)))
    case = make_case(seed)
    a = render_case(case, tmp_path)
    b = render_case(case, tmp_path)
    assert np.array_equal(a[0], b[0]) and a[0].dtype == b[0].dtype
    assert a[1] == b[1] and a[3] == b[3]
    assert (a[2] is None) == (b[2] is None)
    other = replace(case, spec=replace(case.spec, noise_sigma=case.spec.noise_sigma * 2))
    render_case(other, tmp_path)
    assert len(list(tmp_path.glob("*.json"))) == 2


def test_truth_of_a_jpeg_case_says_it_is_a_jpeg(tmp_path):
    """A case compressed after rendering keeps a truth that names the format and quality it
    is stored with (not the render spec's TIFF default), fresh and from the cache alike."""
    from softplot.synthetic.sweep import render_case

    seed = min((s for s in range(60) if make_case(s).jpeg), key=lambda s: _pixels(make_case(s)))
    case = make_case(seed)
    for _ in range(2):  # rendered, then read back from the cache
        truth = render_case(case, tmp_path)[1]
        assert truth["spec"]["file_format"] == "jpeg"
        assert truth["spec"]["jpeg_quality"] == case.jpeg


def test_one_armed_crosses_are_scored_along_their_bar_too():
    """A one-armed cross (or a lone bar measured on a cross) is scored across its bar against
    its bound, and along it by its normalised error: a position along the bar 3 sigma off
    shows as 3, not hidden by the across-bar figures."""
    from types import SimpleNamespace

    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import aggregate, misses, score

    _, truth = render_scan("rollei-6006", ScanSpec(dpi=400, one_armed=6), 3)
    ms = truth["marks"]
    xy = np.array([[m["x"], m["y"]] for m in ms])
    one = [i for i, m in enumerate(ms) if m["arms"] == 1 and m["state"] == "visible"
           and not m["damaged"]]
    two = next(i for i, m in enumerate(ms) if m["arms"] == 2 and m["state"] == "visible"
               and not m["damaged"])
    assert len(one) >= 3
    cov = np.tile(np.diag([1e-4, 1e-4]), (len(ms), 1, 1))
    arms = np.full(len(ms), 2)
    for i in one + [two]:  # lone bars: along x (pixel system) 0.5 px, across 0.01 px
        cov[i] = np.diag([0.25, 1e-4])
        arms[i] = 1
    det = SimpleNamespace(
        name=[m["name"] for m in ms], kind=["reseau"] * len(ms), status=["measured"] * len(ms),
        reason=[""] * len(ms), xy=xy.copy(), cov=cov, arms=arms)
    bounds = {m["name"]: 0.01 for m in ms}
    exact = score(det, truth, bounds)
    assert len(exact.z2_along) == len(one) + 1 and max(exact.z2_along) < 1e-20
    det.xy[two] += (1.5, 0.0)  # 3 sigma along the lone bar
    sc = score(det, truth, bounds)
    assert max(sc.z2_along) == pytest.approx(9.0)
    row = aggregate([(make_case(0), sc)])["all"]
    assert row["z_along_rms"] == pytest.approx(np.sqrt(9.0 / len(sc.z2_along)))
    assert not any("along the bar" in m for m in misses(row))
    det.xy[two] += (2.0, 0.0)  # 7 sigma: the pooled figure goes above 1.5, a miss
    row = aggregate([(make_case(0), score(det, truth, bounds))])["all"]
    assert row["z_along_rms"] > 1.5
    assert any("along the bar" in m for m in misses(row))


def test_a_lone_bar_on_a_cross_is_scored_along_the_bar_the_detection_names():
    """A lone bar measured on a two-armed cross whose prediction along the bar is more
    certain than the fit across it (the covariance's larger axis across the bar): scored
    along the bar the detection says it measured (``Detection.bar``), not along the larger
    axis. Counterfactual: without ``bar`` the error along the bar is taken across it."""
    from types import SimpleNamespace

    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import score

    _, truth = render_scan("rollei-6006", ScanSpec(dpi=400), 3)
    ms = truth["marks"]
    xy = np.array([[m["x"], m["y"]] for m in ms])
    two = next(i for i, m in enumerate(ms) if m["arms"] == 2 and m["state"] == "visible"
               and not m["damaged"])
    cov = np.tile(np.diag([1e-4, 1e-4]), (len(ms), 1, 1))
    cov[two] = np.diag([0.04, 0.09])  # a bar along x (pixel system): 0.2 px along, 0.3 across
    arms = np.full(len(ms), 2)
    arms[two] = 1
    bar = np.full((len(ms), 2), np.nan)
    bar[two] = (1.0, 0.0)
    det = SimpleNamespace(
        name=[m["name"] for m in ms], kind=["reseau"] * len(ms), status=["measured"] * len(ms),
        reason=[""] * len(ms), xy=xy.copy(), cov=cov, arms=arms, bar=bar)
    det.xy[two] += (0.6, 0.0)  # 3 sigma along the bar
    bounds = {m["name"]: 0.01 for m in ms}
    assert score(det, truth, bounds).z2_along == [pytest.approx(9.0)]
    det.bar = None  # a detection that does not say: the larger axis, across the bar
    assert score(det, truth, bounds).z2_along == [pytest.approx(0.0, abs=1e-20)]


def test_one_armed_crosses_are_compared_with_their_renders_whole_crosses():
    """``rms1_over_render``: one-armed crosses as far off across their bar, for their bound,
    as their render's whole crosses are score 1 however hard the render (a render at 3x its
    bounds and one at 1x); one-armed crosses twice as far off as that score 2; a render
    without measured whole crosses is left out. The same from the logs' pooled sums."""
    from softplot.synthetic.sweep import Score, aggregate, one_arm_over_render

    def render(q, q1, n1=3, n2=5):  # whole crosses at q x their bound, one-armed at q1 x
        b2, b1 = np.linspace(0.02, 0.1, n2), np.linspace(0.05, 0.2, n1)
        return Score(result=True, err2=list((q * b2) ** 2), crb2=list(b2**2),
                     err2_1=list((q1 * b1) ** 2), crb2_1=list(b1**2))

    alike = [render(3.0, 3.0), render(1.0, 1.0)]
    assert one_arm_over_render(alike) == pytest.approx(1.0)
    assert aggregate([(make_case(0), s) for s in alike])["all"]["rms1_over_crb1"] > 2.0
    worse = [render(3.0, 6.0), render(1.0, 2.0), Score(err2_1=[1.0], crb2_1=[1e-4])]
    assert one_arm_over_render(worse) == pytest.approx(2.0)
    logged = [Score.from_dict(s.to_dict()) for s in worse]
    assert one_arm_over_render(logged) == pytest.approx(2.0)
    assert np.isnan(one_arm_over_render([render(2.0, 2.0, n1=0)]))


# -- what is detectable: the crosses' signal-to-noise ratio --------------------------------


def test_the_snr_is_the_rendered_marks_energy_over_the_noise():
    """``mark_snr`` is sqrt(sum s^2) / sigma of the mark as the renderer draws it: ``s`` the
    render minus the same render without marks (noise-free), whole crosses and the single
    bars of one-armed crosses alike, on a rotated scan."""
    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import _pitch_px, mark_snr

    for one_armed in (0, 6):
        spec = ScanSpec(dpi=400, scene="none", noise_sigma=0.0, bits=32, one_armed=one_armed,
                        rotation_deg=3.0)
        img, truth = render_scan("rollei-6006", spec, 3, clip=False)
        bare, _ = render_scan("rollei-6006", spec, 3, marks=False, clip=False)
        s = img.astype(float) - bare
        truth["render"]["noise_sigma"] = 0.01  # the noise the ratio is taken against
        snr = mark_snr(truth)
        h = int(0.45 * _pitch_px(truth))
        ratio = []
        for m in truth["marks"]:
            if m["name"] in snr:
                x, y = int(round(m["x"])), int(round(m["y"]))
                win = s[max(0, y - h): y + h + 1, max(0, x - h): x + h + 1]
                ratio.append(np.sqrt(np.sum(win**2)) / 0.01 / snr[m["name"]][0])
        assert len(ratio) == 121
        assert one_armed == 0 or sum(m["arms"] == 1 for m in truth["marks"]) == 6
        assert np.abs(np.array(ratio) - 1).max() < 0.005, (one_armed, min(ratio), max(ratio))


def test_the_detection_threshold_holds_its_false_alarm_rate():
    """Over white noise, the maximum of the matched filter's normalised output over a
    64 x 64 search exceeds ``detection_threshold(64^2, ...)`` at p_fa = 0.1 in 10 % of the
    trials (Monte Carlo); a threshold that ignores the search (a single position) is passed
    nearly always. A cross at the threshold plus z(p_d) is found with probability p_d."""
    import math

    from scipy.signal import fftconvolve
    from scipy.special import ndtri

    from softplot.synthetic.sweep import _mark_template, _template_energy, detection_threshold

    T = _mark_template(16.0, 2.0, 1.0, np.eye(2), None, phases=1)
    e, rough = _template_energy(T)
    k = (T[0] / math.sqrt(e))[::-1, ::-1]
    n, hk = 64, T.shape[1] // 2
    u = float(detection_threshold(n * n, rough, p_fa=0.1))
    u0 = float(detection_threshold(0.0, rough, p_fa=0.1))
    rng = np.random.default_rng(1)
    peaks = np.array([fftconvolve(rng.standard_normal((n + 2 * hk, n + 2 * hk)), k,
                                  mode="valid").max() for _ in range(1000)])
    assert 0.07 <= np.mean(peaks > u) <= 0.13, (u, np.mean(peaks > u))
    assert np.mean(peaks > u0) > 0.95
    assert float(detection_threshold(n * n, rough, p_fa=0.1, p_d=0.9)) == pytest.approx(
        u + ndtri(0.9))
    # a larger search needs a stronger mark
    assert float(detection_threshold(100 * n * n, rough, p_fa=0.1)) > u + 0.5


def _flat_render(contrast: float, noise: float, **kw):
    from softplot.synthetic import ScanSpec
    from softplot.synthetic.sweep import mark_snr

    _, truth = render_scan("rollei-6006", ScanSpec(dpi=400, scene="none", contrast=contrast,
                                                   noise_sigma=noise, **kw), 3)
    return truth, mark_snr(truth)


def test_a_render_below_detection_is_not_asked_for_a_result():
    """A refusal on a render whose crosses are at SNR 2 misses no target (scored with the
    SNR); the same refusal at SNR 50 does, and so does the one at SNR 2 scored without it
    (the old rule: every render with 3 x 3 visible crosses)."""
    from softplot.synthetic.sweep import aggregate, detectable_render, identifiable, refused

    faint, snr_f = _flat_render(0.03, 0.03)
    clear, snr_c = _flat_render(0.3, 0.01)
    assert max(v[0] for v in snr_f.values()) < 2.5 and min(v[0] for v in snr_c.values()) > 20
    assert detectable_render(faint, snr_f) and identifiable(faint, snr_f)
    assert detectable_render(clear, snr_c) == "" and identifiable(clear, snr_c) == ""

    def row(truth, snr):
        return aggregate([(make_case(0), refused(truth, "no reseau found", snr))])["all"]

    assert not misses(row(faint, snr_f))  # nothing was detectable: nothing missed
    assert row(faint, snr_f)["below"] == 121 and row(faint, snr_f)["required"] == 0
    assert any(m.startswith("result on 0/1") for m in misses(row(clear, snr_c)))
    assert any(m.startswith("result on 0/1") for m in misses(row(faint, None)))


def test_crosses_below_detection_are_neither_missed_nor_claims_unless_gross():
    """On a render with a band of faint crosses (SNR 3, below their threshold) among clear
    ones (SNR 9): the faint ones missed leave the detectable crosses 100 % measured (the old
    figure, of all visible, drops); measured, they are scored for their error; measured
    grossly off, they are claims below detection (and gross, as before). A clear cross
    missed is still a miss."""
    from types import SimpleNamespace

    from softplot.synthetic.sweep import aggregate, identifiable, score

    truth, snr = _flat_render(0.1, 0.02, dark_rows=((3, 4),), dark_level=0.3)
    ms = truth["marks"]
    faint = [i for i, m in enumerate(ms) if m["name"] in snr
             and snr[m["name"]][0] < snr[m["name"]][1]]
    clear = [i for i, m in enumerate(ms) if m["name"] in snr
             and snr[m["name"]][0] >= 2 * snr[m["name"]][1]]
    assert len(faint) == 22 and len(clear) == 99
    assert max(snr[ms[i]["name"]][0] for i in faint) < 3.5
    xy = np.array([[m["x"], m["y"]] for m in ms])
    bounds = {m["name"]: 0.01 for m in ms}
    why = identifiable(truth, snr)
    assert why == ""

    def row(status, xy):
        det = SimpleNamespace(name=[m["name"] for m in ms], kind=["reseau"] * len(ms),
                              status=status, reason=[""] * len(ms), xy=xy,
                              sigma_xy=np.full((len(ms), 2), 0.01))
        return aggregate([(make_case(0), score(det, truth, bounds, why, snr))])["all"]

    status = ["missing" if i in faint else "measured" for i in range(len(ms))]
    r = row(status, xy.copy())
    assert r["measured_detectable_rate"] == 1.0 and r["detectable"] == 99
    assert r["measured_rate"] == pytest.approx(99 / 121)
    assert not [m for m in misses(r) if "measured" in m or "result" in m]  # (exact: z is 0)
    r = row(["measured"] * len(ms), xy.copy())
    assert r["below_measured"] == 22 and r["claimed_below"] == 0 and r["gross"] == 0
    off = xy.copy()
    off[faint[0]] += (1.5, 0.0)
    r = row(["measured"] * len(ms), off)
    assert r["claimed_below"] == 1 and r["gross"] == 1 and r["claimed"] == 0
    assert any("below detection" in m for m in misses(r))
    status[clear[0]] = "missing"
    r = row(status, xy.copy())
    assert r["measured_detectable_rate"] == pytest.approx(98 / 99)
    assert any("of detectable" in m for m in misses(r))


# -- what the stored scan shows: the signal its clipping leaves ---------------------------


def _clipped_busy_render():
    """A noise-free busy render (seed 145's spec at 400 dpi) whose white roads the scan
    saturates: (truth, scene without marks unclipped, per visible cross the share of its
    signal the stored scan keeps, exactly: (clip(M) - clip(S)) over (M - S) in energy, from
    four renders)."""
    from dataclasses import replace

    from softplot.synthetic.sweep import _pitch_px

    case = make_case(145)
    spec = replace(case.spec, noise_sigma=0.0, bits=32, dpi=400.0)
    shown = render_scan(case.camera, spec, 145)[0] - render_scan(case.camera, spec, 145,
                                                                  marks=False)[0]
    img, truth = render_scan(case.camera, spec, 145, clip=False)
    scene = render_scan(case.camera, spec, 145, marks=False, clip=False)[0]
    full = img - scene
    h = int(0.45 * _pitch_px(truth))
    share = {}
    for m in truth["marks"]:
        if m["kind"] == "reseau" and m["state"] == "visible":
            x, y = int(round(m["x"])), int(round(m["y"]))
            win = np.s_[max(0, y - h): y + h + 1, max(0, x - h): x + h + 1]
            share[m["name"]] = float(np.sqrt(np.sum(shown[win] ** 2) / np.sum(full[win] ** 2)))
    truth["render"]["noise_sigma"] = 0.01  # the noise the ratio is taken against
    return truth, scene, share


def test_the_snr_counts_the_signal_the_stored_scan_keeps():
    """With the scene without marks, ``mark_snr`` scales each cross's ratio by the share of
    its signal that survives the scan's clipping: the share the renderer's own clipped and
    unclipped images show (within 0.01), from none (crosses on saturated roads) to all."""
    from softplot.synthetic.sweep import mark_snr

    truth, scene, share = _clipped_busy_render()
    old, new = mark_snr(truth), mark_snr(truth, 0.0, scene)
    got = {k: new[k][0] / old[k][0] for k in old}
    assert set(got) == set(share)
    dev = max(abs(got[k] - share[k]) for k in share)
    assert dev < 0.01, dev
    assert sum(v < 0.05 for v in share.values()) >= 8
    assert sum(v > 0.99 for v in share.values()) >= 50
    assert all(new[k][1:] == old[k][1:] for k in old)  # the thresholds are the same


def test_a_cross_the_clipping_erased_is_below_detection():
    """Scored with the signal the stored scan keeps, a missed cross whose signal the clipping
    erased is below detection, not a detectable cross missed (with the unclipped scene's
    contrast it was one); a cross whose signal survives, missed, is still a miss; a gross
    measurement of an erased cross is a claim below detection."""
    from types import SimpleNamespace

    from softplot.synthetic.sweep import aggregate, identifiable, mark_snr, score

    truth, scene, share = _clipped_busy_render()
    ms = truth["marks"]
    erased = [i for i, m in enumerate(ms) if share.get(m["name"], 1.0) < 0.02]
    kept = [i for i, m in enumerate(ms) if share.get(m["name"], 0.0) > 0.99]
    assert len(erased) >= 5 and kept
    xy = np.array([[m["x"], m["y"]] for m in ms])
    bounds = {m["name"]: 0.01 for m in ms}

    def row(snr, status, xy):
        det = SimpleNamespace(name=[m["name"] for m in ms], kind=["reseau"] * len(ms),
                              status=status, reason=[""] * len(ms), xy=xy,
                              sigma_xy=np.full((len(ms), 2), 0.01))
        sc = score(det, truth, bounds, identifiable(truth, snr), snr)
        return aggregate([(make_case(0), sc)])["all"]

    old, new = mark_snr(truth), mark_snr(truth, 0.0, scene)
    status = ["missing" if i in erased else "measured" for i in range(len(ms))]
    r_new, r_old = row(new, status, xy.copy()), row(old, status, xy.copy())
    assert r_new["measured_detectable_rate"] == 1.0
    assert r_new["below"] - r_old["below"] >= len(erased)
    assert r_old["measured_detectable_rate"] < 1.0  # the unclipped contrast: missed
    assert r_new["measured_rate"] == r_old["measured_rate"] < 1.0  # of visible: unchanged
    status[kept[0]] = "missing"
    assert row(new, status, xy.copy())["measured_detectable_rate"] < 1.0
    off = xy.copy()
    off[erased[0]] += (1.5, 0.0)
    r = row(new, ["measured"] * len(ms), off)
    assert r["claimed_below"] == 1 and r["gross"] == 1
    assert row(old, ["measured"] * len(ms), off)["claimed_below"] == 0
