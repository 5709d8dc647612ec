"""Camera certificates (softplot.camera): built-ins, round trip, validation, CLI."""

from __future__ import annotations

import math
import re
import tomllib

import numpy as np
import pytest

from softplot.camera import (
    Camera,
    Distortion,
    Fiducial,
    Reseau,
    builtin_names,
    describe,
    load_camera,
    parse_certificate,
    read_certificate,
    to_toml,
    write_certificate,
)
from softplot.cli import main
from softplot.errors import CertificateError, SoftplotError

BUILTINS = [
    "aerial-23x47",
    "hasselblad-mk70",
    "pentax-645",
    "plate-13x18-reseau",
    "rollei-6006",
    "rollei-6008",
    "wild-rc10",
    "zeiss-rmk-a-15-23",
    "zeiss-umk-10-1318",
]


def test_catalogue_names():
    assert builtin_names() == BUILTINS


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_valid_and_round_trip(name, tmp_path):
    cam = load_camera(name)
    assert cam.name == name
    assert cam.kind in ("metric", "semi-metric", "quasi-metric", "non-metric")
    assert cam.c > 0 and all(v > 0 for v in cam.format_mm)
    assert cam.reseau is not None or len(cam.fiducials) > 0
    # every mark lies inside the image format (film mm, origin at the centre)
    half = np.array(cam.format_mm) / 2
    marks = np.vstack([cam.fiducial_film(),
                       cam.reseau.film() if cam.reseau else np.zeros((0, 2))])
    assert np.all(np.abs(marks) < half)
    # nominal values are declared as such in the file
    assert any("nominal" in n for n in cam.notes)
    # round trip through text and through a file
    text = to_toml(cam)
    assert parse_certificate(text, "x") == cam
    p = write_certificate(cam, tmp_path / f"{name}.toml")
    back = read_certificate(p)
    assert back == cam and back.source == str(p)
    assert load_camera(str(p)) == cam
    assert load_camera(cam) is cam
    assert describe(cam).startswith(f"{name}  ({cam.kind})")


def _grid(cam: Camera) -> tuple[int, int, float, float]:
    r = cam.reseau
    return (r.rows, r.cols, r.pitch_x, r.pitch_y)


def test_builtin_geometry_as_specified():
    r6 = load_camera("rollei-6006")
    r8 = load_camera("rollei-6008")
    assert _grid(r6) == _grid(r8) == (11, 11, 5.0, 5.0)
    assert (r6.c, r8.c) == (40.0, 80.0)
    # film system: row 0 on top (largest y), column 0 leftmost
    xy = r6.reseau.film()
    assert r6.reseau.names()[0] == "R0C0" and r6.reseau.names()[-1] == "R10C10"
    np.testing.assert_array_equal(xy[0], [-25.0, 25.0])
    np.testing.assert_array_equal(xy[-1], [25.0, -25.0])
    np.testing.assert_array_equal(xy[60], [0.0, 0.0])  # R5C5, the centre
    assert xy[1, 0] - xy[0, 0] == 5.0 and xy[11, 1] - xy[0, 1] == -5.0

    px = load_camera("pentax-645")
    assert px.kind == "quasi-metric" and _grid(px) == (3, 3, 23.0, 17.0)
    np.testing.assert_array_equal(px.reseau.film()[[0, 8]], [[-23.0, 17.0], [23.0, -17.0]])

    hb = load_camera("hasselblad-mk70")
    assert _grid(hb) == (5, 5, 10.0, 10.0)

    rmk = load_camera("zeiss-rmk-a-15-23")
    assert rmk.format_mm == (230.0, 230.0) and len(rmk.fiducials) == 8 and rmk.reseau is None
    assert rmk.kind == "metric"
    rc10 = load_camera("wild-rc10")
    assert len(rc10.fiducials) == 4 and rc10.reseau is None and rc10.kind == "metric"
    umk = load_camera("zeiss-umk-10-1318")
    assert umk.kind == "metric" and len(umk.fiducials) >= 4
    # fiducials symmetric about the film origin (the fiducial centre)
    for cam in (rmk, rc10, umk):
        np.testing.assert_allclose(cam.fiducial_film().mean(axis=0), 0.0, atol=1e-9)


