"""The plotter loop with virtual motors: contours, single points, faults, drive-to."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.motors import AxisConfig, MotorAlarm, VirtualMotors
from softplot.stereo.model import OrientedPhoto, StereoModel
from softplot.stereo.plotter import Plotter, PlotterHalted
from softplot.synthetic.stereo import aerial_pair

FINE = AxisConfig(resolution_mm=1e-7, min_mm=-150, max_mm=150, max_speed_mm_s=1e9)


def _model(t, corrections):
    photos = []
    for k in range(2):
        f2p, p2f = t.corrections(k) if corrections else (None, None)
        photos.append(OrientedPhoto(t.X0[k], t.angles[k], t.c[k], t.x0[k], t.y0[k], f2p, p2f))
    return StereoModel(*photos)


@pytest.mark.parametrize("corrections", [False, True])
@pytest.mark.parametrize("H", [250.0, 340.0])
def test_contour_traced_by_the_operator(corrections, H):
    """The operator follows the true contour with the main carriage over the right film;
    the plotter drives DX, DY and records a contour at exactly H with the true planimetry."""
    t = aerial_pair(seed=11, deform=corrections)
    model = _model(t, corrections)
    mot = VirtualMotors(FINE, FINE)
    pl = Plotter(model, mot, mode="contour", height=H)
    C = t.contour_truth(H, 72)
    right_film, left_film = t.film(1, C), t.film(0, C)
    pl.begin("CONTOUR")
    for (X, Y), lf in zip(right_film, left_film, strict=True):
        cyc = pl.cycle(X, Y)
        # the left plate sits where the terrain point is imaged: the mark is on the ground
        assert np.max(np.abs(np.array(mot.left_film()) - lf)) < 1e-6
        assert cyc.in_travel
        pl.vertex()
    feat = pl.end(close=True)
    assert feat.kind == "contour" and feat.closed
    v = feat.vertices
    assert np.max(np.abs(v[:, 2] - H)) < 1e-6
    assert np.max(np.hypot(*(v[:-1, :2] - C[:, :2]).T)) < 1e-6


@pytest.mark.parametrize("corrections", [False, True])
def test_single_point_mode_removes_y_parallax(corrections):
    t = aerial_pair(seed=12, deform=corrections)
    model = _model(t, corrections)
    mot = VirtualMotors(FINE, FINE)
    pl = Plotter(model, mot, mode="single")
    P = t.sample_points(40, seed=3)
    rf, lf = t.film(1, P), t.film(0, P)
    for (X, Y), (x1f, y1f), truth in zip(rf, lf, P, strict=True):
        cyc = pl.cycle(X, Y, px=x1f - X)  # the handwheel set on the true x-parallax
        assert abs(cyc.DY - (y1f - Y)) < 1e-9
        # y-parallax of the computed photo points, independently
        py = model.y_parallax([[cyc.x1, cyc.y1]], [[cyc.x2, cyc.y2]])[0]
        assert abs(py) < 1e-9
        assert np.max(np.abs(np.array(cyc.XYZ) - truth)) < 1e-6
        pl.record_point("SPOT")
    assert len(pl.features) == 40
    assert all(f.kind == "point" for f in pl.features)


def test_free_mode_reads_the_carriages_and_reports_parallax():
    t = aerial_pair(seed=13, deform=False)
    model = _model(t, False)
    mot = VirtualMotors(FINE, FINE)
    pl = Plotter(model, mot, mode="free")
    P = t.sample_points(1, seed=5)
    (x1, y1), (x2, y2) = t.photo(0, P)[0], t.photo(1, P)[0]
    mot.move_to(x1 - x2, y1 - y2 + 0.02)  # operator leaves 0.02 mm of y-parallax
    cyc = pl.cycle(x2, y2)
    assert abs(cyc.py - 0.02) < 1e-6
    assert np.linalg.norm(np.array(cyc.XYZ) - P[0]) < 1.0


def test_drive_to_puts_mark_on_object_point():
    t = aerial_pair(seed=14, deform=True)
    model = _model(t, True)
    mot = VirtualMotors(FINE, FINE)
    pl = Plotter(model, mot, mode="single")
    P = t.sample_points(5, seed=2)
    for p in P:
        cyc = pl.drive_to(*p)
        assert np.max(np.abs(np.array(mot.encoders()) - t.film(1, p[None])[0])) < 1e-9
        assert np.max(np.abs(np.array(mot.left_film()) - t.film(0, p[None])[0])) < 1e-6
        assert abs(cyc.py) < 1e-9


def test_step_grid_of_the_instrument():
    """With 0.01 mm steps the left plate is within half a step of the computed position."""
    t = aerial_pair(seed=15, deform=False)
    model = _model(t, False)
    ax = AxisConfig(resolution_mm=0.01, min_mm=-150, max_mm=150)
    mot = VirtualMotors(ax, ax)
    pl = Plotter(model, mot, mode="contour", height=300.0)
    for X, Y in t.film(1, t.contour_truth(300.0, 20)):
        cyc = pl.cycle(X, Y)
        dx, dy = mot.position()
        assert abs(dx - cyc.DX) <= 0.005 + 1e-12 and abs(dy - cyc.DY) <= 0.005 + 1e-12
        assert abs(round(dx / 0.01) * 0.01 - dx) < 1e-12


def test_out_of_travel_is_reported_not_raised():
    t = aerial_pair(seed=16, deform=False)
    ax = AxisConfig(resolution_mm=0.01, min_mm=-1, max_mm=1)
    mot = VirtualMotors(ax, ax)
    pl = Plotter(_model(t, False), mot, mode="contour", height=300.0)
    X, Y = t.film(1, t.contour_truth(300.0, 4))[0]
    cyc = pl.cycle(X, Y)
    assert not cyc.in_travel
    assert mot.position() == (0.0, 0.0)


class _FailingMotors(VirtualMotors):
    def __init__(self, *a, fail_after=3, **k):
        super().__init__(*a, **k)
        self.fail_after = fail_after
        self.stopped = False

    def _start_move(self, motor_steps, speed):
        if self.moves >= self.fail_after:
            raise MotorAlarm("GRBL ALARM:1 (hard limit triggered)", 1)
        super()._start_move(motor_steps, speed)

    def _halt(self):
        self.stopped = True
        super()._halt()


def test_motor_fault_stops_and_keeps_features():
    t = aerial_pair(seed=17, deform=False)
    mot = _FailingMotors(FINE, FINE, fail_after=4)
    faults = []
    pl = Plotter(_model(t, False), mot, mode="contour", height=300.0, on_fault=faults.append)
    pts = t.film(1, t.contour_truth(300.0, 10))
    for k in (0, 2):  # two contour pieces of two vertices
        pl.begin("A")
        for X, Y in pts[k:k + 2]:
            pl.cycle(X, Y)
            pl.vertex()
        pl.end()
    with pytest.raises(PlotterHalted, match="ALARM:1.*motors stopped.*2 features"):
        for X, Y in pts[4:]:
            pl.cycle(X, Y)
    assert mot.stopped
    assert len(faults) == 1 and "hard limit" in faults[0]
    assert len(pl.features) == 2
    with pytest.raises(PlotterHalted):
        pl.cycle(*pts[0])
    pl.recover()
    mot.fail_after = 10**9
    pl.cycle(*pts[0])


def test_bad_plotter_use():
    t = aerial_pair(seed=18, deform=False)
    pl = Plotter(_model(t, False), VirtualMotors(FINE, FINE))
    with pytest.raises(SoftplotError, match="height"):
        pl.set_mode("contour")
    with pytest.raises(SoftplotError, match="mode"):
        pl.set_mode("stereo")
    with pytest.raises(SoftplotError, match="cycle first"):
        pl.record_point("X")
    with pytest.raises(SoftplotError, match="no line open"):
        pl.vertex()
    with pytest.raises(SoftplotError, match="contour mode"):
        pl.begin("C", kind="contour")
    with pytest.raises(SoftplotError, match="feature code"):
        pl.begin("bad code with spaces")


def test_with_interior_orientation_of_a_certificate(tmp_path):
    """Film corrections from softplot.orientation.interior (Wild RC10 certificate, radial
    distortion table): the plotter works on film coordinates and still lands on the truth;
    the corrections survive a session save/resume (as data: an identity film correction on
    the fiducials, then the certificate's interior orientation)."""
    from session_helpers import affine_scan_map
    from softplot.camera import Distortion, load_camera
    from softplot.orientation.interior import InteriorOrientation
    from softplot.pipeline.session import Session

    # the built-in RC10 is uncalibrated (no distortion): a certificate's radial table here
    cam = load_camera("wild-rc10").with_(
        calibration="test certificate",
        distortion=Distortion(model="radial-table",
                              radius_mm=(0.0, 30.0, 60.0, 90.0, 120.0, 150.0),
                              delta_r_um=(0.0, 2.0, 3.5, 3.0, 0.5, -3.0)),
    )
    io = InteriorOrientation(cam)
    t = aerial_pair(seed=19, c=load_camera("wild-rc10").c, deform=False)
    t.x0[:] = 0.0
    t.y0[:] = 0.0
    m = affine_scan_map(cam)
    photos = [
        OrientedPhoto(t.X0[k], t.angles[k], t.c[k], 0.0, 0.0, m, m.inverse)
        for k in range(2)
    ]
    model = StereoModel(*photos)
    s = Session.create(tmp_path / "rc10", model, mode="contour", height=300.0)
    s.close()
    model = Session.resume(tmp_path / "rc10").model
    mot = VirtualMotors(FINE, FINE)
    pl = Plotter(model, mot, mode="contour", height=300.0)
    C = t.contour_truth(300.0, 24)
    rf = io.photo_to_film(t.photo(1, C))
    lf = io.photo_to_film(t.photo(0, C))
    assert np.max(np.abs(rf - t.photo(1, C))) > 1e-4  # the distortion matters here
    for (X, Y), left, truth in zip(rf, lf, C, strict=True):
        cyc = pl.cycle(X, Y)
        assert np.max(np.abs(np.array(mot.left_film()) - left)) < 1e-6
        assert abs(cyc.XYZ[2] - 300.0) < 1e-6
        assert np.hypot(cyc.XYZ[0] - truth[0], cyc.XYZ[1] - truth[1]) < 1e-6
    pl.set_mode("single")
    P = t.sample_points(10, seed=6)
    rf = io.photo_to_film(t.photo(1, P))
    lf = io.photo_to_film(t.photo(0, P))
    for (X, Y), (x1f, _), truth in zip(rf, lf, P, strict=True):
        cyc = pl.cycle(X, Y, px=x1f - X)
        assert abs(model.y_parallax([[cyc.x1, cyc.y1]], [[cyc.x2, cyc.y2]])[0]) < 1e-9
        assert np.max(np.abs(np.array(cyc.XYZ) - truth)) < 1e-6
