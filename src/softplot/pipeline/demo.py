"""The end-to-end demo: a synthetic Rollei 6006 stereo pair from scans to contours.

:func:`run_demo` renders, on the fly and deterministically, two scans of a Rollei 6006 stereo
pair over a synthetic terrain (a Gaussian hill whose contours are exact circles, see
:mod:`softplot.synthetic.stereo`) and runs the whole chain on them:

1. **render** each photo with :func:`softplot.synthetic.render_scan`; the scene is a callable
   ``f(film x mm, film y mm)``: film mm -> photo mm (the camera's interior orientation) ->
   ray (the true exterior orientation) -> intersection with the terrain (Newton) -> a ground
   texture with white signalised targets on the control and check points. The film is then
   deformed (shrinkage + smooth field) and scanned (rotation, offset) by the renderer, which
   keeps the exact film mm <-> pixel mapping (:class:`softplot.synthetic.TruthMapping`);
2. **detect** the reseau crosses of both scans (:func:`softplot.marks.detect`);
3. **film correction** (mesh) and interior orientation
   (:class:`softplot.correction.FilmCorrection`);
4. **relative orientation** (coplanarity) on tie, control and check points and **absolute
   orientation** (7-parameter similarity) on the control points. The image coordinates of these
   points are their *exact truth pixel positions*: they stand in for the operator's
   measurements (a softcopy operator points them to a fraction of a pixel);
5. **contour restitution** at a fixed interval through :class:`softplot.stereo.Plotter` in
   contour mode driving :class:`softplot.motors.VirtualMotors`. The operator is emulated: the
   main carriage follows the *true* contour line in planimetry (right scan);
6. **export**: DXF, GeoJSON and a self-contained HTML report.

Accuracy against truth (all in :class:`DemoResult`):

* detection RMS, px: detected minus true pixel position of every measured cross;
* film correction RMS, um: corrected film mm of check points spread over the format minus
  their true film mm (the points' true pixel positions come from the truth mapping);
* orientation sigma0 (relative: a posteriori / a priori, and in photo um; absolute);
* check-point RMS, object m (X, Y, Z) after absolute orientation;
* contour height error, m: every recorded contour vertex is seen through the TRUE orientation
  at the image points the plotter commanded (right: main carriage, left: the motors' actual
  plate position on their step grid); the two true rays are intersected and the true terrain
  height under that point minus the contour height H is the error (also reported: the height
  of the true ray intersection minus H, and the plan error of the vertex).

Coordinate systems: pixel (px, x right, y down, origin at the centre of the top-left pixel);
film mm (certificate, undeformed); photo mm (reduced to the principal point, distortion-free);
**instrument mm** of the plotter = scan mm of each scan: ``x = (col - (W-1)/2) * p``,
``y = ((H-1)/2 - row) * p`` with ``p = 25.4 / dpi`` (a softcopy plotter's carriages move over
the scans); object m (X east, Y north, Z up).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from softplot.camera import load_camera
from softplot.errors import SoftplotError

__all__ = ["DemoConfig", "DemoResult", "run_demo", "prepare_out_dir", "MARKER"]

#: file that marks a folder as written by ``softplot demo`` (safe to overwrite)
MARKER = ".softplot-demo"
CAMERA = "rollei-6006"
_HALF = 32.0  # film mm half side of the scene's ground raster
_PITCH = 0.2  # film mm between its nodes


@dataclass
class DemoConfig:
    """Size and content of the demo (the defaults are the full demo).

    Attributes
    ----------
    dpi : float
        Scan resolution (600-1000 sensible; lower is faster).
    interval : float
        Contour interval, object m.
    vertices : int
        Vertices per contour (the operator's pointings along the true contour).
    tie_grid : int
        Tie points on a ``tie_grid x tie_grid`` grid over the overlap.
    n_control, n_check : int
        Control points (absolute orientation) and independent check points.
    seed : int
        Everything random (orientation perturbations, point positions, film deformation).
    motor_resolution_mm : float
        Step of the virtual motors, instrument mm (a screen plotter's sub-pixel step).
    """

    dpi: float = 800.0
    interval: float = 10.0
    vertices: int = 72
    tie_grid: int = 5
    n_control: int = 6
    n_check: int = 8
    seed: int = 6006
    motor_resolution_mm: float = 0.0005


@dataclass
class DemoResult:
    """Accuracy reached against truth and where the outputs are.

    Attributes
    ----------
    detection_rms_px : float
        RMS (radial) of detected minus true cross positions over both scans, px.
    detection_measured : list of int
        Crosses measured in the left and right scan.
    correction_rms_um : float
        RMS (radial) of corrected minus true film coordinates at check points spread over
        the whole format, um (both scans).
    correction_rms_reseau_um : float
        The same over the check points inside the reseau (interpolation, not extrapolation).
    relative_sigma0 : float
        Relative orientation a posteriori sigma0 / a priori (2 um).
    relative_sigma0_um : float
        The a posteriori sigma0 in photo micrometres.
    absolute_sigma0 : float
        Absolute orientation sigma0 (unit weights: object m).
    check_rms_m : list of float
        Check-point RMS in X, Y, Z, object m.
    contour_height_rms_m, contour_height_max_m : float
        True terrain height under each recorded vertex (seen through the true orientation)
        minus the contour height, RMS and max |.|, m.
    contour_mark_height_rms_m : float
        Height of the true ray intersection minus H, RMS, m.
    contour_plan_rms_m : float
        Plan distance of each recorded vertex from the true contour point followed, RMS, m.
    contours, vertices : int
        Contour lines and vertices recorded.
    seconds : float
    outputs : dict
        Name -> path of every file written.
    """

    detection_rms_px: float = float("nan")
    detection_measured: list = field(default_factory=list)
    correction_rms_um: float = float("nan")
    correction_rms_reseau_um: float = float("nan")
    relative_sigma0: float = float("nan")
    relative_sigma0_um: float = float("nan")
    absolute_sigma0: float = float("nan")
    check_rms_m: list = field(default_factory=list)
    contour_height_rms_m: float = float("nan")
    contour_height_max_m: float = float("nan")
    contour_mark_height_rms_m: float = float("nan")
    contour_plan_rms_m: float = float("nan")
    contours: int = 0
    vertices: int = 0
    scale: float = float("nan")
    seconds: float = 0.0
    outputs: dict = field(default_factory=dict)

    def summary(self) -> str:
        """The accuracy lines the CLI prints."""
        cx, cy, cz = self.check_rms_m
        return "\n".join(
            [
                f"  detection RMS            {self.detection_rms_px:.4f} px "
                f"({'/'.join(map(str, self.detection_measured))} crosses measured)",
                f"  film correction RMS      {self.correction_rms_um:.2f} um over the format "
                f"({self.correction_rms_reseau_um:.2f} um inside the reseau)",
                f"  relative orientation     sigma0 {self.relative_sigma0:.3f} "
                f"({self.relative_sigma0_um:.3f} um in the photo)",
                f"  absolute orientation     sigma0 {self.absolute_sigma0:.4f} m",
                f"  check points RMS         X {cx:.3f} m, Y {cy:.3f} m, Z {cz:.3f} m "
                f"(photo scale 1:{self.scale:.0f})",
                f"  contour height error     RMS {self.contour_height_rms_m:.3f} m, "
                f"max {self.contour_height_max_m:.3f} m over {self.vertices} vertices of "
                f"{self.contours} contours (floating mark: RMS "
                f"{self.contour_mark_height_rms_m:.3f} m; plan RMS "
                f"{self.contour_plan_rms_m:.3f} m)",
            ]
        )

    def to_json(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- truth


class _Terrain:
    """Ground texture of the synthetic terrain seen by one photo (picklable callable).

    ``__call__(x_mm, y_mm)`` takes undeformed film mm arrays and returns the reflectance in
    [0, 1]: film -> photo (interior orientation) -> ray -> terrain point (Newton on the
    height along the ray) -> texture(X, Y) with white targets of radius ``target_m``.
    """

    def __init__(self, pair, k: int, interior, targets: np.ndarray, target_m: float, seed: int):
        self.pair, self.k, self.io = pair, k, interior
        self.targets = np.asarray(targets, float)[:, :2]
        self.target_m = float(target_m)
        rng = np.random.default_rng(seed + 17)
        n = 10
        ang = rng.uniform(0, np.pi, n)
        lam = np.geomspace(4.0, 60.0, n)
        self.kx = np.cos(ang) * 2 * np.pi / lam
        self.ky = np.sin(ang) * 2 * np.pi / lam
        self.ph = rng.uniform(0, 2 * np.pi, n)
        self.amp = (lam / lam.max()) ** 0.5
        self.amp *= 0.3 / self.amp.sum()
        self._grid = None

    def ground(self, xy_film: np.ndarray) -> np.ndarray:
        """Film mm (N, 2) -> terrain points (N, 3), object m."""
        p = self.pair
        photo = self.io.film_to_photo(xy_film)
        v = np.column_stack([photo, np.full(len(photo), -p.c[self.k])])
        r = v @ p.M(self.k)  # object-frame ray directions
        C = p.X0[self.k]
        Xc, Yc, Z0, A, s = p.hill
        t = (Z0 + 0.5 * A - C[2]) / r[:, 2]
        for _ in range(8):
            X = C[0] + t * r[:, 0]
            Y = C[1] + t * r[:, 1]
            e = A * np.exp(-((X - Xc) ** 2 + (Y - Yc) ** 2) / (2 * s * s))
            Z = Z0 + e
            dzdX = -(X - Xc) / (s * s) * e
            dzdY = -(Y - Yc) / (s * s) * e
            h = C[2] + t * r[:, 2] - Z
            dh = r[:, 2] - dzdX * r[:, 0] - dzdY * r[:, 1]
            t = t - h / dh
        return C + t[:, None] * r

    def texture(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Reflectance of the ground at X, Y (object m, float32 arrays), in [0, 1]."""
        f = np.full(X.shape, 0.5, np.float32)
        for kx, ky, ph, a in zip(self.kx, self.ky, self.ph, self.amp, strict=True):
            f += np.float32(a) * np.sin(np.float32(kx) * X + np.float32(ky) * Y + np.float32(ph))
        r = np.float32(self.target_m)
        for tx, ty in self.targets:
            dx, dy = X - np.float32(tx), Y - np.float32(ty)
            f[dx * dx + dy * dy < r * r] = 0.95
        return f

    def _rasters(self):
        """Ground X, Y (object m) on a film grid of pitch ``_PITCH`` mm: cached, float32."""
        if self._grid is None:
            n = int(round(2 * _HALF / _PITCH)) + 1
            g = np.linspace(-_HALF, _HALF, n)
            fx, fy = np.meshgrid(g, g)
            P = self.ground(np.column_stack([fx.ravel(), fy.ravel()]))
            self._grid = (P[:, 0].reshape(n, n).astype(np.float32),
                          P[:, 1].reshape(n, n).astype(np.float32))
        return self._grid

    def __call__(self, x_mm, y_mm):
        import cv2

        x = np.asarray(x_mm, np.float32)
        shape = x.shape
        flat = x.ravel()
        n = flat.size
        w = 1024
        pad = (-n) % w
        mx = ((np.r_[flat, np.zeros(pad, np.float32)] + _HALF) / _PITCH).reshape(-1, w)
        yy = np.asarray(y_mm, np.float32).ravel()
        my = ((np.r_[yy, np.zeros(pad, np.float32)] + _HALF) / _PITCH).reshape(-1, w)
        my = my.astype(np.float32)
        GX, GY = self._rasters()
        X = cv2.remap(GX, mx.astype(np.float32), my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
        Y = cv2.remap(GY, mx.astype(np.float32), my, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
        return self.texture(X.ravel()[:n], Y.ravel()[:n]).reshape(shape)


def make_pair(camera, seed: int):
    """A Rollei 6006 stereo pair (60 % overlap, 1:7500) over a Gaussian hill: the truth.

    Returns a :class:`softplot.synthetic.stereo.SyntheticPair` (photo mm of the camera's
    collinearity frame, principal point 0 in photo coordinates; no film deformation there:
    the renderer deforms the film).
    """
    from softplot.synthetic.stereo import SyntheticPair

    rng = np.random.default_rng(seed)
    c = float(camera.c)
    half = min(camera.format_mm) / 2
    Z0, H = 200.0, 300.0
    width = 2 * half / c * H
    base = 0.4 * width
    X0 = np.array([[0.0, 0.0, Z0 + H], [base, 0.0, Z0 + H]])
    X0[:, :2] += rng.uniform(-2, 2, (2, 2))
    X0[:, 2] += rng.uniform(-3, 3, 2)
    angles = np.deg2rad(rng.uniform(-1.5, 1.5, (2, 3)))
    D = np.zeros((2, 2, 3))
    D[:, :, :2] = np.eye(2)
    hill = (base / 2, 0.0, Z0, 60.0, 0.12 * width)
    zero = np.zeros(2)
    return SyntheticPair(X0, angles, np.array([c, c]), zero, zero, hill, D, half)


def _points(pair, cfg: DemoConfig):
    """Tie, control and check points on the terrain in the overlap, object m."""
    rng = np.random.default_rng(cfg.seed + 1)
    Xc, Yc = pair.hill[:2]
    half = 0.42 * (pair.X0[1, 0] - pair.X0[0, 0]) / 0.4 * 0.6  # inside the overlap
    g = np.linspace(-half, half, cfg.tie_grid)
    TX, TY = np.meshgrid(Xc + g, Yc + 1.3 * g)
    tie = np.c_[TX.ravel(), TY.ravel()]
    # control around the rim of the overlap, check points inside and on the rim
    a = np.linspace(0, 2 * np.pi, cfg.n_control, endpoint=False) + 0.3
    ctrl = np.c_[Xc + 0.95 * half * np.cos(a), Yc + 1.25 * half * np.sin(a)]
    chk = np.c_[Xc + rng.uniform(-0.85, 0.85, cfg.n_check) * half,
                Yc + rng.uniform(-1.1, 1.1, cfg.n_check) * half]
    out = {}
    for name, xy in (("tie", tie), ("control", ctrl), ("check", chk)):
        out[name] = np.c_[xy, pair.terrain(xy[:, 0], xy[:, 1])]
    return out


# ----------------------------------------------------------------------------- output folder


def prepare_out_dir(out: str | Path) -> Path:
    """Make ``out`` ready for the demo's files without touching anyone else's.

    A missing or empty folder, or one marked by an earlier demo (:data:`MARKER`), is used
    as it is; an existing folder with other content gets a fresh sub-folder
    ``softplot-demo[-N]`` (the user's files are never overwritten); a file is an error.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SoftplotError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).exists():
        n = 0
        while True:
            sub = out / ("softplot-demo" if n == 0 else f"softplot-demo-{n}")
            if not sub.exists() or (sub / MARKER).exists():
                out = sub
                break
            n += 1
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by softplot demo; its files may be overwritten\n",
                              encoding="utf-8")
    return out


# ----------------------------------------------------------------------------- the chain


def _rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def run_demo(out: str | Path | None, config: DemoConfig | None = None,
             progress: bool = True, write_scans: bool = True) -> DemoResult:
    """Run the whole demo chain; write its outputs into ``out`` (None: write nothing).

    Parameters
    ----------
    out : str or Path or None
        Output folder (see :func:`prepare_out_dir`); None runs the chain without files.
    config : DemoConfig, optional
        Size of the demo (the test suite runs a reduced one).
    progress : bool
        tqdm progress bars on stderr.
    write_scans : bool
        Also write the two scans (TIFF) and their detections (JSON).

    Returns
    -------
    DemoResult
    """
    from tqdm import tqdm

    from softplot.correction import FilmCorrection, ScanFrame, ScanPhotoMap
    from softplot.geometry.rotation import angles_from_matrix, rotation_matrix
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.motors.base import AxisConfig
    from softplot.motors.virtual import VirtualMotors
    from softplot.orientation import absolute_orientation, intersect_pair, relative_orientation
    from softplot.orientation.interior import InteriorOrientation
    from softplot.stereo.model import OrientedPhoto, StereoModel
    from softplot.stereo.plotter import Plotter
    from softplot.synthetic import ScanSpec, TruthMapping, render_scan

    cfg = config or DemoConfig()
    t_start = time.perf_counter()
    res = DemoResult()
    out_dir = prepare_out_dir(out) if out is not None else None
    cam = load_camera(CAMERA)
    io = InteriorOrientation(cam)
    pair = make_pair(cam, cfg.seed)
    pts = _points(pair, cfg)
    res.scale = float((pair.X0[0, 2] - pair.hill[2]) / cam.c * 1000.0)
    targets = np.vstack([pts["control"], pts["check"]])

    stages = ["render + detect + correct left", "render + detect + correct right",
              "orientation", "contours", "export"]
    bar = tqdm(total=len(stages), desc="demo", unit="stage", disable=not progress)

    # ---- 1-3: render, detect, correct each scan
    scans = []
    for k in range(2):
        bar.set_postfix_str(stages[k])
        spec = ScanSpec(
            dpi=cfg.dpi, scene=_Terrain(pair, k, io, targets, 1.2, cfg.seed),
            deform_um=12.0, shrink_ppm=150.0 + 100 * k, rotation_deg=(0.35, -0.5)[k],
            offset_px=((3.2, -2.1), (-4.4, 1.7))[k], noise_sigma=0.01, blur_sigma_px=0.8,
        )
        image, truth = render_scan(cam, spec, seed=cfg.seed + k)
        tm = TruthMapping.from_truth(truth)
        scan = Scan.from_array(image, dpi=cfg.dpi)
        det = detect(scan, cam)
        dj = det.to_json()
        dj["image"] = f"{('left', 'right')[k]}.tif"
        # detection accuracy: detected minus true pixel of every measured cross
        true_px = {m["name"]: (m["x"], m["y"]) for m in truth["marks"]}
        d = np.array([[m["x"] - true_px[m["name"]][0], m["y"] - true_px[m["name"]][1]]
                      for m in dj["marks"] if m.get("status") == "measured"
                      and m["name"] in true_px])
        fc = FilmCorrection.from_detection(cam, dj, "mesh")
        # film correction accuracy at check points over the whole format
        rng = np.random.default_rng(cfg.seed + 100 + k)
        hw, hh = (0.98 * v / 2 for v in cam.format_mm)
        film_true = np.c_[rng.uniform(-hw, hw, 400), rng.uniform(-hh, hh, 400)]
        film_est = fc.pixel_to(tm.film_to_pixel(film_true), to="film")[0]
        err_um = 1000.0 * (film_est - film_true)
        inside = np.all(np.abs(film_true) <= 25.0, axis=1)
        frame = ScanFrame.of_scan(image.shape[1], image.shape[0], cfg.dpi)
        scans.append(dict(image=image, truth=truth, tm=tm, det=dj, fc=fc, d=d, err_um=err_um,
                          inside=inside, frame=frame, film_true=film_true,
                          map=ScanPhotoMap(fc, frame)))
        bar.update(1)

    D = np.vstack([s["d"] for s in scans])
    res.detection_rms_px = _rms(np.hypot(D[:, 0], D[:, 1]))
    res.detection_measured = [len(s["d"]) for s in scans]
    E = np.vstack([s["err_um"] for s in scans])
    inside = np.concatenate([s["inside"] for s in scans])
    res.correction_rms_um = _rms(np.hypot(E[:, 0], E[:, 1]))
    res.correction_rms_reseau_um = _rms(np.hypot(E[inside, 0], E[inside, 1]))

    # ---- 4: orientation on the "operator's" measurements (exact truth pixels)
    bar.set_postfix_str(stages[2])

    def true_pixel(k, XYZ):
        film = io.photo_to_film(pair.photo(k, XYZ))
        return scans[k]["tm"].film_to_pixel(film)

    def measured_photo(k, XYZ):
        return scans[k]["fc"].pixel_to(true_pixel(k, XYZ), to="photo")[0]

    allp = np.vstack([pts["tie"], pts["control"], pts["check"]])
    n_tie, n_ctrl = len(pts["tie"]), len(pts["control"])
    xy1, xy2 = measured_photo(0, allp), measured_photo(1, allp)
    sig_photo = 0.002
    ro = relative_orientation(xy1, xy2, cam.c, bx=1.0, sigma=sig_photo)
    # unit weights (sigma0_prior = the a priori sigma): sigma0 comes out in photo mm
    res.relative_sigma0_um = float(ro.sigma0 * 1000.0)
    res.relative_sigma0 = float(ro.sigma0 / sig_photo)
    model = ro.points.XYZ
    m_ctrl = model[n_tie:n_tie + n_ctrl]
    m_chk = model[n_tie + n_ctrl:]
    ao = absolute_orientation(m_ctrl, pts["control"])
    res.absolute_sigma0 = float(ao.sigma0)
    chk_err = ao.apply(m_chk) - pts["check"]
    res.check_rms_m = [_rms(chk_err[:, i]) for i in range(3)]
    # exterior orientation in the object frame
    Ma = ao.M
    photos = []
    for k, (Cm, ang) in enumerate(((np.zeros(3), ro.angles1), (ro.base, ro.angles2))):
        Cobj = ao.apply(Cm[None, :])[0]
        Mk = rotation_matrix(*ang) @ Ma
        photos.append(OrientedPhoto(
            Cobj, np.array(angles_from_matrix(Mk), float), cam.c, 0.0, 0.0,
            to_photo=scans[k]["map"],
            to_film=scans[k]["map"].inverse,
            name=("left", "right")[k],
        ))
    stereo = StereoModel(photos[0], photos[1])
    bar.update(1)

    # ---- 5: contours through the plotter and the virtual motors
    bar.set_postfix_str(stages[3])
    instr_tie = [scans[k]["frame"].to_instrument(true_pixel(k, pts["tie"])) for k in range(2)]
    offset = tuple(np.median(instr_tie[0] - instr_tie[1], axis=0))
    ax = AxisConfig(resolution_mm=cfg.motor_resolution_mm, min_mm=-15.0, max_mm=15.0,
                    max_speed_mm_s=50.0)
    motors = VirtualMotors(ax, ax, left_offset=offset)
    plotter = Plotter(stereo, motors, mode="contour", height=0.0, left_offset=offset)
    Z0, A = pair.hill[2], pair.hill[3]
    heights = np.arange(np.ceil((Z0 + 1e-6) / cfg.interval) * cfg.interval, Z0 + A,
                        cfg.interval)
    heights = heights[heights > Z0 + 0.08 * A]
    rec = []  # per vertex: H, right instr (2), left instr (2), true contour point (3)
    for H in tqdm(heights, desc="contours", unit="contour", disable=not progress, leave=False):
        plotter.set_mode("contour", float(H))
        truth_line = pair.contour_truth(float(H), cfg.vertices)
        right = scans[1]["frame"].to_instrument(true_pixel(1, truth_line))
        plotter.begin("CONTOUR", interval=cfg.interval)
        for P, (X, Y) in zip(truth_line, right, strict=True):
            cyc = plotter.cycle(float(X), float(Y))
            if not cyc.in_travel:
                continue
            motors.wait()
            DX, DY = motors.position()
            plotter.vertex()
            rec.append([H, X, Y, X + offset[0] + DX, Y + offset[1] + DY, *P])
        plotter.end(close=True)
    rec = np.asarray(rec, float)
    feats = plotter.features
    res.contours = len(feats)
    res.vertices = len(rec)
    if len(rec):
        # truth: the commanded image points through the TRUE film mapping and orientation
        ph = []
        for k, cols in ((0, slice(3, 5)), (1, slice(1, 3))):
            px = scans[k]["frame"].to_pixel(rec[:, cols])
            ph.append(io.film_to_photo(scans[k]["tm"].pixel_to_film(px)))
        xt = intersect_pair(ph[0], ph[1], pair.X0[0], pair.angles[0], pair.X0[1],
                            pair.angles[1], cam.c).XYZ
        dh = pair.terrain(xt[:, 0], xt[:, 1]) - rec[:, 0]
        res.contour_height_rms_m = _rms(dh)
        res.contour_height_max_m = float(np.max(np.abs(dh)))
        res.contour_mark_height_rms_m = _rms(xt[:, 2] - rec[:, 0])
        recorded = np.vstack([f.vertices[:-1] if f.closed else f.vertices for f in feats])
        res.contour_plan_rms_m = _rms(np.hypot(*(recorded[:, :2] - rec[:, 5:7]).T))
    bar.update(1)

    # ---- 6: export
    bar.set_postfix_str(stages[4])
    if out_dir is not None:
        from softplot.export.dxf import write_dxf
        from softplot.export.geojson import write_geojson
        from softplot.io import fingerprint
        from softplot.synthetic.files import write_image

        o = res.outputs
        o["dxf"] = str(write_dxf(feats, out_dir / "contours.dxf"))
        o["geojson"] = str(write_geojson(feats, out_dir / "contours.geojson"))
        if write_scans:
            for k, s in enumerate(scans):
                side = ("left", "right")[k]
                p = write_image(out_dir / f"{side}.tif", s["image"], cfg.dpi, "tif",
                                overwrite=True, description=f"softplot demo {side} scan")
                o[f"{side}_scan"] = str(p)
                s["det"]["scan"] = s["fc"].scan = fingerprint(p)
                s["map"].scan_path = Path(p)
                dp = out_dir / f"{side}.detection.json"
                dp.write_text(json.dumps(s["det"], indent=1) + "\n", encoding="utf-8")
                o[f"{side}_detection"] = str(dp)
        o["session"] = str(_write_session(out_dir / "session", stereo, feats, offset,
                                          float(heights[0]) if len(heights) else None))
        o.update(_write_points(out_dir, pts, scans, true_pixel, measured_photo, stereo))
        res.seconds = time.perf_counter() - t_start
        o["report"] = str(_report(out_dir / "report.html", res, cfg, pair, scans, stereo,
                                  feats, pts, chk_err, ao, ro))
        o["result"] = str(out_dir / "demo.json")
        res.seconds = time.perf_counter() - t_start
        from softplot.pipeline.batch import write_json_atomic

        write_json_atomic(out_dir / "demo.json", res.to_json())
    bar.update(1)
    bar.close()
    res.seconds = time.perf_counter() - t_start
    return res


def _write_session(folder: Path, stereo, feats, offset, height) -> Path:
    """The plotting session of the demo's model (its scans, film corrections, orientation and
    the contours just traced), ready for ``softplot view`` and ``softplot plot``."""
    import shutil

    from softplot.pipeline.session import Session

    if folder.exists():  # an earlier demo's session in the demo's own folder
        shutil.rmtree(folder)
    with Session.create(folder, stereo, mode="contour", height=height,
                        left_offset=offset) as session:
        for f in feats:
            session.record(f)
    return folder


def _write_csv(path: Path, header: list[str], rows) -> str:
    import csv

    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            w.writerow([f"{v:.6f}" if isinstance(v, float) else v for v in r])
    return str(path)


def _write_points(out_dir: Path, pts, scans, true_pixel, measured_photo, stereo) -> dict:
    """CSV files for the README tour: the operator's pointings and the control.

    ``points-left.csv``, ``points-right.csv``: name,x,y in pixels of each scan (tie ``T*``,
    control ``C*``, check ``K*``: the exact truth pixels standing in for the operator);
    ``control.csv``, ``check.csv``: name,X,Y,Z object m; ``check-photo.csv``:
    name,x1,y1,x2,y2 photo mm of the check points through the film corrections;
    ``photos.csv``: photo,X0,Y0,Z0,omega,phi,kappa,c (degrees, mm) of the oriented pair.
    """
    names = {k: [f"{p}{i + 1}" for i in range(len(pts[k]))]
             for k, p in (("tie", "T"), ("control", "C"), ("check", "K"))}
    allp = np.vstack([pts["tie"], pts["control"], pts["check"]])
    alln = names["tie"] + names["control"] + names["check"]
    o = {}
    for k, side in enumerate(("left", "right")):
        px = true_pixel(k, allp)
        rows = [[n, *map(float, q)] for n, q in zip(alln, px, strict=True)]
        o[f"points_{side}"] = _write_csv(out_dir / f"points-{side}.csv", ["name", "x", "y"], rows)
    for k in ("control", "check"):
        o[k] = _write_csv(out_dir / f"{k}.csv", ["name", "X", "Y", "Z"],
                          [[n, *map(float, q)]
                           for n, q in zip(names[k], pts[k], strict=True)])
    p1, p2 = measured_photo(0, pts["check"]), measured_photo(1, pts["check"])
    o["check_photo"] = _write_csv(
        out_dir / "check-photo.csv", ["name", "x1", "y1", "x2", "y2"],
        [[n, *map(float, a), *map(float, b)]
         for n, a, b in zip(names["check"], p1, p2, strict=True)])
    o["photos"] = _write_csv(
        out_dir / "photos.csv", ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [[p.name, *map(float, p.X0), *map(float, np.rad2deg(p.angles)), float(p.c)]
         for p in (stereo.left, stereo.right)])
    return o


def _check_rows(chk_err) -> list[list]:
    """Rows of the check-point table (dX, dY, dZ object m) and an RMS row under them."""
    e = np.asarray(chk_err, float).reshape(-1, 3)
    rows = [[f"K{i + 1}", *map(float, r)] for i, r in enumerate(e)]
    rows.append(["RMS", *(_rms(e[:, j]) for j in range(3))])
    return rows


def _orientation_rows(ro, ao) -> list[list]:
    """Rows ``[step, parameter, value, std, unit]`` of the relative orientation's free
    parameters (model units, degrees) and the absolute orientation's seven (scale, degrees,
    object m); the standard deviations are the adjustments' a posteriori ones."""
    rows = []
    for name in ro.free:
        v, s = ro.value(name), ro.std[name]
        if name.startswith("b"):
            rows.append(["relative", name, v, s, "model (bx = 1)"])
        else:
            rows.append(["relative", name, float(np.rad2deg(v)), float(np.rad2deg(s)), "deg"])
    for k, name in enumerate(("scale", "omega", "phi", "kappa", "TX", "TY", "TZ")):
        v, s = float(ao.params[k]), float(ao.std[k])
        if name in ("omega", "phi", "kappa"):
            rows.append(["absolute", name, float(np.rad2deg(v)), float(np.rad2deg(s)), "deg"])
        else:
            rows.append(["absolute", name, v, s, "m per model unit" if k == 0 else "m"])
    return rows


def _value_std_text(value: float, std: float) -> tuple[str, str]:
    """A value and its standard deviation as text: the std to two significant digits and
    the value to the same decimal place."""
    if not (np.isfinite(std) and std > 0):
        return f"{value:.6g}", "" if not np.isfinite(std) else "0"
    dec = max(0, 1 - int(np.floor(np.log10(std))))
    return f"{value:.{dec}f}", f"{std:.{dec}f}"


def _thumbnail(image, width: int = 640):
    """Every ``step``-th pixel of ``image`` (about ``width`` wide) and the step."""
    step = max(1, int(np.ceil(image.shape[1] / width)))
    return image[::step, ::step], step


def _scan_figure(plt, scan: dict, side: str):
    """Thumbnail of a scan with its crosses: measured (green +), missing and rejected (red)."""
    thumb, step = _thumbnail(scan["image"])
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    ax.imshow(thumb, cmap="gray", extent=(-0.5, thumb.shape[1] * step - 0.5,
                                          thumb.shape[0] * step - 0.5, -0.5))
    marks = scan["det"]["marks"]
    styles = {"measured": ("+", "lime", 7), "missing": ("o", "red", 9),
              "rejected": ("x", "red", 9)}
    for status, (mk, col, ms) in styles.items():
        xy = np.array([[m["x"], m["y"]] for m in marks if m.get("status") == status
                       and m.get("x") is not None and np.isfinite(m["x"])], float)
        n = sum(m.get("status") == status for m in marks)
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], mk, color=col, ms=ms, mfc="none",
                    label=f"{status} ({n})")
        elif n:
            ax.plot([], [], mk, color=col, label=f"{status} ({n}, no position)")
    ax.set_xlabel("x px")
    ax.set_ylabel("y px")
    ax.set_title(f"{side} scan")
    ax.legend(loc="upper right", fontsize=7)
    return fig


