"""The scene model's choice: the scene under each cross from the grey opening, or jointly.

``scene="opening"`` takes the grey opening's estimate of the scene under each cross
(:func:`softplot.marks.measure.scene_background`); ``"joint"`` refits every cross with the
scene estimated jointly with it (:mod:`softplot.marks.scene_tv`, :data:`JOINT_PASSES` passes);
``"auto"`` (the default) the joint estimate where the first pass sees sharp scene edges at the
crosses (:func:`busy_scene`), or where its crosses depart from their neighbours far beyond
their own precision and the joint estimate measures them better
(:func:`softplot.marks.measurement.measure_crosses`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SCENE_MODELS", "JOINT_PASSES", "BUSY_EDGE", "BUSY_COUNT", "busy_scene"]

#: the scene models of :func:`softplot.marks.detect.detect` (``scene=``)
SCENE_MODELS = ("auto", "opening", "joint")
#: refits with the joint scene estimate (:func:`softplot.marks.measure._refit_scene`; the
#: third and fourth only for the crosses still moving)
JOINT_PASSES = 4
#: ``scene="auto"`` takes the joint scene estimate when at least BUSY_COUNT crosses have a
#: scene edge steeper than BUSY_EDGE x their contrast per px in their footprint. The sweep's
#: smooth textures reach 0.09 at most, its busy scenes 0.18-0.5 (docs/accuracy.md)
BUSY_EDGE = 0.13
BUSY_COUNT = 2


def busy_scene(edge: np.ndarray) -> bool:
    """Whether the scene has sharp edges at the crosses: at least :data:`BUSY_COUNT` (accepted)
    crosses whose footprint holds a scene edge steeper than :data:`BUSY_EDGE` times their contrast
    per px (:func:`softplot.marks.measure._footprint_gradient`)."""
    e = np.asarray(edge, float)
    return int(np.sum(np.isfinite(e) & (e > BUSY_EDGE))) >= BUSY_COUNT
