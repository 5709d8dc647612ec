"""The native bundle project folder (format documented in ``docs/bundle.md``).

Files (CSV with a header row, UTF-8; TOML for the cameras):

* ``cameras.toml``: ``[[camera]]`` tables: ``name``; optional ``certificate`` (built-in name
  or a path relative to the folder) giving the start values; overrides ``c``, ``x0``, ``y0``
  (mm), ``k1`` .. ``b2``; ``free = [...]`` parameter names; ``[camera.sigma]`` a priori
  standard errors (weighted parameters, mm units as the values); ``sigma_image_um`` (default
  standard error of the image coordinates, default 2.0); ``pixel_size_um``; ``lens``
  (``"forward"``: distortion added to the projected point, the default when a distortion
  parameter is free or weighted; ``"inverse"``: evaluated at the measured point, the
  default otherwise).
* ``photos.csv``: ``photo, camera`` and optional ``X0, Y0, Z0, omega, phi, kappa`` (angles in
  degrees; ``omega_gon`` ... or ``omega_rad`` ... headers select gon or radians; empty cells
  are initialised by resection / relative orientation), ``fixed`` (1/true: exterior
  orientation held), ``series`` (a label for ``softplot calibrate --series``).
* ``observations.csv``: ``photo, name, x, y`` film mm, optional ``sx, sy`` (mm) and ``sxy``
  (their covariance, mm^2). ``name`` is the point's name (the older header ``point`` is
  still read).
* ``control.csv`` (optional): ``name, X, Y, Z`` (or ``point``) and optional ``sX, sY, sZ``
  (0 or empty sigma with a value: fixed; empty value: that coordinate is not control) and ``type``
  (``control``, default, or ``check``).
* ``points.csv`` (optional): ``name, X, Y, Z`` approximate object coordinates (start values,
  not control).

:func:`read_project` returns a :class:`~softplot.orientation.bundle.BundleData`;
:func:`write_project` writes one (used for synthetic projects); neither overwrites input.
"""

from __future__ import annotations

import csv
import math
import tomllib
from pathlib import Path

import numpy as np

from softplot.camera import load_camera
from softplot.errors import SoftplotError
from softplot.geometry.rotation import from_radians, to_radians
from softplot.orientation.bundle import INTRINSICS, BundleCamera, BundleData

__all__ = ["read_project", "write_project", "read_cameras"]

FILES = ("cameras.toml", "photos.csv", "observations.csv", "control.csv", "points.csv")


def _rows(path: Path, required: tuple) -> list[dict]:
    if not path.is_file():
        raise SoftplotError(f"missing {path.name} in {path.parent}")
    with open(path, newline="", encoding="utf-8") as fh:
        rd = csv.DictReader(fh)
        if rd.fieldnames is None:
            raise SoftplotError(f"{path}: empty file (a header row is required)")
        fields = [f.strip() for f in rd.fieldnames]
        # one column name for a point everywhere: ``name`` (the older ``point`` is still read)
        alias = "name" in required and "name" not in fields and "point" in fields
        if alias:
            fields = ["name" if f == "point" else f for f in fields]
        miss = [r for r in required if r not in fields]
        if miss:
            raise SoftplotError(f"{path}: missing column(s) {', '.join(miss)}")
        out = []
        for row in rd:
            r = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            if alias:
                r["name"] = r.pop("point")
            out.append(r)
        return out


def _num(v: str, where: str, default=math.nan) -> float:
    if v is None or v == "":
        return default
    try:
        x = float(v)
    except ValueError as exc:
        raise SoftplotError(f"{where}: not a number: {v!r}") from exc
    if not math.isfinite(x):
        raise SoftplotError(f"{where}: not finite: {v!r}")
    return x


