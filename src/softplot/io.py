"""Scan files in and out: TIFF, PNG, JPEG and camera RAW into a :class:`Scan`.

All arrays here are in the **pixel system**: x right (column), y down (row), (0, 0) the centre
of the top-left pixel (OpenCV convention); ``data[row, col]``.

Readers
-------
* TIFF (``.tif``, ``.tiff``, ``.btf``, ``.tf8``, ``.tf2``) via :mod:`tifffile`: 1/8/16-bit
  integer or 16/32/64-bit float samples, grey, grey+alpha, RGB, RGBA or palette,
  uncompressed or compressed (LZW, deflate, JPEG, zstd ... whatever tifffile and imagecodecs
  decode), stripped or tiled, classic or BigTIFF. In a multi-page file the first page that is
  not a reduced-resolution image (``NewSubfileType`` bit 0) is read, normally page 0. An
  uncompressed, contiguous page is **memory-mapped read-only** (``numpy.memmap``), so a
  gigapixel scan is not copied; :meth:`Scan.grey` converts only the window asked for.
  ``MinIsWhite`` photometric data are kept as stored and inverted by the grey/colour
  conversion. dpi comes from ``XResolution``/``YResolution`` and ``ResolutionUnit``
  (centimetres are converted to inches; unit "none" gives no dpi; a missing unit means inch,
  the TIFF default).
* PNG and JPEG via OpenCV (``cv2.imdecode`` with ``IMREAD_UNCHANGED``: 8 or 16 bit, no EXIF
  orientation applied, BGR(A) reordered to RGB(A)). dpi from the PNG ``pHYs`` chunk, or the
  JPEG JFIF density (when its unit is dpi or dots/cm) or else the EXIF ``XResolution`` /
  ``ResolutionUnit`` of IFD0. OpenCV refuses images above ``OPENCV_IO_MAX_IMAGE_PIXELS``
  (default 2**30 pixels); store larger scans as TIFF.
* Camera RAW (DNG, NEF, CR2, CR3, ARW, ORF, RAF, RW2, PEF, SRW, ...) via :mod:`rawpy`
  (LibRaw), developed **linearly**: ``gamma=(1, 1)``, ``no_auto_bright=True``,
  ``output_bps=16``, ``use_camera_wb=True`` (the white balance as shot), ``user_flip=0`` (no
  rotation: the frame as the sensor read it, whatever the camera's orientation flag says).
  The result is 16-bit RGB; dpi is unknown (None) for a camera file.

The file type is chosen by the file name extension (case-insensitive).

Grey conversion
---------------
Integer samples are divided by ``2**bit_depth - 1`` (so 8-bit 255 and 16-bit 65535 are 1.0);
float samples are taken as they are (assumed to lie in [0, 1]; NaN stays NaN). RGB(A) is
reduced to luminance with the ITU-R BT.601 weights 0.299 R + 0.587 G + 0.114 B (alpha
ignored); grey+alpha keeps the grey channel. The result is float32.

Errors
------
Every problem with a file (missing, a directory, empty, truncated or corrupt, unsupported
extension or sample type, zero-size image, a float image with no finite pixel) raises
:class:`softplot.errors.ScanError` with one line ``"<path>: <problem>"``.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from softplot.errors import ScanError

__all__ = [
    "Scan",
    "load_scan",
    "save_tiff",
    "scan_kind",
    "fingerprint",
    "check_fingerprint",
    "BT601",
    "TIFF_EXTENSIONS",
    "PNG_EXTENSIONS",
    "JPEG_EXTENSIONS",
    "RAW_EXTENSIONS",
    "SUPPORTED_EXTENSIONS",
]

#: ITU-R BT.601 luma weights (R, G, B)
BT601 = (0.299, 0.587, 0.114)

TIFF_EXTENSIONS = frozenset({".tif", ".tiff", ".btf", ".tf8", ".tf2"})
PNG_EXTENSIONS = frozenset({".png"})
JPEG_EXTENSIONS = frozenset({".jpg", ".jpeg", ".jpe", ".jfif"})
RAW_EXTENSIONS = frozenset(
    {
        ".dng", ".nef", ".nrw", ".cr2", ".cr3", ".crw", ".arw", ".srf", ".sr2", ".orf",
        ".raf", ".rw2", ".pef", ".srw", ".3fr", ".fff", ".erf", ".kdc", ".dcr", ".mrw",
        ".mos", ".iiq", ".rwl", ".mef", ".x3f", ".raw",
    }
)
SUPPORTED_EXTENSIONS = TIFF_EXTENSIONS | PNG_EXTENSIONS | JPEG_EXTENSIONS | RAW_EXTENSIONS

#: pixels converted per block by :meth:`Scan.grey` (bounds the temporary memory)
_BLOCK_PIXELS = 1 << 22

_INCH_PER_CM = 1.0 / 2.54


def _one_line(exc: BaseException | str) -> str:
    """An exception message squeezed onto one line."""
    text = str(exc) if str(exc) else type(exc).__name__
    return " ".join(text.split())


def _quiet_logger(name: str) -> None:
    """Give a library logger a NullHandler (so Python's last-resort stderr print is not used)."""
    log = logging.getLogger(name)
    if not any(isinstance(h, logging.NullHandler) for h in log.handlers):
        log.addHandler(logging.NullHandler())


def _codec_error(exc: BaseException) -> bool:
    """True for the error classes of imagecodecs (the compression codecs behind tifffile)."""
    return type(exc).__module__.split(".")[0] == "imagecodecs"


# ---------------------------------------------------------------------------------------------
# the Scan


@dataclass(eq=False)
class Scan:
    """A scanned photograph: its pixels as stored plus metadata.

    Parameters
    ----------
    path : Path or None
        The file it came from (None for an in-memory array).
    data : ndarray
        Native pixels as stored, pixel system, shape (H, W) or (H, W, C), dtype bool, uint8,
        uint16, uint32 or float. Possibly a read-only ``numpy.memmap``: never modify it.
    dpi : float or None
        Scan resolution in dots per inch (the x resolution when x and y differ), None when
        the file does not say.
    bit_depth : int
        Bits per sample as stored (1, 8, 12, 16, ... for integers; 16/32/64 for floats).
        Integer samples are divided by ``2**bit_depth - 1`` to get [0, 1].
    channels : int
        1 grey, 2 grey+alpha, 3 RGB, 4 RGBA.
    file_format : str
        "tiff", "png", "jpeg", "raw" or "array".
    dpi_xy : (float, float) or None
        x and y resolution in dpi.
    min_is_white : bool
        True for grey data stored with 0 = white (TIFF ``MinIsWhite``); the conversions
        invert it.
    """

    path: Path | None
    data: np.ndarray = field(repr=False)
    dpi: float | None = None
    bit_depth: int = 8
    channels: int = 1
    file_format: str = "array"
    dpi_xy: tuple[float, float] | None = None
    min_is_white: bool = False
    _pixels: np.ndarray | None = field(default=None, init=False, repr=False)

    # -- construction ------------------------------------------------------------------------

    @classmethod
    def from_array(
        cls,
        arr: np.ndarray,
        dpi: float | None = None,
        *,
        bit_depth: int | None = None,
        path: str | Path | None = None,
    ) -> "Scan":
        """A Scan around an in-memory array (pixel system, (H, W) or (H, W, C)); no copy.

        ``bit_depth`` defaults to the storage size of an integer dtype (8 for uint8, 16 for
        uint16 ...) and to the float size for floats (whose values are taken as [0, 1]).
        A trailing channel axis of length 1 is dropped (a view).
        """
        a = np.asarray(arr)
        where = str(path) if path is not None else "<array>"
        a = _check_array(a, where)
        depth = _default_depth(a.dtype) if bit_depth is None else int(bit_depth)
        if a.dtype.kind in "ui" and not 1 <= depth <= 8 * a.dtype.itemsize:
            raise ScanError(f"{where}: bit depth {depth} does not fit dtype {a.dtype}")
        dpi_f = _positive_or_none(dpi)
        return cls(
            path=Path(path) if path is not None else None,
            data=a,
            dpi=dpi_f,
            bit_depth=depth,
            channels=1 if a.ndim == 2 else int(a.shape[2]),
            file_format="array",
            dpi_xy=(dpi_f, dpi_f) if dpi_f is not None else None,
        )

    # -- shape -------------------------------------------------------------------------------

    @property
    def width(self) -> int:
        """Number of pixel columns (x extent)."""
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        """Number of pixel rows (y extent)."""
        return int(self.data.shape[0])

    @property
    def is_memmap(self) -> bool:
        """True when :attr:`data` is memory-mapped from the file (not copied)."""
        return isinstance(self.data, np.memmap)

    @property
    def full_scale(self) -> float:
        """The stored value that means 1.0 (``2**bit_depth - 1``; 1.0 for floats)."""
        if self.data.dtype.kind == "f":
            return 1.0
        return float(2**self.bit_depth - 1)

    # -- conversions -------------------------------------------------------------------------

    @property
    def pixels(self) -> np.ndarray:
        """The whole image as float32 grey in [0, 1], shape (H, W), pixel system; cached.

        This allocates 4 bytes per pixel; on a huge scan prefer :meth:`grey` with a window.
        The cached array is read-only (it is shared); ``.copy()`` it to change it.
        """
        if self._pixels is None:
            g = self.grey()
            g.flags.writeable = False  # shared by every caller: copy before changing it
            self._pixels = g
        return self._pixels

    def grey(self, window: tuple[slice, slice] | None = None) -> np.ndarray:
        """Float32 grey in [0, 1] of a window, converting only that window.

        Parameters
        ----------
        window : (slice, slice), optional
            ``(rows, cols)`` slices in the pixel system (``data[rows, cols]``); None is the
            whole image.

        Returns
        -------
        ndarray
            float32, shape (h, w): BT.601 luminance for RGB(A), the grey channel otherwise,
            inverted for ``MinIsWhite`` data.
        """
        block = self.data[_window(window)]
        out = np.empty(block.shape[:2], np.float32)
        scale = np.float32(1.0 / self.full_scale)
        rgb = self.channels >= 3
        step = max(1, _BLOCK_PIXELS // max(1, block.shape[1]))
        tmp = None
        w = [np.float32(c * scale) for c in BT601]
        for r0 in range(0, block.shape[0], step):
            src = block[r0 : r0 + step]
            dst = out[r0 : r0 + step]
            if rgb:
                if tmp is None or tmp.shape != dst.shape:
                    tmp = np.empty_like(dst)
                np.multiply(src[..., 0], w[0], out=dst, dtype=np.float32)
                for k in (1, 2):
                    np.multiply(src[..., k], w[k], out=tmp, dtype=np.float32)
                    dst += tmp
            else:
                src = src[..., 0] if src.ndim == 3 else src
                np.multiply(src, scale, out=dst, dtype=np.float32)
        if self.data.dtype.kind != "f":
            np.minimum(out, np.float32(1.0), out=out)  # rounding of the weights; sub-depth data
        if self.min_is_white:
            np.subtract(np.float32(1.0), out, out=out)
        return out

    def colour(self, window: tuple[slice, slice] | None = None) -> np.ndarray:
        """Float32 samples in [0, 1] of a window, shape (h, w, C) (C = :attr:`channels`).

        Parameters
        ----------
        window : (slice, slice), optional
            ``(rows, cols)`` slices in the pixel system; None is the whole image.
        """
        block = self.data[_window(window)]
        if block.ndim == 2:
            block = block[..., None]
        out = np.multiply(block, np.float32(1.0 / self.full_scale), dtype=np.float32)
        if self.data.dtype.kind != "f":
            np.minimum(out, np.float32(1.0), out=out)
        if self.min_is_white:
            np.subtract(np.float32(1.0), out[..., :1], out=out[..., :1])
        return out

    def summary(self) -> str:
        """One line: size, bit depth, channels, dpi, format (what ``softplot info`` prints)."""
        names = {1: "grey", 2: "grey+alpha", 3: "RGB", 4: "RGBA"}
        kind = "bit float" if self.data.dtype.kind == "f" else "bit"
        dpi = f"{self.dpi:g} dpi" if self.dpi is not None else "dpi unknown"
        if self.dpi_xy is not None and self.dpi_xy[0] != self.dpi_xy[1]:
            dpi = f"{self.dpi_xy[0]:g} x {self.dpi_xy[1]:g} dpi"
        extra = ", memory-mapped" if self.is_memmap else ""
        return (
            f"{self.width} x {self.height} px, {self.bit_depth}-{kind}, {self.channels} "
            f"channel{'s' if self.channels > 1 else ''} ({names.get(self.channels, '?')}), "
            f"{dpi}, {self.file_format.upper()}{extra}"
        )


def _window(window: tuple[slice, slice] | None) -> tuple[slice, slice]:
    if window is None:
        return (slice(None), slice(None))
    if (
        not isinstance(window, tuple)
        or len(window) != 2
        or not all(isinstance(s, slice) for s in window)
    ):
        raise TypeError(f"window must be a (row slice, column slice) pair, got {window!r}")
    return window


def _default_depth(dtype: np.dtype) -> int:
    if dtype.kind == "b":
        return 1
    return 8 * dtype.itemsize


def _positive_or_none(v: float | None) -> float | None:
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) and v > 0 else None


def _check_array(a: np.ndarray, where: str) -> np.ndarray:
    """Validate the shape and dtype of stored pixels; return them (a view) or raise."""
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and not 1 <= a.shape[2] <= 4):
        raise ScanError(f"{where}: unsupported image shape {a.shape} (need H x W or H x W x 1-4)")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ScanError(f"{where}: zero-size image ({a.shape[1]} x {a.shape[0]} pixels)")
    if a.dtype.kind == "b" or (a.dtype.kind == "u" and a.dtype.itemsize <= 4):
        pass
    elif a.dtype.kind == "f" and a.dtype.itemsize in (2, 4, 8):
        if not _any_finite(a):
            raise ScanError(f"{where}: float image has no finite pixel (all NaN or infinite)")
    else:
        raise ScanError(f"{where}: unsupported sample type {a.dtype} (need unsigned int or float)")
    return a


