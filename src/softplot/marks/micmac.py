"""MicMac ``MeasuresIm-<image>.xml``: the image measurements other historical-film tools share.

Written with :mod:`xml.etree.ElementTree`::

    <SetOfMesureAppuisFlottants>
      <MesureAppuiFlottant1Im>
        <NameIm>scan.tif</NameIm>
        <OneMesureAF1I><NamePt>R0C0</NamePt><PtIm>123.4567 89.0123</PtIm></OneMesureAF1I>
        ...

Only measured marks are written. ``PtIm`` is "x y" in the softplot pixel system (x right,
y down, (0, 0) the centre of the top-left pixel). MicMac's ``Ori-InterneScan/`` folder expects
one such file per scan, named ``MeasuresIm-<image file name>.xml``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from softplot.errors import SoftplotError
from softplot.marks.result import Detection

__all__ = ["micmac_name", "write_measures_im", "read_measures_im"]


def micmac_name(image: str) -> str:
    """File name MicMac expects for an image's measurements."""
    return f"MeasuresIm-{Path(image).name}.xml"


def write_measures_im(det: Detection, out_dir: str | Path, overwrite: bool = True) -> Path:
    """Write the measured marks of ``det`` to ``out_dir/MeasuresIm-<image>.xml``."""
    d = Path(out_dir)
    if d.exists() and not d.is_dir():
        raise SoftplotError(f"{d}: not a directory")
    d.mkdir(parents=True, exist_ok=True)
    path = d / micmac_name(det.image)
    if path.exists() and not overwrite:
        raise SoftplotError(f"{path}: exists; refusing to overwrite")
    root = ET.Element("SetOfMesureAppuisFlottants")
    one = ET.SubElement(root, "MesureAppuiFlottant1Im")
    ET.SubElement(one, "NameIm").text = Path(det.image).name
    for i in np.where(det.measured)[0]:
        m = ET.SubElement(one, "OneMesureAF1I")
        ET.SubElement(m, "NamePt").text = det.name[i]
        ET.SubElement(m, "PtIm").text = f"{det.xy[i, 0]:.4f} {det.xy[i, 1]:.4f}"
    ET.indent(root, space="     ")
    body = ET.tostring(root, encoding="unicode")
    path.write_text('<?xml version="1.0" ?>\n' + body + "\n", encoding="utf-8")
    return path


def read_measures_im(path: str | Path) -> tuple[str, dict[str, tuple[float, float]]]:
    """Read a ``MeasuresIm`` file: ``(image name, {point name: (x, y)})``."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise SoftplotError(f"{path}: not a MicMac MeasuresIm file: {exc}") from None
    one = root.find("MesureAppuiFlottant1Im")
    if root.tag != "SetOfMesureAppuisFlottants" or one is None:
        raise SoftplotError(f"{path}: not a MicMac MeasuresIm file")
    name = (one.findtext("NameIm") or "").strip()
    pts = {}
    for m in one.findall("OneMesureAF1I"):
        x, y = (float(v) for v in (m.findtext("PtIm") or "").split())
        pts[(m.findtext("NamePt") or "").strip()] = (x, y)
    return name, pts
