"""``softplot bundle``: bundle adjustment of a project folder or a BAL problem."""

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
    write_json,
    write_residuals_csv,
)
from softplot.cli._orient import angles_option
from softplot.errors import SoftplotError


@click.command("bundle")
@click.argument("project", required=False, type=click.Path(file_okay=False))
@click.option(
    "--bal",
    "bal",
    type=click.Path(dir_okay=False),
    help="Adjust a Bundle Adjustment in the Large file instead of a project.",
)
@output_options()
@click.option(
    "--free",
    "free",
    help="Free interior parameters for every camera, e.g. c,x0,y0,k1 "
    "(default: as cameras.toml says).",
)
@click.option(
    "--free-network",
    is_flag=True,
    help="Ignore control as datum: inner-constraint (minimum-trace) datum.",
)
@click.option(
    "--scale",
    nargs=3,
    type=(str, str, float),
    default=None,
    help="Free network scale from a distance: POINT_A POINT_B DISTANCE.",
)
@angles_option
@click.option(
    "--alpha",
    type=float,
    default=0.001,
    show_default=True,
    help="Data-snooping significance level.",
)
@click.option("--max-iterations", type=click.IntRange(min=1), default=100, show_default=True,
              help="Most Gauss-Newton iterations before the adjustment stops unconverged.")
@click.option(
    "--residuals",
    "residuals_out",
    type=click.Path(dir_okay=False),
    help="Write every image residual (um, px, redundancy numbers, w) to a CSV file.",
)
@click.option(
    "--covariance",
    type=click.Choice(["auto", "full", "interior"]),
    default="auto",
    show_default=True,
    help="Posterior covariance: full (every block, redundancy numbers, data snooping), "
    "interior (the interior orientation only: large blocks), auto (full up to 3000 "
    "camera-side unknowns).",
)
def command(
    project,
    bal,
    json_out,
    report_out,
    plots_dir,
    free,
    free_network,
    scale,
    angle_unit,
    alpha,
    max_iterations,
    residuals_out,
    covariance,
):
    """Bundle adjustment of PROJECT (folder, see docs/bundle.md) or of a BAL file (--bal)."""
    if (project is None) == (bal is None):
        raise SoftplotError("give either a PROJECT folder or --bal FILE")
    from softplot.adjust.sparse_bundle import LMOptions

    if bal is not None:
        from softplot.adjust.bal import read_bal, solve_bal

        guard_output(json_out, [bal])
        prob = read_bal(bal)
        cb, close = lm_progress("LM")
        try:
            res = solve_bal(prob, LMOptions(max_iterations=max_iterations, progress=cb))
        finally:
            close()
        click.echo(
            f"BAL {Path(bal).name}: {prob.n_cameras} cameras, {prob.n_points} points, "
            f"{prob.n_observations} observations"
        )
        click.echo(f"initial_cost {res.initial_cost:.6e}")
        click.echo(f"final_cost   {res.final_cost:.6e}")
        click.echo(f"iterations   {res.iterations}")
        click.echo(f"seconds      {res.seconds:.3f}")
        click.echo(f"rms_px       {res.rms_px:.4f}   ({res.message})")
        if json_out:
            write_json(res.to_json(), json_out)
        return
    from softplot.orientation.bundle import BundleOptions, bundle_adjust
    from softplot.orientation.bundle_init import initialize
    from softplot.orientation.bundle_io import read_project
    from softplot.orientation.bundle_report import text_report

    inputs = project_inputs(project)
    for o in (json_out, report_out, residuals_out):
        guard_output(o, inputs)
    data = read_project(project)
    apply_free(data, parse_free(free))
    if free_network:
        data.control_sigma[:] = float("nan")
    initialize(data)
    cb, close = lm_progress("bundle")
    opt = BundleOptions(
        datum="free" if free_network else "auto",
        scale_distance=scale,
        alpha0=alpha,
        covariance=covariance,
        lm=LMOptions(function_tolerance=1e-10, max_iterations=max_iterations, progress=cb),
    )
    try:
        res = bundle_adjust(data, opt)
    finally:
        close()
    txt = text_report(res, angle_unit=angle_unit, title=f"Bundle adjustment of {project}")
    emit_report(txt, report_out)
    if json_out:
        write_json(with_snooping(res.to_json(), res, alpha), json_out)
    if residuals_out:
        write_residuals_csv(res, residuals_out)
    emit_plots(res, plots_dir)


def snooping_keys(res, alpha0: float) -> dict:
    """The ``blunders`` and ``snooping_test`` JSON keys of a bundle result.

    The bundle tests every image coordinate with Baarda's w-test: ``w = v / (sigma sqrt(qvv))``
    with the image standard errors of the project (``sigma_image_um`` in cameras.toml, or the
    observations' own), i.e. an a priori standard error of unit weight of 1. When the project
    states neither, the standard errors are only a default and the test is Pope's tau test,
    ``tau = w / sigma0`` against the a posteriori sigma0. ``blunders`` names the flagged
    observations ``PHOTO/POINT``, the largest statistic first; the test is ``none`` when no
    redundancy numbers were computed (``--covariance interior``) or the redundancy is too small.
    """
    import numpy as np

    from softplot.adjust import Snooping, snooping_json

    d = res.data
    labels = [
        f"{d.photo_names[f]}/{d.point_names[p]}"
        for f, p in zip(d.obs_photo, d.obs_point, strict=True)
    ]
    w = np.asarray(res.w, dtype=float).ravel()  # (2m,): x, y of every observation
    test = getattr(res, "snooping_test", "baarda-w")
    tau = test == "pope-tau"
    stat = w / res.sigma0 if tau else w
    tested = test != "none" and bool(np.isfinite(stat).any()) and res.redundancy > 0
    sn = Snooping(
        test=test if tested else "none",
        alpha0=float(alpha0),
        critical_value=float(res.critical) if tested else float("nan"),
        statistic=stat if tested else np.full(w.size, np.nan),
        flagged=(np.abs(np.nan_to_num(stat, nan=0.0)) > res.critical) if tested
        else np.zeros(w.size, bool),
        sigma0=float(res.sigma0) if tau else 1.0,
        redundancy=int(res.redundancy),
    )
    return snooping_json(sn, [lab for lab in labels for _ in range(2)])


def with_snooping(js: dict, res, alpha0: float) -> dict:
    """``js`` (a bundle result's JSON) with :func:`snooping_keys` added."""
    return {**js, **snooping_keys(res, alpha0)}
