"""The plotter behind the page: a session, its motors, its pyramids and the floating mark.

:class:`Viewer` owns the :class:`~softplot.pipeline.session.Session` (its journal), the
:class:`~softplot.stereo.plotter.Plotter` wired to it and the motors (virtual: the left
image's sampling position; GRBL: the instrument, whose reported position the screen then
shows). Every operator input of the page arrives as a message (:meth:`Viewer.handle`) and goes
through ``Plotter.cycle`` / ``drive_to`` / the recording calls; the answer is the state of the
floating mark (:meth:`Viewer.state`).

Coordinates: carriages in instrument mm (``X, Y`` the main carriage = the right scan point
under the mark; the left scan point is ``X + BX + DX, Y + BY + DY``); ``left_px``/``right_px``
the mark in each scan's pixels (pixel system: x right = column, y down = row, (0, 0) the
centre of the top-left pixel), through each scan's :class:`softplot.correction.ScanFrame`;
``object`` the model point (object units).
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np

from softplot.errors import SoftplotError

__all__ = ["Viewer", "open_motors", "VIEWS"]

#: composite modes of the page
VIEWS = ("anaglyph-dubois", "anaglyph-pure", "anaglyph-grey", "sbs-parallel", "sbs-cross",
         "mono-left", "mono-right")
SIDES = ("left", "right")


def open_motors(spec: str):
    """``virtual`` or ``grbl:PORT`` -> a :class:`~softplot.motors.base.Motors`."""
    from softplot.motors import AxisConfig, VirtualMotors

    if spec == "virtual":
        fine = AxisConfig(resolution_mm=1e-6, min_mm=-500, max_mm=500, max_speed_mm_s=1e9)
        return VirtualMotors(fine, fine)
    if spec.startswith("grbl:") and len(spec) > 5:
        from softplot.motors.grbl import GrblMotors

        return GrblMotors(spec[5:])
    raise SoftplotError(f"--motors must be virtual or grbl:PORT, got {spec!r}")


def _num(msg: dict, key: str) -> float:
    v = msg.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise SoftplotError(f"{key} must be a finite number")
    return float(v)


def _text(msg: dict, key: str, default: str | None = None) -> str:
    v = msg.get(key, default)
    if not isinstance(v, str) or not v.strip() or len(v) > 64:
        raise SoftplotError(f"{key} must be a short non-empty text")
    return v.strip()


class Viewer:
    """A session opened for viewing and plotting (see the module docstring).

    Parameters
    ----------
    folder : path
        The session folder (``softplot plot new`` / ``softplot demo``).
    motors : str
        ``virtual`` or ``grbl:PORT``.
    cache : path, optional
        Pyramid cache folder (default :func:`softplot.ui.pyramid.default_cache`).
    """

    def __init__(self, folder, motors: str = "virtual", cache=None, *, tile: int = 256):
        from softplot.pipeline.session import Session
        from softplot.ui.pyramid import build_pyramid

        self.folder = Path(folder)
        probe = Session.resume(self.folder)  # reads and checks the folder, journal replayed
        probe.close()
        self.maps = {}
        paths = {}
        for side in SIDES:
            m = probe.photo_map(side)
            if m is None:
                raise SoftplotError(f"session {self.folder}: the {side} photo has no scan and "
                                    "film correction; the viewer shows scans")
            self.maps[side] = m
            paths[side] = probe.scan_path(side)  # one line when moved or changed
        self.pyramids = {
            side: build_pyramid(paths[side], cache,
                                sha256=probe.scan_record(side).get("sha256"), tile=tile)
            for side in SIDES
        }
        self.motors = open_motors(motors)
        self.motors_spec = motors
        self.session = Session.resume(self.folder, motors=self.motors)
        self.plotter = self.session.plotter(self.motors)
        self.left_offset = tuple(self.session.meta.get("left_offset", (0.0, 0.0)))
        self.lock = threading.Lock()
        self.client = {"zoom": None, "view": None, "frames": 0}
        self.journaled_height = self.session.height
        from softplot.ui.measure import Measurements

        self.measure = Measurements(self.folder, {s: (self.pyramids[s].width,
                                                      self.pyramids[s].height) for s in SIDES})
        self._start()
        self.closed = False

    def _start(self) -> None:
        """Put the mark where the session left it (its saved main carriage), else on the
        last recorded vertex, else below the middle of the base at the contour height (or
        Z = 0)."""
        pl, st = self.plotter, self.session.motor_state
        if st and st.get("main"):
            pl.cycle(float(st["main"][0]), float(st["main"][1]))
            return
        m = pl.model
        if pl.features:
            P = np.asarray(pl.features[-1].vertices, float).reshape(-1, 3)[-1]
        else:
            mid = (np.asarray(m.left.X0, float) + np.asarray(m.right.X0, float)) / 2
            P = np.array([mid[0], mid[1], pl.height if pl.height is not None else 0.0])
        try:
            pl.drive_to(*map(float, P))
            if pl.mode != "free":
                pl.cycle(pl.current.X, pl.current.Y)
        except Exception:  # noqa: BLE001 - a start position only: the scan centre will do
            pl.cycle(0.0, 0.0)

    # ------------------------------------------------------------------ state
    def state(self) -> dict:
        """The floating mark: carriages, parallax, object point, scan pixels, client view."""
        c = self.plotter.current
        DX, DY = self.motors.position()
        bx, by = self.left_offset
        lp = self.maps["left"].frame.to_pixel([[c.X + bx + DX, c.Y + by + DY]])[0]
        rp = self.maps["right"].frame.to_pixel([[c.X, c.Y]])[0]
        pl = self.plotter
        return {
            "mode": pl.mode, "X": c.X, "Y": c.Y, "DX": DX, "DY": DY,
            "px": DX, "height": pl.height,
            "object": [float(v) for v in c.XYZ],
            "left_px": [float(lp[0]), float(lp[1])],
            "right_px": [float(rp[0]), float(rp[1])],
            "py": float(c.py), "in_travel": bool(c.in_travel),
            "zoom": self.client["zoom"], "view": self.client["view"],
            "frames": self.client["frames"],
            "open_vertices": 0 if pl._open is None else len(pl._open[2]),
            "features": len(pl.features), "halted": pl.halted,
        }

    def info(self) -> dict:
        """Static facts the page starts from: pyramids, frames, session name, mode."""
        return {
            "session": self.folder.name,
            "motors": self.motors_spec,
            "scans": {s: {**self.pyramids[s].info(), "pixel_mm": self.maps[s].frame.pixel_mm,
                          "name": (self.session.scan_record(s) or {}).get("name")}
                      for s in SIDES},
            "left_offset": list(self.left_offset),
            "views": list(VIEWS),
        }

    def feature_pixels(self) -> list[dict]:
        """Every recorded feature (and the open line) at its image positions, each scan's
        pixels: the object vertices projected into each photo and mapped to its scan."""
        pl = self.plotter
        items = [(f.code, f.kind, np.asarray(f.vertices, float)) for f in pl.features]
        if pl._open is not None and pl._open[2]:
            items.append((pl._open[0], "open", np.asarray(pl._open[2], float)))
        out = []
        for code, kind, v in items:
            v = v.reshape(-1, 3)
            rec = {"code": code, "kind": kind}
            for side, photo in (("left", self.plotter.model.left),
                                ("right", self.plotter.model.right)):
                px = self.maps[side].photo_to_pixel(photo.project(v))
                rec[side] = np.round(px, 4).tolist()
            out.append(rec)
        return out

    # ------------------------------------------------------------------ input
    def handle(self, msg: dict) -> dict:
        """One message of the page; returns the reply (``state``, maybe ``features``).

        Ops: ``cycle`` (X, Y[, px]), ``free`` (X, Y, DX, DY), ``mode`` (mode[, height]),
        ``height`` (contour height, not journalled until something is recorded), ``drive``
        (X, Y, Z object), ``record`` (code), ``begin`` (code[, kind]), ``vertex``, ``end``
        ([close]), ``undo`` (last vertex), ``client`` (zoom, view, frames: for
        ``/api/state``), ``state``. Bad values give ``{"type": "error", "message": ...}``.
        """
        if not isinstance(msg, dict):
            raise SoftplotError("a message is a JSON object")
        op = msg.get("op")
        pl = self.plotter
        feats = False
        with self.lock:
            if op == "cycle":
                px = _num(msg, "px") if msg.get("px") is not None and pl.mode == "single" \
                    else None
                pl.cycle(_num(msg, "X"), _num(msg, "Y"), px)
            elif op == "free":
                if pl.mode != "free":
                    raise SoftplotError("DX, DY are the operator's in free mode only")
                self.motors.move_to(_num(msg, "DX"), _num(msg, "DY"), wait=False)
                pl.cycle(_num(msg, "X"), _num(msg, "Y"))
            elif op == "mode":
                mode = _text(msg, "mode")
                h = msg.get("height")
                h = _num(msg, "height") if h is not None else pl.height
                pl.set_mode(mode, h)
                self.session.set_mode(mode, pl.height)
                self.journaled_height = pl.height
                c = pl.current
                pl.cycle(c.X, c.Y)
            elif op == "height":
                if pl.mode != "contour":
                    raise SoftplotError("the contour height is set in contour mode")
                pl.set_mode("contour", _num(msg, "height"))
                c = pl.current
                pl.cycle(c.X, c.Y)
            elif op == "drive":
                pl.drive_to(_num(msg, "X"), _num(msg, "Y"), _num(msg, "Z"))
            elif op in ("record", "begin", "vertex", "end", "undo"):
                feats = True
                if pl.height != self.journaled_height:
                    self.session.set_mode(pl.mode, pl.height)
                    self.journaled_height = pl.height
                if op == "record":
                    pl.record_point(_text(msg, "code"))
                elif op == "begin":
                    kind = msg.get("kind")
                    pl.begin(_text(msg, "code"), None if kind is None else _text(msg, "kind"))
                elif op == "vertex":
                    pl.vertex()
                elif op == "end":
                    pl.end(close=bool(msg.get("close", False)))
                elif pl._open is not None and pl._open[2]:  # undo the last vertex
                    pl._open[2].pop()
                    pl._open[3].pop()
            elif op == "client":
                z = msg.get("zoom")
                self.client = {"zoom": float(z) if isinstance(z, (int, float)) else None,
                               "view": msg.get("view") if msg.get("view") in VIEWS else None,
                               "frames": int(msg.get("frames") or 0)}
                return {"type": "ok", "seq": msg.get("seq")}
            elif op in ("measure", "unmeasure", "refine", "relor"):
                return self._measure_op(op, msg)
            elif op == "state":
                pass
            elif op == "features":
                feats = True
            else:
                raise SoftplotError(f"unknown op {op!r}")
            out = {"type": "state", "seq": msg.get("seq"), "state": self.state()}
            if feats:
                out["features"] = self.feature_pixels()
            if op == "features":
                out["measure"] = self.measure.as_dict()
            return out

    # ------------------------------------------------------------------ measurement
    def _measure_op(self, op: str, msg: dict) -> dict:
        out = {"type": "state", "seq": msg.get("seq"), "state": self.state()}
        m = self.measure
        if op == "measure":
            side = _text(msg, "side")
            name = _text(msg, "name")
            m.set(side, name, _num(msg, "x"), _num(msg, "y"))
            x, y = m.points[side][name]
            out["note"] = f"{side} {name}: {x:.2f}, {y:.2f} px -> {m.path(side).name}"
        elif op == "unmeasure":
            m.delete(_text(msg, "side"), _text(msg, "name"))
        elif op == "refine":
            out["proposal"] = self.refine(_text(msg, "name"))
            p = out["proposal"]
            out["note"] = (f"right {p['name']}: proposed {p['x']:.2f}, {p['y']:.2f} px (moved "
                           f"{p['shift'][0]:+.2f}, {p['shift'][1]:+.2f}; sigma {p['sigma']:.3f} "
                           f"px, ncc {p['ncc']:.2f}): accept it to keep it")
        else:
            out["relor"] = r = self.relor()
            worst = max(r["points"], key=lambda q: abs(q["py"]))
            out["note"] = (f"relative orientation of {len(r['points'])} points: sigma0 "
                           f"{r['sigma0'] * 1000:.1f} um, largest y-parallax {worst['name']} "
                           f"{worst['py'] * 1000:+.1f} um")
        out["measure"] = m.as_dict()
        return out

    def refine(self, name: str) -> dict:
        """Offer a sub-pixel right position for point ``name`` (measured in both scans) by
        least-squares matching of its left patch (:func:`softplot.ui.measure.refine_right`)."""
        from softplot.ui.measure import refine_right

        pts = self.measure.points
        if name not in pts["left"] or name not in pts["right"]:
            raise SoftplotError(f"point {name!r}: measure it in both scans first")
        p = refine_right(self.pyramids["left"].levels[0], self.pyramids["right"].levels[0],
                         pts["left"][name], pts["right"][name])
        p["name"] = name
        return p

    def relor(self) -> dict:
        """Relative orientation (dependent pair) of the points measured in both scans, their
        pixels reduced to photo mm by each scan's film correction; per-point y-parallax."""
        from softplot.orientation.relative import relative_orientation

        pts = self.measure.points
        names = [n for n in pts["left"] if n in pts["right"]]
        if len(names) < 5:
            raise SoftplotError(f"relative orientation needs >= 5 points measured in both "
                                f"scans, found {len(names)}")
        xy = {s: self.maps[s].pixel_to_photo(np.array([pts[s][n] for n in names]))
              for s in SIDES}
        m = self.plotter.model
        bx = float(np.linalg.norm(np.asarray(m.right.X0) - np.asarray(m.left.X0))) or 1.0
        r = relative_orientation(xy["left"], xy["right"], m.left.c, bx=bx, names=names)
        return {"sigma0": float(r.sigma0), "redundancy": int(r.redundancy),
                "angles_rad": [float(a) for a in r.angles2],
                "points": [{"name": n, "py": float(p)} for n, p in zip(names, r.py, strict=True)]}

    def close(self) -> None:
        """Save the motor state in the journal and close it (and the motors)."""
        if self.closed:
            return
        self.closed = True
        with self.lock:
            try:
                self.session.save_motors(self.motors)
            finally:
                self.session.close()
                try:
                    self.motors.close()
                except Exception:  # noqa: BLE001 - closing must not hide the journal's state
                    pass