def _any_finite(a: np.ndarray) -> bool:
    """True when a float array holds a finite value; samples first, then blocks of rows."""
    step = max(1, int(np.sqrt(a.shape[0] * a.shape[1] / 4096)))
    if np.isfinite(a[::step, ::step]).any():
        return True
    rows = max(1, _BLOCK_PIXELS // max(1, a.shape[1]))
    return any(np.isfinite(a[r : r + rows]).any() for r in range(0, a.shape[0], rows))


# ---------------------------------------------------------------------------------------------
# loading


def scan_kind(path: str | Path) -> str | None:
    """"tiff", "png", "jpeg" or "raw" from the file name extension; None if unsupported."""
    ext = Path(path).suffix.lower()
    for kind, exts in (
        ("tiff", TIFF_EXTENSIONS),
        ("png", PNG_EXTENSIONS),
        ("jpeg", JPEG_EXTENSIONS),
        ("raw", RAW_EXTENSIONS),
    ):
        if ext in exts:
            return kind
    return None


def check_scan_path(path) -> Path:
    """``path`` as a Path when it names a regular file; otherwise :class:`ScanError`, one line
    (``"<path>: file not found"``, a directory, not a regular file). Lets a command refuse a
    missing scan before it starts any work."""
    p = Path(path)
    if not p.exists():
        raise ScanError(f"{p}: file not found")
    if p.is_dir():
        raise ScanError(f"{p}: is a directory, not a scan file")
    if not p.is_file():
        raise ScanError(f"{p}: not a regular file")
    return p


def load_scan(path: str | Path) -> Scan:
    """Read a scan file (TIFF, PNG, JPEG or camera RAW) into a :class:`Scan`.

    Parameters
    ----------
    path : str or Path
        The file; its extension chooses the reader (see the module docstring).

    Returns
    -------
    Scan
        Native pixels (pixel system) plus dpi, bit depth and channels. An uncompressed
        contiguous TIFF is memory-mapped read-only.

    Raises
    ------
    ScanError
        One line ``"<path>: <problem>"`` for a missing, empty, corrupt, truncated or
        unsupported file, a zero-size image or a float image without a finite pixel.
    """
    p = check_scan_path(path)
    kind = scan_kind(p)
    if kind is None:
        raise ScanError(
            f"{p}: unsupported file type {p.suffix or '(no extension)'!r} "
            "(supported: TIFF, PNG, JPEG, camera RAW such as DNG, NEF, CR2, ARW)"
        )
    try:
        size = p.stat().st_size
        if size == 0:
            raise ScanError(f"{p}: empty file (0 bytes)")
        if not os.access(p, os.R_OK):
            raise ScanError(f"{p}: cannot read the file (permission denied)")
        reader = {"tiff": _load_tiff, "png": _load_cv2, "jpeg": _load_cv2, "raw": _load_raw}[kind]
        return reader(p, kind)
    except ScanError:
        raise
    except MemoryError:
        raise ScanError(f"{p}: not enough memory to read the scan") from None
    except OSError as exc:
        raise ScanError(f"{p}: cannot read: {_one_line(exc.strerror or exc)}") from None


def _make(p: Path, data: np.ndarray, kind: str, bit_depth: int,
          dpi_xy: tuple[float, float] | None, min_is_white: bool = False) -> Scan:
    data = _check_array(data, str(p))
    return Scan(
        path=p,
        data=data,
        dpi=dpi_xy[0] if dpi_xy is not None else None,
        bit_depth=bit_depth,
        channels=1 if data.ndim == 2 else int(data.shape[2]),
        file_format=kind,
        dpi_xy=dpi_xy,
        min_is_white=min_is_white,
    )


def _dpi(x: float | None, y: float | None, unit: str | None) -> tuple[float, float] | None:
    """(x, y) dots per inch from a resolution and its unit ("inch", "cm" or None)."""
    if unit not in ("inch", "cm") or x is None:
        return None
    y = x if y is None else y
    f = _INCH_PER_CM if unit == "cm" else 1.0
    x, y = x / f, y / f
    if not (np.isfinite(x) and np.isfinite(y) and x > 0 and y > 0):
        return None
    return (float(x), float(y))


# -- TIFF -------------------------------------------------------------------------------------


def _rational(tag) -> float | None:
    if tag is None:
        return None
    v = tag.value
    if isinstance(v, tuple) and len(v) == 2:
        return v[0] / v[1] if v[1] else None
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _tiff_dpi(page) -> tuple[float, float] | None:
    tags = page.tags
    unit_tag = tags.get("ResolutionUnit")
    code = int(unit_tag.value) if unit_tag is not None else 2  # TIFF default: inch
    unit = {2: "inch", 3: "cm"}.get(code)
    return _dpi(_rational(tags.get("XResolution")), _rational(tags.get("YResolution")), unit)


def _load_tiff(p: Path, kind: str) -> Scan:
    import tifffile

    # tifffile logs what it repairs or gives up on; without a handler of the application's
    # own, Python would print those records to stderr next to our one-line error
    _quiet_logger("tifffile")
    try:
        with tifffile.TiffFile(p) as tif:
            if len(tif.pages) == 0:
                raise ScanError(f"{p}: TIFF holds no image")
            index, page = 0, tif.pages.first
            for i, pg in enumerate(tif.pages):  # skip a leading reduced-resolution thumbnail
                if not int(getattr(pg, "subfiletype", 0)) & 1:
                    index, page = i, pg
                    break
            if page.shape and 0 in page.shape:
                raise ScanError(f"{p}: zero-size image ({page.imagewidth} x {page.imagelength} "
                                "pixels)")
            photometric = int(page.photometric)
            # 0 MinIsWhite, 1 MinIsBlack, 2 RGB, 3 palette, 6 YCbCr (decoded to RGB)
            if photometric not in (0, 1, 2, 3, 6):
                name = getattr(page.photometric, "name", str(photometric))
                raise ScanError(f"{p}: unsupported TIFF photometric interpretation {name}")
            if int(page.sampleformat) == 2:
                raise ScanError(f"{p}: unsupported signed-integer TIFF samples")
            axes = page.axes
            if axes not in ("YX", "YXS", "SYX"):
                raise ScanError(f"{p}: unsupported TIFF page layout {axes!r} (need one 2-D image)")
            depth = int(page.bitspersample)
            dpi_xy = _tiff_dpi(page)
            if page.is_memmappable:
                need = int(page.dataoffsets[0]) + int(np.prod(page.shape)) * page.dtype.itemsize
                if need > p.stat().st_size:
                    raise ScanError(f"{p}: truncated TIFF (image data end beyond the file)")
                data = tifffile.memmap(p, page=index, mode="r")
            else:
                data = page.asarray()
            if axes == "SYX":
                data = np.moveaxis(data, 0, -1)
            if photometric == 3:
                cmap = page.colormap
                if cmap is None:
                    raise ScanError(f"{p}: palette TIFF without a colour map")
                data = np.ascontiguousarray(np.asarray(cmap).T[np.asarray(data)])
                depth = 16
            return _make(p, data, kind, depth, dpi_xy, min_is_white=photometric == 0)
    except ScanError:
        raise
    except MemoryError:
        raise
    except (tifffile.TiffFileError, ValueError, KeyError, IndexError, struct.error,
            RuntimeError, TypeError, EOFError, NotImplementedError) as exc:
        raise ScanError(f"{p}: corrupt or truncated TIFF: {_one_line(exc)}") from None
    except Exception as exc:  # decoder errors from imagecodecs have their own classes
        if _codec_error(exc):
            raise ScanError(f"{p}: corrupt or truncated TIFF: {_one_line(exc)}") from None
        raise


# -- PNG / JPEG -------------------------------------------------------------------------------

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_check(buf: bytes) -> tuple[float, float] | None:
    """Walk the PNG chunks: raise ValueError if truncated; return the pHYs dpi if any."""
    if not buf.startswith(_PNG_MAGIC):
        raise ValueError("not a PNG file (bad signature)")
    pos, dpi, n = 8, None, len(buf)
    while True:
        if pos + 8 > n:
            raise ValueError("truncated PNG (no IEND chunk)")
        length, ctype = struct.unpack(">I4s", buf[pos : pos + 8])
        end = pos + 12 + length
        if end > n:
            raise ValueError(f"truncated PNG (chunk {ctype.decode('latin-1')!r} cut short)")
        if ctype == b"pHYs" and length == 9:
            px, py, unit = struct.unpack(">IIB", buf[pos + 8 : pos + 17])
            if unit == 1:  # pixels per metre
                dpi = _dpi(px / 100.0, py / 100.0, "cm")
        if ctype == b"IEND":
            return dpi
        pos = end


def _exif_dpi(tiff: bytes) -> tuple[float, float] | None:
    """XResolution/YResolution/ResolutionUnit of IFD0 of an EXIF (TIFF-structured) block."""
    bo = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if bo is None or struct.unpack(bo + "H", tiff[2:4])[0] != 42:
        return None
    ifd = struct.unpack(bo + "I", tiff[4:8])[0]
    (count,) = struct.unpack(bo + "H", tiff[ifd : ifd + 2])
    res: dict[int, float] = {}
    unit = 2
    for i in range(count):
        e = ifd + 2 + 12 * i
        tag, typ, _, raw = struct.unpack(bo + "HHI4s", tiff[e : e + 12])
        if tag in (282, 283) and typ == 5:
            (off,) = struct.unpack(bo + "I", raw)
            num, den = struct.unpack(bo + "II", tiff[off : off + 8])
            if den:
                res[tag] = num / den
        elif tag == 296 and typ == 3:
            (unit,) = struct.unpack(bo + "H", raw[:2])
    return _dpi(res.get(282), res.get(283), {2: "inch", 3: "cm"}.get(unit))


def _jpeg_check(buf: bytes) -> tuple[float, float] | None:
    """Check a JPEG's start and end markers; return the JFIF or EXIF dpi if any."""
    if not buf.startswith(b"\xff\xd8\xff"):
        raise ValueError("not a JPEG file (no SOI marker)")
    sos = buf.rfind(b"\xff\xda")
    if sos < 0 or buf.rfind(b"\xff\xd9") < sos:
        raise ValueError("truncated JPEG (no end-of-image marker after the image data)")
    jfif = exif = None
    pos, n = 2, len(buf)
    while pos + 4 <= n and buf[pos] == 0xFF:
        marker = buf[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xDA, 0xD9):  # start of scan / end of image: no more headers
            break
        (length,) = struct.unpack(">H", buf[pos + 2 : pos + 4])
        seg = buf[pos + 4 : pos + 2 + length]
        try:
            if marker == 0xE0 and seg[:5] == b"JFIF\x00" and len(seg) >= 12:
                unit, xd, yd = struct.unpack(">BHH", seg[7:12])
                jfif = _dpi(float(xd), float(yd), {1: "inch", 2: "cm"}.get(unit))
            elif marker == 0xE1 and seg[:6] == b"Exif\x00\x00":
                exif = _exif_dpi(seg[6:])
        except (struct.error, IndexError, ZeroDivisionError):
            pass  # malformed metadata: no dpi, the image itself may still be fine
        pos += 2 + length
    return jfif if jfif is not None else exif


@contextlib.contextmanager
def _quiet_cv2() -> Iterator[None]:
    import cv2

    try:
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - very old OpenCV
        yield
        return
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def _load_cv2(p: Path, kind: str) -> Scan:
    import cv2

    raw = p.read_bytes()
    try:
        dpi_xy = _png_check(raw) if kind == "png" else _jpeg_check(raw)
    except ValueError as exc:
        raise ScanError(f"{p}: {exc}") from None
    buf = np.frombuffer(raw, np.uint8)
    with _quiet_cv2():
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ScanError(f"{p}: corrupt {kind.upper()} file (OpenCV cannot decode it)")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return _make(p, img, kind, _default_depth(img.dtype), dpi_xy)


# -- camera RAW -------------------------------------------------------------------------------


def _load_raw(p: Path, kind: str) -> Scan:
    import rawpy

    try:
        with rawpy.imread(str(p)) as raw:
            # linear 16-bit, no brightening, the sensor's geometry: gamma 1, no auto-bright,
            # no white-level guess from the data (LibRaw's default adjust_maximum_thr=0.75
            # rescales a bright frame by its own maximum, so the same film would get another
            # gain in every exposure), no rotation from the file (the user's --rotate decides)
            rgb = raw.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                use_camera_wb=True,
                user_flip=0,
                adjust_maximum_thr=0.0,
            )
    except rawpy.LibRawError as exc:
        raise ScanError(f"{p}: cannot read camera RAW: {_one_line(exc)}") from None
    return _make(p, rgb, kind, 16, None)


