"""Quality-control plot of a detection (matplotlib, Agg backend, PNG).

Left: the scan's outline with every certificate mark at its measured (or predicted) pixel
position, its residual vector against the global film -> pixel model exaggerated, a scale bar
for the residuals, and the missing/rejected marks flagged; crosses measured across one bar only
ringed by a square, those whose position leans on their neighbours' prediction
(``Detection.from_neighbours``) by a diamond. Right: image chips of the worst
marks (largest residual) with the fitted centre.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softplot.marks import grid
from softplot.marks.result import Detection

__all__ = ["plot_qc", "geometry_text"]


def geometry_text(det: Detection) -> str:
    """One line on the crosses' size as measured on the scan (``det.mark_geometry``)."""
    g = det.mark_geometry or {}
    if not g:
        return ""
    sp = g.get("spread") or {}

    def v(key):
        x, s = g.get(key), sp.get(key)
        if x is None:
            return "?"
        return f"{x * 1000:.1f} um" + (f" +- {s * 1000:.1f}" if s is not None else "")

    src = {"scan": "measured on the scan", "fit": "arm chosen by the fits"}.get(
        g.get("source"), "certificate (not measured)")
    return (f"crosses: arm {v('arm_length_mm')}, line {v('line_width_mm')} "
            f"({src}, {g.get('n', 0)} bars)")


def _nice(v: float) -> float:
    """A round number (1, 2 or 5 times a power of ten) close to ``v``."""
    if not np.isfinite(v) or v <= 0:
        return 1.0
    e = np.floor(np.log10(v))
    m = v / 10**e
    return float((1 if m < 1.5 else 2 if m < 3.5 else 5) * 10**e)


def plot_qc(det: Detection, scan, path: str | Path, n_chips: int = 6, dpi: int = 110) -> Path:
    """Write the QC PNG of ``det`` (``scan`` supplies the image chips); returns the path."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    path = Path(path)
    H = np.array(det.transform["matrix"], float)
    pred = grid.apply_h(H, det.film)
    meas = det.measured
    pos = np.where(meas[:, None], det.xy, pred)
    res = det.residual
    mag = np.hypot(res[:, 0], res[:, 1])
    big = float(np.nanmax(mag)) if np.isfinite(mag).any() else 0.0
    span = max(det.width, det.height)
    bar = _nice(big if big > 0 else 0.1)
    exag = 0.08 * span / bar

    fig = plt.figure(figsize=(13, 7.5))
    gs = fig.add_gridspec(3, 5, width_ratios=[3, 3, 3, 1.6, 1.6])
    ax = fig.add_subplot(gs[:, :3])
    ax.add_patch(plt.Rectangle((-0.5, -0.5), det.width, det.height, fill=False, lw=0.8,
                               ec="0.5"))
    st = np.array(det.status)
    for status, colour, marker in (("measured", "tab:blue", "+"), ("rejected", "tab:red", "x"),
                                   ("missing", "0.6", "o")):
        m = st == status
        if m.any():
            # missing: a hollow ring (a colour given as ``c`` would fill it)
            paint = ({"facecolors": "none", "edgecolors": colour} if marker == "o"
                     else {"c": colour})
            ax.scatter(pos[m, 0], pos[m, 1], marker=marker, s=28 if status != "missing" else 18,
                       label=f"{status} ({int(m.sum())})", **paint)
    one = meas & (np.asarray(det.arms) == 1) if det.arms is not None else np.zeros_like(meas)
    if one.any():  # measured across one bar only: ringed
        ax.scatter(pos[one, 0], pos[one, 1], marker="s", s=60, facecolors="none",
                   edgecolors="tab:orange", label=f"one bar only ({int(one.sum())})")
    nb = (meas & np.asarray(det.from_neighbours, bool) if det.from_neighbours is not None
          else np.zeros_like(meas))
    if nb.any():  # positions that lean on the neighbours' prediction: diamond-ringed
        ax.scatter(pos[nb, 0], pos[nb, 1], marker="D", s=60, facecolors="none",
                   edgecolors="tab:purple", label=f"from neighbours ({int(nb.sum())})")
    ok = meas & np.isfinite(mag)
    if ok.any():
        ax.quiver(pos[ok, 0], pos[ok, 1], res[ok, 0] * exag, res[ok, 1] * exag, angles="xy",
                  scale_units="xy", scale=1.0, color="tab:green", width=0.002)
    # scale bar
    x0, y0 = 0.05 * det.width, 1.04 * det.height
    ax.plot([x0, x0 + bar * exag], [y0, y0], color="tab:green", lw=2)
    ax.text(x0, y0 + 0.02 * span, f"{bar:g} px residual", va="top", fontsize=8)
    ax.set_xlim(-0.05 * span, det.width + 0.05 * span)
    ax.set_ylim(det.height + 0.1 * span, -0.05 * span)
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{det.image}: {det.camera}, {det.polarity}, {det.dpi:.0f} dpi; "
                 f"rms {det.rms_px:.3f} px ({det.transform.get('kind', '')})"
                 + (f"\n{geometry_text(det)}" if det.mark_geometry else ""), fontsize=9)

    # chips of the worst marks (largest residual, then rejected ones)
    order = np.argsort(-np.nan_to_num(mag, nan=-1.0))
    chosen = [i for i in order if meas[i]][: max(0, n_chips - 2)]
    chosen += [i for i in np.where(st == "rejected")[0] if i not in chosen]
    chosen = chosen[:n_chips]
    half = int(max(12, 0.6 * _mark_extent_px(det)))
    for k, i in enumerate(chosen):
        axc = fig.add_subplot(gs[k % 3, 3 + k // 3])
        cx, cy = np.round(pos[i]).astype(int)
        ys = slice(max(cy - half, 0), min(cy + half + 1, det.height))
        xs = slice(max(cx - half, 0), min(cx + half + 1, det.width))
        empty = ys.stop <= ys.start or xs.stop <= xs.start
        chip = np.zeros((1, 1)) if empty else scan.grey((ys, xs))
        axc.imshow(chip, cmap="gray", extent=(xs.start - 0.5, xs.stop - 0.5, ys.stop - 0.5,
                                              ys.start - 0.5))
        axc.plot(pos[i, 0], pos[i, 1], "r+", ms=10)
        axc.set_title(f"{det.name[i]} {det.status[i]}\n|res| {mag[i]:.3f} px"
                      if np.isfinite(mag[i]) else f"{det.name[i]} {det.status[i]}", fontsize=7)
        axc.set_xticks([])
        axc.set_yticks([])
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _mark_extent_px(det: Detection) -> float:
    """Rough half-size of a mark in px (from neighbouring marks' spacing)."""
    ppm = det.dpi / 25.4
    if det.kind and det.kind[0] == "reseau" and len(det.film) > 1:
        d = np.diff(np.unique(det.film[:, 0]))
        return float(0.12 * (d.min() if d.size else 5.0) * ppm)
    return float(1.2 * ppm)
