"""``softplot detect``: measure the reseau crosses / fiducial marks of one or more scans."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from softplot.cli._detect_opts import detection_options
from softplot.cli._outputs import guard_outputs
from softplot.errors import SoftplotError


def _out_path(base: Path | None, stem: str, many: bool, suffix: str) -> Path | None:
    if base is None:
        return None
    if not many:
        return base
    return base.with_name(f"{base.stem}-{stem}{suffix}")


@click.command("detect")
@click.argument("scans", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--camera", required=True, help="Built-in camera name or certificate TOML.")
@click.option("--dpi", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Scan resolution (default: the file's, "
              "else estimated from the image).")
@detection_options
@click.option("--json", "json_out", type=click.Path(dir_okay=False), default=None,
              help="Write the result JSON here (one scan).")
@click.option("--out-dir", type=click.Path(file_okay=False), default=None,
              help="Write DIR/<scan stem>.json for every scan.")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="QC plot PNG (several scans: <name>-<scan stem>.png).")
@click.option("--micmac", type=click.Path(file_okay=False), default=None,
              help="Write MicMac MeasuresIm-<image>.xml into this folder.")
@click.option("--overwrite", is_flag=True, help="Replace existing result files.")
@click.pass_context
def command(ctx, scans, camera, dpi, polarity, rotate, mirror, grid_part, scene, json_out,
            out_dir, plot, micmac, overwrite):
    """Detect and measure the reseau crosses or fiducial marks of SCAN...

    Prints one summary line per scan; the result JSON (keys: image, camera, width,
    height, dpi, polarity, marks, transform, rms_px, warnings) goes to --json or --out-dir.
    A bad scan is reported in one line and the others are still processed (exit code 2).
    Existing result files are never replaced without --overwrite.
    """
    from softplot.camera import load_camera
    from softplot.io import fingerprint, load_scan
    from softplot.marks.micmac import micmac_name, write_measures_im
    from softplot.marks.qc import plot_qc
    from softplot.mirror import MIRROR_NOTE, detect_oriented, mirror_symmetric, side_json

    cam = load_camera(camera)
    many = len(scans) > 1
    if json_out and many:
        raise SoftplotError("--json takes one scan; use --out-dir DIR for several")
    inputs = {Path(s).resolve() for s in scans}
    # every file this run would write, checked (and its folder made) before any work is done
    targets = []
    for s in scans:
        p = Path(s)
        targets += [json_out and Path(json_out), out_dir and Path(out_dir) / f"{p.stem}.json",
                    _out_path(Path(plot) if plot else None, p.stem, many, ".png"),
                    micmac and Path(micmac) / micmac_name(p.name)]
    guard_outputs([t for t in targets if t], scans, overwrite)
    failed = 0
    iterator = scans
    if many and sys.stderr.isatty():
        from tqdm import tqdm

        iterator = tqdm(scans, desc="detect", unit="scan")
    for s in iterator:
        p = Path(s)
        try:
            sc = load_scan(p)
            det = detect_oriented(sc, cam, mirror=mirror, dpi=dpi, polarity=polarity,
                                  rotate=float(rotate), scene=scene, grid_part=grid_part)
            doc = det.to_json()
            doc["scan"] = fingerprint(p)  # the scan it was made on, checked where it is used
            doc.update(side_json(cam, mirror))
            if out_dir:
                d = Path(out_dir)
                d.mkdir(parents=True, exist_ok=True)
                target = d / f"{p.stem}.json"
                if target.resolve() in inputs:
                    raise SoftplotError(f"{target}: is an input scan; refusing to overwrite it")
                target.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
            if json_out:
                Path(json_out).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
            pp = _out_path(Path(plot) if plot else None, p.stem, many, ".png")
            if pp is not None:
                plot_qc(det, sc, pp)
            if micmac:
                write_measures_im(det, micmac)
            click.echo(det.summary())
            if mirror_symmetric(cam):
                given = "mirrored" if mirror else "not mirrored"
                click.echo(f"note: {MIRROR_NOTE} (given: {given})")
        except SoftplotError as exc:
            if not many:
                raise
            failed += 1
            click.echo(f"softplot: error: {exc}", err=True)
    if failed:
        click.echo(f"softplot: {failed} of {len(scans)} scans failed", err=True)
        ctx.exit(2)