def read_cameras(path: Path) -> list[BundleCamera]:
    """Parse ``cameras.toml`` (see the module docstring)."""
    if not path.is_file():
        raise SoftplotError(f"missing {path.name} in {path.parent}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SoftplotError(f"{path}: {exc}") from exc
    tables = data.get("camera")
    if not isinstance(tables, list) or not tables:
        raise SoftplotError(f"{path}: needs at least one [[camera]] table")
    cams = []
    for i, t in enumerate(tables):
        where = f"{path}: camera[{i}]"
        name = str(t.get("name", "")).strip()
        if not name:
            raise SoftplotError(f"{where}: missing name")
        vals = np.zeros(len(INTRINSICS))
        cert = t.get("certificate")
        if cert:
            p = path.parent / str(cert)
            cam = load_camera(p if p.is_file() else str(cert))
            d = cam.distortion
            if d.model == "radial-table" and not t.get("ignore_radial_table", False):
                raise SoftplotError(
                    f"{where}: certificate {cert} has a radial distortion table; give Brown "
                    "k1.. in cameras.toml (or set ignore_radial_table = true)"
                )
            vals[:3] = cam.c, cam.x0, cam.y0
            if d.model == "brown":
                vals[3:10] = d.k1, d.k2, d.k3, d.p1, d.p2, d.b1, d.b2
        for j, n in enumerate(INTRINSICS):
            if n in t:
                try:
                    vals[j] = float(t[n])
                except (TypeError, ValueError) as exc:
                    raise SoftplotError(f"{where}: {n} must be a number") from exc
        if not vals[0] > 0:
            raise SoftplotError(f"{where}: principal distance c must be > 0 (or a certificate)")
        free = t.get("free", [])
        if not isinstance(free, list):
            raise SoftplotError(f"{where}: free must be a list of parameter names")
        sig = t.get("sigma", {})
        if not isinstance(sig, dict):
            raise SoftplotError(f"{where}: [camera.sigma] must be a table")
        px = t.get("pixel_size_um")
        weighted = {k: float(v) for k, v in sig.items()}
        lens = t.get("lens")
        auto = lens is None  # self-calibration of the lens: the forward model (unbiased sigma0)
        if auto:
            lens = "forward" if (set(free) | set(weighted)) & set(INTRINSICS[3:]) else "inverse"
        bc = BundleCamera.build(
            name,
            vals,
            free,
            weighted,
            None if px is None else float(px) / 1000.0,
            model=str(lens),
        )
        bc.model_auto = auto
        if "image_width_px" in t or "image_height_px" in t:
            try:
                bc.image_size = (int(t["image_width_px"]), int(t["image_height_px"]))
            except (KeyError, TypeError, ValueError) as exc:
                raise SoftplotError(
                    f"{where}: image_width_px and image_height_px must be integers"
                ) from exc
        bc.sigma_image_given = "sigma_image_um" in t
        bc.sigma_image_mm = float(t.get("sigma_image_um", 2.0)) / 1000.0
        if not bc.sigma_image_mm > 0:
            raise SoftplotError(f"{where}: sigma_image_um must be > 0")
        cams.append(bc)
    names = [c.name for c in cams]
    if len(set(names)) != len(names):
        raise SoftplotError(f"{path}: duplicate camera names")
    return cams


def _angle_columns(fields) -> tuple[list, str]:
    for unit in ("deg", "gon", "rad"):
        cols = [f"omega_{unit}", f"phi_{unit}", f"kappa_{unit}"]
        if all(c in fields for c in cols):
            return cols, unit
    return ["omega", "phi", "kappa"], "deg"


def read_project(folder: str | Path) -> BundleData:
    """Read a project folder into :class:`BundleData` (NaN where approximations are missing)."""
    root = Path(folder)
    if not root.is_dir():
        raise SoftplotError(f"project folder not found: {root}")
    cams = read_cameras(root / "cameras.toml")
    cam_idx = {c.name: i for i, c in enumerate(cams)}
    prow = _rows(root / "photos.csv", ("photo", "camera"))
    if not prow:
        raise SoftplotError(f"{root / 'photos.csv'}: no photos")
    acols, unit = _angle_columns(prow[0].keys())
    names, pcam, X0, ang, fixed, series = [], [], [], [], [], []
    for k, r in enumerate(prow):
        where = f"photos.csv row {k + 2}"
        if r["camera"] not in cam_idx:
            raise SoftplotError(f"{where}: unknown camera {r['camera']!r}")
        names.append(r["photo"])
        pcam.append(cam_idx[r["camera"]])
        X0.append([_num(r.get(c, ""), where) for c in ("X0", "Y0", "Z0")])
        a = [_num(r.get(c, ""), where) for c in acols]
        ang.append([float(to_radians(v, unit)) if math.isfinite(v) else math.nan for v in a])
        fixed.append(r.get("fixed", "").lower() in ("1", "true", "yes"))
        series.append(r.get("series", ""))
    if len(set(names)) != len(names):
        raise SoftplotError("photos.csv: duplicate photo names")
    ph_idx = {n: i for i, n in enumerate(names)}
    orow = _rows(root / "observations.csv", ("photo", "name", "x", "y"))
    if not orow:
        raise SoftplotError("observations.csv: no observations")
    pt_idx: dict[str, int] = {}
    op, oq, xy, sxy, cxy = [], [], [], [], []
    given = []  # per observation: its precision stated (own sx, sy or the camera's sigma_image_um)
    for k, r in enumerate(orow):
        where = f"observations.csv row {k + 2}"
        if r["photo"] not in ph_idx:
            raise SoftplotError(f"{where}: unknown photo {r['photo']!r}")
        f = ph_idx[r["photo"]]
        op.append(f)
        oq.append(pt_idx.setdefault(r["name"], len(pt_idx)))
        xy.append([_num(r["x"], where, None), _num(r["y"], where, None)])
        if xy[-1][0] is None or xy[-1][1] is None:
            raise SoftplotError(f"{where}: x and y are required")
        s0 = cams[pcam[f]].sigma_image_mm
        own = all(str(r.get(k) or "").strip() != "" for k in ("sx", "sy"))
        given.append(getattr(cams[pcam[f]], "sigma_image_given", True) or own)
        sxy.append([_num(r.get("sx", ""), where, s0), _num(r.get("sy", ""), where, s0)])
        cxy.append(_num(r.get("sxy", ""), where, 0.0))
    P = len(pt_idx)
    control = np.full((P, 3), np.nan)
    csig = np.full((P, 3), np.nan)
    check = np.zeros(P, bool)
    cpath = root / "control.csv"
    if cpath.is_file():
        for k, r in enumerate(_rows(cpath, ("name", "X", "Y", "Z"))):
            where = f"control.csv row {k + 2}"
            if r["name"] not in pt_idx:
                continue  # control not measured in any photo
            j = pt_idx[r["name"]]
            for a, (cn, sn) in enumerate((("X", "sX"), ("Y", "sY"), ("Z", "sZ"))):
                v = _num(r.get(cn, ""), where)
                s = _num(r.get(sn, ""), where, 0.0)
                if s < 0:
                    raise SoftplotError(f"{where}: negative standard error")
                control[j, a] = v
                csig[j, a] = s if math.isfinite(v) else math.nan
            typ = r.get("type", "control").lower() or "control"
            if typ not in ("control", "check"):
                raise SoftplotError(f"{where}: type must be control or check, got {typ!r}")
            check[j] = typ == "check"
    point_names = [None] * P
    for n, j in pt_idx.items():
        point_names[j] = n
    XYZ = np.full((P, 3), np.nan)
    ppath = root / "points.csv"
    if ppath.is_file():  # approximate object coordinates (optional)
        for k, r in enumerate(_rows(ppath, ("name", "X", "Y", "Z"))):
            if r["name"] in pt_idx:
                where = f"points.csv row {k + 2}"
                XYZ[pt_idx[r["name"]]] = [_num(r[a], where) for a in ("X", "Y", "Z")]
    data = BundleData(
        cameras=cams,
        photo_names=names,
        photo_camera=np.array(pcam),
        X0=np.array(X0),
        angles=np.array(ang),
        point_names=point_names,
        XYZ=XYZ,
        control=control,
        control_sigma=csig,
        obs_photo=np.array(op),
        obs_point=np.array(oq),
        xy=np.array(xy, float),
        sigma_xy=np.array(sxy, float),
        cov_xy=np.array(cxy, float),
        precision_given=all(given),
        photo_fixed=np.array(fixed),
        check=check,
    )
    data.series = series
    return data


def write_project(folder: str | Path, data: BundleData, series=None, overwrite=False) -> Path:
    """Write ``data`` as a project folder (angles in degrees); refuses to overwrite files."""
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    for f in FILES:
        if (root / f).exists() and not overwrite:
            raise SoftplotError(f"{root / f} exists; not overwriting")
    lines = []
    for c in data.cameras:
        lines.append("[[camera]]")
        lines.append(f'name = "{c.name}"')
        for n, v in zip(INTRINSICS, c.values, strict=True):
            lines.append(f"{n} = {float(v)!r}")
        free = [n for n, s in zip(INTRINSICS, c.sigma, strict=True) if np.isinf(s)]
        lines.append("free = [" + ", ".join(f'"{n}"' for n in free) + "]")
        lines.append(f'lens = "{c.model}"')
        sim = getattr(c, "sigma_image_mm", None)
        if sim is None:
            sim = float(np.median(data.sigma_xy))
        if data.precision_given:  # an unstated precision stays unstated (Pope's tau test)
            lines.append(f"sigma_image_um = {sim * 1000.0!r}")
        if c.pixel_size_mm:
            lines.append(f"pixel_size_um = {c.pixel_size_mm * 1000.0!r}")
        if c.image_size:
            lines.append(f"image_width_px = {int(c.image_size[0])}")
            lines.append(f"image_height_px = {int(c.image_size[1])}")
        w = {n: s for n, s in zip(INTRINSICS, c.sigma, strict=True) if 0 < s < np.inf}
        if w:
            lines.append("[camera.sigma]")
            lines.extend(f"{n} = {float(s)!r}" for n, s in w.items())
        lines.append("")
    (root / "cameras.toml").write_text("\n".join(lines), encoding="utf-8")
    deg = from_radians(data.angles, "deg")
    with open(root / "photos.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(
            ["photo", "camera", "X0", "Y0", "Z0", "omega", "phi", "kappa", "fixed", "series"]
        )
        for f, n in enumerate(data.photo_names):
            vals = ["" if not np.isfinite(v) else repr(float(v)) for v in [*data.X0[f], *deg[f]]]
            w.writerow(
                [
                    n,
                    data.cameras[data.photo_camera[f]].name,
                    *vals,
                    int(data.photo_fixed[f]),
                    "" if series is None else series[f],
                ]
            )
    with open(root / "observations.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        cov = data.cov_xy
        sig = data.precision_given
        w.writerow(["photo", "name", "x", "y"] + (["sx", "sy"] if sig else [])
                   + ([] if cov is None else ["sxy"]))
        for o in range(data.obs_photo.size):
            w.writerow(
                [
                    data.photo_names[data.obs_photo[o]],
                    data.point_names[data.obs_point[o]],
                    repr(float(data.xy[o, 0])),
                    repr(float(data.xy[o, 1])),
                ]
                + ([repr(float(data.sigma_xy[o, 0])), repr(float(data.sigma_xy[o, 1]))]
                   if sig else [])
                + ([] if cov is None else [repr(float(cov[o]))])
            )
    with open(root / "control.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "X", "Y", "Z", "sX", "sY", "sZ", "type"])
        for p, n in enumerate(data.point_names):
            if not np.any(np.isfinite(data.control[p])):
                continue
            v = ["" if not np.isfinite(x) else repr(float(x)) for x in data.control[p]]
            s = ["" if not np.isfinite(x) else repr(float(x)) for x in data.control_sigma[p]]
            w.writerow([n, *v, *s, "check" if data.check[p] else "control"])
    if np.any(np.isfinite(data.XYZ)):
        with open(root / "points.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(["name", "X", "Y", "Z"])
            for p, n in enumerate(data.point_names):
                if np.all(np.isfinite(data.XYZ[p])):
                    w.writerow([n, *(repr(float(x)) for x in data.XYZ[p])])
    return root
