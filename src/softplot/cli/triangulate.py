"""``softplot triangulate``: aerial triangulation (bundle block or independent models)."""

from __future__ import annotations

from pathlib import Path

import click

from softplot.cli._bundle_common import (
    apply_free,
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
from softplot.errors import SoftplotError


@click.command("triangulate")
@click.argument("project", type=click.Path(file_okay=False))
@click.option(
    "--method",
    type=click.Choice(["bundle", "independent-models"]),
    default="bundle",
    show_default=True,
    help="bundle: one simultaneous bundle adjustment; independent-models: models formed "
    "first, then joined by a 3D similarity each (the classical aerial triangulation).",
)
@click.option(
    "--pc-tie",
    type=click.Choice(["xyz", "z"]),
    default="xyz",
    show_default=True,
    help="independent-models: tie the projection centres in X, Y, Z or in Z only.",
)
@click.option(
    "--free",
    "free",
    default=None,
    help="bundle: free interior parameters, e.g. c,x0,y0 (default: cameras.toml).",
)
@output_options(plots_help="bundle: write residual plots (PNG) into this folder.")
@click.option(
    "--make-synthetic",
    is_flag=True,
    help="Write a synthetic aerial block project into PROJECT (plus truth.json).",
)
@click.option("--strips", type=int, default=5, show_default=True, help="--make-synthetic: strips.")
@click.option(
    "--photos-per-strip",
    type=int,
    default=21,
    show_default=True,
    help="--make-synthetic: photos per strip (models = strips x (photos - 1)).",
)
@click.option("--noise-um", type=float, default=3.0, show_default=True,
              help="--make-synthetic: image noise, micrometres (1 sigma).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="--make-synthetic: seed of the random noise (same seed, same project).")
def command(
    project,
    method,
    pc_tie,
    free,
    json_out,
    report_out,
    plots_dir,
    make_synthetic,
    strips,
    photos_per_strip,
    noise_um,
    seed,
):
    """Aerial triangulation of PROJECT; the report gives the RMS at check points."""
    if make_synthetic:
        _make(project, strips, photos_per_strip, noise_um, seed)
        return
    from softplot.orientation.bundle_io import read_project

    inputs = project_inputs(project)
    for o in (json_out, report_out):
        guard_output(o, inputs)
    data = read_project(project)
    if method == "independent-models":
        from softplot.orientation.block import independent_models

        res = independent_models(data, pc_tie=pc_tie)
        chk = res.check
        lines = [
            f"Independent-model triangulation of {project}",
            f"models {len(res.models)}, projection centres tied in {pc_tie.upper()}",
            f"sigma0 (model coordinates) {res.sigma0:.4f} m, redundancy {res.redundancy}, "
            f"{res.iterations} iterations, {res.seconds:.2f} s",
        ]
        if chk:
            lines.append(
                f"check points ({chk['n']}): RMS X {chk['X']:.4f} m  Y {chk['Y']:.4f} m"
                f"  Z {chk['Z']:.4f} m"
            )
        txt = "\n".join(lines)
        js = res.to_json()
    else:
        from softplot.adjust.sparse_bundle import LMOptions
        from softplot.orientation.bundle import BundleOptions, bundle_adjust
        from softplot.orientation.bundle_init import initialize
        from softplot.orientation.bundle_report import text_report

        apply_free(data, parse_free(free))
        initialize(data)
        cb, close = lm_progress("bundle block")
        try:
            res = bundle_adjust(
                data, BundleOptions(lm=LMOptions(function_tolerance=1e-10, progress=cb))
            )
        finally:
            close()
        txt = text_report(res, title=f"Bundle block triangulation of {project}", max_points=10)
        js = res.to_json()
        emit_plots(res, plots_dir)
    emit_report(txt, report_out, newline=True)
    if json_out:
        write_json(js, json_out)


def _make(project, strips, photos, noise_um, seed):
    from softplot.orientation.bundle_io import write_project
    from softplot.synthetic.block import make_block

    root = Path(project)
    refuse_existing_truth(root)
    if strips < 1 or photos < 2:
        raise SoftplotError("a block needs >= 1 strip of >= 2 photos")
    net = make_block(n_strips=strips, photos_per_strip=photos, noise_um=noise_um, seed=seed)
    data = net.to_bundle_data(free=())
    data.cameras[0].sigma_image_mm = net.sigma_xy
    write_project(root, data)
    write_json(
        {
            "intrinsics": net.intr_true[0],
            "X0": net.X0_true,
            "XYZ": net.XYZ_true,
            "point_names": net.point_names,
            "info": {k: v for k, v in net.info.items() if k != "models"},
        },
        root / "truth.json",
    )
    click.echo(
        f"synthetic block in {root}: {len(data.photo_names)} photos, "
        f"{net.info['n_models']} models, {len(data.point_names)} points"
    )
