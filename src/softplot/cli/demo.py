"""``softplot demo``: render a synthetic Rollei and a Pentax scan and say what was written.

Interim demo of the foundation; a later issue replaces it with the full pipeline.
"""

from __future__ import annotations

from pathlib import Path

import click


@click.command("demo")
@click.option("--out", "out", default="softplot-demo", show_default=True,
              type=click.Path(file_okay=False), help="Output folder.")
def command(out: str) -> None:
    """Render a synthetic Rollei 6006 scan and a Pentax 645 negative into OUT."""
    from softplot.synthetic import ScanSpec, write_scan

    jobs = [
        ("rollei-6006", ScanSpec(dpi=1200, scene="texture", deform_um=30, shrink_ppm=200,
                                 rotation_deg=0.4, dust=8), "rollei-6006-demo"),
        ("pentax-645", ScanSpec(dpi=1200, polarity="negative", scene="texture", deform_um=30,
                                rotation_deg=-0.3, dust=8), "pentax-645-demo"),
    ]
    click.echo(f"softplot demo: writing synthetic scans into {Path(out)}/")
    for cam, spec, stem in jobs:
        img, truth = write_scan(out, cam, spec, seed=1, stem=stem, overwrite=True)
        import json

        t = json.loads(truth.read_text(encoding="utf-8"))
        vis = sum(m["visible"] for m in t["marks"])
        click.echo(
            f"  {img}  {t['width']} x {t['height']} px, {t['dpi']:.0f} dpi, {t['polarity']}, "
            f"{vis}/{len(t['marks'])} marks visible"
        )
        click.echo(f"  {truth}  exact mark positions and the film mm <-> pixel mapping")
