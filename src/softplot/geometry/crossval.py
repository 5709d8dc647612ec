"""Cross-validation of the film-correction methods over the reference marks.

Which correction does this film need? Fit residuals cannot tell (a mesh interpolates its
crosses exactly), so every method is judged by how well it *predicts* crosses it was not
given:

* **leave-one-out** (LOO): for every measured cross, the model is rebuilt without it (for a
  mesh: its meshes are merged, see :mod:`softplot.geometry.mesh`) and the cross's film
  position is predicted from its measured pixel position;
* **checkerboard**: the crosses with even ``row + col`` predict the odd ones and vice versa
  (for fiducials: even and odd positions in the certificate's list); both halves pooled.

Check residual = predicted film - calibrated film, in micrometres. The table gives, per
method, the RMS of the residual vector lengths and the largest one.

Recommendation rule (``docs/correction.md``): among the methods with a LOO result, take the
best LOO RMS; recommend the *simplest* method whose LOO RMS is within 10 % + 0.25 um of it.
Simplicity order: raw-plate, raw-plate-affine, affine, projective, bilinear, poly2, poly3,
then the meshes with the camera's default mesh first. The margin keeps a simpler model
when the measured marks cannot tell the difference (a fuller model would only fit noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softplot.errors import SoftplotError
from softplot.geometry.mesh import MESH_KINDS, default_mesh_kind
from softplot.geometry.models import (
    GLOBAL_METHODS,
    ReferenceMarks,
    build_model,
)

__all__ = ["MethodScore", "CrossValidation", "cross_validate", "recommend", "SIMPLICITY"]

#: order of simplicity of the global methods (the meshes follow, camera default first)
SIMPLICITY = tuple(GLOBAL_METHODS)

#: recommendation tolerance: relative and absolute (micrometres)
REL_TOL = 0.10
ABS_TOL_UM = 0.25


@dataclass
class MethodScore:
    """Cross-validation of one method (micrometres; NaN / None when it could not run)."""

    method: str
    n_params: int | None = None
    fit_rms_um: float = float("nan")
    loo_rms_um: float = float("nan")
    loo_max_um: float = float("nan")
    loo_n: int = 0
    cb_rms_um: float = float("nan")
    cb_max_um: float = float("nan")
    cb_n: int = 0
    note: str = ""
    loo_residuals_um: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    loo_names: list = field(default_factory=list)

    def to_dict(self) -> dict:
        def num(v):
            return None if v is None or (isinstance(v, float) and not np.isfinite(v)) else v

        return {
            "method": self.method,
            "n_params": self.n_params,
            "fit_rms_um": num(self.fit_rms_um),
            "loo_rms_um": num(self.loo_rms_um),
            "loo_max_um": num(self.loo_max_um),
            "loo_n": self.loo_n,
            "checkerboard_rms_um": num(self.cb_rms_um),
            "checkerboard_max_um": num(self.cb_max_um),
            "checkerboard_n": self.cb_n,
            "note": self.note,
        }


@dataclass
class CrossValidation:
    """Scores of all methods and the recommendation."""

    scores: list[MethodScore]
    recommended: str | None
    best: str | None
    default_mesh: str | None
    n_marks: int

    def score(self, method: str) -> MethodScore:
        for s in self.scores:
            if s.method == method:
                return s
        raise KeyError(method)

    def to_dict(self) -> dict:
        return {
            "n_marks": self.n_marks,
            "recommended": self.recommended,
            "best_loo": self.best,
            "default_mesh": self.default_mesh,
            "rule": (
                f"simplest method with LOO RMS <= best * {1 + REL_TOL:.2f} + {ABS_TOL_UM} um; "
                "order: " + ", ".join(SIMPLICITY) + ", meshes (camera default first)"
            ),
            "methods": [s.to_dict() for s in self.scores],
        }

    def table(self) -> str:
        """A plain-text table, micrometres."""
        head = (
            f"{'method':<18} {'params':>6} {'fit rms':>8} {'LOO rms':>8} {'LOO max':>8} "
            f"{'chk rms':>8} {'chk max':>8}  note"
        )
        lines = [head, "-" * len(head)]

        def f(v):
            return f"{v:8.2f}" if np.isfinite(v) else f"{'-':>8}"

        for s in self.scores:
            mark = " *" if s.method == self.recommended else ""
            lines.append(
                f"{s.method:<18} {s.n_params if s.n_params is not None else '-':>6} "
                f"{f(s.fit_rms_um)} {f(s.loo_rms_um)} {f(s.loo_max_um)} "
                f"{f(s.cb_rms_um)} {f(s.cb_max_um)}  {s.note}{mark}"
            )
        lines.append("(micrometres on the film; fit = residuals at the marks used;")
        lines.append(" LOO = leave-one-out check residuals; chk = checkerboard split)")
        if self.recommended:
            lines.append(
                f"recommended: {self.recommended} (best LOO: {self.best}; rule: simplest "
                f"within {REL_TOL:.0%} + {ABS_TOL_UM} um of the best)"
            )
        return "\n".join(lines)


def _rms(v: np.ndarray) -> tuple[float, float]:
    if v.size == 0:
        return float("nan"), float("nan")
    d = np.hypot(v[:, 0], v[:, 1])
    return float(np.sqrt(np.mean(d**2))), float(d.max())


def _predict(method: str, marks: ReferenceMarks, names_out, film, pixel) -> np.ndarray:
    """Check residuals (um) of the marks ``names_out`` predicted without them."""
    model = build_model(method, marks.without(names_out), area=False)
    pred = model.pixel_to_film(pixel)[0]
    return (pred - film) * 1000.0


def cross_validate(marks: ReferenceMarks, methods=None) -> CrossValidation:
    """Leave-one-out and checkerboard cross-validation of ``methods`` (default: all).

    Parameters
    ----------
    marks : ReferenceMarks
        Calibrated film mm and measured pixel positions of the reference marks.
    methods : sequence of str, optional
        Method names; default every global method and, with a reseau, every mesh kind.

    Returns
    -------
    CrossValidation
        Scores in micrometres and the recommended method. Methods that cannot run (too few
        marks) carry the reason in ``note``.
    """
    film, pixel, names = marks.reference()
    n = len(names)
    if n < 3:
        raise SoftplotError(f"cross-validation needs at least 3 measured marks, got {n}")
    default_mesh = default_mesh_kind(*marks.grid_shape) if marks.has_grid else None
    if methods is None:
        methods = list(SIMPLICITY)
        if marks.has_grid:
            methods += [default_mesh] + [k for k in MESH_KINDS if k != default_mesh]
    # parity for the checkerboard split
    if marks.has_grid:
        parity = np.array([(int(s[1:].split("C")[0]) + int(s.split("C")[1])) % 2 for s in names])
    else:
        all_names = list(marks.fid_names)
        parity = np.array([all_names.index(s) % 2 for s in names])
    scores = []
    for m in methods:
        sc = MethodScore(m)
        try:
            full = build_model(m, marks, area=False)
        except SoftplotError as exc:
            sc.note = str(exc)
            scores.append(sc)
            continue
        sc.n_params = int(full.n_params)
        sc.fit_rms_um = _rms(np.asarray(full.residuals_um))[0]
        # leave-one-out
        res, used = [], []
        failed = 0
        for i in range(n):
            try:
                res.append(_predict(m, marks, [names[i]], film[i : i + 1], pixel[i : i + 1])[0])
                used.append(names[i])
            except SoftplotError:
                failed += 1
        if res:
            r = np.array(res)
            sc.loo_rms_um, sc.loo_max_um = _rms(r)
            sc.loo_n = len(res)
            sc.loo_residuals_um = r
            sc.loo_names = used
        if failed:
            sc.note = f"LOO impossible for {failed} marks"
        # checkerboard
        cb = []
        for p in (0, 1):
            out = parity == p
            if not out.any() or out.all():
                continue
            try:
                drop = [s for s, o in zip(names, out, strict=True) if o]
                cb.append(_predict(m, marks, drop, film[out], pixel[out]))
            except SoftplotError as exc:
                sc.note = (sc.note + "; " if sc.note else "") + f"checkerboard: {exc}"
        if cb:
            r = np.concatenate(cb)
            sc.cb_rms_um, sc.cb_max_um = _rms(r)
            sc.cb_n = r.shape[0]
        scores.append(sc)
    rec, best = recommend(scores, default_mesh)
    return CrossValidation(scores, rec, best, default_mesh, n)


def recommend(scores: list[MethodScore], default_mesh: str | None = None):
    """(recommended, best) method names by the rule of the module docstring."""
    ok = [s for s in scores if np.isfinite(s.loo_rms_um)]
    if not ok:
        return None, None
    best = min(ok, key=lambda s: s.loo_rms_um)
    limit = best.loo_rms_um * (1 + REL_TOL) + ABS_TOL_UM
    order = list(SIMPLICITY)
    meshes = [default_mesh] if default_mesh else []
    order += meshes + [k for k in MESH_KINDS if k not in meshes]
    rank = {m: i for i, m in enumerate(order)}
    for s in sorted(ok, key=lambda s: rank.get(s.method, len(rank))):
        if s.loo_rms_um <= limit:
            return s.method, best.method
    return best.method, best.method  # pragma: no cover - best always qualifies
