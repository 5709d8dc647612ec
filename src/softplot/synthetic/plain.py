"""A second scan renderer, written apart from :mod:`softplot.synthetic.scan`: a check that the
detector is not tuned to its own renderer.

It shares no code and none of the image model of :mod:`softplot.synthetic.scan`. Where that
renderer and the detector both describe a cross as a blurred bar template over a Gaussian
point spread, this one:

* integrates each cross's coverage of every pixel by brute force: a grid of ``SUPER x SUPER``
  sample cells per pixel, each cell's share inside the two rotated bars (a ramp across each
  edge, exact for an edge along the cell; exact bar ends, no template);
* forms the image on film: the scene's exposure through a film response (a power law in
  exposure over a toe, a negative's density growing with it, a positive's falling), the
  reseau's shadow recorded sharp (each pixel's transmittance the coverage-weighted mean of
  the film under the cross and beside it), not a grey-level mix of bar and scene;
* blurs with a defocus disc (a pillbox, which a Gaussian model does not describe) followed by
  a Gaussian of the scanner, then sets the sensor's black and white levels (the brightest
  0.2 % saturate);
* adds clumped grain (white noise low-passed, multiplicative on density) and a vignetting
  gradient;
* encodes JPEG with OpenCV's encoder (chroma subsampled for RGB) and colour negatives with an
  orange mask per channel;
* makes scenes of its own: 1/f noise, sharp-edged blocks, a flat dark area over whole rows.

Every figure a user cannot know is drawn independently of the certificate: the true arm length
(0.4-2.5x the certificate's), line width (0.5-2x), opacity, polarity, crop, rotation. Truth is
the crosses' centres in the pixel system of the scan (x right, y down, (0, 0) the centre of the
top-left pixel), each with a state: ``visible`` (wholly inside the scan, changing the
noise-free scan by at least :data:`FAINT` of its grey range and :data:`VISIBLE_SNR` times
the noise's standard deviation around it), ``faint`` (less: neither
expected nor a claim), ``dark`` (below :data:`DARK`, and changing the scan as stored, grain and
sensor noise included, by less than that along its lines on average: a measurement is a claim;
where the noise-free scan clips to black the noise still carries a cross), ``cut`` (the scan's
edge cuts it) or ``outside``.

:func:`make_plain` draws one seeded scan; :func:`score_plain` scores a detection against its
truth; :func:`expected` tells whether the scan shows enough of the grid to be named;
:func:`run_plain` detects and scores one scan as a user would, :func:`summarise` pools the
scores (``tools/sweep_plain.py``, docs/accuracy.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from softplot.camera import load_camera

__all__ = ["PlainCase", "make_plain", "score_plain", "expected", "run_plain", "summarise",
           "CAMERAS", "SUPER", "FAINT", "DARK"]

#: sample cells per pixel side of the coverage integral
SUPER = 8
#: cameras of the check and their weights
CAMERAS = {"rollei-6006": 0.4, "pentax-645": 0.25, "hasselblad-mk70": 0.2,
           "aerial-23x47": 0.15}
#: a cross whose largest change to the noise-free scan is below this fraction of the grey
#: range is "faint": neither expected to be measured nor a claim when it is
FAINT = 0.02
#: below this it is "dark": a measurement there is a claim on an invisible cross
DARK = 0.005
#: a cross is also "faint" where its contrast is below this many times the noise's standard
#: deviation around it (grain and sensor noise, robust estimate): it does not stand out
VISIBLE_SNR = 2.0


@dataclass
class PlainCase:
    """One scan of the independent renderer and its truth."""

    seed: int
    camera: str
    dpi: float
    image: np.ndarray
    truth: dict
    params: dict = field(default_factory=dict)

    def describe(self) -> str:
        """One line: the seed, camera and the drawn parameters."""
        p = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                      for k, v in self.params.items())
        return f"plain {self.seed}: {self.camera}, {self.dpi:.0f} dpi, {p}"


def _bars_cover(px: np.ndarray, py: np.ndarray, c: np.ndarray, ang: float, arm: float,
                width: float, one_bar: int | None) -> np.ndarray:
    """Fraction of each pixel (pixel-system centres ``px``, ``py``, 2-D) that the cross at
    ``c`` covers: two bars of tip-to-tip length ``arm`` and width ``width`` (px), the first
    along the direction ``ang`` (radians, from the x axis), the second across it; ``one_bar``
    0 or 1 keeps only that bar."""
    s = (np.arange(SUPER) + 0.5) / SUPER - 0.5
    ox, oy = np.meshgrid(s, s)
    X = px[..., None, None] + ox - c[0]
    Y = py[..., None, None] + oy - c[1]
    u, v = np.cos(ang), np.sin(ang)
    a = X * u + Y * v
    b = -X * v + Y * u
    h, hw = arm / 2.0, width / 2.0

    def ramp(d):  # share of a sample's cell (1/SUPER px wide) inside ``d`` px of an edge
        return np.clip(d * SUPER + 0.5, 0.0, 1.0)

    c1 = ramp(h - np.abs(a)) * ramp(hw - np.abs(b))
    c2 = ramp(h - np.abs(b)) * ramp(hw - np.abs(a))
    # the union: both bars less their common square (each term exact along the cell's axes)
    both = ramp(hw - np.abs(a)) * ramp(hw - np.abs(b))
    inside = c1 if one_bar == 0 else c2 if one_bar == 1 else c1 + c2 - both
    return inside.mean(axis=(-2, -1))


def _one_over_f(rng, h: int, w: int, beta: float = 1.8) -> np.ndarray:
    """A 1/f^beta random field in [0, 1], shape (h, w)."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    spec = (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)) / f ** (beta / 2)
    spec[0, 0] = 0
    z = np.fft.irfft2(spec, s=(h, w))
    z -= z.min()
    return z / max(z.max(), 1e-12)


