"""Plotting sessions: a folder with the oriented model, its scans and an fsync'd journal.

A session is data: JSON, NumPy ``.npz`` arrays read with ``allow_pickle=False``, and the
journal. Opening a session folder someone sent you runs none of their code.

Folder layout (format ``softplot-session``, version 2)::

    session.json               the model and the operator's settings (below)
    photos/left.correction.json  film correction of the left scan, as data
    photos/left.correction.npz   its arrays (reference marks: film mm, pixel px)
    photos/right.correction.*    the same for the right scan
    journal.jsonl              one JSON record per line, appended and fsync'd

``session.json``::

    {"format": "softplot-session", "version": 2, "created": <unix s>, "softplot": <version>,
     "mode": "single"|"contour"|"free", "height": <contour Z or null>,
     "left_offset": [bx, by],                     instrument mm
     "photos": {"left": PHOTO, "right": PHOTO}}

    PHOTO = {"name": str,
             "orientation": {"X0": [m, m, m], "angles_rad": [omega, phi, kappa], "c": mm,
                             "x0": mm, "y0": mm},
             "camera": <certificate name> or null,
             "correction": "photos/left.correction.json" or null,
             "scan": null or {"path": <relative to the session folder, or absolute>,
                              "name", "size_bytes", "sha256", "mtime_ns",
                              "width", "height", "dpi"}}

Instrument mm: the carriages move over each scan (:class:`softplot.correction.ScanFrame`:
x right, y up, origin at the scan's centre, one pixel = ``pixel_mm``), and the film
correction (:class:`softplot.correction.ScanPhotoMap`) takes them to photo mm. A photo with no
correction is measured in photo mm directly (instrument mm = photo mm).

The scans are not needed to plot (the corrections are data); the stereo viewer and the
surface need them: :meth:`Session.scan_path` finds each scan and checks it is the one the
session was made on (size and modification time, else its sha256).

Journal records (``type``): ``feature`` (a recorded :class:`Feature`), ``motors`` (motor
state: targets, slack side, main carriage), ``mode`` (mode and contour height), ``fault``
(what stopped the motors), ``resume``, ``input`` (an operator-input or photos file a command
read for this session, absolute path: ``softplot plot export`` never writes over one). Every
record is written with one ``write`` of a full line followed by ``flush`` and
:func:`os.fsync`, so after a crash (even ``kill -9``) the journal holds every record whose
call had returned; a torn last line (a crash in the middle of a write) is dropped on resume.

:meth:`Session.resume` restores orientation, film corrections, mode, features and motor state
without measuring anything again; given a :class:`~softplot.motors.base.Motors` it drives the
secondary carriage back to the saved position.

Version 1 folders kept the film corrections as a Python pickle (``corrections.pkl``); they
are refused with the fix: :func:`upgrade_session` (``softplot plot upgrade FOLDER``) converts
them, reading the pickle with an unpickler that builds only softplot and NumPy objects.
"""

from __future__ import annotations

import json
import os
import pickle
import time
from pathlib import Path

from softplot import __version__
from softplot.correction import ScanFrame, ScanPhotoMap, load_correction, save_correction
from softplot.errors import SoftplotError
from softplot.export.features import Feature
from softplot.motors.base import MotorFault, Motors
from softplot.stereo.model import OrientedPhoto, StereoModel
from softplot.stereo.plotter import Plotter, PlotterHalted

__all__ = [
    "Session",
    "upgrade_session",
    "scan_photo_map",
    "SESSION_FILE",
    "JOURNAL_FILE",
    "SESSION_FORMAT",
]

