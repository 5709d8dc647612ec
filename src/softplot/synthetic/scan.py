"""Render a synthetic scan of a film frame with exact truth.

The physics, in order:

1. **Exposure** (undeformed film mm): the scene and the reseau crosses / fiducial marks are
   exposed together. In a positive the film background is ``mark_level + contrast * g``
   (``g`` the scene factor, 1 for an empty scene; ``mark_level = background - contrast``);
   the marks and the unexposed border outside the format are at ``mark_level``. A mark's pixel
   coverage is integrated exactly (see :mod:`softplot.synthetic.marks`).
2. **Deformation** of the film (shrinkage + smooth field) and **scanning** (scanner affine,
   crop): the truth mapping of :mod:`softplot.synthetic.mapping`. Every pixel is rendered at
   its exact undeformed film position, so a mark's true pixel position is
   ``film_to_pixel(certificate film coordinates)``.
3. Film **grain** (white, before the scanner optics), **polarity** (negative: ``1 - value``,
   bright marks on a dark background), the **orange mask** of a colour negative (RGB),
   **dust, scratches and covering blobs** on the film surface, the scanner's **Gaussian blur**
   (``blur_sigma_px``), sensor **noise** (``noise_sigma``), and **quantisation** to 8 or 16 bits.

Values are fractions of full scale (1.0 = white = 255 or 65535 in the file). The image is
composed in horizontal strips (bounded memory, exact because the blur gets a halo and every
random field is seeded per block of rows), so the same seed gives the same pixels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

import cv2
import numpy as np

from softplot.camera import Camera, load_camera
from softplot.errors import SoftplotError
from softplot.synthetic.mapping import Deformation, Scanner, TruthMapping
from softplot.synthetic.marks import (
    MarkShape,
    area_coverage,
    cross_shape,
    fiducial_shape,
    render_marks,
)
from softplot.synthetic.scene import SCENES, Scene

#: transmittance (R, G, B) of the orange mask of a colour negative film base
ORANGE_MASK = (0.85, 0.55, 0.30)
#: ITU-R BT.601 luma weights, as softplot.io converts RGB to grey
LUMA = (0.299, 0.587, 0.114)
POLARITIES = ("positive", "negative")
FILE_FORMATS = ("tif", "jpg", "png")
OCCLUSIONS = ("first-order", "exact")

_BLOCK = 64  # rows per independently seeded block of random numbers
_GRID = 32  # px between exact film-coordinate nodes for the scene maps
_STREAMS = {"deform": 1, "scene": 2, "cover": 3, "dust": 4, "scratch": 5, "grain": 6, "noise": 7,
            "onearm": 8}


@dataclass(frozen=True)
class ScanSpec:
    """How to render a synthetic scan.

    Attributes
    ----------
    dpi : float
        Scan resolution, dots per inch (> 0).
    polarity : str
        "positive" (dark marks on a brighter image, as a print or diapositive) or "negative"
        (bright marks, as a film negative; the scene is inverted too).
    blur_sigma_px : float
        Scanner optics: Gaussian blur sigma in pixels (0 for none).
    noise_sigma : float
        Sensor noise, Gaussian, per channel, fraction of full scale, added after the blur.
    grain_sigma : float
        Film grain, white Gaussian, fraction of full scale, added before the blur.
    contrast : float
        Mark-minus-background amplitude on an empty scene, fraction of full scale.
    background : float
        Positive film background level on an empty scene (the marks are at
        ``background - contrast``; a negative is ``1 - value``).
    scene : str or callable
        "none", "texture", "busy", or ``f(x_mm, y_mm) -> reflectance in [0, 1]`` in
        undeformed film mm (0.5 = nominal background); see :mod:`softplot.synthetic.scene`.
    deform_um : float
        Largest displacement (micrometres) of the smooth film deformation over the format.
    shrink_ppm : float
        Uniform film shrinkage, parts per million (positive shrinks).
    rotation_deg : float
        Scanner rotation: the film frame turned counter-clockwise on screen, degrees.
    offset_px : (float, float)
        Shift (pixel x, y) of the film within the scan from the centred position.
    anisotropy_ppm : float
        Scanner x/y scale difference, ppm (x scale ``1 + a/2``, y scale ``1 - a/2``).
    dust : int
        Number of dust particles and fibres (opaque, dark) on the film surface.
    scratches : int
        Number of long thin scratches (bright or dark).
    cover : int or tuple of str
        Number of marks (or their names) wholly hidden by an opaque blob: state "covered".
    crop_mm : float or (left, top, right, bottom)
        Millimetres cut off the scan's edges (a single number: left and top only). The
        uncropped scan shows the format plus ``margin_mm`` on each side.
    margin_mm : float
        Unexposed film border shown around the format.
    bits : int
        8 or 16 (32: float32, API and TIFF only).
    rgb : bool
        Three channels; with ``polarity="negative"`` an orange-masked colour negative.
    file_format : str
        "tif", "jpg" (8-bit only) or "png" (used by :func:`write_scan`).
    jpeg_quality : int
        JPEG quality (1-100).
    tiff_compression : str or None
        TIFF compression ("zlib", "lzw", ...); None writes uncompressed (memory-mappable).
    subrows : int
        Sub-rows per pixel in the mark integration (>= 8).
    mark_arm_scale, mark_width_scale : float
        The reseau crosses as exposed: arm length and line width are the certificate's times
        these (a certificate's mark sizes are nominal; the truth records the real ones).
    mark_opacity : float
        Opacity of the reseau crosses and fiducials in (0, 1] (1: opaque; 0.6: 40 % of the
        scene's light passes through a mark).
    centre_scale : float
        The reseau's centre cross (odd rows and cols) is this many times the others (arm
        length and line width), as on plates with a larger centre cross.
    one_armed : int or tuple of str
        Number of visible crosses (chosen at random), or their names, of which only one bar
        was imaged (the other faded or aliased away); truth ``arms`` 1 and ``arm_axis``.
    dark_rows : tuple of (int, int)
        Inclusive ranges of reseau rows ``(r0, r1)`` lying under a flat dark region of the
        scene (sky, shadow) that reaches halfway to the neighbouring rows, or the frame's edge
        for the first and last row. Its scene factor is ``dark_level``.
    dark_level : float
        Scene factor in ``dark_rows``, in [0, 1): 0 exposes nothing, so the crosses there
        have no contrast at all (truth state "dark", not visible).
    occlusion : str
        How an opaque mark hides the scene (blurs of 0.4 px and more): "first-order" (the
        default) images it as ``blur(S) + (m - blur(S)) x blur(M)`` (``S`` the scene, ``M``
        the mark's coverage, ``m`` its level), exact where the scene is linear over the blur;
        "exact" as the film is: ``blur(S x (1 - M)) + m x blur(M)``, so that the scene hidden
        under a mark never reaches the image (they differ at sharp scene edges by the marks).
    """

    dpi: float = 1200.0
    polarity: str = "positive"
    blur_sigma_px: float = 0.8
    noise_sigma: float = 0.01
    grain_sigma: float = 0.0
    contrast: float = 0.5
    background: float = 0.8
    scene: str | Callable = "texture"
    deform_um: float = 20.0
    shrink_ppm: float = 0.0
    rotation_deg: float = 0.0
    offset_px: tuple[float, float] = (0.0, 0.0)
    anisotropy_ppm: float = 0.0
    dust: int = 0
    scratches: int = 0
    cover: int | tuple[str, ...] = 0
    crop_mm: float | tuple[float, float, float, float] = 0.0
    margin_mm: float = 1.0
    bits: int = 8
    rgb: bool = False
    file_format: str = "tif"
    jpeg_quality: int = 92
    tiff_compression: str | None = None
    subrows: int = 16
    occlusion: str = "first-order"
    mark_arm_scale: float = 1.0
    mark_width_scale: float = 1.0
    mark_opacity: float = 1.0
    centre_scale: float = 1.0
    one_armed: int | tuple[str, ...] = 0
    dark_rows: tuple[tuple[int, int], ...] = ()
    dark_level: float = 0.0

    def validate(self) -> "ScanSpec":
        """Check every field; raise :class:`SoftplotError` naming the first bad one."""

        def bad(name: str, why: str) -> SoftplotError:
            return SoftplotError(f"synthetic scan: {name} {why}, got {getattr(self, name)!r}")

        def num(name: str, lo: float | None = None, lo_open: bool = False) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise bad(name, "must be a finite number")
            if lo is not None and (v <= lo if lo_open else v < lo):
                raise bad(name, f"must be {'>' if lo_open else '>='} {lo:g}")

        num("dpi", 0.0, lo_open=True)
        if self.dpi > 20000:
            raise bad("dpi", "must be at most 20000")
        for n in ("blur_sigma_px", "noise_sigma", "grain_sigma", "deform_um", "margin_mm"):
            num(n, 0.0)
        for n in ("shrink_ppm", "rotation_deg", "anisotropy_ppm"):
            num(n)
        num("contrast", 0.0, lo_open=True)
        num("background", 0.0, lo_open=True)
        if self.background > 1.0:
            raise bad("background", "must be at most 1")
        if self.contrast > self.background:
            raise bad("contrast", f"must be at most background ({self.background:g})")
        if abs(self.shrink_ppm) >= 1e5 or abs(self.anisotropy_ppm) >= 1e5:
            raise SoftplotError("synthetic scan: shrink_ppm and anisotropy_ppm must be < 1e5")
        if self.deform_um > 1000:
            raise bad("deform_um", "must be at most 1000")
        if self.polarity not in POLARITIES:
            raise bad("polarity", f"must be one of {', '.join(POLARITIES)}")
        if not callable(self.scene) and self.scene not in SCENES:
            raise bad("scene", f"must be one of {', '.join(SCENES)} or a function")
        if self.bits not in (8, 16, 32):
            raise bad("bits", "must be 8 or 16 (32 for float)")
        if self.file_format not in FILE_FORMATS:
            raise bad("file_format", f"must be one of {', '.join(FILE_FORMATS)}")
        if self.file_format == "jpg" and self.bits != 8:
            raise SoftplotError("synthetic scan: JPEG holds 8 bits only (use --bits 8 or tif/png)")
        if self.file_format == "png" and self.bits == 32:
            raise SoftplotError("synthetic scan: PNG cannot hold float samples (use 8 or 16 bits)")
        for n in ("dust", "scratches"):
            v = getattr(self, n)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise bad(n, "must be a non-negative integer")
        if not isinstance(self.cover, (tuple, list)):
            if isinstance(self.cover, bool) or not isinstance(self.cover, (int, np.integer)):
                raise bad("cover", "must be a count or a list of mark names")
            if self.cover < 0:
                raise bad("cover", "must not be negative")
        if len(np.ravel(self.offset_px)) != 2 or not np.all(np.isfinite(self.offset_px)):
            raise bad("offset_px", "must be two finite numbers")
        crop = np.ravel(np.asarray(self.crop_mm, float))
        if crop.size not in (1, 4) or not np.all(np.isfinite(crop)) or np.any(crop < 0):
            raise bad("crop_mm", "must be one or four non-negative numbers")
        if not (isinstance(self.subrows, (int, np.integer)) and 8 <= self.subrows <= 256):
            raise bad("subrows", "must be an integer in 8..256")
        if not (isinstance(self.jpeg_quality, (int, np.integer)) and 1 <= self.jpeg_quality <= 100):
            raise bad("jpeg_quality", "must be an integer in 1..100")
        if self.occlusion not in OCCLUSIONS:
            raise bad("occlusion", f"must be one of {', '.join(OCCLUSIONS)}")
        for n in ("mark_arm_scale", "mark_width_scale", "centre_scale"):
            num(n, 0.0, lo_open=True)
            if getattr(self, n) > 10:
                raise bad(n, "must be at most 10")
        num("mark_opacity", 0.0, lo_open=True)
        if self.mark_opacity > 1:
            raise bad("mark_opacity", "must be at most 1")
        num("dark_level", 0.0)
        if self.dark_level >= 1:
            raise bad("dark_level", "must be below 1")
        if not isinstance(self.one_armed, (tuple, list)):
            if isinstance(self.one_armed, bool) or not isinstance(self.one_armed,
                                                                  (int, np.integer)):
                raise bad("one_armed", "must be a count or a list of cross names")
            if self.one_armed < 0:
                raise bad("one_armed", "must not be negative")
        try:
            ok = all(len(r) == 2 and int(r[0]) == r[0] and int(r[1]) == r[1] and 0 <= r[0] <= r[1]
                     for r in self.dark_rows)
        except TypeError:
            ok = False
        if not ok:
            raise bad("dark_rows", "must be pairs (first row, last row) of row indices")
        return self

    def crop_px(self, px_per_mm: float) -> tuple[int, int, int, int]:
        """(left, top, right, bottom) pixels cut off the uncropped scan."""
        c = np.ravel(np.asarray(self.crop_mm, float))
        c = np.array([c[0], c[0], 0.0, 0.0]) if c.size == 1 else c
        return tuple(int(round(v * px_per_mm)) for v in c)

    def to_dict(self) -> dict:
        """JSON-ready record of the spec (a callable scene is recorded as "callable")."""
        d = asdict(self)
        d["scene"] = self.scene if isinstance(self.scene, str) else "callable"
        d["cover"] = list(self.cover) if isinstance(self.cover, (tuple, list)) else int(self.cover)
        d["offset_px"] = [float(v) for v in np.ravel(self.offset_px)]
        d["crop_mm"] = [float(v) for v in np.ravel(np.asarray(self.crop_mm, float))]
        d["one_armed"] = (list(self.one_armed) if isinstance(self.one_armed, (tuple, list))
                          else int(self.one_armed))
        d["dark_rows"] = [[int(a), int(b)] for a, b in self.dark_rows]
        return d


# ---------------------------------------------------------------------------------------------
# helpers


def _rng(seed: int, stream: str, *more: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), _STREAMS[stream], *more]))


class _BlockNormals:
    """Standard normals for rows [r0, r1) of a (H, W, C) field, seeded per block of rows."""

    def __init__(self, seed: int, stream: str, width: int, channels: int) -> None:
        self.seed, self.stream, self.width, self.channels = seed, stream, width, channels
        self.cache: dict[int, np.ndarray] = {}

    def block(self, b: int) -> np.ndarray:
        if b not in self.cache:
            rng = _rng(self.seed, self.stream, b)
            self.cache[b] = rng.standard_normal((_BLOCK, self.width, self.channels), np.float32)
        return self.cache[b]

    def rows(self, r0: int, r1: int) -> np.ndarray:
        b0, b1 = r0 // _BLOCK, (r1 - 1) // _BLOCK
        for k in [k for k in self.cache if k < b0]:
            del self.cache[k]
        parts = [self.block(b) for b in range(b0, b1 + 1)]
        a = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)
        return a[r0 - b0 * _BLOCK : r1 - b0 * _BLOCK]


@dataclass
class _Patch:
    """An opaque-ish defect on the film surface: alpha (h, w) at pixel (r0, c0), a value."""

    r0: int
    c0: int
    alpha: np.ndarray
    value: float
    kind: str


def _patch(pts_px: np.ndarray, value: float, opacity: float, kind: str,
           thickness: float | None = None) -> _Patch | None:
    """Rasterise a filled polygon (thickness None) or a polyline, anti-aliased, in pixels."""
    pad = int(math.ceil((thickness or 0) / 2)) + 2
    lo = np.floor(pts_px.min(axis=0)).astype(int) - pad
    hi = np.ceil(pts_px.max(axis=0)).astype(int) + pad
    w, h = hi - lo + 1
    if w <= 0 or h <= 0 or w * h > 60_000_000:
        return None
    canvas = np.zeros((h, w), np.uint8)
    pts = np.round((pts_px - lo) * 16).astype(np.int32)
    if thickness is None:
        cv2.fillPoly(canvas, [pts], 255, cv2.LINE_AA, 4)
    else:
        t = max(1, int(round(thickness)))
        opacity *= min(1.0, thickness / t)
        cv2.polylines(canvas, [pts], False, 255, t, cv2.LINE_AA, 4)
    alpha = canvas.astype(np.float32) * np.float32(opacity / 255.0)
    return _Patch(int(lo[1]), int(lo[0]), alpha, float(value), kind)


def _blob(centre: np.ndarray, radius: float, rng: np.random.Generator, n: int = 28) -> np.ndarray:
    """An irregular closed polygon (pixels) whose every edge lies at least ``radius`` out."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.05, 0.05, n)
    k = np.arange(1, 4)
    wobble = sum(rng.uniform(0, 0.15) * np.cos(kk * ang + rng.uniform(0, 6.3)) for kk in k)
    r = radius / math.cos(math.pi / n * 1.2) * (1.0 + np.abs(wobble))
    return centre + np.column_stack([r * np.cos(ang), r * np.sin(ang)])


# ---------------------------------------------------------------------------------------------
# the renderer


@dataclass
class _Marks:
    kind: list
    name: list
    row: list
    col: list
    film: np.ndarray
    shapes: list


def _marks(camera: Camera, spec: ScanSpec | None = None) -> _Marks:
    """The marks as exposed: the certificate's positions, the shapes of ``spec`` (mark sizes
    scaled, a larger centre cross)."""
    spec = spec or ScanSpec()
    kinds, names, rows, cols, film, shapes = [], [], [], [], [], []
    if camera.reseau is not None:
        r = camera.reseau
        arm = r.arm_length_mm * spec.mark_arm_scale
        lw = r.line_width_mm * spec.mark_width_scale
        shp = cross_shape(arm, lw)
        centre = ((r.rows - 1) // 2, (r.cols - 1) // 2) if r.rows % 2 and r.cols % 2 else None
        big = cross_shape(arm * spec.centre_scale, lw * spec.centre_scale)
        for (ri, ci), nm, xy in zip(r.row_col(), r.names(), r.film(), strict=False):
            kinds.append("reseau")
            names.append(nm)
            rows.append(int(ri))
            cols.append(int(ci))
            film.append(xy)
            is_centre = centre is not None and (int(ri), int(ci)) == centre
            shapes.append(big if is_centre and spec.centre_scale != 1.0 else shp)
    for f in camera.fiducials:
        kinds.append("fiducial")
        names.append(f.name)
        rows.append(None)
        cols.append(None)
        film.append((f.x, f.y))
        shapes.append(fiducial_shape(f))
    return _Marks(kinds, names, rows, cols, np.array(film, float).reshape(-1, 2), shapes)


def bar_shape(cross: MarkShape, axis: str) -> MarkShape:
    """One bar of a cross: the horizontal (film x, ``axis="x"``) or the vertical one."""
    hx, hy = float(cross.rects[0, 0]), float(cross.rects[0, 1])  # the x bar: (L, w)
    rect = [hx, hy, 1.0] if axis == "x" else [hy, hx, 1.0]
    return MarkShape(kind="bar", rects=np.array([rect]), discs=np.zeros((0, 2)))


def _inside(mapping, shape: MarkShape, centre_mm, width: int, height: int) -> bool:
    o = mapping.film_to_pixel(shape.outline_mm() + centre_mm)
    return bool(np.all((o >= -0.5) & (o <= np.array([width, height]) - 0.5)))


def _choose_one_armed(spec: ScanSpec, mk: _Marks, mapping, size, rng,
                      exclude: np.ndarray) -> dict[int, str]:
    """{mark index: surviving bar axis} of the one-armed crosses of ``spec``."""
    if isinstance(spec.one_armed, (tuple, list)):
        where = {n: i for i, n in enumerate(mk.name)}
        out = {}
        for n in spec.one_armed:
            if n not in where or mk.kind[where[n]] != "reseau":
                raise SoftplotError(f"synthetic scan: cannot make {n!r} one-armed: no such cross")
            out[where[n]] = "x" if rng.uniform() < 0.5 else "y"
        return out
    n = int(spec.one_armed)
    if n == 0:
        return {}
    pool = [i for i in range(len(mk.name)) if mk.kind[i] == "reseau" and not exclude[i]
            and _inside(mapping, mk.shapes[i], mk.film[i], *size)]
    if n > len(pool):
        raise SoftplotError(f"synthetic scan: cannot make {n} crosses one-armed, only "
                            f"{len(pool)} visible")
    pick = sorted(int(i) for i in rng.choice(pool, n, replace=False))
    return {i: ("x" if rng.uniform() < 0.5 else "y") for i in pick}


def _dark_bands(camera: Camera, spec: ScanSpec) -> list[tuple[float, float]]:
    """Film y intervals (lo, hi), undeformed film mm, of the dark regions of ``spec``."""
    if not spec.dark_rows:
        return []
    r = camera.reseau
    if r is None:
        raise SoftplotError("synthetic scan: dark_rows needs a reseau camera")
    y = r.nominal_film()[:: r.cols, 1]  # film y of each row, top row first
    out = []
    for r0, r1 in spec.dark_rows:
        if r1 >= r.rows:
            raise SoftplotError(f"synthetic scan: dark_rows ({r0}, {r1}): the reseau has "
                                f"{r.rows} rows")
        hi = math.inf if r0 == 0 else 0.5 * (y[r0] + y[r0 - 1])
        lo = -math.inf if r1 == r.rows - 1 else 0.5 * (y[r1] + y[r1 + 1])
        out.append((lo, hi))
    return out


def _shape_key(s: MarkShape) -> tuple:
    return (s.kind, s.rects.round(12).tobytes(), s.discs.round(12).tobytes())


def render_scan(camera, spec: ScanSpec | None = None, seed: int = 0,
                marks: bool = True, clip: bool = True) -> tuple[np.ndarray, dict]:
    """Render a synthetic scan of a film frame of ``camera`` with its exact truth.

    Parameters
    ----------
    camera : Camera or str
        A :class:`softplot.camera.Camera`, a built-in name or a certificate path.
    spec : ScanSpec, optional
        What to render (defaults: ``ScanSpec()``).
    seed : int
        Seed of every random choice (deformation, scene, defects, grain, noise): the same
        seed and spec give the same pixels and truth.
    marks : bool
        False renders the same frame without the marks' images (scene, border, defects and
        noise as with them; the truth still describes the marks): the scene each mark hides,
        e.g. for the Cramer-Rao bound of a render (:func:`softplot.marks.crb.render_crb`).
    clip : bool
        False (float output, ``spec.bits == 32`` only) keeps grey values beyond [0, 1] that
        a scanner would saturate: the level a saturated scene really has.

    Returns
    -------
    image : ndarray
        Pixel system, (H, W) or (H, W, 3) RGB; uint8 (bits 8), uint16 (16) or float32 (32).
    truth : dict
        The truth record (see ``docs`` of :mod:`softplot.synthetic`): image size, dpi,
        polarity, every mark's exact pixel position ``x``, ``y`` and state, the complete
        mapping (``TruthMapping.from_truth``) and the render parameters.
    """
    cam = load_camera(camera)
    spec = (spec or ScanSpec()).validate()
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SoftplotError(f"synthetic scan: seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    s = spec.dpi / 25.4  # px per mm
    fw, fh = cam.format_mm
    deformation = Deformation.random(
        (fw, fh), spec.deform_um, spec.shrink_ppm, _rng(seed, "deform")
    )

    # -- frame: format plus margin, centred, then offset and crop --------------------------
    m = spec.margin_mm
    t = np.linspace(-1.0, 1.0, 65)
    ex, ey = fw / 2 + m, fh / 2 + m
    ring = np.concatenate([
        np.column_stack([t * ex, np.full_like(t, ey)]),
        np.column_stack([t * ex, np.full_like(t, -ey)]),
        np.column_stack([np.full_like(t, ex), t * ey]),
        np.column_stack([np.full_like(t, -ex), t * ey]),
    ])
    sc0 = Scanner(spec.dpi, spec.rotation_deg, spec.anisotropy_ppm, 0.0, 0.0)
    p = sc0.forward(deformation.forward(ring))
    lo, hi = p.min(axis=0), p.max(axis=0)
    width = int(math.ceil(hi[0] - lo[0])) + 1
    height = int(math.ceil(hi[1] - lo[1])) + 1
    off = np.ravel(spec.offset_px).astype(float)
    tx = (width - 1) / 2 - (lo[0] + hi[0]) / 2 + off[0]
    ty = (height - 1) / 2 - (lo[1] + hi[1]) / 2 + off[1]
    cl, ct, cr, cb = spec.crop_px(s)
    tx, ty = tx - cl, ty - ct
    width, height = width - cl - cr, height - ct - cb
    if width < 16 or height < 16:
        raise SoftplotError(f"synthetic scan: crop leaves {max(width, 0)} x {max(height, 0)} px")
    if width * height > 2_000_000_000:
        raise SoftplotError(f"synthetic scan: {width} x {height} px is too large")
    mapping = TruthMapping(
        deformation, Scanner(spec.dpi, spec.rotation_deg, spec.anisotropy_ppm, tx, ty)
    )

    # -- marks: exact coverage, states -------------------------------------------------------
    mk = _marks(cam, spec)
    n_marks = len(mk.name)
    xy_px = mapping.film_to_pixel(mk.film) if n_marks else np.zeros((0, 2))
    bands = _dark_bands(cam, spec)
    in_dark = np.zeros(n_marks, bool)
    for lo, hi in bands:
        in_dark |= (mk.film[:, 1] > lo) & (mk.film[:, 1] < hi) & (np.array(mk.kind) == "reseau")
    one_armed = _choose_one_armed(spec, mk, mapping, (width, height), _rng(seed, "onearm"),
                                  in_dark)
    for i, axis in one_armed.items():
        mk.shapes[i] = bar_shape(mk.shapes[i], axis)
    groups: dict[tuple, list[int]] = {}
    for i, shp in enumerate(mk.shapes):
        groups.setdefault(_shape_key(shp), []).append(i)
    curved = deformation.amp.size > 0
    parts = []
    hidden = []
    post_blur = False
    op = float(spec.mark_opacity)
    for members in groups.values():
        members = np.array(members)
        idx, col, row, val, post_blur = render_marks(
            mapping, mk.film[members], mk.shapes[members[0]], spec.blur_sigma_px,
            spec.subrows, curvature=curved,
        )
        parts.append((members[idx], col, row, val))
        if post_blur and marks and spec.occlusion == "exact":
            # the area each opaque mark hides on the film, exact coverage of every pixel: the
            # scene there never reaches the scanner's optics
            a_idx, a_col, a_row, a_cov = area_coverage(
                mapping, mk.film[members], mk.shapes[members[0]], spec.subrows)
            hidden.append((a_col, a_row, a_cov * op))
    if parts:
        m_idx, m_col, m_row, m_val = (np.concatenate(a) for a in zip(*parts, strict=True))
    else:
        m_idx = m_col = m_row = np.zeros(0, int)
        m_val = np.zeros(0)
    inside = (m_col >= 0) & (m_col < width) & (m_row >= 0) & (m_row < height)
    total = np.bincount(m_idx, weights=m_val, minlength=n_marks)
    within = np.bincount(m_idx[inside], weights=m_val[inside], minlength=n_marks)
    frac = np.clip(np.where(total > 0, within / np.where(total > 0, total, 1.0), 0.0), 0, 1)
    # geometry: every outline point of the mark (exact mapping) inside the pixel area?
    box = np.zeros((n_marks, 4), int)
    geom_in = np.zeros(n_marks, bool)
    halo = int(math.ceil(3 * spec.blur_sigma_px)) + 1
    for i in range(n_marks):
        o = mapping.film_to_pixel(mk.shapes[i].outline_mm() + mk.film[i])
        geom_in[i] = bool(np.all((o >= -0.5) & (o <= np.array([width, height]) - 0.5)))
        lo_, hi_ = np.floor(o.min(axis=0)).astype(int), np.ceil(o.max(axis=0)).astype(int)
        box[i] = (lo_[0] - halo, lo_[1] - halo, hi_[0] + halo, hi_[1] + halo)
    state = np.where(geom_in, "visible", np.where(frac <= 1e-6, "outside", "cut")).astype(object)
    # a flat dark region that exposes (almost) nothing leaves the crosses in it no contrast
    floor = max(spec.noise_sigma, 1.0 / (2**spec.bits - 1) if spec.bits < 32 else 0.0)
    dark = in_dark & (spec.dark_level * spec.contrast * op <= floor)
    state[dark & geom_in] = "dark"
    # intensity centroid of each imaged mark minus its true position (the mapping's curvature
    # across the mark; 0 for an affine mapping)
    shift = np.full((n_marks, 2), np.nan)
    if post_blur and len(m_idx):
        cx = np.bincount(m_idx, weights=m_val * m_col, minlength=n_marks)
        cy = np.bincount(m_idx, weights=m_val * m_row, minlength=n_marks)
        ok = total > 0
        shift[ok, 0] = cx[ok] / total[ok] - xy_px[ok, 0]
        shift[ok, 1] = cy[ok] / total[ok] - xy_px[ok, 1]

    # -- levels ---------------------------------------------------------------------------
    mark_level = spec.background - spec.contrast  # positive film, fraction of full scale
    channels = 3 if spec.rgb else 1
    mask = np.array(ORANGE_MASK if (spec.rgb and spec.polarity == "negative") else (1.0,) * 3)
    mask = mask[:channels] if channels == 3 else np.ones(1)
    luma = float(np.dot(LUMA, mask)) if channels == 3 else 1.0

    # -- defects on the film surface (pixel system) -------------------------------------------
    patches: list[_Patch] = []
    covered = _choose_cover(spec, mk, state, _rng(seed, "cover"))
    rng_c = _rng(seed, "cover", 1)
    jac = mapping.jacobian(mk.film) if n_marks else np.zeros((0, 2, 2))
    for i in covered:
        rad = mk.shapes[i].radius_mm * float(np.max(np.linalg.norm(jac[i], axis=1)))
        need = rad + 3 * spec.blur_sigma_px + 2
        poly = _blob(xy_px[i] + rng_c.uniform(-0.1, 0.1, 2) * rad, need * 1.12, rng_c)
        pt = _patch(poly, rng_c.uniform(0.02, 0.25), 1.0, "cover")
        if pt is not None:
            patches.append(pt)
        state[i] = "covered"
    patches += _dust(spec.dust, width, height, s, _rng(seed, "dust"))
    patches += _scratches(spec.scratches, width, height, s, _rng(seed, "scratch"))
    damaged = np.zeros(n_marks, bool)
    for pt in patches:
        if pt.kind == "cover":
            continue
        ph, pw = pt.alpha.shape
        cand = np.nonzero(
            (box[:, 0] <= pt.c0 + pw - 1) & (box[:, 2] >= pt.c0)
            & (box[:, 1] <= pt.r0 + ph - 1) & (box[:, 3] >= pt.r0)
        )[0]
        for i in cand:
            r0, r1 = max(box[i, 1], pt.r0), min(box[i, 3], pt.r0 + ph - 1) + 1
            c0, c1 = max(box[i, 0], pt.c0), min(box[i, 2], pt.c0 + pw - 1) + 1
            if np.any(pt.alpha[r0 - pt.r0 : r1 - pt.r0, c0 - pt.c0 : c1 - pt.c0] > 0.02):
                damaged[i] = True

    # -- scene ----------------------------------------------------------------------------
    corners = mapping.pixel_to_film(
        np.array([[-1, -1], [width, -1], [-1, height], [width, height]], float)
    )
    ext = (corners[:, 0].min() - 1, corners[:, 0].max() + 1,
           corners[:, 1].min() - 1, corners[:, 1].max() + 1)
    arm = ((cam.reseau.arm_length_mm * spec.mark_arm_scale,
            cam.reseau.line_width_mm * spec.mark_width_scale) if cam.reseau else (1.0, 0.05))
    scene = Scene(spec.scene, ext, s, _rng(seed, "scene"), rgb=spec.rgb, avoid_mm=mk.film,
                  avoid_radius_mm=1.5 * arm[0] + 0.5, cross_mm=arm)

    image = _compose(spec, seed, mapping, scene, (width, height), (fw, fh), s, mark_level,
                     mask, (m_idx, m_col, m_row, m_val * op if marks else m_val * 0), post_blur,
                     patches, clip or spec.bits != 32, bands,
                     hide=tuple(np.concatenate(a) for a in zip(*hidden, strict=True))
                     if hidden else None)

    # -- truth ----------------------------------------------------------------------------
    local = _local_contrast(scene, mk, spec.contrast) * luma * op
    local[in_dark] = spec.contrast * spec.dark_level * luma * op
    r = cam.reseau
    if r is not None:
        lw_mm, arm_mm = arm[1], arm[0]
    elif cam.fiducials:
        lw_mm, arm_mm = cam.fiducials[0].line_width_mm, cam.fiducials[0].size_mm
    else:  # pragma: no cover - a certificate always has marks
        lw_mm, arm_mm = 0.0, 0.0
    scale_px = s * deformation.scale
    bg_grey = (1 - spec.background if spec.polarity == "negative" else spec.background) * luma
    mk_grey = (1 - mark_level if spec.polarity == "negative" else mark_level) * luma
    marks = []
    for i in range(n_marks):
        marks.append({
            "kind": mk.kind[i],
            "name": mk.name[i],
            "row": mk.row[i],
            "col": mk.col[i],
            "film_x": float(mk.film[i, 0]),
            "film_y": float(mk.film[i, 1]),
            "x": float(xy_px[i, 0]),
            "y": float(xy_px[i, 1]),
            "visible": bool(state[i] == "visible"),
            "state": str(state[i]),
            "inside_fraction": float(frac[i]),
            "shape": mk.shapes[i].kind,
            "contrast": float(local[i, 0]),
            "contrast_min": float(local[i, 1]),
            "damaged": bool(damaged[i]),
            "centroid_shift_px": (
                None if np.isnan(shift[i, 0]) else [float(shift[i, 0]), float(shift[i, 1])]
            ),
            "arms": (0 if state[i] in ("dark", "covered", "outside")
                     else 1 if i in one_armed else 2),
            "arm_axis": one_armed.get(i),
            "arm_length_mm": _shape_size(mk.shapes[i])[0],
            "line_width_mm": _shape_size(mk.shapes[i])[1],
            "dark": bool(in_dark[i]),
        })
    noise_grey = spec.noise_sigma * (math.sqrt(sum(w * w for w in LUMA)) if channels == 3 else 1.0)
    truth = {
        "format": "softplot-synthetic-truth",
        "version": 1,
        "image": None,
        "camera": cam.name,
        "width": int(width),
        "height": int(height),
        "dpi": float(spec.dpi),
        "polarity": spec.polarity,
        "bit_depth": int(spec.bits),
        "channels": int(channels),
        "seed": seed,
        "format_mm": [float(fw), float(fh)],
        "marks": marks,
        "mapping": mapping.to_dict(),
        "render": {
            "units": "fraction of full scale of the grey image (BT.601 luma for RGB)",
            "blur_sigma_px": float(spec.blur_sigma_px),
            "psf": (
                "marks: Gaussian(blur_sigma_px) * unit pixel box, exact before sampling; "
                "scene: sampled, then Gaussian(blur_sigma_px)"
                if post_blur else "area-sampled, then Gaussian(blur_sigma_px)"
            ),
            "edge_sigma_px": float(math.sqrt(spec.blur_sigma_px**2 + (1 / 12 if post_blur else 0))),
            "noise_sigma": float(noise_grey),
            "noise_sigma_channel": float(spec.noise_sigma),
            "grain_sigma": float(spec.grain_sigma),
            "contrast": float(spec.contrast * luma),
            "background": float(bg_grey),
            "mark_level": float(mk_grey),
            "line_width_px": float(lw_mm * scale_px),
            "arm_half_length_px": float(arm_mm / 2 * scale_px),
            "subrows": int(spec.subrows),
            "occlusion": spec.occlusion if post_blur else "exact",
            "orange_mask": [float(v) for v in mask] if channels == 3 else None,
        },
        "spec": spec.to_dict(),
    }
    return image, truth


def _shape_size(shape: MarkShape) -> tuple[float | None, float | None]:
    """(arm length, line width) film mm of a cross or bar (None, None for other shapes)."""
    if shape.kind not in ("cross", "bar"):
        return None, None
    hx, hy = float(shape.rects[0, 0]), float(shape.rects[0, 1])
    return 2 * max(hx, hy), 2 * min(hx, hy)


def _choose_cover(spec: ScanSpec, mk: _Marks, state: np.ndarray, rng) -> list[int]:
    if isinstance(spec.cover, (tuple, list)):
        where = {n: i for i, n in enumerate(mk.name)}
        out = []
        for n in spec.cover:
            if n not in where:
                raise SoftplotError(f"synthetic scan: cannot cover {n!r}: no such mark")
            if state[where[n]] != "visible":
                raise SoftplotError(f"synthetic scan: cannot cover {n!r}: it is {state[where[n]]}")
            out.append(where[n])
        return out
    n = int(spec.cover)
    if n == 0:
        return []
    kinds = np.array(mk.kind)
    pool = np.nonzero((state == "visible") & (kinds == "reseau"))[0]
    if len(pool) == 0:
        pool = np.nonzero(state == "visible")[0]
    if n > len(pool):
        raise SoftplotError(f"synthetic scan: cannot cover {n} marks, only {len(pool)} visible")
    return sorted(int(i) for i in rng.choice(pool, n, replace=False))


def _dust(n: int, width: int, height: int, s: float, rng) -> list[_Patch]:
    out = []
    for _ in range(n):
        c = rng.uniform([0, 0], [width, height])
        value = rng.uniform(0.0, 0.15)
        if rng.uniform() < 0.7:  # speck
            r = rng.uniform(0.01, 0.08) * s
            pt = _patch(_blob(c, max(r, 0.7), rng, 12), value, rng.uniform(0.8, 1.0), "dust")
        else:  # fibre
            steps = int(rng.integers(4, 12))
            seg = rng.uniform(0.05, 0.25) * s
            head = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.35, steps))
            pts = c + np.cumsum(np.column_stack([np.cos(head), np.sin(head)]) * seg, axis=0)
            pt = _patch(np.vstack([c, pts]), value, rng.uniform(0.7, 1.0), "dust",
                        thickness=rng.uniform(0.008, 0.025) * s)
        if pt is not None:
            out.append(pt)
    return out


def _scratches(n: int, width: int, height: int, s: float, rng) -> list[_Patch]:
    out = []
    for _ in range(n):
        vertical = rng.uniform() < 0.7
        span = height if vertical else width
        length = rng.uniform(0.3, 1.0) * span
        start = rng.uniform(-0.1, 0.6) * span
        across = rng.uniform(0, width if vertical else height)
        k = 24
        along = start + np.linspace(0, length, k)
        drift = np.cumsum(rng.normal(0, 0.002 * length / k, k)) + np.linspace(0, 1, k) * rng.normal(
            0, 0.01 * length
        )
        pts = np.column_stack([across + drift, along] if vertical else [along, across + drift])
        bright = rng.uniform() < 0.6
        pt = _patch(pts, 1.0 if bright else 0.05, rng.uniform(0.3, 0.7), "scratch",
                    thickness=rng.uniform(0.005, 0.02) * s)
        if pt is not None:
            out.append(pt)
    return out


def _local_contrast(scene: Scene, mk: _Marks, contrast: float) -> np.ndarray:
    """(mean, min) of contrast * g around each mark, over its centre, half-arms and tips."""
    n = len(mk.name)
    out = np.zeros((n, 2))
    if n == 0:
        return out
    pts = []
    for i in range(n):
        o = mk.shapes[i].outline_mm()
        rad = mk.shapes[i].radius_mm
        ring = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [0.7, 0.7], [-0.7, 0.7],
                         [0.7, -0.7], [-0.7, -0.7]]) * rad * 1.15
        pts.append(np.vstack([ring, o[: min(len(o), 8)] * 0.5]) + mk.film[i])
    k = len(pts[0])
    same = all(len(p) == k for p in pts)
    if same:
        g = scene.sample_points(np.vstack(pts)).reshape(n, k)
        out[:, 0] = contrast * g.mean(axis=1)
        out[:, 1] = contrast * g.min(axis=1)
    else:
        for i, p in enumerate(pts):
            g = scene.sample_points(p)
            out[i] = contrast * g.mean(), contrast * g.min()
    return out


