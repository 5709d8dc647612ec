"""Export of restituted features and reports.

:mod:`softplot.export.features` holds the small :class:`~softplot.export.features.Feature`
data model (object coordinates); :mod:`~softplot.export.dxf` (ezdxf),
:mod:`~softplot.export.geojson` and :mod:`~softplot.export.csvfile` write it;
:mod:`~softplot.export.html` builds self-contained HTML reports.
"""
