"""A seeded robustness sweep of reseau detection: scans nobody tuned the detector to.

Each case (:func:`make_case`, one seed) draws a reseau layout and a set of *conditions*, each
switched on at random, with ranges wider than the renderer's defaults:

* the certificate is perturbed independently of the render: the crosses are drawn with arm
  length 0.4-2.5x and line width 0.5-2x the certificate's, opacity 0.6-1;
* scanner: rotation +-5 degrees plus quarter turns (the user states the turn, ``rotate``),
  x/y anisotropy +-0.3 %, the format off-centre by up to 10 %, 200-3200 dpi, blur
  0.5-2.5 px, 8/16 bit, RGB, JPEG quality 40-95 and small web copies (about 1000 px across,
  JPEG 40-75: rendered at the copy's resolution, i.e. an exact low-resolution scan);
* frames: crops through any row or column, half and quarter frames (always at least 3 x 3
  crosses wholly inside the scan, and on each axis at least one edge of the frame: a part of
  a lattice without any frame edge has no row/col to find);
* film: negatives, orange-masked colour negatives, low contrast, dust, scratches, busy
  scenes, one-armed crosses, a larger centre cross, flat dark regions over whole rows
  (crosses there have no contrast: invisible).

The dpi is drawn where the drawn line is at least :data:`MIN_LINE_PX` px wide and a bar
at least :data:`MIN_ARM_PX` px long (a cross below that is not a measurable mark), and the
frame is cropped to at most :data:`MAX_PIXELS` (large formats at high resolution are swept
as parts of the frame).

:func:`run_case` renders a case (pixel system truth, :mod:`softplot.synthetic.scan`), runs
:func:`softplot.marks.detect` in-process and scores it against the truth (:func:`score`);
:func:`aggregate` pools the scores per condition. ``tools/sweep_detect.py`` is the command.
"""

from __future__ import annotations

import math
import time
import traceback
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from softplot.camera import load_camera
from softplot.errors import SoftplotError
from softplot.synthetic.mapping import TruthMapping
from softplot.synthetic.scan import ScanSpec, render_scan

#: the reseau layouts of the sweep (built-in certificates) and the share of cases of each
LAYOUTS = {"rollei-6006": 0.36, "hasselblad-mk70": 0.22, "plate-13x18-reseau": 0.16,
           "pentax-645": 0.14, "aerial-23x47": 0.12}
#: a drawn line narrower than this (px) or a bar shorter (tip to tip, px) is not swept
MIN_LINE_PX = 0.35
MIN_ARM_PX = 8.0
#: pixels of a render at most (larger frames are cropped to a part of the frame)
MAX_PIXELS = 12e6
#: web copies (about 1000 px across) are made of the small formats only (a long side of at
#: most this, mm): a large frame at 1000 px shows no measurable cross
WEB_FORMAT_MM = 60.0
#: probability of each condition in a case
P_ON = 0.22
#: the conditions, in the order of the table; the "layout:..." rows come after them
CONDITIONS = (
    "arm<0.7x", "arm>1.5x", "width<0.75x", "width>1.5x", "opacity<0.8", "rotation>2deg",
    "quarter-turn", "half-turn", "anisotropy", "off-centre", "crop", "half-frame",
    "quarter-frame", "dpi<400", "dpi>=2000", "blur>1.5px", "jpeg", "web-copy", "16-bit", "rgb",
    "negative", "colour-negative", "low-contrast", "dust", "scratches", "busy", "one-armed",
    "centre-cross", "dark-rows",
)


@dataclass
class Case:
    """One render of the sweep and how it is detected.

    ``spec`` is the render (the crosses drawn at ``spec.mark_arm_scale`` /
    ``mark_width_scale`` times the certificate's); ``rotate`` the quarter turn the user
    states (degrees, counter-clockwise); ``jpeg`` the JPEG quality the scan is stored with
    (None: lossless); ``conditions`` the names it is tabulated under; ``part`` the block of
    whole crosses the scan shows, ``(col0, col1, row0, row1)`` (half-open, the certificate's
    columns and rows; the whole grid on a full frame).
    """

    seed: int
    camera: str
    spec: ScanSpec
    rotate: float = 0.0
    jpeg: int | None = None
    conditions: tuple = ()
    part: tuple = ()

    def describe(self) -> str:
        s = self.spec
        crop = [round(float(v), 1) for v in np.ravel(np.asarray(s.crop_mm, float))]
        return (f"seed {self.seed}, {self.camera}, {s.dpi:.0f} dpi, rot {s.rotation_deg:+.2f}, "
                f"rotate {self.rotate:.0f}, arm x{s.mark_arm_scale:.2f}, width "
                f"x{s.mark_width_scale:.2f}, opacity {s.mark_opacity:.2f}, blur "
                f"{s.blur_sigma_px:.2f}, {s.polarity}{' rgb' if s.rgb else ''}, {s.bits} bit"
                f"{f', jpeg q{self.jpeg}' if self.jpeg else ''}, contrast {s.contrast:.2f}, "
                f"scene {s.scene}, crop {crop}; conditions: {', '.join(self.conditions)}")