SESSION_FILE = "session.json"
JOURNAL_FILE = "journal.jsonl"
PHOTOS_DIR = "photos"
LEGACY_CORRECTIONS = "corrections.pkl"
SESSION_FORMAT = "softplot-session"
VERSION = 2
SIDES = ("left", "right")


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def scan_photo_map(scan_path, camera, detection=None, *, method: str = "mesh",
                   dpi: float | None = None) -> ScanPhotoMap:
    """The instrument <-> photo map of a scan: its frame and its film correction.

    Parameters
    ----------
    scan_path : path
        The scan (read for its size and dpi; its marks are detected when ``detection`` is
        None).
    camera : Camera or str
        Certificate.
    detection : dict or path, optional
        A detection (``softplot detect`` JSON) of this scan; it must be of this scan (its
        recorded fingerprint, when it has one, and its size are checked).
    method : str
        Film-correction method (:data:`softplot.correction.METHODS`).
    dpi : float, optional
        The scan's resolution when the file does not say it.
    """
    from softplot.camera import load_camera
    from softplot.correction import FilmCorrection, load_detection
    from softplot.io import check_fingerprint, fingerprint, load_scan

    sp = Path(scan_path)
    cam = load_camera(camera)
    scan = load_scan(sp)
    if dpi and not scan.dpi:
        scan.dpi, scan.dpi_xy = float(dpi), (float(dpi), float(dpi))
    frame = ScanFrame.of_scan(scan.width, scan.height, dpi or scan.dpi)
    if detection is None:
        from softplot.marks import detect

        det = detect(scan, cam).to_json()
        det["scan"] = fingerprint(sp)
    else:
        det = load_detection(detection) if not isinstance(detection, dict) else detection
        where = det.get("_source", "the detection")
        from softplot.provenance import check_camera

        check_camera(det.get("camera"), cam.name, str(where))
        if isinstance(det.get("scan"), dict) and det["scan"].get("sha256"):
            check_fingerprint(sp, det["scan"], what=f"{where}")
        w, h = det.get("width"), det.get("height")
        if w and h and (int(w), int(h)) != (scan.width, scan.height):
            raise SoftplotError(
                f"{where} was made on a {w} x {h} px scan; {sp} is {scan.width} x {scan.height}"
            )
    fc = FilmCorrection.from_detection(cam, det, method)
    if fc.image_size is None:
        fc.image_size = (scan.width, scan.height)
    return ScanPhotoMap(fc, frame, sp)


def _scan_record(folder: Path, scan_path, correction) -> dict | None:
    """The ``scan`` entry of a photo: where the scan is (relative to the folder when it can
    be) and what it is (fingerprint, mtime, size in px, dpi)."""
    from softplot.io import check_fingerprint, fingerprint

    if scan_path is None:
        return None
    sp = Path(scan_path).resolve()
    if isinstance(correction.scan, dict) and correction.scan.get("sha256"):
        check_fingerprint(sp, correction.scan, what="its film correction")
    rec = fingerprint(sp)
    rec["mtime_ns"] = sp.stat().st_mtime_ns
    try:
        rel = os.path.relpath(sp, folder.resolve())
    except ValueError:  # another drive
        rel = str(sp)
    rec["path"] = rel
    return rec


def _photo_entry(folder: Path, side: str, p: OrientedPhoto) -> dict:
    entry = {"name": p.name, "orientation": p.to_dict(), "camera": None, "correction": None,
             "scan": None}
    entry["orientation"].pop("name", None)
    m = p.to_photo
    if m is None:
        return entry
    if not isinstance(m, ScanPhotoMap):
        raise SoftplotError(
            f"the {side} photo's film correction is a {type(m).__name__}: a session stores "
            "film corrections as data (softplot.correction.ScanPhotoMap)"
        )
    fc = m.correction
    rel = f"{PHOTOS_DIR}/{side}.correction.json"
    (folder / PHOTOS_DIR).mkdir(exist_ok=True)
    save_correction(fc, folder / rel, extra={"frame": m.frame.to_dict()})
    entry["camera"] = fc.camera.name
    entry["correction"] = rel
    scan = _scan_record(folder, m.scan_path, fc)
    if scan is not None:
        scan.update(width=m.frame.width, height=m.frame.height, dpi=25.4 / m.frame.pixel_mm)
    entry["scan"] = scan
    return entry