def test_calibrated_reseau_overrides_nominal_and_round_trips():
    base = load_camera("pentax-645")
    cal = np.full((3, 3, 2), np.nan)
    cal[0, 0] = (-23.012, 17.004)
    cal[2, 1] = (0.003, -16.991)
    r = base.reseau
    cam = base.with_(reseau=Reseau(r.rows, r.cols, r.pitch_x, r.pitch_y, r.arm_length_mm,
                                   r.line_width_mm, calibrated=cal))
    expect = r.nominal_film()
    expect[0] = cal[0, 0]
    expect[7] = cal[2, 1]
    np.testing.assert_array_equal(cam.reseau.film(), expect)
    np.testing.assert_array_equal(cam.reseau.nominal_film(), r.nominal_film())
    text = to_toml(cam)
    assert "calibrated = [" in text and "[2, 1, 0.003, -16.991]" in text
    back = parse_certificate(text)
    np.testing.assert_array_equal(back.reseau.film(), expect)
    assert np.isnan(back.reseau.calibrated[1, 1]).all()
    assert "calibrated coordinates" in describe(back)


def test_round_trip_strings_brown_and_custom_fiducials():
    cam = Camera(
        name='odd "name" \\ é',
        kind="non-metric",
        format_mm=(36.0, 24.0),
        c=35.123456789,
        x0=-0.0123,
        y0=0.0456,
        sigma_c=1e-3,
        distortion=Distortion("brown", k1=-1.25e-5, k2=3e-9, k3=-1e-13, p1=2e-6, p2=-3e-6,
                              b1=1e-5, b2=-2e-5),
        fiducials=(Fiducial("A", -17.0, 11.0, "custom", 0.7, 0.02, 0.05),
                   Fiducial("B", 17.0, -11.0, "dot", 0.3)),
        description="two\nlines\tand a tab",
        notes=("first", "sec\x7fond"),
    )
    assert parse_certificate(to_toml(cam)) == cam


# ---------------------------------------------------------------------------------------------
# malformed certificates: each names the file and the field

GOOD = """\
name = "test"
kind = "semi-metric"

[format]
width_mm = 56.0
height_mm = 56.0

[interior]
principal_distance_mm = 40.0
x0_mm = 0.0
y0_mm = 0.0

[distortion]
model = "radial-table"
radius_mm = [0.0, 10.0, 20.0]
delta_r_um = [0.0, 1.0, 2.0]

[[fiducials]]
name = "F1"
x_mm = -20.0
y_mm = 20.0
shape = "cross"

[reseau]
rows = 3
cols = 3
pitch_x_mm = 5.0
pitch_y_mm = 5.0
arm_length_mm = 0.8
line_width_mm = 0.04
calibrated = [[0, 0, -5.001, 5.002]]
"""


def _sub(old: str, new: str) -> str:
    assert GOOD.count(old) == 1, old
    return GOOD.replace(old, new)


