"""Writing synthetic scans: TIFF (with resolution tags), JPEG (JFIF density), PNG (pHYs).

Pixel arrays are in the pixel system, (H, W) grey or (H, W, 3) RGB, uint8 or uint16 (float32
for TIFF only). TIFF goes through :func:`softplot.io.save_tiff` when that exists, otherwise a
small local tifffile writer. JPEG and PNG are encoded by OpenCV; the dpi is then written into
the JFIF APP0 density fields or a PNG ``pHYs`` chunk, so :func:`softplot.io.load_scan` reads it
back. All writers produce byte-identical files for identical pixels.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from softplot.errors import SoftplotError

FORMATS = ("tif", "jpg", "png")


def _check_new(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise SoftplotError(f"{path}: exists; refusing to overwrite (use --overwrite)")


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_tiff(path: Path, image: np.ndarray, dpi: float, overwrite: bool = False,
               description: str | None = None, compression: str | None = None) -> Path:
    """Write a TIFF with XResolution/YResolution in dots per inch (uncompressed by default)."""
    _check_new(path, overwrite)
    try:
        from softplot.io import save_tiff
    except ImportError:  # io not there yet: write it here
        save_tiff = None
    if save_tiff is not None:
        return save_tiff(path, image, dpi=dpi, overwrite=True, compression=compression,
                         description=description)
    import tifffile

    tmp = path.with_name(f".{path.name}.part")
    tifffile.imwrite(
        tmp,
        image,
        photometric="rgb" if image.ndim == 3 else "minisblack",
        resolution=(float(dpi), float(dpi)),
        resolutionunit="INCH",
        compression=compression,
        description=description,
        metadata=None,
    )
    os.replace(tmp, path)
    return path


def _jfif_density(buf: bytes, dpi: float) -> bytes:
    """Set (or insert) the JFIF APP0 density to ``dpi`` dots per inch."""
    d = max(1, min(65535, int(round(dpi))))
    if buf[2:4] == b"\xff\xe0" and buf[6:11] == b"JFIF\x00":
        return buf[:13] + struct.pack(">BHH", 1, d, d) + buf[18:]
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\x00\x01\x01" + struct.pack(">BHH", 1, d, d)
    return buf[:2] + app0 + b"\x00\x00" + buf[2:]


def _png_phys(buf: bytes, dpi: float) -> bytes:
    """Insert a pHYs chunk (pixels per metre) after IHDR."""
    ppm = int(round(dpi / 0.0254))
    data = struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", len(data)) + b"pHYs" + data
    chunk += struct.pack(">I", zlib.crc32(b"pHYs" + data) & 0xFFFFFFFF)
    ihdr_end = 8 + 8 + 13 + 4
    return buf[:ihdr_end] + chunk + buf[ihdr_end:]


def write_image(path: str | Path, image: np.ndarray, dpi: float, file_format: str,
                overwrite: bool = False, jpeg_quality: int = 92,
                description: str | None = None, compression: str | None = None) -> Path:
    """Write ``image`` (pixel system, (H, W) or (H, W, 3) RGB) as tif, jpg or png.

    Raises :class:`SoftplotError` if the file exists and ``overwrite`` is False, or if the
    format cannot hold the samples (JPEG is 8-bit only; float only as TIFF).
    """
    import cv2

    p = Path(path)
    fmt = file_format.lower()
    if fmt not in FORMATS:
        raise SoftplotError(f"unknown image format {file_format!r} (use {', '.join(FORMATS)})")
    if fmt == "tif":
        return write_tiff(p, image, dpi, overwrite, description, compression)
    _check_new(p, overwrite)
    if image.dtype == np.float32 or (fmt == "jpg" and image.dtype != np.uint8):
        raise SoftplotError(f"{p}: {fmt} cannot hold {image.dtype} samples (use 8 bits or tif)")
    a = image[..., ::-1] if image.ndim == 3 else image  # OpenCV wants BGR
    a = np.ascontiguousarray(a)
    if fmt == "jpg":
        ok, enc = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        data = _jfif_density(enc.tobytes(), dpi) if ok else b""
    else:
        ok, enc = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 6])
        data = _png_phys(enc.tobytes(), dpi) if ok else b""
    if not ok:
        raise SoftplotError(f"{p}: OpenCV could not encode the image as {fmt}")
    _atomic_write(p, data)
    return p