def _load_photo(folder: Path, side: str, entry: dict) -> tuple[OrientedPhoto, dict]:
    where = folder / SESSION_FILE
    try:
        o = dict(entry["orientation"])
        o["name"] = entry.get("name", side)
    except (KeyError, TypeError) as exc:
        raise SoftplotError(f"{where}: {side} photo: no orientation ({exc})") from None
    to_photo = to_film = None
    rel = entry.get("correction")
    if rel:
        cp = (folder / rel).resolve()
        if folder.resolve() not in cp.parents:
            raise SoftplotError(f"{where}: {side} correction {rel!r} lies outside the session")
        fc, meta = load_correction(cp)
        try:
            frame = ScanFrame(**meta["frame"])
        except (KeyError, TypeError) as exc:
            raise SoftplotError(f"{cp}: no scan frame ({exc})") from None
        scan = entry.get("scan") or {}
        sp = (folder / scan["path"]) if scan.get("path") else None
        m = ScanPhotoMap(fc, frame, sp)
        to_photo, to_film = m, m.inverse
    try:
        return OrientedPhoto.from_dict(o, to_photo, to_film), entry
    except (KeyError, TypeError, ValueError) as exc:
        raise SoftplotError(f"{where}: {side} photo: bad orientation ({exc})") from None


