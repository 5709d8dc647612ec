"""Reports of a bundle: a calibration-certificate-like text, and plots (matplotlib Agg).

Units in the report: interior orientation in mm (distortion coefficients in their mm units),
residuals in micrometres (film) and pixels when the pixel size is known, angles in degrees or
gon, object coordinates in the object unit (m).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softplot.geometry.rotation import from_radians
from softplot.orientation.bundle import EO_NAMES, INTRINSICS, BundleResult

__all__ = ["text_report", "plot_residuals", "plot_histogram", "write_plots"]


def _n(v, w=8):
    return f"{'-':>{w}}" if v is None else f"{v:>{w}.2f}"


def _fmt(v, s, unit=""):
    if s == 0:
        return f"{v:>14.6g} {unit:<6} (fixed)"
    return f"{v:>14.6g} {unit:<6} +- {s:.3g}"


_UNITS = {
    "c": "mm",
    "x0": "mm",
    "y0": "mm",
    "k1": "mm^-2",
    "k2": "mm^-4",
    "k3": "mm^-6",
    "p1": "mm^-1",
    "p2": "mm^-1",
    "b1": "",
    "b2": "",
    "a": "",
}


def text_report(
    res: BundleResult,
    angle_unit: str = "deg",
    title: str = "Bundle adjustment",
    max_points: int = 30,
) -> str:
    """A plain-text report in the manner of a calibration certificate."""
    d = res.data
    L = []
    L.append(title)
    L.append("=" * len(title))
    L.append("")
    L.append(
        f"photos {len(d.photo_names)}, cameras {len(d.cameras)}, points {len(d.point_names)}, "
        f"image observations {d.obs_photo.size}"
    )
    L.append(f"datum: {res.datum}")
    L.append(
        f"observations (incl. weighted parameters) {res.n_observations}, unknowns "
        f"{res.n_unknowns}, redundancy {res.redundancy}"
    )
    L.append(
        f"sigma0 (a posteriori / a priori) = {res.sigma0:.4f}   "
        f"(variance factor {res.sigma0**2:.4f})"
    )
    rms = res.rms_image_um()
    L.append(
        f"RMS image residuals: x {rms['x']:.2f} um, y {rms['y']:.2f} um, total {rms['xy']:.2f} um"
    )
    px = res.rms_image_px()
    if px:
        L.append(
            f"                     x {px['x']:.3f} px, y {px['y']:.3f} px, total {px['xy']:.3f} px"
        )
    L.append(
        f"LM: {res.iterations} iterations, {res.seconds:.2f} s, cost {res.initial_cost:.6g} "
        f"-> {res.cost:.6g} ({res.message})"
    )
    L.append("")
    for c, cam in enumerate(d.cameras):
        L.append(f"Camera {cam.name} (lens model: {cam.model})")
        L.append("-" * (7 + len(cam.name)))
        for i, n in enumerate(INTRINSICS):
            L.append(f"  {n:<3} {_fmt(res.intrinsics[c, i], res.intrinsics_std[c, i], _UNITS[n])}")
        cor = res.intrinsics_corr[c]
        if cor["names"]:
            L.append("  correlation matrix:")
            L.append("        " + "".join(f"{n:>8}" for n in cor["names"]))
            for n, row in zip(cor["names"], cor["matrix"], strict=True):
                L.append(f"  {n:>5} " + "".join(f"{v:>8.3f}" for v in row))
            mx = res.correlation_eo_max[c]
            if mx:
                L.append("  largest correlation with an exterior orientation:")
                for n, e in mx.items():
                    L.append(f"    {n:<3} {e['corr']:+.3f} with {e['eo']} of {e['photo']}")
        L.append("")
    if res.warnings:
        L.append("Warnings")
        L.append("--------")
        L.extend(f"  ! {w}" for w in res.warnings)
        L.append("")
    au = {"deg": "deg", "gon": "gon", "rad": "rad"}[angle_unit]
    L.append(f"Exterior orientation (object units, {au})")
    L.append("-" * 40)
    hdr = f"  {'photo':<12}" + "".join(f"{n:>22}" for n in EO_NAMES)
    L.append(hdr)
    ang = from_radians(res.angles, angle_unit)
    angs = from_radians(res.eo_std[:, 3:], angle_unit)
    for f, n in enumerate(d.photo_names):
        vals = [*res.X0[f], *ang[f]]
        sds = [*res.eo_std[f, :3], *angs[f]]
        L.append(
            f"  {n:<12}"
            + "".join(
                f"{v:>13.4f} +-{s:<7.2g}" if np.isfinite(s) else f"{v:>13.4f}   {'-':<7}"
                for v, s in zip(vals, sds, strict=True)
            )
        )
    L.append("")
    L.append("Image residuals per photo (RMS; max |w|; flagged; sum of redundancy numbers)")
    L.append("-" * 76)
    L.append(
        f"  {'photo':<12} {'n':>5} {'x um':>8} {'y um':>8} {'xy um':>8} {'xy px':>8} "
        f"{'max|w|':>7} {'flag':>5} {'r':>8}"
    )
    for s in res.photo_statistics():
        px = "-" if s["rms_xy_px"] is None else f"{s['rms_xy_px']:.3f}"
        L.append(
            f"  {s['photo']:<12} {s['n']:>5} {_n(s['rms_x_um'])} {_n(s['rms_y_um'])} "
            f"{_n(s['rms_xy_um'])} {px:>8} {_n(s['max_abs_w'], 7)} {s['flagged']:>5} "
            f"{_n(s['redundancy'])}"
        )
    L.append("")
    std = res.XYZ_std
    L.append("Object points (std)")
    L.append("-------------------")
    L.append(
        f"  RMS std: X {np.sqrt(np.mean(std[:, 0] ** 2)):.4g}  Y "
        f"{np.sqrt(np.mean(std[:, 1] ** 2)):.4g}  Z {np.sqrt(np.mean(std[:, 2] ** 2)):.4g}"
    )
    for p in range(min(max_points, len(d.point_names))):
        L.append(
            f"  {d.point_names[p]:<10} "
            + "".join(
                f"{res.XYZ[p, a]:>14.4f} +-{std[p, a]:<8.2g}"
                if np.isfinite(std[p, a])
                else f"{res.XYZ[p, a]:>14.4f}   {'-':<8}"
                for a in range(3)
            )
        )
    if len(d.point_names) > max_points:
        L.append(f"  ... {len(d.point_names) - max_points} more in the JSON output")
    chk = res.check_rms()
    if chk:
        L.append("")
        L.append(
            f"Check points ({chk['n']}): RMS X {chk['X']:.4g}  Y {chk['Y']:.4g}  Z {chk['Z']:.4g}"
        )
    L.append("")
    if res.snooping_test == "pope-tau":
        L.append(
            f"Largest standardised residuals (w; image precision not stated: Pope's tau = "
            f"w / sigma0, critical |tau| > {res.critical:.2f})"
        )
    else:
        L.append(f"Largest standardised residuals (Baarda w, critical {res.critical:.2f})")
    L.append("-" * 60)
    for r in res.largest_residuals(10):
        wx = "nan" if r["wx"] is None else f"{r['wx']:+.2f}"
        wy = "nan" if r["wy"] is None else f"{r['wy']:+.2f}"
        L.append(
            f"  {r['photo']:<12} {r['point']:<10} vx {r['vx_um']:+8.2f} um  "
            f"vy {r['vy_um']:+8.2f} um  w {wx:>7} {wy:>7}"
            + ("   <-- flagged" if r["flagged"] else "")
        )
    L.append("")
    return "\n".join(L)


def plot_residuals(res: BundleResult, camera: int, path, scale: float | None = None):
    """Image-space residual vectors of all photos of one camera (film mm, x right, y up)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = res.data
    sel = d.photo_camera[d.obs_photo] == camera
    xy = d.xy[sel]
    v = res.residuals_mm[sel] * 1000.0
    if scale is None:
        span = max(np.ptp(xy[:, 0]) if xy.size else 1.0, 1e-9)
        vmax = np.percentile(np.hypot(v[:, 0], v[:, 1]), 95) if v.size else 1.0
        scale = 0.05 * span / max(vmax, 1e-12)  # mm of plot per um
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.quiver(
        xy[:, 0],
        xy[:, 1],
        v[:, 0] * scale,
        v[:, 1] * scale,
        angles="xy",
        scale_units="xy",
        scale=1.0,
        width=0.002,
        color="C0",
    )
    fl = res.flagged[sel]
    if fl.any():
        ax.plot(xy[fl, 0], xy[fl, 1], "o", mfc="none", mec="C3", label="flagged")
        ax.legend(loc="upper right")
    ref = 5.0
    ax.quiver(
        [0.05],
        [0.04],
        [ref * scale],
        [0],
        transform=ax.transAxes,
        angles="xy",
        scale_units="xy",
        scale=1.0,
        width=0.004,
        color="k",
    )
    ax.set_title(
        f"{d.cameras[camera].name}: image residuals (arrow scale: {1 / scale:.3g} um "
        f"per mm; black = {ref:g} um)"
    )
    ax.set_xlabel("x film [mm]")
    ax.set_ylabel("y film [mm]")
    ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_histogram(res: BundleResult, path):
    """Histogram of the image residuals (um) with the normal density of their RMS."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = res.residuals_mm.ravel() * 1000.0
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(v, bins=min(60, max(10, v.size // 20)), density=True, color="C0", alpha=0.7)
    s = float(np.sqrt(np.mean(v**2))) if v.size else 1.0
    t = np.linspace(-4 * s, 4 * s, 200)
    ax.plot(
        t,
        np.exp(-0.5 * (t / s) ** 2) / (s * np.sqrt(2 * np.pi)),
        "k-",
        label=f"normal, RMS {s:.2f} um",
    )
    ax.set_xlabel("image residual [um]")
    ax.set_ylabel("density")
    ax.legend()
    ax.set_title("Distribution of image residuals (x and y)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def write_plots(res: BundleResult, folder) -> list:
    """Residual vectors per camera and the histogram into ``folder`` (PNG); returns paths."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for c, cam in enumerate(res.data.cameras):
        safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in cam.name)
        paths.append(plot_residuals(res, c, out / f"residuals_{safe}.png"))
    paths.append(plot_histogram(res, out / "residual_histogram.png"))
    return paths
