"""Least-squares engine: Gauss-Markov and Gauss-Helmert adjustments with their statistics.

Imports nothing of softplot but :mod:`softplot.errors`. See ``docs/orientation.md`` for the
definitions (redundancy, sigma0, standardised residuals, data snooping).
"""

from softplot.adjust.core import (  # noqa: F401
    SNOOPING_TESTS,
    Adjustment,
    Snooping,
    critical_value,
    data_snooping,
    least_squares,
    linear_least_squares,
    snooping_json,
    tau_critical_value,
    weights_from_sigma,
)
from softplot.adjust.diagnose import (  # noqa: F401
    UndeterminedError,
    check_determined,
    undetermined_directions,
)
from softplot.adjust.helmert import gauss_helmert  # noqa: F401