def _layout(rng: np.random.Generator) -> str:
    names = list(LAYOUTS)
    p = np.array([LAYOUTS[n] for n in names])
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def make_case(seed: int, camera: str | None = None) -> Case:
    """The case of ``seed`` (deterministic), optionally forcing the layout."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 20]))
    cam = load_camera(camera or _layout(rng))
    res = cam.reseau
    on = {c: bool(rng.uniform() < P_ON) for c in CONDITIONS}
    if cam.name == "pentax-645":  # 3 x 3 crosses: no part of the frame shows 3 x 3
        for c in ("crop", "half-frame", "quarter-frame", "dark-rows"):
            on[c] = False
    # mutually exclusive choices
    if on["web-copy"] and max(cam.format_mm) > WEB_FORMAT_MM:
        on["web-copy"], on["jpeg"] = False, True
    if on["half-frame"] or on["quarter-frame"]:
        on["crop"] = False
    if on["half-frame"] and on["quarter-frame"]:
        on[("half-frame", "quarter-frame")[int(rng.integers(2))]] = False
    if on["jpeg"] and on["web-copy"]:
        on["jpeg"] = False
    if on["quarter-turn"] and on["half-turn"]:
        on["half-turn"] = False
    if on["dpi<400"] and on["dpi>=2000"]:
        on["dpi>=2000"] = False
    if on["web-copy"]:
        on["dpi<400"] = on["dpi>=2000"] = False
        on["16-bit"] = False
    if on["jpeg"]:
        on["16-bit"] = False
    if on["arm<0.7x"] and on["arm>1.5x"]:
        on["arm>1.5x"] = False
    if on["width<0.75x"] and on["width>1.5x"]:
        on["width>1.5x"] = False
    if on["negative"] and on["colour-negative"]:
        on["negative"] = False

    arm_s = (rng.uniform(0.4, 0.7) if on["arm<0.7x"] else rng.uniform(1.5, 2.5)
             if on["arm>1.5x"] else rng.uniform(0.7, 1.5))
    wid_s = (rng.uniform(0.5, 0.75) if on["width<0.75x"] else rng.uniform(1.5, 2.0)
             if on["width>1.5x"] else rng.uniform(0.75, 1.5))
    opacity = rng.uniform(0.6, 0.8) if on["opacity<0.8"] else rng.uniform(0.8, 1.0)
    rot = rng.uniform(2.0, 5.0) * rng.choice([-1, 1]) if on["rotation>2deg"] else \
        rng.uniform(-2.0, 2.0)
    turn = (int(rng.choice([90, 270])) if on["quarter-turn"] else 180 if on["half-turn"]
            else 0)
    aniso = rng.uniform(-3000, 3000) if on["anisotropy"] else rng.uniform(-300, 300)
    blur = rng.uniform(1.5, 2.5) if on["blur>1.5px"] else rng.uniform(0.5, 1.5)
    lw_mm = res.line_width_mm * wid_s
    arm_mm = res.arm_length_mm * arm_s
    fw, fh = cam.format_mm
    need = max(MIN_LINE_PX / lw_mm, MIN_ARM_PX / arm_mm) * 25.4  # lowest dpi of the marks
    if on["web-copy"]:
        dpi = 25.4 * rng.uniform(850, 1150) / max(fw, fh)
        if dpi < need:  # the marks would vanish: a web copy of larger marks
            wid_s = max(wid_s, MIN_LINE_PX * 25.4 / dpi / res.line_width_mm * 1.02)
            arm_s = max(arm_s, MIN_ARM_PX * 25.4 / dpi / res.arm_length_mm * 1.02)
            lw_mm, arm_mm = res.line_width_mm * wid_s, res.arm_length_mm * arm_s
            need = max(MIN_LINE_PX / lw_mm, MIN_ARM_PX / arm_mm) * 25.4
    elif on["dpi<400"]:
        dpi = rng.uniform(200, 400)
    elif on["dpi>=2000"]:
        dpi = rng.uniform(2000, 3200)
    else:
        dpi = rng.uniform(400, 2000)
    if dpi < need:
        dpi = need * rng.uniform(1.0, 1.3)
        if on["dpi<400"] and dpi >= 400:
            on["dpi<400"] = False
    if dpi >= 2000:
        on["dpi>=2000"] = True
    ppm = dpi / 25.4
    contrast = rng.uniform(0.06, 0.15) if on["low-contrast"] else rng.uniform(0.25, 0.6)
    background = rng.uniform(max(contrast + 0.1, 0.6), 0.95)
    scene = "busy" if on["busy"] else ("texture" if rng.uniform() < 0.7 else "none")
    polarity = "negative" if (on["negative"] or on["colour-negative"]) else "positive"
    rgb = on["rgb"] or on["colour-negative"]
    bits = 16 if on["16-bit"] else 8
    jpeg = (int(rng.integers(40, 96)) if on["jpeg"] else int(rng.integers(40, 76))
            if on["web-copy"] else None)

    # -- the part of the frame shown: crops in film mm, as a (left, top, right, bottom) crop
    # of the unturned scan (the turn is applied to the crop below)
    margin = rng.uniform(0.5, 0.1 * min(fw, fh)) if on["off-centre"] else 1.0
    offset = (rng.uniform(-0.1, 0.1, 2) * np.array([fw, fh]) * ppm if on["off-centre"]
              else np.zeros(2))
    pitch = np.array([res.pitch_x, res.pitch_y])
    n = np.array([res.cols, res.rows])
    half_span = (n - 1) / 2 * pitch  # film mm of the outer crosses
    lo_keep, hi_keep = -half_span.copy(), half_span.copy()  # film region kept (x, y)

    def keep_block(k: np.ndarray):
        """Keep a block of k (cols, rows) crosses reaching the frame's edge on at least one
        side of each axis (without a frame edge a part of a lattice has no row/col)."""
        start = np.array([0 if rng.uniform() < 0.5 else n[a] - k[a] for a in range(2)])
        lo = -half_span + start * pitch - 0.5 * pitch
        hi = -half_span + (start + k - 1) * pitch + 0.5 * pitch
        return lo, hi

    if on["half-frame"]:
        k = n.copy()
        a = int(rng.integers(2))
        k[a] = max(3, (n[a] + 1) // 2)
        lo_keep, hi_keep = keep_block(k)
    elif on["quarter-frame"]:
        lo_keep, hi_keep = keep_block(np.maximum(3, (n + 1) // 2))
    elif on["crop"]:  # cut through random rows / cols on one side of each axis or none
        for a in range(2):
            if rng.uniform() < 0.75 and n[a] >= 5:
                cut = rng.uniform(0.0, 0.6) * (n[a] - 1) * pitch[a]
                if rng.uniform() < 0.5:
                    lo_keep[a] = -half_span[a] + cut
                else:
                    hi_keep[a] = half_span[a] - cut
    # a pixel budget: large formats at high dpi are swept as a part of the frame
    area_px = lambda lo, hi: np.prod((hi - lo + 2 * (arm_mm + 2)) * ppm)  # noqa: E731
    tries = 0
    while area_px(lo_keep, hi_keep) > MAX_PIXELS and tries < 20:
        k = np.maximum(3, np.round((hi_keep - lo_keep) / pitch * 0.7).astype(int))
        lo_keep, hi_keep = keep_block(np.minimum(k, n))
        tries += 1
    full = np.all(lo_keep <= -half_span) and np.all(hi_keep >= half_span)
    if full:
        crop = (0.0, 0.0, 0.0, 0.0)
    else:
        # crop of the scan in film-aligned mm: the scan is the format plus the margin
        # centred; film x right, film y up (top = +y). Leave the kept crosses' arms whole
        # (a rotation of up to 5 degrees moves an edge cross by 5 % of the kept span)
        slack = arm_mm / 2 + 4 * blur / ppm + 0.06 * (hi_keep - lo_keep).max()
        ex, ey = fw / 2 + margin, fh / 2 + margin
        # where the part reaches the grid's outer crosses the scan keeps the frame's edge
        # (and the margin beyond it): the edge is what names the rows and columns
        lo_out, hi_out = lo_keep <= -half_span + 1e-9, hi_keep >= half_span - 1e-9
        left = 0.0 if lo_out[0] else max(0.0, ex + lo_keep[0] - slack)
        right = 0.0 if hi_out[0] else max(0.0, ex - hi_keep[0] - slack)
        bottom = 0.0 if lo_out[1] else max(0.0, ey + lo_keep[1] - slack)
        top = 0.0 if hi_out[1] else max(0.0, ey - hi_keep[1] - slack)
        crop = (left, top, right, bottom)
        offset = np.zeros(2)  # a part of the frame is off-centre anyway
    crop = _turn_crop(crop, turn)
    if any(c > 0 for c in crop) and not (on["half-frame"] or on["quarter-frame"]):
        on["crop"] = True

    # the rows and columns of the part shown (whole crosses: the kept block), film y up and
    # row 0 at the top
    c_lo = int(np.ceil((lo_keep[0] + half_span[0]) / pitch[0] - 1e-9))
    c_hi = int(np.floor((hi_keep[0] + half_span[0]) / pitch[0] + 1e-9))
    r_lo = int(np.ceil((half_span[1] - hi_keep[1]) / pitch[1] - 1e-9))
    r_hi = int(np.floor((half_span[1] - lo_keep[1]) / pitch[1] + 1e-9))
    part = (max(c_lo, 0), min(c_hi, res.cols - 1) + 1, max(r_lo, 0), min(r_hi, res.rows - 1) + 1)
    n_dark = ()
    shown = part[3] - part[2]
    if on["dark-rows"]:
        r0 = int(rng.integers(0, res.rows))
        r1 = min(res.rows - 1, r0 + int(rng.integers(0, max(1, res.rows // 3))))
    if on["dark-rows"] and shown > 3:
        # the band over rows the scan shows, leaving at least 3 of them exposed (fewer than
        # 3 x 3 visible crosses is not a scan the detector is asked to name)
        k = min(r1 - r0 + 1, shown - 3)
        a = part[2] + (r0 - part[2]) % (shown - k + 1)
        n_dark = ((a, a + k - 1),)
    else:
        on["dark-rows"] = False
    dark_level = 0.0 if rng.uniform() < 0.6 else rng.uniform(0.3, 0.5)
    spec = ScanSpec(
        dpi=float(dpi), polarity=polarity, blur_sigma_px=float(blur),
        noise_sigma=float(rng.uniform(0.003, 0.015)), grain_sigma=0.0,
        contrast=float(contrast), background=float(background), scene=scene,
        deform_um=float(rng.uniform(0, 40)), shrink_ppm=float(rng.uniform(-500, 1500)),
        rotation_deg=float(turn + rot), offset_px=(float(offset[0]), float(offset[1])),
        anisotropy_ppm=float(aniso),
        dust=int(rng.integers(20, 120)) if on["dust"] else 0,
        scratches=int(rng.integers(2, 8)) if on["scratches"] else 0,
        crop_mm=tuple(float(c) for c in crop), margin_mm=float(margin), bits=bits, rgb=rgb,
        mark_arm_scale=float(arm_s), mark_width_scale=float(wid_s),
        mark_opacity=float(opacity),
        centre_scale=2.0 if on["centre-cross"] else 1.0,
        one_armed=int(rng.integers(1, 4)) if on["one-armed"] else 0,
        dark_rows=n_dark, dark_level=float(dark_level),
    ).validate()
    conds = tuple(c for c in CONDITIONS if on[c]) + (f"layout:{cam.name}",)
    return Case(int(seed), cam.name, spec, float(turn), jpeg, conds, part)


def _turn_crop(crop, turn: int):
    """A (left, top, right, bottom) crop of the unturned scan as the turned scan's crop."""
    l, t, r, b = crop
    k = (int(round(turn / 90.0)) % 4)
    for _ in range(k):  # one counter-clockwise quarter turn on screen: left -> bottom, ...
        l, t, r, b = t, r, b, l
    return (l, t, r, b)


