"""``softplot dsm``: dense surface model and automatic contours of a plotting session."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.errors import SoftplotError


@click.command("dsm")
@click.argument("session", type=click.Path(path_type=Path))
@click.option("--gsd", required=True, type=float, help="Grid spacing, object metres.")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="DSM GeoTIFF (.tif); its sidecar DSM.json is written next to it.")
@click.option("--contours", "interval", type=float,
              help="Contour interval, metres: contours to DXF (--dxf) and GeoJSON.")
@click.option("--dxf", "dxf", type=click.Path(path_type=Path),
              help="Contours DXF (default: next to the DSM, <stem>-contours.dxf).")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run.")
def command(session, gsd, out, interval, dxf, overwrite) -> None:
    """Dense surface of the oriented pair of a plotting SESSION, with automatic contours.

    Semi-global matching of the normalised pair (sub-pixel, left-right consistency, a
    confidence per pixel), refined by least-squares matching along the rows, intersected
    through the oriented model and gridded at --gsd metres: a float32 GeoTIFF with two
    bands (height, precision - standard deviation - in metres), no-data -9999 (GDAL_NODATA)
    where nothing was matched (occlusions, blank areas: never interpolated), and a sidecar
    OUT.json (x0, y0 - object X, Y of the centre of the top-left cell; rows run towards -Y -,
    gsd, nodata). --contours INTERVAL adds contour lines on the plotter's CONTOUR layer to DXF
    and GeoJSON. See docs/matching.md.
    """
    from softplot.cli.epipolar import open_session
    from softplot.matching.dsm import contours, dense_surface, write_geotiff
    from softplot.matching.ties import check_outputs

    if not (gsd > 0):
        raise SoftplotError(f"--gsd must be a positive number of metres, got {gsd}")
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise SoftplotError(f"{out}: the DSM is a GeoTIFF: use a .tif or .tiff name")
    if interval is not None and not (interval > 0):
        raise SoftplotError(f"--contours must be a positive interval in metres, got {interval}")
    if dxf is not None and interval is None:
        raise SoftplotError("--dxf needs --contours INTERVAL")
    outs = [out, out.with_suffix(".json")]
    if interval is not None:
        dxf = dxf or out.with_name(out.stem + "-contours.dxf")
        gj = dxf.with_suffix(".geojson")
        outs += [dxf, gj]
    check_outputs(outs, overwrite)
    s, maps, scans = open_session(session)
    dsm = dense_surface(s.model, maps, [sc.data for sc in scans], gsd)
    write_geotiff(out, dsm, overwrite=overwrite)
    v = dsm.info["cells_valid"]
    msg = f"DSM {dsm.Z.shape[1]} x {dsm.Z.shape[0]} cells of {gsd:g} m, {v} valid; wrote {out}"
    if interval is not None:
        from softplot.export.dxf import write_dxf
        from softplot.export.geojson import write_geojson

        feats = contours(dsm, interval)
        write_dxf(feats, dxf)
        write_geojson(feats, gj)
        msg += f"; {len(feats)} contour lines to {dxf} and {gj}"
    click.echo(msg)
