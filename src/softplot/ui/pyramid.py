"""Image pyramids of scans for the stereo viewer: built once, cached by the scan's content.

Level 0 is the scan itself (pixel system: x right = column, y down = row, (0, 0) the centre
of the top-left pixel); level ``L + 1`` is the 2x2 mean of level ``L`` (``cv2.INTER_AREA``;
an odd last row or column is averaged with itself), until the level fits in one tile. Level
``L`` pixel ``(i, j)`` covers level-0 pixels ``[i 2^L, (i + 1) 2^L)``: its centre is at
level-0 coordinate ``i 2^L + (2^L - 1) / 2``.

Levels are stored as ``.npy`` files (native dtype, grey: uint8 or uint16) in a folder named
by the scan's sha256 (:func:`softplot.io.fingerprint`) under the cache folder, so a moved scan
reuses its pyramid and a changed one never does. An uncompressed grey TIFF is memory-mapped
and serves as level 0 directly; other scans are converted to a grey level-0 file first. The
build works in bands of rows, so its memory stays a few tens of megabytes whatever the scan's
size (beyond what reading a compressed scan costs).

Tiles: :meth:`Pyramid.tile` cuts tile ``(tx, ty)`` of level ``L`` (``tile`` px square) with a
1-px gutter on every side (the neighbouring pixels, or the edge pixel repeated), so a
texture of ``tile + 2`` px sampled bilinearly joins its neighbours seamlessly; 16-bit levels
go to 8 bits through the window ``[lo, hi]`` (a lookup table).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from softplot.errors import SoftplotError

__all__ = ["Pyramid", "build_pyramid", "default_cache", "TILE"]

#: tile size, px (content; the texture is TILE + 2 with its gutter)
TILE = 256
FORMAT = "softplot-pyramid"
VERSION = 1
BAND = 2048  # rows per band while building (even)


def default_cache() -> Path:
    """``$SOFTPLOT_CACHE`` or ``$XDG_CACHE_HOME/softplot`` (``~/.cache/softplot``)."""
    env = os.environ.get("SOFTPLOT_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "softplot"


def _grey_level0(scan, out: Path) -> np.ndarray:
    """The scan as a grey uint8/uint16 array, written band by band to ``out`` (.npy)."""
    d = scan.data
    dt = np.uint8 if d.dtype in (np.bool_, np.uint8) or scan.bit_depth <= 8 else np.uint16
    h, w = d.shape[:2]
    a = np.lib.format.open_memmap(out, mode="w+", dtype=dt, shape=(h, w))
    full = 255 if dt == np.uint8 else 65535
    for r0 in range(0, h, BAND):
        b = np.asarray(d[r0:r0 + BAND])
        if b.ndim == 3:
            c = b.shape[2]
            b = b[..., :3].astype(np.float32) @ np.float32([0.299, 0.587, 0.114]) \
                if c >= 3 else b[..., 0]
        if b.dtype == np.bool_:
            b = b.astype(np.float32) * 255
        elif np.issubdtype(b.dtype, np.floating):
            b = np.nan_to_num(b, nan=0.0) * full
        elif b.dtype != dt and np.issubdtype(b.dtype, np.integer):
            b = b.astype(np.float64) * (full / (2.0 ** scan.bit_depth - 1))
        b = np.clip(np.rint(b), 0, full) if not np.issubdtype(b.dtype, np.integer) else b
        if scan.min_is_white:
            b = full - b.astype(np.int64)
        a[r0:r0 + BAND] = b
    del a
    return np.load(out, mmap_mode="r")


def _halve(src: np.ndarray, out: Path) -> np.ndarray:
    """2x2 means of ``src`` (H, W) into ``out`` (.npy, ceil(H/2) x ceil(W/2)), by bands."""
    h, w = src.shape
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    a = np.lib.format.open_memmap(out, mode="w+", dtype=src.dtype, shape=(h2, w2))
    for r0 in range(0, h, BAND):
        b = np.asarray(src[r0:r0 + BAND])
        if b.shape[0] % 2:
            b = np.vstack([b, b[-1:]])
        if w % 2:
            b = np.hstack([b, b[:, -1:]])
        a[r0 // 2:r0 // 2 + b.shape[0] // 2] = cv2.resize(
            b, (b.shape[1] // 2, b.shape[0] // 2), interpolation=cv2.INTER_AREA)
    del a  # no msync: the page cache writes it back; a crash leaves no pyramid.json
    return np.load(out, mmap_mode="r")


def _window(top: np.ndarray) -> tuple[int, int]:
    if top.dtype == np.uint8:
        return 0, 255
    lo, hi = np.percentile(top, [0.1, 99.9])
    lo, hi = int(lo), int(np.ceil(hi))
    return (lo, hi) if hi > lo else (0, 65535)


def build_pyramid(scan_path, cache=None, *, sha256: str | None = None, tile: int = TILE,
                  progress=None) -> "Pyramid":
    """The pyramid of the scan at ``scan_path``, built in ``cache`` unless already there.

    Parameters
    ----------
    scan_path : path
        The scan (any format :func:`softplot.io.load_scan` reads).
    cache : path, optional
        Cache folder (default :func:`default_cache`); the pyramid lives in
        ``cache/pyramids/<sha256>/``.
    sha256 : str, optional
        The scan's content hash when already known (a session records it); else computed.
    tile : int
        Tile size, px (256 or 512).
    """
    from softplot.io import fingerprint, load_scan

    if tile not in (256, 512):
        raise SoftplotError(f"pyramid tile size must be 256 or 512, got {tile}")
    sp = Path(scan_path)
    sha = sha256 or fingerprint(sp)["sha256"]
    root = Path(cache) if cache is not None else default_cache()
    final = root / "pyramids" / f"{sha}-{tile}"
    if (final / "pyramid.json").is_file():
        try:
            return Pyramid(final, sp)
        except SoftplotError:
            shutil.rmtree(final, ignore_errors=True)  # a stale or broken cache entry
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SoftplotError(f"cannot create the pyramid cache {final.parent}: "
                            f"{exc.strerror}") from None
    tmp = final.parent / f".{final.name}.{os.getpid()}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    t0 = time.perf_counter()
    try:
        scan = load_scan(sp)
        d = scan.data
        native = (d.ndim == 2 and d.dtype in (np.uint8, np.uint16) and not scan.min_is_white
                  and scan.bit_depth in (8, 16) and isinstance(d, np.memmap))
        lvl = d if native else _grey_level0(scan, tmp / "level0.npy")
        sizes = [(int(lvl.shape[1]), int(lvl.shape[0]))]
        k = 0
        while max(lvl.shape) > tile:
            k += 1
            lvl = _halve(lvl, tmp / f"level{k}.npy")
            sizes.append((int(lvl.shape[1]), int(lvl.shape[0])))
            if progress:
                progress(k)
        lo, hi = _window(np.asarray(lvl))
        meta = {"format": FORMAT, "version": VERSION, "sha256": sha, "tile": tile,
                "dtype": str(lvl.dtype), "levels": sizes, "level0_is_scan": bool(native),
                "window": [lo, hi], "build_s": time.perf_counter() - t0}
        (tmp / "pyramid.json").write_text(json.dumps(meta, indent=1) + "\n")
        del lvl, d, scan
        try:
            os.replace(tmp, final)
        except OSError:  # another process built it meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return Pyramid(final, sp)


@lru_cache(maxsize=64)
def _lut(lo: int, hi: int, n: int) -> np.ndarray:
    v = (np.arange(n, dtype=np.float64) - lo) * (255.0 / max(hi - lo, 1))
    return np.clip(np.rint(v), 0, 255).astype(np.uint8)


class Pyramid:
    """A built pyramid (see the module docstring): levels, sizes, tiles.

    ``levels[L]`` is an (H_L, W_L) read-only array (memory-mapped), pixel system of level L.
    """

    def __init__(self, folder: Path, scan_path: Path):
        self.folder = Path(folder)
        try:
            meta = json.loads((self.folder / "pyramid.json").read_text())
        except (OSError, ValueError) as exc:
            raise SoftplotError(f"{self.folder}: unreadable pyramid ({exc})") from None
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise SoftplotError(f"{self.folder}: not a version-{VERSION} pyramid")
        self.meta = meta
        self.tile_size = int(meta["tile"])
        self.sizes = [tuple(s) for s in meta["levels"]]
        self.window = tuple(meta["window"])
        self.levels: list[np.ndarray] = []
        for k, (w, h) in enumerate(self.sizes):
            if k == 0 and meta.get("level0_is_scan"):
                from softplot.io import load_scan

                a = load_scan(scan_path).data
            else:
                a = np.load(self.folder / f"level{k}.npy", mmap_mode="r")
            if a.shape != (h, w):
                raise SoftplotError(f"{self.folder}: level {k} is not {w} x {h} px")
            self.levels.append(a)
        self.dtype = self.levels[0].dtype
        self.full = 255 if self.dtype == np.uint8 else 65535

    @property
    def width(self) -> int:
        return self.sizes[0][0]

    @property
    def height(self) -> int:
        return self.sizes[0][1]

    def info(self) -> dict:
        """What the page needs: sizes per level, tile size, dtype, default window."""
        return {"width": self.width, "height": self.height, "tile": self.tile_size,
                "levels": [list(s) for s in self.sizes], "dtype": str(self.dtype),
                "window": list(self.window), "full": self.full}

    def tiles(self, level: int) -> tuple[int, int]:
        """Number of tiles (columns, rows) of ``level``."""
        w, h = self.sizes[level]
        t = self.tile_size
        return (w + t - 1) // t, (h + t - 1) // t

    def tile(self, level: int, tx: int, ty: int, lo: int | None = None,
             hi: int | None = None) -> bytes:
        """Tile ``(tx, ty)`` of ``level`` as ``(tile + 2)^2`` bytes, uint8, row-major.

        Texel ``(u, v)`` is level-``level`` pixel ``(tx tile + u - 1, ty tile + v - 1)``
        (clamped to the level: the gutter repeats the edge). 16-bit values map to 8 bits
        through the window ``[lo, hi]`` (default: the pyramid's). Raises IndexError when the
        tile does not exist.
        """
        if not (0 <= level < len(self.levels)):
            raise IndexError(level)
        nx, ny = self.tiles(level)
        if not (0 <= tx < nx and 0 <= ty < ny):
            raise IndexError((tx, ty))
        a = self.levels[level]
        h, w = a.shape
        t = self.tile_size
        x0, y0 = tx * t - 1, ty * t - 1
        x1, y1 = x0 + t + 2, y0 + t + 2
        cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        p = np.asarray(a[cy0:cy1, cx0:cx1])
        pad = ((cy0 - y0, y1 - cy1), (cx0 - x0, x1 - cx1))
        if any(v for pr in pad for v in pr):
            p = np.pad(p, pad, mode="edge")
        if self.dtype == np.uint8 and (lo is None or (lo, hi) == (0, 255)):
            return np.ascontiguousarray(p).tobytes()
        lo = self.window[0] if lo is None else int(lo)
        hi = self.window[1] if hi is None else int(hi)
        return _lut(lo, hi, self.full + 1)[p].tobytes()