# ---------------------------------------------------------------------------------------------
# running and scoring


def _jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """The image after a JPEG round trip (OpenCV, 4:2:0 for RGB)."""
    bgr = img[..., ::-1] if img.ndim == 3 else img
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover
        raise RuntimeError("JPEG encoding failed")
    out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return out[..., ::-1].copy() if out.ndim == 3 else out


def _grey(img: np.ndarray) -> np.ndarray:
    a = img.astype(np.float32) / np.float32(np.iinfo(img.dtype).max)
    return a @ np.array([0.299, 0.587, 0.114], np.float32) if a.ndim == 3 else a


@dataclass
class Score:
    """How one detection compares with its truth (counts, and per measured cross the error
    and its bound). Errors in px, pixel system; ``err2`` is ``(ex^2 + ey^2) / 2`` for a
    cross and the squared error across the bar for a one-armed cross."""

    result: bool = False
    error: str = ""
    visible: int = 0
    measured: int = 0
    missed: list = field(default_factory=list)
    wrong: list = field(default_factory=list)
    gross: list = field(default_factory=list)
    claimed: list = field(default_factory=list)
    err2: list = field(default_factory=list)
    crb2: list = field(default_factory=list)
    err2_1: list = field(default_factory=list)
    crb2_1: list = field(default_factory=list)
    z2: list = field(default_factory=list)
    z2_along: list = field(default_factory=list)
    seconds: float = 0.0
    ambiguous_truth: str = ""
    ids_ambiguous: bool = False
    ambiguous: list = field(default_factory=list)
    # detectability (:func:`mark_snr`; empty when the score had no SNR): per measured visible
    # cross [snr, threshold, err2, bound^2], per missed one [snr, threshold]; why the render
    # cannot be asked for a result ('' when it can); gross measurements below detection
    snr_scored: bool = False
    snr_measured: list = field(default_factory=list)
    snr_missed: list = field(default_factory=list)
    below_detection: str = ""
    claimed_below: list = field(default_factory=list)

    def to_dict(self) -> dict:
        rms = math.sqrt(np.mean(self.err2)) if self.err2 else float("nan")
        crb = math.sqrt(np.mean(self.crb2)) if self.crb2 else float("nan")
        return {"result": self.result, "error": self.error, "visible": self.visible,
                "measured": self.measured, "missed": self.missed, "wrong": self.wrong,
                "gross": self.gross, "claimed": self.claimed, "rms_px": rms, "crb_px": crb,
                "z_rms": math.sqrt(np.mean(self.z2)) if self.z2 else float("nan"),
                "seconds": self.seconds, "ambiguous_truth": self.ambiguous_truth,
                "ids_ambiguous": self.ids_ambiguous, "ambiguous": self.ambiguous,
                **({"snr_measured": _rounded(self.snr_measured),
                    "snr_missed": _rounded(self.snr_missed),
                    "below_detection": self.below_detection,
                    "claimed_below": self.claimed_below} if self.snr_scored else {}),
                # what the per-condition pools need (count, sum), for merging runs
                "pool": {k: [len(v), float(np.sum(v))] for k, v in (
                    ("err2", self.err2), ("crb2", self.crb2), ("err2_1", self.err2_1),
                    ("crb2_1", self.crb2_1), ("z2", self.z2), ("z2_along", self.z2_along))}}

    @classmethod
    def from_dict(cls, d: dict) -> "Score":
        """A score from :meth:`to_dict` (each pooled list as its count times its mean: the
        per-condition figures of :func:`aggregate` are the same)."""
        sc = cls(**{k: d[k] for k in ("result", "error", "visible", "measured", "missed",
                                      "wrong", "gross", "claimed", "seconds",
                                      "ambiguous_truth", "ids_ambiguous", "ambiguous")})
        for k, (n, tot) in d["pool"].items():
            setattr(sc, k, [tot / n] * n if n else [])
        if "snr_measured" in d:  # a log written with the detectability fields
            sc.snr_scored = True
            for k in ("snr_measured", "snr_missed", "below_detection", "claimed_below"):
                setattr(sc, k, d[k])
        return sc


def _rounded(rows: list) -> list:
    """Per-cross rows for the log, 6 significant digits."""
    return [[float(f"{v:.6g}") for v in r] for r in rows]


def _render_noise(truth: dict, jpeg_rms: float) -> float:
    """The render's white-noise standard deviation (grey, full scale 1): its noise, the
    quantisation (``LSB^2 / 12``) and the JPEG loss at the marks, added in quadrature."""
    from softplot.marks.crb import effective_noise

    r = truth["render"]
    return math.sqrt(effective_noise(r["noise_sigma"], truth["bit_depth"]) ** 2 + jpeg_rms**2)


def _visible_marks(truth: dict, jpeg_rms: float) -> tuple[float, float, list[dict], np.ndarray]:
    """The render's pixels per mm, its white noise (:func:`_render_noise`), its visible reseau
    crosses (truth entries, pixel system) and their pixel -> mark-frame affines (K, 2, 2),
    :func:`_mark_affines` (empty when no cross is visible)."""
    ppm = truth["dpi"] / 25.4
    noise = _render_noise(truth, jpeg_rms)
    vis = [m for m in truth["marks"] if m["kind"] == "reseau" and m["state"] == "visible"]
    A = _mark_affines(truth, vis) if vis else np.zeros((0, 2, 2))
    return ppm, noise, vis, A


def _mark_affines(truth: dict, marks: list[dict]) -> np.ndarray:
    """(N, 2, 2) pixel -> mark-frame affine of each of ``marks`` (mark frame: u along film x,
    v along film -y, nominal px; from the truth mapping's Jacobian at the cross)."""
    ppm = truth["dpi"] / 25.4
    mp = TruthMapping.from_truth(truth)
    film = np.array([[m["film_x"], m["film_y"]] for m in marks])
    return np.linalg.inv(mp.jacobian(film) @ np.diag([1.0 / ppm, -1.0 / ppm]))


def _bounds(case: Case, truth: dict, img_grey: np.ndarray | None, jpeg_rms: float) -> dict:
    """Cramer-Rao bound (px) of every visible cross: ``{name: bound}``.

    The bound of LSM's model (:mod:`softplot.marks.crb`) for the cross as drawn (its true arm
    length and line width, the mapping's local affine), the render's blur and noise
    (quantisation and the JPEG loss, measured on the render, added as white noise). Over a
    busy scene the bound is :func:`softplot.marks.crb.render_crb` against the scene each
    cross hides (a second render without marks); otherwise the flat-background bound at the
    cross's local contrast. For a one-armed cross it is the bound of one axis of the whole
    cross, i.e. across its bar (the other bar adds nothing across this one).
    """
    from softplot.marks.crb import centre_crb, render_crb
    from softplot.marks.template import MarkShape

    r = truth["render"]
    ppm, noise, vis, A = _visible_marks(truth, jpeg_rms)
    if not vis:
        return {}
    out = {}
    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(vis):
        groups.setdefault((round(m["arm_length_mm"], 9), round(m["line_width_mm"], 9)),
                          []).append(i)
    blur = r["blur_sigma_px"]
    for (arm, lw), idx in groups.items():
        shape = MarkShape("cross", length=arm * ppm, width=lw * ppm)
        if case.spec.scene == "busy" and img_grey is not None:
            xy = np.array([[vis[i]["x"], vis[i]["y"]] for i in idx])
            b = render_crb(img_grey, xy, A[idx], shape, blur, r["mark_level"], noise)
            for i, v in zip(idx, b, strict=True):
                if np.isfinite(v):
                    out[vis[i]["name"]] = float(v)
        a0 = np.mean(A[idx], axis=0)
        unit = centre_crb(shape, blur, 1.0, noise, A=a0, phases=2)
        for i in idx:
            c = abs(vis[i]["contrast"])
            out.setdefault(vis[i]["name"], unit / max(c, 1e-6))
    return out


