"""``softplot match``: automatic tie points between the two scans of a stereo pair."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.errors import SoftplotError


def load_pair(left, right, camera, detection_left=None, detection_right=None, method="mesh"):
    """(scans, maps): both scans and their film corrections (marks detected when no
    detection is given). Errors (missing scan, wrong camera, ...) are one line."""
    from softplot.camera import load_camera
    from softplot.io import load_scan
    from softplot.pipeline.session import scan_photo_map

    cam = load_camera(camera)
    scans, maps = [], []
    for side, path, det in (("left", left, detection_left), ("right", right, detection_right)):
        scan = load_scan(path)
        try:
            m = scan_photo_map(path, cam, det, method=method)
        except SoftplotError as exc:
            raise SoftplotError(f"{side} scan {path}: {exc} (is {cam.name} its camera?)") from None
        if m.correction.image_size is None:
            m.correction.image_size = (scan.width, scan.height)
        scans.append(scan)
        maps.append(m)
    return cam, scans, maps


def match_options(f):
    for opt in reversed([
        click.option("--max-ties", type=click.IntRange(1), default=600, show_default=True,
                     help="Ties refined by least-squares matching (spread over the overlap)."),
        click.option("--min-corr", type=click.FloatRange(0, 1), default=0.8, show_default=True,
                     help="Least correlation coefficient of a least-squares match."),
    ]):
        f = opt(f)
    return f


@click.command("match")
@click.argument("scans", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--camera", required=True, help="Camera: built-in name or certificate (TOML).")
@click.option("--detection-left", type=click.Path(path_type=Path),
              help="Marks of the left scan (softplot detect JSON); detected when omitted.")
@click.option("--detection-right", type=click.Path(path_type=Path),
              help="Marks of the right scan (softplot detect JSON); detected when omitted.")
@click.option("--detection", "detections", multiple=True, type=click.Path(path_type=Path),
              help="A block: the marks of each scan (softplot detect JSON), one per scan in "
              "the order of the scans; detected once per scan when omitted.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Output folder: left.csv, right.csv, ties.csv, match.json (a pair); a "
              "bundle project (a block).")
@match_options
@click.option("--block", "as_block", is_flag=True,
              help="Two scans as a block too (a bundle project); three or more always are.")
@click.option("--workers", type=click.IntRange(0), default=2, show_default=True,
              help="A block: worker processes matching the pairs (dask.distributed; 0: in "
              "this process).")
@click.option("--scheduler", help="A block: address of an existing dask scheduler "
              "(tcp://host:8786) instead of local workers.")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run.")
def command(scans, camera, detection_left, detection_right, detections, out, max_ties,
            min_corr, as_block, workers, scheduler, overwrite) -> None:
    """Tie points of a stereo pair (two scans) or a block (more: a bundle project).

    A pair: SIFT in the film-corrected images (ratio test, mutual check), five-point RANSAC
    on photo coordinates, least-squares matching in the scans (to a fraction of a pixel, with
    the standard deviation of every match), then the least-squares relative orientation with
    data snooping. Writes OUT/left.csv and OUT/right.csv (name,x,y scan pixels, the same
    names in the same order: what softplot correct --points takes), OUT/ties.csv (both
    positions, precision sx_px, sy_px, correlation, residual y-parallax py_px) and
    OUT/match.json (n, sigma0, rms_px - the residual y-parallax in pixels -, the ties in the
    six Gruber areas, the relative orientation).

    A block (three or more scans, or --block): every pair matched as above on dask
    workers (pairs that do not overlap are skipped), the ties linked into multi-ray points
    and measured from one template each; OUT becomes a bundle project (cameras.toml,
    photos.csv, observations.csv in film mm with their precision) for softplot bundle OUT,
    with OUT/block.json and each pair's ties in OUT/pairs/. See docs/matching.md.
    """
    from softplot.matching.ties import MatchOptions, check_outputs, match_pair

    if len(scans) < 2:
        raise SoftplotError(f"give two scans (a pair) or more (a block), got {len(scans)}")
    from softplot.io import check_scan_path

    for s in scans:  # a missing scan is refused before any matching starts
        check_scan_path(s)
    opts = MatchOptions(max_ties=max_ties, min_corr=min_corr)
    if len(scans) > 2 or as_block:
        from softplot.matching.block import match_block

        if detection_left or detection_right:
            raise SoftplotError("a block takes --detection once per scan, not "
                                "--detection-left/--detection-right")
        bar = _bar(len(scans) * (len(scans) - 1) // 2)
        try:
            summary = match_block(scans, camera, out, list(detections) or None, options=opts,
                                  workers=workers, scheduler=scheduler, overwrite=overwrite,
                                  progress=bar)
        finally:
            bar.close()
        done = [p for p in summary["pairs"] if p["status"] == "done"]
        rays = ", ".join(f"{v} with {k} rays" for k, v in summary["points_by_rays"].items())
        click.echo(f"{len(done)} of {len(summary['pairs'])} pairs overlap; "
                   f"{summary['points']} points ({rays}), {summary['observations']} "
                   "observations")
        click.echo(f"wrote the bundle project {out} (next: softplot bundle {out})")
        return
    if detections:
        raise SoftplotError("a pair takes --detection-left and --detection-right")
    left, right = scans
    names = ("left.csv", "right.csv", "ties.csv", "match.json")
    if out.exists() and not out.is_dir():
        raise SoftplotError(f"{out}: exists and is not a folder")
    check_outputs([out / n for n in names], overwrite)
    cam, scans, maps = load_pair(left, right, camera, detection_left, detection_right)
    res = match_pair(scans[0], scans[1], maps[0], maps[1], opts)
    res.write(out, overwrite=overwrite)
    g = res.gruber
    click.echo(
        f"{res.n} ties, sigma0 {res.ro.sigma0 * 1000:.2f} um, residual y-parallax RMS "
        f"{res.rms_px:.3f} px; Gruber areas {'/'.join(map(str, g))}"
        + ("" if min(g) > 0 else " (some Gruber areas empty)")
    )
    click.echo(f"wrote {out}")


def _bar(total: int):
    """A progress callback (done, total) drawing a tqdm bar on stderr; ``.close()``."""
    from tqdm import tqdm

    t = tqdm(total=total, unit="pair", desc="match", file=None, leave=False)

    def cb(done, _total):
        t.n = done
        t.refresh()

    cb.close = t.close
    return cb


def auto_photo_ties(scans, camera, ties_dir=None):
    """``softplot relor --auto``: match the two scans and write the ties as photo mm CSVs.

    Returns the (left, right) CSV paths (name,x,y photo mm) in ``ties_dir`` (a temporary
    folder, removed at exit, when None); the pixel ties (softplot match outputs) are kept
    there too.
    """
    import atexit
    import shutil
    import tempfile

    from softplot.matching.ties import _write_csv, check_outputs, match_pair

    if len(scans) != 2:
        raise SoftplotError(f"--auto needs the two scans LEFT RIGHT, got {len(scans)}")
    if camera is None:
        raise SoftplotError("--auto needs --camera (the film correction uses its marks)")
    if ties_dir is None:
        ties_dir = Path(tempfile.mkdtemp(prefix="softplot-ties-"))
        atexit.register(shutil.rmtree, ties_dir, True)
    ties_dir = Path(ties_dir)
    names = ("left.csv", "right.csv", "ties.csv", "match.json", "left-photo.csv",
             "right-photo.csv")
    check_outputs([ties_dir / n for n in names], False)
    cam, sc, maps = load_pair(scans[0], scans[1], camera)
    res = match_pair(sc[0], sc[1], maps[0], maps[1])
    res.write(ties_dir)
    out = []
    for side, xy in (("left", res.left_photo), ("right", res.right_photo)):
        p = ties_dir / f"{side}-photo.csv"
        _write_csv(p, ["name", "x", "y"], ([n, f"{x:.6f}", f"{y:.6f}"] for n, (x, y) in
                                          zip(res.names, xy, strict=True)))
        out.append(p)
    click.echo(f"{res.n} automatic ties (residual y-parallax RMS {res.rms_px:.3f} px)")
    return out[0], out[1]
