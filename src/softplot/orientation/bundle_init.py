"""Approximate values for a bundle: resection, intersection and relative orientation.

:func:`initialize` fills the NaN exterior orientations and object coordinates of a
:class:`~softplot.orientation.bundle.BundleData` (frames as there):

1. points with known control coordinates take them as approximations;
2. repeat: every photo without an orientation that sees >= 4 points with approximations is
   resected (:func:`softplot.orientation.resect`); every point without coordinates seen by >= 2
   oriented photos is intersected (:func:`softplot.orientation.intersect`);
3. when nothing is known at all (a free network without approximations), the pair of photos
   sharing most points is relatively oriented (dependent pair, base 1 along the left photo's
   x axis, :func:`softplot.orientation.relative_orientation`): the left photo's frame becomes
   the object frame, then step 2 continues;
4. when step 2 stops short with only a minimal control datum (three control points, or
   control seen by a few photos: some photo sees fewer than four known points), the block is
   built in a model frame by steps 3 and 2 - the relative orientation of the best pair,
   chained through the block by resections and intersections - and moved onto the control
   by the 7-parameter similarity fitted to the control points it contains (at least three
   not on a line); then step 2 finishes.

Image coordinates are reduced to the camera's principal point; lens distortion is ignored at
this stage (the bundle estimates it).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix
from softplot.orientation.bundle import BundleData, _helmert_to
from softplot.orientation.intersection import intersect
from softplot.orientation.relative import relative_orientation
from softplot.orientation.resection import resect

__all__ = ["initialize"]


def _reduced(data: BundleData, obs: np.ndarray) -> np.ndarray:
    cam = data.photo_camera[data.obs_photo[obs]]
    pp = np.array([[c.values[1], c.values[2]] for c in data.cameras]).reshape(-1, 2)
    return data.xy[obs] - pp[cam]


def _c_of(data: BundleData, f: int) -> float:
    return float(data.cameras[data.photo_camera[f]].values[0])


def initialize(data: BundleData, max_rounds: int = 50) -> BundleData:
    """Fill missing approximations in place and return ``data``.

    Raises
    ------
    SoftplotError
        A photo or point that cannot be reached (names it).
    """
    try:
        return _initialize(data, max_rounds)
    except SoftplotError as first:
        if not _model_frame_start(data, max_rounds):
            raise first from None
    return _initialize(data, max_rounds)


def _model_frame_start(d: BundleData, max_rounds: int) -> bool:
    """Step 4: the block in a model frame from chained relative orientations, moved onto the
    control by a 7-parameter similarity. Fills only what is missing; False if impossible."""
    ctl = np.all(np.isfinite(d.control), axis=1) & ~d.check
    if ctl.sum() < 3:
        return False
    F, P = len(d.photo_names), len(d.point_names)
    m = dataclasses.replace(
        d,
        X0=np.full((F, 3), np.nan),
        angles=np.full((F, 3), np.nan),
        XYZ=np.full((P, 3), np.nan),
        control=np.full((P, 3), np.nan),
        control_sigma=np.full((P, 3), np.nan),
        photo_fixed=np.zeros(F, bool),
    )
    try:
        _relative_start(m)
        _initialize(m, max_rounds, partial=True)
    except SoftplotError:
        return False
    both = ctl & np.all(np.isfinite(m.XYZ), axis=1)
    if both.sum() < 3:
        return False
    src, dst = m.XYZ[both], d.control[both]
    sv = np.linalg.svd(src - src.mean(0), compute_uv=False)
    if sv[1] < 1e-6 * sv[0]:
        return False  # control on a line: the similarity is undetermined
    s, R, t = _helmert_to(src, dst)
    eo = np.all(np.isfinite(m.X0), axis=1)
    miss_eo = eo & ~(np.all(np.isfinite(d.X0), axis=1) & np.all(np.isfinite(d.angles), axis=1))
    M = rotation_matrix(m.angles[eo, 0], m.angles[eo, 1], m.angles[eo, 2]) @ R.T
    X0 = s * m.X0[eo] @ R.T + t
    Xf = np.full((F, 3), np.nan)
    Af = np.full((F, 3), np.nan)
    Xf[eo], Af[eo] = X0, np.column_stack(angles_from_matrix(M))
    d.X0[miss_eo], d.angles[miss_eo] = Xf[miss_eo], Af[miss_eo]
    pts = np.all(np.isfinite(m.XYZ), axis=1) & ~np.all(np.isfinite(d.XYZ), axis=1)
    d.XYZ[pts] = s * m.XYZ[pts] @ R.T + t
    return bool(miss_eo.any() or pts.any())


def _initialize(data: BundleData, max_rounds: int, partial: bool = False) -> BundleData:
    d = data
    P = len(d.point_names)
    ctl_full = np.all(np.isfinite(d.control), axis=1)
    miss = ~np.all(np.isfinite(d.XYZ), axis=1)
    d.XYZ[miss & ctl_full] = d.control[miss & ctl_full]
    eo_ok = np.all(np.isfinite(d.X0), axis=1) & np.all(np.isfinite(d.angles), axis=1)
    pt_ok = np.all(np.isfinite(d.XYZ), axis=1)
    if not pt_ok.any() and not eo_ok.any():
        _relative_start(d)
        eo_ok = np.all(np.isfinite(d.X0), axis=1) & np.all(np.isfinite(d.angles), axis=1)
        pt_ok = np.all(np.isfinite(d.XYZ), axis=1)
    for _ in range(max_rounds):
        progress = False
        # resection of photos
        for f in np.flatnonzero(~eo_ok):
            obs = np.flatnonzero((d.obs_photo == f) & pt_ok[d.obs_point])
            if obs.size < 4:
                continue
            try:
                r = resect(
                    _reduced(d, obs),
                    d.XYZ[d.obs_point[obs]],
                    _c_of(d, f),
                    sigma_xy=float(np.median(d.sigma_xy[obs])),
                )
            except SoftplotError:
                continue
            d.X0[f], d.angles[f] = r.X0, r.angles
            eo_ok[f] = True
            progress = True
        # intersection of points
        rays = np.bincount(d.obs_point[eo_ok[d.obs_photo]], minlength=P)
        new = (~pt_ok) & (rays >= 2)
        if new.any():
            obs = np.flatnonzero(new[d.obs_point] & eo_ok[d.obs_photo])
            pts = np.flatnonzero(new)
            pmap = -np.ones(P, np.int64)
            pmap[pts] = np.arange(pts.size)
            cams = d.photo_camera
            cvals = np.array([c.values[0] for c in d.cameras])[cams]
            try:
                res = intersect(
                    _reduced(d, obs),
                    pmap[d.obs_point[obs]],
                    d.obs_photo[obs],
                    np.nan_to_num(d.X0),
                    np.nan_to_num(d.angles),
                    cvals,
                    n_points=pts.size,
                )
                d.XYZ[pts] = res.XYZ
                pt_ok[pts] = True
                progress = True
            except SoftplotError:
                # intersect point by point to skip the degenerate ones
                for j in pts:
                    o = obs[d.obs_point[obs] == j]
                    try:
                        res = intersect(
                            _reduced(d, o),
                            np.zeros(o.size, int),
                            d.obs_photo[o],
                            np.nan_to_num(d.X0),
                            np.nan_to_num(d.angles),
                            cvals,
                            n_points=1,
                        )
                    except SoftplotError:
                        continue
                    d.XYZ[j] = res.XYZ[0]
                    pt_ok[j] = True
                    progress = True
        if eo_ok.all() and pt_ok.all():
            return d
        if not progress:
            break
    if partial:
        return d
    bad_f = [d.photo_names[f] for f in np.flatnonzero(~eo_ok)]
    bad_p = [d.point_names[p] for p in np.flatnonzero(~pt_ok)]
    raise SoftplotError(
        "cannot initialise the bundle: "
        + (f"photo(s) {bad_f[:5]} see fewer than 4 known points; " if bad_f else "")
        + (f"point(s) {bad_p[:5]} have fewer than 2 oriented rays" if bad_p else "")
    )


def _relative_start(d: BundleData) -> None:
    """Relative orientation of the pair with most common points (sets the object frame)."""
    F = len(d.photo_names)
    P = len(d.point_names)
    A = np.zeros((F, P), bool)
    A[d.obs_photo, d.obs_point] = True
    common = A.astype(int) @ A.T.astype(int)
    np.fill_diagonal(common, 0)
    i, j = np.unravel_index(int(np.argmax(common)), common.shape)
    if common[i, j] < 5:
        raise SoftplotError("free network: no pair of photos shares 5 points to start from")
    if d.photo_camera[i] != d.photo_camera[j]:
        pass  # the relative orientation uses one c; the bundle refines both cameras
    pts = np.flatnonzero(A[i] & A[j])
    key_i = {
        p: o
        for o, p in zip(
            np.flatnonzero(d.obs_photo == i), d.obs_point[d.obs_photo == i], strict=True
        )
    }
    key_j = {
        p: o
        for o, p in zip(
            np.flatnonzero(d.obs_photo == j), d.obs_point[d.obs_photo == j], strict=True
        )
    }
    oi = np.array([key_i[p] for p in pts])
    oj = np.array([key_j[p] for p in pts])
    c = _c_of(d, i)
    xy1, xy2 = _reduced(d, oi), _reduced(d, oj)
    best = None
    for bx in (1.0, -1.0):  # the side of the right photo: keep the better-fitting solution
        try:
            ro = relative_orientation(
                xy1, xy2, c, bx=bx, mode="dependent", sigma=float(np.median(d.sigma_xy))
            )
        except SoftplotError:
            continue
        if best is None or ro.sigma0 < best.sigma0:
            best = ro
    if best is None:
        raise SoftplotError(
            f"free network: relative orientation of {d.photo_names[i]} and "
            f"{d.photo_names[j]} failed"
        )
    ro = best
    d.X0[i] = 0.0
    d.angles[i] = 0.0
    d.X0[j] = ro.base
    d.angles[j] = ro.angles2
    d.XYZ[pts] = ro.points.XYZ