def _mark_template(length: float, width: float, blur: float, A: np.ndarray,
                   axis: str | None = None, phases: int = 4,
                   offsets: np.ndarray | None = None) -> np.ndarray:
    """The blurred cross (or one bar of it) as the render draws it, on the pixel grid:
    ``(phases, n, n)`` values in [0, 1] (1 on the mark), each plane a square of pixels
    (pixel system, rows down) around the centre at one sub-pixel phase.

    ``length``, ``width``: tip-to-tip bar length and line width (px in the mark frame);
    ``blur``: Gaussian sigma (px) of the scanner, the square pixel footprint added as in LSM's
    model (:mod:`softplot.marks.template`); ``A``: the pixel -> mark-frame affine; ``axis``:
    None for a cross, "x" / "y" for the bar along film x / y of a one-armed cross;
    ``offsets``: (phases, 2) the centres' x, y (pixel system) from the planes' middle pixel,
    in [-0.5, 0.5] (None: ``phases`` seeded random phases).
    """
    from softplot.marks.template import aperture, box_pixel_profile, box_profile

    grow = 1.0 / max(float(np.linalg.svd(A, compute_uv=False).min()), 1e-3)
    half = int(np.ceil(0.5 * length * grow + 5 * blur + 4))
    yy, xx = np.mgrid[-half: half + 1, -half: half + 1].astype(np.float64)
    ph = (np.random.default_rng(0).uniform(-0.5, 0.5, (phases, 2)) if offsets is None
          else np.asarray(offsets, float).reshape(-1, 2))
    dx = xx[None] - ph[:, 0, None, None]
    dy = yy[None] - ph[:, 1, None, None]
    u = A[0, 0] * dx + A[0, 1] * dy
    v = A[1, 0] * dx + A[1, 1] * dy
    bu, mu, bv, mv = (float(q) for q in aperture(A))
    s_len = math.sqrt(blur * blur + 1.0 / 12.0)
    Lu, Lv = (box_profile(t, length, s_len)[0].astype(float) for t in (u, v))
    Wu = box_pixel_profile(u, width, blur, bu, mu)[0].astype(float)
    Wv = box_pixel_profile(v, width, blur, bv, mv)[0].astype(float)
    if axis == "x":
        return Lu * Wv
    if axis == "y":
        return Wu * Lv
    return Lu * Wv + Wu * Lv - Wu * Wv


def _template_energy(T: np.ndarray) -> tuple[float, float]:
    """``(sum T^2, sqrt(det Lambda))`` of :func:`_mark_template`'s planes (mean over the
    phases): the matched filter's signal energy per unit contrast, and the roughness of its
    output under white noise, ``Lambda = sum(grad T grad T^T) / sum T^2`` (px^-2, pixel
    system): the covariance of the gradient of the normalised correlation map."""
    gy, gx = np.gradient(T, axis=(1, 2))
    e = float(np.mean(np.sum(T * T, axis=(1, 2))))
    lam = np.array([[np.mean(np.sum(a * b, axis=(1, 2))) for b in (gx, gy)]
                    for a in (gx, gy)]) / e
    return e, math.sqrt(max(float(np.linalg.det(lam)), 0.0))


def mark_snr(truth: dict, jpeg_rms: float = 0.0,
             scene: np.ndarray | None = None) -> dict[str, tuple[float, float, float]]:
    """Matched-filter signal-to-noise ratio of every visible reseau cross of a render and the
    ratios it must reach to be detectable: ``{name: (snr, threshold in its cell, threshold in
    the whole scan)}``.

    ``snr = |contrast| sqrt(sum T^2) / sigma``: the noise-free mark as rendered (its true arm
    length and line width, one bar of a one-armed cross, the render's blur and pixel
    footprint, the mapping's local affine, :func:`_mark_template`; the truth's local contrast)
    against the render's white noise (its noise, quantisation and the JPEG loss at the marks,
    :func:`_render_noise`). It is the output of the ideal detector that knows everything but
    the noise: no detector sees the cross better. The thresholds are
    :func:`detection_threshold` over the cross's cell (a disc of a quarter pitch around it:
    where the score takes a measurement for this cross) and over the whole scan.

    ``scene``: the render's grey scene without marks, unclipped (pixel system, as
    :func:`render_case` gives it for a busy render). With it the ratio counts only the signal
    that survives in the stored scan: it is scaled by :func:`surviving_signal`, the share of
    the mark's signal that the scan's clipping to its grey range leaves (a cross on a white
    road saturated in the scan shows little or nothing of its darkening).
    """
    ppm, noise, vis, A = _visible_marks(truth, jpeg_rms)
    if not vis:
        return {}
    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(vis):
        key = (round(m["arm_length_mm"], 9), round(m["line_width_mm"], 9),
               m.get("arm_axis") if m["arms"] == 1 else None)
        groups.setdefault(key, []).append(i)
    blur = truth["render"]["blur_sigma_px"]
    cell = math.pi * (0.25 * _pitch_px(truth)) ** 2
    scan = float(truth["width"]) * float(truth["height"])
    out = {}
    for (arm, lw, axis), idx in groups.items():
        T = _mark_template(arm * ppm, lw * ppm, blur, np.mean(A[idx], axis=0), axis)
        e, rough = _template_energy(T)
        t_cell, t_scan = detection_threshold(np.array([cell, scan]), rough)
        share = (np.ones(len(idx)) if scene is None else
                 surviving_signal(truth, scene, [vis[i] for i in idx], A[idx]))
        for i, f in zip(idx, share, strict=True):
            snr = abs(vis[i]["contrast"]) * math.sqrt(e) * f / noise
            out[vis[i]["name"]] = (float(snr), float(t_cell), float(t_scan))
    return out


def surviving_signal(truth: dict, scene: np.ndarray, marks: list[dict],
                     A: np.ndarray) -> np.ndarray:
    """The share of each cross's signal that survives in the stored scan: ``(K,)`` in [0, 1].

    ``scene``: the render's grey scene without marks, unclipped and noise-free (pixel
    system); ``marks``: truth entries of crosses of one shape (pixel system), ``A`` their
    pixel -> mark-frame affines (K, 2, 2). The render draws a cross over the scene ``S`` as
    ``M = S + (mark_level - S) opacity T`` (``T`` :func:`_mark_template` at the cross's own
    sub-pixel position) and the scanner stores both clipped to its grey range ``[0, top]``:
    the share is ``||clip(M) - clip(S)|| / ||M - S||`` over the cross's square. 1 where
    nothing clips. ``top`` is the grey of full scale in every channel (the luma of the orange
    mask for a masked negative): a grey approximation of per-channel clipping. Quantisation is
    not applied: it is in the noise the ratio is taken against (``LSB^2 / 12``), and the
    noise dithers it. Crosses whose square leaves the scan are taken over the part inside.
    """
    from softplot.synthetic.scan import LUMA

    r, ppm = truth["render"], truth["dpi"] / 25.4
    mask = r.get("orange_mask")
    top = float(np.dot(LUMA, mask)) if mask else 1.0
    op = float(truth.get("spec", {}).get("mark_opacity", 1.0))
    m0 = marks[0]
    xy = np.array([[m["x"], m["y"]] for m in marks])
    c = np.round(xy).astype(int)
    T = _mark_template(m0["arm_length_mm"] * ppm, m0["line_width_mm"] * ppm,
                       r["blur_sigma_px"], np.mean(A, axis=0),
                       m0.get("arm_axis") if m0["arms"] == 1 else None,
                       offsets=xy - c)
    h = T.shape[1] // 2
    H, W = scene.shape
    out = np.ones(len(marks))
    for k, (x, y) in enumerate(c):
        y0, y1, x0, x1 = max(y - h, 0), min(y + h + 1, H), max(x - h, 0), min(x + h + 1, W)
        if y0 >= y1 or x0 >= x1:
            continue
        S = scene[y0:y1, x0:x1].astype(np.float64)
        t = T[k, y0 - (y - h): y1 - (y - h), x0 - (x - h): x1 - (x - h)]
        M = S + (r["mark_level"] - S) * op * t
        full = float(np.sum((M - S) ** 2))
        if full > 0:
            kept = np.clip(M, 0.0, top) - np.clip(S, 0.0, top)
            out[k] = math.sqrt(float(np.sum(kept * kept)) / full)
    return out


