"""Offline batch work on a Dask cluster: reprocessing archives of recordings (``reprocess``)."""
