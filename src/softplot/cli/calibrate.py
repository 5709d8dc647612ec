"""``softplot calibrate``: test-field calibration of a camera (single or in series)."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.cli._bundle_common import (
    emit_plots,
    emit_report,
    guard_output,
    lm_progress,
    output_options,
    parse_free,
    project_inputs,
    refuse_existing_truth,
    write_json,
)
from softplot.cli._orient import angles_option
from softplot.errors import SoftplotError


@click.command("calibrate")
@click.argument("project", type=click.Path(file_okay=False))
@click.option(
    "--free",
    "free",
    default="c,x0,y0,k1,k2,p1,p2",
    show_default=True,
    help="Interior parameters to estimate; the others stay at their certificate values.",
)
@click.option(
    "--series",
    is_flag=True,
    help="Calibrate every series (photos.csv column 'series') separately and report "
    "the repeatability of x0, y0, c.",
)
@output_options()
@angles_option
@click.option(
    "--make-synthetic",
    is_flag=True,
    help="Write a synthetic 49-point test-field project into PROJECT (plus "
    "truth.json) instead of calibrating.",
)
@click.option(
    "--photos",
    type=int,
    default=24,
    show_default=True,
    help="--make-synthetic: photos (per series).",
)
@click.option(
    "--n-series",
    type=int,
    default=0,
    show_default=True,
    help="--make-synthetic: number of series (0: none).",
)
@click.option(
    "--noise-um", type=float, default=2.0, show_default=True,
    help="--make-synthetic: image noise, micrometres (1 sigma).",
)
@click.option("--seed", type=int, default=0, show_default=True,
              help="--make-synthetic: seed of the random noise (same seed, same project).")
def command(
    project,
    free,
    series,
    json_out,
    report_out,
    plots_dir,
    angle_unit,
    make_synthetic,
    photos,
    n_series,
    noise_um,
    seed,
):
    """Calibrate the camera of PROJECT (a test field: control = target coordinates)."""
    if make_synthetic:
        _make(project, photos, n_series, noise_um, seed)
        return
    from softplot.cli.bundle import snooping_keys, with_snooping
    from softplot.orientation.bundle import BundleOptions
    from softplot.orientation.bundle_io import read_project
    from softplot.orientation.bundle_report import text_report
    from softplot.orientation.calibration import calibrate, calibrate_series

    alpha0 = BundleOptions().alpha0

    inputs = project_inputs(project)
    for o in (json_out, report_out):
        guard_output(o, inputs)
    data = read_project(project)
    names = parse_free(free)
    if series:
        sr = calibrate_series(data, free=names)
        txt = sr.text()
        click.echo(txt)
        if report_out:
            Path(report_out).write_text(txt + "\n", encoding="utf-8")
        if json_out:
            js = sr.to_json()
            for entry, r in zip(js["series"], sr.results, strict=True):
                entry.update(snooping_keys(r, alpha0))
            write_json(js, json_out)
        return
    from softplot.adjust.sparse_bundle import LMOptions

    cb, close = lm_progress("calibration")
    try:
        res = calibrate(
            data,
            names,
            BundleOptions(
                datum="control", alpha0=alpha0,
                lm=LMOptions(function_tolerance=1e-10, progress=cb),
            ),
        )
    finally:
        close()
    txt = text_report(res, angle_unit=angle_unit, title=f"Test-field calibration: {project}")
    emit_report(txt, report_out)
    if json_out:
        write_json(with_snooping(res.to_json(), res, alpha0), json_out)
    emit_plots(res, plots_dir)


def _make(project, photos, n_series, noise_um, seed):
    from softplot.orientation.bundle_io import write_project
    from softplot.synthetic.testfield import make_series, make_testfield

    root = Path(project)
    refuse_existing_truth(root)
    if n_series:
        if n_series < 2:
            raise SoftplotError("--n-series needs at least 2")
        net = make_series(n_series=n_series, photos_per_series=photos, noise_um=noise_um, seed=seed)
        labels = net.info["series"]
    else:
        net = make_testfield(n_photos=photos, noise_um=noise_um, seed=seed)
        labels = None
    data = net.to_bundle_data(free=("c", "x0", "y0", "k1", "k2", "p1", "p2"))
    data.cameras[0].sigma_image_mm = net.sigma_xy
    write_project(root, data, series=labels)
    truth = {
        "camera": net.camera_names[0],
        "intrinsics_names": ["c", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2"],
        "intrinsics": net.intr_true[0],
        "series_truth": net.info.get("series_truth"),
        "noise_um": noise_um,
        "seed": seed,
    }
    write_json(truth, root / "truth.json")
    click.echo(
        f"synthetic test-field project in {root}: {len(data.photo_names)} photos, "
        f"{data.obs_photo.size} observations"
    )