#: false-alarm probability (in the area searched) and detection probability of
#: :func:`detection_threshold`: a cross at the threshold is found half the time, a noise peak
#: passes for it once in a hundred searches
P_FALSE_ALARM = 0.01
P_DETECT = 0.5


def detection_threshold(area_px, roughness: float, p_fa: float = P_FALSE_ALARM,
                        p_d: float = P_DETECT) -> np.ndarray:
    """The signal-to-noise ratio a mark needs for the ideal matched filter, searching an area
    of ``area_px`` pixels for it, to find it with probability ``p_d`` at a false-alarm
    probability ``p_fa`` (per search).

    Over white noise the filter's normalised output is a smooth Gaussian field of unit
    variance whose gradient has the covariance ``Lambda`` (``roughness = sqrt(det Lambda)``,
    px^-2, :func:`_template_energy`). The chance that its maximum over the area exceeds ``u``
    is, for the levels of interest, the expected Euler characteristic of the excursion set
    (Adler 1981; Worsley 1996)::

        P(max > u) ~ Q(u) + area * roughness * u * exp(-u^2 / 2) / (2 pi)^(3/2)

    (``Q`` the normal tail). ``u`` solves ``P = p_fa``; a mark of ratio ``snr`` peaks at
    ``snr + N(0, 1)``, so it is found with probability ``p_d`` at ``snr = u + z(p_d)``.
    ``area_px``: a number or an array (the result has its shape).
    """
    from scipy.special import ndtr, ndtri

    area = np.asarray(area_px, float)
    lo, hi = np.zeros_like(area), np.full_like(area, 40.0)
    for _ in range(60):  # bisection: P(max > u) falls with u
        u = 0.5 * (lo + hi)
        p = ndtr(-u) + area * roughness * u * np.exp(-0.5 * u * u) / (2 * math.pi) ** 1.5
        lo, hi = np.where(p > p_fa, u, lo), np.where(p > p_fa, hi, u)
    return 0.5 * (lo + hi) + ndtri(p_d)


def _pitch_px(truth: dict) -> float:
    """The grid's pitch in the render (px): the median distance from a reseau cross to its
    nearest neighbour (pixel system truth positions)."""
    from scipy.spatial import cKDTree

    txy = np.array([[m["x"], m["y"]] for m in truth["marks"] if m["kind"] == "reseau"])
    if len(txy) < 2:
        return 1e9
    return float(np.median(cKDTree(txy).query(txy, k=2)[0][:, 1]))


def detectable_render(truth: dict, snr: dict) -> str:
    """Why no detector can be asked for a result on this render ('' when it can): it shows
    fewer than 3 x 3 visible crosses, or fewer than 3 x 3 of them are detectable in their
    cells, or none is detectable in a search of the whole scan (before any cross is found,
    nothing says where the grid lies). ``snr``: :func:`mark_snr`."""
    vis = [m for m in truth["marks"] if m["kind"] == "reseau" and m["state"] == "visible"
           and m["name"] in snr]
    rows, cols = {m["row"] for m in vis}, {m["col"] for m in vis}
    if len(vis) < 9 or len(rows) < 3 or len(cols) < 3:
        return f"fewer than 3 x 3 visible crosses ({len(rows)} rows, {len(cols)} cols)"
    if not any(snr[m["name"]][0] >= snr[m["name"]][2] for m in vis):
        best = max(vis, key=lambda m: snr[m["name"]][0] - snr[m["name"]][2])["name"]
        return (f"no cross detectable in a search of the whole scan (best SNR "
                f"{snr[best][0]:.1f} < {snr[best][2]:.1f})")
    det = [m for m in vis if snr[m["name"]][0] >= snr[m["name"]][1]]
    rows, cols = {m["row"] for m in det}, {m["col"] for m in det}
    if len(det) < 9 or len(rows) < 3 or len(cols) < 3:
        return (f"fewer than 3 x 3 detectable crosses ({len(det)} of {len(vis)} visible above "
                f"their SNR threshold: {len(rows)} rows, {len(cols)} cols)")
    return ""


def identifiable(truth: dict, snr: dict | None = None) -> str:
    """Why the render cannot show which rows and columns it holds ('' when it can).

    A scan names its crosses when it shows at least 3 x 3 visible crosses (truth state
    "visible": inside the scan, with contrast; damaged ones count, their arms are mostly
    there) and, on each axis, an end line of the grid (row 0 or the last row; column 0 or
    the last column) with a visible cross *and* the film format's edge beyond that line inside
    the scan: only then does the image say where the grid ends. A part of the lattice without
    such an edge on an axis could be any part of the grid, unless it shows every row (col) of
    the grid. A flat dark region that exposes nothing over the only end row shown hides both
    the row and the edge (its crosses are "dark").

    With ``snr`` (:func:`mark_snr`) the crosses must also be detectable: a render whose
    crosses lie below detection (:func:`detectable_render`) cannot show anything.
    """
    rs = [m for m in truth["marks"] if m["kind"] == "reseau"]
    if not rs:
        return ""
    if snr is not None and (why := detectable_render(truth, snr)):
        return why
    nr = max(m["row"] for m in rs) + 1
    nc = max(m["col"] for m in rs) + 1
    vis = [m for m in rs if m["state"] == "visible"]
    rows = {m["row"] for m in vis}
    cols = {m["col"] for m in vis}
    if len(vis) < 9 or len(rows) < 3 or len(cols) < 3:
        return f"fewer than 3 x 3 visible crosses ({len(rows)} rows, {len(cols)} cols)"
    mp = TruthMapping.from_truth(truth)
    fw, fh = truth["format_mm"]
    W, H = truth["width"], truth["height"]

    def edge_shown(line: list[dict], key: str, side: float) -> bool:
        """Is the format's edge beyond this end line inside the scan (along its crosses)?"""
        if not line:
            return False
        if key == "row":  # an edge at film y = side * fh / 2, along the line's film x
            t = np.array([m["film_x"] for m in line])
            pts = np.column_stack([t, np.full(len(t), side * fh / 2)])
        else:
            t = np.array([m["film_y"] for m in line])
            pts = np.column_stack([np.full(len(t), side * fw / 2), t])
        p = mp.film_to_pixel(pts)
        return bool(np.any((p[:, 0] >= 1) & (p[:, 0] <= W - 2) & (p[:, 1] >= 1)
                           & (p[:, 1] <= H - 2)))

    why = []
    for key, sides in (("row", ((0, 1.0), (nr - 1, -1.0))),
                       ("col", ((0, -1.0), (nc - 1, 1.0)))):
        # every row (col) of the grid seen: no other numbering fits
        ok = {m[key] for m in vis} >= set(range(sides[1][0] + 1))
        for idx, side in sides:
            line = [m for m in vis if m[key] == idx]
            ok |= edge_shown(line, key, side)
        if not ok:
            why.append(f"no frame edge shown beside a visible end {key}")
    return "; ".join(why)


def ids_flagged(det) -> bool:
    """Does the detection say that its rows and columns are ambiguous? (``ids_ambiguous``,
    or a warning saying so.)"""
    flag = getattr(det, "ids_ambiguous", None)
    if flag is not None:
        return bool(flag)
    return any("could be several" in w or "ambiguous" in w
               for w in getattr(det, "warnings", []) or [])