def _contour_image_figure(plt, scan: dict, photo, feats):
    """The contours over the left scan: object vertices through the estimated orientation
    (``photo.project``: object m -> photo mm) and the film correction (photo mm -> pixel),
    labelled with their heights in m."""
    thumb, step = _thumbnail(scan["image"], 900)
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.imshow(thumb, cmap="gray", extent=(-0.5, thumb.shape[1] * step - 0.5,
                                          thumb.shape[0] * step - 0.5, -0.5))
    for f in feats:
        v = np.asarray(f.vertices, float)
        if f.closed:
            v = np.vstack([v, v[:1]])
        px = scan["fc"].to_pixel(photo.project(v), frm="photo")[0]
        ax.plot(px[:, 0], px[:, 1], "-", color="orange", lw=1.0)
        j = int(np.argmin(px[:, 1]))
        ax.annotate(f"{f.height:g} m", px[j], color="orange", fontsize=8,
                    ha="center", va="bottom")
    ax.set_xlabel("x px")
    ax.set_ylabel("y px")
    return fig


def _detection_figure(plt, scans):
    """Detected minus true cross positions of both scans, equal axes on one common scale."""
    fig, axs = plt.subplots(1, 2, figsize=(9, 4.5), sharex=True, sharey=True)
    lim = max([float(np.max(np.abs(s["d"]))) for s in scans if len(s["d"])] + [1e-3]) * 1.1
    for k, s in enumerate(scans):
        d = s["d"]
        rms = _rms(np.hypot(d[:, 0], d[:, 1])) if len(d) else float("nan")
        axs[k].plot(d[:, 0], d[:, 1], ".")
        axs[k].set_title(f"{('left', 'right')[k]}: {len(d)} crosses, RMS {rms:.3f} px")
        axs[k].set_xlabel("dx px")
        axs[k].set_ylabel("dy px")
        axs[k].set_xlim(-lim, lim)
        axs[k].set_ylim(-lim, lim)
        axs[k].set_aspect("equal")
        axs[k].axhline(0, color="0.8", lw=0.5)
        axs[k].axvline(0, color="0.8", lw=0.5)
    return fig


