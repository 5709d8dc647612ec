"""The issue-8 demo chain on a reduced size: accuracy figures against the synthetic truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.pipeline.demo import MARKER, DemoConfig, prepare_out_dir, run_demo


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    cfg = DemoConfig(dpi=600, interval=20.0, vertices=24, tie_grid=4, n_check=6)
    return out, run_demo(out, cfg, progress=False, write_scans=True)


def test_demo_accuracy(demo):
    _, r = demo
    # detection: every cross of both scans, far below a tenth of a pixel
    assert r.detection_measured == [121, 121]
    assert r.detection_rms_px < 0.05
    # film correction at check points over the whole format (mesh + interior orientation)
    assert r.correction_rms_um < 2.0
    assert r.correction_rms_reseau_um < 1.5
    # relative orientation: a posteriori sigma0 in the photo is the film-correction level
    assert 0 < r.relative_sigma0_um < 1.0
    assert 0 < r.absolute_sigma0 < 0.05
    # check points (photo scale ~1:7400: 1 um in the photo ~ 7 mm on the ground)
    assert len(r.check_rms_m) == 3
    assert max(r.check_rms_m) < 0.05
    # contours: two at 20 m, every vertex within travel, true terrain under them at H
    assert r.contours == 2
    assert r.vertices == 2 * 24
    assert r.contour_height_rms_m < 0.03
    assert r.contour_height_max_m < 0.1
    assert r.contour_plan_rms_m < 0.05


def test_demo_outputs(demo):
    out, r = demo
    for key in ("dxf", "geojson", "report", "result"):
        assert (out / r.outputs[key].split("/")[-1]).is_file(), key
    gj = json.loads((out / "contours.geojson").read_text())
    assert len(gj["features"]) == 2
    z = {f["geometry"]["coordinates"][0][2] for f in gj["features"]}
    assert z == {220.0, 240.0}
    html = (out / "report.html").read_text()
    assert "data:image/png;base64," in html and "check points" in html.lower()
    assert json.loads((out / "demo.json").read_text())["vertices"] == r.vertices
    import ezdxf

    doc = ezdxf.readfile(out / "contours.dxf")
    assert len(list(doc.modelspace())) >= 2
    assert np.isfinite(r.seconds)


def test_prepare_out_dir_never_touches_user_files(tmp_path):
    (tmp_path / "mine.txt").write_text("user data")
    d = prepare_out_dir(tmp_path)
    assert d == tmp_path / "softplot-demo" and (d / MARKER).is_file()
    assert (tmp_path / "mine.txt").read_text() == "user data"
    assert prepare_out_dir(tmp_path) == d  # a demo folder is reused
    (d / "x").write_text("1")
    assert prepare_out_dir(d) == d
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(SoftplotError):
        prepare_out_dir(f)


def test_demo_cli_bad_out(tmp_path, capsys):
    from softplot.cli import main

    f = tmp_path / "a-file"
    f.write_text("user data")
    with pytest.raises(SystemExit) as e:
        main(["demo", "--out", str(f), "--quiet"])
    assert e.value.code == 2
    assert f.read_text() == "user data"
    err = capsys.readouterr().err
    assert "a-file" in err and "Traceback" not in err


def test_demo_writes_a_session_ready_to_view(demo):
    """OUT/session: the demo's scans (checked by content), film corrections as data, the
    oriented model and the contours it traced; a scan pixel maps to the photo and back."""
    from softplot.pipeline.session import Session

    out, r = demo
    s = Session.resume(out / "session")
    try:
        assert len(s.features) == r.contours
        assert s.mode == "contour"
        for side in ("left", "right"):
            assert s.scan_path(side) == (out / f"{side}.tif").resolve()
            m = s.photo_map(side)
            px = np.array([[100.25, 200.5], [700.0, 650.75]])
            back = m.photo_to_pixel(m.pixel_to_photo(px))
            assert np.max(np.abs(back - px)) < 1e-6
        # a recorded contour vertex, seen in the right scan through the session's model and
        # film correction, is restituted back onto itself at the contour height
        XYZ = s.features[0].vertices[:3]
        instr = s.model.right.photo_to_film(s.model.right.project(XYZ))
        res = s.model.contour(s.model.right.film_to_photo(instr), float(XYZ[0, 2]))
        assert np.max(np.abs(res.XYZ - XYZ)) < 1e-6
    finally:
        s.close()


def test_demo_report_shows_the_film(demo):
    """The report holds the scans (thumbnails with crosses), the contours over the left scan,
    the check points with their RMS and the orientation with standard deviations and units."""
    import re

    out, r = demo
    html = (out / "report.html").read_text()
    # thumbnails of both scans, contours over the left scan and in plan, detection scatter
    assert html.count("data:image/png;base64,") == 5
    assert "left scan (thumbnail" in html and "right scan (thumbnail" in html
    assert "contours over the left scan" in html
    # an RMS row under the check points, equal to the demo's figures
    rms = re.search(r"<td>RMS</td>((?:<td>[^<]*</td>){3})", html)
    assert rms is not None
    got = [float(v) for v in re.findall(r"<td>([^<]*)</td>", rms.group(1))]
    assert np.allclose(got, r.check_rms_m, rtol=1e-3)
    # the orientation table: value, std, unit for every parameter (5 relative + 7 absolute)
    rows = re.findall(r"<tr><td>(relative|absolute)</td><td>(\w+)</td><td>([^<]*)</td>"
                      r"<td>([^<]*)</td><td>([^<]*)</td></tr>", html)
    assert len(rows) == 12
    assert all(float(sd) > 0 and unit for *_, sd, unit in rows)
    assert {unit for *_, unit in rows} >= {"deg", "m"}
    assert "softplot 0." in html and "UTC" in html


def test_report_figures_and_rows():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from softplot.pipeline.demo import _check_rows, _detection_figure, _scan_figure, _value_std_text

    rows = _check_rows([[3.0, 1.0, 0.0], [-4.0, -1.0, 2.0]])
    assert rows[-1][0] == "RMS"
    assert np.allclose(rows[-1][1:], [np.sqrt(12.5), 1.0, np.sqrt(2.0)])
    assert _value_std_text(123.45678, 0.0123) == ("123.457", "0.012")
    assert _value_std_text(0.5, 2.6) == ("0.5", "2.6")
    # a scan with measured, missing and rejected crosses: all three drawn and named
    marks = [{"name": "a", "x": 10.0, "y": 10.0, "status": "measured"},
             {"name": "b", "x": 50.0, "y": 10.0, "status": "measured"},
             {"name": "c", "x": 10.0, "y": 50.0, "status": "rejected"},
             {"name": "d", "x": 50.0, "y": 50.0, "status": "missing"}]
    scan = {"image": np.zeros((64, 64), np.uint16), "det": {"marks": marks},
            "d": np.array([[0.01, -0.02], [0.03, 0.0]])}
    fig = _scan_figure(plt, scan, "left")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["measured (2)", "missing (1)", "rejected (1)"]
    # detection scatter: both panels on one scale, equal axes
    scan2 = {**scan, "d": np.array([[0.2, 0.1], [-0.1, 0.0]])}
    fig = _detection_figure(plt, [scan, scan2])
    a, b = fig.axes
    assert a.get_xlim() == b.get_xlim() == a.get_ylim() == b.get_ylim()
    assert a.get_xlim()[1] >= 0.2
    assert a.get_aspect() == b.get_aspect() == 1.0
    plt.close("all")
