"""Geometry: plane transforms, mesh models, rotations and the collinearity equations.

Imports nothing else of softplot except :mod:`softplot.errors`.
"""

from softplot.geometry.collinearity import image_rays, project, project_jacobian  # noqa: F401
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix  # noqa: F401