def score(det, truth: dict, bounds: dict, ambiguous: str = "", snr: dict | None = None) -> Score:
    """Compare a :class:`softplot.marks.result.Detection` with the truth (see :class:`Score`).

    * visible: truth state "visible" and not touched by dust or a scratch (``damaged``);
    * wrong row/col: a measured cross on another visible cross's truth (within a quarter
      pitch of it) or more than a quarter pitch from its own;
    * gross: measured more than ``max(1 px, 8 x its bound)`` from its own truth (not wrong;
      listed, and in the RMS like every other measured cross);
    * claimed: measured where the truth has no cross to see (dark, covered, outside) and not
      on another cross;
    * one-armed (the truth's, or a lone bar the detection measured on a cross): the error
      across the bar against the bound, and along it the normalised error (``z2_along``).

    ``ambiguous`` (:func:`identifiable`'s reason) says that the render cannot show its rows
    and columns. If the detection then says so too (:func:`ids_flagged`), a cross measured on
    another visible cross's position is scored as a measurement of that cross and listed in
    ``ambiguous``, not as a wrong row/col; a detection that does not say so has guessed, and
    its wrong names count.

    ``snr`` (:func:`mark_snr`) adds, for every visible cross, its signal-to-noise ratio and
    detection threshold (``snr_measured`` with the error and bound, ``snr_missed``), says
    whether the render can be asked for a result at all (``below_detection``,
    :func:`detectable_render`) and lists a gross measurement of a cross below detection in
    ``claimed_below`` too (a peak of the noise named as the cross). The other fields do not
    change with it.
    """
    sc = Score(result=True, ambiguous_truth=ambiguous, ids_ambiguous=ids_flagged(det))
    if snr is not None:
        sc.snr_scored = True
        sc.below_detection = detectable_render(truth, snr)
    tm = {m["name"]: m for m in truth["marks"]}
    rs = [m for m in truth["marks"] if m["kind"] == "reseau"]
    txy = np.array([[m["x"], m["y"]] for m in rs])
    mp = TruthMapping.from_truth(truth)
    pitch_px = _pitch_px(truth)
    amb_ok = bool(ambiguous) and sc.ids_ambiguous
    cov = getattr(det, "cov", None)
    names = list(det.name)
    status = {}
    done: set[str] = set()
    for i, name in enumerate(names):
        if det.kind[i] != "reseau":
            continue
        t = tm[name]
        vis = t["state"] == "visible" and not t["damaged"]
        sc.visible += vis
        status[name] = f"{det.status[i]} {det.reason[i]}".strip()
        measured = det.status[i] == "measured" and bool(np.all(np.isfinite(det.xy[i])))
        if not measured:
            continue
        d_all = np.hypot(*(txy - det.xy[i]).T)
        j = int(np.argmin(d_all))
        near = d_all[j] <= 0.25 * pitch_px
        if rs[j]["name"] == name and near:
            if t["arms"] == 0:  # found where nothing is to be seen
                sc.claimed.append(f"{name} ({t['state']})")
                continue
        elif near and rs[j]["arms"] > 0:  # on another cross: named wrong
            if not amb_ok:
                sc.wrong.append(f"{name} measured at {rs[j]['name']} "
                                f"({np.hypot(*(det.xy[i] - (t['x'], t['y']))):.1f} px off)")
                continue
            sc.ambiguous.append(f"{name} at {rs[j]['name']}")
            t = rs[j]  # an ambiguous name, declared: scored as the cross it is on
        elif t["arms"] == 0:
            sc.claimed.append(f"{name} ({t['state']})")
            continue
        else:
            sc.wrong.append(f"{name} measured {np.hypot(*(det.xy[i] - (t['x'], t['y']))):.1f}"
                            f" px from its own, nearest {rs[j]['name']}")
            continue
        if t["state"] != "visible" or t["damaged"] or t["name"] in done:
            continue  # cut or damaged: neither counted nor scored
        done.add(t["name"])
        e = np.asarray(det.xy[i], float) - (t["x"], t["y"])
        b = bounds.get(t["name"], float("nan"))
        gross = bool(np.hypot(*e) > max(1.0, 8.0 * b if np.isfinite(b) else 1.0))
        if gross:  # listed, and scored
            sc.gross.append(f"{t['name']} {np.hypot(*e):.2f} px off (bound {b:.3f})")
        sc.measured += 1
        C = (np.asarray(cov[i], float).reshape(2, 2) if cov is not None
             else np.diag(np.square(np.asarray(det.sigma_xy[i], float))))
        lone = int(getattr(det, "arms", [2] * len(names))[i]) == 1
        if t["arms"] == 1:  # across the bar only
            along = mp.jacobian(np.array([[t["film_x"], t["film_y"]]]))[0][:, 0 if
                                                                           t["arm_axis"] == "x"
                                                                           else 1]
            nrm = np.array([-along[1], along[0]]) / np.hypot(*along)
            _along_z(sc, e, C, along / np.hypot(*along))
            ea = float(e @ nrm)
            _note_snr(sc, snr, t["name"], ea * ea, b, gross)
            if np.isfinite(b):
                sc.err2_1.append(ea * ea)
                sc.crb2_1.append(b * b)
            var = float(nrm @ C @ nrm)
            if var > 0:
                sc.z2.append(ea * ea / var)
        else:
            if lone:  # a lone bar measured on a cross: along it, the neighbours' guess
                _along_z(sc, e, C, _lone_bar(det, i))
            _note_snr(sc, snr, t["name"], float(e @ e) / 2, b, gross)
            if np.isfinite(b):
                sc.err2.append(float(e @ e) / 2)
                sc.crb2.append(b * b)
            if np.isfinite(C).all() and np.linalg.det(C) > 0 and C[0, 0] > 0:
                sc.z2.append(float(e @ np.linalg.solve(C, e)) / 2)  # e^T C^-1 e / 2
    for m in rs:  # visible crosses no measurement sits on
        if m["state"] == "visible" and not m["damaged"] and m["name"] not in done:
            sc.missed.append(f"{m['name']}: {status.get(m['name'], 'not listed')}")
            if snr is not None and m["name"] in snr:
                sc.snr_missed.append(list(snr[m["name"]][:2]))
    return sc


def _note_snr(sc: Score, snr: dict | None, name: str, err2: float, bound: float,
              gross: bool) -> None:
    """A measured visible cross's ``[snr, threshold, err2, bound^2]`` into
    ``sc.snr_measured`` (``err2`` as in :class:`Score`, px^2), and its name into
    ``sc.claimed_below`` when it lies below detection and is gross: what the detector named
    there is noise, not the cross."""
    if snr is None or name not in snr:
        return
    ratio, thr = snr[name][:2]
    sc.snr_measured.append([ratio, thr, err2, bound * bound])
    if gross and (ratio < thr or sc.below_detection):
        sc.claimed_below.append(f"{name} (SNR {ratio:.1f} < {thr:.1f})")


def _lone_bar(det, i: int) -> np.ndarray | None:
    """The unit vector (pixel system) of the bar the detection measured mark ``i`` by
    (``Detection.bar``); None where it does not say."""
    bar = getattr(det, "bar", None)
    if bar is None or not np.isfinite(bar[i]).all():
        return None
    b = np.asarray(bar[i], float)
    return b / np.hypot(*b)


def _along_z(sc: Score, e: np.ndarray, C: np.ndarray, along: np.ndarray | None) -> None:
    """The squared normalised error along a bar (its unit vector ``along``, pixel system; None,
    a detection that does not say which bar: the axis along which the covariance ``C`` is
    largest) into ``sc.z2_along``:
    a one-armed cross's position along its bar must be no more certain than it is."""
    if not np.isfinite(C).all():
        return
    if along is None:
        along = np.linalg.eigh(C)[1][:, -1]
    var = float(along @ C @ along)
    if var > 0:
        sc.z2_along.append(float(e @ along) ** 2 / var)


def _loss_at_marks(diff: np.ndarray, truth: dict) -> float:
    """RMS of ``diff`` (grey, pixel system) over the windows of the visible crosses (each
    the square around the drawn cross plus 3 px): the JPEG loss where the marks are measured
    (it concentrates at edges, so the whole image's would understate it)."""
    h, w = diff.shape
    acc, n = 0.0, 0
    ppm = truth["dpi"] / 25.4
    for m in truth["marks"]:
        if m["state"] != "visible" or not m.get("arm_length_mm"):
            continue
        r = int(math.ceil(m["arm_length_mm"] / 2 * ppm)) + 3
        x, y = int(round(m["x"])), int(round(m["y"]))
        win = diff[max(0, y - r): min(h, y + r + 1), max(0, x - r): min(w, x + r + 1)]
        acc += float(np.sum(np.square(win, dtype=np.float64)))
        n += win.size
    return math.sqrt(acc / n) if n else float(np.sqrt(np.mean(np.square(diff))))


