"""A block of scans becomes a bundle project (softplot match SCAN SCAN SCAN, then bundle)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from matching_scenes import make_strip
from matching_scenes import run_cli as run
from softplot.geometry.rotation import rotation_matrix


@pytest.fixture(scope="module")
def strip(tmp_path_factory):
    base = tmp_path_factory.getbasetemp()
    return make_strip(str(base / "matching-strip"), 600.0,
                      pair_folder=str(base / "matching-scene"))


def _invariants(X0, M):
    """Similarity-free figures of a strip: base ratio, angle between the bases (rad), and
    the rotation angle (rad) of each relative rotation M_k M_0'."""
    b1, b2 = X0[1] - X0[0], X0[2] - X0[1]
    ratio = np.linalg.norm(b2) / np.linalg.norm(b1)
    bend = np.arccos(np.clip(b1 @ b2 / np.linalg.norm(b1) / np.linalg.norm(b2), -1, 1))
    return ratio, bend, [M[k] @ M[0].T for k in (1, 2)]


def test_block_of_scans_feeds_the_bundle(strip, tmp_path):
    out = tmp_path / "block"
    dets = [a for d in strip.detections for a in ("--detection", str(d))]
    code, text = run(["match", *map(str, strip.scans), "--camera", "rollei-6006", *dets,
                      "--out", str(out), "--workers", "2"])
    assert code == 0, text
    summary = json.loads((out / "block.json").read_text())
    assert [p["status"] for p in summary["pairs"]] == ["done"] * 3
    assert summary["points_by_rays"].get("3", 0) >= 10  # the triple overlap links the strip
    for p in ("photo1__photo2", "photo2__photo3"):
        assert (out / "pairs" / p / "left.csv").exists()
    # the bundle project, without a typed point: a free network
    code, text = run(["bundle", str(out), "--json", str(tmp_path / "b.json")])
    assert code == 0, text
    b = json.loads((tmp_path / "b.json").read_text())
    assert b["converged"] and b["sigma0"] < 2.0
    X0 = np.array([[p[k]["value"] for k in ("X0", "Y0", "Z0")] for p in b["photos"]])
    ang = np.array([[p[k]["value"] for k in ("omega", "phi", "kappa")] for p in b["photos"]])
    assert all(p["angle_unit"] == "rad" for p in b["photos"])
    est = _invariants(X0, [rotation_matrix(*a) for a in ang])
    tru = _invariants(strip.pair.X0, [strip.pair.M(k) for k in range(3)])
    # within a few times the bundle's own standard deviations (about 1e-4 of the base for
    # the projection centres, 3e-5 to 6e-5 rad for the angles; measured 2e-4, 2e-4, 9e-5)
    assert abs(est[0] - tru[0]) < 1e-3, (est[0], tru[0])
    assert abs(est[1] - tru[1]) < 1e-3, (est[1], tru[1])
    for Re, Rt in zip(est[2], tru[2], strict=True):
        d = np.arccos(np.clip((np.trace(Re @ Rt.T) - 1) / 2, -1, 1))
        assert d < 3e-4, d


def test_block_bad_input(strip, tmp_path):
    out = tmp_path / "block"
    out.mkdir()
    (out / "observations.csv").write_text("mine\n")
    dets = [a for d in strip.detections for a in ("--detection", str(d))]
    code, text = run(["match", *map(str, strip.scans), "--camera", "rollei-6006", *dets,
                      "--out", str(out), "--workers", "0"])
    assert code == 2 and "refusing to overwrite" in text and text.strip().count("\n") == 0
    assert (out / "observations.csv").read_text() == "mine\n"
    code, text = run(["match", *map(str, strip.scans), "--camera", "rollei-6006",
                      "--detection", str(strip.detections[0]), "--out", str(tmp_path / "o")])
    assert code == 2 and "one --detection per scan" in text
    # a missing scan: refused before any work, naming it, nothing written
    gone = tmp_path / "gone.tif"
    code, text = run(["match", *map(str, strip.scans), str(gone), "--camera", "rollei-6006",
                      "--out", str(tmp_path / "o2"), "--workers", "0"])
    assert code == 2 and text == f"softplot: error: {gone}: file not found"
    assert not (tmp_path / "o2").exists()
