"""softplot: a digital softcopy plotter for scanned photogrammetric photographs."""

__version__ = "0.1.0"