def _film_maps(mapping: TruthMapping, width: int, height: int):
    """Exact film mm on a coarse pixel grid, interpolated along x: (Cx_u, Cx_v, node rows)."""
    nx = (width - 1) // _GRID + 2
    ny = (height - 1) // _GRID + 2
    gx, gy = np.meshgrid(np.arange(nx) * _GRID, np.arange(ny) * _GRID)
    film = mapping.pixel_to_film(np.column_stack([gx.ravel(), gy.ravel()]).astype(float))
    fu = film[:, 0].reshape(ny, nx).astype(np.float32)
    fv = film[:, 1].reshape(ny, nx).astype(np.float32)
    x = np.arange(width)
    i0 = x // _GRID
    w = ((x - i0 * _GRID) / _GRID).astype(np.float32)[None, :]
    cu = fu[:, i0] * (1 - w) + fu[:, i0 + 1] * w
    cv = fv[:, i0] * (1 - w) + fv[:, i0 + 1] * w
    return cu, cv


def _rows_film(cu: np.ndarray, cv: np.ndarray, r0: int, r1: int):
    y = np.arange(r0, r1)
    j0 = y // _GRID
    w = ((y - j0 * _GRID) / _GRID).astype(np.float32)[:, None]
    u = cu[j0] * (1 - w) + cu[j0 + 1] * w
    v = cv[j0] * (1 - w) + cv[j0 + 1] * w
    return u, v


