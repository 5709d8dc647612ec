"""Plotting sessions: a project folder with the model and an fsync'd journal (MODEL RESUME).

Folder layout::

    session.json      orientation of both photos, mode, contour height, axis configuration
    corrections.pkl   the film-correction callables of each photo (pickled; optional)
    journal.jsonl     one JSON record per line, appended and fsync'd before each call returns

Journal records (``type``): ``feature`` (a recorded :class:`Feature`), ``motors`` (motor
state: targets, slack side, main carriage), ``mode`` (mode and contour height), ``fault``
(what stopped the motors), ``resume``. Every record is written with one ``write`` of a full
line followed by ``flush`` and :func:`os.fsync`, so after a crash (even ``kill -9``) the
journal holds every record whose call had returned; a torn last line (a crash in the middle
of a write) is dropped on resume.

:meth:`Session.resume` restores orientation, film corrections, mode, features and motor state
without measuring anything again; given a :class:`~softplot.motors.base.Motors` it drives the
secondary carriage back to the saved position.

``corrections.pkl`` is a Python pickle: open only session folders you trust.
"""

from __future__ import annotations

import json
import os
import pickle
import time
from pathlib import Path

from softplot.errors import SoftplotError
from softplot.export.features import Feature
from softplot.motors.base import MotorFault, Motors
from softplot.stereo.model import OrientedPhoto, StereoModel
from softplot.stereo.plotter import Plotter, PlotterHalted

__all__ = ["Session", "SESSION_FILE", "JOURNAL_FILE"]

SESSION_FILE = "session.json"
JOURNAL_FILE = "journal.jsonl"
CORRECTIONS_FILE = "corrections.pkl"
VERSION = 1


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

        ``left_offset`` is the fixed offset of the left plate (see :class:`Plotter`).
        """
        folder = Path(folder)
        if (folder / SESSION_FILE).exists() and not exist_ok:
            raise SoftplotError(f"{folder} already holds a session: resume it or choose another")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SoftplotError(f"cannot create session folder {folder}: {exc.strerror}") from exc
        meta = {
            "version": VERSION,
            "created": time.time(),
            "left": model.left.to_dict(),
            "right": model.right.to_dict(),
            "mode": mode,
            "height": height,
            "left_offset": [float(left_offset[0]), float(left_offset[1])],
        }
        corr = {
            side: (p.to_photo, p.to_film)
            for side, p in (("left", model.left), ("right", model.right))
            if p.to_photo is not None
        }
        if corr:
            try:
                blob = pickle.dumps(corr)
            except Exception as exc:  # noqa: BLE001 - any pickling failure
                raise SoftplotError(
                    f"film corrections cannot be saved in the session ({exc}); pass picklable "
                    "callables (module-level functions or objects' bound methods)"
                ) from exc
            _atomic_write(folder / CORRECTIONS_FILE, blob)
        elif (folder / CORRECTIONS_FILE).exists():
            (folder / CORRECTIONS_FILE).unlink()
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
        corr = {}
        if (folder / CORRECTIONS_FILE).exists():
            try:
                corr = pickle.loads((folder / CORRECTIONS_FILE).read_bytes())
            except Exception as exc:  # noqa: BLE001
                raise SoftplotError(f"cannot load film corrections of {folder}: {exc}") from exc
        try:
            left = OrientedPhoto.from_dict(meta["left"], *corr.get("left", (None, None)))
            right = OrientedPhoto.from_dict(meta["right"], *corr.get("right", (None, None)))
        except (KeyError, TypeError) as exc:
            raise SoftplotError(f"{folder / SESSION_FILE}: bad orientation ({exc})") from exc
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
