"""``softplot synth``: synthetic calibration scans with exact truth."""

from __future__ import annotations

import click

from softplot.errors import SoftplotError


def _number(kind: type, name: str):
    """Click callback: parse a number, failing with a one-line SoftplotError."""

    def convert(ctx, param, value):
        if value is None:
            return None
        try:
            return kind(value)
        except ValueError:
            raise SoftplotError(f"--{name}: not a valid {kind.__name__}: {value!r}") from None

    return convert


def _opt(name: str, kind: type, default, help_: str, metavar: str | None = None):
    return click.option(f"--{name}", type=str, default=str(default), show_default=True,
                        metavar=metavar or ("N" if kind is int else "X"),
                        callback=_number(kind, name), help=help_)


@click.command("synth")
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--camera", "camera", required=True, metavar="NAME|CERT.toml",
              help="Built-in camera name or certificate file.")
@_opt("count", int, 1, "Number of scans (seeds S, S+1, ...).")
@_opt("seed", int, 0, "Seed of the first scan; the same seed gives the same files.", "S")
@_opt("dpi", float, 1200, "Scan resolution, dots per inch.", "D")
@click.option("--negative", is_flag=True, help="Film negative: bright marks, inverted scene.")
@_opt("blur", float, 0.8, "Scanner blur, Gaussian sigma in pixels.", "PX")
@_opt("noise", float, 0.01, "Sensor noise sigma, fraction of full scale.", "SIGMA")
@_opt("grain", float, 0.0, "Film grain sigma, fraction of full scale.", "SIGMA")
@_opt("contrast", float, 0.5, "Mark-minus-background amplitude, fraction of full scale.", "C")
@click.option("--scene", default="texture", show_default=True, metavar="none|texture|busy",
              help="Scene content.")
@_opt("deform", float, 20.0, "Film deformation: largest displacement, micrometres.", "UM")
@_opt("shrink", float, 0.0, "Uniform film shrinkage, ppm.", "PPM")
@_opt("rotate", float, 0.0, "Scanner rotation, degrees (counter-clockwise on screen).", "DEG")
@_opt("offset-x", float, 0.0, "Shift of the film in the scan, pixels (x).", "PX")
@_opt("offset-y", float, 0.0, "Shift of the film in the scan, pixels (y).", "PX")
@_opt("anisotropy", float, 0.0, "Scanner x/y scale difference, ppm.", "PPM")
@_opt("dust", int, 0, "Dust particles and fibres.")
@_opt("scratches", int, 0, "Scratches.")
@_opt("cover", int, 0, "Marks wholly covered by opaque blobs.")
@_opt("crop", float, 0.0, "Millimetres cut off the left and top edges (marks get cut).", "MM")
@_opt("bits", int, 8, "Bits per sample: 8 or 16.", "8|16")
@click.option("--rgb", is_flag=True, help="Three channels (with --negative: orange mask).")
@click.option("--format", "file_format", default="tif", show_default=True,
              metavar="tif|jpg|png", help="Image file format.")
@click.option("--compress", is_flag=True, help="Compress TIFF files (zlib).")
@click.option("--occlusion", default="first-order", show_default=True,
              metavar="first-order|exact",
              help="How opaque marks hide the scene (exact: the scene under a mark never "
                   "reaches the image; see softplot.synthetic.ScanSpec).")
@click.option("--overwrite", is_flag=True, help="Replace existing files.")
def command(outdir, camera, count, seed, dpi, negative, blur, noise, grain, contrast, scene,
            deform, shrink, rotate, offset_x, offset_y, anisotropy, dust, scratches, cover, crop,
            bits, rgb, file_format, compress, occlusion, overwrite) -> None:
    """Render synthetic scans of CAMERA's film frame into OUTDIR, each with <stem>.truth.json.

    The truth holds every mark's exact pixel position and state and the complete
    film mm <-> pixel mapping (see softplot.synthetic). Existing files are never replaced
    without --overwrite.
    """
    from tqdm import tqdm

    from softplot.camera import load_camera
    from softplot.synthetic import ScanSpec, default_stem, scan_paths, write_scan

    cam = load_camera(camera)
    if count < 1:
        raise SoftplotError(f"--count must be at least 1, got {count}")
    if seed < 0:
        raise SoftplotError(f"--seed must not be negative, got {seed}")
    spec = ScanSpec(
        dpi=dpi, polarity="negative" if negative else "positive", blur_sigma_px=blur,
        noise_sigma=noise, grain_sigma=grain, contrast=contrast, scene=scene,
        deform_um=deform, shrink_ppm=shrink, rotation_deg=rotate,
        offset_px=(offset_x, offset_y), anisotropy_ppm=anisotropy, dust=dust,
        scratches=scratches, cover=cover, crop_mm=crop, bits=bits, rgb=rgb,
        file_format=file_format.lower().lstrip(".").replace("tiff", "tif").replace("jpeg", "jpg"),
        tiff_compression="zlib" if compress else None, occlusion=occlusion,
    ).validate()
    seeds = list(range(seed, seed + count))
    if not overwrite:
        for sd in seeds:
            for p in scan_paths(outdir, default_stem(cam.name, sd), spec.file_format):
                if p.exists():
                    raise SoftplotError(f"{p}: exists; refusing to overwrite (use --overwrite)")
    for sd in tqdm(seeds, desc="synth", unit="scan", disable=count < 2, leave=False):
        img, truth = write_scan(outdir, cam, spec, sd, overwrite=overwrite)
        click.echo(f"{img}  {truth}")