MALFORMED = [
    ("missing name", _sub('name = "test"\n', ""), "name", "missing"),
    ("missing kind", _sub('kind = "semi-metric"\n', ""), "kind", "missing"),
    ("bad kind", _sub('"semi-metric"', '"semimetric"'), "kind", "must be one of"),
    ("kind not string", _sub('"semi-metric"', "3"), "kind", "must be a string"),
    ("missing format", _sub("[format]\nwidth_mm = 56.0\nheight_mm = 56.0\n", ""),
     "format", "missing table"),
    ("negative width", _sub("width_mm = 56.0", "width_mm = -56.0"), "format.width_mm",
     "positive"),
    ("missing c", _sub("principal_distance_mm = 40.0\n", ""),
     "interior.principal_distance_mm", "missing"),
    ("c wrong type", _sub("principal_distance_mm = 40.0", 'principal_distance_mm = "40"'),
     "interior.principal_distance_mm", "must be a number"),
    ("c boolean", _sub("principal_distance_mm = 40.0", "principal_distance_mm = true"),
     "interior.principal_distance_mm", "must be a number"),
    ("c infinite", _sub("principal_distance_mm = 40.0", "principal_distance_mm = inf"),
     "interior.principal_distance_mm", "finite"),
    ("interior not a table", "interior = 5\n" + _sub(
        "[interior]\nprincipal_distance_mm = 40.0\nx0_mm = 0.0\ny0_mm = 0.0\n", ""),
     "interior", "must be a table"),
    ("bad distortion model", _sub('"radial-table"', '"spline"'), "distortion.model",
     "must be one of"),
    ("non-increasing table", _sub("[0.0, 10.0, 20.0]", "[0.0, 20.0, 10.0]"),
     "distortion.radius_mm", "increasing"),
    ("table length", _sub("[0.0, 1.0, 2.0]", "[0.0, 1.0]"), "distortion.delta_r_um",
     "2 values for 3 radii"),
    ("table entry type", _sub("[0.0, 1.0, 2.0]", '[0.0, "1", 2.0]'),
     "distortion.delta_r_um[1]", "finite number"),
    ("bad fiducial shape", _sub('shape = "cross"', 'shape = "triangle"'),
     "fiducials[0].shape", "must be one of"),
    ("fiducial x missing", _sub("x_mm = -20.0\n", ""), "fiducials[0].x_mm", "missing"),
    ("fiducial name missing", _sub('name = "F1"\n', ""), "fiducials[0].name", "missing"),
    ("fiducial name type", _sub('name = "F1"', "name = [1]"), "fiducials[0].name",
     "must be a string"),
    ("duplicate fiducial", GOOD + '\n[[fiducials]]\nname = "F1"\nx_mm = 1.0\ny_mm = 1.0\n',
     "fiducials[1].name", "duplicate"),
    ("fiducials not array", _sub("[[fiducials]]", "[fiducials]"), "fiducials",
     "array of tables"),
    ("rows zero", _sub("rows = 3", "rows = 0"), "reseau.rows", "at least 1"),
    ("rows float", _sub("rows = 3", "rows = 3.0"), "reseau.rows", "must be an integer"),
    ("pitch missing", _sub("pitch_y_mm = 5.0\n", ""), "reseau.pitch_y_mm", "missing"),
    ("line wider than arm", _sub("line_width_mm = 0.04", "line_width_mm = 0.9"),
     "reseau.line_width_mm", "smaller than arm_length_mm"),
    ("calibrated out of grid",
     _sub("[[0, 0, -5.001, 5.002]]", "[[0, 0, -5.0, 5.0], [3, 0, 1.0, 1.0]]"),
     "reseau.calibrated[1]", "outside the grid"),
    ("calibrated negative", _sub("[[0, 0, -5.001, 5.002]]", "[[-1, 0, -5.0, 5.0]]"),
     "reseau.calibrated[0]", "outside the grid"),
    ("calibrated bad shape", _sub("[[0, 0, -5.001, 5.002]]", "[[0, 0, -5.001]]"),
     "reseau.calibrated[0]", "must be [row, col, x_mm, y_mm]"),
    ("calibrated not list", _sub("[[0, 0, -5.001, 5.002]]", '"all"'), "reseau.calibrated",
     "must be a list"),
    ("no marks", _sub('[[fiducials]]\nname = "F1"\nx_mm = -20.0\ny_mm = 20.0\nshape = "cross"\n',
                      "").split("[reseau]")[0], "reseau", "needs a [reseau]"),
    ("notes type", 'notes = 5\n' + GOOD, "notes", "list of strings"),
    ("description type", 'description = [1]\n' + GOOD, "description", "must be a string"),
]


def test_good_fixture_is_valid():
    cam = parse_certificate(GOOD, "good")
    assert cam.reseau.film()[0].tolist() == [-5.001, 5.002]