def _on_image_by_row(col, row, val, width, height):
    """Sparse pixel entries (col, row, value) inside the image, sorted by row (stable);
    values float32."""
    keep = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    order = np.argsort(row[keep], kind="stable")
    return col[keep][order], row[keep][order], val[keep][order].astype(np.float32)


def _compose(spec, seed, mapping, scene, size, format_mm, s, mark_level, mask, sparse,
             post_blur, patches, clip=True, bands=(), hide=None):
    width, height = size
    fw, fh = format_mm
    channels = 3 if spec.rgb else 1
    dtype = {8: np.uint8, 16: np.uint16, 32: np.float32}[spec.bits]
    full = {8: 255.0, 16: 65535.0, 32: 1.0}[spec.bits]
    out = np.empty((height, width, channels), dtype)
    sig = spec.blur_sigma_px
    rad = int(math.ceil(4 * sig)) if sig > 0 else 0
    halo = rad + 1 if sig > 0 else 0
    # no per-pixel film coordinates needed
    flat = spec.scene == "none" and not spec.rgb and not bands
    if flat:  # the format's outline in pixels (1/16 px vertices, every ~0.5 mm of film)
        n_side = int(max(fw, fh) / 0.5) + 2
        t = np.linspace(-0.5, 0.5, n_side)
        ring = np.concatenate([
            np.column_stack([t * fw, np.full(n_side, fh / 2)]),
            np.column_stack([np.full(n_side, fw / 2), -t * fh]),
            np.column_stack([-t * fw, np.full(n_side, -fh / 2)]),
            np.column_stack([np.full(n_side, -fw / 2), t * fh]),
        ])
        outline = mapping.film_to_pixel(ring)
    else:
        cu, cv = _film_maps(mapping, width, height)
    m_idx, m_col, m_row, m_val = sparse
    m_col, m_row, m_val = _on_image_by_row(m_col, m_row, m_val, width, height)
    if hide is not None:
        h_col, h_row, h_cov = _on_image_by_row(*hide, width, height)
    sign = np.float32(-1.0 if spec.polarity == "negative" else 1.0)
    grain = _BlockNormals(seed, "grain", width, channels) if spec.grain_sigma > 0 else None
    noise = _BlockNormals(seed, "noise", width, channels) if spec.noise_sigma > 0 else None
    level = np.float32(mark_level)
    contrast = np.float32(spec.contrast)
    mask32 = mask.astype(np.float32)
    strip = max(_BLOCK, min(8 * _BLOCK, (1 << 21) // max(width, 1) // _BLOCK * _BLOCK))
    for r0 in range(0, height, strip):
        r1 = min(height, r0 + strip)
        a0, a1 = max(0, r0 - halo), min(height, r1 + halo)
        # exposed scene inside the format, unexposed film (mark level) outside it
        if flat:
            inside = np.zeros((a1 - a0, width), np.uint8)
            pts = np.round((outline - (0, a0)) * 16).astype(np.int32)
            cv2.fillPoly(inside, [pts], 255, cv2.LINE_AA, 4)
            val = (level + contrast * (inside.astype(np.float32) / np.float32(255)))[:, :, None]
        else:
            u, v = _rows_film(cu, cv, a0, a1)
            g = scene.sample(u, v)
            if bands:  # flat dark regions: the scene replaced by dark_level
                dk = np.zeros(v.shape, bool)
                for lo, hi in bands:
                    dk |= (v > lo) & (v < hi)
                if dk.any():
                    g = np.where(dk[..., None] if g.ndim == 3 else dk, np.float32(spec.dark_level),
                                 g).astype(np.float32)
            val = (level + contrast * g).astype(np.float32)
            if val.ndim == 2:
                val = val[:, :, None]
            outside = np.maximum(np.abs(u) - fw / 2, np.abs(v) - fh / 2) * s  # soft edge, 1 px
            border = np.clip(0.5 + outside, 0.0, 1.0).astype(np.float32)[:, :, None]
            val += (level - val) * border
        # marks: exact coverage before the blur, or the exactly blurred marks after it
        if post_blur:
            lo, hi = np.searchsorted(m_row, [r0, r1])
            rr, cc, mv = m_row[lo:hi] - a0, m_col[lo:hi], m_val[lo:hi, None]
            # mark minus background (k, C), positive film. The opaque mark hides the scene,
            # and both pass the same optics: the image is blur(scene) + (mark - scene) x
            # blur(mark), to first order with the scene taken as the optically blurred one
            # (the unblurred scene would put unblurred scene edges into the mark's image)
            seen = val
            if sig > 0 and hi > lo:
                k = 2 * rad + 1
                seen = cv2.GaussianBlur(val, (k, k), sig, sigmaY=sig,
                                        borderType=cv2.BORDER_REFLECT_101)
                if seen.ndim == 2:
                    seen = seen[:, :, None]
            mark_amp = level - seen[rr, cc]
            trans = np.ones((a1 - a0, width, 1), np.float32)
            corr = None
            if hide is not None and sig > 0:
                # exact physics: the film under an opaque mark shows the mark, not the scene,
                # before the optics blur it: image = blur(scene x (1 - C)) + mark x blur(C)
                # with C the mark's coverage. The mark's term is the analytic blurred mark
                # (exact sampling); the scene's term is the blur of the scene with the marks'
                # pixels cut out by their exact area coverage, plus blur(scene) x (blur(C) -
                # blurred mark), which is 0 for a flat scene (aliasing of the coverage).
                q0, q1 = np.searchsorted(h_row, [a0, a1])
                if q1 > q0:
                    C = np.zeros((a1 - a0, width), np.float32)
                    np.add.at(C, (h_row[q0:q1] - a0, h_col[q0:q1]), h_cov[q0:q1])
                    np.minimum(C, 1.0, out=C)
                    k = 2 * rad + 1
                    Cb = cv2.GaussianBlur(C, (k, k), sig, sigmaY=sig,
                                          borderType=cv2.BORDER_REFLECT_101)[:, :, None]
                    corr = seen * Cb
                    val = val * (1.0 - C[:, :, None])
        else:
            lo, hi = np.searchsorted(m_row, [a0, a1])
            if hi > lo:
                rr, cc, cov = m_row[lo:hi] - a0, m_col[lo:hi], m_val[lo:hi, None]
                val[rr, cc] += (level - val[rr, cc]) * cov
        if grain is not None:
            val += np.float32(spec.grain_sigma) * grain.rows(a0, a1)
        if spec.polarity == "negative":
            val = np.float32(1.0) - val
        if channels == 3:
            val *= mask32
        for pt in patches:
            ph, pw = pt.alpha.shape
            q0, q1 = max(a0, pt.r0), min(a1, pt.r0 + ph)
            c0, c1 = max(0, pt.c0), min(width, pt.c0 + pw)
            if q0 >= q1 or c0 >= c1:
                continue
            al = pt.alpha[q0 - pt.r0 : q1 - pt.r0, c0 - pt.c0 : c1 - pt.c0, None]
            reg = val[q0 - a0 : q1 - a0, c0:c1]
            reg += (np.float32(pt.value) - reg) * al
            if post_blur:
                trans[q0 - a0 : q1 - a0, c0:c1] *= 1 - al
        if sig > 0:
            k = 2 * rad + 1
            blurred = cv2.GaussianBlur(val, (k, k), sig, sigmaY=sig,
                                       borderType=cv2.BORDER_REFLECT_101)
            if blurred.ndim == 2:
                blurred = blurred[:, :, None]
            core = blurred[r0 - a0 : r1 - a0]
        else:
            core = val[r0 - a0 : r1 - a0].copy()
        if post_blur and hi > lo:
            amp = sign * mask32 * mark_amp * trans[rr, cc]
            core[rr - (r0 - a0), cc] += amp * mv
            if corr is not None:
                core += (sign * mask32 * corr * trans)[r0 - a0 : r1 - a0]
        if noise is not None:
            core = core + np.float32(spec.noise_sigma) * noise.rows(r0, r1)
        if clip:
            np.clip(core, 0.0, 1.0, out=core)
        if spec.bits == 32:
            out[r0:r1] = core
        else:
            out[r0:r1] = (core * np.float32(full) + np.float32(0.5)).astype(dtype)
    return out[:, :, 0] if channels == 1 else out
