"""Scan loading (softplot.io): every supported format, dpi, grey conversion, bad input, CLI.

All files are generated in the test; expected pixels are the arrays written.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from softplot import io as sio
from softplot.cli import main
from softplot.errors import ScanError
from softplot.io import BT601, Scan, load_scan, save_tiff

H, W = 48, 64


def pattern(dtype=np.uint8, channels: int = 1, seed: int = 0) -> np.ndarray:
    """A smooth gradient plus a little noise, full range of ``dtype``, pixel system (H, W[, C])."""
    rng = np.random.default_rng(seed)
    top = np.iinfo(dtype).max
    y, x = np.mgrid[0:H, 0:W]
    shape = (H, W) if channels == 1 else (H, W, channels)
    base = np.zeros(shape)
    for c in range(channels):
        plane = 0.5 + 0.45 * np.sin(x / 9.0 + c) * np.cos(y / 7.0 - c)
        if channels == 1:
            base = plane
        else:
            base[..., c] = plane
    base = base + rng.normal(0, 0.01, shape)
    return np.clip(np.rint(base * top), 0, top).astype(dtype)


def grey_reference(a: np.ndarray, full: float) -> np.ndarray:
    """BT.601 luminance in float64 (the independent reference)."""
    a = a.astype(np.float64) / full
    if a.ndim == 3 and a.shape[2] >= 3:
        return a[..., 0] * BT601[0] + a[..., 1] * BT601[1] + a[..., 2] * BT601[2]
    return a[..., 0] if a.ndim == 3 else a


# ---------------------------------------------------------------------------------------------
# TIFF


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_tiff_uncompressed_is_memmapped_and_exact(tmp_path, dtype, channels):
    a = pattern(dtype, channels)
    p = save_tiff(tmp_path / "s.tif", a, dpi=1200)
    s = load_scan(p)
    assert isinstance(s.data, np.memmap) and s.is_memmap
    assert not s.data.flags.writeable
    assert (s.width, s.height, s.channels) == (W, H, channels)
    assert s.bit_depth == 8 * np.dtype(dtype).itemsize
    assert s.dpi == pytest.approx(1200.0)
    np.testing.assert_array_equal(np.asarray(s.data), a)
    full = float(np.iinfo(dtype).max)
    g = s.grey()
    assert g.dtype == np.float32 and g.shape == (H, W)
    np.testing.assert_allclose(g, grey_reference(a, full), atol=2e-7)
    c = s.colour()
    assert c.shape == (H, W, channels) and c.dtype == np.float32
    np.testing.assert_allclose(c, a.reshape(H, W, channels) / full, atol=1e-7)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"compression": "lzw"},
        {"compression": "deflate"},
        {"compression": "zstd"},
        {"tile": (16, 32)},
        {"tile": (16, 16), "compression": "deflate"},
        {"bigtiff": True},
        {"bigtiff": True, "compression": "lzw", "tile": (32, 32)},
    ],
    ids=lambda k: "-".join(f"{v}" for v in k.values()),
)
@pytest.mark.parametrize("channels", [1, 3])
def test_tiff_compressed_tiled_bigtiff_lossless(tmp_path, kwargs, channels):
    a = pattern(np.uint16, channels, seed=3)
    p = save_tiff(tmp_path / "c.tif", a, dpi=600, **kwargs)
    with tifffile.TiffFile(p) as t:
        assert t.is_bigtiff == bool(kwargs.get("bigtiff"))
        assert t.pages.first.is_tiled == ("tile" in kwargs)
    s = load_scan(p)
    np.testing.assert_array_equal(np.asarray(s.data), a)
    assert s.is_memmap == (not kwargs.get("compression") and "tile" not in kwargs)
    assert s.dpi == pytest.approx(600.0)


def test_tiff_jpeg_compressed_rgb(tmp_path):
    a = pattern(np.uint8, 3, seed=1)
    p = save_tiff(tmp_path / "j.tif", a, compression="jpeg")
    s = load_scan(p)
    assert s.channels == 3 and s.bit_depth == 8 and not s.is_memmap
    # lossy, but decoded back to RGB (not YCbCr): the grey stays close
    err = np.abs(s.grey().astype(float) - grey_reference(a, 255.0))
    assert err.mean() < 0.02


def test_tiff_planar_separate_rgb(tmp_path):
    a = pattern(np.uint8, 3, seed=2)
    p = tmp_path / "planar.tif"
    tifffile.imwrite(p, np.moveaxis(a, -1, 0), photometric="rgb", planarconfig="separate")
    s = load_scan(p)
    assert s.data.shape == (H, W, 3) and s.channels == 3
    np.testing.assert_array_equal(np.asarray(s.data), a)


def test_tiff_multipage_reads_first_full_resolution_page(tmp_path):
    a, b = pattern(np.uint8, seed=4), pattern(np.uint8, seed=5)
    p = tmp_path / "multi.tif"
    with tifffile.TiffWriter(p) as tw:
        tw.write(a, metadata=None)
        tw.write(b, metadata=None)
    np.testing.assert_array_equal(np.asarray(load_scan(p).data), a)
    # a reduced-resolution thumbnail in front of the full image is skipped
    q = tmp_path / "thumb.tif"
    with tifffile.TiffWriter(q) as tw:
        tw.write(a[::4, ::4], subfiletype=1, metadata=None)
        tw.write(b, metadata=None)
    np.testing.assert_array_equal(np.asarray(load_scan(q).data), b)


@pytest.mark.parametrize(
    "resolution, unit, expected",
    [
        ((1200, 1200), "INCH", (1200.0, 1200.0)),
        ((400, 400), "CENTIMETER", (1016.0, 1016.0)),
        ((118.11, 236.22), "CENTIMETER", (300.0, 600.0)),
        ((300, 300), "NONE", None),
        (None, None, None),
    ],
)
def test_tiff_dpi_tags(tmp_path, resolution, unit, expected):
    p = tmp_path / "d.tif"
    kw = {} if resolution is None else {"resolution": resolution, "resolutionunit": unit}
    tifffile.imwrite(p, pattern(), metadata=None, **kw)
    s = load_scan(p)
    if expected is None:
        assert s.dpi is None and s.dpi_xy is None
    else:
        np.testing.assert_allclose(s.dpi_xy, expected, rtol=1e-4)
        assert s.dpi == pytest.approx(expected[0], rel=1e-4)


def test_tiff_miniswhite_palette_bilevel_float(tmp_path):
    a = pattern(np.uint8)
    p = tmp_path / "mw.tif"
    tifffile.imwrite(p, a, photometric="miniswhite", metadata=None)
    s = load_scan(p)
    assert s.min_is_white
    np.testing.assert_allclose(s.grey(), 1.0 - a / 255.0, atol=2e-7)

    idx = (pattern(np.uint8) // 64).astype(np.uint8)  # 4 palette entries used
    cmap = np.zeros((3, 256), np.uint16)
    cmap[:, :4] = [[0, 65535, 0, 65535], [0, 0, 65535, 65535], [0, 0, 0, 65535]]
    p = tmp_path / "pal.tif"
    tifffile.imwrite(p, idx, photometric="palette", colormap=cmap, metadata=None)
    s = load_scan(p)
    assert s.channels == 3 and s.bit_depth == 16
    np.testing.assert_array_equal(s.data, cmap.T[idx])

    p = tmp_path / "bi.tif"
    tifffile.imwrite(p, a > 128, photometric="minisblack", metadata=None)
    s = load_scan(p)
    assert s.bit_depth == 1
    np.testing.assert_array_equal(s.grey(), (a > 128).astype(np.float32))
    p = tmp_path / "fax.tif"  # tifffile's default for bilevel: MinIsWhite, set bit = black
    tifffile.imwrite(p, a > 128, metadata=None)
    np.testing.assert_array_equal(load_scan(p).grey(), (a <= 128).astype(np.float32))

    f = (a / 255.0).astype(np.float32)
    f[0, :5] = np.nan
    p = save_tiff(tmp_path / "f.tif", f)
    s = load_scan(p)
    assert s.data.dtype == np.float32 and s.bit_depth == 32
    np.testing.assert_array_equal(s.grey(), f)  # NaN stays NaN, values as stored


def test_tiff_12_bit_packed_scaled_by_4095(tmp_path):
    a = (pattern(np.uint16) >> 4).astype(np.uint16)  # 0 ... 4095
    p = tmp_path / "b12.tif"
    tifffile.imwrite(p, a, bitspersample=12, metadata=None)
    s = load_scan(p)
    assert s.bit_depth == 12 and s.full_scale == 4095.0
    np.testing.assert_array_equal(s.data, a)
    np.testing.assert_allclose(s.grey(), a / 4095.0, atol=1e-7)


def test_gigapixel_tiff_is_not_copied(tmp_path):
    """A 1-gigapixel uncompressed TIFF (sparse file) loads without allocating its pixels."""
    p = tmp_path / "giga.tif"
    tifffile.imwrite(p, shape=(32768, 32768), dtype=np.uint8, metadata=None)
    tracemalloc.start()
    try:
        s = load_scan(p)
        win = s.grey((slice(20000, 20100), slice(30000, 30200)))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert s.is_memmap and s.width * s.height == 2**30
    assert win.shape == (100, 200) and float(win.max()) == 0.0
    assert peak < 16 * 2**20  # 1 GiB of pixels, < 16 MiB allocated


def test_grey_window_blocks_match_whole(tmp_path, monkeypatch):
    a = pattern(np.uint16, 3, seed=6)
    s = load_scan(save_tiff(tmp_path / "w.tif", a))
    whole = s.grey()
    monkeypatch.setattr(sio, "_BLOCK_PIXELS", 100)  # forces many row blocks
    win = (slice(5, 40), slice(3, 61, 2))
    np.testing.assert_array_equal(s.grey(win), whole[win])
    np.testing.assert_array_equal(s.grey(), whole)
    assert s.pixels is s.pixels  # cached, read-only, and grey() still gives a fresh array
    assert not s.pixels.flags.writeable and s.grey().flags.writeable
    np.testing.assert_array_equal(s.pixels, whole)
    np.testing.assert_allclose(s.colour(win), a[win] / 65535.0, atol=1e-7)
    with pytest.raises(TypeError):
        s.grey((1, 2))


def test_from_array(tmp_path):
    a = pattern(np.uint16)
    s = Scan.from_array(a, dpi=2400)
    assert s.data is a or np.shares_memory(s.data, a)
    assert (s.bit_depth, s.channels, s.dpi, s.path) == (16, 1, 2400.0, None)
    np.testing.assert_allclose(s.pixels, a / 65535.0, atol=1e-7)
    s12 = Scan.from_array(a >> 4, bit_depth=12)
    np.testing.assert_allclose(s12.grey(), (a >> 4) / 4095.0, atol=1e-7)
    one = Scan.from_array(a[..., None])
    assert one.data.shape == (H, W) and one.channels == 1
    f = Scan.from_array(np.full((4, 5), 0.25))
    assert f.grey().dtype == np.float32 and np.all(f.grey() == 0.25)
    for bad, msg in [
        (np.zeros((0, 5), np.uint8), "zero-size"),
        (np.zeros((4, 5, 6), np.uint8), "shape"),
        (np.zeros((4, 5), np.int16), "sample type"),
        (np.full((4, 5), np.nan, np.float32), "no finite pixel"),
        (np.zeros(7, np.uint8), "shape"),
    ]:
        with pytest.raises(ScanError, match=msg):
            Scan.from_array(bad)
    with pytest.raises(ScanError, match="bit depth"):
        Scan.from_array(np.zeros((3, 3), np.uint8), bit_depth=12)


def test_save_tiff_refuses_overwrite_and_bad_input(tmp_path):
    a = pattern()
    p = save_tiff(tmp_path / "o.tif", a, dpi=(300, 600))
    before = p.read_bytes()
    with pytest.raises(ScanError, match="refusing to overwrite"):
        save_tiff(p, a[::-1])
    assert p.read_bytes() == before
    save_tiff(p, a[::-1], dpi=(300, 600), overwrite=True)
    np.testing.assert_array_equal(np.asarray(load_scan(p).data), a[::-1])
    assert load_scan(p).dpi_xy == pytest.approx((300.0, 600.0))
    with pytest.raises(ScanError, match="int32"):
        save_tiff(tmp_path / "x.tif", a.astype(np.int32))
    with pytest.raises(ScanError, match="shape"):
        save_tiff(tmp_path / "x.tif", np.zeros((4, 5, 2), np.uint8))
    with pytest.raises(ScanError, match="cannot write TIFF"):
        save_tiff(tmp_path / "x.tif", pattern(np.uint16), compression="jpeg")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["o.tif"]  # no partial files left


# ---------------------------------------------------------------------------------------------
# PNG and JPEG


def png_with_phys(data: bytes, ppm_x: int, ppm_y: int, unit: int = 1) -> bytes:
    """Insert a pHYs chunk after IHDR."""
    body = b"pHYs" + struct.pack(">IIB", ppm_x, ppm_y, unit)
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    ihdr_end = 8 + 12 + 13
    return data[:ihdr_end] + chunk + data[ihdr_end:]


def bgr(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        return a
    return a[..., [2, 1, 0, 3][: a.shape[2]]]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_exact_and_rgb_order(tmp_path, dtype, channels):
    a = pattern(dtype, channels, seed=7)
    p = tmp_path / "a.png"
    assert cv2.imwrite(str(p), bgr(a))
    s = load_scan(p)
    assert (s.channels, s.bit_depth, s.file_format, s.dpi) == (
        channels, 8 * np.dtype(dtype).itemsize, "png", None)
    np.testing.assert_array_equal(s.data, a)  # R first: BGR was reordered
    np.testing.assert_allclose(s.grey(), grey_reference(a, np.iinfo(dtype).max), atol=2e-7)


def test_png_phys_dpi(tmp_path):
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), pattern())
    q = tmp_path / "dpi.png"
    q.write_bytes(png_with_phys(p.read_bytes(), 47244, 23622))  # 1200 x 600 dpi
    s = load_scan(q)
    np.testing.assert_allclose(s.dpi_xy, (1200.0, 600.0), rtol=1e-4)
    r = tmp_path / "nounit.png"
    r.write_bytes(png_with_phys(p.read_bytes(), 2, 1, unit=0))  # aspect only: no dpi
    assert load_scan(r).dpi is None


def jpeg_with_jfif_density(data: bytes, unit: int, xd: int, yd: int) -> bytes:
    assert data[6:11] == b"JFIF\x00"
    return data[:13] + struct.pack(">BHH", unit, xd, yd) + data[18:]


def exif_app1(xres: tuple[int, int], unit: int, big_endian: bool) -> bytes:
    """An APP1 EXIF segment whose IFD0 holds XResolution, YResolution, ResolutionUnit."""
    bo = ">" if big_endian else "<"
    head = (b"MM" if big_endian else b"II") + struct.pack(bo + "HI", 42, 8)
    n = 3
    data_off = 8 + 2 + 12 * n + 4
    ifd = struct.pack(bo + "H", n)
    ifd += struct.pack(bo + "HHII", 282, 5, 1, data_off)
    ifd += struct.pack(bo + "HHII", 283, 5, 1, data_off + 8)
    ifd += struct.pack(bo + "HHIHH", 296, 3, 1, unit, 0)
    ifd += struct.pack(bo + "I", 0)
    rat = struct.pack(bo + "II", *xres) * 2
    body = b"Exif\x00\x00" + head + ifd + rat
    return b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body


def test_jpeg_grey_rgb_and_dpi(tmp_path):
    a = pattern(np.uint8, 3, seed=8)
    p = tmp_path / "a.jpg"
    cv2.imwrite(str(p), bgr(a), [cv2.IMWRITE_JPEG_QUALITY, 100])
    s = load_scan(p)
    assert (s.channels, s.bit_depth, s.file_format) == (3, 8, "jpeg")
    assert np.abs(s.data.astype(int) - a).mean() < 2.0  # lossy, but RGB order
    g = tmp_path / "g.jpeg"
    cv2.imwrite(str(g), a[..., 1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert load_scan(g).channels == 1
    raw = p.read_bytes()
    assert load_scan(p).dpi is None  # JFIF 1:1 aspect, unit 0
    for unit, d, expected in [(1, 1600, 1600.0), (2, 100, 254.0)]:
        q = tmp_path / f"jfif{unit}.jpg"
        q.write_bytes(jpeg_with_jfif_density(raw, unit, d, d))
        assert load_scan(q).dpi == pytest.approx(expected)
    for big in (False, True):
        q = tmp_path / f"exif{big}.jpg"
        q.write_bytes(raw[:2] + exif_app1((2400, 1), 2, big) + raw[2:])
        assert load_scan(q).dpi == pytest.approx(2400.0)
    q = tmp_path / "exifcm.jpg"
    q.write_bytes(raw[:2] + exif_app1((1000, 10), 3, False) + raw[2:])
    assert load_scan(q).dpi == pytest.approx(254.0)


# ---------------------------------------------------------------------------------------------
# camera RAW


def write_dng(path: Path, cfa: np.ndarray, white: int = 4095, orientation: int = 1) -> Path:
    """A minimal valid DNG (uncompressed RGGB Bayer mosaic) that LibRaw reads."""
    extratags = [
        (33421, "H", 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFAPattern: R G / G B
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, "softplot test camera", True),  # UniqueCameraModel
        (50714, "H", 1, 0, True),  # BlackLevel
        (50717, "H", 1, white, True),  # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True),  # AsShotNeutral
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1: D65
        (274, "H", 1, orientation, True),  # Orientation
    ]
    tifffile.imwrite(path, cfa, photometric=32803, extratags=extratags, subfiletype=0,
                     metadata=None)
    return path


def test_raw_dng_linear_no_flip(tmp_path):
    flat = [
        load_scan(write_dng(tmp_path / f"f{v}.dng", np.full((H, W), v, np.uint16)))
        for v in (400, 800, 1600)
    ]
    s = flat[0]
    assert (s.file_format, s.bit_depth, s.channels, s.dpi) == ("raw", 16, 3, None)
    assert s.data.dtype == np.uint16 and s.data.shape == (H, W, 3)
    inner = (slice(4, -4), slice(4, -4))
    levels = np.array([f.grey(inner).mean() for f in flat])
    # linear development, no auto-brightening: grey = raw / white level, within 1 %
    np.testing.assert_allclose(levels, np.array([400, 800, 1600]) / 4095.0, rtol=0.01)
    np.testing.assert_allclose(levels[1:] / levels[:-1], 2.0, rtol=0.002)
    # an Orientation tag of 90 degrees is ignored (user_flip=0): no transposed frame
    r = load_scan(write_dng(tmp_path / "rot.dng", np.full((H, W), 800, np.uint16),
                            orientation=6))
    assert r.data.shape == (H, W, 3)


# ---------------------------------------------------------------------------------------------
# bad input


def _truncate(src: Path, dst: Path, frac: float = 0.5) -> Path:
    b = src.read_bytes()
    dst.write_bytes(b[: int(len(b) * frac)])
    return dst


def make_bad(kind: str, d: Path) -> tuple[Path, str]:
    """A bad input of ``kind`` in ``d`` and a fragment of the expected message."""
    a = pattern()
    if kind == "missing":
        return d / "nothere.tif", "not found"
    if kind == "directory":
        (d / "adir.tif").mkdir()
        return d / "adir.tif", "directory"
    if kind == "empty":
        (d / "empty.png").write_bytes(b"")
        return d / "empty.png", "empty"
    if kind == "unsupported":
        (d / "scan.bmp").write_bytes(b"BM" + bytes(100))
        return d / "scan.bmp", "unsupported file type"
    if kind == "no-extension":
        (d / "scan").write_bytes(bytes(100))
        return d / "scan", "unsupported file type"
    if kind.startswith("garbage"):
        ext = kind.split("-")[1]
        p = d / f"garbage.{ext}"
        p.write_bytes(b"this is not an image at all " * 20)
        return p, {"tif": "corrupt", "png": "not a PNG", "jpg": "not a JPEG",
                   "nef": "camera RAW"}[ext]
    if kind == "truncated-tiff":
        return _truncate(save_tiff(d / "full.tif", a), d / "trunc.tif"), "truncated"
    if kind == "truncated-lzw-tiff":
        return (_truncate(save_tiff(d / "full.tif", pattern(seed=9), compression="lzw"),
                          d / "trunc.tif"), "corrupt or truncated")
    if kind == "truncated-header-tiff":
        return _truncate(save_tiff(d / "full.tif", a), d / "trunc.tif", 0.001), "corrupt"
    if kind == "truncated-png":
        cv2.imwrite(str(d / "full.png"), a)
        return _truncate(d / "full.png", d / "trunc.png"), "truncated PNG"
    if kind == "truncated-jpeg":
        cv2.imwrite(str(d / "full.jpg"), a)
        return _truncate(d / "full.jpg", d / "trunc.jpg", 0.7), "truncated JPEG"
    if kind == "truncated-dng":
        write_dng(d / "full.dng", np.full((H, W), 500, np.uint16))
        return _truncate(d / "full.dng", d / "trunc.dng", 0.3), "camera RAW"
    if kind == "zero-size":
        with pytest.warns(UserWarning):
            tifffile.imwrite(d / "zero.tif", np.zeros((0, 0), np.uint8))
        return d / "zero.tif", "zero-size"
    if kind == "nan-only":
        return save_tiff(d / "nan.tif", np.full((8, 8), np.nan, np.float32)), "no finite pixel"
    if kind == "cmyk":
        tifffile.imwrite(d / "cmyk.tif", np.zeros((8, 8, 4), np.uint8), photometric="separated")
        return d / "cmyk.tif", "unsupported TIFF photometric interpretation SEPARATED"
    if kind == "signed":
        tifffile.imwrite(d / "signed.tif", a.astype(np.int16))
        return d / "signed.tif", "signed"
    raise AssertionError(kind)


BAD = [
    "missing", "directory", "empty", "unsupported", "no-extension", "garbage-tif",
    "garbage-png", "garbage-jpg", "garbage-nef", "truncated-tiff", "truncated-lzw-tiff",
    "truncated-header-tiff", "truncated-png", "truncated-jpeg", "truncated-dng", "zero-size",
    "nan-only", "signed", "cmyk",
]


@pytest.mark.parametrize("kind", BAD)
def test_bad_input_one_line_scan_error(tmp_path, kind):
    p, fragment = make_bad(kind, tmp_path)
    with pytest.raises(ScanError) as e:
        load_scan(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: ")
    assert fragment in msg
    assert "\n" not in msg


# ---------------------------------------------------------------------------------------------
# CLI: softplot info


def test_cli_info_reports_good_and_bad(tmp_path, capsys):
    good = save_tiff(tmp_path / "good.tif", pattern(np.uint16, 3), dpi=1200)
    png = tmp_path / "good.png"
    cv2.imwrite(str(png), pattern())
    bads = [make_bad(k, tmp_path)[0] for k in ("missing", "truncated-png", "unsupported")]
    with pytest.raises(SystemExit) as e:
        main(["info", str(good), *map(str, bads), str(png)])
    assert e.value.code == 2
    out, err = capsys.readouterr()
    lines = out.strip().splitlines()
    assert len(lines) == 2  # both good files reported, also the one after the bad ones
    assert f"{W} x {H} px, 16-bit, 3 channels (RGB), 1200 dpi, TIFF, memory-mapped" in lines[0]
    assert lines[1].startswith(f"{png}: {W} x {H} px, 8-bit, 1 channel (grey), dpi unknown")
    errs = err.strip().splitlines()
    assert len(errs) == 3 and all(line.startswith("softplot: error: ") for line in errs)
    assert all(str(b) in line for b, line in zip(bads, errs, strict=True))

    with pytest.raises(SystemExit) as e:
        main(["info", str(good)])
    assert e.value.code == 0


def test_cli_info_console_script_no_traceback(tmp_path):
    bad = tmp_path / "broken.tif"
    bad.write_bytes(b"II*\x00" + bytes(20))
    exe = Path(sys.executable).with_name("softplot")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "softplot.cli"]
    r = subprocess.run([*cmd, "info", str(bad)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stdout == ""
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert r.stderr.startswith(f"softplot: error: {bad}: ")


def test_fingerprint_names_content_and_catches_a_changed_byte(tmp_path):
    from softplot.errors import ScanError
    from softplot.io import check_fingerprint, fingerprint

    a = tmp_path / "a.tif"
    a.write_bytes(bytes(range(256)) * 100)
    fp = fingerprint(a)
    assert fp["name"] == "a.tif" and fp["size_bytes"] == 25600
    assert len(fp["sha256"]) == 64
    check_fingerprint(a, fp)  # same content: no error
    b = tmp_path / "moved.tif"
    b.write_bytes(a.read_bytes())
    check_fingerprint(b, fp)  # moved or renamed but the same content: accepted
    data = bytearray(a.read_bytes())
    data[1000] ^= 1
    b.write_bytes(bytes(data))
    with pytest.raises(ScanError, match="sha256 mismatch"):
        check_fingerprint(b, fp)
    b.write_bytes(b"short")
    with pytest.raises(ScanError, match="5 bytes"):
        check_fingerprint(b, fp)
    with pytest.raises(ScanError, match="not found"):
        check_fingerprint(tmp_path / "gone.tif", fp)
