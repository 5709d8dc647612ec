"""What every stage of :mod:`softplot.marks` shares: the error, the scan, the grid part.

:class:`DetectionError` (the marks of a certificate are not on a scan), :func:`as_scan`,
:func:`parse_grid_part` / :func:`format_grid_part` (the part of a reseau a scan shows),
:func:`blank_check` (an image with no contrast), :func:`transform_json` (the film mm ->
pixel model of a :class:`~softplot.marks.result.Detection`) and the polarity's names. It
imports no other stage: the reseau path (:mod:`softplot.marks.detect`) and the fiducial path
(:mod:`softplot.marks.fiducial`) both import it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softplot.errors import SoftplotError

__all__ = ["DetectionError", "as_scan", "parse_grid_part", "format_grid_part",
           "blank_check", "transform_json", "polarity_name", "polarity_signs", "MM_PER_INCH",
           "median_rows", "median1"]

MM_PER_INCH = 25.4


def median_rows(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=1)`` of a 2-D float array, the same values in its dtype, from one
    partition of the rows (NumPy's takes three: its two middle ranks and the last, for NaN;
    several times faster on long rows). Rows with NaN: NumPy's own."""
    a = np.asarray(a)
    n = a.shape[1]
    if n == 0 or a.dtype.kind != "f" or not np.isfinite(a).all():
        return np.median(a, axis=1)
    h = n // 2
    p = np.partition(a, h, axis=1)
    if n % 2:
        return p[:, h].copy()
    # the two middle ranks' mean, as NumPy takes it (their sum, halved, in the dtype)
    return (p[:, :h].max(1) + p[:, h]) / a.dtype.type(2)


def median1(a) -> np.floating:
    """``np.median(a)`` of a 1-D float array, the same value in its dtype, from one partition
    (:func:`median_rows`' arithmetic; several times faster on the short profiles of a cross).
    Empty arrays, other dtypes and arrays with NaN: NumPy's own."""
    a = np.asarray(a)
    n = a.shape[0] if a.ndim == 1 else 0
    if n == 0 or a.dtype.kind != "f" or not np.isfinite(a).all():
        return np.median(a)
    h = n // 2
    p = np.partition(a, h)
    if n % 2:
        return p[h]
    return (p[:h].max() + p[h]) / a.dtype.type(2)


class DetectionError(SoftplotError):
    """The marks of the certificate cannot be found on the scan (message: expected vs found)."""


