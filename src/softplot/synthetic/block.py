"""Synthetic aerial block: strips with forward and side overlap, edge control, check points.

Object frame: X along the strips (flight direction), Y across, Z up, metres. Photos are
near-vertical (camera looking down, photo x along the flight, y to the left of it) of an
aerial camera (default Wild RC10: c = 152 mm, 230 x 230 mm; scale 1 : H / c). With format
side ``s`` on the ground ``S = s H / c``, the air base is ``B = (1 - forward) S`` and the strip
spacing ``(1 - side) S``. ``n_strips x photos_per_strip`` photos give
``n_strips (photos_per_strip - 1)`` stereo models.

Ground points lie on a jittered grid of spacing ``B / 2`` (about nine per model) on a terrain
of relief ``relief`` (m). Full control (X, Y, Z) at the block edges every ``control_every``
bases along the strips and at the first and last photo of every strip; ``n_check`` check
points drawn from the interior (their known coordinates are not used by the adjustment).
"""

from __future__ import annotations

import numpy as np

from softplot.synthetic.network import Network, observe, perturb_eo

__all__ = ["make_block", "models_of"]

#: true interior orientation of the aerial camera (c, x0, y0 mm, k1 mm^-2, ...)
RC10 = np.array([152.05, 0.004, -0.006, 2.0e-9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


def make_block(
    n_strips: int = 5,
    photos_per_strip: int = 21,
    forward: float = 0.6,
    side: float = 0.3,
    height: float = 1520.0,
    relief: float = 60.0,
    noise_um: float = 3.0,
    control_sigma_m: float = 0.05,
    control_every: int = 4,
    n_check: int = 20,
    intrinsics=None,
    given=None,
    format_mm: float = 230.0,
    seed: int = 0,
    approx_sigma=(10.0, 0.01),
    attitude_sigma: float = 0.02,
) -> Network:
    """An aerial block with exact truth (see the module docstring).

    Returns
    -------
    Network
        ``info`` holds ``models`` (list of (left photo, right photo) per model), ``base``,
        ``strip_spacing``, ``scale``.
    """
    rng = np.random.default_rng(seed)
    intr = np.asarray(RC10 if intrinsics is None else intrinsics, float)
    giv = np.asarray(intr if given is None else given, float)
    c = intr[0]
    S = format_mm * height / c
    B = (1.0 - forward) * S
    A = (1.0 - side) * S
    X0, M, names, models = [], [], [], []
    for s in range(n_strips):
        for i in range(photos_per_strip):
            C = np.array([i * B, s * A, height]) + rng.normal(0, [5.0, 5.0, 5.0])
            Mi = np.eye(3)  # vertical photo: photo x = +X, y = +Y, looking down (-z)
            dR = _small_rotation(rng.normal(0, attitude_sigma, 3))
            X0.append(C)
            M.append(dR @ Mi)
            names.append(f"S{s + 1}P{i + 1:02d}")
            if i:
                models.append((len(names) - 2, len(names) - 1))
    X0, M = np.array(X0), np.array(M)
    # ground points
    gx = np.arange(-0.45 * S, (photos_per_strip - 1) * B + 0.45 * S, B / 2.0)
    gy = np.arange(-0.45 * S, (n_strips - 1) * A + 0.45 * S, B / 2.0)
    GX, GY = np.meshgrid(gx, gy, indexing="ij")
    P = np.column_stack([GX.ravel(), GY.ravel(), np.zeros(GX.size)])
    P[:, :2] += rng.normal(0, B / 12.0, (P.shape[0], 2))
    kx, ky = rng.uniform(0.5, 1.5, 2) * 2 * np.pi / (4 * B)
    P[:, 2] = relief * 0.5 * (np.sin(kx * P[:, 0]) * np.cos(ky * P[:, 1])) + rng.normal(
        0, relief * 0.1, P.shape[0]
    )
    fm = [(format_mm, format_mm)]
    op, oq, xy_true = observe(intr[None], np.zeros(len(X0), int), X0, M, P, fm, 0, rng)
    # keep points with >= 2 rays
    rays = np.bincount(oq, minlength=P.shape[0])
    keep = rays >= 2
    remap = -np.ones(P.shape[0], int)
    remap[keep] = np.arange(keep.sum())
    sel = keep[oq]
    op, oq, xy_true = op[sel], remap[oq[sel]], xy_true[sel]
    P = P[keep]
    n = P.shape[0]
    # control at the edges: points near the block boundary, thinned along the strips
    x_lo, x_hi = P[:, 0].min(), P[:, 0].max()
    y_lo, y_hi = P[:, 1].min(), P[:, 1].max()
    edge_band = B / 2.0
    at_end = (P[:, 0] < x_lo + edge_band) | (P[:, 0] > x_hi - edge_band)
    at_side = (P[:, 1] < y_lo + edge_band) | (P[:, 1] > y_hi - edge_band)
    along = np.floor((P[:, 0] - x_lo) / B).astype(int) % max(control_every, 1) == 0
    across = np.floor((P[:, 1] - y_lo) / (A / 2.0)).astype(int) % 2 == 0
    ctl = (at_side & along) | (at_end & across)
    interior = ~(at_end | at_side)
    cand = np.flatnonzero(interior)
    check = np.zeros(n, bool)
    check[rng.choice(cand, size=min(n_check, cand.size), replace=False)] = True
    control = np.full((n, 3), np.nan)
    control_sigma = np.full((n, 3), np.nan)
    known = ctl | check
    noise_c = rng.normal(0, control_sigma_m, (n, 3)) if control_sigma_m > 0 else 0.0
    control[known] = (P + noise_c)[known]
    control_sigma[ctl] = control_sigma_m
    noise = noise_um / 1000.0
    xy = xy_true + rng.normal(0, noise, xy_true.shape)
    Xa, ang = perturb_eo(X0, M, rng, *approx_sigma)
    return Network(
        camera_names=["RC10"],
        intr_true=intr[None].copy(),
        intr_given=giv[None].copy(),
        format_mm=fm,
        photo_names=names,
        photo_camera=np.zeros(len(names), int),
        X0_true=X0,
        M_true=M,
        X0_approx=Xa,
        angles_approx=ang,
        point_names=[f"G{i:05d}" for i in range(n)],
        XYZ_true=P,
        XYZ_approx=np.full((n, 3), np.nan),
        control=control,
        control_sigma=control_sigma,
        check=check,
        obs_photo=op,
        obs_point=oq,
        xy=xy,
        xy_true=xy_true,
        sigma_xy=noise if noise > 0 else 0.001,
        info={
            "kind": "block",
            "models": models,
            "base": B,
            "strip_spacing": A,
            "scale": height / c,
            "n_models": len(models),
            "n_control": int(ctl.sum()),
            "n_check": int(check.sum()),
            "seed": seed,
        },
    )


def _small_rotation(v):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(v).as_matrix()


def models_of(photo_names, strip_of=None):
    """Consecutive photo pairs of every strip: ``[(i, i+1), ...]`` by photo name order.

    ``strip_of`` maps a photo name to its strip (default: the part before the last "P").
    """
    strip_of = strip_of or (lambda n: n.rsplit("P", 1)[0])
    out = []
    for i in range(len(photo_names) - 1):
        if strip_of(photo_names[i]) == strip_of(photo_names[i + 1]):
            out.append((i, i + 1))
    return out
