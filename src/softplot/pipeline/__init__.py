"""Whole jobs: process, batch (dask.distributed), demo; projects and sessions."""
