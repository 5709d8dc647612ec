"""The detection result: one entry per certificate mark, and its JSON form (docs/detection.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Detection", "STATUSES"]

#: possible mark statuses
STATUSES = ("measured", "missing", "rejected")


def _num(v, nd=4):
    if v is None:
        return None
    v = float(v)
    if not np.isfinite(v):
        return None
    return round(v, nd)


@dataclass
class Detection:
    """Marks measured on one scan (arrays over the certificate's marks, in certificate order:
    reseau crosses row-major from the top-left, then fiducials).

    Attributes
    ----------
    image : str
        Scan file name (or "<array>").
    camera : str
        Certificate name.
    width, height : int
        Scan size (px).
    dpi : float
        Scan resolution used (given, from the file, or estimated: see ``dpi_source``).
    polarity : str
        "positive" (dark marks on a bright background, a print) or "negative" (bright marks).
    kind : list of str
        "reseau" or "fiducial" per mark.
    name : list of str
        ``R<row>C<col>`` for crosses, the certificate's name for fiducials.
    row, col : (N,) int
        Reseau row/column (-1 for fiducials; null in JSON).
    film : (N, 2) float
        Certificate film coordinates (mm).
    xy : (N, 2) float
        Measured centres, pixel system (NaN when not measured).
    sigma : (N,) float
        Standard deviation of the centre (px) from the LSM covariance, ``sqrt((vx + vy)/2)``.
    sigma_xy : (N, 2) float
        Standard deviations in x and y (px).
    score : (N,) float
        Correlation of data and fitted model (0..1; NaN when not fitted).
    cnr : (N,) float
        Contrast-to-noise ratio of the fitted mark.
    status : list of str
        "measured", "missing" (not found: covered, cut by the scan edge, too weak) or
        "rejected" (found, but an outlier against the global model or failing a shape test).
    reason : list of str
        Why a mark is missing or rejected ("" when measured).
    transform : dict
        The global film mm -> pixel model fitted to the measured marks:
        ``{"kind": "projective", "matrix": 3x3, "rms_px": ..., "n": ...}``.
    rms_px : float
        RMS residual (px) of the measured marks against ``transform``.
    residual : (N, 2) float
        Measured minus model (px), NaN when not measured.
    warnings : list of str
    ids_ambiguous : bool
        The rows and columns could be others (a part of the grid that no edge of the format
        names, or whose edge a dark region hides): one of the warnings says so.
    scene : str
        The scene model under the crosses: "opening" (the grey opening's estimate) or "joint"
        (also estimated jointly with each cross, :mod:`softplot.marks.scene_tv`); fiducials
        always "opening".
    cov : (N, 2, 2) float or None
        Covariance of each centre (px^2, pixel system x, y), NaN when not measured: the
        2 x 2 matrix, not only its diagonal (an arm measured alone is precise across it only).
    mark_geometry : dict or None
        The reseau crosses' size as measured on the scan (film mm):
        ``{"arm_length_mm", "line_width_mm", "spread": {...}, "n", "source"}``
        (:class:`softplot.marks.geometry.MarkGeometry`); None for fiducial cameras.
    arms : (N,) int or None
        Reseau crosses: the bars a measured cross was measured with, 2 (a whole cross) or 1
        (only one bar visible: its position across the bar is measured, along it the
        position is the prediction and its variance in ``cov`` large); 0 where not measured.
    bar : (N, 2) float or None
        Crosses measured as a lone bar (``arms`` 1): the bar's unit vector (pixel system x,
        y), the direction along which ``cov`` holds the prediction's variance; NaN
        elsewhere.
    from_neighbours : (N,) bool or None
        Crosses whose own fit is flat along a direction (a road along an arm, a thin blurred
        arm): their position and ``cov`` combine the fit with their neighbours' prediction
        (:mod:`softplot.marks.neighbour_prior`), so their errors correlate with the
        neighbours'; one of the warnings counts them.
    variance_factor : float
        The factor (at least 1) by which the crosses' covariances were enlarged because their
        departures from their neighbours showed larger errors than the least-squares
        covariances (:mod:`softplot.marks.precision`); ``cov``, ``sigma`` and ``sigma_xy``
        include it.
    """

    image: str
    camera: str
    width: int
    height: int
    dpi: float
    polarity: str
    kind: list
    name: list
    row: np.ndarray
    col: np.ndarray
    film: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    sigma_xy: np.ndarray
    score: np.ndarray
    cnr: np.ndarray
    status: list
    reason: list
    transform: dict
    rms_px: float
    residual: np.ndarray
    warnings: list = field(default_factory=list)
    dpi_source: str = "given"
    timings: dict = field(default_factory=dict)
    scene: str = "opening"
    mark_geometry: dict | None = None
    cov: np.ndarray | None = None
    arms: np.ndarray | None = None
    variance_factor: float = 1.0
    ids_ambiguous: bool = False
    bar: np.ndarray | None = None
    from_neighbours: np.ndarray | None = None

    @property
    def measured(self) -> np.ndarray:
        """Boolean mask of the measured marks."""
        return np.array([s == "measured" for s in self.status], bool)

    def __len__(self) -> int:
        return len(self.name)

    def summary(self) -> str:
        """One line: counts by status, rms, polarity, dpi (and the joint scene model, if used)."""
        m = int(self.measured.sum())
        miss = sum(s == "missing" for s in self.status)
        rej = sum(s == "rejected" for s in self.status)
        return (f"{self.image}: {m}/{len(self)} marks measured, {miss} missing, {rej} rejected; "
                f"rms {self.rms_px:.3f} px against the {self.transform.get('kind', '?')} model; "
                f"{self.polarity}, {self.dpi:.1f} dpi ({self.dpi_source})"
                + ("; scene estimated jointly with the crosses" if self.scene == "joint" else "")
                + ("; names rest on --rotate" if any("rest on --rotate" in w
                                                    for w in self.warnings) else "")
                + ("; a faint grid: the crosses hold only together"
                   if any("too faint to hold one by one" in w for w in self.warnings) else ""))

    def to_json(self) -> dict:
        """The detection JSON document (docs/detection.md; a dict ready for ``json.dump``)."""
        marks = []
        for i in range(len(self)):
            ok = np.all(np.isfinite(self.xy[i]))
            marks.append({
                "kind": self.kind[i],
                "name": self.name[i],
                "row": int(self.row[i]) if self.row[i] >= 0 else None,
                "col": int(self.col[i]) if self.col[i] >= 0 else None,
                "x": _num(self.xy[i, 0], 5) if ok else None,
                "y": _num(self.xy[i, 1], 5) if ok else None,
                "sigma": _num(self.sigma[i], 5),
                "score": _num(self.score[i], 4),
                "status": self.status[i],
                "film_x": _num(self.film[i, 0], 6),
                "film_y": _num(self.film[i, 1], 6),
                "sigma_x": _num(self.sigma_xy[i, 0], 5),
                "sigma_y": _num(self.sigma_xy[i, 1], 5),
                "cov": (None if self.cov is None or not np.isfinite(self.cov[i]).all()
                        else [[_num(self.cov[i, 0, 0], 8), _num(self.cov[i, 0, 1], 8)],
                              [_num(self.cov[i, 1, 0], 8), _num(self.cov[i, 1, 1], 8)]]),
                "arms": (int(self.arms[i]) if self.arms is not None and ok
                         and self.status[i] == "measured" and self.arms[i] > 0 else None),
                "bar": (None if self.bar is None or not ok or self.status[i] != "measured"
                        or not np.isfinite(self.bar[i]).all()
                        else [_num(self.bar[i, 0], 6), _num(self.bar[i, 1], 6)]),
                "from_neighbours": bool(self.from_neighbours is not None and ok
                                        and self.status[i] == "measured"
                                        and self.from_neighbours[i]),
                "cnr": _num(self.cnr[i], 2),
                "residual_x": _num(self.residual[i, 0], 4),
                "residual_y": _num(self.residual[i, 1], 4),
                "reason": self.reason[i] or None,
            })
        return {
            "image": self.image,
            "camera": self.camera,
            "width": int(self.width),
            "height": int(self.height),
            "dpi": _num(self.dpi, 3),
            "dpi_source": self.dpi_source,
            "polarity": self.polarity,
            "scene": self.scene,
            "variance_factor": _num(self.variance_factor, 4),
            "marks": marks,
            "transform": self.transform,
            "rms_px": _num(self.rms_px, 5),
            "warnings": list(self.warnings),
            "ids_ambiguous": bool(self.ids_ambiguous),
            "counts": {s: sum(x == s for x in self.status) for s in STATUSES},
            **({"mark_geometry": self.mark_geometry} if self.mark_geometry else {}),
        }
