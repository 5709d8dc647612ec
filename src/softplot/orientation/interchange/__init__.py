"""Bundle projects in and out of other programs' formats.

* :mod:`.colmap` - COLMAP text models (``cameras.txt``, ``images.txt``, ``points3D.txt``);
* :mod:`.bal` - Bundle Adjustment in the Large problems;
* :mod:`.photomodeler` - PhotoModeler's text export (the format DBAT reads).

Every reader returns a :class:`~softplot.orientation.bundle.BundleData` in softplot's frames
(film mm, x right, y up, origin at the image centre; rotations object -> photo axes, the
camera looking along -z; see ``docs/bundle.md`` for the conversion table of each format's
distortion parameters); every writer takes one and refuses what the target format cannot
represent exactly.
"""

from __future__ import annotations

from softplot.orientation.interchange.bal import read_bal_project, write_bal_project
from softplot.orientation.interchange.colmap import read_colmap, write_colmap

__all__ = ["read_colmap", "write_colmap", "read_bal_project", "write_bal_project"]