def _scene(rng, kind: str, h: int, w: int, ppm: float) -> np.ndarray:
    """Scene transmittance in (0, 1], shape (h, w): ``kind`` "smooth", "texture" or
    "blocks"."""
    base = 0.35 + 0.5 * _one_over_f(rng, h, w, 2.6)
    if kind == "texture":
        base = 0.25 + 0.6 * (0.6 * base + 0.4 * _one_over_f(rng, h, w, 1.4))
    elif kind == "blocks":
        img = (base * 255).astype(np.float32)
        for _ in range(int(rng.integers(40, 120))):
            x0, y0 = rng.uniform(0, w), rng.uniform(0, h)
            sx, sy = rng.uniform(0.5, 6) * ppm, rng.uniform(0.5, 6) * ppm
            ang = rng.uniform(0, 180)
            box = cv2.boxPoints(((x0, y0), (sx, sy), ang)).astype(np.int32)
            cv2.fillPoly(img, [box], float(rng.uniform(40, 240)))
        base = img / 255.0
    return np.clip(base, 0.03, 1.0)


def _density(E: np.ndarray, negative: bool, contrast: float) -> np.ndarray:
    """Density of the processed film for exposure ``E`` (0-1): a straight line in log
    exposure over a toe at 1 % (fog 0.15 on a negative, base 0.1 on a positive)."""
    log_e = np.log10(E + 0.01) + 2.0  # 0 .. 2
    return (0.15 + contrast * log_e) if negative else (0.1 + contrast * (2.0 - log_e))


def _blur(img: np.ndarray, defocus: float, gauss: float) -> np.ndarray:
    """A defocus disc of radius ``defocus`` px (a pillbox, anti-aliased edge; none below
    0.3 px), then a Gaussian of sigma ``gauss`` px."""
    if defocus > 0.3:
        rr = int(np.ceil(defocus))
        dy, dx = np.mgrid[-rr:rr + 1, -rr:rr + 1]
        disc = np.clip(defocus + 0.5 - np.hypot(dx, dy), 0, 1).astype(np.float32)
        img = cv2.filter2D(img, -1, disc / disc.sum(), borderType=cv2.BORDER_REFLECT)
    return cv2.GaussianBlur(img, (0, 0), gauss)


