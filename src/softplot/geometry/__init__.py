"""Geometry: plane transforms, mesh models, rotations and the collinearity equations.

Imports nothing else of softplot except :mod:`softplot.errors`.
"""

from softplot.geometry.collinearity import image_rays, project, project_jacobian  # noqa: F401
from softplot.geometry.mesh import (  # noqa: F401
    FLAG_NAMES,
    FLAG_OK,
    FLAG_OUTSIDE_IMAGE,
    FLAG_OUTSIDE_RESEAU,
    MESH_KINDS,
    MeshModel,
    default_mesh_kind,
)
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix  # noqa: F401
from softplot.geometry.transforms import (  # noqa: F401
    KINDS,
    MIN_POINTS,
    PlaneTransform,
    fit_transform,
    transform_points,
)