@pytest.mark.parametrize("label, text, field, why", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_names_file_and_field(tmp_path, label, text, field, why):
    p = tmp_path / "cert.toml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(CertificateError) as e:
        read_certificate(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: field '{field}': "), msg
    assert why in msg and "\n" not in msg
    assert isinstance(e.value, SoftplotError)


def test_invalid_toml_and_missing_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text(GOOD.replace("[format]", "[format"), encoding="utf-8")
    with pytest.raises(CertificateError, match=re.escape(f"{p}: not valid TOML")):
        read_certificate(p)
    with pytest.raises(CertificateError, match="not valid TOML"):
        parse_certificate("name = ", "inline")
    q = tmp_path / "latin1.toml"
    q.write_bytes(GOOD.replace("test", "t\xe9st").encode("latin-1"))
    with pytest.raises(CertificateError, match=re.escape(f"{q}: not valid TOML")):
        read_certificate(q)
    m = tmp_path / "missing.toml"
    with pytest.raises(CertificateError, match=re.escape(f"{m}: certificate file not found")):
        read_certificate(m)
    with pytest.raises(CertificateError, match=re.escape(f"{m}: certificate file not found")):
        load_camera(m)
    with pytest.raises(CertificateError, match="unknown camera 'no-such-camera'"):
        load_camera("no-such-camera")


def test_write_certificate_refuses_overwrite(tmp_path):
    cam = load_camera("rollei-6006")
    p = write_certificate(cam, tmp_path / "c.toml")
    with pytest.raises(CertificateError, match="refusing to overwrite"):
        write_certificate(load_camera("pentax-645"), p)
    assert read_certificate(p) == cam
    write_certificate(load_camera("pentax-645"), p, overwrite=True)
    assert read_certificate(p).name == "pentax-645"


def test_to_toml_is_plain_toml():
    for name in BUILTINS:
        data = tomllib.loads(to_toml(load_camera(name)))
        assert data["name"] == name and math.isfinite(data["interior"]["principal_distance_mm"])


# ---------------------------------------------------------------------------------------------
# CLI


def _run(capsys, *args) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main(list(args))
    out, err = capsys.readouterr()
    return e.value.code, out, err


def test_cli_cameras_list(capsys):
    code, out, err = _run(capsys, "cameras")
    assert code == 0 and err == ""
    lines = out.strip().splitlines()
    assert [line.split()[0] for line in lines] == BUILTINS
    rollei = next(line for line in lines if line.startswith("rollei-6006"))
    assert "reseau 11x11" in rollei and "c=  40.00 mm" in rollei
    assert "8 fiducials" in next(line for line in lines if line.startswith("zeiss-rmk"))


def test_cli_cameras_show(capsys, tmp_path):
    code, out, _ = _run(capsys, "cameras", "show", "rollei-6006")
    assert code == 0
    assert out.startswith("rollei-6006  (semi-metric)")
    assert "11 x 11 crosses, pitch 5.0 x 5.0 mm" in out
    assert "c  = 40.0000 mm" in out
    code, out, _ = _run(capsys, "cameras", "show", "wild-rc10", "--toml")
    assert code == 0 and parse_certificate(out) == load_camera("wild-rc10")
    p = tmp_path / "mine.toml"
    p.write_text(GOOD, encoding="utf-8")
    code, out, _ = _run(capsys, "cameras", "show", str(p))
    assert code == 0 and out.startswith("test  (semi-metric)") and f"source: {p}" in out


@pytest.mark.parametrize(
    "arg, fragment",
    [("no-such-camera", "unknown camera 'no-such-camera'"), ("nothere.toml", "not found")],
)
def test_cli_cameras_show_bad_exits_2_one_line(capsys, arg, fragment):
    code, out, err = _run(capsys, "cameras", "show", arg)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("softplot: error: ") and fragment in err


def test_cli_cameras_show_malformed_file(capsys, tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text(GOOD.replace('"semi-metric"', '"semimetric"'), encoding="utf-8")
    code, out, err = _run(capsys, "cameras", "show", str(p))
    assert code == 2 and out == ""
    assert err == f"softplot: error: {p}: field 'kind': must be one of metric, semi-metric, " \
                  "quasi-metric, non-metric, got 'semimetric'\n"