def _cache_key(case: Case) -> str:
    """A name for the render of ``case`` that changes with the case and with the renderer's
    code (:func:`render_case` with ``cache``)."""
    import hashlib
    from pathlib import Path

    global _RENDER_CODE
    if _RENDER_CODE is None:  # once per process: the code that made the renders
        import inspect

        here = Path(__file__).parent
        code = b"".join((here / f).read_bytes()
                        for f in ("scan.py", "scene.py", "marks.py", "mapping.py"))
        code += "".join(inspect.getsource(f) for f in (_jpeg, _loss_at_marks)).encode()
        _RENDER_CODE = hashlib.sha1(code).hexdigest()
    h = hashlib.sha1(repr((case.camera, case.spec, case.seed, case.jpeg)).encode())
    h.update(_RENDER_CODE.encode())
    return f"sweep-{case.seed:05d}-{h.hexdigest()[:12]}"


_RENDER_CODE = None


def _as_stored(truth: dict, case: Case) -> dict:
    """The truth of ``case`` saying how its image is stored: a case compressed after rendering
    (``case.jpeg``) is a JPEG of that quality, whatever the render spec's defaults say."""
    if not case.jpeg:
        return truth
    return {**truth, "spec": {**truth.get("spec", {}), "file_format": "jpeg",
                              "jpeg_quality": int(case.jpeg)}}


def render_case(case: Case, cache=None):
    """(image as stored, truth, grey scene without marks or None, JPEG loss rms).

    ``cache``: a folder where renders are kept (``.npy`` + JSON, reused when the case and
    the renderer's code are the same): the sweep's renders cost far more than detection.
    """
    if cache is not None:
        import json
        from pathlib import Path

        base = Path(cache) / _cache_key(case)
        meta = base.with_suffix(".json")
        if meta.exists():
            d = json.loads(meta.read_text(encoding="utf-8"))
            img = np.load(str(base) + ".img.npy")
            scene = np.load(str(base) + ".scene.npy") if d["scene"] else None
            return img, _as_stored(d["truth"], case), scene, d["jpeg_rms"]
        out = render_case(case)
        Path(cache).mkdir(parents=True, exist_ok=True)
        for part, a in (("img", out[0]), ("scene", out[2])):
            if a is not None:  # written under another name, then renamed: never half read
                tmp = Path(f"{base}.{part}.tmp.npy")
                np.save(tmp, a if part == "img" else a.astype(np.float32))
                tmp.replace(f"{base}.{part}.npy")
        tmp = meta.with_suffix(".tmp")
        tmp.write_text(json.dumps({"truth": out[1], "scene": out[2] is not None,
                                   "jpeg_rms": out[3]}), encoding="utf-8")
        tmp.replace(meta)  # written last: a render is complete when its JSON exists
        return out
    img, truth = render_scan(case.camera, case.spec, case.seed)
    jpeg_rms = 0.0
    if case.jpeg:
        stored = _jpeg(img, case.jpeg)
        jpeg_rms = _loss_at_marks(_grey(stored) - _grey(img), truth)
        img, truth = stored, _as_stored(truth, case)
    scene = None
    if case.spec.scene == "busy":
        spec = replace(case.spec, noise_sigma=0.0, bits=32)
        s_img, _ = render_scan(case.camera, spec, case.seed, marks=False, clip=False)
        scene = s_img @ np.array([0.299, 0.587, 0.114]) if s_img.ndim == 3 else s_img
    return img, truth, scene, jpeg_rms


def run_case(case: Case, detect_kw: dict | None = None, cache=None) -> tuple[Score, object]:
    """Render (or take the render from ``cache``, :func:`render_case`), detect in-process,
    score. Returns (score, detection or None)."""
    from softplot.io import Scan
    from softplot.marks import detect

    img, truth, scene, jpeg_rms = render_case(case, cache)
    snr = mark_snr(truth, jpeg_rms, scene)
    bits = truth["bit_depth"] if img.dtype == np.uint16 else 8
    scan = Scan.from_array(img, dpi=truth["dpi"], bit_depth=bits)
    t0 = time.perf_counter()
    try:
        det = detect(scan, load_camera(case.camera), dpi=truth["dpi"], rotate=case.rotate,
                     **(detect_kw or {}))
    except Exception as exc:  # noqa: BLE001 - every failure is a result of the sweep
        error = f"{type(exc).__name__}: {exc}".splitlines()[0]
        if not isinstance(exc, SoftplotError):  # a crash: where
            tb = traceback.extract_tb(exc.__traceback__)[-1]
            error += f" (at {tb.filename.rsplit('/', 1)[-1]}:{tb.lineno})"
        sc = refused(truth, error, snr)
        sc.seconds = time.perf_counter() - t0
        return sc, None
    seconds = time.perf_counter() - t0
    sc = score(det, truth, _bounds(case, truth, scene, jpeg_rms), identifiable(truth, snr),
               snr)
    sc.seconds = seconds
    return sc, det


def refused(truth: dict, error: str, snr: dict | None = None) -> Score:
    """The score of a render the detector gave no result on: its visible crosses all
    missed; with ``snr`` (:func:`mark_snr`) each with its ratio and threshold, and whether
    the render could be asked for a result (``below_detection``)."""
    vis = [m for m in truth["marks"] if m["kind"] == "reseau" and m["state"] == "visible"
           and not m["damaged"]]
    sc = Score(result=False, error=error, visible=len(vis),
               ambiguous_truth=identifiable(truth, snr))
    if snr is not None:
        sc.snr_scored, sc.below_detection = True, detectable_render(truth, snr)
        sc.snr_missed = [list(snr[m["name"]][:2]) for m in vis if m["name"] in snr]
    return sc


def failure_lines(case: Case, sc: Score) -> list[str]:
    """What went wrong in one case (empty when nothing did)."""
    out = []
    if not sc.result:
        why = f" (none required: {sc.below_detection})" if sc.below_detection else ""
        out.append(f"no result{why}: {sc.error}")
    if sc.wrong:
        guess = (f" on a render that cannot show them ({sc.ambiguous_truth}) without saying "
                 "so (ids_ambiguous)" if sc.ambiguous_truth else "")
        out.append(f"wrong row/col ({len(sc.wrong)}){guess}: {'; '.join(sc.wrong[:6])}")
    if sc.claimed:
        out.append(f"claims on invisible crosses ({len(sc.claimed)}): "
                   f"{', '.join(sc.claimed[:8])}")
    if sc.result and sc.missed:
        out.append(f"visible not measured ({len(sc.missed)} of {sc.visible}): "
                   f"{'; '.join(sc.missed[:6])}")
    if sc.gross:
        out.append(f"gross errors ({len(sc.gross)}): {'; '.join(sc.gross[:6])}")
    return out


# ---------------------------------------------------------------------------------------------
# aggregation


