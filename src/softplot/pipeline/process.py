"""``softplot process``: detection, film correction and quality control of real scans.

:func:`process_scan` is one scan's whole job (and the task of :mod:`softplot.pipeline.batch`):

1. load the scan (:func:`softplot.io.load_scan`) and detect its reseau crosses / fiducials
   (:func:`softplot.marks.detect`);
2. cross-validate every film-correction method over the measured marks
   (:func:`softplot.correction.compare`: leave-one-out and checkerboard check residuals,
   micrometres on the film) and take the recommended one (or the one asked for);
3. quality control: flags for missing / rejected marks, the median mark precision and the
   correction's leave-one-out RMS over thresholds (:data:`QC_LIMITS`);
4. optionally write the film-flattened image (:func:`softplot.correction.write_resampled`);
5. write ``<out>/<stem>.json`` atomically, ending with ``"complete": true``.

Per-scan JSON keys: ``softplot`` ("process"), ``version``, ``scan`` (path), ``camera``,
``status`` ("done"), ``marks_total``, ``marks_measured``, ``marks_missing``,
``marks_rejected``, ``rms_px`` (detection residual RMS against the projective film -> pixel
model, px: film deformation included), ``mark_sigma_px`` (median precision of a measured
mark, px), ``method`` (the correction applied), ``recommended``, ``loo_rms_um`` and
``loo_max_um`` of that method, ``crossval`` (every method's scores, see
:meth:`softplot.geometry.crossval.CrossValidation.to_dict`), ``qc`` (``ok`` and a list of
``warnings``), ``worst`` (the marks with the largest residuals: name, x, y px, residual
px), ``detection`` (the detection JSON, docs/detection.md), ``flattened`` (paths or null),
``seconds``, ``complete``.

:func:`write_report` builds the one self-contained HTML report over the results of a run:
a summary table, then per scan the residual vectors of the marks, chips of the worst marks
cut from the scan, and the per-method correction comparison (table and chart).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from softplot import __version__
from softplot.errors import SoftplotError

__all__ = ["process_scan", "process_scans", "write_report", "QC_LIMITS", "load_results"]

#: quality-control limits: median precision of a measured mark (px), LOO RMS of the applied
#: correction (um on the film), share of the marks that must be measured. (``rms_px``, the
#: residual RMS against one projective film -> pixel model, holds the film deformation too:
#: it is reported, not judged.)
QC_LIMITS = {"mark_sigma_px": 0.1, "loo_rms_um": 5.0, "measured_share": 0.9}
N_WORST = 6
_SIGNATURE = b'{\n "softplot": "process"'


def _result_path(out_dir: Path, scan: Path) -> Path:
    return Path(out_dir) / f"{Path(scan).stem}.json"


def _check_output(scan: Path, out_dir: Path) -> Path:
    """The result path of ``scan``; refuse to clobber an input or a foreign file."""
    rp = _result_path(out_dir, scan)
    if rp.resolve() == Path(scan).resolve():
        raise SoftplotError(f"{scan}: the result {rp.name} would overwrite the scan itself")
    if rp.exists():
        raw = rp.read_bytes()
        try:
            prev = json.loads(raw)
            ours = isinstance(prev, dict) and prev.get("softplot") == "process"
        except ValueError:  # a torn file: ours if it starts as our results do
            ours = not raw.strip() or raw.startswith(_SIGNATURE)
        if not ours:
            raise SoftplotError(f"{rp}: exists and is not a softplot result; refusing to "
                                "overwrite it (choose another --out)")
    return rp


def process_scan(
    scan: str | Path,
    out_dir: str | Path,
    *,
    camera,
    method: str | None = None,
    flatten: bool = False,
    pixel_size_um: float | None = None,
    dpi: float | None = None,
    polarity: str = "auto",
    rotate: float = 0.0,
    scene: str = "auto",
    crossval_methods=None,
    mirror: bool = False,
    grid_part: str | None = None,
) -> dict:
    """Detect, correct and check one scan; write ``<out_dir>/<stem>.json`` atomically.

    Parameters
    ----------
    scan : str or Path
        The scan file.
    out_dir : str or Path
        Output folder (created).
    camera : Camera or str
        Certificate (built-in name, TOML path or Camera).
    method : str, optional
        Correction method to apply; default the cross-validation's recommendation.
    flatten : bool
        Also write the film-flattened TIFF ``<stem>.film.tif`` (+ JSON sidecar).
    pixel_size_um : float, optional
        Pixel size of the flattened image (default: the scan's).
    dpi : float, optional
        Scan resolution when the file does not say.
    polarity : {"auto", "positive", "negative"}
    rotate : float
        The photo is turned this much (degrees, counter-clockwise) in the scan.
    mirror : bool
        The scan is mirrored left-right (through the film base; :mod:`softplot.mirror`).
    scene : {"auto", "opening", "joint"}
        The scene estimate under each cross (see :func:`softplot.marks.detect`).
    grid_part : str, optional
        The part of the reseau the scan shows (``cols=A:B,rows=C:D``; see
        :func:`softplot.marks.detect`).
    crossval_methods : sequence of str, optional
        Methods to cross-validate (default: all of :data:`softplot.correction.METHODS`).

    Returns
    -------
    dict
        The result (what was written, without the bulky ``detection`` and ``crossval``).

    Raises
    ------
    SoftplotError
        Unreadable scan, failed detection, bad camera: the batch records it and goes on.
    """
    from softplot.camera import load_camera
    from softplot.correction import (
        METHODS,
        FilmCorrection,
        compare,
        default_pixel_size,
        marks_from_detection,
        resample,
        write_resampled,
    )
    from softplot.io import fingerprint, load_scan
    from softplot.mirror import detect_oriented, side_json
    from softplot.pipeline.batch import write_json_atomic

    t0 = time.perf_counter()
    scan = Path(scan)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rp = _check_output(scan, out_dir)
    cam = load_camera(camera)
    if method is not None and method not in METHODS:
        raise SoftplotError(f"unknown correction method {method!r} (one of {', '.join(METHODS)})")
    sc = load_scan(scan)
    det = detect_oriented(sc, cam, mirror=mirror, dpi=dpi, polarity=polarity, rotate=rotate,
                          scene=scene, grid_part=grid_part)
    dj = det.to_json()
    dj.update(side_json(cam, mirror))
    dj["image"] = str(scan)
    dj["scan"] = fingerprint(scan)  # the scan it was made on, checked where it is used
    marks = dj["marks"]
    counts = dj.get("counts", {})
    n_total = len(marks)
    n_meas = int(counts.get("measured", sum(m.get("status") == "measured" for m in marks)))
    ref = marks_from_detection(cam, dj)
    cv = compare(cam, ref, crossval_methods)
    applied = method or cv.recommended or "mesh"
    if applied == "mesh":  # the camera's default mesh, as the scores name it
        applied = cv.default_mesh or applied
    try:
        score = cv.score(applied)
        loo_rms, loo_max = score.loo_rms_um, score.loo_max_um
    except KeyError:
        loo_rms = loo_max = float("nan")

    # worst marks by residual against the detection's projective model
    meas = [m for m in marks if m.get("status") == "measured" and m.get("residual_x") is not None]
    res_len = np.array([np.hypot(m["residual_x"], m["residual_y"]) for m in meas])
    order = np.argsort(-res_len)[:N_WORST] if len(meas) else []
    worst = [{"name": meas[i]["name"], "x": meas[i]["x"], "y": meas[i]["y"],
              "residual_px": float(res_len[i])} for i in order]

    warnings = list(dj.get("warnings") or [])
    rms_px = dj.get("rms_px")
    if n_total and n_meas / n_total < QC_LIMITS["measured_share"]:
        warnings.append(f"only {n_meas}/{n_total} marks measured")
    sig = [m["sigma"] for m in meas if isinstance(m.get("sigma"), (int, float))]
    mark_sigma = float(np.median(sig)) if sig else None
    if mark_sigma is not None and mark_sigma > QC_LIMITS["mark_sigma_px"]:
        warnings.append(f"median mark precision {mark_sigma:.3f} px > "
                        f"{QC_LIMITS['mark_sigma_px']} px")
    if np.isfinite(loo_rms) and loo_rms > QC_LIMITS["loo_rms_um"]:
        warnings.append(f"{applied} LOO RMS {loo_rms:.2f} um > {QC_LIMITS['loo_rms_um']} um")

    flattened = None
    if flatten:
        fc = FilmCorrection(cam, ref, applied, (sc.width, sc.height))
        ps = (pixel_size_um / 1000.0 if pixel_size_um else default_pixel_size(fc, sc.dpi))
        img_path = out_dir / f"{scan.stem}.film.tif"
        for q in (img_path, img_path.with_name(img_path.name + ".json")):
            if q.exists():
                q.unlink()  # our own output of an earlier (possibly half-done) run
        rs = flatten_image(sc.data, fc, ps, resample)
        p, side = write_resampled(img_path, rs, {"scan": str(scan), "camera": cam.name})
        flattened = {"image": str(p), "sidecar": str(side), "pixel_size_mm": ps}

    def num(v):
        return None if v is None or not np.isfinite(v) else float(v)

    from softplot.pipeline.batch import settings_of

    result = {
        "softplot": "process",
        "version": __version__,
        "scan": str(scan),
        "camera": cam.name,
        "settings": settings_of({"camera": camera, "method": method, "flatten": flatten,
                                 "pixel_size_um": pixel_size_um, "dpi": dpi,
                                 "polarity": polarity, "rotate": float(rotate),
                                 "mirror": bool(mirror), "scene": scene,
                                 "grid_part": grid_part}),
        "status": "done",
        "width": sc.width,
        "height": sc.height,
        "dpi": sc.dpi,
        "marks_total": n_total,
        "marks_measured": n_meas,
        "marks_missing": int(counts.get("missing", 0)),
        "marks_rejected": int(counts.get("rejected", 0)),
        "rms_px": num(rms_px),
        "mark_sigma_px": mark_sigma,
        "method": applied,
        "recommended": cv.recommended,
        "loo_rms_um": num(loo_rms),
        "loo_max_um": num(loo_max),
        "correction_check": _correction_check(cv, applied),
        "certificate": {"name": cam.name, "source": cam.source or None,
                        "calibration": cam.calibration or None},
        "qc": {"ok": not warnings, "warnings": warnings, "limits": QC_LIMITS},
        "worst": worst,
        "flattened": flattened,
        "crossval": cv.to_dict(),
        "detection": dj,
    }
    result["seconds"] = time.perf_counter() - t0
    result["complete"] = True
    write_json_atomic(rp, result)
    stale = out_dir / f"{scan.stem}.error.json"
    if stale.exists():
        stale.unlink()
    return {k: v for k, v in result.items() if k not in ("detection", "crossval")}


def _correction_check(cv, method: str) -> dict:
    """The applied method's leave-one-out residuals at every mark (film um, x right, y up):
    the residual of each mark when the correction is fitted to all the others; what the
    report draws as the residuals after the correction."""
    try:
        sc = cv.score(method)
    except KeyError:
        return {"method": method, "names": [], "residual_um": []}
    r = np.asarray(sc.loo_residuals_um, float).reshape(-1, 2)
    return {"method": method, "kind": "leave-one-out", "names": list(sc.loo_names),
            "residual_um": [[round(float(a), 4), round(float(b), 4)] for a, b in r]}


#: global (smooth) correction methods: their film -> pixel maps are interpolated from a grid
SMOOTH_METHODS = ("raw-plate", "raw-plate-affine", "affine", "projective", "bilinear", "poly2",
                  "poly3")


def coarse_film_maps(correction, pixel_size_mm: float, step: int = 16):
    """Film -> pixel maps of a smooth (global) correction from every ``step``-th node.

    Same output as :func:`softplot.correction.film_maps` (float32 ``mapx``, ``mapy``: the scan
    pixel of every output pixel centre; film ``x_min``, ``y_max`` mm), but the correction's
    film -> pixel inverse (a Newton iteration per point for the polynomials) runs on a grid
    ``step`` output pixels apart and bicubic splines fill in the rest: a workaround for the
    per-pixel inverse, which takes tens of seconds for a poly3 over a full scan. For the
    smooth global models the interpolation error is far below 1e-3 px (test).
    """
    from scipy.interpolate import RectBivariateSpline

    w, h = correction.camera.format_mm
    nx = max(int(round(w / pixel_size_mm)), 1)
    ny = max(int(round(h / pixel_size_mm)), 1)
    x_min, y_max = -nx * pixel_size_mm / 2.0, ny * pixel_size_mm / 2.0
    jn = np.arange(0, nx - 1 + 4 * step, step)
    inn = np.arange(0, ny - 1 + 4 * step, step)
    jn = np.r_[jn[0] - 2 * step, jn]  # nodes beyond both ends: no end effects
    inn = np.r_[inn[0] - 2 * step, inn]
    gx, gy = np.meshgrid(x_min + (jn + 0.5) * pixel_size_mm, y_max - (inn + 0.5) * pixel_size_mm)
    px = correction.model.film_to_pixel(np.column_stack([gx.ravel(), gy.ravel()]))[0]
    maps = []
    for k in range(2):
        spl = RectBivariateSpline(inn, jn, px[:, k].reshape(len(inn), len(jn)))
        maps.append(spl(np.arange(ny), np.arange(nx)).astype(np.float32))
    return maps[0], maps[1], x_min, y_max


def flatten_image(data, correction, pixel_size_mm: float, resample):
    """Film-flattened image: :func:`softplot.correction.resample`, or for a smooth global
    method the same remap through :func:`coarse_film_maps` (fast)."""
    if correction.method not in SMOOTH_METHODS:
        return resample(data, correction, pixel_size_mm)
    import cv2

    from softplot.correction import Resampled

    mapx, mapy, x_min, y_max = coarse_film_maps(correction, pixel_size_mm)
    src = np.ascontiguousarray(data)
    out = cv2.remap(src, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0)
    if out.ndim == 2 and src.ndim == 3:
        out = out[..., None]
    return Resampled(out, float(pixel_size_mm), float(x_min), float(y_max), correction.method)


def process_scans(scans, out_dir, *, progress: bool = True, overwrite: bool = False,
                  **kwargs):
    """Process ``scans`` one after the other in this process (``softplot process``).

    An existing result (``<stem>.json``) is refused unless ``overwrite``, before any work.
    Every scan is attempted; failures are recorded (``<stem>.error.json`` and a "failed"
    row) and the rest go on. Writes ``summary.csv``. Returns a
    :class:`softplot.pipeline.batch.BatchReport`.
    """
    from tqdm import tqdm

    from softplot.pipeline.batch import BatchReport, run_one, write_summary

    out_dir = Path(out_dir)
    if not overwrite:
        for s in scans:
            rp = _result_path(out_dir, Path(s))
            if rp.exists():
                raise SoftplotError(f"{rp}: exists; refusing to overwrite (use --overwrite)")
    out_dir.mkdir(parents=True, exist_ok=True)
    report = BatchReport()
    t0 = time.perf_counter()
    for s in tqdm(list(scans), desc="process", unit="scan", disable=not progress):
        report.rows.append(run_one(process_scan, str(s), str(out_dir), kwargs))
    report.seconds = time.perf_counter() - t0
    write_summary(out_dir / "summary.csv", report.rows)
    return report


def load_results(out_dir, rows) -> list[dict]:
    """The complete per-scan results named by summary ``rows`` (failed ones as rows)."""
    out = []
    for r in rows:
        rp = _result_path(out_dir, Path(r["scan"]))
        if r["status"] in ("done", "skipped") and rp.exists():
            try:
                out.append(json.loads(rp.read_text(encoding="utf-8")))
                continue
            except (OSError, ValueError):
                pass
        out.append({"scan": r["scan"], "status": r["status"], "error": r.get("error")})
    return out


def _chips(scan_path: str, worst: list[dict], half: int = 12):
    """Grey chips (list of 2D arrays) around the worst marks, read through a window."""
    from softplot.io import load_scan

    sc = load_scan(scan_path)
    chips = []
    for w in worst:
        x, y = int(round(w["x"])), int(round(w["y"]))
        r0, r1 = max(0, y - half), min(sc.height, y + half + 1)
        c0, c1 = max(0, x - half), min(sc.width, x + half + 1)
        if r1 > r0 and c1 > c0:
            chips.append((w, sc.grey((slice(r0, r1), slice(c0, c1))), (x - c0, y - r0)))
    return chips


def _report_header(results: list[dict]) -> str:
    """The report's first line: version, date, inputs and certificates."""
    import datetime

    cams = sorted({(r.get("certificate") or {}).get("source") or r.get("camera") or "?"
                   for r in results if r.get("complete")})
    settings = next((r.get("settings") for r in results if r.get("settings")), None) or {}
    used = ", ".join(f"{k} {v}" for k, v in settings.items()
                     if k != "camera" and v is not None and v is not False)
    return (f"softplot {__version__}, "
            f"{datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}; "
            f"{len(results)} scan(s); certificate: {', '.join(cams) or '?'}"
            + (f"; settings: {used}" if used else ""))


def _qc_limits_text() -> str:
    return ("QC limits: median mark precision <= "
            f"{QC_LIMITS['mark_sigma_px']} px, leave-one-out RMS of the correction <= "
            f"{QC_LIMITS['loo_rms_um']} um on the film, at least "
            f"{100 * QC_LIMITS['measured_share']:.0f} % of the marks measured.")


def _scan_text(r: dict) -> str:
    """One paragraph naming each figure of a processed scan for what it is."""
    cert = (r.get("certificate") or {}).get("source") or r["camera"]
    sig = r.get("mark_sigma_px")
    return (
        f"{r['camera']} (certificate {cert}), {r['width']} x {r['height']} px, "
        f"{r['dpi'] or 0:.0f} dpi; marks: {r['marks_measured']} measured, "
        f"{r.get('marks_missing', 0)} missing, {r.get('marks_rejected', 0)} rejected of "
        f"{r['marks_total']}. Mark precision (median of each mark's standard deviation): "
        f"{sig if sig is not None else float('nan'):.4f} px. Residual RMS against one "
        f"projective film -> pixel model (film deformation and scanner error included, not a "
        f"precision): {r['rms_px'] or float('nan'):.4f} px. Correction {r['method']} "
        f"(recommended {r['recommended']}): leave-one-out RMS "
        f"{r['loo_rms_um'] or float('nan'):.2f} um, max {r['loo_max_um'] or float('nan'):.2f} "
        "um on the film.")


def _film_residual_axes(ax, r: dict) -> None:
    """The residuals after the chosen correction (leave-one-out, um) as vectors at the marks'
    certificate positions (film mm, x right, y up), a reference vector, and the missing and
    rejected marks drawn and named."""
    marks = {m["name"]: m for m in r["detection"]["marks"]}
    chk = r.get("correction_check") or {}
    names = [n for n in chk.get("names", []) if n in marks and marks[n].get("film_x") is not None]
    res = {n: v for n, v in zip(chk.get("names", []), chk.get("residual_um", []), strict=True)}
    allf = np.array([[m["film_x"], m["film_y"]] for m in marks.values()
                     if m.get("film_x") is not None], float).reshape(-1, 2)
    if len(allf):
        ax.plot(allf[:, 0], allf[:, 1], ".", color="0.75", ms=2)
    if names:
        xy = np.array([[marks[n]["film_x"], marks[n]["film_y"]] for n in names], float)
        d = np.array([res[n] for n in names], float)
        span = float(np.ptp(allf, axis=0).max()) if len(allf) else 1.0
        ref = float(10 ** np.floor(np.log10(max(np.percentile(np.hypot(*d.T), 90), 1e-3))))
        scale = 0.06 * span / max(np.abs(d).max(), 1e-9)  # mm per um
        q = ax.quiver(xy[:, 0], xy[:, 1], d[:, 0], d[:, 1], angles="xy", scale_units="xy",
                      scale=1 / scale, color="C3", width=0.003)
        ax.quiverkey(q, 0.86, -0.11, ref, f"{ref:g} um", labelpos="E", coordinates="axes")
    for status, mk, col in (("missing", "o", "C0"), ("rejected", "x", "C1")):
        bad = [m for m in marks.values() if m.get("status") == status
               and m.get("film_x") is not None]
        if bad:
            ax.plot([m["film_x"] for m in bad], [m["film_y"] for m in bad], mk, color=col,
                    mfc="none", ms=8, label=f"{status} ({len(bad)})")
            for m in bad:
                ax.annotate(m["name"], (m["film_x"], m["film_y"]), fontsize=6, color=col,
                            xytext=(3, 3), textcoords="offset points")
    if any(m.get("status") in ("missing", "rejected") for m in marks.values()):
        ax.legend(loc="lower right", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("film x mm")
    ax.set_ylabel("film y mm")
    ax.set_title(f"residuals after {chk.get('method', r.get('method'))} "
                 "(leave-one-out), um on the film", fontsize=9)


def write_report(path, results: list[dict], title: str = "softplot process",
                 max_detailed: int = 50) -> Path:
    """One self-contained HTML report over the per-scan ``results``.

    Version, date, inputs, certificates and QC limits; a summary table of every scan; for the
    first ``max_detailed`` done scans: the residuals after the chosen correction (leave-one-out,
    um at the marks' film positions) with the missing and rejected marks, chips of the worst
    marks, the per-method correction
    comparison (cross-validation table and chart, micrometres on the film).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from softplot.export.html import Report

    rep = Report(title)
    done = [r for r in results if r.get("complete")]
    failed = [r for r in results if not r.get("complete")]
    rep.paragraph(_report_header(results), None)
    rep.paragraph(f"{len(done)} scans processed, {len(failed)} failed.",
                  "ok" if not failed else "warn")
    rep.paragraph(_qc_limits_text())
    rep.heading("Summary")
    rows = []
    for r in results:
        if r.get("complete"):
            rows.append([Path(r["scan"]).name, "done", f"{r['marks_measured']}/{r['marks_total']}",
                         r.get("mark_sigma_px"), r.get("rms_px"), r.get("method"),
                         r.get("loo_rms_um"),
                         "ok" if r["qc"]["ok"] else "; ".join(r["qc"]["warnings"])])
        else:
            rows.append([Path(r["scan"]).name, r.get("status", "failed"), None, None, None, None,
                         None, r.get("error") or ""])
    rep.table(["scan", "status", "measured", "mark precision px (median)",
               "projective model residual RMS px", "correction", "LOO RMS um (film)",
               "QC / error"], rows)
    for r in done[:max_detailed]:
        name = Path(r["scan"]).name
        rep.heading(name)
        rep.paragraph(_scan_text(r))
        for w in r["qc"]["warnings"]:
            rep.paragraph(w, "warn")
        fig, axs = plt.subplots(1, 2, figsize=(11, 4.8))
        _film_residual_axes(axs[0], r)
        meths = [m for m in r["crossval"]["methods"] if m.get("loo_rms_um") is not None]
        if meths:
            names = [m["method"] for m in meths]
            axs[1].barh(names, [m["loo_rms_um"] for m in meths], color="C0", label="LOO RMS")
            axs[1].plot([m["loo_max_um"] for m in meths], names, "k|", ms=12, label="LOO max")
            axs[1].set_xlabel("um on the film")
            axs[1].legend(loc="lower right")
            axs[1].set_title("correction methods: leave-one-out check residuals")
        fig.tight_layout()
        rep.figure(fig)
        try:
            chips = _chips(r["scan"], r["worst"])
        except SoftplotError:
            chips = []
        if chips:
            fig, axs = plt.subplots(1, len(chips), figsize=(1.9 * len(chips), 2.2),
                                    squeeze=False)
            for ax, (w, g, (cx, cy)) in zip(axs[0], chips, strict=True):
                ax.imshow(g, cmap="gray", interpolation="nearest")
                ax.plot(cx + (w["x"] - round(w["x"])), cy + (w["y"] - round(w["y"])), "r+")
                ax.set_title(f"{w['name']}\n{w['residual_px']:.3f} px", fontsize=8)
                ax.axis("off")
            rep.figure(fig, "worst marks (largest residuals against the projective film -> pixel "
                            "model), red +: measured position")
        rep.table(["method", "params", "fit rms um", "LOO rms um", "LOO max um",
                   "checkerboard rms um", "note"],
                  [[m["method"], m.get("n_params"), m.get("fit_rms_um"), m.get("loo_rms_um"),
                    m.get("loo_max_um"), m.get("checkerboard_rms_um"), m.get("note", "")]
                   for m in r["crossval"]["methods"]])
    if len(done) > max_detailed:
        rep.paragraph(f"(details of the first {max_detailed} scans only; every scan has its "
                      "JSON result)")
    if failed:
        rep.heading("Failed scans")
        rep.table(["scan", "error"], [[r["scan"], r.get("error") or ""] for r in failed])
    return rep.write(path)