def inverse_2x2(J: np.ndarray, min_det: float) -> np.ndarray:
    """The inverses of a stack of 2 x 2 matrices ``J`` (K, 2, 2), by hand: NaN where
    ``|det| < min_det`` or the inverse is not finite (a degenerate Jacobian gives NaN, not an
    exception)."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    adj = np.stack([np.stack([J[:, 1, 1], -J[:, 0, 1]], -1),
                    np.stack([-J[:, 1, 0], J[:, 0, 0]], -1)], -2)
    with np.errstate(all="ignore"):
        A = adj / det[:, None, None]
    A[~np.isfinite(A).all((1, 2)) | (np.abs(det) < min_det)] = np.nan
    return A


def as_scan(scan, dpi: float | None = None):
    """A :class:`softplot.io.Scan` from a Scan, a path or an array (pixel system)."""
    from softplot import io

    if isinstance(scan, io.Scan):
        return scan
    if isinstance(scan, (str, Path)):
        return io.load_scan(scan)
    return io.Scan.from_array(np.asarray(scan), dpi=dpi)


def parse_grid_part(part, rows: int | None = None, cols: int | None = None):
    """The part of the reseau a scan shows, as ``(col0, col1, row0, row1)`` (half-open ranges
    of the certificate's columns and rows; None for None).

    ``part`` is a text ``"cols=A:B,rows=C:D"`` (either may be left out; ``A:B`` are the
    columns A to B-1, as Python slices; an empty bound is the grid's own), a mapping
    ``{"cols": (A, B), "rows": (C, D)}`` or such a tuple. With ``rows`` and ``cols`` (the
    grid's size) the ranges are checked against the grid and open bounds filled in.
    """
    if part is None:
        return None
    if isinstance(part, str):
        text = part.replace(" ", "")
        if not text:
            raise SoftplotError("--grid-part is empty; give cols=A:B,rows=C:D")
        d: dict = {}
        for item in text.split(","):
            key, eq, rng = item.partition("=")
            if not eq or key not in ("cols", "rows") or key in d or rng.count(":") != 1:
                raise SoftplotError(
                    f"--grid-part {part!r}: expected cols=A:B,rows=C:D (either may be left out), "
                    f"e.g. cols=0:12")
            lo, hi = rng.split(":")
            try:
                d[key] = (int(lo) if lo else None, int(hi) if hi else None)
            except ValueError:
                raise SoftplotError(f"--grid-part {part!r}: {rng!r} is not a range of whole "
                                    "numbers A:B") from None
        part = d
    if isinstance(part, dict):
        c = part.get("cols") or (None, None)
        r = part.get("rows") or (None, None)
        part = (c[0], c[1], r[0], r[1])
    part = tuple(None if v is None else int(v) for v in part)
    if len(part) != 4:
        raise SoftplotError(f"grid part must be (col0, col1, row0, row1), got {part!r}")
    if rows is None or cols is None:
        return part
    c0, c1, r0, r1 = part
    c0, r0 = c0 if c0 is not None else 0, r0 if r0 is not None else 0
    c1, r1 = c1 if c1 is not None else cols, r1 if r1 is not None else rows
    if not (0 <= c0 < c1 <= cols and 0 <= r0 < r1 <= rows):
        raise SoftplotError(
            f"--grid-part cols={c0}:{c1},rows={r0}:{r1} is not a part of the {rows}x{cols} "
            f"grid (columns 0:{cols}, rows 0:{rows})")
    return (c0, c1, r0, r1)


def format_grid_part(part) -> str:
    """The text ``cols=A:B,rows=C:D`` of a grid part (:func:`parse_grid_part`'s input)."""
    c0, c1, r0, r1 = parse_grid_part(part)

    def rng(a, b):
        return f"{'' if a is None else a}:{'' if b is None else b}"

    out = []
    if (c0, c1) != (None, None):
        out.append(f"cols={rng(c0, c1)}")
    if (r0, r1) != (None, None):
        out.append(f"rows={rng(r0, r1)}")
    return ",".join(out) or "cols=:"


def polarity_name(sign: int) -> str:
    """``"negative"`` for bright marks (``sign`` +1), ``"positive"`` for dark ones (-1)."""
    return "negative" if sign > 0 else "positive"


def polarity_signs(polarity: str) -> tuple[int, ...]:
    """The mark signs to try for ``polarity`` ("auto": bright first, then dark)."""
    return (1, -1) if polarity == "auto" else ((1,) if polarity == "negative" else (-1,))


def blank_check(ov, what: str) -> None:
    """Raise :class:`DetectionError` for an empty image or one with no grey range (an
    overview, any pixel system)."""
    if ov.size == 0:
        raise DetectionError(f"{what}: empty image")
    lo, hi = np.percentile(ov[:: max(1, ov.shape[0] // 256), :: max(1, ov.shape[1] // 256)],
                           [1, 99])
    if hi - lo < 2e-3:
        raise DetectionError(
            f"{what}: blank image (grey range {hi - lo:.4f}); expected reseau crosses or fiducial "
            "marks with some contrast")


def transform_json(Hm, rms, n) -> dict:
    """The film mm -> pixel model ``Hm`` (3, 3) as a Detection's ``transform`` (``rms`` px
    over ``n`` marks)."""
    return {
        "kind": "projective",
        "from": "film_mm",
        "to": "pixel",
        "matrix": [[float(v) for v in row] for row in Hm],
        "rms_px": float(rms),
        "n": int(n),
        "formula": "[x y w]^T = H [X Y 1]^T; pixel = (x/w, y/w); X, Y film mm",
    }