def _report(path, res: DemoResult, cfg, pair, scans, stereo, feats, pts, chk_err, ao, ro):
    """The demo's self-contained HTML report."""
    import datetime

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from softplot import __version__
    from softplot.export.html import Report

    rep = Report("softplot demo: Rollei 6006 stereo pair, scans to contours")
    rep.paragraph(
        f"softplot {__version__}, "
        f"{datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}. "
        f"Synthetic pair at photo scale 1:{res.scale:.0f}, scans at {cfg.dpi:.0f} dpi; contour "
        f"interval {cfg.interval:g} m. Image coordinates of tie, control and check points are "
        "their exact truth pixel positions, standing in for the operator's measurements; the "
        "operator of the plotter is emulated by following the true contour lines in planimetry."
    )
    rep.heading("Accuracy against truth")
    rep.preformatted(res.summary())
    rep.heading("The scans and their reseau crosses")
    for k, s in enumerate(scans):
        side = ("left", "right")[k]
        rep.figure(_scan_figure(plt, s, side),
                   f"{side} scan (thumbnail, pixel coordinates of the full scan) with the "
                   "detected crosses: measured, missing and rejected")
        plt.close("all")
    rep.heading("Contours")
    rep.figure(_contour_image_figure(plt, scans[0], stereo.left, feats),
               "restituted contours over the left scan, heights in m")
    plt.close("all")
    fig, ax = plt.subplots(figsize=(7, 6))
    for H in sorted({f.height for f in feats}):
        t = pair.contour_truth(H, 180)
        ax.plot(*np.vstack([t, t[:1]])[:, :2].T, color="0.7", lw=3)
    for f in feats:
        ax.plot(f.vertices[:, 0], f.vertices[:, 1], "b-", lw=0.8)
    ax.plot(*pts["control"][:, :2].T, "r^", label="control")
    ax.plot(*pts["check"][:, :2].T, "gs", label="check")
    ax.plot(*pts["tie"][:, :2].T, "k.", label="tie")
    ax.set_aspect("equal")
    ax.set_xlabel("X m")
    ax.set_ylabel("Y m")
    ax.legend(loc="upper right")
    rep.figure(fig, "restituted contours (blue) over the true ones (grey), object m")
    plt.close("all")
    rep.heading("Detection: detected minus true cross positions")
    rep.figure(_detection_figure(plt, scans), "both scans on one scale, pixels of the scan")
    plt.close("all")
    rep.heading("Check points after absolute orientation (transformed minus true, object m)")
    rep.table(["point", "dX m", "dY m", "dZ m"], _check_rows(chk_err))
    rep.heading("Orientation")
    rep.table(["step", "parameter", "value", "std", "unit"],
              [[a, b, *_value_std_text(v, sd), u] for a, b, v, sd, u in _orientation_rows(ro, ao)])
    rep.paragraph(f"relative orientation: sigma0 {1000 * ro.sigma0:.3f} um (photo), redundancy "
                  f"{ro.redundancy}; "
                  f"absolute orientation: sigma0 {ao.sigma0:.4f} m, redundancy {ao.redundancy}")
    rep.table(["photo", "X0 m", "Y0 m", "Z0 m", "omega deg", "phi deg", "kappa deg"],
              [[p.name, *(f"{v:.3f}" for v in p.X0), *(f"{v:.4f}" for v in np.rad2deg(p.angles))]
               for p in (stereo.left, stereo.right)])
    rep.paragraph("Exterior orientation of each photo in the object frame, composed from the "
                  "relative and absolute orientations above (whose standard deviations the "
                  "table above gives).")
    rep.heading("Outputs")
    rep.table(["what", "file"], [[k, v] for k, v in res.outputs.items()])
    return rep.write(path)
