"""Synthetic scans of film frames with exact truth, for tests and benchmarks.

``render_scan(camera, spec, seed) -> (image, truth)`` renders a scan as if a film frame of
``camera`` had been exposed (scene + reseau crosses / fiducials), deformed (shrinkage + a
smooth displacement field) and scanned (scanner affine, crop), with blur, grain, noise, dust,
scratches, covered marks, either polarity, 8/16 bits, grey or RGB (an orange-masked colour
negative). ``write_scan`` writes the image and ``<stem>.truth.json``.

Truth JSON keys: ``image``, ``camera``, ``width``, ``height``, ``dpi``, ``polarity``,
``bit_depth``, ``channels``, ``seed``, ``format_mm``, ``marks`` (each: ``kind``
"reseau"|"fiducial", ``name``, ``row``, ``col`` (null for fiducials), ``film_x``, ``film_y``
(certificate film mm), ``x``, ``y`` (exact pixel position, pixel system), ``visible``,
``state`` "visible"|"covered"|"cut"|"outside"|"dark" (under a flat dark region that leaves it
no contrast), ``inside_fraction`` (share of the mark's area
inside the image), ``shape``, ``contrast`` and ``contrast_min`` (local mark-minus-background
amplitude, grey, fraction of full scale), ``damaged`` (dust or a scratch touches it),
``centroid_shift_px`` (intensity centroid of the noise-free imaged mark minus ``x``, ``y``:
the deformation's curvature across the mark), ``arms`` (bars imaged: 2, 1 for a one-armed
cross, 0 when covered, dark or outside), ``arm_axis`` ("x" or "y": the film axis of the bar of
a one-armed cross, else null), ``arm_length_mm`` and ``line_width_mm`` (the mark as drawn,
which may differ from the certificate's), ``dark`` (under a dark region)),
``mapping`` (parameters of :class:`TruthMapping`: undeformed film mm <-> pixel), ``render``
(``blur_sigma_px``, ``noise_sigma``, ``contrast``, ``background``, ``mark_level``,
``line_width_px``, ``arm_half_length_px``, ...) and ``spec`` (the :class:`ScanSpec`).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from softplot.camera import load_camera
from softplot.errors import SoftplotError
from softplot.synthetic.files import write_image
from softplot.synthetic.mapping import Deformation, Scanner, TruthMapping
from softplot.synthetic.scan import ScanSpec, render_scan

__all__ = [
    "Deformation",
    "ScanSpec",
    "Scanner",
    "default_stem",
    "TruthMapping",
    "render_scan",
    "scan_paths",
    "write_scan",
]


def default_stem(camera_name: str, seed: int) -> str:
    """File stem of a synthetic scan: ``<camera name>-<seed:04d>`` (file-name safe)."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", camera_name).strip("._") or "camera"
    return f"{safe}-{int(seed):04d}"


def scan_paths(outdir: str | Path, stem: str, file_format: str) -> tuple[Path, Path]:
    """(image path, truth path) of a synthetic scan ``stem`` in ``outdir``."""
    d = Path(outdir)
    return d / f"{stem}.{file_format}", d / f"{stem}.truth.json"


def write_scan(
    outdir: str | Path,
    camera,
    spec: ScanSpec | None = None,
    seed: int = 0,
    stem: str | None = None,
    overwrite: bool = False,
) -> tuple[Path, Path]:
    """Render a scan and write the image and its ``<stem>.truth.json`` into ``outdir``.

    Parameters
    ----------
    outdir : str or Path
        Output folder (created if missing).
    camera : Camera or str
        Camera, built-in name or certificate path.
    spec : ScanSpec, optional
        What to render; ``spec.file_format`` chooses tif, jpg or png.
    seed : int
        Random seed (same seed, same files).
    stem : str, optional
        File name stem; default ``<camera name>-<seed:04d>``.
    overwrite : bool
        Replace existing files; otherwise an existing image or truth file is an error
        (checked before anything is written).

    Returns
    -------
    (Path, Path)
        The image and truth paths.
    """
    cam = load_camera(camera)
    spec = (spec or ScanSpec()).validate()
    stem = stem or default_stem(cam.name, seed)
    img_path, truth_path = scan_paths(outdir, stem, spec.file_format)
    if not overwrite:
        for p in (img_path, truth_path):
            if p.exists():
                raise SoftplotError(f"{p}: exists; refusing to overwrite (use --overwrite)")
    d = Path(outdir)
    if d.exists() and not d.is_dir():
        raise SoftplotError(f"{d}: not a directory")
    d.mkdir(parents=True, exist_ok=True)
    image, truth = render_scan(cam, spec, seed)
    truth["image"] = img_path.name
    write_image(img_path, image, spec.dpi, spec.file_format, overwrite=True,
                jpeg_quality=spec.jpeg_quality, compression=spec.tiff_compression,
                description=f"softplot synthetic scan of {cam.name}, seed {seed}")
    tmp = truth_path.with_name(f".{truth_path.name}.part")
    tmp.write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")
    tmp.replace(truth_path)
    return img_path, truth_path