def aggregate(results: list[tuple[Case, Score]]) -> dict[str, dict]:
    """Per condition (and "all"): pooled figures of the cases that have it."""
    rows: dict[str, list[Score]] = {"all": []}
    for c in CONDITIONS:
        rows[c] = []
    for case, sc in results:
        rows["all"].append(sc)
        for c in case.conditions:
            rows.setdefault(c, []).append(sc)
    out = {}
    for name, scs in rows.items():
        if not scs:
            continue
        err2 = sum((s.err2 for s in scs), [])
        crb2 = sum((s.crb2 for s in scs), [])
        e1 = sum((s.err2_1 for s in scs), [])
        c1 = sum((s.crb2_1 for s in scs), [])
        z2 = sum((s.z2 for s in scs), [])
        za = sum((s.z2_along for s in scs), [])
        vis = sum(s.visible for s in scs if s.result)
        vis_all = sum(s.visible for s in scs)
        rms = math.sqrt(np.mean(err2)) if err2 else float("nan")
        crb = math.sqrt(np.mean(crb2)) if crb2 else float("nan")
        rms1 = math.sqrt(np.mean(e1)) if e1 else float("nan")
        crb1 = math.sqrt(np.mean(c1)) if c1 else float("nan")
        out[name] = {
            "scans": len(scs),
            "results": sum(s.result for s in scs),
            "visible": vis_all,
            "measured": sum(s.measured for s in scs),
            "measured_rate": sum(s.measured for s in scs) / vis_all if vis_all else float("nan"),
            "visible_in_results": vis,
            "wrong": sum(len(s.wrong) for s in scs),
            "claimed": sum(len(s.claimed) for s in scs),
            "gross": sum(len(s.gross) for s in scs),
            "rms_px": rms, "crb_px": crb, "rms_over_crb": rms / crb if crb2 else float("nan"),
            "ambiguous": sum(bool(s.ambiguous_truth) for s in scs),
            "ambiguous_warned": sum(bool(s.ambiguous_truth) and s.ids_ambiguous for s in scs),
            "one_arm": len(e1), "rms1_over_crb1": rms1 / crb1 if e1 else float("nan"),
            "rms1_over_render": one_arm_over_render(scs),
            "z_rms": math.sqrt(np.mean(z2)) if z2 else float("nan"),
            "z_along_rms": math.sqrt(np.mean(za)) if za else float("nan"),
            **_detectability(scs),
        }
    return out


def one_arm_over_render(scs: list[Score]) -> float:
    """The one-armed crosses' RMS error across their bar over what their renders' two-armed
    crosses reach: ``sqrt(sum e1^2 / sum b1^2 q)``, ``e1`` and ``b1`` each one-armed cross's
    error across its bar and bound, ``q`` its render's two-armed ``sum err2 / sum crb2``
    (renders without measured two-armed crosses left out). 1: a one-armed cross is measured
    across its bar as well, for its bound, as the whole crosses of its scan; the rest of
    ``rms1_over_crb1`` is the scans' (blur, scene, JPEG), not the lone bars'. NaN without
    one-armed crosses on such renders."""
    num = den = 0.0
    for s in scs:
        c2 = float(np.sum(s.crb2))
        if not s.err2_1 or c2 <= 0:
            continue
        num += float(np.sum(s.err2_1))
        den += float(np.sum(s.crb2_1)) * float(np.sum(s.err2)) / c2
    return math.sqrt(num / den) if den > 0 else float("nan")


def _detectability(scs: list[Score]) -> dict:
    """The figures of :func:`aggregate` on the crosses and renders a detector can be asked for
    (:func:`mark_snr`): renders that must give a result (``required``: 3 x 3 detectable
    crosses, :func:`detectable_render`) and how many did; visible crosses above their
    detection threshold in those renders (``detectable``) and how many were measured; visible
    crosses below their threshold (``below``, in any render), how many of them were measured
    anyway, and the gross measurements below detection (``claimed_below``). Empty when no
    score has the SNR."""
    scs = [s for s in scs if s.snr_scored]
    if not scs:
        return {}
    req = [s for s in scs if not s.below_detection]
    det_meas = sum(sum(r[0] >= r[1] for r in s.snr_measured) for s in req)
    det_miss = sum(sum(r[0] >= r[1] for r in s.snr_missed) for s in req)
    below = sum(sum(r[0] < r[1] for r in s.snr_missed) for s in scs)
    below_meas = sum(sum(r[0] < r[1] for r in s.snr_measured) for s in scs)
    return {
        "required": len(req), "results_required": sum(s.result for s in req),
        "detectable": det_meas + det_miss, "measured_detectable": det_meas,
        "measured_detectable_rate": (det_meas / (det_meas + det_miss) if det_meas + det_miss
                                     else float("nan")),
        "below": below + below_meas, "below_measured": below_meas,
        "claimed_below": sum(len(s.claimed_below) for s in scs),
    }


#: the targets over the sweep (docs/accuracy.md, "Robustness sweep")
TARGETS = {"results": 1.0, "measured_rate": 0.995, "wrong": 0, "claimed": 0,
           "rms_over_crb": 1.25, "z_rms": (0.67, 1.5)}


def misses(row: dict) -> list[str]:
    """Which targets a table row misses (empty: all met). A row with the detectability
    figures (:func:`_detectability`) is held to them: a result on every render that shows
    3 x 3 detectable crosses, 99.5 % of the detectable crosses measured, no gross measurement
    below detection; otherwise to a result on every render and 99.5 % of the visible
    crosses."""
    out = []
    if "required" in row:  # scored with the SNR: what a detector can be asked for
        if row["results_required"] < row["required"]:
            out.append(f"result on {row['results_required']}/{row['required']} scans that "
                       "show 3 x 3 detectable crosses")
        if row["detectable"] and not row["measured_detectable_rate"] >= TARGETS["measured_rate"]:
            out.append(f"measured {100 * row['measured_detectable_rate']:.2f} % of detectable")
        if row["claimed_below"]:
            out.append(f"{row['claimed_below']} gross measurements below detection")
    else:
        if row["results"] < row["scans"]:
            out.append(f"result on {row['results']}/{row['scans']} scans")
        if not row["measured_rate"] >= TARGETS["measured_rate"]:
            out.append(f"measured {100 * row['measured_rate']:.2f} % of visible")
    if row["wrong"]:
        out.append(f"{row['wrong']} wrong row/col")
    if row["claimed"]:
        out.append(f"{row['claimed']} claims on invisible")
    if np.isfinite(row["rms_over_crb"]) and row["rms_over_crb"] > TARGETS["rms_over_crb"]:
        out.append(f"RMS {row['rms_over_crb']:.2f}x CRB")
    if np.isfinite(row["rms1_over_crb1"]) and row["rms1_over_crb1"] > TARGETS["rms_over_crb"]:
        out.append(f"one-armed RMS {row['rms1_over_crb1']:.2f}x CRB")
    lo, hi = TARGETS["z_rms"]
    if np.isfinite(row["z_rms"]) and not lo <= row["z_rms"] <= hi:
        out.append(f"normalised-error RMS {row['z_rms']:.2f}")
    za = row.get("z_along_rms", float("nan"))
    if np.isfinite(za) and za > hi:  # along a bar, too large a sigma is honest
        out.append(f"one-armed normalised error along the bar {za:.2f}")
    return out


def table(agg: dict[str, dict]) -> str:
    """The per-condition markdown table."""
    def f(v, fmt):
        return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else fmt % v

    head = ("| condition | scans | result | visible | measured | wrong row/col | claims on "
            "invisible | ambiguous: warned | gross | RMS px | CRB px | RMS/CRB | one-armed: n, "
            "RMS/CRB across, normalised error along | normalised-error RMS |")
    sep = "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    snr = any("required" in r for r in agg.values())
    if snr:  # the figures on what is detectable, after the old ones
        head += (" result where 3 x 3 detectable | measured of detectable | below detection: "
                 "visible, measured, gross |")
        sep += "---|---|---|"
    lines = [head + "\n" + sep]
    for name, r in agg.items():
        lines.append(
            f"| {name} | {r['scans']} | {100 * r['results'] / r['scans']:.1f} % | "
            f"{r['visible']} | {f(100 * r['measured_rate'], '%.2f')} % | {r['wrong']} | "
            f"{r['claimed']} | {r['ambiguous_warned']} of {r['ambiguous']} | {r['gross']} | "
            f"{f(r['rms_px'], '%.4f')} | "
            f"{f(r['crb_px'], '%.4f')} | {f(r['rms_over_crb'], '%.2f')} | {r['one_arm']}, "
            f"{f(r['rms1_over_crb1'], '%.2f')}, {f(r.get('z_along_rms'), '%.2f')} | "
            f"{f(r['z_rms'], '%.2f')} |" + (_detectable_cells(r) if snr else ""))
    return "\n".join(lines)


def _detectable_cells(r: dict) -> str:
    """The table's detectability cells of one row (:func:`_detectability`)."""
    if "required" not in r:
        return " - | - | - |"
    rate = r["measured_detectable_rate"]
    return (f" {r['results_required']}/{r['required']} | "
            f"{'-' if not np.isfinite(rate) else f'{100 * rate:.2f} %'} "
            f"({r['measured_detectable']} of {r['detectable']}) | "
            f"{r['below']}, {r['below_measured']}, {r['claimed_below']} |")
