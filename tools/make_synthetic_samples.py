#!/usr/bin/env python3
"""Write the small deterministic sample set of synthetic scans into data/synthetic/.

Each scan comes with ``<stem>.truth.json`` (exact mark positions, states and the complete
film mm <-> pixel mapping; see ``softplot.synthetic``). The set is fully determined by this
file: running it again rewrites byte-identical files.

Usage::

    .venv/bin/python tools/make_synthetic_samples.py [--out data/synthetic]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from softplot.synthetic import ScanSpec, write_scan

#: (stem, camera, spec, seed, what it is)
SAMPLES = [
    ("rollei-6006-positive-700dpi", "rollei-6006",
     ScanSpec(dpi=700, scene="texture", deform_um=30, shrink_ppm=200, rotation_deg=0.4,
              anisotropy_ppm=300, dust=6, tiff_compression="zlib"), 1,
     "Rollei 6006 diapositive, 121 dark crosses, 30 um deformation, slight rotation, dust"),
    ("rollei-6006-negative-600dpi-16bit-cut", "rollei-6006",
     ScanSpec(dpi=600, polarity="negative", scene="busy", deform_um=40, rotation_deg=-0.8,
              crop_mm=(3.9, 3.0, 0.0, 0.0), cover=2, bits=16, scratches=2,
              tiff_compression="zlib"), 2,
     "Rollei negative, 16 bit, busy scene, crosses cut by the left/top edges, 2 covered"),
    ("pentax-645-negative-600dpi", "pentax-645",
     ScanSpec(dpi=600, polarity="negative", scene="texture", deform_um=30, rotation_deg=-0.5,
              dust=4, tiff_compression="zlib"), 3,
     "Pentax 645 negative, 9 bright crosses (23 x 17 mm pitch)"),
    ("pentax-645-colour-negative-600dpi", "pentax-645",
     ScanSpec(dpi=600, polarity="negative", rgb=True, scene="texture", deform_um=25,
              rotation_deg=0.7, file_format="jpg", jpeg_quality=90), 4,
     "Pentax 645 colour negative with orange mask, RGB JPEG"),
    ("hasselblad-mk70-positive-600dpi", "hasselblad-mk70",
     ScanSpec(dpi=600, scene="busy", deform_um=35, shrink_ppm=150, rotation_deg=1.2,
              cover=1, tiff_compression="zlib"), 5,
     "Hasselblad MK70, 5 x 5 reseau, busy scene, one cross covered"),
    ("zeiss-rmk-a-15-23-aerial-200dpi", "zeiss-rmk-a-15-23",
     ScanSpec(dpi=200, scene="texture", deform_um=25, rotation_deg=0.3, blur_sigma_px=0.7,
              tiff_compression="zlib"), 6,
     "Zeiss RMK A 15/23 aerial frame at low resolution, 8 fiducials (circle-dots, crosses)"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = Path(__file__).resolve().parents[1] / "data" / "synthetic"
    ap.add_argument("--out", default=str(default))
    args = ap.parse_args()
    out = Path(args.out)
    total = 0
    lines = []
    for stem, cam, spec, seed, what in SAMPLES:
        img, truth = write_scan(out, cam, spec, seed=seed, stem=stem, overwrite=True)
        size = img.stat().st_size + truth.stat().st_size
        total += size
        print(f"{img}  {size / 1e6:.2f} MB  {what}")
        lines.append(f"| `{img.name}` | {cam} | {spec.dpi:.0f} | {spec.polarity} | {what} |")
    readme = out / "README.md"
    readme.write_text(
        "# Synthetic sample scans\n\n"
        "Written by `tools/make_synthetic_samples.py` (deterministic: run it again for "
        "byte-identical files). Each image has a `<stem>.truth.json` with every mark's exact "
        "pixel position (`x`, `y`, pixel centre convention), its state "
        "(visible/covered/cut/outside) and the complete film mm <-> pixel mapping "
        "(`softplot.synthetic.TruthMapping.from_truth`).\n\n"
        "| image | camera | dpi | polarity | content |\n|---|---|---|---|---|\n"
        + "\n".join(lines) + "\n",
        encoding="utf-8",
    )
    print(f"total {total / 1e6:.2f} MB in {out}")


if __name__ == "__main__":
    main()
