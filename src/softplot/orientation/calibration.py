"""Test-field calibration (Preuss): interior orientation from photos of known targets.

The test field's target coordinates are control with their standard errors (weighted, or
fixed with sigma 0); the photos' exterior orientations and the camera's interior orientation
(any subset of ``c, x0, y0, k1, k2, k3, p1, p2, b1, b2, a``; the others held at their certificate
values - "arbitrary unknowns held constant") are adjusted by the bundle
(:func:`softplot.orientation.bundle.bundle_adjust`).

*Series mode* calibrates every series of photos (one plate loading, one day) separately and
reports the repeatability of the interior orientation as the paper's tables do: per series
``x0, y0, c`` with their standard deviations, and over the series their mean and (sample)
standard deviation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from softplot.errors import SoftplotError
from softplot.orientation.bundle import (
    INTRINSICS,
    BundleData,
    BundleOptions,
    BundleResult,
    bundle_adjust,
)
from softplot.orientation.bundle_init import initialize

__all__ = ["DEFAULT_FREE", "calibrate", "calibrate_series", "SeriesResult", "subset_photos"]

#: parameters a test-field calibration estimates by default
DEFAULT_FREE = ("c", "x0", "y0", "k1", "k2", "p1", "p2")


def subset_photos(data: BundleData, keep) -> BundleData:
    """The part of ``data`` seen by the photos ``keep`` (bool (F,) or indices); points kept."""
    F = len(data.photo_names)
    mask = np.zeros(F, bool)
    mask[np.asarray(keep)] = True
    fmap = -np.ones(F, np.int64)
    fmap[mask] = np.arange(mask.sum())
    o = mask[data.obs_photo]
    pts = np.unique(data.obs_point[o])
    pmap = -np.ones(len(data.point_names), np.int64)
    pmap[pts] = np.arange(pts.size)
    return BundleData(
        cameras=[
            dataclasses.replace(c, values=c.values.copy(), sigma=c.sigma.copy())
            for c in data.cameras
        ],
        photo_names=[n for n, k in zip(data.photo_names, mask, strict=True) if k],
        photo_camera=data.photo_camera[mask],
        X0=data.X0[mask].copy(),
        angles=data.angles[mask].copy(),
        point_names=[data.point_names[p] for p in pts],
        XYZ=data.XYZ[pts].copy(),
        control=data.control[pts].copy(),
        control_sigma=data.control_sigma[pts].copy(),
        obs_photo=fmap[data.obs_photo[o]],
        obs_point=pmap[data.obs_point[o]],
        xy=data.xy[o].copy(),
        sigma_xy=data.sigma_xy[o].copy(),
        cov_xy=None if data.cov_xy is None else data.cov_xy[o].copy(),
        precision_given=data.precision_given,
        photo_fixed=data.photo_fixed[mask].copy(),
        check=data.check[pts].copy(),
        series=None
        if data.series is None
        else [s for s, k in zip(data.series, mask, strict=True) if k],
    )


def _prepare(data: BundleData, free) -> BundleData:
    if free is not None:
        for c in data.cameras:
            for i, n in enumerate(INTRINSICS):
                if n in free:
                    c.sigma[i] = np.inf
                elif np.isinf(c.sigma[i]):
                    c.sigma[i] = 0.0
            c.choose_model()
    if not data.control_used.any():
        raise SoftplotError("calibration needs the test field's target coordinates (control)")
    need = not (
        np.all(np.isfinite(data.X0))
        and np.all(np.isfinite(data.angles))
        and np.all(np.isfinite(data.XYZ))
    )
    if need:
        initialize(data)
    return data


def calibrate(
    data: BundleData, free=DEFAULT_FREE, options: BundleOptions | None = None
) -> BundleResult:
    """Calibrate on a test field: ``free`` parameters estimated (None: as the data says)."""
    opt = options or BundleOptions(datum="control")
    return bundle_adjust(_prepare(data, free), opt)


@dataclass
class SeriesResult:
    """Repeatability of the interior orientation over series (mm)."""

    labels: list
    results: list  # BundleResult per series
    names: tuple = ("x0", "y0", "c")

    def table(self) -> np.ndarray:
        """(n_series, 3, 2): value and std of x0, y0, c per series."""
        idx = [INTRINSICS.index(n) for n in self.names]
        return np.array(
            [[[r.intrinsics[0, i], r.intrinsics_std[0, i]] for i in idx] for r in self.results]
        )

    def mean(self) -> np.ndarray:
        return self.table()[:, :, 0].mean(axis=0)

    def std(self) -> np.ndarray:
        """Sample standard deviation over the series (the repeatability)."""
        t = self.table()[:, :, 0]
        return t.std(axis=0, ddof=1) if len(t) > 1 else np.full(t.shape[1], np.nan)

    def to_json(self) -> dict:
        t = self.table()
        return {
            "series": [
                {
                    "label": lab,
                    "sigma0": r.sigma0,
                    "rms_image_um": r.rms_image_um(),
                    **{
                        n: {"value": float(t[s, j, 0]), "std": float(t[s, j, 1])}
                        for j, n in enumerate(self.names)
                    },
                }
                for s, (lab, r) in enumerate(zip(self.labels, self.results, strict=True))
            ],
            "mean": {n: float(v) for n, v in zip(self.names, self.mean(), strict=True)},
            "repeatability_std": {n: float(v) for n, v in zip(self.names, self.std(), strict=True)},
            "unit": "mm",
        }

    def text(self) -> str:
        t = self.table() * 1000.0
        L = [
            "Repeatability of the interior orientation (um; values relative to the mean)",
            f"  {'series':<10}{'dx0':>9}{'dy0':>9}{'dc':>9}{'mx0':>8}{'my0':>8}{'mc':>8}"
            f"{'sigma0':>8}",
        ]
        m = t[:, :, 0].mean(axis=0)
        for s, lab in enumerate(self.labels):
            d = t[s, :, 0] - m
            L.append(
                f"  {lab:<10}{d[0]:>+9.1f}{d[1]:>+9.1f}{d[2]:>+9.1f}"
                f"{t[s, 0, 1]:>8.1f}{t[s, 1, 1]:>8.1f}{t[s, 2, 1]:>8.1f}"
                f"{self.results[s].sigma0:>8.3f}"
            )
        sd = self.std() * 1000.0
        mm = self.mean()
        L.append(f"  mean: x0 {mm[0]:+.4f} mm, y0 {mm[1]:+.4f} mm, c {mm[2]:.4f} mm")
        L.append(
            f"  repeatability (std over {len(self.labels)} series): "
            f"mx0 = +-{sd[0]:.1f} um, my0 = +-{sd[1]:.1f} um, mc = +-{sd[2]:.1f} um"
        )
        return "\n".join(L)


def calibrate_series(
    data: BundleData, series=None, free=DEFAULT_FREE, options: BundleOptions | None = None
) -> SeriesResult:
    """Calibrate every series separately (labels from ``series`` or ``data.series``)."""
    labels = series if series is not None else data.series
    if labels is None or len(labels) != len(data.photo_names) or not all(labels):
        raise SoftplotError("series mode needs a series label for every photo")
    uniq = list(dict.fromkeys(labels))
    if len(uniq) < 2:
        raise SoftplotError("series mode needs at least two series")
    results = []
    for lab in uniq:
        keep = np.array([s == lab for s in labels])
        results.append(calibrate(subset_photos(data, keep), free, options))
    return SeriesResult(uniq, results)
