"""Every residual reported: per observation, per photo, per point; JSON, CSV, text report."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softplot.cli import main
from softplot.orientation.bundle import bundle_adjust
from softplot.orientation.bundle_io import write_project
from softplot.synthetic.testfield import make_testfield


@pytest.fixture(scope="module")
def result():
    net = make_testfield(n_photos=10, seed=7, control_sigma_m=0.0)
    d = net.to_bundle_data(free=("c", "x0", "y0", "k1"), pixel_size_mm=0.0127)
    d.xy[5] += [0.03, 0.0]  # a blunder of 30 um
    return d, bundle_adjust(d)


def test_every_observation_in_the_json(result):
    d, res = result
    js = res.to_json()
    rows = js["residuals"]
    m = d.obs_photo.size
    assert len(rows) == m and len(js["largest_residuals"]) == 10
    vx = np.array([r["vx_um"] for r in rows])
    np.testing.assert_allclose(vx, res.residuals_mm[:, 0] * 1000, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        [r["vy_px"] for r in rows], res.residuals_mm[:, 1] / 0.0127, rtol=1e-12
    )
    assert [r["photo"] for r in rows] == [d.photo_names[f] for f in d.obs_photo]
    assert [r["point"] for r in rows] == [d.point_names[p] for p in d.obs_point]
    # redundancy numbers: in (0, 1) and summing to the redundancy (fixed control, no priors)
    r = np.array([[o["rx"], o["ry"]] for o in rows])
    assert np.all((r > 0) & (r < 1))
    assert r.sum() == pytest.approx(res.redundancy, rel=1e-9)
    # w = v / (sigma sqrt(r)) for uncorrelated observations
    w = np.array([o["wx"] for o in rows])
    np.testing.assert_allclose(w, res.residuals_mm[:, 0] / d.sigma_xy[:, 0] / np.sqrt(r[:, 0]))
    assert rows[5]["flagged"] and sum(o["flagged"] for o in rows) >= 1


def test_per_photo_and_per_point_statistics(result):
    d, res = result
    ps = res.photo_statistics()
    assert [s["photo"] for s in ps] == d.photo_names
    for f, s in enumerate(ps):
        v = res.residuals_mm[d.obs_photo == f] * 1000
        assert s["n"] == v.shape[0]
        assert s["rms_x_um"] == pytest.approx(np.sqrt(np.mean(v[:, 0] ** 2)), rel=1e-12)
        assert s["rms_xy_px"] == pytest.approx(
            np.sqrt(np.mean(v[:, 0] ** 2) + np.mean(v[:, 1] ** 2)) / 12.7, rel=1e-12
        )
    assert sum(s["flagged"] for s in ps) == int(res.flagged.sum())
    assert sum(s["redundancy"] for s in ps) == pytest.approx(res.redundancy, rel=1e-9)
    pt = res.point_statistics()
    assert sum(s["n"] for s in pt) == d.obs_photo.size
    j = d.obs_point[5]
    assert pt[j]["max_abs_w"] == pytest.approx(np.nanmax(np.abs(res.w[d.obs_point == j])))


def test_cli_writes_residual_csv_and_per_photo_table(result, tmp_path, capsys):
    d, _ = result
    write_project(tmp_path / "p", d)
    out = tmp_path / "res.csv"
    js = tmp_path / "r.json"
    with pytest.raises(SystemExit) as e:
        main(["bundle", str(tmp_path / "p"), "--residuals", str(out), "--json", str(js)])
    txt = capsys.readouterr().out
    assert e.value.code == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == d.obs_photo.size
    assert set(rows[0]) == {
        "photo",
        "point",
        "vx_um",
        "vy_um",
        "vx_px",
        "vy_px",
        "rx",
        "ry",
        "wx",
        "wy",
        "flagged",
    }
    assert "Image residuals per photo" in txt
    table = txt.split("Image residuals per photo")[1]
    for n in d.photo_names:
        assert f"\n  {n} " in table
    assert len(json.loads(js.read_text())["residuals"]) == d.obs_photo.size