# ---------------------------------------------------------------------------------------------
# writing


def save_tiff(
    path: str | Path,
    array: np.ndarray,
    dpi: float | tuple[float, float] | None = None,
    *,
    overwrite: bool = False,
    compression: str | None = None,
    tile: tuple[int, int] | None = None,
    bigtiff: bool = False,
    description: str | None = None,
) -> Path:
    """Write pixels (pixel system, (H, W) grey or (H, W, 3|4) RGB(A)) as a TIFF.

    Parameters
    ----------
    path : str or Path
        Destination; an existing file is refused unless ``overwrite`` is True.
    array : ndarray
        uint8, uint16 or float32 samples; a trailing axis of 1 is dropped.
    dpi : float or (float, float), optional
        Resolution written as ``XResolution``/``YResolution`` with ``ResolutionUnit`` inch.
    compression : str, optional
        Any tifffile compression ("lzw", "deflate", "jpeg" (8-bit only), "zstd" ...).
        Uncompressed (the default) and untiled files are contiguous, so :func:`load_scan`
        memory-maps them.
    tile : (int, int), optional
        Tile shape (multiples of 16).
    bigtiff : bool
        Write a BigTIFF (needed beyond 4 GB).
    description : str, optional
        ``ImageDescription`` text.

    Returns
    -------
    Path
        The written file.
    """
    import tifffile

    p = Path(path)
    a = np.asarray(array)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.dtype not in (np.uint8, np.uint16, np.float32):
        raise ScanError(f"{p}: cannot write {a.dtype} samples (need uint8, uint16 or float32)")
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)) or a.size == 0:
        raise ScanError(f"{p}: cannot write an image of shape {a.shape}")
    if p.exists() and not overwrite:
        raise ScanError(f"{p}: exists; refusing to overwrite")
    res = None
    if dpi is not None:
        dx, dy = (dpi, dpi) if np.isscalar(dpi) else tuple(dpi)
        if not (dx > 0 and dy > 0):
            raise ScanError(f"{p}: dpi must be positive, got {dpi!r}")
        res = (float(dx), float(dy))
    rgb = a.ndim == 3
    tmp = p.with_name(f".{p.name}.part")
    try:
        tifffile.imwrite(
            tmp,
            a,
            photometric="rgb" if rgb else "minisblack",
            extrasamples=("unassalpha",) if rgb and a.shape[2] == 4 else None,
            compression=compression,
            tile=tile,
            bigtiff=bigtiff,
            resolution=res,
            resolutionunit="INCH" if res is not None else None,
            description=description,
            metadata=None,
        )
        os.replace(tmp, p)
    except Exception as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, (OSError, ValueError, TypeError, KeyError)) or _codec_error(exc):
            raise ScanError(f"{p}: cannot write TIFF: {_one_line(exc)}") from None
        raise
    return p


