"""Analytic mark models (blurred crosses, dots, circles with dot) and pixel templates.

Every mark is described in its own *mark frame*: ``(u, v)`` in pixels at the scan's nominal
scale, origin at the mark centre, ``u`` along film +x, ``v`` along film -y (so that the mark
frame has the orientation of the pixel frame when the scan is upright). A pixel ``p`` (pixel
system, x right, y down) maps into the mark frame by ``q = A @ (p - c)`` where ``c`` is the
mark centre in pixels and ``A`` a 2x2 affine shape matrix (identity for an upright scan at the
nominal dpi).

Models are edge-spread functions: a drawn shape (indicator 1 on the mark, 0 off it) convolved
with an isotropic Gaussian of standard deviation ``s`` (scanner blur combined with the pixel
aperture, ``s**2 = sigma_blur**2 + 1/12``). A blurred box of full width ``a`` is
``B(t) = Phi((t + a/2)/s) - Phi((t - a/2)/s)`` exactly, and a cross is the union of two bars,
``T = H + V - S`` (horizontal bar + vertical bar - their common square), which is exact after
blurring because blurring is linear and each of the three terms is a separable box. Dots and
rings use the same 1-D profile along the radius (exact up to curvature terms of order
``s / R``; the model stays point-symmetric, so the centre is unbiased).

Every ``evaluate`` returns the template value and its derivatives with respect to ``u``, ``v``
and ``s``, which least-squares matching (:mod:`softplot.marks.lsm`) needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.camera import Camera, Fiducial

__all__ = ["MarkShape", "cross_shape", "fiducial_shape", "render", "box_profile",
           "box_pixel_profile", "aperture"]

_INV_SQRT2 = np.float32(1.0 / np.sqrt(2.0))
# erf(x) ~ tanh(x (E1 + E3 x^2 + E5 x^4)) on |x| <= 5.5 (minimax fit, |error| < 3.7e-5):
# 40x faster than scipy's erf in float32 and smooth, with an exact derivative. The model stays
# point-symmetric, so the approximation cannot bias a centre; 3.7e-5 of the contrast is far
# below any scan's noise.
_E1, _E3, _E5 = np.float32(1.12814338), np.float32(0.10408119), np.float32(-0.00178647)
# |z| beyond which _Phi_phi is exactly 0 or 1 with a zero density (its clip at |x| = 5.5,
# with a margin for the rounding of z / sqrt(2))
_ZSAT = np.float32(5.5 * np.sqrt(2.0) * (1.0 + 1e-5))


def _Phi_phi(z):
    """Standard normal CDF and its derivative (the density), float32, vectorised."""
    x = np.clip(z * _INV_SQRT2, -5.5, 5.5)
    x2 = x * x
    th = np.tanh(x * (_E1 + x2 * (_E3 + _E5 * x2)))
    P = 0.5 + 0.5 * th
    d = (0.5 * _INV_SQRT2) * (1.0 - th * th) * (_E1 + x2 * (3.0 * _E3 + 5.0 * _E5 * x2))
    return P, d


def box_profile(t, a, s):
    """Blurred box of full width ``a`` (px) and blur ``s`` (px), with derivatives.

    Parameters
    ----------
    t : ndarray
        Coordinate across the box (mark frame, px).
    a : float
        Full width of the box (px).
    s : float or ndarray
        Gaussian blur sigma (px), broadcast against ``t``.

    Returns
    -------
    B, dB_dt, dB_ds : ndarray (float32)
        Value in [0, 1] and its derivatives.
    """
    t = np.asarray(t, np.float32)
    inv = (1.0 / np.asarray(s, np.float32)).astype(np.float32)
    h = np.float32(0.5 * a)
    zp = (t + h) * inv
    zm = (t - h) * inv
    if zp.size >= 4096:
        # where both edges are far (|z| beyond the clip of _Phi_phi) the profile is exactly
        # 0 or 1 with zero derivatives; a long bar is mostly that: evaluate the rest only
        act = (zp > -_ZSAT) & (zm < _ZSAT) & ((zp < _ZSAT) | (zm > -_ZSAT))
        k = np.flatnonzero(act)
        if k.size < 0.6 * zp.size:
            B = np.subtract((zp > 0).view(np.uint8), (zm > 0).view(np.uint8), dtype=np.float32)
            dBdt = np.zeros(zp.shape, np.float32)
            dBds = np.zeros(zp.shape, np.float32)
            zpk, zmk = zp.reshape(-1)[k], zm.reshape(-1)[k]
            invk = inv.reshape(-1)[k] if inv.shape == zp.shape else (
                np.broadcast_to(inv, zp.shape).reshape(-1)[k] if inv.ndim else inv)
            Pp, pp = _Phi_phi(zpk)
            Pm, pm = _Phi_phi(zmk)
            B.reshape(-1)[k] = Pp - Pm
            dBdt.reshape(-1)[k] = (pp - pm) * invk
            dBds.reshape(-1)[k] = -(zpk * pp - zmk * pm) * invk
            return B, dBdt, dBds
    Pp, pp = _Phi_phi(zp)
    Pm, pm = _Phi_phi(zm)
    B = Pp - Pm
    dBdt = (pp - pm) * inv
    dBds = -(zp * pp - zm * pm) * inv
    return B, dBdt, dBds


def box_pixel_profile(t, a, s, b, m):
    """Blurred box seen through square pixels, across the box, with derivatives.

    The box (full width ``a``) is blurred by a Gaussian ``s`` and integrated over the pixel
    footprint. Projected onto the box's normal, a square pixel is the convolution of two boxes
    of widths ``b >= m`` (the absolute direction cosines of the normal, in the same units as
    ``t``); the wide one is kept exactly, the narrow one is folded into the Gaussian
    (variance ``m**2 / 12``). Exact for boxes aligned with the pixel axes (``m = 0``), where
    sub-pixel phase effects ("pixel locking") are strongest; at other angles the phases of the
    pixels along a bar average out.

    With ``S = sqrt(s**2 + m**2/12)``, ``Psi(z) = z Phi(z) + phi(z)`` (the integral of
    ``Phi``) and ``h = a/2``::

        P(t) = S / b * [Psi((t+h+b/2)/S) - Psi((t+h-b/2)/S)
                        - Psi((t-h+b/2)/S) + Psi((t-h-b/2)/S)]

    Parameters
    ----------
    t : ndarray
        Coordinate across the box (mark frame, px).
    a : float
        Full width of the box.
    s : float or ndarray
        Gaussian blur sigma.
    b, m : float or ndarray
        Wide and narrow pixel-footprint widths along ``t`` (``b > 0``).

    Returns
    -------
    P, dP_dt, dP_ds : ndarray (float32)
    """
    t = np.asarray(t, np.float32)
    s = np.asarray(s, np.float32)
    b = np.asarray(b, np.float32)
    S = np.sqrt(s * s + (np.asarray(m, np.float32) ** 2) / np.float32(12.0))
    inv = (1.0 / S).astype(np.float32)
    h = np.float32(0.5 * a)
    hb = 0.5 * b
    out_P = None
    dPdt = None
    dPdS = None
    for sign, off in ((1.0, h + hb), (-1.0, h - hb), (-1.0, -h + hb), (1.0, -h - hb)):
        z = (t + off) * inv
        P_, p_ = _Phi_phi(z)
        psi = z * P_ + p_
        if out_P is None:
            out_P, dPdt, dPdS = psi, P_.copy(), p_.copy()
        elif sign > 0:
            out_P += psi
            dPdt += P_
            dPdS += p_
        else:
            out_P -= psi
            dPdt -= P_
            dPdS -= p_
    ib = 1.0 / b
    return out_P * (S * ib), dPdt * ib, dPdS * ib * (s * inv)


@dataclass(frozen=True)
class MarkShape:
    """Geometry of one kind of mark in its mark frame, in pixels at the nominal scale.

    ``kind`` is "cross", "bar", "dot" or "circle-dot". For a cross ``length`` is the
    tip-to-tip length of each bar and ``width`` the line width; a bar is one bar of such a
    cross, along ``u`` (a one-armed cross, :func:`softplot.marks.measure.measure_one_arm`).
    For a dot ``radius`` is its radius. For a circle-dot ``radius`` is the radius of the
    circle's centre line, ``width`` its stroke width and ``dot_radius`` the radius of the
    central dot (0 for a plain circle).

    ``opacity`` (0 < a <= 1) is the mark's opacity: a mark of opacity ``a`` and level ``m``
    over the scene ``B`` draws ``B + a (m - B) T``, the scene showing through with weight
    ``1 - a`` (a reseau cross on film or a print). The templates of :meth:`evaluate` and
    :meth:`bars` are ``a T`` (and its derivatives), so that the models' ``B (1 - T) + m T``
    is that; 1 (the default) is an opaque mark and leaves every value as it was.
    """

    kind: str
    length: float = 0.0
    width: float = 0.0
    radius: float = 0.0
    dot_radius: float = 0.0
    opacity: float = 1.0

    @property
    def extent(self) -> float:
        """Half-size (px) of the square that holds the undistorted, unblurred mark."""
        if self.kind in ("cross", "bar"):
            return 0.5 * self.length
        if self.kind == "dot":
            return self.radius
        return self.radius + 0.5 * self.width

    def scaled(self, k: float) -> "MarkShape":
        """The same shape at ``k`` times the size (e.g. in a reduced overview image)."""
        return MarkShape(self.kind, self.length * k, self.width * k, self.radius * k,
                         self.dot_radius * k, self.opacity)

    def with_opacity(self, a: float) -> "MarkShape":
        """The same shape of opacity ``a`` (see the class docstring)."""
        return MarkShape(self.kind, self.length, self.width, self.radius, self.dot_radius,
                         float(a))

    def _seen(self, out):
        """The templates ``out`` (a tuple of arrays) through the mark's opacity: unchanged
        (the same arrays) for an opaque mark, else each times ``opacity``."""
        if self.opacity == 1.0:
            return out
        a = np.float32(self.opacity)
        return tuple(o * a for o in out)

    def bars(self, u, v, s, aperture=None):
        """The two bars of a cross each alone and the central square they share, blurred as
        :meth:`evaluate` blurs the cross: ``(T_u, T_v, T_c)`` at mark-frame points ``u``,
        ``v`` (px), the bar along ``u`` (long in ``u``, narrow in ``v``), the bar along
        ``v`` and the product of the two widths' profiles; :meth:`evaluate`'s cross is
        ``T_u + T_v - T_c`` (each times the :attr:`opacity`)."""
        if self.kind != "cross":
            raise ValueError("bars: a cross only")
        if aperture is None:
            Lu, Lv = box_profile(u, self.length, s)[0], box_profile(v, self.length, s)[0]
            Wu, Wv = box_profile(u, self.width, s)[0], box_profile(v, self.width, s)[0]
        else:
            bu, mu, bv, mv = aperture
            s_len = np.sqrt(np.asarray(s, np.float32) ** 2 + np.float32(1.0 / 12.0))
            Lu, Lv = box_profile(u, self.length, s_len)[0], box_profile(v, self.length, s_len)[0]
            Wu = box_pixel_profile(u, self.width, s, bu, mu)[0]
            Wv = box_pixel_profile(v, self.width, s, bv, mv)[0]
        return self._seen((Lu * Wv, Wu * Lv, Wu * Wv))

    def evaluate(self, u, v, s, aperture=None):
        """Template value and derivatives at mark-frame points.

        Parameters
        ----------
        u, v : ndarray
            Mark-frame coordinates (px), any equal shapes.
        s : float or ndarray
            Gaussian blur sigma (px), broadcast against ``u``.
        aperture : tuple of 4 (float or ndarray), optional
            Pixel footprint in the mark frame ``(b_u, m_u, b_v, m_v)``: for the bar across
            ``u`` (the vertical bar) and across ``v``, the wide and narrow footprint widths
            (see :func:`box_pixel_profile` and :func:`aperture`). None treats the pixel as a
            point (the blur then includes the pixel's 1/12 px^2 variance).

        Returns
        -------
        T, dT_du, dT_dv, dT_ds : ndarray
            The blurred mark (1 on the mark, 0 off it; :attr:`opacity` on it where that is
            below 1) and its derivatives.
        """
        return self._seen(self._evaluate(u, v, s, aperture))

    def _evaluate(self, u, v, s, aperture=None):
        """:meth:`evaluate` of the opaque mark."""
        if aperture is not None:
            bu, mu, bv, mv = aperture
            s_len = np.sqrt(np.asarray(s, np.float32) ** 2 + np.float32(1.0 / 12.0))
        if self.kind == "cross":
            if aperture is None:
                Lu, Lu_t, Lu_s = box_profile(u, self.length, s)
                Wu, Wu_t, Wu_s = box_profile(u, self.width, s)
                Lv, Lv_t, Lv_s = box_profile(v, self.length, s)
                Wv, Wv_t, Wv_s = box_profile(v, self.width, s)
            else:
                ds_len = np.asarray(s, np.float32) / s_len
                Lu, Lu_t, Lu_s = box_profile(u, self.length, s_len)
                Lv, Lv_t, Lv_s = box_profile(v, self.length, s_len)
                Lu_s = Lu_s * ds_len
                Lv_s = Lv_s * ds_len
                Wu, Wu_t, Wu_s = box_pixel_profile(u, self.width, s, bu, mu)
                Wv, Wv_t, Wv_s = box_pixel_profile(v, self.width, s, bv, mv)
            T = Lu * Wv + Wu * Lv - Wu * Wv
            Tu = Lu_t * Wv + Wu_t * Lv - Wu_t * Wv
            Tv = Lu * Wv_t + Wu * Lv_t - Wu * Wv_t
            Ts = (Lu_s * Wv + Lu * Wv_s + Wu_s * Lv + Wu * Lv_s - Wu_s * Wv - Wu * Wv_s)
            return T, Tu, Tv, Ts
        if self.kind == "bar":  # one bar of a cross, along u
            if aperture is None:
                Lu, Lu_t, Lu_s = box_profile(u, self.length, s)
                Wv, Wv_t, Wv_s = box_profile(v, self.width, s)
            else:
                Lu, Lu_t, Lu_s = box_profile(u, self.length, s_len)
                Lu_s = Lu_s * (np.asarray(s, np.float32) / s_len)
                Wv, Wv_t, Wv_s = box_pixel_profile(v, self.width, s, bv, mv)
            return Lu * Wv, Lu_t * Wv, Lu * Wv_t, Lu_s * Wv + Lu * Wv_s
        if aperture is not None:
            ds_len = np.asarray(s, np.float32) / s_len
            s = s_len
        r = np.sqrt(u * u + v * v)
        rs = np.maximum(r, np.float32(1e-6))
        if self.kind == "dot":
            T, Tr, Ts = box_profile(r, 2.0 * self.radius, s)
        elif self.kind == "circle-dot":
            # ring: boxes centred at +-radius along the radius (the mirror term keeps it smooth
            # through the centre); dot: a box of width 2*dot_radius
            T1, T1r, T1s = box_profile(r - self.radius, self.width, s)
            T2, T2r, T2s = box_profile(r + self.radius, self.width, s)
            T, Tr, Ts = T1 + T2, T1r + T2r, T1s + T2s
            if self.dot_radius > 0:
                D, Dr, Ds = box_profile(r, 2.0 * self.dot_radius, s)
                T, Tr, Ts = T + D, Tr + Dr, Ts + Ds
        else:
            raise ValueError(f"unknown mark kind {self.kind!r}")
        if aperture is not None:
            Ts = Ts * ds_len
        return T, Tr * u / rs, Tr * v / rs, Ts


def aperture(A):
    """Pixel footprint widths in the mark frame from pixel -> mark-frame affines.

    Parameters
    ----------
    A : (..., 2, 2) array
        Pixel -> mark-frame affine(s).

    Returns
    -------
    (b_u, m_u, b_v, m_v) : tuple of arrays of shape (...)
        For each mark-frame axis, the larger and smaller absolute change of that coordinate
        per pixel step in x and in y (the projected pixel square's two box widths).
    """
    A = np.abs(np.asarray(A, np.float32))
    bu = np.maximum(A[..., 0, 0], A[..., 0, 1])
    mu = np.minimum(A[..., 0, 0], A[..., 0, 1])
    bv = np.maximum(A[..., 1, 0], A[..., 1, 1])
    mv = np.minimum(A[..., 1, 0], A[..., 1, 1])
    return bu, mu, bv, mv


def cross_shape(camera: Camera, px_per_mm: float) -> MarkShape:
    """The reseau cross of ``camera`` at ``px_per_mm`` (pixels per film mm)."""
    r = camera.reseau
    if r is None:
        raise ValueError(f"camera {camera.name} has no reseau")
    return MarkShape("cross", length=r.arm_length_mm * px_per_mm,
                     width=r.line_width_mm * px_per_mm)


def fiducial_shape(fid: Fiducial, px_per_mm: float) -> MarkShape:
    """The shape of a fiducial mark at ``px_per_mm``.

    A "dot" has diameter ``size_mm``; a "custom" fiducial is modelled as a cross of
    ``size_mm`` (as the synthetic renderer draws it).
    """
    k = px_per_mm
    if fid.shape in ("cross", "custom"):
        return MarkShape("cross", length=fid.size_mm * k,
                         width=min(fid.line_width_mm, 0.5 * fid.size_mm) * k)
    if fid.shape == "circle-dot":
        rad = 0.5 * (fid.size_mm - fid.line_width_mm) * k
        return MarkShape("circle-dot", width=fid.line_width_mm * k, radius=rad,
                         dot_radius=0.5 * fid.dot_mm * k)
    d = fid.size_mm
    return MarkShape("dot", radius=0.5 * d * k)


def render(shape: MarkShape, s: float, A=None, half: int | None = None,
           centre=(0.0, 0.0)) -> np.ndarray:
    """A pixel template of ``shape``: float32 square image, bright mark (1) on 0.

    Parameters
    ----------
    shape : MarkShape
        The mark in its frame (px).
    s : float
        Gaussian blur sigma (px); the square pixel footprint is modelled on top.
    A : (2, 2) array_like, optional
        Pixel -> mark-frame affine (rotation, scale); identity if omitted.
    half : int, optional
        Half-size of the template; the template is ``2*half+1`` pixels square with the mark
        centre at pixel ``(half + centre[0], half + centre[1])`` (pixel system).
    """
    A = np.eye(2) if A is None else np.asarray(A, float)
    if half is None:
        grow = 1.0 / max(np.min(np.abs(np.linalg.svd(A, compute_uv=False))), 1e-6)
        half = int(np.ceil(shape.extent * grow + 3.0 * s + 1))
    y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(float)
    x -= centre[0]
    y -= centre[1]
    u = A[0, 0] * x + A[0, 1] * y
    v = A[1, 0] * x + A[1, 1] * y
    return shape.evaluate(u, v, s, aperture=aperture(A))[0].astype(np.float32)
