"""Film correction of one scan: marks -> correction model -> film / photo coordinates.

The facade the CLI and the pipeline use. It wires a camera certificate, the measured marks
(a detection JSON of ``softplot detect`` or a fresh :func:`softplot.marks.detect`), a
correction method of :mod:`softplot.geometry.models` and the interior orientation of
:mod:`softplot.orientation.interior`:

    pixel (px) --correction model--> film (mm) --interior orientation--> photo (mm)

and provides the points CSV reader/writer, the cross-validation report and the resampling of
a scan onto the calibrated film grid (:func:`resample`, :func:`write_resampled`).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softplot.camera import Camera, load_camera, parse_certificate, to_toml
from softplot.errors import SoftplotError
from softplot.geometry.crossval import CrossValidation, cross_validate
from softplot.geometry.mesh import FLAG_NAMES, FLAG_OUTSIDE_IMAGE
from softplot.geometry.models import (
    METHODS,
    CorrectionModel,
    ReferenceMarks,
    build_model,
)
from softplot.orientation.interior import InteriorOrientation

__all__ = [
    "FilmCorrection",
    "marks_from_detection",
    "load_detection",
    "detect_marks",
    "read_points_csv",
    "write_points_csv",
    "compare",
    "resample",
    "film_maps",
    "default_pixel_size",
    "write_resampled",
    "Resampled",
    "METHODS",
    "ScanFrame",
    "ScanPhotoMap",
    "save_correction",
    "load_correction",
    "CORRECTION_FORMAT",
]


# ---------------------------------------------------------------------------------------------
# marks


def load_detection(path: str | Path) -> dict:
    """Read a detection JSON (docs/detection.md); errors name the file and the problem."""
    p = Path(path)
    if not p.is_file():
        raise SoftplotError(f"{p}: detection file not found")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SoftplotError(f"{p}: not a readable JSON file: {exc}") from None
    if not isinstance(d, dict) or not isinstance(d.get("marks"), list):
        raise SoftplotError(f"{p}: not a detection result (no 'marks' list)")
    d.setdefault("_source", str(p))
    return d


def marks_from_detection(camera: Camera | str, detection: dict) -> ReferenceMarks:
    """Reference marks from a detection dict: certificate film mm + measured pixel positions.

    Marks are matched by name (``R<row>C<col>`` or the fiducial's name; for crosses ``row``
    and ``col`` are used when present). Only marks with status "measured" and finite
    ``x``, ``y`` count as measured; everything else is NaN (missing). Each measured mark's
    covariance (px^2) is its ``cov`` (2 x 2), else ``sigma_x``/``sigma_y``, else ``sigma``
    (NaN without any): the models weight the marks by it (:func:`_mark_cov`).
    """
    cam = load_camera(camera)
    where = detection.get("_source", "detection")
    grid_film = grid_px = None
    if cam.reseau is not None:
        R = cam.reseau
        grid_film = R.film().reshape(R.rows, R.cols, 2)
        grid_px = np.full((R.rows, R.cols, 2), np.nan)
        grid_cov = np.full((R.rows, R.cols, 2, 2), np.nan)
    fid_names = tuple(f.name for f in cam.fiducials)
    fid_film = cam.fiducial_film()
    fid_px = np.full((len(fid_names), 2), np.nan)
    fid_cov = np.full((len(fid_names), 2, 2), np.nan)
    grid_cov = grid_cov if cam.reseau is not None else None
    n_cross = n_fid = 0
    for i, m in enumerate(detection["marks"]):
        if not isinstance(m, dict):
            raise SoftplotError(f"{where}: marks[{i}] is not an object")
        if m.get("status", "measured") != "measured":
            continue
        x, y = m.get("x"), m.get("y")
        if x is None or y is None:
            continue
        try:
            x, y = float(x), float(y)
        except (TypeError, ValueError):
            raise SoftplotError(f"{where}: marks[{i}]: x, y must be numbers") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        kind = m.get("kind", "reseau" if m.get("row") is not None else "fiducial")
        if kind == "reseau":
            if grid_px is None:
                raise SoftplotError(
                    f"{where}: has reseau crosses but camera {cam.name} has no reseau"
                )
            r, c = m.get("row"), m.get("col")
            if r is None or c is None:
                name = str(m.get("name", ""))
                try:
                    r, c = (int(v) for v in name[1:].split("C"))
                except ValueError:
                    raise SoftplotError(
                        f"{where}: marks[{i}]: cross without row/col and name {name!r}"
                    ) from None
            r, c = int(r), int(c)
            if not (0 <= r < grid_px.shape[0] and 0 <= c < grid_px.shape[1]):
                raise SoftplotError(
                    f"{where}: cross R{r}C{c} is outside the {grid_px.shape[0]} x "
                    f"{grid_px.shape[1]} reseau of camera {cam.name}: wrong camera?"
                )
            grid_px[r, c] = (x, y)
            grid_cov[r, c] = _mark_cov(m)
            n_cross += 1
        else:
            name = str(m.get("name", ""))
            if name in fid_names:
                fid_px[fid_names.index(name)] = (x, y)
                fid_cov[fid_names.index(name)] = _mark_cov(m)
                n_fid += 1
    if n_cross == 0 and n_fid == 0:
        raise SoftplotError(f"{where}: no measured marks for camera {cam.name}")
    if grid_cov is not None and not np.isfinite(grid_cov).any():
        grid_cov = None
    if not np.isfinite(fid_cov).any():
        fid_cov = None
    return ReferenceMarks(grid_film, grid_px, fid_film, fid_px, fid_names, grid_cov, fid_cov)


def _mark_cov(m: dict) -> np.ndarray:
    """A detection mark's pixel covariance (2, 2), px^2: its ``cov``, else the diagonal of
    ``sigma_x``, ``sigma_y``, else ``sigma`` in both axes; NaN when it has none or it is not
    a positive definite symmetric matrix."""
    nan = np.full((2, 2), np.nan)
    try:
        if m.get("cov") is not None:
            C = np.array(m["cov"], float).reshape(2, 2)
        elif m.get("sigma_x") is not None and m.get("sigma_y") is not None:
            C = np.diag([float(m["sigma_x"]) ** 2, float(m["sigma_y"]) ** 2])
        elif m.get("sigma") is not None:
            C = float(m["sigma"]) ** 2 * np.eye(2)
        else:
            return nan
    except (TypeError, ValueError):
        return nan
    if (not np.isfinite(C).all() or abs(C[0, 1] - C[1, 0]) > 1e-9 * abs(C).max()
            or C[0, 0] <= 0 or np.linalg.det(C) <= 0):
        return nan
    return C


def detect_marks(scan, camera: Camera | str) -> dict:
    """Detect the marks of a scan (path or Scan) with :func:`softplot.marks.detect`."""
    from softplot.marks import detect

    return detect(scan, camera).to_json()


# ---------------------------------------------------------------------------------------------
# the correction of one scan


class FilmCorrection:
    """Pixel -> film -> photo for one scan.

    Parameters
    ----------
    camera : Camera or str
        The certificate.
    marks : ReferenceMarks
        Calibrated film mm and measured pixel positions of the reference marks.
    method : str
        One of :data:`METHODS` (default ``mesh``: the camera's mesh; without a reseau,
        ``affine`` over the fiducials).
    image_size : (int, int), optional
        Scan width and height (px): points outside it are flagged ``outside-image``.
    """

    def __init__(self, camera, marks: ReferenceMarks, method: str = "mesh", image_size=None):
        self.camera = load_camera(camera)
        if method == "mesh" and not marks.has_grid:
            method = "affine"
        self.marks = marks
        self.model: CorrectionModel = build_model(method, marks)
        self.method = self.model.method
        self.interior = InteriorOrientation(self.camera)
        self.image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        #: the scan this correction was made on (:func:`softplot.io.fingerprint`), if known
        self.scan: dict | None = None

    @classmethod
    def from_detection(cls, camera, detection: dict, method: str = "mesh") -> "FilmCorrection":
        """From a detection dict (uses its ``width``/``height`` for ``outside-image``)."""
        marks = marks_from_detection(camera, detection)
        size = None
        if detection.get("width") and detection.get("height"):
            size = (int(detection["width"]), int(detection["height"]))
        fc = cls(camera, marks, method, size)
        if isinstance(detection.get("scan"), dict):
            fc.scan = detection["scan"]
        return fc

    @property
    def bounds(self):
        """(x0, x1, y0, y1) of the scan in px (pixel edges), or None."""
        if self.image_size is None:
            return None
        w, h = self.image_size
        return (-0.5, w - 0.5, -0.5, h - 0.5)

    def _image_flags(self, xy: np.ndarray, flags: np.ndarray) -> np.ndarray:
        b = self.bounds
        if b is None:
            return flags
        out = (xy[:, 0] < b[0]) | (xy[:, 0] > b[1]) | (xy[:, 1] < b[2]) | (xy[:, 1] > b[3])
        flags = flags.copy()
        flags[out] = FLAG_OUTSIDE_IMAGE
        return flags

    def pixel_to(self, xy_px, to: str = "film") -> tuple[np.ndarray, np.ndarray]:
        """Pixel (N, 2) -> film or photo (N, 2) mm, and flags (N,) uint8.

        Flags: 0 ok, 1 outside-reseau, 2 outside-image (:data:`FLAG_NAMES`).
        """
        if to not in ("film", "photo"):
            raise SoftplotError(f"--to must be film or photo, got {to!r}")
        p = np.asarray(xy_px, float).reshape(-1, 2)
        post = self.interior.film_to_photo_xy if to == "photo" else None
        return self.model.pixel_to_film(p, post, self.bounds)

    def to_pixel(self, xy_mm, frm: str = "film") -> tuple[np.ndarray, np.ndarray]:
        """Film or photo (N, 2) mm -> pixel (N, 2), and flags (N,) uint8."""
        f = np.asarray(xy_mm, float).reshape(-1, 2)
        if frm == "photo":
            f = self.interior.photo_to_film(f)
        elif frm != "film":
            raise SoftplotError(f"frm must be film or photo, got {frm!r}")
        px, flags = self.model.film_to_pixel(f)
        return px, self._image_flags(px, flags)

    def pixel_to_photo_point(self, x: float, y: float) -> tuple[float, float, int]:
        """One pixel point -> (photo x mm, photo y mm, flag): plain floats (plotter cycle)."""
        fx, fy, flag = self.model.pixel_to_film_point(x, y)
        px, py = self.interior.film_to_photo_point(fx, fy)
        if self.image_size is not None:
            w, h = self.image_size
            if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
                flag = FLAG_OUTSIDE_IMAGE
        return px, py, flag

    def photo_to_pixel_point(self, x: float, y: float) -> tuple[float, float, int]:
        """One photo point (mm) -> (pixel x, pixel y, flag): plain floats (drive-to)."""
        fx, fy = self.interior.photo_to_film_point(x, y)
        return self.model.film_to_pixel_point(fx, fy)

    def describe(self) -> str:
        return f"{self.model.describe()}; interior: {self.interior.describe()}"

    # ----------------------------------------------------------------- as data
    def to_data(self) -> tuple[dict, dict[str, np.ndarray]]:
        """This correction as plain data: a JSON-able dict and named float64 arrays.

        What is stored is what defines the correction: the certificate (TOML text, read back
        unchanged), the concrete method and the reference marks (calibrated film mm and
        measured pixel px, as arrays). :meth:`from_data` rebuilds the model from them by the
        same deterministic fit, so the numbers it gives are bit-identical. Nothing executable
        is stored (compare a pickle). Every array field of :class:`ReferenceMarks` is stored,
        so marks that gain fields (covariances) keep them.
        """
        arrays: dict[str, np.ndarray] = {}
        fields: dict[str, object] = {}
        for f in dataclasses.fields(self.marks):
            v = getattr(self.marks, f.name)
            if isinstance(v, np.ndarray):
                arrays[f"marks.{f.name}"] = np.ascontiguousarray(v)
            elif v is None:
                fields[f.name] = None
            else:
                fields[f.name] = list(v) if isinstance(v, tuple) else v
        meta = {
            "format": CORRECTION_FORMAT,
            "version": CORRECTION_VERSION,
            "method": self.method,
            "camera": {"name": self.camera.name, "certificate": to_toml(self.camera)},
            "image_size": None if self.image_size is None else list(self.image_size),
            "marks": fields,
            "scan": getattr(self, "scan", None),
        }
        return meta, arrays

    @classmethod
    def from_data(cls, meta: dict, arrays, where: str = "film correction") -> "FilmCorrection":
        """Rebuild a correction from :meth:`to_data`'s dict and arrays (any mapping of name ->
        array, e.g. an ``np.load(..., allow_pickle=False)`` file); errors name ``where``."""
        if meta.get("format") != CORRECTION_FORMAT:
            raise SoftplotError(f"{where}: not a softplot film correction")
        if int(meta.get("version", 0)) > CORRECTION_VERSION:
            raise SoftplotError(
                f"{where}: written by a newer softplot (format version {meta['version']})"
            )
        try:
            cam = parse_certificate(meta["camera"]["certificate"], where=f"{where}: certificate")
            kw = {}
            names = {f.name for f in dataclasses.fields(ReferenceMarks)}
            for name, v in meta.get("marks", {}).items():
                if name in names:
                    kw[name] = tuple(v) if isinstance(v, list) else v
            for key in arrays.keys() if hasattr(arrays, "keys") else arrays.files:
                if key.startswith("marks.") and key[6:] in names:
                    kw[key[6:]] = np.array(arrays[key], dtype=float)
            marks = ReferenceMarks(**kw)
            fc = cls(cam, marks, meta["method"], meta.get("image_size"))
        except (KeyError, TypeError, ValueError) as exc:
            raise SoftplotError(f"{where}: incomplete or malformed ({exc})") from None
        fc.scan = meta.get("scan")
        return fc


#: ``format`` of a film correction stored as data (:func:`save_correction`)
CORRECTION_FORMAT = "softplot-film-correction"
CORRECTION_VERSION = 1


def save_correction(correction: "FilmCorrection", path: str | Path,
                    extra: dict | None = None) -> Path:
    """Write ``correction`` as ``PATH`` (JSON, ``.json``) and ``PATH`` with ``.npz`` (its
    arrays, no pickles): the form sessions and projects keep film corrections in.

    ``extra`` entries (e.g. the scan frame) are stored beside the correction's own data.
    Both files are written atomically (a temporary file, then renamed).
    """
    meta, arrays = correction.to_data()
    if extra:
        meta.update(extra)
    p = Path(path).with_suffix(".json")
    npz = p.with_suffix(".npz")
    meta["arrays"] = npz.name
    tmp = npz.with_name(f".{npz.name}.part")
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    os.replace(tmp, npz)
    tmp = p.with_name(f".{p.name}.part")
    tmp.write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, p)
    return p


def load_correction(path: str | Path) -> tuple["FilmCorrection", dict]:
    """Read what :func:`save_correction` wrote: the correction and the whole JSON dict.

    The arrays are read with ``allow_pickle=False``: a film correction is data, never code.
    """
    p = Path(path)
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SoftplotError(f"{p}: film correction not found") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SoftplotError(f"{p}: not a readable JSON file ({exc})") from None
    if not isinstance(meta, dict):
        raise SoftplotError(f"{p}: not a softplot film correction")
    npz = p.with_name(str(meta.get("arrays") or p.with_suffix(".npz").name))
    if npz.name != Path(npz.name).name or npz.parent != p.parent:
        raise SoftplotError(f"{p}: its arrays must lie beside it")
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise SoftplotError(f"{npz}: film correction arrays not found") from None
    except (OSError, ValueError) as exc:
        raise SoftplotError(f"{npz}: unreadable film correction arrays ({exc})") from None
    return FilmCorrection.from_data(meta, arrays, where=str(p)), meta


@dataclass(frozen=True)
class ScanFrame:
    """Pixel px <-> instrument mm of one scan: the plotter's carriages move over the scan.

    Instrument mm: x right, y up, origin at the centre of the scan,
    ``x = (col - (W - 1) / 2) * pixel_mm``, ``y = ((H - 1) / 2 - row) * pixel_mm``
    (pixel system: x right = column, y down = row, (0, 0) the centre of the top-left pixel).
    """

    width: int
    height: int
    pixel_mm: float

    @classmethod
    def of_scan(cls, width: int, height: int, dpi: float) -> "ScanFrame":
        if not (dpi and dpi > 0):
            raise SoftplotError("the scan's dpi is unknown: give it (--dpi)")
        return cls(int(width), int(height), 25.4 / float(dpi))

    def to_instrument(self, xy_px) -> np.ndarray:
        """Pixel (N, 2) -> instrument mm (N, 2)."""
        px = np.asarray(xy_px, float).reshape(-1, 2)
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        return np.column_stack([(px[:, 0] - cx) * self.pixel_mm, (cy - px[:, 1]) * self.pixel_mm])

    def to_pixel(self, xy_mm) -> np.ndarray:
        """Instrument mm (N, 2) -> pixel (N, 2)."""
        xy = np.asarray(xy_mm, float).reshape(-1, 2)
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        return np.column_stack([xy[:, 0] / self.pixel_mm + cx, cy - xy[:, 1] / self.pixel_mm])

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "pixel_mm": self.pixel_mm}


class ScanPhotoMap:
    """Instrument mm <-> photo mm of one scan: its :class:`ScanFrame` and film correction.

    The ``to_photo`` of a :class:`softplot.stereo.OrientedPhoto` whose carriage moves over a
    scan: instrument mm -> pixel -> film mm (the correction model) -> photo mm (interior
    orientation); :meth:`inverse` is its ``to_film``. Plain data (the frame, the correction,
    the scan's path), so a session stores it without pickling.
    """

    def __init__(self, correction: FilmCorrection, frame: ScanFrame, scan_path=None):
        self.correction = correction
        self.frame = frame
        self.scan_path = None if scan_path is None else Path(scan_path)

    def __call__(self, xy_mm) -> np.ndarray:
        """Instrument mm (N, 2) -> photo mm (N, 2)."""
        return self.correction.pixel_to(self.frame.to_pixel(xy_mm), to="photo")[0]

    def inverse(self, xy_mm) -> np.ndarray:
        """Photo mm (N, 2) -> instrument mm (N, 2)."""
        return self.frame.to_instrument(self.correction.to_pixel(xy_mm, frm="photo")[0])

    def pixel_to_photo(self, xy_px) -> np.ndarray:
        """Pixel (N, 2) -> photo mm (N, 2)."""
        return self.correction.pixel_to(xy_px, to="photo")[0]

    def photo_to_pixel(self, xy_mm) -> np.ndarray:
        """Photo mm (N, 2) -> pixel (N, 2)."""
        return self.correction.to_pixel(xy_mm, frm="photo")[0]


def compare(camera, marks: ReferenceMarks, methods=None) -> CrossValidation:
    """Cross-validation of every method over the marks (see :mod:`softplot.geometry.crossval`)."""
    load_camera(camera)
    return cross_validate(marks, methods)


# ---------------------------------------------------------------------------------------------
# points CSV


def read_points_csv(path: str | Path) -> tuple[list[str], np.ndarray]:
    """Read ``name,x,y`` (pixels) from a CSV with a header; errors name the line.

    Extra columns are ignored; blank lines and lines starting with ``#`` are skipped.
    """
    p = Path(path)
    if not p.is_file():
        raise SoftplotError(f"{p}: points file not found")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise SoftplotError(f"{p}: cannot read: {exc}") from None
    rows = list(csv.reader(text.splitlines()))
    header = None
    names: list[str] = []
    xy: list[tuple[float, float]] = []
    for lineno, row in enumerate(rows, start=1):
        cells = [c.strip() for c in row]
        if not cells or all(c == "" for c in cells) or cells[0].startswith("#"):
            continue
        if header is None:
            header = [c.lower() for c in cells]
            missing = [c for c in ("name", "x", "y") if c not in header]
            if missing:
                raise SoftplotError(
                    f"{p}: line {lineno}: missing column {', '.join(repr(m) for m in missing)} "
                    f"(header has {', '.join(header) or 'nothing'}; need name,x,y)"
                )
            ix, iy, iname = header.index("x"), header.index("y"), header.index("name")
            continue
        if len(cells) < len(header):
            raise SoftplotError(
                f"{p}: line {lineno}: {len(cells)} columns, the header has {len(header)}"
            )
        vals = []
        for col, i in (("x", ix), ("y", iy)):
            try:
                v = float(cells[i])
            except ValueError:
                raise SoftplotError(
                    f"{p}: line {lineno}: {col} is not a number: {cells[i]!r}"
                ) from None
            if not math.isfinite(v):
                raise SoftplotError(f"{p}: line {lineno}: {col} is not finite: {cells[i]!r}")
            vals.append(v)
        names.append(cells[iname])
        xy.append((vals[0], vals[1]))
    if header is None:
        raise SoftplotError(f"{p}: empty points file (need a header name,x,y)")
    return names, np.array(xy, float).reshape(-1, 2)


def write_points_csv(path: str | Path, names, xy_mm: np.ndarray, flags: np.ndarray) -> Path:
    """Write ``name,x,y,flag`` (mm, 6 decimals = 1 nm) to a new file (never overwrites)."""
    p = Path(path)
    if p.exists():
        raise SoftplotError(f"{p}: exists; refusing to overwrite")
    tmp = p.with_name(f".{p.name}.part")
    with open(tmp, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "x", "y", "flag"])
        for n, (x, y), f in zip(names, np.asarray(xy_mm), np.asarray(flags), strict=True):
            w.writerow([n, f"{x:.6f}", f"{y:.6f}", FLAG_NAMES[int(f)]])
    tmp.replace(p)
    return p


# ---------------------------------------------------------------------------------------------
# resampling onto the film grid


@dataclass
class Resampled:
    """A film-flattened image and its pixel <-> film relation.

    Output pixel (row i, column j) - its centre - lies at film
    ``x = x_min + (j + 0.5) * pixel_size``, ``y = y_max - (i + 0.5) * pixel_size`` (mm).
    """

    image: np.ndarray
    pixel_size_mm: float
    x_min_mm: float
    y_max_mm: float
    method: str

    @property
    def affine(self) -> list[list[float]]:
        """2 x 3 matrix (column, row of a pixel centre, 1) -> film mm."""
        ps = self.pixel_size_mm
        return [
            [ps, 0.0, self.x_min_mm + 0.5 * ps],
            [0.0, -ps, self.y_max_mm - 0.5 * ps],
        ]

    def georef(self) -> dict:
        h, w = self.image.shape[:2]
        return {
            "system": "film",
            "units": "mm",
            "method": self.method,
            "width": int(w),
            "height": int(h),
            "pixel_size_mm": self.pixel_size_mm,
            "x_min_mm": self.x_min_mm,
            "y_max_mm": self.y_max_mm,
            "pixel_centre_to_film": self.affine,
            "convention": (
                "film x = x_min_mm + (col + 0.5) * pixel_size_mm, "
                "film y = y_max_mm - (row + 0.5) * pixel_size_mm; (col, row) = (0, 0) is the "
                "centre of the top-left pixel; film x right, y up, mm"
            ),
        }


def _film_grid(camera: Camera, ps: float) -> tuple[int, int, float, float]:
    w, h = camera.format_mm
    nx = max(int(round(w / ps)), 1)
    ny = max(int(round(h / ps)), 1)
    return nx, ny, -nx * ps / 2.0, ny * ps / 2.0


def _row_intervals(T, ys, x_min, ps, nx, free):
    """Owned column interval [j0, j1] per output row of one cell (film plane).

    ``T`` (3, 3) maps film (x, y, 1) to cell parameters (s, t) (h33 = 1). Along a row of
    constant y each condition -e <= s <= 1 + e, -e <= t <= 1 + e is linear in x (times the
    positive denominator), so the owned pixels of the row are one interval. ``free`` =
    (left, right, top, bottom): drop the condition on that side (border cells own everything
    beyond the reseau, as the point location does).
    """
    e = 1e-7
    lo = np.full(ys.shape, -np.inf)
    hi = np.full(ys.shape, np.inf)
    g, h = T[2, 0], T[2, 1]
    wy = h * ys + 1.0  # w = g x + wy
    conds = []
    for r, side_lo, side_hi in ((0, free[0], free[1]), (1, free[2], free[3])):
        a = T[r, 0]
        by = T[r, 1] * ys + T[r, 2]  # numerator = a x + by
        if not side_lo:  # a x + by >= -e (g x + wy)
            conds.append((a + e * g, -(by + e * wy)))
        if not side_hi:  # a x + by <= (1 + e)(g x + wy)  <=>  -(a - (1+e) g) x >= by - (1+e) wy
            conds.append((-(a - (1 + e) * g), by - (1 + e) * wy))
    for alpha, beta in conds:  # alpha x >= beta
        if alpha > 0:
            lo = np.maximum(lo, beta / alpha)
        elif alpha < 0:
            hi = np.minimum(hi, beta / alpha)
        else:
            bad = beta > 0
            lo = np.where(bad, np.inf, lo)
    with np.errstate(invalid="ignore"):
        j0 = np.ceil((lo - x_min) / ps - 0.5)
        j1 = np.floor((hi - x_min) / ps - 0.5)
    j0 = np.clip(np.nan_to_num(j0, nan=nx, posinf=nx, neginf=0), 0, nx).astype(np.intp)
    j1 = np.clip(np.nan_to_num(j1, nan=-1, posinf=nx - 1, neginf=-1), -1, nx - 1).astype(np.intp)
    return j0, j1


def _map_homography_mesh(model, nx, ny, x_min, y_max, ps):
    """Exact film -> pixel maps (float32) for a homography mesh, cell by cell.

    Per cell: its owned pixels row by row (:func:`_row_intervals`, the same cell test as the
    point path), and its film -> pixel homography evaluated separably (one column term plus
    one row term per pixel, float32: the maps are float32 anyway).
    """
    mesh = model.mesh
    H = mesh.film_cell_homographies()  # (K, 3, 3) film -> pixel
    T = mesh._film.to_raw  # (K, 3, 3) film -> (s, t), h33 = 1
    rows, cols = mesh.rows, mesh.cols
    mapx = np.empty((ny, nx), np.float32)
    mapy = np.empty((ny, nx), np.float32)
    xs = x_min + (np.arange(nx) + 0.5) * ps
    ys = y_max - (np.arange(ny) + 0.5) * ps
    jj = np.arange(nx)
    Q = mesh.film_quads()
    for k in range(Q.shape[0]):
        r, c = divmod(k, cols - 1)
        free = (c == 0, c == cols - 2, r == 0, r == rows - 2)
        qy = Q[k, :, 1]
        y1 = np.inf if free[2] else qy.max()
        y0 = -np.inf if free[3] else qy.min()
        i0 = int(np.searchsorted(-ys, -(y1 + 2 * ps)))
        i1 = int(np.searchsorted(-ys, -(y0 - 2 * ps)))
        if i1 <= i0:
            continue
        by = ys[i0:i1]
        j0, j1 = _row_intervals(T[k], by, x_min, ps, nx, free)
        ok = j1 >= j0
        if not ok.any():
            continue
        rs = np.flatnonzero(ok)
        by = by[rs[0] : rs[-1] + 1]
        j0, j1 = j0[rs[0] : rs[-1] + 1], j1[rs[0] : rs[-1] + 1]
        i0, i1 = i0 + rs[0], i0 + rs[-1] + 1
        a, b = int(j0.min()), int(j1.max()) + 1
        bx = xs[a:b]
        own = (jj[None, a:b] >= j0[:, None]) & (jj[None, a:b] <= j1[:, None])
        h = H[k]
        w = (h[2, 0] * bx).astype(np.float32)[None, :] + (h[2, 1] * by + h[2, 2]).astype(
            np.float32
        )[:, None]
        X = (h[0, 0] * bx).astype(np.float32)[None, :] + (h[0, 1] * by + h[0, 2]).astype(
            np.float32
        )[:, None]
        X /= w
        Y = (h[1, 0] * bx).astype(np.float32)[None, :] + (h[1, 1] * by + h[1, 2]).astype(
            np.float32
        )[:, None]
        Y /= w
        np.copyto(mapx[i0:i1, a:b], X, where=own)
        np.copyto(mapy[i0:i1, a:b], Y, where=own)
    return mapx, mapy


def _map_generic(model, nx, ny, x_min, y_max, ps, rows_per_chunk=64):
    """Film -> pixel maps through ``model.film_to_pixel``, in row chunks."""
    mapx = np.empty((ny, nx), np.float32)
    mapy = np.empty((ny, nx), np.float32)
    xs = x_min + (np.arange(nx) + 0.5) * ps
    for i0 in range(0, ny, rows_per_chunk):
        i1 = min(i0 + rows_per_chunk, ny)
        ys = y_max - (np.arange(i0, i1) + 0.5) * ps
        gx, gy = np.meshgrid(xs, ys)
        px = model.film_to_pixel(np.column_stack([gx.ravel(), gy.ravel()]))[0]
        mapx[i0:i1] = px[:, 0].reshape(i1 - i0, nx)
        mapy[i0:i1] = px[:, 1].reshape(i1 - i0, nx)
    return mapx, mapy


def film_maps(correction: FilmCorrection, pixel_size_mm: float):
    """(mapx, mapy, x_min, y_max): scan pixel of every output pixel centre (float32)."""
    cam = correction.camera
    nx, ny, x_min, y_max = _film_grid(cam, pixel_size_mm)
    if nx * ny > 2**31 - 1 or nx > 32767 or ny > 32767:
        raise SoftplotError(
            f"--pixel-size {pixel_size_mm * 1000:g} um gives a {nx} x {ny} image: too large"
        )
    model = correction.model
    if model.method == "mesh-homography":
        mapx, mapy = _map_homography_mesh(model, nx, ny, x_min, y_max, pixel_size_mm)
    else:
        mapx, mapy = _map_generic(model, nx, ny, x_min, y_max, pixel_size_mm)
    return mapx, mapy, x_min, y_max


def default_pixel_size(correction: FilmCorrection, dpi: float | None) -> float:
    """Output pixel size (mm): the scan's pixel size (25.4 / dpi), else measured from the
    marks (the mean scale of the correction model)."""
    if dpi:
        return 25.4 / float(dpi)
    f, p, _ = correction.marks.reference()
    if f.shape[0] >= 2:
        df = np.hypot(*(f[:, None] - f[None]).reshape(-1, 2).T)
        dp = np.hypot(*(p[:, None] - p[None]).reshape(-1, 2).T)
        ok = dp > 0
        return float(np.median(df[ok] / dp[ok]))
    raise SoftplotError("cannot tell the pixel size: give --pixel-size")


def resample(
    data: np.ndarray,
    correction: FilmCorrection,
    pixel_size_mm: float,
    interpolation: str = "linear",
) -> Resampled:
    """Resample scan pixels (H, W) or (H, W, C) onto the calibrated film grid.

    One :func:`cv2.remap` through the correction (the mesh): output pixel (i, j) takes the
    scan at ``film_to_pixel`` of its film centre (:class:`Resampled` gives the relation).
    Outside the scan the output is 0. The dtype and channels of ``data`` are kept.
    """
    import cv2

    if not (pixel_size_mm > 0 and math.isfinite(pixel_size_mm)):
        raise SoftplotError(f"pixel size must be positive, got {pixel_size_mm!r} mm")
    interp = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "nearest": cv2.INTER_NEAREST}
    if interpolation not in interp:
        raise SoftplotError(f"interpolation must be one of {', '.join(interp)}")
    mapx, mapy, x_min, y_max = film_maps(correction, pixel_size_mm)
    src = np.ascontiguousarray(data)
    if src.dtype == np.bool_:
        src = src.astype(np.uint8) * 255
    if src.ndim == 3 and src.shape[2] > 4:
        raise SoftplotError(f"cannot resample an image with {src.shape[2]} channels")
    if max(src.shape[:2]) >= 32767:
        raise SoftplotError("scans of 32767 px or more per side cannot be resampled (OpenCV)")
    out = cv2.remap(src, mapx, mapy, interp[interpolation], borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0)
    if out.ndim == 2 and src.ndim == 3:
        out = out[..., None]
    return Resampled(out, float(pixel_size_mm), float(x_min), float(y_max), correction.method)


def write_resampled(
    path: str | Path, res: Resampled, extra: dict | None = None
) -> tuple[Path, Path]:
    """Write the film-flattened TIFF and its JSON sidecar ``<path>.json``; never overwrites.

    TIFF tags: ``ModelPixelScaleTag`` (33550) = (ps, ps, 0) and ``ModelTiepointTag`` (33922)
    = (0, 0, 0, x_min, y_max, 0): raster corner (0, 0) - the outer corner of the top-left
    pixel - is film (x_min, y_max) mm (GeoTIFF "PixelIsArea" layout, no GeoKeyDirectory: the
    film plane is not a map projection); ``XResolution``/``YResolution`` = 25.4 / ps dpi;
    ``ImageDescription`` = the sidecar's JSON.
    """
    import tifffile

    p = Path(path)
    side = p.with_name(p.name + ".json")
    for q in (p, side):
        if q.exists():
            raise SoftplotError(f"{q}: exists; refusing to overwrite")
    if p.suffix.lower() not in (".tif", ".tiff"):
        raise SoftplotError(f"{p}: the resampled image is a TIFF: use a .tif or .tiff name")
    meta = res.georef()
    if extra:
        meta.update(extra)
    meta["image"] = p.name
    text = json.dumps(meta, indent=1)
    ps = res.pixel_size_mm
    img = res.image
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    photometric = "rgb" if img.ndim == 3 and img.shape[2] in (3, 4) else "minisblack"
    dpi = 25.4 / ps
    tmp = p.with_name(f".{p.name}.part")
    tifffile.imwrite(
        tmp,
        img,
        photometric=photometric,
        resolution=(dpi, dpi),
        resolutionunit="INCH",
        description=json.dumps(meta),
        extratags=[
            (33550, "d", 3, (ps, ps, 0.0), True),
            (33922, "d", 6, (0.0, 0.0, 0.0, res.x_min_mm, res.y_max_mm, 0.0), True),
        ],
        metadata=None,
    )
    tmp.replace(p)
    side.write_text(text + "\n", encoding="utf-8")
    return p, side
