"""The plotter loop: operator input in, DX/DY commands out, features recorded.

As on the STEREOBIT/20 the operator moves the main carriage (X, Y) over the *right* plate and,
in single-point mode, turns the x-parallax handwheel; every cycle the computer works out the
left-plate position that puts the floating mark on the model and commands the secondary
carriage (DX, DY) of the left plate through the :class:`~softplot.motors.base.Motors`
interface. All carriage values are **instrument (film) mm**: the right film point under the
mark is ``(X, Y)``, the left one ``(X + BX + DX, Y + BY + DY)`` where ``(BX, BY)`` is the
fixed offset of the left plate holder (``left_offset``, default 0: the secondary carriage's
travel is small, so an aerial pair's mean x-parallax belongs in BX). Each photo's film correction
(:attr:`OrientedPhoto.to_photo`) maps them to photo mm for the stereo model.

Modes (:data:`MODES`):

``single``  handwheel ``px`` (= DX, the x-parallax) given; DY is computed so that the
            y-parallax vanishes (STEREOBIT a); object point from the two rays.
``contour`` the mark is held on Z = ``height``: DX and DY both computed (STEREOBIT b).
``free``    DX, DY are the operator's (handwheels); object point and residual y-parallax.
``drive-to`` :meth:`Plotter.drive_to` puts the mark on a given object point.

The computed object point is exact (to rounding) for the *computed* left position; the
motors then place the left plate on their step grid (0.01 mm by default, finer on screen).
With identity film corrections a cycle is pure-Python scalar arithmetic
(:class:`~softplot.stereo.model.FastStereo`); with corrections, two small numpy calls.

Recording: :meth:`Plotter.record_point` (spot height), :meth:`Plotter.begin` /
:meth:`Plotter.vertex` / :meth:`Plotter.end` (3D lines and contours), each with a feature
code. Finished features go to ``on_feature`` (the session journal fsyncs them).

What is recorded is what was measured. A spot height is the model point under the mark, so
it is refused where the mark was placed in contour mode (there it is held at Z = height
whatever the terrain; a contour vertex is on the contour height by definition). A point or
vertex is recorded only when the mark stands on it: the secondary carriage reached its
target (the motors are waited for, then their position compared with the target, to half a
step) and the point is in the model (the rays meet in front of both cameras; with scans, the
mark is on both scans). Otherwise :class:`NotReached` says why in one line and nothing is
recorded.

A motor fault (:class:`~softplot.motors.base.MotorFault`) stops the motors, is reported to
``on_fault`` and raised as :class:`PlotterHalted` with a one-line message; the recorded
features are untouched. :meth:`Plotter.recover` clears the halt.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from softplot.errors import SoftplotError
from softplot.export.features import Feature
from softplot.motors.base import MotorFault, MotorLimitError, Motors
from softplot.stereo.model import StereoModel

__all__ = ["Plotter", "Cycle", "PlotterHalted", "NotReached", "MODES"]

MODES = ("single", "contour", "free", "drive-to")


class PlotterHalted(SoftplotError):
    """A motor fault stopped the plotter; the session is kept."""


class NotReached(SoftplotError):
    """The mark is not on a measurable point (carriage not at its target, outside the travel
    or the model): nothing was recorded."""


class Cycle:
    """The state of the floating mark after one cycle (instrument mm, photo mm, object)."""

    __slots__ = ("X", "Y", "DX", "DY", "x1", "y1", "x2", "y2", "XYZ", "py", "in_travel", "mode")

    def __init__(self, X, Y, DX, DY, x1, y1, x2, y2, XYZ, py, in_travel=True, mode="single"):
        self.X, self.Y, self.DX, self.DY = X, Y, DX, DY
        self.x1, self.y1, self.x2, self.y2 = x1, y1, x2, y2
        self.XYZ = XYZ
        self.py = py
        self.in_travel = in_travel
        self.mode = mode  # how the mark was placed: single, contour, free or drive-to

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__slots__}


class Plotter:
    """Real-time restitution loop over a stereo model and a motor set.

    Parameters
    ----------
    model : StereoModel
        Oriented left (1) and right (2) photos with their film corrections.
    motors : Motors
        Secondary carriage of the left plate (virtual or instrument).
    mode : {"single", "contour", "free"}
    height : float, optional
        Contour height Qc (object units), required in contour mode.
    on_feature : callable, optional
        Called with every finished :class:`~softplot.export.features.Feature`.
    on_fault : callable, optional
        Called with the fault message when the motors fail.
    left_offset : (float, float)
        Fixed offset (BX, BY) of the left plate, instrument mm: left film =
        main carriage + offset + (DX, DY).
    reach_timeout : float, optional
        Seconds a recording waits for the secondary carriage to reach its target (None: no
        limit); past it the point is not recorded (:class:`NotReached`).
    """

    def __init__(
        self,
        model: StereoModel,
        motors: Motors,
        *,
        mode: str = "single",
        height: float | None = None,
        on_feature: Callable[[Feature], None] | None = None,
        on_fault: Callable[[str], None] | None = None,
        left_offset: tuple[float, float] = (0.0, 0.0),
        reach_timeout: float | None = 10.0,
    ):
        self.model = model
        self.reach_timeout = reach_timeout
        self.fast = model.fast()
        self.motors = motors
        self.on_feature = on_feature
        self.on_fault = on_fault
        self.identity = model.left.to_photo is None and model.right.to_photo is None
        self.left_offset = (float(left_offset[0]), float(left_offset[1]))
        self.mode = "single"
        self.height = None
        self.set_mode(mode, height)
        self.current: Cycle | None = None
        self.features: list[Feature] = []
        self._open: tuple[str, str, list, list] | None = None
        self.halted: str | None = None

    # ----------------------------------------------------------- mode
    def set_mode(self, mode: str, height: float | None = None) -> None:
        """Switch restitution mode (contour needs ``height``)."""
        if mode not in MODES or mode == "drive-to":
            raise SoftplotError(f"plotter mode must be single, contour or free, got {mode!r}")
        if mode == "contour":
            if height is None or not np.isfinite(height):
                raise SoftplotError("contour mode needs a finite contour height")
            self.height = float(height)
        self.mode = mode

    # ----------------------------------------------------------- the cycle
    def cycle(self, X: float, Y: float, px: float | None = None) -> Cycle:
        """One plotter cycle.

        Parameters
        ----------
        X, Y : float
            Main carriage (right film point under the mark), instrument mm.
        px : float, optional
            x-parallax handwheel = DX, instrument mm (single mode; default: keep DX).

        Returns
        -------
        Cycle
            The computed mark: carriages, photo points, object point, y-parallax.

        Raises
        ------
        PlotterHalted
            On a motor fault (the motors are stopped first).
        """
        if self.halted is not None:
            raise PlotterHalted(self.halted)
        mot = self.motors
        mot.set_main(X, Y)
        mode = self.mode
        bx, by = self.left_offset
        Xl, Yl = X + bx, Y + by  # left film under the mark with DX = DY = 0
        if mode == "free":
            DX, DY = mot.position()
            r = self.model.free(self._to_photo(0, Xl + DX, Yl + DY), self._to_photo(1, X, Y))
            x1, y1 = r.xy1[0]
            x2, y2 = r.xy2[0]
            cyc = Cycle(X, Y, DX, DY, x1, y1, x2, y2, tuple(r.XYZ[0]), float(r.py[0]),
                        mode="free")
            self.current = cyc
            return cyc
        if self.identity:
            f = self.fast
            if mode == "single":
                DX = mot.target()[0] if px is None else px
                x1 = Xl + DX
                y1, XX, YY, ZZ = f.single(X, Y, x1)
                DY = y1 - Yl
            else:
                ZZ = self.height
                x1, y1, XX, YY = f.contour(X, Y, ZZ)
                DX, DY = x1 - Xl, y1 - Yl
            x2, y2 = X, Y
        else:
            x2, y2 = self._to_photo(1, X, Y)
            if mode == "single":
                DX = mot.target()[0] if px is None else px
                x1, y1, y1f, XX, YY, ZZ = self._single_film(Xl + DX, Yl + mot.target()[1], x2, y2)
                DY = y1f - Yl
            else:
                ZZ = self.height
                x1, y1, XX, YY = self.fast.contour(x2, y2, ZZ)
                fx, fy = self.model.left.photo_to_film([[x1, y1]])[0]
                DX, DY = fx - Xl, fy - Yl
        in_travel = True
        try:
            mot.move_to(DX, DY, wait=False)
        except MotorLimitError:
            in_travel = False
        except MotorFault as exc:
            self._fault(exc)
        cyc = Cycle(X, Y, DX, DY, x1, y1, x2, y2, (XX, YY, ZZ), 0.0, in_travel, mode)
        self.current = cyc
        return cyc

    def _to_photo(self, k: int, x: float, y: float):
        photo = self.model.left if k == 0 else self.model.right
        if photo.to_photo is None:
            return (x, y)
        p = photo.film_to_photo([[x, y]])[0]
        return (float(p[0]), float(p[1]))

    def _single_film(self, x1f, y1f, x2, y2, h=1e-3):
        """Left film y that puts the corrected left point on the epipolar line.

        Newton on ``g(y) = y_photo - y_epipolar(x_photo)`` with the slope taken once by a
        finite difference (chord method: film corrections are smooth and near-identity, so
        an affine one converges in one step); stops when ``|g| < 1e-12`` photo mm.
        """
        left = self.model.left
        single = self.fast.single
        p = left.film_to_photo([[x1f, y1f], [x1f, y1f + h]])
        g0 = p[0, 1] - single(x2, y2, p[0, 0])[0]
        g1 = p[1, 1] - single(x2, y2, p[1, 0])[0]
        slope = (g1 - g0) / h
        g = g0
        px, py_ = p[0, 0], p[0, 1]
        for _ in range(8):
            if abs(g) < 1e-12:
                break
            y1f -= g / slope
            q = left.film_to_photo([[x1f, y1f]])
            px, py_ = q[0, 0], q[0, 1]
            g = py_ - single(x2, y2, px)[0]
        x1 = float(px)
        y1, XX, YY, ZZ = single(x2, y2, x1)
        return x1, y1, y1f, XX, YY, ZZ

    def drive_to(self, X: float, Y: float, Z: float) -> Cycle:
        """Put the floating mark on object point (X, Y, Z).

        The main carriage target (right film) is set with :meth:`Motors.set_main` (on
        screen this moves the view; on an instrument the operator follows it) and DX, DY
        are commanded.
        """
        if self.halted is not None:
            raise PlotterHalted(self.halted)
        r = self.model.drive_to([[X, Y, Z]])
        (x1, y1), (x2, y2) = r.xy1[0], r.xy2[0]
        fx2, fy2 = self.model.right.photo_to_film([[x2, y2]])[0]
        fx1, fy1 = self.model.left.photo_to_film([[x1, y1]])[0]
        DX, DY = fx1 - fx2 - self.left_offset[0], fy1 - fy2 - self.left_offset[1]
        self.motors.set_main(fx2, fy2)
        in_travel = True
        try:
            self.motors.move_to(DX, DY, wait=False)
        except MotorLimitError:
            in_travel = False
        except MotorFault as exc:
            self._fault(exc)
        cyc = Cycle(fx2, fy2, DX, DY, x1, y1, x2, y2, (X, Y, Z), float(r.py[0]), in_travel,
                    "drive-to")
        self.current = cyc
        return cyc

    # ----------------------------------------------------------- faults
    def _fault(self, exc: MotorFault):
        msg = f"motor fault: {exc}"
        try:
            self.motors.stop()
            msg += "; motors stopped"
        except Exception as stop_exc:  # noqa: BLE001 - report, never mask the first fault
            same = str(stop_exc) == str(exc)  # each cause named once
            msg += "; the motors could not be stopped" if same else (
                f"; stopping failed too ({stop_exc})"
            )
        msg += f"; session kept ({len(self.features)} features recorded)"
        self.halted = msg
        if self.on_fault is not None:
            self.on_fault(msg)
        raise PlotterHalted(msg) from exc

    def recover(self) -> None:
        """Clear a halt after the motors were fixed (e.g. ``GrblMotors.recover``)."""
        self.halted = None

    # ----------------------------------------------------------- recording
    def _attrs(self, cyc: Cycle, extra: dict) -> dict:
        a = {"mode": self.mode, "x1": cyc.x1, "y1": cyc.y1, "x2": cyc.x2, "y2": cyc.y2}
        a.update(extra)
        return a

    def _emit(self, feat: Feature) -> Feature:
        self.features.append(feat)
        if self.on_feature is not None:
            self.on_feature(feat)
        return feat

    def record_point(self, code: str, **attributes) -> Feature:
        """Record the current mark as a spot height with ``code``.

        Raises
        ------
        SoftplotError
            When the mark was placed in contour mode (held at the contour height, not on the
            terrain; a mark driven to an object point, :meth:`drive_to`, is that point).
        NotReached
            The carriage did not reach the mark's target, or the mark is outside the model.
        """
        cyc = self._need_current()
        if cyc.mode == "contour":
            raise SoftplotError(
                f"a spot height is not measured in contour mode (the mark is held at Z = "
                f"{cyc.XYZ[2]:g} whatever the terrain): switch to single or free mode"
            )
        self.check_reached(cyc)
        return self._emit(Feature(code, "point", [cyc.XYZ], self._attrs(cyc, attributes)))

    def begin(self, code: str, kind: str | None = None, **attributes) -> None:
        """Start a line (``kind="line"``) or, in contour mode by default, a contour."""
        kind = kind or ("contour" if self.mode == "contour" else "line")
        if kind not in ("line", "contour"):
            raise SoftplotError(f"begin: kind must be line or contour, got {kind!r}")
        if kind == "contour" and self.mode != "contour":
            raise SoftplotError("a contour is traced in contour mode")
        Feature(code, "point", [[0.0, 0.0, 0.0]])  # validates the code now
        self._open = (code, kind, [], [])
        self._open_attrs = dict(attributes)
        if kind == "contour":
            self._open_attrs["height"] = self.height

    def vertex(self) -> int:
        """Add the current mark to the open line; returns the number of vertices."""
        if self._open is None:
            raise SoftplotError("vertex: no line open (call begin first)")
        cyc = self._need_current()
        self.check_reached(cyc)
        self._open[2].append(cyc.XYZ)
        self._open[3].append((cyc.x1, cyc.y1, cyc.x2, cyc.y2))
        return len(self._open[2])

    def end(self, *, close: bool = False) -> Feature | None:
        """Finish the open line (``close`` repeats the first vertex); None if < 2 vertices."""
        if self._open is None:
            raise SoftplotError("end: no line open")
        code, kind, verts, img = self._open
        self._open = None
        if len(verts) < 2:
            return None
        if close:
            verts = verts + [verts[0]]
        attrs = dict(self._open_attrs)
        attrs["image_points"] = [list(map(float, p)) for p in img]
        return self._emit(Feature(code, kind, verts, attrs))

    def check_reached(self, cyc: Cycle | None = None) -> None:
        """Raise :class:`NotReached` unless the mark of ``cyc`` (default: the current one) is
        a measurable point: in the travel, in the model, and the carriage at its target
        (waited for up to :attr:`reach_timeout` s; a motor fault halts as in :meth:`cycle`)."""
        cyc = self._need_current() if cyc is None else cyc
        if not cyc.in_travel:
            raise NotReached(
                f"the secondary carriage cannot reach DX = {cyc.DX:.3f}, DY = {cyc.DY:.3f} mm "
                "(outside its travel)"
            )
        problem = self._model_problem(cyc)
        if problem is not None:
            raise NotReached(problem)
        mot = self.motors
        try:
            settled = mot.wait(self.reach_timeout)
        except MotorFault as exc:
            self._fault(exc)
        if not settled:
            raise NotReached(
                f"the secondary carriage did not reach DX = {cyc.DX:.3f}, DY = {cyc.DY:.3f} mm "
                f"within {self.reach_timeout:g} s"
            )
        (tx, ty), (px, py), (rx, ry) = mot.target(), mot.position(), mot.resolution
        if cyc.mode != "free" and (abs(tx - cyc.DX) > 0.5 * rx + 1e-12
                                    or abs(ty - cyc.DY) > 0.5 * ry + 1e-12):
            raise NotReached(
                f"the secondary carriage was not sent to DX = {cyc.DX:.3f}, DY = {cyc.DY:.3f} "
                f"mm (its target is {tx:.3f}, {ty:.3f})"
            )
        if abs(px - tx) > 0.5 * rx + 1e-12 or abs(py - ty) > 0.5 * ry + 1e-12:
            raise NotReached(
                f"the secondary carriage stands at DX = {px:.3f}, DY = {py:.3f} mm, not at its "
                f"target {tx:.3f}, {ty:.3f}"
            )

    def _model_problem(self, cyc: Cycle) -> str | None:
        """Why the mark of ``cyc`` is not a model point (None if it is): no finite
        intersection, behind a camera, or off a scan."""
        XYZ = np.asarray(cyc.XYZ, dtype=float)
        if not np.all(np.isfinite(XYZ)):
            return "no model point under the mark (the rays do not meet)"
        bx, by = self.left_offset
        films = ((cyc.X + bx + cyc.DX, cyc.Y + by + cyc.DY), (cyc.X, cyc.Y))
        for side, photo, xy, film in zip(
            ("right", "left"), (self.model.right, self.model.left),
            ((cyc.x2, cyc.y2), (cyc.x1, cyc.y1)), films[::-1], strict=True,
        ):
            if float(photo.ray([xy])[0] @ (XYZ - photo.X0)) <= 0:
                return f"outside the model: the point is behind the {side} camera"
            frame = getattr(photo.to_photo, "frame", None)
            if frame is not None:
                u, v = frame.to_pixel(np.array([film], dtype=float))[0]
                if not (-0.5 <= u <= frame.width - 0.5 and -0.5 <= v <= frame.height - 0.5):
                    return (
                        f"outside the model: the mark is off the {side} scan (pixel "
                        f"{u:.0f}, {v:.0f} of {frame.width} x {frame.height})"
                    )
        return None

    def _need_current(self) -> Cycle:
        if self.current is None:
            raise SoftplotError("no floating-mark position yet: run a cycle first")
        return self.current
