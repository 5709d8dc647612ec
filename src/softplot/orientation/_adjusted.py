"""Mixin for orientation results that keep their :class:`softplot.adjust.Adjustment`."""

from __future__ import annotations


class AdjustedResult:
    """``sigma0`` and ``redundancy`` read from the result's ``adjustment`` attribute."""

    __slots__ = ()

    @property
    def sigma0(self) -> float:
        """A posteriori standard error of unit weight."""
        return self.adjustment.sigma0

    @property
    def redundancy(self) -> int:
        """Redundancy r (observations + constraints - free unknowns)."""
        return self.adjustment.redundancy
