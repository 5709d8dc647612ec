"""``softplot restitute``: the four modes against the synthetic pair, and bad input."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from softplot.cli import main
from softplot.synthetic.stereo import aerial_pair


def _f(v):
    return repr(float(v))


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def _contour(capsys, photos, points, out, height="300"):
    """Run ``restitute --mode contour`` on a points file; return (code, stdout, stderr)."""
    argv = ["restitute", "--photos", str(photos), "--mode", "contour", "--height", height]
    return _run([*argv, "--points", str(points), "--out", str(out)], capsys)


def _write(path, header, rows):
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def _read(path):
    rows = list(csv.DictReader(path.open()))
    return rows, {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k != "name"}


#: photo coordinates and y-parallax are written to 0.1 um: at most half of that off
PHOTO_TOL = 0.5e-4 + 1e-12


def _half_unit(path, col):
    """Half a unit of the last decimal written in column ``col`` (the rounding's bound)."""
    rows = list(csv.DictReader(path.open()))
    dec = {len(r[col].split(".")[1]) if "." in r[col] else 0 for r in rows}
    assert len(dec) == 1, dec
    return 0.5 * 10.0 ** -dec.pop() + 1e-12


@pytest.fixture
def pair(tmp_path):
    t = aerial_pair(seed=31, deform=False)
    t.x0[:] = 0.0  # the CLI takes photo mm reduced to the principal point
    t.y0[:] = 0.0
    rows = [
        [nm, *t.X0[k], *np.rad2deg(t.angles[k]), t.c[k]] for k, nm in enumerate(("left", "right"))
    ]
    photos = _write(
        tmp_path / "photos.csv",
        ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [[r[0]] + [_f(v) for v in r[1:]] for r in rows],
    )
    return t, photos


def test_single_mode(pair, tmp_path, capsys):
    t, photos = pair
    P = t.sample_points(25, seed=2)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    inp = _write(
        tmp_path / "in.csv",
        ["name", "x2", "y2", "x1"],
        [
            [f"p{i}", _f(a), _f(b), _f(c)]
            for i, (a, b, c) in enumerate(zip(xy2[:, 0], xy2[:, 1], xy1[:, 0], strict=True))
        ],
    )
    code, out, err = _run(
        [
            "restitute",
            "--photos",
            str(photos),
            "--mode",
            "single",
            "--points",
            str(inp),
            "--out",
            str(tmp_path / "o.csv"),
        ],
        capsys,
    )
    assert code == 0, err
    rows, c = _read(tmp_path / "o.csv")
    assert list(rows[0]) == ["name", "x1", "y1", "x2", "y2", "X", "Y", "Z", "py"]
    assert np.max(np.abs(c["y1"] - xy1[:, 1])) <= PHOTO_TOL
    assert np.max(np.abs(np.c_[c["X"], c["Y"], c["Z"]] - P)) <= _half_unit(tmp_path / "o.csv", "X")
    assert np.max(np.abs(c["py"])) <= PHOTO_TOL


def test_contour_free_drive_to(pair, tmp_path, capsys):
    t, photos = pair
    H = 310.0
    C = t.contour_truth(H, 16)
    xy2 = t.photo(1, C)
    inp = _write(
        tmp_path / "c.csv",
        ["name", "x2", "y2"],
        [[f"c{i}", _f(a), _f(b)] for i, (a, b) in enumerate(xy2)],
    )
    code, _, err = _run(
        [
            "restitute",
            "--photos",
            str(photos),
            "--mode",
            "contour",
            "--points",
            str(inp),
            "--height",
            str(H),
            "--out",
            str(tmp_path / "oc.csv"),
        ],
        capsys,
    )
    assert code == 0, err
    _, c = _read(tmp_path / "oc.csv")
    tol = _half_unit(tmp_path / "oc.csv", "X")
    assert np.max(np.abs(c["Z"] - H)) <= tol
    assert np.max(np.abs(np.c_[c["X"] - C[:, 0], c["Y"] - C[:, 1]])) <= tol

    P = t.sample_points(10, seed=4)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    xy1[:, 1] += 0.01  # 10 um of y-parallax
    inp = _write(
        tmp_path / "f.csv",
        ["name", "x1", "y1", "x2", "y2"],
        [[f"f{i}", *map(_f, np.r_[a, b])] for i, (a, b) in enumerate(zip(xy1, xy2, strict=True))],
    )
    code, _, err = _run(
        [
            "restitute",
            "--photos",
            str(photos),
            "--mode",
            "free",
            "--points",
            str(inp),
            "--out",
            str(tmp_path / "of.csv"),
        ],
        capsys,
    )
    assert code == 0, err
    _, c = _read(tmp_path / "of.csv")
    assert np.allclose(c["py"], 0.01, rtol=0, atol=PHOTO_TOL)
    assert np.max(np.abs(np.c_[c["X"], c["Y"], c["Z"]] - P)) < 1.0

    inp = _write(
        tmp_path / "d.csv",
        ["name", "X", "Y", "Z"],
        [[f"d{i}", *map(_f, p)] for i, p in enumerate(P)],
    )
    code, _, err = _run(
        [
            "restitute",
            "--photos",
            str(photos),
            "--mode",
            "drive-to",
            "--points",
            str(inp),
            "--out",
            str(tmp_path / "od.csv"),
        ],
        capsys,
    )
    assert code == 0, err
    _, c = _read(tmp_path / "od.csv")
    assert np.max(np.abs(np.c_[c["x2"], c["y2"]] - xy2)) <= PHOTO_TOL


def test_bad_input_one_line_errors(pair, tmp_path, capsys):
    t, photos = pair
    good = _write(tmp_path / "in.csv", ["name", "x2", "y2"], [["a", "1.0", "2.0"]])
    cases = [
        (["--mode", "contour", "--points", str(good)], "needs --height"),
        (["--mode", "single", "--points", str(good)], "missing column(s) x1"),
        (
            ["--mode", "contour", "--height", "300", "--points", str(tmp_path / "nope.csv")],
            "cannot read points file",
        ),
        (["--mode", "free", "--points", str(good), "--height", "3"], "missing column"),
    ]
    for extra, msg in cases:
        code, _, err = _run(
            ["restitute", "--photos", str(photos), "--out", str(tmp_path / "o.csv"), *extra], capsys
        )
        assert code == 2 and msg in err and err.count("\n") == 1, err
    bad = _write(tmp_path / "b.csv", ["name", "x2", "y2"], [["a", "1.0", "zz"]])
    code, _, err = _contour(capsys, photos, bad, tmp_path / "o.csv")
    assert code == 2 and "line 2" in err
    one = _write(
        tmp_path / "one.csv",
        ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [["l", 0, 0, 1000, 0, 0, 0, 150]],
    )
    code, _, err = _contour(capsys, one, good, tmp_path / "o.csv")
    assert code == 2 and "exactly 2 rows" in err
    before = good.read_bytes()
    code, _, err = _contour(capsys, photos, good, good)
    assert code == 2 and "is an input file" in err and good.read_bytes() == before
    code, _, err = _contour(capsys, photos, good, tmp_path / "o.csv", height="5000")
    assert code == 2 and "behind the right camera" in err


def test_free_mode_writes_precision_and_std(pair, tmp_path, capsys):
    """Coordinates to the precision they have (a tenth of the smallest standard deviation),
    with the standard deviations, which scale with --sigma-image; no 17-digit numbers."""
    t, photos = pair
    P = t.sample_points(8, seed=5)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    inp = _write(tmp_path / "f.csv", ["name", "x1", "y1", "x2", "y2"],
                 [[f"f{i}", *map(_f, np.r_[a, b])] for i, (a, b) in enumerate(zip(xy1, xy2,
                                                                                   strict=True))])
    stds = []
    for sig in ("0.005", "0.0005"):
        out = tmp_path / f"of-{sig}.csv"
        code, _, err = _run(["restitute", "--photos", str(photos), "--mode", "free", "--points",
                             str(inp), "--out", str(out), "--sigma-image", sig], capsys)
        assert code == 0, err
        rows, c = _read(out)
        assert list(rows[0])[-3:] == ["sX", "sY", "sZ"]
        s = np.c_[c["sX"], c["sY"], c["sZ"]]
        assert np.all(s > 0)
        dec = len(rows[0]["X"].split(".")[1])
        # the last digit is at most a tenth of the smallest std, and not ten times finer
        assert 10.0 ** -dec <= s.min() / 10 < 10.0 ** -(dec - 1)
        assert all(len(r["x1"].split(".")[1]) == 4 for r in rows)
        assert np.max(np.abs(np.c_[c["X"], c["Y"], c["Z"]] - P)) <= 0.5 * 10.0**-dec + 1e-12
        stds.append(s)
    assert np.allclose(stds[1], stds[0] / 10, rtol=0.02)


def test_duplicate_point_names_refused(pair, tmp_path, capsys):
    t, photos = pair
    inp = _write(tmp_path / "d.csv", ["name", "X", "Y", "Z"],
                 [["a", "1", "2", "3"], ["b", "1", "2", "3"], ["a", "4", "5", "6"]])
    code, _, err = _run(["restitute", "--photos", str(photos), "--mode", "drive-to", "--points",
                         str(inp), "--out", str(tmp_path / "o.csv")], capsys)
    assert code == 2
    assert "duplicate point name(s) a" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.csv").exists()
