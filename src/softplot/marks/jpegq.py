"""JPEG quantisation of a scan, estimated from its pixels, and what it adds to a mark's
covariance.

A JPEG file stores each 8 x 8 block of the image (blocks aligned on the image's first row and
column) as its 2-D DCT coefficients, each divided by its frequency's quantisation step and
rounded. On the decoded grey image (the luminance, which the scan's grey is) the coefficients
of each frequency therefore cluster on multiples of its step. :func:`estimate` finds the
quality of the IJG tables (what nearly every encoder writes) whose steps explain that
clustering best, on a sample of blocks; a scan whose coefficients show no such periodicity (a
TIFF, a PNG, a 16-bit scan) gets None, and nothing is added.

The rounding of each coefficient is an error of variance ``q_k^2 / 12`` (``q_k`` its step, in
grey units) independent between coefficients and blocks. Least-squares matching sees only
what of it its residuals show: the part along the mark's edges that looks like a shift is
taken up by the fitted shift and leaves no residual, so the mark's reported covariance misses
it. The centre is linear in the pixel errors (``dc = Sum_i h_i sqrt(w_i) e_i``,
:func:`softplot.marks.lsm._correlated_cov`), so the quantisation adds
``Sum_blocks a_b diag(var_k) a_b^T`` with ``a_b`` the centre's influence on the block's DCT
coefficients (:func:`centre_term`). A coefficient smaller than half its step is stored as 0
(the dead zone): its error is the coefficient itself, taken from the fitted mark. The term
is kept apart from the covariance the acceptance and outlier tests see
(:attr:`softplot.marks.lsm.LSMResult.cov_jpeg`) and added to the reported one before the
scan's variance factor is taken (:func:`softplot.marks.validation.jpeg_share`).

The estimate assumes the block grid starts at the scan's first row and column (a JPEG copy
cropped afterwards by other than multiples of 8 px shows no periodicity there and gets no
term) and IJG-scaled tables (an encoder's own tables are found only where they match one).
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from softplot.runtime import concurrent

__all__ = ["estimate", "of_scan", "prefetch", "centre_term", "IJG_LUMA", "ijg_table", "dct_matrix"]

#: the IJG (libjpeg) standard luminance quantisation table at quality 50, row-major
#: (vertical frequency, horizontal frequency)
IJG_LUMA = np.array([
    [16, 11, 10, 16, 24, 40, 51, 61],
    [12, 12, 14, 19, 26, 58, 60, 55],
    [14, 13, 16, 24, 40, 57, 69, 56],
    [14, 17, 22, 29, 51, 87, 80, 62],
    [18, 22, 37, 56, 68, 109, 103, 77],
    [24, 35, 55, 64, 81, 104, 113, 92],
    [49, 64, 78, 87, 103, 121, 120, 101],
    [72, 92, 95, 98, 112, 100, 103, 99]], float)
#: blocks sampled for the estimate (spread over the image)
SAMPLE_BLOCKS = 1024
#: the periodicity score (mean cosine of the informative coefficients' phase against their
#: steps) a quality needs to be taken; the decoded image's rounding to integers leaves about
#: 0.9 at quality 95 and more at lower qualities, a scan that never was a JPEG about 0
MIN_SCORE = 0.6
#: a coefficient is informative when at least this far (8-bit grey units) from 0
MIN_COEF = 1.5
#: informative coefficients needed for an estimate
MIN_COUNT = 200
#: at most this many informative coefficients are tried against each quality's steps
MAX_COEFS = 4000


def ijg_table(quality: int) -> np.ndarray:
    """The IJG luminance quantisation steps (8, 8) at ``quality`` (1-100), 8-bit grey units."""
    quality = int(np.clip(quality, 1, 100))
    scale = 5000.0 / quality if quality < 50 else 200.0 - 2.0 * quality
    return np.clip(np.floor((IJG_LUMA * scale + 50.0) / 100.0), 1.0, 255.0)


#: the qualities tried and their steps (qualities, 63) without the DC term
_QUALITIES = np.arange(10, 100)
_TABLES = np.stack([ijg_table(v).ravel()[1:] for v in _QUALITIES])


def dct_matrix() -> np.ndarray:
    """The orthonormal 8-point DCT-II ``D`` (8, 8): coefficients ``D @ f`` of a length-8 run
    ``f`` (JPEG's transform; in 2-D ``D @ block @ D.T``)."""
    k = np.arange(8)[:, None]
    n = np.arange(8)[None, :]
    D = np.sqrt(2.0 / 8.0) * np.cos(np.pi * (2 * n + 1) * k / 16.0)
    D[0] /= np.sqrt(2.0)
    return D


def _sample_blocks(grey: np.ndarray, n: int) -> np.ndarray:
    """Up to ``n`` 8 x 8 blocks (B, 8, 8) of ``grey`` (pixel system) on the JPEG block grid,
    spread over the image on a regular stride."""
    H, W = grey.shape[:2]
    by, bx = H // 8, W // 8
    if by == 0 or bx == 0:
        return np.zeros((0, 8, 8))
    step = max(1, int(np.sqrt(by * bx / max(n, 1))))
    iy = np.arange(0, by, step)
    ix = np.arange(0, bx, step)
    rows = (iy[:, None] * 8 + np.arange(8)[None, :]).ravel()
    cols = (ix[:, None] * 8 + np.arange(8)[None, :]).ravel()
    sub = np.asarray(grey[np.ix_(rows, cols)], float)
    return sub.reshape(len(iy), 8, len(ix), 8).transpose(0, 2, 1, 3).reshape(-1, 8, 8)


def estimate(grey: np.ndarray, n_blocks: int = SAMPLE_BLOCKS) -> np.ndarray | None:
    """The quantisation steps (8, 8) (8-bit grey units, row-major frequencies) of the JPEG
    ``grey`` (pixel system, grey range 0-1) was decoded from, or None where its block DCT
    coefficients show no quantisation (module docstring)."""
    blocks = _sample_blocks(grey, n_blocks) * 255.0
    if len(blocks) == 0:
        return None
    D = dct_matrix()
    C = D @ (blocks - 128.0) @ D.T  # (B, 8, 8)
    C = C.reshape(len(C), 64)[:, 1:]  # the DC term carries the level shift's rounding
    fi = np.nonzero(np.abs(C) >= MIN_COEF)  # the informative coefficients: (block, freq)
    if len(fi[0]) < MIN_COUNT:
        return None
    keep = slice(None, None, max(1, len(fi[0]) // MAX_COEFS))  # a spread subsample
    c, k = C[fi][keep], fi[1][keep]
    score, cnt = _phase_scores(c, k)
    score[cnt < MIN_COUNT] = -1.0
    i = int(np.argmax(score))  # the first best: the coarsest steps that fit
    best, best_q = float(score[i]), int(_QUALITIES[i])
    if best < MIN_SCORE:
        return None
    return ijg_table(best_q)


def _phase_scores(c: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each quality's periodicity score (qualities,) of the coefficients ``c`` (P,) (8-bit
    grey units) at the frequencies ``k`` (P,) (0..62, the DC term left out): the mean cosine
    of their phases against the quality's steps, over the pairs that say anything; and the
    number of those pairs (qualities,)."""
    a = np.abs(c)
    q = _TABLES[:, k]  # (qualities, coefficients)
    # only coefficients a step's rounding would not send to 0 say anything (a large step fits
    # any small coefficient), and only frequencies with steps above 1 (a step of 1 fits any
    # integer)
    sel = (a >= 0.75 * q) & (q > 1.0)
    cnt = sel.sum(1)
    # the cosines only where selected (a few per cent of the pairs), in an array laid out as
    # ``q``: each row's sum adds the same terms in the same order as the cosines of all pairs
    # masked to 0 (``np.where(sel, cos, 0)``) would, three times faster
    ph = np.zeros_like(q)
    ph[sel] = np.cos(2.0 * np.pi * np.broadcast_to(c, q.shape)[sel] / q[sel])
    return ph.sum(1) / np.maximum(cnt, 1), cnt


#: the sample's windows: a WINDOWS x WINDOWS grid of WINDOW x WINDOW px windows over the scan
WINDOWS = 6
WINDOW = 64


def _windows(scan) -> np.ndarray:
    """A mosaic (pixel system of its own, blocks on the scan's block grid) of small windows
    of the scan's grey spread over the whole image: the quantisation is the same
    everywhere, the content that shows it (edges, texture) is not."""
    H, W = scan.data.shape[:2]
    w = min(WINDOW, H // 8 * 8, W // 8 * 8)
    if w < 8:
        return np.zeros((0, 0))
    ys = np.unique(np.linspace(0, (H - w) // 8, WINDOWS).astype(int) * 8)
    xs = np.unique(np.linspace(0, (W - w) // 8, WINDOWS).astype(int) * 8)
    return np.block([[scan.grey((slice(y, y + w), slice(x, x + w))) for x in xs] for y in ys])


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: the scans whose estimate :func:`prefetch` is computing: their threads
_PENDING: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def prefetch(scan) -> None:
    """Start :func:`of_scan` of ``scan`` on a thread of its own where detection runs on several
    threads (:func:`softplot.runtime.concurrent`): the estimate (5-10 ms whatever the scan's
    size, NumPy that mostly releases the GIL) then runs beside the first stages, which leave
    the second core idle most of the time, and the first fit that asks for it waits for it
    (the same value, computed once). A no-op on one thread, for a scan that is not 8-bit
    (never estimated), already estimated or being estimated, or not weakly referable."""
    if not concurrent() or int(getattr(scan, "bit_depth", 8)) != 8:
        return
    try:
        if scan in _CACHE or scan in _PENDING:
            return
        t = threading.Thread(target=_estimate_quietly, args=(scan,), name="softplot-jpegq",
                             daemon=True)
        _PENDING[scan] = t
    except TypeError:
        return
    t.start()


def _estimate_quietly(scan) -> None:
    # the background estimate of :func:`prefetch`; should it fail, :func:`of_scan` (which waits
    # for this thread) computes it again in the caller, and raises there
    try:
        of_scan(scan)
    except Exception:  # noqa: BLE001, S110 - raised again by the caller's own estimate
        pass


def of_scan(scan) -> np.ndarray | None:
    """:func:`estimate` of a :class:`softplot.io.Scan` (computed once per scan): None unless
    it is an 8-bit scan whose pixels show JPEG quantisation. Returns the quantisation
    variances (8, 8) of its DCT coefficients in grey units squared (grey range 0-1):
    ``(q / 255)^2 / 12``. Waits for the estimate :func:`prefetch` started, if any."""
    try:
        t = _PENDING.get(scan)
    except TypeError:
        t = None
    if t is not None and t is not threading.current_thread():
        t.join()
    try:
        return _CACHE[scan]
    except (KeyError, TypeError):
        pass
    var = None
    if int(getattr(scan, "bit_depth", 8)) == 8:
        q = estimate(_windows(scan))
        if q is not None:
            var = (q / 255.0) ** 2 / 12.0
    try:
        _CACHE[scan] = var
    except TypeError:
        pass
    return var


def centre_term(g: np.ndarray, X: np.ndarray, Y: np.ndarray, valid: np.ndarray,
                var: np.ndarray, image: np.ndarray | None = None,
                origin: np.ndarray | None = None) -> np.ndarray:
    """The quantisation's covariance of each mark's centre (N, 2, 2) px^2.

    ``g`` (N, 2, P): the centre's sensitivity to each pixel's grey value (``h sqrt(w)``,
    px per grey unit); ``X``, ``Y`` (N, P): the pixels' integer positions in the pixel system
    (the JPEG block grid starts at 0); ``valid`` (N, P); ``var`` (8, 8): the coefficients'
    quantisation variances (grey units squared, :func:`of_scan`). With ``image`` (N, h, w),
    an estimate of the scan before the compression around each mark (the fitted model over
    the mark, grey units) whose element [0, 0] is the pixel ``origin`` (N, 2) (x, y), a
    coefficient smaller than half its step (JPEG's dead zone: stored as 0, its error is the
    coefficient itself) contributes its own square instead; blocks not whole in ``image``
    keep ``var``."""
    n, _, P = g.shape
    valid = valid & np.isfinite(X) & np.isfinite(Y)
    if n == 0 or not valid.any():
        return np.zeros((n, 2, 2))
    ix = np.rint(X).astype(np.int64)
    iy = np.rint(Y).astype(np.int64)
    mark = np.broadcast_to(np.arange(n)[:, None], valid.shape)[valid]
    bx, by, j = ix[valid] // 8, iy[valid] // 8, (iy[valid] % 8) * 8 + ix[valid] % 8
    # the blocks the marks' pixels fall in, numbered (the marks' patches may overlap)
    bx0, by0 = bx.min(), by.min()
    nby, nbx = int(by.max() - by0) + 1, int(bx.max() - bx0) + 1
    blocks, inv = np.unique((mark * nby + by - by0) * nbx + bx - bx0, return_inverse=True)
    nb = len(blocks)
    idx = inv.ravel() * 64 + j
    G = np.stack([np.bincount(idx, g[:, a][valid].astype(float), nb * 64) for a in (0, 1)],
                 1).reshape(nb, 8, 8, 2).transpose(0, 3, 1, 2)  # (block, axis, row, col)
    D = dct_matrix()
    A = (D @ G @ D.T).reshape(nb, 2, 64)  # the centre's influence on each coefficient
    V = np.broadcast_to(np.asarray(var, float).ravel(), (nb, 64))
    bm = blocks // (nby * nbx)
    if image is not None:
        V = _dead_zone(V, image, origin, bm, (blocks // nbx) % nby + by0, blocks % nbx + bx0,
                       D)
    Av = A * V[:, None, :]
    out = np.zeros((n, 2, 2))
    for a in (0, 1):
        for c in (0, 1):
            out[:, a, c] = np.bincount(bm, (Av[:, a] * A[:, c]).sum(1), n)
    return out


def _dead_zone(V, image, origin, bm, by, bx, D):
    """The variances ``V`` (blocks, 64) of the blocks (mark ``bm``, block row ``by`` and
    column ``bx`` of the pixel system's grid) with JPEG's dead zone: ``c^2`` where
    ``|c| < q / 2`` (``q^2 = 12 var``), ``c`` the block's coefficients in ``image`` (see
    :func:`centre_term`)."""
    n, h, w = image.shape
    o = np.rint(np.asarray(origin, float)).astype(np.int64).reshape(n, 2)
    x0 = bx * 8 - o[bm, 0]
    y0 = by * 8 - o[bm, 1]
    whole = (x0 >= 0) & (y0 >= 0) & (x0 + 8 <= w) & (y0 + 8 <= h)
    if not whole.any():
        return V
    k = np.arange(8)
    rows = y0[whole, None, None] + k[None, :, None]
    cols = x0[whole, None, None] + k[None, None, :]
    blk = np.asarray(image, float)[bm[whole, None, None], rows, cols]  # (B, 8, 8)
    c2 = ((D @ blk @ D.T).reshape(-1, 64)) ** 2
    V = np.array(V)
    # stored as 0 where below half the step (|c| < q / 2, i.e. c^2 < 3 var): error -c
    V[whole] = np.where(np.isfinite(c2) & (c2 < 3.0 * V[whole]), c2, V[whole])
    return V
