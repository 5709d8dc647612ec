"""Synthetic photogrammetric scenes with exact truth for the orientation tests."""

from __future__ import annotations

import numpy as np

from softplot.geometry.collinearity import project
from softplot.geometry.rotation import rotation_matrix

C = 152.0  # principal distance, mm


def aerial_points(rng, n, extent=500.0, relief=60.0, offset=(0.0, 0.0, 0.0)):
    """n object points over a square of half-size ``extent`` with some relief, metres."""
    return np.c_[
        rng.uniform(-extent, extent, n), rng.uniform(-extent, extent, n), rng.uniform(0, relief, n)
    ] + np.asarray(offset)


def photo(XYZ, X0, angles, c=C, x0=0.0, y0=0.0):
    """Exact photo coordinates (mm)."""
    return project(XYZ, X0, rotation_matrix(*angles), c, x0, y0)


def stereo_pair(rng, n=30, base=600.0, height=1500.0, c=C):
    """Object points in the overlap and two vertical-ish photos (truth dict)."""
    X = np.c_[
        rng.uniform(-0.1 * base, 1.1 * base, n),
        rng.uniform(-450, 450, n),
        rng.uniform(-40, 80, n),
    ]
    C1 = np.array([0.0, 0.0, height])
    C2 = np.array([base, 15.0, height + 12.0])
    a1 = np.array([0.012, -0.021, 0.031])
    a2 = np.array([-0.018, 0.014, -0.042])
    xy1 = photo(X, C1, a1, c)
    xy2 = photo(X, C2, a2, c)
    return {"X": X, "C1": C1, "C2": C2, "a1": a1, "a2": a2, "xy1": xy1, "xy2": xy2, "c": c}
