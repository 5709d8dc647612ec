"""Crosses a few pixels across under blur and JPEG blocks: blobs whose fitted size does not
settle (:func:`softplot.marks.measurement.blob_size`)."""

from __future__ import annotations


def test_sweep_render_of_blob_crosses_gives_a_result():
    """Sweep render 24 (Hasselblad web copy at 472 dpi, JPEG q55, colour negative of contrast
    0.07, arms 0.44 x the certificate's: about 8 px, one JPEG block across): every fit
    shrinks the template to about two thirds, from whatever size it starts, and was refused
    as the wrong size (measured 1 of 25: refused). Judged against the crosses' common size
    they are measured: a result, every cross with its own row and col, none grossly off,
    nothing claimed where no cross shows."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(24))
    assert sc.result, sc.error
    assert sc.wrong == [] and sc.claimed == [] and sc.gross == []
    assert sc.measured >= 4