# ---------------------------------------------------------------------------------------------
# fingerprints: what a result was measured on


def fingerprint(path: str | Path, *, chunk: int = 1 << 22) -> dict:
    """The identity of a file's content: ``{"name", "size_bytes", "sha256"}``.

    ``name`` is the file name (no folder: a scan may move with its results), ``sha256`` the
    hex digest of its bytes, read in ``chunk``-byte pieces (a gigabyte scan costs about a
    second and no memory). Detections, film corrections and sessions record this of the scan
    they were made on, so a result is never applied to another scan by mistake.
    """
    p = Path(path)
    h = hashlib.sha256()
    try:
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(chunk), b""):
                h.update(block)
            size = fh.tell()
    except FileNotFoundError:
        raise ScanError(f"{p}: file not found") from None
    except IsADirectoryError:
        raise ScanError(f"{p}: is a directory, not a file") from None
    except OSError as exc:
        raise ScanError(f"{p}: cannot read: {_one_line(exc)}") from None
    return {"name": p.name, "size_bytes": int(size), "sha256": h.hexdigest()}


def check_fingerprint(path: str | Path, expected: dict, *, what: str = "this result") -> None:
    """Raise :class:`ScanError` (one line naming both) unless ``path`` has the content that
    ``expected`` (a :func:`fingerprint`) records. A size mismatch is caught without hashing."""
    p = Path(path)
    want = expected.get("sha256")
    if not want:
        return
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        raise ScanError(f"{p}: file not found ({what} was made on {expected.get('name')})") \
            from None
    if expected.get("size_bytes") is not None and size != int(expected["size_bytes"]):
        raise ScanError(
            f"{p}: not the scan {what} was made on ({expected.get('name')}, "
            f"{expected['size_bytes']} bytes; this file has {size} bytes)"
        )
    if fingerprint(p)["sha256"] != want:
        raise ScanError(
            f"{p}: not the scan {what} was made on ({expected.get('name')}: its content "
            "differs, sha256 mismatch)"
        )