class Session:
    """A plotting job in a project folder.

    Use :meth:`create` or :meth:`resume`; then :meth:`plotter` for a plotter wired to the
    journal, or :meth:`record` directly.
    """

    def __init__(self, folder: Path, model: StereoModel, meta: dict):
        self.folder = Path(folder)
        self.model = model
        self.meta = meta
        self.mode = meta.get("mode", "single")
        self.height = meta.get("height")
        self.features: list[Feature] = []
        self.motor_state: dict | None = None
        self.faults: list[str] = []
        self.inputs: list[str] = []
        self._fh = None

    # ----------------------------------------------------------- create / resume
    @classmethod
    def create(
        cls,
        folder,
        model: StereoModel,
        *,
        mode: str = "single",
        height: float | None = None,
        left_offset: tuple[float, float] = (0.0, 0.0),
        exist_ok: bool = False,
    ) -> "Session":
        """Start a new session in ``folder`` (created; must not hold a session already).

        ``left_offset`` is the fixed offset of the left plate, instrument mm (see
        :class:`Plotter`). Each photo's ``to_photo`` is None (instrument mm = photo mm) or a
        :class:`softplot.correction.ScanPhotoMap`, stored as data with its scan's fingerprint
        (when it names the scan, the scan must be the one its correction was made on).
        """
        folder = Path(folder)
        if (folder / SESSION_FILE).exists() and not exist_ok:
            raise SoftplotError(f"{folder} already holds a session: resume it or choose another")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SoftplotError(f"cannot create session folder {folder}: {exc.strerror}") from exc
        meta = {
            "format": SESSION_FORMAT,
            "version": VERSION,
            "created": time.time(),
            "softplot": __version__,
            "mode": mode,
            "height": height,
            "left_offset": [float(left_offset[0]), float(left_offset[1])],
            "photos": {
                side: _photo_entry(folder, side, p)
                for side, p in zip(SIDES, (model.left, model.right), strict=True)
            },
        }
        _atomic_write(folder / SESSION_FILE, (json.dumps(meta, indent=1) + "\n").encode())
        (folder / JOURNAL_FILE).open("ab").close()
        _fsync_dir(folder)
        s = cls(folder, model, meta)
        s._append({"type": "mode", "mode": mode, "height": height})
        return s

    @classmethod
    def resume(cls, folder, motors: Motors | None = None) -> "Session":
        """Re-open a session: orientation, corrections, mode, features and motor state.

        Parameters
        ----------
        folder : path
            The session folder.
        motors : Motors, optional
            If given, the secondary carriage is driven back to the saved state
            (:meth:`Motors.restore`).
        """
        folder = Path(folder)
        try:
            meta = json.loads((folder / SESSION_FILE).read_text())
        except FileNotFoundError as exc:
            raise SoftplotError(f"no session in {folder} ({SESSION_FILE} missing)") from exc
        except (OSError, json.JSONDecodeError) as exc:
            raise SoftplotError(f"unreadable {folder / SESSION_FILE}: {exc}") from exc
        if not isinstance(meta, dict):
            raise SoftplotError(f"{folder / SESSION_FILE}: not a softplot session")
        version = int(meta.get("version", 1))
        if version > VERSION:
            raise SoftplotError(
                f"{folder / SESSION_FILE}: written by a newer softplot (session version "
                f"{version}); update softplot"
            )
        if version < 2:
            if (folder / LEGACY_CORRECTIONS).exists():
                raise SoftplotError(
                    f"{folder}: a version-1 session whose film corrections are a Python pickle; "
                    f"convert it with `softplot plot upgrade {folder}` (only for a folder you "
                    "trust)"
                )
            meta = _v1_to_v2_meta(meta)
        photos = meta.get("photos")
        if not isinstance(photos, dict) or any(side not in photos for side in SIDES):
            raise SoftplotError(f"{folder / SESSION_FILE}: needs a left and a right photo")
        (left, _), (right, _) = (_load_photo(folder, side, photos[side]) for side in SIDES)
        s = cls(folder, StereoModel(left, right), meta)
        s._replay()
        s._append({"type": "resume"})
        if motors is not None and s.motor_state is not None:
            try:
                motors.restore(s.motor_state)
            except MotorFault as exc:
                msg = f"motor fault while restoring the motor state: {exc}"
                try:
                    motors.stop()
                    msg += "; motors stopped"
                except Exception as stop_exc:  # noqa: BLE001 - report, never mask the fault
                    msg += f"; stopping failed too ({stop_exc})"
                msg += f"; session kept ({len(s.features)} features recorded)"
                s.fault(msg)
                s.close()
                raise PlotterHalted(msg) from exc
        return s

    # ----------------------------------------------------------- photos and scans
    def photo_map(self, side: str) -> ScanPhotoMap | None:
        """The ``side`` ("left"/"right") photo's instrument <-> photo map, or None."""
        p = self._photo(side)
        return p.to_photo if isinstance(p.to_photo, ScanPhotoMap) else None

    def _photo(self, side: str) -> OrientedPhoto:
        if side not in SIDES:
            raise SoftplotError(f"photo side must be left or right, got {side!r}")
        return self.model.left if side == "left" else self.model.right

    def scan_path(self, side: str) -> Path:
        """The ``side`` photo's scan, checked to be the one the session was made on.

        Raises :class:`SoftplotError` (one line, the path expected) when the session names no
        scan, or the scan is missing, moved or changed. A scan with the recorded size and
        modification time is taken as it is; otherwise its content hash decides.
        """
        from softplot.io import check_fingerprint

        rec = (self.meta.get("photos", {}).get(side) or {}).get("scan")
        if not rec or not rec.get("path"):
            raise SoftplotError(f"session {self.folder}: the {side} photo has no scan")
        path = (self.folder / rec["path"]).resolve()
        if not path.is_file():
            raise SoftplotError(
                f"session {self.folder}: the {side} scan is missing: expected at {path} "
                f"({rec.get('name')}); moved?"
            )
        st = path.stat()
        if st.st_size == rec.get("size_bytes") and st.st_mtime_ns == rec.get("mtime_ns"):
            return path
        try:
            check_fingerprint(path, rec, what=f"session {self.folder}")
        except SoftplotError as exc:
            raise SoftplotError(f"the {side} scan has changed: {exc}") from None
        return path

    def owns(self, path) -> bool:
        """True when ``path`` is one of this session's own files (or its photos folder)."""
        p, f = Path(path).resolve(), self.folder.resolve()
        return p in (f / SESSION_FILE, f / JOURNAL_FILE, f / PHOTOS_DIR, f) or (
            f / PHOTOS_DIR) in p.parents

    def note_input(self, path) -> None:
        """Journal ``path`` as a file read for this session (see :meth:`input_files`)."""
        p = str(Path(path).resolve())
        if p not in self.inputs:
            self.inputs.append(p)
            self._append({"type": "input", "path": p})

    def input_files(self) -> list[Path]:
        """Every file this session was made from: the files of :meth:`note_input` and the
        scans named in session.json (absolute paths; they may no longer exist)."""
        out = [Path(p) for p in self.inputs]
        for side in SIDES:
            rec = (self.meta.get("photos", {}).get(side) or {}).get("scan")
            if rec and rec.get("path"):
                out.append((self.folder / rec["path"]).resolve())
        return out

    def scan_record(self, side: str) -> dict | None:
        """The ``scan`` entry of the ``side`` photo (name, size, sha256, width, height, dpi)."""
        self._photo(side)
        return (self.meta.get("photos", {}).get(side) or {}).get("scan")

    def _replay(self) -> None:
        path = self.folder / JOURNAL_FILE
        if not path.exists():
            return
        data = path.read_bytes()
        good = data.rfind(b"\n") + 1
        if good < len(data):  # torn last record: drop it (its call never returned)
            with open(path, "r+b") as fh:
                fh.truncate(good)
                fh.flush()
                os.fsync(fh.fileno())
        for n, line in enumerate(data[:good].splitlines(), 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as exc:
                raise SoftplotError(f"{path}: line {n} is not JSON ({exc.msg})") from exc
            kind = rec.get("type")
            if kind == "feature":
                self.features.append(Feature.from_record(rec["feature"]))
            elif kind == "motors":
                self.motor_state = rec["state"]
            elif kind == "mode":
                self.mode, self.height = rec["mode"], rec.get("height")
            elif kind == "fault":
                self.faults.append(rec["message"])
            elif kind == "input":
                self.inputs.append(rec["path"])

    # ----------------------------------------------------------- journal
    def _append(self, rec: dict) -> None:
        rec = {"t": time.time(), **rec}
        line = (json.dumps(rec, separators=(",", ":")) + "\n").encode()
        if self._fh is None:
            self._fh = open(self.folder / JOURNAL_FILE, "ab", buffering=0)
        self._fh.write(line)
        os.fsync(self._fh.fileno())

    def record(self, feature: Feature) -> None:
        """Append a feature to the journal; on disk (fsync'd) when this returns."""
        self._append({"type": "feature", "feature": feature.to_record()})
        self.features.append(feature)

    def save_motors(self, motors: Motors) -> None:
        """Journal the motor state (restored by :meth:`resume`)."""
        self.motor_state = motors.state()
        self._append({"type": "motors", "state": self.motor_state})

    def set_mode(self, mode: str, height: float | None = None) -> None:
        """Journal a mode change."""
        self.mode, self.height = mode, height
        self._append({"type": "mode", "mode": mode, "height": height})

    def fault(self, message: str) -> None:
        """Journal a motor fault message."""
        self.faults.append(message)
        self._append({"type": "fault", "message": message})

    def plotter(self, motors: Motors) -> Plotter:
        """A :class:`Plotter` on this session's model whose features and faults go to the
        journal (with the motor state saved after each feature and each fault)."""

        def on_feature(f: Feature) -> None:
            self.record(f)
            self.save_motors(motors)

        def on_fault(msg: str) -> None:
            self.fault(msg)
            try:
                self.save_motors(motors)
            except Exception:  # noqa: BLE001 - motors may be unreachable after a fault
                pass

        pl = Plotter(
            self.model,
            motors,
            mode=self.mode,
            height=self.height,
            on_feature=on_feature,
            on_fault=on_fault,
            left_offset=tuple(self.meta.get("left_offset", (0.0, 0.0))),
        )
        pl.features = list(self.features)
        return pl

    def export(self, path, fmt: str | None = None) -> Path:
        """Write the session's features as DXF, GeoJSON or CSV (by ``fmt`` or suffix)."""
        from softplot.export.csvfile import write_csv
        from softplot.export.dxf import write_dxf
        from softplot.export.geojson import write_geojson

        path = Path(path)
        fmt = (fmt or path.suffix.lstrip(".")).lower()
        writers = {
            "dxf": write_dxf,
            "geojson": write_geojson,
            "json": write_geojson,
            "csv": write_csv,
        }
        if fmt not in writers:
            raise SoftplotError(f"unknown export format {fmt!r}: use dxf, geojson or csv")
        return writers[fmt](self.features, path)

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# --------------------------------------------------------------------------------- version 1


def _v1_to_v2_meta(meta: dict) -> dict:
    """A version-1 ``session.json`` (orientations under ``left``/``right``) as version 2."""
    out = {k: v for k, v in meta.items() if k not in SIDES}
    out["photos"] = {}
    for side in SIDES:
        o = dict(meta.get(side) or {})
        name = o.pop("name", side)
        out["photos"][side] = {"name": name, "orientation": o, "camera": None,
                               "correction": None, "scan": None}
    out["format"], out["version"] = SESSION_FORMAT, VERSION
    return out


class _LegacyFrame:
    """Stands for version 1's pickled scan frame (``p``, ``cx``, ``cy``)."""


class _LegacyMap:
    """Stands for version 1's pickled instrument <-> photo callables (frame, correction)."""


_LEGACY = {
    ("softplot.pipeline.demo", "_ScanFrame"): _LegacyFrame,
    ("softplot.pipeline.demo", "_InstrToPhoto"): _LegacyMap,
    ("softplot.pipeline.demo", "_PhotoToInstr"): _LegacyMap,
}


class _SafeUnpickler(pickle.Unpickler):
    """Builds only softplot and NumPy objects (and plain containers): no other code runs."""

    _BUILTINS = {"tuple", "list", "dict", "set", "frozenset", "slice", "complex", "object"}

    def find_class(self, module: str, name: str):
        if (module, name) in _LEGACY:
            return _LEGACY[(module, name)]
        top = module.split(".")[0]
        if top in ("softplot", "numpy") or (module == "builtins" and name in self._BUILTINS) \
                or (module, name) in (("copyreg", "_reconstructor"),
                                      ("collections", "OrderedDict")):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def _legacy_map(side: str, obj) -> ScanPhotoMap:
    from softplot.correction import FilmCorrection

    if not isinstance(obj, _LegacyMap):
        raise SoftplotError(
            f"the {side} film correction is a {type(obj).__name__}, which version 2 cannot "
            "store as data; make the session again (softplot plot new)"
        )
    fr, old = obj.frame, obj.correction
    frame = ScanFrame(int(round(2 * fr.cx + 1)), int(round(2 * fr.cy + 1)), float(fr.p))
    fc = FilmCorrection(old.camera, old.marks, old.method, old.image_size)
    return ScanPhotoMap(fc, frame)


def upgrade_session(folder) -> Path:
    """Convert a version-1 session folder to version 2, in place; returns ``session.json``.

    The pickled film corrections are read with an unpickler that builds only softplot and
    NumPy objects, converted to data (:func:`softplot.correction.save_correction`) and the
    pickle is kept beside them as ``corrections.pkl.v1`` (nothing the user had is deleted;
    version 2 never reads it). The journal is unchanged. A version-2 folder is refused.
    """
    folder = Path(folder)
    sp = folder / SESSION_FILE
    try:
        meta = json.loads(sp.read_text())
    except FileNotFoundError:
        raise SoftplotError(f"no session in {folder} ({SESSION_FILE} missing)") from None
    except (OSError, ValueError) as exc:
        raise SoftplotError(f"unreadable {sp}: {exc}") from None
    if int(meta.get("version", 1)) >= 2:
        raise SoftplotError(f"{folder}: already a version-{meta['version']} session")
    new = _v1_to_v2_meta(meta)
    pk = folder / LEGACY_CORRECTIONS
    if pk.exists():
        try:
            with open(pk, "rb") as fh:
                corr = _SafeUnpickler(fh).load()
        except Exception as exc:  # noqa: BLE001 - any unpickling failure is one line
            raise SoftplotError(f"{pk}: cannot convert ({exc})") from None
        (folder / PHOTOS_DIR).mkdir(exist_ok=True)
        for side, pair in (corr or {}).items():
            if side not in SIDES:
                continue
            m = _legacy_map(side, pair[0])
            rel = f"{PHOTOS_DIR}/{side}.correction.json"
            save_correction(m.correction, folder / rel, extra={"frame": m.frame.to_dict()})
            new["photos"][side].update(camera=m.correction.camera.name, correction=rel)
    new["upgraded"] = {"from_version": int(meta.get("version", 1)), "at": time.time()}
    _atomic_write(sp, (json.dumps(new, indent=1) + "\n").encode())
    if pk.exists():
        os.replace(pk, pk.with_name(pk.name + ".v1"))
    _fsync_dir(folder)
    return sp
