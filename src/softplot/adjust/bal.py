"""Bundle Adjustment in the Large (BAL) problems on the sparse Schur LM engine.

BAL format (Agarwal et al., ECCV 2010): header ``num_cameras num_points num_observations``;
one line per observation ``camera point x y``; then 9 numbers per camera (Rodrigues rotation
r1 r2 r3, translation t1 t2 t3, focal f, radial k1 k2); then 3 numbers per point.

Camera model (BAL's own frames: world -> camera, camera looks along -z, image coordinates in
pixels relative to the image centre, y up): ``P = R X + t``, ``p = -P[:2] / P[2]``,
``predicted = f (1 + k1 |p|^2 + k2 |p|^4) p``; cost ``0.5 * sum |predicted - observed|^2``.

The rotation is updated on the manifold, ``R <- exp([d]x) R`` (the Rodrigues vector is
recomputed after every step), so its Jacobian is simply ``-[R X]x``; the cost function is
BAL's, only the parametrisation of the increments differs from Ceres's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from softplot.adjust.sparse_bundle import (
    Evaluation,
    LMOptions,
    LMResult,
    SchurStructure,
    levenberg_marquardt,
)
from softplot.errors import SoftplotError

__all__ = ["BALProblem", "BALModel", "read_bal", "solve_bal", "BALResult"]


@dataclass
class BALProblem:
    """A BAL problem: observations (pixels, BAL image frame), cameras (C, 9), points (P, 3)."""

    cam_index: np.ndarray  # (m,) int
    point_index: np.ndarray  # (m,) int
    xy: np.ndarray  # (m, 2) observed image coordinates
    cameras: np.ndarray  # (C, 9): rodrigues(3), t(3), f, k1, k2
    points: np.ndarray  # (P, 3) world
    path: str = ""

    @property
    def n_cameras(self) -> int:
        return int(self.cameras.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_observations(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, cameras) -> "BALProblem":
        """The sub-problem seen by the given camera indices (points re-numbered)."""
        cams = np.asarray(sorted(set(int(c) for c in cameras)))
        cmap = -np.ones(self.n_cameras, np.int64)
        cmap[cams] = np.arange(cams.size)
        keep = cmap[self.cam_index] >= 0
        pts = np.unique(self.point_index[keep])
        pmap = -np.ones(self.n_points, np.int64)
        pmap[pts] = np.arange(pts.size)
        return BALProblem(
            cam_index=cmap[self.cam_index[keep]],
            point_index=pmap[self.point_index[keep]],
            xy=self.xy[keep].copy(),
            cameras=self.cameras[cams].copy(),
            points=self.points[pts].copy(),
            path=self.path,
        )


def read_bal(path: str | Path) -> BALProblem:
    """Read a BAL text file; raise :class:`SoftplotError` naming what is wrong."""
    p = Path(path)
    if not p.is_file():
        raise SoftplotError(f"BAL file not found: {p}")
    try:
        tokens = p.read_text().split()
    except (OSError, UnicodeDecodeError) as exc:
        raise SoftplotError(f"cannot read BAL file {p}: {exc}") from exc
    if len(tokens) < 3:
        raise SoftplotError(f"{p}: missing header 'num_cameras num_points num_observations'")
    try:
        nc, npt, no = (int(t) for t in tokens[:3])
    except ValueError as exc:
        raise SoftplotError(f"{p}: header must be three integers") from exc
    if min(nc, npt, no) <= 0:
        raise SoftplotError(f"{p}: header counts must be positive")
    need = 3 + 4 * no + 9 * nc + 3 * npt
    if len(tokens) != need:
        raise SoftplotError(
            f"{p}: expected {need} numbers for {nc} cameras, {npt} points, {no} observations, "
            f"found {len(tokens)}"
        )
    try:
        vals = np.array(tokens[3:], dtype=float)
    except ValueError as exc:
        raise SoftplotError(f"{p}: non-numeric value ({exc})") from exc
    obs = vals[: 4 * no].reshape(no, 4)
    cams = vals[4 * no : 4 * no + 9 * nc].reshape(nc, 9)
    pts = vals[4 * no + 9 * nc :].reshape(npt, 3)
    ci = obs[:, 0].astype(np.int64)
    pi = obs[:, 1].astype(np.int64)
    if ci.min() < 0 or ci.max() >= nc or pi.min() < 0 or pi.max() >= npt:
        raise SoftplotError(f"{p}: an observation refers to a camera or point out of range")
    if not np.all(np.isfinite(vals)):
        raise SoftplotError(f"{p}: non-finite value")
    return BALProblem(ci, pi, obs[:, 2:4].copy(), cams, pts, str(p))


class BALModel:
    """BAL camera model for :func:`softplot.adjust.sparse_bundle.levenberg_marquardt`.

    State: ``(cameras (C, 9), points (P, 3))``. Camera-side unknowns per camera: rotation
    increment (3, manifold), translation (3), f, k1, k2.
    """

    def __init__(self, problem: BALProblem, dense_limit: int = 4000) -> None:
        self.problem = problem
        C = problem.n_cameras
        self.structure = SchurStructure(
            n_cam=9 * C,
            n_pts=problem.n_points,
            group_params=np.arange(9 * C).reshape(C, 9),
            obs_group=problem.cam_index,
            obs_point=problem.point_index,
            d=2,
            dense_limit=dense_limit,
        )

    def evaluate(self, state, jacobian: bool) -> Evaluation:
        cams, pts = state
        pr = self.problem
        R = Rotation.from_rotvec(cams[:, :3]).as_matrix()  # (C,3,3)
        ci, pi = pr.cam_index, pr.point_index
        X = pts[pi]
        Rc = R[ci]
        Q = np.einsum("mij,mj->mi", Rc, X)
        P = Q + cams[ci, 3:6]
        z = P[:, 2]
        p = -P[:, :2] / z[:, None]
        r2 = np.einsum("mi,mi->m", p, p)
        f, k1, k2 = cams[ci, 6], cams[ci, 7], cams[ci, 8]
        s = 1.0 + r2 * (k1 + k2 * r2)
        pred = (f * s)[:, None] * p
        r = pred - pr.xy
        if not jacobian:
            return Evaluation(r)
        m = r.shape[0]
        # d pred / d p  (m,2,2)
        a = 2.0 * f * (k1 + 2.0 * k2 * r2)
        Dp = a[:, None, None] * p[:, :, None] * p[:, None, :]
        Dp[:, 0, 0] += f * s
        Dp[:, 1, 1] += f * s
        # d p / d P  (m,2,3)
        iz = 1.0 / z
        dpdP = np.zeros((m, 2, 3))
        dpdP[:, 0, 0] = -iz
        dpdP[:, 1, 1] = -iz
        dpdP[:, 0, 2] = P[:, 0] * iz * iz
        dpdP[:, 1, 2] = P[:, 1] * iz * iz
        A = np.matmul(Dp, dpdP)  # d pred / d P
        Jc = np.empty((m, 2, 9))
        # rotation: dP/dd = -[Q]x
        Jc[:, :, 0] = A[:, :, 2] * Q[:, 1, None] - A[:, :, 1] * Q[:, 2, None]
        Jc[:, :, 1] = A[:, :, 0] * Q[:, 2, None] - A[:, :, 2] * Q[:, 0, None]
        Jc[:, :, 2] = A[:, :, 1] * Q[:, 0, None] - A[:, :, 0] * Q[:, 1, None]
        Jc[:, :, 3:6] = A
        Jc[:, :, 6] = s[:, None] * p
        Jc[:, :, 7] = (f * r2)[:, None] * p
        Jc[:, :, 8] = (f * r2 * r2)[:, None] * p
        Jp = np.matmul(A, Rc)
        return Evaluation(r, Jc, Jp)

    def retract(self, state, d_cam, d_pts):
        cams, pts = state
        d = d_cam.reshape(-1, 9)
        new = cams + d
        rot = Rotation.from_rotvec(d[:, :3]) * Rotation.from_rotvec(cams[:, :3])
        new[:, :3] = rot.as_rotvec()
        return new, pts + d_pts


@dataclass
class BALResult:
    """Outcome of :func:`solve_bal`; costs are ``0.5 * sum r^2`` in pixel^2."""

    initial_cost: float
    final_cost: float
    iterations: int
    seconds: float
    converged: bool
    message: str
    n_cameras: int
    n_points: int
    n_observations: int
    rms_px: float
    cameras: np.ndarray
    points: np.ndarray
    history: list = field(default_factory=list)

    def to_json(self) -> dict:
        """JSON-ready summary (no arrays)."""
        return {
            "initial_cost": self.initial_cost,
            "final_cost": self.final_cost,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "converged": self.converged,
            "message": self.message,
            "cameras": self.n_cameras,
            "points": self.n_points,
            "observations": self.n_observations,
            "rms_px": self.rms_px,
            "history": [
                {
                    k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                    for k, v in h.items()
                }
                for h in self.history
            ],
        }


def solve_bal(problem: BALProblem, options: LMOptions | None = None) -> BALResult:
    """Adjust a BAL problem from its given start (timing covers the whole solve).

    Parameters
    ----------
    problem : BALProblem
    options : LMOptions, optional
        LM settings; the defaults are Ceres's.

    Returns
    -------
    BALResult
    """
    t0 = time.perf_counter()
    model = BALModel(problem)
    start = (problem.cameras.copy(), problem.points.copy())
    res: LMResult = levenberg_marquardt(model, start, options)
    seconds = time.perf_counter() - t0
    cams, pts = res.state
    return BALResult(
        initial_cost=res.initial_cost,
        final_cost=res.cost,
        iterations=res.iterations,
        seconds=seconds,
        converged=res.converged,
        message=res.message,
        n_cameras=problem.n_cameras,
        n_points=problem.n_points,
        n_observations=problem.n_observations,
        rms_px=float(np.sqrt(2.0 * res.cost / problem.n_observations)),
        cameras=cams,
        points=pts,
        history=res.history,
    )
