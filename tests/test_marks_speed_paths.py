"""Faster paths of the reseau detection's stages give exactly what the plain formulations
give (the plain ones written out here, as they stood in the package before)."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks import candidates, coarse


def _arm_evidence_plain(image, xy, sign, arm_half, width, s, turn_deg=0.0):
    """:func:`candidates.arm_evidence` as first written: each point's window gathered by
    clipped indices, the mean along an arm by ``mean(-1)``, the third-best arm by a sort."""
    K = len(xy)
    out = np.full(K, -np.inf)
    Hh, W = image.shape
    r0 = max(1.5, width + s)
    r = np.linspace(r0, max(arm_half, r0 + 1.0), 6)
    d = max(1.5, 1.0 * width + 1.5 * s)
    reach = int(np.ceil(np.hypot(r[-1], d))) + 2
    x0 = np.floor(xy[:, 0]).astype(int)
    y0 = np.floor(xy[:, 1]).astype(int)
    ok = (x0 >= 0) & (x0 < W) & (y0 >= 0) & (y0 < Hh)
    t = np.radians(turn_deg + candidates.ARM_TURNS)[:, None] + np.arange(4) * (np.pi / 2)
    u = np.stack([np.cos(t), np.sin(t)], -1)
    nrm = np.stack([-u[..., 1], u[..., 0]], -1)
    side = np.array([0.0, d, -d])
    off = (r[None, None, None, :, None] * u[:, :, None, None, :]
           + side[None, None, :, None, None] * nrm[:, :, None, None, :])
    i = np.flatnonzero(ok)
    ar = np.arange(-reach, reach + 2)
    cy = np.clip(y0[i][:, None] + ar, 0, Hh - 1)
    cx = np.clip(x0[i][:, None] + ar, 0, W - 1)
    win = np.asarray(image[cy[:, :, None], cx[:, None, :]], np.float32)
    p = xy[i]
    fx, fy = p[:, 0] - x0[i] + reach, p[:, 1] - y0[i] + reach
    v = candidates._read(win, fx, fy, off.reshape(-1, 2)).reshape((len(p),) + off.shape[:4])
    v = v.mean(-1)
    d1, d2 = v[..., 0] - v[..., 1], v[..., 0] - v[..., 2]
    a = sign * np.where(sign > 0, np.minimum(d1, d2), np.maximum(d1, d2))
    third = np.sort(a, axis=2)[..., 1]
    bar = np.maximum(np.minimum(a[..., 0], a[..., 2]), np.minimum(a[..., 1], a[..., 3]))
    out[ok] = np.maximum(third, 0.5 * bar).max(1)
    return out


@pytest.mark.parametrize("sign", [1, -1])
def test_arm_evidence_is_the_plain_formulation(sign, monkeypatch):
    """On a float image and on a compact 8-bit overview (inverted grey), points inside, at
    and beyond the edges: the evidence equals the plain formulation's bit for bit (one
    chunk, as the plain one reads them), and -inf outside."""
    import cv2

    rng = np.random.default_rng(11)
    img = rng.uniform(0.3, 0.6, (70, 95)).astype(np.float32)
    cv2.line(img, (20, 30), (60, 30), 0.8, 1)
    cv2.line(img, (40, 10), (40, 50), 0.8, 1)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    q = np.round(img * 255).astype(np.uint8)
    ov = coarse.Overview(q, 1.0 / 255.0, invert=True)
    pts = np.column_stack([rng.uniform(-4, 99, 120), rng.uniform(-4, 74, 120)])
    pts[:4] = [[40.3, 30.6], [0.2, 0.7], [94.5, 69.5], [3.0, 68.2]]
    monkeypatch.setattr(candidates, "ARM_CHUNK", 1000)
    for image in (img, ov):
        for turn in (0.0, 7.5):
            fast = candidates.arm_evidence(image, pts, sign, 8.0, 1.0, 0.7, turn)
            plain = _arm_evidence_plain(image, pts, sign, 8.0, 1.0, 0.7, turn)
            assert np.isfinite(fast).sum() > 80
            assert np.array_equal(fast, plain)