def make_plain(seed: int, max_side: int = 2600, **override) -> PlainCase:
    """Draw the seeded scan ``seed`` (see the module docstring), at most about ``max_side`` px
    across. ``override`` replaces drawn figures by name (the keys of
    :attr:`PlainCase.params`: ``arm_x``, ``width_x``, ``opacity``, ``negative``, ``rgb``,
    ``bits``, ``jpeg``, ``rot``, ``aniso``, ``defocus``, ``gauss``, ``grain``, ``scene``,
    ``contrast``, ``big_centre``, ``dark_rows``, ``crop``); the others keep their values."""
    rng = np.random.default_rng([seed, 1729])
    names = list(CAMERAS)
    cam_name = names[int(rng.choice(len(names), p=list(CAMERAS.values())))]
    cam = load_camera(cam_name)
    res = cam.reseau
    fw, fh = cam.format_mm
    span = max(fw, fh) + 6.0
    dpi_hi = min(2400.0, max_side / span * 25.4)
    dpi = float(np.exp(rng.uniform(np.log(min(500.0, 0.8 * dpi_hi)), np.log(dpi_hi))))
    ppm = dpi / 25.4
    # every figure drawn in a fixed order (an override leaves the others as they were)
    p = {"arm_x": float(rng.uniform(0.4, 2.5)), "width_x": float(rng.uniform(0.5, 2.0)),
         "opacity": float(rng.uniform(0.6, 1.0)), "negative": bool(rng.random() < 0.4),
         "rgb": bool(rng.random() < 0.35), "bits": 16 if rng.random() < 0.25 else 8}
    jq = int(rng.integers(40, 96))
    p["jpeg"] = jq if (p["bits"] == 8 and rng.random() < 0.35) else 0
    p.update(rot=float(rng.uniform(-3.0, 3.0)), aniso=float(rng.uniform(-0.003, 0.003)),
             defocus=float(rng.uniform(0.0, 2.0)), gauss=float(rng.uniform(0.3, 1.2)),
             grain=float(rng.uniform(0.0, 0.05)),
             scene=str(rng.choice(["smooth", "texture", "blocks"], p=[0.3, 0.4, 0.3])),
             contrast=float(rng.uniform(0.5, 1.0)), big_centre=bool(rng.random() < 0.2),
             dark_rows=bool(res.rows >= 5 and rng.random() < 0.25))
    margin = rng.uniform(0.5, 3.0, 4)  # mm beyond the format: left, right, top, bottom
    p["crop"] = bool(rng.random() < 0.25)
    side, frac = int(rng.integers(4)), float(rng.uniform(-0.3, 0.3))
    unknown = set(override) - set(p)
    if unknown:
        raise ValueError(f"make_plain: no figure named {sorted(unknown)}")
    p.update(override)
    arm = res.arm_length_mm * p["arm_x"] * ppm
    width = max(res.line_width_mm * p["width_x"] * ppm, 0.8)  # narrower is not a line a
    # scan can show
    opacity, negative, rgb, bits, jpeg = (p[k] for k in ("opacity", "negative", "rgb", "bits",
                                                        "jpeg"))
    rot, aniso, defocus, gauss, grain = (p[k] for k in ("rot", "aniso", "defocus", "gauss",
                                                       "grain"))
    scene_kind, contrast, big_centre, dark_rows, crop = (
        p[k] for k in ("scene", "contrast", "big_centre", "dark_rows", "crop"))
    if crop:  # through the outer row or column on one side: the scan's edge within
        # 0.3 arm of that row's or column's crosses
        half = ((res.cols - 1) / 2 * res.pitch_x, (res.rows - 1) / 2 * res.pitch_y)[side // 2]
        margin[side] = half + frac * arm / ppm - (fw, fh)[side // 2] / 2
    W = int(round((fw + margin[0] + margin[1]) * ppm))
    H = int(round((fh + margin[2] + margin[3]) * ppm))
    # film mm -> pixel: the format's centre at (cx, cy), rotated, anisotropic
    cx = (fw / 2 + margin[0]) * ppm - 0.5 + rng.uniform(-0.5, 0.5)
    cy = (fh / 2 + margin[2]) * ppm - 0.5 + rng.uniform(-0.5, 0.5)
    t = np.deg2rad(rot)
    R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    S = np.diag([ppm * (1 + aniso), ppm * (1 - aniso)])
    A = R @ S @ np.diag([1.0, -1.0])  # film y up -> pixel y down
    film = res.film()
    xy = film @ A.T + (cx, cy)
    # film deformation: a smooth field of a few um
    amp = rng.uniform(0.0, 8e-3) * ppm
    k = rng.normal(size=(2, 3))
    xy = xy + amp * np.column_stack([
        np.sin(k[0, 0] * film[:, 0] / 20 + k[0, 1] * film[:, 1] / 20 + k[0, 2]),
        np.sin(k[1, 0] * film[:, 0] / 20 + k[1, 1] * film[:, 1] / 20 + k[1, 2])])
    # the exposure: scene inside the format, film base outside
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    inv = np.linalg.inv(A)
    fx = inv[0, 0] * (xx - cx) + inv[0, 1] * (yy - cy)
    fy = inv[1, 0] * (xx - cx) + inv[1, 1] * (yy - cy)
    inside = (np.abs(fx) <= fw / 2) & (np.abs(fy) <= fh / 2)
    scene = _scene(rng, scene_kind, H, W, ppm).astype(np.float32)
    if dark_rows:
        r0 = int(rng.integers(0, max(1, res.rows - 1)))
        y_hi = ((res.rows - 1) / 2 - r0 + 0.5) * res.pitch_y
        y_lo = y_hi - res.pitch_y * float(rng.uniform(1.0, 3.0))
        scene = np.where((fy <= y_hi) & (fy >= y_lo), np.float32(5e-4), scene)
    E = np.where(inside, scene, np.float32(0.0 if negative else 1.0)).astype(np.float32)
    # the crosses' cover, integrated per pixel
    cover = np.zeros((H, W), np.float32)
    centre = (res.rows // 2) * res.cols + res.cols // 2
    one_armed = rng.random(len(xy)) < (0.08 if rng.random() < 0.3 else 0.0)
    states = []
    for i, (x, y) in enumerate(xy):
        a = arm * (2.0 if big_centre and i == centre else 1.0)
        r = int(np.ceil(a / 2 + width + 2))
        x0, x1 = int(np.floor(x)) - r, int(np.ceil(x)) + r + 1
        y0, y1 = int(np.floor(y)) - r, int(np.ceil(y)) + r + 1
        if x1 <= 0 or y1 <= 0 or x0 >= W or y0 >= H:
            states.append("outside")
            continue
        xa, xb, ya, yb = max(x0, 0), min(x1, W), max(y0, 0), min(y1, H)
        px, py = np.meshgrid(np.arange(xa, xb, dtype=np.float64),
                             np.arange(ya, yb, dtype=np.float64))
        ob = (int(rng.integers(2)) if one_armed[i] else None)
        c = _bars_cover(px, py, np.array([x, y]), t, a, width, ob)
        cover[ya:yb, xa:xb] = np.maximum(cover[ya:yb, xa:xb], c)
        m = 0.5 * width + a / 2  # the cross's half extent
        fully = (x - m >= -0.5) and (y - m >= -0.5) and (x + m <= W - 0.5) and (y + m <= H - 0.5)
        if not (0 <= x <= W - 1 and 0 <= y <= H - 1):
            states.append("outside")
        elif not fully:
            states.append("cut")
        else:
            states.append("visible")
    # film response and scan: density from the log exposure over a toe (a negative's density
    # grows with exposure, a positive's falls), vignetting, a defocus disc and the scanner's
    # Gaussian, the sensor's levels; once without the crosses, for their contrast
    # the reseau lies on the film: each pixel's transmittance is the coverage-weighted mean
    # of the film under the cross's shadow and beside it (the film records the cross sharp)
    T_bare = 10.0 ** (-_density(E, negative, contrast))
    T_mark = 10.0 ** (-_density(E * (1.0 - opacity), negative, contrast))
    Tc = T_bare + cover * (T_mark - T_bare)
    vig = (1.0 - 0.15 * (((xx - W / 2) / W) ** 2 + ((yy - H / 2) / H) ** 2)).astype(np.float32)

    def optics(T):  # the film's transmittance as the sensor sees it
        return _blur((T * vig).astype(np.float32), defocus, gauss)

    bare = optics(T_bare)
    clean = optics(Tc)
    T_grain = T_bare
    if grain:  # clumped grain on density
        g = cv2.GaussianBlur(rng.normal(size=(H, W)).astype(np.float32), (0, 0), 0.7)

        def grained(T):
            return T * 10.0 ** (-grain * 3.0 * g * np.sqrt(np.maximum(-np.log10(T), 0.05)))

        Tc, T_grain = grained(Tc), grained(T_bare)
    # the sensor's levels: black and white where the scanner's auto-exposure puts them
    # (the brightest 0.2 % saturate: the clear crosses of a negative often do)
    lo, hi = np.percentile(clean[::4, ::4], [0.2, 99.8])
    span = max(hi - lo, 1e-6)
    # the cross's change to the noise-free scan as stored: where the sensor saturates, none
    diff = np.abs(np.clip((clean - lo) / span, 0, 1) - np.clip((bare - lo) / span, 0, 1))
    sensor = rng.normal(0, 0.004, (H, W)).astype(np.float32)
    img = np.clip((optics(Tc) - lo) / span + sensor, 0, 1)
    noise = img - np.clip((clean - lo) / span, 0, 1)  # grain and sensor noise
    # the cross's change to the scan as stored, with the same grain and sensor noise: where
    # the noise-free scan clips to black, the noise still carries the cross (its lines are
    # black more often than the film beside them)
    stored = np.abs(img - np.clip((optics(T_grain) - lo) / span + sensor, 0, 1))
    if rgb:
        if negative:
            mask = np.array([0.95, 0.62, 0.38], np.float32)  # the orange mask (R, G, B)
        else:
            mask = np.array([1.0, 0.97, 0.9], np.float32)
        img = img[..., None] * mask
    top = 65535 if bits == 16 else 255
    out = np.round(img * top).astype(np.uint16 if bits == 16 else np.uint8)
    if jpeg:
        bgr = out[..., ::-1] if out.ndim == 3 else out
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg])
        dec = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        out = dec[..., ::-1].copy() if dec.ndim == 3 else dec
    # each cross's contrast: the largest change it makes to the noise-free scan (grey range
    # 0-1) within its footprint
    names = res.names()
    marks = []
    for i, (x, y) in enumerate(xy):
        st = states[i]
        r = int(np.ceil(arm / 2 + width + 2))
        xi, yi = int(round(x)), int(round(y))
        win = diff[max(yi - r, 0):max(yi + r + 1, 0), max(xi - r, 0):max(xi + r + 1, 0)]
        con = float(win.max()) if win.size else 0.0
        nwin = noise[max(yi - r, 0):max(yi + r + 1, 0), max(xi - r, 0):max(xi + r + 1, 0)]
        sd = float(1.4826 * np.median(np.abs(nwin - np.median(nwin)))) if nwin.size else 0.0
        if st == "visible" and con < max(FAINT, VISIBLE_SNR * sd):
            # "dark" only where the stored scan, too, hardly changes along the cross's lines
            on = cover[max(yi - r, 0):max(yi + r + 1, 0), max(xi - r, 0):max(xi + r + 1, 0)] > 0.5
            seen = float(stored[max(yi - r, 0):max(yi + r + 1, 0),
                                max(xi - r, 0):max(xi + r + 1, 0)][on].mean()) if on.any() else 0.0
            st = "dark" if max(con, seen) < DARK else "faint"
        marks.append({"name": names[i], "x": float(x), "y": float(y), "state": st,
                      "arms": 1 if one_armed[i] else 2, "contrast": con, "noise": sd})
    params = dict(p, width_x=width / (res.line_width_mm * ppm),
                  one_armed=int(one_armed.sum()))
    pitch = min(res.pitch_x, res.pitch_y) * ppm
    return PlainCase(seed, cam_name, dpi, out, {"marks": marks, "pitch_px": pitch}, params)


def score_plain(case: PlainCase, det) -> dict:
    """Score a :class:`~softplot.marks.Detection` against the case's truth.

    Returns counts ``visible``, ``measured`` (of the visible), ``wrong`` (a measured cross
    nearer another cross's truth than its own, or more than a quarter pitch off),
    ``claimed`` (a measured cross whose truth is ``dark`` or ``outside``), ``gross`` (more
    than 1 px off its truth), the errors (px) of the measured visible two-armed crosses and
    their squared normalised errors per coordinate (``z2``: ``d' C^-1 d / 2`` with ``C`` the
    reported covariance; mean 1 when the covariance is honest), and of the measured visible
    one-armed crosses the normalised errors across and along the bar (``z_lone``: pairs, the
    error along ``C``'s eigenvectors over the root of its eigenvalues: the smaller one is
    across the bar).
    """
    tm = {m["name"]: m for m in case.truth["marks"]}
    q = 0.25 * case.truth["pitch_px"]
    out = {"visible": sum(m["state"] == "visible" for m in tm.values()), "measured": 0,
           "wrong": [], "claimed": [], "gross": [], "errors": [], "missed": [], "z2": [],
           "z_lone": []}
    got = set()
    for i, n in enumerate(det.name):
        if det.kind[i] != "reseau" or det.status[i] != "measured" or n not in tm:
            continue
        t = tm[n]
        e = float(np.hypot(det.xy[i, 0] - t["x"], det.xy[i, 1] - t["y"]))
        if e > q:
            out["wrong"].append(f"{n} {e:.1f} px off")
            continue
        if t["state"] in ("dark", "outside"):
            out["claimed"].append(n)
            continue
        got.add(n)
        if t["state"] != "visible":
            continue
        out["measured"] += 1
        if e > 1.0:
            out["gross"].append(f"{n} {e:.2f} px")
        if det.cov is None or not np.all(np.isfinite(det.cov[i])):
            continue
        d = det.xy[i] - (t["x"], t["y"])
        if t["arms"] == 2:
            out["errors"].append(e)
            out["z2"].append(float(d @ np.linalg.solve(det.cov[i], d)) / 2.0)
        else:
            w, V = np.linalg.eigh(det.cov[i])
            out["z_lone"].append([float(z) for z in (V.T @ d) / np.sqrt(np.maximum(w, 1e-30))])
    out["missed"] = [n for n, t in tm.items() if t["state"] == "visible" and n not in got]
    return out


def expected(case: PlainCase) -> bool:
    """Whether the scan must give a result: its visible crosses span at least 3 rows and
    3 columns of the grid."""
    rc = [(int(n[1:].split("C")[0]), int(n.split("C")[1])) for n in
          (m["name"] for m in case.truth["marks"] if m["state"] == "visible")]
    return len({r for r, _ in rc}) >= 3 and len({c for _, c in rc}) >= 3


def run_plain(seed: int, dpi_known: bool | None = None, **override) -> tuple[PlainCase, dict]:
    """Draw scan ``seed``, detect its crosses as a user would (``softplot detect SCAN
    --camera NAME``, with ``--dpi`` unless ``dpi_known`` is False; by default every third
    seed leaves the dpi to be estimated) and score the result.

    Returns the case and a row: ``seed``, ``camera``, ``expected``, ``result``, ``error``
    (the one line of a refusal) and, with a result, the :func:`score_plain` figures and the
    detection's ``dpi`` and ``dpi_source``.
    """
    from softplot.errors import SoftplotError
    from softplot.io import Scan
    from softplot.marks import detect

    case = make_plain(seed, **override)
    known = (seed % 3 != 0) if dpi_known is None else dpi_known
    row = {"seed": seed, "camera": case.camera, "expected": expected(case), "result": False,
           "error": "", "case": case.describe()}
    try:
        det = detect(Scan.from_array(case.image, dpi=case.dpi if known else None),
                     case.camera)
    except SoftplotError as e:
        row["error"] = str(e)
        return case, row
    row.update(score_plain(case, det), result=True, dpi=float(det.dpi),
               dpi_source=det.dpi_source)
    return case, row


def summarise(rows: list[dict]) -> dict:
    """Pooled figures of :func:`run_plain` rows: scans (``n``), those that must give a result
    (``expected``) and those that did (``results``); visible crosses in the results and the
    share ``measured``; ``wrong``, ``claimed``, ``gross`` counts; the median and RMS error
    (px) and the RMS normalised error (``z``, 1 when the covariances are honest) of the
    measured two-armed crosses; of the one-armed ones the count ``lone`` and the RMS
    normalised errors across (``z_across``) and along (``z_along``) the bar."""
    res = [r for r in rows if r["result"]]
    zl = [z for r in res for z in r.get("z_lone", [])]
    zl = np.asarray(zl, float).reshape(-1, 2)
    err = np.concatenate([np.asarray(r["errors"], float) for r in res]) if res else np.zeros(0)
    z2 = np.concatenate([np.asarray(r["z2"], float) for r in res]) if res else np.zeros(0)
    vis = sum(r["visible"] for r in res)
    return {"n": len(rows), "expected": sum(r["expected"] for r in rows),
            "results": sum(r["result"] for r in rows),
            "results_expected": sum(r["result"] and r["expected"] for r in rows),
            "visible": vis, "measured": sum(r["measured"] for r in res) / max(vis, 1),
            "wrong": sum(len(r["wrong"]) for r in res),
            "claimed": sum(len(r["claimed"]) for r in res),
            "gross": sum(len(r["gross"]) for r in res),
            "median_px": float(np.median(err)) if len(err) else float("nan"),
            "rms_px": float(np.sqrt(np.mean(err ** 2))) if len(err) else float("nan"),
            "z": float(np.sqrt(np.mean(z2))) if len(z2) else float("nan"),
            "lone": len(zl),
            "z_across": float(np.sqrt(np.mean(zl[:, 0] ** 2))) if len(zl) else float("nan"),
            "z_along": float(np.sqrt(np.mean(zl[:, 1] ** 2))) if len(zl) else float("nan")}
