"""``softplot epipolar``: normalised (epipolar) images of an oriented pair."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.errors import SoftplotError


def open_session(folder):
    """(session, maps, scans): a plotting session with both scans and their corrections."""
    from softplot.io import load_scan
    from softplot.pipeline.session import Session

    folder = Path(folder)
    if not (folder / "session.json").is_file():
        raise SoftplotError(f"{folder}: not a plotting session (no session.json)")
    s = Session.resume(folder)
    maps, scans = [], []
    for side in ("left", "right"):
        m = s.photo_map(side)
        if m is None:
            raise SoftplotError(f"session {folder}: the {side} photo has no scan and film "
                                "correction")
        scans.append(load_scan(s.scan_path(side)))
        maps.append(m)
    return s, maps, scans


@click.command("epipolar")
@click.argument("session", type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Output folder: left.tif, right.tif, left.map.npz, right.map.npz, "
                   "epipolar.json.")
@click.option("--pixel-size", type=click.FloatRange(min=0, min_open=True),
              help="Normalised pixel size, micrometres (default: the scans').")
@click.option("--no-maps", is_flag=True, help="Do not store the pixel maps.")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run.")
def command(session, out, pixel_size, no_maps, overwrite) -> None:
    """Normalised images of the oriented pair of a plotting SESSION folder.

    Both photos are rotated to the base with a common principal distance, so rows are
    epipolar lines (y-parallax zero by construction). Each image is resampled once from
    its scan through the film correction (bicubic, tiled for huge scans); the maps from
    normalised pixels to scan pixels are stored (LEFT/RIGHT.map.npz) with the geometry
    (epipolar.json) so that nothing need be resampled twice. See docs/matching.md.
    """
    from softplot.matching.epipolar import resample_pair, write_epipolar
    from softplot.matching.ties import check_outputs

    if out.exists() and not out.is_dir():
        raise SoftplotError(f"{out}: exists and is not a folder")
    names = ["left.tif", "right.tif", "epipolar.json"] + (
        [] if no_maps else ["left.map.npz", "right.map.npz"])
    check_outputs([out / n for n in names], overwrite)
    s, maps, scans = open_session(session)
    geo, imgs, kept = resample_pair(s.model, maps, [sc.data for sc in scans],
                                    None if pixel_size is None else pixel_size / 1000.0,
                                    keep_maps=not no_maps)
    write_epipolar(out, geo, imgs, None if no_maps else kept,
                   {"session": str(Path(session).resolve())}, overwrite=overwrite)
    click.echo(f"normalised pair {geo.cols[0]} + {geo.cols[1]} x {geo.rows} px, pixel "
               f"{geo.pixel_mm * 1000:.2f} um, c {geo.cn:.3f} mm; wrote {out}")
