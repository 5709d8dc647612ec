"""The process/batch report: each figure named for what it is, the residuals after the chosen
correction in micrometres on the film, missing and rejected marks drawn and named, QC limits,
version, date, inputs and the certificate's source."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from softplot import __version__  # noqa: E402
from softplot.pipeline.process import (  # noqa: E402
    QC_LIMITS,
    _film_residual_axes,
    _qc_limits_text,
    _report_header,
    _scan_text,
    process_scan,
    write_report,
)
from softplot.synthetic import ScanSpec, write_scan  # noqa: E402


def _fake_result():
    marks = [
        {"name": "R0C0", "x": 10.0, "y": 10.0, "film_x": -10.0, "film_y": 10.0,
         "status": "measured"},
        {"name": "R0C1", "x": 50.0, "y": 10.0, "film_x": 0.0, "film_y": 10.0,
         "status": "measured"},
        {"name": "R1C0", "x": 10.0, "y": 50.0, "film_x": -10.0, "film_y": 0.0,
         "status": "measured"},
        {"name": "R1C1", "x": None, "y": None, "film_x": 0.0, "film_y": 0.0,
         "status": "missing"},
        {"name": "R2C0", "x": 12.0, "y": 90.0, "film_x": -10.0, "film_y": -10.0,
         "status": "rejected"},
    ]
    return {
        "scan": "/x/scan0.tif", "camera": "rollei-6006", "complete": True, "status": "done",
        "certificate": {"name": "rollei-6006", "source": "builtin:rollei-6006.toml"},
        "settings": {"camera": "rollei-6006", "method": "mesh", "polarity": "negative",
                     "rotate": 90.0, "flatten": False},
        "width": 100, "height": 100, "dpi": 600.0, "marks_total": 5, "marks_measured": 3,
        "marks_missing": 1, "marks_rejected": 1, "rms_px": 0.23, "mark_sigma_px": 0.012,
        "method": "mesh-affine", "recommended": "mesh-affine", "loo_rms_um": 1.5,
        "loo_max_um": 2.0,
        "correction_check": {"method": "mesh-affine", "kind": "leave-one-out",
                             "names": ["R0C0", "R0C1", "R1C0"],
                             "residual_um": [[1.0, -2.0], [0.5, 0.0], [-1.5, 1.0]]},
        "qc": {"ok": True, "warnings": [], "limits": QC_LIMITS},
        "worst": [], "crossval": {"methods": []}, "detection": {"marks": marks},
    }


def test_film_residual_figure():
    r = _fake_result()
    fig, ax = plt.subplots()
    _film_residual_axes(ax, r)
    q = [c for c in ax.collections if c.__class__.__name__ == "Quiver"][0]
    # vectors at the certificate positions (film mm), lengths in um as given
    assert np.allclose(q.get_offsets(), [[-10, 10], [0, 10], [-10, 0]])
    assert np.allclose(np.c_[q.U, q.V], r["correction_check"]["residual_um"])
    texts = [t.get_text() for t in ax.texts] + [c.text.get_text() for c in ax.artists
                                                if hasattr(c, "text")]
    assert any(t.endswith(" um") for t in texts), texts  # the reference vector
    assert {"R1C1", "R2C0"} <= set(texts)  # missing and rejected marks named
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["missing (1)", "rejected (1)"]
    assert ax.get_xlabel() == "film x mm" and "um on the film" in ax.get_title()
    plt.close("all")


def test_report_names_the_figures(tmp_path):
    r = _fake_result()
    text = _scan_text(r)
    assert "detection RMS" not in text
    assert "Mark precision" in text and "0.0120 px" in text
    assert "projective film -> pixel model" in text and "0.2300 px" in text
    assert "builtin:rollei-6006.toml" in text and "1 missing, 1 rejected" in text
    head = _report_header([r])
    assert head.startswith(f"softplot {__version__}, ") and "UTC" in head
    assert "polarity negative" in head and "rotate 90.0" in head
    lim = _qc_limits_text()
    assert str(QC_LIMITS["mark_sigma_px"]) in lim and str(QC_LIMITS["loo_rms_um"]) in lim
    html = write_report(tmp_path / "r.html", [r]).read_text()
    assert head.split(";")[0] in html and "QC limits" in html
    assert "mark precision px (median)" in html and "detection RMS" not in html


def test_process_records_the_correction_check(tmp_path):
    """The residuals the report draws are the applied correction's leave-one-out residuals:
    their RMS is the LOO RMS of the result; the certificate's source is recorded."""
    img, _ = write_scan(tmp_path, "rollei-6006",
                        ScanSpec(dpi=400, deform_um=12, rotation_deg=0.2), seed=3, stem="s")
    r = process_scan(img, tmp_path / "out", camera="rollei-6006")
    import json

    full = json.loads((tmp_path / "out" / "s.json").read_text())
    chk = full["correction_check"]
    assert chk["method"] == r["method"] and len(chk["names"]) == len(chk["residual_um"]) > 50
    d = np.asarray(chk["residual_um"])
    assert np.sqrt(np.mean(np.sum(d * d, axis=1))) == pytest.approx(r["loo_rms_um"], rel=1e-3)
    assert full["certificate"]["source"]


def test_batch_table_names_its_columns():
    from softplot.pipeline.batch import BatchReport

    t = BatchReport(rows=[{"scan": "a.tif", "status": "done", "marks": 121, "measured": 121,
                           "rms_px": 0.23, "method": "poly2", "loo_rms_um": 1.2,
                           "seconds": 1.0}]).table()
    assert "proj px" in t and "rms px" not in t
    assert "projective film -> pixel model" in t and "leave-one-out" in t
