"""Aerial triangulation by independent models (Birardi, ISP 1980) on the sparse engine.

Each model is a pair of consecutive photos of a strip. Its *model coordinates* come from the
relative orientation of the pair (:func:`softplot.orientation.relative_orientation`,
independent pair: left projection centre at the origin, right one at ``(bx, 0, 0)``) of the
photo coordinates reduced to the principal point and corrected for lens distortion with the
camera's known interior orientation. The models are joined into the object frame (X, Y, Z up,
metres) by one 3-D similarity each, ``X = s R x + T``, adjusted simultaneously with the
object coordinates of the tie points, the projection centres and the control:

* every model point gives three residuals ``s R x + T - X`` (object units, unit weight: the
  a posteriori sigma0 is the RMS model-point discrepancy in metres);
* the projection centre of a photo appears in the two models that contain it and ties them in
  X, Y, Z (``pc_tie="xyz"``) or, as Birardi proposes for analogue plotters whose planimetric
  centres are unreliable, in Z only (``pc_tie="z"``);
* control coordinates are fixed (sigma 0) or weighted by their standard errors; check points'
  known coordinates are not used and give the RMS at check points.

Unknowns are solved by :func:`softplot.adjust.sparse_bundle.levenberg_marquardt` (groups =
models with 7 unknowns: translation, rotation increment on the manifold, scale; points 3).
Start: a breadth-first chain of closed-form similarities (Umeyama) from the model with most
control through models sharing >= 3 points.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from softplot.adjust._blas import blas_threads
from softplot.adjust.sparse_bundle import (
    Evaluation,
    LMOptions,
    NormalInverse,
    SchurStructure,
    levenberg_marquardt,
)
from softplot.errors import SoftplotError
from softplot.orientation.absolute import kabsch
from softplot.orientation.bundle import BundleData, distortion
from softplot.orientation.relative import relative_orientation

__all__ = ["ModelCoordinates", "form_models", "independent_models", "IndependentModelResult"]


@dataclass
class ModelCoordinates:
    """One model: photo pair, model coordinates of its points and of both projection centres.

    ``points`` are indices into the block's points; ``xyz`` (n, 3) their model coordinates
    (model frame of the relative orientation, base units); ``pc`` (2, 3) the projection
    centres of the left and right photo in the same frame; ``sigma0`` of the relative
    orientation (photo mm).
    """

    left: int
    right: int
    points: np.ndarray
    xyz: np.ndarray
    pc: np.ndarray
    sigma0: float


def _photo_coordinates(data: BundleData, obs: np.ndarray) -> np.ndarray:
    """Photo coordinates (mm): measured film points reduced and corrected for distortion."""
    cam = data.photo_camera[data.obs_photo[obs]]
    P = np.array([c.values for c in data.cameras])[cam]
    xb = data.xy[obs, 0] - P[:, 1]
    yb = data.xy[obs, 1] - P[:, 2]
    d, _, _ = distortion(xb, yb, P)
    return np.column_stack([xb - d[:, 0], yb - d[:, 1]])


def consecutive_models(data: BundleData, min_common: int = 6) -> list:
    """Consecutive photos (in the data's order) of the same camera sharing >= ``min_common``
    points."""
    F = len(data.photo_names)
    sets = [set(data.obs_point[data.obs_photo == f].tolist()) for f in range(F)]
    return [
        (f, f + 1)
        for f in range(F - 1)
        if data.photo_camera[f] == data.photo_camera[f + 1]
        and len(sets[f] & sets[f + 1]) >= min_common
    ]


def form_models(data: BundleData, models=None) -> list:
    """Relative orientation of every model; returns a list of :class:`ModelCoordinates`."""
    models = consecutive_models(data) if models is None else list(models)
    if not models:
        raise SoftplotError("independent models: no pair of consecutive photos shares points")
    out = []
    for i, j in models:
        oi = np.flatnonzero(data.obs_photo == i)
        oj = np.flatnonzero(data.obs_photo == j)
        pi, pj = data.obs_point[oi], data.obs_point[oj]
        common, ia, ja = np.intersect1d(pi, pj, return_indices=True)
        if common.size < 6:
            raise SoftplotError(
                f"model {data.photo_names[i]}-{data.photo_names[j]}: only {common.size} "
                "common points (need 6)"
            )
        xy1 = _photo_coordinates(data, oi[ia])
        xy2 = _photo_coordinates(data, oj[ja])
        c = float(data.cameras[data.photo_camera[i]].values[0])
        bx = 1.0 if np.mean(xy1[:, 0] - xy2[:, 0]) > 0 else -1.0
        sig = float(np.median(data.sigma_xy[oi]))
        try:
            ro = None
            try:  # near-normal case first (aerial strips): zero rotations as the start
                ro = relative_orientation(
                    xy1,
                    xy2,
                    c,
                    bx=bx,
                    mode="independent",
                    sigma=sig,
                    start=np.array([bx, 0, 0, 0, 0, 0, 0, 0, 0.0]),
                )
                if not ro.sigma0 < 10 * sig:
                    ro = None
            except SoftplotError:
                ro = None
            if ro is None:  # general case: essential-matrix start
                ro = relative_orientation(xy1, xy2, c, bx=bx, mode="independent", sigma=sig)
        except SoftplotError as exc:
            raise SoftplotError(
                f"model {data.photo_names[i]}-{data.photo_names[j]}: {exc}"
            ) from exc
        pc = np.array([[0.0, 0.0, 0.0], ro.base])
        out.append(ModelCoordinates(i, j, common, ro.points.XYZ.copy(), pc, float(ro.sigma0)))
    return out


@dataclass
class IndependentModelResult:
    """Outcome of :func:`independent_models` (object frame, metres)."""

    XYZ: np.ndarray  # (P, 3) adjusted points (nan where in no model)
    XYZ_std: np.ndarray  # (P, 3)
    projection_centres: np.ndarray  # (F, 3) nan for photos in no model
    pc_std: np.ndarray  # (F, 3)
    similarities: np.ndarray  # (n_models, 7): scale, rotation vector (3), T (3)
    models: list
    sigma0: float
    redundancy: int
    iterations: int
    seconds: float
    converged: bool
    pc_tie: str
    check: dict | None
    data: BundleData = field(repr=False)

    def to_json(self) -> dict:
        d = self.data
        ok = np.all(np.isfinite(self.XYZ), axis=1)
        return {
            "method": "independent-models",
            "pc_tie": self.pc_tie,
            "models": len(self.models),
            "sigma0_m": self.sigma0,
            "redundancy": self.redundancy,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "converged": self.converged,
            "check_points_rms": self.check,
            "relative_orientation_sigma0_mm": [m.sigma0 for m in self.models],
            "points": [
                {
                    "name": d.point_names[p],
                    **{
                        a: {"value": float(self.XYZ[p, k]), "std": float(self.XYZ_std[p, k])}
                        for k, a in enumerate("XYZ")
                    },
                }
                for p in np.flatnonzero(ok)
            ],
            "projection_centres": [
                {
                    "photo": d.photo_names[f],
                    **{
                        a: {
                            "value": float(self.projection_centres[f, k]),
                            "std": float(self.pc_std[f, k]),
                        }
                        for k, a in enumerate("XYZ")
                    },
                }
                for f in range(len(d.photo_names))
                if np.isfinite(self.projection_centres[f, 0])
            ],
        }


class _IMModel:
    """Engine model: groups = models (T, rotation increment, scale), points = object points
    followed by projection centres."""

    def __init__(self, models, n_pts, n_photos, pc_tie, control, control_sigma, used, sigma):
        self.models = models
        og, op, ox, rowmask = [], [], [], []
        for g, m in enumerate(models):
            og.append(np.full(m.points.size + 2, g))
            op.append(np.concatenate([m.points, [n_pts + m.left, n_pts + m.right]]))
            ox.append(np.vstack([m.xyz, m.pc]))
            mask = np.ones((m.points.size + 2, 3))
            if pc_tie == "z":
                mask[-2:, :2] = 0.0
            rowmask.append(mask)
        self.og = np.concatenate(og)
        self.op = np.concatenate(op)
        self.ox = np.vstack(ox)
        self.rowmask = np.vstack(rowmask) / sigma
        G = len(models)
        P = n_pts + n_photos
        pf = np.ones((P, 3), bool)
        fixed = used & (control_sigma == 0)
        pf[:n_pts] &= ~fixed
        seen = np.zeros(P, bool)
        seen[self.op] = True
        pf[~seen] = False
        if pc_tie == "z":
            pf[n_pts:, :2] = False
        self.point_free = pf
        self.structure = SchurStructure(
            7 * G, P, np.arange(7 * G).reshape(G, 7), self.og, self.op, d=3, point_free=pf
        )
        wt = used & (control_sigma > 0) & seen[:n_pts, None]  # points in no model: ignored
        self.cp_idx = np.flatnonzero(wt.any(axis=1))
        self.cp_w = np.where(wt, 1.0 / np.where(wt, control_sigma, 1.0), 0.0)[self.cp_idx]
        self.cp_val = np.where(wt, control, 0.0)[self.cp_idx]
        self.n_rows = int(np.count_nonzero(self.rowmask)) + int(np.count_nonzero(self.cp_w))

    def evaluate(self, state, jacobian):
        T, R, s, X = state
        g = self.og
        Rx = np.einsum("mij,mj->mi", R[g], self.ox)
        r = (s[g, None] * Rx + T[g] - X[self.op]) * self.rowmask
        pt_prior = None
        if self.cp_idx.size:
            J = np.zeros((self.cp_idx.size, 3, 3))
            J[:, 0, 0], J[:, 1, 1], J[:, 2, 2] = self.cp_w.T
            pt_prior = (self.cp_idx, (X[self.cp_idx] - self.cp_val) * self.cp_w, J)
        if not jacobian:
            return Evaluation(r, pt_prior=pt_prior)
        m = r.shape[0]
        Jc = np.zeros((m, 3, 7))
        Jc[:, 0, 0] = Jc[:, 1, 1] = Jc[:, 2, 2] = 1.0
        q = s[g, None] * Rx  # d/d delta of exp([d]x) R x s = -[q]x
        Jc[:, 0, 4], Jc[:, 0, 5] = q[:, 2], -q[:, 1]
        Jc[:, 1, 3], Jc[:, 1, 5] = -q[:, 2], q[:, 0]
        Jc[:, 2, 3], Jc[:, 2, 4] = q[:, 1], -q[:, 0]
        Jc[:, :, 6] = Rx
        Jc *= self.rowmask[:, :, None]
        Jp = -np.broadcast_to(np.eye(3), (m, 3, 3)) * self.rowmask[:, :, None]
        return Evaluation(r, Jc, Jp, pt_prior=pt_prior)

    def retract(self, state, d_cam, d_pts):
        T, R, s, X = state
        d = d_cam.reshape(-1, 7)
        R2 = np.matmul(Rotation.from_rotvec(d[:, 3:6]).as_matrix(), R)
        return T + d[:, :3], R2, s + d[:, 6], X + d_pts


def _start(models, n_pts, n_photos, control_ok, control_xyz):
    """Start values ``T, R, s, X``: breadth-first chain of closed-form similarities from the
    model with most control, then one similarity of the whole chain onto the control."""
    G = len(models)
    P = n_pts + n_photos
    sums = np.zeros((P, 3))
    cnt = np.zeros(P)
    T = np.zeros((G, 3))
    R = np.tile(np.eye(3), (G, 1, 1))
    s = np.ones(G)
    placed = np.zeros(G, bool)
    ids = [np.concatenate([m.points, [n_pts + m.left, n_pts + m.right]]) for m in models]
    xyz = [np.vstack([m.xyz, m.pc]) for m in models]
    ctl = np.zeros(P, bool)
    ctl[:n_pts] = control_ok
    first = int(np.argmax([ctl[i].sum() for i in ids]))
    queue = deque([first])
    while not placed.all():
        if not queue:
            rest = np.flatnonzero(~placed)
            raise SoftplotError(
                f"independent models: {rest.size} model(s) share fewer than 3 points with the "
                "rest of the block"
            )
        g = queue.popleft()
        if placed[g]:
            continue
        i = ids[g]
        known = cnt[i] > 0
        if placed.any():
            if known.sum() < 3:
                continue
            sc, Rg, tg = kabsch(
                xyz[g][known], sums[i][known] / cnt[i][known, None], with_scale=True
            )
        else:
            sc, Rg, tg = 1.0, np.eye(3), np.zeros(3)
        T[g], R[g], s[g] = tg, Rg, sc
        placed[g] = True
        sums[i] += sc * xyz[g] @ Rg.T + tg
        cnt[i] += 1
        for h in np.flatnonzero(~placed):
            if (cnt[ids[h]] > 0).sum() >= 3:
                queue.append(h)
    X = sums / np.maximum(cnt, 1)[:, None]
    ok = ctl & (cnt > 0)
    if ok.sum() < 3:
        raise SoftplotError("independent models: fewer than 3 full control points in the block")
    sc, Rg, tg = kabsch(X[ok], control_xyz[ok[:n_pts]], with_scale=True)  # (n_pts, 3)
    X = sc * X @ Rg.T + tg
    T = sc * T @ Rg.T + tg
    R = np.matmul(Rg, R)
    s = s * sc
    return T, R, s, X


def independent_models(
    data: BundleData,
    models=None,
    pc_tie: str = "xyz",
    sigma_model: float = 1.0,
    options: LMOptions | None = None,
) -> IndependentModelResult:
    """Independent-model aerial triangulation (see the module docstring).

    Parameters
    ----------
    data : BundleData
        Photos, observations (film mm), cameras (interior orientation used as known), control
        and check points; approximations are not needed.
    models : list of (left, right) photo indices, optional
        Default: consecutive photos sharing >= 6 points.
    pc_tie : {"xyz", "z"}
        Tie of the projection centres between adjacent models.
    sigma_model : float
        A priori standard error of a model coordinate in object units (1: sigma0 in metres).
    options : LMOptions, optional

    Returns
    -------
    IndependentModelResult
    """
    if pc_tie not in ("xyz", "z"):
        raise SoftplotError(f"pc_tie must be 'xyz' or 'z', got {pc_tie!r}")
    mods = form_models(data, models)
    P, F = len(data.point_names), len(data.photo_names)
    used = data.control_used
    full = used.all(axis=1)
    ctl = np.where(used, data.control, np.nan)
    model = _IMModel(mods, P, F, pc_tie, ctl, data.control_sigma, used, sigma_model)
    start = _start(mods, P, F, full, np.nan_to_num(ctl))
    opt = options or LMOptions(function_tolerance=1e-12)
    with blas_threads(1):
        res = levenberg_marquardt(model, start, opt)
        T, R, s, X = res.state
        ev = model.evaluate(res.state, False)
        red = model.n_rows - model.structure.n_unknowns
        sigma0 = float(np.sqrt(2 * ev.cost / red)) if red > 0 else float("nan")
        inv = NormalInverse(res.linearization)
        Qpp = inv.point_blocks()
    var = sigma0**2 if red > 0 else 1.0
    std = np.sqrt(np.clip(np.einsum("pii->pi", Qpp), 0, None) * var)
    seen = np.zeros(P + F, bool)
    seen[model.op] = True
    Xo = np.where(seen[:, None], X, np.nan)
    if pc_tie == "z":
        # planimetric centres: mean of the models' transformed values
        g = model.og
        pcs = model.op >= P
        tr = s[g[pcs], None] * np.einsum("mij,mj->mi", R[g[pcs]], model.ox[pcs]) + T[g[pcs]]
        ph = model.op[pcs] - P
        for a in range(2):
            num = np.bincount(ph, weights=tr[:, a], minlength=F)
            den = np.bincount(ph, minlength=F)
            Xo[P:, a] = np.where(den > 0, num / np.maximum(den, 1), np.nan)
        std[P:, :2] = np.nan
    check = None
    ok = data.check & np.all(np.isfinite(data.control), axis=1) & seen[:P]
    if ok.any():
        e = Xo[:P][ok] - data.control[ok]
        r = np.sqrt(np.mean(e**2, axis=0))
        check = {"n": int(ok.sum()), "X": float(r[0]), "Y": float(r[1]), "Z": float(r[2])}
    rv = Rotation.from_matrix(R).as_rotvec()
    return IndependentModelResult(
        XYZ=Xo[:P],
        XYZ_std=np.where(seen[:P, None], std[:P], np.nan),
        projection_centres=Xo[P:],
        pc_std=std[P:],
        similarities=np.column_stack([s, rv, T]),
        models=mods,
        sigma0=sigma0,
        redundancy=int(red),
        iterations=res.iterations,
        seconds=res.seconds,
        converged=res.converged,
        pc_tie=pc_tie,
        check=check,
        data=data,
    )
