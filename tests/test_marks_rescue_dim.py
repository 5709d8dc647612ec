"""The rescue of refused crosses (:func:`softplot.marks.validation.rescue`) and of crosses the
scan's edge cuts (:func:`softplot.marks.validation.edge_crosses`) holds a refit to the measured
crosses' precision as it stands, whatever its contrast: a fit inside a black area keeps a third
of its peers' contrast from the area's edge, and at its peers' contrast it would pass."""

from __future__ import annotations


def test_no_cross_is_claimed_inside_a_black_block():
    # the second renderer's scan 234: a Rollei at 824 dpi over sharp-edged blocks; R3C2 lies
    # inside a black block (its contrast 0.0004 of the grey range, under the noise): a refit
    # near its prediction, on the block's edge, has a third of the peers' contrast and,
    # taken to their contrast, their precision; judged as it stands it is refused
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.synthetic.plain import make_plain, score_plain

    case = make_plain(234)
    det = detect(Scan.from_array(case.image, dpi=case.dpi), case.camera)
    row = score_plain(case, det)
    assert row["claimed"] == [], row["claimed"]
    assert not row["wrong"]
    # the scan's visible crosses are measured as before the rescue's allowance
    assert row["measured"] >= 118, (row["measured"], row["visible"])
    tm = {m["name"]: m for m in case.truth["marks"]}
    assert tm["R3C2"]["state"] == "dark"
    i = det.name.index("R3C2")
    assert det.status[i] != "measured"
